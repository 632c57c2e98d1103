"""Compositing: mask operations against kornia, and the CLI end to end on files."""

import numpy as np
import pytest
import torch
from kornia.filters import gaussian_blur2d
from kornia.morphology import erosion

from neuralbokeh.core.io import read_image, write_image
from neuralbokeh.runtime.composite import composite_frame, main
from neuralbokeh.runtime.masks import erode, gaussian_blur
from neuralbokeh.runtime.onnx_model import OnnxBokeh


@pytest.mark.parametrize("radius", [1, 2])
def test_erode_matches_kornia(radius):
    m = np.random.default_rng(radius).uniform(size=(17, 23)).astype(np.float32)
    want = erosion(torch.from_numpy(m)[None, None], torch.ones(2 * radius + 1, 2 * radius + 1))[0, 0].numpy()
    np.testing.assert_allclose(erode(m, radius), want, atol=1e-7)
    with pytest.raises(ValueError, match="integer >= 0"):
        erode(m, -1)


@pytest.mark.parametrize("sigma", [0.8, 2.0])
def test_gaussian_blur_matches_kornia(sigma):
    m = np.random.default_rng(3).uniform(size=(19, 21)).astype(np.float32)
    k = 2 * int(np.ceil(3 * sigma)) + 1
    want = gaussian_blur2d(torch.from_numpy(m)[None, None].double(), (k, k), (sigma, sigma), border_type="reflect")[0, 0]
    np.testing.assert_allclose(gaussian_blur(m, sigma), want.numpy(), atol=1e-6)


def _inputs(m: OnnxBokeh, seed=0):
    g = np.random.default_rng(seed)
    plate = (0.18 * np.exp2(g.uniform(-2, 2, (m.height, m.width, 3)))).astype(np.float32)
    render = (0.18 * np.exp2(g.uniform(-2, 4, (m.height, m.width, 3)))).astype(np.float32)
    depth = np.full((m.height, m.width), 2.3, np.float32)
    alpha = np.zeros((m.height, m.width), np.float32)
    alpha[8:26, 10:30] = 1.0
    return plate, render, depth, alpha


def test_cli_composites_in_linear_light(busy_onnx, tmp_path):
    m = OnnxBokeh(busy_onnx, threads=1)
    plate, render, _, alpha = _inputs(m)
    depth = np.where(alpha > 0, 1.2, np.inf).astype(np.float32)  # ~2 px in front of the focus, nothing behind
    premultiplied = render * alpha[:, :, None]
    for name, img in (("plate", plate), ("render", premultiplied), ("straight", render), ("depth", depth), ("alpha", alpha)):
        write_image(tmp_path / f"{name}.exr", img)
    args = ["--model", str(busy_onnx), "--plate", str(tmp_path / "plate.exr"), "--depth", str(tmp_path / "depth.exr"),
            "--alpha", str(tmp_path / "alpha.exr"), "--focus", "2.0", "--threads", "1"]
    assert main(args + ["--render", str(tmp_path / "render.exr"), "--out", str(tmp_path / "comp.exr")]) == 0
    assert main(args + ["--render", str(tmp_path / "straight.exr"), "--straight", "--out", str(tmp_path / "comp2.exr")]) == 0
    comp = read_image(tmp_path / "comp.exr")
    np.testing.assert_allclose(read_image(tmp_path / "comp2.exr"), comp, rtol=1e-6)  # straight, multiplied here
    np.testing.assert_allclose(comp, composite_frame(m, plate, premultiplied, depth, alpha, 2.0), rtol=1e-6)
    np.testing.assert_allclose(comp[:2], plate[:2], rtol=1e-6)  # beyond the blur's reach: the plate
    blurred = m.render(premultiplied, depth, 2.0)
    np.testing.assert_allclose(comp[14:20, 16:24], blurred[14:20, 16:24], rtol=1e-5)  # deep inside: the blurred CG
    # just outside the matte (row 7), the blurred CG spills over the plate
    assert float(np.abs(comp[7, 12:28] - plate[7, 12:28]).max()) > 0.01


def test_cli_never_overwrites_without_being_told(busy_onnx, tmp_path):
    m = OnnxBokeh(busy_onnx, threads=1)
    for name, img in zip(("plate", "render", "depth", "alpha"), _inputs(m)):
        write_image(tmp_path / f"{name}.exr", img)
    args = ["--model", str(busy_onnx), "--render", str(tmp_path / "render.exr"), "--depth", str(tmp_path / "depth.exr"),
            "--alpha", str(tmp_path / "alpha.exr"), "--focus", "2.0", "--threads", "1"]
    plate = (tmp_path / "plate.exr").read_bytes()
    for extra in ([], ["--overwrite"]):  # its own plate: refused even with --overwrite
        with pytest.raises(SystemExit, match="is one of the inputs"):
            main([*args, "--plate", str(tmp_path / "plate.exr"), "--out", str(tmp_path / "plate.exr"), *extra])
    assert (tmp_path / "plate.exr").read_bytes() == plate
    (tmp_path / "comp.exr").write_bytes(b"an earlier render")
    with pytest.raises(SystemExit, match="already exists.*--overwrite"):
        main([*args, "--plate", str(tmp_path / "plate.exr"), "--out", str(tmp_path / "comp.exr")])
    assert (tmp_path / "comp.exr").read_bytes() == b"an earlier render"
    assert main([*args, "--plate", str(tmp_path / "plate.exr"), "--out", str(tmp_path / "comp.exr"), "--overwrite"]) == 0
    assert read_image(tmp_path / "comp.exr").shape == (m.height, m.width, 3)


def test_cli_sequence_with_focus_pull_and_png(busy_onnx, tmp_path):
    m = OnnxBokeh(busy_onnx, threads=1)
    plate, render, depth, alpha = _inputs(m, seed=1)
    write_image(tmp_path / "plate.exr", plate)
    write_image(tmp_path / "depth.exr", depth)
    for f in (1, 2, 3):
        write_image(tmp_path / f"render.{f:04d}.exr", render * f)
        write_image(tmp_path / f"alpha.{f:04d}.exr", alpha)
    (tmp_path / "focus.csv").write_text("frame,focus_m\n1,2.0\n3,2.6\n")
    args = ["--model", str(busy_onnx), "--plate", str(tmp_path / "plate.exr"), "--render", str(tmp_path / "render.%04d.exr"),
            "--depth", str(tmp_path / "depth.exr"), "--alpha", str(tmp_path / "alpha.%04d.exr"),
            "--focus-curve", str(tmp_path / "focus.csv"), "--threads", "1"]
    assert main([*args, "--frames", "1-3", "--out", str(tmp_path / "out" / "comp.%04d.exr")]) == 0
    outs = [read_image(tmp_path / "out" / f"comp.{f:04d}.exr") for f in (1, 2, 3)]
    want2 = composite_frame(m, plate, render * 2, depth, alpha, 2.3)  # frame 2: focus interpolated to 2.3 m
    np.testing.assert_allclose(outs[1], want2, rtol=1e-6)
    with pytest.raises(SystemExit, match="outside the focus curve"):
        main([*args, "--frames", "1-4", "--out", str(tmp_path / "x.%04d.exr")])
    with pytest.raises(SystemExit, match="sequence pattern: give --frames"):
        main(["--model", str(busy_onnx), "--plate", str(tmp_path / "plate.exr"), "--render", str(tmp_path / "render.%04d.exr"),
              "--depth", str(tmp_path / "depth.exr"), "--alpha", str(tmp_path / "alpha.0001.exr"), "--focus", "2",
              "--out", str(tmp_path / "x.exr")])
    # PNG output: sRGB-encoded; values above 1 are an error unless clipping is asked for
    png = ["--model", str(busy_onnx), "--plate", str(tmp_path / "plate.exr"), "--render", str(tmp_path / "render.0003.exr"),
           "--depth", str(tmp_path / "depth.exr"), "--alpha", str(tmp_path / "alpha.0001.exr"), "--focus", "2", "--threads", "1"]
    with pytest.raises(SystemExit, match="cannot be stored in a PNG"):
        main([*png, "--out", str(tmp_path / "c.png")])
    assert main([*png, "--out", str(tmp_path / "c.png"), "--clip-ldr"]) == 0
    back = read_image(tmp_path / "c.png")  # 16-bit sRGB -> [0, 1]
    lin_ref = np.clip(composite_frame(m, plate, render * 3, depth, alpha, 2.0), 0, 1)
    srgb = np.where(lin_ref <= 0.0031308, 12.92 * lin_ref, 1.055 * lin_ref ** (1 / 2.4) - 0.055)  # IEC 61966-2-1
    np.testing.assert_allclose(back, srgb, atol=2e-3)
    assert (back == 1.0).any() and back.min() < 0.9


def test_demo_inputs_composite_end_to_end(busy_onnx, tiny_dataset, tmp_path, capsys):
    from data_tools.demo_composite import main as demo

    scene = sorted(tiny_dataset.glob("scene_*"))[0]
    assert demo(["--scene", str(scene), "--slice", "1", "--out", str(tmp_path / "demo")]) == 0
    printed = capsys.readouterr().out
    command = printed.split("composite: ")[1].split()
    args = command[command.index("--plate"):]
    args[args.index("--out") + 1] = str(tmp_path / "demo" / "comp.exr")
    alpha = read_image(tmp_path / "demo" / "alpha.exr")[..., 0]
    depth = read_image(tmp_path / "demo" / "depth.exr")[..., 0]
    assert 0 < alpha.mean() < 1 and np.isinf(depth[alpha == 0]).all() and np.isfinite(depth[alpha > 0]).all()
    assert main(["--model", str(busy_onnx), *args, "--threads", "1", "--clamp-coc"]) == 0
    comp, plate = read_image(tmp_path / "demo" / "comp.exr"), read_image(tmp_path / "demo" / "plate.exr")
    assert np.isfinite(comp).all() and not np.array_equal(comp, plate)


def _write_layers(path, channels: dict[str, np.ndarray]) -> None:
    write_image(path, np.stack(list(channels.values()), axis=-1), channel_names=list(channels))


def test_blender_and_nuke_layered_exrs_composite_as_separate_files(busy_onnx, tmp_path):
    """A Blender multi-layer EXR (``ViewLayer.Combined.R..A``, ``ViewLayer.Depth.Z``, plus a
    normal pass) and a Nuke ``rgba`` + ``depth.Z`` file, each given as render, depth and alpha
    at once, composite exactly as the same images in separate files; the same RGBA file as
    render and alpha gives each its own channels (they were cached by path)."""
    m = OnnxBokeh(busy_onnx, threads=1)
    plate, render, depth, alpha = _inputs(m)
    write_image(tmp_path / "plate.exr", plate)
    separate = {"render": render, "depth": depth, "alpha": alpha}
    for name, img in separate.items():
        write_image(tmp_path / f"{name}.exr", img)
    rgb = {c: render[..., i] for i, c in enumerate("RGB")}
    _write_layers(tmp_path / "blender.exr", {**{f"ViewLayer.Combined.{c}": v for c, v in rgb.items()},
                                            "ViewLayer.Combined.A": alpha, "ViewLayer.Depth.Z": depth,
                                            "ViewLayer.Normal.X": depth * 0 + 0.5})
    _write_layers(tmp_path / "nuke.exr", {**rgb, "A": alpha, "depth.Z": depth})
    common = ["--model", str(busy_onnx), "--plate", str(tmp_path / "plate.exr"), "--focus", "2.0", "--threads", "1"]

    def comp(out: str, render_src: str, depth_src: str, alpha_src: str) -> np.ndarray:
        assert main(common + ["--render", render_src, "--depth", depth_src, "--alpha", alpha_src,
                              "--out", str(tmp_path / out)]) == 0
        return read_image(tmp_path / out)

    want = comp("separate.exr", *(str(tmp_path / f"{n}.exr") for n in separate))
    for name in ("blender.exr", "nuke.exr"):
        np.testing.assert_array_equal(comp(f"from_{name}", *[str(tmp_path / name)] * 3), want)
    named = comp("named.exr", f"{tmp_path / 'blender.exr'}:ViewLayer.Combined", f"{tmp_path / 'blender.exr'}:ViewLayer.Depth.Z",
                 f"{tmp_path / 'blender.exr'}:ViewLayer.Combined.A")
    np.testing.assert_array_equal(named, want)
    assert float(np.abs(want - plate).max()) > 0.01  # something was composited


def test_ambiguous_channels_are_refused_with_the_file_s_channels(busy_onnx, tmp_path):
    from neuralbokeh.runtime.channels import pick_channels, split_source

    m = OnnxBokeh(busy_onnx, threads=1)
    plate, render, depth, alpha = _inputs(m)
    for name, img in (("plate", plate), ("render", render), ("alpha", alpha)):
        write_image(tmp_path / f"{name}.exr", img)
    five = {**{c: render[..., i] for i, c in enumerate("RGB")}, "A": alpha, "Y": depth}
    _write_layers(tmp_path / "five.exr", five)
    args = ["--model", str(busy_onnx), "--plate", str(tmp_path / "plate.exr"), "--render", str(tmp_path / "render.exr"),
            "--alpha", str(tmp_path / "alpha.exr"), "--focus", "2.0", "--out", str(tmp_path / "c.exr")]
    with pytest.raises(SystemExit, match=r"which channels are the depth \(Z\)\?.*its channels: R, G, B, (A, Y|Y, A)$"):
        main(args + ["--depth", str(tmp_path / "five.exr")])  # R is not read as depth
    with pytest.raises(SystemExit, match="no depth .* named 'depth.Z'"):
        main(args + ["--depth", f"{tmp_path / 'five.exr'}:depth.Z"])
    assert main(args + ["--depth", f"{tmp_path / 'five.exr'}:Y"]) == 0
    assert split_source(r"C:\shots\a.exr") == (r"C:\shots\a.exr", None)
    assert split_source("a.exr:depth.Z") == ("a.exr", "depth.Z")
    two = ["A.Combined.R", "A.Combined.G", "A.Combined.B", "B.Combined.R", "B.Combined.G", "B.Combined.B"]
    with pytest.raises(ValueError, match="one of the layers A.Combined, B.Combined"):
        pick_channels(two, "rgb")


def test_a_blurred_foreground_over_a_sharp_plate_matches_the_reference_on_the_combined_layers(tmp_path):
    """A CG square 6 px out of focus in front of an in-focus plate, through an untrained lens
    network (its 7-blade prior: a CoC-driven scatter), against the reference renderer on the two
    layers: the blurred render and its blurred alpha composite as the layered scatter does,
    spill past the matte included; cutting the blur with the sharp matte (the old composite)
    is far worse."""
    from neuralbokeh.checkpoint import save_checkpoint
    from neuralbokeh.core.apertures import ApertureModel, parse_aperture
    from neuralbokeh.core.contract import Contract
    from neuralbokeh.core.normalization import Normalization
    from neuralbokeh.core.optics import ThinLens
    from neuralbokeh.export.exporter import export_checkpoint
    from neuralbokeh.networks import ModelConfig, build_model
    from neuralbokeh.render import scatter_layers

    h, w, focus, coc = 40, 48, 2.0, 6.0
    aperture = ApertureModel(parse_aperture("polygon:7"))
    probe = ThinLens(50.0, 1.0, 36.0)
    lens = ThinLens(50.0, float(abs(probe.coc_px(1.0, focus, w, signed=True))) / coc, 36.0)
    cfg = ModelConfig(tile=16, overlap=8, architecture="lens", pupil_init="aperture").resolved(8.0)
    contract = Contract(h, w, Normalization(0.18), 8.0, 8.0, lens, aperture.to_dict())
    torch.manual_seed(0)
    save_checkpoint(tmp_path / "prior.pt", {"model_config": cfg.to_dict(), "contract": contract.to_dict(),
                                            "model_state": build_model(cfg, contract).state_dict(), "step": 0})
    export_checkpoint(tmp_path / "prior.pt", tmp_path / "prior.onnx", kernels="direct", threads=1)
    m = OnnxBokeh(tmp_path / "prior.onnx", threads=1)
    g = np.random.default_rng(4)
    plate = (0.18 * np.exp2(g.uniform(-2, 2, (h, w, 3)))).astype(np.float32)
    alpha = np.zeros((h, w), np.float32)
    alpha[12:28, 14:34] = 1.0
    colour = np.array([2.0, 1.0, 0.3], np.float32)
    premultiplied = colour * alpha[:, :, None]
    depth = np.where(alpha > 0, 1.0, np.inf).astype(np.float32)
    c_cg = float(lens.coc_px(1.0, focus, w, signed=True))
    ref = scatter_layers(torch.from_numpy(np.stack([plate, premultiplied])).permute(0, 3, 1, 2).double(),
                         torch.from_numpy(np.stack([np.ones_like(alpha), alpha]))[:, None].double(), [0.0, c_cg],
                         aperture, fill_holes=False).permute(1, 2, 0).numpy()
    comp = composite_frame(m, plate, premultiplied, depth, alpha, focus)
    matte = gaussian_blur(erode(alpha, 1), 1.0)[:, :, None]  # the old composite: the blur cut by the sharp matte
    cut = matte * m.render(premultiplied, depth, focus) + (1.0 - matte) * plate
    ring = (gaussian_blur(alpha, 3.0) > 0.02) & (alpha == 0)  # outside the matte, within the blur's reach

    def rms(a, where):
        return float(np.sqrt(np.mean((a - ref)[where] ** 2)))

    assert rms(comp, ring) < 0.2 * rms(cut, ring), (rms(comp, ring), rms(cut, ring))
    assert rms(comp, np.ones_like(ring)) < 0.02 * float(colour.max())


def test_depth_in_other_units_inverse_or_as_a_coc_map_gives_the_same_composite(busy_onnx, tmp_path, caplog):
    m = OnnxBokeh(busy_onnx, threads=1)
    plate, render, _, alpha = _inputs(m)
    depth = np.where(alpha > 0, 1.2, 3.0).astype(np.float32)
    files = {"plate": plate, "render": render * alpha[:, :, None], "alpha": alpha, "depth": depth, "depth_mm": depth * 1000,
             "depth_inv": 1.0 / depth, "coc": m.coc_px(depth, 2.0)}
    for name, img in files.items():
        write_image(tmp_path / f"{name}.exr", img)
    base = ["--model", str(busy_onnx), "--plate", str(tmp_path / "plate.exr"), "--render", str(tmp_path / "render.exr"),
            "--alpha", str(tmp_path / "alpha.exr"), "--threads", "1"]

    def comp(name: str, *extra: str) -> np.ndarray:
        assert main(base + ["--depth", str(tmp_path / f"{name}.exr"), "--out", str(tmp_path / f"out_{name}.exr"), *extra]) == 0
        return read_image(tmp_path / f"out_{name}.exr")

    want = comp("depth", "--focus", "2.0")
    assert "unlikely" not in caplog.text
    np.testing.assert_allclose(comp("depth_mm", "--focus", "2.0", "--depth-unit", "mm"), want, rtol=1e-5)
    np.testing.assert_allclose(comp("depth_inv", "--focus", "2.0", "--depth-math", "inverse"), want, rtol=1e-5)
    np.testing.assert_allclose(comp("coc", "--depth-math", "coc"), want, rtol=1e-5, atol=1e-6)
    with pytest.raises(SystemExit, match="leave out --focus"):
        main(base + ["--depth", str(tmp_path / "coc.exr"), "--depth-math", "coc", "--focus", "2", "--out", str(tmp_path / "x.exr")])
    with pytest.raises(SystemExit, match="give --focus"):
        main(base + ["--depth", str(tmp_path / "depth.exr"), "--out", str(tmp_path / "x.exr")])
    # millimetres read as metres: one warning that names the likely cause
    caplog.clear()
    main(base + ["--depth", str(tmp_path / "depth_mm.exr"), "--focus", "2.0", "--out", str(tmp_path / "x.exr")])
    assert caplog.text.count("is unlikely for a") == 1 and "--depth-unit" in caplog.text


def test_hash_and_houdini_patterns_and_frame_steps(busy_onnx, tmp_path):
    """``####`` and ``$F4`` name the same files as ``%04d``; ``1001-1005x2`` renders 1001, 1003
    and 1005 only, each as the printf-pattern run renders it."""
    from neuralbokeh.runtime.composite import parse_frames

    m = OnnxBokeh(busy_onnx, threads=1)
    plate, render, depth, alpha = _inputs(m, seed=2)
    write_image(tmp_path / "plate.exr", plate)
    write_image(tmp_path / "depth.exr", depth)
    write_image(tmp_path / "alpha.exr", alpha)
    for f in range(1001, 1006):
        write_image(tmp_path / f"render.{f:04d}.exr", render * (f - 1000))
    base = ["--model", str(busy_onnx), "--plate", str(tmp_path / "plate.exr"), "--depth", str(tmp_path / "depth.exr"),
            "--alpha", str(tmp_path / "alpha.exr"), "--focus", "2.0", "--threads", "1", "--frames", "1001-1005x2"]
    assert main(base + ["--render", str(tmp_path / "render.####.exr"), "--out", str(tmp_path / "a" / "c.%04d.exr")]) == 0
    assert main(base + ["--render", str(tmp_path / "render.$F4.exr"), "--out", str(tmp_path / "b" / "c.####.exr")]) == 0
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["c.1001.exr", "c.1003.exr", "c.1005.exr"]
    for f in (1001, 1003, 1005):
        got = read_image(tmp_path / "a" / f"c.{f}.exr")
        np.testing.assert_array_equal(got, read_image(tmp_path / "b" / f"c.{f}.exr"))
        np.testing.assert_allclose(got, composite_frame(m, plate, render * (f - 1000), depth, alpha, 2.0), rtol=1e-6)
    assert parse_frames("7") == [7] and parse_frames("1-5x2") == [1, 3, 5]
    for bad in ("5-1", "1-5x0", "1..5", "x2"):
        with pytest.raises(ValueError, match="--frames must be"):
            parse_frames(bad)


def test_outputs_carry_provenance_and_the_plate_s_timing_half_and_jpeg(busy_onnx, tmp_path):
    """The EXR output's header names the model (file, SHA-256), the focus and the version and
    keeps the plate's frame rate and timecode; ``--half`` writes float16; a JPEG is sRGB-encoded
    (HDR refused without ``--clip-ldr``), never linear values."""
    import hashlib

    import OpenImageIO as oiio

    m = OnnxBokeh(busy_onnx, threads=1)
    plate, render, depth, alpha = _inputs(m, seed=3)
    spec = oiio.ImageSpec(m.width, m.height, 3, oiio.FLOAT)
    spec.attribute("FramesPerSecond", oiio.TypeRational, (24000, 1001))
    spec.attribute("smpte:TimeCode", oiio.TypeTimeCode, (0x01020304, 0))
    out = oiio.ImageOutput.create(str(tmp_path / "plate.exr"))
    assert out.open(str(tmp_path / "plate.exr"), spec) and out.write_image(plate)
    out.close()
    for name, img in (("render", render * alpha[:, :, None]), ("depth", depth), ("alpha", alpha)):
        write_image(tmp_path / f"{name}.exr", img)
    args = ["--model", str(busy_onnx), "--plate", str(tmp_path / "plate.exr"), "--render", str(tmp_path / "render.exr"),
            "--depth", str(tmp_path / "depth.exr"), "--alpha", str(tmp_path / "alpha.exr"), "--focus", "2.0", "--threads", "1"]
    assert main(args + ["--out", str(tmp_path / "c.exr")]) == 0
    assert main(args + ["--out", str(tmp_path / "h.exr"), "--half"]) == 0
    got = oiio.ImageInput.open(str(tmp_path / "c.exr"))
    head = got.spec()
    got.close()
    assert head.getattribute("neuralbokeh:model") == busy_onnx.name
    assert head.getattribute("neuralbokeh:model_sha256") == hashlib.sha256(busy_onnx.read_bytes()).hexdigest()
    assert head.getattribute("neuralbokeh:focus_m") == 2.0 and head.getattribute("neuralbokeh:version")
    assert tuple(head.getattribute("FramesPerSecond")) == (24000, 1001)
    assert tuple(head.getattribute("smpte:TimeCode"))[0] == 0x01020304
    half = oiio.ImageInput.open(str(tmp_path / "h.exr"))
    assert half.spec().format == oiio.HALF
    half.close()
    full = read_image(tmp_path / "c.exr")
    np.testing.assert_allclose(read_image(tmp_path / "h.exr"), full, rtol=1e-3)
    with pytest.raises(SystemExit, match="float16 EXR files only"):
        main(args + ["--out", str(tmp_path / "h.png"), "--half"])
    assert not (tmp_path / "h.png").exists()
    assert full.max() > 1.0  # the render's highlights reach the composite
    with pytest.raises(SystemExit, match="cannot be stored in a JPG"):
        main(args + ["--out", str(tmp_path / "c.jpg")])
    assert main(args + ["--out", str(tmp_path / "c.jpg"), "--clip-ldr"]) == 0
    lin = np.clip(full, 0, 1)
    srgb = np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * lin ** (1 / 2.4) - 0.055)  # IEC 61966-2-1
    jpg = read_image(tmp_path / "c.jpg")  # per-pixel noise does not survive JPEG; its mean level does
    assert abs(float(jpg.mean() - srgb.mean())) < 0.01 < abs(float(jpg.mean() - lin.mean())) - 0.05


def test_bad_pixels_are_named_as_the_user_knows_them(busy_onnx):
    m = OnnxBokeh(busy_onnx, threads=1)
    plate, render, depth, alpha = _inputs(m)
    bad = render.copy()
    bad[3, 5, 1] = np.nan
    with pytest.raises(ValueError, match="the render"):
        composite_frame(m, plate, bad, depth, alpha, 2.0)
    bad_plate = plate.copy()
    bad_plate[2, 2] = -1.0
    with pytest.raises(ValueError, match="the plate"):
        composite_frame(m, bad_plate, render, depth, alpha, 2.0)


def test_data_windows_overscan_and_crops_are_placed_on_the_plate(busy_onnx, tmp_path):
    """EXR data windows: a render with overscan is cut to the plate, a depth with a smaller data
    window is in focus where the render is empty, and a plate whose data window is a crop of its
    display window is that crop of the sensor; the output keeps the plate's windows."""
    from neuralbokeh.core.io import image_windows
    from neuralbokeh.core.optics import SensorWindow

    m = OnnxBokeh(busy_onnx, threads=1)
    h, w = m.height, m.width
    plate, render, _, alpha = _inputs(m, seed=4)
    prem = render * alpha[:, :, None]
    depth = np.where(alpha > 0, 1.2, 2.0).astype(np.float32)
    big = np.random.default_rng(5).uniform(0, 1, (h + 8, w + 8, 3)).astype(np.float32)  # 4 px of overscan all round
    big[4:4 + h, 4:4 + w] = prem

    def layers(folder, x, y, depth_cols=20):  # the CG layers with the frame's first pixel at (x, y)
        folder.mkdir()
        display = (0, 0, w + 12, h + 9)
        write_image(folder / "render.exr", big, windows=((x - 4, y - 4, w + 8, h + 8), display))
        write_image(folder / "alpha.exr", np.pad(alpha, 4), windows=((x - 4, y - 4, w + 8, h + 8), display))
        write_image(folder / "depth.exr", np.full((18, depth_cols), 1.2, np.float32),
                    windows=((x + 10, y + 8, depth_cols, 18), display))
        return ["--model", str(busy_onnx), "--focus", "2.0", "--threads", "1"] + [
            a for n in ("render", "depth", "alpha") for a in (f"--{n}", str(folder / f"{n}.exr"))]

    crop = (5, 3, w, h)
    write_image(tmp_path / "plate.exr", plate, windows=(crop, (0, 0, w + 12, h + 9)))
    args = layers(tmp_path / "crop", 5, 3)
    assert main(args + ["--plate", str(tmp_path / "plate.exr"), "--out", str(tmp_path / "comp.exr")]) == 0
    assert image_windows(tmp_path / "comp.exr") == (crop, (0, 0, w + 12, h + 9))
    window = SensorWindow(5 / (w + 12), 3 / (h + 9), w / (w + 12), h / (h + 9))
    want = composite_frame(m, plate, prem, depth, alpha, 2.0, window=window)
    np.testing.assert_allclose(read_image(tmp_path / "comp.exr"), want, rtol=1e-5, atol=1e-6)
    assert float(np.abs(want - composite_frame(m, plate, prem, depth, alpha, 2.0)).max()) > 1e-4  # the crop mattered
    # the same plate as a plain file, with the window given by hand
    write_image(tmp_path / "plain.exr", plate)
    assert main(layers(tmp_path / "plain", 0, 0) + ["--plate", str(tmp_path / "plain.exr"), "--sensor-window",
                                                     *map(str, window.to_dict().values()), "--out", str(tmp_path / "comp2.exr")]) == 0
    np.testing.assert_allclose(read_image(tmp_path / "comp2.exr"), want, rtol=1e-5, atol=1e-6)
    # a depth that leaves part of the render without a value is refused, naming the first pixel
    short = layers(tmp_path / "short", 5, 3, depth_cols=19)
    with pytest.raises(SystemExit, match=r"no value at 18 pixels where the render is not empty, first at column 29, row 8"):
        main(short + ["--plate", str(tmp_path / "plate.exr"), "--out", str(tmp_path / "comp3.exr")])


def test_a_far_equals_zero_map_read_as_distance_names_the_inverse_option(busy_onnx, tmp_path):
    m = OnnxBokeh(busy_onnx, threads=1)
    plate, render, _, alpha = _inputs(m)
    inverse = np.where(alpha > 0, 1 / 1.2, 0.0).astype(np.float32)  # 0 = at infinity
    for name, img in {"plate": plate, "render": render * alpha[:, :, None], "alpha": alpha, "inv": inverse}.items():
        write_image(tmp_path / f"{name}.exr", img)
    args = ["--model", str(busy_onnx), "--focus", "2.0", "--depth", str(tmp_path / "inv.exr"), "--out", str(tmp_path / "o.exr")]
    args += [a for n in ("plate", "render", "alpha") for a in (f"--{n}", str(tmp_path / f"{n}.exr"))]
    n = int((inverse == 0).sum())
    with pytest.raises(SystemExit, match=rf"inv.exr: depth must be > 0 \(inf allowed\), got {n} pixels <= 0 \(min 0\); "
                                         r"0 at infinity is a 1/distance map: give --depth-math inverse"):
        main(args)
    assert main(args + ["--depth-math", "inverse"]) == 0

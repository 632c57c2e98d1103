"""Developed focal stacks (TIFF, PNG, JPEG): transfer function undone, exposure equalised, focus
distances from EXIF or the command line; a stack rendered from a known scene, and the
repository's real stacks."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from kornia.color import linear_rgb_to_rgb

from data_tools.procedural import SceneParams, composite_sharp, make_layers
from data_tools.raw.__main__ import main as raw_main
from data_tools.raw.developed import decode_developed, exposure_gains, parse_transfer
from data_tools.raw.fuse import focus_measure
from neuralbokeh.core.apertures import ApertureModel
from neuralbokeh.core.io import read_image, write_image
from neuralbokeh.core.optics import ThinLens, focus_sweep_m
from neuralbokeh.data.dataset import load_scene
from neuralbokeh.evaluation.metrics import image_metrics
from neuralbokeh.render import scatter_layers

LENS = ThinLens(50.0, 1.8, 12.0)
GAINS = [1.0, 1.25, 0.8, 1.1]  # each slice's exposure against the first


def _encode(linear: np.ndarray) -> np.ndarray:
    x = torch.from_numpy(np.ascontiguousarray(np.clip(linear, 0.0, 1.0).transpose(2, 0, 1)))
    return linear_rgb_to_rgb(x).numpy().transpose(1, 2, 0)


@pytest.fixture(scope="module")
def scene():
    w, h = 96, 72
    rng = np.random.default_rng(11)
    layers = make_layers(rng, h, w, SceneParams(near_m=0.8, far_m=6.0, infinite_background=0.0, highlights=(0, 0)))
    aif, depth = composite_sharp(layers)
    finite = [la.depth_m for la in layers if math.isfinite(la.depth_m)]
    focus = list(focus_sweep_m(min(finite), max(finite), len(GAINS)))
    colors = torch.from_numpy(np.stack([la.color * la.alpha[..., None] for la in layers])).permute(0, 3, 1, 2)
    alphas = torch.from_numpy(np.stack([la.alpha for la in layers]))[:, None]
    slices = []
    for f in focus:
        cocs = [LENS.coc_px(la.depth_m, f, w, signed=True) for la in layers]
        slices.append(scatter_layers(colors, alphas, cocs, ApertureModel()).permute(1, 2, 0).numpy() * 0.5)
    return slices, focus, aif * 0.5, depth


def _write_stack(folder: Path, slices, focus, ext: str, exif: bool) -> None:
    folder.mkdir(parents=True)
    pixel_type = "uint16" if ext == ".tif" else "uint8"
    scale = 65535.0 if pixel_type == "uint16" else 255.0
    for k, (img, f, g) in enumerate(zip(slices, focus, GAINS)):
        attrs = {"Exif:SubjectDistance": float(f), "Exif:FocalLength": 50.0} if exif else {}
        if ext == ".jpg":
            attrs["Compression"] = "jpeg:95"  # a camera's "fine" JPEG
        code = np.round(_encode(img * g) * scale)
        write_image(folder / f"s{k}{ext}", code, attributes=attrs, pixel_type=pixel_type)


@pytest.mark.parametrize("ext, exif", [(".tif", True), (".jpg", True), (".png", False)])
def test_developed_stack_becomes_a_linear_dataset(scene, tmp_path, ext, exif):
    slices, focus, aif, depth = scene
    _write_stack(tmp_path / "stack", slices, focus, ext, exif)
    args = [str(tmp_path / "stack"), "--out", str(tmp_path / "ds"), "--sensor-width", "12", "--no-align", "--f-number", "1.8"]
    if not exif:
        args += ["--focal-length", "50", "--focus-diopters", ",".join(f"{1 / f:.9g}" for f in focus)]
    assert raw_main(args) == 0
    got = load_scene(tmp_path / "ds" / "stack")
    g = got["meta"]["generator"]
    assert g["source"] == "developed" and g["transfer"] == "srgb"
    # exposure: each slice's gain against the reference (the middle slice) undoes the bracketing
    ref = g["reference_slice"]
    want = [GAINS[ref] / x for x in GAINS]
    np.testing.assert_allclose(g["exposure_gains"], want, rtol=0.02 if ext == ".jpg" else 0.005)
    assert got["meta"]["focus_distances_m"] == pytest.approx(sorted(focus), rel=1e-6)
    # linear and equalised: every slice written is the rendered linear slice, up to the one
    # exposure factor (and 8-bit quantisation; JPEG loses ~28 dB on these random colour textures
    # already in sRGB, through its 4:2:0 chroma); a left-in tone curve costs > 5 dB
    order = np.argsort(focus)
    for k, i in enumerate(order):
        linear = got["defocus"][k] / g["exposure_factor"] / GAINS[ref]
        psnr = image_metrics(linear, slices[i])["psnr_linear"]
        assert psnr > {".tif": 60.0, ".png": 45.0, ".jpg": 22.0}[ext], (k, psnr)
        as_is = read_image(tmp_path / "stack" / f"s{i}{ext}")  # the file's values, tone curve left in
        as_is = as_is * float((as_is * slices[i]).sum() / (as_is * as_is).sum())  # at its best exposure
        assert psnr > image_metrics(as_is, slices[i])["psnr_linear"] + 5.0


def test_transfer_options_and_exposure_errors(tmp_path):
    assert parse_transfer("gamma:2.2") == ("gamma", 2.2)
    for bad in ("gamma:0", "gamma:x", "rec709"):
        with pytest.raises(ValueError, match="transfer must be"):
            parse_transfer(bad)
    ramp = np.linspace(0.0, 1.0, 64)[None, :, None].repeat(8, 0).repeat(3, 2)
    write_image(tmp_path / "r.png", np.round(ramp * 255), pixel_type="uint8")
    lin = decode_developed(tmp_path / "r.png", "linear")[0, :, 0]
    gam = decode_developed(tmp_path / "r.png", "gamma:2.2")[0, :, 0]
    np.testing.assert_allclose(gam, lin**2.2, atol=1e-6)
    white = np.ones((32, 32, 3))
    with pytest.raises(ValueError, match="no unclipped"):
        exposure_gains([white * 0.5, white], 0)


def test_mixed_stack_and_bad_focus_options_are_named(tmp_path, scene):
    slices, focus, _, _ = scene
    _write_stack(tmp_path / "s", slices[:2], focus[:2], ".png", False)
    (tmp_path / "s" / "x.dng").write_bytes(b"")
    assert raw_main([str(tmp_path / "s"), "--out", str(tmp_path / "o"), "--sensor-width", "12", "--focus-diopters", "1,2"]) == 1
    (tmp_path / "s" / "x.dng").unlink()
    with pytest.raises(SystemExit, match="not both"):
        raw_main([str(tmp_path / "s"), "--out", str(tmp_path / "o"), "--focus-distances", "1,2", "--focus-diopters", "1,2"])
    with pytest.raises(SystemExit, match="--transfer"):
        raw_main([str(tmp_path / "s"), "--out", str(tmp_path / "o"), "--transfer", "log"])


STACKS = Path(__file__).resolve().parents[2] / "shared" / "data" / "focal_stacks"


@pytest.mark.skipif(not STACKS.is_dir(), reason="../shared/data/focal_stacks is not in this checkout")
@pytest.mark.parametrize("name, lens_args", [
    ("breakfast_dfd", ["--focal-length", "25", "--f-number", "8.3", "--sensor-width", "16", "--focus-distances", "0.869,0.529"]),
    # the phone's EXIF (2.5 mm f/1.8) does not survive the quick copy below; no focus distances
    ("focus-stack_pcb", ["--focal-length", "2.5", "--f-number", "1.8", "--sensor-width", "4.6", "--focus-diopters", "7,6,5,4,3,2,1"]),
])
def test_real_developed_stacks(tmp_path, name, lens_args):
    src = STACKS / name
    folder = tmp_path / name
    folder.mkdir()
    for p in sorted(src.iterdir()):
        if p.suffix.lower() in (".png", ".jpg") and p.stem != "expected":
            img = read_image(p)
            step = max(1, img.shape[1] // 200)  # a quick copy: every step-th pixel, same format
            write_image(folder / p.name, np.round(img[::step, ::step] * 255), pixel_type="uint8")
    assert raw_main([str(folder), "--out", str(tmp_path / "ds")] + lens_args) == 0
    got = load_scene(tmp_path / "ds" / name)
    assert np.isfinite(got["aif"]).all() and np.isfinite(got["depth"]).all()
    # no ground truth here: the fusion must be about as sharp as the sharpest slice everywhere
    slices = got["defocus"]
    fm = focus_measure(slices)
    fused = focus_measure([got["aif"]])[0]
    assert float(fused.mean()) >= 0.9 * float(fm.max(dim=0).values.mean())
    json.dumps(got["meta"]["generator"])  # the record stays JSON


def test_a_mistake_in_the_options_is_one_error_line_not_one_per_stack(scene, tmp_path, capsys):
    from neuralbokeh.core.cli import run_cli

    slices, focus, _, _ = scene
    for name in ("a", "b"):  # no EXIF: no focal length for either stack
        _write_stack(tmp_path / name, slices, focus, ".png", exif=False)
    args = [str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(tmp_path / "ds"), "--sensor-width", "12",
            "--f-number", "1.8", "--focus-diopters", ",".join(f"{1 / f:.9g}" for f in focus)]
    assert run_cli(raw_main, args) == 2
    out, err = capsys.readouterr()
    errors = [line for line in err.splitlines() if line.startswith("error:")]
    assert errors == ["error: no focal length mm in the metadata: give --focal-length (mm) (all 2 stacks)"]
    assert err.count("focal length") == 1
    assert "data.roots" not in out + err

"""RAW focal stacks: real DNG files written from a known scene, decoded by LibRaw, and the
real camera files of ../shared/data/raw."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from kornia.filters import gaussian_blur2d, laplacian

from data_tools.raw.__main__ import main as raw_main
from data_tools.raw.decode import RawDecodeError, decode, read_metadata, white_balance
from data_tools.raw.synthetic import BLACK, WHITE, make_stack, mosaic, write_dng
from neuralbokeh.core.io import read_image
from neuralbokeh.core.optics import SensorWindow, ThinLens
from neuralbokeh.data.dataset import FocalStackDataset, load_scene

LENS = ThinLens(50.0, 1.8, 12.0)


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    """One synthetic 5-slice DNG stack (128 x 96 px) with 3 % focus breathing, and the dataset
    the CLI made of it."""
    root = tmp_path_factory.mktemp("raw")
    truth = make_stack(root / "stack_a", seed=3, size=(128, 96), slices=5, lens=LENS, breathing=0.03)
    rc = raw_main([str(root / "stack_a"), "--out", str(root / "ds"), "--sensor-width", "12", "--white-balance", "none"])
    assert rc == 0
    return root, truth


def test_decode_is_linear_within_the_noise(tmp_path):
    g = np.random.default_rng(0)
    h, w = 64, 80
    ramp = np.linspace(0.02, 0.9, w)[None, :, None] * np.array([1.0, 0.7, 0.4])[None, None]
    truth = np.broadcast_to(ramp, (h, w, 3))
    full_well, read = 20000.0, 4.0
    electrons = g.poisson(mosaic(truth) * full_well) / full_well + g.normal(0, read / full_well, (h, w))
    cfa = np.round(BLACK + electrons * (WHITE - BLACK))
    write_dng(tmp_path / "ramp.dng", cfa, LENS, 2.0)
    got = decode(tmp_path / "ramp.dng", (1.0, 1.0, 1.0))
    assert got.shape == (h, w, 3)
    inner = (slice(4, -4), slice(4, -4))
    sigma = np.sqrt(truth[inner] / full_well + (read / full_well) ** 2)  # per-pixel noise of one sample
    err = got[inner] - truth[inner]
    assert abs(float(err.mean())) < 1e-3  # no gain or offset: black and white levels applied
    assert float(np.sqrt((err**2).mean())) < 3 * float(sigma.mean())  # demosaicing adds at most noise-sized error
    meta = read_metadata(tmp_path / "ramp.dng")
    assert (meta["make"], meta["focal_length_mm"], meta["f_number"], meta["focus_distance_m"]) == ("neuralbokeh", 50.0, 1.8, 2.0)


def test_stack_becomes_a_dataset_with_accurate_aif_depth_and_alignment(stack):
    root, truth = stack
    scene = load_scene(root / "ds" / "stack_a")
    g = scene["meta"]["generator"]
    (r0, r1), (c0, c1) = g["crop"]["rows"], g["crop"]["cols"]
    true_aif = np.minimum(read_image(root / "stack_a" / "truth" / "aif.exr"), 1.0)[r0:r1, c0:c1]  # the sensor clips at 1
    true_depth = read_image(root / "stack_a" / "truth" / "depth.exr")[r0:r1, c0:c1, 0]
    aif = scene["aif"] / g["exposure_factor"]

    def psnr(a):
        return 10 * np.log10(1.0 / float(np.mean((a - true_aif) ** 2)))

    fused = psnr(aif)
    best_slice = max(psnr(d / g["exposure_factor"]) for d in scene["defocus"])
    assert fused >= 30.0 and fused > best_slice  # fusion beats every single slice
    # depth from focus, in diopters, in the textured quarter of the image
    y = torch.from_numpy(np.log(true_aif.mean(axis=2) + 1e-3))[None, None]
    texture = gaussian_blur2d(laplacian(y, 3) ** 2, (9, 9), (2.0, 2.0))[0, 0].numpy()
    textured = texture > np.percentile(texture, 75)
    err = np.abs(1.0 / scene["depth"] - 1.0 / true_depth)
    spacing = float(np.median(np.abs(np.diff(1.0 / np.array(truth["focus_m"])))))
    assert float(np.median(err[textured])) < 0.5 * spacing
    # focus breathing: the simulated magnifications come back (slices sorted near to far)
    got = [a["scale"] for a in g["alignment"]]
    np.testing.assert_allclose(got, truth["magnification"], atol=0.004)
    assert max(a["residual_px"] for a in g["alignment"]) < 1.0
    # CoC maps follow the camera's lens, the crop's window on its sensor and the depth; the loader
    # takes the scene as it is
    lens = ThinLens.from_dict(scene["meta"]["lens"])
    assert lens == LENS  # the whole sensor: the crop is the window, not another lens
    window = SensorWindow.from_dict(scene["meta"]["sensor_window"])
    assert window.width < 1.0  # the breathing slices were cropped to their common area
    coc0 = lens.coc_px(scene["depth"].astype(np.float64), scene["meta"]["focus_distances_m"][0], aif.shape[1], signed=True,
                       window=window)
    np.testing.assert_allclose(scene["coc"][0], coc0, rtol=1e-5, atol=1e-4)
    assert len(FocalStackDataset(root / "ds", "all")) == 5
    report = {"aif_psnr_db": fused, "best_slice_psnr_db": best_slice, "depth_median_err_diopter_textured": float(np.median(err[textured])),
              "magnification_err_max": float(np.max(np.abs(np.array(got) - truth["magnification"])))}
    print(json.dumps(report))  # the figures of the closing note: pytest -s -k stack_becomes


def test_a_bad_file_is_named_and_the_rest_is_kept(stack, tmp_path):
    root, _ = stack
    src = root / "stack_a"
    bad_stack = tmp_path / "stack_b"
    bad_stack.mkdir()
    for f in sorted(src.glob("*.dng"))[:3]:
        (bad_stack / f.name).write_bytes(f.read_bytes())
    (bad_stack / "slice_09.dng").write_bytes(b"not a raw file")
    rc = raw_main([str(bad_stack), "--out", str(tmp_path / "ds"), "--sensor-width", "12", "--white-balance", "none",
                   "--focus-distances", "0.9,1.1,1.4,2.0"])
    assert rc == 1  # something failed ...
    scene = load_scene(tmp_path / "ds" / "stack_b")  # ... and the usable slices still made a scene
    assert len(scene["defocus"]) == 3 and any("slice_09.dng" in s for s in scene["meta"]["generator"]["failed"])
    rc = raw_main([str(bad_stack), "--out", str(tmp_path / "ds"), "--sensor-width", "12"])  # rerun: skipped
    assert rc == 0


def test_missing_metadata_names_the_option(tmp_path, stack, capsys):
    root, _ = stack
    assert raw_main([str(root / "stack_a"), "--out", str(tmp_path / "x")]) == 1  # no --sensor-width
    assert "give --sensor-width" in capsys.readouterr().out
    from data_tools.raw.__main__ import build_parser
    from data_tools.raw.pipeline import lens_for

    args = build_parser().parse_args([str(root), "--out", "x", "--sensor-width", "12"])
    with pytest.raises(ValueError, match="no focal length mm in the metadata: give --focal-length"):
        lens_for([{"focal_length_mm": None, "f_number": 2.0}], args, root)


# --- real camera files -----------------------------------------------------------------------------


@pytest.mark.shared_data
def test_real_camera_files_decode_or_fail_clearly(shared_data):
    raw = shared_data / "raw"
    kodak = read_metadata(raw / "RAW_KODAK_DC50.KDC")
    assert kodak["make"] == "Eastman Kodak Company" and kodak["focal_length_mm"] == 37.0
    assert kodak["f_number"] == pytest.approx(6.2) and kodak["focus_distance_m"] == pytest.approx(8.2)
    img = decode(raw / "RAW_KODAK_DC50.KDC", white_balance(raw / "RAW_KODAK_DC50.KDC", "camera"))
    assert img.shape == (512, 768, 3) and img.dtype == np.float32 and 0 < img.max() <= 1.0
    nikon = read_metadata(raw / "RAW_NIKON_D1.NEF")
    assert nikon["model"] == "NIKON D1" and nikon["focal_length_mm"] == 20.0 and nikon["focus_distance_m"] is None
    wb = white_balance(raw / "RAW_NIKON_D1.NEF", "camera")  # no as-shot multipliers: daylight, not a magenta cast
    assert wb[0] > 1.5 and wb[2] > 0.9
    img = decode(raw / "RAW_NIKON_D1.NEF", wb, )
    assert img.shape[:2] in ((1324, 2012), (2012, 1324))
    with pytest.raises(RawDecodeError, match="not a colour-filter-array RAW"):
        decode(raw / "Nikon_uncompressed_COOLSCAN.nef", (1.0, 1.0, 1.0))
    assert read_metadata(raw / "Blackmagic.dng")["focal_length_mm"] is None  # no EXIF at all
    stripped = shared_data / "raw_metadata_only"
    for name in ("exiftool_DNG_Canon350D_stripped.dng", "exiv2_IMG_1361_iPhone12Pro_stripped.dng"):
        for _ in range(3):  # LibRaw fills a stripped file's image from uninitialised memory: it must not matter
            with pytest.raises(RawDecodeError, match="image data missing or stripped"):
                decode(stripped / name, (1.0, 1.0, 1.0))
    with pytest.raises(RawDecodeError, match="LibRaw cannot"):
        decode(stripped / "Issue_247-1_D70s.nef", (1.0, 1.0, 1.0))
    assert read_metadata(stripped / "Issue_247-1_D70s.nef")["f_number"] == pytest.approx(2.8)


def test_train_py_consumes_the_raw_dataset(stack, tmp_path):
    from neuralbokeh.training import load_config, train

    root, _ = stack
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(f"""
[data]
roots = ["{root / 'ds'}"]
test_fraction = 0.0
[model]
blocks = "auto"
features = 2
tile = 32
overlap = 8
[train]
steps = 2
batch_size = 2
eval_every = 2
checkpoint_every = 2
out_dir = "{tmp_path / 'run'}"
threads = 1
""")
    summary = train(load_config(cfg), progress=False)
    assert summary["steps"] == 2 and summary["train_samples"] == 5 and Path(summary["checkpoint"]).is_file()

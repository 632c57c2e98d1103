"""The photograph path end to end: synthetic DNG stacks of one camera (and the same stacks
developed to 16-bit PNG) -> ``data_tools.raw`` -> training through two held-out evaluations ->
``export.py`` -> the torch-free runtime; the same for refocused light fields. Photographs and
light fields declare no aperture, so there is no oracle."""

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from kornia.color import linear_rgb_to_rgb

from data_tools.lightfield import main as lightfield_main
from data_tools.lightfield import view_offsets
from data_tools.raw.__main__ import main as raw_main
from data_tools.raw.decode import DecodeSettings, decode
from data_tools.raw.synthetic import make_stack
from neuralbokeh.checkpoint import load_model
from neuralbokeh.core.io import write_image
from neuralbokeh.core.optics import SensorWindow, ThinLens
from neuralbokeh.data.check import require_sound
from neuralbokeh.data.dataset import FocalStackDataset, load_scene
from neuralbokeh.export.exporter import export_checkpoint
from neuralbokeh.runtime import OnnxBokeh

ROOT = Path(__file__).resolve().parents[1]
LENS = ThinLens(50.0, 1.8, 12.0)
SIZE = (96, 64)
OUT_SIZE = ("80", "56")


@pytest.fixture(scope="module")
def stacks(tmp_path_factory):
    """Three 3-slice DNG stacks of one camera with 3 % focus breathing, and one registered stack."""
    root = tmp_path_factory.mktemp("photos")
    for i in range(3):
        make_stack(root / f"stack_{i}", seed=4 + i, size=SIZE, slices=3, lens=LENS, breathing=0.03)
    make_stack(root / "registered", seed=5, size=SIZE, slices=3, lens=LENS, breathing=0.0)
    return root


@pytest.fixture(scope="module")
def camera_dataset(stacks, tmp_path_factory):
    """The three breathing stacks through ``data_tools.raw --size 80 56``."""
    out = tmp_path_factory.mktemp("camera") / "ds"
    _raw([stacks / f"stack_{i}" for i in range(3)], out, "--size", *OUT_SIZE)
    return out


def _raw(stack_dirs, out: Path, *extra: str) -> None:
    assert raw_main([*map(str, stack_dirs), "--out", str(out), "--sensor-width", "12", "--white-balance", "none",
                     *extra]) == 0


def test_a_registered_stack_is_left_as_it_is(stacks, tmp_path):
    _raw([stacks / "registered"], tmp_path / "aligned")
    _raw([stacks / "registered"], tmp_path / "as_is", "--no-align")
    got, want = load_scene(tmp_path / "aligned" / "registered"), load_scene(tmp_path / "as_is" / "registered")
    links = got["meta"]["generator"]["alignment"]
    assert not any(a["kept"] for a in links), links  # no fit beat the identity
    assert got["meta"]["image_size"] == {"width": SIZE[0], "height": SIZE[1]}  # nothing cropped
    np.testing.assert_array_equal(got["aif"], want["aif"])
    for a, b in zip(got["defocus"], want["defocus"]):
        np.testing.assert_array_equal(a, b)


def test_stacks_of_one_camera_share_its_lens(camera_dataset):
    ds = FocalStackDataset(camera_dataset, "all")
    contract = ds.contract()  # refused before: each crop recorded its own sensor width
    assert contract.lens == LENS  # the camera's whole sensor, whatever the crop
    windows = [SensorWindow.from_dict(m["sensor_window"]) for m in ds.metas]
    assert all(w.width < 1.0 and w.height < 1.0 for w in windows)  # the alignment cropped each stack
    # kept fits moved the slices: the breathing stacks were aligned
    assert all(any(a["kept"] for a in m["generator"]["alignment"]) for m in ds.metas)
    require_sound(camera_dataset)  # every CoC map agrees with the lens, the window and the depth


def test_a_crop_window_scales_the_coc():
    window = SensorWindow(0.25, 0.1, 0.5, 0.8)
    full = LENS.coc_px(2.0, 1.0, 100, signed=True)
    assert LENS.coc_px(2.0, 1.0, 100, signed=True, window=window) == pytest.approx(2.0 * full, rel=1e-12)
    assert SensorWindow.from_crop((10, 90), (25, 75), 100, 100) == SensorWindow(0.25, 0.1, 0.5, 0.8)
    with pytest.raises(ValueError, match="reaches past the sensor"):
        SensorWindow(0.6, 0.0, 0.5, 1.0)
    with pytest.raises(ValueError, match="fraction of the sensor"):
        SensorWindow(-0.1, 0.0, 0.5, 1.0)


def _develop(stack: Path, out: Path) -> list[float]:
    """The DNGs of ``stack`` as a camera's developed 16-bit sRGB PNGs; returns the focus distances."""
    out.mkdir(parents=True)
    truth = json.loads((stack / "truth" / "truth.json").read_text())
    for k, f in enumerate(sorted(stack.glob("*.dng"))):
        linear = decode(f, (1.0, 1.0, 1.0), DecodeSettings("AHD", False))
        x = torch.from_numpy(np.ascontiguousarray(np.clip(linear, 0.0, 1.0).transpose(2, 0, 1))).double()
        code = np.round(linear_rgb_to_rgb(x).numpy().transpose(1, 2, 0) * 65535.0)
        write_image(out / f"{k:02d}.png", code, pixel_type="uint16")
    return truth["focus_m"]


def _train_export_render(data: Path, tmp_path: Path) -> None:
    """train.py with two held-out evaluations, export.py, then the runtime on a held-out scene."""
    cfg = tmp_path / "photo.toml"
    cfg.write_text(f"""
[data]
roots = ["{data}"]
test_fraction = 0.34
[model]
tile = 32
overlap = 8
pupil_size = 8
pupil_init = "gaussian"
[train]
steps = 4
batch_size = 2
eval_every = 2
checkpoint_every = 2
out_dir = "{tmp_path / 'run'}"
threads = 1
""")
    r = subprocess.run([sys.executable, "train.py", str(cfg)], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr
    printed = r.stdout
    assert "no oracle row" in printed and "Gaussian blur" in printed
    with open(tmp_path / "run" / "log.csv", newline="") as f:
        evaluated = [r for r in csv.DictReader(f) if r["eval_psnr"]]
    assert [r["step"] for r in evaluated] == ["2", "4"]
    assert all(r["oracle_psnr"] == "" and float(r["gaussian_psnr"]) > float(r["identity_psnr"]) for r in evaluated)

    report = export_checkpoint(tmp_path / "run" / "checkpoint.pt", tmp_path / "lens.onnx", threads=1)
    assert max(report["parity"].values()) <= 1e-4
    runtime = OnnxBokeh(tmp_path / "lens.onnx", threads=1)
    model, _ = load_model(tmp_path / "run" / "checkpoint.pt")
    test = FocalStackDataset(data, "test", test_fraction=0.34, normalize=False)
    scene = load_scene(test.scenes[0])
    window = SensorWindow.from_dict(scene["meta"]["sensor_window"])
    focus = scene["meta"]["focus_distances_m"][0]
    got = runtime.render(scene["aif"], scene["depth"], focus, window=window)
    np.testing.assert_allclose(runtime.coc_px(scene["depth"], focus, window), scene["coc"][0], rtol=1e-5, atol=1e-4)
    with torch.no_grad():
        chw = torch.from_numpy(scene["aif"].transpose(2, 0, 1).copy())[None].float()
        coc = torch.from_numpy(scene["coc"][0].copy())[None, None].float()
        want = model.contract.apply(model, chw, coc)[0].numpy().transpose(1, 2, 0)
    assert np.isfinite(got).all()
    np.testing.assert_allclose(got, want, rtol=1e-3, atol=1e-4)


def _light_field(seed: int, n: int = 5, size=(40, 48)) -> tuple[np.ndarray, np.ndarray]:
    """An n x n light field of a textured square (disparity 2) over a textured plane (-1)."""
    rng = np.random.default_rng(seed)
    far, near = (rng.uniform(0.05, 1.0, (*size, 3)).astype(np.float32) for _ in range(2))
    mask = np.zeros(size, bool)
    mask[10 + seed:26 + seed, 12:32] = True
    du, dv = view_offsets(n)
    views = np.empty((n, n, *size, 3), np.float32)
    for r in range(n):
        for c in range(n):
            shift = lambda d: (int(d * dv[r, c]), int(-d * du[r, c]))  # noqa: E731 (the views' signs (-1, 1))
            views[r, c] = np.roll(far, shift(-1), axis=(0, 1))
            m = np.roll(mask, shift(2), axis=(0, 1))
            views[r, c][m] = np.roll(near, shift(2), axis=(0, 1))[m]
    return views, np.where(mask, 2.0, -1.0).astype(np.float32)


def test_light_fields_train_evaluate_export_and_render(tmp_path):
    # a refocused light field declares no aperture either (the views' lens is the learner's to
    # find), so it takes the photograph path: three scenes of one camera, no oracle row
    for i in range(3):
        views, disparity = _light_field(i)
        np.save(tmp_path / f"views_{i}.npy", views)
        np.save(tmp_path / f"disp_{i}.npy", disparity)
        assert lightfield_main([str(tmp_path / f"views_{i}.npy"), "--disparity", str(tmp_path / f"disp_{i}.npy"),
                                "--out", str(tmp_path / "ds"), "--name", f"lf_{i}", "--disparity-to-depth", "-3", "6",
                                "--focus-disparities=-1,0.5,2"]) == 0
    assert json.loads((tmp_path / "ds" / "lf_0" / "scene.json").read_text())["aperture"] is None
    _train_export_render(tmp_path / "ds", tmp_path)


def test_raw_stacks_train_evaluate_export_and_render(camera_dataset, tmp_path):
    _train_export_render(camera_dataset, tmp_path)


def test_developed_stacks_train_evaluate_export_and_render(stacks, tmp_path):
    for i in range(3):
        focus = _develop(stacks / f"stack_{i}", tmp_path / "png" / f"stack_{i}")
        assert raw_main([str(tmp_path / "png" / f"stack_{i}"), "--out", str(tmp_path / "ds"), "--sensor-width", "12",
                         "--focal-length", "50", "--f-number", "1.8", "--size", *OUT_SIZE,
                         "--focus-distances", ",".join(f"{f:.9g}" for f in focus)]) == 0
    assert json.loads((tmp_path / "ds" / "stack_0" / "scene.json").read_text())["generator"]["source"] == "developed"
    _train_export_render(tmp_path / "ds", tmp_path)

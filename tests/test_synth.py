import json
import shutil

import numpy as np
import pytest

from data_tools.synth import main
from neuralbokeh.core.apertures import ApertureModel, Polygon
from neuralbokeh.core.io import write_image
from neuralbokeh.core.optics import ThinLens
from neuralbokeh.data.dataset import find_scenes, load_scene

ARGS = ["--size", "40", "32", "--slices", "3", "--aperture", "polygon:7", "--cat-eye", "0.5", "--seed", "7"]


def _same_scene(a, b):
    sa, sb = load_scene(a), load_scene(b)
    for key in ("aif", "depth"):
        np.testing.assert_array_equal(sa[key], sb[key])
    for key in ("defocus", "coc"):
        for x, y in zip(sa[key], sb[key]):
            np.testing.assert_array_equal(x, y)


def test_scenes_are_consistent(tiny_dataset):
    for folder in find_scenes(tiny_dataset):
        s = load_scene(folder)
        meta = s["meta"]
        assert meta["generator"]["name"] == "data_tools.synth" and meta["generator"]["seed"] == 7
        assert ApertureModel.from_dict(meta["aperture"]) == ApertureModel(Polygon(7), cat_eye=0.5)
        lens = ThinLens.from_dict(meta["lens"])
        assert len(s["defocus"]) == 3 and (s["depth"] > 0).all()
        for k, f in enumerate(meta["focus_distances_m"]):
            np.testing.assert_allclose(s["coc"][k], lens.coc_px(s["depth"].astype(np.float64), f, 40, signed=True), rtol=1e-5, atol=1e-4)
            assert (s["defocus"][k] >= 0).all() and np.isfinite(s["defocus"][k]).all()
        # focus sweeps near to far: the nearest surface gets blurrier slice after slice
        near = s["depth"] <= s["depth"].min() * 1.001
        blur_near = [np.abs(c[near]).mean() for c in s["coc"]]
        assert blur_near == sorted(blur_near) and blur_near[0] < blur_near[-1]
    # HDR highlights (up to 1000x the diffuse level) are there to make bokeh visible
    peaks = [load_scene(f)["aif"].max() for f in find_scenes(tiny_dataset)]
    assert max(peaks) > 50.0


def test_deterministic_across_worker_counts(tiny_dataset, tmp_path):
    out = tmp_path / "parallel"
    assert main(["--out", str(out), "--scenes", "2", "--workers", "2"] + ARGS) == 0
    for a, b in zip(find_scenes(out), find_scenes(tiny_dataset)[:2]):
        assert a.name == b.name
        _same_scene(a, b)


def test_resume_skips_finished_scenes(tiny_dataset, tmp_path, capsys):
    root = tmp_path / "resume"
    shutil.copytree(tiny_dataset, root)
    shutil.rmtree(root / "scene_00003")
    kept = (root / "scene_00000" / "aif.exr").stat().st_mtime_ns
    capsys.readouterr()
    assert main(["--out", str(root), "--scenes", "5"] + ARGS) == 0
    assert "(1 written now, 4 already there)" in capsys.readouterr().out
    assert (root / "scene_00000" / "aif.exr").stat().st_mtime_ns == kept
    _same_scene(root / "scene_00003", tiny_dataset / "scene_00003")


def test_mask_aperture_from_an_image(tmp_path):
    n = 64
    g = (np.arange(n) + 0.5) / n * 2 - 1
    mask = ((g[None, :] ** 2 + g[:, None] ** 2 <= 1) & (g[:, None] < 0.3)).astype(np.float64)  # a clipped disk
    write_image(tmp_path / "mask.png", mask * 255, pixel_type="uint8")
    out = tmp_path / "m"
    assert main(["--out", str(out), "--scenes", "1", "--size", "24", "24", "--slices", "2",
                 "--aperture", f"mask:{tmp_path / 'mask.png'}"]) == 0
    meta = json.loads((out / "scene_00000" / "scene.json").read_text())
    ap = ApertureModel.from_dict(meta["aperture"])
    np.testing.assert_allclose(ap.shape.mask, mask, atol=1e-12)


@pytest.mark.parametrize(
    "args, message",
    [
        (["--aperture", "hexagon"], "bad aperture spec"),
        (["--near", "5", "--far", "2"], "focal length < --near < --far"),
        (["--cat-eye", "3"], "cat_eye must be <"),
        (["--f-number", "0"], "f_number"),
        (["--aperture", "mask:/nonexistent.png"], "no such image file"),
    ],
)
def test_bad_arguments(tmp_path, args, message):
    with pytest.raises(SystemExit, match=message):
        main(["--out", str(tmp_path / "x"), "--scenes", "1"] + args)

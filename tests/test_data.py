import json
import math
import shutil

import numpy as np
import pytest
import torch

from neuralbokeh.core.apertures import ApertureModel, Polygon
from neuralbokeh.core.io import write_image
from neuralbokeh.core.optics import ThinLens
from neuralbokeh.data.dataset import FocalStackDataset, Normalization, find_scenes, load_scene, split_scenes, write_scene

LENS = ThinLens(85.0, 1.4, 36.0)


# --- normalisation -----------------------------------------------------------------------------


def test_normalization_maps_and_inverts_exactly():
    n = Normalization(0.18, offset=0.0)
    x = np.concatenate([[0.0], np.geomspace(1e-6, 1e6, 2001)])
    y = n.encode(x)
    assert y[0] == -1.0 and n.encode(0.18) == 0.0
    assert (np.diff(y) > 0).all() and (y < 1.0).all()  # monotone, no highlight reaches 1: no clipping
    np.testing.assert_allclose(n.decode(y), x, rtol=1e-9, atol=1e-15)
    # it is tanh of half the log-exposure
    np.testing.assert_allclose(y[1:], np.tanh(0.5 * np.log(x[1:] / 0.18)), atol=1e-12)


def test_normalization_offset_keeps_black_off_the_saturated_end():
    n = Normalization()  # offset = scale / 100
    assert n.offset == pytest.approx(0.0018)
    assert n.encode(0.0) == pytest.approx(-99 / 101)  # (o - s) / (o + s)
    assert math.atanh(n.encode(0.0)) == pytest.approx(0.5 * math.log(0.01))
    x = np.array([-0.0018, -0.001, 0.0, 0.5, 1e3])  # slightly negative noise is representable
    np.testing.assert_allclose(n.decode(n.encode(x)), x, rtol=1e-9, atol=1e-15)
    with pytest.raises(ValueError, match=r"linear colour must be finite and >= -0.0018, got -0.01"):
        n.encode(np.array([-0.01]))


def test_normalization_float32_round_trip_and_torch():
    n = Normalization(0.18)
    x = torch.cat([torch.zeros(1), torch.logspace(-4, 2, 500)]).float()
    back = n.decode(n.encode(x))
    assert back.dtype == torch.float32
    torch.testing.assert_close(back, x, rtol=2e-5, atol=1e-7)  # to 1e2 * s, see the docstring


def test_normalization_errors():
    n = Normalization()
    with pytest.raises(ValueError, match=r"linear colour must be finite and >= -0.0018, got -0.1 at pixel \(0, 1\)"):
        n.encode(np.array([[0.5, -0.1]]))
    with pytest.raises(ValueError, match="got inf"):
        n.encode(np.array([[np.inf]]))
    with pytest.raises(ValueError, match=r"\[-1, 1\)"):
        n.decode(np.array([0.5, 1.0]))
    with pytest.raises(ValueError, match="scale"):
        Normalization(0.0)
    assert Normalization.from_dict(Normalization(0.5).to_dict()) == Normalization(0.5)
    with pytest.raises(ValueError, match="offset"):
        Normalization(0.5, offset=-1.0)


# --- scene files -------------------------------------------------------------------------------


def _arrays(h=6, w=8, k=2, seed=0):
    g = np.random.default_rng(seed)
    aif = g.random((h, w, 3)) * 5
    depth = g.uniform(1.0, 10.0, (h, w))
    depth[0, 0] = np.inf
    focus = [1.5, 4.0][:k]
    cocs = [LENS.coc_px(depth, f, w, signed=True) for f in focus]
    defocus = [g.random((h, w, 3)) for _ in focus]
    return aif, depth, defocus, cocs, focus


def test_write_and_load_scene_round_trip(tmp_path):
    aif, depth, defocus, cocs, focus = _arrays()
    ap = ApertureModel(Polygon(7), cat_eye=0.5)
    folder = write_scene(tmp_path / "s0", aif, depth, defocus, cocs, LENS, focus, ap, {"name": "test", "seed": 3})
    s = load_scene(folder)
    np.testing.assert_array_equal(s["aif"], aif.astype(np.float32))
    np.testing.assert_array_equal(s["depth"], depth.astype(np.float32))
    assert math.isinf(s["depth"][0, 0])
    for a, b in zip(s["coc"], cocs):
        np.testing.assert_array_equal(a, b.astype(np.float32))
    meta = s["meta"]
    assert ThinLens.from_dict(meta["lens"]) == LENS
    assert ApertureModel.from_dict(meta["aperture"]) == ap
    assert meta["focus_distances_m"] == focus and meta["generator"]["seed"] == 3
    assert meta["depth_range_m"][1] is None  # infinity
    assert meta["max_abs_coc_px"] == pytest.approx(max(np.abs(c).max() for c in cocs))
    json.dumps(meta, allow_nan=False)  # strict JSON: no NaN/Infinity tokens
    with pytest.raises(FileExistsError):
        write_scene(folder, aif, depth, defocus, cocs, LENS, focus, ap, {})


def test_write_scene_validates(tmp_path):
    aif, depth, defocus, cocs, focus = _arrays()
    ap = ApertureModel()
    with pytest.raises(ValueError, match="one defocus image and one CoC map per focus"):
        write_scene(tmp_path / "a", aif, depth, defocus[:1], cocs, LENS, focus, ap, {})
    bad = depth.copy()
    bad[2, 3] = -2.0
    with pytest.raises(ValueError, match=r"depth must be > 0 \(inf allowed\) m, got -2.0 at pixel \(2, 3\)"):
        write_scene(tmp_path / "b", aif, bad, defocus, cocs, LENS, focus, ap, {})
    with pytest.raises(ValueError, match="defocus\\[1\\] must have shape"):
        write_scene(tmp_path / "c", aif, depth, [defocus[0], defocus[1][:3]], cocs, LENS, focus, ap, {})
    assert not any(tmp_path.iterdir())


def test_write_scene_is_atomic(tmp_path, monkeypatch):
    aif, depth, defocus, cocs, focus = _arrays()
    calls = {"n": 0}
    real = write_image

    def flaky(path, *a, **k):
        calls["n"] += 1
        if calls["n"] == 4:
            raise OSError("disk full")
        return real(path, *a, **k)

    monkeypatch.setattr("neuralbokeh.data.dataset.write_image", flaky)
    with pytest.raises(OSError, match="disk full"):
        write_scene(tmp_path / "s", aif, depth, defocus, cocs, LENS, focus, ApertureModel(), {})
    assert list(tmp_path.iterdir()) == []  # neither the scene nor its temporary folder


# --- the dataset -------------------------------------------------------------------------------


def test_dataset_items_and_normalisation(tiny_dataset):
    ds = FocalStackDataset(tiny_dataset)
    assert len(ds.scenes) == 5 and len(ds) == 15
    item = ds[4]
    assert item["aif"].shape == (3, 32, 40) and item["coc"].shape == (1, 32, 40) and item["defocus"].shape == (3, 32, 40)
    assert all(t.dtype == torch.float32 for t in (item["aif"], item["coc"], item["defocus"]))
    for key in ("aif", "defocus"):
        assert item[key].min() >= -1 and item[key].max() < 1
    assert item["coc"].abs().max() <= 1.0
    raw = FocalStackDataset(tiny_dataset, normalize=False)[4]
    # float32 near n = 1 limits highlights (~1e3 x middle grey here) to ~1e-4 relative (docstring)
    torch.testing.assert_close(ds.normalization.decode(item["aif"].double()), raw["aif"].double(), rtol=2e-4, atol=1e-7)
    torch.testing.assert_close(item["coc"] * ds.coc_scale_px, raw["coc"], rtol=1e-6, atol=1e-6)
    metas = [json.loads((p / "scene.json").read_text()) for p in find_scenes(tiny_dataset)]
    assert ds.max_coc_px == max(m["max_abs_coc_px"] for m in metas)
    batch = next(iter(torch.utils.data.DataLoader(ds, batch_size=4)))
    assert batch["aif"].shape == (4, 3, 32, 40) and len(batch["scene"]) == 4


def test_split_by_scene_never_by_slice(tiny_dataset):
    train = FocalStackDataset(tiny_dataset, split="train", test_fraction=0.4)
    test = FocalStackDataset(tiny_dataset, split="test", test_fraction=0.4)
    train_scenes = {train[i]["scene"] for i in range(len(train))}
    test_scenes = {test[i]["scene"] for i in range(len(test))}
    assert len(test_scenes) == 2 and len(train_scenes) == 3 and not (train_scenes & test_scenes)
    assert len(train) == 9 and len(test) == 6  # all 3 slices of a scene go together
    # the same seed gives the same split; train and test share the CoC scale
    assert FocalStackDataset(tiny_dataset, split="test", test_fraction=0.4).scenes == test.scenes
    assert train.coc_scale_px == test.coc_scale_px


def test_split_scenes_edge_cases(tmp_path):
    scenes = [tmp_path / f"s{i}" for i in range(2)]
    assert len(split_scenes(scenes, "test", 0.2)) == 1  # at least one held out
    with pytest.raises(ValueError, match="split must be"):
        split_scenes(scenes, "val")
    with pytest.raises(ValueError, match="empty"):
        split_scenes(scenes[:1], "test", 0.2)


def test_dataset_errors_name_the_file(tiny_dataset, tmp_path):
    root = tmp_path / "copy"
    shutil.copytree(tiny_dataset, root)
    scene = find_scenes(root)[0]
    (scene / "coc_1.exr").unlink()
    with pytest.raises(FileNotFoundError, match="coc_1.exr listed in scene.json is missing"):
        FocalStackDataset(root)
    shutil.rmtree(scene)

    scene = find_scenes(root)[0]
    write_image(scene / "defocus_0.exr", np.zeros((8, 8, 3)))
    ds = FocalStackDataset(root)
    with pytest.raises(ValueError, match=r"defocus_0.exr: expected shape \(H, W, C\) = \(32, 40, 3\).*got \(8, 8, 3\)"):
        ds[0]
    shutil.rmtree(scene)

    scene = find_scenes(root)[0]
    meta = json.loads((scene / "scene.json").read_text())
    meta["format_version"] = 99
    (scene / "scene.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="format_version 99 is not supported"):
        FocalStackDataset(root)
    shutil.rmtree(scene)

    (root / "notes").mkdir()
    with pytest.raises(FileNotFoundError, match="notes has no scene.json"):
        FocalStackDataset(root)
    (root / "notes").rmdir()

    (root / ".scene_x.abc.tmp").mkdir()  # an interrupted write: ignored
    ds = FocalStackDataset(root, coc_scale_px=1.0)
    with pytest.raises(ValueError, match="exceeds coc_scale_px=1.0"):
        ds[0]
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no scenes"):
        FocalStackDataset(tmp_path / "empty")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        FocalStackDataset(tmp_path / "nowhere")


def test_several_roots(tiny_dataset):
    ds = FocalStackDataset([tiny_dataset, tiny_dataset])
    assert len(ds) == 30

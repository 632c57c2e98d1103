"""The data contract and the tile grid (core, torch-free): their checks, files and one path."""

import numpy as np
import pytest
import torch

from neuralbokeh.core.contract import CONTRACT_VERSION, Contract
from neuralbokeh.core.io import atomic_write
from neuralbokeh.core.normalization import Normalization
from neuralbokeh.core.optics import ThinLens
from neuralbokeh.core.tiling import TileLayout

CONTRACT = Contract(24, 40, Normalization(0.18), 9.5, 8.0, ThinLens(50.0, 2.0, 36.0), {"shape": {"shape": "disk"}})


def test_round_trip_and_refusals():
    d = CONTRACT.to_dict()
    assert d["version"] == CONTRACT_VERSION and Contract.from_dict(d) == CONTRACT
    with pytest.raises(ValueError, match="version"):
        Contract.from_dict({**d, "version": CONTRACT_VERSION + 1})
    with pytest.raises(ValueError, match="lacks"):
        Contract.from_dict({k: v for k, v in d.items() if k != "coc_scale_px"})
    with pytest.raises(ValueError, match="coc_scale_px must be a finite number > 0 px, got 0.0"):
        Contract(24, 40, Normalization(), 0.0, 8.0)
    with pytest.raises(ValueError, match="image_width must be an integer >= 1 px"):
        Contract(24, 0, Normalization(), 1.0, 1.0)


def test_one_path_for_numpy_and_torch():
    g = np.random.default_rng(0)
    aif = 0.18 * np.exp2(g.uniform(-4, 6, (2, 3, 24, 40)))
    coc = g.uniform(-8, 8, (2, 1, 24, 40))
    x = CONTRACT.network_input(aif, coc)
    assert x.shape == (2, 4, 24, 40) and np.allclose(x[:, 3:], coc / 9.5)
    xt = CONTRACT.network_input(torch.from_numpy(aif), torch.from_numpy(coc))
    assert torch.is_tensor(xt) and np.array_equal(xt.numpy(), x)
    # the identity "network" returns the input colour in linear light
    out = CONTRACT.apply(lambda v: v[:, :3], aif, coc)
    np.testing.assert_allclose(out, aif, rtol=1e-12)
    with pytest.raises(ValueError, match=r"input must have shape \(B, 4, 24, 40\)"):
        CONTRACT.check_network_input(x[:, :3])


@pytest.mark.parametrize("h, w, core, overlap, tiling", [(24, 40, 16, 4, "overlap"), (37, 23, 16, 8, "overlap"),
                                                         (30, 30, 16, 4, "no_overlap"), (13, 11, 64, 16, "none")])
def test_tile_grid_covers_the_image_once(h, w, core, overlap, tiling):
    layout = TileLayout.for_image(h, w, core, overlap, tiling)
    hp, wp = layout.padded_size
    top, bottom, left, right = layout.pads(h, w)
    assert top + h + bottom == hp and left + w + right == wp and min(bottom, right) >= layout.overlap
    # the source masks, placed on the canvas, scatter every canvas pixel exactly once
    count = np.zeros((hp, wp))
    for k, r, c in layout.origins():
        count[r : r + layout.window, c : c + layout.window] += layout.source_masks()[k]
    assert (count == 1).all()
    # and each tile's source region in the image is its core, to the image's edge on the last row/column
    cover = np.zeros((h, w), int)
    for k in range(layout.num_tiles):
        r0, r1, c0, c1 = layout.source_region(k, h, w)
        cover[r0:r1, c0:c1] += 1
    assert (cover == 1).all()
    img = np.arange(h * w, dtype=float).reshape(h, w)
    assert layout.pad_image(img, h, w)[top : top + h, left : left + w].tolist() == img.tolist()


def test_atomic_write_keeps_the_target_on_failure(tmp_path):
    target = tmp_path / "model.onnx"
    target.write_text("old")
    with pytest.raises(RuntimeError, match="disk full"):
        with atomic_write(target) as tmp:
            assert tmp.parent == tmp_path and tmp.suffix == ".onnx"
            tmp.write_text("half")
            raise RuntimeError("disk full")
    assert target.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["model.onnx"]
    with atomic_write(target) as tmp:
        tmp.write_text("new")
    assert target.read_text() == "new" and sorted(p.name for p in tmp_path.iterdir()) == ["model.onnx"]

"""The one definition of the lens network's CoC bands (``core.bands``), as the network, the
exported graph and the runtime all use it."""

import json

import numpy as np
import onnx
import pytest
import torch

from neuralbokeh.checkpoint import load_model
from neuralbokeh.core.bands import (
    BandPlan,
    active_bands,
    band_diameters,
    hermite_weights,
    highlight_coc,
    isolated_highlights,
    lattice_coordinate,
    lattice_diameter,
    lattice_step,
)
from neuralbokeh.export.exporter import plate_model
from neuralbokeh.networks import ModelConfig
from neuralbokeh.networks.lens import band_gates
from neuralbokeh.networks.lens import isolated_highlights as torch_highlights
from neuralbokeh.ops.tiles import tile
from neuralbokeh.runtime import OnnxBokeh


def test_a_plan_covers_the_frame_with_the_fewest_bands_of_the_lattice():
    step = lattice_step(13.0, 6)  # d_n = 1 + 2n
    assert step == 2.0 and BandPlan.for_frame(0.9, step, 13.0).blocks == 0
    for coc, blocks in ((1.2, 1), (3.0, 1), (3.01, 2), (13.0, 6), (20.0, 10)):
        plan = BandPlan.for_frame(coc, step, 13.0)
        assert plan.blocks == blocks and plan.c_plan_px >= coc and plan.c_plan_px - step < coc, coc
    # the fill reaches half the trained range, or the plan's where that is larger
    assert BandPlan.for_frame(4.0, step, 13.0).fill_radius_px == 7
    assert BandPlan.for_frame(20.0, step, 13.0).fill_radius_px == 11
    np.testing.assert_allclose(BandPlan.for_frame(13.0, step, 13.0).diameters, band_diameters(13.0, 6))


def test_numpy_and_torch_read_the_same_band_position():
    plan = BandPlan.for_frame(13.0, lattice_step(13.0, 6), 13.0)
    d = plan.diameters
    c = np.concatenate([d, -d, (d[1:] + d[:-1]) / 2, [0.0, 0.5, 1.0, 40.0, -40.0]])
    got_np = plan.position(c)
    got_torch = plan.position(torch.from_numpy(c)).numpy()
    np.testing.assert_array_equal(got_np, got_torch)
    np.testing.assert_allclose(got_np[: len(d)], np.arange(len(d)), atol=1e-12)  # band n at its centre
    assert got_np[-2] == got_np[-1] == 6.0  # beyond d_N: N
    assert (got_np[-5:-2] == 0.0).all()  # 0, 0.5 and 1 px: a point


def test_the_near_focus_lattice_is_dense_near_focus_and_reads_alike_everywhere():
    """``near_px = a``: the lattice is uniform in ``w(c) = c + a (1 - 1/c)``. Its inverse is exact;
    with a = 0 it is the uniform lattice; band spacings grow from near focus outwards; the
    plan's last centre still reaches the frame's CoC; numpy, torch and the plan agree on the
    band of a CoC; the Hermite slope's step is the lattice's local spacing in |c|; ``blocks =
    "auto"`` adds fewer than a / 2 + 1 bands; a file written before the term plans uniformly."""
    c = np.linspace(1.0, 60.0, 600)
    np.testing.assert_allclose(lattice_diameter(lattice_coordinate(c, 4.0), 4.0), c, rtol=1e-12)
    np.testing.assert_array_equal(lattice_coordinate(c, 0.0), c - 1.0)
    np.testing.assert_allclose(band_diameters(13.0, 6, 0.0), band_diameters(13.0, 6))
    step = lattice_step(13.0, 8, 4.0)
    assert step <= 2.0
    plan = BandPlan.for_frame(13.0, step, 13.0, 4.0)
    d = plan.diameters
    assert plan.blocks == 8 and d[-1] == pytest.approx(13.0) and 1.0 < d[1] < 1.6
    gaps = np.diff(np.r_[1.0, d[1:]])  # from the point's edge (1 px) outwards
    assert np.all(np.diff(gaps) > 0) and gaps[0] < 0.3 * gaps[-1], gaps
    assert np.all(d[1:] <= 2 * np.arange(1, 9) + 1)  # block n's 2n + 1 px kernel holds its band
    for coc in (1.2, 2.0, 7.5, 13.0, 20.0):  # beyond the range: more bands, the same lattice
        p = BandPlan.for_frame(coc, step, 13.0, 4.0)
        assert p.c_plan_px >= coc - 1e-9 and (p.blocks == 1 or p.diameters[-2] < coc), coc
    x = np.concatenate([d, -d, (d[1:] + d[:-1]) / 2, [0.5, 40.0]])
    np.testing.assert_allclose(plan.position(x), plan.position(torch.from_numpy(x)).numpy(), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(plan.position(d), np.arange(9), atol=1e-9)
    central = (d[3] - d[1]) / 2.0
    assert plan.band_step_px(2) == pytest.approx(central, rel=0.05)
    for c_max in (5.0, 13.0, 40.0, 120.0):
        extra = ModelConfig(near_focus_px=4.0).resolved(c_max).blocks - ModelConfig(near_focus_px=0.0).resolved(c_max).blocks
        assert 0 <= extra <= 3, (c_max, extra)
    old = BandPlan.from_dict({"step_px": 2.0, "blocks": 6, "fill_radius_px": 7})
    assert old.near_px == 0.0 and np.allclose(old.diameters, band_diameters(13.0, 6))
    assert BandPlan.from_dict(plan.to_dict()) == plan


def test_hermite_weights_keep_the_flux_and_live_where_the_hat_does():
    """The Hermite blend's kernel weights of all bands sum to 1 at every position (the slopes
    sum to 0, so the flux is kept), each band's weights are non-zero exactly where its hat is,
    a band centre takes its own kernel with no slope, between band 0 (a point, no slope) and
    band 1 both keep the hat; numpy and torch read the same."""
    blocks = 5
    pos = np.linspace(0.0, blocks, 1001)
    values = np.stack([hermite_weights(pos, n)[0] for n in range(1, blocks + 1)])
    slopes = np.stack([hermite_weights(pos, n)[1] for n in range(1, blocks + 1)])
    band0 = np.clip(1.0 - pos, 0.0, None)
    np.testing.assert_allclose(band0 + values.sum(0), 1.0, atol=1e-12)
    for n in range(1, blocks + 1):
        hat = np.clip(1.0 - np.abs(pos - n), 0.0, None)
        assert np.array_equal(values[n - 1] > 0, hat > 0), n
        assert not np.any((slopes[n - 1] != 0) & (hat == 0)), n
        at = np.isclose(pos, n)
        np.testing.assert_allclose(values[n - 1][at], 1.0) and np.testing.assert_allclose(slopes[n - 1][at], 0.0)
    first = pos < 1.0
    np.testing.assert_allclose(values[0][first], pos[first]) and np.testing.assert_allclose(slopes[0][first], 0.0)
    t = 0.3  # between centres 2 and 3: h10(t) = t (1 - t)^2 and h11(t) = t^2 (t - 1)
    at = np.asarray([2.0 + t])
    np.testing.assert_allclose([hermite_weights(at, 2)[1][0], hermite_weights(at, 3)[1][0]], [t * (1 - t) ** 2, t**2 * (t - 1)])
    for n in (1, 3):
        for got, want in zip(hermite_weights(torch.from_numpy(pos), n), hermite_weights(pos, n)):
            np.testing.assert_allclose(got.numpy(), want, atol=1e-12)


def test_the_file_carries_the_plate_plan_and_the_runtime_plans_with_it(busy_checkpoint, busy_onnx, tmp_path):
    """The exported file stores the plate's own plan; the runtime reads it (a lens file without
    one is refused: no second copy of the planning rules), and its band flags cover every band
    the network's gates use, by the same position function."""
    model, _ = load_model(busy_checkpoint)
    plate = plate_model(model)
    want = plate.plan(plate.contract.max_coc_px)
    m = OnnxBokeh(busy_onnx, threads=1)
    assert m.plan == want and json.loads(onnx.load(busy_onnx).metadata_props[0].value)["band_plan"] == want.to_dict()
    planless = onnx.load(busy_onnx)
    meta = json.loads(planless.metadata_props[0].value)
    del meta["band_plan"]
    planless.metadata_props[0].value = json.dumps(meta)
    onnx.save(planless, tmp_path / "planless.onnx")
    with pytest.raises(ValueError, match="planless.onnx: a lens model without its band plan: export the checkpoint again"):
        OnnxBokeh(tmp_path / "planless.onnx", threads=1)
    g = np.random.default_rng(3)
    coc = g.uniform(-1.0, 1.0, (1, m.height, m.width)) * want.c_plan_px / 3  # a third of the range,
    coc[..., : m.width // 2] = 0.0  # and the left half in focus
    flags = active_bands(coc, want, m.layout)
    # the network's own gates on what each tile scatters: its windows (edge copies in their
    # padding) under its source mask
    win, layout = m.layout.window, m.layout
    gates = band_gates(torch.from_numpy(coc).float(), want.c_plan_px, want.blocks)  # (1, H, W, N + 1)
    gates = tile(gates.permute(0, 3, 1, 2).contiguous(), layout).view(layout.num_tiles, want.blocks + 1, win, win)
    signed = tile(torch.from_numpy(coc)[:, None].float(), layout).view(layout.num_tiles, win, win)
    masks = torch.from_numpy(layout.source_masks()) > 0
    for n in range(1, want.blocks + 1):
        for k in range(m.num_tiles):
            region = gates[k, n][masks[k]]
            for side, sel in enumerate((signed[k][masks[k]] > 0, signed[k][masks[k]] < 0)):
                used = bool(((region > 0) & sel).any())
                assert flags[k, n - 1, side] >= used, (n, k, side)
    assert flags.sum() < flags.size  # and something was left out
    running = g.random(m.num_tiles) < 0.5  # the runtime asks only for the tiles that run
    np.testing.assert_array_equal(active_bands(coc, want, m.layout, running), flags & running[:, None, None])


def _disk_image(d: float, x0: float, y0: float, half: int = 8, ss: int = 16) -> np.ndarray:
    """A disk of diameter ``d`` px centred at ``(x0, y0)`` px from a pixel's corner, box-filtered
    into pixels (``ss`` x ``ss`` samples each): ``(2 half, 2 half)``, summing to 1."""
    s = (np.arange(-half * ss, half * ss) + 0.5) / ss
    inside = ((s[None, :] - x0) ** 2 + (s[:, None] - y0) ** 2 <= (d / 2) ** 2).astype(float)
    k = inside.reshape(2 * half, ss, 2 * half, ss).sum(axis=(1, 3))
    return k / k.sum()


def test_a_highlight_gets_the_kernel_of_a_point_anywhere_in_its_pixel():
    """An isolated highlight is a light smaller than its pixel, at an unknown place in it: its
    expected defocused image is a disk placed at 8 x 8 places in the pixel, box-filtered,
    averaged. Below 2 px the area raster at ``highlight_coc(d)`` is nearer it (L2, the kernels
    summing to 1) than the raster at ``d`` (0.05 against 0.43 at 1 px, 0.04 against 0.06 at
    1.75) and than the disk of the same variance, ``sqrt(d^2 + 4/3)``. From 2 px on it is the
    raster at ``d``, which is as near as that disk to within 0.04 (the two swing with d)."""
    offsets = (np.arange(8) + 0.5) / 8
    for d in (1.0, 1.25, 1.5, 1.75, 2.0, 3.0, 5.0):
        expected = np.mean([_disk_image(d, a, b) for a in offsets for b in offsets], axis=0)
        raster, grown, same_variance = (np.sqrt(((_disk_image(v, 0.5, 0.5) - expected) ** 2).sum())
                                        for v in (d, float(highlight_coc(np.asarray(d))), np.sqrt(d * d + 4.0 / 3.0)))
        if d < 2.0:
            assert grown < 0.8 * raster and grown < 0.6 * same_variance, (d, raster, grown, same_variance)
        else:
            assert grown == raster and abs(raster - same_variance) < 0.04, (d, raster, same_variance)
    c = np.array([-9.0, -1.5, -1.0, -0.3, 0.0, 0.3, 1.0, 1.5, 2.0, 9.0])
    fade = np.clip(1.0 - c * c / 4.0, 0.0, None)
    grown2 = c * c + 4.0 / 3.0 * fade
    want = np.where(np.abs(c) >= 1, np.sign(c) * np.sqrt(grown2), c * np.sqrt(grown2))
    np.testing.assert_allclose(highlight_coc(c), want, rtol=1e-12)
    np.testing.assert_allclose(highlight_coc(torch.from_numpy(c)).numpy(), want, rtol=1e-12)


def test_isolated_highlights_are_single_bright_pixels_alike_in_numpy_and_torch():
    """A pixel 3 times brighter than its neighbours' mean is one; no pixel of a bright block, edge
    or corner is, however bright; one in the frame's corner is one (the frame mirrored at its
    edge, the pixel itself not repeated); numpy and torch agree on a busy random frame."""
    rgb = np.full((1, 3, 12, 14), 0.1, dtype=np.float32)
    rgb[0, :, 2, 3] = 0.31  # just above 3 x 0.1
    rgb[0, :, 5, 9] = 0.29  # just below
    rgb[0, :, 0, 13] = 50.0  # on the corner of the frame
    rgb[0, :, 7:10, 1:5] = 1e4  # a block: its corners and edges are no highlights
    want = np.zeros((1, 12, 14), dtype=bool)
    want[0, 2, 3] = want[0, 0, 13] = True
    np.testing.assert_array_equal(isolated_highlights(rgb), want)
    np.testing.assert_array_equal(torch_highlights(torch.from_numpy(rgb))[:, 0].numpy(), want)
    busy = (0.18 * np.exp2(np.random.default_rng(4).uniform(-4, 4, (2, 3, 40, 32)))).astype(np.float32)
    found = isolated_highlights(busy)
    assert 0 < found.sum() < found.size
    np.testing.assert_array_equal(torch_highlights(torch.from_numpy(busy))[:, 0].numpy(), found)

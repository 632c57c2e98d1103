"""The torch-free runtime: agreement with PyTorch, its errors, and in-focus tile skipping."""

import json
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch

from neuralbokeh.checkpoint import load_model
from neuralbokeh.runtime.onnx_model import OnnxBokeh

ROOT = Path(__file__).resolve().parents[1]


def _scene(model: OnnxBokeh, seed=0):
    g = np.random.default_rng(seed)
    aif = (0.18 * np.exp2(g.uniform(-3, 3, (model.height, model.width, 3)))).astype(np.float32)
    return aif


def _torch_render(checkpoint, aif, coc_px):
    model, _ = load_model(checkpoint)
    x = model.contract.network_input(aif.astype(np.float64).transpose(2, 0, 1)[None], coc_px[None, None])
    with torch.no_grad():
        return model(torch.from_numpy(x).float())[0].numpy()


def test_render_matches_pytorch_through_lens_and_normalisation(busy_onnx, busy_checkpoint):
    m = OnnxBokeh(busy_onnx, threads=1, skip_in_focus=False)
    aif = _scene(m)
    depth = np.linspace(1.7, 2.5, m.height * m.width).reshape(m.height, m.width)
    focus = 2.0
    coc = m.coc_px(depth, focus)
    assert np.abs(coc).max() <= m.contract.max_coc_px
    out = m.render(aif, depth[..., None], focus)
    assert out.shape == aif.shape and out.dtype == np.float32
    want = _torch_render(busy_checkpoint, aif, coc)
    got = m.contract.normalization.encode(out.astype(np.float64)).transpose(2, 0, 1)
    assert np.abs(got - want).max() < 1e-4
    np.testing.assert_array_equal(out, m.render_coc(aif, coc))
    batch = m.render(np.stack([aif, aif[::-1].copy()]), np.stack([depth, depth]), focus)
    np.testing.assert_allclose(batch[0], out, rtol=1e-6, atol=1e-6)
    assert m.contract == load_model(busy_checkpoint)[0].contract


def test_runtime_errors_name_the_value(busy_onnx):
    m = OnnxBokeh(busy_onnx, threads=1)
    aif = _scene(m)
    depth = np.full((m.height, m.width), 3.0)
    with pytest.raises(ValueError, match=rf"aif must have shape \({m.height}, {m.width}, 3\)"):
        m.render(aif[:-1], depth[:-1], 2.0)
    bad = aif.copy()
    bad[5, 7, 1] = np.nan
    with pytest.raises(ValueError, match=r"aif colour must be finite, got nan at pixel \(5, 7\)"):
        m.render(bad, depth, 2.0)
    bad[5, 7, 1] = np.inf
    with pytest.raises(ValueError, match="must be finite, got inf"):
        m.render(bad, depth, 2.0)
    d = depth.copy()
    d[12, 4] = -1.0
    with pytest.raises(ValueError, match=r"got -1.0 at pixel \(12, 4\)"):
        m.render(aif, d, 2.0)
    with pytest.raises(ValueError, match="depth_m must have shape"):
        m.render(aif, depth[:, :5], 2.0)
    with pytest.raises(ValueError, match=r"exceeds the largest this file renders, .* px; export it again with a larger --max-coc"):
        m.render_coc(aif, np.full(depth.shape, m.contract.max_coc_px * 1.5))
    with pytest.raises(FileNotFoundError):
        OnnxBokeh(busy_onnx.parent / "missing.onnx")


def test_clamping_the_coc_is_explicit_and_warns_once(busy_onnx, caplog):
    m = OnnxBokeh(busy_onnx, threads=1)
    aif = _scene(m)
    coc = np.full((m.height, m.width), m.contract.max_coc_px * 2.0)
    with pytest.raises(ValueError, match=r"clamp_coc=True \(--clamp-coc on the command line\)"):
        m.render_coc(aif, coc)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # logged, not a Python warning with a source line
        out = m.render_coc(aif, coc, clamp_coc=True)
    assert [r.levelname for r in caplog.records if "clamped" in r.getMessage()] == ["WARNING"]
    caplog.clear()
    np.testing.assert_array_equal(out, m.render_coc(aif, np.full_like(coc, m.contract.max_coc_px)))
    assert not caplog.records
    with pytest.raises(ValueError, match="threads must be a whole number >= 1"):
        OnnxBokeh(busy_onnx, threads=-4)


def test_depth_at_infinity_renders_finite(busy_onnx):
    m = OnnxBokeh(busy_onnx, threads=1)
    focus = next(f for f in np.geomspace(0.2, 1e3, 200) if abs(m.coc_px(np.inf, f)) <= m.contract.max_coc_px)
    out = m.render(_scene(m), np.full((m.height, m.width), np.inf), focus)
    assert np.isfinite(out).all()


@pytest.mark.parametrize("which", ["lens", "paper"])
def test_in_focus_tiles_are_skipped_and_defocused_ones_unchanged(which, request):
    busy_onnx = request.getfixturevalue("busy_onnx" if which == "lens" else "busy_paper_onnx")
    m_full = OnnxBokeh(busy_onnx, threads=1, skip_in_focus=False)
    m_skip = OnnxBokeh(busy_onnx, threads=1)
    rows, cols, t, t_o = m_skip.layout
    assert (rows, cols) == (2, 3) and m_skip.width == 40
    aif = _scene(m_skip, seed=3)
    coc = np.zeros((m_skip.height, m_skip.width))
    coc[:, 24:] = 0.8 * m_skip.contract.max_coc_px  # tile column 0's window (x < 20) is all in focus
    coc[:, 10:24] = 0.3  # below the 0.5 px threshold
    full, skip = m_full.render_coc(aif, coc), m_skip.render_coc(aif, coc)
    assert m_full.last_tiles_run == 6 and m_skip.last_tiles_run == 4
    np.testing.assert_array_equal(skip[:, t + t_o :], full[:, t + t_o :])  # covered only by tiles that ran
    np.testing.assert_allclose(skip[:, : t - t_o], aif[:, : t - t_o], rtol=2e-6)  # skipped: the input
    if which == "paper":
        assert np.abs(full[:, : t - t_o] - aif[:, : t - t_o]).max() > 1e-3  # the busy network would have changed it
    else:  # the lens network leaves CoC <= 1 px untouched (highlights up to 0.65 px): skipping is exact everywhere
        np.testing.assert_allclose(skip, full, rtol=2e-6, atol=1e-7)
        # a lens tile scatters its core only: column 0's window reaches the blur, its core does not
        # (0.6 px: an isolated highlight there grows to 0.92 px, still in focus)
        reach = np.where(np.arange(m_skip.width) > t, 0.8 * m_skip.contract.max_coc_px, 0.6)[None].repeat(m_skip.height, 0)
        full, skip = m_full.render_coc(aif, reach), m_skip.render_coc(aif, reach)
        assert m_skip.last_tiles_run == 4 and m_skip.active_tiles(reach[None]).all()
        np.testing.assert_allclose(skip, full, rtol=2e-6, atol=1e-7)
    everything_sharp = m_skip.render_coc(aif, np.zeros_like(coc))
    assert m_skip.last_tiles_run == 0
    np.testing.assert_allclose(everything_sharp, aif, rtol=2e-6)


def test_a_core_no_running_window_reaches_is_the_input_bit_for_bit(busy_onnx):
    m_full = OnnxBokeh(busy_onnx, threads=1, skip_in_focus=False)
    m_skip = OnnxBokeh(busy_onnx, threads=1)
    rows, cols, t, t_o = m_skip.layout
    edge = 2 * t + t_o  # the middle column's window ends here: only the last column runs
    assert cols == 3 and edge + 1 < m_skip.width
    aif = _scene(m_skip, seed=4)
    coc = np.zeros((m_skip.height, m_skip.width))
    coc[:, edge + 1 :] = -0.8 * m_skip.contract.max_coc_px  # a blurred foreground: its light reaches the middle core
    full, skip = m_full.render_coc(aif, coc), m_skip.render_coc(aif, coc)
    assert m_skip.last_tiles_run == rows
    np.testing.assert_allclose(skip, full, rtol=2e-6, atol=1e-7)
    assert np.abs(full[:, t:edge] - aif[:, t:edge]).max() > 1e-3  # the middle core took light from the last one
    # the first column's core: no window that ran reaches it, so the graph hands back its input
    colour, c = m_skip.contract.encode_inputs(aif.transpose(2, 0, 1)[None], coc[None, None])
    active = np.arange(rows * cols) % cols == cols - 1
    bands = m_skip.active_bands(coc[None]) & active[:, None, None]
    feeds = {"aif": colour.astype(np.float32), "coc": c.astype(np.float32), "tile_active": active, "band_active": bands}
    black = np.float32(m_skip.contract.normalization.encode(0.0))
    feeds["aif"][0, 1, 2, 3] = -0.999  # light below 0 (the input allows it): the composite clamps it to black
    out = m_skip.session.run(["defocus"], feeds)[0]
    np.testing.assert_array_equal(out[..., :t], np.maximum(feeds["aif"][..., :t], black))
    assert out[0, 1, 2, 3] == black
    assert not np.array_equal(out[..., t : 2 * t], feeds["aif"][..., t : 2 * t])


def test_bands_no_pixel_of_a_tile_uses_are_left_out_exactly(busy_onnx, busy_checkpoint):
    m_full = OnnxBokeh(busy_onnx, threads=1, skip_in_focus=False)
    m_skip = OnnxBokeh(busy_onnx, threads=1)
    blocks = m_skip.meta["model_config"]["blocks"]
    aif = _scene(m_skip, seed=5)
    g = np.random.default_rng(2)
    coc = g.uniform(-1.0, 1.0, (m_skip.height, m_skip.width)) * m_skip.contract.max_coc_px / 3  # a third of the range
    full, skip = m_full.render_coc(aif, coc), m_skip.render_coc(aif, coc)
    assert m_full.last_bands_run == m_skip.num_tiles * blocks * 2
    assert 0 < m_skip.last_bands_run <= m_skip.num_tiles * 2 * (blocks // 3 + 2)
    np.testing.assert_allclose(skip, full, rtol=2e-6, atol=1e-7)


def test_a_highlight_runs_the_band_its_grown_coc_needs_though_no_pixel_does(busy_onnx, busy_checkpoint, tmp_path):
    """``model.highlight_spread``: isolated highlights at 0.9 px of CoC in an in-focus frame grow
    out of band 0; the skipping runtime runs band 1 for them (no pixel's own CoC needs it) and
    renders what PyTorch does, not the input. A file written before the key does not spread."""
    m = OnnxBokeh(busy_onnx, threads=1)
    assert m.highlight_spread
    aif = np.full((m.height, m.width, 3), 0.05, dtype=np.float32)
    coc = np.full((m.height, m.width), 0.3)
    for r, c in ((3, 4), (9, 27), (14, 35)):
        aif[r, c] = 40.0
        coc[r - 1 : r + 2, c - 1 : c + 2] = 0.9
    assert not m.active_bands(coc[None]).any()  # by their own CoC, nothing to run
    out = m.render_coc(aif, coc)
    assert m.last_bands_run > 0
    got = m.contract.normalization.encode(out.astype(np.float64)).transpose(2, 0, 1)
    assert np.abs(got - _torch_render(busy_checkpoint, aif, coc)).max() < 1e-4
    assert np.abs(out - aif).max() > 1.0  # spread, not passed through
    legacy = onnx.load(busy_onnx)
    meta = json.loads(legacy.metadata_props[0].value)
    del meta["model_config"]["highlight_spread"]
    legacy.metadata_props[0].value = json.dumps(meta)
    onnx.save(legacy, tmp_path / "legacy.onnx")
    assert not OnnxBokeh(tmp_path / "legacy.onnx", threads=1).highlight_spread


def test_active_bands_hold_every_band_the_network_uses(busy_onnx, busy_checkpoint):
    """The runtime's band flags (numpy, float64) cover the PyTorch model's own test (float32), at
    band centres and edges too, where the two could round differently."""
    from neuralbokeh.networks.lens import band_gates
    from neuralbokeh.ops.tiles import tile

    m = OnnxBokeh(busy_onnx, threads=1)
    model, _ = load_model(busy_checkpoint)
    cfg = model.config
    c_max = float(model.contract.coc_scale_px)
    layout = model.layout(m.height, m.width)
    d = m.plan.diameters
    g = np.random.default_rng(8)
    levels = np.concatenate([d, (d[1:] + d[:-1]) / 2, d + 1e-7, d - 1e-7, [0.0, 0.5]])
    coc = g.choice(levels, (2, m.height, m.width)) * g.choice([-1.0, 1.0], (2, m.height, m.width))
    flags = m.active_bands(coc)
    c = tile(torch.from_numpy(coc[:, None] / c_max).float(), layout) * c_max  # (B, T, win, win)
    gates = band_gates(c, c_max, cfg.blocks)  # the network's own
    src = model.source_masks(layout, c.device, c.dtype)
    for n in range(1, cfg.blocks + 1):
        for side, sel in enumerate((c > 0, c < 0)):
            used = ((gates[..., n] * sel * src[None, :, 0]).flatten(2).amax(-1) > 0).any(0).numpy()
            assert not (used & ~flags[:, n - 1, side]).any(), (n, side)
    one = m.active_bands(np.full((1, m.height, m.width), (d[2] + d[3]) / 2))  # between bands 2 and 3, behind
    assert one[:, [1, 2], 0].all() and one.sum() == 2 * m.num_tiles  # and nothing else


def test_runtime_imports_no_torch(busy_onnx):
    code = ("import sys, numpy as np; from neuralbokeh.runtime import OnnxBokeh; "
            f"m = OnnxBokeh(r'{busy_onnx}', threads=1); "
            "m.render_coc(np.full((m.height, m.width, 3), 0.2, np.float32), np.zeros((m.height, m.width))); "
            "assert 'torch' not in sys.modules, 'torch was imported'")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


def test_a_foreign_onnx_file_is_refused(tmp_path):
    import onnx
    from onnx import TensorProto, helper

    g = helper.make_graph([helper.make_node("Identity", ["x"], ["y"])], "g",
                          [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1])],
                          [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1])])
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    m.ir_version = 9
    onnx.save(m, tmp_path / "x.onnx")
    with pytest.raises(ValueError, match="not exported by neuralbokeh"):
        OnnxBokeh(tmp_path / "x.onnx")

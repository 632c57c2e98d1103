"""Numerical stability through PyTorch and ONNX (fp32 and fp16) on stiff and extreme inputs.

Cases (``probe_inputs``): random, everything in focus, everything at the maximum CoC (both
signs), a one-pixel depth edge from in focus to the maximum CoC, 1e4 highlights; models:
a busy 40x32 network (6 tiles), one smaller than one tile and one of odd size, each for the
default (lens) architecture and the paper's; and the lens network exported for plates it was
not trained at (a crop at the sensor's corner of odd size, a CoC twice the trained maximum, a
larger frame). Depth = inf and
NaN/inf inputs are covered through the runtime in ``test_runtime.py`` and below.
"""

import numpy as np
import pytest
import torch
from conftest import busy

from neuralbokeh.checkpoint import load_model, save_checkpoint
from neuralbokeh.core.contract import Contract
from neuralbokeh.core.normalization import Normalization
from neuralbokeh.core.optics import SensorWindow, ThinLens
from neuralbokeh.export.exporter import DEFAULT_TOLERANCE as TOLERANCE
from neuralbokeh.export.exporter import export_checkpoint, plate_model, probe_inputs, run_session
from neuralbokeh.networks import ModelConfig, build_model
from neuralbokeh.runtime.onnx_model import make_session as session


def _random_checkpoint(path, height, width, architecture):
    """A ``height`` x ``width`` network of ``architecture`` (N for a 7 px CoC scale) made busy as
    the suite's shared checkpoints are (``conftest.busy``)."""
    cfg = ModelConfig(features=4, tile=16, overlap=4, architecture=architecture).resolved(7.0)
    contract = Contract(height, width, Normalization(), 7.0, 7.0, ThinLens(50.0, 2.0, 36.0))
    torch.manual_seed(height * 1000 + width)
    plain = save_checkpoint(path.with_name(path.stem + "_plain.pt"), {
        "model_config": cfg.to_dict(), "model_state": build_model(cfg, contract).state_dict(),
        "contract": contract.to_dict(), "step": 0})
    return busy(plain, path, seed=height * 1000 + width)


@pytest.fixture(scope="module", params=[f"{a}_{c}" for a in ("lens", "paper")
                                        for c in ("busy_40x32", "smaller_than_a_tile_13x11", "odd_37x23")])
def checkpoint(request, tmp_path_factory):
    architecture, case = request.param.split("_", 1)
    if case == "busy_40x32":
        return request.getfixturevalue("busy_checkpoint" if architecture == "lens" else "busy_paper_checkpoint")
    h, w = (11, 13) if case.startswith("smaller") else (23, 37)
    return _random_checkpoint(tmp_path_factory.mktemp("stab") / f"{request.param}.pt", h, w, architecture)


@pytest.mark.parametrize("kernels", ["direct", "multires:1"])
@pytest.mark.parametrize("fp16", [False, True], ids=["fp32", "fp16"])
def test_extreme_cases_are_finite_bounded_and_within_parity(checkpoint, fp16, kernels, tmp_path):
    """``multires:1`` (lens only): every band of these small models on a coarser grid."""
    model, _ = load_model(checkpoint)
    cfg = model.config
    if kernels != "direct" and cfg.architecture != "lens":
        pytest.skip("coarser band grids are the lens network's export option")
    report = export_checkpoint(checkpoint, tmp_path / "m.onnx", fp16=fp16, kernels=kernels, threads=1)
    scales = report["band_scales"]
    sess = session(str(tmp_path / "m.onnx"), threads=1)
    norm = Normalization()
    for name, (aif, coc) in probe_inputs(*model.contract.size).items():
        assert report["parity"][name] <= TOLERANCE[fp16], name
        with torch.no_grad():
            x = torch.from_numpy(np.concatenate([aif, coc], axis=1))
            ref = (model(x, scales=scales) if scales else model(x)).numpy()
        got = run_session(sess, aif, coc)
        for out in (ref, got):
            assert np.isfinite(out).all() and np.abs(out).max() < 1.0, name
            assert np.isfinite(norm.decode(out.astype(np.float64))).all(), name
        assert np.abs(got - ref).max() <= TOLERANCE[fp16], name
    if not fp16:  # in-focus 1e4 highlights pass through the fp32 identity head unharmed in the skip
        assert report["parity"]["highlights_1e4"] <= 1e-4


def test_pytorch_model_refuses_nan_and_inf_inputs(busy_checkpoint, monkeypatch):
    """Where inputs enter (the contract's encoding) always; inside forward with the debug switch."""
    from neuralbokeh.core import checks

    model, _ = load_model(busy_checkpoint)
    x = torch.zeros(1, 4, *model.contract.size)
    aif, coc = torch.full((1, 3, *model.contract.size), 0.18), torch.zeros(1, 1, *model.contract.size)
    for bad in (float("nan"), float("inf")):
        x[0, 1, 3, 5] = bad
        coc[0, 0, 3, 5], aif[0, 2, 4, 6] = bad, 0.18
        with pytest.raises(ValueError, match=r"CoC in px must be finite, got (nan|inf) at pixel \(3, 5\)"):
            model.contract.apply(model, aif, coc)
        coc[0, 0, 3, 5], aif[0, 2, 4, 6] = 0.0, bad
        with pytest.raises(ValueError, match=r"linear colour must be finite and >= .*, got (nan|inf) at pixel \(4, 6\)"):
            model.contract.apply(model, aif, coc)
        monkeypatch.setattr(checks, "DEBUG", True)
        with pytest.raises(ValueError, match=r"model input must be finite, got (nan|inf) at pixel \(3, 5\)"):
            model(x)
        monkeypatch.setattr(checks, "DEBUG", False)


@pytest.mark.parametrize("case, size, window, coc_factor", [
    ("corner_crop_odd_29x19", (19, 29), SensorWindow(0.75, 0.8, 0.25, 0.2), 1.0),
    ("coc_2x_trained", None, None, 2.0),
    ("larger_plate_64x48", (48, 64), None, 1.0),
])
@pytest.mark.parametrize("fp16", [False, True], ids=["fp32", "fp16"])
def test_plate_exports_are_finite_bounded_and_within_parity(busy_checkpoint, case, size, window, coc_factor, fp16, tmp_path):
    """The learned lens exported for plates it was not trained at: a crop at the sensor's corner of
    odd size, a CoC twice the trained maximum, a larger frame; the runtime against the PyTorch
    model of the same plate on the extreme probes."""
    trained, ckpt = load_model(busy_checkpoint)
    max_coc = coc_factor * ckpt["contract"]["max_coc_px"]
    report = export_checkpoint(busy_checkpoint, tmp_path / "p.onnx", fp16=fp16, kernels="direct", threads=1, size=size,
                               window=window, max_coc_px=max_coc)
    model = plate_model(trained, size, max_coc)
    assert model.contract.max_coc_px >= max_coc and report["metadata"]["contract"] == model.contract.to_dict()
    w = window or SensorWindow()
    wt = torch.tensor([[w.left, w.top, w.width, w.height]])
    sess = session(str(tmp_path / "p.onnx"), threads=1)
    for name, (aif, coc) in probe_inputs(*model.contract.size).items():
        with torch.no_grad():
            ref = model(torch.from_numpy(np.concatenate([aif, coc], axis=1)), wt, plan_coc_px=model.contract.max_coc_px).numpy()
        got = run_session(sess, aif, coc)
        for out in (ref, got):
            assert np.isfinite(out).all() and np.abs(out).max() < 1.0, name
        assert np.abs(got - ref).max() <= TOLERANCE[fp16], (case, name)

"""Focus-stack fusion and depth from focus on stacks rendered from known layered scenes:
duplicated focus distances, sub-slice depth, and fusion against a per-pixel argmax."""

import math

import numpy as np
import pytest
import torch

from data_tools.procedural import SceneParams, composite_sharp, make_layers
from data_tools.raw.fuse import focus_measure, fuse_stack, peak_diopters
from neuralbokeh.core.apertures import ApertureModel
from neuralbokeh.core.optics import ThinLens, focus_sweep_m
from neuralbokeh.evaluation.metrics import image_metrics
from neuralbokeh.render import scatter_layers

LENS = ThinLens(50.0, 1.8, 12.0)


def _stack(focus_f: list[tuple[float, float]], seed=5, size=(96, 72)):
    """Slices of one layered scene for ``(focus_m, f_number)`` pairs; the true AIF and depth."""
    w, h = size
    rng = np.random.default_rng(seed)
    layers = make_layers(rng, h, w, SceneParams(near_m=0.8, far_m=6.0, infinite_background=0.0, highlights=(1, 3)))
    aif, depth = composite_sharp(layers)
    colors = torch.from_numpy(np.stack([la.color * la.alpha[..., None] for la in layers])).permute(0, 3, 1, 2)
    alphas = torch.from_numpy(np.stack([la.alpha for la in layers]))[:, None]
    slices = []
    for f, n in focus_f:
        lens = ThinLens(LENS.focal_length_mm, n, LENS.sensor_width_mm)
        cocs = [lens.coc_px(la.depth_m, f, w, signed=True) for la in layers]
        slices.append(scatter_layers(colors, alphas, cocs, ApertureModel()).permute(1, 2, 0).numpy())
    return slices, aif, depth, layers


def _argmax_fusion(slices):
    best = focus_measure(slices).argmax(dim=0).numpy()
    return np.take_along_axis(np.stack(slices), best[None, ..., None], 0)[0]


def _scene_range(layers):
    finite = [la.depth_m for la in layers if math.isfinite(la.depth_m)]
    return min(finite), max(finite)


@pytest.mark.parametrize("kind", ["even", "duplicated", "two apertures"])
def test_fusion_is_finite_and_at_least_as_good_as_argmax(kind):
    _, _, _, layers = _stack([(1.0, 1.8)])
    sweep = focus_sweep_m(*_scene_range(layers), 5)
    if kind == "even":
        pairs = [(f, 1.8) for f in sweep]
    elif kind == "duplicated":  # the same distance twice
        pairs = [(f, 1.8) for f in sweep] + [(sweep[2], 1.8)]
    else:  # every distance at f/1.8 and, 0.2 % farther, at f/4
        pairs = [(f, 1.8) for f in sweep] + [(f * 1.002, 4.0) for f in sweep]
    slices, aif, _, _ = _stack(pairs)
    fused = fuse_stack(slices, [p[0] for p in pairs])
    assert np.isfinite(fused.aif).all() and np.isfinite(fused.diopters).all()
    ours = image_metrics(fused.aif, aif)["psnr_srgb"]
    argmax = image_metrics(_argmax_fusion(slices), aif)["psnr_srgb"]
    assert ours >= argmax, (ours, argmax)


def test_depth_from_focus_is_between_the_slices():
    _, _, _, layers = _stack([(1.0, 1.8)])
    near, far = _scene_range(layers)
    sweep = focus_sweep_m(0.8 * near, 1.5 * far, 6)  # wider than the scene: its layers fall between slices
    slices, _, depth, _ = _stack([(f, 1.8) for f in sweep])
    d = 1.0 / np.asarray(sweep)
    fm = focus_measure(slices)
    raw, conf = peak_diopters(fm, d)
    best = fm.argmax(dim=0).numpy()
    inner = (best > 0) & (best < len(d) - 1) & (conf.numpy() > 0.5)  # an end slice has nothing beyond it to fit
    offset = np.abs(raw.numpy() - d[best]) / np.abs(np.diff(d)).mean()
    assert inner.sum() > 100 and float((offset[inner] < 0.01).mean()) < 0.1
    fused = fuse_stack(slices, list(sweep))
    assert np.isfinite(fused.diopters).all() and (fused.depth_m > 0).all()


def test_one_focus_distance_is_an_error():
    slices, _, _, _ = _stack([(1.5, 1.8), (1.5, 4.0)])
    with pytest.raises(ValueError, match="distinct focus distances"):
        fuse_stack(slices, [1.5, 1.5])
    with pytest.raises(ValueError, match="must be > 0 m"):
        fuse_stack(slices, [1.5, -1.0])

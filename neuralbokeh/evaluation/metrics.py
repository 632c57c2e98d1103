"""Image error metrics for the evaluation report (numpy in, floats out; kornia and FLIP do the work).

All inputs are linear scene-referred RGB ``(H, W, 3)``, finite and >= 0.

* ``psnr_linear`` / ``ssim_linear``: in linear light, both images divided by the reference's
  maximum (so the reference spans [0, 1]; HDR highlights set the scale, as they dominate
  linear-light error).
* ``psnr_srgb`` / ``ssim_srgb``: after the same tone map for both: exposure so that 0.18 is
  middle grey, Reinhard ``x / (1 + x)``, then the sRGB transfer function (IEC 61966-2-1), in [0, 1].
* ``flip_hdr``: mean HDR-FLIP (NVIDIA's ``flip-evaluator``, made to compare rendered images,
  needs no learned weights; the paper reports LPIPS, whose weights cannot be downloaded here).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from kornia.metrics import psnr, ssim

from ..core.checks import check_nonnegative


def _t(img: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1), dtype=np.float64))[None]


def tonemap_srgb(img: np.ndarray) -> np.ndarray:
    """Linear RGB -> display sRGB in [0, 1): Reinhard on the linear values, then the sRGB curve."""
    x = img / (1.0 + img)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 0.0031308), 1 / 2.4) - 0.055)


def _check(pred: np.ndarray, ref: np.ndarray) -> None:
    if pred.shape != ref.shape or pred.ndim != 3 or pred.shape[2] != 3:
        raise ValueError(f"images must both be (H, W, 3), got {pred.shape} and {ref.shape}")
    check_nonnegative("prediction", pred)
    check_nonnegative("reference", ref)


def image_metrics(pred: np.ndarray, ref: np.ndarray) -> dict[str, float]:
    """All metrics of the module doc for one prediction against its reference."""
    _check(pred, ref)
    peak = float(ref.max()) or 1.0
    p_lin, r_lin = _t(pred / peak), _t(ref / peak)
    p_s, r_s = _t(tonemap_srgb(pred)), _t(tonemap_srgb(ref))
    return {
        "psnr_linear": float(psnr(p_lin, r_lin, 1.0)),
        "ssim_linear": float(ssim(p_lin, r_lin, 11).mean()),
        "psnr_srgb": float(psnr(p_s, r_s, 1.0)),
        "ssim_srgb": float(ssim(p_s, r_s, 11).mean()),
        "flip_hdr": flip_hdr(pred, ref),
    }


def flip_hdr(pred: np.ndarray, ref: np.ndarray) -> float:
    """Mean HDR-FLIP error in [0, 1] (0: identical)."""
    import flip_evaluator

    _check(pred, ref)
    _, mean, _ = flip_evaluator.evaluate(np.ascontiguousarray(ref, dtype=np.float32),
                                         np.ascontiguousarray(pred, dtype=np.float32), "HDR", applyMagma=False)
    return float(mean)


def pareto_front(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points (time, error) no other point beats in both (lower is better)."""
    front = []
    for i, (t, e) in enumerate(points):
        if not any((t2 <= t and e2 <= e) and (t2 < t or e2 < e) for j, (t2, e2) in enumerate(points) if j != i):
            front.append(i)
    return front


HIGHER_IS_BETTER = {"psnr_linear": True, "ssim_linear": True, "psnr_srgb": True, "ssim_srgb": True, "flip_hdr": False}


def scene_means(per_sample: list[dict], key: str) -> dict[str, float]:
    """A metric averaged over each scene's samples (``sample`` reads ``"scene#slice"``)."""
    groups: dict[str, list[float]] = {}
    for p in per_sample:
        groups.setdefault(p["sample"].rsplit("#", 1)[0], []).append(p[key])
    return {scene: float(np.mean(v)) for scene, v in groups.items()}


def paired_by_scene(ref: list[dict], other: list[dict], key: str, resamples: int = 2000, seed: int = 0) -> dict[str, Any]:
    """``ref`` minus ``other`` on one metric, scene by scene (per-sample lists of the same samples).

    Slices of one scene share their content, so the scene, not the sample, is the unit: the
    interval is a percentile bootstrap of the mean difference over scenes (``resamples`` draws,
    seeded). Returns ``{"scenes", "ahead" (scenes where ref is better), "median", "mean", "ci95"}``.
    """
    if key not in HIGHER_IS_BETTER:
        raise ValueError(f"unknown metric {key!r}: expected one of {sorted(HIGHER_IS_BETTER)}")
    a, b = scene_means(ref, key), scene_means(other, key)
    if a.keys() != b.keys():
        raise ValueError(f"the two methods were scored on different scenes: {sorted(a.keys() ^ b.keys())}")
    d = np.array([a[s] - b[s] for s in sorted(a)])
    sign = 1.0 if HIGHER_IS_BETTER[key] else -1.0
    draws = np.random.default_rng(seed).integers(0, len(d), size=(resamples, len(d)))
    means = d[draws].mean(axis=1)
    return {"scenes": len(d), "ahead": int((sign * d > 0).sum()), "median": float(np.median(d)), "mean": float(d.mean()),
            "ci95": [float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5))]}

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

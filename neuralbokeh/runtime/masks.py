"""Mask operations for compositing, in numpy (the compositing path runs without torch).

Equivalent to kornia's ``morphology.erosion`` with a square structuring element and to
``filters.gaussian_blur2d`` with reflect borders; ``tests/test_composite.py`` checks both
against kornia.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from ..core.checks import check_at_least


def erode(mask: np.ndarray, radius_px: int) -> np.ndarray:
    """Grey-scale erosion of ``(H, W)`` by a ``(2 r + 1)`` square; pixels outside the image are
    ignored (kornia's 'geodesic' border). ``radius_px`` >= 0 (0 returns a copy)."""
    if not isinstance(radius_px, (int, np.integer)) or radius_px < 0:
        raise ValueError(f"erosion radius must be an integer >= 0 px, got {radius_px!r}")
    if radius_px == 0:
        return mask.copy()
    r = int(radius_px)
    padded = np.pad(mask, r, mode="edge")  # an edge copy never lowers a window's minimum
    rows = sliding_window_view(padded, 2 * r + 1, axis=0).min(axis=-1)
    return sliding_window_view(rows, 2 * r + 1, axis=1).min(axis=-1)


def gaussian_kernel1d(sigma_px: float) -> np.ndarray:
    """Normalised 1-D Gaussian of standard deviation ``sigma_px`` (> 0), ``2 ceil(3 sigma) + 1`` taps."""
    check_at_least("Gaussian sigma", sigma_px, 1e-6, " px")
    half = math.ceil(3.0 * sigma_px)
    x = np.arange(-half, half + 1, dtype=np.float64)
    k = np.exp(-0.5 * (x / sigma_px) ** 2)
    return k / k.sum()


def gaussian_blur(mask: np.ndarray, sigma_px: float) -> np.ndarray:
    """Separable Gaussian blur of ``(H, W)`` with reflect borders (``sigma_px`` = 0: a copy)."""
    if sigma_px == 0:
        return mask.copy()
    k = gaussian_kernel1d(sigma_px)
    half = len(k) // 2
    if half >= min(mask.shape):
        raise ValueError(f"Gaussian sigma {sigma_px} px needs an image larger than {half} px on each side, got {mask.shape}")
    out = np.pad(mask.astype(np.float64), ((half, half), (0, 0)), mode="reflect")
    out = sliding_window_view(out, len(k), axis=0) @ k
    out = np.pad(out, ((0, 0), (half, half)), mode="reflect")
    return (sliding_window_view(out, len(k), axis=1) @ k).astype(mask.dtype)

"""All-in-focus fusion and depth from focus for an aligned focal stack (torch + kornia).

1. Focus measure per slice and pixel: the squared Laplacian of log luminance (so a highlight
   and a shadow with the same relative contrast count the same) after a light Gaussian
   pre-filter (sigma 0.7 px: sensor noise and the resampling of alignment then weigh alike
   on every slice), averaged by a Gaussian of ``window_px``.
2. Depth from focus, in diopters (1 / m), where the focus measure of a scene point peaks:
   the best slice per pixel, refined by a parabola through the *log* of the measure at it and
   its neighbours in diopter coordinates (Gaussian interpolation: the measure falls off about
   like a Gaussian of defocus; slices need not be evenly spaced). A pixel whose best slice is
   the first or the last keeps that slice's position (nothing beyond the stack to fit): on the
   repository's PCB stack that is 59 % of the pixels, and it is what makes depths look locked
   to the slices there (of the pixels peaking at an inner slice, 1.9 % lie within 0.01 slice
   of it). Confidence in [0, 1]: how far the peak stands above the stack's mean response,
   times a texture term ``f / (f + floor)``.
3. Edge-aware regularisation: normalised convolution with a guided filter (He et al.; kornia's
   ``guided_blur``, separable box means: memory O(pixels) and time O(radius) per pixel, where
   a joint bilateral filter holds pixels x window^2 values) guided by the log of the
   sharpest slice: ``D <- GF(c D) / GF(c)`` over a few passes of growing radius, then
   ``c D + (1 - c) D_reg``; low-texture regions take the depth of their surroundings with the
   same colour instead of noise. The fill runs on a grid 4x coarser in float32 (16x fewer
   pixels, a quarter of the radius): it only decides where confidence is low, and there a
   4 px blur of the fill is below what the depth from focus resolves. It was 97-99 % of the
   fusion's time at full resolution in float64 (``benchmarks/bench_fusion.py``).
4. Fusion: every pixel takes its sharpest slice (the argmax of the windowed focus measure).
   Measured on stacks rendered from known scenes (``tests/test_fuse.py``,
   ``benchmarks/bench_fusion.py``), every blend tried lost to it: the two slices bracketing
   the *regularised* depth, interpolated (the earlier choice), by 1.2 dB, since between two
   slices neither is sharp and the blend is blurrier than the better one; soft weights
   ``f^g / sum f^g`` by 0.01-1 dB for g = 8-64. With a known depth (``known_diopters``) the
   bracketing blend is used.

Slices focused at the same distance, or within ``merge_diopters`` of each other (a stack shot
at two apertures), are one focus position: of each such group only the slice with the highest
mean focus measure is kept (logged), for the depth and for the fusion alike. This also keeps the
fusion from mixing slices of different depths of field (on the two-aperture stack of the
benchmark: 31.0 dB after merging against 27.7 dB for the argmax over all ten slices).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from kornia.filters import gaussian_blur2d, guided_blur, laplacian

log = logging.getLogger(__name__)

REGULARISE_SCALE = 4  # the depth regularisation runs on a grid this many times coarser


@dataclass
class FusionResult:
    """``aif (H, W, 3)`` linear RGB; ``depth_m (H, W)`` (inf where focused at infinity);
    ``diopters (H, W)``; ``confidence (H, W)`` in [0, 1] (before regularisation)."""

    aif: np.ndarray
    depth_m: np.ndarray
    diopters: np.ndarray
    confidence: np.ndarray


def _chw(img: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1), dtype=np.float32))[None]


def focus_measure(slices: list[np.ndarray], window_px: float = 2.0) -> torch.Tensor:
    """``(K, H, W)`` focus measure of ``K`` aligned ``(H, W, 3)`` linear slices."""
    stack = torch.stack([_chw(s)[0] for s in slices]).double()  # (K, 3, H, W)
    y = stack.mean(dim=1, keepdim=True)
    y = torch.log(y.clamp(min=0.0) + 1e-3 * float(y.mean()) + 1e-12)
    y = gaussian_blur2d(y, (5, 5), (0.7, 0.7), border_type="reflect")
    lap = laplacian(y, kernel_size=3, border_type="reflect") ** 2
    k = 2 * int(np.ceil(3 * window_px)) + 1
    return gaussian_blur2d(lap, (k, k), (window_px, window_px), border_type="reflect")[:, 0]


def peak_diopters(fm: torch.Tensor, diopters: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """Sub-slice peak position (diopters) and confidence from a ``(K, H, W)`` focus measure."""
    k_count = fm.shape[0]
    d = torch.as_tensor(diopters, dtype=fm.dtype)
    best = fm.argmax(dim=0)
    peak = fm.max(dim=0).values
    lo, hi = (best - 1).clamp(min=0), (best + 1).clamp(max=k_count - 1)
    tiny = 1e-6 * float(fm.mean()) + 1e-300
    f0, f1, f2 = (torch.log(v + tiny) for v in (fm.gather(0, lo[None])[0], peak, fm.gather(0, hi[None])[0]))
    x0, x1, x2 = d[lo], d[best], d[hi]
    # vertex of the parabola through (x0, f0), (x1, f1), (x2, f2); ends of the stack keep x1
    den = (x0 - x1) * (x0 - x2) * (x1 - x2)
    a = (x2 * (f1 - f0) + x1 * (f0 - f2) + x0 * (f2 - f1)) / torch.where(den == 0, torch.ones_like(den), den)
    b = (x2**2 * (f0 - f1) + x1**2 * (f2 - f0) + x0**2 * (f1 - f2)) / torch.where(den == 0, torch.ones_like(den), den)
    interior = (lo != best) & (hi != best) & (a < 0)
    vertex = torch.where(interior, -b / (2 * torch.where(a == 0, -torch.ones_like(a), a)), x1)
    lower, upper = torch.minimum(x0, x2), torch.maximum(x0, x2)
    vertex = torch.where(interior, torch.maximum(torch.minimum(vertex, upper), lower), vertex)  # a maximum between its neighbours
    mean = fm.mean(dim=0)
    floor = 1e-2 * float(fm.mean()) + 1e-12
    confidence = ((peak - mean) / (peak + 1e-12)) * (peak / (peak + floor))
    return vertex, confidence.clamp(0.0, 1.0)


def _regularise(depth: torch.Tensor, confidence: torch.Tensor, guide: torch.Tensor, passes: int = 4,
               scale: int = REGULARISE_SCALE) -> torch.Tensor:
    """Confidence-weighted, edge-aware fill of ``depth`` ``(H, W)`` guided by ``guide``
    ``(1, 1, H, W)`` in [0, 1]; radii 4, 8, 16, 32 px, on a grid ``scale`` times coarser (area
    averages in, bilinear out; float32): memory and time O(pixels / scale^2 x radius)."""
    eps = 0.1**2  # guide differences well below 0.1 (a tenth of the log range) count as one surface
    h, w = depth.shape
    small = (max(1, round(h / scale)), max(1, round(w / scale)))

    def down(x: torch.Tensor) -> torch.Tensor:
        return F.interpolate(x.float(), size=small, mode="area") if scale > 1 else x.float()

    num, den, g = down((confidence * depth)[None, None]), down(confidence[None, None]), down(guide)
    for n in range(passes):
        k = 2 * max(1, round(4 * 2**n / scale)) + 1
        num = guided_blur(g, num, k, eps, border_type="reflect", separable=True)
        den = guided_blur(g, den, k, eps, border_type="reflect", separable=True)
    ratio = num / den.clamp(min=1e-6)
    if scale > 1:
        ratio = F.interpolate(ratio, size=(h, w), mode="bilinear", align_corners=False)
    lo, hi = float(depth.amin()), float(depth.amax())
    smooth = ratio[0, 0].double().clamp(lo, hi)  # the guided filter's overshoot stays in range
    return confidence * depth + (1.0 - confidence) * smooth


def merge_focus_duplicates(diopters: np.ndarray, sharpness: np.ndarray, tolerance: float) -> list[int]:
    """Indices of the slices to keep: of every run of slices whose sorted focus positions lie
    within ``tolerance`` diopters of the previous one, the one with the highest ``sharpness``."""
    order = np.argsort(diopters, kind="stable")
    groups: list[list[int]] = [[int(order[0])]]
    for i in order[1:]:
        if diopters[i] - diopters[groups[-1][-1]] <= tolerance:
            groups[-1].append(int(i))
        else:
            groups.append([int(i)])
    keep = sorted(max(g, key=lambda i: sharpness[i]) for g in groups)
    for g in groups:
        if len(g) > 1:
            log.info("slices %s are focused within %.3g diopters of each other: kept slice %d, the sharpest",
                     g, tolerance, max(g, key=lambda i: sharpness[i]))
    return keep


def fuse_stack(slices: list[np.ndarray], focus_m: list[float], window_px: float = 2.0,
               known_diopters: np.ndarray | None = None, merge_diopters: float | None = None) -> FusionResult:
    """All-in-focus image and depth from ``K >= 2`` aligned ``(H, W, 3)`` linear slices focused
    at ``focus_m`` (m, > 0, inf allowed). ``known_diopters`` ``(H, W)`` (1/m, >= 0): a known depth
    (e.g. from multi-view reconstruction) used instead of depth from focus. ``merge_diopters``
    (1/m, >= 0): slices focused closer than this are one focus position (default: 2 % of the
    stack's diopter range; see the module doc).

    Raises:
        ValueError: fewer than two slices or distances, a distance that is not > 0, or fewer than
            two distinct focus positions.
    """
    if len(slices) != len(focus_m) or len(slices) < 2:
        raise ValueError(f"need >= 2 slices with one focus distance each, got {len(slices)} slices, {len(focus_m)} distances")
    bad = [f for f in focus_m if not f > 0]
    if bad:
        raise ValueError(f"focus distances must be > 0 m (inf allowed), got {bad[0]}")
    diopters = np.array([0.0 if np.isinf(f) else 1.0 / f for f in focus_m], dtype=np.float64)
    fm = focus_measure(slices, window_px)
    tolerance = 0.02 * float(np.ptp(diopters)) if merge_diopters is None else float(merge_diopters)
    keep = merge_focus_duplicates(diopters, fm.mean(dim=(1, 2)).numpy(), tolerance)
    if len(keep) < 2:
        raise ValueError(f"need >= 2 distinct focus distances, got {sorted(set(focus_m))} m (within {tolerance:.3g} diopters)")
    if len(keep) < len(slices):
        slices, diopters, fm = [slices[i] for i in keep], diopters[keep], fm[keep]
    stack = torch.stack([_chw(s)[0] for s in slices]).double()  # (K, 3, H, W)
    if known_diopters is not None:
        kd = known_diopters
        if kd.shape != tuple(fm.shape[1:]) or not np.isfinite(kd).all() or (kd < 0).any():
            raise ValueError(f"known depth must be > 0 m (inf allowed) with shape {tuple(fm.shape[1:])}, got shape {kd.shape}")
        d = torch.from_numpy(kd.astype(np.float64))
        conf = torch.ones_like(d)
        aif = _bracket_blend(stack, diopters, d)
    else:
        raw_d, conf = peak_diopters(fm, diopters)
        aif = stack.gather(0, fm.argmax(dim=0)[None, None].expand(1, 3, *fm.shape[1:]))[0]  # each pixel's sharpest slice
        guide = torch.log(aif.clamp(min=0.0) + 1e-3 * float(aif.mean()) + 1e-12)[None]
        guide = (guide - guide.amin()) / (guide.amax() - guide.amin() + 1e-12)
        d = _regularise(raw_d, conf, guide)
    dio = d.numpy()
    with np.errstate(divide="ignore"):
        depth = np.where(dio > 0, 1.0 / np.maximum(dio, 1e-300), np.inf)
    return FusionResult(aif.numpy().transpose(1, 2, 0).astype(np.float32), depth.astype(np.float32), dio.astype(np.float32),
                        conf.numpy().astype(np.float32))


def _bracket_blend(stack: torch.Tensor, diopters: np.ndarray, d: torch.Tensor) -> torch.Tensor:
    """``(3, H, W)``: the two slices of ``(K, 3, H, W)`` whose focus brackets each pixel's
    diopter ``d`` ``(H, W)``, interpolated linearly."""
    order = np.argsort(diopters)
    ds = torch.as_tensor(diopters[order])
    idx = torch.searchsorted(ds, d.contiguous()).clamp(1, len(ds) - 1)
    d0, d1 = ds[idx - 1], ds[idx]
    t = ((d - d0) / (d1 - d0)).clamp(0.0, 1.0)
    s_sorted = stack[torch.as_tensor(order)]
    lo = s_sorted.gather(0, (idx - 1)[None, None].expand(1, 3, *d.shape))[0]
    hi = s_sorted.gather(0, idx[None, None].expand(1, 3, *d.shape))[0]
    return (1 - t) * lo + t * hi

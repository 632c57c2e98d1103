"""Shapes to pixels: the pupil samples of ray-traced renderers and the anti-aliased kernels
(point-spread functions) at a CoC diameter, optionally clipped by a vignetting circle."""

from __future__ import annotations

import math

import numpy as np

from ..checks import check_nonnegative
from .shapes import Aperture, ViewGrid


def pupil_grid(shape: Aperture, n: int, rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Sample points of the pupil where ``shape`` transmits: the one pupil definition of every
    renderer that traces rays (kernels sample the same square).

    The pupil is the square ``[-1, 1]^2`` of normalised coordinates and the shape's own
    transmission is its support: there is no implicit disk (a disk-shaped aperture is a
    ``Disk``), so e.g. ``MaskAperture(np.ones(...))`` is a square in every renderer.

    Args:
        shape: the aperture shape.
        n: points per side of the regular ``n x n`` grid of cell centres, >= 1.
        rng: if given, each point is jittered uniformly inside its cell (stratified sampling).

    Returns:
        ``(M, 2)`` points ``(u right, v up)`` and their transmissions ``(M,)``, all > 0.
    """
    if int(n) != n or n < 1:
        raise ValueError(f"pupil grid size must be an integer >= 1, got {n!r}")
    if isinstance(shape, ViewGrid):  # a light field's aperture is its views: no other point of the pupil
        u, v, w = shape.points()
        return np.stack([u, v], axis=1), w
    cell = np.arange(n, dtype=np.float64)
    if rng is None:
        u, v = np.meshgrid(cell + 0.5, cell + 0.5)
    else:
        u = cell[None, :] + rng.uniform(size=(n, n))
        v = cell[:, None] + rng.uniform(size=(n, n))
    u, v = u / n * 2.0 - 1.0, v / n * 2.0 - 1.0
    t = np.broadcast_to(shape.transmission(u, v), u.shape)
    keep = t > 0
    return np.stack([u[keep], v[keep]], axis=1), t[keep]


def kernel_radius_px(diameter_px: float) -> int:
    """Half-width h of the ``(2h+1, 2h+1)`` kernel for a CoC diameter (px)."""
    return max(0, math.ceil(diameter_px / 2.0 - 0.5))


def shape_kernel_radius_px(shape: Aperture, diameter_px: float) -> int:
    """Half-width of ``shape``'s kernel at a CoC diameter (px): :func:`kernel_radius_px`, one
    more for a :class:`ViewGrid` out of focus (its outermost views' bilinear splats)."""
    h = kernel_radius_px(diameter_px)
    return h + 1 if isinstance(shape, ViewGrid) and h > 0 else h


def _view_kernels(shape: ViewGrid, diameter_px: float, centers: np.ndarray | None, clip_radius: float) -> np.ndarray:
    """:func:`shape_kernels` of a light field's views: each view's point splatted bilinearly."""
    u, v, w = shape.points()
    h = shape_kernel_radius_px(shape, diameter_px)
    k, r = 2 * h + 1, diameter_px / 2.0
    x, y = h + r * u, h - r * v  # kernel pixel coordinates: rows go down, v goes up
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = x - x0, y - y0
    keeps = [np.ones_like(w)] if centers is None else [((u - cu) ** 2 + (v - cv) ** 2 <= clip_radius**2).astype(np.float64)
                                                       for cu, cv in centers]
    kern = np.zeros((len(keeps), k, k))
    for i, keep in enumerate(keeps):
        for dy, wy in ((0, 1.0 - fy), (1, fy)):
            for dx, wx in ((0, 1.0 - fx), (1, fx)):
                np.add.at(kern[i], (np.minimum(y0 + dy, k - 1), np.minimum(x0 + dx, k - 1)), w * keep * wy * wx)
    total = kern.sum(axis=(1, 2))
    if (total <= 0).any():
        raise ValueError(f"the cat-eye's circle (radius {clip_radius}) lets none of the {len(w)} views through")
    return kern / total[:, None, None]


def _auto_supersample(diameter_px: float) -> int:
    # About 128 samples across the diameter, 4..32 per pixel: fine edges for small kernels,
    # bounded cost for large ones.
    return int(min(32, max(4, math.ceil(128.0 / max(diameter_px, 1.0)))))


def shape_kernels(
    shape: Aperture,
    diameter_px: float,
    clip_centers: np.ndarray | None = None,
    clip_radius: float = 1.0,
    supersample: int | None = None,
) -> np.ndarray:
    """Anti-aliased kernels of ``shape`` at one CoC diameter for several vignetting circles.

    The shape is sampled once; only the clip circle changes between the kernels, so many
    positions of a cat-eye grid cost little more than one.

    Args:
        shape: the aperture shape.
        diameter_px: CoC diameter in px, finite and >= 0.
        clip_centers: ``(M, 2)`` centres ``(u, v)`` of the vignetting circles (aperture radii),
            or None for one unclipped kernel.
        clip_radius: radius of the vignetting circle in aperture radii.
        supersample: samples per pixel side (default: automatic, 4 to 32).

    Returns:
        ``(M, k, k)`` float64 (M = 1 without clipping), each summing to 1; ``k = 1`` (a delta)
        below one pixel.

    Raises:
        ValueError: bad diameter, or a shape (after vignetting) that lets no light through.
    """
    check_nonnegative("CoC diameter", diameter_px, " px")
    centers = None if clip_centers is None else np.asarray(clip_centers, dtype=np.float64).reshape(-1, 2)
    m = 1 if centers is None else len(centers)
    h = kernel_radius_px(diameter_px)
    if h == 0:
        return np.ones((m, 1, 1))
    if isinstance(shape, ViewGrid):
        return _view_kernels(shape, diameter_px, centers, clip_radius)
    s = supersample or _auto_supersample(diameter_px)
    r = diameter_px / 2.0
    # Sample positions (in px from the centre) on a regular s x s grid inside each pixel.
    offs = (np.arange(s) + 0.5) / s - 0.5
    pos = (np.arange(-h, h + 1)[:, None] + offs[None, :]).reshape(-1)
    u = pos[None, :] / r
    v = -pos[:, None] / r  # rows go down, v goes up
    t = shape.transmission(u, v)
    k = 2 * h + 1
    if centers is None:
        kern = t.reshape(1, k, s, k, s).mean(axis=(2, 4))
    else:
        kern = np.empty((m, k, k))
        for i, (cu, cv) in enumerate(centers):
            clipped = t * ((u - cu) ** 2 + (v - cv) ** 2 <= clip_radius**2)
            kern[i] = clipped.reshape(k, s, k, s).mean(axis=(1, 3))
    total = kern.sum(axis=(1, 2))
    if (total <= 0).any():
        if h <= 2:  # shape thinner than the sampling at a tiny diameter: a point
            kern[total <= 0] = 0.0
            kern[total <= 0, h, h] = 1.0
            total = kern.sum(axis=(1, 2))
        else:
            raise ValueError(f"aperture {shape.to_dict()['shape']} lets no light through at diameter {diameter_px} px")
    return kern / total[:, None, None]


def shape_kernel(
    shape: Aperture,
    diameter_px: float,
    clip_center: tuple[float, float] | None = None,
    clip_radius: float = 1.0,
    supersample: int | None = None,
) -> np.ndarray:
    """One anti-aliased ``(k, k)`` kernel of ``shape`` at ``diameter_px``, summing to 1.

    ``clip_center`` (``(u, v)`` in aperture radii) intersects the shape with a circle of
    radius ``clip_radius`` (cat-eye vignetting). See :func:`shape_kernels`.
    """
    centers = None if clip_center is None else np.asarray([clip_center])
    return shape_kernels(shape, diameter_px, centers, clip_radius, supersample)[0]

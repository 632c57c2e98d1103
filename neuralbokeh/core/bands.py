"""The CoC bands of the lens network, torch-free: the one definition of a frame's plan.

A lens network splits each pixel's |CoC| into bands on a lattice uniform in the *lattice
coordinate* ``w(|c|) = |c| + a (1 - 1 / |c|)`` (px; ``a`` = ``near_px``, 0 for a lattice uniform
in |c|): band 0 is ``|c| <= 1`` px, a point, and band n is centred where ``w(d_n) = 1 + n step``.
Near focus a step is a large fraction of a band's diameter, and a blend of two kernels there is
far from the kernel in between (a highlight at 1.5 px blended from a point and a 3 px disk); the
second term makes the bands ``1 + a / |c|^2`` times denser there and adds fewer than ``a /
step`` bands in all, wherever the range ends. A frame runs the bands up to the first
whose centre reaches its own largest |CoC|. The network (``networks.lens``), the ONNX builder
(``export.lens_graph``) and the runtime (``runtime.onnx_model``, which switches off the bands a
frame's tiles do not use) all read the lattice, the plan and the band of a CoC from here; the
exported file carries its :class:`BandPlan` so that the runtime plans with the same numbers.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from .tiling import TileLayout

# |c| <= POINT_PX is band 0 (in focus: a point); band n >= 1 is centred where w(d_n) = POINT_PX + n step
POINT_PX = 1.0
# An isolated highlight (a pixel far brighter than its neighbours) is a light smaller than its pixel,
# somewhere in it. Its defocused image is the PSF placed there, box-filtered; not knowing where, the
# best estimate is the PSF blurred by one more pixel box (1/12 px^2 per axis). Every kernel here is
# a disk's area raster, so such a source gets the disk whose raster is nearest (L2) that estimate:
# by brute force sqrt(d^2 + S (1 - d^2 / E^2)) from 1 px to E = 2 px, S = 16 / 12 (the box's variance
# in diameter^2 units), and d itself from E on, where the raster of d is already as near as any
# disk; the disk of the same variance (S at every d) is wider than the nearest from 1 to 3 px
# (docs/network.md, "Isolated highlights").
HIGHLIGHT_SPREAD_PX2 = 16.0 / 12.0
HIGHLIGHT_SPREAD_END_PX = 2.0
# a pixel is an isolated highlight where its luminance exceeds this multiple of its 8 neighbours' mean:
# then at least two thirds of its light is more than its surroundings give, and no pixel of a
# straight edge, of a corner or of a 2 x 2 block qualifies, however bright
HIGHLIGHT_RATIO = 3.0


def lattice_coordinate(coc_px: Any, near_px: float) -> Any:
    """``w(max(|c|, 1)) - 1`` (px) of each signed CoC ``coc_px`` (a float, a numpy array or a torch
    tensor, the same ops), ``w(c) = c + near_px (1 - 1 / c)``: 0 up to 1 px, then increasing;
    ``|c| - 1`` when ``near_px`` is 0."""
    m = abs(coc_px)
    m = max(m, POINT_PX) if isinstance(m, float | int) else m.clip(min=POINT_PX)
    return m - POINT_PX + near_px * (1.0 - POINT_PX / m) if near_px else m - POINT_PX


def highlight_coc(coc_px: Any) -> Any:
    """The CoC (signed px; a numpy array or a torch tensor, the same ops) whose kernel an isolated
    highlight at ``coc_px`` gets: ``sign(c) sqrt(c^2 + S (1 - c^2 / E^2))`` from 1 px to ``E =
    HIGHLIGHT_SPREAD_END_PX`` (``S = HIGHLIGHT_SPREAD_PX2``), ``c`` from ``E`` on, and below 1 px
    the factor at 1 px (``c`` times 1.41): 0 stays 0, as a point in focus lands in its own pixel
    wherever it is in it, and the network draws any disk under 1 px as that point."""
    c2 = coc_px * coc_px
    grown2 = c2 + HIGHLIGHT_SPREAD_PX2 * (1.0 - c2 / HIGHLIGHT_SPREAD_END_PX**2).clip(min=0.0)
    return coc_px * (grown2 / c2.clip(min=POINT_PX**2)) ** 0.5


def isolated_highlights(rgb: np.ndarray, ratio: float = HIGHLIGHT_RATIO) -> np.ndarray:
    """``(B, H, W)`` bool: the pixels of linear ``rgb`` ``(B, 3, H, W)`` whose luminance (the
    channels' mean, at least 0) exceeds ``ratio`` times their 8 neighbours' mean (the frame mirrored at its
    edges, so an edge pixel is not its own neighbour; repeated on a frame 1 px thin). The numpy
    twin of :func:`neuralbokeh.networks.lens.isolated_highlights`."""
    y = np.asarray(rgb, dtype=np.float32).mean(axis=1)
    np.maximum(y, 0.0, out=y)  # (the normalisation's rounding leaves -1e-9 for black)
    h, w = y.shape[-2:]
    p = np.pad(y, ((0, 0), (1, 1), (1, 1)), mode="reflect" if min(h, w) > 1 else "edge")
    rows = p[:, 0:h] + p[:, 1 : h + 1]  # the 3 x 3 sum, rows then columns (in place: a 1080p frame is 8 MB a pass)
    rows += p[:, 2 : h + 2]
    s9 = rows[..., 0:w] + rows[..., 1 : w + 1]
    s9 += rows[..., 2 : w + 2]
    s9 -= y
    s9 *= np.float32(ratio)
    return y * np.float32(8.0) > s9


def lattice_diameter(coordinate_px: Any, near_px: float) -> np.ndarray:
    """The |CoC| (px) at lattice coordinate ``coordinate_px`` >= 0 (numpy or float): the inverse
    of :func:`lattice_coordinate`, the positive root of ``c^2 + (a - y) c - a = 0``, ``y`` the
    coordinate + 1."""
    y = np.asarray(coordinate_px, dtype=np.float64) + POINT_PX
    b = near_px - y
    return 0.5 * (np.sqrt(b * b + 4.0 * near_px) - b)


def lattice_step(c_train_px: float, blocks: int, near_px: float = 0.0) -> float:
    """The lattice spacing (px of lattice coordinate) that puts ``blocks`` bands over a training
    range whose largest |CoC| is ``c_train_px``: ``d_N = c_train`` (2 px when ``blocks`` is 0)."""
    return lattice_coordinate(float(c_train_px), near_px) / blocks if blocks > 0 else 2.0


def lattice_blocks(max_coc_px: float, near_px: float) -> int:
    """The fewest bands at most 2 px of lattice coordinate apart whose last centre reaches
    ``max_coc_px``: then ``d_n <= 1 + 2n``, and block n's 2n + 1 px kernel holds band n."""
    return max(0, math.ceil(lattice_coordinate(float(max_coc_px), near_px) / 2.0 - 1e-9))


def band_diameters(max_coc_px: float, blocks: int, near_px: float = 0.0) -> np.ndarray:
    """Centres ``d_0 = 0``, ``d_n`` (px) of the CoC bands, ``(N + 1,)``, the last at ``max_coc_px``."""
    step = lattice_coordinate(float(max_coc_px), near_px) / max(blocks, 1)
    return BandPlan(step, blocks, 0, near_px).diameters


class BandPlan(NamedTuple):
    """The bands a frame runs: ``blocks`` bands of the lattice ``w(d_n) = 1 + n step_px`` (px,
    ``w(c) = c + near_px (1 - 1 / c)``), the last centred at ``c_plan_px``; ``fill_radius_px``: how far
    (px) the hidden-background fill looks for occluders."""

    step_px: float
    blocks: int
    fill_radius_px: int
    near_px: float = 0.0

    @classmethod
    def for_frame(cls, coc_px: float, step_px: float, c_train_px: float, near_px: float = 0.0) -> BandPlan:
        """The plan of a frame whose largest |CoC| is ``coc_px``: the fewest bands whose last
        centre reaches it (none up to 1 px); the fill reaches half the trained range's largest
        CoC, or the plan's where that is larger (a frame within the range gets the same fill
        whatever its plan)."""
        n = 0 if coc_px <= POINT_PX or step_px <= 0 else max(1, math.ceil(lattice_coordinate(float(coc_px), near_px) / step_px - 1e-6))
        c_plan = float(lattice_diameter(n * step_px, near_px))
        return cls(float(step_px), int(n), math.ceil(max(c_plan, c_train_px) / 2.0), float(near_px))

    @property
    def c_plan_px(self) -> float:
        return float(lattice_diameter(self.blocks * self.step_px, self.near_px))

    @property
    def diameters(self) -> np.ndarray:
        """``(N + 1,)`` band centres (px), ``d_0 = 0``."""
        d = lattice_diameter(np.arange(self.blocks + 1) * self.step_px, self.near_px)
        d[0] = 0.0
        return d

    def band_step_px(self, n: int) -> float:
        """``d d / d pos`` (px of CoC per band) at band ``n``'s centre: the lattice step in |c|
        there, which scales a kernel's slope in the diameter to one per band (Hermite blend)."""
        d = float(lattice_diameter(n * self.step_px, self.near_px))
        return self.step_px / (1.0 + self.near_px / max(d, POINT_PX) ** 2)

    def position(self, coc_px: Any) -> Any:
        """Continuous band index in ``[0, N]`` of each pixel's signed CoC ``coc_px`` (px; a numpy
        array or a torch tensor, the same ops): 0 up to 1 px, ``n`` at ``d_n``, linear in the
        lattice coordinate in between; beyond ``d_N`` it stays at N."""
        if self.blocks == 0 or self.step_px <= 0:  # every CoC is a point
            return abs(coc_px) * 0.0
        return (lattice_coordinate(coc_px, self.near_px) * (1.0 / self.step_px)).clip(max=float(self.blocks))

    def to_dict(self) -> dict[str, Any]:
        return {"step_px": self.step_px, "blocks": self.blocks, "fill_radius_px": self.fill_radius_px, "near_px": self.near_px}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> BandPlan:
        # files written before the lattice had a near-focus term carry no near_px: uniform
        return cls(float(d["step_px"]), int(d["blocks"]), int(d["fill_radius_px"]), float(d.get("near_px", 0.0)))


def hermite_weights(pos: Any, n: int) -> tuple[Any, Any]:
    """Band ``n``'s (kernel, slope) weights at band positions ``pos`` (a numpy array or a torch
    tensor, the same ops) for the cubic Hermite blend (``model.band_blend = "hermite"``).

    Between centres ``n`` and ``n + 1`` a pixel at ``t = pos - n`` takes ``h00(t) K_n +
    h10(t) K'_n + h01(t) K_{n+1} + h11(t) K'_{n+1}``, ``K'`` the kernel's derivative in the
    diameter times the lattice step. So band ``n`` weighs its kernel by ``(1 - |u|)^2 (1 + 2|u|)``
    and its slope by ``u (1 - |u|)^2``, ``u = pos - n``: non-zero exactly where the hat is, the
    kernel weights of two neighbours summing to 1 (flux kept: a slope sums to 0). Band 0 is a
    point, with no slope, so between it and band 1 both keep the hat.
    """
    u = pos - float(n)
    au = abs(u)
    inside = (1.0 - au).clip(min=0.0)
    value, slope = inside * inside * (1.0 + 2.0 * au), u * inside * inside
    if n == 1:  # towards band 0 (u < 0): the hat, no slope
        left = (u < 0.0) * 1.0
        value, slope = left * inside + (1.0 - left) * value, (1.0 - left) * slope
    return value, slope


def active_bands(coc_px: np.ndarray, plan: BandPlan, layout: TileLayout, tiles: np.ndarray | None = None,
                 points: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """``(tiles, N, 2)`` bool: whether any pixel that tile ``k`` scatters (its core, out to the
    window's edge on image-border sides) has a non-zero gate in band ``n = 1..N`` on side ``s``
    (0 behind the focus plane, 1 in front), in any image of the batch ``coc_px`` ``(B, H, W)``
    (signed px). A superset by 1e-3 of a band at the band edges, where float32 may round the
    network's gate either way. ``tiles`` ``(tiles,)`` bool: only these are looked at (the others
    come back all False), so the work is the area of the tiles that run. ``points``: (rows,
    cols, CoC px) of more sources, each with the tile that scatters its pixel (e.g. isolated
    highlights at their grown CoC, :func:`highlight_coc`)."""
    blocks = plan.blocks
    _, height, width = coc_px.shape
    flags = np.zeros((layout.num_tiles, max(blocks, 1), 2), dtype=bool)
    if blocks == 0:
        return flags
    span = blocks + 2
    owner = layout.source_tile(points[0], points[1]) if points is not None and len(points[2]) else None
    for k in range(layout.num_tiles) if tiles is None else np.flatnonzero(tiles):
        r0, r1, c0, c1 = layout.source_region(int(k), height, width)
        c = np.asarray(coc_px[:, r0:r1, c0:c1], dtype=np.float32).ravel()
        if owner is not None:
            c = np.concatenate([c, np.asarray(points[2][owner == k], dtype=np.float32)])
        pos = plan.position(c)
        # 2 span: scatters nothing beyond band 0 (|c| <= 1 px gives position 0, where every band's
        # hat is 0; 1e-4 px of margin for the model's float32 CoC)
        side = np.where(c < 0, np.int32(span), np.int32(0))
        side[np.abs(c) < POINT_PX - 1e-4] = 2 * span  # (4x faster than a nested np.where at 1080p)
        # bands lo and lo + 1 around each pixel's band position, and one more where it sits within
        # 1e-3 of a band centre: a superset of the non-zero hats
        lo = side + np.floor(np.maximum(pos - 1e-3, 0.0)).astype(np.int32)
        hi = side + np.floor(pos + 1e-3).astype(np.int32) + 1
        seen_lo = np.bincount(lo, minlength=3 * span)
        seen = seen_lo + np.roll(seen_lo, 1) + np.bincount(hi, minlength=3 * span + 1)[: 3 * span]
        flags[k] = (seen[: 2 * span].reshape(2, span)[:, 1 : blocks + 1] > 0).T
    return flags

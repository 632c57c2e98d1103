"""The CoC bands of the lens network, torch-free: the one definition of a frame's plan.

A lens network splits each pixel's |CoC| into bands on a px lattice ``d_n = 1 + n step``
(band 0: ``|c| <= 1`` px, a point). A frame runs the bands up to the first whose centre
reaches its own largest |CoC|. The network (``networks.lens``), the ONNX builder
(``export.lens_graph``) and the runtime (``runtime.onnx_model``, which switches off the bands a
frame's tiles do not use) all read the lattice, the plan and the band of a CoC from here; the
exported file carries its :class:`BandPlan` so that the runtime plans with the same numbers.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from .tiling import TileLayout

# |c| <= POINT_PX is band 0 (in focus: a point); band n >= 1 is centred at POINT_PX + n step
POINT_PX = 1.0


def lattice_step(c_train_px: float, blocks: int) -> float:
    """The lattice spacing (px) that puts ``blocks`` bands over a training range whose largest
    |CoC| is ``c_train_px``: ``d_N = c_train`` (2 px when ``blocks`` is 0)."""
    return (max(c_train_px, POINT_PX) - POINT_PX) / blocks if blocks > 0 else 2.0


def band_diameters(max_coc_px: float, blocks: int) -> np.ndarray:
    """Centres ``d_0 = 0, d_n = 1 + n (max_coc_px - 1) / N`` (px) of the CoC bands, ``(N + 1,)``."""
    d = POINT_PX + np.arange(blocks + 1) * (max(max_coc_px, POINT_PX) - POINT_PX) / max(blocks, 1)
    d[0] = 0.0
    return d


class BandPlan(NamedTuple):
    """The bands a frame runs: ``blocks`` bands of the lattice ``d_n = 1 + n step_px`` (px), the
    last centred at ``c_plan_px``; ``fill_radius_px``: how far (px) the hidden-background fill
    looks for occluders."""

    step_px: float
    blocks: int
    fill_radius_px: int

    @classmethod
    def for_frame(cls, coc_px: float, step_px: float, c_train_px: float) -> BandPlan:
        """The plan of a frame whose largest |CoC| is ``coc_px``: the fewest bands whose last
        centre reaches it (none up to 1 px); the fill reaches half the trained range's largest
        CoC, or the plan's where that is larger (a frame within the range gets the same fill
        whatever its plan)."""
        n = 0 if coc_px <= POINT_PX or step_px <= 0 else max(1, math.ceil((coc_px - POINT_PX) / step_px - 1e-6))
        c_plan = POINT_PX + n * step_px
        return cls(float(step_px), int(n), math.ceil(max(c_plan, c_train_px) / 2.0))

    @property
    def c_plan_px(self) -> float:
        return POINT_PX + self.blocks * self.step_px

    @property
    def diameters(self) -> np.ndarray:
        """``(N + 1,)`` band centres (px), ``d_0 = 0``."""
        return band_diameters(self.c_plan_px, self.blocks)

    def position(self, coc_px: Any) -> Any:
        """Continuous band index in ``[0, N]`` of each pixel's signed CoC ``coc_px`` (px; a numpy
        array or a torch tensor, the same ops): 0 up to 1 px, ``n`` at ``d_n``, linear in
        between; beyond ``d_N`` it stays at N."""
        if self.blocks == 0 or self.step_px <= 0:  # every CoC is a point
            return abs(coc_px) * 0.0
        return ((abs(coc_px) - POINT_PX).clip(min=0.0) * (1.0 / self.step_px)).clip(max=float(self.blocks))

    def to_dict(self) -> dict[str, Any]:
        return {"step_px": self.step_px, "blocks": self.blocks, "fill_radius_px": self.fill_radius_px}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> BandPlan:
        return cls(float(d["step_px"]), int(d["blocks"]), int(d["fill_radius_px"]))


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


def active_bands(coc_px: np.ndarray, plan: BandPlan, layout: TileLayout) -> np.ndarray:
    """``(tiles, N, 2)`` bool: whether any pixel that tile ``k`` scatters (its core, out to the
    window's edge on image-border sides) has a non-zero gate in band ``n = 1..N`` on side ``s``
    (0 behind the focus plane, 1 in front), in any image of the batch ``coc_px`` ``(B, H, W)``
    (signed px). A superset by 1e-3 of a band at the band edges, where float32 may round the
    network's gate either way."""
    blocks = plan.blocks
    _, height, width = coc_px.shape
    flags = np.zeros((layout.num_tiles, max(blocks, 1), 2), dtype=bool)
    if blocks == 0:
        return flags
    c = np.asarray(coc_px, dtype=np.float32)
    pos = plan.position(c)
    span = blocks + 2
    # 2 span: scatters nothing beyond band 0 (|c| <= 1 px gives position 0, where every band's
    # hat is 0; 1e-4 px of margin for the model's float32 CoC)
    point = np.abs(c) < POINT_PX - 1e-4
    side = np.where(c < 0, np.int32(span), np.int32(0))
    side[point] = 2 * span  # (4x faster than a nested np.where at 1080p)
    # bands lo and lo + 1 around each pixel's band position, and one more where it sits within
    # 1e-3 of a band centre: a superset of the non-zero hats
    lo = side + np.floor(np.maximum(pos - 1e-3, 0.0)).astype(np.int32)
    hi = side + np.floor(pos + 1e-3).astype(np.int32) + 1
    for k in range(layout.num_tiles):
        r0, r1, c0, c1 = layout.source_region(k, height, width)
        seen_lo = np.bincount(lo[:, r0:r1, c0:c1].ravel(), minlength=3 * span)
        seen = seen_lo + np.roll(seen_lo, 1) + np.bincount(hi[:, r0:r1, c0:c1].ravel(), minlength=3 * span + 1)[: 3 * span]
        flags[k] = (seen[: 2 * span].reshape(2, span)[:, 1 : blocks + 1] > 0).T
    return flags

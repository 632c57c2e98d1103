"""The default network: the paper's tiled skeleton carrying a learned lens (pure definitions).

Same interface as :class:`neuralbokeh.networks.paper.PaperBokeh` (the paper's network, kept as the
``architecture = "paper"`` ablation): input ``(B, 4, H, W)`` = normalised all-in-focus RGB in
[-1, 1) and the CoC divided by ``coc_scale_px``; output ``(B, 3, H, W)`` normalised RGB.

The skeleton of the paper, given what a lens blur is made of:

1. *Linear light.* The input RGB is decoded to linear HDR (the exact inverse of
   :class:`~neuralbokeh.core.normalization.Normalization`); the output is encoded back, which is the
   head's tanh (the normalisation *is* ``tanh(ln((x + o) / s) / 2)``). A blur is linear in
   linear light: a 1000x highlight spread over a disk stays bright.
2. *Tiles with their own weights, from where they lie on the sensor.* The image is cut into
   ``tile`` px cores with ``overlap`` px of context (as the paper). Each tile has a learned
   *pupil* per colour channel and per side of the focus plane (in front, behind): a
   ``pupil_size``^2 grid of log-transmissions over ``[-1.25, 1.25]^2`` aperture radii, the sum
   of a lens-wide pupil and a field correction interpolated (bilinear) at the tile's sensor
   position from ``field_grid``^2 nodes over the sensor (zero at the start; it learns at
   ``train.field_lr_scale`` x lr, so a part of the field that few training pixels reach cannot
   drift far from what the whole sensor teaches). A tile index means nothing: any frame size,
   and any crop of the sensor (its ``window``), finds its pupils by position. This is where
   the lens is learned: the aperture shape, the cat-eye clipping of that part of the field, a
   bright rim or centre, per-channel differences. A learned per-channel scale of the CoC diameter models longitudinal chromatic
   aberration.
3. *C1: the multiplicative CoC gate.* The signed CoC ``c`` (px) of each pixel is split into
   bands by hat functions of ``|c|``: band 0 is ``|c| <= 1`` px (in focus: a point), band
   ``n`` is centred at ``w(d_n) = 1 + n step`` px, ``w(c) = c + a (1 - 1/c)`` (``a`` =
   ``near_focus_px``, default 4; 0: ``d_n = 1 + n step``), a lattice fixed by the training data
   (``step = (w(max_coc_px) - 1) / N`` for its largest CoC and N blocks, so ``d_n <= 2n + 1``;
   ``a > 0`` makes the bands denser near focus). A frame
   runs the bands up to the first whose centre reaches its own largest |CoC| (:meth:`LensBokeh.plan`, :mod:`neuralbokeh.core.bands`):
   a frame with a third of the range runs a third of the bands, one beyond the trained range
   runs more, with the pupil scaled to their diameters. Features of band ``n`` = (colour x gate, gate), for each side.
   With ``band_blend = "hermite"`` the gates are cubic and each band also scatters (colour x
   slope weight, slope weight) by its kernels' derivative in the diameter
   (:func:`neuralbokeh.core.bands.hermite_weights`): a pixel between two centres then gets
   nearly the kernel at its own CoC, not the linear blend of two. With ``highlight_spread`` an
   isolated highlight (a light smaller than its pixel, at an unknown place in it) takes the
   band of a slightly larger CoC, :func:`neuralbokeh.core.bands.highlight_coc`: the kernel
   blurred by one more pixel box; as a receiver it keeps its own CoC.
4. *Residual blocks R_1..R_N.* Block ``n`` scatters its band with per-channel kernels of size
   ``2n + 1`` (the paper's growing kernels, up to the largest CoC): the tile's pupil rasterised
   (anti-aliased, normalised to sum 1) at diameter ``d_n`` x the channel scale, point-reflected
   in front of the focus plane; with ``pixel_blur`` also filtered by a learned 3-tap blur whose
   variance (px^2) grows from 0 in focus to a plateau, what the frame's pixels add beyond the
   area raster (e.g. a light-field refocus's bilinear shifts). It adds colour and coverage to
   the residual stream of accumulators, in the bucket of each receiving pixel it lands on
   (below). A band that no pixel of a tile uses is not computed at all (exact: its gate is
   zero there).
5. *Occlusion* (near over far, without the layered scatter's trap on continuous surfaces).
   Light arriving at pixel ``p`` is sorted by its band's CoC relative to ``p``'s own CoC into
   *near*, *same surface* and *far* buckets (soft ramps :meth:`LensBokeh.occlusion_margin` wide). Inside a
   bucket light is summed, so neighbouring bands of one sloped surface never occlude each
   other; across buckets it is composited near over same over far with sum-to-saturation
   (light-field patent). Coverage that stays below 1 (where a blurred foreground uncovers what
   it hides in the AIF) is filled with the visible background around the occluder
   (``fill = "background"``, as the reference renderer; ``"normalize"`` divides by the
   coverage instead; ``"far_light"`` first takes the mean colour of the far bucket, the blurred
   light from behind that reaches the pixel, for up to a learned gain times that
   light's own coverage: the amplification is bounded, so a far highlight seen through a sliver
   adds at most the gain times its own light; :meth:`LensBokeh.far_light_gain`). With
   ``surface_fill`` a pixel that hides nothing (not an occluder) fills what is left with the
   mean light of its own depth and behind for a learned share: next to a sharp foreground, what
   a blurred background is short of is more of itself, blurred (:meth:`LensBokeh.surface_filled`).
6. *Reassembly.* Each tile scatters the light of its own core (cores partition the image; at
   the image border a core reaches to its window's edge), into its whole window; windows are
   summed into place (light adds, so a tile's blur crosses into its neighbours' cores exactly as
   far as ``overlap`` allows), then composited once (C2: the buckets to RGB) and encoded (tanh).
   The loss is the MSE of the reassembled image, as in the paper.

Departures from the paper, on purpose: the blocks are residual *accumulators* (each adds the
scatter of its band) rather than a ReLU stack; the per-channel kernels are generated from a
pupil instead of free weights (a prior: one aperture shape scaled by the CoC, measured to train
from little data); overlaps are summed as light rather than averaged. The untrained network
(``pupil_init``: ``disk``, ``gaussian`` or ``aperture``, the data's aperture shape without
vignetting) already is a CoC-driven scatter renderer; training learns the real lens.
"""

from __future__ import annotations

import logging
import math
from typing import Any, NamedTuple

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ..core import checks
from ..core.apertures import Aperture, Disk, Gaussian, aperture_from_dict
from ..core.bands import HIGHLIGHT_RATIO, BandPlan, hermite_weights, highlight_coc, lattice_blocks, lattice_step
from ..core.contract import Contract
from ..core.tiling import TileLayout
from ..ops.fftconv import next_fast_len
from ..ops.holes import hidden_estimate, square_max
from ..ops.tiles import overlap_add, tile
from .config import PIXEL_BLUR_MAX_PX2, SILHOUETTE_PX, SURFACE_FILL_EPS, ModelConfig

log = logging.getLogger(__name__)

PUPIL_EXTENT = 1.25  # the pupil grid covers [-PUPIL_EXTENT, PUPIL_EXTENT]^2 aperture radii
FIELD_DELTA = 0.05  # field units (the sensor's half-width = 1) of the centroid drift's central difference
# the drift is evaluated on a lattice of nodes this far apart (field units) fixed on the sensor and
# interpolated: with a 7-blade cat-eye of 0.6 the reference's brightening changes ~6x between the
# frame's centre and its edge
DRIFT_NODE_SPACING = 0.25
PUPIL_FLOOR = 1e-3  # initial transmission outside the prior's shape (log space cannot hold 0)
SUPERSAMPLE = 4  # the fewest pupil samples per kernel pixel side (anti-aliasing)
_EPS = 1e-8
# the half-width (px of CoC) of the central difference that gives a kernel's slope in the diameter:
# well below a pixel (the rasterisation is piecewise smooth at that scale), well above float32's
# rounding of kernels that sum to 1
SLOPE_DELTA_PX = 0.02
# model.field_flow warps a tile's band only where it moves some light by at least this (px): the
# bilinear resampling smears what it moves by up to 0.25 px^2, more than a smaller shift is worth
# (on the Mitsuba set's clean render, with its own lens: docs/benchmarks.md, "The field flow")
FLOW_MIN_PX = 0.25
# the surface fill's share at the start (model.surface_fill): nearly the surface's own blurred light,
# what the optics says is behind a sharp foreground, with room for the data to say otherwise
SURFACE_FILL_START = 0.95
# the light at the band's centre added to a band's carried source CoCs (model.occlusion_source_coc):
# where a band brings about this little light or less, its mean source CoC is not read from
# rounding noise but leans to the centre
SOURCE_COC_MIN_COVER = 1e-4


def _gate(pos: torch.Tensor, n: int) -> torch.Tensor:
    return (1.0 - (pos - n).abs()).clamp_min(0.0)


def band_gates(coc_px: torch.Tensor, max_coc_px: float, blocks: int) -> torch.Tensor:
    """Hat weights of every band at each pixel: ``(..., N + 1)``, summing to 1, for ``blocks``
    bands up to ``max_coc_px`` px.

    Band 0 takes ``|c| <= 1`` px whole (a point); between band centres the weight is linear in
    ``|c|`` (:meth:`~neuralbokeh.core.bands.BandPlan.position`).
    """
    pos = BandPlan(lattice_step(max_coc_px, blocks), blocks, 0).position(coc_px)
    return torch.stack([_gate(pos, n) for n in range(blocks + 1)], dim=-1)


def coc_slope(coc: torch.Tensor) -> torch.Tensor:
    """How fast a surface's CoC changes, ``(..., H, W)`` -> ``(..., H, W)`` (px of CoC per px, >= 0).

    Each axis' derivative is the one-sided difference of the smaller size, or 0 where the two
    differ in sign (minmod): across a depth edge one of them is the jump and the other the
    surface's own slope, so an edge is not read as a slope (a central difference would be half
    the jump). The first and last columns read no slope across, the first and last rows none
    down: each has one difference only.
    """
    def minmod(d: torch.Tensor, dim: int) -> torch.Tensor:
        # the difference to the previous pixel, and to the next one (0 before the first and after the last)
        before, after = (F.pad(d, p) for p in (((1, 0), (0, 1)) if dim == -1 else ((0, 0, 1, 0), (0, 0, 0, 1))))
        return torch.where(before * after > 0, torch.minimum(before.abs(), after.abs()), torch.zeros_like(before))
    gx = minmod(coc[..., :, 1:] - coc[..., :, :-1], -1)
    gy = minmod(coc[..., 1:, :] - coc[..., :-1, :], -2)
    return torch.sqrt(gx * gx + gy * gy)


def source_coc_ranges(plan: BandPlan) -> dict[int, tuple[float, float]]:
    """``{n: (low, high)}``: the |CoC| (px) of band ``n``'s sources less its centre's. Its hat
    reaches the neighbouring centres; the last band also takes every larger CoC (high = inf)."""
    d = [float(v) for v in plan.diameters]
    return {n: (d[n - 1] - d[n], d[n + 1] - d[n] if n < plan.blocks else math.inf) for n in range(1, plan.blocks + 1)}


def mean_source_coc(band_coc: float, carried: torch.Tensor, cover: torch.Tensor, span: tuple[float, float]) -> torch.Tensor:
    """The mean signed CoC (px) of the sources of a band's light at each receiver ``(M, H, W)``:
    the band's centre ``band_coc`` plus the scattered offsets ``carried`` ``(M, H, W)`` over the
    light's coverage ``cover`` ``(M, H, W)`` (both by the green channel's kernel) plus
    ``SOURCE_COC_MIN_COVER``, within ``span`` (:func:`source_coc_ranges`, in |CoC|). The floor
    weighs the band's centre in as that much light: where the band brings almost none, it is
    the centre's CoC."""
    sign = 1.0 if band_coc > 0 else -1.0
    offset = carried / (cover + SOURCE_COC_MIN_COVER)
    return band_coc + sign * (sign * offset).clamp(*span)


def bucket_weights(band_coc: float | torch.Tensor, receiver_coc: torch.Tensor, margin: float | torch.Tensor) -> torch.Tensor:
    """Soft (near, same, far) weights ``(3, ...)`` of light from a band at signed CoC ``band_coc``
    (its centre, or one per receiver shaped as ``receiver_coc``: the light's mean source CoC,
    :func:`mean_source_coc`) arriving at pixels whose own signed CoC is ``receiver_coc`` (px;
    negative = in front), each ramp ``margin`` px wide (> 0; a scalar tensor when learned, or
    one per receiver, shaped as ``receiver_coc``)."""
    delta = band_coc - receiver_coc  # < 0: the source is nearer than the receiver
    near = ((-delta - margin) / margin).clamp(0.0, 1.0)
    far = ((delta - margin) / margin).clamp(0.0, 1.0)
    return torch.stack([near, 1.0 - near - far, far])


def far_light_fill(hole: torch.Tensor, far_color: torch.Tensor, far_cover: torch.Tensor, background: torch.Tensor,
                   gain: torch.Tensor) -> torch.Tensor:
    """Light for the uncovered part ``hole`` ``(B, 3, H, W)`` of each pixel: the far bucket's
    mean colour ``far_color / far_cover`` (premultiplied colour and coverage, ``(B, 3, H, W)``)
    over ``min(hole, gain * far_cover)``, the visible ``background`` over the rest.

    The far bucket is the blurred light from behind the pixel's surface that reaches it: what
    the views a foreground's blur uncovers see, where the background's pull-push only guesses
    it. Its weight is bounded by its own coverage, so the fill adds at most ``gain`` times the
    far light already there (a far highlight seen through a sliver is not spread over the hole).
    """
    # min(hole, gain * cover) * (colour / cover), written so no term grows as 1 / cover
    return torch.minimum(hole / far_cover.clamp_min(_EPS), gain) * far_color + (hole - torch.minimum(hole, gain * far_cover)) * background


def reduction_matrix(k: int, s: int, dtype: torch.dtype = torch.float64, device: torch.device | None = None) -> torch.Tensor:
    """``(k_s, k)`` weights that bin a ``k``-tap kernel (centred) into taps ``s`` px apart.

    Tap ``J`` of the reduced kernel takes the offsets ``o`` with ``|o - s J| < s / 2`` whole and
    those at exactly ``s / 2`` by half: the reduced kernel keeps the sum, and a point-symmetric
    kernel stays centred (an off-centre one may move by up to ``(s - 1) / 2`` px).
    """
    h = k // 2
    j_max = int(math.floor((h + s / 2) / s))
    o = torch.arange(-h, h + 1, dtype=dtype, device=device)
    centres = s * torch.arange(-j_max, j_max + 1, dtype=dtype, device=device)
    dist = (o[None, :] - centres[:, None]).abs()
    return torch.where(dist < s / 2, 1.0, torch.where(dist == s / 2, 0.5, 0.0)).to(dtype)


def reduce_kernel(kernel: torch.Tensor, s: int) -> torch.Tensor:
    """A kernel ``(..., k, k)`` for a grid ``s`` times coarser: ``(..., k_s, k_s)``, same sum."""
    if s == 1:
        return kernel
    r = reduction_matrix(kernel.shape[-1], s, kernel.dtype, kernel.device)
    return r @ kernel @ r.T


def band_scales(diameters: np.ndarray, min_px: float) -> dict[int, int]:
    """Reduced-resolution factor of each band ``n >= 1``: the largest power of two ``s`` (<= 8)
    that leaves the band's CoC at least ``min_px`` coarse pixels wide (1: full resolution).
    ``min_px <= 0`` gives 1 everywhere (the direct evaluation)."""
    out = {}
    for n in range(1, len(diameters)):
        s = 1
        while min_px > 0 and s < 8 and diameters[n] / (2 * s) >= min_px:
            s *= 2
        out[n] = s
    return out


def supersampling(diameter_px: float, size: int) -> int:
    """Pupil samples per kernel pixel side for a CoC of ``diameter_px`` px on a ``size`` x
    ``size`` pupil grid: at least :data:`SUPERSAMPLE`, and at most one grid step apart.

    A kernel pixel is the mean of the pupil over its footprint. Sampled more sparsely than the
    grid, the (bilinear) samples would skip cells: at a 3 px CoC a 48^2 grid has 12 cells per
    kernel pixel, and 4 samples leave most of them without any gradient, so training writes a
    lattice of dots into the pupil that larger CoCs, which resolve it, then show.
    """
    cells_per_px = 2.0 / (max(diameter_px, _EPS) * pupil_step(size))
    return max(SUPERSAMPLE, math.ceil(cells_per_px))


def raster_weights(k: int, ss: int, radius_px: torch.Tensor, size: int, dtype: torch.dtype = torch.float32,
                   device: torch.device | None = None) -> torch.Tensor:
    """``(C, k, size)``: the weight of each of a ``size``-sample pupil axis in each of ``k`` kernel
    pixels (centred) for a pupil of radius ``radius_px`` ``(C,)`` px: the mean over ``ss``
    points per pixel of the linear interpolation between pupil samples (zero beyond the grid)."""
    offs = (torch.arange(ss, dtype=dtype, device=device) + 0.5) / ss - 0.5
    h = k // 2
    pos = (torch.arange(-h, h + 1, dtype=dtype, device=device)[:, None] + offs).reshape(-1)  # (k ss,) px
    at = (pos[None, :] / radius_px.to(dtype)[:, None] / PUPIL_EXTENT + 1.0) * (0.5 * (size - 1))  # (C, k ss) in samples
    hat = (1.0 - (at[..., None] - torch.arange(size, dtype=dtype, device=device)).abs()).clamp_min(0.0)  # (C, k ss, size)
    return hat.unflatten(1, (k, ss)).mean(dim=2)


def pixel_blur_matrix(k: int, variance_px2: torch.Tensor) -> torch.Tensor:
    """``(k, k)``: the 3-tap filter ``[v / 2, 1 - v, v / 2]`` (variance ``v`` px^2, a scalar
    tensor; negative sharpens) along one kernel axis, cut at the kernel's edge (the kernel is
    normalised afterwards)."""
    eye = torch.eye(k, dtype=variance_px2.dtype, device=variance_px2.device)
    side = torch.diag(torch.ones(k - 1, dtype=variance_px2.dtype, device=variance_px2.device), 1)
    return eye * (1.0 - variance_px2) + (side + side.T) * (0.5 * variance_px2)


def prior_transmission(shape: Aperture, size: int) -> np.ndarray:
    """The shape's transmission on the pupil grid, ``(size, size)``, row 0 at the top (v up)."""
    axis = np.linspace(-PUPIL_EXTENT, PUPIL_EXTENT, size)
    s = 4
    offs = ((np.arange(s) + 0.5) / s - 0.5) * (axis[1] - axis[0])
    u = (axis[:, None] + offs[None, :]).reshape(-1)
    t = shape.transmission(u[None, :], -u[:, None])  # rows: v goes down the rows
    return t.reshape(size, s, size, s).mean(axis=(1, 3))


def _prior_shape(cfg: Any, aperture: dict | None) -> Aperture:
    if cfg.pupil_init == "disk":
        return Disk()
    if cfg.pupil_init == "gaussian":
        return Gaussian(0.5)
    if not aperture:
        raise ValueError("pupil_init = 'aperture' needs the data's aperture (the contract's aperture), got none")
    return aperture_from_dict(aperture["shape"])


def _on_grid(feats: torch.Tensor, s: int, flow: torch.Tensor | None) -> torch.Tensor:
    """``feats`` ``(M, C, win, win)`` box-averaged onto a grid ``s`` times coarser (padded to a
    multiple of ``s``; unchanged when ``s = 1``), then moved by ``flow`` ``(M, 2, win, win)`` px
    (:func:`_flow_where_it_moves`; box-averaged as the features, in coarse px), or not (None)."""
    win = feats.shape[-1]
    moves = None if flow is None else flow.abs().flatten(1).amax(dim=1) >= FLOW_MIN_PX
    if s > 1:
        size = -(-win // s) * s
        feats = F.avg_pool2d(F.pad(feats, (0, size - win, 0, size - win)), s)
        if moves is not None and bool(moves.any()):
            flow = F.avg_pool2d(F.pad(flow, (0, size - win, 0, size - win)), s) / s
    return feats if moves is None else _flow_where_it_moves(feats, flow, moves)


def _off_grid(out: torch.Tensor, s: int, win: int) -> torch.Tensor:
    """A grid ``s`` times coarser ``(M, C, n, n)`` back to the window's ``(M, C, win, win)`` (bilinear, half-pixel)."""
    if s == 1:
        return out
    return F.interpolate(out, scale_factor=s, mode="bilinear", align_corners=False)[..., :win, :win]


def _scatter(feats: torch.Tensor, kern: torch.Tensor, which: torch.Tensor, s: int, extra: list[torch.Tensor] | tuple = (),
             flow: torch.Tensor | None = None) -> torch.Tensor:
    """(colour x gate, gate) ``(M, 4, win, win)`` scattered by the kernels ``kern[which]``
    (``(tiles, 3, k, k)``): ``(M, 6, win, win)`` (colour, per-channel coverage), 'same' size,
    on a grid ``s`` times coarser when ``s > 1``. Each further kernel of ``extra`` (shaped as
    ``kern``: the Hermite blend's slope, the field gradient's x and y) scatters the next 4
    channels of ``feats`` ``(M, 4 + 4 len(extra), win, win)``, added. ``flow`` ``(M, 2, win,
    win)`` px (``model.field_flow``): the features are first moved by it (:func:`_on_grid`)."""
    win = feats.shape[-1]
    feats = _on_grid(feats, s, flow)
    kern, extra = reduce_kernel(kern, s), [reduce_kernel(e, s) for e in extra]
    k, n = kern.shape[-1], feats.shape[-1]
    fs = next_fast_len(n + k - 1)
    fx = torch.fft.rfft2(feats, s=(fs, fs))
    prod = 0
    for i, kn in enumerate([kern, *extra]):
        fk = torch.fft.rfft2(kn, s=(fs, fs))[which]  # (M, 3, ...) per tile
        prod = prod + torch.cat([fx[:, 4 * i : 4 * i + 3] * fk, fx[:, 4 * i + 3 : 4 * i + 4] * fk], dim=1)  # (M, 6, ...)
    out = torch.fft.irfft2(prod, s=(fs, fs))[..., k // 2 : k // 2 + n, k // 2 : k // 2 + n]  # 'same'
    return _off_grid(out, s, win)


def _carried_coc(pair: torch.Tensor, kern: torch.Tensor, which: torch.Tensor, s: int, band_coc: float,
                 span: tuple[float, float], flow: torch.Tensor | None = None) -> torch.Tensor:
    """The mean signed CoC (px) of a band's sources at each receiver ``(M, win, win)``
    (``model.occlusion_source_coc``): (gate x (source CoC - ``band_coc``), gate) ``pair`` ``(M, 2, win, win)``
    scattered by the green channel's kernels ``kern[which]`` (``(tiles, 1, k, k)``, full
    resolution) on a grid ``s`` times coarser, moved as :func:`_scatter`'s features; there
    :func:`mean_source_coc` of the band at ``band_coc`` (px) within ``span``, brought back to the
    window bilinearly. A mean over a kernel's reach changes little within a coarse pixel."""
    win = pair.shape[-1]
    x = _on_grid(pair, s, flow)
    kern = reduce_kernel(kern, s)
    k, n = kern.shape[-1], x.shape[-1]
    fs = next_fast_len(n + k - 1)
    prod = torch.fft.rfft2(x, s=(fs, fs)) * torch.fft.rfft2(kern, s=(fs, fs))[which]
    out = torch.fft.irfft2(prod, s=(fs, fs))[..., k // 2 : k // 2 + n, k // 2 : k // 2 + n]  # 'same'
    mean = mean_source_coc(band_coc, out[:, 0], out[:, 1], span)
    return _off_grid(mean.unsqueeze(1), s, win)[:, 0]


def flow_warp(feats: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """``feats`` ``(M, C, h, w)`` sampled at ``p - flow(p)`` (bilinear; the window's edge
    repeated beyond it), ``flow`` ``(M, 2, h, w)`` in px (x right, y down): to first order,
    the light of each source pixel moved by the flow at its destination. A backward warp does not
    scale what it moves; the drift's colour gain (:meth:`LensBokeh.colour_gains`) is its Jacobian."""
    _, _, h, w = feats.shape
    xs = (torch.arange(w, device=feats.device, dtype=feats.dtype) * 2.0 + 1.0) / w - 1.0  # pixel centres, align_corners=False
    ys = (torch.arange(h, device=feats.device, dtype=feats.dtype) * 2.0 + 1.0) / h - 1.0
    grid = torch.stack([xs[None, None, :] - flow[:, 0] * (2.0 / w), ys[None, :, None] - flow[:, 1] * (2.0 / h)], dim=-1)
    return F.grid_sample(feats, grid, mode="bilinear", padding_mode="border", align_corners=False)


def _flow_where_it_moves(feats: torch.Tensor, flow: torch.Tensor, moves: torch.Tensor) -> torch.Tensor:
    """:func:`flow_warp` of the windows of ``feats`` ``(M, C, h, w)`` where ``moves`` ``(M,)``
    (their light moves by at least ``FLOW_MIN_PX`` somewhere), by ``flow`` ``(M, 2, h, w)``; the
    others unchanged."""
    if bool(moves.all()):
        return flow_warp(feats, flow)
    if not bool(moves.any()):
        return feats
    feats = feats.clone()
    feats[moves] = flow_warp(feats[moves], flow[moves])
    return feats


def _in_focus_light(rgb: torch.Tensor, pos: torch.Tensor, src: torch.Tensor, active: torch.Tensor) -> torch.Tensor:
    """The accumulators ``(B, T, 3, 6, win, win)`` before any band is scattered: band 0 (in
    focus, a point) lands where it is, in the receiver's own bucket; an inactive tile's whole
    core passes as in-focus light. ``rgb`` ``(B, T, 3, win, win)`` linear, ``pos`` the band
    positions ``(B, T, win, win)``, ``src`` the cores ``(1, T, 1, win, win)``, ``active`` ``(T,)``."""
    g0 = _gate(pos, 0).unsqueeze(2) * src  # (B, T, 1, win, win)
    same = torch.cat([rgb * g0, g0.expand(-1, -1, 3, -1, -1)], dim=2)
    if not bool(active.all()):
        keep = (~active).view(1, -1, 1, 1, 1).to(rgb.dtype)
        passthrough = torch.cat([rgb * src, src.expand(rgb.shape[0], -1, 3, -1, -1)], dim=2)
        same = keep * passthrough + (1.0 - keep) * same
    zeros = torch.zeros_like(same)
    return torch.stack([zeros, same, zeros], dim=2)


def isolated_highlights(rgb: torch.Tensor) -> torch.Tensor:
    """``(B, 1, H, W)`` bool: the pixels of linear ``rgb`` ``(B, 3, H, W)`` whose luminance (the
    channels' mean, at least 0) exceeds ``HIGHLIGHT_RATIO`` times their 8 neighbours' mean (the frame mirrored
    at its edges; the same sums in the same order as :func:`neuralbokeh.core.bands.isolated_highlights`)."""
    y = rgb.mean(dim=1, keepdim=True).clamp_min(0.0)  # (the normalisation's rounding leaves -1e-9 for black)
    h, w = y.shape[-2:]
    p = F.pad(y, (1, 1, 1, 1), mode="reflect" if min(h, w) > 1 else "replicate")
    rows = p[..., 0:h, :] + p[..., 1 : h + 1, :] + p[..., 2 : h + 2, :]  # the 3 x 3 sum, rows then columns
    s9 = rows[..., 0:w] + rows[..., 1 : w + 1] + rows[..., 2 : w + 2]
    return y * 8.0 > HIGHLIGHT_RATIO * (s9 - y)


def source_coc_px(rgb: torch.Tensor, coc_px: torch.Tensor) -> torch.Tensor:
    """The CoC (signed px) ``(B, 1, H, W)`` whose kernel each source pixel gets: its own, or at an
    isolated highlight of linear ``rgb`` ``(B, 3, H, W)`` :func:`~neuralbokeh.core.bands.highlight_coc`'s
    (``model.highlight_spread``). A frame-wide map: a highlight is found among its neighbours
    whichever tile they fall in."""
    return torch.where(isolated_highlights(rgb), highlight_coc(coc_px), coc_px)


def overlap_for(max_coc_px: float) -> int:
    """The tile overlap (px) that holds the blur of a ``max_coc_px`` CoC: its radius, with 10 %
    of room for a learned channel scale."""
    return math.ceil(0.5 * max_coc_px * 1.1)


def pupil_step(size: int) -> float:
    """The spacing (aperture radii) of a ``size`` x ``size`` pupil grid's samples."""
    return 2.0 * PUPIL_EXTENT / (size - 1)


def vignette_log_mask(pos: torch.Tensor, vignette: torch.Tensor, size: int) -> torch.Tensor:
    """Log-transmission ``(B, T, size, size)`` of the cat-eye's clipping circle on the pupil grid
    at the field positions ``pos`` ``(B, T, 2)`` (x, y in [-1, 1] over the sensor).

    Mechanical vignetting: the lens barrel's image, a circle of radius ``exp(vignette[2])``
    aperture radii (a little over 1 at the start), moves towards the image centre by
    ``vignette[:2]`` (x, y) radii per unit of field (two factors: the sensor's aspect ratio is
    not known), so light passes where the pupil and the circle overlap. Its edge is soft over one grid step so that it learns."""
    axis = torch.linspace(-PUPIL_EXTENT, PUPIL_EXTENT, size, dtype=pos.dtype, device=pos.device)
    centre = -vignette[:2] * pos  # (B, T, 2) in aperture radii; grid columns: x right, rows: y down
    du = axis[None, None, None, :] - centre[..., 0, None, None]
    dv = axis[None, None, :, None] - centre[..., 1, None, None]
    r = torch.sqrt(du * du + dv * dv + _EPS)
    return -F.softplus((r - torch.exp(vignette[2])) / pupil_step(size))  # = log sigmoid((radius - r) / step)


def tile_centres_px(layout: TileLayout, height: int, width: int) -> np.ndarray:
    """``(tiles, 2)``: the centre (x, y; px from the frame's top-left corner) of each tile's core
    in a ``height x width`` frame, where its pupils are taken."""
    regions = [layout.source_region(k, height, width) for k in range(layout.num_tiles)]
    return np.array([(0.5 * (c0 + c1), 0.5 * (r0 + r1)) for r0, r1, c0, c1 in regions], dtype=np.float64)


def window_offsets_px(layout: TileLayout, height: int, width: int) -> np.ndarray:
    """``(tiles, 2)``: the top-left corner of each tile's window less its core's centre
    (:func:`tile_centres_px`; x, y px) in a ``height x width`` frame: window pixel ``(i, j)``'s
    centre lies ``(j + 0.5, i + 0.5)`` px from the corner, beyond the frame too (its padding)."""
    top, _, left, _ = layout.pads(height, width)
    corners = np.array([(c - left, r - top) for _, r, c in layout.origins()], dtype=np.float64)
    return corners - tile_centres_px(layout, height, width)


def field_positions(layout: TileLayout, height: int, width: int, window: torch.Tensor) -> torch.Tensor:
    """The sensor position of each tile's core centre, ``(B, tiles, 2)`` as ``(x, y)`` in [-1, 1]
    (the whole sensor's left/top edge at -1), for images of ``height x width`` px lying on the
    sensor windows ``window`` ``(B, 4)`` = (left, top, width, height) in fractions of the sensor."""
    c = torch.tensor(tile_centres_px(layout, height, width) / [width, height], dtype=window.dtype, device=window.device)
    x = window[:, None, 0] + window[:, None, 2] * c[None, :, 0]
    y = window[:, None, 1] + window[:, None, 3] * c[None, :, 1]
    return torch.stack([x, y], dim=-1) * 2.0 - 1.0


def field_weights(pos: torch.Tensor, g: int) -> torch.Tensor:
    """``(N, g^2)`` bilinear weights of a ``g x g`` grid of nodes over the sensor (row-major, rows
    y) at the positions ``pos`` ``(N, 2)`` (x, y in [-1, 1]; beyond the sensor, its edge's nodes)."""
    if g == 1:
        return pos.new_ones(pos.shape[0], 1)
    u = ((pos.clamp(-1.0, 1.0) + 1.0) * (0.5 * (g - 1)))  # (N, 2) in node units
    i0 = u.detach().floor().clamp(max=g - 2).long()
    f = u - i0.to(u.dtype)
    wx = torch.stack([1.0 - f[:, 0], f[:, 0]], -1)  # (N, 2)
    wy = torch.stack([1.0 - f[:, 1], f[:, 1]], -1)
    w = pos.new_zeros(pos.shape[0], g, g)
    rows = torch.arange(pos.shape[0], device=pos.device)
    for dy in range(2):
        for dx in range(2):
            w = w.index_put((rows, i0[:, 1] + dy, i0[:, 0] + dx), wy[:, dy] * wx[:, dx], accumulate=True)
    return w.flatten(1)


def _neighbour_steps(device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """``(4, 2)``: ``FIELD_DELTA`` field units right, left, down and up, the central differences'
    steps of the drift and of the field gradient."""
    return FIELD_DELTA * torch.tensor([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]], device=device, dtype=dtype)


def pupil_centroids(pupils: torch.Tensor) -> torch.Tensor:
    """``(..., 2)``: the centroid (x right, y down; aperture radii) of the transmission of each
    log-pupil ``(..., P, P)``: where a kernel's light lands on average, in radii of its CoC."""
    t = torch.exp(pupils)
    axis = torch.linspace(-PUPIL_EXTENT, PUPIL_EXTENT, t.shape[-1], dtype=t.dtype, device=t.device)
    total = t.sum(dim=(-2, -1)).clamp_min(_EPS)
    return torch.stack([(t.sum(-2) * axis).sum(-1) / total, (t.sum(-1) * axis).sum(-1) / total], dim=-1)


class FieldParts(NamedTuple):
    """:meth:`LensBokeh.field_parts`: a frame's tiles' pupils ``(B T, 2, 3, P, P)`` (log), the
    centroid drift ``(B T, 2, 3, win, win)`` (None where the pupils do not vary), the field flow's
    centroid offsets ``(B T, 2, 2, win, win)`` (``model.field_flow``), and for
    ``model.field_gradient`` :meth:`LensBokeh.neighbour_pupils` ``(4, B T, ...)``, field units
    per px ``(B T, 2)`` and :meth:`LensBokeh.tile_offsets_px` ``(T, 2, win, win)``."""

    pupils: torch.Tensor
    drift: torch.Tensor | None = None
    offsets: torch.Tensor | None = None
    neighbours: torch.Tensor | None = None
    per_px: torch.Tensor | None = None
    pixel_offsets: torch.Tensor | None = None


class LensBokeh(nn.Module):
    """The default network (see the module doc). Built from a :class:`~neuralbokeh.networks.ModelConfig`.

    It renders any image size and any window of the sensor: the tile grid is laid over each
    frame, each tile's pupil is the lens-wide pupil plus a correction interpolated from a
    ``field_grid``^2 grid over the sensor at the tile's position, and the CoC bands lie on a
    fixed lattice ``w(d_n) = 1 + n step`` (px; ``step`` from the training data's CoC range and N),
    of which a frame uses the bands its own largest |CoC| reaches, beyond the trained range too
    (the pupil is scaled: it is defined in aperture radii).
    """

    def __init__(self, config: ModelConfig, contract: Contract) -> None:
        super().__init__()
        config.check_resolved()
        self.config, self.contract = config, contract
        cfg = config
        c_train = max(float(contract.coc_scale_px), 1.0)
        # the band lattice: N bands over the training range (d_N = c_train, d_n <= 2n + 1)
        self.near_px = float(cfg.near_focus_px)
        self.step_px = lattice_step(c_train, cfg.blocks, self.near_px)
        if self.step_px > 2.0 + 1e-9:  # d_n <= 1 + n step would outgrow block n's 2n + 1 px kernel
            need = lattice_blocks(c_train, self.near_px)
            raise ValueError(f"a CoC scale of {c_train:g} px over {cfg.blocks} blocks puts the bands {self.step_px:.3g} px of lattice "
                             f"coordinate apart, wider than block n's 2n + 1 px kernel allows: use at least {need} blocks "
                             f"(model.blocks = 'auto'), a smaller CoC scale"
                             + (" or model.near_focus_px = 0 (a lattice uniform in the CoC)" if self.near_px else ""))
        prior = prior_transmission(_prior_shape(cfg, contract.aperture), cfg.pupil_size)
        logits = np.log(np.maximum(prior, PUPIL_FLOOR))
        # log-transmissions (side [behind, in front], channel, P, P): one lens-wide pupil, plus a
        # field-dependent correction (cat-eye clipping, field aberrations) on a grid of nodes over
        # the sensor, zero at the start
        init = np.broadcast_to(logits, (2, 3, cfg.pupil_size, cfg.pupil_size)).copy()
        self.pupil_shared = nn.Parameter(torch.from_numpy(init).float())
        g = cfg.field_grid
        self.pupil_field = nn.Parameter(torch.zeros(g, g, 2, 3, cfg.pupil_size, cfg.pupil_size))
        self.log_channel_scale = nn.Parameter(torch.zeros(3))
        # cat-eye: (shift along the sensor's x and y per unit of field, log radius), aperture radii
        # clipping nothing on the axis at the start: the circle 3 grid steps outside the aperture's rim
        rim = 1.0 + 3.0 * pupil_step(cfg.pupil_size)
        self.vignette = nn.Parameter(torch.tensor([0.0, 0.0, math.log(rim)])) if cfg.vignetting else None
        # how much of a hole the far light fills, in units of its own coverage: softplus of this
        # (1 at the start), never stuck at a bound as a clamped gain would be once below it
        self.fill_gain = nn.Parameter(torch.tensor([math.log(math.expm1(1.0))])) if cfg.fill == "far_light" else None
        # logit of the share of a visible pixel's hole that its own surface's blurred light fills
        surface = cfg.surface_fill and cfg.fill != "normalize"
        self.surface_fill = nn.Parameter(torch.tensor([math.log(SURFACE_FILL_START / (1.0 - SURFACE_FILL_START))])) if surface else None
        # log of the factor on the buckets' occlusion margin (1 at the start)
        self.margin_scale = nn.Parameter(torch.zeros(1)) if cfg.occlusion_margin_learned else None
        # (atanh of v_inf / its bound, log d_v / 1 px): the area raster exactly at v_inf = 0, with a gradient there
        self.pixel_blur = nn.Parameter(torch.tensor([math.atanh(cfg.pixel_blur_px2 / PIXEL_BLUR_MAX_PX2), 0.0])) if cfg.pixel_blur else None
        self._masks: dict[tuple[int, ...], torch.Tensor] = {}
        reach = overlap_for(c_train)
        if cfg.tiling == "overlap" and cfg.overlap < reach:
            log.warning("tile overlap %d px is below the largest CoC radius (~%d px): light that a tile's blur would "
                        "carry beyond its window is lost (raise model.overlap)", cfg.overlap, reach)

    def parameter_roles(self) -> dict[str, list[nn.Parameter]]:
        """The parameters by how training scales their learning rate: ``"field"`` (the
        field-dependent pupil corrections) and ``"other"`` (the lens-wide pupil, channel scales)."""
        return {"field": [self.pupil_field], "other": [p for p in self.parameters() if p is not self.pupil_field]}

    # -- the frame's plan ---------------------------------------------------------------------
    def layout(self, height: int, width: int) -> TileLayout:
        """The tile grid over an ``height x width`` frame."""
        return self.config.layout(height, width)

    def plan(self, coc_px: float) -> BandPlan:
        """The plan of a frame whose largest |CoC| is ``coc_px`` (px): its bands on the lattice
        and the reach of its fill (:meth:`~neuralbokeh.core.bands.BandPlan.for_frame`)."""
        return BandPlan.for_frame(coc_px, self.step_px, float(self.contract.coc_scale_px), self.near_px)

    def source_masks(self, layout: TileLayout, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
        """``(tiles, 1, win, win)``: 1 on the pixels whose light a tile scatters."""
        key = tuple(layout)
        if key not in self._masks:
            self._masks[key] = torch.from_numpy(layout.source_masks())[:, None]
        return self._masks[key].to(device=device, dtype=dtype)

    # -- kernels ---------------------------------------------------------------------------
    def kernel_size(self, n: int) -> int:
        return self.config.kernel_size(n)

    def tile_pupils(self, layout: TileLayout, height: int, width: int, window: torch.Tensor | None = None,
                    batch: int = 1) -> torch.Tensor:
        """Log-transmissions of each image's tiles' pupils ``(B, tiles, 2, 3, P, P)`` for frames of
        ``height x width`` px on the sensor ``window`` ``(B, 4)`` (default: the whole sensor)."""
        device, dtype = self.pupil_shared.device, self.pupil_shared.dtype
        if window is None:
            window = torch.tensor([[0.0, 0.0, 1.0, 1.0]], device=device, dtype=dtype)
        if window.ndim != 2 or window.shape[1] != 4 or window.shape[0] not in (1, batch):
            raise ValueError(f"window must have shape ({batch}, 4) or (1, 4): (left, top, width, height), got {tuple(window.shape)}")
        window = window.expand(batch, 4)
        return self.pupils_at(field_positions(layout, height, width, window.to(device=device, dtype=dtype)))

    def neighbour_pupils(self, layout: TileLayout, height: int, width: int, window: torch.Tensor | None = None,
                         batch: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
        """For ``model.field_gradient``: the pupils ``FIELD_DELTA`` field units right of, left of,
        below and above each tile's centre, ``(4, B T, 2, 3, P, P)`` (log), and the field units
        per px of each tile's frame ``(B T, 2)`` (x, y), as :meth:`tile_pupils` lays them."""
        device, dtype = self.pupil_shared.device, self.pupil_shared.dtype
        if window is None:
            window = torch.tensor([[0.0, 0.0, 1.0, 1.0]], device=device, dtype=dtype)
        window = window.to(device=device, dtype=dtype).expand(batch, 4)
        pos = field_positions(layout, height, width, window)  # (B, T, 2)
        steps = _neighbour_steps(device, dtype)
        pupils = self.pupils_at((pos[None] + steps[:, None, None]).flatten(0, 1))  # (4 B, T, 2, 3, P, P)
        per_px = 2.0 * window[:, 2:] / torch.tensor([float(width), float(height)], device=device, dtype=dtype)  # (B, 2)
        return pupils.unflatten(0, (4, batch)).flatten(1, 2), per_px.repeat_interleave(layout.num_tiles, dim=0)

    def kernel_gradients(self, n: int, neighbours: torch.Tensor, diameter: float, per_px: torch.Tensor) -> torch.Tensor:
        """Band ``n``'s kernels' derivative in the source pixel's position (per px, x and y),
        ``(M, 2, 2, 3, k, k)`` (axis, side, channel): a central difference of the kernels of
        :meth:`neighbour_pupils` ``(4, M, ...)`` at CoC ``diameter`` (px), ``per_px`` ``(M, 2)``
        field units per px. Each sums to 0 (every kernel sums to 1), so a point keeps its light;
        on a plane their first moment brightens where the blur's centroid converges: to first
        order :meth:`colour_gains` at the receiving pixel, which the scattered coverage is divided
        by (an opaque plane covers every pixel fully however its light flows)."""
        m = neighbours.shape[1]
        k4 = self.kernels(n, neighbours.flatten(0, 1), diameter, self._supersampling(diameter)).unflatten(0, (4, m))
        scale = per_px / (2.0 * FIELD_DELTA)  # (M, 2)
        return torch.stack([(k4[0] - k4[1]) * scale[:, 0, None, None, None, None],
                            (k4[2] - k4[3]) * scale[:, 1, None, None, None, None]], dim=1)

    def tile_offsets_px(self, layout: TileLayout, height: int, width: int, device: torch.device,
                        dtype: torch.dtype) -> torch.Tensor:
        """``(T, 2, win, win)``: each window pixel's centre less its tile's core centre (px, x and
        y; :func:`window_offsets_px`), where :meth:`tile_pupils` places the tile's pupils."""
        win = layout.window
        ramp = torch.arange(win, device=device, dtype=dtype) + 0.5
        corner = torch.tensor(window_offsets_px(layout, height, width), device=device, dtype=dtype)  # (T, 2)
        x = (ramp[None, :] + corner[:, :1])[:, None, :].expand(-1, win, -1)
        y = (ramp[None, :] + corner[:, 1:])[:, :, None].expand(-1, -1, win)
        return torch.stack([x, y], dim=1)

    def _field_lattice(self, height: int, width: int, window: torch.Tensor | None,
                       batch: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The lattice of :meth:`drift_lattice` that a ``height x width`` frame on the sensor
        ``window`` ``(B, 4)`` reaches: ``(node positions (1, Gy Gx, 2) in field units, rows
        (B, H, Gy), cols (B, W, Gx), field units per px (B, 2), (Gy, Gx))``."""
        device, dtype = self.pupil_shared.device, self.pupil_shared.dtype
        if window is None:
            window = torch.tensor([[0.0, 0.0, 1.0, 1.0]], device=device, dtype=dtype)
        window = window.to(device=device, dtype=dtype).expand(batch, 4)
        per_px = 2.0 * window[:, 2:] / torch.tensor([float(width), float(height)], device=device, dtype=dtype)  # field / px
        nodes, weights = [], []
        for i, size in enumerate((width, height)):
            field = (window[:, i, None] * 2.0 - 1.0 + (torch.arange(size, device=device, dtype=dtype) + 0.5)
                     * per_px[:, i, None]).clamp(-1.0, 1.0)  # (B, size): each pixel centre on the sensor
            lo = math.floor((float(field.min()) + 1.0) / DRIFT_NODE_SPACING + 1e-9)
            hi = math.ceil((float(field.max()) + 1.0) / DRIFT_NODE_SPACING - 1e-9)
            at = torch.arange(lo, max(hi, lo) + 1, device=device, dtype=dtype) * DRIFT_NODE_SPACING - 1.0  # (G,) field
            nodes.append(at)
            weights.append((1.0 - (field[..., None] - at).abs() / DRIFT_NODE_SPACING).clamp_min(0.0))  # (B, size, G)
        (nx, ny), (cols, rows) = nodes, weights
        pos = torch.stack(torch.broadcast_tensors(nx[None, :], ny[:, None]), dim=-1).reshape(1, -1, 2)  # (1, Gy Gx, 2)
        return pos, rows, cols, per_px, (len(ny), len(nx))

    def drift_lattice(self, height: int, width: int, window: torch.Tensor | None = None,
                      batch: int = 1) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The divergence of the pupils' centroid across the frame, ``d mu_x / d col + d mu_y / d
        row`` in aperture radii per px (side, channel), on the nodes of a lattice fixed on the
        sensor (``DRIFT_NODE_SPACING`` field units apart) that a ``height x width`` frame on the
        sensor ``window`` ``(B, 4)`` reaches, and each pixel's weights on them:
        ``(nodes (B, 2, 3, Gy, Gx), rows (B, H, Gy), cols (B, W, Gx))``; the drift at pixel (i, j)
        is ``sum rows[i, y] nodes[.., y, x] cols[j, x]`` (bilinear), the same wherever the frame's
        window lies, so a crop gets the drift the whole frame has there.

        Where the pupil changes over the field (a cat-eye), a blur's centroid drifts by its radius
        times :func:`pupil_centroids`, so defocused light flows across the frame: a plane of one
        colour comes out brighter where the flow converges. A tile's pupil is constant over the
        tile; this slope at every pixel (:meth:`drift_map`) gives back the flow's first-order
        effect (:meth:`colour_gains`)."""
        pos, rows, cols, per_px, (gy, gx) = self._field_lattice(height, width, window, batch)
        device, dtype = pos.device, pos.dtype
        steps = _neighbour_steps(device, dtype)
        # the four neighbours of every node in one evaluation: (4, nodes, 2, 3, 2)
        mu = pupil_centroids(self.pupils_at(pos + steps[:, None])).reshape(4, -1, 2, 3, 2)
        slope_x = (mu[0, ..., 0] - mu[1, ..., 0]) / (2.0 * FIELD_DELTA)  # (nodes, 2, 3) per field unit
        slope_y = (mu[2, ..., 1] - mu[3, ..., 1]) / (2.0 * FIELD_DELTA)
        div = slope_x * per_px[:, 0, None, None, None] + slope_y * per_px[:, 1, None, None, None]  # (B, nodes, 2, 3)
        return div.unflatten(1, (gy, gx)).permute(0, 3, 4, 1, 2), rows, cols

    def centroid_lattice(self, height: int, width: int, window: torch.Tensor | None = None,
                         batch: int = 1) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The pupils' centroid (:func:`pupil_centroids`, the channels' mean; aperture radii) on
        :meth:`drift_lattice`'s nodes: ``(nodes (2, 2, Gy, Gx) as (side, x / y), rows (B, H, Gy),
        cols (B, W, Gx))``; bilinear in between, as the drift."""
        pos, rows, cols, _, (gy, gx) = self._field_lattice(height, width, window, batch)
        mu = pupil_centroids(self.pupils_at(pos))[0].mean(dim=2)  # (nodes, 2, 2)
        return mu.unflatten(0, (gy, gx)).permute(2, 3, 0, 1), rows, cols

    def centroid_offsets(self, layout: TileLayout, pupils: torch.Tensor, height: int, width: int,
                         window: torch.Tensor | None = None, batch: int = 1) -> torch.Tensor:
        """``(B T, 2, 2, win, win)`` (side, x / y): how far (aperture radii) each window pixel's
        own pupil centroid (:meth:`centroid_lattice`) lies from its tile's, whose pupils are
        ``pupils`` ``(B T, 2, 3, P, P)``: :func:`flow_warp`'s flow in units of the CoC radius."""
        nodes, rows, cols = self.centroid_lattice(height, width, window, batch)
        at = torch.einsum("bhy,scyx,bwx->bschw", rows, nodes, cols).flatten(1, 2)  # (B, 4, H, W)
        win = layout.window
        at = tile(at, layout).view(-1, layout.num_tiles, 2, 2, win, win).flatten(0, 1)
        centre = pupil_centroids(pupils).mean(dim=2)  # (B T, 2, 2)
        return at - centre[..., None, None]

    def drift_map(self, height: int, width: int, window: torch.Tensor | None = None, batch: int = 1) -> torch.Tensor:
        """``(B, 2, 3, H, W)``: :meth:`drift_lattice` at every pixel."""
        nodes, rows, cols = self.drift_lattice(height, width, window, batch)
        return torch.einsum("bhy,bscyx,bwx->bschw", rows, nodes, cols)

    def pupils_vary(self) -> bool:
        """Whether the pupils change across the sensor (a field correction or a cat-eye's shift
        that is not zero), or may while training (the drift's gradient is not zero there); where
        they do not, :meth:`drift_map` is zero everywhere."""
        if torch.is_grad_enabled() and any(p.requires_grad for p in (self.pupil_field, self.vignette) if p is not None):
            return True
        if bool(self.pupil_field.detach().abs().max() > 0):
            return True
        return self.vignette is not None and bool(self.vignette.detach()[:2].abs().max() > 0)

    def node_transmissions(self) -> torch.Tensor:
        """``(g^2, 2, 3, P, P)``: the pupils' transmissions at the field grid's nodes, what
        :meth:`pupil_roughness` and :meth:`pupil_chroma` measure (pass it to both to compute it once)."""
        g = self.config.field_grid
        axis = torch.linspace(-1.0, 1.0, g, device=self.pupil_shared.device, dtype=self.pupil_shared.dtype) if g > 1 \
            else self.pupil_shared.new_zeros(1)
        nodes = torch.stack(torch.broadcast_tensors(axis[None, :], axis[:, None]), dim=-1).reshape(1, -1, 2)
        return torch.exp(self.pupils_at(nodes))[0]

    def pupil_roughness(self, t: torch.Tensor | None = None) -> torch.Tensor:
        """Scalar: the pupils' total variation over their mean transmission, ``(mean |d t / d u|
        + mean |d t / d v|) / mean t`` per grid step, averaged over the pupils at the field grid's
        nodes (side, channel). About 0.13 for a flat disk (its rim); a pupil of speckle is 10x that."""
        t = self.node_transmissions() if t is None else t
        tv = (t[..., :, 1:] - t[..., :, :-1]).abs().mean(dim=(-2, -1)) + (t[..., 1:, :] - t[..., :-1, :]).abs().mean(dim=(-2, -1))
        return (tv / t.mean(dim=(-2, -1)).clamp_min(_EPS)).mean()

    def pupil_chroma(self, t: torch.Tensor | None = None) -> torch.Tensor:
        """Scalar, 0 for an achromatic lens: how far the colour channels' pupils differ, ``mean_c
        |t_c - mean_c t| / mean t`` over each pupil at the field grid's nodes (side), plus the
        mean absolute deviation of the log CoC scales from their mean (a relative size)."""
        t = self.node_transmissions() if t is None else t  # (nodes, side, channel, P, P)
        grey = t.mean(dim=2, keepdim=True)
        pupils = ((t - grey).abs().mean(dim=(2, 3, 4)) / grey.mean(dim=(2, 3, 4)).clamp_min(_EPS)).mean()
        return pupils + (self.log_channel_scale - self.log_channel_scale.mean()).abs().mean()

    def pupil_field_spread(self) -> torch.Tensor:
        """Scalar, 0 for a lens whose pupil does not change over the field beyond the cat-eye's
        circle (which is built in, not learned): how far the pupils at the field grid's nodes
        differ from the lens-wide one, ``mean |t_node - t| / mean t`` per side and channel, over
        the nodes. A correction the data does not show is noise fitted per region."""
        g, p = self.config.field_grid, self.config.pupil_size
        shared = torch.exp(self.pupil_shared)  # (2, 3, P, P)
        nodes = torch.exp(self.pupil_shared + self.pupil_field.reshape(g * g, 2, 3, p, p))
        spread = (nodes - shared).abs().mean(dim=(-2, -1)) / shared.mean(dim=(-2, -1)).clamp_min(_EPS)
        return spread.mean()

    def gain_slopes(self, diameter: float) -> torch.Tensor:
        """``(2, 3)``: band ``diameter``'s (px) CoC radius per channel, point-reflected in front of
        the focus (side 0 behind, 1 in front): the slope of :meth:`colour_gains` in the drift."""
        radius = 0.5 * float(diameter) * torch.exp(self.log_channel_scale)  # (3,) px
        return torch.stack([radius, -radius])

    def colour_gains(self, drift: torch.Tensor, diameter: float, side: int | None = None) -> torch.Tensor:
        """What band ``diameter``'s scattered colour is multiplied by at each source pixel,
        ``1 - div m`` for the drift ``m`` of its light (:meth:`drift_map` times the CoC radius,
        point-reflected in front of the focus), shaped as ``drift``: ``(..., 2, 3, H, W)``, or one
        ``side``'s ``(..., 3, H, W)``. Coverage is geometric and keeps 1, as in the reference
        scatter (:mod:`neuralbokeh.render.scatter`)."""
        slopes = self.gain_slopes(diameter).to(drift.dtype)
        return 1.0 - (slopes if side is None else slopes[side])[..., None, None] * drift

    def pupils_at(self, pos: torch.Tensor) -> torch.Tensor:
        """Log-transmissions ``(B, T, 2, 3, P, P)`` of the pupils at sensor positions ``pos``
        ``(B, T, 2)`` (x, y in [-1, 1] over the sensor, its left / top edge at -1): the lens-wide
        pupil, the field correction interpolated there and the cat-eye's circle."""
        g, p = self.config.field_grid, self.config.pupil_size
        # bilinear over the nodes (edges clamped) as one matrix product: its backward is a product
        # too (grid_sample's backward over 6 P^2 channels at a few points took a fifth of a step)
        corr = field_weights(pos.reshape(-1, 2), g) @ self.pupil_field.reshape(g * g, -1)  # (B T, 6 P^2)
        corr = corr.reshape(*pos.shape[:2], 2, 3, p, p)
        pupils = self.pupil_shared + corr
        if self.vignette is None:
            return pupils
        return pupils + vignette_log_mask(pos, self.vignette, p)[:, :, None, None]


    def kernels(self, n: int, pupils: torch.Tensor, diameter: float, ss: int | None = None) -> torch.Tensor:
        """Band ``n``'s kernels ``(M, 2, 3, k, k)`` for the pupils ``(M, 2, 3, P, P)`` (log) at CoC
        ``diameter`` (px): side 0 behind, 1 in front (already point-reflected), each summing to
        1, as a correlation-free PSF (light lands at ``p + offset``).

        Kernel pixel ``(a, b)`` is the mean of the bilinearly interpolated transmission over
        ``ss x ss`` points of its footprint (:func:`supersampling`). Both the sampling and the
        interpolation are separable, so the kernel is ``W T W^T`` with ``W`` ``(k, P)`` the
        row weights (:func:`raster_weights`): two small matrix products per pupil; with
        ``model.pixel_blur`` ``W`` is first filtered by :func:`pixel_blur_matrix`. ``ss``: the
        supersampling (default: :func:`supersampling`'s for ``diameter``)."""
        k = self.kernel_size(n)
        scale = torch.exp(self.log_channel_scale)  # (3,)
        ss = self._supersampling(diameter) if ss is None else ss
        w = raster_weights(k, ss, 0.5 * float(diameter) * scale, self.config.pupil_size, pupils.dtype, pupils.device)
        blur = self.pixel_blur_px2(diameter)
        if blur is not None:
            w = pixel_blur_matrix(k, blur.to(w.dtype)) @ w
        kern = w[None, None] @ torch.exp(pupils) @ w.transpose(-1, -2)[None, None]  # (M, 2, 3, k, k)
        if blur is not None:  # a sharpening blur (v < 0) dips below zero beside a rim; a PSF does not
            kern = kern.clamp_min(0.0)
        kern = kern / kern.sum(dim=(-2, -1), keepdim=True).clamp_min(_EPS)
        # in front of the focus plane the aperture's image is inverted
        return torch.stack([kern[:, 0], kern[:, 1].flip(-2, -1)], dim=1)

    def pixel_blur_px2(self, diameter: float) -> torch.Tensor | None:
        """The learned pixel blur's variance (px^2 per axis, a scalar tensor) at CoC ``diameter``
        (px): ``v_inf (1 - exp(-d / d_v))``; ``None`` without ``model.pixel_blur``."""
        if self.pixel_blur is None:
            return None
        v_inf = PIXEL_BLUR_MAX_PX2 * torch.tanh(self.pixel_blur[0])
        return v_inf * -torch.expm1(-float(diameter) / torch.exp(self.pixel_blur[1]))

    def _supersampling(self, diameter: float) -> int:
        """Supersamples per kernel pixel side at CoC ``diameter`` (px), for the smallest channel scale."""
        return supersampling(float(diameter) * float(torch.exp(self.log_channel_scale).detach().min()), self.config.pupil_size)

    def kernel_slopes(self, n: int, pupils: torch.Tensor, diameter: float, step_px: float) -> torch.Tensor:
        """Band ``n``'s kernels' derivative in the diameter at ``diameter`` (px) times the lattice
        step ``step_px``, shaped as :meth:`kernels`: each sums to 0 (every kernel sums to 1).
        A central difference over +-``SLOPE_DELTA_PX`` with one supersampling, so that it
        differentiates the rasterisation, not a change of its sampling."""
        ss = self._supersampling(diameter)
        up = self.kernels(n, pupils, float(diameter) + SLOPE_DELTA_PX, ss)
        down = self.kernels(n, pupils, float(diameter) - SLOPE_DELTA_PX, ss)
        return (up - down) * (float(step_px) / (2.0 * SLOPE_DELTA_PX))

    # -- forward ---------------------------------------------------------------------------
    def field_parts(self, layout: TileLayout, height: int, width: int, window: torch.Tensor | None, batch: int) -> FieldParts:
        """What a ``height x width`` frame on the sensor ``window`` ``(B, 4)`` (default: the whole
        sensor) needs of the pupils' change across the field (:class:`FieldParts`): the drift,
        the flow's offsets and the gradient's parts only where the pupils vary and the config
        asks for them."""
        pupils = self.tile_pupils(layout, height, width, window, batch).flatten(0, 1)  # (B T, 2, 3, P, P)
        if not self.pupils_vary():  # the drift is exactly zero: no map, every gain 1
            return FieldParts(pupils)
        win = layout.window
        drift = self.drift_map(height, width, window, batch)
        drift = tile(drift.flatten(1, 2), layout).view(-1, 2, 3, win, win)  # (B T, 2, 3, win, win)
        offsets = self.centroid_offsets(layout, pupils, height, width, window, batch) if self.config.field_flow else None
        if not self.config.field_gradient:
            return FieldParts(pupils, drift, offsets)
        neighbours, per_px = self.neighbour_pupils(layout, height, width, window, batch)
        return FieldParts(pupils, drift, offsets, neighbours, per_px,
                          self.tile_offsets_px(layout, height, width, pupils.device, pupils.dtype))

    def source_coc(self, x: torch.Tensor) -> torch.Tensor | None:
        """The frame's :func:`source_coc_px` ``(B, 1, H, W)`` of the input ``(B, 4, H, W)`` with
        ``model.highlight_spread``, else None (every source takes its own CoC)."""
        if not self.config.highlight_spread:
            return None
        return source_coc_px(self.contract.normalization.decode(x[:, :3]), x[:, 3:] * float(self.contract.coc_scale_px))

    def frame_coc(self, x: torch.Tensor, plan_coc_px: float | None = None, source: torch.Tensor | None = None) -> float:
        """The largest |CoC| (px) the frame's plan covers: ``plan_coc_px``, else the input's own
        (and, with ``model.highlight_spread``, its isolated highlights' grown CoC up to the largest
        trained: beyond, as in the exported file's plan, they stay in the last band). ``source``:
        :meth:`source_coc` of ``x`` if already computed."""
        if plan_coc_px is not None:
            return float(plan_coc_px)
        if not x.numel():
            return 0.0
        largest = float((x[:, 3].abs().max() * float(self.contract.coc_scale_px)).item())
        source = self.source_coc(x) if source is None else source
        if source is not None:  # a highlight in focus may need band 1 where no pixel's own CoC does
            largest = max(largest, min(float(source.abs().max().item()), float(self.contract.max_coc_px)))
        return largest

    def tile_accumulators(self, x: torch.Tensor, window: torch.Tensor | None = None, tile_active: torch.Tensor | None = None,
                          scales: dict[int, int] | None = None, plan_coc_px: float | None = None,
                          source: torch.Tensor | None = None) -> torch.Tensor:
        """``(B, 4, H, W)`` -> per-window accumulators ``(B, tiles, 3 buckets, 6, win, win)``
        (premultiplied RGB and per-channel coverage of the near, same-surface and far light).

        ``window`` ``(B, 4)``: each image's part of the sensor (left, top, width, height in
        fractions; default the whole sensor), which places its tiles' pupils in the field.
        ``tile_active`` (``(tiles,)`` bool, optional): inactive tiles pass their core through
        as in-focus light without any convolution (exact when their window is all in focus).
        ``scales`` (``{band: s}``, optional; see :func:`band_scales`): band ``n`` is scattered
        on a grid ``s`` times coarser (box-averaged features, the kernel binned by
        :func:`reduce_kernel`, bilinear upsampling), the approximation the fast export makes;
        the buckets stay at full resolution. ``plan_coc_px``: plan the bands for this largest
        |CoC| instead of the frame's own (larger CoCs then stay in the last band). ``source``:
        :meth:`source_coc` of ``x`` if already computed.
        """
        cfg = self.config
        check_network_input(x)
        if checks.DEBUG:
            checks.check_finite("model input", x)
        b, _, height, width = x.shape
        if window is not None and (window.ndim != 2 or window.shape[1] != 4 or window.shape[0] not in (1, b)):
            raise ValueError(f"window must have shape ({b}, 4) or (1, 4): (left, top, width, height), got {tuple(window.shape)}")
        layout = self.layout(height, width)
        n_t = layout.num_tiles
        if source is None and cfg.highlight_spread:
            source = self.source_coc(x)
        plan = self.plan(self.frame_coc(x, plan_coc_px, source))
        blocks, diameters = plan.blocks, plan.diameters
        xt = tile(x, layout, light=3)  # a point source on the frame's edge is not repeated into the padding
        win = xt.shape[-1]
        xt = xt.view(b, n_t, 4, win, win)
        rgb = self.contract.normalization.decode(xt[:, :, :3])  # linear light
        coc = xt[:, :, 3] * float(self.contract.coc_scale_px)  # (B, T, win, win) signed px
        source_coc = coc  # the CoC whose kernel each source gets; the receivers keep their own
        if source is not None and blocks:  # of the whole frame: a highlight is found among its neighbours in any tile
            source_coc = tile(source, layout).view(b, n_t, win, win)
        pos = plan.position(source_coc)  # continuous band index
        src = self.source_masks(layout, x.device, x.dtype)[None]  # (1, T, 1, win, win)
        active = torch.ones(n_t, dtype=torch.bool, device=x.device) if tile_active is None else tile_active.to(x.device)
        # a tensor of its own, not a view: the bands add into it in place (a view would make each
        # in-place add copy the whole accumulator in the backward)
        acc = _in_focus_light(rgb, pos, src, active).reshape(b * n_t, 3, 6, win, win).clone()
        self.last_convolutions = 0  # (image, tile, band, side) scatters computed by the last call
        if blocks == 0:
            return acc.view(b, n_t, 3, 6, win, win)
        # one set of pupils per distinct window: whole frames (or equal windows) share their tiles' kernels
        shared = window is None or bool((window == window[:1]).all())
        field = self.field_parts(layout, height, width, None if window is None else window[:1] if shared else window,
                                 1 if shared else b)
        pupils, drift, offsets = field.pupils, field.drift, field.offsets
        coc_flat = coc.reshape(b * n_t, win, win)
        slope_flat = None
        if cfg.occlusion_margin_slope:  # of the whole frame: a window's own edge is not a surface's, and no tiling changes it
            frame_slope = coc_slope(x[:, 3:] * float(self.contract.coc_scale_px))
            slope_flat = tile(frame_slope, layout).reshape(b * n_t, win, win)
        rgb_flat = rgb.reshape(b * n_t, 3, win, win)
        spans = source_coc_ranges(plan) if cfg.occlusion_source_coc else None
        scales = scales or {}
        hermite = cfg.band_blend == "hermite"
        for n in range(1, blocks + 1):
            if hermite:
                g, g_slope = (v * src[:, :, 0] for v in hermite_weights(pos, n))  # (B, T, win, win) each
            else:
                g, g_slope = _gate(pos, n) * src[:, :, 0], None
            kern = slope = grad = None
            for side, sign in ((0, 1.0), (1, -1.0)):
                side_mask = ((coc > 0) if side == 0 else (coc < 0)).to(x.dtype)
                gs = g * side_mask
                used = (gs.flatten(2).amax(-1) > 0) & active[None, :]  # (B, T)
                idx = torch.nonzero(used.flatten()).flatten()
                if idx.numel() == 0:
                    continue  # no pixel of any tile uses this band on this side: nothing computed
                # each distinct pupil's kernels once per band, both sides (shared: one set for every image)
                if kern is None:
                    kern = self.kernels(n, pupils, float(diameters[n]))
                    slope = self.kernel_slopes(n, pupils, float(diameters[n]), plan.band_step_px(n)) if hermite else None
                    if field.neighbours is not None:
                        grad = self.kernel_gradients(n, field.neighbours, float(diameters[n]), field.per_px)
                which = idx % n_t if shared else idx
                w = gs.reshape(b * n_t, 1, win, win)[idx]
                colour = rgb_flat[idx]
                if drift is not None and grad is None:  # the gradient's kernels already move the light (their first moment)
                    colour = colour * self.colour_gains(drift[which, side], float(diameters[n]), side)  # (M, 3, win, win)
                feats = torch.cat([colour * w, w], dim=1)  # (M, 4, win, win)
                if hermite:  # the slope's weights on the same pixels, with the same side mask
                    ws = (g_slope * side_mask).reshape(b * n_t, 1, win, win)[idx]
                    feats = torch.cat([feats, colour * ws, ws], dim=1)  # (M, 8, win, win)
                if grad is not None:  # the kernels' change across the tile: by each pixel's offset (px)
                    wo = w * field.pixel_offsets[idx % n_t]  # (M, 2, win, win)
                    feats = torch.cat([feats, colour * wo[:, :1], wo[:, :1], colour * wo[:, 1:], wo[:, 1:]], dim=1)
                # the CoC radius (the channels' mean, point-reflected in front) x the offset
                flow = None if offsets is None else self.gain_slopes(float(diameters[n]))[side].mean() * offsets[which, side]
                extra = ([] if slope is None else [slope[:, side]]) + ([] if grad is None else [grad[:, 0, side], grad[:, 1, side]])
                out = _scatter(feats, kern[:, side], which, scales.get(n, 1), extra, flow)
                band_coc = sign * float(diameters[n])
                if cfg.occlusion_source_coc:  # each source's CoC from the band's centre, carried with its light
                    # offsets from the centre: the FFT's rounding is relative to the largest, and the
                    # division by a coverage as small as the floor magnifies it
                    pair = torch.cat([w * (coc_flat[idx].unsqueeze(1) - band_coc), w], dim=1)
                    band_coc = _carried_coc(pair, kern[:, side, 1:2], which, scales.get(n, 1) * cfg.occlusion_source_coc_grid,
                                            band_coc, spans[n], flow)
                if grad is not None:  # coverage is geometric: divided by a uniform field's light, as the reference scatter's
                    out = torch.cat([out[:, :3], out[:, 3:] / self.colour_gains(drift[which, side], float(diameters[n]), side)], 1)
                margin = self.occlusion_margin(float(diameters[n]), plan.band_step_px(n))
                if slope_flat is not None:  # the receiver's own surface's CoC change across the band's reach
                    margin = torch.maximum(slope_flat[idx] * (0.5 * float(diameters[n])), torch.as_tensor(margin, dtype=x.dtype))
                bw = bucket_weights(band_coc, coc_flat[idx], margin)
                contrib = bw.permute(1, 0, 2, 3).unsqueeze(2) * out.unsqueeze(1)  # (M, 3, 6, win, win)
                # one band at a time: memory stays O(image), not O(image x bands); in place, so no
                # band copies the whole accumulator
                acc.index_add_(0, idx, contrib)  # in place under autograd too: no op saved acc for its backward
                self.last_convolutions += int(idx.numel())
        return acc.view(b, n_t, 3, 6, win, win)

    def hidden(self, x: torch.Tensor, plan_coc_px: float | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """What foregrounds hide in the input ``(B, 4, H, W)``: a linear ``(B, 3, H, W)`` estimate
        (:func:`neuralbokeh.ops.holes.hidden_background`); ``(B, 1, H, W)`` bool, the pixels that
        hide something (:func:`~neuralbokeh.ops.holes.hidden_pixels`; none when nothing is
        blurred) or lie within ``SILHOUETTE_PX`` of one; and the bound the estimate puts on a
        visible pixel's own colour ``(B, 3, H, W)`` (:func:`~neuralbokeh.ops.holes.hidden_estimate`).
        The last two are the surface fill's. Occluders are looked for within the plan's
        ``fill_radius_px``."""
        radius = self.plan(self.frame_coc(x, plan_coc_px)).fill_radius_px
        coc = x[:, 3:] * float(self.contract.coc_scale_px)
        background, bound, hides = hidden_estimate(self.contract.normalization.decode(x[:, :3]), coc, radius_px=radius)
        # a silhouette's pixels mix both surfaces' colours under one of their depths: they keep the estimate
        beside = square_max(hides.to(coc.dtype), SILHOUETTE_PX) > 0.5
        return background, beside, bound

    def occlusion_margin(self, diameter: float, step_px: float = 0.0) -> torch.Tensor | float:
        """The buckets' margin (px of CoC, > 0) for light of a band of diameter ``diameter`` (px):
        ``ModelConfig.occlusion_margin`` times the learned factor (``model.occlusion_margin_learned``),
        and with ``model.occlusion_margin_step`` at least ``step_px``, the lattice's step at the band."""
        base = self.config.occlusion_margin(diameter)
        margin = base if self.margin_scale is None else base * torch.exp(self.margin_scale[0])
        if not self.config.occlusion_margin_step:
            return margin
        return torch.clamp(margin, min=step_px) if torch.is_tensor(margin) else max(margin, step_px)

    def surface_fill_share(self) -> torch.Tensor:
        """The share (0..1) of a visible pixel's hole that its own surface's blurred light fills
        (``model.surface_fill``)."""
        if self.surface_fill is None:
            raise ValueError(f"model.surface_fill is off (or model.fill is {self.config.fill!r}): there is no share")
        return torch.sigmoid(self.surface_fill)

    def surface_filled(self, background: torch.Tensor, color: torch.Tensor, cover: torch.Tensor, hides: torch.Tensor,
                       bound: torch.Tensor) -> torch.Tensor:
        """The fill ``(B, 3, H, W)`` with ``model.surface_fill``: where a pixel hides nothing and is
        not beside one that does (``hides`` ``(B, 1, H, W)`` False, :meth:`hidden`), what its
        coverage leaves short is its own surface behind something nearer, seen blurred: the mean
        colour of the light from its own depth and behind (the same and far buckets of
        ``color``, ``cover`` ``(B, 3, 3, H, W)``) for the learned share, the ``background``
        estimate (its sharp colour) for the rest. With almost no such light
        (below ``SURFACE_FILL_EPS``) the estimate takes over smoothly. The mean is at most
        ``bound``, the estimate's bound on the pixel's own colour: a highlight's light is in
        the mean already, and a surface hidden beside it is not lit by it again."""
        own = (color[:, 1] + color[:, 2] + SURFACE_FILL_EPS * background) / (cover[:, 1] + cover[:, 2] + SURFACE_FILL_EPS)
        own = torch.minimum(own, bound)
        share = self.surface_fill_share() * (~hides).to(background.dtype)
        return background + share * (own - background)

    def composite(self, acc: torch.Tensor, background: torch.Tensor | None = None,
                  surface: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        """Buckets ``(B, 3, 6, H, W)`` -> linear RGB ``(B, 3, H, W)``: near over same over far,
        sum-to-saturation per channel; remaining holes filled with ``background`` ``(B, 3, H, W)``
        (``fill = "background"``; ``"far_light"``: the far bucket's mean colour first, see
        :func:`far_light_fill`; with ``model.surface_fill`` and ``surface`` = (``hides``,
        ``bound``) of :meth:`hidden`, see :meth:`surface_filled`) or by normalising."""
        color, cover = acc[:, :, :3], acc[:, :, 3:].clamp_min(0.0)
        out = torch.zeros_like(color[:, 0])
        taken = torch.zeros_like(out)
        for k in range(3):
            a = cover[:, k]
            room = (1.0 - taken).clamp_min(0.0)
            frac = torch.minimum(torch.ones_like(a), room / a.clamp_min(_EPS))
            out = out + color[:, k] * frac
            # = taken + a * frac, but exactly 1 once saturated: a rounding of 1 - ulp would let
            # a 1e4 highlight behind a covered surface leak through
            taken = torch.clamp_max(taken + a, 1.0)
        if background is None:
            return out / taken.clamp_min(_EPS)
        hole = (1.0 - taken).clamp_min(0.0)
        if self.surface_fill is not None and surface is not None:
            background = self.surface_filled(background, color, cover, *surface)
        if self.fill_gain is not None:
            return out + far_light_fill(hole, color[:, 2], cover[:, 2], background, self.far_light_gain())
        return out + hole * background

    def far_light_gain(self) -> torch.Tensor:
        """The far-light fill's gain (``fill = "far_light"``), > 0: at most this many times its own
        coverage of a hole is filled with the far light's mean colour."""
        if self.fill_gain is None:
            raise ValueError(f"model.fill is {self.config.fill!r}: only a 'far_light' fill has a gain")
        return F.softplus(self.fill_gain)

    def forward(self, x: torch.Tensor, window: torch.Tensor | None = None, return_tiles: bool = False,
                tile_active: torch.Tensor | None = None, scales: dict[int, int] | None = None,
                plan_coc_px: float | None = None) -> torch.Tensor:
        """``(B, 4, H, W)`` (any H, W) -> ``(B, 3, H, W)`` normalised defocused RGB; with
        ``return_tiles`` each window composited on its own ``(B, tiles * 3, win, win)``
        (per-tile-loss ablation). ``window``, ``tile_active``, ``scales``, ``plan_coc_px``:
        see :meth:`tile_accumulators`."""
        cfg = self.config
        check_network_input(x)
        if checks.DEBUG:  # before the plan, whose highlight search decodes the colour
            checks.check_finite("model input", x)
        source = self.source_coc(x)  # once: the plan and the bands share it
        plan_coc_px = self.frame_coc(x, plan_coc_px, source)  # read once (a device sync): the bands and the fill share it
        acc = self.tile_accumulators(x, window, tile_active, scales, plan_coc_px, source)  # (B, T, 3, 6, win, win)
        b, n_t, _, _, win, _ = acc.shape
        h, w = x.shape[-2:]
        layout = self.layout(h, w)
        background, hides, bound = self.hidden(x, plan_coc_px) if cfg.fill != "normalize" else (None, None, None)
        if return_tiles:
            if background is None:
                out = self.composite(acc.view(b * n_t, 3, 6, win, win))
            else:
                bg, hd, bd = (tile(t.to(x.dtype), layout).reshape(b * n_t, -1, win, win) for t in (background, hides, bound))
                out = self.composite(acc.view(b * n_t, 3, 6, win, win), bg, (hd > 0.5, bd))
            return self.contract.normalization.encode(out.clamp_min(0.0)).view(b, n_t * 3, win, win)
        canvas = overlap_add(acc.view(b, n_t, 18, win, win), layout)
        t_o = layout.overlap
        canvas = canvas[:, :, t_o : t_o + h, t_o : t_o + w]
        out = self.composite(canvas.view(b, 3, 6, h, w), background, None if hides is None else (hides, bound))
        return self.contract.normalization.encode(out.clamp_min(0.0))

    def tile_targets(self, y: torch.Tensor) -> torch.Tensor:
        """Cut a target ``(B, 3, H, W)`` into the windows (for the per-tile-loss ablation)."""
        return tile(y, self.layout(*y.shape[-2:]))


def check_network_input(x: torch.Tensor) -> None:
    """Raise ``ValueError`` unless ``x`` is a network input ``(B, 4, H, W)`` (any H, W >= 1)."""
    if x.ndim != 4 or x.shape[1] != 4 or min(x.shape[2:]) < 1:
        raise ValueError(f"input must have shape (B, 4, H, W), got {tuple(x.shape)}")

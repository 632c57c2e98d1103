"""The ONNX graph of the lens architecture (:mod:`neuralbokeh.networks.lens`), from its kernels (onnx + numpy).

Built op by op rather than traced from the module: the traced graphs are slower (docs/runtime.md,
"Where the lens maths lives"; ``benchmarks/bench_traced_export.py``). Its rules come from the module's own
definitions: the band plan (:class:`~neuralbokeh.core.bands.BandPlan`: lattice, band position,
the fill's reach) and the fill's ``ops.holes`` constants (``JUMP_PX``, ``STEP_PX``, ``LOG_OFFSET``, ``OUTLIER_RATIO``).

Named inputs ``aif``, ``coc``, ``tile_active`` (as the paper network's graph, ``graph.py``) and
``band_active`` ``(tiles, N, 2)`` bool; output ``defocus``. The learned pupils are rasterised
once, at export, into each block's per-channel ``(2n + 1)^2`` kernels; the graph holds those.

Per tile (an ONNX ``If`` on ``tile_active``; an inactive tile passes its core through as
in-focus light): decode to linear light, the in-focus band, then per band and side an ``If``
on ``band_active[tile, n - 1, side]`` (the runtime proves from the frame's CoC map which bands
a tile's pixels use, :func:`neuralbokeh.core.bands.active_bands` with the plan stored in the
file; a band that does not run returns an empty tensor, so it costs nothing downstream
either): the band's hat gate, a grouped convolution of (colour x gate, gate) by
the band's kernels (ONNX ``Conv`` correlates: the point-spread functions are stored
point-reflected), and the near / same-surface / far bucket weights at full resolution.

*Rows* (``rows`` and ``multires``; ``direct`` keeps one depthwise ``Conv``): the convolution is
computed as row GEMMs plus a ``Col2Im`` shift-sum (:func:`conv_rows`), the same sums in another
order, 1.4-2.8x faster on CPU for k = 5-23.

*Coarser grids* (``scales``, the default export ``multires:10``): a band whose CoC is wide is
convolved on a grid ``s`` = 2, 4 or 8 times coarser: box-averaged features (``AveragePool``),
the kernel binned by :func:`~neuralbokeh.networks.lens.reduce_kernel`, bilinear upsampling
(``Resize``, half-pixel). A convolution then costs ``1 / s^4`` of the direct one. What it costs
in accuracy, stated in ``tests/test_lens_network.py``: flux kept, light moved by at most
``(s - 1) / 2`` px and widened by at most ``s^2`` px^2 of variance; the PSNR against the direct
export is measured by ``benchmarks/bench_runtime.py``. ``LensBokeh.forward(x, scales=...)`` is
the PyTorch reference the export is checked against.

The output is assembled core by core (an ``If`` per tile core, :func:`_core`): a core that a
window which ran reaches sums those windows' accumulators ((near, same, far) x (RGB, coverage))
over itself, cell by cell, composites them near over far with sum-to-saturation, fills the
coverage left short with the hidden-background estimate (a visible pixel's with its own
surface's blurred light first, for ``model.surface_fill``; or normalises, for ``fill =
"normalize"``) and encodes, as ``LensBokeh.forward`` does; any other core is its input,
unchanged. ``fp16`` runs the convolutions in float16 (inputs and kernels);
gates, buckets and the composite stay float32.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

import numpy as np
import onnx
from onnx import TensorProto, helper

from ..core.bands import HIGHLIGHT_RATIO, HIGHLIGHT_SPREAD_END_PX, HIGHLIGHT_SPREAD_PX2, POINT_PX, BandPlan
from ..core.contract import Contract
from ..core.normalization import Normalization
from ..core.tiling import pyramid_levels
from ..networks.config import SILHOUETTE_PX, SURFACE_FILL_EPS, ModelConfig
from ..networks.lens import FLOW_MIN_PX, SOURCE_COC_MIN_COVER, source_coc_ranges, window_offsets_px
from ..ops.holes import JUMP_PX, LOG_OFFSET, OUTLIER_RATIO, STEP_PX
from .graph import GraphBuilder, finish_model

_EPS = 1e-8
# Bands whose CoC stays >= 10 coarse px wide on a 2, 4 or 8 times coarser grid are convolved there
# (benchmarks/bench_runtime.py measures the speed and the error against the direct export).
LENS_DEFAULT_KERNELS = "multires:10"


class LensKernels(NamedTuple):
    """How the band convolutions are exported (:func:`parse_lens_kernels`)."""

    min_px: float  # the narrowest CoC (coarse px) a band may have on a reduced grid; 0: full resolution
    rows: bool  # row-GEMM convolutions (:func:`conv_rows`) instead of one depthwise ``Conv``


def parse_lens_kernels(spec: str) -> LensKernels:
    """``"direct"`` (full resolution, one depthwise ``Conv`` per band: the reference),
    ``"rows"`` (full resolution, the same sums as row GEMMs, exact to float rounding) or
    ``"multires:PX"`` (PX > 0: coarser grids for bands whose CoC stays at least PX coarse px
    wide, as rows).

    Raises:
        ValueError: anything else, with the accepted forms.
    """
    if spec in ("direct", "rows"):
        return LensKernels(0.0, spec == "rows")
    mode, _, arg = spec.partition(":")
    try:
        px = float(arg)
    except ValueError:
        px = -1.0
    if mode != "multires" or not px > 0 or not np.isfinite(px):
        raise ValueError(f"kernels for the lens network must be 'direct', 'rows' or 'multires:PX' (PX > 0 px), got {spec!r}")
    return LensKernels(px, True)


class Nodes:
    """A list of nodes with a builder: ``op("Add", a, b)`` returns the output name."""

    def __init__(self, b: GraphBuilder, stem: str) -> None:
        self.b, self.stem, self.nodes = b, stem, []

    def op(self, kind: str, *inputs: str, **attrs: Any) -> str:
        out = self.b.fresh(f"{self.stem}.{kind.lower()}")
        self.nodes.append(helper.make_node(kind, list(inputs), [out], name=out, **attrs))
        return out

    def c(self, name: str, value: Any, dtype: Any = np.float32) -> str:
        return self.b.const(f"{self.stem}.{name}", value, dtype)


def _out(name: str) -> onnx.ValueInfoProto:
    return helper.make_tensor_value_info(name, TensorProto.FLOAT, None)


def _branch(g: Nodes, result: str, name: str) -> onnx.GraphProto:
    final = g.b.fresh(f"{name}.result")
    g.nodes.append(helper.make_node("Identity", [result], [final], name=final))
    return helper.make_graph(g.nodes, name, [], [_out(final)], g.b.initializers)


class FillParts(NamedTuple):
    """What the fill computes once per frame (:func:`hidden_parts`); each core takes its own part
    of the rest (:func:`core_fill`)."""

    rgb: str  # (B, 3, H, W) linear light
    keep: str | None  # (B, 1, H, W) float, 0 on the pixels that hide something; None: nothing can hide anything
    masked: str | None  # (B, 3, H, W) the log of the light where keep is 1, else 0
    filled: str | None  # the pull-push's level 1, filled, (B, 3, 2^(L-1), 2^(L-1)); None: a one-pixel frame


def hidden_parts(top: Nodes, colour: str, coc: str, contract: Contract, r: int) -> FillParts:
    """The frame-wide part of ``ops.holes.hidden_estimate`` on the network's input, its
    normalised ``colour`` ``(B, 3, H, W)`` and ``coc`` ``(B, 1, H, W)`` (as ``LensBokeh.hidden``):
    occluders by a separable max over ``2r + 1`` px (``r``: the plan's ``fill_radius_px``), then
    the pull-push fill of the log of the light on the zero-padded ``2^L`` square (``AveragePool``
    2x2), down to its level 1 filled; level 0, the upsampling to it and the bound are per pixel
    and left to :func:`core_fill`."""
    h, w = contract.size
    rgb = _decode(top, colour, contract.normalization)
    if r == 0:
        return FillParts(rgb, None, None, None)  # nothing can hide anything: the fill is the AIF itself
    coc = top.op("Mul", coc, top.c("bg.coc_scale", float(contract.coc_scale_px)))
    far = window_max(top, window_max(top, coc, r, 3, w), r, 2, h)  # rows, then columns (as ops.holes.occluders)
    hide = top.op("Less", coc, top.op("Sub", far, top.c("bg.jump", JUMP_PX)))
    near = window_max(top, window_max(top, coc, 1, 3, w), 1, 2, h)  # the 3 x 3 neighbours
    hide = top.op("Or", hide, top.op("Less", coc, top.op("Sub", near, top.c("bg.step", STEP_PX))))
    keep = top.op("Cast", top.op("Not", hide), to=TensorProto.FLOAT)
    log_rgb = top.op("Log", top.op("Add", top.op("Max", rgb, top.c("bg.zero", 0.0)), top.c("bg.log_offset", LOG_OFFSET)))
    masked = top.op("Mul", log_rgb, keep)
    # the pyramid of push_pull_fill on the zero-padded 2^L square, with level 0 left unpadded:
    # its 2x2 means over the padding are 0 with weight 0, as padding level 1 with zeros gives
    side = 1 << pyramid_levels(h, w)
    if side < 2:
        return FillParts(rgb, keep, masked, None)  # one pixel: nothing stands in front of anything
    image, weight = _pull(top, masked, keep, [0, 0, h % 2, w % 2], premultiplied=True)
    pads = top.c("bg.pads", [0, 0, 0, 0, 0, 0, side // 2 - (h + 1) // 2, side // 2 - (w + 1) // 2], np.int64)
    image, weight = top.op("Pad", image, pads), top.op("Pad", weight, pads)
    levels = []
    size = side // 2
    while size >= 2:  # pull: weight-normalised 2x2 means
        levels.append((image, weight))
        image, weight = _pull(top, image, weight, [0, 0, 0, 0])
        size //= 2
    filled = image
    for image, weight in reversed(levels):  # push: fill each level from the next coarser one
        filled = top.op("Add", top.op("Mul", weight, image), top.op("Mul", top.op("Sub", top.c("bg.one", 1.0), weight),
                                                                      _upsample2(top, filled)))
    return FillParts(rgb, keep, masked, filled)


def core_fill(g: Nodes, parts: FillParts, region: tuple[int, int, int, int], size: tuple[int, int],
              surface: bool) -> tuple[str, str | None, str]:
    """The fill's inputs over the image rows ``[r0, r1)`` and columns ``[c0, c1)`` (``region``)
    of a frame of ``size`` (H, W), from its :func:`hidden_parts`: the hidden-background estimate
    ``(B, 3, h, w)`` (level 0 of the pull-push: level 1 upsampled x2, half-pixel, from the level-1
    pixels this region reads; each visible pixel's own colour clamped by its 3 x 3 geometric mean),
    with ``surface`` 1 where the surface fill may use a pixel's own light ``(B, 1, h, w)`` (no pixel
    within ``SILHOUETTE_PX`` hides anything; else None) and the bound on a visible pixel's own
    colour. The same values as over the whole frame: each neighbourhood is cut with its halo, and
    padded only where the frame ends."""
    r0, r1, c0, c1 = region
    h, w = size

    def cut(t: str, a0: int, a1: int, b0: int, b1: int) -> str:
        return g.op("Slice", t, g.c(f"fill.at{a0}_{b0}", [a0, b0], np.int64), g.c(f"fill.to{a1}_{b1}", [a1, b1], np.int64),
                    g.c("fill.axes", [2, 3], np.int64))

    rgb = cut(parts.rgb, r0, r1, c0, c1)
    if parts.keep is None or parts.filled is None:
        return rgb, (cut(parts.keep, r0, r1, c0, c1) if surface and parts.keep is not None else None), rgb
    # level 0's rows [r0, r1) read level 1's rows r0 // 2 - 1 .. r1 // 2 (x2 half-pixel upsampling)
    half = (1 << pyramid_levels(h, w)) // 2
    y0, x0 = max(r0 // 2 - 1, 0), max(c0 // 2 - 1, 0)
    up = _upsample2(g, cut(parts.filled, y0, min(r1 // 2 + 1, half), x0, min(c1 // 2 + 1, half)))
    up = cut(up, r0 - 2 * y0, r1 - 2 * y0, c0 - 2 * x0, c1 - 2 * x0)
    behind = g.op("Sub", g.op("Exp", up), g.c("fill.log_offset", LOG_OFFSET))
    # visible pixels: their own colour, at most OUTLIER_RATIO x the geometric mean of their visible 3 x 3
    # (count_include_pad=0 divides both sums by the same count: their ratio is the mean over visible pixels)
    lo_r, hi_r, lo_c, hi_c = max(r0 - 1, 0), min(r1 + 1, h), max(c0 - 1, 0), min(c1 + 1, w)
    pads = [1 - (r0 - lo_r), 1 - (c0 - lo_c), 1 - (hi_r - r1), 1 - (hi_c - c1)]  # 1 only where the frame ends
    num = g.op("AveragePool", cut(parts.masked, lo_r, hi_r, lo_c, hi_c), kernel_shape=[3, 3], pads=pads, count_include_pad=0)
    den = g.op("AveragePool", cut(parts.keep, lo_r, hi_r, lo_c, hi_c), kernel_shape=[3, 3], pads=pads, count_include_pad=0)
    level = g.op("Exp", g.op("Div", num, g.op("Max", den, g.c("fill.tiny", 1e-12))))
    bound = g.op("Sub", g.op("Mul", level, g.c("fill.outlier", OUTLIER_RATIO)), g.c("fill.log_offset", LOG_OFFSET))
    visible = g.op("Cast", cut(parts.keep, r0, r1, c0, c1), to=TensorProto.BOOL)
    background = g.op("Where", visible, g.op("Min", rgb, bound), behind)
    if not surface:
        return background, None, bound
    # 1 - the max over the square of (1 - keep), from the square's pixels in the frame
    s_px = SILHOUETTE_PX
    lo_r, hi_r, lo_c, hi_c = max(r0 - s_px, 0), min(r1 + s_px, h), max(c0 - s_px, 0), min(c1 + s_px, w)
    one = g.c("fill.one", 1.0)
    hidden = g.op("Sub", one, cut(parts.keep, lo_r, hi_r, lo_c, hi_c))
    rows = window_max(g, hidden, s_px, 3, hi_c - lo_c, (s_px - (c0 - lo_c), s_px - (hi_c - c1)))
    beside = window_max(g, rows, s_px, 2, hi_r - lo_r, (s_px - (r0 - lo_r), s_px - (hi_r - r1)))
    return background, g.op("Sub", one, beside), bound


def hidden_background_graph(top: Nodes, colour: str, coc: str, contract: Contract, r: int) -> tuple[str, str | None, str]:
    """``(B, 3, H, W)`` linear estimate of what foregrounds hide, ``(B, 1, H, W)`` float, 1 where
    a pixel hides nothing (None: no pixel hides anything), and the estimate's bound on a visible
    pixel's own colour (``ops.holes.hidden_estimate``) over the whole frame: :func:`hidden_parts`
    and :func:`core_fill` of all of it."""
    h, w = contract.size
    parts = hidden_parts(top, colour, coc, contract, r)
    background, _, bound = core_fill(top, parts, (0, h, 0, w), (h, w), False)
    return background, parts.keep, bound


def window_max(g: Nodes, x: str, r: int, axis: int, size: int, pads: tuple[int, int] | None = None) -> str:
    """The max of ``x`` over ``[i - r, i + r]`` along ``axis`` (2 or 3, ``size`` long), nothing
    beyond the edges: as ``MaxPool`` with a ``2r + 1`` window and ``r`` of padding, exactly, but
    as ``log2(2r + 1)`` maxima of two shifted ``Slice``s (-inf padded): ``m[i]`` holds the max of
    ``x[i .. i + span - 1]``, doubled until ``span`` reaches ``2r + 1``. ~3x faster on CPU at
    r = 21 (onnxruntime's ``MaxPool`` reads the whole window for every pixel). ``pads``: the
    -inf padding before and after (default ``(r, r)``; less where ``x`` carries its own halo),
    so the result is ``size + sum(pads) - 2r`` long."""
    before, after = (r, r) if pads is None else pads
    cur = x
    if before or after:
        p = [0] * 8
        p[axis], p[4 + axis] = before, after
        cur = g.op("Pad", x, g.c(f"wm.pads{axis}_{before}_{after}", p, np.int64), g.c("wm.ninf", -np.inf), mode="constant")
    length, span, k = size + before + after, 1, 2 * r + 1
    ax = g.c(f"wm.ax{axis}", [axis], np.int64)
    while span < k:
        shift = min(span, k - span)  # the last step overlaps the window already covered
        head = g.op("Slice", cur, g.c("wm.zero", [0], np.int64), g.c(f"wm.end{axis}_{length - shift}", [length - shift], np.int64), ax)
        tail = g.op("Slice", cur, g.c(f"wm.start{shift}", [shift], np.int64), g.c(f"wm.end{axis}_{length}", [length], np.int64), ax)
        cur, length, span = g.op("Max", head, tail), length - shift, span + shift
    return cur


def _cut(g: Nodes, source: str, window: tuple[str, str, str | None, tuple[str, str, str] | None], light: bool = False) -> str:
    """A tile's window of ``source`` ``(B, C, H, W)``: ``window`` = (its first and its end row and
    column in the frame, clipped to it; the edge padding ``Pad`` adds where the window leaves the
    frame, or None; (the frame's :func:`edge_ring` ``(B, 3, H + 2, W + 2)``, the ring's rows and
    columns the window shows, :meth:`TileLayout.ring_indices`) where it leaves the frame), as a
    cut of the frame edge-padded once, without padding all of it. ``light``: ``source`` is the
    colour, whose padding repeats the ring (a 1 px peak on the edge is not repeated)."""
    starts, ends, edge, ring = window
    if edge is not None and light:
        return g.op("Gather", g.op("Gather", ring[0], ring[1], axis=2), ring[2], axis=3)
    out = g.op("Slice", source, starts, ends, g.c("axes_hw", [2, 3], np.int64))
    return out if edge is None else g.op("Pad", out, edge, mode="edge")


def edge_ring(g: Nodes, source: str, h: int, w: int) -> str:
    """:func:`neuralbokeh.ops.tiles.edge_ring` of the colour ``source`` ``(B, 3, H, W)``, op for op:
    ``(B, 3, H + 2, W + 2)`` of an ``h x w`` frame, the frame in a 1 px ring of its edge pixels,
    each clipped to the larger of its two neighbours along the edge; a corner repeats the end of its row's."""
    def cut(v: str, start: int, end: int, axis: int) -> str:
        return g.op("Slice", v, g.c(f"ring.s{start}", [start], np.int64), g.c(f"ring.e{end}", [end], np.int64),
                    g.c(f"ring.ax{axis}", [axis], np.int64))

    def clipped(v: str, axis: int, n: int) -> str:  # ops.tiles.clip_peaks along ``axis`` (n values)
        if n < 2:
            return v
        before = g.op("Concat", cut(v, 1, 2, axis), cut(v, 0, -1, axis), axis=axis)  # the reflect-padded neighbours
        after = g.op("Concat", cut(v, 1, big, axis), cut(v, -2, -1, axis), axis=axis)
        return g.op("Min", v, g.op("Max", before, after))

    big = 2**62
    top, bottom = (clipped(cut(source, a, b, 2), 3, w) for a, b in ((0, 1), (-1, big)))  # (B, 3, 1, W)
    top, bottom = (g.op("Concat", cut(r, 0, 1, 3), r, cut(r, -1, big, 3), axis=3) for r in (top, bottom))
    left, right = (clipped(cut(source, a, b, 3), 2, h) for a, b in ((0, 1), (-1, big)))  # (B, 3, H, 1)
    return g.op("Concat", top, g.op("Concat", left, source, right, axis=3), bottom, axis=2)


def _pull(g: Nodes, image: str, weight: str, pads: list[int], premultiplied: bool = False) -> tuple[str, str]:
    """One pull step of :func:`neuralbokeh.ops.holes.push_pull_fill`: weight-normalised 2x2
    means and their weight (4 x the mean weight, at most 1); ``pads`` (end side) zero-pads;
    ``premultiplied``: ``image`` is image x weight already."""
    w_small = g.op("AveragePool", weight, kernel_shape=[2, 2], strides=[2, 2], pads=pads, count_include_pad=1)
    product = image if premultiplied else g.op("Mul", image, weight)
    c_small = g.op("Div", g.op("AveragePool", product, kernel_shape=[2, 2], strides=[2, 2], pads=pads,
                               count_include_pad=1), g.op("Max", w_small, g.c("bg.tiny", 1e-12)))
    return c_small, g.op("Min", g.op("Mul", w_small, g.c("bg.four", 4.0)), g.c("bg.one", 1.0))


def _upsample2(g: Nodes, x: str) -> str:
    """x2 bilinear upsampling, half-pixel (``F.interpolate(scale_factor=2, align_corners=False)``)."""
    return g.op("Resize", x, "", g.c("bg.x2", [1.0, 1.0, 2.0, 2.0]), mode="linear", coordinate_transformation_mode="half_pixel")


def _decode(g: Nodes, norm_rgb: str, norm: Normalization) -> str:
    """Linear RGB of normalised RGB: the exact inverse of the normalisation, ``x = s (1 + n) / (1 - n) - o``."""
    one = g.c("one", 1.0)
    return g.op("Sub", g.op("Div", g.op("Mul", g.c("scale", norm.scale), g.op("Add", one, norm_rgb)),
                            g.op("Sub", one, norm_rgb)), g.c("offset", norm.offset))


def conv_rows(g: Nodes, feats: str, weights: np.ndarray, size: int, fp16: bool) -> str:
    """The grouped correlation of ``feats`` ``(B, C G, size, size)`` by ``weights`` ``(C, G, k, k)``
    ('same' size, zero padding), as ``Conv(group=C, pads=k // 2)`` gives it, computed by rows:
    one grouped ``Conv`` correlates each image row with each of the ``k`` kernel rows (``k``
    outputs per channel: a GEMM, where a depthwise ``k x k`` ``Conv`` is a matrix-vector
    product over a ``k^2``-row im2col buffer), then ``Col2Im`` with ``(k, 1)`` blocks adds
    kernel row ``a``'s response ``a - k // 2`` rows up. The same sums in another order: equal to
    float rounding (``tests/test_export.py``), 1.4-2.8x faster on CPU for k = 5-23."""
    c, per_group, k, _ = weights.shape
    p = k // 2
    # output channel c k + j holds kernel row k - 1 - j: Col2Im puts block element j at row r + j - p
    rows = np.ascontiguousarray(weights[:, :, ::-1, :].transpose(0, 2, 1, 3).reshape(c * k, per_group, 1, k))
    x = g.op("Cast", feats, to=TensorProto.FLOAT16) if fp16 else feats
    y = g.op("Conv", x, g.c("w_rows", rows, np.float16 if fp16 else np.float32), group=c, pads=[0, p, 0, p])
    if fp16:
        y = g.op("Cast", y, to=TensorProto.FLOAT)
    cols = g.op("Reshape", y, g.c("cols_shape", [0, c * k, size * size], np.int64))
    return g.op("Col2Im", cols, g.c("rows_hw", [size, size], np.int64), g.c("rows_block", [k, 1], np.int64), pads=[p, 0, p, 0])


def _correlate(g: Nodes, feats: str, weights: np.ndarray, groups: int, size: int, fp16: bool, rows: bool) -> str:
    """The grouped 'same' correlation of ``feats`` ``(B, C G, size, size)`` by ``weights`` ``(C, G, k, k)``
    (``C = groups``): by rows (:func:`conv_rows`) or one ``Conv``, in float16 when ``fp16``."""
    if rows:
        return conv_rows(g, feats, weights, size, fp16)
    p = weights.shape[-1] // 2
    if not fp16:
        return g.op("Conv", feats, g.c("w", weights), group=groups, pads=[p, p, p, p])
    conv = g.op("Conv", g.op("Cast", feats, to=TensorProto.FLOAT16), g.c("w", weights, np.float16), group=groups, pads=[p, p, p, p])
    return g.op("Cast", conv, to=TensorProto.FLOAT)


def _hermite_weights(g: Nodes, pos: str, n: int) -> tuple[str, str]:
    """:func:`~neuralbokeh.core.bands.hermite_weights`, op for op: band ``n``'s (kernel, slope) weights."""
    one = g.c("one", 1.0)
    u = g.op("Sub", pos, g.c(f"n{n}", float(n)))
    au = g.op("Abs", u)
    inside = g.op("Relu", g.op("Sub", one, au))
    sq = g.op("Mul", inside, inside)
    value = g.op("Mul", sq, g.op("Add", one, g.op("Mul", au, g.c("two", 2.0))))
    slope = g.op("Mul", u, sq)
    if n == 1:  # towards band 0 (u < 0): the hat, no slope
        left = g.op("Less", u, g.c("zero", 0.0))
        value = g.op("Where", left, inside, value)
        slope = g.op("Where", left, g.c("zero", 0.0), slope)
    return value, slope


def _pixel_centres(win: int) -> np.ndarray:
    """``(1, win, win, 2)``: the (x, y) of each pixel centre in GridSample's [-1, 1] (align_corners=0)."""
    c = (np.arange(win) * 2.0 + 1.0) / win - 1.0
    return np.stack(np.broadcast_arrays(c[None, :], c[:, None]), axis=-1)[None].astype(np.float32)


def _on_grid(g: Nodes, x: str, scale: int, win: int, warp: tuple[str, float] | None) -> str:
    """:func:`~neuralbokeh.networks.lens._on_grid`, op for op: ``x`` ``(B, C, win, win)`` box-averaged
    onto a grid ``scale`` times coarser, then sampled at ``p - radius x offset`` there (``warp``:
    (the offsets ``(1, 2, win, win)``, the CoC radius), box-averaged as ``x``), or not (None)."""
    n_px = -(-win // scale)
    offsets = None if warp is None else warp[0]
    if scale > 1:
        extra = n_px * scale - win
        pool = dict(kernel_shape=[scale, scale], strides=[scale, scale], pads=[0, 0, extra, extra], count_include_pad=1)
        x = g.op("AveragePool", x, **pool)
        if offsets is not None:
            offsets = g.op("AveragePool", offsets, **pool)
    if warp is None:
        return x
    # flow_warp on this grid: its pixel centres (align_corners=False) minus the flow in its px
    moved = g.op("Mul", g.op("Transpose", offsets, perm=[0, 2, 3, 1]), g.c(f"to_grid{scale}", -2.0 * warp[1] / (scale * n_px)))
    grid = g.op("Add", g.c(f"centres{n_px}", _pixel_centres(n_px)), moved)
    batch = g.op("Concat", g.op("Shape", x, end=1), g.c(f"grid_tail{n_px}", [n_px, n_px, 2], np.int64), axis=0)
    return g.op("GridSample", x, g.op("Expand", grid, batch), mode="bilinear", padding_mode="border", align_corners=0)


def _off_grid(g: Nodes, x: str, scale: int, win: int) -> str:
    """A grid ``scale`` times coarser back to the window's ``(B, C, win, win)`` (bilinear, half-pixel, then cut)."""
    if scale == 1:
        return x
    up = g.op("Resize", x, "", g.c(f"scales{scale}", [1.0, 1.0, float(scale), float(scale)]), mode="linear",
              coordinate_transformation_mode="half_pixel")
    if win % scale == 0:  # the grid covers the window exactly: nothing to cut (a Slice would copy it all)
        return up
    return g.op("Slice", up, g.c("zeros2", [0, 0], np.int64), g.c(f"win2_{win}", [win, win], np.int64), g.c("axes_hw", [2, 3], np.int64))


def _carried_coc(g: Nodes, gate: str, band_coc: float, carry: tuple[float, float, np.ndarray, int, str], win: int,
                 warp: tuple[str, float] | None, rows: bool) -> str:
    """:func:`~neuralbokeh.networks.lens._carried_coc`'s mean signed CoC (px) of a band's sources
    at each receiver ``(B, 1, win, win)``, from the value ``gate`` times (each source's CoC, 1),
    scattered by the green kernel on the carry's grid, where the mean is made. The module carries
    offsets from the band's centre instead (its FFT rounds relative to the largest value); these
    direct sums round relative to their own terms, so the CoC itself saves a node.
    ``carry``: (low, high) the offsets' range in |CoC| (px), the green channel's PSF ``(k, k)``
    binned to that grid, the grid's factor, and the window's (CoC, 1) ``(B, 2, win, win)``. One
    product and one pooling over the window's pixels and the upsampling's write, the rest on the
    coarse grid."""
    lo, hi, kernel, scale, coc_one = carry
    carrier = Nodes(g.b, f"{g.stem}.carry")
    carrier.nodes, g = g.nodes, carrier  # the band's branch: its constants under their own names
    pair = _on_grid(g, g.op("Mul", gate, coc_one), scale, win, warp)
    w = np.stack([kernel, kernel])[:, None, ::-1, ::-1]  # (2, 1, k, k) correlation weights
    # plus the floor's light at the band's centre (mean_source_coc): sum g c + d f, sum g + f
    bias = g.c("carry_bias", np.reshape([band_coc * SOURCE_COC_MIN_COVER, SOURCE_COC_MIN_COVER], (1, 2, 1, 1)))
    # float32 in a float16 export too: dividing by a coverage near the floor magnifies rounding
    out = g.op("Add", _correlate(g, pair, w, 2, -(-win // scale), False, rows), bias)
    carried, cover = (g.b.fresh(f"{g.stem}.split") for _ in range(2))
    g.nodes.append(helper.make_node("Split", [out], [carried, cover], name=carried, axis=1, num_outputs=2))
    lo, hi = sorted(band_coc + band_coc / abs(band_coc) * v for v in (lo, hi))  # the centre plus its offsets, signed as it
    return _off_grid(g, g.op("Clip", g.op("Div", carried, cover), g.c("carry_lo", lo), g.c("carry_hi", hi)), scale, win)


def _band(b: GraphBuilder, k: int, n: int, side: int, pos: str, side_mask: str, src_mask: str, rgb: str, c: str,
          kernel: np.ndarray, flow: tuple[str, np.ndarray] | None, scale: int, win: int, band_coc: float, margin: float,
          fp16: bool, rows: bool, slope: np.ndarray | None = None, warp: tuple[str, float] | None = None,
          gradient: tuple[np.ndarray, tuple[str, str]] | None = None, receiver_slope: str | None = None,
          carry: tuple[float, float, np.ndarray, int, str] | None = None) -> onnx.GraphProto:
    """Then-branch: band ``n``'s contribution ``(1, B, 3, 6, win, win)``, (near, same, far) x (RGB, coverage),
    its convolution on a grid ``scale`` times coarser when ``scale > 1`` (``kernel`` is then
    the binned one, :func:`~neuralbokeh.networks.lens.reduce_kernel`), by rows
    (:func:`conv_rows`) or one depthwise ``Conv``. ``flow``: (the window's colour times this
    side's centroid drift ``(B, 3, win, win)``, the gain's slope ``(3,)``): the colour scattered
    is ``rgb - slope x that`` (:meth:`~neuralbokeh.networks.lens.LensBokeh.colour_gains`); with
    ``gradient``, (the drift alone, the slope): the scattered coverage is divided by ``1 - slope
    x drift`` instead.
    ``slope``: the kernels' slope in the diameter (Hermite blend, ``(2, 3, k, k)`` as
    ``kernel``): each group of the convolution then takes the (kernel, slope) features of one channel.
    ``warp``: (this side's centroid offsets ``(1, 2, win, win)``, the CoC radius (px, signed as
    ``gain_slopes``)): the features are sampled at ``p - radius x offset`` first
    (:func:`~neuralbokeh.networks.lens.flow_warp`, ``model.field_flow``), on the coarse grid
    when ``scale > 1``. ``gradient``: (the kernels' derivative in the source position ``(2, 3,
    k, k)`` (x, y; ``LensBokeh.kernel_gradients``, binned as ``kernel``), the window's pixel
    offsets from the tile's centre, x ``(1, 1, 1, win)`` and y ``(1, 1, win, 1)`` px): two more
    features per channel, the gate times each offset, each scattered by its derivative
    (``model.field_gradient``). ``receiver_slope``: the window's cut of the frame's
    :func:`coc_slope_graph` (``model.occlusion_margin_slope``): each receiver's margin is at
    least it times ``d / 2``. ``carry`` (``model.occlusion_source_coc``): the range (px of |CoC|
    from the band's centre, low and high) of its sources' CoC, the green channel's PSF ``(k,
    k)`` binned to the carry's grid, that grid's factor and the window's (CoC, 1): each source's
    CoC is scattered with its gate there (:func:`_carried_coc`), and the buckets compare the
    receiver with the light's mean source CoC."""
    g = Nodes(GraphBuilder(b.count), f"t{k}.n{n}s{side}")
    # the gradient's features are colour times offsets of up to half a window, whose sums cancel
    # beside a highlight far below float16's precision (a 1e4 highlight missed the 2e-2 parity)
    fp16 = fp16 and gradient is None
    one = g.c("one", 1.0)
    if slope is None:
        weights = [g.op("Relu", g.op("Sub", one, g.op("Abs", g.op("Sub", pos, g.c(f"n{n}", float(n))))))]  # the hat
    else:
        weights = list(_hermite_weights(g, pos, n))
    if flow is not None and gradient is None:
        rgb = g.op("Sub", rgb, g.op("Mul", flow[0], g.c("slope", np.asarray(flow[1]).reshape(1, 3, 1, 1))))
    gates = [g.op("Mul", g.op("Mul", weight, src_mask), side_mask) for weight in weights]
    parts = [g.op("Concat", g.op("Mul", rgb, gate), gate, gate, gate, axis=1) for gate in gates]  # (B, 6, win, win) each
    if gradient is not None:  # the value gate x the pixel's offset from the tile's centre, x and y
        offset_gates = [g.op("Mul", gates[0], offset) for offset in gradient[1]]
        parts += [g.op("Concat", g.op("Mul", rgb, gate), gate, gate, gate, axis=1) for gate in offset_gates]
    if len(parts) == 1:
        feats = parts[0]
    else:  # interleaved per channel, e.g. (kernel, slope): (B, 6, P, win, win) -> (B, 6 P, win, win)
        pair = g.op("Concat", *(g.op("Unsqueeze", f, g.c("ax2", [2], np.int64)) for f in parts), axis=2)
        feats = g.op("Reshape", pair, g.c("pair_shape", [0, 6 * len(parts), win, win], np.int64))
    feats = _on_grid(g, feats, scale, win, warp)
    psfs = [kernel] + ([] if slope is None else [slope]) + ([] if gradient is None else list(gradient[0]))
    w = np.stack([np.concatenate([f, f]) for f in psfs], axis=1)[:, :, ::-1, ::-1]  # (6, P, k, k), correlation weights
    out = _off_grid(g, _correlate(g, feats, w, 6, -(-win // scale), fp16, rows), scale, win)
    ax1 = g.c("ax1", [1], np.int64)
    band = g.c("band_coc", band_coc) if carry is None else _carried_coc(g, gates[0], band_coc, carry, win, warp, rows)
    if flow is not None and gradient is not None:  # the coverage divided by the colour gain at the receiver
        gain = g.op("Sub", one, g.op("Mul", flow[0], g.c("slope", np.asarray(flow[1]).reshape(1, 3, 1, 1))))
        colour_out = g.op("Slice", out, g.c("c0", [0], np.int64), g.c("c3", [3], np.int64), ax1)
        cover_out = g.op("Slice", out, g.c("c3", [3], np.int64), g.c("c6", [6], np.int64), ax1)
        out = g.op("Concat", colour_out, g.op("Div", cover_out, gain), axis=1)
    delta = g.op("Sub", band, c)  # < 0: the band is nearer than the receiver
    zero = g.c("zero", 0.0)
    if receiver_slope is None:
        t = g.op("Mul", delta, g.c("inv_margin", 1.0 / margin))  # in margins
    else:  # one margin per receiver (LensBokeh.tile_accumulators)
        t = g.op("Div", delta, g.op("Max", g.op("Mul", receiver_slope, g.c("half_d", 0.5 * abs(band_coc))), g.c("margin", margin)))
    # bucket_weights' (-delta - m) / m and (delta - m) / m as -t - 1 and t - 1
    near = g.op("Clip", g.op("Sub", g.op("Neg", t), one), zero, one)
    far = g.op("Clip", g.op("Sub", t, one), zero, one)
    same = g.op("Sub", g.op("Sub", one, near), far)
    # one broadcast product (1, B, 3, 1) x (1, B, 1, 6) -> (1, B, 3, 6): written once, and as the
    # branch's output (a Reshape there would be a copy)
    weights = g.op("Unsqueeze", g.op("Concat", near, same, far, axis=1), g.c("ax03", [0, 3], np.int64))
    return _branch(g, g.op("Mul", weights, g.op("Unsqueeze", out, g.c("ax02", [0, 2], np.int64))), f"t{k}_band{n}_{side}")


def source_coc_graph(g: Nodes, colour: str, c: str, norm: Normalization, h: int, w: int) -> str:
    """:func:`~neuralbokeh.networks.lens.source_coc_px` of the frame's normalised ``colour``
    ``(B, 3, H, W)`` and CoC ``c`` ``(B, 1, H, W)`` (px), op for op (``model.highlight_spread``)."""
    y = g.op("Relu", g.op("ReduceMean", _decode(g, colour, norm), g.c("hl.ax1", [1], np.int64), keepdims=1))
    p = g.op("Pad", y, g.c("hl.pads", [0, 0, 1, 1, 0, 0, 1, 1], np.int64), mode="reflect" if min(h, w) > 1 else "edge")

    def three(v: str, axis: int, n: int) -> str:  # the sum of 3 neighbours along ``axis``: rows, then columns
        parts = [g.op("Slice", v, g.c(f"hl.s{i}", [i], np.int64), g.c(f"hl.e{i + n}", [i + n], np.int64),
                      g.c(f"hl.ax{axis}", [axis], np.int64)) for i in range(3)]
        return g.op("Add", g.op("Add", parts[0], parts[1]), parts[2])

    s9 = three(three(p, 2, h), 3, w)
    highlight = g.op("Greater", g.op("Mul", y, g.c("hl.eight", 8.0)), g.op("Mul", g.c("hl.ratio", HIGHLIGHT_RATIO), g.op("Sub", s9, y)))
    c2 = g.op("Mul", c, c)
    fade = g.op("Relu", g.op("Sub", g.c("hl.one", 1.0), g.op("Div", c2, g.c("hl.end2", HIGHLIGHT_SPREAD_END_PX**2))))
    grown2 = g.op("Add", c2, g.op("Mul", g.c("hl.spread", HIGHLIGHT_SPREAD_PX2), fade))
    ratio = g.op("Div", grown2, g.op("Max", c2, g.c("hl.point2", POINT_PX**2)))
    grown = g.op("Mul", c, g.op("Sqrt", ratio))  # core.bands.highlight_coc
    return g.op("Where", highlight, grown, c)


def coc_slope_graph(g: Nodes, c: str, h: int, w: int) -> str:
    """:func:`~neuralbokeh.networks.lens.coc_slope` of the frame's CoC ``(B, 1, h, w)`` (px), op for op."""
    zero = g.c("zero", 0.0)
    parts = []
    for axis, size in ((3, w), (2, h)):
        ax = g.c(f"slope_ax{axis}", [axis], np.int64)
        d = g.op("Sub", g.op("Slice", c, g.c("one_i", [1], np.int64), g.c(f"size{axis}", [size], np.int64), ax),
                 g.op("Slice", c, g.c("zero_i", [0], np.int64), g.c(f"last{axis}", [size - 1], np.int64), ax))
        pad = [0] * 8
        pad[axis] = 1  # before
        before = g.op("Pad", d, g.c(f"slope_before{axis}", pad, np.int64), zero, mode="constant")
        pad = [0] * 8
        pad[4 + axis] = 1  # after
        after = g.op("Pad", d, g.c(f"slope_after{axis}", pad, np.int64), zero, mode="constant")
        agree = g.op("Greater", g.op("Mul", before, after), zero)
        smaller = g.op("Min", g.op("Abs", before), g.op("Abs", after))
        parts.append(g.op("Where", agree, smaller, zero))
    return g.op("Sqrt", g.op("Add", g.op("Mul", parts[0], parts[0]), g.op("Mul", parts[1], parts[1])))


def _tile(b: GraphBuilder, k: int, cut: tuple[str, str, str | None, tuple[str, str, str] | None], kernels: Mapping[int, np.ndarray],
          flow: tuple[str, Mapping[int, np.ndarray]] | None,
          scales: Mapping[int, int], src: np.ndarray, cfg: ModelConfig, contract: Contract, plan: BandPlan, fp16: bool,
          rows: bool, margins: Mapping[int, float], slopes: Mapping[int, np.ndarray] | None = None,
          centroids: tuple[str, np.ndarray, Mapping[int, np.ndarray], np.ndarray] | None = None,
          gradients: tuple[Mapping[int, np.ndarray], np.ndarray] | None = None, coc_slopes: str | None = None,
          carry_kernels: Mapping[int, np.ndarray] | None = None, source_coc: str | None = None) -> onnx.GraphProto:
    """Then-branch: tile ``k``'s accumulators ``(B, 3, 6, win, win)``, flattened to ``(1, B 18 win^2)``,
    from its window of the inputs ``aif`` and ``coc`` (``cut``, :func:`_cut`: a tile that does not
    run cuts nothing); band ``n``, side ``s`` runs where ``band_active[k, n - 1, s]``. A
    band that does not run gives an empty ``(0, B, 3, 6, win, win)``, so the sum over the bands
    costs only the bands that ran. ``flow``: (the centroid drift ``(1, 6, H, W)``,
    ``{n: (2, 3)}`` the gains' slopes) or None (no drift). ``slopes``: ``{n: (2, 3,
    k, k)}`` the kernels' slopes (Hermite blend) or None (hat). ``margins``: ``{n: px}`` each
    band's occlusion margin. ``centroids``: (the pupils' centroid map ``(1, 4, H, W)``, this
    tile's pupils' centroid ``(2, 2)`` (side, x / y), ``{n: (2,)}`` each band's CoC radius per
    side, ``(2,)`` the largest offset over the window per side) for ``model.field_flow``, or
    None; a band and side is warped where radius x offset reaches ``FLOW_MIN_PX``, as the module.
    ``gradients``: (``{n: (2, 2, 3, k, k)}`` (axis, side) the kernels' derivatives in the source
    position, ``(2,)`` the window's top-left corner less the tile's centre (x, y px;
    ``window_offsets_px``)) for ``model.field_gradient``, or None. ``coc_slopes``: the frame's
    :func:`coc_slope_graph` ``(B, 1, H, W)`` (``model.occlusion_margin_slope``), or None.
    ``carry_kernels``: ``{n: (2, k, k)}`` the green PSFs binned to the carried CoC's grid
    (``model.occlusion_source_coc``), or None. ``source_coc``: the frame's :func:`source_coc_graph`
    ``(B, 1, H, W)`` px, whose band each source takes (``model.highlight_spread``), or None (its own CoC)."""
    g = Nodes(GraphBuilder(b.count), f"t{k}")
    blocks, diameters = plan.blocks, plan.diameters
    win = src.shape[-1]
    rgb = _decode(g, _cut(g, "aif", cut, light=True), contract.normalization)
    coc_in = _cut(g, "coc", cut)
    one = g.c("one", 1.0)
    c = g.op("Mul", coc_in, g.c("coc_scale_px", float(contract.coc_scale_px)))
    src_mask = g.c("src", src[None, None])
    if blocks == 0:
        g0, pos = src_mask, None
    else:  # BandPlan.position, op for op
        m = g.op("Max", g.op("Abs", c if source_coc is None else _cut(g, source_coc, cut)), g.c("point", POINT_PX))
        shifted = g.op("Sub", m, g.c("point", POINT_PX))
        if plan.near_px > 0:  # the lattice coordinate's near-focus term
            shifted = g.op("Add", shifted, g.op("Mul", g.op("Sub", one, g.op("Reciprocal", m)), g.c("near_px", plan.near_px)))
        pos = g.op("Min", g.op("Mul", shifted, g.c("inv_step", 1.0 / plan.step_px)), g.c("n_max", float(blocks)))
        g0 = g.op("Mul", g.op("Relu", g.op("Sub", one, pos)), src_mask)
    zeros6 = g.op("Mul", g.op("Concat", rgb, rgb, axis=1), g.c("zero", 0.0))
    base = g.op("Reshape", g.op("Concat", zeros6, g.op("Mul", rgb, g0), g0, g0, g0, zeros6, axis=1),
                g.c("acc_shape", [1, -1, 3, 6, win, win], np.int64))
    parts = [base]
    if pos is not None:
        behind = g.op("Cast", g.op("Greater", c, g.c("zero", 0.0)), to=TensorProto.FLOAT)
        front = g.op("Cast", g.op("Less", c, g.c("zero", 0.0)), to=TensorProto.FLOAT)
        flags = g.op("Gather", "band_active", g.c("index", k, np.int64))  # (N, 2) of this tile
        drift = None if flow is None else _cut(g, flow[0], cut)
        moved = None if flow is None else [  # colour x drift per side; the drift alone for the gradient's coverage
            g.op("Slice", drift, g.c(f"d{s}0", [3 * s], np.int64), g.c(f"d{s}1", [3 * s + 3], np.int64), g.c("ax1", [1], np.int64))
            for s in range(2)]
        if moved is not None and gradients is None:
            moved = [g.op("Mul", rgb, d) for d in moved]
        pixel_offsets = None  # LensBokeh.tile_offsets_px: each window pixel's centre less the tile's, x and y
        if gradients is not None:
            ramp = np.arange(win, dtype=np.float64) + 0.5
            pixel_offsets = (g.c("offset_x", (ramp + gradients[1][0]).reshape(1, 1, 1, win)),
                             g.c("offset_y", (ramp + gradients[1][1]).reshape(1, 1, win, 1)))
        receiver_slope = None if coc_slopes is None else _cut(g, coc_slopes, cut)
        offsets = None
        if centroids is not None:  # LensBokeh.centroid_offsets: each pixel's centroid minus the tile's, per side
            off = g.op("Sub", _cut(g, centroids[0], cut), g.c("centroid", np.reshape(centroids[1], (1, 4, 1, 1))))
            offsets = [g.op("Slice", off, g.c(f"o{s}0", [2 * s], np.int64), g.c(f"o{s}1", [2 * s + 2], np.int64),
                            g.c("ax1", [1], np.int64)) for s in range(2)]
        carries = source_coc_ranges(plan)
        coc_one = None  # the window's (CoC, 1) (B, 2, win, win): each band's carry is its gate times it
        if carry_kernels is not None:
            coc_one = g.op("Concat", c, g.op("Expand", g.c("one4", np.ones((1, 1, 1, 1))), g.op("Shape", c)), axis=1)
        for n in range(1, blocks + 1):
            for side, (mask, sign) in enumerate(((behind, 1.0), (front, -1.0))):
                used = g.op("Gather", g.op("Gather", flags, g.c(f"n{n}_row", n - 1, np.int64)), g.c(f"side{side}", side, np.int64))
                band_flow = None if moved is None else (moved[side], flow[1][n][side])
                then = _band(g.b, k, n, side, pos, mask, src_mask, rgb, c, kernels[n][side], band_flow, scales.get(n, 1), win,
                             sign * float(diameters[n]), margins[n], fp16, rows,
                             None if slopes is None else slopes[n][side],
                             None if offsets is None or abs(centroids[2][n][side]) * centroids[3][side] < FLOW_MIN_PX
                             else (offsets[side], float(centroids[2][n][side])),
                             None if gradients is None else (gradients[0][n][:, side], pixel_offsets), receiver_slope,
                             None if carry_kernels is None else
                             (*carries[n], carry_kernels[n][side], scales.get(n, 1) * cfg.occlusion_source_coc_grid, coc_one))
                skip = Nodes(GraphBuilder(g.b.count), f"t{k}.n{n}s{side}.skip")
                empty = skip.op("Slice", base, skip.c("s0", [0], np.int64), skip.c("s0", [0], np.int64), skip.c("ax0", [0], np.int64))
                else_graph = _branch(skip, empty, f"t{k}_band{n}_{side}_skip")
                g.b.count = max(g.b.count, skip.b.count) + 1
                parts.append(g.op("If", used, then_branch=then, else_branch=else_graph))
    if len(parts) > 1:
        # the sum of the parts that ran as a (1, P) x (P, N) MatMul with ones: ~3x faster on CPU
        # than onnxruntime's ReduceSum over axis 0
        stacked = g.op("Reshape", g.op("Concat", *parts, axis=0), g.c("flat", [0, -1], np.int64))
        count = g.op("Concat", g.c("one_i", [1], np.int64), g.op("Shape", stacked, end=1), axis=0)
        ones = g.op("ConstantOfShape", count, value=helper.make_tensor("one", TensorProto.FLOAT, [1], [1.0]))
        return _branch(g, g.op("MatMul", ones, stacked), f"t{k}_network")  # the output as it is made: no copy
    return _branch(g, g.op("Reshape", base, g.c("flat1", [1, -1], np.int64)), f"t{k}_network")


def _idle(b: GraphBuilder, k: int, win: int) -> onnx.GraphProto:
    """Else-branch of tile ``k``: zeros in place of its accumulators (a memset: a neighbour's core
    sums them; its own core takes its pass-through instead, :func:`_window_light`)."""
    g = Nodes(GraphBuilder(b.count), f"t{k}.idle")
    batch = g.op("Shape", "aif", start=0, end=1)
    shape = g.op("Concat", g.c("one_i", [1], np.int64), g.op("Mul", batch, g.c("per_image", [18 * win * win], np.int64)), axis=0)
    return _branch(g, g.op("ConstantOfShape", shape, value=helper.make_tensor("zero", TensorProto.FLOAT, [1], [0.0])), f"t{k}_idle")


def _multi_branch(g: Nodes, results: list[str], name: str) -> onnx.GraphProto:
    """A branch of ``g``'s nodes with several outputs (an ``Identity`` only for a result the
    branch does not compute itself: onnxruntime copies a tensor there)."""
    made = {o for node in g.nodes for o in node.output}
    finals = [r if r in made and r not in results[:i] else g.op("Identity", r) for i, r in enumerate(results)]
    return helper.make_graph(g.nodes, name, [], [_out(f) for f in finals], g.b.initializers)


def _cut_cells(g: Nodes, acc: str, origin: tuple[int, int], cells: list[tuple[int, int, int, int]]) -> list[str]:
    """``cells`` (image px ``(r0, r1, c0, c1)``) of a window's accumulators ``acc`` ``(B, 18, win, win)``
    whose top-left lies at image px ``origin``: ``(B, 18, h, w)`` each."""
    axes = g.c("axes_hw", [2, 3], np.int64)
    return [g.op("Slice", acc, g.c(f"s{r0 - origin[0]}_{c0 - origin[1]}", [r0 - origin[0], c0 - origin[1]], np.int64),
                 g.c(f"e{r1 - origin[0]}_{c1 - origin[1]}", [r1 - origin[0], c1 - origin[1]], np.int64), axes)
            for r0, r1, c0, c1 in cells]


def _window_light(g: Nodes, k: int, idx: int, origin: tuple[int, int], cells: list[tuple[int, int, int, int]],
                  acc: str, core: tuple[int, int, int, int], contract: Contract) -> list[str]:
    """Window ``idx``'s accumulators ``(B, 18, h, w)`` on ``cells`` (image px ``(r0, r1, c0, c1)``) of
    core ``k`` (``core``), cut from its output ``acc`` ``(B, 18, win, win)`` (its top-left at image px ``origin``;
    zeros where the tile did not run). The core's own window is an ``If`` on ``tile_active[k]``:
    where the tile did not run, its core of the input ``aif`` as in-focus light (the same
    bucket: colour and full cover), as the module's pass-through."""
    if idx != k:
        return _cut_cells(g, acc, origin, cells)
    on = Nodes(GraphBuilder(g.b.count), f"c{k}.own")
    cut = _cut_cells(on, acc, origin, cells)
    off = Nodes(GraphBuilder(on.b.count), f"c{k}.own.off")
    y0, y1, x0, x1 = core
    axes = off.c("axes_hw", [2, 3], np.int64)
    norm_rgb = off.op("Slice", "aif", off.c("start", [y0, x0], np.int64), off.c("stop", [y1, x1], np.int64), axes)
    rgb = _decode(off, norm_rgb, contract.normalization)
    ones = off.op("Add", off.op("Mul", norm_rgb, off.c("zero", 0.0)), off.c("one", 1.0))
    zeros6 = off.op("Mul", off.op("Concat", rgb, rgb, axis=1), off.c("zero", 0.0))
    sharp = off.op("Concat", zeros6, rgb, ones, zeros6, axis=1)
    light = [off.op("Slice", sharp, off.c(f"s{r0 - y0}_{c0 - x0}", [r0 - y0, c0 - x0], np.int64),
                    off.c(f"e{r1 - y0}_{c1 - x0}", [r1 - y0, c1 - x0], np.int64), axes) for r0, r1, c0, c1 in cells]
    then, other = _multi_branch(on, cut, f"c{k}_own"), _multi_branch(off, light, f"c{k}_own_off")
    outs = [off.b.fresh(f"c{k}.own.light") for _ in cells]
    g.b.count = off.b.count + 1
    cond = g.op("Gather", "tile_active", g.c(f"index{idx}", idx, np.int64))
    g.nodes.append(helper.make_node("If", [cond], outs, name=outs[0], then_branch=then, else_branch=other))
    return outs


def _surface_filled(g: Nodes, background: str, keep: str | None, bound: str, colors: list[str], covers: list[str],
                    share: float) -> str:
    """``LensBokeh.surface_filled``: where a pixel hides nothing and none within ``SILHOUETTE_PX``
    does (``keep`` 1, :func:`fill_inputs`), ``share`` of its fill is the mean colour of the same
    and far buckets, at most ``bound`` (the estimate's bound on the pixel's own colour), the
    ``background`` estimate the rest."""
    eps = g.c("surface_eps", SURFACE_FILL_EPS)
    num = g.op("Add", g.op("Add", colors[1], colors[2]), g.op("Mul", background, eps))
    own = g.op("Div", num, g.op("Add", g.op("Add", covers[1], covers[2]), eps))
    own = g.op("Min", own, bound)
    share_c = g.c("surface_share", share)
    weight = share_c if keep is None else g.op("Mul", keep, share_c)
    return g.op("Add", background, g.op("Mul", weight, g.op("Sub", own, background)))


def fill_inputs(top: Nodes, cfg: ModelConfig, contract: Contract, plan: BandPlan,
                surface_share: float | None) -> FillParts | None:
    """The frame-wide part of the fill (:func:`hidden_parts`, as ``LensBokeh.hidden``), under an
    ``If``: only a core that a running window reaches reads the fill, so with no tile running it
    is not computed. None for ``fill = "normalize"``. Each core computes its own part of the
    rest (:func:`core_fill`)."""
    if (surface_share is not None) != (cfg.surface_fill and cfg.fill != "normalize"):
        raise ValueError(f"model.surface_fill is {cfg.surface_fill} with fill {cfg.fill!r}: its share is needed there and only there")
    if cfg.fill == "normalize":
        return None
    g = Nodes(GraphBuilder(top.b.count), "fill")
    parts = hidden_parts(g, "aif", "coc", contract, plan.fill_radius_px)
    results = [t for t in parts if t is not None]
    then = _multi_branch(g, results, "fill")
    none = Nodes(GraphBuilder(g.b.count), "fill.none")
    other = _multi_branch(none, [none.c("zero", 0.0) for _ in results], "fill_none")
    top.b.count = none.b.count + 1
    anyone = top.op("Cast", top.op("ReduceMax", top.op("Cast", "tile_active", to=TensorProto.INT32), keepdims=0), to=TensorProto.BOOL)
    outs = [top.b.fresh("g.fill") for _ in results]
    top.nodes.append(helper.make_node("If", [anyone], outs, name=outs[0], then_branch=then, else_branch=other))
    given = iter(outs)
    return FillParts(*(None if t is None else next(given) for t in parts))


def _composite_buckets(g: Nodes, canvas: str, cfg: ModelConfig, fill: tuple[str, str | None, str] | None,
                       fill_gain: float | None, surface_share: float | None = None) -> str:
    """The reassembled light ``(B, 18, h, w)`` (near / same / far buckets of colour and cover)
    of a part of the frame composited front to back, and what they leave uncovered filled: linear
    RGB ``(B, 3, h, w)`` (``LensBokeh.composite``; ``fill``: :func:`fill_inputs` on the same
    part; ``fill_gain``: its learned gain with ``fill = "far_light"``; ``surface_share``:
    ``LensBokeh.surface_fill_share()`` with ``model.surface_fill``)."""
    one, zero, eps = g.c("one", 1.0), g.c("zero", 0.0), g.c("eps", _EPS)
    ax1 = g.c("ax1", [1], np.int64)
    buckets = [g.op("Slice", canvas, g.c(f"b{q}c0", [6 * q], np.int64), g.c(f"b{q}c2", [6 * q + 6], np.int64), ax1)
               for q in range(3)]
    out = taken = None
    colors, covers = [], []
    for q in range(3):
        color = g.op("Slice", buckets[q], g.c("c0", [0], np.int64), g.c("c3", [3], np.int64), ax1)
        cover = g.op("Max", g.op("Slice", buckets[q], g.c("c3", [3], np.int64), g.c("c6", [6], np.int64), ax1), zero)
        colors.append(color)
        covers.append(cover)
        room = one if taken is None else g.op("Sub", one, taken)
        lit = g.op("Mul", color, g.op("Min", one, g.op("Div", room, g.op("Max", cover, eps))))
        out = lit if out is None else g.op("Add", out, lit)
        # saturated is exactly 1 (taken + cover * frac can round to 1 - ulp, leaking a 1e4 highlight behind)
        taken = g.op("Min", cover if taken is None else g.op("Add", taken, cover), one)
    if fill is None:
        return g.op("Max", g.op("Div", out, g.op("Max", taken, eps)), zero)
    hole = g.op("Max", g.op("Sub", one, taken), zero)
    background, keep, bound = fill
    if surface_share is not None:
        background = _surface_filled(g, background, keep, bound, colors, covers, surface_share)
    if cfg.fill == "background":
        return g.op("Max", g.op("Add", out, g.op("Mul", hole, background)), zero)
    if fill_gain is None:
        raise ValueError("a far_light fill needs the network's fill_gain")
    # far_light_fill: min(hole / cover, gain) colour + (hole - min(hole, gain cover)) background, of the far bucket
    gain = g.c("fill_gain", float(fill_gain))
    far = g.op("Mul", g.op("Min", g.op("Div", hole, g.op("Max", cover, eps)), gain), color)
    rest = g.op("Sub", hole, g.op("Min", hole, g.op("Mul", gain, cover)))
    return g.op("Max", g.op("Add", g.op("Add", out, far), g.op("Mul", rest, background)), zero)


def core_cells(i: int, n: int, start: int, end: int, core: int, overlap: int) -> list[tuple[int, int, list[tuple[int, int]]]]:
    """Along one axis, core ``i`` of ``n``, the image interval ``[start, end)``: its cells
    ``(u, v, [(i', origin)])``, each ``[u, v)`` covered whole by the windows ``i'`` (of cores
    ``i - 1 .. i + 1``; window ``i'`` starts at image px ``origin = i' core - overlap``).

    Raises:
        ValueError: ``2 overlap > core`` (a window would reach beyond its neighbours' cores).
    """
    if not 0 <= 2 * overlap <= core:
        raise ValueError(f"tile overlap must be 0 to half the core ({core} px), got {overlap} px")
    near = [(m, m * core - overlap) for m in range(max(0, i - 1), min(n, i + 2))]
    cuts = sorted({start, end} | {e for m, o in near for e in (o, o + core + 2 * overlap) if start < e < end})
    return [(u, v, [(m, o) for m, o in near if o <= u and v <= o + core + 2 * overlap]) for u, v in zip(cuts, cuts[1:])]


def _core(top: Nodes, layout: Any, k: int, accs: list[str], fill: FillParts | None,
          cfg: ModelConfig, contract: Contract, fill_gain: float | None, surface_share: float | None) -> str:
    """Core ``k`` of the output, normalised ``(B, 3, h_k, w_k)`` (its :meth:`TileLayout.source_region`): an ``If``
    on whether a window that reaches it ran. Then its light is the sum of those windows'
    accumulators (``accs``: each tile's ``(B, 18, win, win)``) over it, cell by cell (:func:`core_cells`,
    :func:`_window_light`), composited and encoded there; else it is the input ``x``, unchanged:
    no window scatters light into it but its own pass-through. The overlap-add, the composite
    and the encoding cost only the cores a frame's blur reaches."""
    h, w = contract.size
    i, j = divmod(k, layout.cols)
    r0, r1, c0, c1 = layout.source_region(k, h, w)
    rows = core_cells(i, layout.rows, r0, r1, layout.core, layout.overlap)
    cols = core_cells(j, layout.cols, c0, c1, layout.core, layout.overlap)
    g = Nodes(GraphBuilder(top.b.count), f"c{k}")
    # the windows that reach the core, (index, origin) along each axis
    row_windows, col_windows = (sorted({w for _, _, over in cells for w in over}) for cells in (rows, cols))
    terms: dict[tuple[int, int], list[str]] = {}
    for m, oy in row_windows:
        for n, ox in col_windows:
            cells = [(a, e) for a, (_, _, over) in enumerate(rows) if (m, oy) in over
                     for e, (_, _, over_c) in enumerate(cols) if (n, ox) in over_c]
            spans = [(rows[a][0], rows[a][1], cols[e][0], cols[e][1]) for a, e in cells]
            idx = m * layout.cols + n
            for cell, light in zip(cells, _window_light(g, k, idx, (oy, ox), spans, accs[idx], (r0, r1, c0, c1), contract)):
                terms.setdefault(cell, []).append(light)
    strips = []
    for a in range(len(rows)):
        cells = [terms[a, e][0] if len(terms[a, e]) == 1 else g.op("Sum", *terms[a, e]) for e in range(len(cols))]
        strips.append(cells[0] if len(cells) == 1 else g.op("Concat", *cells, axis=3))
    canvas = strips[0] if len(strips) == 1 else g.op("Concat", *strips, axis=2)
    part = None if fill is None else core_fill(g, fill, (r0, r1, c0, c1), (h, w), surface_share is not None)
    linear = _composite_buckets(g, canvas, cfg, part, fill_gain, surface_share)
    shifted = g.op("Add", linear, g.c("offset", float(contract.normalization.offset)))
    scale = g.c("scale", float(contract.normalization.scale))
    then = _branch(g, g.op("Div", g.op("Sub", shifted, scale), g.op("Add", shifted, scale)), f"core{k}")
    rest = Nodes(GraphBuilder(g.b.count), f"c{k}.pass")
    sharp = rest.op("Slice", "aif", rest.c("start", [r0, c0], np.int64), rest.c("stop", [r1, c1], np.int64),
                    rest.c("axes_hw", [2, 3], np.int64))
    black = float(contract.normalization.encode(np.float64(0.0)))  # the composite clamps light below 0; encoding keeps order
    other = _branch(rest, rest.op("Max", sharp, rest.c("black", black)), f"core{k}_pass")
    b = top.b
    b.count = rest.b.count + 1
    reach = [top.op("Gather", "tile_active", b.const(f"t{m * layout.cols + n}.index", m * layout.cols + n, np.int64))
             for m, _ in row_windows for n, _ in col_windows]
    cond = reach[0]
    for r in reach[1:]:
        cond = top.op("Or", cond, r)
    return top.op("If", cond, then_branch=then, else_branch=other)


def build_lens_graph(kernels: Mapping[int, np.ndarray], plan: BandPlan, cfg: ModelConfig, contract: Contract,
                     fp16: bool = False, opset: int = 18, metadata: Mapping[str, str] | None = None,
                     scales: Mapping[int, int] | None = None, rows: bool = False,
                     flow: tuple[tuple[np.ndarray, np.ndarray, np.ndarray], Mapping[int, np.ndarray]] | None = None,
                     fill_gain: float | None = None, slopes: Mapping[int, np.ndarray] | None = None,
                     surface_share: float | None = None, *, margins: Mapping[int, float],
                     centroids: tuple[tuple[np.ndarray, np.ndarray, np.ndarray], np.ndarray, Mapping[int, np.ndarray],
                                      np.ndarray] | None = None,
                     gradients: Mapping[int, np.ndarray] | None = None,
                     carry_kernels: Mapping[int, np.ndarray] | None = None) -> onnx.ModelProto:
    """The full-image ONNX model of a ``LensBokeh``.

    Args:
        kernels: ``{n: (tiles, 2, 3, k, k)}`` point-spread functions of block n (side 0 behind,
            1 in front), as ``LensBokeh.kernels`` returns them for the plate's tiles, or binned by
            ``reduce_kernel`` for the bands that ``scales`` reduces.
        plan: the bands (their lattice and centres, how a CoC falls in them) and the fill's
            reach, as ``LensBokeh.plan`` gives them for the plate's largest CoC.
        cfg, contract: the network's config and data contract (its tile grid, normalisation
            and CoC scale).
        fp16: float16 convolutions. opset: >= 18 (``Col2Im``). metadata: ``metadata_props``.
        scales: ``{n: s}`` band n convolved on a grid s times coarser (default: all 1, direct).
        rows: the band convolutions as row GEMMs (:func:`conv_rows`; exact to float
            rounding, faster) instead of depthwise ``Conv`` nodes.
        flow: the cat-eye's flow of light (``LensBokeh.drift_lattice`` and ``colour_gains``):
            ``((nodes (2, 3, Gy, Gx), rows (H, Gy), cols (W, Gx)), {n: (2, 3)} slopes)``; band n's
            scattered colour at pixel (i, j) is multiplied by ``1 - slope x drift``, the drift
            ``rows[i] . nodes . cols[j]``. None: no drift (gains 1).
        fill_gain: ``LensBokeh.far_light_gain()`` (``fill = "far_light"`` only), > 0.
        surface_share: ``LensBokeh.surface_fill_share()`` (``model.surface_fill`` with a
            ``"background"`` or ``"far_light"`` fill only), in (0, 1).
        margins: ``{n: px}`` band n's occlusion margin, ``LensBokeh.occlusion_margin``.
        slopes: ``band_blend = "hermite"`` only: ``{n: (tiles, 2, 3, k, k)}`` the kernels' slopes
            in the diameter times the lattice step (``LensBokeh.kernel_slopes``), binned as
            ``kernels``.
        centroids: ``model.field_flow`` only (else None): ``((nodes (2, 2, Gy, Gx), rows (H, Gy),
            cols (W, Gx)) of LensBokeh.centroid_lattice, (tiles, 2, 2) each tile's pupils'
            centroid, {n: (2,)} band n's CoC radius per side, signed as gain_slopes, (tiles, 2)
            the largest offset (aperture radii) over each tile's window per side)``.
        gradients: ``model.field_gradient`` only (else None): ``{n: (tiles, 2, 2, 3, k, k)}``
            LensBokeh.kernel_gradients, binned as kernels; each source pixel's offset from its
            tile's centre (``LensBokeh.tile_offsets_px``) is made in the graph.
        carry_kernels: ``model.occlusion_source_coc`` only (else None): ``{n: (tiles, 2, k, k)}``
            the green channel's kernels binned by ``reduce_kernel`` to the carried CoC's grid,
            ``model.occlusion_source_coc_grid`` times coarser than band n's.
    """
    if opset < 18:
        raise ValueError(f"the lens graph needs opset >= 18 (Col2Im), got {opset}")
    if (slopes is not None) != (cfg.band_blend == "hermite"):
        raise ValueError(f"model.band_blend is {cfg.band_blend!r}: kernel slopes are needed for 'hermite' and only there")
    if (carry_kernels is not None) != cfg.occlusion_source_coc:
        raise ValueError(f"model.occlusion_source_coc is {cfg.occlusion_source_coc}: its kernels are needed then and only then")
    scales = dict(scales or {})
    layout = cfg.layout(*contract.size)
    source_masks = layout.source_masks()
    h, w = contract.size
    win, n_t = layout.window, layout.num_tiles
    b = GraphBuilder()
    top = Nodes(b, "g")
    pad_t, _, pad_l, _ = layout.pads(h, w)
    drift = None
    if flow is not None:  # the drift at every pixel, rows (H, Gy) x nodes (6, Gy, Gx) x cols^T (each tile cuts its window, as the input's)
        nodes, rows_w, cols_w = flow[0]
        at_rows = top.op("MatMul", b.const("drift_rows", rows_w), b.const("drift_nodes", np.reshape(nodes, (6, *nodes.shape[-2:]))))
        full = top.op("MatMul", at_rows, b.const("drift_cols_t", np.transpose(cols_w)))  # (6, H, W)
        drift = top.op("Unsqueeze", full, b.const("ax0", [0], np.int64))
    centroid_map = None
    if centroids is not None:  # as the drift: the centroid at every pixel from its lattice
        nodes, rows_w, cols_w = centroids[0]
        at_rows = top.op("MatMul", b.const("centroid_rows", rows_w), b.const("centroid_nodes", np.reshape(nodes, (4, *nodes.shape[-2:]))))
        full = top.op("MatMul", at_rows, b.const("centroid_cols_t", np.transpose(cols_w)))  # (4, H, W)
        centroid_map = top.op("Unsqueeze", full, b.const("ax0", [0], np.int64))
    coc_slopes = None
    if cfg.occlusion_margin_slope:  # of the whole frame, each tile cuts its window (LensBokeh.tile_accumulators)
        coc_slopes = coc_slope_graph(top, top.op("Mul", "coc", top.c("coc_scale_px", float(contract.coc_scale_px))), h, w)
    source_coc = None
    if cfg.highlight_spread and plan.blocks:  # of the whole frame: a highlight is found among its neighbours in any tile
        source_coc = source_coc_graph(top, "aif", top.op("Mul", "coc", top.c("coc_scale_px", float(contract.coc_scale_px))),
                                      contract.normalization, h, w)
    corners = window_offsets_px(layout, h, w)
    ring = edge_ring(top, "aif", h, w) if any(layout.pads(h, w)) else None
    ring_rows, ring_cols = layout.ring_indices(h, w)
    placed = []
    for k, r, c in layout.origins():
        y0, x0 = r - pad_t, c - pad_l  # the window in frame px; the edge pads it where it leaves the frame
        top_e, left_e, bottom_e, right_e = max(-y0, 0), max(-x0, 0), max(y0 + win - h, 0), max(x0 + win - w, 0)
        edge = [0, 0, top_e, left_e, 0, 0, bottom_e, right_e]
        cut = (b.const(f"t{k}.starts", [y0 + top_e, x0 + left_e], np.int64),
               b.const(f"t{k}.ends", [y0 + win - bottom_e, x0 + win - right_e], np.int64),
               b.const(f"t{k}.edge", edge, np.int64) if any(edge) else None,
               (ring, b.const(f"t{k}.ring_rows", ring_rows[r : r + win], np.int64),
                b.const(f"t{k}.ring_cols", ring_cols[c : c + win], np.int64)) if any(edge) else None)
        cond = top.op("Gather", "tile_active", b.const(f"t{k}.index", k, np.int64))
        tile_kernels = {n: kernels[n][k] for n in kernels}
        tile_flow = None if drift is None else (drift, flow[1])
        tile_slopes = None if slopes is None else {n: slopes[n][k] for n in slopes}
        tile_centroids = None if centroid_map is None else (centroid_map, centroids[1][k], centroids[2], centroids[3][k])
        tile_gradients = None if gradients is None else ({n: gradients[n][k] for n in gradients}, corners[k])
        tile_carry = None if carry_kernels is None else {n: v[k] for n, v in carry_kernels.items()}
        then = _tile(b, k, cut, tile_kernels, tile_flow, scales, source_masks[k], cfg, contract, plan, fp16, rows, margins, tile_slopes,
                     tile_centroids, tile_gradients, coc_slopes, tile_carry, source_coc)
        b.count += 10_000  # branch-local names stay unique across branches
        other = _idle(b, k, win)
        b.count += 10_000
        placed.append(top.op("If", cond, then_branch=then, else_branch=other))  # (1, B 18 win^2)
    # each core of the output from the windows that reach it (_core): no frame-wide overlap-add
    accs = [top.op("Reshape", p, b.const("acc4_shape", [-1, 18, win, win], np.int64)) for p in placed]
    fill = fill_inputs(top, cfg, contract, plan, surface_share)
    strips = []
    for i in range(layout.rows):
        cores = [_core(top, layout, i * layout.cols + j, accs, fill, cfg, contract, fill_gain, surface_share)
                 for j in range(layout.cols)]
        strips.append(cores[0] if len(cores) == 1 else top.op("Concat", *cores, axis=3))
    frame = strips[0] if len(strips) == 1 else top.op("Concat", *strips, axis=2)
    top.nodes.append(helper.make_node("Identity", [frame], ["defocus"], name="defocus"))
    if plan.blocks != cfg.blocks:
        raise ValueError(f"the plan has {plan.blocks} bands, the network {cfg.blocks}")
    extra = [helper.make_tensor_value_info("band_active", TensorProto.BOOL, [n_t, max(plan.blocks, 1), 2])]
    return finish_model(top.nodes, b.initializers, "neuralbokeh_lens", (h, w), n_t, opset, metadata, extra)

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

The windows' accumulators ((near, same, far) x (RGB, coverage)) are stacked and overlap-added in one ``Col2Im`` (opset 18), then
composited near over far with sum-to-saturation, the coverage left short filled with the
hidden-background estimate (a visible pixel's with its own surface's blurred light first, for
``model.surface_fill``; or normalised, for ``fill = "normalize"``) and encoded, as
``LensBokeh.forward`` does. ``fp16`` runs the convolutions in float16 (inputs and kernels);
gates, buckets and the composite stay float32.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

import numpy as np
import onnx
from onnx import TensorProto, helper

from ..core.bands import POINT_PX, BandPlan
from ..core.contract import Contract
from ..core.normalization import Normalization
from ..core.tiling import pyramid_levels
from ..networks.config import SILHOUETTE_PX, SURFACE_FILL_EPS, ModelConfig
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


def hidden_background_graph(top: Nodes, x: str, contract: Contract, r: int) -> tuple[str, str | None, str]:
    """``(B, 3, H, W)`` linear estimate of what foregrounds hide, ``(B, 1, H, W)`` float, 1 where
    a pixel hides nothing (None: no pixel hides anything), and the estimate's bound on a visible
    pixel's own colour (``ops.holes.hidden_estimate``), as ``LensBokeh.hidden``:
    occluders by a separable max over ``2r + 1`` px (``r``: the plan's ``fill_radius_px``), then
    (:func:`neuralbokeh.ops.holes.hidden_background`) the pull-push fill of the log of the light
    on the zero-padded ``2^L`` square (``AveragePool`` 2x2, ``Resize`` x2 half-pixel), whose
    level 0 is never padded nor upsampled beyond the image (the same values, ~2x less work at
    1080p), and each visible pixel's own colour clamped by its 3 x 3 geometric mean."""
    h, w = contract.size
    _, rgb = _linear_rgb(top, x, contract.normalization)
    coc = top.op("Mul", top.op("Slice", x, top.c("bg.s3", [3], np.int64), top.c("bg.s4", [4], np.int64), top.c("bg.ax1", [1], np.int64)),
                 top.c("bg.coc_scale", float(contract.coc_scale_px)))
    if r == 0:
        return rgb, None, rgb  # nothing can hide anything: the fill is the AIF itself
    far = window_max(top, window_max(top, coc, r, 3, w), r, 2, h)  # rows, then columns (as ops.holes.occluders)
    hide = top.op("Less", coc, top.op("Sub", far, top.c("bg.jump", JUMP_PX)))
    near = window_max(top, window_max(top, coc, 1, 3, w), 1, 2, h)  # the 3 x 3 neighbours
    hide = top.op("Or", hide, top.op("Less", coc, top.op("Sub", near, top.c("bg.step", STEP_PX))))
    keep = top.op("Cast", top.op("Not", hide), to=TensorProto.FLOAT)
    log_rgb = top.op("Log", top.op("Add", top.op("Max", rgb, top.c("bg.zero", 0.0)), top.c("bg.log_offset", LOG_OFFSET)))
    # the pyramid of push_pull_fill on the zero-padded 2^L square, with level 0 left unpadded:
    # its 2x2 means over the padding are 0 with weight 0, as padding level 1 with zeros gives
    side = 1 << pyramid_levels(h, w)
    if side < 2:
        return rgb, keep, rgb  # one pixel: nothing stands in front of anything
    image, weight = _pull(top, log_rgb, keep, [0, 0, h % 2, w % 2])
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
    # level 0 needs rows < h of the x2 upsampling: those read level 1's rows <= h // 2 only
    need = top.c("bg.need", [min(h // 2 + 1, side // 2), min(w // 2 + 1, side // 2)], np.int64)
    up = _upsample2(top, top.op("Slice", filled, top.c("bg.start", [0, 0], np.int64), need, top.c("bg.axes", [2, 3], np.int64)))
    up = top.op("Slice", up, top.c("bg.start", [0, 0], np.int64), top.c("bg.end", [h, w], np.int64), top.c("bg.axes", [2, 3], np.int64))
    behind = top.op("Sub", top.op("Exp", up), top.c("bg.log_offset", LOG_OFFSET))
    # visible pixels: their own colour, at most OUTLIER_RATIO x the geometric mean of their visible 3 x 3
    # (count_include_pad=0 divides both sums by the same count: their ratio is the mean over visible pixels)
    num = top.op("AveragePool", top.op("Mul", log_rgb, keep), kernel_shape=[3, 3], pads=[1, 1, 1, 1], count_include_pad=0)
    den = top.op("AveragePool", keep, kernel_shape=[3, 3], pads=[1, 1, 1, 1], count_include_pad=0)
    level = top.op("Exp", top.op("Div", num, top.op("Max", den, top.c("bg.tiny", 1e-12))))
    bound = top.op("Sub", top.op("Mul", level, top.c("bg.outlier", OUTLIER_RATIO)), top.c("bg.log_offset", LOG_OFFSET))
    own = top.op("Min", rgb, bound)
    return top.op("Add", top.op("Mul", keep, own), top.op("Mul", top.op("Sub", top.c("bg.one", 1.0), keep), behind)), keep, bound


def window_max(g: Nodes, x: str, r: int, axis: int, size: int) -> str:
    """The max of ``x`` over ``[i - r, i + r]`` along ``axis`` (2 or 3, ``size`` long), nothing
    beyond the edges: as ``MaxPool`` with a ``2r + 1`` window and ``r`` of padding, exactly, but
    as ``log2(2r + 1)`` maxima of two shifted ``Slice``s (-inf padded): ``m[i]`` holds the max of
    ``x[i .. i + span - 1]``, doubled until ``span`` reaches ``2r + 1``. ~3x faster on CPU at
    r = 21 (onnxruntime's ``MaxPool`` reads the whole window for every pixel)."""
    pads = [0] * 8
    pads[axis] = pads[4 + axis] = r
    cur = g.op("Pad", x, g.c(f"wm.pads{axis}_{r}", pads, np.int64), g.c("wm.ninf", -np.inf), mode="constant")
    length, span, k = size + 2 * r, 1, 2 * r + 1
    ax = g.c(f"wm.ax{axis}", [axis], np.int64)
    while span < k:
        shift = min(span, k - span)  # the last step overlaps the window already covered
        head = g.op("Slice", cur, g.c("wm.zero", [0], np.int64), g.c(f"wm.end{axis}_{length - shift}", [length - shift], np.int64), ax)
        tail = g.op("Slice", cur, g.c(f"wm.start{shift}", [shift], np.int64), g.c(f"wm.end{axis}_{length}", [length], np.int64), ax)
        cur, length, span = g.op("Max", head, tail), length - shift, span + shift
    return cur


def _pull(g: Nodes, image: str, weight: str, pads: list[int]) -> tuple[str, str]:
    """One pull step of :func:`neuralbokeh.ops.holes.push_pull_fill`: weight-normalised 2x2
    means and their weight (4 x the mean weight, at most 1); ``pads`` (end side) zero-pads."""
    w_small = g.op("AveragePool", weight, kernel_shape=[2, 2], strides=[2, 2], pads=pads, count_include_pad=1)
    c_small = g.op("Div", g.op("AveragePool", g.op("Mul", image, weight), kernel_shape=[2, 2], strides=[2, 2], pads=pads,
                               count_include_pad=1), g.op("Max", w_small, g.c("bg.tiny", 1e-12)))
    return c_small, g.op("Min", g.op("Mul", w_small, g.c("bg.four", 4.0)), g.c("bg.one", 1.0))


def _upsample2(g: Nodes, x: str) -> str:
    """x2 bilinear upsampling, half-pixel (``F.interpolate(scale_factor=2, align_corners=False)``)."""
    return g.op("Resize", x, "", g.c("bg.x2", [1.0, 1.0, 2.0, 2.0]), mode="linear", coordinate_transformation_mode="half_pixel")


def _linear_rgb(g: Nodes, window: str, norm: Normalization) -> tuple[str, str]:
    """``(normalised RGB, linear RGB)`` of a window ``(B, 4, win, win)``: the exact inverse of
    the normalisation, ``x = s (1 + n) / (1 - n) - o``."""
    one = g.c("one", 1.0)
    norm_rgb = g.op("Slice", window, g.c("s0", [0], np.int64), g.c("s3", [3], np.int64), g.c("ax1", [1], np.int64))
    rgb = g.op("Sub", g.op("Div", g.op("Mul", g.c("scale", norm.scale), g.op("Add", one, norm_rgb)),
                           g.op("Sub", one, norm_rgb)), g.c("offset", norm.offset))
    return norm_rgb, rgb


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


def _band(b: GraphBuilder, k: int, n: int, side: int, pos: str, side_mask: str, src_mask: str, rgb: str, c: str,
          kernel: np.ndarray, flow: tuple[str, np.ndarray] | None, scale: int, win: int, band_coc: float, margin: float,
          fp16: bool, rows: bool, slope: np.ndarray | None = None) -> onnx.GraphProto:
    """Then-branch: band ``n``'s contribution ``(1, B, 3, 6, win, win)``, (near, same, far) x (RGB, coverage),
    its convolution on a grid ``scale`` times coarser when ``scale > 1`` (``kernel`` is then
    the binned one, :func:`~neuralbokeh.networks.lens.reduce_kernel`), by rows
    (:func:`conv_rows`) or one depthwise ``Conv``. ``flow``: (the window's colour times this
    side's centroid drift ``(B, 3, win, win)``, the gain's slope ``(3,)``): the colour scattered
    is ``rgb - slope x that`` (:meth:`~neuralbokeh.networks.lens.LensBokeh.colour_gains`).
    ``slope``: the kernels' slope in the diameter (Hermite blend, ``(2, 3, k, k)`` as
    ``kernel``): each group of the convolution then takes the (kernel, slope) features of one channel."""
    g = Nodes(GraphBuilder(b.count), f"t{k}.n{n}s{side}")
    one = g.c("one", 1.0)
    if slope is None:
        weights = [g.op("Relu", g.op("Sub", one, g.op("Abs", g.op("Sub", pos, g.c(f"n{n}", float(n))))))]  # the hat
    else:
        weights = list(_hermite_weights(g, pos, n))
    if flow is not None:
        rgb = g.op("Sub", rgb, g.op("Mul", flow[0], g.c("slope", np.asarray(flow[1]).reshape(1, 3, 1, 1))))
    parts = []
    for i, weight in enumerate(weights):
        gate = g.op("Mul", g.op("Mul", weight, src_mask), side_mask)
        parts.append(g.op("Concat", g.op("Mul", rgb, gate), gate, gate, gate, axis=1))  # (B, 6, win, win)
    if len(parts) == 1:
        feats = parts[0]
    else:  # interleaved (kernel, slope) per channel: (B, 6, 2, win, win) -> (B, 12, win, win)
        pair = g.op("Concat", *(g.op("Unsqueeze", f, g.c("ax2", [2], np.int64)) for f in parts), axis=2)
        feats = g.op("Reshape", pair, g.c("pair_shape", [0, 12, win, win], np.int64))
    if scale > 1:
        extra = -(-win // scale) * scale - win
        feats = g.op("AveragePool", feats, kernel_shape=[scale, scale], strides=[scale, scale], pads=[0, 0, extra, extra],
                     count_include_pad=1)
    psfs = [kernel] if slope is None else [kernel, slope]
    w = np.stack([np.concatenate([f, f]) for f in psfs], axis=1)[:, :, ::-1, ::-1]  # (6, 1 or 2, k, k), correlation weights
    p = kernel.shape[-1] // 2
    if rows:
        out = conv_rows(g, feats, w, -(-win // scale), fp16)
    elif fp16:
        x16 = g.op("Cast", feats, to=TensorProto.FLOAT16)
        conv = g.op("Conv", x16, g.c("w", w, np.float16), group=6, pads=[p, p, p, p])
        out = g.op("Cast", conv, to=TensorProto.FLOAT)
    else:
        out = g.op("Conv", feats, g.c("w", w), group=6, pads=[p, p, p, p])
    if scale > 1:
        up = g.op("Resize", out, "", g.c("scales", [1.0, 1.0, float(scale), float(scale)]), mode="linear",
                  coordinate_transformation_mode="half_pixel")
        out = g.op("Slice", up, g.c("zeros2", [0, 0], np.int64), g.c("win2", [win, win], np.int64),
                   g.c("axes_hw", [2, 3], np.int64))
    delta = g.op("Sub", g.c("band_coc", band_coc), c)  # < 0: the band is nearer than the receiver
    zero, inv = g.c("zero", 0.0), g.c("inv_margin", 1.0 / margin)
    near = g.op("Clip", g.op("Mul", g.op("Sub", g.op("Neg", delta), g.c("margin", margin)), inv), zero, one)
    far = g.op("Clip", g.op("Mul", g.op("Sub", delta, g.c("margin", margin)), inv), zero, one)
    same = g.op("Sub", g.op("Sub", one, near), far)
    # one broadcast product (1, B, 3, 1) x (1, B, 1, 6) -> (1, B, 3, 6): written once, and as the
    # branch's output (a Reshape there would be a copy)
    weights = g.op("Unsqueeze", g.op("Concat", near, same, far, axis=1), g.c("ax03", [0, 3], np.int64))
    return _branch(g, g.op("Mul", weights, g.op("Unsqueeze", out, g.c("ax02", [0, 2], np.int64))), f"t{k}_band{n}_{side}")


def _tile(b: GraphBuilder, k: int, window: str, kernels: Mapping[int, np.ndarray], flow: tuple[str, Mapping[int, np.ndarray]] | None,
          scales: Mapping[int, int], src: np.ndarray, cfg: ModelConfig, contract: Contract, plan: BandPlan, fp16: bool,
          rows: bool, margins: Mapping[int, float], slopes: Mapping[int, np.ndarray] | None = None) -> onnx.GraphProto:
    """Then-branch: tile ``k``'s accumulators ``(B, 3, 6, win, win)``, flattened to ``(1, B 18 win^2)``,
    from the outer ``window``; band ``n``, side ``s`` runs where ``band_active[k, n - 1, s]``. A
    band that does not run gives an empty ``(0, B, 3, 6, win, win)``, so the sum over the bands
    costs only the bands that ran. ``flow``: (the outer window of the centroid drift ``(1, 6,
    win, win)``, ``{n: (2, 3)}`` the gains' slopes) or None (no drift). ``slopes``: ``{n: (2, 3,
    k, k)}`` the kernels' slopes (Hermite blend) or None (hat). ``margins``: ``{n: px}`` each
    band's occlusion margin."""
    g = Nodes(GraphBuilder(b.count), f"t{k}")
    blocks, diameters = plan.blocks, plan.diameters
    win = src.shape[-1]
    _, rgb = _linear_rgb(g, window, contract.normalization)
    coc_in = g.op("Slice", window, g.c("s3", [3], np.int64), g.c("s4", [4], np.int64), g.c("ax1", [1], np.int64))
    one = g.c("one", 1.0)
    c = g.op("Mul", coc_in, g.c("coc_scale_px", float(contract.coc_scale_px)))
    src_mask = g.c("src", src[None, None])
    if blocks == 0:
        g0, pos = src_mask, None
    else:  # BandPlan.position, op for op
        m = g.op("Max", g.op("Abs", c), g.c("point", POINT_PX))
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
        moved = None if flow is None else [
            g.op("Mul", rgb, g.op("Slice", flow[0], g.c(f"d{s}0", [3 * s], np.int64), g.c(f"d{s}1", [3 * s + 3], np.int64),
                                  g.c("ax1", [1], np.int64))) for s in range(2)]  # colour x drift, per side
        for n in range(1, blocks + 1):
            for side, (mask, sign) in enumerate(((behind, 1.0), (front, -1.0))):
                used = g.op("Gather", g.op("Gather", flags, g.c(f"n{n}_row", n - 1, np.int64)), g.c(f"side{side}", side, np.int64))
                band_flow = None if moved is None else (moved[side], flow[1][n][side])
                then = _band(g.b, k, n, side, pos, mask, src_mask, rgb, c, kernels[n][side], band_flow, scales.get(n, 1), win,
                             sign * float(diameters[n]), margins[n], fp16, rows,
                             None if slopes is None else slopes[n][side])
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


def _passthrough(b: GraphBuilder, k: int, window: str, src: np.ndarray, norm: Normalization) -> onnx.GraphProto:
    """Else-branch: the tile's core as in-focus light (no convolution), ``(1, B 18 win^2)`` as :func:`_tile`."""
    g = Nodes(GraphBuilder(b.count), f"t{k}.pass")
    norm_rgb, rgb = _linear_rgb(g, window, norm)
    m = g.c("src", src[None, None])
    ones = g.op("Add", g.op("Mul", norm_rgb, g.c("zero", 0.0)), m)  # (B, 3, win, win) of the mask
    zeros6 = g.op("Mul", g.op("Concat", rgb, rgb, axis=1), g.c("zero", 0.0))
    parts = g.op("Concat", zeros6, g.op("Mul", rgb, m), ones, zeros6, axis=1)
    return _branch(g, g.op("Reshape", parts, g.c("flat", [1, -1], np.int64)), f"t{k}_pass")


def _surface_filled(top: Nodes, background: str, keep: str | None, bound: str, colors: list[str], covers: list[str],
                    share: float, size: tuple[int, int]) -> str:
    """``LensBokeh.surface_filled``: where a pixel hides nothing (``keep`` 1) and none within
    ``SILHOUETTE_PX`` does, ``share`` of its fill is the mean colour of the same and far buckets,
    at most ``bound`` (the estimate's bound on the pixel's own colour), the ``background``
    estimate the rest."""
    b = top.b
    if keep is not None:  # 1 - the max over the square of (1 - keep)
        one = b.const("surface_one", 1.0)
        beside = window_max(top, window_max(top, top.op("Sub", one, keep), SILHOUETTE_PX, 3, size[1]), SILHOUETTE_PX, 2, size[0])
        keep = top.op("Sub", one, beside)
    eps = b.const("surface_eps", SURFACE_FILL_EPS)
    num = top.op("Add", top.op("Add", colors[1], colors[2]), top.op("Mul", background, eps))
    own = top.op("Div", num, top.op("Add", top.op("Add", covers[1], covers[2]), eps))
    own = top.op("Min", own, bound)
    share_c = b.const("surface_share", share)
    weight = share_c if keep is None else top.op("Mul", keep, share_c)
    return top.op("Add", background, top.op("Mul", weight, top.op("Sub", own, background)))


def _composite_buckets(top: Nodes, canvas: str, x: str, cfg: ModelConfig, contract: Contract, plan: BandPlan,
                       fill_gain: float | None, surface_share: float | None = None) -> str:
    """The reassembled light ``(B, 18, H, W)`` (near / same / far buckets of colour and cover)
    composited front to back, and what they leave uncovered filled: linear RGB ``(B, 3, H, W)``
    (``LensBokeh.composite``; ``fill_gain``: its learned gain with ``fill = "far_light"``;
    ``surface_share``: ``LensBokeh.surface_fill_share()`` with ``model.surface_fill``)."""
    b = top.b
    one, zero, eps = b.const("one", 1.0), b.const("zero", 0.0), b.const("eps", _EPS)
    buckets = [top.op("Slice", canvas, b.const(f"b{q}c0", [6 * q], np.int64), b.const(f"b{q}c2", [6 * q + 6], np.int64),
                      b.const("ax1", [1], np.int64)) for q in range(3)]
    out = taken = None
    colors, covers = [], []
    for q in range(3):
        color = top.op("Slice", buckets[q], b.const("c0", [0], np.int64), b.const("c3", [3], np.int64), b.const("ax1", [1], np.int64))
        cover = top.op("Max", top.op("Slice", buckets[q], b.const("c3", [3], np.int64), b.const("c6", [6], np.int64), "ax1"), zero)
        colors.append(color)
        covers.append(cover)
        room = one if taken is None else top.op("Sub", one, taken)
        lit = top.op("Mul", color, top.op("Min", one, top.op("Div", room, top.op("Max", cover, eps))))
        out = lit if out is None else top.op("Add", out, lit)
        # saturated is exactly 1 (taken + cover * frac can round to 1 - ulp, leaking a 1e4 highlight behind)
        taken = top.op("Min", cover if taken is None else top.op("Add", taken, cover), one)
    if cfg.fill == "normalize":
        return top.op("Max", top.op("Div", out, top.op("Max", taken, eps)), zero)
    hole = top.op("Max", top.op("Sub", one, taken), zero)
    background, keep, bound = hidden_background_graph(top, x, contract, plan.fill_radius_px)
    if (surface_share is not None) != (cfg.surface_fill and cfg.fill != "normalize"):
        raise ValueError(f"model.surface_fill is {cfg.surface_fill} with fill {cfg.fill!r}: its share is needed there and only there")
    if surface_share is not None:
        background = _surface_filled(top, background, keep, bound, colors, covers, surface_share, contract.size)
    if cfg.fill == "background":
        return top.op("Max", top.op("Add", out, top.op("Mul", hole, background)), zero)
    if fill_gain is None:
        raise ValueError("a far_light fill needs the network's fill_gain")
    # far_light_fill: min(hole / cover, gain) colour + (hole - min(hole, gain cover)) background, of the far bucket
    gain = b.const("fill_gain", float(fill_gain))
    far = top.op("Mul", top.op("Min", top.op("Div", hole, top.op("Max", cover, eps)), gain), color)
    rest = top.op("Sub", hole, top.op("Min", hole, top.op("Mul", gain, cover)))
    return top.op("Max", top.op("Add", top.op("Add", out, far), top.op("Mul", rest, background)), zero)


def build_lens_graph(kernels: Mapping[int, np.ndarray], plan: BandPlan, cfg: ModelConfig, contract: Contract,
                     fp16: bool = False, opset: int = 18, metadata: Mapping[str, str] | None = None,
                     scales: Mapping[int, int] | None = None, rows: bool = False,
                     flow: tuple[tuple[np.ndarray, np.ndarray, np.ndarray], Mapping[int, np.ndarray]] | None = None,
                     fill_gain: float | None = None, slopes: Mapping[int, np.ndarray] | None = None,
                     surface_share: float | None = None, *, margins: Mapping[int, float]) -> onnx.ModelProto:
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
    """
    if opset < 18:
        raise ValueError(f"the lens graph needs opset >= 18 (Col2Im), got {opset}")
    if (slopes is not None) != (cfg.band_blend == "hermite"):
        raise ValueError(f"model.band_blend is {cfg.band_blend!r}: kernel slopes are needed for 'hermite' and only there")
    scales = dict(scales or {})
    layout = cfg.layout(*contract.size)
    source_masks = layout.source_masks()
    h, w = contract.size
    (hp, wp), win, t, t_o = layout.padded_size, layout.window, layout.core, layout.overlap
    n_t = layout.num_tiles
    b = GraphBuilder()
    top = Nodes(b, "g")
    x = top.op("Concat", "aif", "coc", axis=1)
    pad_t, pad_b, pad_l, pad_r = layout.pads(h, w)
    pads = b.const("pads", [0, 0, pad_t, pad_l, 0, 0, pad_b, pad_r], np.int64)
    padded = top.op("Pad", x, pads, mode="edge")
    drift = None
    if flow is not None:  # the drift at every pixel, rows (H, Gy) x nodes (6, Gy, Gx) x cols^T, padded as the input
        nodes, rows_w, cols_w = flow[0]
        at_rows = top.op("MatMul", b.const("drift_rows", rows_w), b.const("drift_nodes", np.reshape(nodes, (6, *nodes.shape[-2:]))))
        full = top.op("MatMul", at_rows, b.const("drift_cols_t", np.transpose(cols_w)))  # (6, H, W)
        drift = top.op("Pad", top.op("Unsqueeze", full, b.const("ax0", [0], np.int64)), pads, mode="edge")
    placed = []
    for k, r, c in layout.origins():
        starts, ends = b.const(f"t{k}.starts", [r, c], np.int64), b.const(f"t{k}.ends", [r + win, c + win], np.int64)
        window = top.op("Slice", padded, starts, ends, b.const("axes_hw", [2, 3], np.int64))
        cond = top.op("Gather", "tile_active", b.const(f"t{k}.index", k, np.int64))
        tile_kernels = {n: kernels[n][k] for n in kernels}
        tile_flow = None if drift is None else (top.op("Slice", drift, starts, ends, "axes_hw"), flow[1])
        tile_slopes = None if slopes is None else {n: slopes[n][k] for n in slopes}
        then = _tile(b, k, window, tile_kernels, tile_flow, scales, source_masks[k], cfg, contract, plan, fp16, rows, margins, tile_slopes)
        b.count += 10_000  # branch-local names stay unique across branches
        other = _passthrough(b, k, window, source_masks[k], contract.normalization)
        b.count += 10_000
        placed.append(top.op("If", cond, then_branch=then, else_branch=other))  # (1, B 18 win^2)
    # overlap-add of the windows in one pass: (T, B, 3, 6, win, win) -> (B, 18 win^2, T) -> Col2Im
    stacked = top.op("Concat", *placed, axis=0) if len(placed) > 1 else placed[0]  # (T, B 18 win^2)
    stacked = top.op("Reshape", stacked, b.const("acc_shape", [n_t, -1, 3, 6, win, win], np.int64))
    cols_ = top.op("Reshape", top.op("Transpose", stacked, perm=[1, 2, 3, 4, 5, 0]),
                   b.const("cols_shape", [0, 18 * win * win, n_t], np.int64))
    total = top.op("Col2Im", cols_, b.const("canvas_hw", [hp, wp], np.int64), b.const("block_hw", [win, win], np.int64),
                   strides=[t, t])
    canvas = top.op("Slice", total, b.const("crop_start", [t_o, t_o], np.int64), b.const("crop_end", [t_o + h, t_o + w], np.int64),
                    "axes_hw")
    linear = _composite_buckets(top, canvas, x, cfg, contract, plan, fill_gain, surface_share)
    shifted = top.op("Add", linear, b.const("offset", float(contract.normalization.offset)))
    scale = b.const("scale", float(contract.normalization.scale))
    top.nodes.append(helper.make_node("Div", [top.op("Sub", shifted, scale), top.op("Add", shifted, scale)], ["defocus"],
                                      name="encode"))
    if plan.blocks != cfg.blocks:
        raise ValueError(f"the plan has {plan.blocks} bands, the network {cfg.blocks}")
    extra = [helper.make_tensor_value_info("band_active", TensorProto.BOOL, [n_t, max(plan.blocks, 1), 2])]
    return finish_model(top.nodes, b.initializers, "neuralbokeh_lens", (h, w), n_t, opset, metadata, extra)

"""The ONNX graph of the lens architecture (:mod:`neuralbokeh.lensnet`), from its kernels (onnx + numpy).

Same named inputs and output as the paper network's graph (``graph.py``): ``aif``, ``coc``,
``tile_active`` -> ``defocus``. The learned pupils are rasterised once, at export, into each
block's per-channel ``(2n + 1)^2`` kernels; the graph holds those.

Per tile (an ONNX ``If`` on ``tile_active``; an inactive tile passes its core through as in-focus
light): decode to linear light, the CoC bands' hat gates, then per band and side an ``If`` on
whether any pixel of the window uses it (a band no pixel needs is not computed: exact), a
grouped convolution of (colour x gate, gate) by the band's kernels (ONNX ``Conv`` correlates:
the point-spread functions are stored point-reflected), and the near / same-surface / far
bucket weights. The windows' accumulators are summed into place, composited near over far
with sum-to-saturation, normalised and encoded, as ``LensBokeh.forward`` does.

``fp16`` runs the convolutions in float16 (inputs and kernels); gates, buckets and the
composite stay float32.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import onnx
from onnx import TensorProto, helper

from .graph import _Builder, finish_model

_EPS = 1e-8


class _Nodes:
    """A list of nodes with a builder: ``op("Add", a, b)`` returns the output name."""

    def __init__(self, b: _Builder, stem: str) -> None:
        self.b, self.stem, self.nodes = b, stem, []

    def op(self, kind: str, *inputs: str, **attrs: Any) -> str:
        out = self.b.fresh(f"{self.stem}.{kind.lower()}")
        self.nodes.append(helper.make_node(kind, list(inputs), [out], name=out, **attrs))
        return out

    def c(self, name: str, value: Any, dtype: Any = np.float32) -> str:
        return self.b.const(f"{self.stem}.{name}", value, dtype)


def _out(name: str) -> onnx.ValueInfoProto:
    return helper.make_tensor_value_info(name, TensorProto.FLOAT, None)


def _branch(g: _Nodes, result: str, name: str) -> onnx.GraphProto:
    final = g.b.fresh(f"{name}.result")
    g.nodes.append(helper.make_node("Identity", [result], [final], name=final))
    return helper.make_graph(g.nodes, name, [], [_out(final)], g.b.initializers)


def _linear_rgb(g: _Nodes, window: str, cfg: Mapping[str, Any]) -> tuple[str, str]:
    """``(normalised RGB, linear RGB)`` of a window ``(B, 4, win, win)``: the exact inverse of
    the normalisation, ``x = s (1 + n) / (1 - n) - o``."""
    one = g.c("one", 1.0)
    norm_rgb = g.op("Slice", window, g.c("s0", [0], np.int64), g.c("s3", [3], np.int64), g.c("ax1", [1], np.int64))
    rgb = g.op("Sub", g.op("Div", g.op("Mul", g.c("scale", cfg["norm_scale"]), g.op("Add", one, norm_rgb)),
                           g.op("Sub", one, norm_rgb)), g.c("offset", cfg["norm_offset"]))
    return norm_rgb, rgb


def _band(b: _Builder, k: int, n: int, side: int, gate: str, rgb: str, c: str, kernel: np.ndarray, band_coc: float,
          margin: float, fp16: bool) -> onnx.GraphProto:
    """Then-branch: the band's 18-channel contribution (near, same, far) x (RGB, coverage)."""
    g = _Nodes(_Builder(b.count), f"t{k}.n{n}s{side}")
    feats = g.op("Concat", g.op("Mul", rgb, gate), gate, gate, gate, axis=1)  # (B, 6, win, win)
    w = np.concatenate([kernel, kernel])[:, None, ::-1, ::-1]  # (6, 1, k, k), correlation weights
    p = kernel.shape[-1] // 2
    if fp16:
        x16 = g.op("Cast", feats, to=TensorProto.FLOAT16)
        conv = g.op("Conv", x16, g.c("w", w, np.float16), group=6, pads=[p, p, p, p])
        out = g.op("Cast", conv, to=TensorProto.FLOAT)
    else:
        out = g.op("Conv", feats, g.c("w", w), group=6, pads=[p, p, p, p])
    delta = g.op("Sub", g.c("band_coc", band_coc), c)  # < 0: the band is nearer than the receiver
    zero, one, inv = g.c("zero", 0.0), g.c("one", 1.0), g.c("inv_margin", 1.0 / margin)
    near = g.op("Clip", g.op("Mul", g.op("Sub", g.op("Neg", delta), g.c("margin", margin)), inv), zero, one)
    far = g.op("Clip", g.op("Mul", g.op("Sub", delta, g.c("margin", margin)), inv), zero, one)
    same = g.op("Sub", g.op("Sub", one, near), far)
    parts = g.op("Concat", g.op("Mul", out, near), g.op("Mul", out, same), g.op("Mul", out, far), axis=1)
    return _branch(g, parts, f"t{k}_band{n}_{side}")


def _tile(b: _Builder, k: int, window: str, kernels: list[np.ndarray], src: np.ndarray, cfg: Mapping[str, Any],
          diameters: np.ndarray, fp16: bool) -> onnx.GraphProto:
    """Then-branch: tile ``k``'s accumulators ``(B, 18, win, win)`` from the outer ``window``."""
    g = _Nodes(_Builder(b.count), f"t{k}")
    c_max, blocks = float(cfg["coc_scale_px"]), int(cfg["blocks"])
    _, rgb = _linear_rgb(g, window, cfg)
    coc_in = g.op("Slice", window, g.c("s3", [3], np.int64), g.c("s4", [4], np.int64), g.c("ax1", [1], np.int64))
    one = g.c("one", 1.0)
    c = g.op("Mul", coc_in, g.c("c_max", c_max))
    src_mask = g.c("src", src[None, None])
    step = (max(c_max, 1.0) - 1.0) / max(blocks, 1)
    if blocks == 0 or step <= 0:
        pos = None
    else:
        shifted = g.op("Max", g.op("Sub", g.op("Abs", c), one), g.c("zero", 0.0))
        pos = g.op("Min", g.op("Mul", shifted, g.c("inv_step", 1.0 / step)), g.c("n_max", float(blocks)))

    def gate(n: int) -> str:
        if pos is None:
            return src_mask if n == 0 else g.c("zero", 0.0)
        hat = g.op("Relu", g.op("Sub", one, g.op("Abs", g.op("Sub", pos, g.c(f"n{n}", float(n))))))
        return g.op("Mul", hat, src_mask)

    g0 = gate(0)
    zeros6 = g.op("Mul", g.op("Concat", rgb, rgb, axis=1), g.c("zero", 0.0))
    parts = [g.op("Concat", zeros6, g.op("Mul", rgb, g0), g0, g0, g0, zeros6, axis=1)]
    if pos is not None:
        behind = g.op("Cast", g.op("Greater", c, g.c("zero", 0.0)), to=TensorProto.FLOAT)
        front = g.op("Cast", g.op("Less", c, g.c("zero", 0.0)), to=TensorProto.FLOAT)
        zeros18 = g.op("Concat", zeros6, zeros6, zeros6, axis=1)
        for n in range(1, blocks + 1):
            gn = gate(n)
            for side, (mask, sign) in enumerate(((behind, 1.0), (front, -1.0))):
                gs = g.op("Mul", gn, mask)
                used = g.op("Greater", g.op("ReduceMax", gs, keepdims=0), g.c("zero", 0.0))
                then = _band(g.b, k, n, side, gs, rgb, c, kernels[n][side], sign * float(diameters[n]),
                             float(cfg["occlusion_margin_px"]), fp16)
                skip = _Nodes(_Builder(g.b.count), f"t{k}.n{n}s{side}.skip")
                else_graph = _branch(skip, zeros18, f"t{k}_band{n}_{side}_skip")
                g.b.count = max(g.b.count, skip.b.count) + 1
                parts.append(g.op("If", used, then_branch=then, else_branch=else_graph))
    total = g.op("Sum", *parts) if len(parts) > 1 else parts[0]
    return _branch(g, total, f"t{k}_network")


def _passthrough(b: _Builder, k: int, window: str, src: np.ndarray, cfg: Mapping[str, Any]) -> onnx.GraphProto:
    """Else-branch: the tile's core as in-focus light (no convolution)."""
    g = _Nodes(_Builder(b.count), f"t{k}.pass")
    norm_rgb, rgb = _linear_rgb(g, window, cfg)
    m = g.c("src", src[None, None])
    ones = g.op("Add", g.op("Mul", norm_rgb, g.c("zero", 0.0)), m)  # (B, 3, win, win) of the mask
    zeros6 = g.op("Mul", g.op("Concat", rgb, rgb, axis=1), g.c("zero", 0.0))
    return _branch(g, g.op("Concat", zeros6, g.op("Mul", rgb, m), ones, zeros6, axis=1), f"t{k}_pass")


def build_lens_graph(kernels: Mapping[int, np.ndarray], source_masks: np.ndarray, diameters: np.ndarray,
                     cfg: Mapping[str, Any], layout: tuple[int, int, int, int], fp16: bool = False, opset: int = 17,
                     metadata: Mapping[str, str] | None = None) -> onnx.ModelProto:
    """The full-image ONNX model of a ``LensBokeh``.

    Args:
        kernels: ``{n: (tiles, 2, 3, k, k)}`` point-spread functions of block n (side 0 behind,
            1 in front), as ``LensBokeh.kernels(n)`` returns them.
        source_masks: ``(tiles, win, win)`` the pixels each tile scatters.
        diameters: ``(N + 1,)`` band centres in px.
        cfg: ``ModelConfig.to_dict()``; layout: ``ModelConfig.layout``.
        fp16: float16 convolutions. opset: >= 17. metadata: ``metadata_props``.
    """
    if opset < 17:
        raise ValueError(f"opset must be >= 17, got {opset}")
    rows, cols, t, t_o = layout
    h, w = cfg["image_height"], cfg["image_width"]
    hp, wp, win = rows * t + 2 * t_o, cols * t + 2 * t_o, t + 2 * t_o
    b = _Builder()
    top = _Nodes(b, "g")
    x = top.op("Concat", "aif", "coc", axis=1)
    padded = top.op("Pad", x, b.const("pads", [0, 0, t_o, t_o, 0, 0, hp - t_o - h, wp - t_o - w], np.int64), mode="edge")
    placed = []
    for i in range(rows):
        for j in range(cols):
            k = i * cols + j
            window = top.op("Slice", padded, b.const(f"t{k}.starts", [i * t, j * t], np.int64),
                            b.const(f"t{k}.ends", [i * t + win, j * t + win], np.int64), b.const("axes_hw", [2, 3], np.int64))
            cond = top.op("Gather", "tile_active", b.const(f"t{k}.index", k, np.int64))
            tile_kernels = {n: kernels[n][k] for n in kernels}
            then = _tile(b, k, window, tile_kernels, source_masks[k], cfg, diameters, fp16)
            b.count += 10_000  # branch-local names stay unique across branches
            other = _passthrough(b, k, window, source_masks[k], cfg)
            b.count += 10_000
            acc = top.op("If", cond, then_branch=then, else_branch=other)
            placed.append(top.op("Pad", acc, b.const(f"t{k}.place", [0, 0, i * t, j * t, 0, 0, hp - i * t - win, wp - j * t - win],
                                                      np.int64)))
    total = top.op("Sum", *placed) if len(placed) > 1 else placed[0]
    canvas = top.op("Slice", total, b.const("crop_start", [t_o, t_o], np.int64), b.const("crop_end", [t_o + h, t_o + w], np.int64),
                    "axes_hw")
    one, zero, eps = b.const("one", 1.0), b.const("zero", 0.0), b.const("eps", _EPS)
    out = taken = None
    for q in range(3):
        color = top.op("Slice", canvas, b.const(f"b{q}c0", [6 * q], np.int64), b.const(f"b{q}c1", [6 * q + 3], np.int64),
                       b.const("ax1", [1], np.int64))
        cover = top.op("Max", top.op("Slice", canvas, b.const(f"b{q}c1", [6 * q + 3], np.int64),
                                     b.const(f"b{q}c2", [6 * q + 6], np.int64), "ax1"), zero)
        room = one if taken is None else top.op("Max", top.op("Sub", one, taken), zero)
        frac = top.op("Min", one, top.op("Div", room, top.op("Max", cover, eps)))
        lit, got = top.op("Mul", color, frac), top.op("Mul", cover, frac)
        out = lit if out is None else top.op("Add", out, lit)
        taken = got if taken is None else top.op("Add", taken, got)
    linear = top.op("Max", top.op("Div", out, top.op("Max", taken, eps)), zero)
    shifted = top.op("Add", linear, b.const("offset", float(cfg["norm_offset"])))
    scale = b.const("scale", float(cfg["norm_scale"]))
    top.nodes.append(helper.make_node("Div", [top.op("Sub", shifted, scale), top.op("Add", shifted, scale)], ["defocus"],
                                      name="encode"))
    return finish_model(top.nodes, b.initializers, "neuralbokeh_lens", (h, w), rows * cols, opset, metadata)

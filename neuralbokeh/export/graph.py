"""Build the ONNX graph of a trained network from its weights (onnx + numpy, no torch).

Graph inputs, all named:

* ``aif`` ``(batch, 3, H, W)`` float32: normalised all-in-focus RGB in [-1, 1)
  (``Normalization.encode`` of linear RGB);
* ``coc`` ``(batch, 1, H, W)`` float32: signed CoC in px divided by the model's ``coc_scale_px``,
  in [-1, 1];
* ``tile_active`` ``(tiles,)`` bool: which tiles run the network. An inactive tile returns its
  input RGB window without evaluating the network (one ONNX ``If`` per tile, so onnxruntime
  executes only the branch taken). The runtime sets it from the CoC; all true is the full model.

Output ``defocus`` ``(batch, 3, H, W)`` float32: normalised defocused RGB in (-1, 1).

The layout mirrors ``neuralbokeh.networks.paper``: edge padding, one window per tile, C1 (1x1), residual
blocks of per-channel convolutions, concatenation with the window's RGB, C2 (1x1), tanh, the
identity head, then the windows are zero-padded into place, summed and divided by the overlap
count. Per-channel convolutions are written directly or, for a factorised convolution, as
``R`` branches of a ``k x 1`` and a ``1 x k`` depthwise convolution summed (``lowrank.py``).

With ``fp16`` the trunk (C1 and the residual blocks) runs in float16 with float16 weights;
C2, the tanh and the head stay float32, so the RGB skip keeps highlights that float16 cannot
hold near 1 in the normalised space (1e4 x the middle grey is 1 - 3.6e-5).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from ..core.contract import Contract
from ..networks.config import TANH_LIMIT, ModelConfig


class GraphBuilder:
    def __init__(self, count: int = 0) -> None:
        self.initializers: list[onnx.TensorProto] = []
        self.names: set[str] = set()
        self.count = count

    def const(self, name: str, value: Any, dtype: Any = np.float32) -> str:
        """An initializer (once per name: shared constants are stored once)."""
        if name not in self.names:
            self.names.add(name)
            self.initializers.append(numpy_helper.from_array(np.asarray(value, dtype=dtype), name))
        return name

    def fresh(self, stem: str) -> str:
        self.count += 1
        return f"{stem}_{self.count}"


def _conv(nodes: list, b: GraphBuilder, x: str, weight: np.ndarray, bias: np.ndarray | None, name: str,
          dtype: Any, groups: int, pads: list[int]) -> str:
    inputs = [x, b.const(f"{name}.w", weight, dtype)]
    if bias is not None:
        inputs.append(b.const(f"{name}.b", bias, dtype))
    out = b.fresh(name)
    nodes.append(helper.make_node("Conv", inputs, [out], group=groups, pads=pads, name=out))
    return out


def _per_channel(nodes: list, b: GraphBuilder, x: str, kernels: np.ndarray, bias: np.ndarray, name: str,
                 dtype: Any, factors: tuple[np.ndarray, np.ndarray] | None) -> str:
    """Depthwise 'same' convolution of ``(C, k, k)`` kernels, direct or as separable branches."""
    c, k, _ = kernels.shape
    p = k // 2
    if factors is None:
        return _conv(nodes, b, x, kernels[:, None], bias, name, dtype, c, [p, p, p, p])
    cols, rows = factors
    branches = []
    for r in range(cols.shape[1]):
        v = _conv(nodes, b, x, cols[:, r, None, :, None], None, f"{name}.r{r}v", dtype, c, [p, 0, p, 0])
        last_bias = bias if r == cols.shape[1] - 1 else None
        branches.append(_conv(nodes, b, v, rows[:, r, None, None, :], last_bias, f"{name}.r{r}h", dtype, c, [0, p, 0, p]))
    if len(branches) == 1:
        return branches[0]
    out = b.fresh(f"{name}.sum")
    nodes.append(helper.make_node("Sum", branches, [out], name=out))
    return out


def _tile_network(b: GraphBuilder, k: int, window: str, rgb: str, weights: Mapping[str, np.ndarray], cfg: ModelConfig,
                  factors: Mapping[str, tuple[np.ndarray, np.ndarray]], fp16: bool) -> onnx.GraphProto:
    """The If-branch computing tile ``k``'s output from outer-scope ``window`` and ``rgb``.

    Its weights are initializers of the branch itself: measured with onnxruntime 1.31 on CPU,
    a depthwise convolution reading an outer-scope weight ran 4x slower than one whose weight
    lives in the branch.
    """
    b = GraphBuilder(b.count)
    f = cfg.features
    ch = slice(k * f, (k + 1) * f)
    trunk = np.float16 if fp16 else np.float32
    nodes: list = []
    name = f"t{k}"
    x = window
    if fp16:
        x = b.fresh(f"{name}.in16")
        nodes.append(helper.make_node("Cast", [window], [x], to=TensorProto.FLOAT16, name=x))
    h = _conv(nodes, b, x, weights["c1.weight"][ch], weights["c1.bias"][ch], f"{name}.c1", trunk, 1, [0, 0, 0, 0])
    for n in range(cfg.blocks):
        key = f"blocks.{n}"
        a = _per_channel(nodes, b, h, weights[f"{key}.conv_a.conv.weight"][ch, 0], weights[f"{key}.conv_a.conv.bias"][ch],
                         f"{name}.b{n}a", trunk, _tile_factors(factors, f"{key}.conv_a", ch))
        relu = b.fresh(f"{name}.b{n}relu")
        nodes.append(helper.make_node("Relu", [a], [relu], name=relu))
        c = _per_channel(nodes, b, relu, weights[f"{key}.conv_b.conv.weight"][ch, 0], weights[f"{key}.conv_b.conv.bias"][ch],
                         f"{name}.b{n}b", trunk, _tile_factors(factors, f"{key}.conv_b", ch))
        added = b.fresh(f"{name}.b{n}add")
        nodes.append(helper.make_node("Add", [h, c], [added], name=added))
        h = added
    if fp16:
        h32 = b.fresh(f"{name}.out32")
        nodes.append(helper.make_node("Cast", [h], [h32], to=TensorProto.FLOAT, name=h32))
        h = h32
    z = b.fresh(f"{name}.cat")
    nodes.append(helper.make_node("Concat", [h, rgb], [z], axis=1, name=z))
    c2 = _conv(nodes, b, z, weights["c2.weight"][3 * k : 3 * k + 3], weights["c2.bias"][3 * k : 3 * k + 3],
               f"{name}.c2", np.float32, 1, [0, 0, 0, 0])
    t = b.fresh(f"{name}.tanh")
    nodes.append(helper.make_node("Tanh", [c2], [t], name=t))
    out = f"{name}.net_out"
    if cfg.head == "identity":
        ts = b.fresh(f"{name}.scaled")
        nodes.append(helper.make_node("Mul", [t, b.const(f"{name}.limit", TANH_LIMIT)], [ts], name=ts))
        num, prod, den = b.fresh(f"{name}.num"), b.fresh(f"{name}.prod"), b.fresh(f"{name}.den")
        nodes.append(helper.make_node("Add", [rgb, ts], [num], name=num))
        nodes.append(helper.make_node("Mul", [rgb, ts], [prod], name=prod))
        nodes.append(helper.make_node("Add", [prod, b.const(f"{name}.one", 1.0)], [den], name=den))
        nodes.append(helper.make_node("Div", [num, den], [out], name=out))
    else:
        nodes.append(helper.make_node("Identity", [t], [out], name=out))
    return helper.make_graph(nodes, f"{name}_network", [], [helper.make_tensor_value_info(out, TensorProto.FLOAT, None)],
                             b.initializers)


def _tile_factors(factors: Mapping[str, tuple[np.ndarray, np.ndarray]], key: str, ch: slice):
    if key not in factors:
        return None
    cols, rows = factors[key]
    return cols[ch], rows[ch]


def finish_model(nodes: list, initializers: list, name: str, size: tuple[int, int], tiles: int, opset: int,
                 metadata: Mapping[str, str] | None, extra_inputs: list | None = None) -> onnx.ModelProto:
    """The checked model around a graph with the package's named inputs (``aif``, ``coc``,
    ``tile_active``, then ``extra_inputs``) and output (``defocus``) at image size ``(H, W)``."""
    h, w = size
    graph = helper.make_graph(
        nodes, name,
        [helper.make_tensor_value_info("aif", TensorProto.FLOAT, ["batch", 3, h, w]),
         helper.make_tensor_value_info("coc", TensorProto.FLOAT, ["batch", 1, h, w]),
         helper.make_tensor_value_info("tile_active", TensorProto.BOOL, [tiles]), *(extra_inputs or [])],
        [helper.make_tensor_value_info("defocus", TensorProto.FLOAT, ["batch", 3, h, w])],
        initializers,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)], producer_name="neuralbokeh")
    model.ir_version = min(model.ir_version, 9)  # readable by onnxruntime releases of the last two years
    for key, value in (metadata or {}).items():
        model.metadata_props.add(key=key, value=value)
    onnx.checker.check_model(model)
    return model


def build_graph(weights: Mapping[str, np.ndarray], cfg: ModelConfig, contract: Contract,
                factors: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None, fp16: bool = False,
                opset: int = 17, metadata: Mapping[str, str] | None = None) -> onnx.ModelProto:
    """The full-image ONNX model.

    Args:
        weights: the network's state dict as float numpy arrays (``PaperBokeh.state_dict()``).
        cfg, contract: its config and data contract (the tile grid).
        factors: ``{"blocks.n.conv_a": (cols, rows)}`` separable factors ``(C, R, k)`` of the
            convolutions to factorise (all channels of all tiles); the others run direct.
        fp16: float16 trunk (see the module doc).
        opset: ONNX opset, >= 17.
        metadata: ``metadata_props`` to store (strings).
    """
    if opset < 17:
        raise ValueError(f"opset must be >= 17, got {opset}")
    factors = factors or {}
    h, w = contract.size
    layout = cfg.layout(h, w)
    (hp, wp), win, t_o = layout.padded_size, layout.window, layout.overlap
    b = GraphBuilder()
    nodes = [helper.make_node("Concat", ["aif", "coc"], ["x"], axis=1, name="concat_input")]
    top, bottom, left, right = layout.pads(h, w)
    pads = [0, 0, top, left, 0, 0, bottom, right]
    nodes.append(helper.make_node("Pad", ["x", b.const("pads", pads, np.int64)], ["padded"], mode="edge", name="pad"))
    count = np.zeros((1, 1, hp, wp), np.float32)
    placed = []
    for k, r, c in layout.origins():
        window, rgb, cond, out = f"t{k}.window", f"t{k}.rgb", f"t{k}.active", f"t{k}.out"
        nodes.append(helper.make_node("Slice", ["padded", b.const(f"t{k}.starts", [r, c], np.int64),
                                                b.const(f"t{k}.ends", [r + win, c + win], np.int64),
                                                b.const("axes_hw", [2, 3], np.int64)], [window], name=window))
        nodes.append(helper.make_node("Split", [window, b.const("split_rgb_coc", [3, 1], np.int64)],
                                      [rgb, f"t{k}.coc"], axis=1, name=rgb))
        nodes.append(helper.make_node("Gather", ["tile_active", b.const(f"t{k}.index", k, np.int64)], [cond], name=cond))
        then_graph = _tile_network(b, k, window, rgb, weights, cfg, factors, fp16)
        skip = f"t{k}.skip_out"
        else_graph = helper.make_graph([helper.make_node("Identity", [rgb], [skip], name=skip)], f"t{k}_skip", [],
                                       [helper.make_tensor_value_info(skip, TensorProto.FLOAT, None)])
        nodes.append(helper.make_node("If", [cond], [out], then_branch=then_graph, else_branch=else_graph, name=out))
        canvas = f"t{k}.placed"
        place = [0, 0, r, c, 0, 0, hp - r - win, wp - c - win]
        nodes.append(helper.make_node("Pad", [out, b.const(f"t{k}.place", place, np.int64)], [canvas], name=canvas))
        placed.append(canvas)
        count[..., r : r + win, c : c + win] += 1.0
    nodes.append(helper.make_node("Sum", placed, ["total"], name="sum_tiles"))
    nodes.append(helper.make_node("Mul", ["total", b.const("inv_count", 1.0 / count)], ["averaged"], name="average"))
    nodes.append(helper.make_node("Slice", ["averaged", b.const("crop_start", [t_o, t_o], np.int64),
                                            b.const("crop_end", [t_o + h, t_o + w], np.int64), "axes_hw"],
                                  ["defocus"], name="crop"))
    return finish_model(nodes, b.initializers, "neuralbokeh", (h, w), layout.num_tiles, opset, metadata)

"""Checkpoint -> ONNX with a parity check against PyTorch (the torch side of the export)."""

from __future__ import annotations

import copy
import dataclasses
import json
import logging
import os
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import onnxruntime as ort
import torch
from tqdm import tqdm

from .. import __version__
from ..checkpoint import load_model
from ..core.io import atomic_write
from ..core.normalization import Normalization
from ..core.optics import SensorWindow
from ..core.tiling import TileLayout
from ..networks.lens import LensBokeh, band_scales, overlap_for, pupil_centroids, reduce_kernel
from ..networks.paper import PaperBokeh
from ..runtime.onnx_model import FORMAT, FORMAT_VERSION, METADATA_KEY, make_session
from .graph import build_graph
from .lens_graph import LENS_DEFAULT_KERNELS, build_lens_graph, parse_lens_kernels
from .lowrank import DEFAULT_KERNELS, cheaper_ranks, factorize, parse_kernels, reconstruct, relative_error

log = logging.getLogger(__name__)

# Max abs parity error (normalised units, outputs in (-1, 1)) above which the export fails.
DEFAULT_TOLERANCE = {False: 1e-4, True: 2e-2}
# fp32, where the lens graph samples a field flow (GridSample): its sample positions round to float32
# (~2e-5 px in a 288 px window), ~3e-5 of a window's range per sample in onnxruntime and in
# torch alike, which the random-colour probe at 1080p meets as up to ~1.3e-4 (docs/runtime.md); also
# where it scatters the field gradient: its features are the colour times each pixel's offset from
# the tile's centre (px), and beside a 1e4 highlight their float32 sums met the highlight probes of
# the Mitsuba set's trained 128 px model as 1.4-1.6e-4 (5.8e-5 without the gradient or the flow)
FLOW_TOLERANCE = 3e-4


def calibration_inputs(height: int, width: int, count: int = 2, seed: int = 0) -> torch.Tensor:
    """Natural-image-like normalised inputs ``(count, 4, H, W)`` for choosing kernel ranks.

    Colour: 1/f noise (the power spectrum of natural images) as log-exposure over about
    +-3 stops around middle grey with sparse highlights up to ~100x; CoC: a smooth random
    field over [-1, 1] cut by a sharp vertical depth edge. Seeded and deterministic.
    """
    g = np.random.default_rng(seed)
    fy, fx = np.fft.fftfreq(height)[:, None], np.fft.fftfreq(width)[None, :]
    radius = np.sqrt(fy**2 + fx**2)
    radius[0, 0] = 1.0

    def field(shape: tuple[int, ...], power: float) -> np.ndarray:
        spectrum = np.fft.fft2(g.standard_normal(shape)) / radius**power
        f = np.fft.ifft2(spectrum).real
        f -= f.mean(axis=(-2, -1), keepdims=True)
        return f / (f.std(axis=(-2, -1), keepdims=True) + 1e-12)

    log_exposure = field((count, 3, height, width), 1.0) + 0.5 * field((count, 1, height, width), 1.0)
    linear = 0.18 * np.exp2(1.5 * log_exposure)
    linear = np.where(g.uniform(size=(count, 1, height, width)) < 0.002, 100.0 * linear, linear)
    coc = np.tanh(field((count, 1, height, width), 2.0))
    coc[..., width // 2 :] = np.sign(coc[..., width // 2 :] + 1e-9) * (1.0 - 0.5 * np.abs(coc[..., width // 2 :]))
    aif = Normalization().encode(linear)
    return torch.from_numpy(np.concatenate([aif, coc], axis=1).astype(np.float32))


def plan_factors(model: PaperBokeh, kernels: str, calibration: torch.Tensor | None = None,
                 ) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], dict[str, Any]]:
    """Separable factors per convolution under a ``--kernels`` spec, and a per-conv report.

    ``auto:EPS`` measures, one convolution at a time, the RMS change of the model's output on
    ``calibration`` (default :func:`calibration_inputs`) and keeps the smallest cheaper rank
    within ``EPS / sqrt(#convs)`` (binary search over R; the error falls as R grows).
    """
    plan = parse_kernels(kernels)
    convs = [(f"blocks.{n}.{part}", getattr(block, part).conv) for n, block in enumerate(model.blocks)
             for part in ("conv_a", "conv_b")]
    budget = plan.tolerance / max(len(convs), 1) ** 0.5
    if plan.mode == "auto":
        x = calibration if calibration is not None else calibration_inputs(*model.contract.size)
        with torch.no_grad():
            base = model(x)

    def output_rms(conv: torch.nn.Conv2d, weight: np.ndarray, rank: int) -> float:
        original = conv.weight.detach().clone()
        with torch.no_grad():
            conv.weight.copy_(torch.from_numpy(reconstruct(*factorize(weight, rank)))[:, None].to(original.dtype))
            err = float((model(x) - base).pow(2).mean().sqrt())
            conv.weight.copy_(original)
        return err

    factors, report = {}, {}
    for key, conv in convs:
        w = conv.weight.detach().double().numpy()[:, 0]  # (C, k, k)
        k = w.shape[-1]
        ranks = cheaper_ranks(k)
        rank, err = 0, 0.0
        if plan.mode == "lowrank" and plan.rank in ranks:
            rank = plan.rank
        elif plan.mode == "auto" and len(ranks):
            lo, hi = 0, len(ranks)  # find the first rank within budget in ranks[lo:hi]
            errors: dict[int, float] = {}
            while lo < hi:
                mid = (lo + hi) // 2
                errors[ranks[mid]] = output_rms(conv, w, ranks[mid])
                if errors[ranks[mid]] <= budget:
                    hi = mid
                else:
                    lo = mid + 1
            if lo < len(ranks):
                rank, err = ranks[lo], errors[ranks[lo]]
        if rank:
            factors[key] = factorize(w, rank)
        report[key] = {"k": int(k), "rank": rank, "max_rel_kernel_error": float(relative_error(w, rank).max()) if rank else 0.0,
                       "output_rms_error": err}
    return factors, report


def lowrank_reference(model: PaperBokeh, factors: dict[str, tuple[np.ndarray, np.ndarray]]) -> PaperBokeh:
    """A copy of ``model`` whose factorised kernels are replaced by what their factors represent:
    the PyTorch function the ONNX graph must match."""
    ref = copy.deepcopy(model).eval()
    with torch.no_grad():
        for key, (cols, rows) in factors.items():
            n, part = key.split(".")[1:]
            conv = getattr(ref.blocks[int(n)], part).conv
            conv.weight.copy_(torch.from_numpy(reconstruct(cols, rows))[:, None].to(conv.weight.dtype))
    return ref


def probe_inputs(height: int, width: int, seed: int = 0) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Named normalised ``(aif (B, 3, H, W), coc (B, 1, H, W))`` float32 inputs for the parity
    check and the stability suite: random values, everything in focus, everything at the
    maximum CoC (both signs), a depth edge from in focus to the maximum CoC within one pixel,
    and 1e4 highlights on black."""
    g = np.random.default_rng(seed)
    norm = Normalization()
    shape1, shape3 = (1, 1, height, width), (1, 3, height, width)
    scene = norm.encode(0.18 * np.exp2(g.uniform(-4, 4, shape3)))
    highlights = norm.encode(np.where(g.uniform(size=shape3) < 0.3, 1e4, 0.0))
    edge = np.zeros(shape1)
    edge[..., width // 2 :] = 1.0
    cases = {
        "random": (g.uniform(-0.99, 0.99, (2, 3, height, width)), g.uniform(-1, 1, (2, 1, height, width))),
        "all_in_focus": (scene, np.zeros(shape1)),
        "all_max_coc_behind": (scene, np.ones(shape1)),
        "all_max_coc_in_front": (scene, -np.ones(shape1)),
        "depth_edge_one_pixel": (scene, edge),
        "highlights_1e4": (highlights, np.where(g.uniform(size=shape1) < 0.5, -1.0, 1.0)),
        "highlights_1e4_edge": (highlights, edge),
    }
    return {k: (a.astype(np.float32), c.astype(np.float32)) for k, (a, c) in cases.items()}


def parity_tiles(layout: TileLayout) -> np.ndarray:
    """The tiles a plate export's parity check convolves, ``(tiles,)`` bool: the corners, edge
    middles and centre of the grid (its field extremes and middle; every tile of a grid up to
    3 x 3). Every tile's branch is built by the same code from its own kernels, so these stand
    for the rest; the others pass through as in-focus light on both sides."""
    rows = sorted({0, layout.rows // 2, layout.rows - 1})
    cols = sorted({0, layout.cols // 2, layout.cols - 1})
    active = np.zeros(layout.num_tiles, dtype=bool)
    active[[i * layout.cols + j for i in rows for j in cols]] = True
    return active


def run_session(sess: ort.InferenceSession, aif: np.ndarray, coc: np.ndarray,
                tile_active: np.ndarray | None = None) -> np.ndarray:
    """Run an exported graph on normalised ``aif`` ``(B, 3, H, W)`` and ``coc`` ``(B, 1, H, W)``
    (CoC / coc_scale_px): every tile (or ``tile_active``) and, in a lens graph, every band."""
    shapes = {i.name: i.shape for i in sess.get_inputs()}
    feeds = {"aif": aif, "coc": coc,
             "tile_active": np.ones(shapes["tile_active"][0], dtype=bool) if tile_active is None else tile_active}
    if "band_active" in shapes:
        feeds["band_active"] = np.ones(shapes["band_active"], dtype=bool)
    return sess.run(["defocus"], feeds)[0]


def plate_model(model: LensBokeh, size: tuple[int, int] | None = None, max_coc_px: float | None = None,
                tile_px: int | None = None, field_flow: bool | None = None, field_gradient: bool | None = None) -> LensBokeh:
    """The lens network as an export for one plate format sees it: the same weights, a contract
    of the plate's ``size`` ``(H, W)`` px (default: the trained one) whose CoC scale and largest
    CoC are the last band centre of the plan for ``max_coc_px`` (default: the trained maximum;
    larger renders CoCs beyond it, through the scaled pupil), N = that plan's bands, and tile
    cores of ``tile_px`` px (default: the trained ones) with the trained overlap, widened by what
    a CoC beyond the trained range adds to the blur's radius
    (:func:`~neuralbokeh.networks.lens.overlap_for`); ``field_flow``, ``field_gradient``:
    ``model.field_flow`` and ``model.field_gradient`` on or off (default: the trained model's)."""
    if max_coc_px is not None and not (np.isfinite(max_coc_px) and max_coc_px > 0):
        raise ValueError(f"max_coc_px must be a finite number of px > 0, got {max_coc_px!r}")
    height, width = size or model.contract.size
    plan = model.plan(float(max_coc_px if max_coc_px is not None else model.contract.max_coc_px))
    # CoCs beyond the trained range reach further: widen the overlap by what they add to the radius
    c_train = max(float(model.contract.coc_scale_px), 1.0)
    beyond = overlap_for(plan.c_plan_px) - overlap_for(c_train) if plan.c_plan_px > c_train * (1 + 1e-6) else 0
    overlap = model.config.overlap + (max(beyond, 0) if model.config.tiling == "overlap" else 0)
    if tile_px is not None and (isinstance(tile_px, bool) or int(tile_px) != tile_px or tile_px < 2 * overlap):
        raise ValueError(f"tile_px must be a whole number of px >= twice the overlap ({2 * overlap} px), got {tile_px!r}")
    contract = dataclasses.replace(model.contract, image_height=int(height), image_width=int(width),
                                   coc_scale_px=max(plan.c_plan_px, 1.0), max_coc_px=plan.c_plan_px)
    tile = max(model.config.tile, 2 * overlap) if tile_px is None else int(tile_px)
    flow = model.config.field_flow if field_flow is None else bool(field_flow)
    gradient = model.config.field_gradient if field_gradient is None else bool(field_gradient)
    if flow and gradient:
        raise ValueError("field_flow = true: this model has model.field_gradient, which already gives each pixel its own "
                         "pupil's blur; export it without the flow, or with field_gradient = false")
    plate = LensBokeh(dataclasses.replace(model.config, blocks=plan.blocks, tile=tile, overlap=overlap, field_flow=flow,
                                          field_gradient=gradient), contract)
    plate.load_state_dict(model.state_dict())
    return plate.eval()


def export_checkpoint(
    checkpoint: str | os.PathLike,
    out: str | os.PathLike,
    opset: int | None = None,
    fp16: bool = False,
    kernels: str | None = None,
    tolerance: float | None = None,
    threads: int | None = None,
    size: tuple[int, int] | None = None,
    window: SensorWindow | None = None,
    max_coc_px: float | None = None,
    tile_px: int | None = None,
    full_parity: bool = False,
    field_flow: bool | None = None,
    field_gradient: bool | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """Export a checkpoint to ONNX, check it against PyTorch, then move it into place.

    Args:
        checkpoint: a ``train.py`` checkpoint.
        out: the ``.onnx`` file to write (written to a temporary file and renamed after the
            parity check passed; never half-written).
        opset: ONNX opset (default and minimum: 17 for the paper network, 18 for the lens network).
        fp16: float16 trunk (see ``graph.py``) or band convolutions (``lens_graph.py``).
        kernels: paper network: ``direct``, ``lowrank:R`` or ``auto:EPS`` (see ``lowrank.py``;
            default ``DEFAULT_KERNELS``); lens network: ``direct`` (depthwise ``Conv``, the
            reference), ``rows`` (the same sums as row GEMMs) or ``multires:PX`` (as rows; bands
            whose CoC is wide enough convolved on grids 2, 4 or 8 times coarser, keeping the CoC
            at least PX coarse pixels wide; default ``LENS_DEFAULT_KERNELS``).
        tolerance: max abs parity error in normalised units (default 1e-4 fp32, 3e-4 for a lens
            graph that samples a field flow or scatters the field gradient, 2e-2 fp16).
        threads: onnxruntime threads for the parity run.
        size: lens network: the plate format ``(H, W)`` px the file renders (default: the
            trained size); the learned lens renders any size.
        window: lens network: the plate's part of the sensor (default: all of it); it places
            the tiles' pupils in the field and is the runtime's default window.
        max_coc_px: lens network: the largest |CoC| (px) the file renders (default: the
            trained maximum; beyond it the learned pupil is scaled).
        tile_px: lens network: tile cores of this many px (default: the trained size). Each
            tile takes its pupil at its centre, so larger tiles sample the field more coarsely
            but run fewer, larger convolutions (fewer graph branches, less overlap).
        full_parity: lens network: check every tile (minutes for a 4K plate) instead of the
            :func:`parity_tiles` sample of at most 9.
        field_flow, field_gradient: lens network: ``model.field_flow`` and
            ``model.field_gradient`` on or off in the file (default: the checkpoint's; off is
            faster where a cat-eye moves the light).
        progress: a tqdm bar over the build, the load and each parity case (the CLI's).

    Returns:
        A report: ``parity`` (max abs error per probe case, against the PyTorch function
        of the exported kernels), ``parity_tiles`` (the tiles it convolved), ``approximation``
        (max abs error of that function against the trained model, per case: 0 for ``direct``),
        ``kernels`` (rank per convolution), ``band_scales`` (lens network: the grid reduction ``{n: s}`` of each band n >= 1; None
        otherwise), ``metadata`` and ``path``.

    Raises:
        ValueError: bad options, or a parity error above ``tolerance`` (nothing is written).
    """
    given = tolerance
    _check_opset(opset, None)  # before the checkpoint is read
    model, ckpt = load_model(checkpoint)
    lens = model.config.architecture == "lens"
    if not lens and (size or window or max_coc_px or tile_px or full_parity or field_flow is not None or field_gradient is not None):
        raise ValueError("size, window, max_coc_px, tile_px, full_parity, field_flow and field_gradient need the lens network: "
                         "the paper's network "
                         f"renders its trained size {model.contract.size[1]}x{model.contract.size[0]} px only")
    opset = _check_opset(opset, lens)
    window = window or SensorWindow()
    if lens:
        model = plate_model(model, size, max_coc_px, tile_px, field_flow, field_gradient)
        build = _LensExport(model, LENS_DEFAULT_KERNELS if kernels is None else kernels, window)
    else:
        build = _PaperExport(model, DEFAULT_KERNELS if kernels is None else kernels)
    meta = {
        "format": FORMAT, "format_version": FORMAT_VERSION, "package_version": __version__,
        "model_config": model.config.to_dict(), "contract": model.contract.to_dict(),
        "layout": list(model.config.layout(*model.contract.size)),
        "sensor_window": window.to_dict(), "trained_max_coc_px": float(ckpt["contract"]["max_coc_px"]),
        "band_plan": build.plan.to_dict() if build.plan else None,
        "kernels": build.kernels, "kernel_ranks": {k: v["rank"] for k, v in build.report.items()},
        "fp16": fp16, "opset": opset, "source_checkpoint": Path(checkpoint).name,
        "trained_steps": ckpt.get("step"),
        "data_split": ({k: ckpt["train_config"]["data"][k] for k in ("test_fraction", "split_seed")}
                       if ckpt.get("train_config") else None),
    }
    probes = probe_inputs(*model.contract.size)
    layout = model.config.layout(*model.contract.size)
    active = np.ones(layout.num_tiles, dtype=bool) if full_parity or not lens else parity_tiles(layout)
    bar = tqdm(total=2 + len(probes), desc="export: graph", unit="step", disable=not progress)
    onnx_model = build.graph(fp16, opset, {METADATA_KEY: json.dumps(meta, sort_keys=True)})
    bar.update()
    bar.set_description("export: onnxruntime load")
    sess = make_session(onnx_model.SerializeToString(), threads)
    bar.update()
    parity, approx = _parity(sess, probes, build, active, bar)
    bar.close()
    worst = max(parity.values())
    loose = getattr(build, "warps", False) or getattr(build, "gradient", False)
    tolerance = given if given is not None else FLOW_TOLERANCE if loose and not fp16 else DEFAULT_TOLERANCE[fp16]
    log.info("parity (max abs, normalised): %s; approximation: %s", parity, approx)
    if worst > tolerance:
        raise ValueError(f"ONNX and PyTorch differ by up to {worst:.3g} (> tolerance {tolerance:g}) per case {parity}; not written")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(out) as tmp:
        onnx.save(onnx_model, tmp)
    return {"path": str(out), "parity": parity, "parity_tiles": np.flatnonzero(active).tolist(), "tolerance": tolerance,
            "approximation": approx, "kernels": build.report, "band_scales": build.scales, "metadata": meta}


def _check_opset(opset: int | None, lens: bool | None) -> int:
    """``opset``, or the network's lowest (18 lens, 17 paper) when None; ``lens`` None checks the
    range this onnx knows only (before the checkpoint is read)."""
    newest = onnx.defs.onnx_opset_version()
    if opset is not None and not 17 <= opset <= newest:
        raise ValueError(f"opset must be from 17 (18 for the lens network) to {newest} (the newest this onnx "
                         f"{onnx.__version__} knows), got {opset}")
    lowest = 18 if lens else 17
    if opset is not None and lens is not None and opset < lowest:
        raise ValueError(f"opset must be at least {lowest} for the {'lens' if lens else 'paper'} network's operators, got {opset}")
    return lowest if opset is None else opset


class _LensExport:
    """The lens network's side of an export: per-band kernels rasterised from the learned
    pupils at each tile's field position, direct or binned to coarser grids (``multires``)."""

    def __init__(self, model: LensBokeh, kernels: str, window: SensorWindow) -> None:
        self.model, self.kernels = model, kernels
        self.spec = parse_lens_kernels(kernels)
        self.plan = model.plan(model.contract.max_coc_px)
        self.scales = band_scales(self.plan.diameters, self.spec.min_px)
        self.report = {f"band{n}": {"k": model.kernel_size(n), "rank": 0, "scale": self.scales[n]}
                       for n in range(1, model.config.blocks + 1)}
        self.window = torch.tensor([[window.left, window.top, window.width, window.height]])
        self.approximate = any(s > 1 for s in self.scales.values())
        self.exact: LensBokeh | None = None  # the float64 copy of the reference
        self.warps = False  # whether the graph samples a field flow (set by graph())
        self.gradient = False  # whether it scatters the field gradient (set by graph())

    def float64(self) -> LensBokeh:
        """The model in float64: the reference runs it and the graph's kernels are rasterised from
        it. In float32 a cat-eye's 1080p kernels were off by up to ~1e-3 relative in some tiles
        (its pupils' logs by up to ~1e-2), past the parity tolerance beside a 1e4 highlight;
        rounded to float32 once at the end, the graph's kernels are the reference's."""
        if self.exact is None:
            self.exact = copy.deepcopy(self.model).double()
        return self.exact

    def graph(self, fp16: bool, opset: int, props: dict[str, str]) -> onnx.ModelProto:
        m, d, window = self.float64(), self.plan.diameters, self.window.double()
        with torch.no_grad():
            layout = m.config.layout(*m.contract.size)
            pupils = m.tile_pupils(layout, *m.contract.size, window)[0]
            drift, rows, cols = (t[0].double() for t in m.drift_lattice(*m.contract.size, window))
            full = {n: m.kernels(n, pupils, float(d[n])).double() for n in range(1, m.config.blocks + 1)}
            band_kernels = {n: reduce_kernel(v, self.scales[n]).numpy() for n, v in full.items()}
            carry_kernels = None if not m.config.occlusion_source_coc else {  # the green channel's, on the carry's grid
                n: reduce_kernel(v[:, :, 1], self.scales[n] * m.config.occlusion_source_coc_grid).numpy() for n, v in full.items()}
            slopes = {n: m.gain_slopes(float(d[n])).double().numpy() for n in range(1, m.config.blocks + 1)}
            margins = {n: float(m.occlusion_margin(float(d[n]), self.plan.band_step_px(n))) for n in range(1, m.config.blocks + 1)}
            kernel_slopes = None if m.config.band_blend != "hermite" else {
                n: reduce_kernel(m.kernel_slopes(n, pupils, float(d[n]), self.plan.band_step_px(n)).double(), self.scales[n]).numpy()
                for n in range(1, m.config.blocks + 1)}
            centroids = None
            if m.config.field_flow and bool(drift.abs().max() > 0):  # LensBokeh.centroid_offsets' parts
                nodes, c_rows, c_cols = (t.double() for t in m.centroid_lattice(*m.contract.size, window))
                centre = pupil_centroids(pupils).mean(dim=2).double().numpy()  # (tiles, 2, 2)
                radius = {n: slopes[n].mean(axis=1) for n in slopes}  # (2,) per side, as the module's warp
                reach = m.centroid_offsets(layout, pupils, *m.contract.size, window).abs().flatten(2).amax(dim=2)
                centroids = ((nodes.numpy(), c_rows[0].numpy(), c_cols[0].numpy()), centre, radius, reach.double().numpy())
            gradients = None
            if m.config.field_gradient and bool(drift.abs().max() > 0):  # LensBokeh.kernel_gradients and its offsets
                neighbours, per_px = m.neighbour_pupils(layout, *m.contract.size, window)
                gradients = {n: reduce_kernel(m.kernel_gradients(n, neighbours, float(d[n]), per_px).double(), self.scales[n]).numpy()
                             for n in range(1, m.config.blocks + 1)}
        flow = None if not bool(drift.abs().max() > 0) else ((drift.numpy(), rows.numpy(), cols.numpy()), slopes)
        self.warps, self.gradient = centroids is not None, gradients is not None
        if fp16 and self.gradient:
            log.warning("fp16: the bands that scatter model.field_gradient stay float32 (their sums cancel below float16's "
                        "precision beside a highlight); export with field_gradient off for float16 bands")
        gain = None if m.fill_gain is None else float(m.far_light_gain().detach())
        share = None if m.surface_fill is None else float(m.surface_fill_share().detach())
        return build_lens_graph(band_kernels, self.plan, m.config, m.contract, fp16, opset, props, self.scales,
                                self.spec.rows, flow, gain, kernel_slopes, share, margins=margins, centroids=centroids,
                                gradients=gradients, carry_kernels=carry_kernels)

    def reference(self, x: torch.Tensor, active: torch.Tensor) -> torch.Tensor:
        """The PyTorch function of the exported kernels (coarse grids included) on the
        ``active`` tiles, in float64: its FFT convolutions' round-off is relative to a window's
        brightest pixel, so in float32 a 1e4 highlight leaves ~1e-3 of noise in the black next to
        it, where the graph's direct sums are exact."""
        out = self.float64()(x.double(), self.window.double(), tile_active=active, scales=self.scales,
                         plan_coc_px=self.model.contract.max_coc_px)
        return out.to(x.dtype)

    def trained(self, x: torch.Tensor, active: torch.Tensor) -> torch.Tensor:
        return self.model(x, self.window, tile_active=active, plan_coc_px=self.model.contract.max_coc_px)


class _PaperExport:
    """The paper network's side of an export: its weights, with separable factors where the
    ``--kernels`` spec asks for them."""

    plan, scales = None, None  # no CoC bands

    def __init__(self, model: PaperBokeh, kernels: str) -> None:
        self.model, self.kernels = model, kernels
        self.factors, self.report = plan_factors(model, kernels)
        self.approximate = bool(self.factors)
        self.lowrank = lowrank_reference(model, self.factors) if self.factors else model

    def reference(self, x: torch.Tensor, active: torch.Tensor) -> torch.Tensor:
        """The PyTorch function of the exported (separable) kernels; every tile (``active``
        is all of them: the paper network's frame is small)."""
        return self.lowrank(x)

    def trained(self, x: torch.Tensor, active: torch.Tensor) -> torch.Tensor:
        return self.model(x)

    def graph(self, fp16: bool, opset: int, props: dict[str, str]) -> onnx.ModelProto:
        weights = {k: v.detach().numpy() for k, v in self.model.state_dict().items()}
        return build_graph(weights, self.model.config, self.model.contract, self.factors, fp16, opset, props)


def _parity(sess: ort.InferenceSession, probes: dict[str, tuple[np.ndarray, np.ndarray]], build: _LensExport | _PaperExport,
            active: np.ndarray, bar: tqdm) -> tuple[dict[str, float], dict[str, float]]:
    """Max abs error per probe case of onnxruntime against the PyTorch function of the exported
    kernels, and of that function against the trained model (0 where it is the model), with the
    ``active`` tiles ``(tiles,)`` bool convolved."""
    parity, approx = {}, {}
    tiles = torch.from_numpy(active)
    with torch.no_grad():
        for name, (aif, coc) in probes.items():
            bar.set_description(f"export: parity {name}")
            parity[name] = approx[name] = 0.0
            for i in range(aif.shape[0]):  # image by image: a 4K frame holds GBs (dynamic batches: tests/test_export.py)
                got = run_session(sess, aif[i : i + 1], coc[i : i + 1], active)
                if not np.isfinite(got).all():
                    raise ValueError(f"ONNX output is not finite on the {name!r} probe")
                x = torch.from_numpy(np.concatenate([aif[i : i + 1], coc[i : i + 1]], axis=1))
                want = build.reference(x, tiles).numpy()
                parity[name] = max(parity[name], float(np.abs(got - want).max()))
                if build.approximate:
                    approx[name] = max(approx[name], float(np.abs(want - build.trained(x, tiles).numpy()).max()))
            bar.update()
    return parity, approx

"""Run an exported lens model on CPU with onnxruntime: numpy in, numpy out, no torch.

    from neuralbokeh.runtime import OnnxBokeh
    model = OnnxBokeh("lens.onnx", threads=4)
    out = model.render(aif, depth_m, focus_m=2.5)       # (H, W, 3) linear RGB
    out = model.render_coc(aif, coc_px)                 # with a CoC map of your own

Images are numpy ``(H, W, 3)`` or ``(B, H, W, 3)`` linear scene-referred RGB (the layout
OpenImageIO reads), at the resolution the model was trained for. Depth is planar depth along
the optical axis in metres ``(H, W)``, ``(H, W, 1)`` or batched; ``+inf`` is allowed. The lens,
normalisation and CoC range come from the model file's metadata.

Leaving out what a scene does not need: a tile whose |CoC| stays below ``in_focus_px``
(default 0.5 px) over its whole window (the tile and its overlap: tiles are evaluated
independently, so the window is the tile's entire receptive field) returns its input
without running the network. In a lens model (``model.architecture = "lens"``), the CoC
bands and sides of the focus plane that no pixel of a tile scatters are not computed either
(``band_active``, proved from the frame's CoC map by :func:`neuralbokeh.core.bands.active_bands`
with the plan the file carries: a frame whose largest CoC is a third of
the model's runs only a third of the bands), and a tile whose core scatters no band (every
|CoC| there <= 1 px: points) is passed through whatever its window holds, since a lens tile
scatters its own core only. All three are exact: tiles and bands that run give what the full
evaluation gives.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort

from ..core.bands import HIGHLIGHT_RATIO, BandPlan, active_bands, highlight_coc, isolated_highlights
from ..core.checks import check_at_least, check_finite, format_location
from ..core.contract import Contract
from ..core.optics import SensorWindow
from ..core.tiling import TileLayout

log = logging.getLogger(__name__)

METADATA_KEY = "neuralbokeh"  # the ONNX metadata_props entry holding the JSON below
FORMAT = "neuralbokeh-onnx"
FORMAT_VERSION = 2  # 2: "contract", "model_config" and, for the lens network, "band_plan"


# onnxruntime's graph optimisation levels by their names here
OPTIMIZATION = {"all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL, "basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
                "off": ort.GraphOptimizationLevel.ORT_DISABLE_ALL}


def make_session(path_or_bytes: str | bytes, threads: int | None = None, optimization: str = "basic") -> ort.InferenceSession:
    """A CPU onnxruntime session (``threads`` intra-op threads; None: onnxruntime's default).

    ``optimization``: onnxruntime's graph optimisation, ``"all"`` (its default), ``"basic"`` or
    ``"off"``. A lens graph's thousands of ``If`` branches make the load the cost:
    ``benchmarks/bench_load.py`` measures each level's load and render time (``docs/benchmarks.md``). onnxruntime's
    memory pattern (one block planned for the whole graph) is off: with a tile and band ``If``
    per branch it reserved ~0.8 GB more at 1080p for no measurable speed.

    Raises:
        ValueError: the file or bytes are no model onnxruntime can load (empty, truncated, not
            ONNX, an opset it does not know), with its reason in one line; an unknown
            ``optimization``.
    """
    if threads is not None and (int(threads) != threads or threads < 1):
        raise ValueError(f"threads must be a whole number >= 1 (or None: all cores), got {threads!r}")
    if optimization not in OPTIMIZATION:
        raise ValueError(f"optimization must be one of {', '.join(OPTIMIZATION)}, got {optimization!r}")
    so = ort.SessionOptions()
    so.graph_optimization_level = OPTIMIZATION[optimization]
    so.enable_mem_pattern = False
    if threads:
        so.intra_op_num_threads = int(threads)
        so.inter_op_num_threads = 1
    so.log_severity_level = 3
    try:
        return ort.InferenceSession(path_or_bytes, so, providers=["CPUExecutionProvider"])
    except Exception as e:  # noqa: BLE001 - onnxruntime's load errors share no base class but Exception
        source = path_or_bytes if isinstance(path_or_bytes, str) else "the graph"
        reason = " ".join(str(e).split()).split("failed:")[-1].strip()
        raise ValueError(f"{source} is not an ONNX model onnxruntime can load: {reason}") from e


def read_metadata(session: ort.InferenceSession, source: str = "model") -> dict[str, Any]:
    """The exporter's metadata of a session: ``contract`` (a ``Contract.to_dict()``),
    ``model_config`` and, for the lens network, ``band_plan``.

    Raises:
        ValueError: no neuralbokeh metadata, an unknown format or version, or a lens model
            without its band plan (files of earlier versions: export them again).
    """
    props = session.get_modelmeta().custom_metadata_map
    if METADATA_KEY not in props:
        raise ValueError(f"{source} has no {METADATA_KEY!r} metadata: not exported by neuralbokeh's export.py")
    meta: dict[str, Any] = json.loads(props[METADATA_KEY])
    version = meta.get("format_version")
    if meta.get("format") != FORMAT or version != FORMAT_VERSION:
        raise ValueError(f"{source}: unsupported model format {meta.get('format')!r} v{version} (this neuralbokeh reads "
                         f"v{FORMAT_VERSION}): export the checkpoint again with this version's export.py")
    if meta["model_config"].get("architecture") == "lens" and not meta.get("band_plan"):
        raise ValueError(f"{source}: a lens model without its band plan: export the checkpoint again with this version's "
                         "export.py")
    return meta


class OnnxBokeh:
    """A lens model exported by ``export.py``.

    Args:
        path: the ``.onnx`` file.
        threads: onnxruntime intra-op threads (None: onnxruntime's default, all cores).
        skip_in_focus: return in-focus tiles unchanged without running the network.
        in_focus_px: |CoC| in px below which a tile window counts as in focus, >= 0.
        optimization: onnxruntime's graph optimisation (:func:`make_session`): ``"off"`` loads
            fastest (one frame per process), ``"basic"`` (default) or ``"all"``.

    Raises:
        FileNotFoundError: no such file.
        ValueError: the file is not a neuralbokeh model (no or unknown metadata).
    """

    def __init__(self, path: str | Path, threads: int | None = None, skip_in_focus: bool = True,
                 in_focus_px: float = 0.5, optimization: str = "basic") -> None:
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"no such model file: {path}")
        check_at_least("in_focus_px", in_focus_px, 0.0, " px")
        self.session = make_session(str(path), threads, optimization)
        self.meta = read_metadata(self.session, str(path))
        self.contract = Contract.from_dict(self.meta["contract"])
        self.height, self.width = self.contract.size
        self.layout = TileLayout(*(int(v) for v in self.meta["layout"]))
        # the part of the lens's sensor the file was exported for (files without one: all of it)
        self.window = SensorWindow.from_dict(self.meta.get("sensor_window"))
        self.skip_in_focus, self.in_focus_px = skip_in_focus, float(in_focus_px)
        self.has_bands = "band_active" in {i.name for i in self.session.get_inputs()}
        self.plan = self._band_plan() if self.has_bands else None
        # files written before the key existed do not spread highlights (networks.config.LEGACY_DEFAULTS)
        self.highlight_spread = self.has_bands and bool(self.meta["model_config"].get("highlight_spread", False))
        self.last_tiles_run = 0
        self.last_bands_run = 0  # (tile, band, side) scatters run by the last call (lens models)

    @property
    def num_tiles(self) -> int:
        return self.layout.num_tiles

    def coc_px(self, depth_m: np.ndarray, focus_m: float, window: SensorWindow | None = None) -> np.ndarray:
        """Signed CoC diameter in px (negative in front of the focus plane) from planar depth in m
        (> 0, inf allowed) with the model's lens, at the model's image width, for an image of
        ``window`` (default: the window the file was exported for)."""
        if self.contract.lens is None:
            raise ValueError("this model carries no lens metadata; use render_coc with a CoC map")
        return np.asarray(self.contract.lens.coc_px(np.asarray(depth_m, dtype=np.float64), float(focus_m), self.width,
                                                    signed=True, window=window or self.window))

    def render(self, aif: np.ndarray, depth_m: np.ndarray, focus_m: float, clamp_coc: bool = False,
               window: SensorWindow | None = None) -> np.ndarray:
        """Defocus ``aif`` as the lens focused at ``focus_m`` (m) would.

        Args:
            aif: linear RGB, ``(H, W, 3)`` or ``(B, H, W, 3)``, finite, >= -normalisation offset.
            depth_m: planar depth in m, ``(H, W)``, ``(H, W, 1)`` or with a leading batch; > 0, inf allowed.
            focus_m: focus distance in m (greater than the focal length).
            clamp_coc: clamp CoCs beyond the largest the file renders (with a warning) instead of failing.
            window: the part of the lens's sensor the image covers, when it is a crop
                (default: the window the file was exported for, the whole sensor unless told).

        Returns:
            float32 linear RGB in the layout of ``aif``.
        """
        chw, batched = self._images(aif)
        depth = self._per_pixel("depth_m", depth_m, chw, batched)
        return self._run(chw, self.coc_px(depth, focus_m, window), clamp_coc, batched)

    def render_coc(self, aif: np.ndarray, coc_px: np.ndarray, clamp_coc: bool = False) -> np.ndarray:
        """Like :meth:`render` with a signed CoC map in px (``(H, W)``, ``(H, W, 1)`` or batched)."""
        chw, batched = self._images(aif)
        return self._run(chw, self._per_pixel("coc_px", coc_px, chw, batched), clamp_coc, batched)

    def active_tiles(self, coc_px: np.ndarray, points: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """``(tiles,)`` bool: tiles whose window holds a |CoC| >= ``in_focus_px`` in any image of
        the batch ``(B, H, W)``, or that scatter one of ``points`` (rows, cols, CoC px; see
        :meth:`highlights`) with such a CoC (all true when skipping is off)."""
        if not self.skip_in_focus:
            return np.ones(self.num_tiles, dtype=bool)
        size = np.abs(coc_px).max(axis=0)
        top, _, left, _ = self.layout.pads(self.height, self.width)
        win = self.layout.window
        # a window's max over the edge-padded frame is its max over the frame: padding repeats edge pixels
        active = np.array([size[max(r - top, 0) : r - top + win, max(c - left, 0) : c - left + win].max() >= self.in_focus_px
                           for _, r, c in self.layout.origins()], dtype=bool)
        if points is not None:
            rows, cols, _ = (p[np.abs(points[2]) >= self.in_focus_px] for p in points)
            active[self.layout.source_tile(rows, cols)] = True
        return active

    def _band_plan(self) -> BandPlan:
        """The band plan the file was exported with (:func:`read_metadata` checks it is there)."""
        return BandPlan.from_dict(self.meta["band_plan"])

    def active_bands(self, coc_px: np.ndarray, tiles: np.ndarray | None = None,
                     points: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """``(tiles, N, 2)`` bool (lens models): the bands and sides each tile's pixels use in
        the batch ``coc_px`` ``(B, H, W)``, and the ``points`` (rows, cols, CoC px; see
        :meth:`highlights`) it scatters (:func:`neuralbokeh.core.bands.active_bands`, with the
        file's plan), of the ``tiles`` ``(tiles,)`` bool only (default: all); all true when
        skipping is off."""
        if not self.skip_in_focus:
            return np.ones((self.num_tiles, max(self.plan.blocks, 1), 2), dtype=bool)
        return active_bands(coc_px, self.plan, self.layout, tiles, points)

    def highlights(self, aif: np.ndarray, coc_px: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """Where the file spreads isolated highlights (``model.highlight_spread``; else None):
        (rows, columns, grown CoC px) of every pixel of linear ``aif`` ``(B, 3, H, W)`` within 0.1 %
        of the highlight ratio, a superset of the graph's (which decides on the float32 decoded
        input), with :func:`highlight_coc` of its ``coc_px`` ``(B, H, W)``: sources whose tiles
        and bands run as well as their own CoC's."""
        if not self.highlight_spread:
            return None
        b, r, c = np.nonzero(isolated_highlights(aif, HIGHLIGHT_RATIO * (1.0 - 1e-3)))
        return r, c, highlight_coc(coc_px[b, r, c])

    def _images(self, aif: np.ndarray) -> tuple[np.ndarray, bool]:
        a = np.asarray(aif)
        batched = a.ndim == 4
        a4 = a if batched else a[None]
        if a4.ndim != 4 or a4.shape[1:] != (self.height, self.width, 3):
            raise ValueError(f"aif must have shape ({self.height}, {self.width}, 3) or (B, {self.height}, {self.width}, 3) "
                             f"for this model, got {a.shape}")
        # (B, 3, H, W) float32, the graph's layout, copied once (numpy is ~5x slower on the
        # transposed view); errors name the pixel as (row, col)
        chw = np.ascontiguousarray(a4.transpose(0, 3, 1, 2), dtype=np.float32)
        check_finite("aif colour", chw)
        check_at_least("aif colour", chw, -self.contract.normalization.offset)
        return chw, batched

    @staticmethod
    def _per_pixel(name: str, values: np.ndarray, chw: np.ndarray, batched: bool) -> np.ndarray:
        """A one-channel map ``(H, W)``, ``(H, W, 1)`` (or with the batch axis) -> ``(B, H, W)``
        float64, for the images ``chw`` ``(B, 3, H, W)``."""
        a = np.asarray(values, dtype=np.float64)
        if a.ndim == 3 + batched and a.shape[-1] == 1:
            a = a[..., 0]
        shape = chw.shape[:1] + chw.shape[2:]
        if a.ndim == 2:
            a = np.broadcast_to(a, shape[:1] + a.shape)
        if a.shape != shape:
            want = f"{shape} or {shape + (1,)}" if batched else f"{shape[1:]} or {shape[1:] + (1,)}"
            raise ValueError(f"{name} must have shape {want}, got {np.shape(values)}")
        return a

    def _run(self, aif: np.ndarray, coc_px: np.ndarray, clamp_coc: bool, batched: bool) -> np.ndarray:
        """``aif`` ``(B, 3, H, W)`` float32 linear RGB (checked), ``coc_px`` ``(B, H, W)``."""
        check_finite("CoC", coc_px, " px")
        if max(-float(coc_px.min()), float(coc_px.max())) > self.contract.max_coc_px:
            over = np.abs(coc_px) > self.contract.max_coc_px
            where = format_location(np.unravel_index(int(np.argmax(np.abs(coc_px))), coc_px.shape)[1:])
            msg = (f"|CoC| up to {np.abs(coc_px).max():.3f} px at {where} ({int(over.sum())} pixels) exceeds the "
                   f"largest this file renders, {self.contract.max_coc_px:.3f} px")
            if not clamp_coc:
                # a lens file's limit is set at export (--max-coc, the learned pupil scaled beyond training)
                more = "export it again with a larger --max-coc, or " if self.has_bands else ""
                raise ValueError(f"{msg}; {more}clamp it with clamp_coc=True (--clamp-coc on the command line)")
            log.warning("%s; clamped", msg)
            coc_px = np.clip(coc_px, -self.contract.max_coc_px, self.contract.max_coc_px)
        points = self.highlights(aif, coc_px)
        active = self.active_tiles(coc_px, points)
        self.last_tiles_run = int(active.sum())
        colour, coc = self.contract.encode_inputs(aif, coc_px[:, None])
        feeds = {
            # float32 throughout: the graph takes float32, and 1 - n is exact in float32 near n = 1
            "aif": np.ascontiguousarray(colour),
            "coc": np.ascontiguousarray(coc, dtype=np.float32),
            "tile_active": active,
        }
        if self.has_bands:
            bands = self.active_bands(coc_px, active, points) & active[:, None, None]
            # a lens tile scatters its core only: with no band to run it is its pass-through (exact)
            active = active & bands.any(axis=(1, 2))
            self.last_tiles_run = int(active.sum())
            feeds["tile_active"], feeds["band_active"] = active, bands
            self.last_bands_run = int(bands.sum())
        out = self.session.run(["defocus"], feeds)[0]
        if not out.max() < 1.0:
            where = format_location(np.unravel_index(int(np.argmax(out)), out.shape)[2:])
            raise ValueError(f"the model's output saturated (normalised value {out.max()} >= 1) at {where}")
        linear = np.ascontiguousarray(self.contract.output_linear(out).transpose(0, 2, 3, 1), dtype=np.float32)
        return linear if batched else linear[0]

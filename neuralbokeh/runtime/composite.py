"""Composite a rendered CG layer over a photograph with the learned lens blur (paper section 3.4).

    python -m neuralbokeh.runtime.composite --model lens.onnx --plate photo.exr --render cg.exr \\
        --depth cg_depth.exr --alpha cg_alpha.exr --focus 2.5 --out comp.exr

The all-in-focus render (pinhole camera with the real camera's intrinsics) and its alpha are
defocused by the model with the CoC from the render's depth (planar, metres) and the focus
distance, the same kernels for both, and the blurred render is put over the plate in linear
light: ``out = model(a c) + (1 - model(a)) * plate``, ``a c`` the premultiplied render (the EXR
convention; ``--straight`` for a render that is not). A blurred foreground spreads past its
matte. ``--erode`` / ``--feather`` (px) shrink and soften a fringed matte before it is blurred.

Files: EXR and float TIFF are taken as linear. 8/16-bit PNG/TIFF inputs tagged sRGB are
linearised (OpenImageIO's colour conversion) and a PNG output is sRGB-encoded; values above 1
cannot go into a PNG and are an error unless ``--clip-ldr`` says to clip them. Channels and
layers: any input may name them, ``shot.exr:ViewLayer.Combined`` (a layer) or
``shot.exr:depth.Z`` (a channel); without a name the colour is ``R G B``, the depth ``Z`` or
``depth.Z`` and the alpha ``A``, or the one layer that has them (Blender's
``ViewLayer.Combined``, ``ViewLayer.Depth.Z``), or a depth or alpha file's only channel
(:mod:`neuralbokeh.runtime.channels`). A file that leaves the choice open is refused.
EXR data windows: every input is read in the plate's pixel coordinates over the plate's data
window (:func:`plate_frame`); overscan is cut, and a plate cropped inside its display window is
that crop of the sensor.

Sequences: put ``%04d`` (any printf integer pattern), ``####`` (one digit each) or ``$F4``
(Houdini) in any path and give ``--frames 1-48`` (or ``1001-1100x2``, every second frame);
paths without a pattern are used for every frame (a static plate, say). A focus pull is a CSV
``--focus-curve`` of ``frame,focus_m`` rows, interpolated linearly between keys.
Every output file is written atomically; a progress bar runs over the frames.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import logging
import re
import sys
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
from tqdm import tqdm

from ..core.checks import check_at_least, check_finite
from ..core.cli import HelpFormatter, run_cli
from ..core.io import (
    Window,
    image_attributes,
    image_channels,
    image_windows,
    intersect,
    place,
    prepare_output,
    read_image,
    write_image,
)
from ..core.optics import SensorWindow
from .channels import pick_channels, split_source
from .masks import erode, gaussian_blur
from .onnx_model import OnnxBokeh

log = logging.getLogger(__name__)
# frame patterns: printf (%04d, %d), Nuke/Blender hashes (####: one digit each), Houdini ($F4, $F)
_PATTERN = re.compile(r"%0?\d*d|#+|\$F\d?")


def _frame_text(token: str, frame: int) -> str:
    if token.startswith("%"):
        return token % frame
    if token.startswith("$F"):
        return f"{frame:0{int(token[2:] or 1)}d}"
    return f"{frame:0{len(token)}d}"

_LINEAR_FORMATS = (".exr", ".hdr")


def _frame_path(path: str, frame: int | None) -> Path:
    if _PATTERN.search(path):
        if frame is None:
            raise ValueError(f"{path} is a sequence pattern: give --frames")
        return Path(_PATTERN.sub(lambda m: _frame_text(m.group(0), frame), path))
    return Path(path)


def parse_frames(spec: str) -> list[int]:
    """``"1001-1100"``, ``"1001-1100x2"`` (every second frame) or ``"1001"`` -> the frame numbers.

    Raises:
        ValueError: anything else, or FIRST > LAST, or a step below 1.
    """
    m = re.fullmatch(r"(-?\d+)(?:-(-?\d+)(?:x(\d+))?)?", spec.strip())
    if not m or (m.group(2) and int(m.group(1)) > int(m.group(2))) or (m.group(3) and int(m.group(3)) < 1):
        raise ValueError(f"--frames must be FIRST, FIRST-LAST or FIRST-LASTxSTEP with FIRST <= LAST and STEP >= 1, got {spec!r}")
    first = int(m.group(1))
    return list(range(first, int(m.group(2) or first) + 1, int(m.group(3) or 1)))


def _is_ldr_srgb(path: Path) -> bool:
    if path.suffix.lower() in _LINEAR_FORMATS:
        return False
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        return False
    try:
        spec = inp.spec()
        integer = spec.format.basetype in (oiio.UINT8, oiio.UINT16)
        return integer and "srgb" in str(spec.get_string_attribute("oiio:ColorSpace")).lower()
    finally:
        inp.close()


def _convert(arr: np.ndarray, src: str, dst: str) -> np.ndarray:
    out = oiio.ImageBufAlgo.colorconvert(oiio.ImageBuf(np.ascontiguousarray(arr, dtype=np.float32)), src, dst)
    if out.has_error:
        raise OSError(f"colour conversion {src} -> {dst} failed: {out.geterror()}")
    return out.get_pixels(oiio.FLOAT).reshape(arr.shape)


def read_linear(source: str | Path, kind: str, window: Window | None = None) -> np.ndarray:
    """The channels of ``kind`` in ``source`` (``path`` or ``path:NAME``, see
    :func:`~neuralbokeh.runtime.channels.pick_channels`): ``"rgb"`` -> ``(H, W, 3)`` linear
    (sRGB-tagged 8/16-bit files linearised); ``"depth"`` or ``"alpha"`` -> ``(H, W)``.

    ``window``: the pixels ``(x, y, w, h)`` wanted, in the file's pixel coordinates (an EXR's
    data window may be larger, with overscan, or smaller): what the file's data window does not
    cover is 0, or NaN for depth (no depth there); what lies outside is cut off.
    """
    name, selector = split_source(str(source))
    path = Path(name)
    img = read_image(path, channels=pick_channels(image_channels(path), kind, selector, str(path)))
    if kind == "rgb" and _is_ldr_srgb(path):
        img = _convert(img, "sRGB", "linear")
    if window is not None:
        img = place(img, image_windows(path)[0], window, np.nan if kind == "depth" else 0.0)
    return img if kind == "rgb" else img[:, :, 0]


def plate_frame(path: Path, window: SensorWindow | None) -> tuple[Window, Window, SensorWindow | None]:
    """The pixels a composite covers, from the plate's windows: ``(frame, display, sensor window)``.

    The frame is the plate's data window within its display window: a plate's overscan lies
    beyond the sensor the lens was trained on, so it is cut off (logged). A data window inside
    the display window is a crop of the sensor: ``window`` (the display window's part of the
    sensor, default all of it) is narrowed to it.

    Raises:
        ValueError: the data window lies wholly outside the display window.
    """
    data, display = image_windows(path)
    frame = intersect(data, display)
    if frame is None:
        raise ValueError(f"{path}: its data window {data} lies outside its display window {display}")
    if frame != data:
        log.info("%s: the overscan outside the display window %s is cut off (data window %s)", path, display, data)
    if frame != display:
        x, y, w, h = (frame[0] - display[0], frame[1] - display[1], frame[2], frame[3])
        window = (window or SensorWindow()).crop((y, y + h), (x, x + w), display[3], display[2])
    return frame, display, window


# display-referred outputs: sRGB-encoded integers of this many bits (the rest are linear float)
_DISPLAY_FORMATS = {".png": 16, ".jpg": 8, ".jpeg": 8}
# header attributes of the plate a composite keeps (what editorial needs to place the frame)
PLATE_ATTRIBUTES = ("FramesPerSecond", "smpte:TimeCode", "smpte:KeyCode", "DateTime", "capDate", "utcOffset")


def write_output(path: Path, rgb: np.ndarray, clip_ldr: bool, half: bool = False,
                 attributes: dict | None = None, windows: tuple[Window, Window] | None = None) -> None:
    """EXR/TIFF: linear RGB, float32 (``half``: float16, EXR only). PNG/JPEG: sRGB-encoded
    16/8-bit (values outside [0, 1] need ``clip_ldr``). ``attributes``: header metadata.
    ``windows``: the data and display windows (EXR and TIFF; PNG and JPEG hold the pixels only)."""
    bits = _DISPLAY_FORMATS.get(path.suffix.lower())
    if half and path.suffix.lower() != ".exr":
        raise ValueError(f"--half writes float16 EXR files only, got {path}")
    if bits:
        over = int((rgb > 1.0).sum() + (rgb < 0.0).sum())
        if over and not clip_ldr:
            raise ValueError(f"{path}: {over} values outside [0, 1] (max {rgb.max():.3g}) cannot be stored in a "
                             f"{path.suffix.lower()[1:].upper()}; write .exr/.tif or pass --clip-ldr")
        encoded = np.clip(_convert(np.clip(rgb, 0.0, 1.0), "linear", "sRGB"), 0.0, 1.0)
        kind = np.uint16 if bits == 16 else np.uint8
        write_image(path, np.round(encoded * np.iinfo(kind).max).astype(kind), attributes, ["R", "G", "B"], f"uint{bits}")
    else:
        write_image(path, rgb, attributes, ["R", "G", "B"], "float16" if half else "float32", windows)


def provenance(model_path: str) -> dict[str, str]:
    """Header attributes that say how a composite was made: the model file, its SHA-256 and
    the package version (the CLI adds each frame's ``neuralbokeh:focus_m``)."""
    from .. import __version__

    digest = hashlib.sha256(Path(model_path).read_bytes()).hexdigest()
    return {"neuralbokeh:model": Path(model_path).name, "neuralbokeh:model_sha256": digest, "neuralbokeh:version": __version__}


# metres per unit of a depth map (--depth-unit)
DEPTH_UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254, "ft": 0.3048}


def depth_to_metres(values: np.ndarray, unit: str = "m", math: str = "distance", source: str = "depth") -> np.ndarray:
    """A depth channel as planar depth in metres: ``math`` ``"distance"`` (the distance in
    ``unit``) or ``"inverse"`` (1 / distance in 1 / ``unit``, 0 at infinity: Nuke's
    ScanlineRender and ZDefocus's "far = 0").

    Raises:
        ValueError: an unknown unit or math, a distance <= 0 or an inverse depth below 0
            (``source`` names it).
    """
    if unit not in DEPTH_UNITS:
        raise ValueError(f"depth unit must be one of {', '.join(DEPTH_UNITS)}, got {unit!r}")
    if math == "inverse":
        if (values < 0).any():
            raise ValueError(f"{source}: an inverse depth (1/distance) must be >= 0, got values down to {values.min():g}")
        with np.errstate(divide="ignore"):
            values = 1.0 / values.astype(np.float64)
    elif math != "distance":
        raise ValueError(f"depth math must be 'distance' or 'inverse', got {math!r}")
    elif (values <= 0).any():  # NaN (no depth) passes: it is judged where the render is
        bad = values <= 0
        hint = "; 0 at infinity is a 1/distance map: give --depth-math inverse" if (values == 0).any() else ""
        raise ValueError(f"{source}: depth must be > 0 (inf allowed), got {int(bad.sum())} pixels <= 0 "
                         f"(min {values[bad].min():g}){hint}")
    return (values * DEPTH_UNITS[unit]).astype(np.float32)


def warn_if_implausible(depth_m: np.ndarray, focal_length_mm: float, focus_m: float, source: str) -> bool:
    """Warn once, in one line, when a depth map read as metres is unlikely for the lens and the
    focus: its finite range nearer than two focal lengths or farther than 10 km, or the focus
    distance more than 10x outside it (a map in mm or cm, or an inverse one, read as metres).
    Returns whether it warned."""
    finite = depth_m[np.isfinite(depth_m) & (depth_m > 0)]
    if not finite.size:
        return False
    near, far = float(finite.min()), float(finite.max())
    if near >= 2e-3 * focal_length_mm and far <= 1e4 and near / 10.0 <= focus_m <= 10.0 * far:
        return False
    log.warning("%s: depth %.4g-%.4g m focused at %.4g m is unlikely for a %g mm lens; is it in another unit (--depth-unit) "
                "or 1/distance (--depth-math inverse)?", source, near, far, focus_m, focal_length_mm)
    return True


def read_focus_curve(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """CSV ``frame,focus_m`` (header optional) -> sorted ``(frames, focus_m)``."""
    frames, focus = [], []
    with open(path, newline="") as f:
        for n, row in enumerate(csv.reader(f), 1):
            if not row or row[0].strip().startswith("#"):
                continue
            try:
                frames.append(float(row[0]))
                focus.append(float(row[1]))
            except (ValueError, IndexError):
                if n == 1:
                    continue  # a header
                raise ValueError(f"{path}:{n}: expected 'frame,focus_m', got {row!r}") from None
    if not frames:
        raise ValueError(f"{path}: no 'frame,focus_m' rows")
    order = np.argsort(frames)
    fr, fo = np.asarray(frames)[order], np.asarray(focus)[order]
    if (fo <= 0).any() or not np.isfinite(fo).all():
        raise ValueError(f"{path}: focus distances must be finite and > 0 m, got {fo.tolist()}")
    return fr, fo


def focus_at(curve: tuple[np.ndarray, np.ndarray], frame: int) -> float:
    frames, focus = curve
    if not frames[0] <= frame <= frames[-1]:
        raise ValueError(f"frame {frame} is outside the focus curve's frames [{frames[0]:g}, {frames[-1]:g}]")
    return float(np.interp(frame, frames, focus))


def _in_focus_where_empty(depth: np.ndarray, render: np.ndarray, alpha: np.ndarray, in_focus: float) -> np.ndarray:
    """Pixels without a depth (NaN: outside the depth file's data window) are given ``in_focus``
    where the render is empty (no colour, no alpha): nothing there to blur. Elsewhere a missing
    depth is an error."""
    missing = np.isnan(depth)
    if not missing.any():
        return depth
    needed = missing & ((alpha > 0) | (render != 0).any(axis=2))
    if needed.any():
        y, x = np.argwhere(needed)[0]
        raise ValueError(f"the depth has no value at {int(needed.sum())} pixels where the render is not empty, "
                         f"first at column {x}, row {y} of the composite (a data window smaller than the render's, or NaN)")
    return np.where(missing, np.float32(in_focus), depth)


def composite_frame(model: OnnxBokeh, plate: np.ndarray, render: np.ndarray, depth: np.ndarray, alpha: np.ndarray,
                    focus_m: float | None, erode_px: int = 0, feather_px: float = 0.0, clamp_coc: bool = False,
                    window: SensorWindow | None = None, premultiplied: bool = True) -> np.ndarray:
    """One frame: the render *and its alpha* defocused by the same lens, put over the plate in
    linear light: ``out = blur(a c) + (1 - blur(a)) plate``. A blurred foreground spreads past
    its matte, and the plate shows through its blurred edge as much as the light thins there.

    Shapes: plate/render ``(H, W, 3)``, depth/alpha ``(H, W)``; alpha in [0, 1]. ``render``:
    ``focus_m`` None: ``depth`` is the signed CoC map in px already. ``render``:
    premultiplied by its alpha (the EXR convention, as Blender and Nuke write it), or straight
    when ``premultiplied`` is false (then multiplied here). The alpha is eroded (``erode_px``)
    and smoothed (``feather_px``, Gaussian sigma) before it is blurred, for mattes with
    fringes. ``window``: the plate's part of the lens's sensor when it is a crop (default: all).
    """
    for name, img in (("plate", plate), ("render", render)):
        if img.shape != (model.height, model.width, 3):
            raise ValueError(f"{name} must be {model.width}x{model.height} RGB (the model's size), got {img.shape}")
    if alpha.shape != (model.height, model.width):
        raise ValueError(f"alpha must be {model.width}x{model.height}, got {alpha.shape}")
    if not ((alpha >= 0) & (alpha <= 1)).all():
        raise ValueError(f"alpha must be in [0, 1], got values in [{alpha.min()}, {alpha.max()}]")
    for name, img in (("the plate", plate), ("the render", render)):  # named as the user knows them
        check_finite(name, img)
        check_at_least(name, img, -model.contract.normalization.offset)
    depth = _in_focus_where_empty(depth, render, alpha, 0.0 if focus_m is None else focus_m)
    a = gaussian_blur(erode(alpha.astype(np.float32), erode_px), feather_px) if erode_px or feather_px else alpha
    colour = render if premultiplied else render * alpha[:, :, None]
    if erode_px or feather_px:  # the colour follows the matte it is cut by
        colour = colour * (a / np.maximum(alpha, 1e-12))[:, :, None]
    # one batch of three: the light, its coverage and a uniform field, scattered by the same
    # kernels. Where the lens's pupil changes over the field (a cat-eye) defocused light drifts
    # and a plane of one colour comes out brighter or darker; coverage is geometric, so it is
    # divided by the uniform field's scatter, as the reference scatter does
    ones = np.ones_like(colour)
    layers = np.stack([colour, np.repeat(a[:, :, None], 3, axis=2), ones]).astype(np.float32)
    if focus_m is None:
        blurred = model.render_coc(layers, depth, clamp_coc=clamp_coc)
    else:
        blurred = model.render(layers, depth, focus_m, clamp_coc=clamp_coc, window=window)
    # per channel: a lens with chromatic blur spreads each its own way
    cover = np.clip(blurred[1] / np.maximum(blurred[2], 1e-6), 0.0, 1.0)
    return (blurred[0] + (1.0 - cover) * plate).astype(np.float32)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m neuralbokeh.runtime.composite", description=__doc__,
                                formatter_class=HelpFormatter)
    p.add_argument("--model", required=True, help="ONNX model written by export.py")
    p.add_argument("--plate", required=True, help="the photograph (background), linear RGB; FILE or FILE:LAYER")
    p.add_argument("--render", required=True, help="all-in-focus CG render, linear RGB; FILE or FILE:LAYER "
                                                  "(e.g. render.exr:ViewLayer.Combined)")
    p.add_argument("--depth", required=True, help="the render's planar depth in metres (inf allowed); FILE or FILE:CHANNEL "
                                                 "(default channel Z, depth.Z or the file's only one)")
    p.add_argument("--alpha", required=True, help="the render's object mask in [0, 1]; FILE or FILE:CHANNEL "
                                                 "(default channel A or the file's only one)")
    focus = p.add_mutually_exclusive_group()
    focus.add_argument("--focus", type=float, help="focus distance in metres")
    focus.add_argument("--focus-curve", type=Path, help="CSV of frame,focus_m (a focus pull)")
    p.add_argument("--depth-unit", choices=tuple(DEPTH_UNITS), default="m", help="the unit of --depth's distances")
    p.add_argument("--depth-math", choices=("distance", "inverse", "coc"), default="distance",
                   help="what --depth holds: the distance, 1/distance (0 at infinity, as Nuke's ScanlineRender and ZDefocus's "
                        "'far = 0'), or the signed CoC in px already (negative in front; then no --focus)")
    p.add_argument("--out", required=True, help="output file (.exr/.tif linear float, .png/.jpg sRGB 16/8-bit)")
    p.add_argument("--half", action="store_true", help="write float16 EXR (default float32)")
    p.add_argument("--overwrite", action="store_true", help="replace existing output files")
    p.add_argument("--frames", help="the frames of sequence patterns (%%04d, ####, $F4 in any path): FIRST, FIRST-LAST or "
                                    "FIRST-LASTxSTEP, e.g. 1001-1100x2; one command per render-farm chunk")
    p.add_argument("--sensor-window", type=float, nargs=4, metavar=("LEFT", "TOP", "WIDTH", "HEIGHT"),
                   help="the plate's part of the lens's sensor, as fractions of its width and height (a crop; "
                        "default: the whole sensor, 0 0 1 1)")
    p.add_argument("--straight", action="store_true",
                   help="the render is not premultiplied by its alpha (default: premultiplied, as EXR renders are)")
    p.add_argument("--erode", type=int, default=0, help="erode the alpha by this radius in px before it is blurred")
    p.add_argument("--feather", type=float, default=0.0, help="smooth the alpha by this Gaussian sigma in px before it is blurred")
    p.add_argument("--threads", type=int, default=None, help="onnxruntime threads (default: all cores)")
    p.add_argument("--clamp-coc", action="store_true", help="clamp CoCs beyond the model's range (warns) instead of failing")
    p.add_argument("--clip-ldr", action="store_true", help="clip values outside [0, 1] when writing PNG or JPEG")
    p.add_argument("--no-skip", action="store_true", help="run the network on in-focus tiles too")
    p.add_argument("--graph-optimization", choices=("auto", "off", "basic", "all"), default="auto",
                   help="onnxruntime's graph optimisation: off loads the model fastest, basic or all may render a "
                        "little faster; auto: off for one frame (a render-farm task), basic for a sequence")
    p.add_argument("-v", "--verbose", action="store_true", help="tracebacks with errors")
    return p


def _plan_frames(args: argparse.Namespace) -> tuple[list[int | None], tuple[np.ndarray, np.ndarray] | None]:
    """The frames to render and the focus curve, after every check that needs no rendering:
    outputs writable and not among the inputs, one source of focus."""
    if args.frames:
        frames: list[int | None] = list(parse_frames(args.frames))
        if not _PATTERN.search(args.out):
            raise ValueError(f"--out {args.out} needs a frame pattern such as %04d when --frames is given")
    else:
        frames = [None]
    inputs = {_frame_path(split_source(a)[0], f).resolve() for a in (args.plate, args.render, args.depth, args.alpha)
              for f in frames}
    if args.half and Path(args.out).suffix.lower() != ".exr":
        raise ValueError(f"--half writes float16 EXR files only, got --out {args.out}")
    for out in (_frame_path(args.out, frame) for frame in frames):  # before any frame is rendered
        if out.resolve() in inputs:
            raise ValueError(f"--out {out} is one of the inputs: it would be overwritten; choose another output")
        prepare_output(out, args.overwrite)
    if args.depth_math == "coc" and (args.focus is not None or args.focus_curve):
        raise ValueError("--depth-math coc takes the CoC from --depth: leave out --focus and --focus-curve")
    if args.depth_math != "coc" and args.focus is None and not args.focus_curve:
        raise ValueError("give --focus (m) or --focus-curve, or --depth-math coc with a CoC map as --depth")
    curve = read_focus_curve(args.focus_curve) if args.focus_curve else None
    if curve is not None and frames == [None]:
        raise ValueError("--focus-curve needs --frames")
    return frames, curve


class _Inputs:
    """The command's inputs per frame; those without a frame pattern are read once per use."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.static: dict[tuple[str, str, Window], np.ndarray] = {}

    def load(self, arg: str, frame: int | None, kind: str, where: Window) -> np.ndarray:
        key = (arg, kind, where)
        if not _PATTERN.search(arg) and key in self.static:
            return self.static[key]
        img = read_linear(str(_frame_path(arg, frame)), kind, where)
        if kind == "depth" and self.args.depth_math != "coc":
            img = depth_to_metres(img, self.args.depth_unit, self.args.depth_math, str(_frame_path(arg, frame)))
        if not _PATTERN.search(arg):
            self.static[key] = img
        return img


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stdout)
    try:
        frames, curve = _plan_frames(args)
        window = SensorWindow(*args.sensor_window) if args.sensor_window else None
        level = args.graph_optimization if args.graph_optimization != "auto" else "off" if len(frames) == 1 else "basic"
        model = OnnxBokeh(args.model, threads=args.threads, skip_in_focus=not args.no_skip, optimization=level)
        made_by, inputs, warned = provenance(args.model), _Inputs(args), False  # the depth range: checked on the first frame
        for frame in tqdm(frames, desc="composite", unit="frame", disable=len(frames) < 2):
            focus_m = None if args.depth_math == "coc" else args.focus if curve is None else focus_at(curve, frame)
            plate_path = Path(split_source(str(_frame_path(args.plate, frame)))[0])
            where, display, frame_window = plate_frame(plate_path, window)
            depth = inputs.load(args.depth, frame, "depth", where)
            if not warned and focus_m is not None and model.contract.lens is not None:
                warn_if_implausible(depth, model.contract.lens.focal_length_mm, focus_m, str(args.depth))
                warned = True
            comp = composite_frame(model, inputs.load(args.plate, frame, "rgb", where),
                                   inputs.load(args.render, frame, "rgb", where), depth,
                                   inputs.load(args.alpha, frame, "alpha", where), focus_m,
                                   args.erode, args.feather, args.clamp_coc, frame_window, not args.straight)
            out = _frame_path(args.out, frame)
            attributes = {**image_attributes(plate_path, PLATE_ATTRIBUTES), **made_by}
            if focus_m is not None:
                attributes["neuralbokeh:focus_m"] = float(focus_m)
            write_output(out, comp, args.clip_ldr, args.half, attributes, (where, display))
            log.info("wrote %s (%s, %d of %d tiles through the network)", out,
                     "the CoC map's blur" if focus_m is None else f"focus {focus_m:.3f} m", model.last_tiles_run, model.num_tiles)
    except (FileNotFoundError, ValueError, OSError) as e:
        raise SystemExit(f"error: {e}")
    return 0

if __name__ == "__main__":
    sys.exit(run_cli(main))

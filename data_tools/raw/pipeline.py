"""One focal stack folder -> one dataset scene: the pipeline behind ``python -m data_tools.raw``
(see its doc): decode, align, crop, resize, fuse, depth from focus, CoC maps, write."""

from __future__ import annotations

import argparse
import csv
import logging
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from neuralbokeh import __version__
from neuralbokeh.core.io import read_image
from neuralbokeh.core.optics import SensorWindow, ThinLens
from neuralbokeh.data.dataset import write_scene

from .align import align_stack
from .decode import (
    RAW_EXTENSIONS,
    DecodeSettings,
    RawDecodeError,
    decode,
    read_metadata,
    white_balance,
)
from .developed import DEVELOPED_EXTENSIONS, decode_developed, exposure_gains
from .fuse import fuse_stack

log = logging.getLogger("data_tools.raw")


def _area_resize(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    w, h = size
    x = torch.from_numpy(np.ascontiguousarray(np.atleast_3d(img).transpose(2, 0, 1), dtype=np.float64))[None]
    out = F.interpolate(x, size=(h, w), mode="area")[0].numpy().transpose(1, 2, 0)
    return out if img.ndim == 3 else out[..., 0]


def _focus_from_csv(path: Path) -> dict[str, float]:
    table = {}
    with open(path, newline="") as f:
        for n, row in enumerate(csv.reader(f), 1):
            if not row or row[0].startswith("#"):
                continue
            try:
                table[Path(row[0].strip()).name] = float(row[1])
            except (ValueError, IndexError):
                if n > 1:
                    raise ValueError(f"{path}:{n}: expected 'file,focus_m', got {row!r}") from None
    return table


def stack_files(folder: Path) -> tuple[list[Path], bool]:
    """The stack's image files in name order and whether they are developed (not RAW)."""
    visible = [p for p in sorted(folder.iterdir()) if not p.name.startswith(".")]
    raw = [p for p in visible if p.suffix.lower() in RAW_EXTENSIONS]
    developed = [p for p in visible if p.suffix.lower() in DEVELOPED_EXTENSIONS]
    if raw and developed:
        raise ValueError(f"{folder}: mixes RAW ({raw[0].name}, ...) and developed files ({developed[0].name}, ...); "
                         "one kind per stack")
    files = raw or developed
    if len(files) < 2:
        raise ValueError(f"{folder}: a focal stack needs >= 2 RAW, TIFF, PNG or JPEG files, found {len(files)}")
    return files, not raw


def focus_distances(files: list[Path], metas: list[dict], args: argparse.Namespace) -> list[float]:
    if args.focus_distances or args.focus_diopters:
        flag = "--focus-distances" if args.focus_distances else "--focus-diopters"
        try:
            values = [float(v) for v in (args.focus_distances or args.focus_diopters).split(",")]
        except ValueError:
            raise ValueError(f"{flag} must be comma-separated numbers, got {args.focus_distances or args.focus_diopters!r}") from None
        if len(values) != len(files):
            raise ValueError(f"{flag} has {len(values)} values for {len(files)} files in {files[0].parent}")
        if args.focus_diopters:
            bad = [v for v in values if not v >= 0]
            if bad:
                raise ValueError(f"--focus-diopters must be >= 0 (1/m; 0 = infinity), got {bad[0]}")
            values = [float("inf") if v == 0 else 1.0 / v for v in values]
        return values
    if args.focus_csv:
        table = _focus_from_csv(args.focus_csv)
        missing = [f.name for f in files if f.name not in table]
        if missing:
            raise ValueError(f"{args.focus_csv} has no focus distance for {missing}")
        return [table[f.name] for f in files]
    missing = [f.name for f, m in zip(files, metas) if m["focus_distance_m"] is None]
    if missing:
        raise ValueError(f"no focus distance in the metadata of {missing}: give --focus-distances or --focus-csv")
    return [m["focus_distance_m"] for m in metas]


def lens_for(metas: list[dict], args: argparse.Namespace, stack: Path) -> ThinLens:
    def pick(option: float | None, key: str, flag: str, unit: str) -> float:
        if option is not None:
            return option
        values = {m[key] for m in metas if m[key] is not None}
        if not values:
            raise ValueError(f"{stack}: no {key.replace('_', ' ')} in the metadata: give {flag} ({unit})")
        if len(values) > 1:
            raise ValueError(f"{stack}: the files disagree on {key} ({sorted(values)}): give {flag}")
        return values.pop()

    if args.sensor_width is None:
        raise ValueError("cameras do not record the sensor width: give --sensor-width (mm, long side)")
    return ThinLens(pick(args.focal_length, "focal_length_mm", "--focal-length", "mm"),
                    pick(args.f_number, "f_number", "--f-number", "f-number"), args.sensor_width)


def process_stack(stack: Path, out: Path, args: argparse.Namespace, failures: list[str]) -> dict[str, Any] | None:
    """Decode, align, fuse and write one stack; returns a summary (None if skipped)."""
    folder = out / stack.name
    if folder.exists():
        return None
    files, metas, focus, developed = _stack_by_focus(stack, args)
    lens = lens_for(metas, args, stack)
    settings = DecodeSettings(args.demosaic, args.half_size)
    wb = None if developed else white_balance(files[len(files) // 2], args.white_balance)
    # stages of one stack (decoding is most of it); shown on a terminal only (disable=None)
    bar = tqdm(total=len(files) + 2, desc=f"{stack.name}: decode", unit="step", leave=False, disable=None)
    images, kept = _decode_all(stack, files, focus, lambda f: decode_developed(f, args.transfer) if developed
                               else decode(f, wb, settings), failures, bar)
    decoded_h, decoded_w = images[0].shape[:2]
    ref = len(images) // 2  # the middle of the usable slices
    images, gains, exposure = _equalise(stack, images, ref, developed, kept[ref][0])
    bar.set_description(f"{stack.name}: align")
    if args.no_align:
        aligned, info, crop = images, [], (slice(0, decoded_h), slice(0, decoded_w))
    else:
        aligned, info, crop = align_stack(images, ref, rotation=args.rotation)
    crop_h, crop_w = aligned[0].shape[:2]
    size = tuple(args.size) if args.size else (crop_w, crop_h)
    if size != (crop_w, crop_h):
        aligned = [_area_resize(a, size) for a in aligned]
    focus_kept = [fm for _, fm in kept]
    bar.update()
    bar.set_description(f"{stack.name}: fuse and write")
    fused = _fuse(aligned, focus_kept, args, crop, (decoded_h, decoded_w), size)
    # the camera's lens on its whole sensor (the same for every stack it shot); the scene is the
    # alignment crop's window on that sensor, so its CoC maps are in the output's own pixels
    scene_lens = ThinLens(lens.focal_length_mm, lens.f_number, lens.sensor_width_mm * decoded_w / max(decoded_h, decoded_w))
    window = SensorWindow.from_crop((crop[0].start, crop[0].stop), (crop[1].start, crop[1].stop), decoded_h, decoded_w)
    cocs = [scene_lens.coc_px(fused.depth_m.astype(np.float64), fm, size[0], signed=True, window=window)
            for fm in focus_kept]
    generator = {
        "name": "data_tools.raw", "version": __version__, "stack": str(stack),
        "files": [f.name for f, _ in kept], "failed": [s for s in failures if str(stack) in s],
        "metadata": [m for m, f in zip(metas, files) if f in {k for k, _ in kept}],
        "source": "developed" if developed else "raw",
        "white_balance": None if wb is None else list(wb), "exposure_factor": exposure,
        "transfer": args.transfer if developed else None, "exposure_gains": gains,
        "demosaic": None if developed else settings.demosaic, "half_size": settings.half_size, "reference_slice": ref,
        "alignment": [a.to_dict() for a in info], "crop": {"rows": [crop[0].start, crop[0].stop],
                                                           "cols": [crop[1].start, crop[1].stop]},
        "output_size": list(size), "depth_source": str(args.depth) if args.depth else "depth from focus",
        "depth_confidence_mean": float(fused.confidence.mean()), "sensor_width_mm_given": lens.sensor_width_mm,
    }
    write_scene(folder, fused.aif.astype(np.float64), fused.depth_m.astype(np.float64),
                [a.astype(np.float64) for a in aligned], cocs, scene_lens, focus_kept, None, generator, window)
    bar.update()
    bar.close()
    residual = max((a.residual_px for a in info), default=0.0)
    return {"stack": stack.name, "slices": len(aligned), "size": size, "residual_px": residual,
            "max_coc_px": float(max(np.abs(c).max() for c in cocs))}


def _stack_by_focus(stack: Path, args: argparse.Namespace) -> tuple[list[Path], list[dict], list[float], bool]:
    """The stack's files, their metadata and focus distances (m), sorted near to far
    (neighbours are then defocused alike), and whether they are developed files."""
    files, developed = stack_files(stack)
    metas = [read_metadata(f) for f in files]
    focus = focus_distances(files, metas, args)
    bad = [(f.name, d) for f, d in zip(files, focus) if not d > 0]
    if bad:
        raise ValueError(f"{stack}: focus distances must be > 0 m (inf allowed), got {bad}")
    order = sorted(range(len(files)), key=lambda i: focus[i])
    return [files[i] for i in order], [metas[i] for i in order], [focus[i] for i in order], developed


def _decode_all(stack: Path, files: list[Path], focus: list[float], decode_file: Any, failures: list[str],
                bar: Any) -> tuple[list[np.ndarray], list[tuple[Path, float]]]:
    """Every slice that decodes (``decode_file``), with its ``(file, focus_m)``; the others are
    named in ``failures``. ``ValueError`` if fewer than 2 decode or their sizes differ."""
    images, kept = [], []
    for f, fm in zip(files, focus):
        bar.update()
        try:
            images.append(decode_file(f))
            kept.append((f, fm))
        except RawDecodeError as e:
            failures.append(str(e))
            log.error("%s", e)
    if len(images) < 2:
        raise ValueError(f"{stack}: fewer than 2 usable slices")
    shapes = {im.shape for im in images}
    if len(shapes) != 1:
        raise ValueError(f"{stack}: slices have different sizes {sorted(shapes)}")
    return images, kept


def _equalise(stack: Path, images: list[np.ndarray], ref: int, developed: bool,
              ref_file: Path) -> tuple[list[np.ndarray], list[float], float]:
    """Developed slices' exposures matched to slice ``ref``'s, then one factor for all that puts
    the reference's mean at 0.18: ``(images, gains, exposure factor)``."""
    gains = exposure_gains(images, ref) if developed else [1.0] * len(images)
    if developed:
        images = [im * np.float32(g) for im, g in zip(images, gains)]
        log.info("%s: exposure gains against slice %d: %s", stack, ref, ", ".join(f"{g:.3f}" for g in gains))
    y = images[ref].mean()
    if y <= 0:
        raise ValueError(f"{stack}: the reference slice {ref_file.name} is black")
    exposure = 0.18 / float(y)
    return [im * exposure for im in images], gains, exposure


def _fuse(aligned: list[np.ndarray], focus_m: list[float], args: argparse.Namespace, crop: tuple[slice, slice],
          decoded: tuple[int, int], size: tuple[int, int]) -> Any:
    """The all-in-focus image and depth of the aligned slices (from focus, or from ``--depth``,
    a map at the decoded size, cut to the alignment crop and resized to ``size`` in diopters)."""
    if not args.depth:
        return fuse_stack(aligned, focus_m, args.window)
    depth_in = read_image(args.depth)[..., 0].astype(np.float64)
    if depth_in.shape != decoded:
        raise ValueError(f"--depth {args.depth} is {depth_in.shape[1]}x{depth_in.shape[0]}, the decoded stack "
                         f"{decoded[1]}x{decoded[0]}")
    with np.errstate(divide="ignore"):
        dio = _area_resize(1.0 / depth_in[crop], size)  # average in diopters: inf depth -> 0
    return fuse_stack(aligned, focus_m, args.window, known_diopters=dio)

"""Validate a dataset before any work is spent on it (``python -m neuralbokeh.data check ROOT``).

Every file of every scene is read whole (a truncated EXR fails here, not at step 4 of a run) and
checked against ``scene.json``: the image size and channels, finite values, colours >= 0, depth
> 0 m (``+inf`` allowed), the CoC finite and equal to what the scene's lens gives for its depth
and the slice's focus distance (``ThinLens.coc_px``, within ``coc_tolerance``), and the
recorded largest |CoC|. Problems are collected, not raised one by one, so a user sees every bad
file at once. ``train`` and ``neuralbokeh.evaluation.evaluate`` run it before they start.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..core.cli import HelpFormatter
from ..core.io import read_image
from ..core.optics import SensorWindow, ThinLens
from .dataset import find_scenes, read_scene_meta

log = logging.getLogger(__name__)

# |CoC file - lens(depth, focus)| allowed, px: relative to the CoC (float32/half files) plus an absolute floor
COC_RTOL, COC_ATOL = 2e-3, 2e-3


def _first_bad(mask: np.ndarray) -> str:
    r, c = np.unravel_index(int(np.argmax(mask)), mask.shape[:2])
    return f"{int(mask.sum())} pixel(s), first at (row {r}, col {c})"


def check_scene(folder: str | os.PathLike, coc_tolerance: tuple[float, float] = (COC_RTOL, COC_ATOL)) -> list[str]:
    """Problems found in one scene folder (empty: the scene is sound). Each names the file."""
    folder = Path(folder)
    try:
        meta = read_scene_meta(folder)
    except (OSError, ValueError) as e:
        return [str(e)]
    problems: list[str] = []
    h, w = meta["image_size"]["height"], meta["image_size"]["width"]

    def load(name: str, channels: int) -> np.ndarray | None:
        try:
            arr = read_image(folder / name)
        except OSError as e:
            problems.append(f"{folder / name}: unreadable ({' '.join(str(e).split())[:200]})")
            return None
        if arr.shape != (h, w, channels):
            problems.append(f"{folder / name}: shape (H, W, C) {arr.shape}, expected {(h, w, channels)} from scene.json")
            return None
        return arr

    def colour(name: str) -> None:
        arr = load(name, 3)
        if arr is None:
            return
        if not np.isfinite(arr).all():
            problems.append(f"{folder / name}: non-finite colour at {_first_bad(~np.isfinite(arr).all(-1))}")
        elif (arr < 0).any():
            problems.append(f"{folder / name}: negative colour (min {arr.min():.4g}) at {_first_bad((arr < 0).any(-1))}")

    colour(meta["files"]["aif"])
    depth = load(meta["files"]["depth"], 1)
    if depth is not None:
        depth = depth[..., 0].astype(np.float64)
        bad = np.isnan(depth) | (depth <= 0) | (depth == -np.inf)
        if bad.any():
            problems.append(f"{folder / meta['files']['depth']}: depth must be > 0 m (+inf allowed), got "
                            f"{depth[bad].flat[0]} at {_first_bad(bad)}")
            depth = None
    lens, window = _scene_lens(folder, meta, problems)
    largest = 0.0
    rtol, atol = coc_tolerance
    for k, sl in enumerate(meta["slices"]):
        colour(sl["defocus"])
        coc = load(sl["coc"], 1)
        if coc is None:
            continue
        coc = coc[..., 0].astype(np.float64)
        if not np.isfinite(coc).all():
            problems.append(f"{folder / sl['coc']}: non-finite CoC at {_first_bad(~np.isfinite(coc))}")
            continue
        largest = max(largest, float(np.abs(coc).max()))
        if depth is not None and lens is not None:
            problems += _coc_problems(folder, k, sl, coc, depth, lens, window, w, coc_tolerance)
    recorded = float(meta["max_abs_coc_px"])
    if largest > recorded * (1 + rtol) + atol:
        problems.append(f"{folder / 'scene.json'}: max_abs_coc_px {recorded:.4g} is below the largest |CoC| of "
                        f"its files, {largest:.4g} px")
    return problems


def _scene_lens(folder: Path, meta: dict, problems: list[str]) -> tuple[ThinLens | None, SensorWindow | None]:
    """The scene's lens and sensor window, or ``(None, None)`` with a problem added."""
    try:
        return ThinLens.from_dict(meta["lens"]), SensorWindow.from_dict(meta.get("sensor_window"))
    except (KeyError, TypeError, ValueError) as e:
        problems.append(f"{folder / 'scene.json'}: bad lens {meta['lens']!r} or sensor window "
                        f"{meta.get('sensor_window')!r} ({e})")
        return None, None


def _coc_problems(folder: Path, k: int, sl: dict, coc: np.ndarray, depth: np.ndarray, lens: ThinLens,
                  window: SensorWindow, width: int, coc_tolerance: tuple[float, float]) -> list[str]:
    """Where slice ``k``'s CoC map (px) disagrees with its depth (m), lens and focus distance."""
    rtol, atol = coc_tolerance
    try:
        want = lens.coc_px(depth, float(sl["focus_m"]), width, signed=True, window=window)
    except (KeyError, ValueError) as e:
        return [f"{folder / 'scene.json'}: slice {k}: {e}"]
    off = np.abs(coc - want) > rtol * np.abs(want) + atol
    if not off.any():
        return []
    i = np.unravel_index(int(np.argmax(np.abs(coc - want))), coc.shape)
    return [f"{folder / sl['coc']}: CoC differs from the lens and focus of scene.json (focus {sl['focus_m']} m) by up to "
            f"{abs(coc[i] - want[i]):.4g} px ({coc[i]:.4g} vs {want[i]:.4g} at (row {i[0]}, col {i[1]})), {_first_bad(off)}"]


def shared_lens_problems(scenes: Sequence[Path]) -> list[str]:
    """One problem per ``scene.json`` entry that the scenes must share but do not: the lens and
    the aperture (one model learns one lens; image sizes may differ, a model trains on crops)."""
    problems = []
    metas = {}
    for folder in scenes:
        try:
            metas[folder] = read_scene_meta(folder)
        except (OSError, ValueError):
            continue  # reported by check_scene
    for key, plural in (("lens", "lenses"), ("aperture", "apertures")):
        groups: dict[str, list[str]] = {}
        for folder, meta in metas.items():
            groups.setdefault(json.dumps(meta.get(key), sort_keys=True), []).append(folder.name)
        if len(groups) > 1:
            said = "; ".join(f"{value} in {len(names)} ({', '.join(names[:3])}{', ...' if len(names) > 3 else ''})"
                             for value, names in sorted(groups.items(), key=lambda g: -len(g[1])))
            problems.append(f"the scenes have {len(groups)} different {plural} (one model learns one lens): {said}")
    return problems


def check_dataset(roots: str | os.PathLike | Sequence[str | os.PathLike], progress: bool = False) -> list[str]:
    """Problems found in every scene under ``roots`` (empty: the dataset is sound).

    Raises:
        FileNotFoundError / ValueError: a root is missing or holds no scenes (see ``find_scenes``).
    """
    scenes = find_scenes(roots)
    it = scenes
    if progress:
        from tqdm import tqdm

        it = tqdm(scenes, desc="checking scenes", unit="scene")
    problems = [p for folder in it for p in check_scene(folder)] + shared_lens_problems(scenes)
    log.debug("checked %d scenes: %d problem(s)", len(scenes), len(problems))
    return problems


def require_sound(roots: str | os.PathLike | Sequence[str | os.PathLike], progress: bool = False) -> None:
    """:func:`check_dataset`, raising one ``ValueError`` that lists every problem (at most 20 shown)."""
    problems = check_dataset(roots, progress)
    if problems:
        shown = "; ".join(problems[:20]) + (f"; ... and {len(problems) - 20} more" if len(problems) > 20 else "")
        raise ValueError(f"dataset check failed ({len(problems)} problem(s); run `python -m neuralbokeh.data check` "
                         f"for the list): {shown}")


def main(argv: list[str] | None = None) -> int:
    """``python -m neuralbokeh.data check ROOT [ROOT ...]``: validate datasets (:func:`check_dataset`)."""
    p = argparse.ArgumentParser(prog="python -m neuralbokeh.data", description=main.__doc__, formatter_class=HelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)
    check = sub.add_parser("check", help="read every file of every scene and check it against scene.json",
                           formatter_class=HelpFormatter)
    check.add_argument("roots", nargs="+", help="dataset folders (each holding scene folders)")
    check.add_argument("-v", "--verbose", action="store_true", help="tracebacks with errors")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stdout)  # the report is the CLI's output
    t = time.perf_counter()
    problems = check_dataset(args.roots, progress=sys.stderr.isatty())
    for line in problems:
        log.info("%s", line)
    log.info("%d scene(s) checked in %.1f s: %s", len(find_scenes(args.roots)), time.perf_counter() - t,
             f"{len(problems)} problem(s)" if problems else "no problems")
    return 1 if problems else 0

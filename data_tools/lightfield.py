"""4D light fields -> training triples: ``python -m data_tools.lightfield VIEWS --disparity FILE --out DIR``.

A light field of N x N views holds real defocus with a true all-in-focus image and true depth:
its centre view is the all-in-focus image, and averaging its views shifted by a focus disparity
``d0`` is physical refocusing through the aperture the views span (the playback method of
``../shared/papers/lightfield-compression-playback-patent.txt``). A point of disparity ``d`` is
then spread over the N x N view positions ``|d - d0|`` px apart: its blur is the aperture the
views sample, of side ``N |d - d0|`` px (each view one cell of the pupil square), so the signed
CoC is ``N (d0 - d)`` (negative in front: a larger disparity is nearer).

Conventions:
    * Views: view ``k = N row + col`` (the HCI layout), row 0 at the top. In view ``(row, col)``
      a point of disparity ``d`` lies at ``x + sx d (col - c), y + sy d (row - c)`` of its centre
      view position (``c`` the centre index). The signs ``(sx, sy)`` differ between data sets;
      :func:`estimate_signs` picks those that make the views agree at the true disparity.
    * Weights (a synthetic aperture, ``--aperture``): view ``(row, col)`` is the pupil cell whose
      image it carries, so each view is weighted by the shape's transmission at that cell's
      centre (and, with ``--cat-eye``, by whether the pixel's vignetting circle passes it).
      The declared aperture of such a scene is that grid of weighted points (``ViewGrid``), the
      exact discrete aperture at every CoC; without ``--aperture`` every view counts and the scene declares none
      (the learner finds the lens, as for a photograph).
    * Depth: disparity is affine in 1/depth. ``--depth-range NEAR FAR`` (m) places the largest
      and smallest disparity; the scene's ``ThinLens`` then reproduces every CoC map through
      the package's own CoC function. Refocusing keeps the image scale, which a thin lens does
      only as focal length / distance -> 0: the lens is a virtual one of ``--focal-length``
      1e-3 mm (the default), which keeps the mismatch below 1e-4 px; its f-number follows
      from the views' baseline and is far below 1, as a camera array's synthetic aperture is.
"""

from __future__ import annotations

import argparse
import logging
import math
import re
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from neuralbokeh import __version__
from neuralbokeh.core.apertures import ApertureModel, ViewGrid, field_position, parse_aperture
from neuralbokeh.core.cli import HelpFormatter, run_cli
from neuralbokeh.core.io import prepare_output, read_image
from neuralbokeh.core.optics import ThinLens
from neuralbokeh.data.dataset import write_scene

from .raw.developed import decode_developed

log = logging.getLogger("data_tools.lightfield")
_HCI = re.compile(r"input_Cam(\d+)\.\w+$")


def load_views(source: str | Path, pattern: str | None = None, transfer: str = "srgb") -> np.ndarray:
    """An N x N light field as ``(N, N, H, W, 3)`` float32 linear RGB.

    Args:
        source: a folder of view images (``pattern``, or HCI's ``input_Cam000.png`` ...), or a
            ``.npy`` stack ``(N, N, H, W, 3)`` / ``(N * N, H, W, 3)`` already linear.
        pattern: a file name with one integer field for the view index, e.g. ``view_{:03d}.exr``.
        transfer: how integer images were encoded (``srgb``, ``linear``, ``gamma:G``); float
            images (EXR) are taken as linear.

    Raises:
        ValueError: the number of views is not a square, or the views differ in size.
        FileNotFoundError: no views found.
    """
    source = Path(source)
    if source.suffix == ".npy":
        views = np.load(source).astype(np.float32)
    else:
        files = _view_files(source, pattern)
        views = np.stack([_read_view(f, transfer) for f in tqdm(files, desc="views", unit="view",
                                                                  disable=not sys.stderr.isatty())])
    if views.ndim == 4:
        n = math.isqrt(views.shape[0])
        if n * n != views.shape[0]:
            raise ValueError(f"{source}: {views.shape[0]} views is not an N x N grid")
        views = views.reshape(n, n, *views.shape[1:])
    if views.ndim != 5 or views.shape[0] != views.shape[1] or views.shape[-1] != 3 or views.shape[0] < 3 or views.shape[0] % 2 == 0:
        raise ValueError(f"{source}: expected views (N, N, H, W, 3) with N odd (the centre view is the all-in-focus "
                         f"image), got {views.shape}")
    if not np.isfinite(views).all() or (views < 0).any():
        raise ValueError(f"{source}: view colours must be finite and >= 0")
    return views


def _view_files(folder: Path, pattern: str | None) -> list[Path]:
    if not folder.is_dir():
        raise FileNotFoundError(f"no such folder of views: {folder}")
    if pattern is None:
        found = {int(m.group(1)): p for p in folder.iterdir() if (m := _HCI.search(p.name))}
        if not found:
            raise FileNotFoundError(f"{folder}: no input_CamNNN views; give --pattern, e.g. 'view_{{:03d}}.exr'")
        files = [found[k] for k in sorted(found)]
        if sorted(found) != list(range(len(found))):
            raise ValueError(f"{folder}: views input_Cam{{k}} must be numbered 0..{len(found) - 1} without gaps")
        return files
    files = []
    while (folder / pattern.format(len(files))).is_file():
        files.append(folder / pattern.format(len(files)))
    if not files:
        raise FileNotFoundError(f"{folder}: no view {pattern.format(0)}")
    return files


def _read_view(path: Path, transfer: str) -> np.ndarray:
    if path.suffix.lower() in (".exr", ".hdr", ".pfm"):
        return read_image(path)[:, :, :3]
    return decode_developed(path, transfer)


def load_disparity(path: str | Path) -> np.ndarray:
    """A disparity map ``(H, W)`` float32 in px (larger = nearer): PFM (stored bottom row
    first, turned here so row 0 is the top), EXR/TIFF (first channel) or ``.npy``."""
    path = Path(path)
    if path.suffix == ".npy":
        disp = np.load(path)
    else:
        disp = read_image(path)[:, :, 0]
        if path.suffix.lower() == ".pfm":  # OpenImageIO returns PFM rows in file order
            disp = disp[::-1]
    disp = np.ascontiguousarray(disp, dtype=np.float32)
    if disp.ndim != 2 or not np.isfinite(disp).all():
        raise ValueError(f"{path}: a disparity map must be a finite (H, W) array, got shape {disp.shape}")
    return disp


def view_offsets(n: int) -> tuple[np.ndarray, np.ndarray]:
    """``(du, dv)`` of every view, ``(N, N)`` each: its column and row minus the centre's."""
    c = (n - 1) / 2.0
    rows, cols = np.meshgrid(np.arange(n) - c, np.arange(n) - c, indexing="ij")
    return cols, rows


def _shift(view: torch.Tensor, dx: torch.Tensor | float, dy: torch.Tensor | float) -> tuple[torch.Tensor, torch.Tensor]:
    """Sample ``view`` ``(3, H, W)`` at ``(x + dx, y + dy)`` (bilinear; ``dx``/``dy`` scalars or
    ``(H, W)``); returns the samples and where they fell inside the image ``(H, W)``."""
    _, h, w = view.shape
    ys, xs = torch.meshgrid(torch.arange(h, dtype=view.dtype), torch.arange(w, dtype=view.dtype), indexing="ij")
    x, y = xs + dx, ys + dy
    grid = torch.stack([(2 * x + 1) / w - 1, (2 * y + 1) / h - 1], dim=-1)[None]  # align_corners=False
    out = F.grid_sample(view[None], grid, mode="bilinear", padding_mode="zeros", align_corners=False)[0]
    inside = ((x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)).to(view.dtype)
    return out, inside


def pupil_of_views(n: int, signs: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The pupil coordinates ``(u right, v up)`` in [-1, 1] of each view's cell centre ``(N, N)``:
    behind the focus a view's image lands where its pupil cell does in the package's kernels."""
    du, dv = view_offsets(n)
    return -signs[0] * du * 2.0 / n, signs[1] * dv * 2.0 / n


def view_weights(n: int, signs: tuple[int, int], aperture: ApertureModel | None) -> np.ndarray:
    """Each view's weight ``(N, N)``: the aperture shape's transmission at its pupil cell
    (all ones without an aperture)."""
    if aperture is None:
        return np.ones((n, n))
    u, v = pupil_of_views(n, signs)
    w = aperture.shape.transmission(u, v)
    if not w.any():
        raise ValueError(f"the aperture {aperture.shape.to_dict()} passes none of the {n}x{n} view positions")
    return w


def discrete_aperture(weights: np.ndarray, signs: tuple[int, int], cat_eye: float = 0.0) -> ApertureModel:
    """The exact discrete aperture of a weighted refocus: the weights at the views' places in
    the pupil (row 0 at v = +1), each view a point (:class:`~neuralbokeh.core.apertures.ViewGrid`)."""
    u, v = pupil_of_views(weights.shape[0], signs)
    n = weights.shape[0]
    placed = np.zeros_like(weights, dtype=np.float64)
    rows = np.rint((1.0 - v) * n / 2.0 - 0.5).astype(int)
    cols = np.rint((u + 1.0) * n / 2.0 - 0.5).astype(int)
    placed[rows, cols] = weights / weights.max()
    return ApertureModel(ViewGrid(placed), cat_eye=cat_eye)


def refocus(views: np.ndarray, d0: float, signs: tuple[int, int], weights: np.ndarray | None = None,
            cat_eye: ApertureModel | None = None) -> np.ndarray:
    """Shift-and-add refocus at focus disparity ``d0`` (px): ``sum_k w_k view_k(x + s d0 offset_k)
    / sum_k w_k``, over the views whose shifted sample falls inside the image.

    Args:
        views: ``(N, N, H, W, 3)`` linear RGB.
        d0: the disparity brought into focus, px.
        signs: ``(sx, sy)``, see the module docstring.
        weights: ``(N, N)`` view weights (default all ones: the plain mean).
        cat_eye: with ``cat_eye > 0``, each view also counts only where the pixel's vignetting
            circle passes its pupil cell (the weights then depend on the field position).

    Returns:
        ``(H, W, 3)`` float32.
    """
    n, _, h, w, _ = views.shape
    weights = np.ones((n, n)) if weights is None else np.asarray(weights, dtype=np.float64)
    du, dv = view_offsets(n)
    pu, pv = pupil_of_views(n, signs)
    if cat_eye is not None and cat_eye.cat_eye > 0:
        fx, fy = field_position(np.arange(h)[:, None] + 0.0, np.arange(w)[None, :] + 0.0, h, w)
    total = torch.zeros(3, h, w, dtype=torch.float64)
    norm = torch.zeros(h, w, dtype=torch.float64)
    for r in range(n):
        for c in range(n):
            if weights[r, c] == 0:
                continue
            view = torch.from_numpy(views[r, c]).permute(2, 0, 1).double()
            out, inside = _shift(view, signs[0] * d0 * du[r, c], signs[1] * d0 * dv[r, c])
            wk = inside * weights[r, c]
            if cat_eye is not None and cat_eye.cat_eye > 0:
                wk = wk * torch.from_numpy(np.asarray(cat_eye.transmits(pu[r, c], pv[r, c], fx, fy), dtype=np.float64))
            total += out * wk
            norm += wk
    if (norm <= 0).any():
        raise ValueError(f"no view reaches {int((norm <= 0).sum())} pixels at focus disparity {d0:g} px")
    return (total / norm).permute(1, 2, 0).numpy().astype(np.float32)


def view_disagreement(views: np.ndarray, disparity: np.ndarray, signs: tuple[int, int]) -> float:
    """Mean variance across the views after warping each to the centre view by the disparity map
    (``signs``): near zero, but for occlusions and noise, with the right signs."""
    n = views.shape[0]
    du, dv = view_offsets(n)
    disp = torch.from_numpy(disparity).double()
    total = total2 = count = 0.0
    for r in range(n):
        for c in range(n):
            view = torch.from_numpy(views[r, c]).permute(2, 0, 1).double()
            out, inside = _shift(view, signs[0] * disp * du[r, c], signs[1] * disp * dv[r, c])
            total, total2, count = total + out * inside, total2 + out * out * inside, count + inside
    count = count.clamp(min=1.0)
    return float((total2 / count - (total / count) ** 2).clamp(min=0.0).mean())  # no rounding below 0


# the chosen signs' disagreement must be below this share of the next pair's, or the views do not
# tell (a scene nearly at one disparity, or noise above the parallax); HCI's backgammon gives 0.66
SIGN_MARGIN = 0.8


def estimate_signs(views: np.ndarray, disparity: np.ndarray) -> tuple[tuple[int, int], dict[tuple[int, int], float]]:
    """The shift signs ``(sx, sy)`` that minimise :func:`view_disagreement`, and every pair's.

    Raises:
        ValueError: no pair is clearly best (below ``SIGN_MARGIN`` of the next): give the signs.
    """
    scores = {(sx, sy): view_disagreement(views, disparity, (sx, sy)) for sx in (1, -1) for sy in (1, -1)}
    best, second = sorted(scores, key=scores.get)[:2]
    if not scores[best] < SIGN_MARGIN * scores[second]:
        raise ValueError(f"the views do not tell which way points move between them (cross-view variance "
                         f"{scores[best]:.3g} with signs {best}, {scores[second]:.3g} with {second}): give --signs SX SY")
    return best, scores


def lens_for_disparity(disparity: np.ndarray, n: int, width_px: int, depth_range_m: tuple[float, float] | None,
                       focal_length_mm: float = 1e-3, sensor_width_mm: float = 36.0,
                       mapping: tuple[float, float] | None = None) -> tuple[ThinLens, float, float]:
    """The virtual lens and the depth mapping ``depth = beta / (disparity - alpha)`` (m) that make
    ``lens.coc_px`` equal ``N (d0 - d)``: returns ``(lens, alpha px, beta px m)``.

    ``mapping``: ``(alpha, beta)`` given (the camera's: scenes of one camera then share a lens);
    else ``depth_range_m`` ``(near, far)`` places the largest disparity at near, the smallest at far.

    Raises:
        ValueError: near >= far, a flat disparity map, beta <= 0, or a disparity at or below alpha.
    """
    d_max, d_min = float(disparity.max()), float(disparity.min())
    if mapping is not None:
        alpha, beta = (float(v) for v in mapping)
        if not beta > 0 or d_min < alpha:
            raise ValueError(f"--disparity-to-depth ALPHA BETA needs BETA > 0 and every disparity at or above ALPHA "
                             f"(the disparity at infinity), got {alpha:g} {beta:g} for disparities down to {d_min:.4g}")
    else:
        near, far = depth_range_m
        if not 0 < near < far:
            raise ValueError(f"--depth-range NEAR FAR must have 0 < NEAR < FAR m, got {near} {far}")
        if d_max - d_min <= 0:
            raise ValueError("the disparity map is flat: no depth range to place")
        beta = (d_max - d_min) / (1.0 / near - 1.0 / far)  # d = alpha + beta / z through (near, d_max), (far, d_min)
        alpha = d_max - beta / near
    # coc = N beta (1/s - 1/z) [px, z in m] = (W / w_s) (f / f_number) d_s (1/s - 1/z) [z in mm], d_s -> f
    f_number = (width_px / sensor_width_mm) * focal_length_mm**2 / (1e3 * n * beta)
    return ThinLens(focal_length_mm, f_number, sensor_width_mm), alpha, beta


def build_scene(views: np.ndarray, disparity: np.ndarray, out: Path, focus_disparities: list[float] | None = None,
                slices: int = 4, aperture: ApertureModel | None = None, depth_range_m: tuple[float, float] = (1.0, 3.0),
                focal_length_mm: float = 1e-3, signs: tuple[int, int] | None = None,
                source: str = "", mapping: tuple[float, float] | None = None) -> dict[str, Any]:
    """Refocus a light field at several disparities and write it as one dataset scene.

    Args:
        views: ``(N, N, H, W, 3)`` linear RGB; disparity ``(H, W)`` px of the centre view.
        out: the scene folder (must not exist).
        focus_disparities: px; default ``slices`` uniform between the 2nd and 98th percentile
            of the disparity.
        aperture: a synthetic aperture (shape sampled at the views, cat-eye per pixel); None:
            every view, and the scene declares no aperture.
        signs: the view shift signs; default :func:`estimate_signs`.
        mapping: ``(alpha, beta)`` of ``depth = beta / (disparity - alpha)``, see
            :func:`lens_for_disparity` (default: from ``depth_range_m``).

    Returns:
        A summary: signs, focus disparities and distances, largest |CoC|, the largest mismatch
        between the lens's CoC and ``N (d0 - d)``, and seconds taken.
    """
    t = time.perf_counter()
    n, _, h, w, _ = views.shape
    if disparity.shape != (h, w):
        raise ValueError(f"disparity map is {disparity.shape[1]}x{disparity.shape[0]}, the views {w}x{h}")
    if signs is None:
        signs, scores = estimate_signs(views, disparity)
        log.info("view shift signs %s (cross-view variance %s)", signs, {k: f"{v:.3g}" for k, v in scores.items()})
    if focus_disparities is None:  # uniform in disparity, so in diopters, over the scene's range
        lo, hi = np.percentile(disparity, [2, 98])
        focus_disparities = [float(d) for d in np.linspace(lo, hi, slices)]
    lens, alpha, beta = lens_for_disparity(disparity, n, w, depth_range_m, focal_length_mm, mapping=mapping)
    if min(focus_disparities) <= alpha:
        raise ValueError(f"focus disparities must be above {alpha:.4g} px (the disparity at infinity), "
                         f"got {min(focus_disparities):.4g}")
    with np.errstate(divide="ignore"):  # a disparity of alpha is at infinity
        depth = beta / (disparity.astype(np.float64) - alpha)
    weights = view_weights(n, signs, aperture)
    focus_m = [beta / (d0 - alpha) for d0 in focus_disparities]
    cocs = [lens.coc_px(depth, s, w, signed=True) for s in focus_m]
    mismatch = max(float(np.abs(c - n * (d0 - disparity)).max()) for c, d0 in zip(cocs, focus_disparities))
    defocus = [refocus(views, d0, signs, weights, aperture) for d0 in tqdm(
        focus_disparities, desc="refocus", unit="slice", disable=not sys.stderr.isatty())]
    declared = None if aperture is None else discrete_aperture(weights, signs, aperture.cat_eye)
    centre = views[n // 2, n // 2]
    generator = {"tool": "data_tools.lightfield", "version": __version__, "source": source, "views": n,
                 "view_signs": list(signs), "focus_disparities_px": [float(d) for d in focus_disparities],
                 "depth_from_disparity": {"alpha_px": alpha, "beta_px_m": beta}, "coc_mismatch_px": mismatch,
                 "synthetic_aperture": None if aperture is None else aperture.to_dict()}
    order = np.argsort(focus_m)
    write_scene(out, centre.astype(np.float64), depth, [defocus[i].astype(np.float64) for i in order],
                [cocs[i] for i in order], lens, [focus_m[i] for i in order], declared, generator)
    return {"signs": signs, "focus_disparities_px": focus_disparities, "focus_m": focus_m, "mismatch_px": mismatch,
            "max_coc_px": float(max(np.abs(c).max() for c in cocs)), "seconds": time.perf_counter() - t, "lens": lens,
            "alpha": alpha, "beta": beta}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m data_tools.lightfield", description=__doc__, formatter_class=HelpFormatter)
    p.add_argument("views", type=Path, help="a folder of N x N views (HCI's input_CamNNN.png, or --pattern) or a .npy "
                                           "stack (N, N, H, W, 3) linear")
    p.add_argument("--disparity", type=Path, required=True, help="the centre view's disparity in px: PFM, EXR or .npy")
    p.add_argument("--out", type=Path, required=True, help="the dataset folder (the scene is written in it)")
    p.add_argument("--name", help="the scene folder's name (default: the views' folder name)")
    p.add_argument("--pattern", help="view file names with the view index, e.g. 'view_{:03d}.exr' (k = N row + col)")
    p.add_argument("--transfer", default="srgb", help="the encoding of integer view images: srgb, linear or gamma:G")
    p.add_argument("--focus-disparities",
                   help="comma-separated focus disparities in px, e.g. --focus-disparities=-1,0.5 (default: --slices uniform "
                        "between the 2nd and 98th percentile of the scene's)")
    p.add_argument("--signs", type=int, nargs=2, choices=(-1, 1), metavar=("SX", "SY"),
                   help="which way a point moves from view to view: x + SX d (col - c), y + SY d (row - c) (default: "
                        "found from the views)")
    p.add_argument("--slices", type=int, default=4, help="focus settings when --focus-disparities is not given")
    p.add_argument("--aperture", help="a synthetic aperture sampled at the view positions (disk, polygon:N, heart, "
                                      "mask:FILE, ...); default: every view, no declared aperture")
    p.add_argument("--cat-eye", type=float, default=0.0, help="cat-eye vignetting of the synthetic aperture (aperture radii)")
    p.add_argument("--depth-range", type=float, nargs=2, default=(1.0, 3.0), metavar=("NEAR", "FAR"),
                   help="depth in m of the largest and the smallest disparity")
    p.add_argument("--disparity-to-depth", type=float, nargs=2, metavar=("ALPHA", "BETA"),
                   help="depth = BETA / (disparity - ALPHA) in m (ALPHA px: the disparity at infinity; BETA px m): the "
                        "camera's, so that its scenes share one lens (overrides --depth-range)")
    p.add_argument("--focal-length", type=float, default=1e-3, help="the virtual lens's focal length in mm")
    p.add_argument("--overwrite", action="store_true", help="replace an existing scene of that name")
    p.add_argument("-v", "--verbose", action="store_true", help="progress logging, and tracebacks with errors")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(message)s")
    if args.slices < 1:
        raise SystemExit(f"error: --slices must be >= 1, got {args.slices}")
    if args.cat_eye and not args.aperture:
        raise SystemExit("error: --cat-eye vignettes a synthetic aperture: give --aperture too")
    try:
        focus = [float(v) for v in args.focus_disparities.split(",")] if args.focus_disparities else None
    except ValueError:
        raise SystemExit(f"error: --focus-disparities must be numbers in px, got {args.focus_disparities!r}") from None
    aperture = ApertureModel(parse_aperture(args.aperture), cat_eye=args.cat_eye) if args.aperture else None
    folder = args.out / (args.name or args.views.stem)
    if folder.exists() and not args.overwrite:
        raise SystemExit(f"error: {folder} already exists: choose another --name or give --overwrite")
    prepare_output(folder, overwrite=True)  # the folder is writable, before the work
    views, disparity = load_views(args.views, args.pattern, args.transfer), load_disparity(args.disparity)
    new = folder.parent / f".{folder.name}.new"  # the old scene stays until the new one is whole
    shutil.rmtree(new, ignore_errors=True)
    info = build_scene(views, disparity, new, focus, args.slices, aperture, tuple(args.depth_range), args.focal_length,
                       signs=tuple(args.signs) if args.signs else None, source=str(args.views),
                       mapping=args.disparity_to_depth)
    shutil.rmtree(folder, ignore_errors=True)
    new.rename(folder)
    lens = info["lens"]
    print(f"scene        {folder}: {views.shape[0]}x{views.shape[1]} views of {views.shape[3]}x{views.shape[2]} px")
    how = "given" if args.signs else "chosen by the cross-view variance at the true disparity"
    print(f"view signs   {info['signs']} ({how})")
    print("focus        " + ", ".join(f"d0 {d:.3f} px = {s:.3f} m" for d, s in zip(info["focus_disparities_px"], info["focus_m"])))
    print(f"lens         virtual {lens.focal_length_mm:g} mm f/{lens.f_number:.3g}, sensor {lens.sensor_width_mm:g} mm; "
          f"aperture {'none declared' if aperture is None else args.aperture}")
    print(f"depth        {info['beta']:.6g} / (disparity - {info['alpha']:.6g}) m (--disparity-to-depth {info['alpha']:.6g} "
          f"{info['beta']:.6g} makes another scene of this camera share the lens)")
    print(f"max |CoC|    {info['max_coc_px']:.2f} px; lens CoC vs N (d0 - d): largest mismatch {info['mismatch_px']:.2e} px")
    print(f"time         {info['seconds']:.1f} s; train with data.roots=['{args.out}']")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))

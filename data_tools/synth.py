"""Synthetic focal stacks: ``python -m data_tools.synth --out DIR [options]``.

Each scene is a procedural stack of textured fronto-parallel cut-outs with HDR highlights
(``data_tools.procedural``), defocused by the reference scatter renderer at K focus distances
(uniform in diopters over the scene's depth range), and written in the dataset format. The
renderer knows every layer in full, so the defocus is exact for the layered model, including
what foreground objects hide. Deterministic per ``--seed`` (scene i uses seed ``(seed, i)``,
whatever the number of workers); existing scenes are skipped, so an interrupted run resumes.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import multiprocessing as mp
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from neuralbokeh import __version__
from neuralbokeh.core.apertures import ApertureModel, parse_aperture
from neuralbokeh.core.cli import HelpFormatter, run_cli
from neuralbokeh.core.io import read_image
from neuralbokeh.core.optics import ThinLens, focus_sweep_m
from neuralbokeh.data.dataset import FocalStackDataset, read_scene_meta, write_scene
from neuralbokeh.networks import ModelConfig
from neuralbokeh.render import scatter_layers

from .procedural import SceneParams, composite_sharp, make_layers

log = logging.getLogger("data_tools.synth")


def render_scene(index: int, opts: dict[str, Any]) -> dict[str, Any]:
    """Generate, render and write scene ``index``; returns a summary. Runs in a worker."""
    torch.set_num_threads(opts.get("threads", 1))
    folder = Path(opts["out"]) / f"scene_{index:05d}"
    if folder.exists():
        return {"index": index, "skipped": True}
    rng = np.random.default_rng(np.random.SeedSequence([opts["seed"], index]))
    width, height = opts["size"]
    params = SceneParams(**opts["scene_params"])
    lens = ThinLens(**opts["lens"])
    aperture = ApertureModel.from_dict(opts["aperture"])
    layers = make_layers(rng, height, width, params)
    aif, depth = composite_sharp(layers)
    finite = [layer.depth_m for layer in layers if math.isfinite(layer.depth_m)]
    near_f = min(finite) * rng.uniform(1.0, 1.15)
    far_f = max(d for d in finite) * rng.uniform(0.85, 1.0) if finite else params.far_m
    focus = focus_sweep_m(near_f, max(far_f, near_f), opts["slices"])
    colors = torch.from_numpy(np.stack([layer.color * layer.alpha[..., None] for layer in layers])).permute(0, 3, 1, 2)
    alphas = torch.from_numpy(np.stack([layer.alpha for layer in layers]))[:, None]
    defocus, cocs = [], []
    for f in focus:
        layer_coc = [lens.coc_px(layer.depth_m, f, width, signed=True) for layer in layers]
        out = scatter_layers(colors, alphas, layer_coc, aperture, field_grid=opts["field_grid"])
        defocus.append(out.permute(1, 2, 0).numpy())
        cocs.append(lens.coc_px(depth, f, width, signed=True))
    generator = {
        "name": "data_tools.synth",
        "version": __version__,
        "seed": opts["seed"],
        "scene_index": index,
        "renderer": {"name": "neuralbokeh.render.scatter_layers", "field_grid": opts["field_grid"]},
        "scene_params": opts["scene_params"],
    }
    write_scene(folder, aif, depth, defocus, cocs, lens, focus, aperture, generator)
    return {"index": index, "skipped": False, "max_coc": float(max(np.abs(c).max() for c in cocs))}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m data_tools.synth",
        description="Write a synthetic focal-stack dataset (AIF, depth, defocus and CoC per slice).",
        formatter_class=HelpFormatter,
    )
    p.add_argument("--out", required=True, type=Path, help="dataset folder (created; existing scenes are kept)")
    p.add_argument("--scenes", type=int, default=16, help="number of scenes")
    p.add_argument("--size", type=int, nargs=2, default=(128, 128), metavar=("W", "H"), help="image size in px")
    p.add_argument("--slices", type=int, default=4, help="focus distances per scene")
    p.add_argument("--seed", type=int, default=0, help="dataset seed")
    p.add_argument(
        "--aperture",
        default="disk",
        help="disk | polygon:BLADES[:ROT_DEG] | heart | ring[:INNER] | star[:POINTS[:INNER]] | mask:IMAGE",
    )
    p.add_argument("--cat-eye", type=float, default=0.0, help="cat-eye vignetting: circle shift at the corner, aperture radii (0 = off)")
    p.add_argument("--vignetting-radius", type=float, default=1.0, help="radius of the vignetting circle, aperture radii")
    p.add_argument("--chromatic", type=float, nargs=3, default=(1.0, 1.0, 1.0), metavar=("R", "G", "B"), help="per-channel CoC scale")
    p.add_argument("--focal-length", type=float, default=85.0, help="focal length in mm")
    p.add_argument("--f-number", type=float, default=1.4, help="f-number")
    p.add_argument("--sensor-width", type=float, default=36.0, help="sensor width in mm")
    p.add_argument("--near", type=float, default=0.7, help="nearest layer depth in m")
    p.add_argument("--far", type=float, default=20.0, help="farthest finite depth in m")
    p.add_argument("--field-grid", type=int, default=None,
                   help="image-position grid for cat-eye kernels (default: automatic, 1 px accuracy)")
    p.add_argument("--workers", type=int, default=1, help="parallel worker processes")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    return p


def refuse_mixing(out: Path, wanted: dict[str, Any]) -> None:
    """A rerun into ``out`` adds scenes to those already there: refuse (``SystemExit``) when they
    were made with another image size, lens or aperture (``wanted``: those ``scene.json``
    entries of this run), which would mix two datasets in one folder."""
    existing = sorted(out.glob("scene_*/scene.json")) if out.is_dir() else []
    if not existing:
        return
    try:
        meta = read_scene_meta(existing[0].parent)
    except (OSError, ValueError) as e:
        raise SystemExit(f"error: --out {out} holds a scene this run cannot read ({e}); choose another --out") from None
    differ = [k for k, v in wanted.items() if json.dumps(meta.get(k), sort_keys=True) != json.dumps(v, sort_keys=True)]
    if differ:
        said = "; ".join(f"{k} {json.dumps(meta.get(k), sort_keys=True)} there, {json.dumps(wanted[k], sort_keys=True)} now"
                         for k in differ)
        raise SystemExit(f"error: --out {out} holds {len(existing)} scene(s) of another {', '.join(differ)} ({said}): a rerun "
                         "adds scenes to them; choose another --out")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if args.scenes < 1 or args.slices < 1 or args.workers < 1:
        raise SystemExit("error: --scenes, --slices and --workers must be >= 1")
    if min(args.size) < 1:
        raise SystemExit(f"error: --size must be positive, got {args.size}")
    try:
        lens = ThinLens(args.focal_length, args.f_number, args.sensor_width)
        shape = parse_aperture(args.aperture, load_mask=lambda path: read_image(path).mean(axis=2))
        aperture = ApertureModel(shape, args.cat_eye, args.vignetting_radius, tuple(args.chromatic))
        params = SceneParams(near_m=args.near, far_m=args.far)
        if not (lens.focal_length_mm / 1000.0 < args.near < args.far):
            raise ValueError(f"need focal length < --near < --far, got {args.near} m and {args.far} m")
    except (ValueError, OSError) as e:
        raise SystemExit(f"error: {e}")
    refuse_mixing(args.out, {"image_size": {"width": args.size[0], "height": args.size[1]}, "lens": lens.to_dict(),
                             "aperture": aperture.to_dict()})
    args.out.mkdir(parents=True, exist_ok=True)
    opts = {
        "out": str(args.out),
        "size": tuple(args.size),
        "slices": args.slices,
        "seed": args.seed,
        "lens": lens.to_dict(),
        "aperture": aperture.to_dict(),
        "scene_params": params.__dict__,
        "field_grid": args.field_grid,
        "threads": 1 if args.workers > 1 else torch.get_num_threads(),
    }
    t0 = time.perf_counter()
    results = []
    with tqdm(total=args.scenes, desc="scenes", unit="scene") as bar:
        if args.workers == 1:
            for i in range(args.scenes):
                results.append(render_scene(i, opts))
                bar.update()
        else:
            pool = ProcessPoolExecutor(args.workers, mp_context=mp.get_context("spawn"))
            try:
                futures = [pool.submit(render_scene, i, opts) for i in range(args.scenes)]
                for fut in as_completed(futures):
                    results.append(fut.result())
                    bar.update()
            except BaseException:  # Ctrl-C or a failed scene: the queued scenes are dropped, not rendered
                pool.shutdown(wait=False, cancel_futures=True)
                raise
            pool.shutdown()
    elapsed = time.perf_counter() - t0
    written = [r for r in results if not r["skipped"]]
    ds = FocalStackDataset(args.out)
    n_blocks = ModelConfig().resolved(ds.max_coc_px).blocks  # the default network's: the near-focus lattice
    print(f"dataset      {args.out.resolve()}")
    print(f"scenes       {len(ds.scenes)} in the folder ({len(written)} written now, {len(results) - len(written)} already there)")
    print(f"samples      {len(ds)} (scene, focus) pairs; image {args.size[0]}x{args.size[1]} px")
    print(f"lens         {lens.focal_length_mm:g} mm f/{lens.f_number:g}, sensor {lens.sensor_width_mm:g} mm; aperture {args.aperture}"
          + (f", cat-eye {args.cat_eye:g}" if args.cat_eye else ""))
    print(f"max |CoC|    {ds.max_coc_px:.2f} px -> network depth N = {n_blocks} blocks (kernels up to {2 * n_blocks + 1} px)")
    print(f"time         {elapsed:.1f} s ({elapsed / max(len(written), 1):.2f} s per written scene)")
    print(f"load it      FocalStackDataset({str(args.out)!r}, split='train'|'test')")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))

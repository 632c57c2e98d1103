"""Mitsuba 3 focal stacks: ``python -m data_tools.mitsuba --out DIR [options]``.

Per scene: the all-in-focus image (pinhole, the same camera as the slices), planar depth in m
and K defocused slices with their CoC maps, written in the dataset format (one folder per
scene, appearing atomically). Procedural scenes by default (deterministic per ``--seed``: scene
i uses seed ``(seed, i)``), or ``--scene-xml FILE`` for a user's own scene. ``--shard i/n``
renders scenes ``i, i + n, ...`` only, so n jobs build one dataset; finished scenes are skipped,
so a rerun resumes. ``--light-field N`` renders each scene as an N x N light field instead
(pinhole views across the lens's entrance pupil, and the disparity) for ``data_tools.lightfield``.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from neuralbokeh import __version__
from neuralbokeh.core.apertures import ApertureModel, parse_aperture
from neuralbokeh.core.cli import HelpFormatter, run_cli
from neuralbokeh.core.io import atomic_directory, read_image, write_image, write_json
from neuralbokeh.core.optics import ThinLens, focus_sweep_m
from neuralbokeh.data.dataset import write_scene

from .render import METHODS, choose_method, mitsuba_defocus, render_aif, render_depth, render_light_field
from .scenes import Camera, MitsubaSceneParams, camera_from_xml, fov_for_lens, procedural_scene

log = logging.getLogger("data_tools.mitsuba")


def parse_shard(spec: str) -> tuple[int, int]:
    """``"i/n"`` -> ``(i, n)`` with ``0 <= i < n``."""
    try:
        i, n = (int(s) for s in spec.split("/"))
    except ValueError:
        raise ValueError(f"--shard must look like i/n (e.g. 0/4), got {spec!r}") from None
    if not 0 <= i < n:
        raise ValueError(f"--shard i/n needs 0 <= i < n, got {spec!r}")
    return i, n


def shard_indices(scenes: int, shard: tuple[int, int]) -> list[int]:
    """The scene indices of one shard: disjoint across shards, together ``range(scenes)``."""
    i, n = shard
    return list(range(i, scenes, n))


def scene_focus(depth_m: np.ndarray, slices: int, lens: ThinLens) -> list[float]:
    """K focus distances uniform in diopters between the 2nd and 98th percentile of the finite
    depths (the focal length is the floor)."""
    finite = depth_m[np.isfinite(depth_m)]
    if finite.size == 0:
        raise ValueError("the scene has no finite depth (nothing was hit); cannot place the focus")
    near, far = np.percentile(finite, [2, 98])
    near = max(float(near), lens.focal_length_mm / 1000.0 * 1.5)
    return focus_sweep_m(near, max(float(far), near), slices)


def render_one(mi: Any, index: int, opts: dict[str, Any], xml_scene: Any = None) -> dict[str, Any]:
    """Render and write scene ``index``; returns a summary."""
    folder = Path(opts["out"]) / (f"lf_{index:05d}" if opts["light_field"] else f"scene_{index:05d}")
    if folder.exists():
        return {"index": index, "skipped": True}
    lens, aperture, camera = opts["lens"], opts["aperture"], opts["camera"]
    rng = np.random.default_rng(np.random.SeedSequence([opts["seed"], index]))
    if xml_scene is None:
        scene_dict, description = procedural_scene(mi, rng, camera, opts["scene_params"], opts["max_depth"], opts["planar"])
        scene = mi.load_dict(scene_dict)
    else:
        scene, description = xml_scene, {"xml": str(opts["scene_xml"]), "unit_m": opts["unit_m"]}
    seed = int(rng.integers(2**31))
    t0 = time.perf_counter()
    if opts["light_field"]:
        return write_light_field(mi, scene, index, opts, seed, description)
    aif = render_aif(mi, scene, camera, opts["aif_spp"], seed=seed)
    depth = render_depth(mi, scene, camera) * opts["unit_m"]
    focus = opts["focus"] or scene_focus(depth, opts["slices"], lens)
    defocus, cocs, slices = [], [], []
    for k, f in enumerate(focus):
        res = mitsuba_defocus(mi, scene, camera, lens, aperture, f, opts["spp"], opts["method"], opts["noise_target"],
                             opts["rounds"], seed=seed + 7919 * (k + 1), unit_m=opts["unit_m"])
        defocus.append(res.image)
        cocs.append(lens.coc_px(depth, f, camera.width, signed=True))
        slices.append({"focus_m": f, "spp": res.spp, "noise": res.noise, "rounds": res.rounds, "method": res.method})
    generator = {"name": "data_tools.mitsuba", "version": __version__, "mitsuba": mi.__version__, "variant": mi.variant(),
                 "seed": opts["seed"], "scene_index": index, "aif_spp": opts["aif_spp"], "spp_budget": opts["spp"],
                 "noise_target": opts["noise_target"], "slices": slices, "fov_x_deg": camera.fov_x_deg,
                 "camera_to_world": camera.to_world.tolist(), "scene": description,
                 "seconds": round(time.perf_counter() - t0, 3)}
    write_scene(folder, aif.astype(np.float32), depth, [d.astype(np.float32) for d in defocus], cocs, lens, focus,
                aperture, generator)
    return {"index": index, "skipped": False, "spp": [s["spp"] for s in slices]}


def light_field_beta(lens: ThinLens, camera: Camera, n: int) -> float:
    """``BETA`` (px m) of ``depth = BETA / disparity`` for the views of :func:`render_light_field`."""
    return camera.width / (2.0 * camera.tan_half_x) * lens.aperture_diameter_mm / 1000.0 / n


def write_light_field(mi: Any, scene: Any, index: int, opts: dict[str, Any], seed: int, description: Any) -> dict[str, Any]:
    """Render scene ``index`` as an N x N light field into ``lf_NNNNN/`` (``view_000.exr`` ...,
    ``disparity.exr``, ``depth.exr``, ``lightfield.json``), the folder appearing whole."""
    lens, camera, n = opts["lens"], opts["camera"], opts["light_field"]
    t0 = time.perf_counter()
    views, disparity, depth = render_light_field(mi, scene, camera, lens, n, opts["spp"], seed, opts["unit_m"])
    with atomic_directory(Path(opts["out"]) / f"lf_{index:05d}") as tmp:
        for k, view in enumerate(views.reshape(n * n, *views.shape[2:])):
            write_image(tmp / f"view_{k:03d}.exr", view.astype(np.float32))
        write_image(tmp / "disparity.exr", disparity.astype(np.float32))
        write_image(tmp / "depth.exr", depth.astype(np.float32))
        write_json(tmp / "lightfield.json", {
            "views": n, "view_index": "k = N row + col, row 0 at the top", "lens": lens.to_dict(),
            "disparity_to_depth": {"alpha_px": 0.0, "beta_px_m": light_field_beta(lens, camera, n)},
            "generator": {"name": "data_tools.mitsuba", "version": __version__, "mitsuba": mi.__version__,
                          "variant": mi.variant(), "seed": opts["seed"], "scene_index": index, "spp": opts["spp"],
                          "scene": description, "seconds": round(time.perf_counter() - t0, 3)}})
    return {"index": index, "skipped": False, "spp": [opts["spp"]]}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m data_tools.mitsuba", description=__doc__,
                                formatter_class=HelpFormatter)
    p.add_argument("--out", required=True, type=Path, help="dataset folder (created; existing scenes are kept)")
    p.add_argument("--scenes", type=int, default=8, help="number of procedural scenes")
    p.add_argument("--planar", action="store_true", help="procedural scenes of fronto-parallel rectangles only")
    p.add_argument("--scene-xml", type=Path, default=None, help="render this Mitsuba scene file instead (one scene)")
    p.add_argument("--xml-param", action="append", default=[], metavar="NAME=VALUE", help="a $NAME parameter of the XML file")
    p.add_argument("--unit-m", type=float, default=1.0, help="metres per scene unit of --scene-xml (0.001: modelled in mm)")
    p.add_argument("--camera", choices=("file", "lens"), default="file",
                   help="with --scene-xml: take the field of view and film size from the file, or from the lens options and --size")
    p.add_argument("--size", type=int, nargs=2, default=(128, 128), metavar=("W", "H"), help="image size in px")
    p.add_argument("--slices", type=int, default=4, help="focus distances per scene (uniform in diopters over its depths)")
    p.add_argument("--focus", type=float, nargs="+", default=None, metavar="M", help="explicit focus distances in m")
    p.add_argument("--aperture", default="disk", help="aperture shape: disk, polygon:N[:rot], heart, ring:r, star:N:r, mask:FILE")
    p.add_argument("--cat-eye", type=float, default=0.0, help="cat-eye vignetting: circle shift at the corner, aperture radii")
    p.add_argument("--vignetting-radius", type=float, default=1.0, help="radius of the vignetting circle, aperture radii")
    p.add_argument("--focal-length", type=float, default=50.0, help="focal length in mm")
    p.add_argument("--f-number", type=float, default=2.0, help="f-number")
    p.add_argument("--sensor-width", type=float, default=36.0,
                   help="sensor width in mm (with --scene-xml --camera file: from the file's fov)")
    p.add_argument("--near", type=float, default=0.7, help="nearest procedural object in m")
    p.add_argument("--far", type=float, default=12.0, help="back wall of the procedural scenes in m")
    p.add_argument("--spp", type=int, default=256, help="samples per pixel per defocused slice (the budget)")
    p.add_argument("--aif-spp", type=int, default=64, help="samples per pixel of the all-in-focus image")
    p.add_argument("--noise-target", type=float, default=None,
                   help="stop a slice once its estimated noise (RMS std error, tone-mapped) is below this, e.g. 0.005")
    p.add_argument("--rounds", type=int, default=4, help="rounds the spp budget is split into (noise estimate)")
    p.add_argument("--light-field", type=int, default=0, metavar="N",
                   help="render N x N pinhole views across the lens's entrance pupil (odd N) and the disparity, for "
                        "data_tools.lightfield, instead of focal stacks (--spp per view)")
    p.add_argument("--method", choices=METHODS, default="auto", help="defocus: thinlens sensor (disk) or pinhole accumulation (any)")
    p.add_argument("--max-depth", type=int, default=4, help="path length of the procedural scenes' integrator")
    p.add_argument("--seed", type=int, default=0, help="dataset seed")
    p.add_argument("--variant", default=None, help="mitsuba variant (default: llvm_ad_rgb when an LLVM works, else scalar_rgb)")
    p.add_argument("--shard", default="0/1", help="render the scenes i, i+n, ... of shard i/n")
    p.add_argument("--only", type=int, nargs="+", default=None, metavar="I",
                   help="render only these scene indices (0 .. --scenes - 1), e.g. a held-out split again at more spp")
    p.add_argument("-v", "--verbose", action="store_true", help="info logging (the variant probe)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        shard = parse_shard(args.shard)
        if args.light_field and (args.light_field < 3 or args.light_field % 2 == 0):
            raise ValueError(f"--light-field N needs an odd N >= 3 (the centre view is the all-in-focus image), got {args.light_field}")
        if args.scenes < 1 or args.slices < 1:
            raise ValueError(f"--scenes and --slices must be >= 1, got {args.scenes} and {args.slices}")
        if min(args.size) < 1:
            raise ValueError(f"--size must be positive, got {args.size}")
        shape = parse_aperture(args.aperture, load_mask=lambda path: read_image(path).mean(axis=2))
        aperture = ApertureModel(shape, args.cat_eye, args.vignetting_radius)
        choose_method(args.method, aperture)
        if args.focus is not None and any(not (f > args.focal_length / 1000.0) for f in args.focus):
            raise ValueError(f"--focus distances must exceed the focal length ({args.focal_length / 1000.0} m), got {args.focus}")
        from .variant import activate

        mi = activate(args.variant)
        xml_scene = None
        if args.scene_xml is not None:
            bad = [kv for kv in args.xml_param if "=" not in kv]
            if bad:
                raise ValueError(f"--xml-param must be NAME=VALUE, got {bad}")
            if not args.unit_m > 0:
                raise ValueError(f"--unit-m must be > 0, got {args.unit_m}")
            xml_scene, cam = camera_from_xml(mi, args.scene_xml, dict(kv.split("=", 1) for kv in args.xml_param))
            if args.camera == "lens":
                cam = Camera(cam.to_world, fov_for_lens(args.focal_length, args.sensor_width), *args.size)
            sensor_width = 2.0 * args.focal_length * cam.tan_half_x
            indices = [0]
        else:
            look = mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[0, 0, 1], up=[0, 1, 0])
            cam = Camera(np.array(look.matrix, dtype=np.float64).reshape(4, 4), fov_for_lens(args.focal_length, args.sensor_width),
                         *args.size)
            sensor_width = args.sensor_width
            indices = shard_indices(args.scenes, shard)
            if args.only is not None:
                bad = [i for i in args.only if not 0 <= i < args.scenes]
                if bad:
                    raise ValueError(f"--only takes scene indices 0 .. {args.scenes - 1} (--scenes {args.scenes}), got {bad}")
                indices = [i for i in indices if i in set(args.only)]
        lens = ThinLens(args.focal_length, args.f_number, sensor_width)
        params = MitsubaSceneParams(near_m=args.near, far_m=args.far)
    except (ValueError, OSError, ImportError, RuntimeError) as e:  # RuntimeError: mitsuba's XML parser
        raise SystemExit(f"error: {e}")
    args.out.mkdir(parents=True, exist_ok=True)
    opts = {"out": str(args.out), "seed": args.seed, "lens": lens, "aperture": aperture, "camera": cam, "scene_params": params,
            "focus": sorted(args.focus) if args.focus else None, "slices": args.slices, "spp": args.spp, "aif_spp": args.aif_spp,
            "noise_target": args.noise_target, "rounds": args.rounds, "method": args.method, "max_depth": args.max_depth,
            "scene_xml": args.scene_xml, "planar": args.planar, "unit_m": args.unit_m if args.scene_xml else 1.0,
            "light_field": args.light_field}
    t0 = time.perf_counter()
    results = []
    for index in tqdm(indices, desc=f"shard {shard[0]}/{shard[1]}", unit="scene"):
        results.append(render_one(mi, index, opts, xml_scene))
    written = [r for r in results if not r["skipped"]]
    spp = [s for r in written for s in r["spp"]]
    elapsed = time.perf_counter() - t0
    print(f"dataset      {args.out.resolve()}  (mitsuba {mi.__version__}, variant {mi.variant()})")
    print(f"scenes       {len(written)} written, {len(results) - len(written)} already there (shard {shard[0]}/{shard[1]})")
    if spp:
        print(f"spp/slice    median {int(np.median(spp))}, min {min(spp)}, max {max(spp)} (budget {args.spp})")
    print(f"time         {elapsed:.1f} s ({elapsed / max(len(written), 1):.2f} s per written scene)")
    if args.light_field:
        print(f"light fields python -m data_tools.lightfield {args.out}/lf_NNNNN --pattern 'view_{{:03d}}.exr' --disparity "
              f"{args.out}/lf_NNNNN/disparity.exr --transfer linear --signs -1 -1 --disparity-to-depth 0 "
              f"{light_field_beta(lens, cam, args.light_field):.9g} --out DATASET (one lens for all)")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))

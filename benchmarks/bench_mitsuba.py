"""Mitsuba focal stacks: noise against render time, the noise target, and the cross-check
against our scatter renderer.

    python benchmarks/bench_mitsuba.py [--size 128 96] [--ref-spp 4096] [--variant scalar_rgb]

1. Noise vs time (one procedural scene, 7-blade aperture, cat-eye 0.6, one slice): for a
   ladder of spp, the render's error against a ``--ref-spp`` reference (RMS of the
   Reinhard-tone-mapped difference, display units, and linear PSNR), the renderer's own noise
   estimate, and the wall time; ratios against the smallest rung measured in the same run.
2. ``--noise-target``: for a few targets, the spp a slice actually used and its error.
3. Cross-check: the reference scatter renderer fed Mitsuba's AIF and planar depth against
   Mitsuba's defocus, on a fronto-parallel (planar) procedural scene and on a general one.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from data_tools.mitsuba.render import mitsuba_defocus, render_aif, render_depth
from data_tools.mitsuba.scenes import MitsubaSceneParams, axis_camera, procedural_scene
from data_tools.mitsuba.variant import activate
from neuralbokeh.core.apertures import ApertureModel, Polygon
from neuralbokeh.core.optics import ThinLens
from neuralbokeh.evaluation.metrics import image_metrics
from neuralbokeh.render import render_defocus as scatter_render


def _tm(x: np.ndarray) -> np.ndarray:
    return x / (1.0 + x)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", type=int, nargs=2, default=(128, 96))
    p.add_argument("--ref-spp", type=int, default=4096)
    p.add_argument("--ladder", type=int, nargs="+", default=[16, 32, 64, 128, 256, 512, 1024])
    p.add_argument("--targets", type=float, nargs="+", default=[0.02, 0.01, 0.005])
    p.add_argument("--variant", default=None)
    p.add_argument("--seed", type=int, default=5)
    p.add_argument("--parts", default="noise,target,crosscheck", help="comma list of noise, target, crosscheck")
    args = p.parse_args()
    mi = activate(args.variant)
    w, h = args.size
    lens = ThinLens(85.0, 1.4, 36.0)
    cam = axis_camera(mi, 85.0, 36.0, w, h)
    ap = ApertureModel(Polygon(7), cat_eye=0.6)
    params = MitsubaSceneParams(near_m=1.5, far_m=12.0)
    print(f"mitsuba {mi.__version__} variant {mi.variant()}; {w}x{h} px, 85 mm f/1.4, 7 blades, cat-eye 0.6")

    parts = args.parts.split(",")
    if "noise" in parts or "target" in parts:
        _noise_parts(mi, args, cam, lens, ap, params, parts)
    if "crosscheck" in parts:
        _crosscheck(mi, args, cam, lens, ap, params)


def _noise_parts(mi, args, cam, lens, ap, params, parts) -> None:
    w = cam.width
    scene = mi.load_dict(procedural_scene(mi, np.random.default_rng(args.seed), cam, params)[0])
    depth = render_depth(mi, scene, cam)
    focus = float(np.percentile(depth[np.isfinite(depth)], 30))
    print(f"focus {focus:.2f} m; max |CoC| {np.abs(lens.coc_px(depth, focus, w, signed=True)).max():.1f} px")
    t0 = time.perf_counter()
    ref = mitsuba_defocus(mi, scene, cam, lens, ap, focus, args.ref_spp, seed=999).image
    print(f"reference {args.ref_spp} spp: {time.perf_counter() - t0:.1f} s\n")
    if "noise" in parts:
        _ladder(mi, args, scene, cam, lens, ap, focus, ref)
    if "target" in parts:
        _targets(mi, args, scene, cam, lens, ap, focus, ref)


def _ladder(mi, args, scene, cam, lens, ap, focus, ref) -> None:
    print("1. noise against time (one slice)")
    print(f"{'spp':>6} {'seconds':>8} {'x time':>7} {'RMS err (tm)':>13} {'x err':>6} {'estimate':>9} {'PSNR lin':>9}")
    base = None
    for spp in args.ladder:
        t0 = time.perf_counter()
        res = mitsuba_defocus(mi, scene, cam, lens, ap, focus, spp, seed=spp)
        sec = time.perf_counter() - t0
        err = float(np.sqrt(np.mean((_tm(res.image) - _tm(ref)) ** 2)))
        base = base or (sec, err)
        psnr = image_metrics(res.image, ref)["psnr_linear"]
        print(f"{spp:>6} {sec:>8.2f} {sec / base[0]:>7.2f} {err:>13.5f} {err / base[1]:>6.3f} {res.noise:>9.5f} {psnr:>9.2f}")


def _targets(mi, args, scene, cam, lens, ap, focus, ref) -> None:
    print("\n2. --noise-target (budget 1024 spp, 8 rounds)")
    print(f"{'target':>8} {'spp used':>9} {'seconds':>8} {'RMS err (tm)':>13}")
    for target in args.targets:
        t0 = time.perf_counter()
        res = mitsuba_defocus(mi, scene, cam, lens, ap, focus, 1024, noise_target=target, rounds=8, seed=7)
        err = float(np.sqrt(np.mean((_tm(res.image) - _tm(ref)) ** 2)))
        print(f"{target:>8} {res.spp:>9} {time.perf_counter() - t0:>8.2f} {err:>13.5f}")


def _crosscheck(mi, args, cam, lens, ap, params) -> None:
    print("\n3. cross-check: scatter(Mitsuba AIF + depth) against Mitsuba's defocus")
    for name, planar in (("fronto-parallel", True), ("general", False)):
        sc = mi.load_dict(procedural_scene(mi, np.random.default_rng(args.seed + 1), cam, params, planar=planar)[0])
        aif, z = render_aif(mi, sc, cam, 512), render_depth(mi, sc, cam)
        f = float(np.percentile(z[np.isfinite(z)], 30))
        theirs = mitsuba_defocus(mi, sc, cam, lens, ap, f, args.ref_spp, seed=11).image
        ours = scatter_render(torch.from_numpy(aif.transpose(2, 0, 1))[None], torch.from_numpy(z)[None, None], lens, f, ap)
        m = image_metrics(ours[0].numpy().transpose(1, 2, 0), theirs)
        ident = image_metrics(aif, theirs)
        print(f"{name:>16}: PSNR linear {m['psnr_linear']:.2f} dB, sRGB {m['psnr_srgb']:.2f} dB "
              f"(the AIF itself: {ident['psnr_linear']:.2f} / {ident['psnr_srgb']:.2f} dB)")


if __name__ == "__main__":
    main()

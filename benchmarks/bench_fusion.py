"""Focus-stack fusion: quality against a per-pixel argmax, and where the time goes.

    python benchmarks/bench_fusion.py [--stacks ../shared/data/focal_stacks] [--size 384 288]

1. Synthetic stacks rendered from a known layered scene (``--size``; 5 slices evenly spaced in
   diopters, then the same with one distance duplicated, then every distance shot twice at
   f/1.8 and f/4, 0.2 % apart): sRGB PSNR against the true AIF of the fusion and of the hard
   per-pixel argmax of the same focus measure; NaN check.
2. The repository's real stacks (developed JPEG/PNG, read and linearised as
   ``data_tools.raw`` does, at full size, not aligned: the timing is the point): seconds of
   each fusion stage (focus measure, depth from focus, edge-aware regularisation, blending),
   the regularisation's share, peak RSS, and the mean focus measure of the fused AIF against
   the mean per-pixel best slice's (no ground truth there: 1.0 = as sharp as the sharpest
   slice everywhere).
"""

from __future__ import annotations

import argparse
import math
import resource
import time
from pathlib import Path

import numpy as np
import torch

from data_tools.procedural import SceneParams, composite_sharp, make_layers
from data_tools.raw import fuse
from data_tools.raw.developed import DEVELOPED_EXTENSIONS, decode_developed
from neuralbokeh.core.apertures import ApertureModel
from neuralbokeh.core.optics import ThinLens, focus_sweep_m
from neuralbokeh.evaluation.metrics import image_metrics
from neuralbokeh.render import scatter_layers


def synthetic(size: tuple[int, int]) -> None:
    w, h = size
    layers = make_layers(np.random.default_rng(5), h, w, SceneParams(near_m=0.8, far_m=6.0, infinite_background=0.0))
    aif, _ = composite_sharp(layers)
    colors = torch.from_numpy(np.stack([la.color * la.alpha[..., None] for la in layers])).permute(0, 3, 1, 2)
    alphas = torch.from_numpy(np.stack([la.alpha for la in layers]))[:, None]
    finite = [la.depth_m for la in layers if math.isfinite(la.depth_m)]
    sweep = list(focus_sweep_m(min(finite), max(finite), 5))
    cases = {"even": [(f, 1.8) for f in sweep], "duplicated": [(f, 1.8) for f in sweep] + [(sweep[2], 1.8)],
             "two apertures": [(f, 1.8) for f in sweep] + [(f * 1.002, 4.0) for f in sweep]}
    print(f"1. synthetic {w}x{h}: sRGB PSNR against the true AIF")
    print(f"{'stack':<14} {'slices':>6} {'fusion':>7} {'argmax':>7} {'NaN':>4}")
    for name, pairs in cases.items():
        slices = []
        for f, n in pairs:
            lens = ThinLens(50.0, n, 12.0)
            cocs = [lens.coc_px(la.depth_m, f, w, signed=True) for la in layers]
            slices.append(scatter_layers(colors, alphas, cocs, ApertureModel()).permute(1, 2, 0).numpy())
        res = fuse.fuse_stack(slices, [p[0] for p in pairs])
        best = fuse.focus_measure(slices).argmax(dim=0).numpy()
        argmax = np.take_along_axis(np.stack(slices), best[None, ..., None], 0)[0]
        print(f"{name:<14} {len(pairs):>6} {image_metrics(res.aif, aif)['psnr_srgb']:>7.2f} "
              f"{image_metrics(argmax, aif)['psnr_srgb']:>7.2f} {'yes' if np.isnan(res.aif).any() else 'no':>4}")


def real(root: Path) -> None:
    print(f"\n2. real stacks ({root}), full size, 2 threads")
    print(f"{'stack':<18} {'size':>10} {'K':>2} {'measure':>8} {'DFF':>6} {'regul.':>7} {'blend':>6} {'regul. %':>8} "
          f"{'peak RSS':>9} {'sharpness':>9}")
    for folder in sorted(p for p in root.iterdir() if p.is_dir()):
        files = [p for p in sorted(folder.iterdir()) if p.suffix.lower() in DEVELOPED_EXTENSIONS and p.stem != "expected"]
        if len(files) < 2:
            continue
        slices = [decode_developed(p) for p in files]
        t = [time.perf_counter()]
        fm = fuse.focus_measure(slices)
        t.append(time.perf_counter())
        diopters = np.linspace(1.0, 2.0, len(slices))
        raw_d, conf = fuse.peak_diopters(fm, diopters)
        t.append(time.perf_counter())
        stack = torch.stack([fuse._chw(s)[0] for s in slices]).double()
        first = stack.gather(0, fm.argmax(dim=0)[None, None].expand(1, 3, *fm.shape[1:]))[0]
        guide = torch.log(first.clamp(min=0.0) + 1e-3 * float(first.mean()) + 1e-12)[None]
        guide = (guide - guide.amin()) / (guide.amax() - guide.amin() + 1e-12)
        fuse._regularise(raw_d, conf, guide)
        t.append(time.perf_counter())
        best = fm.argmax(dim=0)
        aif = stack.gather(0, best[None, None].expand(1, 3, *best.shape))[0].numpy().transpose(1, 2, 0)
        t.append(time.perf_counter())
        dt = np.diff(t)
        sharp = float(fuse.focus_measure([aif])[0].mean() / fm.max(dim=0).values.mean())
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        h, w_ = slices[0].shape[:2]
        print(f"{folder.name:<18} {f'{w_}x{h}':>10} {len(slices):>2} {dt[0]:>8.2f} {dt[1]:>6.2f} {dt[2]:>7.2f} {dt[3]:>6.2f} "
              f"{100 * dt[2] / dt.sum():>7.1f}% {rss:>7.0f} MB {sharp:>9.3f}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--stacks", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data" / "focal_stacks")
    p.add_argument("--size", type=int, nargs=2, default=(384, 288))
    args = p.parse_args()
    torch.set_num_threads(2)
    synthetic(tuple(args.size))
    if args.stacks.is_dir():
        real(args.stacks)
    else:
        print(f"\n2. skipped: no {args.stacks}")


if __name__ == "__main__":
    main()

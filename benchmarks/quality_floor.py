"""The quality floor of the learned-lens issue: the default model vs. ablations under one time budget.

    python benchmarks/quality_floor.py [--minutes 30] [--scenes 40] [--size 256] [--lens hard] [--tile T]
        [--variants full paper no_tiling no_overlap tile_loss fixed3_kernels] [section.key=value ...]

Makes (once) a synthetic dataset (``--scenes`` scenes x 4 slices, 20% of scenes held out) with
``--lens floor`` (7-blade aperture, cat-eye 0.6, f/2.8) or ``--lens hard`` (heart aperture,
chromatic CoC scale 1.04/1.0/0.96, cat-eye 0.8), trains each variant for ``--minutes`` of wall
time on this machine with the quickstart settings scaled to the image size (tiles of ``--tile``
px, default size/8: the cat-eye changes across a size/4 tile, with size/16 overlap, constant lr:
the lens network's from the quickstart config, 1e-3 for the paper's network, whose 3e-3 diverged
at 256 px with N = 14), and prints one table: held-out PSNR/SSIM (training metric), steps and
s/step of each variant next to the identity (AIF unchanged), the CoC-driven Gaussian blur and
the exact-aperture scatter on the same held-out samples, and which share of the gap between the
Gaussian and the exact scatter each closes.

It also prints an *oracle* row: the foundation's scatter renderer fed the held-out AIF and CoC
with the exact aperture of the data (7-gon, cat-eye). That is the best any method seeing only
(AIF, CoC) can do with perfect knowledge of the lens; what it still misses is the background
that foreground objects hide in the AIF and that the defocused ground truth shows around them
(the synthetic scenes are rendered from layers). ``--baselines-only`` prints the rows that need
no training.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from data_tools.synth import main as synth
from neuralbokeh.core.normalization import Normalization
from neuralbokeh.data.dataset import FocalStackDataset
from neuralbokeh.evaluation.ablations import VARIANTS
from neuralbokeh.training import load_config, train
from neuralbokeh.training.loop import held_out_baselines

ROOT = Path(__file__).resolve().parents[1]
LENSES = {
    "floor": ["--aperture", "polygon:7", "--cat-eye", "0.6", "--f-number", "2.8"],
    "hard": ["--aperture", "heart", "--chromatic", "1.04", "1.0", "0.96", "--cat-eye", "0.8", "--f-number", "2.8"],
}


def baselines(cfg) -> dict[str, tuple[float, float]]:
    """Mean held-out (PSNR, SSIM), in the training metric, of the AIF unchanged, the CoC-driven
    Gaussian scatter and the exact-aperture scatter (oracle), all fed the held-out AIF + CoC
    (``training.loop.held_out_baselines``, what training reports beside the model)."""
    norm = Normalization(cfg.data.normalization_scale)
    ds = FocalStackDataset(cfg.data.roots, "test", cfg.data.test_fraction, cfg.data.split_seed, norm)
    m = held_out_baselines(ds)
    return {k: (m[f"{k}_psnr"], m[f"{k}_ssim"]) for k in ("identity", "gaussian", "oracle")}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--minutes", type=float, default=30.0)
    p.add_argument("--scenes", type=int, default=40)
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--data", type=Path, default=ROOT / "data" / "floor")
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "floor")
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    p.add_argument("--lens", choices=sorted(LENSES), default="floor", help="the data's lens (see the module doc)")
    p.add_argument("--tile", type=int, default=None, help="tile core in px (default: size / 8)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--lr", type=float, default=None, help="one lr for every variant (default: each architecture's own)")
    p.add_argument("--baselines-only", action="store_true", help="no training: identity, Gaussian and oracle rows")
    p.add_argument("overrides", nargs="*", help="section.key=value applied to every variant after its own, "
                   "e.g. model.pixel_blur=false train.pupil_tv=1e-2")
    args = p.parse_intermixed_args()
    torch.set_num_threads(2)
    data = args.data if args.lens == "floor" or args.data != ROOT / "data" / "floor" else ROOT / "data" / f"floor_{args.lens}"
    args.data = data
    synth(["--out", str(args.data), "--scenes", str(args.scenes), "--size", str(args.size), str(args.size),
           "--slices", "4", *LENSES[args.lens], "--seed", "2024", "--workers", str(args.workers)])
    rows = []

    def config(name: str):
        return load_config(ROOT / "configs" / "quickstart.toml", [
            f"data.roots=['{args.data}']", "data.test_fraction=0.2", f"train.out_dir='{args.out / name}'",
            f"model.tile={args.tile or args.size // 8}", f"model.overlap={args.size // 16}", "train.steps=1000000",
            "train.lr_schedule='constant'", "train.eval_every=1000000", "train.checkpoint_every=200", *VARIANTS[name],
            *([f"train.lr={args.lr}"] if args.lr else []), *args.overrides,
        ])

    for name in [] if args.baselines_only else args.variants:
        rows.append((name, train(config(name), time_limit_s=60.0 * args.minutes, overwrite=True)))
    base = baselines(config("full"))
    gauss, oracle = base["gaussian"][0], base["oracle"][0]
    print(f"\nheld-out PSNR dB / SSIM after {args.minutes:g} min each ({args.scenes} scenes x 4 slices, {args.size} px, "
          f"lens {args.lens}); gap = oracle - Gaussian = {oracle - gauss:.2f} dB"
          + (f"; overrides: {' '.join(args.overrides)}" if args.overrides else ""))
    print(f"{'variant':<16} {'steps':>7} {'s/step':>7} {'PSNR':>7} {'SSIM':>7} {'gap closed':>10}")
    for name, s in rows:
        m = s["metrics"]
        closed = (m["eval_psnr"] - gauss) / max(oracle - gauss, 1e-9)
        print(f"{name:<16} {s['steps']:>7} {s['seconds'] / max(s['steps'], 1):>7.2f} {m['eval_psnr']:>7.2f} "
              f"{m['eval_ssim']:>7.4f} {100 * closed:>9.0f}%")
    notes = {"oracle": "   (exact aperture fed AIF + CoC)"}
    for name, (p_, s_) in base.items():
        print(f"{name:<16} {'':>7} {'':>7} {p_:>7.2f} {s_:>7.4f}{notes.get(name, '')}")


if __name__ == "__main__":
    main()

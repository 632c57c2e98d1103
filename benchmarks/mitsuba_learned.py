"""The learned lens on physically rendered data, where the layered scatter is only an approximation.

    python benchmarks/mitsuba_learned.py [--scenes 24] [--size 128] [--minutes 15] [--spp 256] [KEY=VALUE ...]

1. Renders (once; finished scenes are skipped) a Mitsuba 3 focal-stack dataset of non-planar
   procedural scenes (tilted textured rectangles, spheres, boxes, HDR point lights; 7-blade
   aperture with cat-eye 0.6, 85 mm f/1.4, ``--scenes`` x 4 slices at ``--size`` px) with
   ``data_tools.mitsuba`` (its fast variant when libLLVM >= 16 is installed).
2. Trains the default network on the training split for ``--minutes`` (``configs/quickstart.toml``
   with the tiles scaled to the image: size/4 px cores, size/8 px overlap; ``KEY=VALUE``
   overrides go to ``train.py`` after these, e.g. ``train.pupil_tv=1e-3``).
3. Evaluates the checkpoint next to every classical baseline of ``neuralbokeh.evaluation.evaluate`` on the
   held-out split (``report/``: ``report.md``, error-vs-runtime plot, image grids) and prints it.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run(*args: str) -> None:
    print("$", " ".join(args), flush=True)
    subprocess.run([sys.executable, *args], check=True, cwd=ROOT)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", type=int, default=24)
    p.add_argument("--size", type=int, default=128)
    p.add_argument("--spp", type=int, default=256)
    p.add_argument("--minutes", type=float, default=15.0)
    p.add_argument("--data", type=Path, default=ROOT / "data" / "mitsuba_lens")
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "mitsuba_lens")
    p.add_argument("overrides", nargs="*", metavar="KEY=VALUE", help="training config overrides")
    args = p.parse_args()
    run("-m", "data_tools.mitsuba", "--out", str(args.data), "--scenes", str(args.scenes), "--size", str(args.size),
        str(args.size), "--slices", "4", "--aperture", "polygon:7", "--cat-eye", "0.6", "--focal-length", "85",
        "--f-number", "1.4", "--spp", str(args.spp), "--seed", "5")
    run("train.py", "configs/quickstart.toml", "--overwrite", f"data.roots=['{args.data}']", "data.test_fraction=0.25",
        f"model.tile={args.size // 4}", f"model.overlap={args.size // 8}", "train.steps=1000000",
        "train.lr_schedule='constant'", "train.eval_every=1000000", "train.checkpoint_every=200",
        f"train.out_dir='{args.out}'", *args.overrides, "--time-limit", str(args.minutes))
    run("-m", "neuralbokeh.evaluation", "--data", str(args.data), "--test-fraction", "0.25",
        "--models", str(args.out / "checkpoint.pt"), "--baselines", "all", "--repeats", "1", "--out", str(args.out / "report"))


if __name__ == "__main__":
    main()

"""The learned lens on physically rendered data, where the layered scatter is only an approximation.

    python benchmarks/mitsuba_learned.py [--scenes 24] [--size 128] [--minutes 15] [--spp 256] [--test-spp 2048]
        [--extra-test-scenes 0] [--loss-pool 2] [KEY=VALUE ...]

1. Renders (once; finished scenes are skipped) a Mitsuba 3 focal-stack dataset of non-planar
   procedural scenes (tilted textured rectangles, spheres, boxes, HDR point lights; 7-blade
   aperture with cat-eye 0.6, 85 mm f/1.4, ``--scenes`` x 4 slices at ``--size`` px) with
   ``data_tools.mitsuba`` (its fast variant when libLLVM >= 16 is installed).
2. Renders the held-out scenes again at ``--test-spp`` (the all-in-focus image at a quarter of
   it) into ``<data>_test<spp>``: at 256 spp the targets' noise (median 0.0125 RMS, tone-mapped
   display units) is as large as the differences between the best methods; 0 skips it.
   ``--extra-test-scenes N`` adds N new scenes (indices ``--scenes`` .. ``--scenes + N - 1``, never
   trained on) to that clean set: six held-out scenes do not separate the best methods.
3. Trains the default network on the training split for ``--minutes`` (``configs/quickstart.toml``
   with the tiles scaled to the image: size/4 px cores, size/8 px overlap, and
   ``train.loss_pool = --loss-pool``: the renders' noise would otherwise pull the learned blur
   small, ``docs/network.md``; at a constant rate, the weights averaged over the last ~100 steps,
   ``train.ema_steps = 100``; ``KEY=VALUE`` overrides go to ``train.py`` after these, e.g.
   ``train.pupil_tv=1e-3`` or ``model.field_gradient=false model.field_flow=true``).
4. Evaluates the checkpoint next to every classical baseline of ``neuralbokeh.evaluation.evaluate`` on the
   held-out split (``report/``: ``report.md`` with the per-scene comparison, error-vs-runtime
   plot, image grids) and on its clean render (``report_clean/``), and prints both.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from neuralbokeh.data.dataset import find_scenes, split_scenes  # noqa: E402


def run(*args: str) -> None:
    print("$", " ".join(args), flush=True)
    subprocess.run([sys.executable, *args], check=True, cwd=ROOT)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", type=int, default=24)
    p.add_argument("--size", type=int, default=128)
    p.add_argument("--spp", type=int, default=256)
    p.add_argument("--test-spp", type=int, default=2048, help="spp of the held-out scenes' clean render (0: none)")
    p.add_argument("--extra-test-scenes", type=int, default=0,
                   help="new scenes, never trained on, added to the clean held-out render (needs --test-spp > 0)")
    p.add_argument("--minutes", type=float, default=15.0)
    p.add_argument("--loss-pool", type=int, default=2, help="train.loss_pool: px blocks the loss averages in linear light (1: pixels)")
    p.add_argument("--data", type=Path, default=ROOT / "data" / "mitsuba_lens")
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "mitsuba_lens")
    p.add_argument("overrides", nargs="*", metavar="KEY=VALUE", help="training config overrides")
    args = p.parse_args()
    if args.extra_test_scenes < 0 or (args.extra_test_scenes and args.test_spp <= 0):
        p.error(f"--extra-test-scenes must be >= 0 and needs --test-spp > 0, got {args.extra_test_scenes} with --test-spp {args.test_spp}")

    def render(scenes: int) -> list[str]:  # scene i is drawn from the seed (5, i) alone: --scenes only bounds the indices
        return ["-m", "data_tools.mitsuba", "--scenes", str(scenes), "--size", str(args.size), str(args.size), "--slices", "4",
                "--aperture", "polygon:7", "--cat-eye", "0.6", "--focal-length", "85", "--f-number", "1.4", "--seed", "5"]

    run(*render(args.scenes), "--out", str(args.data), "--spp", str(args.spp))
    clean = args.data.with_name(f"{args.data.name}_test{args.test_spp}")
    if args.test_spp > 0:
        held_out = [int(s.name.removeprefix("scene_")) for s in split_scenes(find_scenes(args.data), "test", 0.25, 0)]
        extra = list(range(args.scenes, args.scenes + args.extra_test_scenes))
        run(*render(args.scenes + args.extra_test_scenes), "--out", str(clean), "--spp", str(args.test_spp),
            "--aif-spp", str(max(args.test_spp // 4, 1)), "--only", *map(str, held_out + extra))
    run("train.py", "configs/quickstart.toml", "--overwrite", f"data.roots=['{args.data}']", "data.test_fraction=0.25",
        f"model.tile={args.size // 4}", f"model.overlap={args.size // 8}", f"train.loss_pool={args.loss_pool}", "train.steps=1000000",
        "train.lr_schedule='constant'", "train.ema_steps=100", "train.eval_every=1000000", "train.checkpoint_every=200",
        f"train.out_dir='{args.out}'", *args.overrides, "--time-limit", str(args.minutes))
    run("-m", "neuralbokeh.evaluation", "--data", str(args.data), "--test-fraction", "0.25",
        "--models", str(args.out / "checkpoint.pt"), "--baselines", "all", "--repeats", "1", "--out", str(args.out / "report"))
    if args.test_spp > 0:
        run("-m", "neuralbokeh.evaluation", "--data", str(clean), "--split", "all", "--models", str(args.out / "checkpoint.pt"),
            "--baselines", "all", "--repeats", "1", "--out", str(args.out / "report_clean"))


if __name__ == "__main__":
    main()

"""The learned lens on physically rendered data, where the layered scatter is only an approximation.

    python benchmarks/mitsuba_learned.py [--scenes 24] [--size 128] [--minutes 15] [--spp 256] [--test-spp 1024]
        [--extra-test-scenes 18] [--train-scenes 48] [--loss-pool 2] [KEY=VALUE ...]

1. Renders (once; finished scenes are skipped) a Mitsuba 3 focal-stack dataset of non-planar
   procedural scenes (tilted textured rectangles, spheres, boxes, HDR point lights; 7-blade
   aperture with cat-eye 0.6, 85 mm f/1.4, ``--scenes`` x 4 slices at ``--size`` px) with
   ``data_tools.mitsuba`` (its fast variant when libLLVM >= 16 is installed).
2. Renders the held-out scenes again at ``--test-spp`` (the all-in-focus image at a quarter of
   it) into ``<data>_test<spp>``: at 256 spp the targets' noise (median 0.0125 RMS, tone-mapped
   display units) is as large as the differences between the best methods; 0 skips it.
   ``--extra-test-scenes N`` adds N new scenes (never trained on; the indices after the
   training-only ones of 3.) to that clean set: six held-out scenes do not separate the best methods.
3. ``--train-scenes N`` renders N more scenes at ``--spp`` for training only (indices ``--scenes``
   .. ``--scenes + N - 1``) into ``<data>_train`` (what more training scenes change, and why
   these defaults: ``docs/benchmarks.md``, "Twenty-four clean held-out scenes"). The training
   set is then a folder of links, ``<data>_trainset<N>``: the training split's scenes and these; the held-out split is
   unchanged (the evaluation's note that the model was trained with ``test_fraction`` 0 does
   not apply: no held-out scene is linked).
4. Trains the default network on the training split for ``--minutes`` (``configs/quickstart.toml``
   with the tiles scaled to the image: size/4 px cores, size/8 px overlap, and
   ``train.loss_pool = --loss-pool``: the renders' noise would otherwise pull the learned blur
   small, ``docs/network.md``; at a constant rate, the weights averaged over the last ~100 steps,
   ``train.ema_steps = 100``; ``KEY=VALUE`` overrides go to ``train.py`` after these, e.g.
   ``train.pupil_tv=1e-3`` or ``model.field_gradient=false model.field_flow=true``).
5. Evaluates the checkpoint next to every classical baseline of ``neuralbokeh.evaluation.evaluate`` on the
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


def link_scenes(folder: Path, scenes: list[Path]) -> None:
    """``folder`` holding a link to each of ``scenes`` (scene folders) and nothing else: a
    dataset of scenes from several renders, none copied."""
    folder.mkdir(parents=True, exist_ok=True)
    wanted = {s.name: s.resolve() for s in scenes}
    stale = sorted(e.name for e in folder.iterdir() if e.name not in wanted or e.resolve() != wanted[e.name])
    if stale:
        raise SystemExit(f"error: {folder} holds {len(stale)} entries that are not this run's training scenes "
                         f"(first: {stale[0]}); remove the folder to rebuild it")
    for name, target in wanted.items():
        if not (folder / name).exists():
            (folder / name).symlink_to(target, target_is_directory=True)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", type=int, default=24)
    p.add_argument("--size", type=int, default=128)
    p.add_argument("--spp", type=int, default=256)
    p.add_argument("--test-spp", type=int, default=1024, help="spp of the held-out scenes' clean render (0: none)")
    p.add_argument("--extra-test-scenes", type=int, default=18,
                   help="new scenes, never trained on, added to the clean held-out render (needs --test-spp > 0)")
    p.add_argument("--train-scenes", type=int, default=48,
                   help="new scenes rendered for training only, added to the training split (the held-out split is unchanged)")
    p.add_argument("--minutes", type=float, default=15.0)
    p.add_argument("--loss-pool", type=int, default=2, help="train.loss_pool: px blocks the loss averages in linear light (1: pixels)")
    p.add_argument("--data", type=Path, default=ROOT / "data" / "mitsuba_lens")
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "mitsuba_lens")
    p.add_argument("overrides", nargs="*", metavar="KEY=VALUE", help="training config overrides")
    args = p.parse_args()
    if args.extra_test_scenes < 0 or (args.extra_test_scenes and args.test_spp <= 0):
        p.error(f"--extra-test-scenes must be >= 0 and needs --test-spp > 0, got {args.extra_test_scenes} with --test-spp {args.test_spp}")
    if args.train_scenes < 0:
        p.error(f"--train-scenes must be >= 0, got {args.train_scenes}")

    def render(scenes: int) -> list[str]:  # scene i is drawn from the seed (5, i) alone: --scenes only bounds the indices
        return ["-m", "data_tools.mitsuba", "--scenes", str(scenes), "--size", str(args.size), str(args.size), "--slices", "4",
                "--aperture", "polygon:7", "--cat-eye", "0.6", "--focal-length", "85", "--f-number", "1.4", "--seed", "5"]

    run(*render(args.scenes), "--out", str(args.data), "--spp", str(args.spp))
    clean = args.data.with_name(f"{args.data.name}_test{args.test_spp}")
    if args.test_spp > 0:
        held_out = [int(s.name.removeprefix("scene_")) for s in split_scenes(find_scenes(args.data), "test", 0.25, 0)]
        first_extra = args.scenes + args.train_scenes  # after the training-only scenes
        extra = list(range(first_extra, first_extra + args.extra_test_scenes))
        # the clean set is scored whole: a scene left there by a run with other flags may be a training scene of this one
        there = {e.name for e in clean.iterdir() if e.is_dir() and not e.name.startswith(".")} if clean.is_dir() else set()
        stray = sorted(there - {f"scene_{i:05d}" for i in held_out + extra})
        if stray:
            raise SystemExit(f"error: {clean} holds {len(stray)} scenes outside this run's held-out set (first: {stray[0]}); "
                             "move them out or pass another --data")
        run(*render(first_extra + args.extra_test_scenes), "--out", str(clean), "--spp", str(args.test_spp),
            "--aif-spp", str(max(args.test_spp // 4, 1)), "--only", *map(str, held_out + extra))
    train_root, test_fraction = args.data, 0.25
    if args.train_scenes > 0:
        new = range(args.scenes, args.scenes + args.train_scenes)
        extra_root = args.data.with_name(f"{args.data.name}_train")
        run(*render(new.stop), "--out", str(extra_root), "--spp", str(args.spp), "--only", *map(str, new))
        train_root, test_fraction = args.data.with_name(f"{args.data.name}_trainset{args.train_scenes}"), 0.0
        link_scenes(train_root, split_scenes(find_scenes(args.data), "train", 0.25, 0) + [extra_root / f"scene_{i:05d}" for i in new])
    run("train.py", "configs/quickstart.toml", "--overwrite", f"data.roots=['{train_root}']", f"data.test_fraction={test_fraction}",
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

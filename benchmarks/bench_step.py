"""What a training step of the lens network costs, by tile size, against windows cut and put back
one slice per tile (the way before ``ops.tiles`` used ``unfold`` / ``fold``), in the same run.

    python benchmarks/bench_step.py [--data data/floor] [--tiles 32 64] [--steps 5]

Forward + backward of the MSE on one batch of 4 whole frames of ``--data`` (the floor set of
``quality_floor.py`` by default), the untrained default network (Gaussian pupils, learned
cat-eye), median over ``--steps`` steps after one warm-up, 2 threads.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import neuralbokeh.networks.lens as lens_module  # noqa: E402
from neuralbokeh.data.dataset import FocalStackDataset  # noqa: E402
from neuralbokeh.networks import ModelConfig, build_model  # noqa: E402
from neuralbokeh.ops import tiles  # noqa: E402
from neuralbokeh.training.loop import Samples  # noqa: E402


def sliced_tile(x, layout):
    h, w = x.shape[-2:]
    top, bottom, left, right = layout.pads(h, w)
    x = F.pad(x, (left, right, top, bottom), mode="replicate")
    win = layout.window
    return torch.cat([x[:, :, r : r + win, c : c + win] for _, r, c in layout.origins()], dim=1)


def sliced_overlap_add(windows, layout):
    b, _, c, win, _ = windows.shape
    canvas = windows.new_zeros(b, c, *layout.padded_size)
    for k, r, col in layout.origins():
        canvas[:, :, r : r + win, col : col + win] += windows[:, k]
    return canvas


def step_seconds(model, x, window, y, steps: int) -> float:
    times = []
    for i in range(steps + 1):
        t = time.perf_counter()
        ((model(x, window) - y) ** 2).mean().backward()
        if i:
            times.append(time.perf_counter() - t)
    return statistics.median(times)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=ROOT / "data" / "floor")
    p.add_argument("--tiles", type=int, nargs="+", default=[32, 64])
    p.add_argument("--overlap", type=int, default=16)
    p.add_argument("--steps", type=int, default=5)
    args = p.parse_args()
    torch.set_num_threads(2)
    ds = FocalStackDataset([args.data], split="train", test_fraction=0.2, split_seed=0)
    x, y, _, window, _ = Samples(ds, cache=False).batch([0, 1, 2, 3], torch.device("cpu"))
    print(f"{args.data}: batch of 4 frames {tuple(x.shape[-2:])}, forward + backward, median of {args.steps}")
    print("| tile px | unfold / fold, s | one slice per tile, s | ratio |\n|---|---|---|---|")
    for t in args.tiles:
        model = build_model(ModelConfig(tile=t, overlap=args.overlap, pupil_init="gaussian").resolved(ds.max_coc_px), ds.contract())
        now = step_seconds(model, x, window, y, args.steps)
        lens_module.tile, lens_module.overlap_add = sliced_tile, sliced_overlap_add
        try:
            before = step_seconds(model, x, window, y, args.steps)
        finally:
            lens_module.tile, lens_module.overlap_add = tiles.tile, tiles.overlap_add
        print(f"| {t} | {now:.2f} | {before:.2f} | {before / now:.2f}x |", flush=True)


if __name__ == "__main__":
    main()

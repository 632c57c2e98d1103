"""What a training batch of random crops costs to read: tiled scene files against scanline ones.

    python benchmarks/bench_crops.py [--data DATASET] [--size 1920 1080] [--crop 256] [--repeats 40]

Training on crops of large frames without holding the scenes in memory (``data.cache = false``,
so the trainer's RSS does not grow with the dataset) reads each crop from disk. A scanline EXR
decodes whole rows (a 256^2 crop of a 1920 px frame: 7.5x its pixels); a tiled one only the tiles
holding the crop. Makes (or takes with ``--data``) a dataset, writes a scanline copy and a tiled
copy of its training scenes (the same pixels), and prints the median time to read a batch of 4
crops (``Samples.batch``, the trainer's own reader) from each, and from memory, as ratios to the
scanline files.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402

from data_tools.synth import main as synth  # noqa: E402
from neuralbokeh.core.io import image_attributes, image_channels, read_image, write_image  # noqa: E402
from neuralbokeh.data.dataset import TILE_PX, FocalStackDataset  # noqa: E402
from neuralbokeh.training.loop import Samples  # noqa: E402


def rewrite(src: Path, dst: Path, tile: int | None) -> Path:
    """A copy of dataset ``src``'s scenes with every EXR stored in ``tile`` px tiles (None: scanlines)."""
    for folder in FocalStackDataset(src, "all").scenes:
        (dst / folder.name).mkdir(parents=True)
        shutil.copy(folder / "scene.json", dst / folder.name / "scene.json")
        for f in folder.glob("*.exr"):
            write_image(dst / folder.name / f.name, read_image(f), image_attributes(f, ["neuralbokeh:units"]),
                        image_channels(f), tile=tile)
    return dst


def batch_ms(ds: FocalStackDataset, cache: bool, crop: int, repeats: int) -> float:
    samples, times = Samples(ds, cache, [crop, crop]), []
    if cache:
        for i in range(len(ds)):
            samples.item(i)
    for k in range(repeats):
        t = time.perf_counter()
        samples.batch([(4 * k + j) % len(ds) for j in range(4)], torch.device("cpu"), seed=k)
        times.append(time.perf_counter() - t)
    return 1000 * statistics.median(times)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, help="a dataset to read (default: 2 synthetic scenes made at --size)")
    p.add_argument("--size", nargs=2, type=int, default=[1920, 1080], metavar=("W", "H"))
    p.add_argument("--crop", type=int, default=256)
    p.add_argument("--repeats", type=int, default=40)
    args = p.parse_args()
    torch.set_num_threads(2)
    with tempfile.TemporaryDirectory() as tmp:
        src = args.data
        if src is None:
            src = Path(tmp) / "made"
            synth(["--out", str(src), "--scenes", "2", "--size", *map(str, args.size), "--slices", "4", "--seed", "3"])
        runs = {"scanline": rewrite(src, Path(tmp) / "scan", None), f"tiled {TILE_PX}": rewrite(src, Path(tmp) / "tiled", TILE_PX)}
        ms = {name: batch_ms(FocalStackDataset(d, "all"), False, args.crop, args.repeats) for name, d in runs.items()}
        ms["in memory"] = batch_ms(FocalStackDataset(runs["scanline"], "all"), True, args.crop, args.repeats)
    print(f"batch of 4 crops of {args.crop}^2 px, median of {args.repeats}")
    print(f"{'files':<12} {'ms':>8} {'x scanline':>10}")
    for name, t in ms.items():
        print(f"{name:<12} {t:>8.1f} {t / ms['scanline']:>10.3f}")


if __name__ == "__main__":
    main()

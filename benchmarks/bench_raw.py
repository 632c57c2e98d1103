"""Peak memory and time per slice of ``data_tools.raw`` on synthetic DNG stacks.

    python benchmarks/bench_raw.py                      # 250x186 and 1080x720, 5 slices each

For each ``--sizes`` entry: a 5-slice synthetic DNG stack (``data_tools.raw.synthetic``, made
once under ``--out-dir``), then ``data_tools.raw`` on it in a fresh process (``--worker``), so
the peak RSS printed is the RAW pipeline's own (decode, alignment, fusion, depth from focus,
writing). Also printed: seconds per slice, and the depth error in diopters against the
stack's truth on the textured pixels (the regularisation is what changed; its accuracy is the
other half of the claim).
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def worker(stack: Path, out: Path) -> None:
    sys.path.insert(0, str(ROOT))
    from data_tools.raw.__main__ import main

    t = time.perf_counter()
    rc = main([str(stack), "--out", str(out), "--sensor-width", "12", "--white-balance", "none"])
    print(json.dumps({"rc": rc, "seconds": time.perf_counter() - t,
                      "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))


def depth_error(stack: Path, out: Path) -> float:
    """Median |1/depth - 1/true depth| (diopters) over the output scene (cropped to its window)."""
    from neuralbokeh.core.io import read_image
    from neuralbokeh.data.dataset import load_scene

    scene = load_scene(next(p for p in out.iterdir() if p.is_dir()))
    (r0, r1), (c0, c1) = scene["meta"]["generator"]["crop"]["rows"], scene["meta"]["generator"]["crop"]["cols"]
    truth = read_image(stack / "truth" / "depth.exr")[r0:r1, c0:c1, 0].astype(np.float64)
    est = scene["depth"].astype(np.float64)
    if truth.shape != est.shape:
        return float("nan")  # resized output: not comparable pixel for pixel
    with np.errstate(divide="ignore"):
        return float(np.median(np.abs(1.0 / est - 1.0 / truth)))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", nargs="+", default=["250x186", "1080x720"], help="W x H of the stacks")
    p.add_argument("--slices", type=int, default=5, help="slices per stack")
    p.add_argument("--out-dir", type=Path, default=ROOT / "runs" / "bench_raw", help="stacks and outputs")
    p.add_argument("--worker", nargs=2, type=Path, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.worker:
        worker(*args.worker)
        return
    print(f"{'size':>10} {'slices':>6} {'peak RSS MB':>12} {'s total':>8} {'s / slice':>9} {'median |dD| 1/m':>16}")
    for size in args.sizes:
        w, h = (int(v) for v in size.split("x"))
        stacks = args.out_dir / f"stacks_{size}"
        if not (stacks / "stack_000").exists():
            subprocess.run([sys.executable, "-m", "data_tools.raw.synthetic", "--out", str(stacks), "--stacks", "1", "--size",
                            str(w), str(h), "--slices", str(args.slices)], check=True, cwd=ROOT)
        out = args.out_dir / f"out_{size}"
        shutil.rmtree(out, ignore_errors=True)
        res = subprocess.run([sys.executable, __file__, "--worker", str(stacks / "stack_000"), str(out)], capture_output=True,
                             text=True, cwd=ROOT)
        if res.returncode != 0:
            raise RuntimeError(res.stderr[-3000:])
        r = json.loads(res.stdout.strip().splitlines()[-1])
        err = depth_error(stacks / "stack_000", out)
        print(f"{size:>10} {args.slices:>6} {r['rss_mb']:>12.0f} {r['seconds']:>8.1f} {r['seconds'] / args.slices:>9.2f} {err:>16.4f}",
              flush=True)


if __name__ == "__main__":
    main()

"""What the cat-eye's drift costs a render: the default export of a trained lens model with the
per-pixel colour gain of each band (``LensBokeh.drift_lattice``, ``colour_gains``) against the
same model exported with the drift set to zero, in one process, alternating.

    python benchmarks/bench_drift.py --model runs/any_res/checkpoint.pt [--size 1920 1080]
        [--tile PX] [--repeats 7] [--out-dir runs/bench_drift] [--reuse]

The frames are ``bench_runtime.py``'s procedural 1080p frame (largest |CoC| 40 px, in
proportion to the width at other sizes), a third of its CoC and its left half in focus. Both
files are exported with ``export.py``'s parity check (each against its own PyTorch function: the
zero-drift one against the module with the drift patched to zero, which is what the graph
without the flow's ops computes). Printed: the median ms per frame of each file (renders
alternate, so a drift of the machine's speed hits both), the ratio, and the largest
difference between the two outputs (what the drift changes on these frames).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_runtime import _frames, alternating_ms  # noqa: E402

from neuralbokeh.export.exporter import export_checkpoint  # noqa: E402
from neuralbokeh.networks.lens import LensBokeh  # noqa: E402
from neuralbokeh.runtime.onnx_model import OnnxBokeh  # noqa: E402


def _export(args: argparse.Namespace, out: Path, drift: bool) -> None:
    if args.reuse and out.is_file():
        return
    original = LensBokeh.drift_lattice

    def no_drift(self, *a, **k):
        nodes, rows, cols = original(self, *a, **k)
        return torch.zeros_like(nodes), rows, cols

    if not drift:
        LensBokeh.drift_lattice = no_drift
    try:
        t = time.perf_counter()
        report = export_checkpoint(args.model, out, size=(args.size[1], args.size[0]), tile_px=args.tile, threads=args.threads,
                                   progress=True)
        print(f"exported {out.name} in {time.perf_counter() - t:.0f} s, parity {max(report['parity'].values()):.2e}", flush=True)
    finally:
        LensBokeh.drift_lattice = original


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--model", type=Path, required=True, help="a lens checkpoint (train.py)")
    p.add_argument("--size", type=int, nargs=2, default=(1920, 1080), metavar=("W", "H"))
    p.add_argument("--tile", type=int, default=None, help="export.py --tile (default: the trained tiles)")
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--out-dir", type=Path, default=ROOT / "runs" / "bench_drift")
    p.add_argument("--reuse", action="store_true", help="keep the exports of an earlier run")
    args = p.parse_args()
    args.out_dir.mkdir(parents=True, exist_ok=True)
    w, h = args.size
    frames, _ = _frames(args, h, w, 40.0 * w / 1920)
    files = {name: args.out_dir / f"{name}_{w}x{h}.onnx" for name in ("drift", "no_drift")}
    for name, path in files.items():
        _export(args, path, name == "drift")
    models = {name: OnnxBokeh(path, threads=args.threads) for name, path in files.items()}
    print(f"{'frame':16s} {'drift ms':>9s} {'no drift ms':>12s} {'ratio':>6s} {'max |diff|':>11s}")
    for frame, path in frames.items():
        z = np.load(path)
        med, outs = alternating_ms(models, z["aif"], z["coc"], args.repeats)
        diff = float(np.abs(outs["drift"] - outs["no_drift"]).max())
        print(f"{frame:16s} {med['drift']:9.0f} {med['no_drift']:12.0f} {med['drift'] / med['no_drift']:6.2f} {diff:11.2e}", flush=True)


if __name__ == "__main__":
    main()

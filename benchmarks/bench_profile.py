"""Where a lens export spends a 1080p render: onnxruntime's own profiler, node times summed into
the frame-wide ops, the per-tile ops and the per-band ops.

    python benchmarks/bench_profile.py [--onnx runs/bench_options/prior_default.onnx] [--seed 3]

The file: a lens network's export for 1920x1080 plates (default: the untrained prior's default
export that ``bench_options.py`` writes; run it first). The frames: ``bench_runtime.py``'s
procedural frame (largest |CoC| 40 px), a third of its CoC and its left half in focus. Per frame,
one warm-up and one profiled render each in a session of its own: the render's ms, the node time
(ms) of the graph's frame-wide ops (the windows' cuts, the fill), of each output core's ops (the
overlap-add, the composite and the encoding of the cores a blur reaches), of each tile's own ops
and of its bands' ops (``If`` nodes left out: their time is that of the
nodes they hold), the tiles and band scatters that ran, and the frame-wide ops that cost most.
"""

from __future__ import annotations

import argparse
import collections
import json
import re
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_runtime import H, W, _frames  # noqa: E402

from neuralbokeh.runtime import onnx_model  # noqa: E402


def _part(name: str) -> str:
    """Which part of the graph a node belongs to, from the names ``lens_graph`` gives it."""
    if re.match(r"t\d+\.n\d+s\d", name):
        return "band"
    if re.match(r"c\d+", name):
        return "core"
    return "tile" if re.match(r"t\d+", name) else "frame"


def profile(path: Path, aif: np.ndarray, coc: np.ndarray, threads: int, prefix: str) -> tuple[float, dict, collections.Counter, int, int]:
    """One profiled render: (ms, node ms per part, frame-wide ms per op type, tiles run, band scatters run)."""
    options = ort.SessionOptions

    class Profiled(options):
        def __init__(self) -> None:
            super().__init__()
            self.enable_profiling, self.profile_file_prefix = True, prefix

    onnx_model.ort.SessionOptions = Profiled  # make_session's options, with the profiler on
    try:
        model = onnx_model.OnnxBokeh(path, threads=threads)
    finally:
        onnx_model.ort.SessionOptions = options
    model.render_coc(aif, coc)  # warm-up (profiled too: halved below)
    t = time.perf_counter()
    model.render_coc(aif, coc)
    ms = 1000.0 * (time.perf_counter() - t)
    events = json.loads(Path(model.session.end_profiling()).read_text())
    parts: dict[str, float] = collections.defaultdict(float)
    frame_ops: collections.Counter = collections.Counter()
    for e in events:
        if e.get("cat") != "Node" or not e["name"].endswith("_kernel_time") or e["args"]["op_name"] == "If":
            continue
        part = _part(e["name"])
        parts[part] += e["dur"] / 2000.0  # us over two renders -> ms per render
        if part == "frame":
            frame_ops[e["args"]["op_name"]] += e["dur"] / 2000.0
    return ms, parts, frame_ops, model.last_tiles_run, model.last_bands_run


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--onnx", type=Path, default=ROOT / "runs" / "bench_options" / "prior_default.onnx")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--out-dir", type=Path, default=ROOT / "runs" / "bench_profile")
    args = p.parse_args()
    if not args.onnx.is_file():
        raise SystemExit(f"error: no export at {args.onnx}: run benchmarks/bench_options.py first, or give --onnx")
    args.out_dir.mkdir(parents=True, exist_ok=True)
    args.repeats = 1
    frames, _ = _frames(args, H, W, 40.0)
    heads = ("render ms", "frame-wide", "per core", "per tile", "per band", "tiles", "bands")
    print(f"{'frame':16s} " + " ".join(f"{h:>10s}" for h in heads) + "   costliest frame-wide ops (ms)")
    with tempfile.TemporaryDirectory() as tmp:
        for name, path in frames.items():
            z = np.load(path)
            ms, parts, ops, tiles, bands = profile(args.onnx, z["aif"], z["coc"], args.threads, str(Path(tmp) / name))
            top = ", ".join(f"{op} {v:.0f}" for op, v in ops.most_common(4))
            cells = [ms, parts["frame"], parts["core"], parts["tile"], parts["band"], tiles, bands]
            print(f"{name:16s} " + " ".join(f"{v:10.0f}" for v in cells) + f"   {top}", flush=True)


if __name__ == "__main__":
    main()

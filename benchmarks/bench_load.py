"""What loading a lens model costs before the first frame, per onnxruntime graph optimisation level.

    python benchmarks/bench_load.py MODEL.onnx FRAME.npz     # e.g. bench_runtime.py's default.onnx, frame_1920x1080_full.npz

A render-farm task that renders one frame pays the load every time. For each level (``all`` is
onnxruntime's default), and for a file saved already optimised (``optimized_model_filepath``)
loaded with optimisation off: the load (session creation, median of ``--repeats``, each in a
fresh process so no cache helps) and the render of the frame (median of ``--repeats`` after a
warm-up), as ratios to the default level, and the largest difference from its output.

Then the whole compositing CLI on that frame, one frame per process as a render-farm task runs
it (load + read + render + write, ``--graph-optimization auto``), against the render alone: the
frame as an EXR plate, the same colours as a premultiplied render with alpha 1 everywhere (so
every tile goes through the network) and its CoC map as ``--depth-math coc``. The CLI renders
the colour, its alpha and a uniform field together (a batch of three), so its render is about three
of the row above.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
LEVELS = ("all", "extended", "basic", "disable")


def worker(model: str, frame: str, level: str, repeats: int, threads: int, out: str, save: str | None) -> None:
    import onnxruntime as ort

    from neuralbokeh.runtime.onnx_model import OnnxBokeh

    so = ort.SessionOptions()
    so.graph_optimization_level = {"all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL,
                                   "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
                                   "basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
                                   "disable": ort.GraphOptimizationLevel.ORT_DISABLE_ALL}[level]
    so.enable_mem_pattern = False
    so.intra_op_num_threads, so.inter_op_num_threads = threads, 1
    if save:
        so.optimized_model_filepath = save
    t = time.perf_counter()
    session = ort.InferenceSession(model, so, providers=["CPUExecutionProvider"])
    load = time.perf_counter() - t
    if repeats == 0:  # the load alone
        print(json.dumps({"load_s": load, "render_s": None}))
        return
    m = OnnxBokeh(model, threads=threads)
    m.session = session
    data = np.load(frame)
    res = m.render_coc(data["aif"], data["coc"])
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        res = m.render_coc(data["aif"], data["coc"])
        times.append(time.perf_counter() - t)
    np.save(out, res)
    print(json.dumps({"load_s": load, "render_s": statistics.median(times)}))


def _run(model: Path, frame: Path, level: str, repeats: int, threads: int, out: Path, save: Path | None = None) -> dict:
    cmd = [sys.executable, __file__, str(model), str(frame), "--worker", level, "--repeats", str(repeats), "--threads", str(threads),
           "--out", str(out)] + (["--save", str(save)] if save else [])
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    if res.returncode != 0:
        raise RuntimeError(res.stderr[-3000:])
    return json.loads(res.stdout.strip().splitlines()[-1])


def cli_row(model: Path, frame: Path, threads: int, repeats: int, tmp: Path, render_s: float) -> None:
    """Wall time of ``python -m neuralbokeh.runtime.composite`` on the frame (median of ``repeats``
    fresh processes), and its ratio to ``render_s`` (one render, graph optimisation ``all``)."""
    sys.path.insert(0, str(ROOT))
    from neuralbokeh.core.io import write_image

    data = np.load(frame)
    write_image(tmp / "plate.exr", data["aif"])
    write_image(tmp / "alpha.exr", np.ones(data["coc"].shape, np.float32))
    write_image(tmp / "coc.exr", data["coc"].astype(np.float32))
    cmd = [sys.executable, "-m", "neuralbokeh.runtime.composite", "--model", str(model), "--plate", str(tmp / "plate.exr"),
           "--render", str(tmp / "plate.exr"), "--alpha", str(tmp / "alpha.exr"), "--depth", str(tmp / "coc.exr"),
           "--depth-math", "coc", "--threads", str(threads), "--out", str(tmp / "comp.exr"), "--overwrite"]
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        subprocess.run(cmd, cwd=ROOT, check=True, capture_output=True)
        times.append(time.perf_counter() - t)
    cli = statistics.median(times)
    print(f"compositing CLI, one frame per process: {cli:.2f} s = {cli / render_s:.2f}x the render alone "
          f"({render_s:.3f} s); render, alpha and a uniform field in one batch, EXR read and written", flush=True)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model", type=Path)
    p.add_argument("frame", type=Path, help=".npz with aif (H, W, 3) linear and coc (H, W) px")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--worker", help=argparse.SUPPRESS)
    p.add_argument("--out", help=argparse.SUPPRESS)
    p.add_argument("--save", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.worker:
        worker(str(args.model), str(args.frame), args.worker, args.repeats, args.threads, args.out, args.save)
        return
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        print(f"{args.model.name}: {args.model.stat().st_size / 1e6:.0f} MB, {args.threads} threads, median of {args.repeats}")
        print(f"{'optimisation':<22} {'load s':>7} {'x all':>6} {'render s':>9} {'x all':>6} {'max diff':>9}", flush=True)
        base = None
        for level in LEVELS:
            runs = [_run(args.model, args.frame, level, 0 if i else args.repeats, args.threads, tmp / f"{level}.npy")
                    for i in range(args.repeats)]
            load, render = statistics.median(r["load_s"] for r in runs), runs[0]["render_s"]
            base = base or (load, render, np.load(tmp / "all.npy"))
            print(f"{level:<22} {load:7.2f} {load / base[0]:6.2f} {render:9.3f} {render / base[1]:6.2f} "
                  f"{np.abs(np.load(tmp / f'{level}.npy') - base[2]).max():9.1e}", flush=True)
        cli_row(args.model, args.frame, args.threads, args.repeats, tmp, base[1])
        saved = tmp / "optimised.onnx"
        _run(args.model, args.frame, "all", 0, args.threads, tmp / "save.npy", saved)
        try:
            _run(saved, args.frame, "disable", 0, args.threads, tmp / "saved.npy")
        except RuntimeError as e:  # onnxruntime may write an optimised file it cannot read back
            print(f"saved optimised model: onnxruntime cannot load it: {str(e).strip().splitlines()[-1][:200]}")


if __name__ == "__main__":
    main()

"""Exported files of one plate size, timed against each other on the same frames, in one process,
renders alternating.

    python benchmarks/bench_files.py A.onnx B.onnx [...] [--repeats 9] [--threads 2] [--seed 3]
        [--first-runtime DIR]

For comparing graphs that compute the same thing (an export of an earlier version of the
builder against today's, or two export options): the frames are ``bench_runtime.py``'s
procedural frame at the files' size (largest |CoC| 40 px at 1080p, in proportion to the width at
other sizes), a third of its CoC, its left half in focus and all of it in focus; and a frame of
the same colours whose CoC is continuous (a ramp across the width from the largest |CoC| in
front to the largest behind) and that ramp at a third. Each round
renders every file on every frame, so a drift of the machine's speed hits all alike, the ratios
between frames included. Printed per frame: each file's median ms, its ratio to the first
file, and the largest difference of its output from the first file's (linear light; float32
rounding of the normalised output is ~3e-5 of a value near 1e2); then per file how much
faster the lighter frames are than the full one, and the ramp than its third. ``--first-runtime
DIR`` renders the first file with the runtime of another checkout (e.g. ``git worktree add
/tmp/before <commit>``), loaded beside this one, so that a change of the runtime's own numpy work
is timed with its graph.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_runtime import _frames  # noqa: E402

from neuralbokeh.runtime.onnx_model import OnnxBokeh  # noqa: E402


def runtime_of(root: Path) -> type:
    """The ``OnnxBokeh`` class of the checkout at ``root``, imported as the package ``bench_first``
    (its runtime imports its own package relatively, so it runs that checkout's code throughout)."""
    init = root / "neuralbokeh" / "__init__.py"
    if not init.is_file():
        raise SystemExit(f"error: no neuralbokeh checkout at {root} (no {init})")
    spec = importlib.util.spec_from_file_location("bench_first", init, submodule_search_locations=[str(init.parent)])
    package = importlib.util.module_from_spec(spec)
    sys.modules["bench_first"] = package
    spec.loader.exec_module(package)
    return importlib.import_module("bench_first.runtime.onnx_model").OnnxBokeh


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("files", nargs="+", type=Path, help="exported .onnx files of one plate size")
    p.add_argument("--repeats", type=int, default=9)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--out-dir", type=Path, default=ROOT / "runs" / "bench_files")
    p.add_argument("--first-runtime", type=Path, help="render the first file with the runtime of the checkout at this folder")
    args = p.parse_args()
    for f in args.files:
        if not f.is_file():
            raise SystemExit(f"error: no exported file at {f}")
    args.out_dir.mkdir(parents=True, exist_ok=True)
    first_class = runtime_of(args.first_runtime) if args.first_runtime else OnnxBokeh
    models = {f.name: (first_class if i == 0 else OnnxBokeh)(f, threads=args.threads) for i, f in enumerate(args.files)}
    if len(models) != len(args.files):
        raise SystemExit("error: give files of different names (they label the columns)")
    sizes = {(m.height, m.width) for m in models.values()}
    if len(sizes) != 1:
        raise SystemExit(f"error: the files are exported for different plate sizes {sorted(sizes)}; give files of one size")
    (h, w), = sizes
    frames, _ = _frames(args, h, w, 40.0 * w / 1920)
    z = np.load(frames["full"])
    ramp = np.broadcast_to(np.linspace(-1.0, 1.0, w), (h, w)) * np.abs(z["coc"]).max()  # a continuous CoC, near to far
    for name, coc in (("all_in_focus", np.zeros_like(z["coc"])), ("ramp", ramp), ("ramp_third", ramp / 3.0)):
        frames[name] = args.out_dir / f"frame_{w}x{h}_{name}.npz"
        np.savez(frames[name], aif=z["aif"], coc=coc)
    first = next(iter(models))
    inputs = {frame: dict(np.load(path)) for frame, path in frames.items()}
    outs = {(frame, n): m.render_coc(z["aif"], z["coc"]) for frame, z in inputs.items() for n, m in models.items()}  # warm-up
    times: dict[tuple[str, str], list[float]] = {key: [] for key in outs}
    for _ in tqdm(range(args.repeats), desc="rounds", unit="round"):
        for (frame, n), m in ((key, models[key[1]]) for key in outs):  # every file on every frame, each round
            z = inputs[frame]
            time.sleep(0.1)  # the last session's threads stop spin-waiting (onnxruntime's default), not stealing this one's cores
            t = time.perf_counter()
            m.render_coc(z["aif"], z["coc"])
            times[frame, n].append(1000.0 * (time.perf_counter() - t))
    med = {key: statistics.median(v) for key, v in times.items()}
    print(f"{'frame':16s} " + " ".join(f"{name:>28s}" for name in models) + "   (ms, x first, max |difference| from the first)")
    for frame in frames:
        cells = [f"{med[frame, n]:8.0f} {med[frame, n] / med[frame, first]:5.2f}x "
                 f"{np.abs(outs[frame, n] - outs[frame, first]).max():9.1e}" for n in models]
        print(f"{frame:16s} " + " ".join(f"{c:>28s}" for c in cells), flush=True)
    for name in models:
        lighter = [frame for frame in frames if not frame.startswith(("full", "ramp"))]
        ratios = ", ".join(f"{frame} {med['full', name] / med[frame, name]:.2f}x" for frame in lighter)
        print(f"{name}: the full frame's time over the lighter frames': {ratios}; "
              f"the ramp's over its third's: {med['ramp', name] / med['ramp_third', name]:.2f}x")


if __name__ == "__main__":
    main()

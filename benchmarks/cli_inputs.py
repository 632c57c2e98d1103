"""What the command-line tools do with a compositor's inputs: exit code, message, data kept.

    python benchmarks/cli_inputs.py                         # the checkout's code (~2 min on 2 cores)
    git worktree add /tmp/old REV && python benchmarks/cli_inputs.py --repo /tmp/old   # another revision's

Every case of the compositor issue (overwrites, multi-layer EXRs, depth conventions, broken
files, frame patterns, outputs) is run as a user would, each command in its own process, with
``--repo``'s code (``python -m`` and the CLI scripts run from that folder, so its package is the
one imported). A small synthetic dataset, two short training runs, an export and the compositing
demo's inputs are made first with the same code. Printed per case: the exit code, what the user
saw on stderr (``one line``, ``traceback``, ``warned`` or nothing) and whether the files the case
must not touch are byte-identical afterwards (``kept`` / ``LOST``). Nothing here is timed.
"""

from __future__ import annotations

import argparse
import hashlib
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _run(repo: Path, argv: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *argv], cwd=repo, capture_output=True, text=True)


def _digest(paths: list[Path]) -> list[str | None]:
    return [hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else None for p in paths]


def _seen(res: subprocess.CompletedProcess) -> str:
    err = res.stderr
    if "Traceback" in err:
        return f"traceback ({len(err.splitlines())} lines)"
    lines = [ln for ln in err.splitlines() if ln.strip() and "%|" not in ln]  # progress bars aside
    errors = [ln for ln in lines if ln.startswith("error:")]
    if errors:
        return f"one line: {errors[0][:90]}" if len(errors) == 1 else f"{len(errors)} error lines"
    warned = [ln for ln in (res.stdout + err).splitlines() if "unlikely" in ln or "warning" in ln.lower()]
    return f"warned: {warned[0][:90]}" if warned else "-"


def setup(repo: Path, ws: Path) -> dict[str, Path]:
    """Dataset, two finished runs, an export and the demo's compositing inputs, made by ``repo``."""
    steps = [["-m", "data_tools.synth", "--out", str(ws / "data"), "--scenes", "4", "--size", "64", "64",
              "--slices", "2", "--seed", "1"]]
    for run in ("run_a", "run_b"):
        cfg = ws / f"{run}.toml"
        cfg.write_text(f'[data]\nroots = ["{ws / "data"}"]\ntest_fraction = 0.25\n[model]\ntile = 32\noverlap = 8\n'
                       f'[train]\nsteps = 20\nbatch_size = 2\neval_every = 20\ncheckpoint_every = 20\n'
                       f'out_dir = "{ws / run}"\n')
        steps.append(["train.py", str(cfg)])
    steps += [["export.py", str(ws / "run_a" / "checkpoint.pt"), "--out", str(ws / "lens.onnx")],
              ["-m", "data_tools.demo_composite", "--scene", str(ws / "data" / "scene_00000"), "--out", str(ws / "demo")]]
    for argv in steps:
        res = _run(repo, argv)
        if res.returncode != 0:
            raise RuntimeError(f"setup step {argv[:2]} failed:\n{res.stderr[-2000:]}")
    return {"onnx": ws / "lens.onnx", "demo": ws / "demo"}


def layered_files(ws: Path, demo: Path) -> None:
    """The demo's layers as a Blender multi-layer EXR, a Nuke rgba + depth.Z EXR, an RGBA EXR,
    a 5-channel EXR, and depth maps in mm and as 1/z."""
    sys.path.insert(0, str(ROOT))
    from neuralbokeh.core.io import read_image, write_image

    rgb, z, a = (read_image(demo / f"{n}.exr") for n in ("render", "depth", "alpha"))
    write_image(ws / "blender.exr", np.concatenate([rgb, a, z], axis=2),
                channel_names=[f"ViewLayer.Combined.{c}" for c in "RGBA"] + ["ViewLayer.Depth.Z"])
    write_image(ws / "nuke.exr", np.concatenate([rgb, a, z], axis=2), channel_names=["R", "G", "B", "A", "depth.Z"])
    write_image(ws / "rgba.exr", np.concatenate([rgb, a], axis=2), channel_names=["R", "G", "B", "A"])
    write_image(ws / "five.exr", np.concatenate([rgb, a, z], axis=2), channel_names=["R", "G", "B", "A", "Q"])
    write_image(ws / "depth_mm.exr", z * 1000.0)
    write_image(ws / "depth_inv.exr", np.where(np.isfinite(z), 1.0 / z, 0.0).astype(np.float32))
    (ws / "empty.onnx").write_bytes(b"")
    (ws / "truncated.onnx").write_bytes((ws / "lens.onnx").read_bytes()[:2000])
    (ws / "garbage.pt").write_bytes(b"garbage" * 100)
    write_image(ws / "existing.exr", rgb)
    for f in (1001, 1003):
        write_image(ws / f"plate.{f}.exr", read_image(demo / "plate.exr"))


def cases(ws: Path, focus: str) -> list[tuple[str, list[str], list[Path]]]:
    """``(name, argv, files that must stay as they are)``."""
    d, onnx = ws / "demo", str(ws / "lens.onnx")
    comp = ["-m", "neuralbokeh.runtime.composite", "--model", onnx, "--plate", str(d / "plate.exr"), "--focus", focus]
    layers = ["--render", str(d / "render.exr"), "--depth", str(d / "depth.exr"), "--alpha", str(d / "alpha.exr")]
    out = ["--out", str(ws / "out.exr"), "--overwrite"]
    (ws / "report").mkdir(exist_ok=True)
    (ws / "report" / "report.json").write_text("{}\n")
    evaluation = ["-m", "neuralbokeh.evaluation", "--data", str(ws / "data"), "--baselines", "identity"]
    return [
        ("train --resume another run's checkpoint", ["train.py", str(ws / "run_b.toml"), "--resume",
                                                     str(ws / "run_a" / "checkpoint.pt"), "--stop-at", "25"],
         [ws / "run_b" / "checkpoint.pt", ws / "run_b" / "log.csv"]),
        ("composite --out an existing file", comp + layers + ["--out", str(ws / "existing.exr")], [ws / "existing.exr"]),
        ("composite --out its own --plate", comp + layers + ["--out", str(d / "plate.exr"), "--overwrite"], [d / "plate.exr"]),
        ("export.py over an existing ONNX", ["export.py", str(ws / "run_b" / "checkpoint.pt"), "--out", onnx], [ws / "lens.onnx"]),
        ("evaluation --out an existing report", evaluation + ["--models", onnx, "--out", str(ws / "report")],
         [ws / "report" / "report.json"]),
        ("RGBA file as --render and --alpha", comp + ["--render", str(ws / "rgba.exr"), "--alpha", str(ws / "rgba.exr"),
                                                      "--depth", str(d / "depth.exr")] + out, []),
        ("Blender multi-layer EXR", comp + [a for n in ("render", "depth", "alpha") for a in (f"--{n}", str(ws / "blender.exr"))]
         + out, []),
        ("Nuke rgba + depth.Z EXR", comp + [a for n in ("render", "depth", "alpha") for a in (f"--{n}", str(ws / "nuke.exr"))]
         + out, []),
        ("5-channel EXR as --depth", comp + ["--render", str(d / "render.exr"), "--alpha", str(d / "alpha.exr"),
                                            "--depth", str(ws / "five.exr")] + out, []),
        ("depth in mm, read as m", comp + ["--render", str(d / "render.exr"), "--alpha", str(d / "alpha.exr"),
                                          "--depth", str(ws / "depth_mm.exr")] + out, []),
        ("1/z depth (far = 0), no option", comp + ["--render", str(d / "render.exr"), "--alpha", str(d / "alpha.exr"),
                                                  "--depth", str(ws / "depth_inv.exr")] + out, []),
        ("empty ONNX as --model", [*comp[:3], str(ws / "empty.onnx"), *comp[4:]] + layers + out, []),
        ("truncated ONNX as --model", [*comp[:3], str(ws / "truncated.onnx"), *comp[4:]] + layers + out, []),
        ("a .pt as --model", [*comp[:3], str(ws / "run_a" / "checkpoint.pt"), *comp[4:]] + layers + out, []),
        ("evaluation --models truncated ONNX", evaluation + ["--models", str(ws / "truncated.onnx"), "--out",
                                                            str(ws / "report2")], []),
        ("export.py --opset 99", ["export.py", str(ws / "run_a" / "checkpoint.pt"), "--out", str(ws / "o99.onnx"),
                                  "--opset", "99"], []),
        ("export.py on a garbage checkpoint", ["export.py", str(ws / "garbage.pt"), "--out", str(ws / "g.onnx")], []),
        ("data_tools.raw --size 0 0", ["-m", "data_tools.raw", str(ws / "demo"), "--out", str(ws / "raw_out"),
                                       "--size", "0", "0"], []),
        ("#### pattern, --frames 1001-1003x2", comp[:5] + [str(ws / "plate.####.exr")] + comp[6:] + layers
         + ["--frames", "1001-1003x2", "--out", str(ws / "seq" / "comp.####.exr")], []),
        ("--out x.jpg with HDR values", comp + layers + ["--out", str(ws / "x.jpg")], []),
        ("--threads -4", comp + layers + out + ["--threads", "-4"], []),
    ]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repo", type=Path, default=ROOT, help="the checkout whose code is run (default: this one)")
    p.add_argument("--keep", help="make the files in this folder and leave them there")
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        ws = Path(args.keep) if args.keep else Path(tmp)
        paths = setup(args.repo.resolve(), ws)
        layered_files(ws, paths["demo"])
        focus = _demo_focus(ws)
        print(f"code: {args.repo.resolve()}; {'case':<40} {'exit':>4}  {'data':<5}  what the user saw")
        for name, argv, keep in cases(ws, focus):
            before = _digest(keep)
            res = _run(args.repo, argv)
            kept = "-" if not keep else "kept" if _digest(keep) == before else "LOST"
            print(f"{name:<40} {res.returncode:>4}  {kept:<5}  {_seen(res)}", flush=True)


def _demo_focus(ws: Path) -> str:
    sys.path.insert(0, str(ROOT))
    from neuralbokeh.core.io import read_json

    meta = read_json(ws / "data" / "scene_00000" / "scene.json")
    return f"{meta['focus_distances_m'][0]:.6g}"


if __name__ == "__main__":
    main()

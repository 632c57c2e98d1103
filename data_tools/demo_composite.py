"""Make inputs for a compositing demo from a dataset scene: a "photograph" and a CG layer.

    python -m data_tools.demo_composite --scene data/quickstart/scene_00000 --slice 1 --out data/demo

Writes into ``--out``: ``plate.exr`` (the scene's defocused slice: a photograph taken through
the lens), ``render.exr`` (procedural cut-outs and HDR highlights over black, all in focus),
``depth.exr`` (their planar depth in metres, ``inf`` where there is nothing), ``alpha.exr``
(their coverage), ``focus_m.txt`` (the slice's focus distance in metres, for ``--focus``) and prints
the ``neuralbokeh.runtime.composite`` command with it. The CG layer has the plate's size, so a model trained on the dataset applies.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from neuralbokeh.core.cli import HelpFormatter, run_cli
from neuralbokeh.core.io import write_image, write_text
from neuralbokeh.data.dataset import load_scene

from .procedural import SceneParams, composite_sharp, make_layers


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    p.add_argument("--scene", type=Path, required=True, help="a scene folder of a dataset")
    p.add_argument("--slice", type=int, default=0, help="which defocused slice is the plate")
    p.add_argument("--out", type=Path, required=True, help="folder to write plate.exr, render.exr, depth.exr, alpha.exr into")
    p.add_argument("--seed", type=int, default=0, help="seed of the procedural CG layer")
    p.add_argument("-v", "--verbose", action="store_true", help="tracebacks with errors")
    args = p.parse_args(argv)
    try:
        scene = load_scene(args.scene)
    except (FileNotFoundError, ValueError) as e:
        raise SystemExit(f"error: {e}")
    meta = scene["meta"]
    if not 0 <= args.slice < len(meta["slices"]):
        raise SystemExit(f"error: --slice must be in [0, {len(meta['slices']) - 1}] for {args.scene}, got {args.slice}")
    plate = scene["defocus"][args.slice]
    h, w = plate.shape[:2]
    depths = meta["depth_range_m"]
    params = SceneParams(near_m=float(depths[0]), far_m=float(min(depths[1], 50.0)), layers=(2, 3), highlights=(4, 8))
    layers = make_layers(np.random.default_rng(args.seed), h, w, params)[1:]  # drop the background
    render, depth = composite_sharp(layers)
    alpha = 1.0 - np.prod([1.0 - layer.alpha for layer in layers], axis=0)  # coverage of the union
    depth = np.where(alpha > 0, depth, np.inf)
    args.out.mkdir(parents=True, exist_ok=True)
    for name, img in (("plate", plate), ("render", render), ("depth", depth), ("alpha", alpha)):
        write_image(args.out / f"{name}.exr", img.astype(np.float32))
    focus = meta["slices"][args.slice]["focus_m"]
    write_text(args.out / "focus_m.txt", f"{focus:.6g}\n")
    o = args.out
    print(f"wrote {o}/plate.exr, render.exr, depth.exr, alpha.exr, focus_m.txt ({w}x{h}); the plate is focused at {focus:.3f} m")
    print(f"composite: .venv/bin/python -m neuralbokeh.runtime.composite --model MODEL.onnx --plate {o}/plate.exr "
          f"--render {o}/render.exr --depth {o}/depth.exr --alpha {o}/alpha.exr --focus {focus:.3f} --out {o}/comp.exr")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))

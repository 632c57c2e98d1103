"""Export a trained checkpoint to ONNX: ``python export.py CHECKPOINT --out model.onnx``.

The file runs on CPU with onnxruntime alone (``neuralbokeh.runtime``); it carries the lens,
image size, tile layout, normalisation, CoC range and kernel plan as metadata. onnxruntime is
checked against PyTorch on random and extreme inputs before the file is moved into place; the
export fails (and writes nothing) when they differ by more than the tolerance.
"""

from __future__ import annotations

import argparse
import logging
import sys

from neuralbokeh.core.cli import HelpFormatter, run_cli
from neuralbokeh.core.io import prepare_output
from neuralbokeh.core.optics import SensorWindow
from neuralbokeh.export.exporter import export_checkpoint
from neuralbokeh.export.lens_graph import LENS_DEFAULT_KERNELS
from neuralbokeh.export.lowrank import DEFAULT_KERNELS


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    p.add_argument("checkpoint", help="checkpoint written by train.py")
    p.add_argument("--out", required=True, help="ONNX file to write")
    p.add_argument("--opset", type=int, default=None,
                   help="ONNX opset (default and minimum: 18 for the lens network, 17 for the paper network)")
    p.add_argument("--fp16", action="store_true",
                   help="float16 convolutions (paper network: weights and trunk, C2, tanh and head stay float32; "
                        "lens network: the band convolutions)")
    p.add_argument("--kernels", default=None,
                   help=f"lens network: direct | rows (the same convolutions as row GEMMs, faster) | multires:PX (rows; "
                        f"bands convolved on grids 2, 4 or 8 times coarser where their CoC stays >= PX coarse px wide; "
                        f"default {LENS_DEFAULT_KERNELS}). Paper network: direct | lowrank:R | "
                        "auto:EPS (per convolution the smallest separable rank whose effect on the model's output is within "
                        f"EPS / sqrt(#convolutions); default {DEFAULT_KERNELS})")
    p.add_argument("--tolerance", type=float, help="max abs parity error, normalised units (default 1e-4; 3e-4 where the lens "
                                                   "graph samples a field flow or the field gradient; 2e-2 with --fp16)")
    p.add_argument("--threads", type=int, default=None, help="onnxruntime threads for the parity check")
    p.add_argument("--size", type=int, nargs=2, metavar=("W", "H"),
                   help="lens network: the plate format the file renders, in px (default: the trained size)")
    p.add_argument("--sensor-window", type=float, nargs=4, metavar=("LEFT", "TOP", "WIDTH", "HEIGHT"),
                   help="lens network: the plate's part of the sensor, fractions of its width and height (default 0 0 1 1)")
    p.add_argument("--max-coc", type=float, metavar="PX",
                   help="lens network: the largest |CoC| the file renders, px (default: the trained maximum; beyond it the "
                        "learned pupil is scaled)")
    p.add_argument("--tile", type=int, metavar="PX",
                   help="lens network: tile cores of PX px (default: the trained size; larger runs faster, and samples the "
                        "field-dependent pupil once per tile, so more coarsely)")
    p.add_argument("--no-field-flow", action="store_true",
                   help="lens network: leave out model.field_flow (where a cat-eye moves a tile's light, it stays at the "
                        "tile centre's place; faster: 1.16x at 1080p with a cat-eye of 0.6, docs/benchmarks.md)")
    p.add_argument("--no-field-gradient", action="store_true",
                   help="lens network: leave out model.field_gradient (each tile's kernels stay those of its centre; faster: "
                        "1.24x at 1080p with a cat-eye of 0.6, docs/benchmarks.md)")
    p.add_argument("--full-parity", action="store_true",
                   help="lens network: check every tile against PyTorch (default: the corners, edge middles and centre of "
                        "the tile grid; minutes more on a 4K plate)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    p.add_argument("-v", "--verbose", action="store_true", help="info logging, and tracebacks with errors")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        prepare_output(args.out, args.overwrite)  # before minutes of export and parity checks
        if args.size and min(args.size) < 1:
            raise ValueError(f"--size must be W H in px >= 1, got {args.size[0]} {args.size[1]}")
        report = export_checkpoint(args.checkpoint, args.out, args.opset, args.fp16, args.kernels, args.tolerance, args.threads,
                                   size=(args.size[1], args.size[0]) if args.size else None,
                                   window=SensorWindow(*args.sensor_window) if args.sensor_window else None,
                                   max_coc_px=args.max_coc, tile_px=args.tile, full_parity=args.full_parity,
                                   field_flow=False if args.no_field_flow else None,
                                   field_gradient=False if args.no_field_gradient else None, progress=True)
    except (FileNotFoundError, FileExistsError, PermissionError, ValueError) as e:
        raise SystemExit(f"error: {e}")
    meta = report["metadata"]
    ranks = [r for r in meta["kernel_ranks"].values() if r]
    reduced = {k: v["scale"] for k, v in report["kernels"].items() if v.get("scale", 1) > 1}
    contract, (rows, cols, _, _) = meta["contract"], meta["layout"]
    size = contract["image_size"]
    print(f"model      {size['width']}x{size['height']} px, N = {meta['model_config']['blocks']}, {rows * cols} tiles, "
          f"max CoC {contract['max_coc_px']:.2f} px, {'fp16' if meta['fp16'] else 'fp32'}, opset {meta['opset']}")
    print(f"kernels    {meta['kernels']}: {len(ranks)} of {len(meta['kernel_ranks'])} convolutions separable"
          + (f" (ranks {min(ranks)}-{max(ranks)})" if ranks else "")
          + (f"; {len(reduced)} bands on coarser grids (x{min(reduced.values())}-x{max(reduced.values())})" if reduced else ""))
    for case, err in report["parity"].items():
        print(f"parity     {case:<20} max abs {err:.2e} (tolerance {report['tolerance']:g})"
              f"   approximation vs trained {report['approximation'][case]:.2e}")
    checked = len(report["parity_tiles"])
    if checked < rows * cols:
        print(f"parity     {checked} of {rows * cols} tiles convolved in the check (the grid's corners, edge middles and "
              "centre; --full-parity for all)")
    print(f"written    {report['path']}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))

"""Focal stacks -> training triples: ``python -m data_tools.raw STACK_DIR [STACK_DIR ...] --out DIR``.

A stack is a folder of RAW files (anything LibRaw reads) or of developed 8/16-bit TIFF, PNG or
JPEG files (one kind per stack) of one static scene at different focus distances. Per stack:
linear decode (RAW: with one white balance, ``--white-balance``, from the reference slice;
developed files: the transfer function undone, ``--transfer``, sRGB by default, and each
slice's exposure equalised to the reference slice's), one exposure normalisation (the
reference slice's mean luminance -> 0.18),
alignment of every slice to the reference (the middle slice) with a similarity transform,
crop to the common area, optional area-averaged downscale (``--size``), all-in-focus fusion and
depth from focus (or ``--depth FILE``), a CoC map per slice, all written as one scene of the
dataset format (``scene.json`` records the metadata, white balance, exposure factor, alignment
per slice with its residual, and the crop).

Focus distances: ``--focus-distances 0.5,0.7,...`` (m) or ``--focus-diopters 2,1.4,...`` (1/m,
0 = infinity; both in file-name order, for every stack), ``--focus-csv`` (``file,focus_m`` rows)
or the files' EXIF SubjectDistance. Lens: focal length
and f-number from EXIF unless given; the sensor width (of the long side, mm) must be given
(cameras do not record it). A file that cannot be used is named with the reason and dropped;
the rest of its stack (if >= 2 slices remain) and all other stacks are still written, and the
exit status is 1. Finished scenes are skipped on a rerun.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from tqdm import tqdm

from neuralbokeh.core.cli import HelpFormatter, run_cli

from .developed import parse_transfer
from .pipeline import process_stack


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m data_tools.raw", description=__doc__,
                                formatter_class=HelpFormatter)
    p.add_argument("stacks", nargs="+", type=Path, help="folders of RAW or developed (TIFF/PNG/JPEG) files, one static scene each")
    p.add_argument("--out", type=Path, required=True, help="dataset folder to write scenes into")
    p.add_argument("--focus-distances", help="comma-separated focus distances in m, in file-name order")
    p.add_argument("--focus-diopters", help="comma-separated focus positions in 1/m (0 = infinity), in file-name order")
    p.add_argument("--focus-csv", type=Path, help="CSV of file,focus_m")
    p.add_argument("--transfer", default="srgb", help="developed files: srgb | linear | gamma:G (the tone curve to undo)")
    p.add_argument("--focal-length", type=float, help="mm (default: EXIF)")
    p.add_argument("--f-number", type=float, help="default: EXIF")
    p.add_argument("--sensor-width", type=float, help="mm, the sensor's long side (required)")
    p.add_argument("--size", type=int, nargs=2, metavar=("W", "H"), help="area-averaged output size")
    p.add_argument("--depth", type=Path, help="depth map in m at the decoded size (one stack) instead of depth from focus")
    p.add_argument("--white-balance", default="camera", help="camera | daylight | none | R,G,B multipliers")
    p.add_argument("--demosaic", default="AHD", help="LibRaw demosaic algorithm (AHD, DCB, PPG, VNG, LINEAR, ...)")
    p.add_argument("--half-size", action="store_true", help="average 2x2 CFA blocks instead of demosaicing")
    p.add_argument("--rotation", action="store_true", help="also fit a rotation when aligning")
    p.add_argument("--no-align", action="store_true", help="the slices are already registered")
    p.add_argument("--window", type=float, default=2.0, help="focus-measure window sigma in px (default 2)")
    p.add_argument("-v", "--verbose", action="store_true", help="progress logging, and tracebacks with errors")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(message)s")
    if "," in args.white_balance:
        try:
            args.white_balance = tuple(float(v) for v in args.white_balance.split(","))
        except ValueError:
            raise SystemExit(f"error: --white-balance R,G,B must be numbers, got {args.white_balance!r}") from None
    if args.focus_distances and args.focus_diopters:
        raise SystemExit("error: give --focus-distances or --focus-diopters, not both")
    if args.size and min(args.size) < 1:
        raise SystemExit(f"error: --size W H must be at least 1 px each, got {args.size[0]} {args.size[1]}")
    try:
        parse_transfer(args.transfer)
    except ValueError as e:
        raise SystemExit(f"error: --transfer: {e}") from None
    if args.depth and len(args.stacks) != 1:
        raise SystemExit("error: --depth applies to one stack; give one STACK_DIR")
    missing = [str(s) for s in args.stacks if not Path(s).is_dir()]
    if missing:  # a mistyped argument, not a bad file inside a stack: nothing is processed
        raise SystemExit(f"error: no such stack folder: {', '.join(missing)}")
    args.out.mkdir(parents=True, exist_ok=True)
    failures: list[str] = []
    rows = []
    reasons: set[str] = set()  # why whole stacks failed: one reason for all is a mistake in the options
    for stack in tqdm(args.stacks, desc="stacks", unit="stack", disable=len(args.stacks) < 2):
        try:
            row = process_stack(stack, args.out, args, failures)
        except (ValueError, FileNotFoundError, OSError) as e:
            failures.append(f"{stack}: {e}")
            reasons.add(str(e).removeprefix(f"{stack}: "))
            continue
        rows.append(row or {"stack": stack.name, "skipped": True})
    if len(args.stacks) > 1 and not rows and len(reasons) == 1 and len(failures) == len(args.stacks):
        raise SystemExit(f"error: {reasons.pop()} (all {len(failures)} stacks)")  # the options, not the data
    for r in rows:
        if r.get("skipped"):
            print(f"{r['stack']:<24} already written, skipped")
        else:
            print(f"{r['stack']:<24} {r['slices']} slices {r['size'][0]}x{r['size'][1]} px, alignment residual "
                  f"<= {r['residual_px']:.3f} px, max |CoC| {r['max_coc_px']:.2f} px")
    for f in failures:
        print(f"FAILED  {f}")
    written = sum(not r.get("skipped") for r in rows)
    print(f"dataset {args.out}: {written} scene(s) written" + (f"; train with data.roots=['{args.out}']" if rows else ""))
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(run_cli(main))

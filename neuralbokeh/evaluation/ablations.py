"""The paper's design validation (Table 1): five variants, one dataset, one budget.

    python -m neuralbokeh.evaluation.ablations configs/quickstart.toml --data DIR --minutes 10 --out runs/ablations

Trains ``full`` (the default architecture), ``paper`` (the paper's network as written, at its
own learning rate), ``fixed3_kernels`` (3x3 kernels), ``no_tiling``,
``no_overlap`` (tiling without overlap) and ``tile_loss`` (loss per tile) from the same config,
each for the same wall time (``--minutes``; or a fixed ``train.steps=N`` override with
``--minutes 0``), then evaluates every checkpoint on the held-out split with
``neuralbokeh.evaluation.evaluate`` and writes ``table.md`` / ``table.json`` in the form of Table 1 (PSNR,
SSIM and, in place of LPIPS whose weights are not available here, HDR-FLIP; tone-mapped sRGB).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any

from ..core.io import write_json, write_text
from ..data.dataset import FocalStackDataset
from ..training.config import load_config
from ..training.loop import train
from .evaluate import evaluate_methods, model_method

log = logging.getLogger(__name__)

VARIANTS: dict[str, list[str]] = {
    "full": [],
    "paper": ["model.architecture='paper'", "train.lr=1e-3", "train.pupil_tv=0", "train.pupil_chroma=0", "train.pupil_field_spread=0"],
    "fixed3_kernels": ["model.kernel_sizes='fixed3'"],
    "no_tiling": ["model.tiling='none'"],
    "no_overlap": ["model.tiling='no_overlap'"],
    "tile_loss": ["train.loss='tile'"],
}
LABELS = {"full": "Lens network (default)", "paper": "Neural Bokeh as in the paper", "fixed3_kernels": "3x3 kernel size",
          "no_tiling": "No tiling", "no_overlap": "Tiling w/o overlap", "tile_loss": "Loss per tile"}


def run_ablations(config: Path, data: Path, out: Path, minutes: float, overrides: list[str] = (),
                  variants: list[str] | None = None, samples: int = 0, threads: int = 2) -> list[dict[str, Any]]:
    """Train and evaluate each variant; returns one row per variant (also written to ``out``)."""
    names = variants or list(VARIANTS)
    unknown = [n for n in names if n not in VARIANTS]
    if unknown:
        raise ValueError(f"unknown variants {unknown}; expected some of {list(VARIANTS)}")
    rows = []
    budget = ["train.steps=1000000", "train.eval_every=1000000"] if minutes > 0 else []  # the clock decides
    for name in names:
        cfg = load_config(config, [f"data.roots=['{data}']", f"train.out_dir='{out / name}'", *budget, *overrides,
                                   *VARIANTS[name]])
        summary = train(cfg, time_limit_s=60.0 * minutes if minutes > 0 else None, overwrite=True)
        ds = FocalStackDataset(cfg.data.roots, "test", cfg.data.test_fraction, cfg.data.split_seed, normalize=False)
        n = len(ds) if samples <= 0 else min(samples, len(ds))
        result = evaluate_methods({name: model_method(Path(summary["checkpoint"]), threads)}, [ds[i] for i in range(n)], repeats=1)
        m = result["methods"][name]
        rows.append({"variant": name, "label": LABELS[name], "steps": summary["steps"], "seconds": summary["seconds"],
                     "psnr_srgb": m["psnr_srgb"], "ssim_srgb": m["ssim_srgb"], "flip_hdr": m["flip_hdr"],
                     "psnr_linear": m["psnr_linear"], "samples": n})
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "table.json", rows)
    lines = ["| Design | steps | PSNR (sRGB) dB | SSIM (sRGB) | HDR-FLIP |", "|---|---|---|---|---|"]
    lines += [f"| {r['label']} | {r['steps']} | {r['psnr_srgb']:.2f} | {r['ssim_srgb']:.4f} | {r['flip_hdr']:.4f} |" for r in rows]
    write_text(out / "table.md", "\n".join(lines) + "\n")
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m neuralbokeh.evaluation.ablations", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("config", type=Path, help="base config, e.g. configs/quickstart.toml")
    p.add_argument("overrides", nargs="*", help="section.key=value applied to every variant")
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--minutes", type=float, default=10.0, help="wall time per variant (0: use train.steps)")
    p.add_argument("--variants", nargs="+", choices=list(VARIANTS))
    p.add_argument("--samples", type=int, default=0, help="held-out samples to evaluate (0: all)")
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stdout)
    try:
        run_ablations(args.config, args.data, args.out, args.minutes, args.overrides, args.variants, args.samples, args.threads)
    except (FileNotFoundError, ValueError, TypeError) as e:
        raise SystemExit(f"error: {e}")
    log.info("%s", (args.out / "table.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Train a Neural Bokeh model: ``python train.py CONFIG.toml [section.key=value ...] [--resume CKPT]``.

Multi-process: ``torchrun --nproc_per_node=2 train.py CONFIG.toml`` (gloo on CPU, nccl on GPU).
Prints the held-out metrics next to the identity and Gaussian baselines, and the checkpoint path.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys

from neuralbokeh.core.cli import HelpFormatter, run_cli
from neuralbokeh.training import load_config, train


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    p.add_argument("config", help="TOML config (see configs/)")
    p.add_argument("overrides", nargs="*", help="section.key=value, e.g. train.steps=50")
    p.add_argument("--resume", help="checkpoint to continue from (written by this tool with the same config)")
    p.add_argument("--stop-at", type=int, help="stop with a checkpoint after this step (continue with --resume)")
    p.add_argument("--time-limit", type=float,
                   help="stop with a final evaluation and checkpoint after this many minutes")
    p.add_argument("--overwrite", action="store_true", help="start afresh in a train.out_dir that already holds a run")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging, and tracebacks with errors")
    args = p.parse_intermixed_args(argv)  # overrides may follow options
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        cfg = load_config(args.config, args.overrides)
    except (FileNotFoundError, ValueError, TypeError) as e:
        raise SystemExit(f"error: {e}")
    time_limit = None if args.time_limit is None else 60.0 * args.time_limit
    summary = train(cfg, resume=args.resume, stop_at=args.stop_at, time_limit_s=time_limit, overwrite=args.overwrite)
    if int(os.environ.get("RANK", "0")) != 0:
        return 0
    m = summary["metrics"]
    mc = summary["model"]
    what = f"{mc['features']} features" if mc["architecture"] == "paper" else f"learned {mc['pupil_size']}^2 pupils"
    print(f"model        {mc['architecture']}: N = {mc['blocks']} blocks, {what}, "
          f"tiles {mc['tiling']} ({mc['tile']} + {mc['overlap']} px)")
    print(f"trained      {summary['steps']} steps in {summary['seconds']} s on {summary['train_samples']} samples "
          f"({summary['skipped_steps']} skipped as non-finite)")
    if m:
        print(f"held out     {summary['test_samples']} samples    PSNR dB   SSIM")
        print(f"  model                          {m['eval_psnr']:7.2f}  {m['eval_ssim']:.4f}")
        print(f"  identity (AIF unchanged)       {m['identity_psnr']:7.2f}  {m['identity_ssim']:.4f}")
        print(f"  Gaussian blur from the CoC     {m['gaussian_psnr']:7.2f}  {m['gaussian_ssim']:.4f}")
        if "oracle_psnr" not in m:
            print("  (no oracle row: the held-out scenes declare no aperture, as photographs; the lens is what is learned)")
            gap = 0.0
        else:
            print(f"  oracle (scene.json aperture)   {m['oracle_psnr']:7.2f}  {m['oracle_ssim']:.4f}")
            gap = m["oracle_psnr"] - m["gaussian_psnr"]
        if gap > 0:
            print(f"  the model closes {100 * (m['eval_psnr'] - m['gaussian_psnr']) / gap:.0f} % of the gap between the "
                  f"Gaussian and the oracle ({gap:.2f} dB)")
    print(f"checkpoint   {summary['checkpoint']}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))

"""Error against run time of the exported model on CPU: kernel options and in-focus tile skipping.

    python benchmarks/bench_onnx.py --checkpoint runs/onnx_bench/checkpoint.pt --data data/onnx_bench

Without ``--checkpoint`` it makes one: a synthetic dataset (7-blade aperture, cat-eye 0.6,
f/1.4 at 192 px, so the largest CoC is >= 41 px and N >= 20) and ``--minutes`` of training of
the paper's network (the kernel options are its export's; the lens network exports direct
kernels) with the quickstart settings. Then, in one process with a fixed thread count:

1. Kernels: the model is exported with each ``--kernels`` option; for each, held-out PSNR
   (the training metric, on the normalised images) through ``neuralbokeh.runtime`` and the
   median wall time per megapixel of ``--repeats`` renders; ratios against ``direct``.
2. Skipping: the default export run on a held-out image whose CoC is zeroed over about half
   of the tiles, against the same image fully defocused; time ratio, and the check that the
   pixels covered only by tiles that ran are identical to the full evaluation.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from neuralbokeh.checkpoint import load_checkpoint
from neuralbokeh.data.dataset import FocalStackDataset
from neuralbokeh.export.exporter import export_checkpoint
from neuralbokeh.export.lowrank import DEFAULT_KERNELS
from neuralbokeh.runtime.onnx_model import OnnxBokeh

ROOT = Path(__file__).resolve().parents[1]


def _median_ms(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return 1000.0 * statistics.median(times)


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean(((a - b) / 2.0) ** 2))  # images in [-1, 1) -> [0, 1)
    return 10.0 * np.log10(1.0 / mse)


def make_checkpoint(data: Path, out: Path, minutes: float) -> Path:
    subprocess.run([sys.executable, "-m", "data_tools.synth", "--out", str(data), "--scenes", "24", "--size", "192", "192",
                    "--slices", "4", "--aperture", "polygon:7", "--cat-eye", "0.6", "--f-number", "1.4", "--seed", "41",
                    "--workers", "2"], check=True, cwd=ROOT)
    subprocess.run([sys.executable, "train.py", "configs/quickstart.toml", "--overwrite", f"data.roots=['{data}']",
                    "data.test_fraction=0.2",
                    "model.tile=96", "model.overlap=24", "train.steps=100000", "train.lr=1e-3", "model.architecture='paper'",
                    "train.pupil_tv=0", "train.pupil_chroma=0", "train.pupil_field_spread=0",  # no pupils to regularise
                    "train.lr_schedule='constant'",
                    "train.eval_every=100000", "train.checkpoint_every=50", f"train.out_dir='{out}'",
                    "--time-limit", str(minutes)], check=True, cwd=ROOT)
    return out / "checkpoint.pt"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", type=Path)
    p.add_argument("--data", type=Path, default=ROOT / "data" / "onnx_bench")
    p.add_argument("--minutes", type=float, default=12.0, help="training time when no checkpoint is given")
    p.add_argument("--kernels", nargs="+", default=["direct", "lowrank:1", "lowrank:2", "lowrank:4", DEFAULT_KERNELS, "auto:0.01"])
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--samples", type=int, default=8, help="held-out samples for PSNR")
    args = p.parse_args()
    ckpt_path = args.checkpoint or make_checkpoint(args.data, ROOT / "runs" / "onnx_bench", args.minutes)
    ckpt = load_checkpoint(ckpt_path)
    cfg, size = ckpt["model_config"], ckpt["contract"]["image_size"]
    k_max = 2 * cfg["blocks"] + 1
    test = FocalStackDataset(args.data, "test", ckpt["train_config"]["data"]["test_fraction"],
                             ckpt["train_config"]["data"]["split_seed"], normalize=False)
    items = [test[i] for i in range(min(args.samples, len(test)))]
    mp = size["height"] * size["width"] / 1e6
    print(f"model: {size['width']}x{size['height']}, N = {cfg['blocks']} (k_max {k_max}), {cfg['features']} features, "
          f"{ckpt['step']} training steps; {len(items)} held-out samples; {args.threads} threads, median of {args.repeats}")
    rows, models = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        for spec in args.kernels:
            path = Path(tmp) / f"{spec.replace(':', '_')}.onnx"
            rep = export_checkpoint(ckpt_path, path, kernels=spec, threads=args.threads)
            m = OnnxBokeh(path, threads=args.threads, skip_in_focus=False)
            models[spec] = path
            psnrs = []
            for it in items:
                out = m.render_coc(it["aif"].numpy().transpose(1, 2, 0), it["coc"][0].numpy())
                psnrs.append(_psnr(m.contract.normalization.encode(out.astype(np.float64)),
                                   m.contract.normalization.encode(it["defocus"].numpy().transpose(1, 2, 0).astype(np.float64))))
            first = items[0]
            ms = _median_ms(lambda m=m, it=first: m.render_coc(it["aif"].numpy().transpose(1, 2, 0), it["coc"][0].numpy()),
                            args.repeats)
            ranks = [v["rank"] for v in rep["kernels"].values()]
            rows.append((spec, float(np.mean(psnrs)), ms / mp, sum(r > 0 for r in ranks), len(ranks)))
        base_psnr, base_ms = rows[0][1], rows[0][2]
        print(f"\n{'kernels':<14} {'PSNR dB':>8} {'dPSNR':>7} {'ms/MP':>9} {'speed-up':>9} {'separable':>10}")
        for spec, psnr, ms_mp, sep, total in rows:
            print(f"{spec:<14} {psnr:>8.3f} {psnr - base_psnr:>+7.3f} {ms_mp:>9.0f} {base_ms / ms_mp:>8.2f}x {sep:>4}/{total}")

        m_skip = OnnxBokeh(models.get(DEFAULT_KERNELS, models[args.kernels[0]]), threads=args.threads)
        m_full = OnnxBokeh(models.get(DEFAULT_KERNELS, models[args.kernels[0]]), threads=args.threads, skip_in_focus=False)
        it = items[0]
        aif, coc = it["aif"].numpy().transpose(1, 2, 0), it["coc"][0].numpy().astype(np.float64)
        rows_, cols, t, t_o = m_skip.layout
        defocused = np.where(np.abs(coc) < 1.0, np.sign(coc + 1e-9) * 1.0, coc)  # every tile defocused
        half = defocused.copy()
        cut = (cols // 2) * t  # tile columns left of `cut` (and their overlap) in focus
        half[:, : max(cut - t_o, 0)] = 0.0
        half[:, max(cut - t_o, 0) : cut + t_o] = 0.0
        ms_full = _median_ms(lambda: m_skip.render_coc(aif, defocused), args.repeats)
        run_full = m_skip.last_tiles_run
        ms_half = _median_ms(lambda: m_skip.render_coc(aif, half), args.repeats)
        run_half = m_skip.last_tiles_run
        same = np.array_equal(m_skip.render_coc(aif, half)[:, cut + t_o :], m_full.render_coc(aif, half)[:, cut + t_o :])
        print(f"\nskipping: fully defocused {ms_full:.0f} ms ({run_full}/{m_skip.num_tiles} tiles run), "
              f"half in focus {ms_half:.0f} ms ({run_half}/{m_skip.num_tiles} tiles): {ms_full / ms_half:.2f}x faster; "
              f"pixels of tiles that ran identical to the full evaluation: {same}")


if __name__ == "__main__":
    main()

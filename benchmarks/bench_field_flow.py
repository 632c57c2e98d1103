"""What ``model.field_flow`` and ``model.field_gradient`` gain and cost at 1080p, through the runtime.

    python benchmarks/bench_field_flow.py [--cat-eye 0.6] [--repeats 5] [--threads 2]   # ~15 min on 2 cores

The model: ``bench_runtime.py``'s 1080p lens network (7-blade prior, N = 22 bands, 240 px tiles,
24 px overlap), untrained but for a cat-eye of ``--cat-eye`` set on its learned vignette (the
truth's, in the network's field units), so that its pupils vary over the field, exported
(the default ``multires:10`` export) three times: the pupils' change across a tile left out
(``neither``), ``field_flow`` (each pixel's blur moved by its own pupil's centroid) and
``field_gradient`` (each pixel's kernels to first order in its offset from the tile's centre). The frame:
``bench_runtime.py``'s procedural frame (largest |CoC| 40 px); its truth the layered render through
the same cat-eye aperture (``scatter_layers``: each source pixel's own kernel).

Printed per export: ms per frame (median of ``--repeats`` renders after a warm-up, the
exports alternating in one process), the ratio to ``neither``, and the metrics of
``neuralbokeh.evaluation.metrics`` against the truth.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.bench_runtime import H, W, make_frame, make_model  # noqa: E402

VARIANTS = {"neither": {"field_flow": False}, "field_flow": {"field_flow": True},
            "field_gradient": {"field_flow": False, "field_gradient": True}}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cat-eye", type=float, default=0.6)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--out-dir", type=Path, default=ROOT / "runs" / "bench_field_flow")
    args = p.parse_args()
    import torch

    from neuralbokeh.checkpoint import load_checkpoint, save_checkpoint
    from neuralbokeh.evaluation.metrics import image_metrics
    from neuralbokeh.runtime.onnx_model import OnnxBokeh

    torch.set_num_threads(args.threads)
    aif, coc, _, truth = make_frame(args.seed, cat_eye=args.cat_eye)
    half_diag = 0.5 * np.hypot(W - 1, H - 1)
    models = {}
    for name, options in VARIANTS.items():
        tag = f"{name}_"
        prior = make_model(args.out_dir, False, names=(), tag=tag, options=options)["checkpoint"]
        data = load_checkpoint(prior)
        state = dict(data["model_state"])  # the truth's cat-eye, in the network's field units (half-width, half-height)
        state["vignette"] = torch.tensor([args.cat_eye * (W - 1) / 2 / half_diag, args.cat_eye * (H - 1) / 2 / half_diag, 0.0])
        data["model_state"] = state
        save_checkpoint(prior, {k: v for k, v in data.items() if k not in ("format", "format_version", "package_version")})
        path = make_model(args.out_dir, False, names=("default",), checkpoint=prior, tag=tag)["default"]
        models[name] = OnnxBokeh(path, threads=args.threads)
    times: dict[str, list[float]] = {name: [] for name in models}
    outputs = {name: m.render_coc(aif, coc) for name, m in models.items()}  # the warm-up
    for _ in range(args.repeats):
        for name, m in models.items():
            t = time.perf_counter()
            m.render_coc(aif, coc)
            times[name].append(time.perf_counter() - t)
    ms = {name: 1000 * statistics.median(t) for name, t in times.items()}
    print(f"1920x1080, cat-eye {args.cat_eye}, largest |CoC| {np.abs(coc).max():.1f} px, {args.threads} threads, "
          f"median of {args.repeats}")
    print("| variant | ms/frame | ratio | PSNR lin dB | SSIM lin | PSNR sRGB dB | SSIM sRGB | FLIP |")
    print("|---|---|---|---|---|---|---|---|")
    for name in models:
        m = image_metrics(np.maximum(outputs[name].astype(np.float64), 0.0), truth.astype(np.float64))
        print(f"| {name} | {ms[name]:.0f} | {ms[name] / ms['neither']:.3f} | {m['psnr_linear']:.2f} | "
              f"{m['ssim_linear']:.4f} | {m['psnr_srgb']:.2f} | {m['ssim_srgb']:.4f} | {m['flip_hdr']:.4f} |")


if __name__ == "__main__":
    main()

"""Worst error per stability case, PyTorch vs ONNX (fp32 and fp16), for given checkpoints.

    python benchmarks/stability_report.py runs/quickstart/checkpoint.pt [more.pt ...]

Exports each checkpoint (direct kernels) in fp32 and fp16 and prints, per case of
``neuralbokeh.export.exporter.probe_inputs`` (random, all in focus, all at +-max CoC, a one-pixel
depth edge, 1e4 highlights), the max abs difference between onnxruntime and PyTorch in
normalised units, and the largest |output| (must stay < 1: finite after de-normalisation).
The suite in ``tests/test_stability.py`` asserts the same on tiny models.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from neuralbokeh.export.exporter import export_checkpoint, probe_inputs, run_session
from neuralbokeh.runtime.onnx_model import make_session as session


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("checkpoints", nargs="+", type=Path)
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        for ckpt in args.checkpoints:
            rows = {}
            for fp16 in (False, True):
                path = Path(tmp) / f"{ckpt.stem}_{int(fp16)}.onnx"
                rep = export_checkpoint(ckpt, path, fp16=fp16, kernels="direct", threads=args.threads)
                meta = rep["metadata"]
                sess = session(str(path), args.threads)
                size = meta["contract"]["image_size"]
                for name, (aif, coc) in probe_inputs(size["height"], size["width"]).items():
                    out = run_session(sess, aif, coc)
                    rows.setdefault(name, []).extend([rep["parity"][name], float(np.abs(out).max())])
            print(f"\n{ckpt}: {size['width']}x{size['height']}, N = {meta['model_config']['blocks']}, "
                  f"{meta['layout'][0] * meta['layout'][1]} tiles")
            print(f"{'case':<24} {'fp32 max err':>13} {'fp32 max|y|':>12} {'fp16 max err':>13} {'fp16 max|y|':>12}")
            for name, (e32, y32, e16, y16) in rows.items():
                print(f"{name:<24} {e32:>13.2e} {y32:>12.7f} {e16:>13.2e} {y16:>12.7f}")


if __name__ == "__main__":
    main()

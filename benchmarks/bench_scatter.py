"""Time and peak memory of the reference scatter renderer at 512x512, max CoC 21 and 41 px.

    python benchmarks/bench_scatter.py [--size 512] [--repeats 3] [--threads N] [--device cpu|cuda]

Cases (each at each max CoC):
  baseline   one layer blurred with one kernel: a single full-image FFT blur (the floor)
  layers-8   8 fronto-parallel layers, 7-blade aperture (how data_tools.synth renders)
  cateye-8   the same with cat-eye vignetting 0.6 (spatially varying kernels, automatic grid)
  ramp       an AIF with a continuous depth ramp over the whole CoC range (worst case for
             slicing: 4 * max CoC slices of 0.5 px)
Times are medians of ``--repeats`` runs in this process with the same thread count; ratios are
against the baseline of the same CoC measured in the same run. Peak memory is the largest
resident-set growth (CPU, sampled every 2 ms, one cold run in a fresh process so that memory
freed by earlier runs cannot hide it) or torch's peak allocation (CUDA) during a run.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import threading
import time

import numpy as np
import torch

from neuralbokeh.core.apertures import ApertureModel, Polygon
from neuralbokeh.render import scatter_defocus, scatter_layers


def _rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096


class PeakMemory:
    """Peak growth of memory during a ``with`` block (RSS sampling on CPU, torch stats on CUDA)."""

    def __init__(self, device: torch.device):
        self.device = device
        self.peak = 0

    def __enter__(self):
        if self.device.type == "cuda":
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
            self.base = torch.cuda.memory_allocated()
            return self
        self.base = _rss_bytes()
        self.top = self.base
        self.running = True

        def sample():
            while self.running:
                self.top = max(self.top, _rss_bytes())
                time.sleep(0.002)

        self.thread = threading.Thread(target=sample, daemon=True)
        self.thread.start()
        return self

    def __exit__(self, *exc):
        if self.device.type == "cuda":
            torch.cuda.synchronize()
            self.peak = torch.cuda.max_memory_allocated() - self.base
        else:
            self.running = False
            self.thread.join()
            self.peak = max(self.top, _rss_bytes()) - self.base


def _scene(size: int, max_coc: float, device: torch.device, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    aif = torch.rand(3, size, size, generator=g) * 0.8
    aif[:, torch.randint(size, (40,), generator=g), torch.randint(size, (40,), generator=g)] = 500.0
    n = 8
    alphas = torch.zeros(n, 1, size, size)
    alphas[0] = 1.0
    yy, xx = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    for i in range(1, n):
        cy, cx, r = (torch.rand(3, generator=g) * torch.tensor([size, size, size / 3])).tolist()
        alphas[i, 0] = (((yy - cy) ** 2 + (xx - cx) ** 2) <= r * r).float()
    colors = aif[None] * alphas
    cocs = np.linspace(-max_coc, max_coc, n).tolist()
    ramp = torch.linspace(-max_coc, max_coc, size).expand(1, 1, size, size)
    return aif.to(device), colors.to(device), alphas.to(device), cocs, ramp.to(device)


def _cases(size: int, max_coc: float, device: torch.device) -> dict:
    aif, colors, alphas, cocs, ramp = _scene(size, max_coc, device)
    disk, blades = ApertureModel(), ApertureModel(Polygon(7))
    cateye = ApertureModel(Polygon(7), cat_eye=0.6)
    return {
        "baseline": lambda: scatter_layers(colors[:1], alphas[:1], [max_coc], disk),
        "layers-8": lambda: scatter_layers(colors, alphas, cocs, blades),
        "cateye-8": lambda: scatter_layers(colors, alphas, cocs, cateye),
        "ramp": lambda: scatter_defocus(aif[None], ramp, disk),
    }


def _peak_in_fresh_process(args: argparse.Namespace, name: str, max_coc: float) -> float:
    cmd = [sys.executable, __file__, "--memory-case", name, "--size", str(args.size), "--cocs", str(max_coc),
           "--threads", str(args.threads), "--device", args.device]
    return float(subprocess.run(cmd, check=True, capture_output=True, text=True).stdout.split()[-1])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", type=int, default=512)
    p.add_argument("--cocs", type=float, nargs="+", default=[21.0, 41.0])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=torch.get_num_threads())
    p.add_argument("--device", default="cpu")
    p.add_argument("--memory-case", help=argparse.SUPPRESS)  # internal: one cold run, print peak MB
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    if args.memory_case:
        fn = _cases(args.size, args.cocs[0], device)[args.memory_case]
        with PeakMemory(device) as pm:
            fn()
        print(pm.peak / 2**20)
        return
    print(f"scatter renderer, {args.size}x{args.size}, device {device}, {args.threads} thread(s), median of {args.repeats}")
    print(f"{'case':<10} {'max CoC':>7} {'time s':>9} {'x base':>7} {'peak MB':>9} {'x base':>7}")
    for max_coc in args.cocs:
        base_t = base_m = None
        for name, fn in _cases(args.size, max_coc, device).items():
            fn()  # warm-up (kernels, FFT plans)
            times = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                fn()
                if device.type == "cuda":
                    torch.cuda.synchronize()
                times.append(time.perf_counter() - t0)
            t, m = statistics.median(times), _peak_in_fresh_process(args, name, max_coc)
            if name == "baseline":
                base_t, base_m = t, max(m, 1e-3)
            print(f"{name:<10} {max_coc:>7.0f} {t:>9.3f} {t / base_t:>7.1f} {m:>9.1f} {m / base_m:>7.1f}", flush=True)


if __name__ == "__main__":
    main()

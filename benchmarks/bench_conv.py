"""Training-step time of the network with direct vs FFT per-channel convolutions.

    python benchmarks/bench_conv.py [--size 256] [--blocks 10 20] [--repeats 3] [--threads N]

For each N: one optimiser step (forward, full-image MSE, backward, Adam) of the same network
(256x256, 4 tiles of 128 + 32 px, 8 features, batch 2) with every per-channel convolution
direct (``fft_min_kernel_train`` = never) and with the default switch (FFT from 5x5 when
training). Times are medians of ``--repeats`` steps after one warm-up, in this process with the
same threads; the ratio is direct / fast. A second table gives the per-layer crossover: forward
and forward+backward of one depthwise layer by kernel size.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
import torch.nn.functional as F

from neuralbokeh.core.contract import Contract
from neuralbokeh.core.normalization import Normalization
from neuralbokeh.networks.config import ModelConfig
from neuralbokeh.networks.paper import PaperBokeh, PerChannelConv


def _step_time(cfg: ModelConfig, size: int, batch: int, repeats: int) -> float:
    torch.manual_seed(0)
    model = PaperBokeh(cfg, Contract(size, size, Normalization(), 1.0, 1.0))
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    x = torch.rand(batch, 4, size, size) * 1.9 - 0.95
    y = torch.rand(batch, 3, size, size) * 1.9 - 0.95
    times = []
    for i in range(repeats + 1):
        t0 = time.perf_counter()
        opt.zero_grad()
        F.mse_loss(model(x), y).backward()
        opt.step()
        if i:  # the first step is a warm-up
            times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _layer_times(k: int, fft: bool, repeats: int) -> tuple[float, float]:
    threshold = 1 if fft else 10**6
    conv = PerChannelConv(32, k, threshold, threshold)
    x = torch.rand(2, 32, 192, 192, requires_grad=True)
    fwd, both = [], []
    for i in range(repeats + 1):
        t0 = time.perf_counter()
        y = conv(x)
        t1 = time.perf_counter()
        y.sum().backward()
        t2 = time.perf_counter()
        if i:
            fwd.append(t1 - t0)
            both.append(t2 - t0)
    return statistics.median(fwd), statistics.median(both)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--blocks", type=int, nargs="+", default=[10, 20])
    p.add_argument("--batch", type=int, default=2)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=torch.get_num_threads())
    p.add_argument("--kernels", type=int, nargs="*", default=[3, 5, 7, 9, 13, 15, 21, 41])
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    print(f"training step, {args.size}x{args.size}, batch {args.batch}, {args.threads} thread(s), median of {args.repeats}")
    print(f"{'N':>3} {'k max':>6} {'direct s':>9} {'fft s':>8} {'direct/fft':>11}")
    for n in args.blocks:
        common = dict(blocks=n, features=8, tile=args.size // 2, overlap=args.size // 8)
        direct = _step_time(ModelConfig(**common, fft_min_kernel=10**6, fft_min_kernel_train=10**6, architecture="paper"),
                            args.size, args.batch, args.repeats)
        fast = _step_time(ModelConfig(**common, architecture="paper"), args.size, args.batch, args.repeats)
        print(f"{n:>3} {2 * n + 1:>6} {direct:>9.2f} {fast:>8.2f} {direct / fast:>11.1f}", flush=True)
    print("\none depthwise layer, 32 channels, 2 x 192 x 192 (ms)")
    print(f"{'k':>3} {'direct fwd':>11} {'fft fwd':>8} {'direct f+b':>11} {'fft f+b':>8}")
    for k in args.kernels:
        df, db = _layer_times(k, False, args.repeats)
        ff, fb = _layer_times(k, True, args.repeats)
        print(f"{k:>3} {df * 1e3:>11.1f} {ff * 1e3:>8.1f} {db * 1e3:>11.1f} {fb * 1e3:>8.1f}", flush=True)


if __name__ == "__main__":
    main()

"""The Neural Bokeh network (Mandl et al. 2024, sections 3.1-3.2): pure definitions, no I/O.

Input ``(B, 4, H, W)``: normalised all-in-focus RGB in [-1, 1) and the CoC map scaled to
[-1, 1]. Output ``(B, 3, H, W)``: the normalised defocused RGB in (-1, 1).

1. *Tiling.* The image is cut into a grid of ``tile x tile`` cores, each extended by
   ``overlap`` px on every side (windows of ``tile + 2 overlap``). Images whose size is not a
   multiple of ``tile`` are padded at the bottom/right (edge replication) to the next multiple,
   and by ``overlap`` all round; the padding is cropped away at the end. The windows are
   concatenated along channels and every window has its own weights (grouped convolutions,
   one group per tile).
2. ``C1`` (1x1, 4 -> ``features``) -> residual blocks ``R_1 .. R_N``; block n is
   ``x + conv_b(relu(conv_a(x)))`` with per-channel convolutions of size ``2n + 1``
   (``kernel_sizes = "fixed3"``: all 3x3, the paper's ablation) -> concatenation with the window's
   RGB -> ``C2`` (1x1, ``features + 3`` -> 3) -> tanh.
3. Windows are put back in place and overlaps averaged (exactly: see :func:`untile`).

Head (``head``): the paper applies tanh to C2's output. ``"identity"`` (default) predicts in
atanh space instead: ``tanh(atanh(rgb) + d)`` with ``d = C2(...)`` initialised to zero, so the
untrained network returns its input and in-focus pixels cost nothing to learn. With the
package's normalisation ``atanh(n) = ln((x + o) / s) / 2``: ``d`` is a correction in log
exposure. It is evaluated as ``(rgb + tanh d) / (1 + rgb tanh d)`` (the tanh addition
formula), which returns the input bit for bit when ``d = 0`` and never evaluates atanh(+-1);
``tanh d`` is scaled by ``1 - 1e-6`` so the denominator cannot vanish (a clamp would zero
the gradient of saturated pixels for good: measured as a training run that never recovered). ``"paper"`` is the plain
tanh with default initialisation, kept as an ablation.

Per-channel convolutions run through the FFT (exact: same results and gradients as direct
convolution to float rounding) from ``fft_min_kernel`` up when no gradient is needed and from
``fft_min_kernel_train`` up when one is: on a 2-core CPU PyTorch's direct depthwise forward
is fast to 13x13 and collapses at 15x15, while its backward is slower than the FFT from 5x5
(``benchmarks/bench_conv.py``).

The second convolution of every residual block starts at zero (a "zero-init residual"), so the
untrained blocks pass C1's features through unchanged.
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from ..core import checks
from ..core.contract import Contract
from ..ops.fftconv import fft_convolve2d
from ..ops.tiles import tile, untile
from .config import TANH_LIMIT, ModelConfig


class PerChannelConv(nn.Module):
    """Depthwise (per-channel) ``k x k`` convolution with zero 'same' padding and bias.

    Direct convolution below the threshold, FFT convolution from it up (``fft_min_kernel``
    without gradients, ``fft_min_kernel_train`` with): the same function and gradients to
    float rounding.
    """

    def __init__(self, channels: int, kernel_size: int, fft_min_kernel: int = 15, fft_min_kernel_train: int = 5) -> None:
        super().__init__()
        if kernel_size % 2 == 0:
            raise ValueError(f"kernel_size must be odd, got {kernel_size}")
        self.conv = nn.Conv2d(channels, channels, kernel_size, padding=kernel_size // 2, groups=channels)
        self.kernel_size = kernel_size
        self.fft_min_kernel, self.fft_min_kernel_train = fft_min_kernel, fft_min_kernel_train

    def use_fft(self) -> bool:
        grad = torch.is_grad_enabled() and self.conv.weight.requires_grad
        return self.kernel_size >= (self.fft_min_kernel_train if grad else self.fft_min_kernel)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.use_fft():
            return self.conv(x)
        # F.conv2d correlates; the FFT helper convolves: flip the kernel.
        k = self.conv.weight.flip(-1, -2).transpose(0, 1)  # (1, C, k, k)
        return fft_convolve2d(x, k) + self.conv.bias[None, :, None, None]


class ResidualBlock(nn.Module):
    """``x + conv_b(relu(conv_a(x)))`` with per-channel convolutions of one size."""

    def __init__(self, channels: int, kernel_size: int, fft_min_kernel: int = 15, fft_min_kernel_train: int = 5) -> None:
        super().__init__()
        self.conv_a = PerChannelConv(channels, kernel_size, fft_min_kernel, fft_min_kernel_train)
        self.conv_b = PerChannelConv(channels, kernel_size, fft_min_kernel, fft_min_kernel_train)
        nn.init.zeros_(self.conv_b.conv.weight)  # zero-init residual: the block starts as identity
        nn.init.zeros_(self.conv_b.conv.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv_b(F.relu(self.conv_a(x)))


class PaperBokeh(nn.Module):
    """The tiled per-channel residual network. See the module doc for the architecture."""

    def __init__(self, config: ModelConfig, contract: Contract) -> None:
        super().__init__()
        config.check_resolved()
        self.config, self.contract = config, contract
        self.layout = config.layout(*contract.size)
        n, f = self.layout.num_tiles, config.features
        self.c1 = nn.Conv2d(4 * n, f * n, 1, groups=n)
        self.blocks = nn.ModuleList(
            ResidualBlock(f * n, config.kernel_size(i), config.fft_min_kernel, config.fft_min_kernel_train)
            for i in range(1, config.blocks + 1)
        )
        self.c2 = nn.Conv2d((f + 3) * n, 3 * n, 1, groups=n)
        if config.head == "identity":
            nn.init.zeros_(self.c2.weight)
            nn.init.zeros_(self.c2.bias)

    def parameter_roles(self) -> dict[str, list[nn.Parameter]]:
        """The parameters by how training scales their learning rate: ``"kernel"`` (the
        per-channel k x k kernels, whose fan-in is k^2) and ``"other"``."""
        kernels = [getattr(block, part).conv.weight for block in self.blocks for part in ("conv_a", "conv_b")]
        ids = {id(p) for p in kernels}
        return {"kernel": kernels, "other": [p for p in self.parameters() if id(p) not in ids]}

    def forward_tiles(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, 4, H, W)`` -> per-tile outputs ``(B, tiles * 3, win, win)`` before reassembly."""
        cfg = self.config
        self.contract.check_network_input(x)
        if checks.DEBUG:
            checks.check_finite("model input", x)
        n, f = self.layout.num_tiles, cfg.features
        xt = tile(x, self.layout)  # (B, n*4, win, win)
        b, _, win, _ = xt.shape
        h = self.c1(xt)
        for block in self.blocks:
            h = block(h)
        rgb = xt.view(b, n, 4, win, win)[:, :, :3]
        z = torch.cat([h.view(b, n, f, win, win), rgb], dim=2).view(b, n * (f + 3), win, win)
        out = torch.tanh(self.c2(z))
        if cfg.head == "identity":
            t = out * TANH_LIMIT  # strictly inside (-1, 1); unlike a clamp it never zeroes the gradient
            r = rgb.reshape(b, n * 3, win, win)
            out = (r + t) / (1.0 + r * t)  # = tanh(atanh(r) + d)
        return out

    def forward(self, x: torch.Tensor, window: torch.Tensor | None = None, return_tiles: bool = False) -> torch.Tensor:
        """``(B, 4, H, W)`` -> ``(B, 3, H, W)`` normalised defocused RGB (or the un-blended
        tiles ``(B, tiles * 3, win, win)`` with ``return_tiles``, for the per-tile loss).
        ``window`` (the images' place on the sensor) is accepted and ignored: the paper's network
        renders its trained frame only and knows nothing of the sensor."""
        tiles = self.forward_tiles(x)
        return tiles if return_tiles else untile(tiles, self.layout, *self.contract.size)

    def tile_targets(self, y: torch.Tensor) -> torch.Tensor:
        """Cut a target ``(B, 3, H, W)`` into the same windows (for the per-tile-loss ablation)."""
        return tile(y, self.layout)

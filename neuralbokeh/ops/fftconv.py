"""Exact linear 2-D convolution through the FFT, per channel, differentiable.

Direct per-channel convolution costs O(k^2) per pixel; through the FFT it costs O(log n)
whatever the kernel size, which is what large circles of confusion need.
"""

from __future__ import annotations

import torch

from ..core.checks import check_shape


def next_fast_len(n: int) -> int:
    """Smallest integer >= n whose prime factors are 2, 3, 5 and 7 (fast FFT sizes)."""
    m = max(1, n)
    while True:
        r = m
        for p in (2, 3, 5, 7):
            while r % p == 0:
                r //= p
        if r == 1:
            return m
        m += 1


def fft_convolve2d(
    x: torch.Tensor, kernel: torch.Tensor, compute_dtype: torch.dtype | None = None, mode: str = "same"
) -> torch.Tensor:
    """Per-channel linear *convolution* of ``x`` with ``kernel``.

    Zero padding outside ``x`` (callers pad first for other borders). This is a true
    convolution (the kernel is the point-spread function: a pixel scatters the kernel around
    itself), i.e. ``F.conv2d`` with the kernel point-reflected. The kernel's centre is at
    ``(kh // 2, kw // 2)``; kernel sizes must be odd.

    Args:
        x: ``(N, C, H, W)`` input.
        kernel: ``(N, C, kh, kw)`` or ``(1, C, kh, kw)`` per-channel kernels (broadcast on N).
        compute_dtype: dtype of the FFT (default: ``x``'s; float64 gives ~1e-15 relative error).
        mode: ``"same"`` (output ``(H, W)``, aligned with ``x``) or ``"full"`` (output
            ``(H + kh - 1, W + kw - 1)``, everything the input scatters; ``x[0, 0]``'s centre
            lands at ``(kh // 2, kw // 2)``).

    Returns:
        ``(N, C, H, W)`` (or the full size) in ``x``'s dtype.

    Raises:
        ValueError: shapes do not match or the kernel size is even.
    """
    dims = check_shape("x", x, "N C H W")
    kd = check_shape("kernel", kernel, "M C kh kw", C=dims["C"])
    if kd["M"] not in (1, dims["N"]):
        raise ValueError(f"kernel batch must be 1 or {dims['N']}, got {kd['M']}")
    kh, kw = kd["kh"], kd["kw"]
    if kh % 2 == 0 or kw % 2 == 0:
        raise ValueError(f"kernel size must be odd, got {kh}x{kw}")
    if mode not in ("same", "full"):
        raise ValueError(f"mode must be 'same' or 'full', got {mode!r}")
    h, w = dims["H"], dims["W"]
    dtype = compute_dtype or x.dtype
    fh, fw = h + kh - 1, w + kw - 1
    sh, sw = next_fast_len(fh), next_fast_len(fw)  # circular size >= linear size: exact
    fx = torch.fft.rfft2(x.to(dtype), s=(sh, sw))
    fk = torch.fft.rfft2(kernel.to(device=x.device, dtype=dtype), s=(sh, sw))
    full = torch.fft.irfft2(fx * fk, s=(sh, sw))
    if mode == "full":
        return full[..., :fh, :fw].to(x.dtype)
    ph, pw = kh // 2, kw // 2
    return full[..., ph : ph + h, pw : pw + w].to(x.dtype)

"""Low-rank separable factorisation of per-channel kernels (numpy only).

A ``k x k`` kernel ``K`` is approximated by the first ``R`` terms of its SVD,
``K ~= sum_r s_r u_r v_r^T``: R pairs of a ``k x 1`` and a ``1 x k`` convolution, ``2 k R``
multiply-adds per pixel instead of ``k^2``. onnxruntime runs plain depthwise convolutions of
any shape on its fast path, so the pairs are laid out as R branches of two depthwise
convolutions each, summed (see ``graph.py``).

Kernel choice (``--kernels``):

* ``direct``: every kernel as trained.
* ``lowrank:R``: rank R for every kernel where that is cheaper than direct (``2 R < k``).
* ``auto:EPS`` (default ``auto:0.004``): per convolution the smallest rank R with ``2 R < k``
  whose effect on the *network's output* stays within an error budget: factorising that one
  convolution changes the output on calibration images by at most ``EPS / sqrt(#convs)`` RMS
  (normalised units, outputs in (-1, 1)), so the errors of all convolutions add up to about
  ``EPS``. A kernel's own SVD error says little about this (a block whose second convolution
  is small barely feels an error in its first), hence the end-to-end criterion; it is
  evaluated in ``exporter.plan_factors``. Convolutions that need ``2 R >= k`` stay direct.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DEFAULT_KERNELS = "auto:0.004"


@dataclass(frozen=True)
class KernelPlan:
    """Parsed ``--kernels`` option: ``mode`` in ``direct|lowrank|auto`` with its parameter."""

    mode: str
    rank: int = 0
    tolerance: float = 0.0

    def __str__(self) -> str:
        return {"direct": "direct", "lowrank": f"lowrank:{self.rank}", "auto": f"auto:{self.tolerance:g}"}[self.mode]


def parse_kernels(spec: str) -> KernelPlan:
    """``"direct"``, ``"lowrank:R"`` (R >= 1) or ``"auto:EPS"`` (0 <= EPS < 1) -> :class:`KernelPlan`.

    Raises:
        ValueError: anything else, with the accepted forms.
    """
    forms = "expected 'direct', 'lowrank:R' (integer R >= 1) or 'auto:EPS' (0 <= EPS < 1)"
    if spec == "direct":
        return KernelPlan("direct")
    mode, _, arg = spec.partition(":")
    try:
        if mode == "lowrank":
            rank = int(arg)
            if rank >= 1:
                return KernelPlan("lowrank", rank=rank)
        elif mode == "auto":
            eps = float(arg)
            if 0.0 <= eps < 1.0:
                return KernelPlan("auto", tolerance=eps)
    except ValueError:
        pass
    raise ValueError(f"kernels must be {forms}, got {spec!r}")


def factorize(kernels: np.ndarray, rank: int) -> tuple[np.ndarray, np.ndarray]:
    """Rank-``rank`` separable factors of per-channel kernels.

    Args:
        kernels: ``(C, k, k)`` float array.
        rank: number of separable terms, 1 <= rank <= k.

    Returns:
        ``(cols, rows)``, each ``(C, rank, k)`` float64, with
        ``kernels[c] ~= sum_r outer(cols[c, r], rows[c, r])`` (the singular values are split
        evenly between the two factors, keeping both at the kernel's scale).
    """
    if kernels.ndim != 3 or kernels.shape[1] != kernels.shape[2]:
        raise ValueError(f"kernels must have shape (C, k, k), got {kernels.shape}")
    k = kernels.shape[1]
    if not 1 <= rank <= k:
        raise ValueError(f"rank must be in [1, {k}] for {k}x{k} kernels, got {rank}")
    u, s, vt = np.linalg.svd(kernels.astype(np.float64))
    root = np.sqrt(s[:, :rank])
    cols = np.transpose(u[:, :, :rank], (0, 2, 1)) * root[:, :, None]
    rows = vt[:, :rank, :] * root[:, :, None]
    return cols, rows


def reconstruct(cols: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``(C, R, k)`` factors -> the ``(C, k, k)`` kernels they represent."""
    return np.einsum("cri,crj->cij", cols, rows)


def relative_error(kernels: np.ndarray, rank: int) -> np.ndarray:
    """Per-channel ``||K - K_rank||_F / ||K||_F`` (0 for an all-zero kernel), shape ``(C,)``."""
    s = np.linalg.svd(kernels.astype(np.float64), compute_uv=False)
    total = np.sqrt((s**2).sum(axis=1))
    rest = np.sqrt((s[:, rank:] ** 2).sum(axis=1))
    return np.divide(rest, total, out=np.zeros_like(total), where=total > 0)


def cheaper_ranks(k: int) -> range:
    """Ranks R whose separable form (2 k R multiply-adds) is cheaper than a direct k x k kernel."""
    return range(1, (k + 1) // 2)

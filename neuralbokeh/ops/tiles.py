"""Overlapping tiles: cutting an image into windows concatenated along channels and back.

Shared by both networks (:mod:`neuralbokeh.networks.paper`, :mod:`neuralbokeh.networks.lens`). A layout is
``(rows, cols, core, overlap)``: cores of ``core`` px on a grid, each window extended by
``overlap`` px on every side.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def tile(x: torch.Tensor, layout: tuple[int, int, int, int]) -> torch.Tensor:
    """Cut ``(B, C, H, W)`` into overlapping windows, concatenated along channels.

    Returns ``(B, rows * cols * C, t + 2 t_o, t + 2 t_o)``, tile-major (tile k owns channels
    ``k*C .. k*C + C - 1``). Padding: edge replication to ``rows * t x cols * t``, then
    ``t_o`` all round.
    """
    rows, cols, t, t_o = layout
    b, c, h, w = x.shape
    pad = (t_o, t_o + cols * t - w, t_o, t_o + rows * t - h)
    if any(pad):
        x = F.pad(x, pad, mode="replicate")
    win = t + 2 * t_o
    tiles = [x[:, :, i * t : i * t + win, j * t : j * t + win] for i in range(rows) for j in range(cols)]
    return torch.cat(tiles, dim=1)


def untile(y: torch.Tensor, layout: tuple[int, int, int, int], height: int, width: int) -> torch.Tensor:
    """Put windows back and average the overlaps; the inverse of :func:`tile` on its output.

    ``y`` is ``(B, rows * cols * C, win, win)``; returns ``(B, C, height, width)``. With
    ``2 t_o <= t`` windows of tiles two apart never overlap, so the four parity classes of the
    grid are placed without summing and combined as ``((P00 + P01) + (P10 + P11)) / count``:
    untouched tiles reassemble to the input bit for bit.
    """
    rows, cols, t, t_o = layout
    b, n_c, win, _ = y.shape
    c = n_c // (rows * cols)
    hp, wp = rows * t + 2 * t_o, cols * t + 2 * t_o
    canvases = [[y.new_zeros(b, c, hp, wp) for _ in range(2)] for _ in range(2)]
    counts = [[torch.zeros(1, 1, hp, wp, dtype=y.dtype, device=y.device) for _ in range(2)] for _ in range(2)]
    for i in range(rows):
        for j in range(cols):
            k = i * cols + j
            sl = (slice(None), slice(None), slice(i * t, i * t + win), slice(j * t, j * t + win))
            canvases[i % 2][j % 2][sl] = y[:, k * c : (k + 1) * c]
            counts[i % 2][j % 2][sl] = 1.0
    total = (canvases[0][0] + canvases[0][1]) + (canvases[1][0] + canvases[1][1])
    count = (counts[0][0] + counts[0][1]) + (counts[1][0] + counts[1][1])
    return (total / count)[:, :, t_o : t_o + height, t_o : t_o + width]

"""Overlapping tiles of torch images: cutting into windows concatenated along channels and back.

The grid is :class:`neuralbokeh.core.tiling.TileLayout` (shared with the ONNX graph builders and
the runtime); both networks cut their input with :func:`tile`.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..core.tiling import TileLayout


def clip_peaks(line: torch.Tensor) -> torch.Tensor:
    """``(B, C, n)``: each value at most the larger of its two neighbours along the last dim (an
    end's one neighbour counts twice; ``n = 1`` is kept): a 1 px peak drops to its neighbours'."""
    if line.shape[-1] < 2:
        return line
    padded = F.pad(line, (1, 1), mode="reflect")
    return torch.minimum(line, torch.maximum(padded[..., :-2], padded[..., 2:]))


def edge_ring(x: torch.Tensor, light: int = 0) -> torch.Tensor:
    """``(B, C, H, W)`` -> ``(B, C, H + 2, W + 2)``: the frame with a 1 px ring of its edge pixels
    around it, what the tiles' padding repeats. In the first ``light`` channels (colour, in any
    encoding that keeps order) each ring pixel is its edge pixel clipped to the larger of its two
    neighbours along the edge (:func:`clip_peaks`; a corner of the ring repeats the end of its
    row's): beyond the frame an extended surface goes on, a point source cut by the frame's edge
    does not, and repeating it would lay a streak of light as wide as the padding."""
    ring = F.pad(x, (1, 1, 1, 1), mode="replicate")  # a fresh tensor: written in place, under autograd too
    if light:
        ring[:, :light, 0] = F.pad(clip_peaks(x[:, :light, 0]), (1, 1), mode="replicate")
        ring[:, :light, -1] = F.pad(clip_peaks(x[:, :light, -1]), (1, 1), mode="replicate")
        ring[:, :light, 1:-1, 0] = clip_peaks(x[:, :light, :, 0])
        ring[:, :light, 1:-1, -1] = clip_peaks(x[:, :light, :, -1])
    return ring


def tile(x: torch.Tensor, layout: TileLayout, light: int = 0) -> torch.Tensor:
    """Cut ``(B, C, H, W)`` into overlapping windows, concatenated along channels.

    Returns ``(B, tiles * C, window, window)``, tile-major (tile k owns channels ``k*C .. k*C +
    C - 1``), padded as :meth:`TileLayout.pads` says by repeating the edge pixels; the first
    ``light`` channels repeat the ring of :func:`edge_ring` (a 1 px peak on the edge is not repeated).
    """
    h, w = x.shape[-2:]
    top, bottom, left, right = layout.pads(h, w)
    if light and (top or bottom or left or right):
        rows, cols = (torch.from_numpy(i).to(x.device) for i in layout.ring_indices(h, w))
        x = edge_ring(x, light).index_select(-2, rows).index_select(-1, cols)
    elif top or bottom or left or right:
        x = F.pad(x, (left, right, top, bottom), mode="replicate")
    win = layout.window
    # one unfold (its backward is one fold) instead of a slice per tile, whose backward would
    # each write a zero canvas of the whole input
    cols = F.unfold(x, win, stride=layout.core)  # (B, C win win, tiles), tiles row-major as origins()
    b, c = x.shape[:2]
    return cols.view(b, c, win, win, -1).permute(0, 4, 1, 2, 3).reshape(b, -1, win, win)


def overlap_add(windows: torch.Tensor, layout: TileLayout) -> torch.Tensor:
    """Sum windows ``(B, tiles, C, window, window)`` into place on the padded canvas
    ``(B, C, H_p, W_p)`` (:meth:`TileLayout.padded_size`): the adjoint of :func:`tile`'s cut."""
    b, n_t, c, win, _ = windows.shape
    return F.fold(windows.reshape(b, n_t, c * win * win).transpose(1, 2), layout.padded_size, win, stride=layout.core)


def untile(y: torch.Tensor, layout: TileLayout, height: int, width: int) -> torch.Tensor:
    """Put windows back and average the overlaps; the inverse of :func:`tile` on its output.

    ``y`` is ``(B, tiles * C, window, window)``; returns ``(B, C, height, width)``. With
    ``2 overlap <= core`` windows of tiles two apart never overlap, so the four parity classes of
    the grid are placed without summing and combined as ``((P00 + P01) + (P10 + P11)) / count``:
    untouched tiles reassemble to the input bit for bit.
    """
    b, n_c, win, _ = y.shape
    c = n_c // layout.num_tiles
    hp, wp = layout.padded_size
    canvases = [[y.new_zeros(b, c, hp, wp) for _ in range(2)] for _ in range(2)]
    counts = [[torch.zeros(1, 1, hp, wp, dtype=y.dtype, device=y.device) for _ in range(2)] for _ in range(2)]
    for k, r, col in layout.origins():
        i, j = divmod(k, layout.cols)
        sl = (slice(None), slice(None), slice(r, r + win), slice(col, col + win))
        canvases[i % 2][j % 2][sl] = y[:, k * c : (k + 1) * c]
        counts[i % 2][j % 2][sl] = 1.0
    total = (canvases[0][0] + canvases[0][1]) + (canvases[1][0] + canvases[1][1])
    count = (counts[0][0] + counts[0][1]) + (counts[1][0] + counts[1][1])
    t_o = layout.overlap
    return (total / count)[:, :, t_o : t_o + height, t_o : t_o + width]

"""The tile grid of both networks, torch-free: the one definition of where tiles and windows lie.

Used by the networks (``neuralbokeh.ops.tiles`` cuts tensors with it), the ONNX graph builders
(which slice and place the same windows) and the runtime (which decides from a frame's CoC map
which tiles and bands to run). An image of ``H x W`` px is padded at the bottom/right by edge
replication to ``rows * core x cols * core``, then by ``overlap`` px all round; tile ``k = i *
cols + j`` owns the core ``[i core, (i + 1) core) x [j core, (j + 1) core)`` of the image and
sees the window of ``core + 2 overlap`` px around it. The lens network's light repeats its edge
pixels through :meth:`TileLayout.ring_indices` (``neuralbokeh.ops.tiles.edge_ring``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np


class TileLayout(NamedTuple):
    """``rows x cols`` tiles with cores of ``core`` px, windows extended by ``overlap`` px on
    every side (px; ``0 <= 2 overlap <= core``)."""

    rows: int
    cols: int
    core: int
    overlap: int

    @classmethod
    def for_image(cls, height: int, width: int, tile: int, overlap: int, tiling: str = "overlap") -> TileLayout:
        """The grid covering ``height x width`` px: ``tiling`` ``"overlap"`` (cores of ``tile`` px
        with ``overlap`` px of context), ``"no_overlap"`` (context 0) or ``"none"`` (one tile)."""
        if tiling == "none":
            return cls(1, 1, max(height, width), 0)
        return cls(math.ceil(height / tile), math.ceil(width / tile), tile, 0 if tiling == "no_overlap" else overlap)

    @property
    def num_tiles(self) -> int:
        return self.rows * self.cols

    @property
    def window(self) -> int:
        """Side of a tile's window (px)."""
        return self.core + 2 * self.overlap

    @property
    def padded_size(self) -> tuple[int, int]:
        """``(H, W)`` of the padded canvas the windows are cut from and placed back on."""
        return self.rows * self.core + 2 * self.overlap, self.cols * self.core + 2 * self.overlap

    def pads(self, height: int, width: int) -> tuple[int, int, int, int]:
        """``(top, bottom, left, right)`` edge padding of an ``height x width`` image to the canvas."""
        hp, wp = self.padded_size
        return self.overlap, hp - self.overlap - height, self.overlap, wp - self.overlap - width

    def ring_indices(self, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
        """``(H_p,)`` and ``(W_p,)`` int64: the row and column of the frame with a 1 px ring around it
        (``(H + 2) x (W + 2)``, :func:`neuralbokeh.ops.tiles.edge_ring`) that each canvas row and
        column shows: the frame inside, the ring's row or column beyond each edge."""
        top, bottom, left, right = self.pads(height, width)
        return (np.clip(np.arange(-top, height + bottom), -1, height) + 1,
                np.clip(np.arange(-left, width + right), -1, width) + 1)

    def origins(self) -> list[tuple[int, int, int]]:
        """``(k, row, col)``: each tile's window's top-left corner on the padded canvas."""
        return [(i * self.cols + j, i * self.core, j * self.core) for i in range(self.rows) for j in range(self.cols)]

    def pad_image(self, image: np.ndarray, height: int, width: int) -> np.ndarray:
        """``(..., H, W)`` numpy -> the padded canvas ``(..., H_p, W_p)`` (edge replication)."""
        top, bottom, left, right = self.pads(height, width)
        return np.pad(image, [(0, 0)] * (image.ndim - 2) + [(top, bottom), (left, right)], mode="edge")

    def source_region(self, k: int, height: int, width: int) -> tuple[int, int, int, int]:
        """``(r0, r1, c0, c1)``: the image pixels tile ``k`` scatters (its core; a border tile's
        core reaches the image edge, its padding repeating pixels of its own core)."""
        i, j = divmod(k, self.cols)
        r1 = min((i + 1) * self.core, height) if i < self.rows - 1 else height
        c1 = min((j + 1) * self.core, width) if j < self.cols - 1 else width
        return i * self.core, r1, j * self.core, c1

    def source_tile(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """The tile that scatters each image pixel ``(rows, cols)`` (int arrays): the one whose
        :meth:`source_region` holds it (the regions partition the image)."""
        return np.minimum(rows // self.core, self.rows - 1) * self.cols + np.minimum(cols // self.core, self.cols - 1)

    def source_masks(self) -> np.ndarray:
        """``(tiles, window, window)`` float32: 1 on the window pixels a tile scatters (its core,
        out to the window's edge on the image-border sides), so that every pixel of the padded
        canvas is scattered by exactly one tile."""
        win, t_o, t = self.window, self.overlap, self.core
        masks = np.zeros((self.num_tiles, win, win), np.float32)
        for k, _, _ in self.origins():
            i, j = divmod(k, self.cols)
            r0, r1 = (0 if i == 0 else t_o), (win if i == self.rows - 1 else t_o + t)
            c0, c1 = (0 if j == 0 else t_o), (win if j == self.cols - 1 else t_o + t)
            masks[k, r0:r1, c0:c1] = 1.0
        return masks


def pyramid_levels(height: int, width: int) -> int:
    """Levels ``L`` of the pull-push pyramid: the image fits a ``2^L`` square."""
    return max(0, math.ceil(math.log2(max(height, width))))

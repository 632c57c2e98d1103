"""The networks (torch, pure definitions: no files, no datasets, no training).

``lens.py`` is the default architecture (the paper's tiled skeleton carrying a learned lens),
``paper.py`` the Neural Bokeh network as the paper writes it (the ``architecture = "paper"``
ablation); ``config.py`` (torch-free) is the configuration both are rebuilt from.
"""

from __future__ import annotations

from typing import Protocol

import torch
import torch.nn as nn

from ..core.contract import Contract
from .config import ModelConfig
from .lens import LensBokeh
from .paper import PaperBokeh


class BokehNetwork(Protocol):
    """What training, evaluation and export rely on, and both networks provide."""

    config: ModelConfig
    contract: Contract

    def __call__(self, x: torch.Tensor, window: torch.Tensor | None = None, return_tiles: bool = False) -> torch.Tensor:
        """Normalised ``(B, 4, H, W)`` (RGB, CoC / ``contract.coc_scale_px``) with each image's
        place on the sensor ``window`` ``(B, 4)`` -> normalised RGB ``(B, 3, H, W)``; with
        ``return_tiles``, each tile's window on its own ``(B, tiles * 3, win, win)`` (the
        per-tile loss of the ablation)."""

    def tile_targets(self, y: torch.Tensor) -> torch.Tensor:
        """A target ``(B, C, H, W)`` cut into the windows ``return_tiles`` gives."""

    def parameter_roles(self) -> dict[str, list[nn.Parameter]]:
        """The parameters by how training scales their learning rate (``"kernel"``: per-channel
        k x k kernels, learnt at lr / k^2; ``"field"``: field-dependent corrections; ``"other"``)."""


def build_model(config: ModelConfig, contract: Contract) -> nn.Module:
    """The network a config describes, for the data a contract describes: :class:`LensBokeh` or
    :class:`PaperBokeh` (``config.blocks`` resolved: :meth:`ModelConfig.resolved`)."""
    return (LensBokeh if config.architecture == "lens" else PaperBokeh)(config, contract)


__all__ = ["BokehNetwork", "LensBokeh", "ModelConfig", "PaperBokeh", "build_model"]

"""The networks (torch, pure definitions: no files, no datasets, no training).

``lens.py`` is the default architecture (the paper's tiled skeleton carrying a learned lens),
``paper.py`` the Neural Bokeh network as the paper writes it (the ``architecture = "paper"``
ablation); ``config.py`` (torch-free) is the configuration both are rebuilt from.
"""

from __future__ import annotations

import torch.nn as nn

from .config import ModelConfig
from .lens import LensBokeh
from .paper import NeuralBokeh


def build_model(config: ModelConfig) -> nn.Module:
    """The network a config describes: :class:`LensBokeh` or :class:`NeuralBokeh`."""
    return LensBokeh(config) if config.architecture == "lens" else NeuralBokeh(config)


__all__ = ["LensBokeh", "ModelConfig", "NeuralBokeh", "build_model"]

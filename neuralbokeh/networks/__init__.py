"""The networks (torch, pure definitions: no files, no datasets, no training).

``lens.py`` is the default architecture (the paper's tiled skeleton carrying a learned lens),
``paper.py`` the Neural Bokeh network as the paper writes it (the ``architecture = "paper"``
ablation); ``config.py`` (torch-free) is the configuration both are rebuilt from.
"""

from __future__ import annotations

import torch.nn as nn

from ..core.contract import Contract
from .config import ModelConfig
from .lens import LensBokeh
from .paper import PaperBokeh


def build_model(config: ModelConfig, contract: Contract) -> nn.Module:
    """The network a config describes, for the data a contract describes: :class:`LensBokeh` or
    :class:`PaperBokeh` (``config.blocks`` resolved: :meth:`ModelConfig.resolved`)."""
    return (LensBokeh if config.architecture == "lens" else PaperBokeh)(config, contract)


__all__ = ["LensBokeh", "ModelConfig", "PaperBokeh", "build_model"]

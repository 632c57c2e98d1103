"""Training: typed configs and the loop (single- and multi-process).

The CLI ``train.py`` is a thin layer over :func:`neuralbokeh.training.loop.train`; checkpoints
are :mod:`neuralbokeh.checkpoint`.
"""

from .config import TrainConfig, load_config
from .loop import train

__all__ = ["TrainConfig", "load_config", "train"]

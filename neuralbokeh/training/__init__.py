"""Training: typed configs, the loop (single- and multi-process), checkpoints.

The CLI ``train.py`` is a thin layer over :func:`neuralbokeh.training.loop.train`.
"""

from ..checkpoint import load_checkpoint, load_model, save_checkpoint
from .config import TrainConfig, load_config
from .loop import train

__all__ = ["TrainConfig", "load_checkpoint", "load_config", "load_model", "save_checkpoint", "train"]

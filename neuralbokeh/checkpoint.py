"""Checkpoints: everything needed to rebuild the model (and to resume training) in one file.

A checkpoint stores the model config next to the weights, with the lens, aperture,
normalisation and CoC scale of the data it was trained on, so ``load_model(path)`` needs no
other input. Files are written to a temporary name and renamed (never half-written).
"""

from __future__ import annotations

import os
import pickle
import tempfile
from pathlib import Path
from typing import Any

import torch

from . import __version__
from .networks import ModelConfig, build_model
from .networks.paper import NeuralBokeh

FORMAT = "neuralbokeh-checkpoint"
FORMAT_VERSION = 1


def save_checkpoint(path: str | os.PathLike, payload: dict[str, Any]) -> Path:
    """Write ``payload`` (must hold ``model_config`` and ``model_state``) atomically."""
    path = Path(path)
    for key in ("model_config", "model_state"):
        if key not in payload:
            raise ValueError(f"checkpoint payload needs {key!r}")
    path.parent.mkdir(parents=True, exist_ok=True)
    data = {"format": FORMAT, "format_version": FORMAT_VERSION, "package_version": __version__, **payload}
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        torch.save(data, tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def load_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Read and validate a checkpoint file.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a neuralbokeh checkpoint, or an unsupported version.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such checkpoint: {path}")
    try:
        data = torch.load(path, map_location=map_location, weights_only=False)
    except (pickle.UnpicklingError, EOFError, RuntimeError) as e:  # not a torch file, or a truncated one
        raise ValueError(f"{path} is not a neuralbokeh checkpoint (torch.load: {' '.join(str(e).split())[:200]})") from e
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise ValueError(f"{path} is not a neuralbokeh checkpoint")
    if data.get("format_version") != FORMAT_VERSION:
        raise ValueError(f"{path}: checkpoint format_version {data.get('format_version')} is not supported")
    return data


def load_model(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> tuple[NeuralBokeh, dict[str, Any]]:
    """Rebuild the network from a checkpoint alone; returns ``(model in eval mode, checkpoint)``."""
    data = load_checkpoint(path, map_location)
    model = build_model(ModelConfig.from_dict(data["model_config"]))
    model.load_state_dict(data["model_state"])
    return model.eval(), data

"""Checkpoints: everything needed to rebuild the model (and to resume training) in one file.

A checkpoint stores the model config and the data contract (:class:`~neuralbokeh.core.contract.Contract`:
image size, normalisation, CoC scale, largest CoC, lens, aperture) next to the weights, so
``load_model(path)`` needs no other input. Files are written atomically (``core.io.atomic_write``).
Older formats are refused with a one-line reason (no user holds one).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch
import torch.nn as nn

from . import __version__
from .core.contract import Contract
from .core.io import atomic_write
from .networks import ModelConfig, build_model

FORMAT = "neuralbokeh-checkpoint"
FORMAT_VERSION = 3  # 3: the lens network's pupils on a field grid over the sensor (any image size)


def save_checkpoint(path: str | os.PathLike, payload: dict[str, Any]) -> Path:
    """Write ``payload`` atomically; it must hold ``model_config`` (``ModelConfig.to_dict()``),
    ``contract`` (``Contract.to_dict()``) and ``model_state``."""
    path = Path(path)
    for key in ("model_config", "contract", "model_state"):
        if key not in payload:
            raise ValueError(f"checkpoint payload needs {key!r}")
    path.parent.mkdir(parents=True, exist_ok=True)
    data = {"format": FORMAT, "format_version": FORMAT_VERSION, "package_version": __version__, **payload}
    with atomic_write(path) as tmp:
        torch.save(data, tmp)
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
    except Exception as e:  # noqa: BLE001 - whatever torch.load fails with (pickle, zip, text), the file is no checkpoint
        raise ValueError(f"{path} is not a neuralbokeh checkpoint (torch.load: {' '.join(str(e).split())[:200]})") from e
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise ValueError(f"{path} is not a neuralbokeh checkpoint")
    version = data.get("format_version")
    if version != FORMAT_VERSION:
        hint = " (written before networks of any image size: retrain it)" if isinstance(version, int) and version < 3 else ""
        raise ValueError(f"{path}: checkpoint format_version {version!r} is not supported (this neuralbokeh reads "
                         f"{FORMAT_VERSION}){hint}")
    return data


def load_model(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> tuple[nn.Module, dict[str, Any]]:
    """Rebuild the network from a checkpoint alone; returns ``(model in eval mode, checkpoint)``
    (the model's ``contract`` attribute is the checkpoint's)."""
    data = load_checkpoint(path, map_location)
    model = build_model(ModelConfig.from_dict(data["model_config"]), Contract.from_dict(data["contract"]))
    model.load_state_dict(data["model_state"])
    return model.eval(), data

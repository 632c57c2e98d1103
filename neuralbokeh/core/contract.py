"""The contract between a model's training data and everything that runs the model (torch-free).

A dataset decides how colours are normalised, how CoC maps are scaled for the network, the
largest CoC the model has seen, the image size, and the lens and aperture it was shot with.
Training stores that agreement in the checkpoint, export copies it into the ONNX metadata,
and the runtime and evaluation read it back: one :class:`Contract`, written and read by
:meth:`Contract.to_dict` / :meth:`Contract.from_dict` (versioned), never loose keys.

:meth:`Contract.apply` is the one way to run a network on linear images: normalise (colour
through :class:`~neuralbokeh.core.normalization.Normalization`, CoC divided by
``coc_scale_px``), run, decode back to linear light. It works on numpy arrays and torch tensors.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from .checks import check_finite, is_tensor
from .normalization import Normalization
from .optics import ThinLens

CONTRACT_VERSION = 1


@dataclass(frozen=True)
class Contract:
    """What a model expects of its inputs and what its outputs mean.

    Args:
        image_height, image_width: the image size the model is built for (px), >= 1: the
            paper network's only size; the lens network's training size (its crops) in a
            checkpoint and its plate format in an ONNX file (it renders any size).
        normalization: the colour map between linear HDR and the network's [-1, 1).
        coc_scale_px: the CoC input's px per unit (the network sees ``coc_px / coc_scale_px``),
            > 0; by default the data's largest |CoC| (at least 1 px).
        max_coc_px: the largest |CoC| in the training data (px), >= 0; the runtime refuses
            larger ones unless told to clamp.
        lens: the data's thin lens (so depth maps can be turned into CoC maps), or None.
        aperture: the data's aperture, ``ApertureModel.to_dict()``, or None.
    """

    image_height: int
    image_width: int
    normalization: Normalization
    coc_scale_px: float
    max_coc_px: float
    lens: ThinLens | None = None
    aperture: dict | None = None

    def __post_init__(self) -> None:
        for name in ("image_height", "image_width"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{name} must be an integer >= 1 px, got {v!r}")
        if not (math.isfinite(self.coc_scale_px) and self.coc_scale_px > 0):
            raise ValueError(f"coc_scale_px must be a finite number > 0 px, got {self.coc_scale_px!r}")
        if not (math.isfinite(self.max_coc_px) and self.max_coc_px >= 0):
            raise ValueError(f"max_coc_px must be a finite number >= 0 px, got {self.max_coc_px!r}")

    @property
    def size(self) -> tuple[int, int]:
        """``(H, W)`` in px."""
        return self.image_height, self.image_width

    def check_network_input(self, x: Any) -> None:
        """Raise ``ValueError`` unless ``x`` has the network input's shape ``(B, 4, H, W)``."""
        if len(x.shape) != 4 or x.shape[1] != 4 or tuple(x.shape[2:]) != self.size:
            raise ValueError(f"input must have shape (B, 4, {self.image_height}, {self.image_width}) for this model, "
                             f"got {tuple(x.shape)}")

    # -- the one path through a network ----------------------------------------------------
    def encode_inputs(self, aif: Any, coc_px: Any) -> tuple[Any, Any]:
        """Linear RGB and signed CoC in px (numpy or torch, any matching shapes) -> what the
        network sees: ``(normalised colour, coc_px / coc_scale_px)``."""
        check_finite("CoC in px", coc_px)
        return self.normalization.encode(aif), coc_px / self.coc_scale_px

    def network_input(self, aif: Any, coc_px: Any) -> Any:
        """Linear RGB ``(B, 3, H, W)`` and signed CoC ``(B, 1, H, W)`` in px (numpy or torch) ->
        the network's input ``(B, 4, H, W)`` (:meth:`encode_inputs`, concatenated)."""
        colour, coc = self.encode_inputs(aif, coc_px)
        if is_tensor(colour):  # torch is loaded whenever a tensor exists; this module never imports it
            return sys.modules["torch"].cat([colour, coc.to(colour.dtype)], dim=1)
        return np.concatenate([colour, np.asarray(coc, dtype=colour.dtype)], axis=1)

    def output_linear(self, output: Any) -> Any:
        """The network's normalised output ``(B, 3, H, W)`` -> linear RGB."""
        return self.normalization.decode(output)

    def apply(self, network: Callable[[Any], Any], aif: Any, coc_px: Any) -> Any:
        """Run ``network`` (normalised ``(B, 4, H, W)`` -> normalised ``(B, 3, H, W)``) on linear
        RGB ``(B, 3, H, W)`` and a CoC map ``(B, 1, H, W)`` in px; returns linear RGB."""
        return self.output_linear(network(self.network_input(aif, coc_px)))

    # -- files -----------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            "version": CONTRACT_VERSION,
            "image_size": {"height": int(self.image_height), "width": int(self.image_width)},
            "normalization": self.normalization.to_dict(),
            "coc_scale_px": float(self.coc_scale_px),
            "max_coc_px": float(self.max_coc_px),
            "lens": self.lens.to_dict() if self.lens else None,
            "aperture": self.aperture,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Contract:
        """Read :meth:`to_dict`'s output (any version up to this one).

        Raises:
            ValueError: a newer version, or missing keys (named).
        """
        version = d.get("version")
        if not isinstance(version, int) or not 1 <= version <= CONTRACT_VERSION:
            raise ValueError(f"contract version must be 1..{CONTRACT_VERSION}, got {version!r} (written by a newer neuralbokeh?)")
        missing = [k for k in ("image_size", "normalization", "coc_scale_px", "max_coc_px") if k not in d]
        if missing:
            raise ValueError(f"contract lacks {missing}")
        return cls(int(d["image_size"]["height"]), int(d["image_size"]["width"]), Normalization.from_dict(d["normalization"]),
                   float(d["coc_scale_px"]), float(d["max_coc_px"]),
                   ThinLens.from_dict(d["lens"]) if d.get("lens") else None, d.get("aperture"))

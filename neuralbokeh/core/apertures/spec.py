"""The command-line form of an aperture shape (``polygon:7``, ``ring:0.6``, ``mask:PATH``, ...)."""

from __future__ import annotations

from typing import Callable

import numpy as np

from .shapes import Aperture, Disk, Gaussian, Heart, MaskAperture, Polygon, Ring, Star


def parse_aperture(spec: str, load_mask: Callable[[str], np.ndarray] | None = None) -> Aperture:
    """Parse a command-line aperture spec.

    Forms: ``disk``, ``polygon:BLADES[:ROTATION_DEG]``, ``heart``, ``ring[:INNER_RATIO]``,
    ``star[:POINTS[:INNER_RATIO]]``, ``gaussian[:SIGMA_RATIO]``, ``mask:PATH`` (needs
    ``load_mask(path) -> (H, W)``).

    Raises:
        ValueError: an unknown shape or malformed parameters (the message shows the forms).
    """
    forms = "disk, polygon:BLADES[:ROTATION_DEG], heart, ring[:INNER], star[:POINTS[:INNER]], gaussian[:SIGMA_RATIO], mask:PATH"
    name, _, rest = spec.partition(":")
    args = rest.split(":") if rest else []
    try:
        if name == "disk" and not args:
            return Disk()
        if name == "heart" and not args:
            return Heart()
        if name == "gaussian" and len(args) <= 1:
            return Gaussian(*(float(a) for a in args))
        if name == "polygon" and 1 <= len(args) <= 2:
            return Polygon(int(args[0]), float(args[1]) if len(args) > 1 else 0.0)
        if name == "ring" and len(args) <= 1:
            return Ring(*(float(a) for a in args))
        if name == "star" and len(args) <= 2:
            return Star(*([int(args[0])] if args else []), *(float(a) for a in args[1:]))
        if name == "mask" and rest:
            if load_mask is None:
                raise ValueError("a mask aperture needs an image loader")
            return MaskAperture(load_mask(rest))
    except ValueError as e:
        raise ValueError(f"bad aperture spec {spec!r}: {e}") from None
    raise ValueError(f"bad aperture spec {spec!r}; expected one of: {forms}")

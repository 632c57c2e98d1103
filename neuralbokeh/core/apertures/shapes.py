"""Aperture shapes: transmission functions on the pupil square ``[-1, 1]^2`` (numpy, float64),
and their JSON form (see the package doc for the conventions)."""

from __future__ import annotations

import base64
import hashlib
import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from ..checks import check_in_range


class Aperture:
    """Base class of aperture shapes: a transmission in [0, 1] on the pupil square [-1, 1]^2 (its support is the shape)."""

    name: ClassVar[str] = ""

    def transmission(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Transmission (0..1) at normalised pupil coordinates ``u`` (right), ``v`` (up)."""
        raise NotImplementedError

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable description; :func:`aperture_from_dict` rebuilds the shape."""
        d = {k: v for k, v in self.__dict__.items()}
        return {"shape": self.name, **d}


@dataclass(frozen=True)
class Disk(Aperture):
    """A circular aperture (the unit disk)."""

    name: ClassVar[str] = "disk"

    def transmission(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return (u * u + v * v <= 1.0).astype(np.float64)


@dataclass(frozen=True)
class Polygon(Aperture):
    """A regular polygon of ``blades`` sides (diaphragm blades) inscribed in the unit circle.

    Args:
        blades: number of sides, >= 3.
        rotation_deg: rotation of the first vertex from the +u axis, counter-clockwise, degrees.
    """

    blades: int = 6
    rotation_deg: float = 0.0
    name: ClassVar[str] = "polygon"

    def __post_init__(self) -> None:
        if int(self.blades) != self.blades or self.blades < 3:
            raise ValueError(f"polygon blades must be an integer >= 3, got {self.blades!r}")

    def transmission(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        n = int(self.blades)
        rot = math.radians(self.rotation_deg)
        apothem = math.cos(math.pi / n)
        inside = np.ones(np.broadcast(u, v).shape, dtype=bool)
        for k in range(n):
            a = rot + (2 * k + 1) * math.pi / n  # outward normal of edge k
            inside &= u * math.cos(a) + v * math.sin(a) <= apothem
        return inside.astype(np.float64)


@dataclass(frozen=True)
class Heart(Aperture):
    """A heart, (x^2 + y^2 - 1)^3 <= x^2 y^3, centred on its area centroid, lobes up."""

    name: ClassVar[str] = "heart"
    # Centroid of the implicit heart is at y = 0.2935; its farthest point from the centroid
    # is at 1.2935 (measured on a 3001^2 grid): shift and scale so it fits the unit circle.
    _CENTROID_Y: ClassVar[float] = 0.2935
    _SCALE: ClassVar[float] = 1.2935

    def transmission(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        x = u * self._SCALE
        y = v * self._SCALE + self._CENTROID_Y
        return ((x * x + y * y - 1.0) ** 3 - x * x * y**3 <= 0.0).astype(np.float64)


@dataclass(frozen=True)
class Ring(Aperture):
    """An annulus between ``inner_ratio`` and 1 (e.g. a catadioptric mirror lens).

    Args:
        inner_ratio: inner radius over outer radius, in [0, 1).
    """

    inner_ratio: float = 0.6
    name: ClassVar[str] = "ring"

    def __post_init__(self) -> None:
        if not (0.0 <= self.inner_ratio < 1.0):
            raise ValueError(f"ring inner_ratio must be in [0, 1), got {self.inner_ratio!r}")

    def transmission(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        r2 = u * u + v * v
        return ((r2 <= 1.0) & (r2 >= self.inner_ratio**2)).astype(np.float64)


@dataclass(frozen=True)
class Star(Aperture):
    """A star polygon with ``points`` tips on the unit circle and inner vertices at ``inner_ratio``.

    Args:
        points: number of tips, >= 3.
        inner_ratio: radius of the inner vertices, in (0, 1].
        rotation_deg: angle of the first tip from +u, counter-clockwise, degrees (90 = tip up).
    """

    points: int = 5
    inner_ratio: float = 0.45
    rotation_deg: float = 90.0
    name: ClassVar[str] = "star"

    def __post_init__(self) -> None:
        if int(self.points) != self.points or self.points < 3:
            raise ValueError(f"star points must be an integer >= 3, got {self.points!r}")
        if not (0.0 < self.inner_ratio <= 1.0):
            raise ValueError(f"star inner_ratio must be in (0, 1], got {self.inner_ratio!r}")

    def transmission(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        n = int(self.points)
        half = math.pi / n
        rho = np.hypot(u, v)
        phi = np.mod(np.arctan2(v, u) - math.radians(self.rotation_deg), 2 * half)
        phi = np.where(phi > half, 2 * half - phi, phi)  # fold into one half-sector [0, pi/n]
        px, py = rho * np.cos(phi), rho * np.sin(phi)
        ax, ay = 1.0, 0.0  # the tip
        bx, by = self.inner_ratio * math.cos(half), self.inner_ratio * math.sin(half)
        # Inside when the point is on the origin's side of the edge tip -> inner vertex.
        side = (bx - ax) * (py - ay) - (by - ay) * (px - ax)
        origin_side = (bx - ax) * (0.0 - ay) - (by - ay) * (0.0 - ax)
        return (side * origin_side >= 0.0).astype(np.float64)


@dataclass(frozen=True)
class Gaussian(Aperture):
    """A Gaussian profile exp(-r^2 / (2 sigma^2)) cut at the CoC radius: not a real aperture but
    the CoC-driven Gaussian blur that simple defocus approximations use (a baseline).

    Args:
        sigma_ratio: sigma over the CoC radius, in (0, 1] (default 0.5: the CoC diameter is 4 sigma).
    """

    sigma_ratio: float = 0.5
    name: ClassVar[str] = "gaussian"

    def __post_init__(self) -> None:
        if not (0.0 < self.sigma_ratio <= 1.0):
            raise ValueError(f"gaussian sigma_ratio must be in (0, 1], got {self.sigma_ratio!r}")

    def transmission(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        r2 = u * u + v * v
        return np.where(r2 <= 1.0, np.exp(-r2 / (2.0 * self.sigma_ratio**2)), 0.0)


@dataclass(frozen=True, eq=False)
class MaskAperture(Aperture):
    """An arbitrary aperture from a transmission image covering the square [-1, 1]^2.

    Args:
        mask: ``(H, W)`` array of transmissions in [0, 1]; row 0 is the top (v = +1). The
            whole square is the pupil (kernels span it at the CoC diameter as their side):
            an all-ones mask is a square aperture.

    It is stored in JSON as 8-bit data (exact for binary masks).
    """

    mask: np.ndarray = field(default_factory=lambda: np.ones((1, 1)))
    name: ClassVar[str] = "mask"

    def __post_init__(self) -> None:
        m = np.asarray(self.mask, dtype=np.float64)
        if m.ndim != 2 or min(m.shape) < 1:
            raise ValueError(f"aperture mask must be a 2-D (H, W) array, got shape {m.shape}")
        check_in_range("aperture mask", m, 0.0, 1.0)
        if not m.any():
            raise ValueError("aperture mask is all zero: no light would pass")
        object.__setattr__(self, "mask", m)

    def _key(self) -> str:
        return hashlib.sha256(np.ascontiguousarray(self.mask).tobytes()).hexdigest()

    def __hash__(self) -> int:
        return hash(self._key())

    def __eq__(self, other: object) -> bool:
        return isinstance(other, MaskAperture) and self._key() == other._key()

    def transmission(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return _cell_lookup(self.mask, u, v)

    def to_dict(self) -> dict[str, Any]:
        q = np.round(self.mask * 255.0).astype(np.uint8)
        return {"shape": self.name, "size": list(q.shape), "data_b64": base64.b64encode(q.tobytes()).decode()}


def _cell_lookup(table: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``table`` ``(H, W)`` (row 0 at v = +1) as cells covering the pupil square, at ``(u, v)``."""
    h, w = table.shape
    col = np.floor((u + 1.0) * 0.5 * w).astype(np.int64)
    row = np.floor((1.0 - v) * 0.5 * h).astype(np.int64)
    ok = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    out = np.zeros(np.broadcast(u, v).shape, dtype=np.float64)
    out[ok] = table[np.broadcast_to(row, out.shape)[ok], np.broadcast_to(col, out.shape)[ok]]
    return out


@dataclass(frozen=True, eq=False)
class ViewGrid(Aperture):
    """The aperture of a shift-and-add refocus of an N x N grid of pinhole views (a light
    field): a point of the pupil square at each view's cell centre, weighted.

    Args:
        weights: ``(N, N)`` view weights in [0, 1], row 0 at the top (v = +1), not all zero.

    Its kernels are the points splatted bilinearly (:func:`~neuralbokeh.core.apertures.shape_kernels`),
    which is what averaging bilinearly shifted views does: once the views' shifts are a pixel
    apart or more (a CoC of N px), the refocus is N x N copies of the image, which no shape with
    an area makes. Ray-traced renderers take the points themselves. :meth:`transmission`
    (pictures of the pupil, a network's starting pupil) gives each view its cell, the
    sub-aperture it stands for.
    """

    weights: np.ndarray = field(default_factory=lambda: np.ones((1, 1)))
    name: ClassVar[str] = "views"

    def __post_init__(self) -> None:
        w = np.asarray(self.weights, dtype=np.float64)
        if w.ndim != 2 or w.shape[0] != w.shape[1] or w.shape[0] < 1:
            raise ValueError(f"view weights must be a square (N, N) array, got shape {w.shape}")
        check_in_range("view weights", w, 0.0, 1.0)
        if not w.any():
            raise ValueError("view weights are all zero: no view would count")
        object.__setattr__(self, "weights", w)

    def __hash__(self) -> int:
        return hash(self.weights.tobytes())

    def __eq__(self, other: object) -> bool:
        return isinstance(other, ViewGrid) and np.array_equal(self.weights, other.weights)

    def points(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The views that count: their pupil positions ``u`` (right), ``v`` (up) in [-1, 1] and
        weights, each ``(M,)``."""
        n = self.weights.shape[0]
        rows, cols = np.nonzero(self.weights)
        return (2.0 * cols + 1.0) / n - 1.0, 1.0 - (2.0 * rows + 1.0) / n, self.weights[rows, cols]

    def transmission(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return _cell_lookup(self.weights, u, v)

    def to_dict(self) -> dict[str, Any]:
        return {"shape": self.name, "weights": self.weights.tolist()}


_SHAPES: dict[str, type[Aperture]] = {c.name: c for c in (Disk, Polygon, Heart, Ring, Star, Gaussian, MaskAperture, ViewGrid)}
SHAPE_NAMES = tuple(_SHAPES)


def aperture_from_dict(d: dict[str, Any]) -> Aperture:
    """Rebuild a shape from :meth:`Aperture.to_dict`."""
    d = dict(d)
    name = d.pop("shape", None)
    if name not in _SHAPES:
        raise ValueError(f"unknown aperture shape {name!r}; expected one of {SHAPE_NAMES}")
    if name == "mask":
        h, w = d["size"]
        raw = np.frombuffer(base64.b64decode(d["data_b64"]), dtype=np.uint8)
        return MaskAperture(raw.reshape(h, w).astype(np.float64) / 255.0)
    try:
        return _SHAPES[name](**d)
    except TypeError as e:
        raise ValueError(f"bad parameters for aperture {name!r}: {d} ({e})") from None

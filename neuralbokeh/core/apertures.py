"""Aperture shapes and the blur kernels (point-spread functions) they make.

Pure math on numpy (float64): kernels are small, and keeping this module torch-free lets the
compositing runtime use it too. Renderers move kernels to their input's device and dtype.

Conventions:
    * A shape is a transmission function on *normalised pupil coordinates* ``(u, v)`` in the
      square ``[-1, 1]^2`` (``u`` right, ``v`` up); the shape's own transmission is its
      support (no implicit disk: a circular pupil is ``Disk``). Kernels and every ray-traced
      renderer (:func:`pupil_grid`) sample that same square; the CoC diameter is its side.
    * A kernel is the shape's image for a CoC diameter ``d`` px: an odd ``(k, k)`` array,
      ``k = 2 * ceil(d/2 - 1/2) + 1``, its centre pixel on the point's position, row 0 at the
      top. It is anti-aliased by box-filtering the shape over each pixel (supersampling) and
      normalised to sum 1. Diameters below one pixel give the 1x1 delta, continuously.
    * This is the bokeh of a point *behind* the focus plane; in front of it the image of the
      aperture is inverted (renderers point-reflect the kernel for negative signed CoC).
    * Spatially varying effects (``ApertureModel``): cat-eye mechanical vignetting intersects
      the aperture with a circle of radius ``vignetting_radius`` (in aperture radii) whose
      centre moves from the pupil centre towards the image centre by ``cat_eye`` aperture radii
      at the image corner, in proportion to the field position. A per-channel scale of the
      diameter models longitudinal chromatic aberration.
"""

from __future__ import annotations

import base64
import hashlib
import math
from dataclasses import dataclass, field
from typing import Any, Callable, ClassVar

import numpy as np

from .checks import check_in_range, check_nonnegative, check_positive


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
        h, w = self.mask.shape
        col = np.floor((u + 1.0) * 0.5 * w).astype(np.int64)
        row = np.floor((1.0 - v) * 0.5 * h).astype(np.int64)
        ok = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        out = np.zeros(np.broadcast(u, v).shape, dtype=np.float64)
        out[ok] = self.mask[np.broadcast_to(row, out.shape)[ok], np.broadcast_to(col, out.shape)[ok]]
        return out

    def to_dict(self) -> dict[str, Any]:
        q = np.round(self.mask * 255.0).astype(np.uint8)
        return {"shape": self.name, "size": list(q.shape), "data_b64": base64.b64encode(q.tobytes()).decode()}


_SHAPES: dict[str, type[Aperture]] = {c.name: c for c in (Disk, Polygon, Heart, Ring, Star, Gaussian, MaskAperture)}
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


def pupil_grid(shape: Aperture, n: int, rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Sample points of the pupil where ``shape`` transmits: the one pupil definition of every
    renderer that traces rays (kernels sample the same square).

    The pupil is the square ``[-1, 1]^2`` of normalised coordinates and the shape's own
    transmission is its support: there is no implicit disk (a disk-shaped aperture is a
    ``Disk``), so e.g. ``MaskAperture(np.ones(...))`` is a square in every renderer.

    Args:
        shape: the aperture shape.
        n: points per side of the regular ``n x n`` grid of cell centres, >= 1.
        rng: if given, each point is jittered uniformly inside its cell (stratified sampling).

    Returns:
        ``(M, 2)`` points ``(u right, v up)`` and their transmissions ``(M,)``, all > 0.
    """
    if int(n) != n or n < 1:
        raise ValueError(f"pupil grid size must be an integer >= 1, got {n!r}")
    cell = np.arange(n, dtype=np.float64)
    if rng is None:
        u, v = np.meshgrid(cell + 0.5, cell + 0.5)
    else:
        u = cell[None, :] + rng.uniform(size=(n, n))
        v = cell[:, None] + rng.uniform(size=(n, n))
    u, v = u / n * 2.0 - 1.0, v / n * 2.0 - 1.0
    t = np.broadcast_to(shape.transmission(u, v), u.shape)
    keep = t > 0
    return np.stack([u[keep], v[keep]], axis=1), t[keep]


def kernel_radius_px(diameter_px: float) -> int:
    """Half-width h of the ``(2h+1, 2h+1)`` kernel for a CoC diameter (px)."""
    return max(0, math.ceil(diameter_px / 2.0 - 0.5))


def _auto_supersample(diameter_px: float) -> int:
    # About 128 samples across the diameter, 4..32 per pixel: fine edges for small kernels,
    # bounded cost for large ones.
    return int(min(32, max(4, math.ceil(128.0 / max(diameter_px, 1.0)))))


def shape_kernels(
    shape: Aperture,
    diameter_px: float,
    clip_centers: np.ndarray | None = None,
    clip_radius: float = 1.0,
    supersample: int | None = None,
) -> np.ndarray:
    """Anti-aliased kernels of ``shape`` at one CoC diameter for several vignetting circles.

    The shape is sampled once; only the clip circle changes between the kernels, so many
    positions of a cat-eye grid cost little more than one.

    Args:
        shape: the aperture shape.
        diameter_px: CoC diameter in px, finite and >= 0.
        clip_centers: ``(M, 2)`` centres ``(u, v)`` of the vignetting circles (aperture radii),
            or None for one unclipped kernel.
        clip_radius: radius of the vignetting circle in aperture radii.
        supersample: samples per pixel side (default: automatic, 4 to 32).

    Returns:
        ``(M, k, k)`` float64 (M = 1 without clipping), each summing to 1; ``k = 1`` (a delta)
        below one pixel.

    Raises:
        ValueError: bad diameter, or a shape (after vignetting) that lets no light through.
    """
    check_nonnegative("CoC diameter", diameter_px, " px")
    centers = None if clip_centers is None else np.asarray(clip_centers, dtype=np.float64).reshape(-1, 2)
    m = 1 if centers is None else len(centers)
    h = kernel_radius_px(diameter_px)
    if h == 0:
        return np.ones((m, 1, 1))
    s = supersample or _auto_supersample(diameter_px)
    r = diameter_px / 2.0
    # Sample positions (in px from the centre) on a regular s x s grid inside each pixel.
    offs = (np.arange(s) + 0.5) / s - 0.5
    pos = (np.arange(-h, h + 1)[:, None] + offs[None, :]).reshape(-1)
    u = pos[None, :] / r
    v = -pos[:, None] / r  # rows go down, v goes up
    t = shape.transmission(u, v)
    k = 2 * h + 1
    if centers is None:
        kern = t.reshape(1, k, s, k, s).mean(axis=(2, 4))
    else:
        kern = np.empty((m, k, k))
        for i, (cu, cv) in enumerate(centers):
            clipped = t * ((u - cu) ** 2 + (v - cv) ** 2 <= clip_radius**2)
            kern[i] = clipped.reshape(k, s, k, s).mean(axis=(1, 3))
    total = kern.sum(axis=(1, 2))
    if (total <= 0).any():
        if h <= 2:  # shape thinner than the sampling at a tiny diameter: a point
            kern[total <= 0] = 0.0
            kern[total <= 0, h, h] = 1.0
            total = kern.sum(axis=(1, 2))
        else:
            raise ValueError(f"aperture {shape.to_dict()['shape']} lets no light through at diameter {diameter_px} px")
    return kern / total[:, None, None]


def shape_kernel(
    shape: Aperture,
    diameter_px: float,
    clip_center: tuple[float, float] | None = None,
    clip_radius: float = 1.0,
    supersample: int | None = None,
) -> np.ndarray:
    """One anti-aliased ``(k, k)`` kernel of ``shape`` at ``diameter_px``, summing to 1.

    ``clip_center`` (``(u, v)`` in aperture radii) intersects the shape with a circle of
    radius ``clip_radius`` (cat-eye vignetting). See :func:`shape_kernels`.
    """
    centers = None if clip_center is None else np.asarray([clip_center])
    return shape_kernels(shape, diameter_px, centers, clip_radius, supersample)[0]


@dataclass(frozen=True)
class ApertureModel:
    """A lens's aperture: shape, cat-eye vignetting and longitudinal chromatic aberration.

    Args:
        shape: the aperture shape.
        cat_eye: displacement (aperture radii) of the vignetting circle at the image corner,
            >= 0; 0 turns vignetting off. Typical 0.3..1.0.
        vignetting_radius: radius of the vignetting circle (aperture radii), > 0.
        channel_scale: per-channel (R, G, B) factors on the CoC diameter, each > 0
            (e.g. ``(1.05, 1.0, 0.95)``); all 1 turns chromatic aberration off.
    """

    shape: Aperture = field(default_factory=Disk)
    cat_eye: float = 0.0
    vignetting_radius: float = 1.0
    channel_scale: tuple[float, float, float] = (1.0, 1.0, 1.0)

    def __post_init__(self) -> None:
        check_nonnegative("cat_eye", self.cat_eye, " aperture radii")
        check_positive("vignetting_radius", self.vignetting_radius, " aperture radii")
        if len(self.channel_scale) != 3:
            raise ValueError(f"channel_scale must have 3 values (R, G, B), got {self.channel_scale!r}")
        check_positive("channel_scale", np.asarray(self.channel_scale, dtype=np.float64))
        if self.cat_eye >= 1.0 + self.vignetting_radius:
            raise ValueError(
                f"cat_eye must be < 1 + vignetting_radius = {1.0 + self.vignetting_radius} "
                f"(else the image corner gets no light), got {self.cat_eye}"
            )
        object.__setattr__(self, "channel_scale", tuple(float(c) for c in self.channel_scale))

    @property
    def spatially_varying(self) -> bool:
        """True when the kernel depends on the image position (cat-eye on)."""
        return self.cat_eye > 0.0

    @property
    def chromatic(self) -> bool:
        """True when the channels have different kernels."""
        return len(set(self.channel_scale)) > 1

    @property
    def vignetted(self) -> bool:
        """True when the vignetting circle clips the aperture somewhere."""
        return self.cat_eye > 0.0 or self.vignetting_radius < 1.0

    def vignetting_center(self, fx: Any, fy: Any) -> tuple[Any, Any]:
        """Centre ``(u, v)`` (aperture radii; u right, v up) of the vignetting circle at field
        position ``(fx, fy)`` (:func:`field_position`; x right, y down): it moves towards the
        image centre by ``cat_eye`` per unit of field. Scalars or arrays."""
        return -self.cat_eye * fx, self.cat_eye * fy

    def transmits(self, u: Any, v: Any, fx: Any, fy: Any) -> Any:
        """Whether pupil point ``(u, v)`` lies inside the vignetting circle at field ``(fx, fy)``
        (the shape itself is not tested); broadcasts over arrays."""
        cu, cv = self.vignetting_center(fx, fy)
        return (u - cu) ** 2 + (v - cv) ** 2 <= self.vignetting_radius**2

    def kernel_radius_px(self, diameter_px: float) -> int:
        """Half-width of the (common) kernel for all channels at this CoC diameter."""
        return kernel_radius_px(diameter_px * max(self.channel_scale))

    def kernels(self, diameter_px: float, field_xy: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
        """Per-channel kernels at a CoC diameter and one field position.

        Args:
            diameter_px: CoC diameter in px (>= 0) of the green/reference channel.
            field_xy: image position relative to the centre, normalised so that the image
                corners are at distance 1: ``x`` right, ``y`` down.

        Returns:
            ``(3, k, k)`` float64, each channel summing to 1, all padded to one size.
        """
        return self.kernels_at(diameter_px, np.asarray([field_xy], dtype=np.float64))[0]

    def kernels_at(self, diameter_px: float, fields_xy: np.ndarray) -> np.ndarray:
        """Per-channel kernels at one CoC diameter for ``(M, 2)`` field positions: ``(M, 3, k, k)``.

        The aperture is sampled once per distinct channel scale, whatever M.
        """
        fields = np.asarray(fields_xy, dtype=np.float64).reshape(-1, 2)
        centers = None
        if self.vignetted:
            centers = np.stack(self.vignetting_center(fields[:, 0], fields[:, 1]), axis=1)
        h = self.kernel_radius_px(diameter_px)
        out = np.zeros((len(fields), 3, 2 * h + 1, 2 * h + 1))
        done: dict[float, np.ndarray] = {}
        for c, scale in enumerate(self.channel_scale):
            if scale not in done:
                k = shape_kernels(self.shape, diameter_px * scale, centers, self.vignetting_radius)
                done[scale] = np.broadcast_to(k, (len(fields),) + k.shape[1:])
            k = done[scale]
            p = h - k.shape[-1] // 2
            out[:, c, p : p + k.shape[-2], p : p + k.shape[-1]] = k
        return out

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable description."""
        return {
            "shape": self.shape.to_dict(),
            "cat_eye": self.cat_eye,
            "vignetting_radius": self.vignetting_radius,
            "channel_scale": list(self.channel_scale),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "ApertureModel":
        """Inverse of :meth:`to_dict`."""
        return cls(
            shape=aperture_from_dict(d["shape"]),
            cat_eye=float(d.get("cat_eye", 0.0)),
            vignetting_radius=float(d.get("vignetting_radius", 1.0)),
            channel_scale=tuple(d.get("channel_scale", (1.0, 1.0, 1.0))),
        )


def field_position(row: Any, col: Any, height: int, width: int) -> tuple[Any, Any]:
    """Normalised field position ``(x right, y down)`` of pixel ``(row, col)`` (scalars or
    arrays, fractional allowed): centre 0, corners at distance 1."""
    half_diag = 0.5 * math.hypot(width - 1, height - 1) or 1.0
    return ((col - (width - 1) / 2.0) / half_diag, (row - (height - 1) / 2.0) / half_diag)

"""A lens's aperture: shape, cat-eye vignetting, longitudinal chromatic aberration, and its
kernels and point-spread functions over the field."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..checks import check_nonnegative, check_positive
from .raster import shape_kernel_radius_px, shape_kernels
from .shapes import Aperture, Disk, aperture_from_dict


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
        return shape_kernel_radius_px(self.shape, diameter_px * max(self.channel_scale))

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

    def psfs_at(self, coc_px: float, fields_xy: np.ndarray) -> np.ndarray:
        """Point-spread functions at a *signed* CoC diameter (px; negative in front of the focus
        plane) for ``(M, 2)`` field positions: :meth:`kernels_at` of ``|coc_px|``, point-reflected
        in front of the focus plane, where the aperture's image is inverted. ``(M, 3, k, k)``."""
        k = self.kernels_at(abs(coc_px), fields_xy)
        return k[..., ::-1, ::-1].copy() if coc_px < 0 else k  # a copy: no negative strides (torch refuses them)

    def psf(self, coc_px: float, field_xy: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
        """:meth:`psfs_at` at one field position: ``(3, k, k)``."""
        return self.psfs_at(coc_px, np.asarray([field_xy], dtype=np.float64))[0]

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

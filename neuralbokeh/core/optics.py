"""Thin-lens optics: circle of confusion (eq. 1 of the Neural Bokeh paper) and network depth.

Units: lens figures in millimetres, scene distances (depth, focus) in metres, the circle of
confusion (CoC) as a *diameter in pixels*. Pure math: imports numpy and ``checks`` only, so the
torch-free runtime can use it; torch tensors are accepted and returned as tensors (same dtype
and device) through plain arithmetic.

Eq. (1) of Mandl et al. 2024::

    c = (w_i / w_s) * a * d_s * |d_p - d_f| / (d_p * d_f)

with ``w_i`` the image width (px), ``w_s`` the sensor width (mm), ``a = f / N`` the aperture
diameter (mm), ``d_s = f d_f / (d_f - f)`` the lens-to-sensor distance from the thin-lens law
(mm), ``d_p`` the point's depth and ``d_f`` the focus distance. It is evaluated in the
equivalent, numerically clean form ``c = K (1/d_f - 1/d_p)`` with ``K = (w_i/w_s) a d_s``,
which gives the finite limit ``K / d_f`` for ``d_p = inf`` without special cases.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Iterable, Sequence

from .checks import check_positive

MM_PER_M = 1000.0


@dataclass(frozen=True)
class SensorWindow:
    """The part of the sensor an image covers, in fractions of the full sensor's width and height
    (0 at its left and top edges): ``(0, 0, 1, 1)`` is the whole sensor. A crop of a frame (an
    alignment crop, a 2.39:1 plate cut from a 3:2 sensor) is a window on the same lens, not
    another lens: its pixels keep the pitch of the sensor they lie on.

    Raises:
        ValueError: a fraction outside [0, 1], an empty window, or one reaching past the sensor.
    """

    left: float = 0.0
    top: float = 0.0
    width: float = 1.0
    height: float = 1.0

    def __post_init__(self) -> None:
        for name in ("left", "top", "width", "height"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and 0.0 <= v <= 1.0):
                raise ValueError(f"sensor window {name} must be a fraction of the sensor in [0, 1], got {v!r}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"sensor window must have width and height > 0, got {self.width} x {self.height}")
        if self.left + self.width > 1.0 + 1e-6 or self.top + self.height > 1.0 + 1e-6:  # float32 round-off
            raise ValueError(f"sensor window {self.to_dict()} reaches past the sensor (left + width and top + height "
                             "must be <= 1)")

    @classmethod
    def from_crop(cls, rows: tuple[int, int], cols: tuple[int, int], full_height_px: int, full_width_px: int) -> SensorWindow:
        """The window of the pixel rows ``[r0, r1)`` and columns ``[c0, c1)`` of a full frame."""
        return cls().crop(rows, cols, full_height_px, full_width_px)

    def crop(self, rows: tuple[int, int], cols: tuple[int, int], height_px: int, width_px: int) -> SensorWindow:
        """The window of rows ``[r0, r1)`` and columns ``[c0, c1)`` of an image of this window
        that is ``height_px x width_px`` px."""
        (r0, r1), (c0, c1) = rows, cols
        return SensorWindow(self.left + self.width * c0 / width_px, self.top + self.height * r0 / height_px,
                            self.width * (c1 - c0) / width_px, self.height * (r1 - r0) / height_px)

    def sensor_width_px(self, image_width_px: float) -> float:
        """The width (px) the whole sensor has at the scale of an image of this window."""
        return image_width_px / self.width

    def to_dict(self) -> dict[str, float]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> SensorWindow:
        """Inverse of :meth:`to_dict`; None is the whole sensor."""
        if d is None:
            return cls()
        keys = {"left", "top", "width", "height"}
        if set(d) != keys:
            raise ValueError(f"sensor window must have exactly the keys {sorted(keys)}, got {sorted(d)}")
        return cls(**{k: float(v) for k, v in d.items()})


@dataclass(frozen=True)
class ThinLens:
    """An ideal thin lens on a sensor of known width.

    Args:
        focal_length_mm: focal length f in mm, finite and > 0.
        f_number: the f-number N (aperture diameter = f / N), finite and > 0.
        sensor_width_mm: width of the sensor area the image covers, in mm, finite and > 0.

    Raises:
        ValueError: any figure is not finite and > 0.
    """

    focal_length_mm: float
    f_number: float
    sensor_width_mm: float

    def __post_init__(self) -> None:
        check_positive("focal_length_mm", self.focal_length_mm, " mm")
        check_positive("f_number", self.f_number)
        check_positive("sensor_width_mm", self.sensor_width_mm, " mm")

    @property
    def aperture_diameter_mm(self) -> float:
        """Entrance-pupil diameter a = f / N in mm."""
        return self.focal_length_mm / self.f_number

    def _check_focus(self, focus_m: float) -> float:
        focus_m = float(focus_m)
        check_positive("focus distance", focus_m, " m", allow_inf=True)
        if focus_m * MM_PER_M <= self.focal_length_mm:
            raise ValueError(
                f"focus distance must be greater than the focal length "
                f"({self.focal_length_mm} mm), got {focus_m} m"
            )
        return focus_m

    def sensor_distance_mm(self, focus_m: float) -> float:
        """Lens-to-sensor distance d_s (mm) that focuses at ``focus_m`` (m, may be inf).

        Thin-lens law 1/f = 1/d_f + 1/d_s, so d_s = f d_f / (d_f - f); d_s = f at infinity.
        """
        focus_m = self._check_focus(focus_m)
        f = self.focal_length_mm
        if math.isinf(focus_m):
            return f
        d_f = focus_m * MM_PER_M
        return f * d_f / (d_f - f)

    def coc_constant_pxmm(self, focus_m: float, image_width_px: float) -> float:
        """K = (w_i / w_s) a d_s in px*mm: the CoC is K (1/d_f - 1/d_p) with distances in mm
        (``image_width_px``: the px the whole sensor width spans, > 0)."""
        if isinstance(image_width_px, bool) or not (isinstance(image_width_px, (int, float)) and
                                                    math.isfinite(image_width_px) and image_width_px > 0):
            raise ValueError(f"image_width_px must be a finite number of px > 0, got {image_width_px!r}")
        d_s = self.sensor_distance_mm(focus_m)
        return (image_width_px / self.sensor_width_mm) * self.aperture_diameter_mm * d_s

    def coc_px(self, depth_m: Any, focus_m: float, image_width_px: int, signed: bool = False,
               window: SensorWindow | None = None) -> Any:
        """Circle-of-confusion diameter in pixels, eq. (1).

        Args:
            depth_m: distance of the scene point(s) along the optical axis in m: a float, a numpy
                array or a torch tensor of any shape (e.g. ``(H, W)`` or ``(B, 1, H, W)``);
                each value > 0, ``+inf`` allowed (gives the finite limit).
            focus_m: focus distance in m, greater than the focal length; ``inf`` allowed.
            image_width_px: width of the image in pixels (the sensor width maps onto it, or the
                ``window``'s width when the image covers only part of the sensor).
            signed: if True the result is negative in front of the focus plane (depth < focus)
                and positive behind it; otherwise the absolute diameter.
            window: the part of the sensor the image covers (default: all of it).

        Returns:
            The CoC diameter(s) in px, same type/shape (and dtype/device for arrays and tensors)
            as ``depth_m``; a Python float for a scalar input.

        Raises:
            ValueError: a depth is <= 0, NaN or -inf (the message gives the number of bad
                pixels and the first location), or the focus distance is invalid.
        """
        if window is not None:
            image_width_px = window.sensor_width_px(image_width_px)
        k = self.coc_constant_pxmm(focus_m, image_width_px)
        inv_focus = 1.0 / (float(focus_m) * MM_PER_M)
        scalar = isinstance(depth_m, (int, float))
        if scalar:
            depth_m = float(depth_m)
        check_positive("depth", depth_m, " m", allow_inf=True)
        c = k * (inv_focus - 1.0 / (depth_m * MM_PER_M))
        if not signed:
            c = abs(c)
        return float(c) if scalar else c

    def to_dict(self) -> dict[str, float]:
        """JSON-serialisable description (units in the key names)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "ThinLens":
        """Inverse of :meth:`to_dict`; unknown or missing keys raise ``ValueError``."""
        keys = {"focal_length_mm", "f_number", "sensor_width_mm"}
        if set(d) != keys:
            raise ValueError(f"lens description must have exactly the keys {sorted(keys)}, got {sorted(d)}")
        return cls(**{k: float(v) for k, v in d.items()})


def max_coc_px(
    lens: ThinLens,
    depth_range_m: tuple[float, float],
    focus_distances_m: Iterable[float],
    image_width_px: int,
) -> float:
    """Largest CoC diameter (px) over a depth range and a set of focus distances.

    |c| = K |1/d_f - 1/d_p| is monotonic in 1/d_p, so its maximum over ``[near, far]`` is at
    one of the two ends; ``far`` may be ``inf``.

    Args:
        lens: the lens.
        depth_range_m: ``(near, far)`` in m with ``0 < near <= far`` (far may be inf).
        focus_distances_m: one or more focus distances in m.
        image_width_px: image width in px.

    Raises:
        ValueError: empty focus list, or an invalid range or distance.
    """
    near, far = (float(v) for v in depth_range_m)
    check_positive("near depth", near, " m")
    check_positive("far depth", far, " m", allow_inf=True)
    if far < near:
        raise ValueError(f"depth range must have near <= far, got ({near}, {far}) m")
    focus = list(focus_distances_m)
    if not focus:
        raise ValueError("focus_distances_m must hold at least one focus distance, got none")
    return max(lens.coc_px(d, f, image_width_px) for f in focus for d in (near, far))


def blocks_for_coc(max_coc: float) -> int:
    """Number of residual blocks N for a largest CoC diameter ``max_coc`` (px).

    The smallest N >= 0 with 2N + 1 >= max_coc: block n has kernels of size 2n + 1, so the
    last block's kernel covers the largest CoC. N = 0 means nothing in the data set is
    blurred beyond one pixel.

    Raises:
        ValueError: ``max_coc`` is negative, NaN or infinite.
    """
    c = float(max_coc)
    if not (c >= 0 and math.isfinite(c)):
        raise ValueError(f"max_coc must be finite and >= 0 px, got {max_coc!r}")
    return max(0, math.ceil((c - 1.0) / 2.0))


def focus_sweep_m(near_m: float, far_m: float, count: int) -> list[float]:
    """``count`` focus distances spaced uniformly in diopters between ``near_m`` and ``far_m``.

    Uniform diopter spacing gives equal CoC steps between neighbouring focus settings.
    ``far_m`` may be inf. Returned near to far.
    """
    if count < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    check_positive("near focus", near_m, " m")
    check_positive("far focus", far_m, " m", allow_inf=True)
    if far_m < near_m:
        raise ValueError(f"focus range must have near <= far, got ({near_m}, {far_m}) m")
    d0, d1 = 1.0 / near_m, 1.0 / far_m
    if count == 1:
        return [2.0 / (d0 + d1)]
    out: list[float] = []
    for i in range(count):
        dio = d0 + (d1 - d0) * i / (count - 1)
        out.append(math.inf if dio == 0 else 1.0 / dio)
    return out


__all__: Sequence[str] = [
    "ThinLens",
    "max_coc_px",
    "blocks_for_coc",
    "focus_sweep_m",
]

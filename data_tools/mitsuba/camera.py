"""The pinhole camera shared by the Mitsuba scenes and the renderer (world units: metres; the
procedural camera sits at the origin looking along +z with +y up)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import ModuleType

import numpy as np

from neuralbokeh.core.checks import check_positive


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: pose, horizontal field of view and film size.

    Attributes:
        to_world: 4x4 camera-to-world matrix (Mitsuba camera space: +z forward, +y up, image
            right is -x).
        fov_x_deg: horizontal field of view in degrees, in (0, 180).
        width, height: film size in px.
    """

    to_world: np.ndarray
    fov_x_deg: float
    width: int
    height: int

    @property
    def tan_half_x(self) -> float:
        return math.tan(math.radians(self.fov_x_deg) / 2.0)


def fov_for_lens(focal_length_mm: float, sensor_width_mm: float) -> float:
    """Horizontal field of view (degrees) of a lens focused at infinity on a sensor of that width."""
    check_positive("focal_length_mm", focal_length_mm, " mm")
    check_positive("sensor_width_mm", sensor_width_mm, " mm")
    return math.degrees(2.0 * math.atan(sensor_width_mm / (2.0 * focal_length_mm)))


def axis_camera(mi: ModuleType, focal_length_mm: float, sensor_width_mm: float, width: int, height: int) -> Camera:
    """The procedural scenes' camera: at the origin looking along +z (+y up), with the field of
    view of that lens on that sensor (:func:`fov_for_lens`), ``width x height`` px."""
    look = mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[0, 0, 1], up=[0, 1, 0])
    return Camera(np.array(look.matrix, dtype=np.float64).reshape(4, 4), fov_for_lens(focal_length_mm, sensor_width_mm),
                  width, height)

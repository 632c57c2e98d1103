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

The package: ``shapes.py`` (the shapes and their JSON form), ``spec.py`` (the command-line
form), ``raster.py`` (pupil samples and kernels), ``lens.py`` (``ApertureModel``: the
spatially varying lens aperture). Import from here.
"""

from .lens import ApertureModel, field_position
from .raster import kernel_radius_px, pupil_grid, shape_kernel, shape_kernel_radius_px, shape_kernels
from .shapes import SHAPE_NAMES, Aperture, Disk, Gaussian, Heart, MaskAperture, Polygon, Ring, Star, ViewGrid, aperture_from_dict
from .spec import parse_aperture

__all__ = ["SHAPE_NAMES", "Aperture", "ApertureModel", "Disk", "Gaussian", "Heart", "MaskAperture", "Polygon", "Ring",
           "Star", "ViewGrid", "aperture_from_dict", "field_position", "kernel_radius_px", "parse_aperture",
           "pupil_grid", "shape_kernel", "shape_kernel_radius_px", "shape_kernels"]

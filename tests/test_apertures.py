import math

import numpy as np
import pytest

from neuralbokeh.core.apertures import (
    ApertureModel,
    Disk,
    Gaussian,
    Heart,
    MaskAperture,
    Polygon,
    Ring,
    Star,
    ViewGrid,
    aperture_from_dict,
    field_position,
    kernel_radius_px,
    parse_aperture,
    pupil_grid,
    shape_kernel,
)

SHAPES = [Disk(), Polygon(7), Polygon(5, 20.0), Heart(), Ring(0.6), Star(5, 0.45), Gaussian()]


def _heart_area() -> float:
    # area of the implicit heart, by a dense grid (independent of the kernel code), in unit-circle units
    g = np.linspace(-1.6, 1.6, 4001)
    x, y = np.meshgrid(g, g)
    inside = (x * x + y * y - 1) ** 3 - x * x * y**3 <= 0
    return inside.sum() * (g[1] - g[0]) ** 2 / Heart._SCALE**2


# Areas of each shape inscribed in a circle of radius 1, from closed forms.
AREAS = {
    "disk": math.pi,
    "polygon7": 7 / 2 * math.sin(2 * math.pi / 7),
    "polygon5": 5 / 2 * math.sin(2 * math.pi / 5),
    "ring": math.pi * (1 - 0.6**2),
    "star": 5 * 0.45 * math.sin(math.pi / 5),  # 2n triangles of sides 1 and 0.45 at angle pi/n
}


def _area_key(shape):
    return shape.name + (str(shape.blades) if isinstance(shape, Polygon) else "")


@pytest.mark.parametrize("shape", SHAPES, ids=lambda s: s.name)
@pytest.mark.parametrize("d", [0.3, 0.99, 1.0, 1.5, 2.7, 6.0, 17.09, 41.0])
def test_kernels_normalised_and_odd(shape, d):
    k = shape_kernel(shape, d)
    assert k.ndim == 2 and k.shape[0] == k.shape[1] and k.shape[0] % 2 == 1
    assert k.shape[0] == 2 * kernel_radius_px(d) + 1
    assert k.sum() == pytest.approx(1.0, abs=1e-12)
    assert (k >= 0).all()


@pytest.mark.parametrize("shape", SHAPES, ids=lambda s: s.name)
def test_subpixel_diameters_converge_to_delta(shape):
    assert shape_kernel(shape, 0.0).tolist() == [[1.0]]
    assert shape_kernel(shape, 0.9).tolist() == [[1.0]]
    # just above one pixel the mass is still (almost) all in the centre: continuous
    k = shape_kernel(shape, 1.05)
    assert k.shape == (3, 3) and k[1, 1] > 0.95


@pytest.mark.parametrize("shape", [s for s in SHAPES if s.name not in ("heart", "gaussian")] + [Heart()], ids=lambda s: s.name)
def test_area_matches_closed_form(shape):
    d = 61.0
    s = shape_kernel(shape, d)
    area_px = s.sum() / s.max()  # interior pixels have full coverage
    expected = (_heart_area() if shape.name == "heart" else AREAS[_area_key(shape)]) * (d / 2) ** 2
    assert area_px == pytest.approx(expected, rel=0.01)


@pytest.mark.parametrize("shape", SHAPES, ids=lambda s: s.name)
def test_kernel_centred(shape):
    k = shape_kernel(shape, 31.0)
    r = np.arange(k.shape[0]) - k.shape[0] // 2
    assert abs((k.sum(1) * r).sum()) < 0.05 and abs((k.sum(0) * r).sum()) < 0.05


def test_polygon_symmetry_and_rotation():
    k7 = shape_kernel(Polygon(7), 25.0)
    k7r = shape_kernel(Polygon(7, 360.0 / 7), 25.0)
    np.testing.assert_allclose(k7, k7r, atol=1e-12)
    # with a vertex on +u (right), the 7-gon is mirror-symmetric top/bottom, not left/right
    np.testing.assert_allclose(k7, k7[::-1, :], atol=1e-12)
    assert np.abs(k7 - k7[:, ::-1]).max() > 1e-3


def test_heart_points_down():
    k = shape_kernel(Heart(), 41.0)
    rows = np.nonzero(k.sum(1))[0]
    top, bottom = k[rows[0] + 3], k[rows[-1] - 3]
    # near the top the two lobes are wide; near the bottom the tip is narrow
    assert (top > 0).sum() > 2 * (bottom > 0).sum()
    half = k.shape[0] // 2
    assert k[:half].sum() > k[half + 1 :].sum()  # more light in the lobes than in the tip
    np.testing.assert_allclose(k, k[:, ::-1], atol=1e-12)


def test_gaussian_profile():
    k = shape_kernel(Gaussian(0.5), 41.0)
    r = np.arange(41) - 20
    yy, xx = np.meshgrid(r, r, indexing="ij")
    sigma = np.sqrt((k * xx**2).sum())
    # a 2-D Gaussian cut at R = 2 sigma: per-axis variance sigma^2 (1 - (1 + R^2/2s^2) e^-R^2/2s^2) / (1 - e^-R^2/2s^2)
    e = math.exp(-2.0)
    expected = (41 / 4) * math.sqrt((1 - 3 * e) / (1 - e))
    assert sigma == pytest.approx(expected, rel=2e-3)
    assert k[20, 20] == k.max() and k[20, 0] < 0.2 * k.max()


def test_ring_has_a_hole():
    k = shape_kernel(Ring(0.6), 41.0)
    assert k[20, 20] == 0.0 and k[20, 2] > 0


def test_mask_aperture_matches_disk():
    n = 512
    g = (np.arange(n) + 0.5) / n * 2 - 1
    disk = (g[None, :] ** 2 + g[:, None] ** 2 <= 1).astype(float)
    k_mask = shape_kernel(MaskAperture(disk), 21.0)
    k_disk = shape_kernel(Disk(), 21.0)
    assert np.abs(k_mask - k_disk).sum() < 0.01


def test_mask_aperture_validation():
    with pytest.raises(ValueError, match="2-D"):
        MaskAperture(np.ones((3, 3, 3)))
    with pytest.raises(ValueError, match=r"in \[0.0, 1.0\]"):
        MaskAperture(np.full((3, 3), 2.0))
    with pytest.raises(ValueError, match="all zero"):
        MaskAperture(np.zeros((3, 3)))


def test_a_light_field_s_views_are_points_of_the_pupil_splatted_bilinearly():
    weights = np.zeros((3, 3))
    weights[0, 2], weights[1, 1] = 1.0, 0.5  # top-right view and the centre view
    views = ViewGrid(weights)
    # CoC 10.5 px: the views' cells are 3.5 px apart, the top-right one at (+3.5, -3.5) px
    k = shape_kernel(views, 10.5)
    h = k.shape[0] // 2
    assert h == kernel_radius_px(10.5) + 1 and k.sum() == pytest.approx(1.0)
    want = np.zeros_like(k)
    want[h, h] = 1.0 / 3.0
    want[h - 4 : h - 2, h + 3 : h + 5] = 0.25 * 2.0 / 3.0  # half-way between 4 pixels: a quarter each
    np.testing.assert_allclose(k, want, atol=1e-12)
    pts, t = pupil_grid(views, 16)  # ray tracers take the views themselves, whatever the grid
    np.testing.assert_allclose(pts, [[2.0 / 3.0, 2.0 / 3.0], [0.0, 0.0]])
    np.testing.assert_allclose(t, [1.0, 0.5])
    assert views.transmission(np.array([0.9]), np.array([0.4]))[0] == 1.0  # pictures: each view its cell
    model = ApertureModel(views, cat_eye=0.9)  # at the right edge the circle (centre u = -0.9) passes the centre view only
    corner = model.kernels(10.5, (1.0, 0.0))[1]
    assert corner[h, h] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="square"):
        ViewGrid(np.ones((2, 3)))
    with pytest.raises(ValueError, match="all zero"):
        ViewGrid(np.zeros((3, 3)))


def test_cat_eye_centre_unchanged_corner_tangential():
    model = ApertureModel(Disk(), cat_eye=0.8)
    centre = model.kernels(31.0, (0.0, 0.0))[1]
    np.testing.assert_allclose(centre, shape_kernel(Disk(), 31.0), atol=1e-12)
    s = 1 / math.sqrt(2)
    corner = model.kernels(31.0, (s, s))[1]  # bottom-right corner
    unnorm_area = corner.sum() / corner.max()
    assert unnorm_area < 0.7 * math.pi * 15.5**2  # clipped
    # second moments: the long axis is tangential (perpendicular to the radial direction)
    r = np.arange(corner.shape[0]) - corner.shape[0] // 2
    yy, xx = np.meshgrid(r, r, indexing="ij")
    my, mx = (corner * yy).sum(), (corner * xx).sum()
    radial = ((xx - mx) + (yy - my)) / math.sqrt(2)
    tangential = ((xx - mx) - (yy - my)) / math.sqrt(2)
    assert (corner * tangential**2).sum() > 2 * (corner * radial**2).sum()
    # the clipping circle sits towards the image centre (up-left of the kernel centre)
    assert mx < -1 and my < -1


def test_chromatic_channel_scale():
    model = ApertureModel(Disk(), channel_scale=(1.2, 1.0, 0.8))
    k = model.kernels(21.0)
    assert k.shape == (3, 27, 27)  # red: 21 * 1.2 = 25.2 px needs a 27 px kernel
    np.testing.assert_allclose(k.sum(axis=(1, 2)), 1.0)
    support = [(k[c] > 0).sum() for c in range(3)]
    assert support[0] > support[1] > support[2]
    np.testing.assert_allclose(k[1][3:-3, 3:-3], shape_kernel(Disk(), 21.0), atol=1e-12)


def test_field_position():
    assert field_position(0, 0, 101, 201) == pytest.approx((-100 / math.hypot(100, 50), -50 / math.hypot(100, 50)))
    assert field_position(50, 100, 101, 201) == (0.0, 0.0)
    assert math.hypot(*field_position(100, 200, 101, 201)) == pytest.approx(1.0)


@pytest.mark.parametrize("shape", SHAPES + [MaskAperture(np.eye(4)), ViewGrid(np.eye(3) * 0.3)], ids=lambda s: s.name)
def test_dict_round_trip(shape):
    back = aperture_from_dict(shape.to_dict())
    assert back == shape
    model = ApertureModel(shape, 0.5, 1.1, (1.02, 1.0, 0.98))
    assert ApertureModel.from_dict(model.to_dict()) == model


def test_parse_aperture():
    assert parse_aperture("disk") == Disk()
    assert parse_aperture("polygon:7") == Polygon(7)
    assert parse_aperture("polygon:6:15") == Polygon(6, 15.0)
    assert parse_aperture("ring:0.4") == Ring(0.4)
    assert parse_aperture("star:6:0.5") == Star(6, 0.5)
    assert parse_aperture("heart") == Heart()
    assert parse_aperture("gaussian:0.4") == Gaussian(0.4)
    mask = np.ones((4, 4))
    assert parse_aperture("mask:any.png", load_mask=lambda p: mask) == MaskAperture(mask)
    for bad in ["hexagon", "polygon", "polygon:2", "ring:1.5", "disk:3", "mask:x.png"]:
        with pytest.raises(ValueError, match="aperture spec"):
            parse_aperture(bad)


def test_model_validation():
    with pytest.raises(ValueError, match="cat_eye must be < 1 \\+ vignetting_radius"):
        ApertureModel(Disk(), cat_eye=2.5)
    with pytest.raises(ValueError, match="cat_eye"):
        ApertureModel(Disk(), cat_eye=-0.1)
    with pytest.raises(ValueError, match="channel_scale"):
        ApertureModel(Disk(), channel_scale=(1.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="3 values"):
        ApertureModel(Disk(), channel_scale=(1.0, 1.0))
    with pytest.raises(ValueError, match="CoC diameter"):
        shape_kernel(Disk(), -1.0)

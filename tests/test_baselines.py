"""The paper-sourced classical baselines: each on a point light and on a step edge at a depth
discontinuity, against the reference scatter or the slow per-pixel Gaussian spread."""

import subprocess
import sys

import numpy as np
import pytest
import torch

from neuralbokeh.core.apertures import ApertureModel, Disk, MaskAperture, Polygon
from neuralbokeh.render import scatter_defocus
from neuralbokeh.render.baselines import gather_defocus, pseudo_ray_trace
from neuralbokeh.render.buckets import bucket_gather
from neuralbokeh.render.lens_trace import hidden_layer, lens_ray_trace, refract, singlet_zone_profile
from neuralbokeh.render.pyramid import gaussian_spread_reference, pyramid_spread, quadtree_sites, tensor_filter

SIZE = 48
HEPTAGON = ApertureModel(Polygon(7))


def _point(coc_px: float, background: float = 0.0, size: int = SIZE):
    x = torch.full((1, 3, size, size), background, dtype=torch.float64)
    x[..., size // 2, size // 2 - 4] = 1000.0
    return x, torch.full((1, 1, size, size), coc_px, dtype=torch.float64)


def _step(left_coc: float, right_coc: float):
    """Bright left half (5.0), dark right half (0.2), each at its own CoC."""
    x = torch.full((1, 3, SIZE, SIZE), 0.2, dtype=torch.float64)
    x[..., : SIZE // 2] = 5.0
    c = torch.full((1, 1, SIZE, SIZE), right_coc, dtype=torch.float64)
    c[..., : SIZE // 2] = left_coc
    return x, c


def _moments(img: torch.Tensor):
    o = img[0, 0]
    yy, xx = torch.meshgrid(torch.arange(o.shape[0], dtype=torch.float64), torch.arange(o.shape[1], dtype=torch.float64), indexing="ij")
    m = o.sum()
    my, mx = (o * yy).sum() / m, (o * xx).sum() / m
    return float(m), float(my), float(mx), float((((yy - my) ** 2) * o).sum() / m) ** 0.5


# --- the light-field patent's buckets ---

def test_buckets_point_light_is_the_aperture_and_keeps_flux():
    x, c = _point(9.0, background=0.1)
    out = bucket_gather(x, c, HEPTAGON)
    assert float((out - scatter_defocus(x, c, HEPTAGON)).abs().max()) < 1e-9  # one depth: all in the mid bucket
    assert float(out.sum()) == pytest.approx(float(x.sum()), rel=1e-9)


@pytest.mark.parametrize("left, right", [(0.0, 9.0), (-9.0, 0.0)])
def test_buckets_step_edge_matches_the_occlusion_aware_scatter(left, right):
    x, c = _step(left, right)
    # the patent fills what a blurred foreground uncovers with the foreground's own colours
    # (normalising), the scatter's fill="normalize"
    out, ref = bucket_gather(x, c, HEPTAGON), scatter_defocus(x, c, HEPTAGON, fill="normalize")
    assert float((out - ref).abs().max()) < 1e-9
    if left == 0.0:  # sharp bright foreground, blurred background: nothing leaks behind the edge
        assert torch.allclose(out[..., SIZE // 2 :], x[..., SIZE // 2 :], atol=1e-12)
        assert float(gather_defocus(x, c, HEPTAGON)[0, 0, 20, SIZE // 2 + 1]) > 1.0  # where the naive gather leaks
    else:  # blurred foreground spills over the sharp background (near bucket first)
        assert float(out[0, 0, 20, SIZE // 2 + 1]) > 1.0


def test_buckets_saturation_drops_hidden_samples():
    # A dark foreground (CoC -12, radius 6) before a bright, more blurred background (CoC 20,
    # radius 10): 8 px inside the foreground its own samples already sum to one, so the
    # background samples that reach it (a spread would add them) are dropped as hidden.
    x, c = _step(20.0, -12.0)
    # bright (5.0) background on the left, dark (0.2) foreground on the right
    p = SIZE // 2 + 8
    out = bucket_gather(x, c, HEPTAGON)
    assert float(out[0, 0, 20, p]) == pytest.approx(0.2, abs=1e-12)
    assert float(pyramid_spread(x, c)[0, 0, 20, p]) > 0.25  # without occlusion the background shows through
    assert float(out[0, 0, 20, SIZE // 2 + 1]) > 0.25  # at the rim the background still fills what is left
    with pytest.raises(ValueError, match="spread"):
        bucket_gather(x, c, HEPTAGON, spread=0.0)


# --- Kosloff and Barsky: pyramid spreading and the tensor filter ---

@pytest.mark.parametrize("coc_px", [0.0, 5.0, 9.0, 17.0, 30.0])
def test_pyramid_point_light_against_the_per_pixel_spread(coc_px):
    x, c = _point(coc_px)
    got, ref = pyramid_spread(x, c), gaussian_spread_reference(x, c)
    m, my, mx, s = _moments(got)
    rm, rmy, rmx, rs = _moments(ref)
    assert m == pytest.approx(_moments(ref)[0], rel=5e-3)  # flux kept (what crosses the frame's edge is lost by both)
    assert abs(my - rmy) < 0.1 and abs(mx - rmx) < 0.1  # subpixel placement on coarse levels
    assert s == pytest.approx(rs, rel=0.1, abs=1e-9)  # the collapsed PSF has the intended size
    assert float((got - ref).abs().max()) <= 0.15 * float(ref.max())


@pytest.mark.parametrize("left, right", [(0.0, 9.0), (-9.0, 0.0), (-12.0, 6.0)])
def test_pyramid_step_edge_against_the_per_pixel_spread(left, right):
    x, c = _step(left, right)
    got, ref = pyramid_spread(x, c), gaussian_spread_reference(x, c)
    inner = (slice(None), slice(None), slice(8, 40), slice(8, 40))
    assert float((got - ref)[inner].abs().max()) < 0.1  # of a 5.0 - 0.2 edge
    if left == 0.0:  # no occlusion in a spread: the blurred background bleeds over the sharp edge
        assert float(got[0, 0, 20, SIZE // 2 - 1]) > 5.0 + 0.05
        assert float((got[..., :8] - x[..., :8]).abs().max()) < 1e-6  # in focus, beyond the spread's reach: untouched
    with pytest.raises(ValueError, match="taps must be odd"):
        pyramid_spread(x, c, taps=6)


@pytest.mark.parametrize("coc_px", [5.0, 9.0, 17.0])
def test_tensor_filter_point_light(coc_px):
    x, c = _point(coc_px)
    m, my, mx, s = _moments(tensor_filter(x, c))
    _, rmy, rmx, rs = _moments(gaussian_spread_reference(x, c))
    assert m == pytest.approx(1000.0, rel=1e-3)
    assert abs(my - rmy) < 0.05 and abs(mx - rmx) < 0.05
    assert s == pytest.approx(rs, rel=0.05)


def test_tensor_filter_step_edge_and_quadtree_sites():
    x, c = _step(0.0, 9.0)  # sigma 2.25 on the right
    sites = quadtree_sites(0.25 * c[0, 0])
    assert sum(float(s[:, 3].sum()) for s in sites) == SIZE * SIZE  # the leaves tile the image once
    assert [len(s) for s in sites] == [SIZE * SIZE // 2, (SIZE // 2) * (SIZE // 4)]  # 2x2 leaves where blurred
    out, ref = tensor_filter(x, c), gaussian_spread_reference(x, c)
    assert torch.equal(out[..., :12], x[..., :12])  # in focus, out of the sites' reach: one site per pixel, an identity
    far = (slice(None), slice(None), slice(16, 32), slice(33, 39))  # 4 sigma from the edge and the frame
    assert float(((out - ref)[far]).abs().max()) < 0.01
    assert float(out[0, 0, 20, SIZE // 2 + 1]) > 0.5  # a gather: the sharp bright side leaks into the blur
    uniform = tensor_filter(*_point(0.0, background=0.3))
    assert torch.equal(uniform, _point(0.0, background=0.3)[0])


# --- Lee, Eisemann and Seidel: layered ray tracing through a spherical lens ---

def test_snell_refraction_and_singlet_profile():
    d = np.array([[np.sin(0.3), np.cos(0.3)]])
    out = refract(d, np.array([[0.0, -1.0]]), 1.0 / 1.5)
    assert np.sin(0.3) == pytest.approx(1.5 * out[0, 0] / np.linalg.norm(out[0]))
    rho = np.linspace(0, 1, 11)
    g = singlet_zone_profile(rho)
    assert g[0] == pytest.approx(0.0, abs=1e-6) and g[-1] == pytest.approx(1.0)
    assert np.all(np.diff(g) > 0) and np.max(np.abs(g - rho**2)) < 0.05  # third order: ~rho^2 at f/2
    fast = singlet_zone_profile(rho, f_number=1.2)
    assert np.max(np.abs(fast - rho**2)) > np.max(np.abs(g - rho**2))  # higher orders grow with the aperture
    with pytest.raises(ValueError, match="bending"):
        singlet_zone_profile(rho, bending=1.0)


def _rim_to_centre(img: np.ndarray) -> float:
    cy, cx = SIZE // 2, SIZE // 2 - 4
    yy, xx = np.mgrid[:SIZE, :SIZE]
    rad = np.hypot(yy - cy, xx - cx)
    rmax = rad[img > 0].max()
    return float(img[(rad >= 0.75 * rmax) & (img > 0)].mean() / img[rad <= 0.4 * rmax].mean())


def test_lens_trace_point_light_and_spherical_aberration():
    ratios = {}
    for sa in (0.0, 8.0):
        for coc in (-16.0, 16.0):
            x, c = _point(coc)
            out = lens_ray_trace(x, c, ApertureModel(Disk()), spherical_aberration_px=sa, grid=24)
            assert float(out[0, 0].sum()) == pytest.approx(1000.0, rel=1e-12)  # every ray finds the point once
            ratios[sa, coc] = _rim_to_centre(out[0, 0].numpy())
    assert ratios[0.0, -16.0] == pytest.approx(ratios[0.0, 16.0])  # thin lens: point-symmetric bokeh
    # under-corrected: bright rim in front of the focus, bright centre behind it
    assert ratios[8.0, -16.0] > 1.5 * ratios[0.0, -16.0]
    assert ratios[8.0, 16.0] < 0.85 * ratios[0.0, 16.0]
    x, c = _point(9.0, background=0.1)
    out, ref = lens_ray_trace(x, c, HEPTAGON, grid=12), scatter_defocus(x, c, HEPTAGON)
    lit, want = int(((out[0, 0] - 0.1) > 1.0).sum()), int(((ref[0, 0] - 0.1) > 1.0).sum())
    assert 0.7 * want <= lit <= want  # the heptagon, one ray per pupil sample


def test_lens_trace_step_edges_and_the_hidden_layer():
    x, c = _step(0.0, 9.0)  # sharp bright foreground, blurred dark background
    out = lens_ray_trace(x, c, HEPTAGON, grid=12)
    assert torch.equal(out[..., : SIZE // 2], x[..., : SIZE // 2])  # in focus: not traced at all
    assert torch.allclose(out[..., SIZE // 2 + 2 :], x[..., SIZE // 2 + 2 :])  # no foreground behind the edge
    x, c = _step(-9.0, 0.0)  # blurred bright foreground over a sharp dark background
    one, two = lens_ray_trace(x, c, HEPTAGON, grid=12, layers=1), lens_ray_trace(x, c, HEPTAGON, grid=12, layers=2)
    assert float(one[0, 0, 20, SIZE // 2 + 1]) > 1.0  # the foreground spills over
    # rays at the foreground's rim pass it and meet the hidden background only with the second layer
    assert float(one[0, 0, 20, SIZE // 2 - 1]) == pytest.approx(5.0)
    assert 0.2 < float(two[0, 0, 20, SIZE // 2 - 1]) < 4.5
    col, lc = hidden_layer(x[0], c[0, 0])
    band = ~torch.isnan(lc)
    assert bool(band[:, SIZE // 2 - 5 : SIZE // 2].all()) and not bool(band[:, SIZE // 2 :].any())
    assert torch.allclose(col[:, band], torch.full_like(col[:, band], 0.2)) and bool((lc[band] == 0.0).all())
    with pytest.raises(ValueError, match="layers must be 1 or 2"):
        lens_ray_trace(x, c, layers=3)


@pytest.mark.parametrize("method", ["pseudo", "lens"])
def test_ray_tracers_keep_the_aperture_upright(method):
    # A triangle with a vertex up: behind the focus its bokeh is upright (the kernels'
    # convention, which the scatter renderer applies); the ray tracers must agree.
    from neuralbokeh.render.baselines import pseudo_ray_trace

    tri = ApertureModel(Polygon(3, rotation_deg=90.0))
    x, c = _point(15.0)
    ref = scatter_defocus(x, c, tri)[0, 0]
    out = (pseudo_ray_trace(x, c, tri, grid=24) if method == "pseudo" else lens_ray_trace(x, c, tri, grid=24))[0, 0]
    cy, cx = SIZE // 2, SIZE // 2 - 4
    win = (slice(cy - 9, cy + 10), slice(cx - 9, cx + 10))
    upright = float(np.corrcoef(out[win].flatten().numpy(), ref[win].flatten().numpy())[0, 1])
    flipped = float(np.corrcoef(out[win].flatten().numpy(), ref[win].flip(0).flatten().numpy())[0, 1])
    assert upright > 0.8 and upright > flipped + 0.2, (upright, flipped)


# --- one pupil for every renderer ---

SQUARE = ApertureModel(MaskAperture(np.ones((8, 8))))


def _support_iou(img: np.ndarray, coc_px: float, centre: tuple[int, int]) -> float:
    """IoU of the lit pixels (above a quarter of the brightest) with the square of side
    ``coc_px`` centred on the point (pixel centres inside it)."""
    yy, xx = np.mgrid[: img.shape[0], : img.shape[1]]
    square = (np.abs(yy - centre[0]) <= coc_px / 2) & (np.abs(xx - centre[1]) <= coc_px / 2)
    lit = img > 0.25 * img.max()
    return float((lit & square).sum() / (lit | square).sum())


@pytest.mark.parametrize("method", ["scatter", "gather", "raytrace", "buckets", "lenstrace"])
def test_a_square_aperture_is_a_square_in_every_renderer(method):
    render = {
        "scatter": lambda x, c, ap: scatter_defocus(x, c, ap),
        "gather": lambda x, c, ap: gather_defocus(x, c, ap),
        "raytrace": lambda x, c, ap: pseudo_ray_trace(x, c, ap, grid=32),
        "buckets": lambda x, c, ap: bucket_gather(x, c, ap),
        "lenstrace": lambda x, c, ap: lens_ray_trace(x, c, ap, grid=32),
    }[method]
    coc = 17.0
    x, c = _point(coc)
    centre = (SIZE // 2, SIZE // 2 - 4)
    square = _support_iou(render(x, c, SQUARE)[0, 0].numpy(), coc, centre)
    disk = _support_iou(render(x, c, ApertureModel(Disk()))[0, 0].numpy(), coc, centre)
    assert square >= 0.9 > disk, (square, disk)  # the disk is not mistaken for a square either


@pytest.mark.skipif(sys.platform != "linux", reason="address-space limits and ru_maxrss in KiB are Linux's")
def test_tensor_filter_memory_is_bounded_by_the_chunk_not_the_blur():
    # a noisy CoC ramp out to +-44 px at 512^2: hundreds of thousands of single-pixel sites with wide
    # windows (one window for all of them needed 3.4 GB allocations and 23 GB in all)
    script = (
        "import resource, torch\n"
        "resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))\n"
        "from neuralbokeh.render.pyramid import tensor_filter\n"
        "g = torch.Generator().manual_seed(0)\n"
        "ramp = torch.linspace(-44, 44, 512, dtype=torch.float64)[:, None].expand(512, 512)\n"
        "coc = (ramp + torch.rand(512, 512, generator=g, dtype=torch.float64) * 6 - 3)[None, None].contiguous()\n"
        "out = tensor_filter(torch.rand(1, 3, 512, 512, generator=g, dtype=torch.float64), coc)\n"
        "assert bool(torch.isfinite(out).all())\n"
        "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert int(done.stdout.split()[-1]) < 4 << 20  # peak RSS in KiB, under the 4 GiB address-space cap anyway


def test_tensor_filter_chunks_do_not_change_the_result():
    g = torch.Generator().manual_seed(2)
    x = torch.rand(1, 3, 40, 44, generator=g, dtype=torch.float64)
    c = (torch.rand(1, 1, 40, 44, generator=g, dtype=torch.float64) - 0.5) * 30
    torch.testing.assert_close(tensor_filter(x, c, chunk_taps=500), tensor_filter(x, c, chunk_taps=10**9), atol=1e-12, rtol=0)

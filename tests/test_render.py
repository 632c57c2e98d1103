import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from neuralbokeh.core.apertures import ApertureModel, Disk, Heart, Polygon, Star, shape_kernel
from neuralbokeh.core.optics import ThinLens
from neuralbokeh.ops.fftconv import fft_convolve2d
from neuralbokeh.ops.holes import hidden_background
from neuralbokeh.render import render_defocus, scatter_defocus, scatter_layers
from neuralbokeh.render.reference import reference_scatter_defocus, reference_scatter_layers
from neuralbokeh.render.scatter import auto_field_grid

LENS = ThinLens(50.0, 1.4, 36.0)
TELE = ThinLens(200.0, 2.8, 36.0)  # CoC of 15..40 px on the tiny test images


def _layer_scene(h=16, w=16, seed=0):
    g = np.random.default_rng(seed)
    alphas = np.zeros((3, 1, h, w))
    alphas[0] = 1.0
    alphas[1, :, 2:10, 1:12] = 1.0
    alphas[1, :, 2:10, 12] = 0.5  # an anti-aliased edge
    alphas[2, :, 8:15, 6:15] = 0.7
    colors = g.random((3, 3, h, w)) * alphas
    colors[2, :, 11, 9] = 50.0 * alphas[2, :, 11, 9]  # a highlight
    return colors, alphas


# --- FFT convolution --------------------------------------------------------------------------


def test_fft_convolve_equals_direct_convolution():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 3, 20, 23, dtype=torch.float64, generator=g)
    k = torch.rand(1, 3, 7, 5, dtype=torch.float64, generator=g)
    direct = F.conv2d(x, k.flip(-1, -2).transpose(0, 1), padding=(3, 2), groups=3)
    torch.testing.assert_close(fft_convolve2d(x, k), direct, atol=1e-12, rtol=0)


def test_fft_convolve_gradients():
    g = torch.Generator().manual_seed(1)
    x = torch.rand(1, 2, 6, 7, dtype=torch.float64, generator=g, requires_grad=True)
    k = torch.rand(1, 2, 3, 3, dtype=torch.float64, generator=g, requires_grad=True)
    assert torch.autograd.gradcheck(fft_convolve2d, (x, k))


def test_fft_convolve_full_mode_and_fast_lengths():
    from neuralbokeh.ops.fftconv import next_fast_len

    assert [next_fast_len(n) for n in (1, 11, 13, 97, 121)] == [1, 12, 14, 98, 125]
    x = torch.zeros(1, 1, 5, 6, dtype=torch.float64)
    x[0, 0, 0, 0] = 1.0
    k = torch.arange(9, dtype=torch.float64).reshape(1, 1, 3, 3)
    full = fft_convolve2d(x, k, mode="full")
    assert full.shape == (1, 1, 7, 8)
    torch.testing.assert_close(full[0, 0, :3, :3], k[0, 0], atol=1e-12, rtol=0)


def test_fft_convolve_rejects_even_kernels():
    with pytest.raises(ValueError, match="odd"):
        fft_convolve2d(torch.zeros(1, 1, 8, 8), torch.zeros(1, 1, 4, 4))
    with pytest.raises(ValueError, match="kernel"):
        fft_convolve2d(torch.zeros(1, 2, 8, 8), torch.zeros(1, 3, 3, 3))


# --- exactness against the literal reference ----------------------------------------------------


@pytest.mark.parametrize(
    "aperture",
    [ApertureModel(), ApertureModel(Heart(), channel_scale=(1.15, 1.0, 0.85))],
    ids=["disk", "heart-chromatic"],
)
def test_layers_match_reference(aperture):
    colors, alphas = _layer_scene()
    cocs = [4.3, -2.2, -6.6]
    ref = reference_scatter_layers(colors, alphas, cocs, aperture)
    fast = scatter_layers(torch.from_numpy(colors), torch.from_numpy(alphas), cocs, aperture).numpy()
    np.testing.assert_allclose(fast, ref, atol=1e-10, rtol=0)


@pytest.mark.parametrize("occlusion, fill", [("over", "normalize"), ("surface", "normalize"), ("surface", "background")])
def test_defocus_from_coc_map_matches_reference(occlusion, fill):
    g = np.random.default_rng(3)
    h, w = 14, 15
    aif = g.random((3, h, w)) * 2
    coc = np.tile(np.linspace(-6.0, 5.0, w), (h, 1))
    coc[3:8, 4:9] = -3.1  # a nearer block
    x, c = torch.from_numpy(aif)[None], torch.from_numpy(coc)[None, None]
    background = hidden_background(x, c)[0].numpy() if fill == "background" else None
    ref = reference_scatter_defocus(aif, coc, ApertureModel(Polygon(6)), 0.5, 4.0 if occlusion == "surface" else 0.0, background)
    fast = scatter_defocus(x, c, ApertureModel(Polygon(6)), occlusion=occlusion, fill=fill)
    np.testing.assert_allclose(fast[0].numpy(), ref, atol=1e-10, rtol=0)


def _sloped_foreground_scene(size=48):
    """A sloped textured foreground square (CoC -13.5 .. -10.5 px down the rows, so the depth
    map cuts it into horizontal slices, all of which meet its left and right silhouettes) in
    front of an in-focus textured background that the layers know in full."""
    g = torch.Generator().manual_seed(4)
    bg = torch.rand(1, 3, size, size, dtype=torch.float64, generator=g) * 0.5 + 0.1
    fg = torch.rand(1, 3, size, size, dtype=torch.float64, generator=g) * 0.5 + 1.0
    mask = torch.zeros(1, 1, size, size, dtype=torch.float64)
    mask[..., 14:34, 14:34] = 1.0
    slope = torch.linspace(-13.5, -10.5, size, dtype=torch.float64)[:, None].expand(1, 1, size, size)
    coc = torch.where(mask > 0, slope, torch.zeros_like(slope))
    aif = fg * mask + bg * (1 - mask)
    return aif, coc, bg, fg, mask


def test_continuous_foreground_spills_like_one_surface():
    # The truth: the same slices, each composited over the *complete* background (which the
    # depth map hides); slices of one surface sit side by side and never occlude each other.
    aif, coc, bg, fg, mask = _sloped_foreground_scene()
    idx = torch.round(coc / 0.5)
    fg_levels = [v for v in torch.unique(idx).tolist() if v != 0]
    layers = [(bg, torch.ones_like(mask), 0.0)]
    for v in fg_levels:
        m = (idx == v).double() * mask
        layers.append((fg * m, m, float(coc[m > 0].mean())))
    colours = torch.cat([la[0] for la in layers])
    alphas = torch.cat([la[1] for la in layers])
    # summing the foreground slices (no mutual occlusion) is the one-surface truth: scatter them
    # as one layer per slice onto a black canvas additively, then over the background
    fg_sum = sum(scatter_layers(colours[i : i + 1], alphas[i : i + 1], [layers[i][2]], fill_holes=False) for i in range(1, len(layers)))
    fg_cov = sum(scatter_layers(alphas[i : i + 1].expand(1, 3, -1, -1).contiguous(), alphas[i : i + 1], [layers[i][2]], fill_holes=False)
                 for i in range(1, len(layers)))
    truth = fg_sum + (1 - fg_cov) * bg[0]
    errors = {}
    for name, kw in {"over": dict(occlusion="over", fill="normalize"), "default": {}}.items():
        out = scatter_defocus(aif, coc, **kw)[0]
        errors[name] = float(((out - truth) ** 2).mean().sqrt())
        # just outside the silhouette the foreground's light must lie over the background as
        # much as in the truth (the sharp background showing through is the failure)
        ring = (slice(None), slice(10, 38), slice(34, 40))
        errors[name + " spill"] = float((out[ring] - truth[ring]).abs().mean())
    # exact outside (the background there is visible, so known); inside the silhouette the
    # hidden background is an estimate from around it
    assert errors["default spill"] < 1e-9 < 0.002 < errors["over spill"], errors
    assert errors["default"] < 0.3 * errors["over"], errors


@pytest.mark.parametrize("preserve_uniform", [False, True])
def test_cat_eye_interpolation_converges_to_exact(preserve_uniform):
    # The reference evaluates every pixel's own kernel; the fast path interpolates a grid.
    colors, alphas = _layer_scene(18, 18)
    cocs = [5.2, -3.0, -7.4]
    aperture = ApertureModel(Polygon(7), cat_eye=0.8)
    ref = reference_scatter_layers(colors, alphas, cocs, aperture, preserve_uniform=preserve_uniform)
    errs = []
    for grid in (2, 5, 9, None):
        fast = scatter_layers(
            torch.from_numpy(colors), torch.from_numpy(alphas), cocs, aperture, field_grid=grid, preserve_uniform=preserve_uniform
        )
        errs.append(np.abs(fast.numpy() - ref).mean() / ref.mean())
    assert errs[0] > errs[1] > errs[2]
    assert errs[3] < 6e-3  # the automatic grid: 11 x 11 here


# --- energy ------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "aperture, preserve_uniform",
    [
        (ApertureModel(), False),
        (ApertureModel(Star(), channel_scale=(1.1, 1.0, 0.9)), False),
        (ApertureModel(Polygon(7), cat_eye=0.6), True),
    ],
    ids=["disk", "star-chromatic", "polygon-cateye-preserve-uniform"],
)
def test_uniform_plane_stays_uniform(aperture, preserve_uniform):
    aif = torch.full((1, 3, 40, 48), 0.37)
    steps = 48 if not aperture.spatially_varying else 2  # a CoC ramp, or a two-level step
    ramp = torch.linspace(-15, 15, steps).repeat_interleave(48 // steps).expand(1, 1, 40, 48)
    for coc in (torch.full((1, 1, 40, 48), 13.0), ramp):
        out = scatter_defocus(aif, coc, aperture, preserve_uniform=preserve_uniform)
        assert (out - 0.37).abs().max() < 1e-6


def test_cat_eye_uniform_plane_deviation_is_bounded():
    # Physical scatter: spot centroids move with the clipped pupil, so the light density of a
    # defocused uniform plane changes by about 2 * cat_eye * r / half_diagonal (module doc).
    size, coc, cat_eye = 64, 13.0, 0.6
    aif = torch.full((1, 3, size, size), 1.0, dtype=torch.float64)
    out = scatter_defocus(aif, torch.full((1, 1, size, size), coc, dtype=torch.float64), ApertureModel(Polygon(7), cat_eye=cat_eye))
    predicted = 2 * cat_eye * (coc / 2) / (0.5 * math.hypot(size - 1, size - 1))
    deviation = (out - 1.0).abs().max().item()
    assert 0.2 * predicted < deviation < 1.5 * predicted


def test_flux_preserved_away_from_borders():
    g = torch.Generator().manual_seed(0)
    aif = torch.zeros(1, 3, 64, 64)
    aif[..., 16:48, 16:48] = torch.rand(3, 32, 32, generator=g) * 10
    aif[0, :, 30, 30] = 1000.0
    for aperture in (ApertureModel(Disk()), ApertureModel(Heart()), ApertureModel(Polygon(7), cat_eye=0.6)):
        out = scatter_defocus(aif, torch.full((1, 1, 64, 64), -21.0), aperture)
        rel = (out.sum(dim=(2, 3)) / aif.sum(dim=(2, 3)) - 1).abs().max()
        assert rel < 1e-3
    assert auto_field_grid(ApertureModel(Polygon(7), cat_eye=0.6), 21.0, 64, 64) > 5


@pytest.mark.parametrize("coc", [9.0, -9.0])
def test_a_point_on_the_frame_edge_blurs_as_if_black_lay_beyond(coc):
    """Beyond the frame a layer repeats its edge ring, whose 1 px peaks along the edge are clipped
    (``scatter._pad``): points of 1000 on black on the edges, in a corner and 1 px inside them
    blur as the same points with black beyond the frame (a larger canvas, cropped), to 1e-9 of
    their light: each point's ring pixel drops to its black neighbours'. The mirror this replaced
    doubled the points 1 px inside the edge (1.59x their light), a plain copy laid those on the
    edge out as streaks (2.5-6.3x)."""
    s, m = 48, 12
    points = [(24, 0), (0, 24), (47, 24), (24, 47), (47, 47), (1, 12), (12, 46)]
    aperture = ApertureModel(Polygon(7))
    frame, big = torch.zeros(1, 3, s, s, dtype=torch.float64), torch.zeros(1, 3, s + 2 * m, s + 2 * m, dtype=torch.float64)
    for r, c in points:
        frame[..., r, c] = big[..., r + m, c + m] = 1000.0
    out = scatter_defocus(frame, torch.full((1, 1, s, s), coc, dtype=torch.float64), aperture)
    ref = scatter_defocus(big, torch.full((1, 1, s + 2 * m, s + 2 * m), coc, dtype=torch.float64), aperture)[..., m:-m, m:-m]
    assert float(ref.sum()) > 1000.0  # their light lands in the frame
    assert float((out - ref).abs().sum()) < 1e-9 * 1000.0 * 3 * len(points)


# --- the HDR point -----------------------------------------------------------------------------


def _iou(a, b):
    return (a & b).sum() / (a | b).sum()


@pytest.mark.parametrize("shape", [Disk(), Polygon(7), Heart(), Star()], ids=lambda s: s.name)
@pytest.mark.parametrize("depth", [3.0, 0.9], ids=["behind", "in-front"])
def test_hdr_point_images_as_aperture(shape, depth):
    focus, size = 1.4, 96
    depth_map = torch.full((1, 1, size, size), depth, dtype=torch.float64)
    aif = torch.ones(1, 3, size, size, dtype=torch.float64)
    aif[0, :, 48, 48] = 1000.0
    out = render_defocus(aif, depth_map, TELE, focus, ApertureModel(shape))
    spot = (out[0, 1] - 1.0).numpy()  # the uniform background stays 1 exactly
    coc = TELE.coc_px(depth, focus, size)
    assert 15 < coc < 40
    k = shape_kernel(shape, coc)
    if depth < focus:
        k = k[::-1, ::-1]  # the aperture's image is inverted in front of the focus plane
    r = k.shape[0] // 2
    expected = np.zeros_like(spot)
    expected[48 - r : 48 + r + 1, 48 - r : 48 + r + 1] = k
    assert _iou(spot > 0.5 * spot.max(), expected > 0.5 * expected.max()) >= 0.9
    assert spot.sum() == pytest.approx(999.0, rel=0.01)
    if isinstance(shape, Disk):
        equivalent_diameter = 2 * math.sqrt((spot > 0.5 * spot.max()).sum() / math.pi)
        assert abs(equivalent_diameter - coc) < 1.0
    if isinstance(shape, Heart):  # not point-symmetric: the flip must be visible
        assert _iou(spot > 0.5 * spot.max(), expected[::-1, ::-1] > 0.5 * expected.max()) < 0.8


# --- occlusion ---------------------------------------------------------------------------------


def _two_planes(size=64):
    aif = torch.empty(1, 3, size, size, dtype=torch.float64)
    aif[0, :, :, :] = torch.tensor([0.1, 0.1, 0.5], dtype=torch.float64)[:, None, None]  # background
    aif[0, :, :, : size // 2] = 1.0  # foreground: left half, white
    depth = torch.full((1, 1, size, size), 5.0, dtype=torch.float64)
    depth[..., : size // 2] = 1.0
    return aif, depth


def test_blurred_foreground_spills_over_in_focus_background():
    aif, depth = _two_planes()
    out = render_defocus(aif, depth, TELE, 5.0)
    coc = TELE.coc_px(1.0, 5.0, 64)
    assert coc > 15
    edge = 32
    just_outside = out[0, 0, :, edge + 2]
    assert (just_outside > 0.3).all()  # white light from the foreground covers the background
    far = int(edge + math.ceil(coc / 2) + 1)
    torch.testing.assert_close(out[..., far:], aif[..., far:], atol=1e-9, rtol=0)


def test_blurred_background_never_bleeds_over_in_focus_foreground():
    aif, depth = _two_planes()
    out = render_defocus(aif, depth, TELE, 1.0)
    assert TELE.coc_px(5.0, 1.0, 64) > 15
    torch.testing.assert_close(out[..., :32], aif[..., :32], atol=1e-9, rtol=0)


def test_everything_in_focus_is_identity():
    aif = torch.rand(1, 3, 20, 20) * 100
    out = scatter_defocus(aif, torch.zeros(1, 1, 20, 20))
    assert torch.equal(out, aif)


def test_dtype_preserved():
    aif = torch.rand(2, 3, 16, 16, dtype=torch.float32)
    out = scatter_defocus(aif, torch.full((2, 1, 16, 16), 5.0))
    assert out.dtype == torch.float32 and out.shape == aif.shape


# --- errors ------------------------------------------------------------------------------------


def test_errors_are_named():
    aif = torch.ones(1, 3, 8, 8)
    coc = torch.zeros(1, 1, 8, 8)
    bad = aif.clone()
    bad[0, 1, 2, 3] = -0.5
    with pytest.raises(ValueError, match=r"aif must be finite and >= 0, got -0.5 at pixel \(2, 3\)"):
        scatter_defocus(bad, coc)
    nan = coc.clone()
    nan[0, 0, 4, 4] = float("nan")
    with pytest.raises(ValueError, match=r"coc must be finite px, got nan at pixel \(4, 4\)"):
        scatter_defocus(aif, nan)
    with pytest.raises(ValueError, match=r"aif must have shape \(B 3 H W\)"):
        scatter_defocus(torch.ones(1, 4, 8, 8), coc)
    with pytest.raises(ValueError, match="coc must have shape"):
        scatter_defocus(aif, torch.zeros(1, 1, 8, 9))
    with pytest.raises(ValueError, match="one value per layer"):
        scatter_layers(torch.ones(2, 3, 8, 8), torch.ones(2, 1, 8, 8), [1.0])
    with pytest.raises(ValueError, match="layer coverage"):
        scatter_layers(torch.ones(1, 3, 8, 8), torch.full((1, 1, 8, 8), 1.5), [1.0])
    with pytest.raises(ValueError, match="depth must be > 0"):
        render_defocus(aif, torch.zeros(1, 1, 8, 8), LENS, 2.0)

"""The default (lens) network: what its untrained form must already get right, physically."""

import numpy as np
import pytest
import torch

from neuralbokeh.apertures import ApertureModel, Disk
from neuralbokeh.lensnet import band_diameters, band_gates, bucket_weights
from neuralbokeh.model import ModelConfig, build_model
from neuralbokeh.normalization import Normalization
from neuralbokeh.render import scatter_defocus

NORM = Normalization()
C_MAX = 13.0


def _model(size=48, tile=24, overlap=8, blocks=6, init="disk", **kw):
    torch.manual_seed(0)
    cfg = ModelConfig(image_height=size, image_width=size, blocks=blocks, tile=tile, overlap=overlap,
                      coc_scale_px=C_MAX, pupil_init=init, **kw)
    return build_model(cfg).eval()


def _run(model, linear, coc_px):
    x = torch.cat([NORM.encode(linear), coc_px / C_MAX], 1).float()
    with torch.no_grad():
        return NORM.decode(model(x).double())


def test_gates_are_a_partition_of_unity_and_band_zero_is_in_focus():
    c = torch.linspace(-C_MAX, C_MAX, 1001)
    g = band_gates(c, C_MAX, 6)
    assert torch.allclose(g.sum(-1), torch.ones(1001), atol=1e-6)
    assert torch.all(g[c.abs() <= 1.0, 0] == 1.0)
    d = band_diameters(C_MAX, 6)
    assert d[-1] == pytest.approx(C_MAX) and all(d[n] <= 2 * n + 1 for n in range(7))
    w = bucket_weights(-10.0, torch.tensor([0.0, -10.0, -30.0]), 2.0)  # near, same, far
    assert torch.equal(w[:, 0], torch.tensor([1.0, 0.0, 0.0])) and torch.equal(w[:, 1], torch.tensor([0.0, 1.0, 0.0]))
    assert torch.equal(w[:, 2], torch.tensor([0.0, 0.0, 1.0]))


def test_in_focus_and_uniform_images_come_back_unchanged():
    m = _model()
    g = torch.Generator().manual_seed(1)
    img = 0.18 * torch.exp2(4 * torch.rand(1, 3, 48, 48, generator=g, dtype=torch.float64) - 2)
    sharp = _run(m, img, 0.9 * torch.ones(1, 1, 48, 48, dtype=torch.float64))
    assert torch.allclose(sharp, img, rtol=1e-5)
    flat = torch.full((1, 3, 48, 48), 0.7, dtype=torch.float64)
    coc = (2 * torch.rand(1, 1, 48, 48, generator=g, dtype=torch.float64) - 1) * C_MAX
    assert torch.allclose(_run(m, flat, coc), flat, rtol=1e-5)


def test_point_light_is_the_aperture_at_its_coc_and_keeps_flux():
    m = _model()
    d = float(band_diameters(C_MAX, 6)[5])  # exactly on a band centre
    img = torch.zeros(1, 3, 48, 48, dtype=torch.float64)
    img[..., 20, 27] = 1000.0
    coc = torch.full((1, 1, 48, 48), d, dtype=torch.float64)
    out = _run(m, img, coc)[0, 1] - NORM.decode(NORM.encode(torch.zeros(())))  # remove the black level's round trip
    ref = scatter_defocus(img, coc, ApertureModel(Disk()))[0, 1]
    assert float(out.sum()) == pytest.approx(1000.0, rel=1e-3)  # flux, in linear light
    corr = float((out * ref).sum() / (out.norm() * ref.norm()))
    assert corr > 0.97, corr  # the disk pupil rasterised at the CoC is the disk kernel
    assert float(out[20, 27]) < 0.1 * 1000.0  # spread, not left as a spike


def test_blurred_foreground_spills_over_an_in_focus_background_and_not_the_reverse():
    """The continuous-depth trap: a sloped foreground (many CoC bands) must stay opaque."""
    m = _model(size=64, tile=32, overlap=8)
    img = torch.full((1, 3, 64, 64), 0.05, dtype=torch.float64)
    img[..., :32] = 2.0  # bright foreground on the left
    coc = torch.zeros(1, 1, 64, 64, dtype=torch.float64)
    coc[..., :32] = -torch.linspace(8.0, 12.0, 32, dtype=torch.float64)  # sloped, 8..12 px in front
    out = _run(m, img, coc)
    assert float(out[0, 0, 32, 28]) > 1.9  # the foreground's own interior stays opaque (no see-through)
    assert float(out[0, 0, 32, 34]) > 0.3  # and spills over the in-focus background beside it
    # the reverse: sharp foreground over a blurred background keeps its edge
    coc2 = torch.full((1, 1, 64, 64), 12.0, dtype=torch.float64)
    coc2[..., :32] = 0.0
    out2 = _run(m, img, coc2)
    assert torch.allclose(out2[..., :32], img[..., :32], rtol=1e-5)


def test_bands_no_pixel_uses_are_not_computed_and_inactive_tiles_are_exact():
    m = _model()
    img = torch.full((1, 3, 48, 48), 0.3, dtype=torch.float64)
    img[..., ::7, ::5] = 50.0
    coc = torch.zeros(1, 1, 48, 48, dtype=torch.float64)
    d = band_diameters(C_MAX, 6)
    coc[:, :, 24:, :] = float(d[3] + d[4]) / 2  # between bands 3 and 4, behind, in the lower tiles only
    x = torch.cat([NORM.encode(img), coc / C_MAX], 1).float()
    with torch.no_grad():
        full = m(x)
        assert m.last_convolutions == 4  # bands 3 and 4, behind, by the 2 tiles whose cores hold them: 4 of 48
        active = torch.tensor([False, False, True, True])  # the upper tiles' windows stay sharp
        coc[:, :, 24:32, :] = 0.0
        x = torch.cat([NORM.encode(img), coc / C_MAX], 1).float()
        assert torch.allclose(m(x, tile_active=active), m(x), atol=1e-6)
    assert torch.isfinite(full).all()


def test_trains_towards_a_lens_it_was_not_started_from(tmp_path):
    """A Gaussian start learns a 7-blade cat-eye lens from a few samples: loss falls."""
    from neuralbokeh.apertures import Polygon

    torch.manual_seed(0)
    lens = ApertureModel(Polygon(7), cat_eye=0.5)
    g = torch.Generator().manual_seed(3)
    img = 0.18 * torch.exp2(6 * torch.rand(2, 3, 48, 48, generator=g, dtype=torch.float64) - 3)
    img[..., 5::9, 4::9] = 30.0
    coc = torch.full((2, 1, 48, 48), 11.0, dtype=torch.float64)
    coc[1] = -11.0
    target = NORM.encode(scatter_defocus(img, coc, lens)).float()
    m = _model(init="gaussian").train()
    x = torch.cat([NORM.encode(img), coc / C_MAX], 1).float()
    opt = torch.optim.Adam(m.parameters(), lr=0.05)
    losses = []
    for _ in range(25):
        opt.zero_grad()
        loss = torch.nn.functional.mse_loss(m(x), target)
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert np.isfinite(losses).all() and losses[-1] < 0.6 * losses[0], losses


def test_tile_corrections_learn_slower_than_the_lens_wide_pupil():
    from neuralbokeh.training.loop import param_groups

    m = _model()
    scale = {id(p): g["lr_scale"] for g in param_groups(m, "fan_in", 0.25) for p in g["params"]}
    assert scale[id(m.pupil_tile)] == 0.25 and scale[id(m.pupil_shared)] == 1.0
    assert float(m.pupil_tile.abs().max()) == 0.0  # every tile starts as the lens-wide pupil

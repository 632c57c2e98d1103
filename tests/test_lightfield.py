"""Light fields -> triples: shift-and-add refocus, its signs, its aperture and CoC against the
package's own scatter and lens, the CLI end to end, and the shared HCI scene."""

import numpy as np
import pytest
import torch

from data_tools.lightfield import (
    build_scene,
    discrete_aperture,
    estimate_signs,
    load_disparity,
    load_views,
    main,
    refocus,
    view_disagreement,
    view_offsets,
    view_weights,
)
from neuralbokeh.core.apertures import ApertureModel, parse_aperture
from neuralbokeh.data.check import check_scene
from neuralbokeh.data.dataset import load_scene
from neuralbokeh.render import scatter_defocus

N, SIGNS = 5, (-1, 1)


def _plane(disparity: int, size=(40, 48), signs=SIGNS, seed=0) -> np.ndarray:
    """An N x N light field of one textured fronto-parallel plane of integer disparity (views
    are exact circular shifts of the texture)."""
    tex = np.random.default_rng(seed).uniform(0.05, 1.0, (*size, 3)).astype(np.float32)
    du, dv = view_offsets(N)
    return np.stack([np.stack([np.roll(tex, (int(signs[1] * disparity * dv[r, c]), int(signs[0] * disparity * du[r, c])),
                                       axis=(0, 1)) for c in range(N)]) for r in range(N)])


def test_all_ones_weights_are_the_plain_mean_of_shifted_views():
    views = _plane(3)
    du, dv = view_offsets(N)
    d0 = 1
    want = np.mean([np.roll(views[r, c], (-int(SIGNS[1] * d0 * dv[r, c]), -int(SIGNS[0] * d0 * du[r, c])), axis=(0, 1))
                    for r in range(N) for c in range(N)], axis=0)
    got = refocus(views, float(d0), SIGNS)
    m = N // 2 * d0  # the border, where some shifted views fall outside and are left out
    np.testing.assert_allclose(got[m:-m, m:-m], want[m:-m, m:-m], rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(refocus(views, 3.0, SIGNS), views[N // 2, N // 2], rtol=1e-6)  # in focus: the centre view


@pytest.mark.parametrize("side", [1, -1])  # the plane behind the focus (CoC > 0) and in front of it (CoC < 0)
@pytest.mark.parametrize("step", [0.5, 1.0, 2.5])  # the views' shifts (px) from one to the next: CoC = N step
def test_one_plane_refocused_is_the_package_s_scatter_with_the_discrete_aperture(side, step):
    # from a pixel apart the refocus is N x N copies of the image: the views are points of the
    # pupil, not cells of it (a mask of cells is exact only at a step of 1 px)
    views = _plane(2, size=(56, 64))
    aperture = ApertureModel(parse_aperture("heart"))  # not symmetric: orientation and the sign both show
    weights = view_weights(N, SIGNS, aperture)
    assert 0 < (weights > 0).sum() < N * N
    got = refocus(views, 2.0 + side * step, SIGNS, weights)
    aif = torch.from_numpy(views[N // 2, N // 2]).permute(2, 0, 1)[None].double()
    coc = torch.full((1, 1, *aif.shape[2:]), N * side * step, dtype=torch.float64)
    want = scatter_defocus(aif, coc, discrete_aperture(weights, SIGNS))[0].permute(1, 2, 0).numpy()
    m = int(N // 2 * (2 + step)) + N + 2  # away from the border: views shifted in from outside are left out there
    np.testing.assert_allclose(got[m:-m, m:-m], want[m:-m, m:-m], rtol=1e-6, atol=1e-7)
    wrong = scatter_defocus(aif, -coc, discrete_aperture(weights, SIGNS))[0].permute(1, 2, 0).numpy()
    assert np.abs(got - wrong)[m:-m, m:-m].max() > 0.05  # the other sign is another image


def test_the_signs_are_found_from_the_views():
    for signs in ((1, 1), (-1, 1), (1, -1)):
        views = _plane(2, signs=signs, seed=3)
        found, scores = estimate_signs(views, np.full(views.shape[2:4], 2.0, np.float32))
        assert found == signs and scores[found] < 1e-3 * min(v for k, v in scores.items() if k != found)


def _two_planes(tmp_path):
    """A near square (disparity 2) over a far plane (disparity -1), views as a .npy stack."""
    far, near = _plane(-1, seed=1), _plane(2, seed=2)
    mask = np.zeros((40, 48), bool)
    mask[12:28, 14:34] = True
    du, dv = view_offsets(N)
    views = far.copy()
    for r in range(N):
        for c in range(N):
            m = np.roll(mask, (int(SIGNS[1] * 2 * dv[r, c]), int(SIGNS[0] * 2 * du[r, c])), axis=(0, 1))
            views[r, c][m] = near[r, c][m]
    disparity = np.where(mask, 2.0, -1.0).astype(np.float32)
    np.save(tmp_path / "views.npy", views)
    np.save(tmp_path / "disp.npy", disparity)
    return views, disparity


def test_cli_writes_a_scene_the_package_s_lens_and_check_agree_with(tmp_path, capsys):
    views, disparity = _two_planes(tmp_path)
    args = [str(tmp_path / "views.npy"), "--disparity", str(tmp_path / "disp.npy"), "--out", str(tmp_path / "ds"),
            "--focus-disparities=-1,0.5,2"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "view signs   (-1, 1)" in out
    mismatch = float(out.split("largest mismatch ")[1].split()[0])
    assert mismatch <= 1e-3
    scene = load_scene(tmp_path / "ds" / "views")
    assert scene["meta"]["aperture"] is None and check_scene(tmp_path / "ds" / "views") == []
    np.testing.assert_allclose(scene["aif"], views[N // 2, N // 2], rtol=1e-6)
    for k, d0 in enumerate([-1.0, 0.5, 2.0][::-1]):  # written near focus last: by focus distance, far first
        np.testing.assert_allclose(scene["coc"][k], N * (d0 - disparity), atol=1e-3)
    with pytest.raises(SystemExit, match="already exists"):
        main(args)
    # a synthetic aperture with cat-eye: declared as the views' discrete aperture, and another image
    assert main(args + ["--name", "disk", "--aperture", "disk", "--cat-eye", "0.5"]) == 0
    disk = load_scene(tmp_path / "ds" / "disk")
    assert disk["meta"]["aperture"]["cat_eye"] == 0.5 and check_scene(tmp_path / "ds" / "disk") == []
    assert np.abs(disk["defocus"][0] - scene["defocus"][0]).max() > 0.01


def test_bad_inputs_are_one_line_errors(tmp_path):
    np.save(tmp_path / "even.npy", np.zeros((4, 6, 6, 3), np.float32))
    with pytest.raises(ValueError, match="N odd"):
        load_views(tmp_path / "even.npy")
    np.save(tmp_path / "eight.npy", np.zeros((8, 6, 6, 3), np.float32))
    with pytest.raises(ValueError, match="8 views is not an N x N grid"):
        load_views(tmp_path / "eight.npy")
    views, disparity = _two_planes(tmp_path)
    with pytest.raises(ValueError, match="disparity map is 47x40, the views 48x40"):
        build_scene(views, disparity[:, :47], tmp_path / "x")
    flat = _plane(0)  # every view the same: nothing tells the signs
    with pytest.raises(ValueError, match="the views do not tell which way points move between them"):
        estimate_signs(flat, np.zeros(flat.shape[2:4], np.float32))
    assert build_scene(flat, np.linspace(0, 1, 48 * 40, dtype=np.float32).reshape(40, 48), tmp_path / "given",
                       signs=(1, 1))["signs"] == (1, 1)  # given signs are not questioned
    with pytest.raises(SystemExit, match="--cat-eye vignettes a synthetic aperture"):
        main([str(tmp_path / "views.npy"), "--disparity", str(tmp_path / "disp.npy"), "--out", str(tmp_path / "y"),
              "--cat-eye", "0.3"])


@pytest.mark.shared_data
def test_the_hci_scene_loads_upright_and_its_signs_are_clear(shared_data):
    """The views agree best, warped by the disparity map, with the signs found by hand on
    patches (a point moves against the view index on both axes), and with the PFM read top row
    first. The scene's fine stripes make the vertical match weaker than the horizontal one."""
    folder = shared_data / "light_fields" / "hci_backgammon"
    disparity = load_disparity(folder / "gt_disp_lowres.pfm")
    views = load_views(folder)
    assert views.shape == (9, 9, 512, 512, 3) and disparity.shape == (512, 512)
    small = views[::2, ::2, 128:384, 128:384]  # 5 x 5 views of the middle, to keep the test short
    signs, scores = estimate_signs(small, disparity[128:384, 128:384] * 2)  # every second view: twice the disparity
    assert signs == (-1, -1) and scores[signs] < 0.8 * min(v for k, v in scores.items() if k != signs), scores
    upside_down = np.ascontiguousarray(disparity[::-1][128:384, 128:384] * 2)  # the PFM's rows as stored
    flipped = [view_disagreement(small, upside_down, (sx, sy)) for sx in (1, -1) for sy in (1, -1)]
    assert min(flipped) > 1.3 * scores[signs]


def test_scenes_of_one_camera_share_a_lens_through_its_disparity_to_depth(tmp_path):
    from neuralbokeh.data.check import shared_lens_problems

    _two_planes(tmp_path)
    base = [str(tmp_path / "views.npy"), "--disparity", str(tmp_path / "disp.npy"), "--out", str(tmp_path / "ds"),
            "--disparity-to-depth", "-3", "6"]
    assert main(base + ["--name", "a", "--focus-disparities=-1,2"]) == 0
    assert main(base + ["--name", "b", "--focus-disparities=0.5", "--depth-range", "1", "9"]) == 0  # the mapping wins
    assert shared_lens_problems([tmp_path / "ds" / "a", tmp_path / "ds" / "b"]) == []
    assert check_scene(tmp_path / "ds" / "b") == []
    with pytest.raises(ValueError, match="every disparity at or above ALPHA"):
        main(base[:-2] + ["-0.5", "6", "--name", "c"])

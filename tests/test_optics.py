import math

import numpy as np
import pytest
import torch

from neuralbokeh.core.optics import ThinLens, blocks_for_coc, focus_sweep_m, max_coc_px

LENS = ThinLens(50.0, 2.0, 36.0)


def test_hand_computed_value():
    # 50 mm f/2 -> a = 25 mm; focus 2 m: d_s = 50*2000/1950 = 51.28205 mm.
    # |4000-2000| / (4000*2000) = 2.5e-4 /mm -> 25 * 51.28205 * 2.5e-4 = 0.3205128 mm on the sensor
    # 0.3205128 mm * 1920 px / 36 mm = 17.09402 px.
    assert LENS.sensor_distance_mm(2.0) == pytest.approx(51.282051, rel=1e-7)
    assert LENS.coc_px(4.0, 2.0, 1920) == pytest.approx(17.094017, rel=1e-6)
    # 1 m in front: |1000-2000|/(1000*2000) = 5e-4 /mm -> twice the CoC, negative when signed.
    assert LENS.coc_px(1.0, 2.0, 1920) == pytest.approx(34.188034, rel=1e-6)
    assert LENS.coc_px(1.0, 2.0, 1920, signed=True) == pytest.approx(-34.188034, rel=1e-6)
    assert LENS.coc_px(4.0, 2.0, 1920, signed=True) > 0
    assert LENS.coc_px(2.0, 2.0, 1920) == 0.0


def test_infinite_depth_gives_finite_limit():
    # d_p -> inf: c -> (w_i/w_s) a d_s / d_f = 1920/36 * 25 * 51.28205 / 2000 = 34.188 px
    c = LENS.coc_px(math.inf, 2.0, 1920)
    assert c == pytest.approx(34.188034, rel=1e-6)
    assert c == pytest.approx(LENS.coc_px(1e12, 2.0, 1920), rel=1e-9)


def test_focus_at_infinity():
    # d_s = f; c = (w_i/w_s) a f / d_p = 1920/36*25*50/4000 = 16.6667 px, all in front.
    assert LENS.sensor_distance_mm(math.inf) == 50.0
    assert LENS.coc_px(4.0, math.inf, 1920, signed=True) == pytest.approx(-16.666667, rel=1e-6)
    assert LENS.coc_px(math.inf, math.inf, 1920) == 0.0


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_numpy_type_and_dtype_preserved(dtype):
    d = np.array([[1.0, 4.0], [np.inf, 2.0]], dtype=dtype)
    c = LENS.coc_px(d, 2.0, 1920)
    assert isinstance(c, np.ndarray) and c.dtype == dtype and c.shape == (2, 2)
    np.testing.assert_allclose(c, [[34.188034, 17.094017], [34.188034, 0.0]], rtol=1e-5)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_torch_type_dtype_device_preserved(dtype):
    d = torch.tensor([[[[1.0, 4.0], [math.inf, 2.0]]]], dtype=dtype)
    c = LENS.coc_px(d, 2.0, 1920, signed=True)
    assert isinstance(c, torch.Tensor) and c.dtype == dtype and c.device == d.device
    torch.testing.assert_close(c, torch.tensor([[[[-34.188034, 17.094017], [34.188034, 0.0]]]], dtype=dtype))


def test_float_in_float_out():
    assert isinstance(LENS.coc_px(3, 2.0, 1920), float)


def test_bad_depth_names_count_and_first_pixel():
    d = np.full((64, 64), 3.0)
    d[12, 40] = -1.0
    d[20, 5] = 0.0
    d[30, 30] = np.nan
    with pytest.raises(ValueError, match=r"depth must be > 0.*got -1.0 at pixel \(12, 40\) \(3 bad pixels of 4096\)"):
        LENS.coc_px(d, 2.0, 1920)
    t = torch.ones(1, 1, 8, 8)
    t[0, 0, 3, 4] = float("nan")
    with pytest.raises(ValueError, match=r"got nan at pixel \(3, 4\) of axis0=0, axis1=0 \(1 bad pixel"):
        LENS.coc_px(t, 2.0, 1920)
    with pytest.raises(ValueError, match="depth"):
        LENS.coc_px(-math.inf, 2.0, 1920)
    with pytest.raises(ValueError, match="got 0.0"):
        LENS.coc_px(0.0, 2.0, 1920)


def test_bad_focus_and_lens():
    with pytest.raises(ValueError, match="greater than the focal length"):
        LENS.coc_px(3.0, 0.05, 1920)  # focus == focal length
    with pytest.raises(ValueError, match="greater than the focal length"):
        LENS.coc_px(3.0, 0.01, 1920)
    with pytest.raises(ValueError, match="focus distance"):
        LENS.coc_px(3.0, float("nan"), 1920)
    with pytest.raises(ValueError, match="f_number"):
        ThinLens(50.0, 0.0, 36.0)
    with pytest.raises(ValueError, match="focal_length_mm"):
        ThinLens(-50.0, 2.0, 36.0)
    with pytest.raises(ValueError, match="image_width_px"):
        LENS.coc_px(3.0, 2.0, 0)


def test_lens_dict_round_trip():
    assert ThinLens.from_dict(LENS.to_dict()) == LENS
    with pytest.raises(ValueError, match="keys"):
        ThinLens.from_dict({"focal_length_mm": 50})


def test_max_coc_matches_dense_search():
    focus = [0.8, 2.0, 7.5]
    depths = np.concatenate([np.geomspace(0.5, 1e4, 20001), [np.inf]])
    dense = max(float(LENS.coc_px(depths, f, 640).max()) for f in focus)
    assert max_coc_px(LENS, (0.5, math.inf), focus, 640) == pytest.approx(dense, rel=1e-9)
    with pytest.raises(ValueError, match="near <= far"):
        max_coc_px(LENS, (3.0, 1.0), focus, 640)
    with pytest.raises(ValueError, match="at least one"):
        max_coc_px(LENS, (1.0, 3.0), [], 640)


@pytest.mark.parametrize(
    "c, n", [(0.0, 0), (0.5, 0), (1.0, 0), (1.01, 1), (3.0, 1), (3.01, 2), (17.094, 9), (41.0, 20), (81.0, 40)]
)
def test_blocks_for_coc(c, n):
    assert blocks_for_coc(c) == n
    assert 2 * n + 1 >= c and (n == 0 or 2 * (n - 1) + 1 < c)


@pytest.mark.parametrize("bad", [-1.0, math.nan, math.inf])
def test_blocks_for_coc_rejects(bad):
    with pytest.raises(ValueError, match="max_coc"):
        blocks_for_coc(bad)


def test_focus_sweep_uniform_in_diopters():
    f = focus_sweep_m(1.0, math.inf, 5)
    assert f[0] == pytest.approx(1.0) and f[-1] == math.inf
    np.testing.assert_allclose(np.diff([1.0 / x for x in f]), -0.25)
    assert focus_sweep_m(2.0, 2.0, 1) == [2.0]

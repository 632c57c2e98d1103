"""The hidden-background estimate: occluders against a literal definition, pull-push fill."""

import math

import numpy as np
import pytest
import torch

from neuralbokeh.ops.holes import JUMP_PX, LOG_OFFSET, OUTLIER_RATIO, STEP_PX, hidden_background, occluders, push_pull_fill


def test_occluders_match_the_literal_definition():
    g = torch.Generator().manual_seed(0)
    coc = (torch.rand(1, 1, 13, 17, generator=g, dtype=torch.float64) - 0.5) * 20
    radius, jump = 3, 2.0
    got = occluders(coc, radius, jump)[0, 0].numpy()
    c = coc[0, 0].numpy()
    want = np.zeros_like(got)
    for y in range(c.shape[0]):
        for x in range(c.shape[1]):
            window = c[max(0, y - radius) : y + radius + 1, max(0, x - radius) : x + radius + 1]
            want[y, x] = c[y, x] < window.max() - jump
    np.testing.assert_array_equal(got, want)
    assert not occluders(coc, 0, jump).any()


def test_push_pull_keeps_known_pixels_and_fills_holes_from_around():
    img = torch.zeros(1, 3, 32, 40, dtype=torch.float64)
    img[..., :20] = 2.0  # left half 2, right half 5
    img[..., 20:] = 5.0
    weight = torch.ones(1, 1, 32, 40, dtype=torch.float64)
    weight[..., 8:24, 4:12] = 0.0  # a hole inside the left half
    weight[..., 8:24, 28:36] = 0.0  # one inside the right half
    out = push_pull_fill(img, weight)
    known = weight.expand_as(img) > 0
    assert torch.equal(out[known], img[known])
    left, right = out[..., 8:24, 4:12], out[..., 8:24, 28:36]
    assert (left - 2.0).abs().max() < 0.35 and (right - 5.0).abs().max() < 0.35  # from its own side
    assert (out >= 2.0 - 1e-9).all() and (out <= 5.0 + 1e-9).all()  # a convex combination: no overshoot
    const = push_pull_fill(torch.full_like(img, 0.7), weight)
    torch.testing.assert_close(const, torch.full_like(img, 0.7), atol=1e-12, rtol=0)
    assert torch.equal(push_pull_fill(img, torch.zeros_like(weight)), img)  # nothing known: unchanged


def test_hidden_background_replaces_the_foreground_by_its_surroundings():
    aif = torch.full((1, 3, 40, 40), 0.2, dtype=torch.float64)
    aif[..., 15:25, 15:25] = 3.0  # a bright foreground square
    coc = torch.zeros(1, 1, 40, 40, dtype=torch.float64)
    coc[..., 15:25, 15:25] = -12.0  # in front, blurred
    bg = hidden_background(aif, coc)
    torch.testing.assert_close(bg, torch.full_like(aif, 0.2), atol=1e-12, rtol=0)
    # a plane, however sloped (0.5 px of CoC per px), hides nothing: a texture comes back unchanged
    slope = torch.linspace(-10, 10, 40, dtype=torch.float64).expand(1, 1, 40, 40)
    texture = 0.2 + 0.1 * torch.sin(torch.arange(40, dtype=torch.float64) / 3.0).expand(1, 3, 40, 40)
    assert not occluders(slope, 5, JUMP_PX).any() and not occluders(slope, 1, STEP_PX).any()
    assert torch.equal(hidden_background(texture, slope), texture)


def test_a_highlight_is_not_counted_twice_by_the_fill():
    """Its light is scattered already: where coverage falls short the fill must not add its sharp
    value again, neither on its own plane nor a little in front of a wall (a 2.6 px CoC step,
    below JUMP_PX: a light bulb in front of the wall it lights), nor behind an occluder beside it."""
    aif = torch.full((1, 3, 40, 40), 0.2, dtype=torch.float64)
    aif[..., 20, 10] = 1e4
    coc = torch.full((1, 1, 40, 40), 9.0, dtype=torch.float64)
    coc[..., 25:] = 0.0  # an in-focus occluder 5 px to the right of a second highlight
    aif[..., 20, 23] = 1e4
    on_plane = hidden_background(aif, coc)
    level = math.exp((math.log(1e4 + LOG_OFFSET) + 8 * math.log(0.2 + LOG_OFFSET)) / 9)  # its 3 x 3 geometric mean
    assert float(on_plane[..., 20, 10].max()) == pytest.approx(OUTLIER_RATIO * level - LOG_OFFSET, rel=1e-9)  # 2.7, not 1e4
    assert float(on_plane[..., 25:].max()) < 0.3  # what the occluder hides is the wall, not a copy of the light
    front = torch.full((1, 1, 40, 40), 0.0, dtype=torch.float64)
    front[..., 20, 10] = -2.6
    filled = hidden_background(aif, front)
    assert float(filled[..., 20, 10].max()) == pytest.approx(0.2, rel=1e-9)  # the wall behind the bulb


def test_bad_inputs_are_named():
    with pytest.raises(ValueError, match="coc must have shape"):
        occluders(torch.zeros(1, 2, 4, 4), 1)
    with pytest.raises(ValueError, match="jump_px"):
        occluders(torch.zeros(1, 1, 4, 4), 1, 0.0)
    with pytest.raises(ValueError, match="weight must have shape"):
        push_pull_fill(torch.zeros(1, 3, 4, 4), torch.zeros(1, 1, 4, 5))

"""What a depth map hides: an estimate of the surfaces behind the foreground.

An all-in-focus image plus depth has one colour per pixel, so the layers a renderer cuts from
it have holes wherever something nearer stands. A blurred foreground is partly transparent at
its edges, and through it a lens sees the hidden background. These functions estimate that
background from the visible one nearby (torch, no file I/O):

* :func:`occluders`: pixels standing in front of something within reach of the blur (a depth
  discontinuity in signed CoC: nearer by more than ``jump_px`` than the farthest pixel within
  ``radius_px``);
* :func:`push_pull_fill`: fills masked pixels from the unmasked ones around them, coarse to fine
  (pull-push interpolation: normalised box averages on an image pyramid, then each level
  fills the holes of the finer one bilinearly);
* :func:`hidden_pixels`: the pixels whose surface a renderer must guess behind them (occluders
  within reach of the widest blur, or in front of a neighbour);
* :func:`hidden_background`: both together, in the log of the light, the colour a renderer puts
  where its coverage falls short (``fill="background"`` of
  :func:`neuralbokeh.render.scatter_defocus`), with no highlight counted twice.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from ..core.checks import check_nonnegative, check_positive, check_shape
from ..core.tiling import pyramid_levels

JUMP_PX = 4.0  # the least signed-CoC step (px) that counts as a depth discontinuity
# ... or, to a neighbour (3 x 3), this step: the in-focus band's width. Without it a one-pixel HDR
# light 2.6 px in front of a wall filled the coverage its own scattered light left short with its
# own sharp value (Mitsuba renders: up to 1.6x the light around such highlights; docs/benchmarks.md).
# Along a slope neighbours differ by less than 1 px, so a plane still hides nothing.
STEP_PX = 1.0
LOG_OFFSET = 0.0018  # linear units (1 % of middle grey) added before the fill's logarithm, so black has one
OUTLIER_RATIO = 4.0  # a visible pixel's fill is at most this times the geometric mean of its 3 x 3 square


def occluders(coc: torch.Tensor, radius_px: int, jump_px: float = JUMP_PX) -> torch.Tensor:
    """``(B, 1, H, W)`` signed CoC (px) -> ``(B, 1, H, W)`` bool: in front of a farther pixel.

    A pixel is an occluder when its signed CoC is more than ``jump_px`` below the largest
    signed CoC (the farthest point) within the ``(2 radius_px + 1)^2`` square around it. The
    square max is taken separably (rows, then columns). Image borders are not padded with
    anything farther.
    """
    check_shape("coc", coc, "B 1 H W")
    check_nonnegative("radius_px", radius_px, " px")
    check_positive("jump_px", jump_px, " px")
    if radius_px == 0:
        return torch.zeros_like(coc, dtype=torch.bool)
    return coc < square_max(coc, radius_px) - jump_px


def square_max(x: torch.Tensor, radius_px: int) -> torch.Tensor:
    """``(B, C, H, W)`` -> the max over the ``(2 radius_px + 1)^2`` square around each pixel
    (separably: rows, then columns; nothing beyond the image's edges)."""
    if radius_px == 0:
        return x
    k = 2 * int(radius_px) + 1
    out = F.max_pool2d(x, (1, k), stride=1, padding=(0, radius_px))
    return F.max_pool2d(out, (k, 1), stride=1, padding=(radius_px, 0))


def hidden_pixels(coc: torch.Tensor, radius_px: int, jump_px: float = JUMP_PX, step_px: float = STEP_PX) -> torch.Tensor:
    """``(B, 1, H, W)`` signed CoC (px) -> ``(B, 1, H, W)`` bool: the pixels that stand in front of
    something a blur can reveal: :func:`occluders` within ``radius_px`` by ``jump_px``, or within
    the 3 x 3 neighbours by ``step_px`` (the in-focus band's width). What such a pixel hides is
    another surface; where any other pixel's coverage falls short, its own surface is hidden."""
    return occluders(coc, radius_px, jump_px) | occluders(coc, 1, step_px)


def push_pull_fill(image: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """Fill where ``weight`` is 0 from where it is 1 (pull-push interpolation).

    The image is zero-padded (weight 0) to a ``2^L`` square, ``L = ceil(log2(max(H, W)))``, so
    every level halves exactly (the same pyramid the ONNX export builds); at each level the
    weight-normalised 2x2 averages are filled from the next coarser level, upsampled bilinearly.

    Args:
        image: ``(B, C, H, W)`` values (e.g. linear RGB).
        weight: ``(B, 1, H, W)`` confidence in [0, 1]: 1 keeps the pixel, 0 fills it.

    Returns:
        ``(B, C, H, W)``: ``weight * image + (1 - weight) * coarse``. An image with no weight
        at all comes back unchanged.
    """
    check_shape("image", image, "B C H W")
    check_shape("weight", weight, "B 1 H W", B=image.shape[0], H=image.shape[2], W=image.shape[3])
    if not bool((weight > 0).any()):
        return image
    h, w = image.shape[-2:]
    side = 1 << pyramid_levels(h, w)
    pad = (0, side - w, 0, side - h)
    filled = _pull_push(F.pad(image, pad), F.pad(weight.to(image.dtype), pad))
    return filled[..., :h, :w]


def _pull_push(image: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    if image.shape[-1] < 2:
        return image
    w_small = F.avg_pool2d(weight, 2)
    c_small = F.avg_pool2d(image * weight, 2) / w_small.clamp_min(1e-12)
    # a coarse pixel with any support is trusted in proportion to it (at most fully)
    coarse = _pull_push(c_small, (4.0 * w_small).clamp(max=1.0))
    up = F.interpolate(coarse, scale_factor=2.0, mode="bilinear", align_corners=False)
    return weight * image + (1.0 - weight) * up


def visible_geometric_mean(log_image: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """``exp`` of the mean of ``log_image`` ``(B, C, H, W)`` over the pixels of weight 1 in the
    3 x 3 square around each pixel (``weight`` ``(B, 1, H, W)``, 0 or 1; nothing beyond the
    edges): the local level of a surface, which a lone highlight barely moves."""
    num = F.avg_pool2d(log_image * weight, 3, 1, 1, count_include_pad=False)
    den = F.avg_pool2d(weight, 3, 1, 1, count_include_pad=False)
    return torch.exp(num / den.clamp_min(1e-12))


def hidden_background(aif: torch.Tensor, coc: torch.Tensor, jump_px: float = JUMP_PX, radius_px: int | None = None,
                      step_px: float = STEP_PX) -> torch.Tensor:
    """What fills the coverage a blurred edge leaves short: behind every occluder (in front of the
    farthest pixel within reach by ``jump_px``, or of a neighbour by ``step_px``:
    :func:`occluders`) the visible background around it (:func:`push_pull_fill` of the log of
    the light, so that a highlight among the visible pixels does not light up what it hides);
    elsewhere the pixel's own colour, at most :data:`OUTLIER_RATIO` x the geometric mean of the
    visible 3 x 3 square around it (a highlight's light is scattered already; its sharp value
    would add it a second time wherever its own surface's coverage falls short).

    Args:
        aif: ``(B, 3, H, W)`` all-in-focus linear RGB (values below 0 count as 0).
        coc: ``(B, 1, H, W)`` signed CoC in px.
        jump_px: the least CoC step (px) that counts as a depth discontinuity, > 0.
        radius_px: how far (px) an occluder is looked for, >= 0 (default: half the largest
            |CoC|, the reach of the widest blur); 0 returns ``aif`` (nothing is scattered).
        step_px: the least CoC step (px) to a neighbour that counts as one, > 0.

    Returns:
        ``(B, 3, H, W)`` linear RGB.
    """
    return hidden_estimate(aif, coc, jump_px, radius_px, step_px)[0]


def hidden_estimate(aif: torch.Tensor, coc: torch.Tensor, jump_px: float = JUMP_PX, radius_px: int | None = None,
                    step_px: float = STEP_PX) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`hidden_background` ``(B, 3, H, W)``; the bound it puts on a visible pixel's own
    colour, :data:`OUTLIER_RATIO` x the geometric mean of its visible 3 x 3 square (linear,
    ``(B, 3, H, W)``; ``aif`` itself where ``radius_px`` is 0): what a surface's light is
    expected to reach there without a highlight's; and :func:`hidden_pixels` ``(B, 1, H, W)``
    (none where ``radius_px`` is 0)."""
    if radius_px is None:
        radius_px = math.ceil(float(coc.abs().max()) / 2.0) if coc.numel() else 0
    if radius_px == 0:
        return aif, aif, torch.zeros_like(coc, dtype=torch.bool)
    hide = hidden_pixels(coc, radius_px, jump_px, step_px)
    keep = (~hide).to(aif.dtype)
    log_aif = torch.log(aif.clamp_min(0.0) + LOG_OFFSET)
    behind = torch.exp(push_pull_fill(log_aif, keep)) - LOG_OFFSET
    bound = OUTLIER_RATIO * visible_geometric_mean(log_aif, keep) - LOG_OFFSET
    return torch.where(hide, behind, torch.minimum(aif, bound)), bound, hide

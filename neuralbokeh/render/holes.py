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
* :func:`hidden_background`: both together, the colour a renderer puts where its coverage
  falls short (``fill="background"`` of :func:`neuralbokeh.render.scatter_defocus`).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from ..checks import check_nonnegative, check_positive, check_shape


def occluders(coc: torch.Tensor, radius_px: int, jump_px: float = 4.0) -> torch.Tensor:
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
    k = 2 * int(radius_px) + 1
    far = F.max_pool2d(coc, (1, k), stride=1, padding=(0, radius_px))
    far = F.max_pool2d(far, (k, 1), stride=1, padding=(radius_px, 0))
    return coc < far - jump_px


def push_pull_fill(image: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """Fill where ``weight`` is 0 from where it is 1 (pull-push interpolation).

    Args:
        image: ``(B, C, H, W)`` values (e.g. linear RGB).
        weight: ``(B, 1, H, W)`` confidence in [0, 1]: 1 keeps the pixel, 0 fills it.

    Returns:
        ``(B, C, H, W)``: ``weight * image + (1 - weight) * coarse`` where ``coarse`` is the
        weight-normalised average of the next coarser level, upsampled bilinearly. An image with
        no weight at all comes back unchanged.
    """
    check_shape("image", image, "B C H W")
    check_shape("weight", weight, "B 1 H W", B=image.shape[0], H=image.shape[2], W=image.shape[3])
    if not bool((weight > 0).any()):
        return image
    levels = max(0, math.ceil(math.log2(max(image.shape[-2:]))))
    return _pull_push(image, weight.to(image.dtype), levels)


def _pull_push(image: torch.Tensor, weight: torch.Tensor, levels: int) -> torch.Tensor:
    if levels == 0 or min(image.shape[-2:]) < 2:
        total = (image * weight).sum((-2, -1), keepdim=True) / weight.sum((-2, -1), keepdim=True).clamp_min(1e-12)
        return weight * image + (1.0 - weight) * total
    w_small = F.avg_pool2d(weight, 2, ceil_mode=True)
    c_small = F.avg_pool2d(image * weight, 2, ceil_mode=True) / w_small.clamp_min(1e-12)
    # a coarse pixel with any support is trusted in proportion to it (at most fully)
    coarse = _pull_push(c_small, (4.0 * w_small).clamp(max=1.0), levels - 1)
    up = F.interpolate(coarse, size=image.shape[-2:], mode="bilinear", align_corners=False)
    return weight * image + (1.0 - weight) * up


def hidden_background(aif: torch.Tensor, coc: torch.Tensor, jump_px: float = 4.0) -> torch.Tensor:
    """The AIF with every occluder (:func:`occluders` within the largest blur radius) replaced by
    the visible background around it (:func:`push_pull_fill`).

    Args:
        aif: ``(B, 3, H, W)`` all-in-focus linear RGB.
        coc: ``(B, 1, H, W)`` signed CoC in px.
        jump_px: the least CoC step (px) that counts as a depth discontinuity, > 0.

    Returns:
        ``(B, 3, H, W)``, equal to ``aif`` wherever nothing nearer stands within reach.
    """
    radius = math.ceil(float(coc.abs().max()) / 2.0) if coc.numel() else 0
    hide = occluders(coc, radius, jump_px)
    return push_pull_fill(aif, (~hide).to(aif.dtype))

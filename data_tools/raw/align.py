"""Alignment of focal-stack slices: focus breathing is a change of magnification.

Each slice is registered to a reference slice with a similarity transform (isotropic scale
about the image centre and a translation, optionally a rotation) by kornia's
``ImageRegistrator`` (coarse-to-fine gradient descent on a Gaussian pyramid, symmetric L1
loss over the overlap) on log luminance, which makes the fit insensitive to exposure and lets
highlights count no more than shadows. The slices are then resampled (bicubic) into the
reference frame and all are cropped to the largest centred rectangle that every warped slice
covers. The residual misalignment is measured by registering each aligned slice to the
reference again with a translation-only model; it is reported in pixels.

A fitted link (slice to its neighbour) is kept only where it beats the identity on the stack's
own photo-consistency (:func:`photo_consistency`) by :data:`KEEP_GAIN`: on an already registered
stack a similarity fit still lowers the registration loss a little, by trading a difference in
blur for a spurious magnification, and the fused all-in-focus image then gets worse.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from kornia.filters import gaussian_blur2d
from kornia.geometry import create_meshgrid
from kornia.geometry.linalg import transform_points
from kornia.geometry.transform import HomographyWarper, ImageRegistrator
from kornia.geometry.transform.image_registrator import Similarity

log = logging.getLogger(__name__)

# A fit must lower the photo-consistency error by this fraction to replace the identity: above what
# spurious fits gain on registered synthetic DNG stacks (up to +2.5 %), below what right fits of 3 %
# focus breathing gain (+3.1 % to +24 %).
KEEP_GAIN = 0.03
# relative blurs (working px, sigma) a neighbour may differ by: photo-consistency forgives them
_BLUR_SIGMAS = (0.0, 0.7, 1.4, 2.8, 5.6)
_PRESMOOTH = 2.0  # px: noise and the warp's own interpolation smoothing stop counting
_WINDOW = 4.0  # px: the neighbourhood over which one relative blur is chosen


@dataclass(frozen=True)
class SliceAlignment:
    """Where one slice sat relative to the reference: ``scale`` (its content magnified by this
    factor), ``rotation_deg``, ``shift_px`` (x, y, in reference pixels), ``residual_px`` after
    alignment."""

    scale: float
    rotation_deg: float
    shift_px: tuple[float, float]
    residual_px: float
    gain: float = 0.0  # photo-consistency gain of this slice's fitted link over the identity
    kept: bool = True  # the fit was used (False: the link was left as the identity)

    def to_dict(self) -> dict:
        return {"scale": self.scale, "rotation_deg": self.rotation_deg, "shift_px": list(self.shift_px),
                "residual_px": self.residual_px, "gain": self.gain, "kept": self.kept}


def _log_luma(img: np.ndarray, max_side: int) -> torch.Tensor:
    y = torch.from_numpy(np.ascontiguousarray(img.mean(axis=2), dtype=np.float32))[None, None]
    y = torch.log(y + 1e-3 * max(float(y.mean()), 1e-6))
    y = (y - y.mean()) / (y.std() + 1e-6)
    scale = max(y.shape[-2:]) / max_side
    if scale > 1:
        y = F.interpolate(y, scale_factor=1 / scale, mode="area", recompute_scale_factor=False)
    return y


def _registrator(model: Similarity, levels: int) -> ImageRegistrator:
    return ImageRegistrator(model, warper=HomographyWarper, loss_fn=F.l1_loss, pyramid_levels=levels, lr=2e-3,
                            num_iterations=120, tolerance=1e-6)


def _fit(src: torch.Tensor, dst: torch.Tensor, rotation: bool, scale: bool) -> torch.Tensor:
    levels = max(1, min(4, int(np.log2(min(src.shape[-2:]) / 16))))
    reg = _registrator(Similarity(rotation=rotation, scale=scale, shift=True), levels)
    return reg.register(src, dst).detach()


def _warp_luma(y: torch.Tensor, matrix: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    h, w = y.shape[-2:]
    grid = create_meshgrid(h, w, normalized_coordinates=True, dtype=torch.float64)
    grid = transform_points(matrix.double(), grid.reshape(1, -1, 2)).reshape(1, h, w, 2)
    out = F.grid_sample(y.double(), grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out, (grid.abs() <= 1.0 - 2.0 / min(h, w)).all(dim=-1)[:, None].double()


def _smooth(x: torch.Tensor, sigma: float) -> torch.Tensor:
    if sigma == 0:
        return x
    k = 2 * math.ceil(3 * sigma) + 1
    return gaussian_blur2d(x, (k, k), (sigma, sigma), border_type="replicate")


def photo_consistency(src: torch.Tensor, dst: torch.Tensor, mask: torch.Tensor) -> float:
    """Mean blur-equalised L1 between two log-luminance images ``(1, 1, H, W)`` over ``mask``:
    in each neighbourhood the smaller error of either image blurred by any of ``_BLUR_SIGMAS``
    against the other, so that a difference in defocus costs nothing and a geometric misfit does."""
    a, b = _smooth(src.double(), _PRESMOOTH), _smooth(dst.double(), _PRESMOOTH)
    weight = _smooth(mask, _WINDOW).clamp_min(1e-6)
    errors = [_smooth((x - y).abs() * mask, _WINDOW) / weight
              for s in _BLUR_SIGMAS for x, y in ((_smooth(a, s), b), (a, _smooth(b, s)))]
    best = torch.stack(errors).min(dim=0).values
    return float((best * mask).sum() / mask.sum().clamp_min(1.0))


def fit_gain(src: torch.Tensor, dst: torch.Tensor, matrix: torch.Tensor) -> float:
    """How much ``matrix`` (src -> dst) lowers :func:`photo_consistency` relative to the identity,
    both measured on the pixels the warped ``src`` covers (a fraction; <= 0: no better)."""
    warped, mask = _warp_luma(src, matrix)
    before = photo_consistency(src, dst, mask)
    return (before - photo_consistency(warped, dst, mask)) / max(before, 1e-12)


def _warp(img: np.ndarray, matrix: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Resample ``img`` with the fitted transform: bicubic, so resampled slices keep their
    sharpness (a bilinear resampling softened them and biased the focus measure towards the
    untouched reference slice: depth from focus returned the reference's distance nearly
    everywhere); the valid mask marks pixels with full support."""
    h, w = img.shape[:2]
    x = torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1), dtype=np.float32))[None].double()
    grid = create_meshgrid(h, w, normalized_coordinates=True, dtype=torch.float64)  # (1, H, W, 2)
    grid = transform_points(matrix.double(), grid.reshape(1, -1, 2)).reshape(1, h, w, 2)
    out = F.grid_sample(x, grid, mode="bicubic", padding_mode="border", align_corners=True)
    inside = (grid.abs() <= 1.0 - 2.0 / min(h, w)).all(dim=-1)[0].numpy()
    # bicubic kernels ring: next to a dark edge they undershoot below zero, which is not light.
    # Such values are set to 0; how far they went is logged (a few % of the local contrast).
    undershoot = float(out.min())
    if undershoot < 0:
        log.info("bicubic resampling undershoot down to %.3g set to 0 (%d values)", undershoot, int((out < 0).sum()))
    return out[0].clamp(min=0.0).numpy().transpose(1, 2, 0).astype(np.float32), inside


def _largest_centred_crop(valid: np.ndarray) -> tuple[slice, slice]:
    h, w = valid.shape
    top, bottom, left, right = 0, h, 0, w
    while top < bottom and left < right and not valid[top:bottom, left:right].all():
        rows_bad = ~valid[top:bottom, left:right].all(axis=1)
        cols_bad = ~valid[top:bottom, left:right].all(axis=0)
        # shrink the side with the most invalid pixels, keeping the crop roughly centred
        if rows_bad[0] or rows_bad[-1] or not (cols_bad[0] or cols_bad[-1]):
            top += int(rows_bad[0])
            bottom -= int(rows_bad[-1])
        if cols_bad[0] or cols_bad[-1]:
            left += int(cols_bad[0])
            right -= int(cols_bad[-1])
        if not (rows_bad[0] or rows_bad[-1] or cols_bad[0] or cols_bad[-1]):  # holes inside: shrink all sides
            top, bottom, left, right = top + 1, bottom - 1, left + 1, right - 1
    if top >= bottom or left >= right:
        raise ValueError("the aligned slices have no common area: the stack is too misaligned to use")
    return slice(top, bottom), slice(left, right)


def align_stack(slices: list[np.ndarray], reference: int, rotation: bool = False, max_side: int = 384,
                ) -> tuple[list[np.ndarray], list[SliceAlignment], tuple[slice, slice]]:
    """Align ``slices`` (``(H, W, 3)`` linear RGB, in focus order) to ``slices[reference]``.

    Each slice is registered to its neighbour towards the reference and the transforms are
    chained: neighbours are defocused alike, so the fit is not biased by a difference in blur
    (registering the nearest-focused slice straight to a far-focused reference misjudged the
    magnification by up to 0.6 % on synthetic stacks; chained, see ``tests/test_raw.py``).

    Returns the aligned slices cropped to their common area, one :class:`SliceAlignment` per
    slice (the reference's is the identity) and the crop ``(rows, cols)`` in the original frame.
    """
    h, w = slices[0].shape[:2]
    for k, img in enumerate(slices):
        if img.shape != slices[0].shape:
            raise ValueError(f"slice {k} has shape {img.shape}, the stack's first slice {slices[0].shape}")
    lumas = [_log_luma(img, max_side) for img in slices]
    ref = lumas[reference]
    eye = torch.eye(3, dtype=torch.float64)[None]
    chained: dict[int, torch.Tensor] = {reference: eye}
    gains: dict[int, float] = {reference: 0.0}
    for step in (-1, 1):
        k = reference + step
        while 0 <= k < len(slices):
            fit = _fit(lumas[k], lumas[k - step], rotation, True).double()
            gains[k] = fit_gain(lumas[k], lumas[k - step], fit)
            chained[k] = (fit if gains[k] >= KEEP_GAIN else eye) @ chained[k - step]
            k += step
    aligned, info, valid = [], [], np.ones((h, w), bool)
    for k, img in enumerate(slices):
        kept = gains[k] >= KEEP_GAIN
        if k != reference and not kept:
            log.info("slice %d: fit gains %.1f %% photo-consistency over the identity (< %.0f %%): link left as the identity",
                     k, 100 * gains[k], 100 * KEEP_GAIN)
        if torch.equal(chained[k], eye):  # nothing to resample: the slice is used as decoded
            aligned.append(img)
            info.append(SliceAlignment(1.0, 0.0, (0.0, 0.0), 0.0, gains[k], kept))
            continue
        matrix = chained[k]
        out, ok = _warp(img, matrix)
        valid &= ok
        linear = matrix[0, :2, :2]
        s = float(torch.sqrt(torch.det(linear).abs()))
        # normalised coordinates span 2 units per image side: shifts to pixels. The fitted
        # scale s is the magnification of the slice's content relative to the reference
        # (tests/test_raw.py recovers a simulated focus breathing with it).
        shift = (float(matrix[0, 0, 2]) * w / 2, float(matrix[0, 1, 2]) * h / 2)
        rot = float(np.degrees(np.arctan2(float(linear[1, 0]) * w / h, float(linear[0, 0]))))
        residual = _fit(_log_luma(out, max_side), ref, False, False)
        res_px = float(np.hypot(float(residual[0, 0, 2]) * w / 2, float(residual[0, 1, 2]) * h / 2))
        info.append(SliceAlignment(s, rot, shift, res_px, gains[k], kept))
        aligned.append(out)
        log.info("slice %d: magnification %.5f, rotation %.3f deg, shift (%.2f, %.2f) px, residual %.3f px",
                 k, s, rot, shift[0], shift[1], res_px)
    rows, cols = _largest_centred_crop(valid)
    return [a[rows, cols] for a in aligned], info, (rows, cols)

"""Developed focal stacks (8/16-bit TIFF, PNG, JPEG) back to linear light.

Most focus-stacking users hold developed images (Helicon Focus, Zerene and focus-stack all take
them), not RAW files. A developed file went through a tone curve; the training triples are in
linear light, so the curve is undone (``transfer``):

* ``srgb`` (default): the sRGB transfer function (IEC 61966-2-1; kornia's
  ``rgb_to_linear_rgb``), what cameras and raw converters write unless told otherwise;
* ``linear``: the file is already linear (e.g. a 16-bit TIFF exported linear);
* ``gamma:G``: a pure power law, ``linear = value ** G``.

Any other tone curve (a camera's picture style, a raw converter's contrast) is not undone: the
result is then only approximately linear. Colours stay in the file's RGB primaries (sRGB for
these files). Integer files are scaled to [0, 1] by OpenImageIO; 8-bit highlights are clipped
at 1, as the camera wrote them.

Exposure: the slices of a stack may differ in brightness (auto exposure, flicker, aperture
bracketing). :func:`exposure_gains` measures each slice's gain against the reference slice in
linear light on a coarse grid (so the defocus, which moves light but keeps its local mean,
does not count) over the pixels unclipped in both.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from kornia.color import rgb_to_linear_rgb

from neuralbokeh.core.io import read_image

from .decode import RawDecodeError

DEVELOPED_EXTENSIONS = {".tif", ".tiff", ".png", ".jpg", ".jpeg"}
CLIPPED = 0.98  # linear values at or above this count as clipped


def parse_transfer(spec: str) -> tuple[str, float]:
    """``"srgb"``, ``"linear"`` or ``"gamma:G"`` (G > 0) -> ``(kind, gamma)``."""
    if spec in ("srgb", "linear"):
        return spec, 1.0
    if spec.startswith("gamma:"):
        try:
            g = float(spec.split(":", 1)[1])
        except ValueError:
            g = float("nan")
        if g > 0:
            return "gamma", g
    raise ValueError(f"transfer must be 'srgb', 'linear' or 'gamma:G' with G > 0, got {spec!r}")


def decode_developed(path, transfer: str = "srgb") -> np.ndarray:
    """One developed image -> ``(H, W, 3)`` float32 linear RGB in [0, 1].

    Raises:
        RawDecodeError: unreadable file, or not an RGB(A) / grey image.
    """
    kind, gamma = parse_transfer(transfer)
    try:
        img = read_image(path)
    except OSError as e:
        raise RawDecodeError(f"{path}: cannot read it ({e})") from None
    channels = img.shape[2]
    if channels in (1, 2):  # grey (+ alpha)
        img = np.repeat(img[..., :1], 3, axis=2)
    elif channels in (3, 4):
        img = img[..., :3]
    else:
        raise RawDecodeError(f"{path}: expected a grey or RGB image, got {channels} channels")
    img = np.clip(img, 0.0, 1.0)  # integer files are in [0, 1] already; float TIFFs are taken as they are within it
    if kind == "srgb":
        x = torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1)))
        img = rgb_to_linear_rgb(x).numpy().transpose(1, 2, 0)
    elif kind == "gamma":
        img = img**gamma
    return np.ascontiguousarray(img, dtype=np.float32)


def exposure_gains(images: list[np.ndarray], ref: int, grid: int = 16) -> list[float]:
    """Gain that brings each linear ``(H, W, 3)`` image to the exposure of ``images[ref]``.

    Each image is averaged into ``grid x grid`` cells (area-weighted); cells clipped
    (>= :data:`CLIPPED` in any channel of either image) or black in either are left out, and
    the gain is the ratio of the sums of the rest (1 for the reference).

    Raises:
        ValueError: an image with no cell usable against the reference.
    """
    def cells(img: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        x = torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1), dtype=np.float64))[None]
        mean = F.adaptive_avg_pool2d(x, grid)[0]
        peak = F.adaptive_max_pool2d(x, grid)[0]
        return mean.sum(0), peak.amax(0)

    ref_mean, ref_peak = cells(images[ref])
    gains = []
    for k, img in enumerate(images):
        if k == ref:
            gains.append(1.0)
            continue
        mean, peak = cells(img)
        ok = (ref_peak < CLIPPED) & (peak < CLIPPED) & (mean > 0) & (ref_mean > 0)
        if not bool(ok.any()):
            raise ValueError(f"slice {k} has no unclipped, non-black region in common with the reference slice {ref}")
        gains.append(float(ref_mean[ok].sum() / mean[ok].sum()))
    return gains

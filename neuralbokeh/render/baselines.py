"""Classical baselines for the evaluation report (torch, no file I/O).

* :func:`gaussian_defocus`: the CoC-driven Gaussian blur, the kind of approximation the Neural
  Bokeh paper compares against (section 2: methods that learn or apply only the *amount* of
  blur). Rendered by the reference scatter with a Gaussian pupil (sigma = diameter / 4), so it
  differs from the reference only in the shape of the blur.
* :func:`gather_defocus`: naive spatially varying gather, the post-filter that the scatter
  ("spreading") methods of ``../shared/papers/pyramid-spreading-tensor-filtering-kosloff-barsky.txt``
  are contrasted with: every pixel averages the all-in-focus image over *its own* aperture
  kernel at *its own* CoC, with no notion of occlusion, so sharp foreground leaks into blurred
  background and a blurred foreground does not spread over a sharp background.
* :func:`neuralbokeh.render.scatter_defocus` with the true aperture: the reference (the
  foundation's renderer); the evaluation calls it the oracle when the aperture is the data's.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..apertures import ApertureModel, Gaussian
from ..checks import check_finite, check_nonnegative, check_positive, check_shape
from .fftconv import fft_convolve2d
from .scatter import scatter_defocus


def gaussian_defocus(aif: torch.Tensor, coc: torch.Tensor) -> torch.Tensor:
    """``(B, 3, H, W)`` linear RGB, ``(B, 1, H, W)`` signed CoC (px) -> Gaussian-blurred RGB."""
    return scatter_defocus(aif, coc, ApertureModel(Gaussian(0.5)))


def gather_defocus(aif: torch.Tensor, coc: torch.Tensor, aperture: ApertureModel | None = None,
                   coc_step: float = 1.0) -> torch.Tensor:
    """Naive gather: ``out(p) = (K_{c(p)} * aif)(p)`` with ``K_c`` the aperture kernel at CoC ``c``.

    The image is convolved with the kernel of every CoC level ``coc_step`` apart (signed:
    in-front kernels are point-reflected, as in the scatter renderer; the aperture is taken at
    the image centre, so cat-eye is ignored) and each pixel interpolates linearly between the
    two levels around its own CoC. Where the CoC is uniform this is the scatter's result
    (same kernel, same orientation); the two differ only where the CoC varies.

    Args:
        aif: ``(B, 3, H, W)`` linear RGB, finite, >= 0.
        coc: ``(B, 1, H, W)`` signed CoC diameter in px, finite.
        aperture: aperture model (default disk).
        coc_step: spacing of the CoC levels in px, > 0.

    Returns:
        ``(B, 3, H, W)`` linear RGB (float64).
    """
    d = check_shape("aif", aif, "B 3 H W")
    check_shape("coc", coc, "B 1 H W", B=d["B"], H=d["H"], W=d["W"])
    check_nonnegative("aif", aif)
    check_finite("coc", coc, " px")
    check_positive("coc_step", coc_step, " px")
    aperture = aperture or ApertureModel()
    x, c = aif.double(), coc.double() / coc_step
    lo = int(torch.floor(c.min()))
    hi = int(torch.ceil(c.max()))
    out = torch.zeros_like(x)
    for level in range(lo, hi + 1):
        weight = (1.0 - (c - level).abs()).clamp(min=0.0)  # hat function: linear interpolation between levels
        if not bool((weight > 0).any()):
            continue
        diameter = abs(level) * coc_step
        k = torch.from_numpy(aperture.kernels(diameter)).to(x)  # (3, k, k), sums to 1 per channel
        if level < 0:
            k = k.flip(-1, -2)
        r = k.shape[-1] // 2  # edge replication outside the frame, like the scatter renderer's border handling
        blurred = fft_convolve2d(F.pad(x, (r, r, r, r), mode="replicate"), k[None])
        out += weight * blurred[..., r : r + d["H"], r : r + d["W"]]
    return out

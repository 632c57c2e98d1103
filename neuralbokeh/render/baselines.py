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
* :func:`pseudo_ray_trace`: Yang et al.'s depth-aware pseudo ray tracing with their weighted
  colour blending as an option (``../shared/papers/virtual-dslr-yang.txt``).
* in their own modules: :func:`neuralbokeh.render.buckets.bucket_gather` (the light-field
  patent's near/mid/far buckets), :func:`neuralbokeh.render.pyramid.pyramid_spread` and
  :func:`neuralbokeh.render.pyramid.tensor_filter` (Kosloff and Barsky),
  :func:`neuralbokeh.render.lens_trace.lens_ray_trace` (Lee, Eisemann and Seidel).
* :func:`neuralbokeh.render.scatter_defocus` with the true aperture: the reference (the
  foundation's renderer); the evaluation calls it the oracle when the aperture is the data's.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from ..core.apertures import ApertureModel, Gaussian, pupil_grid
from ..core.checks import check_finite, check_nonnegative, check_positive, check_shape
from ..ops.fftconv import fft_convolve2d
from .scatter import scatter_defocus


def check_baseline_inputs(aif: torch.Tensor, coc: torch.Tensor, coc_step: float) -> dict[str, int]:
    """The shared checks of the baselines: ``(B, 3, H, W)`` colour >= 0, ``(B, 1, H, W)`` finite CoC."""
    d = check_shape("aif", aif, "B 3 H W")
    check_shape("coc", coc, "B 1 H W", B=d["B"], H=d["H"], W=d["W"])
    check_nonnegative("aif", aif)
    check_finite("coc", coc, " px")
    check_positive("coc_step", coc_step, " px")
    return d


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
    d = check_baseline_inputs(aif, coc, coc_step)
    aperture = aperture or ApertureModel()
    x, c = aif.double(), coc.double() / coc_step
    lo = int(torch.floor(c.min()))
    hi = int(torch.ceil(c.max()))
    out = torch.zeros_like(x)
    for level in range(lo, hi + 1):
        weight = (1.0 - (c - level).abs()).clamp(min=0.0)  # hat function: linear interpolation between levels
        if not bool((weight > 0).any()):
            continue
        k = torch.from_numpy(aperture.psf(level * coc_step)).to(x)  # (3, k, k), sums to 1 per channel
        r = k.shape[-1] // 2  # edge replication outside the frame, like the scatter renderer's border handling
        blurred = fft_convolve2d(F.pad(x, (r, r, r, r), mode="replicate"), k[None])
        out += weight * blurred[..., r : r + d["H"], r : r + d["W"]]
    return out


def aperture_rays(aperture: ApertureModel, n: int) -> np.ndarray:
    """Equal-weight rays through an ``n x n`` grid of the pupil (:func:`neuralbokeh.core.apertures.pupil_grid`)
    where the shape transmits more than half, ``(N, 2)`` as (x right, y down)."""
    pts, t = pupil_grid(aperture.shape, n)
    pts = pts[t > 0.5] * np.array([1.0, -1.0])  # the shape's v is up, image rows go down
    if len(pts) == 0:
        raise ValueError(f"the aperture {aperture.shape} has no sample point on a {n}x{n} grid")
    return pts


def pseudo_ray_trace(aif: torch.Tensor, coc: torch.Tensor, aperture: ApertureModel | None = None, grid: int | None = None,
                     coc_step: float = 0.5, blending: str = "radiance", sigma: float = 80.0) -> torch.Tensor:
    """Depth-aware pseudo ray tracing (Yang et al., ``../shared/papers/virtual-dslr-yang.txt``).

    For every output pixel ``p`` and every sample ``v`` of the aperture (a regular grid of the pupil
    square where the shape transmits, :func:`aperture_rays`), the ray is followed through the scene without building a light
    field: a scene point whose signed CoC is ``c`` is seen by that ray at ``q = p - (c / 2) v``
    (the CoC form of the paper's eq. 4, with our sign convention: in front of the focus plane
    the image is point-reflected), so the candidates ``c`` are tried from the nearest to the
    farthest (``coc_step`` apart) and the first ``q`` whose own CoC matches (within
    ``coc_step / 2 + 0.5`` px) is the front-most hit. When no candidate matches, ``p`` itself is
    used (the paper's rule against background bleeding into a focused foreground). Colours of
    the hits are averaged: ``blending="radiance"`` averages linear light (what a sensor does);
    ``"yang"`` applies the paper's eq. 5 weights ``exp(-(I_max - 255)^2 / (2 sigma^2))`` with
    ``I`` the 8-bit tone-mapped intensity (its remedy for highlights in display-referred input).
    Cat-eye is ignored (the aperture is taken at the image centre).

    Args:
        aif: ``(B, 3, H, W)`` linear RGB, finite, >= 0.
        coc: ``(B, 1, H, W)`` signed CoC diameter in px, finite.
        aperture: aperture model (default disk).
        grid: rays per pixel: the points of a ``grid x grid`` lattice inside the pupil (default: one
            per pixel of the largest CoC, as the paper's aperture mask of size K).
        coc_step: spacing of the CoC candidates along a ray, px, > 0.
        blending: ``"radiance"`` or ``"yang"``.
        sigma: eq. 5's sigma (8-bit units), > 0.

    Returns:
        ``(B, 3, H, W)`` linear RGB (float64).
    """
    d = check_baseline_inputs(aif, coc, coc_step)
    check_positive("sigma", sigma)
    if blending not in ("radiance", "yang"):
        raise ValueError(f"blending must be 'radiance' or 'yang', got {blending!r}")
    n = grid if grid is not None else max(2, int(np.ceil(float(coc.abs().max()))))
    pts = torch.from_numpy(aperture_rays(aperture or ApertureModel(), n))
    h, w = d["H"], d["W"]
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    outs = []
    for b in range(d["B"]):
        x, c = aif[b].double(), coc[b, 0].double()
        cands = torch.arange(float(c.min()), float(c.max()) + coc_step, coc_step, dtype=torch.float64)  # near -> far
        if blending == "yang":
            intensity = 255.0 * (x / (1.0 + x)).amax(dim=0)
            weight_map = torch.exp(-((intensity - 255.0) ** 2) / (2.0 * sigma**2))
        else:
            weight_map = torch.ones(h, w, dtype=torch.float64)
        acc = torch.zeros(3, h, w, dtype=torch.float64)
        wsum = torch.zeros(h, w, dtype=torch.float64)
        for vx, vy in pts.tolist():
            qy = torch.round(ys[None] - cands[:, None, None] / 2 * vy).long()  # (M, H, W)
            qx = torch.round(xs[None] - cands[:, None, None] / 2 * vx).long()
            inside = (qy >= 0) & (qy < h) & (qx >= 0) & (qx < w)
            flat = (qy.clamp(0, h - 1) * w + qx.clamp(0, w - 1))
            hit = inside & ((c.flatten()[flat] - cands[:, None, None]).abs() <= coc_step / 2 + 0.5)
            first = torch.where(hit.any(dim=0), hit.double().argmax(dim=0), torch.full((h, w), -1))
            own = (ys * w + xs).long()
            chosen = torch.where(first >= 0, flat.gather(0, first.clamp(min=0)[None])[0], own)
            wq = weight_map.flatten()[chosen]
            acc += wq * x.reshape(3, -1)[:, chosen]
            wsum += wq
        outs.append(acc / wsum)
    return torch.stack(outs)

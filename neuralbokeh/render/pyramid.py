"""Gaussian-PSF methods of Kosloff and Barsky: pyramid spreading and the tensor filter.

``../shared/papers/pyramid-spreading-tensor-filtering-kosloff-barsky.txt``. Both assume a
Gaussian PSF, here ``sigma = |c| / 4`` for a CoC diameter ``c`` (px), the same as
:func:`neuralbokeh.render.baselines.gaussian_defocus`; neither knows occlusion or the aperture
shape. :func:`gaussian_spread_reference` is the slow, readable per-pixel spread both are tested
against.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from ..core.checks import check_at_least, check_positive
from .baselines import check_baseline_inputs

SIGMA_PER_COC = 0.25  # Gaussian sigma per px of CoC diameter
_UPSAMPLE_VAR = 0.75  # variance (fine px^2) that one bilinear 2x upsampling adds
_MIN_SIGMA = 0.6  # smallest Gaussian written to a coarse level (level px): narrower ones snap to the grid


def _gaussian_taps(dist2: torch.Tensor, var: torch.Tensor) -> torch.Tensor:
    """Unnormalised Gaussian weights ``exp(-d^2 / (2 var))`` for squared distances ``d^2``;
    a variance of 0 gives a delta at ``d = 0``."""
    return torch.exp(-dist2 / (2.0 * var.clamp(min=1e-12)))


def _pixel_sigma(coc: torch.Tensor) -> torch.Tensor:
    return SIGMA_PER_COC * coc.double().abs()


def gaussian_spread_reference(aif: torch.Tensor, coc: torch.Tensor) -> torch.Tensor:
    """Slow reference: every pixel spreads its colour as a normalised, pixel-sampled Gaussian of
    ``sigma = |c| / 4`` (truncated at 3 sigma), no occlusion; beyond the frame the image is
    continued by edge replication. ``(B, 3, H, W)`` -> ``(B, 3, H, W)`` float64."""
    check_baseline_inputs(aif, coc, 1.0)
    h0, w0 = aif.shape[-2:]
    border = math.ceil(3.0 * float(_pixel_sigma(coc).max()))
    pad = (border, border, border, border)
    x, c = F.pad(aif.double(), pad, mode="replicate"), F.pad(coc.double(), pad, mode="replicate")
    out = torch.zeros_like(x)
    h, w = x.shape[-2:]
    for b in range(x.shape[0]):
        for i in range(h):
            for j in range(w):
                sigma = SIGMA_PER_COC * abs(float(c[b, 0, i, j]))
                r = max(0, math.ceil(3 * sigma))
                d = torch.arange(-r, r + 1, dtype=torch.float64)
                g = _gaussian_taps(d[:, None] ** 2 + d[None] ** 2, torch.tensor(sigma**2, dtype=torch.float64))
                g = g / g.sum()
                y0, y1, x0, x1 = max(0, i - r), min(h, i + r + 1), max(0, j - r), min(w, j + r + 1)
                out[b, :, y0:y1, x0:x1] += x[b, :, i, j, None, None] * g[y0 - i + r : y1 - i + r, x0 - j + r : x1 - j + r]
    return out[..., border : border + h0, border : border + w0]



def pyramid_spread(aif: torch.Tensor, coc: torch.Tensor, taps: int = 7) -> torch.Tensor:
    """Pyramid spreading (Kosloff and Barsky, section 5): Gaussian PSFs written to coarse levels.

    Every pixel spreads a ``taps x taps`` subpixel-positioned Gaussian into the level ``l`` where
    its PSF (``sigma = |c| / 4``) is 1-2 level pixels wide, and, linearly in ``log2 sigma``, into
    ``l + 1`` (the paper's "write to both levels" for sizes between levels). The written
    Gaussian's variance is the PSF's less what the collapse will add (bilinear 2x upsampling adds
    0.75 fine px^2 per level), so the collapsed PSF has the intended size. Levels are stored as
    flux per fine-pixel area and collapsed coarse to fine by bilinear upsampling. Pixels with
    ``sigma < 1`` stay at level 0; only pixels that have weight on a level are spread there.

    Args:
        aif: ``(B, 3, H, W)`` linear RGB, finite, >= 0.
        coc: ``(B, 1, H, W)`` signed CoC diameter in px, finite (its sign is ignored).
        taps: odd footprint width of a written Gaussian in level pixels, >= 3 (the paper: 7).

    Returns:
        ``(B, 3, H, W)`` linear RGB (float64); beyond the frame the image is continued by edge
        replication (so the border is not darkened by flux that nothing outside sends back).
    """
    check_baseline_inputs(aif, coc, 1.0)
    check_at_least("taps", taps, 3)
    if taps % 2 == 0:
        raise ValueError(f"taps must be odd, got {taps}")
    h0, w0 = aif.shape[-2:]
    border = math.ceil(3.0 * float(_pixel_sigma(coc).max()))  # edge replication, as the scatter renderer does
    pad = (border, border, border, border)
    x, sigma = F.pad(aif.double(), pad, mode="replicate"), _pixel_sigma(F.pad(coc.double(), pad, mode="replicate"))
    d = {"B": x.shape[0], "H": x.shape[-2], "W": x.shape[-1]}
    lam = torch.log2(sigma.clamp(min=1.0))
    l0 = lam.floor()
    frac = lam - l0
    top = int(l0.max()) + 1
    size = 2**top
    hp, wp = math.ceil(d["H"] / size) * size, math.ceil(d["W"] / size) * size
    ys, xs = torch.meshgrid(torch.arange(d["H"], dtype=torch.float64), torch.arange(d["W"], dtype=torch.float64), indexing="ij")
    half = taps // 2
    k = torch.arange(-half, half + 1, dtype=torch.float64)
    ky, kx = torch.meshgrid(k, k, indexing="ij")
    ky, kx = ky.reshape(-1, 1), kx.reshape(-1, 1)  # (T, 1)
    levels = []
    for level in range(top + 1):
        scale = 2.0**level
        hl, wl = hp // 2**level, wp // 2**level
        img = torch.zeros(d["B"], 3, (hl + 2 * half) * (wl + 2 * half), dtype=torch.float64)
        weight = torch.where(l0 == level, 1.0 - frac, 0.0) + torch.where(l0 == level - 1, frac, 0.0)
        for b in range(d["B"]):
            sel = weight[b, 0] > 0
            if not bool(sel.any()):
                continue
            py, px = (ys[sel] + 0.5) / scale - 0.5, (xs[sel] + 0.5) / scale - 0.5  # level-pixel coordinates
            var = (sigma[b, 0][sel] / scale) ** 2 - _UPSAMPLE_VAR / 3.0 * (1.0 - 4.0**-level)
            var = var.clamp(min=_MIN_SIGMA**2) if level > 0 else sigma[b, 0][sel] ** 2
            dy, dx = py.round() + ky, px.round() + kx  # (T, N) destination level pixels
            g = _gaussian_taps((dy - py) ** 2 + (dx - px) ** 2, var)
            g = g / g.sum(dim=0, keepdim=True)
            flux = x[b][:, sel] * weight[b, 0][sel] / scale**2  # per fine-pixel area of this level
            idx = ((dy + half) * (wl + 2 * half) + (dx + half)).long().reshape(-1)
            img[b].index_add_(1, idx, (flux[:, None, :] * g[None]).reshape(3, -1))
        levels.append(img.reshape(d["B"], 3, hl + 2 * half, wl + 2 * half)[..., half : half + hl, half : half + wl])
    out = levels[-1]
    for level in range(top - 1, -1, -1):
        out = levels[level] + F.interpolate(out, scale_factor=2, mode="bilinear", align_corners=False)
    return out[..., border : border + h0, border : border + w0]


def quadtree_sites(sigma: torch.Tensor, spacing: float = 1.0, tolerance: float = 0.25) -> list[torch.Tensor]:
    """Sites of the tensor filter: the leaves of a quadtree that compresses the blur map.

    A square block of side ``s`` (a power of two) is a leaf when its blur is large enough for
    sites ``s`` apart (``s <= max(1, spacing * min sigma)``) and nearly uniform
    (``max - min <= tolerance * max(min, 1)``), and no larger block containing it is a leaf;
    single pixels always qualify. Strongly blurred regions thus get few, large leaves and
    in-focus regions one site per pixel.

    Args:
        sigma: ``(H, W)`` Gaussian PSF sigma per pixel (px), >= 0.
        spacing: largest site spacing per px of sigma, > 0.
        tolerance: allowed relative spread of sigma inside a leaf, > 0.

    Returns:
        One ``(N_k, 4)`` float64 tensor per block size ``2^k`` (k = 0, 1, ...): rows
        ``(centre_y, centre_x, sigma, pixel_count)`` of the leaves, the sigma being the block's
        mean over its pixels inside the image.
    """
    check_positive("spacing", spacing)
    check_positive("tolerance", tolerance)
    h, w = sigma.shape
    top = max(0, int(math.floor(math.log2(max(1.0, spacing * float(sigma.max()))))))
    size = 2**top
    hp, wp = math.ceil(h / size) * size, math.ceil(w / size) * size
    s = F.pad(sigma.double()[None, None], (0, wp - w, 0, hp - h), value=float("nan"))
    inside = ~torch.isnan(s)
    covered = torch.zeros(1, 1, 1, 1, dtype=torch.bool)
    sites: list[torch.Tensor] = [torch.zeros(0, 4, dtype=torch.float64) for _ in range(top + 1)]
    for k in range(top, -1, -1):
        b = 2**k
        smax = F.max_pool2d(torch.nan_to_num(s, nan=-math.inf), b)
        smin = -F.max_pool2d(torch.nan_to_num(-s, nan=-math.inf), b)
        count = F.avg_pool2d(inside.double(), b) * b * b
        mean = F.avg_pool2d(torch.nan_to_num(s, nan=0.0), b) * b * b / count.clamp(min=1)
        ok = (b <= torch.clamp(spacing * smin, min=1.0)) & (smax - smin <= tolerance * smin.clamp(min=1.0)) & (count > 0)
        covered = covered.expand_as(ok) if covered.numel() == 1 else covered
        leaf = ok & ~covered if k > 0 else (count > 0) & ~covered
        iy, ix = torch.nonzero(leaf[0, 0], as_tuple=True)
        cy, cx = iy.double() * b + (b - 1) / 2.0, ix.double() * b + (b - 1) / 2.0
        sites[k] = torch.stack([cy, cx, mean[0, 0, iy, ix], count[0, 0, iy, ix]], dim=1)
        if k > 0:
            covered = F.interpolate((covered | leaf).double(), scale_factor=2, mode="nearest").bool()
    return sites


def _window_radius(var: torch.Tensor) -> torch.Tensor:
    """Half-width (px) of the tap window of sites with Gaussian variance ``var``: 3 sigma + 1."""
    return (3.0 * var.sqrt()).ceil().long() + 1


def _by_window(leaves: torch.Tensor, chunk_taps: int):
    """Leaves ``(N, 4)`` in groups of one window radius each, at most ``chunk_taps`` taps a group."""
    if len(leaves) == 0:
        return
    radius = _window_radius(leaves[:, 2] ** 2 / 2.0)
    for r in torch.unique(radius).tolist():
        group = leaves[radius == r]
        per = max(1, chunk_taps // (2 * r + 2) ** 2)
        for s in range(0, len(group), per):
            yield group[s : s + per]


def _gather_spread(flat: torch.Tensor, leaves: torch.Tensor, h: int, w: int, num: torch.Tensor, den: torch.Tensor) -> None:
    """Gather at ``leaves`` (one window radius) from ``flat`` ``(3, H*W)`` and spread into ``num``/``den``."""
    cy, cx, var = leaves[:, 0], leaves[:, 1], (leaves[:, 2] ** 2) / 2.0
    r = int(_window_radius(var).max())
    by, bx = cy.floor(), cx.floor()
    off = torch.arange(-r, r + 2, dtype=torch.float64)
    oy, ox = torch.meshgrid(off, off, indexing="ij")
    py, px = by[None] + oy.reshape(-1, 1), bx[None] + ox.reshape(-1, 1)  # (T, N) pixels near each site
    valid = (py >= 0) & (py < h) & (px >= 0) & (px < w)
    g = _gaussian_taps((py - cy) ** 2 + (px - cx) ** 2, var) * valid
    idx = (py.clamp(0, h - 1) * w + px.clamp(0, w - 1)).long()
    gathered = (flat[:, idx] * g).sum(dim=1) / g.sum(dim=0)  # (3, N): the gather
    spread = g * (leaves[:, 3] / g.sum(dim=0))  # a site spreads the weight of the pixels it stands for
    num.index_add_(1, idx.reshape(-1), (gathered[:, None, :] * spread[None]).reshape(3, -1))  # the spread
    den.index_add_(0, idx.reshape(-1), spread.reshape(-1))


def tensor_filter(aif: torch.Tensor, coc: torch.Tensor, spacing: float = 1.0, tolerance: float = 0.25,
                  chunk_taps: int = 2_000_000) -> torch.Tensor:
    """The tensor method (Kosloff and Barsky, section 6): a gather then a spread at quadtree sites.

    The blur operator is compressed to overlapping separable pieces, one per site
    (:func:`quadtree_sites`): each site gathers a Gaussian-weighted mean of the input around
    itself (``sigma_g = sigma / sqrt 2``) and spreads it as a Gaussian (``sigma_s`` the same, so
    the two compose to the PSF's ``sigma``). A site spreads the weight of the pixels its leaf
    stands for; dividing by the weight each output pixel receives removes the gaps and seams
    that sites at varying density would leave (where sites are uniform the divisor is ~1). Cost is roughly constant in the
    blur size: larger blur, fewer sites.

    Args:
        aif: ``(B, 3, H, W)`` linear RGB, finite, >= 0.
        coc: ``(B, 1, H, W)`` signed CoC diameter in px, finite (its sign is ignored).
        spacing: largest site spacing per px of sigma, > 0 (larger: faster, coarser).
        tolerance: allowed relative spread of sigma within a leaf, > 0.
        chunk_taps: (site, tap) pairs evaluated at once, >= 1. Sites are grouped by their own
            window size (3 sigma), so memory is O(pixels + chunk_taps) (about 100 bytes per
            tap) whatever the blur.

    Returns:
        ``(B, 3, H, W)`` linear RGB (float64).
    """
    d = check_baseline_inputs(aif, coc, 1.0)
    check_at_least("chunk_taps", chunk_taps, 1)
    x, sigma = aif.double(), _pixel_sigma(coc)
    h, w = d["H"], d["W"]
    outs = []
    for b in range(d["B"]):
        num = torch.zeros(3, h * w, dtype=torch.float64)
        den = torch.zeros(h * w, dtype=torch.float64)
        flat = x[b].reshape(3, -1)
        for level in quadtree_sites(sigma[b, 0], spacing, tolerance):
            for leaves in _by_window(level, chunk_taps):
                _gather_spread(flat, leaves, h, w, num, den)
        outs.append((num / den).reshape(3, h, w))
    return torch.stack(outs)

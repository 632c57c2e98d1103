"""Image-space ray tracing through depth layers with a spherical-aberration lens model.

After Lee, Eisemann and Seidel, "Real-time lens blur effects and focus control"
(``../shared/papers/real-time-lens-blur-lee-eisemann-seidel-wordlist.txt``, a word list of the
paper): the scene is a stack of depth-peeled layers; rays from each sensor pixel through
samples of the aperture are refracted by a lens with spherical surfaces and intersected with
the layers in image space, the search along each ray narrowed with a min/max depth hierarchy.

What we have and what we do:

* **Layers.** Our input is one view (AIF + CoC), so layer 0 is the input itself. Layer 1 is
  the surface hidden behind layer 0's near side of every depth discontinuity, hallucinated by
  extending the farther side under the nearer one (colour and depth of the farthest
  neighbour, grown pixel by pixel up to the largest CoC radius); elsewhere layer 1 is empty.
* **Lens.** A ray from pixel ``p`` through the unit-pupil point ``u`` meets a scene point of
  signed CoC ``c`` (px, negative in front of the focus) at image position
  ``q = p - (c + sa * g(|u|)) / 2 * u``: a thin lens when ``sa = 0``. ``g`` is the zone
  profile of a spherical singlet's longitudinal aberration, traced exactly with Snell's law
  through its two spherical surfaces (:func:`singlet_zone_profile`, ``g(0) = 0``,
  ``g(1) = 1``); ``sa`` (px) is the CoC offset of the marginal rays. ``sa > 0`` is an
  under-corrected lens (marginal rays focus nearer the lens, as in any simple positive lens):
  bokeh behind the focus gets a bright centre and bokeh in front a bright rim.
* **Search.** ``T_i`` holds, at the image's resolution, the min/max layer CoC over the
  ``(2^(i+1) + 1)^2`` square around each pixel. The CoC interval a pixel's rays can hit is
  narrowed by clamping it to ``T`` over the interval's own footprint, three times; the rays
  then march ``steps`` samples through what is left, near to far, and the first sample at or
  just behind a layer's surface is the hit (nearest layer wins). Pixels whose interval leaves
  all rays within half a pixel of themselves are not traced (their own colour is the answer).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from ..core.apertures import ApertureModel
from ..core.checks import check_at_least, check_finite, check_positive
from .baselines import aperture_rays, check_baseline_inputs

_REFINE = 3  # narrowing passes of the min/max search


def refract(d: np.ndarray, n: np.ndarray, eta: float) -> np.ndarray:
    """Snell's law for unit direction ``d`` at unit normal ``n`` (facing against ``d``),
    ``eta = n_in / n_out``; rows of ``(M, 2)``."""
    cos_i = -(d * n).sum(axis=1, keepdims=True)
    k = 1.0 - eta**2 * (1.0 - cos_i**2)
    if (k < 0).any():
        raise ValueError("total internal reflection in the singlet: lower the f-number's aperture or the bending")
    return eta * d + (eta * cos_i - np.sqrt(k)) * n


def _hit_sphere(o: np.ndarray, d: np.ndarray, vertex_z: float, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Intersections of rays (rows ``(y, z)``) with the spherical surface of vertex ``vertex_z``
    on the axis and signed radius ``radius`` (centre at ``vertex_z + radius``); point and the
    unit normal facing the incoming ray."""
    centre = np.array([0.0, vertex_z + radius])
    oc = o - centre
    b = (oc * d).sum(axis=1)
    disc = b**2 - ((oc**2).sum(axis=1) - radius**2)
    if (disc < 0).any():
        raise ValueError(f"a ray misses the singlet's surface of radius {radius:.3f}: the aperture is too large for it")
    t = -b - np.sign(radius) * np.sqrt(disc)  # the cap nearest the vertex
    p = o + t[:, None] * d
    normal = (p - centre) / radius  # points towards the centre's far side: against d on both surfaces
    return p, -np.sign((normal * d).sum(axis=1, keepdims=True)) * normal


def singlet_zone_profile(rho: np.ndarray, index: float = 1.5168, bending: float = 0.7,
                         f_number: float = 2.0, thickness: float = 0.1) -> np.ndarray:
    """Normalised longitudinal spherical aberration of a spherical singlet by pupil zone.

    Rays parallel to the axis at height ``rho`` times the marginal height are traced through
    the two spherical surfaces with Snell's law (focal length 1, radii from the lensmaker's
    equation and the Coddington shape factor ``bending = (R2 + R1) / (R2 - R1)``); the axis
    crossing's shift from the paraxial focus is divided by the marginal ray's.

    Args:
        rho: pupil zones in ``[0, 1]`` (any shape).
        index: refractive index of the glass (default N-BK7 at 587.6 nm), > 1.
        bending: shape factor, in ``(-1, 1)`` (0: equiconvex; about 0.7 is a singlet's minimum
            spherical aberration for a distant object).
        f_number: sets the marginal ray height ``1 / (2 N)``, > 0.
        thickness: centre thickness in focal lengths, >= 0.

    Returns:
        ``g(rho)`` with ``g(0) = 0`` and ``g(1) = 1`` (about ``rho^2`` for a slow lens).
    """
    check_positive("index - 1", index - 1.0)
    check_positive("f_number", f_number)
    check_at_least("thickness", thickness, 0.0)
    if not -1.0 < bending < 1.0:
        raise ValueError(f"bending must be in (-1, 1), got {bending}")
    rho = np.asarray(rho, dtype=np.float64)
    if (rho < 0).any() or (rho > 1).any():
        raise ValueError(f"rho must be in [0, 1], got values in [{rho.min()}, {rho.max()}]")
    r1 = 2.0 * (index - 1.0) / (bending + 1.0)
    r2 = 2.0 * (index - 1.0) / (bending - 1.0)

    def focus(heights: np.ndarray) -> np.ndarray:
        o = np.stack([heights, np.full_like(heights, -1.0)], axis=1)
        d = np.tile([0.0, 1.0], (len(heights), 1))
        p, n = _hit_sphere(o, d, 0.0, r1)
        d = refract(d, n, 1.0 / index)
        p, n = _hit_sphere(p, d, thickness, r2)
        d = refract(d, n, index)
        return p[:, 1] - p[:, 0] * d[:, 1] / d[:, 0]  # where the ray crosses the axis

    h = 0.5 / f_number
    flat = np.maximum(rho.reshape(-1), 1e-6)  # the axial ray itself never crosses the axis
    lsa = focus(np.concatenate([flat * h, [1e-4 * h, h]]))
    paraxial, marginal = lsa[-2], lsa[-1]
    return ((lsa[:-2] - paraxial) / (marginal - paraxial)).reshape(rho.shape)


def hidden_layer(aif: torch.Tensor, coc: torch.Tensor, gap: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """The second depth layer of one view: the far side of each depth edge grown under the near side.

    Args:
        aif: ``(3, H, W)`` linear RGB.
        coc: ``(H, W)`` signed CoC in px.
        gap: a pixel is an occluder when some pixel within the largest CoC radius is more than
            ``gap`` px of CoC farther (> 0).

    Returns:
        ``(colour (3, H, W), coc (H, W))`` of layer 1; ``coc`` is ``nan`` where the layer is empty.
    """
    check_positive("gap", gap, " px")
    radius = max(1, math.ceil(float(coc.abs().max()) / 2.0))
    farthest = F.max_pool2d(coc[None, None], 2 * radius + 1, stride=1, padding=radius)[0, 0]
    todo = farthest - coc > gap
    col, c = aif.clone(), torch.where(todo, torch.tensor(-math.inf, dtype=coc.dtype), coc)
    h, w = coc.shape
    for _ in range(radius):
        if not bool((todo & torch.isinf(c)).any()):
            break
        cand = F.pad(c[None, None], (1, 1, 1, 1), value=-math.inf)
        windows = F.unfold(cand, 3)[0].reshape(9, h, w)  # the 3x3 neighbours' CoC
        best, which = windows.max(dim=0)
        grow = torch.isinf(c) & (best > coc + gap)  # only from surfaces behind the occluder
        if not bool(grow.any()):
            break
        dy, dx = which // 3 - 1, which % 3 - 1
        ys, xs = torch.nonzero(grow, as_tuple=True)
        sy, sx = ys + dy[grow], xs + dx[grow]
        col[:, ys, xs] = col[:, sy, sx]
        c = c.clone()
        c[ys, xs] = c[sy, sx]
    return col, torch.where(todo & torch.isfinite(c), c, torch.tensor(math.nan, dtype=coc.dtype))


def _minmax_hierarchy(c: torch.Tensor, levels: int) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """``T_i`` for i < levels: min/max of ``c`` (``(H, W)``, nan = empty) over the square of
    radius ``2^i`` around each pixel, at full resolution (empty squares: min +inf, max -inf)."""
    hi = torch.nan_to_num(c, nan=-math.inf)[None, None]
    lo = torch.nan_to_num(-c, nan=-math.inf)[None, None]
    out = []
    for i in range(levels):
        r = 2**i
        out.append((-F.max_pool2d(lo, 2 * r + 1, stride=1, padding=r)[0, 0], F.max_pool2d(hi, 2 * r + 1, stride=1, padding=r)[0, 0]))
    return out


def lens_ray_trace(aif: torch.Tensor, coc: torch.Tensor, aperture: ApertureModel | None = None,
                   spherical_aberration_px: float = 0.0, grid: int = 8, steps: int = 16,
                   layers: int = 2, bending: float = 0.7, index: float = 1.5168) -> torch.Tensor:
    """Layered image-space ray tracing with a spherical-aberration lens (see the module docstring).

    Args:
        aif: ``(B, 3, H, W)`` linear RGB, finite, >= 0.
        coc: ``(B, 1, H, W)`` signed CoC diameter in px, finite (negative in front of the focus).
        aperture: aperture model (default disk); rays go through the points of a
            ``grid x grid`` lattice inside its shape (cat-eye ignored).
        spherical_aberration_px: CoC offset of the marginal rays in px (0: a thin lens;
            > 0: under-corrected).
        grid: pupil lattice size, >= 2.
        steps: samples per ray in the narrowed interval, >= 2.
        layers: 1 (the input view only) or 2 (with the hallucinated hidden layer).
        bending, index: the singlet whose zone profile shapes the aberration
            (:func:`singlet_zone_profile`).

    Returns:
        ``(B, 3, H, W)`` linear RGB (float64): the mean colour of each pixel's rays.
    """
    d = check_baseline_inputs(aif, coc, 1.0)
    check_finite("spherical_aberration_px", spherical_aberration_px, " px")
    check_at_least("grid", grid, 2)
    check_at_least("steps", steps, 2)
    if layers not in (1, 2):
        raise ValueError(f"layers must be 1 or 2, got {layers}")
    sa = float(spherical_aberration_px)
    pts = aperture_rays(aperture or ApertureModel(), grid)
    # the zone profile ends at the rim: corners of a square pupil take its value there
    rho = np.minimum(np.hypot(pts[:, 0], pts[:, 1]), 1.0)
    shift = sa * singlet_zone_profile(rho, index=index, bending=bending) if sa != 0 else np.zeros(len(pts))
    h, w = d["H"], d["W"]
    outs = []
    for b in range(d["B"]):
        x, c = aif[b].double(), coc[b, 0].double()
        stack = [(x, c)] + ([hidden_layer(x, c)] if layers == 2 else [])
        outs.append(_trace_view(x, c, stack, torch.from_numpy(pts), torch.from_numpy(shift), sa, steps, h, w))
    return torch.stack(outs)


def _search_interval(c: torch.Tensor, layer_c: torch.Tensor, sa: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Per pixel, the CoC interval ``[a, b]`` its rays can hit in one layer (``a > b``: none)."""
    cmax = float(torch.nan_to_num(layer_c.abs(), nan=0.0).max()) + abs(sa)
    levels = max(1, math.ceil(math.log2(cmax / 2.0 + 2.0)) + 1)
    tables = _minmax_hierarchy(layer_c, levels)
    a = torch.full_like(c, float(torch.nan_to_num(layer_c, nan=math.inf).min()))
    b = torch.full_like(c, float(torch.nan_to_num(layer_c, nan=-math.inf).max()))
    if not bool(torch.isfinite(a[0, 0])):
        return a, b  # an empty layer: +inf > -inf everywhere
    for _ in range(_REFINE):
        reach = (torch.maximum(a.abs(), b.abs()) + abs(sa)) / 2.0 + 1.0  # footprint radius, px
        reach = torch.where(a <= b, reach, 1.0)  # an empty interval stays empty
        level = torch.ceil(torch.log2(reach.clamp(min=1.0))).long().clamp(max=levels - 1)
        lo = torch.stack([t[0] for t in tables]).gather(0, level[None])[0]
        hi = torch.stack([t[1] for t in tables]).gather(0, level[None])[0]
        a, b = torch.maximum(a, lo), torch.minimum(b, hi)
    return a, b


def _trace_view(x: torch.Tensor, c: torch.Tensor, stack: list[tuple[torch.Tensor, torch.Tensor]], pts: torch.Tensor,
                shift: torch.Tensor, sa: float, steps: int, h: int, w: int) -> torch.Tensor:
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    intervals = [_search_interval(c, lc, sa) for _, lc in stack]
    reach = torch.zeros_like(c)
    for a, b in intervals:
        ok = a <= b
        reach = torch.maximum(reach, torch.where(ok, (torch.maximum(a.abs(), b.abs()) + abs(sa)) / 2.0, 0.0))
    active = reach >= 0.5  # elsewhere every ray lands on the pixel itself
    out = x.clone()
    if not bool(active.any()):
        return out
    py, px = ys[active], xs[active]
    t = torch.linspace(0.0, 1.0, steps, dtype=torch.float64)[:, None]
    acc = torch.zeros(3, len(py), dtype=torch.float64)
    flat_layers = [(col.reshape(3, -1), torch.nan_to_num(lc, nan=math.inf).reshape(-1)) for col, lc in stack]
    own = (py * w + px).long()
    for (ux, uy), s in zip(pts.tolist(), shift.tolist()):
        best = torch.full((len(py),), math.inf, dtype=torch.float64)  # CoC of the nearest hit so far
        colour = x.reshape(3, -1)[:, own]  # no hit in any layer: the pixel itself
        for (lcol, lc), (a, b) in zip(flat_layers, intervals):
            ok = a[active] <= b[active]
            if not bool(ok.any()):
                continue
            a_, b_ = torch.where(ok, a[active], 0.0), torch.where(ok, b[active], 0.0)
            cs = a_ + (b_ - a_) * t  # (steps, N) candidate CoCs, near to far
            qy = torch.round(py - (cs + s) / 2.0 * uy)
            qx = torch.round(px - (cs + s) / 2.0 * ux)
            inside = (qy >= 0) & (qy < h) & (qx >= 0) & (qx < w)
            idx = (qy.clamp(0, h - 1) * w + qx.clamp(0, w - 1)).long()
            f = lc[idx] - cs  # > 0: the ray is still in front of the layer's surface there
            hit = inside & ok & (f <= 0) & (f >= -((b_ - a_) / (steps - 1) + 1.0))
            k = hit.double().argmax(dim=0, keepdim=True)  # the first hit, near to far
            c_hit = torch.where(hit.any(dim=0), cs.gather(0, k)[0], math.inf)
            take = c_hit < best  # layers compete by depth (each has its own interval)
            colour = torch.where(take[None], lcol[:, idx.gather(0, k)[0]], colour)
            best = torch.minimum(best, c_hit)
        acc += colour
    out[:, active] = acc / len(pts)
    return out

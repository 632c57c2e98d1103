"""Bucketed near / mid / far gather with summing to saturation.

After the "stochastic blur" stage of ``../shared/papers/lightfield-compression-playback-patent.txt``
(sections "Multi-Depth View Blur", "Buckets" and "Occlusion"), with every sample pixel of the
volume of confusion summed (the patent's exact form; its stochastic sample patterns are a speed
device, left out so the result is deterministic):

* A sample pixel ``s`` contributes to the centre pixel ``p`` with the weight its own defocus
  kernel puts on ``p``: ``w = K_{c(s)}(p - s)`` (the patent's "area of the intersection of the
  sample's region with the CoC of radius C_s, divided by the CoC's area", with our aperture
  shape in place of the circle). The patent's lambda depth is our signed CoC ``c`` (px,
  negative in front of the focus plane): both are linear in inverse depth.
* Samples go to three buckets by depth relative to the centre pixel: *near*
  (``c(s) < c(p) - spread``), *mid* and *far* (``c(s) > c(p) + spread``); within
  ``spread / 2`` of a boundary a sample is shared between the two buckets linearly.
* The buckets are combined near -> mid -> far with sum-to-saturation: once the weights reach
  one, farther colour only fills what is left, so samples likely hidden are dropped.
* Occlusion: when the total weight stays below one (colour was hidden), the rest is filled
  with the far bucket's colour (the patent's first estimate of the occluded colour), or, with
  no far samples, the sum is normalised by its weight.
"""

from __future__ import annotations

import torch

from ..core.apertures import ApertureModel
from ..core.checks import check_positive
from .baselines import check_baseline_inputs


def _kernel_table(aperture: ApertureModel, lo: int, hi: int, radius: int, like: torch.Tensor) -> torch.Tensor:
    """``(levels, 3, 2r+1, 2r+1)`` kernels at integer signed CoC levels ``lo..hi`` (px), centred
    and zero-padded to one size; in-front (negative) levels point-reflected as in the scatter."""
    size = 2 * radius + 1
    table = torch.zeros(hi - lo + 1, 3, size, size, dtype=like.dtype, device=like.device)
    for i, level in enumerate(range(lo, hi + 1)):
        k = torch.from_numpy(aperture.psf(float(level))).to(like)
        r = k.shape[-1] // 2
        table[i, :, radius - r : radius + r + 1, radius - r : radius + r + 1] = k
    return table


def _sum_to_saturation(ca: torch.Tensor, wa: torch.Tensor, cb: torch.Tensor, wb: torch.Tensor):
    """The patent's Sum-to-saturation of weighted colours ``(c, w)`` (``c`` premultiplied by
    ``w``): plain sum while ``wa + wb <= 1``, else ``b`` fills only ``1 - wa``; ``a`` must
    already be saturated or below (``wa <= 1``)."""
    room = (1.0 - wa).clamp(min=0.0)
    take = torch.where(wa + wb <= 1.0, torch.ones_like(wb), room / wb.clamp(min=1e-300))
    return ca + cb * take, wa + wb * take


def bucket_gather(aif: torch.Tensor, coc: torch.Tensor, aperture: ApertureModel | None = None,
                  spread: float | None = None) -> torch.Tensor:
    """Bucketed near/mid/far gather with sum-to-saturation (see the module docstring).

    Args:
        aif: ``(B, 3, H, W)`` linear RGB, finite, >= 0.
        coc: ``(B, 1, H, W)`` signed CoC diameter in px, finite (negative in front of the focus).
        aperture: aperture model (default disk); taken at the image centre (cat-eye ignored).
        spread: bucket spread in px of CoC, > 0: samples within ``spread`` of the centre pixel's
            CoC go to the mid bucket. Default: ``max(1, 0.05 * (max(c) - min(c)))``, the patent's
            "small constant times the range of lambda depths in the scene".

    Returns:
        ``(B, 3, H, W)`` linear RGB (float64). Cost: ``(2R + 1)^2`` passes over the image with
        ``R`` the largest CoC radius, so an in-focus scene costs one pass.
    """
    d = check_baseline_inputs(aif, coc, 1.0)
    aperture = aperture or ApertureModel()
    x, c = aif.double(), coc.double()
    lo, hi = int(torch.floor(c.min())), int(torch.ceil(c.max()))
    if spread is None:
        spread = max(1.0, 0.05 * (hi - lo))
    check_positive("spread", spread, " px")
    radius = max(aperture.kernel_radius_px(float(max(abs(lo), abs(hi)))), 0)
    table = _kernel_table(aperture, lo, hi, radius, x)  # (L, 3, k, k)
    level = (c - lo).clamp(0, hi - lo)  # fractional index into the table, (B, 1, H, W)
    l0 = level.floor().long().clamp(max=max(hi - lo - 1, 0))
    frac = level - l0
    l1 = (l0 + 1).clamp(max=hi - lo)
    h, w = d["H"], d["W"]
    pad = (radius, radius, radius, radius)
    xp = torch.nn.functional.pad(x, pad, mode="replicate")  # samples beyond the frame: edge replication
    cp = torch.nn.functional.pad(c, pad, mode="replicate")
    l0p = torch.nn.functional.pad(l0.double(), pad, mode="replicate").long()
    l1p = torch.nn.functional.pad(l1.double(), pad, mode="replicate").long()
    fp = torch.nn.functional.pad(frac, pad, mode="replicate")
    zeros = torch.zeros_like(x)
    acc = {k: (zeros.clone(), zeros.clone()) for k in ("near", "mid", "far")}
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            ys, xs = slice(radius + dy, radius + dy + h), slice(radius + dx, radius + dx + w)
            cs = cp[..., ys, xs]
            # the sample s = p + (dy, dx) puts K_{c(s)}(p - s) = K[r - dy, r - dx] on p
            k0 = table[:, :, radius - dy, radius - dx]  # (L, 3)
            f = fp[..., ys, xs]
            ws = (1 - f) * k0[l0p[:, 0, ys, xs]].permute(0, 3, 1, 2) + f * k0[l1p[:, 0, ys, xs]].permute(0, 3, 1, 2)
            if not bool((ws > 0).any()):
                continue
            rel = cs - c  # > 0: the sample is behind the centre pixel
            t_near = (0.5 - (rel + spread) / spread).clamp(0.0, 1.0)
            t_far = (0.5 + (rel - spread) / spread).clamp(0.0, 1.0)
            t_mid = 1.0 - t_near - t_far
            col = xp[..., ys, xs]
            for name, t in (("near", t_near), ("mid", t_mid), ("far", t_far)):
                cw, ww = acc[name]
                cw += t * ws * col
                ww += t * ws
    (cn, wn), (cm, wm), (cf, wf) = acc["near"], acc["mid"], acc["far"]
    over = wn > 1.0  # a near bucket alone beyond saturation is normalised to weight one
    cn, wn = torch.where(over, cn / wn.clamp(min=1e-300), cn), torch.where(over, torch.ones_like(wn), wn)
    col, wt = _sum_to_saturation(cn, wn, cm, wm)
    col, wt = _sum_to_saturation(col, wt, cf, wf)
    far_colour = cf / wf.clamp(min=1e-300)
    filled = col + (1.0 - wt).clamp(min=0.0) * far_colour
    normalised = col / wt.clamp(min=1e-300)
    return torch.where((wt < 1.0) & (wf > 0), filled, torch.where(wt < 1.0, normalised, col))

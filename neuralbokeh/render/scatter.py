"""Occlusion-aware layered scatter: the reference defocus renderer.

Linear HDR in, linear HDR out. The scene is a stack of fronto-parallel layers, each with
premultiplied colour ``C`` and coverage ``A`` and one signed CoC ``c`` (px, negative in front of
the focus plane). Each layer is *scattered*: every pixel spreads its colour and coverage over
the aperture kernel at diameter ``|c|`` (point-reflected for ``c < 0``), and the blurred layers
are composited back to front with "over"::

    C_out <- K*C + (1 - K*A) C_out,    A_out <- K*A + (1 - K*A) A_out

For a scene that *is* such a stack (:func:`scatter_layers`, e.g. the synthetic generator, which
knows every layer in full) this is exact. Each layer's scatter conserves flux (kernels sum to
1; beyond the frame a layer repeats its edge ring, :func:`_pad`, so a uniform plane stays
uniform and a point source on the frame's edge is not laid out as a streak).

What it approximates for an all-in-focus image plus a depth map (:func:`render_defocus`,
:func:`scatter_defocus`), i.e. non-layered scenes:

* Depth is sliced into layers of equal signed-CoC width ``coc_step`` (default 0.5 px); each
  slice is blurred with the kernel at its pixels' mean CoC, so a sloped surface is
  staircased with a CoC error of at most ``coc_step / 2``.
* Slices of one continuous surface must not occlude each other: a thin slice's blurred
  coverage is fractional, and "over" of many such slices lets what lies behind show through
  a blurred foreground (its silhouette stays sharp over the background). With
  ``occlusion="surface"`` (default) a slice hides only the slices more than ``jump_px``
  behind it (a depth discontinuity; nearer ones add up side by side), and of those only the
  light that does not fit beside the surface it belongs to (the far light, coverage ``A``,
  is scaled to fit into ``1 - a``, ``a`` the coverage of the slices within ``jump_px``, only
  where ``a + A > 1``; exact when the ray bundles are nested, i.e. both behind or both in
  front of the focus plane). ``occlusion="over"`` treats every slice as a complete layer.
* What a foreground hides in the all-in-focus image is unknown. Its hole in the layers behind
  leaves the accumulated coverage below 1 where a blurred foreground edge becomes partly
  transparent. ``fill="background"`` (default) fills that shortfall with the visible
  background around the occluder (:func:`neuralbokeh.ops.holes.hidden_background`), which
  is what a lens sees through a blurred edge; ``fill="normalize"`` divides by the coverage
  (the foreground's own colours fill the hole, so it looks opaque); ``"none"`` leaves it dark.
* ``coc_step`` 0.5, ``jump_px`` 4 and the two defaults above were chosen on Mitsuba renders of a
  scene with continuous depth against the alternatives (``benchmarks/bench_continuous.py``; the
  figures are in ``docs/benchmarks.md``): a coarser ``coc_step`` smears blurred highlights, a
  finer one gains nothing.
* Partial occlusion inside the lens (a point seen around the edge of a nearer object from
  part of the aperture) is modelled only through the layer order, as in all layered methods.
* Cat-eye kernels vary continuously over the image; they are evaluated on a
  ``field_grid x field_grid`` grid of image positions and interpolated bilinearly, linear in
  the source (each source pixel scatters the bilinear blend of its four nodes' kernels). The
  error falls about linearly with the node spacing (a clipped edge moves between nodes); the
  default grid keeps neighbouring nodes' clip circles within 0.5 px (:func:`auto_field_grid`).
  Each node convolves only its own support, so a fine grid costs little more than a coarse one.
  Kernels carry the bokeh *shape* only (each sums to 1: the vignetting fall-off is taken as
  flat-fielded), and each source pixel's kernel is the one of its own image position, as a
  path tracer with the same pupil model would give: a clipped pupil moves the spot's centroid
  (towards the image centre behind the focus plane, away from it in front), so each source's
  flux is conserved but a defocused uniform plane is not exactly uniform - the light density
  changes by about ``2 * cat_eye * (CoC/2) / half_diagonal`` (13% for a 21 px CoC on a 64 px
  image, ~1% at 1920 px with a 41 px CoC). Coverage, being geometric, is always divided by
  the layer's scatter of a uniform field (an opaque plane stays fully opaque). With
  ``preserve_uniform=True`` colour is divided too: a uniform plane stays exactly uniform and
  flux moves by that much instead. The two agree exactly, and the step is skipped,
  for spatially invariant kernels.

Leaves out what a scene does not need: layers with ``|c| < 1`` px are composited without any
convolution, empty slices and empty (layer, grid node) pairs are skipped.
"""

from __future__ import annotations

import logging
from typing import Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from ..core.apertures import ApertureModel, field_position
from ..core.checks import check_finite, check_in_range, check_nonnegative, check_positive, check_shape
from ..core.optics import ThinLens
from ..ops.fftconv import fft_convolve2d
from ..ops.holes import hidden_background
from ..ops.tiles import edge_ring

log = logging.getLogger(__name__)

_EPS_COVERAGE = 1e-6
OCCLUSION_MODES = ("surface", "over")
FILL_MODES = ("background", "normalize", "none")


def _node_positions(size: int, grid: int) -> np.ndarray:
    return np.linspace(0.0, size - 1.0, grid) if grid > 1 else np.array([(size - 1) / 2.0])


def _tent_weights(size: int, nodes: np.ndarray) -> np.ndarray:
    """(G, size) bilinear (tent) weights of pixels w.r.t. nodes; columns sum to 1."""
    if len(nodes) == 1:
        return np.ones((1, size))
    x = np.arange(size, dtype=np.float64)
    spacing = nodes[1] - nodes[0]
    return np.clip(1.0 - np.abs(x[None, :] - nodes[:, None]) / spacing, 0.0, None)


def _pad(x: torch.Tensor, p: int) -> torch.Tensor:
    """``(C, H, W)`` padded by ``p`` px all round with its edge ring repeated
    (:func:`~neuralbokeh.ops.tiles.edge_ring`, every channel's 1 px peaks along the edge clipped),
    as the lens network's tiles pad their colour: an extended surface goes on beyond the frame, a
    point source cut by the frame's edge does not. Against Mitsuba's renders, which see the scene
    beyond the frame, it measured ahead of a mirror (``docs/benchmarks.md``, "The edge ring")."""
    if p == 0:
        return x
    return F.pad(edge_ring(x[None], light=x.shape[0]), (p - 1,) * 4, mode="replicate")[0]


def _pad_1d(weights: torch.Tensor, p: int) -> torch.Tensor:
    """Pad (G, size) weights along size as the image is padded: a padding pixel takes its edge pixel's."""
    return weights if p == 0 else F.pad(weights[None], (p, p), mode="replicate")[0]


def auto_field_grid(aperture: ApertureModel, max_coc_px: float, height: int, width: int, max_shift_px: float = 0.5) -> int:
    """Grid size for cat-eye kernels so neighbouring nodes' clip circles differ by <= ``max_shift_px``.

    The clip circle moves ``cat_eye * r`` px per unit of field position (r = CoC radius), and
    neighbouring nodes are ``(size - 1) / (G - 1) / half_diagonal`` field units apart. Returns 1
    for spatially invariant apertures; at most 65.
    """
    if not aperture.spatially_varying:
        return 1
    r = 0.5 * max_coc_px * max(aperture.channel_scale)
    half_diag = 0.5 * float(np.hypot(height - 1, width - 1)) or 1.0
    span = (max(height, width) - 1) / half_diag
    grid = int(np.ceil(1 + aperture.cat_eye * r * span / max_shift_px))
    if grid > 65:
        log.warning("cat-eye needs a %d x %d kernel grid for %.1f px accuracy; capped at 65", grid, grid, max_shift_px)
    return int(min(max(grid, 2), 65))


def _kernel_stacks(aperture: ApertureModel, coc: float, fields: np.ndarray, pad: int, n_a: int, n_u: int) -> np.ndarray:
    """``(M, 3 + n_a + n_u, 2 pad + 1, 2 pad + 1)`` kernels for colour, coverage and uniform-field
    channels at ``(M, 2)`` field positions."""
    k = aperture.psfs_at(coc, fields)
    out = np.zeros(k.shape[:2] + (2 * pad + 1, 2 * pad + 1))
    o = pad - k.shape[-1] // 2
    out[..., o : o + k.shape[-2], o : o + k.shape[-1]] = k
    parts = [out, out if n_a == 3 else out[:, 1:2]]
    if n_u:
        parts.append(out if n_u == 3 else out[:, 1:2])
    return np.concatenate(parts, 1)


def _scatter_layer(
    src: torch.Tensor,
    coc: float,
    aperture: ApertureModel,
    grid: int,
    pad: int,
    n_a: int,
    n_u: int,
    chunk: int,
    preserve_uniform: bool,
) -> tuple[torch.Tensor, int]:
    """Scatter one layer's ``src = [C (3), A (n_a)]`` (H, W); returns ``[C', A']`` and #convolutions.

    The layer is padded by ``pad`` (:func:`_pad`); with a kernel grid each node convolves only its
    own tent support (a crop), and the full convolution of the crop is added onto a canvas.
    """
    _, h, w = src.shape
    rows, cols = _node_positions(h, grid), _node_positions(w, grid)
    wr = _pad_1d(torch.as_tensor(_tent_weights(h, rows), dtype=src.dtype, device=src.device), pad)
    wc = _pad_1d(torch.as_tensor(_tent_weights(w, cols), dtype=src.dtype, device=src.device), pad)
    padded = _pad(src, pad)
    ones = torch.ones((n_u,) + padded.shape[1:], dtype=src.dtype, device=src.device)
    nodes: list[tuple[torch.Tensor, tuple[float, float], int, int]] = []
    for a in range(grid):
        r_idx = torch.nonzero(wr[a]).flatten()
        r0, r1 = int(r_idx[0]), int(r_idx[-1]) + 1
        for b in range(grid):
            c_idx = torch.nonzero(wc[b]).flatten()
            c0, c1 = int(c_idx[0]), int(c_idx[-1]) + 1
            weight = wr[a][r0:r1, None] * wc[b][None, c0:c1]
            part = padded[:, r0:r1, c0:c1] * weight
            if n_u:  # the uniform field is needed wherever this layer's light can land
                part = torch.cat([part, ones[:, r0:r1, c0:c1] * weight], 0)
            elif not bool((part[3:] > 0).any()):
                continue  # nothing of this layer near this node
            nodes.append((part, field_position(rows[a], cols[b], h, w), r0, c0))
    kernels = _kernel_stacks(aperture, coc, np.asarray([n[1] for n in nodes]), pad, n_a, n_u) if nodes else []
    work: dict[tuple[int, int], list[tuple[torch.Tensor, np.ndarray, int, int]]] = {}
    for (part, _, r0, c0), k in zip(nodes, kernels):
        work.setdefault(tuple(part.shape[1:]), []).append((part, k, r0, c0))
    canvas = torch.zeros((3 + n_a + n_u, h + 4 * pad, w + 4 * pad), dtype=src.dtype, device=src.device)
    n_conv = 0
    for (bh, bw), jobs in work.items():
        for s in range(0, len(jobs), chunk):
            part = jobs[s : s + chunk]
            x = torch.stack([j[0] for j in part])
            k = torch.as_tensor(np.stack([j[1] for j in part]), device=src.device)
            y = fft_convolve2d(x, k, compute_dtype=torch.float64, mode="full")
            for (_, _, r0, c0), yi in zip(part, y):
                canvas[:, r0 : r0 + bh + 2 * pad, c0 : c0 + bw + 2 * pad] += yi
            n_conv += len(part)
    out = canvas[:, 2 * pad : 2 * pad + h, 2 * pad : 2 * pad + w].clamp_min(0.0)  # FFT round-off
    if n_u:
        # Coverage is geometric: an opaque plane covers every pixel fully however its light
        # drifts, so coverage is always divided by the scatter of a uniform field; colour only
        # when asked to keep uniform planes uniform (module doc).
        u = out[3 + n_a :].clamp_min(_EPS_COVERAGE)
        color = out[:3] / u.expand(3, h, w) if preserve_uniform else out[:3]
        out = torch.cat([color, out[3 : 3 + n_a] / u], 0)
    return out, n_conv


def _composite(
    layer_fn: Callable[[int], tuple[torch.Tensor, torch.Tensor]],
    cocs: list[float],
    aperture: ApertureModel,
    shape: tuple[int, int],
    like: torch.Tensor,
    field_grid: int | None,
    fill: str,
    chunk: int,
    preserve_uniform: bool = False,
    surface_px: float = 0.0,
    background: torch.Tensor | None = None,
) -> torch.Tensor:
    """Scatter and composite layers far to near; ``layer_fn(i)`` gives ``(C (3,H,W), A (1,H,W))``.

    A layer hides (``"over"``) only the layers more than ``surface_px`` behind it (0: every
    layer behind it, as for complete layers); the others add up as parts of one surface.
    ``fill``: ``"normalize"``, ``"background"`` (needs ``background``, ``(3, H, W)``) or
    ``"none"`` (see the module doc). Only one layer's blurred maps are alive at a time: memory
    does not grow with the layers.
    """
    _check_composite(fill, background, field_grid, chunk)
    h, w = shape
    n_a = 3 if aperture.chromatic else 1
    max_coc = max([abs(c) for c in cocs] + [0.0])
    pad = aperture.kernel_radius_px(max_coc)
    if not aperture.spatially_varying:
        grid = 1
    else:
        grid = field_grid or auto_field_grid(aperture, max_coc, h, w)
    n_u = n_a if grid > 1 else 0  # channels of the uniform-field response
    out_c = torch.zeros((3, h, w), dtype=like.dtype, device=like.device)  # slices that others hide
    out_a = torch.zeros((n_a, h, w), dtype=like.dtype, device=like.device)
    window: list[tuple[float, torch.Tensor, torch.Tensor]] = []  # within surface_px of the current slice
    win_a = torch.zeros_like(out_a)  # their coverage
    n_conv = 0
    for i in sorted(range(len(cocs)), key=lambda j: -cocs[j]):  # far to near
        c = cocs[i]
        color, alpha = layer_fn(i)
        if not bool((alpha > 0).any()):
            continue
        src = torch.cat([color, alpha.expand(n_a, h, w)], 0)
        if aperture.kernel_radius_px(abs(c)) == 0:
            blurred = src  # in focus: a delta kernel, nothing to compute
        else:
            blurred, n = _scatter_layer(src, c, aperture, grid, pad, n_a, n_u, chunk, preserve_uniform)
            n_conv += n
        cc, aa = blurred[:3], blurred[3:].clamp(0.0, 1.0)
        while window and (surface_px <= 0 or window[0][0] > c + surface_px):  # more than surface_px behind: now hidden by nearer slices
            _, wc, wa = window.pop(0)
            out_c, out_a, win_a = out_c + wc, out_a + wa, win_a - wa
        window.append((c, cc, aa))
        win_a = win_a + aa
        if surface_px > 0:  # hide only the light that does not fit beside this surface's (see module doc)
            keep = ((1.0 - win_a).clamp_min(0.0) / out_a.clamp_min(_EPS_COVERAGE)).clamp(max=1.0)
        else:
            keep = 1.0 - aa
        out_c = keep * out_c
        out_a = keep * out_a
    for _, wc, wa in window:  # the nearest surface: side by side, nothing in front of it
        out_c, out_a = out_c + wc, out_a + wa
    log.debug("scatter: %d layers, %d convolutions, grid %d, kernel pad %d px", len(cocs), n_conv, grid, pad)
    return _fill(out_c, out_a, fill, background)


def _check_composite(fill: str, background: torch.Tensor | None, field_grid: int | None, chunk: int) -> None:
    if fill not in FILL_MODES or (fill == "background" and background is None):
        raise ValueError(f"fill must be one of {FILL_MODES} (background with an image), got {fill!r}")
    if field_grid is not None and field_grid < 2:
        raise ValueError(f"field_grid must be >= 2 (or None for automatic), got {field_grid}")
    if chunk < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")


def _fill(out_c: torch.Tensor, out_a: torch.Tensor, fill: str, background: torch.Tensor | None) -> torch.Tensor:
    """Composited light ``(3, H, W)`` and coverage ``(n_a, H, W)`` -> the image, where the
    coverage falls short divided by it (``"normalize"``), filled from ``background`` or left dark."""
    if fill == "normalize":
        cover = out_a.expand_as(out_c)
        return torch.where(cover > _EPS_COVERAGE, out_c / cover.clamp_min(_EPS_COVERAGE), out_c)
    out_c = out_c / out_a.clamp_min(1.0)  # parts of one surface side by side may overlap a little
    if fill == "background":
        out_c = out_c + (1.0 - out_a).clamp_min(0.0) * background
    return out_c


def scatter_layers(
    colors: torch.Tensor,
    alphas: torch.Tensor,
    coc_px: Sequence[float],
    aperture: ApertureModel | None = None,
    *,
    field_grid: int | None = None,
    fill_holes: bool = True,
    chunk: int = 8,
    preserve_uniform: bool = False,
) -> torch.Tensor:
    """Defocus a stack of fronto-parallel layers by scatter and back-to-front "over".

    Args:
        colors: ``(L, 3, H, W)`` *premultiplied* linear RGB of each layer (colour x coverage),
            finite and >= 0.
        alphas: ``(L, 1, H, W)`` coverage of each layer in [0, 1].
        coc_px: ``L`` signed CoC diameters (px) of the layers, negative in front of the focus
            plane. Layers are composited far (largest signed CoC) to near.
        aperture: aperture model (default: a disk, no vignetting, no chromatic aberration).
        field_grid: image-position grid for spatially varying (cat-eye) kernels, >= 2
            (default: :func:`auto_field_grid`, neighbours within 0.5 px of clip-circle shift).
        fill_holes: divide by the accumulated coverage where it is in (0, 1) (see module doc).
        chunk: (layer, node) convolutions per FFT batch (memory against speed).
        preserve_uniform: with cat-eye kernels, divide each layer by its scatter of a uniform
            field (a uniform plane stays exactly uniform; see the module doc).

    Returns:
        ``(3, H, W)`` defocused linear RGB, same dtype and device as ``colors``.

    Raises:
        ValueError: bad shapes, values or CoC list.
    """
    d = check_shape("colors", colors, "L 3 H W")
    check_shape("alphas", alphas, "L 1 H W", L=d["L"], H=d["H"], W=d["W"])
    cocs = [float(c) for c in coc_px]
    if len(cocs) != d["L"]:
        raise ValueError(f"coc_px must have one value per layer ({d['L']}), got {len(cocs)}")
    check_finite("layer CoC", np.asarray(cocs), " px")
    check_nonnegative("layer colour", colors)
    check_in_range("layer coverage", alphas, 0.0, 1.0)
    return _composite(
        lambda i: (colors[i], alphas[i]),
        cocs,
        aperture or ApertureModel(),
        (d["H"], d["W"]),
        colors,
        field_grid,
        "normalize" if fill_holes else "none",
        chunk,
        preserve_uniform,
    )


def slice_by_coc(coc: torch.Tensor, coc_step: float) -> tuple[torch.Tensor, list[int]]:
    """Slice index map ``round(coc / coc_step)`` and the sorted list of slices present.

    Args:
        coc: ``(H, W)`` signed CoC in px.
        coc_step: slice width in px, > 0.
    """
    check_positive("coc_step", coc_step, " px")
    idx = torch.round(coc / coc_step).to(torch.int64)
    return idx, sorted(int(v) for v in torch.unique(idx))


def scatter_defocus(
    aif: torch.Tensor,
    coc: torch.Tensor,
    aperture: ApertureModel | None = None,
    *,
    coc_step: float = 0.5,
    field_grid: int | None = None,
    fill: str = "background",
    chunk: int = 8,
    preserve_uniform: bool = False,
    occlusion: str = "surface",
    jump_px: float = 4.0,
) -> torch.Tensor:
    """Defocus an all-in-focus image given its signed CoC map (layered approximation).

    Args:
        aif: ``(B, 3, H, W)`` all-in-focus linear RGB, finite and >= 0.
        coc: ``(B, 1, H, W)`` signed CoC diameter in px (negative in front of the focus plane).
        aperture: aperture model (default disk).
        coc_step: width (px) of the CoC slices the depth is cut into, > 0.
        field_grid: image-position grid for cat-eye kernels (default automatic).
        fill: what fills the coverage the slices leave short (where a blurred foreground is
            partly transparent onto what it hides): ``"background"`` (default: the visible
            background around the occluder, :func:`neuralbokeh.ops.holes.hidden_background`),
            ``"normalize"`` (divide by the coverage: the foreground's own colours) or ``"none"``.
        chunk: convolutions per FFT batch.
        preserve_uniform: see :func:`scatter_layers`.
        occlusion: how a slice hides the slices behind it: ``"surface"`` (default: only those
            more than ``jump_px`` behind it, and of those only the light that does not fit
            beside its own; slices closer than that add up as parts of one surface) or
            ``"over"`` (every slice a complete layer: under-counts a blurred continuous
            surface and lets what it hides show through). See the module doc.
        jump_px: the least CoC step (px) that counts as a depth discontinuity, > 0: for
            ``occlusion="surface"`` and for finding occluders (``fill="background"``).

    Returns:
        ``(B, 3, H, W)`` defocused linear RGB.
    """
    d = check_shape("aif", aif, "B 3 H W")
    check_shape("coc", coc, "B 1 H W", B=d["B"], H=d["H"], W=d["W"])
    check_nonnegative("aif", aif)
    check_finite("coc", coc, " px")
    if occlusion not in OCCLUSION_MODES:
        raise ValueError(f"occlusion must be one of {OCCLUSION_MODES}, got {occlusion!r}")
    outs = []
    hidden = hidden_background(aif, coc, jump_px) if fill == "background" else None
    for b in range(d["B"]):
        idx, present = slice_by_coc(coc[b, 0], coc_step)
        flat = (idx - present[0]).flatten()
        sums = torch.bincount(flat, weights=coc[b, 0].flatten().double())
        counts = torch.bincount(flat).double()
        means = [float(sums[s - present[0]] / counts[s - present[0]]) for s in present]

        def layer(i: int, b: int = b, idx: torch.Tensor = idx, present: list[int] = present):
            mask = (idx == present[i]).to(aif.dtype).unsqueeze(0)
            return aif[b] * mask, mask

        outs.append(
            _composite(
                layer, means, aperture or ApertureModel(), (d["H"], d["W"]), aif, field_grid, fill, chunk,
                preserve_uniform, jump_px if occlusion == "surface" else 0.0, None if hidden is None else hidden[b],
            )
        )
    return torch.stack(outs)


def render_defocus(
    aif: torch.Tensor,
    depth_m: torch.Tensor,
    lens: ThinLens,
    focus_m: float,
    aperture: ApertureModel | None = None,
    **kwargs,
) -> torch.Tensor:
    """Defocus an all-in-focus image from its depth map through a thin lens.

    Args:
        aif: ``(B, 3, H, W)`` all-in-focus linear RGB, finite and >= 0.
        depth_m: ``(B, 1, H, W)`` planar depth in m, > 0 (inf allowed).
        lens: the thin lens; the sensor width maps onto the image width ``W``.
        focus_m: focus distance in m (> focal length; inf allowed).
        aperture: aperture model (default disk).
        **kwargs: passed to :func:`scatter_defocus` (``coc_step``, ``field_grid``, ``fill``, ``occlusion``,
            ``preserve_uniform``).

    Returns:
        ``(B, 3, H, W)`` defocused linear RGB.
    """
    d = check_shape("depth_m", depth_m, "B 1 H W")
    coc = lens.coc_px(depth_m, focus_m, d["W"], signed=True)
    return scatter_defocus(aif, coc, aperture, **kwargs)

"""Slow, readable reference versions of the renderers (numpy float64, explicit loops).

For tests only: every fast path in this package is checked against one of these with stated
tolerances. They follow the definitions literally: each source pixel adds its own kernel
(evaluated at its *own* image position, so cat-eye kernels are exact here, where the fast path
interpolates them from a grid) onto a canvas; with cat-eye kernels coverage (and with
``preserve_uniform`` colour) is divided by the same scatter of a uniform field; the layers are then composited back to front.
Use them on tiny images only (a few thousand pixels).
"""

from __future__ import annotations

import numpy as np

from ..core.apertures import ApertureModel, field_position


def _edge_ring(image: np.ndarray) -> np.ndarray:
    """``(C, H, W)`` -> ``(C, H + 2, W + 2)``: the image in a 1 px ring of its edge pixels, each
    at most the larger of its neighbours along the edge; a corner repeats its row's end. What the
    padding beyond the frame repeats, as in the fast path."""
    c, h, w = image.shape
    ring = np.zeros((c, h + 2, w + 2))
    ring[:, 1:-1, 1:-1] = image

    def clipped(line: np.ndarray) -> np.ndarray:  # (C, n)
        out = line.copy()
        for i in range(line.shape[1]):
            beside = [line[:, j] for j in (i - 1, i + 1) if 0 <= j < line.shape[1]]
            if beside:
                out[:, i] = np.minimum(line[:, i], np.max(beside, axis=0))
        return out

    ring[:, 0, 1:-1], ring[:, -1, 1:-1] = clipped(image[:, 0]), clipped(image[:, -1])
    ring[:, 1:-1, 0], ring[:, 1:-1, -1] = clipped(image[:, :, 0]), clipped(image[:, :, -1])
    for row in (0, -1):
        ring[:, row, 0], ring[:, row, -1] = ring[:, row, 1], ring[:, row, -2]
    return ring


def _ring_index(i: int, n: int, p: int) -> int:
    """Row (or column) of the edge ring ``(n + 2)`` that padded position ``i`` shows: the frame
    inside, the ring beyond it however far."""
    return min(max(i - p, -1), n) + 1


def reference_scatter_layers(
    colors: np.ndarray,
    alphas: np.ndarray,
    coc_px: list[float],
    aperture: ApertureModel | None = None,
    fill_holes: bool = True,
    preserve_uniform: bool = False,
    surface_px: float = 0.0,
    background: np.ndarray | None = None,
) -> np.ndarray:
    """Literal scatter + back-to-front compositing of fronto-parallel layers.

    Args:
        colors: ``(L, 3, H, W)`` premultiplied linear RGB.
        alphas: ``(L, 1, H, W)`` coverage.
        coc_px: signed CoC (px) per layer.
        aperture: aperture model (default disk).
        fill_holes: divide by the accumulated coverage (as the fast path).
        preserve_uniform: divide each layer by its scatter of a uniform field (as the fast path).
        surface_px: 0: "over" (a layer of blurred coverage ``a`` scales everything behind it by
            ``1 - a``). Else a layer adds to the layers within ``surface_px`` behind it (with
            it, coverage ``a``) and scales those farther (coverage ``A``) by
            ``min(1, max(0, 1 - a) / A)``.
        background: ``(3, H, W)``: divide by the coverage where it exceeds 1 and add
            ``(1 - coverage) * background`` where it falls short (``fill_holes`` is ignored).

    Returns:
        ``(3, H, W)`` float64.
    """
    aperture = aperture or ApertureModel()
    colors = np.asarray(colors, dtype=np.float64)
    alphas = np.asarray(alphas, dtype=np.float64)
    pad = max(aperture.kernel_radius_px(abs(c)) for c in coc_px)
    done: list[tuple[int, np.ndarray, np.ndarray]] = []  # (layer, colour, coverage) so far
    for i in sorted(range(len(colors)), key=lambda j: -coc_px[j]):  # far to near
        done.append((i, *_scatter_layer(colors[i], alphas[i, 0], coc_px[i], aperture, pad, preserve_uniform)))
        _occlude(done, coc_px, surface_px)
    out_c = sum(d[1] for d in done)
    out_a = sum(d[2] for d in done)
    if background is not None:
        return out_c / np.maximum(out_a, 1.0) + np.maximum(1.0 - out_a, 0.0) * background
    if fill_holes:
        cover = np.broadcast_to(out_a, out_c.shape)
        out_c = np.where(cover > 1e-6, out_c / np.maximum(cover, 1e-6), out_c)
    return out_c


def _scatter_layer(color: np.ndarray, alpha: np.ndarray, c: float, aperture: ApertureModel, pad: int,
                   preserve_uniform: bool) -> tuple[np.ndarray, np.ndarray]:
    """One layer (``color`` ``(3, H, W)``, ``alpha`` ``(H, W)``) scattered pixel by pixel with the
    PSF at CoC ``c`` px and each pixel's field position, its edge ring repeated ``pad`` px beyond
    its edges (a padding pixel at its edge pixel's position): ``(colour (3, H, W), coverage (1 or
    3, H, W))``."""
    h, w = alpha.shape
    ring = _edge_ring(np.concatenate([color, alpha[None]]))
    n_a = 3 if aperture.chromatic else 1
    n_u = n_a if aperture.spatially_varying else 0  # uniform-field response channels
    rad = aperture.kernel_radius_px(abs(c))
    m = pad + rad  # the canvas covers the padded image plus one kernel radius on every side
    canvas = np.zeros((3 + n_a + n_u, h + 2 * m, w + 2 * m))
    for py in range(h + 2 * pad):
        ry = _ring_index(py, h, pad)
        for px in range(w + 2 * pad):
            rx = _ring_index(px, w, pad)
            a = ring[3, ry, rx]
            if a == 0 and n_u == 0:
                continue
            k = aperture.psf(c, field_position(min(max(ry - 1, 0), h - 1), min(max(rx - 1, 0), w - 1), h, w))
            r = k.shape[-1] // 2
            # colour, coverage, and a uniform unit field (every pixel scatters 1)
            value = np.concatenate([ring[:3, ry, rx], np.full(n_a, a), np.ones(n_u)])
            kk = np.concatenate([k, k if n_a == 3 else k[1:2]] + ([k if n_u == 3 else k[1:2]] if n_u else []), 0)
            y0, x0 = py + (m - pad) - r, px + (m - pad) - r
            canvas[:, y0 : y0 + 2 * r + 1, x0 : x0 + 2 * r + 1] += kk * value[:, None, None]
    layer = canvas[:, m : m + h, m : m + w]
    if n_u:  # coverage always, colour on request, divided by the uniform-field response
        u = np.maximum(layer[3 + n_a :], 1e-6)
        color = layer[:3] / np.broadcast_to(u, (3, h, w)) if preserve_uniform else layer[:3]
        layer = np.concatenate([color, layer[3 : 3 + n_a] / u])
    return layer[:3], np.clip(layer[3:], 0.0, 1.0)


def _occlude(done: list[tuple[int, np.ndarray, np.ndarray]], coc_px: list[float], surface_px: float) -> None:
    """The newest (nearest) layer of ``done`` hides the layers it is in front of, in place:
    "over" (``surface_px`` <= 0) or only their light that does not fit beside its surface."""
    c, aa = coc_px[done[-1][0]], done[-1][2]
    hidden = [j for j, (k, _, _) in enumerate(done[:-1]) if surface_px <= 0 or coc_px[k] > c + surface_px]
    if surface_px <= 0:
        keep = 1.0 - aa
    else:  # only the light of the hidden layers that does not fit beside this surface's
        behind = sum((done[j][2] for j in hidden), np.zeros_like(aa))
        beside = sum((d[2] for j, d in enumerate(done) if j not in hidden), np.zeros_like(aa))
        keep = np.ones_like(aa)
        full = beside + behind > 1.0
        keep[full] = np.minimum(np.maximum(1.0 - beside[full], 0.0) / np.maximum(behind[full], 1e-6), 1.0)
    for j in hidden:
        k, jc, ja = done[j]
        done[j] = (k, keep * jc, keep * ja)


def reference_scatter_defocus(
    aif: np.ndarray,
    coc: np.ndarray,
    aperture: ApertureModel | None = None,
    coc_step: float = 0.5,
    surface_px: float = 4.0,
    background: np.ndarray | None = None,
) -> np.ndarray:
    """Slice ``(3, H, W)`` AIF by ``round(coc / coc_step)`` and scatter the slices literally.

    Each slice uses the mean CoC of its pixels; ``surface_px`` and ``background`` as in
    :func:`reference_scatter_layers` (without a background the result is divided by the
    coverage). Returns ``(3, H, W)`` float64.
    """
    aif = np.asarray(aif, dtype=np.float64)
    coc = np.asarray(coc, dtype=np.float64)
    idx = np.round(coc / coc_step).astype(np.int64)
    slices = sorted(set(idx.ravel().tolist()))
    masks = np.stack([(idx == s).astype(np.float64) for s in slices])[:, None]
    means = [float(coc[idx == s].mean()) for s in slices]
    return reference_scatter_layers(aif[None] * masks, masks, means, aperture, surface_px=surface_px, background=background)

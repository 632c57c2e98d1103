"""Procedural layered scenes: textured cut-outs at random depths plus HDR point highlights.

A scene is a list of fronto-parallel layers, each with a straight (not premultiplied) linear
RGB texture, an anti-aliased coverage mask and one depth in metres; the background covers the
whole frame at a large or infinite depth. Everything is drawn from one ``numpy`` generator, so
a scene is a pure function of its seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from kornia.filters import gaussian_blur2d

_SUPERSAMPLE = 4


@dataclass
class Layer:
    """One fronto-parallel layer: ``color (H, W, 3)`` straight linear RGB, ``alpha (H, W)``, ``depth_m``."""

    color: np.ndarray
    alpha: np.ndarray
    depth_m: float


@dataclass(frozen=True)
class SceneParams:
    """Ranges the generator draws from.

    Args:
        near_m: nearest layer depth (m).
        far_m: farthest finite depth (m); the background sits in [far/2, far] or at infinity.
        layers: (min, max) number of cut-out layers.
        infinite_background: probability that the background is at infinity.
        highlights: (min, max) number of HDR point highlights.
        highlight_gain: (min, max) highlight intensity relative to the diffuse level.
        diffuse_level: linear value of a white diffuse surface.
    """

    near_m: float = 0.7
    far_m: float = 20.0
    layers: tuple[int, int] = (3, 6)
    infinite_background: float = 0.5
    highlights: tuple[int, int] = (4, 12)
    highlight_gain: tuple[float, float] = (1.0, 1000.0)
    diffuse_level: float = 1.0


def _noise_texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Smooth multi-octave colour noise, (H, W, 3) in [0, 1]."""
    out = torch.zeros(1, 3, h, w, dtype=torch.float64)
    amp, total = 1.0, 0.0
    for octave in range(4):
        cells = 2 ** (octave + 2)
        base = torch.from_numpy(rng.random((1, 3, cells, cells)))
        out += amp * F.interpolate(base, size=(h, w), mode="bicubic", align_corners=False)
        total += amp
        amp *= 0.5
    out = (out / total).clamp(0.0, 1.0)
    return out[0].permute(1, 2, 0).numpy()


def _pattern_texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Stripes or a checkerboard at a random angle and period, (H, W) in [0, 1], blurred a little."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    ang = rng.uniform(0, math.pi)
    period = rng.uniform(4.0, max(6.0, min(h, w) / 4))
    u = (xx * math.cos(ang) + yy * math.sin(ang)) / period
    v = (-xx * math.sin(ang) + yy * math.cos(ang)) / period
    if rng.random() < 0.5:
        p = (np.floor(u) % 2).astype(np.float64)
    else:
        p = ((np.floor(u) + np.floor(v)) % 2).astype(np.float64)
    t = torch.from_numpy(p)[None, None]
    t = gaussian_blur2d(t, (5, 5), (0.7, 0.7), border_type="reflect")
    return t[0, 0].numpy()


def _texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """A random albedo texture (H, W, 3) in [0.02, 0.9]: coloured noise or a two-colour pattern."""
    if rng.random() < 0.5:
        tex = _noise_texture(rng, h, w)
        tint = rng.uniform(0.3, 1.0, size=3)
        tex = tex * tint
    else:
        p = _pattern_texture(rng, h, w)[..., None]
        c0, c1 = rng.uniform(0.0, 1.0, size=3), rng.uniform(0.0, 1.0, size=3)
        tex = p * c0 + (1 - p) * c1
    return 0.02 + 0.88 * tex


def _shape_mask(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Anti-aliased random cut-out (ellipse, rotated rectangle or random polygon), (H, W) in [0, 1]."""
    s = _SUPERSAMPLE
    ys = (np.arange(h * s) + 0.5) / s
    xs = (np.arange(w * s) + 0.5) / s
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    cx, cy = rng.uniform(0.1, 0.9) * w, rng.uniform(0.1, 0.9) * h
    scale = min(h, w)
    rx, ry = rng.uniform(0.08, 0.35) * scale, rng.uniform(0.08, 0.35) * scale
    ang = rng.uniform(0, math.pi)
    u = (xx - cx) * math.cos(ang) + (yy - cy) * math.sin(ang)
    v = -(xx - cx) * math.sin(ang) + (yy - cy) * math.cos(ang)
    kind = rng.integers(3)
    if kind == 0:
        inside = (u / rx) ** 2 + (v / ry) ** 2 <= 1.0
    elif kind == 1:
        inside = (np.abs(u) <= rx) & (np.abs(v) <= ry)
    else:  # star-shaped random polygon: radius varies with angle
        n = int(rng.integers(5, 10))
        radii = rng.uniform(0.5, 1.0, size=n)
        theta = np.mod(np.arctan2(v / ry, u / rx), 2 * math.pi) / (2 * math.pi) * n
        i0 = np.floor(theta).astype(np.int64) % n
        frac = theta - np.floor(theta)
        r = radii[i0] * (1 - frac) + radii[(i0 + 1) % n] * frac
        inside = np.hypot(u / rx, v / ry) <= r
    m = torch.from_numpy(inside.astype(np.float64))[None, None]
    return F.avg_pool2d(m, s)[0, 0].numpy()


def _highlights(rng: np.random.Generator, h: int, w: int, count: int, params: SceneParams) -> tuple[np.ndarray, np.ndarray]:
    """``count`` small HDR discs: (H, W, 3) radiance and (H, W) coverage."""
    s = _SUPERSAMPLE
    ys = (np.arange(h * s) + 0.5) / s
    xs = (np.arange(w * s) + 0.5) / s
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    cover = np.zeros((h * s, w * s))
    color = np.zeros((h * s, w * s, 3))
    lo, hi = params.highlight_gain
    for _ in range(count):
        cx, cy = rng.uniform(0, w), rng.uniform(0, h)
        r = rng.uniform(0.5, 1.5)
        gain = math.exp(rng.uniform(math.log(lo), math.log(hi))) * params.diffuse_level
        tint = rng.uniform(0.6, 1.0, size=3)
        disc = (xx - cx) ** 2 + (yy - cy) ** 2 <= r * r
        cover[disc] = 1.0
        color[disc] = gain * tint
    cov = F.avg_pool2d(torch.from_numpy(cover)[None, None], s)[0, 0].numpy()
    col = F.avg_pool2d(torch.from_numpy(color).permute(2, 0, 1)[None], s)[0].permute(1, 2, 0).numpy()
    # straight colour: average radiance over the covered part of each pixel
    col = np.where(cov[..., None] > 0, col / np.maximum(cov[..., None], 1e-12), 0.0)
    return col, cov


def make_layers(rng: np.random.Generator, height: int, width: int, params: SceneParams) -> list[Layer]:
    """Draw a scene: background first, then cut-outs and a layer of floating highlights.

    Returns the layers in arbitrary order (compositing sorts them by depth).
    """
    if rng.random() < params.infinite_background:
        bg_depth = math.inf
    else:
        bg_depth = rng.uniform(params.far_m / 2, params.far_m)
    far_layer = min(bg_depth, params.far_m)
    layers = [Layer(_texture(rng, height, width) * params.diffuse_level, np.ones((height, width)), bg_depth)]
    n = int(rng.integers(params.layers[0], params.layers[1] + 1))
    for _ in range(n):
        # depths uniform in diopters: as many layers near as far in CoC terms
        dio = rng.uniform(1.0 / far_layer, 1.0 / params.near_m)
        layers.append(
            Layer(_texture(rng, height, width) * params.diffuse_level, _shape_mask(rng, height, width), 1.0 / dio)
        )
    n_hl = int(rng.integers(params.highlights[0], params.highlights[1] + 1))
    # Highlights: part on existing layers (at their depth), part floating at their own depth.
    on_layers = n_hl // 2
    for _ in range(on_layers):
        layer = layers[int(rng.integers(len(layers)))]
        col, cov = _highlights(rng, height, width, 1, params)
        cov = cov * (layer.alpha >= 0.999)  # only where the layer is solid
        layer.color = layer.color * (1 - cov[..., None]) + col * cov[..., None]
    col, cov = _highlights(rng, height, width, n_hl - on_layers, params)
    if cov.any():
        dio = rng.uniform(1.0 / far_layer, 1.0 / params.near_m)
        layers.append(Layer(col, cov, 1.0 / dio))
    return layers


def composite_sharp(layers: list[Layer]) -> tuple[np.ndarray, np.ndarray]:
    """All-in-focus image (over, far to near) and depth map (nearest layer with coverage >= 0.5)."""
    order = sorted(layers, key=lambda layer: -layer.depth_m)
    h, w = order[0].alpha.shape
    rgb = np.zeros((h, w, 3))
    depth = np.full((h, w), order[0].depth_m)
    for layer in order:
        a = layer.alpha[..., None]
        rgb = layer.color * a + (1 - a) * rgb
        depth = np.where(layer.alpha >= 0.5, layer.depth_m, depth)
    return rgb, depth

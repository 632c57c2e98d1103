"""Rendering with Mitsuba 3: all-in-focus image, planar depth and defocused slices.

Camera model. All images of a scene share one pinhole camera (pose, horizontal field of view
``camera.fov_x_deg``, film size), so every slice is pixel-registered with the AIF (no focus
breathing). For the CoC of ``neuralbokeh.core.optics.ThinLens`` (``c = K (1/d_f - 1/d)``, ``K``
from the lens-to-sensor distance at that focus) to hold in this camera, the lens radius in
the scene is ``R = K * 2 tan(fov_x / 2) / (2 W)`` metres: with the field of view of the lens
focused at infinity that is ``d_s / (2 N)``. :func:`lens_radius_m` computes it; the tests check
the blur of an emissive point against ``coc_px`` directly.

Defocus, two ways (both put the focus plane at planar depth ``d_f``):

* ``thinlens``: Mitsuba's thin-lens sensor (disk aperture only, no cat-eye), its
  ``aperture_radius``/``focus_distance`` updated through ``mi.traverse`` for every slice.
* ``accumulate``: pinhole renders from points of the aperture, each camera moved to its lens
  point and its principal point shifted (``principal_point_offset_x/y``) so that the focus
  plane stays registered; their mean is the defocused image. Any aperture shape (points on a
  jittered grid, weighted by the shape's transmission) works the same way. Cat-eye
  vignetting follows ``neuralbokeh.core.apertures.ApertureModel`` (and so our scatter renderer): a
  scene point's bundle is clipped by the vignetting circle of *its own* field position. Each
  view also renders the depth AOV, which gives every ray's scene point, its CoC and so its
  pinhole image position; the ray counts only when its lens point is inside that position's
  circle, weighted by the inverse of the aperture fraction the circle leaves (kernels sum to
  one: vignetting reshapes the bokeh, it does not darken the corners).

A lens point ``(u, v)`` of the pupil square ``[-1, 1]^2`` (u right, v up as seen in the image) sits at camera
coordinates ``(-u R, v R, 0)`` (Mitsuba camera space: image right is -x), so that a point
behind the focus plane images as the upright aperture shape and one in front as its point
reflection, the convention of ``neuralbokeh.core.apertures``.

Depth. The ``depth`` AOV is the ray distance from the near-clip plane (``near_clip`` times the
ray's length per unit of planar depth), 0 for misses, and mixed at edges unless the film uses
a box filter at one sample. :func:`render_depth` renders it with one unjittered sample at each
pixel centre and a box filter, converts to planar depth ``z = aov / r + near_clip`` with
``r = sqrt(1 + x^2 + y^2)`` (``x, y`` the pixel centre's tangent coordinates) and gives misses
``+inf``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np

from neuralbokeh.core.apertures import ApertureModel, Disk, field_position, pupil_grid
from neuralbokeh.core.checks import check_at_least, check_positive
from neuralbokeh.core.optics import ThinLens

from .camera import Camera

NEAR_CLIP = 0.01  # scene units
METHODS = ("auto", "thinlens", "accumulate")


def _sensor(camera: Camera, spp: int, kind: str = "perspective", jitter: bool = True, **extra: Any) -> dict[str, Any]:
    sampler = {"type": "independent", "sample_count": spp} if jitter else {"type": "stratified", "sample_count": 1, "jitter": False}
    return {"type": kind, "fov": camera.fov_x_deg, "fov_axis": "x", "near_clip": NEAR_CLIP, "far_clip": 1e5,
            "to_world": camera.to_world, "sampler": sampler, **extra,
            "film": {"type": "hdrfilm", "width": camera.width, "height": camera.height, "rfilter": {"type": "box"},
                     "pixel_format": "rgb", "component_format": "float32"}}


def _load_sensor(mi: ModuleType, d: dict[str, Any]) -> Any:
    d = dict(d)
    d["to_world"] = mi.ScalarTransform4f(np.asarray(d["to_world"], dtype=np.float64).tolist())
    return mi.load_dict(d)


def _numpy(img: Any) -> np.ndarray:
    return np.array(img, dtype=np.float64)


def render_aif(mi: ModuleType, scene: Any, camera: Camera, spp: int, seed: int = 0) -> np.ndarray:
    """The all-in-focus (pinhole) image, ``(H, W, 3)`` linear RGB float64, box pixel filter."""
    check_at_least("spp", spp, 1)
    return _numpy(mi.render(scene, sensor=_load_sensor(mi, _sensor(camera, spp)), spp=spp, seed=seed))[..., :3]


def tangent_grid(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """``(x, y)`` tangent coordinates of the pixel centres, ``(H, W)`` each: x right, y down."""
    tx = camera.tan_half_x
    ty = tx * camera.height / camera.width
    x = ((np.arange(camera.width) + 0.5) / camera.width * 2.0 - 1.0) * tx
    y = ((np.arange(camera.height) + 0.5) / camera.height * 2.0 - 1.0) * ty
    return np.broadcast_to(x[None], (camera.height, camera.width)), np.broadcast_to(y[:, None], (camera.height, camera.width))


def planar_depth_from_aov(aov: np.ndarray, camera: Camera, near_clip: float = NEAR_CLIP) -> np.ndarray:
    """Mitsuba's ``depth`` AOV at pixel centres -> planar depth along the axis, in scene units
    like the AOV and ``near_clip`` (misses: +inf)."""
    x, y = tangent_grid(camera)
    r = np.sqrt(1.0 + x**2 + y**2)
    return np.where(aov > 0.0, aov / r + near_clip, np.inf)


def render_depth(mi: ModuleType, scene: Any, camera: Camera) -> np.ndarray:
    """Planar depth in scene units (metres for our scenes) at the pixel centres, ``(H, W)``
    float64, ``+inf`` where nothing is hit."""
    integrator = mi.load_dict({"type": "aov", "aovs": "z:depth"})
    aov = _numpy(mi.render(scene, sensor=_load_sensor(mi, _sensor(camera, 1, jitter=False)), integrator=integrator, spp=1))
    return planar_depth_from_aov(aov[..., -1], camera)


def lens_radius_m(lens: ThinLens, focus_m: float, camera: Camera) -> float:
    """Radius (m) of the scene-space lens that gives ``lens.coc_px`` in ``camera``."""
    k = lens.coc_constant_pxmm(focus_m, camera.width)  # px * mm
    return k / 1000.0 * 2.0 * camera.tan_half_x / (2.0 * camera.width)


def lens_points(aperture: ApertureModel, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Points of the pupil on a jittered ``n x n`` grid where the shape transmits
    (:func:`neuralbokeh.core.apertures.pupil_grid`): ``(M, 2)`` as (u right, v up) and their
    transmissions ``(M,)``."""
    return pupil_grid(aperture.shape, n, rng)


def clip_fraction_table(aperture: ApertureModel, grid: int = 33, samples: int = 160) -> np.ndarray:
    """Transmission-weighted fraction of the aperture inside the vignetting circle, on a
    ``grid x grid`` table of field positions ``(fy, fx)`` in ``[-1, 1]^2``."""
    g = (np.arange(samples) + 0.5) / samples * 2.0 - 1.0
    u, v = np.meshgrid(g, g)
    t = aperture.shape.transmission(u, v)
    f = np.linspace(-1.0, 1.0, grid)
    table = np.empty((grid, grid))
    for i, fy in enumerate(f):
        for j, fx in enumerate(f):
            table[i, j] = (t * aperture.transmits(u, v, fx, fy)).sum() / t.sum()
    return table


def _lookup(table: np.ndarray, fx: np.ndarray, fy: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a :func:`clip_fraction_table` (fields clamped to ``[-1, 1]``)."""
    n = table.shape[0] - 1
    x = (np.clip(fx, -1.0, 1.0) + 1.0) / 2.0 * n
    y = (np.clip(fy, -1.0, 1.0) + 1.0) / 2.0 * n
    x0, y0 = np.minimum(np.floor(x).astype(int), n - 1), np.minimum(np.floor(y).astype(int), n - 1)
    ax, ay = x - x0, y - y0
    return ((1 - ay) * ((1 - ax) * table[y0, x0] + ax * table[y0, x0 + 1])
            + ay * ((1 - ax) * table[y0 + 1, x0] + ax * table[y0 + 1, x0 + 1]))


def vignetting_weight(aperture: ApertureModel, camera: Camera, lens: ThinLens, focus_m: float, u: float, v: float,
                      depth_m: np.ndarray, table: np.ndarray) -> np.ndarray:
    """Weight ``(H, W)`` of lens point ``(u, v)`` for the rays of one pinhole view.

    A ray's scene point (planar depth ``depth_m`` from the view's depth AOV) has its own CoC
    ``c``; its pinhole image is ``q = p - (c / 2) (u, -v)`` (px, rows down). The ray counts
    when ``(u, v)`` is inside the vignetting circle of ``q``'s field position, divided by the
    fraction of the aperture that circle leaves (so each source keeps its flux): the source
    point's kernel of ``ApertureModel.kernels``, as our scatter renderer applies it.
    """
    h, w = camera.height, camera.width
    c = lens.coc_px(depth_m, focus_m, w, signed=True)
    cols, rows = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    fx, fy = field_position(rows + c / 2.0 * v, cols - c / 2.0 * u, h, w)
    return np.where(aperture.transmits(u, v, fx, fy), 1.0 / np.maximum(_lookup(table, fx, fy), 1e-6), 0.0)


@dataclass
class SliceResult:
    """A defocused slice: ``image`` ``(H, W, 3)``, the spp spent, the estimated noise (RMS
    standard error of the Reinhard-tone-mapped mean, display units), rounds and method."""

    image: np.ndarray
    spp: int
    noise: float
    rounds: int
    method: str


def _noise(rounds: list[np.ndarray]) -> float:
    if len(rounds) < 2:
        return math.inf
    t = np.stack([r / (1.0 + r) for r in rounds])
    se = np.nanstd(t, axis=0, ddof=1) / math.sqrt(len(rounds))
    return float(np.sqrt(np.nanmean(se**2)))


def choose_method(method: str, aperture: ApertureModel) -> str:
    """``auto`` -> ``thinlens`` for a plain disk, else ``accumulate``; checks the combination."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if any(s != 1.0 for s in aperture.channel_scale):
        raise ValueError(f"per-channel CoC scale {aperture.channel_scale} is not rendered by Mitsuba; use data_tools.synth")
    plain_disk = isinstance(aperture.shape, Disk) and not aperture.vignetted
    if method == "thinlens" and not plain_disk:
        raise ValueError(f"the thinlens sensor renders a plain disk only, got {aperture.to_dict()}; use method 'accumulate'")
    return method if method != "auto" else ("thinlens" if plain_disk else "accumulate")


def mitsuba_defocus(mi: ModuleType, scene: Any, camera: Camera, lens: ThinLens, aperture: ApertureModel, focus_m: float,
                   spp: int, method: str = "auto", noise_target: float | None = None, rounds: int = 4,
                   seed: int = 0, unit_m: float = 1.0) -> SliceResult:
    """One defocused slice focused at ``focus_m`` (planar, m).

    The ``spp`` budget is spent in ``rounds`` equal rounds (``accumulate``: one sample per lens
    point, ``spp / rounds`` points a round; ``thinlens``: ``spp / rounds`` samples a round). The
    spread of the rounds estimates the noise of their mean; with ``noise_target`` the slice
    stops after the first round (at least two) whose estimate is below it.

    Args:
        spp: samples per pixel at most, >= rounds.
        method: ``auto``, ``thinlens`` or ``accumulate`` (see the module docstring).
        noise_target: stop once the estimated noise is below this (display units, e.g. 0.005).
        rounds: number of rounds the budget is split into, >= 2.
        seed: sampling seed.
        unit_m: metres per scene unit (e.g. 0.001 for a scene modelled in mm), > 0.
    """
    check_at_least("rounds", rounds, 2)
    check_at_least("spp", spp, rounds)
    check_positive("focus_m", focus_m, " m")
    if noise_target is not None:
        check_positive("noise_target", noise_target)
    check_positive("unit_m", unit_m, " m")
    method = choose_method(method, aperture)
    per_round = spp // rounds
    radius = lens_radius_m(lens, focus_m, camera) / unit_m  # scene units from here on
    focus = focus_m / unit_m
    rng = np.random.default_rng(np.random.SeedSequence([seed, 7]))
    images: list[np.ndarray] = []
    total = np.zeros((camera.height, camera.width, 3))
    weight = np.zeros((camera.height, camera.width, 1))
    spent = 0
    if method == "thinlens":
        sensor = _load_sensor(mi, _sensor(camera, per_round, "thinlens", aperture_radius=radius, focus_distance=focus))
    else:
        sensor = _load_sensor(mi, _sensor(camera, 1))
        params = mi.traverse(sensor)
        table = clip_fraction_table(aperture)
        vignetted = aperture.vignetted
        integrator = scene.integrator() or mi.load_dict({"type": "path"})
        if vignetted:  # each ray's depth too: the vignetting follows its scene point
            integrator = mi.load_dict({"type": "aov", "aovs": "z:depth", "integrator": integrator})
    for r in range(rounds):
        if method == "thinlens":
            img = _numpy(mi.render(scene, sensor=sensor, spp=per_round, seed=_seed(seed, r)))[..., :3]
            acc, w = img, np.ones_like(weight)
        else:
            n = max(1, round(math.sqrt(per_round * 4.0 / math.pi)))
            pts, trans = lens_points(aperture, n, rng)
            while len(pts) < per_round:  # the grid's disk rarely holds exactly per_round points
                more, t_more = lens_points(aperture, n, rng)
                pts, trans = np.concatenate([pts, more]), np.concatenate([trans, t_more])
            pick = rng.permutation(len(pts))[:per_round]
            pts, trans = pts[pick], trans[pick]
            acc, w = np.zeros_like(total), np.zeros_like(weight)
            for i, ((u, v), t) in enumerate(zip(pts, trans)):
                x_cam, y_cam = float(-u * radius), float(v * radius)
                params["to_world"] = mi.ScalarTransform4f((camera.to_world @ _translate(x_cam, y_cam)).tolist())
                params["principal_point_offset_x"] = x_cam / (focus * 2.0 * camera.tan_half_x)
                params["principal_point_offset_y"] = y_cam / (focus * 2.0 * camera.tan_half_x * camera.height / camera.width)
                params.update()
                out = _numpy(mi.render(scene, sensor=sensor, integrator=integrator, spp=1, seed=_seed(seed, r, i)))
                pw = t * np.ones_like(weight)
                if vignetted:
                    z = planar_depth_from_aov(out[..., -1], camera) * unit_m
                    pw = pw * vignetting_weight(aperture, camera, lens, focus_m, u, v, z, table)[..., None]
                acc += pw * out[..., :3]
                w += t  # sources keep their flux: normalise by the lens points, not by what reached the pixel
        spent += per_round
        total += acc
        weight += w
        with np.errstate(invalid="ignore", divide="ignore"):
            images.append(np.where(w > 0, acc / np.where(w > 0, w, 1.0), np.nan))
        noise = _noise(images)
        if noise_target is not None and noise < noise_target:
            break
    image = total / weight
    return SliceResult(image, spent, _noise(images), len(images), method)


def render_light_field(mi: ModuleType, scene: Any, camera: Camera, lens: ThinLens, n: int, spp: int, seed: int = 0,
                       unit_m: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An N x N light field through the lens's entrance pupil: pinhole views from the centres of
    the pupil square's N x N cells (a parallel camera array; view ``(row, col)``, row 0 at the
    top, col 0 at the left), and the centre view's depth and disparity.

    Args:
        lens: its entrance pupil (``f / N``) is the array's extent; the pupil square's side.
        n: views per side, odd, >= 3.
        spp: samples per pixel of every view (anti-aliasing and the integrator's noise).

    Returns:
        ``(views (N, N, H, W, 3), disparity (H, W) px between neighbouring views (0 at infinity,
        larger = nearer), depth (H, W) m)``, float64.
    """
    if n < 3 or n % 2 == 0:
        raise ValueError(f"a light field needs an odd number >= 3 of views per side, got {n}")
    check_at_least("spp", spp, 1)
    step = lens.aperture_diameter_mm / 1000.0 / n / unit_m  # the views' spacing, scene units
    sensor = _load_sensor(mi, _sensor(camera, spp))
    params = mi.traverse(sensor)
    c = (n - 1) / 2.0
    views = np.zeros((n, n, camera.height, camera.width, 3))
    for row in range(n):
        for col in range(n):  # the pupil's u (right) and v (up) of the cell, as mitsuba_defocus moves the camera
            u, v = (col - c) * step, (c - row) * step
            params["to_world"] = mi.ScalarTransform4f((camera.to_world @ _translate(-u, v)).tolist())
            params.update()
            views[row, col] = _numpy(mi.render(scene, sensor=sensor, spp=spp, seed=_seed(seed, row, col)))[..., :3]
    depth = render_depth(mi, scene, camera) * unit_m
    focal_px = camera.width / (2.0 * camera.tan_half_x)
    disparity = focal_px * step * unit_m / depth  # +inf depth: 0
    return views, disparity, depth


def _seed(*parts: int) -> int:
    """A 32-bit sampler seed from integers (Mitsuba's seeds are unsigned 32-bit)."""
    return int(np.random.SeedSequence([int(p) for p in parts]).generate_state(1)[0])


def _translate(x: float, y: float) -> np.ndarray:
    m = np.eye(4)
    m[0, 3], m[1, 3] = x, y
    return m

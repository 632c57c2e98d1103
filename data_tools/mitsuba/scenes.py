"""Scenes for the Mitsuba renderer: a procedural generator and user XML files.

World units are metres. The procedural camera sits at the origin looking along +z with +y up,
so a point's planar depth is its z. Everything is built as plain ``mi.load_dict`` dictionaries
plus numpy textures; ``mi`` is the module returned by :func:`data_tools.mitsuba.variant.activate`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from neuralbokeh.core.checks import check_positive

from .camera import Camera, axis_camera, fov_for_lens  # noqa: F401  (the scenes' camera, also named here)
from .render import render_depth


@dataclass(frozen=True)
class MitsubaSceneParams:
    """Ranges of the procedural scenes (depths in m)."""

    near_m: float = 0.7
    far_m: float = 12.0
    rectangles: tuple[int, int] = (2, 5)
    spheres: tuple[int, int] = (1, 4)
    boxes: tuple[int, int] = (1, 3)
    highlights: tuple[int, int] = (2, 6)
    highlight_radiance: tuple[float, float] = (30.0, 3000.0)


def _texture(rng: np.random.Generator, size: int = 64) -> np.ndarray:
    """A random RGB texture (stripes, checks or blobs on a base colour), float32 in [0.02, 0.9]."""
    y, x = np.mgrid[:size, :size] / size
    base, other = rng.uniform(0.05, 0.9, 3), rng.uniform(0.05, 0.9, 3)
    kind = rng.integers(3)
    if kind == 0:
        f, a = rng.uniform(2, 10), rng.uniform(0, np.pi)
        m = (np.sin(2 * np.pi * f * (x * np.cos(a) + y * np.sin(a))) > 0).astype(float)
    elif kind == 1:
        n = rng.integers(2, 9)
        m = ((np.floor(x * n) + np.floor(y * n)) % 2).astype(float)
    else:
        m = np.zeros_like(x)
        for _ in range(rng.integers(3, 9)):
            cx, cy, r = rng.uniform(0, 1), rng.uniform(0, 1), rng.uniform(0.05, 0.25)
            m = np.maximum(m, ((x - cx) ** 2 + (y - cy) ** 2 < r * r).astype(float))
    tex = base[None, None] * (1 - m[..., None]) + other[None, None] * m[..., None]
    return np.clip(tex, 0.02, 0.9).astype(np.float32)


def _in_view(rng: np.random.Generator, camera: Camera, depth: float, margin: float = 0.9) -> tuple[float, float]:
    """A random (x, y) at planar depth ``depth`` inside the procedural camera's view."""
    tx = camera.tan_half_x * margin
    ty = tx * camera.height / camera.width
    return float(rng.uniform(-tx, tx) * depth), float(rng.uniform(-ty, ty) * depth)


def procedural_scene(mi: ModuleType, rng: np.random.Generator, camera: Camera, params: MitsubaSceneParams,
                     max_depth: int = 4, planar: bool = False) -> tuple[dict[str, Any], dict[str, Any]]:
    """A random scene: textured rectangles (some tilted), spheres and boxes spread over depth
    (log-uniform), small emissive spheres as HDR highlights, a textured back wall at the far
    depth and a constant environment. Deterministic for a given ``rng`` state. ``planar``: only
    fronto-parallel rectangles (and the point-like highlights), the layered model's own world.

    Returns:
        ``(scene dict without sensor, description)``: the description (JSON) lists the objects.
    """
    T = mi.ScalarTransform4f
    check_positive("near_m", params.near_m, " m")
    if not params.near_m < params.far_m:
        raise ValueError(f"need near_m < far_m, got {params.near_m} and {params.far_m}")
    log_near, log_far = math.log(params.near_m), math.log(params.far_m)

    def depth() -> float:
        return float(math.exp(rng.uniform(log_near, log_far * 0.98 + log_near * 0.02)))

    def textured() -> dict[str, Any]:
        return {"type": "diffuse", "reflectance": {"type": "bitmap", "bitmap": mi.Bitmap(_texture(rng)), "raw": True}}

    # rectangles face -z after the 180 degree turn: diffuse surfaces are one-sided
    scene: dict[str, Any] = {"type": "scene", "integrator": {"type": "path", "max_depth": max_depth},
                             "environment": {"type": "constant", "radiance": {"type": "rgb", "value": float(rng.uniform(0.5, 1.5))}}}
    desc: list[dict[str, Any]] = []
    wall = params.far_m
    half = camera.tan_half_x * wall * 1.2
    scene["wall"] = {"type": "rectangle", "to_world": T().translate([0.0, 0.0, wall]).rotate([0, 1, 0], 180.0).scale([half, half, 1.0]),
                     "bsdf": textured()}
    desc.append({"kind": "wall", "depth_m": wall})
    for i in range(int(rng.integers(*params.rectangles, endpoint=True))):
        z = depth()
        x, y = _in_view(rng, camera, z)
        size = z * camera.tan_half_x * rng.uniform(0.15, 0.5)
        tilt = rng.uniform(-50, 50) if rng.uniform() < 0.5 and not planar else 0.0
        scene[f"rect{i}"] = {"type": "rectangle", "bsdf": textured(),
                             "to_world": T().translate([x, y, z]).rotate([0, 1, 0], 180.0 + tilt).scale([size, size, 1.0])}
        desc.append({"kind": "rectangle", "depth_m": z, "tilt_deg": tilt})
    for i in range(0 if planar else int(rng.integers(*params.spheres, endpoint=True))):
        z = depth()
        x, y = _in_view(rng, camera, z)
        r = z * camera.tan_half_x * rng.uniform(0.05, 0.2)
        scene[f"sphere{i}"] = {"type": "sphere", "center": [x, y, z + r], "radius": r, "bsdf": textured()}
        desc.append({"kind": "sphere", "depth_m": z})
    for i in range(0 if planar else int(rng.integers(*params.boxes, endpoint=True))):
        z = depth()
        x, y = _in_view(rng, camera, z)
        s = z * camera.tan_half_x * rng.uniform(0.05, 0.2)
        scene[f"box{i}"] = {"type": "cube", "bsdf": textured(),
                            "to_world": T().translate([x, y, z + s]).rotate([0, 1, 0], rng.uniform(0, 90)).scale(s)}
        desc.append({"kind": "box", "depth_m": z})
    for i in range(int(rng.integers(*params.highlights, endpoint=True))):
        z = depth()
        # a point light on a pixel centre, 0.9 px across: the depth sample at that centre sees it
        # and no neighbour's does, so the AIF + depth describe it consistently
        col, row = int(rng.integers(camera.width)), int(rng.integers(camera.height))
        tx = ((col + 0.5) / camera.width * 2.0 - 1.0) * camera.tan_half_x
        ty = ((row + 0.5) / camera.height * 2.0 - 1.0) * camera.tan_half_x * camera.height / camera.width
        x, y = -tx * z, -ty * z  # image right is world -x, image down is world -y
        r = z * camera.tan_half_x * 2.0 / camera.width * 0.45
        radiance = float(math.exp(rng.uniform(*np.log(params.highlight_radiance))))
        colour = rng.uniform(0.6, 1.0, 3) * radiance
        scene[f"light{i}"] = {"type": "sphere", "center": [x, y, z], "radius": r,
                              "emitter": {"type": "area", "radiance": {"type": "rgb", "value": colour.tolist()}}}
        desc.append({"kind": "highlight", "depth_m": z, "radiance": radiance})
    return scene, {"objects": desc}


OCCLUSION_WALL_M, OCCLUSION_FG_FOCUS_M = 3.0, 0.85  # the wall's depth, a focus on the foreground


def occlusion_scene(mi: ModuleType, cam: Camera, seed: int, highlights: int = 14) -> dict[str, Any]:
    """A scene with continuous depth and strong occlusion, for testing renderers on depth maps.

    A textured sphere, a tilted board and a box in the foreground (0.8-1.1 m) stand on a floor
    that runs back to a textured wall (:data:`OCCLUSION_WALL_M`); ``highlights`` small HDR
    emitters (radiance 10-200) sit on the surfaces, half of them on the foreground, placed on
    the depth map of the scene without them, so an AIF + depth describes them. Focus
    on the wall to blur the foreground over a sharp background, on
    :data:`OCCLUSION_FG_FOCUS_M` for the reverse. Made for the pinhole camera of
    ``benchmarks/bench_continuous.py`` (85 mm on 36 mm, looking along +z).

    Returns:
        The scene dict without a sensor.
    """
    T = mi.ScalarTransform4f
    rng = np.random.default_rng(seed)

    def tex() -> dict[str, Any]:
        return {"type": "diffuse", "reflectance": {"type": "bitmap", "bitmap": mi.Bitmap(_texture(rng)), "raw": True}}

    half = cam.tan_half_x * OCCLUSION_WALL_M * 1.3
    scene: dict[str, Any] = {
        "type": "scene", "integrator": {"type": "path", "max_depth": 3},
        "environment": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
        "wall": {"type": "rectangle", "bsdf": tex(),
                 "to_world": T().translate([0.0, 0.0, OCCLUSION_WALL_M]).rotate([0, 1, 0], 180.0).scale([half, half, 1.0])},
        # the floor: a horizontal plane 0.1 m below the axis, from 0.6 m to the wall
        "floor": {"type": "rectangle", "bsdf": tex(),
                  "to_world": T().translate([0.0, -0.1, 1.8]).rotate([1, 0, 0], -90.0).scale([half, 1.2, 1.0])},
        "sphere": {"type": "sphere", "center": [-0.03, -0.04, 0.8 + 0.06], "radius": 0.06, "bsdf": tex()},
        "board": {"type": "rectangle", "bsdf": tex(),
                  "to_world": T().translate([0.09, 0.0, 0.9]).rotate([0, 1, 0], 180.0 + 55.0).scale([0.035, 0.07, 1.0])},
        "box": {"type": "cube", "bsdf": tex(),
                "to_world": T().translate([-0.11, -0.07, 0.95]).rotate([0, 1, 0], 35.0).scale(0.025)},
    }
    depth = render_depth(mi, mi.load_dict(scene), cam)
    tx = ((np.arange(cam.width) + 0.5) / cam.width * 2.0 - 1.0) * cam.tan_half_x
    ty = ((np.arange(cam.height) + 0.5) / cam.height * 2.0 - 1.0) * cam.tan_half_x * cam.height / cam.width
    near = np.argwhere(depth < 1.2)  # half of the highlights on the foreground objects
    for i in range(highlights):
        if i % 2 and len(near):
            r, c = (int(v) for v in near[rng.integers(len(near))])
        else:
            r, c = int(rng.integers(cam.height)), int(rng.integers(cam.width))
        z = float(depth[r, c]) * 0.995
        if not np.isfinite(z):
            continue
        radius = z * cam.tan_half_x * 2.0 / cam.width * 0.45  # under a pixel: one depth sample sees it
        colour = rng.uniform(0.6, 1.0, 3) * float(np.exp(rng.uniform(np.log(10.0), np.log(200.0))))
        scene[f"light{i}"] = {"type": "sphere", "center": [-tx[c] * z, -ty[r] * z, z], "radius": radius,
                              "emitter": {"type": "area", "radiance": {"type": "rgb", "value": colour.tolist()}}}
    return scene


def camera_from_xml(mi: ModuleType, path: Path, params: dict[str, str] | None = None) -> tuple[Any, Camera]:
    """Load a user's Mitsuba scene (``params``: values of its ``$name`` parameters) and its
    first sensor's pinhole camera.

    Raises:
        ValueError: the file has no perspective-like sensor, or one with a principal-point offset.
    """
    scene = mi.load_file(str(path), **(params or {}))
    if not scene.sensors():
        raise ValueError(f"{path}: the scene has no sensor; give the camera with the lens options")
    sensor = scene.sensors()[0]
    params = mi.traverse(sensor)
    if "x_fov" not in params:
        raise ValueError(f"{path}: sensor {sensor.class_().name()} has no field of view; need a perspective or thinlens sensor")
    for key in ("principal_point_offset_x", "principal_point_offset_y"):
        if key in params and abs(float(params[key])) > 1e-9:
            raise ValueError(f"{path}: {key} = {float(params[key])}; only centred cameras are supported")
    size = sensor.film().size()
    matrix = np.array(sensor.world_transform().matrix, dtype=np.float64).reshape(4, 4)
    return scene, Camera(matrix, float(np.asarray(params["x_fov"]).reshape(-1)[0]), int(size[0]), int(size[1]))

"""The on-disk focal-stack dataset and its loader (the normalisation lives in ``normalization``).

Format (``format_version`` 1): one folder per scene (any name not starting with ``.``)::

    aif.exr          all-in-focus linear RGB, float32, >= 0
    depth.exr        planar depth along the optical axis in metres, float32, > 0, +inf allowed
    defocus_<k>.exr  slice k: the defocused linear RGB at focus distance k
    coc_<k>.exr      slice k: signed CoC diameter in px (negative in front of the focus plane)
    scene.json       image size, lens (mm), the image's window on the lens's sensor, aperture,
                     focus distances (m), per-slice max |CoC|, generator and seed, units

A scene is written into a hidden temporary folder and renamed into place when complete, so a
scene folder either is whole or does not exist (tools can resume by skipping existing scenes).
"""

from __future__ import annotations

import json
import logging
import math
import os
import random
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from ..core.apertures import ApertureModel
from ..core.checks import check_finite, check_nonnegative, check_positive, check_shape
from ..core.contract import Contract
from ..core.io import atomic_directory, read_image, read_json, write_image, write_json
from ..core.normalization import Normalization
from ..core.optics import SensorWindow, ThinLens

log = logging.getLogger(__name__)

FORMAT = "neuralbokeh-focal-stack"
FORMAT_VERSION = 1
TILE_PX = 64  # EXR tile side of the scene files: a 256^2 crop decodes 1.3-1.6x its pixels, not 7.5x (full rows)
UNITS = {
    "color": "linear scene-referred RGB (HDR), >= 0",
    "depth": "m along the optical axis (planar), > 0, inf allowed",
    "coc": "px, signed diameter (negative in front of the focus plane)",
    "lens": "mm",
    "focus": "m",
}


def write_scene(
    folder: str | os.PathLike,
    aif: np.ndarray,
    depth_m: np.ndarray,
    defocus: Sequence[np.ndarray],
    coc_px: Sequence[np.ndarray],
    lens: ThinLens,
    focus_distances_m: Sequence[float],
    aperture: ApertureModel | None,
    generator: dict[str, Any],
    sensor_window: SensorWindow | None = None,
) -> Path:
    """Write one scene atomically in the dataset format.

    Args:
        folder: the scene folder to create; must not exist yet.
        aif: ``(H, W, 3)`` all-in-focus linear RGB, finite, >= 0.
        depth_m: ``(H, W)`` planar depth in m, > 0 (inf allowed).
        defocus: K arrays ``(H, W, 3)``, defocused linear RGB, finite, >= 0.
        coc_px: K arrays ``(H, W)``, signed CoC in px, finite.
        lens: the lens the CoC maps were computed with.
        focus_distances_m: K focus distances in m.
        aperture: the aperture model of the defocus images; None when unknown (photographs:
            the lens itself is what the network learns).
        generator: provenance (tool name, version, seed, options); JSON-serialisable.
        sensor_window: the part of ``lens``'s sensor the image covers (default: all of it);
            the CoC maps are in this image's px (``lens.coc_px(..., window=sensor_window)``).

    Returns:
        The scene folder.

    Raises:
        FileExistsError: ``folder`` exists.
        ValueError: inconsistent shapes or counts, or invalid values (named).
    """
    folder = Path(folder)
    if folder.exists():
        raise FileExistsError(f"scene folder already exists: {folder}")
    dims = check_shape("aif", aif, "H W 3")
    check_nonnegative("aif", aif)
    check_shape("depth_m", depth_m, "H W", H=dims["H"], W=dims["W"])
    check_positive("depth", depth_m, " m", allow_inf=True)
    k = len(focus_distances_m)
    if not (len(defocus) == len(coc_px) == k) or k == 0:
        raise ValueError(
            f"need one defocus image and one CoC map per focus distance, got {len(defocus)} defocus, "
            f"{len(coc_px)} CoC and {k} focus distances"
        )
    for i, (img, coc) in enumerate(zip(defocus, coc_px)):
        check_shape(f"defocus[{i}]", img, "H W 3", H=dims["H"], W=dims["W"])
        check_nonnegative(f"defocus[{i}]", img)
        check_shape(f"coc[{i}]", coc, "H W", H=dims["H"], W=dims["W"])
        check_finite(f"coc[{i}]", coc, " px")
    finite = depth_m[np.isfinite(depth_m)]
    far = float(depth_m.max())
    meta = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "image_size": {"width": dims["W"], "height": dims["H"]},
        "lens": lens.to_dict(),
        "sensor_window": (sensor_window or SensorWindow()).to_dict(),
        "aperture": aperture.to_dict() if aperture is not None else None,
        "focus_distances_m": [float(f) for f in focus_distances_m],
        "depth_range_m": [float(finite.min()) if finite.size else None, far if math.isfinite(far) else None],
        "files": {"aif": "aif.exr", "depth": "depth.exr"},
        "slices": [
            {"focus_m": float(f), "defocus": f"defocus_{i}.exr", "coc": f"coc_{i}.exr", "max_abs_coc_px": float(np.abs(c).max())}
            for i, (f, c) in enumerate(zip(focus_distances_m, coc_px))
        ],
        "max_abs_coc_px": float(max(np.abs(c).max() for c in coc_px)),
        "generator": generator,
        "units": UNITS,
    }
    with atomic_directory(folder) as tmp:
        rgb = ["R", "G", "B"]
        # tiled, so that a training crop decodes its own tiles, not the frame's full rows
        write_image(tmp / "aif.exr", aif, channel_names=rgb, tile=TILE_PX)
        write_image(tmp / "depth.exr", depth_m, channel_names=["Z"], attributes={"neuralbokeh:units": "m"}, tile=TILE_PX)
        for i, (img, coc) in enumerate(zip(defocus, coc_px)):
            write_image(tmp / f"defocus_{i}.exr", img, channel_names=rgb, tile=TILE_PX)
            write_image(tmp / f"coc_{i}.exr", coc, channel_names=["Y"], attributes={"neuralbokeh:units": "px"},
                        tile=TILE_PX)
        write_json(tmp / "scene.json", meta)
    return folder


def read_scene_meta(folder: str | os.PathLike) -> dict[str, Any]:
    """Read and validate ``scene.json`` of a scene folder (files listed must exist).

    Raises:
        FileNotFoundError: scene.json or a listed image is missing (named).
        ValueError: wrong format/version or malformed content (named).
    """
    folder = Path(folder)
    meta = read_json(folder / "scene.json")
    if meta.get("format") != FORMAT:
        raise ValueError(f"{folder / 'scene.json'}: format must be {FORMAT!r}, got {meta.get('format')!r}")
    if meta.get("format_version") != FORMAT_VERSION:
        raise ValueError(
            f"{folder / 'scene.json'}: format_version {meta.get('format_version')!r} is not supported "
            f"(this neuralbokeh reads version {FORMAT_VERSION})"
        )
    for key in ("image_size", "lens", "aperture", "slices", "files", "max_abs_coc_px"):
        if key not in meta:
            raise ValueError(f"{folder / 'scene.json'}: missing key {key!r}")
    if not meta["slices"]:
        raise ValueError(f"{folder / 'scene.json'}: no slices")
    names = [meta["files"]["aif"], meta["files"]["depth"]]
    names += [s[k] for s in meta["slices"] for k in ("defocus", "coc")]
    for name in names:
        if not (folder / name).is_file():
            raise FileNotFoundError(f"scene {folder}: file {name} listed in scene.json is missing")
    return meta


def _load(folder: Path, name: str, channels: int, size: dict[str, int], rows: tuple[int, int] | None = None,
          cols: tuple[int, int] | None = None) -> np.ndarray:
    arr = read_image(folder / name, rows=rows, cols=cols)
    want = (size["height"] if rows is None else rows[1] - rows[0], size["width"] if cols is None else cols[1] - cols[0],
            channels)
    if arr.shape != want:
        raise ValueError(f"{folder / name}: expected shape (H, W, C) = {want} from scene.json, got {arr.shape}")
    return arr


def load_scene(folder: str | os.PathLike) -> dict[str, Any]:
    """Load a whole scene as numpy arrays: ``aif (H,W,3)``, ``depth (H,W)``, ``defocus`` and
    ``coc`` lists, plus ``meta`` (the validated scene.json)."""
    folder = Path(folder)
    meta = read_scene_meta(folder)
    size = meta["image_size"]
    return {
        "meta": meta,
        "aif": _load(folder, meta["files"]["aif"], 3, size),
        "depth": _load(folder, meta["files"]["depth"], 1, size)[..., 0],
        "defocus": [_load(folder, s["defocus"], 3, size) for s in meta["slices"]],
        "coc": [_load(folder, s["coc"], 1, size)[..., 0] for s in meta["slices"]],
    }


def find_scenes(roots: str | os.PathLike | Sequence[str | os.PathLike]) -> list[Path]:
    """Scene folders under one or more dataset roots, sorted; hidden (temporary) folders ignored.

    Raises:
        FileNotFoundError: a root does not exist, or a sub-folder has no scene.json.
        ValueError: no scene at all.
    """
    if isinstance(roots, (str, os.PathLike)):
        roots = [roots]
    scenes: list[Path] = []
    for root in map(Path, roots):
        if not root.is_dir():
            raise FileNotFoundError(f"dataset folder does not exist: {root}")
        for sub in sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")):
            if not (sub / "scene.json").is_file():
                raise FileNotFoundError(f"{sub} has no scene.json: not a scene of the dataset format (incomplete?)")
            scenes.append(sub)
    if not scenes:
        raise ValueError(f"no scenes found in {[str(r) for r in roots]}")
    return scenes


def split_scenes(scenes: Sequence[Path], split: str, test_fraction: float = 0.2, seed: int = 0) -> list[Path]:
    """Scene-level split: a seeded shuffle, the first ``round(n * test_fraction)`` are ``test``.

    With two or more scenes and a fraction in (0, 1) both parts hold at least one scene.
    Slices of one scene are never split apart.
    """
    if split not in ("train", "test", "all"):
        raise ValueError(f"split must be 'train', 'test' or 'all', got {split!r}")
    if not (0.0 <= test_fraction < 1.0):
        raise ValueError(f"test_fraction must be in [0, 1), got {test_fraction}")
    if split == "all":
        return list(scenes)
    order = sorted(scenes, key=str)
    random.Random(seed).shuffle(order)
    n = len(order)
    n_test = round(n * test_fraction)
    if test_fraction > 0 and n >= 2:
        n_test = min(max(n_test, 1), n - 1)
    chosen = order[:n_test] if split == "test" else order[n_test:]
    if not chosen:
        raise ValueError(f"split {split!r} is empty: {n} scene(s) with test_fraction={test_fraction}")
    return sorted(chosen, key=str)


class FocalStackDataset(torch.utils.data.Dataset):
    """(all-in-focus RGB, CoC map) -> defocused RGB samples, one per (scene, slice).

    Args:
        roots: one or more dataset folders (each holding scene folders).
        split: ``"train"``, ``"test"`` or ``"all"``; split by scene (see :func:`split_scenes`).
        test_fraction: share of scenes held out for ``"test"``.
        split_seed: seed of the scene shuffle.
        normalization: HDR <-> [-1, 1) map for colours (default :class:`Normalization`).
        coc_scale_px: CoC value (px) mapped to 1 (default: the largest |CoC| over *all* scenes
            of ``roots``, at least 1 px, so train and test share it). A larger |CoC| in an item
            raises ``ValueError`` instead of being clipped.
        normalize: if False, return linear colours and CoC in px.

    Each item is a dict: ``aif (3, H, W)``, ``coc (1, H, W)``, ``defocus (3, H, W)`` float32
    tensors (normalised unless ``normalize=False``), ``window (4,)`` (the image's part of the
    sensor: left, top, width, height in fractions), ``scene`` (folder name), ``slice`` (index)
    and ``focus_m``.

    Raises:
        FileNotFoundError / ValueError: missing or inconsistent files, named.
    """

    def __init__(
        self,
        roots: str | os.PathLike | Sequence[str | os.PathLike],
        split: str = "all",
        test_fraction: float = 0.2,
        split_seed: int = 0,
        normalization: Normalization | None = None,
        coc_scale_px: float | None = None,
        normalize: bool = True,
    ) -> None:
        all_scenes = find_scenes(roots)
        metas = {p: read_scene_meta(p) for p in all_scenes}
        self.scenes = split_scenes(all_scenes, split, test_fraction, split_seed)
        self.metas = [metas[p] for p in self.scenes]
        self.items = [(i, k) for i, m in enumerate(self.metas) for k in range(len(m["slices"]))]
        self.max_coc_px = max(float(m["max_abs_coc_px"]) for m in metas.values())
        self.coc_scale_px = float(coc_scale_px) if coc_scale_px is not None else max(self.max_coc_px, 1.0)
        check_positive("coc_scale_px", self.coc_scale_px, " px")
        self.normalization = normalization or Normalization()
        self.normalize = normalize
        log.info("FocalStackDataset(%s): %d scenes, %d samples, max |CoC| %.2f px", split, len(self.scenes), len(self.items),
                 self.max_coc_px)

    def __len__(self) -> int:
        return len(self.items)

    def shared(self, key: str) -> Any:
        """A ``scene.json`` entry (``"lens"``, ``"aperture"``, ``"image_size"``) that every scene
        of this split must share (one model learns one lens at one size).

        Raises:
            ValueError: the scenes differ, with the values found.
        """
        values = {json.dumps(m[key], sort_keys=True) for m in self.metas}
        if len(values) != 1:
            raise ValueError(f"all scenes of one model must share {key!r}; found {len(values)} different ones: {sorted(values)}")
        return self.metas[0][key]

    def contract(self, crop: Sequence[int] | None = None) -> Contract:
        """The data contract a model trained on this split keeps (:class:`Contract`).

        ``crop`` ``(height, width)`` px: a model trained on crops of this size (the scenes may
        differ in size, each at least this big); else every scene must share one image size.
        Every scene must share one lens (on its whole sensor) and aperture.

        Raises:
            ValueError: scenes that differ in lens, aperture or (without ``crop``) size, or a
                scene smaller than ``crop`` (named).
        """
        lens = self.shared("lens")
        if crop:
            height, width = (int(v) for v in crop)
            small = [f"{p.name} ({m['image_size']['width']}x{m['image_size']['height']})" for p, m in zip(self.scenes, self.metas)
                     if m["image_size"]["height"] < height or m["image_size"]["width"] < width]
            if small:
                raise ValueError(f"scenes smaller than the {width}x{height} px training crop: {', '.join(small)}; "
                                 "lower data.crop")
        else:
            size = self.shared("image_size")
            height, width = int(size["height"]), int(size["width"])
        return Contract(height, width, self.normalization, self.coc_scale_px, self.max_coc_px,
                        ThinLens.from_dict(lens) if lens else None, self.shared("aperture"))

    def __getitem__(self, index: int) -> dict[str, Any]:
        return self._read(index)

    def crop_item(self, index: int, size: Sequence[int], generator: torch.Generator) -> dict[str, Any]:
        """Item ``index`` cut to a random crop of ``size`` ``(h, w)`` px (the place drawn from
        ``generator``: a row, then a column, as :func:`random_crop_place`), reading only the
        crop's rows; its ``window`` is the crop's part of the sensor."""
        meta = self.metas[self.items[index][0]]
        r, c = random_crop_place((meta["image_size"]["height"], meta["image_size"]["width"]), size, generator)
        return self._read(index, (r, r + int(size[0])), (c, c + int(size[1])))

    def _read(self, index: int, rows: tuple[int, int] | None = None, cols: tuple[int, int] | None = None) -> dict[str, Any]:
        i, k = self.items[index]
        folder, meta = self.scenes[i], self.metas[i]
        size, sl = meta["image_size"], meta["slices"][k]
        aif = _load(folder, meta["files"]["aif"], 3, size, rows, cols)
        defocus = _load(folder, sl["defocus"], 3, size, rows, cols)
        coc = _load(folder, sl["coc"], 1, size, rows, cols)
        check_nonnegative(str(folder / meta["files"]["aif"]), aif)
        check_nonnegative(str(folder / sl["defocus"]), defocus)
        check_finite(str(folder / sl["coc"]), coc, " px")
        if self.normalize:
            limit = np.abs(coc).max()
            if limit > self.coc_scale_px:
                raise ValueError(
                    f"{folder / sl['coc']}: |CoC| up to {limit:.3f} px exceeds coc_scale_px={self.coc_scale_px} px"
                )
            aif, defocus = self.normalization.encode(aif), self.normalization.encode(defocus)
            coc = coc / self.coc_scale_px

        def chw(a: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1), dtype=np.float32))

        window = SensorWindow.from_dict(meta.get("sensor_window"))
        if rows is not None:
            window = window.crop(rows, cols, size["height"], size["width"])
        full = (size["height"], size["width"])
        return {
            "aif": chw(aif),
            "coc": chw(coc),
            "defocus": chw(defocus),
            "window": torch.tensor([window.left, window.top, window.width, window.height], dtype=torch.float32),
            "cut_sides": cut_sides(rows or (0, full[0]), cols or (0, full[1]), *full),
            "scene": folder.name,
            "slice": k,
            "focus_m": float(sl["focus_m"]),
        }


def cut_sides(rows: Sequence[int], cols: Sequence[int], height: int, width: int) -> torch.Tensor:
    """``(4,)`` bool: which sides (top, bottom, left, right) of the crop ``rows`` x ``cols``
    (``[start, stop)`` px) of a ``height`` x ``width`` frame cut through the frame. Next to such a
    side the defocused target holds light from beyond the crop that the crop's input lacks."""
    return torch.tensor([rows[0] > 0, rows[1] < height, cols[0] > 0, cols[1] < width])


def random_crop_place(size: Sequence[int], crop: Sequence[int], generator: torch.Generator) -> tuple[int, int]:
    """``(row, col)`` of a random ``crop`` ``(h, w)`` inside an image of ``size`` ``(H, W)`` px."""
    r = int(torch.randint(0, int(size[0]) - int(crop[0]) + 1, (1,), generator=generator))
    c = int(torch.randint(0, int(size[1]) - int(crop[1]) + 1, (1,), generator=generator))
    return r, c

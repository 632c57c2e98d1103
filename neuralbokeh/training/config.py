"""Typed training configuration, loaded from TOML with command-line overrides.

A config file has three tables, ``[data]``, ``[model]`` and ``[train]``, whose keys are the
fields of the dataclasses below; a top-level ``extends = "other.toml"`` (relative to the file)
starts from another config. Unknown keys and wrong types are errors. Overrides are
``section.key=value`` with TOML values (``train.steps=50``, ``data.roots=["a", "b"]``); a value
that is not valid TOML is taken as a string (``train.out_dir=runs/x``).
"""

from __future__ import annotations

import math
import tomllib
import types
import typing
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

from ..networks.config import ModelConfig


@dataclass
class DataConfig:
    """Where the focal stacks are and how they are split and normalised.

    Args:
        roots: dataset folders (relative paths are relative to the working directory).
        test_fraction: share of scenes held out for evaluation, in [0, 1).
        split_seed: seed of the scene-level split.
        normalization_scale: linear value mapped to 0 by :class:`neuralbokeh.core.normalization.Normalization`.
        cache: keep loaded samples in memory (small datasets).
        crop: ``[height, width]`` px of the random crop each training sample is cut to (scenes
            of any sizes, mixed, each at least this big; every crop carries its window on the
            sensor); ``[]``: whole scenes, which must then share one size. Held-out evaluation
            always runs on whole frames. Lens network only.
        crop_margin: px the loss stays away from each side where a crop cuts through its
            frame (the target there holds light from beyond the crop that the crop's input
            lacks), >= 0, or ``"auto"``: the data's largest CoC radius. 0 takes the loss on the
            whole crop (an ablation).
    """

    roots: list[str] = field(default_factory=list)
    test_fraction: float = 0.2
    split_seed: int = 0
    normalization_scale: float = 0.18
    cache: bool = True
    crop: list[int] = field(default_factory=list)
    crop_margin: int | str = "auto"


@dataclass
class TrainSection:
    """The optimisation.

    Args:
        steps: optimiser steps.
        batch_size: samples per step over all processes (divisible by the process count).
        lr: Adam learning rate.
        lr_kernel_scaling: ``"fan_in"`` (default): the per-channel k x k kernels learn at
            ``lr / k^2``. Adam moves every weight by about ``lr`` per step whatever its fan-in,
            so a 41x41 kernel's output would move ~1700x more than a 1x1 weight's; dividing by
            the fan-in gives every layer the same output step (as muP prescribes for Adam).
            ``"none"``: one learning rate for all (measured: diverges at N = 20 with lr 1e-3).
        field_lr_scale: the lens network's field-dependent pupil corrections learn at this
            fraction of ``lr`` (the lens-wide pupil at ``lr``), in (0, 1].
        ssim_weight: weight of ``1 - SSIM`` (the held-out metric, on the same pixels) added to
            the MSE, >= 0 (0: the MSE alone, as the paper). The MSE rewards a blur that is right
            on average; SSIM also asks for the structure (e.g. how much of a fine texture survives
            a given CoC), where the MSE alone traded it away for PSNR.
        loss_pool: px, an integer >= 1: the loss (MSE and SSIM) is taken on the images averaged
            over ``loss_pool`` x ``loss_pool`` px blocks in linear light (1: on the pixels). A
            target's noise biases a loss on normalised pixels towards a smaller blur (the
            normalisation is concave: see :func:`~neuralbokeh.training.loop.pool_linear`); the
            block mean divides that bias by about ``loss_pool ** 2``. ``loss = "image"`` only.
        pupil_tv: weight of the lens network's pupil roughness
            (:meth:`~neuralbokeh.networks.lens.LensBokeh.pupil_roughness`, the total variation of
            the transmission over its mean) added to the loss, >= 0 (0: off). An aperture is flat
            with a rim; a pupil that fits the noise of a few training renders is not.
        pupil_chroma: weight of the lens network's colour spread
            (:meth:`~neuralbokeh.networks.lens.LensBokeh.pupil_chroma`: how far the three
            channels' pupils and CoC scales differ) added to the loss, >= 0 (0: off). A lens's
            colours differ only as far as the data shows (lateral and axial colour); channels
            learned apart from noise put colour fringes on highlights.
        pupil_field_spread: weight of the lens network's field spread
            (:meth:`~neuralbokeh.networks.lens.LensBokeh.pupil_field_spread`: how far the pupils
            at the field grid's nodes differ from the lens-wide pupil) added to the loss, >= 0
            (0: off). A lens's pupil changes over the field as far as the data shows; corrections
            learned per region from a few noisy renders fit their noise.
        lr_schedule: ``"cosine"`` (to 10% of lr) or ``"constant"``, after ``warmup_steps``.
        ema_steps: steps, an integer >= 0: the weights that are evaluated, checkpointed as the
            model and exported are an exponential moving average of the trained ones over about
            this many recent steps (decay ``1 - 1 / ema_steps``, shorter in the first steps;
            :func:`~neuralbokeh.training.loop.ema_weight`); 0: the trained weights themselves. At a
            constant rate Adam moves every weight by about ``lr`` a step in noisy directions; the
            average keeps the point the weights wander around.
        warmup_steps: linear warm-up steps.
        grad_clip: clip the gradient norm to this value (0 = off).
        loss: ``"image"`` (MSE of the reassembled image, the paper) or ``"tile"`` (ablation).
        seed: seed of initialisation and data order.
        eval_every: steps between held-out evaluations (and at the end).
        checkpoint_every: steps between checkpoints (and at the end).
        max_nonfinite: abort after this many non-finite steps in a row.
        out_dir: folder for checkpoints and logs.
        threads: torch CPU threads per process (0 = torch's default).
    """

    steps: int = 1000
    batch_size: int = 4
    lr: float = 2e-3
    lr_schedule: str = "cosine"
    ema_steps: int = 0
    lr_kernel_scaling: str = "fan_in"
    field_lr_scale: float = 0.25
    ssim_weight: float = 0.0
    loss_pool: int = 1
    pupil_tv: float = 0.0
    pupil_chroma: float = 0.0
    pupil_field_spread: float = 0.0
    warmup_steps: int = 20
    grad_clip: float = 1.0
    loss: str = "image"
    seed: int = 0
    eval_every: int = 200
    checkpoint_every: int = 200
    max_nonfinite: int = 5
    out_dir: str = "runs/default"
    threads: int = 0


@dataclass
class TrainConfig:
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    train: TrainSection = field(default_factory=TrainSection)

    def __post_init__(self) -> None:
        d, t = self.data, self.train
        if not d.roots:
            raise ValueError("data.roots must name at least one dataset folder")
        if not (0.0 <= d.test_fraction < 1.0):
            raise ValueError(f"data.test_fraction must be in [0, 1), got {d.test_fraction}")
        for name, value, allowed in (
            ("train.lr_schedule", t.lr_schedule, ("cosine", "constant")),
            ("train.lr_kernel_scaling", t.lr_kernel_scaling, ("fan_in", "none")),
            ("train.loss", t.loss, ("image", "tile")),
        ):
            if value not in allowed:
                raise ValueError(f"{name} must be one of {allowed}, got {value!r}")
        for name in ("steps", "batch_size", "eval_every", "checkpoint_every", "max_nonfinite"):
            if getattr(t, name) < 1:
                raise ValueError(f"train.{name} must be >= 1, got {getattr(t, name)}")
        if isinstance(t.ssim_weight, bool) or not (isinstance(t.ssim_weight, (int, float)) and math.isfinite(t.ssim_weight)
                                                     and t.ssim_weight >= 0.0):
            raise ValueError(f"train.ssim_weight must be a finite number >= 0, got {t.ssim_weight!r}")
        if isinstance(t.loss_pool, bool) or not isinstance(t.loss_pool, int) or t.loss_pool < 1:
            raise ValueError(f"train.loss_pool must be an integer >= 1 (px), got {t.loss_pool!r}")
        if t.loss_pool > 1 and t.loss != "image":
            raise ValueError(f"train.loss_pool = {t.loss_pool} needs train.loss = 'image' (the reassembled image), got {t.loss!r}")
        for name in ("pupil_tv", "pupil_chroma", "pupil_field_spread"):
            w = getattr(t, name)
            if isinstance(w, bool) or not (isinstance(w, (int, float)) and math.isfinite(w) and w >= 0.0):
                raise ValueError(f"train.{name} must be a finite number >= 0, got {w!r}")
            if w > 0 and self.model.architecture != "lens":
                raise ValueError(f"train.{name} needs the lens architecture (it has pupils), "
                                 f"got model.architecture = {self.model.architecture!r}")
        if isinstance(t.ema_steps, bool) or not isinstance(t.ema_steps, int) or t.ema_steps < 0:
            raise ValueError(f"train.ema_steps must be an integer >= 0 (steps; 0: off), got {t.ema_steps!r}")
        if not (0.0 < t.field_lr_scale <= 1.0):
            raise ValueError(f"train.field_lr_scale must be in (0, 1], got {t.field_lr_scale}")
        if d.crop and (len(d.crop) != 2 or any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in d.crop)):
            raise ValueError(f"data.crop must be [height, width] in px (integers >= 1) or [] for whole scenes, got {d.crop!r}")
        if d.crop_margin != "auto" and (isinstance(d.crop_margin, bool) or not isinstance(d.crop_margin, int)
                                        or d.crop_margin < 0):
            raise ValueError(f"data.crop_margin must be an integer >= 0 (px) or \"auto\", got {d.crop_margin!r}")
        if d.crop and self.model.architecture != "lens":
            raise ValueError(f"data.crop needs the lens network (model.architecture = 'lens'): the "
                             f"{self.model.architecture!r} network is built for one image size")
        if t.lr <= 0 or t.grad_clip < 0 or t.warmup_steps < 0 or t.threads < 0:
            raise ValueError("train.lr must be > 0 and train.grad_clip, warmup_steps, threads >= 0")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


_SECTIONS = {"data": DataConfig, "model": ModelConfig, "train": TrainSection}


def _check_type(where: str, value: Any, hint: Any) -> Any:
    """Return ``value`` converted where lossless (int -> float), else raise ``TypeError``."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        for option in typing.get_args(hint):
            try:
                return _check_type(where, value, option)
            except TypeError:
                pass
        raise TypeError(f"{where} must be {hint}, got {value!r} ({type(value).__name__})")
    if origin is list:
        (inner,) = typing.get_args(hint)
        if not isinstance(value, list):
            raise TypeError(f"{where} must be a list, got {value!r} ({type(value).__name__})")
        return [_check_type(f"{where}[{i}]", v, inner) for i, v in enumerate(value)]
    if hint is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if hint is int and isinstance(value, bool) or not isinstance(value, hint):
        raise TypeError(f"{where} must be {getattr(hint, '__name__', hint)}, got {value!r} ({type(value).__name__})")
    return value


def _merge(base: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in extra.items():
        out[key] = _merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def _read_toml(path: Path, seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    path = path.resolve()
    if path in seen:
        raise ValueError(f"config {path} extends itself (cycle: {' -> '.join(map(str, seen))})")
    if not path.is_file():
        raise FileNotFoundError(f"no such config file: {path}")
    try:
        raw = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"{path}: invalid TOML: {e}") from None
    parent = raw.pop("extends", None)
    if parent is None:
        return raw
    return _merge(_read_toml(path.parent / parent, seen + (path,)), raw)


def parse_override(text: str) -> tuple[str, str, Any]:
    """``"section.key=value"`` -> (section, key, value) with the value parsed as TOML."""
    lhs, sep, rhs = text.partition("=")
    section, dot, key = lhs.strip().partition(".")
    if not sep or not dot or not key:
        raise ValueError(f"override must look like section.key=value, got {text!r}")
    try:
        value = tomllib.loads(f"v = {rhs}")["v"]
    except tomllib.TOMLDecodeError:
        value = rhs.strip()
    return section, key, value


def build_config(raw: dict[str, Any], source: str = "config") -> TrainConfig:
    """Typed :class:`TrainConfig` from a nested dict; unknown keys and wrong types raise."""
    unknown = set(raw) - set(_SECTIONS)
    if unknown:
        raise ValueError(f"{source}: unknown section(s) {sorted(unknown)}; expected {sorted(_SECTIONS)}")
    parts = {}
    for name, cls in _SECTIONS.items():
        values = dict(raw.get(name, {}))
        hints = typing.get_type_hints(cls)
        known = {f.name for f in fields(cls)}
        bad = set(values) - known
        if bad:
            raise ValueError(f"{source}: unknown key(s) {sorted(bad)} in [{name}]; expected {sorted(known)}")
        parts[name] = cls(**{k: _check_type(f"{name}.{k}", v, hints[k]) for k, v in values.items()})
    return TrainConfig(**parts)


def load_config(path: str | Path, overrides: list[str] | None = None) -> TrainConfig:
    """Load a TOML config (following ``extends``) and apply ``section.key=value`` overrides.

    Raises:
        FileNotFoundError: the file (or one it extends) is missing.
        ValueError / TypeError: invalid TOML, unknown keys, wrong types or values.
    """
    raw = _read_toml(Path(path))
    for text in overrides or []:
        section, key, value = parse_override(text)
        if section not in _SECTIONS:
            raise ValueError(f"command-line override {text!r}: unknown section {section!r}; expected {sorted(_SECTIONS)}")
        known = {f.name for f in fields(_SECTIONS[section])}
        if key not in known:
            raise ValueError(f"command-line override {text!r}: unknown key {key!r} in [{section}]; expected {sorted(known)}")
        raw.setdefault(section, {})[key] = value
    return build_config(raw, str(path))

"""The training loop: seeded, resumable bit for bit on CPU, single- or multi-process.

Multi-process: started by ``torchrun`` (``WORLD_SIZE`` > 1), it uses gloo on CPU and nccl on
GPU, a ``DistributedSampler`` over the training scenes' samples, and rank 0 for logging,
evaluation and checkpoints. Data order is a pure function of (seed, step), which is what makes
``resume`` continue exactly where a run stopped.

Loss: MSE of the reassembled image in the normalised space (``loss = "tile"``: MSE of the
un-blended tiles, the paper's ablation), with ``loss_pool`` on blocks averaged in linear light
(:func:`pool_linear`), plus the SSIM term and the pupil priors the config weighs. A step whose
loss or gradient is not finite is skipped and counted; ``max_nonfinite`` in a row abort with the
step and the batch's scenes named.

Evaluation (held-out scenes): PSNR and SSIM (kornia) of the normalised images mapped to [0, 1]
(``(n + 1) / 2``), next to three baselines on the same samples, computed once: the identity (the
all-in-focus image returned unchanged), a CoC-driven Gaussian blur (the scatter renderer with a
Gaussian profile, sigma = CoC / 4) and the "oracle" (the scatter renderer with the aperture the
data's ``scene.json`` declares: exact on data it rendered; what knowing the lens is worth; absent
for photographs, whose aperture is unknown).
"""

from __future__ import annotations

import contextlib
import csv
import gc
import logging
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import torch
import torch.distributed as dist
import torch.nn.functional as F
from kornia.metrics import psnr, ssim
from torch.nn.parallel import DistributedDataParallel
from torch.optim.swa_utils import AveragedModel
from torch.utils.data.distributed import DistributedSampler
from tqdm import tqdm

from ..checkpoint import load_checkpoint, save_checkpoint
from ..core.apertures import ApertureModel, Gaussian
from ..core.io import write_json
from ..core.normalization import Normalization
from ..core.optics import SensorWindow
from ..data.check import require_sound
from ..data.dataset import FocalStackDataset, cut_sides, random_crop_place
from ..networks import ModelConfig, build_model
from ..render import scatter_defocus
from .config import TrainConfig

log = logging.getLogger(__name__)

CSV_FIELDS = [
    "step", "loss", "lr", "skipped", "eval_psnr", "eval_ssim",
    "identity_psnr", "identity_ssim", "gaussian_psnr", "gaussian_ssim", "oracle_psnr", "oracle_ssim", "elapsed_s",
]


def run_model(model: torch.nn.Module, x: torch.Tensor, window: torch.Tensor | None, **kwargs: Any) -> torch.Tensor:
    """``model(x, window)`` with each image's sensor ``window`` ``(B, 4)`` (the
    :class:`~neuralbokeh.networks.BokehNetwork` call)."""
    return model(x, window, **kwargs)


def compute_loss(model: torch.nn.Module, x: torch.Tensor, y: torch.Tensor, kind: str,
                 window: torch.Tensor | None = None, weights: torch.Tensor | None = None,
                 ssim_weight: float = 0.0, pool: int = 1, normalization: Normalization | None = None) -> torch.Tensor:
    """MSE of the reassembled image (``"image"``) or of the un-blended tiles (``"tile"``), over
    the pixels where ``weights`` ``(B, 1, H, W)`` is 1 (all when None; see :func:`loss_weights`),
    plus ``ssim_weight`` x (1 - SSIM) over the same pixels (the images mapped to [0, 1], 11 px
    window: the evaluation's SSIM). ``pool`` > 1 (``"image"`` only) takes both on the images
    averaged over ``pool`` x ``pool`` px blocks in linear light (see :func:`pool_linear`;
    ``normalization``: the data's, default :class:`Normalization`)."""
    if kind == "tile":
        inner = model.module if isinstance(model, DistributedDataParallel) else model
        pred, y = run_model(model, x, window, return_tiles=True), inner.tile_targets(y)
        weights = None if weights is None else inner.tile_targets(weights)
    else:
        pred = run_model(model, x, window)
    if pool > 1:
        if kind == "tile":
            raise ValueError(f"train.loss_pool = {pool} needs train.loss = 'image', got 'tile'")
        norm = normalization or Normalization()
        pred, y = pool_linear(pred, pool, norm), pool_linear(y, pool, norm)
        weights = None if weights is None else F.avg_pool2d(weights, pool, ceil_mode=True)
    def mean(per_pixel: torch.Tensor) -> torch.Tensor:  # over the kept pixels
        if weights is None:
            return per_pixel.mean()
        return (per_pixel * weights).sum() / (weights.sum() * per_pixel.shape[1]).clamp_min(1.0)

    loss = mean((pred - y).square())
    if ssim_weight > 0:
        loss = loss + ssim_weight * mean(1.0 - ssim((pred + 1) / 2, (y + 1) / 2, 11))
    return loss


def pool_linear(n: torch.Tensor, pool: int, normalization: Normalization) -> torch.Tensor:
    """Normalised images ``(B, C, H, W)`` averaged over ``pool`` x ``pool`` px blocks in linear
    light, normalised again: ``(B, C, ceil(H / pool), ceil(W / pool))``.

    Why: a target's noise (Monte Carlo, sensor) is zero-mean in linear light, but the
    normalisation is concave, so a noisy pixel's normalised value is darker on average than its
    clean one, most where the noise is large against the signal (a blurred highlight's rim). A
    loss on normalised pixels then pays the lens to put less light there: a smaller blur. The
    block mean divides that bias by about ``pool ** 2`` (the noise's variance) and keeps what
    a blur's size changes. Computed in float64: decoding near the normalisation's highlight end
    loses float32's precision.
    """
    lin = normalization.decode(n.double())
    return normalization.encode(F.avg_pool2d(lin, pool, ceil_mode=True)).to(n.dtype)


def crop_loss_margin(crop: list[int] | None, max_coc_px: float, margin: int | str = "auto") -> int:
    """How far (px) the loss stays from a side where a training crop cuts its frame: ``margin``,
    ``"auto"`` being the largest CoC radius of the data (0 without crops). ``ValueError`` if that
    leaves a crop no pixel."""
    if not crop:
        return 0
    margin = math.ceil(max_coc_px / 2.0) if margin == "auto" else int(margin)
    if min(crop) <= 2 * margin:
        raise ValueError(f"data.crop = {list(crop)} px leaves no pixel for the loss: the loss stays "
                         f"{margin} px (data.crop_margin) from each side where a crop cuts its frame; "
                         f"use crops larger than {2 * margin} px")
    return margin


def loss_weights(cut: torch.Tensor, size: tuple[int, int], margin_px: int) -> torch.Tensor | None:
    """``(B, 1, H, W)``: 0 within ``margin_px`` of each side where a crop cuts through its frame
    (``cut`` ``(B, 4)``: top, bottom, left, right, as :func:`~neuralbokeh.data.dataset.cut_sides`),
    1 elsewhere; None when no crop of the batch cuts its frame. Light from beyond such a side
    reaches the target up to the largest CoC radius in, and the crop's input cannot show it: a
    loss there would teach the lens to make up light that is not in its input."""
    if margin_px <= 0 or not bool(cut.any()):
        return None
    h, w = size
    rows, cols = torch.arange(h, device=cut.device), torch.arange(w, device=cut.device)
    top, bottom, left, right = (cut[:, k, None] for k in range(4))
    keep_r = ~((top & (rows < margin_px)) | (bottom & (rows >= h - margin_px)))
    keep_c = ~((left & (cols < margin_px)) | (right & (cols >= w - margin_px)))
    return (keep_r[:, :, None] & keep_c[:, None, :]).to(torch.float32)[:, None]


def param_groups(model: torch.nn.Module, scaling: str, field_lr_scale: float = 1.0) -> list[dict[str, Any]]:
    """Adam parameter groups, each with an ``lr_scale``: the paper network's per-channel k x k
    kernels at ``1 / k^2`` with ``scaling = "fan_in"`` (see ``TrainSection.lr_kernel_scaling``),
    the lens network's field-dependent pupil corrections at ``field_lr_scale``, everything else at
    1; the network declares which is which (``parameter_roles``)."""
    groups: dict[float, list[torch.nn.Parameter]] = {}
    for role, params in model.parameter_roles().items():
        for p in params:
            scale = 1.0
            if role == "kernel" and scaling == "fan_in":
                scale = 1.0 / (p.shape[-1] * p.shape[-2])
            elif role == "field":
                scale = field_lr_scale
            groups.setdefault(scale, []).append(p)
    return [{"params": ps, "lr_scale": s} for s, ps in sorted(groups.items(), reverse=True)]


def _lr_factor(step: int, cfg: TrainConfig) -> float:
    """The schedule's factor on ``train.lr`` at ``step`` (0-based), a function of the step alone
    (a time limit does not anneal: measured worse, docs/benchmarks.md)."""
    t = cfg.train
    if step < t.warmup_steps:
        return (step + 1) / t.warmup_steps
    if t.lr_schedule == "constant":
        return 1.0
    progress = (step - t.warmup_steps) / max(1, t.steps - t.warmup_steps)
    return 0.1 + 0.9 * 0.5 * (1.0 + math.cos(math.pi * min(1.0, progress)))


def ema_weight(count: torch.Tensor, ema_steps: int) -> torch.Tensor:
    """The share of the newest weights in the moving average after ``count`` (a tensor) earlier
    updates: ``1 / (count + 1)`` (the plain mean of all steps so far) until that falls to
    ``1 / ema_steps``, then ``1 / ema_steps`` (an exponential average over about ``ema_steps``
    steps). The plain mean first keeps the initial weights from lingering in the average of a short run."""
    return (1.0 / (count + 1.0)).clamp(min=1.0 / ema_steps)


def averaged(model: torch.nn.Module, ema_steps: int) -> AveragedModel:
    """The moving average of ``model``'s weights (``train.ema_steps``; :func:`ema_weight`),
    updated by ``update_parameters(model)`` after each step; the averaged network is ``.module``."""
    def average(avg: torch.Tensor, new: torch.Tensor, count: torch.Tensor) -> torch.Tensor:
        return avg + (new - avg) * ema_weight(count, ema_steps).to(avg.dtype)

    ema = AveragedModel(model, avg_fn=average, use_buffers=True)
    for p in ema.parameters():
        p.requires_grad_(False)
    return ema


class Samples:
    """Dataset items as batched tensors, optionally cached in memory, optionally cut to random
    crops (``crop`` ``(height, width)`` px), each with its window on the sensor."""

    def __init__(self, ds: FocalStackDataset, cache: bool, crop: list[int] | None = None) -> None:
        self.ds, self.cache, self.store, self.crop = ds, cache, {}, crop or None
        self.aifs: dict[int, torch.Tensor] = {}  # by scene index

    def item(self, i: int) -> dict[str, Any]:
        if i in self.store:
            return self.store[i]
        it = self.ds[i]
        if self.cache:  # the slices of a scene share one all-in-focus image
            it["aif"] = self.aifs.setdefault(self.ds.items[i][0], it["aif"])
            self.store[i] = it
        return it

    def batch(self, indices: list[int], device: torch.device, seed: int = 0,
              ) -> tuple[torch.Tensor, torch.Tensor, list[str], torch.Tensor, torch.Tensor]:
        """``(x (B, 4, h, w), y (B, 3, h, w), names, windows (B, 4), cut (B, 4))``, ``cut``: the
        sides where a crop cuts through its frame (:func:`~neuralbokeh.data.dataset.cut_sides`);
        the crops' places are a function of ``seed`` (the step) alone, so a resumed run cuts the
        same crops."""
        g = torch.Generator().manual_seed(seed)
        xs, ys, windows, names, cuts = [], [], [], [], []
        for i in indices:
            if self.crop and not self.cache:  # read the crop's rows only
                it = self.ds.crop_item(i, self.crop, g)
            else:
                it = self.item(i)
                if self.crop:
                    it = random_crop(it, self.crop, g)
            xs.append(torch.cat([it["aif"], it["coc"]], 0))
            ys.append(it["defocus"])
            windows.append(it["window"])
            cuts.append(it["cut_sides"])
            names.append(f"{it['scene']}#{it['slice']}")
        return (torch.stack(xs).to(device), torch.stack(ys).to(device), names, torch.stack(windows).to(device),
                torch.stack(cuts).to(device))


def random_crop(item: dict[str, Any], size: list[int], generator: torch.Generator) -> dict[str, Any]:
    """A dataset item (whole scene, in memory) cut to a random ``size`` = ``(h, w)`` px crop, at
    the place :meth:`FocalStackDataset.crop_item` draws from the same generator state, with the
    crop's window on the sensor."""
    full = item["aif"].shape[-2:]
    r, c = random_crop_place(full, size, generator)
    (h, w), cut = size, (slice(None), slice(r, r + size[0]), slice(c, c + size[1]))
    window = SensorWindow(*(float(v) for v in item["window"])).crop((r, r + h), (c, c + w), *full)
    return {**item, "aif": item["aif"][cut], "coc": item["coc"][cut], "defocus": item["defocus"][cut],
            "window": torch.tensor([window.left, window.top, window.width, window.height], dtype=torch.float32),
            "cut_sides": cut_sides((r, r + h), (c, c + w), *full)}


def _metrics(pred: torch.Tensor, target: torch.Tensor) -> tuple[float, float]:
    a, b = (pred + 1) / 2, (target + 1) / 2
    return float(psnr(a, b, 1.0)), float(ssim(a, b, 11).mean())


def oracle_apertures(ds: FocalStackDataset) -> list[ApertureModel] | None:
    """Each held-out scene's declared aperture (``scene.json``), or None when any scene declares
    none (photographs, light fields: the lens is what is being learned, so there is no oracle)."""
    declared = [m["aperture"] for m in ds.metas]
    return None if any(a is None for a in declared) else [ApertureModel.from_dict(a) for a in declared]


@torch.no_grad()
def held_out_baselines(ds: FocalStackDataset, samples: Samples | None = None,
                       device: torch.device | None = None) -> dict[str, float]:
    """Mean PSNR/SSIM (``identity_*``, ``gaussian_*``, ``oracle_*``) of the baselines on a
    held-out split, in the training metric: the AIF unchanged, the CoC-driven Gaussian scatter and
    the scatter with each scene's own aperture (``scene.json``), all fed the held-out AIF + CoC.
    The ``oracle_*`` keys are left out when a scene declares no aperture (:func:`oracle_apertures`)."""
    samples = samples or Samples(ds, cache=False)
    device = device or torch.device("cpu")
    norm, scale = ds.normalization, ds.coc_scale_px
    gauss = ApertureModel(Gaussian(0.5))
    exact = oracle_apertures(ds)
    names = ("identity", "gaussian") + (("oracle",) if exact else ())
    sums = {f"{n}_{m}": 0.0 for n in names for m in ("psnr", "ssim")}
    for i in range(len(ds)):
        x, y, _, _, _ = samples.batch([i], device)
        linear, coc = norm.decode(x[:, :3].double()), x[:, 3:].double() * scale
        preds = {"identity": x[:, :3], "gaussian": norm.encode(scatter_defocus(linear, coc, gauss)).float()}
        if exact:
            preds["oracle"] = norm.encode(scatter_defocus(linear, coc, exact[ds.items[i][0]])).float()
        for name, pred in preds.items():
            p, s = _metrics(pred, y)
            sums[f"{name}_psnr"] += p
            sums[f"{name}_ssim"] += s
    n = max(len(ds), 1)
    return {k: v / n for k, v in sums.items()}


@torch.no_grad()
def held_out_metrics(model: torch.nn.Module, samples: Samples, device: torch.device,
                     baselines: dict | None = None) -> dict[str, float]:
    """Mean PSNR/SSIM (``eval_*``) of the model over held-out samples, with the baselines of
    :func:`held_out_baselines` (computed when not given)."""
    model.eval()
    sums = {"eval_psnr": 0.0, "eval_ssim": 0.0}
    for i in range(len(samples.ds)):  # whole frames, each with its own sensor window
        x, y, _, window, _ = samples.batch([i], device)
        p, s = _metrics(run_model(model, x, window), y)
        sums["eval_psnr"] += p
        sums["eval_ssim"] += s
    out = {k: v / max(len(samples.ds), 1) for k, v in sums.items()}
    out.update(baselines if baselines is not None else held_out_baselines(samples.ds, samples, device))
    model.train()
    return out


def _digest(model: torch.nn.Module) -> str:
    import hashlib

    h = hashlib.sha256()
    for name, t in sorted(model.state_dict().items()):
        h.update(name.encode())
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


@contextlib.contextmanager
def torch_threads(threads: int) -> Iterator[None]:
    """Run the block with ``threads`` intra-op threads (0: unchanged), then restore the previous
    count: library code never leaves a process-wide setting changed behind it."""
    before = torch.get_num_threads()
    if threads:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def train(
    cfg: TrainConfig,
    resume: str | os.PathLike | None = None,
    progress: bool = True,
    stop_at: int | None = None,
    time_limit_s: float | None = None,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Train from a config with ``cfg.train.threads`` threads; returns a summary (final metrics,
    checkpoint path, skipped steps).

    The dataset is checked whole first (:func:`~neuralbokeh.data.check.require_sound`). A run
    that dies (an exception, Ctrl-C, too many non-finite steps) writes a checkpoint of its last
    completed step before the error propagates, so ``resume`` continues from there.

    Args:
        cfg: the training configuration.
        resume: a checkpoint written by this function to continue from (same config).
        progress: show a tqdm progress bar (rank 0).
        stop_at: stop (with a checkpoint) after this step, e.g. to fit a job's time limit;
            ``resume`` continues exactly as if the run had not stopped.
        time_limit_s: stop (with a final evaluation and checkpoint) at the first step that ends
            after this many seconds of training (budgets such as "30 minutes per variant").
        overwrite: start afresh in an ``out_dir`` that already holds a run (otherwise refused).

    Raises:
        ValueError: a dataset that fails its check, a dataset too small for the batch, a
            checkpoint from another model config, an ``out_dir`` holding another run.
        RuntimeError: ``max_nonfinite`` non-finite steps in a row.
    """
    with torch_threads(cfg.train.threads):
        proc = _Process.start()
        if cfg.train.batch_size % proc.world:
            raise ValueError(f"train.batch_size ({cfg.train.batch_size}) must be divisible by the number of processes "
                             f"({proc.world})")
        _check_out_dir(Path(cfg.train.out_dir), resume, overwrite)
        require_sound(cfg.data.roots)
        run = _Run.start(cfg, proc, resume)
        summary = run.loop(progress, stop_at, time_limit_s)
        del run  # its DDP wrapper before the process group goes (see _Process.finish)
        proc.finish()
        return summary


def _check_out_dir(out_dir: Path, resume: str | os.PathLike | None, overwrite: bool) -> None:
    """Refuse to start over, or to resume into, a folder that holds another run."""
    held = [n for n in ("checkpoint.pt", "log.csv") if (out_dir / n).exists()]
    if held and not resume and not overwrite:
        raise ValueError(f"train.out_dir {out_dir} already holds a run ({', '.join(held)}): continue it with --resume "
                         f"{out_dir / 'checkpoint.pt'}, choose another train.out_dir, or start afresh with --overwrite")
    if held and resume and Path(resume).resolve().parent != out_dir.resolve() and not overwrite:
        raise ValueError(f"--resume {resume} is another run's checkpoint, and train.out_dir {out_dir} holds a run of its "
                         f"own ({', '.join(held)}): set train.out_dir={Path(resume).parent} to continue that run there, "
                         "choose an empty train.out_dir, or replace this one with --overwrite")


class _Run:
    """One training run's state: data, network, optimiser, and where the run stands (step,
    skipped steps)."""

    def __init__(self, cfg: TrainConfig, proc: _Process) -> None:
        self.cfg, self.proc, self.lead = cfg, proc, proc.rank == 0
        self.out_dir = Path(cfg.train.out_dir)
        norm = Normalization(cfg.data.normalization_scale)
        split = {"test_fraction": cfg.data.test_fraction, "split_seed": cfg.data.split_seed, "normalization": norm}
        held_out = cfg.data.test_fraction > 0
        self.train_ds = FocalStackDataset(cfg.data.roots, "train" if held_out else "all", **split)
        self.test_ds = FocalStackDataset(cfg.data.roots, "test", **split) if held_out else None
        self.contract = self.train_ds.contract(cfg.data.crop or None)
        self.mcfg = cfg.model.resolved(self.train_ds.max_coc_px)
        torch.manual_seed(cfg.train.seed)
        self.model = build_model(self.mcfg, self.contract).to(proc.device)
        t = cfg.train
        self.optimizer = torch.optim.Adam(param_groups(self.model, t.lr_kernel_scaling, t.field_lr_scale), lr=t.lr)
        self.ema = averaged(self.model, t.ema_steps) if t.ema_steps else None
        self.step, self.skipped, self.t0 = 0, 0, time.perf_counter()
        self.per_rank = t.batch_size // proc.world
        self.sampler = DistributedSampler(self.train_ds, num_replicas=proc.world, rank=proc.rank, shuffle=True, seed=t.seed,
                                          drop_last=True)
        self.steps_per_epoch = len(self.sampler) // self.per_rank
        if self.steps_per_epoch < 1:
            raise ValueError(f"{len(self.train_ds)} training samples are too few for batch_size {t.batch_size}")
        self.samples = Samples(self.train_ds, cfg.data.cache, cfg.data.crop)
        self.margin_px = crop_loss_margin(cfg.data.crop, self.train_ds.max_coc_px, cfg.data.crop_margin)
        self.test_samples = Samples(self.test_ds, cfg.data.cache) if self.test_ds else None
        self._order: tuple[int, list[int]] = (-1, [])

    @classmethod
    def start(cls, cfg: TrainConfig, proc: _Process, resume: str | os.PathLike | None) -> _Run:
        """A new run, or one continued from the checkpoint ``resume`` (the same model config)."""
        run = cls(cfg, proc)
        if resume:
            ck = load_checkpoint(resume, map_location=proc.device)
            if ModelConfig.from_dict(ck["model_config"]).to_dict() != run.mcfg.to_dict():
                raise ValueError(f"checkpoint {resume} is for model {ck['model_config']}, this config builds "
                                 f"{run.mcfg.to_dict()}")
            # with train.ema_steps the checkpoint's model is the average, the trained weights beside it
            run.model.load_state_dict(ck.get("trained_state", ck["model_state"]))
            if run.ema is not None:
                run.ema.module.load_state_dict(ck["model_state"])
                run.ema.n_averaged.fill_(ck["step"])
            run.optimizer.load_state_dict(ck["optimizer_state"])
            run.step, run.skipped = ck["step"], ck["skipped_steps"]
            torch.set_rng_state(ck["rng_state"])
        run.net = DistributedDataParallel(run.model) if proc.distributed else run.model
        run.run_log = _RunLog(run.out_dir, cfg, append=bool(resume)) if run.lead else None
        if run.lead:
            log.info("model %s: N=%d over the training range, %d parameters", run.mcfg.to_dict(), run.mcfg.blocks,
                     sum(p.numel() for p in run.model.parameters()))
        return run

    @property
    def result(self) -> torch.nn.Module:
        """The network this run evaluates, checkpoints as its model and a user exports: the moving
        average of the weights with ``train.ema_steps``, else the trained network."""
        return self.model if self.ema is None else self.ema.module

    def checkpoint(self, metrics: dict) -> Path:
        trained = {} if self.ema is None else {"trained_state": self.model.state_dict()}
        return save_checkpoint(self.out_dir / "checkpoint.pt", {
            "model_config": self.mcfg.to_dict(), "contract": self.contract.to_dict(), "model_state": self.result.state_dict(),
            **trained,
            "optimizer_state": self.optimizer.state_dict(),
            "step": self.step, "skipped_steps": self.skipped, "rng_state": torch.get_rng_state(),
            "train_config": self.cfg.to_dict(), "metrics": metrics,
        })

    def batch(self) -> tuple[torch.Tensor, torch.Tensor, list[str], torch.Tensor, torch.Tensor | None]:
        """This rank's batch of the current step: ``(x, y, names, window, loss weights)``."""
        epoch, pos = divmod(self.step, self.steps_per_epoch)
        if epoch != self._order[0]:
            self.sampler.set_epoch(epoch)
            self._order = (epoch, list(self.sampler))
        t = self.cfg.train
        x, y, names, window, cut = self.samples.batch(self._order[1][pos * self.per_rank : (pos + 1) * self.per_rank],
                                                      self.proc.device, seed=t.seed * 1_000_003 + self.step * 101 + self.proc.rank)
        return x, y, names, window, loss_weights(cut, tuple(y.shape[-2:]), self.margin_px)

    def loop(self, progress: bool, stop_at: int | None, time_limit_s: float | None) -> dict[str, Any]:
        """Train to ``train.steps`` (or ``stop_at``, or the time limit); returns the summary."""
        t, proc = self.cfg.train, self.proc
        baselines, metrics, consecutive, start = None, {}, 0, self.step
        self.t0 = time.perf_counter()
        bar = tqdm(total=t.steps, initial=start, desc="train", unit="step", disable=not (progress and self.lead))
        last = t.steps if stop_at is None else min(t.steps, stop_at)
        try:
            while self.step < last:
                x, y, names, window, weights = self.batch()
                loss, finite = _step(self.net, self.model, self.optimizer, x, y, window, weights, self.cfg, self.step, proc,
                                     self.train_ds.normalization)
                self.skipped += not finite
                if self.ema is not None:  # every step, skipped ones too: its count stays the step's
                    self.ema.update_parameters(self.model)
                consecutive = 0 if finite else consecutive + 1
                if not finite:
                    log.warning("step %d: non-finite loss or gradient, step skipped (scenes %s)", self.step + 1, names)
                if consecutive >= t.max_nonfinite:
                    raise RuntimeError(f"{consecutive} non-finite steps in a row, the last at step {self.step + 1} (batch "
                                       f"scenes on rank {proc.rank}: {', '.join(names)}); lower train.lr or check the data")
                row = {"step": self.step + 1, "loss": loss, "lr": t.lr * _lr_factor(self.step, self.cfg), "skipped": self.skipped}
                self.step += 1
                if time_limit_s is not None and proc.elapsed(self.t0) > time_limit_s:  # rank 0's clock: all ranks stop alike
                    last = self.step
                if self.step % t.eval_every == 0 or self.step == last:
                    if self.lead and self.test_samples:
                        metrics = held_out_metrics(self.result, self.test_samples, proc.device, baselines)
                        baselines = {k: v for k, v in metrics.items() if not k.startswith("eval_")}
                        row.update(metrics)
                        bar.set_postfix(psnr=f"{metrics['eval_psnr']:.2f}", gauss=f"{metrics['gaussian_psnr']:.2f}")
                    proc.barrier()
                if self.lead:
                    self.run_log.write({**row, "elapsed_s": round(time.perf_counter() - self.t0, 3)})
                    if self.step % t.checkpoint_every == 0 or self.step == last:
                        self.checkpoint(metrics)
                bar.update()
        except BaseException:  # an exception, Ctrl-C, the non-finite abort: keep what was learned
            if self.lead and self.step > start:
                path = self.checkpoint(metrics)
                log.error("training stopped at step %d; its checkpoint is %s (continue with --resume)", self.step, path)
            raise
        bar.close()
        return self.summary(metrics)

    def summary(self, metrics: dict) -> dict[str, Any]:
        summary = {
            "checkpoint": str((self.out_dir / "checkpoint.pt").resolve()), "steps": self.step, "skipped_steps": self.skipped,
            "metrics": metrics, "model": self.mcfg.to_dict(), "world_size": self.proc.world,
            "rank_weight_digests": self.proc.gather(_digest(self.model)),
            "train_samples": len(self.train_ds), "test_samples": len(self.test_ds) if self.test_ds else 0,
            "seconds": round(time.perf_counter() - self.t0, 1),
        }
        if self.lead:
            self.run_log.close()
            write_json(self.out_dir / "summary.json", summary)
        return summary


def _step(net: torch.nn.Module, model: torch.nn.Module, optimizer: torch.optim.Optimizer, x: torch.Tensor, y: torch.Tensor,
          window: torch.Tensor, weights: torch.Tensor | None, cfg: TrainConfig, step: int, proc: _Process,
          normalization: Normalization) -> tuple[float, bool]:
    """One optimiser step (skipped, on every rank, when any rank's loss or gradient is not
    finite); returns ``(loss, finite)``."""
    t = cfg.train
    for group in optimizer.param_groups:  # the schedule is a function of the step alone
        group["lr"] = group["lr_scale"] * t.lr * _lr_factor(step, cfg)
    optimizer.zero_grad(set_to_none=True)
    loss = compute_loss(net, x, y, t.loss, window, weights, ssim_weight=t.ssim_weight, pool=t.loss_pool,
                        normalization=normalization)
    if t.pupil_tv > 0 or t.pupil_chroma > 0:
        nodes = model.node_transmissions()  # once for both priors
        if t.pupil_tv > 0:
            loss = loss + t.pupil_tv * model.pupil_roughness(nodes)
        if t.pupil_chroma > 0:
            loss = loss + t.pupil_chroma * model.pupil_chroma(nodes)
    if t.pupil_field_spread > 0:
        loss = loss + t.pupil_field_spread * model.pupil_field_spread()
    loss.backward()
    finite = torch.tensor(
        [float(torch.isfinite(loss)) * float(all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None))],
        device=proc.device,
    )
    if proc.distributed:
        dist.all_reduce(finite, op=dist.ReduceOp.MIN)
    if finite.item() < 1.0:
        optimizer.zero_grad(set_to_none=True)
        return loss.item(), False
    if t.grad_clip > 0:
        torch.nn.utils.clip_grad_norm_(model.parameters(), t.grad_clip)
    optimizer.step()
    return loss.item(), True


@dataclass
class _Process:
    """This process's place in a (possibly ``torchrun``) run: gloo on CPU, nccl on GPU."""

    world: int
    rank: int
    device: torch.device

    @property
    def distributed(self) -> bool:
        return self.world > 1

    @classmethod
    def start(cls) -> _Process:
        world = int(os.environ.get("WORLD_SIZE", "1"))
        if world > 1 and not dist.is_initialized():
            dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
        local_rank = int(os.environ.get("LOCAL_RANK", "0"))
        device = torch.device(f"cuda:{local_rank}") if torch.cuda.is_available() else torch.device("cpu")
        return cls(world, dist.get_rank() if world > 1 else 0, device)

    def barrier(self) -> None:
        if self.distributed:
            dist.barrier()

    def elapsed(self, t0: float) -> float:
        """Rank 0's seconds since ``t0`` (all ranks must agree on when to stop and on the rate)."""
        elapsed = torch.tensor([time.perf_counter() - t0], dtype=torch.float64)
        if self.distributed:
            dist.broadcast(elapsed, 0)
        return float(elapsed)

    def gather(self, value: Any) -> list[Any]:
        """``value`` of every rank, in rank order."""
        if not self.distributed:
            return [value]
        gathered: list[Any] = [None] * self.world
        dist.all_gather_object(gathered, value)
        return gathered

    def finish(self) -> None:
        """Leave the process group. The caller drops its DDP wrapper first: DDP's reducer keeps
        the last gloo work objects, and freed after ``destroy_process_group`` (in interpreter
        teardown) gloo aborted about one run in 20 ("terminate called without an active
        exception")."""
        if self.distributed:
            gc.collect()
            dist.barrier()
            dist.destroy_process_group()


class _RunLog:
    """Rank 0's record of a run in ``out_dir``: ``config.json``, the ``log.csv`` curve (a row per
    step, flushed as written; appended to on resume) and TensorBoard when installed."""

    def __init__(self, out_dir: Path, cfg: TrainConfig, append: bool) -> None:
        out_dir.mkdir(parents=True, exist_ok=True)
        write_json(out_dir / "config.json", cfg.to_dict())
        new_log = not (append and (out_dir / "log.csv").exists())
        self.csv_file = open(out_dir / "log.csv", "w" if new_log else "a", newline="")
        self.writer = csv.DictWriter(self.csv_file, CSV_FIELDS)
        if new_log:
            self.writer.writeheader()
        try:
            from torch.utils.tensorboard import SummaryWriter

            self.board = SummaryWriter(str(out_dir / "tensorboard"))
        except ImportError:
            self.board = None
            log.warning("TensorBoard is not installed: the curves go to %s only (pip install -e '.[tensorboard]' "
                        "for %s)", out_dir / "log.csv", out_dir / "tensorboard")

    def write(self, row: dict[str, Any]) -> None:
        self.writer.writerow(row)
        self.csv_file.flush()
        if self.board:
            for k, v in row.items():
                if k != "step":
                    self.board.add_scalar(k, v, row["step"])

    def close(self) -> None:
        self.csv_file.close()
        if self.board:
            self.board.close()

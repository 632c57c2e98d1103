"""Error against run time for every method on a held-out set.

    python -m neuralbokeh.evaluation --data DIR --models a.onnx b.pt --baselines all --out report/

Methods: trained models (``.onnx`` through ``neuralbokeh.runtime``, ``.pt`` checkpoints through
PyTorch) and the baselines of ``neuralbokeh.render.baselines``: ``identity`` (the AIF returned),
``gaussian`` (CoC-driven Gaussian), ``gather`` (naive gather with the data's aperture),
``raytrace`` (Yang et al.'s depth-aware pseudo ray tracing with the data's aperture, 8x8 rays),
``buckets`` (the light-field patent's near/mid/far gather with sum-to-saturation), ``pyramid`` and
``tensor`` (Kosloff and Barsky's Gaussian pyramid spreading and tensor filter), ``lenstrace``
(Lee, Eisemann and Seidel's layered image-space ray tracing; no spherical aberration, since the
data has none) and ``scatter`` (the reference renderer with the data's aperture, fed the same AIF +
CoC as every other method: the data's lens without learning. It is not a bound: it cannot see what
foregrounds hide in the AIF, and on data rendered layer by layer, identity or a learned model can
beat it on some metrics).

Per method and held-out sample: the metrics of ``neuralbokeh.evaluation.metrics`` (PSNR/SSIM in linear
light and tone-mapped sRGB, HDR-FLIP) and the wall time per megapixel, the median of
``--repeats`` runs in this process with ``--threads`` threads. Writes ``report.json``,
``report.md``, ``error_vs_runtime.png`` (log time axis, Pareto front marked) and image grids
(AIF | ground truth | each method, error maps below) for the median and the worst scene, and
the first method against each other one scene by scene (``metrics.paired_by_scene``).
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from ..core.apertures import ApertureModel
from ..core.cli import HelpFormatter
from ..core.contract import Contract
from ..core.io import atomic_write, prepare_output, write_json, write_text
from ..data.check import require_sound
from ..data.dataset import FocalStackDataset
from ..render import scatter_defocus
from ..render.baselines import gather_defocus, gaussian_defocus, pseudo_ray_trace
from ..render.buckets import bucket_gather
from ..render.lens_trace import lens_ray_trace
from ..render.pyramid import pyramid_spread, tensor_filter
from .metrics import image_metrics, paired_by_scene, pareto_front, tonemap_srgb

log = logging.getLogger(__name__)
BASELINES = ("identity", "gaussian", "gather", "raytrace", "buckets", "pyramid", "tensor", "lenstrace", "scatter")
Method = Callable[[np.ndarray, np.ndarray], np.ndarray]  # (aif (H, W, 3), coc px (H, W)) -> (H, W, 3)


def _torch_method(fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]) -> Method:
    def run(aif: np.ndarray, coc: np.ndarray) -> np.ndarray:
        x = torch.from_numpy(aif.transpose(2, 0, 1).astype(np.float64))[None]
        c = torch.from_numpy(coc.astype(np.float64))[None, None]
        return fn(x, c)[0].numpy().transpose(1, 2, 0)
    return run


def baseline_methods(names: list[str], aperture: ApertureModel | None) -> dict[str, Method]:
    """The named baselines; those with an aperture shape use ``aperture`` (a disk when unknown)."""
    ap = aperture or ApertureModel()
    table: dict[str, Method] = {
        "identity": lambda aif, coc: aif.copy(),
        "gaussian": _torch_method(gaussian_defocus),
        "gather": _torch_method(lambda x, c: gather_defocus(x, c, ap)),
        # 8x8 rays (~50 in a 7-gon) and 1 px CoC steps: the paper's one ray per mask pixel costs
        # minutes per image at 256 px and max CoC 28 on 2 cores
        "raytrace": _torch_method(lambda x, c: pseudo_ray_trace(x, c, ap, grid=8, coc_step=1.0)),
        "buckets": _torch_method(lambda x, c: bucket_gather(x, c, ap)),
        "pyramid": _torch_method(pyramid_spread),
        "tensor": _torch_method(tensor_filter),
        "lenstrace": _torch_method(lambda x, c: lens_ray_trace(x, c, ap, grid=8, steps=16)),
        "scatter": _torch_method(lambda x, c: scatter_defocus(x, c, ap)),
    }
    unknown = [n for n in names if n not in table]
    if unknown:
        raise ValueError(f"unknown baselines {unknown}; expected some of {list(table)} or 'all'")
    return {n: table[n] for n in names}


@dataclass
class LoadedModel:
    """A trained model ready to run: ``run`` (a :data:`Method`), the image ``size`` ``(H, W)`` it
    was built for and its training ``split`` (``{"test_fraction", "split_seed"}``, or None when
    the file does not record it)."""

    run: Method
    size: tuple[int, int]
    split: dict[str, Any] | None


def model_labels(paths: list[Path]) -> list[str]:
    """Each model's row name: its file name, with as many parent folders as it takes to tell
    apart models that share one (``a/run/checkpoint.pt`` and ``b/run/checkpoint.pt`` ->
    ``a/run/checkpoint.pt``, ``b/run/checkpoint.pt``), so no row replaces another."""
    if len({p.resolve() for p in paths}) < len(paths):
        raise ValueError(f"--models names one file twice: {[str(p) for p in paths]}")
    parts = [p.resolve().parts for p in paths]
    depth = [1] * len(paths)
    while True:
        labels = ["/".join(q[-d:]) for q, d in zip(parts, depth)]
        clash = [i for i, label in enumerate(labels) if labels.count(label) > 1]
        if not clash:
            return labels
        for i in clash:
            depth[i] += 1


def load_model_method(path: Path, threads: int) -> LoadedModel:
    """A trained model: ``.onnx`` (onnxruntime, in-focus tiles and unused bands skipped; its
    metadata read once by the runtime) or a ``.pt`` checkpoint (read once)."""
    if path.suffix == ".onnx":
        from ..runtime.onnx_model import OnnxBokeh

        m = OnnxBokeh(path, threads=threads)
        return LoadedModel(lambda aif, coc: m.render_coc(aif, coc), (m.height, m.width), m.meta.get("data_split"))
    from ..checkpoint import load_model

    model, ckpt = load_model(path)
    contract: Contract = model.contract
    data = ckpt.get("train_config", {}).get("data")

    def network(x: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return model(torch.from_numpy(x).float()).double().numpy()

    def run(aif: np.ndarray, coc: np.ndarray) -> np.ndarray:
        return contract.apply(network, aif.astype(np.float64).transpose(2, 0, 1)[None], coc[None, None])[0].transpose(1, 2, 0)
    split = {k: data[k] for k in ("test_fraction", "split_seed")} if data else None
    return LoadedModel(run, contract.size, split)


def model_method(path: Path, threads: int) -> Method:
    """:func:`load_model_method`'s runnable alone."""
    return load_model_method(path, threads).run


def split_of_models(models: list[LoadedModel], test_fraction: float | None, split_seed: int | None) -> tuple[float, int]:
    """The scene split to score: the one given, else the training run's (the first model that
    records it: ``train_config`` of a checkpoint, ``data_split`` of an export), so that training
    scenes are not scored as held out by accident; else (0.2, 0). A given value that differs from
    the model's training split is logged as a warning."""
    recorded = next(((float(m.split["test_fraction"]), int(m.split["split_seed"])) for m in models if m.split), None)
    fraction = test_fraction if test_fraction is not None else recorded[0] if recorded else 0.2
    seed = split_seed if split_seed is not None else recorded[1] if recorded else 0
    if recorded and (fraction, seed) != recorded:
        log.warning("scoring with test_fraction %s, split_seed %s; the model was trained with %s, %s: some scored "
                    "scenes may be training scenes", fraction, seed, *recorded)
    return fraction, seed


def _median_ms(fn: Callable[[], Any], repeats: int) -> tuple[float, Any]:
    times, out = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(1000.0 * (time.perf_counter() - t))
    return statistics.median(times), out


def evaluate_methods(methods: dict[str, Method], samples: list[dict], repeats: int = 3, progress: bool = False) -> dict[str, Any]:
    """Metrics and time per method; ``samples`` are linear items of a ``FocalStackDataset``
    (``normalize=False``). Returns ``{"methods": {name: {...}}, "predictions": {name: [...]}}``.
    ``progress``: a tqdm bar over (method, sample) runs (the CLI's)."""
    results, predictions = {}, {}
    bar = tqdm(total=len(methods) * len(samples), desc="evaluate", unit="run", disable=not progress)
    for name, fn in methods.items():
        per, preds = [], []
        bar.set_postfix(method=name)
        for it in samples:
            aif = it["aif"].numpy().transpose(1, 2, 0).astype(np.float64)
            coc = it["coc"][0].numpy().astype(np.float64)
            gt = it["defocus"].numpy().transpose(1, 2, 0).astype(np.float64)
            ms, pred = _median_ms(lambda: fn(aif, coc), repeats)
            pred = np.asarray(pred, dtype=np.float64)
            # the normalisation admits values down to -offset (a small negative); metrics and FLIP
            # take light >= 0, so predictions are measured with negatives at 0 and the minimum kept
            m = image_metrics(np.maximum(pred, 0.0), gt)
            m["min_value"] = float(pred.min())
            m["ms_per_mp"] = ms / (aif.shape[0] * aif.shape[1] / 1e6)
            m["sample"] = f"{it['scene']}#{it['slice']}"
            per.append(m)
            preds.append(pred)
            bar.update()
        keys = [k for k in per[0] if k not in ("sample", "min_value")]
        summary = {k: float(np.mean([p[k] for p in per])) for k in keys}
        summary["ms_per_mp"] = float(np.median([p["ms_per_mp"] for p in per]))
        results[name] = {**summary, "per_sample": per}
        predictions[name] = preds
        log.info("%s: %s", name, {k: round(v, 4) for k, v in summary.items()})
    bar.close()
    return {"methods": results, "predictions": predictions}


def write_report(out: Path, result: dict[str, Any], samples: list[dict], info: dict[str, Any]) -> list[Path]:
    """report.json, report.md, error_vs_runtime.png and the two image grids; returns the paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    methods = result["methods"]
    names = list(methods)
    by_scene_lines, by_scene = scene_comparison(methods)
    written = [write_json(out / "report.json", {"info": info, "methods": methods, "by_scene": by_scene})]
    cols = ["psnr_linear", "ssim_linear", "psnr_srgb", "ssim_srgb", "flip_hdr", "ms_per_mp"]
    what = {"test": "held-out", "train": "training", "all": "all"}.get(info.get("split", "test"), "")
    lines = [f"# Evaluation on {info['samples']} {what} samples ({info['data']})", "",
             f"Threads: {info['threads']}; time: median of {info['repeats']} runs per sample, median over samples.", "",
             *([] if info.get("aperture") else ["The data declares no single aperture (photographs, light fields): the baselines "
                                                "that need an aperture shape use a disk, so none of them is an oracle.", ""]),
             "| method | PSNR lin dB | SSIM lin | PSNR sRGB dB | SSIM sRGB | FLIP | ms/MP |", "|---|---|---|---|---|---|---|"]
    for n in names:
        m = methods[n]
        lines.append(f"| {n} | " + " | ".join(f"{m[c]:.4f}" if "ssim" in c or "flip" in c else f"{m[c]:.2f}" for c in cols) + " |")
    write_text(out / "report.md", "\n".join(lines + by_scene_lines) + "\n")
    written.append(out / "report.md")

    points = [(max(methods[n]["ms_per_mp"], 1e-3), methods[n]["flip_hdr"]) for n in names]
    front = set(pareto_front(points))
    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    markers = "osD^v<>ph*"
    for i, (n, (t, e)) in enumerate(zip(names, points)):  # named in the legend: labels never overlap
        color = plt.get_cmap("tab10")(i % 10)
        ax.scatter([t], [e], marker=markers[i % len(markers)], s=50, label=n + (" (Pareto)" if i in front else ""),
                   facecolors=color if i in front else "none", edgecolors=color)
    fr = sorted(points[i] for i in front)
    ax.plot([p[0] for p in fr], [p[1] for p in fr], "--", lw=1, color="grey", label="Pareto front")
    ax.set_xscale("log")
    ax.set_xlabel("wall time per megapixel (ms, log)")
    ax.set_ylabel("mean HDR-FLIP (lower is better)")
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.02, 0.5), frameon=False)
    fig.tight_layout()
    with atomic_write(out / "error_vs_runtime.png") as tmp:
        fig.savefig(tmp, dpi=120, bbox_inches="tight")
    plt.close(fig)
    written.append(out / "error_vs_runtime.png")

    ref = names[0]
    order = np.argsort([p["flip_hdr"] for p in methods[ref]["per_sample"]])
    for label, idx in (("median", int(order[len(order) // 2])), ("worst", int(order[-1]))):
        path = _grid(plt, out, label, ref, samples[idx], names, result, idx)
        written.append(path)
    return written


SCENE_KEYS = ("psnr_linear", "psnr_srgb", "flip_hdr")


def scene_comparison(methods: dict[str, Any]) -> tuple[list[str], dict[str, Any]]:
    """The first method against each other one, scene by scene: report.md lines and their figures.

    Means over a few scenes hide that one scene can carry them; a reader needs how many scenes
    each method wins and how wide the mean's interval is (``metrics.paired_by_scene``).
    """
    names = list(methods)
    ref = names[0]
    figures = {n: {k: paired_by_scene(methods[ref]["per_sample"], methods[n]["per_sample"], k) for k in SCENE_KEYS}
               for n in names[1:]}
    if not figures:
        return [], {}
    n_scenes = next(iter(figures.values()))[SCENE_KEYS[0]]["scenes"]
    lines = ["", f"## {ref} against each method, scene by scene ({n_scenes} scenes)", "",
             f"Per cell: scenes where {ref} is better / median and mean of ({ref} - method) over the scenes (a scene: "
             "the mean of its samples) [95 % bootstrap interval of the mean, scenes resampled].", "",
             "| method | PSNR lin dB | PSNR sRGB dB | FLIP |", "|---|---|---|---|"]
    for n, row in figures.items():
        cells = []
        for k in SCENE_KEYS:
            f, fmt = row[k], "+.4f" if k == "flip_hdr" else "+.2f"
            cells.append(f"{f['ahead']}/{f['scenes']}, {f['median']:{fmt}}, {f['mean']:{fmt}} "
                         f"[{f['ci95'][0]:{fmt}}, {f['ci95'][1]:{fmt}}]")
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    return lines, {"reference": ref, "methods": figures}


ERROR_GAIN = 4.0  # error maps show ERROR_GAIN x |sRGB difference|: white = a difference of 1 / ERROR_GAIN


def _grid(plt: Any, out: Path, label: str, ref: str, it: dict, names: list[str], result: dict[str, Any], idx: int) -> Path:
    """One titled image grid: AIF | ground truth | each method (PSNR, FLIP) over the error maps."""
    aif = it["aif"].numpy().transpose(1, 2, 0)
    gt = it["defocus"].numpy().transpose(1, 2, 0)
    cols = ["all-in-focus input", "ground truth"] + names
    images = [aif, gt] + [np.maximum(result["predictions"][n][idx], 0.0) for n in names]
    h, w = aif.shape[:2]
    fig, axes = plt.subplots(2, len(cols), figsize=(1.9 * len(cols), 1.9 * 2 * h / w + 0.9), squeeze=False)
    for j, (title, img) in enumerate(zip(cols, images)):
        top, bottom = axes[0, j], axes[1, j]
        top.imshow(np.clip(tonemap_srgb(img), 0, 1))
        if j >= 2:
            m = result["methods"][title]["per_sample"][idx]
            title = f"{title}\nPSNR {m['psnr_srgb']:.2f}  FLIP {m['flip_hdr']:.3f}"
            err = np.clip(ERROR_GAIN * np.abs(tonemap_srgb(img) - tonemap_srgb(gt)), 0, 1)
            bottom.imshow(err)
        else:
            bottom.axis("off")
        top.set_title(title, fontsize=7)
        for a in (top, bottom):
            a.set_xticks([])
            a.set_yticks([])
    axes[0, 0].set_ylabel("tone-mapped sRGB", fontsize=7)
    axes[1, min(2, len(cols) - 1)].set_ylabel(f"|error| x {ERROR_GAIN:g}\n(white = {1 / ERROR_GAIN:g} sRGB)", fontsize=7)
    fig.suptitle(f"{label} sample by {ref}'s HDR-FLIP: {it['scene']} slice {it['slice']} "
                 "(PSNR: tone-mapped sRGB, dB; FLIP: HDR-FLIP)", fontsize=8)
    fig.tight_layout()
    path = out / f"grid_{label}.png"
    with atomic_write(path) as tmp:
        fig.savefig(tmp, dpi=130)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m neuralbokeh.evaluation", description=__doc__,
                                formatter_class=HelpFormatter)
    p.add_argument("--data", type=Path, required=True, help="dataset folder (checked whole before anything runs)")
    p.add_argument("--models", type=Path, nargs="*", default=[], help=".onnx files or .pt checkpoints")
    p.add_argument("--baselines", default="all", help="'all', 'none' or a comma list of " + ", ".join(BASELINES))
    p.add_argument("--out", type=Path, required=True, help="report folder (report.json, report.md, plots, image grids)")
    p.add_argument("--overwrite", action="store_true", help="replace a report already in --out")
    p.add_argument("--split", choices=("test", "train", "all"), default="test",
                   help="which scenes to score: the held-out ones, the training ones or the whole dataset")
    p.add_argument("--test-fraction", type=float, default=None,
                   help="share of the scenes held out (default: the training run's, from the first model that records "
                        "it, else 0.2)")
    p.add_argument("--split-seed", type=int, default=None, help="seed of the scene split (default: the training run's, else 0)")
    p.add_argument("--samples", type=int, default=0, help="evaluate the first N samples of the split (0: all)")
    p.add_argument("--repeats", type=int, default=3, help="timed runs per method and sample (median)")
    p.add_argument("--threads", type=int, default=2, help="torch and onnxruntime threads")
    p.add_argument("-v", "--verbose", action="store_true", help="tracebacks with errors")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stdout)
    torch.set_num_threads(args.threads)
    try:
        prepare_output(args.out / "report.json", args.overwrite)  # before the scoring, which can take minutes
        require_sound(args.data)
        loaded = {label: load_model_method(m, args.threads) for label, m in zip(model_labels(args.models), args.models)}
        test_fraction, split_seed = split_of_models(list(loaded.values()), args.test_fraction, args.split_seed)
        ds = FocalStackDataset(args.data, args.split, test_fraction if args.split != "all" else 0.0, split_seed, normalize=False)
        if len(ds) == 0:
            raise ValueError(f"{args.data}: no samples in split {args.split!r} with test_fraction {test_fraction}")
        n = len(ds) if args.samples <= 0 else min(args.samples, len(ds))
        samples = [ds[i] for i in range(n)]
        apertures = {json.dumps(m["aperture"], sort_keys=True) for m in ds.metas}
        aperture = ApertureModel.from_dict(ds.metas[0]["aperture"]) if len(apertures) == 1 and ds.metas[0]["aperture"] else None
        names = [] if args.baselines == "none" else list(BASELINES) if args.baselines == "all" else args.baselines.split(",")
        size = tuple(samples[0]["aif"].shape[-2:])
        for name, m in loaded.items():  # refused before any work
            if m.size != size:
                raise ValueError(f"{name} is for {m.size[1]}x{m.size[0]} images, the data is {size[1]}x{size[0]}")
        methods = {name: m.run for name, m in loaded.items()}
        methods.update(baseline_methods(names, aperture))
        if not methods:
            raise ValueError("nothing to evaluate: give --models and/or --baselines")
    except (FileNotFoundError, FileExistsError, PermissionError, ValueError) as e:
        raise SystemExit(f"error: {e}")
    log.info("scoring %d sample(s) of split %r (test_fraction %s, split_seed %d) with %d method(s)", n, args.split,
             test_fraction, split_seed, len(methods))
    result = evaluate_methods(methods, samples, args.repeats, progress=True)
    info = {"data": str(args.data), "split": args.split, "test_fraction": test_fraction, "split_seed": split_seed,
            "samples": n, "threads": args.threads, "repeats": args.repeats,
            "aperture": ds.metas[0]["aperture"] if aperture else None}
    for path in write_report(args.out, result, samples, info):
        log.info("wrote %s", path)
    log.info("%s", (args.out / "report.md").read_text())
    return 0


"""Compositing speed at 1080p: the torch-free runtime against PyTorch and the classical scatters.

    python benchmarks/bench_runtime.py                  # ~35 min on 2 cores (exports included)
    python benchmarks/bench_runtime.py --reuse          # keep the exports of an earlier run
    python benchmarks/bench_runtime.py --model runs/any_res/checkpoint.pt [--size 3840 2160] [--tiles 256 384]

The model: a lens network (``architecture = "lens"``) built for 1920x1080 with k_max = 41
(coc_scale_px 41, N = 22 blocks: `blocks = "auto"` on the near-focus lattice), 240 px tiles with 24 px overlap, *initialised from the lens
prior* (``pupil_init = "aperture"``: a 7-blade aperture), not trained: training at 1080p is out
of reach on a CPU, and the run time does not depend on the weights. It is exported four ways:
the default (``multires:10``), the direct-convolution export (``--kernels direct``, one depthwise
``Conv`` per band: the reference), ``rows`` (the same convolutions as row GEMMs: exact, at full
resolution) and the default in float16.

The frame: a procedural layered scene (``data_tools.procedural``, seed ``--seed``) at 1920x1080,
its CoC from a 50 mm lens on a 36 mm sensor focused at the 30 % depth quantile, the f-number
chosen so that the largest |CoC| is 40 px. Two variants for "leave out what a frame does not
need": the same CoC divided by 3 (largest CoC a third of the model's), and the left half of the
frame in focus.

Every row runs in its own process (``--worker``), so its peak RSS is its own, with ``--threads``
threads (torch and onnxruntime), median of ``--repeats`` renders after a warm-up. Printed: ms per
frame, the ratio against the CoC Gaussian scatter of the same run, peak RSS, and for the model
rows the PSNR (normalised images, the training metric) against the exact-aperture scatter of
the same frame, and its difference from the fp32 direct export's.

``--model CKPT`` times a *trained* lens checkpoint instead (its default and rows exports for
``--size`` plates, the frame's largest CoC in proportion to its width, the learned pupil scaled
where that exceeds the trained range), on the same three frames, next to the prior's default
export of them at 1080p; ``--tiles PX ...`` adds its default export with tile cores of each
PX px (``export.py --tile``).

``--trained CKPT`` (with ``--data``, the dataset it was trained on) adds what the default
export costs a *trained* model: the checkpoint exported direct and default, the held-out PSNR of
each through the runtime (its training split), and the difference. The frame above flatters
the direct export (an untrained prior with the truth's own aperture matches the layered render
to ~58 dB), so it magnifies any approximation; a trained model's own error is what a user sees.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
H, W, C_MAX, TILE, OVERLAP = 1080, 1920, 41.0, 240, 24


def make_frame(seed: int, height: int = H, width: int = W, max_coc_px: float = 40.0, device: str = "cpu",
               cat_eye: float = 0.0) -> tuple[np.ndarray, np.ndarray, dict, np.ndarray]:
    """``(aif (H, W, 3) linear, signed CoC (H, W) px, lens dict, truth (H, W, 3))`` of the
    benchmark frame (``height`` x ``width`` px, largest |CoC| ``max_coc_px``); the truth is the
    layered render (``scatter_layers``: every layer whole, what foregrounds hide included), as
    ``data_tools.synth`` renders training data (on ``device``), through a 7-blade aperture with
    ``cat_eye``."""
    sys.path.insert(0, str(ROOT))
    import torch

    from data_tools.procedural import SceneParams, composite_sharp, make_layers
    from neuralbokeh.core.apertures import ApertureModel, parse_aperture
    from neuralbokeh.core.optics import ThinLens
    from neuralbokeh.render import scatter_layers

    H, W = height, width  # noqa: N806 (the frame's, not the module's)
    layers = make_layers(np.random.default_rng(seed), H, W, SceneParams())
    aif, depth = composite_sharp(layers)
    focus = float(np.quantile(depth[np.isfinite(depth)], 0.3))
    probe = ThinLens(50.0, 1.8, 36.0)
    lens = ThinLens(50.0, 1.8 * float(np.abs(probe.coc_px(depth, focus, W, signed=True)).max()) / max_coc_px, 36.0)
    colors = torch.from_numpy(np.stack([layer.color * layer.alpha[..., None] for layer in layers])).permute(0, 3, 1, 2).to(device)
    alphas = torch.from_numpy(np.stack([layer.alpha for layer in layers]))[:, None].to(device)
    truth = scatter_layers(colors, alphas, [lens.coc_px(layer.depth_m, focus, W, signed=True) for layer in layers],
                           ApertureModel(parse_aperture("polygon:7"), cat_eye=cat_eye))
    return (aif.astype(np.float32), lens.coc_px(depth, focus, W, signed=True), lens.to_dict(),
            truth.permute(1, 2, 0).cpu().numpy().astype(np.float32))


def _peak_rss_mb() -> float:
    """This process's own peak RSS (``VmHWM``: unlike ``ru_maxrss`` it is not inherited across exec)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


EXPORTS = {"default": (None, False), "direct": ("direct", False), "rows": ("rows", False), "default_fp16": (None, True)}


def make_model(out: Path, reuse: bool, names: tuple[str, ...] = tuple(EXPORTS), checkpoint: Path | None = None,
               size: tuple[int, int] | None = None, max_coc_px: float | None = None, tag: str = "",
               tile_px: int | None = None, options: dict | None = None) -> dict[str, Path]:
    """The prior-initialised 1080p checkpoint (with the ``ModelConfig`` ``options`` changed; or
    ``checkpoint``, exported for plates of ``size`` ``(H, W)`` up to ``max_coc_px`` with
    ``tile_px`` px tiles) and its exports ``names`` (keys of ``EXPORTS``), files ``<tag><name>.onnx``."""
    import torch

    from neuralbokeh.checkpoint import save_checkpoint
    from neuralbokeh.core.apertures import ApertureModel, parse_aperture
    from neuralbokeh.core.contract import Contract
    from neuralbokeh.core.normalization import Normalization
    from neuralbokeh.core.optics import ThinLens
    from neuralbokeh.export.exporter import export_checkpoint
    from neuralbokeh.networks import ModelConfig, build_model

    out.mkdir(parents=True, exist_ok=True)
    aperture = ApertureModel(parse_aperture("polygon:7"))
    base = {"blocks": "auto", "tile": TILE, "overlap": OVERLAP, "architecture": "lens", "pupil_init": "aperture"}
    cfg = ModelConfig(**base | (options or {})).resolved(C_MAX)
    contract = Contract(H, W, Normalization(0.18), C_MAX, C_MAX, ThinLens(50.0, 1.8, 36.0), aperture.to_dict())
    ckpt = checkpoint or out / f"{tag}prior_1080p.pt"
    if checkpoint is None and not (reuse and ckpt.exists()):
        torch.manual_seed(0)
        save_checkpoint(ckpt, {"model_config": cfg.to_dict(), "contract": contract.to_dict(),
                               "model_state": build_model(cfg, contract).state_dict(), "step": 0})
    paths = {"checkpoint": ckpt}
    for name in names:
        kernels, fp16 = EXPORTS[name]
        path = out / f"{tag}{name}.onnx"
        if not (reuse and path.exists()):
            t = time.perf_counter()
            rep = export_checkpoint(ckpt, path, kernels=kernels, fp16=fp16, threads=2, size=size, max_coc_px=max_coc_px,
                                    tile_px=tile_px)
            print(f"exported {tag}{name:<13} in {time.perf_counter() - t:5.0f} s: kernels {rep['metadata']['kernels']}, "
                  f"parity {max(rep['parity'].values()):.1e}", flush=True)
        paths[name] = path
    return paths


def trained_loss(ckpt: Path, data: Path, out: Path, threads: int) -> None:
    """Held-out PSNR (normalised, the training metric) of a trained checkpoint's direct and
    default exports through the runtime, and ms per frame (median over the samples)."""
    from neuralbokeh.checkpoint import load_checkpoint
    from neuralbokeh.data.dataset import FocalStackDataset
    from neuralbokeh.export.exporter import export_checkpoint
    from neuralbokeh.runtime.onnx_model import OnnxBokeh

    if data is None:
        raise SystemExit("error: --trained needs --data (the dataset it was trained on)")
    split = load_checkpoint(ckpt)["train_config"]["data"]
    test = FocalStackDataset(data, "test", split["test_fraction"], split["split_seed"], normalize=False)
    items = [test[i] for i in range(len(test))]
    out.mkdir(parents=True, exist_ok=True)
    psnr = {}
    for name, kernels in (("direct", "direct"), ("default", None)):
        path = out / f"trained_{name}.onnx"
        rep = export_checkpoint(ckpt, path, kernels=kernels, threads=threads)
        model = OnnxBokeh(path, threads=threads)
        values, times = [], []
        for it in items:
            aif, coc = it["aif"].numpy().transpose(1, 2, 0), it["coc"][0].numpy()
            t = time.perf_counter()
            got = model.render_coc(aif, coc)
            times.append(time.perf_counter() - t)
            values.append(_psnr(got, it["defocus"].numpy().transpose(1, 2, 0)))
        psnr[name] = float(np.mean(values))
        print(f"trained {ckpt}: {name:<7} export ({rep['metadata']['kernels']}): held-out PSNR {psnr[name]:.3f} dB over "
              f"{len(items)} samples, {1000 * statistics.median(times):.0f} ms per frame", flush=True)
    print(f"trained: the default export costs {psnr['direct'] - psnr['default']:+.3f} dB against the direct one\n", flush=True)


def worker(args: argparse.Namespace) -> None:
    """One row: render the frame ``repeats`` times, print JSON, save the output (linear RGB)."""
    data = np.load(args.frame)
    aif, coc = data["aif"], data["coc"]
    kind, _, arg = args.worker.partition(":")
    if kind == "onnx":
        from neuralbokeh.runtime.onnx_model import OnnxBokeh

        model = OnnxBokeh(arg, threads=args.threads)

        def run() -> np.ndarray:
            return model.render_coc(aif, coc)
    else:
        import torch

        from neuralbokeh.core.apertures import ApertureModel, parse_aperture
        from neuralbokeh.render import scatter_defocus
        from neuralbokeh.render.baselines import gaussian_defocus

        torch.set_num_threads(args.threads)
        a = torch.from_numpy(aif).permute(2, 0, 1)[None].double()
        c = torch.from_numpy(coc)[None, None].double()
        if kind == "eager":
            from neuralbokeh.checkpoint import load_model

            model, _ = load_model(arg)

            def network(x: torch.Tensor) -> torch.Tensor:
                with torch.no_grad():
                    return model(x.float()).double()

            def run() -> np.ndarray:
                return model.contract.apply(network, a, c)[0].permute(1, 2, 0).numpy()
        elif kind == "gaussian":
            def run() -> np.ndarray:
                return gaussian_defocus(a, c)[0].permute(1, 2, 0).numpy()
        elif kind == "scatter":
            aperture = ApertureModel(parse_aperture("polygon:7"))

            def run() -> np.ndarray:
                return scatter_defocus(a, c, aperture)[0].permute(1, 2, 0).numpy()
        else:
            raise ValueError(f"unknown worker {args.worker!r}")
    out = run()  # warm-up
    times = []
    for _ in range(args.repeats):
        t = time.perf_counter()
        out = run()
        times.append(time.perf_counter() - t)
    np.save(args.out, np.asarray(out, dtype=np.float32))
    print(json.dumps({"ms": 1000.0 * statistics.median(times), "rss_mb": _peak_rss_mb()}))


def alternating_times(models: dict, aif: np.ndarray, coc: np.ndarray, repeats: int) -> tuple[dict[str, list[float]], dict[str, np.ndarray]]:
    """The ms of each ``render_coc(aif, coc)`` per model, ``repeats`` rounds in which every model
    renders once (a drift of the machine's speed hits a round's renders alike), after one
    warm-up each; and the warm-up outputs."""
    outs = {name: m.render_coc(aif, coc) for name, m in models.items()}
    times: dict[str, list[float]] = {name: [] for name in models}
    for _ in range(repeats):
        for name, m in models.items():
            t = time.perf_counter()
            m.render_coc(aif, coc)
            times[name].append(1000 * (time.perf_counter() - t))
    return times, outs


def alternating_ms(models: dict, aif: np.ndarray, coc: np.ndarray, repeats: int) -> tuple[dict[str, float], dict[str, np.ndarray]]:
    """Median ms per model of :func:`alternating_times`' renders, and the warm-up outputs."""
    times, outs = alternating_times(models, aif, coc, repeats)
    return {name: statistics.median(v) for name, v in times.items()}, outs


def _row(spec: str, frame: Path, out: Path, threads: int, repeats: int) -> dict:
    cmd = [sys.executable, __file__, "--worker", spec, "--frame", str(frame), "--out", str(out), "--threads", str(threads),
           "--repeats", str(repeats)]
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    if res.returncode != 0:
        raise RuntimeError(f"worker {spec} failed:\n{res.stderr[-3000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    from neuralbokeh.core.normalization import Normalization

    norm = Normalization(0.18)
    mse = float(np.mean(((norm.encode(a.astype(np.float64)) - norm.encode(b.astype(np.float64))) / 2.0) ** 2))
    return 10.0 * np.log10(1.0 / mse) if mse > 0 else float("inf")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out-dir", type=Path, default=ROOT / "runs" / "bench_runtime", help="exports, frames and outputs")
    p.add_argument("--reuse", action="store_true", help="keep the checkpoint and exports of an earlier run")
    p.add_argument("--threads", type=int, default=2, help="threads of the main rows (a 1-thread row is added)")
    p.add_argument("--repeats", type=int, default=5, help="renders per row (median)")
    p.add_argument("--seed", type=int, default=3, help="the procedural scene")
    p.add_argument("--trained", type=Path, help="a trained lens checkpoint: held-out PSNR of its direct and default exports")
    p.add_argument("--data", type=Path, help="the dataset --trained was trained on")
    p.add_argument("--model", type=Path, help="time this trained lens checkpoint instead of the untrained prior (exports "
                   "default and rows for --size plates; at 1080p next to the prior's default export)")
    p.add_argument("--size", type=int, nargs=2, default=(W, H), metavar=("W", "H"), help="the frame with --model")
    p.add_argument("--tiles", type=int, nargs="*", default=[], metavar="PX",
                   help="with --model: also its default export with tile cores of each PX px (export.py --tile)")
    p.add_argument("--tiles-only", action="store_true",
                   help="with --model and --tiles: leave out the exports with the trained tiles (at 3840x2160 their "
                        "parity check needs about 26 GB)")
    p.add_argument("--worker", help=argparse.SUPPRESS)
    p.add_argument("--frame", type=Path, help=argparse.SUPPRESS)
    p.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.worker:
        worker(args)
        return
    sys.path.insert(0, str(ROOT))
    args.out_dir.mkdir(parents=True, exist_ok=True)
    if args.trained:
        trained_loss(args.trained, args.data, args.out_dir, args.threads)
    if args.model:
        model_speed(args)
        return
    paths = make_model(args.out_dir, args.reuse)
    frames, truth = _frames(args, H, W, 40.0)
    rows = [("runtime, default export", f"onnx:{paths['default']}", "full", args.threads),
            ("runtime, default export, 1 thread", f"onnx:{paths['default']}", "full", 1),
            ("runtime, default export, fp16", f"onnx:{paths['default_fp16']}", "full", args.threads),
            ("runtime, direct-convolution export", f"onnx:{paths['direct']}", "full", args.threads),
            ("runtime, rows export (exact)", f"onnx:{paths['rows']}", "full", args.threads),
            ("PyTorch eager (FFT, exact)", f"eager:{paths['checkpoint']}", "full", args.threads),
            ("exact-aperture scatter (7-gon)", "scatter", "full", args.threads),
            ("CoC Gaussian scatter", "gaussian", "full", args.threads),
            ("runtime, default, max CoC / 3", f"onnx:{paths['default']}", "third", args.threads),
            ("runtime, default, half in focus", f"onnx:{paths['default']}", "half_in_focus", args.threads),
            ("runtime, direct, max CoC / 3", f"onnx:{paths['direct']}", "third", args.threads),
            ("runtime, rows, max CoC / 3", f"onnx:{paths['rows']}", "third", args.threads),
            ("runtime, rows, half in focus", f"onnx:{paths['rows']}", "half_in_focus", args.threads)]
    results = _run_rows(rows, frames, args)
    _table(results, truth, "runtime, direct-convolution export")
    ms = {k: v["ms"] for k, v in results.items()}
    gauss, default = ms["CoC Gaussian scatter"], ms["runtime, default export"]
    print(f"\ndefault export: {default / gauss:.2f}x the CoC Gaussian's time, {ms['runtime, direct-convolution export'] / default:.1f}x "
          f"faster than the direct export; 1 -> {args.threads} threads {ms['runtime, default export, 1 thread'] / default:.2f}x")
    print(f"max CoC / 3: default {default / ms['runtime, default, max CoC / 3']:.2f}x faster than the full frame "
          f"(direct: {ms['runtime, direct-convolution export'] / ms['runtime, direct, max CoC / 3']:.2f}x); "
          f"half in focus: {default / ms['runtime, default, half in focus']:.2f}x faster")
    rows_full = ms["runtime, rows export (exact)"]
    print(f"rows export (exact): {ms['runtime, direct-convolution export'] / rows_full:.1f}x faster than the direct export; "
          f"max CoC / 3 {rows_full / ms['runtime, rows, max CoC / 3']:.2f}x, half in focus "
          f"{rows_full / ms['runtime, rows, half in focus']:.2f}x faster than its full frame")


def _frames(args: argparse.Namespace, height: int, width: int, max_coc_px: float) -> tuple[dict[str, Path], np.ndarray]:
    """The frame (``full``) and its two variants (``third``: the CoC / 3; ``half_in_focus``: the
    left half at CoC 0), saved for the workers; and the full frame's truth."""
    aif, coc, lens, truth = make_frame(args.seed, height, width, max_coc_px)
    frames = {}
    half = np.where(np.arange(width)[None, :] < width // 2, 0.0, coc)
    for name, c in (("full", coc), ("third", coc / 3.0), ("half_in_focus", half)):
        frames[name] = args.out_dir / f"frame_{width}x{height}_{name}.npz"
        np.savez(frames[name], aif=aif, coc=c)
    print(f"frame: {width}x{height} procedural scene (seed {args.seed}), f/{lens['f_number']:.2f}, |CoC| up to "
          f"{np.abs(coc).max():.1f} px, {100 * np.mean(np.abs(coc) <= 1):.0f} % of pixels within 1 px; median of {args.repeats}")
    return frames, truth


def _run_rows(rows: list[tuple[str, str, str, int]], frames: dict[str, Path], args: argparse.Namespace) -> dict[str, dict]:
    results = {}
    for label, spec, frame, threads in rows:
        out = args.out_dir / f"out_{len(results)}.npy"
        r = _row(spec, frames[frame], out, threads, args.repeats)
        results[label] = {**r, "frame": frame, "threads": threads, "image": np.load(out)}
        print(f"  ran {label}: {r['ms']:.0f} ms", flush=True)
    return results


def _table(results: dict[str, dict], truth: np.ndarray, reference: str) -> None:
    gauss = results["CoC Gaussian scatter"]["ms"]
    ref = results[reference]
    base_psnr = _psnr(ref["image"], truth)
    print(f"\nPSNR: against the layered render of the full frame (normalised images, the training metric); dPSNR: minus "
          f"{reference!r}'s; vs ref: PSNR of the row against that row's output")
    print(f"\n{'':<38} {'frame':<14} {'thr':>3} {'ms/frame':>9} {'x Gauss':>8} {'RSS MB':>7} {'PSNR':>7} {'dPSNR':>7} {'vs ref':>9}")
    for label, r in results.items():
        psnr = _psnr(r["image"], truth) if r["frame"] == "full" else None
        vs_ref = _psnr(r["image"], ref["image"]) if psnr is not None and r is not ref else None
        print(f"{label:<38} {r['frame']:<14} {r['threads']:>3} {r['ms']:>9.0f} {r['ms'] / gauss:>8.2f} {r['rss_mb']:>7.0f} "
              + (f"{psnr:>7.2f} {psnr - base_psnr:>+7.3f} " if psnr is not None else f"{'':>7} {'':>7} ")
              + (f"{vs_ref:>9.2f}" if vs_ref is not None else ""))


def model_speed(args: argparse.Namespace) -> None:
    """``--model``: a trained lens checkpoint exported for ``--size`` plates (default and rows
    exports), timed on the frame and its two variants; at 1080p next to the untrained prior's
    default export ("today's way") in the same run. The frame's largest CoC is 40 px at 1920 px
    wide, in proportion at other widths (the same lens on the same sensor)."""
    width, height = args.size
    max_coc = 40.0 * width / W
    frames, truth = _frames(args, height, width, max_coc)
    from neuralbokeh.checkpoint import load_checkpoint

    trained_max = float(load_checkpoint(args.model)["contract"]["max_coc_px"])
    beyond = max_coc * 1.001 if max_coc > trained_max else None  # scaled pupil beyond the trained range
    if args.tiles_only and not args.tiles:
        raise SystemExit("error: --tiles-only needs --tiles PX ...")
    trained_tiles = () if args.tiles_only else ("default", "rows")
    paths = make_model(args.out_dir, args.reuse, trained_tiles, checkpoint=args.model, size=(height, width),
                       max_coc_px=beyond, tag=f"model_{width}x{height}_")
    rows = [(f"model, {e} export{', ' + f if f != 'full' else ''}{', 1 thread' if t == 1 else ''}", f"onnx:{paths[e]}", f,
             t or args.threads) for e, f, t in (("default", "full", 0), ("default", "full", 1), ("default", "third", 0),
                                                ("default", "half_in_focus", 0), ("rows", "full", 0), ("rows", "third", 0),
                                                ("rows", "half_in_focus", 0)) if e in trained_tiles]
    for tile in args.tiles:  # the same model with larger tiles: fewer, larger convolutions
        big = make_model(args.out_dir, args.reuse, ("default",), checkpoint=args.model, size=(height, width),
                         max_coc_px=beyond, tag=f"model_{width}x{height}_tile{tile}_", tile_px=tile)["default"]
        rows += [(f"model, default export, tiles {tile}{', ' + f if f != 'full' else ''}", f"onnx:{big}", f, args.threads)
                 for f in ("full", "third", "half_in_focus")]
    rows += [("exact-aperture scatter (7-gon)", "scatter", "full", args.threads),
             ("CoC Gaussian scatter", "gaussian", "full", args.threads)]
    if (width, height) == (W, H):  # today's way: the untrained prior's default export of the same frames
        prior = make_model(args.out_dir, args.reuse, ("default",))["default"]
        rows += [(f"prior, default export{', ' + f if f != 'full' else ''}", f"onnx:{prior}", f, args.threads)
                 for f in ("full", "third", "half_in_focus")]
    results = _run_rows(rows, frames, args)
    _table(results, truth, "model, rows export" if trained_tiles else f"model, default export, tiles {args.tiles[0]}")
    ms = {k: v["ms"] for k, v in results.items()}
    for e in (*trained_tiles, *(f"default export, tiles {t}" for t in args.tiles)):
        name = f"model, {e}" if "tiles" in e else f"model, {e} export"
        full = ms[name]
        print(f"{name}: {full:.0f} ms per frame, peak RSS {results[name]['rss_mb'] / 1024:.2f} GB; "
              f"max CoC / 3 {full / ms[f'{name}, third']:.2f}x and half in focus "
              f"{full / ms[f'{name}, half_in_focus']:.2f}x faster than the full frame")
    if "prior, default export" in ms:
        print(f"against the prior's default export (today's way): full {ms['prior, default export'] / ms['model, default export']:.2f}x, "
              f"max CoC / 3 {ms['prior, default export, third'] / ms['model, default export, third']:.2f}x, half in focus "
              f"{ms['prior, default export, half_in_focus'] / ms['model, default export, half_in_focus']:.2f}x (> 1: the model is faster)")


if __name__ == "__main__":
    main()

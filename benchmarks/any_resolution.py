"""A lens, not a picture size: train on crops of large frames, score whole frames at three formats.

    python benchmarks/any_resolution.py [--size 1920 1080] [--scenes 16] [--minutes 30] [--crop 256]
        [--f-number 13] [--data data/any_res] [--out runs/any_res] [--steps N] [--crop-margin auto|PX]
        [section.key=value ...]

Makes (once) ``--scenes`` synthetic scenes x 4 slices at ``--size`` (7-blade aperture, cat-eye
0.6; f-number chosen so that the largest |CoC| is >= 40 px at 1080p), 25 % of the scenes held
out. Trains the default lens network in a child process (``train.py``, so its peak RSS is the
child's own) on random ``--crop``^2 crops for ``--minutes`` of wall time (tiles of 128 + 32 px:
the overlap covers the largest CoC radius; each crop reads only its tiles of the scene files, unless ``--cache``
keeps the scenes in memory). Then scores the held-out scenes, in the training
metric (PSNR/SSIM of the normalised images mapped to [0, 1]), as three plate formats:

- ``whole``: the frames as rendered (training's own final held-out evaluation);
- ``half``: the same frames at half the resolution (AIF and ground truth area-averaged 2x2,
  the CoC halved: the same lens on a coarser sensor; the truth is the full-size render
  downsampled, not a render at half size);
- ``2.39:1``: a centred 2.39:1 crop of the frames, with its window on the sensor.

Each format prints the identity (AIF unchanged), the CoC-driven Gaussian, the exact-aperture
scatter (oracle) and the model, and the share of the gap (oracle - Gaussian) the model closes,
then the training steps, s/step and the trainer's peak RSS. With a GPU, training and scoring run
on it (``--device``); the data are still made on the CPU.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from data_tools.synth import main as synth
from neuralbokeh.checkpoint import load_model
from neuralbokeh.core.apertures import ApertureModel
from neuralbokeh.core.normalization import Normalization
from neuralbokeh.core.optics import SensorWindow, ThinLens
from neuralbokeh.data.dataset import FocalStackDataset, load_scene, write_scene
from neuralbokeh.training.loop import Samples, held_out_baselines, held_out_metrics

ROOT = Path(__file__).resolve().parents[1]
TEST_FRACTION, SPLIT_SEED = 0.25, 0


def _area2(a: np.ndarray) -> np.ndarray:
    x = torch.from_numpy(np.ascontiguousarray(np.atleast_3d(a).transpose(2, 0, 1), dtype=np.float64))[None]
    out = F.avg_pool2d(x[..., : x.shape[-2] // 2 * 2, : x.shape[-1] // 2 * 2], 2)[0].numpy().transpose(1, 2, 0)
    return out if a.ndim == 3 else out[..., 0]


def plate_dataset(scenes: list[Path], out: Path, kind: str) -> Path:
    """The held-out ``scenes`` as plates of another format (``half`` or ``crop239``), written once."""
    for src in scenes:
        folder = out / src.name
        if folder.exists():
            continue
        s = load_scene(src)
        meta = s["meta"]
        h, w = s["aif"].shape[:2]
        window = SensorWindow.from_dict(meta.get("sensor_window"))
        if kind == "half":
            aif, depth = _area2(s["aif"]), s["depth"][: h // 2 * 2 : 2, : w // 2 * 2 : 2]
            defocus, coc = [_area2(d) for d in s["defocus"]], [_area2(c) / 2.0 for c in s["coc"]]
        else:  # the centred 2.39:1 rows of the frame
            rows = min(h, round(w / 2.39))
            r0 = (h - rows) // 2
            cut = slice(r0, r0 + rows)
            aif, depth, defocus, coc = s["aif"][cut], s["depth"][cut], [d[cut] for d in s["defocus"]], [c[cut] for c in s["coc"]]
            window = SensorWindow(window.left, window.top + window.height * r0 / h, window.width, window.height * rows / h)
        aperture = ApertureModel.from_dict(meta["aperture"]) if meta["aperture"] else None
        write_scene(folder, aif, depth.astype(np.float64), defocus, coc, ThinLens.from_dict(meta["lens"]),
                    meta["focus_distances_m"], aperture, {"name": "benchmarks/any_resolution.py", "from": str(src),
                                                          "format": kind}, window)
    return out


def score(model: torch.nn.Module, data: Path, norm: Normalization, device: torch.device) -> dict[str, float]:
    ds = FocalStackDataset(data, "all", normalization=norm, coc_scale_px=model.contract.coc_scale_px)
    samples = Samples(ds, cache=False)
    return held_out_metrics(model.to(device), samples, device, held_out_baselines(ds, samples, device))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", type=int, nargs=2, default=(1920, 1080), metavar=("W", "H"))
    p.add_argument("--scenes", type=int, default=16)
    p.add_argument("--minutes", type=float, default=30.0)
    p.add_argument("--crop", type=int, default=256)
    p.add_argument("--f-number", type=float, default=13.0)
    p.add_argument("--data", type=Path, default=ROOT / "data" / "any_res")
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "any_res")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--steps", type=int, help="train this many steps instead of --minutes of wall time (a control run "
                   "that CPU contention cannot change)")
    p.add_argument("--crop-margin", default="auto", help="data.crop_margin: px the loss stays from a crop's cut sides, "
                   "or auto (the largest CoC radius); 0 for the loss on the whole crop")
    p.add_argument("--skip-training", action="store_true", help="score the checkpoint already in --out")
    p.add_argument("--cache", action="store_true",
                   help="keep the training scenes in memory (RSS grows with the data; the same crops as reading them)")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu",
                   help="where the scoring runs (training takes the GPU by itself when there is one)")
    p.add_argument("overrides", nargs="*", help="more training settings, section.key=value (train.py's), e.g. "
                   "train.field_lr_scale=1.0")
    args = p.parse_args()
    torch.set_num_threads(2)
    t0 = time.perf_counter()
    synth(["--out", str(args.data), "--scenes", str(args.scenes), "--size", *map(str, args.size), "--slices", "4",
           "--aperture", "polygon:7", "--cat-eye", "0.6", "--f-number", str(args.f_number), "--seed", "2026",
           "--workers", str(args.workers)])
    print(f"data         {time.perf_counter() - t0:.0f} s (made once)")
    overrides = [f"data.roots=['{args.data}']", f"data.test_fraction={TEST_FRACTION}", f"data.split_seed={SPLIT_SEED}",
                 f"data.cache={'true' if args.cache else 'false'}", f"data.crop=[{args.crop}, {args.crop}]",
                 "model.tile=128", "model.overlap=32",
                 f"train.steps={args.steps or 1000000}", "train.lr_schedule='constant'", "train.eval_every=1000000",
                 "data.crop_margin=" + ("'auto'" if args.crop_margin == "auto" else str(int(args.crop_margin))),
                 "train.checkpoint_every=100", "train.threads=2", f"train.out_dir='{args.out}'", *args.overrides]
    if not args.skip_training:
        cmd = [sys.executable, str(ROOT / "train.py"), str(ROOT / "configs" / "quickstart.toml"), *overrides,
               *([] if args.steps else ["--time-limit", str(args.minutes)]), "--overwrite"]
        print("train        " + " ".join(cmd[1:]), flush=True)
        subprocess.run(cmd, check=True, cwd=ROOT)
    rss_gb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 2**20  # kB on Linux
    summary = json.loads((args.out / "summary.json").read_text())
    model, ckpt = load_model(args.out / "checkpoint.pt")
    norm = Normalization(ckpt["train_config"]["data"]["normalization_scale"])
    held = FocalStackDataset(args.data, "test", TEST_FRACTION, SPLIT_SEED).scenes
    formats = {"whole": args.data.parent / f"{args.data.name}_heldout", "half": args.data.parent / f"{args.data.name}_half",
               "2.39:1": args.data.parent / f"{args.data.name}_239"}
    formats["whole"].mkdir(parents=True, exist_ok=True)
    for scene in held:  # the held-out scenes alone, as links (no copy)
        link = formats["whole"] / scene.name
        if not link.exists():
            link.symlink_to(scene.resolve(), target_is_directory=True)
    plate_dataset(held, formats["half"], "half")
    plate_dataset(held, formats["2.39:1"], "crop239")
    print(f"\nheld-out scenes: {len(held)} x 4 slices; model trained {summary['steps']} steps in {summary['seconds']:.0f} s "
          f"({summary['seconds'] / max(summary['steps'], 1):.2f} s/step) on {args.crop}^2 crops; trainer peak RSS "
          f"{rss_gb:.2f} GB" + (" (training skipped: RSS of this run's children only)" if args.skip_training else ""))
    print(f"{'format':<8} {'size':>10} {'identity':>9} {'Gaussian':>9} {'oracle':>9} {'model':>9} {'SSIM m/G':>15} {'gap closed':>10}")
    for name, folder in formats.items():
        t = time.perf_counter()
        # whole frames: training's own final held-out evaluation (the same frames, the same metric)
        m = summary["metrics"] if name == "whole" and summary["metrics"] else score(model, folder, norm, torch.device(args.device))
        first = FocalStackDataset(folder, "all")[0]["aif"].shape
        gap = m["oracle_psnr"] - m["gaussian_psnr"]
        closed = (m["eval_psnr"] - m["gaussian_psnr"]) / gap if gap > 0 else float("nan")
        print(f"{name:<8} {first[2]:>5}x{first[1]:<4} {m['identity_psnr']:>9.2f} {m['gaussian_psnr']:>9.2f} "
              f"{m['oracle_psnr']:>9.2f} {m['eval_psnr']:>9.2f} {m['eval_ssim']:>7.4f}/{m['gaussian_ssim']:.4f} "
              f"{100 * closed:>9.0f}%   ({time.perf_counter() - t:.0f} s)", flush=True)


if __name__ == "__main__":
    main()

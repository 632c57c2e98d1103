"""A trained lens network rendered by PyTorch on a GPU, against the classical scatters on the same GPU.

    python benchmarks/bench_gpu.py --model runs/any_res/checkpoint.pt [--sizes 1920x1080 3840x2160]
        [--repeats 20] [--seed 3] [--json runs/gpu.json]

The compositing runtime (ONNX) runs on the CPU by design; this is what training, evaluation and a
PyTorch user get on a GPU. Frames: ``bench_runtime.py``'s procedural frame at each size (largest
|CoC| 40 px at 1920 px wide, in proportion at other widths: the same lens on the same sensor;
above the trained range the learned pupil is scaled), a third of its CoC, its left half in focus,
and all of it in focus. The module plans its bands per frame from the frame's largest |CoC| and
skips the (tile, band, side) scatters no pixel uses; the rest (gates, in-focus light, composite)
runs over the whole frame. Printed per size and frame: median ms
(CUDA-synchronised, after two warm-ups), peak GPU memory, and the full frame's ratio to the CoC
Gaussian and the exact-aperture scatter of the same run; then PSNR against the layered render
(training metric), and the largest difference of the GPU render from the CPU render of the same
module at the first size, with cuDNN's TF32 convolutions on (PyTorch's default) and off.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_runtime import W, _psnr, make_frame  # noqa: E402

from neuralbokeh.checkpoint import load_model  # noqa: E402
from neuralbokeh.core.apertures import ApertureModel, parse_aperture  # noqa: E402
from neuralbokeh.render import scatter_defocus  # noqa: E402
from neuralbokeh.render.baselines import gaussian_defocus  # noqa: E402


def _timed(fn, repeats: int, device: torch.device) -> tuple[float, float, torch.Tensor]:
    """Median ms of ``fn()`` and its peak memory (GB, GPU only), after two warm-ups; and its output."""
    out = fn()
    fn()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        times.append(1000.0 * (time.perf_counter() - t))
    peak = torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else float("nan")
    return statistics.median(times), peak, out


def _renderer(model: torch.nn.Module, aif: torch.Tensor, coc: torch.Tensor):
    """The model's linear render of ``aif`` (1, 3, H, W) with ``coc`` (1, 1, H, W) px, as a callable."""
    contract = model.contract

    @torch.no_grad()
    def run() -> torch.Tensor:
        return contract.output_linear(model(contract.network_input(aif, coc).float()))

    return run


def bench_size(model: torch.nn.Module, height: int, width: int, args: argparse.Namespace, device: torch.device) -> dict:
    aif_np, coc_np, _, truth = make_frame(args.seed, height, width, 40.0 * width / W, str(device))
    cocs = {"full": coc_np, "third": coc_np / 3.0, "half_in_focus": np.where(np.arange(width)[None] < width // 2, 0.0, coc_np),
            "all_in_focus": np.zeros_like(coc_np)}
    aif = torch.from_numpy(aif_np).permute(2, 0, 1)[None].to(device)
    rows = {}
    for name, c in cocs.items():
        coc = torch.from_numpy(np.ascontiguousarray(c, dtype=np.float32))[None, None].to(device)
        ms, peak, out = _timed(_renderer(model, aif, coc), args.repeats, device)
        rows[name] = {"ms": ms, "peak_gb": peak}
        if name == "full":
            rows[name]["psnr"] = _psnr(out[0].permute(1, 2, 0).cpu().numpy(), truth)
            full_out = out
    a64, c64 = aif.double(), torch.from_numpy(coc_np)[None, None].to(device).double()
    aperture = ApertureModel(parse_aperture("polygon:7"))
    for name, fn in (("gaussian", lambda: gaussian_defocus(a64, c64)), ("scatter", lambda: scatter_defocus(a64, c64, aperture))):
        ms, peak, _ = _timed(fn, max(3, args.repeats // 4), device)
        rows[name] = {"ms": ms, "peak_gb": peak}
    return {"rows": rows, "output": full_out, "aif": aif, "coc": torch.from_numpy(coc_np)[None, None]}


def cpu_parity(model: torch.nn.Module, checkpoint: Path, case: dict) -> dict[str, float]:
    """Largest |GPU - CPU| of the full frame's render (linear light) over the CPU render's largest
    value, cuDNN TF32 on and off."""
    cpu_model = load_model(checkpoint)[0].eval()
    reference = _renderer(cpu_model, case["aif"].cpu(), case["coc"].float())()
    out = {}
    for tf32 in (True, False):
        torch.backends.cudnn.allow_tf32 = tf32
        gpu = _renderer(model, case["aif"], case["coc"].to(case["aif"].device).float())()
        out[f"tf32_{'on' if tf32 else 'off'}"] = float((gpu.cpu() - reference).abs().max() / reference.abs().max())
    torch.backends.cudnn.allow_tf32 = True
    return out


def profile_render(model: torch.nn.Module, case: dict, device: torch.device, rows: int = 25) -> str:
    """torch.profiler's table of one full-frame render (after the timed ones): the ops by their
    total device time (CPU time on the CPU), and how often the host waited for the device."""
    from torch.profiler import ProfilerActivity, profile

    render = _renderer(model, case["aif"], case["coc"].to(device).float())
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    with profile(activities=activities) as prof:
        render()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
    key = "self_cuda_time_total" if device.type == "cuda" else "self_cpu_time_total"
    return prof.key_averages().table(sort_by=key, row_limit=rows)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--model", type=Path, required=True, help="a lens checkpoint (train.py's checkpoint.pt)")
    p.add_argument("--sizes", nargs="+", default=["1920x1080", "3840x2160"], help="plate sizes, WxH")
    p.add_argument("--repeats", type=int, default=20)
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--json", type=Path, help="also write the figures here")
    p.add_argument("--device", default="cuda", help="cuda, or cpu for a dry run of the script (no parity check)")
    p.add_argument("--profile", action="store_true", help="also print torch.profiler's costliest ops of one full-frame render per size")
    args = p.parse_args()
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("error: --device cuda needs a CUDA GPU (torch.cuda.is_available() is False); --device cpu for a dry run")
    model = load_model(args.model)[0].eval().to(device)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    print(f"{name}, torch {torch.__version__}; model {args.model}: trained max |CoC| "
          f"{model.contract.max_coc_px:.1f} px; median of {args.repeats}")
    report = {}
    for i, size in enumerate(args.sizes):
        width, height = (int(v) for v in size.lower().split("x"))
        case = bench_size(model, height, width, args, device)
        rows = case["rows"]
        print(f"\n{width}x{height} (largest |CoC| {40.0 * width / W:.0f} px; full-frame PSNR {rows['full']['psnr']:.2f} dB)")
        print(f"{'frame':<16} {'ms':>9} {'GPU GB':>7} {'full / this':>11}")
        for name, r in rows.items():
            print(f"{name:<16} {r['ms']:>9.1f} {r['peak_gb']:>7.2f} {rows['full']['ms'] / r['ms']:>11.2f}")
        report[size] = rows
        if args.profile:
            print(profile_render(model, case, device))
        if i == 0 and device.type == "cuda":
            report[f"{size}_cpu_parity_rel"] = cpu_parity(model, args.model, case)
            print(f"GPU against CPU, full frame (max |diff| / max |CPU|): {report[f'{size}_cpu_parity_rel']}")
        del case
        if device.type == "cuda":
            torch.cuda.empty_cache()
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()

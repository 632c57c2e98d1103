"""Can the lens network's ONNX graph come from the PyTorch module itself? (issue 26, item 4)

    python benchmarks/bench_traced_export.py            # ~15 min on 2 cores

The model and frames are ``bench_runtime.py``'s: a lens network for 1920x1080 (N = 20 bands,
240 px tiles, 24 px overlap) initialised from its 7-blade prior, on a procedural frame with
|CoC| up to 40 px, the same CoC / 3, and its left half in focus.

Exported two ways, each at full resolution (``direct``) and on coarser grids for wide bands
(``multires:10``, the default export):

* **built**: today's exporter (``export/lens_graph.py``), one ``If`` per tile and one per
  (tile, band, side), run through the runtime (``OnnxBokeh``), which switches off from the
  frame's CoC map every tile and band that nothing uses;
* **traced**: ``torch.onnx.export`` of a module written with the lens network's own functions
  (:class:`TracedPlate`: tiles as a batch, one grouped ``conv2d`` per band and side over all
  tiles, ``F.fold`` overlap-add, the module's composite and fill). Tracing records no control
  flow, so every band of every tile runs;
* **traced, cond** (``--dynamo``, needs ``onnxscript``): the dynamo exporter with a
  ``torch.cond`` per (band, side) on a frame-level flag: whole bands are skipped, tiles are not.

Printed: ms per frame (median of ``--repeats`` after a warm-up, ``--threads`` threads), the ratio
to the built graph on the same frame, and the max abs difference from PyTorch (normalised units).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_runtime import H, W, make_frame, make_model  # noqa: E402

from neuralbokeh.checkpoint import load_model  # noqa: E402
from neuralbokeh.core.tiling import pyramid_levels  # noqa: E402
from neuralbokeh.export.exporter import plate_model  # noqa: E402
from neuralbokeh.networks.lens import LensBokeh, _gate, band_scales, bucket_weights, reduce_kernel  # noqa: E402
from neuralbokeh.ops.holes import _pull_push, occluders  # noqa: E402
from neuralbokeh.ops.tiles import tile  # noqa: E402
from neuralbokeh.runtime.onnx_model import OnnxBokeh, make_session  # noqa: E402


class TracedPlate(nn.Module):
    """A :class:`LensBokeh` plate (one size, whole sensor) as straight-line torch ops over all
    tiles at once: ``(aif (1, 3, H, W), coc (1, 1, H, W)[, band_on (N, 2) bool])`` normalised ->
    ``(1, 3, H, W)``. ``cond``: each band and side behind ``torch.cond(band_on[n - 1, s])``."""

    def __init__(self, model: LensBokeh, scales: dict[int, int], cond: bool = False) -> None:
        super().__init__()
        self.model, self.scales, self.cond = model, scales, cond
        h, w = model.contract.size
        self.lay = model.layout(h, w)
        self.plan = model.plan(model.contract.max_coc_px)
        self.blocks, self.diameters = self.plan.blocks, self.plan.diameters
        with torch.no_grad():
            pupils = model.tile_pupils(self.lay, h, w)[0]
            drift = tile(model.drift_map(h, w).flatten(1, 2), self.lay)  # (1, T 6, win, win)
            self.register_buffer("drift", drift.view(-1, 2, 3, *drift.shape[-2:]))  # (T, 2, 3, win, win)
            for n in range(1, self.blocks + 1):
                kern = reduce_kernel(model.kernels(n, pupils, float(self.diameters[n])), scales[n])  # (T, 2, 3, k, k)
                for side in range(2):
                    k6 = torch.cat([kern[:, side], kern[:, side]], dim=1).flip(-2, -1)  # correlation weights
                    self.register_buffer(f"w{n}_{side}", k6.reshape(-1, 1, *k6.shape[-2:]).contiguous())
        self.register_buffer("src", torch.from_numpy(self.lay.source_masks())[:, None])

    def band(self, acc, rgb, c, pos, n: int, side: int):
        t, win = rgb.shape[0], rgb.shape[-1]
        gs = _gate(pos, n) * self.src[:, 0] * ((c > 0) if side == 0 else (c < 0)).to(rgb.dtype)  # (T, win, win)
        gains = self.model.colour_gains(self.drift[:, side], float(self.diameters[n]), side)  # (T, 3, win, win)
        feats = torch.cat([rgb * gains * gs[:, None], gs[:, None].expand(-1, 3, -1, -1)], dim=1).reshape(1, t * 6, win, win)
        s = self.scales[n]
        if s > 1:
            size = -(-win // s) * s
            feats = F.avg_pool2d(F.pad(feats, (0, size - win, 0, size - win)), s)
        weight = getattr(self, f"w{n}_{side}")
        out = F.conv2d(feats, weight, padding=weight.shape[-1] // 2, groups=t * 6)
        if s > 1:
            out = F.interpolate(out, scale_factor=float(s), mode="bilinear", align_corners=False)[..., :win, :win]
        sign = 1.0 if side == 0 else -1.0
        bw = bucket_weights(sign * float(self.diameters[n]), c, self.model.config.occlusion_margin_px)  # (3, T, win, win)
        return acc + bw.permute(1, 0, 2, 3).unsqueeze(2) * out.reshape(t, 1, 6, win, win)

    def forward(self, aif: torch.Tensor, coc: torch.Tensor, band_on: torch.Tensor | None = None) -> torch.Tensor:
        m, lay = self.model, self.lay
        x = torch.cat([aif, coc], dim=1)
        h, w = x.shape[-2:]
        win, n_t = lay.window, lay.num_tiles
        xt = tile(x, lay).view(n_t, 4, win, win)
        rgb = self.decode(xt[:, :3])
        c = xt[:, 3] * float(m.contract.coc_scale_px)
        pos = self.plan.position(c)
        g0 = _gate(pos, 0)[:, None] * self.src
        same = torch.cat([rgb * g0, g0.expand(-1, 3, -1, -1)], dim=1)
        acc = torch.stack([torch.zeros_like(same), same, torch.zeros_like(same)], dim=1)  # (T, 3, 6, win, win)
        for n in range(1, self.blocks + 1):
            for side in range(2):
                if self.cond:
                    acc = torch.cond(band_on[n - 1, side], lambda a, r, cc, p, n=n, s=side: self.band(a, r, cc, p, n, s),
                                     lambda a, r, cc, p: a.clone(), (acc, rgb, c, pos))
                else:
                    acc = self.band(acc, rgb, c, pos, n, side)
        hp, wp = lay.padded_size
        cols = acc.reshape(n_t, 18 * win * win).transpose(0, 1)[None]
        canvas = F.fold(cols, (hp, wp), win, stride=lay.core)[:, :, lay.overlap : lay.overlap + h, lay.overlap : lay.overlap + w]
        background, hides, bound = self.hidden(x) if self.cond else m.hidden(x, float(m.contract.max_coc_px))
        out = m.composite(canvas.view(1, 3, 6, h, w), background, (hides, bound)).clamp_min(0.0)
        if not self.cond:
            return m.contract.normalization.encode(out)
        norm = m.contract.normalization  # Normalization.encode without its range check (data-dependent)
        return (out + norm.offset - norm.scale) / (out + norm.offset + norm.scale)

    def decode(self, n: torch.Tensor) -> torch.Tensor:
        """``Normalization.decode``; in cond mode without its range check, a data-dependent branch
        that ``torch.export`` refuses."""
        norm = self.model.contract.normalization
        return norm.scale * (1.0 + n) / (1.0 - n) - norm.offset if self.cond else norm.decode(n)

    def hidden(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``LensBokeh.hidden`` with ``push_pull_fill``'s early return ("no weight at all", a
        data-dependent branch) left out."""
        m, (h, w) = self.model, x.shape[-2:]
        hides = occluders(x[:, 3:] * float(m.contract.coc_scale_px), self.plan.fill_radius_px)
        keep = (~hides).to(x.dtype)
        side = 1 << pyramid_levels(h, w)
        pad = (0, side - w, 0, side - h)
        background = _pull_push(F.pad(self.decode(x[:, :3]), pad), F.pad(keep, pad))[..., :h, :w]
        return background, hides, background  # the surface fill bounded by the estimate itself: the same ops, close enough to time


def _time(fn, repeats: int) -> tuple[float, np.ndarray]:
    out = fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return 1000.0 * statistics.median(times), out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out-dir", type=Path, default=ROOT / "runs" / "bench_traced")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--dynamo", action="store_true", help="also the dynamo exporter with torch.cond per band (onnxscript)")
    p.add_argument("--no-trace", action="store_true", help="leave out the plain traced export (with --dynamo: only the cond one)")
    p.add_argument("--variants", nargs="+", default=["multires:10"], choices=["multires:10", "direct"],
                   help="exports to compare (direct: ~15 min more at 1080p, every band of every tile at full resolution)")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    exports = {"multires:10": "default", "direct": "direct"}
    paths = make_model(args.out_dir, reuse=True, names=tuple(exports[v] for v in args.variants))
    saved = args.out_dir / f"frame_seed{args.seed}.npz"
    if not saved.exists():
        aif, coc_full, _, _ = make_frame(args.seed)
        np.savez(saved, aif=aif, coc=coc_full)
    aif, coc_full = np.load(saved)["aif"], np.load(saved)["coc"]
    frames = {"full": coc_full, "third": coc_full / 3.0,
              "half_in_focus": np.where(np.arange(W)[None, :] < W // 2, 0.0, coc_full)}
    model, _ = load_model(paths["checkpoint"])
    plate = plate_model(model)
    built = {v: OnnxBokeh(paths[exports[v]], threads=args.threads) for v in args.variants}
    diameters = plate.plan(plate.contract.max_coc_px).diameters
    variants = [(v, 10.0 if v == "multires:10" else 0.0) for v in args.variants]
    traced = {}
    for name, min_px in variants:
        mod = TracedPlate(plate, band_scales(diameters, min_px)).eval()
        a0 = torch.zeros(1, 3, H, W)
        c0 = torch.from_numpy((coc_full / plate.contract.coc_scale_px).astype(np.float32))[None, None]
        path = args.out_dir / f"traced_{name.replace(':', '')}.onnx"
        t = time.perf_counter()
        if not args.no_trace:
            with torch.no_grad():
                torch.onnx.export(mod, (a0, c0), str(path), input_names=["aif", "coc"], output_names=["defocus"],
                                  opset_version=18, dynamo=False)
            print(f"traced {name}: exported in {time.perf_counter() - t:.0f} s, {path.stat().st_size / 1e6:.0f} MB", flush=True)
            traced[name] = (mod, make_session(str(path), args.threads))
        if args.dynamo:
            cmod = TracedPlate(plate, band_scales(diameters, min_px), cond=True).eval()
            cpath = args.out_dir / f"cond_{name.replace(':', '')}.onnx"
            on = torch.ones(plate.config.blocks, 2, dtype=torch.bool)
            t = time.perf_counter()
            try:
                with torch.no_grad():
                    prog = torch.onnx.export(cmod, (a0, c0, on), input_names=["aif", "coc", "band_on"],
                                             output_names=["defocus"], opset_version=18, dynamo=True)
                prog.save(str(cpath))
                print(f"cond {name}: exported in {time.perf_counter() - t:.0f} s", flush=True)
                traced["cond " + name] = (cmod, make_session(str(cpath), args.threads))
            except Exception as e:  # noqa: BLE001 - the measurement reports what the exporter could not do
                print(f"cond {name}: the dynamo exporter failed after {time.perf_counter() - t:.0f} s: "
                      f"{type(e).__name__}: {str(e).splitlines()[0][:300]}", flush=True)
    print(f"\n1920x1080, N = {plate.config.blocks}, {plate.layout(H, W).num_tiles} tiles, {args.threads} threads, "
          f"median of {args.repeats}")
    print(f"{'frame':<14} {'graph':<22} {'ms':>8} {'x built':>8} {'vs torch':>9}")
    for frame, coc in frames.items():
        base = {}
        for name, rt in built.items():
            ms, _ = _time(lambda: rt.render_coc(aif, coc), args.repeats)
            base[name] = ms
            print(f"{frame:<14} {'built ' + name:<22} {ms:8.0f} {1.0:8.2f} {'':>9}", flush=True)
        colour, c_in = plate.contract.encode_inputs(np.ascontiguousarray(aif.transpose(2, 0, 1))[None], coc[None, None])
        feeds = {"aif": colour.astype(np.float32), "coc": c_in.astype(np.float32)}
        for name, (mod, sess) in traced.items():
            f = dict(feeds)
            if name.startswith("cond"):
                f["band_on"] = built[args.variants[0]].active_bands(coc[None]).any(axis=0)
            ms, got = _time(lambda: sess.run(["defocus"], f)[0], args.repeats)
            with torch.no_grad():
                want = mod(*(torch.from_numpy(v) for v in f.values())).numpy()
            key = name.split(" ")[-1]
            print(f"{frame:<14} {'traced ' + name:<22} {ms:8.0f} {ms / base[key]:8.2f} {np.abs(got - want).max():9.1e}",
                  flush=True)


if __name__ == "__main__":
    main()

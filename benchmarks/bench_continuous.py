"""Continuous depth: the classical renderers against Mitsuba on non-planar scenes.

    python benchmarks/bench_continuous.py [--size 256 192] [--spp 8192]   (~12 min on 2 cores;
                                         --truth-renders 4 --cases fg: 713 s of
                                         Mitsuba truths, the figure the README quotes)

The scene is :func:`data_tools.mitsuba.scenes.occlusion_scene`: continuous depth everywhere (a
textured sphere, a tilted board and a box in the foreground at 0.8-1.1 m, standing on a floor
that runs back to a textured wall at 3 m), with small HDR highlights on the surfaces. 85 mm
f/1.4 on a 36 mm sensor, disk aperture (Mitsuba's thin-lens sensor). Two cases:

* ``fg blurred``: focus on the wall, the foreground blurred (CoC down to -47 px at 256 px)
  must spill over the sharp wall;
* ``bg blurred``: focus on the sphere, the background blurred behind a sharp foreground.

For each case the script renders Mitsuba's thin-lens defocus (the truth; the AIF and planar
depth once), then feeds the AIF + CoC to identity, the CoC Gaussian, the naive gather and the
scatter with the true aperture, and prints linear / sRGB PSNR and seconds. ``--network`` adds
the lens network, untrained, given the scene's own lens, with the hidden-background fill and the
far-light fill (at its starting gain); ``--network-options K=V[,K=V] ...`` adds a row per spec
with those ``ModelConfig`` fields changed; ``--fill-from CKPT ...`` a row per trained network with
the fill it learned, and one with its occlusion-margin factor left at 1. ``--save DIR`` keeps the
AIF, the depth and the truths; ``--load DIR`` scores against them without Mitsuba (seconds
instead of minutes).

Overscan (``--overscan M``, default 24 px, half the largest CoC): the truth, the AIF and the depth
are rendered M px wider on every side (the same scene, camera and pixel pitch) and every method
gets the wider AIF + CoC; scores are taken on the original frame. Without it, the blur that
spills into the frame from outside it (the floor closest to the camera has a 47 px CoC) is
unknown to every method and dominates their errors at the frame's edge (``--overscan 0``
measures that too).

The truth is a Monte-Carlo estimate, and its noise caps every PSNR: differences between good
methods shrink. ``--truth-renders K`` (K >= 2) renders it K times with independent seeds,
scores against their mean, and adds a column: the linear PSNR against the *noise-free* image,
estimated without bias by subtracting the mean's noise variance (the per-pixel sample variance
of the K renders over K) from the mean squared error. The noise narrows the margins between
good methods: the scatter's lead over the Gaussian on the blurred foreground reads +2.94 dB with
K = 2 and +3.01 with K = 4 (noise-free +3.17 and +3.12). Scatter rows: the
default (``occlusion="surface"``, ``fill="background"``, ``coc_step`` 0.5, ``jump_px`` 4),
``fill="normalize"``, the old default (``occlusion="over"``, normalising) and the Gaussian
with it, then ``jump_px`` and ``coc_step`` sweeps: the defaults were chosen from these rows.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch

from data_tools.mitsuba.render import mitsuba_defocus, render_aif, render_depth
from data_tools.mitsuba.scenes import OCCLUSION_FG_FOCUS_M, OCCLUSION_WALL_M, axis_camera, occlusion_scene
from data_tools.mitsuba.variant import activate
from neuralbokeh.core.apertures import ApertureModel, Gaussian
from neuralbokeh.core.optics import ThinLens
from neuralbokeh.evaluation.metrics import image_metrics
from neuralbokeh.render import scatter_defocus
from neuralbokeh.render.baselines import gather_defocus, gaussian_defocus


def methods(aperture: ApertureModel, steps: list[float], jumps: list[float]) -> dict:
    def t(fn):
        def run(aif: np.ndarray, coc: np.ndarray) -> np.ndarray:
            x = torch.from_numpy(aif.transpose(2, 0, 1).copy())[None]
            return fn(x, torch.from_numpy(coc)[None, None])[0].numpy().transpose(1, 2, 0)
        return run

    out = {"identity": lambda a, c: a, "gaussian": t(gaussian_defocus), "gather": t(lambda x, c: gather_defocus(x, c, aperture))}
    out["scatter (default)"] = t(lambda x, c: scatter_defocus(x, c, aperture))
    out["scatter fill=normalize"] = t(lambda x, c: scatter_defocus(x, c, aperture, fill="normalize"))
    out["scatter over+norm 0.5"] = t(lambda x, c: scatter_defocus(x, c, aperture, occlusion="over", fill="normalize"))
    out["gaussian over+norm"] = t(lambda x, c: scatter_defocus(x, c, ApertureModel(Gaussian(0.5)), occlusion="over", fill="normalize"))
    for j in jumps:
        out[f"scatter jump {j:g}"] = t(lambda x, c, j=j: scatter_defocus(x, c, aperture, jump_px=j))
    for s in steps:
        out[f"scatter step {s:g}"] = t(lambda x, c, s=s: scatter_defocus(x, c, aperture, coc_step=s))
    return out


# what a trained network's fill is: its config fields and the parameters it learns
FILL_FIELDS = ("fill", "surface_fill", "occlusion_margin_px", "occlusion_margin_rel", "occlusion_margin_learned",
               "occlusion_margin_step", "occlusion_margin_slope", "occlusion_source_coc")
FILL_PARAMETERS = ("fill_gain", "surface_fill", "margin_scale")


def network_rows(aperture: ApertureModel, lens: ThinLens, size: tuple[int, int], max_coc_px: float,
                 variants: list[str], fill_from: Sequence[Path] = ()) -> dict:
    """The lens network, untrained, given the scene's own lens (``pupil_init = "aperture"``, no
    cat-eye: Mitsuba's thin lens has none), with the hidden-background fill and with the
    far-light fill at its starting gain (1): what each fill rule does where a blurred foreground
    uncovers the wall, before any training moves the gain. Each of ``variants`` (``KEY=VALUE``
    ModelConfig fields, comma-separated) adds a row with the background fill and those fields.
    Each of ``fill_from`` (trained checkpoints) adds a row with that network's fill settings and
    the fill parameters it learned (far-light gain, surface-fill share, occlusion-margin factor),
    the rest as the other rows: the learned fill on a scene and lens it was not trained on; and,
    where it learned a margin factor, a second row (", margin x1") with that factor at its start."""
    from bench_options import parse_option

    from neuralbokeh.checkpoint import load_checkpoint
    from neuralbokeh.core.contract import Contract
    from neuralbokeh.core.normalization import Normalization
    from neuralbokeh.networks import ModelConfig, build_model

    h, w = size
    overlap = int(np.ceil(max_coc_px / 2.0)) + 4
    contract = Contract(h, w, Normalization(0.18), max_coc_px, max_coc_px, lens, aperture.to_dict())
    rows = {}
    configs = {f"network, fill {fill}": {"fill": fill} for fill in ("background", "far_light")}
    configs |= {f"network, {spec}": dict(parse_option(o) for o in spec.split(",")) for spec in variants}
    learned = {}  # row -> (checkpoint, the fill parameters it learned, those left at their start)
    for path in fill_from:
        ck = load_checkpoint(path)
        run_name = "/".join(path.parent.parts[-2:])
        state = {k: v for k, v in ck["model_state"].items() if k in FILL_PARAMETERS}
        base_row = f"network, the fill {run_name} learned"
        rows_of = {base_row: ()}
        if "margin_scale" in state:
            # the margin factor is how far apart in CoC one surface may be in the training data's
            # depth: a second row keeps it at 1, to tell the fill's own parameters from it
            rows_of[f"{base_row}, margin x1"] = ("margin_scale",)
        for row, start in rows_of.items():
            learned[row] = path, {k: v for k, v in state.items() if k not in start}, start
            trained = ModelConfig.from_dict(ck["model_config"])  # a key the checkpoint predates: what it meant then
            configs[row] = {k: getattr(trained, k) for k in FILL_FIELDS}
    for name, options in configs.items():
        base = {"tile": 2 * overlap, "overlap": overlap, "pupil_init": "aperture", "vignetting": False}
        cfg = ModelConfig(**base | options).resolved(max_coc_px)
        model = build_model(cfg, contract)
        if name in learned:
            path, state, start = learned[name]
            missing = sorted(set(state) ^ {k for k in FILL_PARAMETERS if getattr(model, k) is not None and k not in start})
            if missing:
                raise ValueError(f"--fill-from {path}: fill parameters {missing} are in only one of the checkpoint and its network")
            model.load_state_dict(state, strict=False)
        model = model.eval().double()

        def run(aif: np.ndarray, coc: np.ndarray, model=model) -> np.ndarray:
            x = torch.from_numpy(aif.transpose(2, 0, 1).copy())[None].double()
            with torch.no_grad():
                out = contract.apply(model, x, torch.from_numpy(coc)[None, None].double())
            return out[0].clamp_min(0.0).numpy().transpose(1, 2, 0)
        rows[f"{name} (N {cfg.blocks})"] = run
    return rows


def arguments() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", type=int, nargs=2, default=(256, 192))
    p.add_argument("--spp", type=int, default=8192, help="samples per pixel of the Mitsuba defocus (the truth)")
    p.add_argument("--steps", type=float, nargs="*", default=[0.25, 1.0, 2.0], help="coc_step sweep (none: skip)")
    p.add_argument("--jumps", type=float, nargs="*", default=[1.0, 2.0, 8.0], help="jump_px sweep (none: skip)")
    p.add_argument("--cases", nargs="+", choices=["fg", "bg"], default=["fg", "bg"], help="blurred foreground, blurred background")
    p.add_argument("--overscan", type=int, default=24, help="px rendered beyond the frame on every side and given to every method")
    p.add_argument("--truth-renders", type=int, default=1, help="independent truth renders (>= 2: noise-corrected PSNR column)")
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--network", action="store_true", help="add the untrained lens network with each fill (the scene's own lens)")
    p.add_argument("--network-options", nargs="*", default=[], metavar="K=V[,K=V]",
                   help="with --network: one more network row per spec, these ModelConfig fields changed")
    p.add_argument("--fill-from", type=Path, nargs="*", default=[], metavar="CKPT",
                   help="with --network: two more rows per trained checkpoint, with the fill it learned (gain, share, margin; margin x1)")
    p.add_argument("--variant", default=None)
    p.add_argument("--load", type=Path, default=None, help="a --save folder: its AIF, depth and truths instead of Mitsuba")
    p.add_argument("--save", type=Path, default=None, help="folder to write the AIF and the truths to (EXR)")
    args = p.parse_args()
    if args.fill_from and not args.network:
        p.error("--fill-from adds a network row: give --network too")
    for path in args.fill_from:
        if not path.is_file():
            p.error(f"--fill-from {path}: no such checkpoint file")
    if args.save:  # before minutes of Mitsuba: a folder that cannot be made is said now
        try:
            args.save.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            p.error(f"--save {args.save}: cannot make the folder ({e.strerror})")
    return args


def inputs(args: argparse.Namespace, lens: ThinLens, aperture: ApertureModel) -> tuple[np.ndarray, np.ndarray, Callable]:
    """The AIF and depth with the overscan, and ``truths(case, focus)``: the list of truth renders
    (cropped to the frame), from ``--load`` or from Mitsuba."""
    w, h = args.size
    m = args.overscan
    if args.load:
        from neuralbokeh.core.io import read_image

        print(f"{args.load}: its AIF, depth and truths; {w}x{h} (+{m} px overscan), 85 mm f/1.4, disk")

        def truths(case: str, focus: float) -> list[np.ndarray]:
            return [read_image(f) for f in sorted(args.load.glob(f"{case.replace(' ', '_')}_truth_*.exr"))]
        return read_image(args.load / "aif.exr"), np.load(args.load / "depth.npy"), truths
    mi = activate(args.variant)
    desc = occlusion_scene(mi, axis_camera(mi, 85.0, 36.0, w, h), args.seed)  # the scene is placed for the frame itself
    cam = axis_camera(mi, 85.0, lens.sensor_width_mm, w + 2 * m, h + 2 * m)
    scene = mi.load_dict(desc)
    aif, depth = render_aif(mi, scene, cam, 1024), render_depth(mi, scene, cam)
    print(f"mitsuba {mi.__version__} {mi.variant()}; {w}x{h} (+{m} px overscan), 85 mm f/1.4, disk; truth {args.spp} spp thin-lens")

    def truths(case: str, focus: float) -> list[np.ndarray]:
        return [mitsuba_defocus(mi, scene, cam, lens, aperture, focus, args.spp, seed=17 + i).image[m:m + h, m:m + w]
                for i in range(args.truth_renders)]
    return aif, depth, truths


def score(table: dict, aif: np.ndarray, coc: np.ndarray, renders: list[np.ndarray], crop: tuple[slice, slice]) -> None:
    """Print each method's linear / sRGB PSNR and seconds against the mean of ``renders`` (and, for
    two or more, the linear PSNR against the noise-free image, estimated from their spread)."""
    truth = np.mean(renders, axis=0)
    peak = float(truth.max()) or 1.0
    # the variance of the mean's noise, per pixel, in peak-normalised linear units
    noise = float(np.mean(np.var(np.stack(renders) / peak, axis=0, ddof=1) / len(renders))) if len(renders) > 1 else None
    if noise:
        print(f"its own noise caps linear PSNR at {-10 * np.log10(noise):.2f} dB")
    print(f"{'method':<44} {'PSNR lin':>9} {'PSNR sRGB':>10} {'seconds':>8}" + (f" {'lin, noise-free est.':>21}" if noise else ""))
    for name, fn in table.items():
        t0 = time.perf_counter()
        pred = np.asarray(fn(aif, coc))[crop]
        sec = time.perf_counter() - t0
        q = image_metrics(pred, truth)
        extra = ""
        if noise:
            mse = float(np.mean((pred.astype(np.float64) / peak - truth / peak) ** 2)) - noise
            extra = f" {-10 * np.log10(mse):>21.2f}" if mse > 0 else f" {'(below the noise)':>21}"
        print(f"{name:<44} {q['psnr_linear']:>9.2f} {q['psnr_srgb']:>10.2f} {sec:>8.2f}{extra}", flush=True)


def main() -> None:
    args = arguments()
    w, h = args.size
    m = args.overscan
    # the same pixel pitch over a film M px wider on every side: the frame is its centre crop
    lens = ThinLens(85.0, 1.4, 36.0 * (w + 2 * m) / w)
    crop = (slice(m, m + h), slice(m, m + w))
    cases = {"fg": ("fg blurred", OCCLUSION_WALL_M), "bg": ("bg blurred", OCCLUSION_FG_FOCUS_M)}
    aperture = ApertureModel()
    aif, depth, truths = inputs(args, lens, aperture)
    table = methods(aperture, args.steps, args.jumps)
    if args.network:
        coc_max = max(float(np.abs(lens.coc_px(depth, f, w + 2 * m, signed=True)).max()) for f in (OCCLUSION_WALL_M, OCCLUSION_FG_FOCUS_M))
        table |= network_rows(aperture, lens, (h + 2 * m, w + 2 * m), coc_max, args.network_options, args.fill_from)
    if args.save:
        from neuralbokeh.core.io import write_image

        write_image(args.save / "aif.exr", aif)  # with the overscan
        np.save(args.save / "depth.npy", depth)
    for case, focus in (cases[c] for c in args.cases):
        coc = lens.coc_px(depth, focus, w + 2 * m, signed=True)
        t0 = time.perf_counter()
        renders = truths(case, focus)
        print(f"\n{case}: focus {focus} m, CoC {coc[crop].min():.1f} .. {coc[crop].max():.1f} px, truth ({len(renders)} x {args.spp} spp) "
              f"in {time.perf_counter() - t0:.0f} s")
        if args.save:
            for i, r in enumerate(renders):
                write_image(args.save / f"{case.replace(' ', '_')}_truth_{i}.exr", r)
        score(table, aif, coc, renders, crop)


if __name__ == "__main__":
    main()

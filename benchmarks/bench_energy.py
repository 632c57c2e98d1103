"""Where the light of highlights goes at depth edges: which of the occlusion buckets' margin, the
sum-to-saturation or the fill gains or loses it, on a Mitsuba set's held-out split.

    python benchmarks/bench_energy.py [--data data/mitsuba_lens] [--tile 32 --overlap 16]
    python benchmarks/bench_energy.py --data runs/lightfield_learned/test --split all   # the light field's held-out quadrant

The data: ``benchmarks/mitsuba_learned.py``'s set (render it with that script first; a square
frame, a declared aperture), or any such folder, e.g. ``benchmarks/lightfield_learned.py``'s
held-out quadrant (``--split all``: every scene of the folder). Nothing is trained, so the lens
is known: the untrained lens network given the data's own aperture (``pupil_init =
"aperture"``, its cat-eye set from the declared one) and the exact-aperture scatter (the
oracle), each as it is and with one of its parts changed, and the light-field patent's buckets
with the same aperture:

* the buckets' ``occlusion_margin_px`` at 1 and 4 px (default 2);
* ``"over"``: near light hides what lies behind it in proportion to its coverage (the layered
  "over"), instead of sum-to-saturation (visible light fills the room the nearer light leaves);
* the fill: ``fill = "normalize"``, ``"far_light"`` (at its starting gain, 1), and the fill
  before 2026-12-03 (occluders only at 4 px steps within the blur's reach, the pull-push of the
  light itself, each visible pixel its own sharp value).

``--network-options K=V[,K=V] ...`` adds a network row per spec with those ``ModelConfig`` fields
changed (e.g. ``near_focus_px=0``: the band lattice uniform in the CoC).

Printed per row: held-out linear PSNR (both images divided by the truth's peak, the
evaluation's ``psnr_linear``), and around the highlights (AIF pixels brighter than 20x the
frame's median, grown by the largest CoC radius) the ratio of the rendered to the true light:
mean, min and max over the samples that have highlights.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from neuralbokeh.data.dataset import FocalStackDataset  # noqa: E402
from neuralbokeh.networks import ModelConfig, build_model  # noqa: E402
from neuralbokeh.networks.lens import LensBokeh  # noqa: E402
from neuralbokeh.ops import holes  # noqa: E402
from neuralbokeh.render import scatter_defocus  # noqa: E402
from neuralbokeh.render.buckets import bucket_gather  # noqa: E402
from neuralbokeh.training.loop import Samples, oracle_apertures  # noqa: E402


def fill_before(aif: torch.Tensor, coc: torch.Tensor, jump_px: float = 4.0, radius_px: int | None = None) -> torch.Tensor:
    """The hidden-background fill as it was: occluders at ``jump_px`` steps only, the pull-push
    of the linear light, every visible pixel its own value."""
    if radius_px is None:
        radius_px = math.ceil(float(coc.abs().max()) / 2.0) if coc.numel() else 0
    keep = (~holes.occluders(coc, radius_px, jump_px)).to(aif.dtype)
    return holes.push_pull_fill(aif, keep)


def estimate_before(aif: torch.Tensor, coc: torch.Tensor, jump_px: float = 4.0, radius_px: int | None = None,
                    step_px: float = 1.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`fill_before` where the network reads ``ops.holes.hidden_estimate``, with no bound
    on the surface fill (the AIF) and its occluders as the pixels that hide something."""
    if radius_px is None:
        radius_px = math.ceil(float(coc.abs().max()) / 2.0) if coc.numel() else 0
    return fill_before(aif, coc, jump_px, radius_px), aif, holes.occluders(coc, radius_px, jump_px)


def composite_over(self: LensBokeh, acc: torch.Tensor, background: torch.Tensor | None = None,
                   surface: object = None) -> torch.Tensor:
    """Near light over the rest (same + far, summed, at most one coverage), in proportion to the
    near coverage, then the fill (``surface``, the surface fill's inputs, unused): the layered
    "over" in place of sum-to-saturation."""
    color, cover = acc[:, :, :3], acc[:, :, 3:].clamp_min(0.0)
    near = cover[:, 0].clamp(max=1.0)
    rest_c, rest_a = color[:, 1] + color[:, 2], cover[:, 1] + cover[:, 2]
    out = color[:, 0] / cover[:, 0].clamp_min(1.0) + (1.0 - near) * rest_c / rest_a.clamp_min(1.0)
    taken = near + (1.0 - near) * rest_a.clamp(max=1.0)
    return out + (1.0 - taken).clamp_min(0.0) * background


class Patched:
    """Replace ``obj.name`` by ``value`` for a ``with`` block."""

    def __init__(self, *patches: tuple[object, str, object]) -> None:
        self.patches, self.saved = patches, []

    def __enter__(self) -> None:
        self.saved = [(obj, name, getattr(obj, name)) for obj, name, _ in self.patches]
        for obj, name, value in self.patches:
            setattr(obj, name, value)

    def __exit__(self, *exc: object) -> None:
        for obj, name, value in self.saved:
            setattr(obj, name, value)


def _network(ds: FocalStackDataset, args: argparse.Namespace, **overrides: object) -> LensBokeh:
    cfg = ModelConfig(**{"tile": args.tile, "overlap": args.overlap, "pupil_init": "aperture"} | overrides).resolved(ds.max_coc_px)
    model = build_model(cfg, ds.contract()).eval()
    aperture = ds.contract().aperture
    with torch.no_grad():  # the data's cat-eye on a square frame: the corner (1, 1) is the lens model's field (1, 1) / sqrt 2
        shift = float(aperture["cat_eye"]) / math.sqrt(2.0)
        model.vignette.copy_(torch.tensor([shift, shift, math.log(float(aperture["vignetting_radius"]))]))
    return model


def _rows(ds: FocalStackDataset, args: argparse.Namespace) -> dict[str, Callable]:
    norm = ds.normalization
    from bench_options import parse_option

    extra = {f"network, {spec}": dict(parse_option(o) for o in spec.split(",")) for spec in args.network_options}
    nets = {name: _network(ds, args, **kw) for name, kw in (*extra.items(),
        ("default", {}), ("margin 1", {"occlusion_margin_px": 1.0}), ("margin 4", {"occlusion_margin_px": 4.0}),
        ("normalize", {"fill": "normalize"}), ("far light", {"fill": "far_light"}), ("hermite", {"band_blend": "hermite"}),
        ("far light, hermite", {"fill": "far_light", "band_blend": "hermite"}))}
    exact = oracle_apertures(ds)

    def net(name: str, *patches: tuple[object, str, object]) -> Callable:
        def run(x, window, lin, coc, i):
            with Patched(*patches), torch.no_grad():
                return norm.decode(nets[name](x, window).double()).clamp_min(0.0)
        return run

    def oracle(*patches: tuple[object, str, object], **kw: object) -> Callable:
        def run(x, window, lin, coc, i):
            with Patched(*patches):
                return scatter_defocus(lin, coc, exact[ds.items[i][0]], **kw)
        return run

    old_fill = ((sys.modules[scatter_defocus.__module__], "hidden_background", fill_before),
                (sys.modules[LensBokeh.__module__], "hidden_estimate", estimate_before))
    return {
        "network": net("default"),
        "network, margin 1 px": net("margin 1"),
        "network, margin 4 px": net("margin 4"),
        "network, over": net("default", (LensBokeh, "composite", composite_over)),
        "network, fill normalize": net("normalize"),
        "network, fill before": net("default", *old_fill),
        "network, fill far_light": net("far light"),
        "network, hermite blend": net("hermite"),
        "network, far_light, hermite": net("far light, hermite"),
        **{name: net(name) for name in extra},
        "oracle": oracle(),
        "oracle, over": oracle(occlusion="over"),
        "oracle, fill normalize": oracle(fill="normalize"),
        "oracle, fill before": oracle(*old_fill),
        "buckets (exact aperture)": lambda x, window, lin, coc, i: bucket_gather(lin, coc, exact[ds.items[i][0]]),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=ROOT / "data" / "mitsuba_lens")
    p.add_argument("--test-fraction", type=float, default=0.25)
    p.add_argument("--split", choices=("test", "all"), default="test", help="'all': every scene of --data (a folder of held-out scenes)")
    p.add_argument("--tile", type=int, default=32)
    p.add_argument("--overlap", type=int, default=16)
    p.add_argument("--network-options", nargs="*", default=[], metavar="K=V[,K=V]",
                   help="one more network row per spec, these ModelConfig fields changed")
    args = p.parse_args()
    torch.set_num_threads(2)
    ds = FocalStackDataset([args.data], args.split, args.test_fraction, 0)
    if ds.contract().aperture is None or ds.contract().size[0] != ds.contract().size[1]:
        raise SystemExit(f"{args.data}: needs square frames with a declared aperture (mitsuba_learned.py's set)")
    samples, norm, scale = Samples(ds, cache=False), ds.normalization, ds.coc_scale_px
    rows = _rows(ds, args)
    scores: dict[str, list[tuple[float, float]]] = {name: [] for name in rows}
    for i in range(len(ds)):
        x, y, _, window, _ = samples.batch([i], torch.device("cpu"))
        lin, coc = norm.decode(x[:, :3].double()).clamp_min(0.0), x[:, 3:].double() * scale
        truth = norm.decode(y.double()).clamp_min(0.0)
        lum = lin.mean(1, keepdim=True)
        r = math.ceil(float(coc.abs().max()) / 2.0)
        near_light = (F.max_pool2d((lum > 20.0 * lum.median()).double(), 2 * r + 1, 1, r) > 0).expand_as(truth)
        for name, run in rows.items():
            pred = run(x, window, lin, coc, i)
            mse = float(((pred - truth) / truth.max()).pow(2).mean())
            ratio = float(pred[near_light].sum() / truth[near_light].sum()) if near_light.any() else float("nan")
            scores[name].append((10.0 * math.log10(1.0 / mse), ratio))
    print(f"{args.data}: {len(ds)} held-out samples, tiles {args.tile} + {args.overlap} px")
    print(f"{'row':28s} {'linear PSNR':>11s}   light near highlights / truth: mean (min .. max)")
    for name, vals in scores.items():
        a = np.array(vals)
        ratio = a[:, 1][~np.isnan(a[:, 1])]
        flux = f"{ratio.mean():.3f} ({ratio.min():.3f} .. {ratio.max():.3f}), {len(ratio)} samples" if len(ratio) else "-"
        print(f"{name:28s} {a[:, 0].mean():11.2f}   {flux}")


if __name__ == "__main__":
    main()

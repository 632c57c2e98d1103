"""What a model option costs a 1080p render: the untrained prior of ``bench_runtime.py`` (N = 22,
240 + 24 px tiles, a 7-blade aperture) with one ``ModelConfig`` option changed, against the prior
as it is, each through its default export (``multires:10``), in one process, renders alternating.

    python benchmarks/bench_options.py [--options band_blend=hermite fill=far_light near_focus_px=4,blocks=22] [--repeats 7] [--reuse]
        [--files NAME=PATH.onnx ...]

About 12 minutes on 2 cores, most of it the exports' parity checks. The frames are
``bench_runtime.py``'s procedural 1920x1080 frame (largest |CoC| 40 px), a third of its CoC and
its left half in focus. Printed per frame: the median ms of each file (the renders alternate, so
a drift of the machine's speed hits all alike) and each option's ratio to the prior as it is:
the ratio of the medians, and the median and quartiles of the ratios within each round.
The run time does not depend on the weights, so an untrained prior times what a trained model
with the option costs. ``--files`` times other exports of the same prior and frames beside them
(e.g. ``prior_default.onnx`` of an earlier commit's run: what the code's changes since cost).
"""

from __future__ import annotations

import argparse
import re
import statistics
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_runtime import H, W, _frames, alternating_times, make_model  # noqa: E402

from neuralbokeh.runtime.onnx_model import OnnxBokeh  # noqa: E402


def parse_option(spec: str) -> tuple[str, object]:
    """``KEY=VALUE`` -> (key, value as an int, float, true / false or else the string)."""
    key, sep, value = spec.partition("=")
    if not sep or not key or not value:
        raise SystemExit(f"error: an option is KEY=VALUE (a ModelConfig field), got {spec!r}")
    if value in ("true", "false"):
        return key, value == "true"
    for kind in (int, float):
        try:
            return key, kind(value)
        except ValueError:
            pass
    return key, value


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--options", nargs="+", default=["band_blend=hermite", "fill=far_light"], metavar="K=V[,K=V]",
                   help="ModelConfig options (comma-separated fields change together), each spec timed against the prior as it is")
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--out-dir", type=Path, default=ROOT / "runs" / "bench_options")
    p.add_argument("--reuse", action="store_true", help="keep the exports of an earlier run")
    p.add_argument("--files", nargs="*", default=[], metavar="NAME=PATH",
                   help="other 1920x1080 exports of the prior (an earlier commit's) timed beside the options")
    args = p.parse_args()
    variants = {"prior": {}} | {spec: dict(parse_option(o) for o in spec.split(",")) for spec in args.options}
    extra = dict(spec.partition("=")[::2] for spec in args.files)
    for name, path in extra.items():
        if not name or name in variants or not Path(path).is_file():
            raise SystemExit(f"error: --files takes NAME=PATH, a new name and an existing .onnx file, got {name}={path}")
    args.out_dir.mkdir(parents=True, exist_ok=True)
    frames, _ = _frames(args, H, W, 40.0)
    files = {}
    for name, options in variants.items():  # files named by their options: --reuse finds each one's own
        tag = re.sub(r"[^A-Za-z0-9.]+", "_", name) + "_"
        files[name] = make_model(args.out_dir, args.reuse, ("default",), tag=tag, options=options)["default"]
    files |= {name: Path(path) for name, path in extra.items()}
    models = {name: OnnxBokeh(path, threads=args.threads) for name, path in files.items()}
    print(f"{'frame':16s} " + " ".join(f"{name + ' ms':>22s}" for name in models)
          + "   ratios to the prior: of the medians; the median [quartiles] of each round's")
    for frame, path in frames.items():
        z = np.load(path)
        times, _ = alternating_times(models, z["aif"], z["coc"], args.repeats)
        med = {name: statistics.median(v) for name, v in times.items()}
        ratios = "  ".join(f"{name}: {med[name] / med['prior']:.2f}x; {_round_ratios(times[name], times['prior'])}"
                           for name in models if name != "prior")
        print(f"{frame:16s} " + " ".join(f"{med[name]:22.0f}" for name in models) + f"   {ratios}", flush=True)


def _round_ratios(times: list[float], prior: list[float]) -> str:
    """The median and quartiles of each round's ratio: a render and the prior's of the same round
    share the machine's state, so on a machine whose speed wanders this is the steadier figure."""
    q1, q2, q3 = statistics.quantiles([t / p for t, p in zip(times, prior)], n=4)
    return f"{q2:.3f}x [{q1:.3f}, {q3:.3f}]"


if __name__ == "__main__":
    main()

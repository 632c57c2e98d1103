"""The learned lens on real light-field defocus that no renderer of ours made (the HCI scene).

    python benchmarks/lightfield_learned.py [--minutes 8] [--aperture polygon:6] [--mitsuba-scenes 4] [KEY=VALUE ...]

1. Cuts the shared HCI light field (``../shared/data/light_fields/hci_backgammon``, 9 x 9 views
   of 512 x 512) into its four 256 x 256 quadrants and writes each as a scene with
   ``data_tools.lightfield`` (4 focus settings uniform between the 2nd and 98th disparity
   percentile of the whole scene, one disparity-to-depth mapping so the quadrants share one
   lens). With ``--aperture``
   the views are weighted by that shape (the oracle row is then the scatter with that exact
   discrete aperture); ``--aperture none`` uses every view and declares no aperture.
   ``--mitsuba-scenes`` procedural scenes are rendered as 9 x 9 light fields by
   ``data_tools.mitsuba --light-field 9`` (256 x 256, a different image formation: path-traced
   pinhole views) and written through the same tool, with the same disparity-to-depth mapping
   and aperture, so that every scene shares one (virtual) lens.
2. Trains the default network (``configs/quickstart.toml`` with 32 + 16 px tiles: the overlap
   reaches the data's largest CoC radius, ~9 px; and ``model.pixel_blur``: a refocus splats each
   view bilinearly, a blur the area raster lacks; then the ``KEY=VALUE`` overrides) on three
   quadrants and the Mitsuba light fields for ``--minutes``.
3. Evaluates on the fourth quadrant (``--test-quadrant``, default the bottom right), next to every
   classical baseline of ``neuralbokeh.evaluation``: linear and sRGB PSNR, SSIM, HDR-FLIP, ms/MP.
4. Draws the learned pupils (sensor centre, right edge, top-right corner) next to the views'
   exact discrete aperture (``neuralbokeh.evaluation.pupils``): ``--work``/report/pupils.png.

What is held out: a quarter of the image, never seen in training, at the same four focus
settings. It shares the scene's lighting and materials with the training quadrants, and its
defocus comes from the same views; it is content the network has not fitted, not another
camera. The data's licence (CC BY-NC-SA 4.0) keeps it out of the repository: the datasets and
runs are written under ``--work`` only.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
HCI = ROOT.parent / "shared" / "data" / "light_fields" / "hci_backgammon"
QUADRANTS = {"tl": (0, 0), "tr": (0, 256), "bl": (256, 0), "br": (256, 256)}


def run(*args: str) -> None:
    print("$", " ".join(args), flush=True)
    subprocess.run([sys.executable, *args], check=True, cwd=ROOT)


def make_datasets(work: Path, aperture: str, test: str) -> None:
    sys.path.insert(0, str(ROOT))
    from data_tools.lightfield import lens_for_disparity, load_disparity, load_views

    views, disparity = load_views(HCI), load_disparity(HCI / "gt_disp_lowres.pfm")
    _, alpha, beta = lens_for_disparity(disparity, 9, 256, (1.0, 3.0))
    (work / "mapping.txt").write_text(f"{alpha!r} {beta!r}\n")
    focus = ",".join(f"{d:.4f}" for d in np.linspace(*np.percentile(disparity, [2, 98]), 4))
    for name, (y, x) in QUADRANTS.items():
        np.save(work / f"{name}_views.npy", views[:, :, y:y + 256, x:x + 256])
        np.save(work / f"{name}_disp.npy", disparity[y:y + 256, x:x + 256])
        out = work / ("test" if name == test else "train")
        args = ["-m", "data_tools.lightfield", str(work / f"{name}_views.npy"), "--disparity", str(work / f"{name}_disp.npy"),
                "--out", str(out), "--name", name, f"--focus-disparities={focus}", "--disparity-to-depth", str(alpha), str(beta)]
        run(*args, *([] if aperture == "none" else ["--aperture", aperture]))


def mitsuba_scenes(work: Path, count: int, aperture: str, spp: int) -> None:
    """``count`` Mitsuba light fields into the training set, through the same tool and mapping."""
    if count == 0:
        return
    run("-m", "data_tools.mitsuba", "--out", str(work / "mitsuba_lf"), "--scenes", str(count), "--size", "256", "256",
        "--light-field", "9", "--spp", str(spp), "--f-number", "1.4", "--seed", "11")
    mapping = (work / "mapping.txt").read_text().split()
    for folder in sorted((work / "mitsuba_lf").glob("lf_*")):
        args = ["-m", "data_tools.lightfield", str(folder), "--pattern", "view_{:03d}.exr", "--disparity",
                str(folder / "disparity.exr"), "--transfer", "linear", "--out", str(work / "train"), "--name",
                f"mitsuba_{folder.name}", "--signs", "-1", "-1", "--disparity-to-depth", *mapping]
        run(*args, *([] if aperture == "none" else ["--aperture", aperture]))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--minutes", type=float, default=8.0, help="training time")
    p.add_argument("--aperture", default="polygon:6", help="a synthetic aperture for the views, or 'none'")
    p.add_argument("--mitsuba-scenes", type=int, default=4, help="Mitsuba light fields added to the training set")
    p.add_argument("--spp", type=int, default=16, help="samples per pixel of each Mitsuba view")
    p.add_argument("--test-quadrant", choices=tuple(QUADRANTS), default="br")
    p.add_argument("--work", type=Path, default=ROOT / "runs" / "lightfield_learned", help="datasets, run and report")
    p.add_argument("overrides", nargs="*", metavar="KEY=VALUE", help="training config overrides (e.g. model.blocks=40)")
    args = p.parse_args()
    if not HCI.is_dir():
        raise SystemExit(f"error: the HCI light field is not at {HCI} (only the project's machines have it)")
    shutil.rmtree(args.work, ignore_errors=True)
    args.work.mkdir(parents=True)
    make_datasets(args.work, args.aperture, args.test_quadrant)
    mitsuba_scenes(args.work, args.mitsuba_scenes, args.aperture, args.spp)
    run("train.py", "configs/quickstart.toml", "--overwrite", f"data.roots=['{args.work / 'train'}']", "data.test_fraction=0.0",
        "data.cache=true", "model.tile=32", "model.overlap=16", "train.steps=1000000", "train.lr_schedule='constant'",
        "train.eval_every=1000000", "train.checkpoint_every=200", f"train.out_dir='{args.work / 'run'}'", "model.pixel_blur=true",
        *args.overrides,
        "--time-limit", str(args.minutes))
    run("-m", "neuralbokeh.evaluation", "--data", str(args.work / "test"), "--split", "all", "--models",
        str(args.work / "run" / "checkpoint.pt"), "--baselines", "all", "--repeats", "1", "--out", str(args.work / "report"))
    run("-m", "neuralbokeh.evaluation.pupils", str(args.work / "run" / "checkpoint.pt"), "--out",
        str(args.work / "report" / "pupils.png"), "--scene", str(args.work / "test" / args.test_quadrant))
    print((args.work / "report" / "report.md").read_text())


if __name__ == "__main__":
    main()

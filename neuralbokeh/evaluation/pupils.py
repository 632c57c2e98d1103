"""What a lens network learned, as a picture: its pupils across the sensor next to a known aperture.

    python -m neuralbokeh.evaluation.pupils CHECKPOINT --out pupils.png [--scene SCENE_DIR | --aperture SPEC] [--overwrite]

One panel per place on the sensor (the centre, the middle of the right edge, the top-right
corner by default): the learned transmission behind the focus plane (in front it is the same,
point-reflected), i.e. the bokeh of a point light there as it lands in the image, each colour
channel in its own channel, scaled to its brightest value (a PNG holds the transmission x 255,
not sRGB-encoded light). The reference panel on the left is
the aperture the data declares (``--scene``: the ``scene.json`` of a scene, e.g. a light field's
exact view-grid aperture) or ``--aperture SPEC`` (``polygon:7``, ``disk``, ...), rasterised on
the same grid, without vignetting; the log then gives the centre pupil's distance from it
(:func:`pupil_distance`: where no cat-eye clips the pupil, its shape and size in one number).
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from ..checkpoint import load_model
from ..core.apertures import Aperture, ApertureModel, ViewGrid
from ..core.apertures.spec import parse_aperture
from ..core.cli import HelpFormatter
from ..core.io import prepare_output, read_json, write_image
from ..networks.lens import PUPIL_EXTENT, LensBokeh, prior_transmission, pupil_step

log = logging.getLogger(__name__)

# (label, sensor position (x, y) in [-1, 1], the left / top edge at -1)
PLACES = (("centre", (0.0, 0.0)), ("right edge", (1.0, 0.0)), ("top-right corner", (1.0, -1.0)))


def learned_pupils(model: LensBokeh, places: Sequence[tuple[float, float]] = tuple(p for _, p in PLACES)) -> np.ndarray:
    """The model's transmissions behind the focus plane at sensor positions ``places`` (x, y in
    [-1, 1]): ``(len(places), P, P, 3)``, rows down the image, in [0, 1] per channel."""
    if not isinstance(model, LensBokeh):
        raise ValueError(f"only the lens network learns pupils; this checkpoint holds a {type(model).__name__}")
    pos = torch.tensor([list(places)], dtype=model.pupil_shared.dtype)
    with torch.no_grad():
        t = torch.exp(model.pupils_at(pos))[0, :, 0]  # (places, 3, P, P), side 0: behind
    t = t / t.amax(dim=(-2, -1), keepdim=True).clamp_min(1e-12)
    return t.permute(0, 2, 3, 1).numpy()


def pupil_sheet(panels: Sequence[np.ndarray], scale: int = 4, gap: int = 4) -> np.ndarray:
    """Panels ``(P, P, 3)`` side by side, each ``scale`` x enlarged (nearest), ``gap`` px apart
    on white: ``(P s, n (P s + gap) - gap, 3)``."""
    big = [np.repeat(np.repeat(np.asarray(p, dtype=np.float32), scale, 0), scale, 1) for p in panels]
    h = big[0].shape[0]
    white = np.ones((h, gap, 3), dtype=np.float32)
    parts = [x for b in big for x in (b, white)][:-1]
    return np.concatenate(parts, axis=1)


def reference_panel(aperture: Aperture, size: int) -> np.ndarray:
    """``aperture`` rasterised on a ``size``^2 pupil grid, grey ``(size, size, 3)`` in [0, 1]; a
    light field's views (:class:`~neuralbokeh.core.apertures.ViewGrid`) as one sample each, the
    points its kernels are made of."""
    if isinstance(aperture, ViewGrid):
        u, v, w = aperture.points()
        rows = np.rint((PUPIL_EXTENT - v) / pupil_step(size)).astype(int)  # row 0 at the top (v up)
        cols = np.rint((u + PUPIL_EXTENT) / pupil_step(size)).astype(int)
        t = np.zeros((size, size))
        t[rows, cols] = w
    else:
        t = prior_transmission(aperture, size)
    return np.repeat((t / max(float(t.max()), 1e-12))[..., None], 3, axis=2).astype(np.float32)


def pupil_distance(learned: np.ndarray, reference: np.ndarray) -> float:
    """How far one pupil is from another: the total-variation distance between the two
    transmissions, each scaled to sum 1 per channel, averaged over the channels.

    Args:
        learned: ``(P, P, 3)`` transmission, >= 0.
        reference: ``(P, P, 3)`` transmission, >= 0.

    Returns:
        0 for the same shape and size (any brightness), 1 where they share no sample.
    """
    if learned.shape != reference.shape or learned.ndim != 3:
        raise ValueError(f"pupils must both be (P, P, C), got {learned.shape} and {reference.shape}")
    a, b = np.asarray(learned, dtype=np.float64), np.asarray(reference, dtype=np.float64)
    a, b = a / np.maximum(a.sum(axis=(0, 1)), 1e-12), b / np.maximum(b.sum(axis=(0, 1)), 1e-12)
    return float(0.5 * np.abs(a - b).sum(axis=(0, 1)).mean())


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m neuralbokeh.evaluation.pupils", description=__doc__, formatter_class=HelpFormatter)
    p.add_argument("checkpoint", type=Path, help="a lens network's checkpoint")
    p.add_argument("--out", type=Path, required=True, help="the picture (.png: 8-bit, transmission x 255; .exr/.tif: float)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    ref = p.add_mutually_exclusive_group()
    ref.add_argument("--scene", type=Path, help="a scene folder whose scene.json declares the aperture to show beside")
    ref.add_argument("--aperture", help="an aperture spec to show beside (polygon:7, disk, ...)")
    p.add_argument("--scale", type=int, default=4, help="screen px per pupil sample")
    p.add_argument("-v", "--verbose", action="store_true", help="show tracebacks")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """The CLI (see the module doc)."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stdout)
    if args.scale < 1:
        raise ValueError(f"--scale must be a whole number >= 1, got {args.scale}")
    prepare_output(args.out, args.overwrite)
    model, _ = load_model(args.checkpoint)
    panels, labels = list(learned_pupils(model)), [label for label, _ in PLACES]
    aperture = None
    if args.scene is not None:
        declared = read_json(args.scene / "scene.json").get("aperture")
        if declared is None:
            raise ValueError(f"{args.scene / 'scene.json'} declares no aperture: pass --aperture SPEC to show one")
        aperture = ApertureModel.from_dict(declared).shape
    elif args.aperture is not None:
        aperture = parse_aperture(args.aperture)
    if aperture is not None:
        panels.insert(0, reference_panel(aperture, model.config.pupil_size))
        labels.insert(0, "reference")
        log.info("centre pupil against the reference: %.4f (total-variation distance, 0: the same, 1: disjoint)",
                 pupil_distance(panels[1], panels[0]))
    sheet = pupil_sheet(panels, args.scale)
    if args.out.suffix.lower() in (".png", ".jpg", ".jpeg"):  # a transmission, not light: 0..1 to 0..255 as it is
        write_image(args.out, np.round(sheet * 255).astype(np.uint8), pixel_type="uint8")
    else:
        write_image(args.out, sheet)
    log.info("wrote %s: %s (left to right)", args.out, ", ".join(labels))
    return 0


if __name__ == "__main__":
    from ..core.cli import run_cli

    raise SystemExit(run_cli(main))

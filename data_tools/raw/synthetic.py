"""Synthetic RAW focal stacks with known truth: real DNG files for testing ``data_tools.raw``.

    python -m data_tools.raw.synthetic --out data/raw_synth --stacks 2 --size 256 192 --slices 5

Per stack: a procedural layered scene rendered with the reference scatter renderer (disk
aperture) at K focus distances; each slice magnified by its own focus-breathing factor about
the image centre; exposed so a white diffuse surface sits at ``exposure`` of the white level
(HDR highlights clip, as on a sensor); mosaiced to an RGGB Bayer pattern; shot noise (Poisson,
``full_well`` electrons at white) and read noise added; quantised between a black and a white
level and written as 16-bit DNG (``pidng``) with make, model, focal length, f-number and the
focus distance as EXIF SubjectDistance. ``truth/`` holds the true AIF (in the same exposure
units: 1 = white level), planar depth, focus distances and magnifications.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import torch
from kornia.geometry.transform import get_rotation_matrix2d, warp_affine

from neuralbokeh.core.apertures import ApertureModel, Disk
from neuralbokeh.core.cli import HelpFormatter
from neuralbokeh.core.io import write_image
from neuralbokeh.core.optics import ThinLens, focus_sweep_m
from neuralbokeh.render import scatter_layers

from ..procedural import SceneParams, composite_sharp, make_layers

BLACK, WHITE = 1024, 60000


def _magnify(img: np.ndarray, factor: float) -> np.ndarray:
    """Scale ``(H, W, 3)`` about its centre by ``factor`` (bilinear, edges replicated)."""
    h, w = img.shape[:2]
    x = torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1)))[None].double()
    m = get_rotation_matrix2d(torch.tensor([[(w - 1) / 2, (h - 1) / 2]], dtype=x.dtype), torch.zeros(1, dtype=x.dtype),
                              torch.full((1, 2), factor, dtype=x.dtype))
    return warp_affine(x, m, (h, w), mode="bilinear", padding_mode="border")[0].numpy().transpose(1, 2, 0)


def mosaic(rgb: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` -> ``(H, W)`` RGGB Bayer (R at (0, 0), B at (1, 1))."""
    cfa = rgb[..., 1].copy()
    cfa[0::2, 0::2] = rgb[0::2, 0::2, 0]
    cfa[1::2, 1::2] = rgb[1::2, 1::2, 2]
    return cfa


def write_dng(path: Path, cfa: np.ndarray, lens: ThinLens, focus_m: float, make: str = "neuralbokeh",
              model: str = "synthetic") -> None:
    """Write a 16-bit RGGB DNG of sensor values ``cfa`` (uint16, black/white levels above)."""
    from pidng.core import RAW2DNG, DNGTags, Tag
    from pidng.defs import (
        CalibrationIlluminant,
        CFAPattern,
        DNGVersion,
        Orientation,
        PhotometricInterpretation,
    )

    h, w = cfa.shape
    t = DNGTags()
    t.set(Tag.ImageWidth, w)
    t.set(Tag.ImageLength, h)
    t.set(Tag.TileWidth, w)
    t.set(Tag.TileLength, h)
    t.set(Tag.Orientation, Orientation.Horizontal)
    t.set(Tag.PhotometricInterpretation, PhotometricInterpretation.Color_Filter_Array)
    t.set(Tag.SamplesPerPixel, 1)
    t.set(Tag.BitsPerSample, 16)
    t.set(Tag.CFARepeatPatternDim, [2, 2])
    t.set(Tag.CFAPattern, CFAPattern.RGGB)
    t.set(Tag.BlackLevel, BLACK)
    t.set(Tag.WhiteLevel, WHITE)
    t.set(Tag.ColorMatrix1, [[1, 1], [0, 1], [0, 1], [0, 1], [1, 1], [0, 1], [0, 1], [0, 1], [1, 1]])
    t.set(Tag.CalibrationIlluminant1, CalibrationIlluminant.D65)
    t.set(Tag.AsShotNeutral, [[1, 1], [1, 1], [1, 1]])
    t.set(Tag.Make, make)
    t.set(Tag.Model, model)
    t.set(Tag.UniqueCameraModel, f"{make} {model}")
    t.set(Tag.FNumber, [[round(lens.f_number * 100), 100]])
    t.set(Tag.FocalLength, [[round(lens.focal_length_mm * 100), 100]])
    t.set(Tag.SubjectDistance, [[round(focus_m * 10000), 10000]])
    t.set(Tag.DNGVersion, DNGVersion.V1_4)
    t.set(Tag.PreviewColorSpace, 0)
    r = RAW2DNG()
    r.options(t, path="", compress=False)
    path.write_bytes(bytes(r.convert(cfa.astype(np.uint16))))


def make_stack(out: Path, seed: int, size: tuple[int, int], slices: int, lens: ThinLens, breathing: float = 0.02,
               exposure: float = 0.25, full_well: float = 20000.0, read_noise: float = 4.0) -> dict:
    """Write one synthetic RAW stack folder ``out`` (DNGs) and ``out/truth``; returns the truth."""
    w, h = size
    if w % 2 or h % 2:
        raise ValueError(f"size must be even for a Bayer mosaic, got {w}x{h}")
    rng = np.random.default_rng(seed)
    layers = make_layers(rng, h, w, SceneParams(near_m=0.8, far_m=6.0, infinite_background=0.0, highlights=(2, 5),
                                                highlight_gain=(2.0, 20.0)))
    aif, depth = composite_sharp(layers)
    finite = [layer.depth_m for layer in layers if math.isfinite(layer.depth_m)]
    focus = focus_sweep_m(min(finite), max(finite), slices)
    colors = torch.from_numpy(np.stack([layer.color * layer.alpha[..., None] for layer in layers])).permute(0, 3, 1, 2)
    alphas = torch.from_numpy(np.stack([layer.alpha for layer in layers]))[:, None]
    aperture = ApertureModel(Disk())
    magnification = [1.0 + breathing * (k / max(slices - 1, 1) - 0.5) for k in range(slices)]
    out.mkdir(parents=True, exist_ok=True)
    for k, f in enumerate(focus):
        cocs = [lens.coc_px(layer.depth_m, f, w, signed=True) for layer in layers]
        img = scatter_layers(colors, alphas, cocs, aperture).permute(1, 2, 0).numpy()
        img = _magnify(img, magnification[k]) * exposure
        electrons = rng.poisson(np.clip(mosaic(img), 0.0, 1.0) * full_well).astype(np.float64)
        signal = electrons / full_well + rng.normal(0.0, read_noise / full_well, electrons.shape)
        cfa = np.clip(np.round(BLACK + signal * (WHITE - BLACK)), 0, 65535)  # a sensor's ADC saturates
        write_dng(out / f"slice_{k:02d}.dng", cfa, lens, f)
    truth = {"focus_m": list(focus), "magnification": magnification, "exposure": exposure, "seed": seed,
             "lens": lens.to_dict(), "full_well": full_well, "read_noise": read_noise}
    (out / "truth").mkdir(exist_ok=True)
    write_image(out / "truth" / "aif.exr", (aif * exposure).astype(np.float32))
    write_image(out / "truth" / "depth.exr", depth.astype(np.float32))
    (out / "truth" / "truth.json").write_text(json.dumps(truth, indent=2))
    return truth


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="folder to write the stacks (stack_<i>/) and their truth into")
    p.add_argument("--stacks", type=int, default=1, help="number of focal stacks (scenes)")
    p.add_argument("--size", type=int, nargs=2, default=(256, 192), metavar=("W", "H"), help="image size in px")
    p.add_argument("--slices", type=int, default=5, help="focus distances (RAW files) per stack")
    p.add_argument("--breathing", type=float, default=0.02, help="magnification spread across the stack")
    p.add_argument("--seed", type=int, default=0, help="seed of the scenes and the sensor noise")
    p.add_argument("--focal-length", type=float, default=50.0, help="focal length in mm (written to EXIF)")
    p.add_argument("--f-number", type=float, default=1.8, help="f-number (written to EXIF)")
    p.add_argument("--sensor-width", type=float, default=12.0, help="mm (small: CoCs of several px at small sizes)")
    args = p.parse_args(argv)
    lens = ThinLens(args.focal_length, args.f_number, args.sensor_width)
    for i in range(args.stacks):
        make_stack(args.out / f"stack_{i:03d}", args.seed + i, tuple(args.size), args.slices, lens, args.breathing)
    print(f"wrote {args.stacks} stack(s) of {args.slices} DNGs to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

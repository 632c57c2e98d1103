"""Linear decoding of camera RAW files (rawpy / LibRaw) and their metadata (exifread).

Decoding gives *linear camera RGB*: LibRaw subtracts the black level, scales the white level to
65535 and demosaics (with LibRaw's "adjust maximum" off: by default it rescales each file by its
own brightest pixels, a gain that differed by 12.5 % on a test ramp and would differ between
the slices of a stack); no colour matrix (``ColorSpace.raw``), no gamma, no auto-brightening, no
highlight reconstruction, 16-bit output, orientation applied. One set of white-balance
multipliers is used for every slice of a stack (see :func:`white_balance`) so refocusing can
never change colours; the exposure normalisation is one factor for the whole stack too
(applied by the caller).

Demosaicing (``demosaic``): LibRaw's AHD by default (good on edges, the usual choice); ``DCB``,
``PPG``, ``VNG``, ``LINEAR`` (bilinear, fastest, softest) and the others LibRaw builds with
are accepted. ``half_size`` averages each 2x2 CFA block instead (no interpolation at all,
half resolution), the most faithful choice when the output is downscaled anyway.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import exifread
import numpy as np
import rawpy

log = logging.getLogger(__name__)

RAW_EXTENSIONS = {".3fr", ".arw", ".cr2", ".cr3", ".crw", ".dcr", ".dng", ".erf", ".iiq", ".k25", ".kdc", ".mef",
                  ".mos", ".mrw", ".nef", ".nrw", ".orf", ".pef", ".raf", ".raw", ".rw2", ".rwl", ".sr2", ".srf",
                  ".srw", ".x3f"}


# Fewer bits per sensor pixel than this cannot hold an image: lossless RAW codecs spend >= 1 bit
# per sample, lossy DNGs ~1-2. Stripped sample files hold 0.013-0.04. LibRaw decodes such a file
# from uninitialised memory (all zero, or sparse garbage from one call to the next), so the
# size, not the decoded values, is what tells.
MIN_BITS_PER_PIXEL = 0.25


class RawDecodeError(ValueError):
    """A RAW file that cannot be used; the message names the file and the reason."""


@dataclass(frozen=True)
class DecodeSettings:
    """How RAW files are developed. ``demosaic``: a ``rawpy.DemosaicAlgorithm`` name."""

    demosaic: str = "AHD"
    half_size: bool = False

    def __post_init__(self) -> None:
        names = [a.name for a in rawpy.DemosaicAlgorithm]
        if self.demosaic.upper() not in names:
            raise ValueError(f"demosaic must be one of {names}, got {self.demosaic!r}")


def _open(path: Path) -> rawpy.RawPy:
    try:
        return rawpy.imread(str(path))
    except (rawpy.LibRawError, OSError) as e:
        raise RawDecodeError(f"{path}: LibRaw cannot read it ({type(e).__name__}: {e})") from None


def white_balance(path: Path, mode: str | tuple[float, float, float]) -> tuple[float, float, float]:
    """White-balance multipliers (R, G, B, normalised to G = 1) of the reference file.

    ``mode``: ``"camera"`` (as shot; falls back to daylight, with a warning, when the file has
    none: LibRaw reports all ones or zeros then), ``"daylight"``, ``"none"`` (1, 1, 1) or
    explicit multipliers.
    """
    if isinstance(mode, tuple):
        r, g, b = (float(v) for v in mode)
        if min(r, g, b) <= 0:
            raise ValueError(f"white balance multipliers must be > 0, got {mode}")
        return r / g, 1.0, b / g
    if mode == "none":
        return 1.0, 1.0, 1.0
    if mode not in ("camera", "daylight"):
        raise ValueError(f"white balance must be 'camera', 'daylight', 'none' or R,G,B, got {mode!r}")
    with _open(path) as raw:
        cam, day = list(raw.camera_whitebalance[:3]), list(raw.daylight_whitebalance[:3])
    chosen = cam if mode == "camera" else day
    if mode == "camera" and (min(cam) <= 0 or cam == [1.0, 1.0, 1.0]):
        log.warning("%s carries no as-shot white balance (%s); using daylight %s", path, cam, day)
        chosen = day
    if min(chosen) <= 0:
        raise RawDecodeError(f"{path}: no usable {mode} white balance ({chosen}); pass explicit multipliers")
    return chosen[0] / chosen[1], 1.0, chosen[2] / chosen[1]


def decode(path: Path, wb: tuple[float, float, float], settings: DecodeSettings = DecodeSettings()) -> np.ndarray:
    """One RAW file -> ``(H, W, 3)`` float32 linear camera RGB in [0, 1] (1 = the white level).

    Raises:
        RawDecodeError: unreadable file, not a Bayer/X-Trans CFA (e.g. a film scanner's NEF),
            or a file too small to hold its image (DNGs whose image data was stripped), or an
            image that decodes to all zeros.
    """
    with _open(path) as raw:
        try:  # LibRaw unpacks lazily: a truncated file fails at the first attribute that needs the data
            _check_holds_image(path, raw.sizes.raw_width * raw.sizes.raw_height)
            cfa = raw.raw_pattern is not None and raw.num_colors == 3
            kind = f"raw type {raw.raw_type.name}, {raw.num_colors} colours"
            rgb = None
            if cfa:
                rgb = raw.postprocess(
                    demosaic_algorithm=rawpy.DemosaicAlgorithm[settings.demosaic.upper()], half_size=settings.half_size,
                    use_camera_wb=False, use_auto_wb=False, user_wb=[wb[0], wb[1], wb[2], wb[1]],
                    output_color=rawpy.ColorSpace.raw, output_bps=16, gamma=(1.0, 1.0), no_auto_bright=True,
                    highlight_mode=rawpy.HighlightMode.Clip, user_flip=None, adjust_maximum_thr=0.0,
                )
        except (rawpy.LibRawError, OSError) as e:
            raise RawDecodeError(f"{path}: LibRaw cannot decode it ({type(e).__name__}: {e})") from None
    if not cfa:
        raise RawDecodeError(f"{path}: not a colour-filter-array RAW ({kind}): a scanner's or an already "
                             "demosaiced (linear DNG) file is not supported")
    if rgb.max() == 0:
        raise RawDecodeError(f"{path}: decodes to an all-zero image (image data missing or stripped)")
    return rgb.astype(np.float32) / 65535.0


def _check_holds_image(path: Path, pixels: int) -> None:
    size = path.stat().st_size
    if size * 8 < MIN_BITS_PER_PIXEL * pixels:
        raise RawDecodeError(f"{path}: image data missing or stripped ({size} bytes for {pixels} sensor pixels, "
                             f"{size * 8 / pixels:.3f} bits each; a RAW image needs >= {MIN_BITS_PER_PIXEL})")


def _number(value: Any) -> float | None:
    try:
        v = value.values[0] if hasattr(value, "values") else value
        f = float(Fraction(v.num, v.den)) if hasattr(v, "num") else float(v)
    except (TypeError, ValueError, ZeroDivisionError, IndexError):
        return None
    return f if np.isfinite(f) and f > 0 else None


def read_metadata(path: Path) -> dict[str, Any]:
    """Make, model, focal length (mm), f-number, focus distance (m), exposure time (s) and ISO
    where the file's EXIF carries them (None otherwise)."""
    with open(path, "rb") as f:
        tags = exifread.process_file(f, details=False)

    def first(*names: str) -> Any:
        for n in names:
            for prefix in ("EXIF ", "Image "):
                if prefix + n in tags:
                    return tags[prefix + n]
        return None

    text = lambda v: str(v).strip() if v is not None else None  # noqa: E731
    return {
        "make": text(first("Make")), "model": text(first("Model")), "lens_model": text(first("LensModel")),
        "focal_length_mm": _number(first("FocalLength")), "f_number": _number(first("FNumber")),
        "focus_distance_m": _number(first("SubjectDistance")), "exposure_time_s": _number(first("ExposureTime")),
        "iso": _number(first("ISOSpeedRatings", "PhotographicSensitivity")),
    }

"""Image and JSON files: OpenImageIO reads and writes, every write atomic.

One reader and one writer for the whole package. Arrays are numpy ``(H, W, C)``; EXR is written
as float32 with lossless ZIP compression, so linear HDR values (and +inf depths) survive exactly.
Writes go to a temporary file in the target folder and are renamed over the target, so a crash
never leaves a half-written file under the final name.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import OpenImageIO as oiio

_FORMATS = {"float32": oiio.FLOAT, "float16": oiio.HALF, "uint8": oiio.UINT8, "uint16": oiio.UINT16}


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def default_mode(directory: bool = False) -> int:
    """Permissions a plain ``open``/``mkdir`` would give (0o666/0o777 less the umask)."""
    return (0o777 if directory else 0o666) & ~_umask()


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike) -> Iterator[Path]:
    """``with atomic_write(path) as tmp:`` write ``tmp`` (any writer: ``torch.save``,
    ``onnx.save``, ``open``); on leaving the block it is renamed over ``path``. If the block
    raises, ``tmp`` is removed and ``path`` is untouched: never a half-written file under the
    final name. ``tmp`` lies in ``path``'s folder (which must exist), keeps its extension and
    has the permissions a plain ``open`` would give."""
    path = Path(path)
    fd, name = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    tmp = Path(name)
    os.chmod(tmp, default_mode())  # mkstemp makes 0600 files
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def prepare_output(path: str | os.PathLike, overwrite: bool = False, flag: str = "--overwrite") -> Path:
    """Check, before any work, that ``path`` can be written: its folder is created and must be
    writable, and an existing file or folder there is replaced only with ``overwrite``.

    Raises:
        FileExistsError: ``path`` exists and ``overwrite`` is False (the message names ``flag``).
        PermissionError: its folder cannot be written.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} already exists: choose another output or give {flag} to replace it")
    path.parent.mkdir(parents=True, exist_ok=True)
    if not os.access(path.parent, os.W_OK | os.X_OK):
        raise PermissionError(f"cannot write into {path.parent} (no write permission) for {path.name}")
    return path


@contextlib.contextmanager
def atomic_directory(path: str | os.PathLike) -> Iterator[Path]:
    """``with atomic_directory(folder) as tmp:`` fill the temporary folder ``tmp``; on leaving the
    block it is renamed to ``folder`` (which must not exist), so the folder appears complete or
    not at all. If the block raises, ``tmp`` is removed. The parent folder is created."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    try:
        yield tmp
        os.chmod(tmp, default_mode(directory=True))  # mkdtemp makes 0700 folders
        os.rename(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write a text file atomically (see :func:`atomic_write`)."""
    with atomic_write(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def write_image(
    path: str | os.PathLike,
    image: np.ndarray,
    attributes: dict[str, Any] | None = None,
    channel_names: list[str] | None = None,
    pixel_type: str = "float32",
    windows: tuple[Window, Window] | None = None,
    tile: int | None = None,
) -> Path:
    """Write an image atomically; the format comes from the extension (.exr, .tif, .png, ...).

    Args:
        path: destination; its folder must exist.
        image: ``(H, W)`` or ``(H, W, C)`` array. Float data is written as given (no clipping);
            for integer pixel types it must already be in the type's range.
        attributes: extra metadata stored in the file header: strings, ints, floats, or
            ``(TypeDesc, value)`` pairs as :func:`image_attributes` returns them.
        channel_names: e.g. ``["R", "G", "B"]`` or ``["Z"]`` (default: OpenImageIO's).
        pixel_type: one of ``float32``, ``float16``, ``uint8``, ``uint16``.
        windows: ``(data window, display window)`` (see :func:`image_windows`); the data
            window's size must be the image's (default: both ``(0, 0, W, H)``).
        tile: store the pixels in ``tile`` x ``tile`` px tiles (EXR and TIFF) instead of
            scanlines, so that :func:`read_image` decodes a crop's tiles only, not its whole
            rows (training sets); default scanlines (what compositing applications read fastest).

    Returns:
        The path written.

    Raises:
        ValueError: bad array shape, pixel type, or values outside an integer type's range.
        OSError: OpenImageIO cannot write the file (its message included).
    """
    path = Path(path)
    arr = np.asarray(image)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.ndim != 3 or min(arr.shape) < 1:
        raise ValueError(f"image must have shape (H, W) or (H, W, C), got {np.shape(image)}")
    if pixel_type not in _FORMATS:
        raise ValueError(f"pixel_type must be one of {sorted(_FORMATS)}, got {pixel_type!r}")
    if pixel_type.startswith("uint"):
        hi = np.iinfo(pixel_type).max
        if arr.min() < 0 or arr.max() > hi:
            raise ValueError(f"{pixel_type} image values must be in [0, {hi}], got [{arr.min()}, {arr.max()}]")
        arr = np.ascontiguousarray(arr, dtype=pixel_type)
    else:
        arr = np.ascontiguousarray(arr, dtype=np.float32)
    h, w, c = arr.shape
    spec = oiio.ImageSpec(w, h, c, _FORMATS[pixel_type])
    if channel_names:
        if len(channel_names) != c:
            raise ValueError(f"channel_names must name {c} channels, got {channel_names}")
        spec.channelnames = tuple(channel_names)
    if windows is not None:
        (x, y, dw, dh), (fx, fy, fw, fh) = windows
        if (dw, dh) != (w, h) or fw < 1 or fh < 1:
            raise ValueError(f"data window {windows[0]} must be the image's {w}x{h} and the display window not empty")
        spec.x, spec.y, spec.full_x, spec.full_y, spec.full_width, spec.full_height = x, y, fx, fy, fw, fh
    if path.suffix.lower() == ".exr":
        spec.attribute("compression", "zip")
    if tile is not None:
        if path.suffix.lower() not in (".exr", ".tif", ".tiff") or tile < 16 or tile % 16:
            raise ValueError(f"tile must be a multiple of 16 px for an .exr or .tif file, got {tile} for {path.name}")
        spec.tile_width = spec.tile_height = int(tile)
    for key, value in (attributes or {}).items():
        if isinstance(value, tuple) and len(value) == 2 and isinstance(value[0], oiio.TypeDesc):
            spec.attribute(key, value[0], value[1])  # typed, as image_attributes reads them (a timecode, say)
        else:
            spec.attribute(key, value)
    with atomic_write(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise OSError(f"cannot write {path}: {oiio.geterror()}")
        if not out.open(str(tmp), spec) or not out.write_image(arr):
            msg = out.geterror()
            out.close()
            raise OSError(f"cannot write {path}: {msg}")
        out.close()
    return path


@contextlib.contextmanager
def _image_input(path: Path) -> Iterator[Any]:
    """An open ``oiio.ImageInput`` of ``path``, closed on exit.

    Raises:
        FileNotFoundError: no such file.
        OSError: OpenImageIO cannot open it (its message included).
    """
    if not path.is_file():
        raise FileNotFoundError(f"no such image file: {path}")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise OSError(f"cannot read {path}: {oiio.geterror()}")
    try:
        yield inp
    finally:
        inp.close()


def image_attributes(path: str | os.PathLike, names: list[str]) -> dict[str, tuple[Any, Any]]:
    """The header attributes ``names`` that an image file has, as ``{name: (TypeDesc, value)}``
    (typed, so that a timecode or a rational frame rate is written back as it was)."""
    with _image_input(Path(path)) as inp:
        return {a.name: (a.type, a.value) for a in inp.spec().extra_attribs if a.name in names}


def image_channels(path: str | os.PathLike) -> list[str]:
    """The channel names of an image file's first part (``["R", "G", "B", "A", "depth.Z"]``).

    Raises:
        FileNotFoundError: no such file.
        OSError: OpenImageIO cannot read it.
    """
    with _image_input(Path(path)) as inp:
        return list(inp.spec().channelnames)


# A pixel rectangle (x, y, width, height) in an image's absolute pixel coordinates, as EXR's data
# and display windows are: (0, 0, W, H) for most files; a crop's data window lies inside its
# display window, a render's overscan reaches beyond it.
Window = tuple[int, int, int, int]


def image_windows(path: str | os.PathLike) -> tuple[Window, Window]:
    """``(data window, display window)`` of an image file's first part, each ``(x, y, w, h)``.

    Raises:
        FileNotFoundError: no such file.
        OSError: OpenImageIO cannot read it.
    """
    with _image_input(Path(path)) as inp:
        s = inp.spec()
        return (s.x, s.y, s.width, s.height), (s.full_x, s.full_y, s.full_width, s.full_height)


def intersect(a: Window, b: Window) -> Window | None:
    """The overlap of two windows, or None when they do not overlap."""
    x0, y0 = max(a[0], b[0]), max(a[1], b[1])
    x1, y1 = min(a[0] + a[2], b[0] + b[2]), min(a[1] + a[3], b[1] + b[3])
    return (x0, y0, x1 - x0, y1 - y0) if x1 > x0 and y1 > y0 else None


def place(image: np.ndarray, data: Window, window: Window, fill: float = 0.0) -> np.ndarray:
    """``image`` ``(h, w, C)`` of data window ``data`` laid into ``window``: the overlap is
    copied, what ``data`` does not cover is ``fill`` (EXR's rule: no pixel outside the data
    window), what lies outside ``window`` is cut off. Returns ``(window h, window w, C)``."""
    out = np.full((window[3], window[2], image.shape[2]), fill, dtype=image.dtype)
    both = intersect(data, window)
    if both is not None:
        x, y, w, h = both
        out[y - window[1]:y - window[1] + h, x - window[0]:x - window[0] + w] = \
            image[y - data[1]:y - data[1] + h, x - data[0]:x - data[0] + w]
    return out


def read_image(path: str | os.PathLike, with_attributes: bool = False, rows: tuple[int, int] | None = None,
               channels: list[str] | None = None, cols: tuple[int, int] | None = None) -> Any:
    """Read an image as float32 ``(H, W, C)`` (integer files scaled to [0, 1] by OpenImageIO).

    Args:
        path: any format OpenImageIO reads.
        with_attributes: also return the header metadata as a dict.
        rows: ``(r0, r1)``: read only these rows, counted from the data window's top.
        channels: the channels to return, by name, in this order (default: all of them).
        cols: ``(c0, c1)``: keep only these columns. A tiled file (``write_image(tile=...)``)
            decodes only the tiles holding ``rows`` x ``cols``; a scanline file decodes whole
            rows (EXR: only the blocks holding ``rows``).

    Returns:
        The array ``(r1 - r0, c1 - c0, C)``, or ``(array, attributes)``.

    Raises:
        FileNotFoundError: no such file.
        ValueError: ``rows`` or ``cols`` outside the image, or a channel it lacks.
        OSError: OpenImageIO cannot read it (its message included).
    """
    path = Path(path)
    with _image_input(path) as inp:
        spec = inp.spec()
        (r0, r1), (c0, c1) = rows or (0, spec.height), cols or (0, spec.width)
        if not (0 <= r0 < r1 <= spec.height and 0 <= c0 < c1 <= spec.width):
            raise ValueError(f"rows {rows}, cols {cols} are outside {path}'s {spec.width}x{spec.height} px")
        arr, (r, c) = _read_region(inp, spec, (r0, r1), (c0, c1))
        if arr is None:
            raise OSError(f"cannot read {path}: {inp.geterror()}")
        attrs = {a.name: a.value for a in spec.extra_attribs} if with_attributes else None
        names = list(spec.channelnames)
    arr = np.asarray(arr, dtype=np.float32).reshape(r[1] - r[0], c[1] - c[0], spec.nchannels)
    arr = arr[r0 - r[0]:r1 - r[0], c0 - c[0]:c1 - c[0]]
    if channels is not None:
        missing = [ch for ch in channels if ch not in names]
        if missing:
            raise ValueError(f"{path} has no channel {missing[0]!r}; its channels: {', '.join(names)}")
        arr = arr[:, :, [names.index(ch) for ch in channels]]
    arr = np.ascontiguousarray(arr)
    return (arr, attrs) if with_attributes else arr


def _read_region(inp: Any, spec: Any, rows: tuple[int, int], cols: tuple[int, int]) -> tuple[Any, tuple]:
    """The smallest block OpenImageIO can decode that holds ``rows`` x ``cols`` (whole tiles of
    a tiled file, whole rows of a scanline one), with the rows and columns it spans."""
    if (rows, cols) == ((0, spec.height), (0, spec.width)):
        return inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT), (rows, cols)
    if spec.tile_width and spec.tile_height:
        tw, th = spec.tile_width, spec.tile_height
        r = (rows[0] // th * th, min(-(-rows[1] // th) * th, spec.height))
        c = (cols[0] // tw * tw, min(-(-cols[1] // tw) * tw, spec.width))
        return inp.read_tiles(0, 0, spec.x + c[0], spec.x + c[1], spec.y + r[0], spec.y + r[1], 0, 1,
                              0, spec.nchannels, oiio.FLOAT), (r, c)
    return inp.read_scanlines(0, 0, spec.y + rows[0], spec.y + rows[1], 0, 0, spec.nchannels, oiio.FLOAT), \
        (rows, (0, spec.width))


def write_json(path: str | os.PathLike, data: Any) -> Path:
    """Write JSON atomically (indented, keys in given order; ``inf`` written as ``Infinity``)."""
    return write_text(path, json.dumps(data, indent=2) + "\n")


def read_json(path: str | os.PathLike) -> Any:
    """Read a JSON file; ``FileNotFoundError`` or ``ValueError`` (with the path) on failure."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such file: {path}")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path} is not valid JSON: {e}") from None

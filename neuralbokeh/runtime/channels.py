"""Which channels of an image file are the colour, the depth or the alpha (torch-free).

Compositing files hold more than RGB: Nuke writes ``R G B A`` with ``depth.Z`` beside them,
Blender's multi-layer EXR ``ViewLayer.Combined.R`` ... ``ViewLayer.Combined.A`` and
``ViewLayer.Depth.Z``. A source is a path, optionally followed by ``:NAME`` (``render.exr:
ViewLayer.Combined``, ``shot.exr:depth.Z``): ``NAME`` is a channel, or a layer whose ``.R .G .B``
(colour), ``.Z`` (depth) or ``.A`` (alpha) channels are meant. Without one, the defaults are what
Nuke and Blender write (:func:`pick_channels`); a file where the choice is not clear is refused
with its channels listed, never read from its first channel by chance.
"""

from __future__ import annotations

import re
from pathlib import Path

# "file.exr:NAME": the selector follows the last ':' after an extension (a drive letter "C:\" is
# no extension, so Windows paths stay whole)
_SOURCE = re.compile(r"(?P<path>.*\.[A-Za-z0-9]+):(?P<name>[^:/\\]+)")
_WANTED = {"rgb": ("R", "G", "B"), "depth": ("Z",), "alpha": ("A",)}
_WHAT = {"rgb": "colour (R, G, B)", "depth": "depth (Z)", "alpha": "alpha (A)"}


def split_source(source: str) -> tuple[str, str | None]:
    """``"path.exr:NAME"`` -> ``("path.exr", "NAME")``; a plain path -> ``(path, None)``."""
    m = _SOURCE.fullmatch(source)
    if m and not Path(source).exists():
        return m.group("path"), m.group("name")
    return source, None


def _in_layer(names: list[str], layer: str, kind: str) -> list[str] | None:
    want = [f"{layer}.{c}" if layer else c for c in _WANTED[kind]]
    return want if all(w in names for w in want) else None


def pick_channels(names: list[str], kind: str, selector: str | None = None, source: str = "the file") -> list[str]:
    """The channel names of ``kind`` (``"rgb"``, ``"depth"`` or ``"alpha"``) among a file's ``names``.

    ``selector``: a channel name (depth, alpha) or a layer (its ``.R .G .B``, ``.Z`` or ``.A``).
    Without one: the bare channels (``R G B``, ``Z``, ``A``); else ``depth.Z`` for depth; else
    the one layer that has them (Blender's ``ViewLayer.Combined`` wins among several); else, for
    depth and alpha, a file's only channel.

    Raises:
        ValueError: the selector matches nothing, or the file leaves the choice open; the
            message lists the file's channels.
    """
    listed = f"its channels: {', '.join(names)}"
    if selector is not None:
        found = _in_layer(names, selector, kind) or ([selector] if kind != "rgb" and selector in names else None)
        if not found:
            raise ValueError(f"{source}: no {_WHAT[kind]} channel or layer named {selector!r}; {listed}")
        return found
    found = _in_layer(names, "", kind) or (["depth.Z"] if kind == "depth" and "depth.Z" in names else None)
    if found:
        return found
    layers = sorted({n.rsplit(".", 1)[0] for n in names if "." in n and _in_layer(names, n.rsplit(".", 1)[0], kind)})
    combined = [la for la in layers if la.split(".")[-1] == "Combined"]
    if len(layers) == 1 or len(combined) == 1:
        return _in_layer(names, (combined or layers)[0], kind)
    if kind != "rgb" and len(names) == 1:
        return list(names)
    hint = f"one of the layers {', '.join(layers)}" if layers else "the channel"
    raise ValueError(f"{source}: which channels are the {_WHAT[kind]}? name {hint} as {source}:NAME; {listed}")

"""The HDR <-> [-1, 1) colour normalisation shared by training, export and the runtime.

numpy/torch agnostic and torch-free, so the compositing runtime can use it without torch.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .checks import all_within, check_at_least, check_nonnegative, check_positive, is_tensor


@dataclass(frozen=True)
class Normalization:
    """Exactly invertible map of linear HDR values [-offset, inf) onto the network's [-1, 1).

    ``n = (x + o - s) / (x + o + s)``, i.e. ``n = tanh(ln((x + o) / s) / 2)``: a tanh of
    log-exposure, so a network's final tanh works in log space. ``s - o`` maps to 0 and
    highlights approach 1 without ever being clipped; the inverse is
    ``x = s (1 + n) / (1 - n) - o``. The offset ``o`` keeps black off the saturated end of the
    tanh: with the default ``o = s / 100``, ``n(0) = -0.980`` (``atanh = -2.3``), so light can
    still be learned into black pixels (a CG background, say); it also admits slightly negative
    values (sensor noise around a subtracted black level) down to ``-o``. In float32 the round
    trip is exact to about 1e-6 relative for x up to 1e2 s and ~1e-3 at 1e4 s (the precision of
    n near 1); use float64 where more is needed. The same map is applied to input and target, so
    a pixel the lens leaves unchanged is the identity in either space.

    Args:
        scale: ``s`` in linear units, finite and > 0 (default 0.18, middle grey).
        offset: ``o`` in linear units, finite and >= 0 (default ``scale / 100``).
    """

    scale: float = 0.18
    offset: float | None = None

    def __post_init__(self) -> None:
        check_positive("normalization scale", self.scale)
        if self.offset is None:
            object.__setattr__(self, "offset", self.scale / 100.0)
        check_nonnegative("normalization offset", self.offset)

    def encode(self, x: Any) -> Any:
        """Linear HDR (finite, >= -offset; array or tensor of any shape) -> [-1, 1)."""
        check_at_least("linear colour", x, -self.offset)
        shifted = x + self.offset
        if isinstance(shifted, np.ndarray):  # the same operations in place: 2 image temporaries, not 4
            out = shifted - self.scale
            shifted += self.scale
            out /= shifted
            return out
        return (shifted - self.scale) / (shifted + self.scale)

    def decode(self, n: Any) -> Any:
        """[-1, 1) -> linear HDR; the exact inverse of :meth:`encode`."""
        arr = n if (is_tensor(n) or isinstance(n, np.ndarray)) else np.asarray(n, dtype=np.float64)
        if isinstance(arr, np.ndarray) and all_within(arr, -1.0, 1.0):  # then the same operations in place
            out = 1.0 + arr
            out *= self.scale
            out /= 1.0 - arr
            out -= self.offset
            return out
        bad = ~((arr >= -1.0) & (arr < 1.0))
        if bool(bad.any()):
            raise ValueError(f"normalised colour must be in [-1, 1), got values in [{float(arr.min())}, {float(arr.max())}]")
        return self.scale * (1.0 + n) / (1.0 - n) - self.offset

    def to_dict(self) -> dict[str, Any]:
        return {"kind": "mobius-log", "scale": self.scale, "offset": self.offset}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Normalization":
        if d.get("kind") != "mobius-log":
            raise ValueError(f"unknown normalisation {d.get('kind')!r}; expected 'mobius-log'")
        return cls(scale=float(d["scale"]), offset=float(d["offset"]))

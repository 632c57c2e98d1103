"""Typed value and shape checks shared by the whole package.

A leaf module: imports numpy only (never torch, never the rest of the package) so that the
torch-free runtime can use it. Works on floats, numpy arrays and torch tensors alike (torch
tensors are recognised by duck typing, without importing torch).

Every check raises ``ValueError`` (bad values) or ``TypeError``/``ValueError`` (bad shapes)
with a message that names the quantity, the offending value, how many elements are bad and
where the first one is, e.g. ``depth must be > 0 m, got -1.0 at pixel (12, 40) (3 pixels)``.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

# Value checks inside the networks' forward passes copy a mask to the host on every call (a
# GPU sync per training step), so they run only when NEURALBOKEH_DEBUG=1 (or this is set True);
# inputs are checked where they enter: the dataset check, Contract.encode_inputs, the runtime.
DEBUG = os.environ.get("NEURALBOKEH_DEBUG", "") == "1"


def is_tensor(x: Any) -> bool:
    """True for a torch tensor (recognised without importing torch)."""
    return type(x).__module__.split(".")[0] == "torch"


def to_numpy(x: Any) -> np.ndarray:
    """A numpy view/copy of a float, array or tensor (for error reporting and tests)."""
    if is_tensor(x):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def format_location(index: tuple[int, ...]) -> str:
    """Human-readable location of an element: ``pixel (row, col)`` for images.

    The last two axes are taken as (row, col); leading axes (batch, channel) are named too.
    """
    if len(index) == 0:
        return "the scalar"
    if len(index) == 1:
        return f"index {index[0]}"
    lead = index[:-2]
    where = f"pixel ({index[-2]}, {index[-1]})"
    if lead:
        where += " of " + ", ".join(f"axis{i}={v}" for i, v in enumerate(lead))
    return where


def _report(name: str, expected: str, x: Any, bad: Any, unit: str) -> None:
    bad_np = to_numpy(bad)
    if not bad_np.any():
        return
    x_np = to_numpy(x)
    count = int(bad_np.sum())
    if bad_np.ndim == 0:
        value = x_np.item()
        raise ValueError(f"{name} must be {expected}{unit}, got {value!r}")
    index = tuple(int(i) for i in np.argwhere(bad_np)[0])
    value = x_np[index].item()
    noun = "pixel" if bad_np.ndim >= 2 else "element"
    raise ValueError(
        f"{name} must be {expected}{unit}, got {value!r} at {format_location(index)} "
        f"({count} bad {noun}{'s' if count != 1 else ''} of {bad_np.size})"
    )


def all_within(arr: Any, low: float, high: float, low_inclusive: bool = True, high_inclusive: bool = False) -> bool:
    """True when ``arr`` is a non-empty float numpy array whose every element lies between ``low``
    and ``high`` (each end included as told): two reductions and no temporaries, the checks' fast
    path on large images. NaN fails (``min``/``max`` propagate it); False sends the caller to the
    elementwise check, which finds and names the bad pixel."""
    if not isinstance(arr, np.ndarray) or arr.dtype.kind != "f" or arr.size == 0:
        return False
    lo, hi = arr.min(), arr.max()
    return bool((lo >= low if low_inclusive else lo > low) and (hi <= high if high_inclusive else hi < high))


def check_positive(name: str, x: Any, unit: str = "", allow_inf: bool = False) -> None:
    """Raise ``ValueError`` unless every element of ``x`` is > 0 (and finite unless allowed).

    NaN always fails. ``unit`` is appended to the message (e.g. ``" m"``).
    """
    arr = x if (is_tensor(x) or isinstance(x, np.ndarray)) else np.asarray(x, dtype=np.float64)
    if all_within(arr, 0.0, float("inf"), low_inclusive=False, high_inclusive=allow_inf):
        return
    if allow_inf:
        bad = ~(arr > 0)
        expected = "> 0 (inf allowed)"
    else:
        bad = ~((arr > 0) & (arr < float("inf")))
        expected = "finite and > 0"
    _report(name, expected, arr, bad, unit)


def check_finite(name: str, x: Any, unit: str = "") -> None:
    """Raise ``ValueError`` if any element of ``x`` is NaN or +-inf."""
    arr = x if (is_tensor(x) or isinstance(x, np.ndarray)) else np.asarray(x, dtype=np.float64)
    if all_within(arr, -float("inf"), float("inf"), low_inclusive=False):
        return
    bad = ~((arr > -float("inf")) & (arr < float("inf")))
    _report(name, "finite", arr, bad, unit)


def check_nonnegative(name: str, x: Any, unit: str = "") -> None:
    """Raise ``ValueError`` unless every element of ``x`` is finite and >= 0."""
    arr = x if (is_tensor(x) or isinstance(x, np.ndarray)) else np.asarray(x, dtype=np.float64)
    if all_within(arr, 0.0, float("inf")):
        return
    bad = ~((arr >= 0) & (arr < float("inf")))
    _report(name, "finite and >= 0", arr, bad, unit)


def check_at_least(name: str, x: Any, low: float, unit: str = "") -> None:
    """Raise ``ValueError`` unless every element of ``x`` is finite and >= ``low``."""
    arr = x if (is_tensor(x) or isinstance(x, np.ndarray)) else np.asarray(x, dtype=np.float64)
    if all_within(arr, low, float("inf")):
        return
    bad = ~((arr >= low) & (arr < float("inf")))
    _report(name, f"finite and >= {low:g}", arr, bad, unit)


def check_in_range(name: str, x: Any, low: float, high: float, unit: str = "") -> None:
    """Raise ``ValueError`` unless every element is finite and within ``[low, high]``."""
    arr = x if (is_tensor(x) or isinstance(x, np.ndarray)) else np.asarray(x, dtype=np.float64)
    if all_within(arr, low, high, high_inclusive=True):
        return
    bad = ~((arr >= low) & (arr <= high))
    _report(name, f"in [{low}, {high}]", arr, bad, unit)


def check_shape(name: str, x: Any, pattern: str, **fixed: int) -> dict[str, int]:
    """Check that ``x`` has the shape described by ``pattern`` (e.g. ``"B 3 H W"``).

    Letters are free dimensions (bound consistently within the pattern and to ``fixed``),
    integers are exact sizes. Returns the bound sizes.

    Raises:
        TypeError: ``x`` has no ``shape``.
        ValueError: the rank or a size differs.
    """
    if not hasattr(x, "shape"):
        raise TypeError(f"{name} must be an array or tensor of shape ({pattern}), got {type(x).__name__}")
    dims = pattern.split()
    shape = tuple(int(s) for s in x.shape)
    if len(shape) != len(dims):
        raise ValueError(f"{name} must have shape ({pattern}), got {shape}")
    bound: dict[str, int] = dict(fixed)
    for dim, size in zip(dims, shape):
        if dim.isdigit():
            if size != int(dim):
                raise ValueError(f"{name} must have shape ({pattern}), got {shape}")
        elif dim in bound and bound[dim] != size:
            raise ValueError(f"{name} must have shape ({pattern}) with {dim}={bound[dim]}, got {shape}")
        else:
            bound[dim] = size
    return bound

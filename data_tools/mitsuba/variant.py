"""Mitsuba variant selection.

``llvm_ad_rgb`` (vectorised, JIT-compiled) is much faster than ``scalar_rgb`` but needs an LLVM
shared library that Dr.Jit can drive: Debian's ``libllvm19`` works, while libLLVM 15 aborts the
whole process on the first render. Every candidate library is therefore tried in a
subprocess that renders a tiny scene; the first that succeeds is used (its path is put in
``DRJIT_LIBLLVM_PATH`` before mitsuba is imported), otherwise ``scalar_rgb``.
"""

from __future__ import annotations

import glob
import logging
import os
import re
import subprocess
import sys
from types import ModuleType

log = logging.getLogger(__name__)

FAST, SAFE = "llvm_ad_rgb", "scalar_rgb"
_PROBE = """
import mitsuba as mi
mi.set_variant({variant!r})
scene = mi.load_dict({{"type": "scene", "integrator": {{"type": "path", "max_depth": 2}},
    "shape": {{"type": "sphere", "center": [0, 0, 3]}}, "light": {{"type": "constant"}},
    "sensor": {{"type": "perspective", "film": {{"type": "hdrfilm", "width": 4, "height": 4}}}}}})
img = mi.render(scene, spp=2)
assert img.shape == (4, 4, 3)
print("probe-ok")
"""
_LLVM_GLOBS = ("/usr/lib/x86_64-linux-gnu/libLLVM*.so*", "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
               "/usr/lib/llvm-*/lib/libLLVM*.so*", "/usr/local/lib/libLLVM*.so*", "/usr/lib64/libLLVM*.so*",
               "/opt/homebrew/opt/llvm/lib/libLLVM.dylib", "/usr/local/opt/llvm/lib/libLLVM.dylib")


def _llvm_version(path: str) -> int:
    m = re.search(r"LLVM-?(\d+)", path) or re.search(r"llvm-(\d+)", path)
    return int(m.group(1)) if m else 0


def llvm_candidates() -> list[str | None]:
    """LLVM libraries to try, newest first: ``$DRJIT_LIBLLVM_PATH`` if set, the system's
    ``libLLVM*`` and finally ``None`` (Dr.Jit's own search)."""
    found = sorted({os.path.realpath(p) for pattern in _LLVM_GLOBS for p in glob.glob(pattern)}, key=_llvm_version, reverse=True)
    first = [os.environ["DRJIT_LIBLLVM_PATH"]] if os.environ.get("DRJIT_LIBLLVM_PATH") else []
    return [*first, *[p for p in found if p not in first], None]


def probe(variant: str, llvm_path: str | None = None, timeout_s: float = 120.0) -> bool:
    """True when a subprocess can render a 4x4 image with ``variant`` (and ``llvm_path``)."""
    env = dict(os.environ)
    env.pop("DRJIT_LIBLLVM_PATH", None)
    if llvm_path:
        env["DRJIT_LIBLLVM_PATH"] = llvm_path
    try:
        r = subprocess.run([sys.executable, "-c", _PROBE.format(variant=variant)], env=env, capture_output=True,
                           text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        log.info("mitsuba %s with %s: timed out", variant, llvm_path or "default LLVM")
        return False
    ok = r.returncode == 0 and "probe-ok" in r.stdout
    log.info("mitsuba %s with %s: %s", variant, llvm_path or "default LLVM", "works" if ok else f"fails (exit {r.returncode})")
    return ok


def choose_variant(requested: str | None = None) -> tuple[str, str | None]:
    """``(variant, llvm_path)``: ``requested`` as given, else the fast variant with the first
    working LLVM, else the scalar one."""
    if requested:
        return requested, os.environ.get("DRJIT_LIBLLVM_PATH")
    for path in llvm_candidates():
        if probe(FAST, path):
            return FAST, path
    return SAFE, None


def activate(requested: str | None = None) -> ModuleType:
    """Import mitsuba with the chosen variant set (see :func:`choose_variant`); returns the module.

    Raises:
        ImportError: mitsuba is not installed.
        ValueError: ``requested`` is not a variant of this mitsuba build.
    """
    variant, path = choose_variant(requested)
    if path:
        os.environ["DRJIT_LIBLLVM_PATH"] = path
    import mitsuba as mi

    if variant not in mi.variants():
        raise ValueError(f"mitsuba variant {variant!r} is not available; this build has {mi.variants()}")
    mi.set_variant(variant)
    log.info("mitsuba %s: variant %s%s", mi.__version__, variant, f" (LLVM {path})" if path else "")
    return mi

"""Classical defocus renderers (torch, no file I/O).

``scatter`` is the reference: occlusion-aware layered scatter in linear HDR. ``reference``
holds slow, readable loop versions that the fast paths are tested against.
"""

from .scatter import render_defocus, scatter_defocus, scatter_layers, slice_by_coc

__all__ = ["render_defocus", "scatter_defocus", "scatter_layers", "slice_by_coc"]

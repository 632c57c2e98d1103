"""Classical defocus renderers (torch, no file I/O).

``scatter`` is the reference: occlusion-aware layered scatter in linear HDR. ``reference``
holds slow, readable loop versions that the fast paths are tested against.
"""

from ..ops.fftconv import fft_convolve2d
from .scatter import render_defocus, scatter_defocus, scatter_layers, slice_by_coc

__all__ = ["fft_convolve2d", "render_defocus", "scatter_defocus", "scatter_layers", "slice_by_coc"]

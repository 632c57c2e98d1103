"""The compositing runtime: exported ONNX models on CPU with numpy and onnxruntime, never torch
(compositing machines have no torch). Imports only ``neuralbokeh.core``.

    from neuralbokeh.runtime import BokehModel
"""

from .onnx_model import BokehModel

__all__ = ["BokehModel"]

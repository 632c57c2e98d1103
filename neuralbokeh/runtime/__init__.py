"""The compositing runtime: exported ONNX models on CPU with numpy and onnxruntime, never torch
(compositing machines have no torch). Imports only ``neuralbokeh.core``.

    from neuralbokeh.runtime import OnnxBokeh
"""

from .onnx_model import OnnxBokeh

__all__ = ["OnnxBokeh"]

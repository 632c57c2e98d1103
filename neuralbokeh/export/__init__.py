"""Export of trained networks to ONNX for the torch-free compositing runtime.

``graph.py`` builds the ONNX graph from weights (onnx + numpy), ``lowrank.py`` factorises large
kernels into separable pairs (numpy), ``exporter.py`` loads a checkpoint, exports and checks
onnxruntime against PyTorch. The CLI is ``export.py`` at the repository root.
"""

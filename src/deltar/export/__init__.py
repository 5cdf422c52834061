"""Model export (ONNX) and the onnxruntime runner: see :mod:`deltar.export.onnx`."""

"""From an image and a zone frame to a depth map: the estimator and what it needs.

``load_estimator(source)`` builds an estimator from any model source (bundled name,
checkpoint, official weights, ONNX file, preset). Torch is imported only inside
functions, so importing this package stays light.
"""

from deltar.inference.checks import InputSizeError
from deltar.inference.loading import MODEL_SOURCE_KINDS, load_estimator, resolve_source

__all__ = ["MODEL_SOURCE_KINDS", "InputSizeError", "load_estimator", "resolve_source"]

"""Monocular depth backends behind one protocol (``DepthBackend.predict``).

``onnx`` runs any depth network exported to ONNX; ``simulated`` makes monocular-like
predictions from simulator ground truth with documented errors. Backends are imported
lazily by ``make_backend`` so that ``import toolkit.depth`` never pulls onnxruntime.
"""

from toolkit.depth.protocol import DEPTH_KINDS, DepthBackend, DepthKind, DepthPrediction

__all__ = ["DEPTH_KINDS", "DepthBackend", "DepthKind", "DepthPrediction"]

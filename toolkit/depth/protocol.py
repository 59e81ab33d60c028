"""The one protocol every depth backend follows: an RGB image in, depth and its meaning out.

``kind`` says how later stages must read ``values``:

- ``metric_depth``: z-depth in metres (a metric network; its scale may still be off);
- ``relative_depth``: z-depth up to one unknown positive scale (``z = s * values``);
- ``relative_disparity``: inverse depth up to scale and shift (``1 / z = s * values + t``),
  what Depth Anything's and MiDaS's relative models output.

Invalid pixels are NaN (never 0: 0 is a valid disparity).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Protocol, runtime_checkable

import numpy as np

DepthKind = Literal["metric_depth", "relative_depth", "relative_disparity"]
DEPTH_KINDS: tuple[str, ...] = ("metric_depth", "relative_depth", "relative_disparity")


@dataclass
class DepthPrediction:
    """One frame's prediction at the image's own resolution."""

    values: np.ndarray  # [H, W] float32, NaN where invalid
    kind: DepthKind
    latency_s: float = 0.0  # time spent in the network (or simulator) for this frame
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.values = np.asarray(self.values, dtype=np.float32)
        if self.values.ndim != 2:
            raise ValueError(f"depth prediction must be [H, W], got {self.values.shape}")
        if self.kind not in DEPTH_KINDS:
            raise ValueError(f"unknown depth kind {self.kind!r}; expected one of {DEPTH_KINDS}")

    @property
    def is_disparity(self) -> bool:
        return self.kind == "relative_disparity"

    def as_depth(self, scale: float = 1.0, shift: float = 0.0) -> np.ndarray:
        """[H, W] float32 z-depth after applying a scale and shift.

        Depth kinds: ``scale * values + shift`` (NaN where the value or the result is not
        positive). Disparity: ``1 / (scale * values + shift)``; pixels whose corrected
        disparity is not positive are NaN (beyond infinity).
        """
        v = self.values  # float32 throughout: this runs on every pixel of every frame
        with np.errstate(divide="ignore", invalid="ignore"):
            if self.is_disparity:
                disp = np.float32(scale) * v + np.float32(shift)
                z = np.where(disp > 0, np.float32(1.0) / disp, np.float32(np.nan))
            else:
                z = np.float32(scale) * v
                if shift:
                    z += np.float32(shift)
                z = np.where((v > 0) & (z > 0), z, np.float32(np.nan))
        return z.astype(np.float32, copy=False)


@runtime_checkable
class DepthBackend(Protocol):
    """Anything that turns an RGB frame into a ``DepthPrediction``."""

    kind: DepthKind

    def predict(self, rgb: np.ndarray) -> DepthPrediction:
        """``rgb`` [H, W, 3] uint8 -> prediction with ``values`` [H, W]."""
        ...

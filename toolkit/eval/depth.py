"""Depth accuracy: RMSE, AbsRel, delta < 1.25 against lidar ranges or ground-truth depth.

The paper's protocol (Table IV) compares depth with the lidar at the projected lidar
pixels; with a simulator the whole image is compared with ground truth too. Both are
the same arithmetic on (prediction, reference) pairs, so one function serves both.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


@dataclass(frozen=True)
class DepthErrors:
    """Errors of predicted z-depth against a reference, over ``count`` valid pairs."""

    rmse_m: float
    mae_m: float
    absrel: float  # mean |pred - ref| / ref
    delta1: float  # fraction with max(pred/ref, ref/pred) < 1.25
    count: int

    def as_dict(self, prefix: str = "") -> dict[str, float | int]:
        return {f"{prefix}{k}": v for k, v in asdict(self).items()}


NAN_ERRORS = DepthErrors(float("nan"), float("nan"), float("nan"), float("nan"), 0)


def depth_errors(pred: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None,
                 max_depth: float | None = None) -> DepthErrors:
    """Errors of ``pred`` against ``ref`` (same shape, metres; NaN, 0 and +inf invalid in
    either: +inf is a lidar beam without return, not a range)."""
    return DepthReference(ref, mask, max_depth).errors(pred)


class DepthReference:
    """A reference depth [any shape] made ready once to score several predictions of its
    pixels (``errors``): its validity test and its valid values in float64 are the same
    for each (the fuse stage scores three depths of every frame against its true depth).
    ``mask`` and ``max_depth`` as for ``depth_errors``."""

    def __init__(self, ref: np.ndarray, mask: np.ndarray | None = None,
                 max_depth: float | None = None) -> None:
        r = np.asarray(ref).reshape(-1)
        with np.errstate(invalid="ignore"):
            # Comparisons are False for NaN, so these also drop NaN.
            ok = (r > 0) & (r < np.inf)  # [P]
            if max_depth is not None:
                ok &= r <= max_depth
        if mask is not None:
            ok &= np.asarray(mask, bool).reshape(-1)
        self.size = r.size
        # None: every pixel is valid, and a prediction needs no gather to line up with it.
        self._ok: np.ndarray | None = None if ok.all() else ok
        self._ref = r[ok].astype(np.float64)  # [R] the valid values, in pixel order
        # max(p / r, r / p) < 1.25 without the two divisions (p, r > 0): 1.25 r is exact in
        # float64 for a float32 r, and the same for every prediction.
        self._ref_125 = 1.25 * self._ref  # [R]

    def errors(self, pred: np.ndarray) -> DepthErrors:
        """Errors of ``pred`` (the reference's size; NaN, 0 and +inf invalid) against it."""
        p = np.asarray(pred).reshape(-1)
        if p.size != self.size:
            raise ValueError(f"prediction of {p.size} values for a reference of {self.size}")
        # The validity test in the prediction's own precision and float64 for the valid
        # pairs only: this runs on three whole images per fused frame.
        if self._ok is not None:
            p = p[self._ok]  # [R]
        with np.errstate(invalid="ignore"):
            ok = (p > 0) & (p < np.inf)  # [R]
        n = int(np.count_nonzero(ok))
        if n == 0:
            return NAN_ERRORS
        r, r_125 = self._ref, self._ref_125
        if n < len(p):
            p, r, r_125 = p[ok], r[ok], r_125[ok]
        p = p.astype(np.float64)  # a copy of its own: the arithmetic below reuses it
        d1 = np.count_nonzero((p < r_125) & (r < 1.25 * p))
        e = np.subtract(p, r, out=p)
        se = np.dot(e, e)
        ae = np.abs(e, out=e)
        return DepthErrors(float(np.sqrt(se / n)), float(ae.sum() / n),
                           float(np.divide(ae, r, out=ae).sum() / n), float(d1 / n), n)


class ErrorAccumulator:
    """Pools pairs over many frames so that sequence figures weight every pixel alike."""

    def __init__(self) -> None:
        self.n = 0
        self.se = 0.0
        self.ae = 0.0
        self.rel = 0.0
        self.d1 = 0

    def add(self, pred: np.ndarray, ref: np.ndarray | DepthReference,
            mask: np.ndarray | None = None, max_depth: float | None = None) -> DepthErrors:
        """Pool ``pred``'s pairs with ``ref`` (``depth_errors``; a ``DepthReference``
        comes with its own mask and depth cap) and return their errors."""
        if isinstance(ref, DepthReference):
            if mask is not None or max_depth is not None:
                raise ValueError("a DepthReference has its mask and max_depth already")
            e = ref.errors(pred)
        else:
            e = depth_errors(pred, ref, mask, max_depth)
        if e.count:
            self.n += e.count
            self.se += e.rmse_m**2 * e.count
            self.ae += e.mae_m * e.count
            self.rel += e.absrel * e.count
            self.d1 += int(round(e.delta1 * e.count))
        return e

    def result(self) -> DepthErrors:
        if self.n == 0:
            return NAN_ERRORS
        return DepthErrors(float(np.sqrt(self.se / self.n)), self.ae / self.n, self.rel / self.n,
                           self.d1 / self.n, self.n)


def scale_error(estimated: np.ndarray, true: np.ndarray) -> dict[str, float]:
    """Per-frame scale error |s_est / s_true - 1| summarised (both [F], NaN skipped)."""
    e = np.asarray(estimated, np.float64)
    t = np.asarray(true, np.float64)
    ok = np.isfinite(e) & np.isfinite(t) & (t > 0)
    if not ok.any():
        return {"scale_error_mean": float("nan"), "scale_error_median": float("nan"),
                "scale_error_max": float("nan"), "frames": 0}
    rel = np.abs(e[ok] / t[ok] - 1.0)
    return {"scale_error_mean": float(rel.mean()), "scale_error_median": float(np.median(rel)),
            "scale_error_max": float(rel.max()), "frames": int(ok.sum())}

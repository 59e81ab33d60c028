"""Monocular-like depth predictions made from simulator ground truth.

A real monocular network is wrong in structured ways, and "without lidar" numbers only
mean something if the simulated errors are those and are stated. Each error below is one
documented parameter of ``SimulatedDepthParams`` (set in the recipe), applied in order:

1. invalid ground truth (0/NaN: a sensor's holes, in TUM RGB-D or a bag) stays invalid
   (NaN): there is nothing to make a prediction from;
2. ``edge_blur_px``: Gaussian blur of the depth, so edges become ramps (flying pixels)
   as with a network's limited receptive field at object borders; over the valid pixels
   only (filled with a far depth first, a hole's border came out up to 9 m deep);
3. ``distortion``: a smooth low-frequency multiplicative field ``exp(a * f(u, v, t))``
   (a few random cosines of ``distortion_cycles`` cycles per image, RMS 1) that drifts
   over ``distortion_frames`` frames: the shape error of monocular depth;
4. ``noise``: per-pixel multiplicative noise, spatially correlated over
   ``noise_corr_px``;
5. low texture: errors 3 and 4 are multiplied by ``1 + low_texture_gain * ramp``, the
   ramp rising from 0 at an image gradient of ``texture_threshold`` to 1 at none (flat
   walls are where networks guess);
6. ``scale``: one unknown scale for the whole sequence (prediction = scale * depth),
   optionally drawn per seed with ``scale_log_sigma``, times a slow per-frame wander
   (an Ornstein-Uhlenbeck process in log scale with stationary std ``wander_sigma`` and
   correlation time ``wander_frames``);
7. ``kind``: ``metric_depth``/``relative_depth`` output the depth; ``relative_disparity``
   outputs ``1 / depth + shift * median(1 / depth)`` (scale and shift unknown, as
   Depth Anything's relative models).

Everything is seeded: frame i always gets the same prediction for the same parameters.
The ``paper`` preset (the defaults) has a 1.5x scale error, chosen so that on the simulated
house the unscaled RMSE against the lidar (the paper's protocol) is near the paper's
unscaled figure (1.46 m with UniDepth). Its shape errors (2 % low-frequency distortion,
2.5x that on low-texture walls, 1 % noise, 1.5 px edge blur) leave an AbsRel of about 3 %
after per-frame scaling, near what small relative networks reach indoors after alignment.
"""

from __future__ import annotations

import time
from typing import Any

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from toolkit.depth.protocol import DepthKind, DepthPrediction


class SimulatedDepthParams(BaseModel):
    """Errors of the simulated monocular network (see the module docstring)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kind: DepthKind = "relative_depth"
    scale: float = Field(1.5, gt=0)  # prediction = scale * true depth
    scale_log_sigma: float = Field(0.0, ge=0)  # > 0: scale *= exp(N(0, sigma)) from the seed
    shift: float = 0.15  # disparity shift, fraction of the median disparity
    wander_sigma: float = Field(0.02, ge=0)  # stationary std of the log-scale wander
    wander_frames: float = Field(40.0, gt=0)  # correlation time of the wander
    distortion: float = Field(0.02, ge=0)  # RMS of the low-frequency log-depth field
    distortion_cycles: float = Field(0.8, gt=0)  # spatial frequency, cycles per image width
    distortion_frames: float = Field(80.0, gt=0)  # frames for the field to change fully
    edge_blur_px: float = Field(1.5, ge=0)  # Gaussian sigma on depth
    noise: float = Field(0.01, ge=0)  # relative per-pixel noise std
    noise_corr_px: float = Field(1.5, ge=0)
    low_texture_gain: float = Field(1.5, ge=0)
    texture_threshold: float = Field(6.0, gt=0)  # grey levels per pixel
    seed: int = Field(0, ge=0)


PRESETS: dict[str, dict[str, Any]] = {
    # The paper's unscaled error (defaults above).
    "paper": {},
    # Only the unknown scale: isolates the scale estimators.
    "scale_only": {"wander_sigma": 0.0, "distortion": 0.0, "edge_blur_px": 0.0, "noise": 0.0,
                   "low_texture_gain": 0.0},
    # The exact ground-truth depth, metric: the upper bound of the benchmark's rows (what a
    # perfect network would give at these poses).
    "groundtruth": {"kind": "metric_depth", "scale": 1.0, "wander_sigma": 0.0,
                    "distortion": 0.0, "edge_blur_px": 0.0, "noise": 0.0,
                    "low_texture_gain": 0.0},
    # A weaker network: stronger shape errors.
    "hard": {"wander_sigma": 0.05, "distortion": 0.08, "edge_blur_px": 3.0, "noise": 0.03},
}


def low_texture_weight(rgb: np.ndarray, threshold: float, window: int = 15) -> np.ndarray:
    """[H, W] float32 in [0, 1]: 1 where the smoothed grey gradient is far below
    ``threshold`` (grey levels/px), 0 on texture."""
    grey = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY).astype(np.float32)
    gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    mag = cv2.blur(np.sqrt(gx * gx + gy * gy), (window, window))
    return np.clip(1.0 - mag / np.float32(threshold), 0.0, 1.0)


def _blur_gain(sigma: float) -> float:
    """1 / the L2 norm of the kernel cv2.GaussianBlur uses for ``sigma`` on float32
    images: blurring white noise scales its std by that norm. Read off OpenCV itself (a
    blurred unit impulse is the kernel), not from the continuous limit 1 / (2 sqrt(pi)
    sigma), which gave 0.36x the std at sigma 0.1."""
    m = 2 * int(np.ceil(4 * sigma)) + 5  # room for OpenCV's radius of about 4 sigma
    impulse = np.zeros((m, m), np.float32)
    impulse[m // 2, m // 2] = 1.0
    k = cv2.GaussianBlur(impulse, (0, 0), sigma).astype(np.float64)
    return float(1.0 / np.sqrt(np.sum(k * k)))


class SimulatedDepthBackend:
    """``DepthBackend`` that needs ``gt_depth`` (and ``frame_index``) with each frame."""

    def __init__(self, params: SimulatedDepthParams | None = None) -> None:
        self.params = params or SimulatedDepthParams()
        self.kind: DepthKind = self.params.kind
        p = self.params
        rng = np.random.default_rng([p.seed, 1])
        # Drawn whatever the sigma (0 gives the scale itself): drawn only for a positive
        # sigma, turning it on redrew the whole distortion field below.
        self.sequence_scale = float(p.scale * np.exp(rng.normal(0.0, p.scale_log_sigma)))
        # Random cosines of the distortion field: 4 directions and phases per seed.
        n = 4
        ang = rng.uniform(0, np.pi, n)
        freq = p.distortion_cycles * rng.uniform(0.6, 1.4, n)
        self._dirs = np.stack([np.cos(ang), np.sin(ang)], -1) * freq[:, None]  # [n, 2]
        self._phase0 = rng.uniform(0, 2 * np.pi, n)
        self._phase_rate = rng.choice([-1.0, 1.0], n) * rng.uniform(0.5, 1.5, n)
        self._log_wander = np.zeros(0)
        self._grid_cache: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        self._noise_gain = _blur_gain(p.noise_corr_px) if p.noise_corr_px > 0 else 1.0

    # ------------------------------------------------------------------ pieces
    def frame_scale(self, index: int) -> float:
        """The true scale applied to frame ``index`` (sequence scale times wander)."""
        return self.sequence_scale * float(np.exp(self._wander(index)))

    def _wander(self, index: int) -> float:
        p = self.params
        if p.wander_sigma == 0:
            return 0.0
        # The series' first value is drawn before its steps, so a longer series begins
        # with the same values (numpy draws in order): frame i reads the same value
        # whichever length was generated, and a depth stage resumed at frame 300 predicts
        # what an uninterrupted one did. (Drawn after the steps, it changed with the
        # length, and the log-scale jumped at frames 256, 512, ...: 39x a normal step for
        # a wander of 2000 frames.)
        if len(self._log_wander) <= index:
            n = max(256, 2 * index)
            rng = np.random.default_rng([p.seed, 2])
            a = np.exp(-1.0 / p.wander_frames)
            first = rng.normal(0.0, p.wander_sigma)
            steps = rng.normal(0.0, p.wander_sigma * np.sqrt(1 - a * a), n)
            w = np.empty(n)
            w[0] = first
            for i in range(1, n):
                w[i] = a * w[i - 1] + steps[i]
            self._log_wander = w
        return float(self._log_wander[index])

    def _grid(self, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
        if (h, w) not in self._grid_cache:
            # Normalised by width so cycles mean "per image width" for any aspect.
            u = (np.arange(w, dtype=np.float32) / w)[None, :]
            v = (np.arange(h, dtype=np.float32) / w)[:, None]
            self._grid_cache[(h, w)] = (u, v)
        return self._grid_cache[(h, w)]

    def distortion_field(self, h: int, w: int, index: int) -> np.ndarray:
        """[H, W] float32 smooth field with RMS about 1 at frame ``index``."""
        u, v = self._grid(h, w)
        t = index / self.params.distortion_frames
        f = np.zeros((h, w), np.float32)
        for k in range(len(self._dirs)):
            ph = self._phase0[k] + 2 * np.pi * self._phase_rate[k] * t
            f += np.cos(2 * np.pi * (self._dirs[k, 0] * u + self._dirs[k, 1] * v) + ph,
                        dtype=np.float32)
        return f * np.float32(np.sqrt(2.0 / len(self._dirs)))

    def noise_field(self, h: int, w: int, index: int) -> np.ndarray:
        rng = np.random.default_rng([self.params.seed, 3, index])
        n = rng.standard_normal((h, w), dtype=np.float32)
        s = self.params.noise_corr_px
        if s > 0:
            # Undone so that 'noise' is the per-pixel std the recipe asked for.
            n = cv2.GaussianBlur(n, (0, 0), s)
            n *= np.float32(self._noise_gain)
        return n

    # ------------------------------------------------------------------ predict
    def simulate(self, rgb: np.ndarray, gt_depth: np.ndarray, index: int) -> np.ndarray:
        """[H, W] float32 values of the configured kind."""
        p = self.params
        z = np.asarray(gt_depth, dtype=np.float32)
        h, w = z.shape
        if rgb.shape[:2] != (h, w):
            raise ValueError(f"image {rgb.shape[:2]} and ground-truth depth {z.shape} differ")
        valid = np.isfinite(z) & (z > 0)  # [H, W]
        if valid.all():
            if p.edge_blur_px > 0:
                z = cv2.GaussianBlur(z, (0, 0), p.edge_blur_px)
        else:
            z = np.where(valid, z, np.float32(0.0))
            if p.edge_blur_px > 0:
                # Normalised convolution: the blur of the valid depth over the blur of
                # the valid mask, so a hole adds nothing to its border.
                m = valid.astype(np.float32)
                wsum = cv2.GaussianBlur(m, (0, 0), p.edge_blur_px)
                with np.errstate(invalid="ignore", divide="ignore"):
                    z = cv2.GaussianBlur(z, (0, 0), p.edge_blur_px) / wsum
            z = np.where(valid, z, np.float32(np.nan))
        gain = np.float32(1.0)
        if p.low_texture_gain > 0 and (p.distortion > 0 or p.noise > 0):
            gain = 1.0 + np.float32(p.low_texture_gain) * low_texture_weight(
                rgb, p.texture_threshold)
        log_err = np.zeros((h, w), np.float32)
        if p.distortion > 0:
            log_err += np.float32(p.distortion) * self.distortion_field(h, w, index)
        if p.noise > 0:
            log_err += np.float32(p.noise) * self.noise_field(h, w, index)
        z = z * np.exp(log_err * gain) * np.float32(self.frame_scale(index))
        if p.kind == "relative_disparity":
            disp = 1.0 / z
            return (disp + np.float32(p.shift) * np.nanmedian(disp)).astype(np.float32)
        return z.astype(np.float32)

    def predict(self, rgb: np.ndarray, gt_depth: np.ndarray | None = None,
                frame_index: int = 0, **_: Any) -> DepthPrediction:
        """Prediction for one frame; ``gt_depth`` [H, W] metres is required."""
        if gt_depth is None:
            raise ValueError("the simulated depth backend needs the frame's ground-truth depth; "
                             "it only runs on simulator sequences (use backend 'onnx' otherwise)")
        t0 = time.perf_counter()
        values = self.simulate(rgb, gt_depth, frame_index)
        return DepthPrediction(values, self.kind, latency_s=time.perf_counter() - t0,
                               extra={"true_scale": self.frame_scale(frame_index)})

    def describe(self) -> dict[str, Any]:
        return {"backend": "simulated", "kind": self.kind,
                "sequence_scale": self.sequence_scale, "params": self.params.model_dump()}

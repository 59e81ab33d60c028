"""Image quality metrics: PSNR and SSIM, pure functions on numpy arrays or torch tensors.

Images are [H, W] or [H, W, C], values in 0..``data_range`` (floats; uint8 is divided by
255 and compared on a 0..1 range). SSIM is the standard Wang et al. 2004 form with an
11x11 Gaussian window (sigma 1.5), K1 = 0.01, K2 = 0.03, computed on the valid region
(no padding) and averaged over pixels and channels - the definition of torchmetrics and
scikit-image's ``structural_similarity(gaussian_weights=True,
use_sample_covariance=False)``, which the tests compare against (3DGS's training loss
zero-pads the border and averages over every pixel: 0.949 against 0.946 on one pair).
The torch version is differentiable, so training uses the same function as evaluation.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

Array = np.ndarray | Tensor


def _as_float(img: Array) -> Tensor:
    if isinstance(img, np.ndarray):
        t = torch.from_numpy(np.ascontiguousarray(img))
        if img.dtype == np.uint8:
            return t.to(torch.float64) / 255.0
        return t.to(torch.float64)
    if img.dtype == torch.uint8:
        return img.to(torch.float32) / 255.0
    return img


def _check_uint8_range(name: str, data_range: float, *images: Array) -> None:
    """uint8 images are compared on 0..1: scikit-image's data_range=255 for them made
    PSNR 48 dB too high and SSIM near 1."""
    if data_range != 1.0 and any(img.dtype in (np.uint8, torch.uint8) for img in images):
        raise ValueError(f"{name}: uint8 images are compared on 0..1 here; leave data_range "
                         f"at 1 (got {data_range:g})")


def _as_mask(mask: Array) -> Tensor:
    """A mask as bool, whatever it came as: a 0/1 uint8 mask read as an image was 0 and
    1/255, and SSIM found no pixel in it."""
    if isinstance(mask, np.ndarray):
        return torch.from_numpy(np.ascontiguousarray(mask) != 0)
    return mask.bool()


def _check(a: Tensor, b: Tensor) -> None:
    if a.shape != b.shape:
        raise ValueError(f"images differ in shape: {tuple(a.shape)} vs {tuple(b.shape)}")
    if a.dim() not in (2, 3):
        raise ValueError(f"images must be [H, W] or [H, W, C], got {tuple(a.shape)}")


def _out(x: Tensor, like: Array) -> Any:
    return float(x) if isinstance(like, np.ndarray) else x


def mse(a: Array, b: Array, mask: Array | None = None) -> Any:
    """Mean squared error (over ``mask`` [H, W] pixels when given)."""
    ta, tb = _as_float(a), _as_float(b)
    _check(ta, tb)
    d = (ta - tb) ** 2
    if mask is not None:
        d = d[_as_mask(mask)]
    return _out(d.mean(), a)


def psnr(a: Array, b: Array, data_range: float = 1.0, mask: Array | None = None) -> Any:
    """Peak signal-to-noise ratio in dB; inf for identical images. uint8 images count as
    0..1; float ones must lie in 0..data_range (a numpy float image in 0..255 with the
    default 1.0 is refused: it scored -42 dB)."""
    _check_uint8_range("psnr", data_range, a, b)
    for img in (a, b):
        if isinstance(img, np.ndarray) and img.dtype != np.uint8 and img.size:
            top = float(np.nanmax(img))
            if top > 1.5 * data_range:
                raise ValueError(f"psnr: values reach {top:g} but data_range is "
                                 f"{data_range:g}: divide 0..255 float images by 255 (or "
                                 "pass uint8 images)")
    m = mse(a, b, mask)
    if isinstance(a, np.ndarray):
        return float("inf") if m == 0 else 10.0 * math.log10(data_range**2 / m)
    return 10.0 * torch.log10(data_range**2 / m)


def _gauss_window(size: int, sigma: float, dtype: torch.dtype, device: torch.device) -> Tensor:
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def ssim_map(a: Array, b: Array, data_range: float = 1.0, window: int = 11,
             sigma: float = 1.5) -> Tensor:
    """[H - window + 1, W - window + 1, C] local SSIM (valid region only)."""
    _check_uint8_range("ssim", data_range, a, b)
    ta, tb = _as_float(a), _as_float(b)
    _check(ta, tb)
    if ta.dim() == 2:
        ta, tb = ta[..., None], tb[..., None]
    if min(ta.shape[0], ta.shape[1]) < window:
        raise ValueError(f"images of {tuple(ta.shape[:2])} are smaller than the SSIM window "
                         f"({window})")
    C = ta.shape[2]
    g = _gauss_window(window, sigma, ta.dtype, ta.device)
    x, y = ta.permute(2, 0, 1), tb.permute(2, 0, 1)  # [C, H, W]
    # The five local moments blurred together, a column pass then a row pass (depthwise
    # convolutions): 2 convolutions instead of 10, 2 backward instead of 6 (a masked SSIM's
    # forward and backward on one CPU thread: 160x120 9.3 -> 6.3 ms, 640x480 116 -> 96 ms).
    z = torch.cat([x, y, x * x, y * y, x * y])[None]  # [1, 5C, H, W]
    kv = g.reshape(1, 1, window, 1).expand(5 * C, 1, window, 1)
    kh = g.reshape(1, 1, 1, window).expand(5 * C, 1, 1, window)
    m = F.conv2d(F.conv2d(z, kv, groups=5 * C), kh, groups=5 * C)[0]  # [5C, h, w]
    mu_x, mu_y, exx, eyy, exy = m.split(C)
    mxx, myy, mxy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    s = ((2 * mxy + c1) * (2 * (exy - mxy) + c2)) / (
        (mxx + myy + c1) * ((exx - mxx) + (eyy - myy) + c2))
    return s.permute(1, 2, 0)


def ssim(a: Array, b: Array, data_range: float = 1.0, window: int = 11,
         sigma: float = 1.5, mask: Array | None = None) -> Any:
    """Mean SSIM: a float for numpy input, a differentiable 0-d tensor for torch input.

    ``mask`` [H, W] bool: the pixels that count (an undistorted image's lens corners have
    no source pixel); the mean is then over the windows lying wholly on them (or, with
    none, over those centred on them). Windows over masked pixels that hold the target
    itself scored 1 and lifted a flat grey render from 0.07 to 0.15."""
    s = ssim_map(a, b, data_range, window, sigma)  # [h, w, C]
    if mask is None:
        return _out(s.mean(), a)
    m = _as_mask(mask).to(s.device, s.dtype)
    if m.shape != _as_float(a).shape[:2]:
        raise ValueError(f"mask of {tuple(m.shape)} for images of {tuple(_as_float(a).shape)}")
    # [h, w] valid share of each window, a column then a row mean (121 -> 22 additions a
    # pixel: the 11x11 pool took 19 ms at 640x480)
    inside = F.avg_pool2d(F.avg_pool2d(m[None, None], (window, 1), stride=1), (1, window),
                          stride=1)[0, 0]
    keep = inside > 1.0 - 1e-6
    n = keep.sum()
    if not bool(n):
        r = (window - 1) // 2
        keep = m[r:r + s.shape[0], r:r + s.shape[1]] > 0.5
        n = keep.sum()
        if not bool(n):
            raise ValueError("the SSIM mask holds no pixel")
    # A select and a sum, not s[keep]: no index kernels and no scatter in the backward
    # pass; torch.where, not s * keep, so a NaN in a window that does not count (outside
    # the mask) stays out of the mean.
    return _out(torch.where(keep[..., None], s, 0.0).sum() / (n * s.shape[2]), a)

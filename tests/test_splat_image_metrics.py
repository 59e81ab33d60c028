"""toolkit.eval.image: PSNR and SSIM against scikit-image, numpy and torch inputs alike."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from toolkit.eval.image import psnr, ssim


def _pair(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    a = rng.random((40, 52, 3))
    # a smooth image plus noise, so SSIM is neither ~0 nor ~1
    y, x = np.mgrid[0:40, 0:52]
    b = np.clip(0.5 + 0.3 * np.sin(x / 5.0)[..., None] + 0.2 * (a - 0.5), 0, 1)
    return a, b


def test_ssim_matches_scikit_image() -> None:
    metrics = pytest.importorskip("skimage.metrics")
    a, b = _pair()
    ref = metrics.structural_similarity(a, b, gaussian_weights=True, sigma=1.5,
                                        use_sample_covariance=False, data_range=1.0,
                                        channel_axis=-1)
    assert abs(ssim(a, b) - ref) < 1e-6
    assert abs(ssim(a, a) - 1.0) < 1e-12
    # grey images too
    ref2 = metrics.structural_similarity(a[..., 0], b[..., 0], gaussian_weights=True, sigma=1.5,
                                         use_sample_covariance=False, data_range=1.0)
    assert abs(ssim(a[..., 0], b[..., 0]) - ref2) < 1e-6


def test_psnr_matches_scikit_image_and_uint8() -> None:
    metrics = pytest.importorskip("skimage.metrics")
    a, b = _pair(1)
    assert abs(psnr(a, b) - metrics.peak_signal_noise_ratio(a, b, data_range=1.0)) < 1e-9
    a8, b8 = (a * 255).round().astype(np.uint8), (b * 255).round().astype(np.uint8)
    ref = metrics.peak_signal_noise_ratio(a8, b8, data_range=255)
    assert abs(psnr(a8, b8) - ref) < 1e-9
    assert psnr(a, a) == float("inf")
    # scikit-image's call for uint8 (data_range=255) scored 48 dB too high: refused.
    for fn in (psnr, ssim):
        with pytest.raises(ValueError, match="uint8 images are compared on 0..1"):
            fn(a8, b8, data_range=255)


def test_torch_version_is_differentiable_and_agrees() -> None:
    a, b = _pair(2)
    ta = torch.tensor(a, dtype=torch.float64, requires_grad=True)
    tb = torch.tensor(b, dtype=torch.float64)
    s = ssim(ta, tb)
    assert isinstance(s, torch.Tensor) and abs(float(s.detach()) - ssim(a, b)) < 1e-12
    s.backward()
    assert ta.grad is not None and torch.isfinite(ta.grad).all() and ta.grad.abs().sum() > 0
    assert abs(float(psnr(ta.detach(), tb)) - psnr(a, b)) < 1e-9


def test_masked_ssim_scores_the_windows_on_valid_pixels() -> None:
    """Pixels outside the mask hold the target (the lens corners of an undistorted image):
    SSIM is the mean over windows wholly inside the mask, the same as cropping to it."""
    a, b = _pair(3)
    mask = np.zeros(a.shape[:2], bool)
    mask[5:35, 10:45] = True
    filled = np.where(mask[..., None], a, b)  # outside the mask: the target itself
    crop = (slice(5, 35), slice(10, 45))
    assert ssim(filled, b) > ssim(a[crop], b[crop]) + 0.05  # unmasked: lifted by the fill
    assert abs(ssim(filled, b, mask=mask) - ssim(a[crop], b[crop])) < 1e-12
    t = ssim(torch.tensor(filled), torch.tensor(b), mask=torch.tensor(mask))
    assert abs(float(t) - ssim(a[crop], b[crop])) < 1e-12
    # Whatever lies outside the mask, even no number at all, does not count.
    holed = filled.astype(np.float64)
    holed[~mask] = np.nan
    assert abs(ssim(holed, b, mask=mask) - ssim(a[crop], b[crop])) < 1e-12
    with pytest.raises(ValueError, match="no pixel"):
        ssim(a, b, mask=np.zeros(a.shape[:2], bool))


def test_errors() -> None:
    a, b = _pair()
    with pytest.raises(ValueError, match="shape"):
        ssim(a, b[:-1])
    with pytest.raises(ValueError, match="smaller than the SSIM window"):
        ssim(a[:8, :8], b[:8, :8])
    with pytest.raises(ValueError, match="divide 0..255 float images by 255"):
        psnr(a * 255, b * 255)  # scored -42 dB
    assert np.isfinite(psnr(a * 255, b * 255, data_range=255.0))


def test_a_uint8_mask_counts_its_nonzero_pixels() -> None:
    """A 0/1 uint8 mask was read as an image (0 and 1/255): PSNR took it, SSIM found no
    pixel in it."""
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, (32, 32, 3), dtype=np.uint8)
    b = a.copy()
    b[:, :8] = 0  # different outside the mask only
    inside = np.zeros((32, 32), bool)
    inside[:, 16:] = True
    for mask in (inside, inside.astype(np.uint8), inside.astype(np.uint8) * 255):
        assert ssim(a, b, mask=mask) == pytest.approx(1.0)
        assert psnr(a, b, mask=mask) == float("inf")

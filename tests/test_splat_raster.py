"""Rasterisers: the expected ellipse, gradients vs finite differences, C++ vs reference.

The C++ extension is built once per session (a module fixture; the first build takes
20 s to 2 min and is cached afterwards) and its tests skip, saying why, when no compiler
is available.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from toolkit.camera import PinholeCamera
from toolkit.splat.model import Gaussians, init_from_points
from toolkit.splat.rasterize import cpp_ext, render, resolve_backend
from toolkit.splat.rasterize.common import CameraTensors, project
from toolkit.splat.synthetic import perturbed, room_camera, room_points

# one torch thread for every test here (conftest.one_thread)
pytestmark = pytest.mark.usefixtures("one_thread")



def _one_gaussian(dtype: torch.dtype = torch.float64) -> tuple[Gaussians, np.ndarray]:
    """One anisotropic, rotated Gaussian 2.5 m in front of the camera (world = camera)."""
    mean = torch.tensor([[0.15, -0.1, 2.5]], dtype=dtype)
    quat = torch.tensor([[np.cos(0.3), 0.2 * np.sin(0.3), 0.1, np.sin(0.3)]], dtype=dtype)
    log_s = torch.log(torch.tensor([[0.12, 0.05, 0.02]], dtype=dtype))
    logit = torch.logit(torch.tensor([0.8], dtype=dtype))
    sh = torch.zeros(1, 1, 3, dtype=dtype)
    sh[0, 0] = torch.tensor([0.3, -0.2, 0.1], dtype=dtype)
    return Gaussians(mean, quat, log_s, logit, sh), np.eye(4)


def _expected_alpha(g: Gaussians, cam: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
    """Independent numpy EWA: alpha image [H, W] and projected centre [2]."""
    from scipy.spatial.transform import Rotation

    m = g.means[0].numpy()
    q = g.quats[0].numpy()
    R = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()  # scipy is xyzw
    S = np.diag(np.exp(g.log_scales[0].numpy()))
    cov3 = R @ S @ S @ R.T
    x, y, z = m
    J = np.array([[cam.fx / z, 0, -cam.fx * x / z**2], [0, cam.fy / z, -cam.fy * y / z**2]])
    cov2 = J @ cov3 @ J.T + 0.3 * np.eye(2)
    centre = np.array([cam.fx * x / z + cam.cx, cam.fy * y / z + cam.cy])
    u, v = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    d = np.stack([u - centre[0], v - centre[1]], -1)
    q2 = np.einsum("hwi,ij,hwj->hw", d, np.linalg.inv(cov2), d)
    op = float(torch.sigmoid(g.opacity_logits[0]))
    alpha = np.minimum(op * np.exp(-0.5 * q2), 0.999)
    alpha[alpha < 1 / 255] = 0
    return alpha, centre


@pytest.mark.parametrize("backend", ["torch", "cpp"])
def test_single_gaussian_renders_expected_ellipse(backend: str, request: pytest.FixtureRequest) -> (
    None
):
    if backend == "cpp":
        request.getfixturevalue("cpp")
    g, T = _one_gaussian()
    cam = PinholeCamera(96, 72, 80.0, 82.0, 47.3, 35.6)
    out = render(g, cam, T, background=[0.0, 0.0, 0.0], backend=backend)
    assert out.meta.backend == backend
    alpha = out.alpha.numpy()
    want, centre = _expected_alpha(g, cam)
    # Pixel-wise the same ellipse (float64 end to end).
    assert np.abs(alpha - want).max() < 1e-9
    # Its alpha-weighted centroid is the projected centre (symmetric, so to truncation).
    u, v = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    c = np.array([(alpha * u).sum(), (alpha * v).sum()]) / alpha.sum()
    assert np.abs(c - centre).max() < 0.01
    # Colour = SH colour x alpha over a black background; depth = z wherever it is seen.
    rgb = 0.28209479177387814 * g.sh[0, 0].numpy() + 0.5
    np.testing.assert_allclose(out.color.numpy(), alpha[..., None] * rgb, atol=1e-9)
    seen = alpha > 0
    np.testing.assert_allclose(out.depth.numpy()[seen], 2.5, rtol=1e-9)
    np.testing.assert_allclose(out.meta.means2d.detach().numpy()[0], centre, atol=1e-9)


def _small_scene(dtype: torch.dtype, n: int = 4, seed: int = 0) -> list[torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=gen, dtype=dtype) * torch.tensor([0.6, 0.4, 0.5],
                                                                       dtype=dtype)
    means = means + torch.tensor([-0.3, -0.2, 2.0], dtype=dtype)
    quats = torch.randn(n, 4, generator=gen, dtype=dtype)
    log_s = torch.log(0.08 + 0.1 * torch.rand(n, 3, generator=gen, dtype=dtype))
    logit = torch.logit(0.2 + 0.4 * torch.rand(n, generator=gen, dtype=dtype))
    sh = 0.3 * torch.randn(n, 4, 3, generator=gen, dtype=dtype)
    viewmat = torch.eye(4, dtype=dtype)
    viewmat[:3, 3] = torch.tensor([0.02, -0.01, 0.05], dtype=dtype)
    return [t.requires_grad_(True) for t in (means, quats, log_s, logit, sh, viewmat)]


@pytest.mark.parametrize("backend", ["torch", "cpp"])
def test_gradients_match_finite_differences(backend: str, request: pytest.FixtureRequest) -> (
    None
):
    if backend == "cpp":
        request.getfixturevalue("cpp")
    cam = PinholeCamera(16, 12, 14.0, 14.0, 7.5, 5.5)
    inputs = _small_scene(torch.float64, n=3)
    # The Jacobian is checked through 6 random projections of the 960 image values (colour,
    # alpha, accumulated depth): a wrong derivative anywhere shows up in all of them, and
    # gradcheck then needs 6 backward passes instead of 960.
    proj = torch.randn(6, 12 * 16 * 5, generator=torch.Generator().manual_seed(1),
                       dtype=torch.float64)

    def f(means: torch.Tensor, quats: torch.Tensor, log_s: torch.Tensor, logit: torch.Tensor,
          sh: torch.Tensor, viewmat: torch.Tensor) -> torch.Tensor:
        out = render(Gaussians(means, quats, log_s, logit, sh), cam, viewmat,
                     background=[0.2, 0.1, 0.3], backend=backend, tile_size=8)
        img = torch.cat([out.color, out.alpha[..., None], (out.depth * out.alpha)[..., None]],
                        -1)
        return proj @ img.reshape(-1)

    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-4,
                                    nondet_tol=1e-10)


def _bench_like(n: int, width: int, height: int) -> tuple[Gaussians, PinholeCamera, np.ndarray]:
    pts, rgb = room_points(n, seed=3)
    g = perturbed(init_from_points(pts, rgb, sh_degree=3).gaussians(), seed=3)
    g = Gaussians(*(t.detach().clone().requires_grad_(True) for t in
                    (g.means, g.quats, g.log_scales, g.opacity_logits, g.full_sh())))
    cam, T = room_camera(width, height)
    return g, cam, T


def _render_and_grads(g: Gaussians, cam: PinholeCamera, T: np.ndarray, backend: str,
                      tile: int) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    out = render(g, cam, T, background=[0.1, 0.2, 0.3], backend=backend, tile_size=tile)
    wts = torch.linspace(0.0, 1.0, cam.width * cam.height * 3).reshape(cam.height, cam.width, 3)
    loss = (out.color * wts).sum() + out.alpha.sum() + 0.1 * (out.depth * out.alpha).sum()
    params = [g.means, g.quats, g.log_scales, g.opacity_logits, g.sh]
    grads = torch.autograd.grad(loss, params)
    images = [out.color.detach(), out.alpha.detach(), (out.depth * out.alpha).detach()]
    return images, list(grads)


def test_cpp_matches_reference(cpp: None) -> None:
    g, cam, T = _bench_like(3000, 80, 60)
    ref_img, ref_grad = _render_and_grads(g, cam, T, "torch", 8)
    assert float(ref_img[1].mean()) > 0.5  # the view is mostly covered: a real test
    for tile in (8, 16, 32):
        img, grad = _render_and_grads(g, cam, T, "cpp", tile)
        color, alpha, depth_acc = (a - b for a, b in zip(img, ref_img, strict=True))
        # 3e-6, not 1e-6: the projection runs in C++ too (another float32 rounding order;
        # 1.04e-6 seen, 2026-11-28)
        assert float(color.abs().max()) <= 3e-6, tile
        assert float(alpha.abs().max()) <= 3e-6, tile
        # accumulated depth is in metres (up to ~6 m): 1e-6 relative
        assert float(depth_acc.abs().max()) <= 1e-6 * float(ref_img[2].abs().max()), tile
        for a, b in zip(grad, ref_grad, strict=True):
            assert float((a - b).abs().max()) <= 1e-5 * float(b.abs().max()), tile


def test_cpp_matches_reference_where_pixels_stop(cpp: None) -> None:
    """Opaque Gaussians stop most pixels long before their tile's list ends: the C++ passes
    skip lane groups of stopped pixels, which must change nothing."""
    g, cam, T = _bench_like(3000, 80, 60)
    with torch.no_grad():
        g.opacity_logits.fill_(6.0)  # opacity 0.9975: T 0.0025 after one layer, the next
        # would take it to 6e-6, below 1e-4, so the pixel stops there
    ref_img, ref_grad = _render_and_grads(g, cam, T, "torch", 8)
    assert float((ref_img[1] > 0.99).float().mean()) > 0.5  # most pixels covered
    for tile in (8, 16, 32):
        img, grad = _render_and_grads(g, cam, T, "cpp", tile)
        for a, b in zip(img, ref_img, strict=True):
            assert float((a - b).abs().max()) <= 3e-6 * max(1.0, float(b.abs().max())), tile
        # 1e-4, not 1e-5: the C++ backward recovers T by dividing by 1 - alpha, 400x at
        # this opacity (1.1e-5 seen, with and without the skip)
        for a, b in zip(grad, ref_grad, strict=True):
            assert float((a - b).abs().max()) <= 1e-4 * float(b.abs().max()), tile


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cpp_depth_order_is_torchs_stable_argsort(cpp: None, dtype: torch.dtype) -> None:
    """The binning's radix sort gives torch.argsort(stable=True)'s order: ties in model
    order, -0 equal to +0, negatives, infinities, NaN last."""
    ext = cpp_ext.load_extension()
    g = torch.Generator().manual_seed(0)
    for n in (0, 1, 2, 1000, 70_000):
        x = (torch.rand(n, generator=g, dtype=torch.float64) * 8).round(decimals=2).to(dtype)
        if n >= 1000:  # ties by the hundred, and the special values
            x[:6] = torch.tensor([-0.0, 0.0, -1.5, float("inf"), float("-inf"), float("nan")],
                                 dtype=dtype)
            x[500:510] = torch.tensor([float("nan"), -0.0] * 5, dtype=dtype)
        assert torch.equal(ext.depth_order(x), torch.argsort(x, stable=True)), (n, dtype)
    # one byte of the key shared by all (a pass that moves nothing)
    x = torch.full((300,), 2.0, dtype=dtype) + torch.arange(300, dtype=dtype) * 2.0**-20
    assert torch.equal(ext.depth_order(x.flip(0)), torch.argsort(x.flip(0), stable=True))


def test_reference_does_not_depend_on_tile_size() -> None:
    g, cam, T = _bench_like(1500, 40, 30)
    a = render(g, cam, T, backend="torch", tile_size=4)
    b = render(g, cam, T, backend="torch", tile_size=16)
    assert torch.equal(a.color, b.color) and torch.equal(a.alpha, b.alpha)


def test_culling_and_meta() -> None:
    cam = PinholeCamera(32, 24, 30.0, 30.0, 15.5, 11.5)
    means = torch.tensor([[0.0, 0.0, 2.0],  # visible
                          [0.0, 0.0, -2.0],  # behind the camera
                          [50.0, 0.0, 2.0],  # far off to the side
                          [0.1, 0.0, 3.0]])  # visible, but transparent
    n = len(means)
    quats = torch.tensor([[1.0, 0, 0, 0]] * n)
    log_s = torch.full((n, 3), np.log(0.05))
    logit = torch.logit(torch.tensor([0.5, 0.5, 0.5, 0.001]))
    sh = torch.zeros(n, 1, 3)
    ct = CameraTensors.of(cam, np.eye(4))
    p = project(means, quats, log_s, logit, sh, ct, 0)
    assert p.gaussian_ids.tolist() == [0]
    out = render(Gaussians(means, quats, log_s, logit, sh), cam, np.eye(4), backend="torch")
    assert out.meta.visible.tolist() == [True, False, False, False]
    assert out.meta.radii.shape == (1, 2) and int(out.meta.radii.min()) > 0


def test_distorted_camera_is_refused() -> None:
    cam = PinholeCamera(32, 24, 30.0, 30.0, 15.5, 11.5, np.array([0.1, 0, 0, 0, 0]))
    g, T = _one_gaussian(torch.float32)
    with pytest.raises(ValueError, match="undistorted"):
        render(g, cam, T, backend="torch")


def test_backend_resolution() -> None:
    with pytest.raises(ValueError, match="unknown rasteriser backend"):
        resolve_backend("vulkan", torch.device("cpu"))
    with pytest.raises(RuntimeError, match="CUDA"):
        resolve_backend("gsplat", torch.device("cpu"))
    assert resolve_backend("torch", torch.device("cpu")) == "torch"


def test_fallback_without_compiler(monkeypatch: pytest.MonkeyPatch) -> None:
    """No compiler: the loader reports why and ``auto`` renders with the reference."""
    monkeypatch.setattr(cpp_ext, "_state", {"tried": False, "module": None, "error": None})
    monkeypatch.setenv("CXX", "definitely-not-a-compiler")
    assert cpp_ext.load_extension() is None
    assert "no C++ compiler" in (cpp_ext.extension_error() or "")
    g, T = _one_gaussian(torch.float32)
    out = render(g, PinholeCamera(32, 24, 30.0, 30.0, 15.5, 11.5), T, backend="auto")
    assert out.meta.backend == "torch"


def test_bench_refuses_cuda_without_a_cuda_device(capsys: pytest.CaptureFixture[str]) -> None:
    """--device cuda on a CPU-only torch says what is missing (it ended in a traceback)."""
    import torch

    from toolkit.splat.bench import main

    if torch.cuda.is_available():
        pytest.skip("this machine has a CUDA device")
    with pytest.raises(SystemExit) as exc:
        main(["--device", "cuda", "--backends", "gsplat"])
    assert exc.value.code == 2 and "sees no CUDA device" in capsys.readouterr().err


def test_gsplat_backend_composites_the_background_itself(monkeypatch: pytest.MonkeyPatch) -> (
        None):
    """gsplat 1.5.3's packed rasteriser refuses every per-camera background (its shape check
    wants none for the camera), so the backend asks for none and composites
    color + (1 - alpha) * background, as gsplat would have. A stand-in for gsplat with
    1.5.3's check (the real one runs in test_splat_gpu.py on a GPU)."""
    from types import SimpleNamespace

    from toolkit.splat.rasterize import gsplat_backend

    h, w, n = 4, 5, 3

    def rasterization(**kw: object) -> tuple[torch.Tensor, torch.Tensor, dict]:
        bg = kw.get("backgrounds")
        assert bg is None or tuple(bg.shape) == (4,), tuple(bg.shape)  # gsplat 1.5.3, packed
        alphas = torch.full((1, h, w, 1), 0.25)
        colors = torch.cat([torch.full((1, h, w, 3), 0.1), torch.full((1, h, w, 1), 2.0)], -1)
        info = {"means2d": torch.zeros(n, 2), "radii": torch.ones(n, 2, dtype=torch.int32),
                "gaussian_ids": torch.arange(n), "depths": torch.ones(n)}
        return colors, alphas, info

    monkeypatch.setattr(gsplat_backend, "_import", lambda: SimpleNamespace(
        rasterization=rasterization))
    g = init_from_points(np.zeros((n, 3)) + [0, 0, 2], np.full((n, 3), 0.5)).gaussians()
    cam = CameraTensors.of(PinholeCamera(w, h, 5.0, 5.0, 2.0, 1.5), np.eye(4))
    out = gsplat_backend.render(g, cam, torch.tensor([0.2, 0.4, 0.8]), 0, 0.01, 100.0, 0.3)
    np.testing.assert_allclose(out.color[0, 0].numpy(), 0.1 + 0.75 * np.array([0.2, 0.4, 0.8]),
                               rtol=1e-6)
    assert float(out.depth[0, 0]) == 2.0 and float(out.alpha[0, 0]) == 0.25

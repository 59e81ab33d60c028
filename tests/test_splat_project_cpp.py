"""The C++ EWA projection (``cpp_ext.project_cpp``) against the PyTorch ``project``.

Random scenes with the cases the culling and the Jacobian clamp exist for: Gaussians
behind the near plane, far outside the frustum, nearly transparent ones, degenerate
(tiny, huge, overflowing) scales, and a rotated and translated camera. Forward: the same
survivors, radii and outputs; backward: the gradients of a random linear loss on every
output equal autograd through ``project`` for every input, the camera pose included.
Skips, saying why, where the extension cannot be built.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from toolkit.camera import PinholeCamera
from toolkit.splat.model import Gaussians
from toolkit.splat.rasterize import cpp_ext, render
from toolkit.splat.rasterize.common import CameraTensors, Projected, project

# one torch thread for every test here (conftest.one_thread)
pytestmark = pytest.mark.usefixtures("one_thread")



def _pose(seed: int) -> np.ndarray:
    """A rotated, translated T_camera_world (about 25 degrees, ~0.7 m)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.25, 3)).as_matrix()
    T[:3, 3] = rng.normal(0, 0.4, 3)
    return T


def _scene(n: int, seed: int, dtype: torch.dtype) -> tuple[
    list[torch.Tensor], np.ndarray
]:
    """[means, quats, log_scales, opacity_logits, sh] in world coordinates of ``_pose``."""
    g = torch.Generator().manual_seed(seed)
    T = _pose(seed)
    # Camera-frame points: most in front, some behind the camera or the near plane, some
    # far outside the frustum (up to 20x the image's half-width: the Jacobian clamp).
    pc = torch.empty(n, 3, dtype=torch.float64)
    pc[:, 2] = torch.empty(n, dtype=torch.float64).uniform_(-1.0, 6.0, generator=g)
    pc[:, :2] = torch.randn(n, 2, dtype=torch.float64, generator=g) * 0.6 * pc[:, 2:].abs()
    wide = torch.rand(n, generator=g) < 0.15
    pc[wide, :2] *= 8.0 + 12.0 * torch.rand(int(wide.sum()), 1, generator=g, dtype=torch.float64)
    near = torch.rand(n, generator=g) < 0.03
    pc[near, 2] = torch.empty(int(near.sum()), dtype=torch.float64).uniform_(0.0, 0.02,
                                                                              generator=g)
    R, t = torch.as_tensor(T[:3, :3]), torch.as_tensor(T[:3, 3])
    means = (pc - t) @ R  # world = R^T (p_c - t)
    quats = torch.randn(n, 4, dtype=torch.float64, generator=g) * 2.0
    log_scales = torch.log(torch.empty(n, 3, dtype=torch.float64).uniform_(0.005, 0.3,
                                                                         generator=g))
    kind = torch.randint(0, 12, (n,), generator=g)
    log_scales[kind == 0, 0] = -20.0  # flat: a degenerate 3D covariance, kept by eps2d
    log_scales[kind == 1] = -25.0  # a point
    log_scales[kind == 2, 1] = 3.0  # huge footprint
    log_scales[kind == 3, 2] = 400.0  # exp overflows in float32, a and c in float64: culled
    logits = torch.randn(n, dtype=torch.float64, generator=g) * 3.0
    logits[kind == 4] = float(np.log(0.5 / 255))  # opacity under 1/255
    sh = torch.randn(n, 4, 3, dtype=torch.float64, generator=g) * 0.3
    params = [x.to(dtype).requires_grad_(True) for x in (means, quats, log_scales, logits, sh)]
    return params, T


CAM = PinholeCamera(64, 48, 50.0, 52.0, 31.2, 23.9)


def _both(dtype: torch.dtype, seed: int, n: int = 3000) -> tuple[
    Projected, Projected, list[torch.Tensor], torch.Tensor
]:
    params, T = _scene(n, seed, dtype)
    viewmat = torch.as_tensor(T, dtype=dtype).requires_grad_(True)
    ct = CameraTensors.of(CAM, viewmat, dtype)
    ref = project(*params, ct, 1)
    new = cpp_ext.project_cpp(*params, ct, 1)
    return ref, new, params, viewmat


def _outputs(p: Projected) -> list[torch.Tensor]:
    return [p.means2d, p.conics, p.depths, p.opacities, p.colors]


def _row_err(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """[M] largest difference per row, relative to the row's size (floored at 1e-3 of the
    largest row: rows that are all but zero only count in absolute terms)."""
    a, b = a.detach().reshape(len(a), -1), b.detach().reshape(len(b), -1)
    rows = b.abs().amax(1, keepdim=True).clamp_min(1e-3 * float(b.abs().max()) + 1e-30)
    return ((a - b).abs() / rows).amax(1)


def _rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(_row_err(a, b).max()) if len(b) else 0.0


def _as_accurate(a: torch.Tensor, b: torch.Tensor, exact: torch.Tensor, tol: float,
                 what: str = "") -> None:
    """float32 ``a`` is about as close to float64 ``exact`` as float32 ``b`` is: at the
    99th percentile of the rows and at the worst row."""
    en, er = _row_err(a.double(), exact), _row_err(b.double(), exact)
    q = torch.tensor([0.99, 1.0], dtype=torch.float64)
    (n99, nmax), (r99, rmax) = en.quantile(q).tolist(), er.quantile(q).tolist()
    assert n99 <= 2.0 * r99 + tol and nmax <= 3.0 * rmax + tol, (what, n99, r99, nmax, rmax)


def _pick(x: torch.Tensor, ids: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
    """Rows of packed ``x`` (ids ``ids``) for the model indices ``keep``."""
    pos = torch.searchsorted(ids, keep)
    return x[pos]


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_forward_matches_project(cpp: None, dtype: torch.dtype, seed: int) -> None:
    ref, new, params, viewmat = _both(dtype, seed)
    n = len(params[0])
    assert 0.1 * n < len(ref.gaussian_ids) < 0.6 * n  # both culled and kept ones: a real test
    assert torch.equal(new.gaussian_ids, ref.gaussian_ids)
    if dtype == torch.float64:
        assert torch.equal(new.radii, ref.radii)
    else:  # ceil() of a float32 value a rounding apart: seen on radii in the 1000s
        d = (new.radii - ref.radii).abs()
        assert int(d.max()) <= 1 and int((d > 0).sum()) <= 3
        assert bool((d == 0)[ref.radii.amax(1) < 1000].all())
    assert new.radii.dtype == torch.int32 and new.gaussian_ids.dtype == torch.int64
    for a in _outputs(new):
        assert a.dtype == dtype
    if dtype == torch.float64:
        for a, b in zip(_outputs(new), _outputs(ref), strict=True):
            assert a.shape == b.shape and _rel_err(a, b) <= 1e-10
        return
    # float32: near-plane and needle-like Gaussians are ill-conditioned (conics of a
    # nearly singular covariance; x / z at z ~ 0.01), so both float32 versions are
    # compared with the float64 projection of the same inputs: the C++ one must be about
    # as accurate as PyTorch's.
    exact = project(*[p.detach().double() for p in params], CameraTensors.of(
        CAM, viewmat.detach().double(), torch.float64), 1)
    common = ref.gaussian_ids[torch.isin(ref.gaussian_ids, exact.gaussian_ids)]
    assert len(common) >= len(ref.gaussian_ids) - 3
    for a, b, e in zip(_outputs(new), _outputs(ref), _outputs(exact), strict=True):
        ids, eids = new.gaussian_ids, exact.gaussian_ids
        a, b, e = _pick(a, ids, common), _pick(b, ids, common), _pick(e, eids, common)
        _as_accurate(a, b, e, 1e-5)


def test_culling_cases(cpp: None) -> None:
    """Each reason to cull, one Gaussian each, and the Jacobian clamp's kept neighbour."""
    cam = PinholeCamera(32, 24, 30.0, 30.0, 15.5, 11.5)
    means = torch.tensor([[0.0, 0.0, 2.0],  # visible
                          [0.0, 0.0, -2.0],  # behind the camera
                          [0.0, 0.0, 0.005],  # in front of the camera, behind near
                          [50.0, 0.0, 2.0],  # far off to the side
                          [0.1, 0.0, 3.0],  # transparent
                          [0.0, 0.1, 2.0],  # scale overflows
                          [3.0, 0.0, 2.0]])  # off-screen centre, footprint reaches in
    n = len(means)
    quats = torch.tensor([[1.0, 0, 0, 0]] * n)
    log_s = torch.full((n, 3), float(np.log(0.05)))
    log_s[5, 0] = 100.0
    log_s[6] = float(np.log(1.5))
    logit = torch.logit(torch.tensor([0.5, 0.5, 0.5, 0.5, 0.001, 0.5, 0.9]))
    sh = torch.zeros(n, 1, 3)
    ct = CameraTensors.of(cam, np.eye(4))
    ref = project(means, quats, log_s, logit, sh, ct, 0)
    new = cpp_ext.project_cpp(means, quats, log_s, logit, sh, ct, 0)
    assert ref.gaussian_ids.tolist() == [0, 6]
    assert new.gaussian_ids.tolist() == [0, 6]
    assert torch.equal(new.radii, ref.radii)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_overflowing_scales_get_zero_gradients(cpp: None, dtype: torch.dtype) -> None:
    """Gaussians whose scale overflows are culled and change no gradient, in both paths.

    Known answer: the scene's gradients equal those of the same scene without them, and
    theirs are 0. Two kinds: exp(log_scale) itself overflows (100 in float32, 800 in
    float64), and a finite scale whose row of J W_R R_q S overflows (88, 708: |J W_R| is
    about fx / z = 15 here). PyTorch gave NaN for both, spread to the viewmat's gradient.
    """
    cam = PinholeCamera(32, 24, 30.0, 30.0, 15.5, 11.5)
    big_exp, big_row = (100.0, 88.0) if dtype == torch.float32 else (800.0, 708.0)
    means = torch.tensor([[0.0, 0.0, 2.0], [0.1, 0.05, 2.0], [0.2, -0.1, 2.5],
                          [-0.1, 0.1, 2.0], [0.05, 0.0, 3.0]], dtype=dtype)  # [5, 3]
    n = len(means)
    quats = torch.tensor([[1.0, 0.1, -0.2, 0.05]] * n, dtype=dtype)
    log_s = torch.full((n, 3), float(np.log(0.05)), dtype=dtype)
    log_s[1, 0] = big_exp
    log_s[3, 1] = big_row
    logit = torch.zeros(n, dtype=dtype)
    sh = torch.full((n, 1, 3), 0.2, dtype=dtype)
    bad = torch.tensor([1, 3])
    good = torch.tensor([0, 2, 4])
    pose = _pose(7)
    pose[:3, 3] = 0.0  # the Gaussians stay in view

    def grads(fn, rows: torch.Tensor) -> list[torch.Tensor]:
        params = [x[rows].clone().requires_grad_(True) for x in (means, quats, log_s, logit, sh)]
        viewmat = torch.as_tensor(pose, dtype=dtype).requires_grad_(True)
        out = fn(*params, CameraTensors.of(cam, viewmat, dtype), 0)
        loss = sum((x * (1.0 + torch.arange(x.numel(), dtype=dtype).reshape(x.shape))).sum()
                   for x in _outputs(out))
        return list(torch.autograd.grad(loss, [*params[:4], viewmat]))

    for fn in (project, cpp_ext.project_cpp):
        with_bad = grads(fn, torch.arange(n))
        without = grads(fn, good)
        for name, a, b in zip(["means", "quats", "log_scales", "logits", "viewmat"],
                              with_bad, without, strict=True):
            assert bool(torch.isfinite(a).all()), (fn.__name__, name)
            if name == "viewmat":
                assert float(a.abs().max()) > 0
                assert torch.allclose(a, b, rtol=1e-5, atol=0), (fn.__name__, name)
            else:
                assert bool((a[bad] == 0).all()), (fn.__name__, name)
                assert torch.allclose(a[good], b, rtol=1e-5, atol=0), (fn.__name__, name)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("seed", [0, 3])
def test_gradients_match_autograd(cpp: None, dtype: torch.dtype, seed: int) -> None:
    ref, new, params, viewmat = _both(dtype, seed)
    assert torch.equal(new.gaussian_ids, ref.gaussian_ids)
    g = torch.Generator().manual_seed(100 + seed)
    weights = [torch.randn(x.shape, generator=g, dtype=torch.float64).to(dtype)
               for x in _outputs(ref)]
    inputs = [*params[:4], viewmat]  # SH colours run the same PyTorch code in both
    grads = []
    for p in (ref, new):
        loss = sum((w * x).sum() for w, x in zip(weights, _outputs(p), strict=True))
        grads.append(torch.autograd.grad(loss, inputs))
    names = ["means", "quats", "log_scales", "opacity_logits", "viewmat"]
    if dtype == torch.float64:
        for name, a, b in zip(names, grads[1], grads[0], strict=True):
            assert float(b.abs().max()) > 0, name
            assert _rel_err(a, b) <= 1e-9, name
        return
    # float32: against float64 autograd through ``project`` of the same inputs, the C++
    # gradients must be about as accurate as PyTorch's float32 ones (see the forward test;
    # the worst rows, 1-30 % off in both, are 20 m needles seen edge-on).
    p64 = [p.detach().double().requires_grad_(True) for p in params]
    v64 = viewmat.detach().double().requires_grad_(True)
    exact = project(*p64, CameraTensors.of(CAM, v64, torch.float64), 1)
    assert torch.equal(exact.gaussian_ids, ref.gaussian_ids)
    loss = sum((w.double() * x).sum() for w, x in zip(weights, _outputs(exact), strict=True))
    g64 = torch.autograd.grad(loss, [*p64[:4], v64])
    for name, a, b, e in zip(names, grads[1], grads[0], g64, strict=True):
        _as_accurate(a, b, e, 1e-4, name)


def test_viewmat_gradient_is_deterministic(cpp: None) -> None:
    """Same bytes for any thread count (a fixed partition of the sum over Gaussians)."""
    before = cpp_ext.get_threads()
    out = []
    try:
        for threads in (1, 2, 3):
            cpp_ext.set_threads(threads)
            _, new, params, viewmat = _both(torch.float32, 4, 5000)
            loss = sum(x.sum() for x in _outputs(new))
            out.append(torch.autograd.grad(loss, [*params[:4], viewmat]))
    finally:
        cpp_ext.set_threads(before)
    for other in out[1:]:
        for a, b in zip(other, out[0], strict=True):
            assert torch.equal(a, b)


def test_render_matches_torch_backend(cpp: None) -> None:
    """End to end: image and every gradient (pose included) against the PyTorch backend."""
    params, T = _scene(3000, 5, torch.float64)
    viewmat = torch.as_tensor(T).requires_grad_(True)
    gs = Gaussians(*params)
    results = []
    for backend in ("torch", "cpp"):
        out = render(gs, CAM, viewmat, background=[0.1, 0.2, 0.3], backend=backend,
                     tile_size=8)
        out.meta.means2d.retain_grad()
        wts = torch.linspace(0, 1, CAM.width * CAM.height * 3,
                             dtype=torch.float64).reshape(CAM.height, CAM.width, 3)
        loss = (out.color * wts).sum() + out.alpha.sum() + 0.1 * (out.depth * out.alpha).sum()
        grads = torch.autograd.grad(loss, [*params, viewmat], retain_graph=True)
        loss.backward()
        results.append((out, grads))
    (ref, ref_g), (new, new_g) = results
    assert float(ref.alpha.mean().detach()) > 0.2
    # the cpp backend's render goes through the C++ projection
    assert "_Project" in type(new.meta.means2d.grad_fn).__name__
    assert float((new.color - ref.color).detach().abs().max()) <= 1e-9
    assert float((new.alpha - ref.alpha).detach().abs().max()) <= 1e-9
    for a, b in zip(new_g, ref_g, strict=True):
        assert float((a - b).abs().max()) <= 1e-8 * float(b.abs().max())
    # densification reads the screen-space gradient
    assert new.meta.means2d.grad is not None
    assert torch.allclose(new.meta.means2d.grad, ref.meta.means2d.grad, rtol=1e-8, atol=1e-12)


def test_each_torch_installation_gets_its_own_build_folder(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    # ninja's build file names torch's include folders: two venvs with the same torch
    # version sharing one folder rebuilt the extension each time they took turns.
    name = cpp_ext.build_name()
    assert cpp_ext.build_name() == name  # stable
    monkeypatch.setattr(torch, "__file__", str(tmp_path / "other_venv" / "torch" / "__init__.py"))
    assert cpp_ext.build_name() != name

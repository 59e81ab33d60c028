"""gsplat (CUDA) against the CPU rasteriser: same scene, same image.

Run with ``python -m pytest -m gpu tests/test_splat_gpu.py`` on a machine with a CUDA GPU and
the ``cuda`` extra (gsplat) installed; everywhere else these tests skip.
"""

from __future__ import annotations

import pytest
import torch

from toolkit.splat.model import Gaussians, init_from_points
from toolkit.splat.rasterize import render
from toolkit.splat.synthetic import perturbed, room_camera, room_points

pytestmark = pytest.mark.gpu


def _need_gsplat() -> None:
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    from toolkit.splat.rasterize import gsplat_backend

    if not gsplat_backend.available():
        pytest.skip(f"gsplat unusable: {gsplat_backend.unavailable_reason()}")


def _scene(n: int, width: int, height: int) -> tuple[Gaussians, object, object]:
    pts, rgb = room_points(n, seed=5)
    g = perturbed(init_from_points(pts, rgb, sh_degree=3).gaussians(), seed=5)
    cam, T = room_camera(width, height)
    return g, cam, T


def _to(g: Gaussians, device: str) -> Gaussians:
    return Gaussians(*(t.detach().to(device).clone().requires_grad_(True) for t in
                       (g.means, g.quats, g.log_scales, g.opacity_logits, g.full_sh())))


def test_gsplat_matches_cpu_render() -> None:
    _need_gsplat()
    g, cam, T = _scene(20_000, 160, 120)
    cpu = render(_to(g, "cpu"), cam, T, background=[0.1, 0.2, 0.3], backend="auto")
    gpu = render(_to(g, "cuda"), cam, T, background=[0.1, 0.2, 0.3], backend="gsplat")
    assert gpu.meta.backend == "gsplat"
    diff = (gpu.color.detach().cpu() - cpu.color.detach()).abs()
    assert float(diff.mean()) <= 1e-3, float(diff.mean())
    adiff = (gpu.alpha.detach().cpu() - cpu.alpha.detach()).abs()
    assert float(adiff.mean()) <= 1e-3
    seen = (cpu.alpha.detach() > 0.5) & (gpu.alpha.detach().cpu() > 0.5)
    ddiff = (gpu.depth.detach().cpu() - cpu.depth.detach())[seen].abs()
    assert float(ddiff.mean()) <= 1e-3 * float(cpu.depth.detach()[seen].mean())


def test_gsplat_gradients_point_the_same_way() -> None:
    _need_gsplat()
    g, cam, T = _scene(5_000, 96, 72)
    grads = {}
    for dev, backend in (("cpu", "auto"), ("cuda", "gsplat")):
        gg = _to(g, dev)
        out = render(gg, cam, T, backend=backend)
        (out.color.mean() + out.alpha.mean()).backward()
        grads[dev] = [t.grad.detach().cpu().flatten() for t in (gg.means, gg.opacity_logits,
                                                                 gg.sh)]
    for a, b in zip(grads["cpu"], grads["cuda"], strict=True):
        cos = torch.nn.functional.cosine_similarity(a, b, dim=0)
        assert float(cos) > 0.99

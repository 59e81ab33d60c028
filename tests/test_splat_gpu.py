"""gsplat (CUDA) against the CPU rasteriser: same scene, same image.

Run with ``python -m pytest -m gpu tests/test_splat_gpu.py`` on a machine with a CUDA GPU and
the ``cuda`` extra (gsplat) installed; everywhere else these tests skip.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from toolkit.camera import PinholeCamera
from toolkit.geometry import inv_se3
from toolkit.splat.model import GaussianModel, Gaussians, init_from_points
from toolkit.splat.rasterize import render
from toolkit.splat.strategy import StrategyConfig
from toolkit.splat.synthetic import (
    ground_truth_model,
    orbit_poses,
    perturbed,
    room_camera,
    room_points,
)
from toolkit.splat.trainer import TrainConfig, Trainer, TrainView, evaluate_views

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


def test_training_on_cuda_fits_and_its_checkpoint_resumes_on_the_cpu(tmp_path: Path) -> None:
    """The splat stage's device: cuda: the model on the GPU, views in CPU memory, pose
    refinement and densification on; then the finished checkpoint read on a CPU trainer."""
    _need_gsplat()
    gt = ground_truth_model(1500, seed=1)
    cam = PinholeCamera.from_fov(64, 48, 70.0)
    views = []
    with torch.no_grad():
        for i, T_wc in enumerate(orbit_poses(4, seed=1)):
            T_cw = inv_se3(T_wc)
            out = render(gt, cam, T_cw)
            img = (out.color.clamp(0, 1) * 255 + 0.5).to(torch.uint8)
            depth = torch.where(out.alpha > 0.5, out.depth, torch.zeros(()))
            views.append(TrainView(img, cam, T_cw, depth, f"v{i}"))

    def start() -> GaussianModel:
        pts, _ = room_points(1500, seed=1)
        rng = np.random.default_rng(2)
        grey = np.full_like(pts, 0.5) + rng.normal(0, 0.05, pts.shape)
        return init_from_points(pts + rng.normal(0, 0.01, pts.shape), grey, sh_degree=1)

    cfg = TrainConfig(iterations=100, sh_degree=1, lr_sh0=0.05, lr_opacities=0.1,
                      depth_weight=0.1, pose_refine=True, checkpoint_every=50,
                      densify=StrategyConfig(refine_start_iter=5, refine_every=10,
                                             reset_every=1000, grow_grad2d=2e-5))
    model = start().to("cuda")
    before = evaluate_views(model, views)["psnr_db"]
    trainer = Trainer(model, views, cfg, tmp_path)
    trainer.train()
    after = evaluate_views(trainer.model, views)["psnr_db"]
    assert trainer.model.means.device.type == "cuda"
    assert len(trainer.model) != 1500  # densification ran on the GPU
    assert after > before + 6.0, (before, after)
    on_cpu = Trainer(start(), views, cfg, tmp_path)
    assert on_cpu.resume() and on_cpu.done is not None
    assert on_cpu.model.means.device.type == "cpu"
    assert abs(evaluate_views(on_cpu.model, views)["psnr_db"] - after) < 0.5


def test_splat_stage_on_cuda_trains_as_well_as_on_the_cpu(tmp_path: Path) -> None:
    """The recipe stage end to end with ``device: cuda`` (model, densification, pose
    refinement and export on the GPU, views in CPU memory) against ``device: cpu`` on the
    same synthetic room: both fit, the held-out PSNRs agree, the GPU's splats export."""
    _need_gsplat()
    import yaml
    from recipe_helpers import SplatInputs  # the tests folder is on sys.path

    from toolkit.recipe import load_recipe, registry, run_recipe
    from toolkit.splat.export import read_ply
    from toolkit.splat.stage import SplatStage

    registry.register("t_splat_inputs", SplatInputs)
    registry.register("splat", SplatStage)
    metrics = {}
    try:
        for device in ("cpu", "cuda"):
            recipe = {"name": f"splat_{device}", "output": str(tmp_path / device), "stages": [
                {"stage": "t_splat_inputs", "frames": 24, "width": 128, "height": 96,
                 "gaussians": 8000},
                {"stage": "splat", "device": device, "iterations": 300, "downscale": 1,
                 "holdout_every": 6, "init_budget": 8000, "max_seconds": None,
                 "log_every": 100, "pose_refine": True,
                 "densify": {"refine_start_iter": 50, "refine_every": 25}}]}
            path = tmp_path / f"{device}.yaml"
            path.write_text(yaml.safe_dump(recipe, sort_keys=False))
            res = run_recipe(load_recipe(path))
            assert res.ok, res.error
            metrics[device] = res.metrics["splat"]
    finally:
        registry.unregister("t_splat_inputs")
        registry.unregister("splat")
    cpu, gpu = metrics["cpu"], metrics["cuda"]
    print(f"\nsplat stage, 300 steps at 128x96: cpu {cpu['train_seconds']:.1f} s "
          f"{cpu['heldout_psnr_db']:.2f} dB {cpu['n_gaussians']} Gaussians; cuda "
          f"{gpu['train_seconds']:.1f} s {gpu['heldout_psnr_db']:.2f} dB "
          f"{gpu['n_gaussians']} Gaussians")
    assert cpu["device"] == "cpu" and gpu["device"] == torch.cuda.get_device_name()
    assert gpu["backend"] == "gsplat"
    assert gpu["heldout_psnr_db"] > 20.0
    assert gpu["n_gaussians"] != 8000  # densification ran
    assert abs(gpu["heldout_psnr_db"] - cpu["heldout_psnr_db"]) < 1.5
    model = read_ply(tmp_path / "cuda" / "splat" / "splats.ply")
    assert len(model) == gpu["n_gaussians"]

"""The ``splat`` recipe stage on a small synthetic room (sequence + fused inputs)."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from recipe_helpers import SplatInputs  # the tests folder is on sys.path

from toolkit.geometry import Trajectory
from toolkit.io.tum import write_tum
from toolkit.recipe import Stage, StageConfig, StageContext, load_recipe, registry, run_recipe
from toolkit.splat.export import read_ply
from toolkit.splat.stage import SplatStage


class TrajectoryStage(Stage):
    """Provide the ground-truth camera trajectory as if SLAM had estimated it (test stage)."""

    name = "t_splat_traj"
    Config = StageConfig
    requires = ("sequence",)
    provides = ("trajectory",)

    def run(self, ctx: StageContext) -> None:
        from toolkit.io.sequence import read_sequence

        seq = read_sequence(ctx.artifact("sequence"))
        gt = seq.groundtruth
        assert gt is not None and gt.poses_base is not None
        traj = Trajectory(gt.poses_base.stamps, gt.poses_base.poses @ seq.rig.T_base_camera,
                          "world", "camera")
        write_tum(ctx.stage_dir / "trajectory_camera.tum", traj)
        ctx.provide("trajectory", ctx.stage_dir)


@pytest.fixture(autouse=True)
def stages() -> Iterator[None]:
    for name, cls in (("t_splat_inputs", SplatInputs), ("t_splat_traj", TrajectoryStage),
                      ("splat", SplatStage)):
        registry.register(name, cls)
    yield
    for name in ("t_splat_inputs", "t_splat_traj", "splat"):
        registry.unregister(name)


def _recipe(tmp_path: Path, with_traj: bool, **splat: Any) -> Path:
    stages: list[dict[str, Any]] = [{"stage": "t_splat_inputs"}]
    if with_traj:
        stages.append({"stage": "t_splat_traj"})
    stages.append({"stage": "splat", "iterations": 25, "downscale": 1, "holdout_every": 4,
                   "init_budget": 2000, "checkpoint_every": 10, "max_seconds": None,
                   "log_every": 10, **splat})
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump({"name": "splat_test", "output": str(tmp_path / "run"),
                                    "stages": stages}, sort_keys=False))
    return path


def test_stage_trains_exports_and_reports(tmp_path: Path) -> None:
    res = run_recipe(load_recipe(_recipe(tmp_path, with_traj=True)))
    assert res.ok, res.error
    out = tmp_path / "run" / "splat"
    m = res.metrics["splat"]
    assert m["poses"] == "trajectory"
    assert m["iterations"] == 25 and m["train_views"] == 9  # frames 0, 4, 8 held out
    assert m["heldout_frames"] == 3 and np.isfinite(m["heldout_psnr_db"])
    assert 0 < m["heldout_ssim"] <= 1
    assert m["sim_heldout_views"] == 2 and np.isfinite(m["sim_heldout_psnr_db"])
    assert "heldout_depth_mae_m" in m and "sim_heldout_depth_mae_m" in m
    model = read_ply(out / "splats.ply")
    assert len(model) == m["n_gaussians"]
    assert (out / "renders.png").exists() and (out / "checkpoints" / "checkpoint.pt").exists()
    hist = json.loads((out / "train_history.json").read_text())
    assert [h["step"] for h in hist] == [9, 19, 24]
    report = (tmp_path / "run" / "report.md").read_text()
    assert "splat/renders.png" in report and "GROUND-TRUTH" not in report
    # unchanged inputs and settings: cached
    again = run_recipe(load_recipe(_recipe(tmp_path, with_traj=True)))
    assert again.statuses["splat"] == "cached"


def test_stage_without_trajectory_uses_ground_truth_and_says_so(tmp_path: Path) -> None:
    res = run_recipe(load_recipe(_recipe(tmp_path, with_traj=False, iterations=5,
                                         holdout_every=0, strip_views=1)))
    assert res.ok, res.error
    assert res.metrics["splat"]["poses"] == "groundtruth"
    assert "heldout_psnr_db" not in res.metrics["splat"]
    report = (tmp_path / "run" / "report.md").read_text()
    assert "GROUND-TRUTH" in report

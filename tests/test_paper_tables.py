"""paper_tables: the benchmark tables from other stages' results, with known figures."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pytest

from toolkit.camera import PinholeCamera
from toolkit.geometry import Trajectory, se2_to_se3, se3
from toolkit.io.sequence import SequenceWriter
from toolkit.io.tum import write_tum
from toolkit.recipe import Stage, StageConfig, StageContext, parse_recipe, registry, run_recipe
from toolkit.sensors import LaserScan, Rig

R_BASE_OPTICAL = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=float)


class SceneConfig(StageConfig):
    stage: Literal["t_pscene"] = "t_pscene"
    # Camera-position error of the "SLAM" trajectory: +-err_m in y, alternating.
    err_m: float = 0.01


class Scene(Stage):
    """A sequence with ground truth and a SLAM camera trajectory with a known error."""

    name = "t_pscene"
    Config = SceneConfig
    provides = ("sequence", "trajectory")

    def run(self, ctx: StageContext) -> None:
        cfg: Any = self.config
        cam = PinholeCamera(16, 12, 10.0, 10.0, 7.5, 5.5)
        rig = Rig(cam, se3(R_BASE_OPTICAL, [0.1, 0, 0.5]), se3(np.eye(3), [0, 0, 0.3]))
        w = SequenceWriter(ctx.stage_dir / "sequence", rig, "fake")
        stamps = np.arange(40) * 0.1
        poses = np.stack([se2_to_se3(0.05 * i, 0.01 * i * i, 0.03 * i) for i in range(40)])
        for t in stamps:
            w.add_frame(float(t), np.zeros((12, 16, 3), np.uint8))
            w.add_scan(LaserScan(float(t), np.ones(8), 0.0, np.pi / 4))
        w.groundtruth_poses = Trajectory(stamps, poses)
        w.close()
        cams = poses @ rig.T_base_camera
        # World-frame y offsets +-err: zero mean, so no rigid alignment can remove them.
        cams[:, 1, 3] += cfg.err_m * np.where(np.arange(40) % 2 == 0, 1.0, -1.0)
        write_tum(ctx.stage_dir / "trajectory_camera.tum",
                  Trajectory(stamps, cams, "world", "camera"))
        ctx.provide("sequence", ctx.stage_dir / "sequence")
        ctx.provide("trajectory", ctx.stage_dir)
        ctx.add_metrics({"work_seconds": 2.0, "work_cpu_seconds": 2.0, "work_frames": 200})


class FiguresConfig(StageConfig):
    stage: Literal["t_figures"] = "t_figures"
    figures: dict[str, Any] = {}


class Figures(Stage):
    """Publishes the metrics it is given (a stand-in for depth, fuse, evaluate...)."""

    name = "t_figures"
    Config = FiguresConfig

    def run(self, ctx: StageContext) -> None:
        ctx.add_metrics(dict(self.config.figures))  # type: ignore[attr-defined]


@pytest.fixture
def stages():
    registry.register("t_pscene", Scene)
    registry.register("t_figures", Figures)
    yield
    registry.unregister("t_pscene")
    registry.unregister("t_figures")


def test_tables_from_known_figures(tmp_path: Path, stages) -> None:
    fuse = {"work_seconds": 3.0, "work_cpu_seconds": 3.0, "work_frames": 100,
            "lidar_unscaled_rmse_m": 1.5, "lidar_scaled_rmse_m": 0.12,
            "lidar_rmse_ratio_scaled_unscaled": 0.08, "gt_scaled_absrel": 0.03,
            "gt_rmse_ratio_scaled_unscaled": 0.12, "dynamic_fraction": 0.004,
            "dynamic_fraction_before_carving": 0.007, "dynamic_fraction_raw": 0.005,
            "dynamic_points": 40,
            "frame_to_mesh_median_m": 0.012, "frame_to_mesh_median_max_m": 0.02,
            "fusion_fps": 25.0, "fusion_fps_per_frame_only": 35.0}
    geo = {"accuracy_mean_m": 0.02, "completeness_mean_m": 0.03, "chamfer_m": 0.025,
           "fscore_2cm": 0.5, "fscore_5cm": 0.92, "fscore_10cm": 0.97}

    def recipe_dict() -> dict[str, Any]:
        return {"name": "tables", "output": str(tmp_path / "run"), "stages": [
            {"stage": "t_pscene", "id": "slam"},
            {"stage": "t_figures", "id": "depth_a",
             "figures": {"work_seconds": 1.0, "work_cpu_seconds": 2.0, "work_frames": 100,
                         "backend": "simulated"}},
            {"stage": "t_figures", "id": "fuse_a", "figures": fuse},
            {"stage": "t_figures", "id": "eval_a", "figures": {"fused_map": geo}},
            {"stage": "t_figures", "id": "fuse_a_kept",
             "figures": {"dynamic_fraction": 0.06, "dynamic_points": 640,
                         "dynamic_removal": False}},
            {"stage": "t_figures", "id": "depth_b",
             "figures": {"work_seconds": 30.0, "work_cpu_seconds": 60.0, "work_frames": 100}},
            {"stage": "paper_tables", "slam": "slam", "position_rmse_target_m": 0.02, "rows": [
                {"label": "A", "depth": "depth_a", "fuse": "fuse_a", "evaluate": "eval_a",
                 "fuse_without_removal": "fuse_a_kept", "fps_target": 10,
                 "fscore_5cm_target": 0.9},
                {"label": "B", "depth": "depth_b", "fusion_time_from": "fuse_a",
                 "timing_only": True, "fps_target": 3},
            ]},
        ]}

    res = run_recipe(parse_recipe(recipe_dict()))
    assert res.ok, res.error
    t = json.loads((tmp_path / "run" / "paper_tables" / "tables.json").read_text())
    row = t["table_i"]["with lidar: 2D lidar SLAM (SE(3)-aligned)"]
    assert row["position_rmse_m"] == pytest.approx(0.01, abs=1e-3)
    assert row["poses"] == 40
    # Per frame: SLAM 2 s / 200 + depth 1 s / 100 + fusion 3 s / 100 = 0.05 s -> 20 frames/s;
    # CPU 0.01 + 0.02 + 0.03 = 0.06 s per 0.05 s -> 120 %.
    a = t["table_ii"]["A"]
    assert a["fps"] == pytest.approx(20.0) and a["cpu_load_pct"] == pytest.approx(120.0)
    # B: 0.01 + 0.3 + 0.03 = 0.34 s -> 2.94 frames/s, below its 3 frames/s target.
    assert t["table_ii"]["B"]["fps"] == pytest.approx(1 / 0.34)
    by_label = {c["target"]: c["met"] for c in t["targets"]}
    assert next(v for k, v in by_label.items() if k.startswith("camera position")) is True
    assert by_label["A: >= 10 frames/s at CPU load <= 200 %"] is True
    assert by_label["B: >= 3 frames/s at CPU load <= 200 %"] is False
    assert by_label["A: fused cloud: F-score at 5 cm >= 0.9"] is True
    assert any(k.startswith("A: scaled / unscaled RMSE vs lidar") and v for k, v in
               by_label.items())
    assert by_label["A: scaled / unscaled RMSE vs ground truth, whole images <= 0.1"] is False
    # Moving obstacles: 0.4 % of the map with the removal, 6 % in the run without it.
    assert by_label["A: map points on moving obstacles <= 1 % (without the removal: 6.00 %)"]
    assert t["table_iv"]["A"]["dynamic_fraction_without_removal"] == pytest.approx(0.06)
    # ... and as people points kept: 40 of the 640 the map without removal held.
    assert t["table_iv"]["A"]["dynamic_points_kept_fraction"] == pytest.approx(0.0625)
    # docs/depth_fusion.md's fusion targets: AbsRel and per-frame map-to-mesh distance with
    # simulated depth, the fusion's own frames/s (25 with the end of the run: not met).
    values = {c["target"]: c["value"] for c in t["targets"]}
    fusion_targets = {
        "A: scaled depth AbsRel vs ground truth <= 0.05 (simulated depth)": ("0.030", True),
        "A: per-frame median map-to-mesh distance, median over frames <= 3 cm (simulated "
        "depth)": ("1.2 cm (worst frame 2.0 cm)", True),
        "A: fusion >= 30 frames/s (network excluded, wall clock with the end of the run)":
            ("25.0 frames/s (per-frame work 35.0)", False)}
    for target, (value, met) in fusion_targets.items():
        assert (values[target], by_label[target]) == (value, met)

    report = (tmp_path / "run" / "report.md").read_text()
    for heading in ("Table I", "Table II", "Table III", "Table IV", "Targets"):
        assert heading in report
    # The share before carving is over the map the same consensus and outlier steps leave
    # (the raw map's, 0.5 %, is before those steps too: it read as if carving added people).
    assert ("| 0.40 % (0.70 % without carving, after the same consensus and outlier steps; "
            "without removal 6.00 %, 6.2 % of its people points kept) |") in report
    assert (tmp_path / "run" / "paper_tables" / "figure5_trajectories.png").exists()

    # A network's depth: its AbsRel and distances are not held to the simulated targets.
    spec = recipe_dict()
    spec["stages"][1]["figures"]["backend"] = "onnx"
    res = run_recipe(parse_recipe(spec))
    assert res.ok, res.error
    t = json.loads((tmp_path / "run" / "paper_tables" / "tables.json").read_text())
    assert [c["target"] for c in t["targets"] if c["target"] in fusion_targets] == [
        "A: fusion >= 30 frames/s (network excluded, wall clock with the end of the run)"]

    # A "without removal" stage that did remove moving obstacles is refused, by name.
    spec = recipe_dict()
    spec["stages"][4]["figures"] = {"dynamic_fraction": 0.004, "dynamic_removal": True}
    res = run_recipe(parse_recipe(spec))
    assert not res.ok and "fuse_a_kept" in res.error and "dynamic_removal: false" in res.error
    # ... and so is one that does not say (another kind of stage, an older fuse result).
    spec["stages"][4]["figures"] = {"dynamic_fraction": 0.004}
    res = run_recipe(parse_recipe(spec))
    assert not res.ok and "does not record dynamic_removal" in res.error


def test_table_ii_heading_says_what_the_stages_ran_on() -> None:
    """The heading comes from the cores and depth device the stages recorded (it was a
    fixed "2 CPU cores, no GPU", also for a depth stage on cuda on a 16-core machine)."""
    from toolkit.eval.paper_tables import PaperTablesConfig, PaperTablesStage, TableRow
    from toolkit.recipe.stage import StageResult

    def heading(cores: list[int | None], devices: list[str]) -> str:
        work = [{"work_seconds": 1.0, "work_cpu_seconds": 2.0, "work_frames": 100}
                | ({"work_cpu_cores": c} if c else {}) for c in cores]
        metrics = {"slam2d": work[0], "fuse": work[1]}
        rows = []
        for k, dev in enumerate(devices):
            metrics[f"depth{k}"] = work[2 + k] | {"device": dev}
            rows.append(TableRow(label=f"R{k}", depth=f"depth{k}", fuse="fuse"))
        res = {i: StageResult(i, i, m, 1.0, 1.0, Path("/nonexistent") / i)
               for i, m in metrics.items()}
        cfg = PaperTablesConfig(rows=rows)
        return PaperTablesStage(cfg)._table_ii(cfg, res, {}, [])[0]

    assert heading([16, 16, 16], ["cuda"]) == (
        "### Table II: runtime (16 CPU cores; depth of 'R0' on cuda)")
    assert heading([2, 2, 2, 2], ["cpu", "cpu"]) == (
        "### Table II: runtime (2 CPU cores; no GPU used)")
    # Cached stages of another machine, and one from before the cores were recorded.
    assert heading([2, 16, None, 16], ["cpu", "cuda"]) == (
        "### Table II: runtime (2-16 CPU cores: stages from different machines, not recorded "
        "by 1 of 4 stages; depth of 'R1' on cuda)")
    assert heading([None, None, None], ["cpu"]) == (
        "### Table II: runtime (CPU cores not recorded; no GPU used)")


def test_colmap_line_names_a_global_mapper() -> None:
    from toolkit.eval.paper_tables import _colmap_lines

    sfm = {"sfm": {"registered_images": 159, "images": 161, "models": 1,
                   "reprojection_error_px": 0.48}}
    assert _colmap_lines({**sfm, "mapper": "global"})[0].startswith(
        "COLMAP SfM (global mapping) on the images alone: 159 of 161")
    for m in (sfm, {**sfm, "mapper": "incremental"}):  # runs from before the key: incremental
        assert _colmap_lines(m)[0].startswith("COLMAP SfM on the images alone")

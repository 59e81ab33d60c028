"""The evaluate stage on a synthetic run with known errors."""

from pathlib import Path
from typing import Literal

import numpy as np
import open3d as o3d
import pytest

from toolkit.camera import PinholeCamera
from toolkit.geometry import Trajectory, se2_to_se3, se3
from toolkit.io.sequence import SequenceWriter
from toolkit.io.tum import write_tum
from toolkit.recipe import Stage, StageConfig, StageContext, parse_recipe, registry, run_recipe
from toolkit.sensors import LaserScan, Rig

R_BASE_OPTICAL = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=float)
# The "SLAM world" differs from the ground-truth world by this rigid transform.
T_SLAM_WORLD = se2_to_se3(0.4, -0.2, 0.3)


def _room_mesh() -> o3d.geometry.TriangleMesh:
    m = o3d.geometry.TriangleMesh.create_box(4.0, 4.0, 2.5)
    m.translate([-2.0, -2.0, 0.0])
    return m


class FakeSourceConfig(StageConfig):
    stage: Literal["t_scene"] = "t_scene"
    groundtruth: Literal["full", "partial", "none"] = "full"
    # Where the map was built: at the SLAM poses (its frame) or at ground-truth poses (the
    # world's, as fuse with ``poses: groundtruth`` beside a slam2d stage writes it).
    map_frame: Literal["slam", "world"] = "slam"
    with_mesh: bool = True


class FakeScene(Stage):
    """A tiny sequence with ground truth, a SLAM trajectory and a fused map."""

    name = "t_scene"
    Config = FakeSourceConfig
    provides = ("sequence", "trajectory", "fused")

    def run(self, ctx: StageContext) -> None:
        cam = PinholeCamera(16, 12, 10.0, 10.0, 7.5, 5.5)
        rig = Rig(cam, se3(R_BASE_OPTICAL, [0.1, 0, 0.5]), se3(np.eye(3), [0, 0, 0.3]))
        root = ctx.stage_dir / "sequence"
        w = SequenceWriter(root, rig, "fake")
        stamps = np.arange(20) * 0.1
        poses = np.stack([se2_to_se3(0.05 * i, 0.0, 0.02 * i) for i in range(20)])
        for t in stamps:
            w.add_frame(float(t), np.zeros((12, 16, 3), np.uint8))
            w.add_scan(LaserScan(float(t), np.ones(8), 0.0, np.pi / 4))
        gt = self.config.groundtruth  # type: ignore[attr-defined]
        if gt != "none":
            part = slice(5, 15) if gt == "partial" else slice(None)  # mocap started late
            w.groundtruth_poses = Trajectory(stamps[part], poses[part])
            if self.config.with_mesh:  # type: ignore[attr-defined]
                o3d.io.write_triangle_mesh(str(w.mesh_path()), _room_mesh())
        w.close()
        # Exact trajectory, expressed in the SLAM frame.
        cams = T_SLAM_WORLD @ poses @ rig.T_base_camera
        write_tum(ctx.stage_dir / "trajectory_camera.tum", Trajectory(stamps, cams, "world",
                                                                       "camera"))
        # The map: the room surface 3 cm too high, in the SLAM frame.
        o3d.utility.random.seed(1)
        pts = np.asarray(_room_mesh().sample_points_uniformly(300000).points)
        pts[:, 2] += 0.03
        if self.config.map_frame == "slam":  # type: ignore[attr-defined]
            pts = pts @ T_SLAM_WORLD[:3, :3].T + T_SLAM_WORLD[:3, 3]
        else:
            cams = poses @ rig.T_base_camera
        write_tum(ctx.stage_dir / "camera_poses.tum", Trajectory(stamps, cams, "world",
                                                                  "camera"))
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        o3d.io.write_point_cloud(str(ctx.stage_dir / "map.ply"), pcd)
        ctx.provide("sequence", root)
        ctx.provide("trajectory", ctx.stage_dir)
        ctx.provide("fused", ctx.stage_dir)


@pytest.fixture
def fake_scene():
    registry.register("t_scene", FakeScene)
    yield
    registry.unregister("t_scene")


def test_evaluate_scores_known_errors(tmp_path: Path, fake_scene):
    recipe = parse_recipe({"name": "ev", "output": str(tmp_path / "run"), "stages": [
        {"stage": "t_scene"},
        {"stage": "evaluate", "mesh_spacing_m": 0.01},
    ]})
    res = run_recipe(recipe)
    assert res.ok, res.error
    m = res.metrics["evaluate"]
    # A rigid offset of the whole SLAM frame is not an error.
    assert m["trajectory"]["position_rmse_m"] < 1e-9
    assert m["trajectory"]["poses"] == m["trajectory"]["poses_total"] == 20
    # The map sits 3 cm above the floor/ceiling: 3 cm there, 0 on walls near the edges.
    fm = m["fused_map"]
    # Precision at 2 cm is the walls' share of the surface: 40 m^2 of 72 m^2 = 0.56.
    assert 0.5 < fm["precision_2cm"] < 0.62 and fm["fscore_5cm"] > 0.95
    assert 0.01 < fm["accuracy_mean_m"] < 0.031
    assert (tmp_path / "run" / "evaluate" / "trajectory.png").exists()
    report = (tmp_path / "run" / "report.md").read_text()
    assert "Table I" in report and "F@5cm" in report
    assert "cm over 20 frames." in report


def test_a_map_built_at_ground_truth_poses_is_not_moved(tmp_path: Path, fake_scene):
    """evaluate moved every map by the SLAM trajectory's alignment: a map fused at
    ground-truth poses next to a slam2d stage was put 0.65 m off (F@5cm 0.011)."""
    scores = {}
    for frame in ("slam", "world"):
        recipe = parse_recipe({"name": "ev", "output": str(tmp_path / frame), "stages": [
            {"stage": "t_scene", "map_frame": frame},
            {"stage": "evaluate", "mesh_spacing_m": 0.02},
        ]})
        res = run_recipe(recipe)
        assert res.ok, res.error
        scores[frame] = res.metrics["evaluate"]["fused_map"]
    for key in ("accuracy_mean_m", "fscore_5cm", "precision_2cm"):
        assert scores["world"][key] == pytest.approx(scores["slam"][key], abs=1e-6)


def test_map_to_world_recovers_the_slam_frame_offset() -> None:
    from types import SimpleNamespace

    from toolkit.eval.alignment import apply, map_to_world

    stamps = np.arange(30) * 0.1
    base = np.stack([se2_to_se3(0.1 * i, 0.02 * i * i, 0.05 * i) for i in range(30)])
    T_base_camera = se3(R_BASE_OPTICAL, [0.1, 0, 0.5])
    seq = SimpleNamespace(groundtruth=SimpleNamespace(poses_base=Trajectory(stamps, base)),
                          rig=SimpleNamespace(T_base_camera=T_base_camera))
    T_map_world = se2_to_se3(-1.4, 0.3, 0.2)  # where the SLAM put its origin
    cams = T_map_world @ base @ T_base_camera
    S = map_to_world(seq, stamps, cams)
    np.testing.assert_allclose(S @ T_map_world, np.eye(4), atol=1e-9)
    p = np.array([[1.0, 2.0, 0.5]])
    np.testing.assert_allclose(apply(S, apply(T_map_world, p)), p, atol=1e-9)


@pytest.mark.parametrize("groundtruth", ["none", "partial"])
def test_evaluate_without_or_with_partial_ground_truth(tmp_path: Path, fake_scene,
                                                       groundtruth: str) -> None:
    """A user's own recording (no ground truth) ends the recipe cleanly; ground truth over
    part of it scores the part it covers, and the metrics and report say of how many
    (the report said "over 10 frames" of a 20-frame trajectory)."""
    recipe = parse_recipe({"name": "ev", "output": str(tmp_path / "run"), "stages": [
        {"stage": "t_scene", "groundtruth": groundtruth},
        {"stage": "evaluate", "mesh_spacing_m": 0.05},
    ]})
    res = run_recipe(recipe)
    assert res.ok, res.error
    m = res.metrics["evaluate"]
    if groundtruth == "none":
        assert m == {"ground_truth": False}
        assert "No ground truth in this recording" in (tmp_path / "run/report.md").read_text()
    else:
        assert (m["trajectory"]["poses"], m["trajectory"]["poses_total"]) == (10, 20)
        assert m["trajectory"]["position_rmse_m"] < 1e-6
        report = (tmp_path / "run/report.md").read_text()
        assert "cm over the 10 of 20 frames that have ground truth." in report


class LidarOnlyConfig(StageConfig):
    stage: Literal["t_lidar_only"] = "t_lidar_only"


class LidarOnly(Stage):
    """A lidar-only recording with ground-truth base poses (what ingest makes of a CARMEN or
    g2o log): scans in a square room along a known path, no camera frames."""

    name = "t_lidar_only"
    Config = LidarOnlyConfig
    provides = ("sequence",)

    def run(self, ctx: StageContext) -> None:
        from test_slam2d import _drive, make_scan  # the tests folder is on sys.path

        rig = Rig(PinholeCamera(16, 12, 10.0, 10.0, 7.5, 5.5),
                  se3(R_BASE_OPTICAL, [0.1, 0.0, 0.5]), np.eye(4))
        w = SequenceWriter(ctx.stage_dir / "seq", rig, "lidar_only")
        truth = _drive(40)
        stamps = np.arange(40, dtype=float)
        for p, t in zip(truth, stamps, strict=True):
            w.add_scan(make_scan(p, t))
        w.groundtruth_poses = Trajectory(stamps, np.stack([se2_to_se3(*p) for p in truth]))
        w.close()
        ctx.provide("sequence", ctx.stage_dir / "seq")


def test_evaluate_scores_the_base_of_a_lidar_only_recording(tmp_path: Path) -> None:
    """No camera frames, so no camera poses: the robot base's trajectory is scored (the
    stage failed with "ground truth covers 0 of the 0 trajectory poses")."""
    registry.register("t_lidar_only", LidarOnly)
    try:
        res = run_recipe(parse_recipe({"name": "lo", "output": str(tmp_path / "run"), "stages": [
            {"stage": "t_lidar_only"}, {"stage": "slam2d", "submaps": {"num_range_data": 8}},
            {"stage": "evaluate"}]}))
    finally:
        registry.unregister("t_lidar_only")
    assert res.ok, res.error
    m = res.metrics["evaluate"]
    assert m["trajectory_body"] == "robot base" and m["trajectory"]["poses"] >= 30
    assert m["trajectory"]["position_rmse_m"] == pytest.approx(
        res.metrics["slam2d"]["gt_ate_rmse_m"], abs=0.01)
    assert m["trajectory"]["position_rmse_m"] < 0.05


def test_maps_left_unscored_without_a_mesh_are_said_to_be(tmp_path: Path, fake_scene):
    """Ground-truth poses but no mesh (motion capture, no scanned model): the maps were
    dropped from the report and metrics without a word."""
    res = run_recipe(parse_recipe({"name": "t", "output": str(tmp_path / "run"), "stages": [
        {"stage": "t_scene", "with_mesh": False}, {"stage": "evaluate"}]}))
    assert res.ok, res.error
    assert res.metrics["evaluate"]["maps_scored"] is False
    assert "the maps are not scored" in (tmp_path / "run" / "report.md").read_text()

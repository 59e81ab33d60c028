"""The ``tsdf``, ``colmap`` and ``camera_only`` stages run through the recipe runner on a
small ray-cast room sequence, with tiny test stages standing in for the upstream ones."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from toolkit.baselines.synthetic import SyntheticRoom, default_camera, orbit_poses
from toolkit.recipe import Stage, StageConfig, StageContext, registry
from toolkit.recipe.runner import run_recipe
from toolkit.recipe.schema import parse_recipe

pytest.importorskip("open3d")

DEPTH_SCALE_ERROR = 1.25  # the fake "network" reads every depth 25 % too far


class RoomConfig(StageConfig):
    frames: int = 12
    width: int = 256
    height: int = 192
    small: bool = False  # a 3.2 x 2.6 m room: fewer surface samples to evaluate
    poses: bool = True  # False: no ground-truth poses (a user's own recording)


class RoomSequence(Stage):
    """A ray-cast textured room as a sequence folder (test stage)."""

    name = "t_room"
    Config = RoomConfig
    provides = ("sequence",)

    def run(self, ctx: StageContext) -> None:
        from toolkit.baselines.synthetic import write_room_sequence

        cfg: Any = self.config
        if cfg.small:
            room = SyntheticRoom(size=(3.2, 2.6, 2.2), boxes=[((0.4, 1.6, 0.0), (1.0, 2.2, 0.8))])
            poses = orbit_poses(room, cfg.frames, radius_m=0.4, height_m=1.1, sweep_deg=300.0,
                                look_distance_m=1.5)
        else:
            room = SyntheticRoom()
            poses = orbit_poses(room, cfg.frames, radius_m=0.8, sweep_deg=100.0)
        cam = default_camera(cfg.width, cfg.height, 70.0)
        root = write_room_sequence(ctx.stage_dir / "seq", room, cam, poses)
        if not cfg.poses:
            (root / "groundtruth" / "poses_base.tum").unlink()
        ctx.provide("sequence", root)


class DepthConfig(StageConfig):
    kind: str = "metric_depth"  # or relative_depth: the same values, no unit claimed


class FakeDepth(Stage):
    """Ground-truth depth x 1.25 stored as a metric network's predictions (test stage)."""

    name = "t_depth"
    Config = DepthConfig
    requires = ("sequence",)
    provides = ("depth",)

    def run(self, ctx: StageContext) -> None:
        from toolkit.depth.protocol import DepthPrediction
        from toolkit.depth.store import DepthStoreWriter
        from toolkit.io.sequence import read_sequence

        seq = read_sequence(ctx.artifact("sequence"))
        kind = self.config.kind  # type: ignore[attr-defined]
        w = DepthStoreWriter(ctx.stage_dir / "depth", kind)
        for i, f in enumerate(seq.frames):
            d = seq.groundtruth.depth(i) * DEPTH_SCALE_ERROR
            w.add(i, f.stamp, DepthPrediction(np.where(d > 0, d, np.nan), kind))
        ctx.provide("depth", w.close())


class FakeFuse(Stage):
    """The fuse artifact's per-frame scaled depth, here exact (test stage)."""

    name = "t_fused"
    Config = StageConfig
    requires = ("sequence",)
    provides = ("fused",)

    def run(self, ctx: StageContext) -> None:
        from toolkit.io.depth import write_depth
        from toolkit.io.sequence import read_sequence

        seq = read_sequence(ctx.artifact("sequence"))
        out = ctx.stage_dir / "scaled_depth"
        rows = ["index,stamp,file,scale,shift"]
        for i, f in enumerate(seq.frames):
            write_depth(out / f"{i:06d}.png", seq.groundtruth.depth(i))
            rows.append(f"{i},{f.stamp!r},{i:06d}.png,1.0,0.0")
        (out / "index.csv").write_text("\n".join(rows) + "\n")
        ctx.provide("fused", ctx.stage_dir)


class FakeSlam(Stage):
    """trajectory_camera.tum = ground truth shifted 3 cm along x (test stage)."""

    name = "t_slam"
    Config = StageConfig
    requires = ("sequence",)
    provides = ("trajectory",)

    def run(self, ctx: StageContext) -> None:
        from toolkit.baselines.common import groundtruth_camera_trajectory
        from toolkit.io.sequence import read_sequence
        from toolkit.io.tum import write_tum

        traj = groundtruth_camera_trajectory(read_sequence(ctx.artifact("sequence")))
        traj.poses[:, 0, 3] += 0.03
        write_tum(ctx.stage_dir / "trajectory_camera.tum", traj)
        ctx.provide("trajectory", ctx.stage_dir)


class MapFrameSlam(Stage):
    """trajectory_camera.tum = the small room's true camera poses in a map frame turned
    40 deg and shifted from the world, for a sequence without ground-truth poses."""

    name = "t_slam_map"
    Config = StageConfig
    requires = ("sequence",)
    provides = ("trajectory",)

    def run(self, ctx: StageContext) -> None:
        from toolkit.geometry import Trajectory, se3
        from toolkit.io.sequence import read_sequence
        from toolkit.io.tum import write_tum

        seq = read_sequence(ctx.artifact("sequence"))
        room = SyntheticRoom(size=(3.2, 2.6, 2.2), boxes=[((0.4, 1.6, 0.0), (1.0, 2.2, 0.8))])
        poses = orbit_poses(room, len(seq.frames), radius_m=0.4, height_m=1.1,
                            sweep_deg=300.0, look_distance_m=1.5)
        a = np.radians(40.0)
        T_map_world = se3(np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0],
                                    [0, 0, 1]]), [-1.5, 0.7, 0.0])
        write_tum(ctx.stage_dir / "trajectory_camera.tum",
                  Trajectory(seq.frame_stamps, T_map_world @ poses, "world", "camera"))
        ctx.provide("trajectory", ctx.stage_dir)


class MapConfig(StageConfig):
    write_poses: bool = True  # camera_poses.tum beside the map, as fuse writes it


class FakeFusedMap(Stage):
    """map.ply = the true surface in the trajectory's map frame, and the poses it was built
    at (the trajectory's) as camera_poses.tum: what fuse at slam2d's poses writes."""

    name = "t_fused_map"
    Config = MapConfig
    requires = ("sequence", "trajectory")
    provides = ("fused",)

    def run(self, ctx: StageContext) -> None:
        import shutil

        from toolkit.baselines.tsdf import read_mesh
        from toolkit.eval.alignment import ground_truth_camera
        from toolkit.eval.geometry import sample_mesh
        from toolkit.fusion.voxel_map import MapArrays, write_map_ply
        from toolkit.geometry import rigid_alignment, se3
        from toolkit.io.sequence import read_sequence
        from toolkit.io.tum import read_tum

        seq = read_sequence(ctx.artifact("sequence"))
        built = read_tum(ctx.artifact("trajectory") / "trajectory_camera.tum")
        S = se3(*rigid_alignment(ground_truth_camera(seq, built.stamps).poses, built.poses))
        pts = sample_mesh(read_mesh(seq.groundtruth.mesh_path), 0.05) @ S[:3, :3].T + S[:3, 3]
        n = len(pts)
        write_map_ply(ctx.stage_dir / "map.ply", MapArrays(
            pts, np.full((n, 3), 128, np.uint8), np.ones(n, np.int64), np.ones(n, np.int32),
            np.zeros(n, np.int32), np.zeros(n, np.int32), np.zeros(n, np.float32)))
        if self.config.write_poses:  # type: ignore[attr-defined]
            shutil.copy(ctx.artifact("trajectory") / "trajectory_camera.tum",
                        ctx.stage_dir / "camera_poses.tum")
        ctx.provide("fused", ctx.stage_dir)


@pytest.fixture(autouse=True)
def stages() -> Iterator[None]:
    from toolkit.baselines.stage import CameraOnlyStage, ColmapStage, TSDFStage

    names = {"t_room": RoomSequence, "t_depth": FakeDepth, "t_fused": FakeFuse,
             "t_slam": FakeSlam, "t_slam_map": MapFrameSlam, "t_fused_map": FakeFusedMap,
             "tsdf": TSDFStage,
             "colmap": ColmapStage,
             "camera_only": CameraOnlyStage}
    for n, cls in names.items():
        registry.register(n, cls)
    yield
    for n in names:
        registry.unregister(n)


def _run(tmp_path: Path, stages: list[dict[str, Any]], force: bool = False) -> Any:
    recipe = parse_recipe({"name": "baselines", "output": str(tmp_path / "run"),
                           "stages": stages})
    from rich.console import Console

    return run_recipe(recipe, force=force, console=Console(quiet=True))


def test_tsdf_stage_groundtruth_depth_without_trajectory(tmp_path: Path) -> None:
    res = _run(tmp_path, [{"stage": "t_room", "frames": 8, "width": 160, "height": 120,
                           "small": True},
                          {"stage": "tsdf", "depth_source": "groundtruth", "views": 2,
                           "eval_spacing_m": 0.015}])
    assert res.ok, res.error
    m = res.metrics["tsdf"]
    assert m["poses"] == "groundtruth" and m["frames"] == 8
    assert m["geometry"]["fscore_2cm"] > 0.9, m["geometry"]
    assert m["views"]["psnr_db"] > 20
    run = tmp_path / "run"
    assert (run / "tsdf" / "mesh.ply").stat().st_size > 10_000
    assert (run / "tsdf" / "views.png").exists()
    report = (run / "report.md").read_text()
    assert "GROUND TRUTH" in report and "tsdf/views.png" in report


def test_tsdf_mesh_in_a_map_frame_is_not_scored_without_poses_to_align_it(
        tmp_path: Path) -> None:
    # A ground-truth mesh but no ground-truth poses: the mesh, exact but in the SLAM map
    # frame, scored 1.50 m accuracy and F@5cm 0.043 "vs GT mesh".
    res = _run(tmp_path, [{"stage": "t_room", "frames": 12, "width": 160, "height": 120,
                           "small": True, "poses": False},
                          {"stage": "t_slam_map"},
                          {"stage": "tsdf", "depth_source": "groundtruth", "views": 0,
                           "eval_spacing_m": 0.015}])
    assert res.ok, res.error
    m = res.metrics["tsdf"]
    assert m["poses"] != "groundtruth" and "geometry" not in m
    assert m["geometry_scored"] is False
    assert "not scored" in (tmp_path / "run" / "report.md").read_text()


def test_tsdf_stage_scaled_depth_at_trajectory_poses(tmp_path: Path) -> None:
    base = [{"stage": "t_room", "frames": 12, "width": 160, "height": 120, "small": True}]
    res = _run(tmp_path, [*base, {"stage": "tsdf"}])
    assert not res.ok and "fuse stage upstream" in res.error
    res = _run(tmp_path, [*base, {"stage": "tsdf", "depth_source": "groundtruth",
                                  "mask_dynamic": "groundtruth"}])
    assert not res.ok and "no ground-truth masks" in res.error
    res = _run(tmp_path, [*base, {"stage": "t_slam"}, {"stage": "t_fused"},
                          {"stage": "tsdf", "views": 0, "eval_spacing_m": 0.015}])
    assert res.ok, res.error
    m = res.metrics["tsdf"]
    assert m["poses"] == "trajectory" and m["depth_source"] == "scaled"
    assert m["min_observations"] == 2  # the default for scaled depth: drop single-frame junk
    # Exact depth at poses 3 cm off in x: a rigid offset of the whole trajectory (a SLAM map
    # frame) is undone by the map-to-world alignment before the comparison, so the surface
    # scores as exact depth does at this sampling (~1 cm), not 3 cm off.
    g = m["geometry"]
    assert g["fscore_10cm"] > 0.9, g
    assert g["accuracy_mean_m"] < 0.015, g



def test_tsdf_stage_sizes_its_volume_to_its_frames_and_frees_it_after_the_mesh(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # The quickstart's tsdf peak: a hash map doubled to 8192 blocks for 4728 (640 MiB of
    # voxels), kept alive while the stage rendered its views.
    import weakref

    from toolkit.baselines.stage import TSDFStage
    from toolkit.baselines.tsdf import TSDFVolume

    extract, views = TSDFVolume.extract_mesh, TSDFStage._views
    seen: dict[str, Any] = {}

    def extract_mesh(self: TSDFVolume) -> Any:
        hm = self.grid.hashmap()
        seen.update(size=hm.size(), capacity=hm.capacity(), volume=weakref.ref(self))
        return extract(self)

    def views_after(*a: Any, **kw: Any) -> Any:
        seen["alive_at_views"] = seen["volume"]() is not None
        return views(*a, **kw)

    monkeypatch.setattr(TSDFVolume, "extract_mesh", extract_mesh)
    monkeypatch.setattr(TSDFStage, "_views", staticmethod(views_after))
    res = _run(tmp_path, [{"stage": "t_room", "frames": 8, "width": 160, "height": 120,
                           "small": True},
                          {"stage": "tsdf", "depth_source": "groundtruth", "views": 1,
                           "geometry": False}])
    assert res.ok, res.error
    # Room for the blocks held plus one frame's (Open3D's insertion test), not 4096.
    assert seen["size"] < seen["capacity"] < 2 * seen["size"], seen
    assert seen["alive_at_views"] is False


def test_tsdf_stage_resumes_from_its_checkpoint(tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    from toolkit.baselines.tsdf import TSDFVolume

    stages = [{"stage": "t_room", "frames": 8, "width": 160, "height": 120, "small": True},
              {"stage": "tsdf", "depth_source": "groundtruth", "views": 0,
               "geometry": False, "checkpoint_every_s": 1e-9}]
    full = _run(tmp_path / "full", stages)
    assert full.ok, full.error
    integrate = TSDFVolume.integrate
    calls: list[int] = []
    killed: list[bool] = []

    def dies_at_the_6th(self: TSDFVolume, *a: Any) -> None:
        calls.append(self.frames)
        if len(calls) == 6 and not killed:
            killed.append(True)
            raise RuntimeError("killed")
        integrate(self, *a)

    monkeypatch.setattr(TSDFVolume, "integrate", dies_at_the_6th)
    assert not _run(tmp_path / "cut", stages).ok
    assert (tmp_path / "cut/run/tsdf/checkpoint.pkl").exists()
    calls.clear()
    again = _run(tmp_path / "cut", stages)
    assert again.ok, again.error
    # The volume came back with the frames of its last checkpoint (one a frame at first;
    # the interval stretches as saves take longer: Checkpoint.max_share) and took only the
    # rest.
    k = again.metrics["tsdf"]["frames_resumed"]
    assert 0 < k <= 5 and calls == list(range(k, 8))
    assert not (tmp_path / "cut/run/tsdf/checkpoint.pkl").exists()
    # The same mesh, byte for byte (vertices and triangles in canonical order).
    assert (tmp_path / "full/run/tsdf/mesh.ply").read_bytes() == (
        tmp_path / "cut/run/tsdf/mesh.ply").read_bytes()



def test_colmap_stage_keeps_the_database_of_a_killed_run(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import toolkit.baselines.colmap as colmap

    stages = [{"stage": "t_room", "frames": 6, "width": 320, "height": 240, "small": True},
              {"stage": "colmap", "overlap": 3, "max_features": 512, "triangulate": False,
               "export": False}]
    run_sfm = colmap.run_sfm

    def killed(*a: Any, **kw: Any) -> Any:
        raise RuntimeError("killed while mapping")

    monkeypatch.setattr(colmap, "run_sfm", killed)
    assert not _run(tmp_path, stages).ok
    assert (tmp_path / "run/colmap/database.json").exists()
    monkeypatch.setattr(colmap, "run_sfm", run_sfm)
    extractions: list[int] = []
    extract = colmap.extract_and_match
    monkeypatch.setattr(colmap, "extract_and_match",
                        lambda *a, **kw: extractions.append(1) or extract(*a, **kw))
    res = _run(tmp_path, stages)
    assert res.ok, res.error
    assert extractions == [] and res.metrics["colmap"]["database_resumed"]
    assert res.metrics["colmap"]["sfm"]["extract_s"] > 0  # the first run's time, reported
    # Finished, the database is an output: a forced rerun extracts and matches afresh.
    assert not (tmp_path / "run/colmap/database.json").exists()
    res = _run(tmp_path, stages, force=True)
    assert extractions == [1] and not res.metrics["colmap"]["database_resumed"]
    extractions.clear()
    # Other settings: the database is not theirs.
    res = _run(tmp_path, [stages[0], {**stages[1], "max_features": 256}])
    assert res.ok, res.error
    assert extractions == [1] and not res.metrics["colmap"]["database_resumed"]


def test_colmap_stage_mapper_setting_reaches_pycolmap(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """mapper: global reaches pycolmap.global_mapping through the stage (and camera_only's
    own COLMAP settings); left at incremental it is no part of the settings, so stages run
    before the key existed keep their cache key."""
    import pycolmap

    from toolkit.baselines.stage import CameraOnlyConfig, ColmapConfig

    calls: list[str] = []
    real = pycolmap.global_mapping
    monkeypatch.setattr(pycolmap, "global_mapping",
                        lambda *a, **kw: calls.append("global") or real(*a, **kw))
    res = _run(tmp_path, [{"stage": "t_room", "frames": 6, "width": 320, "height": 240,
                           "small": True},
                          {"stage": "colmap", "overlap": 3, "max_features": 512,
                           "triangulate": False, "export": False, "mapper": "global"}])
    assert res.ok, res.error
    # Which views it registers is test_baselines_colmap's (this room's 6 small views give
    # neither mapper a model); here: the stage ran that mapper, and says so.
    assert calls == ["global"] and res.metrics["colmap"]["mapper"] == "global"
    assert "global mapping on 6 images" in (tmp_path / "run/report.md").read_text()
    for cls, name in ((ColmapConfig, "colmap"), (CameraOnlyConfig, "camera_only")):
        assert "mapper" not in cls(stage=name).model_dump()
        on = cls(stage=name, mapper="global")
        assert on.model_dump()["mapper"] == "global"
        assert on.colmap_settings().mapper == "global"


def test_colmap_figure_draws_the_lidar_path_aligned_to_ground_truth() -> None:
    """A SLAM map frame starts at the robot's first pose, so the lidar curve is stored a
    rigid motion away from ground truth; trajectories.png must draw it on the ground truth,
    not 1.4 m beside it (as it did on the paper benchmark)."""
    from scipy.spatial.transform import Rotation

    from toolkit.baselines.stage import lidar_curve
    from toolkit.geometry import Trajectory, inv_se3

    n = 40
    a = np.linspace(0.0, 1.8 * np.pi, n)
    P = np.tile(np.eye(4), (n, 1, 1))  # [N, 4, 4] a loop in the world, heading along it
    P[:, :3, 3] = np.stack([1.5 + np.cos(a), np.sin(a), np.full(n, 0.45)], axis=1)
    P[:, :3, :3] = Rotation.from_euler("z", (a + np.pi / 2)[:, None]).as_matrix()
    stamps = np.arange(n) * 0.1
    gt = Trajectory(stamps, P, "world", "camera")
    # The map frame: the first pose is the origin.
    lidar = Trajectory(stamps, inv_se3(P[0]) @ P, "map", "camera")
    assert np.linalg.norm(lidar.positions - gt.positions, axis=1).min() > 0.5
    drawn = lidar_curve(lidar, gt)
    assert drawn is not None
    label, xyz = drawn
    assert label == "lidar SLAM (SE(3)-aligned)"
    np.testing.assert_allclose(xyz, gt.positions, atol=1e-9)
    # No ground truth: nothing to align to, the curve is drawn as stored.
    label, xyz = lidar_curve(lidar, None)  # type: ignore[misc]
    assert label == "lidar SLAM" and np.array_equal(xyz, lidar.positions)
    # No stamps in common: left out rather than drawn in another frame.
    assert lidar_curve(Trajectory(stamps + 100.0, lidar.poses), gt) is None


def test_colmap_export_puts_the_fused_map_in_the_exported_poses_frame(tmp_path: Path) -> None:
    """fuse at the SLAM poses builds its map in the SLAM map frame (turned 40 deg, 1.66 m
    from the world); colmap exporting ground-truth poses wrote that map beside them, where
    0.9 % of the points lay on the surfaces the cameras see. The export moves the map by the
    rigid fit of fuse's poses onto the exported ones, or, with nothing to fit, leaves it out."""
    from toolkit.eval.map_accuracy import MeshDistance
    from toolkit.io.colmap_text import read_colmap_model
    from toolkit.io.sequence import read_sequence

    room = {"stage": "t_room", "frames": 6, "width": 160, "height": 120, "small": True}
    colmap = {"stage": "colmap", "overlap": 3, "max_features": 256, "triangulate": False,
              "export_images": False, "poses": "groundtruth"}
    res = _run(tmp_path, [room, {"stage": "t_slam_map"}, {"stage": "t_fused_map"}, colmap])
    assert res.ok, res.error
    ex = res.metrics["colmap"]["export"]
    assert ex["poses"] == "groundtruth" and "moved by their rigid fit" in ex["points_from"]
    seq = read_sequence(tmp_path / "run" / "t_room" / "seq")
    model = read_colmap_model(tmp_path / "run" / "colmap" / "export" / "sparse" / "0")
    d = MeshDistance(seq.groundtruth.mesh_path).distance(model.points)  # [P] metres
    assert len(d) > 100 and np.max(d) < 1e-3, np.max(d)
    # Without the poses it was built at, the map's frame is unknown: not exported under
    # auto, refused when asked for.
    fuse = {"stage": "t_fused_map", "write_poses": False}
    res = _run(tmp_path, [room, {"stage": "t_slam_map"}, fuse, colmap])
    assert res.ok, res.error
    ex = res.metrics["colmap"]["export"]
    assert ex["points"] == 0 and "camera_poses.tum is missing" in ex["points_from"]
    res = _run(tmp_path, [room, {"stage": "t_slam_map"}, fuse,
                          {**colmap, "export_points": "fused"}])
    assert not res.ok and "export_points: fused" in res.error and "camera_poses.tum" in (
        res.error)


def test_colmap_without_any_poses_runs_sfm_alone(tmp_path: Path) -> None:
    """A recording with neither slam2d upstream nor ground truth: the defaults (triangulate
    and export at our poses) must not fail the stage after its SfM has run."""
    res = _run(tmp_path, [{"stage": "t_room", "frames": 6, "width": 320, "height": 240,
                           "small": True, "poses": False},
                          {"stage": "colmap", "overlap": 3, "max_features": 512}])
    assert res.ok, res.error
    m = res.metrics["colmap"]
    assert "triangulation" not in m and "export" not in m and m["sfm"]["images"] == 6
    assert "No poses of ours" in (tmp_path / "run/report.md").read_text()


@pytest.mark.slow
def test_colmap_and_camera_only_stages(tmp_path: Path) -> None:
    from toolkit.io.colmap_text import read_colmap_model

    res = _run(tmp_path, [{"stage": "t_room"}, {"stage": "t_slam"}, {"stage": "t_depth"},
                          {"stage": "colmap", "overlap": 5, "max_features": 2048},
                          {"stage": "camera_only"}])
    assert res.ok, res.error
    c = res.metrics["colmap"]
    assert c["sfm"]["registered_images"] >= 11
    assert c["sfm_vs_groundtruth"]["ate_sim3_rmse_m"] < 0.01
    # Against the lidar trajectory (ground truth + 3 cm in x) the shape is the same too.
    assert c["sfm_vs_lidar"]["ate_sim3_rmse_m"] < 0.01
    # The written Sim(3)-aligned trajectory is the one the figure scores.
    from toolkit.baselines.common import groundtruth_camera_trajectory
    from toolkit.io.sequence import read_sequence
    from toolkit.io.tum import read_tum

    aligned = read_tum(tmp_path / "run" / "colmap" / "sfm" / "trajectory_sim3.tum")
    gt = groundtruth_camera_trajectory(read_sequence(tmp_path / "run" / "t_room" / "seq"))
    assert gt is not None
    err = aligned.positions - gt.interpolate(aligned.stamps).positions  # [N, 3]
    assert np.sqrt(np.mean(np.sum(err**2, axis=1))) == pytest.approx(
        c["sfm_vs_groundtruth"]["ate_sim3_rmse_m"], abs=1e-5)
    # Triangulation at the (shifted) trajectory poses: consistent tracks; the rigid 3 cm
    # shift of the whole trajectory is undone by the map-to-world alignment before the
    # points are compared with the mesh.
    assert c["triangulation"]["poses"] == "trajectory"
    assert c["triangulation"]["reprojection_error_px"] < 0.5
    assert c["triangulation"]["gt_mesh_distance_median_m"] < 0.01
    run = tmp_path / "run"
    model = read_colmap_model(run / "colmap" / "export" / "sparse" / "0")
    assert len(model.images) == 12 and len(list((run / "colmap" / "export" / "images")
                                                .glob("*.png"))) == 12
    assert c["export"]["points_from"] == "triangulation at our poses"
    # Camera only: metric network 25 % too far -> the map is 25 % too big, shape fine.
    o = res.metrics["camera_only"]
    assert o["colmap_reused"] and o["scale_source"] == "network"
    assert o["trajectory"]["scale_to_reference"] == pytest.approx(1 / DEPTH_SCALE_ERROR,
                                                                   rel=0.03)
    assert o["trajectory"]["ate_sim3_rmse_m"] < 0.01
    assert o["depth_own_scale"]["absrel"] == pytest.approx(DEPTH_SCALE_ERROR - 1, abs=0.03)
    assert o["depth_sim3"]["absrel"] < 0.03
    assert o["geometry_sim3"]["fscore_5cm"] > 0.9
    assert o["geometry_own_scale"]["fscore_5cm"] < o["geometry_sim3"]["fscore_5cm"]
    assert (run / "camera_only" / "map.ply").exists()
    assert "camera_only/camera_only.png" in (run / "report.md").read_text()


def test_camera_only_runs_colmap_itself_without_a_colmap_stage(tmp_path: Path) -> None:
    res = _run(tmp_path, [{"stage": "t_room", "frames": 8, "width": 320, "height": 240},
                          {"stage": "t_depth"},
                          {"stage": "camera_only", "reuse_colmap": False, "overlap": 4,
                           "max_features": 1024, "geometry": False, "eval_frames": 4,
                           # fuse's smoothing keys are the stage's too (unused by the
                           # network's metres: one global factor, no per-frame scale)
                           "smoothing": "median", "smoothing_window": 5,
                           "outlier_tol": 0.25}])
    assert res.ok, res.error
    o = res.metrics["camera_only"]
    assert o["scale_smoothing"] == "none" and o["frames_flagged"] == 0
    assert not o["colmap_reused"] and not o["database_resumed"]
    assert o["registered_images"] >= 6 and o["scale_source"] == "network"
    assert (tmp_path / "run/camera_only/database.db").exists()
    assert not (tmp_path / "run/camera_only/database.json").exists()  # not an interrupted run's


def test_camera_only_records_the_mapper_of_the_model_it_reuses(tmp_path: Path) -> None:
    """camera_only reusing the colmap stage's model reported no mapper; its own key says
    nothing then (the colmap stage's applies). A change of the colmap stage's mapper reruns
    camera_only (the colmap output's token is drawn on each run) and the record follows."""
    base = [{"stage": "t_room", "frames": 8, "width": 320, "height": 240}, {"stage": "t_depth"}]
    colmap = {"stage": "colmap", "overlap": 4, "max_features": 1024, "triangulate": False,
              "export": False}
    # mapper: global on camera_only is not what made the reused model
    only = {"stage": "camera_only", "geometry": False, "eval_frames": 4, "mapper": "global"}
    res = _run(tmp_path, [*base, colmap, only])
    assert res.ok, res.error
    o = res.metrics["camera_only"]
    assert o["colmap_reused"] and o["mapper"] == res.metrics["colmap"]["mapper"] == "incremental"
    report = (tmp_path / "run/report.md").read_text()
    assert "COLMAP poses (incremental mapping, reused from the colmap stage)" in report
    res = _run(tmp_path, [*base, {**colmap, "mapper": "global"}, only])
    assert res.ok, res.error
    assert res.statuses["colmap"] == res.statuses["camera_only"] == "ran"
    assert res.metrics["camera_only"]["mapper"] == res.metrics["colmap"]["mapper"] == "global"
    # run alone, camera_only's model is its own mapper's
    res = _run(tmp_path, [*base, {**only, "reuse_colmap": False, "overlap": 4,
                                  "max_features": 1024, "mapper": "incremental"}])
    assert res.ok, res.error
    o = res.metrics["camera_only"]
    assert not o["colmap_reused"] and o["mapper"] == "incremental"


def test_camera_only_in_colmaps_unit_does_not_report_a_scale_error(tmp_path: Path) -> None:
    """Scaled by SfM points, the map is in COLMAP's unit, which the mapper sets from the
    camera path's extent (~10 units): the same room gave 12.4x, 7.9x and 6.9x the truth's
    size for arcs of 0.84, 1.39 and 1.95 m. The report called that the method's scale
    error; it now names the unit."""
    res = _run(tmp_path, [{"stage": "t_room", "frames": 8, "width": 320, "height": 240},
                          {"stage": "t_depth", "kind": "relative_depth"},
                          {"stage": "camera_only", "reuse_colmap": False, "overlap": 4,
                           "max_features": 1024, "geometry": False, "eval_frames": 4}])
    assert res.ok, res.error
    o = res.metrics["camera_only"]
    assert o["scale_source"] == "sfm" and o["own_scale_is"] == "colmap_unit"
    assert o["scale_smoothing"] == "none" and o["frames_flagged"] == 0
    # Shape right, whatever the unit.
    assert o["depth_sim3"]["absrel"] < 0.03
    report = (tmp_path / "run" / "report.md").read_text()
    assert "**scale error**" not in report and "ATE vs groundtruth, COLMAP's unit" in report


def test_camera_only_says_which_colmap_keys_a_reused_model_ignores(
        caplog: pytest.LogCaptureFixture) -> None:
    """With the colmap stage's model reused, ``every`` or ``max_images`` set on camera_only
    changed nothing and nobody said so (the paper benchmark's ``every: 1`` ran on the
    colmap stage's every 4th frame)."""
    import logging
    from types import SimpleNamespace

    from toolkit.baselines.stage import CameraOnlyConfig, _warn_colmap_keys_unused

    ctx = SimpleNamespace(stage_id="camera_only", log=logging.getLogger("toolkit.test"))
    with caplog.at_level(logging.WARNING, logger="toolkit.test"):
        _warn_colmap_keys_unused(ctx, CameraOnlyConfig(stage="camera_only", every=2,
                                                       max_images=50, min_points=20))
    assert len(caplog.records) == 1
    text = caplog.records[0].getMessage()
    assert "'every', 'max_images' not used" in text and "min_points" not in text
    assert "reuse_colmap: false" in text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="toolkit.test"):
        _warn_colmap_keys_unused(ctx, CameraOnlyConfig(stage="camera_only", min_points=20))
    assert not caplog.records

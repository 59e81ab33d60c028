"""``splat`` without a fused map (init: random) and the TSDF-mesh comparison at held-out views."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import yaml
from recipe_helpers import SplatInputs, SplatSequenceOnly  # the tests folder is on sys.path

from toolkit.camera import PinholeCamera
from toolkit.geometry import inv_se3
from toolkit.recipe import Stage, StageConfig, StageContext, load_recipe, registry, run_recipe
from toolkit.splat.mesh_compare import Comparison, MeshViewRenderer
from toolkit.splat.model import init_random_in_views, random_points_in_views
from toolkit.splat.stage import SplatStage
from toolkit.splat.synthetic import look_pose, orbit_poses, room_points, write_synthetic_inputs


class RoomMesh(Stage):
    """The synthetic room's box as a vertex-coloured mesh, like the tsdf stage's (test stage)."""

    name = "t_room_mesh"
    Config = StageConfig
    provides = ("tsdf_mesh",)

    def run(self, ctx: StageContext) -> None:
        import open3d as o3d
        from scipy.spatial import cKDTree

        box = o3d.geometry.TriangleMesh.create_box(6.0, 4.0, 2.6)
        box.translate((-3.0, -2.0, 0.0))
        box = box.subdivide_midpoint(5)
        pts, rgb = room_points(20_000)
        _, nn = cKDTree(pts).query(np.asarray(box.vertices))
        box.vertex_colors = o3d.utility.Vector3dVector(rgb[nn])
        path = ctx.stage_dir / "mesh.ply"
        o3d.io.write_triangle_mesh(str(path), box)
        ctx.provide("tsdf_mesh", path)


@pytest.fixture(autouse=True)
def stages() -> Iterator[None]:
    names = {"t_seq_only": SplatSequenceOnly, "t_room_mesh": RoomMesh,
             "t_seq_fused": SplatInputs, "splat": SplatStage}
    for name, cls in names.items():
        registry.register(name, cls)
    yield
    for name in names:
        registry.unregister(name)


def _recipe(tmp_path: Path, first: str, mesh: bool, **splat: Any) -> Path:
    stages: list[dict[str, Any]] = [{"stage": first}]
    if mesh:
        stages.append({"stage": "t_room_mesh"})
    stages.append({"stage": "splat", "iterations": 40, "downscale": 1, "holdout_every": 4,
                   "init_budget": 2000, "max_seconds": None, "log_every": 10,
                   "checkpoint_every": 0, **splat})
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump({"name": "splat_test", "output": str(tmp_path / "run"),
                                    "stages": stages}, sort_keys=False))
    return path


# ------------------------------------------------------------------------ random init
def test_random_points_lie_in_some_frustum_at_the_asked_depths() -> None:
    cam = PinholeCamera.from_fov(40, 30, 70.0)
    poses = orbit_poses(5)
    pts = random_points_in_views([cam] * 5, list(poses), 3000, (0.5, 2.0), seed=1)
    assert pts.shape == (3000, 3) and np.isfinite(pts).all()
    inside = np.zeros(len(pts), bool)
    for T in poses:
        p = pts @ inv_se3(T)[:3, :3].T + inv_se3(T)[:3, 3]
        uv, z = cam.project(p)
        ok = (z >= 0.5 - 1e-9) & (z <= 2.0 + 1e-9)
        ok &= (uv[:, 0] >= -0.5) & (uv[:, 0] <= 39.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= 29.5)
        inside |= ok
    assert inside.all()
    again = random_points_in_views([cam] * 5, list(poses), 3000, (0.5, 2.0), seed=1)
    assert np.array_equal(pts, again)
    model = init_random_in_views([cam] * 5, list(poses), 500, (0.5, 2.0), sh_degree=1)
    assert len(model) == 500
    assert torch.allclose(model.opacities, torch.full((500,), 0.1), atol=1e-6)


def test_random_init_trains_without_a_fused_map(tmp_path: Path) -> None:
    settings = {"init": "random", "depth_weight": 0.0, "random_depth_m": [0.5, 4.0],
                "init_budget": 800, "iterations": 60}
    path = _recipe(tmp_path, "t_seq_only", mesh=False, **settings)
    # The untrained start as a second splat stage of the same run (shares the sequence).
    r = yaml.safe_load(path.read_text())
    r["stages"].insert(1, {**r["stages"][1], "id": "start", "iterations": 0})
    path.write_text(yaml.safe_dump(r, sort_keys=False))
    res = run_recipe(load_recipe(path))
    assert res.ok, res.error
    m = res.metrics["splat"]
    assert m["init"] == "random" and m["n_gaussians_init"] == 800
    assert m["iterations"] == 60 and np.isfinite(m["heldout_psnr_db"])
    report = (tmp_path / "run" / "report.md").read_text()
    assert "at random" in report
    # It learns the scene: held-out PSNR above the untrained grey start (+2.5 dB seen).
    assert m["heldout_psnr_db"] > res.metrics["start"]["heldout_psnr_db"] + 1.5


def test_fused_init_without_fused_map_is_a_clear_error(tmp_path: Path) -> None:
    res = run_recipe(load_recipe(_recipe(tmp_path, "t_seq_only", mesh=False)))
    assert not res.ok
    assert "init: fused" in str(res.error) and "init: random" in str(res.error)


# ------------------------------------------------------------------------ TSDF comparison
def test_mesh_view_renderer_background_coverage_and_colour(tmp_path: Path) -> None:
    import open3d as o3d

    # A 1 x 1 m red square 2 m in front of a camera at the origin looking along +x.
    quad = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector([[2, -0.5, 0.5], [2, 0.5, 0.5], [2, 0.5, 1.5],
                                    [2, -0.5, 1.5]]),
        o3d.utility.Vector3iVector([[0, 1, 2], [0, 2, 3]]))
    quad.vertex_colors = o3d.utility.Vector3dVector(np.tile([[1.0, 0.0, 0.0]], (4, 1)))
    path = tmp_path / "quad.ply"
    o3d.io.write_triangle_mesh(str(path), quad)
    cam = PinholeCamera.from_fov(80, 60, 60.0)
    T_wc = look_pose(np.array([0.0, 0.0, 1.0]), 0.0)
    r = MeshViewRenderer(path, cam, (40, 30), background=(0.0, 0.0, 1.0))
    out = r.render(inv_se3(T_wc))
    assert out.color.shape == (30, 40, 3) and out.coverage.shape == (30, 40)
    # Coverage: the square spans 1 m at 2 m, i.e. fx * 0.5 m / 2 m each side of the centre.
    half_px = cam.fx * 0.25 / 2  # at the 40x30 size
    expect = (2 * half_px) ** 2 / (40 * 30)
    assert abs(float(out.coverage.mean()) - expect) < 0.02
    c = out.color.numpy()
    assert np.allclose(c[out.covered], [1, 0, 0], atol=1 / 255)
    none = out.coverage == 0
    assert none.any() and np.allclose(c[none], [0, 0, 1])
    edge = (out.coverage > 0) & (out.coverage < 1)
    assert edge.any()  # area-resized like the images: mixed colours along the silhouette
    comp = Comparison()
    target = out.color.clone()
    splat = torch.zeros_like(target)
    comp.add(out, splat, target)
    m = comp.metrics("heldout")
    assert m["tsdf_heldout_psnr_db"] == float("inf") or m["tsdf_heldout_psnr_db"] > 60
    # Splats black vs red on the covered pixels: MSE 1/3 over the channels.
    assert m["heldout_psnr_on_tsdf_covered_db"] == pytest.approx(10 * np.log10(3.0), abs=1e-4)
    assert m["tsdf_heldout_coverage"] == pytest.approx(out.covered.mean())
    # Pixels the splats are not scored on (lens corners without a source pixel) do not
    # count against the mesh either: a wrong colour there changes nothing.
    valid = torch.ones(target.shape[:2], dtype=torch.bool)
    valid[:, :5] = False
    off = target.clone()
    off[:, :5] = 0.5
    masked = Comparison()
    masked.add(type(out)(off, out.coverage), splat, target, valid)
    assert masked.metrics("heldout")["tsdf_heldout_psnr_db"] > 60


def test_stage_reports_tsdf_mesh_at_the_same_heldout_views(tmp_path: Path) -> None:
    res = run_recipe(load_recipe(_recipe(tmp_path, "t_seq_fused", mesh=True,
                                         iterations=25)))
    assert res.ok, res.error
    m = res.metrics["splat"]
    for p in ("heldout", "sim_heldout"):
        assert np.isfinite(m[f"tsdf_{p}_psnr_db"]) and np.isfinite(m[f"tsdf_{p}_ssim"])
        assert m[f"tsdf_{p}_coverage"] > 0.95  # a closed room: every ray hits a wall
        assert np.isfinite(m[f"tsdf_{p}_psnr_covered_db"])
        assert np.isfinite(m[f"{p}_psnr_on_tsdf_covered_db"])
        assert m[f"{p}_psnr_gain_over_tsdf_db"] == pytest.approx(
            m[f"{p}_psnr_db"] - m[f"tsdf_{p}_psnr_db"])
    assert m["tsdf_mesh_triangles"] == 12 * 4**5
    assert (tmp_path / "run" / "splat" / "splat_vs_tsdf.png").exists()
    report = (tmp_path / "run" / "report.md").read_text()
    assert "TSDF mesh PSNR" in report and "splat/splat_vs_tsdf.png" in report


def test_simulator_heldout_poses_are_moved_into_the_trajectory_frame(tmp_path: Path) -> None:
    from toolkit.geometry import Trajectory
    from toolkit.io.sequence import read_sequence
    from toolkit.splat.stage import groundtruth_to_trajectory_frame

    seq_dir, _ = write_synthetic_inputs(tmp_path, n_frames=8, width=16, height=12,
                                        n_gaussians=200)
    seq = read_sequence(seq_dir)
    gt = seq.groundtruth
    assert gt is not None and gt.poses_base is not None
    # A SLAM-like frame: origin elsewhere and turned, as slam2d's map is w.r.t. the simulator's.
    T_off = look_pose(np.array([-1.4, 0.3, 0.0]), 0.7) @ inv_se3(look_pose(np.zeros(3), 0.0))
    cams = gt.poses_base.poses @ seq.rig.T_base_camera
    traj = Trajectory(gt.poses_base.stamps, T_off @ cams, "world", "camera")
    T, rmse = groundtruth_to_trajectory_frame(seq, traj)  # type: ignore[misc]
    assert rmse < 1e-9
    assert np.allclose(T, T_off, atol=1e-9)

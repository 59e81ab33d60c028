"""The shape correction recovers a known smooth depth distortion from floor and lidar."""

from __future__ import annotations

import numpy as np
import pytest

from toolkit.camera import PinholeCamera
from toolkit.fusion.refine import CorrectionGrid, DepthRefiner, RefineOptions, floor_depth

CAM = PinholeCamera.from_fov(160, 120, 90.0)
HEIGHT_M = 0.45
WALL_X_M = 4.0


def camera_pose(pitch_deg: float = 10.0) -> np.ndarray:
    """T_base_camera: optical frame looking along base x, pitched down, 0.45 m up."""
    p = np.radians(pitch_deg)
    # optical z (forward) = base x tilted down; optical x (right) = -base y
    z = np.array([np.cos(p), 0.0, -np.sin(p)])
    x = np.array([0.0, -1.0, 0.0])
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], 1)
    T[:3, 3] = [0.0, 0.0, HEIGHT_M]
    return T


def scene_depth(T_world_camera: np.ndarray) -> np.ndarray:
    """[H, W] z-depth of a floor (z = 0) and a wall (x = 4 m) seen from the camera."""
    rays = CAM.pixel_rays() @ T_world_camera[:3, :3].T  # [H, W, 3]
    c = T_world_camera[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_floor = np.where(rays[..., 2] < 0, -c[2] / rays[..., 2], np.inf)
        t_wall = np.where(rays[..., 0] > 0, (WALL_X_M - c[0]) / rays[..., 0], np.inf)
    return np.minimum(t_floor, t_wall).astype(np.float32)


def distortion(h: int, w: int, amplitude: float = 0.04) -> np.ndarray:
    """[H, W] a smooth log-depth field, like a monocular network's shape error."""
    v, u = np.mgrid[0:h, 0:w]
    return (amplitude * (np.cos(2 * np.pi * (0.6 * u / w + 0.3 * v / h) + 0.4)
                         + 0.5 * np.sin(2 * np.pi * 0.5 * v / h))).astype(np.float32)


def wall_lidar(T_world_camera: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lidar pixels [N, 2] (col, row) and depths [N] on the wall at the lidar's height."""
    # The lidar plane (z = 0.25 m) crosses the wall along a line; project it.
    ys = np.linspace(-3.5, 3.5, 200)
    pts = np.stack([np.full_like(ys, WALL_X_M), ys, np.full_like(ys, 0.25)], 1)
    T_cw = np.linalg.inv(T_world_camera)
    pc = pts @ T_cw[:3, :3].T + T_cw[:3, 3]
    uv, z = CAM.project(pc)
    keep = (z > 0) & CAM.in_image(uv)
    px = np.rint(uv[keep]).astype(np.int64)
    return px, z[keep]


def log_error(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    return float(np.median(np.abs(np.log(a[mask] / b[mask]))))


def test_floor_depth_matches_plane_intersection() -> None:
    T = camera_pose()
    rays = CAM.pixel_rays()[[100, 110], [80, 20]] @ T[:3, :3].T
    t = floor_depth(rays, T[:3, 3], np.array([0.0, 0.0, 1.0]), np.zeros(3))
    pts = T[:3, 3] + t[:, None] * rays
    np.testing.assert_allclose(pts[:, 2], 0.0, atol=1e-9)
    # A ray going up never meets the floor.
    up = (CAM.pixel_rays()[0, 80] @ T[:3, :3].T)[None]
    assert np.isinf(floor_depth(up, T[:3, 3], np.array([0.0, 0.0, 1.0]), np.zeros(3)))[0]


def test_grid_fits_a_field_it_can_represent() -> None:
    g = CorrectionGrid(160, 120, (5, 4))
    nodes = np.random.default_rng(0).normal(0, 0.05, (4, 5))
    rows, cols = np.mgrid[0:120:6, 0:160:6]
    rows, cols = rows.ravel(), cols.ravel()
    A = g.design(rows, cols)
    fitted = g.fit(A, A.dot(nodes), smooth=1e-4, huber=1.0)
    np.testing.assert_allclose(fitted, nodes, atol=1e-3)


@pytest.mark.parametrize("outliers", [False, True])
def test_floor_and_lidar_remove_a_smooth_distortion(outliers: bool) -> None:
    T = camera_pose()
    truth = scene_depth(T)
    pred = truth * np.exp(distortion(*truth.shape))
    if outliers:
        # A box on the floor, 30 % of the floor pixels: much nearer than the floor there.
        floor = truth < (WALL_X_M - 0.1) / np.cos(np.radians(10))
        rows = np.flatnonzero(floor.any(1))
        box = np.zeros_like(floor)
        box[rows[0]:, 40:90] = True
        box &= floor
        assert box.sum() > 0.25 * floor.sum()
        truth = np.where(box, truth * 0.6, truth)
        pred = np.where(box, truth * np.exp(distortion(*truth.shape)), pred)
    px, z = wall_lidar(T, truth)
    refiner = DepthRefiner(CAM, RefineOptions(grid=(6, 5), step_px=4), floor_height_m=0.0)
    out, info = refiner.refine(pred, T, np.eye(4), px, z)
    assert info.applied and info.anchors_lidar > 50 and info.anchors_floor > 100
    valid = np.isfinite(truth)
    before = log_error(pred, truth, valid)
    after = log_error(out, truth, valid)
    assert before > 0.015
    # The box's own pixels follow the field fitted around them (it is smooth).
    assert after < 0.25 * before, (before, after)


@pytest.mark.parametrize("base_height_m", [0.0, 0.3])
def test_floor_lies_floor_height_below_base_link(base_height_m: float) -> None:
    """base_link 0.3 m above the floor (a robot's body frame, not REP 105's footprint):
    with ``floor_height_m`` 0.3 the floor reference is the true floor, and the columns
    through the lidar points start on it; the correction then removes the distortion."""
    T = camera_pose()  # the camera 0.45 m above the floor, whatever base_link's height
    T_world_base = np.eye(4)
    T_world_base[2, 3] = base_height_m
    truth = scene_depth(T)
    refiner = DepthRefiner(CAM, RefineOptions(grid=(6, 5), step_px=4),
                           floor_height_m=base_height_m)
    ref = refiner.floor_reference(T, T_world_base)  # [M]
    rays = CAM.pixel_rays()[refiner.rows, refiner.cols] @ T[:3, :3].T
    on_floor = np.isfinite(ref) & (rays[:, 0] * ref / np.linalg.norm(rays, axis=1) < 3.0)
    true_at = truth[refiner.rows, refiner.cols]
    assert on_floor.sum() > 50
    np.testing.assert_allclose(ref[on_floor], true_at[on_floor], rtol=1e-4)
    px, z = wall_lidar(T, truth)
    pts = np.column_stack([(px[:, 0] - CAM.cx) / CAM.fx * z, (px[:, 1] - CAM.cy) / CAM.fy * z, z])
    cols_px, cols_z = refiner.column_anchors(pts, T, T_world_base)
    # Column points lie on the wall, between the floor and column_top_m above it.
    Xw = (np.column_stack([(cols_px[:, 0] - CAM.cx) / CAM.fx, (cols_px[:, 1] - CAM.cy) / CAM.fy,
                           np.ones(len(cols_z))]) * cols_z[:, None]) @ T[:3, :3].T + T[:3, 3]
    assert Xw[:, 2].min() == pytest.approx(0.0, abs=0.05)
    assert Xw[:, 2].max() <= RefineOptions().column_top_m + 0.05
    pred = truth * np.exp(distortion(*truth.shape))
    out, info = refiner.refine(pred, T, T_world_base, px, z)
    valid = np.isfinite(truth)
    assert info.applied and info.anchors_floor > 100
    assert log_error(out, truth, valid) < 0.25 * log_error(pred, truth, valid)


def test_lidar_only_corrects_the_lidar_row_and_needs_anchors() -> None:
    T = camera_pose()
    truth = scene_depth(T)
    field = distortion(*truth.shape)
    pred = truth * np.exp(field)
    px, z = wall_lidar(T, truth)
    refiner = DepthRefiner(CAM, RefineOptions(grid=(6, 5)), floor_height_m=None)
    out, info = refiner.refine(pred, T, np.eye(4), px, z)
    assert info.applied and info.anchors_floor == 0
    at = (px[:, 1], px[:, 0])
    assert np.median(np.abs(np.log(out[at] / truth[at]))) < 0.3 * np.median(np.abs(field[at]))
    # Nothing to anchor to: the depth comes back unchanged.
    same, none = refiner.refine(pred, T, np.eye(4))
    assert not none.applied and same is pred


def test_consensus_keeps_the_middle_of_a_shell_of_views() -> None:
    """Ten views of a wall 4 m away, each 2 % too near or too far: the voxel map would
    hold a shell 16 cm thick; the consensus surface is the wall itself."""
    from toolkit.fusion.consensus import ConsensusSurface

    T = camera_pose(pitch_deg=0.0)
    truth = scene_depth(T)
    truth = np.where(truth < 3.9, np.nan, truth)  # the wall only, not the floor
    surface = ConsensusSurface(CAM, voxel_size_m=0.04, trunc_voxels=6, depth_max_m=6.0,
                               downsample=2)
    for k in range(10):
        err = 0.02 if k % 2 else -0.02
        surface.integrate(truth * np.float32(1 + err), T)
    rows, cols = np.mgrid[10:110:10, 10:150:10]
    rays = CAM.pixel_rays()[rows.ravel(), cols.ravel()]
    z = truth[rows.ravel(), cols.ravel()]
    ok = np.isfinite(z)
    on_wall = (rays[ok] * z[ok, None]) @ T[:3, :3].T + T[:3, 3]  # [N, 3] world
    assert not surface.off_surface(on_wall, 0.04).any()
    shifted = on_wall + np.array([0.15, 0.0, 0.0])  # 15 cm behind the wall
    assert surface.off_surface(shifted, 0.04).all()


def test_consensus_measures_the_distance_to_the_surface_not_to_its_nearest_sample() -> None:
    """A slanted wall seen from five views: the TSDF's zero crossings lie on it but up to
    a voxel apart, so points on the wall (and 2.5 cm off it, within the 3 cm asked) were
    dropped by their distance to the nearest crossing: a fifth of those on it with 6 cm
    voxels. Points 4 and 6 cm off it still go."""
    from scipy.spatial.transform import Rotation

    from toolkit.fusion.consensus import ConsensusSurface
    from toolkit.geometry import se3

    cam = PinholeCamera(640, 480, 500.0, 505.0, 321.7, 238.4)
    normal = np.array([-0.3, 0.0, 1.0])  # the wall: normal . p = 4
    unit = normal / np.linalg.norm(normal)
    rng = np.random.default_rng(0)
    xy = rng.uniform([-1.5, -1.0], [1.5, 1.0], (5000, 2))
    on_wall = np.stack([xy[:, 0], xy[:, 1], 4.0 + 0.3 * xy[:, 0]], 1)  # [N, 3]
    for voxel in (0.04, 0.06):
        surface = ConsensusSurface(cam, voxel, 6.0, 8.0, 2)
        for k in range(5):
            T = se3(Rotation.from_euler("y", 0.05 * (k - 2)).as_matrix(),
                    [0.1 * (k - 2), 0.05 * k, 0.0])
            rays = cam.pixel_rays().reshape(-1, 3) @ T[:3, :3].T
            t = (4.0 - T[:3, 3] @ normal) / (rays @ normal)
            surface.integrate(t.reshape(480, 640).astype(np.float32), T)
        for off, dropped in ((0.0, False), (0.025, False), (0.04, True), (0.06, True)):
            got = surface.off_surface(on_wall + off * unit, 0.03)
            assert got.all() if dropped else not got.any(), (voxel, off, got.mean())


def test_consensus_keeps_both_faces_of_a_wall_seen_from_both_sides() -> None:
    """A 10 cm wall (a door, an interior wall) 2 m from ten views on one side and five on
    the other: each view writes "inside" 24 cm behind the face it sees, across the wall.
    In one shared volume both faces were dropped whole (the crossings ended up in free
    space 10 cm before and 14 cm behind them); with a volume per heading both are kept.
    A view 10 % off among the ten is still dropped."""
    from toolkit.fusion.consensus import ConsensusSurface

    cam = PinholeCamera.from_fov(320, 240, 70.0)
    front, back = 2.013, 2.113  # the faces' x, off the 4 cm grid

    def pose(x: float, y: float, z: float, plus_x: bool) -> np.ndarray:
        T = np.eye(4)  # optical z along +x or -x, image y down (-z)
        T[:3, :3] = np.stack([[0, -1, 0], [0, 0, -1], [1, 0, 0]] if plus_x else
                             [[0, 1, 0], [0, 0, -1], [-1, 0, 0]], 1)
        T[:3, 3] = [x, y, z]
        return T

    rng = np.random.default_rng(0)
    yz = rng.uniform([-0.8, 0.2], [0.8, 1.3], (2000, 2))
    faces = [np.column_stack([np.full(len(yz), x), yz]) for x in (front, back)]
    for bins, dropped in ((1, 1.0), (4, 0.0)):
        surface = ConsensusSurface(cam, 0.04, 6.0, 6.0, 2, direction_bins=bins)
        for k in range(15):
            plus_x = k < 10
            x = front - 2.0 - 0.3 * rng.random() if plus_x else back + 2.0 + 0.3 * rng.random()
            T = pose(x, rng.uniform(-0.3, 0.3), rng.uniform(0.5, 1.0), plus_x)
            surface.integrate(np.full((240, 320), abs((front if plus_x else back) - x),
                                      np.float32), T)
        for f in faces:
            assert abs(surface.off_surface(f, 0.03).mean() - dropped) < 0.01, (bins, f[0, 0])
    # The bad view: 10 % too near, among the ten of the front face.
    x = front - 2.0
    bad = np.column_stack([np.full(len(yz), x + 0.9 * (front - x)), yz])
    surface.integrate(np.full((240, 320), 0.9 * (front - x), np.float32),
                      pose(x, 0.0, 0.75, True))
    assert surface.off_surface(bad, 0.03).all()
    assert not surface.off_surface(faces[0], 0.03).any()


def test_consensus_keeps_a_wall_just_behind_a_nearer_object() -> None:
    """A panel 20 cm in front of a wall, seen by eleven views walking past it: the views
    that see the panel write "inside" one band behind it. With the 6-voxel band (24 cm)
    of before it reached the wall, and 29 % of the wall beside the panel (seen straight by
    the other views) was dropped; the default 4-voxel band (16 cm) keeps all of it. The
    panel itself stays either way."""
    from toolkit.fusion.consensus import ConsensusSurface

    cam = PinholeCamera.from_fov(320, 240, 70.0)
    panel_x, wall_x = 2.013, 2.213  # off the 4 cm grid

    def pose(y: float) -> np.ndarray:
        T = np.eye(4)  # optical z along +x, image y down (-z)
        T[:3, :3] = np.stack([[0, -1, 0], [0, 0, -1], [1, 0, 0]], 1)
        T[:3, 3] = [0.0, y, 0.75]
        return T

    def depth(T: np.ndarray) -> np.ndarray:  # [240, 320] z-depth of panel and wall
        rays = cam.pixel_rays().reshape(-1, 3) @ T[:3, :3].T  # [N, 3], unit z-depth
        t_panel = (panel_x - T[0, 3]) / rays[:, 0]
        hit = T[:3, 3] + t_panel[:, None] * rays
        on_panel = (np.abs(hit[:, 1]) < 0.3) & (hit[:, 2] > 0.2) & (hit[:, 2] < 1.3)
        t_wall = (wall_x - T[0, 3]) / rays[:, 0]
        return np.where(on_panel, t_panel, t_wall).reshape(240, 320).astype(np.float32)

    rng = np.random.default_rng(0)
    yz = rng.uniform([0.3, 0.3], [0.6, 1.2], (2000, 2))
    beside = np.column_stack([np.full(len(yz), wall_x), yz])  # [N, 3] wall beside the panel
    yz = rng.uniform([-0.25, 0.3], [0.25, 1.2], (2000, 2))
    panel = np.column_stack([np.full(len(yz), panel_x), yz])
    for surface, dropped in ((ConsensusSurface(cam, 0.04, 6.0, 6.0, 2), 0.29),
                             (ConsensusSurface(cam), 0.0)):
        for y in np.linspace(-1.0, 1.0, 11):
            surface.integrate(depth(pose(y)), pose(y))
        assert surface.off_surface(beside, 0.03).mean() == pytest.approx(dropped, abs=0.02)
        assert not surface.off_surface(panel, 0.03).any()


def test_max_columns_is_a_maximum() -> None:
    """A wall 4 m ahead hit by 120-400 lidar points: never more columns than 120 (121-239
    points all had one, 240 half as many), and never fewer than half of them."""
    T = camera_pose(0.0)
    refiner = DepthRefiner(CAM, RefineOptions(max_columns=120), floor_height_m=0.0)
    T_cw = np.linalg.inv(T)

    def anchors(n: int) -> int:
        pw = np.column_stack([np.full(n, 4.0), np.linspace(-3.0, 3.0, n), np.full(n, 0.25)])
        return len(refiner.column_anchors(pw @ T_cw[:3, :3].T + T_cw[:3, 3], T, np.eye(4))[1])

    full = anchors(120)  # one column per point, all of the same height here
    for n in (121, 200, 239, 240, 400):
        assert full / 2 <= anchors(n) <= full, n


def test_column_anchor_pixels_cover_k_minus_half_to_k_plus_half() -> None:
    """A column straight ahead of a camera with cx = 2.5 projects to u = 2.5 exactly:
    pixel 3 ([2.5, 3.5)), where np.rint put it in pixel 2 (halves to even)."""
    cam = PinholeCamera(6, 40, 4.0, 4.0, 2.5, 19.5)
    refiner = DepthRefiner(cam, RefineOptions(grid=(2, 2), step_px=2))
    T = camera_pose(0.0)  # level, 0.45 m above the floor
    px, z = refiner.column_anchors(np.array([[0.0, 0.0, 2.0]]), T, np.eye(4))
    assert len(z) > 10
    np.testing.assert_allclose(z, 2.0)
    assert (px[:, 0] == 3).all(), px[:, 0]

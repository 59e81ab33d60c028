"""Property tests of the pure functions users call as a library: invariances, round trips
and known answers on random inputs (camera against OpenCV, scale estimators, trajectory
metrics, file formats). Example counts are bounded so that each test takes about a second
or two."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from toolkit import geometry as g
from toolkit.camera import PinholeCamera
from toolkit.eval import trajectory as tr
from toolkit.fusion import scale as sc
from toolkit.io import colmap_text, depth, occupancy, tum

seeds = st.integers(0, 2**31 - 1)
# tmp_path is shared by a test's examples: every example writes the same names afresh.
quick = settings(max_examples=25, deadline=None,
                 suppress_health_check=[HealthCheck.function_scoped_fixture])


def random_pose(rng: np.random.Generator, t_scale: float = 5.0) -> np.ndarray:
    return g.se3(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3) * t_scale)


def random_camera(rng: np.random.Generator, distorted: bool) -> PinholeCamera:
    w, h = int(rng.integers(16, 1300)), int(rng.integers(16, 1000))
    f = rng.uniform(0.4, 2.0) * w
    dist = (np.r_[rng.uniform(-0.4, 0.4), rng.uniform(-0.2, 0.2), rng.uniform(-0.01, 0.01, 2),
                  rng.uniform(-0.1, 0.1)] if distorted else np.zeros(5))
    return PinholeCamera(w, h, f, f * rng.uniform(0.9, 1.1), w / 2 + rng.normal(0, 5),
                         h / 2 + rng.normal(0, 5), dist)


# ---------------------------------------------------------------------------- camera


@quick
@given(seeds, st.booleans())
def test_projection_matches_opencv_and_undistortion_inverts_it(seed: int, distorted: bool) -> None:
    rng = np.random.default_rng(seed)
    cam = random_camera(rng, distorted)
    P = np.c_[rng.uniform(-0.5, 0.5, (50, 2)), rng.uniform(0.5, 5.0, 50)]  # [50, 3]
    P[:, :2] *= P[:, 2:]
    uv, z = cam.project(P)
    ref, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    ok = np.isfinite(uv).all(1)  # rays past the distortion's peak are NaN by design
    np.testing.assert_allclose(uv[ok], ref.reshape(-1, 2)[ok], atol=1e-6)
    np.testing.assert_array_equal(z, P[:, 2])
    inside = ok & cam.in_image(uv)
    xy = cam.undistort_points(uv[inside])
    np.testing.assert_allclose(xy, P[inside, :2] / P[inside, 2:], atol=1e-6)
    behind, _ = cam.project(np.array([[0.1, 0.2, -1.0], [0.0, 0.0, 0.0], [0.0, 0.0, -0.0]]))
    assert np.isnan(behind).all() and not cam.in_image(behind).any()


@quick
@given(seeds, st.integers(8, 2000), st.integers(8, 2000), st.integers(1, 4))
def test_image_edges_resizing_and_striding(seed: int, w2: int, h2: int, step: int) -> None:
    """Pixel (0, 0) spans [-0.5, 0.5): the image is [-0.5, W - 0.5) x [-0.5, H - 0.5)."""
    rng = np.random.default_rng(seed)
    cam = random_camera(rng, bool(rng.integers(2)))
    W, H = cam.width, cam.height
    edges = np.array([[-0.5, -0.5], [W - 0.5, 0.0], [0.0, H - 0.5],
                      [np.nextafter(W - 0.5, 0), np.nextafter(H - 0.5, 0)],
                      [np.nextafter(-0.5, -1), 0.0]])
    assert cam.in_image(edges).tolist() == [True, False, False, True, False]
    back = cam.scaled(w2, h2).scaled(W, H)
    for k in ("fx", "fy", "cx", "cy"):
        assert getattr(back, k) == pytest.approx(getattr(cam, k), rel=1e-12, abs=1e-9)
    P = np.c_[rng.uniform(-0.3, 0.3, (20, 2)), np.ones(20)]  # [20, 3]
    uv, _ = cam.project(P)
    uv2, _ = cam.scaled(w2, h2).project(P)
    np.testing.assert_allclose((uv + 0.5) * [w2 / W, h2 / H] - 0.5, uv2, atol=1e-6)
    uv3, _ = cam.strided(step).project(P)
    np.testing.assert_allclose(uv / step, uv3, atol=1e-9)


# ---------------------------------------------------------------------------- scale


def _pairs(rng: np.random.Generator, n: int, scale: float, outliers: float) -> tuple[
        np.ndarray, np.ndarray]:
    """Lidar depths [n] and predictions [n] = depth / scale with 0.5 % noise, a share of
    them 1.3-3x too far (pairs seen past an edge)."""
    lidar = rng.uniform(0.5, 10.0, n)
    pred = lidar / scale * np.exp(rng.normal(0, 0.005, n))
    far = rng.random(n) < outliers
    pred[far] *= rng.uniform(1.3, 3.0, far.sum())
    return lidar, pred


@settings(max_examples=40, deadline=None)
@given(seeds, st.sampled_from(sc.METHODS), st.floats(1e-3, 1e3))
def test_scale_estimators_are_equivariant_and_order_free(seed: int, method: str,
                                                         k: float) -> None:
    """Prediction times k: the scale divides by k; shuffled pairs: the same fit; a fit
    flagged ok is within 2 % of the true scale with up to 30 % outliers."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(10, 300))
    s = 10 ** rng.uniform(-2, 2)
    lidar, pred = _pairs(rng, n, s, rng.uniform(0, 0.3))
    e = sc.estimate_scale(method, lidar, pred)
    e_k = sc.estimate_scale(method, lidar, pred * k)
    assert e_k.scale == pytest.approx(e.scale / k, rel=1e-6) and e_k.quality == e.quality
    p = rng.permutation(n)
    e_p = sc.estimate_scale(method, lidar[p], pred[p])
    assert e_p.scale == pytest.approx(e.scale, rel=1e-6) and e_p.quality == e.quality
    if e.ok:
        assert e.scale == pytest.approx(s, rel=0.02)


@settings(max_examples=30, deadline=None)
@given(seeds, st.sampled_from(sc.METHODS))
def test_scale_estimators_drop_invalid_pairs_and_refuse_degenerate_frames(seed: int,
                                                                          method: str) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(10, 100))
    lidar, pred = _pairs(rng, n, 10 ** rng.uniform(-1, 1), 0.0)
    bad = rng.random(n) < 0.2
    spoilt = pred.copy()
    spoilt[bad] = rng.choice([np.nan, np.inf, -np.inf, 0.0, -1.0], bad.sum())
    e, clean = sc.estimate_scale(method, lidar, spoilt), sc.estimate_scale(
        method, lidar[~bad], pred[~bad])
    assert (np.isnan(e.scale) and np.isnan(clean.scale)) or e.scale == clean.scale
    same = sc.estimate_scale(method, np.full(n, 2.0), np.full(n, 4.0))
    assert same.ok and same.scale == pytest.approx(0.5)
    assert sc.estimate_scale(method, np.array([2.0]), np.array([4.0])).quality == sc.FEW_PAIRS
    assert not sc.estimate_scale(method, np.zeros(n), np.zeros(n)).ok


@settings(max_examples=25, deadline=None)
@given(seeds, st.sampled_from(["clustered", "robust"]))
def test_disparity_fits_recover_depth_and_are_equivariant(seed: int, method: str) -> None:
    rng = np.random.default_rng(seed)
    lidar = rng.uniform(0.5, 10.0, int(rng.integers(20, 300)))
    s, t = 10 ** rng.uniform(-1, 1), rng.uniform(-0.05, 0.3)
    disp = (1 / lidar - t) / s * np.exp(rng.normal(0, 0.003, len(lidar)))
    keep = disp > 0
    lidar, disp = lidar[keep], disp[keep]
    e = sc.estimate_scale(method, lidar, disp, disparity=True)
    if e.ok:
        z = 1 / (e.scale * disp + e.shift)
        assert np.median(np.abs(z / lidar - 1)) < 0.01
    k = 10 ** rng.uniform(-2, 2)
    e_k = sc.estimate_scale(method, lidar, disp * k, disparity=True)
    assert e_k.quality == e.quality
    if np.isfinite(e.scale):
        assert e_k.scale == pytest.approx(e.scale / k, rel=1e-5)
        assert e_k.shift == pytest.approx(e.shift, rel=1e-5, abs=1e-9)


@settings(max_examples=40, deadline=None)
@given(seeds)
def test_smoothed_scales_follow_the_units_and_replace_an_outlier_frame(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n, s = int(rng.integers(5, 40)), 10 ** rng.uniform(-1, 1)
    raw = s * np.exp(rng.normal(0, 0.01, n))  # [n]
    out = sc.smooth_scales([sc.ScaleEstimate(float(v), 0.0, 50, 60) for v in raw])
    k = 10 ** rng.uniform(-2, 2)
    out_k = sc.smooth_scales([sc.ScaleEstimate(float(v * k), 0.0, 50, 60) for v in raw])
    np.testing.assert_allclose(out_k.scale, out.scale * k, rtol=1e-9)
    j = int(rng.integers(0, n))
    raw[j] *= 2.0
    o = sc.smooth_scales([sc.ScaleEstimate(float(v), 0.0, 50, 60) for v in raw])
    assert o.flag[j] == sc.OUTLIER_FRAME and o.scale[j] == pytest.approx(s, rel=0.05)


# ---------------------------------------------------------------------------- trajectories


@settings(max_examples=30, deadline=None)
@given(seeds, st.booleans(), st.sampled_from(["general", "plane", "line"]))
def test_ate_and_rpe_do_not_depend_on_the_estimates_frame(seed: int, with_scale: bool,
                                                          shape: str) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(3, 30))
    ref = np.stack([random_pose(rng) for _ in range(n)])  # [n, 4, 4]
    if shape == "line":
        ref[:, :3, 3] = np.outer(np.linspace(0, 10, n), [1.0, 0.3, 0.0])
    elif shape == "plane":
        ref[:, 2, 3] = 0.0
    est = ref.copy()
    est[:, :3, 3] += rng.normal(0, 0.05, (n, 3))
    est[:, :3, :3] = est[:, :3, :3] @ Rotation.from_rotvec(rng.normal(0, 0.02, (n, 3))
                                                           ).as_matrix()
    R, E = g.Trajectory(np.arange(n), ref), g.Trajectory(np.arange(n), est)
    moved = E.transform(T_left=random_pose(rng, 100.0))
    align = "sim3" if with_scale else "se3"
    if with_scale:
        moved.poses[:, :3, 3] *= 3.7
    for component, tol in (("trans", 1e-9), ("rot", 1e-7)):
        a, _ = tr.ape(E, R, align, component)
        b, _ = tr.ape(moved, R, align, component)
        assert b.rmse == pytest.approx(a.rmse, abs=tol)
    pairs = tr.pairs_by_frames(n, 1, all_pairs=True)
    a, b = tr.rpe(E, R, pairs), tr.rpe(E.transform(T_left=random_pose(rng, 100.0)), R, pairs)
    assert b.rmse == pytest.approx(a.rmse, abs=1e-9)


@settings(max_examples=30, deadline=None)
@given(seeds)
def test_association_keeps_every_pair_in_any_order_and_a_barely_overlapping_one(
        seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 40))
    stamps = 1.7e9 + np.cumsum(rng.uniform(0.02, 0.2, n))  # [n]
    ref = g.Trajectory(stamps, np.stack([random_pose(rng) for _ in range(n)]))
    est = g.Trajectory(stamps + rng.uniform(-0.009, 0.009, n), ref.poses)
    i, j = tr.associate(est, ref, 0.01)
    assert i.tolist() == list(range(n)) and j.tolist() == list(range(n))
    p = rng.permutation(n)
    i, j = tr.associate(est, ref.slice(p), 0.01)
    assert i.tolist() == list(range(n)) and p[j].tolist() == list(range(n))
    # An estimate that ends where the reference starts shares that one pose.
    early = g.Trajectory(np.r_[stamps[0] - 10.0 + np.arange(5), stamps[0] + 0.005],
                         np.tile(np.eye(4), (6, 1, 1)))
    i, j = tr.associate(early, ref, 0.01)
    assert i.tolist() == [5] and j.tolist() == [0]


@settings(max_examples=40, deadline=None)
@given(seeds)
def test_slerp_takes_the_short_way_across_the_wrap_at_unix_stamps(seed: int) -> None:
    rng = np.random.default_rng(seed)
    a = rng.uniform(-np.pi, np.pi)
    b = a + rng.uniform(-np.pi + 1e-3, np.pi - 1e-3)
    t0 = 1.7e9 + rng.uniform(0, 100)
    t1 = t0 + rng.uniform(0.01, 1.0)
    P = np.stack([g.se2_to_se3(0, 0, a), g.se2_to_se3(1, 2, b)])  # [2, 4, 4]
    q = t0 + rng.uniform(0, 1) * (t1 - t0)
    out = g.interpolate_poses([t0, t1], P, [q, t0, t1])
    w = (q - t0) / (t1 - t0)
    assert abs(g.wrap_angle(g.se3_to_se2(out[0])[2] - (a + w * (b - a)))) < 1e-6
    np.testing.assert_allclose(out[1:], P, atol=1e-9)


@settings(max_examples=40, deadline=None)
@given(seeds, st.sampled_from(["near_pi", "near_zero", "any"]))
def test_quaternions_and_angles_round_trip_near_zero_and_pi(seed: int, kind: str) -> None:
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = {"near_pi": np.pi - 10 ** rng.uniform(-12, -2),
             "near_zero": 10 ** rng.uniform(-15, -3), "any": rng.uniform(0, np.pi)}[kind]
    T = g.se3(Rotation.from_rotvec(axis * angle).as_matrix(), rng.normal(size=3) * 1e3)
    xyz, q = g.pose_to_xyz_quat(T)
    assert q[3] >= 0
    np.testing.assert_allclose(g.pose_from_xyz_quat(xyz, q), T, atol=1e-12)
    assert g.rotation_angle(T[:3, :3]) == pytest.approx(angle, abs=1e-7)


@settings(max_examples=40, deadline=None)
@given(seeds)
def test_umeyama_never_returns_a_reflection(seed: int) -> None:
    rng = np.random.default_rng(seed)
    src = rng.normal(size=(int(rng.integers(3, 10)), 3))  # [n, 3]
    for with_scale in (False, True):
        R, _, s = g.umeyama_alignment(src, src * [1.0, 1.0, -1.0], with_scale)
        assert np.linalg.det(R) == pytest.approx(1.0) and s > 0


@settings(max_examples=30, deadline=None)
@given(seeds)
def test_odometry_interpolation_of_a_consistent_odometry_is_the_plain_one(seed: int) -> None:
    """Odometry that is the trajectory itself in another frame (5 km away) adds nothing:
    the result is the plain interpolation, exact at the samples."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 15))
    stamps = 1.7e9 + np.cumsum(rng.uniform(0.05, 0.2, n))  # [n]
    traj = g.Trajectory(stamps, np.stack([random_pose(rng, 3.0) for _ in range(n)]))
    C = random_pose(rng, 5000.0)
    o_st = np.unique(np.r_[rng.uniform(stamps[0] - 0.1, stamps[-1] + 0.1, 3 * n), stamps])
    odom = g.Trajectory(o_st, C @ traj.interpolate(np.clip(o_st, stamps[0], stamps[-1])).poses)
    q = np.sort(rng.uniform(stamps[0], stamps[-1], 10))
    np.testing.assert_allclose(traj.interpolate_with_odometry(odom, q).poses,
                               traj.interpolate(q).poses, atol=1e-6)
    np.testing.assert_allclose(traj.interpolate_with_odometry(odom, stamps).poses, traj.poses,
                               atol=1e-9)


# ---------------------------------------------------------------------------- files


@quick
@given(seeds, st.floats(1.0e9, 2.0e9))
def test_tum_files_keep_unix_stamps_and_poses_exactly(tmp_path: Path, seed: int,
                                                      t0: float) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 20))
    stamps = t0 + np.cumsum(rng.uniform(1e-6, 1.0, n))  # [n] microseconds apart at least
    traj = g.Trajectory(stamps, np.stack([random_pose(rng, 1e3) for _ in range(n)]), "map",
                        "base_footprint")
    tum.write_tum(tmp_path / "t.txt", traj, header="two\nlines")
    back = tum.read_tum(tmp_path / "t.txt")
    np.testing.assert_array_equal(back.stamps, stamps)
    np.testing.assert_allclose(back.poses, traj.poses, atol=1e-9)
    assert (back.frame, back.child) == ("map", "base_footprint")


@quick
@given(seeds, st.sampled_from([".png", ".npy"]))
def test_depth_files_round_trip_within_their_precision(tmp_path: Path, seed: int,
                                                       suffix: str) -> None:
    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(1, 30)), int(rng.integers(1, 30))
    d = rng.uniform(-1.0, 15.0, (h, w)).astype(np.float32)  # [H, W] metres
    d[rng.random((h, w)) < 0.1] = np.nan
    d[rng.random((h, w)) < 0.05] = np.float32(depth.PNG_DEPTH_MAX_M)
    tiny = rng.random((h, w)) < 0.05  # [H, W] positive, below half a PNG unit (0.1 mm)
    d[tiny] = rng.uniform(1e-9, 0.99e-4, int(tiny.sum()))
    path = tmp_path / f"d{suffix}"
    beyond = depth.write_depth(path, d)
    back = depth.read_depth(path)
    assert depth.file_complete(path) and back.dtype == np.float32 and back.shape == d.shape
    valid = np.isfinite(d) & (d > 0)
    assert (back[~valid] == 0).all()
    if suffix == ".npy":
        np.testing.assert_array_equal(back[valid], d[valid])
        return
    fits = valid & (np.round(d.astype(np.float64) * depth.PNG_DEPTH_SCALE) <= 65535)
    assert beyond == int((valid & ~fits).sum()) and (back[valid & ~fits] == 0).all()
    assert (back[valid & fits] > 0).all()  # a valid depth never reads back as invalid
    near = fits & ~tiny  # tiny ones are written as one unit, 0.2 mm: off by < 1 unit
    assert np.abs(back[near] - d[near]).max(initial=0) <= 0.5 / depth.PNG_DEPTH_SCALE + 1e-6
    assert np.abs(back[tiny] - d[tiny]).max(initial=0) <= 1.0 / depth.PNG_DEPTH_SCALE


@quick
@given(st.floats(0.01, 0.5), st.floats(0.0, 1.0))
def test_occupancy_maps_read_back_as_classified(tmp_path: Path, free: float,
                                                gap: float) -> None:
    occupied = free + 0.01 + gap * (0.98 - free)
    p = np.array([[0.0, free * 0.5, 1.0, np.nan, 0.5 * (free + occupied)]], np.float32)
    grid = occupancy.OccupancyMap(p, 0.05, (1.0, -2.0, 0.0))
    occupancy.write_occupancy(tmp_path / "m.yaml", grid, occupied, free)
    back = occupancy.read_occupancy(tmp_path / "m.yaml")
    expected = {occupancy.FREE: 0.0, occupancy.OCCUPIED: 1.0, occupancy.UNKNOWN: np.nan}
    want = np.array([[expected[v] for v in grid.trinary(occupied, free)[0]]], np.float32)
    np.testing.assert_array_equal(back.occupancy, want)
    assert back.origin == grid.origin and back.resolution == grid.resolution


@quick
@given(seeds, st.integers(0, 2))
def test_colmap_models_round_trip_cameras_poses_and_points(tmp_path: Path, seed: int,
                                                           lens: int) -> None:
    rng = np.random.default_rng(seed)
    dist = [np.zeros(5), np.r_[rng.normal(0, 0.1, 4), 0.0], rng.normal(0, 0.1, 5)][lens]
    cam = PinholeCamera(int(rng.integers(1, 2000)), int(rng.integers(1, 2000)),
                        rng.uniform(1, 2000), rng.uniform(1, 2000), rng.uniform(-10, 2000),
                        rng.uniform(-10, 2000), dist)
    n = int(rng.integers(1, 6))
    poses = np.stack([random_pose(rng, 100.0) for _ in range(n)])  # [n, 4, 4]
    poses[0, :3, :3] = Rotation.from_rotvec([np.pi, 0, 0]).as_matrix()  # w = 0
    points, colours = rng.normal(size=(7, 3)), rng.random((7, 3))
    colmap_text.write_poses_as_colmap(tmp_path, cam, [f"{i}.png" for i in range(n)], poses,
                                      points, colours)
    model = colmap_text.read_colmap_model(tmp_path)
    back = model.camera()
    for k in ("fx", "fy", "cx", "cy"):
        assert getattr(back, k) == pytest.approx(getattr(cam, k), abs=1e-12)
    assert back.size == cam.size and np.array_equal(back.dist, cam.dist)
    for im, T in zip(model.images, poses, strict=True):
        np.testing.assert_allclose(im.T_world_camera, T, atol=1e-10)
        np.testing.assert_allclose(im.center, T[:3, 3], atol=1e-10)
    np.testing.assert_array_equal(model.points, points)
    np.testing.assert_array_equal(model.colors, np.round(colours * 255).astype(np.uint8))


# ------------------------------------------------- second round: scans, de-skewing, SLAM grid

from dataclasses import replace  # noqa: E402

from test_deskew import circle_ranges  # noqa: E402  # the tests folder is on sys.path

from toolkit import deskew as dk  # noqa: E402
from toolkit.io.sequence import read_sequence, write_sequence  # noqa: E402
from toolkit.sensors import CameraFrame, LaserScan, Rig, Sequence  # noqa: E402
from toolkit.slam2d.grid import ProbabilityGrid  # noqa: E402
from toolkit.slam2d.matcher import GridPyramid, correlative_search, refine  # noqa: E402

bounded = settings(max_examples=40, deadline=None,
                   suppress_health_check=[HealthCheck.function_scoped_fixture])


@bounded
@given(seeds, st.booleans())
def test_scan_points_keep_valid_beams_at_their_angle_and_range(seed: int, backwards: bool) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 400))
    inc = rng.uniform(0.001, 2 * np.pi / n) * (-1 if backwards else 1)
    r_min, r_max = rng.uniform(0, 0.5), rng.uniform(5, 30)
    r = rng.uniform(-1, 35, n).astype(np.float32)  # [n]
    special = rng.random(n) < 0.3
    r[special] = rng.choice(np.array([np.nan, np.inf, -np.inf, 0.0, r_min, r_max], np.float32),
                            special.sum())
    scan = LaserScan(0.0, r, float(rng.uniform(-np.pi, np.pi)), float(inc), float(r_min),
                     float(r_max))
    want = np.isfinite(r) & (r > 0) & (r >= np.float32(r_min)) & (r < np.float32(r_max))
    p = scan.points()
    assert p.shape == (want.sum(), 2)
    np.testing.assert_allclose(np.hypot(p[:, 0], p[:, 1]), r[want], rtol=1e-6)
    a = scan.angle_min + np.flatnonzero(want) * inc
    d = np.angle(np.exp(1j * (np.arctan2(p[:, 1], p[:, 0]) - a)))
    assert np.all(np.abs(d) < 1e-6)
    assert np.isclose(scan.angles()[-1], scan.angle_max)
    p3 = scan.points_3d()
    np.testing.assert_array_equal(p3[:, :2], p)
    assert np.all(p3[:, 2] == 0)


@bounded
@given(seeds, st.integers(1, 130))
def test_scan_at_picks_the_nearest_stamp_at_ends_and_off_midpoints(seed: int, n: int) -> None:
    rng = np.random.default_rng(seed)
    # Both lookup paths: bisect below 64 stamps, searchsorted from 64 on.
    stamps = 1.7e9 + np.cumsum(rng.uniform(0.01, 0.2, n))  # [n]
    scans = [LaserScan(float(t), np.ones(3), 0.0, 0.1) for t in stamps]
    seq = Sequence(rig=None, frames=[], scans=scans)  # type: ignore[arg-type]
    for i, t in enumerate(stamps):
        assert seq.scan_index_at(float(t)) == i
    assert seq.scan_index_at(float(stamps[0]) - 0.5) == 0
    assert seq.scan_index_at(float(stamps[-1]) + 0.5) == n - 1
    for i in range(n - 1):
        a, b = float(stamps[i]), float(stamps[i + 1])
        mid = a + (b - a) / 2
        eps = 1e-3 * (b - a)
        assert seq.scan_index_at(mid - eps) == i
        assert seq.scan_index_at(mid + eps) == i + 1
        assert seq.scan_at(mid - eps) is scans[i]
    with pytest.raises(LookupError):
        seq.scan_index_at(float(stamps[-1]) + 0.5, max_dt=0.4)


@bounded
@given(seeds, st.booleans(), st.booleans(), st.booleans())
def test_deskew_undoes_a_constant_velocity_sweep_in_a_round_room(
        seed: int, back_angles: bool, back_time: bool, both_ends: bool) -> None:
    rng = np.random.default_rng(seed)
    # both_ends: a beam at -pi and at pi, as rplidar's driver spaces them (n - 1 steps).
    n, R = 360 + both_ends, float(rng.uniform(3, 8))
    inc = 2 * np.pi / 360 * (-1 if back_angles else 1)
    a0 = float(rng.uniform(-np.pi, np.pi))
    start = rng.uniform(-1, 1, 2)  # laser at the first beam, room-centred frame, heading 0
    m = np.r_[rng.uniform(-0.1, 0.1, 2), rng.uniform(-0.2, 0.2)]  # [3] motion over the sweep
    f = np.arange(n) / (n - 1)
    ang = a0 + np.arange(n) * inc
    skewed = circle_ranges(start[0] + f * m[0], start[1] + f * m[1], f * m[2] + ang, R)
    scan = LaserScan(5.0, skewed, a0, inc, 0.1, 50.0,
                     time_increment=(-1e-4 if back_time else 1e-4))
    out = dk.deskew_scan(scan, m)
    want = circle_ranges(np.full(n, start[0]), np.full(n, start[1]), ang, R)
    assert out.time_increment == 0
    # A turn against the beams' direction leaves a wedge no beam looked into: NaN there
    # (widened by the translation's parallax: walls are at least R - 1.5 m away).
    gap = np.isnan(out.ranges)
    turn_against = abs(m[2]) if m[2] * inc < 0 else 0.0
    assert gap.sum() <= (turn_against + np.hypot(m[0], m[1]) / (R - 1.5)) / abs(inc) + 2
    # Next to the wedge a bin takes its nearest point (up to half a beam off), unblended.
    edge = gap | np.roll(gap, 1) | np.roll(gap, -1)
    np.testing.assert_allclose(out.ranges[~edge], want[~edge], atol=2e-3)


@bounded
@given(seeds)
def test_deskew_of_a_standing_robot_or_an_instant_scan_changes_nothing(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 500))
    r = rng.uniform(0.2, 20, n).astype(np.float32)
    r[rng.random(n) < 0.2] = np.nan
    scan = LaserScan(1.7e9, r, -2.0, 4.0 / n, 0.1, 20.0, intensities=rng.random(n),
                     time_increment=1e-5)
    for m, s in ((np.zeros(3), scan), (rng.normal(size=3), replace(scan, time_increment=0.0))):
        out = dk.deskew_scan(s, m)
        np.testing.assert_array_equal(out.ranges, scan.ranges)
        np.testing.assert_array_equal(out.intensities, scan.intensities)
        assert out.time_increment == 0 and out.stamp == scan.stamp


@bounded
@given(seeds, st.sampled_from([0.01, 0.025, 0.05, 0.1, 0.2]))
def test_grid_cell_of_is_the_cell_whose_corner_is_at_or_below(seed: int, res: float) -> None:
    rng = np.random.default_rng(seed)
    grid = ProbabilityGrid(res, center=tuple(rng.uniform(-50, 50, 2)))
    c = rng.integers(-3000, 3000, (200, 2))  # [200, 2] grid cells, negative ones too
    corner = grid.origin + c * res  # [200, 2]
    # A point a hair (1e-6 cell) inside either side of a border; exactly on it is rounding.
    np.testing.assert_array_equal(grid.cell_of(corner + res * 1e-6), c)
    np.testing.assert_array_equal(grid.cell_of(corner - res * 1e-6), c - 1)
    np.testing.assert_array_equal(grid.cell_of(corner + res * rng.uniform(0.01, 0.99, c.shape)), c)


@bounded
@given(seeds, st.sampled_from([0.01, 0.025, 0.05, 0.1, 0.2]))
def test_grid_point_on_a_border_is_in_the_cell_whose_corner_it_is(seed: int, res: float) -> None:
    rng = np.random.default_rng(seed)
    grid = ProbabilityGrid(res, center=tuple(rng.uniform(-50, 50, 2)))
    c = rng.integers(-3000, 3000, (200, 2))  # [200, 2] grid cells
    corner = grid.origin + c * res  # [200, 2] cell -> world, rounded either way
    np.testing.assert_array_equal(grid.cell_of(corner), c)
    # Decimal borders too (0.3 / 0.1 = 2.9999999999999996 in floats), and a scan's hit
    # on one is inserted into that same cell.
    k = rng.integers(-3000, 3000, (200, 2))  # [200, 2] lattice cells (cell (0, 0) at 0 m)
    on = np.round(k * res, 6)  # [200, 2] the nearest floats to the decimal borders
    np.testing.assert_array_equal(grid.cell_of(on), k + grid.cell_of(np.zeros((1, 2))))
    near = ProbabilityGrid(res, center=tuple(on[0]))  # small: the whole span is 1200 m
    near.insert(on[0] + 1.0, on[:1])
    hit = near.cell_of(on[:1])[0]
    assert near.occupancy()[hit[1], hit[0]] > 0.5


def _room_points(rng: np.random.Generator) -> np.ndarray:
    """[N, 2] points on the walls of a 6 x 4 m room with a pillar: no symmetry to slide on."""
    t = rng.uniform(0, 1, 600)
    u = 8 * np.pi * t[550:]  # [50] round the pillar
    walls = [np.c_[-3 + 6 * t[:150], np.full(150, -2.0)],
             np.c_[-3 + 6 * t[150:300], np.full(150, 2.0)],
             np.c_[np.full(150, -3.0), -2 + 4 * t[300:450]],
             np.c_[np.full(100, 3.0), -2 + 4 * t[450:550]],
             np.c_[1.0 + 0.3 * np.cos(u), -0.5 + 0.3 * np.sin(u)]]
    return np.concatenate(walls)


def _se2(p: np.ndarray, pts: np.ndarray) -> np.ndarray:
    c, s = np.cos(p[2]), np.sin(p[2])
    return np.c_[c * pts[:, 0] - s * pts[:, 1] + p[0], s * pts[:, 0] + c * pts[:, 1] + p[1]]


@settings(max_examples=10, deadline=None)
@given(seeds)
def test_scan_matcher_recovers_a_known_small_shift_and_is_rigid_invariant(seed: int) -> None:
    rng = np.random.default_rng(seed)
    res = 0.05
    world = _room_points(rng)
    frame = np.r_[rng.uniform(-5, 5, 2), rng.uniform(-np.pi, np.pi)]  # rigid motion of both
    truth = np.r_[rng.uniform(-0.15, 0.15, 2), rng.uniform(-0.08, 0.08)]
    errs = []
    for T in (np.zeros(3), frame):
        grid = ProbabilityGrid(res, center=tuple(T[:2]))
        mapped = _se2(T, world)
        for _ in range(3):
            grid.insert(T[:2], mapped)
        field, origin = grid.matching_field(0.05)
        pyr = GridPyramid(field, origin, res, 4, grid.p_min, int(0.4 / res))
        # The scan, in its own frame, of a robot at T + truth (composed in T's frame).
        pose = np.r_[_se2(T, truth[None, :2])[0], T[2] + truth[2]]
        c, s = np.cos(pose[2]), np.sin(pose[2])
        d = mapped - pose[:2]
        scan = np.c_[c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]]
        found = correlative_search(pyr, scan, T, 0.3, 0.15, np.radians(0.5))
        assert found.found
        ref = refine(field, origin, res, scan, found.pose, translation_weight=0.0,
                     rotation_weight=0.0)
        # Walls along the grid's axes sit anywhere in their cells but score at the cells'
        # centres: up to half a cell off (the identity frame), ~1 mm when turned (measured).
        assert np.hypot(*(ref.pose[:2] - pose[:2])) < 0.6 * res
        assert abs(np.angle(np.exp(1j * (ref.pose[2] - pose[2])))) < np.radians(0.5)
        errs.append(_se2(np.r_[0, 0, -T[2]], (ref.pose[:2] - T[:2])[None])[0])
    # The same scan and map moved together match to about the same relative pose.
    assert np.hypot(*(errs[0] - errs[1])) < 0.6 * res


@settings(max_examples=15, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seeds)
def test_sequence_keeps_unix_stamps_from_nanoseconds_to_the_bit(tmp_path: Path, seed: int) -> None:
    rng = np.random.default_rng(seed)
    # ROS stamps: integer ns near 1.7e9 s, taken to float seconds as the bag reader does.
    f_ns = 1_700_000_000_000_000_000 + np.cumsum(rng.integers(1, 10**8, 4))  # [4]
    s_ns = 1_700_000_000_000_000_000 + np.cumsum(rng.integers(1, 10**8, 5))  # [5]
    f_t, s_t = [int(v) / 1e9 for v in f_ns], [int(v) / 1e9 for v in s_ns]
    rig = Rig(PinholeCamera(8, 6, 10.0, 10.0, 4.0, 3.0))
    frames = [CameraFrame.from_array(t, np.full((6, 8, 3), k, np.uint8), k)
              for k, t in enumerate(f_t)]
    scans = [LaserScan(t, rng.uniform(1, 5, 9), -1.0, 0.25, time_increment=1e-4) for t in s_t]
    write_sequence(Sequence(rig, frames, scans), tmp_path / "seq")
    back = read_sequence(tmp_path / "seq")
    assert back.frame_stamps.tolist() == f_t and back.scan_stamps.tolist() == s_t
    # float64 holds 1.7e9 s to 2**-22 s (238 ns): the ns come back within that.
    assert np.abs(np.round(back.scan_stamps * 1e9).astype(np.int64) - s_ns).max() <= 256
    assert [s.time_increment for s in back.scans] == [1e-4] * 5


@bounded
@given(seeds)
def test_rig_transforms_compose_and_remounting_keeps_the_camera(seed: int) -> None:
    rng = np.random.default_rng(seed)
    cam = PinholeCamera(64, 48, 50.0, 50.0, 32.0, 24.0)
    rig = Rig(cam, random_pose(rng, 0.5), random_pose(rng, 0.5))
    P = rng.normal(size=(20, 3))  # [20, 3] laser-frame points
    h = np.c_[P, np.ones(20)]
    via_base = (g.inv_se3(rig.T_base_camera) @ rig.T_base_laser @ h.T).T[:, :3]
    np.testing.assert_allclose((rig.T_camera_laser @ h.T).T[:, :3], via_base, atol=1e-12)
    T_new = random_pose(rng, 0.5)
    moved = rig.with_T_camera_laser(T_new)
    np.testing.assert_array_equal(moved.T_base_camera, rig.T_base_camera)
    np.testing.assert_allclose(moved.T_camera_laser, T_new, atol=1e-12)
    again = moved.with_T_camera_laser(rig.T_camera_laser)
    np.testing.assert_allclose(again.T_base_laser, rig.T_base_laser, atol=1e-12)


@pytest.mark.parametrize("n", [5, 100])  # both lookup paths: bisect, searchsorted
def test_nearest_stamp_refuses_a_nan_time(n: int) -> None:
    # NaN compared false everywhere: it passed the range check and max_dt and got scan 0
    # from 5 scans, the last from 100, without a word.
    stamps = 1.7e9 + np.arange(n) * 0.1
    frames = [CameraFrame.from_array(float(t), np.zeros((2, 2, 3)), k)
              for k, t in enumerate(stamps)]
    scans = [LaserScan(float(t), np.ones(3), 0.0, 0.1) for t in stamps]
    seq = Sequence(rig=None, frames=frames, scans=scans)  # type: ignore[arg-type]
    for look in (seq.scan_index_at, seq.frame_index_at):
        with pytest.raises(ValueError, match="nan"):
            look(float("nan"))
        with pytest.raises(ValueError, match="nan"):
            look(float("nan"), max_dt=0.05)

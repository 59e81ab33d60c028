"""Known-answer and property tests for toolkit.geometry."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from toolkit import geometry as g

angles = st.floats(-np.pi, np.pi, allow_nan=False)
coords = st.floats(-50, 50, allow_nan=False)
seeds = st.integers(0, 2**31 - 1)


def random_pose(rng: np.random.Generator, t_scale: float = 5.0) -> np.ndarray:
    return g.se3(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3) * t_scale)


@settings(max_examples=50, deadline=None)
@given(seeds)
def test_inverse_composes_to_identity(seed):
    rng = np.random.default_rng(seed)
    T = random_pose(rng)
    assert np.allclose(g.compose(T, g.inv_se3(T)), np.eye(4), atol=1e-12)
    assert np.allclose(g.inv_se3(T), np.linalg.inv(T), atol=1e-12)


@settings(max_examples=50, deadline=None)
@given(seeds)
def test_compose_is_associative_and_maps_points(seed):
    rng = np.random.default_rng(seed)
    A, B, C = (random_pose(rng) for _ in range(3))
    assert np.allclose(g.compose(g.compose(A, B), C), g.compose(A, g.compose(B, C)), atol=1e-9)
    p = rng.normal(size=(7, 3))
    assert np.allclose(g.transform_points(g.compose(A, B), p),
                       g.transform_points(A, g.transform_points(B, p)), atol=1e-9)


@settings(max_examples=50, deadline=None)
@given(coords, coords, angles, coords, coords, angles)
def test_se2_compose_matches_matrices(x1, y1, t1, x2, y2, t2):
    a, b = np.array([x1, y1, t1]), np.array([x2, y2, t2])
    M = g.se2_to_matrix(*a) @ g.se2_to_matrix(*b)
    c = g.se2_compose(a, b)
    assert np.allclose(g.se2_to_matrix(*c), M, atol=1e-9)
    assert np.allclose(g.se2_compose(g.se2_inverse(a), a)[:2], 0, atol=1e-9)
    assert abs(g.wrap_angle(g.se2_compose(g.se2_inverse(a), a)[2])) < 1e-9
    # SE(2) embeds in SE(3) and projects back.
    assert np.allclose(g.se3_to_se2(g.se2_to_se3(*c)), c, atol=1e-9)


@settings(max_examples=30, deadline=None)
@given(seeds, st.floats(0.0, 1.0))
def test_interpolation_is_slerp_and_lerp(seed, alpha):
    rng = np.random.default_rng(seed)
    A, B = random_pose(rng), random_pose(rng)
    T = g.interpolate_poses(np.array([0.0, 2.0]), np.stack([A, B]), np.array([2.0 * alpha]))[0]
    assert np.allclose(T[:3, 3], (1 - alpha) * A[:3, 3] + alpha * B[:3, 3], atol=1e-9)
    # The rotation lies on the geodesic: angle(A->T) = alpha * angle(A->B).
    ang_ab = g.rotation_angle(A[:3, :3].T @ B[:3, :3])
    ang_at = g.rotation_angle(A[:3, :3].T @ T[:3, :3])
    ang_tb = g.rotation_angle(T[:3, :3].T @ B[:3, :3])
    assert np.isclose(ang_at, alpha * ang_ab, atol=1e-7)
    assert np.isclose(ang_at + ang_tb, ang_ab, atol=1e-7)


def test_interpolation_hits_knots_and_rejects_outside():
    rng = np.random.default_rng(0)
    P = np.stack([random_pose(rng) for _ in range(4)])
    st_ = np.array([0.0, 1.0, 2.5, 3.0])
    assert np.allclose(g.interpolate_poses(st_, P, st_), P, atol=1e-12)
    with pytest.raises(ValueError, match="outside the trajectory span"):
        g.interpolate_poses(st_, P, np.array([3.5]))
    # A small tolerance clamps to the end pose rather than extrapolating.
    assert np.allclose(g.interpolate_poses(st_, P, np.array([3.05]), extrapolate_s=0.1)[0], P[-1])


@settings(max_examples=30, deadline=None)
@given(seeds, st.floats(-1e4, 1e9))
def test_tum_line_round_trip(seed, stamp):
    rng = np.random.default_rng(seed)
    T = random_pose(rng)
    t2, T2 = g.tum_line_to_pose(g.pose_to_tum_line(stamp, T))
    assert t2 == stamp
    assert np.allclose(T2, T, atol=1e-12)


def half_turns() -> list[list[np.ndarray]]:
    """Groups of half-turns [3, 3]: each group one rotation computed in ways that differ by
    rounding only, which scipy turns into a w of +-6e-17 or 2e-16 (q or -q)."""
    def rv(v: list[float] | np.ndarray) -> np.ndarray:
        return Rotation.from_rotvec(v).as_matrix()

    ax = np.array([1.0, 2.0, 2.0]) / 3
    return [[rv([0, 0, np.pi]), rv([0, 0, -np.pi]), rv([0, 0, np.pi / 2]) @ rv([0, 0, np.pi / 2]),
             np.diag([-1.0, -1.0, 1.0])],
            [rv([np.pi, 0, 0]), rv([-np.pi, 0, 0]), np.diag([1.0, -1.0, -1.0])],
            [rv([0, -np.pi, 0]), rv([0, np.pi, 0])],
            [rv(np.pi * ax), rv(-np.pi * ax)]]


def test_a_half_turn_is_written_with_one_quaternion_sign_however_it_was_computed() -> None:
    t = np.array([1.0, -2.0, 3.0])
    for group in half_turns():
        lines = {g.pose_to_tum_line(5.0, g.se3(R, t)) for R in group}
        assert len(lines) == 1, lines
        q = np.array(lines.pop().split()[4:], dtype=float)  # [4] xyzw
        assert q[3] == 0 and q[np.flatnonzero(q[:3])[0]] > 0
        for R in group:
            np.testing.assert_allclose(g.tum_line_to_pose(g.pose_to_tum_line(5.0, g.se3(R, t)))[1],
                                       g.se3(R, t), atol=1e-15)
    # The same half-turn as 2 a a^T - I differs from the rotation vector's in the last
    # digits of x, y, z; the sign still agrees.
    a = np.array([1.0, 2.0, 2.0]) / 3
    _, q1 = g.pose_to_xyz_quat(g.se3(2 * np.outer(a, a) - np.eye(3)))
    _, q2 = g.pose_to_xyz_quat(g.se3(Rotation.from_rotvec(-np.pi * a).as_matrix()))
    np.testing.assert_allclose(q1, q2, atol=1e-15)
    # Batches take the same rule; w > 0 stays as it was, w < 0 flips.
    qs = np.array([[0.0, 0.0, -1.0, -1e-17], [-0.6, 0.0, 0.0, 0.8], [0.6, 0.0, 0.0, -0.8]])
    want = [[0.0, 0.0, 1.0, 0.0], [-0.6, 0.0, 0.0, 0.8], [-0.6, 0.0, 0.0, 0.8]]
    np.testing.assert_array_equal(g.canonical_quat(qs), want)


def test_tum_line_rejects_bad_input():
    with pytest.raises(ValueError, match="8 numbers"):
        g.tum_line_to_pose("1 2 3")
    with pytest.raises(ValueError, match="non-finite"):
        g.tum_line_to_pose("0 nan 0 0 0 0 0 1")


def test_umeyama_with_scale_refuses_identical_source_points_without_a_warning() -> None:
    """The check came after dividing by their zero spread: a RuntimeWarning first, and that
    instead of the ValueError where warnings are errors."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ValueError, match="all identical"):
            g.umeyama_alignment(np.ones((4, 3)), np.arange(12.0).reshape(4, 3), True)


def test_wrap_angle_stays_in_its_half_open_range_just_below_minus_pi() -> None:
    """Angles within a few ulp below -pi wrapped to +pi (the sum with pi rounds to a tiny
    negative number whose modulo rounds up to 2 pi): outside [-pi, pi)."""
    a = -np.pi - np.logspace(-16, -14, 200)  # [200]
    w = g.wrap_angle(a)
    assert np.all((w >= -np.pi) & (w < np.pi))
    assert all(-np.pi <= g.wrap_angle(float(x)) < np.pi for x in a)
    assert g.wrap_angle(np.nextafter(-np.pi, -4.0)) == -np.pi


@settings(max_examples=30, deadline=None)
@given(seeds, st.booleans())
def test_umeyama_recovers_random_sim3_exactly(seed, with_scale):
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=rng).as_matrix()
    t = rng.normal(size=3) * 10
    s = float(rng.uniform(0.1, 10.0)) if with_scale else 1.0
    src = rng.normal(size=(20, 3)) * 3
    dst = s * src @ R.T + t
    R2, t2, s2 = g.umeyama_alignment(src, dst, with_scale=with_scale)
    assert np.allclose(R2, R, atol=1e-9)
    assert np.allclose(t2, t, atol=1e-8)
    assert np.isclose(s2, s, rtol=1e-9)


def test_align_trajectory_sim3():
    rng = np.random.default_rng(3)
    P = np.stack([random_pose(rng) for _ in range(10)])
    ref = g.Trajectory(np.arange(10.0), P)
    S = g.sim3(Rotation.from_euler("z", 0.7).as_matrix(), np.array([1.0, -2.0, 0.5]), 2.5)
    est_P = P.copy()
    est_P[:, :3, 3] = (P[:, :3, 3] - S[:3, 3]) @ np.linalg.inv(S[:3, :3]).T
    est_P[:, :3, :3] = Rotation.from_euler("z", -0.7).as_matrix() @ P[:, :3, :3]
    aligned, S_found = g.align_trajectory(g.Trajectory(np.arange(10.0), est_P), ref, True)
    assert np.allclose(aligned.poses, P, atol=1e-9)
    assert np.allclose(S_found, S, atol=1e-9)


def test_trajectory_covers_its_span_but_not_its_gaps():
    from toolkit.geometry import Trajectory

    st = np.r_[np.arange(0.0, 10.0, 0.1), np.arange(30.0, 40.0, 0.1)]  # a 20 s gap
    traj = Trajectory(st, np.tile(np.eye(4), (len(st), 1, 1)))
    q = np.array([-0.1, 0.0, 5.05, 9.9, 15.0, 30.0, 35.0, 39.9, 40.0, 39.95])
    assert traj.covers(q).tolist() == [False, True, True, True, False, True, True, True,
                                       False, False]
    assert traj.covers(q, slack_s=0.2).tolist()[0] and traj.covers(q, slack_s=0.2)[-2]
    assert traj.covers(np.array([15.0]), max_gap_s=25.0)[0]  # a gap one accepts
    # Within slack_s of an end that a long gap follows: interpolation takes the end pose
    # there, so the gap does not matter (both were refused).
    ends = Trajectory(np.array([0.0, 20.0, 20.1, 40.0]), np.tile(np.eye(4), (4, 1, 1)))
    assert ends.covers(np.array([-0.1, 40.1, 10.0]), max_gap_s=1.0, slack_s=0.2).tolist() == [
        True, True, False]


def test_a_weaving_drive_is_aligned_by_its_positions_not_its_orientations() -> None:
    """A 50 m drive weaving 1 m (sideways spread 4.8 % of the length, under the old 5 %
    "line" ratio), positions exact, orientations 2 deg off in roll, in another map frame:
    the alignment recovers the map frame exactly (the roll from the orientations had put
    2.4 cm of ATE on the exact positions and turned the map 2 deg)."""
    x = np.linspace(0.0, 50.0, 400)
    y = np.sin(2 * np.pi * x / 10.0)
    yaw = np.arctan2(np.gradient(y), np.gradient(x))
    pos = np.stack([x, y, np.full_like(x, 0.3)], 1)
    rot = [Rotation.from_euler("z", a).as_matrix() for a in yaw]
    B = Rotation.from_euler("x", 2.0, degrees=True).as_matrix()
    M = g.se3(Rotation.from_euler("z", 30, degrees=True).as_matrix(), [2.0, -1.0, 0.0])
    gt = np.stack([g.se3(r, p) for r, p in zip(rot, pos, strict=True)])
    est = M @ np.stack([g.se3(B @ r, p) for r, p in zip(rot, pos, strict=True)])
    R, t, _ = g.pose_alignment(est, gt)
    np.testing.assert_allclose(g.se3(R, t) @ M, np.eye(4), atol=1e-9)


@settings(max_examples=20, deadline=None)
@given(seeds, st.booleans())
def test_a_straight_drive_aligns_the_same_in_any_frame_of_the_estimate(seed: int,
                                                                       with_scale: bool) -> None:
    """The alignment onto an exactly straight reference, of an estimate with 0.2 m of noise,
    must not depend on the frame the estimate is given in. The turn about the line was
    taken about the estimate's own principal axis after Umeyama's rotation, whose part
    about the line the positions leave free: the aligned positions moved by up to 11 mm
    with a rigid motion of the estimate (200 such drives)."""
    rng = np.random.default_rng(seed)
    n = 20
    ref = np.tile(np.eye(4), (n, 1, 1))  # [n, 4, 4]
    ref[:, :3, :3] = Rotation.random(n, random_state=rng).as_matrix()
    ref[:, :3, 3] = np.outer(np.linspace(0.0, 20.0, n), [0.6, 0.8, 0.0])
    est = ref.copy()
    est[:, :3, 3] += rng.normal(0.0, 0.2, (n, 3))
    est[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.01, (n, 3))).as_matrix() @ est[
        :, :3, :3]
    aligned = []
    for k in range(3):
        M = random_pose(rng, 10.0) if k else np.eye(4)
        moved = M @ est
        if with_scale:
            moved[:, :3, 3] *= 2.5
        R, t, s = g.pose_alignment(moved, ref, with_scale)
        aligned.append(s * moved[:, :3, 3] @ R.T + t)  # [n, 3]
    np.testing.assert_allclose(aligned[1], aligned[0], atol=1e-9)
    np.testing.assert_allclose(aligned[2], aligned[0], atol=1e-9)


def _turn_onset_drive(stamps: np.ndarray) -> np.ndarray:
    """[N, 4, 4] base poses of a robot driving 0.3 m/s straight that starts turning at
    1 rad/s at t = 1.05 s (between two 10 Hz samples): the yaw's kink is where a straight
    line between scan poses goes wrong."""
    fine = np.arange(0.0, stamps.max() + 1e-3, 1e-3)
    w = np.where(fine > 1.05, 1.0, 0.0)
    yaw = np.r_[0.0, np.cumsum(w[1:] * 1e-3)]
    x = np.r_[0.0, np.cumsum(0.3 * np.cos(yaw[1:]) * 1e-3)]
    y = np.r_[0.0, np.cumsum(0.3 * np.sin(yaw[1:]) * 1e-3)]
    out = []
    for t in stamps:
        k = int(round(t / 1e-3))
        out.append(g.se3(Rotation.from_euler("z", yaw[k]).as_matrix(), [x[k], y[k], 0.0]))
    return np.stack(out)


def test_odometry_carries_poses_between_samples_through_a_turn_onset() -> None:
    """Scan poses at 10 Hz, exact; wheel odometry at 50 Hz, exact motion but in its own
    frame (an odom origin 3 m and 40 deg away): camera stamps 41 ms before each scan get
    the true pose with the odometry, but for the odometry's own 20 ms interpolation across
    the kink (0.03 deg), where a straight line between scans is 1.2 deg off at the turn's
    start; at the samples themselves both are exact."""
    from toolkit.geometry import Trajectory

    scan_t = np.round(np.arange(0.1, 2.01, 0.1), 6)
    odom_t = np.round(np.arange(0.0, 2.05, 0.02), 6)
    T_world_odom = g.se3(Rotation.from_euler("z", 40, degrees=True).as_matrix(), [3.0, -1, 0])
    traj = Trajectory(scan_t, _turn_onset_drive(scan_t))
    odom = Trajectory(odom_t, g.inv_se3(T_world_odom) @ _turn_onset_drive(odom_t), "odom")
    q = scan_t[1:] - 0.041  # a camera stamp 41 ms before each scan
    truth = _turn_onset_drive(q)

    def yaw_err_deg(P: np.ndarray) -> np.ndarray:
        R = np.swapaxes(truth[:, :3, :3], 1, 2) @ P[:, :3, :3]
        return np.degrees(np.abs(Rotation.from_matrix(R).as_rotvec()[:, 2]))

    plain = traj.interpolate(q).poses
    with_odom = traj.interpolate_with_odometry(odom, q).poses
    assert yaw_err_deg(plain).max() > 1.0  # the turn's start between 1.0 and 1.1 s
    assert yaw_err_deg(with_odom).max() < 0.05
    assert np.abs(with_odom[:, :3, 3] - truth[:, :3, 3]).max() < 1e-4
    assert np.allclose(traj.interpolate_with_odometry(odom, scan_t).poses, traj.poses,
                       atol=1e-12)


def test_odometry_interpolation_falls_back_to_a_straight_line() -> None:
    """No odometry, odometry that never moves, and queries the odometry does not cover
    all give the plain interpolation."""
    from toolkit.geometry import Trajectory

    scan_t = np.round(np.arange(0.1, 2.01, 0.1), 6)
    traj = Trajectory(scan_t, _turn_onset_drive(scan_t))
    q = np.linspace(0.1, 2.0, 77)
    plain = traj.interpolate(q).poses
    still = Trajectory(np.arange(0.0, 2.1, 0.02), np.tile(np.eye(4), (105, 1, 1)), "odom")
    assert np.allclose(traj.interpolate_with_odometry(None, q).poses, plain, atol=1e-12)
    assert np.allclose(traj.interpolate_with_odometry(still, q).poses, plain, atol=1e-12)
    odom_t = np.round(np.arange(0.0, 1.0, 0.02), 6)  # ends at 0.98 s
    odom = Trajectory(odom_t, _turn_onset_drive(odom_t), "odom")
    late = q > 0.9  # the sample after 0.9 s has no odometry: a straight line there
    got = traj.interpolate_with_odometry(odom, q).poses
    assert np.allclose(got[late], plain[late], atol=1e-12)
    camera = Trajectory(odom_t, _turn_onset_drive(odom_t), "odom", "camera")  # another child
    assert np.allclose(traj.interpolate_with_odometry(camera, q).poses, plain, atol=1e-12)


def test_odometry_interpolation_does_not_depend_on_the_odometry_origin() -> None:
    """The same odometry (15 % too much yaw in a 1 rad/s turn) expressed about an origin
    at the robot and one 5 km away gives the same poses between exact scan poses (blending
    the map -> odom corrections moved them 14 cm at 5 km); odometry standing still 100 m
    from its origin gives the straight line between the scan poses."""
    from toolkit.geometry import Trajectory

    scan_t = np.round(np.arange(0.0, 2.01, 0.1), 6)
    odom_t = np.round(np.arange(0.0, 2.01, 0.01), 6)

    def drive(t: np.ndarray, rate: float) -> np.ndarray:
        yaw = rate * t
        return np.stack([g.se3(Rotation.from_euler("z", a).as_matrix(),
                               [0.3 * np.sin(a) / rate, 0.3 * (1 - np.cos(a)) / rate, 0.0])
                         for a in yaw])

    traj = Trajectory(scan_t, drive(scan_t, 1.0))
    q = np.linspace(0.0, 2.0, 91)
    near = Trajectory(odom_t, drive(odom_t, 1.15), "odom")
    far_origin = g.se3(Rotation.from_euler("z", 0.3).as_matrix(), [5000.0, 0.0, 0.0])
    far = Trajectory(odom_t, far_origin @ drive(odom_t, 1.15), "odom")
    a = traj.interpolate_with_odometry(near, q).poses
    b = traj.interpolate_with_odometry(far, q).poses
    assert np.abs(a[:, :3, 3] - b[:, :3, 3]).max() < 1e-6
    assert np.allclose(a[:, :3, :3], b[:, :3, :3], atol=1e-9)
    still = Trajectory(odom_t, np.tile(g.se3(np.eye(3), [100.0, 0.0, 0.0]), (len(odom_t), 1, 1)),
                       "odom")
    assert np.allclose(traj.interpolate_with_odometry(still, q).poses, traj.interpolate(q).poses,
                       atol=1e-9)

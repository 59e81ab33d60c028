"""Trajectory metrics: hand-computed answers and evo's reference values."""

import json
import zipfile

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from toolkit.eval.trajectory import (
    ErrorStats,
    ape,
    associate,
    pairs_by_frames,
    pairs_by_path,
    per_axis_errors,
    rpe,
    trajectory_report,
)
from toolkit.geometry import Trajectory, se2_to_se3, se3, sim3
from toolkit.io.kitti import read_kitti
from toolkit.io.tum import read_tum


def line_traj(n: int = 5) -> Trajectory:
    return Trajectory(np.arange(n, dtype=float), np.stack([se2_to_se3(i, 0, 0) for i in range(n)]))


def test_error_stats_hand_computed():
    s = ErrorStats.of(np.array([3.0, 4.0]))
    assert s.rmse == pytest.approx(np.sqrt(12.5)) and s.mean == 3.5 and s.max == 4.0


def test_ape_without_alignment_is_offset():
    ref = line_traj()
    est = ref.transform(T_left=se2_to_se3(0.0, 0.3, 0.0))
    stats, _ = ape(est, ref, align="none")
    assert stats.rmse == pytest.approx(0.3) and stats.std == pytest.approx(0.0, abs=1e-12)
    # SE(3) alignment removes a rigid offset completely.
    assert ape(est, ref, align="se3")[0].rmse == pytest.approx(0.0, abs=1e-9)


def test_sim3_alignment_removes_scale():
    rng = np.random.default_rng(0)
    P = np.stack([se3(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3))
                  for _ in range(12)])
    ref = Trajectory(np.arange(12.0), P)
    S = sim3(Rotation.from_euler("xyz", [0.1, 0.2, 0.3]).as_matrix(), [1, 2, 3], 0.5)
    est_P = P.copy()
    est_P[:, :3, 3] = P[:, :3, 3] @ S[:3, :3].T + S[:3, 3]
    est = Trajectory(np.arange(12.0), est_P)
    assert ape(est, ref, "se3")[0].rmse > 0.1
    assert ape(est, ref, "sim3")[0].rmse == pytest.approx(0.0, abs=1e-9)


def test_sim3_ate_does_not_depend_on_the_estimates_units():
    """A monocular estimate's units are arbitrary: the same 3-D path at 1/100 of its scale
    was taken for a line (its spread under the 5 cm floor in its own units) and aligned by
    its orientations instead of Umeyama."""
    rng = np.random.default_rng(3)
    n = 60
    pos = np.cumsum(rng.normal(0, 0.05, (n, 3)), 0)  # a 3-D wander of about 0.4 m
    gt = np.stack([se3(Rotation.random(random_state=rng).as_matrix(), q) for q in pos])
    est = gt.copy()
    est[:, :3, 3] += rng.normal(0, 0.01, (n, 3))
    est[:, :3, :3] = np.einsum("ij,njk->nik",
                               Rotation.from_euler("z", 5, degrees=True).as_matrix(),
                               est[:, :3, :3])  # orientations off: they must not be used
    stamps = np.arange(n) * 0.1
    base = ape(Trajectory(stamps, est), Trajectory(stamps, gt), "sim3")[0].rmse
    for k in (0.1, 0.01):
        small = est.copy()
        small[:, :3, 3] *= k
        got = ape(Trajectory(stamps, small), Trajectory(stamps, gt), "sim3")[0].rmse
        assert got == pytest.approx(base, rel=1e-9)


def test_rpe_of_constant_drift_per_step():
    ref = line_traj(6)
    # Each step of the estimate is 1.1 m instead of 1 m: relative error 0.1 m per step.
    est = Trajectory(ref.stamps, np.stack([se2_to_se3(1.1 * i, 0, 0) for i in range(6)]))
    s = rpe(est, ref, pairs_by_frames(6, 1, all_pairs=True))
    assert s.mean == pytest.approx(0.1) and s.count == 5
    assert pairs_by_path(ref.positions, 2.0) == [(2, 4)]


def test_per_axis_errors():
    ref = line_traj()
    est = ref.transform(T_right=se3(Rotation.from_euler("z", 2, degrees=True).as_matrix(),
                                    [0, 0, 0.05]))
    e = per_axis_errors(est, ref)
    assert e["z_rmse_m"] == pytest.approx(0.05) and e["x_rmse_m"] == pytest.approx(0.0)
    assert e["yaw_rmse_deg"] == pytest.approx(2.0) and e["orientation_rmse_deg"] == pytest.approx(2)


def test_associate_one_to_one():
    a = Trajectory(np.array([0.0, 1.0, 1.003, 2.0]), np.tile(np.eye(4), (4, 1, 1)))
    b = Trajectory(np.array([0.005, 1.002, 3.0]), np.tile(np.eye(4), (3, 1, 1)))
    i, j = associate(a, b, max_diff=0.01)
    assert i.tolist() == [0, 2] and j.tolist() == [0, 1]
    # TUM's rule: a stamp whose nearest partner is taken pairs with its next candidate
    c = Trajectory(np.array([1.000, 1.003]), np.tile(np.eye(4), (2, 1, 1)))
    d = Trajectory(np.array([1.002, 1.008]), np.tile(np.eye(4), (2, 1, 1)))
    i, j = associate(c, d, max_diff=0.01)
    assert i.tolist() == [0, 1] and j.tolist() == [1, 0]


def test_associate_pairs_a_reference_whose_stamps_are_not_sorted() -> None:
    """A Trajectory built by hand may hold its stamps in any order; associate.py pairs them
    all the same. The binary search in unsorted stamps kept 3 of these 10 pairs, and
    trajectory_report scored the 3 without a word."""
    rng = np.random.default_rng(0)
    stamps = np.cumsum(rng.uniform(0.05, 0.2, 10))  # [10]
    est = Trajectory(stamps, np.stack([se2_to_se3(t, 0.1 * t, 0.0) for t in stamps]))
    shuffled = rng.permutation(10)
    ref = Trajectory(stamps[shuffled], est.poses[shuffled])
    i, j = associate(est, ref, max_diff=0.01)
    assert i.tolist() == list(range(10))
    assert shuffled[j].tolist() == list(range(10))  # each pose with its own copy
    report = trajectory_report(est, ref)
    assert report["ate_count"] == 10 and report["ate_rmse_m"] < 1e-12


def test_evo_reference_kitti(shared_data):
    d = shared_data / "eval" / "evo-reference"
    gt = read_kitti(d / "KITTI_00_gt.txt", d / "KITTI_00_gt_times.txt")
    orb = read_kitti(d / "KITTI_00_ORB.txt", d / "KITTI_00_gt_times.txt")
    stats, _ = ape(orb, gt, align="se3")
    ref_ape = json.loads(zipfile.ZipFile(d / "res_files" / "orb_ape.zip").read("stats.json"))
    assert stats.rmse == pytest.approx(1.3034497, abs=1e-4)
    assert stats.rmse == pytest.approx(ref_ape["rmse"], abs=1e-6)
    assert stats.mean == pytest.approx(1.1569971, abs=1e-4)
    assert stats.max == pytest.approx(3.5879491, abs=1e-4)
    # evo walks the estimate's path to choose the pairs.
    r = rpe(orb, gt, pairs_by_path(orb.positions, 10.0))
    ref_rpe = json.loads(zipfile.ZipFile(d / "res_files" / "orb_rpe.zip").read("stats.json"))
    assert r.rmse == pytest.approx(0.2262613, abs=1e-4)
    assert r.rmse == pytest.approx(ref_rpe["rmse"], abs=1e-6)


def test_tum_reference_files_parse_and_report(shared_data):
    d = shared_data / "eval" / "evo-reference"
    gt = read_tum(d / "freiburg1_xyz-groundtruth.txt")
    est = read_tum(d / "freiburg1_xyz-rgbdslam.txt")
    rep = trajectory_report(est, gt, align="se3", max_diff=0.01)
    assert rep["ate_count"] > 500 and 0.0 < rep["ate_rmse_m"] < 0.1


def test_per_axis_heading_error_is_yaw_for_optical_cameras():
    # A camera looking forward (optical frame) on a robot whose heading is off by 1 degree.
    R_base_optical = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=float)
    ref = Trajectory(np.arange(3.0), np.stack([se2_to_se3(i, 0, 0) @ se3(R_base_optical)
                                               for i in range(3)]))
    est = ref.transform(T_left=se3(Rotation.from_euler("z", 1, degrees=True).as_matrix()))
    e = per_axis_errors(est.transform(), ref)
    assert e["yaw_rmse_deg"] == pytest.approx(1.0) and e["pitch_rmse_deg"] < 1e-9


def test_trajectory_report_refuses_poses_of_different_bodies():
    from toolkit.eval.trajectory import trajectory_report
    from toolkit.geometry import Trajectory

    st = np.arange(10.0)
    P = np.tile(np.eye(4), (10, 1, 1))
    P[:, 0, 3] = st
    base = Trajectory(st, P, "world", "base_link")
    cam = Trajectory(st, P, "world", "camera")
    with pytest.raises(ValueError, match="same body"):
        trajectory_report(cam, base)
    assert trajectory_report(base, base)["ate_rmse_m"] < 1e-9


def test_ground_truth_camera_poses_are_labelled_as_the_camera(tmp_path):
    from toolkit.eval.alignment import ground_truth_camera
    from toolkit.eval.trajectory import trajectory_report
    from toolkit.fusion.synthetic import write_box_room
    from toolkit.io.sequence import read_sequence

    seq = read_sequence(write_box_room(tmp_path / "seq", n_frames=6))
    cam = ground_truth_camera(seq, seq.frame_stamps)
    assert cam.child == "camera"
    assert np.allclose(cam.poses[0], seq.groundtruth.poses_base.interpolate(
        seq.frame_stamps[:1]).poses[0] @ seq.rig.T_base_camera)
    assert trajectory_report(cam, cam)["ate_rmse_m"] < 1e-9


def test_straight_drive_is_aligned_by_its_orientations():
    """Positions along a line leave the turn about it free to an SE(3) fit of the positions
    (a perfect estimate showed 7 deg orientation error and moved the map 0.3 m)."""
    from toolkit.geometry import align_trajectory, rigid_alignment

    n = 40
    R_cam = Rotation.from_euler("xyz", [-90, 0, -90], degrees=True).as_matrix()
    gt = np.stack([se3(R_cam, [x, 0.0, 0.3]) for x in np.linspace(0, 4.9, n)])
    T = se3(Rotation.from_euler("z", 40, degrees=True).as_matrix(), [2.0, -1.0, 0.0])
    est = np.einsum("ij,njk->nik", np.linalg.inv(T), gt)  # the same path in its own frame
    est[:, :3, 3] += np.random.default_rng(1).normal(0, 0.001, (n, 3))
    R, t = rigid_alignment(est, gt)
    # The line's direction from the noisy positions (1 mm over 4.9 m), the turn about it
    # from the orientations: not 180 deg off.
    assert np.degrees(Rotation.from_matrix(R.T @ T[:3, :3]).magnitude()) < 0.05
    stamps = np.arange(n) * 0.1
    for with_scale in (False, True):
        aligned, _ = align_trajectory(Trajectory(stamps, est), Trajectory(stamps, gt),
                                      with_scale)
        ang = Rotation.from_matrix(np.einsum("nji,njk->nik", aligned.poses[:, :3, :3],
                                             gt[:, :3, :3])).magnitude()
        assert np.degrees(ang).max() < 0.05
        assert np.abs(aligned.positions - gt[:, :3, 3]).max() < 0.005


def test_a_heading_bias_on_a_straight_drive_does_not_move_its_positions():
    """Exact positions, orientations 3 deg off in yaw: the alignment follows the positions
    (ATE 0), where the orientations' rotation turned the drive (0.3 m ATE on 20 m)."""
    from toolkit.eval.trajectory import trajectory_report

    n = 200
    x = np.linspace(0.0, 20.0, n)
    pos = np.stack([x, 0.3 * np.sin(x / 2.0), np.zeros(n)], 1)  # a 0.3 m weave
    yaw = np.arctan2(np.gradient(pos[:, 1]), np.gradient(x))
    gt = np.stack([se3(Rotation.from_euler("z", a).as_matrix(), q)
                   for a, q in zip(yaw, pos, strict=True)])
    est = np.stack([se3(Rotation.from_euler("z", a + np.radians(3)).as_matrix(), q)
                    for a, q in zip(yaw, pos, strict=True)])
    stamps = np.arange(n) * 0.1
    for align in ("se3", "sim3"):
        rep = trajectory_report(Trajectory(stamps, est), Trajectory(stamps, gt), align)
        assert rep["ate_rmse_m"] < 1e-6 and rep["are_rmse_deg"] == pytest.approx(3.0, abs=0.01)


def test_ground_truth_gaps_are_not_scored(tmp_path):
    from toolkit.eval.alignment import covered_ground_truth
    from toolkit.fusion.synthetic import write_box_room
    from toolkit.io.sequence import read_sequence

    seq = read_sequence(write_box_room(tmp_path / "seq", n_frames=30))
    gt = seq.groundtruth.poses_base
    keep = np.ones(len(gt), bool)
    keep[len(gt) // 3: 2 * len(gt) // 3] = False  # motion capture lost for 2 s
    holed = Trajectory(gt.stamps[keep], gt.poses[keep], gt.frame, gt.child)
    seq.groundtruth.poses_base = holed
    est = Trajectory(seq.frame_stamps, np.tile(np.eye(4), (len(seq.frame_stamps), 1, 1)),
                     "world", "camera")
    kept, cam = covered_ground_truth(seq, est)
    assert holed.covers(kept.stamps, slack_s=0.05).all() and len(kept) == len(cam)
    assert len(kept) < len(est)  # the frames in the gap are left out


def _drive(t: np.ndarray) -> np.ndarray:
    """A robot at 1 m/s on a gently weaving path: T_world_base [N, 4, 4]."""
    return np.stack([se2_to_se3(s, 0.5 * np.sin(s), 0.5 * np.cos(s)) for s in t])


def test_poses_past_the_ground_truths_ends_are_not_scored() -> None:
    """Ground truth from 0 to 10 s, frames from -0.04 to 10.04 s, the estimate exact: the
    frames past the ends are left out (they were scored against the end pose held, up to
    4.5 cm off), so a perfect estimate scores 0."""
    from types import SimpleNamespace

    from toolkit.eval.alignment import covered_ground_truth

    gt_t = np.arange(0.0, 10.0 + 1e-9, 0.1)
    cam_t = np.arange(-0.04, 10.04 + 1e-9, 1 / 30)
    seq = SimpleNamespace(groundtruth=SimpleNamespace(
        poses_base=Trajectory(gt_t, _drive(gt_t), "world", "base_link")),
        rig=SimpleNamespace(T_base_camera=np.eye(4)))
    est, gt = covered_ground_truth(seq, Trajectory(cam_t, _drive(cam_t), "world", "camera"))
    assert est.stamps[0] >= 0.0 and est.stamps[-1] <= 10.0 and len(est) == 300
    assert np.abs(est.positions - gt.positions).max() < 1e-3  # interpolation only


def test_slam2d_ate_interpolates_a_ground_truth_on_its_own_clock() -> None:
    """Motion capture at 100 Hz, 4 ms off the scans' clock, the estimate exact: every scan
    is scored, at ~0 (nearest stamps within 1 ms scored a fifth of them, or none)."""
    from toolkit.slam2d.bench import ate_se2

    scan_t = np.arange(0.0, 30.0, 1 / 30)
    gt_t = np.arange(-0.5, 30.5, 0.01) + 0.004
    est = Trajectory(scan_t, _drive(scan_t), "world", "base_link")
    ate = ate_se2(est, Trajectory(gt_t, _drive(gt_t), "world", "base_link"))
    assert ate["ate_poses"] == len(scan_t)
    assert ate["ate_rmse_m"] < 2e-4  # linear interpolation of the weave between samples
    with pytest.raises(ValueError, match="covers 0 of"):
        ate_se2(est, Trajectory(gt_t + 100, _drive(gt_t), "world", "base_link"))


@pytest.mark.parametrize("delta", [0, -1, -3, 1.5, True])
@pytest.mark.parametrize("all_pairs", [False, True])
def test_pairs_by_frames_refuses_a_delta_that_is_no_frame_count(delta, all_pairs) -> None:
    """delta 0 paired each pose with itself (an RPE of 0 for any trajectory) or failed
    inside range(); a negative one paired poses with indices wrapped from the end."""
    with pytest.raises(ValueError, match=f"delta is {delta!r}: .* 1 or more"):
        pairs_by_frames(6, delta, all_pairs)
    assert pairs_by_frames(6, 2) == [(0, 2), (2, 4)]
    assert pairs_by_frames(4, 1, all_pairs=True) == [(0, 1), (1, 2), (2, 3)]


@pytest.mark.parametrize("delta_m", [0.0, -1.0, float("nan"), float("inf")])
def test_pairs_by_path_refuses_a_length_that_is_no_positive_distance(delta_m) -> None:
    """0 or a negative length marked every pose (neighbours paired whatever was asked);
    NaN or inf marked none, without a word."""
    positions = np.cumsum(np.ones((6, 3)), axis=0)  # [6, 3] steps of sqrt(3) m
    with pytest.raises(ValueError, match="delta_m is .*more than 0"):
        pairs_by_path(positions, delta_m)
    assert pairs_by_path(positions, 3.0) == [(2, 4)]

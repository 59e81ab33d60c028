"""The rigid transform from a SLAM map frame to the simulator's world frame.

A SLAM run starts its map where the robot starts; ground truth lives in the world the
recording was made in. Before an estimated map is compared with the ground-truth mesh it
must be moved by one rigid transform, taken from the camera trajectory (SE(3) Umeyama on
the camera centres, by their orientations where the centres lie along a line): no scale, so
a scale error stays visible. With ground-truth poses the transform is the identity.
"""

from __future__ import annotations

import numpy as np

from toolkit.geometry import Trajectory, rigid_alignment, se3
from toolkit.sensors import Sequence


def ground_truth_camera(seq: Sequence, stamps: np.ndarray,
                        extrapolate_s: float = 0.05) -> Trajectory:
    """T_world_camera from the sequence's ground-truth base poses at ``stamps``."""
    gt = seq.groundtruth.poses_base.interpolate(stamps, extrapolate_s=extrapolate_s)
    cam = gt.transform(T_right=seq.rig.T_base_camera)
    cam.child = "camera"  # what the poses now hold (trajectory_report compares children)
    return cam


def covered_ground_truth(seq: Sequence, est: Trajectory, slack_s: float = 0.0) -> (
        tuple[Trajectory, Trajectory]):
    """(``est`` at the stamps the ground truth covers, the ground-truth camera there): not
    past its ends, nor across a gap in it (motion capture lost for seconds), where an
    interpolated pose is a straight line between the gap's ends, not the truth (a perfect
    estimate scored 0.16 m there). No end slack by default: the poses that building a map
    takes up to ``END_SLACK_S`` past the ends are the end pose held, not a measurement (a
    perfect estimate at 1 m/s scored 4.5 cm there)."""
    keep = seq.groundtruth.poses_base.covers(est.stamps, slack_s=slack_s)
    est = est.slice(keep)
    return est, ground_truth_camera(seq, est.stamps, slack_s)


def map_to_world(seq: Sequence, stamps: np.ndarray, T_map_camera: np.ndarray,
                 extrapolate_s: float = 0.0) -> np.ndarray | None:
    """[4, 4] S with ``x_world = S @ x_map``, fitted on the camera centres of ``T_map_camera``
    [N, 4, 4] at ``stamps`` [N] against the sequence's ground truth (where it is measured
    or interpolated, as ``covered_ground_truth``); None without it."""
    gt = seq.groundtruth
    if gt is None or gt.poses_base is None or len(stamps) < 3:
        return None
    stamps = np.asarray(stamps, dtype=np.float64)
    T = np.asarray(T_map_camera, dtype=np.float64)
    inside = gt.poses_base.covers(stamps, slack_s=extrapolate_s)
    if inside.sum() < 3:
        return None
    ref = ground_truth_camera(seq, stamps[inside], extrapolate_s)
    R, t = rigid_alignment(T[inside], ref.poses)
    return se3(R, t)


def apply(S: np.ndarray | None, points: np.ndarray) -> np.ndarray:
    """``points`` [N, 3] moved by S (unchanged when S is None)."""
    if S is None:
        return points
    return np.asarray(points) @ S[:3, :3].T + S[:3, 3]


def built_at_ground_truth(seq: Sequence, poses: Trajectory, tol_m: float = 1e-3) -> bool:
    """Whether ``poses`` (T_world_camera a map was built at) are the sequence's ground-truth
    camera poses (every camera centre the ground truth covers within ``tol_m``): such a map
    is in the world frame already, and moving it by a SLAM map's alignment put a perfect
    map 0.65 m off (F@5cm 0.011)."""
    gt = seq.groundtruth
    if gt is None or gt.poses_base is None or not len(poses):
        return False
    inside = gt.poses_base.covers(poses.stamps, slack_s=0.05)
    if not inside.any():
        return False
    ref = ground_truth_camera(seq, poses.stamps[inside])
    off = np.linalg.norm(poses.positions[inside] - ref.positions, axis=1)
    return bool(off.max() <= tol_m)

"""Trajectory accuracy: association, ATE (APE) and RPE with SE(3)/Sim(3) alignment.

Definitions follow Sturm et al. 2012 (TUM RGB-D) and evo, and are checked against evo's
reference values (tests/test_eval_trajectory.py). The paper's Table I columns (per-axis
position and orientation RMSE) are in ``per_axis_errors``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from toolkit.geometry import Trajectory, align_trajectory, inv_se3, rotation_angle


@dataclass(frozen=True)
class ErrorStats:
    """Summary of per-pose errors (units of the error: m or deg)."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    count: int

    @classmethod
    def of(cls, e: np.ndarray) -> ErrorStats:
        e = np.asarray(e, dtype=np.float64)
        if len(e) == 0:
            raise ValueError("no errors to summarise: the trajectories share no poses")
        return cls(float(np.sqrt(np.mean(e**2))), float(np.mean(e)), float(np.median(e)),
                   float(np.std(e)), float(np.min(e)), float(np.max(e)), int(len(e)))

    def as_dict(self, unit: str) -> dict[str, float]:
        return {f"{k}_{unit}" if k != "count" else k: v for k, v in self.__dict__.items()}


def associate(est: Trajectory, ref: Trajectory, max_diff: float = 0.01, offset: float = 0.0) -> (
    tuple[np.ndarray, np.ndarray]
):
    """Index pairs [K], [K] of stamps closer than ``max_diff`` (one-to-one, nearest first).

    Same rule as TUM's associate.py and evo's ``associate_trajectories``, whatever order
    either trajectory's stamps come in.
    """
    t_est = est.stamps + offset
    # The candidate search below needs sorted reference stamps; a Trajectory built by hand
    # need not have them, and binary search in unsorted stamps silently dropped most pairs
    # (3 of 10 kept for a shuffled copy of the estimate's own stamps). associate.py pairs
    # stamps regardless of order, so the reference is searched sorted and its indices
    # mapped back.
    ref_order = np.argsort(ref.stamps, kind="stable")  # [M]
    t_ref = ref.stamps[ref_order]  # [M] sorted
    # Every pair within max_diff, nearest first; a stamp already paired passes its next
    # candidate on (taking each one's nearest only dropped pairs associate.py keeps).
    lo = np.searchsorted(t_ref, t_est - max_diff, side="left")
    hi = np.searchsorted(t_ref, t_est + max_diff, side="right")
    counts = hi - lo
    i_all = np.repeat(np.arange(len(t_est)), counts)  # [C]
    j_all = (np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
             + np.repeat(lo, counts))
    d_all = np.abs(t_ref[j_all] - t_est[i_all])
    keep = d_all < max_diff
    i_all, j_all, d_all = i_all[keep], ref_order[j_all[keep]], d_all[keep]
    used_est: set[int] = set()
    used_ref: set[int] = set()
    pairs = []
    for k in np.argsort(d_all, kind="stable"):
        i, jr = int(i_all[k]), int(j_all[k])
        if i in used_est or jr in used_ref:
            continue
        used_est.add(i)
        used_ref.add(jr)
        pairs.append((i, jr))
    pairs.sort()
    if not pairs:
        raise ValueError(f"no stamps of the two trajectories lie within {max_diff} s of each other")
    a = np.array(pairs, dtype=np.int64)
    return a[:, 0], a[:, 1]


def synced(est: Trajectory, ref: Trajectory, max_diff: float = 0.01) -> tuple[Trajectory,
                                                                              Trajectory]:
    """The associated sub-trajectories (equal length, paired by index)."""
    i, j = associate(est, ref, max_diff)
    return est.slice(i), ref.slice(j)


def ape(est: Trajectory, ref: Trajectory, align: str = "se3", component: str = "trans") -> (
    tuple[ErrorStats, Trajectory]
):
    """Absolute pose error of associated trajectories of equal length.

    ``align``: "none", "se3" or "sim3" (Umeyama on positions). ``component``: "trans" (m) or
    "rot" (deg). Returns the statistics and the aligned estimate.
    """
    if len(est) != len(ref):
        raise ValueError(f"associate first: {len(est)} estimated vs {len(ref)} reference poses")
    if align == "none":
        aligned = est
    elif align in ("se3", "sim3"):
        aligned, _ = align_trajectory(est, ref, with_scale=align == "sim3")
    else:
        raise ValueError(f"align must be none, se3 or sim3, got {align!r} (a planar "
                         "trajectory in SE(2): toolkit.slam2d.bench.ate_se2)")
    if component == "trans":
        e = np.linalg.norm(aligned.positions - ref.positions, axis=1)
    elif component == "rot":
        E = np.swapaxes(ref.poses[:, :3, :3], 1, 2) @ aligned.poses[:, :3, :3]
        e = np.degrees(rotation_angle(E))
    else:
        raise ValueError(f"component must be trans or rot, got {component!r}")
    return ErrorStats.of(e), aligned


def pairs_by_path(positions: np.ndarray, delta_m: float) -> list[tuple[int, int]]:
    """Consecutive pose pairs ~``delta_m`` of travelled path apart (evo's non-all-pairs rule).

    evo walks the *estimated* trajectory's path; pass ``est.positions`` to reproduce its
    figures. Walk the path; every time the distance accumulated since the last mark reaches delta,
    mark that pose; pair consecutive marks. ``delta_m`` is a positive, finite length.
    """
    # 0 or less marked every pose (pairs of neighbours, whatever the length asked for);
    # NaN marked none (no pairs, no word).
    if not 0 < delta_m < np.inf:
        raise ValueError(f"delta_m is {delta_m!r}: give the path length between the poses "
                         "of a pair, in metres, more than 0")
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    marks = []
    acc = 0.0
    for i, s in enumerate(steps, start=1):
        acc += s
        if acc >= delta_m:
            marks.append(i)
            acc = 0.0
    return list(zip(marks, marks[1:], strict=False))


def pairs_by_frames(n: int, delta: int, all_pairs: bool = False) -> list[tuple[int, int]]:
    """Pose pairs ``delta`` indices apart (consecutive blocks, or every start with all_pairs);
    ``delta`` is a whole number of frames, 1 or more (evo's ``delta`` as well)."""
    # 0 paired each pose with itself (an RPE of 0 whatever the trajectory) or failed in
    # range(); a negative delta wrapped around the end as negative indices.
    if isinstance(delta, bool) or not isinstance(delta, (int, np.integer)) or delta < 1:
        raise ValueError(f"delta is {delta!r}: give the frames between the poses of a pair, "
                         "a whole number of 1 or more")
    if all_pairs:
        return [(i, i + delta) for i in range(n - delta)]
    ids = list(range(0, n, delta))
    return list(zip(ids, ids[1:], strict=False))


def rpe(est: Trajectory, ref: Trajectory, pairs: list[tuple[int, int]],
        component: str = "trans") -> ErrorStats:
    """Relative pose error over index ``pairs`` of associated trajectories.

    E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j); its translation norm (m) or rotation angle (deg).
    """
    if not pairs:
        raise ValueError("no pose pairs for RPE: the delta is longer than the trajectory")
    i = np.array([p[0] for p in pairs])
    j = np.array([p[1] for p in pairs])
    rel_ref = inv_se3(ref.poses[i]) @ ref.poses[j]
    rel_est = inv_se3(est.poses[i]) @ est.poses[j]
    E = inv_se3(rel_ref) @ rel_est
    if component == "trans":
        return ErrorStats.of(np.linalg.norm(E[:, :3, 3], axis=1))
    if component == "rot":
        return ErrorStats.of(np.degrees(rotation_angle(E[:, :3, :3])))
    raise ValueError(f"component must be trans or rot, got {component!r}")


def per_axis_errors(est_aligned: Trajectory, ref: Trajectory) -> dict[str, float]:
    """The paper's Table I: RMSE of x, y, z (m), roll, pitch, yaw (deg), position, orientation.

    Orientation errors are the world-frame error rotation R_est R_ref^T as roll/pitch/yaw
    about the world's x, y, z (z up: yaw is heading). Taken in the sensor's own frame
    instead, an optical camera's heading error would read as "pitch".
    """
    d = est_aligned.positions - ref.positions
    E = est_aligned.poses[:, :3, :3] @ np.swapaxes(ref.poses[:, :3, :3], 1, 2)
    rpy = np.degrees(Rotation.from_matrix(E).as_euler("xyz"))

    def rmse(a: np.ndarray) -> float:
        return float(np.sqrt(np.mean(a**2)))

    return {
        "x_rmse_m": rmse(d[:, 0]), "y_rmse_m": rmse(d[:, 1]), "z_rmse_m": rmse(d[:, 2]),
        "roll_rmse_deg": rmse(rpy[:, 0]), "pitch_rmse_deg": rmse(rpy[:, 1]),
        "yaw_rmse_deg": rmse(rpy[:, 2]),
        "position_rmse_m": rmse(np.linalg.norm(d, axis=1)),
        "orientation_rmse_deg": rmse(np.degrees(rotation_angle(E))),
    }


def trajectory_report(est: Trajectory, ref: Trajectory, align: str = "se3",
                      max_diff: float = 0.01) -> dict[str, float | str]:
    """ATE, rotation APE and Table-I columns after association and alignment, as a flat dict
    (figures in float, ``alignment`` the method). Both must hold the same body's poses
    (``child``): a camera trajectory against the base's ground truth is refused."""
    if est.child != ref.child:
        raise ValueError(
            f"the estimate holds {est.child} poses, the reference {ref.child} poses: compare "
            f"the same body (move one with the rig, e.g. T_world_camera = T_world_base @ "
            f"rig.T_base_camera)")
    e, r = synced(est, ref, max_diff)
    stats, aligned = ape(e, r, align, "trans")
    rot, _ = ape(e, r, align, "rot")
    out = {f"ate_{k}": v for k, v in stats.as_dict("m").items()}
    out.update({f"are_{k}": v for k, v in rot.as_dict("deg").items() if k != "count"})
    out.update(per_axis_errors(aligned, r))
    out["alignment"] = align  # type: ignore[assignment]
    return out

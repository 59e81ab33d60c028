"""The Freiburg relations metric (Kuemmerle et al. 2009, "On measuring the accuracy of
SLAM algorithms", Autonomous Robots 27(4)).

A relation (t1, t2, delta*) is the reference relative pose between the robot at t1 and
at t2, expressed in the frame at t1. The error of an estimate is
``delta_est (-) delta*`` with ``delta_est = pose(t1)^-1 * pose(t2)``; its translational
part is ``|| t_est - t* ||`` (the rotation of the difference does not change the norm)
and its rotational part ``|wrap(theta_est - theta*)|``. The benchmark reports the mean
and standard deviation of the absolute and of the squared errors over all relations.

Cartographer's ``compute_relations_metrics`` (the tool behind Hess et al. 2016, Table II)
composes the other way, ``delta_est * delta*^-1``, whose translation is
``t_est - R(theta_est - theta*) t*``: it adds about the relation's length times its
rotation error (on Killian's 658 relations 0.0354 m where the paper's composition gives
0.0342 m). ``relations_metric`` gives that figure too (``*_cartographer`` keys), so a
comparison with a published Cartographer figure is made like for like.

Relation files have lines ``t1 t2 x y z roll pitch yaw``; only x, y and yaw matter in 2D.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from toolkit.errors import InputError, MissingInputError
from toolkit.geometry import Trajectory, se2_between, se3_to_se2, wrap_angle


@dataclass
class Relations:
    t1: np.ndarray  # [R]
    t2: np.ndarray  # [R]
    delta: np.ndarray  # [R, 3] (x, y, yaw) of the robot at t2 in the frame at t1

    def __len__(self) -> int:
        return len(self.t1)


def read_relations(path: Path | str) -> Relations:
    """Read a Freiburg ``.relations`` file; errors name the file and line."""
    path = Path(path)
    if not path.exists():
        raise MissingInputError(f"{path}: relations file not found")
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split()
        if len(parts) < 8:
            raise InputError(f"{path}:{lineno}: expected 't1 t2 x y z roll pitch yaw', "
                             f"got {len(parts)} fields")
        try:
            rows.append([float(v) for v in parts[:8]])
        except ValueError:
            raise InputError(f"{path}:{lineno}: non-numeric field") from None
    a = np.array(rows, dtype=np.float64).reshape(-1, 8)
    return Relations(a[:, 0], a[:, 1], a[:, [2, 3, 7]])


def _lookup(stamps: np.ndarray, query: np.ndarray, tol: float) -> np.ndarray:
    """[Q] index of the stamp within ``tol`` of each query, -1 where none."""
    order = np.argsort(stamps)
    s = stamps[order]
    i = np.clip(np.searchsorted(s, query), 1, max(len(s) - 1, 1))
    left, right = s[i - 1], s[np.minimum(i, len(s) - 1)]
    pick = np.where(np.abs(query - left) <= np.abs(right - query), i - 1, i)
    pick = np.minimum(pick, len(s) - 1)
    ok = np.abs(s[pick] - query) <= tol
    return np.where(ok, order[pick], -1)


def select_relations(relations: Relations, stamps: np.ndarray, tol: float = 1e-3) -> np.ndarray:
    """[R] bool: relations whose two stamps are both in ``stamps`` (within ``tol`` s)."""
    stamps = np.asarray(stamps, dtype=np.float64)
    if len(stamps) == 0:
        return np.zeros(len(relations), bool)
    return (_lookup(stamps, relations.t1, tol) >= 0) & (_lookup(stamps, relations.t2, tol) >= 0)


def relation_errors(
    estimate: Trajectory | tuple[np.ndarray, np.ndarray],
    relations: Relations,
    tol: float = 1e-3,
    composition: Literal["kuemmerle", "cartographer"] = "kuemmerle",
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(translational [R] m, rotational [R] rad, used [R] bool) errors of each relation.

    ``estimate``: a trajectory, or (stamps [S], poses [S, 3] as x, y, theta). Relations
    whose stamps are not estimate stamps (within ``tol`` s) are not used (NaN errors).
    ``composition``: ``kuemmerle`` (the paper's ``delta*^-1 * delta_est``, translational
    error ``|t_est - t*|``) or ``cartographer`` (``delta_est * delta*^-1``, as
    Cartographer's compute_relations_metrics; the rotational error is the same).
    """
    if composition not in ("kuemmerle", "cartographer"):
        raise ValueError(f"composition must be 'kuemmerle' or 'cartographer', got {composition!r}")
    if isinstance(estimate, Trajectory):
        stamps, poses = estimate.stamps, se3_to_se2(estimate.poses)
    else:
        stamps, poses = (np.asarray(v, dtype=np.float64) for v in estimate)
    i1 = _lookup(stamps, relations.t1, tol) if len(stamps) else np.full(len(relations), -1)
    i2 = _lookup(stamps, relations.t2, tol) if len(stamps) else np.full(len(relations), -1)
    used = (i1 >= 0) & (i2 >= 0)
    et = np.full(len(relations), np.nan)
    er = np.full(len(relations), np.nan)
    if used.any():
        est = se2_between(poses[i1[used]], poses[i2[used]])  # [U, 3]
        ref = relations.delta[used]
        dth = wrap_angle(est[:, 2] - ref[:, 2])
        if composition == "kuemmerle":
            et[used] = np.hypot(est[:, 0] - ref[:, 0], est[:, 1] - ref[:, 1])
        else:  # translation of delta_est * delta*^-1: t_est - R(dth) t*
            c, s = np.cos(dth), np.sin(dth)
            et[used] = np.hypot(est[:, 0] - (c * ref[:, 0] - s * ref[:, 1]),
                                est[:, 1] - (s * ref[:, 0] + c * ref[:, 1]))
        er[used] = np.abs(dth)
    return et, er, used


def relations_metric(
    estimate: Trajectory | tuple[np.ndarray, np.ndarray],
    relations: Relations,
    tol: float = 1e-3,
) -> dict[str, float | int]:
    """Mean and std of absolute and squared errors (units in the keys; rotations in deg).
    The ``*_cartographer`` keys: the translational error composed as Cartographer's tool
    composes it (module docstring), for comparisons with its published figures."""
    et, er, used = relation_errors(estimate, relations, tol)
    t = et[used]
    r = np.degrees(er[used])
    out: dict[str, float | int] = {"relations_used": int(used.sum()),
                                   "relations_total": len(relations)}
    if len(t) == 0:
        return out
    out.update({
        "trans_abs_mean_m": float(t.mean()),
        "trans_abs_std_m": float(t.std()),
        "trans_abs_max_m": float(t.max()),
        "trans_sq_mean_m2": float((t**2).mean()),
        "trans_sq_std_m2": float((t**2).std()),
        "rot_abs_mean_deg": float(r.mean()),
        "rot_abs_std_deg": float(r.std()),
        "rot_abs_max_deg": float(r.max()),
        "rot_sq_mean_deg2": float((r**2).mean()),
        "rot_sq_std_deg2": float((r**2).std()),
    })
    tc = relation_errors(estimate, relations, tol, composition="cartographer")[0][used]
    out.update({"trans_abs_mean_m_cartographer": float(tc.mean()),
                "trans_abs_std_m_cartographer": float(tc.std())})
    return out

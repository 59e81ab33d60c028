"""Rigid and similarity transforms, pose interpolation and trajectory alignment.

Conventions (README, "Conventions"): ``T_a_b`` maps points from frame b into frame a,
stored as 4x4 float64 (3x3 for SE(2)); quaternions are scipy's xyzw, as in TUM files.
Rotation maths goes through ``scipy.spatial.transform`` rather than hand-written code.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

# ---------------------------------------------------------------------------- SE(3)


def se3(R: np.ndarray | None = None, t: np.ndarray | None = None) -> np.ndarray:
    """Build a 4x4 transform from a rotation matrix [3, 3] and a translation [3]."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if t is not None:
        T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def checked_rigid(T: np.ndarray) -> np.ndarray:
    """The [4, 4] rigid transform ``T`` as given, its rotation made exactly orthonormal
    when it is off by rounding (up to 1e-3 in R R^T: a 30 deg yaw written 0.8660 / 0.5000
    is 4e-5 off); otherwise a ValueError whose message continues the caller's name of
    the matrix ("T_base_laser " + message: "is a reflection ...")."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"must be a finite 4x4 matrix (list of 4 rows), got shape "
                         f"{list(T.shape)}")
    if not np.allclose(T[3], [0, 0, 0, 1]):
        raise ValueError(f"has the last row {T[3].tolist()}, not [0, 0, 0, 1] (transposed? "
                         "give the matrix as a list of rows)")
    R = T[:3, :3]
    off = float(np.abs(R @ R.T - np.eye(3)).max())
    if off > 1e-3:
        # Not rounding (up to 1e-3 passes): a scaled, sheared or hand-typed matrix.
        raise ValueError(f"is not a rigid transform: R R^T is {off:.2g} off the identity "
                         "(the rotation is not orthonormal); export it again, with all its "
                         "digits, from the tool that made it, or estimate it: python -m "
                         "calibration extrinsic ... --out rig.yaml writes a rig from "
                         "checkerboard views (docs/calibration.md)")
    if np.linalg.det(R) < 0:
        raise ValueError("is a reflection (det -1), not a rotation: frames are right-handed "
                         "(REP 103); check the optical-frame axes (x right, y down, z "
                         "forward)")
    if off > 1e-12:
        U, _, Vt = np.linalg.svd(R)
        T = T.copy()
        T[:3, :3] = U @ Vt  # the nearest rotation
    return T


def inv_se3(T: np.ndarray) -> np.ndarray:
    """Inverse of one [4, 4] or a batch [N, 4, 4] of rigid transforms (exact, no LU)."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def compose(*Ts: np.ndarray) -> np.ndarray:
    """Chain transforms left to right: ``compose(T_a_b, T_b_c) == T_a_c`` (batches broadcast)."""
    out = np.asarray(Ts[0], dtype=np.float64)
    for T in Ts[1:]:
        out = out @ np.asarray(T, dtype=np.float64)
    return out


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply [4, 4] ``T`` to points [N, 3] (or [N, 2] with a [3, 3] SE(2) ``T``)."""
    points = np.asarray(points, dtype=np.float64)
    T = np.asarray(T, dtype=np.float64)
    d = points.shape[-1]
    if T.shape != (d + 1, d + 1):
        raise ValueError(f"a {T.shape[0]}x{T.shape[1]} transform for points of {d} "
                         f"coordinates: give [N, 3] points with a 4x4 transform or [N, 2] "
                         f"with a 3x3 one")
    return points @ T[:d, :d].T + T[:d, d]


def pose_from_xyz_quat(xyz: np.ndarray, quat_xyzw: np.ndarray) -> np.ndarray:
    """[4, 4] (or [N, 4, 4]) from positions [.., 3] and xyzw quaternions [.., 4]."""
    xyz = np.asarray(xyz, dtype=np.float64)
    quat = np.asarray(quat_xyzw, dtype=np.float64)
    batch = xyz.ndim == 2
    xyz2, quat2 = np.atleast_2d(xyz), np.atleast_2d(quat)
    T = np.tile(np.eye(4), (len(xyz2), 1, 1))
    T[:, :3, :3] = Rotation.from_quat(quat2).as_matrix()
    T[:, :3, 3] = xyz2
    return T if batch else T[0]


# Quaternion components within this of 0 are rounding: a half-turn's w comes out of scipy
# as +-6e-17 or 2e-16 by how its matrix was computed, and its sign would pick q or -q.
_QUAT_ZERO = 8 * float(np.finfo(np.float64).eps)


def canonical_quat(q_xyzw: np.ndarray) -> np.ndarray:
    """[.., 4] the xyzw unit quaternions [.., 4] with one sign per rotation, so that written
    files are reproducible: w > 0, or when w is 0 the first non-zero of x, y, z positive.
    Components within 8 eps (1.8e-15) of 0 count as 0 and are written as 0 (moving the
    rotation by at most 3.6e-15 rad)."""
    q = np.array(q_xyzw, dtype=np.float64)  # [.., 4] a copy
    q[np.abs(q) <= _QUAT_ZERO] = 0.0
    wxyz = q[..., [3, 0, 1, 2]]  # [.., 4]
    first = np.take_along_axis(wxyz, np.argmax(wxyz != 0, axis=-1)[..., None], -1)  # [.., 1]
    return np.where(first < 0, -q, q) + 0.0  # + 0.0 turns -0.0 into 0.0 for the text


def pose_to_xyz_quat(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions [.., 3] and xyzw quaternions [.., 4] of transforms [.., 4, 4], signs as
    ``canonical_quat``."""
    T = np.asarray(T, dtype=np.float64)
    batch = T.ndim == 3
    T2 = T if batch else T[None]
    q = canonical_quat(Rotation.from_matrix(T2[:, :3, :3]).as_quat())
    xyz = T2[:, :3, 3].copy()
    return (xyz, q) if batch else (xyz[0], q[0])


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Angle in radians of rotation matrices [.., 3, 3], robust near 0 and pi."""
    R = np.asarray(R, dtype=np.float64)
    return np.linalg.norm(Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec(), axis=-1).reshape(
        R.shape[:-2]
    )


# ---------------------------------------------------------------------------- SE(2)


def wrap_angle(a: np.ndarray | float) -> np.ndarray | float:
    """Wrap angles to [-pi, pi)."""
    w = (np.asarray(a, dtype=np.float64) + np.pi) % (2.0 * np.pi) - np.pi
    # Just below -pi (within 2e-15) the sum rounds to a tiny negative number, whose modulo
    # rounds up to 2 pi: the result was +pi, outside the half-open range.
    w = np.where(w >= np.pi, -np.pi, w)
    return w if np.ndim(a) else float(w)


def se2_to_matrix(x: float, y: float, theta: float) -> np.ndarray:
    """[3, 3] homogeneous SE(2) matrix."""
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def matrix_to_se2(T: np.ndarray) -> tuple[float, float, float]:
    """(x, y, theta) of a [3, 3] SE(2) matrix or the planar part of a [4, 4] SE(3) one."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape == (4, 4):
        return float(T[0, 3]), float(T[1, 3]), float(np.arctan2(T[1, 0], T[0, 0]))
    return float(T[0, 2]), float(T[1, 2]), float(np.arctan2(T[1, 0], T[0, 0]))


def se2_to_se3(x: float, y: float, theta: float, z: float = 0.0) -> np.ndarray:
    """[4, 4] transform of a planar pose (rotation about +z)."""
    T = np.eye(4)
    c, s = np.cos(theta), np.sin(theta)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = [x, y, z]
    return T


def se3_to_se2(T: np.ndarray) -> np.ndarray:
    """[.., 3] (x, y, yaw) of transforms [.., 4, 4]: the planar projection."""
    T = np.asarray(T, dtype=np.float64)
    return np.stack([T[..., 0, 3], T[..., 1, 3], np.arctan2(T[..., 1, 0], T[..., 0, 0])], -1)


def se2_compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Compose (x, y, theta) poses [.., 3]: a * b."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack(
        [
            a[..., 0] + c * b[..., 0] - s * b[..., 1],
            a[..., 1] + s * b[..., 0] + c * b[..., 1],
            wrap_angle(a[..., 2] + b[..., 2]),
        ],
        -1,
    )


def se2_inverse(a: np.ndarray) -> np.ndarray:
    """Inverse of (x, y, theta) poses [.., 3]."""
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack(
        [-c * a[..., 0] - s * a[..., 1], s * a[..., 0] - c * a[..., 1], wrap_angle(-a[..., 2])], -1
    )


def se2_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Relative pose a^-1 * b of (x, y, theta) poses [.., 3]."""
    return se2_compose(se2_inverse(a), b)


# ---------------------------------------------------------------------------- interpolation


def interpolate_poses(
    stamps: np.ndarray, poses: np.ndarray, query: np.ndarray, extrapolate_s: float = 0.0
) -> np.ndarray:
    """Poses [M, 4, 4] at ``query`` stamps: slerp on rotation, lerp on translation.

    ``stamps`` [N] must be strictly increasing. Queries up to ``extrapolate_s`` outside
    the covered span are clamped to the end poses; further ones raise ``ValueError``
    (a camera frame before the first scan has no trustworthy pose).
    """
    stamps = np.asarray(stamps, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64)
    query = np.atleast_1d(np.asarray(query, dtype=np.float64))
    if len(stamps) == 0:
        raise ValueError("cannot interpolate an empty trajectory")
    if np.any(np.diff(stamps) <= 0):
        raise ValueError("trajectory stamps must be strictly increasing")
    lo, hi = stamps[0] - extrapolate_s, stamps[-1] + extrapolate_s
    bad = (query < lo - 1e-9) | (query > hi + 1e-9)
    if np.any(bad):
        raise ValueError(
            f"{int(bad.sum())} query stamps lie outside the trajectory span "
            f"[{stamps[0]:.6f}, {stamps[-1]:.6f}] s (+-{extrapolate_s} s allowed), "
            f"first offender {query[bad][0]:.6f}"
        )
    if len(stamps) == 1:
        return np.repeat(poses[:1], len(query), axis=0)
    q = np.clip(query, stamps[0], stamps[-1])
    slerp = Slerp(stamps, Rotation.from_matrix(poses[:, :3, :3]))
    out = np.tile(np.eye(4), (len(q), 1, 1))
    out[:, :3, :3] = slerp(q).as_matrix()
    for k in range(3):
        out[:, k, 3] = np.interp(q, stamps, poses[:, k, 3])
    return out


@dataclass
class Trajectory:
    """Time-stamped poses: ``poses[i]`` is ``T_<frame>_<child>`` at ``stamps[i]``.

    ``frame``/``child`` name what the poses map between (e.g. world / base_link), so a
    file written from it says which transform it holds.
    """

    stamps: np.ndarray  # [N] seconds, strictly increasing
    poses: np.ndarray  # [N, 4, 4]
    frame: str = "world"
    child: str = "base_link"
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.stamps = np.asarray(self.stamps, dtype=np.float64).reshape(-1)
        poses = np.asarray(self.poses, dtype=np.float64)
        if poses.shape[-2:] != (4, 4):
            raise ValueError(f"poses must be [N, 4, 4] homogeneous transforms, got "
                             f"{list(poses.shape)}" + (": SE(2) poses? se2_to_se3 makes them"
                                                       if poses.shape[-2:] == (3, 3) or
                                                       poses.shape[-1:] == (3,) else ""))
        self.poses = poses.reshape(-1, 4, 4)
        if len(self.stamps) != len(self.poses):
            raise ValueError(f"{len(self.stamps)} stamps but {len(self.poses)} poses")

    def __len__(self) -> int:
        return len(self.stamps)

    @property
    def positions(self) -> np.ndarray:
        """[N, 3] translations."""
        return self.poses[:, :3, 3]

    def interpolate(self, query: np.ndarray, extrapolate_s: float = 0.0) -> Trajectory:
        """The trajectory at other stamps (see ``interpolate_poses``)."""
        query = np.atleast_1d(np.asarray(query, dtype=np.float64))
        return Trajectory(
            query,
            interpolate_poses(self.stamps, self.poses, query, extrapolate_s),
            self.frame,
            self.child,
        )

    def interpolate_with_odometry(self, odometry: Trajectory | None, query: np.ndarray,
                                  extrapolate_s: float = 0.0) -> Trajectory:
        """The trajectory at ``query`` stamps, its motion between samples taken from
        ``odometry`` (``T_odom_<child>``, e.g. wheel odometry): each of the two samples
        around a query predicts its pose by the odometry's motion since (or until) it,
        ``pose_k @ inv(odom(t_k)) @ odom(t)``, and the two predictions are blended by time
        (slerp, lerp), so the result is exact at the samples and does not depend on where
        the odometry's origin lies (blending the map -> odom corrections themselves moved
        poses 14 cm with an odometry origin 5 km away). A straight line between two 10 Hz
        scan poses was up to 1.2 deg (11 px) off where a turn starts or stops; the
        odometry's own motion over the 40 ms to a camera stamp 0.3 deg. Queries the
        odometry does not cover, or whose neighbouring samples it does not, are
        interpolated plainly (as ``interpolate``), as is everything without odometry (None,
        another child, fewer than two poses); odometry that does not move gives the plain
        interpolation. Queries past the ends (``extrapolate_s``) take the end sample's
        prediction."""
        q = np.atleast_1d(np.asarray(query, dtype=np.float64))
        out = self.interpolate(q, extrapolate_s)
        if (odometry is None or len(odometry) < 2 or odometry.child != self.child
                or len(self) < 2 or len(q) == 0):
            return out
        st = self.stamps
        at_sample = odometry.covers(st)  # [N] samples whose odometry pose is known
        hi = np.clip(np.searchsorted(st, q), 1, len(st) - 1)
        use = odometry.covers(q) & at_sample[hi - 1] & at_sample[hi]  # [Q]
        if not use.any():
            return out
        hi = hi[use]
        lo = hi - 1
        O_q = odometry.interpolate(q[use]).poses  # [U, 4, 4]
        need = np.unique(np.r_[lo, hi])
        O_s = np.empty((len(st), 4, 4))
        O_s[need] = odometry.interpolate(st[need]).poses
        A = self.poses[lo] @ inv_se3(O_s[lo]) @ O_q  # [U, 4, 4] from the sample before
        B = self.poses[hi] @ inv_se3(O_s[hi]) @ O_q  # [U, 4, 4] from the sample after
        w = np.clip((q[use] - st[lo]) / (st[hi] - st[lo]), 0.0, 1.0)  # [U]
        Ra = Rotation.from_matrix(A[:, :3, :3])
        step = (Ra.inv() * Rotation.from_matrix(B[:, :3, :3])).as_rotvec()  # [U, 3]
        blend = np.tile(np.eye(4), (len(w), 1, 1))
        blend[:, :3, :3] = (Ra * Rotation.from_rotvec(step * w[:, None])).as_matrix()
        blend[:, :3, 3] = (1 - w)[:, None] * A[:, :3, 3] + w[:, None] * B[:, :3, 3]
        out.poses[use] = blend
        return out

    # A frame or scan stamped this close outside a trajectory's ends takes the end pose
    # (``covers(..., slack_s=END_SLACK_S)``): half a 10 Hz scan period, within which the
    # clocks of two drivers commonly disagree. slam2d's camera poses, fuse and evaluate use
    # the same rule, so they pose the same frames.
    END_SLACK_S: ClassVar[float] = 0.05

    def gap_limit_s(self) -> float:
        """The longest gap between samples that ``covers`` bridges by default: 5 times the
        median spacing, at least 1 s."""
        if len(self.stamps) < 2:
            return 1.0
        return max(1.0, 5.0 * float(np.median(np.diff(self.stamps))))

    def covers(self, query: np.ndarray, max_gap_s: float | None = None,
               slack_s: float = 0.0) -> np.ndarray:
        """[Q] bool: stamps an interpolated pose can be trusted at - within the span (give
        or take ``slack_s``) and between two samples at most ``max_gap_s`` apart (default:
        5 times the median spacing, at least 1 s). Across a longer gap (a blocked lidar,
        dropped scans) a straight line between its ends is a guess, metres off. A stamp in
        the slack outside the span takes the end pose, whatever gap follows it."""
        q = np.atleast_1d(np.asarray(query, dtype=np.float64))
        st = self.stamps
        if len(st) == 0:
            return np.zeros(len(q), bool)
        ok = (q >= st[0] - slack_s) & (q <= st[-1] + slack_s)
        if len(st) < 2:
            return ok
        if max_gap_s is None:
            max_gap_s = self.gap_limit_s()
        j = np.clip(np.searchsorted(st, q), 1, len(st) - 1)
        on_sample = (st[j] == q) | (st[j - 1] == q)
        # Outside the span (within slack_s) j is the first or last gap, which interpolation
        # there does not cross.
        outside = (q < st[0]) | (q > st[-1])
        return ok & (on_sample | outside | (st[j] - st[j - 1] <= max_gap_s))

    def transform(self, T_left: np.ndarray | None = None, T_right: np.ndarray | None = None) -> (
        Trajectory
    ):
        """``T_left @ pose @ T_right`` for every pose (re-rooting or changing the child)."""
        P = self.poses
        if T_left is not None:
            P = np.asarray(T_left) @ P
        if T_right is not None:
            P = P @ np.asarray(T_right)
        return Trajectory(self.stamps.copy(), P, self.frame, self.child)

    def slice(self, index: np.ndarray | slice) -> Trajectory:
        """Subset by index array, boolean mask or slice."""
        return Trajectory(self.stamps[index], self.poses[index], self.frame, self.child)


# ---------------------------------------------------------------------------- TUM lines


def pose_to_tum_line(stamp: float, T: np.ndarray) -> str:
    """``t tx ty tz qx qy qz qw`` with enough digits for an exact float64 round trip."""
    xyz, q = pose_to_xyz_quat(T)
    vals = [stamp, *xyz, *q]
    return " ".join(repr(float(v)) for v in vals)


def tum_line_to_pose(line: str) -> tuple[float, np.ndarray]:
    """Parse one TUM line into (stamp, [4, 4])."""
    parts = line.split()
    if len(parts) != 8:
        raise ValueError(f"TUM line needs 8 numbers (t tx ty tz qx qy qz qw), got {len(parts)}")
    v = np.array([float(p) for p in parts])
    if not np.all(np.isfinite(v)):
        raise ValueError("TUM line holds a non-finite value")
    q = v[4:8]
    n = np.linalg.norm(q)
    if not 0.5 < n < 2.0:
        raise ValueError(f"TUM quaternion norm {n:.3g} is far from 1")
    return float(v[0]), pose_from_xyz_quat(v[1:4], q / n)


# ---------------------------------------------------------------------------- alignment


def umeyama_alignment(
    src: np.ndarray, dst: np.ndarray, with_scale: bool = False
) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares (R, t, s) with ``dst ~= s * R @ src + t`` (Umeyama 1991).

    ``src``, ``dst``: [N, d] corresponding points (d = 2 or 3). With ``with_scale`` False
    this is the SE(d) alignment and ``s`` is 1.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2:
        raise ValueError(f"point sets must have the same [N, d] shape, got {src.shape} {dst.shape}")
    n, d = src.shape
    if n < d:
        raise ValueError(f"need at least {d} point pairs to align, got {n}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    sigma_s = (xs**2).sum() / n
    cov = xd.T @ xs / n  # [d, d]
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(d)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[-1, -1] = -1.0
    R = U @ S @ Vt
    # Checked before the division: 0 / 0 warned "invalid value encountered" first (an
    # error of its own where warnings are errors, as under pytest -W error).
    if with_scale and sigma_s <= 0:
        raise ValueError("degenerate source points: all identical")
    s = float(np.trace(np.diag(D) @ S) / sigma_s) if with_scale else 1.0
    t = mu_d - s * R @ mu_s
    return R, t, s


def sim3(R: np.ndarray, t: np.ndarray, s: float = 1.0) -> np.ndarray:
    """[4, 4] similarity ``x -> s R x + t``."""
    T = np.eye(4)
    T[:3, :3] = s * np.asarray(R)
    T[:3, 3] = t
    return T


def rigid_alignment(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) with ``dst ~= R @ src + t`` for corresponding poses ``src``, ``dst`` [N, 4, 4]
    (``pose_alignment`` without scale)."""
    R, t, _ = pose_alignment(src, dst)
    return R, t


def pose_alignment(src: np.ndarray, dst: np.ndarray, with_scale: bool = False) -> (
    tuple[np.ndarray, np.ndarray, float]
):
    """(R, t, s) with ``dst ~= s R @ src + t`` for corresponding poses [N, 4, 4]: Umeyama
    on the positions, the metric trajectory errors are about.

    Positions along a line (a straight drive: a sideways spread under 5 cm RMS, or under
    5 % of the length and 3 times the fit's residual) leave the turn about the line free:
    1 mm of noise picked it 180 deg wrong with a 2 mm residual. The orientations then set that one
    angle; the rest stays the positions' (taking the whole rotation from the orientations
    turned exact positions by a 3 deg heading bias: 0.3 m ATE on a 20 m drive). Positions
    all in one place (a robot turning on the spot) give no direction at all: the rotation
    nearest the mean of ``R_dst R_src^T`` and the mean offset (without scale only)."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    p, q = src[:, :3, 3], dst[:, :3, 3]
    n = len(p)
    sv = np.linalg.svd(p - p.mean(0), compute_uv=False) if n > 1 else np.zeros(3)
    M = np.einsum("nij,nkj->ik", dst[:, :3, :3], src[:, :3, :3])  # sum R_dst R_src^T
    floor = 0.05 * np.sqrt(n)  # an RMS spread of 5 cm
    if (n < 3 or sv[0] < floor) and not with_scale:
        U, _, Vt = np.linalg.svd(M)
        R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
        return R, (q - p @ R.T).mean(0), 1.0
    R, t, s = umeyama_alignment(p, q, with_scale)
    # The floor is in the reference's units: a monocular estimate's own units are
    # arbitrary, and Sim(3) alignment must not depend on them (at 1/10 of its scale a 3-D
    # TUM trajectory was taken for a line: ATE 10.6 mm against 9.8 mm). A path is a line
    # only where its sideways spread is also within a few times the fit's residual: a
    # 50 m drive weaving 2 m (4 % of its length) fixes the turn from its positions, and
    # taking it from orientations 2 deg off put 2.4 cm of ATE on an exact estimate.
    resid = np.sqrt(np.mean(np.sum((q - s * p @ R.T - t) ** 2, axis=1)))
    if s * sv[1] >= max(min(0.05 * s * sv[0], 3.0 * resid * np.sqrt(n)), floor):
        return R, t, s
    # Along a line: R = Rot(d, theta) R_u, d the line's direction after R_u, with theta
    # maximising tr(R^T M) = const + a sin(theta) + c cos(theta) (Rodrigues' formula).
    # d is the reference's side of the positions' covariance, which R_u turns the
    # estimate's side onto whatever it does about it; the estimate's own principal axis
    # after R_u depended on that free part, and so did the result on the frame the
    # estimate came in (aligned positions 11 mm apart on a 20 m drive with 0.2 m noise).
    U, _, _ = np.linalg.svd((q - q.mean(0)).T @ (p - p.mean(0)))
    d = U[:, 0]
    K = np.array([[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]])
    B = M @ R.T
    theta = np.arctan2(-np.trace(K @ B), -np.trace(K @ K @ B))
    R = (np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K) @ R
    pc, qc = p - p.mean(0), q - q.mean(0)
    if with_scale:
        s = float(np.sum(qc * (pc @ R.T)) / np.sum(pc * pc))
    return R, q.mean(0) - s * (p.mean(0) @ R.T), s


def align_trajectory(
    est: Trajectory, ref: Trajectory, with_scale: bool = False
) -> tuple[Trajectory, np.ndarray]:
    """Align ``est`` onto ``ref`` (same length, associated) by SE(3) or Sim(3) Umeyama
    (positions along a line: the turn about it from the orientations, ``pose_alignment``).

    Returns the aligned trajectory (rotations stay orthonormal; positions scaled) and the
    [4, 4] similarity that was applied.
    """
    R, t, s = pose_alignment(est.poses, ref.poses, with_scale)
    S = sim3(R, t, s)
    P = est.poses.copy()
    P[:, :3, :3] = R @ P[:, :3, :3]
    P[:, :3, 3] = s * est.positions @ R.T + t
    return Trajectory(est.stamps.copy(), P, ref.frame, est.child), S

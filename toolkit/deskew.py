"""Scans measured while the robot moved, re-expressed as if taken at their stamp.

A spinning 2D lidar measures its beams one after another (ROS ``time_increment``): a
robot turning at 1 rad/s under a 10 Hz scanner has turned 0.1 rad between a sweep's first
beam and its last, which moves the last beam's point 0.5 m at 5 m and bends straight
walls into spirals. De-skewing moves every beam's point into the laser frame at the
first beam (the stamp, ROS's convention) with the motion over the sweep and resamples the
points onto the scan's own angle grid, so that everything downstream reads an ordinary
scan. The motion is the trajectory's own where it has poses inside the sweep (odometry
faster than the lidar, the simulator's path samples): each beam's pose is interpolated
between the poses around its time. Between the sweep's ends alone it is taken at constant
velocity, as ``laser_geometry`` and Cartographer place beams. The resampling interpolates
the range between neighbouring points of one surface (exact on planes to well under a
millimetre at 1 degree beams) and takes the nearest point across depth jumps.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from toolkit.geometry import Trajectory, interpolate_poses, inv_se3
from toolkit.sensors import LaserScan, Sequence

# Neighbouring points further apart than this (metres + share of the range) are on
# different surfaces: no range is interpolated between them.
JUMP_M = 0.05
JUMP_REL = 0.10


def planar_motion(T_start: np.ndarray, T_end: np.ndarray) -> np.ndarray:
    """[..., 3] (x, y, theta) of the frame ``T_end`` [..., 4, 4] in the frame ``T_start``
    (both world-from-frame; the laser plane is their x-y plane)."""
    rel = inv_se3(T_start) @ T_end
    return np.stack([rel[..., 0, 3], rel[..., 1, 3],
                     np.arctan2(rel[..., 1, 0], rel[..., 0, 0])], -1)


def deskew_scan(scan: LaserScan, motion: np.ndarray) -> LaserScan:
    """``scan`` with every beam's point moved into the laser frame at the stamp.

    ``motion`` [3]: (x, y, theta) of the laser at the last beam in the laser frame at the
    first; beam i has moved ``i / (B - 1)`` of it (constant velocity). Or [B, 3]: the
    laser's pose at every beam in that frame (theta unwrapped along the sweep). The result
    has the same beams
    (angles, limits) and ``time_increment`` 0. Bins no point lands in keep the original
    beam's value when it had no return (no-return and too-close codes stay), else NaN.
    A range of exactly ``range_max`` is such a code too (CARMEN and many drivers write
    no-return so; the SLAM reads it so): moved, half of them would land just inside the
    limit and read as a wall at range_max.
    """
    n = len(scan)
    m = np.asarray(motion, np.float64)
    if m.ndim == 2 and m.shape != (n, 3):
        raise ValueError(f"per-beam motion must be [{n}, 3] (x, y, theta at each of the "
                         f"scan's {n} beams), got {list(m.shape)}")
    if m.ndim != 2:
        m = m.reshape(3)
    done = replace(scan, time_increment=0.0)
    if scan.time_increment == 0 or n < 2 or not np.any(m):
        return done
    with np.errstate(invalid="ignore"):
        moves = scan.valid_mask() & (scan.ranges < scan.range_max)  # [B] real returns
    ok = np.flatnonzero(moves)
    # [V, 3] the laser's pose at each moved beam (at constant velocity its share of the sweep)
    at = m[ok] if m.ndim == 2 else (ok / (n - 1))[:, None] * m
    a = scan.angles()[ok]
    r = scan.ranges[ok].astype(np.float64)
    th = a + at[:, 2]
    qx = r * np.cos(th) + at[:, 0]  # [V] point in the first beam's frame
    qy = r * np.sin(th) + at[:, 1]
    rho = np.hypot(qx, qy)
    # Fractional beam index of each moved point, unwrapped next to its own beam.
    phi = a + np.angle(np.exp(1j * (np.arctan2(qy, qx) - a)))
    u = (phi - scan.angle_min) / scan.angle_increment
    order = np.argsort(u, kind="stable")
    u, rho, src = u[order], rho[order], ok[order]
    if abs(scan.angle_increment) * n >= 2 * np.pi - 1e-6 and len(u):
        # A full turn: the points past one end continue at the other, a turn (not n beams)
        # away: drivers that put a beam at both -pi and pi (rplidar's n - 1 increments over
        # the turn) overlap the ends, and n beams put the wrapped points a beam off.
        turn = 2 * np.pi / abs(scan.angle_increment)
        u = np.concatenate([u - turn, u, u + turn])
        rho = np.tile(rho, 3)
        src = np.tile(src, 3)
    out = np.where(moves, np.nan, scan.ranges).astype(np.float32)
    inten = None if scan.intensities is None else scan.intensities.copy()
    if len(u):
        k = np.arange(n, dtype=np.float64)
        right = np.searchsorted(u, k, side="left")  # first point at or after bin k
        left = right - 1
        has_l, has_r = left >= 0, right < len(u)
        li, ri = np.clip(left, 0, len(u) - 1), np.clip(right, 0, len(u) - 1)
        ul, ur = u[li], u[ri]
        rl, rr = rho[li], rho[ri]
        same = (has_l & has_r & (ur - ul <= 1.5)
                & (np.abs(rl - rr) <= JUMP_M + JUMP_REL * np.minimum(rl, rr)))
        w = np.where(same, (k - ul) / np.maximum(ur - ul, 1e-12), 0.0)
        interp = rl + w * (rr - rl)
        dl = np.where(has_l, k - ul, np.inf)
        dr = np.where(has_r, ur - k, np.inf)
        near = np.where(dl <= dr, li, ri)
        near_ok = np.minimum(dl, dr) <= 0.5
        val = np.where(same, interp, np.where(near_ok, rho[near], np.nan))
        got = same | near_ok
        out[got] = val[got]
        if inten is not None:
            inten[got] = scan.intensities[src[near[got]]]  # type: ignore[index]
    return replace(done, ranges=out, intensities=inten)


def is_swept(scan: LaserScan) -> bool:
    """Whether the scan's beams carry their own times (``deskew_scans`` de-skews it)."""
    return scan.time_increment != 0 and len(scan) > 1


def deskew_scans(scans: list[LaserScan], traj: Trajectory, T_base_laser: np.ndarray,
                 covered_only: bool = False) -> list[LaserScan]:
    """Every scan with per-beam timing de-skewed with the motion of ``traj`` (T_base in
    any fixed frame: world, odom) over its sweep; scans without timing come back as they
    are. Where ``traj`` has poses inside a sweep (odometry faster than the lidar), each
    beam's pose is interpolated between the poses around its time (the sweep's ends
    interpolated as before); with none inside, the motion between the sweep's ends is
    spread at constant velocity (accelerating, turning drives under a 10 Hz lidar: 4.4 mm
    worst residual skew over 24 drives; 0.07 mm from poses at 200 Hz, 1.2 mm at 20 Hz).
    A sweep reaching outside the trajectory takes the motion of the same length of time at
    the trajectory's end at constant velocity (clipped to the end poses, the last scan of
    a trajectory stamped at the scans got no motion at all and stayed skewed: 6.9 cm
    median, 78 cm worst, turning at 1 rad/s), or with ``covered_only`` keeps its timing
    for someone else to de-skew - as do sweeps in a gap of it then (``Trajectory.covers``:
    a straight line across a gap is a guess)."""
    lo, hi = (traj.stamps[0], traj.stamps[-1]) if len(traj) else (np.inf, -np.inf)
    timed = [k for k, s in enumerate(scans) if is_swept(s)]
    if covered_only and timed and len(traj):
        ends = np.array([[scans[k].stamp, scans[k].stamp + scans[k].sweep_s] for k in timed])
        ok = traj.covers(ends.ravel()).reshape(-1, 2).all(1)
        timed = [k for k, keep in zip(timed, ok, strict=True) if keep]
    if not timed or not len(traj):
        return scans
    t0 = np.array([scans[k].stamp for k in timed])
    sweep = np.array([scans[k].sweep_s for k in timed])  # [T] negative: beams ran back
    t1 = t0 + sweep
    # Sweeps past an end slide inside the trajectory where it is long enough to hold them.
    start = np.minimum(t0, t1)
    length = np.abs(sweep)
    # Trajectory samples strictly inside each sweep that lies within the trajectory:
    # samples [first, last) of traj.stamps; a sweep slid inside keeps constant velocity.
    first = np.searchsorted(traj.stamps, start, side="right")
    last = np.searchsorted(traj.stamps, start + length, side="left")
    inner = (start >= lo) & (start + length <= hi) & (last > first)  # [T]
    fits = length <= hi - lo
    slid = np.where(fits, np.clip(start, lo, hi - np.where(fits, length, 0.0)), start)
    t0 = np.where(sweep >= 0, slid, slid + length)
    t1 = np.where(sweep >= 0, slid + length, slid)
    poses = interpolate_poses(traj.stamps, traj.poses, np.clip(np.concatenate([t0, t1]), lo, hi))
    T_wl = poses @ T_base_laser  # [2T, 4, 4]
    motion = planar_motion(T_wl[: len(timed)], T_wl[len(timed):])  # [T, 3]
    out = list(scans)
    for j, k in enumerate(timed):
        m = motion[j]
        if inner[j]:
            T_in = traj.poses[first[j]:last[j]] @ T_base_laser  # [I, 4, 4]
            ends = (T_wl[j], T_wl[len(timed) + j])  # at the stamp, at the last beam
            if sweep[j] < 0:  # the knots in time order: the last beam came first
                ends = ends[::-1]
            knots = np.concatenate([ends[0][None], T_in, ends[1][None]])  # [I + 2, 4, 4]
            knot_t = np.concatenate([[start[j]], traj.stamps[first[j]:last[j]],
                                     [start[j] + length[j]]])  # [I + 2]
            m = beam_motion(scans[k], knot_t, planar_motion(T_wl[j], knots))
        out[k] = deskew_scan(scans[k], m)
    return out


def beam_motion(scan: LaserScan, knot_t: np.ndarray, knots: np.ndarray) -> np.ndarray:
    """[B, 3] the laser's (x, y, theta) at each beam of ``scan`` in the laser frame at
    its stamp, interpolated (SE(2): x, y and theta each linearly) between ``knots`` [K, 3]
    (poses in that frame) at increasing times ``knot_t`` [K] that span the sweep."""
    kn = np.array(knots, np.float64)  # [K, 3]
    kn[:, 2] = np.unwrap(kn[:, 2])  # a sweep turning past +-pi in the stamp's frame
    tb = scan.stamp + scan.beam_times()  # [B]
    return np.stack([np.interp(tb, knot_t, kn[:, c]) for c in range(3)], -1)


def deskew_sequence(seq: Sequence, traj: Trajectory) -> Sequence:
    """``seq`` with its scans de-skewed along ``traj`` (the same object when no scan has
    per-beam timing)."""
    scans = deskew_scans(seq.scans, traj, seq.rig.T_base_laser)
    return seq if scans is seq.scans else replace(seq, scans=scans)

"""Differential-drive motion along a route, and wheel odometry with drift.

A route (waypoints) becomes a drivable path: gentle corners are rounded with circular arcs,
sharp ones (beyond ``spin_above_deg``) are taken by stopping and turning on the spot, as a
differential-drive robot does. Speed follows a profile limited by top speed, acceleration
and yaw rate (slow in tight arcs). The path is sampled every centimetre; a pose at any time
is the linear interpolation of those samples, which *defines* the ground truth, so the
poses the renderer uses and the poses written to disk are the same numbers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from toolkit.geometry import se2_between, se2_compose, se2_to_se3, wrap_angle

DS = 0.01  # path sampling step, metres


@dataclass(frozen=True)
class MotionLimits:
    """Limits of the robot's motion (SI units)."""

    v_max: float = 0.45  # cruise speed, m/s (0.3-0.6 per the spec)
    a_max: float = 0.5  # m/s^2
    w_max: float = 0.9  # yaw rate, rad/s
    alpha_max: float = 1.5  # yaw acceleration, rad/s^2
    corner_radius: float = 0.45  # largest arc radius at a corner, m
    spin_above_deg: float = 120.0  # sharper corners: stop and turn in place
    pause_s: float = 0.5  # standing still at the start and the end


@dataclass(frozen=True)
class OdometryNoise:
    """Wheel-odometry error model: biases (drift) plus random walk per metre / radian."""

    scale_bias: float = 0.01  # travelled distance over-read by this fraction
    yaw_bias: float = 0.01  # turned angle over-read by this fraction
    trans_std: float = 0.01  # m per sqrt(m)
    rot_std: float = 0.01  # rad per sqrt(rad)
    rot_per_m_std: float = 0.005  # rad per sqrt(m): heading noise from slip while driving


@dataclass
class RobotPath:
    """Dense samples of a drive: the ground truth of ``T_world_base`` at any time."""

    t: np.ndarray  # [N] seconds from the start, increasing
    xy: np.ndarray  # [N, 2]
    yaw: np.ndarray  # [N] unwrapped
    v_max: float
    laps: float  # how many times the route was driven (1 = once, start to start)

    @property
    def duration(self) -> float:
        return float(self.t[-1])

    @property
    def length(self) -> float:
        return float(np.linalg.norm(np.diff(self.xy, axis=0), axis=1).sum())

    def pose2d(self, t: np.ndarray) -> np.ndarray:
        """[M, 3] (x, y, yaw) at times [M] (clamped to the drive)."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        return np.stack([np.interp(t, self.t, self.xy[:, 0]), np.interp(t, self.t, self.xy[:, 1]),
                         wrap_angle(np.interp(t, self.t, self.yaw))], -1)

    def T_world_base(self, t: np.ndarray) -> np.ndarray:
        """[M, 4, 4] base poses (z = 0: the base frame sits on the floor)."""
        poses = [se2_to_se3(*p) for p in self.pose2d(t)]
        return np.stack(poses) if poses else np.zeros((0, 4, 4))


def _speed_profile(s: np.ndarray, kappa: np.ndarray, lim: MotionLimits, v_max: float) -> (
    np.ndarray
):
    """[N] speeds along arc length ``s`` [N], starting and ending at rest."""
    k = np.abs(kappa)
    # A sample next to an arc limits the speed too: the step onto the arc already turns.
    k = np.maximum(k, np.maximum(np.concatenate([k[1:], [0.0]]), np.concatenate([[0.0], k[:-1]])))
    with np.errstate(divide="ignore"):
        v = np.minimum(v_max, lim.w_max / k)
    v[0] = v[-1] = 0.0
    ds = np.diff(s)
    for i in range(1, len(v)):
        v[i] = min(v[i], np.sqrt(v[i - 1] ** 2 + 2 * lim.a_max * ds[i - 1]))
    for i in range(len(v) - 2, -1, -1):
        v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 2 * lim.a_max * ds[i]))
    return v


def _spin_times(angle: float, lim: MotionLimits, n: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """Times [n] and yaw offsets [n] of a turn on the spot by ``angle`` (trapezoid profile)."""
    a = abs(angle)
    w, al = lim.w_max, lim.alpha_max
    if a < w * w / al:  # never reaches full yaw rate
        tt = 2.0 * np.sqrt(a / al)
        w = al * tt / 2
    else:
        tt = a / w + w / al
    t = np.linspace(0.0, tt, n)
    ta = w / al
    th = np.where(t < ta, 0.5 * al * t**2,
                  np.where(t > tt - ta, a - 0.5 * al * (tt - t) ** 2, 0.5 * al * ta**2
                           + w * (t - ta)))
    return t, np.sign(angle) * th


def _geometry(route: np.ndarray, start_yaw: float, lim: MotionLimits,
              end_yaw: float | None = None) -> list[tuple[str, np.ndarray]]:
    """Pieces of the path: ("drive", [N, 4] x y yaw kappa) and ("spin", [2, 3] pose pairs).

    ``end_yaw``: turn on the spot at the last waypoint to face this way (closing a loop
    where it started, looking the same way: the last images overlap the first ones).
    """
    P = np.asarray(route, dtype=np.float64)
    seg = np.diff(P, axis=0)
    L = np.linalg.norm(seg, axis=1)
    head = np.arctan2(seg[:, 1], seg[:, 0])
    K = len(P)
    tau = np.zeros(K)  # tangent length used by the fillet at each waypoint
    radius = np.zeros(K)
    spin = np.zeros(K, bool)
    turn = np.zeros(K)
    for i in range(1, K - 1):
        th = float(wrap_angle(head[i] - head[i - 1]))
        turn[i] = th
        if abs(th) > np.radians(lim.spin_above_deg):
            spin[i] = True
        elif abs(th) > 1e-6:
            tan_h = np.tan(abs(th) / 2)
            r = min(lim.corner_radius, 0.5 * min(L[i - 1], L[i]) / tan_h)
            radius[i] = r
            tau[i] = r * tan_h
    pieces: list[tuple[str, np.ndarray]] = []
    first_turn = float(wrap_angle(head[0] - start_yaw))
    if abs(first_turn) > 1e-6:
        pieces.append(("spin", np.array([[*P[0], start_yaw], [*P[0], start_yaw + first_turn]])))
    run: list[np.ndarray] = []
    for i in range(K - 1):
        d = seg[i] / L[i]
        a = P[i] + tau[i] * d
        b = P[i + 1] - tau[i + 1] * d
        n = max(int(np.ceil(np.linalg.norm(b - a) / DS)), 1)
        f = np.arange(0, n + 1) / n
        line = a + (b - a) * f[:, None]
        run.append(np.column_stack([line, np.full(len(f), head[i]), np.zeros(len(f))]))
        j = i + 1
        if j == K - 1:
            break
        if spin[j]:
            pieces.append(("drive", np.concatenate(run)))
            run = []
            pieces.append(("spin", np.array([[*P[j], head[i]], [*P[j], head[i] + turn[j]]])))
        elif radius[j] > 0:
            sgn = np.sign(turn[j])
            left = np.array([-d[1], d[0]])
            ctr = b + sgn * radius[j] * left
            phi0 = np.arctan2(b[1] - ctr[1], b[0] - ctr[0])
            m = max(int(np.ceil(radius[j] * abs(turn[j]) / DS)), 2)
            ang = phi0 + sgn * abs(turn[j]) * np.arange(1, m + 1) / m
            arc = ctr + radius[j] * np.column_stack([np.cos(ang), np.sin(ang)])
            yaw = head[i] + turn[j] * np.arange(1, m + 1) / m
            run.append(np.column_stack([arc, yaw, np.full(m, sgn / radius[j])]))
    if run:
        pieces.append(("drive", np.concatenate(run)))
    if end_yaw is not None:
        last = float(wrap_angle(end_yaw - head[-1]))
        if abs(last) > 1e-6:
            pieces.append(("spin", np.array([[*P[-1], head[-1]], [*P[-1], head[-1] + last]])))
    return pieces


def _timed(pieces: list[tuple[str, np.ndarray]], lim: MotionLimits, v_max: float) -> (
    tuple[np.ndarray, np.ndarray, np.ndarray]
):
    ts, xys, yaws = [], [], []
    t0 = 0.0
    yaw_prev: float | None = None

    def push(t: np.ndarray, xy: np.ndarray, yaw: np.ndarray) -> None:
        nonlocal t0, yaw_prev
        if yaw_prev is not None:  # keep yaw continuous (unwrapped) across pieces
            yaw = yaw + np.round((yaw_prev - yaw[0]) / (2 * np.pi)) * 2 * np.pi
        yaw = np.unwrap(yaw)
        if ts:
            t, xy, yaw = t[1:], xy[1:], yaw[1:]  # first sample repeats the previous end
        ts.append(t0 + t)
        xys.append(xy)
        yaws.append(yaw)
        t0 = float(ts[-1][-1])
        yaw_prev = float(yaws[-1][-1])

    for kind, data in pieces:
        if kind == "spin":
            t, dth = _spin_times(float(wrap_angle(data[1, 2] - data[0, 2])), lim)
            push(t, np.repeat(data[:1, :2], len(t), 0), data[0, 2] + dth)
        else:
            xy = data[:, :2]
            keep = np.concatenate([[True], np.linalg.norm(np.diff(xy, axis=0), axis=1) > 1e-9])
            data = data[keep]
            s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(data[:, :2], axis=0),
                                                                axis=1))])
            v = _speed_profile(s, data[:, 3], lim, v_max)
            dt = 2.0 * np.diff(s) / np.maximum(v[:-1] + v[1:], 1e-9)
            push(np.concatenate([[0.0], np.cumsum(dt)]), data[:, :2], data[:, 2])
    return np.concatenate(ts), np.concatenate(xys), np.concatenate(yaws)


def plan_path(route: np.ndarray, start_yaw: float, lim: MotionLimits = MotionLimits(),
              duration_s: float | None = None) -> RobotPath:
    """The timed drive along ``route`` [K, 2] (a loop when first == last waypoint).

    With ``duration_s`` the cruise speed is chosen in [0.3, 0.6] m/s so that one lap takes
    that long; a longer duration drives further laps (turning on the spot at the start),
    a shorter one ends early (the loop is then not closed).
    """
    route = np.asarray(route, dtype=np.float64)
    v_max = lim.v_max
    laps = 1
    end_yaw = start_yaw if np.linalg.norm(route[0] - route[-1]) < 1e-6 else None
    if duration_s is not None:
        def lap_time(v: float) -> float:
            t, _, _ = _timed(_geometry(route, start_yaw, lim, end_yaw), lim, v)
            return float(t[-1]) + 2 * lim.pause_s

        lo, hi = 0.3, 0.6
        if lap_time(hi) >= duration_s:
            v_max = hi
        elif lap_time(lo) <= duration_s:
            v_max = lo
            laps = int(np.ceil(duration_s / lap_time(lo)))
        else:
            for _ in range(30):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if lap_time(mid) > duration_s else (lo, mid)
            v_max = 0.5 * (lo + hi)
    full = route
    for _ in range(laps - 1):
        full = np.concatenate([full, route[1:]])
    t, xy, yaw = _timed(_geometry(full, start_yaw, lim, end_yaw), lim, v_max)
    # Standing still at the start and the end (sensors settle; SLAM gets a clean first scan).
    p = lim.pause_s
    if p > 0:
        t = np.concatenate([[0.0], t + p, [t[-1] + 2 * p]])
        xy = np.concatenate([xy[:1], xy, xy[-1:]])
        yaw = np.concatenate([yaw[:1], yaw, yaw[-1:]])
    done = float(t[-1])
    if duration_s is not None and done < duration_s - 1e-9:
        # Laps were counted with one lap's pauses and final turn each, which the joined
        # path holds once: the robot stands at the start for the rest of the time.
        t = np.concatenate([t, [duration_s]])
        xy = np.concatenate([xy, xy[-1:]])
        yaw = np.concatenate([yaw, yaw[-1:]])
    if duration_s is not None and done > duration_s + 1e-9:
        keep = t <= duration_s
        end = np.array([np.interp(duration_s, t, xy[:, 0]), np.interp(duration_s, t, xy[:, 1])])
        yaw_end = np.interp(duration_s, t, yaw)
        t = np.concatenate([t[keep], [duration_s]])
        xy = np.concatenate([xy[keep], end[None]])
        yaw = np.concatenate([yaw[keep], [yaw_end]])
        frac = duration_s / done * laps
    else:
        frac = float(laps)
    return RobotPath(t, xy, yaw, v_max, frac)


def simulate_odometry(poses2d: np.ndarray, noise: OdometryNoise,
                      rng: np.random.Generator) -> np.ndarray:
    """[N, 3] wheel-odometry poses ``T_odom_base`` (starting at the origin) for true poses.

    Each step's travelled distance and turned angle are read with a bias and a random walk
    whose variance grows with the step (so the drift does not depend on the sampling rate).
    """
    poses2d = np.asarray(poses2d, dtype=np.float64)
    rel = se2_between(poses2d[:-1], poses2d[1:])  # [N-1, 3] true increments, base frame
    d = np.hypot(rel[:, 0], rel[:, 1])
    dth = rel[:, 2]
    ad, ath = d, np.abs(dth)
    d_m = d * (1.0 + noise.scale_bias) + rng.standard_normal(len(d)) * noise.trans_std * np.sqrt(ad)
    th_m = dth * (1.0 + noise.yaw_bias) + rng.standard_normal(len(d)) * np.sqrt(
        noise.rot_std**2 * ath + noise.rot_per_m_std**2 * ad)
    # The measured step: the true one scaled by the distance error and turned by half the
    # heading error (the wheels read the turn wrong all along the step). Noise-free
    # settings reproduce the true motion exactly.
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(d > 0, d_m / d, 0.0)
    err = 0.5 * (th_m - dth)
    c, s = np.cos(err), np.sin(err)
    steps = np.column_stack([scale * (c * rel[:, 0] - s * rel[:, 1]),
                             scale * (s * rel[:, 0] + c * rel[:, 1]), th_m])
    out = np.zeros((len(poses2d), 3))
    for k, st in enumerate(steps):
        out[k + 1] = se2_compose(out[k], st)
    return out

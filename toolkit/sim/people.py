"""People: moving obstacles walking their own routes, intersected analytically.

A person is two legs and a torso (vertical capped cylinders) and a head (sphere). They are
not part of the static mesh: the BVH is built once, and people are intersected in numpy
and merged with the static hits by the smaller distance. Walkers go back and forth along
a route (corridor <-> room, or room <-> room), pausing 0.5-2 s at its ends, or, with
``stand_s``, standing there for a drawn while (legs still); when the robot comes close they
make way (step back along their route or stand), and plans that still come within
``MIN_ROBOT_DIST`` of the robot are re-drawn, so the camera never ends up inside anyone.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from toolkit.sim.robot import RobotPath

MIN_ROBOT_DIST = 0.6  # person centre to robot centre, metres
LEG_R, LEG_H, LEG_SEP = 0.075, 0.85, 0.1
TORSO_R, TORSO_H = 0.19, 1.45
HEAD_R, HEAD_Z = 0.11, 1.58
BOUND_R = 0.32  # encloses a person at any gait phase (legs swing 0.12 m)
STRIDE = 1.4  # metres per gait cycle

SHIRTS = [(0.8, 0.15, 0.15), (0.15, 0.35, 0.75), (0.2, 0.6, 0.3), (0.9, 0.7, 0.1),
          (0.5, 0.2, 0.6), (0.9, 0.9, 0.88), (0.3, 0.3, 0.32)]
TROUSERS = [(0.15, 0.18, 0.35), (0.25, 0.22, 0.2), (0.1, 0.1, 0.1), (0.55, 0.5, 0.4)]
SKINS = [(0.95, 0.78, 0.65), (0.75, 0.55, 0.4), (0.45, 0.32, 0.22), (0.98, 0.85, 0.75)]


@dataclass
class Walker:
    """One person's simulated track on a regular time grid."""

    t: np.ndarray  # [M] seconds
    xy: np.ndarray  # [M, 2]
    heading: np.ndarray  # [M] unwrapped radians
    gait: np.ndarray  # [M] metres walked (drives the leg swing)
    colors: np.ndarray  # [3, 3] RGB 0..1 of legs, torso, head
    route: np.ndarray  # [K, 2]
    # [P, 2] the stops drawn at the route's ends: start time (s) and drawn length (s). The
    # walker stands for that long, longer when it steps aside for the robot meanwhile.
    stops: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    def state(self, t: float) -> tuple[np.ndarray, float, float]:
        """(xy [2], heading, gait) at time ``t``."""
        xy = np.array([np.interp(t, self.t, self.xy[:, 0]), np.interp(t, self.t, self.xy[:, 1])])
        return xy, float(np.interp(t, self.t, self.heading)), float(np.interp(t, self.t,
                                                                              self.gait))


@dataclass
class Primitive:
    """A shape of one person at one instant."""

    kind: str  # "cyl" | "sphere"
    params: np.ndarray  # cyl: cx cy r z0 z1; sphere: cx cy cz r
    color: np.ndarray  # [3] 0..1
    person: int


def primitives_at(walkers: list[Walker], t: float) -> list[Primitive]:
    """All people's shapes at time ``t``."""
    out: list[Primitive] = []
    for k, w in enumerate(walkers):
        xy, hd, gait = w.state(t)
        f = np.array([np.cos(hd), np.sin(hd)])
        left = np.array([-f[1], f[0]])
        swing = 0.12 * np.sin(2 * np.pi * gait / STRIDE)
        for s in (-1.0, 1.0):
            c = xy + s * LEG_SEP * left + s * swing * f
            out.append(Primitive("cyl", np.array([c[0], c[1], LEG_R, 0.0, LEG_H]), w.colors[0], k))
        out.append(Primitive("cyl", np.array([xy[0], xy[1], TORSO_R, LEG_H, TORSO_H]),
                             w.colors[1], k))
        out.append(Primitive("sphere", np.array([xy[0], xy[1], HEAD_Z, HEAD_R]), w.colors[2], k))
    return out


def intersect(prim: Primitive, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Ray parameters [N] (inf on a miss) of rays ``o + t d``, ``d`` [N, 3], ``o`` [3] or
    [N, 3] (rays of one height: a sweeping lidar)."""
    return intersect_cols(prim, o, d[:, 0], d[:, 1], d[:, 2])


def intersect_cols(prim: Primitive, o: np.ndarray, dx: np.ndarray, dy: np.ndarray,
                   dz: np.ndarray) -> np.ndarray:
    """``intersect`` with the direction components as separate [N] arrays.

    Works in the dtype of the directions (float32 for images, float64 for the lidar):
    the scalars are cast first, or numpy would promote whole arrays to float64. Rays
    start outside every person (``MIN_ROBOT_DIST``), so the nearer root is the visible one.
    """
    f = dx.dtype.type
    inf = f(np.inf)
    o = np.asarray(o, np.float64)
    if o.ndim == 2 and np.ptp(o[:, 2]) > 1e-9:
        raise ValueError("rays from per-ray origins must share one height")
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        if prim.kind == "cyl":
            cx, cy, r, z0, z1 = (float(v) for v in prim.params)
            ox, oy, oz = f(o[..., 0] - cx), f(o[..., 1] - cy), float(o[..., 2].flat[0])
            a = dx * dx + dy * dy
            b = ox * dx + oy * dy
            disc = b * b - a * f(ox * ox + oy * oy - r * r)
            t = (-b - np.sqrt(disc)) / a
            zs = f(oz) + t * dz
            t[~((t > 0) & (zs >= f(z0)) & (zs <= f(z1)))] = inf  # NaN (no root) fails too
            for zc, up in ((z1, True), (z0, False)):
                if (oz <= zc) if up else (oz >= zc):
                    continue  # this cap faces away from the viewer
                tc = f(zc - oz) / dz
                px, py = ox + tc * dx, oy + tc * dy
                okc = (tc > 0) & (px * px + py * py <= f(r * r)) & (tc < t)
                t[okc] = tc[okc]
            return t
        cx, cy, cz, r = (float(v) for v in prim.params)
        ox, oy, oz = f(o[..., 0] - cx), f(o[..., 1] - cy), f(o[..., 2] - cz)
        a = dx * dx + dy * dy + dz * dz
        b = ox * dx + oy * dy + oz * dz
        disc = b * b - a * f(ox * ox + oy * oy + oz * oz - r * r)
        t = (-b - np.sqrt(disc)) / a
        t[~(t > 0)] = inf
        return t


def surface_normal(prim: Primitive, p: np.ndarray) -> np.ndarray:
    """[N, 3] unit outward normals at surface points [N, 3] of ``prim``."""
    n = np.zeros_like(p)
    if prim.kind == "cyl":
        cx, cy, r, z0, z1 = prim.params
        n[:, 0] = (p[:, 0] - cx) / r
        n[:, 1] = (p[:, 1] - cy) / r
        # Points on a cap lie inside the circle, side points on it.
        on_cap = (n[:, 0] ** 2 + n[:, 1] ** 2) < 0.98
        n[on_cap] = 0.0
        n[on_cap, 2] = np.where(np.abs(p[on_cap, 2] - z1) < np.abs(p[on_cap, 2] - z0), 1.0, -1.0)
        return n
    return (p - prim.params[:3]) / prim.params[3]


def plan_people(routes: list[np.ndarray], robot: RobotPath, n_people: int,
                rng: np.random.Generator, dt: float = 0.05,
                stand_s: tuple[float, float] | None = None) -> list[Walker]:
    """Tracks for ``n_people`` walkers over the robot's drive (fewer if no safe plan).

    ``stand_s`` (low, high): at each end of its route a walker stands for a time drawn
    uniformly from that range (seconds) instead of the usual 0.5-2 s pause; None keeps the
    pause (and every track drawn before this option, to the bit)."""
    walkers: list[Walker] = []
    if n_people <= 0 or not routes:
        return walkers
    T = robot.duration
    grid = np.arange(0.0, T + dt, dt)
    robot_xy = robot.pose2d(grid)[:, :2]
    for k in range(n_people):
        for attempt in range(30):
            route = routes[(k + attempt) % len(routes)]
            w = _walk(route, grid, robot_xy, rng, stand_s=stand_s)
            if w is None:
                continue
            if np.linalg.norm(w.xy - robot_xy, axis=1).min() >= MIN_ROBOT_DIST:
                walkers.append(w)
                break
    return walkers


def _walk(route: np.ndarray, grid: np.ndarray, robot_xy: np.ndarray,
          rng: np.random.Generator, look_ahead_s: float = 2.5,
          stand_s: tuple[float, float] | None = None) -> Walker | None:
    """Walk back and forth, never stepping to within 1 m of where the robot soon is;
    stopping at the route's ends for 0.5-2 s, or for a time drawn from ``stand_s``."""
    seg = np.linalg.norm(np.diff(route, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    length = float(cum[-1])
    if length < 0.5:
        return None
    # The route densely sampled: positions by arc length without per-step interpolation.
    ds = 0.02
    s_tab = np.arange(0.0, length + ds, ds)
    xy_tab = np.stack([np.interp(s_tab, cum, route[:, 0]), np.interp(s_tab, cum, route[:, 1])],
                      -1)
    speed = rng.uniform(0.7, 1.1)
    s = rng.uniform(0, length)
    direction = 1.0 if rng.random() < 0.5 else -1.0
    pause = rng.uniform(0.0, 2.0)
    dt = grid[1] - grid[0]
    n_ahead = int(look_ahead_s / dt)
    xs = np.empty(len(grid))
    gait = np.empty(len(grid))
    walked = 0.0
    stops: list[tuple[float, float]] = []

    def clearance(si: float, i: int) -> float:
        p = xy_tab[min(int(round(si / ds)), len(s_tab) - 1)]
        fut = robot_xy[i:i + n_ahead]
        return float(np.min(np.hypot(fut[:, 0] - p[0], fut[:, 1] - p[1])))

    for i in range(len(grid)):
        xs[i] = s
        gait[i] = walked
        step = speed * dt
        near = np.min(np.abs(robot_xy[i:i + n_ahead] - xy_tab[min(int(round(s / ds)),
                                                                  len(s_tab) - 1)]).sum(1)) < 3.0
        if near:
            # Give way: of stepping on, stepping back or standing, keep the most room from
            # where the robot will be in the next seconds.
            cands = [min(max(s + direction * step, 0.0), length),
                     min(max(s - direction * step, 0.0), length), s]
            room = [clearance(c, i) for c in cands]
            best = int(np.argmax(room))
            if room[0] >= 1.0:
                best = 0  # enough room ahead: keep walking
            walked += abs(cands[best] - s)
            s = cands[best]
            continue
        if pause > 0:
            pause -= dt
            continue
        s_new = s + direction * step
        if s_new >= length or s_new <= 0:
            s_new = min(max(s_new, 0.0), length)
            direction = -direction
            # The default pause is drawn as before the option existed: the same draws from
            # the people stream keep every older recording's tracks bit for bit.
            pause = rng.uniform(0.5, 2.0) if stand_s is None else rng.uniform(*stand_s)
            # The stop begins at the next sample, where the walker arrives at the end.
            stops.append((float(grid[min(i + 1, len(grid) - 1)]), float(pause)))
        walked += abs(s_new - s)
        s = s_new
    xy = np.stack([np.interp(xs, cum, route[:, 0]), np.interp(xs, cum, route[:, 1])], -1)
    v = np.gradient(xy, axis=0)
    moving = np.linalg.norm(v, axis=1) > 1e-4
    hd = np.arctan2(v[:, 1], v[:, 0])
    # Standing people keep the heading they last walked with.
    idx = np.where(moving, np.arange(len(hd)), 0)
    np.maximum.accumulate(idx, out=idx)
    hd = np.unwrap(hd[idx])
    colors = np.array([TROUSERS[int(rng.integers(len(TROUSERS)))],
                       SHIRTS[int(rng.integers(len(SHIRTS)))],
                       SKINS[int(rng.integers(len(SKINS)))]])
    return Walker(grid.copy(), xy, hd, gait, colors, route,
                  np.array(stops, np.float64).reshape(-1, 2))

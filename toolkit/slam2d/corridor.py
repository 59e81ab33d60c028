"""A drive down a featureless corridor: the degenerate case of 2D scan matching.

Two parallel walls and nothing else fix a scan's lateral offset and heading but not its
position along the corridor; with a short-range lidar the ends are out of reach for most
of the drive. ``corridor_drive`` renders such a recording (exact ray casts against the
wall segments, range noise, wheel odometry with a per-step error) with its true poses, for
the benchmark (``python -m toolkit.slam2d.bench corridor``) and the tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from toolkit.geometry import Trajectory, se2_between, se2_compose, se2_to_se3
from toolkit.sensors import LaserScan


def corridor_walls(length: float, width: float, door_spacing: float = 0.0,
                   door_width: float = 1.0, door_depth: float = 0.4) -> np.ndarray:
    """[S, 4] wall segments (x0, y0, x1, y1): the corridor from x = -1 to ``length`` - 1,
    y = 0 to ``width``, closed at both ends. ``door_spacing`` > 0: identical door niches
    (``door_width`` x ``door_depth``) in the y = 0 wall every ``door_spacing`` m from
    x = 1, an office corridor whose views repeat."""
    x0, x1 = -1.0, length - 1.0
    walls = [[x0, width, x1, width], [x0, 0.0, x0, width], [x1, 0.0, x1, width]]
    x = x0
    if door_spacing > 0:
        for xd in np.arange(1.0, x1 - door_width, door_spacing):
            xe = xd + door_width
            walls += [[x, 0.0, xd, 0.0], [xd, 0.0, xd, -door_depth],
                      [xd, -door_depth, xe, -door_depth], [xe, -door_depth, xe, 0.0]]
            x = xe
    walls.append([x, 0.0, x1, 0.0])
    return np.array(walls, dtype=np.float64)


def cast_rays(walls: np.ndarray, pose: np.ndarray, angles: np.ndarray,
              max_range: float) -> np.ndarray:
    """[B] range to the nearest of ``walls`` [S, 4] along each beam of a laser at ``pose``
    (x, y, theta); inf beyond ``max_range`` or without a hit."""
    d = np.stack([np.cos(angles + pose[2]), np.sin(angles + pose[2])], -1)  # [B, 2]
    a, e = walls[:, :2], walls[:, 2:] - walls[:, :2]  # [S, 2]
    w = a - pose[:2]  # [S, 2]
    den = d[:, None, 1] * e[None, :, 0] - d[:, None, 0] * e[None, :, 1]  # [B, S]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[None, :, 1] * e[None, :, 0] - w[None, :, 0] * e[None, :, 1]) / den
        u = (d[:, None, 0] * w[None, :, 1] - d[:, None, 1] * w[None, :, 0]) / den
    hit = (np.abs(den) > 1e-12) & (t > 0) & (u >= 0) & (u <= 1)
    r = np.where(hit, t, np.inf).min(axis=1)
    r[r > max_range] = np.inf
    return r


@dataclass
class CorridorDrive:
    scans: list[LaserScan]
    odometry: Trajectory  # T_odom_base with the per-step error
    truth: Trajectory  # T_world_base
    walls: np.ndarray  # [S, 4]


def corridor_drive(length: float = 40.0, width: float = 2.0, max_range: float = 8.0,
                   step: float = 0.1, back: bool = True, odometry_error: float = 0.03,
                   heading_noise: float = 0.002, range_noise: float = 0.01,
                   beams: int = 360, rate_hz: float = 10.0, angle_deg: float = 0.0,
                   seed: int = 0, door_spacing: float = 0.0) -> CorridorDrive:
    """Drive along the corridor's centre line from x = 0.5 to 2.5 m short of its far end
    (``step`` m per scan), and with ``back`` turn on the spot and drive back.

    Odometry: each step's true motion times (1 + ``odometry_error`` N(0, 1)) per axis (so
    no sideways error on the straight parts), plus ``heading_noise`` rad N(0, 1) of
    heading. Beams without a return read ``max_range``
    (the ROS convention for "nothing within range"). ``angle_deg`` turns the whole world
    (corridor, path, odometry) about the origin, and the robot starts turned back by it
    (heading 0 in the world) and turns onto the corridor's axis on the spot (10 deg per
    scan) before it drives: the SLAM's grid axes follow its first pose, so the corridor
    lies at ``angle_deg`` to the grid. (Turning the world alone turned the first pose with
    it, and the corridor lay along the grid whatever the angle.) ``door_spacing``: door
    niches along one wall (``corridor_walls``).
    """
    rng = np.random.default_rng(seed)
    walls = corridor_walls(length, width, door_spacing)
    end = length - 3.5
    y = width / 2
    back_by = np.sign(angle_deg) * np.arange(abs(angle_deg), 0.0, -10.0)  # deg, to 0
    out = [np.array([0.5, y, -a]) for a in np.radians(back_by)]
    out += [np.array([x, y, 0.0]) for x in np.arange(0.5, end + 1e-9, step)]
    if back:
        out += [np.array([end, y, a]) for a in np.linspace(0.0, np.pi, 19)[1:]]
        out += [np.array([x, y, np.pi]) for x in np.arange(end - step, 0.5 - 1e-9, -step)]
    turn = np.array([0.0, 0.0, np.radians(angle_deg)])
    truth = se2_compose(turn, np.array(out))  # [N, 3]
    zero = np.zeros(len(walls))
    walls = np.concatenate([se2_compose(turn, np.c_[walls[:, :2], zero])[:, :2],
                            se2_compose(turn, np.c_[walls[:, 2:], zero])[:, :2]], 1)
    angles = -np.pi + np.arange(beams) * 2 * np.pi / beams
    odo = [truth[0].copy()]
    for k in range(1, len(truth)):
        d = se2_between(truth[k - 1], truth[k]) * (1 + odometry_error * rng.normal(size=3))
        d[2] += heading_noise * rng.normal()
        odo.append(se2_compose(odo[-1], d))
    scans = []
    for k, p in enumerate(truth):
        r = cast_rays(walls, p, angles, max_range) + rng.normal(0, range_noise, beams)
        r = np.minimum(np.where(np.isfinite(r), r, max_range), max_range)
        scans.append(LaserScan(stamp=k / rate_hz, ranges=r.astype(np.float32),
                               angle_min=float(angles[0]), angle_increment=2 * np.pi / beams,
                               range_min=0.05, range_max=max_range))
    stamps = np.arange(len(truth)) / rate_hz
    return CorridorDrive(scans, Trajectory(stamps, _se3(odo), "odom", "base_link"),
                         Trajectory(stamps, _se3(truth), "world", "base_link"), walls)


def _se3(poses: list[np.ndarray] | np.ndarray) -> np.ndarray:
    return np.stack([se2_to_se3(*p) for p in poses])  # [N, 4, 4]

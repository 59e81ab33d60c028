"""Running ``LidarSlam2D`` over a recording and turning its outputs into files.

The algorithm knows nothing of sequences, logs or files; this module feeds it scans in
order with odometry looked up at each scan stamp, and converts its grid to the
map_server representation.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable, Sequence

import numpy as np

from toolkit.deskew import deskew_scans
from toolkit.geometry import Trajectory
from toolkit.io.occupancy import OccupancyMap
from toolkit.sensors import LaserScan
from toolkit.slam2d.config import Slam2DConfig
from toolkit.slam2d.grid import ProbabilityGrid
from toolkit.slam2d.slam import LidarSlam2D, ScanLike, SlamResult

_log = logging.getLogger(__name__)


def odometry_at(odometry: Trajectory | None, stamps: np.ndarray) -> list[np.ndarray | None]:
    """T_odom_base [4, 4] at each stamp (interpolated), None outside the odometry's span and
    in gaps of it (``Trajectory.covers``): across a gap a straight line and the shorter
    turn are a guess, and a robot that spun 270 deg while the odometry was silent was
    predicted turning the other way (1.8 m / 177 deg off; scan-only it stays on track)."""
    out: list[np.ndarray | None] = [None] * len(stamps)
    if odometry is None or len(odometry) == 0:
        return out
    inside = odometry.covers(stamps)
    if len(odometry) == 1:
        inside &= stamps == odometry.stamps[0]
    idx = np.flatnonzero(inside)
    if len(idx):
        P = odometry.interpolate(stamps[idx]).poses
        for k, i in enumerate(idx):
            out[i] = P[k]
    return out


def run_slam(
    scans: Sequence[ScanLike],
    odometry: Trajectory | None = None,
    T_base_laser: np.ndarray | None = None,
    config: Slam2DConfig | None = None,
    progress: Callable[[Iterable], Iterable] | None = None,
) -> SlamResult:
    """Process ``scans`` in the given order (bad or out-of-order ones are counted and
    skipped by the SLAM). Adds wall and CPU times and real-time factors to the metrics."""
    t0 = time.perf_counter()
    c0 = time.process_time()
    slam = LidarSlam2D(config, T_base_laser)
    if odometry is not None and len(odometry) == 0:
        _log.warning("the odometry holds no poses; every scan is matched scan-only")
        odometry = None
    by_odometry = 0
    if odometry is not None and len(odometry) > 1:
        # Wheel odometry knows the motion during each sweep (forward of the stamp, which
        # the SLAM's own velocity cannot): simulated house at 5 Hz, scans de-skewed
        # with odometry 0.010 m / 0.35 deg ATE, by the SLAM 0.014 m / 0.47 deg, not at
        # all 0.044 m / 2.75 deg (with odometry, following its poses inside each sweep
        # instead of constant velocity: 0.0116 m / 0.354 deg -> 0.0098 m / 0.174 deg on
        # a 30 s drive). The SLAM de-skews the scans odometry does not cover.
        laser = np.eye(4) if T_base_laser is None else np.asarray(T_base_laser, np.float64)
        timed = [s for s in scans if isinstance(s, LaserScan)]
        if len(timed) == len(scans) and any(s.time_increment for s in timed):
            deskewed = deskew_scans(timed, odometry, laser, covered_only=True)
            by_odometry = sum(a is not b for a, b in zip(timed, deskewed, strict=True))
            scans = deskewed
    stamps = np.array([float(s.stamp) for s in scans], dtype=np.float64)
    odom = odometry_at(odometry, stamps)
    with_odom = sum(o is not None for o in odom)
    if odometry is not None and with_odom < len(scans):
        # Odometry in another time base (or a shorter recording) leaves scans without it:
        # the SLAM runs scan-only there, which the user should know.
        _log.warning("odometry covers %d of %d scans (odometry %.3f..%.3f s, scans %.3f..%.3f"
                     " s); the others are matched scan-only", with_odom, len(scans),
                     odometry.stamps[0], odometry.stamps[-1], np.nanmin(stamps),
                     np.nanmax(stamps))
    items: Iterable = zip(scans, odom, strict=True)
    if progress is not None:
        items = progress(items)
    for scan, o in items:
        slam.add_scan(scan, o)
    result = slam.finish()
    wall = time.perf_counter() - t0
    cpu = time.process_time() - c0
    finite = stamps[np.isfinite(stamps)]
    span = float(finite.max() - finite.min()) if len(finite) > 1 else 0.0
    result.metrics["wall_time_s"] = round(wall, 3)
    result.metrics["log_duration_s"] = round(span, 3)
    result.metrics["realtime_factor"] = round(span / wall, 2) if wall > 0 else None
    # CPU time of this process: the speed on an unloaded core when the machine is shared.
    result.metrics["cpu_time_s"] = round(cpu, 3)
    result.metrics["realtime_factor_cpu"] = round(span / cpu, 2) if cpu > 0 else None
    result.metrics["odometry_used"] = with_odom > 0
    # scans_deskewed counts the SLAM's own (with its velocity); these went in de-skewed
    result.metrics["scans_deskewed_odometry"] = by_odometry
    result.metrics["scans_with_odometry"] = with_odom
    return result


def grid_to_occupancy(grid: ProbabilityGrid, crop: bool = True, margin_cells: int = 10) -> (
        OccupancyMap):
    """The grid as an ``OccupancyMap`` (NaN = never observed), cropped to observed cells."""
    origin = grid.origin.copy()
    lo = hi = None
    if crop:
        b = grid.known_bounds()
        if b is not None:
            H, W = grid.values.shape
            lo = np.maximum(b[0] - margin_cells, 0)
            hi = np.minimum(b[1] + margin_cells, [W, H])
            origin = origin + lo * grid.resolution
    # Cropped before converting: the grid grows with slack (half its size at a time), and
    # a float32 copy of all of it plus its mask took 0.4 GB for Killian's map.
    occ = grid.occupancy(lo, hi)  # [h, w]
    return OccupancyMap(np.ascontiguousarray(occ), grid.resolution,
                        (float(origin[0]), float(origin[1]), 0.0))

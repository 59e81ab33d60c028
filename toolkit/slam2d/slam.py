"""``LidarSlam2D``: Cartographer-style 2D SLAM that takes scans one at a time.

Local SLAM matches each scan against the older of two active submaps (correlative search
around the predicted pose, then continuous refinement on the interpolated grid), applies
a motion filter, and inserts the scan into both submaps. Global SLAM keeps a sparse pose
graph of scan nodes and submaps (intra-submap constraints from local SLAM, consecutive
local-SLAM and odometry constraints, loop closures found by branch-and-bound search of
finished submaps) and optimises it every ``optimize_every_n_nodes`` nodes and at the end.

The algorithm is this class; reading logs, running over a sequence and writing files are
in ``run_slam`` and ``toolkit.slam2d.stage`` (kiss-icp's split between ``KissICP`` and
its pipeline).
"""

from __future__ import annotations

import logging
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from toolkit.deskew import deskew_scan, planar_motion
from toolkit.geometry import (
    Trajectory,
    inv_se3,
    se2_between,
    se2_compose,
    se2_inverse,
    se2_to_matrix,
    se2_to_se3,
    se3_to_se2,
    transform_points,
    wrap_angle,
)
from toolkit.sensors import LaserScan
from toolkit.slam2d.config import Slam2DConfig
from toolkit.slam2d.grid import ProbabilityGrid
from toolkit.slam2d.loop_closure import LoopCloser
from toolkit.slam2d.matcher import (
    GridPyramid,
    SearchResult,
    correlative_search,
    interpolate,
    normal_spread,
    refine,
    voxel_filter,
    weak_direction,
)
from toolkit.slam2d.pose_graph import PoseGraph2D
from toolkit.slam2d.submaps import ActiveSubmaps, Submap

log = logging.getLogger(__name__)

EDGE_INTRA, EDGE_LOCAL, EDGE_ODOM, EDGE_LOOP = 0, 1, 2, 3


class ScanLike(Protocol):
    """What the SLAM reads from a scan (``toolkit.sensors.LaserScan`` fits; a
    ``LaserScan`` with a ``time_increment`` is de-skewed)."""

    stamp: float
    ranges: np.ndarray
    angle_min: float
    angle_increment: float
    range_min: float
    range_max: float


@dataclass
class Node:
    index: int
    stamp: float
    local_pose: np.ndarray  # [3] in the local SLAM frame
    vertex: int
    hits: np.ndarray  # [N, 2] float32 returns in the base frame
    free: np.ndarray  # [M, 2] float32 ends of rays without return, base frame
    match_points: np.ndarray  # [K, 2] float64 loop-closure points, base frame
    odom: np.ndarray | None  # [3] T_odom_base, when odometry was given
    submaps: list[int] = field(default_factory=list)
    # Added by the motion filter's time limit alone (the robot had not moved): not
    # searched for loop closures, see LoopClosureOptions.stationary_nodes.
    stationary: bool = False
    spread: float | None = None  # normal_spread of hits, once a test has needed it


@dataclass
class SlamResult:
    trajectory: Trajectory  # T_world_base at every accepted scan stamp
    poses: np.ndarray  # [S, 3] the same as (x, y, theta)
    nodes: np.ndarray  # [S] bool: the scan became a pose-graph node
    map: ProbabilityGrid  # all node scans re-inserted at their optimised poses
    metrics: dict


def _se2_apply(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """[N, 2] ``points`` moved by ``pose`` (x, y, theta)."""
    return transform_points(se2_to_matrix(*pose), points)


def _mid_sweep_to_stamp(stamps: np.ndarray, sweep: np.ndarray, poses: np.ndarray) -> (
        np.ndarray):
    """[S, 3] poses at the scans' stamps from ``poses`` [S, 3] at mid-sweep (where
    ``sweep`` [S] is not 0; negative: beams ran back in time): the first half of each
    sweep undone at the velocity of that time, interpolated between the motion from the
    previous scan and to the next."""
    out = poses.copy()
    n = len(poses)
    if n < 2 or not np.any(sweep != 0):
        return out
    t_mid = stamps + sweep / 2  # [S]
    step = se2_between(poses[:-1], poses[1:])  # [S-1, 3]
    # At least the usual spacing: a stamp glitched early would make a velocity of ten
    # times the real one from a tenth of the time (the sweep is timed by its beams).
    dt = np.diff(t_mid)  # [S-1]
    vel = step / np.maximum(dt, np.median(dt))[:, None]  # [S-1, 3] per second, earlier frame
    centre = (t_mid[:-1] + t_mid[1:]) / 2  # [S-1] time each velocity holds at
    k = np.flatnonzero(sweep != 0)
    t = stamps[k] + sweep[k] / 4  # [K] the middle of the half sweep to undo
    v = np.stack([np.interp(t, centre, vel[:, i]) for i in range(3)], -1)  # [K, 3]
    out[k] = se2_compose(poses[k], se2_inverse(v * (sweep[k, None] / 2)))
    return out


def _adaptive_filter(points: np.ndarray, max_points: int, start: float) -> np.ndarray:
    """Coarsen a voxel filter until at most ``max_points`` remain (Cartographer's adaptive
    filter keeps matching cost bounded whatever the scanner's beam count)."""
    if len(points) <= max_points:
        return points
    size = start
    out = voxel_filter(points, size)
    while len(out) > max_points:
        size *= 1.5
        out = voxel_filter(points, size)
    return out


class LidarSlam2D:
    """Incremental 2D SLAM: feed ``add_scan`` in time order, then call ``finish``."""

    def __init__(self, config: Slam2DConfig | None = None,
                 T_base_laser: np.ndarray | None = None) -> None:
        self.config = config or Slam2DConfig()
        c = self.config
        T = np.eye(4) if T_base_laser is None else np.asarray(T_base_laser, dtype=np.float64)
        if T.shape != (4, 4):
            raise ValueError(f"T_base_laser must be 4x4, got {T.shape}")
        if abs(T[2, 2]) < 0.99:
            raise ValueError("the laser plane must be horizontal (T_base_laser tilts it)")
        # Points (x, y, 0) of the laser map to base x-y through the top-left 2x2 block; it
        # is a reflection for an upside-down laser, which this handles without special cases.
        self._T_base_laser = T
        self._A = T[:2, :2].copy()  # [2, 2]
        self._sensor = T[:2, 3].copy()  # [2] laser origin in the base frame
        grid_kwargs = dict(
            resolution=c.grid.resolution,
            hit_probability=c.grid.hit_probability,
            miss_probability=c.grid.miss_probability,
            min_probability=c.grid.min_probability,
            max_probability=c.grid.max_probability,
        )
        self.submaps = ActiveSubmaps(c.submaps.num_range_data, grid_kwargs)
        self.graph = PoseGraph2D()
        self.loop = LoopCloser(c.loop_closure, c.grid.resolution, c.grid.matching_sigma_m)
        self.nodes: list[Node] = []
        # Per accepted scan: stamp, node it hangs off, pose relative to that node.
        self._scan_stamps: list[float] = []
        self._scan_sweep: list[float] = []  # seconds; a de-skewed scan's pose is mid-sweep
        self._scan_ref: list[int] = []
        self._scan_rel: list[np.ndarray] = []
        self._scan_is_node: list[bool] = []
        self._last_stamp: float | None = None
        self._last_local: np.ndarray | None = None
        self._last_odom: np.ndarray | None = None
        self._last_delta: np.ndarray | None = None  # [3] last scan-to-scan motion
        self._last_moving: np.ndarray | None = None  # [3] last non-stationary node's local
        self._last_dt = 0.0  # seconds the last motion took
        self._recent_stamps: deque[float] = deque(maxlen=21)  # for the usual scan spacing
        self._recent_scores: deque[float] = deque(maxlen=20)  # scan-only search scores
        self._T_global_local = np.zeros(3)
        self._nodes_since_opt = 0
        self._newly_finished: list[Submap] = []  # searched for old nodes at the next step
        self.warnings: Counter[str] = Counter()
        self.counts: Counter[str] = Counter()
        self.timings: Counter[str] = Counter()
        self._finished = False

    # ------------------------------------------------------------------ input

    def _warn(self, key: str, message: str) -> None:
        if self.warnings[key] == 0:
            log.warning("%s (further ones are counted in metrics as %s)", message, key)
        self.warnings[key] += 1

    def _preprocess(self, scan: ScanLike) -> tuple[np.ndarray, np.ndarray] | None:
        """(hits [N, 2], free ends [M, 2]) in the base frame, or None for a bad scan."""
        c = self.config.scan
        stored = np.asarray(scan.ranges)
        r = stored.astype(np.float64)
        ang = scan.angle_min + np.arange(len(r)) * scan.angle_increment
        # The limits as the ranges hold them: a driver's no-return written as range_max
        # 5.6 is 5.5999999 in float32, which read in float64 became a wall at the
        # scanner's reach, moving with the robot (tracking 4.4 m RMS off).
        cast = stored.dtype.type if stored.dtype.kind == "f" else np.float64
        with np.errstate(invalid="ignore", over="ignore"):
            finite = np.isfinite(r)
            rmin = max(float(cast(scan.range_min)), c.min_range)
            rmax = float(cast(scan.range_max)) if np.isfinite(scan.range_max) else np.inf
            # A reading at (or past) the sensor's range_max is a beam without return:
            # CARMEN and many drivers report no-return as exactly range_max.
            no_return = (r == np.inf) | (finite & (r >= rmax))
            # A zero is no return too, whatever the limits say (LaserScan.valid_mask): with
            # scan.min_range 0 a driver's zeros were walls at the laser, moving with it.
            ok = finite & (r > 0) & (r >= rmin) & ~no_return
            hit = ok & (r <= c.max_range)
            free = no_return | (ok & (r > c.max_range))
        bad = int(len(r) - ok.sum() - no_return.sum())
        if bad:
            self.counts["invalid_beams"] += bad
        n_hit = int(hit.sum())
        if n_hit < c.min_valid_beams:
            self._warn("scans_too_few_returns",
                       f"scan at {scan.stamp:.6f} has {n_hit} usable returns "
                       f"(< {c.min_valid_beams}); skipped")
            return None
        cs = np.stack([np.cos(ang), np.sin(ang)], -1)  # [B, 2]
        hits = (cs[hit] * r[hit, None]) @ self._A.T + self._sensor
        # Not past the sensor's own reach: a 4 m lidar's no-return says nothing at 5 m.
        free_len = min(c.missing_data_ray_length, c.max_range, rmax)
        if free_len > 0 and free.any():
            free_pts = (cs[free] * free_len) @ self._A.T + self._sensor
        else:
            free_pts = np.zeros((0, 2))
        return hits, free_pts

    def _sweep_motion(self, sweep_s: float, stamp: float, odom: np.ndarray | None) -> (
            np.ndarray | None):
        """(x, y, theta) of the base over a sweep of ``sweep_s`` seconds, in the base frame
        at the stamp, at the latest velocity (odometry's since the last scan, else the
        last scan-to-scan motion); None before any motion is known."""
        if odom is not None and self._last_odom is not None and self._last_stamp is not None:
            delta, dt = se2_between(self._last_odom, odom), stamp - self._last_stamp
        elif self._last_delta is not None and self._last_dt > 0:
            delta, dt = self._last_delta, self._last_dt
        else:
            return None
        return delta * (sweep_s / dt)  # first order: sweeps are short

    # ------------------------------------------------------------------ local SLAM

    def _predict(self, stamp: float, odom: np.ndarray | None) -> np.ndarray:
        assert self._last_local is not None and self._last_stamp is not None
        if odom is not None and self._last_odom is not None:
            return se2_compose(self._last_local, se2_between(self._last_odom, odom))
        return self._last_local.copy()

    def _match_field(self, grid: ProbabilityGrid, pred: np.ndarray, points: np.ndarray,
                     lin: float, ang: float, with_odom: bool) -> tuple[
                         np.ndarray, np.ndarray, GridPyramid]:
        """(field, its origin, search pyramid) of the submap cropped to where the scan can
        land from ``pred`` within the window: the box of its points at the prediction,
        grown by the largest shift the search can make (rotation included)."""
        lc = self.config.local
        res = grid.resolution
        w = int(np.ceil(lin / res))
        depth = max(0, int(np.floor(np.log2(max(w, 1)))) - 1)
        margin = lin + 6 * res + 4 * self.config.grid.matching_sigma_m
        if not with_odom and self._last_delta is not None:
            margin += float(np.hypot(*self._last_delta[:2])) + lc.motion_tiebreak_linear_window_m
        at_pred = _se2_apply(pred, points)
        r_max = float(np.sqrt((points**2).sum(1)).max())
        swing = r_max * min(2.0, 2.0 * np.sin(min(ang + np.radians(10), np.pi) / 2))
        lo_xy = np.maximum(at_pred.min(0) - swing, pred[:2] - r_max) - margin
        hi_xy = np.minimum(at_pred.max(0) + swing, pred[:2] + r_max) + margin
        lo = grid.cell_of(lo_xy[None])[0]
        hi = grid.cell_of(hi_xy[None])[0] + 1
        # Scan-only the search's window is wide and its prediction "stood still": there a
        # pose that puts returns off the map would win on unknown cells scored above free
        # space (Intel / ACES ATE 0.086 / 0.084 m -> 11.7 / 23.4 m), so only with odometry.
        u = lc.unknown_score if with_odom and lc.unknown_score > grid.p_min else None
        field, f_origin = grid.matching_field(self.config.grid.matching_sigma_m, lo, hi,
                                              unknown=u)
        return field, f_origin, GridPyramid(field, f_origin, res, depth, grid.p_min, w,
                                            pad_value=u)

    def _scan_match(self, pred: np.ndarray, points: np.ndarray, spread: float | None,
                    with_odom: bool, dt: float) -> tuple[np.ndarray, float]:
        sm = self.submaps.matching
        assert sm is not None
        lc = self.config.local
        grid = sm.grid
        res = grid.resolution
        full = (lc.scan_only_linear_window_m, np.radians(lc.scan_only_angular_window_deg))
        if with_odom:
            lin, ang = lc.linear_window_m, np.radians(lc.angular_window_deg)
        elif len(self._recent_scores) < (self._recent_scores.maxlen or 0):
            # The full window until the usual score is known: on the first scans every
            # score is low (the map is young), a wrong match's too.
            lin, ang = full
        else:
            lin = min(full[0], max(lc.linear_window_m, lc.scan_only_max_speed_m_s * dt))
            ang = min(full[1], np.radians(max(lc.angular_window_deg,
                                              lc.scan_only_max_turn_rate_deg_s * dt)))
        t0 = time.perf_counter()
        # Scan-only the pyramid also serves the motion tie-break's window below.
        pyr_lin = lin if with_odom else max(lin, lc.motion_tiebreak_linear_window_m)
        field, f_origin, pyr = self._match_field(grid, pred, points, pyr_lin, ang, with_odom)
        t1 = time.perf_counter()
        # Priors towards the prediction only mean something with odometry. Without it the
        # prediction is "stood still", and pulling towards it biases the match backwards
        # along corridors (measured on the Radish logs, docs/slam2d.md).

        def search(pyramid: GridPyramid, lin: float, ang: float) -> SearchResult:
            return correlative_search(
                pyramid, points, pred, lin, ang, np.radians(lc.angular_step_deg),
                min_score=0.0,
                translation_cost=lc.translation_delta_cost_weight if with_odom else 0.0,
                rotation_cost=(lc.rotation_delta_cost_weight if with_odom
                               else lc.scan_only_rotation_delta_cost_weight),
                max_candidates=lc.max_candidates,
            )

        if with_odom:
            # The prediction is good to centimetres: the returns on surfaces the submap has
            # not seen are told apart there. (Scan-only, from "stood still", they are not:
            # leaving points out at the search's pose took the Intel / ACES ATE from 0.086 /
            # 0.084 m to 0.112 / 0.188 m.)
            points = self._seen_points(grid, pred, points)
        found = search(pyr, lin, ang)
        if not with_odom:
            usual = float(np.median(self._recent_scores)) if self._recent_scores else 0.0
            if (lin < full[0] or ang < full[1]) and \
                    found.score < lc.scan_only_retry_score_ratio * usual:
                # The robot moved more than the bound allows (a fast turn, a stamp off):
                # a match far below the usual score is searched again with the full window.
                wide_field = self._match_field(grid, pred, points, *full, with_odom)
                wide = search(wide_field[2], *full)
                self.counts["scan_only_window_retries"] += 1
                if wide.score > found.score:
                    found, (field, f_origin, pyr) = wide, wide_field
            self._recent_scores.append(found.score)
        if not with_odom and lc.motion_tiebreak_margin > 0 and self._last_delta is not None:
            # Repeat the last forward advance, not its turn: the turn ends with the bend.
            repeat = se2_compose(pred, np.array([max(self._last_delta[0], 0.0), 0.0, 0.0]))
            alt = correlative_search(
                pyr, points, repeat, lc.motion_tiebreak_linear_window_m,
                np.radians(lc.motion_tiebreak_angular_window_deg),
                np.radians(lc.angular_step_deg), min_score=0.0,
                rotation_cost=lc.scan_only_rotation_delta_cost_weight,
                max_candidates=lc.max_candidates)
            if alt.found and alt.score >= found.score - lc.motion_tiebreak_margin:
                if np.hypot(*(alt.pose[:2] - found.pose[:2])) > 2 * res:
                    self.counts["motion_tiebreaks"] += 1
                found = alt
        t2 = time.perf_counter()
        start = found.pose if found.found else pred
        target = pred if with_odom else start
        ref = refine(
            field, f_origin, res, points, start,
            prior_translation=target[:2], prior_rotation=float(target[2]),
            occupied_weight=lc.occupied_space_weight,
            translation_weight=(lc.translation_weight if with_odom
                                else lc.scan_only_translation_weight),
            rotation_weight=lc.rotation_weight if with_odom else lc.scan_only_rotation_weight,
            max_iterations=lc.max_iterations,
        )
        t3 = time.perf_counter()
        self.timings["local_pyramid_s"] += t1 - t0
        self.timings["local_search_s"] += t2 - t1
        self.timings["local_refine_s"] += t3 - t2
        pose = ref.pose.copy()
        score = ref.score
        if with_odom and spread is not None and spread < lc.degenerate_spread:
            held = self._hold_degenerate_direction(field, f_origin, points, pose, pred)
            if np.any(held != pose[:2]):
                pose[:2] = held
                score = float(interpolate(field, f_origin, res, _se2_apply(pose, points))[0]
                              .mean())
        pose[2] = wrap_angle(pose[2])
        return pose, score

    def _seen_points(self, grid: ProbabilityGrid, pose: np.ndarray,
                     points: np.ndarray) -> np.ndarray:
        """``points`` [N, 2] (base frame) less those that land, at ``pose``, on a surface
        the submap has not observed: their cell ``unseen_approach_cells`` cells back along
        the beam was never observed (``LocalMatchingOptions.unseen_approach_cells``). All
        of them when fewer than a quarter (or than ``scan.min_valid_beams``) would stay."""
        k = self.config.local.unseen_approach_cells
        if k <= 0 or len(points) == 0:
            return points
        world = _se2_apply(pose, points)
        ray = world - _se2_apply(pose, self._sensor[None])
        n = np.linalg.norm(ray, axis=1, keepdims=True)
        back = world - k * grid.resolution * ray / np.maximum(n, 1e-9)
        seen = grid.observed(back)
        kept = int(seen.sum())
        if kept == len(points) or kept < max(self.config.scan.min_valid_beams,
                                             len(points) // 4):
            return points
        self.counts["unseen_points_left_out"] += len(points) - kept
        return points[seen]

    def _hold_degenerate_direction(self, field: np.ndarray, f_origin: np.ndarray,
                                   points: np.ndarray, pose: np.ndarray,
                                   pred: np.ndarray) -> np.ndarray:
        """[2] the match's translation, moved to the prediction along a direction the
        scan does not constrain (solution remapping, Zhang et al., ICRA 2016)."""
        lc = self.config.local
        drop, v = weak_direction(field, f_origin, self.config.grid.resolution, points, pose)
        hold = float(np.clip(2.0 - 2.0 * drop / lc.degenerate_drop, 0.0, 1.0))
        if hold == 0.0:
            return pose[:2]
        self.counts["degenerate_matches"] += 1
        return pose[:2] + hold * v * float(v @ (pred[:2] - pose[:2]))

    def add_scan(self, scan: ScanLike, odometry: np.ndarray | None = None) -> np.ndarray | None:
        """Process one scan; returns its T_world_base as (x, y, theta), None if skipped
        (at mid-sweep for a de-skewed scan: ``finish`` gives every scan's at its stamp).

        ``odometry``: T_odom_base at the scan stamp, as [4, 4] or (x, y, theta).
        """
        if self._finished:
            raise RuntimeError("add_scan after finish()")
        t_start = time.perf_counter()
        stamp = float(scan.stamp)
        if not np.isfinite(stamp):
            self._warn("scans_bad_stamp", "scan with a non-finite stamp; skipped")
            return None
        if self._last_stamp is not None and stamp <= self._last_stamp:
            key = "scans_duplicate_stamp" if stamp == self._last_stamp else "scans_out_of_order"
            self._warn(key, f"scan at {stamp:.6f} is not after the previous one "
                            f"({self._last_stamp:.6f}); skipped")
            return None
        odom = None
        if odometry is not None:
            o = np.asarray(odometry, dtype=np.float64)
            if o.shape not in ((4, 4), (3,)):
                raise ValueError(f"odometry must be a [4, 4] T_odom_base or (x, y, theta), "
                                 f"got shape {list(o.shape)}")
            odom = se3_to_se2(o) if o.shape == (4, 4) else o.copy()
            if not np.all(np.isfinite(odom)):
                self._warn("odometry_non_finite", f"non-finite odometry at {stamp:.6f}; ignored")
                odom = None
        half: np.ndarray | None = None  # base motion over half the sweep
        sweep = 0.0  # seconds, when the pose is at mid-sweep
        if getattr(scan, "time_increment", 0.0) and isinstance(scan, LaserScan):
            motion = self._sweep_motion(scan.sweep_s, stamp, odom)
            ml = np.zeros(3)
            if motion is not None:
                sweep = scan.sweep_s
                self.counts["scans_deskewed"] += 1
                half = 0.5 * motion
                T_bl = self._T_base_laser
                ml = planar_motion(np.eye(4), inv_se3(T_bl) @ se2_to_se3(*motion) @ T_bl)
            scan = deskew_scan(scan, ml)
        pre = self._preprocess(scan)
        if pre is None:
            return None
        hits, free = pre  # in the base frame at the stamp (the first beam)
        spread: float | None = None  # normal_spread(hits), where a degeneracy test needs it
        self.counts["scans_used"] += 1
        if half is not None:
            # A de-skewed scan is placed at mid-sweep: an error in the assumed velocity
            # then bends both ends of the scan alike and leaves that pose unbiased, and
            # the velocity taken from those poses stays clean. (Placed at its first beam,
            # the pose takes half the error and the next velocity all of it, with the
            # opposite sign: scan-only SLAM oscillated, 0.39 m ATE.) ``finish`` moves the
            # poses back to the stamps with the velocity of both neighbours.
            back = se2_inverse(half)
            hits, free = _se2_apply(back, hits), _se2_apply(back, free)
        match_pts = _adaptive_filter(hits, self.config.scan.max_match_points,
                                     self.config.grid.resolution)

        if self._last_local is None:
            local = np.zeros(3)
            if odom is not None:
                # Start the world frame on the odometry frame so both read alike.
                self._T_global_local = odom.copy()
        else:
            pred = self._predict(stamp, odom)
            with_odom = odom is not None and self._last_odom is not None
            # The cheap test first: the score drop is only measured for flat scans. Kept on
            # the node for the loop-closure test.
            if with_odom and self.config.local.degenerate_drop > 0:
                spread = normal_spread(hits)
            # The time since the last scan, but at least the usual spacing (the mean over
            # the last 20: robust to a stamp glitched early, Intel has scans 0.01 s apart
            # with 34 deg turned, and to a driver that stamps scans in bunches): it sizes
            # the scan-only window and turns the last motion into the velocity de-skew uses.
            dt = stamp - float(self._last_stamp)  # type: ignore[arg-type]
            if len(self._recent_stamps) > 1:
                spacing = ((self._recent_stamps[-1] - self._recent_stamps[0])
                           / (len(self._recent_stamps) - 1))
                dt = max(dt, spacing)
            local, score = self._scan_match(pred, match_pts, spread, with_odom, dt)
            self.counts["local_score_sum"] += score
            self.counts["local_matches"] += 1
            self._last_delta = se2_between(self._last_local, local)
            self._last_dt = dt
        self._last_local = local
        self._last_stamp = stamp
        self._recent_stamps.append(stamp)
        self._last_odom = odom

        # Motion filter: a scan too close to the last node only gets a pose.
        mf = self.config.motion_filter
        stationary = False
        if self.nodes:
            last = self.nodes[-1]
            d = se2_between(last.local_pose, local)
            close = self._within_motion_filter(d)
            # Stationary: let through by the time limit alone and still within the
            # filter's distance and angle of the last node that moved there. Measured
            # from that node, not from the last one, a robot crawling less than
            # max_distance_m per max_time_s still gets searched nodes.
            if close and self._last_moving is not None:
                stationary = self._within_motion_filter(se2_between(self._last_moving, local))
            if close and stamp - last.stamp <= mf.max_time_s:
                self._scan_stamps.append(stamp)
                self._scan_sweep.append(sweep)
                self._scan_ref.append(last.index)
                self._scan_rel.append(d)
                self._scan_is_node.append(False)
                self.counts["scans_motion_filtered"] += 1
                self.timings["local_s"] += time.perf_counter() - t_start
                return se2_compose(self.graph.poses[last.vertex], d)
        node = self._add_node(stamp, local, hits, free, odom, stationary)
        node.spread = spread
        if not stationary:
            self._last_moving = local.copy()
        self._scan_sweep.append(sweep)
        self.timings["local_s"] += time.perf_counter() - t_start

        t_g = time.perf_counter()
        self._global_step(node)
        self.timings["global_s"] += time.perf_counter() - t_g
        return self.graph.poses[node.vertex].copy()

    def _within_motion_filter(self, d: np.ndarray) -> bool:
        """Whether the motion ``d`` (x, y, theta) is within the motion filter's distance
        and angle."""
        mf = self.config.motion_filter
        return bool(np.hypot(d[0], d[1]) <= mf.max_distance_m
                    and abs(d[2]) <= np.radians(mf.max_angle_deg))

    def _add_node(self, stamp: float, local: np.ndarray, hits: np.ndarray, free: np.ndarray,
                  odom: np.ndarray | None, stationary: bool = False) -> Node:
        pg = self.config.pose_graph
        c, s = np.cos(local[2]), np.sin(local[2])
        R = np.array([[c, -s], [s, c]])
        t_ins = time.perf_counter()
        idx = len(self.nodes)
        n_before = len(self.submaps.all)
        inserted, finished = self.submaps.insert(
            idx, R @ self._sensor + local[:2], hits @ R.T + local[:2],
            free @ R.T + local[:2], local)
        self.timings["insert_s"] += time.perf_counter() - t_ins
        vertex = self.graph.add_vertex(se2_compose(self._T_global_local, local))
        lc = self.config.loop_closure
        match_pts = _adaptive_filter(hits, lc.max_points, 2 * self.config.grid.resolution)
        node = Node(idx, stamp, local, vertex, hits.astype(np.float32),
                    free.astype(np.float32), match_pts, odom, stationary=stationary)
        self.counts["nodes_stationary"] += stationary
        self.nodes.append(node)
        self._scan_stamps.append(stamp)
        self._scan_ref.append(idx)
        self._scan_rel.append(np.zeros(3))
        self._scan_is_node.append(True)
        for sm in self.submaps.all[n_before:]:
            sm.vertex = self.graph.add_vertex(se2_compose(self._T_global_local, sm.local_pose))
        for sm in inserted:
            self.graph.add_edge(sm.vertex, vertex, se2_between(sm.local_pose, local),
                                pg.intra_submap_translation_weight,
                                pg.intra_submap_rotation_weight, kind=EDGE_INTRA)
            node.submaps.append(sm.index)
        if idx > 0:
            prev = self.nodes[idx - 1]
            if pg.local_slam_translation_weight > 0:
                self.graph.add_edge(prev.vertex, vertex, se2_between(prev.local_pose, local),
                                    pg.local_slam_translation_weight,
                                    pg.local_slam_rotation_weight, robust=pg.local_slam_loss,
                                    robust_scale=pg.local_slam_loss_scale, kind=EDGE_LOCAL)
            if odom is not None and prev.odom is not None and pg.odometry_translation_weight > 0:
                self.graph.add_edge(prev.vertex, vertex, se2_between(prev.odom, odom),
                                    pg.odometry_translation_weight,
                                    pg.odometry_rotation_weight, kind=EDGE_ODOM)
        for sm in finished:
            self.loop.on_submap_finished(sm, self.nodes)
        self._newly_finished.extend(finished)
        self.counts["nodes"] += 1
        return node

    # ------------------------------------------------------------------ global SLAM

    def _global_step(self, node: Node) -> None:
        if self.config.loop_closure.enabled:
            t0 = time.perf_counter()
            self._search_old_nodes(node.index)
            for sm in self.submaps.all:
                if not self._searchable(node) or not sm.finished or sm.index in node.submaps:
                    continue
                self._try_closure(node, sm)
            self.timings["loop_search_s"] += time.perf_counter() - t0
        self._nodes_since_opt += 1
        every = self.config.pose_graph.optimize_every_n_nodes
        if every and self._nodes_since_opt >= every:
            self._optimize(self.config.pose_graph.max_iterations)

    def _search_old_nodes(self, before: int) -> None:
        """Search the nodes older than ``before`` against the submaps finished since the
        last call (Cartographer's other direction). Without it a node is only ever
        constrained to submaps finished before it, so a scan that local SLAM placed
        wrongly (the spin at the start of Intel, a slide along a corridor) stays wrong
        inside its own submaps however often the robot comes back."""
        if not self.config.loop_closure.old_nodes:
            self._newly_finished.clear()
            return
        # ``old_nodes_skip`` leaves out the nodes just before the submap, which local SLAM
        # already ties to it through the overlapping predecessor submap.
        skip = self.config.loop_closure.old_nodes_skip
        while self._newly_finished:
            sm = self._newly_finished.pop(0)
            if not any(self._searchable(self.nodes[i]) for i in sm.nodes):
                continue  # made while standing still: the place of the node before it
            for n in self.nodes[:max(0, min(before, sm.nodes[0] - skip))]:
                if self.loop.saturated(sm.index):
                    break
                if self._searchable(n):
                    self._try_closure(n, sm)

    def _searchable(self, node: Node) -> bool:
        return self.config.loop_closure.stationary_nodes or not node.stationary

    def _try_closure(self, node: Node, sm: Submap, force: bool = False) -> bool:
        poses = self.graph.poses
        found = self.loop.maybe_search(node, sm, poses[sm.vertex], poses[node.vertex], force)
        if found is None:
            return False
        lc = self.config.loop_closure
        if found.weak_drop < lc.degenerate_drop:
            # Along a featureless corridor a match fixes the lateral offset and heading
            # but not the position along it: such a closure is as likely metres off as
            # right, and bends the map when it is wrong.
            self.counts["loop_closures_degenerate"] += 1
            return False
        self.graph.add_edge(sm.vertex, node.vertex, found.relative_pose, lc.translation_weight,
                            lc.rotation_weight, robust=lc.loss, robust_scale=lc.loss_scale,
                            kind=EDGE_LOOP)
        self.loop.accepted(sm.index)
        self.counts["loop_closures"] += 1
        return True

    def _optimize(self, iterations: int) -> None:
        rep = self.graph.optimize(iterations)
        self._nodes_since_opt = 0
        self.counts["optimizations"] += 1
        self.timings["optimize_s"] += rep.seconds
        # New nodes enter the world through the newest optimised submap's correction.
        sm = self.submaps.all[-1]
        self._T_global_local = se2_compose(self.graph.poses[sm.vertex],
                                           se2_inverse(sm.local_pose))
        log.debug("optimised %d vertices in %.3fs (%d its, cost %.3g -> %.3g, %d outliers)",
                  self.graph.num_vertices, rep.seconds, rep.iterations, rep.initial_cost,
                  rep.final_cost, rep.outlier_edges)
        self.counts["loop_outliers"] = rep.outlier_edges

    # ------------------------------------------------------------------ output

    def current_pose(self) -> np.ndarray | None:
        """T_world_base (x, y, theta) of the last accepted scan."""
        if not self._scan_stamps:
            return None
        ref = self.nodes[self._scan_ref[-1]]
        return se2_compose(self.graph.poses[ref.vertex], self._scan_rel[-1])

    def finish(self) -> SlamResult:
        """Final loop-closure pass and optimisation; the trajectory and the map."""
        if self._finished:
            raise RuntimeError("finish() called twice")
        self._finished = True
        t0 = time.perf_counter()
        for sm in self.submaps.finish_all():
            self.loop.on_submap_finished(sm, self.nodes)
            self._newly_finished.append(sm)
        if self.config.loop_closure.enabled:
            t_l = time.perf_counter()
            self._search_old_nodes(len(self.nodes))
            self.timings["loop_search_s"] += time.perf_counter() - t_l
        if self.nodes:
            self._optimize(self.config.pose_graph.final_max_iterations)
        self.timings["final_optimize_s"] += time.perf_counter() - t0
        t1 = time.perf_counter()
        stamps = np.array(self._scan_stamps)
        node_poses = self.graph.poses[[n.vertex for n in self.nodes]] if self.nodes else \
            np.zeros((0, 3))
        if len(stamps):
            poses = se2_compose(node_poses[np.array(self._scan_ref)], np.array(self._scan_rel))
            poses = _mid_sweep_to_stamp(stamps, np.array(self._scan_sweep), poses)
        else:
            poses = np.zeros((0, 3))
        grid = self.render_map(node_poses)
        self.timings["map_s"] += time.perf_counter() - t1
        T = np.stack([se2_to_se3(*p) for p in poses]) if len(poses) else np.zeros((0, 4, 4))
        traj = Trajectory(stamps, T, "world", "base_link")
        return SlamResult(traj, poses, np.array(self._scan_is_node, bool), grid,
                          self.metrics())

    def render_map(self, node_poses: np.ndarray | None = None) -> ProbabilityGrid:
        """All node scans inserted at their (optimised) world poses into one grid."""
        c = self.config
        if node_poses is None:
            node_poses = self.graph.poses[[n.vertex for n in self.nodes]]
        # Centred on the drive, not on the world origin: with odometry the world is the
        # odometry frame, which may start hundreds of metres (UTM: kilometres) away, and
        # the grid grew to span that (finish() ran out of memory).
        centre = ((node_poses[:, :2].min(0) + node_poses[:, :2].max(0)) / 2
                  if len(node_poses) else np.zeros(2))
        grid = ProbabilityGrid(c.map.resolution, c.map.hit_probability,
                               c.map.miss_probability, c.grid.min_probability,
                               c.grid.max_probability, center=(float(centre[0]),
                                                               float(centre[1])),
                               initial_size_m=40.0)
        for n, p in zip(self.nodes, node_poses, strict=True):
            cth, sth = np.cos(p[2]), np.sin(p[2])
            R = np.array([[cth, -sth], [sth, cth]])
            grid.insert(R @ self._sensor + p[:2], n.hits.astype(np.float64) @ R.T + p[:2],
                        n.free.astype(np.float64) @ R.T + p[:2])
        return grid

    def metrics(self) -> dict:
        t = self.timings
        m = {
            "scans_used": self.counts["scans_used"],
            "nodes": self.counts["nodes"],
            "scans_motion_filtered": self.counts["scans_motion_filtered"],
            "submaps": len(self.submaps.all),
            "loop_closures": self.counts["loop_closures"],
            "loop_closure_searches": self.loop.searches,
            "loop_closure_wide_searches": self.loop.wide_searches,
            "loop_closure_outliers": self.counts["loop_outliers"],
            "loop_closures_degenerate": self.counts["loop_closures_degenerate"],
            "loop_closures_ambiguous": self.loop.ambiguous,
            "nodes_stationary": self.counts["nodes_stationary"],
            "submaps_search_bounded": sum(self.loop.saturated(sm.index)
                                          for sm in self.submaps.all),
            "degenerate_matches": self.counts["degenerate_matches"],
            "optimizations": self.counts["optimizations"],
            "motion_tiebreaks": self.counts["motion_tiebreaks"],
            "scan_only_window_retries": self.counts["scan_only_window_retries"],
            "invalid_beams": self.counts["invalid_beams"],
            "scans_deskewed": self.counts["scans_deskewed"],
            # Over the scans matched (motion-filtered ones too, not the nodes alone: a robot
            # standing still reported a "mean" of 4.3 for scores of at most 0.9)
            "mean_local_score": (self.counts["local_score_sum"] / self.counts["local_matches"]
                                 if self.counts["local_matches"] else None),
        }
        m.update({f"skipped_{k}": v for k, v in sorted(self.warnings.items())})
        m.update({f"time_{k}": round(v, 3) for k, v in sorted(t.items())})
        return m

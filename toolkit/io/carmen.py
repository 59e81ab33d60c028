"""CARMEN logs (``FLASER``, ``ROBOTLASER1``, ``ODOM``; gzip or plain) and g2o files with
``ROBOTLASER1`` lines (``VERTEX_SE2`` / ``EDGE_SE2``), as in the Radish and Freiburg
collections.

Line formats (CARMEN ``logger`` documentation):

- ``FLASER n r1..rn x y theta odom_x odom_y odom_theta timestamp host logger_timestamp``;
  the beams span 180 deg from -90 deg (n = 180/181: 1 deg steps, 360/361: 0.5 deg).
- ``ROBOTLASER1 type start_angle fov resolution max_range accuracy remission_mode n
  r1..rn n_remissions rem1..remk laser_x laser_y laser_theta robot_x robot_y robot_theta
  tv rv forward_safety side_safety turn_axis timestamp host logger_timestamp``.
- ``ODOM x y theta tv rv accel timestamp host logger_timestamp``.

Which poses may be used is the caller's business: the poses stored in corrected logs
(Radish ``*-corrected``) and a g2o file's ``VERTEX_SE2`` are a finished SLAM solution,
never an input to a SLAM under test (see ``G2OLog.odometry``).
"""

from __future__ import annotations

import gzip
import io
import logging
import zipfile
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from toolkit.errors import InputError, MissingInputError
from toolkit.geometry import Trajectory, se2_compose, se2_to_se3
from toolkit.ingest.sync import longest_increasing
from toolkit.sensors import LaserScan

log = logging.getLogger(__name__)


class CarmenFormatError(InputError):
    """A malformed line; the message names the file and the line number."""


def _open_text(path: Path) -> Iterator[str]:
    """Lines of a plain, gzip or zip (first .g2o/.log/.clf member) text file.

    A compressed file cut short (a download or copy that stopped) is a ``CarmenFormatError``
    naming the file and how to keep its readable part, not a bare ``EOFError``.
    """
    try:
        yield from _read_lines(path)
    except (EOFError, gzip.BadGzipFile, zipfile.BadZipFile, zlib.error) as e:
        raise CarmenFormatError(
            f"{path}: the compressed file is cut short or corrupt ({e}); copy or download "
            f"it again, or keep its readable part with 'zcat {path} > {path.stem}' (a zip: "
            "'unzip -p') and give that file, deleting its last line if it was cut off"
        ) from None


def _bad_line(path: Path, lineno: int, line: str, kind: str, e: Exception) -> CarmenFormatError:
    # A last line without its newline is what a cut-off copy leaves: say so, or the user
    # hunts for a format problem in a file that is only incomplete.
    cut = "" if line.endswith("\n") else (
        "; the line has no end of line: the file looks truncated (copied or downloaded "
        "only in part): copy it again, or delete this last line")
    return CarmenFormatError(f"{path}:{lineno}: bad {kind} line: {e}{cut}")


def _read_lines(path: Path) -> Iterator[str]:
    with open(path, "rb") as fh:
        magic = fh.read(4)
    if magic[:2] == b"\x1f\x8b":
        with gzip.open(path, "rt", encoding="latin-1") as fh:
            yield from fh
    elif magic == b"PK\x03\x04":
        with zipfile.ZipFile(path) as zf:
            names = [n for n in zf.namelist() if not n.startswith("__MACOSX")
                     and n.lower().endswith((".g2o", ".log", ".clf", ".txt", ".gz"))]
            # A log's own suffixes first: a README.txt beside intel.log was read as the log.
            names.sort(key=lambda n: n.lower().endswith((".txt", ".gz")))
            if not names:
                raise CarmenFormatError(f"{path}: zip holds no .g2o/.log/.clf member")
            with zf.open(names[0]) as raw:
                data = raw.read()
            if data[:2] == b"\x1f\x8b":
                data = gzip.decompress(data)
            yield from io.StringIO(data.decode("latin-1"))
    else:
        with open(path, encoding="latin-1") as fh:
            yield from fh


def _pose(values: list[str], what: str, finite: bool = True) -> np.ndarray:
    """[3] x, y, theta of a line's pose fields. Python reads 'nan' and 'inf' as numbers: a
    non-finite pose went into odometry.tum or the reference poses, and the converted
    sequence was refused by the next stage, naming that file instead of this line.
    ``finite=False`` (odometry fields): returned as read, for the ingest to leave out and
    count - one glitched odometry reading refused the whole log."""
    p = np.array([float(v) for v in values], dtype=np.float64)
    if len(p) != 3:
        raise ValueError(f"{what}: {len(p)} numbers, expected x y theta")
    if finite and not np.all(np.isfinite(p)):
        raise ValueError(f"{what} {p.tolist()} is not finite")
    return p


def _ranges(values: list[str], max_range: float) -> np.ndarray:
    r = np.array(values, dtype=np.float32)
    # CARMEN has no invalid marker but zero/negative readings; the project's LaserScan
    # marks invalid as non-finite, never zero. A reading at or past max_range is a beam
    # without return, +inf as in REP 117 (free space, no surface).
    r[~(r > 0)] = np.nan
    r[r >= max_range] = np.inf
    return r


def flaser_angles(n: int) -> tuple[float, float]:
    """(angle_min, angle_increment) of an n-beam FLASER line, which carries no angles: the
    beam count says the scanner's mode, as CARMEN's own reader guesses it (readlog.c).
    180/181 and 360/361 beams: 180 deg from -90 deg, 1 or 0.5 deg apart; 400/401 beams: a
    SICK LMS at 0.25 deg, which scans 100 deg, centred ahead. Any other count is taken as
    180 deg (``flaser_fov_known`` says whether it was guessed so)."""
    if n in (400, 401):
        inc = np.pi / 720
        return float(-inc * (n - 1) / 2), float(inc)
    inc = np.pi / (n - 1) if n % 2 == 1 else np.pi / n
    return -np.pi / 2, float(inc)


def flaser_fov_known(n: int) -> bool:
    """Whether an n-beam FLASER line's field of view is known from its beam count."""
    return n in (180, 181, 360, 361, 400, 401)


@dataclass
class CarmenLog:
    """The laser scans and odometry of a CARMEN log, in file order."""

    path: Path
    scans: list[LaserScan]
    scan_poses: np.ndarray  # [S, 3] pose stored with each scan (laser pose; may be corrected)
    # [S, 3] odometry (robot) pose stored with each scan; may be non-finite (a glitch),
    # left for the ingest to skip and count
    scan_odometry: np.ndarray
    odom_stamps: np.ndarray  # [K] ODOM line stamps
    odom_poses: np.ndarray  # [K, 3] ODOM line poses, non-finite where the line's are
    T_base_laser: np.ndarray  # [4, 4]
    params: dict[str, str] = field(default_factory=dict)
    scan_lines: list[str] = field(default_factory=list)  # [S] "FLASER" or "ROBOTLASER1"
    scan_linenos: list[int] = field(default_factory=list)  # [S] file line, named in errors

    @property
    def duration_s(self) -> float:
        st = [s.stamp for s in self.scans]
        return float(max(st) - min(st)) if st else 0.0

    def reference(self) -> Trajectory:
        """The poses stored with the scans as T_world_base (for corrected logs: the
        reference solution to evaluate against, not an input). Out-of-order and duplicate
        stamps are dropped: the longest increasing run of them is kept, as for the scans
        (keeping whatever came after the last kept stamp, one stamp glitched into the
        future cut off every pose after it)."""
        stamps = np.array([s.stamp for s in self.scans])
        keep = longest_increasing(stamps)
        poses = np.stack([se2_to_se3(*p) for p in self.scan_poses[keep]]) @ np.linalg.inv(
            self.T_base_laser) if keep.any() else np.zeros((0, 4, 4))
        return Trajectory(stamps[keep], poses, "world", "base_link")


def _parse_robotlaser1(f: list[str], robot_finite: bool = True) -> tuple[
    LaserScan, np.ndarray, np.ndarray
]:
    """The scan, laser pose [3] and robot pose [3] of a line; ``robot_finite=False``: the
    robot pose (a log's odometry) as read, as ``_pose``'s ``finite``."""
    start, fov, res, max_range = (float(v) for v in f[2:6])
    n = int(f[8])
    ranges = _ranges(f[9 : 9 + n], max_range)
    k = 9 + n
    n_rem = int(f[k])
    k += 1 + n_rem
    laser = _pose(f[k : k + 3], "laser pose (laser_x laser_y laser_theta)")
    robot = _pose(f[k + 3 : k + 6], "robot pose (x y theta)", finite=robot_finite)
    stamp = float(f[k + 11])
    if len(ranges) != n:
        raise ValueError(f"{len(ranges)} ranges, expected {n}")
    del fov
    scan = LaserScan(stamp=stamp, ranges=ranges, angle_min=start, angle_increment=res,
                     range_min=0.0, range_max=max_range)
    return scan, laser, robot


def read_carmen(path: Path | str, max_range: float = 50.0) -> CarmenLog:
    """Read FLASER / ROBOTLASER1 / ODOM lines (other messages are skipped).

    ``max_range``: range_max given to FLASER scans (the line does not carry it); readings
    at or past it are beams without return (SICK reports 81.9 m, logs often 50 m).
    """
    path = Path(path)
    if not path.exists():
        raise MissingInputError(f"{path}: CARMEN log not found")
    scans: list[LaserScan] = []
    poses: list[np.ndarray] = []
    odoms: list[np.ndarray] = []
    o_t: list[float] = []
    o_p: list[list[float]] = []
    params: dict[str, str] = {}
    laser_offsets: list[np.ndarray] = []
    guessed: set[int] = set()  # FLASER beam counts of no known scanner, warned about
    kinds: list[str] = []
    linenos: list[int] = []
    for lineno, line in enumerate(_open_text(path), 1):
        f = line.split()
        if not f or f[0].startswith("#"):
            continue
        try:
            if f[0] == "FLASER":
                n = int(f[1])
                if n < 2:
                    raise ValueError(f"{n} beams; a scan needs at least 2 to have an angle "
                                     "step (delete the line, or fix the beam count)")
                ranges = _ranges(f[2 : 2 + n], max_range)
                if len(ranges) != n:
                    raise ValueError(f"{len(ranges)} ranges, expected {n}")
                rest = f[2 + n :]
                amin, inc = flaser_angles(n)
                if not flaser_fov_known(n) and n not in guessed:
                    guessed.add(n)
                    log.warning("%s:%d: FLASER lines of %d beams carry no angles and no "
                                "scanner known to CARMEN has that count: read as 180 deg "
                                "from -90 deg (%.3f deg apart); if the scanner covers "
                                "another angle, convert the log to ROBOTLASER1 lines",
                                path, lineno, n, np.degrees(inc))
                scans.append(LaserScan(stamp=float(rest[6]), ranges=ranges, angle_min=amin,
                                       angle_increment=inc, range_min=0.0,
                                       range_max=max_range))
                kinds.append(f[0])
                linenos.append(lineno)
                poses.append(_pose(rest[0:3], "laser pose (x y theta)"))
                odoms.append(_pose(rest[3:6], "odometry pose (odom_x odom_y odom_theta)",
                                   finite=False))
            elif f[0] == "ROBOTLASER1":
                # The robot pose is the log's odometry: a glitched one is skipped and
                # counted by the ingest, as a FLASER line's; the mount is the median of
                # the other lines' offsets.
                scan, laser, robot = _parse_robotlaser1(f, robot_finite=False)
                scans.append(scan)
                kinds.append(f[0])
                linenos.append(lineno)
                poses.append(laser)
                odoms.append(robot)
                if np.isfinite(robot).all():
                    laser_offsets.append(_laser_offset(laser, robot))
            elif f[0] == "ODOM":
                o_p.append(_pose(f[1:4], "odometry pose (x y theta)", finite=False).tolist())
                o_t.append(float(f[7]))
            elif f[0] == "PARAM" and len(f) >= 3:
                params[f[1]] = f[2]
        except (ValueError, IndexError) as e:
            raise _bad_line(path, lineno, line, f[0], e) from None
    T_base_laser = np.eye(4)
    if laser_offsets:
        T_base_laser = _median_offset(laser_offsets)
    else:
        if "ROBOTLASER1" in kinds:
            log.warning("%s: no ROBOTLASER1 line has a finite robot pose, so the laser's "
                        "mount is not known from them: taken from PARAM "
                        "robot_frontlaser_offset, or the robot's origin", path)
        if "robot_frontlaser_offset" in params:
            T_base_laser[0, 3] = float(params["robot_frontlaser_offset"])
    return CarmenLog(
        path=path,
        scans=scans,
        scan_poses=np.array(poses).reshape(-1, 3),
        scan_odometry=np.array(odoms).reshape(-1, 3),
        odom_stamps=np.array(o_t, dtype=np.float64),
        odom_poses=np.array(o_p, dtype=np.float64).reshape(-1, 3),
        T_base_laser=T_base_laser,
        params=params,
        scan_lines=kinds,
        scan_linenos=linenos,
    )


def _median_offset(offsets: list) -> np.ndarray:
    """T_base_laser [4, 4] from per-line (x, y, yaw) offsets [N, 3]: the median of x and y,
    the heading of the median direction (a laser facing backwards logs +pi-e and -pi+e;
    the median yaw of an even split was 0, forwards)."""
    o = np.asarray(offsets, dtype=np.float64)
    yaw = np.arctan2(np.median(np.sin(o[:, 2])), np.median(np.cos(o[:, 2])))
    return se2_to_se3(float(np.median(o[:, 0])), float(np.median(o[:, 1])), float(yaw))


def _laser_offset(laser: np.ndarray, robot: np.ndarray) -> np.ndarray:
    """Laser pose in the robot frame from the two world poses of a ROBOTLASER1 line."""
    c, s = np.cos(robot[2]), np.sin(robot[2])
    d = laser[:2] - robot[:2]
    return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1],
                     (laser[2] - robot[2] + np.pi) % (2 * np.pi) - np.pi])


# ---------------------------------------------------------------------------- g2o


@dataclass
class G2OLog:
    """A g2o pose graph with laser scans attached to (some of) its vertices."""

    path: Path
    vertex_ids: np.ndarray  # [V]
    vertex_poses: np.ndarray  # [V, 3] as written: for killian.g2o a corrected solution
    edges: np.ndarray  # [E, 2] int (i, j)
    edge_measurements: np.ndarray  # [E, 3] (x, y, theta) of j in i
    # [E, 6] upper triangle of the information matrix; NaN where the line gives none
    edge_information: np.ndarray
    scans: list[LaserScan]
    scan_vertex: np.ndarray  # [S] vertex id each scan belongs to
    scan_laser_poses: np.ndarray  # [S, 3] ROBOTLASER1 laser pose (corrected too)
    T_base_laser: np.ndarray  # [4, 4]
    scan_linenos: list[int] = field(default_factory=list)  # [S] file line, named in errors

    @property
    def duration_s(self) -> float:
        st = [s.stamp for s in self.scans]
        return float(max(st) - min(st)) if st else 0.0

    def sequential_edges(self) -> np.ndarray:
        """[E] bool: edges from a vertex to the next vertex id of the file (odometry; the
        ids need not be consecutive numbers, 0 10 20 ... is a chain too); the others are
        someone's loop closures."""
        ids = np.unique(self.vertex_ids)  # [V] sorted
        if len(ids) < 2 or len(self.edges) == 0:
            return np.zeros(len(self.edges), dtype=bool)
        pos = np.searchsorted(ids, self.edges[:, 0])
        has_next = (pos < len(ids) - 1) & (ids[np.minimum(pos, len(ids) - 1)] == self.edges[:, 0])
        nxt = ids[np.minimum(pos + 1, len(ids) - 1)]
        return has_next & (self.edges[:, 1] == nxt)

    def odometry(self) -> Trajectory:
        """T_odom_base at the scan stamps: the sequential ``EDGE_SE2`` chain dead-reckoned
        from the identity. This, not ``vertex_poses``, is the raw odometry input."""
        seq = self.sequential_edges()
        step = {int(i): z for (i, _), z in zip(self.edges[seq], self.edge_measurements[seq],
                                               strict=True)}
        vids = np.sort(self.scan_vertex)
        ids = np.unique(self.vertex_ids)
        chain = ids[(ids >= vids[0]) & (ids <= vids[-1])]  # the vertices from first to last scan
        pose = {int(vids[0]): np.zeros(3)}
        cur = np.zeros(3)
        for a, b in zip(chain[:-1].tolist(), chain[1:].tolist(), strict=True):
            if a not in step:
                raise CarmenFormatError(
                    f"{self.path}: no odometry edge {a} -> {b} (the chain of EDGE_SE2 from "
                    f"each vertex to the next is the odometry)")
            cur = se2_compose(cur, step[a])
            pose[b] = cur
        stamps = np.array([s.stamp for s in self.scans])
        P = np.stack([se2_to_se3(*pose[int(v)]) for v in self.scan_vertex])
        o = np.argsort(stamps, kind="stable")
        keep = longest_increasing(stamps[o])
        return Trajectory(stamps[o][keep], P[o][keep], "odom", "base_link")

    def reference(self) -> Trajectory:
        """The written vertex poses at the scan stamps (a corrected solution)."""
        idx = {int(v): k for k, v in enumerate(self.vertex_ids)}
        stamps = np.array([s.stamp for s in self.scans])
        P = np.stack([se2_to_se3(*self.vertex_poses[idx[int(v)]]) for v in self.scan_vertex])
        o = np.argsort(stamps, kind="stable")
        keep = longest_increasing(stamps[o])
        return Trajectory(stamps[o][keep], P[o][keep], "world", "base_link")


def read_g2o(path: Path | str) -> G2OLog:
    """Read ``VERTEX_SE2``, ``EDGE_SE2`` and ``ROBOTLASER1`` lines (plain, gzip or zip).

    A ``ROBOTLASER1`` line belongs to the ``VERTEX_SE2`` line before it.
    """
    path = Path(path)
    if not path.exists():
        raise MissingInputError(f"{path}: g2o file not found")
    vids: list[int] = []
    vposes: list[list[float]] = []
    eij: list[tuple[int, int]] = []
    ez: list[list[float]] = []
    einfo: list[list[float]] = []
    scans: list[LaserScan] = []
    svert: list[int] = []
    slaser: list[np.ndarray] = []
    linenos: list[int] = []
    offsets: list[np.ndarray] = []
    for lineno, line in enumerate(_open_text(path), 1):
        f = line.split()
        if not f or f[0].startswith("#"):
            continue
        try:
            if f[0] == "VERTEX_SE2":
                vids.append(int(f[1]))
                vposes.append(_pose(f[2:5], "vertex pose (x y theta)").tolist())
            elif f[0] == "EDGE_SE2":
                eij.append((int(f[1]), int(f[2])))
                ez.append(_pose(f[3:6], "edge measurement (dx dy dtheta)").tolist())
                info = [float(v) for v in f[6:12]]
                # Some or none: a line of 1 to 5 failed later as a bare ValueError naming
                # no line, and edges all without one gave 0 rows for E edges.
                if len(info) not in (0, 6):
                    raise ValueError(f"{len(info)} information numbers, expected the 6 of "
                                     "its upper triangle (I11 I12 I13 I22 I23 I33) or none")
                einfo.append(info or [np.nan] * 6)
            elif f[0] == "ROBOTLASER1":
                if not vids:
                    raise ValueError("ROBOTLASER1 before any VERTEX_SE2")
                scan, laser, robot = _parse_robotlaser1(f)
                scans.append(scan)
                linenos.append(lineno)
                svert.append(vids[-1])
                slaser.append(laser)
                offsets.append(_laser_offset(laser, robot))
        except (ValueError, IndexError) as e:
            raise _bad_line(path, lineno, line, f[0], e) from None
    T_base_laser = _median_offset(offsets) if offsets else np.eye(4)
    return G2OLog(
        path=path,
        vertex_ids=np.array(vids, dtype=np.int64),
        vertex_poses=np.array(vposes, dtype=np.float64).reshape(-1, 3),
        edges=np.array(eij, dtype=np.int64).reshape(-1, 2),
        edge_measurements=np.array(ez, dtype=np.float64).reshape(-1, 3),
        edge_information=np.array(einfo, dtype=np.float64).reshape(-1, 6),
        scans=scans,
        scan_vertex=np.array(svert, dtype=np.int64),
        scan_laser_poses=np.array(slaser).reshape(-1, 3),
        T_base_laser=T_base_laser,
        scan_linenos=linenos,
    )

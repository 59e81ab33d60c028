"""What a reader hands the converter: a recording indexed but not yet loaded.

A reader (``toolkit.io.rosbag``, ``toolkit.io.tum_rgbd``, ``toolkit.io.carmen_ingest``,
or a sequence folder) makes one cheap pass over its input and returns a ``Recording``:
the rig, all scans (small), the stamps of every candidate camera frame and depth image,
odometry and ground truth. Pixels are loaded later, only for the frames the sync plan
keeps, through ``Recording.load`` - so a recording never sits in memory whole, and a
resumed conversion reads only what is still missing.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from toolkit.camera import PinholeCamera
from toolkit.errors import InputError
from toolkit.geometry import Trajectory
from toolkit.sensors import LaserScan, Rig


class IngestError(InputError):
    """An input cannot be converted. The message names the file, topic or field, and the fix."""


@dataclass
class FrameData:
    """Pixels of one kept camera frame, as the converter writes them."""

    stamp: float
    image: np.ndarray | None = None  # [H, W, 3] RGB uint8
    image_path: Path | None = None  # a PNG copied verbatim instead of ``image``
    image_jpeg: bytes | None = None  # the JPEG ``image`` came from, kept where exact
    depth: np.ndarray | None = None  # [H, W] float32 metres, 0 = invalid
    mask: np.ndarray | None = None  # [H, W] bool, dynamic pixels
    # 16-bit source samples: "scaled" to 8 bits (255/65535), or "clipped" at 255 by the
    # recording's JPEG codec (toolkit.io.rosbag.jpeg_of_16bit); None: 8-bit
    from_16bit: str | None = None
    peak_16bit: int = 0  # brightest 16-bit sample of a scaled frame


# (frame index, depth index or -1) pairs in stamp order -> their pixels in the same order.
FrameLoader = Callable[[Sequence[tuple[int, int]]], Iterator[FrameData]]


@dataclass
class Recording:
    """A recording after the reader's index pass (see the module docstring)."""

    name: str
    source: str  # what it came from, for meta.yaml ("rosbag run.bag", ...)
    rig: Rig
    scans: list[LaserScan]
    frame_stamps: np.ndarray  # [F] candidate camera frames, strictly increasing
    load: FrameLoader
    depth_stamps: np.ndarray | None = None  # [D] depth images, strictly increasing
    odometry: Trajectory | None = None  # T_odom_base
    groundtruth: Trajectory | None = None  # T_world_base
    has_camera: bool = True
    meta: dict[str, Any] = field(default_factory=dict)  # goes into meta.yaml
    dropped: dict[str, int] = field(default_factory=dict)  # messages dropped while indexing
    # Odometry messages left out as no pose (non-finite, zero quaternion): source (topic,
    # "ODOM lines") -> ``skipped_record``'s dict, for meta.yaml, metrics and the report.
    skipped: dict[str, dict[str, Any]] = field(default_factory=dict)
    # tf transforms that were no rigid motion, skipped: "parent -> child" -> count (bags).
    tf_skipped: dict[str, int] = field(default_factory=dict)
    scan_dynamic: np.ndarray | None = None  # [S, B] bool (sequence folders only)
    # The scans are made from the depth images (TUM RGB-D's virtual lidar): the depth
    # stream is then the lidar's clock and keeps its stamps when the camera's delay
    # (sync.camera_delay_s) is taken out of the colour stamps.
    depth_is_scan_clock: bool = False
    # Camera delay already taken out of frame_stamps (a sequence folder converted before
    # with sync.camera_delay_s): sync.camera_delay_s is the total against the raw stamps.
    camera_delay_applied_s: float = 0.0
    # Extra writes on the SequenceWriter, given the source frames kept [F] (in order).
    finish: Callable[[Any, np.ndarray], None] | None = None


# Odometry is refused when fewer than this share of its messages are poses. A driver's
# few bad messages (before its first fix, a glitch) are left out; one that fails more
# often than it works is broken, and the poses between its failures are no prior to
# trust - nor should a mostly empty odometry be reported as "odometry: yes".
MIN_VALID_ODOMETRY = 0.5
STAMPS_SHOWN = 5  # skipped messages' stamps named in the warning and the record


def skipped_record(where: str, total: int, bad_stamps_s: Sequence[float], reason: str,
                   fix: str) -> dict[str, Any] | None:
    """The record of ``len(bad_stamps_s)`` of ``total`` odometry messages that are no
    pose (None when there are none); ``IngestError`` when fewer than
    ``MIN_VALID_ODOMETRY`` of them are poses. ``reason``: what was wrong with the first
    one (field and value); ``fix``: how to go on without this odometry."""
    n = len(bad_stamps_s)
    if n == 0:
        return None
    shown = ", ".join(f"{t:.6f}" for t in bad_stamps_s[:STAMPS_SHOWN]) + (
        ", ..." if n > STAMPS_SHOWN else "")
    good = total - n
    if good < MIN_VALID_ODOMETRY * total:
        raise IngestError(
            f"{where}: {n} of {total} messages are no pose ({reason}; stamps {shown} s): "
            f"only {good} remain, under the {MIN_VALID_ODOMETRY:.0%} an odometry must keep "
            f"to be used (its driver fails more often than it works). Fix: {fix}")
    return {"count": n, "of": total, "first_stamps_s": [round(float(t), 6)
                                                        for t in bad_stamps_s[:STAMPS_SHOWN]],
            "first_reason": reason}


def note_skipped_gaps(record: dict[str, Any], odometry: Trajectory, valid_t: np.ndarray,
                      kept: np.ndarray, before: np.ndarray, where: str,
                      log: logging.Logger) -> None:
    """Add to ``record`` the gaps the skipped messages leave in ``odometry`` and warn.

    ``valid_t`` [V]: stamps of the valid messages in message order; ``kept`` [V] bool: those
    in ``odometry`` (others were dropped for their stamps); ``before`` [B]: for each skipped
    message, how many valid messages came before it. A gap is the time between the kept
    messages either side of a run of skipped ones; the SLAM interpolates the odometry only
    across gaps up to ``Trajectory.gap_limit_s`` (``odometry_at`` uses ``covers``) and
    matches the scans in a longer one without it - which the warning says, so a dead
    odometry for minutes is not taken for a smooth one."""
    K = np.flatnonzero(kept)  # [N] indices into valid_t of the poses kept
    pos = np.searchsorted(K, np.asarray(before, dtype=np.int64))  # [B]
    inner = (pos > 0) & (pos < len(K))  # skipped runs with a kept pose on both sides
    pairs = np.unique(np.stack([K[pos[inner] - 1], K[pos[inner]]], axis=1), axis=0) \
        if inner.any() else np.zeros((0, 2), np.int64)  # [G, 2]
    gaps = valid_t[pairs[:, 1]] - valid_t[pairs[:, 0]] if len(pairs) else np.zeros(0)  # [G]
    limit = odometry.gap_limit_s()
    long = gaps > limit
    record["longest_gap_s"] = round(float(gaps.max()), 6) if len(gaps) else 0.0
    record["gaps_not_interpolated"] = int(long.sum())
    n, total = record["count"], record["of"]
    shown = ", ".join(f"{t:.6f}" for t in record["first_stamps_s"]) + (
        ", ..." if n > len(record["first_stamps_s"]) else "")
    if long.any():
        i = int(np.argmax(gaps))
        gap = (f"they leave {int(long.sum())} gaps longer than the {limit:.2f} s the odometry "
               f"is interpolated across (the longest {gaps[i]:.2f} s, from "
               f"{valid_t[pairs[i, 0]]:.3f} s): the scans in them are matched without "
               "odometry")
    elif len(gaps):
        gap = (f"the longest gap they leave, {gaps.max():.3f} s, is interpolated across "
               f"(up to {limit:.2f} s is)")
    else:
        gap = ("they come before the first or after the last pose kept: the odometry "
               "starts later or ends sooner")
    log.warning("%s: %d of %d messages left out as no pose (%s; stamps %s s); the odometry "
                "keeps %d poses; %s", where, n, total, record["first_reason"], shown,
                len(odometry), gap)


def placeholder_camera() -> PinholeCamera:
    """Nominal intrinsics for lidar-only recordings (the rig format requires a camera);
    meta.yaml then says ``has_camera: false`` so no stage mistakes it for a real one."""
    return PinholeCamera.from_fov(640, 480, 90.0)


# Base (x forward, y left, z up) <- camera optical (x right, y down, z forward), REP 103.
R_BASE_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def optical_mount(t: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """[4, 4] T_base_camera of a level, forward-looking camera at ``t``."""
    T = np.eye(4)
    T[:3, :3] = R_BASE_OPTICAL
    T[:3, 3] = t
    return T


def uniform_scans(scans: list[LaserScan],
                  source: str = "the recording") -> tuple[list[LaserScan], int]:
    """Give every scan the most common beam count.

    The sequence format stores scans as one [S, B] array, with each scan's own angle_min,
    angle_increment and time_increment, but cheap lidars (RPLidar and the like) vary the
    count from turn to turn. Scans of the common count are kept as they are, whatever
    their start bearing and step; scans of another count are resampled by nearest bearing
    onto the first common one's beams, which never invents a range between two surfaces
    (interpolation would). Returns the scans and how many were resampled. ``source``
    (``Recording.source``) names the input in errors.
    """
    if not scans:
        return scans, 0
    # A message without beams (drivers send them on start-up and dropouts) becomes a scan
    # without returns: it must not set the count, nor be indexed.
    counts = Counter(len(s) for s in scans if len(s))
    if not counts:
        raise IngestError(
            f"{source}: all {len(scans)} scans have no beams (field 'ranges' is empty in "
            "every one): the lidar sent no measurements. Fix: name the lidar's scan source "
            "if this is not it (e.g. rosbag.topics.scan), or record again with the lidar "
            "running")
    common = counts.most_common(1)[0][0]
    ref = next(s for s in scans if len(s) == common)
    target = ref.angles()  # [B]
    out: list[LaserScan] = []
    changed = 0
    for s in scans:
        if len(s) == common:
            # Resampled onto the reference's bearings, a turn starting 0.45 beam later
            # was stored rotated by 0.45 beam, and one starting 10 deg later lost 10 deg.
            out.append(s)
            continue
        changed += 1
        if not len(s):
            out.append(LaserScan(s.stamp, np.full(len(target), np.nan, np.float32),
                                 ref.angle_min, ref.angle_increment, ref.range_min,
                                 ref.range_max))
            continue
        u = (target - s.angle_min) / s.angle_increment  # [B] fractional source beam
        if abs(s.angle_increment) * len(s) >= 2 * np.pi - 1e-6:
            # A full turn: bearings before its first beam are its last ones (a turn that
            # started 10 deg later lost those 10 deg as "outside").
            u = np.mod(u + 0.5, 2 * np.pi / abs(s.angle_increment)) - 0.5
        j = np.clip(np.rint(u).astype(np.int64), 0, len(s) - 1)
        # Nearest source beam of each target bearing; none within half a beam: no return.
        off = np.angle(np.exp(1j * (s.angles()[j] - target)))  # [B] wrapped to +-pi
        inside = np.abs(off) <= abs(s.angle_increment) / 2 + 1e-9
        r = np.where(inside, s.ranges[j], np.nan).astype(np.float32)
        inten = None
        if s.intensities is not None:
            inten = np.where(inside, s.intensities[j], 0.0).astype(np.float32)
        # Beam timing follows the source beams (the stamp stays the first beam's time,
        # within one source beam when angle_min moved).
        dt = s.time_increment * ref.angle_increment / s.angle_increment
        out.append(LaserScan(s.stamp, r, ref.angle_min, ref.angle_increment, s.range_min,
                             s.range_max, inten, dt))
    return out, changed

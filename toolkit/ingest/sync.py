"""Time synchronisation, stamp checks and frame decimation (pure numpy, no I/O).

The plan is made from stamps alone, before any pixel is decoded: which camera frames
have a scan (and, with a depth camera, a depth image) within the tolerance, which of
those survive decimation, and how many were dropped for each reason. Being a pure
function of the stamps, the plan is the same on every run, which is what lets an
interrupted conversion resume at the first frame it had not written.
"""

from __future__ import annotations

import bisect
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from toolkit.geometry import Trajectory, inv_se3, rotation_angle
from toolkit.ingest.recording import IngestError


class SyncOptions(BaseModel):
    """Pairing of camera frames with their partners."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    # A camera frame is kept only if a scan lies within this many seconds of it: fusion
    # projects "the" scan of a frame into it, and a scan taken 0.1 s away at 1 m/s is
    # 10 cm off. Half a scan period (0.05 s for a 10 Hz lidar) keeps every frame of a
    # well-behaved recording.
    tolerance_s: float = Field(0.05, gt=0)
    # Depth image <-> camera frame, as TUM's associate.py (--max_difference 0.02).
    depth_tolerance_s: float = Field(0.02, gt=0)
    # False keeps frames without a nearby scan (poses are interpolated between scans
    # anyway); they are then only counted.
    require_scan: bool = True
    # The camera's stamps are this much later than its exposures (a driver stamping on
    # arrival): frame stamps (and a depth camera's, except TUM RGB-D's, whose depth images
    # make the scans) are moved back by it before anything is paired.
    # `python -m calibration time-offset` measures it. The whole delay against the raw
    # stamps: a sequence folder converted before with one is moved by the difference;
    # None keeps what the source has (0 for recordings).
    camera_delay_s: float | None = Field(None, ge=-1.0, le=1.0)


class DecimateOptions(BaseModel):
    """Thinning of camera frames: none, one per time interval, or one per motion step."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    by: Literal["none", "time", "motion"] = "none"
    min_interval_s: float = Field(0.5, gt=0)  # by: time
    min_translation_m: float = Field(0.10, ge=0)  # by: motion (either threshold keeps)
    min_rotation_deg: float = Field(5.0, ge=0)  # by: motion


# Float64 resolves Unix-epoch seconds (1.7e9) to 2.4e-7 s: 0.2 s between two such stamps
# may come out as 0.1999998 s. Comparisons with a configured interval allow this much.
STAMP_SLACK_S = 1e-6


def stamps_keep(stamps: np.ndarray, where: str, policy: Literal["error", "drop"],
                fix: str = "", unit_s: float = 1.0,
                lines: Sequence[int] | None = None) -> np.ndarray:
    """[N] bool mask keeping a strictly increasing subsequence of ``stamps`` (in units of
    ``unit_s`` seconds: int64 nanoseconds compare exactly).

    ``policy="error"`` raises at the first stamp that is not after the one before it,
    naming ``where`` (file or topic), the message number and both stamps; ``"drop"``
    keeps the longest strictly increasing subsequence (its earliest messages where several
    are as long), so one stamp glitched far into the future or the past costs that one
    message, not every message after it. ``lines``: the file line of each stamp, named in
    the error instead of the message number (text files).
    """
    st = np.asarray(stamps)
    if st.dtype.kind == "f" and not np.isfinite(st).all():
        i = int(np.flatnonzero(~np.isfinite(st))[0])
        raise IngestError(f"{where}: stamp of {_message(i, lines)} is not finite ({st[i]!r})")
    if policy == "error":
        bad = np.flatnonzero(st[1:] <= st[:-1])
        if len(bad):
            i = int(bad[0]) + 1
            t, last = float(st[i]) * unit_s, float(st[i - 1]) * unit_s
            what = "repeats" if st[i] == st[i - 1] else "goes backwards"
            raise IngestError(
                f"{where}: stamps are not monotonic: {_message(i, lines)} at {t!r} {what} "
                f"(previous {last!r}, {float(st[i] - st[i - 1]) * unit_s:+.6f} s). Fix: set "
                f"'on_non_monotonic: drop' to skip such messages{fix}")
        return np.ones(len(st), dtype=bool)
    return longest_increasing(st)


def _message(i: int, lines: Sequence[int] | None) -> str:
    return f"message {i}" if lines is None else f"line {lines[i]}"


def longest_increasing(values: np.ndarray) -> np.ndarray:
    """[N] bool: the longest strictly increasing subsequence, earliest elements first among
    equally long ones (O(N log N))."""
    v = [x.item() for x in np.asarray(values)]  # Python scalars: exact ints stay exact
    n = len(v)
    # from_here[i]: length of the longest increasing run of values starting at i, found as
    # the longest decreasing one ending at i when walking backwards (patience tails).
    from_here = [0] * n
    tails: list = []  # tails[k]: -(the largest start of a run of length k + 1 so far)
    for i in range(n - 1, -1, -1):
        k = bisect.bisect_left(tails, -v[i])
        if k == len(tails):
            tails.append(-v[i])
        else:
            tails[k] = -v[i]
        from_here[i] = k + 1
    keep = np.zeros(n, dtype=bool)
    need = len(tails)
    last = None
    for i in range(n):
        if need and from_here[i] >= need and (last is None or v[i] > last):
            keep[i] = True
            last = v[i]
            need -= 1
    return keep


def match_nearest(query: np.ndarray, ref: np.ndarray, tolerance: float) -> np.ndarray:
    """[M] index into ``ref`` (sorted) of the stamp nearest each ``query`` stamp, -1 where
    the nearest is further than ``tolerance`` (ties go to the earlier stamp, and among equal
    stamps to the first, as ``argmin(|ref - q|)`` picks)."""
    q = np.asarray(query, dtype=np.float64)
    r = np.asarray(ref, dtype=np.float64)
    if len(r) == 0:
        return np.full(len(q), -1, dtype=np.int64)
    hi = np.clip(np.searchsorted(r, q), 1, len(r) - 1) if len(r) > 1 else np.zeros(
        len(q), np.int64)
    lo = np.searchsorted(r, r[np.maximum(hi - 1, 0)], side="left")  # first of equal stamps
    pick = np.where(np.abs(r[lo] - q) <= np.abs(r[hi] - q), lo, hi)
    return np.where(np.abs(r[pick] - q) <= tolerance + STAMP_SLACK_S, pick, -1).astype(
        np.int64)


def decimate_by_time(stamps: np.ndarray, min_interval_s: float) -> np.ndarray:
    """[N] bool: keep a frame when at least ``min_interval_s`` passed since the last kept,
    give or take a tenth of the frame period: a camera's stamps jitter by milliseconds,
    and 10 Hz frames at 0.2 s kept 0.2 and 0.3 s apart in turn (3.9 Hz, not 5)."""
    keep = np.zeros(len(stamps), dtype=bool)
    st = np.asarray(stamps, dtype=np.float64)
    period = float(np.median(np.diff(st))) if len(st) > 1 else 0.0
    slack = max(STAMP_SLACK_S, 0.1 * period)
    last = -np.inf
    for i, t in enumerate(st):
        if t - last >= min_interval_s - slack:
            keep[i] = True
            last = t
    return keep


def decimate_by_motion(stamps: np.ndarray, poses: Trajectory, min_translation_m: float,
                       min_rotation_deg: float) -> np.ndarray:
    """[N] bool: keep a frame when the base moved ``min_translation_m`` or turned
    ``min_rotation_deg`` since the last kept frame (poses interpolated at the stamps).

    Frames outside the pose trajectory's span cannot be judged and are kept.
    """
    st = np.asarray(stamps, dtype=np.float64)
    keep = np.ones(len(st), dtype=bool)
    if len(poses) == 0 or len(st) == 0:
        return keep
    inside = (st >= poses.stamps[0]) & (st <= poses.stamps[-1])
    P = np.full((len(st), 4, 4), np.nan)
    if inside.any():
        P[inside] = poses.interpolate(st[inside]).poses
    last: np.ndarray | None = None
    min_rot = np.radians(min_rotation_deg)
    for i in range(len(st)):
        if not inside[i]:
            continue
        if last is not None:
            d = inv_se3(last) @ P[i]
            moved = np.linalg.norm(d[:3, 3]) >= min_translation_m
            turned = float(rotation_angle(d[:3, :3])) >= min_rot
            if not (moved or turned):
                keep[i] = False
                continue
        last = P[i]
    return keep


@dataclass
class FramePlan:
    """Which candidate frames get written, with their depth partners, and why others not."""

    frames: np.ndarray  # [K] indices into the candidate frame stamps, increasing
    depth: np.ndarray  # [K] index of each kept frame's depth image, -1 without depth
    candidates: int
    dropped: dict[str, int] = field(default_factory=dict)  # reason -> count
    decimated: int = 0
    # Frames kept without a scan within tolerance (require_scan: false; before the first
    # scan or after the last, later stages cannot pose them).
    without_scan: int = 0

    def pairs(self) -> list[tuple[int, int]]:
        return [(int(f), int(d)) for f, d in zip(self.frames, self.depth, strict=True)]


def plan_frames(frame_stamps: np.ndarray, scan_stamps: np.ndarray,
                depth_stamps: np.ndarray | None, sync: SyncOptions,
                decimate: DecimateOptions, poses: Trajectory | None = None) -> FramePlan:
    """Pair frames with scans and depth within tolerance, then decimate the survivors.

    A frame without a partner is dropped (and counted under ``no_scan`` / ``no_depth``);
    decimation by motion needs ``poses`` (odometry, else ground truth).
    """
    fs = np.asarray(frame_stamps, dtype=np.float64)
    keep = np.ones(len(fs), dtype=bool)
    dropped: dict[str, int] = {}
    scan_match = match_nearest(fs, scan_stamps, sync.tolerance_s)
    if sync.require_scan:
        no_scan = scan_match < 0
        dropped["no_scan"] = int(no_scan.sum())
        keep &= ~no_scan
    depth = np.full(len(fs), -1, dtype=np.int64)
    if depth_stamps is not None:
        depth = match_nearest(fs, depth_stamps, sync.depth_tolerance_s)
        no_depth = keep & (depth < 0)
        dropped["no_depth"] = int(no_depth.sum())
        keep &= ~no_depth
    idx = np.flatnonzero(keep)
    decimated = 0
    if decimate.by == "time":
        k = decimate_by_time(fs[idx], decimate.min_interval_s)
        decimated, idx = int((~k).sum()), idx[k]
    elif decimate.by == "motion":
        if poses is None:
            raise IngestError(
                "decimate.by: motion needs poses, but this recording has no odometry or "
                "ground truth. Fix: use 'decimate: {by: time, min_interval_s: ...}'")
        k = decimate_by_motion(fs[idx], poses, decimate.min_translation_m,
                               decimate.min_rotation_deg)
        decimated, idx = int((~k).sum()), idx[k]
    return FramePlan(frames=idx, depth=depth[idx], candidates=len(fs), dropped=dropped,
                     decimated=decimated, without_scan=int((scan_match[idx] < 0).sum()))

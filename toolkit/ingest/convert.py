"""Streaming conversion of a ``Recording`` into a sequence folder, resumable.

The converter plans the frames from stamps (``sync.plan_frames``), then streams the
kept frames through a ``SequenceWriter`` opened in resume mode: frames an interrupted
run already wrote stay on disk and are skipped, so only what is missing gets decoded.
Scans, trajectories and meta are cheap and are written again at the end.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, TypeVar

import numpy as np

from toolkit.ingest.recording import IngestError, Recording, uniform_scans
from toolkit.ingest.sync import (
    DecimateOptions,
    FramePlan,
    SyncOptions,
    match_nearest,
    plan_frames,
)
from toolkit.io.depth import PNG_DEPTH_MAX_M
from toolkit.io.sequence import SequenceWriter

T = TypeVar("T")
Progress = Callable[..., Iterator[Any]]  # ctx.progress(iterable, total=, description=)

_log = logging.getLogger("toolkit.ingest")


def no_progress(iterable: Iterable[T], total: int | None = None,
                description: str = "") -> Iterator[T]:
    """The default progress wrapper outside a recipe run: none."""
    del total, description
    yield from iterable


@dataclass
class ConvertResult:
    """What a conversion wrote, for the log, metrics.json and the report."""

    root: Path
    plan: FramePlan
    frames: int  # frames in the folder
    frames_resumed: int  # of which an earlier, interrupted run had written
    scans: int
    scans_resampled: int
    seconds: float
    has_camera: bool
    has_depth: bool
    has_odometry: bool
    has_groundtruth: bool
    dropped_indexing: dict[str, int] = field(default_factory=dict)
    skipped_invalid: dict[str, dict[str, Any]] = field(default_factory=dict)  # Recording.skipped
    tf_skipped_invalid: dict[str, int] = field(default_factory=dict)  # Recording.tf_skipped
    depth_pixels_beyond_format: int = 0  # written as invalid (a PNG holds up to 13.107 m)
    # Frames of 16-bit samples this run converted (FrameData.from_16bit): scaled to 8 bits,
    # or clipped at 255 by the recording's JPEG codec; the brightest scaled sample.
    frames_16bit_scaled: int = 0
    frames_16bit_clipped: int = 0
    peak_16bit: int = 0

    def metrics(self) -> dict[str, Any]:
        """Figures for metrics.json (units in the names)."""
        return {
            "frames": self.frames,
            "frames_candidates": self.plan.candidates,
            "frames_dropped_no_scan": self.plan.dropped.get("no_scan", 0),
            "frames_without_scan": self.plan.without_scan,
            "frames_dropped_no_depth": self.plan.dropped.get("no_depth", 0),
            "frames_decimated": self.plan.decimated,
            "frames_resumed": self.frames_resumed,
            "scans": self.scans,
            "scans_resampled": self.scans_resampled,
            "messages_dropped_non_monotonic": sum(self.dropped_indexing.values()),
            "messages_skipped_invalid": sum(r["count"] for r in self.skipped_invalid.values()),
            "tf_transforms_skipped_invalid": sum(self.tf_skipped_invalid.values()),
            "depth_pixels_beyond_format": self.depth_pixels_beyond_format,
            "frames_16bit_scaled": self.frames_16bit_scaled,
            "frames_16bit_clipped": self.frames_16bit_clipped,
            "convert_s": round(self.seconds, 3),
        }

    def summary(self) -> str:
        """Human-readable account of what was converted."""
        p = self.plan
        lines = [f"converted into {self.root}:"]
        if self.has_camera:
            lines.append(
                f"  camera frames: {self.frames} written of {p.candidates} in the recording"
                + (f" ({self.frames_resumed} kept from an interrupted run)"
                   if self.frames_resumed else ""))
            lines.append(f"    dropped for lack of a scan within tolerance: "
                         f"{p.dropped.get('no_scan', 0)}")
            if p.without_scan:
                lines.append(f"    kept without a scan within tolerance (require_scan: "
                             f"false): {p.without_scan}")
            if self.has_depth:
                lines.append(f"    dropped for lack of a depth image within tolerance: "
                             f"{p.dropped.get('no_depth', 0)}")
            lines.append(f"    decimated: {p.decimated}")
            if self.depth_pixels_beyond_format:
                lines.append(f"    depth pixels beyond a PNG's {PNG_DEPTH_MAX_M:.3f} m, "
                             f"written as invalid: {self.depth_pixels_beyond_format} "
                             "(depth_format: npy keeps them)")
            if self.frames_16bit_scaled:
                lines.append(f"    16-bit frames scaled to 8 bits (255/65535, as cv_bridge): "
                             f"{self.frames_16bit_scaled} (brightest sample "
                             f"{self.peak_16bit} of 65535)")
            if self.frames_16bit_clipped:
                lines.append(f"    16-bit frames the recording's JPEG codec clipped at 255: "
                             f"{self.frames_16bit_clipped}")
        else:
            lines.append("  camera frames: none (lidar-only recording; the rig camera is a "
                         "placeholder)")
        lines.append(f"  scans: {self.scans}" + (
            f" ({self.scans_resampled} resampled to the common beam layout)"
            if self.scans_resampled else ""))
        for what, n in self.dropped_indexing.items():
            if n:
                lines.append(f"  messages dropped for non-monotonic stamps on {what}: {n}")
        for what, r in self.skipped_invalid.items():
            lines.append(f"  odometry messages left out as no pose on {what}: {r['count']} of "
                         f"{r['of']} (first stamps {r['first_stamps_s']} s; gaps not "
                         f"interpolated across: {r['gaps_not_interpolated']})")
        if self.tf_skipped_invalid:
            lines.append("  tf transforms skipped as no rigid motion: " + ", ".join(
                f"{k} ({n}x)" for k, n in self.tf_skipped_invalid.items()))
        lines.append(f"  odometry: {'yes' if self.has_odometry else 'no'}, ground truth: "
                     f"{'yes' if self.has_groundtruth else 'no'}, depth: "
                     f"{'yes' if self.has_depth else 'no'}")
        return "\n".join(lines)


def convert(recording: Recording, out: Path | str, sync: SyncOptions | None = None,
            decimate: DecimateOptions | None = None,
            depth_format: Literal["png", "npy"] = "png", resume: bool = True,
            progress: Progress = no_progress,
            log: logging.Logger | None = None, workers: int | None = None) -> ConvertResult:
    """Write ``recording`` as a sequence folder at ``out``.

    With ``resume`` (the default) frames written by an interrupted earlier conversion
    into ``out`` are kept; the caller must make sure it converted the same input with the
    same settings (the ``ingest`` stage checks a fingerprint). If what is on disk does not
    match the plan, the folder is started afresh rather than mixed.

    ``workers``: threads encoding and writing the frames' files while the next frames are
    read (default: the CPU count, at most 4; 0 writes each frame before reading the next).
    The folder's files are the same bytes either way.
    """
    log = log or _log
    sync = sync or SyncOptions()
    decimate = decimate or DecimateOptions()
    out = Path(out)
    start = time.perf_counter()
    scans, resampled = uniform_scans(recording.scans, recording.source)
    if resampled:
        log.warning("%d of %d scans had another beam count and were resampled by nearest "
                    "angle to %d beams", resampled, len(scans), len(scans[0]))
    scan_stamps = np.array([s.stamp for s in scans], dtype=np.float64)
    if len(scan_stamps) > 1 and np.any(np.diff(scan_stamps) <= 0):
        # A reader's broken promise, not the recording's fault: shown as the bug it is.
        raise RuntimeError(f"{recording.source}: scan stamps are not strictly increasing; "
                           "the reader should have caught this")
    poses = recording.odometry if recording.odometry is not None else recording.groundtruth
    # The whole delay against the raw stamps: a folder converted with a delay already
    # taken out is shifted by the rest only (following the time-offset advice, the whole
    # setting, on the measured folder itself took the earlier delay out twice); unset, it
    # keeps the source's.
    delay = (recording.camera_delay_applied_s if sync.camera_delay_s is None
             else sync.camera_delay_s)
    shift = delay - recording.camera_delay_applied_s
    if shift and recording.camera_delay_applied_s:
        log.info("%s: %.1f ms of camera delay were taken out at its conversion; shifting "
                 "the frames by %.1f ms more for sync.camera_delay_s %.1f ms in all",
                 recording.source, 1000 * recording.camera_delay_applied_s, 1000 * shift,
                 1000 * delay)
    frame_stamps = recording.frame_stamps - shift  # the exposure times
    # A depth camera's own stream is late like the colour one (one driver), except where
    # the scans are made from it: then it is the clock the delay was measured against.
    depth_stamps = recording.depth_stamps
    if depth_stamps is not None and not recording.depth_is_scan_clock:
        depth_stamps = depth_stamps - shift
    plan = plan_frames(frame_stamps, scan_stamps, depth_stamps, sync, decimate, poses)
    pairs = plan.pairs()
    stamps = frame_stamps[plan.frames] if len(pairs) else np.zeros(0)
    if plan.candidates and sync.require_scan and not len(scan_stamps):
        raise IngestError(
            f"{recording.source}: the recording has {plan.candidates} camera frames but no "
            "lidar scans. Fix: 'sync.require_scan: false' to convert the frames alone, or "
            "name the scan source (e.g. rosbag.topics.scan)")
    if plan.candidates and plan.dropped.get("no_scan") == plan.candidates:
        fs = frame_stamps
        gap = float(np.median(np.abs(scan_stamps[match_nearest(fs, scan_stamps, np.inf)] - fs)))
        overlap = fs[0] <= scan_stamps[-1] and scan_stamps[0] <= fs[-1]
        period = float(np.median(np.diff(scan_stamps))) if len(scan_stamps) > 1 else np.inf
        if overlap and gap <= period:
            # The clocks agree: unsynchronised sensors (a 10 Hz camera 40 ms out of phase
            # with a 10 Hz lidar) just have no scan that near.
            why = (f"the nearest scan is {gap * 1000:.0f} ms away at the median, within one "
                   f"scan period ({period * 1000:.0f} ms): the sensors are not synchronised. "
                   f"Fix: 'sync.tolerance_s' of about half the scan period "
                   f"({period / 2:.3f} s; scans are placed at the image time with the poses)")
        else:
            why = (f"frames span {fs[0]:.3f}..{fs[-1]:.3f} s, scans {scan_stamps[0]:.3f}.."
                   f"{scan_stamps[-1]:.3f} s, the nearest scan {gap:.3f} s away at the median:"
                   " the sensors' clocks disagree. Fix: 'rosbag.stamps: bag' (recording time)"
                   " for a bag, a larger 'sync.tolerance_s', or 'sync.require_scan: false'")
        raise IngestError(f"{recording.source}: none of the {plan.candidates} camera frames "
                          f"has a scan within sync.tolerance_s = {sync.tolerance_s} s: {why}")
    with_scan = plan.candidates - plan.dropped.get("no_scan", 0)
    if with_scan and plan.dropped.get("no_depth", 0) == with_scan:
        # Depth is for evaluation: a clock offset between colour and depth streams must
        # not turn into a sequence without frames.
        ds = depth_stamps
        nearest = "there are no depth images" if not len(ds) else (
            "the nearest is {:.3f} s away at the median".format(float(np.median(np.abs(
                ds[match_nearest(frame_stamps, ds, np.inf)] - frame_stamps)))))
        raise IngestError(
            f"{recording.source}: none of the {with_scan} camera frames has a depth image "
            f"within sync.depth_tolerance_s = {sync.depth_tolerance_s} s ({nearest}). Fix: a "
            "larger 'sync.depth_tolerance_s', or leave depth out (rosbag.topics.depth: none)")
    if recording.has_camera:
        log.info("sync plan: %d of %d camera frames kept; dropped %d without a scan within "
                 "%g s, %d without a depth image within %g s; %d decimated (%s)",
                 len(pairs), plan.candidates, plan.dropped.get("no_scan", 0), sync.tolerance_s,
                 plan.dropped.get("no_depth", 0), sync.depth_tolerance_s, plan.decimated,
                 decimate.by)

    finished = (out / "meta.yaml").exists()
    if finished:
        # A finished sequence is no partial conversion to resume; its optional files
        # (ground truth, held-out views) must not outlive it into the new one. Only the
        # sequence's own files go (SequenceWriter without resume): the folder may hold the
        # bag itself or the user's notes, which a removal of the folder took with it.
        log.warning("replacing the finished sequence in %s", out)
    if workers is None:
        workers = min(4, os.cpu_count() or 1)
    writer = SequenceWriter(out, recording.rig, recording.name, recording.source,
                            depth_format, resume=resume and not finished, workers=workers)
    done = writer.num_frames
    if done and (done > len(pairs) or writer.last_frame_stamp != float(stamps[done - 1])):
        log.warning("%s holds %d frames that do not match this conversion's plan; "
                    "starting it afresh", out, done)
        writer.discard()
        writer = SequenceWriter(out, recording.rig, recording.name, recording.source,
                                depth_format, workers=workers)
        done = 0
    if done:
        log.info("resuming: %d of %d frames already converted", done, len(pairs))
    todo = pairs[done:]
    from_16bit = {"scaled": 0, "clipped": 0}
    peak_16bit = 0
    if todo:
        frames = recording.load(todo)
        try:
            for k, fd in enumerate(progress(frames, total=len(todo), description="frames")):
                if fd.from_16bit is not None:
                    from_16bit[fd.from_16bit] += 1
                    peak_16bit = max(peak_16bit, fd.peak_16bit)
                expected = float(stamps[done + k])
                stamp = float(np.float64(fd.stamp) - shift)  # as the planned stamps were made
                if stamp != expected:
                    raise RuntimeError(f"{recording.source}: loader returned frame at "
                                       f"{fd.stamp!r} where {expected + shift!r} was planned")
                writer.add_frame(stamp, fd.image, fd.depth, fd.mask, image_path=fd.image_path,
                                 image_jpeg=fd.image_jpeg)
            writer.flush()
        except BaseException:
            # Interrupted or failed: the frames in flight land and are journaled, so a
            # rerun resumes after them.
            writer.discard()
            raise
        if writer.num_frames != len(pairs):
            raise IngestError(f"{recording.source}: only {writer.num_frames} of {len(pairs)} "
                              "planned frames could be read (the input ended early: "
                              "truncated?)")
    if writer.depth_pixels_beyond_format:
        log.warning("%d depth pixels lie beyond the %.3f m a 16-bit depth PNG holds and were "
                    "written as invalid; set depth_format: npy to keep them",
                    writer.depth_pixels_beyond_format, PNG_DEPTH_MAX_M)
    if from_16bit["clipped"]:
        log.warning("%s: %d frames are 16-bit images that the recording's JPEG codec clipped "
                    "to 8 bits (image_transport passes a mono16 / Bayer 16 image to OpenCV's "
                    "JPEG encoder unscaled: every sample above 255 of 65535 became 255, "
                    "white); they are stored as the payload holds them, min(v, 255). The bag "
                    "has nothing more: record the raw topic, or the png transport, which "
                    "keeps 16 bits", recording.source, from_16bit["clipped"])
    if from_16bit["scaled"] and peak_16bit < 4096:
        log.warning("%s: the brightest sample of the %d 16-bit frames is %d of 65535: scaled to "
                    "8 bits as cv_bridge scales them (255/65535) they are stored at most %d of "
                    "255, near black. The camera probably writes %d-bit data into 16-bit "
                    "samples; republish it as 8 bits scaled to its own range",
                    recording.source, from_16bit["scaled"], peak_16bit,
                    (peak_16bit + 128) // 257, max(1, peak_16bit.bit_length()))
    dynamic = recording.scan_dynamic
    for k, s in enumerate(scans):
        writer.add_scan(s, None if dynamic is None else dynamic[k])
    writer.odometry = recording.odometry
    writer.groundtruth_poses = recording.groundtruth
    if recording.finish is not None:
        recording.finish(writer, np.asarray(plan.frames, dtype=np.int64).reshape(-1))
    writer.extra_meta.update({
        "has_camera": recording.has_camera,
        **recording.meta,
        "ingest": {
            "candidates": plan.candidates,
            "dropped_no_scan": plan.dropped.get("no_scan", 0),
            "without_scan": plan.without_scan,
            "dropped_no_depth": plan.dropped.get("no_depth", 0),
            "decimated": plan.decimated,
            "sync_tolerance_s": sync.tolerance_s,
            "camera_delay_s": delay,
            "decimate": decimate.model_dump(),
            "scans_resampled": resampled,
            "dropped_non_monotonic": dict(recording.dropped),
            "skipped_invalid": dict(recording.skipped),
            "tf_skipped_invalid": dict(recording.tf_skipped),
            "depth_pixels_beyond_format": writer.depth_pixels_beyond_format,
            "frames_16bit_scaled": from_16bit["scaled"],
            "frames_16bit_clipped": from_16bit["clipped"],
            **({"brightest_16bit_sample": peak_16bit} if from_16bit["scaled"] else {}),
        },
    })
    root = writer.close()
    return ConvertResult(
        root=root, plan=plan, frames=len(pairs), frames_resumed=done, scans=len(scans),
        scans_resampled=resampled, seconds=time.perf_counter() - start,
        has_camera=recording.has_camera, has_depth=recording.depth_stamps is not None,
        has_odometry=recording.odometry is not None,
        has_groundtruth=recording.groundtruth is not None,
        dropped_indexing=dict(recording.dropped),
        skipped_invalid=dict(recording.skipped),
        tf_skipped_invalid=dict(recording.tf_skipped),
        depth_pixels_beyond_format=writer.depth_pixels_beyond_format,
        frames_16bit_scaled=from_16bit["scaled"], frames_16bit_clipped=from_16bit["clipped"],
        peak_16bit=peak_16bit)

"""CARMEN logs and g2o ROBOTLASER1 files as a lidar-only ``Recording`` for ``ingest``.

``toolkit.io.carmen`` parses the files; this adapter decides which of their poses may
enter the sequence and as what:

- odometry (``odometry.tum``, an input to SLAM): the raw robot odometry stored with each
  scan (CARMEN log) or the sequential ``EDGE_SE2`` chain (g2o). A corrected log (Radish
  ``*-corrected``) has SLAM-made poses in those fields, so by default it gets none.
- ground truth (``groundtruth/poses_base.tum``, for evaluation only): the corrected
  poses of a corrected log or the g2o vertices. They are a SLAM solution, not a survey;
  meta.yaml says so.

The sequence has no camera frames; its rig carries a nominal placeholder camera (the
format requires one) and meta.yaml has ``has_camera: false``.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from toolkit.geometry import Trajectory, se2_to_se3
from toolkit.ingest.recording import (
    FrameData,
    IngestError,
    Recording,
    note_skipped_gaps,
    optical_mount,
    placeholder_camera,
    skipped_record,
)
from toolkit.ingest.sync import stamps_keep
from toolkit.io.carmen import CarmenFormatError, read_carmen, read_g2o
from toolkit.sensors import Rig

_log = logging.getLogger("toolkit.io.carmen_ingest")


class CarmenOptions(BaseModel):
    """Settings of the CARMEN / g2o reader (``ingest`` key ``carmen:``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    format: Literal["auto", "log", "g2o"] = "auto"  # auto: g2o if the name says so
    # auto: g2o -> edges; log -> odometry stored with the scans, none if "corrected"
    odometry: Literal["auto", "none", "scans", "odom_lines", "edges"] = "auto"
    # auto: g2o vertices, or the poses of a "corrected" log; else none
    groundtruth: Literal["auto", "none", "reference"] = "auto"
    max_range_m: float = Field(50.0, gt=0)  # range_max of FLASER scans (not in the line)


def _is_g2o(path: Path, fmt: str) -> bool:
    if fmt != "auto":
        return fmt == "g2o"
    return ".g2o" in path.name.lower()


def _odometry(stamps: np.ndarray, xyt: np.ndarray, where: str, fields: str,
              policy: Literal["error", "drop"], log: logging.Logger,
              skipped: dict[str, dict[str, Any]]) -> tuple[Trajectory, int]:
    """The odometry of ``stamps`` [N] / ``xyt`` [N, 3] with its non-finite readings left
    out, counted in ``skipped`` and warned about, as a bag's odometry messages are
    (``skipped_record``: refused when fewer than half are poses)."""
    ok = np.isfinite(xyt).all(axis=1)  # [N]
    bad = np.flatnonzero(~ok)
    first = f"{fields} {xyt[bad[0]].tolist()} is not finite" if len(bad) else ""
    record = skipped_record(where, len(xyt), stamps[bad].tolist(), first,
                            "set 'carmen.odometry: none' to map from the scans alone")
    kept = stamps_keep(stamps[ok], where, policy)  # [V] of the valid readings
    P = np.stack([se2_to_se3(*p) for p in xyt[ok][kept]]) if kept.any() else \
        np.zeros((0, 4, 4))
    odometry = Trajectory(stamps[ok][kept], P, "odom", "base_link")
    n = int((~kept).sum())
    if record is not None:
        before = np.cumsum(ok)[bad]  # [B] valid readings before each skipped one
        note_skipped_gaps(record, odometry, stamps[ok], kept, before, where, log)
        skipped[where.split(": ", 1)[-1]] = record
    return odometry, n


def read_carmen_recording(path: Path | str, options: CarmenOptions | None = None,
                          on_non_monotonic: Literal["error", "drop"] = "error",
                          log: logging.Logger | None = None,
                          name: str | None = None) -> Recording:
    """Read a CARMEN log or g2o file into a lidar-only ``Recording``."""
    opts = options or CarmenOptions()
    log = log or _log
    path = Path(path)
    if not path.exists():
        raise IngestError(f"{path}: CARMEN log / g2o file not found")
    if path.is_dir():
        # Read as a file it failed with a bare IsADirectoryError.
        raise IngestError(f"{path}: a folder, not a CARMEN log or g2o file; give the log "
                          "file (plain, .gz or .zip), or the 'source' that reads this folder "
                          "(rosbag: a ROS 2 bag, tum_rgbd, sequence)")
    # Radish names GMapping-corrected logs *-corrected.log; raw ones are *-raw.log or, in
    # some collections, *-uncorrected.log.
    lower = path.name.lower()
    corrected = "corrected" in lower and "uncorrected" not in lower
    g2o = _is_g2o(path, opts.format)
    try:
        data = read_g2o(path) if g2o else read_carmen(path, max_range=opts.max_range_m)
    except CarmenFormatError as e:
        raise IngestError(str(e)) from None
    if not data.scans:
        raise IngestError(f"{path}: no laser scans (FLASER / ROBOTLASER1 lines) found; "
                          "for another kind of recording set its 'source' (rosbag, tum_rgbd, "
                          "sequence)")
    where = f"{path}: scans"
    stamps = np.array([s.stamp for s in data.scans], dtype=np.float64)
    # The file's line is named, not the scan's number: a log is read with an editor.
    keep = stamps_keep(stamps, where, on_non_monotonic, lines=data.scan_linenos or None)
    scans = [s for s, k in zip(data.scans, keep, strict=True) if k]
    dropped = {"scans": int((~keep).sum())}

    mode = opts.odometry
    if mode == "auto":
        mode = "edges" if g2o else ("none" if corrected else "scans")
        if corrected and not g2o:
            log.info("%s is a corrected log: its odometry fields hold SLAM-made poses, so "
                     "they are not used as odometry (set carmen.odometry to override)",
                     path.name)
    odometry: Trajectory | None = None
    skipped: dict[str, dict[str, Any]] = {}
    if mode == "edges":
        if not g2o:
            raise IngestError(f"{path}: carmen.odometry: edges needs a g2o file")
        try:
            odometry = data.odometry()
        except CarmenFormatError as e:
            raise IngestError(f"{e}; or set 'carmen.odometry: none' to map from the scans "
                              "alone") from None
    elif mode == "scans":
        if g2o:
            raise IngestError(f"{path}: carmen.odometry: scans - a g2o file's ROBOTLASER1 "
                              "poses are corrected ones; use edges (the raw odometry chain)")
        xyt = data.scan_odometry[keep]  # [S', 3]
        bad = np.flatnonzero(~np.isfinite(xyt).all(axis=1))
        robot = len(bad) > 0 and np.asarray(data.scan_lines)[keep][bad[0]] == "ROBOTLASER1"
        fields = ("ROBOTLASER1 robot pose (robot_x robot_y robot_theta)" if robot else
                  "odometry pose (odom_x odom_y odom_theta)")
        odometry, n = _odometry(stamps[keep], xyt, f"{path}: scan lines' odometry", fields,
                                "drop", log, skipped)
        dropped["odometry"] = n
    elif mode == "odom_lines":
        if g2o or len(data.odom_stamps) == 0:
            raise IngestError(f"{path}: carmen.odometry: odom_lines but the file has no ODOM "
                              "lines")
        odometry, n = _odometry(data.odom_stamps, data.odom_poses, f"{path}: ODOM lines",
                                "odometry pose (x y theta)", on_non_monotonic, log, skipped)
        dropped["odom_lines"] = n
    if odometry is not None:
        odometry.frame = "odom"

    gmode = opts.groundtruth
    if gmode == "auto":
        gmode = "reference" if (g2o or corrected) else "none"
    groundtruth = data.reference() if gmode == "reference" else None
    # The reference poses come from the scan lines: a line dropped from both is one
    # message (it was counted twice in messages_dropped_non_monotonic).
    if groundtruth is not None and len(groundtruth) < len(data.scans) - dropped["scans"]:
        dropped["groundtruth"] = len(data.scans) - dropped["scans"] - len(groundtruth)

    rig = Rig(placeholder_camera(), optical_mount(), data.T_base_laser)
    span = scans[-1].stamp - scans[0].stamp if scans else 0.0
    log.info("%s %s: %d scans of %d beams over %.1f s (%.1f Hz), odometry: %s, ground "
             "truth: %s, no camera", "g2o" if g2o else "CARMEN log", path, len(scans),
             len(scans[0]), span, (len(scans) - 1) / span if span > 0 else 0.0, mode,
             "reference poses" if groundtruth is not None else "none")
    meta = {
        "source_kind": "g2o ROBOTLASER1" if g2o else "CARMEN log",
        "odometry_from": mode,
        "groundtruth": ("SLAM-corrected reference poses stored in the file (not surveyed "
                        "ground truth)" if groundtruth is not None else None),
    }

    def load(pairs: Sequence[tuple[int, int]]) -> Iterator[FrameData]:
        if pairs:
            raise IngestError(f"{path}: a lidar-only recording has no camera frames")
        return iter(())

    return Recording(
        name=name or path.name.split(".")[0], source=f"{'g2o' if g2o else 'carmen'} {path}",
        rig=rig, scans=scans, frame_stamps=np.zeros(0), load=load,
        odometry=odometry, groundtruth=groundtruth, has_camera=False, meta=meta,
        dropped={k: v for k, v in dropped.items() if v}, skipped=skipped)

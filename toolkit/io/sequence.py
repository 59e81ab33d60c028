"""The project's sequence folder: one recording on disk (format in datasets/README.md).

    <root>/meta.yaml                     format name + version, sequence name, source, counts
    <root>/rig.yaml                      camera intrinsics, T_base_camera, T_base_laser
    <root>/camera/frames.csv             index,stamp,image[,gt_depth][,gt_mask]
    <root>/camera/images/000000.png      RGB images (paths relative to camera/)
    <root>/scans.npz                     stamps, ranges [S, B], per-scan angle/range limits
    <root>/odometry.tum                  optional, T_odom_base
    <root>/groundtruth/poses_base.tum    optional, T_world_base at sensor stamps
    <root>/groundtruth/depth/*.png|npy   optional, per frame (listed in frames.csv)
    <root>/groundtruth/masks/*.png       optional, dynamic pixels per frame
    <root>/groundtruth/scan_dynamic.npz  optional, [S, B] beams that hit moving obstacles
    <root>/groundtruth/mesh.ply          optional, static scene mesh with colours
    <root>/groundtruth/heldout/          optional, frames.csv + images/ + depth/ + poses_camera.tum

``SequenceWriter`` streams frames to disk (a long recording never sits in memory) and
writes the index files last, atomically, so a folder is readable only once complete.
Until then each written frame is also noted in ``<root>/.frames.journal.jsonl``, so a
writer opened with ``resume=True`` keeps the frames of one that was killed half way.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import re
import shutil
import struct
import zipfile
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from toolkit.camera import PinholeCamera
from toolkit.errors import InputError, WriteError
from toolkit.geometry import Trajectory
from toolkit.io.atomic import (
    atomic_path,
    atomic_write_bytes,
    atomic_write_text,
    remove_temps_under,
)
from toolkit.io.depth import write_depth
from toolkit.io.tum import read_tum, write_tum
from toolkit.io.yaml_file import load_yaml
from toolkit.sensors import (
    CameraFrame,
    GroundTruth,
    HeldOutViews,
    LaserScan,
    Rig,
    Sequence,
    load_rgb,
)

_log = logging.getLogger(__name__)

FORMAT_NAME = "lidarcam-sequence"
FORMAT_VERSION = 1


class SequenceFormatError(InputError):
    """A sequence folder is malformed; the message names the file and the field."""


# Stamps are seconds; a larger one (after the year 5000) is a count of ms, us or ns (what
# ROS 2 and most drivers log), which was read as seconds without a word.
MAX_STAMP_S = 1e11


def check_seconds(stamps: Any, where: str, field: str) -> None:
    """Refuse stamps [N] too large to be seconds, naming ``where``, the field and the
    divisor that makes them seconds."""
    st = np.abs(np.asarray(stamps, dtype=np.float64).reshape(-1))  # [N]
    big = st > MAX_STAMP_S
    if not big.any():
        return
    v = float(st[np.argmax(big)])
    unit, scale = (("nanoseconds", "1e9") if v > 1e17 else ("microseconds", "1e6") if v > 1e14
                   else ("milliseconds", "1e3"))
    raise SequenceFormatError(f"{where}: field '{field}' holds {v:.10g}, which looks like "
                              f"{unit} since 1970: stamps are seconds; divide them by {scale}")


# ---------------------------------------------------------------------------- rig YAML


def rig_to_dict(rig: Rig) -> dict[str, Any]:
    return {
        "camera": rig.camera.to_dict(),
        "T_base_camera": [[float(v) for v in row] for row in rig.T_base_camera],
        "T_base_laser": [[float(v) for v in row] for row in rig.T_base_laser],
        "frames": {"base": "base_link", "camera": "camera_optical (x right, y down, z forward)",
                   "laser": "laser"},
        "convention": "T_a_b maps points from frame b into frame a (p_a = T_a_b @ p_b)",
    }


def rig_from_dict(d: Any, source: str = "rig.yaml") -> Rig:
    """Parse a rig mapping; errors name ``source`` and the field."""
    if not isinstance(d, dict):
        raise SequenceFormatError(f"{source}: expected a mapping with camera, T_base_camera, "
                                  "T_base_laser")
    if "camera" not in d:
        raise SequenceFormatError(f"{source}: missing field 'camera' (intrinsics)")
    try:
        cam = PinholeCamera.from_dict(d["camera"])
    except (KeyError, TypeError, ValueError) as e:
        raise SequenceFormatError(f"{source}: field 'camera': {e}") from None
    mats = {}
    for key in ("T_base_camera", "T_base_laser"):
        if key not in d:
            raise SequenceFormatError(f"{source}: missing field '{key}' (4x4 list of rows)")
        try:
            M = np.asarray(d[key], dtype=np.float64)
        except (TypeError, ValueError) as e:  # a short row, "0.2m"
            raise SequenceFormatError(f"{source}: field '{key}' must be a 4x4 list of rows of "
                                      f"numbers: {e}") from None
        if M.shape != (4, 4) or not np.all(np.isfinite(M)):
            raise SequenceFormatError(f"{source}: field '{key}' must be a finite 4x4 matrix, "
                                      f"got shape {M.shape}")
        mats[key] = M
    try:
        return Rig(cam, mats["T_base_camera"], mats["T_base_laser"])
    except ValueError as e:
        raise SequenceFormatError(f"{source}: {e}") from None


def sequence_with_rig(seq: Sequence, rig_path: Path | str) -> Sequence:
    """``seq`` with the rig of ``rig_path`` (a calibrated extrinsic, e.g. the ``calibrate``
    stage's ``rig``) instead of its own; the camera must be the sequence's size."""
    rig = read_rig(Path(rig_path))
    if seq.frames and rig.camera.size != seq.rig.camera.size:
        raise SequenceFormatError(
            f"{rig_path}: its camera is {rig.camera.width}x{rig.camera.height}, the images of "
            f"{seq.name} are {seq.rig.camera.width}x{seq.rig.camera.height}: calibrate the "
            "camera of this recording")
    return replace(seq, rig=rig)


def write_rig(path: Path, rig: Rig) -> None:
    atomic_write_text(path, yaml.safe_dump(rig_to_dict(rig), sort_keys=False))


def read_rig(path: Path | str) -> Rig:
    path = Path(path)
    data = load_yaml(path, SequenceFormatError, "rig file not found (camera intrinsics and "
                     "T_base_camera / T_base_laser are required)")
    warn_if_unreliable(path, data)
    return rig_from_dict(data, str(path))


def warn_if_unreliable(path: Path, data: Any,
                       error: type[Exception] = SequenceFormatError) -> None:
    """Log a warning when a rig / calibration mapping written by ``python -m calibration``
    says its extrinsic was estimated unreliable (``calibration.reliable: false``); an
    ``error`` naming the file and field when the mark is no YAML boolean."""
    info = data.get("calibration") if isinstance(data, dict) else None
    if not isinstance(info, dict) or "reliable" not in info:
        return
    if not isinstance(info["reliable"], bool):
        # A quoted "false" is not False: such a rig was read without the warning (and
        # read_extrinsic, the calibrate stage's reader, refused it).
        raise error(f"{path}: field 'reliable' is {info['reliable']!r}, not a YAML boolean; "
                    "write reliable: true or reliable: false (unquoted)")
    if info["reliable"] is False:
        _log.warning("%s: its extrinsic was marked unreliable when it was estimated (%s); "
                     "calibrate again with more varied board views", path,
                     "; ".join(map(str, info.get("unreliable_because") or [])) or "no reason")


# ---------------------------------------------------------------------------- scans


def scans_to_arrays(scans: list[LaserScan], source: str = "scans") -> dict[str, np.ndarray]:
    if not scans:
        # Every array scans_from_arrays asks for, empty: without the limits a file of no
        # scans was written but read back as "missing array 'angle_min'".
        return {"stamps": np.zeros(0), "ranges": np.zeros((0, 0), np.float32),
                **{k: np.zeros(0) for k in ("angle_min", "angle_increment", "range_min",
                                            "range_max")}}
    nb = {len(s) for s in scans}
    if len(nb) != 1:
        raise SequenceFormatError(f"{source}: scans have different beam counts {sorted(nb)}; "
                                  "resample them to one count")
    out = {
        "stamps": np.array([s.stamp for s in scans], dtype=np.float64),
        "ranges": np.stack([s.ranges for s in scans]).astype(np.float32),
        "angle_min": np.array([s.angle_min for s in scans], dtype=np.float64),
        "angle_increment": np.array([s.angle_increment for s in scans], dtype=np.float64),
        "range_min": np.array([s.range_min for s in scans], dtype=np.float64),
        "range_max": np.array([s.range_max for s in scans], dtype=np.float64),
    }
    has = np.array([s.intensities is not None for s in scans], bool)  # [S]
    if has.any():
        out["intensities"] = np.stack([
            s.intensities if s.intensities is not None else np.zeros(len(s), np.float32)
            for s in scans
        ]).astype(np.float32)
        if not has.all():  # which rows are zeros for want of intensities, not measured zeros
            out["has_intensities"] = has
    if any(s.time_increment != 0 for s in scans):
        out["time_increment"] = np.array([s.time_increment for s in scans], dtype=np.float64)
    return out


def _per_scan(value: Any, key: str, n: int, source: str) -> np.ndarray:
    """[n] float64 of a value given once per scan or once for all."""
    a = np.asarray(value, dtype=np.float64)
    if a.size not in (1, n):
        raise SequenceFormatError(f"{source}: '{key}' has {a.size} values for {n} scans; "
                                  "give one per scan or one for all")
    return np.broadcast_to(a.reshape(-1), (n,))


def scans_from_arrays(data: Any, source: str) -> list[LaserScan]:
    for key in ("stamps", "ranges", "angle_min", "angle_increment", "range_min", "range_max"):
        if key not in data:
            raise SequenceFormatError(f"{source}: missing array '{key}'")
    stamps = np.asarray(data["stamps"], dtype=np.float64)  # [S]
    if stamps.ndim != 1:
        raise SequenceFormatError(f"{source}: 'stamps' must hold one stamp per scan ([S]), "
                                  f"got shape {stamps.shape}")
    check_seconds(stamps, source, "stamps")
    try:
        ranges = np.asarray(data["ranges"], dtype=np.float32)  # [S, B]
    except ValueError:
        raise SequenceFormatError(f"{source}: 'ranges' must hold numbers (metres), got "
                                  f"{np.asarray(data['ranges']).dtype}") from None
    n = len(stamps)
    if ranges.ndim != 2 or len(ranges) != n:
        raise SequenceFormatError(f"{source}: 'ranges' must be [S, B] with S = {n} stamps, got "
                                  f"{ranges.shape}")
    if not np.all(np.isfinite(stamps)):
        raise SequenceFormatError(f"{source}: 'stamps' holds non-finite values")
    if n > 1 and np.any(np.diff(stamps) <= 0):
        i = int(np.argmax(np.diff(stamps) <= 0)) + 1
        # float32 holds Unix seconds to 128 s: every stamp of a minute's drive is one value.
        why = ("; they are float32, which holds Unix seconds to 128 s: store them as float64"
               if np.asarray(data["stamps"]).dtype == np.float32 else "")
        raise SequenceFormatError(f"{source}: 'stamps' not strictly increasing at scan {i} "
                                  f"({float(stamps[i - 1])!r} then {float(stamps[i])!r}){why}")
    per = {key: _per_scan(data[key], key, n, source)
           for key in ("angle_min", "angle_increment", "range_min", "range_max")}
    if np.any(per["angle_increment"] == 0):
        raise SequenceFormatError(f"{source}: 'angle_increment' is zero for some scans")
    for key, a in per.items():
        bad = np.isnan(a) if key == "range_max" else ~np.isfinite(a)  # range_max may be inf
        if bad.any():
            raise SequenceFormatError(f"{source}: '{key}' holds non-finite values (scan "
                                      f"{int(np.flatnonzero(bad)[0])})")
    if np.any(per["range_min"] >= per["range_max"]):
        raise SequenceFormatError(f"{source}: 'range_min' is not below 'range_max' (scan "
                                  f"{int(np.argmax(per['range_min'] >= per['range_max']))}): "
                                  "no return would count")
    inten = np.asarray(data["intensities"], np.float32) if "intensities" in data else None
    if inten is not None and inten.shape[:1] != (n,):
        rows = inten.shape[0] if inten.ndim else 0
        raise SequenceFormatError(f"{source}: 'intensities' has {rows} rows for {n} scans")
    has = np.ones(n, bool)
    if "has_intensities" in data:
        has = np.asarray(data["has_intensities"], bool).reshape(-1)
        if has.shape != (n,):
            raise SequenceFormatError(f"{source}: 'has_intensities' has {len(has)} values for "
                                      f"{n} scans")
    # Written only when a scan has per-beam timing; files from before it hold none.
    dt = _per_scan(data["time_increment"] if "time_increment" in data else 0.0,
                   "time_increment", n, source)
    if not np.all(np.isfinite(dt)):
        raise SequenceFormatError(f"{source}: 'time_increment' holds non-finite values "
                                  "(0 for scans without per-beam timing)")
    scans = []
    for i in range(n):
        try:
            scans.append(LaserScan(float(stamps[i]), ranges[i], float(per["angle_min"][i]),
                                   float(per["angle_increment"][i]), float(per["range_min"][i]),
                                   float(per["range_max"][i]),
                                   None if inten is None or not has[i] else inten[i],
                                   float(dt[i])))
        except ValueError as e:
            # The file is readable; one scan's values are not (degrees for radians, ...).
            raise SequenceFormatError(f"{source}: scan {i}: {e}") from None
    return scans


def write_scans(path: Path, scans: list[LaserScan]) -> None:
    buf = io.BytesIO()
    np.savez_compressed(buf, **scans_to_arrays(scans, str(path)))
    atomic_write_bytes(path, buf.getvalue())


def read_scans(path: Path) -> list[LaserScan]:
    if not path.exists():
        raise SequenceFormatError(f"{path}: scan file not found")
    try:
        with np.load(path) as data:
            return scans_from_arrays({k: data[k] for k in data.files}, str(path))
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:  # truncated: the last two
        if isinstance(e, SequenceFormatError):
            raise
        raise SequenceFormatError(f"{path}: not a readable npz scan file ({e}); write it "
                                  "again (toolkit.io.sequence.write_scans)") from None


# ---------------------------------------------------------------------------- frames.csv


def _csv_rows(path: Path) -> list[dict[str, str]]:
    """Rows of a CSV file with a header. UTF-8 with or without a BOM (Excel's "CSV UTF-8"
    put it into the first column's name, so 'stamp' was missing); spaces after the commas
    are dropped (an 'index, stamp, image' header was refused too)."""
    data = path.read_bytes()
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = data[:e.start].count(b"\n") + 1
        raise SequenceFormatError(f"{path}:{line}: not UTF-8 text (byte "
                                  f"{data[e.start:e.start + 1]!r}); "
                                  "save the file as UTF-8") from None
    return list(csv.DictReader(io.StringIO(text, newline=""), skipinitialspace=True))


def _read_frames_csv(path: Path) -> list[dict[str, str]]:
    if not path.exists():
        raise SequenceFormatError(f"{path}: frame index not found")
    rows = _csv_rows(path)
    if rows and not {"stamp", "image"} <= set(rows[0]):
        raise SequenceFormatError(f"{path}: header must contain 'stamp' and 'image', got "
                                  f"{list(rows[0])}")
    return rows


def _frames_from_rows(rows: list[dict[str, str]], base: Path, csv_path: Path) -> (
    tuple[list[CameraFrame], list[Path] | None, list[Path] | None]
):
    frames: list[CameraFrame] = []
    depth: list[Path] = []
    masks: list[Path] = []
    prev = -np.inf
    for i, row in enumerate(rows):
        line = i + 2  # header is line 1
        try:
            stamp = float(row["stamp"])
        except (TypeError, ValueError):
            raise SequenceFormatError(f"{csv_path}:{line}: field 'stamp' is not a number: "
                                      f"{row['stamp']!r}") from None
        if not np.isfinite(stamp):
            raise SequenceFormatError(f"{csv_path}:{line}: field 'stamp' is not finite")
        check_seconds(stamp, f"{csv_path}:{line}", "stamp")
        if stamp <= prev:
            raise SequenceFormatError(f"{csv_path}:{line}: field 'stamp' not strictly increasing "
                                      f"({prev!r} then {stamp!r})")
        prev = stamp
        if not row.get("image"):
            raise SequenceFormatError(f"{csv_path}:{line}: field 'image' is empty or missing "
                                      "(a row: index,stamp,image[,gt_depth,gt_mask])")
        img = base / row["image"]
        if not img.exists():
            raise SequenceFormatError(f"{csv_path}:{line}: field 'image' names {img}, which "
                                      "does not exist")
        frames.append(CameraFrame(stamp=stamp, path=img, index=i))
        if row.get("gt_depth"):
            depth.append(base / row["gt_depth"])
        if row.get("gt_mask"):
            masks.append(base / row["gt_mask"])
    for name, lst in (("gt_depth", depth), ("gt_mask", masks)):
        if lst and len(lst) != len(frames):
            raise SequenceFormatError(f"{csv_path}: field '{name}' is given for {len(lst)} of "
                                      f"{len(frames)} frames; give it for all or none")
    return frames, (depth or None), (masks or None)


# ---------------------------------------------------------------------------- reading


# Files of camera/images that count as frames (not Thumbs.db, desktop.ini, notes).
_IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp",
                             ".ppm", ".pgm", ".jp2", ".exr"})


# Names of the robot's base frame (REP 105) a trajectory header may use for base_link.
_BASE_NAMES = ("base_link", "base_footprint", "base")


def _read_pose_file(path: Path, frame: str | None = None, child: str | None = None) -> (
    Trajectory
):
    """``read_tum`` whose errors (a line cut short, a NaN, stamps going back; each named
    by file and line) are the sequence's: the calibration CLI printed the plain
    ValueError's traceback."""
    try:
        return read_tum(path, frame, child)
    except ValueError as e:
        raise SequenceFormatError(str(e)) from None


def _read_base_trajectory(path: Path, frame: str) -> Trajectory:
    """T_<frame>_base_link poses of ``path`` (odometry.tum, poses_base.tum). A header
    (``# T_a_b: b pose in a``, as format_tum writes) naming other frames is refused: camera
    or laser poses, or inverted ones, were read as base poses without a word."""
    # Read once with the header's frames (world / base_link without one), then checked.
    traj = _read_pose_file(path)
    h_frame, h_child = traj.frame, traj.child
    said = f"its header says the poses are T_{h_frame}_{h_child} ({h_child} in {h_frame})"
    want = f"this file holds T_{frame}_base_link (base_link poses in a fixed frame)"
    if h_frame in _BASE_NAMES:
        raise SequenceFormatError(
            f"{path}: {said}, {want}. Fix: invert every pose (T_{h_child}_{h_frame} = "
            f"inv(T_{h_frame}_{h_child})) and write the header '# T_{frame}_base_link: "
            f"base_link pose in {frame}'")
    if h_child not in _BASE_NAMES:
        mount = ("T_base_camera from rig.yaml" if h_child.startswith("camera")
                 else "T_base_laser from rig.yaml"
                 if h_child.startswith(("laser", "lidar", "scan", "base_scan"))
                 else f"T_base_{h_child}, where {h_child} sits on the base")
        raise SequenceFormatError(
            f"{path}: {said}, {want}. Fix: write T_{h_frame}_base_link = "
            f"T_{h_frame}_{h_child} @ inv(T_base_{h_child}) ({mount}) under the header "
            f"'# T_{h_frame}_base_link: base_link pose in {h_frame}'")
    check_seconds(traj.stamps, str(path), "timestamp")
    return Trajectory(traj.stamps, traj.poses, frame, "base_link")


def _check_overlap(spans: list[tuple[str, np.ndarray]], root: Path) -> None:
    """Refuse files whose stamps [N] share no moment with another's: stamps on two clocks
    (or in two units) that a stage later met as 'no scan near this frame'."""
    spans = [(name, st) for name, st in spans if len(st)]
    slack = 1.0  # seconds: a frame just before the first scan is no clock mismatch
    for i, (a, sa) in enumerate(spans):
        for b, sb in spans[i + 1:]:
            if max(sa[0], sb[0]) > min(sa[-1], sb[-1]) + slack:
                raise SequenceFormatError(
                    f"{root}: {a} spans {sa[0]:.3f} .. {sa[-1]:.3f} s and {b} "
                    f"{sb[0]:.3f} .. {sb[-1]:.3f} s: they share no moment, so their stamps are "
                    "on different clocks. Fix: write every file's stamps on one clock (add "
                    "the offset between the clocks to one of them)")


def _sequences_below(root: Path) -> list[Path]:
    """Sequence folders one or two levels down: a recipe run folder keeps its sequence in
    ``<stage>/sequence``, and "runs/NAME" or "runs/NAME/simulate" is what users pass."""
    found = [root / "sequence"] + sorted(root.glob("*/sequence"))
    return [p for p in found if (p / "rig.yaml").is_file()]


# meta.yaml's yes/no fields, read as YAML booleans only.
_META_FLAGS = ("has_camera", "check_image_size", "rectified_images")


def check_sequence_folder(root: Path) -> None:
    """Raise ``SequenceFormatError`` naming the sequence inside ``root`` when ``root`` is a
    run or stage folder holding one rather than a sequence folder itself."""
    if (root / "rig.yaml").exists():
        return
    inner = _sequences_below(root)
    if inner:
        raise SequenceFormatError(
            f"{root}: not a sequence folder (no rig.yaml); give the sequence folder in it: "
            f"{' or '.join(str(p) for p in inner)}")


def read_sequence(root: Path | str) -> Sequence:
    """Load a sequence folder (images stay on disk until used).

    ``meta.yaml`` and each of its keys are optional: a folder is a sequence by its
    ``rig.yaml`` (``check_sequence_folder``), and a hand-made one (rig.yaml, frames.csv,
    scans.npz) is read without a meta.yaml at all. So a meta.yaml without ``format`` is
    read as ``lidarcam-sequence``, without ``version`` as version 1 and without ``name``
    under the folder's name; ``format`` refuses a meta.yaml that names another format,
    and ``version`` one newer than this toolkit reads. (Requiring ``format`` in a
    meta.yaml would refuse a folder that deleting the file makes readable.)
    ``SequenceWriter`` always writes all three.

    A folder ``SequenceWriter`` left without meta.yaml is refused as unfinished: it
    writes meta.yaml last and only then removes its frame journal, so the journal
    without meta.yaml is a write cut short (ground truth, odometry or held-out views
    may be missing)."""
    root = Path(root)
    if not root.is_dir():
        # A file named here was reported as "not found" though it exists.
        raise SequenceFormatError(
            f"{root}: is a file, not a sequence folder (the one holding rig.yaml and "
            "meta.yaml)" if root.exists() else f"{root}: sequence folder not found")
    meta_path = root / "meta.yaml"
    if (root / JOURNAL_NAME).exists() and not meta_path.exists():
        # close() writes rig.yaml, frames.csv and scans.npz before the ground truth and
        # meta.yaml: cut short between them, the folder read as a sequence without them.
        raise SequenceFormatError(
            f"{root}: unfinished sequence: its writer stopped before meta.yaml, which it "
            f"writes last ({JOURNAL_NAME} is still there); write it again (a recipe reruns "
            "the stage that writes it)")
    check_sequence_folder(root)
    meta: dict[str, Any] = {}
    if meta_path.exists():
        meta = load_yaml(meta_path, SequenceFormatError) or {}
        if not isinstance(meta, dict):
            raise SequenceFormatError(f"{meta_path}: expected a mapping (format, version, "
                                      f"name, ...), got {type(meta).__name__}")
        try:
            version = int(meta.get("version", FORMAT_VERSION))
        except (TypeError, ValueError):
            raise SequenceFormatError(f"{meta_path}: field 'version' is "
                                      f"{meta.get('version')!r}, not a whole number") from None
        if meta.get("format", FORMAT_NAME) != FORMAT_NAME:
            raise SequenceFormatError(f"{meta_path}: field 'format' is {meta.get('format')!r}, "
                                      f"expected {FORMAT_NAME!r}")
        if version > FORMAT_VERSION:
            raise SequenceFormatError(f"{meta_path}: field 'version' {meta['version']} is newer "
                                      f"than this toolkit reads ({FORMAT_VERSION}); upgrade it")
        for key in _META_FLAGS:
            # bool() of a quoted "false" is True: a lidar-only recording was taken to
            # have a camera.
            if key in meta and not isinstance(meta[key], bool):
                raise SequenceFormatError(
                    f"{meta_path}: field '{key}' is {meta[key]!r}, not a YAML boolean; write "
                    f"{key}: true or {key}: false (unquoted)")
    rig = read_rig(root / "rig.yaml")
    cam_dir = root / "camera"
    frames_csv = cam_dir / "frames.csv"
    frames: list[CameraFrame] = []
    gt_depth = gt_mask = None
    if frames_csv.exists():
        frames, gt_depth, gt_mask = _frames_from_rows(_read_frames_csv(frames_csv), cam_dir,
                                                      frames_csv)
        images_dir = cam_dir / "images"
        if images_dir.is_dir():
            # Images only: Windows' Thumbs.db or a notes file made a valid folder unreadable.
            on_disk = [p for p in images_dir.iterdir() if not p.name.startswith(".")
                       and p.suffix.lower() in _IMAGE_SUFFIXES]
            if len(on_disk) != len(frames):
                listed = {f.path.resolve() for f in frames if f.path is not None}
                unlisted = sorted(p.name for p in on_disk if p.resolve() not in listed)
                raise SequenceFormatError(
                    f"{frames_csv}: lists {len(frames)} images but {images_dir} holds "
                    f"{len(on_disk)}" + (f" (not listed: {', '.join(unlisted[:3])}"
                                         f"{', ...' if len(unlisted) > 3 else ''})"
                                         if unlisted else "")
                    + "; the index and the folder disagree (an interrupted copy?)")
    scans = read_scans(root / "scans.npz") if (root / "scans.npz").exists() else []
    if not frames and not scans:
        raise SequenceFormatError(f"{root}: neither camera/frames.csv nor scans.npz found; "
                                  "a sequence needs images, scans or both")
    odom = _read_base_trajectory(root / "odometry.tum", "odom") if (
        root / "odometry.tum").exists() else None
    gt = _read_groundtruth(root, gt_depth, gt_mask, len(scans),
                           len(scans[0].ranges) if scans else 0)
    _check_overlap([("camera/frames.csv", np.array([f.stamp for f in frames])),
                    ("scans.npz", np.array([sc.stamp for sc in scans])),
                    ("odometry.tum", odom.stamps if odom is not None else np.zeros(0))], root)
    if gt is not None and gt.exposure_gain is not None and len(gt.exposure_gain) != len(frames):
        raise SequenceFormatError(
            f"{root / 'groundtruth' / 'exposure_gain.csv'}: {len(gt.exposure_gain)} gains for "
            f"{len(frames)} frames; one row per frame of camera/frames.csv")
    seq = Sequence(rig=rig, frames=frames, scans=scans, odometry=odom, groundtruth=gt,
                   name=str(meta.get("name", root.name)), root=root, meta=meta)
    w, h = rig.camera.size
    if frames and meta.get("check_image_size", True):
        first = cv2.imread(str(frames[0].path), cv2.IMREAD_UNCHANGED)
        if first is None:
            raise SequenceFormatError(f"{frames[0].path}: unreadable image")
        if first.shape[1] != w or first.shape[0] != h:
            raise SequenceFormatError(
                f"{frames[0].path}: image is {first.shape[1]}x{first.shape[0]} but "
                f"{root / 'rig.yaml'} field 'camera' says {w}x{h}")
        _check_8bit(frames[0].path, first)
        # The others from their headers (a decode each cost more than reading the folder).
        for f in frames[1:]:
            head = image_header(f.path)  # type: ignore[arg-type]
            if head is None:
                continue
            fw, fh, bits = head
            if (fw, fh) != (w, h):
                raise SequenceFormatError(
                    f"{f.path}: image is {fw}x{fh} but {root / 'rig.yaml'} field 'camera' "
                    f"says {w}x{h} (frame {f.index}; every frame must be the camera's size)")
            if bits != 8:
                raise SequenceFormatError(
                    f"{f.path}: a {bits}-bit image (frame {f.index}); frames are 8-bit RGB: "
                    "convert it (12-bit data divided by 16)")
        # Ground truth of another size failed deep in a stage (an index error in fuse's
        # labels, a shape mismatch in its depth figures) after the work before it.
        for kind, paths in (("depth", gt_depth), ("mask", gt_mask)):
            if not paths:
                continue
            from toolkit.io.depth import read_depth

            try:
                g = read_depth(paths[0]) if kind == "depth" else gt.mask(0)  # type: ignore
            except (OSError, ValueError) as exc:
                raise SequenceFormatError(f"ground-truth {kind}: {exc}") from exc
            if g.shape[:2] != (h, w):
                raise SequenceFormatError(
                    f"{paths[0]}: ground-truth {kind} is {g.shape[1]}x{g.shape[0]} but the "
                    f"images are {w}x{h} ({root / 'rig.yaml'} field 'camera'): write it at "
                    "the image size, or drop the column from camera/frames.csv")
    return seq


_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def image_header(path: Path, max_bytes: int = 1 << 17) -> tuple[int, int, int] | None:
    """(width, height, bits per sample) of a PNG or JPEG from its header, without decoding
    the pixels; None for other formats or a header not found in the first ``max_bytes``."""
    with open(path, "rb") as fh:
        data = fh.read(32)
        if data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR" and len(data) >= 25:
            w, h = struct.unpack(">II", data[16:24])
            return int(w), int(h), int(data[24])
        if data[:2] != b"\xff\xd8":
            return None
        # A JPEG's frame header follows its tables: walk the segments' lengths, reading
        # only their markers (the whole first 128 KiB was most frames' every byte, read
        # on every read_sequence).
        i = 2
        while i + 4 <= max_bytes:
            fh.seek(i)
            head = fh.read(4)
            if len(head) < 2 or head[0] != 0xFF:
                return None
            marker = head[1]
            if marker == 0xFF:  # fill byte
                i += 1
                continue
            if marker in (0x01, *range(0xD0, 0xDA)):  # standalone markers carry no length
                i += 2
                continue
            if len(head) < 4:
                return None
            (length,) = struct.unpack(">H", head[2:4])
            if marker in _JPEG_SOF and i + 9 <= max_bytes:
                sof = fh.read(5)
                if len(sof) < 5:
                    return None
                h, w = struct.unpack(">HH", sof[1:5])
                return int(w), int(h), int(sof[0])
            i += 2 + length
    return None


def _check_8bit(path: Path, pixels: np.ndarray) -> None:
    """Refuse a frame that is not 8-bit: OpenCV's colour read keeps the top 8 of 16 bits,
    so 12-bit data (4000) became 15 of 255, a near-black image, without a word."""
    if pixels.dtype != np.uint8:
        hi = int(pixels.max())
        raise SequenceFormatError(
            f"{path}: a {pixels.dtype} image (brightest value {hi}); frames are 8-bit RGB. "
            "Fix: convert the frames to 8 bits (12-bit data divided by 16, 16-bit by 256)")


def _read_exposure_gains(path: Path) -> np.ndarray:
    """[F] gains from ``index,stamp,gain`` rows, one per frame in frame order."""
    rows = _csv_rows(path)
    try:
        idx = np.array([int(r["index"]) for r in rows])
        gains = np.array([float(r["gain"]) for r in rows])
    except (KeyError, TypeError, ValueError) as exc:
        raise SequenceFormatError(f"{path}: needs columns index,stamp,gain with an integer "
                                  f"index and a number gain per row ({exc})") from exc
    if not np.array_equal(idx, np.arange(len(idx))) or not (gains > 0).all():
        raise SequenceFormatError(f"{path}: rows must be the frames 0, 1, 2, ... in order "
                                  "with positive gains; rewrite it or remove it")
    return gains


def _read_groundtruth(root: Path, depth: list[Path] | None, masks: list[Path] | None,
                      n_scans: int, n_beams: int) -> GroundTruth | None:
    gdir = root / "groundtruth"
    if not gdir.is_dir() and depth is None and masks is None:
        return None
    gt = GroundTruth(depth_paths=depth, mask_paths=masks)
    if (gdir / "poses_base.tum").exists():
        gt.poses_base = _read_base_trajectory(gdir / "poses_base.tum", "world")
    if (gdir / "scan_dynamic.npz").exists():
        with np.load(gdir / "scan_dynamic.npz") as d:
            if "dynamic" not in d.files:
                raise SequenceFormatError(f"{gdir / 'scan_dynamic.npz'}: missing array 'dynamic'")
            dyn = d["dynamic"].astype(bool)
        if dyn.shape != (n_scans, n_beams):
            raise SequenceFormatError(f"{gdir / 'scan_dynamic.npz'}: 'dynamic' is "
                                      f"{list(dyn.shape)} for {n_scans} scans of {n_beams} "
                                      "beams; rewrite it with one flag per beam of every scan")
        gt.scan_dynamic = dyn
    if (gdir / "mesh.ply").exists():
        gt.mesh_path = gdir / "mesh.ply"
    if (gdir / "exposure_gain.csv").exists():
        gt.exposure_gain = _read_exposure_gains(gdir / "exposure_gain.csv")
    hdir = gdir / "heldout"
    if (hdir / "frames.csv").exists():
        rows = _read_frames_csv(hdir / "frames.csv")
        frames, hdepth, _ = _frames_from_rows(rows, hdir, hdir / "frames.csv")
        poses = _read_pose_file(hdir / "poses_camera.tum", "world", "camera")
        check_seconds(poses.stamps, str(hdir / "poses_camera.tum"), "timestamp")
        if len(poses) != len(frames):
            raise SequenceFormatError(f"{hdir / 'poses_camera.tum'}: {len(poses)} poses for "
                                      f"{len(frames)} held-out images")
        gt.heldout = HeldOutViews(poses, [f.path for f in frames], hdepth or [])
    return gt


# ---------------------------------------------------------------------------- writing


JOURNAL_NAME = ".frames.journal.jsonl"
# What a SequenceWriter writes into its folder.
_SEQUENCE_ENTRIES = ("camera", "groundtruth", "scans.npz", "odometry.tum", "rig.yaml",
                     "meta.yaml", JOURNAL_NAME)


def _clear_sequence(root: Path) -> None:
    """Remove an earlier sequence (finished or not) from ``root`` before writing a new one:
    its images, held-out views or odometry must not outlive it. A folder holding such
    names without being a sequence is left alone and refused."""
    present = [n for n in _SEQUENCE_ENTRIES if (root / n).exists()]
    if not present:
        return
    if not ((root / "meta.yaml").exists() or (root / JOURNAL_NAME).exists()):
        raise SequenceFormatError(f"{root}: holds {present} but is no sequence folder; write "
                                  "the sequence into an empty or new folder")
    for n in present:
        p = root / n
        shutil.rmtree(p) if p.is_dir() else p.unlink()


class SequenceWriter:
    """Stream a recording into a sequence folder.

    Images and depth maps are written as they come (each atomically); the index files
    (frames.csv, scans.npz, trajectories, meta.yaml) are written by ``close()``, meta.yaml
    last, so a folder without meta.yaml is an unfinished one (``read_sequence`` refuses it
    while the journal is there).

    Every frame is also appended to a journal once its files are in place. ``resume=True``
    reads the journal of an earlier, unfinished writer on the same folder and continues
    after its last frame (``resumed_frames``, ``last_frame_stamp``); files of frames the
    journal does not list are removed. Only camera frames are journaled: scans,
    trajectories, held-out views and ``extra_meta`` live in memory until ``close()`` and
    must be given again. The caller must make sure the earlier writer converted the same
    input with the same settings.

    ``workers`` > 0 encodes and writes each frame's files in that many threads while the
    caller produces the next frames (OpenCV's PNG and JPEG codecs release the GIL). The
    files are the same bytes under the same names as without; frames are journaled in
    order as their files land, so an interrupted run loses at most the frames in flight
    (at most ``2 * workers``), whose files a resumed writer removes. ``flush()`` (called by
    ``close()``) waits for them; a failed write is raised there or by a later
    ``add_frame``. The arrays given to ``add_frame`` are then read after it returns: the
    caller must not change them.
    """

    def __init__(self, root: Path | str, rig: Rig, name: str = "sequence",
                 source: str = "", depth_format: str = "png", resume: bool = False,
                 workers: int = 0) -> None:
        if depth_format not in ("png", "npy"):
            raise ValueError("depth_format must be 'png' (16-bit, 0.2 mm) or 'npy' (float32)")
        self.root = Path(root)
        self.rig = rig
        self.name = name
        self.source = source
        self.depth_format = depth_format
        self.root.mkdir(parents=True, exist_ok=True)
        if not resume:
            _clear_sequence(self.root)
        (self.root / "meta.yaml").unlink(missing_ok=True)
        self._rows: list[dict[str, str]] = []
        self._scans: list[LaserScan] = []
        self._dynamic: list[np.ndarray] = []
        self._held_rows: list[dict[str, str]] = []
        self._held_poses: list[tuple[float, np.ndarray]] = []
        self.odometry: Trajectory | None = None
        self.groundtruth_poses: Trajectory | None = None
        self.extra_meta: dict[str, Any] = {}
        # Depth pixels written as invalid because the format cannot hold them (a PNG's
        # 13.107 m), by this writer (not the frames a resumed run kept).
        self.depth_pixels_beyond_format = 0
        self._journal_path = self.root / JOURNAL_NAME
        if resume:
            self._rows = _read_journal(self._journal_path, self.root / "camera")
            _remove_unlisted_frames(self.root, len(self._rows))
        else:
            self._journal_path.unlink(missing_ok=True)
        # Rewritten (atomically) from the rows kept, which drops a torn last line.
        atomic_write_text(self._journal_path, "".join(json.dumps(r) + "\n" for r in self._rows))
        self._journal = self._journal_path.open("a", encoding="utf-8")
        self.resumed_frames = len(self._rows)
        self._pool = ThreadPoolExecutor(workers, thread_name_prefix="frames") \
            if workers > 0 else None
        self._max_pending = 2 * workers  # frames held in memory while they are encoded
        # (stamp, its files being written) in frame order
        self._pending: deque[tuple[float, Future[tuple[dict[str, str], int]]]] = deque()

    @property
    def num_frames(self) -> int:
        """Camera frames added so far (including resumed ones and ones still in flight)."""
        return len(self._rows) + len(self._pending)

    @property
    def frame_stamps(self) -> np.ndarray:
        """[F] stamps of the frames added so far (including resumed ones)."""
        return np.array([float(r["stamp"]) for r in self._rows]
                        + [s for s, _ in self._pending], dtype=np.float64)

    @property
    def last_frame_stamp(self) -> float | None:
        """Stamp of the last frame added, None before the first."""
        if self._pending:
            return self._pending[-1][0]
        return float(self._rows[-1]["stamp"]) if self._rows else None

    def add_frame(self, stamp: float, image: np.ndarray | None,
                  gt_depth: np.ndarray | None = None,
                  gt_mask: np.ndarray | None = None, image_path: Path | None = None,
                  image_jpeg: bytes | None = None) -> int:
        """Write one RGB image [H, W, 3] (or copy ``image_path``) with optional ground truth.

        ``image_jpeg``: the JPEG ``image`` was decoded from (a CompressedImage's payload).
        It is stored as it is, as is a JPEG ``image_path``, where every reader decodes it to
        the same pixels (``jpeg_as_is``); otherwise the pixels go into a PNG."""
        i = self.num_frames
        # Checked here, not by the reader only: a NaN passed 'stamp <= previous' (and
        # disabled it for the next frame), and the folder was refused after the whole
        # recording had been written.
        if not np.isfinite(stamp):
            raise ValueError(f"frame {i}: stamp {stamp!r} is not finite")
        check_seconds(stamp, f"frame {i}", "stamp")
        last = self.last_frame_stamp
        if last is not None and stamp <= last:
            raise ValueError(f"frame {i}: stamp {float(stamp)!r} not after the previous "
                             f"frame's {last!r}")
        if self._pool is None:
            self._journal_frame(i, stamp, *self._write_frame_files(
                i, image, gt_depth, gt_mask, image_path, image_jpeg))
            return i
        self._pending.append((float(stamp), self._pool.submit(
            self._write_frame_files, i, image, gt_depth, gt_mask, image_path, image_jpeg)))
        self._journal_done(wait_above=self._max_pending)
        return i

    def flush(self) -> None:
        """Wait for the frames in flight and journal them (raising a failed write)."""
        self._journal_done(wait_above=0)

    def _journal_done(self, wait_above: int) -> None:
        """Journal the finished frames at the head of the queue, in order, waiting for the
        oldest while more than ``wait_above`` are in flight."""
        while self._pending and (self._pending[0][1].done()
                                 or len(self._pending) > wait_above):
            stamp, fut = self._pending[0]
            files, beyond = fut.result()  # a failed write stops here, unjournaled
            self._pending.popleft()
            self._journal_frame(len(self._rows), stamp, files, beyond)

    def _journal_frame(self, i: int, stamp: float, files: dict[str, str],
                       beyond: int) -> None:
        row = {"index": str(i), "stamp": repr(float(stamp)), **files}
        self.depth_pixels_beyond_format += beyond
        self._rows.append(row)
        # After the files: a journaled frame is always complete on disk. Flushed, not
        # fsynced: this guards against a killed process, not against power loss.
        self._journal.write(json.dumps(row) + "\n")
        self._journal.flush()

    def _write_frame_files(self, i: int, image: np.ndarray | None,
                           gt_depth: np.ndarray | None, gt_mask: np.ndarray | None,
                           image_path: Path | None, image_jpeg: bytes | None,
                           ) -> tuple[dict[str, str], int]:
        """Write frame ``i``'s files (in a worker thread with ``workers``): frames.csv's
        file columns (paths relative to camera/) and the depth pixels written as invalid
        because the format cannot hold them."""
        rel = f"images/{i:06d}.png"
        dst = self.root / "camera" / rel
        dst.parent.mkdir(parents=True, exist_ok=True)
        w, h = self.rig.camera.size
        suffix = Path(image_path).suffix.lower() if image_path is not None else ""
        if image is None and image_path is not None and suffix != ".png":
            # Another format (a JPEG sequence): decoded; a JPEG kept as it is where exact.
            if image_header(Path(image_path)) is None:  # TIFF, JPEG 2000, ...
                # The colour read keeps the top 8 of 16 bits: 12-bit data went dark.
                raw = cv2.imread(str(image_path),
                                 cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION)
                if raw is not None:
                    _check_8bit(Path(image_path), raw)
            image = load_rgb(Path(image_path))
            if image.shape[:2] != (h, w):
                raise InputError(f"{image_path}: frame {i} is {image.shape[1]}x"
                                 f"{image.shape[0]}, the camera {w}x{h}")
            if image_jpeg is None and suffix in (".jpg", ".jpeg"):
                image_jpeg = Path(image_path).read_bytes()
        if image_jpeg is not None and image is not None and jpeg_as_is(image_jpeg, image):
            rel = f"images/{i:06d}.jpg"
            atomic_write_bytes(self.root / "camera" / rel, image_jpeg)
        elif suffix == ".png":
            # Decoded once here: a truncated or foreign file copied unread failed stages
            # later, naming this copy (which a rerun then overwrote with the bad source).
            data = Path(image_path).read_bytes()  # type: ignore[arg-type]
            # An empty buffer is OpenCV's assertion error, naming no file.
            pixels = (cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
                      if data else None)
            if pixels is None:
                raise InputError(f"{image_path}: frame {i} is not a readable PNG image "
                                 "(truncated or another format); replace it and run again")
            if pixels.shape[:2] != (h, w):
                raise InputError(f"{image_path}: frame {i} is {pixels.shape[1]}x"
                                 f"{pixels.shape[0]}, the camera {w}x{h}")
            _check_8bit(Path(image_path), pixels)  # type: ignore[arg-type]
            atomic_write_bytes(dst, data)
        else:
            if image is None:
                raise ValueError(f"frame {i}: neither pixels nor an image path")
            _write_rgb(dst, image)
        if gt_depth is not None and np.shape(gt_depth)[:2] != (h, w):
            raise ValueError(f"frame {i}: ground-truth depth of {np.shape(gt_depth)[1]}x"
                             f"{np.shape(gt_depth)[0]}, the camera {w}x{h}")
        files = {"image": rel}
        beyond = 0
        if gt_depth is not None:
            files["gt_depth"] = f"../groundtruth/depth/{i:06d}.{self.depth_format}"
            p = self.root / "camera" / files["gt_depth"]
            p.parent.mkdir(parents=True, exist_ok=True)
            beyond = write_depth(p, gt_depth)
        if gt_mask is not None:
            files["gt_mask"] = f"../groundtruth/masks/{i:06d}.png"
            p = self.root / "camera" / files["gt_mask"]
            p.parent.mkdir(parents=True, exist_ok=True)
            with atomic_path(p) as tmp:
                cv2.imwrite(str(tmp), (np.asarray(gt_mask) > 0).astype(np.uint8) * 255)
        return files, beyond

    def add_scan(self, scan: LaserScan, dynamic: np.ndarray | None = None) -> None:
        """Keep one scan for ``close()``; its stamp must be finite and after the last's."""
        k = len(self._scans)
        if not np.isfinite(scan.stamp):
            raise ValueError(f"scan {k}: stamp {scan.stamp!r} is not finite")
        check_seconds(scan.stamp, f"scan {k}", "stamp")
        if self._scans and scan.stamp <= self._scans[-1].stamp:
            raise ValueError(f"scan {k}: stamp {float(scan.stamp)!r} not after scan {k - 1}'s "
                             f"{float(self._scans[-1].stamp)!r}; sort the scans by stamp and "
                             "drop repeated stamps")
        self._scans.append(scan)
        if dynamic is not None:
            self._dynamic.append(np.asarray(dynamic, dtype=bool))

    def add_heldout(self, stamp: float, T_world_camera: np.ndarray, image: np.ndarray,
                    depth: np.ndarray) -> None:
        i = len(self._held_rows)
        hdir = self.root / "groundtruth" / "heldout"
        (hdir / "images").mkdir(parents=True, exist_ok=True)
        (hdir / "depth").mkdir(parents=True, exist_ok=True)
        _write_rgb(hdir / f"images/{i:06d}.png", image)
        self.depth_pixels_beyond_format += write_depth(
            hdir / f"depth/{i:06d}.{self.depth_format}", depth)
        self._held_rows.append({"index": str(i), "stamp": repr(float(stamp)),
                                "image": f"images/{i:06d}.png",
                                "gt_depth": f"depth/{i:06d}.{self.depth_format}"})
        self._held_poses.append((stamp, np.asarray(T_world_camera, dtype=np.float64)))

    def mesh_path(self) -> Path:
        """Where to write the ground-truth mesh (PLY)."""
        p = self.root / "groundtruth" / "mesh.ply"
        p.parent.mkdir(parents=True, exist_ok=True)
        return p

    def discard(self) -> None:
        """Stop without finishing: the journal is closed, nothing more is written (a new
        writer without ``resume`` then clears the folder's sequence files). Frames in
        flight are finished and journaled up to the first that failed, so a resumed
        writer keeps them."""
        try:
            self._stop_pool()
        finally:
            self._journal.close()

    def _stop_pool(self) -> None:
        """Let the frames in flight land, journal those written in order, stop the threads."""
        if self._pool is None:
            return
        self._pool.shutdown(wait=True)
        while self._pending and self._pending[0][1].exception() is None:
            stamp, fut = self._pending.popleft()
            self._journal_frame(len(self._rows), stamp, *fut.result())
        self._pending.clear()
        self._pool = None

    def close(self) -> Path:
        self.flush()
        self._stop_pool()
        write_rig(self.root / "rig.yaml", self.rig)
        if self._rows:
            _write_csv(self.root / "camera" / "frames.csv", self._rows)
        if self._scans:
            write_scans(self.root / "scans.npz", self._scans)
        if self._dynamic:
            if len(self._dynamic) != len(self._scans):
                raise ValueError("dynamic beam masks given for some scans only")
            buf = io.BytesIO()
            np.savez_compressed(buf, dynamic=np.stack(self._dynamic))
            (self.root / "groundtruth").mkdir(exist_ok=True)
            atomic_write_bytes(self.root / "groundtruth" / "scan_dynamic.npz", buf.getvalue())
        if self.odometry is not None:
            write_tum(self.root / "odometry.tum", self.odometry, "wheel odometry")
        if self.groundtruth_poses is not None:
            (self.root / "groundtruth").mkdir(exist_ok=True)
            write_tum(self.root / "groundtruth" / "poses_base.tum", self.groundtruth_poses,
                      "ground truth")
        if self._held_rows:
            hdir = self.root / "groundtruth" / "heldout"
            _write_csv(hdir / "frames.csv", self._held_rows)
            st = np.array([s for s, _ in self._held_poses])
            write_tum(hdir / "poses_camera.tum",
                      Trajectory(st, np.stack([T for _, T in self._held_poses]), "world",
                                 "camera"), "held-out views (not on the driven path)")
        meta = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "name": self.name,
                "source": self.source, "frames": len(self._rows), "scans": len(self._scans),
                **self.extra_meta}
        atomic_write_text(self.root / "meta.yaml", yaml.safe_dump(meta, sort_keys=False))
        self._journal.close()
        self._journal_path.unlink(missing_ok=True)
        return self.root


_INDEXED = re.compile(r"^(\d{6})\.[a-z]+$")


def _read_journal(path: Path, camera_dir: Path) -> list[dict[str, str]]:
    """Frame rows of an unfinished writer, up to the first torn line or missing file."""
    rows: list[dict[str, str]] = []
    if not path.exists():
        return rows
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            row = json.loads(line)
        except ValueError:
            break  # killed mid-line: everything before it is whole
        if not isinstance(row, dict) or row.get("index") != str(len(rows)):
            break
        files = [row.get("image"), row.get("gt_depth"), row.get("gt_mask")]
        if not all((camera_dir / f).exists() for f in files if f):
            break
        rows.append({str(k): str(v) for k, v in row.items()})
    return rows


def _remove_unlisted_frames(root: Path, n: int) -> None:
    """Delete per-frame files with index >= n (written after the last journaled frame),
    which would otherwise make the folder disagree with its index, and the temporaries of
    writes a kill cut short (up to one per encoding thread)."""
    for sub in ("camera/images", "groundtruth/depth", "groundtruth/masks"):
        d = root / sub
        if not d.is_dir():
            continue
        remove_temps_under(d)
        for p in d.iterdir():
            m = _INDEXED.match(p.name)
            if m and int(m.group(1)) >= n:
                p.unlink()


def jpeg_as_is(data: bytes, image: np.ndarray) -> bool:
    """Whether JPEG bytes ``data`` can be stored as they are for the RGB pixels ``image``
    [H, W, 3]: a JPEG whose decoding, with its EXIF orientation ignored (``load_rgb``, the
    toolkit's reader) and applied (other programs' readers, e.g. COLMAP's), gives exactly
    those pixels. A 73 KB camera JPEG re-encoded as a lossless PNG took 590 KB and 14 ms
    (a long bag's conversion was mostly that); the decoded pixels are the same either way.
    A CMYK or 12-bit JPEG, or one with a turning orientation tag, goes into a PNG."""
    if len(data) < 4 or data[:2] != b"\xff\xd8":
        return False
    buf = np.frombuffer(data, np.uint8)
    img = np.asarray(image)
    for flags in (cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION, cv2.IMREAD_COLOR):
        try:
            bgr = cv2.imdecode(buf, flags)
        except cv2.error:
            return False
        if bgr is None or bgr.shape != img.shape or not np.array_equal(
                cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), img):
            return False
    return True


# Lossless PNG, tuned for speed: the simulator writes 20+ frames/s and a long bag's raw
# Image frames were mostly PNG encoding. Level 1 with the SUB filter (a third faster than
# the default filter at the same size on rendered images). Colour frames with zlib's
# Z_RLE strategy (run matches only): on camera-like synthetic frames (sensor noise, few
# long matches) 1.3x faster and 16% smaller than full matching (noise-free ones: 12%
# slower, 4% smaller). Grey frames stored as RGB (R = G = B, a mono camera's) keep full
# matching: RLE missed their repeats (265 -> 404 KB a frame, no faster). Figures and
# scripts in docs/ingest.md, "Long recordings".
PNG_PARAMS = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_SUB,
              cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE]
PNG_PARAMS_GREY = [cv2.IMWRITE_PNG_COMPRESSION, 1,
                   cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_SUB]


def _looks_grey(img: np.ndarray) -> bool:
    """Whether an [H, W, 3] image has R = G = B on every 16th row: only the PNG settings
    depend on it, both lossless, so a sample decides (the whole frame took 0.7 ms, 7% of
    a grey 640x480 frame's encoding)."""
    rows = img[::16]  # [ceil(H / 16), W, 3]
    return bool((rows[..., 0] == rows[..., 1]).all() and (rows[..., 1] == rows[..., 2]).all())


def _write_rgb(path: Path, image: np.ndarray) -> None:
    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise InputError(f"{path}: images must be RGB uint8 [H, W, 3], got {img.dtype} "
                         f"{img.shape}")
    with atomic_path(path) as tmp:
        params = PNG_PARAMS_GREY if _looks_grey(img) else PNG_PARAMS
        if not cv2.imwrite(str(tmp), cv2.cvtColor(img, cv2.COLOR_RGB2BGR), params):
            raise WriteError(f"{path}: could not write image")


def _write_csv(path: Path, rows: list[dict[str, str]]) -> None:
    fields: list[str] = []
    for r in rows:
        fields += [k for k in r if k not in fields]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, buf.getvalue())


# meta.yaml keys SequenceWriter writes itself (a copy's come from the writer, not the source)
_OWN_META = frozenset({"format", "version", "name", "source", "frames", "scans"})


def copy_groundtruth_files(seq: Sequence, w: SequenceWriter, kept: np.ndarray) -> None:
    """Write into ``w`` the ground truth of ``seq`` that its frames and scans do not carry:
    the mesh, the held-out views, the exposure gains of the frames ``kept`` [F] (source
    indices, in the order written) and ``house.json`` (a copy, or a re-synced one, lost
    the simulator's gains, and fuse its gain figures, without a word)."""
    gt = seq.groundtruth
    if gt is None:
        return
    if gt.mesh_path is not None:
        shutil.copyfile(gt.mesh_path, w.mesh_path())
    if gt.heldout is not None:
        from toolkit.io.depth import read_depth

        h = gt.heldout
        for j, T in enumerate(h.poses_camera.poses):
            w.add_heldout(h.poses_camera.stamps[j], T, load_rgb(h.image_paths[j]),
                          read_depth(h.depth_paths[j]))
    gt_dir = w.root / "groundtruth"
    if gt.exposure_gain is not None and len(kept):
        gt_dir.mkdir(exist_ok=True)
        stamps = w.frame_stamps  # [F] as written
        atomic_write_text(gt_dir / "exposure_gain.csv", "index,stamp,gain\n" + "".join(
            f"{k},{float(stamps[k])!r},{float(gt.exposure_gain[f])!r}\n"
            for k, f in enumerate(kept)))
    src = None if seq.root is None else Path(seq.root) / "groundtruth" / "house.json"
    if src is not None and src.exists():
        gt_dir.mkdir(exist_ok=True)
        shutil.copyfile(src, gt_dir / "house.json")


def write_sequence(seq: Sequence, root: Path | str, depth_format: str = "png") -> Path:
    """Write a whole in-memory or on-disk ``Sequence`` to ``root`` (copying image files)."""
    w = SequenceWriter(root, seq.rig, seq.name, str(seq.meta.get("source", "")), depth_format)
    gt = seq.groundtruth
    for i, f in enumerate(seq.frames):
        depth = gt.depth(i) if gt is not None and gt.depth_paths else None
        mask = gt.mask(i) if gt is not None and gt.mask_paths else None
        if f.path is not None and f._image is None:
            w.add_frame(f.stamp, None, depth, mask, image_path=f.path)
        else:
            w.add_frame(f.stamp, f.image, depth, mask)
    dyn = gt.scan_dynamic if gt is not None else None
    for k, s in enumerate(seq.scans):
        w.add_scan(s, None if dyn is None else dyn[k])
    w.odometry = seq.odometry
    if gt is not None:
        w.groundtruth_poses = gt.poses_base
        copy_groundtruth_files(seq, w, np.arange(len(seq.frames)))
    w.extra_meta.update({k: v for k, v in seq.meta.items() if k not in _OWN_META})
    return w.close()

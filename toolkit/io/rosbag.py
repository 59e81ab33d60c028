"""ROS 1 bags and ROS 2 bags (sqlite3 or mcap) through ``rosbags``, without ROS.

Reads ``sensor_msgs/LaserScan``, ``sensor_msgs/Image`` (rgb8, bgr8, rgba8, bgra8, mono8,
their 16-bit forms, YUV 4:2:2, 8- and 16-bit Bayer - converted to RGB as cv_bridge does -
and 16UC1 / 32FC1 depth), ``sensor_msgs/CompressedImage`` (jpeg/png, and
``compressedDepth``), ``sensor_msgs/CameraInfo`` (plumb_bob distortion),
``nav_msgs/Odometry`` and ``tf`` / ``tf_static`` into a ``Recording``
(``toolkit.ingest.recording``) that the ``ingest`` stage streams into a sequence folder.

Two passes over the bag: ``read_rosbag`` indexes it (scans, odometry, tf and
CameraInfo are read whole - they are small - while of the images only stamps and sizes
are kept), and ``Recording.load`` then decodes just the images the sync plan keeps.

Topics are found by message type (one LaserScan topic, one colour image topic, ...);
where a bag has several of a kind the error lists them and names the option that picks
one. The rig comes from tf: ``T_base_camera`` is base frame <- the image messages'
``header.frame_id`` (an optical frame: x right, y down, z forward), ``T_base_laser`` is
base frame <- the scans' ``header.frame_id``. A calibration YAML fills in or overrides
what tf lacks (see ``load_calibration``).
"""

from __future__ import annotations

import logging
import math
import re
from array import array
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal, NamedTuple

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial.transform import Rotation

from toolkit.camera import OPENCV_DIST_COUNTS, PinholeCamera, plumb_bob_distortion
from toolkit.geometry import (
    Trajectory,
    checked_rigid,
    inv_se3,
    pose_from_xyz_quat,
    rotation_angle,
)
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
from toolkit.io.sequence import warn_if_unreliable
from toolkit.io.yaml_file import load_yaml
from toolkit.sensors import LaserScan, Rig, image_down_angle_deg

_log = logging.getLogger("toolkit.io.rosbag")

# Message types as rosbags names them for ROS 1 and ROS 2 alike.
SCAN = "sensor_msgs/msg/LaserScan"
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
ODOMETRY = "nav_msgs/msg/Odometry"
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")

# A Bayer mosaic's ROS encoding -> OpenCV's demosaic (bilinear, as cv_bridge converts).
# ROS names the first 2x2 block row by row; OpenCV names a pattern by the second row's
# second and third pixels, so ROS rggb is OpenCV's BG (cv_bridge maps them the same way).
# The 16-bit mosaics are demosaiced at 16 bits, then scaled (cv_bridge's order).
BAYER_TO_RGB = {f"bayer_{pattern}{bits}": code
                for pattern, code in (("rggb", cv2.COLOR_BayerBG2RGB),
                                      ("bggr", cv2.COLOR_BayerRG2RGB),
                                      ("gbrg", cv2.COLOR_BayerGR2RGB),
                                      ("grbg", cv2.COLOR_BayerGB2RGB))
                for bits in (8, 16)}


class ColorEncoding(NamedTuple):
    """How a ``sensor_msgs/Image`` colour encoding is stored and turned into 8-bit RGB."""

    channels: int  # samples per pixel in a row (2 for packed YUV 4:2:2: Y, then U or V)
    bits: int  # per sample; 16 is scaled to 8 by 255/65535, as cv_bridge does for rgb8
    to_rgb: int | None  # OpenCV's conversion (cv_bridge's code for rgb8); None: RGB already


_GRAY = cv2.COLOR_GRAY2RGB
# cv_bridge reads 8UC3 as bgr8 and 8UC1 as mono8. YUV 4:2:2 as sensor_msgs'
# image_encodings lays it out: yuv422 is UYVY (U0 Y0 V0 Y1), yuv422_yuy2 is YUYV
# (Y0 U0 Y1 V0); ROS 2 names them uyvy / yuyv too (the old names deprecated). cv_bridge
# converts them with OpenCV's BT.601 (video range) 4:2:2 codes. nv21 / nv24 are not read:
# cv_bridge does not convert them either.
COLOR_ENCODINGS: dict[str, ColorEncoding] = {
    "rgb8": ColorEncoding(3, 8, None), "bgr8": ColorEncoding(3, 8, cv2.COLOR_BGR2RGB),
    "8UC3": ColorEncoding(3, 8, cv2.COLOR_BGR2RGB),
    "rgba8": ColorEncoding(4, 8, cv2.COLOR_RGBA2RGB),
    "bgra8": ColorEncoding(4, 8, cv2.COLOR_BGRA2RGB),
    "mono8": ColorEncoding(1, 8, _GRAY), "8UC1": ColorEncoding(1, 8, _GRAY),
    "rgb16": ColorEncoding(3, 16, None), "bgr16": ColorEncoding(3, 16, cv2.COLOR_BGR2RGB),
    "rgba16": ColorEncoding(4, 16, cv2.COLOR_RGBA2RGB),
    "bgra16": ColorEncoding(4, 16, cv2.COLOR_BGRA2RGB),
    "mono16": ColorEncoding(1, 16, _GRAY),
    "yuv422": ColorEncoding(2, 8, cv2.COLOR_YUV2RGB_UYVY),
    "uyvy": ColorEncoding(2, 8, cv2.COLOR_YUV2RGB_UYVY),
    "yuv422_yuy2": ColorEncoding(2, 8, cv2.COLOR_YUV2RGB_YUY2),
    "yuyv": ColorEncoding(2, 8, cv2.COLOR_YUV2RGB_YUY2),
    **{enc: ColorEncoding(1, 16 if enc.endswith("16") else 8, code)
       for enc, code in BAYER_TO_RGB.items()},
}
DEPTH_ENCODINGS = {"16UC1": 2, "32FC1": 4}  # millimetres / metres (REP 118)


_CALIB_EXAMPLE = """  T_base_camera:          # maps camera optical-frame points into the base frame
    parent: {base}
    child: {camera}
    xyz: [0.10, 0.0, 0.30]
    quat_xyzw: [0.5, -0.5, 0.5, -0.5]   # a level camera looking forward
  T_base_laser:           # maps laser points into the base frame
    parent: {base}
    child: {laser}
    xyz: [0.20, 0.0, 0.15]
    quat_xyzw: [0.0, 0.0, 0.0, 1.0]
(each may also be a 4x4 matrix given as a list of rows)"""


class BagError(IngestError):
    """A bag cannot be read or converted; the message names the bag, topic or field."""


class MissingTransformError(BagError):
    """tf does not connect the base frame to the camera or laser frame."""


# ---------------------------------------------------------------------------- options


class RosbagTopics(BaseModel):
    """Topic overrides; omitted means found by type, ``none`` means do not use."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    scan: str | None = None
    image: str | None = None  # sensor_msgs/Image or CompressedImage, colour
    depth: str | None = None  # registered depth (same size as the colour image)
    camera_info: str | None = None
    odometry: str | None = None


class RosbagFrames(BaseModel):
    """tf frame names of the rig."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    base: str = "base_link"
    camera: str | None = None  # default: header.frame_id of the image messages
    laser: str | None = None  # default: header.frame_id of the scans
    # "optical": the camera frame is x right, y down, z forward (ROS *_optical_frame).
    # "body": it is x forward, y left, z up (camera_link); the optical rotation is added.
    camera_convention: Literal["optical", "body"] = "optical"


class RosbagOptions(BaseModel):
    """Settings of the rosbag reader (``ingest`` key ``rosbag:``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    topics: RosbagTopics = RosbagTopics()
    frames: RosbagFrames = RosbagFrames()
    calibration: str | None = None  # YAML with camera / T_base_camera / T_base_laser
    stamps: Literal["header", "bag"] = "header"  # bag: the time the message was recorded
    # With header stamps: when (header stamp - recording time) differs between the scans
    # and another topic, recorded at the same moment, by more than this, their drivers
    # stamp on different clocks (TAI +37 s, GPS +18 s, time since boot) and pairing by stamp
    # would be wrong: an error. null: no check (a topic that reached the recorder this late).
    max_clock_offset_s: float | None = Field(5.0, gt=0)
    # Images already undistorted (image_rect): intrinsics from CameraInfo P, no distortion.
    # Default: true when the image topic's name contains "rect".
    rectified: bool | None = None
    # Per-beam times (LaserScan time_increment) de-skew scans swept while the robot moved.
    # use: the stamp is the first beam's (ROS's convention); last_beam: the driver stamps
    # the end of the sweep (the stamps move back by the sweep); ignore: drop the timing, for
    # a driver that publishes a wrong time_increment.
    beam_timing: Literal["use", "last_beam", "ignore"] = "use"


# ---------------------------------------------------------------------------- the bag


# The storage files of a ROS 2 bag (rosbag2's sqlite3 and mcap plugins).
ROS2_STORAGE = (".db3", ".mcap")


def bag_paths(path: Path | str | Sequence[Path | str]) -> list[Path]:
    """Normalise what a user names: one ROS 2 bag folder or storage file, or ROS 1 ``.bag``
    files (several for a split recording)."""
    items = [Path(path)] if isinstance(path, str | Path) else [Path(p) for p in path]
    if not items:
        raise BagError("no bag given")
    # A ROS 2 bag's metadata.yaml stands for its folder (it was read as a damaged sqlite3
    # file, with a repair hint, even for an mcap bag).
    items = [p.parent if p.name == "metadata.yaml" and p.is_file() else p for p in items]
    for p in items:
        if not p.exists():
            raise BagError(f"{p}: bag not found")
        if p.is_file() and not is_ros1_bag(p) and (p.parent / "metadata.yaml").exists():
            _whole_recording(p)
        if (p.is_file() and not is_ros1_bag(p) and p.suffix.lower() not in ROS2_STORAGE
                and not (p.parent / "metadata.yaml").exists()):
            # Another kind of recording given to 'source: rosbag' (a CARMEN log, a TUM
            # folder's file) was reported as a damaged sqlite3 bag with a repair recipe.
            raise _not_a_bag(p)
        if p.is_dir() and not (p / "metadata.yaml").exists():
            ros1_files = sorted(str(f) for f in p.iterdir() if is_ros1_bag(f))
            if ros1_files:
                listed = "".join(f"\n  - {f}" for f in ros1_files)
                raise BagError(f"{p}: a folder of ROS 1 bags, not a ROS 2 bag folder (no "
                               "metadata.yaml). Fix: list the bags of the recording under "
                               f"'path:' (a split recording is read as one):{listed}")
            if not any(f.suffix.lower() in ROS2_STORAGE for f in p.iterdir()):
                # An empty, TUM RGB-D or sequence folder: no storage file for 'ros2 bag
                # reindex' to index, so its repair hint was no fix.
                raise _not_a_bag(p, "no metadata.yaml and no "
                                    f"{' / '.join(ROS2_STORAGE)} file in the folder")
    ros1 = [is_ros1_bag(p) for p in items]
    if any(ros1) and not all(ros1):
        raise BagError(f"{', '.join(map(str, items))}: mix of ROS 1 .bag files and other "
                       "paths; give either ROS 1 .bag files or one ROS 2 bag folder")
    if not all(ros1) and len(items) > 1:
        raise BagError(f"{', '.join(map(str, items))}: a ROS 2 recording is one folder "
                       "(with metadata.yaml); give that folder")
    return items


def _not_a_bag(path: Path, why: str = "") -> BagError:
    """The error for a file or folder that holds no ROS bag, naming the other sources."""
    return BagError(
        f"{path}: not a ROS bag{f' ({why})' if why else ''}: a ROS 1 bag starts with "
        f"'#ROSBAG', a ROS 2 bag is a folder with metadata.yaml (or its "
        f"{' / '.join(ROS2_STORAGE)} file). Fix: 'source: carmen' for a CARMEN log or g2o "
        "file, 'source: tum_rgbd' for a TUM RGB-D folder, 'source: sequence' for a "
        "sequence folder")


def _whole_recording(storage: Path) -> None:
    """Refuse one storage file of a ROS 2 recording split over several (it was converted
    in part, without a word: half the scans and images)."""
    import yaml

    try:
        meta = yaml.safe_load((storage.parent / "metadata.yaml").read_text()) or {}
        listed = meta["rosbag2_bagfile_information"]["relative_file_paths"]
    except (OSError, yaml.YAMLError, KeyError, TypeError):
        return  # not a metadata.yaml that lists files: nothing to compare with
    names = [Path(str(f)).name for f in listed or []]
    if len(names) > 1 and storage.name in names:
        raise BagError(f"{storage}: one of the {len(names)} storage files of the recording "
                       f"in {storage.parent} ({', '.join(names)}); give the folder to read "
                       "all of it")


def is_ros1_bag(path: Path) -> bool:
    """A ROS 1 bag file: by its header (``#ROSBAG V2.0``), whatever its name - ``rosbag
    record`` leaves ``NAME.bag.active`` when it is killed, and names vary in case."""
    if not path.is_file():
        return False
    if path.name.lower().endswith((".bag", ".bag.active")):
        return True
    try:
        with path.open("rb") as fh:
            return fh.read(8) == b"#ROSBAG "
    except OSError:
        return False


def _text(e: BaseException) -> str:
    return str(e).strip().rstrip(".")


def _storage_kind(paths: list[Path]) -> str:
    if is_ros1_bag(paths[0]):
        return "ROS 1"
    p = paths[0]
    files = [p] if p.is_file() else list(p.iterdir())
    if any(f.suffix == ".mcap" for f in files):
        return "ROS 2 mcap"
    return "ROS 2 sqlite3"


def _repair_hint(kind: str) -> str:
    if kind == "ROS 1":
        return ("If the recording was cut off (no index at the end), rebuild the index with "
                "'rosbag reindex FILE.bag' (ROS 1 tools) and convert the reindexed bag.")
    if kind == "ROS 2 mcap":
        return ("A cut-off mcap file is rebuilt by 'mcap recover FILE.mcap -o fixed.mcap' "
                "(mcap CLI); a missing metadata.yaml by 'ros2 bag reindex FOLDER'.")
    return ("A damaged sqlite3 file can often be rescued with "
            "'sqlite3 FILE.db3 .recover | sqlite3 fixed.db3'; a missing metadata.yaml is "
            "rebuilt by 'ros2 bag reindex FOLDER'.")


@dataclass
class TopicInfo:
    name: str
    msgtype: str
    count: int


class Bag:
    """An open bag whose read errors name the bag and say how to repair it."""

    def __init__(self, paths: list[Path]) -> None:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        self.paths = paths
        self.kind = _storage_kind(paths)
        self.name = ", ".join(str(p) for p in paths)
        odd = [p for p in paths if self.kind == "ROS 1" and p.suffix != ".bag"]
        if odd:  # rosbags opens ROS 1 bags by their suffix
            active = odd[0].name.lower().endswith(".active")
            raise BagError(
                f"{odd[0]}: a ROS 1 bag named other than *.bag; "
                + ("'rosbag record' was killed before it indexed this one: rebuild the "
                   "index with 'rosbag reindex FILE' (ROS 1 tools), then rename it to end in "
                   "'.bag'" if active else "rename it (or link it) to end in '.bag'"))
        # Only used when a ROS 2 bag stores no message definitions (Foxy era).
        default = None if self.kind == "ROS 1" else get_typestore(Stores.ROS2_FOXY)
        try:
            self.reader = AnyReader(paths, default_typestore=default)
            self.reader.open()
        except Exception as e:  # rosbags raises its own, sqlite's, mcap's and OS errors
            raise BagError(f"{self.name}: cannot open this {self.kind} bag: "
                           f"{type(e).__name__}: {_text(e)}. {_repair_hint(self.kind)}") from e
        self.topics = {name: TopicInfo(name, info.msgtype or "?", info.msgcount)
                       for name, info in self.reader.topics.items()}
        self.start_ns = self.reader.start_time if self.reader.message_count else 0
        self.end_ns = self.reader.end_time if self.reader.message_count else 0

    def close(self) -> None:
        self.reader.close()

    def __enter__(self) -> Bag:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def of_type(self, *msgtypes: str) -> list[str]:
        """Topics carrying one of ``msgtypes`` with at least one message, sorted."""
        return sorted(t.name for t in self.topics.values()
                      if t.msgtype in msgtypes and t.count > 0)

    def messages(self, topics: Sequence[str], start_ns: int | None = None) -> (
        Iterator[tuple[str, int, Any]]
    ):
        """(topic, bag time ns, message) in recording order, errors wrapped."""
        conns = [c for c in self.reader.connections if c.topic in set(topics)]
        if not conns:
            return
        it = self.reader.messages(connections=conns, start=start_ns)
        n = 0
        while True:
            try:
                conn, ns, raw = next(it)
            except StopIteration:
                return
            except Exception as e:
                raise BagError(
                    f"{self.name}: reading failed after {n} messages of "
                    f"{', '.join(topics)}: {type(e).__name__}: {_text(e)}. The bag is truncated or "
                    f"corrupt. {_repair_hint(self.kind)}") from e
            try:
                msg = self.reader.deserialize(raw, conn.msgtype)
            except Exception as e:
                raise BagError(
                    f"{self.name}: topic {conn.topic}: the message recorded at "
                    f"{ns / 1e9:.9f} s does not decode as {conn.msgtype} "
                    f"({type(e).__name__}: {_text(e)}); the bag is corrupt. "
                    f"{_repair_hint(self.kind)}") from e
            n += 1
            yield conn.topic, ns, msg

    def first(self, topic: str) -> Any | None:
        gen = self.messages([topic])
        try:
            return next(gen)[2]
        except StopIteration:
            return None
        finally:
            gen.close()


# ---------------------------------------------------------------------------- decoding


def _frame(name: str) -> str:
    # ROS 1 tf allowed a leading slash ("/base_link"); tf2 and ROS 2 do not.
    return name.lstrip("/")


def header_ns(msg: Any) -> int:
    """header.stamp in integer nanoseconds (exact, unlike float seconds)."""
    st = msg.header.stamp
    return int(st.sec) * 1_000_000_000 + int(st.nanosec)


def image_to_rgb(msg: Any, where: str = "image") -> np.ndarray:
    """[H, W, 3] RGB uint8 of a ``sensor_msgs/Image`` in a colour encoding, converted as
    cv_bridge converts it to rgb8 (``COLOR_ENCODINGS``)."""
    return _to_8bit(_image_rgb(msg, where))


class FramePixels(NamedTuple):
    """A camera message's 8-bit RGB pixels and what became of 16-bit samples on the way."""

    rgb: np.ndarray  # [H, W, 3] uint8
    # None: 8-bit samples; "scaled": 16-bit samples scaled by 255/65535 (cv_bridge's rgb8);
    # "clipped": a 16-bit image the publisher's JPEG codec saturated at 255 (jpeg_of_16bit)
    from_16bit: str | None = None
    peak_16bit: int = 0  # brightest 16-bit sample, where scaled


def frame_pixels(msg: Any, compressed: bool, where: str = "image") -> FramePixels:
    """``image_to_rgb`` / ``compressed_to_rgb`` of one camera message, saying what happened
    to 16-bit samples (the sequence format holds 8 bits)."""
    native = _compressed_native(msg, where) if compressed else _image_rgb(msg, where)
    if native.dtype == np.uint16:
        return FramePixels(_to_8bit(native), "scaled", int(native.max(initial=0)))
    if compressed and jpeg_of_16bit(str(msg.format)):
        return FramePixels(_to_8bit(native), "clipped")
    return FramePixels(_to_8bit(native))


def jpeg_of_16bit(fmt: str) -> bool:
    """Whether a CompressedImage ``format`` is image_transport's JPEG of a 16-bit grey or
    Bayer image ('mono16; jpeg compressed ', 'bayer_rggb16; jpeg compressed '). Its codec
    converts only colour encodings to bgr8 (scaled, 'rgb16; jpeg compressed bgr8'); any
    other image goes to OpenCV's JPEG encoder as it is, which takes 16-bit samples to
    8 bits without scaling (convertTo: saturated), so the payload holds min(v, 255): a
    16-bit camera's frames come out white wherever v > 255. Nothing more is in the bag."""
    enc, order = compressed_format(fmt)
    spec = COLOR_ENCODINGS.get(enc)
    codec = fmt.partition(";")[2].partition("compressed")[0].strip().lower()
    return spec is not None and spec.bits == 16 and codec == "jpeg" and not order


def _image_rgb(msg: Any, where: str) -> np.ndarray:
    """[H, W, 3] RGB of a ``sensor_msgs/Image``, uint8 or (16-bit encodings) uint16."""
    enc = str(msg.encoding)
    spec = COLOR_ENCODINGS.get(enc)
    if spec is None:
        raise BagError(f"{where}: field 'encoding' is {enc!r}, which this reader does not "
                       f"decode (colour: {_accepted_colour()}; depth: "
                       f"{', '.join(DEPTH_ENCODINGS)}); {_encoding_hint(enc)}")
    a = _pixels(msg, _sample_dtype(msg, "u1" if spec.bits == 8 else "u2"), spec.channels,
                where)  # [H, W, C], native byte order
    if enc in BAYER_TO_RGB:
        rgb = _demosaic(a[..., 0], enc, where)
    elif spec.channels == 2 and a.shape[1] % 2:
        raise BagError(f"{where}: a {enc} image is {a.shape[1]} pixels wide (field 'width'); "
                       "YUV 4:2:2 pairs pixels, so the width must be even: the message is "
                       "corrupt")
    else:
        rgb = a if spec.to_rgb is None else cv2.cvtColor(a, spec.to_rgb)  # [H, W, 3]
    return rgb


def _accepted_colour() -> str:
    """The colour encodings read, for error messages (the 16 Bayer names folded)."""
    plain = [e for e in COLOR_ENCODINGS if e not in BAYER_TO_RGB]
    return ", ".join(plain) + ", bayer_{rggb,bggr,gbrg,grbg}{8,16}"


def _encoding_hint(enc: str) -> str:
    if enc in DEPTH_ENCODINGS:
        return "it is a depth encoding: give it as rosbag.topics.depth"
    if enc in ("nv12", "nv21", "nv24"):
        # Neither cv_bridge nor image_transport's codecs read these planar YUV layouts.
        return ("cv_bridge does not convert this planar YUV layout either: have the camera "
                "driver publish another format (e.g. yuyv, rgb8), or name another topic with "
                "rosbag.topics.image")
    return ("republish the images as rgb8 or bgr8 (e.g. with image_proc / cv_bridge) or "
            "name another topic with rosbag.topics.image")


def _to_8bit(img: np.ndarray) -> np.ndarray:
    """``img`` as contiguous uint8: 16-bit samples become round(v * 255 / 65535), cv_bridge's
    convertTo when a 16-bit encoding is read as rgb8 (v * 257 comes back as v exactly)."""
    if img.dtype == np.uint16:
        return ((img.astype(np.uint32) + 128) // 257).astype(np.uint8)
    return np.ascontiguousarray(img)


def _demosaic(mosaic: np.ndarray, enc: str, where: str) -> np.ndarray:
    """[H, W, 3] RGB (of the mosaic's dtype) of a [H, W] Bayer mosaic in ROS encoding
    ``enc``."""
    if min(mosaic.shape) < 2:
        raise BagError(f"{where}: a {mosaic.shape[1]}x{mosaic.shape[0]} {enc} image is "
                       "smaller than one 2x2 Bayer block; the message is corrupt")
    return cv2.cvtColor(np.ascontiguousarray(mosaic), BAYER_TO_RGB[enc])


def image_to_depth(msg: Any, where: str = "depth") -> np.ndarray:
    """[H, W] float32 metres of a 16UC1 (mm) or 32FC1 (m) image; 0 where invalid."""
    enc = str(msg.encoding)
    if enc not in DEPTH_ENCODINGS:
        raise BagError(f"{where}: field 'encoding' is {enc!r}; depth images must be 16UC1 "
                       "(millimetres) or 32FC1 (metres). Name the depth topic with "
                       "rosbag.topics.depth, or 'none' to convert without depth")
    a = _pixels(msg, _sample_dtype(msg, "u2" if enc == "16UC1" else "f4"), 1,
                where)[..., 0]  # [H, W]
    if enc == "16UC1":
        return (a.astype(np.float32) / np.float32(1000.0)).astype(np.float32)
    d = a.astype(np.float32)
    return np.where(np.isfinite(d) & (d > 0), d, np.float32(0.0)).astype(np.float32)


def _sample_dtype(msg: Any, kind: str) -> np.dtype:
    """numpy dtype of one sample (``kind``: 'u1', 'u2', 'f4') in the message's byte order
    (``is_bigendian``: dc1394 / machine-vision cameras send big-endian 16-bit data)."""
    return np.dtype(f"{'>' if msg.is_bigendian else '<'}{kind}")


def _pixels(msg: Any, dtype: np.dtype, channels: int, where: str) -> np.ndarray:
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    row = w * channels * dtype.itemsize
    if h <= 0 or w <= 0:
        raise BagError(f"{where}: image is {w}x{h} (fields 'width'/'height'); the message is "
                       "empty or corrupt")
    if step < row or len(data) < step * (h - 1) + row:
        raise BagError(f"{where}: {len(data)} bytes of data for a {w}x{h} {msg.encoding} "
                       f"image with step {step} (fields 'data'/'step'); the message is "
                       "truncated or corrupt")
    if len(data) < step * h:  # some drivers omit the last row's padding
        data = np.concatenate([data, np.zeros(step * h - len(data), np.uint8)])
    rows = data[: step * h].reshape(h, step)[:, :row]
    # [H, W, C] in native byte order: OpenCV refuses a byte-swapped array.
    return rows.copy().view(dtype).reshape(h, w, channels).astype(dtype.newbyteorder("="),
                                                              copy=False)


def compressed_to_rgb(msg: Any, where: str = "image") -> np.ndarray:
    """[H, W, 3] RGB uint8 of a ``sensor_msgs/CompressedImage`` (jpeg or png)."""
    return _to_8bit(_compressed_native(msg, where))


def _compressed_native(msg: Any, where: str) -> np.ndarray:
    """[H, W, 3] RGB of a CompressedImage, uint8 or (a 16-bit png payload) uint16."""
    fmt = str(msg.format)
    if "compresseddepth" in fmt.lower():
        raise BagError(f"{where}: field 'format' is {fmt!r}, a depth image; give it as "
                       "rosbag.topics.depth")
    data = np.asarray(msg.data, dtype=np.uint8)
    try:  # OpenCV asserts on an empty buffer instead of returning None
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    except cv2.error:
        img = None
    if img is None:
        raise BagError(f"{where}: the {fmt!r} data (field 'data', {len(msg.data)} bytes) does "
                       "not decode; the message is corrupt or the format unknown "
                       "(jpeg and png are read)")
    enc, order = compressed_format(fmt)
    # image_transport's png codec keeps a 16-bit image's depth (rgb16 as 'compressed
    # bgr16', a mono16 or Bayer 16 image as it is); its subscriber decodes it unchanged and
    # cv_bridge scales it when read as rgb8.
    spec = COLOR_ENCODINGS.get(enc)
    if img.dtype != np.uint8 and not (img.dtype == np.uint16 and spec and spec.bits == 16):
        raise BagError(f"{where}: field 'format' {fmt!r} decodes to {img.dtype} pixels; "
                       "colour images must be 8-bit, or 16-bit in a 16-bit encoding named "
                       "before ';' (" + ", ".join(
                           e for e, c in COLOR_ENCODINGS.items() if c.bits == 16) + ")"
                       + ("; a depth image: give it as rosbag.topics.depth (raw or "
                          "compressedDepth)" if enc in DEPTH_ENCODINGS else ""))
    return _compressed_rgb(img, enc, order, where)


def _compressed_rgb(img: np.ndarray, enc: str, order: str, where: str) -> np.ndarray:
    """[H, W, 3] RGB (of ``img``'s dtype) of a decoded CompressedImage payload."""
    if img.ndim == 2 and enc in BAYER_TO_RGB:
        # image_transport compresses a Bayer camera's mosaic as it is: stored as grey, it
        # was the raw checkerboard of R, G and B samples.
        return _demosaic(img, enc, where)
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    # image_transport's subscriber swaps channels only for a payload labelled 'compressed
    # bgr*'; one labelled 'compressed rgb*' (compressed_publisher's color_space: rgb in
    # Autoware's image_transport_plugins, jsk's coral_usb) holds RGB and was stored with red
    # and blue swapped. Unlabelled ('jpeg', 'png' of old publishers): BGR, as OpenCV writes.
    rgb_order = order.startswith("rgb")
    if img.shape[2] == 4:
        return np.ascontiguousarray(img[..., :3]) if rgb_order else \
            cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    return np.ascontiguousarray(img) if rgb_order else cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def compressed_format(fmt: str) -> tuple[str, str]:
    """(encoding of the image before compression, channel order of the payload) of a
    ``sensor_msgs/CompressedImage`` format written by image_transport's compressed codec:
    ``'<encoding>; <codec> compressed <order>'`` ('rgb8; jpeg compressed bgr8'). A mono or
    Bayer image has no order ('bayer_rggb8; jpeg compressed '); old publishers wrote just
    'jpeg' or 'png': ('', '')."""
    enc, sep, rest = fmt.partition(";")
    if not sep:
        return "", ""
    _, word, order = rest.partition("compressed")
    return enc.strip(), order.strip().lower() if word else ""


_PNG = b"\x89PNG\r\n\x1a\n"


def compressed_to_depth(msg: Any, where: str = "depth") -> np.ndarray:
    """[H, W] float32 metres of a ``compressedDepth`` CompressedImage (png)."""
    fmt = str(msg.format)
    raw = bytes(np.asarray(msg.data, dtype=np.uint8))
    # image_transport_plugins' compressed_depth codec: a 12-byte ConfigHeader
    # (int32 format, float32 depthQuantA, depthQuantB) before the PNG; older ones none.
    off = raw.find(_PNG, 0, 64)
    if "compresseddepth" not in fmt.lower() or "rvl" in fmt.lower() or off < 0:
        raise BagError(f"{where}: field 'format' is {fmt!r}; depth CompressedImages must be "
                       "'16UC1; compressedDepth png' or '32FC1; compressedDepth png' "
                       "(rvl is not read). Republish raw depth or set rosbag.topics.depth: none")
    try:
        img = cv2.imdecode(np.frombuffer(raw[off:], np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error:
        img = None
    if img is None or img.dtype != np.uint16 or img.ndim != 2:
        raise BagError(f"{where}: compressedDepth data (field 'data') does not decode to a "
                       "16-bit single-channel PNG; the message is corrupt")
    if fmt.split(";")[0].strip() == "32FC1":
        if off < 12:
            raise BagError(f"{where}: 32FC1 compressedDepth without its quantisation header")
        qa, qb = np.frombuffer(raw[4:12], "<f4")
        with np.errstate(divide="ignore"):
            d = np.where(img > 0, qa / (img.astype(np.float32) - qb), 0.0)
        return np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32)
    return (img.astype(np.float32) / np.float32(1000.0)).astype(np.float32)


def _field(msg: Any, *names: str) -> Any:
    # ROS 1 CameraInfo spells K, D, P; ROS 2 spells k, d, p.
    for n in names:
        if hasattr(msg, n):
            return getattr(msg, n)
    raise AttributeError(names[0])


def _roi(msg: Any) -> tuple[int, int, int, int]:
    """(x_offset, y_offset, width, height) of a CameraInfo's ``roi``; all zero: none."""
    r = msg.roi
    return int(r.x_offset), int(r.y_offset), int(r.width), int(r.height)


def camera_info_size(msg: Any) -> tuple[int, int]:
    """(width, height) of the images a CameraInfo describes: its ROI's where one is set."""
    _, _, rw, rh = _roi(msg)
    return (rw, rh) if rw > 0 and rh > 0 else (int(msg.width), int(msg.height))


# What ROS's distortion models (sensor_msgs/distortion_models.h) hold in D; of these this
# pinhole camera represents plumb_bob, and rational_polynomial with k4..k6 = 0.
_ROS_DIST_TERMS = {"plumb_bob": "5: k1 k2 p1 p2 k3",
                   "rational_polynomial": "8: k1 k2 p1 p2 k3 k4 k5 k6",
                   "equidistant": "4: k1 k2 k3 k4 (fisheye)"}


def camera_info_to_camera(msg: Any, where: str = "camera_info",
                          rectified: bool = False) -> PinholeCamera:
    """A ``PinholeCamera`` from ``sensor_msgs/CameraInfo`` (plumb_bob or 5-term rational).

    ``rectified``: the images are already undistorted (``image_rect``), so the projection
    matrix P holds their intrinsics and there is no distortion. A region of interest
    (``roi``, REP 104: width, height, K and P stay the full sensor's) gives the window's
    size and moves the principal point by its offsets, as image_geometry does.
    """
    w, h = int(msg.width), int(msg.height)
    K = np.asarray(_field(msg, "k", "K"), dtype=np.float64).reshape(3, 3)
    P = np.asarray(_field(msg, "p", "P"), dtype=np.float64).reshape(3, 4)
    D = np.asarray(_field(msg, "d", "D"), dtype=np.float64).reshape(-1)
    model = str(msg.distortion_model)
    fix = ("give the intrinsics in the calibration YAML ('camera: {width, height, fx, fy, "
           "cx, cy, distortion}') and set rosbag.calibration")
    if w <= 0 or h <= 0:
        raise BagError(f"{where}: fields 'width'/'height' are {w}x{h}; {fix}")
    if int(msg.binning_x) > 1 or int(msg.binning_y) > 1:
        raise BagError(f"{where}: fields 'binning_x'/'binning_y' are {msg.binning_x}/"
                       f"{msg.binning_y}; binned images are not supported: {fix}")
    x0, y0, rw, rh = _roi(msg)
    if (x0, y0, rw, rh) != (0, 0, 0, 0):
        if rw <= 0 or rh <= 0 or x0 + rw > w or y0 + rh > h:
            raise BagError(f"{where}: field 'roi' (x_offset {x0}, y_offset {y0}, width "
                           f"{rw}, height {rh}) is no window of the {w}x{h} sensor "
                           f"(fields 'width'/'height'); {fix}")
        # The window's pixel (0, 0) is the sensor's (x0, y0).
        w, h = rw, rh
        K = K.copy()
        P = P.copy()
        K[0, 2] -= x0
        K[1, 2] -= y0
        P[0, 2] -= x0
        P[1, 2] -= y0
    # The fields the camera model is made of must be numbers: a NaN in K or D failed as a
    # bare ValueError naming neither the bag, the topic nor the field.
    for name, value in (("P", P[:, :3]),) if rectified else (("K", K), ("D", D)):
        if not np.all(np.isfinite(value)):
            raise BagError(f"{where}: field '{name}' holds a non-finite value "
                           f"({np.round(value, 6).reshape(-1).tolist()}); {fix}")
    if rectified:
        if not np.any(P[:, :3]):
            raise BagError(f"{where}: field 'P' is all zero, but the images are rectified "
                           f"and need it; {fix}")
        return _pinhole(lambda: PinholeCamera(w, h, P[0, 0], P[1, 1], P[0, 2], P[1, 2]),
                        where, "P", fix)
    if not np.any(K):
        raise BagError(f"{where}: field 'K' is all zero (the camera was not calibrated); {fix}")
    if model in ("plumb_bob", "rational_polynomial", "") or (model == "none" and not D.any()):
        if model == "" and D.any():
            raise BagError(f"{where}: field 'D' has {len(D)} coefficients but "
                           f"'distortion_model' is empty; {fix}")
        if D.any() and len(D) not in OPENCV_DIST_COUNTS:
            # image_geometry hands D to OpenCV as it is, which takes these counts only: a
            # 3-long D (k1 k2 k3 to some tools, k1 k2 p1 to others) was zero-padded as
            # k1 k2 p1, a 6-long one cut to 5, without a word.
            raise BagError(
                f"{where}: field 'D' has {len(D)} coefficients {D.tolist()}, but "
                f"distortion_model {model!r} takes {_ROS_DIST_TERMS[model]} (OpenCV and "
                f"ROS's image_geometry take {', '.join(map(str, OPENCV_DIST_COUNTS))}); "
                "other counts are ambiguous "
                "(3 values are k1 k2 k3 to some tools, k1 k2 p1 to others) and are not "
                "guessed. Fix: give the intrinsics in the calibration YAML ('camera: {width, "
                "height, fx, fy, cx, cy, distortion: [k1, k2, p1, p2, k3]}', zeros for the "
                "terms the lens lacks) and set rosbag.calibration")
        try:
            coefficients = plumb_bob_distortion(model, D, "D")
        except ValueError as e:
            raise BagError(f"{where}: {e}, or convert the rectified images (image_rect) "
                           f"instead, or {fix}") from None
        return _pinhole(lambda: PinholeCamera.from_K(K, w, h, coefficients), where, "K", fix)
    holds = f" (D holds {_ROS_DIST_TERMS[model]})" if model in _ROS_DIST_TERMS else ""
    raise BagError(f"{where}: field 'distortion_model' is {model!r}{holds}; only plumb_bob "
                   "(OpenCV k1 k2 p1 p2 k3) is supported. Use the rectified image topic "
                   "(image_rect, with rosbag.rectified: true) or " + fix)


def _pinhole(make: Callable[[], PinholeCamera], where: str, field_name: str,
             fix: str) -> PinholeCamera:
    """``make()``, its refusal (a transposed K, a negative focal length) as a BagError
    naming the topic and field rather than a bare ValueError."""
    try:
        return make()
    except ValueError as e:
        raise BagError(f"{where}: field '{field_name}': {e}; {fix}") from None


def rectification_rotation(msg: Any, where: str = "camera_info") -> np.ndarray:
    """[3, 3] CameraInfo R (X_rect = R @ X_camera); identity when it is all zero (drivers
    of single cameras often leave it unset)."""
    R = np.asarray(_field(msg, "r", "R"), dtype=np.float64).reshape(3, 3)
    if not np.any(R):
        return np.eye(3)
    if not (np.allclose(R @ R.T, np.eye(3), atol=1e-4) and np.linalg.det(R) > 0):
        raise BagError(f"{where}: field 'R' is not a rotation ({np.round(R, 4).tolist()}); "
                       "give the intrinsics in the calibration YAML and set "
                       "rosbag.calibration")
    return R


class NotATransformError(ValueError):
    """A ``geometry_msgs`` Transform or Pose that is no rigid motion; ``part`` names the
    bad half ('translation' / 'rotation' of a Transform, 'position' / 'orientation' of a
    Pose)."""

    def __init__(self, part: str, message: str) -> None:
        super().__init__(message)
        self.part = part


def transform_to_matrix(tf: Any) -> np.ndarray:
    """[4, 4] of a ``geometry_msgs/Transform`` (or Pose: position / orientation).

    Raises ``NotATransformError`` for a zero or non-finite quaternion and for a non-finite
    translation: a NaN position (an estimator before its first fix or after diverging)
    went through as a NaN pose, into a rig or trajectory the sequence reader refuses.
    """
    xyz, quat = checked_xyz_quat(tf)
    return pose_from_xyz_quat(xyz, quat)


def checked_xyz_quat(tf: Any) -> tuple[np.ndarray, np.ndarray]:
    """(translation [3], unit xyzw quaternion [4]) of a ``geometry_msgs/Transform`` (or
    Pose), refused as ``transform_to_matrix`` refuses it - without building the matrix,
    which costs most of the index pass for 50-100 Hz /tf and odometry."""
    pose = getattr(tf, "translation", None) is None
    t = tf.position if pose else tf.translation
    q = tf.orientation if pose else tf.rotation
    quat = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
    n = np.linalg.norm(quat)
    if not np.isfinite(n) or n < 1e-6:
        raise NotATransformError("orientation" if pose else "rotation",
                                 f"quaternion {quat.tolist()} is not a rotation")
    xyz = np.array([t.x, t.y, t.z], dtype=np.float64)
    if not np.all(np.isfinite(xyz)):
        raise NotATransformError("position" if pose else "translation",
                                 f"{'position' if pose else 'translation'} {xyz.tolist()} "
                                 "is not finite")
    return xyz, quat / n


# ---------------------------------------------------------------------------- tf


class TfTree:
    """Transforms from tf / tf_static (and a calibration file) as a graph of frames.

    Static transforms and /tf transforms that never change are fixed mounts; /tf
    transforms that move (odom -> base_link) are kept apart, so an extrinsic is never
    read off a moving joint by accident.
    """

    def __init__(self) -> None:
        self.fixed: dict[tuple[str, str], np.ndarray] = {}
        self.source: dict[tuple[str, str], str] = {}
        self._static: set[tuple[str, str]] = set()
        self._first: dict[tuple[str, str], np.ndarray] = {}
        self.moving: set[tuple[str, str]] = set()
        # Transforms that were no rigid motion (a zero quaternion: a localisation node
        # before its first fix; a NaN translation), skipped: (parent, child) -> count.
        # Fatal only where a lookup needs that edge.
        self.invalid: dict[tuple[str, str], int] = {}
        # Edges the bag gives different mounts for (two static publishers of one edge, a
        # URDF's and a calibration's; a /tf value beside a static one): (parent, child) ->
        # the sources that disagreed. The latest static value is used; a lookup through
        # such an edge says so rather than pick one without a word.
        self.conflicts: dict[tuple[str, str], set[str]] = {}

    def add_invalid(self, parent: str, child: str) -> None:
        key = (_frame(parent), _frame(child))
        self.invalid[key] = self.invalid.get(key, 0) + 1

    def invalid_note(self) -> str:
        """The skipped transforms, for a message ('' when none)."""
        if not self.invalid:
            return ""
        return ("; skipped as no rotation or not finite (quaternion zero or not finite, or "
                "translation not finite): ") + ", ".join(
            f"{p} -> {c} ({n}x)" for (p, c), n in sorted(self.invalid.items()))

    def add(self, parent: str, child: str, T: np.ndarray, static: bool, source: str,
            override: bool = False) -> None:
        """Add one transform T_parent_child. ``override``: it replaces what the bag says
        (a calibration file's), which is no conflict."""
        key = (_frame(parent), _frame(child))
        # Only a static value can conflict: checked there, not on every /tf message.
        if not override and (static or key in self._static):
            before = self.fixed.get(key, self._first.get(key))
            if key in self.moving or (before is not None and _differs(before, T)):
                self.conflicts.setdefault(key, {self.source.get(key, source)}).add(source)
        if static:  # the latest static transform wins, over /tf too
            self.fixed[key] = T
            self.source[key] = source
            self._static.add(key)
            self.moving.discard(key)
            return
        if key in self._static:
            return
        first = self._first.setdefault(key, T)
        if key in self.moving:
            return
        if _differs(first, T):
            self.moving.add(key)
            self.fixed.pop(key, None)
        else:
            self.fixed[key] = first
            self.source[key] = source

    def is_moving(self, parent: str, child: str) -> bool:
        """The /tf edge parent -> child is known to move: a further /tf value of it
        changes nothing (``add`` keeps its first value only)."""
        return (_frame(parent), _frame(child)) in self.moving

    def frames(self) -> set[str]:
        return {f for k in (*self.fixed, *self.moving) for f in k}

    def conflicts_on(self, path: Sequence[str]) -> list[str]:
        """The edges along ``path`` (frames, as ``lookup`` returns them) the bag gave
        different values for, as 'parent -> child (sources)' with the value used."""
        out = []
        for a, b in zip(path[:-1], path[1:], strict=True):
            for key in ((a, b), (b, a)):
                if key in self.conflicts:
                    T = self.fixed[key]
                    out.append(f"{key[0]} -> {key[1]} (on {', '.join(sorted(self.conflicts[key]))}"
                               f"; used: xyz {np.round(T[:3, 3], 4).tolist()}, rpy deg "
                               f"{np.round(np.degrees(_rpy(T)), 2).tolist()} from "
                               f"{self.source[key]})")
        return out

    def lookup(self, target: str, source: str, include_moving: bool = False) -> (
        tuple[np.ndarray, list[str]] | None
    ):
        """(T_target_source, frames on the path) through fixed edges, None if unconnected.

        With ``include_moving`` the path may use moving edges too (only to explain errors;
        the transform is then the first one seen).
        """
        target, source = _frame(target), _frame(source)
        edges = dict(self.fixed)
        if include_moving:
            edges.update({k: self._first[k] for k in self.moving if k in self._first})
        adj: dict[str, list[tuple[str, np.ndarray]]] = {}
        for (p, c), T in edges.items():
            adj.setdefault(p, []).append((c, T))  # T_p_c: c -> p
            adj.setdefault(c, []).append((p, inv_se3(T)))
        best: dict[str, tuple[np.ndarray, list[str]]] = {target: (np.eye(4), [target])}
        queue = deque([target])
        while queue:
            f = queue.popleft()
            T_tf, path = best[f]
            for nxt, T_f_n in adj.get(f, []):
                if nxt not in best:
                    best[nxt] = (T_tf @ T_f_n, [*path, nxt])
                    queue.append(nxt)
        return best.get(source)


def _differs(A: np.ndarray, B: np.ndarray) -> bool:
    """Two mounts that are not the same (beyond float noise: 1 um, 1 urad)."""
    return bool(np.linalg.norm(A[:3, 3] - B[:3, 3]) > 1e-6
                or float(rotation_angle(A[:3, :3].T @ B[:3, :3])) > 1e-6)


def _rpy(T: np.ndarray) -> np.ndarray:
    """[3] roll, pitch, yaw (radians) of T's rotation, as tf's static_transform_publisher
    takes them (extrinsic x-y-z)."""
    return Rotation.from_matrix(T[:3, :3]).as_euler("xyz")


# ---------------------------------------------------------------------------- calibration


@dataclass
class Calibration:
    """What a calibration YAML gives; every member may be absent."""

    path: Path
    camera: PinholeCamera | None = None
    T_base_camera: np.ndarray | None = None
    T_base_laser: np.ndarray | None = None
    T_camera_laser: np.ndarray | None = None
    transforms: list[tuple[str, str, np.ndarray]] = field(default_factory=list)
    # key -> (parent, child) where a T_* entry was given tf style, to check its direction
    names: dict[str, tuple[str | None, str | None]] = field(default_factory=dict)

    def check_direction(self, key: str, parent: str, child: str,
                        child_known: bool = True) -> None:
        """Fail if a tf-style entry names its frames the other way round (a likely mix-up:
        the key, not the order, fixes the direction), or names another parent, or (when
        the sensor's frame is known: ``child_known``) another child: a body frame
        (camera_link, x forward) given for the optical one turned the view up."""
        given = self.names.get(key)
        if given is None or given == (None, None):
            return
        gp, gc = (_frame(n) if n else None for n in given)
        if (gp, gc) == (child, parent) or (gp == child and gp is not None):
            raise BagError(
                f"{self.path}: field '{key}' has parent {gp!r} and child {gc!r}, which is "
                f"reversed: {key} maps {child} points into {parent}, so parent: {parent} and "
                f"child: {child} (swap them, or invert the transform)")
        if gp is not None and gp != parent:
            raise BagError(f"{self.path}: field '{key}' has parent {gp!r}, but the frame it "
                           f"must map into is {parent!r} (rosbag.frames)")
        if child_known and gc is not None and gc != child:
            raise BagError(f"{self.path}: field '{key}' has child {gc!r}, but the frame it "
                           f"maps from is {child!r} (the sensor messages' header.frame_id, "
                           "or rosbag.frames); give that frame's transform (for a camera, "
                           "its optical frame: x right, y down, z forward) and name it")


def parse_transform(value: Any, where: str) -> tuple[np.ndarray, str | None, str | None]:
    """A 4x4 list of rows, or tf style ``{parent, child, xyz, quat_xyzw}``.

    Returns (T_parent_child, parent, child); parent/child are None for a matrix.
    """
    if isinstance(value, dict):
        unknown = set(value) - {"parent", "child", "xyz", "quat_xyzw"}
        if unknown:
            raise BagError(f"{where}: unknown keys {sorted(unknown)}; a tf-style transform "
                           "has parent, child, xyz, quat_xyzw")
        try:
            xyz = np.asarray(value["xyz"], dtype=np.float64).reshape(3)
            q = np.asarray(value["quat_xyzw"], dtype=np.float64).reshape(4)
        except KeyError as e:
            raise BagError(f"{where}: missing field {e.args[0]!r} (tf style needs xyz and "
                           "quat_xyzw)") from None
        except (TypeError, ValueError):
            raise BagError(f"{where}: xyz must be 3 numbers and quat_xyzw 4") from None
        n = np.linalg.norm(q)
        if not np.all(np.isfinite(xyz)) or not np.isfinite(n) or n < 1e-6:
            raise BagError(f"{where}: xyz / quat_xyzw must be finite with a non-zero "
                           "quaternion")
        parent, child = value.get("parent"), value.get("child")
        return pose_from_xyz_quat(xyz, q / n), (str(parent) if parent else None), (
            str(child) if child else None)
    try:
        T = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        T = np.zeros(0)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise BagError(f"{where}: expected a 4x4 matrix (list of 4 rows) or a mapping with "
                       f"parent, child, xyz, quat_xyzw; got {value!r}")
    try:
        T = checked_rigid(T)
    except ValueError as e:
        raise BagError(f"{where} {e}") from None
    return T, None, None


def load_calibration(path: Path | str) -> Calibration:
    """Read a calibration YAML.

    Keys (all optional): ``camera`` (intrinsics as in rig.yaml), ``T_base_camera``
    (optical frame -> base), ``T_base_laser``, ``T_camera_laser`` (laser -> optical, what
    ``python -m calibration`` estimates), ``transforms`` (a list of tf-style entries with
    parent and child, added to the bag's tf tree). A rig.yaml written by this toolkit is
    a valid calibration file; of one written by ``python -m calibration`` the camera and
    T_camera_laser are read (its base frame is not the robot's).
    """
    path = Path(path)
    data = load_yaml(path, BagError, "calibration file not found (rosbag.calibration)")
    if not isinstance(data, dict):
        raise BagError(f"{path}: expected a mapping with camera / T_base_camera / "
                       "T_base_laser / T_camera_laser / transforms")
    warn_if_unreliable(path, data, BagError)
    if data.get("calibration") is not None and data.get("T_camera_laser") is not None:
        # Written by ``python -m calibration``: what it estimated is T_camera_laser. Its
        # T_base_* only place a base_link of its own (at the laser, without a rig given),
        # which is not the robot's base the bag's tf and odometry speak of.
        data = {k: data[k] for k in ("camera", "T_camera_laser") if k in data}
    known = {"camera", "T_base_camera", "T_base_laser", "T_camera_laser", "transforms",
             "frames", "convention"}
    unknown = set(data) - known
    if unknown:
        raise BagError(f"{path}: unknown keys {sorted(unknown)}; allowed: {sorted(known)}")
    cal = Calibration(path)
    if data.get("camera") is not None:
        try:
            cal.camera = PinholeCamera.from_dict(data["camera"])
        except (KeyError, TypeError, ValueError) as e:
            raise BagError(f"{path}: field 'camera': {e}") from None
    for key in ("T_base_camera", "T_base_laser", "T_camera_laser"):
        if data.get(key) is None:
            continue
        T, parent, child = parse_transform(data[key], f"{path}: field '{key}'")
        setattr(cal, key, T)
        cal.names[key] = (parent, child)
    for i, entry in enumerate(data.get("transforms") or []):
        where = f"{path}: transforms[{i}]"
        if not isinstance(entry, dict) or not entry.get("parent") or not entry.get("child"):
            raise BagError(f"{where}: each entry needs parent, child, xyz, quat_xyzw")
        T, parent, child = parse_transform(entry, where)
        assert parent and child
        cal.transforms.append((parent, child, T))
    return cal


# ---------------------------------------------------------------------------- topics


@dataclass
class TopicChoice:
    """The topics a conversion reads, and why."""

    scan: str | None = None
    image: str | None = None
    image_compressed: bool = False
    depth: str | None = None
    depth_compressed: bool = False
    camera_info: str | None = None
    odometry: str | None = None
    tf: list[str] = field(default_factory=list)
    image_size: tuple[int, int] | None = None  # (w, h) of the first image
    image_encoding: str = ""
    image_frame: str = ""
    scan_frame: str = ""
    notes: list[str] = field(default_factory=list)

    def role(self, topic: str) -> str:
        roles = {self.scan: "scan", self.image: "image", self.depth: "depth",
                 self.camera_info: "camera_info", self.odometry: "odometry"}
        if topic in roles:
            return roles[topic]
        return "tf" if topic in self.tf else ""


def _override(bag: Bag, key: str, value: str | None, types: Sequence[str]) -> (
    tuple[bool, str | None]
):
    """(given, topic) for an override; 'none' disables; unknown topics are errors."""
    if value is None:
        return False, None
    if value.strip().lower() in ("none", ""):
        return True, None
    if value not in bag.topics:
        have = bag.of_type(*types)
        raise BagError(f"{bag.name}: rosbag.topics.{key} is {value!r}, which is not in the bag"
                       f"; {' / '.join(t.split('/')[-1] for t in types)} topics in it: "
                       f"{', '.join(have) or 'none'}")
    if bag.topics[value].msgtype not in types:
        raise BagError(f"{bag.name}: rosbag.topics.{key} is {value!r}, which carries "
                       f"{bag.topics[value].msgtype}, not {' or '.join(types)}")
    return True, value


def _one(bag: Bag, key: str, kind: str, cands: list[str], preferred: Sequence[str]) -> (
    str | None
):
    if len(cands) <= 1:
        return cands[0] if cands else None
    for p in preferred:
        if p in cands:
            return p
    raise BagError(f"{bag.name}: several {kind} topics ({', '.join(cands)}); choose one with "
                   f"rosbag.topics.{key}")


def _strip_transport(topic: str) -> str:
    for suffix in ("/compressed", "/compressedDepth"):
        if topic.endswith(suffix):
            return topic[: -len(suffix)]
    return topic


def _namespace(topic: str) -> str:
    return _strip_transport(topic).rsplit("/", 1)[0]


def _base_name(topic: str) -> str:
    return _strip_transport(topic).rsplit("/", 1)[-1]


# Image topics by encoding, in the order the colour topic is chosen from: 8-bit colour as it
# is; YUV 4:2:2 and 16-bit colour, converted here (a camera's raw stream beside its own
# 8-bit conversion); Bayer mosaics, demosaiced here; grey (mono8, mono16), more often an
# infrared camera (a RealSense's infra1 is mono8, its Y16 mono16) or depth labelled so
# than the colour camera; unknown (an error).
_IMAGE_PILES = ("color", "converted", "bayer", "gray8", "gray16", "other")
_PASSED_OVER = {
    "converted": "YUV / 16-bit colour topics ({}) are passed over for the 8-bit colour ones; "
                 "name one with rosbag.topics.image to convert it here",
    "bayer": "Bayer mosaic topics ({}) are passed over for the colour ones; name one with "
             "rosbag.topics.image to demosaic it here",
    "gray8": "grey topics ({}) are passed over for the colour ones (an infrared camera's); "
             "name one with rosbag.topics.image to read it as grey",
    "gray16": "mono16 topics ({}) are passed over for the colour ones (an infrared camera's, "
              "or depth); name one with rosbag.topics.image to read it as grey",
    "other": "",
}


def _image_pile(enc: str) -> str:
    """Which of ``_IMAGE_PILES`` (or 'depth') an image of encoding ``enc`` belongs to."""
    if enc in BAYER_TO_RGB:
        return "bayer"
    if enc == "mono16":
        return "gray16"
    if enc in COLOR_ENCODINGS:
        spec = COLOR_ENCODINGS[enc]
        if spec.channels == 1:
            return "gray8"
        return "color" if spec.bits == 8 and spec.channels != 2 else "converted"
    return "depth" if enc in DEPTH_ENCODINGS else "other"


def choose_topics(bag: Bag, topics: RosbagTopics) -> TopicChoice:
    """Find the topics by type (see the module docstring), honouring overrides."""
    ch = TopicChoice()
    given, ch.scan = _override(bag, "scan", topics.scan, (SCAN,))
    if not given:
        ch.scan = _one(bag, "scan", "sensor_msgs/LaserScan", bag.of_type(SCAN), ("/scan",))
    if ch.scan is None:
        # An empty recording listed nothing after "Topics in the bag:"; with counts, a
        # topic the recorder subscribed to but never heard from shows as such.
        if not bag.reader.message_count:
            raise BagError(f"{bag.name}: the bag holds no messages (an empty recording: "
                           "the recorder stopped before the drivers published, or a filter "
                           "kept nothing); this toolkit needs a 2D lidar's "
                           "sensor_msgs/LaserScan. Fix: record again with the lidar driver "
                           "running, or convert another bag")
        raise BagError(f"{bag.name}: no sensor_msgs/LaserScan topic with messages; this "
                       "toolkit needs a 2D lidar. Topics in the bag: "
                       + ", ".join(f"{t.name} ({t.msgtype}, {t.count} messages)"
                                   for t in bag.topics.values()))

    # Sort image topics into piles by their first message's encoding.
    peek: dict[str, Any] = {}
    piles: dict[str, list[str]] = {kind: [] for kind in (*_IMAGE_PILES, "depth")}
    for t in bag.of_type(IMAGE, COMPRESSED):
        msg = bag.first(t)
        if msg is None:
            continue
        peek[t] = msg
        if bag.topics[t].msgtype == IMAGE:
            piles[_image_pile(str(msg.encoding))].append(t)
        elif "compresseddepth" in str(msg.format).lower():
            piles["depth"].append(t)
        else:
            kind = _image_pile(compressed_format(str(msg.format))[0])
            if kind == "depth":
                # A depth image through the colour codec ('16UC1; png compressed ', what
                # `rosbag record -a` keeps of a depth camera's /compressed): no colour
                # candidate (it made a bag with one colour camera ambiguous); depth is read
                # from raw or compressedDepth topics.
                continue
            # The payload of a format without a known encoding ('jpeg', 'png') is colour.
            piles[kind if kind in _IMAGE_PILES[:-1] else "color"].append(t)
    depth = piles["depth"]

    given, ch.image = _override(bag, "image", topics.image, (IMAGE, COMPRESSED))
    if not given:
        # A camera driver's (or image_proc's) 8-bit colour stream beats the raw stream it
        # was converted or demosaiced from; an image in an unknown encoding errors when
        # decoded.
        first = next((k for k in _IMAGE_PILES if piles[k]), "other")
        cands = piles[first]
        for kind in _IMAGE_PILES[_IMAGE_PILES.index(first) + 1:]:
            if piles[kind] and _PASSED_OVER[kind]:
                ch.notes.append(_PASSED_OVER[kind].format(", ".join(piles[kind])))
        raw = {t for t in cands if bag.topics[t].msgtype == IMAGE}
        # image_transport republishes /x as /x/compressed: the raw one is lossless.
        cands = [t for t in cands if not (t.endswith("/compressed") and
                                          t[: -len("/compressed")] in raw)]
        ch.image = _one(bag, "image", "colour image", cands, ())
    if ch.image is not None:
        msg = peek.get(ch.image) or bag.first(ch.image)
        if msg is None:
            raise BagError(f"{bag.name}: topic {ch.image} has no messages")
        ch.image_compressed = bag.topics[ch.image].msgtype == COMPRESSED
        if ch.image_compressed:
            rgb = compressed_to_rgb(msg, f"{bag.name}: topic {ch.image}")
            ch.image_size = (rgb.shape[1], rgb.shape[0])
            ch.image_encoding = str(msg.format)
        else:
            ch.image_size = (int(msg.width), int(msg.height))
            ch.image_encoding = str(msg.encoding)
            image_to_rgb(msg, f"{bag.name}: topic {ch.image}")  # unknown encoding: fail now
        ch.image_frame = _frame(str(msg.header.frame_id))

    given, ch.depth = _override(bag, "depth", topics.depth, (IMAGE, COMPRESSED))
    if ch.image is None:
        ch.depth = None
    elif not given and depth:
        same = [t for t in depth if _size(peek[t], f"{bag.name}: topic {t}") == ch.image_size
                and _frame(str(peek[t].header.frame_id)) == ch.image_frame]
        for t in sorted(set(depth) - set(same)):
            ch.notes.append(f"depth topic {t} is not registered to {ch.image} (another image "
                            "size or frame_id); not used")
        pref = [t for t in same if "align" in t or "regist" in t]
        ch.depth = _one(bag, "depth", "registered depth", same, pref[:1] if len(pref) == 1
                        else ())
    if ch.depth is not None:
        ch.depth_compressed = bag.topics[ch.depth].msgtype == COMPRESSED
        msg = peek.get(ch.depth) or bag.first(ch.depth)
        size = _size(msg, f"{bag.name}: topic {ch.depth}") if msg is not None else None
        frame = _frame(str(msg.header.frame_id)) if msg is not None else ""
        if given and frame and ch.image_frame and frame != ch.image_frame:
            ch.notes.append(f"depth topic {ch.depth} is in frame {frame!r}, the images in "
                            f"{ch.image_frame!r}: kept as named, but a depth image registered "
                            "to the colour camera carries its frame_id")
        if size != ch.image_size:
            raise BagError(f"{bag.name}: depth topic {ch.depth} is {size} but the image topic "
                           f"{ch.image} is {ch.image_size} (width, height); the depth must be "
                           "registered to the colour camera (e.g. aligned_depth_to_color). "
                           "Set rosbag.topics.depth to such a topic, or 'none'")

    given, ch.camera_info = _override(bag, "camera_info", topics.camera_info, (CAMERA_INFO,))
    if not given and ch.image is not None:
        infos = bag.of_type(CAMERA_INFO)
        same_ns = [t for t in infos if _namespace(t) == _namespace(ch.image)]
        # Outside the image's namespace only a CameraInfo of the same optical frame and
        # size describes these pixels: a depth or infrared camera's has its own. (Without
        # one in the namespace every CameraInfo's first message is read, once.)
        frames = {t: bag.first(t) for t in infos} if not same_ns else {}
        same_cam = [t for t, m in frames.items() if m is not None
                    and _frame(str(m.header.frame_id)) == ch.image_frame
                    and camera_info_size(m) == ch.image_size]
        ch.camera_info = same_ns[0] if same_ns else (same_cam[0] if len(same_cam) == 1
                                                      else None)
        if ch.camera_info is None and infos:
            ch.notes.append(
                "CameraInfo topics in the bag: " + ", ".join(
                    f"{t} (frame {_frame(str(m.header.frame_id))!r}, "
                    f"{'x'.join(map(str, camera_info_size(m)))})"
                    for t, m in frames.items() if m is not None)
                + f"; none is in the namespace of {ch.image} or of its frame "
                f"{ch.image_frame!r} and size {ch.image_size}, so none is used. If one "
                "describes these images, name it with rosbag.topics.camera_info")

    given, ch.odometry = _override(bag, "odometry", topics.odometry, (ODOMETRY,))
    if not given:
        ch.odometry = _one(bag, "odometry", "nav_msgs/Odometry", bag.of_type(ODOMETRY),
                           ("/odom", "/odometry"))
    ch.tf = bag.of_type(*TF_TYPES)
    scan = bag.first(ch.scan)
    ch.scan_frame = _frame(str(scan.header.frame_id)) if scan is not None else ""
    return ch


def _size(msg: Any, where: str) -> tuple[int, int]:
    if hasattr(msg, "encoding"):
        return int(msg.width), int(msg.height)
    if "compresseddepth" in str(msg.format).lower():
        d = compressed_to_depth(msg, where)
    else:
        d = compressed_to_rgb(msg, where)
    return d.shape[1], d.shape[0]


def format_topics(bag: Bag, ch: TopicChoice,
                  seen: dict[str, tuple[int, int, int]] | None = None) -> str:
    """The table printed before converting: every topic with its count; for the topics
    read, the mean rate and time span of their stamps (``seen``: topic -> (count, first
    ns, last ns)); unread topics are not decoded just to time them."""
    seen = seen or {}
    dur = (bag.end_ns - bag.start_ns) / 1e9
    t0 = datetime.fromtimestamp(bag.start_ns / 1e9, UTC).isoformat(timespec="seconds")
    lines = [f"{bag.kind} bag {bag.name}: {bag.reader.message_count} messages, recorded over "
             f"{dur:.1f} s from {t0}"]
    width = max([len(t) for t in bag.topics] + [5])
    twidth = max([len(t.msgtype) for t in bag.topics.values()] + [4])
    lines.append(f"  {'topic':<{width}}  {'type':<{twidth}}  {'count':>7}  {'rate Hz':>8}  "
                 f"{'span s':>8}  used as")
    for name in sorted(bag.topics):
        t = bag.topics[name]
        rate = span = "-"
        if name in seen:
            n, first, last = seen[name]
            sp = (last - first) / 1e9
            span = f"{sp:.2f}"
            rate = f"{(n - 1) / sp:.2f}" if n > 1 and sp > 0 else "-"
        role = ch.role(name)
        if role == "image":
            role += f" ({ch.image_encoding})"
        lines.append(f"  {name:<{width}}  {t.msgtype:<{twidth}}  {t.count:>7}  {rate:>8}  "
                     f"{span:>8}  {role or '-'}")
    lines += [f"  note: {n}" for n in ch.notes]
    return "\n".join(lines)


# ---------------------------------------------------------------------------- reading


@dataclass
class _Stream:
    """Stamps (ns) and bag times of one topic's messages, as indexed."""

    stamps: list[int] = field(default_factory=list)
    bag_ns: list[int] = field(default_factory=list)
    sizes: list[tuple[int, int]] = field(default_factory=list)


def read_rosbag(path: Path | str | Sequence[Path | str], options: RosbagOptions | None = None,
                on_non_monotonic: Literal["error", "drop"] = "error",
                progress: Callable[..., Iterator[Any]] | None = None,
                log: logging.Logger | None = None, name: str | None = None) -> Recording:
    """Index a bag into a ``Recording`` (see the module docstring).

    Logs the topic table before the index pass. Errors (``BagError``) name the bag, the
    topic and the field, and say what to change.
    """
    opts = options or RosbagOptions()
    log = log or _log
    paths = bag_paths(path)
    cal = load_calibration(opts.calibration) if opts.calibration else None
    with Bag(paths) as bag:
        ch = choose_topics(bag, opts.topics)
        idx = _index_pass(bag, ch, opts, progress)
        log.info("%s", format_topics(bag, ch, idx.seen))
    return _build(paths, bag.kind, ch, idx, opts, cal, on_non_monotonic, log, name)


@dataclass
class _Index:
    scans: list[LaserScan] = field(default_factory=list)
    scan_ns: list[int] = field(default_factory=list)
    scan_bag_ns: list[int] = field(default_factory=list)
    image: _Stream = field(default_factory=_Stream)
    depth: _Stream = field(default_factory=_Stream)
    odom_ns: list[int] = field(default_factory=list)
    odom_bag_ns: list[int] = field(default_factory=list)
    # Odometry poses as flat float64 runs, [N * 3] positions and [N * 4] unit xyzw
    # quaternions (array('d'): 56 bytes a message, where a [4, 4] array each took ~340 and
    # 50 Hz for an hour is 180 000 of them); made into matrices at once in _build.
    odom_xyz: array = field(default_factory=lambda: array("d"))
    odom_quat: array = field(default_factory=lambda: array("d"))
    odom_frames: tuple[str, str] = ("odom", "base_link")
    # Odometry messages that are no pose, left out: their stamps (the header's, the
    # recording time where that is zero), how many valid ones came before each, and
    # what was wrong with the first one.
    odom_bad_s: list[float] = field(default_factory=list)
    odom_bad_before: list[int] = field(default_factory=list)
    odom_bad_reason: str | None = None
    info: Any = None  # the first calibrated CameraInfo (else the first one)
    info_uncalibrated: int = 0  # CameraInfo messages with K all zero before a calibrated one
    # (when, field) where a later CameraInfo first differs from ``info``: "stamp 12.3 s"
    info_changed: tuple[str, str] | None = None
    info_fields: dict[str, np.ndarray] | None = None  # ``info``'s, once it is calibrated
    tf: TfTree = field(default_factory=TfTree)
    seen: dict[str, tuple[int, int, int]] = field(default_factory=dict)  # count, first, last
    intensities_dropped: int = 0  # scans whose intensities did not match their ranges

    def odom_messages(self) -> int:
        """Index of the next odometry message in the topic (valid or not)."""
        return len(self.odom_ns) + len(self.odom_bad_s)


def _camera_info_fields(msg: Any) -> dict[str, np.ndarray]:
    return {"width/height": np.array([int(msg.width), int(msg.height)], np.float64),
            "K": np.asarray(_field(msg, "k", "K"), np.float64),
            "D": np.asarray(_field(msg, "d", "D"), np.float64),
            "P": np.asarray(_field(msg, "p", "P"), np.float64),
            "R": np.asarray(_field(msg, "r", "R"), np.float64),
            "roi": np.array(_roi(msg), np.float64)}


def _note_camera_info(idx: _Index, msg: Any, stamp_ns: int, clock: str = "stamp") -> None:
    """Keep the first calibrated CameraInfo; note where a later one differs from it. Only
    the first one was read: a camera calibrated while recording took the uncalibrated
    first message's all-zero K (refused as uncalibrated), and intrinsics changed mid-bag
    were applied to every frame without a word. ``clock`` names what ``stamp_ns`` is."""
    calibrated = bool(np.any(_field(msg, "k", "K")))
    if idx.info is None or not np.any(_field(idx.info, "k", "K")):  # none calibrated yet
        idx.info_uncalibrated += not calibrated
        if idx.info is None or calibrated:
            idx.info = msg
        return
    if idx.info_changed is not None or not calibrated:
        return
    # The first one's fields are made once, and equal fields skip allclose: remade and
    # compared for every message (15-30 Hz for the whole recording) they took 1.15 s of a
    # 5-min bag's index pass under cProfile (0.25 ms a message).
    if idx.info_fields is None:
        idx.info_fields = _camera_info_fields(idx.info)
    first, now = idx.info_fields, _camera_info_fields(msg)
    for name, value in now.items():
        if np.array_equal(value, first[name]):
            continue  # the usual case, decided without allclose's cost
        # NaN equals NaN here: a field that holds one in every message did not change
        # (it was reported as a recalibration); camera_info_to_camera names it instead.
        if value.shape != first[name].shape or not np.allclose(
                value, first[name], rtol=1e-9, atol=1e-9, equal_nan=True):
            idx.info_changed = (f"{clock} {stamp_ns / 1e9:.6f} s", name)
            return


def _stamp(msg: Any, ns: int, opts: RosbagOptions, where: str) -> int:
    if opts.stamps == "bag":
        return ns
    s = header_ns(msg)
    if s == 0:
        raise BagError(f"{where}: field 'header.stamp' is zero; the driver did not stamp its "
                       "messages. Fix: set 'rosbag.stamps: bag' to use the recording time")
    return s


def _index_pass(bag: Bag, ch: TopicChoice, opts: RosbagOptions,
                progress: Callable[..., Iterator[Any]] | None) -> _Index:
    idx = _Index()
    topics = [t for t in (ch.scan, ch.image, ch.depth, ch.camera_info, ch.odometry) if t]
    topics += ch.tf
    total = sum(bag.topics[t].count for t in topics)
    it = bag.messages(topics)
    if progress is not None:
        it = progress(it, total=total, description="indexing bag")
    for topic, ns, msg in it:
        where = f"{bag.name}: topic {topic}"
        # Rates come from the stamps that will be used (recording time for tf).
        t = ns if topic in ch.tf or opts.stamps == "bag" else header_ns(msg)
        # A zero CameraInfo stamp is no error (below); its rate is the recording's.
        rate_t = ns if t == 0 and topic == ch.camera_info else t
        n, first, last = idx.seen.get(topic, (0, rate_t, rate_t))
        idx.seen[topic] = (n + 1, min(first, rate_t), max(last, rate_t))
        if topic == ch.scan:
            stamp = _stamp(msg, ns, opts, where)
            # (A default-constructed message, no ranges, holds zeros there: a dropout.)
            if len(msg.ranges) and not float(msg.range_min) < float(msg.range_max):
                raise BagError(f"{where}: message {len(idx.scans)}: fields 'range_min' "
                               f"({float(msg.range_min)}) and 'range_max' "
                               f"({float(msg.range_max)}): no reading could count as a "
                               "return; the driver fills them wrongly (fix its parameters or "
                               "rewrite the bag's scans)")
            try:
                inten = np.array(msg.intensities, dtype=np.float32)
                if len(inten) and len(inten) != len(msg.ranges):
                    idx.intensities_dropped += 1
                inc = float(msg.angle_increment)
                if not len(msg.ranges) and inc == 0:
                    # A default-constructed message (a driver's dropout): its layout is
                    # replaced by the common one (uniform_scans), so any step will do.
                    inc = 1.0
                scan = LaserScan(stamp / 1e9, np.array(msg.ranges, dtype=np.float32),
                                 float(msg.angle_min), inc,
                                 float(msg.range_min), float(msg.range_max),
                                 inten if len(inten) == len(msg.ranges) else None,
                                 float(msg.time_increment))
            except ValueError as e:
                raise BagError(f"{where}: message {len(idx.scans)}: {e}") from None
            idx.scans.append(scan)
            idx.scan_ns.append(stamp)
            idx.scan_bag_ns.append(ns)
        elif topic in (ch.image, ch.depth):
            s = idx.image if topic == ch.image else idx.depth
            s.stamps.append(_stamp(msg, ns, opts, where))
            s.bag_ns.append(ns)
            compressed = ch.image_compressed if topic == ch.image else ch.depth_compressed
            s.sizes.append((-1, -1) if compressed else (int(msg.width), int(msg.height)))
        elif topic == ch.camera_info:
            # Its stamp only names where the intrinsics change: a zero one (a static or
            # hand-published camera_info) stopped the conversion, even with the intrinsics
            # from a calibration YAML, and 'stamps: bag' re-timed every scan and image.
            _note_camera_info(idx, msg, rate_t, "recording time" if t == 0 else "stamp")
        elif topic == ch.odometry:
            try:
                xyz, quat = checked_xyz_quat(msg.pose.pose)
            except NotATransformError as e:
                # A driver's message before its first fix, or a glitch: left out and
                # counted (as /tf's are), the topic refused in _build only when few
                # poses remain. Its stamp may be zero too (a default-constructed message).
                if idx.odom_bad_reason is None:
                    idx.odom_bad_reason = (f"message {idx.odom_messages()} of the topic: "
                                           f"field 'pose.pose.{e.part}': {e}")
                h = header_ns(msg) if opts.stamps == "header" else 0
                idx.odom_bad_s.append((h or ns) / 1e9)
                idx.odom_bad_before.append(len(idx.odom_ns))
                continue
            idx.odom_ns.append(_stamp(msg, ns, opts, where))
            idx.odom_bag_ns.append(ns)
            idx.odom_xyz.extend(xyz)
            idx.odom_quat.extend(quat)
            idx.odom_frames = (_frame(str(msg.header.frame_id)) or "odom",
                               _frame(str(msg.child_frame_id)) or opts.frames.base)
        else:  # tf
            static = "static" in topic
            for tr in msg.transforms:
                parent, child = str(tr.header.frame_id), str(tr.child_frame_id)
                try:
                    if not static and idx.tf.is_moving(parent, child):
                        # odom -> base_link at 50-100 Hz: only counted when invalid, as
                        # before, but no matrix is built that add() would drop.
                        checked_xyz_quat(tr.transform)
                        continue
                    T = transform_to_matrix(tr.transform)
                except NotATransformError:
                    idx.tf.add_invalid(parent, child)
                    continue
                idx.tf.add(parent, child, T, static, topic)
    return idx


def _check_clocks(idx: _Index, ch: TopicChoice, opts: RosbagOptions, bag_name: str) -> None:
    """Refuse header stamps of topics whose drivers use different clocks: the recorder
    receives them all within a fraction of a second, so (header stamp - recording time)
    is about the same for every topic on one clock at any one moment of the recording.
    Compared moment by moment (the scans' offset interpolated at each message's recording
    time), not as whole-stream medians: replayed at another rate, or from a simulator
    slower than real time, the offset drifts through the recording for every topic alike."""
    limit = opts.max_clock_offset_s
    if opts.stamps != "header" or limit is None or not idx.scan_ns:
        return
    scan_bag = np.asarray(idx.scan_bag_ns, dtype=np.int64)
    order = np.argsort(scan_bag, kind="stable")
    scan_bag_s = (scan_bag[order] - scan_bag[order][0]) / 1e9
    scan_off_s = (np.asarray(idx.scan_ns, dtype=np.int64)[order] - scan_bag[order]) / 1e9
    ref = float(np.median(scan_off_s))
    for topic, stamps, bag_ns in ((ch.image, idx.image.stamps, idx.image.bag_ns),
                                  (ch.depth, idx.depth.stamps, idx.depth.bag_ns),
                                  (ch.odometry, idx.odom_ns, idx.odom_bag_ns)):
        if not topic or not stamps:
            continue
        bag = np.asarray(bag_ns, dtype=np.int64)
        own = (np.asarray(stamps, dtype=np.int64) - bag) / 1e9
        at = np.interp((bag - scan_bag[order][0]) / 1e9, scan_bag_s, scan_off_s)
        diff = float(np.median(own - at))
        off = ref + diff
        if abs(diff) > limit:
            raise BagError(
                f"{bag_name}: the drivers stamp on different clocks: header stamp minus "
                f"recording time is {ref:+.3f} s on {ch.scan} but {off:+.3f} s on {topic} "
                f"(medians, at the same recording times), so messages {abs(diff):.2f} s "
                "apart would be paired. One "
                "driver stamps in another time base (TAI/GPS time, time since boot). Fix: "
                "'rosbag.stamps: bag' (the recording time for every topic), or correct that "
                "driver's clock; if the recorder really received this topic that late, set "
                f"'rosbag.max_clock_offset_s' above {abs(diff):.1f} (or null)")


def _keep(stamps: list[int], where: str, policy: Literal["error", "drop"],
          dropped: dict[str, int], key: str) -> np.ndarray:
    # In integer nanoseconds: float seconds tie where nanoseconds do not.
    keep = stamps_keep(np.asarray(stamps, dtype=np.int64), where, policy,
                       fix=", or 'rosbag.stamps: bag' to use the recording time", unit_s=1e-9)
    dropped[key] = int((~keep).sum())
    return keep


def _beam_timing(scans: list[LaserScan], use: str, stamps: str, where: str,
                 log: logging.Logger) -> list[LaserScan]:
    """``scans`` with their time_increment, checked (a sweep longer than the time between
    scans is a driver's error, e.g. a whole turn's time per beam), stamped at the first
    beam (``last_beam``), or dropped."""
    timed = any(s.time_increment for s in scans)
    if timed and use != "ignore" and stamps == "bag":
        # Recording times come after the sweep by an unknown delay: de-skewing from them
        # doubled the error of ignoring the timing on a simulated drive.
        log.warning("%s: rosbag.stamps is 'bag', so a scan's stamp is not its first beam's "
                    "time; its beam timing (time_increment) is not used", where)
        use = "ignore"
    if use == "ignore":
        return [replace(s, time_increment=0.0) if s.time_increment else s for s in scans]
    sweeps = np.array([abs(s.sweep_s) for s in scans])
    if len(scans) < 2 or not sweeps.any():
        return scans
    period = float(np.median(np.diff([s.stamp for s in scans])))
    sweep = float(np.median(sweeps))
    if period > 0 and sweep > 1.5 * period:
        raise BagError(
            f"{where}: time_increment says one sweep takes {sweep:.4f} s, but scans come "
            f"every {period:.4f} s; the driver's beam timing is wrong - set "
            "'rosbag: {beam_timing: ignore}' to use the scans without it")
    if use == "last_beam":
        out = [replace(s, stamp=s.stamp - s.sweep_s) if s.time_increment else s
               for s in scans]
        # Each scan moves back by its own sweep: one glitched time_increment put a scan
        # before the one ahead of it, which the stamp checks had passed.
        back = np.flatnonzero(np.diff([s.stamp for s in out]) <= 0)
        if len(back):
            i = int(back[0]) + 1
            raise BagError(
                f"{where}: scan {i} (of those kept): stamped at its first beam, "
                f"{scans[i].sweep_s:.4f} s before its stamp (time_increment "
                f"{scans[i].time_increment:g}), it is no longer after scan {i - 1}; the "
                "driver's beam timing is wrong for it - set 'rosbag: {beam_timing: ignore}' "
                "to use the scans without it")
        return out
    return scans


def _build(paths: list[Path], kind: str, ch: TopicChoice, idx: _Index, opts: RosbagOptions,
           cal: Calibration | None, policy: Literal["error", "drop"], log: logging.Logger,
           name: str | None) -> Recording:
    bag_name = ", ".join(str(p) for p in paths)
    _check_clocks(idx, ch, opts, bag_name)
    if idx.tf.invalid:
        log.warning("%s: tf transforms that are no rotation or not finite were skipped%s",
                    bag_name,
                    idx.tf.invalid_note().partition(":")[2])
    if idx.intensities_dropped:
        log.warning("%s: topic %s: %d scans carry intensities of another length than their "
                    "ranges; stored without intensities (zeros)", bag_name, ch.scan,
                    idx.intensities_dropped)
    dropped: dict[str, int] = {}
    # --- stamps
    k = _keep(idx.scan_ns, f"{bag_name}: topic {ch.scan}", policy, dropped, str(ch.scan))
    scans = [s for s, keep in zip(idx.scans, k, strict=True) if keep]
    if not scans:
        raise BagError(f"{bag_name}: topic {ch.scan} has no scans")
    scans = _beam_timing(scans, opts.beam_timing, opts.stamps, f"{bag_name}: topic {ch.scan}",
                         log)
    img = _filtered(idx.image, f"{bag_name}: topic {ch.image}", policy, dropped, ch.image)
    dep = _filtered(idx.depth, f"{bag_name}: topic {ch.depth}", policy, dropped, ch.depth) \
        if ch.depth else None

    # --- camera
    base = _frame(opts.frames.base)
    tree = idx.tf
    if cal is not None:
        for parent, child, T in cal.transforms:
            tree.add(parent, child, T, True, str(cal.path), override=True)
    has_camera = ch.image is not None
    # image_rect / image_rect_color / image_mono_rect carry undistorted pixels (image_proc's
    # names): "rect" as a word of the name, not inside one (image_color_corrected is raw).
    rectified = opts.rectified if opts.rectified is not None else (
        has_camera and re.search(r"(^|_)rect(_|$)", _base_name(str(ch.image))) is not None)
    if not has_camera:
        camera = placeholder_camera()
    elif cal is not None and cal.camera is not None:
        camera = cal.camera
    elif idx.info is not None:
        if idx.info_changed is not None:
            when, what = idx.info_changed
            raise BagError(
                f"{bag_name}: topic {ch.camera_info}: field '{what}' changes at {when} "
                "(the camera was calibrated again while recording): one set "
                "of intrinsics would be applied to every frame. Fix: give the intrinsics "
                "that hold for the images in a calibration YAML ('camera: {width, height, "
                "fx, fy, cx, cy, distortion}', rosbag.calibration), or convert the parts "
                "before and after the change separately")
        if idx.info_uncalibrated and np.any(_field(idx.info, "k", "K")):
            log.info("%s: %d CameraInfo messages with K all zero (not yet calibrated) came "
                     "before the first calibrated one; that one is used", bag_name,
                     idx.info_uncalibrated)
        camera = camera_info_to_camera(idx.info, f"{bag_name}: topic {ch.camera_info}",
                                       rectified=bool(rectified))
    else:
        about = [n for n in ch.notes if n.startswith("CameraInfo topics")]
        raise BagError(
            f"{bag_name}: no sensor_msgs/CameraInfo for image topic {ch.image}"
            + (f" ({about[0]})" if about else "") + ". Fix: name one "
            "with rosbag.topics.camera_info, or give the intrinsics in a calibration YAML "
            "('camera: {width, height, fx, fy, cx, cy, distortion: [k1, k2, p1, p2, k3]}') "
            "and set rosbag.calibration")
    if has_camera:
        w, h = camera.size
        from_info = cal is None or cal.camera is None
        src = f"CameraInfo topic {ch.camera_info}" if from_info else \
            f"calibration file {cal.path}"  # type: ignore[union-attr]
        fields = "roi.width/roi.height" if from_info and any(_roi(idx.info)) else \
            "width/height"
        # Raw images: every size is known from the index; compressed: the first one.
        for i, size in enumerate([ch.image_size or (w, h), *idx.image.sizes]):
            if size != (-1, -1) and size != (w, h):
                raise BagError(
                    f"{bag_name}: topic {ch.image}: image {max(i - 1, 0)}"
                    f" is {size[0]}x{size[1]} but the {src} says {w}x{h} (fields "
                    f"{fields}). Fix: use the CameraInfo of this image stream "
                    "(rosbag.topics.camera_info), or give intrinsics for this image size in "
                    "the calibration YAML ('camera:')")

    # --- extrinsics
    cam_frame = _frame(opts.frames.camera or ch.image_frame)
    laser_frame = _frame(opts.frames.laser or ch.scan_frame)
    sources: dict[str, str] = {}
    if has_camera:
        if cal is not None and cal.T_base_camera is not None:
            cal.check_direction("T_base_camera", base, cam_frame or "camera", bool(cam_frame))
            T_base_camera = cal.T_base_camera
            sources["T_base_camera"] = str(cal.path)
            _warn_if_not_upright(T_base_camera, cam_frame or "camera", opts, log, cal.path)
        else:
            if not cam_frame:
                raise BagError(f"{bag_name}: topic {ch.image}: field 'header.frame_id' is "
                               "empty; name the camera frame with rosbag.frames.camera")
            T_base_camera = _lookup(tree, base, cam_frame, "camera", bag_name, ch, laser_frame,
                                    log)
            if opts.frames.camera_convention == "body":
                T_base_camera = T_base_camera @ optical_mount()
            sources["T_base_camera"] = f"tf {base} <- {cam_frame}"
            if rectified and idx.info is not None:
                # Rectified pixels belong to the frame turned by CameraInfo's R (stereo
                # rectification; identity for a single camera): X_rect = R @ X_camera -
                # wherever the intrinsics come from (a calibration YAML's camera too).
                T_camera_rect = np.eye(4)
                T_camera_rect[:3, :3] = rectification_rotation(
                    idx.info, f"{bag_name}: topic {ch.camera_info}").T
                T_base_camera = T_base_camera @ T_camera_rect
            _warn_if_not_upright(T_base_camera, cam_frame, opts, log)
    else:
        T_base_camera = optical_mount()
        sources["T_base_camera"] = "placeholder (no camera)"
    if cal is not None and cal.T_base_laser is not None:
        cal.check_direction("T_base_laser", base, laser_frame or "laser", bool(laser_frame))
        T_base_laser = cal.T_base_laser
        sources["T_base_laser"] = str(cal.path)
    elif cal is not None and cal.T_camera_laser is not None and has_camera:
        cal.check_direction("T_camera_laser", cam_frame or "camera", laser_frame or "laser",
                            bool(laser_frame))
        T_base_laser = T_base_camera @ cal.T_camera_laser
        sources["T_base_laser"] = f"T_base_camera @ T_camera_laser from {cal.path}"
    else:
        if not laser_frame:
            raise BagError(f"{bag_name}: topic {ch.scan}: field 'header.frame_id' is empty; "
                           "name the laser frame with rosbag.frames.laser")
        T_base_laser = _lookup(tree, base, laser_frame, "laser", bag_name, ch, cam_frame, log)
        sources["T_base_laser"] = f"tf {base} <- {laser_frame}"
    rig = Rig(camera, T_base_camera, T_base_laser)

    # --- odometry
    odometry = None
    skipped: dict[str, dict[str, Any]] = {}
    bad = skipped_record(
        f"{bag_name}: topic {ch.odometry}", idx.odom_messages(), idx.odom_bad_s,
        idx.odom_bad_reason or "", "leave the odometry out (rosbag.topics.odometry: none; the "
        "SLAM runs on the scans alone) or name another topic") if ch.odometry else None
    if ch.odometry and idx.odom_ns:
        ko = _keep(idx.odom_ns, f"{bag_name}: topic {ch.odometry}", policy, dropped,
                   ch.odometry)
        st = np.asarray(idx.odom_ns, dtype=np.int64)[ko] / 1e9
        P = pose_from_xyz_quat(np.frombuffer(idx.odom_xyz).reshape(-1, 3)[ko],
                               np.frombuffer(idx.odom_quat).reshape(-1, 4)[ko])  # [N, 4, 4]
        child = idx.odom_frames[1]
        if child != base:
            found = tree.lookup(child, base)
            if found is not None:
                P = P @ found[0]  # T_odom_child @ T_child_base
            else:
                log.warning("odometry on %s is for frame %r, which tf does not connect to %r; "
                            "using it as the base pose", ch.odometry, child, base)
        odometry = Trajectory(st, P, "odom", "base_link")
        if bad is not None:
            note_skipped_gaps(bad, odometry, np.asarray(idx.odom_ns, dtype=np.int64) / 1e9, ko,
                              np.asarray(idx.odom_bad_before, dtype=np.int64),
                              f"{bag_name}: topic {ch.odometry}", log)
            skipped[ch.odometry] = bad
        scan_t = np.array([sc.stamp for sc in scans])
        covered = float(odometry.covers(scan_t, slack_s=0.1).mean())
        if covered == 0.0:
            raise BagError(
                f"{bag_name}: topic {ch.odometry}: the odometry (stamps {st[0]:.3f} .. "
                f"{st[-1]:.3f} s) covers none of the scans ({scan_t[0]:.3f} .. "
                f"{scan_t[-1]:.3f} s): its driver stamps on another clock. Fix: "
                "'rosbag.stamps: bag', or leave it out with 'rosbag.topics.odometry: none'")
        if covered < 0.5:
            log.warning("%s: the odometry on %s covers %.0f %% of the scans' times; the rest "
                        "are matched without an odometry prior", bag_name, ch.odometry,
                        100 * covered)

    frame_stamps = np.asarray(img.stamps, dtype=np.int64) / 1e9 if has_camera else np.zeros(0)
    meta = {
        "source_kind": kind,
        "topics": {k: v for k, v in (("scan", ch.scan), ("image", ch.image),
                                     ("depth", ch.depth), ("camera_info", ch.camera_info),
                                     ("odometry", ch.odometry)) if v},
        "frames": {"base": base, "camera": cam_frame if has_camera else None,
                   "laser": laser_frame},
        "extrinsics_from": sources,
        "stamps": opts.stamps,
        "beam_timing": ("none in the bag" if not any(s.time_increment for s in idx.scans)
                        else opts.beam_timing if any(s.time_increment for s in scans)
                        else "ignored"),
    }
    if rectified and has_camera:
        meta["rectified_images"] = True
    loader = _make_loader(paths, ch, opts, img, dep, camera) if has_camera else _no_frames
    return Recording(
        name=name or paths[0].stem, source=f"rosbag {bag_name}", rig=rig, scans=scans,
        frame_stamps=frame_stamps, load=loader,
        depth_stamps=np.asarray(dep.stamps, dtype=np.int64) / 1e9 if dep else None,
        odometry=odometry, has_camera=has_camera, meta=meta, dropped=dropped,
        skipped=skipped,
        tf_skipped={f"{p} -> {c}": n for (p, c), n in sorted(idx.tf.invalid.items())})


def _no_frames(pairs: Sequence[tuple[int, int]]) -> Iterator[FrameData]:
    if pairs:
        raise BagError("this recording has no camera")
    return iter(())


def _filtered(s: _Stream, where: str, policy: Literal["error", "drop"],
              dropped: dict[str, int], topic: str | None) -> _Stream:
    if not topic:
        return _Stream()
    k = _keep(s.stamps, where, policy, dropped, topic)
    return _Stream([x for x, y in zip(s.stamps, k, strict=True) if y],
                   [x for x, y in zip(s.bag_ns, k, strict=True) if y],
                   [x for x, y in zip(s.sizes, k, strict=True) if y])


def _lookup(tree: TfTree, base: str, frame: str, role: str, bag_name: str, ch: TopicChoice,
            other: str, log: logging.Logger) -> np.ndarray:
    found = tree.lookup(base, frame)
    if found is not None:
        clash = tree.conflicts_on(found[1])
        if clash:
            key = "T_base_camera" if role == "camera" else "T_base_laser"
            log.warning("%s: the bag's tf gives different values for the %s mount's edge %s; "
                        "the latest static one is used for every frame. If another is the "
                        "mount (a URDF's beside a calibration's, a mount corrected while "
                        "recording), give %s in a calibration YAML (rosbag.calibration)",
                        bag_name, role, "; ".join(clash), key)
        return found[0]
    moving = tree.lookup(base, frame, include_moving=True)
    key = "T_base_camera" if role == "camera" else "T_base_laser"
    known = sorted(tree.frames())
    if moving is not None:
        raise MissingTransformError(
            f"{bag_name}: the transform {base} <- {frame} ({role}) passes through a joint that "
            f"moves during the recording (path {' -> '.join(moving[1])}); the toolkit needs a "
            f"fixed mount. Give {key} in a calibration YAML (rosbag.calibration)"
            f"{tree.invalid_note()}")
    example = _CALIB_EXAMPLE.format(base=base, camera=frame if role == "camera" else other
                                    or "camera_optical_frame",
                                    laser=frame if role == "laser" else other or "laser")
    raise MissingTransformError(
        f"{bag_name}: no transform between the base frame {base!r} and the {role} frame "
        f"{frame!r} (rosbag.frames.{role}, by default the "
        f"{'images' if role == 'camera' else 'scans'}' header.frame_id) in "
        f"{', '.join(ch.tf) or 'the bag (it has no tf topics)'}. Frames tf knows: "
        f"{', '.join(known) or 'none'}{tree.invalid_note()}. Fix: give {key} in a "
        "calibration YAML and set "
        f"'rosbag.calibration: calib.yaml', e.g.\n{example}\nor name other frames with "
        f"rosbag.frames.base / rosbag.frames.{role}")


def _warn_if_not_upright(T: np.ndarray, frame: str, opts: RosbagOptions,
                         log: logging.Logger, calibration: Path | None = None) -> None:
    """Warn when the image's down direction (optical +y, ``T_base_camera[:3, 1]``) is more
    than 60 deg from the base's down: on a ground robot that is almost always a frame
    taken in the wrong convention (camera_link read as optical turns the view up or
    sideways; an optical frame read as body turns it by 90 deg)."""
    angle = image_down_angle_deg(T)
    if angle <= 60.0:
        return
    if calibration is not None:
        log.warning("T_base_camera in %s: the image's down direction is %.0f deg from the "
                    "base's down and the camera looks along %s in the base frame. If the "
                    "camera is not mounted rolled, upside down or straight down, this is not "
                    "the optical frame's transform (x right, y down, z forward): a body "
                    "frame's (camera_link: x forward) needs the optical rotation after it",
                    calibration, angle, np.round(T[:3, 2], 2).tolist())
        return
    other = "body" if opts.frames.camera_convention == "optical" else "optical"
    log.warning("camera frame %r read as %s: the image's down direction is %.0f deg from "
                "the base's down and the camera looks along %s in the base frame. If the "
                "camera is not mounted rolled, upside down or straight down, the convention "
                "is wrong: set rosbag.frames.camera_convention: %s (camera_link frames are "
                "body, *_optical_frame ones optical), or name the optical frame with "
                "rosbag.frames.camera", frame, opts.frames.camera_convention, angle,
                np.round(T[:3, 2], 2).tolist(), other)


def _make_loader(paths: list[Path], ch: TopicChoice, opts: RosbagOptions, img: _Stream,
                 dep: _Stream | None, camera: PinholeCamera) -> Callable[
                     [Sequence[tuple[int, int]]], Iterator[FrameData]]:
    def load(pairs: Sequence[tuple[int, int]]) -> Iterator[FrameData]:
        if not pairs:
            return
        # Planned messages by (stamp, bag time): a message dropped as glitched may carry
        # exactly a kept one's stamp, and came first (its pixels went under that frame).
        want_img: dict[tuple[int, int], int] = {}
        want_dep: dict[tuple[int, int], list[int]] = {}
        start = math.inf
        for k, (f, d) in enumerate(pairs):
            want_img[(img.stamps[f], img.bag_ns[f])] = k
            start = min(start, img.bag_ns[f])
            if d >= 0 and dep is not None:
                want_dep.setdefault((dep.stamps[d], dep.bag_ns[d]), []).append(k)
                start = min(start, dep.bag_ns[d])
        # slot k: [rgb, depth, depth expected, JPEG payload, FramePixels]
        slots: dict[int, list[Any]] = {}
        nxt = 0
        w, h = camera.size
        topics = [t for t in (ch.image, ch.depth) if t]
        with Bag(paths) as bag:
            for topic, ns, msg in bag.messages(topics, start_ns=int(start)):
                where = f"{bag.name}: topic {topic}"
                stamp = ns if opts.stamps == "bag" else header_ns(msg)
                if topic == ch.image and (stamp, ns) in want_img:
                    k = want_img.pop((stamp, ns))
                    # Which message: a bad one stops every run at the same frame, and the
                    # user cuts it out of the bag by its time (rosbag filter, ros2 bag
                    # convert).
                    at = (f"{where}, message stamped {stamp / 1e9:.9f} s (recorded at "
                          f"{ns / 1e9:.9f} s)")
                    px = frame_pixels(msg, ch.image_compressed, at)
                    rgb = px.rgb
                    if rgb.shape[1] != w or rgb.shape[0] != h:
                        raise BagError(
                            f"{where}: image at {stamp / 1e9:.9f} s is {rgb.shape[1]}x"
                            f"{rgb.shape[0]} but the camera model is {w}x{h}; the stream "
                            "changed size. Fix: give intrinsics matching these images in the "
                            "calibration YAML ('camera:') or convert a part of constant size")
                    slot = slots.setdefault(k, [None, None, pairs[k][1] >= 0, None, None])
                    slot[0] = rgb
                    slot[4] = px
                    if ch.image_compressed:  # stored as it is where that is exact
                        slot[3] = np.asarray(msg.data, dtype=np.uint8).tobytes()
                elif topic == ch.depth and (stamp, ns) in want_dep:
                    d = compressed_to_depth(msg, where) if ch.depth_compressed else \
                        image_to_depth(msg, where)
                    if d.shape != (h, w):
                        raise BagError(f"{where}: depth at {stamp / 1e9:.9f} s is "
                                       f"{d.shape[1]}x{d.shape[0]}, the images {w}x{h}")
                    for k in want_dep.pop((stamp, ns)):
                        slots.setdefault(k, [None, None, True, None, None])[1] = d
                while nxt in slots and slots[nxt][0] is not None and (
                        slots[nxt][1] is not None or not slots[nxt][2]):
                    rgb, d, _, jpeg, px = slots.pop(nxt)
                    yield FrameData(stamp=img.stamps[pairs[nxt][0]] / 1e9, image=rgb, depth=d,
                                    image_jpeg=jpeg, from_16bit=px.from_16bit,
                                    peak_16bit=px.peak_16bit)
                    nxt += 1
                if nxt == len(pairs):
                    return
        raise BagError(f"{', '.join(map(str, paths))}: {len(pairs) - nxt} planned frames were "
                       "not found when reading the images (the bag changed since it was "
                       "indexed?)")

    return load

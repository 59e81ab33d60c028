"""ROS 1 / ROS 2 (sqlite3, mcap) bags written here with the rosbags writer, converted by the
``ingest`` path, and compared exactly with what was written."""

from __future__ import annotations

import dataclasses
import logging
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from toolkit.geometry import pose_from_xyz_quat
from toolkit.ingest.convert import convert
from toolkit.ingest.recording import IngestError
from toolkit.ingest.sync import DecimateOptions, SyncOptions
from toolkit.io.rosbag import (
    BagError,
    MissingTransformError,
    RosbagOptions,
    camera_info_to_camera,
    compressed_to_rgb,
    image_to_rgb,
    read_rosbag,
)
from toolkit.io.sequence import read_sequence

T0 = 1_700_000_000  # seconds: real bags carry Unix time
W, H = 32, 24
K = np.array([[40.0, 0.0, 15.5], [0.0, 41.0, 11.5], [0.0, 0.0, 1.0]])
D = np.array([0.1, -0.05, 0.001, -0.002, 0.01])
Q_OPTICAL = [0.5, -0.5, 0.5, -0.5]  # camera_link (x forward) <- optical (z forward)

# The rig the bags describe in tf_static.
T_BASE_CAMLINK = pose_from_xyz_quat(np.array([0.2, 0.05, 0.4]), np.array([0, 0.0998, 0, 0.995]))
T_CAMLINK_OPT = pose_from_xyz_quat(np.zeros(3), np.array(Q_OPTICAL))
T_BASE_LASER = pose_from_xyz_quat(np.array([0.1, 0.0, 0.25]), np.array([0, 0, 0.3827, 0.9239]))


def ns(t: float) -> int:
    return int(round(t * 1e9))


@dataclass
class BagContent:
    """What a test bag holds: the truth the conversion is compared with."""

    scan_t: list[float] = field(default_factory=list)
    time_increment: float = 0.0  # of every scan
    ranges: list[np.ndarray] = field(default_factory=list)
    intensities: list[np.ndarray] = field(default_factory=list)
    image_t: list[float] = field(default_factory=list)
    images: list[np.ndarray] = field(default_factory=list)  # RGB
    depth_t: list[float] = field(default_factory=list)
    depth_mm: list[np.ndarray] = field(default_factory=list)
    odom_t: list[float] = field(default_factory=list)
    odom_xy: list[tuple[float, float]] = field(default_factory=list)


def make_content(n_scans: int = 20, n_images: int = 8, seed: int = 0) -> BagContent:
    rng = np.random.default_rng(seed)
    c = BagContent()
    for i in range(n_scans):
        c.scan_t.append(T0 + 0.1 * i)
        r = rng.uniform(0.2, 9.0, 90).astype(np.float32)
        r[::17] = np.nan
        r[5] = np.inf
        c.ranges.append(r)
        c.intensities.append(rng.uniform(0, 100, 90).astype(np.float32))
    for i in range(n_images):
        c.image_t.append(T0 + 0.013 + 0.2 * i)
        c.images.append(rng.integers(0, 256, (H, W, 3), dtype=np.uint8))
        c.depth_t.append(T0 + 0.016 + 0.2 * i)
        c.depth_mm.append(rng.integers(0, 9000, (H, W), dtype=np.uint16))
    for i in range(2 * n_scans):
        c.odom_t.append(T0 + 0.05 * i)
        c.odom_xy.append((0.1 * i, 0.02 * i))
    return c


class BagBuilder:
    """Serialise messages for one typestore (ROS 1 noetic or ROS 2 humble)."""

    def __init__(self, ros1: bool) -> None:
        self.ros1 = ros1
        self.ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
        if "tf2_msgs/msg/TFMessage" not in self.ts.types:  # noetic's store lacks tf2_msgs
            self.ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                                "tf2_msgs/msg/TFMessage"))
        self.T = self.ts.types

    def header(self, t: float, frame: str):
        stamp = self.T["builtin_interfaces/msg/Time"](sec=int(ns(t) // 10**9),
                                                      nanosec=int(ns(t) % 10**9))
        if self.ros1:
            return self.T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)
        return self.T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def serialize(self, msg, msgtype: str) -> bytes:
        if self.ros1:
            return self.ts.serialize_ros1(msg, msgtype)
        return self.ts.serialize_cdr(msg, msgtype)

    def scan(self, t, ranges, inten, frame="laser", time_increment=0.0):
        return self.T["sensor_msgs/msg/LaserScan"](
            header=self.header(t, frame), angle_min=-1.5, angle_max=-1.5 + 89 * 0.0349,
            angle_increment=0.0349, time_increment=time_increment, scan_time=0.1,
            range_min=0.1,
            range_max=10.0, ranges=ranges, intensities=inten)

    def image(self, t, pixels: np.ndarray, encoding: str, frame="camera_optical",
              width=None, height=None, step=None, bigendian=False):
        h, w = pixels.shape[:2]
        row = pixels.reshape(h, -1).shape[1] * pixels.itemsize
        return self.T["sensor_msgs/msg/Image"](
            header=self.header(t, frame), height=height or h, width=width or w,
            encoding=encoding, is_bigendian=int(bigendian), step=step or row,
            data=np.frombuffer(pixels.tobytes(), np.uint8).copy())

    def compressed(self, t, data: bytes, fmt: str, frame="camera_optical"):
        return self.T["sensor_msgs/msg/CompressedImage"](
            header=self.header(t, frame), format=fmt, data=np.frombuffer(data, np.uint8).copy())

    def camera_info(self, t, w=W, h=H, frame="camera_optical", model="plumb_bob", d=D):
        roi = self.T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0,
                                                         width=0, do_rectify=False)
        P = np.zeros(12)
        P[[0, 2, 5, 6, 10]] = [K[0, 0], K[0, 2], K[1, 1], K[1, 2], 1.0]
        fields = dict(header=self.header(t, frame), height=h, width=w, distortion_model=model,
                      binning_x=0, binning_y=0, roi=roi)
        mats = {"D": np.asarray(d, float), "K": K.reshape(-1), "R": np.eye(3).reshape(-1),
                "P": P}
        for key, v in mats.items():
            fields[key if self.ros1 else key.lower()] = v
        return self.T["sensor_msgs/msg/CameraInfo"](**fields)

    def transform(self, t, parent, child, T):
        from scipy.spatial.transform import Rotation

        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        V = self.T["geometry_msgs/msg/Vector3"](x=T[0, 3], y=T[1, 3], z=T[2, 3])
        Q = self.T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])
        return self.T["geometry_msgs/msg/TransformStamped"](
            header=self.header(t, parent), child_frame_id=child,
            transform=self.T["geometry_msgs/msg/Transform"](translation=V, rotation=Q))

    def tf(self, transforms):
        return self.T["tf2_msgs/msg/TFMessage"](transforms=transforms)

    def odom(self, t, x, y):
        P = self.T["geometry_msgs/msg/Point"](x=x, y=y, z=0.0)
        Q = self.T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
        pose = self.T["geometry_msgs/msg/PoseWithCovariance"](
            pose=self.T["geometry_msgs/msg/Pose"](position=P, orientation=Q),
            covariance=np.zeros(36))
        V = self.T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
        tw = self.T["geometry_msgs/msg/TwistWithCovariance"](
            twist=self.T["geometry_msgs/msg/Twist"](linear=V, angular=V), covariance=np.zeros(36))
        return self.T["nav_msgs/msg/Odometry"](header=self.header(t, "odom"),
                                               child_frame_id="base_link", pose=pose, twist=tw)


SCAN_T = "sensor_msgs/msg/LaserScan"
IMAGE_T = "sensor_msgs/msg/Image"
COMP_T = "sensor_msgs/msg/CompressedImage"
INFO_T = "sensor_msgs/msg/CameraInfo"
TF_T = "tf2_msgs/msg/TFMessage"
ODOM_T = "nav_msgs/msg/Odometry"


def standard_messages(b: BagBuilder, c: BagContent, *, image="raw", depth=True, tf=True,
                      info=True, odom=True, encoding="rgb8",
                      compressed_format="rgb8; png compressed bgr8", codec=".png"):
    """(topic, type, bag time, message) of a bag with everything the reader handles."""
    out = []
    if tf:
        out.append(("/tf_static", TF_T, T0 - 1.0, b.tf([
            b.transform(T0, "base_link", "camera_link", T_BASE_CAMLINK),
            b.transform(T0, "camera_link", "camera_optical", T_CAMLINK_OPT),
            b.transform(T0, "/base_link", "laser", T_BASE_LASER)])))
    for t, r, inten in zip(c.scan_t, c.ranges, c.intensities, strict=True):
        out.append(("/scan", SCAN_T, t + 0.004, b.scan(t, r, inten,
                                                       time_increment=c.time_increment)))
    for i, t in enumerate(c.image_t):
        rgb = c.images[i]
        if image == "raw":
            px = {"rgb8": rgb, "bgr8": rgb[..., ::-1], "mono8": rgb[..., :1]}[encoding]
            out.append(("/camera/color/image_raw", IMAGE_T, t + 0.03,
                        b.image(t, np.ascontiguousarray(px), encoding)))
        else:
            # The payload's channel order is the format's word after 'compressed'.
            payload = rgb if compressed_format.endswith("rgb8") else rgb[..., ::-1]
            ok, buf = cv2.imencode(codec, np.ascontiguousarray(payload))
            assert ok
            out.append(("/camera/color/image_raw/compressed", COMP_T, t + 0.03,
                        b.compressed(t, buf.tobytes(), compressed_format)))
        if info:
            out.append(("/camera/color/camera_info", INFO_T, t + 0.031, b.camera_info(t)))
    if depth:
        for t, d in zip(c.depth_t, c.depth_mm, strict=True):
            out.append(("/camera/aligned_depth_to_color/image_raw", IMAGE_T, t + 0.035,
                        b.image(t, d, "16UC1")))
    if odom:
        for t, (x, y) in zip(c.odom_t, c.odom_xy, strict=True):
            out.append(("/odom", ODOM_T, t + 0.001, b.odom(t, x, y)))
            out.append(("/tf", TF_T, t + 0.001, b.tf([b.transform(
                t, "odom", "base_link", pose_from_xyz_quat(np.array([x, y, 0.0]),
                                                           np.array([0, 0, 0, 1.0])))])))
    return sorted(out, key=lambda m: m[2])


def write_bag(path: Path, fmt: str, messages) -> Path:
    """Write ``messages`` as a ROS 1 bag or a ROS 2 bag (sqlite3 / mcap) at ``path``."""
    b = BagBuilder(fmt == "ros1")
    if fmt == "ros1":
        path = path.with_suffix(".bag")
        with Writer1(path) as w:
            conns = {}
            for topic, msgtype, t, msg in messages:
                if topic not in conns:
                    conns[topic] = w.add_connection(topic, msgtype, typestore=b.ts)
                w.write(conns[topic], ns(t), b.serialize(msg, msgtype))
        return path
    plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
    with Writer2(path, version=9, storage_plugin=plugin) as w:
        conns = {}
        for topic, msgtype, t, msg in messages:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msgtype, typestore=b.ts)
            w.write(conns[topic], ns(t), b.serialize(msg, msgtype))
    return path


def make_bag(tmp_path: Path, fmt: str, content: BagContent | None = None, name="run",
             **kw) -> tuple[Path, BagContent]:
    c = content or make_content()
    b = BagBuilder(fmt == "ros1")
    return write_bag(tmp_path / name, fmt, standard_messages(b, c, **kw)), c


FORMATS = ["ros1", "sqlite3", "mcap"]


# ---------------------------------------------------------------------------- exact round trip


@pytest.mark.parametrize("fmt", FORMATS)
def test_bag_converts_exactly(tmp_path, fmt):
    bag, c = make_bag(tmp_path, fmt)
    rec = read_rosbag(bag)
    result = convert(rec, tmp_path / "seq")
    seq = read_sequence(tmp_path / "seq")

    # scans: stamps and ranges bit for bit, intensities, angles
    assert len(seq.scans) == len(c.scan_t)
    for s, t, r, inten in zip(seq.scans, c.scan_t, c.ranges, c.intensities, strict=True):
        assert s.stamp == ns(t) / 1e9
        assert s.ranges.tobytes() == r.tobytes()
        assert s.intensities.tobytes() == inten.tobytes()
        assert s.angle_min == np.float32(-1.5) and s.angle_increment == np.float32(0.0349)
        assert (s.range_min, s.range_max) == (np.float32(0.1), np.float32(10.0))
    # images bit for bit, stamps exact
    assert len(seq.frames) == len(c.image_t) == result.frames
    for f, t, rgb in zip(seq.frames, c.image_t, c.images, strict=True):
        assert f.stamp == ns(t) / 1e9
        assert np.array_equal(f.image, rgb)
    # registered depth -> reference depth, exact in millimetres
    for i, mm in enumerate(c.depth_mm):
        got = seq.groundtruth.depth(i)
        assert np.array_equal(np.round(got * 1000).astype(np.uint16), mm)
    # intrinsics and distortion
    cam = seq.rig.camera
    assert np.array_equal(cam.K, K) and np.array_equal(cam.dist, D)
    assert cam.size == (W, H)
    # extrinsics from tf_static (through camera_link -> camera_optical)
    np.testing.assert_allclose(seq.rig.T_base_camera, T_BASE_CAMLINK @ T_CAMLINK_OPT,
                               atol=1e-12)
    np.testing.assert_allclose(seq.rig.T_base_laser, T_BASE_LASER, atol=1e-12)
    # odometry
    assert seq.odometry is not None and len(seq.odometry) == len(c.odom_t)
    np.testing.assert_allclose(seq.odometry.positions[:, :2], np.array(c.odom_xy), atol=1e-12)
    assert seq.meta["has_camera"] is True
    assert seq.meta["topics"]["image"] == "/camera/color/image_raw"
    assert result.plan.dropped == {"no_scan": 0, "no_depth": 0}


@pytest.mark.parametrize("fmt, compressed_format", [("ros1", "rgb8; png compressed bgr8"),
                                                    ("mcap", "rgb8; png compressed rgb8")])
def test_compressed_images_and_summary(tmp_path, fmt, compressed_format, caplog):
    bag, c = make_bag(tmp_path, fmt, image="compressed", depth=False,
                      compressed_format=compressed_format)
    with caplog.at_level(logging.INFO, logger="toolkit"):
        rec = read_rosbag(bag)
    table = caplog.text
    assert "/camera/color/image_raw/compressed" in table and "image (rgb8; png" in table
    assert "/scan" in table and "20" in table and "rate Hz" in table
    convert(rec, tmp_path / "seq")
    seq = read_sequence(tmp_path / "seq")
    for f, rgb in zip(seq.frames, c.images, strict=True):
        assert np.array_equal(f.image, rgb)  # png is lossless
    assert seq.groundtruth is None or seq.groundtruth.depth_paths is None


@pytest.mark.parametrize("fmt, compressed_format", [("sqlite3", "bgr8; jpeg compressed bgr8"),
                                                    ("ros1", "rgb8; jpeg compressed rgb8")])
def test_compressed_jpeg_frames_are_stored_as_they_are(tmp_path, fmt, compressed_format):
    """A camera's JPEG became a lossless PNG of its decoded pixels: 7.7x the bag on disk
    and 14 of a frame's 17 ms on a long bag. Where reading the JPEG gives exactly the
    pixels the PNG held, it is stored as it is; a payload in RGB order (decoded, then its
    channels taken as they are) is not what a reader of the file would see: PNG."""
    bag, c = make_bag(tmp_path, fmt, image="compressed", depth=False,
                      compressed_format=compressed_format, codec=".jpg")
    convert(read_rosbag(bag), tmp_path / "seq")
    seq = read_sequence(tmp_path / "seq")
    from rosbags.highlevel import AnyReader

    with AnyReader([bag]) as reader:
        conns = [x for x in reader.connections if x.topic.endswith("/compressed")]
        payloads = [reader.deserialize(raw, con.msgtype).data.tobytes()
                    for con, _, raw in reader.messages(connections=conns)]
    rgb_order = compressed_format.endswith("rgb8")
    assert len(seq.frames) == len(payloads) == len(c.images)
    for f, data in zip(seq.frames, payloads, strict=True):
        decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        want = decoded if rgb_order else decoded[..., ::-1]
        assert np.array_equal(f.image, want)
        assert f.path.suffix == (".png" if rgb_order else ".jpg")
        if not rgb_order:
            assert f.path.read_bytes() == data


def _two_colours() -> np.ndarray:
    """[H, W, 3] RGB: one colour on the left half, another on the right."""
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[:, : W // 2] = (200, 30, 10)
    rgb[:, W // 2:] = (10, 60, 220)
    return rgb


def _mosaic(rgb: np.ndarray, pattern: str) -> np.ndarray:
    """[H, W] Bayer mosaic of ``rgb``; ``pattern`` names the 2x2 block row by row, as ROS."""
    m = np.zeros(rgb.shape[:2], np.uint8)
    for k, (dy, dx) in enumerate([(0, 0), (0, 1), (1, 0), (1, 1)]):
        m[dy::2, dx::2] = rgb[dy::2, dx::2, "rgb".index(pattern[k])]
    return m


# Bilinear demosaicing is exact inside a patch of one colour, 2 pixels from its edges.
INNER = np.ones((H, W), bool)
INNER[:2] = INNER[-2:] = False
INNER[:, :2] = INNER[:, -2:] = False
INNER[:, W // 2 - 2: W // 2 + 2] = False


@pytest.mark.parametrize("fmt, payload", [
    ("rgb8; png compressed bgr8", "bgr"), ("bgr8; png compressed bgr8", "bgr"),
    ("png", "bgr"), ("rgb8; jpeg compressed rgb8", "rgb"), ("bgr8; png compressed rgb8", "rgb"),
    ("rgba8; png compressed rgba8", "rgba"), ("bgra8; png compressed bgra8", "bgra")])
def test_compressed_channel_order_follows_the_format(fmt, payload):
    """image_transport names the payload's channel order after 'compressed': an 'rgb8'
    payload was read as BGR, so every frame was stored with red and blue swapped."""
    rgb = _two_colours()
    alpha = np.full((H, W, 1), 255, np.uint8)
    px = {"rgb": rgb, "bgr": rgb[..., ::-1], "rgba": np.concatenate([rgb, alpha], axis=2),
          "bgra": np.concatenate([rgb[..., ::-1], alpha], axis=2)}[payload]
    # PNG whatever the name says: lossless, so the comparison is exact
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(px))
    assert ok
    got = compressed_to_rgb(BagBuilder(ros1=False).compressed(0.0, buf.tobytes(), fmt))
    assert np.array_equal(got, rgb)


@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
def test_bayer_images_are_demosaiced(pattern):
    """A raw Bayer image was refused; its image_transport republication ('bayer_rggb8; jpeg
    compressed ') was stored as a grey copy of the mosaic. OpenCV names the patterns
    differently from ROS: each is checked against known colours."""
    rgb = _two_colours()
    mosaic = _mosaic(rgb, pattern)
    b = BagBuilder(ros1=True)
    ok, buf = cv2.imencode(".png", mosaic)
    assert ok
    raw = image_to_rgb(b.image(0.0, mosaic, f"bayer_{pattern}8"))
    packed = compressed_to_rgb(b.compressed(0.0, buf.tobytes(),
                                            f"bayer_{pattern}8; png compressed "))
    for got in (raw, packed):
        assert got.shape == (H, W, 3)
        assert np.array_equal(got[INNER], rgb[INNER])


@pytest.mark.parametrize("streams", ["raw+compressed", "compressed", "raw+colour"])
def test_a_bayer_camera_bag(tmp_path, streams, caplog):
    """A Bayer camera's image_raw is demosaiced (lossless, it beats its /compressed), its
    /compressed alone too; a demosaiced stream beside them (image_proc's image_color) wins."""
    c = make_content(n_images=3)
    b = BagBuilder(ros1=True)
    rgb = _two_colours()
    mosaic = _mosaic(rgb, "rggb")
    ok, buf = cv2.imencode(".png", mosaic)
    assert ok
    msgs = [m for m in standard_messages(b, c, depth=False) if m[0] != "/camera/color/image_raw"]
    for t, colour in zip(c.image_t, c.images, strict=True):
        if "raw" in streams:
            msgs.append(("/camera/color/image_raw", IMAGE_T, t + 0.03,
                         b.image(t, mosaic, "bayer_rggb8")))
        msgs.append(("/camera/color/image_raw/compressed", COMP_T, t + 0.03,
                     b.compressed(t, buf.tobytes(), "bayer_rggb8; png compressed ")))
        if "colour" in streams:
            msgs.append(("/camera/color/image_color", IMAGE_T, t + 0.03,
                         b.image(t, colour, "rgb8")))
    bag = write_bag(tmp_path / "bayer", "ros1", sorted(msgs, key=lambda m: m[2]))
    with caplog.at_level(logging.INFO, logger="toolkit"):
        rec = read_rosbag(bag)
    convert(rec, tmp_path / "seq")
    seq = read_sequence(tmp_path / "seq")
    assert len(seq.frames) == 3
    if streams == "raw+colour":
        assert seq.meta["topics"]["image"] == "/camera/color/image_color"
        assert "Bayer mosaic topics (/camera/color/image_raw, /camera/color/image_raw/" \
            "compressed) are passed over" in caplog.text
        for f, colour in zip(seq.frames, c.images, strict=True):
            assert np.array_equal(f.image, colour)
        return
    topic = "/camera/color/image_raw" + ("" if "raw" in streams else "/compressed")
    assert seq.meta["topics"]["image"] == topic
    for f in seq.frames:
        assert np.array_equal(f.image[INNER], rgb[INNER])


@pytest.mark.parametrize("encoding", ["bgr8", "mono8"])
def test_other_encodings(tmp_path, encoding):
    bag, c = make_bag(tmp_path, "sqlite3", depth=False, encoding=encoding)
    convert(read_rosbag(bag), tmp_path / "seq")
    seq = read_sequence(tmp_path / "seq")
    want = c.images[0] if encoding == "bgr8" else np.repeat(c.images[0][..., :1], 3, axis=2)
    assert np.array_equal(seq.frames[0].image, want)


def test_image_row_padding_and_camera_info_fields():
    b = BagBuilder(ros1=False)
    rgb = np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3)
    padded = np.zeros((4, 16), np.uint8)
    padded[:, :15] = rgb.reshape(4, 15)
    msg = b.image(0.0, padded, "rgb8", width=5, height=4, step=16)
    assert np.array_equal(image_to_rgb(msg), rgb)
    cam = camera_info_to_camera(b.camera_info(0.0))
    assert np.array_equal(cam.K, K) and np.array_equal(cam.dist, D)
    rect = camera_info_to_camera(b.camera_info(0.0), rectified=True)
    assert not rect.has_distortion and rect.fx == K[0, 0]



# ---------------------------------------------------------------------------- YUV and 16-bit


def _smooth_red() -> np.ndarray:
    """[H, W, 3] RGB, strongly red (a swapped channel order is off by > 100 levels) and
    smooth (ramps: 4:2:2 chroma and bilinear demosaicing lose next to nothing)."""
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    return np.round(np.stack([180 + 1.5 * x, 30 + y, 15 + 0.5 * (x + y)], axis=2)).astype(
        np.uint8)


def _yuv422(rgb: np.ndarray, order: str) -> np.ndarray:
    """[H, W, 2] packed YUV 4:2:2 of ``rgb`` as a camera sends it: BT.601 video range (the
    inverse of OpenCV's conversion), one U, V pair (the two pixels' mean) per two pixels of
    a row; ``order`` 'uyvy' (ROS yuv422: U0 Y0 V0 Y1) or 'yuyv' (yuv422_yuy2: Y0 U0 Y1 V0)."""
    r, g, b = (rgb[..., k].astype(np.float64) for k in range(3))
    y = 16 + (65.481 * r + 128.553 * g + 24.966 * b) / 255
    u = 128 + (-37.797 * r - 74.203 * g + 112.0 * b) / 255
    v = 128 + (112.0 * r - 93.786 * g - 18.214 * b) / 255

    def q(a: np.ndarray) -> np.ndarray:
        return np.clip(np.round(a), 0, 255).astype(np.uint8)

    y, u, v = q(y), q((u[:, 0::2] + u[:, 1::2]) / 2), q((v[:, 0::2] + v[:, 1::2]) / 2)
    out = np.empty(rgb.shape[:2] + (2,), np.uint8)
    luma, chroma = (1, 0) if order == "uyvy" else (0, 1)
    out[..., luma] = y
    out[:, 0::2, chroma] = u
    out[:, 1::2, chroma] = v
    return out


def _sixteen(a: np.ndarray) -> np.ndarray:
    return a.astype(np.uint16) * np.uint16(257)  # 8-bit v as 16-bit: v * 65535 / 255


# Encoding -> (pixels a driver publishes for the RGB image, the RGB expected back, tolerance
# in levels where it is compared). 16-bit v * 257 comes back as v exactly (cv_bridge's
# 255 / 65535); YUV within what 4:2:2 chroma and 8-bit rounding lose on a smooth image;
# Bayer 16 within bilinear demosaicing's error, away from the image's border.
def _driver_pixels(enc: str, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    alpha = np.full(rgb.shape[:2] + (1,), 255, np.uint8)
    if enc in ("yuv422", "uyvy"):
        return _yuv422(rgb, "uyvy"), rgb, 3
    if enc in ("yuv422_yuy2", "yuyv"):
        return _yuv422(rgb, "yuyv"), rgb, 3
    if enc == "mono16":
        return _sixteen(rgb[..., :1]), np.repeat(rgb[..., :1], 3, axis=2), 0
    if enc.startswith("bayer_"):
        return _sixteen(_mosaic(rgb, enc[6:10]))[..., None], rgb, 1
    order = {"rgb16": rgb, "bgr16": rgb[..., ::-1],
             "rgba16": np.concatenate([rgb, alpha], axis=2),
             "bgra16": np.concatenate([rgb[..., ::-1], alpha], axis=2)}[enc]
    return _sixteen(order), rgb, 0


def _raw_image(b: BagBuilder, t: float, px: np.ndarray, enc: str, *, bigendian=False,
               pad=0):
    """A sensor_msgs/Image of ``px`` ([H, W, C]) as a driver fills it: 16-bit samples in the
    byte order it names, each row followed by ``pad`` bytes of padding (step)."""
    h, w = px.shape[:2]
    if px.dtype == np.uint16:
        px = px.astype(">u2" if bigendian else "<u2")
    rows = np.ascontiguousarray(px).reshape(h, -1).view(np.uint8)  # [H, bytes of a row]
    data = np.concatenate([rows, np.full((h, pad), 0xAB, np.uint8)], axis=1)
    return b.image(t, data, enc, width=w, height=h, step=data.shape[1], bigendian=bigendian)


def _compressed_png(b: BagBuilder, t: float, px: np.ndarray, fmt: str):
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(px))
    assert ok
    return b.compressed(t, buf.tobytes(), fmt)


def _border(n: int) -> np.ndarray:
    """[H, W] mask of the pixels at least ``n`` from the image's border."""
    m = np.zeros((H, W), bool)
    m[n:H - n, n:W - n] = True
    return m


def _images_read_back(tmp_path: Path, topic_msgs: list, name: str) -> tuple[list, dict]:
    """Frames ([H, W, 3] RGB) and meta of a bag whose image topic carries ``topic_msgs``
    ((topic, type, make(b, t)) per image time), read by the toolkit's reader."""
    c = make_content(n_images=2)
    b = BagBuilder(ros1=True)
    msgs = [m for m in standard_messages(b, c, depth=False)
            if m[0] != "/camera/color/image_raw"]
    for t in c.image_t:
        msgs += [(topic, mtype, t + 0.03, make(b, t)) for topic, mtype, make in topic_msgs]
    rec = read_rosbag(write_bag(tmp_path / name, "ros1", sorted(msgs, key=lambda m: m[2])))
    frames = list(rec.load([(i, -1) for i in range(len(rec.frame_stamps))]))
    assert len(frames) == 2
    return [f.image for f in frames], rec.meta


NEW_ENCODINGS = ["yuv422", "uyvy", "yuv422_yuy2", "yuyv", "rgb16", "bgr16", "rgba16",
                 "bgra16", "mono16", "bayer_rggb16", "bayer_bggr16", "bayer_gbrg16",
                 "bayer_grbg16"]


@pytest.mark.parametrize("layout", ["plain", "big-endian, padded rows"])
@pytest.mark.parametrize("enc", NEW_ENCODINGS)
def test_yuv_and_16_bit_images_are_converted_as_cv_bridge_does(tmp_path, enc, layout):
    """usb_cam's yuv422 (UYVY) / yuv422_yuy2 (YUYV) and machine-vision cameras' 16-bit
    images (Bayer 16, mono16, rgb16 ...) were refused as unknown encodings. Each is made
    from a known RGB image as its driver sends it, through a bag and the reader; padded rows
    (step) and big-endian 16-bit samples (is_bigendian) as dc1394 cameras send them."""
    rgb = _smooth_red()
    px, want, tol = _driver_pixels(enc, rgb)
    odd = layout != "plain"
    if odd and px.dtype == np.uint16:
        # v * 257 has equal bytes and reads the same in either byte order: +-100 still
        # rounds to v, and makes the two bytes differ.
        y, x = np.mgrid[0:H, 0:W]
        step = np.where((x + y) % 2, 100, -100)[..., None]
        px = np.clip(px.astype(np.int32) + step, 0, 65535).astype(np.uint16)
    images, meta = _images_read_back(tmp_path, [(
        "/camera/color/image_raw", IMAGE_T,
        lambda b, t: _raw_image(b, t, px, enc, bigendian=odd, pad=6 if odd else 0))], "enc")
    assert meta["topics"]["image"] == "/camera/color/image_raw"
    where = _border(2) if enc.startswith("bayer_") else np.ones((H, W), bool)
    for got in images:
        assert got.shape == (H, W, 3) and got.dtype == np.uint8
        err = np.abs(got.astype(int) - want.astype(int))[where]
        assert err.max() <= tol, (enc, err.max())
    if enc.startswith("bayer_"):  # the border too, as OpenCV's bilinear demosaic fills it
        assert np.abs(images[0].astype(int) - rgb.astype(int)).max() <= 3


def test_16_bit_samples_round_to_8_bits_as_cv_bridge_scales_them():
    """cv_bridge reads a 16-bit image as rgb8 by convertTo(CV_8U, 255 / 65535): rounded,
    not the high byte (129 -> 1, 386 -> 2, where v >> 8 gives 0 and 1)."""
    v = np.array([[0, 128, 129, 385, 386, 32767, 32768, 65535]], np.uint16)
    got = image_to_rgb(BagBuilder(ros1=False).image(0.0, v, "mono16"))
    assert got[..., 0].tolist() == [[0, 0, 1, 1, 2, 127, 128, 255]]
    assert np.array_equal(got[..., 0], got[..., 2])


@pytest.mark.parametrize("enc, fmt", [
    ("bayer_rggb16", "bayer_rggb16; png compressed "),
    ("bayer_gbrg16", "bayer_gbrg16; png compressed "),
    ("rgb16", "rgb16; png compressed bgr16"),
    ("bgra16", "bgra16; png compressed bgr16"),
    ("mono16", "mono16; png compressed ")])
def test_16_bit_png_compressed_images(tmp_path, enc, fmt):
    """image_transport's png codec keeps 16 bits: a Bayer 16 mosaic as it is (demosaiced as
    the raw one), rgb16 / bgra16 as 16-bit BGR ('compressed bgr16'), mono16 as grey. They
    were refused as 'colour images must be 8-bit'."""
    rgb = _smooth_red()
    px, want, tol = _driver_pixels(enc, rgb)
    if enc in ("rgb16", "bgra16"):
        px = _sixteen(rgb[..., ::-1])  # what the publisher's cv_bridge made of it: bgr16
    images, meta = _images_read_back(tmp_path, [(
        "/camera/color/image_raw/compressed", COMP_T,
        lambda b, t: _compressed_png(b, t, px[..., 0] if px.shape[2] == 1 else px, fmt))],
        "png16")
    assert meta["topics"]["image"] == "/camera/color/image_raw/compressed"
    raw = image_to_rgb(_raw_image(BagBuilder(ros1=True), 0.0, _driver_pixels(enc, rgb)[0],
                                  enc))
    where = _border(2) if enc.startswith("bayer_") else np.ones((H, W), bool)
    for got in images:
        assert np.array_equal(got, raw)  # as the raw topic reads
        assert np.abs(got.astype(int) - want.astype(int))[where].max() <= tol


def test_16_bit_compressed_image_of_another_encoding_is_refused():
    """A 16-bit payload is read only under a 16-bit colour encoding: 16UC1 through the
    colour codec is depth, a bare 'png' says nothing of what it holds."""
    b = BagBuilder(ros1=False)
    mm = np.full((H, W), 1234, np.uint16)
    for fmt, says in (("16UC1; png compressed ", "rosbag.topics.depth"), ("png", "mono16")):
        with pytest.raises(BagError, match="decodes to uint16 pixels") as e:
            compressed_to_rgb(_compressed_png(b, 0.0, mm, fmt), "topic /cam")
        assert "/cam" in str(e.value) and "'format'" in str(e.value) and says in str(e.value)


def test_yuv422_of_odd_width_is_refused():
    px = np.zeros((H, W - 1, 2), np.uint8)
    with pytest.raises(BagError, match=r"topic /cam: a yuv422_yuy2 image is 31 pixels wide "
                                       r"\(field 'width'\).*even"):
        image_to_rgb(BagBuilder(ros1=True).image(0.0, px, "yuv422_yuy2"), "topic /cam")


@pytest.mark.parametrize("case", ["yuv beside bgr8", "bayer16 beside rgb16",
                                  "mono16 beside yuyv", "mono8 beside yuyv",
                                  "bayer16 and its png", "depth's /compressed"])
def test_colour_topic_choice_with_yuv_and_16_bit_streams(tmp_path, case, caplog):
    """8-bit colour (a driver's or image_proc's image_color) beats the YUV / 16-bit stream it
    was converted from, colour beats a 16-bit Bayer mosaic as it does an 8-bit one, and a
    grey stream (mono8 or mono16: an infrared camera; a RealSense's infra1 is mono8) is
    passed over; a raw stream beats its /compressed; a depth image through the colour codec
    ('16UC1; png compressed ') is no colour candidate (it made the choice ambiguous)."""
    rgb = _smooth_red()
    raw_t = "/camera/color/image_raw"

    def stream(topic: str, enc: str, fmt: str = ""):
        if enc == "16UC1":  # depth in millimetres
            px = np.full(rgb.shape[:2] + (1,), 1500, np.uint16)
        elif enc == "mono8":
            px = rgb[..., :1]
        else:
            px = rgb[..., ::-1] if enc == "bgr8" else _driver_pixels(enc, rgb)[0]
        if fmt:
            return (topic, COMP_T, lambda b, t: _compressed_png(b, t, px[..., 0], fmt))
        return (topic, IMAGE_T, lambda b, t: _raw_image(b, t, px, enc))

    streams, want, note = {
        "yuv beside bgr8": ([stream(raw_t, "yuv422"),
                             stream("/camera/color/image_color", "bgr8")],
                            "/camera/color/image_color",
                            f"YUV / 16-bit colour topics ({raw_t}) are passed over"),
        "bayer16 beside rgb16": ([stream(raw_t, "bayer_rggb16"),
                                  stream("/camera/color/image_color", "rgb16")],
                                 "/camera/color/image_color",
                                 f"Bayer mosaic topics ({raw_t}) are passed over"),
        "mono16 beside yuyv": ([stream(raw_t, "yuyv"),
                                stream("/camera/infra1/image_rect_raw", "mono16")], raw_t,
                               "mono16 topics (/camera/infra1/image_rect_raw) are passed over"),
        "mono8 beside yuyv": ([stream(raw_t, "yuyv"),
                               stream("/camera/infra1/image_rect_raw", "mono8")], raw_t,
                              "grey topics (/camera/infra1/image_rect_raw) are passed over"),
        "bayer16 and its png": ([stream(raw_t, "bayer_rggb16"),
                                 stream(raw_t + "/compressed", "bayer_rggb16",
                                        "bayer_rggb16; png compressed ")], raw_t, ""),
        "depth's /compressed": ([stream(raw_t, "yuyv"),
                                 stream("/camera/depth/image_rect_raw/compressed", "16UC1",
                                        "16UC1; png compressed ")], raw_t, ""),
    }[case]
    with caplog.at_level(logging.INFO, logger="toolkit"):
        images, meta = _images_read_back(tmp_path, streams, "choice")
    assert meta["topics"]["image"] == want
    assert note in caplog.text
    assert np.abs(images[0].astype(int) - rgb.astype(int))[_border(2)].max() <= 3


def test_lidar_only_bag(tmp_path):
    c = make_content()
    b = BagBuilder(ros1=True)
    msgs = [m for m in standard_messages(b, c, depth=False, info=False)
            if not m[0].startswith("/camera")]
    bag = write_bag(tmp_path / "lidar", "ros1", msgs)
    convert(read_rosbag(bag), tmp_path / "seq")
    seq = read_sequence(tmp_path / "seq")
    assert seq.frames == [] and len(seq.scans) == 20
    assert seq.meta["has_camera"] is False


# ---------------------------------------------------------------------------- sync, decimation


def test_sync_drops_frames_without_partner_and_decimates(tmp_path):
    c = make_content(n_scans=10, n_images=8)  # scans cover [T0, T0 + 0.9]
    bag, _ = make_bag(tmp_path, "sqlite3", content=c)
    rec = read_rosbag(bag)
    res = convert(rec, tmp_path / "a", sync=SyncOptions(tolerance_s=0.05))
    # images at T0 + 0.013 + 0.2 i: those after the last scan (+0.05) have no partner
    assert res.plan.dropped["no_scan"] == 3 and res.frames == 5
    seq = read_sequence(tmp_path / "a")
    assert seq.meta["ingest"]["dropped_no_scan"] == 3
    assert "dropped for lack of a scan within tolerance: 3" in res.summary()

    # No frame with a depth image near enough: an error naming the setting, not an empty
    # sequence (depth is for evaluation; a colour/depth clock offset must not lose frames).
    with pytest.raises(IngestError, match=r"none of the 5 camera frames has a depth image "
                       r"within sync.depth_tolerance_s = 0.001 s .*median.*rosbag.topics.depth"):
        convert(rec, tmp_path / "b", sync=SyncOptions(tolerance_s=0.05, depth_tolerance_s=0.001))
    assert not (tmp_path / "b").exists()

    res = convert(rec, tmp_path / "c", decimate=DecimateOptions(by="time", min_interval_s=0.35))
    assert res.frames == 3 and res.plan.decimated == 2  # keeps 0.013, 0.413, 0.813
    # odometry moves 0.1 m per 0.05 s = 2 m/s: 0.2 s between frames is 0.4 m
    res = convert(rec, tmp_path / "d",
                  decimate=DecimateOptions(by="motion", min_translation_m=0.7,
                                           min_rotation_deg=90))
    assert res.frames == 3


def test_resume_keeps_converted_frames(tmp_path):
    bag, c = make_bag(tmp_path, "mcap")
    rec = read_rosbag(bag)
    out = tmp_path / "seq"

    class Stop(Exception):
        pass

    def stop_after(n):
        def progress(it, total=None, description=""):
            for k, x in enumerate(it):
                if k == n:
                    raise Stop
                yield x
        return progress

    with pytest.raises(Stop):
        convert(rec, out, progress=stop_after(3))
    assert not (out / "meta.yaml").exists()
    assert len(list((out / "camera" / "images").glob("*.png"))) == 3

    decoded = []
    real_load = rec.load

    def counting(pairs):
        decoded.append(len(pairs))
        return real_load(pairs)

    rec.load = counting
    res = convert(rec, out)
    assert decoded == [len(c.image_t) - 3] and res.frames_resumed == 3
    seq = read_sequence(out)
    assert [f.stamp for f in seq.frames] == [ns(t) / 1e9 for t in c.image_t]
    for f, rgb in zip(seq.frames, c.images, strict=True):
        assert np.array_equal(f.image, rgb)


def test_a_new_conversion_replaces_only_the_sequence(tmp_path):
    """Converting again into the folder that holds the bag removed the whole folder, the
    bag and the user's notes with it; an off-plan partial sequence did the same."""
    bag, c = make_bag(tmp_path, "ros1")  # tmp_path / run.bag
    (tmp_path / "notes.txt").write_text("field notes")
    convert(read_rosbag(bag), tmp_path)
    convert(read_rosbag(bag), tmp_path)  # a finished sequence there: replaced
    assert bag.exists() and (tmp_path / "notes.txt").read_text() == "field notes"
    assert len(read_sequence(tmp_path).frames) == len(c.image_t)
    # A partial sequence of more frames than another bag's plan is started afresh.
    out = tmp_path / "out"
    (out / "bags").mkdir(parents=True)
    (out / "notes.txt").write_text("field notes")

    class Stop(Exception):
        pass

    def stop_after_5(it, total=None, description=""):
        for k, x in enumerate(it):
            if k == 5:
                raise Stop
            yield x

    with pytest.raises(Stop):
        convert(read_rosbag(bag), out, progress=stop_after_5)
    short, _ = make_bag(out / "bags", "ros1", make_content(n_images=4))
    convert(read_rosbag(short), out)
    assert short.exists() and (out / "notes.txt").exists()
    assert len(read_sequence(out).frames) == 4


def test_depth_beyond_a_png_is_counted_and_kept_as_npy(tmp_path, caplog):
    """A 16UC1 depth camera reads up to 65 m; a depth PNG holds 13.107 m, and farther
    pixels became invalid without a word."""
    import logging

    c = make_content(n_images=4)
    c.depth_mm = [np.full((H, W), 15000, np.uint16) for _ in c.depth_mm]  # 15 m
    bag, _ = make_bag(tmp_path, "sqlite3", c)
    with caplog.at_level(logging.WARNING):
        res = convert(read_rosbag(bag), tmp_path / "png")
    n = res.frames * H * W
    assert res.metrics()["depth_pixels_beyond_format"] == n
    assert "beyond the 13.107 m" in caplog.text and "depth_format: npy" in caplog.text
    assert f"written as invalid: {n}" in res.summary()
    assert read_sequence(tmp_path / "png").meta["ingest"]["depth_pixels_beyond_format"] == n
    res = convert(read_rosbag(bag), tmp_path / "npy", depth_format="npy")
    assert res.depth_pixels_beyond_format == 0
    assert np.all(read_sequence(tmp_path / "npy").groundtruth.depth(0) == 15.0)


# ---------------------------------------------------------------------------- errors


def test_missing_transform_names_frames_and_fix(tmp_path):
    c = make_content()
    b = BagBuilder(ros1=False)
    msgs = [m for m in standard_messages(b, c) if m[0] != "/tf_static"]
    bag = write_bag(tmp_path / "notf", "sqlite3", msgs)
    with pytest.raises(MissingTransformError) as e:
        read_rosbag(bag)
    msg = str(e.value)
    assert "'base_link'" in msg and "'camera_optical'" in msg and "calibration" in msg
    assert "T_base_camera" in msg and "quat_xyzw" in msg

    # the fix it names works: tf style and matrix style
    calib = tmp_path / "calib.yaml"
    q = [float(v) for v in __import__("toolkit.geometry", fromlist=["x"]).pose_to_xyz_quat(
        T_BASE_CAMLINK @ T_CAMLINK_OPT)[1]]
    calib.write_text(yaml.safe_dump({
        "T_base_camera": {"parent": "base_link", "child": "camera_optical",
                          "xyz": (T_BASE_CAMLINK @ T_CAMLINK_OPT)[:3, 3].tolist(),
                          "quat_xyzw": q},
        "T_base_laser": T_BASE_LASER.tolist()}))
    rec = read_rosbag(bag, RosbagOptions(calibration=str(calib)))
    np.testing.assert_allclose(rec.rig.T_base_camera, T_BASE_CAMLINK @ T_CAMLINK_OPT, atol=1e-9)
    np.testing.assert_allclose(rec.rig.T_base_laser, T_BASE_LASER, atol=1e-12)

    # a rig.yaml written by the toolkit is a calibration file too
    from toolkit.io.sequence import write_rig

    write_rig(tmp_path / "rig.yaml", rec.rig)
    rec2 = read_rosbag(bag, RosbagOptions(calibration=str(tmp_path / "rig.yaml")))
    np.testing.assert_array_equal(rec2.rig.T_base_laser, rec.rig.T_base_laser)
    assert rec2.rig.camera == rec.rig.camera

    # a reversed tf-style entry is caught
    calib.write_text(yaml.safe_dump({
        "T_base_laser": {"parent": "laser", "child": "base_link", "xyz": [0, 0, 0],
                         "quat_xyzw": [0, 0, 0, 1]},
        "T_base_camera": T_BASE_CAMLINK.tolist()}))
    with pytest.raises(BagError, match="reversed"):
        read_rosbag(bag, RosbagOptions(calibration=str(calib)))


@pytest.mark.parametrize("fmt", FORMATS)
def test_truncated_bag_is_named_with_repair_hint(tmp_path, fmt):
    bag, _ = make_bag(tmp_path, fmt)
    target = bag if fmt == "ros1" else next(p for p in bag.iterdir()
                                            if p.suffix in (".db3", ".mcap"))
    data = target.read_bytes()
    target.write_bytes(data[: len(data) // 2])
    with pytest.raises(BagError) as e:
        rec = read_rosbag(bag)
        convert(rec, tmp_path / "seq")
    msg = str(e.value)
    assert str(bag) in msg
    assert {"ros1": "rosbag reindex", "sqlite3": ".recover", "mcap": "mcap recover"}[fmt] in msg


def test_garbage_and_missing_metadata(tmp_path):
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"not a bag at all" * 50)
    with pytest.raises(BagError, match="cannot open"):
        read_rosbag(junk)
    bag, _ = make_bag(tmp_path, "sqlite3")
    (bag / "metadata.yaml").unlink()
    with pytest.raises(BagError, match="ros2 bag reindex"):
        read_rosbag(bag)


def test_a_file_that_is_no_bag_names_the_other_sources(tmp_path):
    """A CARMEN log given to 'source: rosbag' was reported as a damaged ROS 2 sqlite3 bag,
    with a sqlite3 repair recipe; a ROS 2 storage file named alone is still read."""
    log = tmp_path / "intel.log.gz"
    log.write_bytes(b"FLASER 180 1.0 2.0" * 20)
    with pytest.raises(BagError) as e:
        read_rosbag(log)
    msg = str(e.value)
    assert msg.startswith(f"{log}: not a ROS bag") and "'source: carmen'" in msg
    assert "sqlite3" not in msg
    bag, _ = make_bag(tmp_path, "sqlite3")
    (bag / "metadata.yaml").unlink()
    assert len(read_rosbag(next(bag.glob("*.db3"))).scans) == 20


def test_a_folder_that_holds_no_bag_names_the_other_sources(tmp_path):
    """An empty folder, a TUM RGB-D folder or a sequence folder given to 'source: rosbag'
    was a damaged ROS 2 sqlite3 bag ("Expected metadata file ... does not exist") with a
    sqlite3 repair recipe; a bag folder that lost its metadata.yaml keeps that hint."""
    (tmp_path / "empty").mkdir()
    tum = tmp_path / "rgbd_dataset_freiburg1_xyz"
    tum.mkdir()
    (tum / "rgb.txt").write_text("# timestamp filename\n")
    for folder in (tmp_path / "empty", tum):
        with pytest.raises(BagError) as e:
            read_rosbag(folder)
        msg = str(e.value)
        assert msg.startswith(f"{folder}: not a ROS bag") and "'source: tum_rgbd'" in msg, msg
        assert "sqlite3 FILE.db3" not in msg and "no metadata.yaml" in msg, msg


def test_unknown_encoding(tmp_path):
    c = make_content(n_images=2)
    b = BagBuilder(ros1=False)
    msgs = [m for m in standard_messages(b, c, depth=False) if m[0] != "/camera/color/image_raw"]
    # NV21 (4:2:0, a Y plane of H rows and an interleaved VU plane of H / 2): cv_bridge
    # does not read it either.
    msgs += [("/camera/color/image_raw", IMAGE_T, c.image_t[0] + 0.03,
              b.image(c.image_t[0], np.zeros((H * 3 // 2, W), np.uint8), "nv21", height=H))]
    bag = write_bag(tmp_path / "nv21", "sqlite3", sorted(msgs, key=lambda m: m[2]))
    with pytest.raises(BagError) as e:
        read_rosbag(bag)
    msg = str(e.value)
    assert "/camera/color/image_raw" in msg and "'encoding'" in msg and "'nv21'" in msg
    for accepted in ("rgb8", "yuv422", "yuv422_yuy2", "rgb16", "mono16",
                     "bayer_{rggb,bggr,gbrg,grbg}{8,16}", "16UC1"):
        assert accepted in msg
    assert "cv_bridge does not convert" in msg and "rosbag.topics.image" in msg


@pytest.mark.parametrize("fmt", ["ros1", "sqlite3"])
def test_non_monotonic_stamps(tmp_path, fmt):
    c = make_content()
    b = BagBuilder(fmt == "ros1")
    msgs = standard_messages(b, c)
    # scans 7 and 8 recorded in order, but with their header stamps swapped
    at = [i for i, m in enumerate(msgs) if m[0] == "/scan"][7:9]
    (t7, m7), (t8, m8) = [(msgs[i][2], msgs[i][3]) for i in at]
    msgs[at[0]] = ("/scan", SCAN_T, t7, m8)
    msgs[at[1]] = ("/scan", SCAN_T, t8, m7)
    bag = write_bag(tmp_path / "nm", fmt, msgs)
    with pytest.raises(IngestError) as e:
        read_rosbag(bag)
    msg = str(e.value)
    assert "/scan" in msg and "message 8" in msg and "on_non_monotonic: drop" in msg
    rec = read_rosbag(bag, on_non_monotonic="drop")
    assert len(rec.scans) == 19 and rec.dropped["/scan"] == 1
    res = convert(rec, tmp_path / "seq")
    assert res.metrics()["messages_dropped_non_monotonic"] == 1
    # the recording time is monotonic by construction
    assert len(read_rosbag(bag, RosbagOptions(stamps="bag")).scans) == 20


def test_a_dropped_image_with_a_kept_ones_stamp_does_not_replace_it(tmp_path):
    """Image 1 carries image 3's header stamp (a glitch into the future): dropped while
    indexing, it was still found first by that stamp and its pixels written as frame 3."""
    c = make_content()
    b = BagBuilder(ros1=False)
    msgs = standard_messages(b, c, depth=False)
    imgs = [i for i, m in enumerate(msgs) if m[0] == "/camera/color/image_raw"]
    topic, mtype, t, _ = msgs[imgs[1]]
    msgs[imgs[1]] = (topic, mtype, t, b.image(c.image_t[3], c.images[1], "rgb8"))
    rec = read_rosbag(write_bag(tmp_path / "dup", "mcap", msgs), on_non_monotonic="drop")
    assert rec.dropped["/camera/color/image_raw"] == 1
    convert(rec, tmp_path / "seq")
    seq = read_sequence(tmp_path / "seq")
    assert len(seq.frames) == len(c.images) - 1
    for f in seq.frames:
        k = int(np.argmin(np.abs(np.array(c.image_t) - f.stamp)))
        assert np.array_equal(f.image, c.images[k]), k


def test_image_size_differs_from_camera_info(tmp_path):
    c = make_content(n_images=3)
    b = BagBuilder(ros1=True)
    msgs = [m if m[1] != INFO_T else (m[0], m[1], m[2], b.camera_info(c.image_t[0], w=64, h=48))
            for m in standard_messages(b, c)]
    bag = write_bag(tmp_path / "size", "ros1", msgs)
    with pytest.raises(BagError) as e:
        read_rosbag(bag)
    msg = str(e.value)
    assert "32x24" in msg and "64x48" in msg and "/camera/color/camera_info" in msg
    assert "width/height" in msg and "calibration" in msg


def test_ambiguous_topics_are_listed(tmp_path):
    c = make_content(n_images=2)
    b = BagBuilder(ros1=False)
    msgs = standard_messages(b, c)
    msgs += [("/scan_rear", SCAN_T, t + 0.005, b.scan(t, r, i))
             for t, r, i in zip(c.scan_t, c.ranges, c.intensities, strict=True)]
    bag = write_bag(tmp_path / "two", "sqlite3", sorted(msgs, key=lambda m: m[2]))
    # "/scan" is the conventional name and wins
    assert read_rosbag(bag).meta["topics"]["scan"] == "/scan"
    rec = read_rosbag(bag, RosbagOptions(topics={"scan": "/scan_rear"}))
    assert rec.meta["topics"]["scan"] == "/scan_rear"
    with pytest.raises(BagError, match="not in the bag"):
        read_rosbag(bag, RosbagOptions(topics={"scan": "/nope"}))
    shutil.rmtree(bag)


def test_depth_encodings():
    from toolkit.io.rosbag import compressed_to_depth, image_to_depth

    b = BagBuilder(ros1=False)
    m = np.array([[0.0, 1.5], [np.nan, 2.25]], np.float32)
    d = image_to_depth(b.image(0.0, m, "32FC1"))
    assert d.dtype == np.float32 and d.tolist() == [[0.0, 1.5], [0.0, 2.25]]
    mm = np.array([[0, 1234], [65535, 7]], np.uint16)
    ok, png = cv2.imencode(".png", mm)
    header = np.array([0], "<i4").tobytes() + np.array([0.0, 0.0], "<f4").tobytes()
    msg = b.compressed(0.0, header + png.tobytes(), "16UC1; compressedDepth png")
    np.testing.assert_array_equal(compressed_to_depth(msg), mm.astype(np.float32) / 1000)
    with pytest.raises(BagError, match="'format'"):
        compressed_to_depth(b.compressed(0.0, png.tobytes(), "16UC1; compressedDepth rvl"))


def test_ros1_bag_named_otherwise_is_recognised_by_its_header(tmp_path):
    bag, _ = make_bag(tmp_path, "ros1")
    active = bag.with_name("run.bag.active")
    bag.rename(active)  # what 'rosbag record' leaves when killed
    with pytest.raises(BagError, match=r"run.bag.active: a ROS 1 bag named other than \*.bag; "
                       r".*rosbag reindex"):
        read_rosbag(active)
    upper = tmp_path / "RUN.BAG"
    active.rename(upper)
    with pytest.raises(BagError, match=r"rename it \(or link it\) to end in '.bag'"):
        read_rosbag(upper)


# ---------------------------------------------------------------------------- beam timing


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
def test_beam_timing_kept_checked_or_ignored(tmp_path, fmt):
    # 90 beams at 0.5 ms: a 45 ms sweep in a 10 Hz stream is kept, bit for bit.
    c = make_content()
    c.time_increment = 0.0005
    bag, _ = make_bag(tmp_path, fmt, content=c)
    convert(read_rosbag(bag), tmp_path / "seq")
    seq = read_sequence(tmp_path / "seq")
    assert all(s.time_increment == np.float32(0.0005) for s in seq.scans)
    assert seq.scans[0].sweep_s == pytest.approx(89 * 0.0005, rel=1e-6)
    # A whole turn's time per beam (9 s sweeps every 0.1 s) is the driver's error.
    c.time_increment = 0.1
    bag, _ = make_bag(tmp_path, fmt, content=c, name="wrong")
    with pytest.raises(BagError, match="beam_timing: ignore"):
        read_rosbag(bag)
    rec = read_rosbag(bag, RosbagOptions(beam_timing="ignore"))
    assert all(s.time_increment == 0 for s in rec.scans)


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
def test_beam_timing_needs_first_beam_stamps(tmp_path, fmt, caplog):
    c = make_content()
    c.time_increment = 0.0005
    bag, _ = make_bag(tmp_path, fmt, content=c)
    # A driver stamping the end of the sweep: stamps move back by the sweep.
    rec = read_rosbag(bag, RosbagOptions(beam_timing="last_beam"))
    sweep = 89 * np.float32(0.0005)
    for s, t in zip(rec.scans, c.scan_t, strict=True):
        assert s.stamp == pytest.approx(ns(t) / 1e9 - sweep, abs=1e-9)
    # Recording times are no beam's time: the timing is not used.
    with caplog.at_level(logging.WARNING, logger="toolkit"):
        rec = read_rosbag(bag, RosbagOptions(stamps="bag"))
    assert all(s.time_increment == 0 for s in rec.scans)
    assert "not its first beam's time" in caplog.text and rec.meta["beam_timing"] == "ignored"


# ---------------------------------------------------------------------------- what a user's
# bag gets wrong: clocks, another camera's topics, conventions, broken messages


def _shifted(messages, topic: str, dt: float):
    """``messages`` with the header stamps of ``topic`` moved by ``dt`` seconds (a driver on
    another clock); the recording times stay."""
    b = BagBuilder(True)
    out = []
    for top, msgtype, t, msg in messages:
        if top == topic:
            st = msg.header.stamp
            t_new = st.sec + st.nanosec * 1e-9 + dt
            msg.header.stamp = b.T["builtin_interfaces/msg/Time"](
                sec=int(ns(t_new) // 10**9), nanosec=int(ns(t_new) % 10**9))
        out.append((top, msgtype, t, msg))
    return out


def test_drivers_on_different_clocks_are_refused(tmp_path):
    c = make_content()
    b = BagBuilder(True)
    # The lidar stamps in TAI (UTC + 37 s): every frame would be paired with a scan taken
    # 37 s away, or dropped.
    bag = write_bag(tmp_path / "tai", "ros1",
                    _shifted(standard_messages(b, c, odom=False), "/scan", 37.0))
    with pytest.raises(BagError, match=r"different clocks.*\+36\.99.*-0\.030.*rosbag.stamps: bag"):
        read_rosbag(bag)
    rec = read_rosbag(bag, RosbagOptions(stamps="bag"))
    assert len(rec.scans) == len(c.scan_t)
    # A topic that really reached the recorder late may switch the check off.
    rec = read_rosbag(bag, RosbagOptions(max_clock_offset_s=None))
    assert rec.scans[0].stamp == pytest.approx(c.scan_t[0] + 37.0)


def test_odometry_on_another_clock_is_refused(tmp_path):
    c = make_content()
    c.odom_t = [t - T0 + 100.0 for t in c.odom_t]  # seconds since the base's MCU booted
    bag, _ = make_bag(tmp_path, "ros1", c)  # (recorded at those times too)
    with pytest.raises(BagError, match=r"/odom.*covers none of the scans.*odometry: none"):
        read_rosbag(bag)


def test_camera_info_of_another_camera_is_not_used(tmp_path):
    c = make_content()
    b = BagBuilder(True)
    msgs = [m for m in standard_messages(b, c, depth=False) if m[0] != "/camera/color/camera_info"]
    msgs.append(("/camera/depth/camera_info", INFO_T, c.image_t[0],
                 b.camera_info(c.image_t[0], frame="camera_depth_optical_frame")))
    bag = write_bag(tmp_path / "other_info", "ros1", sorted(msgs, key=lambda m: m[2]))
    with pytest.raises(BagError, match=r"no sensor_msgs/CameraInfo.*camera_depth_optical_frame"
                       r".*rosbag.topics.camera_info"):
        read_rosbag(bag)
    rec = read_rosbag(bag, RosbagOptions(topics={"camera_info": "/camera/depth/camera_info"}))
    assert np.array_equal(rec.rig.camera.K, K)


def test_depth_of_another_optical_frame_is_not_reference_depth(tmp_path):
    c = make_content()
    b = BagBuilder(True)
    msgs = standard_messages(b, c, depth=False)
    for t, d in zip(c.depth_t, c.depth_mm, strict=True):  # unregistered: the depth camera's
        msgs.append(("/camera/depth/image_rect_raw", IMAGE_T, t + 0.035,
                     b.image(t, d, "16UC1", frame="camera_depth_optical_frame")))
    bag = write_bag(tmp_path / "unregistered", "ros1", sorted(msgs, key=lambda m: m[2]))
    rec = read_rosbag(bag)
    assert rec.depth_stamps is None and "depth" not in rec.meta["topics"]


def test_empty_scan_messages_are_dropouts(tmp_path):
    c = make_content()
    b = BagBuilder(True)
    msgs = standard_messages(b, c)
    empty = b.scan(c.scan_t[5] + 0.05, np.zeros(0, np.float32), np.zeros(0, np.float32))
    empty.angle_increment = 0.0  # a default-constructed message
    msgs.append(("/scan", SCAN_T, c.scan_t[5] + 0.054, empty))
    bag = write_bag(tmp_path / "dropout", "ros1", sorted(msgs, key=lambda m: m[2]))
    convert(read_rosbag(bag), tmp_path / "seq")
    seq = read_sequence(tmp_path / "seq")
    assert len(seq.scans) == len(c.scan_t) + 1
    assert not seq.scans[6].valid_mask().any()


def test_empty_compressed_image_is_a_bag_error(tmp_path):
    c = make_content()
    b = BagBuilder(True)
    msgs = standard_messages(b, c, image="compressed", depth=False)
    msgs = [(t, m, s, b.compressed(s - 0.03, b"", "rgb8; png compressed bgr8"))
            if t.endswith("/compressed") and abs(s - 0.03 - c.image_t[3]) < 1e-9 else (t, m, s, x)
            for t, m, s, x in msgs]
    bag = write_bag(tmp_path / "empty_image", "ros1", msgs)
    with pytest.raises(BagError, match=r"/compressed.*0 bytes.*does not decode") as e:
        convert(read_rosbag(bag), tmp_path / "seq")
    # ... naming the message, so that it can be cut out of the bag
    assert f"message stamped {ns(c.image_t[3]) / 1e9:.9f} s" in str(e.value)


def test_folder_of_ros1_bags_asks_for_the_list(tmp_path):
    folder = tmp_path / "recording"
    folder.mkdir()
    make_bag(folder, "ros1", name="run_0")
    make_bag(folder, "ros1", name="run_1")
    with pytest.raises(BagError, match=r"(?s)folder of ROS 1 bags.*run_0.bag.*run_1.bag"):
        read_rosbag(folder)


def test_rectified_images_use_the_rectified_frame(tmp_path):
    from scipy.spatial.transform import Rotation

    c = make_content()
    b = BagBuilder(True)
    R = Rotation.from_euler("xyz", [0.01, -0.04, 0.02]).as_matrix()  # X_rect = R @ X_camera
    msgs = []
    for top, msgtype, t, msg in standard_messages(b, c, depth=False):
        if top == "/camera/color/camera_info":
            msg.R = R.reshape(-1)
        msgs.append((top.replace("image_raw", "image_rect"), msgtype, t, msg))
    bag = write_bag(tmp_path / "rect", "ros1", msgs)
    rec = read_rosbag(bag)
    assert rec.meta["rectified_images"] is True
    T_rect = np.eye(4)
    T_rect[:3, :3] = R.T
    np.testing.assert_allclose(rec.rig.T_base_camera, T_BASE_CAMLINK @ T_CAMLINK_OPT @ T_rect,
                               atol=1e-12)
    # The same intrinsics from a calibration YAML: the pixels are still the rectified ones
    # (R was dropped: 2.6 deg off).
    (tmp_path / "calib.yaml").write_text(yaml.safe_dump({"camera": rec.rig.camera.to_dict()}))
    rec2 = read_rosbag(bag, RosbagOptions(calibration=str(tmp_path / "calib.yaml")))
    np.testing.assert_allclose(rec2.rig.T_base_camera, rec.rig.T_base_camera, atol=1e-12)


def test_rect_is_a_word_of_the_topic_name_not_part_of_one(tmp_path):
    """image_color_corrected is a raw stream: its distortion stays (it was read as
    rectified: intrinsics from P, no distortion)."""
    c = make_content()
    b = BagBuilder(ros1=True)
    for name, rectified in (("image_color_corrected", False), ("image_rect_color", True)):
        msgs = [(t.replace("image_raw", name), mt, st, m)
                for t, mt, st, m in standard_messages(b, c, depth=False)]
        rec = read_rosbag(write_bag(tmp_path / name, "ros1", msgs))
        assert bool(rec.meta.get("rectified_images", False)) is rectified, name
        assert bool((rec.rig.camera.dist == 0).all()) is rectified, name


def test_camera_frame_in_the_wrong_convention_is_warned(tmp_path, caplog):
    bag, _ = make_bag(tmp_path, "ros1", depth=False)
    with caplog.at_level(logging.WARNING, logger="toolkit"):
        read_rosbag(bag)
    assert "convention" not in caplog.text
    # camera_link (x forward, pitched down) read as an optical frame looks up and sideways.
    with caplog.at_level(logging.WARNING, logger="toolkit"):
        read_rosbag(bag, RosbagOptions(frames={"camera": "camera_link"}))
    assert "camera_convention: body" in caplog.text
    caplog.clear()
    # An optical frame read as a body frame.
    with caplog.at_level(logging.WARNING, logger="toolkit"):
        read_rosbag(bag, RosbagOptions(frames={"camera_convention": "body"}))
    assert "camera_convention: optical" in caplog.text


def test_a_bag_replayed_at_another_rate_is_one_clock(tmp_path):
    """Recorded again while replaying at another rate (or from a simulator slower than
    real time): header - recording time drifts through the bag for every topic alike, and
    a camera starting later than the lidar must not look like another clock."""
    c = make_content()
    b = BagBuilder(True)
    # Recording time runs 20 times as fast (a 2 s bag becomes 40 s), the camera starts
    # 1.2 s (24 s recorded) after the lidar: the whole-stream medians of the offset differ
    # by 6.7 s, the offsets at the same recording time by nothing.
    msgs = [(top, mt, T0 + 20.0 * (t - T0), m)
            for top, mt, t, m in standard_messages(b, c, odom=False)
            if not (top.startswith("/camera") and t < T0 + 1.2)]
    bag = write_bag(tmp_path / "replayed", "ros1", msgs)
    rec = read_rosbag(bag)
    assert len(rec.scans) == len(c.scan_t) and rec.frame_stamps[0] >= T0 + 1.2


# ---------------------------------------------------------------------------- driver faults


def _replace_scans(b: BagBuilder, c: BagContent, **fields) -> list:
    """standard_messages with every LaserScan's ``fields`` replaced (a per-scan callable
    of the scan number is called)."""
    out, k = [], 0
    for topic, typ, t, m in standard_messages(b, c, depth=False):
        if typ == SCAN_T:
            kw = {f: getattr(m, f) for f in ("header", "angle_min", "angle_max",
                                             "angle_increment", "time_increment", "scan_time",
                                             "range_min", "range_max", "ranges", "intensities")}
            kw.update({f: v(k) if callable(v) else v for f, v in fields.items()})
            m = b.T[SCAN_T](**kw)
            k += 1
        out.append((topic, typ, t, m))
    return out


def test_a_bad_transform_off_the_rigs_path_is_skipped_and_named(tmp_path, caplog):
    """A map -> odom transform with a zero quaternion (a localisation node before its first
    fix) stopped the whole conversion though no lookup needs it."""
    import logging

    c = make_content(n_images=4)
    b = BagBuilder(False)
    msgs = standard_messages(b, c)
    zero = b.tf([b.T["geometry_msgs/msg/TransformStamped"](
        header=b.header(T0 + 0.5, "map"), child_frame_id="odom",
        transform=b.T["geometry_msgs/msg/Transform"](
            translation=b.T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
            rotation=b.T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=0.0)))])
    msgs = sorted([*msgs, ("/tf", TF_T, T0 + 0.5, zero)], key=lambda m: m[2])
    bag = write_bag(tmp_path / "run", "sqlite3", msgs)
    with caplog.at_level(logging.WARNING):
        rec = read_rosbag(bag)
    assert len(rec.scans) == len(c.scan_t)
    assert "no rotation or not finite were skipped map -> odom (1x)" in caplog.text
    # counted beyond the log too, as skipped odometry messages are
    assert rec.tf_skipped == {"map -> odom": 1}
    res = convert(rec, tmp_path / "seq")
    assert res.metrics()["tf_transforms_skipped_invalid"] == 1
    assert "tf transforms skipped as no rigid motion: map -> odom (1x)" in res.summary()
    meta = yaml.safe_load((tmp_path / "seq" / "meta.yaml").read_text())
    assert meta["ingest"]["tf_skipped_invalid"] == {"map -> odom": 1}


def test_driver_faults_name_topic_field_and_fix(tmp_path, caplog):
    import logging

    c = make_content(n_images=4)
    b = BagBuilder(False)
    # range_min >= range_max: converted, then unreadable naming scans.npz.
    bag = write_bag(tmp_path / "limits", "sqlite3",
                    _replace_scans(b, c, range_min=0.0, range_max=0.0))
    with pytest.raises(BagError, match=r"topic /scan: message 0: fields 'range_min' \(0.0\) "
                                       r"and 'range_max' \(0.0\)"):
        read_rosbag(bag)
    # One glitched time_increment: stamped at its first beam, scan 5 went before scan 4
    # and convert failed with "the reader should have caught this".
    bag = write_bag(tmp_path / "sweep", "sqlite3", _replace_scans(
        b, c, time_increment=lambda k: (0.2 if k == 5 else 0.05) / 89))
    with pytest.raises(BagError, match=r"scan 5 .* no longer after scan 4.*beam_timing: "
                                       "ignore"):
        read_rosbag(bag, RosbagOptions(beam_timing="last_beam"))
    # Intensities of another length than the ranges: zeros, now counted.
    c2 = make_content(n_images=4)
    c2.intensities = [i[:-1] if k % 2 else i for k, i in enumerate(c2.intensities)]
    bag = write_bag(tmp_path / "inten", "sqlite3", standard_messages(b, c2, depth=False))
    with caplog.at_level(logging.WARNING):
        read_rosbag(bag)
    assert "10 scans carry intensities of another length" in caplog.text
    # Coefficients past k3 were cut off without a word.
    msg = b.camera_info(0.0, model="plumb_bob", d=[0.1, -0.05, 0, 0, 0.01, 0.3, 0, 0])
    with pytest.raises(BagError, match=r"non-zero past k1 k2 p1 p2 k3 \(D\[5\] = 0.3\)"):
        camera_info_to_camera(msg, "topic /cam/camera_info")


@pytest.mark.parametrize("model, d, expect", [
    # A count OpenCV and image_geometry do not take: 3 values were zero-padded as k1 k2 p1
    # (to other tools they are k1 k2 k3), 6 were cut to 5, both without a word.
    ("plumb_bob", [0.1, -0.05, 0.01], "field 'D' has 3 coefficients [0.1, -0.05, 0.01], but "
     "distortion_model 'plumb_bob' takes 5: k1 k2 p1 p2 k3"),
    ("plumb_bob", [0.1, -0.05, 0, 0, 0.01, 0], "field 'D' has 6 coefficients"),
    ("rational_polynomial", [0.1, -0.05, 0, 0, 0.01, 0, 0],
     "field 'D' has 7 coefficients [0.1, -0.05, 0.0, 0.0, 0.01, 0.0, 0.0], but distortion_model "
     "'rational_polynomial' takes 8: k1 k2 p1 p2 k3 k4 k5 k6"),
    # A NaN past k3 was reported as a coefficient "non-zero past k1 k2 p1 p2 k3".
    ("rational_polynomial", [0.1, -0.05, 0, 0, 0.01, 0, float("nan"), 0],
     "field 'D' holds a non-finite value"),
    ("equidistant", [0.1, -0.05, 0.01, 0.0], "field 'distortion_model' is 'equidistant' (D "
     "holds 4: k1 k2 k3 k4 (fisheye)); only plumb_bob"),
    # What the pinhole model holds: none, k1 k2 p1 p2 (OpenCV's 4), the 5 of plumb_bob, a
    # rational_polynomial or a longer OpenCV D with nothing past k3, zeros of any count.
    ("plumb_bob", [], [0, 0, 0, 0, 0]),
    ("plumb_bob", [0.1, -0.05, 0.001, 0.002], [0.1, -0.05, 0.001, 0.002, 0]),
    ("plumb_bob", [0.1, -0.05, 0.001, 0.002, 0.01], [0.1, -0.05, 0.001, 0.002, 0.01]),
    ("rational_polynomial", [0.1, -0.05, 0.001, 0.002, 0.01, 0, 0, 0],
     [0.1, -0.05, 0.001, 0.002, 0.01]),
    ("plumb_bob", [0.1, -0.05, 0.001, 0.002, 0.01] + [0] * 9, [0.1, -0.05, 0.001, 0.002, 0.01]),
    ("plumb_bob", [0, 0, 0], [0, 0, 0, 0, 0]),
    ("none", [0, 0, 0], [0, 0, 0, 0, 0]),
])
def test_camera_info_distortion_counts_follow_the_model(model, d, expect):
    """CameraInfo's D as ROS's distortion models and OpenCV define it: a count neither
    takes is refused naming the bag and topic, the field and the fix, not padded or cut."""
    msg = BagBuilder(False).camera_info(0.0, model=model, d=d)
    where = "run.db3: topic /cam/camera_info"
    if isinstance(expect, str):
        with pytest.raises(BagError) as err:
            camera_info_to_camera(msg, where)
        text = str(err.value)
        assert text.startswith(f"{where}: ") and expect in text, text
        assert "rosbag.calibration" in text, text
    else:
        cam = camera_info_to_camera(msg, where)
        assert np.allclose(cam.dist, expect, rtol=0, atol=1e-15), cam.dist


@pytest.mark.parametrize("model, d", [
    ("plumb_bob", [0.1, -0.05, 0.001, 0.002, 0.01]),
    ("plumb_bob", [0.1, -0.05, 0.001, 0.002]),
    ("plumb_bob", [0.1, -0.05, 0.001, 0.002, 0.01, 0, 0, 0]),
    ("plumb_bob", [0.1, -0.05, 0.001, 0.002, 0.01, 0.3, 0, 0]),
    ("rational_polynomial", [0.1, -0.05, 0.001, 0.002, 0.01, 0, 0, 0]),
    ("rational_polynomial", [0.1, -0.05, 0.001, 0.002, 0.01, 0, 0, 0.2]),
    ("rational_polynomial", [0.1, -0.05, 0.001, 0.002, 0.01] + [0] * 7),
    ("rational_polynomial", [0.1, -0.05, 0.001, 0.002, 0.01] + [0] * 9),
    ("rational_polynomial", [0.1, -0.05, 0.001, 0.002, 0.01] + [0] * 8 + [0.02]),
    ("equidistant", [0.1, -0.05, 0.01, 0.0]),
])
def test_camera_info_and_camera_mapping_take_the_same_lenses(model, d):
    """A lens the CameraInfo reader takes, a camera file's mapping takes too, with the same
    coefficients, and both refuse the rest naming the field: plumb_bob's 8 with a term past
    k3 were refused by the mapping with a bare "distortion has 8 coefficients", and
    rational_polynomial's 12 and 14 with nothing past k3 as another lens model."""
    from toolkit.camera import PinholeCamera

    msg = BagBuilder(False).camera_info(0.0, model=model, d=d)
    mapping = {"width": W, "height": H, "fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2],
               "cy": K[1, 2], "distortion": d, "distortion_model": model}
    try:
        from_bag = camera_info_to_camera(msg, "run.db3: topic /cam/camera_info").dist
    except BagError as e:
        from_bag = None
        assert "field 'D'" in str(e) or "field 'distortion_model'" in str(e), str(e)
    try:
        from_mapping = PinholeCamera.from_dict(mapping).dist
    except ValueError as e:
        from_mapping = None
        assert "field 'distortion'" in str(e) or "field 'distortion_model'" in str(e), str(e)
    assert (from_bag is None) == (from_mapping is None), (from_bag, from_mapping)
    if from_bag is not None:
        assert from_bag.tolist() == from_mapping.tolist()


def test_a_calibrations_body_frame_for_the_camera_is_refused(tmp_path, caplog):
    """A tf-style T_base_camera whose child is camera_link (x forward) was read as the
    optical frame: the view turned up, without a word."""
    import logging

    c = make_content(n_images=4)
    b = BagBuilder(False)
    bag = write_bag(tmp_path / "run", "sqlite3", standard_messages(b, c, depth=False, tf=False))
    laser = {"parent": "base_link", "child": "laser", "xyz": [0.2, 0, 0.15],
             "quat_xyzw": [0, 0, 0, 1]}
    calib = tmp_path / "calib.yaml"
    calib.write_text(yaml.safe_dump({
        "T_base_camera": {"parent": "base_link", "child": "camera_link", "xyz": [0.1, 0, 0.3],
                          "quat_xyzw": [0, 0, 0, 1]}, "T_base_laser": laser}))
    with pytest.raises(BagError, match="field 'T_base_camera' has child 'camera_link', but "
                                       "the frame it maps from is 'camera_optical'"):
        read_rosbag(bag, RosbagOptions(calibration=str(calib)))
    # Unnamed, the same body-frame matrix is warned about.
    calib.write_text(yaml.safe_dump({"T_base_camera": np.eye(4).tolist(),
                                     "T_base_laser": laser}))
    with caplog.at_level(logging.WARNING):
        read_rosbag(bag, RosbagOptions(calibration=str(calib)))
    assert "is not the optical frame's transform" in caplog.text


def test_a_ros2_bag_is_named_by_its_folder_or_metadata_not_by_one_of_its_files(tmp_path):
    """One storage file of a split recording was converted in part without a word; a
    path to metadata.yaml was read as a damaged sqlite3 file."""
    import yaml

    from toolkit.io.rosbag import BagError, bag_paths

    bag = tmp_path / "run"
    bag.mkdir()
    for name in ("run_0.mcap", "run_1.mcap"):
        (bag / name).write_bytes(b"\x89MCAP0\r\n")
    (bag / "metadata.yaml").write_text(yaml.safe_dump({"rosbag2_bagfile_information": {
        "relative_file_paths": ["run_0.mcap", "run_1.mcap"]}}))
    assert bag_paths(bag) == [bag]
    assert bag_paths(bag / "metadata.yaml") == [bag]
    with pytest.raises(BagError, match="one of the 2 storage files .* give the folder"):
        bag_paths(bag / "run_0.mcap")


@pytest.mark.parametrize("change", ["recalibrated", "calibrated_later"])
def test_camera_info_is_read_as_a_stream(tmp_path, change, caplog):
    """Only the first CameraInfo was read: intrinsics changed mid-bag were applied to every
    frame without a word, and a camera calibrated while recording (K all zero first) was
    refused as uncalibrated."""
    b = BagBuilder(True)
    c = make_content()
    msgs = standard_messages(b, c)
    at = [i for i, m in enumerate(msgs) if m[0] == "/camera/color/camera_info"]
    for i in at[: len(at) // 2]:
        topic, kind, t, info = msgs[i]
        k = np.array(info.K, dtype=np.float64)  # the builder's arrays are shared
        p = np.array(info.P, dtype=np.float64)
        if change == "recalibrated":
            k[0] *= 0.75
        else:
            k[:] = 0.0
            p[:] = 0.0
        msgs[i] = (topic, kind, t, dataclasses.replace(info, K=k, P=p))
    bag = write_bag(tmp_path / "run", "ros1", msgs)
    if change == "recalibrated":
        with pytest.raises(BagError, match="field 'K' changes at stamp .* calibration YAML"):
            read_rosbag(bag)
    else:
        with caplog.at_level(logging.INFO, logger="toolkit"):
            rec = read_rosbag(bag)
        assert np.array_equal(rec.rig.camera.K, K)
        assert f"{len(at) // 2} CameraInfo messages with K all zero (not yet calibrated)" \
            in caplog.text


def test_zero_stamped_camera_info_is_no_error(tmp_path):
    """A static or hand-published camera_info stamps zero. Its stamp only names where the
    intrinsics change, yet it refused the conversion (even with the intrinsics from a
    calibration YAML), and the fix offered, 'stamps: bag', re-timed every scan and image."""
    b = BagBuilder(False)
    c = make_content()
    msgs = [m if m[1] != INFO_T else
            (m[0], m[1], m[2], dataclasses.replace(m[3], header=b.header(0.0, "camera_optical")))
            for m in standard_messages(b, c, depth=False)]
    rec = read_rosbag(write_bag(tmp_path / "zero", "sqlite3", msgs))
    assert np.array_equal(rec.rig.camera.K, K)
    assert [s.stamp for s in rec.scans] == [ns(t) / 1e9 for t in c.scan_t]  # header stamps
    assert np.array_equal(rec.frame_stamps, [ns(t) / 1e9 for t in c.image_t])
    # a change of intrinsics is named by its recording time
    at = [i for i, m in enumerate(msgs) if m[1] == INFO_T][4]
    info = msgs[at][3]
    msgs[at] = (*msgs[at][:3], dataclasses.replace(info, k=np.array(info.k) * 0.5))
    with pytest.raises(BagError, match=r"field 'K' changes at recording time "
                       rf"{msgs[at][2]:.6f} s"):
        read_rosbag(write_bag(tmp_path / "zero_changed", "sqlite3", msgs))


def _with_roi(b: BagBuilder, info, x0: int, y0: int, w: int, h: int):
    roi = b.T["sensor_msgs/msg/RegionOfInterest"](x_offset=x0, y_offset=y0, width=w, height=h,
                                                  do_rectify=False)
    return dataclasses.replace(info, roi=roi)


def test_region_of_interest_camera(tmp_path):
    """REP 104: CameraInfo's width, height, K and P are the full sensor's, its roi the window
    the images hold. The roi was ignored: images of a 16x12 window were refused as being of
    another camera than their own CameraInfo."""
    b = BagBuilder(True)
    info = _with_roi(b, b.camera_info(0.0), 8, 6, 16, 12)
    cam = camera_info_to_camera(info)
    full = camera_info_to_camera(b.camera_info(0.0))
    assert cam.size == (16, 12) and (cam.cx, cam.cy) == (K[0, 2] - 8, K[1, 2] - 6)
    assert (cam.fx, cam.fy) == (K[0, 0], K[1, 1]) and np.array_equal(cam.dist, D)
    # a point seen at sensor pixel (u, v) is at (u - 8, v - 6) in the window
    pts = np.array([[0.1, -0.05, 2.0], [-0.2, 0.1, 3.0]])  # [N, 3]
    np.testing.assert_allclose(cam.project(pts)[0], full.project(pts)[0] - [8, 6], atol=1e-12)
    rect = camera_info_to_camera(info, rectified=True)
    assert rect.size == (16, 12) and (rect.cx, rect.cy) == (K[0, 2] - 8, K[1, 2] - 6)
    with pytest.raises(BagError, match=r"field 'roi' \(x_offset 20, .* 32x24 sensor"):
        camera_info_to_camera(_with_roi(b, b.camera_info(0.0), 20, 6, 16, 12))

    # end to end: the window's images, the stream's CameraInfo
    c = make_content(n_images=3)
    for i, rgb in enumerate(c.images):
        c.images[i] = np.ascontiguousarray(rgb[6:18, 8:24])
    msgs = [m if m[1] != INFO_T else (*m[:3], _with_roi(b, m[3], 8, 6, 16, 12))
            for m in standard_messages(b, c, depth=False)]
    convert(read_rosbag(write_bag(tmp_path / "roi", "ros1", msgs)), tmp_path / "seq")
    seq = read_sequence(tmp_path / "seq")
    assert seq.rig.camera == cam
    for f, rgb in zip(seq.frames, c.images, strict=True):
        assert np.array_equal(f.image, rgb)
    # the window moving while recording changes the intrinsics
    at = [i for i, m in enumerate(msgs) if m[1] == INFO_T][1]
    msgs[at] = (*msgs[at][:3], _with_roi(b, msgs[at][3], 9, 6, 16, 12))
    with pytest.raises(BagError, match="field 'roi' changes at stamp"):
        read_rosbag(write_bag(tmp_path / "roi_moved", "ros1", msgs))
    # full-sensor images under a ROI CameraInfo: the size check names the roi
    msgs = [m if m[1] != INFO_T else (*m[:3], _with_roi(b, m[3], 8, 6, 16, 12))
            for m in standard_messages(b, make_content(n_images=2), depth=False)]
    with pytest.raises(BagError, match=r"is 32x24 but the CameraInfo .* says 16x12 \(fields "
                       r"roi.width/roi.height\)"):
        read_rosbag(write_bag(tmp_path / "roi_full", "ros1", msgs))


def test_non_finite_poses_and_intrinsics_are_named_at_ingest(tmp_path, caplog):
    """NaN where drivers emit it: odometry before its estimator's first fix went into
    odometry.tum and the next stage refused the finished sequence (naming that file, not
    the bag); a NaN tf translation on the laser's mount stopped the conversion with a bare
    "T_base_laser must be a finite 4x4 matrix"; a NaN in CameraInfo K was reported as a
    recalibration while recording, and a transposed K as a bare ValueError."""
    c = make_content(n_images=4)
    b = BagBuilder(False)
    # odometry: the first three poses NaN - left out, named (they refused the whole
    # topic until too few poses remain: test_odometry_with_too_few_poses_is_refused...)
    c.odom_xy[:3] = [(np.nan, np.nan)] * 3
    bag = write_bag(tmp_path / "odom", "sqlite3", standard_messages(b, c, depth=False))
    with caplog.at_level(logging.WARNING):
        rec = read_rosbag(bag)
    assert len(rec.odometry) == 37 and np.isfinite(rec.odometry.poses).all()
    assert re.search(r"topic /odom: 3 of 40 messages left out as no pose \(message 0 of the "
                     r"topic: field 'pose.pose.position'", caplog.text)

    # tf: a NaN translation is skipped like a zero quaternion, and named where needed
    c = make_content(n_images=4)
    T_nan = T_BASE_LASER.copy()
    T_nan[0, 3] = np.nan
    msgs = [m for m in standard_messages(b, c, depth=False) if m[0] != "/tf_static"]
    static = ("/tf_static", TF_T, T0 - 1.0, b.tf([
        b.transform(T0, "base_link", "camera_link", T_BASE_CAMLINK),
        b.transform(T0, "camera_link", "camera_optical", T_CAMLINK_OPT),
        b.transform(T0, "base_link", "laser", T_nan)]))
    with pytest.raises(MissingTransformError, match=r"'laser'.*not finite.*base_link -> "
                                                    r"laser \(1x\)"):
        read_rosbag(write_bag(tmp_path / "tf", "sqlite3", [static, *msgs]))
    off_path = ("/tf", TF_T, T0 + 0.5, b.tf([b.transform(T0 + 0.5, "map", "odom", T_nan)]))
    good = standard_messages(b, c, depth=False)
    with caplog.at_level(logging.WARNING):
        rec = read_rosbag(write_bag(tmp_path / "tf_off", "sqlite3", [*good, off_path]))
    np.testing.assert_allclose(rec.rig.T_base_laser, T_BASE_LASER, atol=1e-12)
    assert "map -> odom (1x)" in caplog.text

    # CameraInfo: a NaN in K in every message is no recalibration; the field is named
    msgs = standard_messages(b, c, depth=False)
    K_nan = K.copy()
    K_nan[0, 2] = np.nan
    msgs = [m if m[1] != INFO_T else (*m[:3], dataclasses.replace(m[3], k=K_nan.reshape(-1)))
            for m in msgs]
    with pytest.raises(BagError, match=r"topic /camera/color/camera_info: field 'K' holds a "
                                       r"non-finite value.*calibration YAML") as e:
        read_rosbag(write_bag(tmp_path / "info", "sqlite3", msgs))
    assert "changes" not in str(e.value)
    # a transposed K (cx, cy in the bottom row): BagError naming topic and field
    info = b.camera_info(0.0)
    bad = dataclasses.replace(info, k=K.T.reshape(-1).copy())
    with pytest.raises(BagError, match=r"topic /cam/camera_info: field 'K': K must be"):
        camera_info_to_camera(bad, "topic /cam/camera_info")


@pytest.mark.parametrize("fmt", FORMATS)
def test_an_empty_bag_says_so(tmp_path, fmt):
    """An empty recording was reported as 'Topics in the bag: ' followed by nothing; a bag
    without scans lists its topics with their message counts."""
    with pytest.raises(BagError, match=r"holds no messages.*record again"):
        read_rosbag(write_bag(tmp_path / "empty", fmt, []))
    b = BagBuilder(fmt == "ros1")
    c = make_content(n_images=2)
    msgs = [m for m in standard_messages(b, c, depth=False) if m[0] != "/scan"]
    bag = write_bag(tmp_path / "silent", fmt, msgs)
    with pytest.raises(BagError, match=r"no sensor_msgs/LaserScan topic with messages.*"
                                       r"/odom \(nav_msgs/msg/Odometry, \d+ messages\)"):
        read_rosbag(bag)


def test_conflicting_mounts_in_tf_are_named(tmp_path, caplog):
    """Two static publishers of one edge (a URDF's base_link -> camera_link beside a
    calibration launch's), or a /tf value beside a static one: the latest static value was
    used for every frame without a word."""
    c = make_content(n_images=4)
    b = BagBuilder(True)
    T_other = pose_from_xyz_quat(np.array([0.25, 0.05, 0.4]), np.array([0, 0, 0, 1.0]))
    T_laser_tf = T_BASE_LASER.copy()
    T_laser_tf[2, 3] += 0.03
    msgs = standard_messages(b, c, depth=False)  # tf_static: the rig at T0 - 1
    extra = [
        # the same static set again (a latched republish): no conflict
        ("/tf_static", TF_T, T0 - 0.5, b.tf([
            b.transform(T0, "base_link", "camera_link", T_BASE_CAMLINK),
            b.transform(T0, "camera_link", "camera_optical", T_CAMLINK_OPT)])),
        # /tf gives the laser's mount 3 cm higher than tf_static
        ("/tf", TF_T, T0 + 0.2, b.tf([b.transform(T0 + 0.2, "base_link", "laser",
                                                  T_laser_tf)]))]
    with caplog.at_level(logging.WARNING, logger="toolkit"):
        rec = read_rosbag(write_bag(tmp_path / "laser", "ros1", [*msgs, *extra]))
    np.testing.assert_allclose(rec.rig.T_base_laser, T_BASE_LASER, atol=1e-12)  # static
    assert "laser mount's edge base_link -> laser (on /tf, /tf_static" in caplog.text
    assert "camera mount" not in caplog.text

    # a second static publisher of base_link -> camera_link, later in the bag: used, named
    caplog.clear()
    later = ("/tf_static", TF_T, T0 + 0.3, b.tf([
        b.transform(T0, "base_link", "camera_link", T_other)]))
    with caplog.at_level(logging.WARNING, logger="toolkit"):
        rec = read_rosbag(write_bag(tmp_path / "camera", "ros1", [*msgs, later]))
    np.testing.assert_allclose(rec.rig.T_base_camera, T_other @ T_CAMLINK_OPT, atol=1e-12)
    assert "camera mount's edge base_link -> camera_link (on /tf_static; used: xyz " \
        "[0.25, 0.05, 0.4]" in caplog.text and "T_base_camera in a calibration" in caplog.text
    assert "laser mount" not in caplog.text

    # a calibration file's transform overrides the bag's: no conflict
    caplog.clear()
    calib = tmp_path / "calib.yaml"
    calib.write_text(yaml.safe_dump({"transforms": [{
        "parent": "base_link", "child": "laser", "xyz": [0.0, 0.0, 0.3],
        "quat_xyzw": [0.0, 0.0, 0.0, 1.0]}]}))
    with caplog.at_level(logging.WARNING, logger="toolkit"):
        rec = read_rosbag(write_bag(tmp_path / "calibrated", "ros1", msgs),
                          RosbagOptions(calibration=str(calib)))
    assert rec.rig.T_base_laser[2, 3] == 0.3 and "mount's edge" not in caplog.text


# ---------------------------------------------------------------------------- long recordings


def test_index_pass_builds_no_matrix_per_moving_tf_or_odometry_message(tmp_path, monkeypatch,
                                                                         caplog):
    """A long bag's /tf (odom -> base_link at 50-100 Hz) and odometry built a 4x4 matrix
    per message through scipy - most of the index pass (2.3 of 5 min's 2.5 s, on every run
    and every resume) - and kept each odometry pose as its own [4, 4] array (~340 bytes a
    message). A moving edge keeps its first value only, so later values are now checked,
    not built, and the odometry is made into matrices at once. An invalid value on the
    moving edge is still counted."""
    import toolkit.io.rosbag as rosbag_module

    c = make_content(n_scans=30, n_images=4)
    b = BagBuilder(False)
    zero = b.tf([b.T["geometry_msgs/msg/TransformStamped"](
        header=b.header(T0 + 2.02, "odom"), child_frame_id="base_link",
        transform=b.T["geometry_msgs/msg/Transform"](
            translation=b.T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
            rotation=b.T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=0.0)))])
    msgs = sorted([*standard_messages(b, c, depth=False), ("/tf", TF_T, T0 + 2.02, zero)],
                  key=lambda m: m[2])
    bag = write_bag(tmp_path / "run", "sqlite3", msgs)
    n_moving = sum(m[0] == "/tf" for m in msgs)
    assert n_moving == len(c.odom_t) + 1 == 61

    built = []
    real = rosbag_module.pose_from_xyz_quat

    def counting(xyz, quat):
        built.append(np.shape(xyz))
        return real(xyz, quat)

    monkeypatch.setattr(rosbag_module, "pose_from_xyz_quat", counting)
    with caplog.at_level(logging.WARNING):
        rec = read_rosbag(bag)
    # 3 static mounts, the /tf edge's first value and the one that shows it moves, one
    # batch of odometry (it was 3 + 61 + 60)
    assert len(built) == 6, built
    assert (len(c.odom_t), 3) in built
    np.testing.assert_array_equal(rec.odometry.poses[:, :2, 3], np.array(c.odom_xy))
    np.testing.assert_allclose(rec.odometry.stamps, np.array(c.odom_t), rtol=0, atol=1e-6)
    assert "were skipped odom -> base_link (1x)" in caplog.text


def test_index_pass_compares_repeated_camera_info_cheaply(tmp_path, monkeypatch):
    """Every CameraInfo (15-30 Hz for the whole recording) remade the first one's fields
    and ran six np.allclose against it: 0.25 ms a message, half the rest of the index
    pass. Identical messages are now told apart by exact comparison; a changed one is still
    found (test_camera_info_is_read_as_a_stream)."""
    import toolkit.io.rosbag as rosbag_module

    bag, c = make_bag(tmp_path, "sqlite3", make_content(n_images=20), depth=False)
    calls = []
    real = rosbag_module.np.allclose

    def counting(*a, **kw):
        calls.append(1)
        return real(*a, **kw)

    monkeypatch.setattr(rosbag_module.np, "allclose", counting)
    read_rosbag(bag)
    assert len(c.image_t) == 20
    assert len(calls) < 5, len(calls)  # it was 6 for each CameraInfo after the first: 114


# ---------------------------------------------------------------------------- bad odometry


def _odometry_with_bad(b: BagBuilder, c: BagContent, bad: set[int], how: str) -> list:
    """``standard_messages`` with odometry messages ``bad`` (indices) made no pose: a zero
    quaternion (a driver before its first fix) or a NaN position (a glitch)."""
    msgs, k = [], 0
    for m in standard_messages(b, c, depth=False):
        if m[0] == "/odom":
            if k in bad:
                msg = m[3]
                if how == "zero_quaternion":
                    msg.pose.pose.orientation = b.T["geometry_msgs/msg/Quaternion"](
                        x=0.0, y=0.0, z=0.0, w=0.0)
                else:
                    msg.pose.pose.position = b.T["geometry_msgs/msg/Point"](
                        x=np.nan, y=0.0, z=0.0)
            k += 1
        msgs.append(m)
    return msgs


@pytest.mark.parametrize("how", ["zero_quaternion", "nan_position"])
def test_one_bad_odometry_message_is_left_out_not_the_topic(tmp_path, caplog, how):
    """One message of 50 that is no pose refused the whole odometry topic (and so the
    bag); it is left out, counted, and its stamp named."""
    c = make_content(n_scans=25, n_images=2)  # 50 odometry messages at 20 Hz
    b = BagBuilder(False)
    bag = write_bag(tmp_path / "odom", "sqlite3", _odometry_with_bad(b, c, {17}, how))
    with caplog.at_level(logging.WARNING):
        rec = read_rosbag(bag)
    assert len(rec.odometry) == 49
    expected_t = np.delete(np.asarray(c.odom_t), 17)
    np.testing.assert_allclose(rec.odometry.stamps, expected_t, atol=1e-9)
    np.testing.assert_allclose(rec.odometry.poses[:, 0, 3],
                               np.delete(np.asarray(c.odom_xy)[:, 0], 17), atol=1e-12)
    assert rec.skipped["/odom"]["count"] == 1 and rec.skipped["/odom"]["of"] == 50
    assert rec.skipped["/odom"]["first_stamps_s"] == [round(c.odom_t[17], 6)]
    assert rec.skipped["/odom"]["gaps_not_interpolated"] == 0
    assert rec.skipped["/odom"]["longest_gap_s"] == pytest.approx(0.1, abs=1e-6)
    field = "orientation" if how == "zero_quaternion" else "position"
    assert (f"topic /odom: 1 of 50 messages left out as no pose (message 17 of the topic: "
            f"field 'pose.pose.{field}'") in caplog.text
    assert f"{c.odom_t[17]:.6f}" in caplog.text and "is interpolated across" in caplog.text
    # the count reaches the conversion's metrics, summary and meta.yaml
    res = convert(rec, tmp_path / "seq")
    assert res.metrics()["messages_skipped_invalid"] == 1
    assert "odometry messages left out as no pose on /odom: 1 of 50" in res.summary()
    meta = yaml.safe_load((tmp_path / "seq" / "meta.yaml").read_text())
    assert meta["ingest"]["skipped_invalid"]["/odom"]["count"] == 1
    assert len(read_sequence(tmp_path / "seq").odometry) == 49


def test_odometry_with_too_few_poses_is_refused_naming_topic_count_and_fix(tmp_path):
    c = make_content(n_scans=25, n_images=2)
    b = BagBuilder(False)
    bag = write_bag(tmp_path / "all", "sqlite3",
                    _odometry_with_bad(b, c, set(range(50)), "zero_quaternion"))
    with pytest.raises(IngestError, match=r"topic /odom: 50 of 50 messages are no pose "
                                          r"\(message 0 of the topic: field "
                                          r"'pose.pose.orientation'.*only 0 remain.*Fix: "
                                          r"leave the odometry out \(rosbag.topics.odometry: "
                                          r"none"):
        read_rosbag(bag)
    # under half left: refused too; half left: kept
    bag = write_bag(tmp_path / "most", "sqlite3",
                    _odometry_with_bad(b, c, set(range(26)), "nan_position"))
    with pytest.raises(IngestError, match=r"26 of 50 messages are no pose.*only 24 remain"):
        read_rosbag(bag)
    bag = write_bag(tmp_path / "half", "sqlite3",
                    _odometry_with_bad(b, c, set(range(25)), "nan_position"))
    rec = read_rosbag(bag)
    assert len(rec.odometry) == 25 and rec.skipped["/odom"]["count"] == 25
    # the driver's first 25 messages: nothing to interpolate across, the span is shorter
    assert rec.skipped["/odom"]["longest_gap_s"] == 0.0


def test_a_long_run_of_bad_odometry_is_not_interpolated_across(tmp_path, caplog):
    """Skipped messages leave a gap: the SLAM's odometry prior must not draw a straight
    line across a long one (Trajectory.covers) - and the ingest says which it is."""
    from toolkit.slam2d.pipeline import odometry_at

    c = make_content(n_scans=40, n_images=2)  # 80 odometry messages, 0.05 s apart
    b = BagBuilder(False)
    bad = set(range(30, 55))  # 25 messages: a 1.3 s gap, over the 1 s bridged
    bag = write_bag(tmp_path / "gap", "sqlite3", _odometry_with_bad(b, c, bad, "nan_position"))
    with caplog.at_level(logging.WARNING):
        rec = read_rosbag(bag)
    r = rec.skipped["/odom"]
    assert r["count"] == 25 and r["gaps_not_interpolated"] == 1
    assert r["longest_gap_s"] == pytest.approx(c.odom_t[55] - c.odom_t[29], abs=1e-6)
    assert "1 gaps longer than the 1.00 s the odometry is interpolated across" in caplog.text
    assert "matched without odometry" in caplog.text
    # downstream: no odometry pose inside the gap, poses either side of it
    t = np.array([c.odom_t[29] - 0.01, c.odom_t[40], c.odom_t[55] + 0.01])
    at = odometry_at(rec.odometry, t)
    assert at[0] is not None and at[1] is None and at[2] is not None

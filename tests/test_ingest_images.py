"""Raw camera frames through the ingest writer: lossless PNGs, the same bytes with or without
the writer's encoding threads, and an interrupted threaded conversion resumed to the same
folder."""

from __future__ import annotations

import hashlib
import logging
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from test_ingest_rosbag import (
    COMP_T,
    IMAGE_T,
    INFO_T,
    SCAN_T,
    T0,
    T_BASE_CAMLINK,
    T_BASE_LASER,
    T_CAMLINK_OPT,
    TF_T,
    BagBuilder,
    write_bag,
)

from toolkit.camera import PinholeCamera
from toolkit.ingest.convert import convert
from toolkit.io.rosbag import read_rosbag
from toolkit.io.sequence import JOURNAL_NAME, SequenceWriter, _write_rgb, read_sequence
from toolkit.sensors import Rig, load_rgb

W, H = 64, 48


def camera_frames(n: int, seed: int = 0) -> list[np.ndarray]:
    """[H, W, 3] uint8 frames: flat blocks (long runs) beside sensor-like noise."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        img = np.clip(rng.normal(120, 40, (H, W, 3)), 0, 255).astype(np.uint8)
        img[: H // 2, : W // 2] = (10 * i % 256, 200, 30)  # a flat block, as a wall
        img[-1, -1] = (255, 0, 255)
        out.append(img)
    return out


def raw_image_bag(tmp_path: Path, encoding: str, frames: list[np.ndarray],
                  message=None) -> Path:
    """A ROS 2 bag of raw Image frames at 15 Hz (in ``encoding``) with scans, CameraInfo
    and the rig in tf_static; ``message(b, t, frame)``: another camera message
    (topic, type, message) for each frame."""
    b = BagBuilder(ros1=False)
    msgs = [("/tf_static", TF_T, T0 - 1.0, b.tf([
        b.transform(T0, "base_link", "camera_link", T_BASE_CAMLINK),
        b.transform(T0, "camera_link", "camera_optical", T_CAMLINK_OPT),
        b.transform(T0, "base_link", "laser", T_BASE_LASER)]))]
    for i in range(int(len(frames) / 1.5) + 2):
        t = T0 + 0.1 * i
        msgs.append(("/scan", SCAN_T, t + 0.004,
                     b.scan(t, np.full(90, 2.0, np.float32), np.zeros(90, np.float32))))
    for i, rgb in enumerate(frames):
        t = T0 + 0.02 + i / 15.0
        if message is not None:
            topic, msgtype, msg = message(b, t, rgb)
            msgs.append((topic, msgtype, t + 0.03, msg))
        else:
            px = {"rgb8": rgb, "bgr8": rgb[..., ::-1], "mono8": rgb[..., 1:2]}[encoding]
            msgs.append(("/camera/image_raw", IMAGE_T, t + 0.03,
                         b.image(t, np.ascontiguousarray(px), encoding)))
        msgs.append(("/camera/camera_info", INFO_T, t + 0.031, b.camera_info(t, w=W, h=H)))
    return write_bag(tmp_path / f"bag_{encoding}", "sqlite3", sorted(msgs, key=lambda m: m[2]))


def digests(root: Path) -> dict[str, str]:
    """SHA-256 of every file of a sequence folder, by relative path."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "mono8"])
def test_raw_frames_round_trip_exactly_and_threads_write_the_same_bytes(tmp_path, encoding):
    frames = camera_frames(21)
    rec = read_rosbag(raw_image_bag(tmp_path, encoding, frames))
    convert(rec, tmp_path / "serial", workers=0)
    res = convert(rec, tmp_path / "threads", workers=3)
    assert res.frames == len(frames)
    seq = read_sequence(tmp_path / "threads")
    for f, rgb in zip(seq.frames, frames, strict=True):
        assert f.path.suffix == ".png"
        want = np.repeat(rgb[..., 1:2], 3, axis=2) if encoding == "mono8" else rgb
        assert np.array_equal(f.image, want)
    assert digests(tmp_path / "threads") == digests(tmp_path / "serial")


def test_png_frames_are_lossless_on_noise_flat_areas_and_extremes(tmp_path):
    rng = np.random.default_rng(3)
    cases = {"noise": rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
             "flat": np.full((H, W, 3), 77, np.uint8),
             "extremes": np.where(rng.random((H, W, 1)) < 0.5, 0, 255).astype(np.uint8)
             .repeat(3, axis=2)}
    # Grey (R = G = B, encoded with the grey frames' settings) but for one row the
    # writer's sample of rows skips: still exact.
    grey = rng.integers(0, 256, (H, W, 1), dtype=np.uint8).repeat(3, axis=2)
    grey[1] = rng.integers(0, 256, (W, 3), dtype=np.uint8)
    cases["grey but one row"] = grey
    for name, img in cases.items():
        _write_rgb(tmp_path / f"{name}.png", img)
        assert np.array_equal(load_rgb(tmp_path / f"{name}.png"), img), name


class Interrupt(Exception):
    pass


def test_an_interrupted_threaded_conversion_resumes_to_the_same_folder(tmp_path):
    frames = camera_frames(30, seed=1)
    rec = read_rosbag(raw_image_bag(tmp_path, "rgb8", frames))
    convert(rec, tmp_path / "whole", workers=0)

    real_load = rec.load

    def load_then_stop(pairs):
        for k, fd in enumerate(real_load(pairs)):
            if k == 17:
                raise Interrupt  # Ctrl-C while frames are in flight
            yield fd

    rec.load = load_then_stop
    with pytest.raises(Interrupt):
        convert(rec, tmp_path / "cut", workers=3)
    # Every frame handed over before the interrupt landed and was journaled, in order.
    journal = (tmp_path / "cut" / JOURNAL_NAME).read_text().splitlines()
    assert len(journal) == 17
    assert sorted(p.name for p in (tmp_path / "cut/camera/images").iterdir()) == \
        [f"{i:06d}.png" for i in range(17)]

    rec.load = real_load
    res = convert(rec, tmp_path / "cut", workers=3)
    assert res.frames_resumed == 17 and res.frames == 30
    assert digests(tmp_path / "cut") == digests(tmp_path / "whole")


def test_a_failed_frame_write_in_a_thread_is_raised_and_not_journaled(tmp_path, monkeypatch):
    import toolkit.io.sequence as sequence

    rig = Rig(PinholeCamera.from_fov(W, H, 60.0))
    real = sequence._write_rgb

    def full_disk(path, image):
        if path.name == "000004.png":
            raise OSError(28, "No space left on device")
        real(path, image)

    monkeypatch.setattr(sequence, "_write_rgb", full_disk)
    w = SequenceWriter(tmp_path / "s", rig, workers=2)
    with pytest.raises(OSError, match="No space"):
        for k, img in enumerate(camera_frames(12)):
            w.add_frame(float(k), img)
        w.flush()
    w.discard()
    rows = (tmp_path / "s" / JOURNAL_NAME).read_text().splitlines()
    assert len(rows) == 4  # the frames before the failed one, never one after it
    monkeypatch.setattr(sequence, "_write_rgb", real)
    w = SequenceWriter(tmp_path / "s", rig, resume=True, workers=2)
    assert w.resumed_frames == 4
    assert not (tmp_path / "s/camera/images/000005.png").exists()


# ---------------------------------------------------------------------------- 16-bit frames


def grey16_frames(n: int, top: int, seed: int = 0) -> list[np.ndarray]:
    """[H, W] uint16 frames with samples in 0..top (top itself in each)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        v = rng.integers(0, top + 1, (H, W), dtype=np.uint16)
        v[0, 0] = top
        out.append(v)
    return out


@pytest.mark.parametrize("encoding", ["mono16", "bayer_rggb16"])
def test_16bit_jpeg_payloads_are_counted_and_warned_about_as_clipped(tmp_path, caplog,
                                                                      encoding):
    """image_transport's JPEG codec hands a mono16 / Bayer 16 image to OpenCV's JPEG encoder
    unscaled, which saturates every sample above 255 (compressed_publisher.cpp: only colour
    encodings are converted to bgr8 first). The frames were stored as min(v, 255), mostly
    white, without a word; the bag holds nothing more, so they are kept as the payload
    holds them, counted and warned about."""
    grey = grey16_frames(9, 40000)
    payloads = []

    def jpeg_of(b, t, rgb):
        v = grey.pop(0)
        ok, buf = cv2.imencode(".jpg", v, [cv2.IMWRITE_JPEG_QUALITY, 100])  # as the codec
        assert ok
        payloads.append(buf.tobytes())
        return ("/camera/image_raw/compressed", COMP_T,
                b.compressed(t, buf.tobytes(), f"{encoding}; jpeg compressed "))

    bag = raw_image_bag(tmp_path, encoding, camera_frames(9), message=jpeg_of)
    with caplog.at_level(logging.WARNING):
        res = convert(read_rosbag(bag), tmp_path / "seq")
    assert res.frames == 9 and res.metrics()["frames_16bit_clipped"] == 9
    assert res.metrics()["frames_16bit_scaled"] == 0
    assert "clipped" in res.summary()
    assert "JPEG codec clipped" in caplog.text and "png transport" in caplog.text
    meta = yaml.safe_load((tmp_path / "seq" / "meta.yaml").read_text())
    assert meta["ingest"]["frames_16bit_clipped"] == 9
    # stored as the payload decodes: the 8-bit samples (a grey payload: replicated)
    seq = read_sequence(tmp_path / "seq")
    first = cv2.imdecode(np.frombuffer(payloads[0], np.uint8), cv2.IMREAD_UNCHANGED)
    assert first.dtype == np.uint8 and (first >= 250).mean() > 0.95  # saturated: white
    if encoding == "mono16":
        assert np.array_equal(seq.frames[0].image, np.repeat(first[..., None], 3, axis=2))


def test_16bit_frames_are_scaled_exactly_and_counted(tmp_path, caplog):
    grey = grey16_frames(9, 65535, seed=2)
    truth = [g.copy() for g in grey]

    def mono16(b, t, rgb):
        return "/camera/image_raw", IMAGE_T, b.image(t, grey.pop(0), "mono16")

    bag = raw_image_bag(tmp_path, "mono16", camera_frames(9), message=mono16)
    with caplog.at_level(logging.WARNING):
        res = convert(read_rosbag(bag), tmp_path / "seq", workers=2)
    m = res.metrics()
    assert (m["frames_16bit_scaled"], m["frames_16bit_clipped"]) == (9, 0)
    assert res.peak_16bit == 65535 and "near black" not in caplog.text
    seq = read_sequence(tmp_path / "seq")
    for f, v in zip(seq.frames, truth, strict=True):
        want = np.round(v.astype(np.float64) * 255 / 65535).astype(np.uint8)
        assert np.array_equal(f.image, np.repeat(want[..., None], 3, axis=2))


def test_12bit_data_in_16bit_frames_is_warned_about_as_near_black(tmp_path, caplog):
    """A machine-vision camera's 12-bit data in mono16 samples (0..4095), scaled as cv_bridge
    scales 16 bits, is stored as 0..16 of 255; the log says so, with the brightest sample."""
    grey = grey16_frames(6, 4095, seed=4)

    def mono16(b, t, rgb):
        return "/camera/image_raw", IMAGE_T, b.image(t, grey.pop(0), "mono16")

    bag = raw_image_bag(tmp_path, "mono16", camera_frames(6), message=mono16)
    with caplog.at_level(logging.WARNING):
        res = convert(read_rosbag(bag), tmp_path / "seq")
    assert res.peak_16bit == 4095 and res.frames_16bit_scaled == 6
    assert "brightest sample of the 6 16-bit frames is 4095 of 65535" in caplog.text
    assert "at most 16 of 255" in caplog.text and "12-bit data" in caplog.text
    meta = yaml.safe_load((tmp_path / "seq" / "meta.yaml").read_text())
    assert meta["ingest"]["brightest_16bit_sample"] == 4095


def test_a_resumed_writer_removes_the_temporaries_of_writes_a_kill_cut_short(tmp_path):
    """A SIGKILL mid-write leaves the hidden temporary of each frame in flight (one per
    encoding thread) beside the frames; a resumed conversion through the Python API kept
    them (only the recipe runner swept them, after the stage)."""
    rig = Rig(PinholeCamera.from_fov(W, H, 60.0))
    w = SequenceWriter(tmp_path / "s", rig)
    for k, img in enumerate(camera_frames(3)):
        w.add_frame(float(k + 1), img)
    w._journal.close()  # killed: no close()
    images = tmp_path / "s/camera/images"
    for name in (".000003.4242.0badc0de.tmp.png", ".000004.4242.deadbeef.tmp.png"):
        (images / name).write_bytes(b"half a png")
    w = SequenceWriter(tmp_path / "s", rig, resume=True)
    assert w.resumed_frames == 3
    assert sorted(p.name for p in images.iterdir()) == [f"{i:06d}.png" for i in range(3)]


@pytest.mark.parametrize("fmt, clipped", [
    ("mono16; jpeg compressed ", True), ("bayer_gbrg16; jpeg compressed ", True),
    ("rgb16; jpeg compressed bgr8", False),  # the codec scaled it to bgr8 first
    ("mono16; png compressed ", False),  # png keeps 16 bits
    ("mono8; jpeg compressed ", False), ("jpeg", False), ("rgb8; jpeg compressed bgr8", False)])
def test_which_compressed_formats_hold_clipped_16bit_samples(fmt, clipped):
    from toolkit.io.rosbag import jpeg_of_16bit

    assert jpeg_of_16bit(fmt) is clipped

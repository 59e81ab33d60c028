"""Raw camera frames through the ingest writer: lossless PNGs, the same bytes with or without
the writer's encoding threads, and an interrupted threaded conversion resumed to the same
folder."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
from test_ingest_rosbag import (
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


def raw_image_bag(tmp_path: Path, encoding: str, frames: list[np.ndarray]) -> Path:
    """A ROS 2 bag of raw Image frames at 15 Hz (in ``encoding``) with scans, CameraInfo
    and the rig in tf_static."""
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

"""Sequence folder: exact round trip and errors that name the file and field."""

from pathlib import Path

import numpy as np
import pytest
import yaml

from toolkit.camera import PinholeCamera
from toolkit.geometry import Trajectory, se2_to_se3, se3
from toolkit.ingest.sync import match_nearest
from toolkit.io.depth import read_depth, write_depth
from toolkit.io.sequence import (
    SequenceFormatError,
    SequenceWriter,
    image_header,
    read_sequence,
    write_sequence,
)
from toolkit.io.tum import read_tum, write_tum
from toolkit.sensors import LaserScan, Rig, Sequence

W, H = 32, 24


def make_rig() -> Rig:
    cam = PinholeCamera(W, H, 30.0, 31.0, 15.5, 11.5, [0.01, -0.002, 0.0, 0.0, 0.0])
    R_base_optical = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=float)
    return Rig(cam, se3(R_base_optical, [0.1, 0.0, 0.4]), se3(np.eye(3), [0.05, 0, 0.2]))


def write_small(root: Path, n_frames: int = 4, n_scans: int = 6, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    w = SequenceWriter(root, make_rig(), name="tiny", depth_format="npy")
    images, depths, masks = [], [], []
    for i in range(n_frames):
        img = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        d = rng.uniform(0.5, 10, (H, W)).astype(np.float32)
        d[0, 0] = 0.0
        m = rng.random((H, W)) > 0.8
        w.add_frame(0.1 * i + 0.013, img, d, m)
        images.append(img)
        depths.append(d)
        masks.append(m)
    scans = []
    for k in range(n_scans):
        r = rng.uniform(0.2, 10, 90).astype(np.float32)
        r[3] = np.inf
        r[5] = np.nan
        s = LaserScan(0.1 * k, r, -np.pi / 2, -np.pi / 89, 0.12, 12.0)
        dyn = rng.random(90) > 0.9
        w.add_scan(s, dyn)
        scans.append((s, dyn))
    stamps = np.arange(10) * 0.05
    poses = np.stack([se2_to_se3(0.1 * i, 0.02 * i, 0.01 * i) for i in range(10)])
    w.groundtruth_poses = Trajectory(stamps, poses, "world", "base_link")
    w.odometry = Trajectory(stamps, poses @ se2_to_se3(0.01, 0, 0.001), "odom", "base_link")
    w.add_heldout(0.5, se3(np.eye(3), [1.0, 2.0, 0.4]), images[0], depths[0])
    w.close()
    return {"images": images, "depths": depths, "masks": masks, "scans": scans, "poses": poses}


def test_round_trip_is_exact(tmp_path):
    truth = write_small(tmp_path / "a")
    seq = read_sequence(tmp_path / "a")
    assert seq.name == "tiny"
    assert len(seq.frames) == 4 and len(seq.scans) == 6
    for i, f in enumerate(seq.frames):
        assert np.array_equal(f.image, truth["images"][i])
        assert np.array_equal(seq.groundtruth.depth(i), truth["depths"][i])
        assert np.array_equal(seq.groundtruth.mask(i), truth["masks"][i])
    for s, (s0, _dyn) in zip(seq.scans, truth["scans"], strict=True):
        assert np.array_equal(s.ranges, s0.ranges, equal_nan=True)
        assert (s.stamp, s.angle_min, s.angle_increment) == (s0.stamp, s0.angle_min,
                                                             s0.angle_increment)
    assert np.array_equal(seq.groundtruth.scan_dynamic, np.stack([d for _, d in truth["scans"]]))
    assert np.array_equal(seq.groundtruth.poses_base.poses.round(12), truth["poses"].round(12))
    assert seq.rig.camera == make_rig().camera
    assert np.array_equal(seq.rig.T_base_camera, make_rig().T_base_camera)
    assert seq.groundtruth.heldout is not None and len(seq.groundtruth.heldout.image_paths) == 1

    # Writing what was read and reading it again changes nothing.
    write_sequence(seq, tmp_path / "b", depth_format="npy")
    seq2 = read_sequence(tmp_path / "b")
    for a, b in zip(seq.frames, seq2.frames, strict=True):
        assert a.stamp == b.stamp and np.array_equal(a.image, b.image)
    for i in range(4):
        assert np.array_equal(seq.groundtruth.depth(i), seq2.groundtruth.depth(i))
    # Poses pass through quaternions in TUM files: equal to float64 rounding.
    assert np.max(np.abs(seq.odometry.poses - seq2.odometry.poses)) < 1e-15
    assert np.array_equal(seq.groundtruth.poses_base.stamps, seq2.groundtruth.poses_base.stamps)


def test_time_indexed_access(tmp_path):
    write_small(tmp_path / "a")
    seq = read_sequence(tmp_path / "a")
    assert seq.frame_index_at(0.12) == 1  # frames at 0.013, 0.113, 0.213, ...
    assert seq.scan_at(0.26).stamp == pytest.approx(0.3)
    assert [s.stamp for s in seq.scans_between(0.1, 0.3)] == pytest.approx([0.1, 0.2])
    # Images load lazily: a frame holds a path, not pixels.
    assert seq.frames[0]._image is None and seq.frames[0].path.exists()


def test_laser_scan_points_drop_invalid_and_follow_negative_increment():
    r = np.array([1.0, np.inf, 2.0, 0.05, np.nan, 3.0], np.float32)
    s = LaserScan(0.0, r, np.pi / 2, -np.pi / 2, 0.1, 10.0)
    p = s.points()
    # Beams at 90, 0, -90, -180, -270, -360 degrees; valid: 0, 2, 5.
    assert np.allclose(p, [[0, 1], [0, -2], [3, 0]], atol=1e-6)
    assert s.valid_mask().tolist() == [True, False, True, False, False, True]


def test_zero_ranges_are_no_return_and_degrees_are_refused() -> None:
    """Many drivers write "no return" as 0: with range_min 0 it was a point at the laser,
    which projected into the image set the lidar scale (127 of 220 pairs, scale 0.63 for
    2.5, flagged ok). Angles in degrees gave SLAM 16 m off without a word."""
    s = LaserScan(0.0, np.array([0.0, 1.0, -1.0, 2.0], np.float32), -0.1, 0.05)
    assert s.valid_mask().tolist() == [False, True, False, True]
    assert len(s.points()) == 2
    with pytest.raises(ValueError, match="radians"):
        LaserScan(0.0, np.ones(181, np.float32), -90.0, 1.0)
    with pytest.raises(ValueError, match="radians"):
        LaserScan(0.0, np.ones(3, np.float32), -135.0, 0.25)
    LaserScan(0.0, np.ones(361, np.float32), -np.pi, 2 * np.pi / 360)  # a full turn: fine


def test_depth_png_round_trip(tmp_path):
    d = (np.arange(12, dtype=np.float32).reshape(3, 4) * 1.2345).astype(np.float32)
    d[0, 0] = np.nan
    write_depth(tmp_path / "d.png", d)
    once = read_depth(tmp_path / "d.png")
    # NaN and depths beyond the format's 13.1 m become invalid (0), never a wrong value.
    assert once[0, 0] == 0 and once[2, 3] == 0
    ok = np.isfinite(d) & (d < 13.1)
    assert np.max(np.abs(once[ok] - d[ok])) <= 0.5 / 5000 + 1e-6
    write_depth(tmp_path / "e.png", once)
    assert np.array_equal(read_depth(tmp_path / "e.png"), once)


def test_depth_png_keeps_a_positive_depth_below_half_its_quantum_valid(tmp_path: Path) -> None:
    q = 1 / 5000  # m, one PNG unit
    d = np.array([[1e-30, 1e-6, 0.49 * q, 0.51 * q, 0.0, -1e-6]], np.float32)  # [1, 6]
    assert write_depth(tmp_path / "d.png", d) == 0
    back = read_depth(tmp_path / "d.png")
    np.testing.assert_allclose(back, [[q, q, q, q, 0.0, 0.0]], rtol=1e-6)


def test_missing_rig_is_named(tmp_path):
    write_small(tmp_path / "a")
    (tmp_path / "a" / "rig.yaml").unlink()
    with pytest.raises(SequenceFormatError, match=r"rig\.yaml.*not found"):
        read_sequence(tmp_path / "a")


@pytest.mark.parametrize("given", ["run", "run/simulate"])
def test_a_run_or_stage_folder_points_to_the_sequence_in_it(tmp_path, given):
    # What a user passes after reading "runs/quickstart/...": the run or the stage folder.
    write_small(tmp_path / "run" / "simulate" / "sequence")
    with pytest.raises(SequenceFormatError,
                       match=r"not a sequence folder.*give .*run/simulate/sequence"):
        read_sequence(tmp_path / given)


def test_rig_missing_field_is_named(tmp_path):
    write_small(tmp_path / "a")
    p = tmp_path / "a" / "rig.yaml"
    d = yaml.safe_load(p.read_text())
    del d["T_base_laser"]
    p.write_text(yaml.safe_dump(d))
    with pytest.raises(SequenceFormatError, match="T_base_laser"):
        read_sequence(tmp_path / "a")


def test_image_count_mismatch(tmp_path):
    write_small(tmp_path / "a")
    (tmp_path / "a" / "camera" / "images" / "000002.png").unlink()
    with pytest.raises(SequenceFormatError, match=r"frames\.csv.*'image'.*does not exist"):
        read_sequence(tmp_path / "a")
    write_small(tmp_path / "b")
    extra = tmp_path / "b" / "camera" / "images" / "000099.png"
    extra.write_bytes((tmp_path / "b" / "camera" / "images" / "000000.png").read_bytes())
    with pytest.raises(SequenceFormatError, match=r"lists 4 images but .* holds 5 \(not "
                                                  r"listed: 000099.png\)"):
        read_sequence(tmp_path / "b")
    # Files that are no images (Windows' Thumbs.db) made a valid folder unreadable.
    extra.unlink()
    (extra.parent / "Thumbs.db").write_bytes(b"\0" * 64)
    (extra.parent / "desktop.ini").write_text("[.ShellClassInfo]\n")
    assert len(read_sequence(tmp_path / "b").frames) == 4


def test_nan_pose(tmp_path):
    write_small(tmp_path / "a")
    p = tmp_path / "a" / "groundtruth" / "poses_base.tum"
    lines = p.read_text().splitlines()
    parts = lines[5].split()
    parts[2] = "nan"
    lines[5] = " ".join(parts)
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"poses_base\.tum:6: .*non-finite"):
        read_sequence(tmp_path / "a")


def test_non_monotonic_stamps(tmp_path):
    write_small(tmp_path / "a")
    p = tmp_path / "a" / "camera" / "frames.csv"
    lines = p.read_text().splitlines()
    f2, f3 = lines[3].split(","), lines[4].split(",")
    f2[1], f3[1] = f3[1], f2[1]
    lines[3], lines[4] = ",".join(f2), ",".join(f3)
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(SequenceFormatError, match=r"frames\.csv:5: field 'stamp' not strictly"):
        read_sequence(tmp_path / "a")
    # Scans too.
    write_small(tmp_path / "b")
    sp = tmp_path / "b" / "scans.npz"
    with np.load(sp) as z:
        data = {k: z[k] for k in z.files}
    data["stamps"][3] = data["stamps"][1]
    np.savez(sp, **data)
    with pytest.raises(SequenceFormatError, match=r"scans\.npz.*'stamps' not strictly increasing"):
        read_sequence(tmp_path / "b")


def test_image_size_disagreeing_with_rig(tmp_path):
    write_small(tmp_path / "a")
    p = tmp_path / "a" / "rig.yaml"
    d = yaml.safe_load(p.read_text())
    d["camera"]["width"] = 64
    p.write_text(yaml.safe_dump(d))
    with pytest.raises(SequenceFormatError, match="32x24 but .*rig.yaml"):
        read_sequence(tmp_path / "a")


@pytest.mark.parametrize("kind", ["depth", "mask"])
def test_ground_truth_of_another_size_is_refused_on_reading(tmp_path: Path, kind: str) -> None:
    """It failed deep in fuse (an index error on the labels) after the stages before it."""
    import cv2

    write_small(tmp_path / "a")
    if kind == "depth":
        np.save(tmp_path / "a" / "groundtruth" / "depth" / "000000.npy",
                np.ones((H // 2, W // 2), np.float32))
    else:
        cv2.imwrite(str(tmp_path / "a" / "groundtruth" / "masks" / "000000.png"),
                    np.zeros((H, W * 2), np.uint8))
    size = "16x12" if kind == "depth" else "64x24"
    with pytest.raises(SequenceFormatError, match=f"000000.*ground-truth {kind} is {size} but "
                       "the images are 32x24"):
        read_sequence(tmp_path / "a")


def test_tum_file_round_trip_and_header(tmp_path):
    traj = Trajectory(np.array([1.0, 2.0]), np.stack([np.eye(4), se2_to_se3(1, 2, 0.3)]),
                      "world", "camera")
    write_tum(tmp_path / "t.tum", traj)
    back = read_tum(tmp_path / "t.tum")
    assert (back.frame, back.child) == ("world", "camera")
    assert np.allclose(back.poses, traj.poses, atol=1e-15)
    # Any frame names come back, underscores and all (REP 105's map read as world, and
    # its camera poses as base_link ones, defeated the camera-vs-base check).
    for frame, child in (("map", "camera"), ("map", "base_footprint"), ("odom", "imu_link")):
        write_tum(tmp_path / "t.tum", Trajectory(traj.stamps, traj.poses, frame, child))
        back = read_tum(tmp_path / "t.tum")
        assert (back.frame, back.child) == (frame, child)


def test_writing_over_an_earlier_sequence_leaves_none_of_it(tmp_path: Path) -> None:
    """A new sequence written into the folder of an older one (simulate() twice into one
    folder): the older's held-out views and extra images must not outlive it."""
    root = tmp_path / "seq"
    w = SequenceWriter(root, make_rig(), name="old", depth_format="npy")
    for i in range(5):
        w.add_frame(0.1 * i, np.zeros((H, W, 3), np.uint8), np.ones((H, W), np.float32))
    w.add_heldout(0.05, np.eye(4), np.zeros((H, W, 3), np.uint8), np.ones((H, W), np.float32))
    w.close()
    assert read_sequence(root).groundtruth.heldout is not None
    w = SequenceWriter(root, make_rig(), name="new")
    for i in range(2):
        w.add_frame(0.1 * i, np.zeros((H, W, 3), np.uint8))
    w.close()
    seq = read_sequence(root)
    assert len(seq.frames) == 2 and seq.groundtruth is None
    assert len(list((root / "camera" / "images").iterdir())) == 2
    # A folder that holds such names but is no sequence is not emptied.
    other = tmp_path / "mine"
    (other / "camera").mkdir(parents=True)
    with pytest.raises(SequenceFormatError, match="no sequence folder"):
        SequenceWriter(other, make_rig())
    assert (other / "camera").is_dir()


def test_lookups_far_outside_the_recording_are_errors(tmp_path: Path) -> None:
    write_small(tmp_path / "s")
    seq = read_sequence(tmp_path / "s")
    t0 = seq.time_span[0]
    assert seq.scan_index_at(t0 + 0.21) == 2 and seq.frame_index_at(t0 + 1.2) == 3
    with pytest.raises(ValueError, match="outside the recording"):
        seq.scan_at(-1e9)  # seconds into the recording given as a stamp
    # Nearest within a tolerance: the last scan is "nearest" to a time well past it.
    assert seq.scan_at(t0 + 0.21, max_dt=0.05).stamp == pytest.approx(0.2)
    with pytest.raises(LookupError, match="nothing within 0.05 s"):
        seq.scan_at(seq.scan_stamps[-1] + 0.3, max_dt=0.05)
    with pytest.raises(LookupError, match="nothing within"):
        seq.frame_at(t0 + 1.2, max_dt=0.1)


def test_scans_between_refuses_nan_limits() -> None:
    scans = [LaserScan(t, np.ones(3), 0.0, 0.1) for t in (1.0, 2.0, 3.0)]
    seq = Sequence(rig=None, frames=[], scans=scans)  # type: ignore[arg-type]
    assert [s.stamp for s in seq.scans_between(1.5, 3.0)] == [2.0]
    for t0, t1 in ((float("nan"), 3.0), (1.0, float("nan")), (np.nan, np.nan)):
        with pytest.raises(ValueError, match="not a time"):
            seq.scans_between(t0, t1)


def test_scan_at_midway_takes_the_earlier_and_the_first_of_equal_stamps() -> None:
    stamps = (1.0, 2.0, 2.0, 3.0, 3.0)
    scans = [LaserScan(t, np.ones(3), 0.0, 0.1) for t in stamps]
    seq = Sequence(rig=None, frames=[], scans=scans)  # type: ignore[arg-type]
    assert seq.scan_index_at(1.5) == 0  # midway: the earlier
    assert seq.scan_index_at(2.5) == 1  # midway, the earlier stamp twice: the first of them
    assert seq.scan_index_at(2.0) == 1 and seq.scan_index_at(3.4) == 3
    assert seq.scan_at(2.5) is scans[1]
    # The same picks as the ingest's nearest matching.
    q = np.array([1.5, 2.5, 2.0, 3.4])
    assert match_nearest(q, np.array(stamps), np.inf).tolist() == [0, 1, 1, 3]


def test_formats_round_trip_what_they_hold(tmp_path: Path) -> None:
    """A scan without intensities beside scans with them read back as zeros; a copy lost
    the exposure gains and meta.yaml's own keys; a scan_dynamic.npz of another beam count
    was taken; JPEG frames could not be copied."""
    import cv2

    write_small(tmp_path / "a")
    seq = read_sequence(tmp_path / "a")
    scans = seq.scans
    scans[0] = LaserScan(scans[0].stamp, scans[0].ranges, scans[0].angle_min,
                         scans[0].angle_increment, scans[0].range_min, scans[0].range_max,
                         np.arange(90, dtype=np.float32))
    w = SequenceWriter(tmp_path / "b", make_rig(), name="b")
    w.add_frame(0.0, np.zeros((H, W, 3), np.uint8))
    for s in scans[:3]:
        w.add_scan(s)
    w.close()
    back = read_sequence(tmp_path / "b").scans
    assert np.array_equal(back[0].intensities, np.arange(90)) and back[1].intensities is None
    # The simulator's gains and meta survive a copy.
    (tmp_path / "a" / "groundtruth" / "exposure_gain.csv").write_text(
        "index,stamp,gain\n" + "".join(f"{k},{f.stamp!r},{1 + 0.1 * k}\n"
                                       for k, f in enumerate(seq.frames)))
    meta = yaml.safe_load((tmp_path / "a" / "meta.yaml").read_text())
    (tmp_path / "a" / "meta.yaml").write_text(yaml.safe_dump({**meta, "simulator": {"seed": 3}}))
    write_sequence(read_sequence(tmp_path / "a"), tmp_path / "c")
    copy = read_sequence(tmp_path / "c")
    assert np.allclose(copy.groundtruth.exposure_gain, [1.0, 1.1, 1.2, 1.3])
    assert copy.meta["simulator"] == {"seed": 3}
    # A dynamic-beam file of the wrong width is refused, naming it.
    np.savez(tmp_path / "a" / "groundtruth" / "scan_dynamic.npz", dynamic=np.zeros((6, 7), bool))
    with pytest.raises(SequenceFormatError, match=r"scan_dynamic.npz: 'dynamic' is \[6, 7\] for "
                                                  r"6 scans of 90 beams"):
        read_sequence(tmp_path / "a")
    # JPEG frames are read (and stored as they are: test_jpeg_frames_are_kept_as_they_are).
    jpg = tmp_path / "f.jpg"
    cv2.imwrite(str(jpg), np.full((H, W, 3), 128, np.uint8))
    w = SequenceWriter(tmp_path / "d", make_rig(), name="d")
    w.add_frame(0.0, None, image_path=jpg)  # type: ignore[arg-type]
    w.close()
    assert read_sequence(tmp_path / "d").frames[0].image.shape == (H, W, 3)


def test_trajectory_headers_naming_other_frames_are_refused(tmp_path: Path) -> None:
    """odometry.tum / poses_base.tum hold base poses; a header saying camera, laser or
    inverted poses was overridden and the poses read as base ones (camera ground truth
    scored ATE against the camera's lever-arm path)."""
    root = tmp_path / "a"
    truth = write_small(root)
    gt_path, odo_path = root / "groundtruth" / "poses_base.tum", root / "odometry.tum"
    stamps = np.arange(10) * 0.05
    cases = [
        (gt_path, Trajectory(stamps, truth["poses"], "world", "camera"),
         r"poses_base.tum: its header says the poses are T_world_camera.*"
         r"T_world_camera @ inv\(T_base_camera\)"),
        (odo_path, Trajectory(stamps, truth["poses"], "base_link", "odom"),
         r"odometry.tum: its header says the poses are T_base_link_odom.*invert every pose"),
        (odo_path, Trajectory(stamps, truth["poses"], "odom", "laser"),
         r"odometry.tum: .*T_odom_laser @ inv\(T_base_laser\)"),
    ]
    for path, traj, match in cases:
        original = path.read_bytes()
        write_tum(path, traj)
        with pytest.raises(SequenceFormatError, match=match):
            read_sequence(root)
        path.write_bytes(original)
    # REP 105's other names for the same frames, and a file without a header, still read.
    write_tum(gt_path, Trajectory(stamps, truth["poses"], "map", "base_footprint"))
    odo_path.write_text("".join(line + "\n" for line in odo_path.read_text().splitlines()
                                if not line.startswith("#")))
    seq = read_sequence(root)
    assert (seq.groundtruth.poses_base.frame, seq.groundtruth.poses_base.child) == (
        "world", "base_link")
    assert (seq.odometry.frame, seq.odometry.child) == ("odom", "base_link")
    assert np.allclose(seq.groundtruth.poses_base.poses, truth["poses"], atol=1e-12)


def test_stamps_in_other_units_or_clocks_are_refused(tmp_path: Path) -> None:
    """Unix nanoseconds (what ROS 2 and most drivers log) were read as seconds: a folder
    wholly in ns read as the year 5e10, frames in ns against scans in s reached ingest's
    bag advice, and odometry in ns overlapped no scan without a word."""
    root = tmp_path / "a"
    write_small(root)
    csv_path, scans_path, odo_path = (root / "camera" / "frames.csv", root / "scans.npz",
                                      root / "odometry.tum")
    originals = {p: p.read_bytes() for p in (csv_path, scans_path, odo_path)}
    ns = 1_700_000_000_000_000_000

    def frames_ns() -> None:
        lines = csv_path.read_text().splitlines()
        csv_path.write_text("\n".join([lines[0]] + [
            ",".join([r.split(",")[0], str(ns + 10**8 * i)] + r.split(",")[2:])
            for i, r in enumerate(lines[1:])]) + "\n")

    def scans_ns() -> None:
        with np.load(scans_path) as d:
            arrays = {k: d[k] for k in d.files}
        arrays["stamps"] = ns + np.arange(len(arrays["stamps"]), dtype=np.int64) * 10**8
        np.savez(scans_path, **arrays)

    def odometry(stamps: np.ndarray) -> None:
        odo = read_tum(odo_path)
        write_tum(odo_path, Trajectory(stamps, odo.poses, "odom", "base_link"))

    stamps = np.arange(10) * 0.05
    cases = [
        (frames_ns, r"frames.csv:2: field 'stamp' holds 1.7e\+18, which looks like "
                    r"nanoseconds.*divide them by 1e9"),
        (scans_ns, r"scans.npz: field 'stamps' holds 1.7e\+18.*nanoseconds.*by 1e9"),
        (lambda: odometry(1.7e12 + 1000 * stamps),
         r"odometry.tum: field 'timestamp' holds 1.7e\+12.*milliseconds.*by 1e3"),
        (lambda: odometry(1000.0 + stamps),
         r"frames.csv spans 0.013 .. 0.313 s and odometry.tum 1000.000 .. 1000.450 s: they "
         r"share no moment.*one clock"),
    ]
    for spoil, match in cases:
        spoil()
        with pytest.raises(SequenceFormatError, match=match):
            read_sequence(root)
        for p, data in originals.items():
            p.write_bytes(data)
    # Odometry starting just after the last frame (within a second) is one clock.
    odometry(0.8 + stamps)
    assert read_sequence(root).odometry.stamps[0] == 0.8


@pytest.mark.parametrize("orientation", [3, 6])
def test_exif_orientation_is_not_applied_to_frames(tmp_path: Path, orientation: int) -> None:
    """A JPEG tagged 'rotate 180' (3) was read rotated, its white top-left corner at the
    bottom right, while the size check read it as stored: the camera rolled 180 degrees
    against its rig without a word; tagged 'rotate 90' (6) it came out 24x32 after the
    32x24 size check passed. Frames are the stored pixels, as the intrinsics are."""
    from PIL import Image

    from toolkit.sensors import load_rgb

    root = tmp_path / "seq"
    w = SequenceWriter(root, make_rig(), name="jpeg")
    img = np.zeros((H, W, 3), np.uint8)  # [H, W, 3]
    img[:4, :4] = 255
    exif = Image.Exif()
    exif[0x0112] = orientation
    for i in range(2):
        jpg = tmp_path / f"{i}.jpg"
        Image.fromarray(img).save(jpg, exif=exif.tobytes(), quality=95)
        assert load_rgb(jpg).shape == (H, W, 3)
        w.add_frame(0.1 * i, None, image_path=jpg)  # type: ignore[arg-type]
    w.close()
    frame = read_sequence(root).frames[0].image
    assert frame.shape == (H, W, 3)
    assert np.allclose(np.argwhere(frame[..., 0] > 200).mean(0), [1.5, 1.5], atol=0.5)


def test_jpeg_frames_are_kept_as_they_are(tmp_path: Path) -> None:
    """A JPEG frame was decoded and re-encoded as a lossless PNG (a camera's 73 KB became
    590 KB). Kept as it is where every reader decodes it to the same pixels; one with a
    turning EXIF tag (another program would turn it) or pixels other than the file's
    still becomes a PNG of the stored pixels."""
    import cv2
    from PIL import Image

    from toolkit.io.sequence import jpeg_as_is
    from toolkit.sensors import load_rgb

    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.integers(0, 256, (H, W, 3), dtype=np.uint8), (5, 5), 0)
    plain, turned = tmp_path / "plain.jpg", tmp_path / "turned.jpg"
    Image.fromarray(img).save(plain, quality=90)
    exif = Image.Exif()
    exif[0x0112] = 3  # rotate 180
    Image.fromarray(img).save(turned, exif=exif.tobytes(), quality=90)
    pixels = load_rgb(plain)
    assert jpeg_as_is(plain.read_bytes(), pixels)
    assert not jpeg_as_is(turned.read_bytes(), load_rgb(turned))
    assert not jpeg_as_is(plain.read_bytes(), pixels[..., ::-1])  # not these pixels
    ok, png = cv2.imencode(".png", pixels[..., ::-1])
    assert ok and not jpeg_as_is(png.tobytes(), pixels)
    w = SequenceWriter(tmp_path / "seq", make_rig(), name="jpeg")
    w.add_frame(0.0, None, image_path=plain)  # type: ignore[arg-type]
    w.add_frame(0.1, None, image_path=turned)  # type: ignore[arg-type]
    w.add_frame(0.2, pixels, image_jpeg=plain.read_bytes())
    w.add_frame(0.3, pixels[..., ::-1].copy(), image_jpeg=plain.read_bytes())
    w.close()
    frames = read_sequence(tmp_path / "seq").frames
    assert [f.path.suffix for f in frames] == [".jpg", ".png", ".jpg", ".png"]
    assert frames[0].path.read_bytes() == plain.read_bytes() == frames[2].path.read_bytes()
    for f, want in zip(frames, [pixels, load_rgb(turned), pixels, pixels[..., ::-1]],
                       strict=True):
        assert np.array_equal(f.image, want)


def test_writer_refuses_stamps_its_reader_would_refuse(tmp_path: Path) -> None:
    """NaN / inf frame stamps and unsorted, repeated or NaN scan stamps were written and
    close()d as a finished folder that read_sequence then refused."""
    img = np.zeros((H, W, 3), np.uint8)

    def scan(t: float) -> LaserScan:
        return LaserScan(t, np.full(8, 2.0, np.float32), -1.5, 3.0 / 7, 0.1, 10.0)

    cases = [
        ([np.nan, 0.1], [], r"frame 0: stamp nan is not finite"),
        ([0.0, np.nan, 0.2], [], r"frame 1: stamp nan is not finite"),
        ([0.0, np.inf], [], r"frame 1: stamp inf is not finite"),
        ([0.0, 0.1, 0.05], [], r"frame 2: stamp 0.05 not after the previous frame's 0.1"),
        ([1.7e18], [], r"frame 0: field 'stamp' holds 1.7e\+18.*nanoseconds"),
        ([0.0], [0.1, 0.0, 0.2], r"scan 1: stamp 0.0 not after scan 0's 0.1; sort the scans"),
        ([0.0], [0.0, 0.0], r"scan 1: stamp 0.0 not after scan 0's 0.0"),
        ([0.0], [0.0, np.nan], r"scan 1: stamp nan is not finite"),
    ]
    for frames, scans, match in cases:
        w = SequenceWriter(tmp_path / "s", make_rig())
        with pytest.raises(ValueError, match=match):
            for t in frames:
                w.add_frame(t, img)
            for t in scans:
                w.add_scan(scan(t))
        w.discard()
    w = SequenceWriter(tmp_path / "s", make_rig())
    w.add_frame(0.0, img)
    for t in (0.0, 0.05):
        w.add_scan(scan(t))
    w.close()
    assert read_sequence(tmp_path / "s").scan_stamps.tolist() == [0.0, 0.05]


def test_frames_csv_as_spreadsheets_save_it(tmp_path: Path) -> None:
    """Excel's "CSV UTF-8" starts with a BOM, which hid the 'stamp' column; a cp1252 file
    raised a bare UnicodeDecodeError naming no file; spaces after the commas hid every
    column but the first."""
    root = tmp_path / "a"
    write_small(root)
    csv_path = root / "camera" / "frames.csv"
    lines = csv_path.read_text().splitlines()
    header = lines[0].split(",")
    # stamp first: the BOM landed in its name
    body = "\n".join([",".join(header[1:])] + [",".join(r.split(",")[1:]) for r in lines[1:]])
    csv_path.write_bytes(b"\xef\xbb\xbf" + body.replace("\n", "\r\n").encode() + b"\r\n")
    assert read_sequence(root).frame_stamps.tolist() == [0.1 * i + 0.013 for i in range(4)]
    csv_path.write_text("\n".join(r.replace(",", ", ") for r in lines) + "\n")
    assert read_sequence(root).frame_stamps.tolist() == [0.1 * i + 0.013 for i in range(4)]
    csv_path.write_bytes(("\n".join(lines[:2] + [lines[2] + ",bild_\xe4.png"]) + "\n")
                         .encode("cp1252"))
    with pytest.raises(SequenceFormatError, match=r"frames.csv:3: not UTF-8 text "
                                                  r"\(byte b'\\xe4'\); save the file as UTF-8"):
        read_sequence(root)


def test_frames_of_more_than_8_bits_are_refused(tmp_path: Path) -> None:
    """A 16-bit PNG of 12-bit data (4000) read as 15 of 255 and ingest copied the 16-bit
    file on, although frames are 8-bit."""
    import cv2

    root = tmp_path / "a"
    write_small(root)
    deep = np.full((H, W, 3), 4000, np.uint16)  # [H, W, 3]
    cv2.imwrite(str(root / "camera" / "images" / "000000.png"), deep)
    with pytest.raises(SequenceFormatError, match=r"000000.png: a uint16 image \(brightest "
                                                  r"value 4000\); frames are 8-bit.*by 16"):
        read_sequence(root)
    src = tmp_path / "deep.png"
    cv2.imwrite(str(src), deep)
    _writer_refuses_frame(tmp_path / "b", src, r"deep.png: a uint16 image")


def _writer_refuses_frame(root: Path, image_path: Path, match: str) -> None:
    """SequenceWriter.add_frame refuses ``image_path`` with an error matching ``match``."""
    w = SequenceWriter(root, make_rig())
    with pytest.raises(ValueError, match=match):
        w.add_frame(0.0, None, image_path=image_path)  # type: ignore[arg-type]
    w.discard()


def test_every_frame_is_checked_for_the_cameras_size_and_8_bits(tmp_path: Path) -> None:
    # Only frame 0 was: a later frame of another size passed read_sequence.
    import cv2

    root = tmp_path / "a"
    write_small(root)
    images = root / "camera" / "images"
    cv2.imwrite(str(images / "000002.png"), np.zeros((2 * H, 2 * W, 3), np.uint8))
    with pytest.raises(SequenceFormatError, match=rf"000002.png: image is {2 * W}x{2 * H} "
                                                  rf"but .*says {W}x{H} \(frame 2"):
        read_sequence(root)
    cv2.imwrite(str(images / "000002.png"), np.zeros((H, W, 3), np.uint16))
    with pytest.raises(SequenceFormatError, match=r"000002.png: a 16-bit image \(frame 2\)"):
        read_sequence(root)
    jpg = tmp_path / "f.jpg"
    cv2.imwrite(str(jpg), np.zeros((H, W, 3), np.uint8))
    assert image_header(jpg) == (W, H, 8)
    # Other formats are decoded to check: a 16-bit TIFF was cut to 8 bits without a word.
    tif = tmp_path / "deep.tif"
    cv2.imwrite(str(tif), np.full((H, W, 3), 4000, np.uint16))
    assert image_header(tif) is None
    _writer_refuses_frame(tmp_path / "b", tif, r"deep.tif: a uint16 image")


def test_scan_file_values_are_named_not_called_unreadable(tmp_path: Path) -> None:
    root = tmp_path / "a"
    write_small(root)
    path = root / "scans.npz"
    with np.load(path) as f:
        good = {k: f[k] for k in f.files}
    n = len(good["stamps"])

    def refused(match: str, **change: np.ndarray) -> None:
        np.savez(path, **{**good, **change})
        with pytest.raises(SequenceFormatError, match=match) as e:
            read_sequence(root)
        assert "not a readable npz" not in str(e.value)

    refused(r"'range_min' has 4 values for 6 scans; give one per scan or one for all",
            range_min=np.full(4, 0.1))
    refused(r"scan 0: .*angles are radians", angle_min=np.full(n, -90.0),
            angle_increment=np.full(n, 180.0 / 89))
    refused(r"not strictly increasing at scan 1 \(1700000000.0 then 1700000000.0\); they are "
            r"float32.*store them as float64",
            stamps=(1.7e9 + good["stamps"]).astype(np.float32))
    # Before: a TypeError ("only 0-dimensional arrays"), numpy's broadcast error called the
    # file unreadable, and the same arrays stopped calibration's npz reader with a traceback.
    refused(r"'stamps' must hold one stamp per scan \(\[S\]\), got shape \(6, 1\)",
            stamps=good["stamps"][:, None])
    refused(r"'time_increment' has 4 values for 6 scans; give one per scan or one for all",
            time_increment=np.zeros(4))
    refused(r"'ranges' must hold numbers \(metres\)", ranges=np.full(good["ranges"].shape, "far"))
    from calibration.scans import read_scan_file

    np.savez(path, **{**good, "time_increment": np.zeros(4)})
    with pytest.raises(SequenceFormatError, match="'time_increment' has 4 values"):
        read_scan_file(path)


def test_a_malformed_pose_file_is_a_sequence_format_error(tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]
                                                         ) -> None:
    """A bad line of odometry.tum or groundtruth/poses_base.tum was the TUM reader's plain
    ValueError: ``python -m calibration check | time-offset | extrinsic --sequence`` printed
    its traceback and exited 1 instead of the one-line error and exit 2."""
    from calibration.cli import main

    root = tmp_path / "a"
    write_small(root)
    for name in ("odometry.tum", "groundtruth/poses_base.tum"):
        path = root / name
        good = path.read_text()
        lines = good.splitlines()
        lines[-1] = lines[-1][: len(lines[-1]) // 3]  # cut short mid-line
        path.write_text("\n".join(lines) + "\n")
        with pytest.raises(SequenceFormatError, match=rf"{name}:\d+: TUM line needs 8"):
            read_sequence(root)
        assert main(["time-offset", "--sequence", str(root), "--out",
                     str(tmp_path / "t")]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"error: {path}:") and "Traceback" not in err, err
        path.write_text(good)


def test_a_file_given_as_the_sequence_folder_is_not_called_missing(tmp_path: Path) -> None:
    """A file named as the sequence folder (its meta.yaml, a bag) was reported as
    "sequence folder not found" though it exists."""
    f = tmp_path / "meta.yaml"
    f.write_text("name: x\n")
    with pytest.raises(SequenceFormatError, match=r"meta.yaml: is a file, not a sequence "
                       r"folder \(the one holding rig.yaml and meta.yaml\)"):
        read_sequence(f)
    with pytest.raises(SequenceFormatError, match=r"nowhere: sequence folder not found"):
        read_sequence(tmp_path / "nowhere")


@pytest.mark.parametrize("distortion", [[0.1, -0.05, 0.01], [[0.1], [-0.05], [0.0], [0.0]]])
def test_rig_distortion_lists_opencv_does_not_take_are_refused(
        tmp_path: Path, distortion: list) -> None:
    """A 3-list (k1 k2 k3 to tools that give radial terms only) was read as k1 k2 p1, and a
    nested list was flattened: both read without a word; now the file and field are named."""
    write_small(tmp_path)
    rig = yaml.safe_load((tmp_path / "rig.yaml").read_text())
    rig["camera"]["distortion"] = distortion
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(rig))
    with pytest.raises(SequenceFormatError, match=r"rig.yaml: field 'camera': field "
                       r"'distortion' (has 3 coefficients|is \[\[)"):
        read_sequence(tmp_path)
    rig["camera"]["distortion"] = [0.1, -0.05, 0.0, 0.0]  # k1 k2 p1 p2: OpenCV's 4
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(rig))
    assert read_sequence(tmp_path).rig.camera.dist.tolist() == [0.1, -0.05, 0.0, 0.0, 0.0]


@pytest.mark.parametrize("key", ["has_camera", "check_image_size"])
def test_meta_flags_are_yaml_booleans_only(tmp_path: Path, key: str) -> None:
    """A quoted "false" was read with bool() (or as truthy): True, so a lidar-only
    recording counted as having a camera."""
    write_small(tmp_path)
    meta_path = tmp_path / "meta.yaml"
    meta = yaml.safe_load(meta_path.read_text())
    meta_path.write_text(yaml.safe_dump({**meta, key: "false"}))
    with pytest.raises(SequenceFormatError, match=rf"meta.yaml: field '{key}' is 'false', "
                       rf"not a YAML boolean; write {key}: true or {key}: false"):
        read_sequence(tmp_path)
    meta_path.write_text(yaml.safe_dump({**meta, key: False}))
    assert read_sequence(tmp_path).meta[key] is False


def test_a_rig_marked_reliable_by_quoted_text_is_refused(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """calibration.reliable: "false" (quoted) is no YAML boolean: read_rig and a bag's
    rosbag.calibration read such a rig without the warning an unreliable extrinsic gets,
    while read_extrinsic (the calibrate stage's reader) refused it."""
    import logging

    from toolkit.io.rosbag import BagError, load_calibration
    from toolkit.io.sequence import read_rig, rig_to_dict

    path = tmp_path / "rig.yaml"
    base = rig_to_dict(make_rig())
    for mark in ("false", "no", None, 0):
        path.write_text(yaml.safe_dump({**base, "calibration": {"reliable": mark}}))
        with pytest.raises(SequenceFormatError, match=rf"rig.yaml: field 'reliable' is "
                           rf"{mark!r}, not a YAML boolean; write reliable: true or "
                           "reliable: false"):
            read_rig(path)
        with pytest.raises(BagError, match=r"rig.yaml: field 'reliable' is .*not a YAML "
                           "boolean"):
            load_calibration(path)
    path.write_text(yaml.safe_dump({**base, "calibration": {
        "reliable": False, "unreliable_because": ["2 views"]}}))
    with caplog.at_level(logging.WARNING):
        read_rig(path)
    assert "its extrinsic was marked unreliable when it was estimated (2 views)" in caplog.text
    caplog.clear()
    for calibration in ({"reliable": True}, {"rms_m": 0.01}):
        path.write_text(yaml.safe_dump({**base, "calibration": calibration}))
        with caplog.at_level(logging.WARNING):
            assert np.allclose(read_rig(path).T_base_laser, make_rig().T_base_laser)
        assert "unreliable" not in caplog.text

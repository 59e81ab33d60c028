"""Readers of files users bring: map_server maps, rigs and calibrations, COLMAP text,
KITTI, TUM, depth; the conventions of the tools that wrote them and errors that name the
file, the line and the fix."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from calibration.files import (
    CalibrationFileError,
    extrinsic_from_mapping,
    rig_for_extrinsic,
    write_rig_with_calibration,
)
from toolkit.camera import PinholeCamera
from toolkit.fusion.cloud import CloudOptions, RayCache, depth_to_points
from toolkit.io.colmap_text import read_colmap_model
from toolkit.io.depth import read_depth
from toolkit.io.kitti import read_kitti
from toolkit.io.occupancy import _pgm_bytes, read_occupancy
from toolkit.io.rosbag import BagError, load_calibration, parse_transform
from toolkit.io.sequence import SequenceFormatError, read_rig, rig_to_dict
from toolkit.io.tum import read_tum
from toolkit.sensors import Rig

MIRROR = [[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]  # det -1


# ---------------------------------------------------------------------------- map_server


def _map(tmp_path: Path, pixels: list[int], **meta) -> Path:
    (tmp_path / "m.pgm").write_bytes(_pgm_bytes(np.array([pixels], np.uint8), 0.05))
    d = {"image": "m.pgm", "resolution": 0.05, "origin": [0.0, 0.0, 0.0], "negate": 0,
         "occupied_thresh": 0.65, "free_thresh": 0.25, **meta}
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(d))
    return tmp_path / "m.yaml"


def test_occupancy_raw_mode_as_nav2(tmp_path):
    # nav2 map_io: raw pixels <= 100 are the occupancy in percent, above it unknown.
    occ = read_occupancy(_map(tmp_path, [0, 100, 40, 255], mode="raw")).occupancy
    np.testing.assert_allclose(occ[0, :3], [0.0, 1.0, 0.4])
    assert np.isnan(occ[0, 3])
    # Trinary stays as map_server: 254 free, 0 occupied, 205 unknown.
    occ = read_occupancy(_map(tmp_path, [254, 0, 205], free_thresh=0.196)).occupancy
    assert occ[0, 0] == 0 and occ[0, 1] == 1 and np.isnan(occ[0, 2])


@pytest.mark.parametrize("meta, match", [({"mode": "trinery"}, "mode"),
                                         ({"origin": [1.0, 2.0]}, "origin"),
                                         ({"resolution": float("nan")}, "resolution")])
def test_occupancy_yaml_errors_name_the_field(tmp_path, meta, match):
    with pytest.raises(ValueError, match=f"m.yaml: field '{match}'"):
        read_occupancy(_map(tmp_path, [0, 254], **meta))


def test_truncated_pgm_and_bad_yaml_name_the_file(tmp_path):
    y = _map(tmp_path, [0, 254, 205])
    data = (tmp_path / "m.pgm").read_bytes()
    (tmp_path / "m.pgm").write_bytes(data[:-2])
    with pytest.raises(FileNotFoundError, match="m.yaml: field 'image' names .*m.pgm, which "
                       "is unreadable or truncated"):
        read_occupancy(y)
    (tmp_path / "m.pgm").unlink()
    with pytest.raises(FileNotFoundError, match="m.yaml: field 'image' names .*m.pgm, which "
                       "is not there"):
        read_occupancy(y)
    (tmp_path / "m.pgm").write_bytes(b"P2\n# ascii\n3 1\n255\n0 254 128\n")
    occ = read_occupancy(y).occupancy  # ASCII PGM, as some map tools write
    assert occ[0, 0] == 1 and occ[0, 1] == 0 and np.isnan(occ[0, 2])
    y.write_text("image: m.pgm\nresolution: [0.05\n")
    with pytest.raises(ValueError, match="m.yaml: not valid YAML"):
        read_occupancy(y)


# ---------------------------------------------------------------------------- rigs


def test_mirrored_mounts_are_refused_everywhere(tmp_path):
    cam = PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5)
    with pytest.raises(ValueError, match="reflection"):
        Rig(cam, np.array(MIRROR, float), np.eye(4))
    d = rig_to_dict(Rig(cam, np.eye(4), np.eye(4)))
    d["T_base_camera"] = MIRROR
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(d))
    with pytest.raises(SequenceFormatError, match="rig.yaml: T_base_camera is a reflection"):
        read_rig(tmp_path / "rig.yaml")
    with pytest.raises(BagError, match="reflection"):
        parse_transform(MIRROR, "calib.yaml: field 'T_base_laser'")
    with pytest.raises(CalibrationFileError, match="'T_camera_laser' is a reflection"):
        extrinsic_from_mapping({"T_camera_laser": MIRROR}, "ext.yaml")


def test_rounded_rotations_are_taken_and_transposed_matrices_named(tmp_path):
    """A 30 deg yaw written to 4 decimals (R R^T 4e-5 off) was refused as 'not
    orthonormal', and so was a transposed matrix, for the wrong reason."""
    cam = PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5)
    T = [[0.8660, -0.5000, 0.0, 0.1], [0.5000, 0.8660, 0.0, 0.0], [0.0, 0.0, 1.0, 0.3],
         [0.0, 0.0, 0.0, 1.0]]
    for rig in (Rig(cam, np.eye(4), np.array(T)),
                Rig(cam, np.eye(4), extrinsic_from_mapping({"T_camera_laser": T}, "e.yaml"))):
        R = rig.T_base_laser[:3, :3]
        assert np.abs(R @ R.T - np.eye(3)).max() < 1e-12
        assert np.degrees(np.arctan2(R[1, 0], R[0, 0])) == pytest.approx(30.0, abs=0.01)
    assert parse_transform(T, "c.yaml: field 'T_base_laser'")[0][0, 3] == 0.1
    with pytest.raises(ValueError, match=r"T_base_laser has the last row \[0.1, 0.0, 0.3, "
                                         r"1.0\], not \[0, 0, 0, 1\] \(transposed"):
        Rig(cam, np.eye(4), np.array(T).T)
    with pytest.raises(ValueError, match="T_base_camera is not a rigid transform: R R"):
        Rig(cam, np.diag([1.0, 1.1, 1.0, 1.0]), np.eye(4))


def test_a_rig_that_is_not_rigid_says_what_to_do(tmp_path):
    """rig.yaml with a non-orthonormal rotation said "R R^T is 0.21 off the identity" and
    no way out: the message names the fix (export it again, or the calibration command
    that writes a rig)."""
    d = rig_to_dict(Rig(PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5), np.eye(4), np.eye(4)))
    d["T_base_camera"] = np.diag([1.0, 1.1, 1.0, 1.0]).tolist()  # R R^T: diag(1, 1.21, 1)
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(d))
    with pytest.raises(SequenceFormatError) as info:
        read_rig(tmp_path / "rig.yaml")
    assert str(info.value) == (
        f"{tmp_path / 'rig.yaml'}: T_base_camera is not a rigid transform: R R^T is 0.21 off "
        "the identity (the rotation is not orthonormal); export it again, with all its "
        "digits, from the tool that made it, or estimate it: python -m calibration "
        "extrinsic ... --out rig.yaml writes a rig from checkerboard views "
        "(docs/calibration.md)")


def test_calibration_output_feeds_bag_ingest_and_back(tmp_path):
    cam = PinholeCamera(640, 480, 519.3, 518.9, 331.1, 229.4)
    T_cl = np.array([[0, -1, 0, 0.02], [0, 0, -1, 0.1], [1, 0, 0, -0.05], [0, 0, 0, 1.0]])
    write_rig_with_calibration(tmp_path / "rig.yaml", rig_for_extrinsic(cam, T_cl),
                               {"rms_m": 0.01})
    cal = load_calibration(tmp_path / "rig.yaml")
    # What was estimated is read; calibration's own base frame is not the robot's.
    np.testing.assert_allclose(cal.T_camera_laser, T_cl)
    assert cal.T_base_camera is None and cal.T_base_laser is None
    assert cal.camera is not None and cal.camera.fx == cam.fx
    # Ingest's calibration file with a tf-style entry reads in the calibration tool.
    (tmp_path / "calib.yaml").write_text(
        "T_base_camera: {parent: base_link, child: camera_optical, xyz: [0.1, 0.0, 0.3],\n"
        "                quat_xyzw: [0.5, -0.5, 0.5, -0.5]}\n"
        "T_base_laser: [[1, 0, 0, 0.2], [0, 1, 0, 0], [0, 0, 1, 0.15], [0, 0, 0, 1]]\n")
    T = extrinsic_from_mapping(yaml.safe_load((tmp_path / "calib.yaml").read_text()), "c")
    # The laser sits 0.1 m ahead of and 0.15 m below the camera: optical z 0.1, y 0.15.
    np.testing.assert_allclose(T[:3, 3], [0.0, 0.15, 0.1], atol=1e-12)


# ---------------------------------------------------------------------------- lenses


def test_pixels_no_ray_reaches_get_none():
    # ACFR's calibration (k3 < 0): the distorted radius peaks at 0.699, the corners
    # of the 640x480 image lie at 0.776 - OpenCV returned rays 40 px off for them.
    cam = PinholeCamera(640, 480, 519.268, 518.894, 331.112, 229.434,
                        np.array([0.11418, 0.19343, -0.00268, 0.00372, -1.09540]))
    rays = cam.pixel_rays()
    reach = np.isfinite(rays[..., 0])
    assert not reach[0, 0] and reach[240, 320]
    assert 6000 < (~reach).sum() < 8000  # 6753 pixels beyond the peak radius
    uv, _ = cam.project(rays[reach])
    v, u = np.nonzero(reach)
    assert np.abs(uv - np.stack([u, v], -1)).max() < 0.05
    # The fusion's clouds leave those pixels out instead of placing NaN points.
    cache = RayCache(cam, 2)
    pts, _, _ = depth_to_points(np.full((480, 640), 2.0, np.float32),
                                np.zeros((480, 640, 3), np.uint8), cache, np.eye(4),
                                CloudOptions(edge_threshold=0.0, stride=2))
    assert np.isfinite(pts).all() and len(pts) == int(cache.reachable.sum())


# ---------------------------------------------------------------------------- COLMAP


def _colmap(tmp_path: Path, cameras: str, images: str) -> Path:
    (tmp_path / "cameras.txt").write_text(cameras)
    (tmp_path / "images.txt").write_text(images)
    return tmp_path


def test_colmap_text_read_as_colmap_reads_it(tmp_path):
    # Trimmed lines, blank lines and indented comments between images (COLMAP and
    # pycolmap skip them); the line after an image line is its observations, even empty.
    folder = _colmap(tmp_path, "# cameras\n1 PINHOLE 640 480 500 500 320 240\n",
                     "1 1 0 0 0 0 0 0 1 a.png\n\n\n   # comment\n"
                     "2 1 0 0 0 0 -1 0 1 b.png\n10.5 20.5 -1\n")
    m = read_colmap_model(folder)
    assert [im.name for im in m.images] == ["a.png", "b.png"]
    assert len(m.images[0].xys) == 0 and m.images[1].xys.tolist() == [[10.5, 20.5]]


@pytest.mark.parametrize("cameras, images, match", [
    ("1 OPENCV 640 480 500 500 320 240 0.1\n", "", r"cameras.txt:1: OPENCV has 8"),
    ("1 PINHOLE 640 480 500\n", "", r"cameras.txt:1: PINHOLE has 4"),
    ("1 PINHOLE 640 480 5x0 500 320 240\n", "", r"cameras.txt:1: could not convert"),
    ("1 PINHOLE 640 480 500 500 320 240\n", "1 1 0 0 0 0 0 1 a.png\n", r"images.txt:1: image"),
    ("1 PINHOLE 640 480 500 500 320 240\n", "1 1 0 0 0 0 0 0 1 a.png\n1 2\n",
     r"images.txt:2: observations"),
])
def test_colmap_text_errors_name_file_and_line(tmp_path, cameras, images, match):
    with pytest.raises(ValueError, match=match):
        read_colmap_model(_colmap(tmp_path, cameras, images))


def test_colmap_point_colour_out_of_range_names_file_and_line(tmp_path):
    folder = _colmap(tmp_path, "1 PINHOLE 640 480 500 500 320 240\n", "")
    (folder / "points3D.txt").write_text("# points\n7 0 0 1 300 0 0 0.5\n")
    with pytest.raises(ValueError, match=r"points3D.txt:2: colour R G B \[300, 0, 0\] "
                                         r"outside 0..255"):
        read_colmap_model(folder)


# ---------------------------------------------------------------------------- poses, depth


def test_kitti_tum_and_depth_readers_check_what_they_read(tmp_path):
    (tmp_path / "k.txt").write_text("2 0 0 0 0 2 0 0 0 0 2 0\n")
    with pytest.raises(ValueError, match="k.txt:1: not a rigid pose"):
        read_kitti(tmp_path / "k.txt")
    (tmp_path / "k.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 x\n")
    with pytest.raises(ValueError, match="k.txt:1: could not convert"):
        read_kitti(tmp_path / "k.txt")
    (tmp_path / "k.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(FileNotFoundError, match="times.txt: KITTI times file not found"):
        read_kitti(tmp_path / "k.txt", tmp_path / "times.txt")
    # A byte-order mark before the header comment (Windows editors) is no data line.
    (tmp_path / "t.tum").write_text("\ufeff# stamp tx ty tz qx qy qz qw\n1.0 0 0 0 0 0 0 1\n",
                                    encoding="utf-8")
    assert len(read_tum(tmp_path / "t.tum")) == 1
    # A repeated stamp is named by its file line (comments counted), not its pose number.
    (tmp_path / "r.tum").write_text("# a\n# b\n1.0 0 0 0 0 0 0 1\n\n1.0 0 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match=r"r.tum:5: stamps not strictly increasing: 1.0 "
                                         r"repeats 1.0 \(line 3\)"):
        read_tum(tmp_path / "r.tum")
    # format_tum's own frames line wins over a caller's header that looks like one.
    from toolkit.geometry import Trajectory
    from toolkit.io.tum import write_tum
    write_tum(tmp_path / "h.tum", Trajectory(np.array([0.0]), np.eye(4)[None], "world",
                                             "camera"),
              header="T_odom_base_link: from the wheel encoders, not used here")
    back = read_tum(tmp_path / "h.tum")
    assert (back.frame, back.child) == ("world", "camera")
    (tmp_path / "d.npy").write_bytes(b"\x93NUMPY garbage")
    with pytest.raises(ValueError, match="d.npy: not a readable .npy depth map"):
        read_depth(tmp_path / "d.npy")
    # An empty file (a copy cut short) was numpy's EOFError "No data left in file".
    (tmp_path / "e.npy").write_bytes(b"")
    with pytest.raises(ValueError, match="e.npy: not a readable .npy depth map"):
        read_depth(tmp_path / "e.npy")


def test_scan_arrays_and_frame_rows_name_what_is_wrong(tmp_path):
    """NaN range limits, range_min >= range_max and intensities for fewer scans were read
    (the lidar pairs then failed, blaming the extrinsics); a frames.csv row without its
    image field was a TypeError."""
    from toolkit.io.sequence import SequenceFormatError, scans_from_arrays

    good = {"stamps": np.array([0.0, 0.1]), "ranges": np.ones((2, 4), np.float32),
            "angle_min": np.zeros(2), "angle_increment": np.full(2, 0.1),
            "range_min": np.full(2, 0.1), "range_max": np.full(2, np.inf)}
    assert len(scans_from_arrays(good, "s.npz")) == 2  # range_max inf: no limit
    for key, value, match in (("range_max", np.array([10.0, np.nan]), "'range_max' holds non-"),
                              ("range_min", np.array([np.nan, 0.1]), "'range_min' holds non-"),
                              ("range_min", np.array([0.1, 20.0]), "'range_min' is not below"),
                              ("intensities", np.ones((1, 4)), "'intensities' has 1 rows")):
        bad = {**good, key: value}
        if "below" in match:
            bad["range_max"] = np.full(2, 10.0)
        with pytest.raises(SequenceFormatError, match=rf"s\.npz: {match}"):
            scans_from_arrays(bad, "s.npz")
    from toolkit.io.sequence import _frames_from_rows

    with pytest.raises(SequenceFormatError, match=r"frames\.csv:2: field 'image' is empty"):
        _frames_from_rows([{"index": "0", "stamp": "1.0", "image": None}], tmp_path,
                          tmp_path / "frames.csv")


def test_empty_odometry_runs_scan_only():
    """An odometry file of comments only: the SLAM runs scan-only (an IndexError before)."""
    from test_slam2d import _drive, make_scan  # the tests folder is on sys.path

    from toolkit.geometry import Trajectory
    from toolkit.slam2d.pipeline import run_slam

    scans = [make_scan(p, float(k)) for k, p in enumerate(_drive(6))]
    res = run_slam(scans, Trajectory(np.zeros(0), np.zeros((0, 4, 4)), "odom", "base_link"))
    assert res.metrics["scans_with_odometry"] == 0 and len(res.poses) == len(scans)


def test_meta_yaml_keys_are_optional_but_another_format_is_refused(tmp_path):
    """As read_sequence's docstring says: meta.yaml and its keys are optional (a folder
    is a sequence by its rig.yaml), a format other than lidarcam-sequence is refused."""
    from toolkit.fusion.synthetic import write_box_room
    from toolkit.io.sequence import SequenceFormatError, read_sequence

    root = write_box_room(tmp_path / "seq", n_frames=2)
    assert yaml.safe_load((root / "meta.yaml").read_text())["format"] == "lidarcam-sequence"
    (root / "meta.yaml").write_text("version: 1\nname: box\n")
    assert read_sequence(root).name == "box"
    (root / "meta.yaml").unlink()
    assert read_sequence(root).name == "seq"
    (root / "meta.yaml").write_text("format: tum-rgbd\n")
    with pytest.raises(SequenceFormatError, match=r"meta\.yaml: field 'format' is 'tum-rgbd'"):
        read_sequence(root)


def test_a_sequence_whose_writer_stopped_before_meta_yaml_is_refused(tmp_path, monkeypatch):
    """SequenceWriter.close() writes rig.yaml, frames.csv and scans.npz, then the ground
    truth, then meta.yaml last (its "finished" mark) and only then drops its journal: a
    write cut short between them was read as a sequence without ground truth."""
    import toolkit.io.sequence as sequence
    from toolkit.geometry import Trajectory
    from toolkit.io.sequence import SequenceWriter, read_sequence
    from toolkit.sensors import LaserScan

    root = tmp_path / "seq"
    w = SequenceWriter(root, Rig(PinholeCamera(8, 6, 5.0, 5.0, 3.5, 2.5)), name="cut")
    for k in range(3):
        w.add_frame(0.1 * k, np.full((6, 8, 3), 40 * k, np.uint8))
        w.add_scan(LaserScan(0.1 * k, np.full(8, 2.0, np.float32), -np.pi, np.pi / 4, 0.1, 10.0))
    w.groundtruth_poses = Trajectory(np.array([0.0, 0.2]), np.stack([np.eye(4)] * 2))

    def disk_full(*args: object, **kwargs: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(sequence, "write_tum", disk_full)
    with pytest.raises(OSError, match="No space"):
        w.close()
    assert (root / "camera" / "frames.csv").exists() and (root / "scans.npz").exists()
    assert not (root / "meta.yaml").exists()
    with pytest.raises(SequenceFormatError, match=r"unfinished sequence: its writer stopped "
                       r"before meta\.yaml.*\.frames\.journal\.jsonl"):
        read_sequence(root)
    # Without the journal it is a hand-made folder, which meta.yaml's absence does not refuse.
    (root / sequence.JOURNAL_NAME).unlink()
    assert len(read_sequence(root).frames) == 3


def test_a_broken_meta_yaml_names_the_file(tmp_path):
    """A parse error or a version that is no number named neither file nor field."""
    from toolkit.fusion.synthetic import write_box_room
    from toolkit.io.sequence import SequenceFormatError, read_sequence

    root = write_box_room(tmp_path / "seq", n_frames=2)
    for text, match in (("version: one\n", "field 'version' is 'one'"),
                        ("[a, b\n", "not valid YAML"), ("- x\n", "expected a mapping")):
        (root / "meta.yaml").write_text(text)
        with pytest.raises(SequenceFormatError, match=rf"meta\.yaml: {match}"):
            read_sequence(root)

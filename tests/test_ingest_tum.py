"""TUM RGB-D folders built here: images, depth, ground truth and the virtual lidar."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from toolkit.camera import PinholeCamera
from toolkit.geometry import pose_to_tum_line
from toolkit.ingest.convert import convert
from toolkit.ingest.recording import R_BASE_OPTICAL, IngestError
from toolkit.io.sequence import read_sequence
from toolkit.io.tum_rgbd import (
    TumRgbdOptions,
    VirtualLidar,
    VirtualLidarOptions,
    level_mount,
    read_tum_rgbd,
)

W, H = 64, 48
CAM = {"width": W, "height": H, "fx": 50.0, "fy": 50.0, "cx": 31.5, "cy": 23.5}
WALL_M = 2.0  # a flat wall this far along the optical axis fills every depth image
T0 = 1305031102.0


def camera_pose(i: int, pitch_deg: float = 0.0) -> np.ndarray:
    """T_world_camera: a level base turning and driving, the camera on it (maybe pitched)."""
    yaw = 0.1 * i
    R_world_base = Rotation.from_euler("z", yaw).as_matrix()
    R_pitch = Rotation.from_euler("y", np.radians(pitch_deg)).as_matrix()  # + = nose down
    T = np.eye(4)
    T[:3, :3] = R_world_base @ R_pitch @ R_BASE_OPTICAL
    T[:3, 3] = [0.3 * i, 0.1 * i, 1.2]
    return T


def make_tum(root: Path, n: int = 6, pitch_deg: float = 0.0, gt: bool = True,
             rgb_extra: bool = True, rgb_delay: float = 0.0) -> list[np.ndarray]:
    """A TUM RGB-D folder: n rgb/depth pairs 5 ms apart (the rgb stamped ``rgb_delay``
    late besides), and one rgb without a depth partner within 0.02 s."""
    rng = np.random.default_rng(1)
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb_lines, depth_lines, images = ["# color images", "# timestamp filename"], [], []
    for i in range(n):
        t = T0 + 0.2 * i
        img = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        tc = t + rgb_delay
        cv2.imwrite(str(root / f"rgb/{tc:.6f}.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        rgb_lines.append(f"{tc:.6f} rgb/{tc:.6f}.png")
        images.append(img)
        td = t + 0.005
        depth = np.full((H, W), int(WALL_M * 5000), np.uint16)
        depth[0, 0] = 0  # a missing reading
        cv2.imwrite(str(root / f"depth/{td:.6f}.png"), depth)
        depth_lines.append(f"{td:.6f} depth/{td:.6f}.png")
    if rgb_extra:  # 0.04 s after the last depth image: a scan within 0.05 s, no depth
        t = T0 + 0.2 * (n - 1) + 0.045 + rgb_delay
        cv2.imwrite(str(root / f"rgb/{t:.6f}.png"), np.zeros((H, W, 3), np.uint8))
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    if gt:
        lines = ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
        for k in range(int(n * 0.2 / 0.01) + 20):  # 100 Hz mocap
            t = T0 - 0.1 + 0.01 * k
            lines.append(pose_to_tum_line(t, camera_pose_at(t, pitch_deg)))
        (root / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    return images


def camera_pose_at(t: float, pitch_deg: float) -> np.ndarray:
    s = (t - T0) / 0.2  # continuous "frame index"
    yaw = 0.1 * s
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", yaw).as_matrix() @ Rotation.from_euler(
        "y", np.radians(pitch_deg)).as_matrix() @ R_BASE_OPTICAL
    T[:3, 3] = [0.3 * s, 0.1 * s, 1.2]
    return T


def wall_tolerance(angle: np.ndarray, inc: float, d: float = WALL_M) -> np.ndarray:
    # A beam reports the nearest point of its bin, which lies up to half a bin from the
    # beam's own bearing: on a wall that is at most this far from d / cos(angle).
    a = np.abs(angle)
    return d / np.cos(a + inc / 2) - d / np.cos(a) + 1e-6


@pytest.mark.parametrize("level", ["auto", "camera"])
def test_flat_wall_gives_d_over_cos(tmp_path, level):
    images = make_tum(tmp_path / "tum")
    opts = TumRgbdOptions(camera=CAM, lidar=VirtualLidarOptions(level=level, band_m=0.1))
    rec = read_tum_rgbd(tmp_path / "tum", opts)
    assert len(rec.scans) == 6
    s = rec.scans[0]
    a, r, ok = s.angles(), s.ranges, s.valid_mask()
    assert ok.mean() > 0.95  # every beam sees the wall
    expected = WALL_M / np.cos(a)
    assert np.all(np.abs(r[ok] - expected[ok]) <= wall_tolerance(a[ok], s.angle_increment))
    # beams span the camera's field of view, left (+y) positive
    half = np.arctan((W / 2) / CAM["fx"])
    assert s.angle_min == pytest.approx(-half, abs=0.02)
    assert s.angle_max == pytest.approx(half, abs=0.02)
    np.testing.assert_allclose(rec.rig.T_base_camera[:3, :3], R_BASE_OPTICAL, atol=1e-9)

    res = convert(rec, tmp_path / "seq")
    seq = read_sequence(tmp_path / "seq")
    assert res.plan.dropped["no_depth"] == 1 and len(seq.frames) == 6
    for f, img in zip(seq.frames, images, strict=True):
        assert np.array_equal(f.image, img)
    d = seq.groundtruth.depth(0)
    assert d[0, 0] == 0 and np.all(d.reshape(-1)[1:] == np.float32(WALL_M))
    assert seq.meta["virtual_lidar"]["level"] == ("groundtruth" if level == "auto" else "camera")


def test_groundtruth_becomes_base_poses(tmp_path):
    make_tum(tmp_path / "tum")
    rec = read_tum_rgbd(tmp_path / "tum", TumRgbdOptions(camera=CAM))
    gt = rec.groundtruth
    assert gt is not None and gt.frame == "world" and gt.child == "base_link"
    # the base is level (z up) and carries the camera: T_world_base = T_world_cam inv(T_bc)
    i = int(np.argmin(np.abs(gt.stamps - (T0 + 0.4))))
    T = gt.poses[i]
    np.testing.assert_allclose(T[:3, 2], [0, 0, 1], atol=1e-9)
    np.testing.assert_allclose(T @ rec.rig.T_base_camera, camera_pose_at(gt.stamps[i], 0.0),
                               atol=1e-9)


def test_pitched_camera_levels_from_groundtruth():
    R = np.stack([camera_pose(i, pitch_deg=15.0)[:3, :3] for i in range(10)])
    R_bc, stats = level_mount(R, (0, 0, 1))
    expected = Rotation.from_euler("y", np.radians(15.0)).as_matrix() @ R_BASE_OPTICAL
    np.testing.assert_allclose(R_bc, expected, atol=1e-9)
    assert stats["tilt_down_deg"] == pytest.approx(15.0)
    assert stats["up_spread_max_deg"] == pytest.approx(0.0, abs=1e-6)


def test_virtual_lidar_plane_below_the_camera():
    # A wall 3 m ahead gives beams at 3 / cos(angle) at any height of the plane.
    cam = PinholeCamera(W, H, 50.0, 50.0, 31.5, 23.5)
    lidar = VirtualLidar(cam, R_BASE_OPTICAL, VirtualLidarOptions(height_m=-0.3, band_m=0.1))
    depth = np.full((H, W), 3.0, np.float32)  # optical z = base x = 3 m everywhere
    s = lidar.scan(depth, 0.0)
    ok = s.valid_mask()
    assert ok.mean() > 0.95
    a = s.angles()[ok]
    assert np.all(np.abs(s.ranges[ok] - 3.0 / np.cos(a)) <=
                  wall_tolerance(a, s.angle_increment, 3.0))
    # nothing in the band: all beams invalid (NaN), never zero
    far = lidar.scan(np.zeros((H, W), np.float32), 0.0)
    assert np.all(np.isnan(far.ranges))
    # A wall beyond range_max on the left half, too near on the right half of the
    # remaining: REP 117's +inf (the SLAM clears free space along it; NaN cleared none)
    # and -inf; a hole stays NaN.
    d = np.full((H, W), 3.0, np.float32)
    d[:, : W // 4] = 9.0  # beyond the default 8 m
    d[:, W // 4: W // 2] = 0.0  # no depth
    d[:, 3 * W // 4:] = 0.05  # nearer than range_min
    wide = VirtualLidar(cam, R_BASE_OPTICAL, VirtualLidarOptions(height_m=-0.3, band_m=0.6))
    s = wide.scan(d, 0.0)
    left = s.angles() > np.radians(25)  # image left is base +y, positive bearing
    right = s.angles() < -np.radians(25)
    assert np.all(np.isposinf(s.ranges[left]))
    assert np.all(np.isneginf(s.ranges[right]))
    hole = (s.angles() > np.radians(3)) & (s.angles() < np.radians(15))
    assert hole.any() and np.all(np.isnan(s.ranges[hole]))


def test_plane_outside_the_view_is_an_error(tmp_path):
    make_tum(tmp_path / "tum")
    opts = TumRgbdOptions(camera=CAM, lidar=VirtualLidarOptions(height_m=5.0))
    with pytest.raises(IngestError, match="height_m"):
        read_tum_rgbd(tmp_path / "tum", opts)


def test_tum_errors_name_file_and_line(tmp_path):
    make_tum(tmp_path / "a")
    lines = (tmp_path / "a" / "rgb.txt").read_text().splitlines()
    lines[3], lines[4] = lines[4], lines[3]
    (tmp_path / "a" / "rgb.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(IngestError) as e:
        read_tum_rgbd(tmp_path / "a", TumRgbdOptions(camera=CAM))
    assert "rgb.txt" in str(e.value) and "line 5 " in str(e.value)
    rec = read_tum_rgbd(tmp_path / "a", TumRgbdOptions(camera=CAM), on_non_monotonic="drop")
    assert rec.dropped == {"rgb.txt": 1}

    make_tum(tmp_path / "b")
    (tmp_path / "b" / "depth.txt").write_text("1305031102.5 depth/missing.png\n")
    with pytest.raises(IngestError, match=r"depth.txt:1: depth/missing.png does not exist"):
        read_tum_rgbd(tmp_path / "b", TumRgbdOptions(camera=CAM))

    make_tum(tmp_path / "c")
    with pytest.raises(IngestError, match="64x48 but the camera model 'ros_default' is 640x480"):
        read_tum_rgbd(tmp_path / "c")

    # The ground truth's repeated stamp is named by its line, as rgb.txt's are (was
    # "message 2": the pose count, comments not counted).
    make_tum(tmp_path / "d")
    gt = (tmp_path / "d" / "groundtruth.txt").read_text().splitlines()
    gt[3] = gt[2]  # file line 4 repeats line 3 (two comment lines first)
    (tmp_path / "d" / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    with pytest.raises(IngestError, match=r"groundtruth.txt: stamps are not monotonic: line 4 "):
        read_tum_rgbd(tmp_path / "d", TumRgbdOptions(camera=CAM))


def test_no_groundtruth_uses_a_level_mount(tmp_path):
    make_tum(tmp_path / "tum", gt=False)
    rec = read_tum_rgbd(tmp_path / "tum", TumRgbdOptions(camera=CAM))
    assert rec.groundtruth is None and rec.meta["virtual_lidar"]["level"] == "camera"
    with pytest.raises(IngestError, match="no groundtruth.txt"):
        read_tum_rgbd(tmp_path / "tum", TumRgbdOptions(
            camera=CAM, lidar=VirtualLidarOptions(level="groundtruth")))


def test_a_late_colour_stamp_is_moved_back_and_the_depth_clock_kept(tmp_path):
    """TUM's scans are made from the depth images, so the delay is the colour camera's
    against them: only the colour stamps move (moving both kept them 60 ms apart)."""
    from toolkit.ingest.sync import SyncOptions

    make_tum(tmp_path / "tum", rgb_delay=0.06, rgb_extra=False)
    rec = read_tum_rgbd(tmp_path / "tum", TumRgbdOptions(camera=CAM))
    with pytest.raises(IngestError, match="has a scan within"):  # 55 ms from the scans
        convert(rec, tmp_path / "late")
    res = convert(rec, tmp_path / "fixed", SyncOptions(camera_delay_s=0.06))
    seq = read_sequence(res.root)
    assert len(seq.frames) == 6
    expected = T0 + 0.2 * np.arange(6)
    assert seq.frame_stamps == pytest.approx(expected, abs=1e-6)
    assert [s.stamp for s in seq.scans] == pytest.approx(expected + 0.005, abs=1e-6)


def test_a_file_given_as_the_folder_is_not_called_missing(tmp_path: Path) -> None:
    """A file named as the TUM folder (rgb.txt itself, a bag) was reported as "TUM RGB-D
    folder not found" though it exists."""
    f = tmp_path / "rgb.txt"
    f.write_text("# timestamp filename\n")
    with pytest.raises(IngestError, match=r"rgb.txt: is a file, not a TUM RGB-D folder"):
        read_tum_rgbd(f)
    with pytest.raises(IngestError, match=r"nowhere: TUM RGB-D folder not found"):
        read_tum_rgbd(tmp_path / "nowhere")

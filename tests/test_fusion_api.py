"""The library entry point for one image's lidar scale from the user's own arrays, and the
rig's checks for an extrinsic given the wrong way round."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from toolkit.camera import PinholeCamera
from toolkit.depth.protocol import DepthPrediction
from toolkit.fusion.pipeline import FusionConfig, scale_from_scan
from toolkit.fusion.synthetic import R_BASE_OPTICAL
from toolkit.geometry import inv_se3, se3
from toolkit.sensors import LaserScan, Rig

CAM = PinholeCamera(160, 120, 120.0, 120.0, 79.5, 59.5)
# Laser x forward, z up, 0.1 m below the optical centre (optical: x right, y down, z ahead).
T_CAMERA_LASER = se3(np.array([[0, -1, 0], [0, 0, -1], [1, 0, 0]], float), [0.0, 0.1, 0.0])


def _wall_scan(distance: float = 3.0, n: int = 361) -> LaserScan:
    a = np.linspace(-np.pi, np.pi, n)
    ahead = np.abs(a) < 1.4
    r = np.where(ahead, distance / np.cos(np.where(ahead, a, 0.0)), np.inf)
    return LaserScan(0.0, r.astype(np.float32), -np.pi, 2 * np.pi / (n - 1), 0.05, 20.0)


@pytest.mark.parametrize("method", ["ratio", "clustered", "robust"])
def test_scale_from_scan_recovers_a_known_scale(method: str) -> None:
    """A wall 3 m ahead, predicted at 1 / 2.5 of its depth: every estimator finds 2.5."""
    pred = DepthPrediction(np.full((120, 160), 3.0 / 2.5, np.float32), "relative_depth")
    fp = scale_from_scan(pred, _wall_scan(), CAM, T_CAMERA_LASER, FusionConfig(scale=method))
    assert fp.estimate.quality == "ok" and len(fp.lidar) > 50
    assert fp.estimate.scale == pytest.approx(2.5, rel=1e-4)
    np.testing.assert_allclose(pred.as_depth(fp.estimate.scale, fp.estimate.shift), 3.0,
                               rtol=1e-4)


def test_scans_with_beam_timing_and_upside_down_lasers_are_taken(
        caplog: pytest.LogCaptureFixture) -> None:
    """A ROS scan carries time_increment (refused as "de-skew first", which needs a
    trajectory the caller has none of); a laser mounted upside down is no inverted
    extrinsic."""
    import dataclasses

    pred = DepthPrediction(np.full((120, 160), 3.0 / 2.5, np.float32), "relative_depth")
    timed = dataclasses.replace(_wall_scan(), time_increment=1e-4)
    assert scale_from_scan(pred, timed, CAM, T_CAMERA_LASER).estimate.scale == pytest.approx(
        2.5, rel=1e-4)
    # Upside down: the laser's z points down, so a bearing a reads -a.
    scan = _wall_scan()
    flipped = LaserScan(0.0, scan.ranges.copy(), np.pi, -scan.angle_increment, 0.05, 20.0)
    T_flip = T_CAMERA_LASER @ se3(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 0.0])
    with caplog.at_level(logging.WARNING):
        fp = scale_from_scan(pred, flipped, CAM, T_flip)
    assert fp.estimate.scale == pytest.approx(2.5, rel=1e-4)
    assert "inverted" not in caplog.text


def test_an_inverted_extrinsic_is_named(caplog: pytest.LogCaptureFixture) -> None:
    pred = DepthPrediction(np.full((120, 160), 1.2, np.float32), "relative_depth")
    with caplog.at_level(logging.WARNING):
        scale_from_scan(pred, _wall_scan(), CAM, inv_se3(T_CAMERA_LASER))
    assert "a transform is inverted" in caplog.text


def test_rig_mount_warnings() -> None:
    level = Rig(CAM, se3(R_BASE_OPTICAL, [0.1, 0, 0.4]), se3(np.eye(3), [0.05, 0, 0.2]))
    assert level.mount_warnings() == []
    upside_down = Rig(CAM, level.T_base_camera, se3(np.diag([1.0, -1.0, -1.0]), [0, 0, 0.2]))
    assert upside_down.mount_warnings() == []  # a flipped scanner still scans level
    c, s = np.cos(np.radians(50)), np.sin(np.radians(50))
    tilted = Rig(CAM, level.T_base_camera, se3(np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
                                               [0, 0, 0.2]))
    assert any("tilted 50 deg" in w for w in tilted.mount_warnings())
    body = Rig(CAM, se3(np.eye(3), [0.1, 0, 0.4]), level.T_base_laser)  # camera_link as optical
    assert any("image's down direction is 90 deg" in w for w in body.mount_warnings())


def test_library_calls_name_wrong_shapes_and_colour_ranges() -> None:
    """A 3x3 pose, SE(2) poses, colours in 0..1: clear errors, not an IndexError or a
    reshape message (or a black map)."""
    from toolkit.fusion.cloud import CloudOptions, RayCache, depth_to_points
    from toolkit.fusion.voxel_map import VoxelMap
    from toolkit.geometry import Trajectory

    rays = RayCache(CAM, 2)
    depth = np.full((120, 160), 2.0, np.float32)
    rgb = np.zeros((120, 160, 3), np.uint8)
    with pytest.raises(ValueError, match=r"T_world_camera must be \[4, 4\]"):
        depth_to_points(depth, rgb, rays, np.eye(3), CloudOptions())
    with pytest.raises(ValueError, match="SE\\(2\\) poses\\? se2_to_se3"):
        Trajectory(np.arange(3.0), np.stack([np.eye(3)] * 3))
    pts, col, _ = depth_to_points(depth, rgb, rays, np.eye(4), CloudOptions())
    vm = VoxelMap(0.02)
    with pytest.raises(ValueError, match="colours must be uint8"):
        vm.integrate(pts, col.astype(np.float32) / 255, 0)
    vm.integrate(pts, col, 0)
    assert len(vm.arrays()) > 0

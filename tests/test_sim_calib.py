"""Calibration capture: detectable boards, lidar points on the board plane, exact extrinsic."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from toolkit.camera import PinholeCamera
from toolkit.geometry import se3
from toolkit.sim.calib_capture import capture_calibration


def read_pcd(path: Path) -> np.ndarray:
    lines = path.read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("DATA")) + 1
    header = {line.split()[0]: line.split()[1:] for line in lines[:start] if line[0] != "#"}
    assert header["FIELDS"] == ["x", "y", "z"] and header["DATA"] == ["ascii"]
    pts = np.array([[float(v) for v in line.split()] for line in lines[start:]])
    assert len(pts) == int(header["POINTS"][0])
    return pts


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return capture_calibration(tmp_path_factory.mktemp("calib"), n_views=4, seed=3,
                               board=(11, 8), square=0.05, lidar_noise=0.01)


def test_layout_and_camera(capture: Path) -> None:
    images = sorted((capture / "images").glob("*.png"))
    lasers = sorted((capture / "lasers").glob("*.pcd"))
    assert len(images) == len(lasers) == 4
    # Stamps in nanoseconds, images and scans not simultaneous (paired by nearest stamp).
    ti = np.array([int(p.stem) for p in images])
    tl = np.array([int(p.stem) for p in lasers])
    assert np.all((tl - ti > 5e6) & (tl - ti < 6e7))
    cam = PinholeCamera.from_dict(yaml.safe_load((capture / "camera.yaml").read_text()))
    assert cam.size == (640, 480)


def test_boards_detectable_at_their_true_corners(capture: Path) -> None:
    gt = yaml.safe_load((capture / "groundtruth.yaml").read_text())
    for view in gt["views"]:
        grey = cv2.imread(str(capture / view["image"]), cv2.IMREAD_GRAYSCALE)
        ok, corners = cv2.findChessboardCorners(grey, (11, 8))
        assert ok, view["image"]
        corners = cv2.cornerSubPix(grey, corners, (5, 5), (-1, -1),
                                   (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3))
        c = corners.reshape(-1, 2)
        true = np.array(view["corners_px"])
        # OpenCV may start from either end of the (asymmetric) grid.
        err = min(np.abs(c - true).max(), np.abs(c[::-1] - true).max())
        assert err < 0.5


def test_lidar_board_points_on_the_board_plane(capture: Path) -> None:
    gt = yaml.safe_load((capture / "groundtruth.yaml").read_text())
    T_cl = np.array(gt["T_camera_laser"])
    assert np.allclose(T_cl[:3, :3] @ T_cl[:3, :3].T, np.eye(3), atol=1e-12)
    # The laser sits below and behind the camera, its plane horizontal.
    assert T_cl[1, 3] > 0.1  # 0.2 m lower = +y in the optical frame
    for view in gt["views"]:
        pts = read_pcd(capture / view["scan"])
        assert np.all(pts[:, 2] == 0)
        idx = np.array(view["board_points"])
        assert len(idx) >= 8
        p_cam = pts[idx] @ T_cl[:3, :3].T + T_cl[:3, 3]
        n, d = np.array(view["board_plane_camera"][:3]), view["board_plane_camera"][3]
        dist = p_cam @ n - d
        assert np.abs(dist).max() < 0.045  # 1 cm range noise, never more than 4.5 sigma
        assert np.abs(dist).mean() < 0.015
        # The same plane from the board pose.
        T_cb = np.array(view["T_camera_board"])
        assert np.allclose(T_cb[:3, 2], n) and np.isclose(T_cb[:3, 2] @ T_cb[:3, 3], d)
        # A wrong extrinsic (2 cm shift along the board normal) breaks the agreement.
        bad = se3(np.eye(3), 0.02 * n) @ T_cl
        p_bad = pts[idx] @ bad[:3, :3].T + bad[:3, 3]
        assert abs(np.mean(p_bad @ n - d)) > abs(np.mean(dist)) + 0.01


def test_capture_follows_the_protocol(capture: Path) -> None:
    """Boards lean forward and back, turn left and right, at spread distances."""
    gt = yaml.safe_load((capture / "groundtruth.yaml").read_text())
    T_bc = np.array(gt["T_base_camera"])
    lean, turn, dist = [], [], []
    for view in gt["views"]:
        n_base = T_bc[:3, :3] @ np.array(view["T_camera_board"])[:3, 2]  # board normal
        lean.append(np.degrees(np.arcsin(n_base[2])))  # >0: the board's face tilts up
        turn.append(np.degrees(np.arctan2(n_base[1], n_base[0])))
        dist.append(np.array(view["T_camera_board"])[2, 3])
    lean, turn = np.array(lean), np.array(turn)
    # Forward-left, back-left, forward-right, back-right: every sign in four views.
    assert set(np.sign(lean)) == {-1.0, 1.0} and set(np.sign(turn)) == {-1.0, 1.0}
    assert np.all(np.abs(lean) > 12)  # 20-45 deg about the board's own axis (turn mixes in)
    assert np.ptp(dist) > 0.3  # near and far, not one distance
    assert gt["protocol"]["lean_deg"] == [20.0, 45.0]


def test_capture_is_deterministic(tmp_path: Path) -> None:
    a = capture_calibration(tmp_path / "a", n_views=2, seed=5)
    b = capture_calibration(tmp_path / "b", n_views=2, seed=5)
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files and files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    for f in files:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f

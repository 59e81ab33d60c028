"""COLMAP text model export: exact round trip, COLMAP's pose convention, pycolmap agrees."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_geometry import half_turns  # the tests folder is on sys.path

from toolkit.camera import PinholeCamera
from toolkit.geometry import inv_se3, se3
from toolkit.io.colmap_text import (
    ColmapImage,
    camera_from_colmap,
    camera_to_colmap,
    format_cameras,
    format_images,
    format_points,
    model_from_poses,
    pose_to_colmap,
    read_colmap_model,
    write_colmap_model,
    write_poses_as_colmap,
)


def _poses(n: int = 7, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    T[:, :3, 3] = rng.uniform(-5, 5, (n, 3))
    return T


def test_pose_convention_hand_computed() -> None:
    # A camera at (1, 2, 3) looking along world +x (optical z = world x, x = -y, y = -z).
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    T[:3, 3] = [1.0, 2.0, 3.0]
    q, t = pose_to_colmap(T)
    # cam_from_world: R = T[:3,:3]^T, t = -R c = (2, 3, -1) by hand.
    np.testing.assert_allclose(t, [2.0, 3.0, -1.0], atol=1e-15)
    # Hamilton wxyz of M = R^T = [[0,-1,0],[0,0,-1],[1,0,0]]: w = sqrt(1 + tr M) / 2 = 0.5,
    # x = (M21 - M12) / 4w = 0.5, y = (M02 - M20) / 4w = -0.5, z = (M10 - M01) / 4w = 0.5.
    np.testing.assert_allclose(q, [0.5, 0.5, -0.5, 0.5], atol=1e-15)


def test_a_half_turn_is_written_with_one_quaternion_sign_however_it_was_computed(
        tmp_path: Path) -> None:
    cam = PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5, np.zeros(5))
    for k, group in enumerate(half_turns()):
        poses = np.stack([se3(R, [1.0, -2.0, 3.0]) for R in group])  # [n, 4, 4]
        texts = set()
        for T in poses:
            q, t = pose_to_colmap(T)
            assert q[0] == 0 and q[1 + np.flatnonzero(q[1:])[0]] > 0
            line = format_images([ColmapImage(1, q, t, 1, "a.png")]).splitlines()[4]
            texts.add(" ".join(line.split()[1:5]))  # QW QX QY QZ (t differs by rounding)
        assert len(texts) == 1, texts
        folder = write_poses_as_colmap(tmp_path / str(k), cam, [f"{i}.png" for i in
                                                                range(len(poses))], poses)
        back = np.stack([im.T_world_camera for im in read_colmap_model(folder).images])
        np.testing.assert_allclose(back, poses, atol=1e-15)


def test_round_trip_is_exact_and_centres_are_minus_rt_t(tmp_path: Path) -> None:
    cam = PinholeCamera(640, 480, 525.0, 524.5, 319.25, 239.75, np.array([0.1, -0.05, 1e-3,
                                                                          -2e-3, 0.0]))
    poses = _poses()
    names = [f"{i:06d}.png" for i in range(len(poses))]
    rng = np.random.default_rng(1)
    pts, cols = rng.normal(size=(50, 3)), rng.integers(0, 256, (50, 3)).astype(np.uint8)
    folder = write_poses_as_colmap(tmp_path / "m", cam, names, poses, pts, cols)
    m = read_colmap_model(folder)
    # Text equality after a second write: nothing is lost or rounded on the way.
    assert format_cameras(m.cameras) == (folder / "cameras.txt").read_text()
    assert format_images(m.images) == (folder / "images.txt").read_text()
    assert format_points(m) == (folder / "points3D.txt").read_text()
    assert m.camera(1) == cam
    assert [im.name for im in m.images] == names
    assert [im.image_id for im in m.images] == list(range(1, len(poses) + 1))
    np.testing.assert_array_equal(m.points, pts)
    np.testing.assert_array_equal(m.colors, cols)
    for im, T in zip(m.images, poses, strict=True):
        R = im.T_camera_world[:3, :3]
        np.testing.assert_allclose(-R.T @ im.tvec, T[:3, 3], atol=1e-12)
        np.testing.assert_allclose(im.center, T[:3, 3], atol=1e-12)
        np.testing.assert_allclose(im.T_world_camera, T, atol=1e-12)
        assert im.qvec[0] >= 0


def test_principal_point_uses_colmap_pixel_corner_origin() -> None:
    cam = PinholeCamera.from_fov(320, 240, 60.0)  # cx = 159.5 (centre of 320 px, OpenCV)
    model, params = camera_to_colmap(cam)
    assert model == "PINHOLE"
    assert params[2:] == [160.0, 120.0]  # COLMAP: image centre = width / 2
    assert camera_from_colmap(model, 320, 240, params) == cam
    k3 = PinholeCamera(320, 240, 300.0, 300.0, 160.0, 120.0, np.array([0.1, 0.01, 0, 0, 0.002]))
    assert camera_to_colmap(k3)[0] == "FULL_OPENCV"
    assert camera_from_colmap(*[camera_to_colmap(k3)[0], 320, 240, camera_to_colmap(k3)[1]]) == k3
    with pytest.raises(ValueError, match="pinhole model"):
        camera_from_colmap("FISHEYE_FOV", 320, 240, [1, 2, 3, 4, 5])


def test_pycolmap_reads_our_model_and_we_read_its_output(tmp_path: Path) -> None:
    pycolmap = pytest.importorskip("pycolmap")
    cam = PinholeCamera(320, 240, 250.0, 251.0, 158.0, 121.0)
    poses = _poses(5)
    names = [f"img_{i}.png" for i in range(5)]
    ours = write_poses_as_colmap(tmp_path / "ours", cam, names, poses,
                                 np.zeros((3, 3)), np.full((3, 3), 200, np.uint8))
    rec = pycolmap.Reconstruction(ours)
    assert rec.num_reg_images() == 5 and rec.num_points3D() == 3
    for im in rec.images.values():
        T = poses[names.index(im.name)]
        np.testing.assert_allclose(im.projection_center(), T[:3, 3], atol=1e-9)
        cfw = im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world
        np.testing.assert_allclose(cfw.matrix(), inv_se3(T)[:3], atol=1e-9)
        # COLMAP projects a point seen at our pixel (u, v) to (u + 0.5, v + 0.5).
        X = T[:3, :3] @ np.array([0.3, -0.2, 2.0]) + T[:3, 3]
        uv, _ = cam.project(np.array([[0.3, -0.2, 2.0]]))
        np.testing.assert_allclose(im.project_point(X), uv[0] + 0.5, atol=1e-9)
    # pycolmap's own writer (it adds rigs.txt and frames.txt) reads back to the same poses.
    (tmp_path / "theirs").mkdir()
    rec.write_text(tmp_path / "theirs")
    m = read_colmap_model(tmp_path / "theirs")
    assert m.camera(1) == cam
    for im in m.images:
        np.testing.assert_allclose(im.T_world_camera, poses[names.index(im.name)], atol=1e-9)


def test_observations_and_tracks_round_trip(tmp_path: Path) -> None:
    cam = PinholeCamera.from_fov(100, 80, 70.0)
    m = model_from_poses(cam, ["a.png", "b.png"], _poses(2), np.ones((1, 3)))
    m.images[0].xys = np.array([[10.5, 20.25], [30.0, 40.0]])
    m.images[0].point3d_ids = np.array([1, -1])
    m.tracks = [np.array([[1, 0]])]
    write_colmap_model(tmp_path, m)
    r = read_colmap_model(tmp_path)
    np.testing.assert_array_equal(r.images[0].xys, m.images[0].xys)
    np.testing.assert_array_equal(r.images[0].point3d_ids, [1, -1])
    assert len(r.images[1].xys) == 0
    np.testing.assert_array_equal(r.tracks[0], [[1, 0]])
    with pytest.raises(ValueError, match="space"):
        format_images(model_from_poses(cam, ["a b.png"], _poses(1)).images)


def test_integer_colours_of_any_width_are_0_to_255_and_out_of_range_is_refused():
    cam = PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5)
    pts = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 2.0]])
    cols = np.array([[200, 100, 50], [0, 255, 7]])  # numpy's default int64
    m = model_from_poses(cam, ["a.png"], np.eye(4)[None], pts, cols)
    np.testing.assert_array_equal(m.colors, cols.astype(np.uint8))
    m = model_from_poses(cam, ["a.png"], np.eye(4)[None], pts, np.array([[1.0, 0.5, 0], [0, 0, 0]]))
    np.testing.assert_array_equal(m.colors, [[255, 128, 0], [0, 0, 0]])
    with pytest.raises(ValueError, match="0..255"):
        model_from_poses(cam, ["a.png"], np.eye(4)[None], pts, cols * 2)
    with pytest.raises(ValueError, match="uint8"):
        model_from_poses(cam, ["a.png"], np.eye(4)[None], pts, cols.astype(np.float32))

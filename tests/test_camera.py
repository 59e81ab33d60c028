"""PinholeCamera against OpenCV, with distortion."""

import re

import cv2
import numpy as np
import pytest

from toolkit.camera import PinholeCamera

DIST = np.array([0.11418, 0.19343, -0.00268, 0.00372, -1.09540])  # a real lens (ACFR)


@pytest.fixture
def cam() -> PinholeCamera:
    return PinholeCamera(640, 480, 519.268, 518.894, 331.112, 229.434, DIST)


def points_in_view(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    z = rng.uniform(0.5, 8.0, n)
    x = rng.uniform(-0.5, 0.5, n) * z
    y = rng.uniform(-0.4, 0.4, n) * z
    return np.stack([x, y, z], -1)


def test_project_matches_cv2(cam):
    P = points_in_view(500)
    uv, z = cam.project(P)
    ref, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    assert np.max(np.abs(uv - ref.reshape(-1, 2))) < 1e-6
    assert np.allclose(z, P[:, 2])


def test_undistort_matches_cv2(cam):
    uv, _ = cam.project(points_in_view(500, 1))
    ours = cam.undistort_pixels(uv)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    ref = cv2.undistortPoints(uv.reshape(-1, 1, 2), cam.K, cam.dist, None, None, cam.K, crit)
    assert np.max(np.abs(ours - ref.reshape(-1, 2))) < 1e-6


def test_project_backproject_round_trip(cam):
    P = points_in_view(500, 2)
    uv, z = cam.project(P)
    assert np.max(np.abs(cam.backproject(uv, z) - P)) < 1e-6
    # And pixel -> ray -> pixel.
    uv2, _ = cam.project(cam.backproject(uv, np.ones(len(uv))))
    assert np.max(np.abs(uv2 - uv)) < 1e-6


def test_behind_camera_is_nan_and_in_image(cam):
    uv, _ = cam.project(np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 2.0], [100.0, 0.0, 1.0]]))
    assert np.all(np.isnan(uv[0]))
    assert cam.in_image(uv).tolist() == [False, True, False]


def test_undistort_image_agrees_with_cv2(cam):
    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (480, 640, 3), dtype=np.uint8)
    ref = cv2.undistort(img, cam.K, cam.dist, None, cam.K)
    assert np.array_equal(cam.undistort_image(img), ref)
    # A point seen through the lens lands, after undistortion, where the ideal camera puts it.
    ideal = cam.undistorted()
    P = points_in_view(20, 3)
    uv_d, _ = cam.project(P)
    uv_i, _ = ideal.project(P)
    assert np.max(np.abs(cam.undistort_pixels(uv_d) - uv_i)) < 1e-6


def test_backproject_depth_image_plane():
    cam = PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5)
    depth = np.full((48, 64), 2.0, np.float32)
    pts = cam.backproject_depth(depth)
    assert np.allclose(pts[..., 2], 2.0)
    assert np.allclose(pts[23, 31], [(31 - 31.5) / 50 * 2, (23 - 23.5) / 50 * 2, 2.0])


def test_conversions(cam):
    model, params = cam.to_colmap()
    # COLMAP's pixel centres sit at +0.5.
    assert model == "FULL_OPENCV" and params[:4] == [cam.fx, cam.fy, cam.cx + 0.5, cam.cy + 0.5]
    assert cam.undistorted().to_colmap()[0] == "PINHOLE"
    no_k3 = PinholeCamera(640, 480, 500, 500, 320, 240, [0.1, -0.05, 0.001, 0.002, 0.0])
    assert no_k3.to_colmap() == ("OPENCV", [500.0, 500.0, 320.5, 240.5, 0.1, -0.05, 0.001, 0.002])
    assert cam.colmap_line(3).startswith("3 FULL_OPENCV 640 480 519.268")
    o3d_cam = cam.to_open3d()
    assert np.allclose(np.asarray(o3d_cam.intrinsic_matrix), cam.K)
    assert PinholeCamera.from_dict(cam.to_dict()) == cam


def test_scaled_camera_projects_consistently(cam):
    half = cam.undistorted().scaled(320, 240)
    P = points_in_view(50, 4)
    uv_full, _ = cam.undistorted().project(P)
    uv_half, _ = half.project(P)
    # Pixel centres: u_half + 0.5 = (u_full + 0.5) / 2.
    assert np.allclose(uv_half + 0.5, (uv_full + 0.5) / 2, atol=1e-9)


def test_rejects_bad_intrinsics():
    with pytest.raises(ValueError, match="focal"):
        PinholeCamera(640, 480, 0.0, 500, 320, 240)
    with pytest.raises(ValueError, match="size"):
        PinholeCamera(0, 480, 500, 500, 320, 240)
    # Non-finite values fail here, not in a LinAlgError far from the file that gave them.
    with pytest.raises(ValueError, match="cx must be finite"):
        PinholeCamera(640, 480, 500, 500, float("nan"), 240)
    with pytest.raises(ValueError, match="distortion .* finite"):
        PinholeCamera(640, 480, 500, 500, 320, 240, np.array([np.nan, 0, 0, 0, 0]))


def test_from_K_refuses_a_transposed_or_misshapen_matrix(caplog):
    """A transposed K read as cx = cy = 0, a 4x4 identity as fx = 1, without a word."""
    import logging

    K = np.array([[500.0, 0, 319.5], [0, 505.0, 239.5], [0, 0, 1]])
    cam = PinholeCamera.from_K(K, 640, 480)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (500.0, 505.0, 319.5, 239.5)
    with pytest.raises(ValueError, match="transposed"):
        PinholeCamera.from_K(K.T, 640, 480)
    with pytest.raises(ValueError, match=r"\[3, 3\]"):
        PinholeCamera.from_K(np.eye(4), 640, 480)
    skewed = K.copy()
    skewed[0, 1] = 2.0
    with caplog.at_level(logging.WARNING):
        PinholeCamera.from_K(skewed, 640, 480)
    # Dropping skew s moves a pixel by s (v - cy) / fy: 2 * 240 / 505 at the bottom row.
    assert "skew 2" in caplog.text and "up to 0.95 px off" in caplog.text


def test_camera_mappings_name_their_lens_model():
    """An empty ``distortion:`` is none; another lens model's coefficients (a fisheye's
    k1..k4 read as k1 k2 p1 p2) are refused; rational_polynomial with k4-k6 zero is ours."""
    base = {"width": 640, "height": 480, "fx": 500, "fy": 500, "cx": 319.5, "cy": 239.5}
    assert not PinholeCamera.from_dict({**base, "distortion": None}).dist.any()
    five = [0.1, -0.05, 0.001, -0.002, 0.01]
    for model in ("pinhole", "plumb_bob", "radtan", None):
        cam = PinholeCamera.from_dict({**base, "distortion": five, "distortion_model": model})
        assert cam.dist.tolist() == five
    cam = PinholeCamera.from_dict({**base, "distortion": [*five, 0, 0, 0],
                                   "distortion_model": "rational_polynomial"})
    assert cam.dist.tolist() == five
    for key, model in (("distortion_model", "equidistant"), ("model", "OPENCV_FISHEYE")):
        with pytest.raises(ValueError, match=f"field '{key}' is"):
            PinholeCamera.from_dict({**base, "distortion": [*five, 0.3, 0, 0], key: model})
    with pytest.raises(ValueError, match=r"non-zero past k1 k2 p1 p2 k3 \(distortion\[5\] = 0.3\)"):
        PinholeCamera.from_dict({**base, "distortion": [*five, 0.3, 0, 0],
                                 "distortion_model": "rational_polynomial"})
    cam = PinholeCamera(640, 480, 500, 500, 319.5, 239.5, np.array(five))
    assert PinholeCamera.from_dict(cam.to_dict()) == cam  # round trip
    for key in ("distorsion", "distortion_coeffs", "distortion_coefficients"):
        with pytest.raises(ValueError, match=f"unknown key.*{key}.*'distortion'"):
            PinholeCamera.from_dict({**base, key: five})


@pytest.mark.parametrize("model, tail", [
    ("plumb_bob", [0, 0, 0]), (None, [0, 0, 0]),
    ("rational_polynomial", [0] * 7), ("rational_polynomial", [0] * 9),
    ("plumb_bob", [0] * 9),
])
def test_camera_mapping_takes_opencv_lists_with_nothing_past_k3(model, tail):
    """OpenCV's 8-, 12- and 14-term lists with zeros past k3 are the 5-term lens (as the
    CameraInfo reader takes them): plumb_bob's 8 were refused with "k1 k2 p1 p2 k3 at most",
    rational_polynomial's 12 and 14 as another lens model."""
    base = {"width": 640, "height": 480, "fx": 500, "fy": 500, "cx": 319.5, "cy": 239.5}
    five = [0.1, -0.05, 0.001, -0.002, 0.01]
    cam = PinholeCamera.from_dict({**base, "distortion": [*five, *tail],
                                   "distortion_model": model})
    assert cam.dist.tolist() == five


@pytest.mark.parametrize("model, d, terms", [
    ("plumb_bob", [0.1, -0.05, 0, 0, 0.01, 0.3, 0, 0], "distortion[5] = 0.3"),
    (None, [0.1, -0.05, 0, 0, 0.01, 0, 0, 0.2], "distortion[7] = 0.2"),
    ("rational_polynomial", [0.1, -0.05, 0, 0, 0.01, 0, 0, 0, 0.004, 0, 0, 0],
     "distortion[8] = 0.004"),
    ("radtan", [0.1, -0.05, 0, 0, 0.01] + [0] * 7 + [0.01, 0.02],
     "distortion[12] = 0.01, distortion[13] = 0.02"),
])
def test_camera_mapping_names_the_terms_past_k3(model, d, terms):
    """A lens with terms past k3 is refused naming the field, the terms and the fix; for
    plumb_bob's 8 the message was a bare "distortion has 8 coefficients"."""
    base = {"width": 640, "height": 480, "fx": 500, "fy": 500, "cx": 319.5, "cy": 239.5}
    with pytest.raises(ValueError) as err:
        PinholeCamera.from_dict({**base, "distortion": d, "distortion_model": model})
    text = str(err.value)
    assert text.startswith(f"field 'distortion' has {len(d)} coefficients, non-zero past "
                           f"k1 k2 p1 p2 k3 ({terms})"), text
    assert "Fix: calibrate with that model" in text, text


def test_projection_and_transforms_refuse_points_of_the_wrong_shape():
    from toolkit.eval.geometry import geometry_metrics
    from toolkit.geometry import transform_points

    cam = PinholeCamera(100, 80, 100.0, 100.0, 50.0, 40.0)
    pts = np.array([[0.1, 0.2, 2.0], [0.0, 0.0, 1.0], [0.3, -0.1, 3.0]])
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        cam.project(pts[:, :2])  # a scan's [N, 2] laser points
    with pytest.raises(ValueError, match="4x4"):
        transform_points(np.eye(4), pts[:, :2])
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        geometry_metrics(pts.T[:, :2], pts)  # [3, N]
    uv, z = cam.project(pts)
    assert uv.shape == (3, 2) and np.allclose(z, pts[:, 2])


def test_rays_past_the_distortion_peak_do_not_fold_back_into_the_image(cam):
    """With k3 < 0 the distorted radius peaks (37 deg off-axis for this lens) and turns
    back: a ray 45 deg off-axis landed inside the image, on the calibration board."""
    r2 = cam.max_radius2()
    assert 0.5 < r2 < 0.7  # undistorted radius 0.765
    k1, k2, _, _, k3 = DIST
    s = np.array([r2 * 0.99, r2, r2 * 1.01])
    slope = 1 + 3 * k1 * s + 5 * k2 * s**2 + 7 * k3 * s**3
    assert slope[0] > 0 and abs(slope[1]) < 1e-9 and slope[2] < 0
    off_axis = np.radians([30.0, 45.0])
    P = np.stack([np.tan(off_axis), np.zeros(2), np.ones(2)], -1)
    uv, _ = cam.project(P)
    assert cam.in_image(uv[:1]).all() and np.isnan(uv[1]).all()
    assert PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0).max_radius2() == np.inf


def test_optimisers_may_project_past_the_peak(cam):
    P = np.array([[np.tan(np.radians(45.0)), 0.0, 1.0]])
    assert np.isnan(cam.project(P)[0]).all()
    assert np.isfinite(cam.project(P, past_peak=True)[0]).all()
    inside = points_in_view(50)  # the same pixels either way where the model is regular
    np.testing.assert_array_equal(cam.project(inside, past_peak=True)[0], cam.project(inside)[0])


def test_every_pixel_of_a_strong_barrel_lens_has_its_ray():
    """OpenCV's fixed-point undistortion does not converge in the corners of a strong
    barrel lens (156 pixels had no ray, others were 0.05 px off); the distortion grows
    with the radius everywhere here, so every pixel has one."""
    cam = PinholeCamera(640, 480, 320.0, 320.0, 319.5, 239.5, [-0.35, 0.12, 0, 0, 0])
    assert cam.max_radius2() == float("inf")
    rays = cam.pixel_rays().reshape(-1, 3)
    assert np.isfinite(rays).all()
    u, v = np.meshgrid(np.arange(640.0), np.arange(480.0))
    back, _ = cam.project(rays)
    assert np.abs(back - np.stack([u.ravel(), v.ravel()], -1)).max() < 1e-6


def test_camera_fields_name_what_is_wrong():
    base = {"width": 640, "height": 480, "fx": 500.0, "fy": 500.0, "cx": 319.5, "cy": 239.5}
    for key, value, match in (("fx", "500", "field 'fx' is '500': give a number"),
                              ("fy", None, "field 'fy' is None"),
                              ("width", "640px", "field 'width' is '640px': give a number of "
                                                 "pixels"),
                              ("height", 480.7, "height must be a whole number of pixels")):
        with pytest.raises(ValueError, match=match):
            PinholeCamera.from_dict({**base, key: value})
    assert PinholeCamera.from_dict({**base, "width": 640.0}).width == 640


def test_no_pixels_undistort_and_backproject_to_no_rays(cam):
    # OpenCV returns None for an empty array: a frame whose lidar returns all fall outside
    # the image would stop the fusion.
    assert cam.undistort_points(np.zeros((0, 2))).shape == (0, 2)
    assert cam.backproject(np.zeros((0, 2)), np.zeros(0)).shape == (0, 3)


def test_distortion_under_other_tools_names_is_refused():
    """ROS's D, Kalibr / ORB-SLAM's k1 k2 p1 p2 keys or 'coeffs' were ignored and the lens
    taken as undistorted: with k1 = -0.3 the image corner was modelled 56 px off."""
    base = {"model": "pinhole", "width": 640, "height": 480, "fx": 525.0, "fy": 525.0,
            "cx": 319.5, "cy": 239.5}
    coeffs = [-0.3, 0.1, 0.0, 0.0, 0.0]
    for extra, named in (({"D": coeffs}, "['D']"), ({"coeffs": coeffs}, "['coeffs']"),
                         ({"k1": -0.3, "k2": 0.1, "p1": 0.0, "p2": 0.0},
                          "['k1', 'k2', 'p1', 'p2']"),
                         ({"K": [[525, 0, 319.5], [0, 525, 239.5], [0, 0, 1]]}, "['K']")):
        with pytest.raises(ValueError, match=rf"unknown key\(s\) {re.escape(named)}: the lens "
                                             r"distortion is read only from 'distortion'"):
            PinholeCamera.from_dict({**base, **extra})
    cam = PinholeCamera.from_dict({**base, "distortion": coeffs})
    # The corner ray lands where OpenCV's lens puts it.
    ray = np.array([[(0 - 319.5) / 525, (0 - 239.5) / 525, 1.0]])
    ref = cv2.projectPoints(ray, np.zeros(3), np.zeros(3), cam.K, np.array(coeffs))[0]
    assert np.allclose(cam.project(ray)[0], ref.reshape(-1, 2), atol=1e-6)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_pixel_index_puts_k_minus_half_to_k_plus_half_in_pixel_k(dtype):
    """Pixel k spans [k - 0.5, k + 0.5), in_image's half-open span; np.rint rounds halves
    to even (0.5 -> 0, 2.5 -> 2), and floor(u + 0.5) rounds 0.49999999999999994 up."""
    from toolkit.camera import pixel_index

    below_half = np.nextafter(dtype(0.5), dtype(0.0))
    u = np.array([-0.5, 0.5, 1.5, 2.5, 3.5, below_half, 1.0, -0.25, 62.5,
                  np.nextafter(dtype(63.5), dtype(0.0))], dtype)
    want = np.array([0, 1, 2, 3, 4, 0, 1, 0, 63, 63])
    np.testing.assert_array_equal(pixel_index(u), want)
    # Any shape; a column of (u, v) pairs as well.
    np.testing.assert_array_equal(pixel_index(np.stack([u, u[::-1]], 1)),
                                  np.stack([want, want[::-1]], 1))
    assert pixel_index(u).dtype == np.int64

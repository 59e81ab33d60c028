"""Simulator rendering against known answers: box rooms, planes, cylinders, textures."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import uniform_filter

from toolkit.camera import PinholeCamera
from toolkit.geometry import se2_to_se3, se3
from toolkit.sensors import LaserScan
from toolkit.sim.people import HEAD_R, HEAD_Z, TORSO_R, Walker, primitives_at
from toolkit.sim.scene import Box, Scene, Surface
from toolkit.sim.sensors import R_BASE_OPTICAL, CameraRenderer, CameraSpec, LidarRenderer, LidarSpec
from toolkit.sim.textures import MATERIAL_ID, build_texture_bank

# Interior of the box room: x in [0, X], y in [0, Y], z in [0, Z] (inner wall faces).
X, Y, Z = 6.0, 4.0, 2.5


def box_room(wall: str = "plaster", brick_wall: bool = False) -> list[Box]:
    t = 0.1
    east = Surface("brick", (1.0, 0.7, 0.6)) if brick_wall else Surface(wall)
    return [
        Box([X / 2, Y / 2, -t / 2], [X + 2 * t, Y + 2 * t, t], surface=Surface("wood"),
            label="floor"),
        Box([X / 2, Y / 2, Z + t / 2], [X + 2 * t, Y + 2 * t, t], surface=Surface("ceiling"),
            label="ceiling"),
        Box([-t / 2, Y / 2, Z / 2], [t, Y, Z], surface=Surface(wall), label="wall"),
        Box([X + t / 2, Y / 2, Z / 2], [t, Y, Z], surface=east, label="wall"),
        Box([X / 2, -t / 2, Z / 2], [X + 2 * t, t, Z], surface=Surface(wall), label="wall"),
        Box([X / 2, Y + t / 2, Z / 2], [X + 2 * t, t, Z], surface=Surface(wall), label="wall"),
    ]


@pytest.fixture(scope="module")
def room() -> Scene:
    return Scene.from_boxes(box_room(brick_wall=True), build_texture_bank(0))


def ray_box_interior(o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """[N] ray parameter where rays o + t d (d [N, 3]) leave the room's interior box."""
    lo, hi = np.zeros(3), np.array([X, Y, Z])
    with np.errstate(divide="ignore", invalid="ignore"):
        t_hi = np.where(d > 0, (hi - o) / d, np.inf)
        t_lo = np.where(d < 0, (lo - o) / d, np.inf)
    return np.minimum(t_hi, t_lo).min(axis=1)


def test_lidar_ranges_equal_analytic_wall_distances(room: Scene) -> None:
    spec = LidarSpec(noise_std=0.0, dropout=0.0)
    T_world_laser = se2_to_se3(1.3, 0.7, 0.3, z=0.25)
    ret = LidarRenderer(room, spec).render(T_world_laser, noisy=False)
    a = spec.angles() + 0.3
    d = np.column_stack([np.cos(a), np.sin(a), np.zeros_like(a)])
    expected = ray_box_interior(np.array([1.3, 0.7, 0.25]), d)
    # In memory (float64): exact up to rounding.
    assert np.max(np.abs(ret.true_ranges - expected)) < 1e-9
    assert np.max(np.abs(ret.ranges - expected)) < 1e-9
    # As stored (float32 ranges in a LaserScan): still within 1e-6 m up to 12 m.
    scan = LaserScan(0.0, ret.ranges.astype(np.float32), spec.angle_min, spec.angle_increment,
                     spec.range_min, spec.range_max)
    assert np.max(np.abs(scan.ranges.astype(np.float64) - expected)) < 1e-6
    assert not ret.dynamic.any()


def test_lidar_noise_dropouts_and_range_limits(room: Scene) -> None:
    spec = LidarSpec(noise_std=0.01, dropout=0.05, range_max=3.0)
    rng = np.random.default_rng(1)
    r = LidarRenderer(room, spec)
    T = se2_to_se3(1.0, 1.0, 0.0, z=0.25)
    rets = [r.render(T, rng=rng) for _ in range(40)]
    ranges = np.stack([x.ranges for x in rets])
    true = rets[0].true_ranges
    ok = np.isfinite(ranges)
    err = (ranges - true)[ok]
    assert abs(err.std() - 0.01) < 0.002
    assert np.isnan(ranges).mean() > 0.03  # dropouts are NaN, never zero
    assert np.all(ranges[np.isposinf(ranges)] != 0)
    far = ranges[:, true > 3.1]  # beyond range_max: +inf (or a NaN dropout)
    assert np.all(np.isposinf(far) | np.isnan(far)) and np.isposinf(far).mean() > 0.9
    assert not np.any(ranges == 0)


def test_depth_equals_ray_plane_distance(room: Scene) -> None:
    cam = PinholeCamera(160, 120, 100.0, 100.0, 79.5, 59.5)
    # Turned and tilted so that no plane is axis-aligned in the image.
    T_wc = se3(_yaw(0.4) @ R_BASE_OPTICAL @ np.array(
        [[1, 0, 0], [0, np.cos(0.2), -np.sin(0.2)], [0, np.sin(0.2), np.cos(0.2)]]),
        [1.0, 1.5, 1.2])
    img = CameraRenderer(room, cam).render(T_wc, want_material=True)
    rays_c = cam.pixel_rays().reshape(-1, 3)  # z = 1
    rays_w = rays_c @ T_wc[:3, :3].T
    expected = ray_box_interior(T_wc[:3, 3], rays_w).reshape(cam.height, cam.width)
    # z-depth: the ray parameter of a camera ray with z = 1 (not the ray length).
    err = np.abs(img.depth - expected)
    assert np.max(err / expected) < 2e-6
    assert np.all(img.material >= 0)


def test_textures_visible_and_plain_walls_plain(room: Scene) -> None:
    cam = PinholeCamera(320, 240, 200.0, 200.0, 159.5, 119.5)
    r = CameraRenderer(room, cam)
    # Facing the brick east wall, with the plaster north wall in view on the left.
    T_wc = se3(_yaw(0.6) @ R_BASE_OPTICAL, [2.5, 1.2, 1.2])
    img = r.render(T_wc, want_material=True)
    grey = img.rgb.astype(np.float64).mean(-1)
    mean = uniform_filter(grey, 5)
    local_std = np.sqrt(np.maximum(uniform_filter(grey**2, 5) - mean**2, 0))
    inner = np.zeros_like(grey, bool)
    inner[3:-3, 3:-3] = True
    mat = img.material
    # Away from material boundaries only.
    brick = (uniform_filter((mat == MATERIAL_ID["brick"]).astype(float), 7) == 1) & inner
    plain = (uniform_filter((mat == MATERIAL_ID["plaster"]).astype(float), 7) == 1) & inner
    assert brick.sum() > 1000 and plain.sum() > 1000
    brick_std = np.median(local_std[brick])
    plain_std = np.median(local_std[plain])
    assert brick_std > 4.0
    assert plain_std < 1.5
    assert brick_std > 4.0 * plain_std


def _yaw(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def walker_at(x: float, y: float, heading: float) -> Walker:
    """A person standing still (legs side by side across ``heading``)."""
    t = np.array([0.0, 100.0])
    return Walker(t, np.array([[x, y], [x, y]]), np.full(2, heading), np.zeros(2),
                  np.array([[0.2, 0.2, 0.4], [0.8, 0.1, 0.1], [0.9, 0.7, 0.6]]),
                  np.array([[x, y], [x, y]]))


def test_people_in_depth_masks_and_beams(room: Scene) -> None:
    spec = CameraSpec(width=320, height=240, fx=150.0, fy=150.0, pitch_deg=0.0)
    cam = spec.camera()
    T_wb = se2_to_se3(0.3, 2.0, 0.0)
    T_wc = T_wb @ spec.T_base_camera()
    # Facing +y: legs at x = 3 -+ 0.1, torso and head centred on (3, 2).
    prims = primitives_at([walker_at(3.0, 2.0, np.pi / 2)], 0.0)
    img = CameraRenderer(room, cam).render(T_wc, prims)
    o = T_wc[:3, 3]
    for z_target, radius, (z0, z1) in ((1.2, TORSO_R, (0.85, 1.45)), (HEAD_Z, None, (0.0, 0.0))):
        u = 160
        v = int(round(cam.cy - cam.fy * (z_target - o[2]) / (3.0 - o[0] - 0.15)))
        d = T_wc[:3, :3] @ np.array([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0])
        if radius is not None:  # vertical cylinder about (3, 2)
            oc = o[:2] - [3.0, 2.0]
            a, b, c = d[:2] @ d[:2], oc @ d[:2], oc @ oc - radius**2
            t = (-b - np.sqrt(b * b - a * c)) / a
            assert z0 <= o[2] + t * d[2] <= z1
        else:  # head sphere
            oc = o - [3.0, 2.0, HEAD_Z]
            a, b, c = d @ d, oc @ d, oc @ oc - HEAD_R**2
            t = (-b - np.sqrt(b * b - a * c)) / a
        assert 0 <= v < cam.height and img.dynamic[v, u]
        assert abs(img.depth[v, u] - t) < 1e-4  # t is the z-depth (camera rays have z = 1)
    assert not img.dynamic[:, :40].any() and not img.dynamic[:, -40:].any()
    assert 0.01 < img.dynamic.mean() < 0.3

    lspec = LidarSpec(noise_std=0.0, dropout=0.0)
    ret = LidarRenderer(room, lspec).render(T_wb @ lspec.T_base_laser(), prims, noisy=False)
    a = lspec.angles()
    i0 = int(np.argmin(np.abs(a)))
    assert a[i0] == 0.0
    # Straight ahead: the nearer leg's surface, x = 3 - 0.1 - 0.075, from the laser at 0.3.
    assert abs(ret.true_ranges[i0] - (3.0 - 0.1 - 0.075 - 0.3)) < 1e-9
    assert ret.dynamic[i0] and 1 <= ret.dynamic.sum() < 20
    back = np.abs(np.abs(a) - np.pi) < np.radians(5)
    assert not ret.dynamic[back].any()
    assert np.allclose(ret.true_ranges[back], 0.3 / np.abs(np.cos(a[back])), atol=1e-9)


def test_distorted_camera_depth_still_exact(room: Scene) -> None:
    cam = PinholeCamera(160, 120, 100.0, 100.0, 80.0, 60.0, np.array([-0.2, 0.05, 0.001,
                                                                      -0.001, 0.0]))
    T_wc = se3(R_BASE_OPTICAL, [1.0, 2.0, 1.0])
    img = CameraRenderer(room, cam).render(T_wc)
    rays_c = cam.pixel_rays().reshape(-1, 3)
    expected = ray_box_interior(T_wc[:3, 3], rays_c @ T_wc[:3, :3].T).reshape(120, 160)
    assert np.max(np.abs(img.depth - expected) / expected) < 2e-6
    # Points back-projected from the depth land on the distorted pixel they came from.
    uv = np.array([[5.0, 7.0], [150.0, 110.0], [80.0, 60.0]])
    p = cam.backproject(uv, img.depth[uv[:, 1].astype(int), uv[:, 0].astype(int)])
    uv2, _ = cam.project(p)
    assert np.allclose(uv2, uv, atol=1e-6)


def test_a_beam_that_hits_nothing_stays_no_return() -> None:
    """A miss's zero normal read as grazing incidence: half the no-return beams of an open
    scene became NaN (dropout) instead of +inf (REP 117)."""
    scene = Scene.from_boxes([Box([3.0, 0, 1.0], [0.1, 2.0, 2.0])], build_texture_bank(0))
    lidar = LidarRenderer(scene, LidarSpec())
    rng = np.random.default_rng(0)
    for _ in range(5):
        ret = lidar.render(se3(np.eye(3), [0, 0, 0.25]), rng=rng)
        miss = ~np.isfinite(ret.true_ranges)
        assert miss.sum() > 100 and np.isposinf(ret.ranges[miss]).all()

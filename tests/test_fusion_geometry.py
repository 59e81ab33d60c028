"""Projection against known geometry, flying-pixel removal, voxel map bookkeeping."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from toolkit.camera import PinholeCamera
from toolkit.eval.depth import depth_errors
from toolkit.fusion.cloud import (
    CloudOptions,
    RayCache,
    depth_to_points,
    edge_mask,
    ramp_mask,
    valid_pixels,
)
from toolkit.fusion.projection import (
    LidarPixels,
    LidarProjector,
    edge_pairs,
    occluded_lidar,
    project_points,
    project_scan,
    sample_depth,
    zbuffer_lidar,
)
from toolkit.fusion.synthetic import R_BASE_OPTICAL
from toolkit.fusion.voxel_map import (
    KeyTable,
    VoxelMap,
    key_centres,
    read_map_ply,
    voxel_keys,
    write_map_ply,
)
from toolkit.geometry import inv_se3, se2_to_se3, se3
from toolkit.sensors import CameraFrame, LaserScan, Rig, Sequence

WALL_X = 3.0  # a wall at x = 3 m in the world, facing the robot


def _wall_scan(T_world_laser: np.ndarray, stamp: float = 0.0, n: int = 721) -> LaserScan:
    """Exact ranges of a planar scan against the wall x = WALL_X (z = 0 plane of the laser)."""
    angles = -np.pi / 2 + np.arange(n) * (np.pi / (n - 1))
    R = T_world_laser[:3, :3]
    o = T_world_laser[:3, 3]
    d = np.stack([np.cos(angles), np.sin(angles), np.zeros(n)], 1) @ R.T
    with np.errstate(divide="ignore"):
        r = (WALL_X - o[0]) / d[:, 0]
    r[(d[:, 0] <= 1e-6) | (r > 30)] = np.nan
    return LaserScan(stamp, r, -np.pi / 2, np.pi / (n - 1), 0.05, 30.0)


def _rig(dist: np.ndarray | None = None) -> Rig:
    cam = PinholeCamera(320, 240, 250.0, 250.0, 159.5, 119.5,
                        np.zeros(5) if dist is None else dist)
    # Camera 0.4 m above the laser and tilted down 10 degrees so the scan crosses the image.
    tilt = np.array([[1, 0, 0], [0, np.cos(0.17), -np.sin(0.17)],
                     [0, np.sin(0.17), np.cos(0.17)]])
    T_base_camera = se3(R_BASE_OPTICAL @ tilt, [0.05, 0.02, 0.7])
    T_base_laser = se3(None, [0.2, 0.0, 0.3])
    return Rig(cam, T_base_camera, T_base_laser)


def _wall_depth(camera: PinholeCamera, T_world_camera: np.ndarray) -> np.ndarray:
    """[H, W] exact z-depth of the wall for every pixel (rays with z = 1)."""
    rays = camera.pixel_rays() @ T_world_camera[:3, :3].T  # world directions per pixel
    o = T_world_camera[:3, 3]
    lam = (WALL_X - o[0]) / rays[..., 0]  # distance in units of the z = 1 ray: z-depth
    return np.where(lam > 0, lam, np.nan).astype(np.float64)


@pytest.mark.parametrize("dist", [None, np.array([-0.28, 0.09, 0.001, -0.0005, 0.0])])
def test_static_projection_lands_on_the_wall(dist: np.ndarray | None) -> None:
    rig = _rig(dist)
    T_world_base = se2_to_se3(0.0, 0.0, 0.2)
    scan = _wall_scan(T_world_base @ rig.T_base_laser)
    lp = project_scan(rig.camera, scan, rig.T_camera_laser)
    assert len(lp) > 100
    expect = _wall_depth(rig.camera, T_world_base @ rig.T_base_camera)
    # Exact comparison at the projected sub-pixel position: interpolate the analytic depth
    # along the rays through uv (undistort the pixel, intersect the wall).
    xy = rig.camera.undistort_points(lp.uv)
    rays = np.concatenate([xy, np.ones((len(xy), 1))], 1) @ (
        T_world_base @ rig.T_base_camera)[:3, :3].T
    z_expect = (WALL_X - (T_world_base @ rig.T_base_camera)[0, 3]) / rays[:, 0]
    np.testing.assert_allclose(lp.z, z_expect, rtol=1e-6)
    # And at the nearest pixel of the analytic depth image, within a pixel's depth change.
    d = sample_depth(expect, lp)
    assert np.median(np.abs(d - lp.z)) < 0.01


def _moving_sequence(rig: Rig, yaw_rate: float) -> tuple[Sequence, np.ndarray, np.ndarray]:
    """One image at t = 0.05 and scans at t = 0.0 and 0.1 while the robot turns."""
    def pose(t: float) -> np.ndarray:
        return se2_to_se3(0.3 * t, 0.0, yaw_rate * t)

    scans = [_wall_scan(pose(t) @ rig.T_base_laser, t) for t in (0.0, 0.1)]
    frames = [CameraFrame.from_array(0.05, np.zeros((240, 320, 3), np.uint8))]
    seq = Sequence(rig, frames, scans)
    return seq, np.stack([pose(0.05)]), np.stack([pose(0.0), pose(0.1)])


def test_motion_compensation_places_scans_at_their_own_stamp() -> None:
    rig = _rig()
    seq, fposes, sposes = _moving_sequence(rig, yaw_rate=1.5)  # 1.5 rad/s: a fast turn
    expect = _wall_depth(rig.camera, fposes[0] @ rig.T_base_camera)
    comp = LidarProjector(seq, fposes, sposes, scans_per_frame=2).project_frame(0)
    naive = LidarProjector(seq, scans_per_frame=1).project_frame(0)
    err_comp = np.abs(sample_depth(expect, comp) - comp.z)
    err_naive = np.abs(sample_depth(expect, naive) - naive.z)
    assert len(comp) > 2 * 100 and set(comp.scan.tolist()) == {0, 1}
    assert np.median(err_comp) < 0.01
    # Without poses the 0.05 s of turning (4 degrees) moves the points along the wall; the
    # z error is visible where the wall is seen at an angle.
    assert np.median(err_naive) > 3 * np.median(err_comp)


def test_zbuffer_keeps_nearest_per_pixel() -> None:
    from toolkit.fusion.projection import LidarPixels

    lp = LidarPixels(np.array([[10.2, 5.0], [9.8, 5.1], [20.0, 5.0]]), np.array([3.0, 2.0, 4.0]),
                     np.zeros((3, 3)), np.arange(3), np.zeros(3, int))
    z = zbuffer_lidar(lp, (10, 30))
    assert sorted(z.z.tolist()) == [2.0, 4.0]


def test_lidar_pixel_k_covers_k_minus_half_to_k_plus_half() -> None:
    """Pixel k spans [k - 0.5, k + 0.5) (in_image's half-open span): np.rint put u = 0.5
    in pixel 0 and u = 1.5 and 2.5 both in pixel 2 (halves to even)."""
    below_half = np.nextafter(0.5, 0.0)  # 0.49999999999999994: floor(u + 0.5) gives 1
    u = np.array([-0.5, 0.5, 1.5, 2.5, 3.5, below_half, 1.0, 63.0, np.nextafter(63.5, 0.0)])
    want = np.array([0, 1, 2, 3, 4, 0, 1, 63, 63])
    uv = np.stack([u, u[::-1]], 1)  # [9, 2] the rows as well as the columns
    lp = LidarPixels(uv, np.ones(len(u)), np.zeros((len(u), 3)), np.arange(len(u)),
                     np.zeros(len(u), int))
    np.testing.assert_array_equal(lp.pixel, np.stack([want, want[::-1]], 1))
    # Every point in_image keeps is sampled in the image, on the pixel whose span holds it.
    cam = PinholeCamera(64, 64, 50.0, 50.0, 31.5, 31.5)
    rng = np.random.default_rng(0)
    k = rng.integers(0, 64, (1000, 2))  # [1000, 2] pixels
    uv = k + rng.choice([-0.5, 0.0, 0.25, -0.25], (1000, 2))  # [1000, 2] exact sums
    top = rng.random((1000, 2)) < 0.2
    uv[top] = np.nextafter(k[top] + 0.5, 0.0)  # the largest float in the pixel's span
    assert cam.in_image(uv).all()
    lp = LidarPixels(uv, np.ones(1000), np.zeros((1000, 3)), np.arange(1000), np.zeros(1000, int))
    np.testing.assert_array_equal(lp.pixel, k)
    values = np.arange(64 * 64, dtype=np.float32).reshape(64, 64)  # [H, W] value = row * 64 + col
    np.testing.assert_array_equal(sample_depth(values, lp), k[:, 1] * 64 + k[:, 0])


def test_occlusion_drops_far_side_of_range_jumps_only() -> None:
    # One beam spacing is 525 * 1 deg = 9.2 px at the image centre. A chair leg at 1 m in
    # front of a wall at 3 m: the wall beams next to it are hidden from the camera above;
    # the leg itself and wall beams two spacings away are not. A wall seen obliquely (depth
    # growing 5 cm per beam) is no jump.
    u = 319.5 + 9.2 * np.arange(-3, 4)
    z = np.array([3.0, 3.0, 3.0, 1.0, 3.0, 3.0, 3.0])
    lp = LidarPixels(np.stack([u, np.full(7, 240.0)], 1), z, np.zeros((7, 3)), np.arange(7),
                     np.zeros(7, int))
    occ = occluded_lidar(lp, 525.0, 319.5, np.radians(1.0), 1.5)
    assert occ.tolist() == [False, False, True, False, True, False, False]
    # The nearer point projects lower (it is nearer the lidar plane below the camera): only
    # columns count.
    lp.uv[3, 1] = 300.0
    assert occluded_lidar(lp, 525.0, 319.5, np.radians(1.0), 1.5).tolist() == occ.tolist()
    oblique = LidarPixels(lp.uv, 2.0 + 0.05 * np.arange(7), lp.points_cam, lp.beam, lp.scan)
    assert not occluded_lidar(oblique, 525.0, 319.5, np.radians(1.0), 1.5).any()
    assert not occluded_lidar(lp, 525.0, 319.5, np.radians(1.0), 0.0).any()


def test_edge_pairs_flag_lidar_pixels_on_depth_edges() -> None:
    d = np.full((60, 80), 4.0, np.float32)
    d[:, 40:] = 2.0
    d[10, 10] = np.nan  # an invalid neighbour is no edge
    lp = LidarPixels(np.array([[10.0, 11.0], [39.0, 30.0], [60.0, 30.0], [5.0, 5.0]]),
                     np.ones(4), np.zeros((4, 3)), np.arange(4), np.zeros(4, int))
    assert edge_pairs(d, lp, 0.06, 5).tolist() == [False, True, False, False]


def test_near_stride_keeps_every_voxel_with_fewer_points() -> None:
    cam = PinholeCamera(160, 120, 100.0, 100.0, 79.5, 59.5)
    rays = RayCache(cam, 2)
    depth = np.full((120, 160), 0.5, np.float32)  # a wall at 0.5 m
    depth[:, 80:] = 3.0  # and one at 3 m: beyond near_depth_m, untouched
    rgb = np.zeros((120, 160, 3), np.uint8)
    plain = CloudOptions(edge_threshold=0.0, stride=2)
    near = CloudOptions(edge_threshold=0.0, stride=2, near_stride=4,
                        near_depth_m=0.05 * 100.0 / 8)  # voxel * fx / (2 near_stride)
    p0, _, i0 = depth_to_points(depth, rgb, rays, np.eye(4), plain)
    p1, _, i1 = depth_to_points(depth, rgb, rays, np.eye(4), near)
    assert set(i1.tolist()) <= set(i0.tolist())
    far0, far1 = p0[p0[:, 2] > 2], p1[p1[:, 2] > 2]
    assert len(far1) == len(far0)
    assert len(p1) - len(far1) == pytest.approx((len(p0) - len(far0)) / 4, rel=0.05)
    k0 = np.unique(voxel_keys(p0[p0[:, 2] < 2], 0.05))
    k1 = np.unique(voxel_keys(p1[p1[:, 2] < 2], 0.05))
    assert np.array_equal(k0, k1)  # 2 cm spacing < half a 5 cm voxel: every voxel keeps one


def test_voxel_map_weights_and_nearest_depth() -> None:
    vm = VoxelMap(0.1)
    a = np.array([[0.01, 0.01, 0.01], [0.05, 0.05, 0.05]])
    col = np.array([[0, 0, 0], [100, 0, 0]], np.uint8)
    vm.integrate(a, col, 0, depths=np.array([2.0, 2.0]), weights=np.array([3, 1]))
    vm.integrate(a[:1], col[:1], 1, depths=np.array([1.0]))
    m = vm.arrays()
    assert len(m) == 1 and m.count[0] == 5 and m.frames[0] == 2
    np.testing.assert_allclose(m.points[0], (4 * a[0] + a[1]) / 5)
    assert m.colors[0, 0] == 20
    assert m.near[0] == pytest.approx(1.0)
    assert m.select(np.array([True])).near[0] == pytest.approx(1.0)


def test_voxel_map_release_frees_its_arrays_and_keeps_what_was_taken() -> None:
    """``release`` (Fusion.finish, once the map's arrays are taken) drops the voxel map's
    own arrays, which at the end of a long fusion are the largest thing it holds; what
    ``arrays`` returned stays intact, and the map refuses further use by name."""
    def held(vm: VoxelMap) -> int:
        return sum(v.nbytes for v in vars(vm).values() if isinstance(v, np.ndarray))

    rng = np.random.default_rng(1)
    vm = VoxelMap(0.02)
    for f in range(3):
        pts = rng.uniform(-2, 2, (50_000, 3))  # [N, 3] mostly new voxels each frame
        vm.integrate(pts, rng.integers(0, 256, (50_000, 3)).astype(np.uint8), f)
    m = vm.arrays()
    points, count = m.points.copy(), m.count.copy()
    assert held(vm) > 10 * 2**20
    vm.release()
    assert held(vm) < 2**16
    np.testing.assert_array_equal(m.points, points)
    np.testing.assert_array_equal(m.count, count)
    for use in (vm.arrays, lambda: len(vm),
                lambda: vm.integrate(points[:1], np.zeros((1, 3), np.uint8), 3)):
        with pytest.raises(RuntimeError, match="released"):
            use()


def test_voxel_map_arrays_free_the_batch_buffer_and_the_map_goes_on() -> None:
    """``arrays`` merges the frames waiting in the batch buffer and frees its room (1 M
    entries or more, 80 bytes each: at the fuse stage's peak beside the map's own arrays
    and their copy); frames integrated after it make room again, and the map is the one
    of a map read only at the end."""
    def pending(vm: VoxelMap) -> int:
        return sum(getattr(vm, n).nbytes for n in VoxelMap._PENDING)

    rng = np.random.default_rng(3)
    frames = [(rng.uniform(-2, 2, (40_000, 3)), rng.integers(0, 256, (40_000, 3)).astype(
        np.uint8)) for _ in range(4)]  # [N, 3] points and colours of each frame
    read, once = VoxelMap(0.02), VoxelMap(0.02)
    for f, (pts, col) in enumerate(frames[:3]):
        read.integrate(pts, col, f)
        once.integrate(pts, col, f)
    assert pending(read) > 3 * 40_000 * 64  # all three frames wait in the buffer
    first = read.arrays()
    assert pending(read) == 0
    assert len(first) == len(read)
    read.integrate(*frames[3], 3)
    once.integrate(*frames[3], 3)
    a, b = read.arrays(), once.arrays()
    for name in ("points", "colors", "count", "frames", "first", "last", "label", "near"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_voxel_map_batch_buffer_holds_one_batch_and_a_frame() -> None:
    """The batch buffer grows by half up to the batch size, and past it only to what the
    frame that fills the batch needs: growing by half from below the batch made room for
    1.48 M entries (113 MiB) for batches of 1 M on the quickstart. Merges come at the
    same frames, so the map is the same."""
    rng = np.random.default_rng(4)
    vm, batch, per_frame = VoxelMap(0.02, batch_entries=100_000), 100_000, 30_000
    most = 0
    for f in range(12):
        pts = rng.uniform(-3, 3, (per_frame, 3))  # [N, 3] about one voxel each
        vm.integrate(pts, np.zeros((per_frame, 3), np.uint8), f)
        most = max(most, vm._p_keys.shape[-1])
    assert batch <= most <= batch + per_frame
    assert len(vm) == len(np.unique(vm._keys)) > 11 * per_frame * 0.99


def test_voxel_map_arrays_take_little_beyond_their_result() -> None:
    """``arrays`` of a large map (the fuse stage's peak, taken while the map still holds its
    own arrays) needs little memory beyond the arrays it returns (55 bytes a voxel): 89
    bytes a voxel more traced before it divided the sums row by row, 8 after; the values
    are those of the sums divided by the counts."""
    import tracemalloc

    rng = np.random.default_rng(2)
    vm = VoxelMap(0.02)
    pts = rng.uniform(-3, 3, (200_000, 3))  # [N, 3] about one voxel each
    cols = rng.integers(0, 256, (200_000, 3)).astype(np.uint8)
    vm.integrate(pts, cols, 0, labels=rng.uniform(0, 1, 200_000))
    vm.integrate(pts, cols, 1)
    n = len(vm)  # merged: the measurement is arrays' own
    tracemalloc.start()
    try:
        m = vm.arrays()
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert len(m) == n
    result = sum(getattr(m, f).nbytes for f in ("points", "colors", "count", "frames", "first",
                                                "last", "label", "near"))
    assert (peak - result) / n < 40, f"{(peak - result) / n:.0f} bytes a voxel beyond"
    k = vm._row  # [V] rows in key order, the order arrays returns
    s, c = vm._sums[:, k], vm._count[k].astype(np.float64)
    np.testing.assert_array_equal(m.points, (s[:3] / c).T)
    np.testing.assert_array_equal(m.colors, np.clip(np.rint(s[3:6] / c), 0, 255).T)
    np.testing.assert_array_equal(m.label, (s[6] / c).astype(np.float32))


def test_map_ply_reads_back_what_was_written(tmp_path: Path) -> None:
    """Written by Open3D, read by plyfile (the splat stage's reader): same points, same
    colours; a file that is no PLY is refused by name."""
    vm = VoxelMap(0.1)
    rng = np.random.default_rng(0)
    pts = rng.uniform(-3, 3, (500, 3))
    col = rng.integers(0, 256, (500, 3)).astype(np.uint8)
    vm.integrate(pts, col, 0)
    m = vm.arrays()
    write_map_ply(tmp_path / "map.ply", m)
    p, c = read_map_ply(tmp_path / "map.ply")
    np.testing.assert_allclose(p, m.points, atol=1e-6)  # stored as float32
    np.testing.assert_array_equal(c, m.colors)
    bad = tmp_path / "bad.ply"
    bad.write_text("not a ply\n")
    with pytest.raises(ValueError, match="bad.ply"):
        read_map_ply(bad)


def test_edge_mask_drops_flying_pixels_only() -> None:
    d = np.full((60, 80), 4.0, np.float32)
    d[:, 40:] = 2.0
    d[:, 38:42] = np.linspace(4.0, 2.0, 4)  # a blurred edge: ramp pixels fly
    m = edge_mask(d, 0.06, 5)
    assert m[:, 37:43].all()
    assert not m[:, :33].any() and not m[:, 47:].any()


def test_ramp_mask_passes_planes_at_any_slant() -> None:
    # A floor 0.45 m below a camera pitched 10 deg down, and a wall slanted 37 deg across
    # the view: only the line where they meet bends (border pixels included: planes are
    # continued past the image's edge).
    cam = PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)
    rays = cam.pixel_rays()  # [H, W, 3], z = 1
    c, s = np.cos(np.radians(10)), np.sin(np.radians(10))
    d = rays @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]]).T
    with np.errstate(divide="ignore"):
        t_floor = np.where(d[..., 1] > 1e-6, 0.45 / d[..., 1], np.inf)
        n = np.array([0.6, 0.0, -0.8])
        t_wall = np.where(d @ n < -1e-6, -5.0 / (d @ n), np.inf)
    depth = (np.minimum(t_floor, t_wall) * rays[..., 2]).astype(np.float32)  # [H, W]
    floor = (t_floor < t_wall).astype(np.uint8)
    corner = cv2.dilate(cv2.morphologyEx(floor, cv2.MORPH_GRADIENT, np.ones((3, 3))),
                        np.ones((9, 9), np.uint8)).astype(bool)
    m = ramp_mask(depth, 0.003)
    assert not (m & ~corner).any()
    assert m[corner].mean() > 0.3  # the corner itself does bend


def test_ramp_mask_finds_gentle_ramps_the_range_test_misses() -> None:
    # A chair 3.6 m away in front of a wall at 4 m, the edge blurred over 6 pixels as a
    # smooth network draws it: a 5x5 window spans at most 6.2 % of the depth.
    d = np.full((60, 80), 4.0, np.float32)
    d[:, 40:] = 3.6
    d[:, 37:43] = np.linspace(4.0, 3.6, 8)[1:-1]
    edge = edge_mask(d, 0.06, 5)
    ramp = ramp_mask(d, 0.003)
    assert edge[:, 37:43].mean() < 0.5
    assert (edge | ramp)[:, 37:43].mean() > 0.8
    assert not ramp[:, :32].any() and not ramp[:, 48:].any()
    ok = valid_pixels(d, CloudOptions(ramp_threshold=0.003))
    np.testing.assert_array_equal(ok, ~(edge | ramp))


def test_strided_pixel_masks_are_the_full_masks_strided() -> None:
    """valid_pixels, edge_mask and ramp_mask at a stride (the exposure's sparse points)
    are the full-resolution masks at those pixels, with invalid pixels, edges and ramps
    about; the caller's depth keeps its NaN and inf."""
    rng = np.random.default_rng(9)
    yy, xx = np.mgrid[0:61, 0:83]
    d = (1.0 / (0.5 + 0.002 * xx + 0.001 * yy)).astype(np.float32)  # a plane, 1.2-2 m
    d[10:30, 20:40] *= 0.8  # a box in front of it: edges
    d[35:50, 50:70] = cv2.GaussianBlur(d, (9, 9), 4.0)[35:50, 50:70] * 1.02  # ramps
    d[rng.random(d.shape) < 0.01] = np.nan
    d[5, 7], d[40, 50], d[0, 0] = np.inf, -1.0, 0.0
    before = d.copy()
    opts = CloudOptions(ramp_threshold=0.003)
    for s in (2, 3, 4):
        np.testing.assert_array_equal(edge_mask(d, 0.06, 5, s), edge_mask(d, 0.06, 5)[::s, ::s])
        np.testing.assert_array_equal(ramp_mask(d, 0.003, s), ramp_mask(d, 0.003)[::s, ::s])
        np.testing.assert_array_equal(valid_pixels(d, opts, s), valid_pixels(d, opts)[::s, ::s])
    full = valid_pixels(d, opts)
    assert 0.3 < full.mean() < 0.95
    np.testing.assert_array_equal(d, before)


def test_depth_to_points_transform_colour_and_range() -> None:
    cam = PinholeCamera(40, 30, 30.0, 30.0, 19.5, 14.5)
    rays = RayCache(cam, stride=1)
    depth = np.full((30, 40), 2.0, np.float32)
    depth[0, 0] = np.nan
    depth[0, 1] = 9.0  # beyond max_depth
    rgb = np.zeros((30, 40, 3), np.uint8)
    rgb[..., 0] = 200
    T = se3(None, [1.0, 2.0, 3.0])
    pts, col, idx = depth_to_points(depth, rgb, rays, T, CloudOptions(max_depth_m=6.0,
                                                                      edge_threshold=0.0))
    assert len(pts) == 30 * 40 - 2
    np.testing.assert_allclose(pts[:, 2], 5.0, atol=1e-6)  # z = 2 in camera, +3
    assert (col[:, 0] == 200).all()
    back = (pts - [1.0, 2.0, 3.0])
    uv, z = cam.project(back)
    np.testing.assert_allclose(uv[:, 0], idx % 40, atol=1e-4)


def test_depth_to_points_refuses_images_that_are_not_rgb() -> None:
    cam = PinholeCamera(40, 30, 30.0, 30.0, 19.5, 14.5)
    rays = RayCache(cam, stride=1)
    depth = np.full((30, 40), 2.0, np.float32)
    for shape in ((30, 40, 4), (30, 40)):  # RGBA gave half the points shifted colours
        with pytest.raises(ValueError, match=r"RGB image \[H, W, 3\]"):
            depth_to_points(depth, np.zeros(shape, np.uint8), rays, np.eye(4), CloudOptions())


def test_poses_beyond_the_maps_key_range_are_refused_before_fusing() -> None:
    from toolkit.fusion.pipeline import FusionConfig, check_world_extent

    poses = np.stack([se3(None, [x, 0.0, 0.0]) for x in (0.0, 5.0)])
    check_world_extent(poses, FusionConfig())
    check_world_extent(poses + se3(None, [15000.0, -12000.0, 0.0]) - np.eye(4),
                       FusionConfig())  # within +-21 km at 2 cm
    utm = poses + se3(None, [500000.0, 5000000.0, 0.0]) - np.eye(4)
    with pytest.raises(ValueError, match="local frame") as e:
        check_world_extent(utm, FusionConfig())
    assert "voxel_size_m 0.02" in str(e.value)
    # 10 cm voxels reach 105 km; the exposure's 10 cm cells 52 km.
    far = poses + se3(None, [60000.0, 0.0, 0.0]) - np.eye(4)
    with pytest.raises(ValueError, match="exposure_cell_m 0.1"):
        check_world_extent(far, FusionConfig(voxel_size_m=0.1))
    check_world_extent(far, FusionConfig(voxel_size_m=0.1, exposure="none"))


def test_voxel_map_means_counts_and_frames() -> None:
    vm = VoxelMap(0.1, batch_entries=5)  # tiny batches exercise the merging
    a = np.array([[0.01, 0.01, 0.01], [0.03, 0.05, 0.02], [0.55, 0.0, 0.0]])
    col = np.array([[100, 0, 0], [200, 0, 0], [0, 50, 0]], np.uint8)
    vm.integrate(a, col, 3, labels=np.array([1.0, 0.0, 0.0]))
    vm.integrate(a[:1] + 0.02, col[:1], 7)
    m = vm.arrays()
    assert len(m) == 2
    i = int(np.argmin(m.points[:, 0]))
    assert m.count[i] == 3 and m.frames[i] == 2 and m.first[i] == 3 and m.last[i] == 7
    np.testing.assert_allclose(m.points[i], np.mean(np.r_[a[:2], a[:1] + 0.02], 0))
    assert m.colors[i, 0] == round((100 + 200 + 100) / 3)
    assert m.label[i] == pytest.approx(1 / 3)
    assert len(vm.arrays(min_frames=2)) == 1
    keys = voxel_keys(np.array([[-0.05, 0.12, 7.0]]), 0.1)
    np.testing.assert_allclose(key_centres(keys, 0.1), [[-0.05, 0.15, 7.05]])


def test_depth_errors_values() -> None:
    ref = np.array([1.0, 2.0, 4.0, 0.0])
    pred = np.array([1.1, 2.0, 2.0, 5.0])
    e = depth_errors(pred, ref)
    assert e.count == 3
    assert e.rmse_m == pytest.approx(np.sqrt((0.01 + 0 + 4) / 3))
    assert e.absrel == pytest.approx((0.1 + 0 + 0.5) / 3)
    assert e.delta1 == pytest.approx(2 / 3)
    # A lidar beam without return (+inf) is no reference (it made every figure inf).
    with_inf = depth_errors(np.r_[pred, 3.0], np.r_[ref, np.inf])
    assert with_inf == e and type(e.delta1) is float


def _errors_as_defined(pred: np.ndarray, ref: np.ndarray, ok: np.ndarray) -> tuple:
    """The figures of depth_errors written out on the valid pairs ``ok``, float64."""
    p, r = pred[ok].astype(np.float64), ref[ok].astype(np.float64)
    n = len(p)
    e = p - r
    d1 = np.count_nonzero((p < 1.25 * r) & (r < 1.25 * p))
    return (float(np.sqrt(np.dot(e, e) / n)), float(np.abs(e).sum() / n),
            float((np.abs(e) / r).sum() / n), float(d1 / n), n)


def test_a_depth_reference_scores_each_prediction_as_depth_errors() -> None:
    """DepthReference (the reference tested and widened once, for the fuse stage's three
    depths per frame) gives each prediction the figures depth_errors gives it, to the bit,
    as do an ErrorAccumulator fed with it and a depth kind's values in place of its
    as_depth(1, 0); the caller's arrays are left as they were."""
    from toolkit.depth.protocol import DepthPrediction
    from toolkit.eval.depth import DepthReference, ErrorAccumulator

    rng = np.random.default_rng(3)
    ref = rng.uniform(0.2, 12.0, (48, 64)).astype(np.float32)
    ref.reshape(-1)[rng.choice(ref.size, 300, replace=False)] = np.float32(np.nan)
    ref[0, :5] = [0.0, np.inf, -1.0, 10.0, np.nextafter(np.float32(10), np.float32(11))]
    mask = rng.uniform(size=ref.shape) < 0.9
    preds = [ref * np.float32(s) for s in (0.8, 1.0, 1.3)]
    preds.append(rng.uniform(-1.0, 13.0, ref.shape).astype(np.float32))
    preds[-1][5, :4] = [np.nan, np.inf, -np.inf, 0.0]
    preds.append(preds[0].astype(np.float64))
    before = [p.copy() for p in preds]
    for m, cap in ((None, None), (None, 10.0), (mask, 10.0), (mask, None)):
        reference = DepthReference(ref, m, cap)
        ok_ref = (np.isfinite(ref) & (ref > 0) & (True if cap is None else ref <= cap)
                  & (True if m is None else m))
        for p in preds:
            ok = ok_ref & (p > 0) & np.isfinite(p)
            want = _errors_as_defined(p, ref, ok)
            assert tuple(reference.errors(p).as_dict().values()) == want
            assert tuple(depth_errors(p, ref, m, cap).as_dict().values()) == want
    for p, b in zip(preds, before, strict=True):
        np.testing.assert_array_equal(p, b)
    # Pooled: the same sums with the reference made once or per call.
    reference = DepthReference(ref, max_depth=10.0)
    a, b = ErrorAccumulator(), ErrorAccumulator()
    for p in preds:
        a.add(p, ref, max_depth=10.0)
        b.add(p, reference)
    assert a.result() == b.result()
    # The stage scores a depth kind's values as its unscaled depth.
    values = preds[-2]
    pred = DepthPrediction(values, "relative_depth")
    assert reference.errors(pred.values) == reference.errors(pred.as_depth(1.0, 0.0))
    with pytest.raises(ValueError, match="prediction of 10 values for a reference of 3072"):
        reference.errors(np.ones(10))
    with pytest.raises(ValueError, match="has its mask and max_depth"):
        a.add(preds[0], reference, max_depth=10.0)
    assert DepthReference(np.full(4, np.nan)).errors(np.ones(4)).count == 0


def test_inverse_transform_consistency() -> None:
    rig = _rig()
    T = rig.T_camera_laser
    np.testing.assert_allclose(inv_se3(T) @ T, np.eye(4), atol=1e-12)


def test_scans_of_a_frame_are_its_nearest_in_time() -> None:
    """The n nearest scans (ties to the earlier one) within max_dt, found without sorting
    every stamp per frame."""
    rig = _rig()
    stamps = np.r_[0.0, 0.1, 0.1, 0.2, 0.35, 0.5, 0.5, 0.9]
    scans = [LaserScan(float(t), np.ones(3), 0.0, 0.1) for t in stamps]
    seq = Sequence(rig, [], scans)
    for n in (1, 2, 3):
        proj = LidarProjector(seq, scans_per_frame=n, max_dt=0.3)
        for t in np.linspace(-0.5, 1.5, 81):
            order = np.argsort(np.abs(stamps - t), kind="stable")[:n]
            expect = [int(k) for k in order if abs(stamps[k] - t) <= 0.3]
            assert proj.scan_indices(float(t)) == expect, (n, t)


def test_dynamic_beams_flag_what_other_scans_see_through() -> None:
    from toolkit.fusion.dynamic import cylinder_mask, dynamic_beams

    T = se3(None, [0.0, 0.0, 0.3])
    scans = [_wall_scan(T, float(t)) for t in np.arange(0, 6.0, 0.5)]
    # A person 1 m in front of the lidar at t = 2 s covers a few beams around bearing 0.
    s = scans[4]
    person = np.abs(s.angles()) < 0.08
    s.ranges[person] = 1.0
    s.ranges[100] = 1.5  # and a lone beam (a chair leg thinner than the beam spacing)
    flags = dynamic_beams(scans, np.stack([T] * len(scans)))
    assert np.array_equal(flags[4], person)
    assert not any(f.any() for k, f in enumerate(flags) if k != 4)
    assert dynamic_beams(scans, np.stack([T] * len(scans)), isolated=True)[4][100]
    pts = np.array([[1.0, 0.0, 1.0], [1.0, 0.45, 0.5], [1.0, 0.0, 2.5], [3.0, 0.0, 1.0]])
    m = cylinder_mask(pts, np.array([[1.0, 0.0]]), 0.5, 2.0)
    assert m.tolist() == [True, True, False, False]


def _seen_through_reference(scans: list[LaserScan], T_world_laser: np.ndarray,
                            offsets: tuple[float, ...], margin_m: float, margin_rel: float,
                            tol: float) -> list[np.ndarray]:
    """Votes of ``dynamic_beams`` one scan and one partner at a time, with a linear
    nearest-stamp search: the definition the batched version must reproduce."""
    stamps = np.array([s.stamp for s in scans])
    votes = []
    for k, sk in enumerate(scans):
        v = np.zeros(len(sk.ranges), np.int32)
        ok_k = sk.valid_mask()
        a = sk.angles()
        p = T_world_laser[k] @ np.stack([np.where(ok_k, sk.ranges * np.cos(a), 0),
                                         np.where(ok_k, sk.ranges * np.sin(a), 0),
                                         np.zeros(len(a)), np.ones(len(a))])
        for off in offsets:
            j = int(np.argmin(np.abs(stamps - (sk.stamp + off))))
            if abs(stamps[j] - sk.stamp) < 0.5 * abs(off) or j == k:
                continue
            sj = scans[j]
            q = np.linalg.inv(T_world_laser[j]) @ p
            rq = np.hypot(q[0], q[1])
            n = len(sj.ranges)
            full = abs(sj.angle_increment) * n >= 2 * np.pi - 1e-6
            reach = np.where(np.isposinf(sj.ranges), sj.range_max, sj.ranges)
            reach = np.where(np.isfinite(reach) & (reach >= sj.range_min), reach, -np.inf)
            b = np.rint((np.arctan2(q[1], q[0]) - sj.angle_min) / sj.angle_increment)
            far = np.full(len(b), np.inf)
            for db in (-1, 0, 1):
                bb = (b + db).astype(int) % n if full else (b + db).astype(int)
                inside = (bb >= 0) & (bb < n)
                far = np.where(inside, np.minimum(far, reach[np.clip(bb, 0, n - 1)]), -np.inf)
            v += ok_k & (np.abs(q[2]) < tol) & (far > rq + margin_m + margin_rel * rq) & (
                rq < sj.range_max)
        votes.append(v)
    return votes


def test_dynamic_beams_batched_matches_one_scan_at_a_time() -> None:
    """Two scanners (360 beams all round, 181 over the front), a moving robot, a person,
    dropouts, max-range beams, duplicate stamps and a gap: the batched test (any chunk
    size) flags what testing one scan against one partner at a time flags."""
    from toolkit.fusion.dynamic import dynamic_beams

    rng = np.random.default_rng(4)
    stamps = np.r_[np.arange(0, 6, 0.25), 6.0, 6.0, np.arange(12.0, 14.0, 0.25)]
    scans, poses = [], []
    for i, t in enumerate(stamps):
        n, a0, inc = (360, -np.pi, 2 * np.pi / 360) if i % 3 else (181, -np.pi / 2, np.pi / 180)
        a = a0 + np.arange(n) * inc
        c, sn = np.cos(0.05 * t), np.sin(0.05 * t)
        T = se3(np.array([[c, -sn, 0], [sn, c, 0], [0, 0, 1]]), [0.1 * t, 0.02 * np.sin(t), 0.3])
        # A square room 8 m wide seen from the pose: exact ranges to its walls
        d = np.stack([np.cos(a + 0.05 * t), np.sin(a + 0.05 * t)], 1)
        o = T[:2, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.min(np.abs(np.stack([(np.sign(d[:, 0]) * 4 - o[0]) / d[:, 0],
                                        (np.sign(d[:, 1]) * 4 - o[1]) / d[:, 1]])), 0)
        r += rng.normal(0, 0.01, n)
        if 2.0 <= t <= 3.0:  # a person 1.5 m ahead for a second
            r[np.abs(np.angle(np.exp(1j * a))) < 0.1] = 1.5
        r[rng.random(n) < 0.03] = np.nan
        r[rng.random(n) < 0.02] = np.inf
        scans.append(LaserScan(float(t), r, a0, inc, 0.05, 5.0))
        poses.append(T)
    T_wl = np.stack(poses)
    offsets = (-4.0, -2.0, -1.0, -0.5, 0.5, 1.0, 2.0, 4.0)
    votes = _seen_through_reference(scans, T_wl, offsets, 0.15, 0.03, 0.1)
    expect = [v >= 2 for v in votes]
    assert any(e.any() for e in expect)
    for chunk in (256, 5):
        got = dynamic_beams(scans, T_wl, offsets, 0.15, 0.03, 2, 0.1, isolated=True,
                            chunk=chunk)
        for g, e in zip(got, expect, strict=True):
            assert np.array_equal(g, e)


def test_voxel_map_matches_a_one_shot_reduction_and_pickles_mid_way() -> None:
    """Many frames in small batches (index insertions, row growth) give what reducing all
    points at once gives; a map pickled half way (a checkpoint) carries on to the same map."""
    import pickle

    rng = np.random.default_rng(3)
    frames = [(rng.uniform(-1, 1, (int(rng.integers(50, 400)), 3)),
               rng.integers(0, 255, (1, 3)).astype(np.uint8)) for _ in range(40)]
    vm = VoxelMap(0.1, batch_entries=300)
    for f, (pts, col) in enumerate(frames):
        vm.integrate(pts, np.repeat(col, len(pts), 0), f)
        if f == 20:
            vm = pickle.loads(pickle.dumps(vm))
    m = vm.arrays()
    allp = np.concatenate([p for p, _ in frames])
    allc = np.concatenate([np.repeat(c, len(p), 0) for p, c in frames]).astype(np.float64)
    fr = np.concatenate([np.full(len(p), f) for f, (p, _) in enumerate(frames)])
    keys, inv, cnt = np.unique(voxel_keys(allp, 0.1), return_inverse=True, return_counts=True)
    assert len(m) == len(keys)
    np.testing.assert_array_equal(voxel_keys(m.points, 0.1), keys)  # sorted by key
    np.testing.assert_array_equal(m.count, cnt)
    mean = np.stack([np.bincount(inv, allp[:, k]) for k in range(3)], 1) / cnt[:, None]
    np.testing.assert_allclose(m.points, mean, atol=1e-12)
    rgb = np.stack([np.bincount(inv, allc[:, k]) for k in range(3)], 1) / cnt[:, None]
    np.testing.assert_array_equal(m.colors, np.clip(np.rint(rgb), 0, 255).astype(np.uint8))
    first = np.full(len(keys), 10**6)
    np.minimum.at(first, inv, fr)
    last = np.zeros(len(keys), int)
    np.maximum.at(last, inv, fr)
    np.testing.assert_array_equal(m.first, first)
    np.testing.assert_array_equal(m.last, last)
    seen = np.zeros((len(keys), len(frames)), bool)
    seen[inv, fr] = True
    np.testing.assert_array_equal(m.frames, seen.sum(1))


def test_key_table_gives_np_unique_of_the_packed_keys() -> None:
    """A frame's sorted unique keys and inverse as np.unique gives them, from the table over
    its box (reused frame after frame: the cells marked by one must not show in the next)
    or, for a box too large for the table, by sorting; an empty frame has none."""
    rng = np.random.default_rng(5)
    table = KeyTable(max_cells=1 << 16, cells_per_point=64)
    bits = [20, 20, 20, 2]
    cases = [[rng.integers(500, 540, 3000), rng.integers(7, 30, 3000),
              rng.integers(0, 9, 3000), rng.integers(0, 4, 3000)],  # dense: 33 k cells
             [rng.integers(100, 120, 500), rng.integers(0, 20, 500),
              rng.integers(40, 45, 500), rng.integers(0, 4, 500)],  # dense, another box
             [rng.integers(0, 1 << 20, 800), rng.integers(0, 1 << 20, 800),
              rng.integers(0, 1 << 20, 800), rng.integers(0, 4, 800)],  # sorted
             [np.zeros(0, np.int64)] * 4]
    for cols in cases:
        cols = [c.astype(np.int64) for c in cols]
        keys = (cols[0] << 42) | (cols[1] << 22) | (cols[2] << 2) | cols[3]
        want, want_inv = np.unique(keys, return_inverse=True)
        got, inv = table.unique(cols, bits)
        assert got.dtype == np.int64
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(inv, want_inv)
    assert not table._seen.any()


def test_voxel_map_from_an_older_checkpoint_carries_on() -> None:
    """A map pickled before it kept a key table and its pending frames in arrays (a list of
    per-frame tuples then: an older run's checkpoint) resumes to the same map."""
    rng = np.random.default_rng(6)
    pts = [rng.uniform(-1, 1, (200, 3)) for _ in range(4)]
    col = np.full((200, 3), 90, np.uint8)
    ref = VoxelMap(0.1)
    for f in range(2):
        ref.integrate(pts[f], col, f, depths=np.full(200, 1.0 + f))
    state = ref.__getstate__()
    n = state["_pending_n"]
    assert n > 0
    legacy = {k: v for k, v in state.items() if not k.startswith("_p_") and k != "_table"}
    legacy["_pending"] = [(state["_p_keys"], state["_p_sums"], state["_p_count"],
                           np.ones(n, np.int32), state["_p_frame"], state["_p_frame"],
                           state["_p_near"])]
    vm = VoxelMap.__new__(VoxelMap)
    vm.__setstate__(legacy)
    for f in range(2, 4):
        vm.integrate(pts[f], col, f, depths=np.full(200, 1.0 + f))
        ref.integrate(pts[f], col, f, depths=np.full(200, 1.0 + f))
    got, want = vm.arrays(), ref.arrays()
    for name in ("points", "colors", "count", "frames", "first", "last", "near"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))


def test_lidar_carving_counts_every_voxel_in_reach_and_only_those() -> None:
    """A scan tests only the map blocks within its longest beam (an hour-long map is mostly
    out of reach): the free / hit counts equal a direct test of every voxel near the plane
    against the beams at its bearing (free: that beam and both neighbours reach past it),
    on a 60 m map of which a scan reaches 6 m."""
    from toolkit.fusion.dynamic import CarveOptions, SeeThroughCounter

    rng = np.random.default_rng(4)
    pts = np.c_[rng.uniform(-30, 30, (200_000, 2)), rng.uniform(0.1, 0.3, 200_000)]
    opts = CarveOptions()
    counter = SeeThroughCounter(pts, opts)
    free = np.zeros(len(pts), int)
    hit = np.zeros(len(pts), int)
    n_beams = 360
    for x, y, yaw in [(0.0, 0.0, 0.3), (12.5, -7.0, 2.0), (29.0, 29.0, -1.0)]:
        ranges = rng.uniform(1.0, 6.0, n_beams).astype(np.float32)
        ranges[::7] = np.inf  # beyond range_max: says nothing
        scan = LaserScan(0.0, ranges, -np.pi, 2 * np.pi / n_beams, 0.05, 8.0)
        T_world_laser = se2_to_se3(x, y, yaw)
        T_world_laser[2, 3] = 0.2
        T_lw = inv_se3(T_world_laser)
        counter.add_scan(scan, T_lw)
        q = pts @ T_lw[:3, :3].T + T_lw[:3, 3]
        near = np.abs(q[:, 2]) < opts.lidar_plane_tol_m
        r = np.hypot(q[:, 0], q[:, 1])
        beam = np.mod(np.rint((np.arctan2(q[:, 1], q[:, 0]) + np.pi) / (2 * np.pi / n_beams)),
                      n_beams).astype(int)
        rb = ranges[beam].astype(np.float64)
        ok = near & np.isfinite(rb)
        three = np.array([ranges[np.mod(beam + d, n_beams)] for d in (-1, 0, 1)])  # [3, N]
        reach = np.where(np.isfinite(three).all(0), three.min(0), -np.inf)  # inf: none
        free += near & (r < reach - opts.lidar_margin_m)
        hit += ok & (np.abs(r - rb) <= opts.lidar_margin_m)
    assert free.sum() > 300 and hit.sum() > 100
    np.testing.assert_array_equal(counter.lidar_free, free)
    np.testing.assert_array_equal(counter.lidar_hit, hit)


def test_sampling_values_not_at_the_image_size_is_refused() -> None:
    """A network output never resized back to the image (or transposed): the clipped
    lookups sampled the wrong pixels and the scale came out 3.6x off, flagged ok."""
    cam = PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5)
    pc = np.array([[-0.5, 0.0, 1.0], [0.6, 0.2, 1.0], [0.0, 0.0, 2.0]])
    uv, z, keep = project_points(cam, pc)
    lp = LidarPixels(uv, z, pc[keep], np.arange(len(z)), np.zeros(len(z), int))
    assert len(sample_depth(np.ones((48, 64)), lp)) == 3
    for shape in ((24, 32), (64, 48)):
        with pytest.raises(ValueError, match="at the camera image's size"):
            sample_depth(np.ones(shape), lp)


def test_carving_sees_the_whole_image_of_a_barrel_lens() -> None:
    """The views' field of view came from cx / fx (+10 %): a barrel lens sees to tan 1.0
    where 0.88 was used, and an obstacle at the image's side was never carved."""
    from toolkit.fusion.dynamic import CarveOptions, SeeThroughCounter

    cam = PinholeCamera(640, 480, 400.0, 400.0, 319.5, 239.5, np.array([-0.3, 0.1, 0, 0, 0]))
    pts = np.array([[1.0, 0.0, 2.0], [1.9, 0.0, 2.0], [-1.9, 0.0, 2.0]])  # tan 0.5, +-0.95
    assert cam.in_image(cam.project(pts)[0]).all()
    c = SeeThroughCounter(pts, CarveOptions())
    for _ in range(4):  # a wall at 5 m seen through them
        c.add_depth_view(cam, np.eye(4), np.full((480, 640), 5.0, np.float32), 1, 7.0)
    assert c.free.tolist() == [4, 4, 4]


@pytest.mark.parametrize("stride", [1, 2])
def test_carving_tests_a_voxel_at_the_pixel_whose_span_holds_it(stride: int) -> None:
    """Subsampled pixel j covers [j - 0.5, j + 0.5) in uv / stride, as lidar pixels do: a
    voxel straight ahead at uv / stride = (2.5, 1.0) is in column 3, where np.rint took
    column 2 (halves to even) and counted the wall at the voxel's depth as a hit."""
    from toolkit.fusion.dynamic import CarveOptions, SeeThroughCounter

    cam = PinholeCamera(6 * stride, 3 * stride, 4.0, 4.0, 2.5 * stride, 1.0 * stride)
    depth = np.full((3, 6), 2.0, np.float32)  # [H / stride, W / stride] a wall at the voxel
    depth[:, 3] = 5.0  # and far behind it in column 3
    c = SeeThroughCounter(np.array([[0.0, 0.0, 2.0]]), CarveOptions())
    c.add_depth_view(cam, np.eye(4), depth, stride, 7.0)
    assert (c.depth_free.tolist(), c.depth_hit.tolist()) == ([1], [0])


def test_point_rendering_draws_a_point_in_the_pixel_whose_span_holds_it() -> None:
    """u = 2.5 is in pixel 3 ([2.5, 3.5)); np.rint drew it in pixel 2."""
    from toolkit.fusion.figures import render_points

    cam = PinholeCamera(6, 4, 4.0, 4.0, 2.5, 1.5)
    img = render_points(np.array([[0.0, 0.0, 2.0]]), np.array([[0, 0, 0]], np.uint8), cam,
                        np.eye(4), splat=1)
    drawn = np.argwhere((img != 255).any(-1))  # [K, 2] (row, col)
    assert drawn.tolist() == [[2, 3]]


def test_pair_edges_are_tested_on_depth_for_a_disparity() -> None:
    """A smooth slanted wall at 4-5.3 m spans 0.7 % in depth around a pixel; its raw
    disparity (1/z = d + 0.18) spans more than the 6 % threshold at the far end."""
    h, w = 120, 160
    z = 4.0 + 0.008 * np.arange(w)[None, :].repeat(h, 0)
    d = (1 / z - 0.18).astype(np.float32)
    cols = np.arange(10, 150, 5)
    rows = np.full(cols.size, 60)
    lp = LidarPixels(np.stack([cols, rows], 1).astype(float), z[rows, cols],
                     np.zeros((cols.size, 3)), np.arange(cols.size), np.zeros(cols.size, int))
    assert edge_pairs(d, lp, 0.06).sum() > 0  # the raw disparity's span
    assert edge_pairs(d, lp, 0.06, 5, True, 1.0, 0.18).sum() == 0
    assert edge_pairs(z.astype(np.float32), lp, 0.06).sum() == 0


def test_lidar_carving_keeps_tops_just_off_the_scan_plane() -> None:
    """A chest top 3 cm below the scan plane and a table top 2 cm above it, nothing moving:
    the beams pass over / under them to the walls and no scan ever hits them, so every scan
    'saw through' them and both were carved (all 2 x 323 cells). The lidar clears only
    cells some scan has hit: a leg there for the first three scans still goes."""
    from toolkit.fusion.dynamic import SeeThroughCounter

    n = 360
    angles = -np.pi + np.arange(n) * 2 * np.pi / n
    directions = np.stack([np.cos(angles), np.sin(angles)], 1)  # [B, 2]
    z_laser = 0.30

    def cast(x: float, y: float, leg: np.ndarray | None) -> np.ndarray:
        """Ranges from (x, y) to the walls of a 8 x 8 m room (and a leg's circle)."""
        t = np.full(n, np.inf)
        for axis, val in ((0, -4.0), (0, 4.0), (1, -4.0), (1, 4.0)):
            with np.errstate(divide="ignore", invalid="ignore"):
                tt = (val - (x, y)[axis]) / directions[:, axis]
            t = np.where((tt > 0) & (tt < t), tt, t)
        if leg is not None:  # a 10 cm leg: ray / circle
            oc = np.array([x, y]) - leg
            bq = directions @ oc
            disc = bq * bq - (oc @ oc - 0.05 ** 2)
            tl = -bq - np.sqrt(np.maximum(disc, 0))
            t = np.where((disc > 0) & (tl > 0) & (tl < t), tl, t)
        return t.astype(np.float32)

    g = np.arange(0.03, 1.14, 0.06)
    gx, gy = np.meshgrid(1.0 + g, -0.5 + g[:17])
    top = np.c_[gx.ravel(), gy.ravel()]  # [323, 2] one 6 cm cell each
    leg = np.array([-1.5, 1.0])
    cells = np.concatenate([np.c_[top, np.full(len(top), z_laser - 0.03)],  # chest top
                            np.c_[top - [0, 2.0], np.full(len(top), z_laser + 0.02)],  # table
                            [[*leg - [0.05, 0], z_laser]]])  # the leg's near side
    counter = SeeThroughCounter(cells)
    for k, x in enumerate(np.linspace(-3.0, 3.0, 13)):
        y = -1.0 if k % 2 else 1.2
        T_world_laser = se2_to_se3(x, y, 0.1 * k, z_laser)
        counter.add_scan(LaserScan(float(k), cast(x, y, leg if k < 3 else None), -np.pi,
                                   2 * np.pi / n, 0.05, 12.0), inv_se3(T_world_laser))
    tops = slice(0, 2 * len(top))
    assert counter.hit[tops].sum() == 0  # never seen by the lidar
    assert not counter.dynamic_mask()[tops].any()
    assert counter.hit[-1] >= 2 and counter.dynamic_mask()[-1]


def test_lidar_carving_keeps_a_corridor_wall_seen_at_grazing_angles() -> None:
    """Exact scans down a 2 m corridor, nothing moving: far along the walls one beam's
    range differs from its neighbours' by decimetres, and with the nearest beam alone
    32 of 468 wall cells were carved. A cell is seen through only when its beam and both
    neighbours reach past it."""
    from toolkit.fusion.dynamic import SeeThroughCounter

    n = 360
    angles = -np.pi + np.arange(n) * 2 * np.pi / n
    directions = np.stack([np.cos(angles), np.sin(angles)], 1)  # [B, 2]

    def cast(x: float) -> np.ndarray:  # walls y = +-1, ends x = -3 and 13
        t = np.full(n, np.inf)
        for axis, val in ((1, 1.0), (1, -1.0), (0, -3.0), (0, 13.0)):
            with np.errstate(divide="ignore", invalid="ignore"):
                tt = (val - (x if axis == 0 else 0.0)) / directions[:, axis]
            t = np.where((tt > 0) & (tt < t), tt, t)
        return t.astype(np.float32)

    xs = np.arange(-2.0, 12.0, 0.06) + 0.03
    cells = np.concatenate([np.c_[xs, np.full_like(xs, y), np.full_like(xs, 0.3)]
                            for y in (0.99, -0.99)])  # [468, 3]
    counter = SeeThroughCounter(cells)
    for k, x in enumerate(np.arange(0.0, 10.0, 0.25)):
        T_world_laser = se2_to_se3(x, 0.0, 0.0, 0.3)
        counter.add_scan(LaserScan(float(k), cast(x), -np.pi, 2 * np.pi / n, 0.05, 12.0),
                         inv_se3(T_world_laser))
    assert counter.hit.sum() > 500
    assert not counter.dynamic_mask().any()


def test_scans_from_0_to_270_deg_test_their_bearings_past_180() -> None:
    """A scan whose angles run 0..269 deg (angle_min 0): arctan2 gives the bearings past
    180 deg as negative angles, and neither the carving nor the moving-obstacle test
    looked there (a ghost at 200 deg stayed, a person there was not flagged)."""
    from toolkit.fusion.dynamic import SeeThroughCounter, dynamic_beams

    n, inc = 270, np.radians(1.0)
    for bearing in (90.0, 200.0):
        b = np.radians(bearing)
        counter = SeeThroughCounter(np.array([[2 * np.cos(b), 2 * np.sin(b), 0.0]]))
        # A person there at first (the lidar clears only what it has hit), then gone.
        there = np.full(n, 4.0, np.float32)
        there[int(round(bearing)) - 2: int(round(bearing)) + 3] = 2.0
        counter.add_scan(LaserScan(-1.0, there, 0.0, inc, 0.05, 10.0), np.eye(4))
        for k in range(5):
            counter.add_scan(LaserScan(float(k), np.full(n, 4.0, np.float32), 0.0, inc, 0.05,
                                       10.0), np.eye(4))
        assert counter.lidar_hit[0] == 1, bearing
        assert counter.free[0] == 5 and counter.dynamic_mask()[0], bearing
    scans = []
    for t in np.arange(0.0, 6.0, 0.1):
        r = np.full(n, 4.0, np.float32)
        if t < 1.0:
            r[198:203] = r[88:93] = 1.5  # people there for the first second
        scans.append(LaserScan(float(t), r, 0.0, inc, 0.05, 10.0))
    flags = dynamic_beams(scans, np.stack([np.eye(4)] * len(scans)))
    assert flags[0][88:93].all() and flags[0][198:203].all()
    # ... and the same with the beams running backwards (negative increment).
    back = [LaserScan(s.stamp, s.ranges[::-1].copy(), np.radians(269.0), -inc, 0.05, 10.0)
            for s in scans]
    flags = dynamic_beams(back, np.stack([np.eye(4)] * len(scans)))
    assert flags[0][::-1][88:93].all() and flags[0][::-1][198:203].all()


def _ray_circle(o: np.ndarray, d: np.ndarray, c: np.ndarray, r: float) -> np.ndarray:
    """[N] distances along unit rays ``d`` [N, 2] from ``o`` [2] to a circle (inf: miss)."""
    oc = o - c
    b = d @ oc
    disc = b * b - (oc @ oc - r * r)
    with np.errstate(invalid="ignore"):
        t = -b - np.sqrt(disc)
    return np.where((disc >= 0) & (t > 0), t, np.inf)


def test_far_partners_flag_a_person_who_stood_still_and_left_not_a_chair_leg() -> None:
    """A person (legs 20 cm across) stands 20 s beside the path, then leaves; the robot
    drives on and sees the place empty. Scans within 4 s flag only the last 4 s of the
    stay; the far partners (6-128 s) the whole stay. A 4 cm chair leg seen from 1-5 m
    slips between the far scans' beams: their votes need a 10 cm surface."""
    from toolkit.fusion.dynamic import dynamic_beams
    from toolkit.fusion.pipeline import FusionConfig

    n = 360
    angles = -np.pi + np.arange(n) * 2 * np.pi / n
    d = np.stack([np.cos(angles), np.sin(angles)], 1)  # [N, 2]
    person, leg = np.array([2.0, 1.0]), np.array([3.0, -1.0])
    scans, poses = [], []
    for t in np.arange(0.0, 30.0, 0.1):
        o = np.array([0.2 * t, 0.0])  # 0.2 m/s along x, walls at y = +-3 and x = -1, 9
        with np.errstate(divide="ignore"):
            walls = np.stack([(3 - o[1]) / d[:, 1], (-3 - o[1]) / d[:, 1],
                              (9 - o[0]) / d[:, 0], (-1 - o[0]) / d[:, 0]], 1)
        r = np.where(walls > 0, walls, np.inf).min(1)
        r = np.minimum(r, _ray_circle(o, d, leg, 0.02))
        if t < 20.0:
            r = np.minimum(r, _ray_circle(o, d, person, 0.1))
        scans.append(LaserScan(float(t), r.astype(np.float32), -np.pi, 2 * np.pi / n, 0.05,
                               20.0))
        poses.append(se2_to_se3(o[0], o[1], 0.0))
    T = np.stack(poses)

    def on(centre: np.ndarray, radius: float) -> list[np.ndarray]:
        """Per scan, [B] bool: beams ending within ``radius`` of ``centre``."""
        out = []
        for s, P in zip(scans, T, strict=True):
            end = P[:2, 3] + s.ranges[:, None].astype(np.float64) * d
            out.append(np.linalg.norm(end - centre, axis=1) < radius)
        return out

    on_person, on_leg = on(person, 0.15), on(leg, 0.05)
    stay = [k for k, s in enumerate(scans) if s.stamp < 20.0 and on_person[k].sum() >= 2]
    assert len(stay) > 150 and sum(int(m.sum()) for m in on_leg) > 300
    near = dynamic_beams(scans, T)
    flagged = [k for k in stay if near[k][on_person[k]].any()]
    assert all(scans[k].stamp > 15.5 for k in flagged)  # only near the departure
    far = FusionConfig().dynamic_far_offsets_s
    flags = dynamic_beams(scans, T, far_offsets_s=far)
    flagged = [k for k in stay if flags[k][on_person[k]].any()]
    assert len(flagged) >= 0.95 * len(stay)  # the whole stay
    assert not any(f[m].any() for f, m in zip(flags, on_leg, strict=True))
    rest = [f & ~p for f, p in zip(flags, on_person, strict=True)]
    assert sum(int(f.sum()) for f in rest) == 0  # walls and the leg stay
    # Without the width rule the far scans do flag the leg.
    loose = dynamic_beams(scans, T, far_offsets_s=far, far_min_width_m=0.0)
    assert any(f[m].any() for f, m in zip(loose, on_leg, strict=True))
    # Scans are laid out in a ring of the rows a chunk needs: small chunks with partners
    # 8 s away (a ring of about 180 rows for 300 scans) reuse rows, and flag the same.
    whole = dynamic_beams(scans, T, far_offsets_s=(-8.0, 8.0), chunk=len(scans))
    ring = dynamic_beams(scans, T, far_offsets_s=(-8.0, 8.0), chunk=16)
    assert all(np.array_equal(a, b) for a, b in zip(whole, ring, strict=True))
    assert sum(int(f.sum()) for f in whole) > 100


def test_a_static_glass_pane_is_not_a_moving_obstacle() -> None:
    """Glass returns the laser only near normal incidence (+inf from other angles): with
    no return read as free space, all its returns were flagged as moving, and the camera
    points within 0.5 m of them dropped. No return says nothing unless asked."""
    from toolkit.fusion.dynamic import dynamic_beams

    n = 360
    angles = -np.pi + np.arange(n) * 2 * np.pi / n
    scans, poses = [], []
    for t in np.arange(0.0, 20.0, 0.1):
        x = 0.3 * t  # driving along the pane (y = 1.5, 2 < x < 4) and a wall (y = -1.5)
        with np.errstate(divide="ignore", invalid="ignore"):
            to_pane = 1.5 / np.sin(angles)
            to_wall = -1.5 / np.sin(angles)
        along = x + to_pane * np.cos(angles)
        head_on = np.degrees(np.arccos(np.clip(np.abs(np.sin(angles)), 0, 1))) < 15
        r = np.where((to_pane > 0) & (along > 2) & (along < 4) & head_on, to_pane, np.inf)
        r = np.where(~np.isfinite(r) & (to_wall > 0) & (to_wall < 20), to_wall, r)
        scans.append(LaserScan(float(t), r.astype(np.float32), -np.pi, 2 * np.pi / n,
                               0.05, 20.0))
        poses.append(se2_to_se3(x, 0.0, 0.0))
    pane = angles > 0
    assert sum(int(np.isfinite(s.ranges[pane]).sum()) for s in scans) > 1000
    flags = dynamic_beams(scans, np.stack(poses))
    assert sum(int(f.sum()) for f in flags) == 0
    # Asked to (open spaces beyond the scanner's reach), the pane goes as before.
    flags = dynamic_beams(scans, np.stack(poses), no_return_is_free=True)
    assert sum(int(f[pane].sum()) for f in flags) > 1000


def test_carving_counts_the_views_after_each_voxels_last_frame_apart() -> None:
    """With ``last_frame`` / ``last_stamp``, the counts of the views taken after each
    voxel's last fused frame (depth views of later frames, scans stamped later) are those
    of the whole-drive counts restricted to those views; ``after_last`` removes the voxels
    those alone see through, the majority rule's verdicts staying as they were."""
    from toolkit.fusion.dynamic import CarveOptions, SeeThroughCounter

    rng = np.random.default_rng(5)
    pts = np.c_[rng.uniform(-5, 5, (20_000, 2)), rng.uniform(0.1, 0.3, 20_000)]
    last = rng.integers(0, 4, len(pts))
    stamp = last * 1.0 + 0.05
    counters = [SeeThroughCounter(pts, CarveOptions(min_free=1, after_last=a), last_frame=last,
                                  last_stamp=stamp) for a in (False, True)]
    per_scan = []
    for k in range(4):
        ranges = rng.uniform(1.0, 6.0, 360).astype(np.float32)
        scan = LaserScan(k + 0.5, ranges, -np.pi, 2 * np.pi / 360, 0.05, 8.0)
        T_world_laser = se2_to_se3(rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-3, 3))
        T_world_laser[2, 3] = 0.2
        one = SeeThroughCounter(pts)
        for c in (*counters, one):
            c.add_scan(scan, inv_se3(T_world_laser))
        per_scan.append((one.lidar_free.copy(), one.lidar_hit.copy(), stamp < k + 0.5))
    for c in counters:
        np.testing.assert_array_equal(c.late["lidar_free"],
                                      sum(f * late for f, _, late in per_scan))
        np.testing.assert_array_equal(c.late["lidar_hit"],
                                      sum(h * late for _, h, late in per_scan))
        assert c.late["lidar_free"].sum() > 100
    majority, either = (c.dynamic_mask() for c in counters)
    lt = counters[1].late
    free = lt["lidar_free"] * (counters[1].lidar_hit > 0)
    late_rule = (free >= 1) & (free >= 0.5 * np.maximum(free + lt["lidar_hit"], 1))
    np.testing.assert_array_equal(either, majority | late_rule)
    assert (either & ~majority).any()

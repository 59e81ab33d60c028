"""Property tests, round three: lidar -> image projection, depth -> points, flying-pixel
filters, voxel fusion, free-space carving, the depth backends' pre/post-processing, the
geometry and image metrics and the extrinsic calibration, on random synthetic inputs with
known answers. Example counts are bounded so that each test takes about a second or two."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import ndimage
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from toolkit import geometry as g
from toolkit.camera import UNDISTORT_TOL_PX, PinholeCamera
from toolkit.fusion.cloud import (
    CloudOptions,
    RayCache,
    depth_to_points,
    edge_mask,
    ramp_mask,
    valid_pixels,
)
from toolkit.fusion.dynamic import CarveOptions, SeeThroughCounter
from toolkit.fusion.projection import LidarProjector, project_points
from toolkit.fusion.voxel_map import VoxelMap
from toolkit.sensors import CameraFrame, LaserScan, Rig, Sequence

seeds = st.integers(0, 2**31 - 1)
quick = settings(max_examples=25, deadline=None,
                 suppress_health_check=[HealthCheck.function_scoped_fixture])
few = settings(max_examples=8, deadline=None,
               suppress_health_check=[HealthCheck.function_scoped_fixture])

# base (x forward, y left, z up) -> camera optical frame (z forward, x right, y down)
R_BASE_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def random_camera(rng: np.random.Generator, distorted: bool, w: int | None = None,
                  h: int | None = None) -> PinholeCamera:
    w = int(rng.integers(16, 400)) if w is None else w
    h = int(rng.integers(16, 300)) if h is None else h
    f = rng.uniform(0.5, 1.5) * w
    dist = (np.r_[rng.uniform(-0.3, 0.3), rng.uniform(-0.1, 0.1), rng.uniform(-0.01, 0.01, 2),
                  rng.uniform(-0.05, 0.05)] if distorted else np.zeros(5))
    return PinholeCamera(w, h, f, f * rng.uniform(0.9, 1.1), w / 2 + rng.normal(0, 3),
                         h / 2 + rng.normal(0, 3), dist)


def small_rotation(rng: np.random.Generator, deg: float) -> np.ndarray:
    return Rotation.from_rotvec(rng.normal(size=3) * np.radians(deg)).as_matrix()


# ---------------------------------------------------------------------------- projection


@quick
@given(seeds, st.booleans())
def test_project_points_keeps_exactly_the_visible_points(seed: int, distorted: bool) -> None:
    """A point is kept iff it is in front (z > min_z) and its pixel is in the image, and its
    pixel is OpenCV's; behind-camera points never come back, whatever their x, y."""
    rng = np.random.default_rng(seed)
    cam = random_camera(rng, distorted)
    P = np.c_[rng.uniform(-1.5, 1.5, (300, 2)), rng.uniform(-3.0, 5.0, 300)]  # [300, 3]
    P[:, :2] *= np.abs(P[:, 2:]) + 0.1
    uv, z, keep = project_points(cam, P, min_z=0.05)
    assert (P[keep, 2] > 0.05).all()
    if keep.any():  # OpenCV returns None for no points
        ref, _ = cv2.projectPoints(P[keep], np.zeros(3), np.zeros(3), cam.K, cam.dist)
        np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-6)
    np.testing.assert_array_equal(z, P[keep, 2])
    assert cam.in_image(uv).all()
    # Pixels are whole: every kept point's pixel index lies in the image.
    px = np.rint(uv).astype(int)
    assert ((px >= 0) & (px < [cam.width, cam.height])).all()
    # Points in front whose ray is well inside the image and the lens model's range are kept.
    xy = P[:, :2] / np.where(P[:, 2:] > 0, P[:, 2:], 1)
    uv_all, _ = cam.project(P)
    ok = (P[:, 2] > 0.05) & np.isfinite(uv_all).all(1) & cam.in_image(uv_all, margin=1.0)
    if distorted:
        # rays past the distortion's fold are dropped on purpose
        back = cam.undistort_points(np.nan_to_num(uv_all[ok]))
        good = np.linalg.norm(back - xy[ok], axis=1) < 1e-6
        ok[np.flatnonzero(ok)[~good]] = False
    assert keep[ok].all()


@quick
@given(seeds, st.booleans(), st.floats(0.0, 0.2))
def test_projector_places_scan_at_its_stamp_and_image_at_its_own(seed: int, distorted: bool,
                                                                 dt: float) -> None:
    """With poses, a scan point lands where the camera at the image stamp sees the world
    point the laser measured at the scan stamp: T_camera(t_img)^-1 T_world_base(t_scan)
    T_base_laser, for any rig and any motion between the two stamps."""
    rng = np.random.default_rng(seed)
    cam = random_camera(rng, distorted, 320, 240)
    T_base_camera = g.se3(R_BASE_OPTICAL @ small_rotation(rng, 5) @ np.diag([1, 1, 1]),
                          rng.normal(0, 0.2, 3))
    T_base_laser = g.se3(small_rotation(rng, 2), rng.normal(0, 0.2, 3))
    rig = Rig(cam, T_base_camera, T_base_laser)
    n = 360
    ranges = rng.uniform(0.5, 8.0, n)
    scan = LaserScan(10.0, ranges, -np.pi, 2 * np.pi / n)
    frame = CameraFrame.from_array(10.0 + dt, np.zeros((240, 320, 3), np.uint8))
    seq = Sequence(rig, [frame], [scan])
    pose_scan = g.se2_to_se3(*rng.normal(0, 3, 2), rng.uniform(-np.pi, np.pi))
    pose_img = pose_scan @ g.se2_to_se3(*rng.normal(0, 0.3, 2), rng.normal(0, 0.3))
    lp = LidarProjector(seq, pose_img[None], pose_scan[None], max_dt=0.25).project_frame(0)
    # Expected: float32 ranges as the scan holds them
    r = scan.ranges.astype(np.float64)
    a = scan.angle_min + np.arange(n) * scan.angle_increment
    p_laser = np.c_[r * np.cos(a), r * np.sin(a), np.zeros(n)]  # [n, 3]
    world = g.transform_points(pose_scan @ T_base_laser, p_laser)
    pc = g.transform_points(g.inv_se3(pose_img @ T_base_camera), world)  # [n, 3]
    _, _, keep = project_points(cam, pc)
    assert sorted(lp.beam.tolist()) == np.flatnonzero(keep).tolist()
    np.testing.assert_allclose(lp.points_cam, pc[lp.beam], atol=1e-9)
    uv, _ = cam.project(pc[lp.beam])
    np.testing.assert_allclose(lp.uv, uv, atol=1e-6)
    assert (lp.scan == 0).all()



@quick
@given(seeds, st.integers(1, 4))
def test_projector_takes_the_nearest_usable_scans(seed: int, n: int) -> None:
    """scan_indices gives the n nearest scans among the usable ones (ties to the earlier),
    within max_dt, nearest first - however the unusable ones lie around the image stamp
    (a brute-force sort of every usable stamp is the reference)."""
    rng = np.random.default_rng(seed)
    cam = PinholeCamera(32, 24, 30.0, 30.0, 15.5, 11.5, np.zeros(5))
    stamps = np.sort(np.round(rng.uniform(0, 2, int(rng.integers(1, 40))), 2))  # ties too
    usable = rng.uniform(size=len(stamps)) < rng.uniform(0.1, 1.0)
    scans = [LaserScan(float(t), np.ones(3), 0.0, 0.1) for t in stamps]
    seq = Sequence(Rig(cam), [], scans)
    max_dt = float(rng.uniform(0.05, 1.0))
    proj = LidarProjector(seq, scans_per_frame=n, max_dt=max_dt, scan_usable=usable)
    cand = np.flatnonzero(usable)
    for t in rng.uniform(-0.5, 2.5, 30):
        order = cand[np.argsort(np.abs(stamps[cand] - t), kind="stable")[:n]]
        expect = [int(k) for k in order if abs(stamps[k] - t) <= max_dt]
        assert proj.scan_indices(float(t)) == expect, (t, stamps.tolist(), usable.tolist())

# ---------------------------------------------------------------------------- depth -> points


def plane_depth(cam: PinholeCamera, normal: np.ndarray, d: float) -> np.ndarray:
    """[H, W] z-depth of the plane n . X = d through every pixel centre."""
    rays = cam.pixel_rays()  # [H, W, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        return d / (rays @ normal)


@quick
@given(seeds, st.booleans(), st.integers(1, 3))
def test_depth_to_points_inverts_projection(seed: int, distorted: bool, stride: int) -> None:
    """Back-projected depth pixels project back to their own pixel at their own depth, and
    land where T_world_camera puts them."""
    rng = np.random.default_rng(seed)
    cam = random_camera(rng, distorted, int(rng.integers(16, 120)), int(rng.integers(16, 90)))
    depth = rng.uniform(0.5, 5.0, (cam.height, cam.width)).astype(np.float32)  # [H, W]
    rgb = rng.integers(0, 256, (cam.height, cam.width, 3), dtype=np.uint8)
    T = g.se3(Rotation.random(random_state=rng).as_matrix(), rng.normal(0, 3, 3))
    opts = CloudOptions(min_depth_m=0.0, max_depth_m=np.inf, edge_threshold=0.0, stride=stride)
    rays = RayCache(cam, stride)
    pw, col, idx = depth_to_points(depth, rgb, rays, T, opts)
    h, w = rays.shape
    rows, cols = np.divmod(idx, w)
    rows, cols = rows * stride, cols * stride
    reachable = np.isfinite(cam.pixel_rays()[::stride, ::stride, 0])
    assert len(idx) == reachable.sum()
    np.testing.assert_array_equal(col, rgb[rows, cols])
    pc = g.transform_points(g.inv_se3(T), pw.astype(np.float64))  # [N, 3]
    uv, z = cam.project(pc)
    np.testing.assert_allclose(z, depth[rows, cols], rtol=1e-5)
    # Near a lens model's peak undistortion converges only to its documented tolerance.
    np.testing.assert_allclose(uv, np.c_[cols, rows], atol=UNDISTORT_TOL_PX if distorted else 1e-3)


@quick
@given(seeds, st.floats(0.0, 60.0), st.booleans())
def test_filters_keep_a_slanted_planar_wall(seed: int, slant_deg: float,
                                            distorted: bool) -> None:
    """A plane has no depth edge: the ramp filter (inverse depth is affine on a pinhole image)
    keeps all of it whatever the slant, and the range filter agrees with a max/min filter
    reference (scipy.ndimage) on every pixel."""
    rng = np.random.default_rng(seed)
    cam = random_camera(rng, distorted, int(rng.integers(24, 160)), int(rng.integers(24, 120)))
    az = rng.uniform(0, 2 * np.pi)
    s = np.radians(slant_deg)
    normal = np.array([np.sin(s) * np.cos(az), np.sin(s) * np.sin(az), np.cos(s)])
    depth = plane_depth(cam, normal, rng.uniform(0.5, 5.0)).astype(np.float32)
    assume_ok = np.isfinite(depth) & (depth > 0)
    if not assume_ok.all():
        return  # the plane does not cover the image (a ray parallel to it)
    if not distorted:
        assert not ramp_mask(depth, 0.02).any()
    thr = 0.06
    got = edge_mask(depth, thr, 5)
    hi = ndimage.maximum_filter(depth, size=5, mode="nearest")
    lo = ndimage.minimum_filter(depth, size=5, mode="nearest")
    ratio = (hi.astype(np.float64) - lo) / depth
    clear = np.abs(ratio - thr) > 1e-4
    np.testing.assert_array_equal(got[clear], (ratio > thr)[clear])


# ---------------------------------------------------------------------------- voxel map


def random_frames(rng: np.random.Generator, n_frames: int) -> list[tuple[np.ndarray, ...]]:
    frames = []
    for _ in range(n_frames):
        n = int(rng.integers(0, 400))
        spread = rng.choice([0.05, 0.5, 50.0])  # compact (key table) and wide (sort) frames
        pts = rng.normal(0, spread, (n, 3)) + rng.normal(0, 0.2, 3)
        pts[: n // 4] = np.round(pts[: n // 4] / 0.04) * 0.04  # exactly on voxel faces
        frames.append((pts, rng.integers(0, 256, (n, 3), dtype=np.uint8), rng.uniform(0, 1, n),
                       rng.uniform(0.2, 6.0, n)))
    return frames


@quick
@given(seeds, st.integers(1, 6), st.integers(1, 2000))
def test_voxel_map_fusion_is_order_free_and_averages(seed: int, n_frames: int,
                                                     batch: int) -> None:
    """Frames fused in any order and batch size give the same map (floats to tolerance);
    each voxel holds the mean position and rounded mean colour of its points, their count,
    the frames that saw it and the first and last of them."""
    rng = np.random.default_rng(seed)
    vs = 0.04
    frames = random_frames(rng, n_frames)
    ids = rng.permutation(100)[:n_frames]  # frame indices, not in order
    maps = []
    for order in (np.arange(n_frames), rng.permutation(n_frames)):
        m = VoxelMap(vs, batch_entries=batch if len(maps) else 1_000_000)
        for k in order:
            pts, col, lab, dep = frames[k]
            m.integrate(pts, col, int(ids[k]), labels=lab, depths=dep)
        maps.append(m.arrays())
    a, b = maps
    np.testing.assert_allclose(a.points, b.points, rtol=0, atol=1e-12)
    for f in ("colors", "count", "frames", "first", "last"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)
    np.testing.assert_allclose(a.label, b.label, atol=1e-6)
    np.testing.assert_allclose(a.near, b.near, rtol=1e-6)
    # Reference: group all points by floor(p / vs) with numpy
    P = np.concatenate([f[0] for f in frames]) if n_frames else np.zeros((0, 3))
    C = np.concatenate([f[1] for f in frames]).astype(np.float64)
    F = np.concatenate([np.full(len(f[0]), ids[k]) for k, f in enumerate(frames)])
    cell = np.floor(P / vs).astype(np.int64)
    uc, inv = np.unique(cell, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    assert len(a) == len(uc)
    cnt = np.bincount(inv, minlength=len(uc))
    mean = np.stack([np.bincount(inv, P[:, k], len(uc)) for k in range(3)], 1) / cnt[:, None]
    # Our voxel of each reference one, by its mean (floor(mean / vs) can fall an ulp into
    # the neighbour for points on a voxel face)
    dist, ref_order = cKDTree(mean).query(a.points)
    assert dist.max() < 1e-9 and len(set(ref_order.tolist())) == len(uc)
    np.testing.assert_array_equal(a.count, cnt[ref_order])
    cmean = np.stack([np.bincount(inv, C[:, k], len(uc)) for k in range(3)], 1) / cnt[:, None]
    np.testing.assert_array_equal(a.colors, np.rint(cmean[ref_order]))
    pairs = np.unique(np.c_[inv, F], axis=0)  # [K, 2] (voxel, frame) seen
    nfr = np.bincount(pairs[:, 0], minlength=len(uc))
    np.testing.assert_array_equal(a.frames, nfr[ref_order])
    first, last = np.full(len(uc), 10**6), np.full(len(uc), -1)
    np.minimum.at(first, inv, F)
    np.maximum.at(last, inv, F)
    np.testing.assert_array_equal(a.first, first[ref_order])
    np.testing.assert_array_equal(a.last, last[ref_order])

# ---------------------------------------------------------------------------- carving


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """T_world_camera (optical frame) at ``eye`` looking at ``target``, image down = -z."""
    zc = target - eye
    zc /= np.linalg.norm(zc)
    xc = np.cross(zc, [0.0, 0.0, 1.0])
    xc /= np.linalg.norm(xc)
    return g.se3(np.c_[xc, np.cross(zc, xc), zc], eye)


def render_depth(cam: PinholeCamera, T_world_camera: np.ndarray,
                 boxes: list[tuple[np.ndarray, np.ndarray]], wall_x: float) -> np.ndarray:
    """[H, W] z-depth of the wall x = wall_x and axis-aligned boxes (lo, hi) in front."""
    rays = cam.pixel_rays().reshape(-1, 3)  # [HW, 3] z = 1
    d = rays @ T_world_camera[:3, :3].T  # world direction per unit z
    o = T_world_camera[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (wall_x - o[0]) / d[:, 0]
        t = np.where(t > 0, t, np.inf)
        for lo, hi in boxes:
            t1, t2 = (lo - o) / d, (hi - o) / d
            # NaN (a ray in a face's plane) bounds nothing
            tn = np.where(np.isnan(t1), -np.inf, np.minimum(t1, t2)).max(1)
            tf = np.where(np.isnan(t1), np.inf, np.maximum(t1, t2)).min(1)
            hit = (tn <= tf) & (tn > 0)
            t = np.where(hit & (tn < t), tn, t)
    return t.reshape(cam.height, cam.width)


@few
@given(seeds, st.booleans())
def test_carving_removes_a_box_that_left_and_never_a_static_wall(seed: int,
                                                                 distorted: bool) -> None:
    """Map = a wall seen by every frame + a box fused from frame 0 only. Depth views of the
    later frames (the box gone) carve the whole box and no wall voxel."""
    rng = np.random.default_rng(seed)
    cam = random_camera(rng, distorted, 96, 72)
    cam = PinholeCamera(96, 72, 60.0, 60.0, 47.5, 35.5, cam.dist)
    wall_x = 6.0
    centre = np.r_[rng.uniform(2.5, 3.5), rng.uniform(-0.3, 0.3), rng.uniform(-0.2, 0.2)]
    half = rng.uniform(0.15, 0.3, 3)
    box = (centre - half, centre + half)
    vs = 0.05
    vm = VoxelMap(vs)
    views = []
    for k in range(8):
        eye = np.r_[rng.uniform(-0.5, 0.5), rng.uniform(-1.0, 1.0), rng.uniform(-0.2, 0.2)]
        T = look_at(eye, np.r_[wall_x, rng.uniform(-0.5, 0.5), 0.0])
        dep = render_depth(cam, T, [box] if k == 0 else [], wall_x)
        ok = np.isfinite(dep) & (dep < 8.0)
        pc = cam.pixel_rays()[ok] * dep[ok][:, None]
        pw = g.transform_points(T, pc)
        vm.integrate(pw, np.zeros((len(pw), 3), np.uint8), k)
        views.append((T, np.where(ok, dep, np.nan)))
    m = vm.arrays()
    on_box = (np.abs(m.points - centre) <= half + 1e-6).all(1)
    on_wall = np.abs(m.points[:, 0] - wall_x) < 1e-6
    assert on_box.sum() > 10 and on_wall.sum() > 100 and (on_box | on_wall).all()
    counter = SeeThroughCounter(m.points, CarveOptions(min_free=3))
    for k, (T, dep) in enumerate(views):
        counter.add_depth_view(cam, g.inv_se3(T), dep, index=k)
    gone = counter.dynamic_mask()
    assert not gone[on_wall].any()
    # Box voxels the later frames see (all of its front; the back hides behind it)
    seen_later = counter.free + counter.hit >= 3
    assert gone[on_box & seen_later].all() and (on_box & seen_later).sum() > 5


@quick
@given(seeds)
def test_lidar_never_carves_a_static_wall_and_carves_what_left(seed: int) -> None:
    """Scans of a straight wall from random places and angles (grazing too) never see
    through it; a post hit by the first scan and gone from the next ones is carved."""
    rng = np.random.default_rng(seed)
    wall_x = 5.0
    n = int(rng.choice([360, 720, 1081]))
    span = 2 * np.pi if n != 1081 else np.radians(270)
    inc = span / n
    a0 = -span / 2
    post = np.r_[rng.uniform(2.0, 3.5), rng.uniform(-1, 1)]
    ys = np.arange(-20.0, 20.0, 0.02)
    wall = np.c_[np.full(len(ys), wall_x), ys, np.zeros(len(ys))]  # [M, 3]
    ang = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    post_pts = np.c_[post + 0.1 * np.c_[np.cos(ang), np.sin(ang)], np.zeros(60)]
    counter = SeeThroughCounter(np.r_[wall, post_pts], CarveOptions(min_free=3))
    for k in range(10):
        xy = np.r_[rng.uniform(-1.0, 1.5), rng.uniform(-3, 3)]
        yaw = rng.uniform(-np.pi, np.pi)
        T_world_laser = g.se2_to_se3(xy[0], xy[1], yaw)
        a = a0 + np.arange(n) * inc + yaw  # world bearings
        d = np.c_[np.cos(a), np.sin(a)]
        with np.errstate(divide="ignore"):
            r = np.where(d[:, 0] > 0, (wall_x - xy[0]) / d[:, 0], np.inf)
        r = np.where(r < 30.0, r, np.inf)
        if k == 0:  # the post is there
            oc = post - xy
            b = d @ oc
            disc = b * b - (oc @ oc - 0.01)
            t = b - np.sqrt(np.maximum(disc, 0))
            r = np.where((disc > 0) & (t > 0) & (t < r), t, r)
        scan = LaserScan(float(k), r, a0, inc, range_max=30.0)
        counter.add_scan(scan, g.inv_se3(T_world_laser))
    gone = counter.dynamic_mask()
    assert not gone[: len(wall)].any()
    hit_post = counter.lidar_hit[len(wall):] > 0
    seen = hit_post & (counter.free[len(wall):] >= 3)
    assert gone[len(wall):][seen].all()


# ---------------------------------------------------------------------------- depth


def channel_model(path: Path, channel: int, pool: int) -> Path:
    """An ONNX model whose output is input channel ``channel`` [1, 1, h, w], averaged over
    ``pool`` x ``pool`` blocks (an output at a fraction of the input's resolution)."""
    from onnx import TensorProto, helper, numpy_helper
    from onnx_graphs import save_graph  # the tests folder is on sys.path

    idx = numpy_helper.from_array(np.array([channel], np.int64), "idx")
    nodes = [helper.make_node("Constant", [], ["idx"], value=idx),
             helper.make_node("Gather", ["image", "idx"], ["c" if pool > 1 else "depth"],
                              axis=1)]
    if pool > 1:
        nodes.append(helper.make_node("AveragePool", ["c"], ["depth"],
                                      kernel_shape=[pool, pool], strides=[pool, pool]))
    return save_graph(path, nodes, [helper.make_tensor_value_info(
        "image", TensorProto.FLOAT, [1, 3, "h", "w"])])


@few
@given(seeds, st.sampled_from(["rgb", "bgr"]), st.integers(0, 2))
def test_onnx_preprocess_matches_a_hand_normalisation(tmp_path: Path, seed: int, order: str,
                                                      channel: int) -> None:
    """At the network's own size the input is (pixel / 255 - mean) / std in the configured
    channel order, channels first; a model that returns one input channel gives it back
    over the image unchanged."""
    from toolkit.depth.onnx_backend import OnnxDepthBackend, OnnxDepthConfig

    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(8, 40)), int(rng.integers(8, 40))
    mean, std = tuple(rng.uniform(0.2, 0.6, 3)), tuple(rng.uniform(0.1, 0.4, 3))
    model = channel_model(tmp_path / "c.onnx", channel, 1)
    be = OnnxDepthBackend(OnnxDepthConfig(
        model=model, kind="relative_disparity", input_size=(h, w), multiple_of=1,
        mean=mean, std=std, channel_order=order, threads=1, device="cpu"))
    rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    src = rgb if order == "rgb" else rgb[..., ::-1]
    expect = (src / 255.0 - np.array(mean)) / np.array(std)  # [h, w, 3] float64
    x = be.preprocess(rgb)
    assert x.shape == (1, 3, h, w) and x.dtype == np.float32
    np.testing.assert_allclose(x[0].transpose(1, 2, 0), expect, rtol=1e-5, atol=1e-5)
    out = be.predict(rgb).values
    np.testing.assert_allclose(out, expect[..., channel], rtol=1e-5, atol=1e-5)


@quick
@given(seeds, st.sampled_from(["stretch", "keep_aspect", "letterbox"]), st.sampled_from([1, 2, 4]),
       st.sampled_from(["linear", "cubic", "area", "nearest"]))
def test_onnx_output_of_a_uniform_image_is_uniform_over_the_image(
        tmp_path: Path, seed: int, resize: str, pool: int, interp: str) -> None:
    """A uniform image stays uniform through any resize to the network and its output's
    resize back, at any output resolution: a letterbox's fill (set far from the image's
    colour) must not bleed into the image's border. (An output pixel that straddles the
    image's edge in the input mixes fill and image in the network itself: there only the
    rows and columns beyond it are checked.)"""
    from toolkit.depth.onnx_backend import OnnxDepthBackend, OnnxDepthConfig

    rng = np.random.default_rng(seed)
    H, W = int(rng.integers(12, 90)), int(rng.integers(12, 90))
    ih, iw = 4 * int(rng.integers(4, 20)), 4 * int(rng.integers(4, 20))
    size = ih if resize == "keep_aspect" else (ih, iw)
    colour = rng.integers(0, 256, 3)
    model = channel_model(tmp_path / "c.onnx", 1, pool)
    be = OnnxDepthBackend(OnnxDepthConfig(
        model=model, kind="relative_disparity", input_size=size, multiple_of=4, resize=resize,
        interpolation=interp, mean=(0.5, 0.5, 0.5), std=(0.25, 0.25, 0.25),
        fill=(255.0 - colour).astype(float).tolist() if resize == "letterbox" else None,
        threads=1, device="cpu"))
    rgb = np.broadcast_to(colour.astype(np.uint8), (H, W, 3)).copy()
    out = be.predict(rgb).values
    assert out.shape == (H, W)
    top, left, nh, nw = be.placement((H, W))
    inner = (slice(None), slice(None))
    if any(e % pool for e in (top, left, top + nh, left + nw)):
        # the straddling output pixel spans up to pool input rows into the image, reaches
        # half an output pixel further when upsampled and one input row more when resized
        # to the image; the input's rows are H / nh image rows apart (columns: W / nw)
        k = 2 * pool + 2
        mr, mc = int(np.ceil(k * H / nh)) + 1, int(np.ceil(k * W / nw)) + 1
        inner = (slice(mr, max(mr, H - mr)), slice(mc, max(mc, W - mc)))
    np.testing.assert_allclose(out[inner], (colour[1] / 255.0 - 0.5) / 0.25, atol=1e-5)



@quick
@given(seeds, st.sampled_from([2, 4]), st.integers(1, 3), st.booleans())
def test_onnx_letterbox_fill_stays_out_of_a_coarse_output(tmp_path: Path, seed: int, pool: int,
                                                          up: int, bands_above: bool) -> None:
    """A letterbox whose fill ends on the output's pixel grid: an output at 1/pool of the
    input holds pure fill and pure image pixels, and none of the fill's prediction may
    reach the image (upsampled bilinearly, the fill's last output row was blended into the
    image's first rows)."""
    from toolkit.depth.onnx_backend import OnnxDepthBackend, OnnxDepthConfig

    rng = np.random.default_rng(seed)
    fill_side = pool * int(rng.integers(1, 6))  # fill on each side, a whole output pixel
    n_img, n_other = pool * int(rng.integers(2, 12)), pool * int(rng.integers(2, 12))
    ih, iw = (n_img + 2 * fill_side, n_other) if bands_above else (n_other, n_img + 2 * fill_side)
    H, W = (n_img * up, n_other * up) if bands_above else (n_other * up, n_img * up)
    colour = rng.integers(0, 256, 3)
    be = OnnxDepthBackend(OnnxDepthConfig(
        model=channel_model(tmp_path / "c.onnx", 0, pool), kind="relative_disparity",
        input_size=(ih, iw), multiple_of=pool, resize="letterbox", interpolation="linear",
        mean=(0.5, 0.5, 0.5), std=(0.25, 0.25, 0.25),
        fill=(255.0 - colour).astype(float).tolist(), threads=1, device="cpu"))
    assert be.placement((H, W)) == ((fill_side, 0, n_img, n_other) if bands_above else
                                    (0, fill_side, n_other, n_img))
    rgb = np.broadcast_to(colour.astype(np.uint8), (H, W, 3)).copy()
    out = be.predict(rgb).values
    np.testing.assert_allclose(out, (colour[0] / 255.0 - 0.5) / 0.25, atol=1e-5)


@few
@given(seeds, st.integers(0, 2))
def test_onnx_output_resized_back_lands_on_its_pixels(tmp_path: Path, seed: int,
                                                      channel: int) -> None:
    """A ramp image run at twice its size (linear resizes both ways) through a model that
    returns one input channel comes back as that ramp, away from the border: the resize to
    the network and the one back share pixel centres (a half-pixel slip would move it by
    half its slope of 3-5 grey levels a pixel)."""
    from toolkit.depth.onnx_backend import OnnxDepthBackend, OnnxDepthConfig

    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(8, 24)), int(rng.integers(8, 24))
    be = OnnxDepthBackend(OnnxDepthConfig(
        model=channel_model(tmp_path / "c.onnx", channel, 1), kind="relative_disparity",
        input_size=(2 * h, 2 * w), multiple_of=1, interpolation="linear",
        mean=(0.0, 0.0, 0.0), std=(1.0, 1.0, 1.0), threads=1, device="cpu"))
    a, b = rng.choice([-1, 1], 2) * rng.uniform(3, 5, 2)
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    ramp = a * u + b * v
    ramp += 5 - ramp.min()  # [h, w] in 5..245
    rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    rgb[..., channel] = np.rint(ramp)
    out = be.predict(rgb).values
    # the image and the upsampled input are whole grey levels: half a level each
    np.testing.assert_allclose(out[1:-1, 1:-1], ramp[1:-1, 1:-1] / 255.0, atol=1.0 / 255 + 1e-6)

@quick
@given(seeds, st.floats(0.05, 20.0), st.sampled_from(["relative_depth", "relative_disparity",
                                                        "metric_depth"]))
def test_simulated_backend_documented_parameters(seed: int, scale: float, kind: str) -> None:
    """No errors: the prediction is scale x ground truth (its inverse for disparity), exactly
    in float32, NaN where the truth has no depth; the 'groundtruth' preset is the truth; and
    as_depth with the inverse scale gives the truth back."""
    from toolkit.depth.protocol import DepthPrediction
    from toolkit.depth.simulated import PRESETS, SimulatedDepthBackend, SimulatedDepthParams

    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(4, 60)), int(rng.integers(4, 60))
    gt = rng.uniform(0.3, 30.0, (h, w)).astype(np.float32)
    gt[rng.uniform(size=(h, w)) < 0.1] = np.nan
    gt[rng.uniform(size=(h, w)) < 0.05] = 0.0
    rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    truth = np.where(gt > 0, gt, np.nan)
    params = SimulatedDepthParams(**{**PRESETS["scale_only"], "kind": kind, "scale": scale,
                                     "shift": 0.0, "seed": int(rng.integers(0, 1000))})
    be = SimulatedDepthBackend(params)
    index = int(rng.integers(0, 500))
    p = be.predict(rgb, gt_depth=gt, frame_index=index)
    assert be.frame_scale(index) == scale and p.extra["true_scale"] == scale
    z = np.float32(gt) * np.float32(scale)
    with np.errstate(divide="ignore"):
        expect = 1.0 / z if kind == "relative_disparity" else z
    np.testing.assert_array_equal(np.isnan(p.values), np.isnan(truth))
    np.testing.assert_allclose(p.values, np.where(np.isnan(truth), np.nan, expect), rtol=2e-7)
    back = p.as_depth(scale=scale) if kind == "relative_disparity" else p.as_depth(1 / scale)
    np.testing.assert_allclose(back, truth, rtol=1e-6)
    exact = SimulatedDepthBackend(SimulatedDepthParams(**PRESETS["groundtruth"]))
    got = exact.predict(rgb, gt_depth=gt, frame_index=index).values
    np.testing.assert_array_equal(got, np.where(np.isnan(truth), np.nan, gt))
    d = DepthPrediction(1.0 / (2.5 * truth) - 0.1, "relative_disparity")
    np.testing.assert_allclose(d.as_depth(1.0, 0.1) / 2.5, truth, rtol=1e-5)


# ---------------------------------------------------------------------------- eval metrics


@few
@given(seeds, st.floats(0.001, 0.2))
def test_mesh_distances_of_samples_and_offset_points(seed: int, offset: float) -> None:
    """Points sampled on a mesh are on it (distance ~ 0), wherever the mesh lies (UTM-sized
    coordinates included); moved out along a box face's normal by d they are d from it."""
    import open3d as o3d

    from toolkit.eval.geometry import mesh_distances, sample_mesh

    rng = np.random.default_rng(seed)
    size = rng.uniform(0.5, 5.0, 3)
    box = o3d.geometry.TriangleMesh.create_box(*size)
    T = g.se3(Rotation.random(random_state=rng).as_matrix(),
              rng.choice([1.0, 1e3, 5e6]) * rng.uniform(-1, 1, 3))
    box.transform(T)
    pts = sample_mesh(box, spacing_m=0.05, seed=int(rng.integers(0, 100)))
    assert np.abs(mesh_distances(pts, box)).max() < 1e-5 * max(1.0, size.max())
    # The face x = size[0] of the box, its outward normal +x, away from the edges
    q = np.c_[np.full(200, size[0]), rng.uniform(0.1, 0.9, (200, 2)) * size[1:]]
    q[:, 0] += offset
    got = mesh_distances(g.transform_points(T, q), box)
    np.testing.assert_allclose(got, offset, atol=2e-6)


@quick
@given(seeds, st.floats(0.001, 0.3))
def test_geometry_metrics_at_a_known_offset(seed: int, offset: float) -> None:
    """A reconstruction that is the reference moved by d along the normal of its plane: every
    point is d from the other side, so accuracy = completeness = Chamfer = d, and precision,
    recall and F-score are 1 below a threshold above d and 0 at one below it."""
    from toolkit.eval.geometry import geometry_metrics, within_key  # noqa: F401

    rng = np.random.default_rng(seed)
    n = int(rng.integers(5, 40))
    u, v = np.meshgrid(np.arange(n) * 0.01, np.arange(n) * 0.01)
    ref = np.c_[u.ravel(), v.ravel(), np.zeros(n * n)]  # [M, 3] 1 cm grid, spacing < offset?
    R = Rotation.random(random_state=rng).as_matrix()
    ref_w = ref @ R.T
    rec_w = (ref + [0, 0, offset]) @ R.T
    # The nearest reference point of each moved one is its own only when the offset
    # grid spacing allows it: on a 1 cm grid the moved point's nearest is straight below.
    lo, hi = offset * 0.5, offset * 1.5
    m = geometry_metrics(rec_w, ref_w, thresholds_m=(lo, hi))
    for k in ("accuracy_mean_m", "accuracy_median_m", "accuracy_rmse_m", "completeness_mean_m",
              "completeness_median_m", "chamfer_m"):
        assert m[k] == pytest.approx(offset, rel=1e-9, abs=1e-12), k
    tag_lo, tag_hi = [k.split("_", 1)[1] for k in m if k.startswith("fscore_")]
    assert (m[f"precision_{tag_lo}"], m[f"recall_{tag_lo}"], m[f"fscore_{tag_lo}"]) == (0, 0, 0)
    assert (m[f"precision_{tag_hi}"], m[f"recall_{tag_hi}"], m[f"fscore_{tag_hi}"]) == (1, 1, 1)


@quick
@given(seeds, st.booleans())
def test_psnr_and_ssim_known_answers(seed: int, as_uint8: bool) -> None:
    """Identical images: PSNR inf, SSIM 1. A constant offset c: PSNR -20 log10(c) (uint8:
    c counted on 0..1). SSIM equals scikit-image's Gaussian SSIM (sigma 1.5, population
    covariance), which is the definition this implementation follows."""
    from skimage.metrics import structural_similarity

    from toolkit.eval.image import psnr, ssim

    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(11, 48)), int(rng.integers(11, 48))
    if as_uint8:
        k = int(rng.integers(1, 40))
        a = rng.integers(0, 256 - k, (h, w, 3)).astype(np.uint8)
        b = (a + k).astype(np.uint8)
        c = k / 255.0
    else:
        c = float(rng.uniform(0.001, 0.3))
        a = rng.uniform(0, 1 - c, (h, w, 3))
        b = a + c
    assert psnr(a, a) == np.inf and ssim(a, a) == pytest.approx(1.0, abs=1e-12)
    assert psnr(a, b) == pytest.approx(-20 * np.log10(c), abs=1e-6)
    ref = structural_similarity(a.astype(np.float64) / (255.0 if as_uint8 else 1.0),
                                b.astype(np.float64) / (255.0 if as_uint8 else 1.0),
                                data_range=1.0, channel_axis=-1, gaussian_weights=True,
                                sigma=1.5, use_sample_covariance=False)
    assert ssim(a, b) == pytest.approx(ref, abs=1e-6)


# ---------------------------------------------------------------------------- calibration


@settings(max_examples=5, deadline=None)
@given(seeds)
def test_extrinsic_solve_recovers_a_known_extrinsic_in_any_view_order(seed: int) -> None:
    """Noise-free synthetic boards with a random T_camera_laser: the solve recovers it, and
    shuffling the views changes nothing beyond float noise."""
    from calibration.extrinsic import calibrate_extrinsic, make_view, transform_error
    from calibration.synthetic import default_extrinsic, make_capture

    rng = np.random.default_rng(seed)
    T_true = default_extrinsic()
    T_true = g.se3(small_rotation(rng, 3) @ T_true[:3, :3], T_true[:3, 3] + rng.normal(0, 0.05, 3))
    cap = make_capture(8, seed=int(rng.integers(0, 1000)), T_camera_laser=T_true,
                       lidar_noise=0.0, image_noise=0.0)
    views = [make_view(v.name, v.corners, cap.board, cap.camera, v.scan_points[v.on_board])
             for v in cap.views]
    res = calibrate_extrinsic(views, camera=cap.camera)
    rot, tra = transform_error(res.T_camera_laser, T_true)
    assert rot < 1e-3 and tra < 1e-4, (rot, tra)
    shuffled = [views[i] for i in rng.permutation(len(views))]
    res2 = calibrate_extrinsic(shuffled, camera=cap.camera)
    rot2, tra2 = transform_error(res2.T_camera_laser, res.T_camera_laser)
    assert rot2 < 1e-6 and tra2 < 1e-8, (rot2, tra2)


# ---------------------------------------------------------------------------- fusion helpers


@quick
@given(seeds)
def test_window_extreme_and_zbuffer_match_brute_force(seed: int) -> None:
    """The windowed minimum / maximum of every query at once, and the nearest lidar point per
    pixel, equal a loop over every query and pixel."""
    from toolkit.fusion.projection import LidarPixels, window_extreme, zbuffer_lidar

    rng = np.random.default_rng(seed)
    m = int(rng.integers(0, 60))
    keys = np.round(rng.uniform(0, 50, m), int(rng.integers(0, 3)))  # ties among keys
    vals = rng.uniform(0, 10, m)
    lo = rng.uniform(-5, 55, 40)
    hi = lo + rng.choice([0.0, 0.5, 5.0, 80.0], 40)
    for op, empty, red in ((np.minimum, np.inf, np.min), (np.maximum, -np.inf, np.max)):
        got = window_extreme(keys, vals, lo, hi, op)
        ref = [red(vals[(keys >= a) & (keys <= b)], initial=empty)
               for a, b in zip(lo, hi, strict=True)]
        np.testing.assert_array_equal(got, ref)
    n = int(rng.integers(1, 80))
    uv = np.c_[rng.uniform(-0.5, 7.5, n), rng.uniform(-0.5, 4.5, n)]
    z = np.round(rng.uniform(0.5, 3, n), 1)  # equal depths on one pixel too
    lp = LidarPixels(uv, z, np.c_[uv, z], np.arange(n), np.zeros(n, np.int64))
    zb = zbuffer_lidar(lp, (5, 8))
    px = lp.pixel
    for p in {tuple(q) for q in px.tolist()}:
        on = (px == p).all(1)
        kept = (zb.pixel == p).all(1)
        assert kept.sum() == 1 and zb.z[kept][0] == z[on].min()
    assert len(zb) == len({tuple(q) for q in px.tolist()})


@quick
@given(seeds, st.floats(0.3, 3.0), st.floats(-0.2, 0.2))
def test_edge_pairs_on_disparity_equal_those_on_its_depth(seed: int, scale: float,
                                                         shift: float) -> None:
    """edge_pairs on a disparity with (scale, shift) flags what it flags on the depth that
    disparity stands for: the test is on depth, whatever the prediction's kind."""
    from toolkit.fusion.projection import LidarPixels, edge_pairs

    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(6, 30)), int(rng.integers(6, 30))
    depth = rng.uniform(1.0, 1.1, (h, w))
    depth[:, int(rng.integers(1, w)):] += rng.uniform(0, 2)  # an edge, maybe
    depth[rng.uniform(size=(h, w)) < 0.05] = np.nan
    disp = (1.0 / depth - shift) / scale  # so that 1 / (scale * disp + shift) = depth
    n = 40
    uv = np.c_[rng.integers(0, w, n), rng.integers(0, h, n)].astype(float)
    lp = LidarPixels(uv, np.ones(n), np.zeros((n, 3)), np.arange(n), np.zeros(n, np.int64))
    a = edge_pairs(depth, lp, 0.06)
    b = edge_pairs(disp, lp, 0.06, disparity=True, scale=scale, shift=shift)
    np.testing.assert_array_equal(a, b)


@quick
@given(seeds)
def test_voxel_map_weights_count_as_repeated_points_and_survive_a_pickle(seed: int) -> None:
    """A point of integer weight w counts as w copies of it (count, mean, colour, depth);
    a map pickled with frames pending gives the same map as one never pickled."""
    import pickle

    rng = np.random.default_rng(seed)
    a, b = VoxelMap(0.05), VoxelMap(0.05, batch_entries=int(rng.integers(1, 500)))
    for k in range(int(rng.integers(1, 5))):
        n = int(rng.integers(1, 200))
        pts = rng.normal(0, 0.3, (n, 3))
        col = rng.integers(0, 256, (n, 3), dtype=np.uint8)
        dep = rng.uniform(0.5, 4, n)
        wt = rng.integers(1, 5, n)
        a.integrate(pts, col, k, depths=dep, weights=wt)
        b.integrate(np.repeat(pts, wt, 0), np.repeat(col, wt, 0), k, depths=np.repeat(dep, wt))
        if k == 0:
            b = pickle.loads(pickle.dumps(b))
    ma, mb = a.arrays(), b.arrays()
    np.testing.assert_allclose(ma.points, mb.points, atol=1e-12)
    np.testing.assert_allclose(ma.near, mb.near, rtol=1e-6)
    for f in ("colors", "count", "frames", "first", "last"):
        np.testing.assert_array_equal(getattr(ma, f), getattr(mb, f), err_msg=f)



def fuse_view(depth: np.ndarray) -> np.ndarray:
    """A carving view as the fuse stage keeps it: NaN where the frame adds no points
    (``valid_pixels``: out of range, on a depth edge)."""
    d = depth.astype(np.float32)
    return np.where(valid_pixels(d, CloudOptions(max_depth_m=8.0)), d, np.nan)


@few
@given(seeds)
def test_a_static_box_seen_by_every_frame_is_never_carved(seed: int) -> None:
    """A box and a wall in every frame, exact depth and poses, carving views masked as the
    fuse stage masks them: nothing is carved (the edge filter leaves the silhouettes,
    where a voxel's nearest pixel may look past the box, without a vote)."""
    rng = np.random.default_rng(seed)
    w, h = [(96, 72), (192, 144)][int(rng.integers(2))]
    cam = PinholeCamera(w, h, 0.62 * w, 0.62 * w, (w - 1) / 2, (h - 1) / 2, np.zeros(5))
    wall_x = 6.0
    centre = np.r_[rng.uniform(2.5, 3.5), rng.uniform(-0.3, 0.3), rng.uniform(-0.2, 0.2)]
    half = rng.uniform(0.15, 0.3, 3)
    vm = VoxelMap(0.05)
    views = []
    for k in range(8):
        eye = np.r_[rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3), rng.uniform(-0.1, 0.1)]
        T = look_at(eye, np.r_[wall_x, centre[1], 0.0])
        dep = render_depth(cam, T, [(centre - half, centre + half)], wall_x)
        ok = np.isfinite(dep) & (dep < 8.0)
        vm.integrate(g.transform_points(T, cam.pixel_rays()[ok] * dep[ok][:, None]),
                     np.zeros((int(ok.sum()), 3), np.uint8), k)
        views.append((T, fuse_view(dep)))
    m = vm.arrays()
    counter = SeeThroughCounter(m.points, CarveOptions(min_free=3))
    for k, (T, dep) in enumerate(views):
        counter.add_depth_view(cam, g.inv_se3(T), dep, index=k)
    assert not counter.dynamic_mask().any()


@few
@given(seeds)
def test_after_last_carves_a_box_that_stood_most_of_the_time_then_left(seed: int) -> None:
    """(Carving views masked as the fuse stage masks them.) A box fused in the first 5 of
    8 frames outvotes the 3 frames that see through it, so the majority rule keeps what
    they saw; with ``after_last`` the views after its last frame carve it. The wall stays
    either way."""
    rng = np.random.default_rng(seed)
    cam = PinholeCamera(96, 72, 60.0, 60.0, 47.5, 35.5, np.zeros(5))
    wall_x = 6.0
    centre = np.r_[rng.uniform(2.5, 3.5), rng.uniform(-0.3, 0.3), rng.uniform(-0.2, 0.2)]
    half = rng.uniform(0.15, 0.3, 3)
    box = (centre - half, centre + half)
    vm = VoxelMap(0.05)
    views = []
    for k in range(8):
        eye = np.r_[rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3), rng.uniform(-0.1, 0.1)]
        T = look_at(eye, np.r_[wall_x, centre[1], 0.0])
        dep = render_depth(cam, T, [box] if k < 5 else [], wall_x)
        ok = np.isfinite(dep) & (dep < 8.0)
        pw = g.transform_points(T, cam.pixel_rays()[ok] * dep[ok][:, None])
        vm.integrate(pw, np.zeros((len(pw), 3), np.uint8), k)
        views.append((T, fuse_view(dep)))
    m = vm.arrays()
    on_box = (np.abs(m.points - centre) <= half + 1e-6).all(1)
    on_wall = np.abs(m.points[:, 0] - wall_x) < 1e-6
    gone, hit = {}, {}
    for after_last in (False, True):
        counter = SeeThroughCounter(m.points, CarveOptions(min_free=3, after_last=after_last),
                                    last_frame=m.last, last_stamp=m.last.astype(float))
        for k, (T, dep) in enumerate(views):
            counter.add_depth_view(cam, g.inv_se3(T), dep, index=k)
        gone[after_last], hit[after_last] = counter.dynamic_mask(), counter.hit
        late_seen = counter.late["depth_free"] + counter.late["depth_hit"] >= 3
    # Box voxels that more early views saw where they are than the 3 later ones can see
    # through stay under the majority rule (its rim, on the early views' masked depth
    # edges, has no view that saw it there, and goes).
    kept = on_box & (hit[False] > 3)
    assert kept.any() and not gone[False][kept].any() and not gone[True][on_wall].any()
    front = on_box & late_seen  # the box's faces the later frames look at
    assert front.sum() > 5 and gone[True][front].all()


@quick
@given(seeds, st.integers(0, 600))
def test_simulated_scale_wander_does_not_depend_on_query_order(seed: int, index: int) -> None:
    """A frame's scale is the same whether the frames before it were asked first or not
    (a depth stage resumed mid-sequence predicts what an uninterrupted one did); the
    correlated noise field has the per-pixel std it is scaled to (1)."""
    from toolkit.depth.simulated import SimulatedDepthBackend, SimulatedDepthParams

    rng = np.random.default_rng(seed)
    p = SimulatedDepthParams(seed=int(rng.integers(0, 1000)), scale_log_sigma=0.3,
                             wander_sigma=0.05, noise_corr_px=float(rng.uniform(0.1, 3.0)))
    a, b = SimulatedDepthBackend(p), SimulatedDepthBackend(p)
    first = a.frame_scale(index)
    for k in range(0, 2 * index + 300, 97):
        b.frame_scale(k)
    assert b.frame_scale(index) == first
    n = a.noise_field(256, 256, index)
    assert abs(float(n.std()) - 1.0) < 0.1


@quick
@given(seeds, st.booleans())
def test_lidar_carving_does_not_depend_on_how_the_beams_are_listed(seed: int,
                                                                   full: bool) -> None:
    """The same scan listed backwards (negative increment from the last bearing) or, for a
    full turn, starting at another beam, sees through and hits the same voxels."""
    rng = np.random.default_rng(seed)
    n = 720 if full else 541
    inc = (2 * np.pi if full else np.radians(270)) / n
    a0 = float(rng.uniform(-np.pi, np.pi)) if full else -np.radians(135)
    ranges = rng.uniform(0.5, 6.0, n)
    ranges[rng.uniform(size=n) < 0.05] = np.inf
    pts = np.c_[rng.uniform(-6, 6, (3000, 2)), rng.uniform(-0.04, 0.04, 3000)]  # [V, 3]
    # and voxels on the beams' end points, to be hit
    a = a0 + np.arange(n) * inc
    ends = np.c_[ranges * np.cos(a), ranges * np.sin(a), np.zeros(n)][np.isfinite(ranges)]
    pts = np.r_[pts, ends]
    T = g.se2_to_se3(*rng.normal(0, 2, 2), rng.uniform(-np.pi, np.pi))  # T_world_laser
    world = g.transform_points(T, pts)
    listings = [(a0, inc, ranges), (a0 + (n - 1) * inc, -inc, ranges[::-1])]
    if full:
        k = int(rng.integers(1, n))
        listings.append((a0 + k * inc, inc, np.roll(ranges, -k)))
    counts = []
    for amin, step, r in listings:
        c = SeeThroughCounter(world, CarveOptions())
        c.add_scan(LaserScan(0.0, r, float(amin), float(step), range_max=30.0), g.inv_se3(T))
        counts.append((c.lidar_free.copy(), c.lidar_hit.copy()))
    assert counts[0][1].sum() > 0 and counts[0][0].sum() > 0
    # A voxel half way between two beams (to float32's precision, in which carving works)
    # may go to either, whichever way the beams are listed.
    frac = np.mod((np.arctan2(pts[:, 1], pts[:, 0]) - a0) / inc, 1.0)
    clear = np.abs(frac - 0.5) > 1e-3
    for free, hit in counts[1:]:
        np.testing.assert_array_equal(free[clear], counts[0][0][clear])
        np.testing.assert_array_equal(hit[clear], counts[0][1][clear])


@quick
@given(seeds, st.floats(0.5, 2.0))
def test_depth_errors_pooled_over_frames_equal_those_of_all_pairs(seed: int,
                                                                  scale: float) -> None:
    """Frames pooled by ErrorAccumulator score what all their pairs score together; a
    prediction of exactly scale x reference has AbsRel |scale - 1| and RMSE |scale - 1| x
    the reference's RMS; invalid pairs (NaN, 0, inf on either side) count nowhere."""
    from toolkit.eval.depth import ErrorAccumulator, depth_errors

    rng = np.random.default_rng(seed)
    acc = ErrorAccumulator()
    preds, refs = [], []
    for _ in range(int(rng.integers(1, 5))):
        ref = rng.uniform(0.3, 10, int(rng.integers(0, 50)))
        pred = ref * scale
        bad = rng.uniform(size=len(ref)) < 0.2
        ref[bad] = rng.choice([np.nan, 0.0, np.inf], int(bad.sum()))
        acc.add(pred, ref)
        preds.append(pred)
        refs.append(ref)
    p, r = np.concatenate(preds), np.concatenate(refs)
    whole, pooled = depth_errors(p, r), acc.result()
    assert whole.count == pooled.count == int((np.isfinite(r) & (r > 0)).sum())
    if whole.count:
        for k in ("rmse_m", "mae_m", "absrel", "delta1"):
            assert getattr(pooled, k) == pytest.approx(getattr(whole, k), rel=1e-9), k
        ok = np.isfinite(r) & (r > 0)
        assert whole.absrel == pytest.approx(abs(scale - 1), abs=1e-12)
        assert whole.rmse_m == pytest.approx(abs(scale - 1) * np.sqrt(np.mean(r[ok] ** 2)),
                                             rel=1e-9, abs=1e-12)


@quick
@given(seeds, st.sampled_from([0.01, 0.02, 0.05, 0.3]))
def test_voxel_keys_centres_and_map_ply_round_trip(tmp_path: Path, seed: int,
                                                   vs: float) -> None:
    """A point's voxel centre is within half a voxel of it on every axis (negative
    coordinates too); a map written as PLY reads back with its float32 positions and its
    colours exactly."""
    from toolkit.fusion.voxel_map import key_centres, read_map_ply, voxel_keys, write_map_ply

    rng = np.random.default_rng(seed)
    p = rng.normal(0, 1, (200, 3)) * rng.choice([0.1, 10.0, 1000.0])
    c = key_centres(voxel_keys(p, vs), vs)
    assert (np.abs(c - p) <= vs / 2 * (1 + 1e-9)).all()
    vm = VoxelMap(vs)
    vm.integrate(p, rng.integers(0, 256, (200, 3), dtype=np.uint8), 0)
    m = vm.arrays()
    write_map_ply(tmp_path / "m.ply", m)
    pts, col = read_map_ply(tmp_path / "m.ply")
    np.testing.assert_array_equal(pts, m.points.astype(np.float32))
    np.testing.assert_array_equal(col, m.colors)

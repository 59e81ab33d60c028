"""TSDF baseline and the ray-cast mesh renderer on scenes with known answers."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from toolkit.baselines.common import observed_mask, observed_reference, psnr
from toolkit.baselines.synthetic import SyntheticRoom, default_camera, look_at, orbit_poses
from toolkit.baselines.tsdf import (
    MeshRenderer,
    TSDFSettings,
    TSDFVolume,
    integrate_frames,
    read_mesh,
    render_mesh,
    write_mesh,
)
from toolkit.camera import PinholeCamera
from toolkit.eval.geometry import geometry_metrics, sample_mesh

o3d = pytest.importorskip("open3d")

SMALL_ROOM = SyntheticRoom(size=(3.2, 2.6, 2.2),
                           boxes=[((0.4, 1.6, 0.0), (1.0, 2.2, 0.8)),
                                  ((2.2, 0.4, 0.0), (2.8, 0.9, 1.1))])


@pytest.fixture(scope="module")
def room_frames() -> tuple[PinholeCamera, np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    cam = default_camera(160, 120, 80.0)
    poses = orbit_poses(SMALL_ROOM, 16, radius_m=0.4, height_m=1.1, sweep_deg=337.5,
                        look_distance_m=1.5)
    render = SMALL_ROOM.renderer()
    return cam, poses, [render.render(cam, T) for T in poses]


def test_renderer_interpolates_vertex_colours_with_barycentrics() -> None:
    # One triangle in the plane z = 2 with red, green and blue corners, seen head-on.
    tri = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.array([[-1.0, -1.0, 2.0], [1.5, -1.0, 2.0],
                                             [-1.0, 1.5, 2.0]])),
        o3d.utility.Vector3iVector(np.array([[0, 1, 2]])))
    tri.vertex_colors = o3d.utility.Vector3dVector(np.eye(3))
    cam = PinholeCamera(40, 30, 20.0, 20.0, 19.5, 14.5)
    rgb, depth = render_mesh(tri, cam, np.eye(4))
    u, v = 25, 10  # a pixel inside the triangle
    p = np.array([(u - cam.cx) / cam.fx * 2.0, (v - cam.cy) / cam.fy * 2.0])  # hit (x, y)
    # Barycentrics by hand: p = a v0 + b v1 + c v2 with a + b + c = 1.
    A = np.array([[-1.0, 1.5, -1.0], [-1.0, -1.0, 1.5], [1.0, 1.0, 1.0]])
    abc = np.linalg.solve(A, [p[0], p[1], 1.0])
    np.testing.assert_allclose(rgb[v, u], np.round(abc * 255), atol=1)
    assert depth[v, u] == pytest.approx(2.0, abs=1e-5)  # z-depth, not ray length
    assert depth[0, 0] == 0 and tuple(rgb[0, 0]) == (0, 0, 0)  # off the triangle: empty


def _shaded_from_cast(renderer: MeshRenderer, cam: PinholeCamera, T: np.ndarray,
                      background: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The renderer's image as it was made before its fast path: from ``cast``'s hits, the
    hit pixels picked out, float64 barycentric interpolation."""
    hits = renderer.cast(cam, T)
    rgb = np.empty((cam.height, cam.width, 3), dtype=np.uint8)
    rgb[:] = np.asarray(background, dtype=np.uint8)
    m = hits.valid
    if renderer.colors is None:
        rgb[m] = 200
    else:
        tri = renderer.triangles[hits.triangle[m]]
        b1, b2 = hits.uv[m, 0:1].astype(np.float64), hits.uv[m, 1:2].astype(np.float64)
        c = ((1.0 - b1 - b2) * renderer.colors[tri[:, 0]] + b1 * renderer.colors[tri[:, 1]]
             + b2 * renderer.colors[tri[:, 2]])
        rgb[m] = np.clip(np.round(c * 255.0), 0, 255).astype(np.uint8)
    return rgb, np.where(m, hits.depth, 0.0).astype(np.float32)


@pytest.mark.parametrize("colours", ["8-bit", "any", "none"])
def test_render_is_the_cast_hits_shaded_bit_for_bit(colours: str) -> None:
    """``render`` shades every pixel from one per-triangle colour table instead of picking
    the hit pixels out of ``cast``: the same bytes, for 8-bit vertex colours (a PLY's, the
    uint8 table), for any float colours (the float64 table) and for an uncoloured mesh."""
    mesh, _ = _wall_and_boxes()
    rng = np.random.default_rng(2)
    n = len(mesh.vertices)
    if colours == "8-bit":
        mesh.vertex_colors = o3d.utility.Vector3dVector(rng.integers(0, 256, (n, 3)) / 255.0)
    elif colours == "any":
        mesh.vertex_colors = o3d.utility.Vector3dVector(rng.random((n, 3)))
    cam = PinholeCamera(160, 120, 100.0, 100.0, 79.5, 59.5)
    renderer = MeshRenderer(mesh)
    for k, bg in enumerate([(0, 0, 0), (10, 200, 255), (255, 255, 255)]):
        T = look_at([0.3 * k, -0.4, 1.1], [3.0, 0.2 * k, 0.9])
        rgb, depth = renderer.render(cam, T, bg)
        old_rgb, old_depth = _shaded_from_cast(renderer, cam, T, bg)
        hit = depth > 0
        assert 0.2 < hit.mean() < 1.0  # background in view
        assert rgb.dtype == np.uint8 and depth.dtype == np.float32
        np.testing.assert_array_equal(rgb, old_rgb)
        np.testing.assert_array_equal(depth, old_depth)
        assert (rgb[~hit] == bg).all()
    if colours != "none":
        expect = np.uint8 if colours == "8-bit" else np.float64
        assert renderer._corner_colors().dtype == expect


def test_room_renderer_depth_equals_plane_distance() -> None:
    cam = default_camera(64, 48)
    T = look_at([1.0, 1.3, 1.1], [3.2, 1.3, 1.1])  # facing the wall x = 3.2, 2.2 m away
    _, depth = SMALL_ROOM.renderer().render(cam, T)
    assert depth[24, 32] == pytest.approx(2.2, abs=1e-5)


def test_the_seen_surface_is_built_once_for_the_same_mesh_and_poses(
        room_frames: tuple, monkeypatch: pytest.MonkeyPatch) -> None:
    """A benchmark's evaluate stages score their maps against one ground truth seen from
    the same poses: the second asks no view again, gets the same samples (a copy), and
    other poses or another mesh are built afresh."""
    import toolkit.baselines.common as common

    cam, poses, _ = room_frames
    monkeypatch.setattr(common, "_REFERENCES", {})  # none from other tests
    renders = []
    depth = MeshRenderer.depth_where  # the rays each view's test reads
    monkeypatch.setattr(MeshRenderer, "depth_where",
                        lambda self, c, T, need: renders.append(1) or depth(self, c, T, need))
    first = observed_reference(SMALL_ROOM.mesh(), cam, poses[:4], spacing_m=0.03)
    n = len(renders)
    assert n == 4 and len(first) > 1000
    first[:] = 0.0  # the caller's copy: the stored one stays
    again = observed_reference(SMALL_ROOM.mesh(), cam, poses[:4], spacing_m=0.03)
    assert len(renders) == n and np.abs(again).sum() > 0
    other = observed_reference(SMALL_ROOM.mesh(), cam, poses[:3], spacing_m=0.03)
    assert len(renders) == n + 3 and len(other) <= len(again)
    moved = SMALL_ROOM.mesh().translate([0.01, 0.0, 0.0])
    observed_reference(moved, cam, poses[:4], spacing_m=0.03)
    assert len(renders) == n + 7


def test_tsdf_from_exact_depth_matches_the_room(room_frames: tuple) -> None:
    cam, poses, frames = room_frames
    vol = integrate_frames(((d, rgb, T) for (rgb, d), T in zip(frames, poses, strict=True)), cam,
                           # ints on purpose: Open3D's bindings reject them unless cast
                           TSDFSettings(voxel_size_m=0.02, trunc_voxels=4, depth_max_m=8))
    mesh = vol.extract_mesh()
    assert len(mesh.triangles) > 10_000 and mesh.has_vertex_colors()
    # 1.5 cm sampling: a point of one set has its neighbour in the other within 2 cm with
    # probability 1 - exp(-pi (2 / 1.5)^2) = 0.996, so F @ 2 cm measures the mesh, not sampling.
    ref = observed_reference(SMALL_ROOM.mesh(), cam, poses, spacing_m=0.015)
    g = geometry_metrics(sample_mesh(mesh, 0.015), ref)
    assert g["fscore_2cm"] > 0.9, g
    assert g["accuracy_median_m"] < 0.01, g
    # Colours: the mesh rendered at a training pose looks like the image there.
    rgb, depth = MeshRenderer(mesh).render(cam, poses[5])
    m = (depth > 0) & (frames[5][1] > 0)
    assert m.mean() > 0.95
    assert psnr(rgb, frames[5][0], m) > 22.0
    assert np.abs(depth[m] - frames[5][1][m]).mean() < 0.01


def test_single_frame_integrates_and_errors_are_clear(room_frames: tuple, tmp_path: Path) -> None:
    cam, poses, frames = room_frames
    vol = TSDFVolume()
    with pytest.raises(ValueError, match="empty"):
        vol.extract_mesh()
    (rgb, d), T = frames[0], poses[0]
    with pytest.raises(ValueError, match="undistorted"):
        vol.integrate(d, rgb, PinholeCamera(160, 120, 90, 90, 80, 60, np.array([0.1])), T)
    with pytest.raises(ValueError, match="WxH"):
        vol.integrate(d[:-1], rgb, cam, T)
    d_nan = d.copy()
    d_nan[:10] = np.nan  # NaN is invalid depth, as 0 is
    vol.integrate(d_nan, rgb, cam, T)
    mesh = vol.extract_mesh()
    assert len(mesh.triangles) > 1000
    write_mesh(tmp_path / "m.ply", mesh)
    back = read_mesh(tmp_path / "m.ply")
    assert len(back.triangles) == len(mesh.triangles) and back.has_vertex_colors()
    with pytest.raises(FileNotFoundError):
        read_mesh(tmp_path / "missing.ply")


def test_observed_mask_ignores_occluded_and_out_of_view_points() -> None:
    cam = PinholeCamera(20, 20, 10.0, 10.0, 9.5, 9.5)
    depth = np.full((20, 20), 2.0, np.float32)  # a wall at z = 2
    pts = np.array([[0.0, 0.0, 2.0],  # on the wall: seen
                    [0.0, 0.0, 3.0],  # behind the wall: occluded
                    [50.0, 0.0, 2.0],  # outside the image
                    [0.0, 0.0, -2.0]])  # behind the camera
    np.testing.assert_array_equal(observed_mask(pts, cam, np.eye(4)[None], [depth]),
                                  [True, False, False, False])


def _wall_and_boxes() -> tuple[Any, dict[str, np.ndarray]]:
    """A 0.2 m thick wall 3 m ahead of a camera at (0, 0, 1) looking along +x, a box hidden
    behind it and a box in front, left of it; and points on their faces, by face."""
    def box(lo: tuple, hi: tuple) -> Any:
        b = o3d.geometry.TriangleMesh.create_box(*(np.subtract(hi, lo)))
        return b.translate(lo)

    mesh = (box((3.0, -1.0, 0.0), (3.2, 1.0, 2.0)) + box((3.6, -0.3, 0.5), (4.0, 0.3, 1.0))
            + box((1.8, 1.1, 0.5), (2.2, 1.5, 0.9)))
    g = np.linspace(0.0, 1.0, 41)[1:-1]  # [39] inside each face, off its edges
    a, b = (x.ravel() for x in np.meshgrid(g, g))

    def face(x: float | np.ndarray, y: float | np.ndarray, z: float | np.ndarray) -> np.ndarray:
        return np.stack(np.broadcast_arrays(x, y, z), -1).astype(np.float64)

    faces = {
        "wall_front": face(3.0, -1 + 2 * a, 2 * b),  # seen: nothing in front of it
        "wall_back": face(3.2, -1 + 2 * a, 2 * b),  # 0.2 m behind the front: not seen
        "hidden_front": face(3.6, -0.3 + 0.6 * a, 0.5 + 0.5 * b),  # behind the wall
        "box_front": face(1.8, 1.1 + 0.4 * a, 0.5 + 0.4 * b),  # seen where in the image
        "box_back": face(2.2, 1.1 + 0.4 * a, 0.5 + 0.4 * b),  # behind its front
    }
    return mesh, faces


def test_observed_mask_sees_a_wall_but_not_the_box_behind_it() -> None:
    """Known visibility, and the same mask whether each view's whole depth map is rendered
    (``observed_mask``) or only the rays the test reads (``observed_reference``)."""
    mesh, faces = _wall_and_boxes()
    cam = PinholeCamera(160, 120, 100.0, 100.0, 79.5, 59.5)
    T = look_at([0.0, 0.0, 1.0], [3.0, 0.0, 1.0])
    renderer = MeshRenderer(mesh)
    pts = np.concatenate(list(faces.values()))  # [M, 3]
    seen = observed_mask(pts, cam, T[None], [renderer.depth(cam, T)])
    parts = dict(zip(faces, np.split(seen, np.cumsum([len(f) for f in faces.values()])[:-1]),
                     strict=True))
    assert parts["wall_front"].all()
    assert not parts["wall_back"].any() and not parts["hidden_front"].any()
    # The side of the box facing the camera ends at its back: only the back within 5 cm
    # of that edge's depth counts.
    assert not parts["box_back"][faces["box_back"][:, 1] > 1.2].any()
    T_cw = np.linalg.inv(T)
    uv, _ = cam.project(faces["box_front"] @ T_cw[:3, :3].T + T_cw[:3, 3])
    inside = cam.in_image(uv)
    assert 0 < inside.sum() < len(inside)  # partly out of the image: that part is not seen
    np.testing.assert_array_equal(parts["box_front"], inside)
    # Several views, from both sides of the wall: the ray-cast subset gives the same mask.
    poses = np.stack([T, look_at([0.2, -0.5, 1.2], [3.0, 0.5, 0.8]),
                      look_at([5.0, 0.3, 1.5], [3.0, -0.2, 0.6]),
                      look_at([1.0, 2.5, 1.0], [2.0, 0.0, 0.7])])
    ref = sample_mesh(mesh, 0.01)
    full = observed_mask(ref, cam, poses, [renderer.depth(cam, P) for P in poses])
    assert 0.2 < full.mean() < 0.8
    np.testing.assert_array_equal(observed_reference(mesh, cam, poses, spacing_m=0.01),
                                  ref[full])


def test_depth_where_casts_the_needed_rays_bit_for_bit() -> None:
    mesh, _ = _wall_and_boxes()
    cam = PinholeCamera(160, 120, 100.0, 100.0, 79.5, 59.5)
    T = look_at([0.3, -0.4, 1.1], [3.0, 0.2, 0.9])
    renderer = MeshRenderer(mesh)
    whole = renderer.depth(cam, T)
    need = np.random.default_rng(0).random((120, 160)) < 0.3
    need[7] = False  # a row with nothing needed
    part = renderer.depth_where(cam, T, need)
    assert part.dtype == np.float32 and (whole[need] > 0).mean() > 0.2
    np.testing.assert_array_equal(part[need], whole[need])  # exactly, not approximately
    assert not part[~need].any()
    assert not renderer.depth_where(cam, T, np.zeros_like(need)).any()


@pytest.mark.parametrize("size", [(640, 480), (97, 61)])
def test_depth_where_is_bit_for_bit_at_full_size_from_many_poses(size: tuple[int, int]) -> None:
    """The needed rays' directions are rotated as one block, not image row by image row:
    at the quickstart's 640 x 480 and at an odd size (rows that are no multiple of a BLAS
    block), from poses all round, the depths are the whole view's to the bit."""
    mesh, _ = _wall_and_boxes()
    w, h = size
    cam = PinholeCamera(w, h, 0.8 * w, 0.8 * w, (w - 1) / 2, (h - 1) / 2)
    renderer = MeshRenderer(mesh)
    rng = np.random.default_rng(1)
    for k in range(6):
        eye = [rng.uniform(-0.5, 1.5), rng.uniform(-1.0, 1.0), rng.uniform(0.5, 1.5)]
        T = look_at(eye, [3.0 + rng.uniform(-0.5, 0.5), rng.uniform(-1.0, 1.0), 0.9])
        whole = renderer.depth(cam, T)
        need = rng.random((h, w)) < (0.2, 0.5, 0.9, 0.01, 1.0, 0.5)[k]
        part = renderer.depth_where(cam, T, need)
        assert (whole[need] > 0).any()
        np.testing.assert_array_equal(part[need], whole[need])
        assert not part[~need].any()


def test_observed_mask_runs_blas_on_one_thread_and_gives_the_same_mask() -> None:
    """OpenBLAS's threads made the per-view [n, 3] products 50 times slower on the busy
    2-core machine: the test runs on one, its views' renders included, and gives the mask
    the library's default threads give."""
    from threadpoolctl import threadpool_info

    from toolkit.baselines.common import _observed_mask, _observed_mask_one_blas_thread

    mesh, _ = _wall_and_boxes()
    cam = PinholeCamera(160, 120, 100.0, 100.0, 79.5, 59.5)
    poses = np.stack([look_at([0.0, 0.0, 1.0], [3.0, 0.0, 1.0]),
                      look_at([0.2, -0.5, 1.2], [3.0, 0.5, 0.8])])
    renderer = MeshRenderer(mesh)
    ref = sample_mesh(mesh, 0.01)
    blas_threads: list[set[int]] = []

    def view(T: np.ndarray) -> Any:
        def depth(need: np.ndarray) -> np.ndarray:
            blas_threads.append({i["num_threads"] for i in threadpool_info()
                                 if i["user_api"] == "blas"})
            return renderer.depth_where(cam, T, need)
        return depth

    seen = _observed_mask(ref, cam, poses, [view(T) for T in poses], 0.05, np.inf)
    assert blas_threads == [{1}, {1}] and 0.1 < seen.mean() < 0.9
    default = _observed_mask_one_blas_thread(ref, cam, poses, [view(T) for T in poses],
                                             0.05, np.inf)
    np.testing.assert_array_equal(default, seen)


def _plain_observed_mask(pts: np.ndarray, cam: PinholeCamera, poses: np.ndarray,
                         depths: list[np.ndarray], tol: float, max_depth: float) -> np.ndarray:
    """[M] bool: the per-point test written out (all points, every view, the four pixels
    around each clipped to the image)."""
    h, w = cam.height, cam.width
    expect = np.zeros(len(pts), bool)
    for T, d in zip(poses, depths, strict=True):
        T_cw = np.linalg.inv(T)
        pc = pts @ T_cw[:3, :3].T + T_cw[:3, 3]
        uv, z = cam.project(pc)
        ok = (z > 1e-6) & (z <= max_depth) & cam.in_image(uv)
        u0, v0 = np.floor(uv[ok, 0]).astype(int), np.floor(uv[ok, 1]).astype(int)
        near = np.stack([d[np.clip(v0 + dv, 0, h - 1), np.clip(u0 + du, 0, w - 1)]
                         for du in (0, 1) for dv in (0, 1)]).astype(np.float64)  # [4, n]
        valid = near > 0
        lo = np.where(valid, near, np.inf).min(0)
        hi = np.where(valid, near, -np.inf).max(0)
        expect[np.flatnonzero(ok)[(z[ok] > lo - tol) & (z[ok] < hi + tol)]] = True
    return expect


def test_observed_mask_matches_the_plain_test_at_the_image_borders() -> None:
    """Points over the whole image, its half-pixel borders included, against random depth
    maps with holes (0 and NaN): the mask is the plain per-point test's."""
    rng = np.random.default_rng(3)
    cam = PinholeCamera(40, 30, 30.0, 30.0, 19.5, 14.5)
    poses = np.stack([look_at(rng.uniform(-0.3, 0.3, 3), [0.0, 0.0, 3.0]) for _ in range(5)])
    depths = [rng.uniform(1.0, 5.0, (30, 40)).astype(np.float32) for _ in poses]
    for d in depths:
        d[rng.random(d.shape) < 0.1] = 0.0
        d[rng.random(d.shape) < 0.05] = np.nan
    pts = []
    for T, d in zip(poses, depths, strict=True):  # near each view's depth, some beyond
        uv = np.c_[rng.uniform(-0.5, 39.5, 3000), rng.uniform(-0.5, 29.5, 3000)]
        z = d[np.clip(np.round(uv[:, 1]).astype(int), 0, 29),
              np.clip(np.round(uv[:, 0]).astype(int), 0, 39)] + rng.normal(0, 0.05, 3000)
        z = np.where(np.isfinite(z) & (z > 0.1), z, 2.0)
        pc = np.c_[(uv[:, 0] - cam.cx) / cam.fx * z, (uv[:, 1] - cam.cy) / cam.fy * z, z]
        pts.append(pc @ T[:3, :3].T + T[:3, 3])
    pts = np.concatenate(pts)
    expect = _plain_observed_mask(pts, cam, poses, depths, 0.05, 4.0)
    assert 0.2 < expect.mean() < 0.9
    seen = observed_mask(pts, cam, poses, iter(depths), tolerance_m=0.05, max_depth_m=4.0)
    np.testing.assert_array_equal(seen, expect)


def test_observed_mask_matches_the_plain_test_all_round_the_cameras() -> None:
    """Points all round the cameras, behind them and in their image plane: the views
    project every candidate before they drop the ones behind or too far, and the mask is
    still the plain per-point test's."""
    rng = np.random.default_rng(5)
    cam = PinholeCamera(48, 36, 30.0, 30.0, 23.5, 17.5)
    poses = np.stack([np.eye(4)] + [look_at(rng.uniform(-1.0, 1.0, 3),
                                            rng.uniform(-3.0, 3.0, 3)) for _ in range(5)])
    depths = [rng.uniform(0.5, 4.5, (36, 48)).astype(np.float32) for _ in poses]
    for d in depths:
        d[rng.random(d.shape) < 0.1] = 0.0
    pts = rng.uniform(-4.0, 4.0, (20000, 3))  # [M, 3] all round, cubes cut by every frustum
    # In the first camera's image plane, just in front of it and behind it.
    plane = np.c_[rng.uniform(-1, 1, (300, 2)), np.repeat([0.0, 1e-7, -1.0], 100)]
    pts = np.concatenate([pts, plane])
    # Near each view's depth too, so that a fair share is seen.
    for T, d in zip(poses, depths, strict=True):
        uv = np.c_[rng.uniform(-0.5, 47.5, 2000), rng.uniform(-0.5, 35.5, 2000)]
        xy = cam.undistort_points(uv)
        z = d[np.clip(np.round(uv[:, 1]).astype(int), 0, 35),
              np.clip(np.round(uv[:, 0]).astype(int), 0, 47)] + rng.normal(0, 0.05, 2000)
        pc = np.c_[xy * z[:, None], z]
        pts = np.concatenate([pts, pc @ T[:3, :3].T + T[:3, 3]])
    expect = _plain_observed_mask(pts, cam, poses, depths, 0.05, 3.5)
    assert 0.1 < expect.mean() < 0.6
    seen = observed_mask(pts, cam, poses, iter(depths), tolerance_m=0.05, max_depth_m=3.5)
    np.testing.assert_array_equal(seen, expect)


@pytest.mark.parametrize("dist", [[-0.3, 0.0, 0.01, 0.0, 0.0],  # turns back at r = 1.05
                                  [-0.3, 0.08, 0.0, 0.0, 0.0]])  # never turns back
def test_observed_mask_keeps_what_a_distorted_image_holds(dist: list[float]) -> None:
    """A barrel lens's corners see wider than a pinhole with its fx: the views' frustum
    test bounded rays by the pinhole's, and 0.8 % (a model that turns back) and 1.8 %
    (one that does not) of these points, which the image holds, were never tested."""
    rng = np.random.default_rng(5)
    cam = PinholeCamera(48, 36, 30.0, 30.0, 23.5, 17.5, np.array(dist))
    poses = np.stack([np.eye(4)] + [look_at(rng.uniform(-1.0, 1.0, 3),
                                            rng.uniform(-3.0, 3.0, 3)) for _ in range(5)])
    depths = [rng.uniform(0.5, 4.5, (36, 48)).astype(np.float32) for _ in poses]
    for d in depths:
        d[rng.random(d.shape) < 0.1] = 0.0
    pts = [rng.uniform(-4.0, 4.0, (20000, 3))]  # [M, 3] all round
    for T, d in zip(poses, depths, strict=True):  # near each view's depth too
        uv = np.c_[rng.uniform(-0.5, 47.5, 2000), rng.uniform(-0.5, 35.5, 2000)]
        xy = cam.undistort_points(uv)
        z = d[np.clip(np.round(uv[:, 1]).astype(int), 0, 35),
              np.clip(np.round(uv[:, 0]).astype(int), 0, 47)] + rng.normal(0, 0.05, 2000)
        pc = np.c_[xy * z[:, None], z][np.isfinite(xy).all(1)]  # no ray past the peak
        pts.append(pc @ T[:3, :3].T + T[:3, 3])
    pts = np.concatenate(pts)
    expect = _plain_observed_mask(pts, cam, poses, depths, 0.05, 3.5)
    assert 0.1 < expect.mean() < 0.6
    seen = observed_mask(pts, cam, poses, iter(depths), tolerance_m=0.05, max_depth_m=3.5)
    np.testing.assert_array_equal(seen, expect)


def test_observed_mask_keeps_the_half_pixel_beside_an_off_centre_principal_point() -> None:
    """Pixel centres span -0.5 .. width - 0.5: with the principal point at the right edge
    the image reaches (cx + 0.5) / fx to the left, and the frustum test's bound, cx / fx,
    dropped the points on a wall 100 m ahead that land in the left half pixel."""
    cam = PinholeCamera(20, 10, 10.0, 10.0, 19.0, 4.5)
    u = np.linspace(-0.5, 19.49, 400)
    v = np.linspace(-0.5, 9.49, 7)
    uu, vv = (a.ravel() for a in np.meshgrid(u, v))
    pts = np.c_[(uu - cam.cx) / cam.fx * 100.0, (vv - cam.cy) / cam.fy * 100.0,
                np.full(len(uu), 100.0)]  # [M, 3] on the wall z = 100
    seen = observed_mask(pts, cam, np.eye(4)[None], [np.full((10, 20), 100.0, np.float32)])
    assert seen.all()


def test_observed_mask_leaves_non_finite_points_unseen_and_the_others_alone() -> None:
    """A NaN point was bucketed with the others: its cube index, cast from NaN, gave every
    cube a wrong centre, and the view saw none of a wall it faces."""
    cam = PinholeCamera(20, 20, 10.0, 10.0, 9.5, 9.5)
    g = np.linspace(-1.5, 1.5, 31)
    xx, yy = (a.ravel() for a in np.meshgrid(g, g))
    wall = np.c_[xx, yy, np.full(len(xx), 2.0)]  # [M, 3] on the wall z = 2, in the image
    pts = np.concatenate([wall, [[np.nan, 0.0, 2.0], [0.0, np.inf, 2.0]]])
    seen = observed_mask(pts, cam, np.eye(4)[None], [np.full((20, 20), 2.0, np.float32)])
    np.testing.assert_array_equal(seen, [True] * len(wall) + [False, False])


def test_pinhole_pixels_are_projects_bit_for_bit() -> None:
    """The reference's views place samples with ``_pinhole_pixels``: the pixels and depths
    of ``PinholeCamera.project`` to the bit wherever z > 0 (samples behind the camera and
    in its plane included in the input, dropped by z by the caller)."""
    from toolkit.baselines.common import _pinhole_pixels

    rng = np.random.default_rng(11)
    cam = PinholeCamera(640, 480, 525.3, 524.7, 319.61, 239.37)
    rotated = rng.uniform(-7.0, 7.0, (20000, 3))  # [N, 3]
    rotated[:50, 2] = 0.0
    t = np.array([0.123456789, -1.7, 0.3])
    u, v, z = _pinhole_pixels(cam, rotated, t)
    uv, zp = cam.project(rotated + t)
    front = zp > 0
    assert 0.3 < front.mean() < 0.7
    np.testing.assert_array_equal(z, zp)
    np.testing.assert_array_equal(u[front], uv[front, 0])
    np.testing.assert_array_equal(v[front], uv[front, 1])
    with pytest.raises(ValueError, match="dist="):
        _pinhole_pixels(PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5,
                                      np.array([-0.1, 0.0, 0.0, 0.0, 0.0])), rotated, t)


def test_corner_extreme_is_the_min_and_max_of_each_2x2_block() -> None:
    """``_corner_extreme`` against the four cells' min / max taken one block at a time,
    with infinities (the reference's holes) among the values."""
    from toolkit.baselines.common import _corner_extreme

    rng = np.random.default_rng(12)
    img = rng.uniform(0.5, 6.0, (9, 13)).astype(np.float32)  # [rows, row]
    img[rng.random(img.shape) < 0.2] = np.inf
    lo = _corner_extreme(img.reshape(-1), 13, np.minimum)
    hi = _corner_extreme(-img.reshape(-1), 13, np.maximum)
    assert lo.shape == hi.shape == (9 * 13 - 14,) and lo.dtype == np.float32
    for r in range(8):
        for c in range(12):
            block = img[r:r + 2, c:c + 2]
            assert lo[r * 13 + c] == block.min()
            assert hi[r * 13 + c] == (-block).max()


def test_a_grazing_floor_is_observed_where_it_is_visible() -> None:
    """The depth of a floor seen at a grazing angle changes by more than the tolerance
    from one pixel to the next: compared with the nearest pixel's alone, a fifth of the
    visible floor at 5-6 m (640x480, f 525, 0.45 m up) was left out of the reference."""
    v = np.array([[0, -2, 0], [8, -2, 0], [8, 2, 0], [0, 2, 0]], float)
    floor = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v),
                                      o3d.utility.Vector3iVector(np.array([[0, 1, 2], [0, 2, 3]])))
    cam = PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)
    T = look_at([0, 0, 0.45], [5, 0, 0.45 - 5 * np.tan(np.radians(5))])
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(0, 8, 50000), rng.uniform(-2, 2, 50000), np.zeros(50000)]
    T_cw = np.linalg.inv(T)
    uv, z = cam.project(pts @ T_cw[:3, :3].T + T_cw[:3, 3])
    visible = (z > 0) & (z <= 6.0) & cam.in_image(uv)
    depth = MeshRenderer(floor).cast(cam, T).depth
    seen = observed_mask(pts, cam, T[None], [np.where(np.isfinite(depth), depth, 0.0)],
                         tolerance_m=0.05, max_depth_m=6.0)
    far = visible & (z >= 5.0)
    assert seen[far].mean() > 0.99 and seen[visible].mean() > 0.995
    assert not (seen & ~visible).any()


def test_canonical_order_is_independent_of_how_the_mesh_was_listed() -> None:
    import open3d as o3d

    from toolkit.baselines.tsdf import canonical_order

    box = o3d.geometry.TriangleMesh.create_box(1.0, 2.0, 3.0)
    box.vertex_colors = o3d.utility.Vector3dVector(np.random.default_rng(0).random((8, 3)))
    v, t, c = (np.asarray(x) for x in (box.vertices, box.triangles, box.vertex_colors))
    perm = np.random.default_rng(1).permutation(len(v))
    inv = np.argsort(perm)
    shuffled = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v[perm]),
                                         o3d.utility.Vector3iVector(
                                             np.roll(inv[t], 1, axis=1)[::-1].astype(np.int32)))
    shuffled.vertex_colors = o3d.utility.Vector3dVector(c[perm])
    a, b = canonical_order(box), canonical_order(shuffled)
    for f in ("vertices", "vertex_colors", "triangles"):
        np.testing.assert_array_equal(np.asarray(getattr(a, f)), np.asarray(getattr(b, f)))
    # Winding kept: the outward normals of the box are unchanged.
    a.compute_triangle_normals()
    box.compute_triangle_normals()
    centre = np.asarray(a.vertices).mean(0)
    tri_c = np.asarray(a.vertices)[np.asarray(a.triangles)].mean(1)
    assert (np.sum(np.asarray(a.triangle_normals) * (tri_c - centre), 1) > 0).all()


@pytest.mark.parametrize("downsample", [1, 2])
def test_open3d_volumes_read_the_pixel_the_camera_means(downsample: int) -> None:
    """Open3D reads depth pixel int(u) where our pixel centres are integers: without the
    half-pixel shift a slanted plane came out 3.4 mm off (one exact 160x120 frame)."""
    from toolkit.fusion.consensus import ConsensusSurface

    W, H, f = 160, 120, 120.0
    cam = PinholeCamera(W, H, f, f, (W - 1) / 2, (H - 1) / 2)
    r = cam.pixel_rays()
    a, b = 0.5, 0.3  # the plane z = 1 + a x + b y in the camera
    depth = (1.0 / (1.0 - a * r[..., 0] - b * r[..., 1])).astype(np.float32)
    n = np.array([-a, -b, 1.0]) / np.linalg.norm([-a, -b, 1.0])
    d = 1.0 / np.linalg.norm([-a, -b, 1.0])
    if downsample == 1:
        vol = TSDFVolume(TSDFSettings(voxel_size_m=0.005, trunc_voxels=4, depth_max_m=3))
        vol.integrate(depth, np.full((H, W, 3), 128, np.uint8), cam, np.eye(4))
        signed = np.asarray(vol.extract_mesh().vertices) @ n - d
        assert abs(signed.mean()) < 0.5e-3
        return
    big = PinholeCamera(4 * W, 4 * H, 4 * f, 4 * f, (4 * W - 1) / 2, (4 * H - 1) / 2)
    r = big.pixel_rays()
    depth = (1.0 / (1.0 - a * r[..., 0] - b * r[..., 1])).astype(np.float32)
    cs = ConsensusSurface(big, voxel_size_m=0.01, trunc_voxels=4, depth_max_m=3,
                          downsample=downsample)
    cs.integrate(depth, np.eye(4))
    signed = cs.surface() @ n - d
    assert abs(signed.mean()) < 1e-3


def test_reference_views_follow_motion_not_frame_count() -> None:
    """A drive of 2 m then a full turn on the spot: evenly spaced frames would all but skip
    the turn (its frames are few); views every 0.25 m or 15 deg take both."""
    from toolkit.baselines.common import spread_views
    from toolkit.geometry import se2_to_se3

    drive = [se2_to_se3(x, 0.0, 0.0) for x in np.linspace(0, 2, 200)]
    turn = [se2_to_se3(2.0, 0.0, a) for a in np.linspace(0, 2 * np.pi, 24)[1:]]
    sel = spread_views(np.stack(drive + turn))
    assert sum(sel < 200) == 8 and sum(sel >= 200) == 23  # 0.25 m apart; 15.7 deg apart
    assert sel[0] == 0 and sel[-1] == 222
    assert len(spread_views(np.stack(drive + turn), max_views=5)) == 5


def test_tsdf_views_are_scored_against_the_images_at_the_meshs_exposure(
        tmp_path: Path) -> None:
    """The mesh holds the colours with fuse's exposure gains divided out; scored against
    the raw images, a frame 30 % brighter read 16.9 dB for a mesh 41.4 dB from the images
    it was built from."""
    from types import SimpleNamespace

    from toolkit.baselines.stage import TSDFConfig, TSDFStage
    from toolkit.baselines.synthetic import SyntheticRoom, default_camera, orbit_poses
    from toolkit.baselines.tsdf import TSDFSettings, TSDFVolume
    from toolkit.fusion.exposure import corrected_image

    room = SyntheticRoom(size=(3.2, 2.6, 2.2), boxes=[])
    cam = default_camera(96, 72, 50.0)
    poses = orbit_poses(room, 4, radius_m=0.3, height_m=1.1, sweep_deg=60,
                        look_distance_m=1.5)
    renderer = room.renderer()
    frames = [renderer.render(cam, T) for T in poses]
    gain = np.array([1.3, 1.3, 1.3])
    raw = [np.clip(rgb.astype(float) * gain, 0, 255).astype(np.uint8) for rgb, _ in frames]
    vol = TSDFVolume(TSDFSettings(min_observations=1))
    for img, (_, depth), T in zip(raw, frames, poses, strict=True):
        vol.integrate(depth, corrected_image(img, gain), cam, T)
    seq = SimpleNamespace(frames=[SimpleNamespace(image=im) for im in raw],
                          rig=SimpleNamespace(camera=cam))
    ctx = SimpleNamespace(stage_dir=tmp_path)
    cfg = TSDFConfig(stage="tsdf", views=2)
    out = TSDFStage._views(ctx, seq, vol.extract_mesh(), cam, np.arange(4), poses, cfg,
                           dict.fromkeys(range(4), gain))
    assert out["metrics"]["psnr_db"] > 35.0


def test_mesh_colour_is_the_mean_of_what_the_frames_saw() -> None:
    # uint16 colour storage truncated the running mean at every update: a grey 128 wall
    # seen 60 times with noise came out 116.
    W, H = 80, 60
    cam = PinholeCamera(W, H, 60.0, 60.0, (W - 1) / 2, (H - 1) / 2)
    depth = np.full((H, W), 1.5, np.float32)
    rng = np.random.default_rng(0)
    vol = TSDFVolume()
    images = []
    for _ in range(60):
        img = np.clip(np.round(128 + 10 * rng.standard_normal((H, W, 3))), 0, 255)
        images.append(img.astype(np.uint8))
        vol.integrate(depth, images[-1], cam, np.eye(4))
    colour = np.asarray(vol.extract_mesh().vertex_colors).mean() * 255
    assert colour == pytest.approx(np.mean(images), abs=1.0)


def test_a_frame_without_valid_depth_is_skipped_and_counted(room_frames: tuple) -> None:
    # Open3D refuses a frame that touches no block: one frame facing a far wall stopped
    # the whole stage.
    cam, poses, frames = room_frames
    (rgb, d), T = frames[0], poses[0]
    vol = TSDFVolume()
    vol.integrate(np.full_like(d, np.nan), rgb, cam, T)
    vol.integrate(np.full_like(d, vol.settings.depth_max_m + 1.0), rgb, cam, T)
    assert vol.skipped == 2 and vol.frames == 0
    vol.integrate(d, rgb, cam, T)
    assert vol.frames == 1 and len(vol.extract_mesh().triangles) > 1000
    resumed = TSDFVolume()
    resumed.restore(vol.state())
    assert resumed.skipped == 2 and resumed.frames == 1


def test_reserve_for_sizes_the_map_once_and_keeps_the_mesh(room_frames: tuple) -> None:
    # Open3D doubles a full hash map, and to insert a frame's blocks it wants room for all
    # of them, held or not: the quickstart's volume went 4096 -> 8192 blocks for 4728.
    cam, poses, frames = room_frames
    plain = integrate_frames(((d, rgb, T) for (rgb, d), T in zip(frames, poses, strict=True)),
                             cam, TSDFSettings(block_count=1))
    vol = TSDFVolume(TSDFSettings(block_count=1))
    blocks = [vol.frame_blocks(d, cam, T) for (_, d), T in zip(frames, poses, strict=True)]
    assert vol.frame_blocks(np.full_like(frames[0][1], np.nan), cam, poses[0]) is None
    held: set[tuple[int, ...]] = set()
    need = 0
    for b in blocks:
        need = max(need, len(held) + len(b))
        held |= set(map(tuple, b.tolist()))
    assert vol.reserve_for(blocks) == need < plain.grid.hashmap().capacity()
    for ((rgb, d), T), b in zip(zip(frames, poses, strict=True), blocks, strict=True):
        vol.integrate(d, rgb, cam, T, b)
        assert vol.grid.hashmap().capacity() == need  # never grew
    assert vol.grid.hashmap().size() == len(held) == plain.grid.hashmap().size()
    assert vol.reserve_for([]) == need  # never shrinks (Open3D's reserve would)
    a, b = plain.extract_mesh(), vol.extract_mesh()
    for attr in ("vertices", "triangles", "vertex_colors", "vertex_normals"):
        np.testing.assert_array_equal(np.asarray(getattr(a, attr)), np.asarray(getattr(b, attr)))


def _box(lo: tuple[float, float, float], hi: tuple[float, float, float]) -> Any:
    """An axis-aligned box mesh from corner ``lo`` to corner ``hi``."""
    b = o3d.geometry.TriangleMesh.create_box(*(np.subtract(hi, lo)))
    return b.translate(np.asarray(lo, dtype=np.float64))


def test_reference_holds_surface_that_only_frames_between_spread_views_saw() -> None:
    """A wall at y = 1 m with a 2 cm slit at x = 0.09-0.11 m, a back wall at y = 2 m, and a
    camera sliding 4 cm per frame along x from 0 to 0.24 m, looking along +y. Through the
    slit each frame sees its own strip of the back wall: from x_c the strip
    0.18 - x_c .. 0.22 - x_c, so 0.06-0.10 m from the frame at x = 0.12 m alone. The 0.24 m
    drive is one spread step (0.25 m): the spread views were the first and last frames
    only, and that strip, which a camera saw, was missing from the reference."""
    from toolkit.baselines.synthetic import look_at

    scene = (_box((-1.0, 1.0, -1.0), (0.09, 1.05, 1.0))
             + _box((0.11, 1.0, -1.0), (1.0, 1.05, 1.0))
             + _box((-1.0, 2.0, -1.0), (1.0, 2.05, 1.0)))
    cam = PinholeCamera(160, 120, 400.0, 400.0, 79.5, 59.5)
    xs = np.arange(7) * 0.04
    poses = np.stack([look_at([x, 0.0, 0.0], [x, 1.0, 0.0]) for x in xs])
    ref = observed_reference(scene, cam, poses, spacing_m=0.005)
    back = ref[np.abs(ref[:, 1] - 2.0) < 1e-6]  # the back wall's face towards the camera
    strip = back[np.abs(back[:, 2]) < 0.1]
    # Every frame's strip is there, the middle frame's (0.06-0.10 m) included ...
    for x in xs:
        lo, hi = 0.18 - x, 0.22 - x
        inner = strip[(strip[:, 0] > lo + 0.005) & (strip[:, 0] < hi - 0.005)]
        assert len(inner) > 20, (x, len(inner))
    # ... and nothing of the back wall that no frame could see through the slit.
    assert np.all((strip[:, 0] > -0.07) & (strip[:, 0] < 0.23)), strip[:, 0].min()
    # More poses than max_views: a view every 0.25 m or 15 deg, thinned to max_views.
    ref2 = observed_reference(scene, cam, poses, spacing_m=0.005, max_views=3)
    back2 = ref2[np.abs(ref2[:, 1] - 2.0) < 1e-6]
    assert not np.any((back2[:, 0] > 0.065) & (back2[:, 0] < 0.095) & (np.abs(back2[:, 2]) < 0.1))


def test_stage_references_test_every_frame_up_to_reference_views(tmp_path: Path) -> None:
    """The tsdf and camera_only stages' own ground-truth comparisons measured completeness
    against spread views once a sequence had more than 400 frames, while evaluate (version
    6) tests every frame up to its completeness_views (1000). ``reference_views`` now sets
    it, 1000 by default: on the slit scene above, all 7 frames keep the middle frame's strip
    of the back wall; 3 spread views lose it. Left at any value with ``geometry: false`` it
    is not part of the settings a run records (its cache key), as it changes nothing."""
    from types import SimpleNamespace

    import open3d as o3d

    from toolkit.baselines.stage import CameraOnlyConfig, TSDFConfig, _mesh_reference
    from toolkit.baselines.synthetic import look_at

    scene = (_box((-1.0, 1.0, -1.0), (0.09, 1.05, 1.0))
             + _box((0.11, 1.0, -1.0), (1.0, 1.05, 1.0))
             + _box((-1.0, 2.0, -1.0), (1.0, 2.05, 1.0)))
    path = tmp_path / "scene.ply"
    o3d.io.write_triangle_mesh(str(path), scene)
    cam = PinholeCamera(160, 120, 400.0, 400.0, 79.5, 59.5)
    seq = SimpleNamespace(groundtruth=SimpleNamespace(mesh_path=path),
                          rig=SimpleNamespace(camera=cam))
    poses = np.stack([look_at([x, 0.0, 0.0], [x, 1.0, 0.0]) for x in np.arange(7) * 0.04])

    def middle_strip(max_views: int) -> int:
        _, ref = _mesh_reference(seq, poses, 6.0, 0.005, max_views)
        back = ref[np.abs(ref[:, 1] - 2.0) < 1e-6]
        return int(np.sum((back[:, 0] > 0.065) & (back[:, 0] < 0.095)
                          & (np.abs(back[:, 2]) < 0.1)))

    assert TSDFConfig(stage="tsdf").reference_views == 1000
    assert middle_strip(TSDFConfig(stage="tsdf", reference_views=7).reference_views) > 20
    assert middle_strip(3) == 0
    for cfg in (TSDFConfig, CameraOnlyConfig):
        assert "reference_views" in cfg(stage="x").model_dump()
        assert "reference_views" not in cfg(stage="x", geometry=False,
                                             reference_views=5).model_dump()

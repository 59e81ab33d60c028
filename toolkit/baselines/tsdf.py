"""TSDF fusion baseline: per-frame depth + colour at known poses -> coloured triangle mesh.

Open3D's tensor ``VoxelBlockGrid`` does the fusion. The legacy ``ScalableTSDFVolume`` is not
used on purpose: in the Open3D 0.20 wheels it integrates without error but extracts empty
meshes (shared/notes/dependencies-measured.md, section 2).

The renderer here draws the coloured mesh at a camera pose with Open3D's ``RaycastingScene``
and interpolates vertex colours with the hit triangle's barycentric coordinates, so image
comparisons (TSDF mesh vs. camera image, splats vs. mesh) need no OpenGL context, which the
headless machines this runs on do not have.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from toolkit.camera import PinholeCamera
from toolkit.errors import InputError, MissingInputError, WriteError
from toolkit.geometry import inv_se3
from toolkit.io.atomic import atomic_path
from toolkit.io.voxel_grid import GridCheckpoint


@dataclass(frozen=True)
class TSDFSettings:
    """Volume parameters; the defaults suit rooms seen from a robot (metres)."""

    voxel_size_m: float = 0.02
    # Truncation distance in voxels (Open3D's trunc_voxel_multiplier): 4 voxels keep thin
    # furniture from being eaten by the far side while tolerating ~cm depth noise.
    trunc_voxels: float = 4.0
    depth_max_m: float = 8.0
    block_resolution: int = 16
    # Initial hash-map capacity in blocks (16^3 voxels, 80 KB each with the float32
    # attributes below). Open3D doubles it when full, but each rehash copies everything; a
    # 5 x 4 m room needs ~1000 blocks at 2 cm. Allocation is zeroed up front, so a huge
    # default costs seconds for small scenes. ``TSDFVolume.reserve_for`` sizes it to the
    # frames instead (the ``tsdf`` stage does).
    block_count: int = 4096
    # Frames that must have seen a voxel for it to be part of the surface; 2 or more drops
    # surfaces seen once (often flying pixels of a single bad depth map).
    min_observations: int = 1

    @property
    def weight_threshold(self) -> float:
        # Every integration adds weight 1 and Open3D keeps voxels strictly above the
        # threshold, so a threshold of exactly 1 would drop everything seen only once.
        return self.min_observations - 0.5


class TSDFVolume(GridCheckpoint):
    """A TSDF + colour voxel block grid in the world frame.

    ``integrate`` takes z-depth in metres (0 or NaN = invalid), RGB uint8 and the camera
    pose ``T_world_camera`` (optical frame); Open3D wants the inverse (world-to-camera)
    as its "extrinsic", which is done here so callers keep the project's convention.
    """

    def __init__(self, settings: TSDFSettings | None = None) -> None:
        import open3d as o3d
        import open3d.core as o3c

        self.settings = settings or TSDFSettings()
        s = self.settings
        self._o3d, self._o3c = o3d, o3c
        # float32 weight and colour (20 bytes per voxel): Open3D's uint16 layout (12 bytes)
        # truncates the running colour mean at every update, so a voxel seen w times
        # ignores any colour within w grey levels above its mean and the mesh darkens (a
        # grey 128 wall seen 60 times came out 116; the views' PSNR 38.3 against 41.7 dB).
        self.grid = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight", "color"),
            attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
            attr_channels=((1), (1), (3)),
            voxel_size=float(s.voxel_size_m),
            block_resolution=int(s.block_resolution),
            block_count=int(s.block_count),
            device=o3c.Device("CPU:0"),
        )
        # Depth units per metre for the uint16 depth image: 0.2 mm steps, or coarser when
        # depth_max_m would not fit in 16 bits.
        self.depth_scale = float(min(5000.0, np.floor(65535.0 / (1.001 * s.depth_max_m))))
        self.frames = 0
        self.skipped = 0  # frames without a valid depth pixel

    def state(self) -> dict[str, Any]:
        return {**super().state(), "skipped": self.skipped}

    def restore(self, state: dict[str, Any]) -> None:
        super().restore(state)
        self.skipped = int(state.get("skipped", 0))

    def integrate(self, depth: np.ndarray, color: np.ndarray, camera: PinholeCamera,
                  T_world_camera: np.ndarray, blocks: np.ndarray | None = None) -> None:
        """Fuse one frame: ``depth`` [H, W] metres, ``color`` [H, W, 3] uint8 RGB.

        The camera must be distortion-free (undistort images and depth first): the
        volume projects voxels with a plain pinhole ``K``. ``blocks`` [B, 3] int32: the
        frame's ``frame_blocks``, computed earlier (``reserve_for``); None computes them.
        """
        inputs = self._depth_inputs(depth, camera, T_world_camera)
        if color.shape[:2] != np.shape(depth):
            raise ValueError(f"colour {color.shape} and depth {np.shape(depth)} differ in size")
        if inputs is None:
            # Open3D refuses a frame that touches no block ("check depth_scale and
            # voxel_size"): one frame facing a far wall stopped the whole stage.
            self.skipped += 1
            return
        o3d, o3c = self._o3d, self._o3c
        depth_img, K, extrinsic = inputs
        color_img = o3d.t.geometry.Image(
            o3c.Tensor(np.ascontiguousarray(np.asarray(color, dtype=np.uint8))))
        s = self.settings
        dmax, trunc = float(s.depth_max_m), float(s.trunc_voxels)
        if blocks is None:
            blocks = self._blocks(depth_img, K, extrinsic)
        else:
            blocks = o3c.Tensor(np.ascontiguousarray(blocks, dtype=np.int32))
        self.grid.integrate(blocks, depth_img, color_img, K, K, extrinsic, self.depth_scale,
                            dmax, trunc)
        self.frames += 1

    def frame_blocks(self, depth: np.ndarray, camera: PinholeCamera,
                     T_world_camera: np.ndarray) -> np.ndarray | None:
        """[B, 3] int32 coordinates of the blocks ``integrate`` of this depth [H, W] (metres)
        would fill, None for a frame without valid depth (``integrate`` skips it)."""
        inputs = self._depth_inputs(depth, camera, T_world_camera)
        return None if inputs is None else self._blocks(*inputs).numpy()

    def reserve_for(self, frame_blocks: Iterable[np.ndarray | None]) -> int:
        """Size the hash map, once, for integrating frames whose ``frame_blocks`` these are
        (in this order, after what the volume holds); returns its capacity in blocks.

        To insert a frame's B blocks Open3D wants room for B more than it holds, new or not,
        and a full map doubles: on the quickstart it went 4096 -> 8192 blocks for the 4728
        it filled (640 MiB of voxels for 370 MiB used), and the copy held both tables. The
        capacity here is the largest (blocks held before a frame + that frame's), so the
        map never grows while the frames go in."""
        hm = self.grid.hashmap()
        held = {tuple(k) for k in hm.key_tensor()[hm.active_buf_indices()].numpy().tolist()}
        need = len(held)
        for b in frame_blocks:
            if b is None:
                continue
            need = max(need, len(held) + len(b))
            held.update(map(tuple, np.asarray(b).tolist()))
        if need > hm.capacity():  # Open3D's reserve also shrinks
            hm.reserve(need)
        return int(hm.capacity())

    def _depth_inputs(self, depth: np.ndarray, camera: PinholeCamera,
                      T_world_camera: np.ndarray) -> tuple[Any, Any, Any] | None:
        """Open3D's (uint16 depth image, K, world-to-camera extrinsic) of a frame, None when
        no pixel of ``depth`` [H, W] is valid."""
        o3d, o3c = self._o3d, self._o3c
        if camera.has_distortion:
            raise ValueError("TSDF integration needs undistorted frames; pass "
                             "camera.undistorted() with undistorted images and depth")
        depth = np.asarray(depth, dtype=np.float32)
        if depth.shape != (camera.height, camera.width):
            raise ValueError(f"depth is {depth.shape[::-1]} (WxH), camera is "
                             f"{camera.width}x{camera.height}")
        s = self.settings
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(depth) & (depth > 0) & (depth <= s.depth_max_m)
        if not ok.any():
            return None
        d16 = np.where(ok, np.round(depth * self.depth_scale), 0).astype(np.uint16)
        depth_img = o3d.t.geometry.Image(o3c.Tensor(d16))
        K = o3c.Tensor(camera.open3d_K(), o3c.float64)
        extrinsic = o3c.Tensor(inv_se3(T_world_camera), o3c.float64)  # world -> camera
        return depth_img, K, extrinsic

    def _blocks(self, depth_img: Any, K: Any, extrinsic: Any) -> Any:
        """Open3D's [B, 3] Int32 tensor of the blocks a frame touches."""
        s = self.settings
        # float(): Open3D's bindings reject a Python int where they declare a float.
        return self.grid.compute_unique_block_coordinates(
            depth_img, K, extrinsic, self.depth_scale, float(s.depth_max_m),
            float(s.trunc_voxels))

    def extract_mesh(self) -> Any:
        """Legacy ``open3d.geometry.TriangleMesh`` with vertex colours in [0, 1] and normals."""
        if self.frames == 0:
            raise ValueError("no frame integrated: the TSDF volume is empty")
        w = self.settings.weight_threshold
        mesh = canonical_order(self.grid.extract_triangle_mesh(weight_threshold=w).to_legacy())
        if len(mesh.vertex_colors):
            mesh.vertex_colors = self._o3d.utility.Vector3dVector(
                np.clip(np.asarray(mesh.vertex_colors), 0.0, 1.0))
        mesh.compute_vertex_normals()
        return mesh

    def extract_points(self) -> np.ndarray:
        """[N, 3] surface points (zero crossings) of the volume."""
        if self.frames == 0:
            raise ValueError("no frame integrated: the TSDF volume is empty")
        pcd = self.grid.extract_point_cloud(weight_threshold=self.settings.weight_threshold)
        return pcd.point.positions.numpy().astype(np.float64)


def canonical_order(mesh: Any) -> Any:
    """``mesh`` (legacy TriangleMesh) with vertices sorted by position (then colour) and
    triangles by their vertices, winding kept.

    Open3D's grid fills its hash map from several threads, so the same frames give the
    same surface listed in another order each run - and everything sampled from the mesh
    by index (the evaluation's surface samples) moved with it (F-scores +-0.001).
    """
    import open3d as o3d

    v = np.asarray(mesh.vertices)
    if len(v) == 0:
        return mesh
    c = np.asarray(mesh.vertex_colors) if mesh.has_vertex_colors() else np.zeros((len(v), 0))
    keys = np.hstack([v, c])  # [V, 3 or 6]
    order = np.lexsort(keys.T[::-1])  # x first
    rank = np.empty(len(v), np.int64)
    rank[order] = np.arange(len(v))
    tri = rank[np.asarray(mesh.triangles)]  # [T, 3]
    first = np.argmin(tri, axis=1)
    tri = np.take_along_axis(tri, (first[:, None] + np.arange(3)) % 3, axis=1)  # same winding
    tri = tri[np.lexsort(tri.T[::-1])]
    out = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v[order]),
                                    o3d.utility.Vector3iVector(tri.astype(np.int32)))
    if c.shape[1]:
        out.vertex_colors = o3d.utility.Vector3dVector(c[order])
    return out


def integrate_frames(
    frames: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]],
    camera: PinholeCamera,
    settings: TSDFSettings | None = None,
) -> TSDFVolume:
    """Fuse ``(depth [H, W] m, color [H, W, 3] uint8, T_world_camera [4, 4])`` tuples."""
    vol = TSDFVolume(settings)
    for depth, color, T in frames:
        vol.integrate(depth, color, camera, T)
    return vol


def write_mesh(path: Path | str, mesh: Any) -> None:
    """Write a triangle mesh as binary PLY, atomically (a reader never sees half a file)."""
    import open3d as o3d

    path = Path(path)
    with atomic_path(path) as tmp:
        if not o3d.io.write_triangle_mesh(str(tmp), mesh, write_ascii=False):
            raise WriteError(f"{path}: Open3D could not write the mesh")


def read_mesh(path: Path | str) -> Any:
    """Read a PLY (or any Open3D mesh format); error if the file is missing or empty."""
    import open3d as o3d

    path = Path(path)
    if not path.exists():
        raise MissingInputError(f"{path}: mesh file not found")
    mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.triangles) == 0:
        raise InputError(f"{path}: the mesh has no triangles")
    return mesh


# ---------------------------------------------------------------------------- rendering


@dataclass
class RayHits:
    """First hits of one camera's pixel rays: all arrays are [H, W] (uv is [H, W, 2])."""

    depth: np.ndarray  # [H, W] float32 z-depth in metres, inf where nothing was hit
    triangle: np.ndarray  # [H, W] int64 triangle index, -1 where nothing was hit
    uv: np.ndarray  # [H, W, 2] float32 barycentrics (b1, b2) of the hit triangle
    points: np.ndarray  # [H, W, 3] float64 world hit points (NaN where nothing was hit)

    @property
    def valid(self) -> np.ndarray:
        """[H, W] bool: the ray hit the mesh."""
        return self.triangle >= 0


class MeshRenderer:
    """Ray-cast a triangle mesh from pinhole cameras (build once, render many views).

    Rays go through pixel centres with z = 1 in the camera (``PinholeCamera.pixel_rays``,
    which also undoes distortion), so the hit distance is z-depth, not ray length.
    """

    def __init__(self, mesh: Any) -> None:
        import open3d as o3d

        self.vertices = np.asarray(mesh.vertices, dtype=np.float64)  # [V, 3]
        self.triangles = np.asarray(mesh.triangles, dtype=np.int64)  # [T, 3]
        if len(self.triangles) == 0:
            raise ValueError("cannot render a mesh without triangles")
        self.colors = (np.asarray(mesh.vertex_colors, dtype=np.float64)
                       if mesh.has_vertex_colors() else None)  # [V, 3] in [0, 1]
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
        self._rays_cache: dict[tuple, np.ndarray] = {}
        self._corners: np.ndarray | None = None  # built by the first render

    def _camera_rays(self, camera: PinholeCamera) -> np.ndarray:
        key = (camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy,
               tuple(camera.dist))
        if key not in self._rays_cache:
            self._rays_cache = {key: camera.pixel_rays()}  # [H, W, 3], keep only the latest
        return self._rays_cache[key]

    def _cast_rays(self, camera: PinholeCamera, T: np.ndarray) -> tuple[np.ndarray, dict]:
        import open3d.core as o3c

        dirs = self._camera_rays(camera) @ T[:3, :3].T  # [H, W, 3] world, |z_cam| = 1
        rays = np.empty((*dirs.shape[:2], 6), dtype=np.float32)
        rays[..., :3] = T[:3, 3]
        rays[..., 3:] = dirs
        return dirs, self.scene.cast_rays(o3c.Tensor(rays))

    def depth_where(self, camera: PinholeCamera, T_world_camera: np.ndarray,
                    need: np.ndarray) -> np.ndarray:
        """[H, W] float32: ``depth`` at the pixels where ``need`` [H, W] bool is set, 0
        elsewhere, casting only those rays.

        The values are ``depth``'s bit for bit: OpenBLAS computes each row of a product
        with a 3 x 3 matrix on its own, so the needed rays' directions, picked out first
        and multiplied as one [n, 3] block, are the rows ``depth``'s whole-image product
        gives them (``test_depth_where_casts_the_needed_rays_bit_for_bit``; and the same
        observed reference on the quickstart), and Embree intersects each ray on its own.
        Picking them out first rotates only the needed rays (about half of a view's in
        ``observed_reference``) and picks float64 [n, 3] rows by index, not by mask.
        """
        import open3d.core as o3c

        T = np.asarray(T_world_camera, dtype=np.float64)
        need = np.asarray(need, dtype=bool)
        out = np.zeros(need.shape, np.float32)  # [H, W]
        idx = np.flatnonzero(need)  # [n] in row-major order
        if len(idx) == 0:
            return out
        cam_rays = self._camera_rays(camera).reshape(-1, 3)  # [H * W, 3]
        rays = np.empty((len(idx), 6), dtype=np.float32)  # [n, 6]
        rays[:, :3] = T[:3, 3]
        rays[:, 3:] = np.take(cam_rays, idx, axis=0) @ T[:3, :3].T
        t = self.scene.cast_rays(o3c.Tensor.from_numpy(rays))["t_hit"].numpy()  # [n]
        out.reshape(-1)[idx] = np.where(np.isfinite(t), t, 0.0)
        return out

    def depth(self, camera: PinholeCamera, T_world_camera: np.ndarray) -> np.ndarray:
        """[H, W] float32 z-depth, 0 where nothing was hit: ``cast`` without the hit points,
        triangles and barycentrics (half its time on a 640x480 view)."""
        _, ans = self._cast_rays(camera, np.asarray(T_world_camera, dtype=np.float64))
        t = ans["t_hit"].numpy()
        return np.where(np.isfinite(t), t, 0.0).astype(np.float32)

    def cast(self, camera: PinholeCamera, T_world_camera: np.ndarray) -> RayHits:
        T = np.asarray(T_world_camera, dtype=np.float64)
        dirs, ans = self._cast_rays(camera, T)
        t = ans["t_hit"].numpy()
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        hit = np.isfinite(t)
        prim[~hit] = -1
        points = np.full(dirs.shape, np.nan)
        points[hit] = T[:3, 3] + dirs[hit] * t[hit, None].astype(np.float64)
        return RayHits(t.astype(np.float32), prim, ans["primitive_uvs"].numpy(), points)

    def _corner_colors(self) -> np.ndarray:
        """[T, 3, 3] each triangle's corner colours: uint8 (0..255) when every vertex colour
        is k / 255 exactly (a PLY's 8-bit colours, as the TSDF mesh has), float64 (0..1)
        otherwise. One gather per pixel from it instead of a triangle lookup and three
        colour lookups; 8-bit, it takes 9 bytes a triangle (10 MB for the quickstart's
        1.2 M) instead of 72."""
        if self._corners is None:
            assert self.colors is not None
            k = np.round(self.colors * 255.0)  # [V, 3]
            table = (k.astype(np.uint8) if np.array_equal(k / 255.0, self.colors)
                     else self.colors)
            self._corners = table[self.triangles]
        return self._corners

    def render(self, camera: PinholeCamera, T_world_camera: np.ndarray,
               background: tuple[int, int, int] = (0, 0, 0)) -> tuple[np.ndarray, np.ndarray]:
        """RGB uint8 [H, W, 3] and z-depth float32 [H, W] (0 where empty) of the mesh.

        The pixels are ``cast``'s hits shaded as before, bit for bit (the same float64
        expression, element by element), without the hit points ``cast`` builds, and over
        every pixel rather than the hit ones picked out (on a view along the quickstart's path
        99 % of them hit; docs/baselines.md, "Rendering without OpenGL")."""
        _, ans = self._cast_rays(camera, np.asarray(T_world_camera, dtype=np.float64))
        t = ans["t_hit"].numpy()  # [H, W] float32, inf where nothing was hit
        hit = np.isfinite(t)  # [H, W]
        bg = np.asarray(background, dtype=np.uint8)  # [3]
        if self.colors is None or not hit.any():
            # An uncoloured mesh renders grey, so its silhouette still shows.
            rgb = np.where(hit[..., None], np.uint8(200), bg)  # [H, W, 3] uint8
        else:
            # A missed ray's id is 2^32 - 1 (and its barycentrics 0): triangle 0 stands in,
            # its colour is not kept.
            prim = np.where(hit, ans["primitive_ids"].numpy(), 0).reshape(-1)  # [N]
            corners = np.take(self._corner_colors(), prim, axis=0)  # [N, 3, 3]

            def corner(j: int) -> np.ndarray:
                """[N, 3] float64 colours of corner j; 8-bit ones made the vertex colours
                again, exactly, one corner at a time (a third of the memory)."""
                return corners[:, j] / 255.0 if corners.dtype == np.uint8 else corners[:, j]

            uv = ans["primitive_uvs"].numpy().reshape(-1, 2).astype(np.float64)  # [N, 2]
            b1, b2 = uv[:, 0:1], uv[:, 1:2]
            # Embree's barycentrics: p = (1 - b1 - b2) v0 + b1 v1 + b2 v2; summed in this
            # order, as before, so each value is the same to the last bit.
            c = (1.0 - b1 - b2) * corner(0)  # [N, 3]
            c += b1 * corner(1)
            c += b2 * corner(2)
            c *= 255.0
            np.round(c, out=c)
            np.clip(c, 0, 255, out=c)
            rgb = np.where(hit[..., None], c.astype(np.uint8).reshape(*hit.shape, 3), bg)
        depth = np.where(hit, t, 0.0).astype(np.float32)
        return rgb, depth


def render_mesh(mesh: Any, camera: PinholeCamera, T_world_camera: np.ndarray,
                background: tuple[int, int, int] = (0, 0, 0)) -> tuple[np.ndarray, np.ndarray]:
    """One-off ``MeshRenderer(mesh).render(...)``: RGB [H, W, 3] uint8, depth [H, W] float32."""
    return MeshRenderer(mesh).render(camera, T_world_camera, background)

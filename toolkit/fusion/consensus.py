"""The multi-view consensus surface of the fused frames: a coarse TSDF of the same depth.

Each frame's scaled depth is off by a few per cent in its own way, so one wall seen from
many views becomes, in a voxel map of points, a shell several voxels thick. A TSDF
averages the signed distance along each view's rays, and its zero crossing is the
weighted middle of that shell. The fusion keeps the voxel map (its colours, counts and
moving-obstacle bookkeeping) and drops the voxels that lie farther than a threshold from
this surface. The volume runs on downsampled frames with coarse voxels and no colour: it
only has to say where the middle is.

One volume per viewing direction (``direction_bins`` bins of the camera's heading, centred
on the axes): each view writes "inside" 4 voxels behind the surface it sees, so views of a
door or a 10 cm wall from its other side (or any surface within 16 cm behind) voted
against the first side's zero crossing, and one shared volume dropped both faces of such
a slab whole (with the 6-voxel band of before: its crossings ended up 10 and 14 cm
off in free space). Opposite views now
fill different volumes; a map voxel is on the surface when it is near that of any of them.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from toolkit.camera import PinholeCamera
from toolkit.geometry import inv_se3
from toolkit.io.voxel_grid import GridCheckpoint

# The band each view writes around the surface it sees, in voxels (FusionConfig's
# consensus_trunc_voxels; why 4: there).
TRUNC_VOXELS = 4.0
# Blocks a direction volume has room for at first (8^3 voxels of 4 bytes tsdf + 4 weight:
# 4 KiB each). 4096 held 64 MiB for the quickstart's four volumes, of which their 1102 to
# 2502 blocks used 27; from 1024, doubling as needed, three of them stop at 2048 (40 MiB).
# Sizing them once from every frame's blocks, as the tsdf stage does, would need the
# frames' refined depth before the map pass makes it.
INITIAL_BLOCKS = 1024


class ConsensusSurface:
    """The consensus of the fused frames: one ``DirectionVolume`` per heading bin of the
    camera (the module docstring)."""

    def __init__(self, camera: PinholeCamera, voxel_size_m: float = 0.04,
                 trunc_voxels: float = TRUNC_VOXELS, depth_max_m: float = 6.0,
                 downsample: int = 2, direction_bins: int = 4) -> None:
        if int(direction_bins) < 1:
            raise ValueError(f"consensus direction_bins must be at least 1, got "
                             f"{direction_bins}")
        self.bins = int(direction_bins)
        self._settings = (camera, voxel_size_m, trunc_voxels, depth_max_m, downsample)
        # Made on a bin's first frame: each grid holds its own block memory.
        self.volumes: list[DirectionVolume | None] = [None] * self.bins

    @property
    def frames(self) -> int:
        return sum(v.frames for v in self.volumes if v is not None)

    def direction_bin(self, T_world_camera: np.ndarray) -> int:
        """Bin of the camera's heading: its optical axis about world z, bins centred on
        0, 360 / bins, ... degrees (rooms' walls are mostly seen square on, in the middle
        of a bin)."""
        axis = T_world_camera[:3, 2]
        yaw = np.arctan2(axis[1], axis[0])
        return int(np.floor(yaw / (2 * np.pi) * self.bins + 0.5)) % self.bins

    def integrate(self, depth: np.ndarray, T_world_camera: np.ndarray,
                  valid: np.ndarray | None = None) -> None:
        """Add one frame to its heading's volume (``DirectionVolume.integrate``)."""
        k = self.direction_bin(T_world_camera)
        if self.volumes[k] is None:
            self.volumes[k] = DirectionVolume(*self._settings)
        vol = self.volumes[k]
        assert vol is not None
        vol.integrate(depth, T_world_camera, valid)

    def surface(self) -> np.ndarray:
        """[M, 3] points on every volume's surface."""
        parts = [v.surface() for v in self.volumes if v is not None]
        return np.concatenate(parts) if parts else np.zeros((0, 3))

    def off_surface(self, points: np.ndarray, max_distance_m: float) -> np.ndarray:
        """[N] bool: points [N, 3] farther than ``max_distance_m`` from the surface of
        every volume (``DirectionVolume.off_surface``)."""
        off = np.ones(len(points), bool)
        for v in self.volumes:
            if v is not None and off.any():
                off[off] = v.off_surface(points[off], max_distance_m)
        return off

    def state(self) -> dict[str, Any]:
        """Every volume's ``state`` (None: a bin without frames), picklable."""
        return {"volumes": [None if v is None else v.state() for v in self.volumes]}

    def restore(self, state: dict[str, Any]) -> None:
        """Continue from ``state()`` of a consensus with the same settings."""
        saved = state["volumes"]
        if len(saved) != self.bins:
            raise ValueError(f"consensus checkpoint has {len(saved)} direction bins, the "
                             f"settings {self.bins}: resume with the settings it was made "
                             "with, or start the stage afresh")
        for k, st in enumerate(saved):
            self.volumes[k] = None
            if st is not None:
                self.volumes[k] = DirectionVolume(*self._settings)
                self.volumes[k].restore(st)  # type: ignore[union-attr]


class DirectionVolume(GridCheckpoint):
    """A coarse, geometry-only TSDF (Open3D VoxelBlockGrid) of the frames of one
    heading."""

    def __init__(self, camera: PinholeCamera, voxel_size_m: float = 0.04,
                 trunc_voxels: float = TRUNC_VOXELS, depth_max_m: float = 6.0,
                 downsample: int = 2) -> None:
        import open3d as o3d
        import open3d.core as o3c

        self._o3d, self._o3c = o3d, o3c
        self.camera = camera
        # Never below 320 pixels across: a coarser image leaves holes between its rays
        # at a few metres that the 4 cm voxels cannot bridge.
        self.downsample = max(1, min(int(downsample), camera.width // 320))
        # The volume sees every downsample-th pixel (a stride, not an area resize).
        self.volume_camera = camera.undistorted().strided(self.downsample)
        self.K = o3c.Tensor(self.volume_camera.open3d_K(), o3c.float64)
        self.trunc_voxels = float(trunc_voxels)
        self.depth_max_m = float(depth_max_m)
        # Depth units per metre for the uint16 depth image (Open3D's integrator wants it).
        self.depth_scale = float(min(5000.0, np.floor(65535.0 / (1.001 * depth_max_m))))
        # 8^3 blocks: a truncation band of 24 cm touched fewer voxels than with 16^3
        # blocks (measured 6.4 vs 8.9 ms per frame). Room for INITIAL_BLOCKS at first, which
        # Open3D doubles when a frame needs more.
        self.grid = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32),
            attr_channels=((1), (1)), voxel_size=float(voxel_size_m), block_resolution=8,
            block_count=INITIAL_BLOCKS, device=o3c.Device("CPU:0"))
        self.voxel_size_m = float(voxel_size_m)
        self.frames = 0
        self._surface: np.ndarray | None = None
        self._normals: np.ndarray | None = None  # [M, 3] unit, or 0 where unknown

    def integrate(self, depth: np.ndarray, T_world_camera: np.ndarray,
                  valid: np.ndarray | None = None) -> None:
        """Add one frame: z-depth [H, W] in metres (0 or NaN where not to be used) at the
        full resolution of the fused camera; ``valid`` [H, W] bool, if given, also limits
        the pixels used."""
        o3d, o3c = self._o3d, self._o3c
        s = self.downsample
        if self.camera.has_distortion:
            d = np.asarray(depth, np.float32) if valid is None else np.where(
                valid, depth, np.float32(0.0)).astype(np.float32)
            # Nearest, and then every s-th pixel: averaging depth across an edge would
            # make points that exist nowhere.
            d = self.camera.undistort_image(np.nan_to_num(d, nan=0.0), cv2.INTER_NEAREST)
            d = np.ascontiguousarray(d[::s, ::s])
        else:
            # Every s-th pixel first, then the masking on s^2 fewer pixels.
            d = np.asarray(depth[::s, ::s], np.float32)
            if valid is not None:
                d = np.where(valid[::s, ::s], d, np.float32(0.0))
        with np.errstate(invalid="ignore"):
            ok = (d > 0) & (d <= self.depth_max_m)
        if not ok.any():
            # Nothing to add (every pixel masked, e.g. noisy depth under the ramp test):
            # Open3D would refuse a frame that touches no block.
            return
        d16 = np.where(ok, np.round(d * self.depth_scale), 0).astype(np.uint16)
        img = o3d.t.geometry.Image(o3c.Tensor(d16))
        ext = o3c.Tensor(inv_se3(T_world_camera), o3c.float64)  # world -> camera
        blocks = self.grid.compute_unique_block_coordinates(
            img, self.K, ext, self.depth_scale, self.depth_max_m, self.trunc_voxels)
        self.grid.integrate(blocks, img, self.K, ext, self.depth_scale, self.depth_max_m,
                            self.trunc_voxels)
        self.frames += 1
        self._surface = None

    def restore(self, state: dict[str, Any]) -> None:
        super().restore(state)
        self._surface = self._normals = None

    def surface(self) -> np.ndarray:
        """[M, 3] points on the consensus surface (zero crossings of the TSDF)."""
        if self._surface is None:
            self._surface, self._normals = np.zeros((0, 3)), np.zeros((0, 3))
            if self.frames:
                # Weight above 0.5: every voxel a frame reached counts (one frame = 1).
                try:
                    pcd = self.grid.extract_point_cloud(weight_threshold=0.5)
                except RuntimeError as e:
                    # Open3D 0.20 raises when it finds no surface point ("Tensor has shape
                    # {0}"): frames with only a few pixels, or a plane exactly on the
                    # voxel grid. No surface, not a failed run.
                    if "shape {0}" not in str(e):
                        raise
                else:
                    self._surface = pcd.point.positions.numpy().astype(np.float64)
                    n = (pcd.point.normals.numpy().astype(np.float64) if "normals" in pcd.point
                         else np.zeros_like(self._surface))
                    norm = np.linalg.norm(n, axis=1, keepdims=True)
                    self._normals = np.where(norm > 0.5, n / np.maximum(norm, 1e-12), 0.0)
        return self._surface

    def off_surface(self, points: np.ndarray, max_distance_m: float) -> np.ndarray:
        """[N] bool: points [N, 3] farther than ``max_distance_m`` from the surface.

        The distance is to the tangent plane of the nearest surface point (within
        ``max_distance_m`` plus a voxel): the surface's points are its zero crossings on
        voxel edges, up to a voxel apart, and the distance to the nearest one alone added
        up to 0.7 voxel (with 4 cm voxels and 3 cm, points 2.5 cm off a wall were dropped
        43 % of the time; with 6 cm voxels a fifth of the points on it). Not the TSDF's
        own value either: that one is measured along the views' rays and, on a floor seen
        at a grazing angle, is several times the distance to the floor (on the simulated
        house it dropped a tenth of the good floor points: recall 0.79 instead of 0.86 at
        the same precision).
        """
        s = self.surface()
        normals = self._normals
        assert normals is not None
        if len(s) == 0:
            return np.ones(len(points), bool)
        if len(points) == 0:
            return np.zeros(0, bool)
        radius = float(max_distance_m) + self.voxel_size_m
        # Open3D's radius-limited search: the same answer as a k-d tree query with an upper
        # bound, in half the time (0.22 vs 0.41 s for 0.9 M map voxels on 2 cores).
        o3c = self._o3c
        nns = o3c.nns.NearestNeighborSearch(o3c.Tensor(np.ascontiguousarray(s, np.float32)))
        nns.hybrid_index(radius)
        idx, dist2, found = nns.hybrid_search(
            o3c.Tensor(np.ascontiguousarray(points, np.float32)), radius, 1)
        found = found.numpy().reshape(-1) > 0  # [N]
        j = idx.numpy().reshape(-1)[found].astype(np.int64)
        d = np.sqrt(dist2.numpy().reshape(-1)[found].astype(np.float64))  # Euclidean
        n = normals[j]
        along = np.abs(np.einsum("ij,ij->i", np.asarray(points, np.float64)[found] - s[j], n))
        # Where the TSDF gave no normal, the Euclidean distance (the stricter one).
        d = np.where(np.any(n != 0, axis=1), along, d)
        off = np.ones(len(points), bool)
        off[found] = d > max_distance_m
        return off

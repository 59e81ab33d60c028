"""The multi-view consensus surface of the fused frames: a coarse TSDF of the same depth.

Each frame's scaled depth is off by a few per cent in its own way, so one wall seen from
many views becomes, in a voxel map of points, a shell several voxels thick. A TSDF
averages the signed distance along each view's rays, and its zero crossing is the
weighted middle of that shell. The fusion keeps the voxel map (its colours, counts and
moving-obstacle bookkeeping) and drops the voxels that lie farther than a threshold from
this surface. The volume runs on downsampled frames with coarse voxels: it only has to
say where the middle is.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial import cKDTree

from toolkit.baselines.tsdf import TSDFSettings, TSDFVolume
from toolkit.camera import PinholeCamera


class ConsensusSurface:
    """A coarse TSDF of the fused frames, queried for the distance to its surface."""

    def __init__(self, camera: PinholeCamera, voxel_size_m: float = 0.04,
                 trunc_voxels: float = 6.0, depth_max_m: float = 6.0,
                 downsample: int = 2) -> None:
        self.camera = camera
        # Never below 320 pixels across: a coarser image leaves holes between its rays
        # at a few metres that the 4 cm voxels cannot bridge.
        self.downsample = max(1, min(int(downsample), camera.width // 320))
        w, h = camera.width // self.downsample, camera.height // self.downsample
        self.volume_camera = camera.undistorted().scaled(w, h)
        self.volume = TSDFVolume(TSDFSettings(voxel_size_m=voxel_size_m,
                                              trunc_voxels=trunc_voxels,
                                              depth_max_m=depth_max_m, block_resolution=8,
                                              block_count=4096))
        self.frames = 0
        self._surface: np.ndarray | None = None

    def integrate(self, depth: np.ndarray, rgb: np.ndarray, T_world_camera: np.ndarray) -> None:
        """Add one frame: z-depth [H, W] in metres (0 or NaN where not to be used) and its
        RGB image [H, W, 3], at full resolution of the fused camera."""
        d = np.nan_to_num(np.asarray(depth, np.float32), nan=0.0)
        if self.camera.has_distortion:
            d = self.camera.undistort_image(d, cv2.INTER_NEAREST)
            rgb = self.camera.undistort_image(rgb)
        size = (self.volume_camera.width, self.volume_camera.height)
        if self.downsample > 1:
            # Nearest: averaging depth across an edge would make points that exist nowhere.
            d = cv2.resize(d, size, interpolation=cv2.INTER_NEAREST)
            rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
        self.volume.integrate(d, rgb, self.volume_camera, T_world_camera)
        self.frames += 1
        self._surface = None

    def surface(self) -> np.ndarray:
        """[M, 3] points on the consensus surface (zero crossings of the TSDF)."""
        if self._surface is None:
            self._surface = self.volume.extract_points() if self.frames else np.zeros((0, 3))
        return self._surface

    def off_surface(self, points: np.ndarray, max_distance_m: float) -> np.ndarray:
        """[N] bool: points [N, 3] farther than ``max_distance_m`` from every surface point.

        Euclidean distance to the surface's points, not the TSDF's own value: that one is
        measured along the views' rays and, on a floor seen at a grazing angle, is several
        times the distance to the floor (on the simulated house it dropped a tenth of the
        good floor points: recall 0.79 instead of 0.86 at the same precision).
        """
        s = self.surface()
        if len(s) == 0:
            return np.ones(len(points), bool)
        d, _ = cKDTree(s).query(points, k=1, distance_upper_bound=max_distance_m, workers=-1)
        return ~np.isfinite(d)

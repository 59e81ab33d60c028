"""Held-out camera views: poses near, but off, the driven path (novel-view evaluation)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from toolkit.geometry import se3
from toolkit.sim.scene import INVALID_ID
from toolkit.sim.sensors import R_BASE_OPTICAL

if TYPE_CHECKING:
    from toolkit.sim.simulate import SimWorld

MIN_SURFACE_DIST = 0.3  # metres from the camera centre to any surface
MIN_PATH_DIST = 0.25  # metres from the camera centre to the driven path (xy)


def is_free(world: SimWorld, p: np.ndarray, min_dist: float = MIN_SURFACE_DIST) -> bool:
    """Whether ``p`` [3] lies in open space: not inside any box, not close to a surface.

    Rays along the six axes must all hit front faces (a ray from inside a box meets the
    back of one of its faces) no closer than ``min_dist``.
    """
    dirs = np.vstack([np.eye(3), -np.eye(3)])
    rays = np.hstack([np.repeat(p[None], 6, 0), dirs]).astype(np.float32)
    hit = world.scene.cast(rays)
    if np.any(hit["primitive_ids"] == INVALID_ID):
        return False
    facing = np.einsum("ij,ij->i", hit["primitive_normals"], dirs)
    if np.any(facing > 0):
        return False
    near = hit["t_hit"][[0, 1, 3, 4]]  # horizontal distances
    return bool(np.all(near > min_dist) and np.all(hit["t_hit"][[2, 5]] > 0.15))


def sample_heldout(world: SimWorld, rng: np.random.Generator, n: int) -> tuple[np.ndarray,
                                                                               np.ndarray]:
    """Relative times [n] (sorted, unique) and ``T_world_camera`` [n, 4, 4]."""
    path = world.path
    mount = np.asarray(world.config.camera.mount_xyz, dtype=np.float64)
    path_xy = path.xy[:: max(len(path.xy) // 4000, 1)]
    times, poses = [], []
    tries = 0
    while len(times) < n and tries < 200 * max(n, 1):
        tries += 1
        t = float(rng.uniform(0.0, path.duration))
        x, y, yaw = path.pose2d(np.array([t]))[0]
        f = np.array([np.cos(yaw), np.sin(yaw)])
        left = np.array([-f[1], f[0]])
        side = rng.choice([-1.0, 1.0]) * rng.uniform(0.3, 0.7)
        xy = np.array([x, y]) + side * left + rng.uniform(-0.3, 0.3) * f
        z = mount[2] + rng.uniform(-0.15, 0.4)
        p = np.array([xy[0], xy[1], z])
        if np.min(np.linalg.norm(path_xy - xy, axis=1)) < MIN_PATH_DIST:
            continue
        if not is_free(world, p):
            continue
        yaw_c = yaw + rng.uniform(-0.45, 0.45)
        pitch = np.radians(rng.uniform(-5.0, 20.0))  # positive looks down
        roll = np.radians(rng.uniform(-3.0, 3.0))
        # Base-like frame (x forward, z up) turned by yaw, pitch, roll; then optical axes.
        R_body = Rotation.from_euler("ZYX", [yaw_c, pitch, roll]).as_matrix()
        times.append(t)
        poses.append(se3(R_body @ R_BASE_OPTICAL, p))
    if not times:
        return np.zeros(0), np.zeros((0, 4, 4))
    order = np.argsort(times)
    ts = np.asarray(times)[order]
    # Stamps must increase strictly (TUM files); two draws at the same instant are split.
    for i in range(1, len(ts)):
        if ts[i] <= ts[i - 1]:
            ts[i] = ts[i - 1] + 1e-6
    return ts, np.stack(poses)[order]

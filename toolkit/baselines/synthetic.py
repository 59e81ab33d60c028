"""A textured box room rendered by ray casting: a small, exact scene for the baselines' tests.

The house simulator (``toolkit/sim``) is the real test world; this scene is the one the
baselines are unit-tested on because it is tiny, fast and fully known: a rectangular room
with a few boxes, coloured by a solid (3D) value-noise texture evaluated at each ray's hit
point, so every surface has the blob-like detail SIFT needs and no UV mapping is involved.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from toolkit.camera import PinholeCamera
from toolkit.geometry import Trajectory, inv_se3
from toolkit.sensors import Rig

# base_link (x forward, y left, z up) -> optical (z forward, x right, y down): REP 103.
_HASH_SIZE = 1 << 16

R_BASE_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _box(lo: np.ndarray, hi: np.ndarray) -> Any:
    import open3d as o3d

    size = np.asarray(hi, dtype=np.float64) - np.asarray(lo, dtype=np.float64)
    box = o3d.geometry.TriangleMesh.create_box(*size)
    box.translate(np.asarray(lo, dtype=np.float64))
    return box


@dataclass
class SyntheticRoom:
    """A closed room [0, size] with boxes standing on the floor; z up, metres."""

    size: tuple[float, float, float] = (5.0, 4.0, 2.5)
    boxes: list[tuple[tuple[float, float, float], tuple[float, float, float]]] = field(
        default_factory=lambda: [((1.0, 2.6, 0.0), (1.8, 3.4, 0.9)),
                                 ((3.4, 0.6, 0.0), (4.2, 1.2, 1.4)),
                                 ((2.2, 1.6, 0.0), (2.8, 2.2, 0.5))])
    seed: int = 0
    # Value-noise octaves: (cell size m, weight). Cells of 3-25 cm give SIFT blobs at the
    # scales a 320x240 camera 1-4 m away resolves.
    octaves: tuple[tuple[float, float], ...] = ((0.25, 0.45), (0.09, 0.35), (0.035, 0.2))

    def __post_init__(self) -> None:
        rng = np.random.default_rng(self.seed)
        self._values = rng.random((_HASH_SIZE, 3))  # per lattice hash: an RGB value
        self._tint = rng.uniform(0.6, 1.0, 3)

    def mesh(self) -> Any:
        """Open3D TriangleMesh of walls, floor, ceiling and boxes (no colours)."""
        mesh = _box(np.zeros(3), np.asarray(self.size))
        for lo, hi in self.boxes:
            mesh += _box(np.asarray(lo), np.asarray(hi))
        return mesh

    def colored_mesh(self, subdivide_m: float = 0.05) -> Any:
        """The mesh with vertex colours from the texture (subdivided so colours vary)."""
        import open3d as o3d

        mesh = self.mesh()
        tris = np.asarray(mesh.triangles)
        longest = max(np.linalg.norm(np.asarray(mesh.vertices)[tris[:, 0]]
                                     - np.asarray(mesh.vertices)[tris[:, 1]], axis=1).max(), 1e-9)
        iters = int(np.clip(np.ceil(np.log2(longest / subdivide_m)), 0, 7))
        mesh = mesh.subdivide_midpoint(number_of_iterations=iters)
        mesh.vertex_colors = o3d.utility.Vector3dVector(self.texture(np.asarray(mesh.vertices)))
        return mesh

    def texture(self, points: np.ndarray) -> np.ndarray:
        """[N, 3] RGB in [0, 1] of world points [N, 3] (solid value noise)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        out = np.zeros((len(p), 3))
        for k, (cell, weight) in enumerate(self.octaves):
            out += weight * self._value_noise(p / cell + 17.0 * k)
        return np.clip(0.15 + 0.85 * out * self._tint, 0.0, 1.0)

    def _value_noise(self, q: np.ndarray) -> np.ndarray:
        i0 = np.floor(q).astype(np.int64)  # [N, 3] lattice cell
        f = q - i0
        f = f * f * (3.0 - 2.0 * f)  # smoothstep: no visible lattice creases
        # Spatial hash (Teschner et al. 2003) split per axis so each corner costs one XOR
        # and one gather; no visible period, unlike a small permutation table.
        hx = (i0[:, 0] * 73856093, (i0[:, 0] + 1) * 73856093)
        hy = (i0[:, 1] * 19349663, (i0[:, 1] + 1) * 19349663)
        hz = (i0[:, 2] * 83492791, (i0[:, 2] + 1) * 83492791)
        wx = (1.0 - f[:, 0], f[:, 0])
        wy = (1.0 - f[:, 1], f[:, 1])
        wz = (1.0 - f[:, 2], f[:, 2])
        out = np.zeros((len(q), 3))
        for a in (0, 1):
            for b in (0, 1):
                hab, wab = hx[a] ^ hy[b], wx[a] * wy[b]
                for c in (0, 1):
                    h = (hab ^ hz[c]) & (_HASH_SIZE - 1)
                    out += (wab * wz[c])[:, None] * self._values[h]
        return out

    def renderer(self) -> RoomRenderer:
        return RoomRenderer(self)


class RoomRenderer:
    """Renders RGB (texture at the hit point) and exact z-depth of a ``SyntheticRoom``."""

    def __init__(self, room: SyntheticRoom) -> None:
        from toolkit.baselines.tsdf import MeshRenderer

        self.room = room
        self._mesh_renderer = MeshRenderer(room.mesh())

    def render(self, camera: PinholeCamera, T_world_camera: np.ndarray) -> (
        tuple[np.ndarray, np.ndarray]
    ):
        """RGB uint8 [H, W, 3] and depth float32 [H, W] metres (0 where nothing is hit)."""
        hits = self._mesh_renderer.cast(camera, T_world_camera)
        rgb = np.zeros((camera.height, camera.width, 3), dtype=np.uint8)
        m = hits.valid
        rgb[m] = np.round(self.room.texture(hits.points[m]) * 255).astype(np.uint8)
        depth = np.where(m, hits.depth, 0.0).astype(np.float32)
        return rgb, depth


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    """[4, 4] T_world_camera of an optical-frame camera at ``eye`` looking at ``target``."""
    eye, target = np.asarray(eye, dtype=np.float64), np.asarray(target, dtype=np.float64)
    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=np.float64)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # points down when up is +z
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], 1)
    T[:3, 3] = eye
    return T


def orbit_poses(room: SyntheticRoom, n: int, radius_m: float = 0.8, height_m: float = 1.2,
                sweep_deg: float = 120.0, look_distance_m: float = 2.0) -> np.ndarray:
    """[n, 4, 4] T_world_camera on an arc around the room centre, looking outwards.

    The camera moves along the arc while it turns, so consecutive views have both baseline
    (for triangulation) and overlap (for matching), like a robot turning in a room.
    """
    c = np.array([room.size[0] / 2, room.size[1] / 2, height_m])
    poses = []
    for a in np.radians(np.linspace(-sweep_deg / 2, sweep_deg / 2, n)):
        d = np.array([np.cos(a), np.sin(a), 0.0])
        eye = c - radius_m * d
        target = eye + look_distance_m * d + np.array([0.0, 0.0, -0.3])
        poses.append(look_at(eye, target))
    return np.stack(poses)


def default_camera(width: int = 320, height: int = 240, hfov_deg: float = 70.0) -> PinholeCamera:
    return PinholeCamera.from_fov(width, height, hfov_deg)


def write_room_sequence(root: Path | str, room: SyntheticRoom, camera: PinholeCamera,
                        poses: np.ndarray, rate_hz: float = 5.0, name: str = "box_room") -> Path:
    """A sequence folder (images, GT depth, GT poses, GT mesh; no scans) of the room.

    The rig puts the camera 0.3 m ahead of base_link in the REP 103 optical orientation, so
    readers must apply ``T_base_camera``; ground truth is ``T_world_base`` at frame stamps.
    """
    import open3d as o3d

    from toolkit.io.sequence import SequenceWriter

    T_base_camera = np.eye(4)
    T_base_camera[:3, :3] = R_BASE_OPTICAL
    T_base_camera[:3, 3] = [0.3, 0.0, 0.0]
    rig = Rig(camera, T_base_camera, np.eye(4))
    writer = SequenceWriter(root, rig, name, "toolkit.baselines.synthetic", depth_format="npy")
    render = room.renderer()
    stamps = 100.0 + np.arange(len(poses)) / rate_hz
    for t, T in zip(stamps, poses, strict=True):
        rgb, depth = render.render(camera, T)
        writer.add_frame(float(t), rgb, depth)
    writer.groundtruth_poses = Trajectory(stamps, poses @ inv_se3(T_base_camera), "world",
                                          "base_link")
    o3d.io.write_triangle_mesh(str(writer.mesh_path()), room.colored_mesh())
    return writer.close()

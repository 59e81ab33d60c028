"""A tiny raycast box room (with an optional walking "person" box, and an optional one that
stands still and then leaves) for tests and benchmarks.

It writes a regular sequence folder with ground truth (depth, dynamic masks, poses, mesh,
dynamic lidar beams) so fusion can be checked against known answers without the full
house simulator (``toolkit.sim``), and in a second rather than a minute.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from toolkit.camera import PinholeCamera
from toolkit.geometry import Trajectory, se2_to_se3, se3
from toolkit.sensors import LaserScan, Rig

# Where the standing box stands (x, y): in view from the drive's first frames to its last.
STANDING_BOX_XY = (2.2, 0.6)
# base_link (x forward, y left, z up) -> camera optical (x right, y down, z forward)
R_BASE_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _box_mesh(center: np.ndarray, size: np.ndarray) -> object:
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_box(*size)
    m.translate(np.asarray(center) - np.asarray(size) / 2)
    return m


def room_meshes(room: tuple[float, float, float] = (6.0, 4.0, 2.5)) -> list:
    """Static parts: floor, ceiling, four walls (inward facing boxes) and a table box."""
    L, W, H = room
    t = 0.1
    parts = [
        ((0, 0, -t / 2), (L + 2 * t, W + 2 * t, t)),  # floor
        ((0, 0, H + t / 2), (L + 2 * t, W + 2 * t, t)),  # ceiling
        ((L / 2 + t / 2, 0, H / 2), (t, W, H)),
        ((-L / 2 - t / 2, 0, H / 2), (t, W, H)),
        ((0, W / 2 + t / 2, H / 2), (L, t, H)),
        ((0, -W / 2 - t / 2, H / 2), (L, t, H)),
        ((1.6, 1.0, 0.4), (0.6, 0.6, 0.8)),  # a cabinet
        ((2.0, -1.2, 0.25), (0.8, 0.5, 0.5)),  # a low chest (below the camera)
    ]
    return [_box_mesh(np.array(c, float), np.array(s, float)) for c, s in parts]


def _colour(points: np.ndarray, part: np.ndarray, seed: int) -> np.ndarray:
    """Procedural texture: a per-part base colour times a few world-space sine patterns."""
    rng = np.random.default_rng(seed)
    base = rng.uniform(60, 220, (16, 3))
    freq = rng.uniform(3.0, 9.0, (3, 3))
    pattern = np.zeros(len(points))
    for k in range(3):
        pattern += np.sin(points @ freq[k] + k)
    c = base[part % 16] * (0.8 + 0.07 * pattern[:, None])
    # Plain low-texture band on the walls above 1.6 m (a low-texture test case).
    plain = (points[:, 2] > 1.6) & (part >= 2) & (part <= 5)
    c[plain] = base[part[plain] % 16] * 0.85
    return np.clip(c, 0, 255).astype(np.uint8)


def write_box_room(root: Path | str, n_frames: int = 30, width: int = 160, height: int = 120,
                   hfov_deg: float = 70.0, moving_box: bool = True, frame_rate: float = 5.0,
                   scan_rate: float = 10.0, seed: int = 0, depth_format: str = "npy",
                   standing_box: bool = False, stand_until: float = 0.7) -> Path:
    """Render the box room to a sequence folder at ``root`` and return it. ``standing_box``:
    a second "person" box stands still, in view, for the first ``stand_until`` of the
    drive and then is gone (seen there by most of the views of its place)."""
    import open3d as o3d

    from toolkit.io.sequence import SequenceWriter

    cam = PinholeCamera.from_fov(width, height, hfov_deg)
    T_base_camera = se3(R_BASE_OPTICAL, [0.1, 0.0, 0.6])
    T_base_laser = se3(None, [0.15, 0.0, 0.3])
    rig = Rig(cam, T_base_camera, T_base_laser)
    duration = n_frames / frame_rate

    def base_pose(t: np.ndarray) -> np.ndarray:
        # Drive along x while yawing gently: every wall comes into view.
        s = np.asarray(t) / duration
        x = -1.8 + 1.6 * s
        y = -0.3 + 0.4 * s
        yaw = -0.5 + 1.2 * s
        return np.stack([se2_to_se3(a, b, c) for a, b, c in zip(x, y, yaw, strict=True)])

    def person_center(t: float) -> np.ndarray:
        # Walks across the room in front of the robot, against its turn, so the places it
        # leaves are seen again (a person walking along with the gaze never is).
        s = t / duration
        return np.array([0.8, 1.5 - 3.0 * s, 0.8])

    person_size = np.array([0.4, 0.4, 1.6])
    stand_center = np.array(STANDING_BOX_XY + (0.8,))
    static = room_meshes()
    static_mesh = o3d.geometry.TriangleMesh()
    part_of_tri = []
    for i, m in enumerate(static):
        static_mesh += m
        part_of_tri += [i] * len(m.triangles)
    part_of_tri = np.array(part_of_tri)

    def scene_at(t: float) -> tuple[o3d.t.geometry.RaycastingScene, int]:
        sc = o3d.t.geometry.RaycastingScene()
        sc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(static_mesh))
        dyn_ids: list[int] = []
        if moving_box:
            dyn_ids.append(sc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(
                _box_mesh(person_center(t), person_size))))
        if standing_box and t < stand_until * duration:
            dyn_ids.append(sc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(
                _box_mesh(stand_center, person_size))))
        return sc, np.array(dyn_ids, np.int64)

    writer = SequenceWriter(root, rig, name="box_room", source="toolkit.fusion.synthetic",
                            depth_format=depth_format)
    rays_cam = cam.pixel_rays().reshape(-1, 3)  # [HW, 3] z = 1
    frame_t = (np.arange(n_frames) + 0.5) / frame_rate
    scan_t = np.arange(int(duration * scan_rate) + 1) / scan_rate
    for t in frame_t:
        T_wc = base_pose([t])[0] @ T_base_camera
        sc, dyn_ids = scene_at(float(t))
        d = rays_cam @ T_wc[:3, :3].T
        o = np.broadcast_to(T_wc[:3, 3], d.shape)
        ans = sc.cast_rays(o3d.core.Tensor(np.concatenate([o, d], 1).astype(np.float32)))
        th = ans["t_hit"].numpy().astype(np.float64)  # along rays with z = 1: z-depth
        gid = ans["geometry_ids"].numpy()
        pid = ans["primitive_ids"].numpy().astype(np.int64)
        hit = np.isfinite(th)
        pts = o + d * np.where(hit, th, 0)[:, None]
        is_dyn = np.isin(gid, dyn_ids)
        part = np.where(is_dyn, 15, part_of_tri[np.clip(pid, 0, len(part_of_tri) - 1)])
        img = _colour(pts, part, seed).reshape(height, width, 3)
        depth = np.where(hit, th, 0).reshape(height, width).astype(np.float32)
        mask = is_dyn.reshape(height, width) & hit.reshape(height, width)
        writer.add_frame(float(t), img, depth, mask)
    n_beams = 360
    angles = -np.pi + np.arange(n_beams) * (2 * np.pi / n_beams)
    for t in scan_t:
        T_wl = base_pose([t])[0] @ T_base_laser
        sc, dyn_ids = scene_at(float(t))
        d = np.stack([np.cos(angles), np.sin(angles), np.zeros(n_beams)], 1) @ T_wl[:3, :3].T
        o = np.broadcast_to(T_wl[:3, 3], d.shape)
        ans = sc.cast_rays(o3d.core.Tensor(np.concatenate([o, d], 1).astype(np.float32)))
        r = ans["t_hit"].numpy().astype(np.float32)
        r[~np.isfinite(r)] = np.nan
        writer.add_scan(LaserScan(float(t), r, -np.pi, 2 * np.pi / n_beams, 0.05, 12.0),
                        dynamic=np.isin(ans["geometry_ids"].numpy(), dyn_ids))
    stamps = np.unique(np.concatenate([frame_t, scan_t]))
    writer.groundtruth_poses = Trajectory(stamps, base_pose(stamps), "world", "base_link")
    o3d.io.write_triangle_mesh(str(writer.mesh_path()), static_mesh)
    return writer.close()

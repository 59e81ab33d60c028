"""Small synthetic scenes for tests, benchmarks and examples (no simulator needed).

A box room with procedurally coloured walls, as points with colours; a ground-truth
Gaussian model on those points; camera poses inside the room; and a writer that stores
renders of the ground truth as a sequence folder plus a ``fused``-style folder (map.ply and
per-frame depth), which is everything the ``splat`` stage reads.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from toolkit.camera import PinholeCamera
from toolkit.geometry import Trajectory, inv_se3
from toolkit.splat.model import GaussianModel, Gaussians, init_from_points

# Optical frame (z forward, x right, y down) of a camera looking along world +x (z up).
R_WORLD_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def room_points(n: int, seed: int = 0, size: tuple[float, float, float] = (6.0, 4.0, 2.6)) -> (
    tuple[np.ndarray, np.ndarray]
):
    """[n, 3] points on the six faces of a box room (area-weighted) and [n, 3] RGB 0..1.

    The room spans x in [-sx/2, sx/2], y in [-sy/2, sy/2], z in [0, sz].
    """
    rng = np.random.default_rng(seed)
    sx, sy, sz = size
    faces = [  # (fixed axis, its value, the two free axes)
        (0, -sx / 2, 1, 2), (0, sx / 2, 1, 2), (1, -sy / 2, 0, 2), (1, sy / 2, 0, 2),
        (2, 0.0, 0, 1), (2, sz, 0, 1),
    ]
    ext = {0: (-sx / 2, sx / 2), 1: (-sy / 2, sy / 2), 2: (0.0, sz)}
    areas = np.array([np.ptp(ext[a]) * np.ptp(ext[b]) for _, _, a, b in faces])
    which = rng.choice(len(faces), size=n, p=areas / areas.sum())
    pts = np.zeros((n, 3))
    for f, (axis, val, a, b) in enumerate(faces):
        m = which == f
        pts[m, axis] = val
        pts[m, a] = rng.uniform(*ext[a], size=m.sum())
        pts[m, b] = rng.uniform(*ext[b], size=m.sum())
    # Per-face colour with a checker and stripes, so images have texture to fit.
    base = rng.uniform(0.2, 0.8, size=(len(faces), 3))
    checker = ((np.floor(pts[:, 0] * 2) + np.floor(pts[:, 1] * 2) + np.floor(pts[:, 2] * 2))
               % 2)[:, None]
    stripes = 0.5 + 0.5 * np.sin(pts @ np.array([7.0, 5.0, 3.0]))[:, None]
    rgb = np.clip(base[which] * (0.6 + 0.4 * checker) * (0.8 + 0.2 * stripes), 0, 1)
    return pts, rgb


def look_pose(position: np.ndarray, yaw: float, pitch: float = 0.0) -> np.ndarray:
    """[4, 4] T_world_camera of a camera at ``position`` looking along ``yaw`` (about +z)."""
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    Rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    Ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])  # pitch down for sp > 0
    T = np.eye(4)
    T[:3, :3] = Rz @ Ry @ R_WORLD_OPTICAL
    T[:3, 3] = position
    return T


def room_camera(width: int, height: int, hfov_deg: float = 70.0) -> (
    tuple[PinholeCamera, np.ndarray]
):
    """The benchmark view: near one end of the room, looking down its length, turned 20 deg."""
    cam = PinholeCamera.from_fov(width, height, hfov_deg)
    return cam, inv_se3(look_pose(np.array([-2.2, -0.8, 1.2]), np.radians(20.0)))


def orbit_poses(n: int, radius: float = 0.8, height: float = 1.3, seed: int = 0) -> np.ndarray:
    """[n, 4, 4] T_world_camera on a small circle in the room, looking outwards at the walls."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        a = 2 * np.pi * i / n
        p = np.array([radius * np.cos(a), radius * np.sin(a), height + rng.uniform(-0.1, 0.1)])
        out.append(look_pose(p, a + rng.uniform(-0.3, 0.3), rng.uniform(-0.15, 0.15)))
    return np.stack(out)


def ground_truth_model(n: int, seed: int = 0, opaque: bool = True) -> GaussianModel:
    """Gaussians on the room's walls: the scene the synthetic images are rendered from."""
    pts, rgb = room_points(n, seed)
    model = init_from_points(pts, rgb, sh_degree=3, init_opacity=0.9 if opaque else 0.1,
                             seed=seed)
    with torch.no_grad():
        model.log_scales.add_(np.log(1.5))  # overlap, so the walls render without holes
    return model


def perturbed(g: Gaussians, seed: int = 0, opacity: float | None = None) -> Gaussians:
    """A 'mid-training' copy: anisotropic scales, random rotations and opacities, SH noise."""
    n = len(g)
    gen = torch.Generator().manual_seed(seed)
    log_s = g.log_scales + 0.4 * torch.randn(n, 3, generator=gen)
    quats = torch.randn(n, 4, generator=gen)
    op = (torch.full((n,), opacity) if opacity is not None
          else torch.rand(n, generator=gen) * 0.9 + 0.05)
    sh = g.full_sh().detach().clone()
    sh[:, 1:] = 0.05 * torch.randn(n, sh.shape[1] - 1, 3, generator=gen)
    return Gaussians(g.means.detach().clone(), quats, log_s.detach(), torch.logit(op), sh)


def write_synthetic_inputs(root: Path, n_frames: int = 16, width: int = 64, height: int = 48,
                           n_gaussians: int = 4000, seed: int = 0, heldout: int = 2,
                           depth_folder: str = "depth") -> tuple[Path, Path]:
    """A sequence folder and a fused folder rendered from ``ground_truth_model``.

    Returns (sequence_dir, fused_dir). The sequence has ground-truth base poses (base =
    camera here), ground-truth depth and ``heldout`` simulator-style held-out views.
    """
    from toolkit.io.depth import write_depth
    from toolkit.io.sequence import SequenceWriter
    from toolkit.sensors import Rig
    from toolkit.splat.rasterize import render

    root = Path(root)
    model = ground_truth_model(n_gaussians, seed)
    cam = PinholeCamera.from_fov(width, height, 70.0)
    poses = orbit_poses(n_frames + heldout, seed=seed)
    images, depths = [], []
    with torch.no_grad():
        for T_wc in poses:
            out = render(model, cam, inv_se3(T_wc))
            images.append((out.color.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8))
            depths.append(np.where(out.alpha.numpy() > 0.5, out.depth.numpy(), 0.0))
    seq_dir, fused_dir = root / "sequence", root / "fused"
    w = SequenceWriter(seq_dir, Rig(cam), name="synthetic_room", source="toolkit.splat.synthetic")
    stamps = np.arange(n_frames) * 0.1
    for i in range(n_frames):
        w.add_frame(float(stamps[i]), images[i], gt_depth=depths[i])
    for j in range(heldout):
        k = n_frames + j
        w.add_heldout(float(stamps[-1] + 0.1 * (j + 1)), poses[k], images[k], depths[k])
    w.groundtruth_poses = Trajectory(stamps, poses[:n_frames], "world", "base_link")
    w.close()
    # The fused map: the wall points with a little noise, coloured; depth as the fuse stage
    # writes it (per frame index).
    from toolkit.fusion.voxel_map import write_points_ply

    rng = np.random.default_rng(seed + 1)
    pts, rgb = room_points(n_gaussians, seed)
    fused_dir.mkdir(parents=True, exist_ok=True)
    write_points_ply(fused_dir / "map.ply", pts + rng.normal(0, 0.01, pts.shape),
                     np.clip(np.rint(rgb * 255), 0, 255).astype(np.uint8))
    for i in range(n_frames):
        write_depth(fused_dir / depth_folder / f"{i:06d}.npy", depths[i])
    return seq_dir, fused_dir

"""KITTI odometry pose files: 12 numbers per line, the top 3x4 of T_world_camera row-major."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from toolkit.geometry import Trajectory


def read_kitti(path: Path | str, times_path: Path | str | None = None) -> Trajectory:
    """Read poses; stamps from a KITTI ``times.txt`` file or 0, 1, 2, ... otherwise."""
    path = Path(path)
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        v = line.split()
        if len(v) != 12:
            raise ValueError(f"{path}:{lineno}: KITTI pose lines hold 12 numbers, got {len(v)}")
        rows.append([float(x) for x in v])
    M = np.array(rows, dtype=np.float64).reshape(-1, 3, 4)
    poses = np.tile(np.eye(4), (len(M), 1, 1))
    poses[:, :3, :] = M
    if times_path is not None:
        stamps = np.loadtxt(times_path, dtype=np.float64).reshape(-1)
        if len(stamps) != len(poses):
            raise ValueError(f"{times_path}: {len(stamps)} stamps for {len(poses)} poses in {path}")
    else:
        stamps = np.arange(len(poses), dtype=np.float64)
    return Trajectory(stamps, poses, "world", "camera")

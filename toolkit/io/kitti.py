"""KITTI odometry pose files: 12 numbers per line, the top 3x4 of T_world_camera row-major."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from toolkit.errors import InputError, MissingInputError
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
            raise InputError(f"{path}:{lineno}: KITTI pose lines hold 12 numbers, got {len(v)}")
        try:
            row = np.array([float(x) for x in v])
        except ValueError as e:
            raise InputError(f"{path}:{lineno}: {e}") from None
        R = row.reshape(3, 4)[:, :3]
        if not np.all(np.isfinite(row)) or not np.allclose(R @ R.T, np.eye(3), atol=1e-4) \
                or np.linalg.det(R) < 0:
            raise InputError(f"{path}:{lineno}: not a rigid pose (the first 3 of each group "
                             "of 4 numbers must form a rotation matrix, row-major)")
        rows.append(row)
    M = np.array(rows, dtype=np.float64).reshape(-1, 3, 4)
    poses = np.tile(np.eye(4), (len(M), 1, 1))
    poses[:, :3, :] = M
    if times_path is not None:
        if not Path(times_path).exists():
            raise MissingInputError(f"{times_path}: KITTI times file not found (give the "
                                    "sequence's times.txt, or none for stamps 0, 1, 2, ...)")
        try:
            stamps = np.loadtxt(times_path, dtype=np.float64).reshape(-1)
        except (OSError, ValueError) as e:
            raise InputError(f"{times_path}: not a KITTI times file (one number per line): "
                             f"{e}") from None
        if len(stamps) != len(poses):
            raise InputError(f"{times_path}: {len(stamps)} stamps for {len(poses)} poses in {path}")
    else:
        stamps = np.arange(len(poses), dtype=np.float64)
    return Trajectory(stamps, poses, "world", "camera")

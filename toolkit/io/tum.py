"""TUM trajectory files: ``t tx ty tz qx qy qz qw`` per line, ``#`` comments."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from toolkit.geometry import Trajectory, pose_to_tum_line, tum_line_to_pose
from toolkit.io.atomic import atomic_write_text


def format_tum(traj: Trajectory, header: str | None = None) -> str:
    """The file text. The header says which transform the poses are (``T_frame_child``)."""
    lines = [f"# T_{traj.frame}_{traj.child}: {traj.child} pose in {traj.frame}"]
    if header:
        lines += [f"# {h}" for h in header.splitlines()]
    lines.append("# timestamp tx ty tz qx qy qz qw")
    lines += [pose_to_tum_line(t, T) for t, T in zip(traj.stamps, traj.poses, strict=True)]
    return "\n".join(lines) + "\n"


def write_tum(path: Path | str, traj: Trajectory, header: str | None = None) -> None:
    """Write atomically (a reader never sees half a trajectory)."""
    atomic_write_text(Path(path), format_tum(traj, header))


def read_tum(
    path: Path | str, frame: str | None = None, child: str | None = None,
    require_monotonic: bool = True,
) -> Trajectory:
    """Read a TUM file; errors name the file and line. Frames come from our header if present."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: trajectory file not found")
    stamps, poses = [], []
    hdr_frame, hdr_child = "world", "base_link"
    for lineno, line in enumerate(path.read_text(encoding="utf-8-sig").splitlines(), 1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            if s.startswith("# T_") and ":" in s:
                name = s[4:].split(":", 1)[0]
                for known in ("base_link", "camera", "laser", "odom", "world"):
                    if name.startswith(known + "_"):
                        hdr_frame, hdr_child = known, name[len(known) + 1:]
                        break
            continue
        try:
            t, T = tum_line_to_pose(s.replace(",", " "))
        except ValueError as e:
            raise ValueError(f"{path}:{lineno}: {e}") from None
        stamps.append(t)
        poses.append(T)
    st = np.array(stamps, dtype=np.float64)
    if require_monotonic and len(st) > 1 and np.any(np.diff(st) <= 0):
        bad = int(np.argmax(np.diff(st) <= 0)) + 1
        raise ValueError(f"{path}: stamps not strictly increasing at pose {bad} "
                         f"({float(st[bad - 1])!r} then {float(st[bad])!r}, line order); "
                         "sort the file by stamp and remove repeated stamps")
    return Trajectory(st, np.array(poses).reshape(-1, 4, 4), frame or hdr_frame,
                      child or hdr_child)

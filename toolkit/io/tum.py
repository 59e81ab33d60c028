"""TUM trajectory files: ``t tx ty tz qx qy qz qw`` per line, ``#`` comments."""

from __future__ import annotations

import re
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
                hdr_frame, hdr_child = _header_frames(s, hdr_frame, hdr_child)
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


def _header_frames(line: str, frame: str, child: str) -> tuple[str, str]:
    """(frame, child) from a ``# T_<frame>_<child>: <child> pose in <frame>`` header line
    (``format_tum``'s; names may hold underscores: ``map``, ``base_footprint``,
    ``camera_optical``), else from ``# T_<frame>_<child>`` with a known frame name first;
    ``frame``, ``child`` when neither reads."""
    name, _, rest = line[4:].partition(":")
    said = re.fullmatch(r"\s*(.+?) pose in (.+?)\s*", rest)
    if said and name == f"{said.group(2)}_{said.group(1)}":
        return said.group(2), said.group(1)
    for known in ("base_link", "camera", "laser", "odom", "world", "map"):
        if name.startswith(known + "_"):
            return known, name[len(known) + 1:]
    return frame, child

"""TUM trajectory files: ``t tx ty tz qx qy qz qw`` per line, ``#`` comments."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from toolkit.errors import InputError, MissingInputError
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
    require_monotonic: bool = True, *, default_child: str = "base_link",
) -> Trajectory:
    """Read a TUM file; errors name the file and line. Frames come from our header if
    present (the first ``# T_`` comment line that names them, anywhere in the file),
    else world and ``default_child``; ``frame`` / ``child`` override both."""
    return read_tum_with_lines(path, frame, child, require_monotonic,
                               default_child=default_child)[0]


def read_tum_with_lines(
    path: Path | str, frame: str | None = None, child: str | None = None,
    require_monotonic: bool = True, *, default_child: str = "base_link",
) -> tuple[Trajectory, np.ndarray]:
    """``read_tum`` and the file line [N] int of each pose, for callers that check the
    stamps themselves and name the line."""
    path = Path(path)
    if not path.exists():
        raise MissingInputError(f"{path}: trajectory file not found")
    stamps, poses, lines = [], [], []
    header: tuple[str, str] | None = None
    for lineno, line in enumerate(path.read_text(encoding="utf-8-sig").splitlines(), 1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            # The first header that names the frames wins: format_tum writes its own first,
            # and a caller's free-text header after it must not replace it.
            if header is None and s.startswith("# T_") and ":" in s:
                header = _header_frames(s)
            continue
        try:
            t, T = tum_line_to_pose(s.replace(",", " "))
        except ValueError as e:
            raise InputError(f"{path}:{lineno}: {e}") from None
        stamps.append(t)
        poses.append(T)
        lines.append(lineno)
    st = np.array(stamps, dtype=np.float64)
    if require_monotonic and len(st) > 1 and np.any(np.diff(st) <= 0):
        bad = int(np.argmax(np.diff(st) <= 0)) + 1
        what = "repeats" if st[bad] == st[bad - 1] else "goes back from"
        raise InputError(f"{path}:{lines[bad]}: stamps not strictly increasing: "
                         f"{float(st[bad])!r} {what} {float(st[bad - 1])!r} (line "
                         f"{lines[bad - 1]}); sort the file by stamp and remove repeated "
                         "stamps")
    hdr_frame, hdr_child = header or ("world", default_child)
    traj = Trajectory(st, np.array(poses).reshape(-1, 4, 4), frame or hdr_frame,
                      child or hdr_child)
    return traj, np.array(lines, dtype=np.int64)


def _header_frames(line: str) -> tuple[str, str] | None:
    """(frame, child) from a ``# T_<frame>_<child>: <child> pose in <frame>`` header line
    (``format_tum``'s; names may hold underscores: ``map``, ``base_footprint``,
    ``camera_optical``), else from ``# T_<frame>_<child>`` with a known frame name first;
    None when neither reads."""
    name, _, rest = line[4:].partition(":")
    said = re.fullmatch(r"\s*(.+?) pose in (.+?)\s*", rest)
    if said and name == f"{said.group(2)}_{said.group(1)}":
        return said.group(2), said.group(1)
    for known in ("base_link", "camera", "laser", "odom", "world", "map"):
        if name.startswith(known + "_"):
            return known, name[len(known) + 1:]
    return None

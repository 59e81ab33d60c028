"""Which frames the ``splat`` stage holds out, in one place for every stage that asks.

The splat stage scores every ``holdout_every``-th of the frames it uses; the ``fuse`` stage
can leave those very frames out of its map (its ``holdout_every``), so that the cloud the
splats start from has not seen the images they are scored on. Both call ``heldout_split``
on the same posed frames (``camera_trajectory``): a second copy of the rule in either
stage could drift from the other without a test noticing.

Kept free of torch: the fuse stage imports it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np

from toolkit.geometry import Trajectory, inv_se3
from toolkit.recipe.stage import StageError
from toolkit.sensors import Sequence

PoseSetting = Literal["auto", "trajectory", "groundtruth"]


def camera_trajectory(seq: Sequence, trajectory: Path | None, poses: PoseSetting,
                      who: str = "splat") -> tuple[Trajectory, str]:
    """T_world_camera at the frames the poses cover, and where they came from ("trajectory"
    or "groundtruth"); ``extra["frame_index"]`` holds those frames' indices in the
    sequence. ``trajectory``: the upstream ``trajectory`` artifact (a TUM file or a folder
    holding one), None without one. ``who`` names the stage in errors."""
    from toolkit.io.tum import read_tum

    stamps = seq.frame_stamps
    if poses in ("auto", "trajectory") and trajectory is not None:
        path = Path(trajectory)
        if path.is_dir():
            names = ["trajectory_camera.tum", "camera_poses.tum", "trajectory.tum",
                     "poses_base.tum"]
            cands = [path / n for n in names if (path / n).exists()] or sorted(path.glob("*.tum"))
            if not cands:
                raise StageError(f"{who}: trajectory artifact {path} holds no .tum file")
            path = cands[0]
        # Without a header the file name is the only word on the poses' frame; the
        # reader's own header rule (anywhere in the file, after a UTF-8 BOM too) decides.
        traj = read_tum(path, default_child="camera" if "camera" in path.name else "base_link")
        if traj.child in ("base_link", "base"):
            traj = traj.transform(T_right=seq.rig.T_base_camera)
        elif traj.child == "laser":
            traj = traj.transform(T_right=inv_se3(seq.rig.T_base_laser) @ seq.rig.T_base_camera)
        traj.child = "camera"
        return _at(traj, stamps), "trajectory"
    if poses == "trajectory":
        raise StageError(f"{who}: poses: trajectory, but no stage upstream provides one "
                         f"(add slam2d before {who})")
    gt = seq.groundtruth
    if gt is None or gt.poses_base is None:
        raise StageError(f"{who}: no poses - run slam2d before {who}, or use a sequence with "
                         "ground-truth poses")
    traj = gt.poses_base.transform(T_right=seq.rig.T_base_camera)
    traj.child = "camera"
    return _at(traj, stamps), "groundtruth"


def _at(traj: Trajectory, stamps: np.ndarray) -> Trajectory:
    """Interpolated at ``stamps`` the trajectory covers (others dropped): inside its span
    and not across a gap in it (``Trajectory.covers``: slam2d gives frames in a gap
    between scans no pose, and a straight line across one is metres off)."""
    inside = traj.covers(stamps, slack_s=1e-6)
    out = traj.interpolate(stamps[inside], extrapolate_s=1e-6)
    out.extra["frame_index"] = np.nonzero(inside)[0]
    return out


def heldout_split(n_posed: int, frame_stride: int, holdout_every: int) -> tuple[
        list[int], list[int]]:
    """(training, held-out) positions among ``n_posed`` posed frames: every
    ``frame_stride``-th is used, and every ``holdout_every``-th of those used is held out
    (0: none; the Mip-NeRF 360 convention). Counted over the frames used, not all posed
    ones: with a frame_stride that would hold out too many, or all."""
    if frame_stride < 1 or holdout_every < 0:
        raise ValueError(f"frame_stride {frame_stride} must be >= 1 and holdout_every "
                         f"{holdout_every} >= 0")
    used = range(0, n_posed, frame_stride)
    held = [holdout_every > 0 and j % holdout_every == 0 for j in range(len(used))]
    train = [k for k, hd in zip(used, held, strict=True) if not hd]
    test = [k for k, hd in zip(used, held, strict=True) if hd]
    return train, test


def heldout_frames(seq: Sequence, trajectory: Path | None, poses: PoseSetting,
                   frame_stride: int, holdout_every: int, who: str = "fuse") -> list[int]:
    """Sequence indices of the frames a ``splat`` stage with these settings holds out, at
    the poses it would take (the same ``trajectory`` artifact and ``poses`` setting)."""
    if holdout_every == 0:
        return []
    index = camera_trajectory(seq, trajectory, poses, who)[0].extra["frame_index"]
    return [int(index[k]) for k in heldout_split(len(index), frame_stride, holdout_every)[1]]

"""The fuse stage's ``holdout_every``: the splat stage's held-out frames left out of the map,
chosen by the one rule both stages call (``toolkit.heldout``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from recipe_helpers import SequenceFolder, run_stages  # the tests folder is on sys.path

from toolkit.fusion.synthetic import write_box_room
from toolkit.geometry import Trajectory
from toolkit.io.sequence import read_sequence
from toolkit.io.tum import read_tum, write_tum

N_FRAMES = 20


@pytest.fixture(scope="module")
def box_room(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_box_room(tmp_path_factory.mktemp("box") / "seq", n_frames=N_FRAMES)


def test_split_counts_the_frames_used() -> None:
    """12 posed frames at frame_stride 2 are positions 0, 2, ..., 10; every 4th of those
    six (the 1st and 5th) is held out: positions 0 and 8."""
    from toolkit.heldout import heldout_split

    assert heldout_split(12, 2, 4) == ([2, 4, 6, 10], [0, 8])
    assert heldout_split(5, 1, 0) == ([0, 1, 2, 3, 4], [])


def test_held_out_frames_follow_the_posed_frames_not_the_frame_numbers(
        box_room: Path, tmp_path: Path) -> None:
    """A trajectory that starts at frame 2 poses frames 2..19: every 8th of those is frames
    2, 10 and 18 (not 0, 8, 16), for the fuse stage's question as for the splat stage."""
    from toolkit.heldout import camera_trajectory, heldout_frames

    seq = read_sequence(box_room)
    gt = seq.groundtruth
    assert gt is not None and gt.poses_base is not None
    st = seq.frame_stamps
    keep = gt.poses_base.stamps >= st[2] - 1e-9
    cam = Trajectory(gt.poses_base.stamps[keep],
                     gt.poses_base.poses[keep] @ seq.rig.T_base_camera, "world", "camera")
    write_tum(tmp_path / "trajectory_camera.tum", cam)
    index = camera_trajectory(seq, tmp_path, "auto")[0].extra["frame_index"]
    assert list(index) == list(range(2, N_FRAMES))
    assert heldout_frames(seq, tmp_path, "auto", 1, 8) == [2, 10, 18]
    # Ground-truth poses cover every frame.
    assert heldout_frames(seq, None, "auto", 3, 2) == [0, 6, 12, 18]


@pytest.mark.parametrize("before", ["\ufeff", "# a\n# b\n# c\n# d\n# e\n# f\n"])
def test_camera_trajectory_reads_the_header_as_read_tum_does(
        box_room: Path, tmp_path: Path, before: str) -> None:
    """A base_link trajectory in camera_poses.tum whose header comes after a UTF-8 BOM or
    after 5 other comment lines: read_tum reads its header, camera_trajectory looked for it
    in the first 5 lines without the BOM stripped and, by the file name, took the base
    poses for camera poses (off by the rig's camera offset)."""
    from toolkit.heldout import camera_trajectory
    from toolkit.io.tum import format_tum

    seq = read_sequence(box_room)
    gt = seq.groundtruth
    assert gt is not None and gt.poses_base is not None
    path = tmp_path / "camera_poses.tum"
    path.write_text(before + format_tum(gt.poses_base), encoding="utf-8")
    assert read_tum(path).child == "base_link"
    traj, source = camera_trajectory(seq, path, "auto")
    index = traj.extra["frame_index"]
    expected, _ = camera_trajectory(seq, None, "groundtruth")
    assert source == "trajectory" and list(index) == list(range(N_FRAMES))
    np.testing.assert_allclose(traj.poses, expected.poses, atol=1e-9)


def test_the_default_leaves_the_settings_as_before() -> None:
    """Off, the hold-out options are not serialised: fuse runs made before them keep their
    cache key. On, they are."""
    from toolkit.fusion.stage import FuseConfig

    off = FuseConfig(stage="fuse").model_dump(mode="json")
    assert "holdout_every" not in off and "holdout_frame_stride" not in off
    on = FuseConfig(stage="fuse", holdout_every=8, holdout_frame_stride=2).model_dump()
    assert on["holdout_every"] == 8 and on["holdout_frame_stride"] == 2


def test_fuse_leaves_the_splat_stages_held_out_frames_out_of_the_map(
        box_room: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """frame_stride 3 and holdout_every 2 over 20 posed frames: frames 0, 3, ..., 18 are
    used, every 2nd of those held out: 0, 6, 12, 18. None of them reaches the map or the
    exposure solve; the splat stage behind it scores exactly those four, and finds none of
    them in the map it starts from."""
    from toolkit.depth.stage import DepthStage
    from toolkit.fusion.pipeline import Fusion
    from toolkit.fusion.stage import FuseStage
    from toolkit.splat.stage import SplatStage

    integrated: list[int] = []
    observed: list[int] = []
    integrate, observe = Fusion.integrate, Fusion.exposure_observations

    def record_integrate(self: Fusion, index: int, *a: object, **k: object) -> int:
        integrated.append(index)
        return integrate(self, index, *a, **k)  # type: ignore[arg-type]

    def record_observe(self: Fusion, index: int, *a: object, **k: object) -> object:
        observed.append(index)
        return observe(self, index, *a, **k)  # type: ignore[arg-type]

    monkeypatch.setattr(Fusion, "integrate", record_integrate)
    monkeypatch.setattr(Fusion, "exposure_observations", record_observe)
    held = {0, 6, 12, 18}
    res = run_stages(tmp_path, [
        {"stage": "t_sequence", "path": str(box_room)},
        {"stage": "depth", "backend": "simulated", "simulated": {"seed": 1}},
        {"stage": "fuse", "mesh_eval_frames": 0, "exposure": "gain",
         "holdout_every": 2, "holdout_frame_stride": 3},
        {"stage": "splat", "iterations": 3, "downscale": 2, "frame_stride": 3,
         "holdout_every": 2, "init_budget": 500, "max_seconds": None, "strip_views": 1},
    ], {"t_sequence": SequenceFolder, "depth": DepthStage, "fuse": FuseStage,
        "splat": SplatStage})
    assert res.ok, res.error
    m = res.metrics["fuse"]
    assert m["frames_flagged"] == 0  # so every other frame is fused
    assert sorted(integrated) == sorted(set(range(N_FRAMES)) - held)
    assert observed and not set(observed) & held
    assert m["frames_held_out"] == 4 and m["frames_held_out_indices"] == sorted(held)
    assert m["frames_fused"] == N_FRAMES - 4
    fuse_dir = tmp_path / "run" / "fuse"
    seq = read_sequence(box_room)
    fused_stamps = read_tum(fuse_dir / "camera_poses.tum").stamps
    assert not np.isin(np.round(seq.frame_stamps[sorted(held)], 6),
                       np.round(fused_stamps, 6)).any()
    assert not any((fuse_dir / "scaled_depth" / f"{i:06d}.png").exists() for i in held)
    s = res.metrics["splat"]
    assert s["heldout_frames"] == 4 and s["train_views"] == 3
    assert s["heldout_frames_in_fused_map"] == 0


def test_the_splat_stage_counts_the_held_out_frames_a_map_saw(
        box_room: Path, tmp_path: Path) -> None:
    """Without the fuse stage's hold-out every held-out frame is in the map: 3 of 3."""
    from toolkit.depth.stage import DepthStage
    from toolkit.fusion.stage import FuseStage
    from toolkit.splat.stage import SplatStage

    res = run_stages(tmp_path, [
        {"stage": "t_sequence", "path": str(box_room)},
        {"stage": "depth", "backend": "simulated", "simulated": {"seed": 1}},
        {"stage": "fuse", "mesh_eval_frames": 0},
        {"stage": "splat", "iterations": 2, "downscale": 2, "holdout_every": 8,
         "init_budget": 500, "max_seconds": None, "strip_views": 1},
    ], {"t_sequence": SequenceFolder, "depth": DepthStage, "fuse": FuseStage,
        "splat": SplatStage})
    assert res.ok, res.error
    assert res.metrics["fuse"]["frames_fused"] == N_FRAMES
    s = res.metrics["splat"]
    assert s["heldout_frames"] == 3 and s["heldout_frames_in_fused_map"] == 3

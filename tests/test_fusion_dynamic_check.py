"""python -m toolkit.fusion.dynamic_check: the lidar's moving-obstacle flags scored against a
simulated recording's per-beam truth, standing people apart."""

from __future__ import annotations

from pathlib import Path

import pytest

import toolkit.sim.simulate as sim
from toolkit.fusion.dynamic_check import check
from toolkit.sim.sensors import CameraSpec


def test_far_partners_find_the_people_who_stood(tmp_path: Path) -> None:
    """A 30-s drive (seed 2, 80x60 camera: the lidar is what is scored) with two people who
    stand 8-12 s at their routes' ends: the near partners (+-4 s) find few of the standing
    people's beams (0.04 when measured), the far ones most (0.69), precision staying high."""
    cam = CameraSpec(width=80, height=60, fx=65.6, fy=65.6)
    root = sim.simulate(sim.SimConfig(seed=2, n_people=2, duration_s=30.0, n_heldout=0,
                                      camera=cam, people_stand_s=(8.0, 12.0)),
                        tmp_path / "sim").root
    out = check(root)
    assert out["truth"]["standing"] > 500
    near, far = out["near"], out["near+far"]
    assert near["recall_standing"] < 0.2 < 0.5 < far["recall_standing"]
    assert far["recall_moving"] >= near["recall_moving"] > 0.8
    assert min(near["precision"], far["precision"]) > 0.95


def test_a_recording_without_people_tracks_is_scored_whole(tmp_path: Path) -> None:
    """The synthetic box room has per-beam truth but no house.json: it was a
    FileNotFoundError; now the flags are scored without the standing split."""
    from toolkit.fusion.synthetic import write_box_room

    out = check(write_box_room(tmp_path / "seq", n_frames=20))
    assert "recall_standing" not in out["near"] and "standing" not in out["truth"]
    assert out["truth"]["beams"] > 0 and out["near"]["precision"] > 0.9


def test_cli_names_a_wrong_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``python -m toolkit.fusion.dynamic_check <sequence>`` given a folder that is not a
    sequence ended in a traceback (SequenceFormatError); now one error line and exit 2,
    and the usage line names the module, not ``dynamic_check.py``."""
    from toolkit.fusion.dynamic_check import main

    assert main([str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "sequence folder not found" in err
    assert str(tmp_path / "none") in err and "Traceback" not in err
    with pytest.raises(SystemExit):
        main(["--help"])
    assert "python -m toolkit.fusion.dynamic_check" in capsys.readouterr().out

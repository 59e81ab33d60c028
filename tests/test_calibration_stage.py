"""The recipe stage ``calibrate`` run by the recipe runner on a capture folder."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from recipe_helpers import run_stages  # the tests folder is on sys.path

from calibration.stage import CalibrateStage
from calibration.synthetic import make_capture, write_capture


def test_calibrate_stage_writes_rig_and_metrics(tmp_path: Path) -> None:
    from toolkit.io.sequence import read_rig

    cap = make_capture(6, seed=21)
    write_capture(cap, tmp_path / "capture")
    res = run_stages(tmp_path, [
        {"stage": "calibrate", "capture": str(tmp_path / "capture"), "board": "11x8",
         "square_m": 0.05, "leave_one_out": False, "range_noise_m": 0.012}],
        {"calibrate": CalibrateStage})
    assert res.ok, res.error
    m = res.metrics["calibrate"]
    assert m["views_used"] == 6 and m["residual_rms_m"] < 0.012
    assert m["rotation_error_deg"] < 0.5 and m["translation_error_m"] < 0.01
    rig = read_rig(tmp_path / "run" / "calibrate" / "rig.yaml")
    assert np.allclose(rig.T_camera_laser, cap.T_camera_laser, atol=0.01)
    calib = yaml.safe_load((tmp_path / "run" / "calibrate" / "calibration.yaml").read_text())
    assert "T_camera_laser" in calib and "error_vs_ground_truth" in calib
    # The range noise given sets the board-line band (2 sigma) instead of the measured one.
    assert calib["lidar_range_noise_source"] == "given"
    assert calib["board_line_band_m"] == pytest.approx(0.024)
    assert "Extrinsic from 6 board views" in (tmp_path / "run" / "report.md").read_text()


def test_an_unreliable_extrinsic_stops_the_stage(tmp_path: Path) -> None:
    """Eight upright boards turned only about the vertical leave the extrinsic's height
    and pitch free: the checks call it unreliable, and the stage stops (it passed the
    result on as the rig, 16 deg / 0.3 m off) unless allow_unreliable says otherwise."""
    cap = make_capture(8, seed=7, min_tilt_deg=0.0, max_tilt_deg=0.0)
    write_capture(cap, tmp_path / "capture")
    stage = {"stage": "calibrate", "capture": str(tmp_path / "capture"), "board": "11x8",
             "square_m": 0.05, "leave_one_out": False}
    (tmp_path / "a").mkdir()
    res = run_stages(tmp_path / "a", [stage], {"calibrate": CalibrateStage})
    assert not res.ok and "unreliable" in res.error and "allow_unreliable" in res.error
    assert ".." not in res.error, res.error  # each reason ends in a period of its own
    out = tmp_path / "a" / "run" / "calibrate"
    assert (out / "calibration.unreliable.yaml").exists() and not (out / "rig.yaml").exists()
    (tmp_path / "b").mkdir()
    res = run_stages(tmp_path / "b", [{**stage, "allow_unreliable": True}],
                     {"calibrate": CalibrateStage})
    assert res.ok and res.metrics["calibrate"]["reliable"] is False


@pytest.mark.slow  # renders a 4 s drive through the house: 10 s CPU, a minute on a busy machine
def test_check_only_after_simulate_separates_a_2_degree_error(tmp_path: Path) -> None:
    """What the quickstart runs: `calibrate` with `mode: check` after `simulate`.

    The simulator's rig is exact, so the stage scores the true extrinsic and the same turned
    by 2 degrees, and writes the overlays into the report.
    """
    from toolkit.recipe.runner import run_recipe
    from toolkit.recipe.schema import load_recipe

    recipe = {"name": "t", "output": str(tmp_path / "run"), "stages": [
        {"stage": "simulate", "preset": "small_house", "seed": 0, "duration_s": 4.0,
         "n_people": 1, "n_heldout": 0},
        {"stage": "calibrate", "mode": "check", "check_frames": 12}]}
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(recipe))
    res = run_recipe(load_recipe(tmp_path / "r.yaml", []))
    assert res.ok, res.error
    m = res.metrics["calibrate"]
    assert m["check_kind"] == "depth" and m["rotation_error_deg"] == 0.0
    assert m["check_score_true"] > 0.9
    assert m["check_score_true_rotated_2deg"] < 0.8 * m["check_score_true"]
    report = (tmp_path / "run" / "report.md").read_text()
    assert "the simulator's exact rig" in report and "| rotated ry+2deg |" in report
    for k in range(2):
        assert (tmp_path / "run" / "calibrate" / "check" / f"overlay_vs_rotated_{k}.png").exists()
        assert f"(calibrate/check/overlay_vs_rotated_{k}.png)" in report
    # 4 s of driving hold no turn to read a camera delay from: the report says so.
    assert "**Camera time offset**" in report
    assert "Not reliable: the robot's turning hardly changed" in report
    assert not m["camera_delay_reliable"]


def test_missing_calibration_files_stop_validate(tmp_path: Path) -> None:
    from toolkit.recipe.runner import missing_inputs
    from toolkit.recipe.schema import parse_recipe

    for stage in ({"stage": "calibrate", "mode": "check", "extrinsic": str(tmp_path / "e")},
                  {"stage": "calibrate", "capture": str(tmp_path / "cap")}):
        recipe = parse_recipe({"name": "t", "output": str(tmp_path / "run"),
                               "stages": [stage]})
        problems = missing_inputs(recipe)
        assert len(problems) == 1 and "does not exist" in problems[0]

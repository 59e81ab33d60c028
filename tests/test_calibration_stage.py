"""The recipe stage ``calibrate`` run by the recipe runner on a capture folder."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from calibration.stage import CalibrateStage
from calibration.synthetic import make_capture, write_capture


def test_calibrate_stage_writes_rig_and_metrics(tmp_path: Path) -> None:
    from toolkit.io.sequence import read_rig
    from toolkit.recipe import registry
    from toolkit.recipe.runner import run_recipe
    from toolkit.recipe.schema import load_recipe

    cap = make_capture(6, seed=21)
    write_capture(cap, tmp_path / "capture")
    recipe = {"name": "t", "output": str(tmp_path / "run"), "stages": [
        {"stage": "calibrate", "capture": str(tmp_path / "capture"), "board": "11x8",
         "square_m": 0.05, "leave_one_out": False}]}
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(recipe))
    registry.register("calibrate", CalibrateStage)
    try:
        res = run_recipe(load_recipe(tmp_path / "r.yaml", []))
    finally:
        registry.unregister("calibrate")
    assert res.ok, res.error
    m = res.metrics["calibrate"]
    assert m["views_used"] == 6 and m["residual_rms_m"] < 0.012
    assert m["rotation_error_deg"] < 0.5 and m["translation_error_m"] < 0.01
    rig = read_rig(tmp_path / "run" / "calibrate" / "rig.yaml")
    assert np.allclose(rig.T_camera_laser, cap.T_camera_laser, atol=0.01)
    calib = yaml.safe_load((tmp_path / "run" / "calibrate" / "calibration.yaml").read_text())
    assert "T_camera_laser" in calib and "error_vs_ground_truth" in calib
    assert "Extrinsic from 6 board views" in (tmp_path / "run" / "report.md").read_text()

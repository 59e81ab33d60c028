"""Full benchmark runs on the shipped real logs and the simulated corridor (slow: minutes
each; ``pytest -m slow``).

Bounds are the figures measured when the benchmarks were last run (docs/slam2d.md) with a
margin, so that a regression shows; the issue's targets are in the docs next to them.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from toolkit.slam2d.bench import run_benchmark, shared_data_dir

pytestmark = pytest.mark.slow


def _data() -> Path:
    d = shared_data_dir()
    if not (d / "slam2d").exists():
        pytest.skip(f"{d}/slam2d is not on this machine (set TOOLKIT_SHARED_DATA)")
    return d


def test_killian_relations(tmp_path: Path):
    f = run_benchmark("killian", tmp_path, data_dir=_data())
    rel = f["relations"]
    assert rel["relations_used"] == 658
    assert rel["trans_abs_mean_m"] < 0.038
    assert rel["rot_abs_mean_deg"] < 0.34
    assert f["slam"]["realtime_factor_cpu"] > 40


@pytest.mark.parametrize("name", ["intel", "aces"])
def test_radish_scan_only_ate(tmp_path: Path, name: str):
    f = run_benchmark(name, tmp_path, data_dir=_data())
    assert f["ate"]["ate_rmse_m"] < 0.12
    assert (tmp_path / f"{name}_map.png").exists()


@pytest.mark.parametrize("angle", [0.0, 35.0])
def test_corridor_benchmark(tmp_path: Path, angle: float):
    """The simulated featureless corridor, along the grid and at an angle to it:
    centimetres with the odometry held along the corridor and the closures that the
    corridor leaves free along its axis rejected (docs/slam2d.md: seed 0 0.046 / 0.037 m;
    medians over eight drives 0.048 / 0.030 m)."""
    f = run_benchmark("corridor", tmp_path, corridor_angle_deg=angle)
    assert f["ate"]["ate_rmse_m"] < 0.06
    assert f["slam"]["loop_closures_degenerate"] > 0
    assert (tmp_path / "corridor_map.png").exists()


def test_corridor_seeds(tmp_path: Path):
    """--seeds drives seeds 0..N-1: seed 0's figures as one run's, the spread beside them
    (one drive's ATE swings with its odometry noise)."""
    f = run_benchmark("corridor", tmp_path, seeds=3)
    spread = f["ate_seeds"]
    assert spread["seeds"] == 3 and len(spread["ate_rmse_m"]) == 3
    assert spread["ate_rmse_m"][0] == f["ate"]["ate_rmse_m"]
    assert len(set(spread["ate_rmse_m"])) == 3  # different drives
    assert spread["ate_rmse_min_m"] <= spread["ate_rmse_median_m"] <= spread["ate_rmse_max_m"]
    with pytest.raises(ValueError, match="recording"):
        run_benchmark("killian", tmp_path, seeds=2)

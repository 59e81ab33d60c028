"""Camera - lidar time offset: a known camera delay is measured from the turning and undone
by ingest."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from calibration.cli import main as calibration_main
from calibration.time_offset import (
    TimeOffsetError,
    estimate_camera_delay,
    up_in_camera,
    yaw_of_rotation,
)
from toolkit.geometry import Trajectory, inv_se3, se2_to_se3
from toolkit.ingest.convert import convert
from toolkit.ingest.stage import read_sequence_recording
from toolkit.ingest.sync import SyncOptions
from toolkit.io.sequence import read_sequence
from toolkit.sim.sensors import CameraSpec
from toolkit.sim.simulate import SimConfig, simulate


def _turning(t: np.ndarray) -> np.ndarray:
    """Yaw (rad) of a robot that turns left and right at up to ~0.8 rad/s."""
    return 0.5 * np.sin(1.3 * t) + 0.3 * np.sin(0.45 * t + 1.0)


def _trajectory(t: np.ndarray) -> Trajectory:
    return Trajectory(t, np.stack([se2_to_se3(0.1 * s, 0.0, y) for s, y in
                                   zip(t, _turning(t), strict=True)]), "world", "base_link")


def test_a_known_delay_is_found_with_noise_and_outliers() -> None:
    rng = np.random.default_rng(0)
    scan_t = np.arange(0.0, 60.0, 0.1) + 0.043  # the lidar's clock
    traj = _trajectory(scan_t)
    taken = np.arange(0.5, 59.0, 0.1) + rng.uniform(-0.002, 0.002, 585)
    delay = 0.065
    dyaw = np.diff(_turning(taken)) + rng.normal(0, np.radians(0.1), len(taken) - 1)
    bad = rng.random(len(dyaw)) < 0.1  # tracking failures: wild rotations
    dyaw[bad] += rng.normal(0, np.radians(5), int(bad.sum()))
    dyaw[rng.random(len(dyaw)) < 0.05] = np.nan  # no rotation found
    res = estimate_camera_delay(taken + delay, dyaw, traj)
    assert res.reliable, res.reasons
    assert res.delay_s == pytest.approx(delay, abs=0.002)
    assert res.std_s < 0.005
    assert res.residual_deg < res.residual_at_zero_deg
    # Early stamps are a negative delay.
    assert estimate_camera_delay(taken - 0.03, dyaw, traj).delay_s == pytest.approx(-0.03,
                                                                                    abs=0.002)


def test_a_straight_drive_or_a_steady_circle_cannot_tell_and_says_so() -> None:
    t = np.arange(0.0, 30.0, 1 / 30)  # tracking noise at 30 Hz read as turning before
    rng = np.random.default_rng(1)
    noise = rng.normal(0, np.radians(0.1), len(t) - 31)
    for yaw_rate in (0.0, 0.4):
        traj = Trajectory(t, np.stack([se2_to_se3(0.3 * s, 0.0, 0.2 + yaw_rate * s)
                                       for s in t]))
        frames = t[15:-15]
        res = estimate_camera_delay(frames + 0.05, yaw_rate * np.diff(frames) + noise, traj)
        assert not res.reliable
        assert any("turning hardly changed" in r for r in res.reasons), res.reasons
    with pytest.raises(TimeOffsetError, match="trajectory must cover"):
        estimate_camera_delay(t[5:-5] + 100.0, np.zeros(len(t) - 11), traj)


def test_the_reported_spread_is_the_estimates_spread() -> None:
    """Overlapping windows share frame pairs: resampled one by one they gave spreads 1.5-3x
    too small; runs of windows give the spread of the estimates over noise draws."""
    scan_t = np.arange(0.0, 40.0, 0.1)
    traj = _trajectory(scan_t)
    taken = np.arange(1.0, 39.0, 1 / 30)  # 30 Hz: 15 frames a window
    est, spread = [], []
    for seed in range(12):
        rng = np.random.default_rng(seed)
        dyaw = np.diff(_turning(taken)) + rng.normal(0, np.radians(0.3), len(taken) - 1)
        res = estimate_camera_delay(taken + 0.05, dyaw, traj, bootstrap=40)
        est.append(res.delay_s)
        spread.append(res.std_s)
    ratio = float(np.mean(spread)) / float(np.std(est))
    assert 0.6 < ratio < 1.7, ratio


def test_camera_rotation_reads_as_the_robots_yaw() -> None:
    """A left turn of the base is a positive yaw, whatever the camera's pitch."""
    spec = CameraSpec(pitch_deg=12.0)
    T_bc = spec.T_base_camera()
    T_wc0 = se2_to_se3(1.0, 2.0, 0.3) @ T_bc
    T_wc1 = se2_to_se3(1.1, 2.0, 0.3 + np.radians(4.0)) @ T_bc
    R = (inv_se3(T_wc1) @ T_wc0)[:3, :3]  # x1 = R x0
    assert np.degrees(yaw_of_rotation(R, up_in_camera(T_bc))) == pytest.approx(4.0, abs=1e-9)


@pytest.fixture(scope="module")
def delayed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 24 s drive (several turns) whose camera stamps its images 60 ms late."""
    root = tmp_path_factory.mktemp("delayed")
    cam = CameraSpec(stamp_delay_s=0.06)  # 640x480: at 320x240 tracking read 2.7 ms late
    simulate(SimConfig(seed=0, n_people=0, duration_s=24.0, n_heldout=0, camera=cam),
             root / "seq")
    return root / "seq"


def test_the_simulated_delay_is_measured_and_undone_by_ingest(delayed: Path,
                                                               tmp_path: Path) -> None:
    seq = read_sequence(delayed)
    # The simulator stamps late; its ground truth stays on the true clock.
    assert seq.groundtruth is not None and seq.groundtruth.poses_base.covers(
        seq.frame_stamps).all()
    out = tmp_path / "to"
    assert calibration_main(["time-offset", "--sequence", str(delayed), "--out",
                             str(out)]) == 0  # against the sequence's wheel odometry
    found = json.loads((out / "time_offset.json").read_text())
    assert found["reliable"]
    assert found["delay_s"] == pytest.approx(0.06, abs=0.003)
    assert (out / "time_offset.png").stat().st_size > 10_000

    fixed = convert(read_sequence_recording(delayed), tmp_path / "fixed",
                    SyncOptions(camera_delay_s=found["delay_s"]))
    assert fixed.frames == len(seq.frames)
    again = read_sequence(tmp_path / "fixed")
    assert again.frame_stamps == pytest.approx(seq.frame_stamps - found["delay_s"], abs=1e-6)
    out2 = tmp_path / "to2"
    assert calibration_main(["time-offset", "--sequence", str(tmp_path / "fixed"), "--out",
                             str(out2)]) == 0
    assert json.loads((out2 / "time_offset.json").read_text())["delay_s"] == pytest.approx(
        0.0, abs=0.005)


def test_time_offset_cli_names_what_is_missing(delayed: Path, tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    assert calibration_main(["time-offset", "--sequence", str(tmp_path / "none")]) == 2
    assert "sequence folder not found" in capsys.readouterr().err
    far = tmp_path / "far.tum"
    seq = read_sequence(delayed)
    from toolkit.io.tum import write_tum

    gt = seq.groundtruth.poses_base
    write_tum(far, Trajectory(gt.stamps + 1000.0, gt.poses))
    assert calibration_main(["time-offset", "--sequence", str(delayed), "--trajectory",
                             str(far), "--out", str(tmp_path / "o")]) == 2
    assert "another clock?" in capsys.readouterr().err


def test_time_offset_cli_names_a_sequence_without_images(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A lidar-only sequence (a converted CARMEN log) was refused with '0 camera frames;
    at least 3 are needed', naming neither the folder nor why it had none."""
    from toolkit.io.carmen_ingest import read_carmen_recording

    log = tmp_path / "run.log"
    log.write_text("".join(f"FLASER 4 1.0 2.0 3.0 3.5 {0.1 * i:.1f} 0 0 {0.1 * i:.1f} 0 0 "
                           f"{10 + 0.1 * i:.1f} host {10 + 0.1 * i:.1f}\n" for i in range(20)))
    convert(read_carmen_recording(log), tmp_path / "lidar_only")
    assert calibration_main(["time-offset", "--sequence", str(tmp_path / "lidar_only"),
                             "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert str(tmp_path / "lidar_only") in err and "0 camera frames" in err, err
    assert "lidar-only" in err, err


def test_the_calibrate_check_reports_the_delay(delayed: Path, tmp_path: Path) -> None:
    """The quickstart's `calibrate` check measures the delay and says how to undo it."""
    from recipe_helpers import SequenceFolder, run_stages  # the tests folder is on sys.path

    from calibration.stage import CalibrateStage

    res = run_stages(tmp_path, [{"stage": "t_sequence", "path": str(delayed)},
                                {"stage": "calibrate", "mode": "check", "check_frames": 4}],
                     {"t_sequence": SequenceFolder, "calibrate": CalibrateStage})
    assert res.ok, res.error
    m = res.metrics["calibrate"]
    assert m["camera_delay_reliable"]
    assert m["camera_delay_s"] == pytest.approx(0.06, abs=0.003)
    report = (tmp_path / "run" / "report.md").read_text()
    assert "sync: {camera_delay_s: 0.06" in report
    assert (tmp_path / "run" / "calibrate" / "check" / "time_offset.png").exists()
    assert "(calibrate/check/time_offset.png)" in report


def test_a_partly_corrected_recording_is_told_the_whole_setting(delayed: Path,
                                                                tmp_path: Path) -> None:
    """Measured after a conversion that took out 30 ms, the advice is the sum, not the rest
    (the check runs on the converted sequence; the recipe's setting is the whole delay)."""
    convert(read_sequence_recording(delayed), tmp_path / "part",
            SyncOptions(camera_delay_s=0.03))
    out = tmp_path / "to"
    assert calibration_main(["time-offset", "--sequence", str(tmp_path / "part"), "--out",
                             str(out)]) == 0
    found = json.loads((out / "time_offset.json").read_text())
    assert found["applied_at_conversion_s"] == 0.03
    assert found["delay_s"] == pytest.approx(0.03, abs=0.003)
    from calibration.time_offset import TimeOffsetResult, advice

    res = TimeOffsetResult(0.0301, 0.001, 100, 5, 0.3, 0.1, 0.2, True)
    assert "camera_delay_s: 0.0601}" in advice(res, 0.03)
    # The whole setting applied to the measured folder itself moves it by the rest only,
    # to the stamps a single conversion of the original gives (it took 30 ms out twice).
    # Unset, a conversion keeps the folder's correction.
    once = convert(read_sequence_recording(delayed), tmp_path / "once",
                   SyncOptions(camera_delay_s=0.06))
    again = convert(read_sequence_recording(tmp_path / "part"), tmp_path / "again",
                    SyncOptions(camera_delay_s=0.06))
    kept = convert(read_sequence_recording(tmp_path / "part"), tmp_path / "kept")
    stamps = {p.name: read_sequence(p).frame_stamps
              for p in (once.root, again.root, kept.root, tmp_path / "part")}
    np.testing.assert_allclose(stamps["again"], stamps["once"], atol=1e-9)
    np.testing.assert_allclose(stamps["kept"], stamps["part"], atol=1e-9)
    assert read_sequence(again.root).meta["ingest"]["camera_delay_s"] == 0.06
    assert "Nothing to correct (+30.0 ms already taken out" in advice(
        TimeOffsetResult(0.0004, 0.001, 100, 5, 0.3, 0.1, 0.1, True), 0.03)


def test_frames_too_far_apart_are_named_before_the_images_are_read() -> None:
    from calibration.time_offset import check_inputs

    t = np.arange(0.0, 60.0, 0.1)
    traj = _trajectory(t)
    with pytest.raises(TimeOffsetError, match="1.00 s apart"):
        check_inputs(np.arange(1.0, 50.0, 1.0), traj, "odometry")
    with pytest.raises(TimeOffsetError, match="another clock"):
        check_inputs(np.arange(1.0, 50.0, 0.1) + 500.0, traj, "odometry")
    check_inputs(np.arange(1.0, 50.0, 0.2), traj, "odometry")  # 5 Hz: fine


def test_a_long_recording_is_read_in_runs_of_frames(delayed: Path, tmp_path: Path) -> None:
    """An hour at 10 Hz is 36,000 frames to read: at most max_frames, in runs of 100
    consecutive ones; no rotation is measured across the gaps between runs."""
    from calibration.time_offset import camera_yaw_increments, frames_to_use

    assert np.array_equal(frames_to_use(250, 300), np.arange(250))
    use = frames_to_use(36_000)
    assert len(use) == 3000 and use[0] == 0 and use[-1] == 35_999
    assert int((np.diff(use) > 1).sum()) == 29  # 30 runs
    # Fewer than two runs' worth: two shorter runs at both ends (it was one run of 100
    # from the start, none of the rest of the recording).
    use = frames_to_use(36_000, 150)
    assert len(use) == 150 and use[0] == 0 and use[-1] == 35_999
    assert int((np.diff(use) > 1).sum()) == 1
    seq = read_sequence(delayed)
    pick = np.r_[0:3, 10:12]  # two runs
    images = [seq.frames[k].image for k in pick]
    dyaw, inliers = camera_yaw_increments(images, seq.rig.camera, seq.rig.T_base_camera,
                                          linked=np.diff(pick) == 1)
    assert np.isnan(dyaw[2]) and inliers[2] == 0  # the gap: not measured
    assert np.isfinite(dyaw[[0, 1, 3]]).all()
    out = tmp_path / "to"
    assert calibration_main(["time-offset", "--sequence", str(delayed), "--max-frames", "200",
                             "--out", str(out)]) in (0, 3)
    found = json.loads((out / "time_offset.json").read_text())
    assert found["frames"] == 200

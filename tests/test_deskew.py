"""Scans swept while moving (ROS time_increment): de-skew, storage, SLAM and simulator."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from toolkit.deskew import deskew_scan, deskew_scans, planar_motion
from toolkit.eval.trajectory import ape, synced
from toolkit.geometry import Trajectory, se2_compose, se2_to_se3
from toolkit.ingest.recording import uniform_scans
from toolkit.io.sequence import SequenceFormatError, read_scans, read_sequence, write_scans
from toolkit.sensors import LaserScan
from toolkit.sim.sensors import CameraSpec, LidarSpec
from toolkit.sim.simulate import SimConfig, simulate
from toolkit.slam2d.pipeline import run_slam

ROOM = (-4.0, 6.0, -3.5, 4.5)  # x0, x1, y0, y1 walls of a box room


def cast(origins: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """[B] ranges from ``origins`` [B, 2] along ``angles`` [B] to the room's walls."""
    d = np.stack([np.cos(angles), np.sin(angles)], -1)
    t = np.full(len(angles), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        for axis, walls in ((0, ROOM[:2]), (1, ROOM[2:])):
            for w in walls:
                tt = (w - origins[:, axis]) / d[:, axis]
                t = np.minimum(t, np.where(tt > 0, tt, np.inf))
    return t


def swept_scan(w: float, v: float, dt: float, beams: int = 360) -> tuple[LaserScan, np.ndarray,
                                                                           np.ndarray]:
    """A scan swept while driving an arc (v m/s, w rad/s), the true motion over the sweep
    and the ranges an instantaneous scan at the stamp would have."""
    inc = 2 * np.pi / beams
    a = -np.pi + np.arange(beams) * inc
    t = np.arange(beams) * dt
    th = w * t
    x = v / w * np.sin(w * t) if w else v * t
    y = v / w * (1 - np.cos(w * t)) if w else 0 * t
    scan = LaserScan(0.0, cast(np.stack([x, y], -1), a + th), -np.pi, inc, 0.05, 30.0,
                     time_increment=dt)
    return scan, np.array([x[-1], y[-1], th[-1]]), cast(np.zeros((beams, 2)), a)


def circle_ranges(px: np.ndarray, py: np.ndarray, th: np.ndarray, R: float) -> np.ndarray:
    """[B] distance from (px, py) along heading th to a circle of radius R about 0."""
    dx, dy = np.cos(th), np.sin(th)
    b = px * dx + py * dy
    return -b + np.sqrt(b * b - (px * px + py * py - R * R))


def base_at(t: np.ndarray, v0: float, acc: float, w0: float, alpha: float) -> np.ndarray:
    """[T, 3] planar base poses at times t [T] of a drive from the origin (heading 0) at
    speed v0 + acc t and turn rate w0 + alpha t, integrated finely."""
    fine = np.linspace(-0.5, 0.5, 20001)
    dt = fine[1] - fine[0]
    th = w0 * fine + 0.5 * alpha * fine**2
    v = v0 + acc * fine
    x = np.cumsum(v * np.cos(th)) * dt
    y = np.cumsum(v * np.sin(th)) * dt
    i0 = np.searchsorted(fine, 0.0)
    x, y = x - x[i0], y - y[i0]
    return np.stack([np.interp(t, fine, x), np.interp(t, fine, y), np.interp(t, fine, th)], 1)


def accelerating_sweep(drive: tuple[float, float, float, float], mount: np.ndarray,
                       start: np.ndarray, R: float, time_increment: float,
                       pose_rate_hz: float) -> tuple[LaserScan, Trajectory, np.ndarray]:
    """A 360-beam scan swept in a round room (radius R about the origin) while the base
    drives ``drive`` (v0, acc, w0, alpha: see ``base_at``) through ``start`` (x, y at the
    stamp 0, heading 0), the laser at ``mount`` (x, y, theta on the base); the base
    trajectory sampled at ``pose_rate_hz`` over -0.4..0.4 s (from the origin), and the
    ranges [B] of the scan taken at the stamp."""
    n = 360
    inc = 2 * np.pi / n
    base = base_at(np.arange(n) * time_increment, *drive)  # [B, 3]
    laser = np.array([se2_compose(b, mount) for b in base])  # [B, 3]
    ang = -np.pi + np.arange(n) * inc
    skewed = circle_ranges(start[0] + laser[:, 0], start[1] + laser[:, 1],
                           laser[:, 2] + ang, R)
    scan = LaserScan(0.0, skewed.astype(np.float32), -np.pi, inc, 0.1, 50.0,
                     time_increment=time_increment)
    stamps = np.linspace(-0.4, 0.4, round(0.8 * pose_rate_hz) + 1)
    traj = Trajectory(stamps, np.stack([se2_to_se3(*p) for p in base_at(stamps, *drive)]))
    want = circle_ranges(np.full(n, start[0] + laser[0, 0]), np.full(n, start[1]
                         + laser[0, 1]), laser[0, 2] + ang, R)
    return scan, traj, want


def skew_errors(out: LaserScan, want: np.ndarray) -> np.ndarray:
    """[V] |range - want| of the de-skewed ``out`` off its gaps' edges (a bin beside a
    gap interpolates towards nothing)."""
    gap = np.isnan(out.ranges)
    edge = gap | np.roll(gap, 1) | np.roll(gap, -1)
    assert gap.sum() < 0.05 * len(gap)
    return np.abs(out.ranges[~edge] - want[~edge])


def test_deskew_follows_the_poses_inside_the_sweep():
    """Braking from 1 m/s while a 1 rad/s turn slows (3 rad/s^2) under a 10 Hz lidar
    mounted off the base's centre: with the trajectory's 200 Hz poses inside the sweep,
    each beam's pose interpolated between them, the worst residual skew is 0.044 mm (3.5
    mm at constant velocity between the sweep's ends, as before; 75 mm not de-skewed).
    With no pose inside the sweep, the constant velocity stays, to the bit."""
    mount = np.array([0.25, -0.15, 2.0])
    args = ((1.0, -1.0, 1.0, -3.0), mount, np.array([0.6, -0.4]), 6.0, 0.1 / 360)
    scan, dense, want = accelerating_sweep(*args, pose_rate_hz=200.0)
    _, ends, _ = accelerating_sweep(*args, pose_rate_hz=10.0)  # samples at 0 and 0.1 s
    T_bl = se2_to_se3(*mount)
    along_ends = deskew_scans([scan], ends, T_bl)[0]
    along_dense = deskew_scans([scan], dense, T_bl)[0]
    assert np.abs(scan.ranges - want).max() > 0.05
    assert skew_errors(along_ends, want).max() > 2.5e-3
    assert skew_errors(along_dense, want).max() < 2e-4
    T_wl = ends.interpolate(np.array([0.0, scan.sweep_s])).poses @ T_bl
    same = deskew_scan(scan, planar_motion(T_wl[0], T_wl[1]))
    np.testing.assert_array_equal(along_ends.ranges, same.ranges)
    with pytest.raises(ValueError, match=r"\[360, 3\]"):
        deskew_scan(scan, np.zeros((359, 3)))


@pytest.mark.parametrize("w, v, dt", [(1.0, 0.5, 1 / 3600), (-1.5, 0.3, 1 / 3600),
                                      (1.0, 0.5, -1 / 3600)])
def test_deskew_recovers_the_scan_at_the_stamp(w, v, dt):
    scan, motion, truth = swept_scan(w, v, dt)
    assert scan.beam_times()[-1] == pytest.approx(scan.sweep_s) == pytest.approx(359 * dt)
    skewed = np.abs(scan.ranges - truth)
    assert np.nanmax(skewed) > 0.25  # the far walls moved by decimetres
    out = deskew_scan(scan, motion)
    err = np.abs(out.ranges - truth)
    assert out.time_increment == 0 and len(out) == len(scan)
    assert out.angle_min == scan.angle_min and out.angle_increment == scan.angle_increment
    # A turn with the beams covers more than 360 deg: every bin gets a point (the ends
    # wrap); a turn against them leaves a gap of the angle turned, which nothing saw.
    gap = int(np.ceil(max(-motion[2], 0) / scan.angle_increment))
    assert len(out) - gap - 1 <= np.isfinite(out.ranges).sum()
    assert np.nanmedian(err) < 1e-3 and np.nanpercentile(err, 95) < 5e-3
    assert np.nanmax(err) < 0.06  # interpolation across the room's corners


def test_deskew_keeps_codes_and_moves_intensities():
    scan, motion, _ = swept_scan(1.0, 0.5, 1 / 3600)
    r = scan.ranges.copy()
    r[100:110] = np.inf  # no return: stays a no-return where no point lands
    inten = np.arange(len(r), dtype=np.float32)
    scan = replace(scan, ranges=r, intensities=inten)
    out = deskew_scan(scan, motion)
    assert np.isinf(out.ranges[102:108]).all()
    # Intensities follow their point: the bin a beam's point lands in carries it.
    assert np.all(np.abs(out.intensities[200:210] - np.arange(200, 210)) <= 6)
    # Nothing to do: same ranges, timing cleared.
    same = deskew_scan(scan, np.zeros(3))
    assert same.time_increment == 0 and np.array_equal(same.ranges, scan.ranges,
                                                       equal_nan=True)


def test_range_max_readings_stay_no_returns():
    """CARMEN and many drivers write no-return as exactly range_max: moved like returns,
    half of them landed inside the limit and the SLAM saw a wall there."""
    scan, motion, _ = swept_scan(1.0, 0.5, 1 / 3600)
    r = scan.ranges.copy()
    r[50:150] = 12.0
    scan = replace(scan, ranges=r, range_max=12.0)
    out = deskew_scan(scan, motion)
    assert np.all((out.ranges[55:145] == 12.0) | np.isnan(out.ranges[55:145]))
    moved = np.abs(out.ranges - r) > 1e-4
    assert moved[200:300].any()  # real returns still move
    # Nor are they points: the fusion's lidar pixels and the carving read valid_mask
    # (15 phantom points at a corridor scan's 8 m reach before).
    assert not scan.valid_mask()[50:150].any() and scan.valid_mask()[200:300].all()
    assert len(scan.points()) == int(np.isfinite(r).sum()) - 100


def test_deskew_scans_along_a_trajectory_and_only_covered():
    scan, motion, truth = swept_scan(0.8, 0.4, 1 / 3600)
    t = np.linspace(-1.0, 1.0, 201)
    w, v = 0.8, 0.4
    traj = Trajectory(t, np.stack([se2_to_se3(v / w * np.sin(w * s), v / w * (1 - np.cos(w * s)),
                                               w * s) for s in t]))
    out = deskew_scans([scan], traj, np.eye(4))[0]
    assert np.median(np.abs(out.ranges - truth)) < 2e-3
    np.testing.assert_allclose(planar_motion(traj.poses[100], traj.interpolate(
        np.array([scan.sweep_s])).poses[0]), motion, atol=1e-4)
    late = replace(scan, stamp=0.95)  # sweep ends after the trajectory
    assert deskew_scans([late], traj, np.eye(4), covered_only=True)[0] is late
    # A sweep in a gap of the trajectory (odometry silent for 1.6 s) is not de-skewed with
    # the straight line across it either; the ones beside the gap are.
    holed = traj.slice((t < -0.8) | (t > 0.8))
    assert deskew_scans([scan], holed, np.eye(4), covered_only=True)[0] is scan
    early = replace(scan, stamp=-0.95)
    assert deskew_scans([early], holed, np.eye(4), covered_only=True)[0] is not early
    # A trajectory stamped at the scans ends at the last scan's first beam: its sweep
    # takes the motion of the trajectory's last stretch as long as the sweep (clipped to
    # the end pose it got none and stayed skewed), half past the end as well.
    for end in (0.0, scan.sweep_s / 2):
        ending = traj.slice(t <= end + 1e-9)
        out = deskew_scans([scan], ending, np.eye(4))[0]
        assert np.median(np.abs(out.ranges - truth)) < 2e-3, end


def test_scan_files_store_beam_timing(tmp_path: Path):
    scan, _, _ = swept_scan(1.0, 0.5, 1 / 3600)
    write_scans(tmp_path / "scans.npz", [scan, replace(scan, stamp=0.1)])
    back = read_scans(tmp_path / "scans.npz")
    assert [s.time_increment for s in back] == [1 / 3600] * 2
    # Files without it (written before it existed, or instantaneous scans): 0.
    write_scans(tmp_path / "plain.npz", [replace(scan, time_increment=0.0)])
    with np.load(tmp_path / "plain.npz") as d:
        assert "time_increment" not in d.files
    assert read_scans(tmp_path / "plain.npz")[0].time_increment == 0
    with np.load(tmp_path / "scans.npz") as d:
        arrays = {k: d[k] for k in d.files}
    arrays["time_increment"] = np.array([np.nan, 0.0])
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(SequenceFormatError, match="time_increment"):
        read_scans(tmp_path / "bad.npz")


def test_resampled_scans_keep_their_timing():
    scan, _, _ = swept_scan(1.0, 0.5, 1 / 3600)
    coarse = LaserScan(0.2, np.ones(180, np.float32), -np.pi, 2 * np.pi / 180,
                       time_increment=2 / 3600)
    out, changed = uniform_scans([scan, replace(scan, stamp=0.1), coarse])
    assert changed == 1
    assert out[2].time_increment == pytest.approx(1 / 3600)  # per target beam


@pytest.fixture(scope="module")
def swept_sequences(tmp_path_factory) -> tuple[Path, Path]:
    """The same 20 s drive with an instantaneous and a sweeping 5 Hz lidar."""
    root = tmp_path_factory.mktemp("swept")
    cam = CameraSpec(width=80, height=60, fx=65.0, fy=65.0, rate_hz=1.0)
    out = []
    for sweep in (False, True):
        cfg = SimConfig(seed=0, n_people=0, duration_s=20.0, n_heldout=0, camera=cam,
                        lidar=LidarSpec(sweep=sweep, rate_hz=5.0))
        simulate(cfg, root / f"sweep{int(sweep)}")
        out.append(root / f"sweep{int(sweep)}")
    return out[0], out[1]


def test_simulated_sweep_deskews_to_the_instantaneous_scans(swept_sequences):
    still, swept = (read_sequence(p) for p in swept_sequences)
    assert swept.scans[3].time_increment == pytest.approx(1 / (360 * 5.0))
    assert still.scans[3].time_increment == 0
    fixed = deskew_scans(swept.scans, swept.groundtruth.poses_base, swept.rig.T_base_laser)

    # The swept recording ends with the last sweep that ends on the drive.
    assert 0 < len(still.scans) - len(swept.scans) <= 1
    assert [s.stamp for s in swept.scans] == [s.stamp for s in still.scans[:len(swept.scans)]]

    def median_error(scans):
        e = [np.nanmedian(np.abs(a.ranges - b.ranges))
             for a, b in zip(still.scans[:len(scans)], scans, strict=True)]
        return float(np.nanmedian(e))

    # Same seed, same noise draws: what differs is when each beam fired.
    assert median_error(swept.scans) > 0.01
    assert median_error(fixed) < 0.3 * median_error(swept.scans)


@pytest.mark.parametrize("odometry", [True, False])
def test_slam_deskews_swept_scans(swept_sequences, odometry):
    seq = read_sequence(swept_sequences[1])
    odo = seq.odometry if odometry else None
    gt = seq.groundtruth.poses_base

    def errors(scans):
        res = run_slam(scans, odo, seq.rig.T_base_laser)
        est, ref = synced(res.trajectory, gt)
        return ape(est, ref)[0].rmse, ape(est, ref, "se3", "rot")[0].rmse, res.metrics

    t_on, r_on, m = errors(seq.scans)
    t_off, r_off, _ = errors([replace(s, time_increment=0.0) for s in seq.scans])
    # With odometry run_slam de-skews with it; scan-only the SLAM uses its own velocity.
    assert (m["scans_deskewed"] < 5) if odometry else (m["scans_deskewed"] > 90)
    # The ones odometry de-skewed before matching are counted too (the metric read 0).
    assert (m["scans_deskewed_odometry"] > 90) if odometry else (
        m["scans_deskewed_odometry"] == 0)
    assert t_on < 0.6 * t_off and r_on < 0.4 * r_off

"""Exposure gains solved over the frames' overlaps: known gains recovered from synthetic
observations with outliers, the edges' medians, the image correction, the gains file, and
the fuse stage on a simulated auto-exposure drive (map colours and the tsdf stage)."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from recipe_helpers import SequenceFolder, run_stages  # the tests folder is on sys.path

from toolkit.fusion.exposure import (
    ExposureObservations,
    ExposureOptions,
    GainEdges,
    cell_keys,
    cell_observations,
    corrected_image,
    gain_edges,
    gain_error,
    gains_from_neighbours,
    read_exposure_gains,
    solve_gains,
    spread_gains,
    write_exposure_gains,
)


def _corridor_drive(true_gain: np.ndarray, outlier_fraction: float, seed: int = 0) -> (
        ExposureObservations):
    """A textured wall 20 m long seen by a camera driving along it and back, each frame's
    colours at its gain; in each frame ``outlier_fraction`` of the 10 cm cells it sees are
    0.5-2x darker or brighter (a person, a shadow, a reflection)."""
    rng = np.random.default_rng(seed)
    n = 150_000
    pts = np.c_[rng.uniform(0, 20, n), np.zeros(n), rng.uniform(0, 2.5, n)]  # [N, 3]
    albedo = 60 + 120 * (0.5 + 0.5 * np.sin(3 * pts[:, :1] + 5 * pts[:, 2:])) * np.array(
        [1.0, 0.85, 0.7])  # [N, 3]
    f_count = len(true_gain)
    pos = np.r_[np.linspace(1, 19, f_count // 2), np.linspace(19, 1, f_count - f_count // 2)]
    obs, opts = ExposureObservations(), ExposureOptions()
    for f in range(f_count):
        sel = rng.choice(np.flatnonzero(np.abs(pts[:, 0] - pos[f]) < 1.5), 3000, replace=False)
        col = albedo[sel] * true_gain[f] + rng.normal(0, 2, (len(sel), 3))
        cell = np.floor(pts[sel][:, [0, 2]] / 0.1).astype(int) @ np.array([1000, 1])
        uc, inv = np.unique(cell, return_inverse=True)
        factor = np.where(rng.random(len(uc)) < outlier_fraction,
                          np.exp(rng.uniform(-0.7, 0.7, len(uc))), 1.0)
        col *= factor[inv][:, None]
        keys, log_rgb, _ = cell_observations(pts[sel], np.clip(col, 0, 255).astype(np.uint8),
                                             np.array([pos[f], -2.0, 1.0]), opts)
        obs.add(f, keys, log_rgb)
    return obs


def test_known_gains_are_recovered_with_outliers() -> None:
    t = np.linspace(0, 1, 200)
    true = np.exp(0.25 * np.sin(7 * t) + 0.08 * np.sin(31 * t))  # spread ~18 %
    opts = ExposureOptions()
    edges = gain_edges(*_corridor_drive(true, outlier_fraction=0.3).arrays(), opts)
    sol = solve_gains(edges, len(true), opts)
    err = gain_error(sol.gains, true)
    assert err["gain_true_spread_pct"] > 15
    assert err["gain_error_rms_pct"] < 0.5 and err["gain_error_max_pct"] < 1.5
    assert sol.frames_linked == len(true)
    # One common factor per channel: the geometric mean is 1, and the channels agree.
    assert np.exp(np.log(sol.gains).mean(0)) == pytest.approx(1.0, abs=1e-9)
    assert np.ptp(np.log(sol.gains), axis=1).max() < 0.02


def test_a_slow_drift_over_a_long_drive_is_kept() -> None:
    # 5000 frames, each sharing surfaces with the next 8 only, the exposure drifting
    # slowly by +-30 % (a ridge on every frame had flattened it to two thirds).
    n = 5000
    true = np.linspace(-0.3, 0.3, n)
    a = np.concatenate([np.arange(n - k) for k in (1, 2, 4, 8)])
    b = np.concatenate([np.arange(k, n) for k in (1, 2, 4, 8)])
    edges = GainEdges(a, b, np.repeat((true[a] - true[b])[:, None], 3, 1),
                      np.full(len(a), 200))
    sol = solve_gains(edges, n, ExposureOptions())
    assert gain_error(sol.gains, np.exp(true))["gain_error_rms_pct"] < 0.01
    assert sol.groups == 1


def test_groups_that_share_no_surface_are_counted() -> None:
    # Frames 0-4 and 5-9 each overlap among themselves, never across.
    a, b = np.array([0, 1, 2, 3, 5, 6, 7, 8]), np.array([1, 2, 3, 4, 6, 7, 8, 9])
    sol = solve_gains(GainEdges(a, b, np.zeros((8, 3)), np.full(8, 50)), 10, ExposureOptions())
    assert sol.frames_linked == 10 and sol.groups == 2


def test_a_frame_seeing_nothing_shared_follows_its_neighbours() -> None:
    true = np.exp(np.linspace(-0.1, 0.1, 60))
    obs = _corridor_drive(true, 0.0)
    # Frame 30 saw only surfaces no other frame saw.
    obs.key[30] = obs.key[30] + (1 << 60)
    opts = ExposureOptions()
    sol = solve_gains(gain_edges(*obs.arrays(), opts), len(true), opts)
    assert sol.frames_linked == len(true) - 1
    g = np.log(sol.gains.mean(1))
    assert g[30] == pytest.approx(0.5 * (g[29] + g[31]), abs=0.005)


def test_a_long_drive_keeps_fewer_cells_then_fewer_frames() -> None:
    opts = ExposureOptions(max_observations=100_000, min_cells=200)
    assert opts.plan(40) == (1, 2500)
    assert opts.plan(250) == (1, 400)
    assert opts.plan(2000) == (4, 200)  # 500 frames solved, 200 cells each
    with pytest.raises(ValueError, match="min_cells"):
        ExposureOptions(min_cells=10)
    # Frames between the solved ones get log-linear gains; the first and last are solved.
    at = np.array([0, 4, 8, 9])
    solved = np.exp(np.array([[0.0] * 3, [0.4] * 3, [0.0] * 3, [0.1] * 3]))
    g = spread_gains(solved, at, 10)
    assert np.log(g[:, 0]) == pytest.approx([0, .1, .2, .3, .4, .3, .2, .1, 0, .1])


def test_a_cell_budget_keeps_the_same_cells_in_overlapping_frames() -> None:
    rng = np.random.default_rng(1)
    pts = rng.uniform(0, 3, (40_000, 3))
    col = np.full((len(pts), 3), 100, np.uint8)
    opts = ExposureOptions(min_points=1)
    a, _, _ = cell_observations(pts[:30_000], col[:30_000], np.array([1.5, -5, 1]), opts, 300)
    b, _, _ = cell_observations(pts[10_000:], col[10_000:], np.array([1.5, -5, 1]), opts, 300)
    assert len(a) == len(b) == 300
    # Of the ~18 000 cells each frame has, the 300 lowest hashes mostly agree (300 picked
    # at random would share about 5).
    assert len(np.intersect1d(a, b)) > 200


def test_edges_hold_the_median_difference_of_the_common_cells() -> None:
    # Frames 0 and 1 share cells 10..14: differences 0.1 in four of them, 0.9 in one.
    frames = np.r_[np.zeros(5), np.ones(5), np.full(2, 2)].astype(np.int32)
    keys = np.r_[10:15, 10:15, 99, 98].astype(np.int64)
    log0 = np.full((5, 3), 4.0)
    log1 = log0 - np.array([0.1, 0.1, 0.1, 0.9, 0.1])[:, None]
    e = gain_edges(frames, keys, np.r_[log0, log1, np.zeros((2, 3))].astype(np.float32),
                   ExposureOptions(min_common=3))
    assert e.a.tolist() == [0] and e.b.tolist() == [1] and e.common.tolist() == [5]
    assert e.diff[0] == pytest.approx([0.1] * 3, abs=1e-6)


def test_edge_medians_match_a_two_key_sort_for_any_difference() -> None:
    # Exposure jumps of up to 30x (log differences beyond 3), many pairs and ties.
    rng = np.random.default_rng(3)
    n = 40_000
    frames = rng.integers(0, 300, n).astype(np.int32)
    keys = rng.integers(0, 2000, n).astype(np.int64)
    log_rgb = np.round(rng.uniform(2.1, 5.5, (n, 3)), 2).astype(np.float32)
    opts = ExposureOptions(min_common=1)
    e = gain_edges(frames, keys, log_rgb, opts)
    # The reference: every pair's differences gathered and their median taken directly.
    order = np.lexsort((frames, keys))
    k, f, c = keys[order], frames[order], log_rgb[order].astype(np.float64)
    diffs: dict[tuple[int, int], list[np.ndarray]] = {}
    for off in opts.offsets:
        same = np.flatnonzero(k[off:] == k[:-off])
        for t in same:
            diffs.setdefault((int(f[t]), int(f[t + off])), []).append(c[t] - c[t + off])
    assert len(e.a) == len(diffs) and np.abs(e.diff).max() > 3
    for a, b, d in zip(e.a[:500], e.b[:500], e.diff[:500], strict=True):
        assert d == pytest.approx(np.median(np.array(diffs[(int(a), int(b))]), axis=0),
                                  abs=1e-6)
    # A non-finite observation is left out, not sorted to the end where it shifted others.
    bad = log_rgb.copy()
    bad[0] = np.nan
    e2 = gain_edges(frames, keys, bad, opts)
    assert np.isfinite(e2.diff).all()


def test_cells_with_a_dark_or_clipped_pixel_are_dropped_whole() -> None:
    pts = np.array([[0.01, 0.01, 0.01]] * 6 + [[0.51, 0.01, 0.01]] * 4
                   + [[1.01, 0.01, 0.01]] * 5, np.float32)
    col = np.array([[100, 50, 25]] * 4 + [[255, 50, 25], [90, 50, 25]]
                   + [[80, 80, 80]] * 3 + [[80, 3, 80]] + [[60, 70, 80]] * 5, np.uint8)
    keys, log_rgb, count = cell_observations(pts, col, np.array([0.0, -3.0, 1.0]),
                                             ExposureOptions(min_points=4))
    # One clipped and one dark pixel drop their cells; the third is whole.
    assert len(keys) == 1 and count.tolist() == [5]
    assert np.exp(log_rgb[0]) == pytest.approx([60, 70, 80], rel=1e-5)


def test_gains_are_unbiased_on_mostly_white_walls() -> None:
    """40 frames at gains 0.7-1.3 all seeing 300 textured cells (+-20 % per pixel), 70 %
    of them white paint (base 200-225) that clips in the bright frames. With the clipped
    pixels dropped one by one a cell's mean in a bright frame lost its brightest pixels,
    compressing the gains: 0.88 % RMS / 2.3 % max off. Whole cells: 0.18 / 0.35 %."""
    rng = np.random.default_rng(0)
    opts = ExposureOptions()
    n_cells, per = 300, 16
    cx = np.repeat(np.arange(n_cells), per)  # [N] cell of each pixel
    pts = np.c_[np.full(len(cx), 3.0),
                (cx % 30) * 0.1 + 0.05 + rng.uniform(-0.04, 0.04, len(cx)),
                (cx // 30) * 0.1 + 0.05 + rng.uniform(-0.04, 0.04, len(cx))]  # [N, 3]
    base = np.where(np.arange(n_cells) % 10 < 7, rng.uniform(200, 225, n_cells),
                    rng.uniform(60, 180, n_cells))
    albedo = base[cx][:, None] * rng.uniform(0.8, 1.2, (len(cx), 3))  # [N, 3]
    true = np.exp(np.linspace(np.log(0.7), np.log(1.3), 40))[rng.permutation(40)]
    obs = ExposureObservations()
    for f, g in enumerate(true):
        col = np.clip(np.rint(albedo * g), 0, 255).astype(np.uint8)
        obs.add(f, *cell_observations(pts, col, np.zeros(3), opts)[:2])
    sol = solve_gains(gain_edges(*obs.arrays(), opts), len(true), opts)
    err = gain_error(sol.gains, true)
    assert err["gain_error_rms_pct"] < 0.25 and err["gain_error_max_pct"] < 0.6


def test_the_two_sides_of_a_thin_wall_are_different_cells() -> None:
    # Both faces of a 4 cm wall in one 10 cm cell, seen from the two rooms.
    front = np.array([[0.05, 0.01, 1.01]] * 5, np.float32)
    back = front + np.array([0.0, 0.04, 0.0], np.float32)
    col = np.full((5, 3), 120, np.uint8)
    opts = ExposureOptions()
    k_front, _, _ = cell_observations(front, col, np.array([0.0, -2.0, 1.0]), opts)
    k_back, _, _ = cell_observations(back, col, np.array([0.5, 2.0, 1.0]), opts)
    k_near, _, _ = cell_observations(front, col, np.array([-0.2, -1.0, 0.5]), opts)
    assert len(k_front) == len(k_back) == 1
    assert k_front[0] != k_back[0] and k_front[0] == k_near[0]
    with pytest.raises(ValueError, match="cannot be keyed"):
        cell_keys(np.array([[1e6, 0.0, 0.0]]), np.zeros(3), 0.1)


def test_cell_observations_reusing_a_key_table_match_a_sort_of_the_keys() -> None:
    """Frames grouped through one key table kept from frame to frame give the cells, means
    and counts that sorting each frame's cell_keys gives (a dark pixel spoils its cell)."""
    from toolkit.fusion.voxel_map import KeyTable

    rng = np.random.default_rng(8)
    opts = ExposureOptions(min_points=2)
    table = KeyTable()
    for f in range(3):
        pts = rng.uniform(-2, 2, (4000, 3)).astype(np.float32) + f
        col = rng.integers(0, 256, (4000, 3)).astype(np.uint8)
        col[rng.random(4000) < 0.9] |= 16  # most pixels off the dark end
        origin = np.array([0.3 * f, -1.0, 0.5])
        keys, log_rgb, count = cell_observations(pts, col, origin, opts, table=table)
        uk, inv, cnt = np.unique(cell_keys(pts, origin, opts.cell_m), return_inverse=True,
                                 return_counts=True)
        ok = ((col > opts.dark) & (col < opts.bright)).all(1)
        good = (cnt >= opts.min_points) & (np.bincount(inv, ~ok, len(uk)) == 0)
        mean = np.stack([np.bincount(inv, col[:, k].astype(float), len(uk)) for k in range(3)],
                        1) / cnt[:, None]
        assert 0 < good.sum() < len(uk)
        np.testing.assert_array_equal(keys, uk[good])
        np.testing.assert_array_equal(count, cnt[good])
        np.testing.assert_array_equal(log_rgb, np.log(mean[good]).astype(np.float32))


def test_corrected_image_divides_each_channel() -> None:
    rgb = np.array([[[100, 200, 50], [255, 0, 10]]], np.uint8)
    out = corrected_image(rgb, np.array([2.0, 0.5, 1.0]))
    assert out.dtype == np.uint8
    assert out.tolist() == [[[50, 255, 50], [128, 0, 10]]]
    with pytest.raises(ValueError, match="uint8"):
        corrected_image(rgb.astype(np.float32), np.ones(3))


def test_gains_from_neighbours_ignore_the_wanted_frames_own_gains() -> None:
    """Frames 3 and 7 wanted, known 2, 4, 6, 9 (any order): 3 between 2 (1.0) and 4 (4.0)
    is 2.0 (log-linear), 7 a third of the way from 6 (1.0) to 9 (8.0) is 2.0 in every
    channel; a frame before the first known one takes its gain; the wanted frames' own
    entries (99) are never read."""
    gains = {i: np.full(3, 99.0) for i in range(12)}
    gains |= {2: np.full(3, 1.0), 4: np.full(3, 4.0), 6: np.array([1.0, 2.0, 0.5]),
              9: np.array([8.0, 2.0, 0.5])}
    got = gains_from_neighbours(gains, [9, 2, 6, 4], [3, 7, 0])
    assert sorted(got) == [0, 3, 7]
    np.testing.assert_allclose(got[3], [2.0, 2.0, 2.0])
    np.testing.assert_allclose(got[7], [2.0, 2.0, 0.5])
    np.testing.assert_allclose(got[0], [1.0, 1.0, 1.0])
    assert gains_from_neighbours(gains, [2], []) == {}
    with pytest.raises(ValueError, match="no known frames"):
        gains_from_neighbours(gains, [], [3])


def test_gains_file_round_trip_and_bad_rows(tmp_path: Path) -> None:
    p = tmp_path / "exposure_gains.csv"
    gains = np.array([[1.0, 1.1, 0.9], [0.8, 0.8, 0.8]])
    write_exposure_gains(p, [(3, 10.0), (7, 10.5)], gains)
    back = read_exposure_gains(p)
    assert sorted(back) == [3, 7] and back[7] == pytest.approx(gains[1])
    p.write_text("index,stamp,gain_r,gain_g,gain_b\n3,10.0,1.0,-1.0,1.0\n")
    with pytest.raises(ValueError, match="line 2: gains must be positive"):
        read_exposure_gains(p)
    p.write_text("index,stamp,gain_r,gain_g,gain_b\n3,10.0,inf,1.0,1.0\n")
    with pytest.raises(ValueError, match="positive and finite"):
        read_exposure_gains(p)
    p.write_text("index,stamp,gain\n3,10.0,1.0\n")
    with pytest.raises(ValueError, match="gain_r"):
        read_exposure_gains(p)


def test_fuse_solves_a_simulated_auto_exposure_and_tsdf_uses_it(tmp_path: Path) -> None:
    sim = pytest.importorskip("toolkit.sim.simulate")
    from toolkit.baselines.stage import TSDFStage
    from toolkit.depth.stage import DepthStage
    from toolkit.fusion.stage import FuseStage
    from toolkit.sim.sensors import CameraSpec

    cam = CameraSpec(width=160, height=120, fx=131.25, fy=131.25, auto_exposure=True,
                     exposure_target=150.0, exposure_speed=0.5)
    root = sim.simulate(sim.SimConfig(seed=0, n_people=0, duration_s=8.0, n_heldout=0,
                                      camera=cam), tmp_path / "sim").root
    fuse = {"stage": "fuse", "exposure": "gain", "mesh_eval_frames": 0, "stride": 1,
            "exposure_stride": 1, "checkpoint_every_s": 0}
    res = run_stages(tmp_path, [
        {"stage": "t_sequence", "path": str(root)},
        {"stage": "depth", "backend": "simulated", "simulated": {"seed": 1}},
        {"stage": "fuse", "id": "fuse_plain", "mesh_eval_frames": 0, "stride": 1,
         "exposure": "none"},
        fuse,  # last: the tsdf stage takes the latest fused artifact
        {"stage": "tsdf", "views": 0, "geometry": False},
    ], {"t_sequence": SequenceFolder, "depth": DepthStage, "fuse": FuseStage,
        "tsdf": TSDFStage})
    assert res.ok, res.error
    m = res.metrics["fuse"]
    assert m["exposure_gain_true_spread_pct"] > 3
    # measured 0.12 % RMS against a spread of 4.5 %
    assert m["exposure_gain_error_rms_pct"] < 0.1 * m["exposure_gain_true_spread_pct"]
    assert m["exposure_frames_linked"] == m["frames_fused"]
    assert "exposure_edges" not in res.metrics["fuse_plain"]
    run = tmp_path / "run"
    assert m["checkpoints_saved"] == 0 and m["exposure_groups"] == 1
    # Every frame of the sequence has a gain, the frames fuse did not use interpolated.
    gains = read_exposure_gains(run / "fuse" / "exposure_gains.csv")
    assert sorted(gains) == list(range(m["frames"]))
    report = (run / "report.md").read_text()
    assert "(fuse/exposure.png)" in report and (run / "fuse" / "exposure.png").exists()
    assert "exposure gains the `fuse` stage solved" in report  # the tsdf stage's note
    # The same drive without auto exposure gives the reference colours (nearly the same
    # voxels: the same poses, scans and ground-truth depth).
    ref_root = sim.simulate(sim.SimConfig(seed=0, n_people=0, duration_s=8.0, n_heldout=0,
                                          camera=replace(cam, auto_exposure=False)),
                            tmp_path / "sim_ref").root
    (tmp_path / "ref").mkdir()
    ref = run_stages(tmp_path / "ref", [
        {"stage": "t_sequence", "path": str(ref_root)},
        {"stage": "depth", "backend": "simulated", "simulated": {"seed": 1}},
        {"stage": "fuse", "mesh_eval_frames": 0, "stride": 1, "exposure": "none"},
    ], {"t_sequence": SequenceFolder, "depth": DepthStage, "fuse": FuseStage})
    assert ref.ok, ref.error
    from toolkit.fusion.voxel_map import read_map_ply, voxel_keys

    def brightness(path: Path) -> dict[int, float]:
        pts, col = read_map_ply(path)
        return dict(zip(voxel_keys(pts, 0.02).tolist(), col.astype(float).mean(1).tolist(),
                        strict=True))

    want = brightness(tmp_path / "ref" / "run" / "fuse" / "map.ply")
    spread = {}
    for name in ("fuse", "fuse_plain"):
        got = brightness(run / name / "map.ply")
        common = [k for k in got if k in want and 10 < want[k] < 240]
        assert len(common) > 0.7 * len(got)
        r = np.log([got[k] / want[k] for k in common])
        # Median absolute deviation: the simulated depth's noise depends on the image
        # texture, so a few voxels at texture edges mix other colours in one map.
        spread[name] = float(np.median(np.abs(r - np.median(r))))
    assert spread["fuse"] < 0.4 * spread["fuse_plain"], spread  # measured 0.45 vs 1.79 %


def test_tsdf_refuses_gains_that_miss_frames(tmp_path: Path) -> None:
    from recipe_helpers import SplatInputs

    from toolkit.baselines.stage import TSDFStage

    stages = [{"stage": "t_splat_inputs", "exposure_gain": 2.0, "exposure_gain_frames": 6},
              {"stage": "tsdf", "views": 0, "geometry": False}]
    register = {"t_splat_inputs": SplatInputs, "tsdf": TSDFStage}
    res = run_stages(tmp_path, stages, register)
    assert not res.ok and "has no gain for 6 of the 12 frames" in str(res.error)
    assert "exposure: none" in str(res.error)
    (tmp_path / "none").mkdir()
    stages[1]["exposure"] = "none"
    assert run_stages(tmp_path / "none", stages, register).ok

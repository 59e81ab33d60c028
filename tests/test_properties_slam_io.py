"""Property tests, round 4: the SLAM back end (pose graph, branch-and-bound search), the
stamp matching of ingest, file round trips and the calibration helpers that the earlier
rounds (test_properties.py, test_properties_fusion.py) did not reach. Known answers come
from brute force or from construction; example counts keep each test to a second or two."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from calibration.time_offset import frames_to_use
from toolkit.geometry import se2_between, se2_compose, wrap_angle
from toolkit.ingest.sync import longest_increasing, match_nearest
from toolkit.io.carmen import CarmenFormatError, read_g2o
from toolkit.io.sequence import read_scans, write_scans
from toolkit.sensors import LaserScan
from toolkit.slam2d import LidarSlam2D, Slam2DConfig
from toolkit.slam2d.config import ScanOptions
from toolkit.slam2d.grid import lattice_cells
from toolkit.slam2d.matcher import GridPyramid, correlative_search
from toolkit.slam2d.pose_graph import PoseGraph2D

seeds = st.integers(0, 2**31 - 1)
# tmp_path is shared by a test's examples: every example writes the same names afresh.
quick = settings(max_examples=25, deadline=None,
                 suppress_health_check=[HealthCheck.function_scoped_fixture])
many = settings(max_examples=150, deadline=None)


# ---------------------------------------------------------------------------- pose graph


def _graph(poses: np.ndarray, edges: list[tuple]) -> PoseGraph2D:
    g = PoseGraph2D()
    for p in poses:
        g.add_vertex(p)
    for e in edges:
        g.add_edge(*e[:5], robust=e[5] if len(e) > 5 else "none")
    return g


def _assert_same_poses(a: np.ndarray, b: np.ndarray, atol: float) -> None:
    np.testing.assert_allclose(a[:, :2], b[:, :2], atol=atol)
    assert np.abs(wrap_angle(a[:, 2] - b[:, 2])).max() < atol


@quick
@given(seeds, st.integers(2, 10), st.booleans())
def test_pose_graph_returns_to_a_consistent_graph_across_the_angle_wrap(
        seed: int, n: int, near_pi: bool) -> None:
    """Edges measured from the true poses: perturbed, the solve returns to them, headings
    within a milliradian of +-pi included (each edge's angle error is wrapped)."""
    rng = np.random.default_rng(seed)
    X = np.c_[rng.normal(0, 3, (n, 2)), rng.uniform(-np.pi, np.pi, n)]  # [V, 3]
    if near_pi:
        X[:, 2] = wrap_angle(np.pi + rng.uniform(-1e-3, 1e-3, n))
    edges = [(a, b, se2_between(X[a], X[b]), rng.uniform(0.5, 5), rng.uniform(0.5, 5),
              str(rng.choice(["none", "huber", "cauchy"])))
             for a in range(n) for b in range(a + 1, n) if b == a + 1 or rng.random() < 0.5]
    start = X.copy()
    start[1:] += rng.normal(0, 0.05, (n - 1, 3))
    g = _graph(start, edges)
    g.optimize(max_iterations=50, tolerance=1e-14)
    _assert_same_poses(g.poses, X, 1e-5)


@quick
@given(seeds, st.integers(3, 9))
def test_pose_graph_solution_moves_with_a_rigid_motion_of_its_input(seed: int, n: int) -> None:
    """Noisy edges: the first vertex holds the gauge, so moving every initial pose by one
    rigid motion moves the optimum by it and changes nothing else."""
    rng = np.random.default_rng(seed)
    X = np.c_[rng.normal(0, 3, (n, 2)), rng.uniform(-np.pi, np.pi, n)]  # [V, 3]
    edges = [(a, b, se2_between(X[a], X[b]) + rng.normal(0, 0.1, 3), rng.uniform(0.5, 5),
              rng.uniform(0.5, 5))
             for a in range(n) for b in range(a + 1, n) if b == a + 1 or rng.random() < 0.5]
    start = X + rng.normal(0, 0.1, X.shape)
    T = np.r_[rng.normal(0, 10, 2), rng.uniform(-np.pi, np.pi)]  # [3]
    out = []
    for init in (start, se2_compose(T[None], start)):
        g = _graph(init, edges)
        g.optimize(max_iterations=100, tolerance=1e-14)
        out.append(g.poses.copy())
    _assert_same_poses(se2_compose(T[None], out[0]), out[1], 1e-4)


# ---------------------------------------------------------------------------- matcher


@settings(max_examples=40, deadline=None)
@given(seeds, st.integers(0, 3), st.integers(1, 5), st.booleans(),
       st.floats(-np.pi - 0.2, np.pi + 0.2))
def test_branch_and_bound_finds_the_brute_force_best_pose(seed: int, depth: int, w: int,
                                                         prior: bool, th0: float) -> None:
    """Without a candidate cap the search is exact: its score is the best of every pose of
    the window (translations out to its edges, headings across +-pi), with and without
    the motion prior."""
    rng = np.random.default_rng(seed)
    H, W = (int(v) for v in rng.integers(5, 25, 2))
    res = 0.05
    prob = rng.uniform(0.1, 0.9, (H, W)).astype(np.float32)  # [H, W]
    origin = rng.normal(0, 1, 2)
    pyr = GridPyramid(prob, origin, res, depth, 0.1, w)
    pts = rng.normal(0, 0.4, (int(rng.integers(1, 20)), 2))  # [N, 2]
    x0 = origin + rng.uniform(0, 1, 2) * [W * res, H * res]
    lin, ang, step = w * res * rng.uniform(0.3, 1.0), rng.uniform(0, 0.2), 0.05
    tc, rc = (rng.uniform(0, 5), rng.uniform(0, 5)) if prior else (0.0, 0.0)
    found = correlative_search(pyr, pts, np.r_[x0, th0], lin, ang, step, min_score=0.0,
                               translation_cost=tc, rotation_cost=rc, max_candidates=10**9)
    wc = min(int(np.ceil(lin / res)), w)
    n_ang = int(np.ceil(ang / step)) if ang > 0 else 0
    fine = pyr.levels[0].reshape(pyr.shape)
    best = 0.0
    for k in range(-n_ang, n_ang + 1):
        c, s = np.cos(th0 + k * step), np.sin(th0 + k * step)
        at = np.c_[c * pts[:, 0] - s * pts[:, 1], s * pts[:, 0] + c * pts[:, 1]] + x0
        for ox in range(-wc, wc + 1):
            for oy in range(-wc, wc + 1):
                cell = lattice_cells(at + [ox * res, oy * res] - pyr.origin, res)
                # Off the padded grid: unknown space, as the padding reads.
                cell = np.clip(cell, 0, [pyr.shape[1] - 1, pyr.shape[0] - 1])
                v = fine[cell[:, 1], cell[:, 0]].astype(np.int64).sum() / (255.0 * len(pts))
                if prior:
                    v *= np.exp(-(tc * np.hypot(ox, oy) * res + rc * abs(k) * step) ** 2)
                best = max(best, v)
    assert found.found and abs(found.score - best) < 1e-9


# ---------------------------------------------------------------------------- ingest sync


@many
@given(st.lists(st.integers(0, 20), max_size=8), st.lists(st.integers(-2, 22), min_size=1,
                                                           max_size=6), st.integers(0, 5))
def test_match_nearest_is_argmin_with_ties_to_the_earlier_and_first_stamp(
        ref: list[int], query: list[int], tol: int) -> None:
    """Against ``argmin(|ref - q|)`` on quarter seconds: repeated stamps, queries half-way
    between two, before the first and after the last, tolerance met exactly."""
    r = np.sort(np.array(ref, float)) / 4
    q = np.array(query, float) / 4
    got = match_nearest(q, r, tol / 4)
    for k, x in enumerate(q):
        if not len(r):
            assert got[k] == -1
            continue
        d = np.abs(r - x)
        b = int(np.argmin(d))
        assert got[k] == (b if d[b] <= tol / 4 else -1)


@many
@given(st.lists(st.integers(0, 6), max_size=9))
def test_longest_increasing_is_strict_and_as_long_as_any(values: list[int]) -> None:
    v = np.array(values, dtype=np.int64)
    keep = longest_increasing(v)
    assert np.all(np.diff(v[keep]) > 0)
    n = len(v)
    longest = max((bin(m).count("1") for m in range(1 << n)
                   if np.all(np.diff(v[[i for i in range(n) if m >> i & 1]]) > 0)), default=0)
    assert keep.sum() == longest


# ---------------------------------------------------------------------------- files


@quick
@given(seeds, st.integers(0, 5), st.integers(1, 30))
def test_scan_files_round_trip_odd_ranges_and_no_scans_at_all(tmp_path: Path, seed: int,
                                                             n: int, beams: int) -> None:
    """NaN and +-inf ranges, scans with and without intensities, beams either way round,
    per-beam timing, Unix stamps; and a file of no scans reads back as none (it was written,
    then refused: "missing array 'angle_min'")."""
    rng = np.random.default_rng(seed)
    t0 = rng.uniform(0, 2e9)
    scans = []
    for i in range(n):
        r = rng.uniform(0.1, 30, beams).astype(np.float32)  # [B]
        r[rng.random(beams) < 0.2] = np.nan
        r[rng.random(beams) < 0.1] = np.inf
        r[rng.random(beams) < 0.1] = -np.inf
        inten = rng.uniform(0, 100, beams).astype(np.float32) if rng.random() < 0.5 else None
        scans.append(LaserScan(t0 + 0.1 * i, r, float(rng.uniform(-3, 3)),
                               float(rng.choice([-1, 1]) * rng.uniform(1e-3, 0.1)), 0.05,
                               float(rng.choice([30.0, np.inf])), inten,
                               float(rng.choice([0.0, 1e-5]))))
    path = tmp_path / "scans.npz"
    write_scans(path, scans)
    back = read_scans(path)
    assert len(back) == n
    for a, b in zip(scans, back, strict=True):
        np.testing.assert_array_equal(a.ranges, b.ranges)
        assert (a.intensities is None) == (b.intensities is None)
        if a.intensities is not None:
            np.testing.assert_array_equal(a.intensities, b.intensities)
        assert (a.stamp, a.angle_min, a.angle_increment, a.range_min, a.range_max,
                a.time_increment) == (b.stamp, b.angle_min, b.angle_increment, b.range_min,
                                      b.range_max, b.time_increment)


# ---------------------------------------------------------------------------- calibration


@many
@given(st.integers(1, 40_000), st.integers(1, 5000), st.integers(1, 300))
@example(80, 50, 100)  # --max-frames 50 on an 80-frame recording
def test_time_offset_reads_at_most_max_frames_all_of_them_recording_frames(
        n: int, max_frames: int, block: int) -> None:
    """Indices within the recording, increasing, no more than ``max_frames``; all frames
    when they are few enough. ``--max-frames 50`` on 80
    frames read one run of 100, frames 80..99 past the end (an IndexError)."""
    use = frames_to_use(n, max_frames, block)
    assert len(use) <= max_frames and np.all(np.diff(use) > 0)
    assert use[0] == 0 and use[-1] < n
    if n <= max_frames:
        assert len(use) == n


# ---------------------------------------------------------------------------- g2o files


def _robotlaser1(stamp: float, ranges: np.ndarray, laser: np.ndarray,
                 robot: np.ndarray) -> str:
    return (f"ROBOTLASER1 0 -1.5708 3.14159 0.0174533 50 0.01 0 {len(ranges)} "
            + " ".join(f"{r:.3f}" for r in ranges) + " 0 "
            + " ".join(repr(float(v)) for v in (*laser, *robot)) + f" 0 0 0 0 0 {stamp!r} h 0\n")


@quick
@given(seeds, st.integers(2, 8), st.booleans())
def test_g2o_odometry_is_the_edge_chain_and_information_rows_match_edges(
        tmp_path: Path, seed: int, n: int, with_info: bool) -> None:
    """Vertex ids with gaps (0 10 20 ...), an odometry edge from each to the next with or
    without its information numbers, a loop edge, a scan at some vertices: the odometry
    is the chain composed from the first scan's vertex, and there is one information row
    per edge (edges without numbers gave 0 rows for E edges)."""
    rng = np.random.default_rng(seed)
    ids = np.cumsum(rng.integers(1, 12, n))  # [V]
    X = np.c_[rng.normal(0, 3, (n, 2)), rng.uniform(-np.pi, np.pi, n)]  # [V, 3]
    info = " 500 0 0 500 0 2000" if with_info else ""
    lines = [f"VERTEX_SE2 {i} " + " ".join(repr(float(v)) for v in x) + "\n"
             for i, x in zip(ids, X, strict=True)]
    lines += [f"EDGE_SE2 {ids[k]} {ids[k + 1]} "
              + " ".join(repr(float(v)) for v in se2_between(X[k], X[k + 1])) + info + "\n"
              for k in range(n - 1)]
    lines.append(f"EDGE_SE2 {ids[-1]} {ids[0]} 0 0 0{info}\n")
    scanned = np.flatnonzero(rng.random(n) < 0.7)
    if len(scanned) == 0:
        scanned = np.array([0])
    body = []
    for k in range(n):
        body.append(lines[k])
        if k in scanned:
            body.append(_robotlaser1(1e9 + 0.1 * k, rng.uniform(1, 5, 9),
                                     se2_compose(X[k], np.array([0.2, 0.0, 0.0])), X[k]))
    path = tmp_path / "graph.g2o"
    path.write_text("".join(body + lines[n:]))
    g2o = read_g2o(path)
    assert g2o.edge_information.shape == (n, 6)
    assert np.isnan(g2o.edge_information).all() != with_info
    assert g2o.sequential_edges().tolist() == [True] * (n - 1) + [False]
    odo = g2o.odometry()
    first = X[scanned[0]]
    want = se2_between(np.broadcast_to(first, (len(scanned), 3)), X[scanned])  # [S, 3]
    got = np.c_[odo.poses[:, 0, 3], odo.poses[:, 1, 3],
                np.arctan2(odo.poses[:, 1, 0], odo.poses[:, 0, 0])]
    _assert_same_poses(got, want, 1e-9)
    np.testing.assert_allclose(g2o.T_base_laser[:2, 3], [0.2, 0.0], atol=1e-9)


def test_g2o_edge_with_part_of_its_information_names_the_line(tmp_path: Path) -> None:
    path = tmp_path / "part.g2o"
    path.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\n"
                    "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 1 0 -1 0 0 1 0 0\n")
    with pytest.raises(CarmenFormatError, match=r"part\.g2o:4: bad EDGE_SE2 line: 3 "
                                                r"information numbers"):
        read_g2o(path)


# ---------------------------------------------------------------------------- SLAM input


@many
@given(seeds, st.floats(0.0, 0.5), st.sampled_from([4.0, 5.6, 30.0, np.inf]),
       st.sampled_from([0.0, 0.02, 0.3]))
def test_slam_hits_are_the_scans_valid_returns_within_reach(
        seed: int, min_range: float, range_max: float, range_min: float) -> None:
    """The SLAM inserts as walls exactly the beams ``LaserScan.valid_mask`` calls returns
    (within scan.max_range), and casts free space along the no-returns, whatever the
    configured min_range: with min_range 0 a driver's zero (no return) was a wall at the
    laser itself, moving with the robot."""
    rng = np.random.default_rng(seed)
    n = 64
    r = rng.uniform(0.0, 8.0, n).astype(np.float32)  # [B]
    for code in (0.0, -1.0, np.nan, np.inf, -np.inf, range_max):
        r[rng.random(n) < 0.08] = code
    scan = LaserScan(0.0, r, -np.pi, 2 * np.pi / n, range_min, range_max)
    slam = LidarSlam2D(Slam2DConfig(scan=ScanOptions(min_range=min_range, max_range=6.0,
                                                     min_valid_beams=3)))
    pre = slam._preprocess(scan)
    with np.errstate(invalid="ignore"):
        want = scan.valid_mask() & (r >= min_range) & (r <= 6.0)  # [B]
        no_return = (r == np.inf) | (np.isfinite(r) & (r >= np.float32(range_max)))
    if want.sum() < 3:
        assert pre is None
        return
    assert pre is not None
    hits, free = pre
    np.testing.assert_allclose(np.sort(np.hypot(*hits.T)), np.sort(r[want]), rtol=1e-6)
    assert len(free) == int(no_return.sum() + (scan.valid_mask() & (r > 6.0)).sum())

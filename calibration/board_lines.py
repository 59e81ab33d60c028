"""Finding the scan points that hit the calibration board.

A planar board cut by the laser plane is a straight segment in the scan. Segments are
extracted by sequential RANSAC (seeded, so results repeat) and split at gaps; the board's
segment is then the one that agrees best with what the camera saw: its distance, its
incidence angle and (optionally) a bearing window. Once an extrinsic estimate exists,
``points_near_plane`` re-selects the board points from the predicted plane instead, which
also recovers board points RANSAC had put into a neighbouring segment.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Segment:
    """A straight run of scan points."""

    indices: np.ndarray  # [K] int, into the scan's points
    points: np.ndarray  # [K, 2] metres
    normal: np.ndarray  # [2] unit, pointing away from the laser origin
    offset: float  # metres: normal . p = offset for points on the line (>= 0)
    rms: float  # metres, perpendicular scatter
    length: float  # metres, extent along the line

    @property
    def midpoint(self) -> np.ndarray:
        """[2] centre of the segment's extent."""
        d = np.array([-self.normal[1], self.normal[0]])
        s = self.points @ d
        return self.offset * self.normal + 0.5 * (s.min() + s.max()) * d

    @property
    def bearing(self) -> float:
        """Radians, counter-clockwise from laser +x, of the midpoint."""
        m = self.midpoint
        return float(np.arctan2(m[1], m[0]))


def fit_line(points: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Total least squares line of [K, 2] points: unit normal [2], offset, rms."""
    c = points.mean(0)
    _, s, vt = np.linalg.svd(points - c, full_matrices=False)
    n = vt[-1]
    off = float(n @ c)
    if off < 0:
        n, off = -n, -off
    rms = float(s[-1] / np.sqrt(len(points))) if len(s) > 1 else 0.0
    return n, off, rms


def range_noise(scans: list[np.ndarray], min_samples: int = 100) -> float | None:
    """The lidar's range noise (1 sigma, metres) measured on scans [N, 2] themselves, or
    None when they hold fewer than ``min_samples`` usable beam triples.

    Each beam's range is compared with where the chord between its two neighbours crosses
    its bearing: zero on any straight surface whatever the incidence, the range noise
    combined with half each neighbour's (variance 1.5 sigma^2) otherwise. The median
    absolute difference ignores the few triples across depth jumps and corners. Simulated
    captures read 9.9 / 19.8 / 24.8 / 29.7 mm at 1 / 2 / 2.5 / 3 cm of noise, the ACFR
    Hokuyo 2.2 mm.
    """
    devs = []
    for pts in scans:
        p = np.asarray(pts, dtype=np.float64)
        if len(p) < 3:
            continue
        a = np.arctan2(p[:, 1], p[:, 0])
        order = np.argsort(a)
        p, a = p[order], a[order]
        da = np.diff(a)
        if not np.any(da > 1e-9):
            continue
        step = float(np.median(da[da > 1e-9]))
        # Triples of neighbouring beams: no beam missing between them.
        i = np.flatnonzero((np.abs(da[:-1] - step) < 0.5 * step)
                           & (np.abs(da[1:] - step) < 0.5 * step)) + 1
        prev, chord = p[i - 1], p[i + 1] - p[i - 1]  # [T, 2]
        u = np.stack([np.cos(a[i]), np.sin(a[i])], -1)  # [T, 2] the middle beam's ray
        cross_u = u[:, 0] * chord[:, 1] - u[:, 1] * chord[:, 0]
        cross_p = prev[:, 0] * chord[:, 1] - prev[:, 1] * chord[:, 0]
        # A chord nearly along the ray (grazing incidence) says nothing about the range.
        ok = np.abs(cross_u) > 0.2 * np.linalg.norm(chord, axis=1)
        r = np.linalg.norm(p[i], axis=1)
        devs.append(r[ok] - cross_p[ok] / cross_u[ok])
    d = np.concatenate(devs) if devs else np.zeros(0)
    if len(d) < min_samples:
        return None
    return float(1.4826 * np.median(np.abs(d)) / np.sqrt(1.5))


def extract_segments(points: np.ndarray, seed: int = 0, inlier_m: float = 0.02,
                     min_points: int = 6, max_gap_m: float = 0.1, max_segments: int = 30,
                     iterations: int = 300) -> list[Segment]:
    """Straight segments of a scan [N, 2] by sequential RANSAC, largest first.

    Each round fits the line with most inliers, splits its inliers at gaps longer than
    ``max_gap_m`` (two walls on one line are two segments) and removes them from the pool.
    """
    pts = np.asarray(points, dtype=np.float64)
    rng = np.random.default_rng(seed)
    pool = np.arange(len(pts))
    segments: list[Segment] = []
    while len(pool) >= min_points and len(segments) < max_segments:
        P = pts[pool]  # [M, 2]
        a = rng.integers(0, len(P), iterations)
        b = rng.integers(0, len(P), iterations)
        d = P[b] - P[a]  # [T, 2]
        norm = np.linalg.norm(d, axis=1)
        keep = norm > 1e-6
        if not np.any(keep):
            break
        n = np.stack([-d[keep, 1], d[keep, 0]], -1) / norm[keep, None]  # [T, 2]
        # |n . (p - p_a)| for every hypothesis t and point m: [T, M]
        dist = np.abs(P @ n.T - np.einsum("tj,tj->t", n, P[a[keep]])).T
        counts = (dist < inlier_m).sum(1)
        best = int(np.argmax(counts))
        if counts[best] < min_points:
            break
        inl = dist[best] < inlier_m
        # Refit on the inliers and take the inliers of the refit, twice: the sampled pair
        # is noisy, the refit is not.
        for _ in range(2):
            nn, off, _ = fit_line(P[inl])
            inl = np.abs(P @ nn - off) < inlier_m
        idx = pool[inl]
        tang = np.array([-nn[1], nn[0]])
        s = pts[idx] @ tang
        order = np.argsort(s)
        idx, s = idx[order], s[order]
        breaks = np.nonzero(np.diff(s) > max_gap_m)[0] + 1
        for run in np.split(idx, breaks):
            if len(run) >= min_points:
                rn, roff, rrms = fit_line(pts[run])
                rs = pts[run] @ np.array([-rn[1], rn[0]])
                segments.append(Segment(run, pts[run], rn, roff, rrms,
                                        float(rs.max() - rs.min())))
        pool = pool[~inl]
    segments.sort(key=lambda sg: -len(sg.indices))
    return segments


@dataclass
class BoardExpectation:
    """What the camera says about the board, for picking its segment in the scan.

    Without an extrinsic the laser origin is only known to lie within ``max_offset_m``
    of the camera's, so the board's distance is known to that tolerance; its incidence
    angle (between the viewing ray and the board normal) is the same for both sensors
    up to the parallax of that offset.
    """

    distance_m: float  # camera centre to the board plane
    center_range_m: float  # camera centre to the middle of the corner grid
    incidence_rad: float  # angle between the ray to the board and the board normal
    min_length_m: float  # a shorter segment cannot be the board
    max_length_m: float
    max_offset_m: float = 0.5
    bearing_window_rad: tuple[float, float] | None = None  # laser bearings to search
    # Where a guess of the extrinsic puts the board (radians in the laser frame), and how
    # far from that a segment may be; None when no guess is made.
    expected_bearing_rad: float | None = None
    bearing_tol_rad: float = np.radians(35.0)
    expected_length_m: float = 0.0  # shorter segments pay the shortfall in the cost


def in_bearing_window(angle: np.ndarray | float, lo: float, hi: float,
                      turn: float = 2 * np.pi) -> np.ndarray:
    """Whether ``angle`` lies on the arc from ``lo`` counter-clockwise to ``hi`` (one
    unit throughout: radians, or degrees with ``turn`` 360). Arcs cross +-180 deg: 150..210
    and 170..-170 both face backwards; an arc of a whole turn or more holds every angle."""
    a = np.asarray(angle, dtype=np.float64)
    if hi - lo >= turn:
        return np.ones(a.shape, bool)
    return np.mod(a - lo, turn) <= np.mod(hi - lo, turn)


def select_board_segment(segments: list[Segment], expect: BoardExpectation) -> (
    tuple[Segment | None, str]
):
    """The segment that best matches the board, or None with the reason why."""
    best: tuple[float, Segment] | None = None
    reasons: dict[str, int] = {}
    for sg in segments:
        if expect.bearing_window_rad is not None:
            lo, hi = expect.bearing_window_rad
            if not in_bearing_window(sg.bearing, lo, hi):
                reasons["outside the angular window"] = reasons.get(
                    "outside the angular window", 0) + 1
                continue
        if not expect.min_length_m <= sg.length <= expect.max_length_m:
            reasons["wrong length"] = reasons.get("wrong length", 0) + 1
            continue
        # In-plane distance of the line can only exceed the 3D distance to the plane
        # (the laser plane may cut the board obliquely); both differ by the sensor offset.
        dd = sg.offset - expect.distance_m
        if not -expect.max_offset_m <= dd <= expect.max_offset_m + 0.5 * expect.distance_m:
            reasons["wrong distance"] = reasons.get("wrong distance", 0) + 1
            continue
        rng = float(np.linalg.norm(sg.midpoint))
        if abs(rng - expect.center_range_m) > expect.max_offset_m + expect.max_length_m / 2:
            reasons["wrong range"] = reasons.get("wrong range", 0) + 1
            continue
        dbear = 0.0
        if expect.expected_bearing_rad is not None:
            dbear = abs((sg.bearing - expect.expected_bearing_rad + np.pi) % (2 * np.pi) - np.pi)
            if dbear > expect.bearing_tol_rad:
                reasons["away from the expected bearing"] = reasons.get(
                    "away from the expected bearing", 0) + 1
                continue
        inc = float(np.arccos(np.clip(abs(sg.normal @ sg.midpoint) / max(rng, 1e-9), 0, 1)))
        # Costs in comparable units: metres of distance mismatch; incidence and bearing
        # mismatch scaled so that 10 degrees weighs like 10 cm; the length shortfall
        # (a clutter fragment is shorter than the board); a little for scatter.
        deg10 = 0.1 / np.radians(10)
        cost = (abs(dd) + abs(inc - expect.incidence_rad) * deg10 + dbear * deg10
                + max(0.0, expect.expected_length_m - sg.length) + sg.rms)
        if best is None or cost < best[0]:
            best = (cost, sg)
    if best is None:
        why = ", ".join(f"{v} {k}" for k, v in reasons.items()) or "no straight segments"
        return None, f"no segment matches the board ({len(segments)} segments: {why})"
    return best[1], ""


def points_near_plane(points: np.ndarray, normal_l: np.ndarray, offset_l: float,
                      center_l: np.ndarray, max_dist_m: float, max_extent_m: float,
                      max_gap_m: float = 0.1) -> np.ndarray:
    """[K] indices of scan points [N, 2] on a plane predicted in the laser frame.

    The plane is ``normal_l . p = offset_l`` (normal [3], laser frame); points must lie
    within ``max_dist_m`` of it and within ``max_extent_m`` of ``center_l`` [3] (the
    board's middle) along the cut. Of those, the contiguous run nearest the board centre
    is kept so a wall in line with the board is not taken for it.
    """
    pts = np.asarray(points, dtype=np.float64)
    p3 = np.concatenate([pts, np.zeros((len(pts), 1))], -1)  # [N, 3]
    near = np.abs(p3 @ normal_l - offset_l) < max_dist_m
    near &= np.linalg.norm(p3 - center_l, axis=1) < max_extent_m
    idx = np.nonzero(near)[0]
    if len(idx) < 2:
        return idx
    # Order along the cut line and split at gaps.
    line_dir = np.cross(normal_l, [0.0, 0.0, 1.0])[:2]
    nrm = np.linalg.norm(line_dir)
    if nrm < 1e-9:
        return idx
    s = pts[idx] @ (line_dir / nrm)
    order = np.argsort(s)
    idx, s = idx[order], s[order]
    runs = np.split(np.arange(len(idx)), np.nonzero(np.diff(s) > max_gap_m)[0] + 1)
    c = center_l[:2] @ (line_dir / nrm)
    best = min(runs, key=lambda r: (0.0 if s[r[0]] <= c <= s[r[-1]] else
                                    min(abs(s[r[0]] - c), abs(s[r[-1]] - c)), -len(r)))
    return np.sort(idx[best])


def board_edge_points(points: np.ndarray, board_idx: np.ndarray, min_gap_m: float = 0.05) -> (
    tuple[np.ndarray, np.ndarray]
):
    """Where the scan leaves the board: crossing points [E, 2] and their sigmas [E] (m).

    The edge lies between the outermost beam on the board and the next beam, which must
    pass the board and hit something farther away (a nearer hit means an occluder, and
    the board may go on behind it: no edge is reported there). The crossing is taken
    half a beam step out along the board's line; its error is uniform over one step,
    so its sigma is the step length over sqrt(12).
    """
    pts = np.asarray(points, dtype=np.float64)
    idx = np.asarray(board_idx)
    if len(idx) < 3:
        return np.zeros((0, 2)), np.zeros(0)
    ang = np.arctan2(pts[:, 1], pts[:, 0])
    rng = np.linalg.norm(pts, axis=1)
    order = np.argsort(ang)
    steps = np.diff(ang[order])
    steps = steps[steps > 1e-6]
    if len(steps) == 0:
        return np.zeros((0, 2)), np.zeros(0)
    step = float(np.median(steps))
    n, off, _ = fit_line(pts[idx])
    # Bearings about the board's own mean: a board across the laser's +-180 deg bearing
    # (a backward-mounted or 360 deg lidar) had its two ends taken from inside it.
    mean = np.arctan2(np.sin(ang[idx]).sum(), np.cos(ang[idx]).sum())
    b_ang = (ang[idx] - mean + np.pi) % (2 * np.pi) - np.pi
    out, sig = [], []
    for end, sign in ((int(idx[np.argmin(b_ang)]), -1.0), (int(idx[np.argmax(b_ang)]), 1.0)):
        a_end = ang[end]

        def on_line(a: float) -> np.ndarray | None:
            d = np.array([np.cos(a), np.sin(a)])
            den = float(n @ d)
            return None if den < 1e-6 else d * (off / den)

        nxt = a_end + sign * step
        # The neighbouring beam: the scan point closest to the next beam's bearing.
        k = int(np.argmin(np.abs((ang - nxt + np.pi) % (2 * np.pi) - np.pi)))
        if abs((ang[k] - nxt + np.pi) % (2 * np.pi) - np.pi) > 0.5 * step or k in set(idx):
            continue  # no return there (or still on the board): edge position unknown
        p_next = on_line(nxt)
        p_mid = on_line(a_end + sign * step / 2)
        p_end = on_line(a_end)
        if p_next is None or p_mid is None or p_end is None:
            continue
        if rng[k] < np.linalg.norm(p_next) + min_gap_m:
            continue  # something in front of the board's continuation: maybe occluded
        out.append(p_mid)
        sig.append(float(np.linalg.norm(p_next - p_end)) / np.sqrt(12.0))
    return np.array(out).reshape(-1, 2), np.array(sig)

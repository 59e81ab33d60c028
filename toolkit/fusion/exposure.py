"""Per-frame exposure gains from the frames' overlaps, for auto-exposure cameras.

Most robot cameras run auto exposure: a wall looks brighter in a frame taken facing a
dark corridor than in one facing a window. Averaged into voxels, the map's colours then
carry each room's exposure. A frame's gain cannot be read from the frame alone, nor
from the map as it grows (measured on the simulated house: such sequential estimates
drift, and against the finished map they are compressed, since the frames that see a
voxel share one room's exposure). So the gains are solved jointly over the whole drive:

- every frame's points are grouped into coarse surface cells (``cell_m``, and the side
  they are seen from) and each cell's mean colour is one observation
  ``log c = log albedo + log g_frame``;
- two frames that see the same cell measure ``log g_a - log g_b``; the median over all
  their common cells is one robust edge (moving people, parallax and texture differences
  inside a cell are outliers to it);
- a sparse weighted least squares over the edges (Huber-reweighted), with a weak pull
  between consecutive frames so that every frame is tied to the others, gives each
  frame's log gain up to one common offset per channel, fixed by a geometric mean of 1.

Gains are per colour channel, so auto white balance is undone too. Pixel values are
taken as proportional to the exposure: true for a linear sensor and, for a power-law
gamma, with the gain raised to 1/gamma, which is still one factor per frame.
"""

from __future__ import annotations

import csv
import time
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from toolkit.errors import InputError
from toolkit.fusion.voxel_map import KeyTable, pack_key_columns
from toolkit.io.atomic import atomic_write_text


@dataclass(frozen=True)
class ExposureOptions:
    """How the observations are taken and the gains solved."""

    cell_m: float = 0.10  # surface cells the frames are compared on
    stride: int = 4  # every n-th pixel in both directions
    min_points: int = 4  # pixels a cell needs in a frame to be an observation
    dark: int = 8  # channel values at or below it are not used (noise dominates)...
    bright: int = 247  # ...nor at or above it (clipped)
    # Each observation is compared with the same cell's observations this many
    # observations later (in frame order): near frames and, through the longer offsets,
    # the frames of a later visit.
    offsets: tuple[int, ...] = (1, 2, 4, 8, 16, 32)
    # Cells two frames must share to make an edge: a median over a few cells can be all
    # outliers (the quickstart's house at stride 4: gains 0.36 % RMS off with 8, 0.05 %
    # with 30, the truth's spread 9.3 %; re-measured in session 34: 0.065 % with 8,
    # 0.077 % with 30).
    min_common: int = 30
    max_weight: float = 200.0  # an edge's weight is its cell count up to this
    huber_log: float = 0.03  # Huber threshold on an edge's residual, in log gain
    smooth_weight: float = 2.0  # pull between consecutive frames' log gains
    iterations: int = 6
    # Observations kept over the whole drive (the quickstart's 644 frames make 0.57 M;
    # 4 M took 1.3 GB to compare): a longer drive keeps fewer cells per frame, down to
    # ``min_cells``, then solves every n-th frame only (``plan``); an hour at 10 Hz would
    # have made 32 M.
    max_observations: int = 2_000_000
    # Fewer cells per frame lose the far edges: on the auto-exposure house gains 0.077 %
    # RMS off with all (~855), 0.081 / 0.108 / 0.365 / 0.90 % with 400 / 200 / 100 / 60
    # (session 34; docs/depth_fusion.md, "Exposure").
    min_cells: int = 200

    def plan(self, n_frames: int) -> tuple[int, int]:
        """(every how many frames to solve, the most cells a solved frame keeps) for a
        drive of ``n_frames``."""
        n = max(n_frames, 1)
        cells = self.max_observations // n
        if cells >= self.min_cells:
            return 1, cells
        return -(-n * self.min_cells // self.max_observations), self.min_cells

    def __post_init__(self) -> None:
        if self.cell_m <= 0 or self.stride < 1 or self.min_points < 1:
            raise ValueError("exposure: cell_m must be > 0, stride and min_points >= 1")
        if not 0 <= self.dark < self.bright <= 255:
            raise ValueError(f"exposure: need 0 <= dark < bright <= 255, got {self.dark}, "
                             f"{self.bright}")
        if not self.offsets or min(self.offsets) < 1:
            raise ValueError("exposure: offsets must be positive integers")
        if self.min_cells < self.min_common or self.max_observations < self.min_cells:
            raise ValueError("exposure: need min_common <= min_cells <= max_observations")


_CELL_BITS = 20
_CELL_OFFSET = 1 << (_CELL_BITS - 1)
CELL_RANGE = _CELL_OFFSET  # points within this many cells of the origin can be keyed


def cell_keys(points: np.ndarray, origin: np.ndarray, cell_m: float) -> np.ndarray:
    """[N] int64 key of each point's cell [N, 3] and the quadrant of the horizontal
    direction it was seen from (from ``origin`` [3], the camera centre).

    The quadrant keeps the two sides of a thin wall apart: a 10 cm cell can hold both, and
    a later visit from the other room then compared the rooms' paint, not the exposures
    (on the quickstart's house at stride 2: gains 7 % RMS off without it, 0.16 % with it;
    re-measured in session 34: 2.69 % and 0.068 %).
    """
    return pack_key_columns(cell_key_columns(points, origin, cell_m), _CELL_KEY_BITS)


_CELL_KEY_BITS = [_CELL_BITS] * 3 + [2]  # x, y, z cell and the quadrant


def cell_key_columns(points: np.ndarray, origin: np.ndarray, cell_m: float) -> list[
        np.ndarray]:
    """What ``cell_keys`` packs, column by column: the cell's x, y, z index (offset to be
    non-negative) and the quadrant, [N] int64 each."""
    p = np.asarray(points)
    o = np.asarray(origin, np.float64)
    cols = []
    for k in range(3):
        pk = p[:, k].astype(np.float64)  # [N]
        cols.append(np.floor(pk / cell_m).astype(np.int64) + _CELL_OFFSET)
    if len(p) and (min(int(c.min()) for c in cols) < 0
                   or max(int(c.max()) for c in cols) >= 1 << _CELL_BITS):
        raise ValueError(f"points beyond +-{_CELL_OFFSET * cell_m:.0f} m cannot be keyed")
    east = (p[:, 0].astype(np.float64) - o[0]) >= 0
    north = (p[:, 1].astype(np.float64) - o[1]) >= 0
    cols.append(east.astype(np.int64) | (north.astype(np.int64) << 1))
    return cols


def cell_observations(points: np.ndarray, colors: np.ndarray, origin: np.ndarray,
                      opts: ExposureOptions, max_cells: int | None = None,
                      table: KeyTable | None = None) -> tuple[
                          np.ndarray, np.ndarray, np.ndarray]:
    """One frame's observations from its points [N, 3] seen from ``origin`` [3] and their
    colours [N, 3] uint8: cell keys [M] int64 (``cell_keys``), log mean colours [M, 3]
    float32 and pixel counts [M], for the cells with at least ``min_points`` pixels and
    none dark or clipped in any channel. With ``max_cells``, only that many: those whose
    keys hash lowest, so that frames seeing the same surface keep the same cells
    (``plan``). ``table``: one to group the keys with, kept from frame to frame (None: a
    fresh one)."""
    c = np.asarray(colors)  # [N, 3]
    if len(c) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3), np.float32), np.zeros(0, np.int32)
    # A cell with a dark or clipped pixel is no observation at all: dropping the pixels
    # one by one took a bright frame's brightest pixels and a dark frame's darkest out of
    # the same cell's means, whose ratio then compressed the gains (70 % white-paint cells
    # at gains 0.7-1.3: 0.88 % RMS / 2.3 % max off, 0.18 / 0.35 % with whole cells).
    # Channel by channel: reductions along the short axis of [N, 3] are numpy's slow case.
    ok = c[:, 0] > opts.dark  # [N]
    for k in range(3):
        if k:
            ok &= c[:, k] > opts.dark
        ok &= c[:, k] < opts.bright
    uk, inv = (table or KeyTable()).unique(cell_key_columns(points, origin, opts.cell_m),
                                           _CELL_KEY_BITS)
    cnt = np.bincount(inv, minlength=len(uk))  # [M']
    n_bad = np.bincount(inv, ~ok, len(uk))  # [M']
    mean = np.stack([np.bincount(inv, c[:, k].astype(np.float64), len(uk)) for k in range(3)],
                    1) / cnt[:, None]
    keep = np.flatnonzero((cnt >= opts.min_points) & (n_bad == 0))
    if max_cells is not None and len(keep) > max_cells:
        # A multiplicative hash (Fibonacci hashing; uint64 arithmetic wraps).
        h = uk[keep].astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
        keep = np.sort(keep[np.argpartition(h, max_cells - 1)[:max_cells]])
    return uk[keep], np.log(mean[keep]).astype(np.float32), cnt[keep].astype(np.int32)


@dataclass
class ExposureObservations:
    """The observations of every frame, in the order they were added (picklable, so a
    checkpoint can hold them)."""

    frame: list[np.ndarray] = field(default_factory=list)
    key: list[np.ndarray] = field(default_factory=list)
    log_rgb: list[np.ndarray] = field(default_factory=list)

    def add(self, frame: int, keys: np.ndarray, log_rgb: np.ndarray) -> None:
        """Observations of frame ``frame`` (its position, 0..F-1, among the solved ones)."""
        self.frame.append(np.full(len(keys), frame, np.int32))
        self.key.append(np.asarray(keys, np.int64))
        self.log_rgb.append(np.asarray(log_rgb, np.float32))

    def __len__(self) -> int:
        return sum(len(k) for k in self.key)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """frames [K] int32, cell keys [K] int64, log colours [K, 3] float32."""
        if not self.key:
            return np.zeros(0, np.int32), np.zeros(0, np.int64), np.zeros((0, 3), np.float32)
        return (np.concatenate(self.frame), np.concatenate(self.key),
                np.concatenate(self.log_rgb))


@dataclass
class GainEdges:
    """Frame pairs that share cells: ``log g_a - log g_b ~ diff``."""

    a: np.ndarray  # [E] int
    b: np.ndarray  # [E] int, > a
    diff: np.ndarray  # [E, 3] median log colour difference over the common cells
    common: np.ndarray  # [E] cells compared

    @staticmethod
    def empty() -> GainEdges:
        return GainEdges(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)),
                         np.zeros(0, np.int64))


def gain_edges(frames: np.ndarray, keys: np.ndarray, log_rgb: np.ndarray,
               opts: ExposureOptions) -> GainEdges:
    """The frame pairs' median colour differences over their common cells."""
    order = np.lexsort((frames, keys))
    k, f, c = keys[order], frames[order], log_rgb[order]
    parts_a, parts_b, parts_d = [], [], []
    for off in opts.offsets:
        if off >= len(k):
            break
        same = k[off:] == k[:-off]
        parts_a.append(f[:-off][same])
        parts_b.append(f[off:][same])
        parts_d.append(c[:-off][same] - c[off:][same])
    if not parts_a or not sum(len(p) for p in parts_a):
        return GainEdges.empty()
    a = np.concatenate(parts_a)
    b = np.concatenate(parts_b)
    d = np.concatenate(parts_d).astype(np.float64)  # [P, 3]
    del parts_a, parts_b, parts_d
    finite = np.isfinite(d).all(1)
    if not finite.all():
        a, b, d = a[finite], b[finite], d[finite]
    if not len(a):
        return GainEdges.empty()
    n_frames = int(max(a.max(), b.max())) + 1
    # a < b: observations are in frame order within a cell
    pid = a.astype(np.int64) * n_frames + b
    del a, b
    upid, inv = KeyTable().unique([pid], [63])  # np.unique's, without sorting the pairs
    cnt = np.bincount(inv, minlength=len(upid))
    start = np.r_[0, np.cumsum(cnt)[:-1]]
    # The median of each pair's differences: sort by (pair, value) and take the middle.
    lo, hi = start + (cnt - 1) // 2, start + cnt // 2
    med = np.empty((len(upid), 3))
    # One float64 key, pair then value, each pair's slot wider than its values' range:
    # the order of a two-key lexsort in a fifth of its time (2.25 -> 0.45 s for the
    # house's 0.6 M observations). Exact while inv * width stays far below 2^52.
    width = 2.0 * np.ceil(np.abs(d).max()) + 2.0
    for ch in range(3):
        srt = d[np.argsort(inv * width + (d[:, ch] + 0.5 * width)), ch]
        med[:, ch] = 0.5 * (srt[lo] + srt[hi])
    keep = cnt >= opts.min_common
    return GainEdges(upid[keep] // n_frames, upid[keep] % n_frames, med[keep], cnt[keep])


@dataclass
class GainSolution:
    """Each frame's gain (observed = gain x exposure-free colour), per channel."""

    gains: np.ndarray  # [F, 3], geometric mean 1 per channel
    edges: int  # frame pairs used
    frames_linked: int  # frames in at least one edge (the rest follow their neighbours)
    groups: int  # groups of linked frames with no edge between them (1: all in one)
    residual_log_rms: float  # weighted RMS of the edges' residuals (log gain)
    outlier_edges: int  # edges down-weighted by the Huber loss at the end
    seconds: float = 0.0  # comparing and solving (solve_exposure), wall clock...
    cpu_seconds: float = 0.0  # ... and CPU time


def _huber(resid: np.ndarray, threshold: float) -> np.ndarray:
    """Huber weights [E] of residuals [E] (1 up to ``threshold``, falling as 1 / r past it)."""
    return np.minimum(1.0, threshold / np.maximum(resid, 1e-12))


def solve_gains(edges: GainEdges, n_frames: int, opts: ExposureOptions) -> GainSolution:
    """Log gains by sparse weighted least squares over the edges (Huber-reweighted) and a
    weak pull between consecutive frames; ``n_frames`` gains."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.sparse.linalg import splu

    if n_frames < 1:
        raise ValueError("solve_gains: no frames")
    a, b = edges.a, edges.b
    base_w = np.minimum(edges.common, opts.max_weight).astype(np.float64)
    w = base_w.copy()
    # Consecutive frames: difference 0 with a weak weight (the exposure moves smoothly;
    # this ties a frame without overlaps to its neighbours and fixes nothing else). It is
    # Huber-reweighted like the edges: held at full weight while the rounds took down the
    # edges that disagreed with it, it pulled frames whose overlaps fixed their gains
    # together (exact observations, exposure jumping 2x between frames sharing 40 cells:
    # 2.6 % off each jump; random gains over 400 cells: 0.68 in log gain at worst of 40
    # drives, 0.071 with the pull reweighted).
    sa = np.arange(n_frames - 1)
    ia = np.concatenate([a, sa])
    ib = np.concatenate([b, sa + 1])
    x = np.zeros((n_frames, 3))
    resid = np.zeros(len(a))
    pull_w = np.full(len(sa), opts.smooth_weight)
    for _ in range(max(1, opts.iterations)):
        ww = np.concatenate([w, pull_w])
        dd = np.concatenate([edges.diff, np.zeros((len(sa), 3))])
        rows = np.concatenate([ia, ib, ia, ib])
        cols = np.concatenate([ia, ib, ib, ia])
        vals = np.concatenate([ww, ww, -ww, -ww])
        # The first frame held at 0 fixes the common offset (removed below) and nothing
        # else; a ridge on every frame instead grew with the drive and, on thousands of
        # frames, flattened a slow drift of the exposure (a +-0.3 ramp over 10 000 frames
        # came out at a fifth of its slope).
        N = coo_matrix((np.r_[vals, max(float(ww.max()), 1.0)],
                        (np.r_[rows, 0], np.r_[cols, 0])), shape=(n_frames, n_frames)).tocsc()
        rhs = np.zeros((n_frames, 3))
        for ch in range(3):
            rhs[:, ch] = (np.bincount(ia, ww * dd[:, ch], n_frames)
                          - np.bincount(ib, ww * dd[:, ch], n_frames))
        x = splu(N, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                 options={"SymmetricMode": True}).solve(rhs)
        resid = np.abs((x[a] - x[b] - edges.diff).mean(1))  # [E] on the grey level
        w = base_w * _huber(resid, opts.huber_log)
        pull_w = opts.smooth_weight * _huber(np.abs((x[sa] - x[sa + 1]).mean(1)), opts.huber_log)
    x -= x.mean(0)
    linked = np.zeros(n_frames, bool)
    linked[a] = True
    linked[b] = True
    # Groups of frames that share surfaces among themselves but with no other group: their
    # gains relative to each other come from the pull alone (taken as equal where they meet).
    groups, _ = connected_components(coo_matrix(
        (np.ones(len(a)), (a, b)), shape=(n_frames, n_frames)), directed=False)
    rms = float(np.sqrt(np.sum(base_w * resid**2) / base_w.sum())) if len(a) else 0.0
    return GainSolution(np.exp(x), int(len(a)), int(linked.sum()),
                        int(groups) - int((~linked).sum()), rms,
                        int((resid > opts.huber_log).sum()))


def frames_to_solve(n_frames: int, opts: ExposureOptions) -> tuple[np.ndarray, int]:
    """Positions [K] of the frames to observe among ``n_frames`` (every ``plan`` step-th
    and the last) and the most cells each keeps."""
    step, max_cells = opts.plan(n_frames)
    return np.unique(np.r_[np.arange(0, n_frames, step), n_frames - 1]), max_cells


def solve_exposure(observations: Iterable[tuple[np.ndarray, np.ndarray]], at: np.ndarray,
                   n_frames: int, opts: ExposureOptions) -> tuple[np.ndarray, GainSolution,
                                                                  int]:
    """Gains [n_frames, 3] from the observations (cell keys, log colours) of the frames
    at positions ``at`` (``frames_to_solve``), in that order; the frames between them
    interpolated. Also the solution and the number of observations."""
    obs = ExposureObservations()
    for k, (keys, log_rgb) in enumerate(observations):
        obs.add(k, keys, log_rgb)
    if len(obs.key) != len(at):
        raise ValueError(f"solve_exposure: {len(obs.key)} frames observed for {len(at)} "
                         "positions")
    t0, c0 = time.perf_counter(), time.process_time()
    sol = solve_gains(gain_edges(*obs.arrays(), opts), len(at), opts)
    gains = spread_gains(sol.gains, at, n_frames)
    sol = replace(sol, seconds=time.perf_counter() - t0, cpu_seconds=time.process_time() - c0)
    return gains, sol, len(obs)


def spread_gains(solved: np.ndarray, at: np.ndarray, n_frames: int) -> np.ndarray:
    """Gains [n_frames, 3] of every frame from those [K, 3] solved at frames ``at`` [K]
    (increasing): log-linear between them, held beyond the ends."""
    logs = np.log(solved)
    x = np.arange(n_frames)
    return np.exp(np.stack([np.interp(x, at, logs[:, c]) for c in range(3)], 1))


def gains_from_neighbours(gains: dict[int, np.ndarray], known: Iterable[int],
                          wanted: Iterable[int]) -> dict[int, np.ndarray]:
    """Frame index -> gain [3] of the ``wanted`` frames from the ``known`` frames' gains
    alone, by ``spread_gains``'s rule (log-linear in the frame index between them, the
    nearest one's beyond the ends): the exposure of a frame whose own pixels must not
    decide it (a held-out view), predicted from its neighbours."""
    at = np.unique(np.asarray(list(known), np.int64))
    if not len(at):
        raise ValueError("gains_from_neighbours: no known frames")
    want = np.asarray(list(wanted), np.int64)
    if not len(want):
        return {}
    # spread_gains covers 0..n-1: shift so the smallest index asked for is 0
    lo = int(min(at.min(), want.min()))
    full = spread_gains(np.array([gains[int(i)] for i in at], np.float64).reshape(-1, 3),
                        at - lo, int(max(at.max(), want.max())) - lo + 1)
    return {int(i): full[int(i) - lo] for i in want}


def gain_error(solved: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """Solved gains [F, 3] (or [F]) against true gains [F] (one per frame, all channels),
    up to the common factor neither can know: RMS and max of the log ratio after removing
    its mean, as percent, and the spread of the true gains for scale."""
    s = np.log(np.asarray(solved, np.float64))
    if s.ndim == 2:
        s = s.mean(1)
    t = np.log(np.asarray(truth, np.float64))
    e = (s - t) - np.mean(s - t)
    return {"gain_error_rms_pct": float(100 * np.sqrt(np.mean(e**2))),
            "gain_error_max_pct": float(100 * np.max(np.abs(e))),
            "gain_true_spread_pct": float(100 * np.std(t))}


def corrected_image(rgb: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """The image [H, W, 3] uint8 at gain 1: each channel divided by the frame's gain [3]."""
    g = np.asarray(gain, np.float64).reshape(3)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"corrected_image: need an [H, W, 3] uint8 image, got {rgb.dtype} "
                         f"{list(rgb.shape)}")
    if rgb.size == 0:  # OpenCV returns None for no pixels (a frame with no valid depth)
        return rgb.copy()
    # OpenCV's per-channel scalar product (double precision), rounded and saturated:
    # 0.8 ms at 640x480 against 5.6 ms in float32 numpy, whose reciprocal and round-half-
    # up differ by one level at or near halves (no byte of 85 M channel values of the house
    # at its solved gains; 110 of 15 M at random gains).
    return cv2.multiply(np.ascontiguousarray(rgb), (1.0 / g[0], 1.0 / g[1], 1.0 / g[2], 0.0))


EXPOSURE_FILE = "exposure_gains.csv"


def write_exposure_gains(path: Path, frames: list[tuple[int, float]], gains: np.ndarray,
                         solved: np.ndarray | None = None) -> None:
    """``index,stamp,gain_r,gain_g,gain_b,solved`` for the frames (index, stamp), gains
    [U, 3] and whether each was solved [U] bool (else interpolated; None: all solved)."""
    sv = np.ones(len(frames), bool) if solved is None else np.asarray(solved, bool)
    atomic_write_text(path, "index,stamp,gain_r,gain_g,gain_b,solved\n" + "".join(
        f"{i},{float(t)!r},{g[0]:.6f},{g[1]:.6f},{g[2]:.6f},{int(v)}\n"
        for (i, t), g, v in zip(frames, gains, sv, strict=True)))


def read_exposure_gains(path: Path) -> dict[int, np.ndarray]:
    """Frame index -> gain [3] from a file ``write_exposure_gains`` wrote."""
    out: dict[int, np.ndarray] = {}
    with open(path, newline="") as fh:
        for n, row in enumerate(csv.DictReader(fh), start=2):
            try:
                g = np.array([float(row[f"gain_{c}"]) for c in "rgb"])
                out[int(row["index"])] = g
            except (KeyError, TypeError, ValueError) as exc:
                raise InputError(f"{path} line {n}: needs index,stamp,gain_r,gain_g,gain_b "
                                 f"({exc}); rerun the fuse stage to rewrite it") from exc
            if not (np.isfinite(g).all() and (g > 0).all()):
                raise InputError(f"{path} line {n}: gains must be positive and finite; rerun "
                                 "the fuse stage to rewrite it")
    return out


def gains_for_frames(fused: Path | None, frames: Iterable[int]) -> dict[int, np.ndarray]:
    """Frame index -> gain [3] for ``frames`` from the fuse stage folder ``fused`` (its
    ``EXPOSURE_FILE``; empty when there is none). ValueError when the file is broken or
    misses one of ``frames``: mixing corrected and raw images is worse than either."""
    path = None if fused is None else Path(fused) / EXPOSURE_FILE
    if path is None or not path.exists():
        return {}
    gains = read_exposure_gains(path)
    if not gains:
        return {}
    wanted = [int(i) for i in frames]
    missing = [i for i in wanted if i not in gains]
    if missing:
        raise InputError(f"{path} has no gain for {len(missing)} of the {len(wanted)} frames "
                         f"(first: {missing[0]}): rerun the fuse stage (it writes every "
                         "frame's), or set exposure: none here")
    return gains

"""Probability grid with Cartographer-style hit/miss odds updates.

Cells store a quantised probability in ``uint16`` (0 = never observed, 1..32767 =
probability in [p_min, p_max]) so an update is a table look-up: ``v <- table[v]``. A hit
multiplies the cell's odds by odds(p_hit), a miss by odds(p_miss), clamped to
[p_min, p_max], and every cell is updated at most once per scan (hits win over misses),
as in Cartographer's ``ProbabilityGridRangeDataInserter2D``. Scan matchers score
against ``matching_field``, a smoothed version of the grid.

The grid grows when a scan reaches past its border, so a submap never needs its extent
in advance. Indexing is ``array[row, col] = array[iy, ix]`` with cell (ix, iy) covering
``origin + res * [ix, ix + 1) x [iy, iy + 1)``.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

_N_VALUES = 32768  # uint16 values 0..32767; 0 is "unknown"
_SHIFT = 4  # cv2 fixed-point bits for sub-cell ray end points


_LUT_STEPS = 8  # field look-up table entries per cell of distance

# World -> cell treats points within this many cells of a border as on it: a border
# computed as origin + res * ix (cell -> world), or a decimal one (0.3 / 0.1 =
# 2.9999999999999996), is off by rounding (~1e-11 cells at 1e5 cells from 0) and would
# otherwise floor into the cell below.
_BORDER_TOL = 1e-9


def lattice_cells(points: np.ndarray, resolution: float) -> np.ndarray:
    """[..., 2] int64 lattice cells (ix, iy) of metric points [..., 2]: cell (ix, iy) covers
    ``res * [ix, ix + 1) x [iy, iy + 1)``, a point on a border (within rounding) is in
    the cell above it."""
    u = np.asarray(points, dtype=np.float64) / resolution  # [..., 2] in cells
    return np.floor(u + _BORDER_TOL).astype(np.int64)


@lru_cache(maxsize=8)
def _field_lut(resolution: float, sigma: float, p_min: float, p_max: float) -> np.ndarray:
    """Field value by distance in 1/_LUT_STEPS cells, out to 4 sigma."""
    n = int(np.ceil(4.0 * sigma / resolution * _LUT_STEPS)) + 2
    d = np.arange(n) / _LUT_STEPS * resolution
    f = p_min + (p_max - p_min) * np.exp(-(d**2) / (2.0 * sigma**2))
    f[-1] = p_min
    return f.astype(np.float32)


def _odds(p: np.ndarray | float) -> np.ndarray | float:
    return p / (1.0 - p)


@lru_cache(maxsize=8)
def value_tables(
    p_min: float, p_max: float, p_hit: float, p_miss: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(probability_of_value [32768] float32, hit_table, miss_table [32768] uint16).

    ``probability_of_value[0]`` is p_min: unknown cells score like free space in the
    matchers (Cartographer does the same), so a scan is never rewarded for leaving the map.
    """
    v = np.arange(_N_VALUES)
    prob = p_min + (v - 1) / (_N_VALUES - 2) * (p_max - p_min)
    prob[0] = p_min

    def to_value(p: np.ndarray) -> np.ndarray:
        p = np.clip(p, p_min, p_max)
        return (1 + np.rint((p - p_min) / (p_max - p_min) * (_N_VALUES - 2))).astype(np.uint16)

    def table(p_update: float) -> np.ndarray:
        o = _odds(prob) * _odds(p_update)
        t = to_value(o / (1.0 + o))
        t[0] = to_value(np.array([p_update]))[0]  # first observation sets p_update itself
        return t

    return prob.astype(np.float32), table(p_hit), table(p_miss)


def rasterize(resolution: float, sensor_xy: np.ndarray, hits: np.ndarray,
              free_ends: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Lattice cells (ix, iy) of one scan: unique hit cells [N, 2] and missed cells [M, 2]
    (on a ray from the sensor, not hit by this scan: hits win, each cell once)."""
    hits = np.asarray(hits, dtype=np.float64).reshape(-1, 2)
    ends = hits if free_ends is None or len(free_ends) == 0 else np.concatenate(
        [hits, np.asarray(free_ends, dtype=np.float64).reshape(-1, 2)])
    sensor_xy = np.asarray(sensor_xy, dtype=np.float64).reshape(2)
    allp = np.concatenate([ends, sensor_xy[None]])
    # cv2 draws with pixel centres at integers: cell i is pixel i after a half-cell shift.
    u_all = allp / resolution - 0.5  # [N+1, 2]
    b0 = np.floor(u_all.min(0)).astype(np.int64) - 1
    b1 = np.ceil(u_all.max(0)).astype(np.int64) + 2
    mask = np.zeros((int(b1[1] - b0[1]), int(b1[0] - b0[0])), np.uint8)
    scale = 1 << _SHIFT
    start = np.rint((u_all[-1] - b0) * scale).astype(np.int32)
    stop = np.rint((u_all[:-1] - b0) * scale).astype(np.int32)
    if len(stop):
        segs = np.empty((len(stop), 2, 2), np.int32)
        segs[:, 0] = start
        segs[:, 1] = stop
        cv2.polylines(mask, list(segs), False, 1, 1, cv2.LINE_8, _SHIFT)
    hc = lattice_cells(hits, resolution) - b0  # [N, 2] in mask coordinates
    Wm = mask.shape[1]
    key = np.unique(hc[:, 1] * Wm + hc[:, 0])
    hy, hx = np.divmod(key, Wm)
    mask[hy, hx] = 0  # hits win over misses (and a ray's last pixel is its hit cell)
    my, mx = np.nonzero(mask)
    hit_cells = np.stack([hx + b0[0], hy + b0[1]], -1)
    miss_cells = np.stack([mx + b0[0], my + b0[1]], -1)
    return hit_cells, miss_cells


class ProbabilityGrid:
    """A growing occupancy probability grid (one submap, or the final map)."""

    def __init__(
        self,
        resolution: float,
        hit_probability: float = 0.55,
        miss_probability: float = 0.49,
        min_probability: float = 0.1,
        max_probability: float = 0.9,
        center: tuple[float, float] = (0.0, 0.0),
        initial_size_m: float = 20.0,
    ) -> None:
        if not 0.0 < min_probability < 0.5 < max_probability < 1.0:
            raise ValueError("need 0 < min_probability < 0.5 < max_probability < 1")
        self.resolution = float(resolution)
        self.p_min = float(min_probability)
        self.p_max = float(max_probability)
        self._prob_of_value, self._hit_table, self._miss_table = value_tables(
            self.p_min, self.p_max, float(hit_probability), float(miss_probability)
        )
        n = max(8, int(np.ceil(initial_size_m / resolution)))
        # Every grid of a resolution shares one lattice (origin a whole number of cells),
        # so a scan is rasterised once and applied to both active submaps.
        self._offset = np.floor(np.asarray(center, dtype=np.float64) / resolution
                                - 0.5 * n).astype(np.int64)  # [2] (ix, iy) of cell (0, 0)
        self.values = np.zeros((n, n), np.uint16)  # [H, W]
        # Cells above this value are more likely occupied than free.
        self._occupied_value = int(np.searchsorted(self._prob_of_value[1:], 0.5, "right") + 1)
        self.num_scans = 0

    # ------------------------------------------------------------------ geometry

    @property
    def origin(self) -> np.ndarray:
        """[2] metric corner of cell (0, 0)."""
        return self._offset * self.resolution

    @property
    def shape(self) -> tuple[int, int]:
        H, W = self.values.shape  # numpy 1.26 types shape tuple[int, ...]: unpacked, not cast
        return H, W

    def cell_of(self, points: np.ndarray) -> np.ndarray:
        """[N, 2] int (ix, iy) cell of metric points [N, 2] (may lie outside the grid); a
        point on a border (within rounding) is in the cell whose corner it is."""
        return lattice_cells(points, self.resolution) - self._offset

    def observed(self, points: np.ndarray) -> np.ndarray:
        """[N] bool: whether the cell under each metric point [N, 2] was ever observed (hit
        or missed); points outside the grid were not."""
        c = self.cell_of(np.asarray(points, dtype=np.float64).reshape(-1, 2))
        H, W = self.values.shape
        inside = (c[:, 0] >= 0) & (c[:, 1] >= 0) & (c[:, 0] < W) & (c[:, 1] < H)
        out = np.zeros(len(c), bool)
        out[inside] = self.values[c[inside, 1], c[inside, 0]] > 0
        return out

    def _grow(self, c0: np.ndarray, c1: np.ndarray) -> None:
        """Enlarge so that lattice cells [c0, c1) (ix, iy) fit, with slack so growth is rare."""
        H, W = self.values.shape
        lo = c0 - self._offset
        hi = c1 - self._offset
        if lo[0] >= 0 and lo[1] >= 0 and hi[0] <= W and hi[1] <= H:
            return
        # Grow by at least half the current size on a side that overflows (amortised).
        px0 = max(int(-lo[0]), W // 2) if lo[0] < 0 else 0
        py0 = max(int(-lo[1]), H // 2) if lo[1] < 0 else 0
        px1 = max(int(hi[0] - W), W // 2) if hi[0] > W else 0
        py1 = max(int(hi[1] - H), H // 2) if hi[1] > H else 0
        self.values = np.pad(self.values, ((py0, py1), (px0, px1)))
        self._offset = self._offset - np.array([px0, py0])

    # ------------------------------------------------------------------ insertion

    def insert(
        self, sensor_xy: np.ndarray, hits: np.ndarray, free_ends: np.ndarray | None = None
    ) -> None:
        """Insert one scan given in the grid frame.

        sensor_xy: [2] ray origin. hits: [N, 2] beam end points (hit + free space before).
        free_ends: [M, 2] end points of rays without a return (free space only).
        """
        self.apply(*rasterize(self.resolution, sensor_xy, hits, free_ends))

    def apply(self, hit_cells: np.ndarray, miss_cells: np.ndarray) -> None:
        """Apply one scan's updates: unique lattice cells [N, 2] hit and [M, 2] missed."""
        allc = np.concatenate([hit_cells, miss_cells]) if len(miss_cells) else hit_cells
        if len(allc):
            self._grow(allc.min(0), allc.max(0) + 1)
        W = self.values.shape[1]
        vflat = self.values.reshape(-1)
        if len(miss_cells):
            m = (miss_cells[:, 1] - self._offset[1]) * W + (miss_cells[:, 0] - self._offset[0])
            vflat[m] = self._miss_table[vflat[m]]
        if len(hit_cells):
            h = (hit_cells[:, 1] - self._offset[1]) * W + (hit_cells[:, 0] - self._offset[0])
            vflat[h] = self._hit_table[vflat[h]]
        self.num_scans += 1

    # ------------------------------------------------------------------ views

    def probability(self) -> np.ndarray:
        """[H, W] float32 probabilities (unknown = p_min)."""
        return self._prob_of_value[self.values]

    def matching_field(self, sigma: float, lo: np.ndarray | None = None,
                       hi: np.ndarray | None = None,
                       unknown: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(field [h, w] float32, origin [2]) that scan matchers score against.

        ``p_min + (p_max - p_min) * exp(-d^2 / (2 sigma^2))`` with d the distance to the
        nearest cell that is more likely occupied than free: a smoothed probability grid.
        Scoring the raw grid favours poses that put a scan on often-seen walls; when scans
        are far apart (a metre, tens of degrees) the walls ahead of the robot were only
        grazed by earlier beams, and in corridors the raw score then prefers a pose
        metres behind the true one. The distance field scores every observed wall alike
        and gives the continuous refinement a basin of a few cells. ``lo``/``hi`` (ix, iy)
        crop the computation to where a scan can land. ``unknown``: never-observed cells
        score at least this (None: like free space, p_min).
        """
        H, W = self.values.shape
        lo = np.zeros(2, int) if lo is None else np.clip(np.asarray(lo), 0, [W, H])
        hi = np.array([W, H]) if hi is None else np.clip(np.asarray(hi), lo, [W, H])
        v = self.values[lo[1] : hi[1], lo[0] : hi[0]]
        free = (v < self._occupied_value).astype(np.uint8)
        origin = self.origin + lo * self.resolution
        if free.size == 0:
            fill = self.p_min if unknown is None else max(self.p_min, unknown)
            return np.full((1, 1), fill, np.float32), origin
        d = cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_5)  # [h, w] in cells
        lut = _field_lut(self.resolution, sigma, self.p_min, self.p_max)
        # With no occupied cell in the window OpenCV gives a distance near float32's
        # top, whose product overflows to inf: the table's last entry all the same.
        with np.errstate(over="ignore"):
            idx = np.minimum(d * _LUT_STEPS, len(lut) - 1).astype(np.int32)
        field = lut[idx]  # [h, w]
        if unknown is not None and unknown > self.p_min:
            # A point on a never-observed cell is not evidence against the pose, as one on
            # observed free space is: scored alike, a pose that pulls a newly seen wall back
            # onto the mapped part wins (a scan slides backwards along a corridor).
            unseen = v == 0
            field[unseen] = np.maximum(field[unseen], np.float32(unknown))
        return field, origin

    def occupancy(self, lo: np.ndarray | None = None, hi: np.ndarray | None = None) -> (
            np.ndarray):
        """[h, w] float32 occupancy probability with NaN for never-observed cells, of the
        cells ``lo`` to ``hi`` (ix, iy; hi exclusive; default the whole grid)."""
        H, W = self.values.shape
        lo = np.zeros(2, int) if lo is None else np.clip(np.asarray(lo), 0, [W, H])
        hi = np.array([W, H]) if hi is None else np.clip(np.asarray(hi), lo, [W, H])
        v = self.values[lo[1] : hi[1], lo[0] : hi[0]]
        p = self._prob_of_value[v].astype(np.float32, copy=False)  # a new array either way
        p[v == 0] = np.nan
        return p

    def known_bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(lo, hi) cell index bounds [2] (ix, iy) of observed cells, hi exclusive."""
        rows = np.flatnonzero(self.values.any(axis=1))
        if len(rows) == 0:
            return None
        cols = np.flatnonzero(self.values.any(axis=0))
        return np.array([cols[0], rows[0]]), np.array([cols[-1] + 1, rows[-1] + 1])

    def finish(self, margin_cells: int = 2) -> None:
        """Crop to the observed cells (finished submaps are many and never grow again)."""
        b = self.known_bounds()
        if b is not None:
            lo = np.maximum(b[0] - margin_cells, 0)
            hi = np.minimum(b[1] + margin_cells, [self.values.shape[1], self.values.shape[0]])
            self.values = np.ascontiguousarray(self.values[lo[1] : hi[1], lo[0] : hi[0]])
            self._offset = self._offset + lo

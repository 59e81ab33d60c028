"""Frames fused into one voxel map: per-voxel mean position and colour, observation counts.

Each voxel keeps sums (position, colour, an optional label such as ground-truth "dynamic"),
its point count, the number of frames that saw it and the first/last of those frames.
Frames are reduced to their own voxels as they come and merged into the map in batches,
so integration stays O(points) per frame (a dict per voxel would be 100x slower in
Python, and Open3D's ``voxel_down_sample`` cannot accumulate counts across calls; Open3D's
tensor ``HashMap`` took 12 ms to look up a frame's 30 k voxels, more than this whole map).

The voxels' values live in rows appended as voxels appear; a sorted key array with each
key's row finds them. A batch's new voxels are inserted into that index only (16 bytes a
voxel moved per batch instead of all 88 of its values): with the values kept in key order,
inserting made every batch cost O(map) - 10.6 ms a frame on the quickstart's 644 frames.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from toolkit.errors import InputError

_BITS = 21
_OFFSET = 1 << (_BITS - 1)  # voxel indices in [-2^20, 2^20): +-21 km at 2 cm
_MASK = (1 << _BITS) - 1
KEY_RANGE_VOXELS = _OFFSET  # points within this many voxels of the origin can be keyed


def voxel_keys(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """[N] int64 key of the voxel holding each point [N, 3]."""
    return pack_key_columns(voxel_index_columns(points, voxel_size), [_BITS] * 3)


def pack_key_columns(cols: list[np.ndarray], bits: list[int]) -> np.ndarray:
    """[N] int64 keys packing the non-negative integer columns ``cols`` (each [N] int64,
    the first the most significant), column k taking ``bits[k]`` bits."""
    shifts = np.cumsum([0] + bits[:0:-1])[::-1]  # [K] bits below each column
    keys = cols[0] << int(shifts[0])
    for c, sh in zip(cols[1:], shifts[1:], strict=True):
        keys = keys | (c << int(sh))
    return keys


def voxel_index_columns(points: np.ndarray, voxel_size: float) -> list[np.ndarray]:
    """The voxel indices x, y, z ([N] int64 each, offset to be non-negative) that
    ``voxel_keys`` packs, column by column (contiguous, for ``KeyTable``)."""
    pts = np.asarray(points)
    cols = [np.floor(pts[:, k].astype(np.float64) / voxel_size).astype(np.int64) + _OFFSET
            for k in range(3)]
    if len(pts) and (min(int(c.min()) for c in cols) < 0
                     or max(int(c.max()) for c in cols) > _MASK):
        raise ValueError(f"points beyond +-{_OFFSET * voxel_size:.0f} m cannot be keyed")
    return cols


class KeyTable:
    """Sorted unique keys of a frame's points and each point's index among them, as
    ``np.unique(keys, return_inverse=True)`` gives them, without sorting the points: a table
    over the points' bounding box marks the occupied cells, and reading it in order gives
    the keys sorted. A frame's box is small (at 2 cm a median 2 M voxels for 52 k points);
    its 56 k keys took 2.7 ms to sort, the table 0.4 ms. Boxes larger than ``max_cells``,
    or than ``cells_per_point`` cells a point, are sorted as before.

    The arrays stay allocated between frames: fresh ones cost more in page faults than the
    work on them."""

    def __init__(self, max_cells: int = 1 << 23, cells_per_point: int = 256) -> None:
        self.max_cells = max_cells
        self.cells_per_point = cells_per_point
        self._seen = np.zeros(0, bool)  # all False between calls
        self._slot = np.zeros(0, np.int32)  # scratch: read only where just written

    def __getstate__(self) -> dict[str, object]:
        # Scratch space: a pickle (a checkpoint) holds the settings alone.
        return {"max_cells": self.max_cells, "cells_per_point": self.cells_per_point}

    def __setstate__(self, state: dict[str, object]) -> None:
        self.__init__(**state)  # type: ignore[misc]

    def unique(self, cols: list[np.ndarray], bits: list[int]) -> tuple[np.ndarray,
                                                                         np.ndarray]:
        """(sorted unique keys [M] int64, inverse [N] int) of the keys that pack the
        non-negative integer columns ``cols`` (each [N] int64, the first the most
        significant), column k taking ``bits[k]`` bits."""
        n = len(cols[0])
        lo = [int(c.min()) for c in cols] if n else []
        span = [int(c.max()) - a + 1 for c, a in zip(cols, lo, strict=False)]
        cells = float(np.prod(span, dtype=np.float64))
        if not n or cells > min(self.max_cells, self.cells_per_point * n):
            uk, inv = np.unique(pack_key_columns(cols, bits), return_inverse=True)
            return uk, inv
        shifts = np.cumsum([0] + bits[:0:-1])[::-1]  # [K] bits below each column
        # Mixed-radix cell index in the box, in the keys' order (the first column slowest).
        at = cols[0] - lo[0]
        for c, a, sp in zip(cols[1:], lo[1:], span[1:], strict=True):
            at = at * sp + (c - a)
        size = int(cells)
        if len(self._seen) < size:
            self._seen = np.zeros(max(size, len(self._seen) * 3 // 2), bool)
            self._slot = np.empty(len(self._seen), np.int32)
        self._seen[at] = True
        occupied = np.flatnonzero(self._seen[:size])  # [M] sorted
        self._seen[occupied] = False
        self._slot[occupied] = np.arange(len(occupied), dtype=np.int32)
        inv = self._slot[at]
        # The occupied cells' keys, unpacked from the box index, last column first.
        uk = np.zeros(len(occupied), np.int64)
        rest = occupied
        for k in range(len(cols) - 1, -1, -1):
            rest, digit = np.divmod(rest, span[k])
            uk |= (digit + lo[k]) << int(shifts[k])
        return uk, inv


def unique_voxels(points: np.ndarray, voxel_size: float,
                  table: KeyTable | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(voxel_keys(points, voxel_size), return_inverse=True)`` of points [N, 3]
    (sorted keys [M] and inverse [N]), through ``table`` (None: a fresh one)."""
    return (table or KeyTable()).unique(voxel_index_columns(points, voxel_size), [_BITS] * 3)


def key_centres(keys: np.ndarray, voxel_size: float) -> np.ndarray:
    """[N, 3] centres of voxels with ``keys`` [N]."""
    q = np.stack([(keys >> (2 * _BITS)) & _MASK, (keys >> _BITS) & _MASK, keys & _MASK], -1)
    return (q - _OFFSET + 0.5) * voxel_size


@dataclass
class MapArrays:
    """The map as flat arrays (one row per voxel)."""

    points: np.ndarray  # [V, 3] float64 mean position
    colors: np.ndarray  # [V, 3] uint8 mean colour
    count: np.ndarray  # [V] int64 points that fell in the voxel
    frames: np.ndarray  # [V] int32 frames that saw it
    first: np.ndarray  # [V] int32 first frame index
    last: np.ndarray  # [V] int32 last frame index
    label: np.ndarray  # [V] float32 mean label (e.g. fraction of ground-truth dynamic points)
    # [V] float32 camera depth of the nearest frame that saw the voxel (inf: not recorded)
    near: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.points)

    def select(self, mask: np.ndarray) -> MapArrays:
        return MapArrays(*(getattr(self, f)[mask] for f in
                           ("points", "colors", "count", "frames", "first", "last", "label")),
                         near=None if self.near is None else self.near[mask])


class VoxelMap:
    """Accumulates coloured points into voxels of ``voxel_size`` metres."""

    def __init__(self, voxel_size: float = 0.02, batch_entries: int = 1_000_000) -> None:
        if voxel_size <= 0:
            raise ValueError("voxel_size must be positive")
        self.voxel_size = float(voxel_size)
        self.batch_entries = batch_entries
        self._keys = np.zeros(0, np.int64)  # [V] sorted keys of the map's voxels
        self._row = np.zeros(0, np.int64)  # [V] each sorted key's row in the value arrays
        self._n = 0  # value rows in use (the arrays have room for more)
        # Sums x y z r g b label as 7 rows: gathers and updates by voxel row are 1-D, which
        # numpy does several times faster than picking rows of an [N, 7] array.
        self._sums = np.zeros((7, 0), np.float64)
        self._count = np.zeros(0, np.int64)
        self._frames = np.zeros(0, np.int32)
        self._first = np.zeros(0, np.int32)
        self._last = np.zeros(0, np.int32)
        self._near = np.zeros(0, np.float32)
        # Frames reduced to their voxels, waiting for the next merge: the first _pending_n
        # entries of arrays kept from batch to batch (keys, sums x y z r g b label, points,
        # frame, mean depth): concatenating each batch's frames anew was 0.4 of the 1.6 s
        # of merges on the paper benchmark's fuse_net.
        self._no_pending()
        self.frames_integrated = 0
        self._table = KeyTable()  # each frame's voxels

    def integrate(self, points: np.ndarray, colors: np.ndarray, frame: int,
                  labels: np.ndarray | None = None, depths: np.ndarray | None = None,
                  weights: np.ndarray | None = None) -> None:
        """Add one frame's points [N, 3], colours [N, 3] uint8, optional labels [N], the
        points' camera depths [N] (the voxel keeps the nearest frame's mean depth) and
        integer weights [N] (a point standing for several pixels counts as many)."""
        self._check_held()
        if np.asarray(colors).dtype != np.uint8:
            # Colours in 0..1 were averaged as they came and written as black.
            raise ValueError(f"colours must be uint8 0..255, got {np.asarray(colors).dtype}: "
                             "(np.clip(c * 255, 0, 255) + 0.5).astype(np.uint8) for 0..1")
        if len(points) == 0:
            self.frames_integrated += 1
            return
        uk, inv = unique_voxels(points, self.voxel_size, self._table)
        m = len(uk)
        a, b = self._pending_n, self._pending_n + m
        # Growing by half stops at the batch size: the buffer never holds more than a batch
        # and the frame that fills it (1.48 M entries of room, 113 MiB, on the quickstart).
        self._grow(self._PENDING, a, b, limit=self.batch_entries)
        self._p_keys[a:b] = uk
        # Sums stored column by column ([7, m], x y z r g b label): the batch merge adds them
        # with one bincount per column instead of permuting an [n, 7] array.
        sums = self._p_sums[:, a:b]
        w = None if weights is None else np.asarray(weights, np.float64)
        for c in range(3):
            sums[c] = np.bincount(inv, points[:, c] if w is None else w * points[:, c], m)
            sums[3 + c] = np.bincount(inv, colors[:, c] if w is None else w * colors[:, c], m)
        if labels is None:
            sums[6] = 0.0
        else:
            sums[6] = np.bincount(inv, labels if w is None else w * labels, m)
        cnt = (np.bincount(inv, minlength=m) if w is None else np.rint(
            np.bincount(inv, w, m))).astype(np.int64)
        self._p_count[a:b] = cnt
        self._p_frame[a:b] = frame
        if depths is None:
            self._p_near[a:b] = np.inf
        else:
            # The frame's mean depth in the voxel: a 2 cm voxel spans a few cm of depth at
            # most, and bincount is far cheaper than a per-voxel minimum.
            self._p_near[a:b] = np.bincount(inv, depths if w is None else w * depths, m) / cnt
        self._pending_n = b
        self.frames_integrated += 1
        if self._pending_n >= self.batch_entries:
            self._merge()

    def _merge(self) -> None:
        n = self._pending_n
        if not n:
            return
        keys = self._p_keys[:n]
        order = np.argsort(keys, kind="stable")
        ks = keys[order]
        head = np.r_[True, ks[1:] != ks[:-1]]
        start = np.flatnonzero(head)
        uk = ks[start]  # sorted unique keys of the batch
        m = len(uk)
        grp = np.empty(n, np.int64)  # batch voxel of every pending entry
        grp[order] = np.cumsum(head) - 1
        del ks, head
        # Additive fields by bincount (no permutation of the big arrays); min/max fields,
        # 1-D and small, by reduceat in sorted order.
        sums = np.empty((7, m), np.float64)
        for c in range(7):
            sums[c] = np.bincount(grp, self._p_sums[c, :n], m)
        cnt = np.bincount(grp, self._p_count[:n], m).astype(np.int64)
        nfr = np.bincount(grp, minlength=m).astype(np.int32)  # a frame's voxels are unique
        frame = self._p_frame[:n][order]
        first = np.minimum.reduceat(frame, start)
        last = np.maximum.reduceat(frame, start)
        near = np.minimum.reduceat(self._p_near[:n][order], start)
        self._pending_n = 0
        # Voxels already in the map are updated in their rows; new ones get rows at the
        # end and their keys go into the sorted index.
        pos = np.searchsorted(self._keys, uk)
        old = pos < len(self._keys)
        old[old] = self._keys[pos[old]] == uk[old]
        g = self._row[pos[old]]
        for c in range(7):
            self._sums[c, g] += sums[c, old]
        self._count[g] += cnt[old]
        self._frames[g] += nfr[old]
        self._first[g] = np.minimum(self._first[g], first[old])
        self._last[g] = np.maximum(self._last[g], last[old])
        self._near[g] = np.minimum(self._near[g], near[old])
        new = ~old
        k = int(new.sum())
        if k:
            self._reserve(self._n + k)
            rows = slice(self._n, self._n + k)
            self._sums[:, rows] = sums[:, new]
            self._count[rows] = cnt[new]
            self._frames[rows] = nfr[new]
            self._first[rows] = first[new]
            self._last[rows] = last[new]
            self._near[rows] = near[new]
            at = pos[new]
            self._keys = np.insert(self._keys, at, uk[new])
            self._row = np.insert(self._row, at, np.arange(self._n, self._n + k))
            self._n += k

    def _no_pending(self) -> None:
        self._pending_n = 0
        self._p_keys = np.zeros(0, np.int64)
        self._p_sums = np.zeros((7, 0), np.float64)
        self._p_count = np.zeros(0, np.int64)
        self._p_frame = np.zeros(0, np.int32)
        self._p_near = np.zeros(0, np.float32)

    _VALUES = ("_sums", "_count", "_frames", "_first", "_last", "_near")
    _PENDING = ("_p_keys", "_p_sums", "_p_count", "_p_frame", "_p_near")

    def _reserve(self, rows: int) -> None:
        """Room for ``rows`` value rows."""
        self._grow(self._VALUES, self._n, rows)

    def _grow(self, names: tuple[str, ...], used: int, rows: int,
              limit: int | None = None) -> None:
        """Room for ``rows`` entries in the arrays ``names`` (the entry axis last), of which
        the first ``used`` are kept; growing by half, so appending is amortised O(1), but
        to no more than ``limit`` entries beyond ``rows`` (None: no limit)."""
        have = getattr(self, names[0]).shape[-1]
        if rows <= have:
            return
        spare = max(have * 3 // 2, 1024)
        cap = max(rows, spare if limit is None else min(spare, limit))
        for name in names:
            old = getattr(self, name)
            grown = np.empty((*old.shape[:-1], cap), old.dtype)
            grown[..., :used] = old[..., :used]
            setattr(self, name, grown)

    def __getstate__(self) -> dict[str, object]:
        # A checkpoint holds the rows in use, not the spare room (pending frames stay
        # pending: merging them early would change the order of the float sums).
        state = self.__dict__.copy()
        for names, used in ((self._VALUES, self._n), (self._PENDING, self._pending_n)):
            for name in names:
                state[name] = state[name][..., :used]  # pickle writes only the view's data
        return state

    def __setstate__(self, state: dict[str, object]) -> None:
        state = dict(state)
        # Checkpoints from before the key table and the pending arrays: a list of frames.
        parts = state.pop("_pending", None)
        self.__dict__.update(state)
        if "_table" not in state:
            self._table = KeyTable()
        if parts is not None:
            self._no_pending()
            for uk, sums, cnt, _, frame, _, near in parts:
                a, b = self._pending_n, self._pending_n + len(uk)
                self._grow(self._PENDING, a, b)
                self._p_keys[a:b], self._p_sums[:, a:b], self._p_count[a:b] = uk, sums, cnt
                self._p_frame[a:b], self._p_near[a:b] = frame, near
                self._pending_n = b

    def __len__(self) -> int:
        self._check_held()
        self._merge()
        return len(self._keys)

    def release(self) -> None:
        """Drop the map's arrays once its ``arrays`` have been taken for the last time. At
        the end of a long fusion they are the largest thing held (values, key index and
        batch buffer: 0.36 GB at 2.4 M voxels), and finishing the map needs memory of its
        own. The map cannot be used after it."""
        voxel_size, batch_entries = self.voxel_size, self.batch_entries
        self.__dict__.clear()
        self.voxel_size, self.batch_entries = voxel_size, batch_entries
        self._released = True

    def _check_held(self) -> None:
        if self.__dict__.get("_released", False):
            raise RuntimeError("the voxel map was released (VoxelMap.release, called by "
                               "Fusion.finish): it holds no voxels any more")

    def arrays(self, min_count: int = 1, min_frames: int = 1) -> MapArrays:
        """The map, keeping voxels with at least ``min_count`` points and ``min_frames``
        frames."""
        self._check_held()
        self._merge()
        # The batch buffer is empty now, and its room (1 M entries or more, 80 bytes each)
        # is freed before the copy below: at the end of a fusion it was beside the map's own
        # arrays and the copy, at the fuse stage's peak. The next frame makes room again.
        self._no_pending()
        rows = self._row  # in key order: the map's voxels sorted by their keys
        if min_count > 1 or min_frames > 1:  # every voxel has >= 1 of both
            rows = rows[(self._count[rows] >= min_count) & (self._frames[rows] >= min_frames)]
        count = self._count[rows]
        c = count.astype(np.float64)
        # One sum row at a time, the same divisions as on all seven at once: the [7, V]
        # gather and its quotients took 89 bytes a voxel beyond the result, at the fuse
        # stage's peak (the map still holds its own arrays then); now 8.
        pts = np.empty((len(rows), 3))  # [V, 3]
        col = np.empty((len(rows), 3), np.uint8)  # [V, 3]
        for k in range(3):
            pts[:, k] = self._sums[k, rows] / c
            col[:, k] = np.clip(np.rint(self._sums[3 + k, rows] / c), 0, 255)
        label = (self._sums[6, rows] / c).astype(np.float32)
        return MapArrays(pts, col, count, self._frames[rows], self._first[rows],
                         self._last[rows], label, self._near[rows])


def statistical_inliers(points: np.ndarray, nb_neighbors: int = 20,
                        std_ratio: float = 2.0) -> np.ndarray:
    """[N] bool: Open3D's statistical outlier removal (mean neighbour distance within
    ``std_ratio`` standard deviations of the global mean)."""
    import open3d as o3d

    keep = np.zeros(len(points), bool)
    if len(points) <= nb_neighbors:
        keep[:] = True
        return keep
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    _, idx = pc.remove_statistical_outlier(nb_neighbors=nb_neighbors, std_ratio=std_ratio)
    keep[np.asarray(idx, dtype=np.int64)] = True
    return keep


def write_points_ply(path: Path, points: np.ndarray, colors: np.ndarray,
                     **per_point: np.ndarray) -> None:
    """Binary PLY of points [N, 3] (float32 x y z), colours [N, 3] (uchar red green blue)
    and int32 per-point properties (count=..., frames=...), written atomically: common
    viewers read positions and colours, ``read_map_ply`` reads it back."""
    from plyfile import PlyData, PlyElement

    from toolkit.io.atomic import atomic_path

    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"),
              ("blue", "u1")] + [(name, "<i4") for name in per_point]
    v = np.empty(len(points), dtype=fields)
    for k, axis in enumerate("xyz"):
        v[axis] = points[:, k]
    for k, channel in enumerate(("red", "green", "blue")):
        v[channel] = colors[:, k]
    for name, values in per_point.items():
        v[name] = np.clip(values, -(2**31), 2**31 - 1)
    with atomic_path(path) as tmp:
        PlyData([PlyElement.describe(v, "vertex")], text=False, byte_order="<").write(str(tmp))


def write_map_ply(path: Path, m: MapArrays) -> None:
    """The map as PLY: x y z, red green blue and per-voxel count / frames."""
    write_points_ply(path, m.points, m.colors, count=m.count, frames=m.frames)


def read_map_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Positions [N, 3] float64 and colours [N, 3] uint8 (grey where it has none) of a map
    PLY.

    Read with plyfile rather than Open3D: the splat stage reads the map too, and on a GPU
    machine set up for training it needs nothing else of Open3D's. Raises ValueError naming
    the file for one that is not a readable point cloud PLY.
    """
    from plyfile import PlyData

    try:
        ply = PlyData.read(str(path))
    except Exception as e:  # noqa: BLE001 - plyfile raises several kinds, none naming the file
        raise InputError(f"{path}: not a readable PLY file ({type(e).__name__}: {e}); rerun "
                         "the fuse stage to write it again") from e
    v = ply["vertex"].data if "vertex" in ply else None
    names = set(v.dtype.names or ()) if v is not None else set()
    if not {"x", "y", "z"} <= names:
        raise InputError(f"{path}: no vertex x, y, z properties; not a point cloud PLY")
    pts = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)  # [N, 3]
    if {"red", "green", "blue"} <= names:
        col = np.stack([v["red"], v["green"], v["blue"]], axis=1)  # [N, 3]
        if col.dtype.kind == "f":  # 0..1 floats
            col = np.rint(np.clip(col, 0.0, 1.0) * 255)
        col = np.clip(col, 0, 255).astype(np.uint8)
    else:  # no colours: mid grey
        col = np.full((len(pts), 3), 128, np.uint8)
    return pts, col

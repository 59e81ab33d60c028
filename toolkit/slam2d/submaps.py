"""Submaps: probability grids built from a fixed number of consecutive scans.

As in Cartographer, two submaps are active at a time: every scan goes into both, scans
are matched against the older one (which holds more data), and when the newer one has
``num_range_data`` scans a third is started and the oldest is finished (it then holds
``2 * num_range_data`` scans). Finished submaps never change again; they are what loop
closure searches. A submap's grid lives in the local SLAM frame; its pose in the local
frame is the translation of the scan that started it (rotation zero), and the pose graph
estimates its pose in the world frame.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from toolkit.slam2d.grid import ProbabilityGrid, rasterize
from toolkit.slam2d.matcher import GridPyramid


@dataclass
class Submap:
    index: int
    local_pose: np.ndarray  # [3] pose of the submap frame in the local SLAM frame
    grid: ProbabilityGrid
    nodes: list[int] = field(default_factory=list)  # scan nodes inserted
    finished: bool = False
    vertex: int = -1  # pose-graph vertex


class ActiveSubmaps:
    """The two submaps local SLAM inserts into; finishes the oldest when a new one starts."""

    def __init__(self, num_range_data: int, grid_kwargs: dict) -> None:
        if num_range_data < 1:
            raise ValueError("num_range_data must be >= 1")
        self.num_range_data = int(num_range_data)
        self.grid_kwargs = dict(grid_kwargs)
        self.all: list[Submap] = []
        self.active: list[Submap] = []

    @property
    def matching(self) -> Submap | None:
        """The submap scans are matched against: the oldest active one."""
        return self.active[0] if self.active else None

    def insert(self, node: int, sensor_local: np.ndarray, hits_local: np.ndarray,
               free_local: np.ndarray, scan_local_pose: np.ndarray) -> tuple[
                   list[Submap], list[Submap]]:
        """Insert a scan (already in the local frame) into the active submaps.

        Returns (submaps inserted into, submaps finished by this insertion). A new submap
        is started *before* inserting when the newest one is full, so the scan that starts
        a submap is its first one (its pose anchors the submap).
        """
        finished: list[Submap] = []
        if not self.active or self.active[-1].grid.num_scans >= self.num_range_data:
            origin = np.array([scan_local_pose[0], scan_local_pose[1], 0.0])
            sm = Submap(len(self.all), origin,
                        ProbabilityGrid(center=(origin[0], origin[1]), **self.grid_kwargs))
            self.all.append(sm)
            self.active.append(sm)
            if len(self.active) > 2:
                old = self.active.pop(0)
                old.finished = True
                old.grid.finish()
                finished.append(old)
        cells = rasterize(self.active[0].grid.resolution, sensor_local, hits_local, free_local)
        for sm in self.active:
            sm.grid.apply(*cells)
            sm.nodes.append(node)
        return list(self.active), finished

    def finish_all(self) -> list[Submap]:
        """Finish the active submaps (end of the log)."""
        out = []
        for sm in self.active:
            sm.finished = True
            sm.grid.finish()
            out.append(sm)
        self.active = []
        return out


class PyramidCache:
    """LRU cache of the search pyramid and float grid of finished submaps (both large)."""

    def __init__(self, sigma: float, max_bytes: int = 400 << 20) -> None:
        self.sigma = float(sigma)
        self.max_bytes = int(max_bytes)
        self._items: OrderedDict[int, tuple[GridPyramid, np.ndarray]] = OrderedDict()
        self._bytes = 0
        self.builds = 0

    def get(self, submap: Submap, depth: int, window_cells: int) -> tuple[
            GridPyramid, np.ndarray]:
        """(pyramid, matching field [H, W] float32) of a finished submap; the field shares
        the grid's origin."""
        item = self._items.get(submap.index)
        if item is not None and item[0].depth >= depth and item[0].window_cells >= window_cells:
            self._items.move_to_end(submap.index)
            return item
        if item is not None:
            self._bytes -= item[0].nbytes + item[1].nbytes
            del self._items[submap.index]
        prob, origin = submap.grid.matching_field(self.sigma)
        pyr = GridPyramid(prob, origin, submap.grid.resolution, depth,
                          submap.grid.p_min, window_cells)
        self.builds += 1
        self._items[submap.index] = (pyr, prob)
        self._bytes += pyr.nbytes + prob.nbytes
        while self._bytes > self.max_bytes and len(self._items) > 1:
            _, old = self._items.popitem(last=False)
            self._bytes -= old[0].nbytes + old[1].nbytes
        return pyr, prob

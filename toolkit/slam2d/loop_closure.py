"""Loop-closure constraints: search finished submaps for the scans of new nodes.

As Cartographer's ``ConstraintBuilder2D``: a node is tried against every finished submap
whose centre lies within ``max_constraint_distance_m`` of it (by the current global
estimate), a fixed fraction of those pairs (``sampling_ratio``, deterministic per
submap) is searched with branch-and-bound over a window around the estimated relative
pose, and a match scoring at least ``min_score`` is refined on the interpolated grid and
becomes a constraint ``submap -> node``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from toolkit.geometry import se2_between, se2_compose, se2_to_matrix, transform_points
from toolkit.slam2d.config import LoopClosureOptions
from toolkit.slam2d.matcher import (
    GridPyramid,
    correlative_search,
    interpolate,
    normal_spread,
    refine,
    weak_direction,
)
from toolkit.slam2d.submaps import PyramidCache, Submap

if TYPE_CHECKING:
    from toolkit.slam2d.slam import Node


@dataclass
class Closure:
    relative_pose: np.ndarray  # [3] node pose in the submap frame
    score: float  # branch-and-bound score
    refined_score: float
    # Least fall of the match score over +-0.2 m in any direction; inf when the node's
    # scan has surfaces every way (not computed: the test is for featureless scans).
    weak_drop: float


class LoopCloser:
    def __init__(self, options: LoopClosureOptions, resolution: float, sigma: float) -> None:
        self.options = options
        self.resolution = float(resolution)
        self.cache = PyramidCache(sigma)
        self._centres: dict[int, np.ndarray] = {}  # submap -> centre in its own frame [2]
        self._pulses: dict[int, int] = {}
        self._samples: dict[int, int] = {}
        self._searched: dict[int, int] = {}  # by submap
        self._closures: dict[int, int] = {}
        self.searches = 0
        self.wide_searches = 0  # with the wide window (the expensive ones)
        self.found = 0
        self.ambiguous = 0  # found, rejected: as good a match elsewhere
        self.seconds = 0.0
        o = options
        self._w_cells = int(np.ceil(o.linear_window_m / resolution))
        self._depth = min(o.branch_and_bound_depth,
                          max(0, int(np.floor(np.log2(max(self._w_cells, 1)))) - 1))

    def on_submap_finished(self, submap: Submap, nodes: list[Node]) -> None:
        """Remember where the submap's scans were (its centre, in the submap frame)."""
        pts = np.array([nodes[i].local_pose[:2] for i in submap.nodes])
        self._centres[submap.index] = pts.mean(0) - submap.local_pose[:2]

    def saturated(self, submap: int) -> bool:
        """The submap has had its share of searches or closures (not searched again)."""
        o = self.options
        return bool(
            (o.max_searches_per_submap and
             self._searched.get(submap, 0) >= o.max_searches_per_submap)
            or (o.max_closures_per_submap and
                self._closures.get(submap, 0) >= o.max_closures_per_submap))

    def _sample(self, submap: int) -> bool:
        p = self._pulses.get(submap, 0) + 1
        s = self._samples.get(submap, 0)
        self._pulses[submap] = p
        if s / p < self.options.sampling_ratio:  # Cartographer's FixedRatioSampler
            self._samples[submap] = s + 1
            return True
        return False

    def maybe_search(self, node: Node, submap: Submap, submap_global: np.ndarray,
                     node_global: np.ndarray, force: bool = False) -> Closure | None:
        o = self.options
        centre = self._centres.get(submap.index)
        if centre is None or self.saturated(submap.index):
            return None
        c, s = np.cos(submap_global[2]), np.sin(submap_global[2])
        centre_g = submap_global[:2] + np.array([c * centre[0] - s * centre[1],
                                                 s * centre[0] + c * centre[1]])
        if np.hypot(*(node_global[:2] - centre_g)) > o.max_constraint_distance_m:
            return None
        if not force and not self._sample(submap.index):
            return None
        # Nodes a short way (in the node sequence) before or after the submap's own have
        # drifted little relative to it; the others get the wide window.
        gap = max(node.index - submap.nodes[-1], submap.nodes[0] - node.index)
        recent = gap <= o.recent_nodes
        return self.search(node, submap, se2_between(submap_global, node_global), recent)

    def search(self, node: Node, submap: Submap, relative_guess: np.ndarray,
               recent: bool = False) -> Closure | None:
        """Branch-and-bound around ``relative_guess`` (node in submap frame), then refine."""
        o = self.options
        lin = o.recent_linear_window_m if recent else o.linear_window_m
        ang = o.recent_angular_window_deg if recent else o.angular_window_deg
        t0 = time.perf_counter()
        self.searches += 1
        self.wide_searches += not recent
        self._searched[submap.index] = self._searched.get(submap.index, 0) + 1
        pyr, prob = self.cache.get(submap, self._depth, self._w_cells)
        guess = se2_compose(submap.local_pose, relative_guess)  # grid (local) coordinates
        found = correlative_search(
            pyr, node.match_points, guess, lin, np.radians(ang),
            np.radians(o.angular_step_deg), min_score=o.min_score,
            max_candidates=o.max_candidates)
        out = None
        if found.found and not recent and self._ambiguous(node, submap, pyr, prob, guess,
                                                          found.pose, np.radians(ang)):
            self.ambiguous += 1
        elif found.found:
            ref = refine(prob, submap.grid.origin, submap.grid.resolution,
                         node.hits.astype(np.float64), found.pose,
                         occupied_weight=o.refine_occupied_space_weight,
                         translation_weight=o.refine_translation_weight,
                         rotation_weight=o.refine_rotation_weight)
            drop = np.inf
            if o.degenerate_drop > 0 and (
                    self._matched_spread(node, submap, prob, ref.pose) < o.degenerate_spread):
                drop, _ = weak_direction(prob, submap.grid.origin, submap.grid.resolution,
                                         node.match_points, ref.pose)
            out = Closure(se2_between(submap.local_pose, ref.pose), found.score, ref.score,
                          drop)
            self.found += 1
        self.seconds += time.perf_counter() - t0
        return out

    def _ambiguous(self, node: Node, submap: Submap, pyr: GridPyramid, field: np.ndarray,
                   guess: np.ndarray, pose: np.ndarray, ang: float) -> bool:
        """The match ``pose`` [3] (grid frame) lies twice ``ambiguity_radius_m`` or more
        from the estimate ``guess`` [3], and a pose within that radius of the estimate
        matches about as well over the points on seen cells: a door one spacing along a
        corridor, where the estimate is no worse than the match. (Matches nearer than
        twice the radius were compared with their own basin's edge: on ACES 23 right
        closures 1.0-1.1 m from the estimate were rejected so.)

        The search's score averages over all points, and points off the submap's seen
        cells score as far from any wall: between two equally good matches it picks the
        one that overlaps the submap more, so the comparison is over seen cells only. A
        match near the estimate is kept however many alike lie further away."""
        o = self.options
        r = o.ambiguity_radius_m
        if r <= 0 or o.ambiguity_margin <= 0 or np.hypot(*(pose[:2] - guess[:2])) < 2 * r:
            return False
        near = correlative_search(
            pyr, node.match_points, guess, r, ang, np.radians(o.angular_step_deg),
            min_score=o.ambiguity_min_score, max_candidates=o.max_candidates)
        if not near.found:
            return False
        far = self._seen_score(node, submap, field, pose)
        return bool(self._seen_score(node, submap, field, near.pose) >= far - o.ambiguity_margin)

    @staticmethod
    def _seen_score(node: Node, submap: Submap, field: np.ndarray, pose: np.ndarray) -> float:
        """Mean matching field under the scan's points [N] at ``pose`` that land on cells
        the submap has observed (0 when none does)."""
        g = submap.grid
        pts = transform_points(se2_to_matrix(*pose), node.match_points)  # [N, 2] grid frame
        c = g.cell_of(pts)  # [N, 2] (ix, iy); the field shares the grid's cells
        H, W = g.values.shape
        on = (c[:, 0] >= 0) & (c[:, 0] < W) & (c[:, 1] >= 0) & (c[:, 1] < H)
        c = c[on]
        seen = g.values[c[:, 1], c[:, 0]] > 0
        if not seen.any():
            return 0.0
        return float(field[c[seen, 1], c[seen, 0]].mean())

    def accepted(self, submap: int) -> None:
        """A closure found with ``submap`` went into the graph: it counts towards the
        submap's ``max_closures_per_submap`` (one rejected as degenerate does not, or a
        corridor's submaps were closed to search with no closure in the graph)."""
        self._closures[submap] = self._closures.get(submap, 0) + 1

    def _matched_spread(self, node: Node, submap: Submap, field: np.ndarray,
                        pose: np.ndarray) -> float:
        """normal_spread of the node's returns that land on the submap's walls at ``pose``
        (within about the matching sigma of one).

        Only those constrain the match: at the end of a featureless corridor a scan sees
        the end wall, so its own normals spread, but against a submap made further along
        the corridor the end wall lands where the submap has nothing and the match slides
        along the corridor as freely as without it (corridor benchmark: six closures
        1.2-6.4 m off passed the test on the whole scan's spread)."""
        if node.spread is None:
            node.spread = normal_spread(node.hits)
        if node.spread < self.options.degenerate_spread:
            return node.spread
        g = submap.grid
        hits = node.hits.astype(np.float64)
        at_pose = transform_points(se2_to_matrix(*pose), hits)  # [N, 2] grid frame
        val, _ = interpolate(field, g.origin, g.resolution, at_pose)
        on_wall = val > 0.5 * (g.p_min + g.p_max)  # [N]
        if on_wall.all():
            return node.spread
        return normal_spread(hits[on_wall])

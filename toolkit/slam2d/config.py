"""Settings of the 2D lidar SLAM, as nested pydantic models (unknown keys are errors).

Defaults follow Cartographer's 2D options where they carry over, and are the ones the
benchmarks in docs/slam2d.md were measured with: the same values for every log.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from toolkit.settings import AddedOptions


class _Options(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class GridOptions(_Options):
    resolution: float = Field(0.05, gt=0, description="submap cell size, m")
    hit_probability: float = Field(0.55, gt=0.5, lt=1)
    miss_probability: float = Field(0.49, gt=0, lt=0.5)
    min_probability: float = Field(0.1, gt=0, lt=0.5)
    max_probability: float = Field(0.9, gt=0.5, lt=1)
    matching_sigma_m: float = Field(
        0.1, gt=0, description="width of the smoothed field scans are matched against, m"
    )


class ScanOptions(_Options):
    min_range: float = Field(0.05, ge=0, description="beams shorter than this are dropped, m")
    max_range: float = Field(30.0, gt=0, description="longer beams only clear free space, m")
    missing_data_ray_length: float = Field(
        5.0, ge=0, description="free space cleared along a beam without return, m"
    )
    min_valid_beams: int = Field(20, ge=3, description="fewer returns: the scan is skipped")
    max_match_points: int = Field(
        250, ge=10, description="voxel-filter the points used for matching down to this many"
    )

    @model_validator(mode="after")
    def _ordered(self) -> ScanOptions:
        # Otherwise every scan is skipped (too few returns) after the run has started.
        if self.min_range >= self.max_range:
            raise ValueError(f"scan.min_range ({self.min_range} m) must be below "
                             f"scan.max_range ({self.max_range} m)")
        return self


class MotionFilterOptions(_Options):
    max_time_s: float = Field(5.0, ge=0)
    max_distance_m: float = Field(0.2, ge=0)
    max_angle_deg: float = Field(1.0, ge=0)


class LocalMatchingOptions(_Options, AddedOptions):
    # Left at 0, unseen_approach_cells (session 26) is not written: the slam2d stage's cache
    # key and slam2d_config.json (part of the trajectory artifact) stay those of runs made
    # before it, so they are neither redone nor make fuse rerun.
    added_off = {"unseen_approach_cells": 0.0, "unknown_score": 0.0}
    # Correlative search window around the predicted pose. With odometry the prediction is
    # good to centimetres; without it the robot may have moved a metre and turned tens of
    # degrees since the last scan (sparse logs), so the window is wider.
    linear_window_m: float = Field(0.2, ge=0)
    angular_window_deg: float = Field(5.0, ge=0)
    scan_only_linear_window_m: float = Field(1.2, ge=0)
    scan_only_angular_window_deg: float = Field(90.0, ge=0)
    # ... but scan-only no wider than the robot can move since the last scan at these
    # speeds (and no narrower than the windows with odometry): at 10 Hz the full window
    # searched 36x the area and 5x the angles that 2 m/s and 180 deg/s can cover, and the
    # search was 70 % of the scan-only time on the simulated house. Sparse logs (a scan
    # every 2-3 s, Intel, ACES) keep the full window, as do the first 20 scan-only
    # matches. A match scoring below ``scan_only_retry_score_ratio`` times the median of
    # the last 20 is searched again with the full window (a turn faster than the bound,
    # a stamp off; docs/slam2d.md, "Scan-only speed bound").
    scan_only_max_speed_m_s: float = Field(2.0, gt=0)
    scan_only_max_turn_rate_deg_s: float = Field(180.0, gt=0)
    scan_only_retry_score_ratio: float = Field(0.75, ge=0, le=1)
    angular_step_deg: float = Field(0.5, gt=0, description="search step, refined afterwards")
    translation_delta_cost_weight: float = Field(0.1, ge=0)
    rotation_delta_cost_weight: float = Field(0.1, ge=0)
    max_candidates: int = Field(600, ge=10)
    # Continuous refinement (Cartographer's CeresScanMatcher2D cost); these priors and
    # the delta costs above pull towards the odometry prediction. Cartographer's 10 / 40
    # made the Killian scan-to-scan poses no better than the odometry (0.039 m on the
    # consecutive relations); 1 / 1 lets the scan speak (0.034 m), lower slides in
    # corridors (docs/slam2d.md).
    occupied_space_weight: float = Field(1.0, gt=0)
    translation_weight: float = Field(1.0, ge=0)
    rotation_weight: float = Field(1.0, ge=0)
    max_iterations: int = Field(20, ge=1)
    # Degeneracy (with odometry): where the scan barely constrains the translation in
    # some direction (a corridor without features), the match is set from the odometry
    # prediction along it; the matcher would otherwise slide backwards, where the walls
    # ahead, not yet mapped, score like free space. Held fully where moving the scan
    # +-0.2 m along its weakest direction lowers the match score by less than half of
    # ``degenerate_drop``, not at all above it, and only when the scan's surface normals
    # spread less than ``degenerate_spread`` (0: off). Featureless corridor benchmark:
    # 3.2 m -> 0.036 m ATE; Killian: 37 of 3873 scans held, relations 0.0350 -> 0.0346 m
    # (docs/slam2d.md).
    degenerate_drop: float = Field(0.04, ge=0)
    degenerate_spread: float = Field(0.003, ge=0, le=0.5)
    # A return on a surface the submap has not seen yet (the part of a wall that comes
    # out from behind a corner as the robot drives on) lands on unobserved cells, and the
    # smoothed field of the seen part's end pulls it onto that end: towards where the
    # surface was seen from, away from the robot. With a forward-looking lidar every such
    # pull pushes the match forward, and the trajectory came out stretched (Killian
    # 0.7 % longer than its odometry; a simulated corridor with exact odometry and scans
    # every 0.5 m 1.6 %). With odometry, a point whose cell this many cells back towards
    # the sensor was never observed is left out of the match (0, the default: all points
    # count; 2: that corridor 0.05 %, Killian 0.40 %). Off by default: it cost Killian's
    # relations 0.0342 -> 0.0357 m and the simulated house's ATE 0.0125 -> 0.0139 m while
    # the corridor and doors benchmarks gained (0.046 -> 0.020, 0.050 -> 0.036 m);
    # docs/slam2d.md, "Along-track scale".
    unseen_approach_cells: float = Field(0.0, ge=0)
    # With odometry, cells the submap never observed score at least this in the local
    # matcher's field (search and refinement), not p_min like observed free space. A wall
    # the scan sees for the first time lies on unknown cells; scored as free, a pose a
    # little further back, which puts it on the mapped part, wins, and the match slides
    # back along a corridor. 0.5 (a probability grid's unknown prior): corridor benchmark
    # 0.048 -> 0.026 m, doors 0.063 -> 0.023 m, hold off 3.29 -> 1.99 m; but Killian's
    # relations 0.03424 -> 0.03488 m / 0.314 -> 0.327 deg and the simulated house
    # 0.0125 -> 0.0134 m, so off (0) by default. Not used scan-only (see slam.py).
    # docs/slam2d.md, "Unknown cells scored apart from free ones".
    unknown_score: float = Field(0.0, ge=0, lt=1)
    # Without odometry the prediction ("stood still") carries no information about the
    # translation: no translation cost in the search, and the refinement is only held to
    # the search result, weakly, so that it cannot slide along a corridor. A mild rotation
    # cost keeps a rectangular room from matching a quarter turn off.
    scan_only_rotation_delta_cost_weight: float = Field(0.5, ge=0)
    scan_only_translation_weight: float = Field(1.0, ge=0)
    scan_only_rotation_weight: float = Field(1.0, ge=0)
    # Scan-only, in a corridor whose walls ahead were only grazed by earlier beams, a pose
    # a metre behind can score a little better than the true one (the scan slides along
    # the corridor). The pose that repeats the last forward advance is searched too (small
    # window) and wins when it scores within this margin of the best pose: the data
    # decides when it is clear, the robot's motion when it is not.
    motion_tiebreak_margin: float = Field(0.04, ge=0)
    motion_tiebreak_linear_window_m: float = Field(0.25, ge=0)
    motion_tiebreak_angular_window_deg: float = Field(10.0, ge=0)


class SubmapOptions(_Options):
    num_range_data: int = Field(35, ge=1, description="scans per submap (each is in two)")


class LoopClosureOptions(_Options):
    enabled: bool = True
    max_constraint_distance_m: float = Field(15.0, ge=0)
    sampling_ratio: float = Field(0.3, gt=0, le=1)
    old_nodes: bool = Field(
        True, description="also search old nodes against each newly finished submap")
    # A robot standing still gets a node every motion_filter.max_time_s; searching each
    # against every submap within reach made the search grow with the square of the
    # time stood (a review: 1.4 s for 150 such nodes, 14 s for 450). Such a node sits
    # where the node before it is, tied to it by local SLAM: not searched by default.
    stationary_nodes: bool = Field(
        False, description="also search nodes the motion filter added for time alone")
    # Cartographer searches all old nodes (0). Skipping the nodes just before the submap
    # (tied to it by local SLAM already) helped the simulated house and hurt Killian, by
    # a few tenths of a millimetre to two millimetres each way (docs/slam2d.md).
    old_nodes_skip: int = Field(
        0, ge=0, description="... except the nodes this many before the submap's first")
    # On the smoothed field (not Cartographer's raw grid) a wrong match in clutter scores
    # higher: 0.55 let hundreds of false closures through on the Intel log, 0.75 few.
    min_score: float = Field(0.75, gt=0, lt=1)
    # A corridor with doors every few metres matches a scan as well one door further on:
    # the mean score then prefers the pose whose points fall more on the submap's seen
    # cells, and 70 of 234 closures were a door spacing (5 m) off, each pulling the map
    # (0.53 m ATE, 0.06 m without loop closure; Huber does not outvote a consistent
    # set). A wide-window match twice ``ambiguity_radius_m`` or more from the estimate
    # is rejected as ambiguous when the best pose within that radius of the estimate (scoring
    # at least ``ambiguity_min_score``) scores within ``ambiguity_margin`` of it over the
    # points that land on seen cells. 0: no test.
    ambiguity_radius_m: float = Field(1.0, ge=0)
    ambiguity_margin: float = Field(0.15, ge=0, lt=1)
    ambiguity_min_score: float = Field(0.5, gt=0, lt=1)
    # A match in a corridor without features fixes the node's lateral offset and heading
    # but not its position along the corridor: such a closure is rejected when both the
    # fall of the match score over +-0.2 m along its weakest direction and the spread of
    # the surface normals of the scan's returns that land on the submap's walls (0: all
    # one way, 0.5: even) are below these (0: off). On the corridor benchmark this takes
    # the map from 1.1 m to 0.036 m ATE; Killian / ACES / Intel lose 56 / 4 / 10 of
    # 1938 / 90 / 911 closures (all 4 ACES ones and 7 of the Intel ones 0.2-6.5 m wrong;
    # docs/slam2d.md).
    degenerate_drop: float = Field(0.04, ge=0)
    degenerate_spread: float = Field(0.003, ge=0, le=0.5)
    linear_window_m: float = Field(7.0, ge=0)
    angular_window_deg: float = Field(30.0, ge=0)
    # Work per submap is bounded, so that a robot driving the same rooms for hours does
    # not search every new node against every submap made there before (the searches per
    # lap grew with the laps: 3, 78, 174, ... 1737 in the 15th lap of a test room). A
    # submap that has given this many closures, or been searched this many times, is not
    # searched again; the newer submaps of the same place still are. Above what the
    # benchmark logs reach (busiest submap: Intel 80 closures / 231 searches, Killian
    # 57 / 83), so their figures are unchanged. 0: no limit.
    max_closures_per_submap: int = Field(100, ge=0)
    max_searches_per_submap: int = Field(400, ge=0)
    # A submap finished a short way back along the trajectory has drifted little from
    # the node: a small window is enough there and costs a fiftieth of the big one.
    recent_nodes: int = Field(100, ge=0, description="'a short way back', in nodes")
    recent_linear_window_m: float = Field(1.5, ge=0)
    recent_angular_window_deg: float = Field(10.0, ge=0)
    angular_step_deg: float = Field(0.25, gt=0)
    branch_and_bound_depth: int = Field(6, ge=0, le=10)
    max_candidates: int = Field(800, ge=10)
    max_points: int = Field(120, ge=10, description="scan points used by the search")
    translation_weight: float = Field(1.1e4, gt=0)
    rotation_weight: float = Field(1e5, gt=0)
    loss: Literal["huber", "cauchy", "none"] = "huber"
    loss_scale: float = Field(10.0, gt=0, description="on the weighted residual norm")
    # Refinement of a found closure (Cartographer's constraint-builder Ceres options).
    refine_occupied_space_weight: float = Field(20.0, gt=0)
    refine_translation_weight: float = Field(10.0, ge=0)
    refine_rotation_weight: float = Field(1.0, ge=0)


class PoseGraphOptions(_Options):
    optimize_every_n_nodes: int = Field(90, ge=0, description="0: only at the end")
    max_iterations: int = Field(6, ge=1, description="per periodic optimisation (warm start)")
    final_max_iterations: int = Field(50, ge=1)
    intra_submap_translation_weight: float = Field(5e2, gt=0)
    intra_submap_rotation_weight: float = Field(1.6e3, gt=0)
    local_slam_translation_weight: float = Field(1e5, ge=0)
    local_slam_rotation_weight: float = Field(1e5, ge=0)
    # Scan-only, a wrong scan match is the likeliest gross error: a robust loss on the
    # consecutive local-SLAM edges lets consistent loop closures outvote it.
    local_slam_loss: Literal["huber", "cauchy", "none"] = "none"
    local_slam_loss_scale: float = Field(10.0, gt=0)
    # Odometry edges are weak (Cartographer: 1e5, as strong as local SLAM): the local
    # SLAM's consecutive poses already use odometry as their prior and are closer to the
    # truth; at 1e5 they were averaged with the raw odometry (Killian consecutive
    # relations 0.0352 m instead of 0.0335 m).
    odometry_translation_weight: float = Field(1e3, ge=0)
    odometry_rotation_weight: float = Field(1e3, ge=0)


class MapOptions(_Options):
    """The output occupancy grid: every node's scan re-inserted at its optimised pose.

    Stronger updates than the submaps' so that a few observations already cross
    map_server's thresholds (0.65 occupied, 0.196 free) in sparse logs."""

    resolution: float = Field(0.05, gt=0, description="output occupancy grid cell size, m")
    hit_probability: float = Field(0.7, gt=0.5, lt=1)
    miss_probability: float = Field(0.3, gt=0, lt=0.5)


class Slam2DConfig(_Options):
    grid: GridOptions = GridOptions()
    scan: ScanOptions = ScanOptions()
    motion_filter: MotionFilterOptions = MotionFilterOptions()
    local: LocalMatchingOptions = LocalMatchingOptions()
    submaps: SubmapOptions = SubmapOptions()
    loop_closure: LoopClosureOptions = LoopClosureOptions()
    pose_graph: PoseGraphOptions = PoseGraphOptions()
    map: MapOptions = MapOptions()

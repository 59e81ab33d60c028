"""The fusion algorithm apart from the recipe runner: scale every frame, then map them.

``FramePairs`` (lidar vs prediction at the lidar pixels) come first for every frame,
because temporal smoothing of the scale needs the whole sequence; then every frame's
scaled depth becomes a coloured cloud integrated into a ``VoxelMap``; finally moving
obstacles are carved out with later depth views and lidar scans, and statistical
outliers are dropped.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from toolkit.camera import PinholeCamera
from toolkit.depth.protocol import DepthPrediction
from toolkit.errors import MissingInputError
from toolkit.fusion.cloud import CloudOptions, RayCache, depth_to_points, valid_pixels
from toolkit.fusion.consensus import TRUNC_VOXELS, ConsensusSurface
from toolkit.fusion.dynamic import (
    CarveOptions,
    SeeThroughCounter,
    cylinder_mask,
    dynamic_beams,
    grow_dynamic,
)
from toolkit.fusion.exposure import (
    CELL_RANGE,
    ExposureOptions,
    cell_observations,
    corrected_image,
)
from toolkit.fusion.projection import (
    LidarPixels,
    LidarProjector,
    edge_pairs,
    jump_near_side,
    occluded_lidar,
    occlusion_window,
    project_points,
    rays_pass_near,
    sample_depth,
    window_extreme,
    zbuffer_lidar,
)
from toolkit.fusion.refine import DepthRefiner, Refinement, RefineOptions, seam_free_beams
from toolkit.fusion.scale import (
    ScaleEstimate,
    SmoothedScale,
    estimate_scale,
    pair_agreement,
    smooth_scales,
)
from toolkit.fusion.voxel_map import (
    KEY_RANGE_VOXELS,
    KeyTable,
    MapArrays,
    VoxelMap,
    statistical_inliers,
    unique_voxels,
)
from toolkit.geometry import Trajectory, inv_se3, transform_points
from toolkit.io.atomic import atomic_path
from toolkit.io.depth import file_complete
from toolkit.sensors import CameraFrame, LaserScan, Rig, Sequence

log = logging.getLogger(__name__)


class FusionConfig(BaseModel):
    """Every setting of the fusion (the ``fuse`` stage's keys, without the stage ones)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    # scale estimation
    scale: Literal["ratio", "clustered", "robust", "none"] = "clustered"
    # widest log-ratio gate for valid pairs (narrowed to 3 robust sigmas of each frame's
    # ratios, down to 0.03); None (null): the paper's plain sum. Not 0: no pair passes a
    # zero gate, and every frame went unscaled.
    ratio_gate: float | None = 0.2
    cluster_algorithm: Literal["dbscan", "meanshift"] = "dbscan"
    cluster_eps: float = Field(0.03, gt=0)
    cluster_min_samples: int = 5
    cluster_min_fraction: float = Field(0.03, ge=0, le=1)  # core points need this share too
    robust_threshold: float = Field(0.05, gt=0)
    # robust, clustered: None -> shift for disparity models only (ratio: never)
    fit_shift: bool | None = None
    min_pairs: int = Field(20, ge=2)
    # temporal smoothing
    smoothing: Literal["median", "none"] = "median"
    smoothing_window: int = Field(9, ge=1)
    outlier_tol: float = Field(0.1, gt=0)  # log scale distance from the window median
    few_pairs: Literal["smoothed", "skip"] = "smoothed"
    # lidar projection
    scans_per_frame: int = Field(1, ge=1)
    max_scan_dt_s: float = Field(0.2, gt=0)
    motion_compensation: bool = True
    # Which pairs both sensors see (FramePairs.covisible, metrics lidar_visible_*): a lidar
    # point next to a nearer one (within this many beam spacings in the image) is occluded
    # from the camera above it; 0 keeps them (and turns pair_neighbour_scans off). The
    # shape correction's anchors (FramePairs.visible) are the pairs this test leaves,
    # without those on a depth edge of the prediction (same test as the map's flying
    # pixels, edge_threshold) when pair_edge_filter is on; the tests after it change the
    # metrics' pairs only.
    pair_occlusion_beams: float = Field(1.5, ge=0)
    pair_occlusion_margin_m: float = 0.05
    pair_occlusion_margin_rel: float = 0.05
    # ... and the points of the scans up to this many before and after the pair's own
    # (static beams, placed with their own poses, where the own scan has no point within
    # 5 cm: a thin leg its beams passed beside) hide lidar points the same way; 0: off.
    pair_neighbour_scans: int = Field(2, ge=0)
    # Pairs on a moving obstacle the lidar saw (beams other scans see through, and points
    # in the cylinders around such hits near the frame's time), and pairs whose camera ray
    # passes within pair_moving_ray_m of such a hit in the floor plane (the image shows a
    # person the scan, 40 ms later, looks past; 0: not that test). The flags come from
    # dynamic_removal with lidar_dynamic: without them this test has nothing to go on.
    pair_moving_filter: bool = True
    pair_moving_ray_m: float = Field(0.3, ge=0)
    # Pairs on the near side of a range jump in their own scan (a neighbouring beam reads
    # farther by the occlusion margin): the camera often sees the background beside the
    # edge there, and any network blurs it (see docs/depth_fusion.md for what it does to
    # the metrics).
    pair_jump_filter: bool = True
    pair_edge_filter: bool = True
    # Low-frequency shape correction of each frame's scaled depth (toolkit.fusion.refine):
    # a smooth log-depth field fitted to the floor (a plane floor_height_m below base_link;
    # 0 where base_link is on the floor, REP 105's base_footprint) and the lidar pairs
    # ("floor_lidar"), or to the lidar pairs alone ("lidar", a robot not on a flat floor).
    refine: Literal["none", "floor_lidar", "lidar"] = "none"
    floor_height_m: float = 0.0
    refine_grid: tuple[int, int] = (8, 6)  # nodes across, down
    refine_gate: float = Field(0.12, gt=0)
    refine_gate_final: float = Field(0.06, gt=0)
    refine_smooth: float = Field(1.0, gt=0)
    # Also anchor vertical columns through the lidar points (walls stand upright), gated
    # by the prediction like the floor: a table top above a leg the lidar hit falls out.
    refine_columns: bool = True
    refine_column_top_m: float = Field(2.2, gt=0)  # columns reach this far above the floor
    # Then rescale the image region around a run of at least this many consecutive lidar
    # pairs that agree with each other but not with the field (a room seen through a
    # doorway, which networks squash; toolkit.fusion.refine.correct_regions). 0: off.
    refine_region_beams: int = Field(5, ge=0)
    # clouds and map
    stride: int = Field(2, ge=1)
    # Every near_stride-th pixel only where that spacing stays below half a voxel (depth <
    # voxel_size * fx / (2 near_stride), 1.3 m for 2 cm voxels at fx 525): a 1 m wall gives
    # 25 points per voxel at stride 2, which cost time and average into one voxel. 0: off.
    near_stride: int = Field(4, ge=0)
    min_depth_m: float = Field(0.2, ge=0)
    max_depth_m: float = Field(6.0, gt=0)
    edge_threshold: float = 0.06
    # Pixels where the scaled depth's inverse bends by more than this (relative 3x3 Laplacian,
    # cloud.ramp_mask) stay out of the map: a smooth network's ramps across depth edges
    # (0: off).
    ramp_threshold: float = Field(0.0, ge=0)
    # Metres: 15 (meant as mm or cm) fused a room into 5 points without a word; no map
    # of a robot's rooms is made of voxels over a metre.
    voxel_size_m: float = Field(0.02, gt=0, le=1.0)
    min_voxel_frames: int = Field(1, ge=1)
    # Multi-view consensus: the same depth also goes into a coarse TSDF (Open3D), whose
    # surface is the weighted average of every view along the rays; map voxels farther
    # than consensus_m from that surface are dropped. One view's depth error (a few % of
    # the depth) spreads a surface into a shell many voxels thick; the TSDF finds its
    # middle. Half-resolution frames and 4 cm voxels keep it cheap.
    consensus: bool = False
    consensus_m: float = Field(0.03, gt=0)
    consensus_voxel_m: float = Field(0.04, gt=0)
    # The band each view writes around the surface it sees, in consensus voxels: 4 (16 cm)
    # keeps more of the surfaces just behind a nearer one (benchmark F@5cm, 3 / 4 / 5 / 6
    # voxels: simulated row 0.911 / 0.915 / 0.914 / 0.911, network 0.849 / 0.853 / 0.851 /
    # 0.848; a thinner band stops averaging the shell: precision fell at 3).
    consensus_trunc_voxels: float = Field(TRUNC_VOXELS, gt=0)
    consensus_downsample: int = Field(2, ge=1)
    consensus_every: int = Field(1, ge=1)
    # One consensus volume per bin of the camera's heading: views of a surface's other
    # side (a 10 cm wall, a door) vote "inside" on it (consensus.py); 1: one volume
    consensus_direction_bins: int = Field(4, ge=1)
    outlier_neighbors: int = 20  # statistical outlier removal; 0 disables it
    outlier_std_ratio: float = 2.0
    outlier_voxel_m: float = 0.06  # cells the outlier test runs on (<= voxel size: voxels)
    # moving obstacles
    dynamic_removal: bool = True
    # lidar: beams that other scans see through mark a moving obstacle; the camera points
    # within dynamic_radius_m of such hits (and below dynamic_height_m) are not fused
    lidar_dynamic: bool = True
    dynamic_radius_m: float = 0.5
    dynamic_height_m: float = 2.0
    dynamic_scan_window_s: float = 0.15
    # Time offsets (s) of the scans each scan is compared with (dynamic_beams)
    dynamic_offsets_s: tuple[float, ...] = (-4.0, -2.0, -1.0, -0.5, 0.5, 1.0, 2.0, 4.0)
    # ... and far ones, each sqrt(2) farther, for a person who stood still, then left (see
    # docs/depth_fusion.md); their votes count on surfaces at least dynamic_far_min_width_m
    # wide (not chair legs). () is the fusion before version 13.
    dynamic_far_offsets_s: tuple[float, ...] = (
        -128.0, -90.0, -64.0, -45.0, -32.0, -22.0, -16.0, -11.0, -8.0, -6.0,
        6.0, 8.0, 11.0, 16.0, 22.0, 32.0, 45.0, 64.0, 90.0, 128.0)
    dynamic_far_min_width_m: float = Field(0.1, ge=0)
    # A beam with no return (+inf, range_max) as free space out to range_max: for open
    # spaces beyond the scanner's reach; off, since glass and black or shiny surfaces
    # return nothing from most angles and would mark what is behind them as moving.
    lidar_no_return_free: bool = False
    carve_every: int = Field(5, ge=1)  # every n-th frame is a depth view for carving
    carve_voxel_m: float = 0.06  # cell size of the carving test
    carve_scans_every: int = Field(5, ge=1)
    carve_with_depth: bool = True
    carve_with_lidar: bool = True
    depth_margin_m: float = 0.10
    depth_margin_rel: float = 0.15
    lidar_margin_m: float = 0.10
    lidar_plane_tol_m: float = 0.05
    min_free: int = 3
    free_ratio: float = 0.5
    # Also carve a cell that min_free / free_ratio hold for over the views after it was last
    # fused alone (depth views of later frames, later scans): a person who stood still for
    # most of the drive and then walked off (see docs/depth_fusion.md).
    carve_after_last: bool = False
    grow_radius_m: float = 0.0  # > 0: also remove touching short-lived voxels (see dynamic)
    grow_slack_frames: int = 2
    grow_iterations: int = 6
    grow_max_frames: int = 4
    # Auto-exposure cameras (toolkit.fusion.exposure): "gain" solves every frame's gain
    # per colour channel over the frames' overlaps before the map pass and divides it out
    # of the colours the map takes (the tsdf and splat stages read the same gains); the
    # geometry is unchanged. On by default: most robot cameras run auto exposure, and at a
    # fixed exposure the gains come out within 0.3-0.6 % of 1 (the quickstart and the
    # benchmark's rows), for about 3.5 ms of fusion work a frame.
    exposure: Literal["none", "gain"] = "gain"
    exposure_cell_m: float = Field(0.10, gt=0)  # surface cells the frames are compared on
    exposure_stride: int = Field(4, ge=1)  # pixels sampled for that, in both directions

    @model_validator(mode="after")
    def _depth_range(self) -> FusionConfig:
        if self.min_depth_m >= self.max_depth_m:
            raise ValueError(f"min_depth_m ({self.min_depth_m}) must be below max_depth_m "
                             f"({self.max_depth_m}): no depth would reach the map")
        if self.ratio_gate is not None and not self.ratio_gate > 0:
            raise ValueError(f"ratio_gate {self.ratio_gate}: no pair passes a gate of 0 and "
                             "no frame would get a scale; give a positive log-ratio gate "
                             "(0.2), or null for the paper's plain sum over all pairs")
        return self

    def cloud_options(self, fx: float = 0.0) -> CloudOptions:
        """Cloud settings; ``fx`` (pixels) sets the depth below which ``near_stride`` holds."""
        near = self.voxel_size_m * fx / (2 * self.near_stride) if self.near_stride else 0.0
        return CloudOptions(self.min_depth_m, self.max_depth_m, self.edge_threshold, 5,
                            self.stride, self.near_stride, near, self.ramp_threshold)

    def refine_options(self) -> RefineOptions:
        return RefineOptions(grid=self.refine_grid, gate=self.refine_gate,
                             gate_final=self.refine_gate_final, smooth=self.refine_smooth,
                             max_depth_m=self.max_depth_m,
                             column_top_m=(self.refine_column_top_m if self.refine_columns
                                           else 0.0),
                             region_min_beams=self.refine_region_beams)

    def exposure_options(self) -> ExposureOptions:
        return ExposureOptions(cell_m=self.exposure_cell_m, stride=self.exposure_stride)

    def carve_options(self) -> CarveOptions:
        return CarveOptions(self.depth_margin_m, self.depth_margin_rel, self.lidar_margin_m,
                            self.lidar_plane_tol_m, self.min_free, self.free_ratio,
                            self.carve_after_last)


class CarveViews:
    """The strided depth views kept for carving until the map is finished: in memory, or
    one ``.npy`` per view in ``folder``. An hour at 10 Hz keeps about 7200 views of 150 KB
    (1.1 GB): in memory they would grow the process and every checkpoint pickles them."""

    def __init__(self, folder: Path | None = None) -> None:
        self.folder = folder
        self.indices: list[int] = []
        self._arrays: dict[int, np.ndarray] = {}
        if folder is not None:
            folder.mkdir(parents=True, exist_ok=True)

    def _path(self, index: int) -> Path:
        assert self.folder is not None
        return self.folder / f"{index:06d}.npy"

    def add(self, index: int, view: np.ndarray) -> None:
        if self.folder is None:
            self._arrays[index] = view
        else:
            with atomic_path(self._path(index)) as tmp:
                np.save(tmp, view)
        self.indices.append(index)

    def __iter__(self) -> Iterator[tuple[int, np.ndarray]]:
        for index in self.indices:
            yield index, (self._arrays[index] if self.folder is None
                          else np.load(self._path(index)))

    def state(self) -> dict[str, object]:
        """What a checkpoint holds: the views themselves only when they live in memory."""
        return {"indices": list(self.indices),
                "arrays": dict(self._arrays) if self.folder is None else None}

    def restore(self, state: dict[str, object] | list[tuple[int, np.ndarray]]) -> None:
        if isinstance(state, list):  # a checkpoint from before the views had a store
            self.indices, self._arrays = [], {}
            for index, view in state:
                self.add(index, view)
            return
        self.indices = list(state["indices"])  # type: ignore[call-overload]
        if self.folder is None:
            self._arrays = dict(state["arrays"] or {})  # type: ignore[call-overload]
            return
        # A view cut short (power loss, a hand) is as gone as a deleted one: loaded at the
        # end of the map pass it failed with numpy's EOF error, naming no file.
        missing = [i for i in self.indices if not file_complete(self._path(i))]
        if missing:
            raise MissingInputError(f"{self.folder}: carving views of frames {missing[:5]} are "
                                    "gone or cut short; run the stage again with --force")


@dataclass
class FramePairs:
    """Lidar vs prediction at the lidar pixels of one frame."""

    lidar: LidarPixels
    pred: np.ndarray  # [N] predicted values at the lidar pixels
    estimate: ScaleEstimate
    # [N] bool: pairs the shape correction anchors to (not behind a nearer point of their
    # own scan, not on a depth edge of the prediction)
    visible: np.ndarray
    # [N] bool: pairs both sensors see, for the metrics: by the sensors alone, the same
    # pairs whatever the prediction (not behind a nearer point of their own or the
    # neighbouring scans, not on or behind a moving obstacle, not on the near side of a
    # range jump; docs/depth_fusion.md); None in old checkpoints
    covisible: np.ndarray | None = None

    @property
    def seen_by_both(self) -> np.ndarray:
        """[N] bool: the pairs the metrics use (``covisible``; ``visible`` in checkpoints
        written before it)."""
        return self.visible if self.covisible is None else self.covisible


def _first_of_block(last: int | None, index: int, every: int) -> bool:
    """Whether frame ``index`` is the first fused of its block of ``every`` frame indices
    (``last``: the one taken before). With every frame fused in order that is every
    ``every``-th (index 0, 5, 10, ...); with a caller's subset (81, 86, ...) still one per
    block, where ``index % every == 0`` would take none."""
    return last is None or last // every != index // every


def pose_arrays(seq: Sequence, T_world_base: Trajectory, use_odometry: bool = True) -> tuple[
        np.ndarray, np.ndarray, np.ndarray]:
    """``T_world_base`` at every frame [F, 4, 4] and scan [S, 4, 4] stamp, plus [F] bool of
    frames inside the trajectory's time span and not in a gap of it (others have no
    trustworthy pose: ``Trajectory.covers``). Between the trajectory's poses the robot
    moves as the sequence's odometry says, when it has one and ``use_odometry``
    (``Trajectory.interpolate_with_odometry``).

    The trajectory must hold the robot base's poses (``child`` "base_link", as the slam2d
    stage's ``trajectory_base.tum`` and a sequence's ground truth), not the camera's."""
    traj = T_world_base
    if not isinstance(traj, Trajectory):
        raise TypeError(f"T_world_base must be a toolkit.geometry.Trajectory, not "
                        f"{type(traj).__name__} (read a file with toolkit.io.tum.read_tum)")
    if traj.child != "base_link":
        raise ValueError(
            f"the trajectory holds T_{traj.frame}_{traj.child}, the fusion needs the robot "
            f"base's (T_world_base_link: the slam2d stage's trajectory_base.tum); from camera "
            f"poses: T_world_base = T_world_camera @ inv(rig.T_base_camera); if these are the "
            f"base's poses under another name, set child='base_link' (a TUM file's header "
            f"'# T_world_base_link')")
    t0, t1 = traj.stamps[0], traj.stamps[-1]
    fs = seq.frame_stamps
    inside = traj.covers(fs, slack_s=Trajectory.END_SLACK_S)
    odom = seq.odometry if use_odometry else None
    slack = Trajectory.END_SLACK_S  # as slam2d's camera poses: the odometry carries them there

    def at(stamps: np.ndarray) -> np.ndarray:
        if not len(stamps):
            return np.zeros((0, 4, 4))
        return traj.interpolate_with_odometry(odom, np.clip(stamps, t0 - slack, t1 + slack),
                                              extrapolate_s=slack).poses

    frame_poses, scan_poses = at(fs), at(seq.scan_stamps)
    return frame_poses, scan_poses, inside


def scans_covered(seq: Sequence, T_world_base: Trajectory) -> np.ndarray:
    """[S] bool: scans stamped where ``T_world_base`` has a trustworthy pose (inside its
    span, not in a gap: ``Trajectory.covers``). ``pose_arrays`` gives the others the pose
    at the trajectory's nearest end; placed there, a scan taken elsewhere "sees through"
    walls and carves the static map."""
    return T_world_base.covers(seq.scan_stamps, slack_s=Trajectory.END_SLACK_S)


def check_world_extent(T_world_base: np.ndarray, config: FusionConfig) -> None:
    """Refuse poses [F, 4, 4] whose points the map cannot key (``voxel_map.voxel_keys``:
    +-2^20 voxels, 21 km at 2 cm), before any frame is fused: a trajectory in a UTM-like
    frame (the odometry's, 500 km out) failed after every frame had been scaled."""
    if len(T_world_base) == 0:
        return
    reach = float(np.abs(T_world_base[:, :3, 3]).max()) + config.max_depth_m + 1.0
    limits = {"voxel_size_m": KEY_RANGE_VOXELS * config.voxel_size_m}
    if config.exposure != "none":
        limits["exposure_cell_m"] = CELL_RANGE * config.exposure_cell_m
    key, limit = min(limits.items(), key=lambda kv: kv[1])
    if reach > limit:
        raise ValueError(
            f"the robot's poses lie up to {reach / 1000:.1f} km from the world frame's "
            f"origin, and the map keys points within +-{limit / 1000:.1f} km (by {key} "
            f"{getattr(config, key):g}; float32 points lose millimetres further out): "
            "express the trajectory in a local frame, e.g. subtract its first position "
            "from every pose (and from the ground truth, to score against it)")


class Fusion:
    """Per-frame pieces of the fusion, shared by the stage and the benchmark."""

    def __init__(self, seq: Sequence, config: FusionConfig, frame_poses: np.ndarray,
                 scan_poses: np.ndarray, views_dir: Path | None = None,
                 scan_covered: np.ndarray | None = None) -> None:
        """``frame_poses`` [F, 4, 4] / ``scan_poses`` [S, 4, 4]: ``T_world_base`` at the
        frame and scan stamps (``pose_arrays``); the sequence's scans de-skewed if they carry
        per-beam timing (``toolkit.deskew.deskew_sequence``). ``views_dir``: where the
        carving views wait for ``finish`` (None: in memory). ``scan_covered`` [S] bool: scans
        whose pose is trustworthy (``scans_covered``; None: all); the others place no lidar
        pairs, flag no moving obstacle and carve nothing."""
        self.seq = seq
        self.cfg = config
        self.camera = seq.rig.camera
        for warning in seq.rig.mount_warnings():
            log.warning("fusion: %s", warning)
        self.frame_poses = frame_poses  # [F, 4, 4] T_world_base
        self.scan_poses = scan_poses  # [S, 4, 4]
        check_world_extent(frame_poses, config)
        self.scan_covered = (np.ones(len(seq.scans), bool) if scan_covered is None
                             else np.asarray(scan_covered, bool))  # [S]
        if len(self.scan_covered) != len(seq.scans):
            raise ValueError(f"scan_covered has {len(self.scan_covered)} entries for "
                             f"{len(seq.scans)} scans")
        self.projector = LidarProjector(
            seq, frame_poses if config.motion_compensation else None,
            scan_poses if config.motion_compensation else None,
            config.scans_per_frame, config.max_scan_dt_s,
            scan_usable=self.scan_covered if config.motion_compensation else None)
        self.rays = RayCache(self.camera, config.stride)
        self._full_rays: RayCache | None = None  # every pixel's ray (moving_pixels)
        self._exposure_rays: RayCache | None = None  # exposure_observations' stride
        self._exposure_table = KeyTable()  # its cells
        self.cloud_opts = config.cloud_options(self.camera.fx)
        # One beam spacing for the occlusion test of the pairs (scanners of one sequence
        # share it; the finest one is the strictest test)
        steps = [abs(s.angle_increment) for s in seq.scans[:1]]
        self._beam_step = float(min(steps)) if steps else np.radians(1.0)
        # [S] beams of each full-circle scan (its last beam next to its first), 0 for others
        self._seam_beams = np.array(
            [len(sc.ranges) if abs(sc.angle_increment) * len(sc.ranges) >= 2 * np.pi - 1e-6
             else 0 for sc in seq.scans], np.int64)
        self.refiner = None if config.refine == "none" else DepthRefiner(
            self.camera, config.refine_options(),
            config.floor_height_m if config.refine == "floor_lidar" else None)
        self.map = VoxelMap(config.voxel_size_m)
        self.consensus: ConsensusSurface | None = None
        if config.consensus:
            self.consensus = ConsensusSurface(
                self.camera, config.consensus_voxel_m, config.consensus_trunc_voxels,
                config.max_depth_m, config.consensus_downsample,
                config.consensus_direction_bins)
        self.views = CarveViews(views_dir)  # frame -> strided scaled depth
        self.beam_dynamic: list[np.ndarray] = []
        self._world_cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # _scan_world
        self._dyn_xy: list[np.ndarray] = []
        self.points_masked_dynamic = 0
        self._consensus_last: int | None = None  # frame last integrated into the consensus
        if config.dynamic_removal and config.lidar_dynamic and len(seq.scans):
            T_wl = scan_poses @ seq.rig.T_base_laser
            self.beam_dynamic = [np.zeros(len(s.ranges), bool) for s in seq.scans]
            placed = np.flatnonzero(self.scan_covered)
            flagged = dynamic_beams([seq.scans[k] for k in placed], T_wl[placed],
                                    config.dynamic_offsets_s,
                                    no_return_is_free=config.lidar_no_return_free,
                                    far_offsets_s=config.dynamic_far_offsets_s,
                                    far_min_width_m=config.dynamic_far_min_width_m)
            for k, flags in zip(placed, flagged, strict=True):
                self.beam_dynamic[k] = flags
            for k, s in enumerate(seq.scans):
                b = np.flatnonzero(self.beam_dynamic[k])
                r = s.ranges[b].astype(np.float64)
                a = s.angles()[b]
                pl = np.stack([r * np.cos(a), r * np.sin(a), np.zeros_like(r)], 1)
                self._dyn_xy.append((pl @ T_wl[k][:3, :3].T + T_wl[k][:3, 3])[:, :2])
        # Imports take seconds on a busy machine; pay them here, not in the timed loop.
        if config.scale == "clustered":
            import sklearn.cluster  # noqa: F401
        if config.outlier_neighbors > 0:
            import open3d  # noqa: F401

    def T_world_camera(self, index: int) -> np.ndarray:
        return self.frame_poses[index] @ self.seq.rig.T_base_camera

    # ------------------------------------------------------------------ scale
    def frame_pairs(self, index: int, pred: DepthPrediction) -> FramePairs:
        """The lidar pairs of frame ``index`` with the prediction ``pred`` (at the image's
        resolution) and its scale estimate."""
        shape = (self.camera.height, self.camera.width)
        if pred.values.shape != shape:
            raise ValueError(f"frame {index}: prediction of {pred.values.shape[1]}x"
                             f"{pred.values.shape[0]}, the camera's images are {shape[1]}x"
                             f"{shape[0]}: resize it to the image (the depth backends do)")
        lidar = zbuffer_lidar(self.projector.project_frame(index), pred.values.shape)
        d = sample_depth(pred.values, lidar)
        c = self.cfg
        hidden, dropped = self._pair_tests(index, lidar)
        covis = ~hidden & ~dropped
        if c.scale == "none":
            est = ScaleEstimate(1.0, 0.0, len(d), len(d), "ok", "none")
        else:
            opts: dict[str, object] = {"min_pairs": c.min_pairs}
            if c.scale == "ratio":
                opts["gate"] = c.ratio_gate
            elif c.scale == "clustered":
                opts.update(algorithm=c.cluster_algorithm, eps=c.cluster_eps,
                            min_samples=c.cluster_min_samples,
                            min_fraction=c.cluster_min_fraction, fit_shift=c.fit_shift)
            else:
                opts.update(threshold=c.robust_threshold, fit_shift=c.fit_shift)
            # From all pairs: the estimators reject the hidden ones as outliers anyway, and
            # the edge test also drops good pairs on noisy flat walls, so the visible pairs
            # alone gave a slightly worse scale (simulated house: median error vs the oracle
            # 0.76 % instead of 0.70 %, worst frame 5.1 % instead of 3.1 %).
            est = estimate_scale(c.scale, lidar.z, d, pred.is_disparity, **opts)
        # The shape correction's anchors keep the pairs the other sensor-only tests drop:
        # with those dropped too the maps came out worse (simulated house, session 24:
        # F@5cm 0.911 -> 0.909 with `paper` depth, 0.849 -> 0.848 with the shipped network;
        # RMSE vs ground truth after the correction 0.0827 -> 0.0833 and 0.1233 -> 0.1252 m).
        # The pairs on moving obstacles `refine` leaves out itself.
        vis = ~hidden
        if c.pair_edge_filter and c.edge_threshold > 0:
            # The same test as the map's flying pixels, on depth: a disparity's span is
            # another one (with its shift unknown, the raw one: a scale alone keeps it).
            known = est.ok and np.isfinite(est.scale) and est.scale > 0
            vis &= ~edge_pairs(pred.values, lidar, c.edge_threshold, self.cloud_opts.edge_window,
                               pred.is_disparity, est.scale if known else 1.0,
                               est.shift if known else 0.0)
        return FramePairs(lidar, d, est, vis, covis)

    def _pair_tests(self, index: int, lidar: LidarPixels) -> tuple[np.ndarray, np.ndarray]:
        """Frame ``index``'s lidar pixels [N] that the camera may not see, by the sensors
        alone (the same pairs whatever the prediction): (hidden behind a nearer point of
        their own scans, ``pair_occlusion_beams``; dropped by the other tests: behind a
        neighbouring scan's static point, ``pair_neighbour_scans``; on or behind a moving
        obstacle the lidar saw, ``pair_moving_filter``, ``pair_moving_ray_m``; on the near
        side of a range jump, ``pair_jump_filter``). ``FramePairs.covisible`` has neither."""
        c = self.cfg
        hidden = np.zeros(len(lidar), bool)  # [N]
        dropped = np.zeros(len(lidar), bool)  # [N]
        if not len(lidar):
            return hidden, dropped
        if c.pair_occlusion_beams > 0:
            occ = (self.camera.fx, self.camera.cx, self._beam_step, c.pair_occlusion_beams,
                   c.pair_occlusion_margin_m, c.pair_occlusion_margin_rel)
            hidden = occluded_lidar(lidar, *occ)
            extra = self._neighbour_occluders(index, lidar) if c.pair_neighbour_scans else None
            if extra is not None:
                dropped |= occluded_lidar(lidar, *occ, occluders=extra)
        if c.pair_moving_filter:
            dropped |= self._pairs_by_moving(index, lidar)
        if c.pair_jump_filter:
            for k in np.unique(lidar.scan):
                at = lidar.scan == k
                dropped[at] |= jump_near_side(self.seq.scans[k], lidar.beam[at],
                                              c.pair_occlusion_margin_m,
                                              c.pair_occlusion_margin_rel)
        return hidden, dropped

    def _neighbour_occluders(self, index: int, lidar: LidarPixels) -> (
            tuple[np.ndarray, np.ndarray] | None):
        """(u [M], z [M]) in frame ``index``'s image of the static points of the scans up to
        ``pair_neighbour_scans`` before and after the pairs' own that no own-scan point lies
        within 5 cm of (None: none). At 1 deg spacing a 3-5 cm table leg falls between the
        own scan's beams, so ``occluded_lidar`` had no nearer point to test, while the
        camera 10 cm ahead of the lidar looks through it at the wall point; the robot has
        moved by the next scans, whose beams hit it. Points near an own-scan point say
        little the own scan does not, and their slightly other view of the same edges
        dropped more good pairs (all of them: 5.0 % of the pairs on the simulated house
        instead of 3.2 %)."""
        if self.projector.frame_poses is None:  # no poses: other scans cannot be placed
            return None
        n = self.cfg.pair_neighbour_scans
        own = set(lidar.scan.tolist())  # a frame's pairs come from a scan or a few
        near = sorted({k + d for k in own for d in range(-n, n + 1)} - own)
        near = [k for k in near if 0 <= k < len(self.seq.scans) and self.scan_covered[k]]
        if not near:
            return None
        # A person seen from another scan hides nothing now: static beams only.
        world = np.concatenate([self._scan_world(k)[1] for k in near])  # [M, 3]
        uv, z, keep = project_points(self.camera, transform_points(
            inv_se3(self.T_world_camera(index)), world), self.projector.min_z)
        # Only a point nearer than some pair within the widest window can hide one; most
        # are the same walls seen again, and need no look at the own scan.
        c = self.cfg
        u = lidar.uv[:, 0]  # [N]
        win = occlusion_window(u, self.camera.fx, self.camera.cx, self._beam_step,
                               c.pair_occlusion_beams).max()
        reach = lidar.z - (c.pair_occlusion_margin_m + c.pair_occlusion_margin_rel * lidar.z)
        cand = z < window_extreme(u, reach, uv[:, 0] - win, uv[:, 0] + win, np.maximum)
        if not cand.any():
            return None
        xy = world[keep][cand, :2]  # [C, 2]
        own_xy = np.concatenate([self._scan_world(k)[0][:, :2] for k in sorted(own)])  # [P, 2]
        if len(own_xy):
            dx = xy[:, 0, None] - own_xy[None, :, 0]  # [C, P]
            dy = xy[:, 1, None] - own_xy[None, :, 1]
            gap2 = (dx * dx + dy * dy).min(1)  # [C]
            cand[np.flatnonzero(cand)[gap2 <= 0.05 ** 2]] = False  # an own point within 5 cm
        return uv[cand, 0], z[cand]

    def _scan_world(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Scan ``k``'s valid end points [P, 3] and its static ones (beams no other scan
        sees through) [Q, 3] in the world, placed with its pose (kept for the next few
        frames: a scan neighbours 2 n + 1 of them)."""
        if k not in self._world_cache:
            if len(self._world_cache) > 64:
                self._world_cache.clear()
            pts, beams = self.projector.laser_points(k)
            world = transform_points(self.scan_poses[k] @ self.seq.rig.T_base_laser, pts)
            static = world[~self.beam_dynamic[k][beams]] if self.beam_dynamic else world
            self._world_cache[k] = (world, static)
        return self._world_cache[k]

    def _pairs_by_moving(self, index: int, lidar: LidarPixels) -> np.ndarray:
        """[N] bool: pairs on a moving obstacle the lidar saw (beams other scans see through,
        points in the cylinders around such hits of the frame's time window), or whose
        camera ray passes within ``pair_moving_ray_m`` of such a hit in the floor plane.
        The scan is stamped 40 ms after the image on the simulated house: a leg has moved
        by 4 cm and swung by up to 12, the lidar hits it where the image shows the floor
        behind, or looks past where the image still shows it."""
        c = self.cfg
        out = self.pairs_on_moving(lidar)  # [N]
        hits = self.dynamic_hits(index)  # [K, 2]
        if not len(hits):
            return out
        T = self.T_world_camera(index)
        X = transform_points(T, lidar.points_cam)  # [N, 3] world
        out |= cylinder_mask(X, hits, c.dynamic_radius_m, c.dynamic_height_m)
        if c.pair_moving_ray_m > 0:
            o = T[:2, 3]  # [2]
            v = X[:, :2] - o  # [N, 2]
            L = np.linalg.norm(v, axis=1)
            # Short of the lidar point by 5 cm: the ray's own end is the surface it hit.
            ends = o + v * (np.maximum(L - 0.05, 0.0) / np.maximum(L, 1e-9))[:, None]
            out |= rays_pass_near(o, ends, hits, c.pair_moving_ray_m)
        return out

    def dynamic_hits(self, index: int) -> np.ndarray:
        """[K, 2] world xy of lidar hits on moving obstacles near frame ``index``'s time."""
        if not self._dyn_xy:
            return np.zeros((0, 2))
        t = self.seq.frame_stamps[index]
        st = self.seq.scan_stamps
        lo, hi = np.searchsorted(st, [t - self.cfg.dynamic_scan_window_s,
                                      t + self.cfg.dynamic_scan_window_s])
        parts = [self._dyn_xy[k] for k in range(lo, hi) if len(self._dyn_xy[k])]
        return np.concatenate(parts) if parts else np.zeros((0, 2))

    def _near_moving(self, index: int, pts: np.ndarray) -> np.ndarray | None:
        """[N] bool: world points [N, 3] of frame ``index`` in the cylinders of the moving
        obstacles the lidar saw near its time; None when there are none."""
        centres = self.dynamic_hits(index)
        if not len(centres):
            return None
        moving = cylinder_mask(pts, centres, self.cfg.dynamic_radius_m,
                               self.cfg.dynamic_height_m)
        return moving if moving.any() else None

    def pairs_on_moving(self, lidar: LidarPixels) -> np.ndarray:
        """[N] bool: lidar pixels from beams flagged as hitting a moving obstacle."""
        out = np.zeros(len(lidar), bool)  # [N]
        if not self.beam_dynamic or not len(lidar):
            return out
        # By scan (a frame's pairs come from a few): refine asks this of every frame.
        for k in np.unique(lidar.scan):
            sel = lidar.scan == k
            out[sel] = self.beam_dynamic[k][lidar.beam[sel]]
        return out

    def moving_pixels(self, index: int, depth: np.ndarray) -> np.ndarray | None:
        """[H, W] bool: pixels of frame ``index``'s scaled ``depth`` within the space of a
        moving obstacle the lidar saw near its time (what ``integrate`` keeps out of the
        map), at full resolution; None where there is none. The scaled depth written for
        later stages leaves them out too: the TSDF fused the people walking through into
        ghost surfaces, and splats took them as depth targets."""
        centres = self.dynamic_hits(index)
        if not len(centres):
            return None
        if self._full_rays is None:
            self._full_rays = RayCache(self.camera, 1)
        T = self.T_world_camera(index).astype(np.float32)
        ok = np.isfinite(depth) & (depth > 0)
        if self._full_rays.reachable is not None:
            ok &= self._full_rays.reachable
        rays = self._full_rays.rays.reshape(-1, 3)  # [H * W, 3]
        full = ok.all()
        if full:
            # The usual scaled depth, valid everywhere: the rays as they are, no gather of
            # them and no scatter of the result (the same points, bit for bit).
            z = depth.reshape(-1).astype(np.float32, copy=False)  # [H * W]
            pc = rays * z[:, None]  # [H * W, 3]
        else:
            # Flat indices and row gathers (as depth_to_points): a 2-D boolean mask on the
            # [H, W, 3] rays took 12 of this call's 15 ms a frame on the quickstart.
            idx = np.flatnonzero(ok)  # [N]
            z = depth.reshape(-1)[idx].astype(np.float32)  # [N]
            pc = np.take(rays, idx, axis=0) * z[:, None]  # [N, 3]
        inside = cylinder_mask(pc @ T[:3, :3].T + T[:3, 3], centres,
                               self.cfg.dynamic_radius_m, self.cfg.dynamic_height_m)
        if full:
            return inside.reshape(depth.shape)
        out = np.zeros(depth.size, bool)
        out[idx] = inside
        return out.reshape(depth.shape)

    def smooth(self, estimates: list[ScaleEstimate], pairs: list[FramePairs] | None = None,
               disparity: bool = False) -> SmoothedScale:
        """Temporal smoothing and outlier frames (``smooth_scales``). With the frames'
        ``pairs`` (the ``frame_pairs`` the estimates came from, in the same order; their
        predictions ``disparity`` or not), a frame off its neighbours whose own pairs back
        its fit and reject theirs keeps its scale."""
        c = self.cfg
        if c.scale == "none":
            n = len(estimates)
            return SmoothedScale(np.ones(n), np.zeros(n), np.ones(n), ["ok"] * n,
                                 np.ones(n, bool))
        agreement = None
        if pairs is not None:
            if len(pairs) != len(estimates):
                raise ValueError(f"{len(pairs)} frames' pairs for {len(estimates)} estimates")
            # Half the outlier distance: scales that far apart cannot both take a pair.
            tol = c.outlier_tol / 2

            def agreement(i: int, scale: float, shift: float) -> float:
                # Pairs on beams other scans see through (a person walking by) back
                # nothing: a person taking two thirds of a frame's pairs kept a fit 50 %
                # off. The rest must span depths (1.25x), as a room does and a person not.
                lid = pairs[i].lidar
                keep = ~self.pairs_on_moving(lid)
                return pair_agreement(lid.z[keep], pairs[i].pred[keep], disparity, scale,
                                      shift, tol, min_spread=1.25)
        return smooth_scales(estimates, c.smoothing_window, c.outlier_tol, c.smoothing,
                             c.few_pairs, agreement)

    def refine(self, index: int, depth: np.ndarray, pairs: FramePairs) -> tuple[
            np.ndarray, Refinement]:
        """The scaled depth [H, W] with its low-frequency shape error corrected (unchanged
        when ``refine`` is none or too few anchors agree)."""
        if self.refiner is None:
            return depth, Refinement(False)
        lid = pairs.lidar
        # Not the pairs on moving obstacles (as ``smooth``): the camera, a few tens of ms
        # off the scan, sees the background there, and the region pass rescaled it to the
        # person's depth (15-17 % of a frame more than 10 % off in the box room).
        v = pairs.visible & ~self.pairs_on_moving(lid)
        beam = lid.beam[v].copy()
        for k in np.unique(lid.scan[v]):
            if self._seam_beams[k]:
                at = lid.scan[v] == k
                beam[at] = seam_free_beams(beam[at], int(self._seam_beams[k]))
        return self.refiner.refine(depth, self.T_world_camera(index), self.frame_poses[index],
                                   lid.pixel[v], lid.z[v], lid.points_cam[v],
                                   np.stack([lid.scan[v], beam], 1))

    # ------------------------------------------------------------------ exposure
    def exposure_observations(self, index: int, depth: np.ndarray, rgb: np.ndarray,
                              max_cells: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Frame ``index``'s surface cells for the exposure solve (``toolkit.fusion.
        exposure``): cell keys [M] and log mean colours [M, 3], from its scaled depth
        [H, W] every ``exposure_stride`` pixels, without the moving obstacles the lidar
        saw; at most ``max_cells`` (``ExposureOptions.plan``)."""
        opts = self.cfg.exposure_options()
        if self._exposure_rays is None:
            self._exposure_rays = RayCache(self.camera, opts.stride)
        pts, col, _ = depth_to_points(depth, rgb, self._exposure_rays, self.T_world_camera(index),
                                      dataclasses.replace(self.cloud_opts, stride=opts.stride,
                                                          near_stride=0))
        moving = self._near_moving(index, pts)
        if moving is not None:
            pts, col = pts[~moving], col[~moving]
        keys, log_rgb, _ = cell_observations(pts, col, self.T_world_camera(index)[:3, 3], opts,
                                             max_cells, self._exposure_table)
        return keys, log_rgb

    # ------------------------------------------------------------------ map
    def integrate(self, index: int, depth: np.ndarray, rgb: np.ndarray,
                  labels: np.ndarray | None = None, drop: np.ndarray | None = None,
                  valid: np.ndarray | None = None, gain: np.ndarray | None = None) -> int:
        """Add one frame's scaled depth [H, W] to the map; returns the number of points.

        ``labels`` [H, W] (e.g. ground-truth dynamic pixels) only ride along for
        evaluation; ``drop`` [H, W] bool removes pixels before integration; ``valid`` is
        ``valid_pixels(depth, self.cloud_opts)`` when the caller already has it. ``gain``
        [3]: the frame's exposure gain (``exposure_observations``, ``solve_exposure``),
        divided out of the colours the map takes, as ``corrected_image`` divides it out
        of the image, on the pixels taken only (a sixth of them at stride 2).
        """
        ok = valid_pixels(depth, self.cloud_opts) if valid is None else valid
        pts, col, idx = depth_to_points(depth, rgb, self.rays, self.T_world_camera(index),
                                        self.cloud_opts, drop, ok)
        if gain is not None:
            col = corrected_image(col.reshape(-1, 1, 3), gain).reshape(-1, 3)
        moving = self._near_moving(index, pts)
        if moving is not None:
            self.points_masked_dynamic += int(moving.sum())
            pts, col, idx = pts[~moving], col[~moving], idx[~moving]
        lab = None
        if labels is not None:
            lab = labels[:: self.rays.stride, :: self.rays.stride].reshape(-1)[idx].astype(
                np.float64)
        z = depth[:: self.rays.stride, :: self.rays.stride].reshape(-1)[idx]
        w = None
        o = self.cloud_opts
        if o.near_stride > o.stride and o.near_depth_m > 0:
            # A near point stands for (near_stride / stride)^2 pixels: voxel means keep the
            # weight the nearer, more accurate views had at the plain stride.
            w = np.where(z < o.near_depth_m, (o.near_stride // o.stride) ** 2, 1)
        self.map.integrate(pts, col, index, lab, z, w)
        if self.consensus is not None and _first_of_block(
                self._consensus_last, index, self.cfg.consensus_every):
            self.consensus.integrate(depth, self.T_world_camera(index),
                                     ok if drop is None else ok & ~drop)
            self._consensus_last = index
        if self.cfg.dynamic_removal and self.cfg.carve_with_depth and _first_of_block(
                self.views.indices[-1] if self.views.indices else None, index,
                self.cfg.carve_every):
            s = self.rays.stride
            view = np.where(ok[::s, ::s], depth[::s, ::s], np.nan).astype(np.float16)
            self.views.add(index, view)
        return len(pts)

    def state(self) -> dict[str, object]:
        """What the fused frames built (voxel map, carving views, consensus volume), to be
        pickled: ``restore`` on a fusion of the same settings continues from it."""
        return {"map": self.map, "views": self.views.state(),
                "points_masked_dynamic": self.points_masked_dynamic,
                "consensus": None if self.consensus is None else self.consensus.state(),
                "consensus_last": self._consensus_last}

    def restore(self, state: dict[str, object]) -> None:
        self.map = state["map"]  # type: ignore[assignment]
        self.views.restore(state["views"])  # type: ignore[arg-type]
        self.points_masked_dynamic = int(state["points_masked_dynamic"])  # type: ignore
        self._consensus_last = state.get("consensus_last")  # type: ignore[assignment]
        if self.consensus is not None and state["consensus"] is not None:
            self.consensus.restore(state["consensus"])  # type: ignore[arg-type]

    def finish(self) -> tuple[MapArrays, dict[str, np.ndarray]]:
        """(raw map, per-voxel masks of it). The map to keep is ``raw.select(masks["keep"])``
        (what the fuse stage writes): not on a moving obstacle, near the multi-view
        surface when ``consensus`` is on, not a statistical outlier. Masks [V] bool:
        ``keep``, ``dynamic`` (removed as moving: lidar-detected or carved), ``consensus``
        (removed: off the consensus surface), ``outlier``, ``dynamic_off_surface`` (removed
        as moving, and off the consensus surface too: the map without carving would lack
        them as well); with ``dynamic_removal`` also ``carved`` (seen through by later
        views) and ``free_views`` / ``hit_views`` [V] int (views that saw through / hit each
        voxel's carving cell). It ends the fusion: the voxel map is released."""
        raw = self.map.arrays(min_frames=self.cfg.min_voxel_frames)
        # Nothing reads the voxel map past this copy: freed now, it does not add to the
        # peak of the steps below (its values, key index and batch buffer: 0.36 GB at
        # 2.4 M voxels).
        self.map.release()
        masks = {k: np.zeros(len(raw), bool) for k in ("dynamic", "consensus", "outlier",
                                                      "dynamic_off_surface")}
        c = self.cfg
        cell_inv: np.ndarray | None = None  # [V] carving cell of every voxel
        cell_size = 0.0
        if c.dynamic_removal and len(raw):
            # Carving tests coarse cells (centroids of the map voxels in each): a person is
            # many cells wide, and it is 10x fewer points to project into every view.
            cell_size = max(c.carve_voxel_m, c.voxel_size_m)
            _, inv = unique_voxels(raw.points, cell_size)
            cell_inv = inv
            n_cells = int(inv.max()) + 1
            cells = np.stack([np.bincount(inv, raw.points[:, k], n_cells) for k in range(3)], 1)
            cells /= np.bincount(inv, minlength=n_cells)[:, None]
            last = None
            if c.carve_after_last:
                # Each cell's last fused frame: the latest of its voxels'.
                last = np.zeros(n_cells, np.int64)
                np.maximum.at(last, inv, raw.last.astype(np.int64))
            counter = SeeThroughCounter(
                cells, c.carve_options(), last_frame=last,
                last_stamp=None if last is None else np.asarray(self.seq.frame_stamps)[last])
            if c.carve_with_depth:
                for index, view in self.views:
                    counter.add_depth_view(self.camera, inv_se3(self.T_world_camera(index)),
                                           view.astype(np.float32), self.rays.stride,
                                           c.max_depth_m + 1.0, index)
            if c.carve_with_lidar and len(self.seq.scans):
                T_bl = self.seq.rig.T_base_laser
                for k in range(0, len(self.seq.scans), c.carve_scans_every):
                    if self.scan_covered[k]:
                        counter.add_scan(self.seq.scans[k],
                                         inv_se3(self.scan_poses[k] @ T_bl))
            dyn = counter.dynamic_mask()[inv]
            masks["carved"] = dyn
            if c.grow_radius_m > 0:
                dyn = grow_dynamic(raw.points, raw.first, raw.last, raw.frames, dyn,
                                   c.grow_radius_m, c.grow_slack_frames, c.grow_iterations,
                                   c.grow_max_frames)
            masks["dynamic"] = dyn
            masks["free_views"] = counter.free[inv]
            masks["hit_views"] = counter.hit[inv]
        keep = ~masks["dynamic"]
        # A consensus without a surface (frames of a few pixels each) judges nothing.
        if (self.consensus is not None and self.consensus.frames and keep.any()
                and len(self.consensus.surface())):
            # The voxels removed as moving are judged too (each point on its own, so the
            # rest's verdicts are unchanged): the share of moving obstacles before carving
            # is over the map the consensus leaves without it, not over the raw map (there
            # the 1.5 M static voxels the consensus drops made carving look as if it added
            # people: 0.38 % before, 0.48 % after, with half of them removed).
            off = self.consensus.off_surface(raw.points, c.consensus_m)  # [V]
            masks["consensus"] = off & keep
            masks["dynamic_off_surface"] = off & masks["dynamic"]
            keep &= ~off
        if c.outlier_neighbors > 0 and keep.sum() > c.outlier_neighbors:
            idx = np.flatnonzero(keep)
            pts = raw.points[idx]
            if c.outlier_voxel_m > c.voxel_size_m:
                # On coarse cell centroids: a floating blob is isolated at 6 cm as at 2 cm,
                # and the k-NN search over a few million map voxels would take longer than
                # fusing the frames.
                if cell_inv is not None and cell_size == c.outlier_voxel_m:
                    # The carving's cells, without the removed voxels: no second keying
                    # and sort of the whole map.
                    _, inv = KeyTable().unique([cell_inv[idx]], [63])
                else:
                    _, inv = unique_voxels(pts, c.outlier_voxel_m)
                n = int(inv.max()) + 1
                cells = np.stack([np.bincount(inv, pts[:, k], n) for k in range(3)], 1)
                cells /= np.bincount(inv, minlength=n)[:, None]
                inl = statistical_inliers(cells, c.outlier_neighbors, c.outlier_std_ratio)[inv]
            else:
                inl = statistical_inliers(pts, c.outlier_neighbors, c.outlier_std_ratio)
            masks["outlier"][idx[~inl]] = True
            keep[idx[~inl]] = False
        masks["keep"] = keep
        return raw, masks


@dataclass
class PairStats:
    """Lidar/prediction pairs pooled over frames for the paper's lidar metrics."""

    lidar: list[np.ndarray] = field(default_factory=list)
    unscaled: list[np.ndarray] = field(default_factory=list)
    scaled: list[np.ndarray] = field(default_factory=list)

    def add(self, lidar_z: np.ndarray, unscaled: np.ndarray, scaled: np.ndarray) -> None:
        self.lidar.append(lidar_z)
        self.unscaled.append(unscaled)
        self.scaled.append(scaled)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        def cat(a: list[np.ndarray]) -> np.ndarray:
            return np.concatenate(a) if a else np.zeros(0)

        return cat(self.lidar), cat(self.unscaled), cat(self.scaled)


def scaled_at_pairs(pairs: FramePairs, disparity: bool, scale: float, shift: float) -> (
    np.ndarray
):
    """[N] depth at the lidar pixels after scaling (NaN where the disparity is not > 0)."""
    v = pairs.pred
    if disparity:
        with np.errstate(divide="ignore", invalid="ignore"):
            disp = scale * v + shift
            return np.where(disp > 0, 1.0 / disp, np.nan)
    z = scale * v + shift
    return np.where(z > 0, z, np.nan)


def scale_from_scan(prediction: DepthPrediction, scan: LaserScan, camera: PinholeCamera,
                    T_camera_laser: np.ndarray, config: FusionConfig | None = None) -> (
                        FramePairs):
    """The lidar scale of one image from your own arrays, as the ``fuse`` stage finds it.

    ``prediction``: the network's output at the image's size (``DepthPrediction(values
    [H, W], kind)``); ``scan``: a scan taken with the image (angles in radians, ranges in
    metres); ``T_camera_laser`` [4, 4]: maps laser points into the camera's optical frame
    (x right, y down, z forward). The same pairs and filters as the stage (nearest lidar
    point per pixel, points the camera cannot see, pairs on the prediction's depth
    edges) and ``config``'s estimator (default: ``clustered``). Returns the frame's
    ``FramePairs``: ``.estimate`` (scale, shift, inliers, quality), ``.lidar`` (pixels and
    depths) and ``.pred`` (the prediction there); the metric depth is
    ``prediction.as_depth(est.scale, est.shift)``. No motion between scan and image is
    compensated: give the scan nearest in time.
    """
    # The laser is the base (turned over when it is mounted upside down, its z axis along
    # the image's down): the rig's mount checks then test the camera against the scan
    # plane, which flags an inverted extrinsic.
    T_cl = np.asarray(T_camera_laser, dtype=np.float64)
    T_base_laser = np.diag([1.0, -1.0, -1.0, 1.0]) if T_cl[1, 2] > 0 else np.eye(4)
    rig = Rig(camera, T_base_laser @ inv_se3(T_cl), T_base_laser)
    # Scan and image are taken as one instant here: the beams' own times play no part.
    scan = dataclasses.replace(scan, time_increment=0.0)
    h, w = camera.height, camera.width
    frame = CameraFrame.from_array(scan.stamp, np.zeros((h, w, 3), np.uint8))
    seq = Sequence(rig, [frame], [scan], name="scale_from_scan")
    poses = np.eye(4)[None]  # [1, 4, 4]
    cfg = config or FusionConfig()
    return Fusion(seq, cfg.model_copy(update={"motion_compensation": False}), poses,
                  poses).frame_pairs(0, prediction)

"""Recipe stage ``fuse``: lidar-scaled depth -> coloured metric map of the world.

Writes into its folder (the ``fused`` artifact):

    map.ply               final voxel map (x y z, red green blue, count, frames)
    scaled_depth/         per-frame scaled z-depth (TUM 16-bit PNG) + index.csv
    camera_poses.tum      T_world_camera of every fused frame
    scales.csv            per-frame pairs, estimate, flag, used scale (and shift)
    *.png                 report figures
"""

from __future__ import annotations

import csv
import io
import shutil
import time
from collections.abc import Iterator
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Literal, NamedTuple

import numpy as np
from pydantic import Field

from toolkit.depth.protocol import DepthPrediction
from toolkit.depth.store import DepthStore
from toolkit.deskew import deskew_sequence
from toolkit.eval.depth import DepthReference, ErrorAccumulator, depth_errors, scale_error
from toolkit.eval.map_accuracy import MeshDistance
from toolkit.fusion.cloud import valid_pixels
from toolkit.fusion.exposure import (
    EXPOSURE_FILE,
    frames_to_solve,
    gain_error,
    read_exposure_gains,
    solve_exposure,
    spread_gains,
    write_exposure_gains,
)
from toolkit.fusion.pipeline import (
    FramePairs,
    Fusion,
    FusionConfig,
    PairStats,
    pose_arrays,
    scaled_at_pairs,
    scans_covered,
)
from toolkit.fusion.projection import sample_depth
from toolkit.fusion.refine import Refinement
from toolkit.fusion.scale import SmoothedScale, depth_order_agreement
from toolkit.fusion.voxel_map import MapArrays
from toolkit.geometry import Trajectory
from toolkit.heldout import heldout_frames
from toolkit.io.atomic import atomic_write_text
from toolkit.io.prefetch import WriteBehind, prefetched
from toolkit.recipe.checkpoint import Checkpoint
from toolkit.recipe.stage import Stage, StageConfig, StageContext, StageError
from toolkit.recipe.timing import work_metrics
from toolkit.sensors import Sequence
from toolkit.settings import AddedOptions


class FuseConfig(FusionConfig, StageConfig, AddedOptions):
    """Settings of the ``fuse`` stage: the fusion's own (``FusionConfig``) plus these."""

    # Left at their defaults, the hold-out settings (session 27) are not part of the
    # settings: fuse stages made before them keep their cache key.
    added_off = {"holdout_every": 0, "holdout_frame_stride": 1}

    # Where T_world_base comes from: the upstream 'trajectory' artifact (slam2d), the
    # sequence's ground truth, or the first of those that exists (auto).
    poses: Literal["auto", "trajectory", "groundtruth"] = "auto"
    # Between the trajectory's poses (slam2d's: at the scan stamps) the robot moves as the
    # sequence's wheel odometry says, when it has one; false: a straight line between them
    # (1.2 deg off at a turn's start on the simulated house). null: as the slam2d stage
    # that made the trajectory placed its camera poses (its use_odometry), so the frames
    # are fused where the TSDF and splat stages, which take those poses, see them; with
    # ground-truth poses, or a slam2d folder from before it recorded use_odometry, true.
    odometry: bool | None = None
    write_depth: Literal["png", "npy", "none"] = "png"
    # Read the next frames and write the scaled depth in a thread: the stage finishes
    # sooner (quickstart 80 -> 61-71 s), but its measured fusion time then includes that
    # thread's competition for the cores. Benchmarks that report the fusion's time: false.
    prefetch: bool = True
    # depth comparisons (lidar and truth) nearer than this
    eval_max_depth_m: float = Field(10.0, gt=0)
    mesh_eval_frames: int = Field(30, ge=0)  # frames whose clouds are measured to the mesh
    mesh_eval_points: int = Field(200_000, ge=1)  # map points measured to the mesh (subsample)
    figure_frame: int | None = None  # frame shown in the report (None: the middle one)
    # Save the map built so far this often (seconds; 0: never), so that a killed run resumes
    # where it was instead of fusing every frame again. A save writes the whole voxel map
    # (about 0.1 KB per voxel: 0.3 GB for the quickstart's).
    checkpoint_every_s: float = Field(300.0, ge=0)
    # Leave out of the map (its points, colours, consensus and carving views, and the
    # exposure solve) the frames a splat stage with holdout_every / frame_stride of these
    # values holds out, at the same poses: the splats then start from a cloud that never
    # saw the images they are scored on. Their lidar still scales and smooths their
    # neighbours' depth (no image of theirs is in that). 0: every frame is fused.
    holdout_every: int = Field(0, ge=0, description="leave out the frames a splat stage "
                               "with this holdout_every holds out (0: none)")
    holdout_frame_stride: int = Field(1, ge=1, description="that splat stage's frame_stride")


def oracle_scale(gt_depth: np.ndarray, values: np.ndarray) -> float:
    """The scale ground truth gives a frame's prediction: the median of depth / prediction
    [H, W] over the pixels valid in both (NaN with 100 or fewer)."""
    ok = (gt_depth > 0) & np.isfinite(values) & (values > 0)
    if ok.sum() <= 100:
        return float("nan")
    return float(np.median(gt_depth[ok] / values[ok]))


def _pair_metrics(metrics: dict[str, object], stats: PairStats, prefix: str,
                  cap: float) -> int:
    """Unscaled and scaled depth errors of lidar pairs under ``prefix``; returns the count."""
    lidar, unscaled, scaled = stats.arrays()
    e_un = depth_errors(unscaled, lidar, max_depth=cap)
    e_sc = depth_errors(scaled, lidar, max_depth=cap)
    metrics.update(e_un.as_dict(f"{prefix}unscaled_"))
    metrics.update(e_sc.as_dict(f"{prefix}scaled_"))
    if e_un.count and e_un.rmse_m > 0:
        metrics[f"{prefix}rmse_ratio_scaled_unscaled"] = e_sc.rmse_m / e_un.rmse_m
    return int(e_un.count)


@dataclass
class FuseProgress:
    """What the stage has accumulated so far; a checkpoint holds it with the fusion's map."""

    oracle: np.ndarray  # [F] per-frame scale from ground truth (NaN: none)
    pairs: dict[int, FramePairs] = field(default_factory=dict)  # pass 1, by frame
    scales_done: int = 0  # frames of pass 1 done
    map_done: int = 0  # used frames of pass 2 done
    lid: PairStats = field(default_factory=PairStats)
    lid_valid: PairStats = field(default_factory=PairStats)  # at pixels the map uses
    lid_vis: PairStats = field(default_factory=PairStats)  # pairs both sensors see
    lid_ref_vis: PairStats = field(default_factory=PairStats)  # the same after refine
    acc_un: ErrorAccumulator = field(default_factory=ErrorAccumulator)
    acc_sc: ErrorAccumulator = field(default_factory=ErrorAccumulator)
    acc_ref: ErrorAccumulator = field(default_factory=ErrorAccumulator)
    refinements: list[Refinement] = field(default_factory=list)
    frame_clouds: list[np.ndarray] = field(default_factory=list)  # for map-to-mesh per frame
    depth_rows: list[str] = field(default_factory=list)  # scaled_depth/index.csv
    pose_rows: list[tuple[float, np.ndarray]] = field(default_factory=list)
    fig_data: tuple | None = None
    t_core: float = 0.0  # wall seconds of the fusion's own work
    c_core: float = 0.0  # CPU seconds of the same: the machine may be shared
    fusion: dict[str, object] | None = None  # Fusion.state() when saved
    gains: np.ndarray | None = None  # [U, 3] exposure gains of the used frames (exposure: gain)
    gains_solved: np.ndarray | None = None  # [U] bool: solved (else interpolated)
    exposure: dict[str, float] = field(default_factory=dict)  # the gain solve's figures

    def add_errors(self, fp: FramePairs, disparity: bool, scale_shift: tuple[float, float],
                   pred: DepthPrediction, scaled: np.ndarray, refined: np.ndarray | None,
                   valid: np.ndarray, g: np.ndarray | None, cap: float) -> None:
        """One frame's depth against its lidar pairs and, if given, the true depth ``g``:
        unscaled, ``scaled`` (the frame's scale) and ``refined`` (after the shape
        correction; None without one). ``valid`` [H, W]: the pixels the map uses."""
        unscaled_pairs = scaled_at_pairs(fp, disparity, 1.0, 0.0)
        scaled_pairs = scaled_at_pairs(fp, disparity, *scale_shift)
        z = fp.lidar.z
        self.lid.add(z, unscaled_pairs, scaled_pairs)
        # Pairs both sensors see by the sensors alone: a set chosen by the prediction's own
        # edges would drop its worst pairs (the simulated `paper` row kept 58 % of the
        # pairs, the others 87 %, and scored 0.071 against 0.096 on these).
        v = fp.seen_by_both
        self.lid_vis.add(z[v], unscaled_pairs[v], scaled_pairs[v])
        if refined is not None:
            # In-sample for the lidar: the correction was fitted to these pairs.
            self.lid_ref_vis.add(z[v], unscaled_pairs[v],
                                 sample_depth(refined, fp.lidar)[v].astype(np.float64))
        if len(fp.lidar):
            px = fp.lidar.pixel
            ok = valid[np.clip(px[:, 1], 0, valid.shape[0] - 1),
                       np.clip(px[:, 0], 0, valid.shape[1] - 1)]
            self.lid_valid.add(z[ok], unscaled_pairs[ok], scaled_pairs[ok])
        if g is not None:
            ref = DepthReference(g, max_depth=cap)  # tested and widened once, used 3 times
            # A depth kind's values are its unscaled depth: as_depth(1, 0) only copies them
            # and puts NaN where they are not > 0, which the errors leave out anyway.
            self.acc_un.add(pred.as_depth(1.0, 0.0) if pred.is_disparity else pred.values, ref)
            self.acc_sc.add(scaled, ref)
            if refined is not None:
                self.acc_ref.add(refined, ref)


def _depth_metrics(cfg: FuseConfig, st: FuseProgress, refined: bool, has_gt_depth: bool,
                   disparity: bool, sm: SmoothedScale, oracle: np.ndarray) -> dict[str, object]:
    """Depth errors against the lidar pairs and the true depth, scale errors, refine stats."""
    metrics: dict[str, object] = {}
    # The same depth cap as for the ground truth: a 2D lidar sees 12 m down a corridor,
    # where the camera's depth is guesswork that the map does not use either.
    cap = cfg.eval_max_depth_m
    n_all = _pair_metrics(metrics, st.lid, "lidar_", cap)
    # The same protocol on the pairs both sensors see (FramePairs.covisible: by the sensors
    # alone, the same pairs for every prediction). With ground-truth depth as the
    # prediction the all-pairs RMSE is 0.196 m on the simulated house against 0.011 m on
    # these pairs (0.095 m with the occlusion test alone, before session 24).
    n_vis = _pair_metrics(metrics, st.lid_vis, "lidar_visible_", cap)
    metrics["pairs_visible_fraction"] = n_vis / max(n_all, 1)
    _pair_metrics(metrics, st.lid_valid, "lidar_valid_", cap)
    if refined:
        _pair_metrics(metrics, st.lid_ref_vis, "lidar_visible_refined_", cap)
        done = [r for r in st.refinements if r.applied]
        metrics.update({
            "refine": cfg.refine, "refine_frames_applied": len(done),
            "refine_anchors_floor_median": float(np.median(
                [r.anchors_floor for r in st.refinements])) if st.refinements else 0.0,
            "refine_anchors_lidar_median": float(np.median(
                [r.anchors_lidar for r in st.refinements])) if st.refinements else 0.0,
            "refine_field_rms_median": float(np.median(
                [r.field_rms for r in done])) if done else 0.0,
            "refine_field_max": float(max(r.field_max for r in done)) if done else 0.0,
            "refine_regions": int(sum(r.regions for r in done)),
            "refine_frames_with_regions": sum(1 for r in done if r.regions),
        })
    if has_gt_depth:
        g_un, g_sc = st.acc_un.result(), st.acc_sc.result()
        metrics.update(g_un.as_dict("gt_unscaled_"))
        metrics.update(g_sc.as_dict("gt_scaled_"))
        if g_un.rmse_m > 0:
            metrics["gt_rmse_ratio_scaled_unscaled"] = g_sc.rmse_m / g_un.rmse_m
        if refined:
            g_ref = st.acc_ref.result()
            metrics.update(g_ref.as_dict("gt_refined_"))
            if g_un.rmse_m > 0:
                metrics["gt_rmse_ratio_refined_unscaled"] = g_ref.rmse_m / g_un.rmse_m
        if not disparity:
            metrics.update({f"{k}": v for k, v in scale_error(
                sm.scale, oracle).items() if k != "frames"})
            metrics.update({f"raw_{k}": v for k, v in scale_error(
                sm.raw_scale, oracle).items() if k != "frames"})
    return metrics


def _map_metrics(cfg: FuseConfig, seq: Sequence, raw: MapArrays, masks: dict[str, np.ndarray],
                 final: MapArrays, fused_poses: Trajectory | None,
                 frame_clouds: list[np.ndarray], has_masks: bool,
                 md: MeshDistance | None) -> dict[str, object]:
    """Moving-obstacle shares and distances of the map and per-frame clouds to the true mesh
    (``md``: the sequence's ground-truth mesh, None without one)."""
    metrics: dict[str, object] = {"dynamic_removal": cfg.dynamic_removal}
    if has_masks and len(raw):
        # Every share lacks what the lidar masked in the images; the fraction without any
        # removal comes from a run with dynamic_removal: false. Before carving: the map the
        # consensus and outlier steps leave with the carved voxels back in (those off the
        # consensus surface stay out), so that the two shares are over the same steps; the
        # raw map's share is before the consensus too, which drops static voxels (1.5 M on
        # the paper benchmark) and made carving look as if it added people.
        dyn = raw.label > 0.5  # [V]
        before = masks["keep"] | (masks["dynamic"] & ~masks["dynamic_off_surface"])  # [V]
        metrics["dynamic_fraction_raw"] = float(np.mean(dyn))
        metrics["dynamic_fraction_before_carving"] = float(np.mean(dyn[before])) if (
            before.any()) else 0.0
        metrics["dynamic_fraction"] = float(np.mean(final.label > 0.5)) if len(final) else 0.0
        metrics["dynamic_points_raw"] = int(dyn.sum())
        metrics["dynamic_points_before_carving"] = int((dyn & before).sum())
        metrics["dynamic_points"] = int((dyn & masks["keep"]).sum())
        static = raw.label <= 0.5
        metrics["static_points_removed_fraction"] = float(
            np.mean(masks["dynamic"][static])) if static.any() else 0.0
    if md is not None:
        from toolkit.eval.alignment import apply, map_to_world
        from toolkit.eval.map_accuracy import distance_stats

        # The SLAM map frame is not the simulator's world: one rigid transform first.
        S = map_to_world(seq, fused_poses.stamps, fused_poses.poses) if (
            fused_poses is not None) else None
        static_final = final.select(final.label <= 0.5) if has_masks else final
        # A fixed-stride subsample: point-to-mesh queries cost ~10 us each and the
        # statistics settle long before a few million points.
        step = max(1, len(static_final) // cfg.mesh_eval_points)
        metrics.update({f"map_to_mesh_{k}": v for k, v in distance_stats(
            md.distance(apply(S, static_final.points[::step]))).items()})
        if has_masks:
            # Static points the carving removed: if they lie off the true surface, the
            # carving removed depth errors rather than good geometry.
            gone = raw.select(masks["dynamic"] & (raw.label <= 0.5))
            if len(gone):
                step = max(1, len(gone) // 50_000)
                metrics["carved_static_to_mesh_median_m"] = float(np.median(
                    md.distance(apply(S, gone.points[::step]))))
        meds = [float(np.median(md.distance(apply(S, p)))) for p in frame_clouds if len(p)]
        if meds:
            metrics["frame_to_mesh_median_m"] = float(np.median(meds))
            metrics["frame_to_mesh_median_max_m"] = float(np.max(meds))
    return metrics


def _empty_map_message(cfg: FuseConfig, frames: int, voxels: int,
                       masks: dict[str, np.ndarray]) -> str:
    """Why no voxel is left, with the settings that decide it (Open3D would refuse to
    write the empty cloud with a message about the file)."""
    if voxels == 0:
        return (f"fuse: the map is empty: {frames} frame(s) fused, no voxel seen in "
                f"min_voxel_frames={cfg.min_voxel_frames} of them with a depth between "
                f"min_depth_m={cfg.min_depth_m} and max_depth_m={cfg.max_depth_m} (scaled "
                f"depths: see scales.csv and the depth stage's predictions); lower "
                f"min_voxel_frames or widen the depth range")
    steps = ", ".join(f"{k} {int(masks[k].sum())}" for k in ("dynamic", "consensus", "outlier")
                      if k in masks and masks[k].any())
    return (f"fuse: the map is empty: all {voxels} voxels were removed ({steps}); "
            f"switch off the step that took them (dynamic_removal, consensus, "
            f"outlier_neighbors: 0) to see the map it started from")


def load_base_trajectory(path: Path, seq: Sequence) -> Trajectory:
    """``T_world_base`` from a TUM file, or a folder holding one (slam2d's artifact).

    A file whose header says the poses are ``T_world_camera`` is converted with the rig.
    """
    from toolkit.geometry import inv_se3
    from toolkit.io.tum import read_tum

    p = Path(path)
    if p.is_dir():
        cands = [p / n for n in ("trajectory.tum", "poses_base.tum", "poses.tum")
                 if (p / n).exists()] or sorted(p.glob("*.tum"))
        if not cands:
            raise StageError(f"fuse: trajectory artifact {p} holds no .tum file")
        p = cands[0]
    traj = read_tum(p)
    if traj.child in ("camera", "camera_optical"):
        traj = traj.transform(T_right=inv_se3(seq.rig.T_base_camera))
        traj.child = "base_link"
    elif traj.child == "laser":
        traj = traj.transform(T_right=inv_se3(seq.rig.T_base_laser))
        traj.child = "base_link"
    return traj


class OdometryChoice(NamedTuple):
    """Whether fuse places the frames between the trajectory's poses with the wheel
    odometry (``use``), why (for the report), and whether that is a guess for a slam2d
    folder that does not say (``unrecorded``)."""

    use: bool
    why: str
    unrecorded: bool = False


def odometry_choice(setting: bool | None, trajectory: Path | None) -> OdometryChoice:
    """``setting`` (the stage's ``odometry``) where given, else as the slam2d run that wrote
    the ``trajectory`` artifact did (its ``use_odometry``), else true (ground-truth poses;
    a slam2d folder from before it recorded the setting, placed as it was then)."""
    from toolkit.slam2d.stage import recorded_use_odometry

    if setting is not None:
        return OdometryChoice(setting, f"`odometry: {str(setting).lower()}`")
    if trajectory is None:
        return OdometryChoice(True, "the default without a slam2d trajectory")
    try:
        recorded = recorded_use_odometry(trajectory)
    except StageError as exc:
        raise StageError(f"fuse: {exc}") from None
    if recorded is None:
        return OdometryChoice(
            True, f"slam2d's folder {trajectory} does not record its use_odometry", True)
    return OdometryChoice(recorded, f"as slam2d's `use_odometry: {str(recorded).lower()}`")


def metric_scale_warning(kind: str, scale_median: float | None) -> str | None:
    """What to say when a metric network's depth is far from the lidar's (median scale
    outside 2/3..3/2): a setting is off, not the network's accuracy. None otherwise."""
    if kind != "metric_depth" or scale_median is None or 2 / 3 <= scale_median <= 1.5:
        return None
    return (f"**The metric network's depth is {1 / scale_median:.3g} times the lidar's** "
            f"(median scale {scale_median:.3g} over the frames): a setting is likely off - "
            "the depth stage's output_scale (0.001 for a network in millimetres), "
            "canonical_focal (Metric3D: 1000) or input size, or the camera intrinsics. The "
            "map takes the lidar's scale either way; the unscaled figures are this far off.")


def figure_frame(wanted: int | None, frames: list[int], fused: list[int]) -> int:
    """The frame the report's lidar-overlay and depth figures show: ``wanted`` (else the
    middle of ``frames``), or the fused frame nearest it (with ``few_pairs: skip`` the
    wanted one may not be fused, and the figures were left out without a word)."""
    want = wanted if wanted in frames else frames[len(frames) // 2]
    if not fused or want in fused:
        return want
    return min(fused, key=lambda i: (abs(i - want), i))


class FuseStage(Stage):
    """Scale monocular depth with the lidar and fuse the frames into a coloured voxel map."""

    name = "fuse"
    Config = FuseConfig
    requires = ("sequence", "depth")
    # rig: a calibrated extrinsic (calibrate) over the sequence's own
    optional_requires = ("trajectory", "rig")
    provides = ("fused",)
    # 2: floor below base_link; scans off the trajectory unused; smoothing. 3: frames
    # backed by their own pairs keep their scale; moving pixels out of the written depth.
    # 4: the camera's exposure divided out of the map's colours (exposure: gain)
    # 5: regions around lidar runs the smooth shape field cannot follow rescaled (refine)
    # 6: robust's shift only where its inliers spread; a gap's frames take their nearest
    #    good frames' pair; pair edges tested on depth; carving sees a distorted image whole
    # 7: consensus distance to the surface's tangent plane; a lidar cell seen through by
    #    three beams; no return is no evidence; scans past +-180 deg tested
    # 8: clustered keeps the pairs near the densest ratio (no chain into outliers); a good
    #    frame's smoothing window as long before it as after it
    # 9: clustered's disparity refit starts from the best 2-point line among its cluster's
    #    pairs (a large positive shift had most frames low_inliers); the outlier-frame
    #    test's window keeps its length at the sequence's ends and beside lidar gaps;
    #    clustered's refit needs its own inliers to spread (a wall gets the scale alone);
    #    ratio's gate narrows to 3 robust sigmas of each frame's ratios; the map metrics'
    #    alignment fits on the frames the ground truth covers, no end slack
    # 10: the shape correction leaves out the pairs on moving obstacles, and a region
    #    whose other pairs agree with its depth is not rescaled (a passing person moved
    #    the wall behind); one consensus volume per camera heading (both faces of a
    #    10 cm wall seen from both sides were dropped); max_columns a maximum (rounded up);
    #    a region spans the depths its run covers (a far wall turned away kept its error);
    #    the lidar carves only cells some scan has hit (static tops just above or below
    #    the scan plane were removed); an exposure cell with a dark or clipped pixel is
    #    no observation (gains were compressed on bright walls)
    # 11: frames between the trajectory's poses are placed with the wheel odometry's
    #    motion; the co-visible pairs (lidar_visible_* metrics) also leave out those behind a
    #    neighbouring scan's static point, on or behind a moving obstacle the lidar saw, and
    #    on the near side of a range jump (ground-truth depth 0.095 -> 0.016 m from the
    #    lidar on them); the shape correction's anchors are unchanged
    # 12: the consensus band is 4 voxels, not 6 (surfaces just behind a nearer one kept;
    #    F@5cm 0.911 -> 0.915 simulated, 0.848 -> 0.853 network); odometry: null follows
    #    slam2d's use_odometry (the same poses for the shipped recipes)
    # 13: dynamic_beams also asks scans 6-128 s away (dynamic_far_offsets_s) on surfaces
    #    >= 10 cm wide: a person who stood still, then left, is masked in the frames of the
    #    stay (paper benchmark: people 0.51 -> 0.22 % of the simulated map)
    # 14: full-turn scans with a beam at both -pi and pi de-skewed a turn apart
    #     an image's nearest scans searched among the usable ones (next to scans without
    #     a trustworthy pose it got farther scans, or none)
    # 15: frames and scans within END_SLACK_S outside the trajectory's span are used even
    #     when a long gap follows that end (Trajectory.covers refused them)
    # 16: the exposure solve's pull between consecutive frames is Huber-reweighted like the
    #     edges (at full weight it moved frames whose overlaps fixed their gains)
    # 17: swept scans de-skewed with the trajectory's poses inside each sweep (ground
    #     truth's path samples; a slam2d pose of a next scan stamped before the sweep
    #     ends), beam by beam; constant velocity where it has none
    version = 17
    speed_settings = frozenset({"prefetch"})  # reading frames ahead changes no output

    def run(self, ctx: StageContext) -> None:
        from toolkit.io.sequence import read_sequence, sequence_with_rig

        cfg: FuseConfig = self.config  # type: ignore[assignment]
        fcfg = FusionConfig(**{k: getattr(cfg, k) for k in FusionConfig.model_fields})
        seq = read_sequence(ctx.artifact("sequence"))
        if ctx.has_artifact("rig"):
            seq = sequence_with_rig(seq, ctx.artifact("rig"))
        store = DepthStore(ctx.artifact("depth"))
        gt = seq.groundtruth
        # ---------------------------------------------------------------- poses
        traj, pose_note, pose_source = None, "", ""
        if cfg.poses in ("auto", "trajectory") and ctx.has_artifact("trajectory"):
            traj = load_base_trajectory(ctx.artifact("trajectory"), seq)
            pose_note = "Poses from the upstream `trajectory` artifact (2D lidar SLAM)."
            pose_source = "trajectory"
        elif cfg.poses in ("auto", "groundtruth") and gt is not None and gt.poses_base is not None:
            traj = gt.poses_base
            pose_source = "groundtruth"
            pose_note = ("**WARNING: no `trajectory` artifact upstream - fused with the "
                         "sequence's GROUND-TRUTH poses. Map accuracy here is not what the "
                         "method achieves with its own SLAM poses.**")
            ctx.log.warning("fuse: no trajectory artifact; using GROUND-TRUTH poses")
        if traj is None:
            if cfg.poses == "groundtruth":
                raise StageError(f"fuse: poses: groundtruth, but sequence {seq.name} has no "
                                 "ground-truth poses (groundtruth/poses_base.tum); set poses: "
                                 "auto (or trajectory) to fuse at a slam2d stage's poses (add "
                                 "one before fuse if there is none)")
            if cfg.poses == "trajectory":
                raise StageError("fuse: poses: trajectory, but no stage upstream provides a "
                                 "trajectory; add a slam2d stage before fuse, or set poses: "
                                 "groundtruth for a sequence with ground-truth poses")
            raise StageError(f"fuse: no poses: no stage upstream provides a trajectory and "
                             f"sequence {seq.name} has no ground-truth poses; add a slam2d "
                             "stage before fuse")
        # Scans swept while moving (time_increment) are placed beam by beam first.
        seq = deskew_sequence(seq, traj)
        odometry = odometry_choice(
            cfg.odometry, ctx.artifact("trajectory") if pose_source == "trajectory" else None)
        frame_poses, scan_poses, inside = pose_arrays(seq, traj, odometry.use)
        if seq.odometry is not None:
            pose_note += (" Between its poses the frames move as the wheel odometry says "
                          f"({odometry.why}; `odometry: false` for a straight line)."
                          if odometry.use else " Between its poses the frames lie on the "
                          f"straight line ({odometry.why}).")
            if odometry.unrecorded:
                ctx.log.warning("fuse: %s: frames placed with the wheel odometry as before; "
                                "rerun slam2d (--from slam2d) for fuse to follow its "
                                "use_odometry, or set fuse's odometry", odometry.why)
        views_dir = ctx.stage_dir / "carve_views"  # until the map is finished
        fusion = Fusion(seq, fcfg, frame_poses, scan_poses, views_dir,
                        scan_covered=scans_covered(seq, traj))
        disparity = store.kind == "relative_disparity"
        frames = [i for i in store.indices if i < len(seq.frames) and inside[i]]
        if not frames:
            raise StageError("fuse: no frame has both a depth prediction and a pose")
        has_gt_depth = gt is not None and gt.depth_paths is not None
        has_masks = gt is not None and gt.mask_paths is not None
        md = None
        if gt is not None and gt.mesh_path is not None:
            # Read now: a broken mesh found after fusing an hour of frames loses the hour.
            try:
                md = MeshDistance(gt.mesh_path)
            except (ValueError, RuntimeError, OSError) as exc:
                raise StageError(
                    f"fuse: ground-truth mesh {gt.mesh_path} cannot be used ({exc}): replace "
                    "it with a triangle mesh in PLY, or remove it to fuse without the "
                    "map-to-mesh figures") from exc
        # ---------------------------------------------------------------- resume
        t_start = time.perf_counter()
        ckpt = Checkpoint(ctx.stage_dir / "checkpoint.pkl", ctx.resume_key,
                          cfg.checkpoint_every_s, ctx.log)
        st: FuseProgress | None = ckpt.load(lambda x: isinstance(x, FuseProgress) and all(
            hasattr(x, f.name) for f in fields(FuseProgress)) and len(x.oracle) == len(frames))
        from toolkit.io.depth import file_complete

        # The checkpoint promises the scaled depth of the frames it fused: one of them gone
        # or cut short since (by hand, power loss) was kept, and the stage finished with a
        # frame its index.csv lists missing. Their map is in the checkpoint, so start afresh.
        broken = [] if st is None else [
            name for name in (row.split(",")[2] for row in st.depth_rows)
            if not file_complete(ctx.stage_dir / "scaled_depth" / name)]
        if broken:
            ctx.log.warning("fuse: %d scaled depth file(s) of the checkpoint are missing or "
                            "cut short (%s); starting afresh", len(broken),
                            ", ".join(broken[:3]) + (", ..." if len(broken) > 3 else ""))
            st = None
        if st is not None:
            if st.fusion is not None:
                fusion.restore(st.fusion)
            st.fusion = None
            ctx.log.info("fuse: resuming after %d/%d frames' scales and %d frames' map",
                         st.scales_done, len(frames), st.map_done)
        else:
            st = FuseProgress(oracle=np.full(len(frames), np.nan))
            # Views of another run (other settings) must not be taken for this one's.
            for old in views_dir.glob("*.npy"):
                old.unlink()
        resumed = (st.scales_done, st.map_done)

        def save_checkpoint() -> None:
            st.fusion = fusion.state()
            ckpt.save(st)
            st.fusion = None

        # ---------------------------------------------------------------- pass 1: scales
        # The oracle scale (from ground-truth depth) is taken in the map pass, which reads
        # the ground truth anyway; the frames that pass skips get theirs at its end.
        oracle_gt = has_gt_depth and not disparity
        ahead = 2 if cfg.prefetch else 0
        todo = frames[st.scales_done:]
        for i, pred in ctx.progress(prefetched(store.read, todo, ahead), total=len(todo),
                                    description="fuse: scales"):
            t0, c0 = time.perf_counter(), time.process_time()
            st.pairs[i] = fusion.frame_pairs(i, pred)
            st.t_core += time.perf_counter() - t0
            st.c_core += time.process_time() - c0
            st.scales_done += 1
            if ckpt.due():
                save_checkpoint()
        pairs, oracle = st.pairs, st.oracle
        rho, rho_frames = depth_order_agreement((pairs[i].lidar.z, pairs[i].pred)
                                                for i in frames)
        if rho_frames and (rho > 0.3 if disparity else rho < -0.3):
            said, meant = (("relative_disparity", "relative_depth or metric_depth")
                           if disparity else (store.kind, "relative_disparity"))
            raise StageError(
                f"fuse: the predictions {'rise' if disparity else 'fall'} as the lidar depth "
                f"rises (median rank correlation {rho:+.2f} over {rho_frames} frames): the "
                f"network outputs {'depth' if disparity else 'disparity'}, but the depth "
                f"stage says output: {said}. Fix: set the depth stage's output to {meant} "
                "(what the network's documentation says it outputs) and rerun from it "
                "(--from depth)")
        estimates = [pairs[i].estimate for i in frames]
        sm = fusion.smooth(estimates, [pairs[i] for i in frames], disparity)
        if not sm.used.any():
            landed = float(np.median([len(pairs[i].lidar) for i in frames]))
            valid = float(np.median([e.pairs for e in estimates]))
            if landed >= cfg.min_pairs and valid < cfg.min_pairs:
                # The lidar lands in the image; the predictions there are not usable.
                raise StageError(
                    f"fuse: no frame got a scale - a median {landed:g} lidar points per frame "
                    f"land in the image, but only {valid:g} have a valid prediction there "
                    f"(finite and positive; min_pairs {cfg.min_pairs}). Check the depth "
                    f"stage's predictions (its output kind and output_scale) in "
                    f"{store.root}")
            raise StageError(
                f"fuse: no frame got a scale - median {landed:g} lidar points per frame land "
                f"in the image, {valid:g} pairs with a valid prediction (min_pairs "
                f"{cfg.min_pairs}). Check T_base_laser / T_base_camera (does the lidar land in "
                "the image?), the scan stamps, or use scale: none for a metric network")
        used = [(j, i) for j, i in enumerate(frames) if sm.used[j]]
        # The splat stage's held-out frames stay out of everything that reaches the map
        # (exposure solve and map pass below), after the scales: their lidar pairs were
        # fair evidence for their neighbours' scale, their images are the test.
        held_out = set(heldout_frames(
            seq, ctx.artifact("trajectory") if pose_source == "trajectory" else None,
            cfg.poses, cfg.holdout_frame_stride, cfg.holdout_every))
        n_before = len(used)
        if held_out:
            used = [(j, i) for j, i in used if i not in held_out]
            ctx.log.info("fuse: %d frame(s) held out of the map for the splat stage "
                         "(holdout_every %d, frame_stride %d)", len(held_out),
                         cfg.holdout_every, cfg.holdout_frame_stride)
            if not used:
                raise StageError("fuse: holdout_every leaves no frame to fuse")
        # ---------------------------------------------------------------- exposure
        if cfg.exposure == "gain" and st.gains is None:
            st.gains, st.gains_solved, st.exposure = self._solve_exposure(
                ctx, fusion, store, seq, used, sm, ahead)
            # Part of the fusion's work: in its throughput figures (Table II) too.
            st.t_core += st.exposure["exposure_work_seconds"]
            st.c_core += st.exposure["exposure_work_cpu_seconds"]
            if cfg.checkpoint_every_s > 0:
                save_checkpoint()  # the map pass must use these gains if it resumes
        # ---------------------------------------------------------------- pass 2: map
        out_depth = ctx.stage_dir / "scaled_depth"
        if cfg.write_depth != "none":
            out_depth.mkdir(parents=True, exist_ok=True)
        fig_frame = figure_frame(cfg.figure_frame, frames, [i for _, i in used])
        eval_frames = set(np.linspace(0, len(frames) - 1, min(cfg.mesh_eval_frames,
                                                              len(frames))).astype(int).tolist())
        gain_of = {} if st.gains is None else {i: st.gains[k] for k, (_, i) in enumerate(used)}

        def load_pass2(ji: tuple[int, int]) -> tuple[
                DepthPrediction, np.ndarray, np.ndarray | None, np.ndarray | None]:
            i = ji[1]
            return (store.read(i), seq.frames[i].image,
                    gt.mask(i) if has_masks else None,  # type: ignore[union-attr]
                    gt.depth(i) if has_gt_depth else None)  # type: ignore[union-attr]

        # Reading the next frames and writing the scaled depth run in threads (file
        # decoding and encoding release the GIL), unless prefetch is off.
        todo2 = used[st.map_done:]
        with WriteBehind(threaded=cfg.prefetch) as writes:
            for (j, i), (pred, rgb, mask, g) in ctx.progress(
                    prefetched(load_pass2, todo2, ahead), total=len(todo2),
                    description="fuse: map"):
                s, t = float(sm.scale[j]), float(sm.shift[j])
                fp = pairs[i]
                t0, c0 = time.perf_counter(), time.process_time()
                alpha_scaled = pred.as_depth(s, t)
                scaled, refinement = fusion.refine(i, alpha_scaled, fp)
                # The map's pixel mask, also the lidar pairs' "on pixels the map uses".
                valid = valid_pixels(scaled, fusion.cloud_opts)
                fusion.integrate(i, scaled, rgb, labels=mask, valid=valid, gain=gain_of.get(i))
                st.t_core += time.perf_counter() - t0
                st.c_core += time.process_time() - c0
                st.refinements.append(refinement)
                st.add_errors(fp, disparity, (s, t), pred, alpha_scaled,
                              scaled if fusion.refiner is not None else None, valid, g,
                              cfg.eval_max_depth_m)
                if oracle_gt and g is not None:
                    st.oracle[j] = oracle_scale(g, pred.values)
                if j in eval_frames and gt is not None and gt.mesh_path is not None:
                    from toolkit.fusion.cloud import depth_to_points

                    # Every stride-th pixel, as before near_stride: the figure is the accuracy of
                    # the frame's depth, which thinning the near pixels would skew to far ones.
                    pts, _, _ = depth_to_points(scaled, rgb, fusion.rays, fusion.T_world_camera(i),
                                                replace(fusion.cloud_opts, near_stride=0), mask)
                    st.frame_clouds.append(pts[:: max(1, len(pts) // 10000)])
                if cfg.write_depth != "none":
                    from toolkit.io.depth import write_depth

                    name = f"{i:06d}.{cfg.write_depth}"
                    moving = fusion.moving_pixels(i, scaled)
                    out = scaled if moving is None else np.where(moving, np.nan, scaled)
                    writes.submit(write_depth, out_depth / name, out)  # NaN becomes 0
                    st.depth_rows.append(f"{i},{seq.frames[i].stamp!r},{name},{s!r},{t!r}")
                st.pose_rows.append((seq.frames[i].stamp, fusion.T_world_camera(i)))
                if i == fig_frame:
                    # The per-frame-scaled depth last: a checkpoint of an older run
                    # ends at the scale.
                    st.fig_data = (i, rgb, pred.as_depth(1.0, 0.0), scaled, g, fp, s,
                                   alpha_scaled)
                st.map_done += 1
                if ckpt.due():
                    writes.flush()  # the checkpoint promises these frames' files
                    save_checkpoint()
        if oracle_gt:  # the frames the map pass skipped (flagged or held out)
            mapped = np.zeros(len(frames), bool)
            mapped[[j for j, _ in used]] = True
            for j in np.flatnonzero(~mapped & np.isnan(st.oracle)):
                i = frames[j]
                st.oracle[j] = oracle_scale(gt.depth(i), store.read(i).values)  # type: ignore[union-attr]
        t0, c0 = time.perf_counter(), time.process_time()
        raw, masks = fusion.finish()
        t_finish = time.perf_counter() - t0
        c_finish = time.process_time() - c0
        final = raw.select(masks["keep"])
        if len(final) == 0:
            raise StageError(_empty_map_message(cfg, len(frames), len(raw), masks))
        wall = time.perf_counter() - t_start
        # ---------------------------------------------------------------- outputs
        from toolkit.fusion.voxel_map import write_map_ply
        from toolkit.io.tum import write_tum

        write_map_ply(ctx.stage_dir / "map.ply", final)
        if cfg.write_depth != "none":
            atomic_write_text(out_depth / "index.csv",
                              "index,stamp,file,scale,shift\n" + "\n".join(st.depth_rows) + "\n")
        fused_poses = Trajectory(np.array([p[0] for p in st.pose_rows]),
                                 np.stack([p[1] for p in st.pose_rows]), "world",
                                 "camera") if st.pose_rows else None
        if fused_poses is not None:
            write_tum(ctx.stage_dir / "camera_poses.tum", fused_poses,
                      "camera poses of the fused frames")
        self._write_scales(ctx.stage_dir / "scales.csv", seq, frames, estimates, sm, oracle)
        if st.gains is not None:
            # Every frame of the sequence gets a gain (those not fused interpolated between
            # their fused neighbours): the tsdf and splat stages may use frames fuse did not.
            fused_at = np.array([i for _, i in used])
            solved = np.zeros(len(seq.frames), bool)
            solved[fused_at[st.gains_solved]] = True
            write_exposure_gains(ctx.stage_dir / EXPOSURE_FILE,
                                 [(i, f.stamp) for i, f in enumerate(seq.frames)],
                                 spread_gains(st.gains, fused_at, len(seq.frames)), solved)
        ctx.provide("fused", ctx.stage_dir)
        # ---------------------------------------------------------------- metrics
        n_used = len(used)  # the frames the map pass fused
        metrics: dict[str, object] = {
            "frames": len(frames), "frames_fused": n_used,
            "frames_flagged": int(sum(f != "ok" for f in sm.flag)),
            "frames_few_pairs": int(sum(f == "few_pairs" for f in sm.flag)),
            "frames_outlier": int(sum(f == "outlier_frame" for f in sm.flag)),
            "frames_low_inliers": int(sum(f == "low_inliers" for f in sm.flag)),
            # Which frames (up to 50), to look them up in scales.csv and the figure.
            "frames_outlier_indices": [int(i) for i, f in zip(frames, sm.flag, strict=True)
                                       if f == "outlier_frame"][:50],
            "pairs_per_frame_median": float(np.median([e.pairs for e in estimates])),
            "pairs_visible_per_frame_median": float(np.median(
                [int(pairs[i].seen_by_both.sum()) for i in frames])),
            "depth_kind": store.kind, "scale_method": cfg.scale,
            # The lidar's scale over the frames it was used on (a metric network's: ~1).
            "scale_median": float(np.median(sm.scale[sm.used])),
            "poses": pose_source,
            # Frames between the poses placed with the wheel odometry (false: on the
            # straight line, or the sequence has none).
            "poses_follow_odometry": bool(odometry.use and seq.odometry is not None),
            "map_points": len(final), "map_points_raw": len(raw),
            "map_points_removed_dynamic": int(masks["dynamic"].sum()),
            "map_points_removed_outlier": int(masks["outlier"].sum()),
            "map_points_removed_consensus": int(masks["consensus"].sum()),
            "fusion_fps": n_used / max(st.t_core + t_finish, 1e-9),
            "fusion_fps_per_frame_only": n_used / max(st.t_core, 1e-9),
            "fusion_fps_cpu": n_used / max(st.c_core + c_finish, 1e-9),
            "fusion_fps_per_frame_only_cpu": n_used / max(st.c_core, 1e-9),
            "finish_seconds": t_finish,
            "lidar_dynamic_beams": int(sum(int(b.sum()) for b in fusion.beam_dynamic)),
            "points_masked_dynamic": fusion.points_masked_dynamic,
            "stage_seconds": wall,
            # Frames an interrupted run had done, taken from its checkpoint.
            "frames_resumed_scales": resumed[0], "frames_resumed_map": resumed[1],
            "checkpoints_saved": ckpt.saves, "checkpoint_seconds": ckpt.seconds,
            **work_metrics(st.t_core + t_finish, st.c_core + c_finish, n_used),
        }
        if held_out:
            # Those the map pass would have fused otherwise (a flagged one was out anyway).
            metrics["frames_held_out"] = n_before - n_used
            metrics["frames_held_out_indices"] = sorted(held_out)
        metrics.update(_depth_metrics(cfg, st, fusion.refiner is not None, has_gt_depth,
                                      disparity, sm, oracle))
        metrics.update(st.exposure)
        metrics.update(_map_metrics(cfg, seq, raw, masks, final, fused_poses, st.frame_clouds,
                                    has_masks, md))
        ctx.add_metrics(metrics)
        # ---------------------------------------------------------------- report
        self._report(ctx, cfg, seq, metrics, pose_note, st.fig_data, frames, sm, oracle, store,
                     raw, masks, final, traj)
        ckpt.remove()  # every output is written: a rerun has nothing to resume
        shutil.rmtree(views_dir, ignore_errors=True)

    @staticmethod
    def _solve_exposure(ctx: StageContext, fusion: Fusion, store: DepthStore, seq: Sequence,
                        used: list[tuple[int, int]], sm: SmoothedScale, ahead: int) -> tuple[
                            np.ndarray, np.ndarray, dict[str, float]]:
        """Every used frame's exposure gain [U, 3] (``toolkit.fusion.exposure``), which of
        them were solved [U] bool (the others interpolated) and the solve's figures, from a
        sparse pass over the frames' scaled depth."""
        t0 = time.perf_counter()

        def load(ji: tuple[int, int]) -> tuple[DepthPrediction, np.ndarray]:
            return store.read(ji[1]), seq.frames[ji[1]].image

        opts = fusion.cfg.exposure_options()
        # A long drive is observed on every n-th frame (and the last); the others get
        # their neighbours' gains, interpolated.
        at, max_cells = frames_to_solve(len(used), opts)
        solved = [used[k] for k in at]
        work = [0.0, 0.0]  # the fusion's own work, file reading excluded (as for the map)

        def observations() -> Iterator[tuple[np.ndarray, np.ndarray]]:
            for (j, i), (pred, rgb) in ctx.progress(prefetched(load, solved, ahead),
                                                    total=len(solved),
                                                    description="fuse: exposure"):
                t1, c1 = time.perf_counter(), time.process_time()
                out = fusion.exposure_observations(
                    i, pred.as_depth(float(sm.scale[j]), float(sm.shift[j])), rgb, max_cells)
                work[0] += time.perf_counter() - t1
                work[1] += time.process_time() - c1
                yield out

        gains, sol, n_obs = solve_exposure(observations(), at, len(used), opts)
        wall, cpu = work[0] + sol.seconds, work[1] + sol.cpu_seconds
        figures = {"exposure_observations": float(n_obs), "exposure_edges": float(sol.edges),
                   "exposure_frame_step": float(at[1] - at[0]) if len(at) > 1 else 1.0,
                   "exposure_frames_solved": float(len(at)),
                   "exposure_frames_linked": float(sol.frames_linked),
                   "exposure_groups": float(sol.groups),
                   "exposure_outlier_edges": float(sol.outlier_edges),
                   "exposure_residual_log_rms": sol.residual_log_rms,
                   "exposure_gain_min": float(gains.min()),
                   "exposure_gain_max": float(gains.max()),
                   "exposure_seconds": time.perf_counter() - t0,
                   "exposure_work_seconds": wall, "exposure_work_cpu_seconds": cpu}
        gt = seq.groundtruth
        if gt is not None and gt.exposure_gain is not None:
            truth = gt.exposure_gain[[i for _, i in used]]
            figures.update({f"exposure_{k}": v for k, v in gain_error(gains, truth).items()})
        if sol.frames_linked < len(solved):
            ctx.log.warning("fuse: exposure: %d of %d frames share no surface with another; "
                            "their gains follow their neighbours'",
                            len(solved) - sol.frames_linked, len(solved))
        if sol.groups > 1:
            ctx.log.warning("fuse: exposure: the frames fall into %d groups that share no "
                            "surface with each other; each group's gains are taken as equal "
                            "to the next one's where they meet in time", sol.groups)
        ctx.log.info("fuse: exposure gains %.3f-%.3f from %d frame pairs (residual %.1f %%)",
                     figures["exposure_gain_min"], figures["exposure_gain_max"], sol.edges,
                     100 * sol.residual_log_rms)
        solved_mask = np.zeros(len(used), bool)
        solved_mask[at] = True
        return gains, solved_mask, figures

    @staticmethod
    def _write_scales(path: Path, seq: Sequence, frames: list[int], estimates: list,
                      sm: object, oracle: np.ndarray) -> None:
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(["frame", "stamp", "pairs", "inliers", "raw_scale", "raw_shift", "flag",
                    "scale", "shift", "used", "oracle_scale"])
        for j, i in enumerate(frames):
            e = estimates[j]
            w.writerow([i, repr(float(seq.frames[i].stamp)), e.pairs, e.inliers,
                        f"{e.scale:.6g}", f"{e.shift:.6g}", sm.flag[j],  # type: ignore[attr-defined]
                        f"{sm.scale[j]:.6g}", f"{sm.shift[j]:.6g}",  # type: ignore[attr-defined]
                        int(sm.used[j]), f"{oracle[j]:.6g}"])  # type: ignore[attr-defined]
        atomic_write_text(path, buf.getvalue())

    @staticmethod
    def _report(ctx: StageContext, cfg: FuseConfig, seq: Sequence, m: dict, pose_note: str,
                fig_data: object, frames: list[int], sm: object, oracle: np.ndarray,
                store: DepthStore, raw: object, masks: dict, final: object,
                traj: Trajectory) -> None:
        from toolkit.fusion import figures

        sid = ctx.stage_id
        md = [pose_note] if pose_note else []
        backend = store.meta.get("backend", "?")
        if backend == "simulated":
            md.append("Depth input: **simulated** monocular predictions (made from ground truth "
                      "with documented errors), not a network.")
        if m["frames_resumed_scales"] or m["frames_resumed_map"]:
            md.append(f"Resumed an interrupted run from its checkpoint: "
                      f"{m['frames_resumed_scales']}/{m['frames']} frames' scales and "
                      f"{m['frames_resumed_map']}/{m['frames_fused']} frames of the map "
                      "were kept.")
        md.append(f"Scale estimator `{cfg.scale}` on `{store.kind}` predictions; "
                  f"{m['frames_fused']}/{m['frames']} frames fused, {m['frames_flagged']} "
                  f"flagged (too few lidar pairs: {m['frames_few_pairs']}, too few of them "
                  f"agreeing: {m.get('frames_low_inliers', 0)}, scale an outlier among its "
                  f"neighbours: {m['frames_outlier']}"
                  + (f", frames {', '.join(map(str, m['frames_outlier_indices']))}"
                     if 0 < m["frames_outlier"] <= 10 else "") + "); median "
                  f"{m['pairs_per_frame_median']:.0f} lidar pairs per frame "
                  f"({m['pairs_visible_per_frame_median']:.0f} seen by both sensors).")
        if "frames_held_out" in m:
            md.append(f"{m['frames_held_out']} frames held out of the map (`holdout_every: "
                      f"{cfg.holdout_every}`, `holdout_frame_stride: "
                      f"{cfg.holdout_frame_stride}`): those a splat stage with these settings "
                      "scores its held-out PSNR on; their lidar still took part in the scales.")
        rows = [("vs lidar (paper's protocol), all pairs", "lidar_unscaled_", "lidar_scaled_"),
                ("vs lidar, pairs both sensors see (not occluded, moving or beside a jump)",
                 "lidar_visible_unscaled_", "lidar_visible_scaled_"),
                ("vs lidar, pairs on pixels the map uses", "lidar_valid_unscaled_",
                 "lidar_valid_scaled_")]
        if "lidar_visible_refined_scaled_count" in m:
            rows.append(("vs lidar, pairs both sensors see, after the shape correction "
                         "(fitted to most of them: in-sample)", "lidar_visible_unscaled_",
                         "lidar_visible_refined_scaled_"))
        if "gt_scaled_rmse_m" in m:
            rows.append(("vs ground-truth depth, whole images", "gt_unscaled_", "gt_scaled_"))
        if "gt_refined_rmse_m" in m:
            rows.append(("vs ground-truth depth, whole images, after the shape correction",
                         "gt_unscaled_", "gt_refined_"))
        table = ["| reference | RMSE unscaled (m) | RMSE scaled (m) | AbsRel scaled | "
                 "delta<1.25 scaled |", "|---|---:|---:|---:|---:|"]
        for name, a, b in rows:
            if not m.get(a + "count"):
                continue
            table.append(f"| {name} | {m[a + 'rmse_m']:.3f} | {m[b + 'rmse_m']:.3f} | "
                         f"{m[b + 'absrel']:.3f} | {m[b + 'delta1']:.3f} |")
        md.append("\n".join(table))
        off = metric_scale_warning(store.kind, m.get("scale_median"))
        if off:
            ctx.log.warning("fuse: %s", off.replace("**", ""))
            md.append(off)
        if store.kind != "metric_depth":
            md.append("Unscaled: the prediction as it comes, its values read as metres (a "
                      f"{store.kind.replace('_', ' ')} has no unit: the figure is what using "
                      "it without the lidar's scale would cost).")
        if "refine_frames_applied" in m:
            md.append(f"Shape correction `{cfg.refine}` (a smooth log-depth field per frame, "
                      f"{cfg.refine_grid[0]}x{cfg.refine_grid[1]} nodes) on "
                      f"{m['refine_frames_applied']}/{m['frames_fused']} frames; median anchors "
                      f"per frame: {m['refine_anchors_floor_median']:.0f} floor, "
                      f"{m['refine_anchors_lidar_median']:.0f} lidar; median field RMS "
                      f"{100 * m['refine_field_rms_median']:.1f} %, largest "
                      f"{100 * m['refine_field_max']:.1f} %. "
                      + (f"Regions the field could not follow (a room seen through a doorway) "
                         f"rescaled to the lidar: {m['refine_regions']} on "
                         f"{m['refine_frames_with_regions']} frames. "
                         if m.get("refine_regions") else "")
                      + ("The map and the scaled depth written for later stages are the "
                         "corrected ones" if cfg.write_depth != "none" else
                         "The map is built from the corrected depth")
                      + "; the rows without "
                      "'shape correction' are the per-frame scale alone (the paper's method).")
        consensus = (f"{m['map_points_removed_consensus']} farther than "
                     f"{cfg.consensus_m * 100:g} cm from the multi-view consensus surface, "
                     if cfg.consensus else "")
        extra = [f"map: {m['map_points']} voxels of {cfg.voxel_size_m * 100:g} cm "
                 f"({m['map_points_removed_dynamic']} removed as moving, {consensus}"
                 f"{m['map_points_removed_outlier']} statistical outliers)",
                 f"fusion throughput {m['fusion_fps']:.1f} frames/s wall clock, "
                 f"{m['fusion_fps_cpu']:.1f} frames/s of CPU time (network and file reading "
                 "excluded" + ("; files were read and written meanwhile in a thread, "
                               "`prefetch: false` times the fusion alone)" if cfg.prefetch
                               else ")")]
        if "dynamic_fraction" in m and cfg.dynamic_removal:
            extra.append(f"map points on moving obstacles: {100 * m['dynamic_fraction']:.2f} % "
                         f"({m['dynamic_points']} voxels); without carving, after the same "
                         f"consensus and outlier steps, "
                         f"{100 * m['dynamic_fraction_before_carving']:.2f} % "
                         f"({m['dynamic_points_before_carving']} voxels); "
                         f"{m['points_masked_dynamic']} image points masked by lidar-detected "
                         "moving obstacles before any of it")
        elif "dynamic_fraction" in m:
            extra.append(f"map points on moving obstacles, nothing removing them "
                         f"(`dynamic_removal: false`): {100 * m['dynamic_fraction']:.2f} % "
                         f"({100 * m['dynamic_fraction_raw']:.2f} % of the raw map, before the "
                         "consensus and outlier steps, which drop some of them too)")
        if "map_to_mesh_mean_m" in m:
            # With ground-truth masks the points labelled as moving people are left out (of
            # the frames' clouds too): said, since evaluate's accuracy of the same map keeps
            # them (paper benchmark: mean 2.9 / RMSE 5.4 cm here, 3.2 / 7.5 cm there).
            which = ("map points off moving people (the ground truth's masks)"
                     if "dynamic_fraction" in m else "map")
            extra.append(f"{which} to ground-truth mesh: mean "
                         f"{100 * m['map_to_mesh_mean_m']:.1f} cm,"
                         f" median {100 * m['map_to_mesh_median_m']:.1f} cm, RMSE "
                         f"{100 * m['map_to_mesh_rmse_m']:.1f} cm; within 2 / 5 / 10 cm: "
                         f"{100 * m['map_to_mesh_within_2cm']:.0f} / "
                         f"{100 * m['map_to_mesh_within_5cm']:.0f} / "
                         f"{100 * m['map_to_mesh_within_10cm']:.0f} % of the points; the "
                         "median over frames of each frame's own cloud's median distance "
                         f"{100 * m.get('frame_to_mesh_median_m', float('nan')):.1f} cm")
        if "scale_error_median" in m:
            extra.append(f"per-frame scale error vs the oracle (from ground truth): median "
                         f"{100 * m['scale_error_median']:.1f} %, max "
                         f"{100 * m['scale_error_max']:.1f} %")
        md.append("\n".join(f"- {e}" for e in extra))
        if fig_data is not None:
            i, rgb, unscaled, fused, g, fp, *used = fig_data  # type: ignore[misc]
            # The scale the panel's depth was scaled by (smoothed, or lent to a flagged
            # frame), not the frame's own fit (a checkpoint of an older run holds only that).
            scale = float(used[0]) if used else fp.estimate.scale
            own = (f", its own fit {fp.estimate.scale:.3f}"
                   if used and abs(fp.estimate.scale - scale) > 5e-4 * scale else "")
            if len(used) > 1:
                scaled = used[1]
            else:  # an older run's checkpoint kept only the depth the map used
                j = frames.index(i)
                scaled = store.read(i).as_depth(float(sm.scale[j]),  # type: ignore[attr-defined]
                                                float(sm.shift[j]))  # type: ignore[attr-defined]
            # "scaled" is the per-frame scale alone, as in every table; the map's depth
            # after the shape correction is a panel of its own (drawn as "scaled" it showed
            # half the error of the paper's method).
            refined = None if np.array_equal(fused, scaled, equal_nan=True) else fused
            figures.lidar_overlay(ctx.stage_dir / "lidar_overlay.png", rgb, fp.lidar.uv,
                                  fp.lidar.z, f"frame {i}: lidar in the image")
            figures.depth_panels(ctx.stage_dir / "depth_scaled_vs_unscaled.png", rgb, unscaled,
                                 scaled, g, f"frame {i}: scale {scale:.3f}{own}"
                                 + (f", then shape correction {cfg.refine}"
                                    if refined is not None else ""), refined)
            md.append(f"![lidar overlay]({sid}/lidar_overlay.png)")
            md.append(f"![scaled vs unscaled depth]({sid}/depth_scaled_vs_unscaled.png)")
        frames_arr = np.array(frames)
        figures.scale_plot(ctx.stage_dir / "scales.png", frames_arr,
                           sm.raw_scale, sm.scale,  # type: ignore[attr-defined]
                           oracle, sm.flag, store.kind,  # type: ignore[attr-defined]
                           # Scale-and-shift fits keep their own pair in either mode.
                           "used (window median)" if cfg.smoothing == "median" and not np.any(
                               sm.shift[sm.used] != 0) else  # type: ignore[attr-defined]
                           "used (own; flagged: neighbours')")
        md.append(f"![per-frame scale]({sid}/scales.png)")
        if "exposure_edges" in m:
            gains = read_exposure_gains(ctx.stage_dir / EXPOSURE_FILE)
            fr = np.array(sorted(gains))
            gt = seq.groundtruth
            truth = gt.exposure_gain[fr] if gt is not None and gt.exposure_gain is not None \
                else None
            figures.exposure_plot(ctx.stage_dir / "exposure.png", fr,
                                  np.stack([gains[i] for i in fr]), truth)
            err = (f"; against the simulator's true gains (spread "
                   f"{m['exposure_gain_true_spread_pct']:.1f} %) "
                   f"{m['exposure_gain_error_rms_pct']:.2f} % RMS, "
                   f"{m['exposure_gain_error_max_pct']:.2f} % at most"
                   if "exposure_gain_error_rms_pct" in m else "")
            md.append(f"Exposure (`exposure: gain`): each frame's gain, solved over "
                      f"{m['exposure_edges']:.0f} pairs of frames that see the same surface "
                      f"({m['exposure_frames_linked']:.0f}/{m['exposure_frames_solved']:.0f} "
                      "frames in at least one pair, "
                      + ("all in one connected group" if m["exposure_groups"] == 1 else
                         f"**{m['exposure_groups']:.0f} groups sharing no surface**, taken as "
                         "equal where they meet in time")
                      + (f"; every {m['exposure_frame_step']:.0f}th frame solved, the others "
                         "interpolated" if m["exposure_frame_step"] > 1 else "") + "), "
                      f"{m['exposure_gain_min']:.3f}-{m['exposure_gain_max']:.3f}, divided out "
                      f"of the map's colours; residual {100 * m['exposure_residual_log_rms']:.1f}"
                      f" %{err} ({m['exposure_seconds']:.1f} s). Gains in "
                      f"[{EXPOSURE_FILE}]({sid}/{EXPOSURE_FILE}).\n\n"
                      f"![exposure gains]({sid}/exposure.png)")
        removed = raw.points[masks["dynamic"]]  # type: ignore[attr-defined]
        xy = traj.positions[:, :2]
        figures.map_views(ctx.stage_dir / "map_views.png", final.points,  # type: ignore
                          final.colors, xy, "fused map", removed)  # type: ignore[attr-defined]
        md.append(f"![coloured map]({sid}/map_views.png)")
        md.append(f"Files: [map.ply]({sid}/map.ply), [scales.csv]({sid}/scales.csv)"
                  + (f", scaled depth in `{sid}/scaled_depth/` ("
                     + ("16-bit PNG, 5000 per metre" if cfg.write_depth == "png" else
                        "float32 .npy, metres") + "; 0 where none"
                     + (", and on moving obstacles the lidar saw" if cfg.dynamic_removal
                        and cfg.lidar_dynamic else "") + ")."
                     if cfg.write_depth != "none"
                     else " (no scaled depth: `write_depth: none`)."))
        ctx.report("\n\n".join(md))

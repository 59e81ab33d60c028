"""The recipe stage ``slam2d``: metric T_world_base from the sequence's scans.

```yaml
- stage: slam2d
  use_odometry: true          # the sequence's odometry as a prior, when it has one
  relations: null             # a Freiburg .relations file to score against (benchmarks)
  local: {scan_only_linear_window_m: 1.2}   # any Slam2DConfig group can be overridden
```

Writes ``trajectory_base.tum`` (T_world_base at every scan used), ``trajectory_camera.tum``
(T_world_camera at the camera stamps inside the scan span), ``map.pgm`` + ``map.yaml``
(map_server), ``map.png`` (the map with the trajectory), ``slam2d_config.json`` (the
SLAM's settings) and ``slam2d_stage.json`` (the stage's settings that later stages follow:
``use_odometry``, which fuse's ``odometry: null`` takes), and provides the folder as
artifact ``trajectory``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from toolkit.recipe.stage import Stage, StageConfig, StageContext, StageError
from toolkit.recipe.timing import work_metrics
from toolkit.slam2d.config import Slam2DConfig

# In the trajectory artifact: inside it, the record joins the cache key of every stage
# reading the trajectory (a rerun with another use_odometry reruns them).
STAGE_RECORD = "slam2d_stage.json"


def recorded_use_odometry(trajectory: Path) -> bool | None:
    """The ``use_odometry`` of the slam2d run that wrote the trajectory folder
    ``trajectory``: whether its camera poses between the scans follow the wheel odometry.
    None where the folder has no record (a run of slam2d before it wrote one, or a
    trajectory file of another source). Raises ``StageError`` for a record that is not
    one."""
    path = Path(trajectory) / STAGE_RECORD
    if not Path(trajectory).is_dir() or not path.exists():
        return None
    fix = "rerun slam2d (--from slam2d) to write it again, or set fuse's odometry: true / false"
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise StageError(f"{path} cannot be read ({exc}); {fix}") from exc
    value = data.get("use_odometry") if isinstance(data, dict) else None
    if not isinstance(value, bool):
        raise StageError(f"{path}: field 'use_odometry' must be true or false (got "
                         f"{value!r}); {fix}")
    return value


class Slam2DStageConfig(Slam2DConfig, StageConfig):
    """Settings of ``slam2d``: the SLAM's option groups plus what the stage reads/scores."""

    use_odometry: bool = True
    relations: str | None = None

    def slam_config(self) -> Slam2DConfig:
        """The SLAM's own settings, without the stage's."""
        return Slam2DConfig(**{g: getattr(self, g) for g in Slam2DConfig.model_fields})


class Slam2DStage(Stage):
    """2D lidar SLAM (Cartographer-style): base poses, occupancy map, loop closures."""

    name = "slam2d"
    Config = Slam2DStageConfig
    requires = ("sequence",)
    optional_requires = ("rig",)  # a calibrated extrinsic (calibrate) over the sequence's
    provides = ("trajectory",)
    # 2: no odometry across its gaps; closure cap counts accepted closures. 3: limits
    # compared as the ranges are stored; hit rays end in their hit cell. 4: hit rays end
    # where they did before 3 (ending them in their cell broke ACES: ATE 8.4 cm -> 21.9 m).
    # 5: far loop-closure matches as good as one near the estimate are rejected
    # 6: the ATE against ground truth interpolates it at the scans' stamps
    # 7: camera poses between the scans' follow the wheel odometry (use_odometry)
    # 8: full-turn scans with a beam at both -pi and pi de-skewed a turn (not n beams)
    #    apart; the map YAML holds map_saver's thresholds (unknown cells read as unknown)
    # 9: zero ranges are no returns with scan.min_range 0 too (they were walls at the laser)
    # 10: a camera frame within END_SLACK_S outside the scans' span gets the end pose even
    #     when a long gap follows that end (Trajectory.covers refused it)
    # 11: swept scans de-skewed with the odometry's poses inside each sweep, beam by beam
    #     (constant velocity between the sweep's ends only where it has none)
    version = 11

    def external_inputs(self) -> list[Path]:
        cfg = self.config
        assert isinstance(cfg, Slam2DStageConfig)
        return [Path(cfg.relations)] if cfg.relations else []

    def run(self, ctx: StageContext) -> None:
        from toolkit.eval.relations import read_relations, relations_metric
        from toolkit.io.atomic import atomic_write_json
        from toolkit.io.occupancy import write_occupancy
        from toolkit.io.sequence import read_sequence, sequence_with_rig
        from toolkit.io.tum import write_tum
        from toolkit.slam2d.bench import ate_se2
        from toolkit.slam2d.pipeline import grid_to_occupancy, run_slam
        from toolkit.slam2d.plot import save_map_png

        cfg = self.config
        assert isinstance(cfg, Slam2DStageConfig)
        seq = read_sequence(ctx.artifact("sequence"))
        if ctx.has_artifact("rig"):
            seq = sequence_with_rig(seq, ctx.artifact("rig"))
        if not seq.scans:
            raise StageError(f"sequence {seq.name} has no laser scans: slam2d needs a 2D lidar")
        # Read before the SLAM: a broken file found afterwards loses the run.
        rel = None
        if cfg.relations:
            try:
                rel = read_relations(cfg.relations)
            except (OSError, ValueError) as exc:
                raise StageError(f"slam2d: setting 'relations': {exc} - give a Freiburg "
                                 ".relations file (t1 t2 x y z roll pitch yaw per line) or "
                                 "relations: null") from exc
        odom = seq.odometry if cfg.use_odometry else None
        ctx.log.info("slam2d on %d scans (%s)", len(seq.scans),
                     "with odometry" if odom is not None else "scan-only")
        result = run_slam(
            seq.scans, odom, seq.rig.T_base_laser, cfg.slam_config(),
            progress=lambda it: ctx.progress(it, total=len(seq.scans), description="slam2d"))
        out = ctx.stage_dir
        traj = result.trajectory
        if len(traj) < 2:
            raise StageError(f"slam2d kept {len(traj)} scans of {len(seq.scans)}: nothing to "
                             f"track (metrics: {result.metrics})")
        write_tum(out / "trajectory_base.tum", traj,
                  header="slam2d: T_world_base at the scan stamps")

        # Camera poses: base poses interpolated at the camera stamps (the motion between
        # two scans the odometry's, when it is used), times the mount; none outside the
        # scans' span (but for END_SLACK_S, as fuse takes them) or across a gap in it
        # (Trajectory.covers).
        fs = seq.frame_stamps
        slack = traj.END_SLACK_S
        span = (fs >= traj.stamps[0] - slack) & (fs <= traj.stamps[-1] + slack)
        inside = traj.covers(fs, slack_s=slack)
        cam = traj.interpolate_with_odometry(odom, fs[inside], extrapolate_s=slack).transform(
            T_right=seq.rig.T_base_camera)
        cam.child = "camera"
        write_tum(out / "trajectory_camera.tum", cam,
                  header="slam2d: T_world_camera (optical) at the camera stamps")
        metrics = dict(result.metrics)
        # Frames are the camera frames it gave poses to (what a per-frame runtime table
        # adds up); a log without a camera counts its scans.
        frames = int(inside.sum()) or int(result.metrics.get("scans_used") or 0)
        metrics.update(work_metrics(result.metrics["wall_time_s"], result.metrics["cpu_time_s"],
                                    frames))
        metrics["camera_poses"] = int(inside.sum())
        metrics["camera_frames_outside_scan_span"] = int((~span).sum())
        metrics["camera_frames_in_scan_gaps"] = int((span & ~inside).sum())
        if metrics["camera_frames_in_scan_gaps"]:
            ctx.log.warning("%d camera frames fall in gaps between scans (no scan for over "
                            "%.1f s): they get no pose", metrics["camera_frames_in_scan_gaps"],
                            traj.gap_limit_s())
        if len(fs) and metrics["camera_frames_outside_scan_span"] > len(fs) // 2:
            # Most frames outside the scans' time span: another time base (or a large time
            # offset), not frames before and after the drive.
            ctx.log.warning("%d of %d camera frames lie outside the scans' time span "
                            "(%.3f..%.3f s; frames %.3f..%.3f s) and get no pose: are the "
                            "camera's and the lidar's stamps on the same clock?",
                            metrics["camera_frames_outside_scan_span"], len(fs),
                            float(traj.stamps[0]), float(traj.stamps[-1]), float(fs[0]),
                            float(fs[-1]))

        occ = grid_to_occupancy(result.map)
        write_occupancy(out / "map.yaml", occ)
        ref_xy = None
        gt = seq.groundtruth.poses_base if seq.groundtruth is not None else None
        if gt is not None and len(gt) >= 3:
            try:
                metrics.update({f"gt_{k}": v for k, v in ate_se2(traj, gt).items()})
            except (ValueError, IndexError) as e:
                ctx.log.warning("no ATE against ground truth: %s", e)
            ref_xy = gt.positions[:, :2]
        if rel is not None:
            metrics["relations"] = relations_metric(traj, rel)
        save_map_png(out / "map.png", occ, traj.positions[:, :2],
                     title=f"{seq.name}: {metrics['nodes']} nodes, {metrics['submaps']} "
                           f"submaps, {metrics['loop_closures']} loop-closure constraints",
                     reference_xy=None if ref_xy is None else _aligned_ref(traj, gt))
        atomic_write_json(out / "slam2d_config.json", cfg.slam_config().model_dump())
        atomic_write_json(out / STAGE_RECORD, {"use_odometry": cfg.use_odometry})
        ctx.add_metrics(metrics)
        said = seq.meta.get("groundtruth")
        ctx.report(_report(ctx.stage_id, metrics, said if isinstance(said, str) else None))
        ctx.provide("trajectory", out)


def _aligned_ref(traj, gt) -> np.ndarray | None:  # noqa: ANN001 - Trajectory pair
    """Ground-truth positions [N, 2] moved into the SLAM's world frame (for the plot),
    aligned where the SLAM trajectory covers the ground truth's stamps (interpolated, as
    ``ate_se2`` scores it)."""
    from toolkit.geometry import umeyama_alignment

    ok = traj.covers(gt.stamps, slack_s=1e-3)
    if ok.sum() < 3:
        return None
    est = traj.interpolate(gt.stamps[ok], extrapolate_s=1e-3)
    R, t, _ = umeyama_alignment(gt.positions[ok, :2], est.positions[:, :2])
    return gt.positions[:, :2] @ R.T + t


def _report(stage_id: str, m: dict, reference: str | None = None) -> str:
    """The map and a table of the figures a reader looks for (all are in metrics.json).

    ``reference``: what the sequence's ``meta.yaml`` says its ground-truth poses are, when
    it says (a CARMEN log's are another SLAM's solution): the error is then against them.
    """
    n_odom = m.get("scans_with_odometry")
    odom = ("no wheel odometry" if not m.get("odometry_used") else "with wheel odometry"
            if n_odom is None else f"{n_odom} of the input scans with wheel odometry")
    rows = [("scans used", f"{m['scans_used']} ({odom})"),
            ("pose-graph nodes / submaps", f"{m['nodes']} / {m['submaps']}"),
            ("loop-closure constraints (scan-to-submap matches; one revisit gives many)",
             f"{m['loop_closures']}, of them outliers in the graph: "
             f"{m.get('loop_closure_outliers', 0)}; matches rejected as degenerate along a "
             f"corridor: {m.get('loop_closures_degenerate', 0)}")]
    # What the SLAM did about hard input, shown only when it happened.
    for key, label in (("degenerate_matches", "scans held to the odometry along a corridor"),
                       ("scan_only_window_retries",
                        "scan-only matches searched again with the full window"),
                       ("submaps_search_bounded", "submaps at their closure-search bound"),
                       ("nodes_stationary", "nodes added standing still (not searched)")):
        if m.get(key):
            rows.append((label, str(m[key])))
    if m.get("realtime_factor") is not None:
        rows.append(("speed", f"{m['realtime_factor']:.1f}x real time "
                              f"({m['wall_time_s']:.1f} s for {m['log_duration_s']:.1f} s of log)"))
    if m.get("gt_ate_rmse_m") is not None:
        against = "the reference poses" if reference else "ground truth"
        rows.append((f"position error vs {against} (ATE, SE(2)-aligned)",
                     f"RMSE {100 * m['gt_ate_rmse_m']:.2f} cm, max "
                     f"{100 * m['gt_ate_max_m']:.2f} cm over {m['gt_ate_poses']} poses"))
        if reference:
            rows.append(("reference poses", reference))
    if "camera_poses" in m and (m["camera_poses"] or m.get("camera_frames_outside_scan_span")):
        gaps = m.get("camera_frames_in_scan_gaps", 0)
        rows.append(("camera poses", f"{m['camera_poses']} (camera frames outside the scans' "
                                     f"time span: {m['camera_frames_outside_scan_span']}"
                                     + (f"; in gaps between scans, without a pose: {gaps}"
                                        if gaps else "") + ")"))
    lines = [f"![map]({stage_id}/map.png)", "", "| figure | value |", "| --- | --- |"]
    lines += [f"| {k} | {v} |" for k, v in rows]
    rel = m.get("relations")
    if rel and "trans_abs_mean_m" in rel:
        # Of all in the file: those whose stamps are not scans of this log are not scored.
        lines.append(f"| relations ({rel['relations_used']} of {rel['relations_total']} "
                     "scored: both stamps scans of this log) | "
                     f"{rel['trans_abs_mean_m']:.4f} ± {rel['trans_abs_std_m']:.4f} m, "
                     f"{rel['rot_abs_mean_deg']:.3f} ± {rel['rot_abs_std_deg']:.3f} deg |")
        if "trans_abs_mean_m_cartographer" in rel:
            lines.append("| relations, translation composed as Cartographer's "
                         "compute_relations_metrics (its published figures) | "
                         f"{rel['trans_abs_mean_m_cartographer']:.4f} ± "
                         f"{rel['trans_abs_std_m_cartographer']:.4f} m |")
    skipped = {k: v for k, v in m.items() if k.startswith("skipped_")}
    if skipped:
        lines.append(f"| skipped scans | {skipped} |")
    return "\n".join(lines) + "\n"

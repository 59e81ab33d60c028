"""Recipe stage ``paper_tables``: the paper's Tables I-IV from the stages of one run.

A benchmark recipe runs each configuration as its own chain of stages (a ``depth`` and a
``fuse`` per row, told apart by ``id:`` and ``inputs:``); this stage reads their metrics
(``ctx.stage_result``) and lays them out as the paper does, with the paper's published
figures beside ours where they are comparable, the targets with a pass/fail mark, and the
figures the paper shows (trajectory, depth error, lidar overlay, map / TSDF / splat views)
linked from the report. Nothing here is measured twice: every number comes from the stage
that produced it, so a table can always be traced back to that stage's section.

Runtime (the paper's Table II) is taken the same way for every row: the ``work_seconds``
and ``work_cpu_seconds`` each pipeline stage records for its processing alone
(``toolkit.recipe.timing``), summed over the stages of the configuration; frames/s is
frames over that sum and CPU load is CPU time over wall time (100 % = one core).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from toolkit.recipe.stage import Stage, StageConfig, StageContext, StageError, StageResult

# The paper's published figures (simulated house; i9 CPU + RTX 4090).
PAPER = {
    "position_rmse_lidar_m": 0.078,
    "position_rmse_camera_only_m": 2.05,
    "fps": "2.2-2.6",
    "cpu_load_pct": "1024-1549",
    "depth_unscaled_rmse_m": 1.46,
    "depth_scaled_rmse_m": 0.40,
    "depth_ratio_unidepth": 0.40 / 1.46,
    "depth_ratio_depth_anything": 0.37,
}


class TableRow(BaseModel):
    """One configuration of the benchmark: the ids of its stages in this recipe."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    label: str
    depth: str | None = None
    fuse: str | None = None
    evaluate: str | None = None
    tsdf: str | None = None
    splat: str | None = None
    # A row whose depth is for timing only (random weights): its fusion time is taken from
    # this stage instead (fusion costs the same whatever the depth values are).
    fusion_time_from: str | None = None
    # A fuse stage of the same depth with ``dynamic_removal: false``: Table IV gives the
    # share of map points on moving obstacles without the removal beside the one with it.
    fuse_without_removal: str | None = None
    timing_only: bool = False
    fps_target: float | None = Field(None, gt=0)
    fscore_5cm_target: float | None = Field(None, gt=0, le=1)


class PaperTablesConfig(StageConfig):
    stage: Literal["paper_tables"] = "paper_tables"
    slam: str | None = "slam2d"
    rows: list[TableRow]
    camera_only: str | None = None
    colmap: str | None = None
    splat_without_fused: str | None = None
    calibrate: str | None = None
    position_rmse_target_m: float = 0.02
    cpu_load_limit_pct: float = 200.0
    depth_ratio_target: float = 0.10
    dynamic_fraction_target: float = Field(0.01, ge=0, le=1)  # map points on moving obstacles
    # The first row with simulated depth: its scaled AbsRel vs ground truth, and the median
    # over frames of each frame's cloud's median distance to the true mesh.
    absrel_target: float = Field(0.05, gt=0)
    frame_to_mesh_target_m: float = Field(0.03, gt=0)
    # The first row's fusion alone (network excluded), wall clock with the end of the run.
    fusion_fps_target: float = Field(30.0, gt=0)
    splat_psnr_target_db: float = 28.0
    splat_gain_over_tsdf_target_db: float = 3.0
    max_time_diff_s: float = 0.02


def _ids(cfg: PaperTablesConfig) -> list[str]:
    ids = [cfg.slam, cfg.camera_only, cfg.colmap, cfg.splat_without_fused, cfg.calibrate]
    for r in cfg.rows:
        ids += [r.depth, r.fuse, r.evaluate, r.tsdf, r.splat, r.fusion_time_from,
                r.fuse_without_removal]
    return list(dict.fromkeys(i for i in ids if i))


def _get(m: dict[str, Any] | None, *path: str) -> Any:
    for key in path:
        if not isinstance(m, dict) or key not in m:
            return None
        m = m[key]
    return m


def _num(v: Any, fmt: str = ".3f", scale: float = 1.0, unit: str = "") -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "-"
    return f"{float(v) * scale:{fmt}}{unit}"


def _mark(ok: bool | None) -> str:
    return "" if ok is None else (" ✓" if ok else " ✗")


def _own_scale_label(m: dict[str, Any]) -> str:
    """What the camera-only rows' unaligned scale is: the network's metres, or (scaled by
    COLMAP's sparse points) COLMAP's normalised unit, no scale error of the method's."""
    return ("COLMAP's unit" if m.get("own_scale_is", "colmap_unit") == "colmap_unit"
            else "own scale")


def _colmap_lines(m: dict[str, Any]) -> list[str]:
    """COLMAP cross-checks: SfM alone against ground truth and lidar, triangulation at the
    lidar poses."""
    md = []
    sfm = m.get("sfm") or {}
    if sfm:
        # A global model registers nearly every image whether or not it is right (the
        # house: 159 of 161 at 2.7 m ATE), so the line says which mapper made it.
        how = " (global mapping)" if m.get("mapper") == "global" else ""
        md.append(f"COLMAP SfM{how} on the images alone: {sfm.get('registered_images')} of "
                  f"{sfm.get('images')} images registered in {sfm.get('models')} model(s), "
                  f"reprojection {_num(sfm.get('reprojection_error_px'), '.2f', 1, ' px')}.")
    for ref in ("groundtruth", "lidar"):
        e = m.get(f"sfm_vs_{ref}")
        if e:
            md.append(f"Its largest model against {ref}: ATE Sim(3) "
                      f"{_num(e.get('ate_sim3_rmse_m'), '.3f', 1, ' m')}, in COLMAP's "
                      "normalised unit (SE(3)) "
                      f"{_num(e.get('ate_se3_rmse_m'), '.3f', 1, ' m')} over "
                      f"{e.get('poses_compared')} poses.")
    tri = m.get("triangulation")
    if tri:
        med = _num(tri.get("gt_mesh_distance_median_m"), ".1f", 100, " cm")
        md.append(f"Triangulation of its features at the lidar-SLAM poses: "
                  f"{tri.get('points')} points, reprojection "
                  f"{_num(tri.get('reprojection_error_px'), '.2f', 1, ' px')}, median distance "
                  f"to the true surface {med}.")
    return [" ".join(md), ""] if md else []


def _per_frame(m: dict[str, Any], key: str, default_frames: int) -> float:
    """Seconds per frame of a stage's work (its own frame count, else ``default_frames``)."""
    return float(m[key]) / max(int(m.get("work_frames") or default_frames), 1)


def _machine(timed: list[dict[str, Any]], depth: dict[str, dict[str, Any]]) -> str:
    """What ran Table II's stages, from what they recorded: the CPU cores of the stages in
    ``timed`` (``work_cpu_cores``) and the device of each row's depth stage in ``depth``
    (by row label). A fixed "2 CPU cores, no GPU" was wrong for a run anywhere else."""
    cores = sorted({int(m["work_cpu_cores"]) for m in timed if m.get("work_cpu_cores")})
    missing = sum(not m.get("work_cpu_cores") for m in timed)
    if not cores:
        text = "CPU cores not recorded"
    else:
        # Cached stages keep the figures of the machine that ran them.
        text = (f"{cores[0]} CPU cores" if len(cores) == 1 else
                f"{cores[0]}-{cores[-1]} CPU cores: stages from different machines")
        if missing:
            text += f", not recorded by {missing} of {len(timed)} stages"
    devices = {label: str(m["device"]) for label, m in depth.items() if m.get("device")}
    if not devices:
        return f"{text}; depth device not recorded"
    if set(devices.values()) == {"cpu"}:
        return f"{text}; no GPU used" + ("" if len(devices) == len(depth) else
                                         " by the depth stages that recorded it")
    return f"{text}; " + ", ".join(f"depth of '{label}' on {dev}"
                                   for label, dev in devices.items() if dev != "cpu")


def _link(res: StageResult | None, name: str, alt: str) -> str | None:
    if res is None or not (res.stage_dir / name).exists():
        return None
    return f"![{alt}]({res.id}/{name})"


class PaperTablesStage(Stage):
    """The paper's Tables I-IV (and targets) from the benchmark's stages, with figures."""

    name = "paper_tables"
    Config = PaperTablesConfig
    requires = ("sequence",)
    provides = ("tables",)
    # 2: Table IV's scaled / unscaled ratio against ground truth over whole images, checked
    # 3: Table I scores no frame past the ground truth's ends; line alignment within error
    # 4: the camera-only rows' unaligned scale labelled COLMAP's unit where it is that
    # 5: Table IV says how the co-visible pairs are chosen (the fuse stage's version 11)
    # 6: Table IV's moving obstacles also as the people points kept of the map without removal
    version = 6

    @classmethod
    def reads_results(cls, config: StageConfig) -> tuple[str, ...]:
        return tuple(_ids(config))  # type: ignore[arg-type]

    def run(self, ctx: StageContext) -> None:
        from toolkit.io.atomic import atomic_write_json
        from toolkit.io.sequence import read_sequence

        cfg: PaperTablesConfig = self.config  # type: ignore[assignment]
        if not cfg.rows:
            raise StageError(f"{ctx.stage_id}: rows: list at least one configuration")
        res = {i: ctx.stage_result(i) for i in _ids(cfg)}
        for row in cfg.rows:
            off = row.fuse_without_removal
            if not off:
                continue
            # The fuse stage records whether it removed moving obstacles; a result without
            # that record (another kind of stage, a fuse stage from before) proves nothing.
            said = res[off].metrics.get("dynamic_removal")
            if said is not False:
                why = ("removed moving obstacles" if said else
                       f"does not record dynamic_removal (a {res[off].type} stage, or a fuse "
                       "stage run before it was recorded: run it again with --force)")
                raise StageError(
                    f"{ctx.stage_id}: row '{row.label}': its fuse_without_removal stage "
                    f"'{off}' {why}; it must be a fuse stage with dynamic_removal: false")
        seq = read_sequence(ctx.artifact("sequence"))
        tables: dict[str, Any] = {}
        checks: list[tuple[str, str, bool | None]] = []
        md: list[str] = []
        md += self._table_i(ctx, cfg, res, seq, tables, checks)
        md += self._table_ii(cfg, res, tables, checks)
        md += self._table_iii(cfg, res, tables, checks)
        md += self._table_iv(cfg, res, tables, checks)
        self._fusion_checks(cfg, res, checks)
        md += self._figures(cfg, res)
        if cfg.calibrate:
            cm = res[cfg.calibrate].metrics
            if cm.get("check_true_beats_rotated_2deg") is not None:
                checks.append(("extrinsic check: the true extrinsic scores above every 2-degree "
                               "rotation of it", f"{_num(cm.get('check_score_true'))}"
                               f" vs yaw +2 deg {_num(cm.get('check_score_true_rotated_2deg'))}",
                               bool(cm["check_true_beats_rotated_2deg"])))
        if checks:
            md += ["### Targets", "", "| target | ours | met |", "|---|---|---|"]
            md += [f"| {t} | {v} | {'yes' if ok else ('no' if ok is False else '-')} |"
                   for t, v, ok in checks]
            md.append("")
        tables["targets"] = [{"target": t, "value": v, "met": ok} for t, v, ok in checks]
        atomic_write_json(ctx.stage_dir / "tables.json", tables)
        ctx.provide("tables", ctx.stage_dir / "tables.json")
        ctx.add_metrics(tables)
        ctx.report("\n".join(md))

    # ------------------------------------------------------------------ Table I
    def _table_i(self, ctx: StageContext, cfg: PaperTablesConfig, res: dict[str, StageResult],
                 seq: Any, tables: dict[str, Any], checks: list) -> list[str]:
        from toolkit.eval.alignment import covered_ground_truth
        from toolkit.eval.stage import trajectory_figures
        from toolkit.eval.trajectory import per_axis_errors, synced
        from toolkit.io.tum import read_tum

        if seq.groundtruth is None or seq.groundtruth.poses_base is None:
            return ["Table I needs ground-truth poses; this sequence has none.", ""]
        rows: list[tuple[str, dict[str, float]]] = []
        curves: dict[str, np.ndarray] = {}
        gt_all = None
        if cfg.slam and (res[cfg.slam].stage_dir / "trajectory_camera.tum").exists():
            est, gt_cam = covered_ground_truth(
                seq, read_tum(res[cfg.slam].stage_dir / "trajectory_camera.tum"))
            fig, aligned, g, _ = trajectory_figures(est, gt_cam, cfg.max_time_diff_s)
            rows.append(("with lidar: 2D lidar SLAM (SE(3)-aligned)", fig))
            curves["with lidar (SE(3))"] = aligned.positions
            gt_all = g
            ok = fig["position_rmse_m"] <= cfg.position_rmse_target_m
            checks.append((f"camera position RMSE with lidar <= {cfg.position_rmse_target_m} m "
                           f"(paper {PAPER['position_rmse_lidar_m']} m)",
                           f"{fig['position_rmse_m']:.4f} m", ok))
        if cfg.camera_only:
            d = res[cfg.camera_only].stage_dir
            own = _own_scale_label(res[cfg.camera_only].metrics)
            for tag, label in (("se3", f"without lidar: COLMAP, {own} (SE(3)-aligned)"),
                               ("sim3", "without lidar: COLMAP, scale corrected (Sim(3))")):
                path = d / f"trajectory_{tag}.tum"
                if not path.exists():
                    continue
                est, gt_cam = covered_ground_truth(seq, read_tum(path))
                e, g = synced(est, gt_cam, cfg.max_time_diff_s)
                if len(e) < 3:
                    continue
                fig = per_axis_errors(e, g)
                fig["poses"] = len(e)
                rows.append((label, fig))
                curves[f"without lidar ({tag.upper()})"] = e.positions
        tables["table_i"] = {label: fig for label, fig in rows}
        md = ["### Table I: camera trajectory against ground truth", "",
              "| configuration | poses | x | y | z | roll | pitch | yaw | position | "
              "orientation |", "|---|---|---|---|---|---|---|---|---|---|"]
        for label, f in rows:
            md.append(f"| {label} | {f['poses']} | " + " | ".join(
                _num(f[k], ".3f", 1, " m") for k in ("x_rmse_m", "y_rmse_m", "z_rmse_m"))
                + " | " + " | ".join(_num(f[k], ".2f", 1, "°") for k in
                                     ("roll_rmse_deg", "pitch_rmse_deg", "yaw_rmse_deg"))
                + f" | **{_num(f['position_rmse_m'], '.3f', 1, ' m')}** | "
                  f"{_num(f['orientation_rmse_deg'], '.2f', 1, '°')} |")
        md += [f"| paper, with lidar | | | | | | | | {PAPER['position_rmse_lidar_m']} m | |",
               f"| paper, without lidar | | | | | | | | {PAPER['position_rmse_camera_only_m']}"
               " m | |", ""]
        if cfg.camera_only and not any(lbl.startswith("without") for lbl, _ in rows):
            md += ["The camera-only stage left no aligned trajectory (COLMAP failed).", ""]
        if cfg.colmap:
            md += _colmap_lines(res[cfg.colmap].metrics)
        if gt_all is not None:
            path = ctx.stage_dir / "figure5_trajectories.png"
            _plot_curves(gt_all.positions, curves, path)
            md += [f"![Figure 5: trajectories]({ctx.stage_id}/{path.name})", ""]
        return md

    # ------------------------------------------------------------------ Table II
    def _table_ii(self, cfg: PaperTablesConfig, res: dict[str, StageResult],
                  tables: dict[str, Any], checks: list) -> list[str]:
        slam = res[cfg.slam].metrics if cfg.slam else {}
        timed: list[dict[str, Any]] = [slam] if cfg.slam else []
        depth_of: dict[str, dict[str, Any]] = {}
        md = ["### Table II: runtime", "",
              "Per configuration, the work of SLAM + depth network + fusion (each stage's own "
              "processing; reports and scoring excluded), frames/s over the fused frames and "
              "CPU load as % of one core.", "",
              "| configuration | frames | SLAM s | depth s | fusion s | total s | frames/s | "
              "CPU load |", "|---|---|---|---|---|---|---|---|"]
        out = {}
        for row in cfg.rows:
            if not row.depth:
                continue
            dep = res[row.depth].metrics
            fuse_src = row.fusion_time_from or row.fuse
            fus = res[fuse_src].metrics if fuse_src else {}
            parts = [(slam.get("work_seconds"), slam.get("work_cpu_seconds")),
                     (dep.get("work_seconds"), dep.get("work_cpu_seconds")),
                     (fus.get("work_seconds"), fus.get("work_cpu_seconds"))]
            if any(p[0] is None for p in parts):
                continue
            timed += [dep, fus]
            depth_of[row.label] = dep
            frames = int(dep.get("work_frames") or 0)
            # Per-frame costs: SLAM and fusion may have handled other frame counts than depth.
            wall_pf = [_per_frame(m, "work_seconds", frames) for m in (slam, dep, fus)]
            cpu_pf = [_per_frame(m, "work_cpu_seconds", frames) for m in (slam, dep, fus)]
            wall, cpu = sum(wall_pf) * frames, sum(cpu_pf) * frames
            fps = frames / wall if wall > 0 else None
            load = 100 * cpu / wall if wall > 0 else None
            out[row.label] = {"frames": frames, "slam_s": wall_pf[0] * frames,
                              "depth_s": wall_pf[1] * frames, "fusion_s": wall_pf[2] * frames,
                              "total_s": wall, "fps": fps, "cpu_load_pct": load}
            o = out[row.label]
            md.append(f"| {row.label} | {frames} | {o['slam_s']:.1f} | {o['depth_s']:.1f} | "
                      f"{o['fusion_s']:.1f} | {wall:.1f} | **{_num(fps, '.1f')}** | "
                      f"{_num(load, '.0f', 1, ' %')} |")
            if row.fps_target is not None and fps is not None:
                ok = fps >= row.fps_target and (load or 0) <= cfg.cpu_load_limit_pct
                checks.append((f"{row.label}: >= {row.fps_target:g} frames/s at CPU load <= "
                               f"{cfg.cpu_load_limit_pct:g} %", f"{fps:.1f} frames/s, "
                               f"{load:.0f} %", ok))
        md += [f"| paper (i9 + RTX 4090) | | | | | | {PAPER['fps']} | {PAPER['cpu_load_pct']} %"
               " |", ""]
        if depth_of:
            md[0] += f" ({_machine(list({id(m): m for m in timed}.values()), depth_of)})"
        notes = []
        for r in cfg.rows:
            if not r.fusion_time_from:
                continue
            src = res[r.fusion_time_from].metrics
            row = out.get(r.label, {})
            # Per frame of the source run: its end-of-run work is spread over its own frame
            # count, which may not be this row's (the DA-V2 row's every 2nd frame: a
            # 322-frame fusion would pay that work about whole, not halved).
            notes.append(
                f"- {r.label}: fusion time per frame taken from `{r.fusion_time_from}` (same "
                f"fusion, depth values do not change its cost), measured there over "
                f"{src.get('work_frames', '?')} frames against this row's "
                f"{row.get('frames', '?')}; its end-of-run work "
                f"({_num(src.get('finish_seconds'), '.1f', 1, ' s')}) is counted per frame.")
        if notes:
            md += [*notes, ""]
        extra = []
        for key, label in ((cfg.colmap, "COLMAP (SfM, whole stage)"),
                           (cfg.camera_only, "camera only (whole stage)")):
            if key and res[key].seconds:
                r = res[key]
                extra.append(f"- {label}: {r.seconds:.0f} s wall, "
                             f"{_num(r.cpu_seconds, '.0f')} s CPU for "
                             f"{_get(r.metrics, 'sfm', 'images') or _get(r.metrics, 'images')}"
                             " images.")
        if extra:
            md += ["Baselines (not online pipelines; whole stage times):", "", *extra, ""]
        tables["table_ii"] = out
        return md

    # ------------------------------------------------------------------ Table III
    def _table_iii(self, cfg: PaperTablesConfig, res: dict[str, StageResult],
                   tables: dict[str, Any], checks: list) -> list[str]:
        md = ["### Table III: maps against the ground-truth mesh and held-out views", "",
              "Geometry: accuracy = map points (evaluate's `max_points` at random, 400000 by "
              "default) to the mesh, completeness = the surface the cameras saw to every map "
              "point, F-score at 2 / 5 / 10 cm "
              "(after the SE(3) alignment of the camera trajectory; no scale correction).", "",
              "| map | accuracy mean | completeness mean | Chamfer | F@2cm | F@5cm | F@10cm |",
              "|---|---|---|---|---|---|---|"]
        out: dict[str, Any] = {}

        def geo_row(label: str, g: dict | None, target: float | None = None) -> None:
            if not g:
                return
            f5 = g.get("fscore_5cm")
            ok = None if target is None or f5 is None else f5 >= target
            md.append(f"| {label} | {_num(g.get('accuracy_mean_m'), '.1f', 100, ' cm')} | "
                      f"{_num(g.get('completeness_mean_m'), '.1f', 100, ' cm')} | "
                      f"{_num(g.get('chamfer_m'), '.1f', 100, ' cm')} | "
                      f"{_num(g.get('fscore_2cm'))} | **{_num(f5)}**{_mark(ok)} | "
                      f"{_num(g.get('fscore_10cm'))} |")
            out[label] = g
            if target is not None and f5 is not None:
                checks.append((f"{label}: F-score at 5 cm >= {target:g}", f"{f5:.3f}", ok))

        for row in cfg.rows:
            if row.evaluate and not row.timing_only:
                ev = res[row.evaluate].metrics
                geo_row(f"{row.label}: fused cloud", ev.get("fused_map"), row.fscore_5cm_target)
                geo_row(f"{row.label}: TSDF mesh", ev.get("tsdf_mesh"))
        if cfg.camera_only:
            m = res[cfg.camera_only].metrics
            geo_row(f"without lidar (camera only), {_own_scale_label(m)}",
                    m.get("geometry_own_scale"))
            geo_row("without lidar (camera only), Sim(3)", m.get("geometry_sim3"))
        md.append("")
        # Splats: held-out views.
        splats = [(r.label, res[r.splat].metrics) for r in cfg.rows if r.splat]
        if cfg.splat_without_fused:
            splats.append(("splats without the fused cloud (random init, no depth term)",
                           res[cfg.splat_without_fused].metrics))
        if splats:
            md += ["Gaussian splats, held-out views (every 8th frame of the drive; the simulator's"
                   " off-path views), and the TSDF mesh coloured from the same images rendered at"
                   " the same held-out frames:", "",
                   "| splats | Gaussians | PSNR held-out | SSIM | TSDF mesh PSNR, same views | "
                   "gain | gain on pixels the TSDF covers | PSNR off-path views |",
                   "|---|---|---|---|---|---|---|---|"]
            for label, m in splats:
                p = m.get("heldout_psnr_db")
                t = m.get("tsdf_heldout_psnr_db")
                gain = m.get("heldout_psnr_gain_over_tsdf_db")
                # The whole-image gain counts the mesh's holes (background colour) too.
                pc, tc = m.get("heldout_psnr_on_tsdf_covered_db"), m.get(
                    "tsdf_heldout_psnr_covered_db")
                gain_c = None if pc is None or tc is None else float(pc) - float(tc)
                md.append(f"| {label} | {m.get('n_gaussians', '-')} | "
                          f"**{_num(p, '.2f', 1, ' dB')}** | {_num(m.get('heldout_ssim'))} | "
                          f"{_num(t, '.2f', 1, ' dB')} | "
                          f"{_num(gain, '+.2f', 1, ' dB')} | {_num(gain_c, '+.2f', 1, ' dB')} | "
                          f"{_num(m.get('sim_heldout_psnr_db'), '.2f', 1, ' dB')} |")
                out[f"splats: {label}"] = {k: m.get(k) for k in (
                    "n_gaussians", "heldout_psnr_db", "heldout_ssim", "tsdf_heldout_psnr_db",
                    "heldout_psnr_gain_over_tsdf_db", "sim_heldout_psnr_db")}
            first = splats[0][1]
            if first.get("heldout_psnr_db") is not None:
                p = float(first["heldout_psnr_db"])
                checks.append((f"{splats[0][0]}: splat held-out PSNR >= "
                               f"{cfg.splat_psnr_target_db:g} dB", f"{p:.2f} dB",
                               p >= cfg.splat_psnr_target_db))
            if first.get("heldout_psnr_gain_over_tsdf_db") is not None:
                gn = float(first["heldout_psnr_gain_over_tsdf_db"])
                checks.append((f"{splats[0][0]}: splats >= "
                               f"{cfg.splat_gain_over_tsdf_target_db:g} dB above the TSDF mesh",
                               f"{gn:+.2f} dB", gn >= cfg.splat_gain_over_tsdf_target_db))
            md.append("")
        md += ["The paper's Table III compares rendering of its own scene with MonoGS; those "
               "numbers are not comparable with this house and are not quoted.", ""]
        tables["table_iii"] = out
        return md

    # ------------------------------------------------------------------ fusion targets
    @staticmethod
    def _fusion_checks(cfg: PaperTablesConfig, res: dict[str, StageResult],
                       checks: list) -> None:
        """The fusion's targets of docs/depth_fusion.md that no table checks: scaled AbsRel
        and per-frame map-to-mesh distance with simulated depth (a network's error is its
        own), and the fusion's throughput without the network."""
        rows = [r for r in cfg.rows if r.fuse and not r.timing_only]
        sim = next((r for r in rows if r.depth and
                    res[r.depth].metrics.get("backend") == "simulated"), None)
        if sim is not None:
            m = res[sim.fuse].metrics  # type: ignore[index]
            absrel = m.get("gt_scaled_absrel")
            if absrel is not None:
                checks.append((f"{sim.label}: scaled depth AbsRel vs ground truth <= "
                               f"{cfg.absrel_target:g} (simulated depth)", f"{absrel:.3f}",
                               absrel <= cfg.absrel_target))
            d = m.get("frame_to_mesh_median_m")
            if d is not None:
                worst = m.get("frame_to_mesh_median_max_m")
                checks.append((f"{sim.label}: per-frame median map-to-mesh distance, median "
                               f"over frames <= {100 * cfg.frame_to_mesh_target_m:g} cm "
                               "(simulated depth)", f"{100 * d:.1f} cm"
                               + (f" (worst frame {100 * worst:.1f} cm)"
                                  if worst is not None else ""),
                               d <= cfg.frame_to_mesh_target_m))
        if rows:
            m = res[rows[0].fuse].metrics  # type: ignore[index]
            fps = m.get("fusion_fps")
            if fps is not None:
                per_frame = m.get("fusion_fps_per_frame_only")
                checks.append((f"{rows[0].label}: fusion >= {cfg.fusion_fps_target:g} frames/s "
                               "(network excluded, wall clock with the end of the run)",
                               f"{fps:.1f} frames/s" + (f" (per-frame work {per_frame:.1f})"
                                                        if per_frame is not None else ""),
                               fps >= cfg.fusion_fps_target))

    # ------------------------------------------------------------------ Table IV
    def _table_iv(self, cfg: PaperTablesConfig, res: dict[str, StageResult],
                  tables: dict[str, Any], checks: list) -> list[str]:
        md = ["### Table IV: depth, unscaled vs lidar-scaled", "",
              "Against the lidar points projected into the images (the paper's protocol, all "
              "pairs; and only the pairs both sensors see: the camera sits higher than the "
              "lidar, so behind a chair leg it sees the leg where the lidar sees the wall - "
              "chosen by the sensors alone, the same pairs for every row: none behind a "
              "nearer point of its own or the two neighbouring scans, on or behind a moving "
              "obstacle the lidar saw, or beside a range jump, where any depth map is least "
              "sure) and "
              "against ground-truth depth over whole images (simulator). The ground-truth row "
              "shows the floor that parallax alone puts on the all-pairs figure. The scaled "
              "columns are the per-frame scale alone (the paper's method); where the fusion "
              "also corrected each frame's shape (`refine`), its AbsRel against ground truth "
              "is the column after δ<1.25, and that corrected depth is what the map holds. "
              "A relative-depth network (the shipped small one, Depth Anything's relative "
              "models) has no metric output: its unscaled column is the error of whatever "
              "constant its output happens to carry, so its ratio says more about that "
              "constant than about the lidar scale; compare its scaled columns.",
              "",
              "| depth | RMSE unscaled vs lidar | RMSE scaled vs lidar | scaled / unscaled, all "
              "pairs | scaled / unscaled, co-visible pairs | RMSE scaled vs GT | scaled / "
              "unscaled vs GT | AbsRel scaled vs GT | δ<1.25 | AbsRel vs GT after shape "
              "correction | scale error median | moving-obstacle points |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        out = {}
        first = first_dyn = True
        for row in cfg.rows:
            if not row.fuse or row.timing_only:
                continue
            m = res[row.fuse].metrics
            ratio = m.get("lidar_rmse_ratio_scaled_unscaled")
            vis = m.get("lidar_visible_rmse_ratio_scaled_unscaled")
            out[row.label] = {k: m.get(k) for k in (
                "lidar_visible_rmse_ratio_scaled_unscaled", "pairs_visible_fraction",
                "lidar_unscaled_rmse_m", "lidar_scaled_rmse_m", "lidar_rmse_ratio_scaled_unscaled",
                "gt_scaled_rmse_m", "gt_scaled_absrel", "gt_scaled_delta1", "scale_error_median",
                "dynamic_fraction", "dynamic_fraction_before_carving", "dynamic_fraction_raw",
                "gt_rmse_ratio_scaled_unscaled", "gt_refined_rmse_m", "gt_refined_absrel",
                "refine")}
            dyn = m.get("dynamic_fraction")
            dyn_off = kept = None
            if row.fuse_without_removal:
                off = res[row.fuse_without_removal].metrics
                dyn_off = off.get("dynamic_fraction")
                out[row.label]["dynamic_fraction_without_removal"] = dyn_off
                # The share depends on the map's size (a larger house dilutes the same
                # people); the people points kept of those the map held without removal
                # does not.
                if m.get("dynamic_points") is not None and off.get("dynamic_points"):
                    kept = m["dynamic_points"] / off["dynamic_points"]
                    out[row.label]["dynamic_points_kept_fraction"] = kept
            if dyn is not None and (first_dyn or row.fuse_without_removal):
                first_dyn = False
                checks.append((f"{row.label}: map points on moving obstacles <= "
                               f"{100 * cfg.dynamic_fraction_target:g} %"
                               + (f" (without the removal: {100 * dyn_off:.2f} %)"
                                  if dyn_off is not None else ""),
                               f"{100 * dyn:.2f} %", dyn <= cfg.dynamic_fraction_target))
            # A fuse result of older code held the raw map's share there: before the
            # consensus and outlier steps too, which drop static voxels (and so it read as if
            # carving added people: 0.38 % before, 0.48 % after).
            before_carving = ("without carving, after the same consensus and outlier steps"
                              if "dynamic_fraction_raw" in m else
                              "of the raw map, before carving, consensus and outlier steps")
            gt_ratio = m.get("gt_rmse_ratio_scaled_unscaled")
            ok = ok_vis = ok_gt = None
            if first and ratio is not None:
                ok = ratio <= cfg.depth_ratio_target
                paper = PAPER["depth_ratio_unidepth"]
                checks.append((f"{row.label}: scaled / unscaled RMSE vs lidar, all pairs <= "
                               f"{cfg.depth_ratio_target:g} (paper {paper:.2f})",
                               f"{ratio:.3f}", ok))
                if vis is not None:
                    ok_vis = vis <= cfg.depth_ratio_target
                    checks.append((f"{row.label}: scaled / unscaled RMSE vs lidar, co-visible "
                                   f"pairs <= {cfg.depth_ratio_target:g}", f"{vis:.3f}", ok_vis))
                if gt_ratio is not None:
                    ok_gt = gt_ratio <= cfg.depth_ratio_target
                    checks.append((f"{row.label}: scaled / unscaled RMSE vs ground truth, "
                                   f"whole images <= {cfg.depth_ratio_target:g}",
                                   f"{gt_ratio:.3f}", ok_gt))
                first = False
            md.append(
                f"| {row.label} | {_num(m.get('lidar_unscaled_rmse_m'), '.3f', 1, ' m')} | "
                f"{_num(m.get('lidar_scaled_rmse_m'), '.3f', 1, ' m')} | **{_num(ratio)}**"
                f"{_mark(ok)} | **{_num(vis)}**{_mark(ok_vis)} "
                f"({_num(m.get('pairs_visible_fraction'), '.0f', 100, ' %')} of pairs) | "
                f"{_num(m.get('gt_scaled_rmse_m'), '.3f', 1, ' m')} | "
                f"{_num(gt_ratio)}{_mark(ok_gt)} | "
                f"{_num(m.get('gt_scaled_absrel'))} | {_num(m.get('gt_scaled_delta1'))} | "
                f"{_num(m.get('gt_refined_absrel'))} | "
                f"{_num(m.get('scale_error_median'), '.1f', 100, ' %')} | "
                f"{_num(dyn, '.2f', 100, ' %')} "
                f"({_num(m.get('dynamic_fraction_before_carving'), '.2f', 100, ' %')} "
                f"{before_carving}"
                + (f"; without removal {_num(dyn_off, '.2f', 100, ' %')}"
                   if row.fuse_without_removal else "")
                + (f", {100 * kept:.1f} % of its people points kept" if kept is not None
                   else "") + ") |")
        if cfg.camera_only:
            m = res[cfg.camera_only].metrics
            for tag, label in (("own_scale",
                                f"without lidar (camera only), {_own_scale_label(m)}"),
                               ("sim3", "without lidar (camera only), Sim(3)")):
                d = m.get(f"depth_{tag}")
                if d:
                    md.append(f"| {label} | - | - | - | - | "
                              f"{_num(d.get('rmse_m'), '.3f', 1, ' m')} | - | "
                              f"{_num(d.get('absrel'))} | {_num(d.get('delta1'))} | - | - | - |")
                    out[label] = d
        md += [f"| paper, UniDepth | {PAPER['depth_unscaled_rmse_m']} m | "
               f"{PAPER['depth_scaled_rmse_m']} m | {PAPER['depth_ratio_unidepth']:.2f} "
               "| | | | | | | | |",
               f"| paper, Depth Anything | | | {PAPER['depth_ratio_depth_anything']:.2f} | | | | |"
               " | | | |", ""]
        tables["table_iv"] = out
        return md

    # ------------------------------------------------------------------ figures
    def _figures(self, cfg: PaperTablesConfig, res: dict[str, StageResult]) -> list[str]:
        first = next((r for r in cfg.rows if not r.timing_only), cfg.rows[0])
        fuse = res.get(first.fuse) if first.fuse else None
        links = [
            ("Figure 3: lidar points projected into the image (calibration check)",
             _link(res.get(cfg.calibrate) if cfg.calibrate else None,
                   "check/overlay_vs_rotated_0.png", "lidar overlay, true vs rotated 2 deg")),
            ("Figure 3: lidar points projected into the image (fusion pairs)",
             _link(fuse, "lidar_overlay.png", "lidar overlay")),
            ("Figure 6: depth error, scaled (per-frame lidar scale) vs unscaled",
             _link(fuse, "depth_scaled_vs_unscaled.png", "depth error")),
            ("The coloured map (fused cloud)", _link(fuse, "map_views.png", "map views")),
            ("The TSDF mesh", _link(res.get(first.tsdf) if first.tsdf else None, "views.png",
                                    "TSDF views")),
            ("The splats (real | rendered | depth)", _link(res.get(first.splat) if first.splat
                                                          else None, "renders.png", "splats")),
            ("Splats vs TSDF at held-out views", _link(res.get(first.splat) if first.splat
                                                       else None, "splat_vs_tsdf.png", "compare")),
            ("Camera only", _link(res.get(cfg.camera_only) if cfg.camera_only else None,
                                  "camera_only.png", "camera only")),
        ]
        md = [f"### Figures ({first.label})", ""]
        for title, link in links:
            if link:
                md += [f"**{title}**", "", link, ""]
        return md


def _plot_curves(gt: np.ndarray, curves: dict[str, np.ndarray], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from toolkit.io.atomic import atomic_path

    fig, ax = plt.subplots(figsize=(7.5, 6))
    ax.plot(gt[:, 0], gt[:, 1], "k-", lw=2.5, label="ground truth")
    for k, (label, p) in enumerate(curves.items()):
        ax.plot(p[:, 0], p[:, 1], f"C{k + 1}-" if k == 0 else f"C{k + 1}--", lw=1.3, label=label)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("camera trajectories (Figure 5)")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)

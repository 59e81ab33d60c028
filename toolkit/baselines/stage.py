"""Recipe stages of the baselines: ``tsdf``, ``colmap`` and ``camera_only``.

Each answers one question a user asks of a run:

- ``tsdf``: does a classic volumetric fusion of the same depth at the same poses give the
  same surface? (and, with ``depth_source: groundtruth``, what is the best any depth could do)
- ``colmap``: do the images alone agree with our poses? SfM poses Sim(3)-aligned to ours,
  and triangulation at our fixed poses; plus our poses exported as a COLMAP text model.
- ``camera_only``: what did the lidar buy? The same map built without it.
"""

from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field

from toolkit.geometry import Trajectory
from toolkit.io.atomic import atomic_write_json
from toolkit.recipe.checkpoint import Checkpoint
from toolkit.recipe.stage import Stage, StageConfig, StageContext, StageError
from toolkit.sensors import Sequence
from toolkit.settings import AddedOptions

# ---------------------------------------------------------------------------- shared


def _read_sequence(ctx: StageContext) -> Sequence:
    from toolkit.io.sequence import read_sequence

    seq = read_sequence(ctx.artifact("sequence"))
    if not seq.frames:
        raise StageError(f"{ctx.stage_id}: sequence {seq.name} has no camera frames")
    return seq


def _poses(ctx: StageContext, seq: Sequence, mode: str) -> Any:
    from toolkit.baselines.common import frame_poses

    use_traj = mode in ("auto", "trajectory") and ctx.has_artifact("trajectory")
    if mode == "trajectory" and not use_traj:
        raise StageError(f"{ctx.stage_id}: poses: trajectory, but no stage upstream provides "
                         "'trajectory' (add slam2d before it)")
    try:
        fp = frame_poses(seq, ctx.artifact("trajectory") if use_traj else None,
                         allow_groundtruth=mode != "trajectory")
    except (ValueError, FileNotFoundError) as e:
        raise StageError(f"{ctx.stage_id}: {e}") from None
    if fp.source == "groundtruth":
        ctx.log.warning("%s: no trajectory artifact; using GROUND-TRUTH poses", ctx.stage_id)
    if len(fp.indices) == 0:
        raise StageError(f"{ctx.stage_id}: no camera frame lies inside the trajectory's span")
    return fp


def lidar_curve(lidar: Trajectory, gt: Trajectory | None,
                max_diff_s: float = 0.02) -> tuple[str, np.ndarray] | None:
    """(label, camera centres [N, 3]) of the lidar SLAM trajectory to draw next to ``gt``.

    The SLAM map frame starts where the robot starts and ground truth lives in the
    recording's world, so drawn as stored the two curves lie a rigid motion apart (1.4 m on
    the paper benchmark, whose ATE is 1.24 cm). With ground truth the whole curve is moved
    by the SE(3) alignment evaluate scores it with (pairs within ``max_diff_s``, Umeyama
    without scale). None: fewer than 3 poses pair with ground truth, nothing to align on.
    """
    from toolkit.eval.trajectory import synced
    from toolkit.geometry import align_trajectory

    if gt is None:
        return "lidar SLAM", lidar.positions
    try:
        e, g = synced(lidar, gt, max_diff_s)
    except ValueError:
        return None
    if len(e) < 3:
        return None
    _, S = align_trajectory(e, g, with_scale=False)
    return "lidar SLAM (SE(3)-aligned)", lidar.positions @ S[:3, :3].T + S[:3, 3]


def _select(indices: np.ndarray, every: int, max_images: int | None) -> np.ndarray:
    """Every ``every``-th index, then thinned evenly to at most ``max_images``."""
    sel = np.asarray(indices)[::every]
    if max_images is not None and len(sel) > max_images:
        sel = sel[np.unique(np.linspace(0, len(sel) - 1, max_images).round().astype(int))]
    return sel


def _mesh_reference(seq: Sequence, poses: np.ndarray, max_depth_m: float,
                    spacing_m: float, max_views: int) -> tuple[Any, np.ndarray] | None:
    """Ground-truth mesh and its samples seen from ``poses`` (None without a mesh); every
    pose is tested up to ``max_views`` of them, as evaluate's ``completeness_views``."""
    gt = seq.groundtruth
    if gt is None or gt.mesh_path is None:
        return None
    from toolkit.baselines.common import observed_reference
    from toolkit.baselines.tsdf import read_mesh

    mesh = read_mesh(gt.mesh_path)
    ref = observed_reference(mesh, seq.rig.camera.undistorted(), poses, spacing_m,
                             max_views=max_views, max_depth_m=max_depth_m)
    return mesh, ref


def _fmt(v: Any, digits: int = 4) -> str:
    if isinstance(v, float):
        return "n/a" if not np.isfinite(v) else f"{v:.{digits}g}"
    return str(v)


def _table(rows: list[tuple[str, Any]]) -> str:
    return "\n".join(["| figure | value |", "|---|---|",
                      *(f"| {k} | {_fmt(v)} |" for k, v in rows)])


def _geometry_rows(prefix: str, g: dict[str, Any]) -> list[tuple[str, Any]]:
    return [(f"{prefix} accuracy mean [m]", g["accuracy_mean_m"]),
            (f"{prefix} completeness mean [m]", g["completeness_mean_m"]),
            (f"{prefix} Chamfer [m]", g["chamfer_m"]),
            (f"{prefix} F-score 2 / 5 / 10 cm",
             f"{g['fscore_2cm']:.3f} / {g['fscore_5cm']:.3f} / {g['fscore_10cm']:.3f}")]


# ---------------------------------------------------------------------------- tsdf


class TSDFConfig(StageConfig, AddedOptions):
    """Settings of the ``tsdf`` stage."""

    added_unused = {"reference_views": "geometry"}

    # scaled: the fuse stage's lidar-scaled depth; groundtruth: the simulator's exact depth
    # (the upper bound any depth network could reach at these poses).
    depth_source: Literal["scaled", "groundtruth"] = "scaled"
    poses: Literal["auto", "trajectory", "groundtruth"] = "auto"
    # Pixels on moving people: "groundtruth" drops them with the simulator's masks; "auto"
    # does so for ground-truth depth only (the upper bound), never for scaled depth, whose
    # row must cope with people as the method does, without ground truth.
    mask_dynamic: Literal["auto", "groundtruth", "none"] = "auto"
    # Metres, as fuse's (over a metre is a unit mistake: 20 gave an empty mesh blamed on
    # the depth).
    voxel_size_m: float = Field(0.02, gt=0, le=1.0)
    trunc_voxels: float = Field(4.0, gt=0)
    depth_max_m: float = Field(6.0, gt=0)  # as fuse's max_depth_m: far mono depth is guesswork
    # Frames that must see a voxel. None: 1 for ground-truth depth, 2 for scaled depth,
    # where it removes single-frame junk (on the simulated house F @ 5 cm 0.47 -> 0.55).
    min_observations: int | None = Field(None, ge=1)
    every: int = Field(1, ge=1)  # integrate every n-th frame
    # fused: colours at the exposure gains an upstream fuse stage solved (its
    # `exposure: gain`; without them the images as they are); none: the images as they are.
    exposure: Literal["fused", "none"] = "fused"
    views: int = Field(3, ge=0)  # rendered comparison views in the report
    eval_spacing_m: float = Field(0.01, gt=0)  # sample spacing for the mesh comparison
    geometry: bool = True  # compare with the ground-truth mesh here (off: leave it to evaluate)
    # Completeness is measured against the surface these many frames saw, every frame up to
    # it (evaluate's completeness_views): spread views above it miss what turns saw.
    reference_views: int = Field(1000, ge=1)
    # Save the volume this often (seconds; 0: never) so that a killed run resumes there.
    checkpoint_every_s: float = Field(300.0, ge=0)


def _scaled_depth_files(fused: Path) -> dict[int, Path]:
    """Frame index -> scaled depth file of the fuse stage (index.csv, else file names)."""
    import csv

    for sub in ("scaled_depth", "depth"):
        d = fused / sub
        if (d / "index.csv").exists():
            with (d / "index.csv").open(newline="") as f:
                return {int(r["index"]): d / r["file"] for r in csv.DictReader(f)}
        if d.is_dir():
            files = sorted([*d.glob("[0-9]*.npy"), *d.glob("[0-9]*.png")])
            return {int(p.stem): p for p in files if p.stem.isdigit()}
    return {}


class TSDFStage(Stage):
    """TSDF mesh (Open3D VoxelBlockGrid) of scaled or ground-truth depth at our poses."""

    name = "tsdf"
    Config = TSDFConfig
    requires = ("sequence",)
    optional_requires = ("trajectory", "fused")
    provides = ("tsdf_mesh",)
    # 2: completeness to the mesh's surface; no poses across trajectory gaps. 3: the poses
    # it was built at written beside the mesh (camera_poses.tum); the observed reference
    # keeps surface seen at grazing angles. 4: its views scored against the images at the
    # mesh's exposure. 5: colour averaged in float32 (uint16 truncated it: darker meshes);
    # frames without valid depth skipped; no geometry score without an alignment
    # 6: the alignment fits on the frames the ground truth covers, no end slack
    # 7: a straight path's alignment turns about the reference's line, not the estimate's
    # 8: frames within the end slack outside the trajectory's span get its end pose even
    #    when a long gap follows that end (Trajectory.covers refused them)
    version = 8

    def run(self, ctx: StageContext) -> None:
        import cv2

        from toolkit.baselines.common import groundtruth_camera_trajectory, poses_at_frames
        from toolkit.baselines.tsdf import TSDFSettings, TSDFVolume, write_mesh
        from toolkit.fusion.exposure import EXPOSURE_FILE, corrected_image, gains_for_frames
        from toolkit.io.depth import read_depth

        cfg: TSDFConfig = self.config  # type: ignore[assignment]
        seq = _read_sequence(ctx)
        gt = seq.groundtruth
        fp = _poses(ctx, seq, cfg.poses)
        if cfg.depth_source == "scaled":
            if not ctx.has_artifact("fused"):
                raise StageError(f"{ctx.stage_id}: depth_source: scaled needs a fuse stage "
                                 "upstream (its per-frame scaled depth); add one, or set "
                                 "depth_source: groundtruth")
            files = _scaled_depth_files(ctx.artifact("fused"))
            if not files:
                raise StageError(f"{ctx.stage_id}: {ctx.artifact('fused')} holds no per-frame "
                                 "scaled depth (was fuse run with write_depth: none?)")

            def depth_of(i: int) -> np.ndarray:
                return read_depth(files[i])
            have = set(files)
            depth_note = "the `fuse` stage's lidar-scaled monocular depth"
        else:
            if gt is None or gt.depth_paths is None:
                raise StageError(f"{ctx.stage_id}: depth_source: groundtruth, but sequence "
                                 f"{seq.name} has no ground-truth depth")

            def depth_of(i: int) -> np.ndarray:
                return gt.depth(i)
            have = set(range(len(seq.frames)))
            depth_note = "**ground-truth depth** (upper bound)"
        keep = np.array([i in have for i in fp.indices], bool)
        indices, poses = fp.indices[keep][:: cfg.every], fp.poses[keep][:: cfg.every]
        if len(indices) == 0:
            raise StageError(f"{ctx.stage_id}: no frame has both a pose and depth")
        use_masks = cfg.mask_dynamic == "groundtruth" or (
            cfg.mask_dynamic == "auto" and cfg.depth_source == "groundtruth")
        if use_masks and (gt is None or gt.mask_paths is None):
            if cfg.mask_dynamic == "groundtruth":
                raise StageError(f"{ctx.stage_id}: mask_dynamic: groundtruth, but sequence "
                                 f"{seq.name} has no ground-truth masks")
            use_masks = False
        if use_masks:
            depth_note += ", pixels on moving people removed with ground-truth masks"
        gains: dict[int, np.ndarray] = {}
        if cfg.exposure == "fused" and ctx.has_artifact("fused"):
            try:
                gains = gains_for_frames(ctx.artifact("fused"), indices)
            except ValueError as exc:
                raise StageError(f"{ctx.stage_id}: {exc}") from exc
        if gains:
            depth_note += (", colours at the exposure gains the `fuse` stage solved "
                           f"(`{EXPOSURE_FILE}`)")
        cam = seq.rig.camera
        ucam = cam.undistorted()
        settings = TSDFSettings(cfg.voxel_size_m, cfg.trunc_voxels, cfg.depth_max_m,
                                min_observations=cfg.min_observations or (
                                    1 if cfg.depth_source == "groundtruth" else 2))
        # One block at first: the frames' blocks, computed before any goes in, size the map
        # once (TSDFVolume.reserve_for; Open3D's doubling held 640 MiB of voxels for 370 used
        # on the quickstart, and 960 while it copied). The mesh is the same to the byte.
        vol = TSDFVolume(replace(settings, block_count=1))
        ckpt = Checkpoint(ctx.stage_dir / "checkpoint.pkl", ctx.resume_key,
                          cfg.checkpoint_every_s, ctx.log)
        saved = ckpt.load(lambda x: isinstance(x, dict) and {"volume", "done", "integrate_s"}
                          <= x.keys())
        resumed, t_int = 0, 0.0
        if saved is not None:
            vol.restore(saved["volume"])
            resumed, t_int = saved["done"], saved["integrate_s"]
            saved = None  # the grid's bytes: as large as the volume
            ctx.log.info("%s: resuming after %d/%d frames", ctx.stage_id, resumed, len(indices))

        def depth_at(k: int) -> np.ndarray:
            """[H, W] metres of the k-th frame to integrate, masked and undistorted."""
            i = int(indices[k])
            depth = depth_of(i)
            if use_masks:
                depth = np.where(gt.mask(i), 0.0, depth).astype(np.float32)
            if cam.has_distortion:
                depth = cam.undistort_image(depth, interpolation=cv2.INTER_NEAREST)
            return depth

        todo = range(resumed, len(indices))
        blocks: list[np.ndarray | None] = []  # [B, 3] int32 per frame, a few KB each
        for k in ctx.progress(todo, total=len(todo), description="tsdf blocks"):
            depth = depth_at(k)
            t0 = time.perf_counter()  # integrate's own work before: timed as integration
            blocks.append(vol.frame_blocks(depth, ucam, poses[k]))
            t_int += time.perf_counter() - t0
        vol.reserve_for(blocks)
        for k in ctx.progress(todo, total=len(todo), description="tsdf"):
            i, T = indices[k], poses[k]
            rgb = seq.frames[i].image
            if int(i) in gains:
                rgb = corrected_image(rgb, gains[int(i)])
            depth = depth_at(k)
            if cam.has_distortion:
                rgb = cam.undistort_image(rgb)
            t0 = time.perf_counter()
            vol.integrate(depth, rgb, ucam, T, blocks[k - resumed])
            t_int += time.perf_counter() - t0
            blocks[k - resumed] = None
            if ckpt.due():
                ckpt.save({"volume": vol.state(), "done": k + 1, "integrate_s": t_int})
        t0 = time.perf_counter()
        mesh = vol.extract_mesh()
        t_ext = time.perf_counter() - t0
        skipped = vol.skipped
        # The voxels are done with: the views and the geometry below ran beside them.
        del vol
        if len(mesh.triangles) == 0:
            raise StageError(f"{ctx.stage_id}: the TSDF mesh is empty (depth all invalid or "
                             f"beyond depth_max_m={cfg.depth_max_m}?)")
        out = ctx.stage_dir / "mesh.ply"
        write_mesh(out, mesh)
        # The poses the mesh was built at, beside it: evaluate aligns a mesh built at SLAM
        # poses to the world, and leaves one built at ground-truth poses where it is.
        from toolkit.geometry import Trajectory
        from toolkit.io.tum import write_tum

        write_tum(ctx.stage_dir / "camera_poses.tum",
                  Trajectory(seq.frame_stamps[indices], poses, "world", "camera"),
                  f"poses: {fp.source}")
        ctx.provide("tsdf_mesh", out)
        metrics: dict[str, Any] = {
            "depth_source": cfg.depth_source, "poses": fp.source, "frames": int(len(indices)),
            "dynamic_masked": use_masks, "min_observations": settings.min_observations,
            "vertices": len(mesh.vertices), "triangles": len(mesh.triangles),
            "integrate_ms_per_frame": 1000 * t_int / len(indices), "extract_s": t_ext,
            "frames_resumed": resumed, "frames_without_depth": skipped,
        }
        if skipped:
            ctx.log.warning("%s: %d of %d frames had no valid depth (0, NaN or beyond "
                            "depth_max_m %g) and added nothing", ctx.stage_id, skipped,
                            len(indices), cfg.depth_max_m)
        rows: list[tuple[str, Any]] = [
            ("frames integrated", len(indices) - skipped),
            ("triangles", len(mesh.triangles)),
            ("integration [ms/frame]", metrics["integrate_ms_per_frame"]),
            ("mesh extraction [s]", t_ext)]
        # Geometry against the ground-truth surface the cameras saw (true poses for visibility).
        gt_traj = groundtruth_camera_trajectory(seq)
        vis_poses = poses_at_frames(gt_traj, seq)[1][:: cfg.every] if gt_traj is not None else poses
        ref = _mesh_reference(seq, vis_poses, cfg.depth_max_m, cfg.eval_spacing_m,
                              cfg.reference_views) if cfg.geometry else None
        S = None
        aligned = fp.source == "groundtruth"  # in the world frame already
        if ref is not None and not aligned:
            from toolkit.eval.alignment import map_to_world

            # SLAM poses live in the map frame, the ground truth in the world: align first.
            S = map_to_world(seq, seq.frame_stamps[indices], poses)
            aligned = S is not None
        if ref is not None and not aligned:
            # A ground-truth mesh without ground-truth poses: nothing ties the map frame to
            # the mesh's (a perfect mesh scored 1.50 m accuracy, F@5cm 0.043).
            ctx.log.warning("%s: geometry not scored: the mesh is in the %s poses' map frame "
                            "and the sequence has no ground-truth poses to align it to the "
                            "ground-truth mesh", ctx.stage_id, fp.source)
            rows.append(("vs GT mesh", "not scored: no ground-truth poses to align to"))
            metrics["geometry_scored"] = False
        elif ref is not None:
            import open3d as o3d

            from toolkit.eval.alignment import apply
            from toolkit.eval.geometry import geometry_metrics, mesh_distances, sample_mesh

            # Accuracy to the mesh itself, as evaluate scores maps: against the observed
            # samples, surface the views did not test counted as error.
            pts = apply(S, sample_mesh(mesh, cfg.eval_spacing_m))
            moved = o3d.geometry.TriangleMesh(mesh)
            if S is not None:
                moved.transform(S)
            # Completeness to the mesh's surface, not to points sampled on it (their gaps
            # cost a perfect mesh 1 cm and 5 % of recall at 2 cm).
            g = geometry_metrics(pts, ref[1], accuracy_distances=mesh_distances(pts, ref[0]),
                                 completeness_distances=mesh_distances(ref[1], moved))
            metrics["geometry"] = g
            rows += _geometry_rows("vs GT mesh:", g)
        md = [f"TSDF fusion (Open3D VoxelBlockGrid, {cfg.voxel_size_m * 100:g} cm voxels, "
              f"truncation {cfg.trunc_voxels:g} voxels) of {depth_note}. {fp.note}",
              _table(rows)]
        if cfg.views > 0:
            views = self._views(ctx, seq, mesh, ucam, indices, poses, cfg, gains)
            metrics["views"] = views["metrics"]
            md.append(f"Camera image (left) and the TSDF mesh rendered at the same pose "
                      f"(right), {cfg.views} of the integrated frames spread along the path "
                      f"(in-sample); PSNR over covered pixels "
                      f"{views['metrics']['psnr_db']:.1f} dB, coverage "
                      f"{views['metrics']['coverage']:.0%}.")
            md.append(f"![TSDF views]({ctx.stage_id}/{views['png']})")
        if resumed:
            md.append(f"Resumed an interrupted run: {resumed}/{len(indices)} frames came from "
                      "its checkpoint.")
        md.append(f"Mesh: [mesh.ply]({ctx.stage_id}/mesh.ply)")
        ctx.add_metrics(metrics)
        ctx.report("\n\n".join(md))
        ckpt.remove()  # every output is written: a rerun has nothing to resume

    @staticmethod
    def _views(ctx: StageContext, seq: Sequence, mesh: Any, cam: Any, indices: np.ndarray,
               poses: np.ndarray, cfg: TSDFConfig,
               gains: dict[int, np.ndarray] | None = None) -> dict[str, Any]:
        from toolkit.baselines.common import psnr, write_png
        from toolkit.baselines.tsdf import MeshRenderer
        from toolkit.fusion.exposure import corrected_image

        renderer = MeshRenderer(mesh)
        # Mid-points of equal parts of the path: a closed loop ends where it began, so the
        # first and last frames showed one viewpoint twice.
        n = min(cfg.views, len(indices))
        sel = np.unique(((np.arange(n) + 0.5) * len(indices) / n).astype(int))
        rows, ps, cov = [], [], []
        for k in sel:
            i = int(indices[k])
            img = seq.frames[i].image
            if gains and i in gains:
                # As the mesh's colours were integrated: the frame's exposure divided out
                # (against the raw image a gain of 1.3 scored 16.9 dB for a 41.4 dB mesh).
                img = corrected_image(img, gains[i])
            if seq.rig.camera.has_distortion:
                img = seq.rig.camera.undistort_image(img)
            rgb, depth = renderer.render(cam, poses[k])
            m = depth > 0
            ps.append(psnr(rgb, img, m))
            cov.append(float(m.mean()))
            rows.append(np.concatenate([img, rgb], 1))
        name = "views.png"
        write_png(ctx.stage_dir / name, np.concatenate(rows, 0))
        return {"png": name, "metrics": {"psnr_db": float(np.mean(ps)),
                                         "coverage": float(np.mean(cov)), "count": len(sel)}}


# ---------------------------------------------------------------------------- colmap


def _matched_database(ctx: StageContext, db: Path, image_dir: Path, names: list[str],
                      cam: Any, settings: Any) -> tuple[dict[str, float], bool]:
    """Features and verified matches of ``names`` in ``db``; the seconds each step took and
    whether they came from an interrupted run of this stage.

    They are most of COLMAP's time, so a complete database that a killed run left (marked
    with the stage's cache key in ``<db>.json`` once matching finished) is used again. The
    mark goes when the stage finishes (``_database_done``): a rerun of a finished stage
    (``--force``) extracts and matches afresh.
    """
    from toolkit.baselines.colmap import extract_and_match

    marker = db.with_suffix(".json")
    done = json.loads(marker.read_text()) if marker.exists() and db.exists() else {}
    if ctx.resume_key and done.get("key") == ctx.resume_key:
        ctx.log.info("%s: features and matches kept from an interrupted run", ctx.stage_id)
        return done["seconds"], True
    marker.unlink(missing_ok=True)
    seconds = extract_and_match(db, image_dir, names, cam, settings)
    atomic_write_json(marker, {"key": ctx.resume_key, "seconds": seconds})
    return seconds, False


def _database_done(ctx: StageContext) -> None:
    """The stage finished: its database is an output now, not an interrupted run's."""
    (ctx.stage_dir / "database.json").unlink(missing_ok=True)


class _ColmapKeys(StageConfig, AddedOptions):
    """COLMAP keys shared by ``colmap`` and ``camera_only``."""

    # mapper (session 29) left at incremental is not part of the settings: stages made
    # before it keep their cache key.
    added_off = {"mapper": "incremental"}

    matching: Literal["sequential", "exhaustive"] = "sequential"
    overlap: int = Field(10, ge=1)
    max_features: int = Field(4096, ge=64)
    intrinsics: Literal["known", "refine", "unknown"] = "known"
    every: int = Field(1, ge=1)  # use every n-th frame
    max_images: int | None = Field(300, ge=3)  # then thin evenly to at most this many
    # More than one thread gives another model from run to run (ColmapSettings).
    threads: int = Field(1, ge=1)
    seed: int = 0
    # incremental (pycolmap.incremental_mapping) or global (pycolmap.global_mapping, COLMAP
    # 4's GLOMAP) on the same features and matches; docs/baselines.md compares them.
    mapper: Literal["incremental", "global"] = "incremental"

    def colmap_settings(self) -> Any:
        from toolkit.baselines.colmap import ColmapSettings

        return ColmapSettings(matching=self.matching, overlap=self.overlap,
                              max_features=self.max_features, intrinsics=self.intrinsics,
                              num_threads=self.threads, seed=self.seed, mapper=self.mapper)


class ColmapConfig(_ColmapKeys):
    """Settings of the ``colmap`` stage."""

    poses: Literal["auto", "trajectory", "groundtruth"] = "auto"  # for triangulation/export
    triangulate: bool = True
    export: bool = True  # our poses + intrinsics as a COLMAP text model
    export_points: Literal["auto", "fused", "triangulated", "none"] = "auto"
    export_images: bool = True  # hard-link (or copy) the (undistorted) images next to it
    # A fused map has ~1M points (~90 MB as text); 3DGS trainers start from ~100k SfM points,
    # so a random subset keeps the file small without changing the initialisation.
    export_max_points: int | None = Field(300_000, ge=1)


class ColmapStage(Stage):
    """COLMAP (pycolmap, CPU) on the images: SfM vs our poses, triangulation at our poses."""

    name = "colmap"
    Config = ColmapConfig
    requires = ("sequence",)
    optional_requires = ("trajectory", "fused")
    provides = ("colmap",)
    # 2: written alignments on covered poses; no poses across trajectory gaps. 3: one
    # thread by default (repeatable). 4: points at SLAM poses not scored against the
    # ground-truth mesh without ground-truth poses to align them
    # 5: the alignment fits on the frames the ground truth covers, no end slack
    # 6: the exported fused map moved into the exported poses' frame (or the triangulated
    # points instead): cameras and points came from different frames
    # 7: a straight path's alignment turns about the reference's line, not the estimate's
    version = 7
    outputs_repeat = False  # sfm/summary.json holds the steps' seconds

    def run(self, ctx: StageContext) -> None:
        from toolkit.baselines.colmap import evaluate_sfm_trajectory, run_sfm, save_sfm
        from toolkit.baselines.common import groundtruth_camera_trajectory, image_folder

        cfg: ColmapConfig = self.config  # type: ignore[assignment]
        seq = _read_sequence(ctx)
        settings = cfg.colmap_settings()
        sel = _select(np.arange(len(seq.frames)), cfg.every, cfg.max_images)
        image_dir, names, cam = image_folder(seq, sel, ctx.stage_dir)
        frame_of = {n: int(i) for n, i in zip(names, sel, strict=True)}
        stamp_of = {n: float(seq.frame_stamps[i]) for n, i in frame_of.items()}
        # Our poses, before the SfM that can take minutes: a recording of the user's own
        # with neither slam2d upstream nor ground truth gets SfM alone (poses: auto).
        fp, pose_note = None, ""
        if cfg.triangulate or cfg.export:
            gt = seq.groundtruth
            if cfg.poses == "auto" and not ctx.has_artifact("trajectory") and (
                    gt is None or gt.poses_base is None):
                pose_note = ("No poses of ours (no slam2d upstream, no ground truth): SfM "
                             "only, no triangulation or export at our poses.")
                ctx.log.warning("colmap: %s", pose_note)
            else:
                fp = _poses(ctx, seq, cfg.poses)
                pose_note = fp.note
        db = ctx.stage_dir / "database.db"
        ctx.log.info("colmap: %d images, %s matching", len(names), cfg.matching)
        seconds, database_kept = _matched_database(ctx, db, image_dir, names, cam, settings)
        sfm = run_sfm(image_dir, names, cam, ctx.stage_dir / "work", settings, database=db)
        sfm.seconds.update(seconds)
        save_sfm(sfm, ctx.stage_dir / "sfm", frame_of, stamp_of, names)
        metrics: dict[str, Any] = {"sfm": sfm.summary(), "mapper": cfg.mapper,
                                   "database_resumed": database_kept}
        rows: list[tuple[str, Any]] = [
            ("images / registered", f"{sfm.images} / {sfm.registered}"),
            ("separate models", sfm.models), ("sparse points", sfm.points),
            ("mean reprojection error [px]", sfm.reprojection_error_px),
            ("extract / match / map [s]", " / ".join(f"{sfm.seconds.get(k, float('nan')):.1f}"
                                                    for k in ("extract", "match", "mapping")))]
        curves: dict[str, np.ndarray] = {}
        gt_traj = groundtruth_camera_trajectory(seq)
        lidar_traj = None
        if ctx.has_artifact("trajectory"):
            from toolkit.baselines.common import load_camera_trajectory

            lidar_traj = load_camera_trajectory(ctx.artifact("trajectory"), seq)
        if gt_traj is not None:
            curves["ground truth"] = gt_traj.positions
        if lidar_traj is not None:
            gt_at_lidar = None
            if gt_traj is not None:
                from toolkit.eval.alignment import covered_ground_truth

                _, gt_at_lidar = covered_ground_truth(seq, lidar_traj)
            drawn = lidar_curve(lidar_traj, gt_at_lidar)
            if drawn is None:
                ctx.log.warning("colmap: ground truth covers fewer than 3 lidar SLAM poses; "
                                "the lidar curve is left out of trajectories.png")
            else:
                curves[drawn[0]] = drawn[1]
        if sfm.registered >= 3:
            est = sfm.trajectory(stamp_of)
            for tag, ref in (("groundtruth", gt_traj), ("lidar", lidar_traj)):
                if ref is None:
                    continue
                try:
                    e = evaluate_sfm_trajectory(est, ref)
                except ValueError as exc:
                    ctx.log.warning("colmap: no comparison with %s: %s", tag, exc)
                    continue
                metrics[f"sfm_vs_{tag}"] = e
                rows += [(f"SfM vs {tag}: ATE Sim(3) [m]", e["ate_sim3_rmse_m"]),
                         (f"SfM vs {tag}: ATE SE(3), own scale [m]", e["ate_se3_rmse_m"]),
                         (f"SfM vs {tag}: scale [m per model unit]", e["scale_to_reference"])]
            ref = gt_traj if gt_traj is not None else lidar_traj
            ref_name = "groundtruth" if gt_traj is not None else "lidar"
            if ref is not None and f"sfm_vs_{ref_name}" in metrics:
                from toolkit.baselines.camera_only import alignments

                # Fitted on the poses the metrics score (inside the reference's span, not
                # across a gap of it): a pose beyond its end, compared with the end pose,
                # bent the written alignment away from the one the figures describe.
                inside = ref.covers(est.stamps)
                ref_at = ref.interpolate(est.stamps[inside])
                al = alignments(est.poses[inside], ref_at.poses)
                for tag, label in (("sim3", "COLMAP, Sim(3)-aligned"),
                                   ("se3", "COLMAP, SE(3), own scale")):
                    S = al[tag]
                    curves[label] = est.positions @ S[:3, :3].T + S[:3, 3]
                    _write_aligned(ctx.stage_dir / "sfm" / f"trajectory_{tag}.tum", est, S,
                                   f"COLMAP camera poses, {tag}-aligned to {ref_name}")
        else:
            ctx.log.warning("colmap: only %d images registered; no trajectory comparison",
                            sfm.registered)
        md = [f"COLMAP {cfg.matching} matching, {cfg.mapper} mapping on {len(names)} images "
              f"(intrinsics: {cfg.intrinsics})."
              + (" Features and matches from an interrupted run of the same settings."
                 if database_kept else "")]
        if pose_note:
            md.append(pose_note)
        if cfg.triangulate and fp is not None:
            tri = self._triangulate(ctx, seq, fp, frame_of, image_dir, cam, db, settings)
            if tri is not None:
                metrics["triangulation"] = tri
                rows += [("triangulation at our poses: points", tri["points"]),
                         ("triangulation at our poses: reprojection [px]",
                          tri["reprojection_error_px"]),
                         ("triangulation at our poses: mean track length",
                          tri["mean_track_length"])]
                if "gt_mesh_distance_median_m" in tri:
                    rows.append(("triangulated points to GT mesh, median [m]",
                                 tri["gt_mesh_distance_median_m"]))
        md.append(_table(rows))
        if len(curves) >= 2:
            from toolkit.baselines.common import plot_topdown

            plot_topdown(ctx.stage_dir / "trajectories.png", curves,
                         "COLMAP camera centres vs reference (top view)")
            md.append(f"![COLMAP trajectories]({ctx.stage_id}/trajectories.png)")
        if cfg.export and fp is not None:
            ex = self._export(ctx, seq, fp, cfg)
            metrics["export"] = ex
            md.append(f"Our poses and intrinsics as a COLMAP text model for Gaussian-splatting "
                      f"and NeRF tools: `{ctx.stage_id}/export/sparse/0/` "
                      f"({ex['images']} images, {ex['points']} points from {ex['points_from']}"
                      + (", images in `export/images/`" if cfg.export_images else "") + ").")
        ctx.add_metrics(metrics)
        ctx.provide("colmap", ctx.stage_dir)
        ctx.report("\n\n".join(md))
        _database_done(ctx)

    @staticmethod
    def _triangulate(ctx: StageContext, seq: Sequence, fp: Any, frame_of: dict[str, int],
                     image_dir: Path, cam: Any, db: Path, settings: Any) -> dict[str, Any] | None:
        from toolkit.baselines.colmap import triangulate_known_poses

        pose_of = {int(i): T for i, T in zip(fp.indices, fp.poses, strict=True)}
        names = [n for n, i in frame_of.items() if i in pose_of]
        if len(names) < 2:
            ctx.log.warning("colmap: fewer than 2 selected frames have poses; no triangulation")
            return None
        poses = np.stack([pose_of[frame_of[n]] for n in names])
        # Features matched under other intrinsics settings are verified with another camera
        # model; triangulation at our poses uses our pinhole K, so match again in that case.
        tri_db = db if settings.intrinsics == "known" else None
        tri = triangulate_known_poses(image_dir, names, cam, poses, ctx.stage_dir / "triangulation",
                                      settings, database=tri_db)
        out: dict[str, Any] = {**tri.summary(), "poses": fp.source}
        gt = seq.groundtruth
        if gt is not None and gt.mesh_path is not None and tri.points > 0:
            from toolkit.eval.alignment import apply, map_to_world
            from toolkit.eval.map_accuracy import MeshDistance

            # Points at SLAM poses are in the map frame: one rigid transform to the world.
            S = map_to_world(seq, seq.frame_stamps[fp.indices], fp.poses) if (
                fp.source != "groundtruth") else None
            if S is None and fp.source != "groundtruth":
                # Without ground-truth poses nothing ties the map frame to the mesh's.
                ctx.log.warning("colmap: triangulated points not scored against the "
                                "ground-truth mesh: no ground-truth poses to align the %s "
                                "poses' map frame to it", fp.source)
                return out
            d = MeshDistance(gt.mesh_path).distance(apply(S, tri.points_xyz()))
            out["gt_mesh_distance_median_m"] = float(np.median(d))
            out["gt_mesh_within_5cm"] = float(np.mean(d < 0.05))
        return out

    @staticmethod
    def _export(ctx: StageContext, seq: Sequence, fp: Any, cfg: ColmapConfig) -> dict[str, Any]:
        from toolkit.baselines.common import image_folder
        from toolkit.io.colmap_text import write_poses_as_colmap

        out = ctx.stage_dir / "export"
        points = colors = None
        source = "none"
        note = ""
        want = cfg.export_points
        if want in ("auto", "fused") and ctx.has_artifact("fused"):
            from toolkit.eval.alignment import apply
            from toolkit.fusion.voxel_map import read_map_ply

            ply = ctx.artifact("fused") / "map.ply"
            if ply.exists():
                # The map lies in the frame of the poses fuse built it at, which need not
                # be the exported ones (fuse at SLAM poses, export at ground truth: 0.9 %
                # of the points where the cameras see a surface, 90 % when consistent).
                S, note = fused_map_to_poses(ctx.artifact("fused") / "camera_poses.tum",
                                             seq.frame_stamps[fp.indices], fp.poses)
                if S is None:
                    if want == "fused":
                        raise StageError(
                            f"{ctx.stage_id}: export_points: fused, but {note}; set the "
                            "fuse stage's poses to this stage's (poses: "
                            f"{fp.source}), or export_points: triangulated")
                    ctx.log.warning("%s: export: %s; exporting the points triangulated at "
                                    "the exported poses instead", ctx.stage_id, note)
                else:
                    points, colors = read_map_ply(ply)
                    points = apply(S, points)
                    source = "the fused map" + (f" ({note})" if note else "")
        elif want == "fused":
            raise StageError(f"{ctx.stage_id}: export_points: fused needs a fuse stage upstream")
        if points is None and want in ("auto", "triangulated"):
            tri_dir = ctx.stage_dir / "triangulation" / "triangulated"
            if (tri_dir / "points3D.bin").exists() or (tri_dir / "points3D.txt").exists():
                import pycolmap

                rec = pycolmap.Reconstruction(tri_dir)
                pts = list(rec.points3D.values())
                points = np.array([p.xyz for p in pts]).reshape(-1, 3)
                colors = np.array([p.color for p in pts], np.uint8).reshape(-1, 3)
                source = "triangulation at our poses"
        if points is not None and cfg.export_max_points and len(points) > cfg.export_max_points:
            keep = np.sort(np.random.default_rng(0).choice(len(points), cfg.export_max_points,
                                                           replace=False))
            points, colors = points[keep], colors[keep]
            source += f" (random {cfg.export_max_points} of them)"
        if cfg.export_images:
            image_dir, names, cam = image_folder(seq, list(fp.indices), out / "_staging")
            img_out = out / "images"
            img_out.mkdir(parents=True, exist_ok=True)
            import shutil

            for n in names:
                _link_or_copy(image_dir / n, img_out / n)
            if (out / "_staging").exists():
                shutil.rmtree(out / "_staging")
        else:
            names = [seq.frames[int(i)].path.name if seq.frames[int(i)].path else
                     f"{int(i):06d}.png" for i in fp.indices]
            cam = seq.rig.camera
        write_poses_as_colmap(out / "sparse" / "0", cam, names, fp.poses, points, colors)
        if points is None and note:
            source += f" (not the fused map: {note})"
        return {"images": len(names), "points": 0 if points is None else len(points),
                "points_from": source, "poses": fp.source}


def fused_map_to_poses(fused_poses: Path, stamps: np.ndarray, poses: np.ndarray,
                       tol_m: float = 1e-3, max_rms_m: float = 0.05) -> (
                           tuple[np.ndarray | None, str]):
    """(S [4, 4] with ``x = S @ x_map`` moving a fused map into the frame of ``poses``
    [N, 4, 4] T_world_camera at ``stamps`` [N], a note for the report), from the poses the
    map was built at (``fused_poses``: fuse's ``camera_poses.tum``) at the stamps both hold.

    The identity and no note when the map was built at these poses (every common camera
    centre within ``tol_m``); the rigid fit of those poses onto these when they differ by
    one rigid motion (a SLAM map frame against ground truth; at most ``max_rms_m`` RMS
    left); None when nothing ties the two frames together.
    """
    from toolkit.eval.alignment import apply
    from toolkit.geometry import rigid_alignment, rotation_angle, se3
    from toolkit.ingest.sync import match_nearest
    from toolkit.io.tum import read_tum

    if not fused_poses.exists():
        return None, f"{fused_poses} is missing: the map's frame cannot be checked"
    built = read_tum(fused_poses)
    stamps = np.asarray(stamps, np.float64)
    # Both are frame stamps; TUM text keeps them to the microsecond or better.
    j = match_nearest(stamps, built.stamps, 1e-3)  # [N]
    common = j >= 0  # [N]
    if common.sum() < 3:
        return None, (f"the map was built at other frames' poses ({fused_poses}: "
                      f"{int(common.sum())} frames in common with the export)")
    src, dst = built.poses[j[common]], np.asarray(poses, np.float64)[common]  # [C, 4, 4]
    if np.linalg.norm(src[:, :3, 3] - dst[:, :3, 3], axis=1).max() <= tol_m:
        return np.eye(4), ""
    R, t = rigid_alignment(src, dst)
    S = se3(R, t)
    moved = apply(S, src[:, :3, 3])  # [C, 3]
    rms = float(np.sqrt(np.mean(np.sum((moved - dst[:, :3, 3]) ** 2, axis=1))))
    if rms > max_rms_m:
        return None, (f"the map was built at other poses ({fused_poses}) that no rigid "
                      f"motion puts on the exported ones ({rms:.3f} m RMS left)")
    angle = float(np.degrees(rotation_angle(R)))
    return S, (f"built at other poses, moved by their rigid fit onto the exported ones: "
               f"{np.linalg.norm(t):.2f} m, {angle:.1f} deg, {rms * 1000:.1f} mm RMS left")


# ---------------------------------------------------------------------------- camera only


class CameraOnlyConfig(_ColmapKeys, AddedOptions):
    """Settings of the ``camera_only`` stage."""

    added_unused = {"reference_views": "geometry"}

    # Reuse an upstream colmap stage's SfM model (same frames) instead of running COLMAP again.
    reuse_colmap: bool = True
    scale_source: Literal["auto", "network", "sfm"] = "auto"
    estimator: Literal["ratio", "clustered", "robust"] = "robust"
    min_points: int = Field(15, ge=2)
    # Temporal smoothing of the per-frame scales, as fuse's keys of the same names, with
    # the same agreement test (a frame whose own SfM points back its fit keeps it). auto:
    # none for relative outputs, whose constant changes from image to image; median for
    # metric depth.
    smoothing: Literal["auto", "median", "none"] = "auto"
    smoothing_window: int = Field(9, ge=1)
    outlier_tol: float = Field(0.1, gt=0)  # log scale distance from the window median
    pixel_stride: int = Field(2, ge=1)
    voxel_fraction: float = Field(0.008, gt=0)
    eval_frames: int = Field(40, ge=1)  # frames compared with ground-truth depth
    # Ground-truth surface samples for the map comparison. Coarser than tsdf's 1 cm: the
    # camera-only map is off by decimetres, and its ~2M points make each comparison slow.
    eval_spacing_m: float = Field(0.015, gt=0)
    # The two map comparisons (own scale, Sim(3)) take most of this stage's time on a house
    # (~2.5 M points each); off leaves the map to the evaluate stage.
    geometry: bool = True
    reference_views: int = Field(1000, ge=1)  # as tsdf's
    eval_max_points: int = Field(400_000, ge=1000)  # map points scored (random subset)
    eval_max_depth_m: float = Field(10.0, gt=0)


def _warn_colmap_keys_unused(ctx: StageContext, cfg: CameraOnlyConfig) -> None:
    """Say which COLMAP keys set on a ``camera_only`` stage go unused: with the colmap
    stage's model reused, its frames (``every``, ``max_images``) and matching are the
    ones that count, and a user setting them here saw no effect and no word."""
    unused = sorted(set(_ColmapKeys.__annotations__) & cfg.model_fields_set)  # its own keys
    if unused:
        ctx.log.warning("%s: %s not used: the colmap stage's model is reused (its own "
                        "settings apply); set them there, or 'reuse_colmap: false' to run "
                        "COLMAP here with them", ctx.stage_id,
                        ", ".join(f"'{k}'" for k in unused))


class CameraOnlyStage(Stage):
    """The 'without lidar' rows: COLMAP poses and SfM-scaled depth, no lidar anywhere."""

    name = "camera_only"
    Config = CameraOnlyConfig
    requires = ("sequence", "depth")
    optional_requires = ("colmap", "trajectory")
    provides = ("camera_only",)
    # 2: recall against every map point; alignment on covered poses. 3: one thread by
    # default (repeatable); SfM points collapsed onto their camera left out. 4: the
    # observed reference keeps surface seen at grazing angles
    # 5: scored on the frames the ground truth covers, no end slack
    # 6: the scale smoothing's agreement test (a frame's own SfM points back its own fit)
    # and no smoothing for relative outputs: a per-image constant was overwritten by the
    # neighbours' (depth AbsRel 0.151 -> 0.0033); sfm mode's own-scale rows labelled as
    # COLMAP's unit, not a scale error
    # 7: SfM points nearer than 5 % of the model's median depth are not depth observations
    # (points triangulated while turning on the spot gave one frame 1 % of the true depth)
    # 8: a straight path's alignment turns about the reference's line, not the estimate's
    # 9: frames within the end slack outside the trajectory's span get its end pose even
    #    when a long gap follows that end (Trajectory.covers refused them)
    version = 9

    def run(self, ctx: StageContext) -> None:
        from toolkit.baselines.camera_only import CameraOnlySettings, camera_only_reconstruction
        from toolkit.baselines.colmap import load_sfm, run_sfm, save_sfm
        from toolkit.baselines.common import image_folder
        from toolkit.depth.store import DepthStore
        from toolkit.fusion.voxel_map import MapArrays, write_map_ply
        from toolkit.geometry import Trajectory
        from toolkit.io.tum import write_tum

        cfg: CameraOnlyConfig = self.config  # type: ignore[assignment]
        seq = _read_sequence(ctx)
        store = DepthStore(ctx.artifact("depth"))
        reused = database_kept = False
        sfm = None
        if cfg.reuse_colmap and ctx.has_artifact("colmap"):
            sfm_dir = ctx.artifact("colmap") / "sfm"
            if (sfm_dir / "frames.csv").exists():
                sfm, frame_of, stamp_of = load_sfm(sfm_dir)
                reused = True
                _warn_colmap_keys_unused(ctx, cfg)
        if sfm is None:
            sel = _select(np.arange(len(seq.frames)), cfg.every, cfg.max_images)
            image_dir, names, cam = image_folder(seq, sel, ctx.stage_dir)
            frame_of = {n: int(i) for n, i in zip(names, sel, strict=True)}
            stamp_of = {n: float(seq.frame_stamps[i]) for n, i in frame_of.items()}
            db = ctx.stage_dir / "database.db"
            seconds, database_kept = _matched_database(ctx, db, image_dir, names, cam,
                                                       cfg.colmap_settings())
            sfm = run_sfm(image_dir, names, cam, ctx.stage_dir / "work", cfg.colmap_settings(),
                          database=db)
            sfm.seconds.update(seconds)
            save_sfm(sfm, ctx.stage_dir / "sfm", frame_of, stamp_of, names)
        if sfm.registered < 3:
            raise StageError(f"{ctx.stage_id}: COLMAP registered {sfm.registered} of "
                             f"{sfm.images} images; the camera alone cannot build a map here")
        settings = CameraOnlySettings(cfg.scale_source, cfg.estimator, cfg.min_points,
                                      smoothing=cfg.smoothing,
                                      smoothing_window=cfg.smoothing_window,
                                      outlier_tol=cfg.outlier_tol,
                                      pixel_stride=cfg.pixel_stride,
                                      voxel_fraction=cfg.voxel_fraction)
        try:
            res = camera_only_reconstruction(
                sfm, frame_of, seq.rig.camera, store.read, lambda i: seq.frames[i].image,
                set(store.indices), settings,
                progress=lambda it: ctx.progress(list(it), description="camera only"))
        except ValueError as e:
            raise StageError(f"{ctx.stage_id}: {e}") from None
        stamps = seq.frame_stamps[res.frame_indices]
        est = Trajectory(stamps, res.poses, "model", "camera")
        write_tum(ctx.stage_dir / "trajectory_camera.tum", est,
                  f"camera-only (COLMAP) poses in {res.units} units, NOT metric world")
        n = len(res.points)
        if n == 0:
            raise StageError(
                f"{ctx.stage_id}: the camera-only map is empty ({res.info['frames_fitted']} of "
                f"{sfm.registered} registered frames had enough SfM points for a depth fit; "
                f"median SfM depth {res.info['median_sparse_depth']:.3g} model units): "
                "COLMAP's model is degenerate. Give it more images (every, max_images) or "
                "more matches (overlap, matching: exhaustive) and rerun from the colmap stage")
        write_map_ply(ctx.stage_dir / "map.ply", MapArrays(
            res.points, res.colors, np.ones(n, np.int64), np.ones(n, np.int32),
            np.zeros(n, np.int32), np.zeros(n, np.int32), np.zeros(n, np.float32)))
        ctx.provide("camera_only", ctx.stage_dir)
        metrics: dict[str, Any] = {
            "scale_source": res.scale_source, "units": res.units, "depth_kind": res.info["kind"],
            "colmap_reused": reused, "database_resumed": database_kept, "images": sfm.images,
            # The mapper that made the model, as the colmap stage's metrics: a reused model's
            # is the colmap stage's (None: saved before it was recorded), not this stage's key.
            "mapper": sfm.mapper,
            "registered_images": sfm.registered,
            "frames_fused": int(res.used.sum()), "frames_fitted": res.info["frames_fitted"],
            "scale_smoothing": res.info["smoothing"],
            # Frames that took a neighbour's scale instead of their own fit.
            "frames_flagged": int(sum(f != "ok" for f in res.flags)),
            "map_points": n,
        }
        rows: list[tuple[str, Any]] = [
            ("registered images", f"{sfm.registered} / {sfm.images}"),
            ("frames fused", int(res.used.sum())),
            ("frames with a neighbour's scale (smoothing: "
             f"{res.info['smoothing']})", metrics["frames_flagged"]),
            ("map points", n)]
        mapper = f"{sfm.mapper} mapping" if sfm.mapper else (
            "mapper not recorded: a model saved before 2026-11-28")
        reuse_note = f" ({mapper}, reused from the colmap stage)" if reused else f" ({mapper})"
        md = [f"Camera only (no lidar anywhere): COLMAP poses{reuse_note}, "
              f"`{res.info['kind']}` predictions scaled by "
              + ("COLMAP's sparse points per frame (map in COLMAP's arbitrary unit)"
                 if res.scale_source == "sfm" else
                 "the network's own metres (COLMAP model rescaled once to them)") + "."]
        ev = self._evaluate(ctx, seq, res, est, store, cfg)
        metrics.update(ev["metrics"])
        rows += ev["rows"]
        if res.scale_source == "network":
            md.append("Evaluated twice: aligned rigidly (SE(3)), keeping the network's metres - "
                      "the **scale error** of the depth network - and by similarity (Sim(3)), "
                      "which removes the scale and leaves the **shape error**.")
        else:
            # COLMAP's mapper normalises its model (the camera centres' 10-90 % spread to
            # 10 units): the same room gave 12.4x, 7.9x and 6.9x for arcs of 0.84, 1.39 and
            # 1.95 m at Sim(3) ATEs of 0.6-1.9 mm. The unit measures the drive, not the method.
            md.append("Evaluated twice: by similarity (Sim(3)), which removes the scale and "
                      "leaves the **shape error**, and rigidly (SE(3)) in **COLMAP's unit**: "
                      "the mapper normalises the camera path to about 10 units, so those rows "
                      "describe that convention against the drive's size, not a measured "
                      "scale error of the camera-only method.")
        md.append(_table(rows))
        if ev.get("png"):
            md.append(f"![camera only]({ctx.stage_id}/{ev['png']})")
        ctx.add_metrics(metrics)
        ctx.report("\n\n".join(md))
        _database_done(ctx)

    @staticmethod
    def _evaluate(ctx: StageContext, seq: Sequence, res: Any, est: Any, store: Any,
                  cfg: CameraOnlyConfig) -> dict[str, Any]:
        from toolkit.baselines.camera_only import (
            CameraOnlySettings,
            alignments,
            apply_similarity,
            depth_of,
        )
        from toolkit.baselines.colmap import evaluate_sfm_trajectory
        from toolkit.baselines.common import (
            groundtruth_camera_trajectory,
            load_camera_trajectory,
            poses_at_frames,
        )

        out: dict[str, Any] = {"metrics": {}, "rows": []}
        ref = groundtruth_camera_trajectory(seq)
        ref_name = "groundtruth"
        if ref is None and ctx.has_artifact("trajectory"):
            ref, ref_name = load_camera_trajectory(ctx.artifact("trajectory"), seq), "lidar"
        if ref is None:
            ctx.log.warning("camera_only: no ground truth and no lidar trajectory to compare to")
            return out
        m, rows = out["metrics"], out["rows"]
        try:
            te = evaluate_sfm_trajectory(est, ref)
        except ValueError as e:
            ctx.log.warning("camera_only: %s", e)
            return out
        m["reference"] = ref_name
        m["trajectory"] = te
        # In sfm mode the own scale is COLMAP's normalised unit (~10 units of camera path),
        # not an error the method makes: say so in every row that keeps it.
        own = "own scale" if res.scale_source == "network" else "COLMAP's unit"
        m["own_scale_is"] = "network_metres" if res.scale_source == "network" else "colmap_unit"
        rows += [(f"ATE vs {ref_name}, {own} (SE(3)) [m]", te["ate_se3_rmse_m"]),
                 (f"ATE vs {ref_name}, Sim(3) [m]", te["ate_sim3_rmse_m"]),
                 # As a size: "Sim(3) scale - 1" = -0.62 read as a map too small, for one
                 # 2.6x too large.
                 ("map size / the reference's (1 / Sim(3) scale)"
                  + ("" if res.scale_source == "network" else ", COLMAP's unit"),
                  1.0 / te["scale_to_reference"] if te["scale_to_reference"] else float("nan"))]
        # On the poses the ATE scores: inside the reference's span, not across its gaps.
        inside = ref.covers(est.stamps)
        ref_at = ref.interpolate(est.stamps[inside])
        al = alignments(est.poses[inside], ref_at.poses)
        for tag in ("se3", "sim3"):
            _write_aligned(ctx.stage_dir / f"trajectory_{tag}.tum", est, al[tag],
                           f"camera-only poses, {tag}-aligned to {ref_name}")
        from toolkit.io.atomic import atomic_write_json

        # The similarities map.ply needs to land in the world frame (x_world = S @ x_map).
        atomic_write_json(ctx.stage_dir / "alignment.json",
                          {"reference": ref_name, **{t: al[t].tolist() for t in al}})
        clouds = {}
        gt_traj = groundtruth_camera_trajectory(seq)
        s_sim = float(np.cbrt(np.linalg.det(al["sim3"][:3, :3])))  # metres per result unit
        if gt_traj is not None and cfg.geometry:
            # The same depth range the reconstruction kept, in metres, so completeness is
            # measured over what it could have seen.
            max_depth_m = CameraOnlySettings().max_depth_factor * res.info[
                "median_sparse_depth"] * s_sim
            mr = _mesh_reference(seq, poses_at_frames(gt_traj, seq)[1], max_depth_m,
                                 cfg.eval_spacing_m, cfg.reference_views)
            if mr is not None:
                from toolkit.eval.geometry import geometry_metrics, mesh_distances

                # A random subset, as evaluate scores maps: the statistics settle long
                # before the ~2.5 M points of a house.
                rng = np.random.default_rng(cfg.seed)
                sub = (rng.choice(len(res.points), cfg.eval_max_points, replace=False)
                       if len(res.points) > cfg.eval_max_points else slice(None))
                for tag in ("se3", "sim3"):
                    pts = apply_similarity(al[tag], res.points)
                    clouds[tag] = pts
                    g = geometry_metrics(pts[sub], mr[1],
                                         accuracy_distances=mesh_distances(pts[sub], mr[0]),
                                         complete_points=pts)  # recall sees every point
                    m[f"geometry_{'own_scale' if tag == 'se3' else 'sim3'}"] = g
                    rows += _geometry_rows(f"{own}:" if tag == "se3" else "Sim(3):", g)
                clouds["gt"] = mr[1]
        gt = seq.groundtruth
        if gt is not None and gt.depth_paths is not None:
            from toolkit.eval.depth import ErrorAccumulator

            accs = {"own_scale": ErrorAccumulator(), "sim3": ErrorAccumulator()}
            ks = np.unique(np.linspace(0, len(res.frame_indices) - 1,
                                       min(cfg.eval_frames, len(res.frame_indices))).astype(int))
            for k in ks:
                if not res.used[k]:
                    continue
                i = res.frame_indices[k]
                d = depth_of(res, int(k), store.read(i))
                g = gt.depth(i)
                accs["own_scale"].add(d, g, max_depth=cfg.eval_max_depth_m)
                accs["sim3"].add(d * s_sim, g, max_depth=cfg.eval_max_depth_m)
            for tag, acc in accs.items():
                r = acc.result()
                m[f"depth_{tag}"] = r.as_dict()
                rows.append((f"depth vs GT, {own if tag == 'own_scale' else 'Sim(3)'}: "
                             "RMSE [m] / AbsRel",
                             f"{r.rmse_m:.3f} / {r.absrel:.3f}"))
        if clouds:
            out["png"] = "camera_only.png"
            _camera_only_figure(ctx.stage_dir / out["png"], clouds, ref_at.positions,
                                {t: apply_similarity(al[t], est.positions[inside])
                                 for t in ("se3", "sim3")})
        return out


def _link_or_copy(src: Path, dst: Path) -> None:
    """Hard-link ``src`` to ``dst`` (images are never modified, and a 600-frame export
    would otherwise double the disk use), copying across filesystems."""
    import os
    import shutil

    dst.unlink(missing_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def _write_aligned(path: Path, est: Any, S: np.ndarray, header: str) -> None:
    """A trajectory moved into the reference frame by similarity ``S`` (T_world_camera)."""
    from toolkit.baselines.camera_only import pose_in_reference
    from toolkit.geometry import Trajectory
    from toolkit.io.tum import write_tum

    poses = np.stack([pose_in_reference(S, T) for T in est.poses])
    write_tum(path, Trajectory(est.stamps, poses, "world", "camera"), header)


def _camera_only_figure(path: Path, clouds: dict[str, np.ndarray], ref_xyz: np.ndarray,
                        est_xyz: dict[str, np.ndarray]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from toolkit.baselines.common import save_figure

    def thin(p: np.ndarray, n: int = 40000) -> np.ndarray:
        return p[:: len(p) // n + 1]

    fig, axes = plt.subplots(1, 2, figsize=(11, 5))
    for ax, tag, title in ((axes[0], "se3", "own scale (SE(3)): scale error"),
                           (axes[1], "sim3", "Sim(3): shape error")):
        g = thin(clouds["gt"])
        ax.scatter(g[:, 0], g[:, 1], s=0.2, color="0.7", label="GT surface seen", rasterized=True)
        p = thin(clouds[tag])
        ax.scatter(p[:, 0], p[:, 1], s=0.2, color="C1", alpha=0.5, label="camera-only map",
                   rasterized=True)
        ax.plot(ref_xyz[:, 0], ref_xyz[:, 1], "-", color="C0", lw=1.4, label="reference path")
        ax.plot(est_xyz[tag][:, 0], est_xyz[tag][:, 1], "--", color="C3", lw=1.4,
                label="camera-only path")
        ax.set_title(title)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
        ax.set_xlabel("x [m]")
    axes[0].set_ylabel("y [m]")
    axes[0].legend(loc="best", fontsize=8, markerscale=20)
    fig.tight_layout()
    save_figure(fig, path)

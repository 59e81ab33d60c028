"""COLMAP baseline through pycolmap (CPU): structure from motion on the images alone, and
triangulation at our poses as a cross-check of poses and intrinsics.

- ``run_sfm``: SIFT extraction, sequential or exhaustive matching, incremental (or global)
  mapping. The model's frame and scale are arbitrary (monocular); ``evaluate_sfm_trajectory``
  aligns it to a reference by Sim(3) and reports the ATE both after that alignment (shape)
  and after a rigid SE(3) one that keeps COLMAP's own scale (what a monocular system gets wrong).
- ``triangulate_known_poses``: the same features and matches, but the poses are ours and
  fixed (``pycolmap.triangulate_points``): if our poses or intrinsics are off, the tracks do
  not close and the reprojection error grows, without any ground truth.

The pycolmap calls are the ones measured to work on these machines
(shared/notes/dependencies-measured.md, section 3).
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

from toolkit.camera import PinholeCamera
from toolkit.errors import MissingInputError
from toolkit.geometry import Trajectory
from toolkit.io.colmap_text import (
    camera_from_colmap,
    camera_to_colmap,
    model_from_poses,
    write_colmap_model,
)

Matching = Literal["sequential", "exhaustive"]
Intrinsics = Literal["known", "refine", "unknown"]
Mapper = Literal["incremental", "global"]


@dataclass(frozen=True)
class ColmapSettings:
    """Feature, matching and mapping settings (COLMAP's defaults where not stated)."""

    matching: Matching = "sequential"
    # Sequential matching pairs each image with the next ``overlap`` ones (and, quadratic,
    # with 2^k further ones), which covers a robot's slow forward motion cheaply.
    overlap: int = 10
    max_features: int = 4096
    # known: our K, held fixed; refine: start from our K, bundle adjustment refines it;
    # unknown: COLMAP guesses a SIMPLE_RADIAL camera from the image size (camera-only runs
    # without calibration).
    intrinsics: Intrinsics = "known"
    # One thread makes a run repeatable: with two, the same images gave another model from
    # run to run (the paper benchmark's 161 images: 38 or 39 registered, ARE 9.5 or 76.6
    # deg), with one the same model every time (ARE 9.67 deg), the whole SfM taking 48-50 s
    # instead of 35-39 s (the colmap stage with its triangulation: 47 s instead of 31 s).
    num_threads: int = 1
    seed: int = 0
    quiet: bool = True
    # incremental: pycolmap.incremental_mapping (image by image from a seed pair); global:
    # pycolmap.global_mapping (COLMAP 4's GLOMAP: rotation averaging, then all positions at
    # once), on the same features and matches.
    mapper: Mapper = "incremental"


@dataclass
class SfMResult:
    """The largest model of the mapping and its summary figures."""

    reconstruction: Any | None  # pycolmap.Reconstruction
    names: list[str]  # registered image names, in input order
    poses: np.ndarray  # [R, 4, 4] T_model_camera of the registered images
    camera: PinholeCamera | None  # as estimated (principal point in pixel-centre origin)
    images: int  # images given
    models: int  # separate models COLMAP made (1 is a connected reconstruction)
    points: int
    reprojection_error_px: float
    mean_track_length: float
    seconds: dict[str, float] = field(default_factory=dict)
    # "incremental" / "global"; None: a model saved before save_sfm recorded it (2026-11-28)
    mapper: str | None = None

    @property
    def registered(self) -> int:
        return len(self.names)

    def trajectory(self, stamps_by_name: dict[str, float]) -> Trajectory:
        """Registered poses as a time-sorted ``Trajectory`` (frame "colmap", child "camera")."""
        st = np.array([stamps_by_name[n] for n in self.names], dtype=np.float64)
        order = np.argsort(st)
        return Trajectory(st[order], self.poses[order], "colmap", "camera")

    def points_xyz_rgb(self) -> tuple[np.ndarray, np.ndarray]:
        """Sparse points [P, 3] in the model frame and their colours [P, 3] uint8."""
        if self.reconstruction is None or self.points == 0:
            return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
        pts = self.reconstruction.points3D
        xyz = np.array([p.xyz for p in pts.values()], dtype=np.float64)
        rgb = np.array([p.color for p in pts.values()], dtype=np.uint8)
        return xyz, rgb

    def summary(self) -> dict[str, float | int]:
        return {
            "images": self.images,
            "registered_images": self.registered,
            "registered_fraction": self.registered / max(self.images, 1),
            "models": self.models,
            "points": self.points,
            "reprojection_error_px": self.reprojection_error_px,
            "mean_track_length": self.mean_track_length,
            **{f"{k}_s": v for k, v in self.seconds.items()},
        }


@dataclass
class TriangulationResult:
    """Points triangulated at fixed (our) poses, and how well they reproject."""

    reconstruction: Any  # pycolmap.Reconstruction
    points: int
    reprojection_error_px: float
    mean_track_length: float
    observations: int
    seconds: float

    def points_xyz(self) -> np.ndarray:
        """[P, 3] triangulated points in our world frame."""
        pts = self.reconstruction.points3D
        return np.array([p.xyz for p in pts.values()], dtype=np.float64).reshape(-1, 3)

    def summary(self) -> dict[str, float | int]:
        return {
            "points": self.points,
            "reprojection_error_px": self.reprojection_error_px,
            "mean_track_length": self.mean_track_length,
            "observations": self.observations,
            "seconds": self.seconds,
        }


# ---------------------------------------------------------------------------- helpers


def _pycolmap() -> Any:
    import pycolmap

    return pycolmap


def _quiet(quiet: bool) -> None:
    # glog prints every registration step to stderr; a stage log wants warnings only.
    pycolmap = _pycolmap()
    pycolmap.logging.minloglevel = 2 if quiet else 0


def cam_from_world_matrix(image: Any) -> np.ndarray:
    """[4, 4] world -> camera of a pycolmap Image (a property in some versions, a method in
    others, as gsplat's parser notes)."""
    cfw = image.cam_from_world
    if callable(cfw):
        cfw = cfw()
    T = np.eye(4)
    T[:3, :] = np.asarray(cfw.matrix(), dtype=np.float64)
    return T


def _reader_options(camera: PinholeCamera | None, intrinsics: Intrinsics) -> Any:
    pycolmap = _pycolmap()
    if intrinsics == "unknown" or camera is None:
        return pycolmap.ImageReaderOptions(camera_model="SIMPLE_RADIAL")
    model, params = camera_to_colmap(camera)
    return pycolmap.ImageReaderOptions(camera_model=model,
                                       camera_params=",".join(repr(p) for p in params))


def extract_and_match(
    database: Path,
    image_dir: Path,
    names: Sequence[str],
    camera: PinholeCamera | None,
    settings: ColmapSettings,
) -> dict[str, float]:
    """SIFT features of ``names`` (one shared camera) and verified matches into ``database``.

    Returns the seconds each step took. An existing database is replaced: features of a
    previous run with other settings must not leak into this one.
    """
    pycolmap = _pycolmap()
    _quiet(settings.quiet)
    database = Path(database)
    database.unlink(missing_ok=True)
    database.parent.mkdir(parents=True, exist_ok=True)
    ext = pycolmap.FeatureExtractionOptions()
    ext.sift.max_num_features = settings.max_features
    ext.num_threads = settings.num_threads
    t0 = time.perf_counter()
    pycolmap.extract_features(
        database, image_dir, image_names=list(names), camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=_reader_options(camera, settings.intrinsics), extraction_options=ext,
        device=pycolmap.Device.cpu)
    t1 = time.perf_counter()
    match = pycolmap.FeatureMatchingOptions()
    match.num_threads = settings.num_threads
    if settings.matching == "sequential":
        pairing = pycolmap.SequentialPairingOptions(overlap=settings.overlap,
                                                    loop_detection=False)
        pycolmap.match_sequential(database, matching_options=match, pairing_options=pairing,
                                  device=pycolmap.Device.cpu)
    elif settings.matching == "exhaustive":
        pycolmap.match_exhaustive(database, matching_options=match, device=pycolmap.Device.cpu)
    else:
        raise ValueError(f"matching must be sequential or exhaustive, got {settings.matching!r}")
    t2 = time.perf_counter()
    return {"extract": t1 - t0, "match": t2 - t1}


def _mapper_options(settings: ColmapSettings) -> Any:
    pycolmap = _pycolmap()
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = settings.num_threads
    opts.random_seed = settings.seed
    opts.mapper.random_seed = settings.seed
    opts.triangulation.random_seed = settings.seed
    fixed = settings.intrinsics == "known"
    opts.ba_refine_focal_length = not fixed
    opts.ba_refine_principal_point = False  # poorly observable; COLMAP's default too
    opts.ba_refine_extra_params = not fixed
    opts.mapper.abs_pose_refine_focal_length = not fixed
    opts.mapper.abs_pose_refine_extra_params = not fixed
    return opts


def _global_options(settings: ColmapSettings) -> Any:
    pycolmap = _pycolmap()
    opts = pycolmap.GlobalPipelineOptions()
    m = opts.mapper
    opts.num_threads = m.num_threads = settings.num_threads
    # Its default seed (-1) is the clock: another model from run to run.
    opts.random_seed = m.random_seed = settings.seed
    m.rotation_averaging.random_seed = settings.seed
    m.global_positioning.random_seed = settings.seed
    m.retriangulation.random_seed = settings.seed
    # CPU only, as the rest of this module (a CUDA build would otherwise pick the GPU
    # solvers above their image counts, and another solver is another model).
    m.global_positioning.use_gpu = False
    m.bundle_adjustment.ceres.use_gpu = False
    # Its bundle adjustment refines focal length and distortion by default; "known" holds
    # our K fixed, as the incremental mapper's options do.
    fixed = settings.intrinsics == "known"
    m.bundle_adjustment.refine_focal_length = not fixed
    m.bundle_adjustment.refine_principal_point = False
    m.bundle_adjustment.refine_extra_params = not fixed
    return opts


def _stats(rec: Any) -> tuple[int, float, float]:
    n = int(rec.num_points3D())
    if n == 0:
        return 0, float("nan"), 0.0
    return n, float(rec.compute_mean_reprojection_error()), float(rec.compute_mean_track_length())


# ---------------------------------------------------------------------------- SfM


def run_sfm(
    image_dir: Path | str,
    names: Sequence[str],
    camera: PinholeCamera | None,
    work_dir: Path | str,
    settings: ColmapSettings | None = None,
    database: Path | None = None,
) -> SfMResult:
    """SfM on ``names`` (paths relative to ``image_dir``), CPU only, with the mapper
    ``settings.mapper`` names (incremental or global).

    ``camera`` must be distortion-free when ``intrinsics`` is "known" (undistort the images
    first); with "unknown" it is ignored. Pass ``database`` to reuse features and matches
    from ``extract_and_match``; otherwise they are computed into ``work_dir``. The model is
    written (binary) to ``work_dir/sparse``.
    """
    pycolmap = _pycolmap()
    settings = settings or ColmapSettings()
    if settings.mapper not in ("incremental", "global"):
        # Before any work: minutes of feature extraction, then a typo.
        raise ValueError(f"mapper must be incremental or global, got {settings.mapper!r}")
    _quiet(settings.quiet)
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    if camera is not None and camera.has_distortion and settings.intrinsics != "unknown":
        raise ValueError("run_sfm with known intrinsics needs undistorted images and camera")
    pycolmap.set_random_seed(settings.seed)
    seconds: dict[str, float] = {}
    if database is None:
        database = work_dir / "database.db"
        seconds.update(extract_and_match(database, Path(image_dir), names, camera, settings))
    out = work_dir / "sparse"
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    t0 = time.perf_counter()
    if settings.mapper == "incremental":
        models = pycolmap.incremental_mapping(database, Path(image_dir), out,
                                              options=_mapper_options(settings))
    else:
        models = pycolmap.global_mapping(database, Path(image_dir), out,
                                         options=_global_options(settings))
    seconds["mapping"] = time.perf_counter() - t0
    if not models:
        return SfMResult(None, [], np.zeros((0, 4, 4)), None, len(names), 0, 0, float("nan"),
                         0.0, seconds, settings.mapper)
    rec = max(models.values(), key=lambda r: r.num_reg_images())
    order = {n: i for i, n in enumerate(names)}
    reg = sorted((rec.images[i] for i in rec.reg_image_ids()),
                 key=lambda im: order.get(im.name, len(order)))
    poses = np.stack([np.linalg.inv(cam_from_world_matrix(im)) for im in reg]) if reg else (
        np.zeros((0, 4, 4)))
    cam = rec.cameras[reg[0].camera_id] if reg else None
    est_cam = camera_from_colmap(cam.model.name, cam.width, cam.height, cam.params) if (
        cam is not None) else None
    n, err, track = _stats(rec)
    return SfMResult(rec, [im.name for im in reg], poses, est_cam, len(names), len(models), n,
                     err, track, seconds, settings.mapper)


def evaluate_sfm_trajectory(est: Trajectory, ref: Trajectory) -> dict[str, Any]:
    """ATE of an SfM trajectory against ``ref`` (poses of the same stamps or interpolable).

    ``ate_sim3_*``: after Umeyama Sim(3) (the shape of the path); ``ate_se3_*``: after a
    rigid alignment that keeps the model's own arbitrary scale; ``scale_to_reference``: the
    factor Sim(3) applied (metres per model unit).
    """
    from toolkit.eval.trajectory import trajectory_report

    inside = ref.covers(est.stamps)  # in its span and not across a gap of it
    if inside.sum() < 3:
        raise ValueError(f"only {int(inside.sum())} SfM poses lie inside the reference span")
    est = est.slice(inside)
    ref_at = ref.interpolate(est.stamps)
    sim = trajectory_report(est, ref_at, "sim3", max_diff=1e-6)
    se3 = trajectory_report(est, ref_at, "se3", max_diff=1e-6)
    from toolkit.geometry import umeyama_alignment

    _, _, s = umeyama_alignment(est.positions, ref_at.positions, with_scale=True)
    out: dict[str, Any] = {"poses_compared": int(len(est)), "scale_to_reference": float(s)}
    for tag, rep in (("sim3", sim), ("se3", se3)):
        out[f"ate_{tag}_rmse_m"] = rep["ate_rmse_m"]
        out[f"ate_{tag}_max_m"] = rep["ate_max_m"]
        out[f"are_{tag}_rmse_deg"] = rep["are_rmse_deg"]
    return out


# ---------------------------------------------------------------------------- fixed poses


def database_image_ids(database: Path) -> dict[str, tuple[int, int]]:
    """Image name -> (image_id, camera_id) as stored in a COLMAP database."""
    pycolmap = _pycolmap()
    with pycolmap.Database.open(Path(database)) as db:
        return {im.name: (int(im.image_id), int(im.camera_id)) for im in db.read_all_images()}


def triangulate_known_poses(
    image_dir: Path | str,
    names: Sequence[str],
    camera: PinholeCamera,
    T_world_camera: np.ndarray,
    work_dir: Path | str,
    settings: ColmapSettings | None = None,
    database: Path | None = None,
    refine_intrinsics: bool = False,
) -> TriangulationResult:
    """Triangulate SIFT tracks with our poses [N, 4, 4] and intrinsics held fixed.

    The reconstruction handed to ``pycolmap.triangulate_points`` is our own COLMAP text
    model (``toolkit.io.colmap_text``), with image and camera ids taken from the database so
    that COLMAP pairs each pose with the right features. Only points are optimised (poses
    stay constant in the bundle adjustment COLMAP's point triangulator runs).
    """
    pycolmap = _pycolmap()
    settings = settings or ColmapSettings(intrinsics="known")
    _quiet(settings.quiet)
    if camera.has_distortion:
        raise ValueError("triangulate_known_poses needs undistorted images and camera")
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    if database is None:
        database = work_dir / "database.db"
        extract_and_match(database, Path(image_dir), names, camera,
                          replace(settings, intrinsics="known"))
    ids = database_image_ids(database)
    missing = [n for n in names if n not in ids]
    if missing:
        raise ValueError(f"{len(missing)} images are not in the database, e.g. {missing[0]}")
    cam_ids = {ids[n][1] for n in names}
    if len(cam_ids) != 1:
        raise ValueError(f"the images use {len(cam_ids)} database cameras; one is expected")
    model = model_from_poses(camera, list(names), T_world_camera,
                             image_ids=[ids[n][0] for n in names], camera_id=cam_ids.pop())
    poses_dir = work_dir / "poses_model"
    write_colmap_model(poses_dir, model)
    rec = pycolmap.Reconstruction(poses_dir)
    out = work_dir / "triangulated"
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    pycolmap.set_random_seed(settings.seed)
    t0 = time.perf_counter()
    rec = pycolmap.triangulate_points(rec, database, Path(image_dir), out, clear_points=True,
                                      options=_mapper_options(settings),
                                      refine_intrinsics=refine_intrinsics)
    seconds = time.perf_counter() - t0
    n, err, track = _stats(rec)
    return TriangulationResult(rec, n, err, track, int(rec.compute_num_observations()), seconds)


# ---------------------------------------------------------------------------- on disk


def save_sfm(result: SfMResult, folder: Path | str, frame_of_name: dict[str, int],
             stamp_of_name: dict[str, float], all_names: Sequence[str]) -> Path:
    """Write the model as COLMAP text plus ``frames.csv`` (name, frame index, stamp,
    registered) and ``summary.json`` (with the mapper that made it), so later stages can
    reuse it without rerunning."""
    import json

    from toolkit.io.atomic import atomic_write_text

    folder = Path(folder)
    model_dir = folder / "model"
    if model_dir.exists():
        shutil.rmtree(model_dir)
    model_dir.mkdir(parents=True)
    if result.reconstruction is not None:
        result.reconstruction.write_text(model_dir)
    reg = set(result.names)
    rows = ["name,index,stamp,registered"] + [
        f"{n},{frame_of_name[n]},{stamp_of_name[n]!r},{int(n in reg)}" for n in all_names]
    atomic_write_text(folder / "frames.csv", "\n".join(rows) + "\n")
    summary = {**result.summary(), "camera": result.camera.to_dict() if result.camera else None,
               "mapper": result.mapper}
    atomic_write_text(folder / "summary.json", json.dumps(summary, indent=2) + "\n")
    return folder


def load_sfm(folder: Path | str) -> tuple[SfMResult, dict[str, int], dict[str, float]]:
    """Read what ``save_sfm`` wrote: the result, frame index and stamp per image name."""
    import csv
    import json

    pycolmap = _pycolmap()
    folder = Path(folder)
    if not (folder / "frames.csv").exists():
        raise MissingInputError(f"{folder}: no frames.csv; not a folder written by save_sfm")
    with (folder / "frames.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    frame_of = {r["name"]: int(r["index"]) for r in rows}
    stamp_of = {r["name"]: float(r["stamp"]) for r in rows}
    summary = json.loads((folder / "summary.json").read_text())
    mapper = summary.get("mapper")  # absent: saved before it was recorded
    model_dir = folder / "model"
    if not (model_dir / "images.txt").exists():
        return SfMResult(None, [], np.zeros((0, 4, 4)), None, len(rows), 0, 0, float("nan"),
                         0.0, mapper=mapper), frame_of, stamp_of
    rec = pycolmap.Reconstruction(model_dir)
    reg = sorted((rec.images[i] for i in rec.reg_image_ids()),
                 key=lambda im: frame_of.get(im.name, 1 << 62))
    poses = np.stack([np.linalg.inv(cam_from_world_matrix(im)) for im in reg])
    cam = rec.cameras[reg[0].camera_id]
    n, err, track = _stats(rec)
    res = SfMResult(rec, [im.name for im in reg], poses,
                    camera_from_colmap(cam.model.name, cam.width, cam.height, cam.params),
                    int(summary.get("images", len(rows))), int(summary.get("models", 1)), n, err,
                    track, {k[:-2]: v for k, v in summary.items() if k.endswith("_s")}, mapper)
    return res, frame_of, stamp_of

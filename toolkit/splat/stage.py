"""Recipe stage ``splat``: Gaussians initialised from the fused map, optimised at fixed poses.

```yaml
- stage: splat
  iterations: 1500        # training steps (one view each)
  downscale: 4            # train and evaluate at 1/4 of the camera resolution
  depth_weight: 0.1       # L1 depth term against the lidar-scaled depth (E_geo)
  max_seconds: 220        # stop training early on a slow machine (null: never)
```

Inputs: ``sequence`` (images, rig, ground truth); ``fused`` (``map.ply`` and per-frame
scaled depth in ``scaled_depth/`` or ``depth/``), needed for ``init: fused`` and for the
depth term; optionally ``trajectory`` (slam2d: a TUM file of camera or base poses) and
``tsdf_mesh`` (the tsdf stage's coloured mesh, rendered at the same held-out views for a
side-by-side PSNR). Without a trajectory the ground-truth poses of the sequence are used,
and the report says so in bold.

Writes into its folder (the ``splats`` artifact is ``splats.ply``):

    splats.ply            standard 3DGS PLY (opens in 3DGS viewers and Open3D)
    renders.png           real | rendered | rendered depth, for a few held-out views
    renders/path_*.png    every held-out frame along the driven path, rendered
    renders/offpath_*.png every simulator held-out view (off the path), rendered
    splat_vs_tsdf.png     real | splats | TSDF mesh, for the views of renders.png (with tsdf_mesh)
    train_history.json    loss / PSNR every log_every steps
    checkpoints/          training checkpoint (resume after an interruption)

Held-out evaluation: every ``holdout_every``-th used frame is left out of training (the
Mip-NeRF 360 convention), and the simulator's held-out views when the sequence has them;
PSNR and SSIM on both, and depth error against ground-truth depth where it exists.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Literal

import cv2
import numpy as np
import torch
from pydantic import Field, model_validator

from toolkit.camera import PinholeCamera
from toolkit.errors import WriteError
from toolkit.fusion.exposure import (
    EXPOSURE_FILE,
    corrected_image,
    gains_for_frames,
    gains_from_neighbours,
)
from toolkit.geometry import Trajectory, inv_se3, rigid_alignment
from toolkit.heldout import camera_trajectory, heldout_split
from toolkit.io.atomic import atomic_path, atomic_write_json
from toolkit.recipe.stage import Stage, StageConfig, StageContext, StageError
from toolkit.recipe.timing import usable_cpus
from toolkit.sensors import Sequence, load_rgb
from toolkit.splat.export import write_ply
from toolkit.splat.mesh_compare import Comparison, MeshViewRenderer
from toolkit.splat.model import init_from_points, init_random_in_views
from toolkit.splat.rasterize import RenderOutput, resolve_backend
from toolkit.splat.trainer import (
    TrainConfig,
    Trainer,
    TrainView,
    evaluate_views,
    gaussian_cap,
)
from toolkit.splat.views import LazyList, ViewSet


class SplatConfig(TrainConfig, StageConfig):
    """Settings of the ``splat`` stage: training (``TrainConfig``) plus data handling."""

    downscale: int = Field(4, ge=1, description="image size divisor for training")
    frame_stride: int = Field(1, ge=1, description="use every n-th frame")
    holdout_every: int = Field(8, ge=0, description="hold out every n-th used frame (0: none)")
    # A recording whose views fit is read once, up front; a longer one is read from disk as
    # training asks for views (the next one while a step trains), holding this much. Same
    # results either way.
    view_cache_mb: float = Field(2048.0, gt=0, description="memory for training views (MB)")
    # At the quickstart's 160x120, 40k initial Gaussians trained to a higher held-out PSNR
    # within the time limit than 100k (more steps; densification adds where needed).
    init_budget: int = Field(40_000, ge=1, description="at most this many initial Gaussians")
    init_opacity: float = Field(0.1, gt=0, lt=1)
    # fused: one Gaussian per point of the fuse stage's map (the method). random: Gaussians
    # on random rays of the training cameras at random depths, grey, no map needed (the
    # paper's "MonoGS with lidar" row: lidar poses, no lidar-scaled cloud; pair it with
    # depth_weight: 0 so that nothing from the depth network enters).
    init: Literal["fused", "random"] = "fused"
    random_depth_m: tuple[float, float] = Field((0.3, 5.0), description="z range for init: "
                                                "random (metres)")
    # Render the upstream tsdf stage's mesh at the same held-out views and report its PSNR
    # beside the splats' (only when a tsdf stage runs before this one).
    compare_tsdf: bool = True
    poses: Literal["auto", "trajectory", "groundtruth"] = "auto"
    strip_views: int = Field(4, ge=0, description="held-out views in renders.png")
    # Torch threads. "auto": torch's default, except 1 on a machine of two cores or fewer
    # (8-13 % faster there, idle) and when the machine is already fully loaded: on a shared
    # 2-core machine PyTorch with 2 OpenMP threads ran 10x slower in wall time than with 1
    # once other processes kept both cores busy (docs/splatting.md). The compositing
    # kernels keep all cores either way (one parallel loop per pass).
    threads: Annotated[int, Field(ge=1)] | Literal["auto"] = "auto"
    # Where the model trains. cuda: on the GPU, rendered by gsplat (the `cuda` extra); auto:
    # cuda where torch sees a GPU and gsplat's kernels load, else the CPU. Views stay in CPU
    # memory and each step's moves to the GPU (docs/splatting.md, "On a GPU").
    device: Literal["auto", "cpu", "cuda"] = "auto"
    # A safety net for the quickstart's 4-minute budget on slow machines; benchmark recipes
    # set it to null.
    max_seconds: float | None = Field(220.0, gt=0)

    @model_validator(mode="after")
    def _runnable(self) -> SplatConfig:
        # Checked with the recipe (`validate`), not after the upstream stages have run.
        lo, hi = self.random_depth_m
        if not 0 < lo < hi:
            raise ValueError(f"random_depth_m {list(self.random_depth_m)}: give [near, far] "
                             "in metres, 0 < near < far")
        if self.backend == "gsplat" and self.device == "cpu":
            raise ValueError("backend gsplat renders CUDA tensors: set device: cuda (or auto), "
                             "or backend auto for the CPU")
        if self.backend in ("cpp", "torch") and self.device == "cuda":
            raise ValueError(f"backend {self.backend} is a CPU rasteriser: with device: cuda "
                             "use backend auto or gsplat")
        return self


def choose_device(setting: str, backend: str = "auto") -> torch.device:
    """The device the ``splat`` stage trains on for its ``device`` setting."""
    if setting == "cpu" or (setting == "auto" and backend in ("cpp", "torch")):
        return torch.device("cpu")
    from toolkit.splat.rasterize import gsplat_backend

    if gsplat_backend.available():
        return torch.device("cuda")
    if setting == "cuda" or backend == "gsplat":
        raise StageError(f"splat: device {setting}, backend {backend}: "
                         f"{gsplat_backend.unavailable_reason()}: "
                         f"{gsplat_backend.unavailable_fix()}; or set splat.device: cpu"
                         + (" and splat.backend: auto" if backend == "gsplat" else ""))
    return torch.device("cpu")


def choose_threads(setting: int | str) -> int:
    """Torch threads for training: ``setting``, or for "auto" the default, except 1 on a
    machine of two cores or fewer, or when the 1-minute load average says every core is
    already busy.

    Two cores: torch's OpenMP threads spin at the end of its small parallel regions while
    the compositing kernels want both cores; one torch thread trained the quickstart's
    splats 8-13 % faster on the idle 2-core machine (docs/splatting.md, "Threads on a busy
    machine"), and its figures no longer depend on the load the recipe's own earlier
    stages left in the load average (which tipped it between 1 and 2)."""
    if setting != "auto":
        return int(setting)
    default = torch.get_num_threads()
    if default <= 1:
        return default
    cores = usable_cpus()
    if cores <= 2:
        return 1
    try:
        load = os.getloadavg()[0]
    except (AttributeError, OSError):
        return default
    return 1 if load >= cores else default


# ------------------------------------------------------------------------ inputs
def camera_poses(seq: Sequence, ctx: StageContext, cfg: SplatConfig) -> tuple[Trajectory, str]:
    """T_world_camera at the frame stamps, and where it came from (``camera_trajectory``,
    which the fuse stage's ``holdout_every`` asks too)."""
    trajectory = Path(ctx.artifact("trajectory")) if ctx.has_artifact("trajectory") else None
    return camera_trajectory(seq, trajectory, cfg.poses)


def groundtruth_to_trajectory_frame(seq: Sequence, poses: Trajectory) -> (
        tuple[np.ndarray, float] | None):
    """T_traj_gt [4, 4] mapping the ground-truth world into the trajectory's world, and the
    RMS residual (m) of the camera positions after alignment; None without ground truth.

    SLAM puts its map origin at the first pose, the simulator elsewhere (1.4 m apart on the
    small house), so the simulator's held-out views (ground-truth poses) must be moved into
    the frame the splats were trained in: an SE(3) Umeyama fit of the ground-truth camera
    positions to the trajectory's at the same stamps, as is usual for evaluating novel views
    with estimated poses. Planar paths are fine (unique when the points are not collinear).
    """
    gt = seq.groundtruth
    if gt is None or gt.poses_base is None:
        return None
    gt_cam = gt.poses_base.transform(T_right=seq.rig.T_base_camera)
    st = poses.stamps
    inside = (st >= gt_cam.stamps[0] - 1e-6) & (st <= gt_cam.stamps[-1] + 1e-6)
    if inside.sum() < 3:
        return None
    gt_poses = gt_cam.interpolate(st[inside], extrapolate_s=1e-6).poses  # [N, 4, 4]
    src = gt_poses[:, :3, 3]
    dst = poses.poses[inside, :3, 3]
    R, t = rigid_alignment(gt_poses, poses.poses[inside])
    rmse = float(np.sqrt(np.mean(np.sum((src @ R.T + t - dst) ** 2, axis=1))))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T, rmse


def find_depth_dir(fused: Path) -> Path | None:
    for name in ("depth", "scaled_depth"):
        if (fused / name).is_dir():
            return fused / name
    return None


def depth_file(depth_dir: Path | None, index: int) -> Path | None:
    if depth_dir is None:
        return None
    for ext in (".npy", ".png"):
        p = depth_dir / f"{index:06d}{ext}"
        if p.exists():
            return p
    return None


def prepare_image(img: np.ndarray, camera: PinholeCamera, size: tuple[int, int]) -> np.ndarray:
    """Undistort (if needed) then area-resize an RGB image to ``size`` (w, h)."""
    img = camera.undistort_image(img)
    if (img.shape[1], img.shape[0]) != size:
        img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
    return img


def image_validity(camera: PinholeCamera, size: tuple[int, int]) -> torch.Tensor | None:
    """[h, w] bool: training pixels whose whole area lies inside the image after
    ``prepare_image`` (undistorting a pincushion lens leaves corners without a source);
    None when every pixel does."""
    if not camera.has_distortion:
        return None
    ones = np.full((camera.height, camera.width), 255, np.uint8)
    m = prepare_image(np.dstack([ones] * 3), camera, size)[..., 0]
    valid = m >= 254  # any black source pixel in the area average
    return None if valid.all() else torch.from_numpy(valid)


def prepare_depth(depth: np.ndarray, camera: PinholeCamera, size: tuple[int, int]) -> np.ndarray:
    """Undistort and resize a depth map with nearest neighbours (no mixing across edges),
    in one remap that samples each target pixel's centre: the training camera
    (``camera.undistorted().scaled``) puts pixel x at (x + 0.5) s - 0.5 of the full image,
    where ``cv2.resize``'s nearest takes floor(s x), 1.5 pixels off at 4x."""
    d = np.asarray(depth, dtype=np.float32)
    if camera.has_distortion or (d.shape[1], d.shape[0]) != size:
        # Nearest sampling copies values, NaN and inf too: cleaned on the target's pixels
        # (a 16th of the quickstart's), not the source's, the same values; the maps made
        # once per camera and size, not once per view.
        d = cv2.remap(d, *_depth_maps(camera, size), cv2.INTER_NEAREST)
    return np.nan_to_num(d, nan=0.0, posinf=0.0, neginf=0.0)


def _depth_maps(camera: PinholeCamera, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """``prepare_depth``'s remap: x and y [h, w] float32 of each target pixel's centre in
    the full image."""
    key = (camera.width, camera.height, *np.ravel(camera.K).tolist(),
           *np.ravel(camera.dist).tolist(), *size)
    maps = _DEPTH_MAPS.get(key)
    if maps is None:
        target = camera.undistorted().scaled(*size)
        maps = cv2.initUndistortRectifyMap(camera.K, camera.dist, None, target.K, size,
                                           cv2.CV_32FC1)
        _DEPTH_MAPS.clear()  # one camera at a time in a stage: keep only the latest
        _DEPTH_MAPS[key] = maps
    return maps


_DEPTH_MAPS: dict[tuple[float, ...], tuple[np.ndarray, np.ndarray]] = {}


def read_map(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Points [N, 3] and colours [N, 3] 0..1 of the fuse stage's map PLY."""
    from toolkit.fusion.voxel_map import read_map_ply

    if not path.exists():
        raise StageError(f"splat: fused map {path} not found")
    try:
        pts, cols = read_map_ply(path)
    except ValueError as exc:
        raise StageError(f"splat: {exc}") from None
    if len(pts) == 0:
        raise StageError(f"splat: fused map {path} holds no points")
    return pts, cols.astype(np.float64) / 255.0


def strip_depth_max(rows: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> float:
    """Metres at the red end of the strip's depth colours: the largest row's 98th
    percentile (one scale for every row, said in the caption)."""
    his = [float(np.percentile(d[d > 0], 98)) for _, _, d in rows if (d > 0).any()]
    return max(his) if his else 1.0


def _strip(rows: list[tuple[np.ndarray, np.ndarray, np.ndarray]], depth_max: float) -> (
        np.ndarray):
    """Rows of real | rendered | depth (turbo from blue at 0 m to red at ``depth_max``, as
    every depth figure of the toolkit) as one RGB image."""
    out = []
    for real, rend, depth in rows:
        valid = depth > 0
        norm = np.clip(depth / max(depth_max, 1e-6), 0, 1)
        cm = cv2.applyColorMap((norm * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
        cm = cv2.cvtColor(cm, cv2.COLOR_BGR2RGB)
        cm[~valid] = 0
        out.append(np.concatenate([real, rend, cm], 1))
    return np.concatenate(out, 0)


def _write_png(path: Path, rgb: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
            raise WriteError(f"{path}: could not write image")


def _to_u8(t: torch.Tensor) -> np.ndarray:
    return (t.detach().cpu().clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)


# ------------------------------------------------------------------------ stage
class SplatStage(Stage):
    """Train 3D Gaussian splats from the fused map at the lidar poses; export a 3DGS PLY."""

    name = "splat"
    Config = SplatConfig
    requires = ("sequence",)
    # fused: the initial cloud and depth targets (init: random trains without it);
    # tsdf_mesh: rendered at the held-out views for the comparison.
    optional_requires = ("trajectory", "fused", "tsdf_mesh")
    # An interrupted training continues under a new time limit or thread count (the
    # trainer's checkpoint ignores them too: ``config_digest``). Not under another step
    # count: the learning rates decay over the whole run, so steps taken on one schedule
    # and continued on another give a model neither run gives.
    # A checkpoint resumes on another device (a GPU run finished on the CPU, or back).
    resume_settings = frozenset({"max_seconds", "log_every", "checkpoint_every", "threads",
                                 "device"})
    # Reading views on demand or up front gives the same model.
    speed_settings = frozenset({"view_cache_mb"})
    provides = ("splats",)
    # 2: off-path views masked like the path's; SSIM over valid windows. 3: images at the
    # fuse stage's exposure gains (exposure: auto). 4: the colour L1 over the valid pixels
    # of a masked view (a distorted camera's lens corners). 5: the training's SSIM term
    # over a masked view's valid windows too. 6: the scene scale is at least the initial
    # cloud's median radius (short drives in large rooms). 7: the path's held-out images at
    # gains interpolated from their training neighbours', not at their own solved ones. 8:
    # the depth MAE's coverage (the share of ground-truth pixels the render covers)
    # Not bumped when the cpp backend's projection moved to C++ (2026-11-28): the same
    # rules in another float rounding order, so a fresh run writes other bytes but a model
    # the old code cached is as valid a result (held-out PSNR within the seed-to-seed
    # noise, docs/splatting.md); a bump would only retrain every cached run.
    version = 8

    def run(self, ctx: StageContext) -> None:
        cfg: SplatConfig = self.config  # type: ignore[assignment]
        from toolkit.splat.rasterize import cpp_ext

        before = torch.get_num_threads()
        threads = choose_threads(cfg.threads)
        if threads != before:
            why = ("setting" if cfg.threads != "auto" else
                   "two cores" if usable_cpus() <= 2 else "busy machine")
            ctx.log.info("splat: %d torch thread(s) (%s), compositing on %d", threads, why,
                         before)
        cpp_ext.set_threads(before)
        torch.set_num_threads(threads)
        try:
            self._run(ctx, cfg)
        finally:
            torch.set_num_threads(before)
            cpp_ext.set_threads(None)

    def _run(self, ctx: StageContext, cfg: SplatConfig) -> None:
        from toolkit.io.sequence import read_sequence

        seq = read_sequence(ctx.artifact("sequence"))
        fused = Path(ctx.artifact("fused")) if ctx.has_artifact("fused") else None
        if not seq.frames:
            raise StageError("splat: the sequence has no camera frames")
        if cfg.init == "fused" and fused is None:
            raise StageError("splat: init: fused needs the fused map, but no stage upstream "
                             "provides 'fused' - add a fuse stage before splat, or set "
                             "init: random (with depth_weight: 0) to start from random "
                             "Gaussians")
        if cfg.depth_weight > 0 and fused is None:
            ctx.log.warning("splat: depth_weight %g but no fused depth upstream: the depth "
                            "term is off (images only)", cfg.depth_weight)
        poses, pose_source = camera_poses(seq, ctx, cfg)
        if pose_source == "groundtruth" and fused is not None:
            self._same_frame_as_the_map(seq, fused)
        index = poses.extra["frame_index"]
        if len(index) == 0:
            fs = seq.frame_stamps
            raise StageError(f"splat: no camera frame has a pose ({pose_source} poses; frames "
                             f"{fs[0]:.3f}..{fs[-1]:.3f} s): the trajectory covers none of "
                             "them - another clock, or frames in gaps between scans")
        used = np.arange(0, len(index), cfg.frame_stride)  # the frames trained or scored
        cam_full = seq.rig.camera
        w, h = cam_full.width // cfg.downscale, cam_full.height // cfg.downscale
        if min(w, h) < 11:
            raise StageError(f"splat: {cam_full.width}x{cam_full.height} images at downscale "
                             f"{cfg.downscale} are {w}x{h}, smaller than the 11-pixel SSIM "
                             "window the held-out views are scored with; lower downscale")
        cam = cam_full.undistorted().scaled(w, h)
        # Depth targets are read only when the loss uses them.
        depth_dir = find_depth_dir(fused) if fused is not None and cfg.depth_weight > 0 else None
        gt = seq.groundtruth

        valid = image_validity(cam_full, (w, h))
        if valid is not None:
            ctx.log.info("splat: %.1f %% of each undistorted image has no source pixel "
                         "(lens corners); neither fitted nor scored",
                         100.0 * (1 - float(valid.float().mean())))

        def load_view(k: int, with_depth: bool) -> TrainView:
            fi = int(index[k])
            img = seq.frames[fi].image
            if fi in gains:
                img = corrected_image(img, gains[fi])
            img = prepare_image(img, cam_full, (w, h))
            dpath = depth_file(depth_dir, fi) if with_depth else None
            depth = None
            if dpath is not None:
                from toolkit.io.depth import read_depth

                depth = torch.from_numpy(prepare_depth(read_depth(dpath), cam_full, (w, h)))
            return TrainView(torch.from_numpy(np.ascontiguousarray(img)), cam,
                             inv_se3(poses.poses[k]), depth, f"frame {fi}", valid)

        def view_set(ks: list[int], cache_bytes: int, with_depth: bool = True) -> ViewSet:
            return ViewSet(np.array([inv_se3(poses.poses[k]) for k in ks]).reshape(-1, 4, 4),
                           [f"frame {int(index[k])}" for k in ks],
                           lambda i: load_view(ks[i], with_depth), cache_bytes,
                           lambda it, total, desc: ctx.progress(it, total=total,
                                                                description=desc))

        # Every holdout_every-th of the frames used; the rule the fuse stage's holdout_every
        # leaves the same frames out of the map by.
        train_k, test_k = heldout_split(len(index), cfg.frame_stride, cfg.holdout_every)
        if not train_k:
            raise StageError("splat: no training views left (check frame_stride / "
                             "holdout_every)")
        gains = self._exposure_gains(cfg, fused, index[used])
        if gains and test_k:
            # A held-out frame's own gain was solved by the fuse stage from that frame's own
            # pixels: dividing its image by it fitted the target's exposure on the very
            # pixels it is scored on, which no prediction of an unseen view can know. Its
            # exposure is predicted from the training frames around it instead.
            train_fi = [int(index[k]) for k in train_k]
            gains = {**{fi: gains[fi] for fi in train_fi},
                     **gains_from_neighbours(gains, train_fi, [int(index[k]) for k in test_k])}
        n_depth = sum(depth_file(depth_dir, int(index[k])) is not None for k in used)
        budget_bytes = int(cfg.view_cache_mb * 2**20)
        train_views = view_set(train_k, budget_bytes)
        # The held-out views are read once each while scoring: what memory is left, or one
        # at a time. Without the fused depth: scoring never reads it (the depth error is
        # against ground truth), and it was a tenth of the quickstart's view reading.
        test_views = view_set(test_k, max(budget_bytes - train_views.held_bytes, 0),
                              with_depth=False)

        def gt_depth(i: int) -> np.ndarray | None:
            if gt is None or gt.depth_paths is None:
                return None
            return prepare_depth(gt.depth(int(index[test_k[i]])), cam_full, (w, h))

        test_gt_depth = LazyList(len(test_k), gt_depth)
        if not train_views.eager:
            ctx.log.info("splat: %d training views of %.0f KB each exceed view_cache_mb %g: "
                         "read from disk as training asks for them (%d held at a time)",
                         len(train_views), train_views.view_bytes / 1024, cfg.view_cache_mb,
                         max(budget_bytes // train_views.view_bytes, 1))

        tcfg = TrainConfig(**{k: getattr(cfg, k) for k in TrainConfig.model_fields})
        # The memory budget caps the initial model too, not only its growth.
        budget = min(cfg.init_budget, gaussian_cap(tcfg))
        if cfg.init == "fused":
            assert fused is not None
            pts, cols = read_map(fused / "map.ply")
            model = init_from_points(pts, cols, budget=budget, sh_degree=cfg.sh_degree,
                                     init_opacity=cfg.init_opacity, seed=cfg.seed)
        else:
            model = init_random_in_views([cam] * len(train_views),
                                         [inv_se3(T) for T in train_views.poses],
                                         budget, cfg.random_depth_m, sh_degree=cfg.sh_degree,
                                         init_opacity=cfg.init_opacity, seed=cfg.seed)
        n_init = len(model)
        gpu_seen = (cfg.device != "cpu" and cfg.backend in ("auto", "gsplat")
                    and torch.cuda.is_available())
        if gpu_seen:
            ctx.log.info("splat: loading gsplat's CUDA kernels (built on first use: minutes)")
        device = choose_device(cfg.device, cfg.backend)
        if gpu_seen and device.type == "cpu":
            from toolkit.splat.rasterize import gsplat_backend

            ctx.log.warning("splat: device auto: a CUDA GPU is present but %s; training on "
                            "the CPU", gsplat_backend.unavailable_reason())
        model = model.to(device)
        data_key = _data_key(fused / "map.ply" if cfg.init == "fused" and fused else None,
                             [cfg.init, budget, cfg.init_opacity, list(cfg.random_depth_m),
                              depth_dir is not None],
                             train_views.names, poses.poses, (w, h))
        trainer = Trainer(model, train_views, tcfg, ctx.stage_dir / "checkpoints",
                          data_key=data_key)
        resumed = trainer.resume()
        backend = resolve_backend(cfg.backend, model.means.device)
        ctx.log.info("splat: %d training views at %dx%d (%d with scaled depth), %d held out, "
                     "%d initial Gaussians, backend %s%s", len(train_views), w, h, n_depth,
                     len(test_views), n_init, backend,
                     f", resumed at step {trainer.step} with {len(trainer.model)} Gaussians"
                     if resumed else "")
        summary = trainer.train(iter_wrapper=lambda it, total, desc: ctx.progress(
            it, total=total, description=desc))
        model = trainer.model
        train_views.close()

        write_ply(ctx.stage_dir / "splats.ply", model)
        atomic_write_json(ctx.stage_dir / "train_history.json", summary.history)

        # ---------------------------------------------------------------- evaluation
        t0 = time.perf_counter()
        metrics: dict[str, object] = {
            "poses": pose_source,
            "backend": backend,
            "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
            "train_views": len(train_views),
            # Images divided by the fuse stage's exposure gains (exposure: fused, or auto
            # with the gains there).
            "exposure_gains_from_fuse": bool(gains),
            "image_width": w,
            "image_height": h,
            "threads": torch.get_num_threads(),
            "iterations": summary.steps,
            "stopped_early": summary.stopped_early,
            "train_seconds": summary.seconds,
            "train_iters_per_s": summary.iters_per_s,
            "init": cfg.init,
            "n_gaussians_init": n_init,
            "n_gaussians": summary.n_gaussians,
            "train_psnr_db": summary.final_psnr_db,
        }
        strip_rows: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        compare_rows: list[np.ndarray] = []
        (ctx.stage_dir / "renders").mkdir(exist_ok=True)
        mesh_r: MeshViewRenderer | None = None
        if cfg.compare_tsdf and ctx.has_artifact("tsdf_mesh"):
            mesh_r = MeshViewRenderer(ctx.artifact("tsdf_mesh"), cam_full.undistorted(), (w, h),
                                      cfg.background)
            metrics["tsdf_mesh_triangles"] = mesh_r.n_triangles
        comparisons: dict[str, Comparison] = {}
        t_mesh = [0.0]
        # Simulator held-out views have ground-truth poses: move them into the trajectory's
        # frame (the splats' frame) first.
        T_traj_gt = np.eye(4)
        if pose_source == "trajectory":
            al = groundtruth_to_trajectory_frame(seq, poses)
            if al is not None:
                T_traj_gt = al[0]
                metrics["sim_heldout_alignment_rmse_m"] = al[1]
        sim_views = self._sim_heldout(seq, cam_full, cam, (w, h), T_traj_gt, valid)
        # Pictures: every held-out view as a PNG; in the strip, views spread along the path
        # and, when the simulator gave some, off-path ones as well.
        n_path = cfg.strip_views - cfg.strip_views // 2 if sim_views else cfg.strip_views
        n_sim = cfg.strip_views - n_path

        def saver(prefix: str, n_total: int, n_strip: int, comp: Comparison | None = None) -> (
                Callable[..., None]):
            # Interior points of the sequence: a loop's first and last frames look alike.
            picks = set(np.linspace(0, n_total - 1, n_strip + 2)[1:-1].round().astype(int)
                        .tolist() if n_strip > 0 and n_total > 0 else [])

            def save(i: int, v: TrainView, out: RenderOutput) -> None:
                color = out.color.detach().cpu()  # pictures and the mesh are on the CPU
                rend = _to_u8(color)
                _write_png(ctx.stage_dir / "renders" / f"{prefix}_{i:03d}.png", rend)
                mesh_img = None
                if mesh_r is not None and comp is not None:
                    t = time.perf_counter()
                    mr = mesh_r.render(v.T_camera_world)
                    comp.add(mr, color.clamp(0, 1), v.target(), v.mask)
                    mesh_img = _to_u8(mr.color)
                    t_mesh[0] += time.perf_counter() - t
                if i in picks:
                    depth = np.where(out.alpha.detach().cpu().numpy() > 0.5,
                                     out.depth.detach().cpu().numpy(), 0.0)
                    strip_rows.append((v.image.numpy(), rend, depth))
                    if mesh_img is not None:
                        compare_rows.append(np.concatenate([v.image.numpy(), rend, mesh_img],
                                                           1))

            return save

        def compared(prefix: str) -> Comparison | None:
            if mesh_r is None:
                return None
            comparisons[prefix] = Comparison()
            return comparisons[prefix]

        if test_views:
            ev = evaluate_views(model, test_views, backend, cfg.background, test_gt_depth,
                                saver("path", len(test_views), n_path, compared("heldout")))
            metrics["heldout_every_n"] = cfg.holdout_every
            metrics["heldout_frames"] = ev["views"]
            metrics["heldout_psnr_db"] = ev["psnr_db"]
            metrics["heldout_psnr_exposure_matched_db"] = ev["psnr_exposure_matched_db"]
            metrics["heldout_ssim"] = ev["ssim"]
            if fused is not None and cfg.init == "fused":
                # The initial cloud's leak in one figure: held-out frames the fuse stage
                # fused into the map (all of them, unless its holdout_every matches).
                n_in = _frames_in_map(fused, seq.frame_stamps[[int(index[k]) for k in test_k]])
                if n_in is not None:
                    metrics["heldout_frames_in_fused_map"] = n_in
            for key in ("depth_mae_m", "depth_rmse_m", "depth_coverage"):
                if key in ev:
                    metrics[f"heldout_{key}"] = ev[key]
        if sim_views:
            views, depths = sim_views
            ev = evaluate_views(model, views, backend, cfg.background, depths,
                                saver("offpath", len(views), n_sim if test_views else
                                      cfg.strip_views, compared("sim_heldout")))
            metrics["sim_heldout_views"] = ev["views"]
            metrics["sim_heldout_psnr_db"] = ev["psnr_db"]
            metrics["sim_heldout_psnr_exposure_matched_db"] = ev["psnr_exposure_matched_db"]
            metrics["sim_heldout_ssim"] = ev["ssim"]
            for key in ("depth_mae_m", "depth_rmse_m", "depth_coverage"):
                if key in ev:
                    metrics[f"sim_heldout_{key}"] = ev[key]
        for prefix, comp in comparisons.items():
            metrics.update(comp.metrics(prefix))
            if f"{prefix}_psnr_db" in metrics:
                metrics[f"{prefix}_psnr_gain_over_tsdf_db"] = (
                    float(metrics[f"{prefix}_psnr_db"])  # type: ignore[arg-type]
                    - metrics[f"tsdf_{prefix}_psnr_db"])
        if mesh_r is not None:
            metrics["tsdf_render_seconds"] = t_mesh[0]
        if strip_rows:
            metrics["renders_depth_max_m"] = strip_depth_max(strip_rows)
            _write_png(ctx.stage_dir / "renders.png",
                       _strip(strip_rows, metrics["renders_depth_max_m"]))  # type: ignore
        if compare_rows:
            _write_png(ctx.stage_dir / "splat_vs_tsdf.png", np.concatenate(compare_rows, 0))
        metrics["eval_seconds"] = time.perf_counter() - t0
        ctx.add_metrics(metrics)
        ctx.report(self._report(ctx, cfg, metrics, pose_source, bool(strip_rows),
                                bool(sim_views), resumed, bool(compare_rows)))
        ctx.provide("splats", ctx.stage_dir / "splats.ply")

    @staticmethod
    def _exposure_gains(cfg: SplatConfig, fused: Path | None,
                        frames: np.ndarray) -> dict[int, np.ndarray]:
        """Frame index -> gain [3] of ``frames`` for ``exposure: fused``, or ``auto`` when
        the fuse stage wrote its gains (else empty)."""
        if cfg.exposure not in ("fused", "auto"):
            return {}
        try:
            gains = gains_for_frames(fused, frames)
        except ValueError as exc:
            raise StageError(f"splat: {exc}") from exc
        if not gains and cfg.exposure == "fused":
            raise StageError("splat: exposure: fused needs the exposure gains of a fuse stage "
                             f"upstream ({EXPOSURE_FILE}), and "
                             + ("there is no fuse stage" if fused is None else
                                f"{fused} has none") + ": set `exposure: gain` on the fuse "
                             "stage, or `exposure: gain` / `none` here")
        return gains

    @staticmethod
    def _sim_heldout(seq: Sequence, cam_full: PinholeCamera, cam: PinholeCamera,
                     size: tuple[int, int], T_traj_gt: np.ndarray,
                     valid: torch.Tensor | None) -> (
                         tuple[list[TrainView], list[np.ndarray | None]] | None):
        """The simulator's held-out views, scored on ``valid`` as the path's are (the lens
        corners of an undistorted image have no source pixel)."""
        gt = seq.groundtruth
        if gt is None or gt.heldout is None or not gt.heldout.image_paths:
            return None
        from toolkit.io.depth import read_depth

        h = gt.heldout
        views, depths = [], []
        for i, p in enumerate(h.image_paths):
            img = prepare_image(load_rgb(p), cam_full, size)
            views.append(TrainView(torch.from_numpy(np.ascontiguousarray(img)), cam,
                                   inv_se3(T_traj_gt @ h.poses_camera.poses[i]), None,
                                   f"held-out {i}", valid))
            d = None
            if h.depth_paths and i < len(h.depth_paths):
                d = prepare_depth(read_depth(h.depth_paths[i]), cam_full, size)
            depths.append(d)
        return views, depths

    @staticmethod
    def _same_frame_as_the_map(seq: Sequence, fused: Path) -> None:
        """Refuse ground-truth poses for a map the fuse stage built at other ones (the SLAM
        frame, 1.4 m and a few degrees off the simulator's world on the small house): the
        splats would start from a map beside them, and nothing would say so."""
        from toolkit.eval.alignment import built_at_ground_truth
        from toolkit.io.tum import read_tum

        path = fused / "camera_poses.tum"
        if path.exists() and not built_at_ground_truth(seq, read_tum(path)):
            raise StageError(
                "splat: poses: groundtruth, but the fused map upstream was built at other "
                f"poses ({path}: the trajectory's frame): set the fuse stage's poses to "
                "groundtruth as well, or leave splat's poses at auto")

    @staticmethod
    def _report(ctx: StageContext, cfg: SplatConfig, m: dict[str, object], pose_source: str,
                strip: bool, sim: bool, resumed: bool, compare_png: bool = False) -> str:
        sid = ctx.stage_id
        lines = []
        if pose_source == "groundtruth":
            why = ("`poses: groundtruth`" if cfg.poses == "groundtruth"
                   else "no `trajectory` artifact upstream")
            lines.append(f"**WARNING: {why} - splats trained at the sequence's GROUND-TRUTH "
                         "camera poses, not the lidar SLAM poses.**\n")
        origin = ("from the fused map" if m["init"] == "fused" else
                  "at random on the cameras' rays (no fused map)")
        lines.append(
            f"{m['n_gaussians_init']} Gaussians {origin} grew to {m['n_gaussians']} "
            f"in {m['iterations']} iterations at {m['image_width']}x{m['image_height']} "
            f"({m['train_seconds']:.0f} s, {m['train_iters_per_s']:.1f} it/s, backend "
            f"`{m['backend']}`, {m['train_views']} training views"
            + (", resumed from a checkpoint" if resumed else "") + ")."
            + (" **Training stopped early at the time limit.**" if m["stopped_early"] else ""))
        rows = []
        if "heldout_psnr_db" in m:
            rows.append((f"every {cfg.holdout_every}-th frame ({m['heldout_frames']})",
                         "heldout"))
        if sim:
            rows.append((f"simulator held-out views ({m['sim_heldout_views']})", "sim_heldout"))
        tsdf = any(f"tsdf_{p}_psnr_db" in m for _, p in rows)

        def f(key: str, fmt: str) -> str:
            v = m.get(key)
            return format(v, fmt) if isinstance(v, float) and np.isfinite(v) else "-"

        if rows:
            head = ("| held-out set | PSNR (dB) | PSNR, exposure matched (dB) | SSIM | "
                    "depth MAE (m), over the covered share of pixels |")
            if tsdf:
                head += (" TSDF mesh PSNR (dB) | TSDF SSIM | gain (dB) | TSDF coverage | "
                         "covered px: TSDF / splats PSNR (dB) |")
            lines.append("\n" + head + "\n" + "|---" * (head.count("|") - 1) + "|")
            for name, p in rows:
                row = (f"| {name} | {f(f'{p}_psnr_db', '.2f')} | "
                       f"{f(f'{p}_psnr_exposure_matched_db', '.2f')} | "
                       f"{f(f'{p}_ssim', '.3f')} | {f(f'{p}_depth_mae_m', '.3f')} "
                       f"({f(f'{p}_depth_coverage', '.1%')}) |")
                if tsdf:
                    row += (f" {f(f'tsdf_{p}_psnr_db', '.2f')} | {f(f'tsdf_{p}_ssim', '.3f')} | "
                            f"{f(f'{p}_psnr_gain_over_tsdf_db', '+.2f')} | "
                            f"{f(f'tsdf_{p}_coverage', '.1%')} | "
                            f"{f(f'tsdf_{p}_psnr_covered_db', '.2f')} / "
                            f"{f(f'{p}_psnr_on_tsdf_covered_db', '.2f')} |")
                lines.append(row)
            lines.append("\nExposure matched: each held-out render scaled per colour channel "
                         "by the gain that fits it to its image best (a camera's exposure is "
                         "not known for a view the splats never saw)"
                         + ("; training fitted that gain to every image too (`exposure: "
                            "gain`)." if cfg.exposure == "gain" else
                            "; training images were divided by the exposure gains the fuse "
                            f"stage solved (`exposure: {cfg.exposure}`), the path's held-out "
                            "images by the gains interpolated from their training neighbours' "
                            "(a held-out frame's own gain was solved from its own pixels)."
                            if m.get("exposure_gains_from_fuse") else "."))
            if tsdf:
                lines.append(
                    "\nTSDF mesh: the upstream `tsdf` stage's mesh (vertex colours) ray-cast at "
                    "the same held-out poses at full resolution and area-resized like the "
                    "images; PSNR over all pixels, pixels without a hit count with the "
                    "background colour. Covered px: pixels every ray of which hit the mesh, "
                    "for the mesh and for the splats on the same pixels.")
        if strip:
            lines.append(f"\n![real, rendered, rendered depth]({sid}/renders.png)\n\n"
                         "Each row: real image | rendered from the splats | rendered depth "
                         "(blue near to red at "
                         f"{float(m.get('renders_depth_max_m', float('nan'))):.1f} m, black "
                         "none; held-out views: along the path first, then off the path).")
        if compare_png:
            lines.append(f"\n![real, splats, TSDF mesh]({sid}/splat_vs_tsdf.png)\n\n"
                         "Each row: real image | splats | TSDF mesh, same views as above.")
        lines.append(f"\nSplats: [{sid}/splats.ply]({sid}/splats.ply) (standard 3DGS PLY).")
        return "\n".join(lines)


def _frames_in_map(fused: Path, stamps: np.ndarray) -> int | None:
    """How many of the frames at ``stamps`` the fuse stage fused into its map (its
    ``camera_poses.tum`` lists every fused frame); None when it wrote no such file."""
    from toolkit.io.tum import read_tum

    path = fused / "camera_poses.tum"
    if not path.exists():
        return None
    fused_st = np.sort(read_tum(path).stamps)  # [M]
    stamps = np.asarray(stamps, np.float64)  # [N]
    if not len(fused_st) or not len(stamps):
        return 0
    # The nearest fused stamp by bisection ([N, M] distances would be gigabytes for an
    # hour's frames). Stamps round-trip the TUM text; frames lie 10s of ms apart.
    i = np.clip(np.searchsorted(fused_st, stamps), 1, len(fused_st) - 1)  # one stamp: 0
    near = np.minimum(np.abs(stamps - fused_st[i - 1]), np.abs(stamps - fused_st[i]))
    return int((near < 1e-4).sum())


def _data_key(map_ply: Path | None, init: list[object], names: list[str], poses: np.ndarray,
              size: tuple[int, int]) -> str:
    """Identity of the training data and initialisation, so a checkpoint from other inputs
    is not resumed."""
    h = hashlib.sha256()
    st = map_ply.stat() if map_ply is not None and map_ply.exists() else None
    h.update(json.dumps([str(map_ply), st.st_size if st else 0, st.st_mtime_ns if st else 0,
                         init, names, list(size)]).encode())
    h.update(np.ascontiguousarray(poses, dtype=np.float64).tobytes())
    return h.hexdigest()[:16]

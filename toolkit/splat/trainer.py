"""Optimise a Gaussian model against posed images (poses fixed, optional refinement).

Loss per step (one view): (1 - lambda) L1 + lambda (1 - SSIM) on colour (the paper's
E_pho, lambda 0.2) plus ``depth_weight`` times the mean L1 between rendered expected depth
and the lidar-scaled depth on its valid pixels (E_geo). Adam, one optimiser per parameter
group with gsplat's learning rates; the means' rate decays exponentially to
``lr_means_final`` of its start, and scales with the scene size. The SH degree rises by one
every ``sh_degree_interval`` steps. Densification is a ``DefaultStrategy``.

Checkpoints (``checkpoint_every`` steps and at the end) hold parameters, optimiser moments,
strategy statistics and the RNG state, written atomically; ``Trainer.resume`` continues
from one and reproduces the uninterrupted run exactly (the view order is a pure function
of the seed and the step).

A checkpoint is a header line, the SHA-256 of the rest, and ``torch.save``'s zip, as the
recipe's checkpoints are (toolkit.recipe.checkpoint). ``torch.load`` checks no CRC: a
byte changed on disk (a bad sector, a bit flipped in the page cache) that still loaded gave
the training a wrong parameter or Adam moment to go on from, whose error then stood in the
stage's cached splats. A checkpoint whose digest does not match is ignored with a warning
(training starts afresh). So is one written before the digest (a bare zip): loading it
unchecked would keep the risk, and starting afresh costs an interrupted training's steps
once, on the first run after the upgrade (a finished stage's checkpoint is never read: a
rerun starts from an empty folder).
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import Tensor, nn

from toolkit.camera import PinholeCamera
from toolkit.eval.image import psnr as psnr_fn
from toolkit.eval.image import ssim as ssim_fn
from toolkit.geometry import inv_se3
from toolkit.io.atomic import (
    FileTail,
    digest_problem,
    digested_write,
    remove_leftover_temps,
)
from toolkit.splat.model import PARAM_NAMES, GaussianModel
from toolkit.splat.rasterize import RenderOutput, render
from toolkit.splat.strategy import DefaultStrategy, StrategyConfig

log = logging.getLogger(__name__)

IterWrapper = Callable[[Iterable[int], int, str], Iterable[int]]
CHECKPOINT_NAME = "checkpoint.pt"
_MAGIC = b"lidarcam-recon splat checkpoint 2\n"
# torch.save's zip alone: the format before the digest.
_OLDER = (b"PK\x03\x04", "written before splat checkpoints carried a checksum (an older "
          "toolkit)")


Unit = Annotated[float, Field(ge=0, le=1)]  # a value in [0, 1]


class TrainConfig(BaseModel):
    """Training settings (every field has a CPU-friendly default)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    iterations: int = Field(1500, ge=0)
    sh_degree: int = Field(3, ge=0, le=3)
    sh_degree_interval: int = Field(300, ge=1, description="steps per SH degree increase")
    lambda_dssim: float = Field(0.2, ge=0.0, le=1.0)
    depth_weight: float = Field(0.1, ge=0.0, description="weight of the L1 depth term (1/m)")
    lr_means: float = Field(1.6e-4, gt=0)  # x scene scale
    # fraction of lr_means reached at the last step (a negative one made the rate complex)
    lr_means_final: float = Field(0.01, gt=0, le=1)
    lr_scales: float = Field(5e-3, gt=0)
    lr_quats: float = Field(1e-3, gt=0)
    lr_opacities: float = Field(5e-2, gt=0)
    lr_sh0: float = Field(2.5e-3, gt=0)
    lr_shN: float = Field(2.5e-3 / 20, gt=0)
    # RGB in 0..1, as the renders and PSNR are (white = [1, 1, 1]; 255 trained against a
    # background no render can reach and crashed the TSDF comparison)
    background: tuple[Unit, Unit, Unit] = (0.0, 0.0, 0.0)
    backend: Literal["auto", "cpp", "torch", "gsplat"] = "auto"
    densify: StrategyConfig = StrategyConfig()
    max_gaussians: int = Field(300_000, ge=1)
    memory_budget_mb: float | None = Field(
        None, gt=0, description="caps the Gaussian count so parameters + Adam state fit")
    scene_scale: float | None = Field(None, gt=0, description="None: from the camera spread")
    pose_refine: bool = False
    lr_pose: float = Field(1e-5, ge=0)
    pose_reg: float = Field(1e-6, ge=0)
    checkpoint_every: int = Field(500, ge=0, description="0: only at the end")
    log_every: int = Field(100, ge=1)
    max_seconds: float | None = Field(None, gt=0, description="stop early after this long")
    seed: int = 0
    # Per-image exposure. "gain": before the loss, each render is scaled per channel by the
    # gain that best fits it to its image (least squares, pulled towards 1 by
    # ``exposure_reg``; no gradient through it), so images of one surface taken at other
    # exposures (a camera's auto exposure) do not pull its colour apart, while the map's
    # overall brightness stays the initial cloud's. Each view is seen a few times in a
    # short CPU training: a gain fitted at every step, not one learnt per view. "fused"
    # (the splat stage): the images are divided by the gains the fuse stage solved over
    # the whole drive (its `exposure: gain`) before training; the renders stay as they
    # are. "auto": fused when the fuse stage wrote gains, else none.
    exposure: Literal["none", "gain", "fused", "auto"] = "auto"
    exposure_reg: float = Field(0.01, ge=0)


@dataclass
class TrainView:
    """One posed image. ``camera`` is undistorted and matches the image size."""

    image: Tensor  # [H, W, 3] uint8
    camera: PinholeCamera
    T_camera_world: np.ndarray  # [4, 4]
    depth: Tensor | None = None  # [H, W] float32 metres, 0 = no value
    name: str = ""
    # [H, W] bool: pixels the image holds (undistorting a pincushion lens leaves corners no
    # ray reaches: black, to be neither fitted nor scored); None: all of them.
    mask: Tensor | None = None

    def __post_init__(self) -> None:
        # numpy arrays are welcome (what images load as; a flipped one such as BGR -> RGB
        # img[..., ::-1] too); the trainer works on tensors.
        self.image = _tensor(self.image)
        if self.image.dtype != torch.uint8 or self.image.ndim != 3 or self.image.shape[2] != 3:
            raise ValueError(f"view {self.name}: image must be uint8 [H, W, 3], got "
                             f"{self.image.dtype} {tuple(self.image.shape)}")
        if self.depth is not None:
            depth = _tensor(self.depth)
            if not depth.is_floating_point():
                # A 16-bit depth PNG (5000 per metre) taken as metres trained on 8271 m.
                raise ValueError(f"view {self.name}: depth must be float metres, got "
                                 f"{depth.dtype}; read depth files with "
                                 "toolkit.io.depth.read_depth, which converts their units")
            self.depth = depth.to(torch.float32)
        if self.mask is not None:
            self.mask = _tensor(self.mask).to(torch.bool)
        h, w = self.image.shape[:2]
        if (w, h) != self.camera.size:
            raise ValueError(f"view {self.name}: image is {w}x{h} but the camera "
                             f"{self.camera.width}x{self.camera.height}")
        if self.depth is not None and tuple(self.depth.shape) != (h, w):
            raise ValueError(f"view {self.name}: depth {tuple(self.depth.shape)} vs image "
                             f"{(h, w)}")
        if self.mask is not None and tuple(self.mask.shape) != (h, w):
            raise ValueError(f"view {self.name}: mask {tuple(self.mask.shape)} vs image "
                             f"{(h, w)}")

    def masked(self, color: Tensor, target: Tensor) -> Tensor:
        """``color`` [H, W, 3] with the pixels outside ``mask`` set to the target's: they add
        no error and no gradient (to L1, SSIM and PSNR alike)."""
        if self.mask is None:
            return color
        return torch.where(self.mask.to(color.device)[..., None], color, target)

    def mask_on(self, device: torch.device | str) -> Tensor | None:
        return None if self.mask is None else self.mask.to(device)

    def target(self, device: torch.device | str = "cpu") -> Tensor:
        """[H, W, 3] float 0..1."""
        # uint8 crosses to the device, a quarter of the float bytes
        return self.image.to(device, non_blocking=True).to(torch.float32) / 255.0


def masked_l1(color: Tensor, target: Tensor, mask: Tensor | None = None) -> Tensor:
    """Mean absolute error of ``color`` [H, W, C] against ``target`` over the pixels of
    ``mask`` [H, W] (``TrainView.masked`` set the others to the target). A mean over every
    pixel shrank the colour loss and its gradients by the valid share: the depth term, a
    mean over its own pixels, grew against it, and the densification threshold rose."""
    if mask is None:
        return (color - target).abs().mean()
    return (color - target).abs().sum() / (target.shape[-1] * mask.sum().clamp(min=1))


def exposure_gain(render: Tensor, target: Tensor, mask: Tensor | None = None,
                  reg: float = 0.0) -> Tensor:
    """[3] per-channel gain g minimising sum |g render - target|^2 over ``mask``'s pixels
    plus reg * N * (g - 1)^2 (N: the pixels fitted), from [H, W, 3] images; no gradient
    flows through it. The pull is per pixel: a render that covers little of its image (dark
    elsewhere) keeps a gain nearer 1, and the splats' overall brightness cannot drift into
    the gains (docs/splatting.md, measured)."""
    r = render.detach()
    t = target.to(r.dtype)
    if mask is not None:
        m = mask[..., None].to(r.dtype)
        r, t, n = r * m, t * m, m.sum()
    else:
        n = torch.tensor(float(r.shape[0] * r.shape[1]), dtype=r.dtype, device=r.device)
    num = (r * t).sum((0, 1)) + reg * n
    den = (r * r).sum((0, 1)) + reg * n
    return (num / den.clamp_min(1e-12)).clamp(0.25, 4.0)


@dataclass
class TrainSummary:
    steps: int
    seconds: float
    iters_per_s: float
    n_gaussians: int
    final_loss: float
    final_psnr_db: float
    stopped_early: bool
    resumed_from: int | None
    history: list[dict[str, float]] = field(default_factory=list)


def _tensor(a: np.ndarray | Tensor, device: torch.device | str | None = None) -> Tensor:
    """A tensor of ``a`` (on ``device`` if given); numpy views with negative strides are
    copied (torch refuses them)."""
    if isinstance(a, Tensor):
        return a if device is None else a.to(device)
    return torch.as_tensor(np.ascontiguousarray(a), device=device)


def bytes_per_gaussian(sh_degree: int) -> int:
    """Parameter + gradient + two Adam moments, float32 (render temporaries excluded)."""
    floats = 3 + 3 + 4 + 1 + 3 * (sh_degree + 1) ** 2
    return floats * 4 * 4


def gaussian_cap(cfg: TrainConfig, sh_degree: int | None = None) -> int:
    """The most Gaussians ``max_gaussians`` and ``memory_budget_mb`` allow, at the model's
    SH degree (None: the config's)."""
    cap = cfg.max_gaussians
    degree = cfg.sh_degree if sh_degree is None else sh_degree
    if cfg.memory_budget_mb is not None:
        cap = min(cap, int(cfg.memory_budget_mb * 2**20 / bytes_per_gaussian(degree)))
    return max(cap, 1)


def view_poses(views: Sequence[TrainView]) -> np.ndarray:
    """[N, 4, 4] T_camera_world of every view, without reading the pixels of views loaded
    on demand (a ``ViewSet`` holds its poses)."""
    poses = getattr(views, "poses", None)
    if poses is not None:
        return np.asarray(poses, dtype=np.float64)
    return np.array([v.T_camera_world for v in views], dtype=np.float64).reshape(-1, 4, 4)


def view_names(views: Sequence[TrainView]) -> list[str]:
    names = getattr(views, "names", None)
    return list(names) if names is not None else [v.name for v in views]


def scene_scale_of(views: Sequence[TrainView], points: Tensor | None = None) -> float:
    """1.1 x the largest camera distance from the cameras' centroid (gsplat), or the cloud's
    median radius [N, 3] where that is larger: a robot that drives a little in a large room
    sees the room. (A switch to the cloud only below 0.1 m of camera spread made the scale
    jump 22x between drives of 9 and 11 cm, and the means' rate and size tests with it.)"""
    centres = np.array([inv_se3(T)[:3, 3] for T in view_poses(views)])
    spread = float(np.linalg.norm(centres - centres.mean(0), axis=1).max()) if len(views) else 0
    scale = max(1.1 * spread, 1e-3)
    if points is not None and len(points):
        p = points.detach().cpu().double()
        scale = max(scale, float((p - p.mean(0)).norm(dim=1).median()))
    return scale


def rotation_6d_to_matrix(d6: Tensor) -> Tensor:
    """[3, 3] from a 6D rotation (two columns, Gram-Schmidt; Zhou et al. 2019)."""
    a1, a2 = d6[:3], d6[3:]
    b1 = a1 / a1.norm()
    b2 = a2 - (b1 * a2).sum() * b1
    b2 = b2 / b2.norm()
    return torch.stack([b1, b2, torch.linalg.cross(b1, b2)], 0)


class PoseRefinement(nn.Module):
    """Per-view correction D (camera frame) applied as D @ T_camera_world; starts at identity."""

    def __init__(self, n_views: int, device: torch.device | str = "cpu") -> None:
        super().__init__()
        # translation 3 + 6D rotation
        self.delta = nn.Parameter(torch.zeros(n_views, 9, device=device))
        self.register_buffer("identity6", torch.tensor([1.0, 0, 0, 0, 1.0, 0], device=device))

    def forward(self, T_cw: Tensor, index: int) -> Tensor:
        d = self.delta[index].to(T_cw.dtype)
        R = rotation_6d_to_matrix(d[3:] + self.identity6.to(T_cw.dtype))
        bottom = torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=T_cw.dtype, device=T_cw.device)
        D = torch.cat([torch.cat([R, d[:3, None]], 1), bottom], 0)  # [4, 4]
        return D @ T_cw

    def corrected(self, T_cw: np.ndarray, index: int) -> np.ndarray:
        with torch.no_grad():
            T = torch.as_tensor(T_cw, dtype=torch.float64, device=self.delta.device)
            return self.forward(T, index).cpu().numpy()


def _adam(params: list[nn.Parameter], lr: float) -> torch.optim.Optimizer:
    try:
        return torch.optim.Adam(params, lr=lr, eps=1e-15, fused=True)
    except (RuntimeError, TypeError):  # fused not supported for this device/dtype/version
        return torch.optim.Adam(params, lr=lr, eps=1e-15, foreach=True)


def config_digest(cfg: TrainConfig, whole: bool = False) -> str:
    """What a checkpoint must agree with to be resumed (the time limit and the checkpoint
    and log intervals may change: they do not touch the optimisation; the step count does,
    through the learning-rate decay over the whole run); ``whole``: with the time limit,
    what a finished run's model must agree with to be taken as the result (the intervals
    still not: a finished training was thrown away and redone from step 0 for another
    ``log_every``)."""
    d = cfg.model_dump(mode="json")
    for k in ("checkpoint_every", "log_every") if whole else (
            "checkpoint_every", "log_every", "max_seconds"):
        d.pop(k, None)
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


class Trainer:
    """Owns the optimisers, strategy and schedule for one model and a set of views."""

    def __init__(self, model: GaussianModel, views: Sequence[TrainView], config: TrainConfig,
                 checkpoint_dir: Path | None = None, data_key: str = "") -> None:
        if not views:
            raise ValueError("no training views")
        if config.sh_degree > model.max_sh_degree:
            raise ValueError(f"config asks for SH degree {config.sh_degree} but the model "
                             f"holds degree {model.max_sh_degree}")
        self.model = model
        # Where the model lives (CPU or a CUDA GPU): views are read into CPU memory and
        # each step's image, depth and mask move there.
        self.device = model.means.device
        self.views = views
        self.T_cw = view_poses(views)  # [N, 4, 4]
        self.cfg = config
        self.checkpoint_dir = checkpoint_dir
        # Identity of the views / initial model, checked on resume; without one from the
        # caller, what the trainer itself sees of them (another scene must not resume).
        self.data_key = data_key or _default_data_key(model, views)
        self.done: dict[str, Any] | None = None  # a finished run's summary, once resumed
        self.step = 0
        # The model's own SH degree sizes it (a degree-3 model under a degree-1 config held
        # 1.6 times its memory budget).
        self.cap = gaussian_cap(config, max(config.sh_degree, model.max_sh_degree))
        self.scene_scale = config.scene_scale or scene_scale_of(views, model.means)
        densify = config.densify
        if densify.refine_stop_iter is None:
            densify = densify.model_copy(update={"refine_stop_iter": config.iterations // 2})
        self.strategy = DefaultStrategy(densify, max_gaussians=self.cap)
        self.strategy_state = self.strategy.initialize_state(len(model), self.scene_scale,
                                                             self.device)
        self.generator = torch.Generator().manual_seed(config.seed)
        self.optimizers = self._make_optimizers()
        self.pose: PoseRefinement | None = None
        self.pose_opt: torch.optim.Optimizer | None = None
        if config.pose_refine:
            self.pose = PoseRefinement(len(views), self.device)
            self.pose_opt = self._make_pose_opt(self.pose)
        self.history: list[dict[str, float]] = []
        # Running averages of loss and PSNR (history, progress bar, final figures): in the
        # checkpoint, so that a resumed run reports what an uninterrupted one does.
        self.ema: dict[str, float] = {}
        self.resumed_from: int | None = None
        if len(model) > self.cap:
            log.warning("model has %d Gaussians, above the cap of %d: growth disabled until "
                        "pruning brings it below", len(model), self.cap)

    # ---------------------------------------------------------------- setup
    def _lrs(self) -> dict[str, float]:
        c = self.cfg
        return {"means": c.lr_means * self.scene_scale, "log_scales": c.lr_scales,
                "quats": c.lr_quats, "opacity_logits": c.lr_opacities, "sh0": c.lr_sh0,
                "shN": c.lr_shN}

    def _make_optimizers(self, params: dict[str, nn.Parameter] | None = None) -> (
            dict[str, torch.optim.Optimizer]):
        """Adam over ``params`` (None: the model's)."""
        # One Adam per group (gsplat): densification swaps one tensor at a time, and eps
        # 1e-15 as in 3DGS (the default 1e-8 stalls tiny SH and position updates). The fused
        # kernel: on CPU the default per-tensor Adam took 38 ms a step for 100k Gaussians,
        # fused 5 ms.
        params = dict(self.model.params) if params is None else params
        return {k: _adam([params[k]], lr) for k, lr in self._lrs().items()}

    def _make_pose_opt(self, pose: PoseRefinement) -> torch.optim.Optimizer:
        return torch.optim.Adam(pose.parameters(), lr=self.cfg.lr_pose,
                                weight_decay=self.cfg.pose_reg)

    def view_index(self, step: int) -> int:
        """Views in a fresh random order every epoch; a function of seed and step only."""
        n = len(self.views)
        epoch, pos = divmod(step, n)
        g = torch.Generator().manual_seed(self.cfg.seed * 1_000_003 + epoch)
        return int(torch.randperm(n, generator=g, device="cpu")[pos])

    def active_sh_degree(self, step: int) -> int:
        return min(step // self.cfg.sh_degree_interval, self.cfg.sh_degree)

    def pose_of(self, index: int) -> np.ndarray | Tensor:
        T = self.T_cw[index]
        if self.pose is None:
            return T
        return self.pose(torch.as_tensor(T, dtype=torch.float32, device=self.device), index)

    # ---------------------------------------------------------------- one step
    def train_step(self) -> dict[str, float]:
        """One optimisation step on one view; returns loss figures."""
        cfg = self.cfg
        step = self.step
        idx = self.view_index(step)
        view = self.views[idx]
        decay = cfg.lr_means_final ** (step / max(cfg.iterations, 1))
        for group in self.optimizers["means"].param_groups:
            group["lr"] = cfg.lr_means * self.scene_scale * decay
        out = render(self.model, view.camera, self.pose_of(idx), background=cfg.background,
                     sh_degree=self.active_sh_degree(step), backend=cfg.backend)
        self.strategy.step_pre_backward(out.meta)
        gt = view.target(out.color.device)
        rendered = out.color
        if cfg.exposure == "gain":
            rendered = rendered * exposure_gain(rendered, gt, view.mask_on(gt.device),
                                                cfg.exposure_reg)
        color = view.masked(rendered, gt)
        mask = view.mask_on(gt.device)
        l1 = masked_l1(color, gt, mask)
        loss = l1
        if cfg.lambda_dssim > 0:
            # Over the windows on valid pixels, as the L1: masked ones hold the target and
            # scored 1, so a lens mask shrank the SSIM term by its valid share.
            loss = (1 - cfg.lambda_dssim) * l1 + cfg.lambda_dssim * (
                1 - ssim_fn(color, gt, mask=mask))
        depth_l1 = torch.zeros((), device=self.device)
        if cfg.depth_weight > 0 and view.depth is not None:
            target = view.depth.to(out.depth.device)
            valid = target > 0
            # The mean over the valid pixels by a select and a sum, not a boolean index: no
            # host sync and no scatter in the backward pass (a view without depth adds 0).
            err = torch.where(valid, (out.depth - target).abs(), 0.0)  # [H, W]
            depth_l1 = err.sum() / valid.sum().clamp(min=1)
            loss = loss + cfg.depth_weight * depth_l1
        with torch.no_grad():
            psnr = psnr_fn(rendered.detach().clamp(0, 1), gt, mask=view.mask_on(gt.device))
        # The step's figures in one read: on a GPU each float() waits for the device.
        loss_v, l1_v, depth_v, psnr_v = torch.stack(
            [t.detach().to(torch.float64) for t in (loss, l1, depth_l1, psnr)]).tolist()
        if not math.isfinite(loss_v):
            raise FloatingPointError(
                f"training step {step}: the loss is {loss_v} on view {view.name!r}: a "
                "Gaussian parameter or the view's image/depth is not finite (check the "
                "initial cloud's colours, and lower the learning rates if it happened "
                "after many steps)")
        changes = self.strategy.no_changes()
        # A view that sees no Gaussian renders the background alone: no gradient to take
        # (the reference rasteriser returns a constant; backward would raise).
        if loss.requires_grad:
            loss.backward()
            for opt in self.optimizers.values():
                opt.step()
                opt.zero_grad(set_to_none=True)
            if self.pose_opt is not None:
                self.pose_opt.step()
                self.pose_opt.zero_grad(set_to_none=True)
            changes = self.strategy.step_post_backward(self.model, self.optimizers,
                                                       self.strategy_state, step, out.meta,
                                                       self.generator)
        self.step += 1
        return {"step": step, "loss": loss_v, "l1": l1_v, "depth_l1_m": depth_v, "psnr_db": psnr_v,
                "n_gaussians": len(self.model), **{k: float(v) for k, v in changes.items()}}

    # ---------------------------------------------------------------- the loop
    def train(self, iter_wrapper: IterWrapper | None = None) -> TrainSummary:
        """Run until ``config.iterations`` (or ``max_seconds``), checkpointing on the way.

        ``iter_wrapper(iterable, total, description)`` wraps the step loop (a recipe's
        progress bar); without one a rich bar with loss and PSNR is shown on a terminal.
        """
        cfg = self.cfg
        if self.done is not None:  # resumed a finished run: its model is the result
            return TrainSummary(steps=self.step, n_gaussians=len(self.model),
                                resumed_from=self.resumed_from, history=self.history,
                                **self.done)
        start = self.step
        t0 = time.perf_counter()
        steps = range(start, cfg.iterations)
        stopped = False
        last: dict[str, float] = {"loss": float("nan"), "psnr_db": float("nan")}
        ema = self.ema
        # Views read on demand: the next step's is read while this one trains.
        prefetch = getattr(self.views, "prefetch", None)
        with _progress(iter_wrapper, steps) as (loop, update):
            for _ in loop:
                if prefetch is not None and self.step + 1 < cfg.iterations:
                    prefetch(self.view_index(self.step + 1))
                last = self.train_step()
                for k in ("loss", "psnr_db"):
                    ema[k] = last[k] if k not in ema else 0.9 * ema[k] + 0.1 * last[k]
                update(ema["loss"], ema["psnr_db"], len(self.model))
                if self.step % cfg.log_every == 0 or self.step == cfg.iterations:
                    rec = {**last, "loss_avg": ema["loss"], "psnr_avg_db": ema["psnr_db"]}
                    self.history.append(rec)
                    log.info("step %d/%d loss %.4f PSNR %.2f dB, %d Gaussians", self.step,
                             cfg.iterations, ema["loss"], ema["psnr_db"], len(self.model))
                if (cfg.checkpoint_every and self.checkpoint_dir is not None
                        and self.step % cfg.checkpoint_every == 0):
                    self.save_checkpoint()
                if cfg.max_seconds is not None and time.perf_counter() - t0 > cfg.max_seconds:
                    stopped = self.step < cfg.iterations
                    log.warning("stopping at step %d: time limit of %.0f s reached",
                                self.step, cfg.max_seconds)
                    break
        seconds = time.perf_counter() - t0
        done = self.step - start
        outcome = {"seconds": seconds, "iters_per_s": done / seconds if seconds > 0 else 0.0,
                   "final_loss": ema.get("loss", last["loss"]),
                   "final_psnr_db": ema.get("psnr_db", last["psnr_db"]),
                   "stopped_early": stopped}
        if self.checkpoint_dir is not None:
            self.save_checkpoint(finished=True, outcome={
                **outcome, "settings": config_digest(cfg, whole=True)})
        return TrainSummary(steps=self.step, n_gaussians=len(self.model),
                            resumed_from=self.resumed_from, history=self.history, **outcome)

    # ---------------------------------------------------------------- checkpoints
    def checkpoint_path(self) -> Path:
        if self.checkpoint_dir is None:
            raise ValueError("this trainer has no checkpoint folder")
        return self.checkpoint_dir / CHECKPOINT_NAME

    def state_dict(self, finished: bool = False,
                   outcome: dict[str, Any] | None = None) -> dict[str, Any]:
        return {
            "finished": finished,
            "outcome": outcome,
            "format": "toolkit-splat-checkpoint/1",
            "step": self.step,
            "config_digest": config_digest(self.cfg),
            "data_key": self.data_key,
            "params": self.model.state(),
            "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
            "strategy_state": self.strategy_state,
            "generator": self.generator.get_state(),
            "pose": None if self.pose is None else self.pose.state_dict(),
            "pose_opt": None if self.pose_opt is None else self.pose_opt.state_dict(),
            "history": self.history,
            "ema": dict(self.ema),
        }

    def save_checkpoint(self, finished: bool = False,
                        outcome: dict[str, Any] | None = None) -> Path:
        """Write the checkpoint atomically (a kill mid-write leaves the previous one).

        ``finished`` marks the end of a training run (with its ``outcome``: time, final
        loss and PSNR, early stop): ``resume`` then takes its model as the result instead
        of training again (a stage interrupted while evaluating).
        """
        path = self.checkpoint_path()
        with digested_write(path, _MAGIC) as out:
            torch.save(self.state_dict(finished, outcome), out)
        return path

    def _read_checkpoint(self) -> dict[str, Any] | None:
        """The checkpoint's contents, or None (with a warning) where its digest does not
        match what was written or it has none."""
        path = self.checkpoint_path()
        with open(path, "rb") as fh:
            problem = digest_problem(fh, _MAGIC, _OLDER)
            if problem is not None:
                log.warning("ignoring checkpoint %s (%s); training from the start", path,
                            problem)
                return None
            # The zip as a file of its own (offsets from 0): torch.load seeks in it, and
            # reading a file from where it stands is no documented guarantee of it.
            ckpt = torch.load(FileTail(fh), map_location="cpu", weights_only=False)
        if not isinstance(ckpt, dict):
            raise ValueError("not a checkpoint of this trainer")
        return ckpt

    def load_state_dict(self, ckpt: dict[str, Any]) -> None:
        """Take the state of ``ckpt`` (``state_dict``'s), all or nothing: every part is read
        into new objects and checked against what it belongs to first, and the trainer
        takes them only once all are, so a checkpoint that fails part way (a missing or
        misshapen optimiser, strategy or pose state) raises and leaves the trainer as it
        was. Half taken, ``resume`` went on "from the start" with the checkpoint's
        parameters and the fresh rest."""
        if ckpt.get("config_digest") != config_digest(self.cfg):
            raise ValueError("checkpoint was written with different training settings")
        if ckpt.get("data_key", "") != self.data_key:
            raise ValueError("checkpoint was written for different input data")
        model = GaussianModel.from_state(ckpt["params"])
        params = {k: nn.Parameter(model.params[k].detach().to(self.device))
                  for k in PARAM_NAMES}
        optimizers = self._make_optimizers(params)
        for k, o in optimizers.items():
            o.load_state_dict(ckpt["optimizers"][k])
            _check_adam_state(o, f"optimiser {k}")
        # Loaded on the CPU (map_location) and moved to this trainer's device: a GPU run's
        # checkpoint resumes on the CPU and back.
        strategy_state = {k: v.to(self.device) if isinstance(v, Tensor) else v
                          for k, v in dict(ckpt["strategy_state"]).items()}
        fresh = self.strategy.initialize_state(len(model), self.scene_scale, self.device)
        for k, v in fresh.items():
            got = strategy_state.get(k)
            if isinstance(v, Tensor) and not (isinstance(got, Tensor)
                                              and got.shape == v.shape):
                raise ValueError(f"strategy state {k!r} is not a tensor of shape "
                                 f"{list(v.shape)} (one per Gaussian)")
        generator_state = ckpt["generator"]
        torch.Generator().set_state(generator_state)  # raises on a foreign state
        pose = pose_opt = None
        if self.pose is not None:
            if ckpt.get("pose") is None or ckpt.get("pose_opt") is None:
                raise ValueError("checkpoint holds no pose corrections, but pose refinement "
                                 "is on")
            pose = PoseRefinement(len(self.views), self.device)
            pose.load_state_dict(ckpt["pose"])  # strict: names and shapes
            pose_opt = self._make_pose_opt(pose)
            pose_opt.load_state_dict(ckpt["pose_opt"])
            _check_adam_state(pose_opt, "pose optimiser")
        history = list(ckpt.get("history", []))
        ema = dict(ckpt.get("ema") or {})
        step = int(ckpt["step"])
        # Everything is read: from here on nothing raises.
        self.model.replace_params(params)
        self.optimizers = optimizers
        self.strategy_state = strategy_state
        self.generator.set_state(generator_state)
        if pose is not None:
            self.pose, self.pose_opt = pose, pose_opt
        self.history, self.ema = history, ema
        self.step = self.resumed_from = step

    def resume(self) -> bool:
        """Continue from the checkpoint in ``checkpoint_dir`` if there is a usable one."""
        if self.checkpoint_dir is None:
            return False
        remove_leftover_temps(self.checkpoint_path())  # of a save killed half way
        if not self.checkpoint_path().exists():
            return False
        try:
            ckpt = self._read_checkpoint()
            if ckpt is None:
                return False
            outcome = ckpt.get("outcome") or {}
            if ckpt.get("finished") and outcome.get("settings") != config_digest(
                    self.cfg, whole=True):
                # Another step count or time limit asks for another training, not more of
                # this one (the learning rates decay over the whole run).
                log.info("checkpoint %s is of a finished run with other settings; training "
                         "afresh", self.checkpoint_path())
                return False
            self.load_state_dict(ckpt)
        except Exception as exc:  # noqa: BLE001 - a truncated or foreign file: start afresh
            # load_state_dict takes all or nothing: the trainer is as it was made
            log.warning("ignoring checkpoint %s (%s: %s); training from the start",
                        self.checkpoint_path(), type(exc).__name__, exc)
            return False
        if ckpt.get("finished"):
            self.done = {k: v for k, v in outcome.items() if k != "settings"}
            log.info("training had finished (step %d) in %s; its model is the result",
                     self.step, self.checkpoint_path())
            return True
        log.info("resumed training at step %d from %s", self.step, self.checkpoint_path())
        return True


def _check_adam_state(opt: torch.optim.Optimizer, what: str) -> None:
    """Raise where a loaded Adam state's moments do not match their parameter's shape
    (``Optimizer.load_state_dict`` checks only the parameter count: a checkpoint with a
    misshapen moment was resumed)."""
    for group in opt.param_groups:
        for p in group["params"]:
            for name, v in opt.state.get(p, {}).items():
                if name != "step" and isinstance(v, Tensor) and v.shape != p.shape:
                    raise ValueError(f"{what}: {name} is {list(v.shape)}, its parameter "
                                     f"{list(p.shape)}")


def _default_data_key(model: GaussianModel, views: Sequence[TrainView]) -> str:
    """What the trainer sees of its inputs: the model's size, the first view's image size
    and the views' names and poses."""
    h = hashlib.sha256()
    h.update(f"{len(model)}:{model.max_sh_degree}:{tuple(views[0].image.shape)}".encode())
    for name, T in zip(view_names(views), view_poses(views), strict=True):
        h.update(name.encode())
        h.update(np.ascontiguousarray(T, dtype=np.float64).tobytes())
    return h.hexdigest()[:16]


class _progress:
    """Context manager giving (loop, update) for the step loop."""

    def __init__(self, iter_wrapper: IterWrapper | None, steps: range) -> None:
        self.iter_wrapper = iter_wrapper
        self.steps = steps
        self.bar: Any = None

    def __enter__(self) -> tuple[Iterable[int], Callable[[float, float, int], None]]:
        if self.iter_wrapper is not None:
            return self.iter_wrapper(self.steps, len(self.steps), "splat training"), _noop
        if not sys.stderr.isatty():
            return self.steps, _noop
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )

        self.bar = Progress(
            TextColumn("splat"), BarColumn(), MofNCompleteColumn(),
            TextColumn("loss {task.fields[loss]:.4f}  PSNR {task.fields[psnr]:.2f} dB  "
                       "{task.fields[n]} G"),
            TimeElapsedColumn(), TimeRemainingColumn(), transient=True)
        self.bar.__enter__()
        task = self.bar.add_task("splat", total=len(self.steps), loss=float("nan"),
                                 psnr=float("nan"), n=0)

        def update(loss: float, psnr: float, n: int) -> None:
            self.bar.update(task, advance=1, loss=loss, psnr=psnr, n=n)

        return self.steps, update

    def __exit__(self, *exc: object) -> None:
        if self.bar is not None:
            self.bar.__exit__(*exc)


def _noop(*_args: object) -> None:
    return None


# -------------------------------------------------------------------- evaluation
def render_view(model: GaussianModel, camera: PinholeCamera, T_camera_world: np.ndarray,
                background: tuple[float, float, float] = (0.0, 0.0, 0.0),
                backend: str = "auto", sh_degree: int | None = None) -> RenderOutput:
    """A no-grad render for evaluation and pictures."""
    with torch.no_grad():
        return render(model, camera, T_camera_world, background=background, backend=backend,
                      sh_degree=sh_degree)


def evaluate_views(model: GaussianModel, views: Sequence[TrainView], backend: str = "auto",
                   background: tuple[float, float, float] = (0.0, 0.0, 0.0),
                   gt_depths: Sequence[np.ndarray | None] | None = None,
                   on_render: Callable[[int, TrainView, RenderOutput], None] | None = None) -> (
                       dict[str, Any]):
    """Mean PSNR / SSIM over ``views`` (and depth errors where ground truth is given).

    ``on_render(i, view, output)`` sees every render (to save pictures without rendering
    twice).
    """
    ps, pm, ss, d_abs, d_sq, d_n, d_valid = [], [], [], 0.0, 0.0, 0, 0
    for i, v in enumerate(views):
        out = render_view(model, v.camera, v.T_camera_world, background, backend)
        if on_render is not None:
            on_render(i, v, out)
        dev = out.color.device
        gt = v.target(dev)
        pred = v.masked(out.color.clamp(0, 1), gt)
        ps.append(float(psnr_fn(pred, gt, mask=v.mask_on(dev))))
        # The held-out image's exposure is not known to the model: scored again with the
        # per-channel gain that fits the render to it best.
        g = exposure_gain(pred, gt, v.mask_on(dev))
        pm.append(float(psnr_fn(v.masked((pred * g).clamp(0, 1), gt), gt, mask=v.mask_on(dev))))
        ss.append(float(ssim_fn(pred, gt, mask=v.mask_on(dev))))
        gd = gt_depths[i] if gt_depths is not None else None
        if gd is not None:
            gdt = _tensor(gd, dev).to(torch.float32)
            m = (gdt > 0) & (out.alpha > 0.5)
            d_valid += int((gdt > 0).sum())
            if bool(m.any()):
                e = (out.depth - gdt)[m]
                d_abs += float(e.abs().sum())
                d_sq += float((e * e).sum())
                d_n += int(m.sum())
    res: dict[str, Any] = {
        "views": len(views),
        "psnr_db": float(np.mean(ps)) if ps else math.nan,
        "ssim": float(np.mean(ss)) if ss else math.nan,
        "psnr_db_per_view": ps,
        "psnr_exposure_matched_db": float(np.mean(pm)) if pm else math.nan,
    }
    if d_n:
        res["depth_mae_m"] = d_abs / d_n
        res["depth_rmse_m"] = math.sqrt(d_sq / d_n)
        res["depth_pixels"] = d_n
    if d_valid:
        # The MAE is over the pixels the render covers (alpha > 0.5): the share of the
        # ground truth's pixels that is says what it leaves out (the empty ones).
        res["depth_coverage"] = d_n / d_valid
    return res


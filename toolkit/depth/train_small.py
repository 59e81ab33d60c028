"""Train the project's small monocular depth network on simulator renders; export ONNX.

    python -m toolkit.depth.train_small                # 45 min: runs/train_small/small-depth.onnx

    python -m toolkit.depth.train_small --init runs/train_small/small-depth.onnx \
        --height 240 --width 320 --lr 0.0003 --minutes 25 --out OUT.onnx   # fine-tune

(the shipped ``datasets/models/small-depth.onnx`` was made so, the first run at 160x120,
the second fine-tuning it at 320x240 with ``--out`` pointing there: the default leaves the
shipped file and its card alone)

A compact U-Net (1.09 M parameters, see ``make_model``) predicts log depth from one
RGB image (160x120 by default). The loss is scale-invariant (Eigen et al. 2014 with lambda = 1,
plus a multi-scale gradient matching term on log depth as in MiDaS), so the network
learns shape and relative depth, not metric scale: its output is ``relative_depth``
(exp of the prediction), to be scaled by the lidar like Depth Anything's relative output.
The exported file carries its preprocessing in ONNX metadata (kind, input size,
mean/std), which ``OnnxDepthBackend`` reads, and a model card is written next to it.

Training images come from ``toolkit.sim`` houses whose seeds differ from the evaluation
house (seed 0, the quickstart's), rendered from poses along each house's robot route with
random yaw, height and pitch changes so that views are not all straight down the corridor.
Renders are cached (``--cache``), so a second training run starts at once.

The shipped file was made by this module's defaults (45 minutes, 40 houses), then
fine-tuned at 320x240 several times on more houses, on a 2-core machine; its card
(``datasets/models/small-depth.md``, written next to every model as ``<model>.md``) lists
every run of that chain with its command and figures.

    python -m toolkit.depth.train_small --eval-only MODEL.onnx \
        --sequence runs/quickstart/simulate/sequence

evaluates a model against a simulated sequence's ground-truth depth (per-image median
scale, the oracle; the ``fuse`` stage measures the lidar-scaled figures).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from toolkit.cli_types import positive_float, positive_int
from toolkit.depth.onnx_backend import IMAGENET_MEAN, IMAGENET_STD
from toolkit.errors import InputError
from toolkit.io.atomic import atomic_write_text


@dataclass
class TrainConfig:
    out: Path = Path("runs/train_small/small-depth.onnx")
    train_seeds: tuple[int, ...] = tuple(range(101, 141))  # 40 houses, none of them seed 0
    val_seed: int = 0  # the evaluation house: never trained on
    images_per_house: int = 150
    val_images: int = 60
    height: int = 120  # network input (4:3 like the 640x480 camera)
    width: int = 160
    # Renders are made at render_factor x the input size and shrunk with the same cubic
    # resize the ONNX backend applies to 640x480 frames (point-sampled renders alias
    # differently). At 320x240 (the shipped network's input) the two are the same 2x
    # shrink; at the first run's 160x120 the frames are shrunk 4x at run time, so they
    # hold a little more fine detail than these renders.
    render_factor: int = 2
    # Training crops (same pixel scale). Off by default: trained on 96x128 crops of the
    # 120x160 frames (with stronger colour changes) for 25 minutes, the network was worse
    # on the quickstart sequence (oracle-scaled AbsRel 0.095 against 0.077 of the previous
    # 96x128 full-frame model). A camera fixed on a robot puts the floor and the horizon at
    # the same rows in every frame; random crops take that cue away.
    crop_height: int | None = None
    crop_width: int | None = None
    # Channels at 1/2 .. 1/32 resolution. The wider deep stages (48/64/96 before) cost
    # little: their maps are small, so an iteration took 10 % longer for 1.8x the weights.
    widths: tuple[int, ...] = (16, 32, 64, 96, 128)
    batch: int = 8
    lr: float = 2e-3
    warmup_iters: int = 50
    minutes: float = 45.0  # training time budget, wall clock (data generation not included)
    max_iters: int = 100000
    grad_weight: float = 0.5
    threads: int = 2
    seed: int = 0
    cache: Path | None = Path("datasets/generated/depth_train")
    # Training state (weights, optimiser, iteration, time used) is saved every
    # checkpoint_minutes next to ``out`` (``<out>.ckpt``); a run started again with the
    # same ``out`` continues from it within the same time budget. 0: no checkpoints.
    checkpoint_minutes: float = 5.0
    # Fine-tuning: start from the weights of an exported model (its BatchNorm folded into
    # the convolutions, as the ONNX file holds them, so this run trains without it),
    # usually at a larger input size than it was trained at. From scratch, the 1.09 M
    # network at 160x120 ran 8 iterations/s and at 320x240 under 2: training at the small
    # size and then fine-tuning at the large one buys the sharper depth edges for a
    # fraction of the time (the shipped model; its card).
    init: Path | None = None
    log: list = field(default_factory=list)


# ---------------------------------------------------------------------------- data


def render_set(seed: int, n: int, height: int, width: int, rng: np.random.Generator,
               factor: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """``n`` renders of house ``seed``: images [n, H, W, 3] uint8, depth [n, H, W] float32.

    With ``factor`` > 1 the camera renders at ``factor`` x (H, W); images are shrunk with
    cv2's cubic resize (what ``OnnxDepthBackend`` does to full frames) and depth is
    subsampled (no averaging: a mean across an object border is a depth nothing has).
    """
    import cv2

    from toolkit.geometry import se3
    from toolkit.sim.people import primitives_at
    from toolkit.sim.sensors import CameraRenderer, CameraSpec
    from toolkit.sim.simulate import SimConfig, build_world

    world = build_world(SimConfig(seed=seed, n_heldout=0))
    spec = CameraSpec()
    cam = spec.camera().scaled(width * factor, height * factor)
    rend = CameraRenderer(world.scene, cam)
    T_bc = world.rig.T_base_camera
    ts = rng.uniform(0, world.path.duration, n)
    imgs = np.empty((n, height, width, 3), np.uint8)
    depth = np.empty((n, height, width), np.float32)
    for k, t in enumerate(ts):
        T_wb = world.path.T_world_base(np.array([t]))[0]
        yaw = rng.uniform(-0.6, 0.6)
        pitch = rng.uniform(-0.15, 0.15)
        c, s = np.cos(yaw), np.sin(yaw)
        Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        cp, sp = np.cos(pitch), np.sin(pitch)
        Ry = np.array([[cp, 0, sp], [0, 1.0, 0], [-sp, 0, cp]])
        jitter = se3(Rz @ Ry, [0.0, rng.uniform(-0.2, 0.2), rng.uniform(-0.15, 0.4)])
        img = rend.render(T_wb @ jitter @ T_bc, primitives_at(world.walkers, float(t)),
                          spec.noise_std, rng)
        if factor > 1:
            imgs[k] = cv2.resize(img.rgb, (width, height), interpolation=cv2.INTER_CUBIC)
            o = factor // 2  # the sample nearest the centre of each output pixel
            depth[k] = img.depth[o::factor, o::factor]
        else:
            imgs[k] = img.rgb
            depth[k] = img.depth
    return imgs, depth


def load_or_render(seed: int, n: int, cfg: TrainConfig) -> tuple[np.ndarray, np.ndarray]:
    """``render_set`` through an on-disk cache keyed by everything that changes the pixels."""
    key = f"house{seed}_n{n}_{cfg.height}x{cfg.width}_f{cfg.render_factor}_s{cfg.seed}.npz"
    path = Path(cfg.cache) / key if cfg.cache else None
    if path is not None and path.is_file():
        with np.load(path) as z:
            return z["images"], z["depth"]
    # One generator per house, so a cached house and a fresh one give the same renders.
    house_rng = np.random.default_rng([cfg.seed, seed])
    imgs, depth = render_set(seed, n, cfg.height, cfg.width, house_rng, cfg.render_factor)
    if path is not None:
        from toolkit.io.atomic import atomic_path

        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.savez(f, images=imgs, depth=depth)
    return imgs, depth


def training_set_bytes(cfg: TrainConfig) -> int:
    """Memory the training renders take: RGB uint8 and float32 depth per image."""
    return len(cfg.train_seeds) * cfg.images_per_house * cfg.height * cfg.width * (3 + 4)


def _available_bytes() -> int | None:
    """MemAvailable of /proc/meminfo (Linux); None where there is none."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        return None
    return None


def load_training_set(cfg: TrainConfig) -> tuple[np.ndarray, np.ndarray]:
    """Every training house's renders in two arrays ([N, H, W, 3] uint8, [N, H, W] float32),
    filled house by house: concatenating a list of them needed twice the memory (160 houses
    at 320x240, 13 GB of renders, were killed at 24 GB)."""
    need = training_set_bytes(cfg)
    free = _available_bytes()
    if free is not None and need > 0.9 * free:
        raise MemoryError(
            f"{len(cfg.train_seeds)} houses x {cfg.images_per_house} renders at "
            f"{cfg.width}x{cfg.height} take {need / 1e9:.1f} GB of memory and "
            f"{free / 1e9:.1f} GB is available: train on fewer --houses (or a smaller "
            "--images-per-house)")
    n = len(cfg.train_seeds) * cfg.images_per_house
    X = np.empty((n, cfg.height, cfg.width, 3), np.uint8)  # [N, H, W, 3]
    D = np.empty((n, cfg.height, cfg.width), np.float32)  # [N, H, W]
    k = 0
    for seed in cfg.train_seeds:
        imgs, depth = load_or_render(seed, cfg.images_per_house, cfg)
        X[k:k + len(imgs)], D[k:k + len(imgs)] = imgs, depth
        k += len(imgs)
    return X, D


# ---------------------------------------------------------------------------- model


def make_model(widths: tuple[int, ...] = TrainConfig.widths, norm: bool = True) -> object:
    """The U-Net: stride-2 residual stages at 1/2 .. 1/32 resolution, an image-wide
    context vector at the bottom, a decoder that upsamples bilinearly and concatenates
    the skips, and a thin full-resolution refinement that sees the input pixels.

    Why this shape: relative depth of a room is mostly layout (which wall is far), which
    needs image-wide context (the global average, broadcast back) that stacked 3x3
    convolutions on a 160x120 input do not reach. The costly layers of a plain U-Net are
    the ones at full resolution (two thirds of the old one's multiply-adds), so here the
    wide features start at 1/2 resolution and only 8 channels run at full resolution,
    enough to put depth edges where the image edges are: blurred edges become flying
    pixels that the fusion has to drop.

    ``norm`` False: no BatchNorm, every convolution with a bias (the layout of an exported
    model, whose BatchNorm the exporter folded into the convolutions; ``load_onnx_weights``).
    """
    import torch
    from torch import nn

    def conv_bn(cin: int, cout: int, stride: int = 1) -> list[nn.Module]:
        if not norm:
            return [nn.Conv2d(cin, cout, 3, stride, 1)]
        return [nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout)]

    def cbr(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
        return nn.Sequential(*conv_bn(cin, cout, stride), nn.ReLU(inplace=True))

    class Res(nn.Module):
        def __init__(self, c: int) -> None:
            super().__init__()
            self.a = cbr(c, c)
            self.b = nn.Sequential(*conv_bn(c, c))

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return torch.relu(x + self.b(self.a(x)))

    class SmallDepthUNet(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            w = list(widths)
            fine = 8
            self.down = nn.ModuleList([nn.Sequential(cbr(3 if i == 0 else w[i - 1], w[i], 2),
                                                     Res(w[i])) for i in range(len(w))])
            self.context = nn.Sequential(nn.Conv2d(w[-1], w[-1], 1), nn.ReLU(inplace=True))
            self.up = nn.ModuleList([cbr(w[i + 1] + w[i], w[i]) for i in range(len(w) - 1)])
            self.fine_in = cbr(3, fine)
            self.fine = cbr(w[0] + fine, fine)
            self.head = nn.Conv2d(fine, 1, 3, padding=1)

        def forward(self, x: torch.Tensor) -> torch.Tensor:  # [B, 3, H, W] -> [B, 1, H, W]
            f = self.fine_in(x)  # [B, 8, H, W]
            skips = []
            for d in self.down:
                x = d(x)
                skips.append(x)
            # [B, C, 1, 1] image-wide context added everywhere at the coarsest level
            x = x + self.context(nn.functional.adaptive_avg_pool2d(x, 1))
            for i in reversed(range(len(self.up))):
                s = skips[i]
                x = nn.functional.interpolate(x, size=s.shape[-2:], mode="bilinear",
                                              align_corners=False)
                x = self.up[i](torch.cat([x, s], 1))
            x = nn.functional.interpolate(x, size=f.shape[-2:], mode="bilinear",
                                          align_corners=False)
            return self.head(self.fine(torch.cat([x, f], 1)))  # log depth + unknown constant

    return SmallDepthUNet()


def load_onnx_weights(model: object, path: Path) -> None:
    """Copy the convolution weights of an exported small-depth model (``path``, .onnx)
    into ``model`` (``make_model(widths, norm=False)``), then check that both give the same
    depth on a random image. The exporter folded each BatchNorm into its convolution and
    keeps the convolutions in the order the forward pass runs them."""
    import onnx
    import onnxruntime as ort
    import torch
    from onnx import numpy_helper

    try:
        m = onnx.load(str(path))
    except Exception as e:  # protobuf's DecodeError / ParseError, or an OSError
        raise InputError(f"{path}: not an ONNX model ({type(e).__name__}: {e}); --init takes "
                         "a .onnx file exported by this script") from e
    nodes = [n for n in m.graph.node if n.op_type == "Conv"]
    if not nodes:  # protobuf reads many a small non-ONNX file as an empty model
        raise InputError(f"{path}: not an ONNX model with convolutions; --init takes a .onnx "
                         "file exported by this script")
    init = {i.name: numpy_helper.to_array(i) for i in m.graph.initializer}
    convs: list[torch.nn.Conv2d] = []
    hooks = [c.register_forward_hook(lambda mod, _i, _o: convs.append(mod))
             for c in model.modules() if isinstance(c, torch.nn.Conv2d)]  # type: ignore
    model.eval()  # type: ignore[attr-defined]
    x = torch.from_numpy(np.random.default_rng(0).normal(size=(1, 3, 48, 64)).astype(
        np.float32))
    with torch.no_grad():
        model(x)  # type: ignore[operator]
    for h in hooks:
        h.remove()
    shapes = [tuple(init[n.input[1]].shape) for n in nodes]
    if len(nodes) != len(convs) or any(
            s != tuple(c.weight.shape) for s, c in zip(shapes, convs, strict=False)):
        raise InputError(f"{path}: its {len(nodes)} convolutions (kernels {shapes[:3]} ...) "
                         f"do not match this network's {len(convs)} (kernels "
                         f"{[tuple(c.weight.shape) for c in convs[:3]]} ...): give the "
                         "--widths it was trained with (its card names them)")
    with torch.no_grad():
        for node, conv in zip(nodes, convs, strict=True):
            conv.weight.copy_(torch.from_numpy(init[node.input[1]].copy()))
            if conv.bias is None or len(node.input) < 3:
                raise InputError(f"{path}: convolution {node.name} has no bias: not an "
                                 "export of toolkit.depth.train_small")
            conv.bias.copy_(torch.from_numpy(init[node.input[2]].copy()))
        ours = torch.exp(model(x)).numpy()  # type: ignore[operator]
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    theirs = sess.run(None, {sess.get_inputs()[0].name: x.numpy()})[0]
    err = float(np.max(np.abs(ours / theirs - 1)))
    if err > 1e-3:
        raise InputError(f"{path}: the network rebuilt from its weights differs from it by "
                         f"{100 * err:.2g} %: not an export of this architecture")


class ExportWrapper:
    """exp() of the log-depth output: the ONNX file outputs relative depth directly."""

    @staticmethod
    def wrap(model: object) -> object:
        import torch

        class Exp(torch.nn.Module):
            def __init__(self, m: torch.nn.Module) -> None:
                super().__init__()
                self.m = m

            def forward(self, x: torch.Tensor) -> torch.Tensor:
                return torch.exp(self.m(x))

        return Exp(model)


# ---------------------------------------------------------------------------- loss


def si_loss(pred_log: object, depth: object, grad_weight: float = 0.5) -> object:
    """Scale-invariant log loss (lambda = 1) + multi-scale gradient matching, masked.

    Both are invariant to adding a constant to ``pred_log``: the network is never asked
    for a metric scale it cannot know from one image. The gradient term (MiDaS) compares
    the spatial derivatives of the log-depth residual at 4 scales, which is what makes
    depth edges sharp and planes flat; the first term alone tolerates smooth blur.
    """
    import torch

    valid = depth > 0  # [B, 1, H, W]
    gt_log = torch.log(torch.where(valid, depth, torch.ones_like(depth)))
    d = (pred_log - gt_log) * valid
    n = valid.sum((1, 2, 3)).clamp(min=1)
    mean = d.sum((1, 2, 3)) / n
    si = (d * d).sum((1, 2, 3)) / n - mean * mean
    loss = si.mean()
    if grad_weight > 0:
        r = (d - mean.view(-1, 1, 1, 1)) * valid
        m = valid.float()
        g = 0.0
        for _ in range(4):
            gx = (r[..., 1:] - r[..., :-1]).abs() * m[..., 1:] * m[..., :-1]
            gy = (r[..., 1:, :] - r[..., :-1, :]).abs() * m[..., 1:, :] * m[..., :-1, :]
            g = g + (gx.sum() + gy.sum()) / m.sum().clamp(min=1)
            r = torch.nn.functional.avg_pool2d(r, 2)
            m = (torch.nn.functional.avg_pool2d(m, 2) > 0.99).float()
            r = r * m
        loss = loss + grad_weight * g
    return loss


# ---------------------------------------------------------------------------- train


def _to_input(imgs: np.ndarray) -> object:
    import torch

    x = imgs.astype(np.float32) / 255.0
    x = (x - np.array(IMAGENET_MEAN, np.float32)) / np.array(IMAGENET_STD, np.float32)
    return torch.from_numpy(np.ascontiguousarray(x.transpose(0, 3, 1, 2)))


def augment(imgs: np.ndarray, depth: np.ndarray, ch: int | None, cw: int | None,
            rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Flips and mild colour and exposure changes, optionally random crops.

    [B, H, W, 3] uint8 and [B, H, W] -> [B, ch, cw, 3] uint8 and [B, ch, cw] (crops keep
    the pixel scale). The changes stay mild because every house is lit by the same
    simulator: strong gamma and exposure changes may cost accuracy on the evaluation house
    (the run with crops and gamma 0.8-1.25, exposure 0.7-1.3 and noise was the worse one;
    the two changes were not tested apart) and buy robustness it does not need.
    """
    B, H, W = depth.shape
    ch, cw = ch or H, cw or W
    out_i = np.empty((B, ch, cw, 3), np.uint8)
    out_d = np.empty((B, ch, cw), np.float32)
    for b in range(B):
        y, x = rng.integers(0, H - ch + 1), rng.integers(0, W - cw + 1)
        im = imgs[b, y:y + ch, x:x + cw].astype(np.float32)
        de = depth[b, y:y + ch, x:x + cw]
        if rng.random() < 0.5:
            im, de = im[:, ::-1], de[:, ::-1]
        im = im * rng.uniform(0.92, 1.08, 3) * rng.uniform(0.8, 1.2)  # white balance, exposure
        out_i[b] = np.clip(im, 0, 255).astype(np.uint8)
        out_d[b] = de
    return out_i, out_d


def evaluate(model: object, imgs: np.ndarray, depth: np.ndarray) -> dict[str, float]:
    """AbsRel, RMSE and delta1 after the per-image median scale (the oracle scale)."""
    import torch

    from toolkit.eval.depth import ErrorAccumulator

    acc = ErrorAccumulator()
    model.eval()  # type: ignore[attr-defined]
    with torch.no_grad():
        for i in range(0, len(imgs), 16):
            pred = torch.exp(model(_to_input(imgs[i:i + 16]))).numpy()[:, 0]  # type: ignore
            for p, g in zip(pred, depth[i:i + 16], strict=True):
                ok = g > 0
                s = np.median(g[ok] / p[ok])
                acc.add(p * s, g)
    e = acc.result()
    return {"absrel": e.absrel, "rmse_m": e.rmse_m, "delta1": e.delta1}


def sequence_problem(sequence: Path) -> str | None:
    """Why ``sequence`` cannot be evaluated against (None: it can); asked before a training
    run, which would otherwise fail only after its model had replaced ``--out``."""
    from toolkit.io.sequence import SequenceFormatError, read_sequence

    try:
        seq = read_sequence(sequence)
    except (SequenceFormatError, FileNotFoundError, ValueError) as e:
        return str(e)
    if seq.groundtruth is None or seq.groundtruth.depth_paths is None:
        return f"{sequence}: no ground-truth depth to evaluate against"
    return None


def evaluate_sequence(model_path: Path, sequence: Path, every: int = 4, threads: int = 2,
                      max_depth: float = 10.0) -> dict[str, float | str]:
    """A model run through ``OnnxDepthBackend`` (the depth stage's code path, full
    640x480 frames) on every ``every``-th frame of a simulated sequence, against its
    ground-truth depth after the per-image median scale (the oracle scale: the lidar-scaled
    figures, which add the scale estimator's own error, come from the ``fuse`` stage).
    Figures in float (``frames`` an int), and ``loadavg`` as text."""
    from toolkit.depth.onnx_backend import OnnxDepthBackend, OnnxDepthConfig
    from toolkit.eval.depth import ErrorAccumulator
    from toolkit.io.sequence import read_sequence

    seq = read_sequence(sequence)
    if seq.groundtruth is None or seq.groundtruth.depth_paths is None:
        raise InputError(f"{sequence}: no ground-truth depth to evaluate against")
    be = OnnxDepthBackend(OnnxDepthConfig(model=model_path, threads=threads))
    acc = ErrorAccumulator()
    lat, cpu = [], []
    for i in range(0, len(seq.frames), every):
        rgb = seq.frames[i].image
        c0 = time.process_time()
        pred = be.predict(rgb)
        cpu.append(time.process_time() - c0)
        lat.append(pred.latency_s)
        gt = seq.groundtruth.depth(i)
        z = pred.as_depth()
        ok = (gt > 0) & (gt <= max_depth) & np.isfinite(z)
        s = np.median(gt[ok] / z[ok])
        acc.add(z * s, gt, max_depth=max_depth)
    e = acc.result()
    return {"absrel": e.absrel, "rmse_m": e.rmse_m, "delta1": e.delta1, "frames": len(lat),
            "network_ms_median": 1000 * float(np.median(lat)),
            "predict_cpu_ms_median": 1000 * float(np.median(cpu)),
            "loadavg": " / ".join(f"{v:.1f}" for v in os.getloadavg())}


def train(cfg: TrainConfig) -> dict:
    import torch

    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    rng = np.random.default_rng(cfg.seed)
    t0, c0 = time.perf_counter(), time.process_time()
    ckpt = checkpoint_path(cfg.out)
    state = None
    if cfg.checkpoint_minutes > 0 and ckpt.is_file():
        state = torch.load(ckpt, weights_only=False)
        # Before the renders: a checkpoint that cannot be resumed should not cost them.
        _check_resumable(ckpt, state["config"], cfg)
    model = make_model(cfg.widths, norm=cfg.init is None)
    if cfg.init is not None and state is None:
        load_onnx_weights(model, Path(cfg.init))  # before the renders, like the checkpoint
    X, D = load_training_set(cfg)
    Xv, Dv = load_or_render(cfg.val_seed, cfg.val_images, cfg)
    t_data = time.perf_counter() - t0
    print(f"{len(X)} training and {len(Xv)} validation images ready in {t_data:.0f} s "
          f"(CPU {time.process_time() - c0:.0f} s)", flush=True)
    if cfg.init is not None and state is None:
        print(f"fine-tuning {cfg.init} at {cfg.width}x{cfg.height}: "
              f"{evaluate(model, Xv, Dv)} before", flush=True)
    n_params = sum(p.numel() for p in model.parameters())  # type: ignore[attr-defined]
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=1e-4)  # type: ignore
    budget = cfg.minutes * 60.0
    it, used, used_cpu = 0, 0.0, 0.0
    if state is not None:
        model.load_state_dict(state["model"])  # type: ignore[attr-defined]
        opt.load_state_dict(state["opt"])
        rng.bit_generator.state = state["rng"]
        it, used, used_cpu = state["iteration"], state["seconds"], state["cpu_seconds"]
        print(f"resuming {ckpt} at iteration {it} ({used / 60:.1f} of {cfg.minutes:g} min)",
              flush=True)
    t1, c1 = time.perf_counter() - used, time.process_time() - used_cpu
    t_ckpt = time.perf_counter()
    loads = [os.getloadavg()[0]]
    losses: list[float] = []
    while it < cfg.max_iters:
        elapsed = time.perf_counter() - t1
        if elapsed > budget:
            break
        if 0 < cfg.checkpoint_minutes * 60 < time.perf_counter() - t_ckpt:
            save_checkpoint(ckpt, cfg, model, opt, rng, it, elapsed, time.process_time() - c1)
            t_ckpt = time.perf_counter()
        # Cosine decay over the time budget, not the iteration count: the machine's speed
        # (shared cores) decides how many iterations fit. A short warm-up keeps the first
        # steps of Adam on fresh BatchNorm statistics from throwing the weights off.
        warm = min(1.0, (it + 1) / cfg.warmup_iters)
        for g in opt.param_groups:
            g["lr"] = warm * cfg.lr * 0.5 * (1 + np.cos(np.pi * min(1.0, elapsed / budget)))
        idx = rng.integers(0, len(X), cfg.batch)
        imgs, dep = augment(X[idx], D[idx], cfg.crop_height, cfg.crop_width, rng)
        model.train()  # type: ignore[attr-defined]
        pred = model(_to_input(imgs))  # type: ignore[operator]
        loss = si_loss(pred, torch.from_numpy(np.ascontiguousarray(dep))[:, None],
                       cfg.grad_weight)
        opt.zero_grad()
        loss.backward()  # type: ignore[attr-defined]
        opt.step()
        losses.append(float(loss.detach()))  # type: ignore[attr-defined]
        it += 1
        if it % 100 == 0:
            loads.append(os.getloadavg()[0])
            print(f"iter {it} loss {np.mean(losses[-100:]):.4f} "
                  f"({time.perf_counter() - t1:.0f} s, CPU {time.process_time() - c1:.0f} s, "
                  f"load {loads[-1]:.1f})", flush=True)
    t_train, c_train = time.perf_counter() - t1, time.process_time() - c1
    val = evaluate(model, Xv, Dv)
    print(f"validation (house seed {cfg.val_seed}, median-scaled): {val}", flush=True)
    export(model, cfg)
    ckpt.unlink(missing_ok=True)  # the run is complete: a rerun trains afresh
    return {"params": int(n_params), "iterations": it, "train_seconds": t_train,
            "train_cpu_seconds": c_train,
            "loadavg": f"{np.mean(loads):.1f} mean, {np.min(loads):.1f}-{np.max(loads):.1f} "
                       "(1-minute load average sampled every 100 iterations)",
            "data_seconds": t_data, "images": int(len(X)), "final_loss": float(
                np.mean(losses[-100:])) if losses else None, "validation": val}


def _check_resumable(ckpt: Path, saved: dict, cfg: TrainConfig) -> None:
    """Refuse a checkpoint made under other settings, naming them (the defaults change
    between releases: a checkpoint of an older default run names what it was made with)."""
    now = _resumable(cfg)
    diff = {k: (saved.get(k), now[k]) for k in now if saved.get(k) != now[k]}
    if diff:
        said = "; ".join(f"{k}: checkpoint {a}, now {b}" for k, (a, b) in diff.items())
        raise InputError(f"{ckpt}: checkpoint of a different training configuration ({said}); "
                         "train with the checkpoint's settings to resume it (--houses, "
                         "--widths), or delete it to start afresh")


def checkpoint_path(out: Path) -> Path:
    return Path(out).with_name(Path(out).name + ".ckpt")


def _resumable(cfg: TrainConfig) -> dict:
    """What a checkpoint must share with the run that resumes it (not the time budget)."""
    keep = ("train_seeds", "images_per_house", "height", "width", "render_factor",
            "crop_height", "crop_width", "widths", "batch", "lr", "grad_weight", "seed")
    return {**{k: getattr(cfg, k) for k in keep},
            "init": None if cfg.init is None else str(cfg.init)}


def save_checkpoint(path: Path, cfg: TrainConfig, model: object, opt: object,
                    rng: np.random.Generator, iteration: int, seconds: float,
                    cpu_seconds: float) -> None:
    import torch

    from toolkit.io.atomic import atomic_path

    with atomic_path(path) as tmp:
        torch.save({"config": _resumable(cfg), "model": model.state_dict(),  # type: ignore
                    "opt": opt.state_dict(), "rng": rng.bit_generator.state,  # type: ignore
                    "iteration": iteration, "seconds": seconds, "cpu_seconds": cpu_seconds},
                   tmp)


def export(model: object, cfg: TrainConfig) -> None:
    import onnx
    import torch

    # The wrapper must be in eval mode too: the exporter puts the whole tree back into
    # the wrapper's mode afterwards, and a fresh module is in training mode.
    wrapped = ExportWrapper.wrap(model).eval()  # type: ignore[attr-defined]
    out = Path(cfg.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp")
    torch.onnx.export(wrapped, (torch.zeros(1, 3, cfg.height, cfg.width),), str(tmp),
                      input_names=["image"], output_names=["depth"],
                      dynamic_axes={"image": {2: "height", 3: "width"},
                                    "depth": {2: "height", 3: "width"}},
                      opset_version=17, dynamo=False)
    m = onnx.load(str(tmp))
    onnx.helper.set_model_props(m, {
        "depth_kind": "relative_depth", "input_height": str(cfg.height),
        "input_width": str(cfg.width), "multiple_of": "1", "channel_order": "rgb",
        "mean": ",".join(str(v) for v in IMAGENET_MEAN),
        "std": ",".join(str(v) for v in IMAGENET_STD),
        "name": "lidarcam small-depth U-Net", "training": "toolkit.depth.train_small"})
    onnx.save(m, str(tmp))
    tmp.replace(out)


def _command(c: dict, out: str, seq_arg: str = "") -> str:
    """The command line of a training run with config ``c`` (``asdict`` of a TrainConfig,
    or the ``config`` of a .train.json)."""
    args = [f"--minutes {c['minutes']:g}", f"--houses {len(c['train_seeds'])}",
            f"--threads {c['threads']}", f"--widths {','.join(map(str, c['widths']))}"]
    if (c["height"], c["width"]) != (TrainConfig.height, TrainConfig.width):
        args += [f"--height {c['height']}", f"--width {c['width']}"]
    if c["lr"] != TrainConfig.lr:
        args.append(f"--lr {c['lr']:g}")
    if c.get("images_per_house", TrainConfig.images_per_house) != TrainConfig.images_per_house:
        args.append(f"--images-per-house {c['images_per_house']}")
    if c.get("init"):
        args.append(f"--init {c['init']}")
    return "python -m toolkit.depth.train_small " + " ".join(args) + f" --out {out}{seq_arg}"


def _run_figures(c: dict, stats: dict) -> str:
    """What a run did; a .train.json of an older release may lack some of the figures."""
    def minutes(key: str) -> str:
        v = stats.get(key)
        return "?" if v is None else f"{v / 60:.1f}"

    data = stats.get("data_seconds")
    return (f"{stats.get('iterations', '?')} iterations at {c['width']}x{c['height']}, "
            f"lr {c['lr']:g}, in {minutes('train_seconds')} min wall "
            f"({minutes('train_cpu_seconds')} min CPU; load average "
            f"{stats.get('loadavg', '?')}), rendering "
            + ("?" if data is None else f"{data:.0f}") + " s")


def _base_chain(stats: dict) -> list[dict]:
    """The runs a training run continues, oldest first: each .train.json holds its
    base's."""
    chain: list[dict] = []
    b = stats.get("base")
    while b:
        chain.insert(0, b)
        b = b.get("base")
    return chain


def _training_text(cfg: TrainConfig, stats: dict, seq_arg: str) -> str:
    import textwrap

    return textwrap.fill(_training_line(cfg, stats, seq_arg), 90, break_long_words=False,
                         break_on_hyphens=False)


def _training_line(cfg: TrainConfig, stats: dict, seq_arg: str) -> str:
    c = {k: str(v) if isinstance(v, Path) else v for k, v in asdict(cfg).items()}
    mine = _command(c, str(cfg.out), seq_arg)
    load = (f"the training's own {cfg.threads} thread(s) make a load of about "
            f"{cfg.threads * 0.75:g}-{cfg.threads:g}; on a busier machine the same minutes "
            "run fewer iterations")
    if cfg.init is None:
        return (f"**Training.** `{mine}` on a 2-core CPU: {_run_figures(c, stats)} ({load}).")
    chain = _base_chain(stats)
    if not chain:
        return (f"**Training.** Fine-tuned from `{cfg.init}` (no .train.json beside it to "
                f"say how that was trained): `{mine}` on a 2-core CPU: "
                f"{_run_figures(c, stats)} ({load}).")
    runs = [(r["config"], r) for r in chain] + [(c, stats)]
    numbers = dict(enumerate(("two", "three", "four", "five", "six", "seven", "eight",
                              "nine"), start=2))
    parts = [f"**Training**, {numbers.get(len(runs), str(len(runs)))} runs on a 2-core CPU "
             f"({load})."]
    for k, (rc, rs) in enumerate(runs):
        last = k == len(runs) - 1
        # The path each run wrote (as its .train.json records it; else the next run's
        # --init), and where the next run found it when the file was moved in between.
        nxt = None if last else str(runs[k + 1][0]["init"])
        out = str(cfg.out) if last else str(rc.get("out") or nxt)
        cmd = mine if last else _command(rc, out)
        figures = _run_figures(rc, rs)
        if not last:
            absrel = rs.get("validation", {}).get("absrel", float("nan"))
            figures += f"; validation AbsRel {absrel:.3f}"
            if nxt != out:
                figures += f"; the file copied to `{nxt}`"
        if k == 0:
            head = ("First from scratch" if not rc.get("init") else
                    f"First a fine-tune of `{rc['init']}` (its own card says how that was made)")
        else:
            prev = runs[k - 1][0]
            grew = rc["height"] * rc["width"] > prev["height"] * prev["width"]
            head = "Then fine-tuned from that file" + (" at the larger input" if grew else "")
        parts.append(f"{head}: `{cmd}`: {figures}.")
        if k == 0 and not rc.get("init"):
            parts.append("The file it wrote holds each BatchNorm folded into its "
                         "convolution, so the fine-tunes train the folded network (no "
                         "BatchNorm) with a lower learning rate.")
    return " ".join(parts)


def card_path(model: Path) -> Path:
    """The model card of ``model``: beside it, named after it (one card per model file; a
    shared MODEL_CARD.md was overwritten by every experiment in the same folder)."""
    return Path(model).with_suffix(".md")


def write_card(path: Path, cfg: TrainConfig, stats: dict) -> None:
    size_mb = Path(cfg.out).stat().st_size / 1e6
    v = stats["validation"]
    seq = stats.get("sequence_eval")
    seq_text = "" if not seq else f"""
On the quickstart sequence itself (`{seq['sequence']}`, every {seq['every']}th of its
640x480 frames, {seq['frames']} frames, through `OnnxDepthBackend` as the depth stage runs
it, pixels up to 10 m, oracle scale): AbsRel {seq['absrel']:.3f}, RMSE {seq['rmse_m']:.3f} m,
delta<1.25 {seq['delta1']:.3f}; network {seq['network_ms_median']:.1f} ms per frame (median,
{cfg.threads} threads, load average {seq['loadavg']}).
"""
    seq_arg = f" --sequence {seq['sequence']}" if seq else ""
    crop_text = (f"random {cfg.crop_width}x{cfg.crop_height} crops (same pixel scale), "
                 if cfg.crop_height else "whole frames, ")
    chain = _base_chain(stats)
    size_note = ""
    if chain:
        bc = chain[0]["config"]  # the oldest run of a fine-tune chain
        if (bc["width"], bc["height"]) != (cfg.width, cfg.height):
            size_note = f" ({bc['width']}x{bc['height']} in the first run)"
    text = f"""# {Path(cfg.out).name}: the project's small monocular depth network

**What it is.** A compact U-Net ({stats['params'] / 1e6:.2f} M parameters, {size_mb:.1f} MB)
that predicts **relative depth** (z-depth up to one unknown scale per image) from one RGB
image. It stands in for Depth Anything in the quickstart so that the main job runs a real
network end to end on a CPU; it is not a general-purpose depth model.

**Architecture.** Five stride-2 stages (channels {list(cfg.widths)} at 1/2 .. 1/32
resolution, each a strided conv and a residual block), a global-average context vector
added at 1/32, a decoder with one conv per level on bilinear upsampling + skip, and an
8-channel full-resolution branch from the input pixels before the output conv. Output:
exp of the predicted log depth.

**Input/output** (also stored as ONNX metadata, read by `toolkit.depth.onnx_backend`):
input `image` [1, 3, H, W] float32, RGB, `(x / 255 - mean) / std` with ImageNet mean
{IMAGENET_MEAN} and std {IMAGENET_STD}, H x W = {cfg.height} x {cfg.width} (the backend
resizes 640x480 frames with cubic interpolation; the graph takes any size); output `depth`
[1, 1, H, W], positive, relative depth (`depth_kind = relative_depth`), resized back to the
frame by the backend. Scale it with the lidar (`fuse` stage).

{_training_text(cfg, stats, seq_arg)}
Data: {stats['images']} renders of {len(cfg.train_seeds)} simulated houses, seeds
{cfg.train_seeds[0]}-{cfg.train_seeds[-1]} ({cfg.images_per_house} each; `toolkit.sim`,
small_house preset, people included; **seed 0, the quickstart house, is never trained
on**), rendered at {cfg.render_factor}x and shrunk to {cfg.width}x{cfg.height}{size_note} with
cubic interpolation, from poses along each robot route with yaw +-0.6 rad, pitch +-0.15
rad, height -0.15..+0.4 m and lateral +-0.2 m jitter. Augmentation: {crop_text}horizontal
flips, per-channel gain 0.92-1.08, exposure 0.8-1.2.
Loss: scale-invariant log loss (lambda = 1) + {cfg.grad_weight} x gradient matching of the
log-depth residual at 4 scales. AdamW (weight decay 1e-4), {cfg.warmup_iters} warm-up
iterations, cosine decay over the time budget, batch {cfg.batch}.
**Reproducing it.** The iteration counts and the learning-rate schedule follow the wall
clock (`--minutes`), so these commands do not replay the runs: on another machine or load
they train other weights. The renders and the batches drawn are the same for the same
seeds (training seed {cfg.seed}); the file and its `.train.json` are the record.

**Measured accuracy** on {cfg.val_images} renders of house seed {cfg.val_seed} (the
evaluation house, never trained on, though runs and settings are compared and chosen on
it, so it is no untouched test house), each scaled by its median ratio to the truth (oracle
scale): AbsRel {v['absrel']:.3f}, RMSE {v['rmse_m']:.3f} m, delta<1.25
{v['delta1']:.3f}.
{seq_text}
**Limits.** Trained on one kind of synthetic house only: expect poor results on real
images. Relative depth only: no metric scale without the lidar.

**Licence.** Same as the project (MIT); trained only on data the project generates.
"""
    atomic_write_text(path, text)


def _widths(text: str) -> tuple[int, ...]:
    """``--widths``: five positive channel counts, comma-separated."""
    try:
        w = tuple(int(v) for v in text.split(","))
    except ValueError:
        w = ()
    if len(w) != 5 or min(w) < 1:
        raise argparse.ArgumentTypeError(f"--widths {text!r}: five positive channel counts "
                                         "(stages at 1/2 .. 1/32 resolution), e.g. 16,32,48,64,96")
    return w


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m toolkit.depth.train_small",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=TrainConfig.out)
    ap.add_argument("--minutes", type=positive_float, default=TrainConfig.minutes)
    ap.add_argument("--images-per-house", type=positive_int, default=TrainConfig.images_per_house)
    ap.add_argument("--houses", type=positive_int, default=len(TrainConfig.train_seeds),
                    help="train on house seeds 101 .. 100 + N")
    ap.add_argument("--threads", type=positive_int, default=TrainConfig.threads)
    ap.add_argument("--widths", type=_widths, default=TrainConfig.widths,
                    help="channels of the five stages at 1/2 .. 1/32 resolution, "
                         "comma-separated (default %(default)s)")
    ap.add_argument("--cache", type=Path, default=TrainConfig.cache,
                    help="folder for rendered training images (git-ignored by default)")
    ap.add_argument("--no-cache", action="store_true")
    ap.add_argument("--checkpoint-minutes", type=float,
                    default=TrainConfig.checkpoint_minutes,
                    help="save the training state (<out>.ckpt) this often; a rerun with the "
                         "same --out resumes from it (0: never)")
    ap.add_argument("--sequence", type=Path, default=None,
                    help="simulated sequence to evaluate the model on after training "
                         "(e.g. runs/quickstart/simulate/sequence); goes into the card")
    ap.add_argument("--every", type=positive_int, default=4, help="--sequence: every n-th frame")
    ap.add_argument("--height", type=int, default=TrainConfig.height,
                    help="network input height (default %(default)s)")
    ap.add_argument("--width", type=int, default=TrainConfig.width,
                    help="network input width (default %(default)s)")
    ap.add_argument("--lr", type=float, default=TrainConfig.lr,
                    help="peak learning rate (default %(default)s; fine-tuning: ~3e-4)")
    ap.add_argument("--init", type=Path, default=None, metavar="MODEL",
                    help="fine-tune from this model (.onnx, exported by this script; "
                         "its .train.json beside it goes into the card), e.g. at a "
                         "larger --height / --width")
    ap.add_argument("--eval-only", type=Path, default=None, metavar="MODEL",
                    help="only evaluate MODEL (.onnx) on --sequence; train nothing")
    a = ap.parse_args(argv)
    # OpenMP worker threads busy-wait between operations by default. On a machine whose
    # cores are shared, that spinning took 14x the CPU time per iteration (3.4 s instead of
    # 0.24 s with 2 threads at load average 15) and 30x the wall time; passive waiting
    # costs nothing measurable on an idle machine. Must be set before torch loads OpenMP.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    if a.eval_only is not None:
        if a.sequence is None:
            ap.error("--eval-only needs --sequence")
        # Asked as the training path asks them: a wrong path is a usage error, not a
        # traceback out of onnxruntime or the sequence reader.
        if not a.eval_only.is_file():
            ap.error(f"--eval-only {a.eval_only}: no such model file")
        if problem := sequence_problem(a.sequence):
            ap.error(f"--sequence: {problem}")
        print(json.dumps(evaluate_sequence(a.eval_only, a.sequence, a.every, a.threads),
                         indent=2))
        return 0
    cfg = TrainConfig(out=a.out, minutes=a.minutes, images_per_house=a.images_per_house,
                      train_seeds=tuple(101 + i for i in range(a.houses)), threads=a.threads,
                      cache=None if a.no_cache else a.cache, widths=a.widths,
                      checkpoint_minutes=a.checkpoint_minutes, height=a.height,
                      width=a.width, lr=a.lr, init=a.init)
    if a.height < 8 or a.width < 8:
        ap.error(f"--height {a.height} / --width {a.width}: at least 8 pixels")
    if a.sequence is not None:
        problem = sequence_problem(a.sequence)
        if problem:
            ap.error(f"--sequence: {problem}")
    base = None
    if a.init is not None:
        if not a.init.is_file():
            ap.error(f"--init {a.init}: no such model file")
        base_json = a.init.with_suffix(".train.json")
        # Read before training: --out may be the same file and overwrite it.
        base = json.loads(base_json.read_text()) if base_json.is_file() else None
    try:
        stats = train(cfg)
    except MemoryError as e:  # the renders do not fit: say so before any training
        print(f"error: {e}", file=sys.stderr)
        return 2
    if base is not None:
        stats["base"] = base
    card = card_path(cfg.out)

    def describe() -> None:
        # Right after the model: whatever fails later, the card and .train.json beside
        # it describe these weights, not an earlier run's.
        write_card(card, cfg, stats)
        atomic_write_text(Path(cfg.out).with_suffix(".train.json"), json.dumps(
            {"config": {k: str(v) if isinstance(v, Path) else v
                        for k, v in asdict(cfg).items() if k != "log"}, **stats}, indent=2))

    describe()
    if a.sequence is not None:
        stats["sequence_eval"] = {"sequence": str(a.sequence), "every": a.every,
                                  **evaluate_sequence(cfg.out, a.sequence, a.every,
                                                      cfg.threads)}
        print(f"quickstart sequence (oracle scale): {stats['sequence_eval']}")
        describe()
    print(f"wrote {cfg.out} ({Path(cfg.out).stat().st_size / 1e6:.1f} MB) and {card}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Train the project's small monocular depth network on simulator renders; export ONNX.

    python -m toolkit.depth.train_small --out datasets/models/small-depth.onnx --minutes 12

A compact U-Net (about 0.22 M parameters) predicts log depth from one RGB image. The loss
is scale-invariant (Eigen et al. 2014, with lambda = 1, plus a multi-scale gradient
matching term on log depth as in MiDaS), so the network learns shape and relative depth,
not metric scale: its output is ``relative_depth`` (exp of the prediction), to be scaled
by the lidar like Depth Anything's relative output. The exported file carries its
preprocessing in ONNX metadata (kind, input size, mean/std), which ``OnnxDepthBackend``
reads, and a model card is written next to it.

Training images come from ``toolkit.sim`` houses whose seeds differ from the evaluation
house (seed 0), rendered from poses along each house's robot route with random yaw,
height and pitch changes so that views are not all straight down the corridor.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from toolkit.depth.onnx_backend import IMAGENET_MEAN, IMAGENET_STD


@dataclass
class TrainConfig:
    out: Path = Path("datasets/models/small-depth.onnx")
    train_seeds: tuple[int, ...] = (101, 102, 103, 104)
    val_seed: int = 0  # the evaluation house: never trained on
    images_per_house: int = 200
    val_images: int = 60
    height: int = 96
    width: int = 128
    widths: tuple[int, ...] = (12, 24, 32, 48)  # channels per U-Net level
    batch: int = 8
    lr: float = 2e-3
    minutes: float = 12.0  # training time budget (data generation not included)
    max_iters: int = 20000
    grad_weight: float = 0.5
    threads: int = 2
    seed: int = 0
    log: list = field(default_factory=list)


# ---------------------------------------------------------------------------- data


def render_set(seed: int, n: int, height: int, width: int, rng: np.random.Generator) -> (
    tuple[np.ndarray, np.ndarray]
):
    """``n`` renders of house ``seed``: images [n, H, W, 3] uint8, depth [n, H, W] float32."""
    from toolkit.geometry import se3
    from toolkit.sim.people import primitives_at
    from toolkit.sim.sensors import CameraRenderer, CameraSpec
    from toolkit.sim.simulate import SimConfig, build_world

    world = build_world(SimConfig(seed=seed, n_heldout=0))
    spec = CameraSpec()
    cam = spec.camera().scaled(width, height)
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
        imgs[k] = img.rgb
        depth[k] = img.depth
    return imgs, depth


# ---------------------------------------------------------------------------- model


def make_model(widths: tuple[int, ...] = (12, 24, 32, 48)) -> object:
    """The U-Net: conv-BN-ReLU pairs, max-pool down, bilinear up with skip connections."""
    import torch
    from torch import nn

    def block(cin: int, cout: int) -> nn.Module:
        return nn.Sequential(
            nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout),
            nn.ReLU(inplace=True),
            nn.Conv2d(cout, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout),
            nn.ReLU(inplace=True))

    class SmallDepthUNet(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            w = list(widths)
            self.enc = nn.ModuleList([block(3 if i == 0 else w[i - 1], w[i])
                                      for i in range(len(w))])
            self.mid = block(w[-1], w[-1])
            self.dec = nn.ModuleList([block(w[i] + (w[i + 1] if i + 1 < len(w) else w[-1]),
                                            w[i]) for i in reversed(range(len(w)))])
            self.head = nn.Conv2d(w[0], 1, 1)

        def forward(self, x: torch.Tensor) -> torch.Tensor:  # [B, 3, H, W] -> [B, 1, H, W]
            skips = []
            for e in self.enc:
                x = e(x)
                skips.append(x)
                x = nn.functional.max_pool2d(x, 2)
            x = self.mid(x)
            for d, s in zip(self.dec, reversed(skips), strict=True):
                x = nn.functional.interpolate(x, size=s.shape[-2:], mode="bilinear",
                                              align_corners=False)
                x = d(torch.cat([x, s], 1))
            return self.head(x)  # log depth up to an additive constant

    return SmallDepthUNet()


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
    for a metric scale it cannot know from one image.
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
        for _ in range(3):
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


def train(cfg: TrainConfig) -> dict:
    import torch

    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    rng = np.random.default_rng(cfg.seed)
    t0 = time.perf_counter()
    parts = [render_set(s, cfg.images_per_house, cfg.height, cfg.width, rng)
             for s in cfg.train_seeds]
    X = np.concatenate([p[0] for p in parts])
    D = np.concatenate([p[1] for p in parts])
    Xv, Dv = render_set(cfg.val_seed, cfg.val_images, cfg.height, cfg.width, rng)
    t_data = time.perf_counter() - t0
    print(f"rendered {len(X)} training and {len(Xv)} validation images in {t_data:.0f} s")
    model = make_model(cfg.widths)
    n_params = sum(p.numel() for p in model.parameters())  # type: ignore[attr-defined]
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=1e-4)  # type: ignore
    budget = cfg.minutes * 60.0
    t1 = time.perf_counter()
    it = 0
    losses = []
    while it < cfg.max_iters:
        elapsed = time.perf_counter() - t1
        if elapsed > budget:
            break
        # Cosine decay over the time budget, not the iteration count: the machine's speed
        # (shared cores) decides how many iterations fit.
        for g in opt.param_groups:
            g["lr"] = cfg.lr * 0.5 * (1 + np.cos(np.pi * min(1.0, elapsed / budget)))
        idx = rng.integers(0, len(X), cfg.batch)
        imgs, dep = X[idx].copy(), D[idx].copy()
        flip = rng.random(cfg.batch) < 0.5
        imgs[flip] = imgs[flip, :, ::-1]
        dep[flip] = dep[flip, :, ::-1]
        gain = rng.uniform(0.75, 1.25, (cfg.batch, 1, 1, 3))
        imgs = np.clip(imgs * gain, 0, 255).astype(np.uint8)
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
            print(f"iter {it} loss {np.mean(losses[-100:]):.4f} "
                  f"({time.perf_counter() - t1:.0f} s)")
    t_train = time.perf_counter() - t1
    val = evaluate(model, Xv, Dv)
    print(f"validation (house seed {cfg.val_seed}, median-scaled): {val}")
    export(model, cfg)
    import os

    return {"params": int(n_params), "iterations": it, "train_seconds": t_train,
            "loadavg": " / ".join(f"{v:.1f}" for v in os.getloadavg()),
            "data_seconds": t_data, "images": int(len(X)), "final_loss": float(
                np.mean(losses[-100:])) if losses else None, "validation": val}


def export(model: object, cfg: TrainConfig) -> None:
    import onnx
    import torch

    model.eval()  # type: ignore[attr-defined]
    wrapped = ExportWrapper.wrap(model)
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
        "input_width": str(cfg.width), "multiple_of": "16", "channel_order": "rgb",
        "mean": ",".join(str(v) for v in IMAGENET_MEAN),
        "std": ",".join(str(v) for v in IMAGENET_STD),
        "name": "lidarcam small-depth U-Net", "training": "toolkit.depth.train_small"})
    onnx.save(m, str(tmp))
    tmp.replace(out)


def write_card(path: Path, cfg: TrainConfig, stats: dict) -> None:
    size_mb = Path(cfg.out).stat().st_size / 1e6
    v = stats["validation"]
    text = f"""# small-depth.onnx: the project's small monocular depth network

**What it is.** A compact U-Net ({stats['params'] / 1e6:.2f} M parameters, {size_mb:.1f} MB)
that predicts **relative depth** (z-depth up to one unknown scale per image) from one RGB
image. It stands in for Depth Anything in the quickstart so that the main job runs a real
network end to end on a CPU; it is not a general-purpose depth model.

**Input/output** (also stored as ONNX metadata, read by `toolkit.depth.onnx_backend`):
input `image` [1, 3, H, W] float32, RGB, `(x / 255 - mean) / std` with ImageNet mean
{IMAGENET_MEAN} and std {IMAGENET_STD}, trained at H x W = {cfg.height} x {cfg.width}
(dynamic; multiples of 16); output `depth` [1, 1, H, W], positive, relative depth
(`depth_kind = relative_depth`). Scale it with the lidar (`fuse` stage).

**Training.** `python -m toolkit.depth.train_small --minutes {cfg.minutes:g} --threads
{cfg.threads}` on a 2-core CPU shared with other jobs (load average
{stats.get('loadavg', '?')} during training, so iterations were several times slower than
on an idle machine): {stats['images']} renders of the simulated houses with seeds
{list(cfg.train_seeds)} (`toolkit.sim`, small_house preset, people included), from poses
along each robot route with yaw +-0.6 rad, pitch +-0.15 rad, height -0.15..+0.4 m and
lateral +-0.2 m jitter; horizontal flips and brightness gain 0.75-1.25.
Loss: scale-invariant log loss (lambda = 1) + {cfg.grad_weight} x multi-scale gradient
matching on log depth. AdamW, lr {cfg.lr} with cosine decay over the time budget, batch
{cfg.batch}; {stats['iterations']} iterations in {stats['train_seconds'] / 60:.1f} min
(rendering {stats['data_seconds']:.0f} s), measured on a shared 2-core machine.

**Validation** on {cfg.val_images} renders of house seed {cfg.val_seed} (the evaluation
house, never trained on), each scaled by its median ratio to the truth (oracle scale):
AbsRel {v['absrel']:.3f}, RMSE {v['rmse_m']:.3f} m, delta<1.25 {v['delta1']:.3f}.

**Limits.** Trained on one kind of synthetic house only: expect poor results on real
images. Relative depth only: no metric scale without the lidar.

**Licence.** Same as the project (MIT); trained only on data the project generates.
"""
    from toolkit.io.atomic import atomic_write_text

    atomic_write_text(path, text)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=TrainConfig.out)
    ap.add_argument("--minutes", type=float, default=TrainConfig.minutes)
    ap.add_argument("--images-per-house", type=int, default=TrainConfig.images_per_house)
    ap.add_argument("--houses", type=int, default=len(TrainConfig.train_seeds))
    ap.add_argument("--threads", type=int, default=TrainConfig.threads)
    a = ap.parse_args(argv)
    cfg = TrainConfig(out=a.out, minutes=a.minutes, images_per_house=a.images_per_house,
                      train_seeds=tuple(101 + i for i in range(a.houses)), threads=a.threads)
    stats = train(cfg)
    card = Path(cfg.out).with_name("MODEL_CARD.md")
    write_card(card, cfg, stats)
    (Path(cfg.out).with_suffix(".train.json")).write_text(json.dumps(
        {"config": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(cfg).items()
                    if k != "log"}, **stats}, indent=2))
    print(f"wrote {cfg.out} ({Path(cfg.out).stat().st_size / 1e6:.1f} MB) and {card}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

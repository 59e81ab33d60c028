"""Latency of a Depth-Anything-V2-Small-sized network under onnxruntime on this CPU.

    python -m toolkit.depth.bench_latency --out runs/bench/depth_latency.json

Builds the architecture with random weights (no download): a DINOv2 ViT-S/14 encoder
(384 wide, 12 blocks, 6 heads, patch 14) and a DPT head as in Depth Anything V2 Small
(features 64, reassemble channels 48/96/192/384 from blocks 3/6/9/12), about 24.8 M
parameters. Weights do not change the run time, only the architecture does. It is
written in plain torch because ``transformers`` is not a dependency of the toolkit; with
``--impl transformers`` (when that package is installed) transformers'
``DepthAnythingForDepthEstimation`` with a ViT-S/14 ``Dinov2Config`` is used instead.

Each input size is exported once (legacy TorchScript exporter: seconds instead of
minutes), checked against torch, and timed with onnxruntime at the given thread counts.
"""

from __future__ import annotations

import argparse
import itertools
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from toolkit.cli_types import positive_int


def vit_s14_dpt(dim: int = 384, depth: int = 12, heads: int = 6, feats: int = 64,
                outs: tuple[int, ...] = (48, 96, 192, 384)) -> object:
    """Depth Anything V2 Small's shape: ViT-S/14 + DPT head (random weights).

    The defaults are V2 Small's; smaller values give a model of the same structure that
    exports in a second (the tests use one).
    """
    import torch
    from torch import nn

    class Block(nn.Module):
        def __init__(self, dim: int, heads: int) -> None:
            super().__init__()
            self.heads = heads
            self.norm1 = nn.LayerNorm(dim, eps=1e-6)
            self.qkv = nn.Linear(dim, 3 * dim)
            self.proj = nn.Linear(dim, dim)
            self.ls1 = nn.Parameter(torch.ones(dim))
            self.norm2 = nn.LayerNorm(dim, eps=1e-6)
            self.mlp = nn.Sequential(nn.Linear(dim, 4 * dim), nn.GELU(), nn.Linear(4 * dim, dim))
            self.ls2 = nn.Parameter(torch.ones(dim))

        def forward(self, x: torch.Tensor) -> torch.Tensor:  # [B, N, C]
            B, N, C = x.shape
            qkv = self.qkv(self.norm1(x)).reshape(B, N, 3, self.heads, C // self.heads)
            q, k, v = qkv.permute(2, 0, 3, 1, 4)  # [B, h, N, c] each
            a = torch.softmax(q @ k.transpose(-2, -1) * (C // self.heads) ** -0.5, dim=-1)
            y = (a @ v).transpose(1, 2).reshape(B, N, C)
            x = x + self.ls1 * self.proj(y)
            return x + self.ls2 * self.mlp(self.norm2(x))

    class RCU(nn.Module):  # residual conv unit of the DPT fusion blocks
        def __init__(self, f: int) -> None:
            super().__init__()
            self.c1 = nn.Conv2d(f, f, 3, padding=1)
            self.c2 = nn.Conv2d(f, f, 3, padding=1)

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return x + self.c2(torch.relu(self.c1(torch.relu(x))))

    class Fusion(nn.Module):
        def __init__(self, f: int, first: bool) -> None:
            super().__init__()
            self.res1 = None if first else RCU(f)
            self.res2 = RCU(f)
            self.out = nn.Conv2d(f, f, 1)

        def forward(self, x: torch.Tensor, skip: torch.Tensor | None,
                    size: tuple[int, int]) -> torch.Tensor:
            if skip is not None and self.res1 is not None:
                x = x + self.res1(skip)
            x = self.res2(x)
            x = nn.functional.interpolate(x, size=size, mode="bilinear", align_corners=True)
            return self.out(x)

    class DepthAnythingSmallShape(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.patch = nn.Conv2d(3, dim, 14, stride=14)
            self.cls = nn.Parameter(torch.zeros(1, 1, dim))
            self.pos = nn.Parameter(torch.zeros(1, 1 + 37 * 37, dim))  # trained at 518
            self.blocks = nn.ModuleList([Block(dim, heads) for _ in range(depth)])
            self.norm = nn.LayerNorm(dim, eps=1e-6)
            self.take = tuple(max(0, depth * k // 4 - 1) for k in (1, 2, 3, 4))  # 2 5 8 11
            self.project = nn.ModuleList([nn.Conv2d(dim, o, 1) for o in outs])
            self.resize = nn.ModuleList([
                nn.ConvTranspose2d(outs[0], outs[0], 4, stride=4),
                nn.ConvTranspose2d(outs[1], outs[1], 2, stride=2),
                nn.Identity(), nn.Conv2d(outs[3], outs[3], 3, stride=2, padding=1)])
            self.rn = nn.ModuleList([nn.Conv2d(o, feats, 3, padding=1, bias=False)
                                     for o in outs])
            self.fuse = nn.ModuleList([Fusion(feats, i == 3) for i in range(4)])
            self.head = nn.Sequential(nn.Conv2d(feats, feats // 2, 3, padding=1))
            # Depth Anything ends in one more ReLU; left out so that the export check compares
            # real numbers (random weights make most outputs of that ReLU zero). It costs
            # nothing measurable.
            self.head2 = nn.Sequential(nn.Conv2d(feats // 2, 32, 3, padding=1), nn.ReLU(),
                                       nn.Conv2d(32, 1, 1))

        def forward(self, x: torch.Tensor) -> torch.Tensor:  # [1, 3, H, W] -> [1, H, W]
            H, W = x.shape[-2:]
            ph, pw = H // 14, W // 14
            t = self.patch(x).flatten(2).transpose(1, 2)  # [B, ph*pw, C]
            pos = self.pos[:, 1:].reshape(1, 37, 37, -1).permute(0, 3, 1, 2)
            if (ph, pw) != (37, 37):  # DINOv2 interpolates its position grid
                pos = nn.functional.interpolate(pos, size=(ph, pw), mode="bicubic",
                                                align_corners=False)
            pos = pos.flatten(2).transpose(1, 2)
            t = torch.cat([self.cls + self.pos[:, :1], t + pos], 1)
            feats = []
            for i, b in enumerate(self.blocks):
                t = b(t)
                if i in self.take:
                    f = self.norm(t)[:, 1:].transpose(1, 2).reshape(1, -1, ph, pw)
                    feats.append(f)
            rs = [self.rn[i](self.resize[i](self.project[i](f))) for i, f in enumerate(feats)]
            y = self.fuse[3](rs[3], None, rs[2].shape[-2:])
            y = self.fuse[2](y, rs[2], rs[1].shape[-2:])
            y = self.fuse[1](y, rs[1], rs[0].shape[-2:])
            y = self.fuse[0](y, rs[0], (rs[0].shape[-2] * 2, rs[0].shape[-1] * 2))
            y = self.head(y)
            y = nn.functional.interpolate(y, size=(ph * 14, pw * 14), mode="bilinear",
                                          align_corners=True)
            return self.head2(y)[:, 0]

    return DepthAnythingSmallShape()


def transformers_model() -> object:
    """transformers' Depth Anything with a ViT-S/14 DINOv2 backbone config (no weights)."""
    from transformers import DepthAnythingConfig, DepthAnythingForDepthEstimation, Dinov2Config

    backbone = Dinov2Config(hidden_size=384, num_hidden_layers=12, num_attention_heads=6,
                            patch_size=14, image_size=518,
                            out_features=["stage3", "stage6", "stage9", "stage12"],
                            reshape_hidden_states=False)
    cfg = DepthAnythingConfig(backbone_config=backbone, fusion_hidden_size=64,
                              neck_hidden_sizes=[48, 96, 192, 384], depth_estimation_type=
                              "relative")
    model = DepthAnythingForDepthEstimation(cfg)

    class Wrap(__import__("torch").nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.m = model

        def forward(self, x: object) -> object:
            return self.m(pixel_values=x).predicted_depth

    return Wrap()


RANDOM_WEIGHTS_WARNING = (
    "RANDOM WEIGHTS: this is a Depth-Anything-V2-Small-sized network with untrained "
    "weights, exported for timing only; its depth is meaningless")


def export_onnx(model: object, path: Path, height: int, width: int,
                random_weights: bool = True) -> float:
    """Export ``model`` at a fixed ``height`` x ``width`` input with the metadata that
    ``OnnxDepthBackend`` reads (Depth Anything's preprocessing, relative disparity out),
    so a recipe's depth stage runs the file with only ``model:`` set. Returns seconds.

    The size is fixed because the position-grid interpolation is traced for one patch
    grid; the backend resizes each frame to it and the output back to the frame.
    """
    import onnx
    import torch

    from toolkit.depth.onnx_backend import IMAGENET_MEAN, IMAGENET_STD
    from toolkit.io.atomic import atomic_path

    t0 = time.perf_counter()
    x = torch.zeros(1, 3, height, width)
    with atomic_path(path) as tmp:
        torch.onnx.export(model, (x,), str(tmp), input_names=["image"], output_names=["depth"],
                          opset_version=17, dynamo=False)
        m = onnx.load(str(tmp))
        props = {"depth_kind": "relative_disparity", "input_height": str(height),
                 "input_width": str(width), "multiple_of": "14", "channel_order": "rgb",
                 "mean": ",".join(str(v) for v in IMAGENET_MEAN),
                 "std": ",".join(str(v) for v in IMAGENET_STD),
                 "name": "Depth-Anything-V2-Small-sized ViT-S/14 + DPT (toolkit.depth."
                         "bench_latency)"}
        if random_weights:
            props.update({"weights": "random", "warning": RANDOM_WEIGHTS_WARNING})
        onnx.helper.set_model_props(m, props)
        onnx.save(m, str(tmp))
    return time.perf_counter() - t0


def quantize_int8(src: Path, dst: Path) -> float:
    """onnxruntime's dynamic int8 quantization of the MatMul/Gemm weights (activations are
    quantized per call): the ViT's linear layers are most of its time. Metadata is kept.
    With real weights check the accuracy before relying on it. Returns seconds."""
    import onnx
    from onnxruntime.quantization import QuantType, quantize_dynamic

    from toolkit.io.atomic import atomic_path

    t0 = time.perf_counter()
    with atomic_path(dst) as tmp:
        quantize_dynamic(str(src), str(tmp), weight_type=QuantType.QInt8,
                         op_types_to_quantize=["MatMul", "Gemm"])
        props = {p.key: p.value for p in onnx.load(str(src), load_external_data=False)
                 .metadata_props}
        m = onnx.load(str(tmp))
        onnx.helper.set_model_props(m, {**props, "quantization": "dynamic int8 (MatMul)"})
        onnx.save(m, str(tmp))
    return time.perf_counter() - t0


def _loadavg() -> float:
    return float(os.getloadavg()[0])


def bench(sizes: list[tuple[int, int]], threads: list[int], runs: int, impl: str,
          spin: bool = False, frame_hw: tuple[int, int] = (480, 640),
          int8: bool = False) -> dict:
    """Export each size, check it against torch, then time it through ``OnnxDepthBackend``
    (the depth stage's code path: resize a ``frame_hw`` frame in, run, resize out).

    Per run: wall time of the network alone and of the whole ``predict``, and the process
    CPU time of ``predict``; the 1-minute load average is recorded with each size because
    on a shared machine wall time says more about the neighbours than about the network.
    """
    import torch

    from toolkit.depth.onnx_backend import OnnxDepthBackend, OnnxDepthConfig

    torch.manual_seed(0)
    model = (vit_s14_dpt() if impl == "torch" else transformers_model()).eval()  # type: ignore
    n_params = sum(p.numel() for p in model.parameters())
    frame = np.random.default_rng(0).integers(0, 256, (*frame_hw, 3), dtype=np.uint8)
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for h, w in sizes:
            x = torch.randn(1, 3, h, w)
            t0, c0 = time.perf_counter(), time.process_time()
            with torch.no_grad():
                ref = model(x).numpy()
            t_torch, c_torch = time.perf_counter() - t0, time.process_time() - c0
            path = Path(tmp) / f"da_small_{h}x{w}.onnx"
            t_export = export_onnx(model, path, h, w)
            variants = [("fp32", path)]
            if int8:
                qpath = path.with_name(f"{path.stem}_int8.onnx")
                quantize_int8(path, qpath)
                variants.append(("int8", qpath))
            for (precision, file), th in itertools.product(variants, threads):
                size_mb = file.stat().st_size / 1e6
                be = OnnxDepthBackend(OnnxDepthConfig(model=file, threads=th, spin=spin))
                xi = x.numpy()
                out = be.session.run(None, {be.input_name: xi})[0]  # warm-up + correctness
                rel = float(np.abs(out - ref).max() / max(np.abs(ref).max(), 1e-12))
                be.predict(frame)
                net, total, cpu, loads = [], [], [], [_loadavg()]
                for _ in range(runs):
                    t0, c0 = time.perf_counter(), time.process_time()
                    be.predict(frame)
                    total.append(time.perf_counter() - t0)
                    cpu.append(time.process_time() - c0)
                    net.append(be.last_timing["network_s"])
                loads.append(_loadavg())
                results.append({"height": h, "width": w, "threads": th,
                                "precision": precision,
                                "latency_median_s": float(np.median(net)),
                                "latency_min_s": float(np.min(net)),
                                "latency_mean_s": float(np.mean(net)),
                                "predict_median_s": float(np.median(total)),
                                "fps": float(1.0 / np.median(total)), "runs": runs,
                                "cpu_s_per_frame": float(np.median(cpu)),
                                "loadavg_1min": [float(v) for v in loads],
                                "spinning": spin, "frame_hw": list(frame_hw),
                                "max_rel_error_vs_torch": rel, "export_s": t_export,
                                "torch_eager_s": t_torch, "torch_eager_cpu_s": c_torch,
                                "onnx_mb": size_mb})
                print(f"{h}x{w} (HxW) {precision} threads {th}: "
                      f"network {np.median(net) * 1000:.0f} ms "
                      f"(min {np.min(net) * 1000:.0f}), predict on {frame_hw[1]}x{frame_hw[0]} "
                      f"{np.median(total) * 1000:.0f} ms wall / {np.median(cpu) * 1000:.0f} ms "
                      f"CPU, load {loads[0]:.1f}-{loads[1]:.1f}, rel err {rel:.1e}", flush=True)
                del be
            for _, file in variants:
                file.unlink()
    return {"impl": impl, "params": int(n_params), "results": results}


def _parse_size(text: str) -> tuple[int, int]:
    """'HxW' (or one side for a square) -> (h, w); both multiples of 14 (ViT-S/14)."""
    parts = [int(v) for v in text.lower().split("x")]
    h, w = (parts[0], parts[0]) if len(parts) == 1 else (parts[0], parts[1])
    if h % 14 or w % 14 or h <= 0 or w <= 0:
        raise SystemExit(f"size {text}: both sides must be positive multiples of 14 (ViT-S/14)")
    return h, w


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m toolkit.depth.bench_latency",
                                 description="Depth-Anything-V2-Small-sized ONNX latency")
    ap.add_argument("--out", type=Path, default=Path("runs/bench/depth_latency.json"))
    ap.add_argument("--sizes", default="518x518,364x364,308x308,266x350",
                    help="HxW list, multiples of 14 (266x350 keeps a 640x480 frame's 4:3)")
    ap.add_argument("--threads", default="1,2", help="comma-separated onnxruntime threads")
    ap.add_argument("--runs", type=positive_int, default=5)
    ap.add_argument("--impl", choices=["torch", "transformers"], default="torch")
    ap.add_argument("--spin", action="store_true",
                    help="let onnxruntime threads spin (faster on an idle machine only)")
    ap.add_argument("--export", type=Path, default=None, metavar="PATH",
                    help="only write the model at --size to PATH (.onnx, random weights, "
                         "with metadata for the depth stage's onnx backend); time nothing")
    ap.add_argument("--size", default="266x350", help="--export: input HxW")
    ap.add_argument("--int8", action="store_true",
                    help="also time (with --export: write) a dynamic-int8 quantized copy")
    a = ap.parse_args(argv)
    try:  # every argument checked before minutes of export or timing
        sizes = [_parse_size(s) for s in (a.size if a.export is not None else a.sizes).split(",")]
        threads = [int(t) for t in a.threads.split(",")]
    except ValueError as e:
        ap.error(f"--size(s)/--threads: {e}; give sizes as HxW (e.g. 266x350), threads as 1,2")
    if min(threads) < 1:
        ap.error("--threads must be at least 1")
    for path in (a.export, a.out):
        if path is not None and path.is_dir():
            ap.error(f"{path} is a folder; give the file to write")
    # Busy-waiting OpenMP threads (torch's default) cost many times the CPU on shared cores
    # (see train_small); set before torch loads OpenMP. onnxruntime has its own setting.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    if a.export is not None:
        import torch

        h, w = sizes[0]
        torch.manual_seed(0)
        model = (vit_s14_dpt() if a.impl == "torch" else transformers_model()).eval()  # type: ignore
        secs = export_onnx(model, a.export, h, w)
        if a.int8:  # the fp32 file is only a step on the way
            fp32 = a.export.with_name(f".{a.export.stem}_fp32.onnx")
            a.export.replace(fp32)
            secs += quantize_int8(fp32, a.export)
            fp32.unlink()
        print(f"wrote {a.export} ({a.export.stat().st_size / 1e6:.0f} MB, input {h}x{w} HxW, "
              f"{secs:.0f} s)\n{RANDOM_WEIGHTS_WARNING}.\nDepth stage: backend: onnx, model: "
              f"{a.export} (kind and preprocessing come from its metadata; threads: 2)")
        return 0
    load0 = os.getloadavg()
    res = bench(sizes, threads, a.runs, a.impl,
                a.spin, int8=a.int8)
    res.update({"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
                "loadavg_before": load0, "loadavg_after": os.getloadavg(),
                "note": "random weights; latency depends on the architecture only. A load "
                        "average above the core count means other processes shared the CPU; "
                        "cpu_s_per_frame (process CPU time) is then the steadier figure."})
    from toolkit.io.atomic import atomic_write_json

    atomic_write_json(a.out, res)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

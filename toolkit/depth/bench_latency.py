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
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np


def vit_s14_dpt() -> object:
    """Depth Anything V2 Small's shape: ViT-S/14 + DPT head (random weights)."""
    import torch
    from torch import nn

    class Block(nn.Module):
        def __init__(self, dim: int = 384, heads: int = 6) -> None:
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
        def __init__(self, dim: int = 384, depth: int = 12, feats: int = 64,
                     outs: tuple[int, ...] = (48, 96, 192, 384)) -> None:
            super().__init__()
            self.patch = nn.Conv2d(3, dim, 14, stride=14)
            self.cls = nn.Parameter(torch.zeros(1, 1, dim))
            self.pos = nn.Parameter(torch.zeros(1, 1 + 37 * 37, dim))  # trained at 518
            self.blocks = nn.ModuleList([Block(dim) for _ in range(depth)])
            self.norm = nn.LayerNorm(dim, eps=1e-6)
            self.take = (2, 5, 8, 11)
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


def bench(sizes: list[tuple[int, int]], threads: list[int], runs: int, impl: str,
          spin: bool = False) -> dict:
    import onnxruntime as ort
    import torch

    torch.manual_seed(0)
    model = (vit_s14_dpt() if impl == "torch" else transformers_model()).eval()  # type: ignore
    n_params = sum(p.numel() for p in model.parameters())  # type: ignore[attr-defined]
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for h, w in sizes:
            x = torch.randn(1, 3, h, w)
            t0 = time.perf_counter()
            with torch.no_grad():
                ref = model(x).numpy()  # type: ignore[operator]
            t_torch = time.perf_counter() - t0
            path = Path(tmp) / f"da_small_{h}x{w}.onnx"
            t0 = time.perf_counter()
            torch.onnx.export(model, (x,), str(path), input_names=["image"],
                              output_names=["depth"], opset_version=17, dynamo=False)
            t_export = time.perf_counter() - t0
            size_mb = sum(p.stat().st_size for p in Path(tmp).glob(f"da_small_{h}x{w}*")) / 1e6
            for th in threads:
                opts = ort.SessionOptions()
                opts.intra_op_num_threads = th
                opts.inter_op_num_threads = 1
                # Spinning worker threads burn the cores other processes need; on a shared
                # machine that makes everyone, this run included, several times slower.
                opts.add_session_config_entry("session.intra_op.allow_spinning",
                                              "1" if spin else "0")
                sess = ort.InferenceSession(str(path), opts,
                                            providers=["CPUExecutionProvider"])
                xi = x.numpy()
                out = sess.run(None, {"image": xi})[0]  # warm-up (and correctness)
                times, cpu = [], []
                for _ in range(runs):
                    t0, c0 = time.perf_counter(), time.process_time()
                    sess.run(None, {"image": xi})
                    times.append(time.perf_counter() - t0)
                    cpu.append(time.process_time() - c0)
                rel = float(np.abs(out - ref).max() / max(np.abs(ref).max(), 1e-12))
                results.append({"height": h, "width": w, "threads": th,
                                "latency_median_s": float(np.median(times)),
                                "latency_min_s": float(np.min(times)),
                                "latency_mean_s": float(np.mean(times)),
                                "fps": float(1.0 / np.median(times)), "runs": runs,
                                "cpu_s_per_frame": float(np.median(cpu)),
                                "spinning": spin,
                                "max_rel_error_vs_torch": rel, "export_s": t_export,
                                "torch_eager_s": t_torch, "onnx_mb": size_mb})
                print(f"{w}x{h} threads {th}: {np.median(times) * 1000:.0f} ms/frame "
                      f"(min {np.min(times) * 1000:.0f}, CPU {np.median(cpu) * 1000:.0f} ms), "
                      f"rel err {rel:.1e}")
                del sess
            path.unlink()
    return {"impl": impl, "params": int(n_params), "results": results}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Depth-Anything-V2-Small-sized ONNX latency")
    ap.add_argument("--out", type=Path, default=Path("runs/bench/depth_latency.json"))
    ap.add_argument("--sizes", default="518x518,518x392,392x392,266x266",
                    help="HxW list, multiples of 14")
    ap.add_argument("--threads", default="1,2", help="comma-separated onnxruntime threads")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--impl", choices=["torch", "transformers"], default="torch")
    ap.add_argument("--spin", action="store_true",
                    help="let onnxruntime threads spin (faster on an idle machine only)")
    a = ap.parse_args(argv)
    sizes = [tuple(int(v) for v in s.split("x")) for s in a.sizes.split(",")]
    for h, w in sizes:
        if h % 14 or w % 14:
            raise SystemExit(f"size {h}x{w}: both sides must be multiples of 14 (ViT-S/14)")
    load0 = os.getloadavg()
    res = bench(sizes, [int(t) for t in a.threads.split(",")], a.runs, a.impl,  # type: ignore
                a.spin)
    res.update({"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
                "loadavg_before": load0, "loadavg_after": os.getloadavg(),
                "note": "random weights; latency depends on the architecture only. A load "
                        "average above the core count means other processes shared the CPU."})
    from toolkit.io.atomic import atomic_write_json

    atomic_write_json(a.out, res)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Rasteriser benchmark: forward+backward iterations per second, written as JSON.

    python -m toolkit.splat.bench --out bench_splat.json            # 320x240, 50k Gaussians
    python -m toolkit.splat.bench --width 640 --height 480 -n 200000 --backends gsplat

Scene: 50k Gaussians on the inside of a 6 x 4 x 2.6 m room with procedurally coloured walls,
seen from inside (70 deg horizontal field of view), the state a model is in a few hundred
iterations into training: sizes from the 3-nearest-neighbour spacing with random anisotropy,
random rotations, opacities spread over 0.05..0.95 and SH degree 3. ``--state init`` uses
the initialisation instead (isotropic, opacity 0.1, which composites more layers per pixel).
One iteration is render + L1 loss against a fixed image + backward, as in training minus the
optimizer step.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from toolkit.camera import PinholeCamera
from toolkit.cli_types import positive_int
from toolkit.io.atomic import atomic_write_json
from toolkit.splat.model import Gaussians, init_from_points
from toolkit.splat.rasterize import cpp_ext, render, resolve_backend
from toolkit.splat.synthetic import perturbed, room_camera, room_points


def bench_scene(n: int = 50_000, width: int = 320, height: int = 240, state: str = "trained",
                seed: int = 0) -> tuple[Gaussians, PinholeCamera, np.ndarray]:
    """Gaussians (leaf tensors requiring grad), camera and T_camera_world of the benchmark."""
    pts, rgb = room_points(n, seed)
    g = init_from_points(pts, rgb, sh_degree=3, seed=seed).gaussians()
    if state == "trained":
        g = perturbed(g, seed)
    elif state != "init":
        raise ValueError(f"state must be 'trained' or 'init', got {state!r}")
    g = Gaussians(*(t.detach().clone().requires_grad_(True) for t in
                    (g.means, g.quats, g.log_scales, g.opacity_logits, g.full_sh())))
    cam, T_cw = room_camera(width, height)
    return g, cam, T_cw


def time_backend(g: Gaussians, cam: PinholeCamera, T_cw: np.ndarray, backend: str,
                 iters: int, warmup: int = 1, tile_size: int | None = None) -> dict[str, Any]:
    """Seconds per forward+backward iteration (median and all), plus scene figures."""
    device = g.means.device
    target = torch.full((cam.height, cam.width, 3), 0.5, device=device)
    times, cpu = [], []
    out = None
    for i in range(warmup + iters):
        if device.type == "cuda":
            torch.cuda.synchronize()
        c0 = time.process_time()
        t0 = time.perf_counter()
        out = render(g, cam, T_cw, backend=backend, tile_size=tile_size)
        loss = (out.color - target).abs().mean()
        loss.backward()
        if device.type == "cuda":
            torch.cuda.synchronize()
        dt = time.perf_counter() - t0
        dc = time.process_time() - c0
        for t in (g.means, g.quats, g.log_scales, g.opacity_logits, g.sh):
            t.grad = None
        if i >= warmup:
            times.append(dt)
            cpu.append(dc)
    assert out is not None
    med = statistics.median(times)
    return {
        "backend": out.meta.backend,
        "tile_size": tile_size,
        "seconds_per_iter_median": med,
        "seconds_per_iter_all": times,
        "iters_per_s": 1.0 / med,
        # CPU seconds of all threads: on a machine shared with other jobs the wall time
        # includes waiting for a core, this does not.
        "cpu_seconds_per_iter_median": statistics.median(cpu),
        "visible_gaussians": int(len(out.meta.gaussian_ids)),
        "mean_alpha": float(out.alpha.detach().mean()),
    }


def run_bench(n: int = 50_000, width: int = 320, height: int = 240, backends: tuple[str, ...] = (
        "cpp", "torch"), iters: int = 10, ref_iters: int = 3, state: str = "trained",
        threads: int | None = None, device: str = "cpu",
        composite_threads: int | None = None,
        say: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Time each backend on the benchmark scene; the result dict is what the CLI writes.

    ``threads``: torch's thread count; ``composite_threads``: the C++ compositing kernels'
    (None: the same as torch's); ``say`` gets a line at each phase.
    """
    say = say or (lambda _: None)
    if threads:
        torch.set_num_threads(threads)
    cpp_ext.set_threads(composite_threads)
    say(f"building the scene: {n} Gaussians at {width}x{height} ({state})")
    g, cam, T_cw = bench_scene(n, width, height, state)
    if device != "cpu":
        g = Gaussians(*(t.detach().to(device).requires_grad_(True) for t in
                        (g.means, g.quats, g.log_scales, g.opacity_logits, g.full_sh())))
    result: dict[str, Any] = {
        "scene": {"gaussians": n, "width": width, "height": height, "state": state,
                  "sh_degree": 3},
        "machine": {"cpu": platform.processor() or platform.machine(),
                    "cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
                    "composite_threads": cpp_ext.get_threads(),
                    "torch": torch.__version__, "python": sys.version.split()[0],
                    "device": (torch.cuda.get_device_name() if device != "cpu" else "cpu"),
                    "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None},
        "backends": {},
    }
    if "cpp" in backends:
        t0 = time.perf_counter()
        say("loading the C++ extension (compiled on first use: about a minute)")
        cpp_ext.load_extension()
        result["cpp_extension_load_s"] = time.perf_counter() - t0
    for b in backends:
        name = resolve_backend(b, g.means.device)
        if b == "cpp" and name != "cpp":
            result["backends"]["cpp"] = {"error": f"unavailable: {cpp_ext.extension_error()}"}
            continue
        k = ref_iters if name == "torch" else iters
        say(f"timing {b}: {k} iterations after warm-up")
        result["backends"][b] = time_backend(g, cam, T_cw, b, k)
    fast, ref = result["backends"].get("cpp", {}), result["backends"].get("torch", {})
    if "iters_per_s" in fast and "iters_per_s" in ref:
        result["speedup_cpp_over_torch"] = fast["iters_per_s"] / ref["iters_per_s"]
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m toolkit.splat.bench",
                                description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("bench_splat.json"))
    p.add_argument("-n", "--gaussians", type=positive_int, default=50_000)
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--backends", default="cpp,torch", help="comma list of cpp, torch, gsplat")
    p.add_argument("--iters", type=positive_int, default=10)
    p.add_argument("--ref-iters", type=positive_int, default=3,
                   help="iterations for the slow reference")
    p.add_argument("--state", choices=("trained", "init"), default="trained")
    p.add_argument("--threads", type=int, default=None, help="torch threads")
    p.add_argument("--composite-threads", type=int, default=None,
                   help="C++ compositing threads (default: as torch)")
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda"),
                   help="cuda for the gsplat backend")
    a = p.parse_args(argv)
    if a.device == "cuda":
        import torch

        if not torch.cuda.is_available():
            p.error("--device cuda: this torch "
                    f"({torch.__version__}) sees no CUDA device; run on a machine with an "
                    "NVIDIA GPU and a CUDA build of torch (plus pip install gsplat)")
    backends = tuple(a.backends.split(","))
    unknown = sorted(set(backends) - {"cpp", "torch", "gsplat"})
    if unknown:
        p.error(f"--backends: unknown {unknown}; choose from cpp, torch, gsplat")
    if "gsplat" in backends and a.device != "cuda":
        p.error("--backends gsplat renders on the GPU: add --device cuda")
    if a.out.is_dir():
        p.error(f"--out {a.out} is a folder; give the JSON file to write")
    res = run_bench(a.gaussians, a.width, a.height, backends, a.iters,
                    a.ref_iters, a.state, a.threads, a.device, a.composite_threads,
                    say=lambda line: print(line, file=sys.stderr, flush=True))
    atomic_write_json(a.out, res)
    for b, r in res["backends"].items():
        if "iters_per_s" in r:
            print(f"{b:7s} {r['iters_per_s']:7.2f} it/s  ({r['seconds_per_iter_median']:.3f} s/it "
                  f"wall, {r['cpu_seconds_per_iter_median']:.3f} CPU-s/it, "
                  f"{r['visible_gaussians']} visible)")
        else:
            print(f"{b:7s} {r.get('error')}")
    if "speedup_cpp_over_torch" in res:
        print(f"cpp / torch: {res['speedup_cpp_over_torch']:.1f}x")
    print(f"written {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

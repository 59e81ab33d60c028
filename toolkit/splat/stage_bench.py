"""The ``splat`` stage end to end on a synthetic room, once per device, written as JSON.

    python -m toolkit.splat.stage_bench --out bench_splat_stage.json            # cpu
    python -m toolkit.splat.stage_bench --devices cuda,cpu --out b.json         # GPU vs CPU
    python -m toolkit.splat.stage_bench --set view_cache_mb=1 --set exposure=gain  # settings

The recording (``toolkit.splat.synthetic``): ``--frames`` views at ``--width`` x
``--height`` of a textured room rendered from a ground-truth model of ``--gaussians``
Gaussians, and a fused-style map of as many noisy wall points with per-frame depth. The
stage trains ``--iterations`` steps from that map with its default settings (every 8th
frame held out, densification, depth loss) and no time limit, through the recipe runner,
so that the figures include what a run pays besides the rasteriser: view upload, the
optimiser, densification, checkpoints, the held-out evaluation. The defaults are the
quickstart's training size (160x120, 40k initial Gaussians, 1500 steps). ``--set KEY=VALUE``
(a YAML value) sets one of the splat stage's settings on every device's run, to time a
setting (``view_cache_mb=1``: views read from disk as training asks) or check it on a GPU.
With both devices, ``speedup_cuda_over_cpu`` is the CPU's training time over the GPU's.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml

from toolkit.cli_types import positive_int
from toolkit.io.atomic import atomic_write_json
from toolkit.recipe import (
    RecipeError,
    Stage,
    StageConfig,
    load_recipe,
    registry,
    run_recipe,
)

INPUT_STAGE = "splat_bench_inputs"
KEYS = ("device", "backend", "iterations", "stopped_early", "train_seconds",
        "train_iters_per_s", "n_gaussians_init", "n_gaussians", "train_views",
        "heldout_psnr_db", "heldout_ssim", "eval_seconds")


class _InputsConfig(StageConfig):
    frames: int = 120
    width: int = 160
    height: int = 120
    gaussians: int = 40_000


class _SyntheticInputs(Stage):
    """The synthetic room as a ``sequence`` and a ``fused`` folder."""

    name = INPUT_STAGE
    Config = _InputsConfig
    provides = ("sequence", "fused")

    def run(self, ctx: Any) -> None:
        from toolkit.splat.synthetic import write_synthetic_inputs

        cfg: Any = self.config
        seq, fused = write_synthetic_inputs(ctx.stage_dir, n_frames=cfg.frames,
                                            width=cfg.width, height=cfg.height,
                                            n_gaussians=cfg.gaussians,
                                            depth_folder="scaled_depth")
        ctx.provide("sequence", seq)
        ctx.provide("fused", fused)


def run_stage_bench(devices: tuple[str, ...], frames: int = 120, width: int = 160,
                    height: int = 120, gaussians: int = 40_000, iterations: int = 1500,
                    workdir: Path | None = None,
                    settings: dict[str, Any] | None = None) -> dict[str, Any]:
    """Run the stage once per device, with ``settings`` (splat stage keys) on top of the
    bench's own; the result dict is what the CLI writes."""
    import torch

    settings = dict(settings or {})
    clash = sorted(set(settings) & {"stage", "id", "needs", "device", "iterations",
                                    "init_budget"})
    if clash:
        raise ValueError(f"{clash}: the bench sets these itself (--devices, --iterations, "
                         "-n)")
    result: dict[str, Any] = {
        "scene": {"frames": frames, "width": width, "height": height,
                  "gaussians": gaussians, "iterations": iterations},
        **({"settings": settings} if settings else {}),
        "machine": {"cpu": platform.processor() or platform.machine(),
                    "cpu_count": os.cpu_count(), "torch": torch.__version__,
                    "gpu": torch.cuda.get_device_name() if torch.cuda.is_available() else None},
        "devices": {},
    }
    registry.register(INPUT_STAGE, _SyntheticInputs)
    try:
        with tempfile.TemporaryDirectory(dir=workdir) as tmp:
            for device in devices:
                recipe = {"name": f"splat_bench_{device}", "output": f"{tmp}/{device}",
                          "stages": [
                              {"stage": INPUT_STAGE, "frames": frames, "width": width,
                               "height": height, "gaussians": gaussians},
                              {"stage": "splat", "device": device, "iterations": iterations,
                               "downscale": 1, "init_budget": gaussians,
                               "max_seconds": None, "log_every": 500, **settings}]}
                path = Path(tmp) / f"{device}.yaml"
                path.write_text(yaml.safe_dump(recipe, sort_keys=False))
                t0 = time.perf_counter()
                run = run_recipe(load_recipe(path))
                m = run.metrics.get("splat", {})
                result["devices"][device] = {
                    "ok": run.ok, "error": run.error,
                    "run_seconds": time.perf_counter() - t0,
                    **{k: m.get(k) for k in KEYS}}
    finally:
        registry.unregister(INPUT_STAGE)
    cpu, gpu = (result["devices"].get(d, {}) for d in ("cpu", "cuda"))
    if cpu.get("train_seconds") and gpu.get("train_seconds"):
        result["speedup_cuda_over_cpu"] = cpu["train_seconds"] / gpu["train_seconds"]
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m toolkit.splat.stage_bench",
                                description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("bench_splat_stage.json"))
    p.add_argument("--devices", default="cpu", help="comma list of cpu, cuda (run in this order)")
    p.add_argument("--frames", type=positive_int, default=120)
    p.add_argument("--width", type=positive_int, default=160)
    p.add_argument("--height", type=positive_int, default=120)
    p.add_argument("-n", "--gaussians", type=positive_int, default=40_000)
    p.add_argument("--iterations", type=positive_int, default=1500)
    p.add_argument("--set", dest="settings", action="append", default=[], metavar="KEY=VALUE",
                   help="a splat stage setting for every device's run (YAML value); repeatable")
    a = p.parse_args(argv)
    settings: dict[str, Any] = {}
    for item in a.settings:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            p.error(f"--set {item!r}: write KEY=VALUE, e.g. --set view_cache_mb=1")
        settings[key.strip()] = yaml.safe_load(value)
    devices = tuple(d.strip() for d in a.devices.split(",") if d.strip())
    unknown = sorted(set(devices) - {"cpu", "cuda"})
    if unknown or not devices or len(set(devices)) != len(devices):
        p.error(f"--devices {a.devices!r}: name cpu and / or cuda, each once")
    if a.frames < 8:
        p.error("--frames: at least 8 (every 8th frame is held out for scoring)")
    if a.out.is_dir():
        p.error(f"--out {a.out} is a folder; give the JSON file to write")
    try:
        res = run_stage_bench(devices, a.frames, a.width, a.height, a.gaussians, a.iterations,
                              settings=settings)
    except (ValueError, RecipeError) as e:  # a key the stage lacks: before anything ran
        p.error(f"--set: {e}")
    atomic_write_json(a.out, res)
    for device, r in res["devices"].items():
        if r["ok"]:
            print(f"{device:5s} {r['train_seconds']:7.1f} s training, "
                  f"{r['train_iters_per_s']:6.1f} it/s, held-out {r['heldout_psnr_db']:.2f} dB, "
                  f"{r['n_gaussians']} Gaussians ({r['device']})")
        else:
            print(f"{device:5s} failed: {r['error']}")
    for k, v in res.items():
        if k.startswith("speedup_"):
            print(f"{k}: {v:.2f}x")
    print(f"written {a.out}")
    return 0 if all(r["ok"] for r in res["devices"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())

"""Simulator speed: ``python -m toolkit.sim.bench [--duration 20] [--out bench.json]``.

Simulates a drive into a temporary folder and reports frames/s of the render + write loop
(one frame = RGB + depth + mask + its lidar scans, all written to disk), the time of the
whole run, CPU milliseconds per frame (all threads; less sensitive to other load on the
machine than wall time) and the cost of the parts: the camera raycast alone, the whole
camera render, a lidar scan and the writes of one frame (RGB, depth and mask PNGs through
the sequence writer; the depth PNG also alone). With ``--quickstart`` it also times one
full lap of the small house (the quickstart recipe's sequence). The 1-minute load average
is recorded at the start and the end: on a shared machine quote it with every figure.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np


def _per_call(fn: Any, n: int) -> tuple[float, float]:
    """(wall ms, CPU ms) per call of ``fn``."""
    w0, c0 = time.perf_counter(), time.process_time()
    for _ in range(n):
        fn()
    return (time.perf_counter() - w0) / n * 1e3, (time.process_time() - c0) / n * 1e3


def run_bench(duration_s: float = 20.0, preset: str = "small_house", seed: int = 0,
              quickstart: bool = False, workdir: Path | None = None,
              say: Callable[[str], None] | None = None,
              progress: Callable[..., Iterator[Any]] | None = None) -> dict[str, Any]:
    """Measure and return the figures (see the module docstring). ``say`` gets a line at
    each phase, ``progress`` wraps the simulation's frame loop (as rich's ``track``)."""
    say = say or (lambda _: None)
    from toolkit.io.depth import write_depth
    from toolkit.io.sequence import SequenceWriter
    from toolkit.sim.people import primitives_at
    from toolkit.sim.sensors import CameraRenderer, LidarRenderer
    from toolkit.sim.simulate import SimConfig, build_world, simulate

    tmp = Path(tempfile.mkdtemp(prefix="simbench-", dir=workdir))
    out: dict[str, Any] = {
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                    "load_avg_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None},
        "preset": preset, "duration_s": duration_s,
    }
    try:
        cfg = SimConfig(preset=preset, seed=seed, duration_s=duration_s, n_heldout=0)
        c0 = time.process_time()
        say(f"simulating {duration_s:g} s of driving in the {preset} (building the world "
            "first: tens of seconds)")
        res = simulate(cfg, tmp / "seq", progress)
        cpu = time.process_time() - c0
        out["frames"] = res.frames
        out["scans"] = res.scans
        # Two scopes, named: the render-and-write loop (the simulator's own frames/s) and
        # the whole run (world building and the end-of-run files too), which the CPU time
        # covers; set against each other they implied more than 200 % of 2 cores.
        out["frames_per_s"] = round(res.frames_per_s, 2)
        out["frames_per_s_scope"] = "render-and-write loop (timings_s.render_write_s)"
        out["total_s"] = round(res.seconds, 3)
        out["frames_per_s_whole_run"] = round(res.frames / max(res.seconds, 1e-9), 2)
        out["cpu_ms_per_frame"] = round(cpu / res.frames * 1e3, 2)
        out["cpu_ms_per_frame_scope"] = "whole run (process CPU time of simulate())"
        out["timings_s"] = {k: round(v, 3) for k, v in res.timings.items()}

        say("timing the parts (camera raycast and render, lidar scan, frame writes)")
        world = build_world(replace(cfg, n_people=2))
        cam_r = CameraRenderer(world.scene, world.rig.camera)
        las_r = LidarRenderer(world.scene, cfg.lidar)
        T = world.path.T_world_base(np.array([world.path.duration / 3]))[0]
        T_wc = T @ world.rig.T_base_camera
        T_wl = T @ world.rig.T_base_laser
        people = primitives_at(world.walkers, world.path.duration / 3)
        rng = np.random.default_rng(0)
        cam_r.render(T_wc)  # warm-up
        rays = cam_r._rays.copy()
        parts = {
            "raycast_640x480": _per_call(lambda: world.scene.cast(rays), 10),
            "camera_render": _per_call(
                lambda: cam_r.render(T_wc, people, cfg.camera.noise_std, rng), 10),
            "lidar_scan": _per_call(lambda: las_r.render(T_wl, people, rng), 50),
        }
        img = cam_r.render(T_wc, people, cfg.camera.noise_std, rng)
        # What the writer thread does per frame (RGB PNG, depth PNG, mask PNG, journal),
        # through the sequence writer itself so the PNG settings are the ones in use.
        wr = SequenceWriter(tmp / "w", world.rig, name="bench")
        stamp = iter(range(1, 10_000))
        parts["write_frame"] = _per_call(
            lambda: wr.add_frame(float(next(stamp)), img.rgb, img.depth, img.dynamic), 10)
        parts["png_depth"] = _per_call(lambda: write_depth(tmp / "d.png", img.depth), 10)
        out["parts_ms"] = {k: {"wall": round(w, 2), "cpu": round(c, 2)}
                           for k, (w, c) in parts.items()}
        if quickstart:
            c0 = time.process_time()
            say("simulating the quickstart's lap of the small house")
            q = simulate(SimConfig(preset="small_house", seed=seed), tmp / "quick", progress)
            out["quickstart"] = {"frames": q.frames, "total_s": round(q.seconds, 2),
                                 "frames_per_s": round(q.frames_per_s, 2),
                                 "cpu_ms_per_frame": round(
                                     (time.process_time() - c0) / q.frames * 1e3, 2),
                                 "drive_s": round(q.world.path.duration, 2)}
        if hasattr(os, "getloadavg"):  # other load during the run, as much as at its start
            out["machine"]["load_avg_1min_end"] = os.getloadavg()[0]
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m toolkit.sim.bench",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=20.0, help="seconds of driving")
    ap.add_argument("--preset", default="small_house", choices=["small_house", "large_building"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quickstart", action="store_true", help="also time a full quickstart lap")
    ap.add_argument("--out", type=Path, default=Path("runs/bench/sim_bench.json"))
    args = ap.parse_args(argv)
    if not args.duration > 1.0:
        ap.error(f"--duration {args.duration}: give more than 1 s of driving")
    if args.out.is_dir():
        ap.error(f"--out {args.out} is a folder; give the JSON file to write")
    from rich.progress import track

    res = run_bench(args.duration, args.preset, args.seed, args.quickstart,
                    say=lambda line: print(line, file=sys.stderr, flush=True),
                    progress=lambda it, total=None, description="": track(
                        it, total=total, description=description, transient=True))
    from toolkit.io.atomic import atomic_write_json

    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(args.out, res)
    print(json.dumps(res, indent=2))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

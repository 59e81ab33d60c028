"""What a checkpoint's save and load cost, SHA-256 included.

``--kind stage`` (the default): a float32 array of MIB mebibytes (a map) and a small dict,
as the fuse and tsdf stages save, with ``toolkit.recipe.checkpoint.Checkpoint``.
``--kind splat``: a splat ``Trainer`` of SH degree 3 with as many Gaussians as make MIB
mebibytes of parameters and Adam moments, saved with ``Trainer.save_checkpoint`` and read
back by a new trainer's ``resume`` (the file read, checked and loaded into it).

Each repeat saves the state and loads it back (the file in the page cache, as it is right
after a save). Prints one JSON object: the file's bytes, the sorted seconds of each step
(wall clock, and the process's CPU time for the loads) and the process's peak resident
memory before the first load and at the end (MiB). Run it with ``PYTHONPATH`` set to
another checkout to time that code (the "before" of a change).

    python benchmarks/checkpoint_cost.py 256 --repeats 5 --work /tmp/checkpoint_cost
"""

from __future__ import annotations

import argparse
import json
import resource
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

import toolkit
from toolkit.recipe.checkpoint import Checkpoint


def _peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux


def _stage(mib: int, work: Path) -> tuple[Path, Callable[[], None], Callable[[], None]]:
    n = mib * 2**20 // 4
    state = {"map": np.random.default_rng(0).random(n, dtype=np.float32),  # [n]
             "frames": 120}
    path = work / "checkpoint.pkl"

    def save() -> None:
        Checkpoint(path, "key", every_s=1).save(state)

    def load() -> None:
        got = Checkpoint(path, "key", every_s=1).load()
        if got is None or got["frames"] != 120 or len(got["map"]) != n:
            raise SystemExit(f"{path}: the checkpoint did not load back")

    return path, save, load


def _splat(mib: int, work: Path) -> tuple[Path, Callable[[], None], Callable[[], None]]:
    import torch

    from toolkit.camera import PinholeCamera
    from toolkit.splat.model import GaussianModel
    from toolkit.splat.trainer import TrainConfig, Trainer, TrainView, bytes_per_gaussian

    # parameters and two Adam moments: three quarters of bytes_per_gaussian (no gradient)
    n = mib * 2**20 * 4 // (3 * bytes_per_gaussian(3))
    g = torch.Generator().manual_seed(0)
    means = torch.rand(n, 3, generator=g) * 4 - 2 + torch.tensor([0.0, 0.0, 5.0])  # [n, 3]
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=1)  # [n, 4]
    model = GaussianModel(means, torch.full((n, 3), -3.0), quats, torch.zeros(n),
                          torch.rand(n, 3, generator=g), torch.zeros(n, 15, 3))
    cam = PinholeCamera.from_fov(16, 12, 70.0)
    views = [TrainView(torch.zeros(12, 16, 3, dtype=torch.uint8), cam, np.eye(4), name="v0")]
    cfg = TrainConfig(checkpoint_every=0)
    trainer = Trainer(model, views, cfg, work)
    for opt in trainer.optimizers.values():  # every moment filled, as after a first step
        for group in opt.param_groups:
            for p in group["params"]:
                p.grad = torch.randn(p.shape, generator=g)
        opt.step()

    def save() -> None:
        trainer.save_checkpoint()

    def load() -> None:
        again = Trainer(model, views, cfg, work)
        if not again.resume() or len(again.model) != n:
            raise SystemExit(f"{trainer.checkpoint_path()}: the checkpoint did not load back")

    return trainer.checkpoint_path(), save, load


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mib", type=int, help="size of the state, MiB")
    parser.add_argument("--kind", choices=("stage", "splat"), default="stage")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--work", type=Path, required=True, help="folder for the file")
    args = parser.parse_args()
    path, save, load = (_stage if args.kind == "stage" else _splat)(args.mib, args.work)
    saves, loads, load_cpu = [], [], []
    peak_before_load = None
    for _ in range(args.repeats):
        t = time.perf_counter()
        save()
        saves.append(time.perf_counter() - t)
        if peak_before_load is None:
            peak_before_load = _peak_mib()
        t, c = time.perf_counter(), time.process_time()
        load()
        loads.append(time.perf_counter() - t)
        load_cpu.append(time.process_time() - c)
    print(json.dumps({"code": str(Path(toolkit.__file__).parents[1]), "kind": args.kind,
                      "mib": args.mib, "file_bytes": path.stat().st_size,
                      "save_s": sorted(round(x, 3) for x in saves),
                      "load_s": sorted(round(x, 3) for x in loads),
                      "load_cpu_s": sorted(round(x, 3) for x in load_cpu),
                      "peak_rss_before_load_mib": round(peak_before_load or 0.0, 1),
                      "peak_rss_mib": round(_peak_mib(), 1)}))
    path.unlink()


if __name__ == "__main__":
    main()

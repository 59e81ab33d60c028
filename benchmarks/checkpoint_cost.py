"""What a stage checkpoint's save and load cost, SHA-256 included.

The state: a float32 array of MIB mebibytes (a map) and a small dict, as the fuse and
tsdf stages save. Each repeat saves it with ``toolkit.recipe.checkpoint.Checkpoint`` and
loads it back (the file in the page cache, as it is right after a save). Prints one JSON
object: the file's bytes and the sorted seconds of each step. Run it with ``PYTHONPATH``
set to another checkout to time that code (the "before" of a change).

    python benchmarks/checkpoint_cost.py 256 --repeats 5 --work /tmp/checkpoint_cost
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import toolkit
from toolkit.recipe.checkpoint import Checkpoint


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mib", type=int, help="size of the state's array, MiB")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--work", type=Path, required=True, help="folder for the file")
    args = parser.parse_args()
    n = args.mib * 2**20 // 4
    state = {"map": np.random.default_rng(0).random(n, dtype=np.float32),  # [n]
             "frames": 120}
    path = args.work / "checkpoint.pkl"
    saves, loads = [], []
    for _ in range(args.repeats):
        ck = Checkpoint(path, "key", every_s=1)
        t = time.perf_counter()
        ck.save(state)
        saves.append(time.perf_counter() - t)
        t = time.perf_counter()
        got = Checkpoint(path, "key", every_s=1).load()
        loads.append(time.perf_counter() - t)
        if got is None or got["frames"] != 120 or len(got["map"]) != n:
            raise SystemExit(f"{path}: the checkpoint did not load back")
    print(json.dumps({"code": str(Path(toolkit.__file__).parents[1]), "mib": args.mib,
                      "file_bytes": path.stat().st_size,
                      "save_s": sorted(round(x, 3) for x in saves),
                      "load_s": sorted(round(x, 3) for x in loads)}))
    path.unlink()


if __name__ == "__main__":
    main()

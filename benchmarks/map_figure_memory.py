"""Peak memory and time of drawing the slam2d map figure alone (``save_map_png``).

A synthetic N x N occupancy grid at 5 cm: free inside, one-cell walls every 200 cells
both ways, an unknown border row. Prints one JSON object: the process's resident memory
after building the grid (``grid_rss_gib``), its peak after drawing (``peak_gib``), their
difference (``drawing_gib``), the drawing's seconds and the figure's black (wall) pixels,
which must not be 0 (walls lost by pooling). Linux only (reads /proc/self/status).

    python benchmarks/map_figure_memory.py 20000 /tmp/map.png

Run it in a fresh process per size: the peak is the process's.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import cv2  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402,F401  (its own memory belongs to the baseline)
import numpy as np  # noqa: E402

from toolkit.io.occupancy import OccupancyMap  # noqa: E402
from toolkit.slam2d.plot import save_map_png  # noqa: E402


def _status_gib(key: str) -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key):
            return int(line.split()[1]) / 1024**2  # kB -> GiB
    raise KeyError(key)


def synthetic_grid(n: int, wall_every: int = 200) -> OccupancyMap:
    """[n, n] occupancy at 5 cm: free, walls every ``wall_every`` cells, unknown border."""
    occ = np.full((n, n), 0.05, np.float32)  # [n, n]
    occ[:, ::wall_every] = 0.95
    occ[::wall_every, :] = 0.95
    occ[0, :] = np.nan
    occ[-1, :] = np.nan
    return OccupancyMap(occ, 0.05, (0.0, 0.0, 0.0))


def main(argv: list[str] | None = None) -> dict[str, float | int]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("cells", type=int, help="grid side N (N x N cells)")
    parser.add_argument("out", type=Path, help="where to write the PNG")
    args = parser.parse_args(argv)
    n = args.cells
    grid = synthetic_grid(n)
    before = _status_gib("VmRSS")
    t0 = time.perf_counter()
    path = np.array([[1.0, 1.0], [n * 0.05 - 1, n * 0.05 - 1]])  # [2, 2] a diagonal
    save_map_png(args.out, grid, path, title=f"{n} x {n} cells")
    seconds = time.perf_counter() - t0
    peak = _status_gib("VmHWM")
    img = cv2.imread(str(args.out), cv2.IMREAD_GRAYSCALE)
    result = {"cells": n, "grid_rss_gib": round(before, 3), "peak_gib": round(peak, 3),
              "drawing_gib": round(peak - before, 3), "draw_seconds": round(seconds, 2),
              "png_height": int(img.shape[0]), "png_width": int(img.shape[1]),
              "black_pixels": int((img == 0).sum())}
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()

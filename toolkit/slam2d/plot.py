"""A PNG of the occupancy map with the trajectory drawn on it (matplotlib, no display)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from toolkit.io.atomic import atomic_path
from toolkit.io.occupancy import FREE, OCCUPIED, UNKNOWN, OccupancyMap


def save_map_png(
    path: Path | str,
    grid: OccupancyMap,
    trajectory_xy: np.ndarray | None = None,
    title: str | None = None,
    reference_xy: np.ndarray | None = None,
    dpi: int = 150,
    max_pixels: int = 4000,
) -> Path:
    """Map in grey (white free, black occupied, grey unknown) with the path in colour.

    trajectory_xy: [N, 2] world positions. reference_xy: [M, 2] optional second path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    img = grid.trinary()  # [H, W] uint8 map order
    shade = np.full(img.shape, 0.75, np.float32)  # [H, W] grey level
    shade[img == FREE] = 1.0
    shade[img == OCCUPIED] = 0.0
    shade[img == UNKNOWN] = 0.75
    H, W = img.shape
    del img
    x0, y0 = grid.origin[0], grid.origin[1]
    extent = (x0, x0 + W * grid.resolution, y0, y0 + H * grid.resolution)
    aspect = H / max(W, 1)
    size_in = min(12.0, max(6.0, max(W, H) / dpi))
    if max(W, H) * 1.0 > max_pixels:
        size_in = max_pixels / dpi
    fig, ax = plt.subplots(figsize=(size_in, max(3.0, size_in * aspect)))
    # Resampled as grey values, coloured after: the same pixels with nearest-neighbour
    # sampling, but matplotlib's default for a map larger than the figure colours every
    # cell first, as float64 RGBA (32 bytes a cell: Killian's 23 M-cell map took 2.2 GB).
    ax.imshow(shade, cmap="gray", vmin=0, vmax=1, origin="lower", extent=extent,
              interpolation="nearest", interpolation_stage="data")
    if reference_xy is not None and len(reference_xy):
        ax.plot(reference_xy[:, 0], reference_xy[:, 1], "-", color="tab:green", lw=0.6,
                label="ground truth (aligned)")
    if trajectory_xy is not None and len(trajectory_xy):
        ax.plot(trajectory_xy[:, 0], trajectory_xy[:, 1], "-", color="tab:red", lw=0.7,
                label="trajectory")
        ax.plot(*trajectory_xy[0], "o", color="tab:blue", ms=4, label="start")
    if reference_xy is not None or trajectory_xy is not None:
        ax.legend(loc="upper right", fontsize=7)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal")
    if title:
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    plt.close(fig)
    return path

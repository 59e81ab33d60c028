"""A PNG of the occupancy map with the trajectory drawn on it (matplotlib, no display)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from toolkit.io.atomic import atomic_path
from toolkit.io.occupancy import FREE, OCCUPIED, UNKNOWN, OccupancyMap

# Cells pooled a strip at a time: the pooling's temporaries stay this size (16 MB of
# float32) whatever the map's area.
_STRIP_CELLS = 1 << 22


def _pool_codes(codes: np.ndarray, f: int) -> np.ndarray:
    """[ceil(h/f), ceil(w/f)] uint8 map_saver codes of ``codes`` [h, w] (uint8 codes)
    pooled in f x f blocks: occupied if any cell is, else free if any cell is, else
    unknown - so a wall one cell thick stays in the figure (a mean or nearest sampling
    loses it among free cells). Blocks past the edge are padded with unknown."""
    h, w = codes.shape
    hr, wr = -(-h // f), -(-w // f)
    pad = np.full((hr * f, wr * f), UNKNOWN, np.uint8)  # [hr * f, wr * f]
    pad[:h, :w] = codes
    blocks = pad.reshape(hr, f, wr, f)
    out = np.full((hr, wr), UNKNOWN, np.uint8)
    out[(blocks == FREE).any(axis=(1, 3))] = FREE
    out[(blocks == OCCUPIED).any(axis=(1, 3))] = OCCUPIED
    return out


def pooled_map(grid: OccupancyMap, f: int) -> np.ndarray:
    """[ceil(H/f), ceil(W/f)] uint8 map_saver codes of ``grid`` pooled in f x f cell blocks
    (``_pool_codes``), a strip of rows at a time: besides the result, memory for one strip,
    not for copies of the whole grid."""
    H, W = grid.shape
    rows = f * max(1, _STRIP_CELLS // (f * f * -(-W // f)))  # a multiple of f
    parts = [_pool_codes(OccupancyMap(grid.occupancy[r:r + rows], grid.resolution,
                                      grid.origin).trinary(), f)
             for r in range(0, H, rows)]
    return np.concatenate(parts, axis=0) if parts else np.zeros((0, -(-W // f)), np.uint8)


def _shade(codes: np.ndarray) -> np.ndarray:
    shade = np.full(codes.shape, 0.75, np.float32)  # [h, w] grey level
    shade[codes == FREE] = 1.0
    shade[codes == OCCUPIED] = 0.0
    return shade


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
    A map of more cells than the plot has pixels is pooled first (``pooled_map``): the
    figure's memory is bounded by its pixels, not the map's area, and thin walls stay.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    H, W = grid.shape
    x0, y0 = grid.origin[0], grid.origin[1]
    extent = (x0, x0 + W * grid.resolution, y0, y0 + H * grid.resolution)
    aspect = H / max(W, 1)
    size_in = min(12.0, max(6.0, max(W, H) / dpi))
    if max(W, H) * 1.0 > max_pixels:
        size_in = max_pixels / dpi
    fig_in = (size_in, max(3.0, size_in * aspect))
    # The plot is smaller than the figure: pooled to the figure's pixels here, then to the
    # plot's once the layout says how large that is. Matplotlib drew the whole map, some
    # 28 bytes a cell at its peak (11 GB for 1 km x 1 km at 5 cm), and its nearest-cell
    # sampling dropped thin walls of a map larger than the plot.
    f = max(1, int(np.ceil(max(W / (fig_in[0] * dpi), H / (fig_in[1] * dpi)))))
    # [H, W] as drawn before pooling existed, else [ceil(H/f), ceil(W/f)]
    codes = grid.trinary() if f == 1 else pooled_map(grid, f)
    shade = _shade(codes)
    fig, ax = plt.subplots(figsize=fig_in)
    # Resampled as grey values, coloured after: the same pixels with nearest-neighbour
    # sampling, but matplotlib's default for a map larger than the figure colours every
    # cell first, as float64 RGBA (32 bytes a cell: Killian's 23 M-cell map took 2.2 GB).
    im = ax.imshow(shade, cmap="gray", vmin=0, vmax=1, origin="lower",
                   extent=_padded(extent, shade.shape, f, grid.resolution),
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
    ax.apply_aspect()
    box = ax.get_position()  # of the figure, after the layout and the equal aspect
    plot_px = (box.width * fig_in[0] * dpi, box.height * fig_in[1] * dpi)
    g = int(np.ceil(max(shade.shape[1] / plot_px[0], shade.shape[0] / plot_px[1])))
    if g > 1 or f > 1:
        if g > 1:  # pooled again, from the figure's pixels to the plot's (a small array)
            f *= g
            shade = _shade(_pool_codes(codes, g))
            im.set_data(shade)
            im.set_extent(_padded(extent, shade.shape, f, grid.resolution))
        # The pooled blocks past the map's edge (unknown) are outside the axes.
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    plt.close(fig)
    return path


def _padded(extent: tuple[float, float, float, float], shape: tuple[int, ...], f: int,
            resolution: float) -> tuple[float, float, float, float]:
    """The extent of a map pooled by ``f`` into ``shape``: its last blocks reach past the
    map's edge (padding), and the drawn cells must keep their size."""
    if f == 1:
        return extent
    return (extent[0], extent[0] + shape[1] * f * resolution,
            extent[2], extent[2] + shape[0] * f * resolution)

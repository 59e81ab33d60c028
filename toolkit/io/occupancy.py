"""Occupancy grids in the ROS ``map_server`` format: a PGM image plus a YAML file.

``map_saver`` writes 254 for free, 0 for occupied and 205 for unknown cells, with the
image's top row at the map's highest y (rows flipped from grid order), and a YAML with
``image``, ``resolution`` (m/px), ``origin`` [x, y, yaw] (pose of the lower-left pixel),
``negate``, ``occupied_thresh`` and ``free_thresh``. ``map_server`` reads a pixel x as
p = (255 - x) / 255 (x / 255 when negated): p > occupied_thresh is occupied, p <
free_thresh free, anything else unknown (``mode: trinary``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from toolkit.errors import InputError, MissingInputError
from toolkit.io.atomic import atomic_write_bytes, atomic_write_text
from toolkit.io.yaml_file import load_yaml

FREE, OCCUPIED, UNKNOWN = 254, 0, 205
# The thresholds a trinary map's YAML holds, whatever thresholds classified its cells:
# map_server reads the pixel 205 as p = 50 / 255 = 0.196, which is unknown only between
# these (ROS 1's map_saver writes them; nav2's since ros-navigation/navigation2#5278).
TRINARY_OCCUPIED_THRESH, TRINARY_FREE_THRESH = 0.65, 0.196


@dataclass
class OccupancyMap:
    """A grid in map order: row 0 is the lowest y, column 0 the lowest x."""

    occupancy: np.ndarray  # [H, W] float32 occupancy probability, NaN where unknown
    resolution: float  # m per cell
    origin: tuple[float, float, float]  # (x, y, yaw) of the lower-left cell's corner

    @property
    def shape(self) -> tuple[int, int]:
        H, W = self.occupancy.shape  # numpy 1.26 types shape tuple[int, ...]: unpacked, not cast
        return H, W

    def trinary(self, occupied_thresh: float = 0.65, free_thresh: float = 0.196) -> np.ndarray:
        """[H, W] uint8 map_saver pixel values (254 free, 0 occupied, 205 unknown), in map
        order (not flipped)."""
        p = self.occupancy
        out = np.full(p.shape, UNKNOWN, np.uint8)
        with np.errstate(invalid="ignore"):
            out[p > occupied_thresh] = OCCUPIED
            out[p < free_thresh] = FREE
        return out

    def cell_centers(self) -> tuple[np.ndarray, np.ndarray]:
        """x [W] and y [H] of cell centres in the map frame (origin yaw assumed 0)."""
        H, W = self.shape
        x = self.origin[0] + (np.arange(W) + 0.5) * self.resolution
        y = self.origin[1] + (np.arange(H) + 0.5) * self.resolution
        return x, y


def _pgm_bytes(img: np.ndarray, resolution: float) -> bytes:
    H, W = img.shape
    header = f"P5\n# CREATOR: toolkit.io.occupancy {resolution:.3f} m/pix\n{W} {H}\n255\n"
    header = header.encode()
    return header + np.ascontiguousarray(img, dtype=np.uint8).tobytes()


def write_occupancy(yaml_path: Path | str, grid: OccupancyMap, occupied_thresh: float = 0.65,
                    free_thresh: float = 0.196) -> Path:
    """Write ``<name>.yaml`` and ``<name>.pgm`` next to it (atomically); returns the PGM path.

    ``occupied_thresh`` and ``free_thresh`` classify the cells into map_saver's pixels; the
    YAML holds map_saver's own 0.65 and 0.196, the thresholds that read those pixels back as
    the same classes (given ones above 0.196, nav2's default 0.25 among them, read every
    unknown cell as free)."""
    yaml_path = Path(yaml_path)
    if yaml_path.suffix not in (".yaml", ".yml"):
        raise InputError(f"{yaml_path}: give the .yaml path; the .pgm goes next to it")
    pgm_path = yaml_path.with_suffix(".pgm")
    img = grid.trinary(occupied_thresh, free_thresh)[::-1]  # map_saver: top row = max y
    atomic_write_bytes(pgm_path, _pgm_bytes(img, grid.resolution))
    meta = {
        "image": pgm_path.name,
        "mode": "trinary",
        "resolution": float(grid.resolution),
        "origin": [float(v) for v in grid.origin],
        "negate": 0,
        "occupied_thresh": TRINARY_OCCUPIED_THRESH,
        "free_thresh": TRINARY_FREE_THRESH,
    }
    atomic_write_text(yaml_path, yaml.safe_dump(meta, sort_keys=False))
    return pgm_path


def read_occupancy(yaml_path: Path | str) -> OccupancyMap:
    """Read a map_server YAML + image into map order (row 0 = lowest y).

    Cells become 1.0 (occupied), 0.0 (free) or NaN (unknown) in trinary mode, the
    pixel's probability p in ``scale`` mode (NaN where map_server would say unknown), or
    pixel / 100 in ``raw`` mode (pixels above 100 unknown, as nav2's loader).
    """
    yaml_path = Path(yaml_path)
    meta = load_yaml(yaml_path, ValueError, "map YAML not found", FileNotFoundError)
    if not isinstance(meta, dict):
        raise InputError(f"{yaml_path}: expected a map_server mapping (image, resolution, "
                         "origin, ...)")
    for key in ("image", "resolution", "origin"):
        if key not in meta:
            raise InputError(f"{yaml_path}: missing field '{key}'")
    try:
        origin = tuple(float(v) for v in meta["origin"])
        resolution = float(meta["resolution"])
    except (TypeError, ValueError):
        origin, resolution = (), float("nan")
    if len(origin) != 3 or not np.all(np.isfinite(origin)):
        raise InputError(f"{yaml_path}: field 'origin' must be [x, y, yaw] (3 numbers), got "
                         f"{meta['origin']!r}")
    if not (np.isfinite(resolution) and resolution > 0):
        raise InputError(f"{yaml_path}: field 'resolution' must be a positive number of "
                         f"metres per cell, got {meta['resolution']!r}")
    mode = meta.get("mode", "trinary")
    if mode not in ("trinary", "scale", "raw"):
        raise InputError(f"{yaml_path}: field 'mode' is {mode!r}; map_server knows trinary, "
                         "scale and raw")
    img_path = (yaml_path.parent / str(meta["image"])).resolve()
    import cv2

    # OpenCV reads binary and ASCII PGM (and the PNGs some map savers write); a truncated
    # file reads as None like a missing one.
    img = cv2.imread(str(img_path), cv2.IMREAD_GRAYSCALE) if img_path.is_file() else None
    if img is None:
        what = "is not there" if not img_path.exists() else "is unreadable or truncated"
        raise MissingInputError(f"{yaml_path}: field 'image' names {img_path}, which {what}; "
                                "keep the map image next to its YAML (or fix the name), or "
                                "save the map again")
    x = img.astype(np.float32)
    p = x / 255.0 if int(meta.get("negate", 0)) else (255.0 - x) / 255.0
    occ_t = float(meta.get("occupied_thresh", 0.65))
    free_t = float(meta.get("free_thresh", 0.196))
    out = np.full(p.shape, np.nan, np.float32)
    if mode == "raw":  # the pixel is the occupancy in percent (negate does not apply)
        out[x <= 100] = x[x <= 100] / 100.0
    elif mode == "scale":
        known = (p > occ_t) | (p < free_t) | ((p >= free_t) & (p <= occ_t) & (x != UNKNOWN))
        out[known] = p[known]
    else:
        out[p > occ_t] = 1.0
        out[p < free_t] = 0.0
    return OccupancyMap(out[::-1].copy(), resolution, origin)

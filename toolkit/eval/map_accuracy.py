"""Map accuracy: distance from map points to the ground-truth mesh (Open3D raycasting)."""

from __future__ import annotations

from typing import Any

import numpy as np

from toolkit.eval.geometry import distance_scene, scene_distances, within_key


class MeshDistance:
    """Unsigned distance of points to a triangle mesh (built once, queried many times)."""

    def __init__(self, mesh: Any) -> None:
        # About the mesh's own origin: Open3D casts in float32 (see distance_scene).
        self.scene, self.origin = distance_scene(mesh)

    def distance(self, points: np.ndarray) -> np.ndarray:
        """[N] metres from points [N, 3] to the nearest surface."""
        return scene_distances(self.scene, self.origin, points)


def distance_stats(d: np.ndarray, thresholds: tuple[float, ...] = (0.02, 0.05, 0.10)) -> (
    dict[str, float]
):
    """mean, RMSE, median, 90th percentile (m) and the fraction under each threshold
    (``within_key``)."""
    if len({within_key(t) for t in thresholds}) < len(thresholds):
        raise ValueError(f"distance thresholds {list(thresholds)} name the same key twice "
                         "(whole millimetres are told apart)")
    d = np.asarray(d, np.float64)
    if len(d) == 0:
        return {"mean_m": float("nan"), "rmse_m": float("nan"), "median_m": float("nan"),
                "p90_m": float("nan"), "points": 0,
                **{within_key(t): float("nan") for t in thresholds}}
    out = {"mean_m": float(d.mean()), "rmse_m": float(np.sqrt(np.mean(d * d))),
           "median_m": float(np.median(d)), "p90_m": float(np.percentile(d, 90)),
           "points": int(len(d))}
    for t in thresholds:
        out[within_key(t)] = float(np.mean(d <= t))
    return out


"""Reconstruction accuracy against a ground-truth surface.

Accuracy: distance from each reconstructed point to the reference; completeness: from each
reference sample to the reconstruction; precision/recall/F-score at thresholds as in
Knapitsch et al. 2017 (Tanks and Temples). The reference is a point set sampled uniformly
from the ground-truth mesh (``sample_mesh``) so both directions are point-to-point.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from toolkit.errors import InputError

DEFAULT_THRESHOLDS_M = (0.02, 0.05, 0.10)


def threshold_tag(threshold_m: float) -> str:
    """``5cm`` for whole centimetres (the names reports use), ``15mm`` otherwise: rounded
    to centimetres, 5 mm and 15 mm both became ``2cm``."""
    mm = int(round(threshold_m * 1000))
    return f"{mm // 10}cm" if mm % 10 == 0 else f"{mm}mm"


def within_key(threshold_m: float) -> str:
    """``within_<threshold_tag>``: the key of the share of distances under a threshold."""
    return f"within_{threshold_tag(threshold_m)}"


def load_mesh(mesh: Any) -> Any:
    """An Open3D TriangleMesh as given, or read from a path (PLY, OBJ, ...)."""
    import open3d as o3d

    if isinstance(mesh, str | Path):
        path = Path(mesh)
        mesh = o3d.io.read_triangle_mesh(str(path))
        if len(mesh.triangles) == 0:
            raise InputError(f"{path}: no triangles (missing or not a mesh)")
    elif not isinstance(mesh, o3d.geometry.TriangleMesh):
        raise TypeError(f"mesh must be an Open3D TriangleMesh or a path to one, not "
                        f"{type(mesh).__name__}")
    return mesh


def sample_mesh(mesh: Any, spacing_m: float = 0.01, seed: int = 0,
                max_points: int = 2_000_000) -> np.ndarray:
    """[N, 3] points uniformly on an Open3D TriangleMesh, about one per ``spacing_m``^2
    but at most ``max_points`` (a 2 M cap: spacing grows on large meshes).

    The whole mesh: a map is only complete where the cameras looked, so the reports'
    completeness and F-scores use ``toolkit.baselines.common.observed_reference`` (the
    samples the cameras saw) instead."""
    import open3d as o3d

    mesh = load_mesh(mesh)
    area = mesh.get_surface_area()
    n = int(min(max_points, max(1000, area / spacing_m**2)))
    o3d.utility.random.seed(seed)
    return np.asarray(mesh.sample_points_uniformly(number_of_points=n).points)


def distance_scene(mesh: Any) -> tuple[Any, np.ndarray]:
    """(Open3D RaycastingScene of ``mesh``, its float64 origin [3]): the scene holds the
    mesh moved by -origin, and queries must be too. Open3D casts in float32, which spaces
    values 0.5 m apart at 5.4e6 m (UTM northings): a perfect map there scored 0.32 cm mean
    and 50 cm worst from its own mesh."""
    import open3d as o3d

    moved = o3d.geometry.TriangleMesh(load_mesh(mesh))  # a copy: the caller's stays put
    origin = moved.get_center() if moved.has_vertices() else np.zeros(3)
    moved.translate(-origin)  # in float64, before the float32 cast
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(moved))
    return scene, np.asarray(origin, dtype=np.float64)


def scene_distances(scene: Any, origin: np.ndarray, points: np.ndarray) -> np.ndarray:
    """[N] distances of points [N, 3] to a ``distance_scene``."""
    import open3d as o3d

    if len(points) == 0:
        return np.zeros(0)
    q = np.ascontiguousarray(np.asarray(points, dtype=np.float64) - origin, dtype=np.float32)
    return scene.compute_distance(o3d.core.Tensor(q)).numpy().astype(np.float64)


def mesh_distances(points: np.ndarray, mesh: Any) -> np.ndarray:
    """[N] exact distance from each point [N, 3] to the surface of an Open3D TriangleMesh
    (or a path to one)."""
    return scene_distances(*distance_scene(mesh), points)


def point_distances(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """[N] distance from each ``src`` point [N, 3] to its nearest ``dst`` point [M, 3]."""
    if len(dst) == 0:
        return np.full(len(src), np.inf)
    d, _ = cKDTree(dst).query(src, k=1, workers=-1)
    return d


def geometry_metrics(
    recon: np.ndarray, reference: np.ndarray,
    thresholds_m: tuple[float, ...] = DEFAULT_THRESHOLDS_M,
    accuracy_distances: np.ndarray | None = None,
    complete_points: np.ndarray | None = None,
    completeness_distances: np.ndarray | None = None,
) -> dict[str, float]:
    """Accuracy, completeness, Chamfer and precision/recall/F-score at each threshold.

    ``recon`` [N, 3] and ``reference`` [M, 3] in the same frame (metres). Keys carry units:
    ``accuracy_mean_m``, ``chamfer_m``, ``fscore_5cm`` ... Pass ``accuracy_distances`` [N]
    (e.g. exact point-to-mesh distances from ``mesh_distances``) to avoid the bias of
    measuring accuracy against a sampled reference, whose spacing adds to every distance.
    ``complete_points`` [K, 3]: the whole reconstruction when ``recon`` is a subsample of
    it, so that completeness and recall see every point (a subsample's gaps would make a
    denser map look less complete). ``completeness_distances`` [M]: from each reference
    point to a reconstructed *surface* (a mesh: ``mesh_distances(reference, mesh)``),
    instead of to its nearest point: points sampled on a mesh leave gaps, and a perfect
    mesh scored 1 cm of completeness and 0.955 recall at 2 cm. ``points`` counts the whole
    reconstruction given, ``points_scored`` the ones accuracy was measured on.
    """
    recon, reference = np.asarray(recon, np.float64), np.asarray(reference, np.float64)
    for name, a in (("recon", recon), ("reference", reference)):
        if a.ndim != 2 or a.shape[1] != 3:
            raise ValueError(f"{name} must be [N, 3] points, got shape {a.shape}")
    if len(recon) == 0 or len(reference) == 0:
        raise ValueError(f"need points on both sides, got {len(recon)} reconstructed and "
                         f"{len(reference)} reference points")
    acc = point_distances(recon, reference) if accuracy_distances is None else np.asarray(
        accuracy_distances, dtype=np.float64).reshape(-1)
    if len(acc) != len(recon):
        raise ValueError(f"{len(acc)} accuracy distances for {len(recon)} points")
    whole = recon if complete_points is None else np.asarray(
        complete_points, dtype=np.float64).reshape(-1, 3)
    if completeness_distances is not None:
        comp = np.asarray(completeness_distances, dtype=np.float64).reshape(-1)
        if len(comp) != len(reference):
            raise ValueError(f"{len(comp)} completeness distances for {len(reference)} "
                             "reference points")
    else:
        comp = point_distances(reference, whole)
    out: dict[str, float] = {
        "accuracy_mean_m": float(acc.mean()),
        "accuracy_median_m": float(np.median(acc)),
        "accuracy_rmse_m": float(np.sqrt(np.mean(acc**2))),
        "completeness_mean_m": float(comp.mean()),
        "completeness_median_m": float(np.median(comp)),
        "chamfer_m": float(0.5 * (acc.mean() + comp.mean())),
        "points": int(len(whole)),
        "points_scored": int(len(recon)),
    }
    tags = [threshold_tag(t) for t in thresholds_m]
    if len(set(tags)) < len(tags):
        raise ValueError(f"thresholds {list(thresholds_m)} name the same key twice (whole "
                         "millimetres are told apart)")
    for t, tag in zip(thresholds_m, tags, strict=True):
        p = float(np.mean(acc < t))
        r = float(np.mean(comp < t))
        f = 2 * p * r / (p + r) if p + r > 0 else 0.0
        out[f"precision_{tag}"] = p
        out[f"recall_{tag}"] = r
        out[f"fscore_{tag}"] = f
    return out

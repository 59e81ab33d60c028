"""Geometry metrics with hand-computed answers."""

import numpy as np
import pytest

from toolkit.eval.geometry import geometry_metrics, sample_mesh


def grid(n: int = 50, z: float = 0.0) -> np.ndarray:
    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    return np.stack([u.ravel(), v.ravel(), np.full(n * n, z)], -1)


def test_identical_clouds_are_perfect():
    m = geometry_metrics(grid(), grid())
    assert m["chamfer_m"] == 0 and m["fscore_2cm"] == 1.0


def test_offset_plane_hand_computed():
    # Every point 3 cm off: accuracy and completeness are exactly 0.03 m.
    m = geometry_metrics(grid(z=0.03), grid())
    assert m["accuracy_mean_m"] == pytest.approx(0.03)
    assert m["completeness_mean_m"] == pytest.approx(0.03)
    assert m["fscore_2cm"] == 0.0 and m["fscore_5cm"] == 1.0


def test_half_missing_lowers_recall_only():
    ref = grid()
    half = ref[ref[:, 0] < 0.5 - 1e-9]
    m = geometry_metrics(half, ref)
    assert m["precision_5cm"] == 1.0
    # Columns x = k/49 lie within 5 cm of the kept half (x < 0.5) for k <= 26: 27 of 50.
    assert m["recall_5cm"] == pytest.approx(27 / 50)
    assert m["fscore_5cm"] == pytest.approx(2 * 0.54 / 1.54)


def test_sample_mesh_covers_surface():
    import open3d as o3d

    box = o3d.geometry.TriangleMesh.create_box(1.0, 2.0, 0.5)
    pts = sample_mesh(box, spacing_m=0.05)
    assert len(pts) >= 1000
    assert np.all(pts.min(0) >= -1e-9) and np.all(pts.max(0) <= [1 + 1e-9, 2 + 1e-9, 0.5 + 1e-9])


def test_exact_accuracy_against_mesh():
    import open3d as o3d

    from toolkit.eval.geometry import mesh_distances

    box = o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0)
    pts = np.array([[0.5, 0.5, 1.03], [0.5, 0.5, 0.5], [2.0, 0.5, 0.5]])
    assert np.allclose(mesh_distances(pts, box), [0.03, 0.5, 1.0], atol=1e-6)


def test_mesh_functions_take_a_path_or_a_mesh(tmp_path):
    import open3d as o3d

    from toolkit.eval.geometry import mesh_distances, sample_mesh

    box = o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0)
    path = tmp_path / "box.ply"
    o3d.io.write_triangle_mesh(str(path), box)
    q = np.array([[0.5, 0.5, 2.0]])
    assert mesh_distances(q, path) == pytest.approx([1.0], abs=1e-5)
    assert mesh_distances(q, box) == pytest.approx([1.0], abs=1e-5)
    assert len(sample_mesh(str(path), 0.1)) >= 600  # 6 m^2 at one per 0.01 m^2
    with pytest.raises(TypeError, match="TriangleMesh"):
        mesh_distances(q, np.zeros((3, 3)))
    with pytest.raises(ValueError, match="no triangles"):
        sample_mesh(tmp_path / "missing.ply")


def test_a_perfect_mesh_is_complete_to_its_surface():
    """Completeness of a mesh measured to points sampled on it counts their gaps (a perfect
    mesh scored about 1 cm and 0.955 recall at 2 cm); to its surface it is complete."""
    import open3d as o3d

    from toolkit.eval.geometry import mesh_distances

    box = o3d.geometry.TriangleMesh.create_box(2.0, 2.0, 2.0)
    reference = sample_mesh(box, spacing_m=0.02, seed=1)  # [M, 3] the truth's samples
    recon = sample_mesh(box, spacing_m=0.02, seed=2)  # the "reconstruction": the same box
    sampled = geometry_metrics(recon, reference, accuracy_distances=mesh_distances(recon, box))
    exact = geometry_metrics(recon, reference, accuracy_distances=mesh_distances(recon, box),
                             completeness_distances=mesh_distances(reference, box))
    assert sampled["completeness_mean_m"] > 0.005 and sampled["recall_2cm"] < 0.99
    assert exact["completeness_mean_m"] < 1e-6 and exact["fscore_2cm"] == pytest.approx(1.0)
    # The map's size and the subsample scored are both reported.
    sub = geometry_metrics(recon[::4], reference, complete_points=recon)
    assert (sub["points"], sub["points_scored"]) == (len(recon), len(recon[::4]))
    with pytest.raises(ValueError, match="completeness distances"):
        geometry_metrics(recon, reference, completeness_distances=np.zeros(3))


def test_distance_thresholds_get_a_key_each():
    from toolkit.eval.map_accuracy import distance_stats

    d = np.array([0.004, 0.012, 0.018, 0.03])
    out = distance_stats(d, (0.005, 0.015, 0.02))
    assert (out["within_5mm"], out["within_15mm"], out["within_2cm"]) == (0.25, 0.5, 0.75)
    with pytest.raises(ValueError, match="same key twice"):
        distance_stats(d, (0.02, 0.0201))


def test_fscore_thresholds_get_a_key_each() -> None:
    """round(t * 100) named 15, 20 and 25 mm all 'fscore_2cm' (one kept) and 5 mm '0cm'."""
    pts = grid(20)
    out = geometry_metrics(pts, pts, (0.005, 0.015, 0.02))
    assert {"fscore_5mm", "fscore_15mm", "fscore_2cm"} <= set(out)
    with pytest.raises(ValueError, match="same key twice"):
        geometry_metrics(pts, pts, (0.02, 0.0201))


def test_mesh_distances_hold_in_georeferenced_coordinates() -> None:
    """Open3D casts in float32, whose values lie 0.5 m apart at a UTM northing of 5.4e6 m:
    points on the mesh read 0.32 cm mean, 50 cm worst from it there."""
    import open3d as o3d

    from toolkit.eval.geometry import mesh_distances
    from toolkit.eval.map_accuracy import MeshDistance

    room = o3d.geometry.TriangleMesh.create_box(4.0, 4.0, 2.5)
    room.translate(np.array([500000.0, 5400000.0, 300.0]))
    o3d.utility.random.seed(3)
    on_it = np.asarray(room.sample_points_uniformly(2000).points)  # [N, 3]
    assert mesh_distances(on_it, room).max() < 1e-3
    assert MeshDistance(room).distance(on_it).max() < 1e-3
    inside = np.array([[500002.0, 5400002.0, 301.5]])  # 1 m below the ceiling
    assert MeshDistance(room).distance(inside)[0] == pytest.approx(1.0, abs=1e-3)

"""3DGS PLY export: layout, pre-activation values, round trip, readable by Open3D."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from plyfile import PlyData

from toolkit.splat.export import ply_attributes, read_ply, write_ply
from toolkit.splat.model import GaussianModel, init_from_points
from toolkit.splat.sh import C0


def _random_model(n: int, degree: int, seed: int = 0) -> GaussianModel:
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2 - 1
    return GaussianModel(torch.randn(n, 3, generator=g), torch.randn(n, 3, generator=g) - 3,
                         torch.randn(n, 4, generator=g), torch.randn(n, generator=g),
                         torch.randn(n, 3, generator=g), torch.randn(n, k, 3, generator=g))


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_round_trip_and_layout(tmp_path: Path, degree: int) -> None:
    m = _random_model(257, degree)
    path = tmp_path / "splats.ply"
    write_ply(path, m)
    ply = PlyData.read(str(path))
    v = ply["vertex"]
    assert not ply.text and ply.byte_order == "<"
    names = [p.name for p in v.properties]
    k = (degree + 1) ** 2 - 1
    assert names == ply_attributes(k)
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[-8:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1",
                          "rot_2", "rot_3"]
    assert all(v.data.dtype[p] == np.dtype("<f4") for p in names)
    # pre-activation values, w-first quaternion, zero normals
    np.testing.assert_array_equal(v["opacity"], m.opacity_logits.detach().numpy())
    np.testing.assert_array_equal(v["scale_1"], m.log_scales[:, 1].detach().numpy())
    np.testing.assert_array_equal(v["rot_0"], m.quats[:, 0].detach().numpy())
    np.testing.assert_array_equal(v["nx"], 0)
    if k:
        # channel-major: f_rest_0..k-1 are the red coefficients, then green, then blue
        np.testing.assert_array_equal(v["f_rest_0"], m.shN[:, 0, 0].detach().numpy())
        np.testing.assert_array_equal(v[f"f_rest_{k}"], m.shN[:, 0, 1].detach().numpy())
        np.testing.assert_array_equal(v[f"f_rest_{2 * k + 1}"], m.shN[:, 1, 2].detach().numpy())
    back = read_ply(path)
    for name, p in m.params.items():
        assert torch.equal(back.params[name], p.detach()), name


def test_open3d_reads_positions(tmp_path: Path) -> None:
    o3d = pytest.importorskip("open3d")
    m = _random_model(100, 3)
    path = tmp_path / "splats.ply"
    write_ply(path, m)
    pc = o3d.io.read_point_cloud(str(path))
    np.testing.assert_allclose(np.asarray(pc.points), m.means.detach().numpy(), atol=1e-6)


def test_colour_convention(tmp_path: Path) -> None:
    """A point's colour survives init -> PLY as the viewers decode it (0.5 + C0 f_dc)."""
    rgb = np.array([[0.9, 0.2, 0.4], [0.1, 0.5, 0.7]])
    m = init_from_points(np.array([[0.0, 0, 0], [1.0, 0, 0]]), rgb, sh_degree=1)
    write_ply(tmp_path / "c.ply", m)
    v = PlyData.read(str(tmp_path / "c.ply"))["vertex"]
    decoded = 0.5 + C0 * np.stack([v["f_dc_0"], v["f_dc_1"], v["f_dc_2"]], 1)
    np.testing.assert_allclose(decoded, rgb, atol=1e-6)
    np.testing.assert_allclose(1 / (1 + np.exp(-v["opacity"])), 0.1, atol=1e-6)


def test_reader_errors(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        read_ply(tmp_path / "missing.ply")
    o3d = pytest.importorskip("open3d")
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.zeros((3, 3))))
    o3d.io.write_point_cloud(str(tmp_path / "cloud.ply"), pc)
    with pytest.raises(ValueError, match="not a 3DGS PLY"):
        read_ply(tmp_path / "cloud.ply")


def test_init_from_points_scales_and_budget() -> None:
    # a grid with 0.1 m spacing: the 3 nearest neighbours are 0.1 m away
    g = np.stack(np.meshgrid(np.arange(10), np.arange(10), [0.0]), -1).reshape(-1, 3) * 0.1
    m = init_from_points(g, None, sh_degree=2)
    assert len(m) == 100 and m.shN.shape == (100, 8, 3)
    interior = (g[:, 0] > 0.05) & (g[:, 0] < 0.85) & (g[:, 1] > 0.05) & (g[:, 1] < 0.85)
    np.testing.assert_allclose(m.scales.detach().numpy()[interior], 0.1, rtol=1e-5)
    assert torch.equal(m.quats[:, 0], torch.ones(100))
    np.testing.assert_allclose(m.opacities.detach().numpy(), 0.1, rtol=1e-5)
    sub = init_from_points(g, None, budget=30)
    assert len(sub) == 30
    dup = init_from_points(np.zeros((5, 3)), None)  # all duplicates: finite, positive scale
    assert torch.isfinite(dup.log_scales).all()


def test_non_finite_inputs_and_models_are_refused(tmp_path: Path) -> None:
    pts = np.array([[0.0, 0, 0], [1.0, 0, 0], [0.0, 1, 0], [0.0, 0, 1]])
    rgb = np.array([[0.2, 0.3, 0.4], [np.nan, 0.5, 0.5], [0.1, 0.1, 0.1], [1.004, 0.5, 0.5]])
    m = init_from_points(pts, rgb, sh_degree=0)
    assert len(m) == 3  # the NaN colour's point is left out
    # a float colour a hair over 1 is still a 0..1 cloud, not 8-bit
    assert float(m.params["sh0"][-1, 0].detach() * C0 + 0.5) == pytest.approx(1.0, abs=1e-6)
    dark = init_from_points(pts, np.ones((4, 3), np.uint8), sh_degree=0)  # 8-bit, all 1
    assert float(dark.params["sh0"][0, 0].detach() * C0 + 0.5) == pytest.approx(1 / 255, abs=1e-6)
    with pytest.raises(ValueError, match="3 colours for 4 points"):
        init_from_points(pts, rgb[:3])
    with torch.no_grad():
        m.params["means"][1, 0] = float("nan")
    with pytest.raises(ValueError, match="1 of 3 Gaussians have non-finite"):
        write_ply(tmp_path / "m.ply", m)
    assert not (tmp_path / "m.ply").exists()


def test_unreadable_ply_names_the_file(tmp_path: Path) -> None:
    bad = tmp_path / "cut.ply"
    bad.write_text("ply\nformat ascii 1.0\nelement vertex 3\n")
    with pytest.raises(ValueError, match=r"cut.ply: not a readable PLY file"):
        read_ply(bad)


def test_one_nan_colour_does_not_turn_an_8_bit_float_cloud_white() -> None:
    pts = np.array([[0.0, 0, 0], [1.0, 0, 0], [0.0, 1, 0]])
    rgb = np.array([[200.0, 40.0, 90.0], [np.nan, 0.0, 0.0], [10.0, 20.0, 30.0]])
    m = init_from_points(pts, rgb, sh_degree=0)
    colour = m.params["sh0"].detach().numpy() * C0 + 0.5  # [2, 3]
    np.testing.assert_allclose(colour, rgb[[0, 2]] / 255.0, atol=1e-6)

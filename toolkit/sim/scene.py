"""The static world as one textured triangle mesh plus an Open3D raycasting scene.

Everything static is built from boxes (walls, floors, furniture parts); each box face gets
its own four vertices so that it carries its own material, tint and texture coordinates.
Per triangle we keep what the renderer needs after a ray hits it: the material, a colour
multiplier (tint x fixed Lambert shading), the texture coordinates of its three corners,
and its plane in float64 so lidar ranges can be refined to float64 exactness (Embree
intersects in float32).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import open3d as o3d

from toolkit.errors import WriteError
from toolkit.sim.textures import MATERIAL_ID, TILE, TextureBank

# Fixed sun-like light: shading depends only on the surface, never on the viewer, so a
# surface has the same colour in every image (what photometric losses assume).
LIGHT_DIR = np.array([0.35, 0.55, 1.0]) / np.linalg.norm([0.35, 0.55, 1.0])
AMBIENT = 0.6

FACES = ("+x", "-x", "+y", "-y", "+z", "-z")
# Per face: outward normal axis/sign and the two in-plane axes used for texture (u, v).
_FACE_AXES = {
    "+x": (0, 1.0, 1, 2), "-x": (0, -1.0, 1, 2),
    "+y": (1, 1.0, 0, 2), "-y": (1, -1.0, 0, 2),
    "+z": (2, 1.0, 0, 1), "-z": (2, -1.0, 0, 1),
}
INVALID_ID = np.iinfo(np.uint32).max  # Open3D's primitive id of a ray that hit nothing


@dataclass
class Surface:
    """Look of one box face: material name, RGB tint, texture mapping."""

    material: str
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)
    # "world": texture coordinates from world position (patterns continue across boxes);
    # "local": from the box's own frame; "fit": the whole tile stretched over the face.
    mapping: str = "world"
    uv_offset: tuple[float, float] = (0.0, 0.0)  # texels


@dataclass
class Box:
    """An oriented box: centre [3], size [3] along its own axes, yaw about +z."""

    center: np.ndarray  # [3] metres
    size: np.ndarray  # [3] metres
    yaw: float = 0.0
    surface: Surface = field(default_factory=lambda: Surface("paint"))
    faces: dict[str, Surface] = field(default_factory=dict)  # per-face overrides
    label: str = "object"  # wall | floor | ceiling | furniture kind ...

    def __post_init__(self) -> None:
        self.center = np.asarray(self.center, dtype=np.float64).reshape(3)
        self.size = np.asarray(self.size, dtype=np.float64).reshape(3)

    def rotation(self) -> np.ndarray:
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    def footprint(self) -> np.ndarray:
        """[4, 2] corners in the xy plane (counter-clockwise)."""
        hx, hy = self.size[:2] / 2
        local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
        return local @ self.rotation()[:2, :2].T + self.center[:2]


@dataclass
class SceneMesh:
    """Triangle soup with per-triangle appearance."""

    vertices: np.ndarray  # [V, 3] float64
    triangles: np.ndarray  # [T, 3] int32
    material: np.ndarray  # [T] int32 material id
    uv: np.ndarray  # [T, 3, 2] float32 level-0 texel coordinates of the corners
    tint: np.ndarray  # [T, 3] float32 colour multiplier (tint x shading)
    label: np.ndarray  # [T] int32 index into ``labels``
    labels: list[str]

    @property
    def normals(self) -> np.ndarray:
        """[T, 3] float64 unit normals (counter-clockwise winding seen from outside)."""
        v = self.vertices[self.triangles]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        return n / np.linalg.norm(n, axis=1, keepdims=True)


def _face_template() -> tuple[np.ndarray, np.ndarray]:
    """Unit-box face corners [6, 4, 3] (signs, counter-clockwise from outside), normals [6, 3]."""
    corners = np.zeros((6, 4, 3))
    normals = np.zeros((6, 3))
    for f, key in enumerate(FACES):
        axis, sign, a1, a2 = _FACE_AXES[key]
        for k, (s1, s2) in enumerate(((-1, -1), (1, -1), (1, 1), (-1, 1))):
            corners[f, k, axis] = sign
            corners[f, k, a1] = s1
            corners[f, k, a2] = s2
        # Winding: (c1-c0) x (c2-c0) must point along the outward normal.
        n = np.cross(corners[f, 1] - corners[f, 0], corners[f, 2] - corners[f, 0])
        if n[axis] * sign < 0:
            corners[f] = corners[f, ::-1]
        normals[f, axis] = sign
    return corners, normals


_TEMPLATE, _NORMALS = _face_template()
_MAPPING = {"world": 0, "local": 1, "fit": 2}


def _planar_uv(p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """[F, 4, 2] metres along the face: x/y on horizontal faces, (horizontal, -z) on walls."""
    horiz = np.abs(n[:, 2]) > 0.9  # [F]
    h = np.hypot(n[:, 0], n[:, 1])
    t = np.stack([-n[:, 1], n[:, 0]], -1) / np.where(h > 0, h, 1.0)[:, None]  # [F, 2]
    vert_uv = np.stack([np.einsum("fkj,fj->fk", p[..., :2], t), -p[..., 2]], -1)
    return np.where(horiz[:, None, None], p[..., :2], vert_uv)


def shade(normals: np.ndarray) -> np.ndarray:
    """[T] view-independent brightness of surfaces with unit normals [T, 3]."""
    return (AMBIENT + (1.0 - AMBIENT) * (0.5 + 0.5 * normals @ LIGHT_DIR)).astype(np.float32)


def build_mesh(boxes: Sequence[Box], bank: TextureBank) -> SceneMesh:
    """Triangulate boxes (12 triangles each, box by box) with their appearance."""
    B = len(boxes)
    if B == 0:
        raise ValueError("a scene needs at least one box")
    C = np.array([b.center for b in boxes])  # [B, 3]
    S = np.array([b.size for b in boxes])  # [B, 3]
    yaw = np.array([b.yaw for b in boxes])
    R = np.zeros((B, 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1] = np.cos(yaw), -np.sin(yaw), np.sin(yaw), \
        np.cos(yaw)
    R[:, 2, 2] = 1.0
    local = _TEMPLATE[None] * (S / 2)[:, None, None, :]  # [B, 6, 4, 3] box frame
    world = np.einsum("bij,bfkj->bfki", R, local) + C[:, None, None, :]
    n_world = np.einsum("bij,fj->bfi", R, _NORMALS)  # [B, 6, 3]

    label_names: list[str] = []
    label_id: dict[str, int] = {}
    mat = np.zeros((B, 6), np.int32)
    tint = np.zeros((B, 6, 3))
    mapping = np.zeros((B, 6), np.int32)
    offset = np.zeros((B, 6, 2))
    label = np.zeros(B, np.int32)
    for i, box in enumerate(boxes):
        if box.label not in label_id:
            label_id[box.label] = len(label_names)
            label_names.append(box.label)
        label[i] = label_id[box.label]
        for f, key in enumerate(FACES):
            surf = box.faces.get(key, box.surface)
            if surf.material not in MATERIAL_ID:
                raise ValueError(f"unknown material {surf.material!r} on a {box.label}")
            mat[i, f] = MATERIAL_ID[surf.material]
            tint[i, f] = surf.tint
            mapping[i, f] = _MAPPING[surf.mapping]
            offset[i, f] = surf.uv_offset

    F = B * 6
    world_f = world.reshape(F, 4, 3)
    nw = n_world.reshape(F, 3)
    nl = np.tile(_NORMALS, (B, 1))
    tpm = bank.texels_per_metre[mat.reshape(F)].astype(np.float64)  # [F]
    # "world": positions in the world (patterns continue across boxes); "local": box frame.
    uv_world = _planar_uv(world_f, nw)
    uv_local = _planar_uv(local.reshape(F, 4, 3), nl)
    m = mapping.reshape(F)
    uv = np.where((m == 1)[:, None, None], uv_local, uv_world)
    # A large positive base keeps coordinates positive so int truncation equals floor.
    uv = uv * tpm[:, None, None] + offset.reshape(F, 1, 2) + 64.0 * TILE
    # "fit" (pictures): the tile spans the face once, upright, half a texel inside.
    fit = (m == 2) | (tpm == 0)
    if fit.any():
        wf, nf = world_f[fit], nw[fit]
        box_y = np.repeat(R[:, :, 1], 6, axis=0)[fit]
        up = np.where((np.abs(nf[:, 2]) < 0.9)[:, None], np.array([0.0, 0.0, 1.0]), box_y)
        right = np.cross(up, nf)  # looking at the face, u grows to the right
        cu = np.einsum("fkj,fj->fk", wf, right)
        cv = -np.einsum("fkj,fj->fk", wf, up)

        def span(c: np.ndarray) -> np.ndarray:
            lo = c.min(1, keepdims=True)
            return 0.5 + (c - lo) / np.maximum(np.ptp(c, axis=1, keepdims=True), 1e-9) * (
                TILE - 1)

        uv[fit] = np.stack([span(cu), span(cv)], -1)

    tri_idx = np.array([[0, 1, 2], [0, 2, 3]])
    base = (np.arange(F) * 4)[:, None, None]
    triangles = (base + tri_idx[None]).reshape(-1, 3).astype(np.int32)  # [2F, 3]
    mesh = SceneMesh(
        vertices=world_f.reshape(-1, 3),
        triangles=triangles,
        material=np.repeat(mat.reshape(F), 2),
        uv=uv[:, tri_idx].reshape(-1, 3, 2).astype(np.float32),
        tint=np.repeat(tint.reshape(F, 3), 2, axis=0).astype(np.float32),
        label=np.repeat(label, 12),
        labels=label_names,
    )
    mesh.tint = (mesh.tint * shade(mesh.normals)[:, None]).astype(np.float32)
    return mesh


class Scene:
    """The static mesh, its texture bank and a raycasting scene built once."""

    def __init__(self, mesh: SceneMesh, bank: TextureBank) -> None:
        self.mesh = mesh
        self.bank = bank
        self.raycaster = o3d.t.geometry.RaycastingScene()
        self.raycaster.add_triangles(
            o3d.core.Tensor(mesh.vertices.astype(np.float32)),
            o3d.core.Tensor(mesh.triangles.astype(np.uint32)),
        )
        n = mesh.normals
        v0 = mesh.vertices[mesh.triangles[:, 0]]
        self.tri_normal = n  # [T, 3] float64
        self.tri_d = np.einsum("ij,ij->i", n, v0)  # [T] plane: n . p = d (float64)
        # Appearance tables with one extra row for rays that hit nothing (drawn black).
        T = len(mesh.triangles)
        uv0 = mesh.uv[:, 0]
        self.tri_uvaff = np.zeros((T + 1, 6), np.float32)  # u0 v0 du1 dv1 du2 dv2
        self.tri_uvaff[:T, 0:2] = uv0
        self.tri_uvaff[:T, 2:4] = mesh.uv[:, 1] - uv0
        self.tri_uvaff[:T, 4:6] = mesh.uv[:, 2] - uv0
        self.tri_uvaff_cols = [np.ascontiguousarray(self.tri_uvaff[:, k]) for k in range(6)]
        self.tri_tint = np.zeros((T + 1, 3), np.float32)
        self.tri_tint[:T] = mesh.tint
        self.tri_material = np.zeros(T + 1, np.int32)
        self.tri_material[:T] = mesh.material
        # Where each triangle's material starts in the flat texel array (int32: < 2^31).
        self.tri_tex_start = bank.offset[self.tri_material, 0].astype(np.int32)
        tpm = bank.texels_per_metre[mesh.material]
        # Pictures are stretched over their face: approximate their density from its size.
        area = 0.5 * np.linalg.norm(np.cross(
            mesh.vertices[mesh.triangles[:, 1]] - v0, mesh.vertices[mesh.triangles[:, 2]] - v0),
            axis=1)
        tpm = np.where(tpm > 0, tpm, TILE / np.sqrt(2.0 * area + 1e-9))
        self.tri_tpm = np.zeros(T + 1, np.float32)  # texels per metre, for mip selection
        self.tri_tpm[:T] = tpm
        self.n_triangles = T

    @classmethod
    def from_boxes(cls, boxes: Sequence[Box], bank: TextureBank) -> Scene:
        return cls(build_mesh(boxes, bank), bank)

    def cast(self, rays: np.ndarray) -> dict[str, np.ndarray]:
        """Cast rays [N, 6] float32 (origin, direction); Open3D's result as numpy arrays.

        ``t_hit`` is in units of the direction's length (so rays with camera-frame z = 1
        return z-depth directly); ``primitive_ids`` is ``INVALID_ID`` on a miss.
        """
        out = self.raycaster.cast_rays(o3d.core.Tensor.from_numpy(rays))
        return {k: v.numpy() for k, v in out.items()}

    def refine_t(self, origin: np.ndarray, dirs: np.ndarray, prim: np.ndarray) -> np.ndarray:
        """[N] float64 ray parameters recomputed from the hit triangles' exact planes.

        ``origin`` [3] or [N, 3], ``dirs`` [N, 3]; misses give inf. Embree's float32
        intersection is good to about 1e-6 relative; this is float64-exact.
        """
        hit = prim != INVALID_ID
        t = np.full(len(prim), np.inf)
        idx = prim[hit].astype(np.int64)
        n = self.tri_normal[idx]
        o = origin if np.ndim(origin) == 1 else origin[hit]
        num = self.tri_d[idx] - (n @ o if np.ndim(origin) == 1 else np.einsum("ij,ij->i", n, o))
        t[hit] = num / np.einsum("ij,ij->i", n, dirs[hit])
        return t

    def to_open3d(self) -> o3d.geometry.TriangleMesh:
        """Legacy Open3D mesh with vertex colours (each face's mean texture colour x tint)."""
        m = self.mesh
        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(m.vertices),
            o3d.utility.Vector3iVector(m.triangles),
        )
        col = self.bank.mean_rgb[m.material] * m.tint  # [T, 3]
        vcol = np.zeros((len(m.vertices), 3))
        vcol[m.triangles.reshape(-1)] = np.repeat(col, 3, axis=0)
        mesh.vertex_colors = o3d.utility.Vector3dVector(vcol.clip(0, 1))
        mesh.compute_triangle_normals()
        return mesh

    def write_ply(self, path: Path) -> None:
        """Write the coloured mesh (atomically) for ground-truth geometry evaluation."""
        from toolkit.io.atomic import atomic_path

        with atomic_path(path) as tmp:
            if not o3d.io.write_triangle_mesh(str(tmp), self.to_open3d(), write_ascii=False):
                raise WriteError(f"{path}: could not write mesh")

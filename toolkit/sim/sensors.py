"""Camera and 2D lidar rendering of the static scene plus people.

Camera: one ray per pixel through the (distorted) pixel centre, precomputed once in the
camera frame with z = 1, so Open3D's ray parameter *is* the z-depth. Colour comes from
the hit triangle's material at the texture coordinates interpolated with the hit's
barycentrics, sampled from a mip level chosen by the pixel's footprint on the surface
(less aliasing far away and at grazing angles), times the triangle's tint and shading.

Lidar: beams in the laser's xy plane; static hits are refined to float64 from the hit
triangle's exact plane, people are intersected in float64, so noise-free ranges are exact
to float64 rounding. Then Gaussian noise, random dropouts (NaN, more likely at grazing
incidence), and out-of-range beams (+inf beyond range_max, -inf below range_min, as
REP 117 says).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from toolkit.camera import PinholeCamera
from toolkit.geometry import se3
from toolkit.sim.people import (
    BOUND_R,
    HEAD_R,
    HEAD_Z,
    Primitive,
    intersect,
    intersect_cols,
    surface_normal,
)
from toolkit.sim.scene import LIGHT_DIR, Scene
from toolkit.sim.textures import LEVELS, TILE

# Base link -> camera optical frame (REP 103: optical x right, y down, z forward).
R_BASE_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True)
class CameraSpec:
    """The simulated camera: intrinsics, mount on the base, rate and noise."""

    width: int = 640
    height: int = 480
    fx: float = 525.0
    fy: float = 525.0
    cx: float | None = None  # None: image centre
    cy: float | None = None
    distortion: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)  # OpenCV k1 k2 p1 p2 k3
    rate_hz: float = 10.0
    mount_xyz: tuple[float, float, float] = (0.10, 0.0, 0.45)  # in base_link, metres
    pitch_deg: float = 5.0  # positive looks down
    noise_std: float = 0.0  # Gaussian image noise, grey levels (optional; PNGs get 2x bigger)

    def camera(self) -> PinholeCamera:
        cx = (self.width - 1) / 2 if self.cx is None else self.cx
        cy = (self.height - 1) / 2 if self.cy is None else self.cy
        return PinholeCamera(self.width, self.height, self.fx, self.fy, cx, cy,
                             np.asarray(self.distortion, dtype=np.float64))

    def T_base_camera(self) -> np.ndarray:
        """[4, 4] optical frame in base_link: mount position, pitched down about base y."""
        p = np.radians(self.pitch_deg)
        Ry = np.array([[np.cos(p), 0.0, np.sin(p)], [0.0, 1.0, 0.0],
                       [-np.sin(p), 0.0, np.cos(p)]])
        return se3(Ry @ R_BASE_OPTICAL, self.mount_xyz)


@dataclass(frozen=True)
class LidarSpec:
    """The simulated planar lidar."""

    beams: int = 360
    fov_deg: float = 360.0
    rate_hz: float = 10.0
    range_min: float = 0.12
    range_max: float = 12.0
    noise_std: float = 0.01  # metres
    dropout: float = 0.01  # probability a beam returns nothing (NaN)
    mount_xyz: tuple[float, float, float] = (0.0, 0.0, 0.25)
    time_offset_s: float = 0.043  # first scan after the first image (not synchronised)

    @property
    def angle_min(self) -> float:
        return -np.radians(self.fov_deg) / 2

    @property
    def angle_increment(self) -> float:
        full = abs(self.fov_deg - 360.0) < 1e-9
        return np.radians(self.fov_deg) / (self.beams if full else self.beams - 1)

    def angles(self) -> np.ndarray:
        """[B] beam angles, counter-clockwise from +x."""
        return self.angle_min + np.arange(self.beams) * self.angle_increment

    def T_base_laser(self) -> np.ndarray:
        return se3(np.eye(3), self.mount_xyz)


@dataclass
class CameraImage:
    rgb: np.ndarray  # [H, W, 3] uint8
    depth: np.ndarray  # [H, W] float32 z-depth metres, 0 where nothing was hit
    dynamic: np.ndarray  # [H, W] bool: pixel shows a person
    material: np.ndarray | None = None  # [H, W] int32 material id (-1 person / miss)


@dataclass
class LidarReturn:
    ranges: np.ndarray  # [B] float64 with noise, dropouts (NaN) and out-of-range (+-inf)
    true_ranges: np.ndarray  # [B] float64 noise-free distance to the first surface (inf: none)
    dynamic: np.ndarray  # [B] bool: the beam hit a person
    extra: dict = field(default_factory=dict)


class CameraRenderer:
    """Renders RGB, z-depth and the dynamic mask of one camera in one scene."""

    def __init__(self, scene: Scene, camera: PinholeCamera) -> None:
        self.scene = scene
        self.camera = camera
        H, W = camera.height, camera.width
        self.rays_cam = camera.pixel_rays().reshape(-1, 3).astype(np.float32)  # [N, 3] z = 1
        self.norm2 = np.einsum("ij,ij->i", self.rays_cam, self.rays_cam)  # [N] |d|^2
        self._rays = np.empty((H * W, 6), np.float32)  # reused cast buffer
        self._rays_cols = [np.ascontiguousarray(self.rays_cam[:, k]) for k in range(3)]
        # |d|^2 / f folds the per-pixel part of the mip footprint into one array.
        self.norm2 = (self.norm2 / np.sqrt(camera.fx * camera.fy)).astype(np.float32)
        off = scene.bank.offset  # [M, LEVELS]
        self._lvl_start = (off[0] - off[0, 0]).astype(np.int32)  # [LEVELS]
        if not np.all(off - off[:, :1] == self._lvl_start):
            raise ValueError("texture pyramids must share one layout")
        self._lvl_size = (TILE >> np.arange(LEVELS)).astype(np.int32)
        self._noise_bank: np.ndarray | None = None

    def render(self, T_world_camera: np.ndarray, people: list[Primitive] | None = None,
               noise_std: float = 0.0, rng: np.random.Generator | None = None,
               want_material: bool = False) -> CameraImage:
        """One image from ``T_world_camera`` [4, 4] with people shapes (optional).

        Hot loop: np.take instead of fancy indexing and no BLAS calls on [N, 3] arrays
        (both are several times slower here, and BLAS threads fight the raycaster's).
        """
        H, W = self.camera.height, self.camera.width
        sc = self.scene
        R = np.asarray(T_world_camera[:3, :3], np.float64)
        o = np.asarray(T_world_camera[:3, 3], np.float64)
        rays = self._rays
        rays[:, :3] = o.astype(np.float32)
        rc = self._rays_cols
        for k in range(3):
            rays[:, 3 + k] = rc[0] * np.float32(R[k, 0]) + rc[1] * np.float32(R[k, 1]) + \
                rc[2] * np.float32(R[k, 2])
        dirs = rays[:, 3:]
        hit = sc.cast(rays)
        t = hit["t_hit"]  # [N] float32 z-depth (inf on a miss)
        idx = np.minimum(hit["primitive_ids"], sc.n_triangles)  # misses -> the black row
        bary = hit["primitive_uvs"]  # [N, 2]
        b0, b1 = bary[:, 0], bary[:, 1]
        g = [np.take(col, idx) for col in sc.tri_uvaff_cols]  # 6 x [N]
        u = g[0] + b0 * g[2] + b1 * g[4]  # level-0 texel coordinates
        v = g[1] + b0 * g[3] + b1 * g[5]
        # Mip level from the pixel footprint: texels per pixel = tpm * range / (f * cos).
        nrm = hit["primitive_normals"]
        ndotd = np.abs(nrm[:, 0] * dirs[:, 0] + nrm[:, 1] * dirs[:, 1] + nrm[:, 2] * dirs[:, 2])
        rho = np.take(sc.tri_tpm, idx) * t * self.norm2 / np.maximum(ndotd, 1e-3)
        lvl = np.clip(np.frexp(rho)[1] - 1, 0, LEVELS - 1).astype(np.int32)
        size = np.take(self._lvl_size, lvl)  # texels per side at that level
        mask = size - 1
        iu = (u.astype(np.int32) >> lvl) & mask
        iv = (v.astype(np.int32) >> lvl) & mask
        # Every material's pyramid has the same layout: start of level 0 + level offset.
        addr = np.take(sc.tri_tex_start, idx) + np.take(self._lvl_start, lvl) + iv * size + iu
        texel = np.take(sc.bank.texels, addr).view(np.uint8).reshape(-1, 4)
        rgb = texel[:, :3] * np.take(sc.tri_tint, idx, axis=0)  # [N, 3] float32
        depth = np.where(np.isfinite(t), t, 0.0).astype(np.float32)
        dynamic = np.zeros(H * W, bool)
        if people:
            self._draw_people(people, o, R, dirs, depth, rgb, dynamic)
        rgb = rgb.reshape(H, W, 3)
        if noise_std > 0:
            rng = rng if rng is not None else np.random.default_rng()
            rgb += self._noise(rng) * np.float32(noise_std)
        np.clip(rgb, 0, 255, out=rgb)
        img = rgb.astype(np.uint8)
        material = None
        if want_material:
            material = np.where(dynamic, -1, np.take(sc.tri_material, idx)).reshape(H, W)
            material[(idx == sc.n_triangles).reshape(H, W)] = -1
        return CameraImage(img, depth.reshape(H, W), dynamic.reshape(H, W), material)

    def _noise(self, rng: np.random.Generator) -> np.ndarray:
        """[H, W, 3] float32 unit Gaussian noise: a random window of a precomputed bank.

        Drawing 900k normals costs more than the rest of the shading; windows at random
        offsets of a few stored fields are uncorrelated from frame to frame in practice.
        """
        H, W = self.camera.height, self.camera.width
        if self._noise_bank is None:
            g = np.random.default_rng(12345)
            self._noise_bank = g.standard_normal((4, H + 64, W + 64, 3), dtype=np.float32)
        k, dy, dx = int(rng.integers(4)), int(rng.integers(64)), int(rng.integers(64))
        return self._noise_bank[k, dy:dy + H, dx:dx + W]

    def _person_window(self, prims: list[Primitive], o: np.ndarray, R: np.ndarray) -> (
        tuple[int, int, int, int] | None
    ):
        """Pixel rectangle (u0, v0, u1, v1) that may show one person; None if unseen."""
        c = prims[-1].params  # head sphere: its centre xy is the person's position
        ang = np.linspace(0, 2 * np.pi, 16, endpoint=False)
        r = BOUND_R * 1.08  # polygon circumscribes the circle
        zs = np.array([0.0, 0.5, 1.0, HEAD_Z + HEAD_R + 0.01])
        ring = np.stack([c[0] + r * np.cos(ang), c[1] + r * np.sin(ang)], -1)
        pts = np.concatenate([np.column_stack([ring, np.full(16, z)]) for z in zs])
        pc = (pts - o) @ R  # world -> camera
        if np.all(pc[:, 2] <= 0.05):
            return None
        if np.any(pc[:, 2] <= 0.05):
            return 0, 0, self.camera.width, self.camera.height
        uv, _ = self.camera.project(pc)
        m = 3
        u0, v0 = np.floor(uv.min(0)).astype(int) - m
        u1, v1 = np.ceil(uv.max(0)).astype(int) + m
        u0, v0 = max(u0, 0), max(v0, 0)
        u1, v1 = min(u1, self.camera.width), min(v1, self.camera.height)
        if u0 >= u1 or v0 >= v1:
            return None
        return int(u0), int(v0), int(u1), int(v1)

    def _draw_people(self, prims: list[Primitive], o: np.ndarray, R: np.ndarray,
                     dirs: np.ndarray, depth: np.ndarray, rgb: np.ndarray,
                     dynamic: np.ndarray) -> None:
        W = self.camera.width
        by_person: dict[int, list[Primitive]] = {}
        for p in prims:
            by_person.setdefault(p.person, []).append(p)
        for group in by_person.values():
            win = self._person_window(group, o, R)
            if win is None:
                continue
            u0, v0, u1, v1 = win
            pix = (np.arange(v0, v1)[:, None] * W + np.arange(u0, u1)[None, :]).reshape(-1)
            dx, dy, dz = dirs[pix, 0], dirs[pix, 1], dirs[pix, 2]
            # Cheap pre-test against the person's bounding cylinder: the window is a
            # rectangle, the person a small part of it.
            c = group[-1].params
            bound = Primitive("cyl", np.array([c[0], c[1], BOUND_R, 0.0, HEAD_Z + HEAD_R]),
                              c[:3], -1)
            inside = np.isfinite(intersect_cols(bound, o, dx, dy, dz))
            if not inside.any():
                continue
            pix, dx, dy, dz = pix[inside], dx[inside], dy[inside], dz[inside]
            best = depth[pix]
            best[best == 0] = np.inf
            which = np.full(len(pix), -1)
            for k, p in enumerate(group):
                tp = intersect_cols(p, o, dx, dy, dz)
                closer = tp < best
                best[closer] = tp[closer]
                which[closer] = k
            hit = which >= 0
            if not hit.any():
                continue
            sel = pix[hit]
            depth[sel] = best[hit]
            dynamic[sel] = True
            pts = o + best[hit, None].astype(np.float64) * np.column_stack(
                [dx[hit], dy[hit], dz[hit]])
            col = np.zeros((len(sel), 3), np.float32)
            for k, p in enumerate(group):
                m = which[hit] == k
                if m.any():
                    nrm = surface_normal(p, pts[m])
                    shade = 0.6 + 0.4 * (0.5 + 0.5 * (nrm @ LIGHT_DIR))
                    col[m] = 255.0 * p.color[None, :] * shade[:, None]
            rgb[sel] = col


class LidarRenderer:
    """Renders planar scans (float64-exact before noise)."""

    def __init__(self, scene: Scene, spec: LidarSpec) -> None:
        self.scene = scene
        self.spec = spec
        a = spec.angles()
        self.dirs_laser = np.column_stack([np.cos(a), np.sin(a), np.zeros_like(a)])  # [B, 3]

    def render(self, T_world_laser: np.ndarray, people: list[Primitive] | None = None,
               rng: np.random.Generator | None = None, noisy: bool = True) -> LidarReturn:
        spec = self.spec
        R = np.asarray(T_world_laser[:3, :3], np.float64)
        o = np.asarray(T_world_laser[:3, 3], np.float64)
        d = self.dirs_laser @ R.T  # [B, 3] unit, world
        rays = np.empty((len(d), 6), np.float32)
        rays[:, :3] = o
        rays[:, 3:] = d
        hit = self.scene.cast(rays)
        prim = hit["primitive_ids"]
        r = self.scene.refine_t(o, d, prim)  # [B] float64
        normal = hit["primitive_normals"].astype(np.float64)
        dynamic = np.zeros(len(d), bool)
        if people:
            which = np.full(len(d), -1)
            for k, p in enumerate(people):
                # Only people whose shape crosses the scan plane can be hit.
                if p.kind == "cyl" and not (p.params[3] <= o[2] <= p.params[4]):
                    continue
                if p.kind == "sphere" and abs(p.params[2] - o[2]) > p.params[3]:
                    continue
                tp = intersect(p, o, d)
                closer = tp < r
                r = np.where(closer, tp, r)
                which[closer] = k
            dynamic = which >= 0
            for k in np.unique(which[dynamic]):
                m = which == k
                normal[m] = surface_normal(people[k], o + r[m, None] * d[m])
        true = r.copy()
        out = r.copy()
        if noisy:
            rng = rng if rng is not None else np.random.default_rng()
            out = out + rng.standard_normal(len(out)) * spec.noise_std
            # Dropouts: rare anywhere, frequent at grazing incidence (little light returns).
            cos_inc = np.abs(np.einsum("ij,ij->i", normal, d))
            p_drop = spec.dropout + 0.5 * np.clip((0.2 - cos_inc) / 0.2, 0.0, 1.0)
            out[rng.random(len(out)) < p_drop] = np.nan
        with np.errstate(invalid="ignore"):
            out[out > spec.range_max] = np.inf
            out[out < spec.range_min] = -np.inf
        return LidarReturn(out, true, dynamic)

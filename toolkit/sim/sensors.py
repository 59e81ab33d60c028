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
    # The driver stamps each image this long after its exposure (USB transfer, a busy
    # computer): frames.csv holds exposure + delay, the ground truth the true times.
    stamp_delay_s: float = 0.0
    # Auto exposure, as most robot cameras run: each frame's gain moves the last frame's
    # mean grey level towards ``exposure_target`` by the fraction ``exposure_speed`` (in
    # log gain), within ``exposure_gain_range``; the same surface then looks brighter in a
    # dark room than in a bright one. Off: every frame at gain 1.
    auto_exposure: bool = False
    exposure_target: float = 110.0
    exposure_speed: float = 0.3
    exposure_gain_range: tuple[float, float] = (0.4, 2.5)

    def next_gain(self, gain: float, mean_grey: float) -> float:
        """The auto exposure's gain for the next frame after one at ``gain`` whose mean
        grey level was ``mean_grey``."""
        if not self.auto_exposure:
            return 1.0
        lo, hi = self.exposure_gain_range
        step = (self.exposure_target / max(mean_grey, 1.0)) ** self.exposure_speed
        return float(np.clip(gain * step, lo, hi))

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
    # ... plus up to this at grazing incidence (cos < 0.2: little light comes back)
    grazing_dropout: float = 0.5
    mount_xyz: tuple[float, float, float] = (0.0, 0.0, 0.25)
    time_offset_s: float = 0.043  # first scan after the first image (not synchronised)
    # True: the beams are measured one after another over a turn of 1 / rate_hz, as a
    # spinning scanner does, while the robot moves (the scans carry time_increment);
    # False: every beam at the scan's stamp.
    sweep: bool = False

    @property
    def time_increment(self) -> float:
        """Seconds between beams (0 without ``sweep``)."""
        return abs(self.angle_increment) / (2 * np.pi * self.rate_hz) if self.sweep else 0.0

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
    """Renders RGB, z-depth and the dynamic mask of one camera in one scene.

    Not thread-safe: the per-pixel work arrays are allocated once and reused by every
    ``render`` call (see ``render``); use one renderer per thread.
    """

    def __init__(self, scene: Scene, camera: PinholeCamera) -> None:
        self.scene = scene
        self.camera = camera
        H, W = camera.height, camera.width
        N = H * W
        self.rays_cam = camera.pixel_rays().reshape(-1, 3).astype(np.float32)  # [N, 3] z = 1
        self.norm2 = np.einsum("ij,ij->i", self.rays_cam, self.rays_cam)  # [N] |d|^2
        self._rays = np.empty((N, 6), np.float32)  # reused cast buffer
        self._rays_cols = [np.ascontiguousarray(self.rays_cam[:, k]) for k in range(3)]
        # pixel_rays() has z = 1 exactly, so the z term of each direction is R[k, 2] itself.
        self._unit_z = bool(np.all(self._rays_cols[2] == 1.0))
        # |d|^2 / f folds the per-pixel part of the mip footprint into one array.
        self.norm2 = (self.norm2 / np.sqrt(camera.fx * camera.fy)).astype(np.float32)
        off = scene.bank.offset  # [M, LEVELS]
        self._lvl_start = (off[0] - off[0, 0]).astype(np.int64)  # [LEVELS]
        if not np.all(off - off[:, :1] == self._lvl_start):
            raise ValueError("texture pyramids must share one layout")
        self._lvl_size = (TILE >> np.arange(LEVELS)).astype(np.int64)
        # Tables gathered by triangle id, int64 so that np.take needs no index conversion.
        self._tri_tex_start = scene.tri_tex_start.astype(np.int64)
        self._noise_bank: np.ndarray | None = None
        # Work arrays reused by every frame. Allocating ~30 fresh [N] temporaries per frame
        # made glibc hand megabytes back to the kernel and fault them in again: ~10k page
        # faults and 25-35 ms of system CPU per 640x480 frame, more than the shading itself.
        self._f = [np.empty(N, np.float32) for _ in range(4)]
        self._i = [np.empty(N, np.int64) for _ in range(5)]
        self._g = np.empty((N, 6), np.float32)  # per-pixel u0 v0 du1 dv1 du2 dv2
        self._tint = np.empty((N, 3), np.float32)
        self._rgbf = np.empty((N, 3), np.float32)
        self._texel = np.empty(N, np.uint32)
        self._ok = np.empty(N, bool)
        # Per-triangle mip factor tpm / h of the current frame; 1 in the miss row (t = inf
        # there gives the coarsest level, and the row is black).
        self._k_tri = np.ones(scene.n_triangles + 1, np.float32)
        self._tri_normal_cols = [np.ascontiguousarray(scene.tri_normal[:, k]) for k in range(3)]

    def render(self, T_world_camera: np.ndarray, people: list[Primitive] | None = None,
               noise_std: float = 0.0, rng: np.random.Generator | None = None,
               want_material: bool = False, gain: float = 1.0) -> CameraImage:
        """One image from ``T_world_camera`` [4, 4] with people shapes (optional).

        Hot loop, written for speed: every per-pixel step writes into a work array made in
        ``__init__`` (``out=``), ``np.take`` with int64 indices and ``mode="clip"`` (no
        index conversion, no bounds-check copy; the ids are in range by construction), no
        BLAS calls on [N, 3] arrays (BLAS threads fight the raycaster's). The arithmetic is
        the plain float32 expression, in the same order, so the pixels are those of the
        straightforward version.
        """
        H, W = self.camera.height, self.camera.width
        N = H * W
        sc = self.scene
        f0, f1, f2, f3 = self._f
        idx, lvl, i2, i3 = self._i[:4]
        R = np.asarray(T_world_camera[:3, :3], np.float64)
        o = np.asarray(T_world_camera[:3, 3], np.float64)
        rays = self._rays
        for k in range(3):  # a strided fill per column: 6x faster than rays[:, :3] = o
            rays[:, k] = np.float32(o[k])
        rc = self._rays_cols
        for k in range(3):
            # (x R[k,0] + y R[k,1]) + z R[k,2], z = 1 for undistorted and distorted rays.
            np.multiply(rc[0], np.float32(R[k, 0]), out=f0)
            np.multiply(rc[1], np.float32(R[k, 1]), out=f1)
            np.add(f0, f1, out=f0)
            if self._unit_z:
                np.add(f0, np.float32(R[k, 2]), out=rays[:, 3 + k])
            else:
                np.multiply(rc[2], np.float32(R[k, 2]), out=f1)
                np.add(f0, f1, out=rays[:, 3 + k])
        dirs = rays[:, 3:]
        hit = sc.cast(rays)
        t = hit["t_hit"]  # [N] float32 z-depth (inf on a miss)
        np.minimum(hit["primitive_ids"], np.uint32(sc.n_triangles), out=idx)  # miss: black row
        bary = hit["primitive_uvs"]  # [N, 2]
        b0, b1 = bary[:, 0], bary[:, 1]
        g = self._g
        np.take(sc.tri_uvaff, idx, axis=0, out=g, mode="clip")
        # Level-0 texel coordinates u = u0 + b0 du1 + b1 du2 (v likewise).
        u, v = f2, f3
        np.multiply(b0, g[:, 2], out=f0)
        np.add(g[:, 0], f0, out=u)
        np.multiply(b1, g[:, 4], out=f0)
        np.add(u, f0, out=u)
        np.multiply(b0, g[:, 3], out=f0)
        np.add(g[:, 1], f0, out=v)
        np.multiply(b1, g[:, 5], out=f0)
        np.add(v, f0, out=v)
        # Mip level from the pixel footprint: texels per pixel = tpm * range / (f * cos)
        # = tpm * t |d| / (f |n.d| / |d|). On the hit triangle's plane n.p = c the ray
        # parameter is t = h / |n.d| with h = |c - n.o| (the camera's distance to the
        # plane), so rho = (tpm / h) * t^2 * |d|^2 / f: one value per triangle and frame
        # instead of a per-pixel dot product with the hit normal.
        k_tri = self._k_tri
        n = self._tri_normal_cols  # no BLAS: a 5k x 3 product starts OpenBLAS threads
        h = np.abs(sc.tri_d - (n[0] * o[0] + n[1] * o[1] + n[2] * o[2]))  # [T] float64
        k_tri[:-1] = sc.tri_tpm[:-1] / np.maximum(h, 1e-9)
        rho = f0
        np.take(k_tri, idx, out=rho, mode="clip")
        np.multiply(rho, t, out=rho)
        np.multiply(rho, t, out=rho)
        np.multiply(rho, self.norm2, out=rho)
        # floor(log2(rho)) clipped to the pyramid, read off the float32 exponent bits (the
        # same as frexp's exponent - 1 for every finite rho >= 0, subnormals and 0 included;
        # inf on a miss gives the coarsest level).
        np.right_shift(rho.view(np.uint32), np.uint32(23), out=lvl)
        np.bitwise_and(lvl, 0xFF, out=lvl)
        np.subtract(lvl, 127, out=lvl)
        np.clip(lvl, 0, LEVELS - 1, out=lvl)
        size, mask = i2, i3
        np.take(self._lvl_size, lvl, out=size, mode="clip")  # texels per side at that level
        np.subtract(size, 1, out=mask)
        tint = self._tint
        np.take(sc.tri_tint, idx, axis=0, out=tint, mode="clip")
        material = None
        if want_material:
            material = np.take(sc.tri_material, idx)
            material[idx == sc.n_triangles] = -1
        # Texel address: start of the material's level 0 + level offset (every pyramid has
        # the same layout) + row * size + column, the coordinates wrapped at that level.
        addr, tmp = self._i[4], idx  # idx is not needed any more
        np.take(self._tri_tex_start, idx, out=addr, mode="clip")
        np.take(self._lvl_start, lvl, out=tmp, mode="clip")
        np.add(addr, tmp, out=addr)
        for coord, row in ((v, True), (u, False)):
            np.copyto(tmp, coord, casting="unsafe")  # truncation: coordinates are positive
            np.right_shift(tmp, lvl, out=tmp)
            np.bitwise_and(tmp, mask, out=tmp)
            if row:
                np.multiply(tmp, size, out=tmp)
            np.add(addr, tmp, out=addr)
        texel = self._texel
        np.take(sc.bank.texels, addr, out=texel, mode="clip")
        rgbf = self._rgbf
        np.multiply(texel.view(np.uint8).reshape(-1, 4)[:, :3], tint, out=rgbf)
        depth = np.empty(N, np.float32)
        ok = self._ok
        np.isfinite(t, out=ok)
        np.copyto(depth, t)
        np.logical_not(ok, out=ok)
        depth[ok] = 0.0
        dynamic = np.zeros(N, bool)
        if people:
            self._draw_people(people, o, R, dirs, depth, rgbf, dynamic)
        rgb = rgbf.reshape(H, W, 3)
        if gain != 1.0:  # exposure: before the sensor's noise and its clipping
            np.multiply(rgb, np.float32(gain), out=rgb)
        if noise_std > 0:
            rng = rng if rng is not None else np.random.default_rng()
            noise = self._tint.reshape(H, W, 3)  # free again: the tint is applied
            np.multiply(self._noise(rng), np.float32(noise_std), out=noise)
            np.add(rgb, noise, out=rgb)
        np.clip(rgb, 0, 255, out=rgb)
        img = np.empty((H, W, 3), np.uint8)
        np.copyto(img, rgb, casting="unsafe")  # truncation, as astype(np.uint8)
        if material is not None:
            material = material.reshape(H, W)
            material[dynamic.reshape(H, W)] = -1
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
        if np.isnan(uv).any():  # part of it past the lens model's field of view
            return 0, 0, self.camera.width, self.camera.height
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
            # Views of the window, no gathers: the window is a rectangle, the person a
            # small part of it, so only the pixels that pass a cheap pre-test are gathered.
            d3 = dirs.reshape(-1, W, 3)[v0:v1, u0:u1]
            wx, wy = d3[..., 0], d3[..., 1]
            # Pre-test: rays that come within BOUND_R of the person's vertical axis, ahead
            # of the camera (disc >= 0 and b < 0 for the infinite bounding cylinder; the
            # camera is outside it). A superset of the hits, whatever their height.
            c = group[-1].params
            ox, oy = np.float32(o[0] - c[0]), np.float32(o[1] - c[1])
            b = wx * ox
            b += wy * oy
            a = wx * wx
            a += wy * wy
            a *= np.float32(ox * ox + oy * oy - BOUND_R * BOUND_R)
            inside = b < 0
            b *= b
            inside &= b >= a
            rows, cols = np.nonzero(inside)
            if len(rows) == 0:
                continue
            pix = (rows + v0) * W + (cols + u0)
            dx, dy, dz = wx[rows, cols], wy[rows, cols], d3[rows, cols, 2]
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
               rng: np.random.Generator | None = None, noisy: bool = True,
               people_by_beams: list[tuple[np.ndarray, list[Primitive]]] | None = None) -> (
                   LidarReturn):
        """One scan from ``T_world_laser`` [4, 4], or [B, 4, 4]: each beam's own pose (a
        sweep while moving; the laser stays at one height). ``people_by_beams``: instead of
        ``people``, (beam indices [K], the people then) for groups of beams fired at
        different times (people walk on during a sweep)."""
        spec = self.spec
        T = np.asarray(T_world_laser, np.float64)
        R = T[..., :3, :3]
        o = T[..., :3, 3]  # [3] or [B, 3]
        d = self.dirs_laser @ R.T if R.ndim == 2 else np.einsum("bij,bj->bi", R, self.dirs_laser)
        # [B, 3] unit, world
        oz = float(o[..., 2].flat[0])
        rays = np.empty((len(d), 6), np.float32)
        rays[:, :3] = o
        rays[:, 3:] = d
        hit = self.scene.cast(rays)
        prim = hit["primitive_ids"]
        r = self.scene.refine_t(o, d, prim)  # [B] float64
        normal = hit["primitive_normals"].astype(np.float64)
        dynamic = np.zeros(len(d), bool)
        groups = people_by_beams if people_by_beams is not None else (
            [(np.arange(len(d)), people)] if people else [])
        hit_by: list[Primitive] = []  # primitives hit, by the index ``which`` holds
        which = np.full(len(d), -1)
        for beams, group in groups:
            ob = o if o.ndim == 1 else o[beams]
            for p in group:
                # Only people whose shape crosses the scan plane can be hit.
                if p.kind == "cyl" and not (p.params[3] <= oz <= p.params[4]):
                    continue
                if p.kind == "sphere" and abs(p.params[2] - oz) > p.params[3]:
                    continue
                tp = intersect(p, ob, d[beams])
                closer = tp < r[beams]
                if closer.any():
                    r[beams[closer]] = tp[closer]
                    which[beams[closer]] = len(hit_by)
                    hit_by.append(p)
        dynamic = which >= 0
        for k in np.unique(which[dynamic]):
            m = which == k
            normal[m] = surface_normal(hit_by[k], (o if o.ndim == 1 else o[m])
                                       + r[m, None] * d[m])
        true = r.copy()
        out = r.copy()
        if noisy:
            rng = rng if rng is not None else np.random.default_rng()
            out = out + rng.standard_normal(len(out)) * spec.noise_std
            # Dropouts: rare anywhere, frequent at grazing incidence (little light returns).
            cos_inc = np.abs(np.einsum("ij,ij->i", normal, d))
            p_drop = spec.dropout + spec.grazing_dropout * np.clip((0.2 - cos_inc) / 0.2, 0.0,
                                                                   1.0)
            # A beam that hits nothing has no surface to drop a return from: it stays +inf
            # (its zero normal read as grazing made half of them NaN in an open scene). The
            # draws are the same, so a closed house's scans do not change.
            p_drop[~np.isfinite(r)] = 0.0
            out[rng.random(len(out)) < p_drop] = np.nan
        with np.errstate(invalid="ignore"):
            out[out > spec.range_max] = np.inf
            out[out < spec.range_min] = -np.inf
        return LidarReturn(out, true, dynamic)

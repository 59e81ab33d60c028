"""Moving obstacles out of the map, using the sensors (no semantic detector).

A point left by a person who walked on is in free space later: a later depth image or
lidar scan sees *through* it, to the wall behind. ``SeeThroughCounter`` counts, per map
voxel, the views that see through it and the views that see it where it is; voxels seen
through often enough are removed: by at least ``min_free`` views and ``free_ratio`` of
those that test it, counted over the whole drive. It is a majority rule, so an object
present for most of the time its place was seen (a person standing still, then walking
off; a door opened late) stays, unless ``after_last``: then a voxel also goes when the same
test passes on the views taken after it was last fused alone (depth views of later frames,
scans stamped later than that frame). A static voxel occluded by a person is not affected:
the ray stops *in front* of it, which is occlusion, not free space. The lidar clears only
what some scan has hit: its beams pass over a chest top or under a table top near the scan
plane without ever seeing them.

Margins absorb depth errors: monocular depth is off by a few percent even after scaling,
so depth views use a relative margin; the lidar is accurate to centimetres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from toolkit.camera import PinholeCamera, pixel_index
from toolkit.geometry import inv_se3
from toolkit.ingest.sync import match_nearest
from toolkit.sensors import LaserScan


@dataclass
class CarveOptions:
    depth_margin_m: float = 0.10
    depth_margin_rel: float = 0.15  # monocular depth disagrees by this much between frames
    lidar_margin_m: float = 0.10
    lidar_plane_tol_m: float = 0.05  # voxel distance from the scan plane to be tested
    min_free: int = 3  # views that must see through a voxel before it goes
    free_ratio: float = 0.5  # ... and this fraction of the views that tested it
    # Also remove a voxel that passes the same test on the views taken after it was last
    # fused alone (``SeeThroughCounter``'s ``last_frame`` / ``last_stamp``).
    after_last: bool = False


def beam_of(bearing: np.ndarray, angle_min: np.ndarray | float,
            angle_increment: np.ndarray | float) -> np.ndarray:
    """Nearest beam index (float, not bounded) of bearings (rad), counted from
    ``angle_min`` the way the beams run: a scan from 0 to 270 deg, or one running
    backwards, finds its beams past +-180 deg too (``arctan2`` turns them negative)."""
    inc = np.asarray(angle_increment, np.float64)
    sign, step = np.sign(inc), np.abs(inc)
    ahead = np.mod(sign * (bearing - angle_min) + step / 2, 2 * np.pi) - step / 2
    return np.rint(ahead / step)


class SeeThroughCounter:
    """Per-voxel counts of see-through (free) and consistent (hit) views.

    Depth views must be masked as the fuse stage masks them: NaN wherever
    ``toolkit.fusion.cloud.valid_pixels(depth, opts)`` is False, with ``opts`` the map's
    ``CloudOptions`` (``FusionConfig.cloud_options``: the depth range and, needed here,
    ``edge_threshold`` > 0), on the full-resolution depth and strided after
    (``Fusion.integrate`` keeps ``np.where(ok[::s, ::s], depth[::s, ::s], nan)``). A voxel
    is tested at its nearest pixel, and on a static object's outline that pixel can look
    past the object to the background: a view sees through it. The edge filter leaves the
    pixels next to a depth jump without a vote. Fed unmasked depth, a box standing still
    in front of a wall, seen by all 8 views, lost 10 of its 130 voxels at 96x72, all on its
    edges, and 1 to 22 voxels in 44 of 80 such scenes (the scene of
    ``test_a_static_box_seen_by_every_frame_is_never_carved`` in
    ``tests/test_properties_fusion.py``, rng seeds 0-39 at 96x72 and 192x144, views left
    unmasked; 2026-11-28, 2-core AMD EPYC). Masked: none, and no wall voxel either way.
    """

    def __init__(self, points: np.ndarray, options: CarveOptions | None = None,
                 block_m: float = 1.0, last_frame: np.ndarray | None = None,
                 last_stamp: np.ndarray | None = None) -> None:
        """``last_frame`` / ``last_stamp`` [V]: the frame index and stamp each voxel was last
        fused at; with both given, the views after them are also counted apart (``late``)."""
        self.points = np.asarray(points, dtype=np.float64)  # [V, 3] world
        self.opts = options or CarveOptions()
        self.last_frame = self.last_stamp = None
        self.late: dict[str, np.ndarray] = {}
        if last_frame is not None and last_stamp is not None:
            self.last_frame = np.asarray(last_frame, np.int64)  # [V]
            self.last_stamp = np.asarray(last_stamp, np.float64)  # [V]
            # The same four counts over the views taken after each voxel was last fused.
            self.late = {k: np.zeros(len(self.points), np.int32) for k in
                         ("depth_free", "depth_hit", "lidar_free", "lidar_hit")}
        # Depth and lidar views counted apart: the lidar's see-through only counts for
        # cells some scan has hit (see ``free``).
        self.depth_free = np.zeros(len(self.points), np.int32)  # [V]
        self.depth_hit = np.zeros(len(self.points), np.int32)  # [V]
        self.lidar_free = np.zeros(len(self.points), np.int32)  # [V]
        self.lidar_hit = np.zeros(len(self.points), np.int32)  # [V]
        self._p32 = self.points.astype(np.float32)
        self._plane_cache: tuple[np.ndarray, float, _Blocks] | None = None
        self._fov_cache: tuple[PinholeCamera, tuple[float, float]] | None = None
        # Voxels grouped into 1 m blocks (sorted by block) so a view tests a few thousand
        # block spheres against its frustum and then only the voxels of visible blocks.
        bk = np.floor(self.points / block_m).astype(np.int64)
        key = (bk[:, 0] << 42) + (bk[:, 1] << 21) + bk[:, 2] if len(bk) else np.zeros(0, int)
        self._order = np.argsort(key, kind="stable")
        ks = key[self._order]
        self._start = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]]) if len(ks) else \
            np.zeros(0, np.int64)
        self._count = np.diff(np.r_[self._start, len(ks)])
        ps = self._p32[self._order]
        self._centre = np.add.reduceat(ps, self._start, axis=0) / self._count[:, None] if \
            len(ks) else np.zeros((0, 3), np.float32)
        self._radius = np.float32(np.sqrt(3) * block_m)  # covers any block from its mean
        self._block_of = np.empty(len(self.points), np.int64)  # [V] block of each voxel
        self._block_of[self._order] = np.repeat(np.arange(len(self._start)), self._count)

    def _visible_voxels(self, R: np.ndarray, t: np.ndarray, tx: float, ty: float,
                        max_depth: float) -> np.ndarray:
        """Indices of voxels in blocks whose bounding sphere meets the view frustum."""
        if len(self._start) == 0:
            return np.zeros(0, np.int64)
        c = self._centre @ R.T + t  # [K, 3] block centres in the camera
        r = self._radius
        vis = (c[:, 2] > -r) & (c[:, 2] < max_depth + r)
        # Side planes |x| = tx z: signed distance of the centre, normalised.
        vis &= (np.abs(c[:, 0]) - tx * c[:, 2]) / np.sqrt(1 + tx * tx) < r
        vis &= (np.abs(c[:, 1]) - ty * c[:, 2]) / np.sqrt(1 + ty * ty) < r
        b = np.flatnonzero(vis)
        if len(b) == 0:
            return np.zeros(0, np.int64)
        n = self._count[b]
        first = np.repeat(self._start[b] - np.r_[0, np.cumsum(n)[:-1]], n)
        return self._order[first + np.arange(n.sum())]

    def add_depth_view(self, camera: PinholeCamera, T_camera_world: np.ndarray,
                       depth: np.ndarray, stride: int = 1, max_depth: float = 8.0,
                       index: int | None = None) -> None:
        """One depth image (metres, NaN/0 invalid) seen from ``T_camera_world``; ``depth``
        may be the full image subsampled by ``stride``. ``index``: its frame, for the
        counts after each voxel's last frame. Masked by ``valid_pixels`` first (see the
        class): unmasked, the outlines of static objects are carved."""
        R = T_camera_world[:3, :3].astype(np.float32)
        t = T_camera_world[:3, 3].astype(np.float32)
        if self._fov_cache is None or self._fov_cache[0] != camera:
            self._fov_cache = (camera, self._half_fov(camera))
        tx, ty = self._fov_cache[1]
        cand = self._visible_voxels(R, t, tx, ty, max_depth)
        if len(cand) == 0:
            return
        pc = self._p32[cand] @ R.T + t
        zf = pc[:, 2]
        inside = (zf > 0.05) & (zf < max_depth) & (np.abs(pc[:, 0]) < tx * zf) & (
            np.abs(pc[:, 1]) < ty * zf)
        front = cand[inside]
        if len(front) == 0:
            return
        pc = pc[inside]
        if camera.has_distortion:
            uv, z = camera.project(pc)
        else:
            # The pinhole in float32 on the cells already in front: camera.project's float64
            # copy was a fifth of the carving time.
            z = pc[:, 2]
            uv = np.empty((len(pc), 2), np.float32)
            np.divide(pc[:, 0], z, out=uv[:, 0])
            np.divide(pc[:, 1], z, out=uv[:, 1])
            uv[:, 0] = uv[:, 0] * np.float32(camera.fx) + np.float32(camera.cx)
            uv[:, 1] = uv[:, 1] * np.float32(camera.fy) + np.float32(camera.cy)
        inside = camera.in_image(uv)
        front, uv, z = front[inside], uv[inside], z[inside]
        # Pixel j of the subsampled image is full-size pixel j * stride, covering
        # [j - 0.5, j + 0.5) in uv / stride.
        px = pixel_index(uv / stride)  # [M, 2] (col, row)
        col = np.clip(px[:, 0], 0, depth.shape[1] - 1)
        row = np.clip(px[:, 1], 0, depth.shape[0] - 1)
        d = depth[row, col]
        ok = np.isfinite(d) & (d > 0)
        front, z, d = front[ok], z[ok], d[ok]
        margin = self.opts.depth_margin_m + self.opts.depth_margin_rel * d
        free, hit = front[z < d - margin], front[np.abs(z - d) <= margin]
        self.depth_free[free] += 1
        self.depth_hit[hit] += 1
        if self.last_frame is not None and index is not None:
            self.late["depth_free"][free[self.last_frame[free] < index]] += 1
            self.late["depth_hit"][hit[self.last_frame[hit] < index]] += 1

    @property
    def free(self) -> np.ndarray:
        """[V] views that see through each voxel. A scan's see-through counts only for
        voxels some scan has hit: the lidar can only clear what it can see. Its beams pass
        just over a chest top or under a table top within ``lidar_plane_tol_m`` of the
        plane to the wall behind, and no scan ever hits them to outvote that (a 2 cm board
        2 cm above the plane lost 642 of 642 voxels, a chest top 3 cm below it 167 of 168);
        a person's legs are hit while the person stands there."""
        return self.depth_free + np.where(self.lidar_hit > 0, self.lidar_free, 0)

    @property
    def hit(self) -> np.ndarray:
        """[V] views that see each voxel where it is (depth and lidar)."""
        return self.depth_hit + self.lidar_hit

    @staticmethod
    def _half_fov(camera: PinholeCamera) -> tuple[float, float]:
        """tan of the half field of view (x, y) with 10 % slack; with distortion from the
        rays of the image's border pixels (a barrel lens sees well past cx / fx: k1 -0.3 at
        f 400 reached tan 1.0 where 0.88 was used, and obstacles at the image's sides were
        never carved)."""
        tx = max(camera.cx + 0.5, camera.width - 0.5 - camera.cx) / camera.fx
        ty = max(camera.cy + 0.5, camera.height - 0.5 - camera.cy) / camera.fy
        if camera.has_distortion:
            w, h = camera.width, camera.height
            u = np.r_[np.arange(w), np.arange(w), np.zeros(h), np.full(h, w - 1)]
            v = np.r_[np.zeros(w), np.full(w, h - 1), np.arange(h), np.arange(h)]
            rays = camera.undistort_points(np.stack([u, v], -1).astype(np.float64))
            with np.errstate(invalid="ignore"):
                tx = max(tx, float(np.nanmax(np.abs(rays[:, 0]), initial=0.0)))
                ty = max(ty, float(np.nanmax(np.abs(rays[:, 1]), initial=0.0)))
        return 1.1 * tx, 1.1 * ty

    def add_scan(self, scan: LaserScan, T_laser_world: np.ndarray) -> None:
        """One lidar scan taken at ``T_laser_world``: tests voxels near its plane."""
        o = self.opts
        valid_r = scan.ranges[scan.valid_mask()]
        if len(valid_r) == 0:
            return
        # A voxel farther than the longest valid beam (+ margin) is neither seen through
        # nor hit: only the blocks near the plane within that reach are tested, so a scan
        # costs what is around the robot, not the whole map (an hour of exploring).
        origin = inv_se3(T_laser_world)[:3, 3].astype(np.float32)
        near = self._near_plane(T_laser_world).within(
            self._centre, origin, float(valid_r.max()) + o.lidar_margin_m + o.lidar_plane_tol_m
            + self._radius)
        if len(near) == 0:
            return
        T = T_laser_world.astype(np.float32)
        p = self._p32[near]
        zl = p @ T[2, :3] + T[2, 3]
        keep = np.abs(zl) < o.lidar_plane_tol_m
        near, p = near[keep], p[keep]
        x = p @ T[0, :3] + T[0, 3]
        y = p @ T[1, :3] + T[1, 3]
        r = np.hypot(x, y)
        beam = beam_of(np.arctan2(y, x), scan.angle_min, scan.angle_increment)
        n = len(scan.ranges)
        # Bearings past the scan's ends wrap for a 360 degree scanner only.
        wrap = abs(scan.angle_increment) * n >= 2 * np.pi - 1e-6
        if wrap:
            beam = np.mod(beam, n)
        ok = (beam >= 0) & (beam < n)
        near, r, beam = near[ok], r[ok], beam[ok].astype(np.int64)
        valid_beam = scan.valid_mask()
        ranges = np.where(valid_beam, scan.ranges, np.nan)  # [B]
        hit = valid_beam[beam] & (np.abs(r - ranges[beam]) <= o.lidar_margin_m)
        self.lidar_hit[near[hit]] += 1
        if self.last_stamp is not None:
            h = near[hit]
            self.late["lidar_hit"][h[self.last_stamp[h] < scan.stamp]] += 1
        # Seen through: the beam and both its neighbours reach past the voxel (as in
        # dynamic_beams). The nearest beam alone carved a wall seen at a grazing angle,
        # where the neighbours' ranges differ by decimetres, and slipped past cells
        # thinner than the beam spacing.
        free = np.ones(len(beam), bool)
        for db in (-1, 0, 1):
            bb = np.mod(beam + db, n) if wrap else beam + db
            inside = (bb >= 0) & (bb < n)
            with np.errstate(invalid="ignore"):
                free &= inside & (r < ranges[np.clip(bb, 0, n - 1)] - o.lidar_margin_m)
        self.lidar_free[near[free]] += 1
        if self.last_stamp is not None:
            f = near[free]
            self.late["lidar_free"][f[self.last_stamp[f] < scan.stamp]] += 1

    def _near_plane(self, T_laser_world: np.ndarray) -> _Blocks:
        """Voxels within the plane tolerance of a scan plane, by block, cached while the
        plane stays put (a robot on a flat floor scans the same world plane all the time)."""
        n = T_laser_world[2, :3]
        d = T_laser_world[2, 3]
        pad = 0.02
        c = self._plane_cache
        if c is not None and np.abs(c[0] - n).max() < 1e-3 and abs(c[1] - d) < pad / 2:
            return c[2]
        zl = self._p32 @ n.astype(np.float32) + np.float32(d)
        near = _Blocks(np.flatnonzero(np.abs(zl) < self.opts.lidar_plane_tol_m + pad),
                       self._block_of)
        self._plane_cache = (n.copy(), float(d), near)
        return near

    def _passes(self, free: np.ndarray, hit: np.ndarray) -> np.ndarray:
        return (free >= self.opts.min_free) & (
            free >= self.opts.free_ratio * np.maximum(free + hit, 1))

    def dynamic_mask(self) -> np.ndarray:
        """[V] bool: voxels to remove: the majority over the whole drive, or with
        ``after_last`` (and the last frames given) over the views after the last frame."""
        out = self._passes(self.free, self.hit)
        if self.opts.after_last and self.late:
            lt = self.late
            # As in ``free``: the lidar clears only cells some scan has hit (at any time).
            free = lt["depth_free"] + np.where(self.lidar_hit > 0, lt["lidar_free"], 0)
            out |= self._passes(free, lt["depth_hit"] + lt["lidar_hit"])
        return out


class _Blocks:
    """Voxel indices grouped by their block, to pick the blocks near a point."""

    def __init__(self, voxels: np.ndarray, block_of: np.ndarray) -> None:
        b = block_of[voxels]
        order = np.argsort(b, kind="stable")
        self.voxels = voxels[order]  # [M]
        b = b[order]
        self.start = np.flatnonzero(np.r_[True, b[1:] != b[:-1]]) if len(b) else \
            np.zeros(0, np.int64)
        self.block = b[self.start]  # [K'] block ids present
        self.count = np.diff(np.r_[self.start, len(b)])

    def __len__(self) -> int:
        return len(self.voxels)

    def within(self, centres: np.ndarray, point: np.ndarray, radius: float) -> np.ndarray:
        """Voxels of the blocks whose centre (``centres`` [K, 3] by block id) lies within
        ``radius`` of ``point`` [3]."""
        if len(self.block) == 0:
            return self.voxels
        d2 = ((centres[self.block] - point) ** 2).sum(1)
        b = np.flatnonzero(d2 < np.float32(radius) ** 2)
        if len(b) == len(self.block):
            return self.voxels
        n = self.count[b]
        first = np.repeat(self.start[b] - np.r_[0, np.cumsum(n)[:-1]], n)
        return self.voxels[first + np.arange(n.sum())]


def grow_dynamic(points: np.ndarray, first: np.ndarray, last: np.ndarray,
                 frames: np.ndarray, dynamic: np.ndarray, radius: float = 0.05,
                 slack_frames: int = 2, iterations: int = 3,
                 max_frames: int = 4) -> np.ndarray:
    """Extend ``dynamic`` [V] bool to touching voxels seen only while the object was there.

    Where a person's feet meet the floor no view can see *through* them by more than the
    depth margin, so carving leaves a rim. A voxel next to a removed one (within
    ``radius``) whose whole observation span [first, last] lies inside its removed
    neighbour's span (+- ``slack_frames``) and that was seen by at most ``max_frames``
    frames appeared and vanished with the object; a floor voxel beside it was seen before
    and after, and stays. Only voxels seen that briefly may grow, so the growth cannot run
    through a static surface that happened to be seen for a short while.
    """
    from scipy.spatial import cKDTree

    out = np.asarray(dynamic, bool).copy()
    if not out.any():
        return out
    brief = np.flatnonzero(frames <= max_frames)
    if len(brief) == 0:
        return out
    tree = cKDTree(points[brief])  # growth candidates only: a small part of a large map
    src = np.flatnonzero(out)
    for _ in range(iterations):
        nbs = tree.query_ball_point(points[src], radius, workers=1)
        lens = np.fromiter((len(n) for n in nbs), np.int64, len(nbs))
        if lens.sum() == 0:
            break
        pair_src = np.repeat(src, lens)  # [P] removed voxel of each neighbour pair
        pair_nb = brief[np.fromiter((j for n in nbs for j in n), np.int64, int(lens.sum()))]
        cand = ~out[pair_nb]
        pair_src, pair_nb = pair_src[cand], pair_nb[cand]
        if len(pair_nb) == 0:
            break
        lo = np.full(len(points), np.iinfo(np.int64).max)
        hi = np.full(len(points), np.iinfo(np.int64).min)
        np.minimum.at(lo, pair_nb, first[pair_src].astype(np.int64))
        np.maximum.at(hi, pair_nb, last[pair_src].astype(np.int64))
        c = np.unique(pair_nb)
        grow = c[(first[c] >= lo[c] - slack_frames) & (last[c] <= hi[c] + slack_frames)]
        if len(grow) == 0:
            break
        out[grow] = True
        # The next round grows from what was just added; the first round already covered
        # everything within reach of the older voxels.
        src = grow
    return out


def dynamic_beams(scans: list[LaserScan], T_world_laser: np.ndarray,
                  offsets_s: tuple[float, ...] = (-4.0, -2.0, -1.0, -0.5, 0.5, 1.0, 2.0, 4.0),
                  margin_m: float = 0.15, margin_rel: float = 0.03, min_votes: int = 2,
                  plane_tol_m: float = 0.1, isolated: bool = False,
                  no_return_is_free: bool = False, chunk: int = 256,
                  far_offsets_s: tuple[float, ...] = (),
                  far_min_width_m: float = 0.1) -> list[np.ndarray]:
    """Per scan, [B] bool: beams whose end point other scans see through (a moving obstacle).

    Scan k's end points are moved into scan j's laser frame (j at the given time offsets);
    a point is seen through when scan j's beams at its bearing (and both neighbours, so a
    corner grazed from another side does not count) reach further by ``margin``. Beams
    without a return (+inf, ``range_max``) say nothing, as dropouts (NaN) do, unless
    ``no_return_is_free`` (open spaces beyond the scanner's reach, no glass or black
    surfaces): then they reach as far as the scanner does.
    A flagged beam without a flagged neighbour is dropped unless ``isolated``: a person's leg
    spans several beams, while a lone flag is mostly a chair leg thinner than the beam
    spacing that other scans slip past (on the simulated house this took precision from
    0.60 to 0.94 at recall 0.83 -> 0.78).

    Far partners (``far_offsets_s``, seconds) find a person who stood still for longer than
    the near offsets span and then left: the scans taken after they left see through the
    hits on their legs. Offsets past the drive's ends pair a scan with the first or last
    one (at least half the offset away), where a loop ends. A far partner's vote counts
    only on beams of a surface at least ``far_min_width_m`` wide in scan k (a run of
    returns without a range jump): seen from elsewhere, a chair or table leg (3-5 cm) slips
    between the beams, where a person's leg (12-15 cm) cannot.

    Scans are tested ``chunk`` at a time against all their partners at once: one scan and
    one offset at a time was mostly numpy call overhead (6440 scans: 9.0 s, batched 3.3 s).
    Each scan is laid out once, in a ring of the rows the chunks still need (26 bytes a
    beam): memory follows the partners' span in time (+-128 s of scans with the far
    offsets), not the drive's length.
    """
    S = len(scans)
    out = [np.zeros(len(s.ranges), bool) for s in scans]
    if S == 0:
        return out
    T_world_laser = np.asarray(T_world_laser, np.float64)  # [S, 4, 4]
    T_laser_world = inv_se3(T_world_laser)
    stamps = np.array([s.stamp for s in scans], np.float64)
    # [S] each: the scan nearest in time to each scan's stamp + offset (scans in time order)
    partner = [match_nearest(stamps + off, stamps, np.inf) for off in offsets_s]
    n_near = len(partner)
    partner += [match_nearest(stamps + off, stamps, np.inf) for off in far_offsets_s]
    all_offsets = tuple(offsets_s) + tuple(far_offsets_s)
    votes = [np.zeros(len(s.ranges), np.int32) for s in scans]
    chunks = [np.arange(k0, min(k0 + chunk, S)) for k0 in range(0, S, chunk)]  # [K] each
    # Rows [lo, hi) each chunk reads: itself and its partners. Far partners reach minutes
    # away, so the scans are laid out once each, in a ring of the rows the chunks still
    # need: memory follows the offsets' span, not the drive's length (an hour at 40 Hz
    # laid out whole was gigabytes), and no scan is laid out twice.
    spans = [(int(min([kk[0], *(j[kk].min() for j in partner)])),
              int(max([kk[-1], *(j[kk].max() for j in partner)])) + 1) for kk in chunks]
    filled = np.maximum.accumulate([hi for _, hi in spans])
    ring = _PaddedScans(int(max(f - lo for (lo, _), f in zip(spans, filled, strict=True))),
                        max(len(s.ranges) for s in scans), no_return_is_free,
                        far_min_width_m if far_offsets_s else 0.0)
    for kk, (_, hi) in zip(chunks, spans, strict=True):
        ring.fill_to(scans, hi)
        for p, (off, jj) in enumerate(zip(all_offsets, (j[kk] for j in partner), strict=True)):
            use = (np.abs(stamps[jj] - stamps[kk]) >= 0.5 * abs(off)) & (jj != kk)
            if not use.any():
                continue
            k, j = kk[use], jj[use]
            rk, rj = ring.rows(k), ring.rows(j)
            seen = ring.seen_through(rk, rj, T_laser_world[j] @ T_world_laser[k],
                                     margin_m, margin_rel, plane_tol_m)  # [K', Bmax]
            if p >= n_near:
                seen &= ring.wide[rk]  # [K', Bmax]
            for row, kv in enumerate(k):
                votes[kv] += seen[row, : len(votes[kv])]
    for k, s in enumerate(scans):
        flag = votes[k] >= min_votes
        if not isolated and flag.any():
            wrap = abs(s.angle_increment) * len(flag) >= 2 * np.pi - 1e-6
            left, right = np.roll(flag, 1), np.roll(flag, -1)
            if not wrap:
                left[0] = right[-1] = False
            flag &= left | right
        out[k] = flag
    return out


class _PaddedScans:
    """Scans as [W, Bmax] arrays in a ring of W rows: scan g in row g % W once laid out
    (beams past a scan's own count are invalid)."""

    def __init__(self, capacity: int, n_beams: int, no_return_is_free: bool = False,
                 min_width_m: float = 0.0) -> None:
        W, B = capacity, n_beams
        self.no_return_is_free, self.min_width_m = no_return_is_free, min_width_m
        self.filled = 0  # scans [0, filled) were laid out; the last W of them are held
        self.n = np.zeros(W, np.int64)  # [W]
        self.angle_min = np.zeros(W)
        self.angle_inc = np.ones(W)
        self.range_max = np.zeros(W)
        self.full = np.zeros(W, bool)  # [W] wraps around
        self.valid = np.zeros((W, B), bool)
        self.x = np.zeros((W, B))  # end points in the scan's own laser frame
        self.y = np.zeros((W, B))
        # How far each beam saw free space: to its return; NaN and short returns say
        # nothing (-inf), and so does no return (+inf, range_max) unless
        # ``no_return_is_free``: glass, black or shiny surfaces return nothing from most
        # angles, and a static pane seen at last head-on was flagged as moving, with the
        # camera points around it.
        self.reach = np.full((W, B), -np.inf)
        # [W, B] beams on a surface at least min_width_m wide (all, without a width).
        self.wide = np.ones((W, B), bool)

    def rows(self, g: np.ndarray) -> np.ndarray:
        """Ring rows of scans ``g`` (laid out, and among the last W)."""
        return np.asarray(g) % len(self.n)

    def fill_to(self, scans: list[LaserScan], hi: int) -> None:
        """Lay out scans [filled, hi), each over the row of the scan W before it."""
        for g in range(self.filled, hi):
            self._lay(g % len(self.n), scans[g])
        self.filled = max(self.filled, hi)

    def _lay(self, i: int, s: LaserScan) -> None:
        m = len(s.ranges)
        self.n[i] = m
        self.angle_min[i], self.angle_inc[i] = s.angle_min, s.angle_increment
        self.range_max[i] = s.range_max
        self.full[i] = abs(s.angle_increment) * m >= 2 * np.pi - 1e-6
        self.valid[i] = False
        self.x[i] = self.y[i] = 0.0
        self.reach[i] = -np.inf
        r = s.ranges.astype(np.float64)
        v = s.valid_mask()
        a = s.angles()
        self.valid[i, :m] = v
        rv = np.where(v, r, 0.0)
        self.x[i, :m] = rv * np.cos(a)
        self.y[i, :m] = rv * np.sin(a)
        reach = np.where(v, r, -np.inf)
        if self.no_return_is_free:
            with np.errstate(invalid="ignore"):
                # Compared as stored (float32): 5.6 is 5.5999999 there.
                reach = np.where(np.isposinf(r) | (s.ranges == s.range_max), s.range_max,
                                 reach)
        self.reach[i, :m] = reach
        if self.min_width_m <= 0:
            return
        # A run of neighbouring returns without a range jump (margins as in seen_through),
        # its chord plus a beam spacing. Far partners see a place from elsewhere: a chair
        # leg (3-5 cm) slips between their beams while a person's leg (12-15 cm) cannot.
        self.wide[i] = False
        if m == 0:
            return
        rn = np.where(v, r, np.nan)
        jump = ~(np.abs(np.diff(rn)) <= 0.1 + 0.03 * np.fmin(rn[1:], rn[:-1]))  # [m-1]
        run = np.concatenate([[0], np.cumsum(jump)])  # [m] run id of each beam
        starts = np.flatnonzero(np.r_[True, run[1:] != run[:-1]])
        ends = np.r_[starts[1:], m] - 1
        x, y = self.x[i, :m], self.y[i, :m]
        chord = np.hypot(x[ends] - x[starts], y[ends] - y[starts])
        width = chord + np.abs(s.angle_increment) * np.nan_to_num(rn[starts])
        self.wide[i, :m] = v & (width >= self.min_width_m)[run]

    def seen_through(self, k: np.ndarray, j: np.ndarray, T_j_k: np.ndarray, margin_m: float,
                     margin_rel: float, plane_tol_m: float) -> np.ndarray:
        """[K, Bmax] bool: scan k's valid end points that scan j sees past (rows of the
        padded run; ``T_j_k`` [K, 4, 4] maps scan k's laser frame into scan j's)."""
        x, y = self.x[k], self.y[k]  # [K, B]
        R, t = T_j_k[:, :3, :3], T_j_k[:, :3, 3]

        def row(c: int) -> np.ndarray:
            return R[:, c, 0, None] * x + R[:, c, 1, None] * y + t[:, c, None]

        qx, qy, qz = row(0), row(1), row(2)
        rq = np.hypot(qx, qy)
        n = self.n[j, None]
        b = beam_of(np.arctan2(qy, qx), self.angle_min[j, None],
                    self.angle_inc[j, None]).astype(np.int64)
        far = np.full(b.shape, np.inf)
        for db in (-1, 0, 1):
            bb = np.where(self.full[j, None], np.mod(b + db, n), b + db)
            ok = (bb >= 0) & (bb < n)
            far = np.where(ok, np.minimum(far, self.reach[j[:, None], np.clip(bb, 0, n - 1)]),
                           -np.inf)
        return (self.valid[k] & (np.abs(qz) < plane_tol_m)
                & (far > rq + margin_m + margin_rel * rq) & (rq < self.range_max[j, None]))


def cylinder_mask(points: np.ndarray, centres_xy: np.ndarray, radius: float,
                  z_max: float) -> np.ndarray:
    """[N] bool: points [N, 3] within ``radius`` (horizontally) of any centre [K, 2] and
    below ``z_max`` - the space a person whose legs the lidar saw can occupy."""
    out = np.zeros(len(points), bool)
    if len(centres_xy) == 0 or len(points) == 0:
        return out
    cand = points[:, 2] < z_max
    lo = centres_xy.min(0) - radius
    hi = centres_xy.max(0) + radius
    cand &= (points[:, 0] > lo[0]) & (points[:, 0] < hi[0]) & (points[:, 1] > lo[1]) & (
        points[:, 1] < hi[1])
    idx = np.flatnonzero(cand)
    if len(idx) == 0:
        return out
    p = points[idx, :2].astype(np.float32)
    r2 = np.float32(radius * radius)
    # Points sorted by x once; each centre then tests only the slice within its radius in x
    # (a person covers a metre of a frame that spans several).
    order = np.argsort(p[:, 0], kind="stable")
    xs = p[order, 0]
    ys = p[order, 1]
    hit = np.zeros(len(idx), bool)
    c32 = centres_xy.astype(np.float32)
    lo_i = np.searchsorted(xs, c32[:, 0] - np.float32(radius), side="left")
    hi_i = np.searchsorted(xs, c32[:, 0] + np.float32(radius), side="right")
    for (cx, cy), a, b in zip(c32, lo_i, hi_i, strict=True):
        if b <= a:
            continue
        dx = xs[a:b] - cx
        dy = ys[a:b] - cy
        hit[a:b] |= (dx * dx + dy * dy) < r2
    out[idx[order[hit]]] = True
    return out

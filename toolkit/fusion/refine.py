"""Per-frame correction of the scaled depth's low-frequency shape error.

One scale per frame fixes a monocular network's unknown scale, not its shape: the error
left after scaling is mostly a smooth multiplicative field over the image (a wall that
bends, a floor that tilts), the same in neighbouring frames, so averaging frames does not
remove it. Two references measure that field in every frame without a model of the scene:

- the lidar pairs (the pixels the scale came from), one curve across the image;
- the floor: a wheeled robot drives on it, so its plane in the camera is known from the
  base pose and the mounting (``floor_height_m`` below ``base_link``; 0 for REP 105's
  ``base_footprint`` convention). Pixels whose prediction is within ``gate`` of the
  floor's depth there are taken as floor; a chair or a wall in front of the floor is
  much nearer and falls out.

The field is fitted in log depth on a coarse grid of nodes (bilinear between them) with a
smoothness penalty between neighbouring nodes and a Huber loss, twice: the second time
only anchors within ``gate_final`` of the first field count. Above the lidar row nothing is
measured and the smoothness carries the field up from the lidar.

A smooth field cannot follow one surface the network put at the wrong depth on its own: a
room seen through a doorway, which monocular networks squash towards the near walls around
it (session 12's network put a wall 5.7 m away at 3.7 m). The gates drop those lidar pairs
as outliers. ``correct_regions`` then looks for runs of consecutive lidar pairs on one
continuous surface that agree with each other but not with the field, and rescales the
image region around each run: the pixels connected to it without crossing a depth edge and
within ``region_band`` (log) of the depths the run covers, by its full ratio over those
depths and tapering to nothing ``region_band`` beyond them.
A lidar farther than the prediction is believed only through an opening (the region's left
and right neighbours, each side on its own, nearer than it; a region at the image's border
is none): a 2D lidar passes under sofas and beds the camera above it sees, and those
pairs, too, agree with each other. A region is left alone, too, when at least as many
other lidar pairs on it agree with its current depth as the run has pairs: the run then
hit something in front of the surface the camera sees there (a person who has moved on).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from threadpoolctl import ThreadpoolController

from toolkit.camera import PinholeCamera, pixel_index
from toolkit.fusion.cloud import edge_mask


@dataclass(frozen=True)
class RefineOptions:
    """How the correction field is fitted (see the module docstring)."""

    grid: tuple[int, int] = (8, 6)  # nodes across and down the image
    step_px: int = 8  # floor anchors on every step_px-th pixel
    gate: float = 0.12  # |log(reference / depth)| for an anchor to count, first fit
    gate_final: float = 0.06  # the same around the first fit's field, second fit
    smooth: float = 1.0  # weight of node differences, per 1000 anchors
    huber: float = 0.03  # log-depth residual where the loss turns linear
    min_anchors: int = 50  # fewer: the frame keeps its depth as scaled
    max_depth_m: float = 6.0  # floor anchors nearer than this
    # Vertical columns through the lidar points (walls stand upright): anchors up to this
    # height above the floor every column_step_m, at most max_columns lidar points (0: off)
    column_top_m: float = 2.2
    column_step_m: float = 0.1
    max_columns: int = 120
    # Region correction (module docstring; 0 beams: off): a run of at least this many
    # consecutive lidar pairs, steps under max(region_step_m, 5 % of the range), whose log
    # ratios to the field's depth have a median beyond gate_final and a median absolute
    # deviation under region_mad
    region_min_beams: int = 5
    region_step_m: float = 0.1
    region_mad: float = 0.03
    region_band: float = 0.15  # log depth around the run's that the region spans
    region_edge: float = 0.1  # log depth jump over 3 x 3 pixels that bounds a region
    # through an opening: the region's side neighbours this much nearer (log)
    region_opening: float = 0.1


@dataclass
class Refinement:
    """What the correction did to one frame."""

    applied: bool
    anchors_floor: int = 0
    anchors_lidar: int = 0
    anchors_columns: int = 0
    field_rms: float = 0.0  # RMS of the log correction over the image
    field_max: float = 0.0  # largest |log correction|
    regions: int = 0  # regions rescaled after the field (``correct_regions``)


def interpolation_weights(n: int, nodes: int) -> np.ndarray:
    """[n, nodes] linear interpolation weights of n pixels between evenly spread nodes."""
    x = np.linspace(0.0, nodes - 1.0, n)
    i0 = np.clip(np.floor(x).astype(np.int64), 0, nodes - 2)
    f = x - i0
    w = np.zeros((n, nodes))
    w[np.arange(n), i0] = 1.0 - f
    w[np.arange(n), i0 + 1] = f
    return w


@dataclass
class Design:
    """Bilinear weights of M pixels on the grid's nodes: 4 nodes per pixel."""

    index: np.ndarray  # [M, 4] int node indices
    weight: np.ndarray  # [M, 4] float weights (sum 1 per row)

    def __len__(self) -> int:
        return len(self.index)

    def select(self, mask: np.ndarray) -> Design:
        return Design(self.index[mask], self.weight[mask])

    def dot(self, nodes: np.ndarray) -> np.ndarray:
        """[M] field values of the node values (any shape with G entries)."""
        return np.einsum("mk,mk->m", self.weight, nodes.reshape(-1)[self.index])

    @staticmethod
    def concat(parts: list[Design]) -> Design:
        return Design(np.concatenate([p.index for p in parts]),
                      np.concatenate([p.weight for p in parts]))


class CorrectionGrid:
    """A smooth log-depth field on ``nodes`` = (across, down) bilinear nodes."""

    def __init__(self, width: int, height: int, nodes: tuple[int, int]) -> None:
        gx, gy = int(nodes[0]), int(nodes[1])
        if gx < 2 or gy < 2:
            raise ValueError(f"refine grid needs at least 2 x 2 nodes, got {nodes}")
        self.gx, self.gy = gx, gy
        self.wx = interpolation_weights(width, gx)  # [W, gx]
        self.wy = interpolation_weights(height, gy)  # [H, gy]
        diffs = []
        for y in range(gy):
            for x in range(gx):
                for dy, dx in ((0, 1), (1, 0)):
                    if y + dy < gy and x + dx < gx:
                        row = np.zeros(gx * gy)
                        row[y * gx + x] = 1.0
                        row[(y + dy) * gx + x + dx] = -1.0
                        diffs.append(row)
        D = np.array(diffs)
        # A small ridge keeps nodes that no anchor reaches at the smoothness's value.
        self.penalty = D.T @ D + 1e-3 * np.eye(gx * gy)  # [G, G]
        # Each pixel's two nodes along each axis and their weights.
        self._x0 = np.minimum(np.argmax(self.wx > 0, axis=1), gx - 2)
        self._y0 = np.minimum(np.argmax(self.wy > 0, axis=1), gy - 2)

    def design(self, rows: np.ndarray, cols: np.ndarray) -> Design:
        """Node weights of the pixels (rows [M], cols [M])."""
        x0, y0 = self._x0[cols], self._y0[rows]
        fx = self.wx[cols, x0 + 1]
        fy = self.wy[rows, y0 + 1]
        g = self.gx
        index = np.stack([y0 * g + x0, y0 * g + x0 + 1, (y0 + 1) * g + x0,
                          (y0 + 1) * g + x0 + 1], 1)
        weight = np.stack([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx], 1)
        return Design(index, weight)

    def fit(self, A: Design, r: np.ndarray, smooth: float, huber: float,
            iterations: int = 4) -> np.ndarray:
        """[gy, gx] node values fitting residuals ``r`` [M] at pixels whose node weights
        are ``A`` (``design``): Huber IRLS on the normal equations, which are summed with
        ``bincount`` over each row's 4 x 4 node pairs (the dense [M, G] product cost 7 ms
        per frame)."""
        G = self.gx * self.gy
        lam = smooth * len(r) / 1000.0
        w = np.ones(len(r))
        c = np.zeros(G)
        pair = (A.index[:, :, None] * G + A.index[:, None, :]).reshape(len(r), 16)
        ww = (A.weight[:, :, None] * A.weight[:, None, :]).reshape(len(r), 16)
        for _ in range(iterations):
            AtA = np.bincount(pair.ravel(), (ww * w[:, None]).ravel(), G * G).reshape(G, G)
            Atr = np.bincount(A.index.ravel(), (A.weight * (w * r)[:, None]).ravel(), G)
            c = np.linalg.solve(AtA + lam * self.penalty, Atr)
            e = np.abs(A.dot(c) - r)
            w = np.where(e <= huber, 1.0, huber / np.maximum(e, 1e-12))
        return c.reshape(self.gy, self.gx)

    def field(self, nodes: np.ndarray) -> np.ndarray:
        """[H, W] float32 field of the node values [gy, gx]."""
        return (self.wy @ nodes @ self.wx.T).astype(np.float32)


def floor_depth(rays_world: np.ndarray, centre: np.ndarray, normal: np.ndarray,
                point: np.ndarray) -> np.ndarray:
    """[M] camera z-depth at which rays [M, 3] (world directions of camera rays with
    z_camera = 1) from ``centre`` [3] meet the plane through ``point`` with upward
    ``normal``; inf where a ray does not go down to it."""
    nd = rays_world @ normal  # [M]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(nd < -1e-6, float(normal @ (point - centre)) / nd, np.inf)
    return np.where(t > 0, t, np.inf)


def lidar_runs(points_cam: np.ndarray, scan_beam: np.ndarray, min_step_m: float,
               step_rel: float = 0.05) -> list[np.ndarray]:
    """Index arrays into the lidar points [N, 3] of runs on one continuous surface: the
    same scan, beams at most 2 apart (one dropped or hidden between), and each step under
    max(``min_step_m``, ``step_rel`` x the range). ``scan_beam`` [N, 2] int: scan and
    beam index of each point."""
    if len(points_cam) == 0:
        return []
    order = np.lexsort((scan_beam[:, 1], scan_beam[:, 0]))  # [N]
    p = points_cam[order]
    sb = scan_beam[order]
    brk = np.ones(len(order), bool)
    step = np.linalg.norm(np.diff(p, axis=0), axis=1)  # [N-1]
    reach = np.maximum(min_step_m, step_rel * np.linalg.norm(p[1:], axis=1))
    brk[1:] = (np.diff(sb[:, 0]) != 0) | (np.diff(sb[:, 1]) > 2) | (step > reach)
    return np.split(order, np.flatnonzero(brk)[1:])


def seam_free_beams(beam: np.ndarray, n_beams: int) -> np.ndarray:
    """[N] beam indices of one full-circle scan renumbered so that no run crosses the
    scan's seam (beam n_beams - 1 next to beam 0: straight ahead for drivers whose scan
    starts forward, 0..2 pi): counted from just after the widest gap between the given
    beams, which for the pixels of one camera lies outside its view."""
    if len(beam) < 2:
        return beam.copy()
    u = np.unique(beam)  # sorted
    gaps = np.diff(np.append(u, u[0] + n_beams))  # [U] from each beam to the next, circular
    start = u[(np.argmax(gaps) + 1) % len(u)]
    return (beam - start) % n_beams


def region_around(log_depth: np.ndarray, edges: np.ndarray, seeds: np.ndarray,
                  level: float, band: float) -> np.ndarray:
    """[H, W] bool: pixels within ``band`` of ``level`` (log depth) connected (4
    neighbours) to a seed pixel [K, 2] (col, row) without crossing an ``edges`` pixel."""
    with np.errstate(invalid="ignore"):
        inside = (np.abs(log_depth - level) <= band) & ~edges
    _, labels = cv2.connectedComponents(inside.astype(np.uint8), connectivity=4)
    hit = np.unique(labels[seeds[:, 1], seeds[:, 0]])
    return np.isin(labels, hit[hit > 0])


def through_opening(log_depth: np.ndarray, region: np.ndarray, level: float, margin: float,
                    reach_px: int) -> bool:
    """Whether the pixels left of ``region`` and those right of it (up to ``reach_px``),
    each side on its own, lie nearer than ``level`` - ``margin`` (log depth): the region
    is seen through an opening in a nearer surface (a doorway), not a surface in front of
    a farther one. A region without one of its sides (at the image's border) is none."""
    valid = np.isfinite(log_depth)
    r8 = region.astype(np.uint8)
    kernel = np.ones((1, reach_px + 1), np.uint8)
    # A one-sided dilation: anchored at the kernel's left end it reaches region pixels up
    # to reach_px to the right (the left side), at its right end those to the left.
    for anchor in (0, reach_px):
        side = (cv2.dilate(r8, kernel, anchor=(anchor, 0)) > 0) & ~region & valid
        if side.sum() < reach_px or not np.median(log_depth[side]) < level - margin:
            return False
    return True


def _log_depth(depth: np.ndarray) -> np.ndarray:
    """log of the depth [any shape], NaN where it is not finite and positive."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.isfinite(depth) & (depth > 0), np.log(depth), np.nan)


def _some_run_disagrees(runs: list[np.ndarray], rho: np.ndarray, o: RefineOptions) -> bool:
    """Whether a run of the lidar pairs passes ``correct_regions``' tests on its own log
    ratios ``rho`` [N] (enough finite pairs, far enough from the field and agreeing with
    each other): only such a run's region can be rescaled."""
    for run in runs:
        r = rho[run]
        r = r[np.isfinite(r)]
        if len(r) < o.region_min_beams:
            continue
        med = float(np.median(r))
        if abs(med) > o.gate_final and np.median(np.abs(r - med)) <= o.region_mad:
            return True
    return False


def correct_regions(depth: np.ndarray, px: np.ndarray, z: np.ndarray, points_cam: np.ndarray,
                    scan_beam: np.ndarray, opts: RefineOptions) -> tuple[np.ndarray, int]:
    """``depth`` [H, W] with the regions around lidar runs it disagrees with rescaled (the
    module docstring), and how many: lidar pixels ``px`` [N, 2] (col, row), z-depths
    ``z`` [N], camera-frame points [N, 3] and scan / beam indices [N, 2]."""
    o = opts
    h, w = depth.shape
    runs = [r for r in lidar_runs(points_cam, scan_beam, o.region_step_m)
            if len(r) >= o.region_min_beams]
    if not runs:
        return depth, 0
    cols, rows = np.clip(px[:, 0], 0, w - 1), np.clip(px[:, 1], 0, h - 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.log(z) - _log_depth(depth[rows, cols])  # [N] log(lidar / depth)
    if not _some_run_disagrees(runs, rho, o):
        # The usual frame: its runs fail the tests on their own pairs, and the whole image's
        # log depth and edges below were most of this function's time (the paper
        # benchmark's fuse_net: 1.1 s over 644 frames, 0.3 s without; 3 regions rescaled).
        return depth, 0
    L = _log_depth(depth)  # [H, W]
    # The map's flying-pixel test over 3 x 3 pixels, its relative jump the log range's
    edges = edge_mask(depth, float(np.expm1(o.region_edge)), window=3) | ~np.isfinite(L)
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.log(z) - L[rows, cols]  # [N] log(lidar / depth)
    out = depth.copy()
    done = np.zeros((h, w), bool)
    reach = max(3, w // 64)
    n = 0
    for run in runs:
        run = run[np.isfinite(rho[run])]
        if len(run) < o.region_min_beams or done[rows[run], cols[run]].mean() > 0.5:
            continue
        med = float(np.median(rho[run]))
        if abs(med) <= o.gate_final or np.median(np.abs(rho[run] - med)) > o.region_mad:
            continue
        # The band spans the depths the run itself covers, and region_band beyond: about
        # its median alone, a far wall turned 10-20 deg from the camera kept 40 % of its
        # error at the run's ends, and from 30 deg the band cut a slice out of the wall
        # whose sides (the same wall) made it no opening (nothing rescaled).
        Lr = L[rows[run], cols[run]]  # [R]
        lo, hi = float(Lr.min()), float(Lr.max())
        level, half = (lo + hi) / 2, (hi - lo) / 2
        region = region_around(L, edges, np.stack([cols[run], rows[run]], 1), level,
                               half + o.region_band) & ~done
        if not region.any():
            continue
        if med > 0 and not through_opening(L, region, float(np.median(Lr)), o.region_opening,
                                           reach):
            continue
        # The region is drawn at the depth as it is, not at the run's: a short run on
        # something the camera no longer sees there (a passing person's leg, the scan a
        # few tens of ms off the image) lay on the wall behind it and rescaled all of it
        # (a person 2.5 m away put a 4 m wall at 2.5 m). The other pairs on the region
        # outvote the run when as many of them agree with the depth as it is.
        others = region[rows, cols]  # [N]
        others[run] = False
        with np.errstate(invalid="ignore"):
            if np.count_nonzero(others & (np.abs(rho) < o.gate_final)) >= len(run):
                continue
        # The full ratio over the run's own depths, tapering to nothing region_band beyond
        beyond = np.maximum(np.abs(L[region] - level) - half, 0.0)
        taper = np.clip(1.0 - beyond / o.region_band, 0.0, 1.0)
        out[region] = out[region] * np.exp(med * taper).astype(out.dtype)
        done |= region
        n += 1
    return out, n


class DepthRefiner:
    """Fits and applies the correction field of one camera's frames."""

    def __init__(self, camera: PinholeCamera, options: RefineOptions | None = None,
                 floor_height_m: float | None = 0.0) -> None:
        self.opts = options or RefineOptions()
        self.camera = camera
        self.floor_height_m = floor_height_m
        h, w = camera.height, camera.width
        self.grid = CorrectionGrid(w, h, self.opts.grid)
        s = self.opts.step_px
        rows = np.arange(s // 2, h, s)
        cols = np.arange(s // 2, w, s)
        rr, cc = np.meshgrid(rows, cols, indexing="ij")
        self.rows, self.cols = rr.ravel(), cc.ravel()  # [M] anchor pixels
        self.rays = camera.pixel_rays()[self.rows, self.cols].astype(np.float64)  # [M, 3]
        self.design = self.grid.design(self.rows, self.cols)  # the same every frame
        # Found once: looking the BLAS libraries up costs 0.45 ms, limiting them 0.01 ms.
        self._threads = ThreadpoolController()

    def floor_reference(self, T_world_camera: np.ndarray, T_world_base: np.ndarray) -> (
        np.ndarray
    ):
        """[M] floor depth at the anchor pixels (inf: the ray misses the floor in range)."""
        if self.floor_height_m is None:
            return np.full(len(self.rows), np.inf)
        normal = T_world_base[:3, 2]
        point = T_world_base[:3, 3] - self.floor_height_m * normal  # below base_link
        d = self.rays @ T_world_camera[:3, :3].T
        t = floor_depth(d, T_world_camera[:3, 3], normal, point)
        return np.where(t <= self.opts.max_depth_m, t, np.inf)

    def column_anchors(self, points_cam: np.ndarray, T_world_camera: np.ndarray,
                       T_world_base: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels [K, 2] (col, row) and z-depths [K] of vertical columns through lidar
        points [N, 3] (camera frame), from the floor (or 0.25 m below the point) up to
        ``column_top_m`` above the floor, every ``column_step_m``."""
        o = self.opts
        if len(points_cam) == 0 or o.column_top_m <= 0:
            return np.zeros((0, 2), np.int64), np.zeros(0)
        # Rounded up: a maximum (floor division let 121-239 points all have one, twice
        # the anchors of 240)
        step = max(1, -(-len(points_cam) // o.max_columns))
        pc = points_cam[::step]  # [C, 3]
        R_cw = T_world_camera[:3, :3].T
        up = R_cw @ T_world_base[:3, 2]  # base z in the camera frame
        # Height of each point above the floor (or the lidar plane's own height).
        pw = pc @ T_world_camera[:3, :3].T + T_world_camera[:3, 3]
        base_z = (pw - T_world_base[:3, 3]) @ T_world_base[:3, 2]  # [C] above base_link
        # The floor's height along base z (floor_height_m below base_link)
        floor = -self.floor_height_m if self.floor_height_m is not None else None
        lo = (floor - base_z) if floor is not None else np.full(len(pc), -0.25)
        top = (floor if floor is not None else 0.0) + o.column_top_m - base_z
        offs = np.arange(0.0, o.column_top_m + 0.25 + 1e-9, o.column_step_m)  # [S]
        s = lo[:, None] + offs[None, :]  # [C, S] metres along up from the point
        valid = s <= top[:, None]
        q = pc[:, None, :] + s[..., None] * up  # [C, S, 3]
        q = q[valid]
        uv, z = self.camera.project(q)
        keep = (z > 0.05) & self.camera.in_image(uv)
        return pixel_index(uv[keep]), z[keep]

    def refine(self, depth: np.ndarray, T_world_camera: np.ndarray,
               T_world_base: np.ndarray, lidar_px: np.ndarray | None = None,
               lidar_z: np.ndarray | None = None,
               lidar_points_cam: np.ndarray | None = None,
               lidar_scan_beam: np.ndarray | None = None) -> tuple[np.ndarray, Refinement]:
        """Corrected depth [H, W] float32 and what was done, from the scaled ``depth``
        [H, W], the poses and the lidar pairs: pixels ``lidar_px`` [N, 2] (col, row) with
        their lidar z-depths ``lidar_z`` [N], camera-frame points ``lidar_points_cam``
        [N, 3] (for the vertical columns) and scan / beam indices ``lidar_scan_beam``
        [N, 2] int (with the points, for the region correction)."""
        # The matrices here are tiny: BLAS's second thread only spins (on 2 cores it
        # doubled the CPU time of the correction and took it from the rest of the fusion).
        with self._threads.limit(limits=1, user_api="blas"):
            return self._refine(depth, T_world_camera, T_world_base, lidar_px, lidar_z,
                                lidar_points_cam, lidar_scan_beam)

    def _refine(self, depth: np.ndarray, T_world_camera: np.ndarray,
                T_world_base: np.ndarray, lidar_px: np.ndarray | None,
                lidar_z: np.ndarray | None, lidar_points_cam: np.ndarray | None,
                lidar_scan_beam: np.ndarray | None) -> tuple[np.ndarray, Refinement]:
        o = self.opts
        h, w = depth.shape
        tf = self.floor_reference(T_world_camera, T_world_base)
        d_anchor = depth[self.rows, self.cols].astype(np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            r_floor = np.log(tf) - np.log(d_anchor)  # [M]
        A, r = [self.design], [r_floor]
        n_floor_all = len(r_floor)

        def add_anchors(px: np.ndarray, z: np.ndarray) -> None:
            """Pixels [K, 2] (col, row) whose depth should be z [K]."""
            cc = np.clip(px[:, 0], 0, w - 1)
            rr = np.clip(px[:, 1], 0, h - 1)
            with np.errstate(divide="ignore", invalid="ignore"):
                r.append(np.log(z) - np.log(depth[rr, cc].astype(np.float64)))
            A.append(self.grid.design(rr, cc))

        if lidar_px is not None and lidar_z is not None and len(lidar_z):
            add_anchors(lidar_px, lidar_z)
        n_lidar_end = sum(len(x) for x in r)
        if lidar_points_cam is not None and len(lidar_points_cam):
            add_anchors(*self.column_anchors(lidar_points_cam, T_world_camera, T_world_base))
        A_a, r_a = Design.concat(A), np.concatenate(r)
        ok = np.isfinite(r_a) & (np.abs(r_a) < o.gate)
        if ok.sum() < o.min_anchors:
            return depth, self._counts(False, ok, n_floor_all, n_lidar_end)
        nodes = self.grid.fit(A_a.select(ok), r_a[ok], o.smooth, o.huber)
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(r_a) & (np.abs(r_a - A_a.dot(nodes)) < o.gate_final)
        if ok.sum() < o.min_anchors:
            return depth, self._counts(False, ok, n_floor_all, n_lidar_end)
        nodes = self.grid.fit(A_a.select(ok), r_a[ok], o.smooth, o.huber)
        f = self.grid.field(nodes)
        out = (depth * np.exp(f)).astype(np.float32)
        info = self._counts(True, ok, n_floor_all, n_lidar_end)
        if (o.region_min_beams > 0 and lidar_scan_beam is not None
                and lidar_points_cam is not None and lidar_px is not None
                and lidar_z is not None):
            out, info.regions = correct_regions(out, lidar_px, lidar_z, lidar_points_cam,
                                                lidar_scan_beam, o)
        info.field_rms = float(np.sqrt(np.mean(f.astype(np.float64) ** 2)))
        info.field_max = float(np.abs(f).max())
        return out, info

    @staticmethod
    def _counts(applied: bool, ok: np.ndarray, n_floor: int, n_lidar_end: int) -> Refinement:
        return Refinement(applied, int(ok[:n_floor].sum()), int(ok[n_floor:n_lidar_end].sum()),
                          anchors_columns=int(ok[n_lidar_end:].sum()))

"""Scan-to-grid matching: a correlative search over a window, then continuous refinement.

Two stages, as in Cartographer:

1. ``correlative_search``: score every pose of a window (angles x translations) by the
   mean grid probability under the scan points, optionally weighted by a motion prior.
   It runs branch-and-bound over a pyramid of max-pooled grids (``GridPyramid``), so one
   routine serves the small real-time window of local SLAM and the metres-wide window of
   loop closure. The pyramid level ``d`` stores, per cell ``i``, the max over the fine
   cells ``[i, i + 2^d)`` at the fine resolution (Cartographer's sliding-window grids): an
   upper bound of the score of all ``2^d`` translations a candidate stands for, read by
   one gather at the same cell offsets on every level. The search is breadth-first and
   vectorised: each level keeps the
   candidates whose bound beats the best score found so far (a greedy dive gives a first
   score), optionally capped to the best ``max_candidates``.
2. ``refine``: Levenberg-Marquardt on the bicubic (Catmull-Rom) interpolated grid with
   translation and rotation priors (Cartographer's ``CeresScanMatcher2D`` cost).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from toolkit.geometry import se2_to_matrix, transform_points
from toolkit.slam2d.grid import lattice_cells


@dataclass
class SearchResult:
    pose: np.ndarray  # [3] (x, y, theta) of the scan in the grid frame
    score: float  # mean probability under the points (times the prior factor, if any)
    found: bool  # False: nothing scored above min_score; pose is then the initial pose
    candidates: int  # candidates scored, for timing statistics


class GridPyramid:
    """Cartographer's precomputation grids for branch-and-bound, as uint8 probabilities.

    Level ``d`` holds at cell (iy, ix) the max of the fine probabilities over
    ``[iy, iy + 2^d) x [ix, ix + 2^d)``: an upper bound of the score of every translation
    a level-``d`` candidate stands for. All levels keep the fine resolution, so a
    candidate's cells are ``base + offset`` at every level and a bound costs one gather.
    The fine grid is padded with p_min by ``2 * window_cells + 2^depth`` cells so that
    clamped indices of points off the grid always read unknown space (``pad_value``
    when unknown cells score apart from free ones).
    """

    def __init__(self, prob: np.ndarray, origin: np.ndarray, resolution: float, depth: int,
                 p_min: float, window_cells: int, pad_value: float | None = None) -> None:
        self.depth = int(depth)
        self.resolution = float(resolution)
        self.window_cells = int(window_cells)
        pad = 2 * self.window_cells + (1 << self.depth) + 1
        h, w = prob.shape
        q_min = int(np.ceil((p_min if pad_value is None else pad_value) * 255.0))
        fine = np.full((h + 2 * pad, w + 2 * pad), q_min, np.uint8)
        # Round up: a bound must never be below the probability it stands for.
        fine[pad : pad + h, pad : pad + w] = np.ceil(prob * 255.0).astype(np.uint8)
        self.origin = np.asarray(origin, dtype=np.float64) - pad * resolution  # [2]
        self.shape = fine.shape
        self.pad = pad
        self.levels: list[np.ndarray] = [fine.reshape(-1)]
        cur = fine
        for d in range(self.depth):
            step = 1 << d
            nxt = cur.copy()
            np.maximum(nxt[:-step], cur[step:], out=nxt[:-step])
            nxt2 = nxt.copy()
            np.maximum(nxt2[:, :-step], nxt[:, step:], out=nxt2[:, :-step])
            cur = nxt2
            self.levels.append(cur.reshape(-1))

    @property
    def nbytes(self) -> int:
        return sum(lv.nbytes for lv in self.levels)


def angular_step(resolution: float, max_range: float) -> float:
    """Angle (rad) that moves the farthest point by about one cell (Cartographer's rule)."""
    r = max(max_range, 2.0 * resolution)
    return float(np.arccos(1.0 - resolution**2 / (2.0 * r**2)))


def correlative_search(
    pyramid: GridPyramid,
    points: np.ndarray,
    initial_pose: np.ndarray,
    linear_window: float,
    angular_window: float,
    angular_resolution: float,
    min_score: float = 0.0,
    translation_cost: float = 0.0,
    rotation_cost: float = 0.0,
    max_candidates: int = 4000,
    greedy_dives: int = 4,
) -> SearchResult:
    """Best pose of ``points`` [N, 2] (scan frame) in the window around ``initial_pose``.

    The score of a pose is mean_n P(cell under point n), times
    ``exp(-(translation_cost * |dt| + rotation_cost * |dtheta|)^2)`` when the costs are
    non-zero (Cartographer's real-time correlative matcher). Windows are half-widths; the
    linear one is clamped to the window the pyramid was padded for. The pose's angle is
    ``initial_pose``'s plus the offset found, not wrapped: ``refine``, which takes it next,
    pulls towards its rotation prior by plain difference, so an angle wrapped across +-pi
    would start it 2 pi from the prior (callers wrap the refined pose).
    """
    pts = np.asarray(points, dtype=np.float64)
    x0, y0, th0 = (float(v) for v in initial_pose)
    res = pyramid.resolution
    D = pyramid.depth
    Hp, Wp = pyramid.shape
    w = min(int(np.ceil(linear_window / res)), pyramid.window_cells)
    n_ang = int(np.ceil(angular_window / angular_resolution)) if angular_window > 0 else 0
    dth = np.arange(-n_ang, n_ang + 1) * angular_resolution  # [K]
    c, s = np.cos(th0 + dth), np.sin(th0 + dth)
    # Fine cell of every point at every angle at zero offset, clamped so that any offset
    # in the window stays on the padded grid. The grid's world -> cell rule: a point on a
    # cell border (within rounding) is in the cell above it, as where the grid inserted it.
    wx = c[:, None] * pts[None, :, 0] - s[:, None] * pts[None, :, 1] + x0  # [K, N]
    wy = s[:, None] * pts[None, :, 0] + c[:, None] * pts[None, :, 1] + y0  # [K, N]
    cell = lattice_cells(np.stack([wx, wy], -1) - pyramid.origin, res)  # [K, N, 2]
    cx = np.clip(cell[..., 0], w, Wp - 1 - w - (1 << D))  # [K, N]
    cy = np.clip(cell[..., 1], w, Hp - 1 - w - (1 << D))
    base = cy * Wp + cx  # [K, N]
    n = pts.shape[0]
    norm = 1.0 / (255.0 * max(n, 1))
    use_prior = translation_cost > 0.0 or rotation_cost > 0.0
    abs_dth = np.abs(dth)

    def score(level: int, k: np.ndarray, ox: np.ndarray, oy: np.ndarray) -> np.ndarray:
        """Bound (level > 0) or exact score (level 0) of candidates [M]."""
        out = np.empty(len(k), np.float64)
        flat = pyramid.levels[level]
        chunk = max(1, 1_000_000 // max(n, 1))
        off = oy.astype(np.int64) * Wp + ox
        for a in range(0, len(k), chunk):
            idx = base[k[a : a + chunk]] + off[a : a + chunk, None]  # [M, N]
            out[a : a + chunk] = flat[idx].sum(axis=1, dtype=np.int64)
        out *= norm
        if use_prior:
            if level:
                # Distance from zero to the candidate's box [o, o + 2^level - 1] per axis.
                size = (1 << level) - 1
                dx = np.where((ox <= 0) & (ox + size >= 0), 0,
                              np.minimum(np.abs(ox), np.abs(ox + size))) * res
                dy = np.where((oy <= 0) & (oy + size >= 0), 0,
                              np.minimum(np.abs(oy), np.abs(oy + size))) * res
            else:
                dx, dy = np.abs(ox) * res, np.abs(oy) * res
            pen = translation_cost * np.hypot(dx, dy) + rotation_cost * abs_dth[k]
            out *= np.exp(-(pen**2))
        return out

    def children(level: int, k: np.ndarray, ox: np.ndarray, oy: np.ndarray) -> tuple[
        np.ndarray, np.ndarray, np.ndarray
    ]:
        half = 1 << (level - 1)
        kk = np.repeat(k, 4)
        xx = np.repeat(ox, 4) + np.tile([0, half, 0, half], len(k))
        yy = np.repeat(oy, 4) + np.tile([0, 0, half, half], len(k))
        keep = (xx <= w) & (yy <= w)
        return kk[keep], xx[keep], yy[keep]

    top = 1 << D
    offs = np.arange(-w, w + 1, top)
    K = len(dth)
    kk, xx, yy = np.meshgrid(np.arange(K), offs, offs, indexing="ij")
    k, ox, oy = kk.ravel(), xx.ravel(), yy.ravel()
    sc = score(D, k, ox, oy)
    evaluated = len(k)

    best = float(min_score)
    best_cand: tuple[int, int, int] | None = None
    # Greedy dives from the most promising top candidates give a score to prune with.
    for i in np.argsort(-sc)[:greedy_dives]:
        if sc[i] <= best:
            break
        ck, cxo, cyo = k[i : i + 1], ox[i : i + 1], oy[i : i + 1]
        leaf = float(sc[i])
        for level in range(D, 0, -1):
            ck, cxo, cyo = children(level, ck, cxo, cyo)
            s_ch = score(level - 1, ck, cxo, cyo)
            evaluated += len(ck)
            j = int(np.argmax(s_ch))
            ck, cxo, cyo = ck[j : j + 1], cxo[j : j + 1], cyo[j : j + 1]
            leaf = float(s_ch[j])
        if leaf > best:
            best, best_cand = leaf, (int(ck[0]), int(cxo[0]), int(cyo[0]))

    keep = sc > best
    k, ox, oy, sc = k[keep], ox[keep], oy[keep], sc[keep]
    for level in range(D, 0, -1):
        if len(k) == 0:
            break
        if len(k) > max_candidates:
            sel = np.argpartition(-sc, max_candidates)[:max_candidates]
            k, ox, oy = k[sel], ox[sel], oy[sel]
        k, ox, oy = children(level, k, ox, oy)
        sc = score(level - 1, k, ox, oy)
        evaluated += len(k)
        keep = sc > best
        k, ox, oy, sc = k[keep], ox[keep], oy[keep], sc[keep]
    if len(k):  # level 0: exact scores above the best so far
        j = int(np.argmax(sc))
        best, best_cand = float(sc[j]), (int(k[j]), int(ox[j]), int(oy[j]))

    if best_cand is None:
        return SearchResult(np.array([x0, y0, th0]), 0.0, False, evaluated)
    kb, oxb, oyb = best_cand
    pose = np.array([x0 + oxb * res, y0 + oyb * res, th0 + dth[kb]])
    return SearchResult(pose, best, True, evaluated)


# ------------------------------------------------------------------ continuous refinement


def _catmull_rom(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weights [N, 4] and their derivatives [N, 4] for offsets -1, 0, 1, 2."""
    # Polynomial coefficients (rows: 1, t, t^2, t^3) times 2, applied as one matrix
    # product: the refinement calls this twice per iteration on a few hundred points,
    # where the cost of each numpy call, not the arithmetic, dominates.
    T = np.stack([np.ones_like(t), t, t * t, t * t * t], -1)  # [N, 4]
    return T @ _CR_W, T[:, :3] @ _CR_DW


_CR_W = 0.5 * np.array([[0, 2, 0, 0], [-1, 0, 1, 0], [2, -5, 4, -1], [-1, 3, -3, 1]],
                       dtype=np.float64)  # [4 powers, 4 taps]
_CR_DW = 0.5 * np.array([[-1, 0, 1, 0], [4, -10, 8, -2], [-3, 9, -9, 3]],
                        dtype=np.float64)  # derivative: [3 powers, 4 taps]
_OFF = np.arange(-1, 3)


def interpolate(prob: np.ndarray, origin: np.ndarray, resolution: float,
                points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bicubic value [N] and metric gradient [N, 2] of ``prob`` at points [N, 2]."""
    H, W = prob.shape
    uv = (points - origin) / resolution - 0.5  # [N, 2]
    iuv = np.floor(uv)
    w, dw = _catmull_rom((uv - iuv).reshape(-1))  # [2N, 4]: rows u0, v0, u1, v1, ...
    wu, wv = w[0::2], w[1::2]
    dwu, dwv = dw[0::2], dw[1::2]
    ii = iuv.astype(np.int64)
    # np.minimum/maximum: np.clip's Python wrapper costs more than the work here.
    cols = np.minimum(np.maximum(ii[:, :1] + _OFF, 0), W - 1)  # [N, 4]
    rows = np.minimum(np.maximum(ii[:, 1:] + _OFF, 0), H - 1)
    # float64 before the products: mixed float32/float64 operands take numpy's slow path.
    patch = prob.reshape(-1)[rows[:, :, None] * W + cols[:, None, :]].astype(np.float64)
    pu = np.einsum("nab,nb->na", patch, wu)  # [N, 4] interpolated along x per row
    pdu = np.einsum("nab,nb->na", patch, dwu)  # ... its x derivative
    val = np.einsum("na,na->n", pu, wv)
    gx = np.einsum("na,na->n", pdu, wv) / resolution
    gy = np.einsum("na,na->n", pu, dwv) / resolution
    return val, np.stack([gx, gy], -1)


@dataclass
class RefineResult:
    pose: np.ndarray  # [3]
    score: float  # mean interpolated probability under the points at the final pose
    iterations: int


def refine(
    prob: np.ndarray,
    origin: np.ndarray,
    resolution: float,
    points: np.ndarray,
    initial_pose: np.ndarray,
    prior_translation: np.ndarray | None = None,
    prior_rotation: float | None = None,
    occupied_weight: float = 1.0,
    translation_weight: float = 10.0,
    rotation_weight: float = 40.0,
    max_iterations: int = 20,
    step_tolerance: float = 1e-4,
    initial_damping: float = 0.1,
) -> RefineResult:
    """Levenberg-Marquardt on ``sum (w_o/sqrt(N) (1 - M(T p)))^2 + priors`` (Cartographer).

    Priors pull the translation to ``prior_translation`` (default: the initial one) and the
    angle to ``prior_rotation`` (default: the initial one).
    """
    pts = np.asarray(points, dtype=np.float64)
    n = len(pts)
    pose = np.asarray(initial_pose, dtype=np.float64).copy()
    pt = pose[:2].copy() if prior_translation is None else np.asarray(prior_translation, float)
    pr = float(pose[2]) if prior_rotation is None else float(prior_rotation)
    sw = occupied_weight / np.sqrt(max(n, 1))
    px, py = pts[:, 0], pts[:, 1]

    def evaluate(p: np.ndarray, jac: bool) -> tuple[float, np.ndarray | None,
                                                   np.ndarray | None, np.ndarray]:
        c, s = np.cos(p[2]), np.sin(p[2])
        wpts = np.stack([c * px - s * py + p[0], s * px + c * py + p[1]], -1)
        val, grad = interpolate(prob, origin, resolution, wpts)
        r = sw * (1.0 - val)  # [N]
        rp = np.array([translation_weight * (p[0] - pt[0]), translation_weight * (p[1] - pt[1]),
                       rotation_weight * (p[2] - pr)])
        cost = float(r @ r + rp @ rp)
        if not jac:
            return cost, None, None, val
        dth_x = -s * px - c * py
        dth_y = c * px - s * py
        J = -sw * np.stack([grad[:, 0], grad[:, 1], grad[:, 0] * dth_x + grad[:, 1] * dth_y], -1)
        Hm = J.T @ J
        g = J.T @ r
        Hm[0, 0] += translation_weight**2
        Hm[1, 1] += translation_weight**2
        Hm[2, 2] += rotation_weight**2
        g += np.array([translation_weight, translation_weight, rotation_weight]) * rp
        return cost, Hm, g, val

    cost, Hm, g, val = evaluate(pose, True)
    # Levenberg-Marquardt with Nielsen's damping update: the damping follows the ratio of
    # actual to predicted decrease, so steps on the non-quadratic bicubic surface are not
    # alternately accepted and rejected (the fixed x0.3 / x10 schedule spent half of its
    # iterations on rejected steps).
    lam, nu = initial_damping, 2.0
    it = 0
    for _ in range(max_iterations):
        it += 1
        A = Hm + lam * np.diag(np.diag(Hm))
        try:
            step = -np.linalg.solve(A, g)
        except np.linalg.LinAlgError:
            break
        # Predicted decrease of sum r^2 under the linear model r + J step.
        predicted = -(2.0 * float(g @ step) + float(step @ Hm @ step))
        cand = pose + step
        c_cost, c_H, c_g, c_val = evaluate(cand, True)
        if c_cost < cost:
            rho = (cost - c_cost) / max(predicted, 1e-300)
            pose, cost, Hm, g, val = cand, c_cost, c_H, c_g, c_val
            lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu = 2.0
            if abs(step[0]) < step_tolerance and abs(step[1]) < step_tolerance \
                    and abs(step[2]) < step_tolerance:
                break
        else:
            lam *= nu
            nu *= 2.0
            if lam > 1e6:
                break
    return RefineResult(pose, float(np.mean(val)), it)


def voxel_filter(points: np.ndarray, size: float) -> np.ndarray:
    """First point [M, 2] of every occupied ``size`` voxel of ``points`` [N, 2] (keeps scan
    order)."""
    key = np.floor(points / size).astype(np.int64)
    _, first = np.unique(key[:, 0] * 1_000_003 + key[:, 1], return_index=True)
    return points[np.sort(first)]


def weak_direction(prob: np.ndarray, origin: np.ndarray, resolution: float,
                   points: np.ndarray, pose: np.ndarray, probe: float = 0.2,
                   directions: int = 32) -> tuple[float, np.ndarray]:
    """(drop, axis [2]): how little the mean interpolated value under the scan at ``pose``
    falls when the scan moves by +-``probe`` m along some direction, and that direction
    (world axes). Near 0 along a corridor without features, tenths where something in
    view fixes the position.

    Moves of twice the smoothed field's width over ``directions`` axes, not the curvature
    at the match: at the scale of a cell, walls at an angle to the grid are stair-steps
    whose ripple reads as curvature along a featureless corridor (one at 27 deg to the
    grid read as held, and none of its closures was rejected).
    """
    wpts = transform_points(se2_to_matrix(*pose), points)  # [N, 2]
    a = np.arange(directions) * np.pi / directions
    axes = np.stack([np.cos(a), np.sin(a)], -1)  # [D, 2] half circle: +- covers the rest
    offs = np.concatenate([np.zeros((1, 2)), probe * axes, -probe * axes])  # [2D + 1, 2]
    val, _ = interpolate(prob, origin, resolution, (wpts[None] + offs[:, None]).reshape(-1, 2))
    m = val.reshape(len(offs), -1).mean(axis=1)  # [2D + 1]
    drop = m[0] - 0.5 * (m[1 : directions + 1] + m[directions + 1 :])  # [D]
    k = int(np.argmin(drop))
    return float(drop[k]), axes[k]


def normal_spread(points: np.ndarray, voxel: float = 0.05, radius: float = 0.5,
                  window: int = 10, min_neighbours: int = 2) -> float:
    """Smallest eigenvalue of the mean ``n n^T`` over the scan's surface normals, in
    [0, 0.5]: 0 when every surface the scan sees runs one way (a corridor without
    features: nothing fixes the position along it), 0.5 when the normals point evenly in
    all directions.

    ``points`` [N, 2] in scan order (a scan's returns are) are thinned to one per
    ``voxel`` first, so that the beam density and range noise do not decide the normals
    (1440 beams with 2 cm noise read a flat corridor as 0.05 from raw neighbours); a
    point's normal is the least-variance axis of the points up to ``window`` before and
    after it in scan order that lie within ``radius``; points with fewer than
    ``min_neighbours`` such are left out. Neighbours in scan order, not from a k-d tree,
    and closed-form 2x2 axes: cheap enough for every scan.
    """
    pts = voxel_filter(np.asarray(points, dtype=np.float64), voxel)  # [M, 2]
    m = len(pts)
    if m < min_neighbours + 1:
        return 0.0
    idx = np.arange(m)[:, None] + np.arange(-window, window + 1)[None]  # [M, W]
    nb = pts[np.clip(idx, 0, m - 1)]  # [M, W, 2]
    near = (idx >= 0) & (idx < m) & (((nb - pts[:, None]) ** 2).sum(-1) <= radius**2)
    cnt = near.sum(1)  # [M] the point itself counts
    ok = cnt >= min_neighbours + 1
    if not ok.any():
        return 0.0
    w = near[ok].astype(np.float64)  # [K, W]
    x, y = nb[ok, :, 0], nb[ok, :, 1]  # [K, W]
    mx, my = (w * x).sum(1) / cnt[ok], (w * y).sum(1) / cnt[ok]  # [K]
    dx, dy = (x - mx[:, None]) * w, (y - my[:, None]) * w
    sxx, syy, sxy = (dx * dx).sum(1), (dy * dy).sum(1), (dx * dy).sum(1)
    major = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)  # [K] direction of most variance
    nx, ny = -np.sin(major), np.cos(major)  # the normal: across it
    a, b, c = (nx * nx).mean(), (nx * ny).mean(), (ny * ny).mean()
    return float(0.5 * (a + c) - np.sqrt(0.25 * (a - c) ** 2 + b * b))

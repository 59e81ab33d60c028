"""Lidar scans into camera images: polar -> laser frame -> camera -> pixels (u, v, z).

With poses, each scan is placed in the world at its own stamp and moved into the camera
at the image stamp, so a robot turning at 1 rad/s between a 10 Hz scan and an image does
not smear the lidar across the picture. Without poses the rig's static ``T_camera_laser``
is used with the scan nearest in time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from toolkit.camera import PinholeCamera, pixel_index
from toolkit.deskew import is_swept
from toolkit.geometry import inv_se3, transform_points
from toolkit.sensors import LaserScan, Sequence


@dataclass
class LidarPixels:
    """Lidar points that land in one image."""

    uv: np.ndarray  # [N, 2] float64 pixel coordinates (distorted image)
    z: np.ndarray  # [N] float64 camera z-depth in metres
    points_cam: np.ndarray  # [N, 3] camera-frame points
    beam: np.ndarray  # [N] int beam index in its scan
    scan: np.ndarray  # [N] int index of the scan in the sequence

    def __len__(self) -> int:
        return len(self.z)

    @property
    def pixel(self) -> np.ndarray:
        """[N, 2] int (col, row) of the pixel each point falls in: pixel k covers
        ``[k - 0.5, k + 0.5)`` (pixel centres on integers, the half-open span
        ``PinholeCamera.in_image`` keeps), so u = 0.5 is in pixel 1 (``pixel_index``)."""
        return pixel_index(self.uv)

    @classmethod
    def empty(cls) -> LidarPixels:
        return cls(np.zeros((0, 2)), np.zeros(0), np.zeros((0, 3)), np.zeros(0, np.int64),
                   np.zeros(0, np.int64))


def scan_points(scan: LaserScan) -> tuple[np.ndarray, np.ndarray]:
    """Valid end points [N, 3] in the laser frame and their beam indices [N]."""
    valid = scan.valid_mask()
    return scan.points_3d(), np.flatnonzero(valid)


def project_points(camera: PinholeCamera, points_cam: np.ndarray, min_z: float = 0.05) -> (
    tuple[np.ndarray, np.ndarray, np.ndarray]
):
    """(uv [M, 2], z [M], keep [N] bool) of camera-frame points [N, 3] that are in front of
    the camera and inside the image."""
    uv, z = camera.project(points_cam)
    keep = (z > min_z) & camera.in_image(uv)
    if camera.has_distortion:
        # Far outside the field of view the polynomial folds back into the image; a point
        # is only kept if undistorting its pixel gives back its own ray.
        xy = camera.undistort_points(uv[keep])
        ray = points_cam[keep, :2] / z[keep, None]
        ok = np.linalg.norm(xy - ray, axis=1) < 1e-3 * (1 + np.linalg.norm(ray, axis=1))
        idx = np.flatnonzero(keep)
        keep[idx[~ok]] = False
    return uv[keep], z[keep], keep


def project_scan(camera: PinholeCamera, scan: LaserScan, T_camera_laser: np.ndarray,
                 scan_index: int = 0, min_z: float = 0.05) -> LidarPixels:
    """Project one scan with a fixed ``T_camera_laser`` [4, 4] (scan and image at once)."""
    pts, beams = scan_points(scan)
    pc = transform_points(T_camera_laser, pts)
    uv, z, keep = project_points(camera, pc, min_z)
    return LidarPixels(uv, z, pc[keep], beams[keep], np.full(int(keep.sum()), scan_index))


class LidarProjector:
    """Projects a sequence's scans into its frames.

    ``frame_poses`` [F, 4, 4] and ``scan_poses`` [S, 4, 4] are ``T_world_base`` at the frame
    and scan stamps; when given, scan k is placed with the pose at its own stamp and brought
    into the camera with the pose at the image stamp (motion compensation between sensors).
    ``scans_per_frame`` > 1 adds the neighbouring scans, which gives more pairs for the
    scale estimate when the robot moves slowly. ``scan_usable`` [S] bool: the scans that
    may be chosen (with poses: those the trajectory covers; None: all).
    """

    def __init__(self, sequence: Sequence, frame_poses: np.ndarray | None = None,
                 scan_poses: np.ndarray | None = None, scans_per_frame: int = 1,
                 max_dt: float = 0.2, min_z: float = 0.05,
                 scan_usable: np.ndarray | None = None) -> None:
        if (frame_poses is None) != (scan_poses is None):
            raise ValueError("give both frame_poses and scan_poses, or neither")
        if frame_poses is not None and (len(frame_poses) != len(sequence.frames)
                                        or len(scan_poses) != len(sequence.scans)):
            raise ValueError(f"{len(frame_poses)} frame poses / {len(scan_poses)} scan poses for "
                             f"{len(sequence.frames)} frames / {len(sequence.scans)} scans")
        swept = sum(is_swept(s) for s in sequence.scans)
        if swept:
            # Each beam was measured at its own time; projected as one instant, the scans
            # of a moving robot land centimetres off (5 cm median on a 5 Hz simulated run).
            raise ValueError(
                f"{swept} of {len(sequence.scans)} scans carry per-beam timing "
                "(time_increment): de-skew them first, "
                "sequence = toolkit.deskew.deskew_sequence(sequence, T_world_base) with the "
                "trajectory the poses come from (the fuse stage does this)")
        if scan_usable is not None and len(scan_usable) != len(sequence.scans):
            raise ValueError(f"scan_usable has {len(scan_usable)} entries for "
                             f"{len(sequence.scans)} scans")
        self.seq = sequence
        self.frame_poses = frame_poses
        self.scan_poses = scan_poses
        # [S] bool or None: scans that may be used (those with a trustworthy pose)
        self.scan_usable = None if scan_usable is None else np.asarray(scan_usable, bool)
        # [U] the usable scans' indices (sorted by stamp) and [U] their stamps: the nearest
        # are searched among these alone. Searched among all stamps and filtered after, a
        # window of n places held too few usable scans next to unusable ones, or none: an
        # image with an unusable scan on each side got no lidar while a usable one lay
        # within max_dt.
        self._usable_index = (np.arange(len(sequence.scans)) if scan_usable is None
                              else np.flatnonzero(self.scan_usable))
        self._usable_stamps = sequence.scan_stamps[self._usable_index]
        self.scans_per_frame = max(1, int(scans_per_frame))
        self.max_dt = max_dt
        self.min_z = min_z
        self.camera = sequence.rig.camera
        self.T_camera_laser = sequence.rig.T_camera_laser
        self._cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def scan_indices(self, t: float) -> list[int]:
        """Indices of the scans used for an image at stamp ``t`` (nearest first)."""
        stamps = self._usable_stamps  # sorted
        if len(stamps) == 0:
            return []
        # The n nearest of sorted stamps lie within n places of t: no sort of every stamp
        # per frame (an hour of 10 Hz scans and frames made that quadratic).
        n = self.scans_per_frame
        at = int(np.searchsorted(stamps, t))
        lo, hi = max(0, at - n), min(len(stamps), at + n)
        # ... and any scan stamped the same as the window's ends (ties go to the earlier).
        lo = int(np.searchsorted(stamps, stamps[lo], "left"))
        hi = int(np.searchsorted(stamps, stamps[hi - 1], "right")) if hi > lo else hi
        cand = np.arange(lo, hi)
        order = cand[np.argsort(np.abs(stamps[cand] - t), kind="stable")[:n]]
        return [int(self._usable_index[k]) for k in order if abs(stamps[k] - t) <= self.max_dt]

    def laser_points(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Scan ``k``'s valid end points [N, 3] in the laser frame and their beams [N]."""
        if k not in self._cache:
            if len(self._cache) > 64:
                self._cache.clear()
            self._cache[k] = scan_points(self.seq.scans[k])
        return self._cache[k]

    def project_frame(self, index: int) -> LidarPixels:
        """Lidar pixels of camera frame ``index`` (empty when no scan is close in time)."""
        t = float(self.seq.frame_stamps[index])
        ks = self.scan_indices(t)
        if not ks:
            return LidarPixels.empty()
        rig = self.seq.rig
        T_camera_world = None
        if self.frame_poses is not None:
            T_camera_world = inv_se3(self.frame_poses[index] @ rig.T_base_camera)
        parts = []
        for k in ks:
            pts, beams = self.laser_points(k)
            if len(pts) == 0:
                continue
            if T_camera_world is None:
                T = self.T_camera_laser
            else:
                # camera(t_img) <- world <- base(t_scan) <- laser
                T = T_camera_world @ self.scan_poses[k] @ rig.T_base_laser
            pc = transform_points(T, pts)
            uv, z, keep = project_points(self.camera, pc, self.min_z)
            parts.append(LidarPixels(uv, z, pc[keep], beams[keep], np.full(len(z), k)))
        if not parts:
            return LidarPixels.empty()
        return LidarPixels(*(np.concatenate([getattr(p, f) for p in parts]) for f in
                             ("uv", "z", "points_cam", "beam", "scan")))


def sample_depth(values: np.ndarray, lidar: LidarPixels) -> np.ndarray:
    """[N] predicted values at the lidar pixels (nearest pixel: bilinear would blend the two
    sides of a depth edge into a value that exists nowhere)."""
    if len(lidar) == 0:
        return np.zeros(0, np.float64)
    px = lidar.pixel
    h, w = values.shape
    # Projected pixels lie in the image; one outside the values means they are not at the
    # image's size (a network output not resized back, [W, H]): clipped, they sampled the
    # wrong pixels and gave a scale 3.6x off, flagged ok.
    if px.min() < 0 or px[:, 0].max() > w - 1 or px[:, 1].max() > h - 1:
        raise ValueError(
            f"lidar pixels reach column {px[:, 0].max()}, row {px[:, 1].max()} but the "
            f"values are {w}x{h} ([H, W] = {values.shape}): give them at the camera image's "
            "size (resize a network's output to the image, as the depth backends do)")
    return values[px[:, 1], px[:, 0]].astype(np.float64)


def occluded_lidar(lidar: LidarPixels, fx: float, cx: float, angle_increment: float,
                   window_beams: float = 1.5, margin_m: float = 0.05,
                   margin_rel: float = 0.05,
                   occluders: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """[N] bool: lidar points the camera probably does not see, because a nearer lidar point
    lies within ``window_beams`` beam spacings of them in the image.

    The camera sits above (and here in front of) the lidar, so the object whose edge the
    lidar grazes - a chair, a person's legs, a table - covers a few more pixels in the image
    than in the scan: the far-side point next to a range jump is paired with the occluder.
    On the simulated house these pairs are 10 % of all pairs and, with ground-truth depth as
    the prediction, make a 0.206 m RMSE against the lidar (0.095 m without them). Where
    the silhouette ends between two beams is unknown, so the whole gap to the neighbouring
    beam (and a half more) counts. The beam spacing in pixels, fx * dtheta * (1 + x^2) with
    x = (u - cx) / fx, grows towards the image sides.

    ``occluders`` (u [M], z [M]): more points in the same image that may hide the lidar
    points but are not tested themselves - the neighbouring scans' points on a thin leg
    that the pair's own scan passed beside (``Fusion.frame_pairs``).
    """
    n = len(lidar)
    out = np.zeros(n, bool)
    if n == 0 or window_beams <= 0:
        return out
    u, z = lidar.uv[:, 0], lidar.z
    uo, zo = u, z
    if occluders is not None and len(occluders[0]):
        uo = np.concatenate([u, np.asarray(occluders[0], np.float64)])
        zo = np.concatenate([z, np.asarray(occluders[1], np.float64)])
    if len(uo) < 2:
        return out
    # Columns only: the occluder stands on the floor, and being nearer it projects lower in
    # the image than the far point (by tens of pixels at a 0.2 m camera-lidar height gap)
    # while its body rises through the far point's row.
    win = occlusion_window(u, fx, cx, angle_increment, window_beams)  # [N] pixels
    # The nearest occluder in each window (a point is never nearer than itself).
    nearest = window_extreme(uo, zo, u - win, u + win, np.minimum)  # [N]
    return nearest < z - (margin_m + margin_rel * z)


def occlusion_window(u: np.ndarray, fx: float, cx: float, angle_increment: float,
                     window_beams: float) -> np.ndarray:
    """[N] half-width in pixels of ``occluded_lidar``'s window at columns ``u`` [N]:
    ``window_beams`` beam spacings, fx * dtheta * (1 + x^2) with x = (u - cx) / fx."""
    x = (u - cx) / fx
    return window_beams * fx * abs(angle_increment) * (1.0 + x * x)


def window_extreme(keys: np.ndarray, values: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                   op: np.ufunc = np.minimum) -> np.ndarray:
    """[Q] the smallest (``op`` np.minimum; np.maximum: largest) of ``values`` [M] whose
    ``keys`` [M] lie in [lo, hi] [Q], all windows at once (+inf / -inf where none does)."""
    empty = np.inf if op is np.minimum else -np.inf
    if len(keys) == 0:
        return np.full(len(lo), empty)
    order = np.argsort(keys, kind="stable")
    ks = keys[order]
    vs = np.append(values[order], empty)  # [M + 1]: reduceat may start at the end
    a = np.searchsorted(ks, lo, side="left")  # [Q] the window is ks[a:b]
    b = np.searchsorted(ks, hi, side="right")
    out = op.reduceat(vs, np.stack([a, b], 1).ravel())[::2]
    return np.where(b > a, out, empty)


def jump_near_side(scan: LaserScan, beams: np.ndarray, margin_m: float = 0.05,
                   margin_rel: float = 0.05) -> np.ndarray:
    """[N] bool: beams [N] of ``scan`` on the near side of a range jump - a neighbouring beam
    (+-1) reads farther by ``margin_m + margin_rel * r``.

    ``occluded_lidar`` drops the far side of a jump; this is its complement. The camera
    and the lidar see an edge from a few centimetres apart, and the image's pose between
    two scans is only as good as the odometry (or the straight line) that places it: a
    point at the edge of an object is often paired with the background beside it. A
    neighbour without a return (+inf, or at ``range_max``, what many drivers write for
    none) is farther; one that is NaN, zero or below ``range_min`` (a dropout, too close)
    tells nothing. A full-circle scan's last beam neighbours its first."""
    b = np.asarray(beams, np.int64)
    out = np.zeros(len(b), bool)
    n = len(scan.ranges)
    if len(b) == 0 or n < 2:
        return out
    r = scan.ranges.astype(np.float64)  # [B]
    r0 = r[b]
    tol = margin_m + margin_rel * r0
    full = abs(scan.angle_increment) * n >= 2 * np.pi - 1e-6
    with np.errstate(invalid="ignore"):
        none = (r == np.inf) | (r >= scan.range_max)  # [B] no return: farther than anything
        known = np.isfinite(r) & (r > 0) & (r >= scan.range_min)
    for step in (-1, 1):
        j = b + step  # [N]
        inside = np.ones(len(b), bool) if full else (j >= 0) & (j < n)
        j = j % n  # a full circle wraps; elsewhere the wrapped beam is not `inside`
        with np.errstate(invalid="ignore"):
            farther = none[j] | (known[j] & (r[j] - r0 > tol))
        out |= inside & farther
    return out


def rays_pass_near(origin_xy: np.ndarray, ends_xy: np.ndarray, points_xy: np.ndarray,
                   radius: float) -> np.ndarray:
    """[N] bool: segments from ``origin_xy`` [2] to ``ends_xy`` [N, 2] that pass within
    ``radius`` of any of ``points_xy`` [K, 2] (in the floor plane)."""
    out = np.zeros(len(ends_xy), bool)
    if len(ends_xy) == 0 or len(points_xy) == 0 or radius <= 0:
        return out
    o = np.asarray(origin_xy, np.float64)
    d = ends_xy - o  # [N, 2]
    L2 = np.maximum(np.einsum("nd,nd->n", d, d), 1e-12)  # [N]
    q = points_xy - o  # [K, 2]
    t = np.clip((d @ q.T) / L2[:, None], 0.0, 1.0)  # [N, K] nearest place along each ray
    gap = q[None] - t[..., None] * d[:, None]  # [N, K, 2]
    return (np.einsum("nkd,nkd->nk", gap, gap) < radius * radius).any(1)


def edge_pairs(values: np.ndarray, lidar: LidarPixels, threshold: float,
               window: int = 5, disparity: bool = False, scale: float = 1.0,
               shift: float = 0.0) -> np.ndarray:
    """[N] bool: lidar pixels whose ``window`` x ``window`` neighbourhood in the prediction
    spans more than ``threshold`` x the value there (a blurred depth edge: the pixel's
    prediction is a ramp between two surfaces, whichever the lidar hit). Only the few lidar
    pixels are looked at, not the whole image. The test is on depth: a disparity, or a
    prediction with a ``shift``, is first turned into depth by (``scale``, ``shift``) (on
    raw disparity a smooth wall at 4-5 m spanned 6 of its 28 pairs out)."""
    n = len(lidar)
    if n == 0 or threshold <= 0:
        return np.zeros(n, bool)
    h, w = values.shape
    px = lidar.pixel
    r = window // 2
    dd = np.arange(-r, r + 1)
    rows = np.clip(px[:, 1, None, None] + dd[None, :, None], 0, h - 1)  # [N, k, 1]
    cols = np.clip(px[:, 0, None, None] + dd[None, None, :], 0, w - 1)  # [N, 1, k]
    win = values[rows, cols].reshape(n, -1).astype(np.float64)  # [N, k*k]
    centre = values[np.clip(px[:, 1], 0, h - 1), np.clip(px[:, 0], 0, w - 1)].astype(
        np.float64)
    if disparity or shift:
        with np.errstate(divide="ignore", invalid="ignore"):
            if disparity:
                win, centre = 1.0 / (scale * win + shift), 1.0 / (scale * centre + shift)
            else:
                win, centre = scale * win + shift, scale * centre + shift
        win[~(win > 0)] = np.nan
        centre[~(centre > 0)] = np.nan
    # An invalid neighbour is no evidence of an edge; an invalid centre is no pair.
    win = np.where(np.isfinite(win), win, centre[:, None])
    with np.errstate(invalid="ignore"):
        span = win.max(1) - win.min(1)
        return ~(span <= threshold * np.abs(centre))


def zbuffer_lidar(lidar: LidarPixels, shape: tuple[int, int]) -> LidarPixels:
    """Keep the nearest lidar point per pixel (the camera sees the nearer one when the
    lidar's slightly different viewpoint puts two points on one pixel)."""
    if len(lidar) == 0:
        return lidar
    px = lidar.pixel
    lin = np.clip(px[:, 1], 0, shape[0] - 1) * shape[1] + np.clip(px[:, 0], 0, shape[1] - 1)
    order = np.lexsort((lidar.z, lin))
    first = np.ones(len(order), bool)
    first[1:] = lin[order][1:] != lin[order][:-1]
    sel = np.sort(order[first])
    return LidarPixels(lidar.uv[sel], lidar.z[sel], lidar.points_cam[sel], lidar.beam[sel],
                       lidar.scan[sel])

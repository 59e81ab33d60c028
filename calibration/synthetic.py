"""Synthetic calibration captures with exact ground truth, for tests and benchmarks.

Analytic, not rendered through the house simulator: random board poses in front of the
camera that the laser plane cuts, exact corners projected through the camera (with
distortion) plus Gaussian pixel noise, and laser beams intersected with the board and the
walls of a surrounding room plus Gaussian range noise. ``write_capture`` also renders the
board images and writes the same folder layout as the simulator's calibration capture
(``images/<ns>.png``, ``lasers/<ns>.pcd``, ``camera.yaml``, ``groundtruth.yaml``), so the
whole command line path can be tested without the simulator.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from calibration.board import BoardSpec
from calibration.frames import R_CAMERA_LASER_NOMINAL
from toolkit.camera import PinholeCamera
from toolkit.geometry import inv_se3, se3
from toolkit.io.atomic import atomic_path, atomic_write_text

# Stamps are Unix times (2023-11), as real recordings name their files: file names of 19
# digits are read as nanoseconds.
EPOCH_S = 1_700_000_000.0


def default_camera() -> PinholeCamera:
    """A 640x480 camera with mild distortion, like a typical robot camera."""
    return PinholeCamera(640, 480, 520.0, 520.0, 319.5, 239.5,
                         np.array([-0.05, 0.02, 0.0, 0.0, 0.0]))


def default_extrinsic() -> np.ndarray:
    """[4, 4] T_camera_laser: laser 12 cm below, 6 cm behind, 3 cm left, tilted by degrees."""
    tilt = Rotation.from_euler("xyz", [1.5, -2.0, 1.0], degrees=True).as_matrix()
    return se3(tilt @ R_CAMERA_LASER_NOMINAL, [-0.03, 0.12, -0.06])


@dataclass
class SyntheticView:
    name: str
    stamp: float  # Unix seconds (image); the scan is stamped ``stamp + scan_dt``
    T_camera_board: np.ndarray  # [4, 4]
    corners: np.ndarray  # [N, 2] noisy distorted pixels
    scan_points: np.ndarray  # [M, 2] laser frame, board and room
    on_board: np.ndarray  # [M] bool, the beam hit the board


@dataclass
class SyntheticCapture:
    camera: PinholeCamera
    board: BoardSpec
    board_size: tuple[float, float]  # physical board (pattern + white margin), metres
    T_camera_laser: np.ndarray  # [4, 4] ground truth
    views: list[SyntheticView]
    scan_dt: float


def board_outline(board: BoardSpec, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Board-frame rectangle: lower [2] and upper [2] corner of the physical board."""
    s = board.square
    lo = np.array([-s - margin, -s - margin])
    hi = np.array([board.cols * s + margin, board.rows * s + margin])
    return lo, hi


def _scan(T_laser_board: np.ndarray, lo: np.ndarray, hi: np.ndarray, rng: np.random.Generator,
          noise: float, room: tuple[float, float, float, float], resolution_deg: float) -> (
    tuple[np.ndarray, np.ndarray]
):
    """Beam end points [M, 2] and on-board mask [M] of one 270 degree scan."""
    ang = np.radians(np.arange(-135.0, 135.0 + 1e-9, resolution_deg))  # [B]
    d = np.stack([np.cos(ang), np.sin(ang)], -1)  # [B, 2]
    # Room walls: axis-aligned box [xmin, xmax, ymin, ymax] around the laser.
    xmin, xmax, ymin, ymax = room
    with np.errstate(divide="ignore", invalid="ignore"):
        tx = np.where(d[:, 0] > 0, xmax / d[:, 0], xmin / d[:, 0])
        ty = np.where(d[:, 1] > 0, ymax / d[:, 1], ymin / d[:, 1])
    r = np.fmin(np.where(tx > 0, tx, np.inf), np.where(ty > 0, ty, np.inf))  # [B]
    n = T_laser_board[:3, 2]
    c = T_laser_board[:3, 3]
    denom = d @ n[:2]
    with np.errstate(divide="ignore", invalid="ignore"):
        rb = (n @ c) / denom
    hit3 = np.c_[d * rb[:, None], np.zeros(len(d))]
    local = (hit3 - c) @ T_laser_board[:3, :3]  # board frame
    inside = ((local[:, 0] >= lo[0]) & (local[:, 0] <= hi[0]) & (local[:, 1] >= lo[1])
              & (local[:, 1] <= hi[1]) & (rb > 0) & (rb < r))
    r = np.where(inside, rb, r)
    r = r + rng.normal(0.0, noise, len(r))
    return d * r[:, None], inside


def make_capture(n_views: int = 10, seed: int = 0, board: BoardSpec | None = None,
                 camera: PinholeCamera | None = None, T_camera_laser: np.ndarray | None = None,
                 lidar_noise: float = 0.01, image_noise: float = 0.3,
                 margin: float = 0.08, distance: tuple[float, float] = (0.7, 1.8),
                 min_tilt_deg: float = 20.0, max_tilt_deg: float = 45.0,
                 resolution_deg: float = 0.25,
                 scan_dt: float = 0.012) -> SyntheticCapture:
    """``n_views`` random board views seen by both sensors (deterministic in ``seed``).

    Boards are turned by ``min_tilt_deg`` to ``max_tilt_deg`` about both in-plane axes,
    with alternating signs, so that the views constrain all six degrees of freedom, as a
    careful calibration session would.
    """
    board = board or BoardSpec(11, 8, 0.05)
    camera = camera or default_camera()
    T_cl = default_extrinsic() if T_camera_laser is None else np.asarray(T_camera_laser)
    T_lc = inv_se3(T_cl)
    rng = np.random.default_rng(seed)
    lo, hi = board_outline(board, margin)
    obj = board.object_points()
    room = (-4.0, 6.0, -3.5, 3.0)
    views: list[SyntheticView] = []
    strata = rng.permutation(n_views)
    tries = 0
    while len(views) < n_views:
        tries += 1
        if tries > 200 * n_views:
            raise RuntimeError("could not place boards visible to both sensors; widen the "
                               "camera field of view or the distance range")
        # A point on the laser plane in front of the laser, inside the camera's view...
        # Distances stratified over the range (near and far boards in every set): a
        # laser tilt and a laser height offset are told apart only by their different
        # effect at different distances.
        k = len(views)
        slot = (strata[k % n_views] + rng.uniform()) / n_views
        rng_m = distance[0] + (distance[1] - distance[0]) * slot
        bearing = rng.uniform(-0.45, 0.45)
        hit_c = T_cl @ np.array([rng_m * np.cos(bearing), rng_m * np.sin(bearing), 0.0, 1.0])
        # ...a board facing the camera, turned about its own axes...
        view_dir = hit_c[:3] / np.linalg.norm(hit_c[:3])
        z = view_dir
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        R_face = np.c_[x, np.cross(z, x), z]
        # The protocol a calibration session follows: alternate the board's pitch and
        # yaw signs (forward/back, left/right) with random magnitudes, so that every view
        # set constrains all six degrees of freedom; purely random tilts sometimes leave
        # all boards nearly upright and the laser height unobservable.
        sx, sy = (1.0 if k % 2 == 0 else -1.0), (1.0 if (k // 2) % 2 == 0 else -1.0)
        lo_t = min_tilt_deg
        tilt = Rotation.from_euler("xyz", [sx * rng.uniform(lo_t, max_tilt_deg),
                                           sy * rng.uniform(lo_t, max_tilt_deg),
                                           rng.uniform(-15, 15)], degrees=True).as_matrix()
        R = R_face @ tilt
        # ...placed so that the laser plane cuts it somewhere inside the pattern.
        u = np.array([rng.uniform(0.15, 0.85) * (hi[0] - lo[0]) + lo[0],
                      rng.uniform(0.15, 0.85) * (hi[1] - lo[1]) + lo[1], 0.0])
        T_cb = se3(R, hit_c[:3] - R @ u)
        uv, depth = camera.project(obj @ T_cb[:3, :3].T + T_cb[:3, 3])
        if not (np.all(depth > 0.3) and np.all(camera.in_image(uv, margin=10))):
            continue
        pts, on = _scan(T_lc @ T_cb, lo, hi, rng, lidar_noise, room, resolution_deg)
        if on.sum() < 15:
            continue
        corners = uv + rng.normal(0.0, image_noise, uv.shape)
        stamp = EPOCH_S + 2.0 * len(views)
        views.append(SyntheticView(f"view{len(views):02d}", stamp, T_cb, corners, pts, on))
    return SyntheticCapture(camera, board, (hi[0] - lo[0], hi[1] - lo[1]), T_cl, views, scan_dt)


# ---------------------------------------------------------------------------- files


def _rays(camera: PinholeCamera, s: int) -> np.ndarray:
    """[H*s * W*s, 3] rays (z = 1) through the sub-pixel centres of a supersampled image.

    Undistorting millions of sub-pixels one by one takes seconds; the distortion is
    smooth, so a grid every 4 pixels, interpolated, is exact to far below 0.01 px.
    """
    step = 4
    gu = np.arange(-1.0, camera.width + step + 1, step)
    gv = np.arange(-1.0, camera.height + step + 1, step)
    U, V = np.meshgrid(gu, gv)
    xy = camera.undistort_points(np.stack([U.ravel(), V.ravel()], -1)).reshape(len(gv),
                                                                                len(gu), 2)
    u = (np.arange(camera.width * s) + 0.5) / s - 0.5
    v = (np.arange(camera.height * s) + 0.5) / s - 0.5
    # Fractional grid coordinates of every sub-pixel, for bilinear interpolation.
    fu, fv = (u - gu[0]) / step, (v - gv[0]) / step
    mu = np.repeat(fu[None], len(v), 0).astype(np.float32)
    mv = np.repeat(fv[:, None], len(u), 1).astype(np.float32)
    out = [cv2.remap(xy[..., k].astype(np.float32), mu, mv, cv2.INTER_LINEAR).astype(np.float64)
           for k in range(2)]
    return np.c_[out[0].ravel(), out[1].ravel(), np.ones(out[0].size)]


def render_board(camera: PinholeCamera, T_camera_board: np.ndarray, board: BoardSpec,
                 margin: float, supersample: int = 2, rays: np.ndarray | None = None) -> (
    np.ndarray
):
    """[H, W, 3] uint8 RGB image of the board in front of a grey background.

    Every pixel's ray is intersected with the board plane (through the distortion model),
    supersampled so that edges are anti-aliased like a real camera's. ``rays`` are
    ``_rays(camera, supersample)``, passed in when rendering many views.
    """
    rays = _rays(camera, supersample) if rays is None else rays  # [P, 3]
    R, t = T_camera_board[:3, :3], T_camera_board[:3, 3]
    n = R[:, 2]
    lam = (n @ t) / (rays @ n)
    local = (rays * lam[:, None] - t) @ R  # board frame
    lo, hi = board_outline(board, margin)
    on_board = ((lam > 0) & (local[:, 0] >= lo[0]) & (local[:, 0] <= hi[0])
                & (local[:, 1] >= lo[1]) & (local[:, 1] <= hi[1]))
    sq = np.floor(local[:, :2] / board.square + 1).astype(np.int64)  # square index, from -inf
    in_pattern = ((sq[:, 0] >= 0) & (sq[:, 0] <= board.cols) & (sq[:, 1] >= 0)
                  & (sq[:, 1] <= board.rows))
    black = in_pattern & ((sq[:, 0] + sq[:, 1]) % 2 == 0)
    val = np.where(on_board, np.where(black, 20.0, 235.0), 110.0)
    s = supersample
    img = val.reshape(camera.height, s, camera.width, s).mean(axis=(1, 3))
    return np.repeat(np.clip(img, 0, 255).astype(np.uint8)[..., None], 3, axis=2)


def write_pcd(path: Path, points: np.ndarray) -> None:
    """ASCII PCD v0.7 with x y z fields, as the ACFR recording and the simulator write."""
    pts = np.asarray(points, dtype=np.float64)
    header = ("# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\n"
              "SIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
              f"WIDTH {len(pts)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(pts)}\n"
              "DATA ascii\n")
    body = "".join(f"{x:.6f} {y:.6f} 0\n" for x, y in pts[:, :2])
    atomic_write_text(path, header + body)


def write_capture(capture: SyntheticCapture, out_dir: Path, margin: float = 0.08) -> Path:
    """Write images, PCD scans, camera.yaml and groundtruth.yaml into ``out_dir``."""
    out = Path(out_dir)
    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "lasers").mkdir(parents=True, exist_ok=True)
    rays = _rays(capture.camera, 2)
    for v in capture.views:
        img = render_board(capture.camera, v.T_camera_board, capture.board, margin, 2, rays)
        with atomic_path(out / "images" / f"{round(v.stamp * 1e9)}.png") as tmp:
            cv2.imwrite(str(tmp), img)
        write_pcd(out / "lasers" / f"{round((v.stamp + capture.scan_dt) * 1e9)}.pcd",
                  v.scan_points)
    atomic_write_text(out / "camera.yaml", yaml.safe_dump(capture.camera.to_dict(),
                                                          sort_keys=False))
    gt = {"T_camera_laser": [[float(x) for x in row] for row in capture.T_camera_laser],
          "convention": "p_camera_optical = T_camera_laser @ p_laser",
          "board": {"inner_corners": [capture.board.cols, capture.board.rows],
                    "square_m": capture.board.square}}
    atomic_write_text(out / "groundtruth.yaml", yaml.safe_dump(gt, sort_keys=False))
    return out

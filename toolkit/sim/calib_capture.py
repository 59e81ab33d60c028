"""Calibration capture: a checkerboard held in front of the camera and the lidar.

Writes the layout of a real capture (like ``shared/data/calib/acfr-cam2dlidar``) plus the
exact answer::

    <out>/images/<stamp_ns>.png     RGB images of the board
    <out>/lasers/<stamp_ns>.pcd     one scan each, ASCII PCD (x y z, laser frame, z = 0)
    <out>/camera.yaml               PinholeCamera.to_dict() of the camera that took them
    <out>/groundtruth.yaml          T_camera_laser, board geometry, per-view board poses

Image and scan stamps differ by 8-56 ms per view (as in the real data), so a consumer
pairs them by nearest stamp; ``groundtruth.yaml`` lists the pairs too. The board is
rendered analytically (exact square edges, 2x2 supersampled so corners are anti-aliased)
over a textured room, and the lidar ranges to it are exact before noise. The board poses
follow ``CaptureProtocol``: what a person holding the board is told to do.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from toolkit.camera import PinholeCamera
from toolkit.geometry import inv_se3, se3
from toolkit.io.atomic import atomic_path, atomic_write_text
from toolkit.sim.scene import Box, Scene, Surface
from toolkit.sim.sensors import CameraRenderer, CameraSpec, LidarRenderer, LidarSpec
from toolkit.sim.textures import build_texture_bank

BLACK, WHITE = 25.0, 235.0  # board print and paper, grey levels before shading
T0_NS = 1_700_000_000_000_000_000


def _room() -> list[Box]:
    """A 10 x 8 x 2.6 m textured room; the rig stands at the origin facing +x."""
    x0, x1, y0, y1, h = -3.0, 7.0, -4.0, 4.0, 2.6
    boxes = [
        Box([(x0 + x1) / 2, (y0 + y1) / 2, -0.05], [x1 - x0, y1 - y0, 0.1],
            surface=Surface("wood", (0.8, 0.6, 0.4)), label="floor"),
        Box([(x0 + x1) / 2, (y0 + y1) / 2, h + 0.05], [x1 - x0, y1 - y0, 0.1],
            surface=Surface("ceiling", (0.97, 0.97, 0.97)), label="ceiling"),
        Box([x1 + 0.05, 0, h / 2], [0.1, y1 - y0, h],
            surface=Surface("brick", (1.0, 0.65, 0.5)), label="wall"),
        Box([x0 - 0.05, 0, h / 2], [0.1, y1 - y0, h],
            surface=Surface("plaster", (0.9, 0.95, 1.0)), label="wall"),
        Box([(x0 + x1) / 2, y1 + 0.05, h / 2], [x1 - x0, 0.1, h],
            surface=Surface("stucco", (1.0, 0.95, 0.8)), label="wall"),
        Box([(x0 + x1) / 2, y0 - 0.05, h / 2], [x1 - x0, 0.1, h],
            surface=Surface("plaster", (0.85, 0.95, 0.85)), label="wall"),
        Box([6.6, -2.0, 0.9], [0.6, 1.2, 1.8],
            surface=Surface("wood", (0.7, 0.5, 0.3), "local"), label="shelf"),
    ]
    return boxes


def _board_geometry(board: tuple[int, int], square: float) -> dict[str, float]:
    cols, rows = board
    margin = square  # white paper around the pattern, one square wide
    return {"x0": -square - margin, "x1": cols * square + margin,
            "y0": -square - margin, "y1": rows * square + margin, "margin": margin}


# Low-discrepancy steps (additive recurrences, Weyl sequences) for the distance and the
# lateral position: every prefix of the views covers both ranges evenly, so the first 5
# views of a capture are as well spread as the first 20. The steps must not be near 1/4 or
# 3/4: the lean and turn signs repeat every 4 views, and with such a step (Roberts' R2
# sequence has 0.755) every forward-leaning board came out near and every backward-leaning
# one far, which confounds the laser's pitch with its height (measured: 10-16 mm height
# errors at 10 views). The golden-ratio step puts views four apart (same lean and turn)
# 0.47 of the range apart; the silver-ratio step spreads the lateral position.
SPREAD_STEP = (0.6180339887498949, 0.4142135623730950)  # distance, lateral


@dataclass(frozen=True)
class CaptureProtocol:
    """How the person holding the board moves it from one view to the next.

    The instructions a calibration session gives (docs/calibration.md, "Capturing a good
    calibration"): lean the board forward and back by ``lean_deg``, turn it left and right
    by ``turn_deg``, cycling through the four combinations (forward-left, back-left,
    forward-right, back-right) so that any four consecutive views hold all of them; step
    between near and far (``distance_m`` from the camera) and from one side of the image
    to the other so that the boards fill the view; rotate it a little in its plane. A
    laser pitch and a laser height are told apart only by boards leaning both ways at
    several distances; boards that barely lean leave the height unobservable.
    """

    distance_m: tuple[float, float] = (0.8, 2.0)
    lean_deg: tuple[float, float] = (20.0, 45.0)  # about the board's horizontal axis
    turn_deg: tuple[float, float] = (15.0, 40.0)  # about the vertical
    in_plane_deg: float = 15.0
    lateral_fill: float = 0.9  # fraction of the sideways room the image leaves
    max_incidence_deg: float = 60.0  # between the board normal and the line of sight


def _board_pose(rng: np.random.Generator, geo: dict[str, float], T_world_cam: np.ndarray,
                laser_z: float, k: int, phase: np.ndarray, proto: CaptureProtocol,
                camera: PinholeCamera, shrink: float) -> np.ndarray:
    """``T_world_board`` of view ``k`` under the protocol (not yet checked for visibility).

    ``phase`` [2] offsets the distance and lateral sequences per capture; ``shrink`` (1 on
    the first try, smaller after failed tries) pulls the board towards the image centre, as
    a person does when told the board is cut off.
    """
    w, h = geo["x1"] - geo["x0"], geo["y1"] - geo["y0"]
    lean_sign = 1.0 if k % 2 == 0 else -1.0
    turn_sign = 1.0 if (k // 2) % 2 == 0 else -1.0
    lean = lean_sign * np.radians(rng.uniform(*proto.lean_deg))
    turn = turn_sign * np.radians(rng.uniform(*proto.turn_deg))
    roll = np.radians(rng.uniform(-proto.in_plane_deg, proto.in_plane_deg))
    # Distance and lateral position from the sequences, jittered within a small stratum.
    su, sv = (phase + (k + 1) * np.asarray(SPREAD_STEP) + rng.uniform(-0.05, 0.05, 2)) % 1.0
    d0, d1 = proto.distance_m
    dist = d0 + (d1 - d0) * su
    # Sideways room at that distance: the image's half-width minus the turned board's.
    half_fov = min(camera.cx, camera.width - camera.cx) / camera.fx
    room = max(dist * half_fov - 0.5 * w * np.cos(turn) - 0.05, 0.0)
    lateral = (2.0 * sv - 1.0) * proto.lateral_fill * room * shrink
    # Facing frame: board z (into the board) along +x of the world, x to the right (-y),
    # y down (-z), so an unrotated board is upright and faces the rig. Lean about the
    # board's horizontal axis first, then turn about the vertical.
    R_face = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    R = Rotation.from_euler("ZYX", [turn, lean, 0.0]).as_matrix() @ R_face @ \
        Rotation.from_euler("z", roll).as_matrix()
    # The laser plane crosses the board somewhere in the middle 60 % of its height (and
    # anywhere along its width), at the chosen distance and lateral position.
    u = np.array([geo["x0"] + w * rng.uniform(0.3, 0.7), geo["y0"] + h * rng.uniform(0.2, 0.8),
                  0.0])
    hit = np.array([T_world_cam[0, 3] + dist, T_world_cam[1, 3] + lateral, laser_z])
    return se3(R, hit - R @ u)


def _inside(pb: np.ndarray, geo: dict[str, float]) -> np.ndarray:
    return (pb[..., 0] >= geo["x0"]) & (pb[..., 0] <= geo["x1"]) & (pb[..., 1] >= geo["y0"]) \
        & (pb[..., 1] <= geo["y1"])


def _checker(pb: np.ndarray, square: float, board: tuple[int, int]) -> np.ndarray:
    """Grey level of board points [N, 2] (board frame): checker inside, paper outside."""
    cols, rows = board
    i = np.floor(pb[:, 0] / square).astype(np.int64) + 1  # 0 .. cols
    j = np.floor(pb[:, 1] / square).astype(np.int64) + 1  # 0 .. rows
    in_pattern = (i >= 0) & (i <= cols) & (j >= 0) & (j <= rows)
    black = in_pattern & ((i + j) % 2 == 0)
    return np.where(black, BLACK, WHITE)


def _write_pcd(path: Path, pts: np.ndarray) -> None:
    head = ("# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\n"
            "SIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
            f"WIDTH {len(pts)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(pts)}\n"
            "DATA ascii\n")
    body = "".join(f"{x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in pts)
    atomic_write_text(path, head + body)


def capture_calibration(out_dir: Path | str, n_views: int, seed: int = 0,
                        board: tuple[int, int] = (11, 8), square: float = 0.05,
                        lidar_noise: float = 0.01, image_noise: float = 2.0,
                        camera: PinholeCamera | None = None,
                        T_camera_laser: np.ndarray | None = None,
                        lidar: LidarSpec | None = None, min_board_points: int = 8,
                        protocol: CaptureProtocol | None = None) -> Path:
    """Render ``n_views`` board views and their scans into ``out_dir``; returns it.

    ``board``: inner corners (columns, rows) as ``cv2.findChessboardCorners`` takes them;
    ``square``: square side in metres. ``camera`` defaults to the simulator's camera,
    ``T_camera_laser`` to the simulator's rig (laser 0.2 m below the camera, 0.1 m
    behind). Every view shows the whole board to the camera and has at least
    ``min_board_points`` lidar returns on it. Boards are placed as ``protocol`` (default
    ``CaptureProtocol()``) tells a person to hold them: leaning forward and back, turned
    left and right, near and far, across the image.
    """
    out = Path(out_dir)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 31]))
    spec = CameraSpec()
    cam = camera if camera is not None else spec.camera()
    T_base_cam = spec.T_base_camera()
    lspec = lidar if lidar is not None else LidarSpec()
    lspec = replace(lspec, noise_std=lidar_noise, dropout=0.0)
    T_base_laser = lspec.T_base_laser() if T_camera_laser is None else \
        T_base_cam @ np.asarray(T_camera_laser, dtype=np.float64)
    T_cam_laser = inv_se3(T_base_cam) @ T_base_laser
    T_world_base = np.eye(4)
    T_world_cam = T_world_base @ T_base_cam
    T_world_laser = T_world_base @ T_base_laser

    bank = build_texture_bank(seed)
    scene = Scene.from_boxes(_room(), bank)
    ss = 2  # supersampling
    big = cam.scaled(cam.width * ss, cam.height * ss)
    cam_r = CameraRenderer(scene, big)
    las_r = LidarRenderer(scene, lspec)
    geo = _board_geometry(board, square)
    cols, rows = board
    corners_b = np.array([[c * square, r * square, 0.0] for r in range(rows) for c in range(cols)])
    outline_b = np.array([[geo["x0"], geo["y0"], 0], [geo["x1"], geo["y0"], 0],
                          [geo["x1"], geo["y1"], 0], [geo["x0"], geo["y1"], 0]], float)

    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "lasers").mkdir(parents=True, exist_ok=True)
    proto = protocol if protocol is not None else CaptureProtocol()
    phase = rng.uniform(0.0, 1.0, 2)
    views = []
    tries = view_tries = 0
    while len(views) < n_views:
        tries += 1
        if tries > 500 * max(n_views, 1):
            raise RuntimeError("could not place the board in view of both sensors; is the "
                               "lidar plane within the camera's view?")
        # Each failed try of the same view moves the board a little nearer the middle.
        T_wb = _board_pose(rng, geo, T_world_cam, T_world_laser[2, 3], len(views), phase,
                           proto, cam, 0.97 ** view_tries)
        view_tries += 1
        T_cb = inv_se3(T_world_cam) @ T_wb
        # Whole board (with its margin) in the image, in front, not too oblique, above floor.
        pc = outline_b @ T_cb[:3, :3].T + T_cb[:3, 3]
        if np.any(pc[:, 2] < 0.3):
            continue
        uv, _ = cam.project(pc)
        if not np.all(cam.in_image(uv, margin=15.0)):
            continue
        n_c = T_cb[:3, 2]
        view_dir = (T_cb[:3, 3] + T_cb[:3, :3] @ outline_b.mean(0))
        if abs(n_c @ view_dir) / np.linalg.norm(view_dir) < np.cos(
                np.radians(proto.max_incidence_deg)):
            continue
        if (outline_b @ T_wb[:3, :3].T + T_wb[:3, 3])[:, 2].min() < 0.03:
            continue

        # Lidar: exact ranges to the board plane inside its outline, else the room.
        ret = las_r.render(T_world_laser, rng=rng, noisy=False)
        d_l = las_r.dirs_laser  # [B, 3] laser frame
        T_lb = inv_se3(T_world_laser) @ T_wb
        n_l, c_l = T_lb[:3, 2], T_lb[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            t_b = (n_l @ c_l) / (d_l @ n_l)
        pb = (t_b[:, None] * d_l - c_l) @ T_lb[:3, :3]  # into the board frame
        on_board = (t_b > 0) & _inside(pb, geo) & (t_b < ret.true_ranges)
        if on_board.sum() < min_board_points:
            continue
        r = np.where(on_board, t_b, ret.true_ranges)
        r = r + rng.standard_normal(len(r)) * lidar_noise
        valid = np.isfinite(r) & (r >= lspec.range_min) & (r <= lspec.range_max)
        pts = np.column_stack([r * d_l[:, 0], r * d_l[:, 1], np.zeros(len(r))])[valid]
        board_idx = np.flatnonzero(on_board[valid])

        # Camera: the room, then the board wherever it is nearer.
        img = cam_r.render(T_world_cam)
        rays = cam_r.rays_cam  # [N, 3] camera frame, z = 1
        n_cc, c_cc = T_cb[:3, 2], T_cb[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            t_c = (n_cc @ c_cc) / (rays @ n_cc)
        pbc = (t_c[:, None] * rays - c_cc) @ T_cb[:3, :3]
        depth = img.depth.reshape(-1)
        front = (t_c > 0) & _inside(pbc, geo) & ((depth == 0) | (t_c < depth))
        rgb = img.rgb.reshape(-1, 3).astype(np.float32)
        # Lambert shading of the board so that it is not perfectly uniform.
        shade = 0.75 + 0.25 * abs(float(n_cc @ np.array([0.3, -0.8, -0.5])))
        rgb[front] = (_checker(pbc[front], square, board) * shade)[:, None]
        rgb = rgb.reshape(big.height, big.width, 3)
        rgb = cv2.resize(rgb, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
        if image_noise > 0:
            rgb = rgb + rng.standard_normal(rgb.shape).astype(np.float32) * image_noise
        rgb8 = np.clip(rgb, 0, 255).astype(np.uint8)

        k = len(views)
        view_tries = 0
        img_ns = T0_NS + k * 2_000_000_000
        las_ns = img_ns + int(rng.uniform(8e6, 56e6))
        img_name, las_name = f"images/{img_ns}.png", f"lasers/{las_ns}.pcd"
        with atomic_path(out / img_name) as tmp:
            cv2.imwrite(str(tmp), cv2.cvtColor(rgb8, cv2.COLOR_RGB2BGR))
        _write_pcd(out / las_name, pts)
        uvc, _ = cam.project(corners_b @ T_cb[:3, :3].T + T_cb[:3, 3])
        views.append({
            "image": img_name, "scan": las_name, "image_stamp_ns": img_ns,
            "scan_stamp_ns": las_ns,
            "T_camera_board": T_cb.tolist(),
            "board_plane_camera": [*map(float, n_cc), float(n_cc @ c_cc)],
            "board_points": board_idx.tolist(),
            "corners_px": uvc.round(4).tolist(),
        })

    atomic_write_text(out / "camera.yaml", yaml.safe_dump(cam.to_dict(), sort_keys=False))
    gt = {
        "convention": "T_a_b maps points from frame b into frame a (p_a = T_a_b @ p_b); "
                      "camera = optical frame (x right, y down, z forward); laser = scan "
                      "frame (x forward, y left, z up; the scan lies in z = 0)",
        "T_camera_laser": T_cam_laser.tolist(),
        "T_base_camera": T_base_cam.tolist(),
        "T_base_laser": T_base_laser.tolist(),
        "board": {
            "inner_corners": [cols, rows], "square_m": float(square),
            "margin_m": float(geo["margin"]),
            "size_m": [float(geo["x1"] - geo["x0"]), float(geo["y1"] - geo["y0"])],
            "frame": "origin at the first inner corner (cv2 corner order), x along a row of "
                     f"{cols} corners, y along a column of {rows}, z = x cross y (the board "
                     "normal, pointing away from the sensors); board_plane_camera is n, d "
                     "with n . p = d for camera-frame points p",
            "corners_board": corners_b.tolist(),
        },
        "lidar": {"noise_std_m": float(lidar_noise), "beams": lspec.beams,
                  "angle_min": float(lspec.angle_min),
                  "angle_increment": float(lspec.angle_increment),
                  "range_min": lspec.range_min, "range_max": lspec.range_max},
        "image_noise_std": float(image_noise),
        "protocol": {k: (list(v) if isinstance(v, tuple) else v)
                     for k, v in asdict(proto).items()},
        "views": views,
    }
    atomic_write_text(out / "groundtruth.yaml", yaml.safe_dump(gt, sort_keys=False))
    return out

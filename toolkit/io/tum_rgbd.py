"""TUM RGB-D folders (``rgb.txt``, ``depth.txt``, ``groundtruth.txt``) with a virtual 2D lidar.

The TUM RGB-D benchmark (Sturm et al., IROS 2012) has real images, registered Kinect
depth (16-bit PNG, 5000 units per metre, 0 = no reading) and motion-capture ground truth
(``t tx ty tz qx qy qz qw``: the colour camera's optical frame in the mocap world, whose
z axis points up). It has no 2D lidar, so one is made from the depth images: the depth
points in a thin horizontal band at a chosen height, binned by bearing into beams, each
beam the nearest point in its bin - what ``pointcloud_to_laserscan`` does on a robot.

Which plane is "horizontal" (``VirtualLidarOptions.level``):

- ``groundtruth`` (the default when groundtruth.txt exists): gravity from the mocap
  poses. The camera's up direction (world +z seen from the camera) is averaged over the
  sequence, and ``base_link`` is defined with z along it and x along the optical axis
  projected onto the horizontal. The mount is assumed rigid, as on a robot: the
  spread of the per-frame up direction is reported (``meta.yaml: virtual_lidar``), and
  a handheld sequence shows up as a large one.
- ``camera``: no ground truth needed; the camera is assumed mounted level (optical axis
  horizontal, image rows horizontal), so ``T_base_camera`` is the REP 103 optical
  rotation and the lidar plane is the camera's own x-z plane.

Either way ``T_base_camera`` is fixed, ``T_base_laser`` is ``height_m`` straight up from
the camera centre (the base origin), and the ground-truth base poses are
``T_world_camera @ inv(T_base_camera)``. The scan therefore projects back onto the very
pixels it came from through the rig, which is what the fusion stage relies on.

Intrinsics: the depth maps are registered to the colour images by the OpenNI driver,
and the dataset's authors recommend the ROS default model (fx = fy = 525, cx = 319.5,
cy = 239.5, no distortion) for turning them into points; that is the default here.
The per-sensor calibrations fr1 / fr2 / fr3 from the dataset page are available too.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from toolkit.camera import PinholeCamera
from toolkit.geometry import Trajectory, inv_se3
from toolkit.ingest.recording import R_BASE_OPTICAL, FrameData, IngestError, Recording
from toolkit.ingest.sync import stamps_keep
from toolkit.io.depth import read_depth
from toolkit.io.tum import read_tum_with_lines
from toolkit.sensors import LaserScan, Rig, load_rgb

_log = logging.getLogger("toolkit.io.tum_rgbd")

DEPTH_SCALE = 5000.0  # TUM: 16-bit PNG units per metre (the same as toolkit.io.depth)

# (fx, fy, cx, cy, k1, k2, p1, p2, k3) for 640x480 images, from the dataset's page
# "Intrinsic Camera Calibration of the Kinect".
TUM_CAMERAS: dict[str, tuple[float, ...]] = {
    "ros_default": (525.0, 525.0, 319.5, 239.5, 0.0, 0.0, 0.0, 0.0, 0.0),
    "fr1": (517.3, 516.5, 318.6, 255.3, 0.2624, -0.9531, -0.0054, 0.0026, 1.1633),
    "fr2": (520.9, 521.0, 325.1, 249.7, 0.2312, -0.7849, -0.0033, -0.0001, 0.9172),
    "fr3": (535.4, 539.2, 320.1, 247.6, 0.0, 0.0, 0.0, 0.0, 0.0),
}


class VirtualLidarOptions(BaseModel):
    """The 2D lidar made from the depth images."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    # Which plane is horizontal (module docstring): auto = groundtruth if present.
    level: Literal["auto", "groundtruth", "camera"] = "auto"
    height_m: float = 0.0  # plane height above the camera centre (negative: below)
    band_m: float = Field(0.04, gt=0)  # thickness of the band of depth points used
    beams: int | None = Field(None, ge=2)  # default: one per pixel column at the centre
    range_min_m: float = Field(0.3, ge=0)  # the Kinect reads nothing closer
    range_max_m: float = Field(8.0, gt=0)
    world_up: tuple[float, float, float] = (0.0, 0.0, 1.0)  # in the groundtruth frame


class TumRgbdOptions(BaseModel):
    """Settings of the TUM RGB-D reader (``ingest`` key ``tum_rgbd:``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    # ros_default | fr1 | fr2 | fr3, or a mapping as in rig.yaml (width, height, fx, ...).
    camera: str | dict[str, Any] = "ros_default"
    lidar: VirtualLidarOptions = VirtualLidarOptions()


def read_list(path: Path, policy: Literal["error", "drop"] = "error") -> (
    tuple[np.ndarray, list[Path], int]
):
    """Stamps [N], files and the number dropped, of a TUM ``rgb.txt`` / ``depth.txt``."""
    if not path.exists():
        raise IngestError(f"{path}: not found; a TUM RGB-D folder has rgb.txt and depth.txt "
                          "(and optionally groundtruth.txt)")
    stamps: list[float] = []
    files: list[Path] = []
    lines: list[int] = []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split()
        if len(parts) != 2:
            raise IngestError(f"{path}:{lineno}: expected 'timestamp filename', got {s!r}")
        try:
            t = float(parts[0])
        except ValueError:
            raise IngestError(f"{path}:{lineno}: timestamp {parts[0]!r} is not a number") \
                from None
        f = path.parent / parts[1]
        if not f.exists():
            raise IngestError(f"{path}:{lineno}: {parts[1]} does not exist in {path.parent} "
                              "(an incomplete download?)")
        stamps.append(t)
        files.append(f)
        lines.append(lineno)
    st = np.asarray(stamps, dtype=np.float64)
    keep = stamps_keep(st, str(path), policy, lines=lines)
    return st[keep], [f for f, k in zip(files, keep, strict=True) if k], int((~keep).sum())


def tum_camera(spec: str | dict[str, Any], where: str = "tum_rgbd.camera") -> PinholeCamera:
    """The camera model named by ``spec`` (see ``TUM_CAMERAS``) or given as a mapping."""
    if isinstance(spec, dict):
        try:
            return PinholeCamera.from_dict(spec)
        except (KeyError, TypeError, ValueError) as e:
            raise IngestError(f"{where}: {e}") from None
    if spec not in TUM_CAMERAS:
        raise IngestError(f"{where}: {spec!r} is not one of {', '.join(TUM_CAMERAS)} (or give "
                          "a mapping with width, height, fx, fy, cx, cy, distortion)")
    fx, fy, cx, cy, *dist = TUM_CAMERAS[spec]
    return PinholeCamera(640, 480, fx, fy, cx, cy, np.array(dist))


def level_mount(R_world_camera: np.ndarray, world_up: Sequence[float]) -> (
    tuple[np.ndarray, dict[str, float]]
):
    """[3, 3] R_base_camera of a level base from camera orientations [N, 3, 3], and the
    spread of the camera's up direction over the frames (degrees).

    Base z is the mean up direction seen from the camera; base x the optical axis
    projected onto the horizontal; base y completes the right-handed frame.
    """
    up_w = np.asarray(world_up, dtype=np.float64)
    up_w = up_w / np.linalg.norm(up_w)
    ups = np.einsum("nji,j->ni", R_world_camera, up_w)  # [N, 3] R^T up: up in the camera
    g = ups.mean(axis=0)
    if np.linalg.norm(g) < 0.5:
        raise IngestError("the ground-truth orientations disagree about which way is up "
                          "(a tumbling camera?); use tum_rgbd.lidar.level: camera")
    g /= np.linalg.norm(g)
    ez = np.array([0.0, 0.0, 1.0])
    f = ez - (ez @ g) * g
    if np.linalg.norm(f) < 1e-3:
        raise IngestError("the camera looks straight up or down in the ground truth; a "
                          "horizontal lidar plane does not cross its view")
    f /= np.linalg.norm(f)
    R_camera_base = np.stack([f, np.cross(g, f), g], axis=1)  # columns: base axes
    dev = np.degrees(np.arccos(np.clip(ups @ g, -1.0, 1.0)))
    tilt = float(np.degrees(np.arcsin(np.clip(-(g @ ez), -1.0, 1.0))))
    stats = {"tilt_down_deg": round(tilt, 3), "up_spread_mean_deg": round(float(dev.mean()), 3),
             "up_spread_max_deg": round(float(dev.max()), 3)}
    return R_camera_base.T, stats


class VirtualLidar:
    """Turns registered depth images into planar scans in the laser frame.

    The laser frame is the base frame raised by ``height_m``: a depth pixel becomes the
    point ``depth * (R_base_camera @ ray)``; points within ``band_m / 2`` of the plane
    are binned by bearing, and each beam reports the nearest one (NaN: no point).
    """

    def __init__(self, camera: PinholeCamera, R_base_camera: np.ndarray,
                 opts: VirtualLidarOptions) -> None:
        self.opts = opts
        self.camera = camera
        rays = camera.pixel_rays().reshape(-1, 3) @ np.asarray(R_base_camera).T  # [HW, 3]
        self.rays = rays.astype(np.float64)
        fwd = rays[:, 0] > 1e-6
        bearing = np.arctan2(rays[fwd, 1], rays[fwd, 0])
        self.angle_min = float(bearing.min())
        angle_max = float(bearing.max())
        if opts.beams is None:
            # One beam per pixel column where columns are densest in angle (the centre),
            # so that no beam falls between two columns and stays empty.
            beams = int(np.floor((angle_max - self.angle_min) * camera.fx)) + 1
        else:
            beams = opts.beams
        self.beams = max(beams, 2)
        self.angle_increment = (angle_max - self.angle_min) / (self.beams - 1)

    def scan(self, depth: np.ndarray, stamp: float, where: str = "depth image") -> LaserScan:
        """The scan [beams] of a depth image [H, W] (metres, 0 = invalid); ``where`` names
        the image in errors."""
        d = np.asarray(depth, dtype=np.float64).reshape(-1)
        if len(d) != len(self.rays):
            w, h = self.camera.size
            raise IngestError(
                f"{where}: depth image is {depth.shape[1]}x{depth.shape[0]}, the camera model "
                f"{w}x{h} (tum_rgbd.camera). Fix: name the camera these images come from, or "
                "give its intrinsics as a mapping ('tum_rgbd.camera: {width, height, fx, fy, "
                "cx, cy}')")
        o = self.opts
        p = self.rays * d[:, None]  # [HW, 3] in the base frame
        z = p[:, 2] - o.height_m
        sel = (d > 0) & (np.abs(z) <= o.band_m / 2) & (p[:, 0] > 0)
        x, y = p[sel, 0], p[sel, 1]
        r = np.hypot(x, y)
        b = np.round((np.arctan2(y, x) - self.angle_min) / self.angle_increment)
        b = b.astype(np.int64)
        inb = (b >= 0) & (b < self.beams)
        r, b = r[inb], b[inb]
        ok = (r >= o.range_min_m) & (r <= o.range_max_m)
        out = np.full(self.beams, np.inf)
        np.minimum.at(out, b[ok], r[ok])
        # REP 117 for a bin without a point in range: +inf when its points all lie beyond
        # range_max (nothing within reach: the SLAM clears free space along it; NaN had it
        # cleared none), -inf when all nearer than range_min, NaN when it has none (a hole
        # in the depth: unknown, never zero).
        seen = np.zeros(self.beams, bool)
        seen[b] = True
        far = np.zeros(self.beams, bool)
        far[b[r > o.range_max_m]] = True
        empty = ~np.isfinite(out)
        out[empty & ~far] = -np.inf
        out[empty & ~seen] = np.nan
        return LaserScan(stamp, out.astype(np.float32), self.angle_min, self.angle_increment,
                         o.range_min_m, o.range_max_m)


def read_tum_rgbd(root: Path | str, options: TumRgbdOptions | None = None,
                  on_non_monotonic: Literal["error", "drop"] = "error",
                  progress: Callable[..., Iterator[Any]] | None = None,
                  log: logging.Logger | None = None, name: str | None = None) -> Recording:
    """Index a TUM RGB-D folder into a ``Recording``; the virtual scans are made here."""
    opts = options or TumRgbdOptions()
    log = log or _log
    root = Path(root)
    if not root.is_dir():
        # A file named here (a bag, a log, rgb.txt itself) was reported as "not found".
        what = ("is a file, not a TUM RGB-D folder (the one holding rgb.txt, depth.txt and "
                "groundtruth.txt); give that folder, or the 'source' that reads this file"
                if root.exists() else "TUM RGB-D folder not found")
        raise IngestError(f"{root}: {what}")
    rgb_t, rgb_f, rgb_drop = read_list(root / "rgb.txt", on_non_monotonic)
    dep_t, dep_f, dep_drop = read_list(root / "depth.txt", on_non_monotonic)
    if len(rgb_t) == 0 or len(dep_t) == 0:
        raise IngestError(f"{root}: rgb.txt and depth.txt must each list at least one image")
    camera = tum_camera(opts.camera)
    first = cv2.imread(str(rgb_f[0]), cv2.IMREAD_UNCHANGED)
    if first is None:
        raise IngestError(f"{rgb_f[0]}: unreadable image")
    if (first.shape[1], first.shape[0]) != camera.size:
        raise IngestError(f"{rgb_f[0]}: image is {first.shape[1]}x{first.shape[0]} but the "
                          f"camera model {opts.camera!r} is {camera.width}x{camera.height}; "
                          "give matching intrinsics in tum_rgbd.camera")

    gt_cam: Trajectory | None = None
    gt_drop = 0
    if (root / "groundtruth.txt").exists():
        try:
            raw, gt_lines = read_tum_with_lines(root / "groundtruth.txt", "world", "camera",
                                                require_monotonic=False)
        except ValueError as e:
            raise IngestError(str(e)) from None
        keep = stamps_keep(raw.stamps, str(root / "groundtruth.txt"), on_non_monotonic,
                           lines=gt_lines.tolist())
        gt_drop = int((~keep).sum())
        gt_cam = raw.slice(keep)

    lv = opts.lidar
    level = lv.level if lv.level != "auto" else ("groundtruth" if gt_cam is not None
                                                 else "camera")
    stats: dict[str, float] = {}
    if level == "groundtruth":
        if gt_cam is None or len(gt_cam) == 0:
            raise IngestError(f"{root}: tum_rgbd.lidar.level is groundtruth but there is no "
                              "groundtruth.txt; use level: camera (a level camera mount)")
        R_base_camera, stats = level_mount(gt_cam.poses[:, :3, :3], lv.world_up)
        if stats["up_spread_mean_deg"] > 5.0:
            log.warning("the camera's tilt varies by %.1f deg on average over %s: not a rigid "
                        "level mount (handheld?); the virtual lidar plane wobbles with it",
                        stats["up_spread_mean_deg"], root.name)
    else:
        R_base_camera = R_BASE_OPTICAL.copy()
    T_base_camera = np.eye(4)
    T_base_camera[:3, :3] = R_base_camera
    T_base_laser = np.eye(4)
    T_base_laser[2, 3] = lv.height_m
    rig = Rig(camera, T_base_camera, T_base_laser)

    lidar = VirtualLidar(camera, R_base_camera, lv)
    scans: list[LaserScan] = []
    it: Any = zip(dep_t, dep_f, strict=True)
    if progress is not None:
        it = progress(it, total=len(dep_t), description="virtual lidar")
    valid = 0
    for t, f in it:
        try:
            depth = read_depth(f)
        except (OSError, ValueError) as e:
            raise IngestError(f"{f}: {e}") from None
        s = lidar.scan(depth, float(t), str(f))
        valid += int(s.valid_mask().sum())
        scans.append(s)
    frac = valid / (len(scans) * lidar.beams)
    if frac < 0.01:
        raise IngestError(
            f"{root}: the virtual lidar plane ({level} level, {lv.height_m:+.2f} m, band "
            f"{lv.band_m} m) crosses almost no depth points ({100 * frac:.2f}% of beams valid)"
            + (f"; the camera looks {stats['tilt_down_deg']:.0f} deg down" if stats else "")
            + ". Fix: move the plane into view with tum_rgbd.lidar.height_m (negative = "
            "below the camera), or use tum_rgbd.lidar.level: camera")

    gt_base = gt_cam.transform(T_right=inv_se3(T_base_camera)) if gt_cam is not None else None
    if gt_base is not None:
        gt_base.frame, gt_base.child = "world", "base_link"
    log.info("TUM RGB-D %s: %d rgb, %d depth, %s; virtual lidar: %d beams over %.1f deg, "
             "level from %s, %.1f%% of beams valid", root, len(rgb_t), len(dep_t),
             f"{len(gt_cam)} ground-truth poses" if gt_cam is not None else "no ground truth",
             lidar.beams, np.degrees(lidar.angle_increment * (lidar.beams - 1)), level,
             100 * frac)

    def load(pairs: Sequence[tuple[int, int]]) -> Iterator[FrameData]:
        for f, d in pairs:
            path = rgb_f[f]
            png = path.suffix.lower() == ".png"
            yield FrameData(stamp=float(rgb_t[f]), image_path=path if png else None,
                            image=None if png else load_rgb(path),
                            depth=read_depth(dep_f[d]) if d >= 0 else None)

    meta = {
        "source_kind": "TUM RGB-D",
        "camera_model": opts.camera if isinstance(opts.camera, str) else "given",
        "virtual_lidar": {"level": level, "height_m": lv.height_m, "band_m": lv.band_m,
                          "beams": lidar.beams, "valid_beam_fraction": round(frac, 4),
                          **stats},
        "groundtruth": "motion capture (TUM RGB-D), T_world_base = T_world_camera @ "
                       "inv(T_base_camera)" if gt_cam is not None else None,
    }
    dropped = {"rgb.txt": rgb_drop, "depth.txt": dep_drop, "groundtruth.txt": gt_drop}
    return Recording(name=name or root.name, source=f"tum_rgbd {root}", rig=rig, scans=scans,
                     frame_stamps=rgb_t, load=load, depth_stamps=dep_t, groundtruth=gt_base,
                     meta=meta, depth_is_scan_clock=True,
                     dropped={k: v for k, v in dropped.items() if v})

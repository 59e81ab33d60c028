"""Sensor data of a recording: laser scans, camera frames, the rig, and the sequence.

These are plain containers with the conventions of ROS messages (REP 103/105,
``sensor_msgs/LaserScan``) so that data from bags, logs and the simulator look alike.
Images load lazily from disk so a long recording never sits in memory.
"""

from __future__ import annotations

import bisect
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from toolkit.camera import PinholeCamera
from toolkit.errors import MissingInputError
from toolkit.geometry import Trajectory, checked_rigid, inv_se3


@dataclass
class LaserScan:
    """One planar scan, as ``sensor_msgs/LaserScan``.

    Beam i points at ``angle_min + i * angle_increment`` (counter-clockwise about +z from
    +x; the increment may be negative) and was measured at ``stamp + i * time_increment``
    (ROS's convention, as ``laser_geometry`` reads it: the stamp is the first beam's time;
    0 means the whole scan at the stamp). Non-finite ranges, ranges <= 0 (many drivers'
    "no return") and ranges outside [range_min, range_max] are invalid.
    """

    stamp: float
    ranges: np.ndarray  # [B] float32 metres
    angle_min: float
    angle_increment: float
    range_min: float = 0.0
    range_max: float = float("inf")
    intensities: np.ndarray | None = None  # [B]
    time_increment: float = 0.0  # seconds between beams

    def __post_init__(self) -> None:
        self.ranges = np.asarray(self.ranges, dtype=np.float32).reshape(-1)
        if self.intensities is not None:
            self.intensities = np.asarray(self.intensities, dtype=np.float32).reshape(-1)
            if len(self.intensities) != len(self.ranges):
                raise ValueError(
                    f"scan at {self.stamp}: {len(self.intensities)} intensities for "
                    f"{len(self.ranges)} ranges"
                )
        if self.angle_increment == 0:
            raise ValueError(f"scan at {self.stamp}: angle_increment is zero")
        if not (np.isfinite(self.angle_min) and np.isfinite(self.angle_increment)):
            raise ValueError(f"scan at {self.stamp}: angle_min ({self.angle_min}) and "
                             f"angle_increment ({self.angle_increment}) must be finite")
        # Degrees taken for radians: a scanner's angles stay within a turn or so (some
        # 360-degree drivers overlap their ends); two turns is no scanner.
        span = abs(self.angle_increment) * max(len(self.ranges) - 1, 0)
        if span > 4 * np.pi or abs(self.angle_min) > 4 * np.pi:
            raise ValueError(
                f"scan at {self.stamp}: angle_min {self.angle_min:g} and angle_increment "
                f"{self.angle_increment:g} span {span:g} over {len(self.ranges)} beams, more "
                "than two turns: angles are radians (np.radians of degrees)")
        if not np.isfinite(self.time_increment):
            raise ValueError(f"scan at {self.stamp}: time_increment ({self.time_increment}) "
                             "must be finite (0 when the driver does not say)")

    def __len__(self) -> int:
        return len(self.ranges)

    @property
    def angle_max(self) -> float:
        return self.angle_min + (len(self.ranges) - 1) * self.angle_increment

    def angles(self) -> np.ndarray:
        """[B] beam angles in radians."""
        return self.angle_min + np.arange(len(self.ranges)) * self.angle_increment

    def beam_times(self) -> np.ndarray:
        """[B] seconds from the stamp at which each beam was measured."""
        return np.arange(len(self.ranges)) * self.time_increment

    @property
    def sweep_s(self) -> float:
        """Seconds from the first beam to the last (0 for an instantaneous scan)."""
        return max(len(self.ranges) - 1, 0) * self.time_increment

    def valid_mask(self) -> np.ndarray:
        """[B] bool: finite, positive ranges in [range_min, range_max). A zero is "no
        return" for many drivers, whatever range_min says, and so is exactly range_max
        (what many drivers write when nothing came back, as the SLAM and the de-skewing
        read it): never a point at the laser or on the scanner's reach."""
        r = self.ranges
        with np.errstate(invalid="ignore"):
            return np.isfinite(r) & (r > 0) & (r >= self.range_min) & (r < self.range_max)

    def points(self) -> np.ndarray:
        """[N, 2] float64 beam end points in the laser frame, invalid beams dropped."""
        m = self.valid_mask()
        a = self.angles()[m]
        r = self.ranges[m].astype(np.float64)
        return np.stack([r * np.cos(a), r * np.sin(a)], -1)

    def points_3d(self) -> np.ndarray:
        """[N, 3] end points in the laser frame (z = 0), invalid beams dropped."""
        p = self.points()
        return np.concatenate([p, np.zeros((len(p), 1))], -1)


@dataclass
class CameraFrame:
    """One camera image with its stamp; pixels load from ``path`` on first use."""

    stamp: float
    path: Path | None = None
    index: int = 0
    _image: np.ndarray | None = field(default=None, repr=False)

    @classmethod
    def from_array(cls, stamp: float, image: np.ndarray, index: int = 0) -> CameraFrame:
        return cls(stamp=stamp, path=None, index=index, _image=np.asarray(image))

    @property
    def image(self) -> np.ndarray:
        """[H, W, 3] RGB uint8 (not cached: a sequence of 10k frames must not pile up)."""
        if self._image is not None:
            return self._image
        if self.path is None:
            raise ValueError(f"frame {self.index} at {self.stamp} has neither pixels nor a path")
        return load_rgb(self.path)


def load_rgb(path: Path) -> np.ndarray:
    """Read an image file as RGB uint8 [H, W, 3], with an error naming the file.

    The pixels as stored: a JPEG's EXIF orientation tag is not applied, since the
    intrinsics, the depth and the masks describe the sensor's pixels (applied, a phone's
    180-degree tag rolled the camera against its rig without a word)."""
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    if bgr is None:
        raise MissingInputError(f"{path}: missing or not a readable image")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def image_down_angle_deg(T_base_camera: np.ndarray) -> float:
    """Degrees between the image's down direction (optical +y) and the base's down (-z):
    near 0 for a camera looking ahead; 90 for one in the body convention or rolled."""
    down = -float(np.asarray(T_base_camera)[2, 1])
    return float(np.degrees(np.arccos(np.clip(down, -1.0, 1.0))))


@dataclass
class Rig:
    """The sensor mounts on the robot base (REP 105 ``base_link``)."""

    camera: PinholeCamera
    T_base_camera: np.ndarray = field(default_factory=lambda: np.eye(4))  # [4, 4] optical frame
    T_base_laser: np.ndarray = field(default_factory=lambda: np.eye(4))  # [4, 4]

    def __post_init__(self) -> None:
        for name in ("T_base_camera", "T_base_laser"):
            try:
                T = checked_rigid(getattr(self, name))
            except ValueError as e:
                raise ValueError(f"{name} {e}") from None
            setattr(self, name, T)

    def mount_warnings(self) -> list[str]:
        """What looks like a transform given the wrong way round (``T_laser_camera`` for
        ``T_camera_laser``, a body frame for the optical one): the scan plane more than 30
        deg from the base's horizontal (2D lidar SLAM needs it level; upside down is fine),
        or the image's down (optical +y) more than 60 deg from the base's down. Empty for a
        usual ground robot; a camera mounted rolled or looking straight down is flagged
        too, and may ignore it."""
        out = []
        tilt = float(np.degrees(np.arccos(np.clip(abs(self.T_base_laser[2, 2]), 0.0, 1.0))))
        if tilt > 30.0:
            out.append(f"the scan plane is tilted {tilt:.0f} deg from the base's horizontal "
                       "(T_base_laser's z axis): 2D lidar SLAM needs it level - is a transform "
                       "inverted (T_laser_camera given for T_camera_laser)?")
        angle = image_down_angle_deg(self.T_base_camera)
        if angle > 60.0:
            out.append(f"the image's down direction is {angle:.0f} deg from the base's down "
                       "(T_base_camera's y axis): unless the camera is mounted rolled or "
                       "looks straight down, a transform is inverted or in the body (x "
                       "forward) instead of the optical (z forward, y down) convention")
        return out

    @property
    def T_camera_laser(self) -> np.ndarray:
        """[4, 4] maps laser points into the camera optical frame."""
        return inv_se3(self.T_base_camera) @ self.T_base_laser

    def with_T_camera_laser(self, T_camera_laser: np.ndarray) -> Rig:
        """A rig with the laser re-mounted so that ``T_camera_laser`` holds (calibration)."""
        return Rig(self.camera, self.T_base_camera.copy(), self.T_base_camera @ T_camera_laser)


@dataclass
class HeldOutViews:
    """Camera views off the driven path for novel-view evaluation (simulator)."""

    poses_camera: Trajectory  # T_world_camera
    image_paths: list[Path]
    depth_paths: list[Path]


@dataclass
class GroundTruth:
    """Optional ground truth of a recording; every member may be absent."""

    poses_base: Trajectory | None = None  # T_world_base at sensor stamps
    depth_paths: list[Path] | None = None  # per camera frame
    mask_paths: list[Path] | None = None  # per camera frame, dynamic pixels
    scan_dynamic: np.ndarray | None = None  # [S, B] bool: beam hit a moving obstacle
    mesh_path: Path | None = None
    heldout: HeldOutViews | None = None
    exposure_gain: np.ndarray | None = None  # [F] each frame's auto-exposure gain

    def depth(self, index: int) -> np.ndarray:
        """[H, W] float32 metres of frame ``index`` (0 where invalid)."""
        if self.depth_paths is None:
            raise ValueError("this sequence has no ground-truth depth")
        from toolkit.io.depth import read_depth

        return read_depth(self.depth_paths[index])

    def mask(self, index: int) -> np.ndarray:
        """[H, W] bool of dynamic pixels of frame ``index``."""
        if self.mask_paths is None:
            raise ValueError("this sequence has no ground-truth masks")
        m = cv2.imread(str(self.mask_paths[index]), cv2.IMREAD_UNCHANGED)
        if m is None:
            raise MissingInputError(f"{self.mask_paths[index]}: missing or unreadable mask")
        return m > 0


@dataclass
class Sequence:
    """A recording: camera frames, laser scans, rig, optional odometry and ground truth."""

    rig: Rig
    frames: list[CameraFrame]
    scans: list[LaserScan]
    odometry: Trajectory | None = None  # T_odom_base
    groundtruth: GroundTruth | None = None
    name: str = "sequence"
    root: Path | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._frame_stamps = np.array([f.stamp for f in self.frames], dtype=np.float64)
        self._scan_stamps = np.array([s.stamp for s in self.scans], dtype=np.float64)

    @property
    def frame_stamps(self) -> np.ndarray:
        """[F] camera stamps."""
        return self._frame_stamps

    @property
    def scan_stamps(self) -> np.ndarray:
        """[S] scan stamps."""
        return self._scan_stamps

    @property
    def time_span(self) -> tuple[float, float]:
        """(first, last) stamp in seconds over the camera frames and scans together."""
        stamps = np.concatenate([self._frame_stamps, self._scan_stamps])
        if len(stamps) == 0:
            raise ValueError("empty sequence")
        return float(stamps.min()), float(stamps.max())

    def iter_frames(self) -> Iterator[CameraFrame]:
        return iter(self.frames)

    @staticmethod
    def _nearest(stamps: np.ndarray, t: float, max_dt: float | None = None) -> int:
        if len(stamps) == 0:
            raise IndexError("no data to look up")
        if t != t:
            # NaN compares false: it passed every check below and got the first or the last
            # item (by the lookup's length), max_dt or not.
            raise ValueError(f"t={t!r} is not a time")
        span = float(stamps[-1] - stamps[0])
        off = max(float(stamps[0]) - t, t - float(stamps[-1]))
        if off > max(span, 1.0):
            # Nearest to a time this far away is the first or last item whatever was meant
            # (12.3 against stamps of 1.7e9 s: seconds into the recording, not its stamps).
            raise ValueError(f"t={t!r} lies {off:.3g} s outside the recording "
                             f"({float(stamps[0])!r} .. {float(stamps[-1])!r}); stamps are "
                             "the recording's own: e.g. seq.time_span[0] + seconds")
        i = bisect.bisect_left(stamps.tolist(), t) if len(stamps) < 64 else int(
            np.searchsorted(stamps, t)
        )
        if i == 0:
            k = 0
        elif i == len(stamps):
            k = len(stamps) - 1
        else:
            k = i if stamps[i] - t < t - stamps[i - 1] else i - 1
        if k > 0 and stamps[k - 1] == stamps[k]:
            # First of equal stamps, as ingest.sync.match_nearest (argmin) picks.
            k = int(np.searchsorted(stamps, stamps[k], "left"))
        if max_dt is not None and abs(float(stamps[k]) - t) > max_dt:
            raise LookupError(f"nothing within {max_dt:g} s of t={t!r}: the nearest is "
                              f"{float(stamps[k]) - t:+.3g} s away")
        return k

    def frame_index_at(self, t: float, max_dt: float | None = None) -> int:
        """Index of the camera frame nearest in time to ``t`` (``LookupError`` when it is
        more than ``max_dt`` seconds away); ties as ``scan_index_at``."""
        return self._nearest(self._frame_stamps, t, max_dt)

    def scan_index_at(self, t: float, max_dt: float | None = None) -> int:
        """Index of the scan nearest in time to ``t`` (``LookupError`` when it is more than
        ``max_dt`` seconds away). A ``t`` exactly midway between two stamps gets the
        earlier, and among equal stamps the first, as ``ingest.sync.match_nearest``."""
        return self._nearest(self._scan_stamps, t, max_dt)

    def frame_at(self, t: float, max_dt: float | None = None) -> CameraFrame:
        return self.frames[self.frame_index_at(t, max_dt)]

    def scan_at(self, t: float, max_dt: float | None = None) -> LaserScan:
        """The scan nearest in time to ``t``; with ``max_dt``, none further than that (the
        last scan, a minute away, is the "nearest" to a time near the recording's end).
        Midway between two stamps: the earlier scan (ties as ``scan_index_at``)."""
        return self.scans[self.scan_index_at(t, max_dt)]

    def scans_between(self, t0: float, t1: float) -> list[LaserScan]:
        """Scans with t0 <= stamp < t1."""
        if t0 != t0 or t1 != t1:
            # NaN sorts after every stamp: it gave no scans as t0, all from t0 on as t1.
            raise ValueError(f"scans_between({t0!r}, {t1!r}): a limit is not a time")
        i0, i1 = np.searchsorted(self._scan_stamps, [t0, t1])
        return self.scans[i0:i1]

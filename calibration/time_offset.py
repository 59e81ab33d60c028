"""Camera - lidar time offset: how much later the camera stamps its images than it takes them.

A camera driver commonly stamps an image when it arrives (USB transfer, a network camera, a
busy computer): tens of milliseconds after the exposure, while a 2D lidar's driver stamps
the scan's first beam. The toolkit places every scan at its own stamp with the poses and
moves it into the camera at the image's stamp, so a delay d puts the image at the pose of
d seconds later: on a robot turning at 1 rad/s, 50 ms turn the lidar points 2.9 deg off
in the image (26 px at f = 525) and put the image's colours on the wrong surfaces.

Method: the robot's turning, seen twice. From the images, the camera's rotation between
consecutive frames (corners tracked with pyramidal Lucas-Kanade, essential matrix with
RANSAC, ``cv2.recoverPose``), its component about the robot's vertical axis; from a
trajectory on the lidar's clock (lidar SLAM or wheel odometry), the robot's yaw change
between the same two instants shifted by a candidate delay. The delay is the shift that
makes the two agree best: a trimmed mean of squared differences of the yaw changes over
windows of consecutive frames (0.5 s), on a grid and then a parabola through the best
three points. Its spread comes from resampling runs of windows (a moving-block
bootstrap: overlapping windows share frame pairs, and resampling them one by one gave
spreads 1.5-3x too small). A change of turning rate is what carries the signal: a
recording driven straight, or round one steady circle, cannot tell a delay, and the
result says so.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from toolkit.camera import PinholeCamera
from toolkit.errors import InputError
from toolkit.geometry import Trajectory

log = logging.getLogger(__name__)


class TimeOffsetError(InputError):
    """Input that cannot give a time offset (too few frames, no trajectory over them)."""


# A delay within twice its spread of zero, or under this, is nothing to correct.
NEGLIGIBLE_S = 0.002


def check_inputs(frame_stamps: np.ndarray, trajectory: Trajectory, source: str,
                 window_s: float = 0.5) -> None:
    """What makes ``estimate_camera_delay`` fail, checked before the images are read (which
    takes a while on a long recording): raises TimeOffsetError naming the fix."""
    t = np.asarray(frame_stamps, np.float64)
    if len(t) < 3:
        raise TimeOffsetError(f"{len(t)} camera frames; at least 3 are needed")
    if len(trajectory) < 2:
        raise TimeOffsetError(f"{source}: {len(trajectory)} poses; the robot's poses over the "
                              "recording are needed")
    covered = float(trajectory.covers(t).mean())
    if covered < 0.5:
        raise TimeOffsetError(
            f"{source} covers {covered:.0%} of the frames (frames {t[0]:.3f}..{t[-1]:.3f} s, "
            f"trajectory {trajectory.stamps[0]:.3f}..{trajectory.stamps[-1]:.3f} s): the "
            "trajectory must cover the frames (another clock?)")
    spacing = float(np.median(np.diff(t)))
    if spacing > window_s:
        raise TimeOffsetError(
            f"the frames are {spacing:.2f} s apart (median), more than the {window_s} s "
            "window: rotations are read between frames close in time (use more frames, "
            "e.g. less decimation)")


def applied_delay(seq: object) -> float:
    """The camera delay a sequence's conversion already took out (ingest's
    ``sync.camera_delay_s``, in its meta.yaml); 0 for others."""
    meta = getattr(seq, "meta", None) or {}
    ingest = meta.get("ingest") if isinstance(meta, dict) else None
    value = ingest.get("camera_delay_s", 0.0) if isinstance(ingest, dict) else 0.0
    return float(value or 0.0)


def needs_correction(result: TimeOffsetResult) -> bool:
    """A reliable delay clearly off zero."""
    return result.reliable and abs(result.delay_s) >= max(2 * result.std_s, NEGLIGIBLE_S)


def advice(result: TimeOffsetResult, applied_s: float = 0.0) -> str:
    """What to do about ``result``, measured on a recording converted with ingest's
    ``sync.camera_delay_s`` = ``applied_s`` already taken out."""
    if not result.reliable:
        return "Not reliable: " + "; ".join(result.reasons) + "."
    total = applied_s + result.delay_s
    done = f" ({applied_s * 1000:+.1f} ms already taken out at conversion)" if applied_s else ""
    if not needs_correction(result):
        return f"Nothing to correct{done}."
    return (f"Images are stamped {abs(total) * 1000:.1f} ms {'after' if total > 0 else 'before'}"
            f" they are taken{done}: convert the recording with ingest's "
            f"`sync: {{camera_delay_s: {total:.4f}}}`.")


@dataclass
class FrameRotation:
    """The camera's rotation between two consecutive images."""

    R: np.ndarray | None  # [3, 3] x1 = R x0 + t (camera 0 -> camera 1); None: not found
    inliers: int  # correspondences the essential matrix explains


def frame_rotation(gray0: np.ndarray, gray1: np.ndarray, camera: PinholeCamera,
                   max_corners: int = 500, min_inliers: int = 30) -> FrameRotation:
    """Rotation of the camera from image 0 to image 1 (uint8 grey, the camera's size)."""
    p0 = cv2.goodFeaturesToTrack(gray0, maxCorners=max_corners, qualityLevel=0.01,
                                 minDistance=8, blockSize=7)
    if p0 is None or len(p0) < min_inliers:
        return FrameRotation(None, 0)
    lk = {"winSize": (21, 21), "maxLevel": 3,
          "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)}
    p1, st, _ = cv2.calcOpticalFlowPyrLK(gray0, gray1, p0, None, **lk)
    # Forward-backward check: a track that does not lead back to its corner is dropped.
    back, st_b, _ = cv2.calcOpticalFlowPyrLK(gray1, gray0, p1, None, **lk)
    good = (st.ravel() == 1) & (st_b.ravel() == 1) & (
        np.linalg.norm((back - p0).reshape(-1, 2), axis=1) < 0.5)
    if int(good.sum()) < min_inliers:
        return FrameRotation(None, int(good.sum()))
    K = camera.K
    dist = np.asarray(camera.dist, np.float64)
    # Normalised coordinates: the lens's distortion out, one focal length.
    n0 = cv2.undistortPoints(p0[good].reshape(-1, 1, 2).astype(np.float64), K, dist)
    n1 = cv2.undistortPoints(p1[good].reshape(-1, 1, 2).astype(np.float64), K, dist)
    f = 0.5 * (camera.fx + camera.fy)
    E, mask = cv2.findEssentialMat(n0, n1, np.eye(3), method=cv2.RANSAC, prob=0.999,
                                   threshold=1.0 / f)
    if E is not None and E.shape == (3, 3):
        n_in, R, _, _ = cv2.recoverPose(E, n0, n1, np.eye(3), mask=mask)
        if n_in >= min_inliers:
            return FrameRotation(R, int(n_in))
    # A turn on the spot has no baseline: the essential matrix is undetermined there, but
    # the images are related by the rotation alone (x1 ~ R x0, a homography).
    H, hmask = cv2.findHomography(n0, n1, cv2.RANSAC, 1.0 / f)
    if H is None or hmask is None or int(hmask.sum()) < min_inliers:
        return FrameRotation(None, 0 if hmask is None else int(hmask.sum()))
    u, _, vt = np.linalg.svd(H)
    R = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt  # the nearest rotation
    return FrameRotation(R, int(hmask.sum()))


def up_in_camera(T_base_camera: np.ndarray) -> np.ndarray:
    """[3] the robot's vertical axis (base_link z) in the optical camera frame."""
    return np.asarray(T_base_camera, np.float64)[:3, :3].T @ np.array([0.0, 0.0, 1.0])


def yaw_of_rotation(R: np.ndarray, up_cam: np.ndarray) -> float:
    """The robot's yaw change (counter-clockwise, radians) that turns its camera by ``R``
    (x1 = R x0): the camera frame turns by the inverse, about ``up_cam``."""
    rvec, _ = cv2.Rodrigues(np.asarray(R, np.float64))
    return -float(rvec.ravel() @ up_cam)


def frames_to_use(n: int, max_frames: int = 3000, block: int = 100) -> np.ndarray:
    """Indices of the frames to read of ``n``: all of them, or on a longer recording
    ``max_frames`` in runs of ``block`` consecutive frames spread along it (rotations are
    read between neighbours; an hour at 10 Hz is 36,000 frames, ten minutes of reading)."""
    if n <= max_frames:
        return np.arange(n)
    # Runs no longer than max_frames: --max-frames 50 on 80 frames read one run of 100,
    # indices past the recording's last frame (an IndexError before any image was read).
    # Runs shorter than block when max_frames holds fewer than two: --max-frames 150 read
    # one run of 100 from the start, none of the rest of the recording. A run needs two
    # frames to measure a rotation.
    block = min(max(min(block, max_frames // 2), 2), max_frames)
    runs = max(max_frames // block, 1)
    starts = np.linspace(0, n - block, runs).round().astype(int)
    return np.unique((starts[:, None] + np.arange(block)).ravel())


def camera_yaw_increments(images: Iterable[np.ndarray], camera: PinholeCamera,
                          T_base_camera: np.ndarray,
                          progress: Callable[[int], None] | None = None,
                          linked: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The robot's yaw change between consecutive images, seen by the camera.

    ``images``: RGB uint8 frames in time order; ``linked`` [K-1] bool: which neighbours to
    measure (False: NaN without the work, e.g. between runs of ``frames_to_use``). Returns
    ``dyaw`` [K-1] (radians, NaN where no rotation was found) and ``inliers`` [K-1].
    """
    up = up_in_camera(T_base_camera)
    dyaw: list[float] = []
    inl: list[int] = []
    prev = None
    for k, img in enumerate(images):
        if img.shape[:2] != (camera.height, camera.width):
            raise TimeOffsetError(f"image {k} is {img.shape[1]}x{img.shape[0]}, the camera "
                                  f"{camera.width}x{camera.height}")
        gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
        if prev is not None and linked is not None and not linked[k - 1]:
            dyaw.append(math.nan)
            inl.append(0)
        elif prev is not None:
            r = frame_rotation(prev, gray, camera)
            dyaw.append(math.nan if r.R is None else yaw_of_rotation(r.R, up))
            inl.append(r.inliers)
        prev = gray
        if progress is not None:
            progress(k)
    return np.array(dyaw, np.float64), np.array(inl, np.int64)


def trajectory_yaw(traj: Trajectory) -> Callable[[np.ndarray], np.ndarray]:
    """Yaw (base_link x about world z, unwrapped, radians) of ``traj`` as a function of
    time, linear between its samples."""
    R = traj.poses[:, :3, :3]
    yaw = np.unwrap(np.arctan2(R[:, 1, 0], R[:, 0, 0]))
    stamps = traj.stamps

    def at(t: np.ndarray) -> np.ndarray:
        return np.interp(t, stamps, yaw)

    return at


@dataclass
class TimeOffsetResult:
    """What ``estimate_camera_delay`` found."""

    delay_s: float  # image stamp - exposure time; subtract it from the stamps
    std_s: float  # bootstrap spread of ``delay_s`` (windows overlap: a lower bound)
    windows: int  # windows of consecutive frames compared
    frames_per_window: int
    turn_change_rad_s: float  # RMS change of the yaw rate across a window (the signal)
    residual_deg: float  # RMS camera - trajectory yaw change per window at the delay
    residual_at_zero_deg: float  # the same without a delay
    reliable: bool
    reasons: list[str] = field(default_factory=list)
    pairs_rejected: int = 0  # frame pairs left out: their rotation far off the trajectory's
    grid_s: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [G] delays tried
    cost: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [G] their cost (rad^2)

    def to_dict(self) -> dict[str, object]:
        return {"delay_s": self.delay_s, "std_s": self.std_s, "windows": self.windows,
                "frames_per_window": self.frames_per_window,
                "pairs_rejected": self.pairs_rejected,
                "turn_change_rad_s": self.turn_change_rad_s,
                "residual_deg": self.residual_deg,
                "residual_at_zero_deg": self.residual_at_zero_deg,
                "reliable": self.reliable, "reasons": list(self.reasons)}


def _trimmed_cost(r: np.ndarray, keep: float) -> np.ndarray:
    """[G] mean of the smallest ``keep`` share of r^2 along the last axis (r: [G, P])."""
    n = max(1, int(round(keep * r.shape[-1])))
    sq = np.sort(r * r, axis=-1)[..., :n]
    return sq.mean(-1)


def estimate_camera_delay(frame_stamps: np.ndarray, cam_dyaw: np.ndarray,
                          trajectory: Trajectory, search_s: float = 0.3,
                          window_s: float = 0.5, step_s: float = 0.002, keep: float = 0.8,
                          bootstrap: int = 100, seed: int = 0) -> TimeOffsetResult:
    """The camera delay that best lines its turning up with ``trajectory``'s.

    Twice: a first estimate, then again without the frame pairs whose rotation is far off
    the trajectory's at it (a mistracked pair spoils every window it lies in: with 10 % of
    them 5 deg off, 41 % of 5-frame windows held one). Arguments: ``_estimate``.
    """
    first = _estimate(frame_stamps, cam_dyaw, trajectory, search_s, window_s, step_s, keep,
                      0, seed)
    t = np.asarray(frame_stamps, np.float64)
    d = np.array(cam_dyaw, np.float64)
    yaw = trajectory_yaw(trajectory)
    r = d - (yaw(t[1:] - first.delay_s) - yaw(t[:-1] - first.delay_s))
    ok = np.isfinite(r)
    sigma = 1.4826 * float(np.median(np.abs(r[ok]))) if ok.any() else 0.0
    wild = ok & (np.abs(r) > max(5.0 * sigma, np.radians(0.3)))
    d[wild] = np.nan
    res = _estimate(t, d, trajectory, search_s, window_s, step_s, keep, bootstrap, seed)
    res.pairs_rejected = int(wild.sum())
    return res


def _estimate(frame_stamps: np.ndarray, cam_dyaw: np.ndarray, trajectory: Trajectory,
              search_s: float, window_s: float, step_s: float, keep: float,
              bootstrap: int, seed: int) -> TimeOffsetResult:
    """One estimate of the camera delay.

    ``frame_stamps`` [K] (the images' stamps), ``cam_dyaw`` [K-1] (``camera_yaw_increments``,
    NaN where none was found), ``trajectory`` T_world_base on the lidar's clock. The yaw
    changes are compared over windows of consecutive frames ``window_s`` long (windows with
    a NaN pair are left out): over one frame (0.1 s) the trajectory's own noise hid the
    signal (lidar SLAM on the simulated house: 22 +- 32 ms for no delay), over 0.5 s
    -0.5 +- 0.7 ms. Delays in [-search_s, search_s] are tried; positive: the images were
    taken before their stamps.
    """
    t = np.asarray(frame_stamps, np.float64)
    d = np.asarray(cam_dyaw, np.float64)
    if len(t) < 2 or len(d) != len(t) - 1:
        raise TimeOffsetError(f"{len(t)} frame stamps need {max(len(t) - 1, 0)} yaw changes, "
                              f"got {len(d)}")
    if not 0 < step_s < search_s:
        raise TimeOffsetError(f"step_s {step_s} must lie in (0, search_s = {search_s})")
    if np.any(np.diff(t) <= 0):
        raise TimeOffsetError("frame stamps must increase")
    m = max(1, int(round(window_s / float(np.median(np.diff(t))))))
    i0 = np.arange(0, max(len(t) - m, 0))
    i1 = i0 + m
    csum = np.concatenate([[0.0], np.cumsum(np.nan_to_num(d))])
    holes = np.concatenate([[0], np.cumsum(~np.isfinite(d))])
    t0, t1 = t[i0], t[i1]
    # The same windows for every delay tried: both ends covered at either end of the search.
    use = holes[i1] == holes[i0]
    for e in (t0, t1):
        use &= trajectory.covers(e - search_s) & trajectory.covers(e + search_s)
    n = int(use.sum())
    if n < 10:
        raise TimeOffsetError(
            f"only {n} windows of {m} frame(s) have camera rotations and trajectory poses "
            f"within {search_s} s around them (of {len(i0)}): the trajectory must cover the "
            "frames (another clock?), and the images need texture to track")
    dw = (csum[i1] - csum[i0])[use]
    t0, t1 = t0[use], t1[use]
    yaw = trajectory_yaw(trajectory)
    grid = np.arange(-search_s, search_s + 0.5 * step_s, step_s)

    def residuals(delays: np.ndarray, i: np.ndarray | slice = slice(None)) -> np.ndarray:
        dl = delays[:, None]
        return dw[i][None] - (yaw(t1[i][None] - dl) - yaw(t0[i][None] - dl))  # [G, P]

    cost = _trimmed_cost(residuals(grid), keep)

    def refine(c: np.ndarray) -> float:
        j = int(np.argmin(c))
        if 0 < j < len(grid) - 1:
            y0, y1, y2 = c[j - 1], c[j], c[j + 1]
            den = y0 - 2 * y1 + y2
            if den > 0:
                return float(grid[j] + 0.5 * step_s * (y0 - y2) / den)
        return float(grid[j])

    delay = refine(cost)
    rng = np.random.default_rng(seed)
    # Runs of m windows (a window shares frame pairs with its m - 1 neighbours each way).
    n_blocks = -(-n // m)
    offsets = np.arange(m)

    def resample() -> np.ndarray:
        starts = rng.integers(0, max(n - m, 0) + 1, n_blocks)
        return np.minimum((starts[:, None] + offsets).ravel()[:n], n - 1)

    boots = [refine(_trimmed_cost(residuals(grid, resample()), keep))
             for _ in range(bootstrap)]
    std = float(np.std(boots)) if boots else math.nan
    # The cost feels a delay through the yaw rate changing between a window's ends: from
    # the trajectory (the camera's own increments carry tracking noise that grows with the
    # frame rate and read as turning).
    h = 0.05

    def rate(q: np.ndarray) -> np.ndarray:
        return (yaw(q + h) - yaw(q - h)) / (2 * h)

    turn_change = float(np.sqrt(np.mean((rate(t1) - rate(t0)) ** 2)))

    def rms_deg(delay_s: float) -> float:
        r = residuals(np.array([delay_s]))
        return float(np.degrees(np.sqrt(_trimmed_cost(r, keep)[0])))

    reasons = []
    if turn_change < 0.05:
        reasons.append(f"the robot's turning hardly changed (yaw rate change over a window "
                       f"{turn_change:.3f} rad/s RMS): a straight drive or one steady circle "
                       "cannot tell a delay; drive turns that start and stop")
    if abs(delay) > search_s - 2 * step_s:
        reasons.append(f"the best delay lies at the edge of the search (+-{search_s} s): "
                       "widen it")
    if not std <= 0.01:
        reasons.append(f"the frame windows disagree: bootstrap spread {std * 1000:.1f} ms "
                       "(more turning, more texture, or a better trajectory)")
    return TimeOffsetResult(delay, std, n, m, turn_change, rms_deg(delay), rms_deg(0.0),
                            not reasons, reasons, 0, grid, cost)


def write_figure(path: str, result: TimeOffsetResult, frame_stamps: np.ndarray,
                 cam_dyaw: np.ndarray, trajectory: Trajectory) -> None:
    """PNG: the two yaw rates before and after the shift, and the cost over the delays."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from toolkit.io.atomic import atomic_path

    t = np.asarray(frame_stamps, np.float64)
    dt = np.diff(t)
    mid = 0.5 * (t[:-1] + t[1:])
    yaw = trajectory_yaw(trajectory)
    fig, (a0, a1) = plt.subplots(2, 1, figsize=(10, 6.5), height_ratios=(2, 1))
    rel = mid - t[0]
    a0.plot(rel, np.degrees(cam_dyaw / dt), ".", ms=3, color="tab:blue",
            label="camera (images)")
    for delay, style, name in ((0.0, ":", "trajectory at the image stamps"),
                               (result.delay_s, "-", "trajectory at the image stamps "
                                f"{-result.delay_s * 1000:+.1f} ms (the estimate)")):
        rate = (yaw(t[1:] - delay) - yaw(t[:-1] - delay)) / dt
        a0.plot(rel, np.degrees(rate), style, lw=1, color="tab:red" if delay else "grey",
                label=name)
    a0.set_xlabel("time since the first frame (s)")
    a0.set_ylabel("yaw rate (deg/s)")
    a0.legend(loc="upper right", fontsize=8)
    a0.set_title("Robot turning seen by the camera and by the trajectory")
    a1.plot(result.grid_s * 1000, np.degrees(np.sqrt(result.cost)), color="k", lw=1)
    a1.axvline(result.delay_s * 1000, color="tab:red", lw=1)
    a1.set_xlabel("camera delay tried (ms): image stamp minus exposure")
    a1.set_ylabel("RMS yaw mismatch\nper window (deg)")
    fig.tight_layout()
    with atomic_path(path, clean_stale=True) as tmp:  # the CLI writes outside run folders
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


@dataclass
class Measurement:
    """What ``measure`` read and found."""

    result: TimeOffsetResult
    stamps: np.ndarray  # [K] stamps of the frames read
    dyaw: np.ndarray  # [K-1] their yaw changes (NaN: none found, or across a gap)
    inliers: np.ndarray  # [K-1]
    pairs_measured: int  # neighbours within one run of frames


def measure(frames: Sequence[Any], camera: PinholeCamera, T_base_camera: np.ndarray,
            trajectory: Trajectory, source: str,
            progress: Callable[[Iterable[Any], int], Iterable[Any]] | None = None,
            max_frames: int = 3000, search_s: float = 0.3,
            window_s: float = 0.5) -> Measurement:
    """The camera delay of a recording's ``frames`` (``CameraFrame``s, time order) against
    ``trajectory`` (named ``source`` in errors): up to ``max_frames`` of them read
    (``frames_to_use``), the inputs checked before any image is; ``progress(iterable,
    total)`` wraps the image reading."""
    use = frames_to_use(len(frames), max_frames)
    chosen = [frames[k] for k in use]
    linked = np.diff(use) == 1
    stamps = np.array([f.stamp for f in chosen])
    check_inputs(stamps, trajectory, source, window_s)  # before the images: they take a while
    it: Iterable[Any] = chosen if progress is None else progress(chosen, len(chosen))
    dyaw, inliers = camera_yaw_increments((f.image for f in it), camera, T_base_camera,
                                          linked=linked)
    res = estimate_camera_delay(stamps, dyaw, trajectory, search_s=search_s,
                                window_s=window_s)
    return Measurement(res, stamps, dyaw, inliers, int(linked.sum()))

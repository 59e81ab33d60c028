"""From image and scan files to an extrinsic: detection, pairing, board points, solve.

This is the edge where files are read; the maths lives in ``board``, ``board_lines`` and
``extrinsic``. ``run_extrinsic`` is what the command line and the recipe stage call.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from calibration.board import (
    BoardError,
    BoardSpec,
    Detection,
    board_hint,
    detect_corners,
    found_in,
    list_images,
    read_image,
)
from calibration.board_lines import (
    BoardExpectation,
    board_edge_points,
    extract_segments,
    in_bearing_window,
    points_near_plane,
    range_noise,
    select_board_segment,
)
from calibration.extrinsic import (
    MIN_VIEWS,
    ExtrinsicError,
    ExtrinsicResult,
    LeaveOneOut,
    SolverOptions,
    View,
    calibrate_extrinsic,
    leave_one_out,
    leave_one_out_warning,
    left_out_text,
    make_view,
)
from calibration.files import CalibrationFileError, check_image_size
from calibration.frames import R_CAMERA_LASER_NOMINAL
from calibration.scans import (
    PairingError,
    StampedScan,
    describe_unpaired,
    pair_by_stamp,
    read_scans,
    refuse_same_stamps,
    stamp_from_name,
)
from toolkit.camera import PinholeCamera
from toolkit.errors import MissingInputError
from toolkit.geometry import Trajectory, inv_se3, se3
from toolkit.sensors import LaserScan

log = logging.getLogger("calibration")
# Progress of long loops; the CLI shows it without -v.
progress_log = logging.getLogger("calibration.progress")


@dataclass
class BoardSearch:
    """How to find the board's points in a scan."""

    angle_window_deg: tuple[float, float] | None = None  # laser bearings to search (manual)
    max_offset_m: float = 0.5  # how far apart the two sensors can be
    min_length_m: float | None = None  # default: half the printed pattern's short side
    max_length_m: float | None = None  # default: the board's diagonal, or 4x the pattern
    # RANSAC line tolerance at the least; widened to LINE_BAND_SIGMAS x the range noise
    inlier_m: float = 0.02
    # The lidar's range noise (1 sigma, m) that sets the bands the board's points are taken
    # in; None: measured from the scans (board_lines.range_noise).
    range_noise_m: float | None = None
    seed: int = 0
    # "forward": without --init, assume the laser looks where the camera does (laser x
    # along the optical axis, z up) to pick segments and as a weak prior; "any": no guess.
    mount: str = "forward"

    def lengths(self, board: BoardSpec) -> tuple[float, float]:
        w, h = board.pattern_extent
        lo = self.min_length_m if self.min_length_m is not None else 0.5 * min(w, h)
        if self.max_length_m is not None:
            hi = self.max_length_m
        elif board.size is not None:
            hi = float(np.hypot(*board.size)) * 1.1
        else:
            hi = max(4.0 * float(np.hypot(w, h)), 1.0)
        return lo, hi


@dataclass
class ViewCandidate:
    """An image/scan pair whose image shows the board."""

    name: str
    detection: Detection
    scan: StampedScan
    dt: float


@dataclass
class ExtrinsicRun:
    """Everything ``run_extrinsic`` found, for reports and the YAML/JSON outputs."""

    result: ExtrinsicResult
    loo: LeaveOneOut | None
    views: list[View]
    candidates: list[ViewCandidate]
    skipped: dict[str, str] = field(default_factory=dict)  # image/view -> why not used
    board: BoardSpec | None = None
    bands: NoiseBands | None = None

    def summary(self) -> dict[str, Any]:
        r = self.result
        out: dict[str, Any] = {
            "reliable": r.reliable,
            "unreliable_because": r.unreliable,
            "board_normal_spread_deg": r.normal_spread_deg,
            "views_used": len(r.views_used),
            "views_rejected": r.views_rejected,
            "images_skipped": self.skipped,
            "residual_rms_m": r.residual_rms_m,
            "per_view_rms_m": r.per_view_rms_m,
            "points_on_board": r.n_points,
            "std_rotation_deg": [float(v) for v in r.std_rotation_deg],
            "std_translation_m": [float(v) for v in r.std_translation_m],
            "std_axes": "camera optical x (right), y (down), z (forward)",
            "weak_directions": [w.description for w in r.weak_directions],
            "initialisation": r.init_method,
            "refinement": r.refinement,
            "warnings": r.warnings,
        }
        if self.loo is not None:
            out["leave_one_out"] = {
                "rotation_spread_deg": self.loo.rotation_spread_deg,
                "translation_spread_m": self.loo.translation_spread_m,
                "rotation_std_deg": [float(v) for v in self.loo.rotation_std_deg],
                "translation_std_m": [float(v) for v in self.loo.translation_std_m],
                "per_view_rotation_deg": self.loo.rotation_deg,
                "per_view_translation_m": self.loo.translation_m,
            }
        if self.board is not None:
            out["board"] = {"inner_corners": [self.board.cols, self.board.rows],
                            "square_m": self.board.square}
        if self.bands is not None:
            out["lidar_range_noise_m"] = self.bands.noise_m
            out["lidar_range_noise_source"] = self.bands.source
            out["board_line_band_m"] = self.bands.line_m
            out["board_reselect_band_m"] = self.bands.reselect_m
        return out


# ---------------------------------------------------------------------------- inputs


@dataclass
class ImageSource:
    paths: list[Path]
    stamps: np.ndarray  # [I] seconds


def images_from_folder(folder: Path, stamp_unit: str = "auto") -> ImageSource:
    paths = list_images(folder)
    stamps = np.array([stamp_from_name(p, stamp_unit) for p in paths])  # [I]
    refuse_same_stamps(Path(folder), [p.name for p in paths], stamps, "images")
    return ImageSource(paths, stamps)


def detect_all(images: ImageSource, board: BoardSpec, camera: PinholeCamera | None,
               camera_source: str = "camera YAML", min_found: int = MIN_VIEWS) -> (
    tuple[dict[int, Detection], dict[str, str]]
):
    """Detect the board in every image; raise if it is found in fewer than ``min_found``.

    Image size is checked against the camera on every image, since a wrong camera YAML
    gives plausible-looking but wrong planes rather than an obvious failure.
    """
    found: dict[int, Detection] = {}
    missed: dict[str, str] = {}
    first_image = None
    n = len(images.paths)
    step = max(1, n // 10)  # about 0.35 s an image without a board: say how far it is
    for i, p in enumerate(images.paths):
        if n > 20 and i % step == 0:
            progress_log.info("board detection: %d/%d images, board found in %d", i, n,
                              len(found))
        img = read_image(p)
        if first_image is None:
            first_image = img
        h, w = img.shape[:2]
        if camera is not None:
            check_image_size(camera, camera_source, p, (w, h))
        det = detect_corners(img, board, name=p.name)
        if det is None:
            missed[p.name] = f"no {board.cols}x{board.rows} board found"
        else:
            found[i] = det
    folder = images.paths[0].parent if images.paths else "?"
    if not found:
        hint = board_hint(first_image, board) if first_image is not None else ""
        raise BoardError(f"no {board} found {found_in(0, len(images.paths))} in "
                         f"{folder}.{hint}")
    if len(found) < min_found:
        names = ", ".join(d.name for d in found.values())
        if missed and first_image is not None:
            hint = board_hint(first_image, board)
        else:  # every image shows the board: there are just too few of them
            hint = (" Each board gives two constraints on the extrinsic's six unknowns; "
                    "capture more views (10 or more), the board leaned forward and back and "
                    "turned left and right by 20-45 degrees.")
        raise BoardError(f"the {board} was found {found_in(len(found), len(images.paths))} "
                         f"in {folder} ({names}); at least "
                         f"{min_found} views are needed.{hint}")
    return found, missed


def pair_views(images: ImageSource, detections: dict[int, Detection], scans: list[StampedScan],
               max_dt: float, skip_unpaired: bool) -> tuple[list[ViewCandidate], dict[str, str]]:
    """Image/scan pairs of the images that show the board."""
    idx = sorted(detections)
    stamps = images.stamps[idx]
    scan_stamps = np.array([s.stamp for s in scans])
    pairs, unpaired = pair_by_stamp(stamps, scan_stamps, max_dt)
    names = [images.paths[i].name for i in idx]
    skipped: dict[str, str] = {}
    if unpaired:
        msg = describe_unpaired(unpaired, names, stamps, scan_stamps, max_dt)
        if not skip_unpaired or not pairs:
            raise PairingError(msg)
        log.warning(msg)
        for k in unpaired:
            skipped[names[k]] = f"no scan within {max_dt * 1000:.0f} ms"
    cands = [ViewCandidate(names[p.image_index], detections[idx[p.image_index]],
                           scans[p.scan_index], p.dt) for p in pairs]
    return cands, skipped


# ---------------------------------------------------------------------------- board points


def mount_guess(search: BoardSearch, init: np.ndarray | None) -> np.ndarray | None:
    """[4, 4] T_camera_laser guess: the given one, the forward mount, or None."""
    if init is not None:
        return init
    if search.mount == "forward":
        return se3(R_CAMERA_LASER_NOMINAL)
    if search.mount == "any":
        return None
    raise ValueError(f"mount {search.mount!r}: use 'forward' or 'any'")


def _expectation(view_plane: Any, board: BoardSpec, search: BoardSearch,
                 guess: np.ndarray | None) -> BoardExpectation:
    T = view_plane.T_camera_board
    c = T[:3, :3] @ board.center + T[:3, 3]
    rng = float(np.linalg.norm(c))
    inc = float(np.arccos(np.clip(abs(view_plane.normal @ c) / rng, 0.0, 1.0)))
    lo, hi = search.lengths(board)
    win = None
    if search.angle_window_deg is not None:
        win = (math.radians(search.angle_window_deg[0]), math.radians(search.angle_window_deg[1]))
    bearing = None
    distance = view_plane.distance
    if guess is not None:
        c_l = (inv_se3(guess) @ np.r_[c, 1.0])[:3]  # the board's middle, laser frame
        if win is None:
            bearing = float(np.arctan2(c_l[1], c_l[0]))
        # The scan sees the board as the line where the laser plane cuts it: compare the
        # segments with that line's offset and in-plane incidence, not the plane's 3D
        # distance and incidence (a leaned board's differ by 0.4 m and 20 deg, and a wall
        # matching the 3D figures was taken for it).
        n_l = guess[:3, :3].T @ view_plane.normal  # board normal, laser frame
        s = float(np.hypot(n_l[0], n_l[1]))
        if s > 0.3:  # the laser plane cuts the board at a usable angle
            distance = (view_plane.distance - view_plane.normal @ guess[:3, 3]) / s
            inc = float(np.arccos(np.clip(abs(n_l[:2] @ c_l[:2]) / s
                                          / max(float(np.hypot(*c_l[:2])), 1e-9), 0.0, 1.0)))
    return BoardExpectation(float(distance), rng, inc, lo, hi, search.max_offset_m, win,
                            bearing, expected_length_m=min(board.pattern_extent))


def _points_from_segments(cand: ViewCandidate, plane: Any, board: BoardSpec,
                          search: BoardSearch, guess: np.ndarray | None) -> (
    tuple[np.ndarray | None, str]
):
    """[K] indices of the scan points of the segment that best matches the board."""
    pts = cand.scan.points
    keep = np.arange(len(pts))
    if search.angle_window_deg is not None:
        a = np.degrees(np.arctan2(pts[:, 1], pts[:, 0]))
        lo, hi = search.angle_window_deg
        keep = np.nonzero(in_bearing_window(a, lo, hi, 360.0))[0]
        pts = pts[keep]
    segs = extract_segments(pts, seed=search.seed, inlier_m=search.inlier_m)
    seg, why = select_board_segment(segs, _expectation(plane, board, search, guess))
    if seg is None:
        return None, why
    return keep[seg.indices], ""


def _points_from_prediction(cand: ViewCandidate, plane: Any, board: BoardSpec,
                            T_camera_laser: np.ndarray, tol_m: float,
                            search: BoardSearch) -> np.ndarray:
    """[K] indices of the scan points on the board plane ``T_camera_laser`` predicts."""
    T_lc = inv_se3(T_camera_laser)
    n_l = T_lc[:3, :3] @ plane.normal
    off_l = plane.distance - plane.normal @ T_camera_laser[:3, 3]
    c_cam = plane.T_camera_board[:3, :3] @ board.center + plane.T_camera_board[:3, 3]
    c_l = T_lc[:3, :3] @ c_cam + T_lc[:3, 3]
    _, hi = search.lengths(board)
    return points_near_plane(cand.scan.points, n_l, off_l, c_l, tol_m, 0.5 * hi + 0.1)


def build_views(cands: list[ViewCandidate], board: BoardSpec, camera: PinholeCamera,
                search: BoardSearch, T_camera_laser: np.ndarray | None = None,
                tol_m: float = 0.03, guess: np.ndarray | None = None) -> (
    tuple[list[View], dict[str, str]]
):
    """Views with their board points: from segments (near where ``guess`` puts the
    board), or, given ``T_camera_laser``, from the predicted plane."""
    views: list[View] = []
    skipped: dict[str, str] = {}
    for c in cands:
        plane_view = make_view(c.name, c.detection.corners, board, camera, np.zeros((0, 2)))
        check_board_distance(c.name, plane_view.plane.distance, board)
        if len(c.scan.points) == 0:
            # All NaN, infinite or at the origin: no board search or plane can say more.
            pts, why = None, "no finite points in the file"
        elif T_camera_laser is None:
            pts, why = _points_from_segments(c, plane_view.plane, board, search, guess)
        else:
            pts = _points_from_prediction(c, plane_view.plane, board, T_camera_laser, tol_m,
                                          search)
            why = "no scan points near the predicted board plane"
        if pts is None or len(pts) < 5:
            skipped[c.name] = f"scan {Path(c.scan.source).name}: {why}"
            continue
        plane_view.points = c.scan.points[pts]
        if board.size is not None and T_camera_laser is not None:
            plane_view.edges, plane_view.edge_sigma = board_edge_points(c.scan.points, pts)
        views.append(plane_view)
    return views, skipped


# A board the camera resolves into corners stands between these distances; a square size
# given in millimetres (50 for 0.05) puts it a thousand times too far.
BOARD_DISTANCE_M = (0.05, 20.0)


def check_board_distance(name: str, distance_m: float, board: BoardSpec) -> None:
    """A ``BoardError`` suggesting the unit slip when a board at ``distance_m`` (in units
    of ``board.square``) cannot be one a camera resolves."""
    lo, hi = BOARD_DISTANCE_M
    if lo <= distance_m <= hi:
        return
    # The distance scales with the square size: suggest the unit slip (mm or cm given as
    # metres, or the reverse) that puts the board nearest a typical 1.5 m.
    factors = (1e-3, 1e-2) if distance_m > hi else (1e2, 1e3)
    f = min(factors, key=lambda k: abs(math.log(distance_m * k / 1.5)))
    raise BoardError(
        f"{name}: with --square {board.square:g} the board comes out {distance_m:.3g} m from "
        f"the camera, outside {lo:g}-{hi:g} m. --square is the side of one square in metres "
        f"(did you mean --square {board.square * f:g}?).")


# ---------------------------------------------------------------------------- the run


# Half-widths of the bands the board's points are taken in, in range-noise sigmas: RANSAC's
# line band (95 % of a line's returns) and the second pass's band about the predicted plane.
# Fixed at 2 and 3 cm, a lidar with 3 cm of noise had its walls cut into strips that used up
# the segment budget (the board found in 1 of 10 views), or its board points clipped to 80 %
# (19 % in one view) with errors up to 7.9 reported sigmas, marked reliable.
LINE_BAND_SIGMAS = 2.0
RESELECT_BAND_SIGMAS = 3.0


@dataclass
class NoiseBands:
    """The lidar's range noise and the bands it sets (metres)."""

    noise_m: float | None  # None: too few neighbouring beams to measure it
    source: str  # "measured" or "given"
    line_m: float  # RANSAC's line band
    # the second pass's band about the predicted board plane (3 times the first solve's
    # residual RMS where that is more)
    reselect_m: float


def noise_bands(cands: list[ViewCandidate], search: BoardSearch) -> NoiseBands:
    """The bands for ``cands``' scans: from ``search.range_noise_m``, else measured."""
    if search.range_noise_m is not None:
        noise, source = search.range_noise_m, "given"
    else:
        noise, source = range_noise([c.scan.points for c in cands]), "measured"
    sigma = noise or 0.0
    return NoiseBands(noise, source, max(search.inlier_m, LINE_BAND_SIGMAS * sigma),
                      max(0.03, RESELECT_BAND_SIGMAS * sigma))


def run_extrinsic(cands: list[ViewCandidate], board: BoardSpec, camera: PinholeCamera,
                  search: BoardSearch | None = None, options: SolverOptions | None = None,
                  init: np.ndarray | None = None, loo: bool = True) -> ExtrinsicRun:
    """Two passes: board segments chosen by what the camera saw, a first solve; then the
    board points re-selected around each predicted board plane and a final solve."""
    search = search or BoardSearch()
    bands = noise_bands(cands, search)
    search = replace(search, inlier_m=bands.line_m)
    opts = options or SolverOptions()
    if opts.max_offset_m is None:
        opts = SolverOptions(**{**opts.__dict__, "max_offset_m": search.max_offset_m})
    guess = mount_guess(search, init)
    if len(cands) < opts.min_views:
        raise ExtrinsicError(
            f"only {len(cands)} image/scan pairs show the board; at least {opts.min_views} "
            "views are needed (each board gives two constraints on the six unknowns). "
            "Capture more views (10 or more), the board leaned forward and back and turned "
            "left and right by 20-45 degrees.")
    views, skipped = build_views(cands, board, camera, search, guess=guess)
    if len(views) < opts.min_views:
        detail = "; ".join(f"{k}: {v}" for k, v in skipped.items())
        ranges = [np.linalg.norm(c.scan.points, axis=1) for c in cands if len(c.scan.points)]
        if not ranges:
            from calibration.check import name_list

            raise ExtrinsicError(
                f"none of the {len(cands)} paired scans holds a finite point "
                f"({name_list([Path(c.scan.source).name for c in cands])}): every value "
                "is NaN, "
                "infinite or at the laser. Check how the scans were exported (a lidar's "
                "no-return value written for every beam?)")
        median = float(np.median(np.concatenate(ranges))) if ranges else 0.0
        # Millimetres read as metres put every board 1000x too far: nothing else says so.
        units = (f" The scans' median range is {median:.0f}: are they in millimetres? "
                 "Scans are read in metres; convert them." if median > 100.0 else "")
        raise ExtrinsicError(
            f"the board was found in the scans of only {len(views)} of {len(cands)} paired "
            f"views ({detail}); at least {opts.min_views} are needed.{units} Pass "
            "--angle-window MIN "
            "MAX (degrees, laser frame, e.g. 150 210 behind it) around the board's "
            "direction, --mount any (or --init) if the laser's 0 deg does not point where "
            "the camera looks (a lidar mounted turned), --max-offset if the sensors are far "
            "apart, --board-size, and check --square (the size of one square in metres).")
    first = _solve_naming_skipped(skipped, views, guess, opts, camera)
    tol = max(bands.reselect_m, 3.0 * first.residual_rms_m)
    bands = replace(bands, reselect_m=tol)  # as used, for the summary
    views2, skipped2 = build_views(cands, board, camera, search, first.T_camera_laser, tol)
    if len(views2) >= opts.min_views:
        # Same data, better points: no need to search for a start again.
        opts2 = SolverOptions(**{**opts.__dict__, "multistart": False})
        result = _solve_naming_skipped(skipped2, views2, guess, opts2, camera,
                                       start=first.T_camera_laser, outline=board.outline())
        views, skipped = views2, skipped2
    else:
        result = first
    stab = leave_one_out(views, result, opts, camera, board.outline()) if loo else None
    if stab is not None:
        warning = leave_one_out_warning(result, stab)
        if warning is not None:
            result.warnings.append(warning)
    return ExtrinsicRun(result, stab, views, cands, skipped, board, bands)


def _solve_naming_skipped(skipped: dict[str, str], views: list[View], *args: Any,
                          **kwargs: Any) -> ExtrinsicResult:
    """``calibrate_extrinsic``, its errors naming the paired views that gave no board
    points: the solve knows only the views it was given."""
    try:
        return calibrate_extrinsic(views, *args, **kwargs)
    except ExtrinsicError as e:
        if not skipped:
            raise
        raise ExtrinsicError(f"{e} Not in the solve: {left_out_text(skipped)}.") from e


def load_candidates(images_dir: Path, scans_src: Path, board: BoardSpec, camera: PinholeCamera,
                    camera_source: str = "the camera given", max_dt: float = 0.1,
                    skip_unpaired: bool = False, stamp_unit: str = "auto") -> tuple[
                        list[ViewCandidate], dict[str, str]]:
    """Read images and scans from disk and pair the images that show the board (each image
    with the nearest scan within ``max_dt`` seconds). ``camera_source`` names where the
    camera came from in errors (an image of another size); the second value says why
    images were left out (no board found, no scan near)."""
    images = images_from_folder(images_dir, stamp_unit)
    scans = read_scans(scans_src, stamp_unit)
    if not scans:
        raise MissingInputError(f"{scans_src}: no scans")
    dets, missed = detect_all(images, board, camera, camera_source)
    cands, skipped = pair_views(images, dets, scans, max_dt, skip_unpaired)
    return cands, {**missed, **skipped}


def load_candidates_from_sequence(root: Path, board: BoardSpec, max_dt: float,
                                  skip_unpaired: bool = False, camera: PinholeCamera | None
                                  = None, camera_source: str | None = None) -> tuple[
                                      list[ViewCandidate], dict[str, str], PinholeCamera]:
    """Pairs from a sequence folder (camera from its rig.yaml unless ``camera`` is given,
    read from ``camera_source``: the file a size mismatch is blamed on)."""
    from toolkit.io.sequence import read_sequence

    seq = read_sequence(root)
    if not seq.frames:
        raise MissingInputError(f"{root}: the sequence has no camera frames")
    if not seq.scans:
        raise MissingInputError(f"{root}: the sequence has no scans (scans.npz)")
    cam = camera or seq.rig.camera
    images = ImageSource([f.path for f in seq.frames if f.path is not None],
                         np.array([f.stamp for f in seq.frames]))
    scans = [StampedScan(s.stamp, s.points(), f"{root / 'scans.npz'}[{i}]")
             for i, s in enumerate(seq.scans)]
    source = camera_source if camera is not None and camera_source else str(root / "rig.yaml")
    dets, missed = detect_all(images, board, cam, source)
    cands, skipped = pair_views(images, dets, scans, max_dt, skip_unpaired)
    return cands, {**missed, **skipped}, cam


# ---------------------------------------------------------------------------- check inputs


def spread_pick(n: int, max_frames: int) -> list[int]:
    """Indices of at most ``max_frames`` of ``n`` items, spread evenly, first and last kept."""
    return [int(k) for k in np.unique(np.linspace(0, n - 1, min(max_frames, n)).round())]


def check_frames_from_sequence(root: Path, T_camera_laser: np.ndarray, max_frames: int = 12,
                               max_dt: float = 0.05, depth_dir: Path | None = None,
                               use_gt_depth: bool = True, camera: PinholeCamera | None = None,
                               camera_source: str | None = None) -> tuple[list[Any], Any]:
    """Frames of a sequence for ``check``: evenly spread images with their nearest scans.

    When the sequence has odometry (or ground-truth poses) the scan is moved to the
    image's time, so robot motion between the two stamps is not blamed on the extrinsic.
    ``camera`` (from ``camera_source``, e.g. a ``--rig`` file) must be the images' size,
    and so must depth maps. Returns the frames and the sequence.
    """
    from calibration.check import CheckFrame
    from toolkit.io.depth import read_depth
    from toolkit.io.sequence import read_sequence

    # As check_frames_from_pairs: a mistyped --depth said "no depth map for frame 0".
    if depth_dir is not None and not Path(depth_dir).is_dir():
        raise MissingInputError(f"{depth_dir}: depth folder (--depth) not found")
    seq = read_sequence(root)
    if not seq.frames or not seq.scans:
        raise MissingInputError(f"{root}: check needs camera frames and scans")
    stamps = seq.scan_stamps
    usable = [i for i, f in enumerate(seq.frames)
              if np.min(np.abs(stamps - f.stamp)) <= max_dt]
    if not usable:
        raise PairingError(f"{root}: no camera frame has a scan within {max_dt * 1000:.0f} ms; "
                           "raise --max-dt")
    pick = [usable[k] for k in spread_pick(len(usable), max_frames)]
    traj = seq.odometry
    if traj is None and seq.groundtruth is not None:
        traj = seq.groundtruth.poses_base
    T_bc = seq.rig.T_base_camera
    T_bl = T_bc @ T_camera_laser
    scan_index = [seq.scan_index_at(seq.frames[i].stamp) for i in pick]
    scans = _deskewed([seq.scans[j] for j in scan_index], traj, T_bl, root)
    frames = []
    for i, j, s in zip(pick, scan_index, scans, strict=True):
        f = seq.frames[i]
        p = s.points_3d()
        if traj is not None and len(traj) > 1:
            try:
                Tb = traj.interpolate(np.array([f.stamp, s.stamp]), extrapolate_s=max_dt).poses
                M = inv_se3(T_bl) @ inv_se3(Tb[0]) @ Tb[1] @ T_bl  # laser(ts) -> laser(tf)
                p = p @ M[:3, :3].T + M[:3, 3]
            except ValueError:
                pass  # stamps outside the trajectory: use the scan as it is
        name = f.path.name if f.path else f"frame{i:06d}"
        img = f.image
        if camera is not None:
            check_image_size(camera, camera_source or f"{root / 'rig.yaml'}",
                             f.path or Path(name), (img.shape[1], img.shape[0]))
        depth = None
        if depth_dir is not None:
            depth = _depth_for(depth_dir, f.path, i, read_depth)
            _check_depth_size(depth, img, depth_dir, name)
        elif use_gt_depth and seq.groundtruth is not None and seq.groundtruth.depth_paths:
            depth = seq.groundtruth.depth(i)
        frames.append(CheckFrame(name, img, p, depth, scan_source=f"{root / 'scans.npz'}[{j}]"))
    return frames, seq


def _deskewed(scans: list[LaserScan], traj: Trajectory | None, T_base_laser: np.ndarray,
              root: Path) -> list[LaserScan]:
    """``scans`` with per-beam timing de-skewed along ``traj``, as the fusion does.

    A spinning lidar measures its beams one after another; projected as one instant, the
    sweep of a robot turning at 1 rad/s under a 10 Hz scanner put the exact extrinsic at
    0.42 (depth score) and a 2-degree-wrong one at 0.83, and the check advised rotating it.
    ``T_base_laser`` is the checked extrinsic's: the lever arm of the laser on the base is
    part of what is checked.
    """
    from calibration.check import CheckError
    from toolkit.deskew import deskew_scans, is_swept

    swept = sum(is_swept(s) for s in scans)
    if not swept:
        return scans
    if traj is None or len(traj) < 2:
        raise CheckError(
            f"{root}: {swept} of the {len(scans)} scans checked carry per-beam timing "
            "(scans.npz field 'time_increment': a spinning lidar measures its beams one after "
            "another) and the sequence has no odometry (odometry.tum) or ground-truth poses "
            "to de-skew them with; projected as one instant, the scans of a moving robot land "
            "centimetres off and the score blames the extrinsic. Convert the recording with "
            "its odometry (ingest: rosbag.topics.odometry), or, if the robot stood still, "
            "without beam timing (rosbag: {beam_timing: ignore}); or check on a static "
            "calibration capture (--images/--scans)")
    return deskew_scans(scans, traj, T_base_laser)


def _check_depth_size(depth: np.ndarray, img: np.ndarray, depth_dir: Path, name: str) -> None:
    if depth.shape != img.shape[:2]:
        raise CalibrationFileError(
            f"{depth_dir}: the depth map of {name} is {depth.shape[1]}x{depth.shape[0]} but "
            f"the image is {img.shape[1]}x{img.shape[0]}; give depth maps at the images' "
            "resolution")


def _depth_for(depth_dir: Path, image_path: Path | None, index: int, reader: Any) -> np.ndarray:
    """[H, W] metres of frame ``index`` from ``depth_dir`` (by index or image stem); a file
    that is no depth map is a ``CalibrationFileError`` saying what one is."""
    from toolkit.io.depth import PNG_DEPTH_SCALE

    # A sequence's images are named by index: each name once in the message.
    stems = list(dict.fromkeys(
        [f"{index:06d}"] + ([image_path.stem] if image_path is not None else [])))
    for stem in stems:
        for ext in (".npy", ".png"):
            p = Path(depth_dir) / f"{stem}{ext}"
            if p.exists():
                try:
                    return reader(p)
                except ValueError as e:  # the reader names the file and what it found
                    raise CalibrationFileError(
                        f"{e}. --depth takes [H, W] float32 metres in .npy, or single-channel "
                        f"16-bit PNG at {PNG_DEPTH_SCALE:g} per metre (TUM's scale: a "
                        "millimetre PNG, ROS 16UC1, reads 5x too deep; save it as .npy in "
                        "metres)") from None
    raise MissingInputError(f"{depth_dir}: no depth map for frame {index} (looked for "
                            f"{', '.join(s + '.npy|.png' for s in stems)})")


def check_frames_from_pairs(images_dir: Path, scans_src: Path, camera: PinholeCamera,
                            camera_source: str, max_dt: float, depth_dir: Path | None = None,
                            stamp_unit: str = "auto", max_frames: int = 12) -> list[Any]:
    """Frames for ``check`` from an image folder and a scan folder (a calibration capture),
    with the depth maps of ``depth_dir`` (named by image stem or image index): at most
    ``max_frames`` pairs spread evenly, as on a sequence (a large capture was loaded and
    drawn whole)."""
    from calibration.check import CheckFrame
    from toolkit.io.depth import read_depth
    from toolkit.sensors import load_rgb

    if depth_dir is not None and not Path(depth_dir).is_dir():
        raise MissingInputError(f"{depth_dir}: depth folder (--depth) not found")
    images = images_from_folder(images_dir, stamp_unit)
    scans = read_scans(scans_src, stamp_unit)
    pairs, unpaired = pair_by_stamp(images.stamps, np.array([s.stamp for s in scans]), max_dt)
    if not pairs:
        raise PairingError(describe_unpaired(unpaired, [p.name for p in images.paths],
                                             images.stamps, np.array([s.stamp for s in scans]),
                                             max_dt))
    if unpaired:
        log.warning("check uses %d of %d images; the others have no scan within --max-dt "
                    "%.3g s:\n%s", len(pairs), len(images.paths), max_dt,
                    describe_unpaired(unpaired, [p.name for p in images.paths],
                                      images.stamps, np.array([s.stamp for s in scans]),
                                      max_dt))
    frames = []
    for p in (pairs[k] for k in spread_pick(len(pairs), max_frames)):
        path = images.paths[p.image_index]
        img = load_rgb(path)
        check_image_size(camera, camera_source, path, (img.shape[1], img.shape[0]))
        pts = scans[p.scan_index].points
        depth = None
        if depth_dir is not None:
            depth = _depth_for(Path(depth_dir), path, p.image_index, read_depth)
            _check_depth_size(depth, img, depth_dir, path.name)
        frames.append(CheckFrame(path.name, img, np.c_[pts, np.zeros(len(pts))], depth,
                                 scan_source=scans[p.scan_index].source))
    return frames

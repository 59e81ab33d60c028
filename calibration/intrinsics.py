"""Camera intrinsics from checkerboard views (OpenCV's Zhang-style calibration).

Pure core: ``calibrate_intrinsics`` takes detections (corners per image) and returns the
camera with its errors; reading images is ``detect_folder``'s job. Images whose
reprojection error stands far above the others' (motion blur, a misdetected corner)
are dropped and the calibration redone, and each drop is reported with its reason.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
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
from toolkit.camera import PinholeCamera
from toolkit.errors import InputError

# Distortion models by name: which of k1 k2 p1 p2 k3 are estimated (COLMAP-like names).
MODELS = {
    "pinhole": "no distortion",
    "radial": "k1 k2",
    "opencv": "k1 k2 p1 p2 (COLMAP's OPENCV)",
    "opencv5": "k1 k2 p1 p2 k3 (k3 needs many views reaching the image corners)",
}
_FLAGS = {
    "pinhole": (cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3
                | cv2.CALIB_ZERO_TANGENT_DIST),
    "radial": cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    "opencv": cv2.CALIB_FIX_K3,
    "opencv5": 0,
}
_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
# Boards whose planes all lie within this angle of one another (and, with the principal
# point fixed, of the image plane) leave the focal length open (Zhang's degenerate
# configurations: parallel planes add no constraint). Fronto-parallel views were
# calibrated without a word: six views of a 600 px camera gave fx 772.5 at 0.066 px RMS,
# three gave 101132.8 with a standard deviation of 0.14 px.
MIN_PLANE_SPREAD_DEG = 5.0
# ``keystone`` of the most tilted view: below it no view is in perspective enough to fix
# the focal length (synthetic 600 px camera, 0.2 px noise: a set whose best view reached
# 0.010-0.015 fitted fx 30-40 % off).
MIN_KEYSTONE = 0.01
_TILT_HINT = ("Capture views with the board tilted 20-45 deg in different directions (left, "
              "right, up, down)")


class IntrinsicsError(InputError):
    """Too few usable views, or inconsistent images."""


@dataclass
class IntrinsicsResult:
    camera: PinholeCamera
    rms_px: float  # over all corners of the used images
    per_image_rms_px: dict[str, float]
    used: list[str]
    rejected: dict[str, str] = field(default_factory=dict)  # image -> reason
    model: str = "opencv"
    std: dict[str, float] = field(default_factory=dict)  # fx fy cx cy k1 ... standard deviations
    # image -> distance of the board from the camera, in the units of the square size given
    board_distance_m: dict[str, float] = field(default_factory=dict)

    def info(self) -> dict[str, object]:
        """The block written under ``calibration`` in the camera YAML."""
        return {"rms_px": self.rms_px, "model": self.model, "images_used": len(self.used),
                "per_image_rms_px": self.per_image_rms_px, "rejected": self.rejected,
                "std": self.std}


def calibrate_intrinsics(detections: list[Detection], board: BoardSpec, model: str = "opencv",
                         max_image_rms_px: float | None = None, min_images: int = 3,
                         reject_factor: float = 3.0) -> IntrinsicsResult:
    """Calibrate from detections of one camera (all the same image size).

    An image is rejected when its RMS exceeds ``max_image_rms_px`` if given, else
    ``reject_factor`` times the median of the others (and 0.5 px), one at a time.
    """
    if model not in _FLAGS:
        raise IntrinsicsError(f"model {model!r}: choose one of {', '.join(MODELS)}")
    sizes = {d.image_size for d in detections}
    if len(sizes) > 1:
        count = {s: sum(d.image_size == s for d in detections) for s in sizes}
        common = max(sorted(sizes), key=lambda s: count[s])
        odd = [d.name for d in detections if d.image_size != common]
        raise IntrinsicsError(
            f"images have different sizes {sorted(sizes)}: {len(odd)} not {common[0]}x"
            f"{common[1]} ({', '.join(odd[:5])}{', ...' if len(odd) > 5 else ''}); calibrate "
            "each camera resolution separately")
    dets = list(detections)
    rejected: dict[str, str] = {}
    obj = board.object_points().astype(np.float32)
    while True:
        if len(dets) < min_images:
            # Only the first pass gets here: an image is dropped only while more than
            # min_images remain, so nothing has been rejected yet.
            raise IntrinsicsError(
                f"{len(dets)} usable views; at least {min_images} are needed (10-20 recommended, "
                "with the board tilted and reaching the image corners)")
        size = dets[0].image_size
        flags = _FLAGS[model]
        if len(dets) < 5 and model != "pinhole":
            # Few views cannot separate the principal point from the board poses.
            flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
        rms, K, dist, rvecs, tvecs, std_intr, _, per_view = cv2.calibrateCameraExtended(
            [obj] * len(dets), [d.corners.astype(np.float32).reshape(-1, 1, 2) for d in dets],
            size, None, None, flags=flags, criteria=_CRITERIA)
        per = {d.name: float(e) for d, e in zip(dets, np.ravel(per_view), strict=True)}
        errs = np.array(list(per.values()))
        worst = int(np.argmax(errs))
        others = float(np.median(np.delete(errs, worst))) if len(errs) > 1 else errs[0]
        limit = max_image_rms_px if max_image_rms_px is not None else max(
            reject_factor * others, 0.5)
        if errs[worst] > limit and len(dets) > min_images:
            rejected[dets[worst].name] = (f"reprojection RMS {errs[worst]:.2f} px above the "
                                          f"limit {limit:.2f} px (blur or a misdetected corner)")
            dets.pop(worst)
            continue
        break
    _check_views(dets, board, K, dist, rvecs,
                 fixed_centre=bool(flags & cv2.CALIB_FIX_PRINCIPAL_POINT))
    d5 = np.zeros(5)
    d5[: min(5, dist.size)] = np.ravel(dist)[:5]
    cam = PinholeCamera.from_K(K, size[0], size[1], d5)
    names = ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"]
    std = {n: float(s) for n, s in zip(names, np.ravel(std_intr)[:9], strict=True)}
    dist_m = {d.name: float(np.linalg.norm(t)) for d, t in zip(dets, tvecs, strict=True)}
    return IntrinsicsResult(cam, float(rms), per, [d.name for d in dets], rejected, model, std,
                            dist_m)


def plane_spread_deg(rvecs: list[np.ndarray], with_image_plane: bool = False) -> float:
    """Largest angle in degrees between the board planes of two views (board rotations
    ``rvecs`` [3] each, camera from board), with the image plane among them if asked."""
    normals = np.array([cv2.Rodrigues(np.asarray(r, np.float64))[0][:, 2]
                        for r in rvecs])  # [V, 3] board z in the camera frame
    if with_image_plane:
        normals = np.vstack([normals, [0.0, 0.0, 1.0]])
    # A plane has no side: n and -n are one plane.
    cos = np.clip(np.abs(normals @ normals.T), 0.0, 1.0)  # [V, V]
    return float(np.degrees(np.arccos(cos.min())))


def keystone(corners: np.ndarray, board: BoardSpec) -> float:
    """How much perspective a view of the board shows: sin(tilt) x (half the corner grid's
    diagonal) / (distance of its middle), from the homography of the undistorted corners
    [N, 2] (its projective row does not depend on the focal length or the principal
    point). 0 for a board parallel to the image plane, about 0.1 for one 0.3 m across
    tilted 30 deg at 0.7 m."""
    xy = board.object_points()[:, :2] - board.center[:2]  # [N, 2] board frame, centred
    H, _ = cv2.findHomography(xy, np.asarray(corners, np.float64).reshape(-1, 2), 0)
    if H is None or H[2, 2] == 0:
        return 0.0
    return float(np.hypot(H[2, 0], H[2, 1]) / abs(H[2, 2])
                 * np.linalg.norm(xy, axis=1).max())


def _check_views(dets: list[Detection], board: BoardSpec, K: np.ndarray, dist: np.ndarray,
                 rvecs: list[np.ndarray], fixed_centre: bool) -> None:
    """Refuse views that leave the focal length undetermined (Zhang's degenerate sets).

    No view in perspective (every board parallel to the image plane, or so far that the
    projection is about affine): any focal length fits, with the board's distance in
    proportion. Measured on the homographies, not on the fit's poses: a degenerate fit
    reads distortion as tilt (three fronto-parallel views fitted fx 101132.8 with k1 901
    and boards 48.5 deg apart). Boards all parallel to one another fix fx and fy only
    with the principal point held at the image centre; free, it is undetermined too."""
    und = [cv2.undistortPoints(d.corners.reshape(-1, 1, 2).astype(np.float64), K, dist,
                               P=K).reshape(-1, 2) for d in dets]  # [N, 2] each
    most = max(keystone(u, board) for u in und)
    if most < MIN_KEYSTONE:
        raise IntrinsicsError(
            f"{len(dets)} views: none shows the board in perspective (keystone at most "
            f"{most:.4f}, at least {MIN_KEYSTONE:g} is needed): boards facing the camera "
            "square-on leave the focal length undetermined, and any value fits them. "
            + _TILT_HINT)
    spread = plane_spread_deg(rvecs, with_image_plane=fixed_centre)
    if spread < MIN_PLANE_SPREAD_DEG:
        what = "the image plane and the boards" if fixed_centre else "the boards"
        raise IntrinsicsError(
            f"{len(dets)} views: the planes of {what} differ by at most {spread:.1f} deg "
            f"(at least {MIN_PLANE_SPREAD_DEG:g} deg is needed): parallel boards leave the "
            "focal length undetermined, and any value fits them. " + _TILT_HINT)


def detect_folder(folder: Path, board: BoardSpec, min_images: int = 3) -> (
    tuple[list[Detection], dict[str, str]]
):
    """Detections in every image of ``folder``; the images without a board, with reasons.

    Found in fewer than ``min_images`` (``calibrate_intrinsics``' least), the error names
    the images without it and, from the first of them, a grid size that is there: a wrong
    --board said only "1 usable views", naming neither.
    """
    paths = list_images(folder)
    dets: list[Detection] = []
    missed: dict[str, str] = {}
    first = None
    first_missed = None
    for p in paths:
        img = read_image(p)
        first = img if first is None else first
        d = detect_corners(img, board, name=p.name)
        if d is None:
            missed[p.name] = f"no {board.cols}x{board.rows} board found"
            first_missed = (img, p.name) if first_missed is None else first_missed
        else:
            dets.append(d)
    if not dets:
        hint = board_hint(first, board) if first is not None else ""
        raise BoardError(f"no {board} found {found_in(0, len(paths))} in {folder}.{hint}")
    if len(dets) < min_images and first_missed is not None:
        names = list(missed)
        shown = ", ".join(names[:10]) + (f" and {len(names) - 10} more" if len(names) > 10
                                         else "")
        raise BoardError(
            f"the {board} was found {found_in(len(dets), len(paths))} in "
            f"{folder} ({', '.join(d.name for d in dets)}); at least {min_images} are "
            f"needed, and there is no board found in {shown}."
            + board_hint(first_missed[0], board, first_missed[1]))
    if len(dets) < min_images:
        # The board is in every image, there are just too few of them: without this the
        # error came from calibrate_intrinsics as "1 usable views", naming no folder.
        raise BoardError(
            f"the {board} was found {found_in(len(dets), len(paths))} in {folder} "
            f"({', '.join(d.name for d in dets)}), but at least {min_images} views are "
            "needed; capture more (10-20 recommended, with the board tilted and reaching "
            "the image corners)")
    return dets, missed

"""Pinhole camera with OpenCV's 5-parameter distortion (k1 k2 p1 p2 k3).

Projection is vectorised numpy (the fusion stage projects millions of points) and is
tested against ``cv2.projectPoints``; undistortion goes through OpenCV itself.
The camera frame is optical: x right, y down, z forward.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

log = logging.getLogger(__name__)

# OpenCV's iterative undistortion stops after 5 iterations by default, which leaves
# errors of 1e-3 px on strong lenses; these criteria take it as far as its fixed-point
# iteration goes. Near the corners of a strong barrel lens that iteration does not
# converge at all (k1 = -0.35, k2 = 0.12 at f = 320 px: 156 pixels of 640x480 left
# without a ray, others 0.05 px off), so Newton steps on the model finish the job.
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
_NEWTON_STEPS = 8
# An undistorted ray must project back within this of its pixel (converged rays: 1e-9 px).
UNDISTORT_TOL_PX = 0.05


# Names of this camera's lens model (OpenCV's k1 k2 p1 p2 k3): ``to_dict``'s, ROS
# camera_info's, Kalibr's, and none at all.
PLUMB_BOB_NAMES = frozenset({"pinhole", "plumb_bob", "radtan", "opencv", "opencv k1 k2 p1 p2 k3",
                             "none", ""})


def pixel_index(uv: np.ndarray) -> np.ndarray:
    """Integer pixel index (same shape as ``uv``, int64) of pixel coordinates: pixel k
    covers ``[k - 0.5, k + 0.5)`` (centres on integers, the half-open span
    ``PinholeCamera.in_image`` keeps), so u = 0.5 is in pixel 1. Works on any shape and
    on float32 as well as float64; a subsampled image's pixel is ``pixel_index(uv / stride)``."""
    # Not np.rint: it rounds halves to even (0.5 -> 0, 1.5 -> 2, 2.5 -> 2). Not
    # floor(uv + 0.5) either: the sum rounds 0.49999999999999994 up to 1. The
    # fraction uv - floor(uv) is exact (float32 too) except for uv in (-0.5, 0), where
    # uv + 1 may round but not below 0.5: pixel 0 either way.
    uv = np.asarray(uv)
    f = np.floor(uv)
    return (f + (uv - f >= 0.5)).astype(np.int64)


def plumb_bob_distortion(model: Any, dist: np.ndarray,
                         field: str = "distortion") -> np.ndarray | None:
    """[5] k1 k2 p1 p2 k3 of the coefficients ``dist`` (a count of ``OPENCV_DIST_COUNTS``,
    or fewer) of a lens named ``model``, or None for another model (an equidistant
    fisheye's k1..k4 read as these project hundreds of pixels off at the edge).

    OpenCV's longer lists (8, 12, 14: k4 k5 k6, s1..s4, tx ty) are this model when every
    term past k3 is zero, under a plumb_bob name or rational_polynomial; a non-zero or
    non-finite one is a ``ValueError`` naming ``field`` and the terms. The one rule of the
    camera files and ROS CameraInfo readers, so a lens one takes the other takes too.
    """
    name = "" if model is None else str(model).strip().lower()
    if name != "rational_polynomial" and name not in PLUMB_BOB_NAMES:
        return None
    dist = np.asarray(dist, dtype=np.float64).reshape(-1)
    if not np.isfinite(dist).all():
        raise ValueError(f"field '{field}' holds a non-finite value ({dist.tolist()})")
    tail = np.flatnonzero(dist[5:]) + 5
    if len(tail):
        # Dropped, the terms past k3 would leave every pixel off by what they add.
        extra = ", ".join(f"{field}[{i}] = {dist[i]:g}" for i in tail)
        raise ValueError(
            f"field '{field}' has {len(dist)} coefficients, non-zero past k1 k2 p1 p2 k3 "
            f"({extra}), under distortion model {name or '(none given)'!r}; only the 5-term "
            "plumb_bob model (k1 k2 p1 p2 k3, or a longer OpenCV list with zeros past k3) "
            "is supported. Fix: calibrate with that model (python -m calibration "
            "intrinsics) or undistort the images first")
    return dist[:5]


# How many coefficients OpenCV takes (k1 k2 p1 p2[ k3[ k4 k5 k6[ s1..s4[ tx ty]]]]). Other
# counts are refused rather than padded with zeros: a 3-list is k1 k2 k3 to tools that give
# radial terms only and was read as k1 k2 p1.
OPENCV_DIST_COUNTS = (4, 5, 8, 12, 14)


def distortion_values(value: Any, field: str = "distortion") -> np.ndarray:
    """[N] coefficients of a camera file's distortion list ``value`` (None or empty: none),
    N one of ``OPENCV_DIST_COUNTS``; a ``ValueError`` naming ``field`` for any other count
    or a nested list (``[[k1], [k2], ...]`` was flattened as if it were one row)."""
    if value is None:
        return np.zeros(0)
    arr = np.asarray(value, dtype=np.float64) if not isinstance(value, (str, bytes, dict)) \
        else None
    if arr is None or arr.ndim != 1:
        raise ValueError(f"field '{field}' is {value!r}: give one flat list of numbers "
                         "[k1, k2, p1, p2, k3] (OpenCV order)")
    if len(arr) and len(arr) not in OPENCV_DIST_COUNTS:
        raise ValueError(
            f"field '{field}' has {len(arr)} coefficients {arr.tolist()}; OpenCV's distortion "
            "takes 4, 5, 8, 12 or 14 (k1 k2 p1 p2 k3 ...), and other counts are ambiguous "
            "(3 values are k1 k2 k3 to some tools, k1 k2 p1 to others). Fix: write them in "
            "OpenCV order with zeros, e.g. [k1, k2, 0, 0, k3] for radial k1 k2 k3")
    return arr


# Lower-cased names other tools give the lens distortion or the intrinsic matrix (ROS
# camera_info's D and K, Kalibr / ORB-SLAM's separate coefficients): refused in a camera
# mapping, which reads them only as 'distortion' and fx, fy, cx, cy.
_LENS_KEYS = frozenset({"d", "k", "coeffs", "coefficients", "camera_matrix", "radial",
                        "tangential", "p1", "p2", *(f"k{i}" for i in range(1, 7))})


@dataclass(eq=False)
class PinholeCamera:
    """Intrinsics of one camera: image size, focal lengths, principal point, distortion."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))  # [5] k1 k2 p1 p2 k3

    def __post_init__(self) -> None:
        d = np.zeros(5)
        given = np.asarray([] if self.dist is None else self.dist, dtype=np.float64).reshape(-1)
        if not np.isfinite(given).all():
            raise ValueError(f"distortion {given.tolist()} is not all finite numbers")
        bad = [k for k in ("fx", "fy", "cx", "cy") if not np.isfinite(float(getattr(self, k)))]
        if bad:
            raise ValueError(f"{', '.join(bad)} must be finite numbers")
        if len(given) > 5:
            raise ValueError(f"distortion has {len(given)} coefficients; k1 k2 p1 p2 k3 at most")
        d[: len(given)] = given
        self.dist = d
        for k in ("width", "height"):
            v = getattr(self, k)
            if isinstance(v, bool) or not float(v).is_integer():
                raise ValueError(f"image {k} must be a whole number of pixels, got {v!r}")
        self.width, self.height = int(self.width), int(self.height)
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"focal lengths must be positive, got fx={self.fx} fy={self.fy}")

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, PinholeCamera):
            return NotImplemented
        return (self.width, self.height, self.fx, self.fy, self.cx, self.cy) == (
            other.width, other.height, other.fx, other.fy, other.cx, other.cy
        ) and np.array_equal(self.dist, other.dist)

    __hash__ = None  # type: ignore[assignment]

    # -------------------------------------------------------------- constructors
    @classmethod
    def from_K(
        cls, K: np.ndarray, width: int, height: int, dist: np.ndarray | None = None
    ) -> PinholeCamera:
        """From a [3, 3] intrinsic matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in pixels."""
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"K must be [3, 3], got {K.shape}")
        # A transposed K (cx, cy in the bottom row) read as cx = cy = 0.
        if not np.allclose(K[2], [0, 0, 1]) or abs(K[1, 0]) > 1e-9 * abs(K[1, 1]):
            raise ValueError(f"K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got "
                             f"{K.tolist()}: transposed?")
        if abs(K[0, 1]) > 1e-6 * abs(K[0, 0]):
            log.warning("K has skew %g: this pinhole model has none, it is dropped (pixels "
                        "up to %.2f px off at the image's edge)", K[0, 1],
                        abs(K[0, 1]) * max(K[1, 2], height - 1 - K[1, 2])
                        / max(abs(K[1, 1]), 1e-9))
        return cls(width, height, K[0, 0], K[1, 1], K[0, 2], K[1, 2],
                   np.zeros(5) if dist is None else dist)

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float) -> PinholeCamera:
        """Square pixels, centred principal point, horizontal field of view."""
        f = 0.5 * width / np.tan(np.radians(hfov_deg) / 2)
        return cls(width, height, f, f, (width - 1) / 2, (height - 1) / 2)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PinholeCamera:
        """From the rig/camera YAML mapping (see ``to_dict``). A lens model other than this
        one (``model`` or ``distortion_model``: an equidistant fisheye's k1..k4 read as
        k1 k2 p1 p2 project hundreds of pixels off at the edge) is a ``ValueError``."""
        missing = [k for k in ("width", "height", "fx", "fy", "cx", "cy") if k not in d]
        if missing:
            raise KeyError(f"camera is missing {missing}")
        # A misspelt distortion key (distorsion, distortion_coeffs), or the names other
        # tools give it (ROS's D, Kalibr's and ORB-SLAM's k1 k2 p1 p2), read as no
        # distortion without a word: the corner of a k1 = -0.3 lens 56 px off.
        odd = [k for k in d if ("dist" in str(k).lower() or str(k).lower() in _LENS_KEYS)
               and k not in ("distortion", "distortion_model")]
        if odd:
            raise ValueError(
                f"unknown key(s) {odd}: the lens distortion is read only from 'distortion' "
                "[k1, k2, p1, p2, k3] (OpenCV order; its model: 'distortion_model') and the "
                "intrinsics from fx, fy, cx, cy; under other names the lens would be taken "
                "as undistorted. Fix: write them there (e.g. 'D: [...]' or 'k1: .., k2: .., "
                "p1: .., p2: ..' as 'distortion: [k1, k2, p1, p2, k3]')")
        dist = distortion_values(d.get("distortion"))
        key = "distortion_model" if "distortion_model" in d else "model"
        model = d.get(key)
        coefficients = plumb_bob_distortion(model, dist)
        if coefficients is None:
            raise ValueError(
                f"field '{key}' is {model!r}: the camera model here is OpenCV's plumb_bob "
                "(k1 k2 p1 p2 k3; also named pinhole, radtan, opencv), so these coefficients "
                "cannot be used as they are; calibrate with that model (python -m calibration "
                "intrinsics) or undistort the images first")
        values = {}
        for k in ("width", "height", "fx", "fy", "cx", "cy"):
            v = d[k]
            # YAML gives a quoted "500" as text and an empty field as None; float() of
            # those failed far from the field's name.
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
                raise ValueError(f"camera field '{k}' is {v!r}: give a number"
                                 + (" of pixels" if k in ("width", "height") else ""))
            values[k] = v
        return cls(values["width"], values["height"], values["fx"], values["fy"],
                   values["cx"], values["cy"], coefficients)

    def to_dict(self) -> dict[str, Any]:
        return {
            "model": "pinhole",
            "width": self.width,
            "height": self.height,
            "fx": float(self.fx),
            "fy": float(self.fy),
            "cx": float(self.cx),
            "cy": float(self.cy),
            "distortion": [float(v) for v in self.dist],
        }

    # -------------------------------------------------------------- properties
    @property
    def K(self) -> np.ndarray:
        """[3, 3] intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def size(self) -> tuple[int, int]:
        """(width, height)."""
        return self.width, self.height

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0))

    def undistorted(self) -> PinholeCamera:
        """The same camera without distortion (what ``undistort_image`` produces)."""
        return PinholeCamera(self.width, self.height, self.fx, self.fy, self.cx, self.cy)

    def strided(self, step: int) -> PinholeCamera:
        """The camera of ``image[::step, ::step]`` (pixel j is pixel j * step here; an
        area resize is ``scaled``)."""
        w, h = -(-self.width // step), -(-self.height // step)
        return PinholeCamera(w, h, self.fx / step, self.fy / step, self.cx / step,
                             self.cy / step, self.dist)

    def open3d_K(self) -> np.ndarray:
        """[3, 3] K for Open3D's TSDF integration. Open3D reads the depth pixel
        ``int(u)`` (pixel i spans [i, i + 1)) where this camera puts pixel centres on
        integers, so the principal point moves by +0.5 for that to be the nearest pixel
        (passing K itself put the surface half a pixel off: a slanted plane 3.4 mm off
        on average at 160x120)."""
        K = self.K
        K[0, 2] += 0.5
        K[1, 2] += 0.5
        return K

    def scaled(self, width: int, height: int) -> PinholeCamera:
        """The camera for the image resized to ``width`` x ``height`` (pixel-centre aware)."""
        sx, sy = width / self.width, height / self.height
        return PinholeCamera(width, height, self.fx * sx, self.fy * sy,
                             (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5, self.dist)

    # -------------------------------------------------------------- geometry
    def distort_normalized(self, xy: np.ndarray) -> np.ndarray:
        """Apply the distortion model to normalised coordinates [N, 2]."""
        k1, k2, p1, p2, k3 = self.dist
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return np.stack([xd, yd], -1)

    def max_radius2(self) -> float:
        """Squared normalised radius up to which the radial distortion grows with the
        radius (inf when it always does). Past it (k2 or k3 < 0) the model turns back:
        a ray 40 deg off-axis can land inside the image next to one at 30 deg."""
        k1, k2, _, _, k3 = self.dist
        # d(r * (1 + k1 r^2 + k2 r^4 + k3 r^6)) / dr = 1 + 3 k1 s + 5 k2 s^2 + 7 k3 s^3, s = r^2
        roots = np.roots(np.trim_zeros([7.0 * k3, 5.0 * k2, 3.0 * k1, 1.0], "f"))
        s = [r.real for r in np.atleast_1d(roots) if abs(r.imag) < 1e-12 and r.real > 0]
        return float(min(s)) if s else float("inf")

    def project(self, points_cam: np.ndarray, past_peak: bool = False) -> (
            tuple[np.ndarray, np.ndarray]):
        """Pixels [N, 2] and depths z [N] of camera-frame points [N, 3].

        Points with z <= 0, or beyond the radius where the distortion model turns back
        (``max_radius2``), get NaN pixels; check ``in_image`` before indexing.
        ``past_peak``: project those too, where the model folds them back (an optimiser
        whose iterate strays there needs finite residuals).
        """
        P = np.asarray(points_cam, dtype=np.float64)
        if P.ndim != 2 or P.shape[1] != 3:
            raise ValueError(f"points_cam must be [N, 3] camera-frame points, got shape "
                             f"{P.shape} (a scan's points() are [N, 2] in the laser frame: "
                             f"transform_points(rig.T_camera_laser, scan.points_3d()))")
        z = P[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = P[:, :2] / z[:, None]
        xy[z <= 0] = np.nan
        if self.has_distortion:
            if not past_peak:
                with np.errstate(invalid="ignore"):
                    xy[(xy * xy).sum(1) >= self.max_radius2()] = np.nan
            xy = self.distort_normalized(xy)
        uv = np.empty_like(xy)
        uv[:, 0] = self.fx * xy[:, 0] + self.cx
        uv[:, 1] = self.fy * xy[:, 1] + self.cy
        return uv, z

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """[N] bool: pixel centres inside the image (pixel (0,0) spans [-0.5, 0.5])."""
        return self.in_image_uv(uv[:, 0], uv[:, 1], margin)

    def in_image_uv(self, u: np.ndarray, v: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """``in_image`` of pixel columns ``u`` [N] and rows ``v`` [N] given apart."""
        with np.errstate(invalid="ignore"):
            return (
                (u >= -0.5 + margin)
                & (u < self.width - 0.5 - margin)
                & (v >= -0.5 + margin)
                & (v < self.height - 0.5 - margin)
            )

    def undistort_points(self, uv: np.ndarray) -> np.ndarray:
        """Normalised undistorted coordinates [N, 2] (z = 1 plane) of distorted pixels [N, 2];
        NaN for pixels no ray reaches through the distortion model."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        if not self.has_distortion:
            return np.stack([(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy], -1)
        if len(uv) == 0:
            # cv2.undistortPoints returns None for no points: a frame whose lidar returns all
            # fall outside the image would stop the run.
            return np.zeros((0, 2))
        out = cv2.undistortPoints(
            uv.reshape(-1, 1, 2), self.K, self.dist, None, None, None, _UNDISTORT_CRITERIA
        ).reshape(-1, 2)
        target = np.stack([(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy], -1)
        out = np.where(np.isfinite(out), out, target)
        with np.errstate(invalid="ignore"):
            off = ~(np.abs(self.distort_normalized(out) - target).max(1) <= 1e-12)
        if off.any():
            out[off] = self._newton_undistort(out[off], target[off])
        # With k3 < 0 (or k2 < 0) the distorted radius peaks and turns back: pixels beyond
        # that peak come from no ray, and OpenCV returns its unconverged iterate for them
        # (on the ACFR calibration a corner pixel's "ray" projected 40 px away). A ray
        # that does not project back onto its pixel is none.
        back, _ = self.project(np.concatenate([out, np.ones((len(out), 1))], -1))
        with np.errstate(invalid="ignore"):
            out[~(np.abs(back - uv).max(axis=1) <= UNDISTORT_TOL_PX)] = np.nan
        return out

    def _newton_undistort(self, xy: np.ndarray, target: np.ndarray) -> np.ndarray:
        """Normalised points [N, 2] that distort onto ``target`` [N, 2], by Newton steps
        from ``xy`` [N, 2] with the model's analytic Jacobian. A step is taken only where it
        lowers the error and stays inside the distortion's peak (``max_radius2``): near the
        peak the Jacobian is nearly singular and a full step can cross it."""
        k1, k2, p1, p2, k3 = self.dist
        peak = self.max_radius2()
        x = np.array(xy, dtype=np.float64)  # [N, 2]

        def error(x: np.ndarray) -> np.ndarray:
            return self.distort_normalized(x) - target  # [N, 2]

        e = error(x)
        for _ in range(_NEWTON_STEPS):
            u, v = x[:, 0], x[:, 1]
            r2 = u * u + v * v
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            d_radial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
            a = radial + 2.0 * u * u * d_radial + 2.0 * p1 * v + 6.0 * p2 * u  # d xd / dx
            b = 2.0 * u * v * d_radial + 2.0 * p1 * u + 2.0 * p2 * v  # d xd / dy = d yd / dx
            d = radial + 2.0 * v * v * d_radial + 6.0 * p1 * v + 2.0 * p2 * u  # d yd / dy
            det = a * d - b * b
            with np.errstate(divide="ignore", invalid="ignore"):
                step = np.stack([d * e[:, 0] - b * e[:, 1], a * e[:, 1] - b * e[:, 0]], -1)
                cand = x - step / det[:, None]
                e_cand = error(cand)
                better = ((np.abs(e_cand).max(1) < np.abs(e).max(1))
                          & ((cand * cand).sum(1) < peak))
            x[better], e[better] = cand[better], e_cand[better]
        return x

    def undistort_pixels(self, uv: np.ndarray) -> np.ndarray:
        """Pixels [N, 2] in the undistorted image of ``undistorted()``."""
        xy = self.undistort_points(uv)
        return np.stack([self.fx * xy[:, 0] + self.cx, self.fy * xy[:, 1] + self.cy], -1)

    def backproject(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Camera-frame points [N, 3] of pixels [N, 2] at z-depth [N] (not ray length)."""
        xy = self.undistort_points(uv)
        z = np.asarray(depth, dtype=np.float64).reshape(-1)
        return np.concatenate([xy * z[:, None], z[:, None]], -1)

    def pixel_rays(self) -> np.ndarray:
        """[H, W, 3] rays with z = 1 through every pixel centre (undistorted); NaN where no
        ray reaches the pixel (``undistort_points``)."""
        u, v = np.meshgrid(np.arange(self.width, dtype=np.float64),
                           np.arange(self.height, dtype=np.float64))
        xy = self.undistort_points(np.stack([u.ravel(), v.ravel()], -1))
        rays = np.concatenate([xy, np.ones((len(xy), 1))], -1)
        return rays.reshape(self.height, self.width, 3)

    def backproject_depth(self, depth: np.ndarray) -> np.ndarray:
        """[H, W, 3] camera-frame points of a z-depth image [H, W]."""
        if depth.shape != (self.height, self.width):
            raise ValueError(f"depth is {depth.shape[::-1]} (WxH) but the camera is "
                             f"{self.width}x{self.height}")
        return self.pixel_rays() * depth[..., None]

    def undistort_image(self, image: np.ndarray, interpolation: int = cv2.INTER_LINEAR) -> (
        np.ndarray
    ):
        """The image as the distortion-free camera ``undistorted()`` would see it."""
        if not self.has_distortion:
            return image
        return cv2.undistort(image, self.K, self.dist, None, self.K) if (
            interpolation == cv2.INTER_LINEAR
        ) else self._remap(image, interpolation)

    def _remap(self, image: np.ndarray, interpolation: int) -> np.ndarray:
        m1, m2 = cv2.initUndistortRectifyMap(self.K, self.dist, None, self.K, self.size,
                                             cv2.CV_32FC1)
        return cv2.remap(image, m1, m2, interpolation)

    # -------------------------------------------------------------- conversions
    def to_open3d(self) -> Any:
        """``open3d.camera.PinholeCameraIntrinsic`` (distortion must be removed first)."""
        import open3d as o3d

        return o3d.camera.PinholeCameraIntrinsic(self.width, self.height, self.fx, self.fy,
                                                 self.cx, self.cy)

    def to_colmap(self) -> tuple[str, list[float]]:
        """COLMAP model name and parameter list: PINHOLE, or OPENCV when distorted.

        COLMAP puts pixel centres at +0.5 (the image's top-left corner is the origin) where
        OpenCV puts them at integers, so the principal point is written as cx + 0.5,
        cy + 0.5. COLMAP's OPENCV model has no k3; a camera with k3 != 0 maps to FULL_OPENCV.
        """
        base = [float(self.fx), float(self.fy), float(self.cx) + 0.5, float(self.cy) + 0.5]
        k1, k2, p1, p2, k3 = (float(v) for v in self.dist)
        if not self.has_distortion:
            return "PINHOLE", base
        if k3 == 0.0:
            return "OPENCV", base + [k1, k2, p1, p2]
        return "FULL_OPENCV", base + [k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]

    def colmap_line(self, camera_id: int = 1) -> str:
        """One ``cameras.txt`` line: CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]."""
        model, params = self.to_colmap()
        return " ".join([str(camera_id), model, str(self.width), str(self.height),
                         *(repr(p) for p in params)])

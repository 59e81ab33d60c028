"""Camera - 2D lidar extrinsic from views of a planar board (Zhang & Pless, IROS 2004).

For every view the camera gives the board's plane ``n . q = d`` in the camera frame
(PnP on the checkerboard corners) and the scan gives points ``p`` on that board in the
laser frame. The extrinsic ``T_camera_laser = [R | t]`` must put those points on the
plane: ``n . (R p + t) - d = 0``. This module solves that:

1. a linear initialisation (Zhang & Pless' ``H = [r1 r2 t]`` least squares) and a guess of
   the mount; when neither fits every view, the 24 axis-aligned mounts as further starts;
   the start with the lowest robust cost wins;
2. a refinement of the point-to-plane distances under a robust loss
   (``scipy.optimize.least_squares``), then a joint maximum-likelihood refinement of the
   extrinsic with every board pose (corner reprojection errors + point-to-plane distances,
   + the scan's end points on the board outline when the board's size is known);
3. rejection of views far off the others (wrong segment picked, board moved between image
   and scan, a scan paired with another view's image): with 6 views or more, when the fit
   of all views leaves a view beyond its noise, first by consensus (fits of four-view
   subsets, the set of views that agree with one chosen by a truncated cost); then each
   view also judged against the fit of the other views without them; fewer than 5 views
   left after that is not called reliable;
4. the covariance from the Jacobian, and the directions the views leave unconstrained;
5. checks that the views determine the answer at all (board normals that span all three
   directions, a laser within the allowed offset of the camera) and leave-one-view-out
   stability, compared with the covariance: a near-degenerate set of views fits a wrong
   extrinsic as well as the right one, and the Jacobian at that wrong one is no guide.

Everything here is pure: arrays in, arrays out, no files.

Parameters are expressed as a rotation perturbation ``R = exp([w]x) R0`` about the
*camera* axes plus the translation ``t`` (the laser origin in the camera frame), so that
covariances and weak directions read as "rotation about camera x" and "along camera y".
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from calibration.board import BoardSpec
from calibration.board_lines import fit_line
from toolkit.camera import PinholeCamera
from toolkit.errors import InputError
from toolkit.geometry import rotation_angle, se3

AXIS_NAMES = (
    "rotation about camera x (right: tilt up/down)",
    "rotation about camera y (down: pan left/right)",
    "rotation about camera z (forward: roll)",
    "translation along camera x (right)",
    "translation along camera y (down)",
    "translation along camera z (forward)",
)
SHORT_NAMES = ("rx", "ry", "rz", "tx", "ty", "tz")


class ExtrinsicError(InputError):
    """The views cannot give an extrinsic; the message says what is missing."""


# Each board gives two constraints on the six unknowns: three boards can be fit exactly by
# several extrinsics (the reviewer's three-view sets gave answers 157 degrees off with a
# 3 mm residual); four is the least with any redundancy.
MIN_VIEWS = 4
# Below this many views left after leaving views out the result is not called reliable:
# four views leave two constraints spare, so a wrong view is fitted as well as the right
# ones and the views left out may be the good ones (8 synthetic views with two scans
# swapped: four good views were left out, the swapped pair kept, and the result was 96
# degrees off, marked reliable, with only the warning that four views are few).
MIN_VIEWS_AFTER_REJECTION = 5
# The views' evidence on the offset out of the plane the board normals span grows with the
# sum of the normals' squared components out of it: N boards at an RMS angle a from that
# plane give N sin(a)^2. Below this the estimate and its covariance are set by noise and
# by which basin the solver lands in (analytic generator, 1 cm lidar noise: untilted
# boards, 1-2 degrees, gave 10-99 degree errors against a reported 2-4; five boards at 4-6
# degrees gave 1-7 degree errors, the worst 14 times their reported covariance (NEES 247);
# ten boards at 4-6 degrees stayed within 1-2 standard deviations). 0.05 asks for 5.7
# degrees with 5 views, 4.1 with 10; the capture protocol's 20-45 degree leans give 18-28.
MIN_NORMAL_INFO = 0.05


# ---------------------------------------------------------------------------- board planes


@dataclass
class BoardPlane:
    """A board seen by the camera: its plane ``normal . q = distance`` in the camera frame."""

    normal: np.ndarray  # [3] unit, pointing from the camera towards the board
    distance: float  # metres, > 0
    T_camera_board: np.ndarray  # [4, 4]
    reprojection_rms_px: float

    @property
    def center(self) -> np.ndarray:
        """[3] board frame origin in the camera frame."""
        return self.T_camera_board[:3, 3]


def board_plane(corners: np.ndarray, board: BoardSpec, camera: PinholeCamera) -> BoardPlane:
    """The board's pose and plane from its detected corners [N, 2] (distorted pixels).

    IPPE gives the planar pose without a starting guess (and without the two-fold
    ambiguity iterative PnP can fall into at oblique views); an iterative refinement
    then minimises the reprojection error through the full distortion model.
    """
    obj = board.object_points()  # [N, 3]
    img = np.asarray(corners, dtype=np.float64).reshape(-1, 1, 2)
    ok, rvec, tvec = cv2.solvePnP(obj, img, camera.K, camera.dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise ExtrinsicError("PnP failed on the board corners")
    ok, rvec, tvec = cv2.solvePnP(obj, img, camera.K, camera.dist, rvec, tvec, True,
                                  flags=cv2.SOLVEPNP_ITERATIVE)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, camera.K, camera.dist)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img.reshape(-1, 2)) ** 2, 1))))
    T = se3(cv2.Rodrigues(rvec)[0], tvec.ravel())
    n = T[:3, 2].copy()
    d = float(n @ T[:3, 3])
    if d < 0:
        n, d = -n, -d
    return BoardPlane(n, d, T, rms)


@dataclass
class View:
    """One calibration view: the board plane from the camera, its points from the laser."""

    name: str
    plane: BoardPlane
    points: np.ndarray  # [K, 2] laser frame metres, on the board
    # For the joint refinement: the detected corners and their board-frame coordinates.
    corners: np.ndarray | None = None  # [N, 2] distorted pixels
    object_points: np.ndarray | None = None  # [N, 3] board frame metres
    # Where the scan leaves the board (laser frame) and their sigmas, for boards of
    # known size: these points lie on the board's outline.
    edges: np.ndarray | None = None  # [E, 2] metres
    edge_sigma: np.ndarray | None = None  # [E] metres


def make_view(name: str, corners: np.ndarray, board: BoardSpec, camera: PinholeCamera,
              points: np.ndarray) -> View:
    """A view from detected corners [N, 2] and the board's laser points [K, 2]."""
    return View(name, board_plane(corners, board, camera), np.asarray(points, np.float64),
                np.asarray(corners, np.float64), board.object_points())


# ---------------------------------------------------------------------------- residuals


def _stack(views: list[View]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per point: laser points [M, 3], normals [M, 3], distances [M], view ids [M]."""
    P = np.concatenate([np.c_[v.points, np.zeros(len(v.points))] for v in views])
    N = np.concatenate([np.repeat(v.plane.normal[None], len(v.points), 0) for v in views])
    D = np.concatenate([np.full(len(v.points), v.plane.distance) for v in views])
    ids = np.concatenate([np.full(len(v.points), i) for i, v in enumerate(views)])
    return P, N, D, ids


def point_to_plane(views: list[View], T_camera_laser: np.ndarray,
                   scale: float = 1.0) -> list[np.ndarray]:
    """Signed distances (metres) of each view's laser points to its board plane (the
    plane's distance times ``scale``: a board distance scale fitted to the views)."""
    R, t = T_camera_laser[:3, :3], T_camera_laser[:3, 3]
    out = []
    for v in views:
        q = np.c_[v.points, np.zeros(len(v.points))] @ R.T + t  # [K, 3]
        out.append(q @ v.plane.normal - scale * v.plane.distance)
    return out


def _jacobian(P: np.ndarray, N: np.ndarray, R: np.ndarray) -> np.ndarray:
    """[M, 6] d residual / d (w, t) at w = 0 for ``R = exp([w]x) R``.

    n . (exp(w) q + t) changes by n . (w x q) = w . (q x n), q = R p.
    """
    q = P @ R.T
    return np.concatenate([np.cross(q, N), N], axis=1)


@dataclass
class _Problem:
    P: np.ndarray  # [M, 3]
    N: np.ndarray  # [M, 3]
    D: np.ndarray  # [M]
    sigma_m: float
    prior: tuple[np.ndarray, float, float] | None  # (T0, sigma_rot_rad, sigma_t_m)


def _solve(prob: _Problem, T0: np.ndarray, loss: str, f_scale: float, max_nfev: int) -> (
    tuple[np.ndarray, float]
):
    """Refine from ``T0``; returns the transform and the final robust cost."""
    R0 = T0[:3, :3].copy()
    t0 = T0[:3, 3].copy()
    cost = np.inf
    # Re-linearise around the current rotation so the analytic Jacobian (exact at w = 0)
    # is exact at the end, where the covariance is read.
    for _ in range(4):
        # R0 relative to the prior's rotation, so each call composes two rotations
        # instead of decomposing a matrix.
        rel = (Rotation.from_matrix(R0 @ prob.prior[0][:3, :3].T)
               if prob.prior is not None else None)

        def fun(x: np.ndarray, R0: np.ndarray = R0, rel: Rotation | None = rel) -> np.ndarray:
            w = Rotation.from_rotvec(x[:3])
            R = w.as_matrix() @ R0
            r = ((prob.P @ R.T + x[3:]) * prob.N).sum(1) - prob.D
            res = [r / prob.sigma_m]
            if prob.prior is not None and rel is not None:
                Tp, s_r, s_t = prob.prior
                res.append((w * rel).as_rotvec() / s_r)
                res.append((x[3:] - Tp[:3, 3]) / s_t)
            return np.concatenate(res)

        def jac(x: np.ndarray, R0: np.ndarray = R0) -> np.ndarray:
            R = Rotation.from_rotvec(x[:3]).as_matrix() @ R0
            J = [_jacobian(prob.P, prob.N, R) / prob.sigma_m]
            if prob.prior is not None:
                _, s_r, s_t = prob.prior
                J.append(np.c_[np.eye(3) / s_r, np.zeros((3, 3))])
                J.append(np.c_[np.zeros((3, 3)), np.eye(3) / s_t])
            return np.concatenate(J)

        sol = least_squares(fun, np.r_[0.0, 0.0, 0.0, t0], jac=jac, loss=loss,
                            f_scale=f_scale, method="trf", x_scale="jac", max_nfev=max_nfev)
        R0 = Rotation.from_rotvec(sol.x[:3]).as_matrix() @ R0
        t0 = sol.x[3:]
        cost = float(sol.cost)
        if np.linalg.norm(sol.x[:3]) < 1e-10:
            break
    return se3(R0, t0), cost


# ---------------------------------------------------------------------------- initialisation


def linear_init(views: list[View]) -> np.ndarray | None:
    """Zhang & Pless' linear estimate, or None when the views do not determine it.

    With laser points ``(x, y, 0)`` the camera point is ``H [x y 1]^T``, ``H = [r1 r2 t]``,
    and every point gives one linear equation ``n^T H p = d`` in the nine entries of H.
    """
    P, N, D, _ = _stack(views)
    A = np.concatenate([P[:, :1] * N, P[:, 1:2] * N, N], axis=1)  # [M, 9]
    if len(A) < 9:
        return None
    h, *_ = np.linalg.lstsq(A, D, rcond=None)
    H = h.reshape(3, 3).T  # columns h1 h2 h3
    h1, h2 = H[:, 0], H[:, 1]
    if np.linalg.norm(h1) < 1e-6 or np.linalg.norm(h2) < 1e-6:
        return None
    M = np.c_[h1, h2, np.cross(h1, h2)]
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    return se3(R, _translation_given_rotation(P, N, D, R))


def _translation_given_rotation(P: np.ndarray, N: np.ndarray, D: np.ndarray,
                                R: np.ndarray) -> np.ndarray:
    """Least-squares t with ``n . t = d - n . R p`` (minimum norm when underdetermined)."""
    t, *_ = np.linalg.lstsq(N, D - ((P @ R.T) * N).sum(1), rcond=None)
    return t


def _axis_aligned_rotations() -> list[np.ndarray]:
    """The 24 proper rotations whose columns are signed unit axes."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            R = np.zeros((3, 3))
            for col, (row, s) in enumerate(zip(perm, signs, strict=True)):
                R[row, col] = s
            if np.linalg.det(R) > 0:
                out.append(R)
    return out


# ---------------------------------------------------------------------------- result


@dataclass
class WeakDirection:
    """A combination of parameters the views hardly constrain."""

    std: float  # in normalised units: 1 = 1 degree or 1 cm
    vector: np.ndarray  # [6] unit, over (rx, ry, rz, tx, ty, tz) in (deg, cm) units
    description: str


@dataclass
class ExtrinsicResult:
    """``T_camera_laser`` and what to think of it."""

    T_camera_laser: np.ndarray  # [4, 4] p_camera_optical = T @ p_laser
    residual_rms_m: float
    per_view_rms_m: dict[str, float]
    views_used: list[str]
    views_rejected: dict[str, str]
    n_points: int
    covariance: np.ndarray  # [6, 6] over (w rad about camera axes, t m); inf where unknown
    weak_directions: list[WeakDirection]
    init_method: str
    refinement: str = "point-to-plane"
    guess: np.ndarray | None = None  # [4, 4] the prior's centre, if any
    warnings: list[str] = field(default_factory=list)
    # Why the views cannot determine the estimate, so that neither it nor its covariance
    # can be trusted (see ``degenerate_views_reason``); empty when the checks pass.
    unreliable: list[str] = field(default_factory=list)
    normal_spread_deg: float = float("nan")  # RMS angle of the normals off a common plane

    @property
    def reliable(self) -> bool:
        return not self.unreliable

    @property
    def std_rotation_deg(self) -> np.ndarray:
        """[3] about camera x, y, z."""
        return np.degrees(np.sqrt(np.diag(self.covariance)[:3]))

    @property
    def std_translation_m(self) -> np.ndarray:
        """[3] along camera x, y, z."""
        return np.sqrt(np.diag(self.covariance)[3:])


def _covariance(info: np.ndarray, weak_std: float) -> tuple[np.ndarray, list[WeakDirection]]:
    """Covariance [6, 6] from the information matrix [6, 6] over (w rad, t m).

    Directions whose standard deviation in (degree, cm) units exceeds ``weak_std`` are
    reported as weak; those with no information at all get an infinite variance rather
    than a pseudo-inverse's misleading zero.
    """
    S = np.diag([math.radians(1.0)] * 3 + [0.01] * 3)  # normalised unit -> (rad, m)
    info_n = S @ info @ S  # [6, 6] in normalised units
    lam, V = np.linalg.eigh(info_n)
    floor = 1e-12 * max(lam.max(), 1e-300)
    inv = np.where(lam > floor, 1.0 / np.maximum(lam, floor), np.inf)
    with np.errstate(invalid="ignore"):
        cov_n = np.zeros((6, 6))
        for k in range(6):
            if np.isinf(inv[k]):
                mask = np.abs(V[:, k]) > 1e-6
                cov_n[np.ix_(mask, mask)] = np.inf
            else:
                cov_n += inv[k] * np.outer(V[:, k], V[:, k])
    cov = S @ cov_n @ S
    weak = []
    for k in np.argsort(-inv):
        std = float(np.sqrt(inv[k]))
        if std <= weak_std:
            continue
        v = V[:, k] * np.sign(V[np.argmax(np.abs(V[:, k])), k])
        parts = [f"{abs(v[j]):.2f} x {SHORT_NAMES[j]}" for j in np.argsort(-np.abs(v))
                 if abs(v[j]) >= 0.25]
        main = AXIS_NAMES[int(np.argmax(np.abs(v)))]
        std_txt = "unconstrained" if math.isinf(std) else f"std {std:.2g} deg|cm"
        weak.append(WeakDirection(std, v, f"{main} ({std_txt}; mix {' + '.join(parts)})"))
    return cov, weak


# ---------------------------------------------------------------------------- solver


@dataclass
class SolverOptions:
    """Settings of ``calibrate_extrinsic`` (defaults suit 1 cm lidar noise)."""

    loss: str = "soft_l1"  # scipy least_squares loss; "linear" for plain least squares
    f_scale_m: float = 0.02  # residual beyond which the robust loss down-weights points
    reject_factor: float = 3.0  # a view is an outlier above this x the others' median RMS
    reject_min_m: float = 0.01  # ... and above this RMS
    # With 5 views or fewer a view above this RMS is rejected outright; one below it only
    # when the others, fit without it, agree within their laser noise (see _outlier_view).
    gross_m: float = 0.05
    min_views: int = MIN_VIEWS
    weak_std: float = 1.0  # report directions with std above 1 degree / 1 cm
    # With a guess (``init``): a weak pull towards it that only decides directions the
    # views leave open; it moves a well-constrained result by a negligible amount. None: off.
    prior_sigma_deg: float | None = 20.0
    prior_sigma_m: float | None = 0.5
    multistart: bool = True
    joint: bool = True  # refine board poses with the extrinsic (needs corners and a camera)
    # How far apart the sensors can be: starts that put the laser farther from the camera
    # lose to any that do not, and a final solution beyond it is an error. None: no limit.
    max_offset_m: float | None = None


def _prior(opts: SolverOptions, guess: np.ndarray | None) -> (
    tuple[np.ndarray, float, float] | None
):
    if guess is None or not opts.prior_sigma_deg or not opts.prior_sigma_m:
        return None
    return guess, math.radians(opts.prior_sigma_deg), float(opts.prior_sigma_m)


def _fit(views: list[View], opts: SolverOptions, guess: np.ndarray | None,
         start: np.ndarray | None = None) -> tuple[np.ndarray, str]:
    """Best refined start: ``start``, ``guess``, linear, then the axis-aligned mounts."""
    P, N, D, _ = _stack(views)
    prob = _Problem(P, N, D, opts.f_scale_m, _prior(opts, guess))
    starts: list[tuple[str, np.ndarray]] = []
    if start is not None:
        starts.append(("previous estimate", start))
    if guess is not None:
        starts.append(("given guess", guess))
    lin = linear_init(views)
    if lin is not None:
        starts.append(("linear (Zhang & Pless)", lin))
    best: tuple[bool, float, np.ndarray, str] | None = None

    def too_far(T: np.ndarray) -> bool:
        return opts.max_offset_m is not None and float(np.linalg.norm(T[:3, 3])) > (
            opts.max_offset_m)

    def try_starts(cands: list[tuple[str, np.ndarray]]) -> None:
        nonlocal best
        for name, T0 in cands:
            T, cost = _solve(prob, T0, opts.loss, 1.0, max_nfev=50)
            far = too_far(T)
            # A solution with the sensors farther apart than they can be loses to any
            # that is not, whatever its cost: with few views a wrong mount can fit better.
            # Earlier starts win ties: with weakly constrained data several starts reach
            # the same cost and the informed one is the better guess.
            if (best is None or far < best[0]
                    or (far == best[0] and cost < best[1] * (1 - 1e-6) - 1e-12)):
                best = (far, cost, T, name)

    try_starts(starts)
    # The axis-aligned mounts are a safety net for a bad linear start (few or similar
    # views, a wrong segment); not needed when a start already fits every view.
    fits = best is not None and not best[0] and bool(
        np.all(_view_rms(views, best[2]) < 3 * opts.f_scale_m))
    if (opts.multistart and not fits) or best is None:
        try_starts([(f"axis-aligned #{k}", se3(R, _translation_given_rotation(P, N, D, R)))
                    for k, R in enumerate(_axis_aligned_rotations())])
    assert best is not None
    T, _ = _solve(prob, best[2], opts.loss, 1.0, max_nfev=200)
    return T, best[3]


def _line_scatter(views: list[View]) -> float:
    """Pooled RMS (metres) of the board points about each view's own fitted line."""
    sq, n = 0.0, 0
    for v in views:
        if len(v.points) > 2:
            _, _, rms = fit_line(v.points)
            sq += rms**2 * len(v.points)
            n += len(v.points)
    return float(np.sqrt(sq / n)) if n else 0.0


def _view_rms(views: list[View], T: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """[V] point-to-plane RMS of each view, metres (``point_to_plane``)."""
    return np.array([np.sqrt(np.mean(r**2)) for r in point_to_plane(views, T, scale)])


def normal_spread(views: list[View]) -> tuple[float, np.ndarray]:
    """How far the board normals leave their best common plane: the RMS angle (degrees)
    and that plane's normal [3] in the camera frame, the direction they do not span.

    Each board fixes the laser's offset only along its normal, and tilts of the scan plane
    only through the normal's component out of it, so normals confined to one plane leave
    the offset along ``direction`` and the tilts that go with it to the noise. The smallest
    eigenvalue of the normals' mean outer product is the mean squared sine of their angle
    to the plane it is orthogonal to.
    """
    N = np.array([v.plane.normal for v in views])  # [V, 3]
    lam, vec = np.linalg.eigh(N.T @ N / len(N))
    return float(np.degrees(np.arcsin(np.sqrt(np.clip(lam[0], 0.0, 1.0))))), vec[:, 0]


def min_normal_spread_deg(n_views: int) -> float:
    """The RMS angle off a common plane that ``n_views`` board normals need."""
    return float(np.degrees(np.arcsin(min(1.0, math.sqrt(MIN_NORMAL_INFO / max(n_views, 1))))))


_CAMERA_AXES = ("camera x (right)", "camera y (down)", "camera z (forward)")


def degenerate_views_reason(views: list[View]) -> str | None:
    """Why the views cannot determine the extrinsic, or None: see ``normal_spread``."""
    spread, u = normal_spread(views)
    need = min_normal_spread_deg(len(views))
    if spread >= need:
        return None
    axis = _CAMERA_AXES[int(np.argmax(np.abs(u)))]
    return (f"the {len(views)} board normals all lie within {spread:.1f} degrees (RMS) of one "
            f"plane (they hardly vary along {axis}; {len(views)} views need {need:.1f}), so "
            "the laser's offset along that axis and the tilts that go with it are set by "
            "noise, and so is the covariance. Capture views with the board leaned forward and "
            "back (about its horizontal axis) as well as turned left and right, 20-45 degrees "
            "each way.")


def _held_by_prior(views: list[View], info: np.ndarray,
                   prior: tuple[np.ndarray, float, float] | None, weak_std: float) -> str | None:
    """A warning to give instead of the unreliable mark, or None: what the views leave open
    is pinned by the prior when, with its information added to the views' ``info`` [6, 6]
    (w rad, t m), every direction's std is within ``weak_std`` (degree, cm).

    That is the remedy for boards that all stand upright: measure the height and pass it
    with --init and a tight --prior-sigma. Judged on the views alone such a result stayed
    unreliable whatever the prior (on the ACFR pairs with 1 deg / 1 cm the leave-one-out
    spread fell from 33 deg / 0.77 m to 1.3 deg / 8 mm, and it was still refused).
    """
    if prior is None:
        return None
    _, s_r, s_t = prior
    info_p = info + np.diag([1.0 / s_r**2] * 3 + [1.0 / s_t**2] * 3)  # [6, 6]
    S = np.diag([math.radians(1.0)] * 3 + [0.01] * 3)  # normalised unit -> (rad, m)
    lam = np.linalg.eigvalsh(S @ info_p @ S)
    worst = float(1.0 / np.sqrt(max(float(lam.min()), 1e-300)))
    if worst > weak_std:
        return None
    spread, u = normal_spread(views)
    what = (f"the laser's offset along {_CAMERA_AXES[int(np.argmax(np.abs(u)))]} and the tilts "
            f"that go with it (the {len(views)} board normals lie within {spread:.1f} degrees "
            f"(RMS) of one plane; {len(views)} views need "
            f"{min_normal_spread_deg(len(views)):.1f})"
            if spread < min_normal_spread_deg(len(views)) else
            "the directions named above as weak")
    return (f"{what} come from your --init prior (--prior-sigma {math.degrees(s_r):g} deg, "
            f"{s_t:g} m), not from the views: they are only as right as that measured guess, "
            "and the views' noise can pull them a few times --prior-sigma away from it (six "
            "untilted boards, the mount given to 1 deg / 1 cm: pitch 1.2-3.9 deg off). With "
            f"the prior every direction's std is at most {worst:.2g} (degree|cm); the std "
            "figures printed are the views' alone. Boards leaned forward and back would "
            "measure them.")


# ---------------------------------------------------------------------------- consensus

# Views in each hypothesis of the consensus search: the least with any redundancy.
CONSENSUS_SUBSET = MIN_VIEWS
# From this many views the views that agree are first sought by consensus. Of five views
# any four can be made to agree, so there the rule in ``_outlier_view`` decides alone.
CONSENSUS_MIN_VIEWS = 6
# Subsets tried: all of them when there are no more than this (8 views: 70), else up to
# this many drawn at random with a fixed seed. With 4 bad views among 15 a quarter of the
# four-view subsets are all good, so 100 draws all miss with probability 1e-12.
CONSENSUS_MAX_SUBSETS = 100


def _plane_residuals(P: np.ndarray, N: np.ndarray, D: np.ndarray, R: np.ndarray,
                     t: np.ndarray) -> np.ndarray:
    """[S, M] point-to-plane residuals of points P [M, 3] under S transforms R [S, 3, 3],
    t [S, 3]."""
    return ((P @ R.transpose(0, 2, 1)) * N).sum(2) + t @ N.T - D


def _fit_many(P: np.ndarray, N: np.ndarray, D: np.ndarray, T0: np.ndarray,
              iterations: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """Plain least-squares point-to-plane fits from S starts T0 [S, 4, 4] at once
    (Levenberg-Marquardt): the transforms [S, 4, 4] and their sums of squares [S].

    For the consensus search, which fits hundreds of four-view subsets assumed clean:
    ``_fit`` took 49 ms a subset (three starts through scipy), too slow for that.
    """
    R = T0[:, :3, :3].copy()  # [S, 3, 3]
    t = T0[:, :3, 3].copy()  # [S, 3]
    r = _plane_residuals(P, N, D, R, t)  # [S, M]
    cost = (r**2).sum(1)  # [S]
    lam = np.full(len(R), 1e-3)
    for _ in range(iterations):
        q = P @ R.transpose(0, 2, 1)  # [S, M, 3]
        J = np.concatenate([np.cross(q, N), np.broadcast_to(N, q.shape)], axis=2)  # [S, M, 6]
        H = np.einsum("smi,smj->sij", J, J)  # [S, 6, 6]
        g = np.einsum("smi,sm->si", J, r)  # [S, 6]
        d = np.einsum("sii->si", H) + 1e-12  # [S, 6]
        step = -np.linalg.solve(H + lam[:, None, None] * (d[:, :, None] * np.eye(6)),
                                g[..., None])[..., 0]  # [S, 6]
        R_new = Rotation.from_rotvec(step[:, :3]).as_matrix() @ R
        t_new = t + step[:, 3:]
        r_new = _plane_residuals(P, N, D, R_new, t_new)
        cost_new = (r_new**2).sum(1)
        better = cost_new < cost
        done = np.all(cost - np.where(better, cost_new, cost) <= 1e-9 * cost)
        R[better], t[better], r[better], cost[better] = (R_new[better], t_new[better],
                                                         r_new[better], cost_new[better])
        lam = np.where(better, lam * 0.1, lam * 10.0)
        if done and np.all(better | (lam > 1e3)):
            break
    T = np.tile(np.eye(4), (len(R), 1, 1))
    T[:, :3, :3], T[:, :3, 3] = R, t
    return T, cost


def _agree_limit(views: list[View], opts: SolverOptions) -> np.ndarray:
    """[V] metres: the point-to-plane RMS up to which each view agrees with a fit,
    ``reject_factor`` times its points' scatter about their own line (the laser noise,
    measured without the extrinsic) and at least ``reject_min_m``."""
    scatter = np.array([_line_scatter([v]) for v in views])  # [V]
    return np.maximum(opts.reject_factor * scatter, opts.reject_min_m)


def _consensus(views: list[View], opts: SolverOptions, guess: np.ndarray | None,
               T: np.ndarray) -> tuple[np.ndarray, np.ndarray, str, np.ndarray] | None:
    """The views that agree with each other, when the fit of all of them ``T`` leaves
    some view beyond its noise; None when every view agrees (or too few do to tell).

    The rejection rule of ``_outlier_view`` judges views by the fit they all pulled on,
    so bad views that pull it their way get good ones rejected: two scans swapped among
    8 views left the fit 178 degrees off and four good views were rejected one by one.
    Here four-view subsets that span all directions are fitted (RANSAC), each fit names
    the views within ``_agree_limit`` of it, each such set is refitted by itself, and the
    set whose refit has the lowest truncated cost over all views wins (MSAC: a view adds
    its squared RMS over its limit, at most 1). It is refitted as the solve does, and
    views that agree with that refit join it. All subsets are tried up to
    ``CONSENSUS_MAX_SUBSETS`` (8 views: 70); beyond, that many are drawn with a fixed
    seed, stopping once a subset of views that agree with the best fit so far would have
    been drawn with probability 0.999 (adaptive RANSAC).

    Returns a mask [V] of the views kept, their fit [4, 4], its start's name and every
    view's RMS [V] under it.
    """
    limit = _agree_limit(views, opts)  # [V]
    if np.all(_view_rms(views, T) <= limit):
        return None
    P, N, D, ids = _stack(views)
    first = np.r_[0, np.cumsum([len(v.points) for v in views])[:-1]]  # [V]
    n_pts = np.array([len(v.points) for v in views], dtype=float)  # [V]

    def rms_of(Ts: np.ndarray) -> np.ndarray:  # [S, V] per-view RMS under Ts [S, 4, 4]
        r = _plane_residuals(P, N, D, Ts[:, :3, :3], Ts[:, :3, 3])
        return np.sqrt(np.add.reduceat(r**2, first, axis=1) / n_pts)

    def near(Ts: np.ndarray) -> np.ndarray:  # [S] bool: within the allowed offset
        return (np.ones(len(Ts), bool) if opts.max_offset_m is None
                else np.linalg.norm(Ts[:, :3, 3], axis=1) <= opts.max_offset_m)

    lin = linear_init(views)
    starts = np.stack([x for x in (T, guess, lin) if x is not None])  # [S, 4, 4]
    axes = _axis_aligned_rotations()
    n_views = len(views)
    sampled = math.comb(n_views, CONSENSUS_SUBSET) > CONSENSUS_MAX_SUBSETS
    if not sampled:
        subsets = list(itertools.combinations(range(n_views), CONSENSUS_SUBSET))
    else:
        rng = np.random.default_rng(0)
        chosen: dict[tuple[int, ...], None] = {}
        while len(chosen) < CONSENSUS_MAX_SUBSETS:
            chosen[tuple(sorted(rng.choice(n_views, CONSENSUS_SUBSET, replace=False)
                                .tolist()))] = None
        subsets = list(chosen)
    hyps = [T]
    # Views the best fit so far agrees with; a fit beyond the allowed offset counts none.
    most = int(np.sum(_view_rms(views, T) <= limit)) if near(T[None])[0] else 0
    for tried, s in enumerate(subsets):
        # Adaptive RANSAC where the subsets are drawn: stop once a subset of views that
        # agree with the best fit so far would have been drawn with probability 0.999.
        share = (most / n_views) ** CONSENSUS_SUBSET
        if sampled and (share >= 1.0 or (share > 0.0 and tried >= math.log(1e-3)
                                         / math.log(1.0 - share))):
            break
        if degenerate_views_reason([views[i] for i in s]) is not None:
            continue  # its fit would be set by noise
        m = np.isin(ids, s)
        Ps, Ns, Ds = P[m], N[m], D[m]
        Ts, cost = _fit_many(Ps, Ns, Ds, starts)
        ok = near(Ts)
        fits = ok.any() and bool(np.all(
            rms_of(Ts[[int(np.argmin(np.where(ok, cost, np.inf)))]])[0, list(s)]
            <= limit[list(s)]))
        if not fits and opts.multistart:
            # As in ``_fit``: the mounts a wrong start cannot reach.
            T_ax = np.stack([se3(R, _translation_given_rotation(Ps, Ns, Ds, R)) for R in axes])
            Ta, cost_a = _fit_many(Ps, Ns, Ds, T_ax)
            Ts, cost, ok = np.r_[Ts, Ta], np.r_[cost, cost_a], np.r_[ok, near(Ta)]
        if ok.any():
            hyps.append(Ts[int(np.argmin(np.where(ok, cost, np.inf)))])
            most = max(most, int(np.sum(rms_of(hyps[-1][None])[0] <= limit)))
    H = np.stack(hyps)  # [K, 4, 4]
    agree = rms_of(H) <= limit  # [K, V]
    # Each set of views a fit is agreed with is refitted by itself and judged by the
    # truncated cost of that refit (MSAC): every view adds its squared RMS over its
    # limit, at most 1. A four-view fit strays on the views it did not see, and counting
    # agreeing views rewards fits that absorb a bad view (two boards moved among 6 views:
    # a set of 5 with both moved ones in it, 6.4 degrees off, beat the 4 good ones).
    best_cost, keep, T_c = np.inf, agree[0], T
    seen: list[np.ndarray] = []
    for k in range(len(H)):
        if agree[k].sum() < CONSENSUS_SUBSET or any(np.array_equal(agree[k], a) for a in seen):
            continue
        seen.append(agree[k])
        m = np.isin(ids, np.flatnonzero(agree[k]))
        T_k = _fit_many(P[m], N[m], D[m], H[k][None])[0]
        if not near(T_k)[0]:
            continue  # a mount beyond the allowed offset loses, as in ``_fit``
        rms_k = rms_of(T_k)[0]
        cost = float(np.minimum((rms_k / limit) ** 2, 1.0).sum())
        if cost < best_cost:
            best_cost, keep, T_c = cost, agree[k] | (rms_k <= limit), T_k[0]
    if not np.isfinite(best_cost) or keep.all() or keep.sum() < max(opts.min_views,
                                                                     MIN_VIEWS):
        return None
    # Views that agree with the refit join; none leaves: a view that the refit leaves
    # just beyond its limit is for ``_outlier_view`` to judge against the others. The
    # consensus only settles which views can agree at all.
    for _ in range(3):
        T_c, method = _fit([views[i] for i in np.flatnonzero(keep)], opts, guess, start=T_c)
        again = keep | (_view_rms(views, T_c) <= limit)
        if np.array_equal(again, keep):
            break
        keep = again
    else:
        T_c, method = _fit([views[i] for i in np.flatnonzero(keep)], opts, guess, start=T_c)
    return keep, T_c, method, _view_rms(views, T_c)


def _outlier_view(views: list[View], opts: SolverOptions, guess: np.ndarray | None,
                  T: np.ndarray) -> tuple[int, float, float] | None:
    """(index, its RMS, the others' median RMS) of the view to reject, or None.

    A view far off the fit of all views is the obvious case. But one bad view can drag
    the fit until every view is a little off (a robust loss prefers spreading the error
    to ignoring a whole board), so each view is also judged against the fit of the
    others without it.

    With five views or fewer the fit is loose (four boards leave two constraints spare),
    so a disagreeing view may be the right one, and leaving any view out lets the fit
    wander. Below ``gross_m`` a view is dropped only when the evidence does not rest on
    the fit alone: the fit of all views leaves some view off by more than
    ``reject_factor`` times its scatter about its own line (the laser noise, measured
    without the extrinsic), and one view clearly explains that best: fit without it, the
    others agree within their noise (and 1.5x better than without any other view) and
    still span all directions (``normal_spread``), and it is off that fit by more than
    ``reject_factor`` times both the others and its own scatter.
    """
    def verdict(rms: np.ndarray, i: int) -> tuple[float, float] | None:
        others = float(np.median(np.delete(rms, i)))
        if rms[i] > max(opts.reject_factor * others, opts.reject_min_m):
            return float(rms[i]), others
        return None

    rms = _view_rms(views, T)
    worst = int(np.argmax(rms))
    v = verdict(rms, worst)
    if v is not None and (len(views) > 5 or v[0] >= opts.gross_m):
        return worst, *v
    if len(views) - 1 < max(opts.min_views, 1):
        return None  # no view can be spared
    quick = SolverOptions(**{**opts.__dict__, "multistart": False})
    if len(views) <= 5:
        noise = np.array([max(_line_scatter([x]), 1e-3) for x in views])  # [V] metres
        if not np.any(rms > opts.reject_factor * noise):
            return None  # every view fits within its own noise: nothing to explain
        n_pts = np.array([len(x.points) for x in views], dtype=float)
        misfit = np.zeros(len(views))  # [V] the others' mean squared residual over noise
        explains: list[tuple[int, float, float] | None] = []
        for i in range(len(views)):
            rest = views[:i] + views[i + 1:]
            r = _view_rms(views, _fit(rest, quick, guess, start=T)[0])
            z2 = np.delete(n_pts * (r / noise) ** 2, i)
            misfit[i] = float(z2.sum() / np.delete(n_pts, i).sum())
            v = verdict(r, i)
            # A view that is noisy rather than wrong is off its own line as much as the fit.
            ok = (v is not None and float(np.max(np.delete(r, i))) <= 1.5 * _line_scatter(rest)
                  and v[0] > opts.reject_factor * noise[i]
                  and degenerate_views_reason(rest) is None)
            explains.append((i, *v) if ok and v is not None else None)
        # Four views can absorb a fifth's error, so leaving out a good view may let the
        # rest fit too. The likeliest culprit is the view whose removal leaves the others
        # fitting best; it is dropped only when that is clearly (1.5x) better than
        # leaving out any other view.
        order = np.argsort(misfit)
        best = int(order[0])
        if explains[best] is not None and misfit[order[1]] >= 1.5 * misfit[best]:
            return explains[best]
        return None
    best: tuple[float, int, float, float] | None = None
    for i in range(len(views)):
        rest = views[:i] + views[i + 1:]
        T_i, _ = _fit(rest, quick, guess, start=T)
        r = _view_rms(views, T_i)
        v = verdict(r, i)
        if v is None:
            continue
        # Only a view that was dragging the others: without it they must fit clearly
        # better. With weakly constrained views, leaving any one out lets the fit wander
        # so that the left-out view disagrees, without it being wrong.
        dragged = np.median(np.delete(r, i)) < 0.7 * np.median(np.delete(rms, i))
        # Or the evidence the few-view case asks for: the others agree within their line
        # noise, and this view is off by more than reject_factor times its own. With 1 cm
        # lidar noise the others' median cannot fall below the noise, so a board moved
        # 6 cm between image and scan never "dragged" them enough (8.3 -> 6.8 mm) and the
        # result came out 1-2 deg off, marked reliable.
        explained = (not dragged
                     and v[0] > opts.reject_factor * max(_line_scatter([views[i]]), 1e-3)
                     and float(np.max(np.delete(r, i))) <= 1.5 * _line_scatter(rest)
                     and degenerate_views_reason(rest) is None)
        if (dragged or explained) and (best is None or v[0] / v[1] > best[0]):
            best = (v[0] / v[1], i, *v)
    return None if best is None else (best[1], best[2], best[3])


def calibrate_extrinsic(views: list[View], init: np.ndarray | None = None,
                        options: SolverOptions | None = None,
                        camera: PinholeCamera | None = None,
                        start: np.ndarray | None = None,
                        outline: tuple[np.ndarray, np.ndarray] | None = None) -> ExtrinsicResult:
    """``T_camera_laser`` from board views, with outlier views rejected.

    ``init`` [4, 4] is an optional starting guess (and, with the prior sigmas set in
    ``options``, a soft constraint for directions the views leave open). With ``camera``
    and views that carry their corners, the final estimate is the joint refinement; with
    the board's ``outline`` (``BoardSpec.outline()``) it also uses the views' edge points.
    """
    opts = options or SolverOptions()
    views = [v for v in views if len(v.points) >= 2]
    if len(views) < opts.min_views:
        raise ExtrinsicError(
            f"{len(views)} usable views; at least {opts.min_views} are needed: each board "
            "gives two constraints on the six unknowns, so fewer boards fit several wrong "
            "extrinsics exactly. Capture more views (10 or more), the board leaned forward "
            "and back and turned left and right by 20-45 degrees.")
    rejected: dict[str, str] = {}
    used = list(views)
    T, init_method = _fit(used, opts, init, start)
    # A board distance scale error (the focal length or --square a few % off) grows with
    # the board's distance, so at scale 1 the far boards look like a few bad views: with
    # the focal length 3.5 % long and a 2 mm lidar, 3 good views of 10 were left out, the
    # near ones absorbed the error (0.88 deg / 34.6 mm off) and the scale of the views kept
    # read 1.00, so it was marked reliable with no warning. When one scale makes every
    # view agree, no view is left out and ``_scale_verdict`` below names it.
    prior = _prior(opts, init)
    scaled = _scale_explains(used, T, opts, prior)
    found_c = (_consensus(used, opts, init, T)
               if len(used) >= CONSENSUS_MIN_VIEWS and len(used) > opts.min_views
               and not scaled else None)
    if found_c is not None:
        keep, T, init_method, rms_c = found_c
        median = float(np.median(rms_c[keep]))
        for i in np.flatnonzero(~keep):
            rejected[used[i].name] = (
                f"point-to-plane RMS {rms_c[i] * 100:.1f} cm against a median of "
                f"{median * 100:.1f} cm for the {int(keep.sum())} views that agree with each "
                "other (wrong scan segment, board moved between image and scan, the scan of "
                "another image, or a bad corner detection)")
        used = [v for v, k in zip(used, keep, strict=True) if k]
    while len(used) > opts.min_views and not scaled:
        found = _outlier_view(used, opts, init, T)
        if found is None:
            break
        worst, rms_w, others = found
        rejected[used[worst].name] = (
            f"point-to-plane RMS {rms_w * 100:.1f} cm against a median of "
            f"{others * 100:.1f} cm for the other views (wrong scan segment, board moved "
            "between image and scan, or a bad corner detection)")
        used.pop(worst)
        T, init_method = _fit(used, opts, init, start=T)
    res = point_to_plane(used, T)
    r = np.concatenate(res)
    # The laser noise seen without the extrinsic: the scatter of each board's points about
    # their own line. With few views the extrinsic can fit the points better than the
    # noise allows (it has as many unknowns as the views have constraints), and residuals
    # alone would then make the covariance overconfident.
    sigma_line = _line_scatter(used)
    refine = "point-to-plane"
    if camera is not None and opts.joint and all(v.corners is not None for v in used):
        sigma_px = max(float(np.sqrt(np.mean([v.plane.reprojection_rms_px**2 for v in used])
                                     / 2.0)), 0.02)
        sigma_m = max(float(np.sqrt(np.mean(r**2))), sigma_line, 1e-3)
        T, _, info = _joint_refine(used, T, camera, opts.loss, opts.f_scale_m / sigma_m,
                                   sigma_px, sigma_m, prior, outline)
        n_edges = sum(len(v.edges) for v in used if v.edges is not None) if outline else 0
        refine = "joint (corners + point-to-plane" + (
            f" + {n_edges} board-edge points)" if n_edges else ")")
        res = point_to_plane(used, T)
        r = np.concatenate(res)
    else:
        P, N, _, _ = _stack(used)
        J = _jacobian(P, N, T[:3, :3])
        info = J.T @ J / max(float(r @ r) / max(len(r) - 6, 1), sigma_line**2, 1e-12)
    cov, weak = _covariance(info, opts.weak_std)
    _check_offset(T, opts.max_offset_m, used, rejected)
    warnings = []
    if len(used) < 5:
        warnings.append(
            f"only {len(used)} views: each board gives two constraints on the six unknowns, "
            "so with fewer than 5 views there is little or no redundancy and a wrong "
            "extrinsic can fit as well as the right one, with a small residual. Use 10 or "
            "more views.")
    if weak:
        warnings.append(
            "the views do not constrain all six degrees of freedom: "
            + "; ".join(w.description for w in weak)
            + ". Add views with the board turned about other axes (tilted forward and back as "
              "well as turned left and right), at several distances.")
    disagreeing = _disagreeing_views(used, res, opts)
    open_reasons = []
    degenerate = degenerate_views_reason(used)
    if degenerate is not None:
        open_reasons.append(degenerate)
    unconstrained = [w.description for w in weak if math.isinf(w.std)]
    if unconstrained:
        open_reasons.append("the views leave " + "; ".join(unconstrained) + " without any "
                            "constraint: the value there is the prior's or arbitrary.")
    held = _held_by_prior(used, info, prior, opts.weak_std) if open_reasons else None
    # Where the prior holds what the views leave open, the scale is judged with it too.
    scale_warning, scale_unreliable = _scale_verdict(used, T, prior if held else None)
    if scaled and (scale_warning or scale_unreliable):
        # The far boards' misfit is the scale's, not theirs: blaming the views would send
        # the user after boards that did not move.
        note = (f"; with it every view agrees, so none was left out: at scale 1 the "
                f"boards farthest from the camera are off by up to "
                f"{float(max(np.sqrt(np.mean(x**2)) for x in res)) * 1000:.1f} mm")
        scale_warning = scale_warning + note if scale_warning else None
        scale_unreliable = scale_unreliable + note if scale_unreliable else None
        disagreeing = []
    warnings += disagreeing
    warnings += [scale_warning] if scale_warning else []
    unreliable = [scale_unreliable] if scale_unreliable else []
    if held is not None:
        warnings.append(held)
    else:
        unreliable += open_reasons
    if rejected and len(used) < MIN_VIEWS_AFTER_REJECTION:
        # The views kept may be the wrong ones: no prior or residual tells.
        unreliable.append(
            f"{len(used)} views kept of {len(used) + len(rejected)} after leaving out "
            f"{', '.join(rejected)}: with fewer than {MIN_VIEWS_AFTER_REJECTION} views a wrong "
            "view is fitted as well as the right ones, so neither the views left out nor "
            "the ones kept are confirmed (8 views with two scans swapped once gave a result "
            "96 degrees off with four good views left out). Check the pairing of images and "
            "scans and the overlays, remove the bad views yourself, and add views.")
    return ExtrinsicResult(
        T_camera_laser=T,
        residual_rms_m=float(np.sqrt(np.mean(r**2))),
        per_view_rms_m={v.name: float(np.sqrt(np.mean(x**2))) for v, x in zip(used, res,
                                                                             strict=True)},
        views_used=[v.name for v in used],
        views_rejected=rejected,
        n_points=int(len(r)),
        covariance=cov,
        weak_directions=weak,
        init_method=init_method,
        refinement=refine,
        guess=init,
        warnings=warnings,
        unreliable=unreliable,
        normal_spread_deg=normal_spread(used)[0],
    )


# The boards' distances from the camera scale with the square size given (and with the
# focal length): a 10 % slip in --square moved the extrinsic 0.2 m with a 5 mm residual,
# marked reliable. A board-distance scale fitted beside the extrinsic finds it.
SCALE_UNRELIABLE = 0.03
SCALE_WARN = 0.015
# A smaller scale still warns when the fit is sure of it: a focal length 1 % long gave
# 0.5-0.9 % at 6-11 standard deviations and the extrinsic 1 cm off, marked reliable with no
# word; exact intrinsics stayed within 1.2 (20 synthetic views, seeds 0-9; the recipe's
# simulated capture within 2.7). The views are still left out or kept by SCALE_WARN.
SCALE_NOTE = 0.004


def board_distance_scale(views: list[View], T: np.ndarray,
                         prior: tuple[np.ndarray, float, float] | None = None) -> (
    tuple[float, float]
):
    """(s, std) of the factor the camera's board distances need for the laser points to
    lie on the boards (``n . (R p + t) = s d``), fitted with the extrinsic from ``T``: 1
    when the square size and the focal length are right.

    With ``prior`` (centre, sigma rad, sigma m) the extrinsic is held by it as in the
    solve: on upright boards the free height and tilts trade with the scale (six untilted
    views at the true extrinsic gave 0.92 +- 0.009), and a measured mount pins them
    (1.000 +- 0.001 with 0.1 deg / 1 mm).
    """
    s, sd, _ = _distance_scale_fit(views, T, prior)
    return s, sd


def _distance_scale_fit(views: list[View], T: np.ndarray,
                        prior: tuple[np.ndarray, float, float] | None = None) -> (
    tuple[float, float, np.ndarray]
):
    """``board_distance_scale``'s (s, std) and the extrinsic [4, 4] fitted with it."""
    P, N, D, _ = _stack(views)
    R0, t0 = T[:3, :3], T[:3, 3]
    # The prior's rows in metres of laser noise, so that one loss and one variance
    # factor serve both.
    noise = max(_line_scatter(views), 1e-3)

    def fun(x: np.ndarray) -> np.ndarray:
        R = Rotation.from_rotvec(x[:3]).as_matrix() @ R0
        r = [((P @ R.T + x[3:6]) * N).sum(1) - x[6] * D]
        if prior is not None:
            Tp, s_r, s_t = prior
            r.append(noise * Rotation.from_matrix(R @ Tp[:3, :3].T).as_rotvec() / s_r)
            r.append(noise * (x[3:6] - Tp[:3, 3]) / s_t)
        return np.concatenate(r)

    sol = least_squares(fun, np.r_[0.0, 0.0, 0.0, t0, 1.0], loss="soft_l1", f_scale=0.01,
                        method="trf", x_scale="jac")
    J = sol.jac  # [M (+6), 7]
    dof = max(len(D) - 7, 1)
    sigma2 = max(float(sol.fun[:len(D)] @ sol.fun[:len(D)]) / dof, 1e-8)
    T_s = se3(Rotation.from_rotvec(sol.x[:3]).as_matrix() @ R0, sol.x[3:6])
    try:
        cov = np.linalg.inv(J.T @ J) * sigma2
    except np.linalg.LinAlgError:
        return float(sol.x[6]), float("inf"), T_s
    return float(sol.x[6]), float(np.sqrt(max(cov[6, 6], 0.0))), T_s


def _scale_explains(views: list[View], T: np.ndarray, opts: SolverOptions,
                    prior: tuple[np.ndarray, float, float] | None) -> bool:
    """Whether a board distance scale clearly off 1 (``_scale_text``) explains why the
    fit ``T`` [4, 4] of all ``views`` leaves some of them beyond ``_agree_limit``: fitted
    with that scale, every view agrees. Then the views are not to be left out.

    A wrong view is not explained so: one scale moves every board in proportion to its
    distance, so it cannot bring one board moved by centimetres into line without
    putting the others out of theirs.
    """
    limit = _agree_limit(views, opts)  # [V] metres
    if len(views) <= opts.min_views or np.all(_view_rms(views, T) <= limit):
        return False
    s, sd, T_s = _distance_scale_fit(views, T, prior)
    if _scale_text(s, sd) is None:
        return False
    return bool(np.all(_view_rms(views, T_s, s) <= limit))


def _scale_verdict(views: list[View], T: np.ndarray,
                   prior: tuple[np.ndarray, float, float] | None = None) -> (
    tuple[str | None, str | None]
):
    """(warning, unreliable reason) from ``board_distance_scale``."""
    s, sd = board_distance_scale(views, T, prior)
    text = _scale_text(s, sd, SCALE_NOTE)
    if text is None:
        return None, None
    return (None, text) if abs(s - 1.0) > SCALE_UNRELIABLE else (text, None)


def _scale_text(s: float, sd: float, floor: float = SCALE_WARN) -> str | None:
    """What a board distance scale ``s`` +- ``sd`` says of --square, or None when it is
    within ``floor`` of 1 or within 5 sd."""
    off = s - 1.0
    if not (abs(off) > floor and abs(off) > 5.0 * sd):
        return None
    return (f"the laser puts the boards {abs(off) * 100:.1f} % {'farther' if off > 0 else 'nearer'}"
            f" than the camera's board poses do (distance scale {s:.3f} +- {sd:.3f}): the "
            f"board's square size (--square) is probably {s:.3f} times the one given - "
            "measure a square on the printed board (printers scale pages) - or the camera's "
            "focal length is off by that factor"
            + ("" if abs(off) > SCALE_WARN else
               " (or the lidar's ranges carry a bias of that share)"))


def left_out_text(left_out: dict[str, str]) -> str:
    """``NAME: reason; ...`` of views or images left out, for error messages."""
    return "; ".join(f"{k}: {v}" for k, v in left_out.items())


def _check_offset(T: np.ndarray, max_offset_m: float | None, views: list[View],
                  rejected: dict[str, str]) -> None:
    """Raise when the solution puts the laser farther from the camera than allowed; the
    message names the views the solve left out (``rejected``), which may be good ones."""
    dist = float(np.linalg.norm(T[:3, 3]))
    if max_offset_m is None or dist <= max_offset_m:
        return
    # A wrong square size moves the laser as far (5 % off on the ACFR pairs: 1.41 m), and
    # raising --max-offset would accept that: the scale fit finds it at this solution. It is
    # named only when the distances so scaled bring the laser within the limit: at a wrong
    # solution (two ACFR scans swapped) the fit gave 0.113 and left the laser 2 m out.
    s, sd, T_s = _distance_scale_fit(views, T)
    scale = _scale_text(s, sd)
    if scale is not None and float(np.linalg.norm(T_s[:3, 3])) > max_offset_m:
        scale = None
    why = degenerate_views_reason(views)
    kept = (f"{len(views)} views kept of {len(views) + len(rejected)} (left out: "
            f"{left_out_text(rejected)})" if rejected else f"{len(views)} views")
    raise ExtrinsicError(
        f"the best fit of the {kept} puts the laser {dist:.2f} m from the camera, "
        f"beyond the largest offset allowed ({max_offset_m:g} m, --max-offset). "
        + (f"First check the board's size: {scale}; with the distances so scaled the laser "
           f"comes to {float(np.linalg.norm(T_s[:3, 3])):.2f} m. Otherwise it is "
           if scale else "It is ")
        + "a wrong solution that too few or too similar views cannot rule out"
        + (f"; here {why.rstrip('.')}" if why else ". Capture more views (10 or more), the "
           "board leaned forward and back and turned left and right by 20-45 degrees")
        + (". A view left out may be a good one outvoted by bad ones (an image paired with "
           "another view's scan, a wrong segment): check the pairing and the overlays"
           if rejected else "")
        + ". Raise --max-offset only if the sensors really are that far apart.")


# A kept view is worth a warning when it fits this many times worse than the other views'
# median, or than its points' scatter about their own line (the laser noise). On 80 clean
# analytic 5-10 view sets neither ratio reached it. A board turned 8 degrees and moved 4 cm
# between image and scan, among five views with 1 cm lidar noise: 3 of 10 rejected, 3
# warned, and in 4 the fit absorbed it without a trace (3-11 degree errors): five views
# are too few to catch every bad one.
WARN_VIEW_RATIO = 2.0


def _disagreeing_views(views: list[View], res: list[np.ndarray],
                       opts: SolverOptions) -> list[str]:
    """Warnings for kept views that fit clearly worse than the others."""
    rms = np.array([np.sqrt(np.mean(r**2)) for r in res])
    out = []
    for i, v in enumerate(views):
        others = float(np.median(np.delete(rms, i)))
        noise = max(_line_scatter([v]), 1e-4)
        if rms[i] > opts.reject_min_m and (rms[i] > WARN_VIEW_RATIO * others
                                           or rms[i] > WARN_VIEW_RATIO * noise):
            out.append(
                f"view {v.name}: point-to-plane RMS {rms[i] * 1000:.1f} mm, "
                f"{rms[i] / max(others, 1e-12):.1f}x the median of the other views "
                f"({others * 1000:.1f} mm) and {rms[i] / noise:.1f}x its points' scatter about "
                f"their own line; kept, since with {len(views)} views it could not be told "
                "whether this view is wrong or another one's error was pushed onto it. Check "
                "that no board moved between its image and scan and that the right scan "
                "segments were taken (--overlays), then drop the bad view or add views.")
    return out


# ---------------------------------------------------------------------------- joint refinement


def _box_sdf(xy: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """[N] signed distance of board-frame points [N, 2] to the rectangle's outline."""
    c, half = (lo + hi) / 2, (hi - lo) / 2
    d = np.abs(xy - c) - half  # [N, 2]
    return np.linalg.norm(np.maximum(d, 0.0), axis=1) + np.minimum(d.max(axis=1), 0.0)


def _joint_refine(views: list[View], T: np.ndarray, camera: PinholeCamera, loss: str,
                  f_scale: float, sigma_px: float, sigma_m: float,
                  prior: tuple[np.ndarray, float, float] | None = None,
                  outline: tuple[np.ndarray, np.ndarray] | None = None) -> (
    tuple[np.ndarray, list[np.ndarray], np.ndarray]
):
    """Maximum-likelihood refinement of the extrinsic together with every board pose.

    The plane-only fit treats each PnP plane as exact, but with sub-pixel corner noise
    a board's tilt is uncertain by tenths of a degree and that error, shared by all the
    view's laser points, dominates. Here the corners' reprojection errors (over
    ``sigma_px``) and the point-to-plane distances (over ``sigma_m``) are minimised
    together, so uncertain planes weigh less and the laser helps to place them.

    Returns the extrinsic, the refined board poses [4, 4] and the marginal information
    matrix [6, 6] of the extrinsic over (w rad, t m).
    """
    V = len(views)
    n_par = 6 + 6 * V
    Rb0 = [v.plane.T_camera_board[:3, :3].copy() for v in views]
    Re0 = T[:3, :3].copy()
    x0 = np.zeros(n_par)
    x0[3:6] = T[:3, 3]
    for i, v in enumerate(views):
        x0[6 + 6 * i + 3: 12 + 6 * i] = v.plane.T_camera_board[:3, 3]
    rows: list[tuple[int, int, bool]] = []  # (view, count, is_laser)
    use_edges = [outline is not None and v.edges is not None and len(v.edges) > 0
                 for v in views]
    for i, v in enumerate(views):
        assert v.corners is not None
        rows.append((i, 2 * len(v.corners), False))
        rows.append((i, len(v.points), True))
        if use_edges[i]:
            assert v.edges is not None
            rows.append((i, len(v.edges), True))
    m = sum(c for _, c, _ in rows) + (6 if prior is not None else 0)
    sparsity = np.zeros((m, n_par), dtype=bool)
    r0 = 0
    for i, c, laser in rows:
        sparsity[r0:r0 + c, 6 + 6 * i: 12 + 6 * i] = True
        if laser:
            sparsity[r0:r0 + c, :6] = True
        r0 += c
    sparsity[r0:, :6] = True  # the prior rows, if any
    P3 = [np.c_[v.points, np.zeros(len(v.points))] for v in views]

    def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[np.ndarray],
                                       list[np.ndarray]]:
        Re = Rotation.from_rotvec(x[:3]).as_matrix() @ Re0
        Rb = [Rotation.from_rotvec(x[6 + 6 * i: 9 + 6 * i]).as_matrix() @ Rb0[i]
              for i in range(V)]
        tb = [x[9 + 6 * i: 12 + 6 * i] for i in range(V)]
        return Re, x[3:6], Rb, tb

    def fun(x: np.ndarray) -> np.ndarray:
        Re, te, Rb, tb = unpack(x)
        out = []
        for i, v in enumerate(views):
            assert v.object_points is not None and v.corners is not None
            uv, _ = camera.project(v.object_points @ Rb[i].T + tb[i], past_peak=True)
            out.append(((uv - v.corners) / sigma_px).ravel())
            n = Rb[i][:, 2]
            out.append(((P3[i] @ Re.T + te) @ n - n @ tb[i]) / sigma_m)
            if use_edges[i]:
                assert v.edges is not None and v.edge_sigma is not None and outline is not None
                e3 = np.c_[v.edges, np.zeros(len(v.edges))] @ Re.T + te
                xy = ((e3 - tb[i]) @ Rb[i])[:, :2]  # board frame
                out.append(_box_sdf(xy, *outline) / v.edge_sigma)
        if prior is not None:
            Tp, s_r, s_t = prior
            out.append(Rotation.from_matrix(Re @ Tp[:3, :3].T).as_rotvec() / s_r)
            out.append((te - Tp[:3, 3]) / s_t)
        return np.concatenate(out)

    sol = least_squares(fun, x0, jac="2-point", jac_sparsity=sparsity, loss=loss,
                        f_scale=f_scale, method="trf", x_scale="jac", max_nfev=100)
    Re, te, Rb, tb = unpack(sol.x)
    J = sol.jac.toarray() if hasattr(sol.jac, "toarray") else np.asarray(sol.jac)  # [M, n]
    if prior is not None:
        # The reported uncertainty is the data's alone, so that weak directions show
        # even where the prior holds them in place.
        J = J[:-6]
        m -= 6
    fun_data = sol.fun[:m]
    # Variance factor, at least 1: the sigmas are independent estimates of the noise, and
    # residuals below them mean overfitting, not better data.
    s2 = max(float(fun_data @ fun_data) / max(m - n_par, 1), 1.0)
    H = J.T @ J / s2
    A, B, C = H[:6, :6], H[:6, 6:], H[6:, 6:]
    # Marginal information of the extrinsic: board poses integrated out (Schur complement).
    info = A - B @ np.linalg.solve(C + 1e-12 * np.eye(len(C)), B.T)
    return se3(Re, te), [se3(Rb[i], tb[i]) for i in range(V)], 0.5 * (info + info.T)


# ---------------------------------------------------------------------------- stability


@dataclass
class LeaveOneOut:
    """Spread of the extrinsic when each view in turn is left out."""

    rotation_deg: dict[str, float]  # left-out view -> angle to the all-views solution
    translation_m: dict[str, float]  # left-out view -> distance to the all-views solution
    rotation_spread_deg: float  # largest of the above
    translation_spread_m: float
    rotation_std_deg: np.ndarray  # [3] std of the rotation over the runs, about camera x y z
    translation_std_m: np.ndarray  # [3]


def leave_one_out(views: list[View], result: ExtrinsicResult,
                  options: SolverOptions | None = None,
                  camera: PinholeCamera | None = None,
                  outline: tuple[np.ndarray, np.ndarray] | None = None) -> LeaveOneOut | None:
    """Re-solve without each used view in turn (None with fewer than ``MIN_VIEWS + 1``).

    The same estimator as the full solve (joint when ``camera`` is given), started from
    the full solution, without view rejection and without the offset limit (a subset that
    runs off is what this is meant to show).
    """
    opts = options or SolverOptions()
    used = [v for v in views if v.name in result.views_used]
    if len(used) < MIN_VIEWS + 1:
        return None
    T_all = result.T_camera_laser
    rot: dict[str, float] = {}
    tra: dict[str, float] = {}
    rvecs, tvecs = [], []
    fixed = SolverOptions(**{**opts.__dict__, "multistart": False,
                             "min_views": len(used) - 1, "max_offset_m": None})
    for i, v in enumerate(used):
        rest = used[:i] + used[i + 1:]
        T = calibrate_extrinsic(rest, result.guess, fixed, camera, start=T_all,
                                outline=outline).T_camera_laser
        dR = T[:3, :3] @ T_all[:3, :3].T
        rot[v.name] = float(np.degrees(rotation_angle(dR)))
        tra[v.name] = float(np.linalg.norm(T[:3, 3] - T_all[:3, 3]))
        rvecs.append(np.degrees(Rotation.from_matrix(dR).as_rotvec()))
        tvecs.append(T[:3, 3])
    return LeaveOneOut(rot, tra, max(rot.values()), max(tra.values()),
                       np.std(rvecs, axis=0), np.std(tvecs, axis=0))


# Leave-one-out against the covariance. Dropping one of V views should move a consistent
# estimate by about its standard deviation over sqrt(V - 1); on the analytic generator's
# well-posed 6-10 view sets the largest move was 0.5-2.9 times the norm of the reported
# standard deviations, on untilted (degenerate) sets 4.5-47 times. Boards leaned by only
# 5-10 degrees gave moves of 3-9 degrees with errors still within 1-2 standard deviations,
# so a large move is a warning, not proof of a wrong result: the degenerate sets are
# caught by ``normal_spread`` already.
LOO_STD_FACTOR = 5.0
LOO_FLOOR = (0.5, 0.01)  # deg, m: below these a move is too small to matter
# Moves beyond these mean the answer hinges on single views, whatever the covariance says
# (on well-posed 6-view sets the largest move was 0.5 deg / 13 mm).
LOO_LIMIT = (2.0, 0.05)  # deg, m
# With five views the four-view subsets are barely determined and some fall into another
# solution while the five-view one is right (10-20 degree leans: the largest move 10-47
# degrees against errors of 0.1-0.7), so the spread says nothing then.
LOO_MIN_VIEWS = 6


def leave_one_out_warning(result: ExtrinsicResult, loo: LeaveOneOut) -> str | None:
    """A warning when the leave-one-out spread is large against the covariance, or None
    (also with fewer than ``LOO_MIN_VIEWS`` views, where it is no evidence either way)."""
    if len(result.views_used) < LOO_MIN_VIEWS:
        return None
    std_r = float(np.linalg.norm(result.std_rotation_deg))
    std_t = float(np.linalg.norm(result.std_translation_m))
    rot, tra = loo.rotation_spread_deg, loo.translation_spread_m
    worst_r = max(loo.rotation_deg, key=lambda k: loo.rotation_deg[k])
    worst_t = max(loo.translation_m, key=lambda k: loo.translation_m[k])
    parts = []
    if rot > LOO_LIMIT[0] or rot > max(LOO_STD_FACTOR * std_r, LOO_FLOOR[0]):
        parts.append(f"leaving out view {worst_r} turns the result by {rot:.2f} degrees "
                     f"(reported rotation std {std_r:.2f} degrees)")
    if tra > LOO_LIMIT[1] or tra > max(LOO_STD_FACTOR * std_t, LOO_FLOOR[1]):
        parts.append(f"leaving out view {worst_t} moves the laser by {tra * 1000:.0f} mm "
                     f"(reported translation std {std_t * 1000:.0f} mm)")
    if not parts:
        return None
    return ("; ".join(parts) + ": the estimate hinges on single views and may be further off "
            "than the standard deviations say. Add views that turn the board about other "
            "axes (leaned forward and back as well as turned left and right) at several "
            "distances, and check the view named.")


def transform_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(rotation error in degrees, translation error in metres) between two extrinsics."""
    dR = T_est[:3, :3] @ T_true[:3, :3].T
    return float(np.degrees(rotation_angle(dR))), float(np.linalg.norm(T_est[:3, 3]
                                                                      - T_true[:3, 3]))

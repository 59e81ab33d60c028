"""Checking an extrinsic on ordinary recordings: overlays and a consistency score.

``overlay`` draws the scan's points into the camera image coloured by range (the paper's
Figure 3): a right extrinsic puts the points on the walls and object edges they hit.

Two scores measure the agreement without a calibration target:

* ``depth``: where a depth map is available (simulator ground truth, or a metric depth
  prediction), the fraction of projected laser points whose camera depth agrees with the
  map within ``rel_tol``. Points that land on the wrong object (the extrinsic is off)
  disagree.
* ``edges`` (after Levinson & Thrun, RSS 2013): laser points at range discontinuities
  (the near side of a jump: object silhouettes) should fall on image edges. The score is
  the edge strength at those points over the image's mean edge strength, so 1 is chance.

A 2D laser sweeps one plane: tilting the extrinsic (about the camera's x or z axis) moves
the points up or down walls, which changes neither the depth they land on much nor which
vertical edges they meet. On the simulated house a 2 degree rotation about the vertical
axis costs the depth score half its value and the edge score a quarter, while tilts cost
the depth score 3-7 % and the edge score nothing reliable. ``sensitivity`` reports each
axis separately so that this is visible rather than averaged away, and ``SEEN_AXES``
says which axes a score can judge.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from toolkit.camera import PinholeCamera
from toolkit.errors import InputError
from toolkit.geometry import inv_se3, transform_points


class CheckError(InputError):
    """The frames cannot give the requested score; the message says what to pass."""


@dataclass
class Projection:
    """Scan points that land in the image."""

    uv: np.ndarray  # [M, 2] pixels
    depth: np.ndarray  # [M] camera z, metres
    range_m: np.ndarray  # [M] laser range, metres
    index: np.ndarray  # [M] int, into the scan's points


def project_scan(points: np.ndarray, T_camera_laser: np.ndarray, camera: PinholeCamera,
                 min_depth: float = 0.05) -> Projection:
    """Project laser points [N, 2|3] (laser frame) into the image."""
    p = np.asarray(points, dtype=np.float64)
    if p.shape[1] == 2:
        p = np.c_[p, np.zeros(len(p))]
    q = transform_points(T_camera_laser, p)  # [N, 3]
    front = q[:, 2] > min_depth
    uv, z = camera.project(q)
    ok = front & camera.in_image(uv)
    idx = np.nonzero(ok)[0]
    return Projection(uv[idx], z[idx], np.linalg.norm(p[idx, :2], axis=1), idx)


def overlay(image_rgb: np.ndarray, proj: Projection, range_limits: tuple[float, float] | None =
            None, radius: int = 2) -> np.ndarray:
    """[H, W, 3] RGB copy of the image with the points drawn, coloured by range (turbo)."""
    out = np.ascontiguousarray(image_rgb.copy())
    if len(proj.uv) == 0:
        return out
    lo, hi = range_limits or (float(np.percentile(proj.range_m, 2)),
                              float(np.percentile(proj.range_m, 98)))
    t = np.clip((proj.range_m - lo) / max(hi - lo, 1e-6), 0, 1)
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_TURBO)
    colours = lut[(t * 255).astype(int), 0, ::-1]  # BGR -> RGB
    # Far points first so near ones (which occlude them in reality) stay visible.
    for k in np.argsort(-proj.range_m):
        u, v = proj.uv[k]
        cv2.circle(out, (int(round(u)), int(round(v))), radius,
                   tuple(int(c) for c in colours[k]), -1, lineType=cv2.LINE_AA)
    _legend(out, lo, hi, lut)
    return out


def _legend(img: np.ndarray, lo: float, hi: float, lut: np.ndarray) -> None:
    h, w = img.shape[:2]
    bw, bh = min(160, w // 3), 10
    x0, y0 = w - bw - 10, h - bh - 22
    if x0 < 0 or y0 < 0 or bw < 40:
        return  # no room for the bar and its two labels: the points alone
    bar = np.repeat(lut[np.linspace(0, 255, bw).astype(int), 0, ::-1][None], bh, axis=0)
    img[y0:y0 + bh, x0:x0 + bw] = bar
    for text, x in ((f"{lo:.1f} m", x0), (f"{hi:.1f} m", x0 + bw - 40)):
        cv2.putText(img, text, (x, y0 + bh + 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 3,
                    cv2.LINE_AA)
        cv2.putText(img, text, (x, y0 + bh + 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    (255, 255, 255), 1, cv2.LINE_AA)


# ---------------------------------------------------------------------------- scores


def depth_agreement(depth_map: np.ndarray, proj: Projection, rel_tol: float = 0.03) -> (
    tuple[float, int]
):
    """Fraction of points whose depth matches the map [H, W] (metres, 0/NaN invalid)."""
    if len(proj.uv) == 0:
        return float("nan"), 0
    u = np.clip(np.round(proj.uv[:, 0]).astype(int), 0, depth_map.shape[1] - 1)
    v = np.clip(np.round(proj.uv[:, 1]).astype(int), 0, depth_map.shape[0] - 1)
    d = depth_map[v, u].astype(np.float64)
    ok = np.isfinite(d) & (d > 0)
    if not np.any(ok):
        return float("nan"), 0
    good = np.abs(d[ok] - proj.depth[ok]) <= rel_tol * proj.depth[ok]
    return float(np.mean(good)), int(ok.sum())


def edge_map(image_rgb: np.ndarray, blur_px: float = 4.0) -> np.ndarray:
    """[H, W] float32 edge strength in [0, 1], widened so near misses earn partial credit."""
    g = cv2.cvtColor(image_rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
    g = cv2.GaussianBlur(g, (0, 0), 1.0)
    mag = cv2.magnitude(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))
    mag /= max(float(np.percentile(mag, 99)), 1e-6)
    mag = np.clip(mag, 0, 1)
    return cv2.GaussianBlur(mag, (0, 0), blur_px)


def discontinuities(points: np.ndarray, min_jump_m: float = 0.2) -> np.ndarray:
    """[N] weight per point: the range jump to a farther neighbour, 0 when none.

    Neighbours are taken in bearing order; only the near side of a jump counts, since
    the far side is where the laser passes behind an object and has no image edge.
    """
    p = np.asarray(points, dtype=np.float64)[:, :2]
    order = np.argsort(np.arctan2(p[:, 1], p[:, 0]))
    r = np.linalg.norm(p[order], axis=1)
    jump = np.zeros(len(r))
    if len(r) > 2:
        prev = np.r_[0.0, r[:-1] - r[1:]]  # >0: the previous neighbour is farther
        nxt = np.r_[r[1:] - r[:-1], 0.0]
        jump = np.clip(np.maximum(prev, nxt), 0.0, 1.0)
        jump[jump < min_jump_m] = 0.0
    out = np.zeros(len(r))
    out[order] = jump
    return out


def edge_alignment(edges: np.ndarray, proj: Projection, weights: np.ndarray) -> float:
    """Edge strength at weighted points over the mean edge strength (1 = chance)."""
    w = weights[proj.index]
    if len(w) == 0 or w.sum() <= 0:
        return float("nan")
    u = np.clip(np.round(proj.uv[:, 0]).astype(int), 0, edges.shape[1] - 1)
    v = np.clip(np.round(proj.uv[:, 1]).astype(int), 0, edges.shape[0] - 1)
    return float((w * edges[v, u]).sum() / w.sum() / max(float(edges.mean()), 1e-6))


# ---------------------------------------------------------------------------- frames


def name_list(names: list[str], most: int = 5) -> str:
    """The first ``most`` of ``names``, comma-separated, "..." when there are more."""
    return ", ".join(names[:most]) + (", ..." if len(names) > most else "")


@dataclass
class CheckFrame:
    """One image with the scan nearest in time, already in the image's time."""

    name: str
    image: np.ndarray  # [H, W, 3] RGB uint8
    points: np.ndarray  # [N, 3] laser points moved to the image's time (laser frame)
    depth: np.ndarray | None = None  # [H, W] metres, when known
    scan_source: str = ""  # the scan's file (and index), for messages
    _edges: np.ndarray | None = field(default=None, repr=False)
    _jumps: np.ndarray | None = field(default=None, repr=False)

    def edges(self) -> np.ndarray:
        """[H, W] edge map, computed once (the sensitivity table scores 7 extrinsics)."""
        if self._edges is None:
            self._edges = edge_map(self.image)
        return self._edges

    def jumps(self) -> np.ndarray:
        """[N] discontinuity weights of the scan points."""
        if self._jumps is None:
            self._jumps = discontinuities(self.points)
        return self._jumps


def perturbed(T: np.ndarray, axis: int, deg: float) -> np.ndarray:
    """T_camera_laser rotated by ``deg`` about camera axis ``axis`` (0 x, 1 y, 2 z)."""
    rv = np.zeros(3)
    rv[axis] = np.radians(deg)
    out = T.copy()
    out[:3, :3] = Rotation.from_rotvec(rv).as_matrix() @ T[:3, :3]
    return out


# Perturbations each score responds to reliably (see the module notes).
SEEN_AXES = {"depth": ("rx", "ry", "rz"), "edges": ("ry",)}


@dataclass
class CheckScores:
    """Scores of an extrinsic over a set of frames, and how they react to perturbations."""

    kind: str  # "depth" or "edges"
    score: float
    perturbed: dict[str, float] = field(default_factory=dict)  # "rx+2" -> score
    n_points: int = 0

    def drop(self, key: str) -> float:
        """Relative score loss of a perturbation (0.2: the score fell by 20 %)."""
        return (self.score - self.perturbed[key]) / max(abs(self.score), 1e-9)

    def to_dict(self) -> dict[str, object]:
        return {"kind": self.kind, "score": self.score, "points": self.n_points,
                "perturbed": self.perturbed,
                "relative_drop": {k: self.drop(k) for k in self.perturbed}}


def score_frames(frames: list[CheckFrame], T_camera_laser: np.ndarray, camera: PinholeCamera,
                 kind: str = "auto", rel_tol: float = 0.03) -> tuple[float, int, str]:
    """Mean score over frames: depth agreement when every frame has depth, else edges."""
    if kind == "auto":
        kind = "depth" if frames and all(f.depth is not None for f in frames) else "edges"
    missing = [f.name for f in frames if f.depth is None]
    if kind == "depth" and missing:
        raise CheckError(
            f"the depth score needs a depth map for every frame, and {len(missing)} of "
            f"{len(frames)} have none ({name_list(missing)}). Give metric depth maps with "
            "--depth DIR (<image stem> or <index:06d>, .npy or .png), or use --score edges.")
    vals, n = [], 0
    for f in frames:
        proj = project_scan(f.points, T_camera_laser, camera)
        if kind == "depth" and f.depth is not None:
            s, k = depth_agreement(f.depth, proj, rel_tol)
        else:
            s = edge_alignment(f.edges(), proj, f.jumps())
            k = len(proj.uv)
        if np.isfinite(s):
            vals.append(s * max(k, 1))
            n += max(k, 1)
    return (float(np.sum(vals) / n) if n else float("nan")), n, kind


# Below this many scored points a score says nothing about the extrinsic.
MIN_CHECK_POINTS = 10


def sensitivity(frames: list[CheckFrame], T_camera_laser: np.ndarray, camera: PinholeCamera,
                deg: float = 2.0, kind: str = "auto", source: str = "the extrinsic") -> (
                    CheckScores):
    """The score of the extrinsic and of it rotated by +-``deg`` about each camera axis.

    A ``CheckError`` naming the likely causes when fewer than ``MIN_CHECK_POINTS`` points
    can be scored (``source`` names where the extrinsic came from): a translation in
    millimetres or the inverse matrix stored put no point in any image, and the check
    printed "score nan" and exited 0.
    """
    s0, n, kind = score_frames(frames, T_camera_laser, camera, kind)
    if n < MIN_CHECK_POINTS or not np.isfinite(s0):
        raise CheckError(_why_unscored(frames, T_camera_laser, camera, n, kind, source))
    out = CheckScores(kind, s0, n_points=n)
    for axis, name in enumerate("xyz"):
        for sign in (1, -1):
            T = perturbed(T_camera_laser, axis, sign * deg)
            out.perturbed[f"r{name}{'+' if sign > 0 else '-'}{deg:g}deg"] = score_frames(
                frames, T, camera, kind)[0]
    return out


def _why_unscored(frames: list[CheckFrame], T_camera_laser: np.ndarray, camera: PinholeCamera,
                  n: int, kind: str, source: str) -> str:
    """What put (almost) no scan point where it can be scored: the unit and direction slips
    tried out (each is said with the points it would score), else where the points went."""
    head = (f"{source}: only {n} scan points of {len(frames)} frames can be scored "
            f"({kind} score; at least {MIN_CHECK_POINTS} are needed)")
    pts = [np.asarray(f.points, np.float64) for f in frames]
    total = sum(len(q) for q in pts)
    if total == 0:
        # The scans' fault, not the extrinsic's: named by their files.
        return (f"only 0 scan points of {len(frames)} frames can be scored: the scans of "
                f"these frames hold no finite points "
                f"({name_list(list(dict.fromkeys(f.scan_source or f.name for f in frames)))}):"
                " every value is NaN, infinite or at the laser. Check how the scans were "
                "exported (a lidar's no-return value written for every beam?)")
    causes = []
    offset = float(np.linalg.norm(T_camera_laser[:3, 3]))
    T_m = T_camera_laser.copy()
    T_m[:3, 3] /= 1000.0
    # One slip at a time: with a translation in millimetres the inverse lands points too.
    n_m = score_frames(frames, T_m, camera, kind)[1]
    n_inv = 0 if n_m >= MIN_CHECK_POINTS else score_frames(
        frames, inv_se3(T_camera_laser), camera, kind)[1]
    if n_m >= MIN_CHECK_POINTS or (offset > 5.0 and n_inv < MIN_CHECK_POINTS):
        causes.append(f"T_camera_laser puts the laser {offset:.3g} m from the camera: is its "
                      "translation in millimetres? It is read in metres"
                      + (f" (divided by 1000, {n_m} points would be scored)"
                         if n_m >= MIN_CHECK_POINTS else ""))
    elif n_inv >= MIN_CHECK_POINTS:
        causes.append(f"Its inverse would score {n_inv} points: is T_laser_camera stored "
                      "under the key T_camera_laser? T_camera_laser maps laser points into "
                      "the camera's optical frame (x right, y down, z forward)")
    if not causes:
        seen = sum(len(project_scan(q, T_camera_laser, camera).index) for q in pts)
        if seen < MIN_CHECK_POINTS:
            causes.append(f"{seen} of the {total} points land in the images: does the camera "
                          "look where the laser scans (the extrinsic's rotation)?")
        elif kind == "depth":
            causes.append(f"{seen} points land in the images but the depth maps hold no "
                          "valid depth there: are they metric depth maps of these images?")
        else:
            causes.append(f"{seen} points land in the images but hardly any at a range jump "
                          "(the near side of a jump of 0.2 m or more), which the edge score "
                          "needs: check frames where objects stand in front of walls, or give "
                          "depth maps (--depth)")
    return f"{head}. " + " ".join(f"{c}." for c in causes)

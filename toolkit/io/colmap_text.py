"""COLMAP text models (cameras.txt, images.txt, points3D.txt): write ours, read any.

Writing our poses and intrinsics in this format lets Gaussian-splatting and NeRF tools
(3DGS, gsplat, nerfstudio's ``colmap`` data parser) train on the toolkit's output directly.

Conventions (COLMAP's, see shared/notes/conventions.md):

- images.txt stores world-to-camera ``cam_from_world``: a Hamilton quaternion ``QW QX QY QZ``
  and a translation ``TX TY TZ``; the camera centre is ``-R^T t``. Camera axes are the
  optical frame (x right, y down, z forward), the same as ours, so no axis flip is needed.
- COLMAP puts the *corner* of the top-left pixel at (0, 0), so that pixel's centre is at
  (0.5, 0.5); ``PinholeCamera`` (OpenCV) puts that centre at (0, 0). The principal point is
  therefore written as ``cx + 0.5, cy + 0.5`` and read back with ``- 0.5``; COLMAP's own SIFT
  keypoints use the same +0.5 convention, so triangulation against them stays unbiased.
- Floats are written with ``repr`` so a write -> read round trip is exact.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from toolkit.camera import PinholeCamera
from toolkit.errors import InputError, MissingInputError
from toolkit.geometry import canonical_quat, inv_se3
from toolkit.io.atomic import atomic_write_text

# COLMAP's pixel-corner origin vs OpenCV's pixel-centre origin (see the module docstring).
PIXEL_OFFSET = 0.5


@dataclass
class ColmapImage:
    """One images.txt entry: pose as cam_from_world (quaternion wxyz, translation)."""

    image_id: int
    qvec: np.ndarray  # [4] w x y z, Hamilton, world -> camera rotation
    tvec: np.ndarray  # [3] world -> camera translation
    camera_id: int
    name: str
    xys: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # [K, 2] COLMAP pixels
    point3d_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # [K], -1

    @property
    def T_camera_world(self) -> np.ndarray:
        """[4, 4] world -> camera (COLMAP's cam_from_world)."""
        T = np.eye(4)
        w, x, y, z = self.qvec
        T[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
        T[:3, 3] = self.tvec
        return T

    @property
    def T_world_camera(self) -> np.ndarray:
        """[4, 4] camera pose in the world (the project's convention)."""
        return inv_se3(self.T_camera_world)

    @property
    def center(self) -> np.ndarray:
        """[3] camera centre in the world: -R^T t."""
        R = self.T_camera_world[:3, :3]
        return -R.T @ self.tvec


@dataclass
class ColmapModel:
    """A whole text model. ``cameras`` maps id -> (MODEL name, width, height, params)."""

    cameras: dict[int, tuple[str, int, int, np.ndarray]]
    images: list[ColmapImage]
    point_ids: np.ndarray  # [P] int64
    points: np.ndarray  # [P, 3] float64
    colors: np.ndarray  # [P, 3] uint8
    errors: np.ndarray  # [P] float64 reprojection error (px), 0 when unknown
    tracks: list[np.ndarray] = field(default_factory=list)  # per point [L, 2] image_id, idx

    def camera(self, camera_id: int = 1) -> PinholeCamera:
        """The camera as a ``PinholeCamera`` (principal point back to pixel-centre origin)."""
        model, w, h, params = self.cameras[camera_id]
        return camera_from_colmap(model, w, h, params)

    def image_by_name(self, name: str) -> ColmapImage:
        for im in self.images:
            if im.name == name:
                return im
        raise KeyError(f"no image named {name!r} in the model")


# ---------------------------------------------------------------------------- cameras


def camera_to_colmap(camera: PinholeCamera) -> tuple[str, list[float]]:
    """COLMAP model name and params, principal point shifted to COLMAP's pixel-corner origin.

    PINHOLE without distortion, OPENCV with k1 k2 p1 p2, FULL_OPENCV when k3 is set.
    """
    # PinholeCamera.to_colmap applies the +PIXEL_OFFSET shift itself.
    return camera.to_colmap()


def camera_from_colmap(model: str, width: int, height: int,
                       params: np.ndarray | list[float]) -> PinholeCamera:
    """A ``PinholeCamera`` from COLMAP's model and params (pinhole-family models only)."""
    p = [float(v) for v in params]
    if model == "SIMPLE_PINHOLE":
        f, cx, cy, dist = p[0], p[1], p[2], []
        fx = fy = f
    elif model == "PINHOLE":
        fx, fy, cx, cy, dist = p[0], p[1], p[2], p[3], []
    elif model == "SIMPLE_RADIAL":
        fx = fy = p[0]
        cx, cy, dist = p[1], p[2], [p[3]]
    elif model == "RADIAL":
        fx = fy = p[0]
        cx, cy, dist = p[1], p[2], [p[3], p[4]]
    elif model == "OPENCV":
        fx, fy, cx, cy, dist = p[0], p[1], p[2], p[3], p[4:8]
    elif model == "FULL_OPENCV":
        if any(v != 0.0 for v in p[9:12]):
            raise ValueError("FULL_OPENCV with rational terms k4..k6 has no PinholeCamera "
                             "equivalent (k1 k2 p1 p2 k3 only)")
        fx, fy, cx, cy, dist = p[0], p[1], p[2], p[3], p[4:9]
    else:
        raise ValueError(f"COLMAP camera model {model!r} is not a pinhole model this toolkit "
                         "reads (SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, "
                         "FULL_OPENCV)")
    return PinholeCamera(width, height, fx, fy, cx - PIXEL_OFFSET, cy - PIXEL_OFFSET,
                         np.asarray(dist, dtype=np.float64))


# ---------------------------------------------------------------------------- writing


def pose_to_colmap(T_world_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(qvec [4] wxyz, tvec [3]) of cam_from_world for a camera pose ``T_world_camera``."""
    T_cw = inv_se3(np.asarray(T_world_camera, dtype=np.float64))
    x, y, z, w = canonical_quat(Rotation.from_matrix(T_cw[:3, :3]).as_quat())
    return np.array([w, x, y, z]), T_cw[:3, 3].copy()


def _f(v: float) -> str:
    return repr(float(v))


def format_cameras(cameras: dict[int, tuple[str, int, int, np.ndarray]]) -> str:
    lines = ["# Camera list with one line of data per camera:",
             "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
             f"# Number of cameras: {len(cameras)}"]
    for cid, (model, w, h, params) in sorted(cameras.items()):
        lines.append(" ".join([str(cid), model, str(int(w)), str(int(h)),
                               *(_f(p) for p in params)]))
    return "\n".join(lines) + "\n"


def format_images(images: list[ColmapImage]) -> str:
    n_obs = sum(len(im.xys) for im in images)
    mean_obs = n_obs / len(images) if images else 0.0
    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
             "#   POINTS2D[] as (X, Y, POINT3D_ID)",
             f"# Number of images: {len(images)}, mean observations per image: {mean_obs}"]
    for im in images:
        if " " in im.name:
            raise ValueError(f"image name {im.name!r} contains a space; COLMAP's text format "
                             "cannot hold it")
        lines.append(" ".join([str(im.image_id), *(_f(v) for v in im.qvec),
                               *(_f(v) for v in im.tvec), str(im.camera_id), im.name]))
        lines.append(" ".join(f"{_f(x)} {_f(y)} {int(pid)}"
                              for (x, y), pid in zip(im.xys, im.point3d_ids, strict=True)))
    return "\n".join(lines) + "\n"


def format_points(model: ColmapModel) -> str:
    n = len(model.points)
    tracks = model.tracks if model.tracks else [np.zeros((0, 2), np.int64)] * n
    mean_track = float(np.mean([len(t) for t in tracks])) if n else 0.0
    lines = ["# 3D point list with one line of data per point:",
             "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
             f"# Number of points: {n}, mean track length: {mean_track}"]
    for i in range(n):
        parts = [str(int(model.point_ids[i])), *(_f(v) for v in model.points[i]),
                 *(str(int(c)) for c in model.colors[i]), _f(model.errors[i])]
        parts += [f"{int(a)} {int(b)}" for a, b in tracks[i]]
        lines.append(" ".join(parts))
    return "\n".join(lines) + "\n"


def write_colmap_model(folder: Path | str, model: ColmapModel) -> Path:
    """Write cameras.txt, images.txt, points3D.txt into ``folder`` (each atomically)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_text(folder / "cameras.txt", format_cameras(model.cameras))
    atomic_write_text(folder / "images.txt", format_images(model.images))
    atomic_write_text(folder / "points3D.txt", format_points(model))
    return folder


def _colors_uint8(C: np.ndarray) -> np.ndarray:
    """[P, 3] uint8 of colours given as integers 0..255 or floats 0..1. Integers of any width
    are 0..255 (numpy's default int64 scaled by 255 saturated to white)."""
    if np.issubdtype(C.dtype, np.integer) or C.dtype == np.bool_:
        if C.size and (C.min() < 0 or C.max() > 255):
            raise ValueError(
                f"integer point colours must lie in 0..255, got {C.min()}..{C.max()}"
            )
        return C.astype(np.uint8)
    C = np.asarray(C, dtype=np.float64)
    if C.size and not (np.nanmin(C) >= 0.0 and np.nanmax(C) <= 1.0):
        raise ValueError(
            f"float point colours must lie in 0..1, got {np.nanmin(C):g}..{np.nanmax(C):g}; "
            "pass colours 0..255 as uint8"
        )
    return np.round(np.nan_to_num(C) * 255.0).astype(np.uint8)


def model_from_poses(
    camera: PinholeCamera,
    names: list[str],
    T_world_camera: np.ndarray,
    points: np.ndarray | None = None,
    colors: np.ndarray | None = None,
    image_ids: list[int] | None = None,
    camera_id: int = 1,
) -> ColmapModel:
    """A model of our poses [N, 4, 4] and one camera; ``points`` [P, 3] (``colors`` [P, 3]
    uint8 or [0, 1] floats) become points3D without tracks, as initialisation clouds.

    ``image_ids`` default to 1..N in the given order (COLMAP ids start at 1).
    """
    poses = np.asarray(T_world_camera, dtype=np.float64).reshape(-1, 4, 4)
    if len(poses) != len(names):
        raise ValueError(f"{len(names)} image names for {len(poses)} poses")
    ids = list(range(1, len(names) + 1)) if image_ids is None else [int(i) for i in image_ids]
    model_name, params = camera_to_colmap(camera)
    images = []
    for iid, name, T in zip(ids, names, poses, strict=True):
        q, t = pose_to_colmap(T)
        images.append(ColmapImage(iid, q, t, camera_id, name))
    P = np.zeros((0, 3)) if points is None else np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if colors is None:
        C = np.full((len(P), 3), 128, np.uint8)
    else:
        C = np.asarray(colors)
        if C.shape != P.shape:
            raise ValueError(f"{len(C)} colours for {len(P)} points")
        C = _colors_uint8(C)
    return ColmapModel(
        cameras={camera_id: (model_name, camera.width, camera.height, np.asarray(params))},
        images=images,
        point_ids=np.arange(1, len(P) + 1, dtype=np.int64),
        points=P,
        colors=C,
        errors=np.zeros(len(P)),
    )


def write_poses_as_colmap(folder: Path | str, camera: PinholeCamera, names: list[str],
                          T_world_camera: np.ndarray, points: np.ndarray | None = None,
                          colors: np.ndarray | None = None) -> Path:
    """Export our poses, intrinsics and (optionally) a coloured cloud as a COLMAP text model."""
    return write_colmap_model(folder, model_from_poses(camera, names, T_world_camera, points,
                                                       colors))


# ---------------------------------------------------------------------------- reading


# Parameters of each camera model (COLMAP's src/colmap/sensor/models.h).
MODEL_PARAMS = {
    "SIMPLE_PINHOLE": "f cx cy", "PINHOLE": "fx fy cx cy", "SIMPLE_RADIAL": "f cx cy k",
    "RADIAL": "f cx cy k1 k2", "OPENCV": "fx fy cx cy k1 k2 p1 p2",
    "OPENCV_FISHEYE": "fx fy cx cy k1 k2 k3 k4",
    "FULL_OPENCV": "fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6", "FOV": "fx fy cx cy omega",
    "SIMPLE_RADIAL_FISHEYE": "f cx cy k", "RADIAL_FISHEYE": "f cx cy k1 k2",
    "THIN_PRISM_FISHEYE": "fx fy cx cy k1 k2 p1 p2 k3 k4 sx1 sy1",
}


def _numbered_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, stripped text) of every line, as COLMAP reads them (trimmed)."""
    if not path.exists():
        raise MissingInputError(f"{path}: COLMAP model file not found")
    text = path.read_text(encoding="utf-8-sig")
    return [(i + 1, ln.strip()) for i, ln in enumerate(text.splitlines())]


def _data(lines: list[tuple[int, str]]) -> list[tuple[int, str]]:
    return [(n, ln) for n, ln in lines if ln and not ln.startswith("#")]


def _parse_camera(p: list[str], where: str) -> tuple[int, tuple[str, int, int, np.ndarray]]:
    if len(p) < 4:
        raise InputError(f"{where}: camera line has {len(p)} fields; expected CAMERA_ID "
                         "MODEL WIDTH HEIGHT PARAMS[]")
    model, params = p[1], np.array([float(v) for v in p[4:]])
    names = MODEL_PARAMS.get(model)
    if names is not None and len(params) != len(names.split()):
        raise InputError(f"{where}: {model} has {len(names.split())} parameters ({names}), "
                         f"this line gives {len(params)}")
    return int(p[0]), (model, int(p[2]), int(p[3]), params)


def read_colmap_model(folder: Path | str) -> ColmapModel:
    """Read a COLMAP text model folder (cameras.txt, images.txt, points3D.txt).

    Lines are read as COLMAP reads them: trimmed, blank and ``#`` lines skipped, except
    that the line after an image line is always its observations (possibly empty).
    COLMAP >= 3.12 may add rigs.txt and frames.txt; they are ignored (one image per frame).
    Errors name the file and line.
    """
    folder = Path(folder)
    cameras: dict[int, tuple[str, int, int, np.ndarray]] = {}
    path = folder / "cameras.txt"
    for n, ln in _data(_numbered_lines(path)):
        try:
            cid, cam = _parse_camera(ln.split(), f"{path}:{n}")
        except (ValueError, IndexError) as e:
            raise ValueError(e if str(e).startswith(str(path)) else f"{path}:{n}: {e}") from None
        cameras[cid] = cam
    path = folder / "images.txt"
    lines = _numbered_lines(path)
    images = []
    k = 0
    while k < len(lines):
        n, ln = lines[k]
        k += 1
        if not ln or ln.startswith("#"):
            continue
        where = f"{path}:{n}"
        head = ln.split()
        if len(head) < 10:
            raise InputError(f"{where}: image line has {len(head)} fields; expected IMAGE_ID "
                             "QW QX QY QZ TX TY TZ CAMERA_ID NAME")
        obs_line = lines[k][1] if k < len(lines) else ""
        k += 1
        obs = obs_line.split()
        if len(obs) % 3:
            raise InputError(f"{path}:{n + 1}: observations of image {head[0]} are not "
                             "X Y POINT3D_ID triples")
        try:
            o = np.array([float(v) for v in obs]).reshape(-1, 3)
            images.append(ColmapImage(
                image_id=int(head[0]),
                qvec=np.array([float(v) for v in head[1:5]]),
                tvec=np.array([float(v) for v in head[5:8]]),
                camera_id=int(head[8]),
                name=" ".join(head[9:]),
                xys=o[:, :2].copy(),
                point3d_ids=o[:, 2].astype(np.int64),
            ))
        except ValueError as e:
            raise InputError(f"{where}: {e}") from None
    ids, pts, cols, errs, tracks = [], [], [], [], []
    points_path = folder / "points3D.txt"
    for n, ln in (_data(_numbered_lines(points_path)) if points_path.exists() else []):
        p = ln.split()
        if len(p) < 8 or (len(p) - 8) % 2:
            raise InputError(f"{points_path}:{n}: point line has {len(p)} fields; expected "
                             "POINT3D_ID X Y Z R G B ERROR and (IMAGE_ID, POINT2D_IDX) pairs")
        try:
            ids.append(int(p[0]))
            pts.append([float(v) for v in p[1:4]])
            rgb = [int(v) for v in p[4:7]]
            if not all(0 <= c <= 255 for c in rgb):
                raise ValueError(f"colour R G B {rgb} outside 0..255")
            cols.append(rgb)
            errs.append(float(p[7]))
            tracks.append(np.array([int(v) for v in p[8:]], dtype=np.int64).reshape(-1, 2))
        except ValueError as e:
            raise InputError(f"{points_path}:{n}: {e}") from None
    return ColmapModel(
        cameras=cameras,
        images=images,
        point_ids=np.array(ids, dtype=np.int64),
        points=np.array(pts, dtype=np.float64).reshape(-1, 3),
        colors=np.array(cols, dtype=np.uint8).reshape(-1, 3),
        errors=np.array(errs, dtype=np.float64),
        tracks=tracks,
    )

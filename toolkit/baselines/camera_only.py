"""The paper's "without lidar" configuration: the same map-building from the camera alone.

Poses come from COLMAP on the images (monocular: frame and scale arbitrary), and the depth
network's predictions get their scale from COLMAP's sparse points instead of the lidar:
per frame, the SfM points seen in that image play the role the projected lidar points play
in ``fuse``, with the same estimators, temporal smoothing and agreement test
(``toolkit.fusion.scale``): a frame off its neighbours whose own SfM points back its own fit
keeps it, as a relative network's output constant changes from image to image.

``scale_source`` says where the world scale comes from:

- ``sfm``: COLMAP's own units. Every frame's depth is fitted to its sparse points (scale, and
  shift for disparity models), so depth and poses agree, but the whole map is in COLMAP's
  unit: the mapper normalises the camera path to about 10 units, so the map's size in it
  follows the drive's extent, not anything the method measured.
- ``network``: the depth network's metres (``metric_depth`` outputs only). One global
  factor moves COLMAP's model into the network's units; depth is used as predicted.

The evaluation aligns to ground truth twice: rigidly (SE(3), own scale: the network's
scale error with ``network``, COLMAP's unit with ``sfm``) and by similarity (Sim(3): the
shape-error figure).
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Iterable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from toolkit.baselines.colmap import SfMResult, cam_from_world_matrix
from toolkit.camera import PinholeCamera, pixel_index

ScaleSource = Literal["auto", "network", "sfm"]


@dataclass(frozen=True)
class CameraOnlySettings:
    """How depth is scaled without the lidar and how the frames become one cloud."""

    scale_source: ScaleSource = "auto"  # auto: network for metric_depth, else sfm
    estimator: Literal["ratio", "clustered", "robust"] = "robust"
    min_points: int = 15  # SfM points a frame needs for its own fit
    # As fuse's keys of the same names; "none" keeps every frame's own fit. auto: none for
    # relative outputs, whose constant changes from image to image (relative depth in
    # x/÷1.4 per image: the window median put frames up to 3.6 % off, their own fits 0.4 %),
    # median for metric depth.
    smoothing: Literal["auto", "median", "none"] = "auto"
    smoothing_window: int = 9
    outlier_tol: float = 0.1  # log scale distance from the window median
    pixel_stride: int = 2
    edge_threshold: float = 0.06  # relative depth jump that marks a flying pixel
    # Unit-free settings, because in COLMAP units metres mean nothing: the voxel is this
    # fraction of the median SfM depth, and depth beyond max_depth_factor x that median
    # is dropped (about 2 cm and 7.5 m for a 2.5 m median).
    voxel_fraction: float = 0.008
    max_depth_factor: float = 3.0
    # SfM points nearer to a camera that sees them than this fraction of the model's median
    # point depth are not depth observations (``min_sparse_depth``).
    near_fraction: float = 0.05
    outlier_neighbors: int = 20
    outlier_std_ratio: float = 2.0


@dataclass
class SparseDepth:
    """SfM points seen in one frame: pixels [K, 2] (our convention) and z-depth [K]."""

    uv: np.ndarray
    z: np.ndarray


@dataclass
class CameraOnlyResult:
    """Poses, per-frame depth scaling and the fused cloud, all in the result's ``units``."""

    frame_indices: list[int]  # registered frames, ascending
    poses: np.ndarray  # [R, 4, 4] T_model_camera, in ``units``
    units: str  # "colmap" or "network_m"
    scale_source: str
    scale: np.ndarray  # [R] depth scale per frame (smoothed)
    shift: np.ndarray  # [R] disparity shift per frame
    used: np.ndarray  # [R] bool: the frame has a usable scale
    flags: list[str]
    points: np.ndarray  # [P, 3] float64
    colors: np.ndarray  # [P, 3] uint8
    voxel_size: float  # in ``units``
    global_factor: float = 1.0  # network mode: network metres per COLMAP unit
    info: dict[str, Any] = field(default_factory=dict)


def collapsed_depth(sfm: SfMResult) -> float:
    """Depth (model units) below which an SfM point cannot be a real observation: 1e-4 of
    the registered cameras' median distance from their median centre (robust: one camera
    registered far off does not raise it; a camera turning on the spot gives 0, no test).

    COLMAP's incremental mapper sometimes (not on every run of the same images) leaves
    points collapsed onto the camera that observes them, at ~1e-8 units along the right
    ray with a sub-pixel reprojection error: on the paper benchmark's house, 1430 of 2079
    points, which made every frame's fitted depth ~1e-8 and the camera-only map empty.
    """
    if len(sfm.poses) < 2:
        return 0.0
    c = sfm.poses[:, :3, 3]  # [R, 3] camera centres (poses are T_model_camera)
    return 1e-4 * float(np.median(np.linalg.norm(c - np.median(c, axis=0), axis=1)))


def observation_depths(sfm: SfMResult) -> np.ndarray:
    """[O] depth (model units) of every SfM point in every registered image that sees it."""
    rec = sfm.reconstruction
    if rec is None:
        return np.zeros(0)
    out = []
    for name in sfm.names:
        im = rec.find_image_with_name(name)
        obs = im.get_observation_points2D() if im is not None else []
        if len(obs) == 0:
            continue
        X = np.array([rec.points3D[p.point3D_id].xyz for p in obs], dtype=np.float64)  # [K, 3]
        T_cw = cam_from_world_matrix(im)
        out.append(X @ T_cw[2, :3] + T_cw[2, 3])
    return np.concatenate(out) if out else np.zeros(0)


def min_sparse_depth(sfm: SfMResult, near_fraction: float = 0.05) -> float:
    """Depth (model units) below which an SfM point is not taken as a depth observation:
    ``collapsed_depth``, or ``near_fraction`` of the median depth of all observations,
    whichever is larger.

    Where the robot turns on the spot, COLMAP's mapper triangulated points from nearly
    coincident camera centres close to those cameras: on the paper benchmark's house 327
    of the 375 points frame 72 sees lie at 0.03-0.12 units (1-4 % of the model's median
    depth of 2.87 units; sub-pixel reprojection errors), a thousand times above
    ``collapsed_depth``. Its own points backed the depth fit they gave, 1/80 of its
    neighbours' scale, so the frame kept a depth 1 % of the truth. A camera rarely sees a
    real surface at a twentieth of its median depth (15 cm at 3 m); a frame that only sees
    such points gets no fit of its own and takes its neighbours'.
    """
    z = observation_depths(sfm)
    z = z[z > 0]
    near = near_fraction * float(np.median(z)) if len(z) else 0.0
    return max(collapsed_depth(sfm), near)


def sparse_depth(sfm: SfMResult, name: str, camera: PinholeCamera,
                 min_z: float = 0.0) -> SparseDepth:
    """The SfM points observed in image ``name`` at depth above ``min_z`` (model units;
    ``min_sparse_depth``), at the pixels where they were observed, in the original image of
    ``camera`` (which may have distortion: predictions live there). COLMAP saw the frames
    undistorted with ``camera``'s own K (``image_folder``); its refined focal length
    (``intrinsics: unknown`` / ``refine``) would put a reprojected point up to 20 px from
    its feature."""
    rec = sfm.reconstruction
    im = rec.find_image_with_name(name)
    if im is None:
        return SparseDepth(np.zeros((0, 2)), np.zeros(0))
    obs = im.get_observation_points2D()
    if len(obs) == 0:
        return SparseDepth(np.zeros((0, 2)), np.zeros(0))
    X = np.array([rec.points3D[p.point3D_id].xyz for p in obs], dtype=np.float64)  # [K, 3]
    T_cw = cam_from_world_matrix(im)
    z = X @ T_cw[2, :3] + T_cw[2, 3]  # [K] depth in the model's units
    # The feature's pixel in the undistorted frame (COLMAP's centres at +0.5), its ray
    # through our K, and that ray's pixel in the original image.
    xy = np.array([p.xy for p in obs], dtype=np.float64) - 0.5  # [K, 2]
    ray = np.stack([(xy[:, 0] - camera.cx) / camera.fx, (xy[:, 1] - camera.cy) / camera.fy,
                    np.ones(len(xy))], -1)
    uv, _ = camera.project(ray)
    ok = (z > max(min_z, 0.0)) & camera.in_image(uv)
    return SparseDepth(uv[ok], z[ok])


def sample_prediction(values: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """[K] prediction at the nearest pixel of each ``uv`` [K, 2] (NaN outside)."""
    h, w = values.shape
    u, v = pixel_index(uv).T  # [K] each
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    out = np.full(len(uv), np.nan, np.float64)
    out[inside] = values[v[inside], u[inside]]
    return out


def resolve_scale_source(source: ScaleSource, kind: str) -> str:
    if source == "auto":
        return "network" if kind == "metric_depth" else "sfm"
    if source == "network" and kind != "metric_depth":
        raise ValueError(f"scale_source 'network' needs metric depth, but the predictions are "
                         f"{kind!r}: relative outputs carry no scale; use scale_source 'sfm'")
    return source


def resolve_smoothing(smoothing: str, kind: str) -> Literal["median", "none"]:
    """The temporal smoothing mode ``auto`` stands for with predictions of ``kind``."""
    if smoothing in ("median", "none"):
        return smoothing  # type: ignore[return-value]
    if smoothing != "auto":
        raise ValueError(f"smoothing {smoothing!r}: use auto, median or none")
    return "median" if kind == "metric_depth" else "none"


def camera_only_reconstruction(
    sfm: SfMResult,
    frame_of_name: dict[str, int],
    camera: PinholeCamera,
    read_prediction: Callable[[int], Any],
    read_rgb: Callable[[int], np.ndarray],
    available: Collection[int],
    settings: CameraOnlySettings | None = None,
    progress: Callable[[Iterable[Any]], Iterable[Any]] | None = None,
) -> CameraOnlyResult:
    """Scale every registered frame's prediction without lidar and fuse them into a cloud.

    ``read_prediction(i)`` returns a ``toolkit.depth.protocol.DepthPrediction`` for frame
    ``i``, one of the ``available`` frames; ``camera`` is the original (possibly distorted)
    one, since predictions are made on the original images.
    """
    from toolkit.fusion.cloud import CloudOptions, RayCache, depth_to_points
    from toolkit.fusion.scale import (
        ScaleEstimate,
        estimate_scale,
        pair_agreement,
        smooth_scales,
    )
    from toolkit.fusion.voxel_map import VoxelMap, statistical_inliers

    s = settings or CameraOnlySettings()
    prog = progress or (lambda it: it)
    if sfm.reconstruction is None or sfm.registered == 0:
        raise ValueError("COLMAP registered no image: nothing to build without lidar")
    items = sorted((frame_of_name[n], n, T) for n, T in zip(sfm.names, sfm.poses, strict=True)
                   if n in frame_of_name)
    items = [it for it in items if it[0] in available]
    if not items:
        raise ValueError("no registered frame has a depth prediction")
    kind = read_prediction(items[0][0]).kind
    source = resolve_scale_source(s.scale_source, kind)
    disparity = kind == "relative_disparity"

    # Pass 1: sparse SfM depth vs prediction per frame -> per-frame (scale, shift).
    estimates, ratios = [], []
    pairs: list[tuple[np.ndarray, np.ndarray]] = []  # per frame: SfM depth [K], prediction [K]
    min_z = min_sparse_depth(sfm, s.near_fraction)
    for i, name, _ in prog(items):
        pred = read_prediction(i)
        sp = sparse_depth(sfm, name, camera, min_z)
        d = sample_prediction(pred.values, sp.uv)
        pairs.append((sp.z, d))
        if source == "network":
            ok = np.isfinite(d) & (d > 0)
            if ok.sum() >= s.min_points:
                ratios.append(np.median(d[ok] / sp.z[ok]))
            estimates.append(ScaleEstimate(1.0, 0.0, int(ok.sum()), int(ok.sum())))
        else:
            estimates.append(estimate_scale(s.estimator, sp.z, d, disparity,
                                            min_pairs=s.min_points))
    smoothing = "none" if source == "network" else resolve_smoothing(s.smoothing, kind)
    if source == "network":
        if not ratios:
            raise ValueError("no frame has enough SfM points to relate COLMAP's units to the "
                             "network's metres")
        factor = float(np.median(ratios))  # network metres per COLMAP unit
        scale = np.ones(len(items))
        shift = np.zeros(len(items))
        used = np.ones(len(items), bool)
        flags = ["ok"] * len(items)
    else:
        factor = 1.0
        # Half the outlier distance, as fuse: scales that far apart cannot both take a
        # pair. Without this test a relative network's per-image constant (drawn in
        # x/÷1.4) was overwritten by the neighbours' in 8 of 12 frames: depth AbsRel 0.151
        # where each frame's own fit gave 0.0033.
        tol = s.outlier_tol / 2

        def agreement(k: int, scale_k: float, shift_k: float) -> float:
            # The agreeing SfM points must span depths (1.25x): one object backs any scale.
            return pair_agreement(pairs[k][0], pairs[k][1], disparity, scale_k, shift_k, tol,
                                  min_spread=1.25)
        sm = smooth_scales(estimates, s.smoothing_window, s.outlier_tol, smoothing,
                           "smoothed", agreement)
        scale, shift, used, flags = sm.scale, sm.shift, sm.used, list(sm.flag)
    all_z = np.concatenate([z for z, _ in pairs]) * factor if pairs else np.zeros(0)
    median_depth = float(np.median(all_z)) if len(all_z) else 1.0
    voxel = s.voxel_fraction * median_depth
    poses = np.stack([T for _, _, T in items]).copy()
    poses[:, :3, 3] *= factor

    # Pass 2: scaled depth -> coloured points in the model frame -> voxel map.
    rays = RayCache(camera, s.pixel_stride)
    opts = CloudOptions(min_depth_m=1e-6, max_depth_m=s.max_depth_factor * median_depth,
                        edge_threshold=s.edge_threshold, stride=s.pixel_stride)
    vmap = VoxelMap(voxel)
    for k, (i, _, _) in enumerate(prog(items)):
        if not used[k]:
            continue
        depth = read_prediction(i).as_depth(float(scale[k]), float(shift[k]))
        pts, col, _ = depth_to_points(depth, read_rgb(i), rays, poses[k], opts)
        vmap.integrate(pts.astype(np.float64), col, i)
    m = vmap.arrays()
    keep = statistical_inliers(m.points, s.outlier_neighbors, s.outlier_std_ratio) if (
        s.outlier_neighbors > 0) else np.ones(len(m.points), bool)
    return CameraOnlyResult(
        frame_indices=[i for i, _, _ in items], poses=poses,
        units="network_m" if source == "network" else "colmap", scale_source=source,
        scale=np.asarray(scale, float), shift=np.asarray(shift, float),
        used=np.asarray(used, bool), flags=flags, points=m.points[keep], colors=m.colors[keep],
        voxel_size=voxel, global_factor=factor,
        info={"kind": kind, "median_sparse_depth": median_depth,
              "smoothing": smoothing,
              "frames_fitted": int(sum(e.ok for e in estimates))},
    )


def depth_of(result: CameraOnlyResult, k: int, prediction: Any) -> np.ndarray:
    """[H, W] z-depth of registered frame ``k`` in the result's units (NaN invalid)."""
    return prediction.as_depth(float(result.scale[k]), float(result.shift[k]))


def apply_similarity(S: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points [N, 3] through a [4, 4] similarity (scale folded into the rotation block)."""
    return np.asarray(points, dtype=np.float64) @ S[:3, :3].T + S[:3, 3]


def alignments(est_poses: np.ndarray, ref_poses: np.ndarray) -> dict[str, np.ndarray]:
    """{"se3": [4, 4], "sim3": [4, 4]} mapping the estimate's frame onto the reference, from
    corresponding poses [N, 4, 4] (``pose_alignment``: a straight drive's turn about its
    line comes from the orientations; positions alone left it to noise, 35 deg off)."""
    from toolkit.geometry import pose_alignment, sim3

    out = {}
    for tag, with_scale in (("se3", False), ("sim3", True)):
        R, t, c = pose_alignment(est_poses, ref_poses, with_scale)
        out[tag] = sim3(R, t, c)
    return out


def pose_in_reference(S: np.ndarray, T: np.ndarray) -> np.ndarray:
    """A camera pose [4, 4] moved by similarity ``S``: rotation stays orthonormal."""
    c = float(np.cbrt(np.linalg.det(S[:3, :3])))
    out = np.eye(4)
    out[:3, :3] = (S[:3, :3] / c) @ T[:3, :3]
    out[:3, 3] = S[:3, :3] @ T[:3, 3] + S[:3, 3]
    return out


"""COLMAP baseline on a small ray-cast textured room: SfM, Sim(3) alignment, triangulation
at fixed poses, and the saved model's round trip."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from toolkit.baselines.synthetic import SyntheticRoom, default_camera, orbit_poses
from toolkit.camera import PinholeCamera
from toolkit.geometry import Trajectory

pycolmap = pytest.importorskip("pycolmap")

from toolkit.baselines.colmap import (  # noqa: E402  (needs pycolmap)
    ColmapSettings,
    SfMResult,
    evaluate_sfm_trajectory,
    extract_and_match,
    load_sfm,
    run_sfm,
    save_sfm,
    triangulate_known_poses,
)
from toolkit.baselines.common import write_png  # noqa: E402

N_IMAGES = 12
SETTINGS = ColmapSettings(matching="sequential", overlap=5, max_features=2048)


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> dict:
    room = SyntheticRoom()
    cam = default_camera(256, 192, 70.0)
    poses = orbit_poses(room, N_IMAGES, radius_m=0.8, sweep_deg=100.0)
    root = tmp_path_factory.mktemp("colmap_scene")
    render = room.renderer()
    names, images, depths = [], [], []
    for i, T in enumerate(poses):
        rgb, depth = render.render(cam, T)
        names.append(f"{i:06d}.png")
        images.append(rgb)
        depths.append(depth)
        write_png(root / "images" / names[-1], rgb)
    db = root / "database.db"
    extract_and_match(db, root / "images", names, cam, SETTINGS)
    return {"room": room, "root": root, "cam": cam, "poses": poses, "names": names, "db": db,
            "images": images, "depths": depths}


@pytest.fixture(scope="module")
def sfm(scene: dict) -> SfMResult:
    return run_sfm(scene["root"] / "images", scene["names"], scene["cam"],
                   scene["root"] / "sfm", SETTINGS, database=scene["db"])


def test_sfm_registers_images_and_aligns_to_the_true_path(scene: dict, sfm: SfMResult) -> None:
    assert sfm.registered >= N_IMAGES - 1
    assert sfm.models == 1
    assert sfm.points > 500
    assert sfm.reprojection_error_px < 0.5
    stamps = {n: 10.0 + i for i, n in enumerate(scene["names"])}
    ref = Trajectory(10.0 + np.arange(N_IMAGES), scene["poses"], "world", "camera")
    e = evaluate_sfm_trajectory(sfm.trajectory(stamps), ref)
    assert e["poses_compared"] == sfm.registered
    # Shape right to millimetres over a ~1.2 m path; scale arbitrary, so a rigid alignment
    # that keeps COLMAP's own scale is far off unless COLMAP happened to pick metres.
    assert e["ate_sim3_rmse_m"] < 0.01, e
    assert e["are_sim3_rmse_deg"] < 1.5, e
    if abs(e["scale_to_reference"] - 1.0) > 0.2:
        assert e["ate_se3_rmse_m"] > 10 * e["ate_sim3_rmse_m"]
    # The estimated camera is ours when intrinsics are known (held fixed).
    assert sfm.camera == scene["cam"]
    # save_sfm / load_sfm give back the same poses and names.
    frame_of = {n: i for i, n in enumerate(scene["names"])}
    save_sfm(sfm, scene["root"] / "saved", frame_of, stamps, scene["names"])
    back, frame_back, stamp_back = load_sfm(scene["root"] / "saved")
    assert back.names == sfm.names and frame_back == frame_of and stamp_back == stamps
    np.testing.assert_allclose(back.poses, sfm.poses, atol=1e-9)
    assert back.points == sfm.points
    # ... and the mapper that made the model; a model saved before it was recorded: None.
    assert sfm.mapper == "incremental" and back.mapper == "incremental"
    summary = scene["root"] / "saved" / "summary.json"
    old = {k: v for k, v in json.loads(summary.read_text()).items() if k != "mapper"}
    summary.write_text(json.dumps(old))
    assert load_sfm(scene["root"] / "saved")[0].mapper is None


def test_triangulation_at_fixed_poses_checks_poses_and_intrinsics(scene: dict) -> None:
    from scipy.spatial.transform import Rotation

    from toolkit.eval.map_accuracy import MeshDistance

    cam: PinholeCamera = scene["cam"]
    images, poses, db = scene["root"] / "images", scene["poses"], scene["db"]
    surface = MeshDistance(scene["room"].mesh())

    def triangulate(camera: PinholeCamera, P: np.ndarray, tag: str) -> tuple[float, float]:
        tri = triangulate_known_poses(images, scene["names"], camera, P, scene["root"] / tag,
                                      SETTINGS, database=db)
        assert tri.points > 500 and tri.mean_track_length > 3
        return tri.reprojection_error_px, float(np.median(surface.distance(tri.points_xyz())))

    # True poses and intrinsics: sub-pixel tracks, points on the room's surfaces (so the
    # model really is in our world frame).
    err, dist = triangulate(cam, poses, "tri")
    assert err < 0.3 and dist < 0.01, (err, dist)
    # Poses off by ~1 cm / 0.5 deg: the tracks no longer close.
    rng = np.random.default_rng(0)
    noisy = poses.copy()
    noisy[:, :3, 3] += rng.normal(0, 0.01, (len(poses), 3))
    noisy[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, np.radians(0.5), (len(poses), 3))
                                            ).as_matrix() @ noisy[:, :3, :3]
    err_p, _ = triangulate(cam, noisy, "tri_poses")
    assert err_p > 1.0 > 3 * err, (err_p, err)
    # A 2 % focal error barely shows in the reprojection error (a turning camera sees a
    # consistently rescaled scene) but moves the points off the surface: check both.
    wrong = PinholeCamera(cam.width, cam.height, cam.fx * 1.02, cam.fy * 1.02, cam.cx, cam.cy)
    err_f, dist_f = triangulate(wrong, poses, "tri_focal")
    assert err_f < 0.5 and dist_f > 5 * dist, (err_f, dist_f, dist)


def test_global_mapper_registers_the_views_and_recovers_the_path(
        scene: dict, monkeypatch: pytest.MonkeyPatch) -> None:
    """mapper: global runs pycolmap.global_mapping on the same database, with our K held
    fixed, one thread and our seed, and gets the orbit's shape as incremental mapping does."""
    calls: list[Any] = []
    real = pycolmap.global_mapping

    def spy(*args: Any, **kwargs: Any) -> Any:
        calls.append(kwargs["options"])
        return real(*args, **kwargs)

    monkeypatch.setattr(pycolmap, "global_mapping", spy)
    monkeypatch.setattr(pycolmap, "incremental_mapping",
                        lambda *a, **kw: pytest.fail("incremental mapping ran"))
    sfm = run_sfm(scene["root"] / "images", scene["names"], scene["cam"],
                  scene["root"] / "sfm_global", replace(SETTINGS, mapper="global"),
                  database=scene["db"])
    assert len(calls) == 1
    opts = calls[0]
    ba = opts.mapper.bundle_adjustment
    assert not ba.refine_focal_length and not ba.refine_extra_params
    assert opts.mapper.num_threads == 1 and opts.mapper.random_seed == SETTINGS.seed
    assert sfm.registered == N_IMAGES and sfm.models == 1 and sfm.points > 500
    assert sfm.reprojection_error_px < 0.5
    assert sfm.camera == scene["cam"]  # K held fixed through its bundle adjustments
    stamps = {n: 10.0 + i for i, n in enumerate(scene["names"])}
    ref = Trajectory(10.0 + np.arange(N_IMAGES), scene["poses"], "world", "camera")
    e = evaluate_sfm_trajectory(sfm.trajectory(stamps), ref)
    assert e["ate_sim3_rmse_m"] < 0.01 and e["are_sim3_rmse_deg"] < 1.5, e


def test_global_mapper_refines_intrinsics_only_when_asked(tmp_path: Path) -> None:
    from toolkit.baselines.colmap import _global_options

    for intrinsics, refined in (("known", False), ("refine", True), ("unknown", True)):
        ba = _global_options(ColmapSettings(intrinsics=intrinsics)).mapper.bundle_adjustment
        assert (ba.refine_focal_length, ba.refine_extra_params) == (refined, refined)
        assert not ba.refine_principal_point
    with pytest.raises(ValueError, match="mapper"):
        run_sfm(tmp_path, ["a.png"], None, tmp_path / "w",
                ColmapSettings(mapper="hierarchical"))  # type: ignore[arg-type]
    assert not (tmp_path / "w").exists()  # refused before any work


def test_sfm_without_matches_reports_nothing_registered(tmp_path: Path) -> None:
    # Two flat grey images: no features, so no model - a result, not an exception.
    cam = default_camera(64, 48)
    for i in range(2):
        write_png(tmp_path / "images" / f"{i}.png", np.full((48, 64, 3), 128, np.uint8))
    sfm = run_sfm(tmp_path / "images", ["0.png", "1.png"], cam, tmp_path / "w", SETTINGS)
    assert sfm.registered == 0 and sfm.reconstruction is None
    assert sfm.summary()["registered_fraction"] == 0.0


def test_camera_only_scales_relative_disparity_with_sfm_points(scene: dict,
                                                              sfm: SfMResult) -> None:
    """Without lidar, SfM points fix each frame's disparity scale and shift: the depth then
    agrees with COLMAP's units, i.e. with the truth up to one global (Sim(3)) scale."""
    pytest.importorskip("sklearn")
    from toolkit.baselines.camera_only import (
        CameraOnlySettings,
        alignments,
        camera_only_reconstruction,
        depth_of,
    )
    from toolkit.depth.protocol import DepthPrediction

    def prediction(i: int) -> DepthPrediction:
        d = scene["depths"][i]
        # Relative disparity: 1/z up to a per-frame scale and shift (as Depth Anything).
        disp = np.where(d > 0, 0.5 * (1 + 0.05 * i) / np.where(d > 0, d, 1) + 0.2, np.nan)
        return DepthPrediction(disp.astype(np.float32), "relative_disparity")

    frame_of = {n: i for i, n in enumerate(scene["names"])}
    res = camera_only_reconstruction(sfm, frame_of, scene["cam"], prediction,
                                     lambda i: scene["images"][i], set(range(N_IMAGES)),
                                     CameraOnlySettings(smoothing_window=1))
    assert res.scale_source == "sfm" and res.units == "colmap"
    assert res.used.all() and len(res.points) > 5000
    with pytest.raises(ValueError, match="metric depth"):
        camera_only_reconstruction(sfm, frame_of, scene["cam"], prediction,
                                   lambda i: scene["images"][i], set(range(N_IMAGES)),
                                   CameraOnlySettings(scale_source="network"))
    S = alignments(res.poses, scene["poses"][res.frame_indices])["sim3"]
    s = float(np.cbrt(np.linalg.det(S[:3, :3])))  # metres per COLMAP unit
    for k, i in enumerate(res.frame_indices):
        d, gt = depth_of(res, k, prediction(i)) * s, scene["depths"][i]
        ok = (gt > 0) & np.isfinite(d)
        rel = np.abs(d[ok] - gt[ok]) / gt[ok]
        assert np.median(rel) < 0.01, (i, np.median(rel))


def test_camera_only_keeps_each_frames_own_scale_of_a_relative_network(
        scene: dict, sfm: SfMResult) -> None:
    """A relative network normalises every image on its own (Depth Anything, MiDaS): its
    output constant jumps from frame to frame. Each frame's own SfM fit recovers it; the
    stage's default smoothing (window 9, outlier_tol 0.1) handed 8 of 12 frames their
    neighbours' scale (depth 15 % off on average, 30 % at worst)."""
    pytest.importorskip("sklearn")
    from toolkit.baselines.camera_only import (
        CameraOnlySettings,
        alignments,
        camera_only_reconstruction,
        depth_of,
    )
    from toolkit.depth.protocol import DepthPrediction

    a = np.exp(np.random.default_rng(3).uniform(np.log(0.7), np.log(1.4), N_IMAGES))  # [F]

    def predictor(kind: str) -> Any:
        def prediction(i: int) -> DepthPrediction:
            d = scene["depths"][i]
            ok = d > 0
            if kind == "relative_disparity":
                inv = np.where(ok, 1 / np.where(ok, d, 1), np.nan)
                v = a[i] * (inv + 0.15 * np.nanmedian(inv))
            else:
                v = np.where(ok, a[i] * d, np.nan)
            return DepthPrediction(v.astype(np.float32), kind)
        return prediction

    frame_of = {n: i for i, n in enumerate(scene["names"])}
    # The defaults (auto: no smoothing for relative outputs), and the window median with
    # the agreement test on its own for the (scale, shift) fits of disparity.
    for kind, smoothing in (("relative_disparity", "auto"), ("relative_depth", "auto"),
                            ("relative_disparity", "median")):
        prediction = predictor(kind)
        res = camera_only_reconstruction(sfm, frame_of, scene["cam"], prediction,
                                         lambda i: scene["images"][i], set(range(N_IMAGES)),
                                         CameraOnlySettings(smoothing=smoothing,
                                                            pixel_stride=4))
        assert res.flags == ["ok"] * len(res.flags), (kind, smoothing, res.flags)
        S = alignments(res.poses, scene["poses"][res.frame_indices])["sim3"]
        s = float(np.cbrt(np.linalg.det(S[:3, :3])))  # metres per COLMAP unit
        for k, i in enumerate(res.frame_indices):
            d, gt = depth_of(res, k, prediction(i)) * s, scene["depths"][i]
            ok = (gt > 0) & np.isfinite(d)
            rel = float(np.median(np.abs(d[ok] - gt[ok]) / gt[ok]))
            assert rel < 0.01, (kind, smoothing, i, rel)


def test_alignments_of_a_straight_drive_take_the_turn_about_it_from_the_orientations() -> None:
    """Camera positions along a line (1 mm of wobble, 5 mm of SfM noise) leave the turn
    about the line to noise: positions alone put it 35 deg off, and a map point 2 m beside
    the path 1.4 m away. The orientations fix it; the scale is the positions'."""
    from scipy.spatial.transform import Rotation

    from toolkit.baselines.camera_only import alignments
    from toolkit.geometry import se3, sim3

    rng = np.random.default_rng(0)
    n = 50
    R_cam = Rotation.from_euler("xyz", [-90, 0, -90], degrees=True).as_matrix()
    ref = np.stack([se3(R_cam, [x, 0.001 * np.sin(x), 0.45]) for x in np.linspace(0, 10, n)])
    S_true = sim3(Rotation.from_euler("xyz", [20, -30, 50], degrees=True).as_matrix(),
                  np.array([1.0, 2.0, -0.5]), 0.5)  # the estimate's frame -> the reference's
    S_inv = np.linalg.inv(S_true)
    est = ref.copy()
    est[:, :3, :3] = S_inv[:3, :3] / 2.0 @ ref[:, :3, :3]  # S_inv is 2 x a rotation
    est[:, :3, 3] = ref[:, :3, 3] @ S_inv[:3, :3].T + S_inv[:3, 3]
    est[:, :3, 3] += rng.normal(0, 0.005 * 2.0, (n, 3))
    al = alignments(est, ref)
    point = np.array([5.0, 2.0, 0.45])  # beside the path, in the reference frame
    in_est = S_inv[:3, :3] @ point + S_inv[:3, 3]
    assert np.linalg.norm(al["sim3"][:3, :3] @ in_est + al["sim3"][:3, 3] - point) < 0.05
    assert float(np.cbrt(np.linalg.det(al["sim3"][:3, :3]))) == pytest.approx(0.5, rel=0.01)
    R_se3 = al["se3"][:3, :3]
    assert np.degrees(Rotation.from_matrix(R_se3.T @ S_true[:3, :3] / 0.5).magnitude()) < 0.5


def test_frames_in_a_gap_of_the_trajectory_get_no_pose(tmp_path: Path) -> None:
    """The SLAM gives the frames in a gap between its poses none (a straight line across
    it is a guess); the TSDF, triangulation and COLMAP export took such an invented pose."""
    from toolkit.baselines.common import poses_at_frames
    from toolkit.fusion.synthetic import write_box_room
    from toolkit.geometry import Trajectory
    from toolkit.io.sequence import read_sequence

    seq = read_sequence(write_box_room(tmp_path / "seq", n_frames=30))
    gt = seq.groundtruth.poses_base
    keep = np.ones(len(gt), bool)
    keep[len(gt) // 3: 2 * len(gt) // 3] = False
    holed = Trajectory(gt.stamps[keep], gt.poses[keep], gt.frame, gt.child)
    idx, poses = poses_at_frames(holed, seq)
    assert 0 < len(idx) < len(seq.frames) and len(poses) == len(idx)
    assert holed.covers(seq.frame_stamps[idx], slack_s=0.05).all()


def _points_pulled_to_their_camera(scene: dict, sfm: SfMResult, tmp_path: Path,
                                   fraction: float) -> tuple[SfMResult, str]:
    """A copy of ``sfm`` whose middle frame has 80 % of its points moved towards its camera
    to ``fraction`` of their distance, and that frame's name."""
    from toolkit.baselines.colmap import cam_from_world_matrix

    frame_of = {n: i for i, n in enumerate(scene["names"])}
    save_sfm(sfm, tmp_path / "m", frame_of, {n: float(i) for n, i in frame_of.items()},
             scene["names"])
    bad, _, _ = load_sfm(tmp_path / "m")  # a copy to damage
    rec = bad.reconstruction
    name = bad.names[len(bad.names) // 2]
    im = rec.find_image_with_name(name)
    T = cam_from_world_matrix(im)
    centre = -T[:3, :3].T @ T[:3, 3]
    ids = [o.point3D_id for o in im.get_observation_points2D()]
    for pid in ids[: int(0.8 * len(ids))]:
        pt = rec.points3D[pid]
        pt.xyz = centre + fraction * (np.array(pt.xyz) - centre)
    return bad, name


def _assert_frame_keeps_its_sound_scale(scene: dict, sfm: SfMResult, bad: SfMResult,
                                        name: str) -> None:
    """Camera only on ``sfm`` and on its damaged copy ``bad``: frame ``name`` keeps the
    scale it has on the sound model (fitted to a relative prediction twice the depth)."""
    from toolkit.baselines.camera_only import CameraOnlySettings, camera_only_reconstruction
    from toolkit.depth.protocol import DepthPrediction

    def prediction(i: int) -> DepthPrediction:
        d = scene["depths"][i]
        return DepthPrediction(np.where(d > 0, 2.0 * d, np.nan).astype(np.float32),
                               "relative_depth")

    frame_of = {n: i for i, n in enumerate(scene["names"])}
    runs = [camera_only_reconstruction(m, frame_of, scene["cam"], prediction,
                                       lambda i: scene["images"][i], set(range(N_IMAGES)),
                                       CameraOnlySettings(smoothing_window=1))
            for m in (sfm, bad)]
    k = runs[1].frame_indices.index(frame_of[name])
    assert runs[1].used[k] and runs[1].scale[k] == pytest.approx(runs[0].scale[k], rel=0.02)


def test_points_collapsed_onto_their_camera_are_not_taken_as_depth(
        scene: dict, sfm: SfMResult, tmp_path: Path) -> None:
    """COLMAP's mapper sometimes leaves points ~1e-8 units from the camera that sees them,
    on the right ray (sub-pixel reprojection error): they must not set that frame's scale."""
    pytest.importorskip("sklearn")
    from toolkit.baselines.camera_only import collapsed_depth, sparse_depth

    bad, name = _points_pulled_to_their_camera(scene, sfm, tmp_path, 1e-8)
    assert np.median(sparse_depth(bad, name, scene["cam"]).z) < 1e-6  # the damage took
    floor = collapsed_depth(bad)
    assert 0 < floor < 1e-3
    kept = sparse_depth(bad, name, scene["cam"], floor)
    assert len(kept.z) > 0 and kept.z.min() > 0.01
    # The damaged frame keeps the scale its sound points give (collapsed: ~1e-8 of it).
    _assert_frame_keeps_its_sound_scale(scene, sfm, bad, name)


def test_points_triangulated_next_to_their_camera_do_not_set_its_scale(
        scene: dict, sfm: SfMResult, tmp_path: Path) -> None:
    """Turning on the spot, COLMAP put most of a frame's points at 1-4 % of their depth
    (sub-pixel reprojection errors, far above the 1e-8 collapse); they backed a depth fit
    1/80 of the neighbours', and the frame kept it."""
    pytest.importorskip("sklearn")
    # Most of its points at 2 % of their depth, as the house's frame 72.
    bad, name = _points_pulled_to_their_camera(scene, sfm, tmp_path, 0.02)
    _assert_frame_keeps_its_sound_scale(scene, sfm, bad, name)


def test_sparse_depth_pairs_each_point_with_the_pixel_it_was_seen_at() -> None:
    """Reprojected with our camera, a model reconstructed with a focal 15 % off (COLMAP's
    own, intrinsics: unknown / refine) put each SfM depth up to 20 px from its feature."""
    from types import SimpleNamespace as NS

    from toolkit.baselines.camera_only import sparse_depth

    ours = PinholeCamera(320, 240, 200.0, 200.0, 159.5, 119.5)
    seen_at = np.array([[300.0, 100.0], [30.0, 200.0], [159.5, 119.5]])
    z = np.array([2.0, 3.0, 4.0])
    f_model = 230.0  # the model is consistent with its own focal length
    X = np.c_[(seen_at - [159.5, 119.5]) / f_model * z[:, None], z]
    image = NS(get_observation_points2D=lambda: [NS(point3D_id=k, xy=seen_at[k] + 0.5)
                                                 for k in range(3)],
               cam_from_world=NS(matrix=lambda: np.eye(4)[:3]))
    rec = NS(find_image_with_name=lambda name: image,
             points3D={k: NS(xyz=X[k]) for k in range(3)})
    sp = sparse_depth(NS(reconstruction=rec), "a.png", ours)
    np.testing.assert_allclose(sp.uv, seen_at, atol=1e-9)
    np.testing.assert_allclose(sp.z, z)


def test_sample_prediction_reads_the_pixel_whose_span_holds_the_point() -> None:
    """Pixel k covers [k - 0.5, k + 0.5) (the lidar pixels' rule): np.rint read
    u = 0.5 from pixel 0 and v = 2.5 from row 2."""
    from toolkit.baselines.camera_only import sample_prediction

    values = np.arange(20, dtype=np.float32).reshape(4, 5)  # [H, W] value = row * 5 + col
    uv = np.array([[0.5, 2.5], [1.5, 0.0], [4.4, 3.4], [4.5, 0.0]])
    out = sample_prediction(values, uv)
    np.testing.assert_array_equal(out[:3], [3 * 5 + 1, 0 * 5 + 2, 3 * 5 + 4])
    assert np.isnan(out[3])  # pixel 5 is past the image

"""The extrinsic check: overlays and scores that tell a 2 degree error from the truth."""

from __future__ import annotations

import numpy as np
import pytest
from recipe_helpers import SequenceFolder, run_stages  # the tests folder is on sys.path

from calibration.check import (
    CheckFrame,
    overlay,
    project_scan,
    score_frames,
    sensitivity,
)
from toolkit.camera import PinholeCamera
from toolkit.geometry import inv_se3, se2_to_se3, se3

R_BASE_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
ROOM = (np.array([-1.0, -3.0, 0.0]), np.array([6.0, 3.0, 2.5]))
BOXES = [  # (lo, hi, grey level): furniture the laser plane cuts
    (np.array([2.0, 0.5, 0.0]), np.array([2.5, 1.2, 0.8]), 60.0),
    (np.array([3.5, -1.5, 0.0]), np.array([4.0, -0.8, 1.0]), 200.0),
    (np.array([1.5, -0.6, 0.0]), np.array([1.7, -0.4, 1.2]), 30.0),
    (np.array([4.5, 1.0, 0.0]), np.array([5.0, 2.0, 0.6]), 170.0),
    (np.array([3.0, 0.2, 0.0]), np.array([3.2, 0.4, 1.5]), 90.0),
]


def _raycast(o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distances [N] along unit-ish rays [N, 3] from ``o`` [3], and grey levels [N]."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        lo, hi = ROOM
        t = np.min(np.maximum((lo - o) * inv, (hi - o) * inv), axis=1)  # leave the room
        grey = np.where(np.abs(d[:, 2]) > 1e-9, np.where(d[:, 2] < 0, 140.0, 230.0), 120.0)
        wall = (o + t[:, None] * d)[:, 2]
        grey = np.where((wall > 0.01) & (wall < 2.49), 120.0, grey)  # walls vs floor/ceiling
        for blo, bhi, g in BOXES:
            a, b = (blo - o) * inv, (bhi - o) * inv
            tmin = np.max(np.minimum(a, b), axis=1)
            tmax = np.min(np.maximum(a, b), axis=1)
            hit = (tmax >= tmin) & (tmin > 0) & (tmin < t)
            t = np.where(hit, tmin, t)
            grey = np.where(hit, g, grey)
    return t, grey


def _frames(camera: PinholeCamera, T_base_camera: np.ndarray, T_base_laser: np.ndarray) -> (
    list[CheckFrame]
):
    frames = []
    rays = camera.pixel_rays().reshape(-1, 3)  # [P, 3], z = 1
    ang = np.radians(np.arange(-180.0, 180.0, 0.5))
    beams = np.c_[np.cos(ang), np.sin(ang), np.zeros(len(ang))]
    for k, yaw in enumerate(np.linspace(-0.5, 0.5, 5)):
        T_wb = se2_to_se3(0.0, 0.2 * k - 0.4, yaw)
        T_wc, T_wl = T_wb @ T_base_camera, T_wb @ T_base_laser
        t, grey = _raycast(T_wc[:3, 3], rays @ T_wc[:3, :3].T)
        depth = t.reshape(camera.height, camera.width)  # rays have z = 1: t is the depth
        img = np.repeat(grey.reshape(camera.height, camera.width, 1), 3, 2).astype(np.uint8)
        r, _ = _raycast(T_wl[:3, 3], beams @ T_wl[:3, :3].T)
        frames.append(CheckFrame(f"f{k}", img, beams * r[:, None], depth.astype(np.float32)))
    return frames


@pytest.fixture(scope="module")
def scene() -> tuple[list[CheckFrame], PinholeCamera, np.ndarray]:
    camera = PinholeCamera.from_fov(320, 240, 70.0)
    T_bc = se3(R_BASE_OPTICAL, [0.05, 0.0, 0.5])
    T_bl = se3(np.eye(3), [0.0, 0.0, 0.3])
    return _frames(camera, T_bc, T_bl), camera, inv_se3(T_bc) @ T_bl


def test_depth_score_separates_a_2_degree_error(scene) -> None:  # noqa: ANN001
    frames, camera, T = scene
    sc = sensitivity(frames, T, camera, 2.0, "depth")
    assert sc.kind == "depth" and sc.score > 0.95 and sc.n_points > 500
    # Yaw (about camera y) is what a horizontal scan sees. Tilts move the points up or
    # down vertical walls, invisible here where no object top is near the scan plane
    # (the simulated house has some: there tilts cost 3-7 %); they must not look better.
    assert sc.drop("ry+2deg") > 0.2 and sc.drop("ry-2deg") > 0.2
    assert all(sc.drop(k) > -0.01 for k in sc.perturbed), sc.to_dict()


def test_edge_score_sees_yaw(scene) -> None:  # noqa: ANN001
    frames, camera, T = scene
    no_depth = [CheckFrame(f.name, f.image, f.points) for f in frames]
    s0, _, kind = score_frames(no_depth, T, camera)
    assert kind == "edges" and s0 > 1.5  # discontinuities land on edges, far above chance
    sc = sensitivity(no_depth, T, camera, 2.0)
    assert sc.drop("ry+2deg") > 0.1 and sc.drop("ry-2deg") > 0.1, sc.to_dict()


def test_overlay_draws_points_coloured_by_range(scene) -> None:  # noqa: ANN001
    frames, camera, T = scene
    proj = project_scan(frames[0].points, T, camera)
    assert len(proj.uv) > 50 and np.all(camera.in_image(proj.uv))
    img = overlay(frames[0].image, proj)
    assert img.shape == frames[0].image.shape and (img != frames[0].image).any()
    assert (frames[0].image == overlay(frames[0].image, project_scan(
        np.zeros((0, 2)), T, camera))).all()


def test_overlay_of_a_small_image_leaves_out_the_range_legend() -> None:
    """An image too small for the range legend (the 32x24 frames of a test bag) stopped
    check with numpy's "could not broadcast (10,10,3) into (0,10,3)"."""
    from calibration.check import Projection

    img = np.full((24, 32, 3), 90, np.uint8)
    proj = Projection(np.array([[5.0, 5.0], [20.0, 12.0]]), np.array([1.0, 2.0]),
                      np.array([1.0, 2.0]), np.array([0, 1]))
    out = overlay(img, proj, radius=1)
    assert out.shape == img.shape and (out[5, 5] != 90).any() and (out[0, 31] == 90).all()


def _write_sequence(scene, root):  # noqa: ANN001, ANN202
    """The boxes scene as a sequence folder (images, scans, ground-truth depth, rig)."""
    from toolkit.io.sequence import SequenceWriter
    from toolkit.sensors import LaserScan, Rig

    frames, camera, T = scene
    T_bc = se3(R_BASE_OPTICAL, [0.05, 0.0, 0.5])
    w = SequenceWriter(root, Rig(camera, T_bc, T_bc @ T), name="boxes")
    for k, f in enumerate(frames):
        w.add_frame(10.0 + k, f.image, gt_depth=f.depth)
        r = np.linalg.norm(f.points[:, :2], axis=1)
        w.add_scan(LaserScan(10.0 + k, r, -np.pi, np.radians(0.5)))
    w.close()
    return T_bc


def _run_with_sequence(seq_dir, stages, tmp_path):  # noqa: ANN001, ANN202
    """Run ``stages`` after a stage that provides the sequence folder ``seq_dir``."""
    from calibration.stage import CalibrateStage

    return run_stages(tmp_path, [{"stage": "t_sequence", "path": str(seq_dir)}, *stages],
                      {"t_sequence": SequenceFolder, "calibrate": CalibrateStage})


def test_stage_with_upstream_sequence_checks_the_result(scene, tmp_path) -> None:  # noqa: ANN001
    """calibrate after a sequence: rig keeps the camera mount, check scores the result."""
    from calibration.synthetic import make_capture, write_capture
    from toolkit.io.sequence import read_rig

    frames, camera, T = scene
    T_bc = _write_sequence(scene, tmp_path / "seq")
    cap = make_capture(6, seed=3, camera=camera, T_camera_laser=T)
    write_capture(cap, tmp_path / "capture")
    res = _run_with_sequence(tmp_path / "seq", [
        {"stage": "calibrate", "capture": str(tmp_path / "capture"), "square_m": 0.05,
         "leave_one_out": False, "check_frames": 5}], tmp_path)
    assert res.ok, res.error
    m = res.metrics["calibrate"]
    assert m["check_kind"] == "depth" and m["check_score"] > 0.9
    assert m["check_score_true"] > m["check_score_true_rotated_2deg"] + 0.2
    rig = read_rig(tmp_path / "run" / "calibrate" / "rig.yaml")
    assert np.allclose(rig.T_base_camera, T_bc)  # the camera stays, the laser moves
    assert np.allclose(rig.T_camera_laser, T, atol=0.01)
    report = (tmp_path / "run" / "report.md").read_text()
    assert "(calibrate/check/overlay_vs_rotated_0.png)" in report
    assert (tmp_path / "run" / "calibrate" / "check" / "overlay_0.png").exists()


def test_stage_check_only_scores_the_rig_and_a_given_extrinsic(scene, tmp_path) -> None:  # noqa: ANN001
    """mode: check calibrates nothing: it scores the sequence's extrinsic (or a file's)."""
    import yaml

    from calibration.check import perturbed
    from calibration.files import extrinsic_to_mapping
    from toolkit.io.sequence import read_rig

    frames, camera, T = scene
    T_bc = _write_sequence(scene, tmp_path / "seq")
    res = _run_with_sequence(tmp_path / "seq", [
        {"stage": "calibrate", "mode": "check", "check_frames": 5}], tmp_path)
    assert res.ok, res.error
    m = res.metrics["calibrate"]
    assert m["check_kind"] == "depth" and m["check_score"] > 0.95
    # Not a simulator sequence: no ground truth is claimed.
    assert "check_score_true" not in m and "rotation_error_deg" not in m
    assert m["check_scores_rotated_2deg"]["ry+2deg"] < 0.8 * m["check_score"]
    run = tmp_path / "run" / "calibrate"
    assert np.allclose(read_rig(run / "rig.yaml").T_base_laser, T_bc @ T)  # passed on as is
    assert yaml.safe_load((run / "calibration.yaml").read_text())["mode"] == "check"
    report = (tmp_path / "run" / "report.md").read_text()
    assert "| rotated ry+2deg |" in report and "overlay_vs_rotated_1.png" in report
    assert (run / "check" / "overlay_vs_rotated_0.png").exists()

    # A given extrinsic 2 degrees off about the vertical scores worse than the rig's.
    wrong = tmp_path / "wrong.yaml"
    wrong.write_text(yaml.safe_dump(extrinsic_to_mapping(perturbed(T, 1, 2.0))))
    (tmp_path / "second").mkdir()
    res2 = _run_with_sequence(tmp_path / "seq", [
        {"stage": "calibrate", "mode": "check", "check_frames": 5,
         "extrinsic": str(wrong)}], tmp_path / "second")
    assert res2.ok, res2.error
    assert res2.metrics["calibrate"]["check_score"] < 0.8 * m["check_score"]


def test_stage_check_only_gates_an_extrinsic_marked_unreliable(scene, tmp_path,  # noqa: ANN001
                                                               caplog) -> None:  # noqa: ANN001
    """mode: check with extrinsic: a rig.unreliable.yaml. It was published as the rig with
    no warning and without its reliable: false mark, so no later reader warned either."""
    import logging

    import yaml

    from calibration.cli import main
    from calibration.files import extrinsic_to_mapping

    frames, camera, T = scene
    _write_sequence(scene, tmp_path / "seq")
    why = "the 5 board normals all lie within 1.3 degrees (RMS) of one plane."  # as written
    marked = tmp_path / "rig.unreliable.yaml"
    marked.write_text(yaml.safe_dump({**extrinsic_to_mapping(T), "calibration": {
        "reliable": False, "unreliable_because": [why]}}))
    stage = {"stage": "calibrate", "mode": "check", "check_frames": 2, "time_offset": False,
             "extrinsic": str(marked)}
    (tmp_path / "a").mkdir()
    with caplog.at_level(logging.WARNING):
        res = _run_with_sequence(tmp_path / "seq", [stage], tmp_path / "a")
    assert not res.ok and "reliable: false" in str(res.error)
    assert "allow_unreliable" in str(res.error) and why in str(res.error)
    assert ".." not in str(res.error), res.error  # the reason's period, then the message's
    assert not (tmp_path / "a" / "run" / "calibrate" / "rig.yaml").exists()
    assert any("marked unreliable" in r.getMessage() for r in caplog.records)
    (tmp_path / "b").mkdir()
    res = _run_with_sequence(tmp_path / "seq", [{**stage, "allow_unreliable": True}],
                             tmp_path / "b")
    assert res.ok, res.error
    assert res.metrics["calibrate"]["reliable"] is False
    published = yaml.safe_load((tmp_path / "b" / "run" / "calibrate" / "rig.yaml").read_text())
    assert published["calibration"]["reliable"] is False
    assert published["calibration"]["unreliable_because"] == [why]
    assert why in (tmp_path / "b" / "run" / "report.md").read_text()
    # The command's check warns on such a file too (it read it silently).
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert main(["check", "--sequence", str(tmp_path / "seq"), "--extrinsic", str(marked),
                     "--frames", "2", "--score", "edges", "--out", str(tmp_path / "chk")]) == 0
    assert any("marked unreliable" in r.getMessage() and why in r.getMessage()
               for r in caplog.records)


def test_stage_check_only_needs_a_sequence(tmp_path) -> None:  # noqa: ANN001
    from calibration.stage import CalibrateStage

    res = run_stages(tmp_path, [{"stage": "calibrate", "mode": "check"}],
                     {"calibrate": CalibrateStage})
    assert not res.ok and "needs a sequence" in str(res.error)


def test_check_on_a_sequence_refuses_a_rig_or_depth_of_another_size(scene, tmp_path) -> None:  # noqa: ANN001
    """check --sequence with a --rig for another resolution, or depth maps of another
    size, stops with exit 2 naming the file (it scored 0.02 and blamed the extrinsic)."""
    from calibration.cli import main
    from toolkit.io.sequence import read_rig, write_rig
    from toolkit.sensors import Rig

    _write_sequence(scene, tmp_path / "seq")
    rig = read_rig(tmp_path / "seq" / "rig.yaml")
    w, h = rig.camera.size
    write_rig(tmp_path / "big.yaml", Rig(rig.camera.scaled(2 * w, 2 * h), rig.T_base_camera,
                                         rig.T_base_laser))
    args = ["check", "--sequence", str(tmp_path / "seq"), "--frames", "3", "--score", "edges"]
    assert main([*args, "--out", str(tmp_path / "own")]) == 0
    assert main([*args, "--rig", str(tmp_path / "big.yaml"), "--out", str(tmp_path / "b")]) == 2
    assert not (tmp_path / "b" / "check.json").exists()
    depth = tmp_path / "depth"
    depth.mkdir()
    for i in range(len(scene[0])):
        np.save(depth / f"{i:06d}.npy", np.ones((h // 2, w // 2), np.float32))
    assert main(["check", "--sequence", str(tmp_path / "seq"), "--frames", "3", "--depth",
                 str(depth), "--out", str(tmp_path / "d")]) == 2


def test_check_on_a_sequence_names_a_missing_depth_folder(scene, tmp_path, capsys) -> None:  # noqa: ANN001
    """check --sequence --depth with a mistyped folder said "no depth map for frame 0
    (looked for 000000.npy|.png, 000000.npy|.png)"; as with --images: the folder is named,
    and a frame's missing map names each file looked for once."""
    from calibration.cli import main

    _write_sequence(scene, tmp_path / "seq")
    args = ["check", "--sequence", str(tmp_path / "seq"), "--frames", "3", "--out",
            str(tmp_path / "d"), "--depth"]
    assert main([*args, str(tmp_path / "nope")]) == 2
    assert capsys.readouterr().err == (
        f"error: {tmp_path / 'nope'}: depth folder (--depth) not found\n")
    (tmp_path / "empty").mkdir()
    assert main([*args, str(tmp_path / "empty")]) == 2
    assert capsys.readouterr().err == (f"error: {tmp_path / 'empty'}: no depth map for frame 0 "
                                       "(looked for 000000.npy|.png)\n")


def _write_swept_sequence(root, odometry: bool = True):  # noqa: ANN001, ANN202
    """The boxes room seen by a robot turning on the spot at 1 rad/s under a 10 Hz spinning
    lidar: beam i measured at the scan's stamp + i * time_increment (as a ROS LaserScan
    carries it), images at the scans' stamps, the exact rig; with odometry when asked."""
    from toolkit.geometry import Trajectory
    from toolkit.io.sequence import SequenceWriter
    from toolkit.sensors import LaserScan, Rig

    camera = PinholeCamera.from_fov(320, 240, 70.0)
    T_bc = se3(R_BASE_OPTICAL, [0.05, 0.0, 0.5])
    T_bl = se3(np.eye(3), [0.0, 0.0, 0.3])  # on the turning axis: the laser does not move

    def pose(t: float) -> np.ndarray:
        return se2_to_se3(0.0, 0.0, -0.5 + 1.0 * (t - 10.0))

    w = SequenceWriter(root, Rig(camera, T_bc, T_bl), name="swept")
    rays = camera.pixel_rays().reshape(-1, 3)  # [P, 3], z = 1
    nb, inc = 720, np.radians(0.5)
    ang = -np.pi + inc * np.arange(nb)  # [B]
    for k in range(5):
        t = 10.0 + 0.1 * k
        T_wc = pose(t) @ T_bc
        depth, grey = _raycast(T_wc[:3, 3], rays @ T_wc[:3, :3].T)
        img = np.repeat(grey.reshape(camera.height, camera.width, 1), 3, 2).astype(np.uint8)
        w.add_frame(t, img, gt_depth=depth.reshape(camera.height, camera.width).astype(
            np.float32))
        # Beam i left the laser i * 0.1 s / B after the stamp, the robot turned meanwhile.
        yaw = -0.5 + (t - 10.0) + ang + 0.1 * np.arange(nb) / nb  # [B] world bearing
        r, _ = _raycast(np.array([0.0, 0.0, 0.3]), np.c_[np.cos(yaw), np.sin(yaw),
                                                         np.zeros(nb)])
        w.add_scan(LaserScan(t, r.astype(np.float32), -np.pi, inc, time_increment=0.1 / nb))
    if odometry:
        st = np.arange(9.5, 11.0, 0.01)
        w.odometry = Trajectory(st, np.stack([pose(s) for s in st]), "odom", "base_link")
    w.close()
    return inv_se3(T_bc) @ T_bl


def test_check_on_a_sequence_deskews_swept_scans(tmp_path) -> None:  # noqa: ANN001
    """Scans whose beams carry their own times are de-skewed with the odometry before
    scoring, as the fusion does: projected as one instant, the exact extrinsic scored
    0.42 and the same turned 2 degrees 0.83, and the check said to rotate it."""
    from calibration.pipeline import check_frames_from_sequence

    T = _write_swept_sequence(tmp_path / "seq")
    frames, seq = check_frames_from_sequence(tmp_path / "seq", T, 5)
    sc = sensitivity(frames, T, seq.rig.camera, 2.0, "depth")
    assert sc.score > 0.95, sc.to_dict()
    assert sc.drop("ry+2deg") > 0.2 and sc.drop("ry-2deg") > 0.2, sc.to_dict()


def test_check_on_a_sequence_refuses_swept_scans_without_poses(tmp_path, capsys) -> None:  # noqa: ANN001
    """Without odometry or ground-truth poses swept scans cannot be de-skewed: exit 2 with
    a message saying what to do, instead of a score that blames the extrinsic."""
    from calibration.cli import main

    _write_swept_sequence(tmp_path / "seq", odometry=False)
    assert main(["check", "--sequence", str(tmp_path / "seq"), "--frames", "3", "--out",
                 str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "time_increment" in err and "odometry" in err and "beam_timing" in err, err
    assert not (tmp_path / "out" / "check.json").exists()


def test_stage_check_deskews_swept_scans_or_says_why_not(tmp_path) -> None:  # noqa: ANN001
    """The recipe stage's check de-skews as the command does; without poses, mode check
    stops naming the fix, and mode calibrate keeps its extrinsic and says the check was
    not run (it scored swept scans as one instant)."""
    from calibration.synthetic import make_capture, write_capture

    T = _write_swept_sequence(tmp_path / "seq")
    (tmp_path / "a").mkdir()
    check = {"stage": "calibrate", "mode": "check", "check_frames": 5, "time_offset": False}
    res = _run_with_sequence(tmp_path / "seq", [check], tmp_path / "a")
    assert res.ok, res.error
    m = res.metrics["calibrate"]
    assert m["check_score"] > 0.95 and m["check_scores_rotated_2deg"]["ry-2deg"] < 0.8, m

    _write_swept_sequence(tmp_path / "bare", odometry=False)
    (tmp_path / "b").mkdir()
    res = _run_with_sequence(tmp_path / "bare", [check], tmp_path / "b")
    assert not res.ok and "time_increment" in str(res.error), res.error
    cap = make_capture(6, seed=3, camera=PinholeCamera.from_fov(320, 240, 70.0),
                       T_camera_laser=T)
    write_capture(cap, tmp_path / "capture")
    (tmp_path / "c").mkdir()
    res = _run_with_sequence(tmp_path / "bare", [
        {"stage": "calibrate", "capture": str(tmp_path / "capture"), "square_m": 0.05,
         "leave_one_out": False, "check_frames": 3, "time_offset": False}], tmp_path / "c")
    assert res.ok, res.error
    assert "check_score" not in res.metrics["calibrate"]
    report = (tmp_path / "c" / "run" / "report.md").read_text()
    assert "Check not run" in report and "time_increment" in report

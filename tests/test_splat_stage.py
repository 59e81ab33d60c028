"""The ``splat`` recipe stage on a small synthetic room (sequence + fused inputs)."""

from __future__ import annotations

import json
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import yaml
from recipe_helpers import SplatInputs  # the tests folder is on sys.path

from toolkit.geometry import Trajectory
from toolkit.io.tum import write_tum
from toolkit.recipe import Stage, StageConfig, StageContext, load_recipe, registry, run_recipe
from toolkit.splat.export import read_ply
from toolkit.splat.stage import SplatStage


class TrajectoryStage(Stage):
    """Provide the ground-truth camera trajectory as if SLAM had estimated it (test stage)."""

    name = "t_splat_traj"
    Config = StageConfig
    requires = ("sequence",)
    provides = ("trajectory",)

    def run(self, ctx: StageContext) -> None:
        from toolkit.io.sequence import read_sequence

        seq = read_sequence(ctx.artifact("sequence"))
        gt = seq.groundtruth
        assert gt is not None and gt.poses_base is not None
        traj = Trajectory(gt.poses_base.stamps, gt.poses_base.poses @ seq.rig.T_base_camera,
                          "world", "camera")
        write_tum(ctx.stage_dir / "trajectory_camera.tum", traj)
        ctx.provide("trajectory", ctx.stage_dir)


@pytest.fixture(autouse=True)
def stages() -> Iterator[None]:
    for name, cls in (("t_splat_inputs", SplatInputs), ("t_splat_traj", TrajectoryStage),
                      ("splat", SplatStage)):
        registry.register(name, cls)
    yield
    for name in ("t_splat_inputs", "t_splat_traj", "splat"):
        registry.unregister(name)


def _recipe(tmp_path: Path, with_traj: bool, inputs: dict[str, Any] | None = None,
            **splat: Any) -> Path:
    stages: list[dict[str, Any]] = [{"stage": "t_splat_inputs", **(inputs or {})}]
    if with_traj:
        stages.append({"stage": "t_splat_traj"})
    stages.append({"stage": "splat", "iterations": 25, "downscale": 1, "holdout_every": 4,
                   "init_budget": 2000, "checkpoint_every": 10, "max_seconds": None,
                   "log_every": 10, **splat})
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump({"name": "splat_test", "output": str(tmp_path / "run"),
                                    "stages": stages}, sort_keys=False))
    return path


def test_stage_trains_exports_and_reports(tmp_path: Path) -> None:
    res = run_recipe(load_recipe(_recipe(tmp_path, with_traj=True)))
    assert res.ok, res.error
    out = tmp_path / "run" / "splat"
    m = res.metrics["splat"]
    assert m["poses"] == "trajectory"
    assert m["iterations"] == 25 and m["train_views"] == 9  # frames 0, 4, 8 held out
    assert m["heldout_frames"] == 3 and np.isfinite(m["heldout_psnr_db"])
    assert 0 < m["heldout_ssim"] <= 1
    assert m["sim_heldout_views"] == 2 and np.isfinite(m["sim_heldout_psnr_db"])
    assert "heldout_depth_mae_m" in m and "sim_heldout_depth_mae_m" in m
    model = read_ply(out / "splats.ply")
    assert len(model) == m["n_gaussians"]
    assert (out / "renders.png").exists() and (out / "checkpoints" / "checkpoint.pt").exists()
    hist = json.loads((out / "train_history.json").read_text())
    assert [h["step"] for h in hist] == [9, 19, 24]
    report = (tmp_path / "run" / "report.md").read_text()
    assert "splat/renders.png" in report and "GROUND-TRUTH" not in report
    # unchanged inputs and settings: cached
    again = run_recipe(load_recipe(_recipe(tmp_path, with_traj=True)))
    assert again.statuses["splat"] == "cached"


def test_stage_without_trajectory_uses_ground_truth_and_says_so(tmp_path: Path) -> None:
    res = run_recipe(load_recipe(_recipe(tmp_path, with_traj=False, iterations=5,
                                         holdout_every=0, strip_views=1)))
    assert res.ok, res.error
    assert res.metrics["splat"]["poses"] == "groundtruth"
    assert "heldout_psnr_db" not in res.metrics["splat"]
    report = (tmp_path / "run" / "report.md").read_text()
    assert "GROUND-TRUTH" in report


def test_exposure_fused_divides_the_images_by_the_fuse_stages_gains(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import toolkit.splat.stage as splat_stage

    seen: list[float] = []
    real = splat_stage.prepare_image

    def recording(img: np.ndarray, *a: Any, **kw: Any) -> np.ndarray:
        seen.append(float(img.mean()))
        return real(img, *a, **kw)

    monkeypatch.setattr(splat_stage, "prepare_image", recording)
    means = {}
    for mode, gain in (("none", 2.0), ("fused", 2.0), ("auto", 2.0), ("auto", None)):
        d = tmp_path / f"{mode}_{gain}"
        d.mkdir()
        seen.clear()
        res = run_recipe(load_recipe(_recipe(d, with_traj=True, iterations=2,
                                             inputs={"exposure_gain": gain}, exposure=mode)))
        assert res.ok, res.error
        means[d.name] = np.mean(seen[:12])  # the path's frames (simulator views follow)
        used = res.metrics["splat"]["exposure_gains_from_fuse"]
        assert used == (mode != "none" and gain is not None)
        assert used == ("divided by the exposure gains" in (d / "run/report.md").read_text())
    for name in ("fused_2.0", "auto_2.0"):
        assert means[name] == pytest.approx(means["none_2.0"] / 2, abs=0.6)
    assert means["auto_None"] == pytest.approx(means["none_2.0"], abs=1e-9)
    (tmp_path / "nogains").mkdir()
    res = run_recipe(load_recipe(_recipe(tmp_path / "nogains", with_traj=True, iterations=2,
                                         exposure="fused")))
    assert not res.ok and "set `exposure: gain` on the fuse stage" in str(res.error)
    # Gains for some frames only: refused, not half the views divided.
    (tmp_path / "subset").mkdir()
    recipe = _recipe(tmp_path / "subset", with_traj=True, iterations=2,
                     inputs={"exposure_gain": 2.0, "exposure_gain_frames": 6})
    res = run_recipe(load_recipe(recipe))
    assert not res.ok and "has no gain for 6 of the 12 frames" in str(res.error)


def test_heldout_frames_are_not_divided_by_their_own_solved_gains(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The fuse stage solves every frame's gain from that frame's own pixels; a held-out
    frame divided by its own gain had its exposure fitted on the pixels it is scored on.
    Frames 0, 4 and 8 are held out (holdout_every 4) with own gains of 2.0, which must not
    be used: frame 4 sits between frames 3 (gain 1.0) and 5 (1.44), so log-linear 1.2;
    frame 8 between 7 (0.9) and 9 (0.9), so 0.9; frame 0 before the first training frame,
    so frame 1's 1.1. Training frames keep their own gains."""
    import hashlib

    import toolkit.splat.stage as splat_stage
    from toolkit.io.sequence import read_sequence

    own = [2.0, 1.1, 1.0, 1.0, 2.0, 1.44, 1.0, 0.9, 2.0, 0.9, 1.0, 1.0]
    used: dict[str, list[float]] = {}
    real = splat_stage.corrected_image

    def recording(img: np.ndarray, gain: np.ndarray) -> np.ndarray:
        used.setdefault(hashlib.sha1(img.tobytes()).hexdigest(), []).append(
            float(np.mean(gain)))
        return real(img, gain)

    monkeypatch.setattr(splat_stage, "corrected_image", recording)
    res = run_recipe(load_recipe(_recipe(tmp_path, with_traj=True, iterations=2,
                                         inputs={"exposure_gains": own}, exposure="fused")))
    assert res.ok, res.error
    seq = read_sequence(tmp_path / "run" / "t_splat_inputs" / "sequence")
    expected = {0: 1.1, 4: 1.2, 8: 0.9} | {i: own[i] for i in range(12) if i % 4}
    for i, g in expected.items():
        key = hashlib.sha1(np.ascontiguousarray(seq.frames[i].image).tobytes()).hexdigest()
        assert used[key] == pytest.approx([g], rel=1e-9), f"frame {i}"


def test_holdout_counts_the_frames_used_and_the_budget_caps_the_start(tmp_path: Path) -> None:
    """With frame_stride 2 the 12 posed frames give 6 used ones; holdout_every 4 holds out
    the 1st and 5th of those (every 4th of all frames would hold out half of them, and a
    stride of 4 all). memory_budget_mb caps the initial model, not only its growth."""
    from toolkit.splat.trainer import bytes_per_gaussian

    budget_mb = 400 * bytes_per_gaussian(0) / 2**20
    res = run_recipe(load_recipe(_recipe(tmp_path, with_traj=True, iterations=3,
                                         frame_stride=2, sh_degree=0,
                                         memory_budget_mb=budget_mb)))
    assert res.ok, res.error
    m = res.metrics["splat"]
    assert m["heldout_frames"] == 2 and m["train_views"] == 4
    assert m["n_gaussians"] <= 400


def test_depth_targets_sample_each_training_pixel_at_its_centre() -> None:
    """Training pixel x of a 4x smaller camera covers full-resolution x in [4x, 4x + 4), its
    centre at 4x + 1.5: the depth target takes the value there, as the area-resized colour
    does (nearest resizing took 4x, 1.5 pixels off at every edge)."""
    from toolkit.camera import PinholeCamera
    from toolkit.splat.stage import prepare_depth

    cam = PinholeCamera(640, 480, 500.0, 500.0, 319.5, 239.5)
    u = np.arange(640, dtype=np.float32)
    depth = np.tile(1.0 + u / 100.0, (480, 1))  # a ramp across the image: depth = f(u)
    small = prepare_depth(depth, cam, (160, 120))
    x = np.arange(160)
    np.testing.assert_allclose(small[60], 1.0 + np.rint(4 * x + 1.5 + 1e-6) / 100.0,
                               atol=1e-6)


@pytest.mark.parametrize("dist", [None, [0.12, -0.05, 0.0, 0.0, 0.0]])
def test_depth_targets_take_non_finite_source_pixels_as_zero(dist: list[float] | None) -> None:
    """NaN and inf depths of the source become 0 wherever a target pixel samples them, the
    other pixels keep their values exactly: the same target as a map cleaned first, for a
    pinhole and a distorted camera, and again from the maps made once (the second call)."""
    import cv2

    from toolkit.camera import PinholeCamera
    from toolkit.splat.stage import prepare_depth

    cam = PinholeCamera(640, 480, 500.0, 500.0, 319.5, 239.5,
                        None if dist is None else np.array(dist))
    rng = np.random.default_rng(5)
    depth = rng.uniform(0.5, 6.0, (480, 640)).astype(np.float32)
    depth[rng.random((480, 640)) < 0.2] = np.nan
    depth[rng.random((480, 640)) < 0.05] = np.inf
    depth[:40, :60] = -np.inf
    clean = np.nan_to_num(depth, nan=0.0, posinf=0.0, neginf=0.0)
    target = cam.undistorted().scaled(160, 120)
    m1, m2 = cv2.initUndistortRectifyMap(cam.K, cam.dist, None, target.K, (160, 120),
                                         cv2.CV_32FC1)
    expected = cv2.remap(clean, m1, m2, cv2.INTER_NEAREST)
    for _ in range(2):
        small = prepare_depth(depth, cam, (160, 120))
        assert small.dtype == np.float32 and np.isfinite(small).all()
        np.testing.assert_array_equal(small, expected)
        assert (small == 0).mean() > 0.15
    # The training size itself, no distortion: only cleaned.
    if dist is None:
        np.testing.assert_array_equal(prepare_depth(depth, cam, (640, 480)), clean)


def test_lens_corners_without_a_source_are_neither_fitted_nor_scored() -> None:
    """Undistorting a pincushion lens (k1 > 0) leaves black corners: a render that is right
    everywhere else must score as right, and those pixels must carry no loss."""
    from toolkit.camera import PinholeCamera
    from toolkit.eval.image import psnr
    from toolkit.splat.stage import image_validity, prepare_image
    from toolkit.splat.trainer import TrainView

    cam = PinholeCamera(640, 480, 500.0, 500.0, 319.5, 239.5,
                        np.array([0.12, 0.0, 0.0, 0.0, 0.0]))
    valid = image_validity(cam, (160, 120))
    assert valid is not None and 0.03 < 1 - float(valid.float().mean()) < 0.15
    assert image_validity(cam.undistorted(), (160, 120)) is None  # nothing to mask
    grey = np.full((480, 640, 3), 128, np.uint8)
    img = torch.from_numpy(prepare_image(grey, cam, (160, 120)))
    view = TrainView(img, cam.undistorted().scaled(160, 120), np.eye(4), mask=valid)
    gt = view.target()
    render = torch.full_like(gt, 128 / 255)  # right wherever the image has a source
    assert psnr(render, gt) < 20  # the corners counted: a perfect render looks bad
    masked = view.masked(render.requires_grad_(), gt)
    assert psnr(masked, gt, mask=valid) > 40
    (masked - gt).abs().mean().backward()
    assert float(render.grad[~valid].abs().sum()) == 0.0


def test_settings_that_cannot_run_are_refused_with_the_recipe() -> None:
    from pydantic import ValidationError

    from toolkit.splat.stage import SplatConfig

    with pytest.raises(ValidationError, match=r"random_depth_m \[5.0, 0.3\]"):
        SplatConfig(stage="splat", random_depth_m=(5.0, 0.3))
    with pytest.raises(ValidationError, match="set device: cuda"):
        SplatConfig(stage="splat", backend="gsplat", device="cpu")
    with pytest.raises(ValidationError, match="backend cpp is a CPU rasteriser"):
        SplatConfig(stage="splat", backend="cpp", device="cuda")
    with pytest.raises(ValidationError):
        SplatConfig(stage="splat", backend="gpu")
    SplatConfig(stage="splat", backend="gsplat", device="auto")


def test_device_cuda_without_a_usable_gpu_says_what_to_do(monkeypatch: pytest.MonkeyPatch) -> (
        None):
    from toolkit.recipe.stage import StageError
    from toolkit.splat.rasterize import gsplat_backend
    from toolkit.splat.stage import choose_device

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert choose_device("cpu").type == "cpu"
    assert choose_device("auto").type == "cpu"  # no GPU: the CPU, silently
    assert gsplat_backend.unavailable_reason() == "no CUDA device"
    with pytest.raises(StageError, match=r"no CUDA device.*splat.device: cpu"):
        choose_device("cuda")
    with pytest.raises(StageError, match=r"backend gsplat: no CUDA device"):
        choose_device("auto", "gsplat")
    assert choose_device("auto", "cpp").type == "cpu"


def test_device_cuda_on_a_gpu_without_the_cuda_toolkit_names_the_toolkit(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """What an H100 machine with its CUDA toolkit moved away showed (session 29): gsplat
    imports, prints "No CUDA toolkit found" and leaves its kernels None. The fix is the
    toolkit torch was built with, not the cuda extra or a GPU (both were there)."""
    import types

    from toolkit.recipe.stage import StageError
    from toolkit.splat.rasterize import gsplat_backend
    from toolkit.splat.stage import choose_device

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.version, "cuda", "13.0")
    for name in ("gsplat", "gsplat.cuda"):
        monkeypatch.setitem(sys.modules, name, types.ModuleType(name))
    monkeypatch.setitem(sys.modules, "gsplat.cuda._backend", types.SimpleNamespace(_C=None))
    assert choose_device("auto").type == "cpu"
    assert "no CUDA toolkit" in (gsplat_backend.unavailable_reason() or "")
    with pytest.raises(StageError) as err:
        choose_device("cuda")
    message = str(err.value)
    assert "CUDA toolkit 13.0" in message and "CUDA_HOME" in message
    assert "cuda extra" not in message and "splat.device: cpu" in message


def test_groundtruth_alignment_on_a_straight_drive() -> None:
    """Camera positions along a line leave the turn about it free: 1 mm of noise turned a
    position-only fit 180 deg (2 mm residual); the orientations pin it."""
    from types import SimpleNamespace

    from scipy.spatial.transform import Rotation

    from toolkit.geometry import se3
    from toolkit.splat.stage import groundtruth_to_trajectory_frame

    n = 50
    stamps = np.arange(n) * 0.1
    base = np.stack([se3(np.eye(3), [x, 0.0, 0.0]) for x in np.linspace(0, 10, n)])
    T_base_camera = se3(Rotation.from_euler("xyz", [-90, 0, -90], degrees=True).as_matrix(),
                        [0.2, 0.0, 0.3])
    seq = SimpleNamespace(groundtruth=SimpleNamespace(
        poses_base=Trajectory(stamps, base, "world", "base_link")),
        rig=SimpleNamespace(T_base_camera=T_base_camera))
    T_true = se3(Rotation.from_euler("z", 30, degrees=True).as_matrix(), [1.41, -0.5, 0.0])
    cam = np.einsum("ij,njk->nik", T_true, base @ T_base_camera)
    cam[:, :3, 3] += np.random.default_rng(0).normal(0, 0.001, (n, 3))
    found = groundtruth_to_trajectory_frame(seq, Trajectory(stamps, cam, "world", "camera"))
    assert found is not None
    T, rmse = found
    # The line's direction from the positions (1 mm noise over 10 m), the turn about it
    # from the orientations.
    np.testing.assert_allclose(T[:3, :3], T_true[:3, :3], atol=1e-3)
    assert np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < 0.002 and rmse < 0.003


def test_simulator_held_out_views_are_scored_on_the_lens_pixels(tmp_path: Path) -> None:
    """The simulator's held-out views are undistorted like the path's, so their lens corners
    have no source pixel either: they carry the same mask (a perfect render scored 13 dB)."""
    from types import SimpleNamespace

    import cv2

    from toolkit.camera import PinholeCamera
    from toolkit.sensors import GroundTruth, HeldOutViews
    from toolkit.splat.model import GaussianModel
    from toolkit.splat.stage import SplatStage, image_validity
    from toolkit.splat.trainer import evaluate_views

    cam_full = PinholeCamera(128, 96, 90.0, 90.0, 63.5, 47.5,
                             np.array([0.3, 0.0, 0.0, 0.0, 0.0]))  # pincushion
    w, h = 64, 48
    cam = cam_full.undistorted().scaled(w, h)
    cv2.imwrite(str(tmp_path / "h0.png"), np.full((96, 128, 3), 128, np.uint8))
    held = HeldOutViews(Trajectory(np.array([0.0]), np.eye(4)[None], "world", "camera"),
                        [tmp_path / "h0.png"], [])
    seq = SimpleNamespace(groundtruth=GroundTruth(heldout=held))
    valid = image_validity(cam_full, (w, h))
    assert valid is not None and float(valid.float().mean()) < 0.9
    found = SplatStage._sim_heldout(seq, cam_full, cam, (w, h), np.eye(4), valid)
    assert found is not None
    views, _ = found
    assert views[0].mask is valid
    model = GaussianModel.empty(1, sh_degree=0)
    with torch.no_grad():
        model.params["means"][:] = torch.tensor([0.0, 0.0, -5.0])  # behind: renders nothing
    res = evaluate_views(model, views, "torch", (128 / 255,) * 3)  # the wall's own grey
    assert res["psnr_db"] == float("inf") and res["ssim"] == pytest.approx(1.0)


def test_views_read_on_demand_train_the_same_splats_and_keep_the_cache(
        tmp_path: Path) -> None:
    """A recording larger than view_cache_mb is read from disk as training asks (a long
    recording does not fill the memory); the splats are the same, and the setting only
    changes speed: a finished stage stays cached when it changes."""
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    held = run_recipe(load_recipe(_recipe(tmp_path / "a", with_traj=True, iterations=12)))
    lazy = run_recipe(load_recipe(_recipe(tmp_path / "b", with_traj=True, iterations=12,
                                          view_cache_mb=0.05)))
    assert held.ok and lazy.ok, (held.error, lazy.error)
    a = read_ply(tmp_path / "a" / "run" / "splat" / "splats.ply")
    b = read_ply(tmp_path / "b" / "run" / "splat" / "splats.ply")
    for k, p in a.params.items():
        assert np.array_equal(p.detach().numpy(), b.params[k].detach().numpy()), k
    for key in ("heldout_psnr_db", "sim_heldout_psnr_db", "heldout_depth_mae_m"):
        assert held.metrics["splat"][key] == lazy.metrics["splat"][key], key
    log = (tmp_path / "b" / "run" / "run.log").read_text()
    assert "read from disk as training asks for them" in log
    again = run_recipe(load_recipe(_recipe(tmp_path / "a", with_traj=True, iterations=12,
                                           view_cache_mb=0.05)))
    assert again.statuses["splat"] == "cached"


def test_fused_depth_is_read_for_the_training_frames_only(tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> (
        None):
    """Scoring a held-out frame never uses its fused depth (the depth error is against
    ground truth): reading it cost a tenth of the quickstart's view reading."""
    import toolkit.io.depth

    read = toolkit.io.depth.read_depth
    seen: list[Path] = []

    def spy(path: Any, *args: Any, **kwargs: Any) -> Any:
        seen.append(Path(path))
        return read(path, *args, **kwargs)

    monkeypatch.setattr(toolkit.io.depth, "read_depth", spy)
    res = run_recipe(load_recipe(_recipe(tmp_path, with_traj=True, iterations=3)))
    assert res.ok, res.error
    fused = sorted(int(p.stem) for p in seen if p.parent.name == "scaled_depth")
    assert fused == [1, 2, 3, 5, 6, 7, 9, 10, 11]  # frames 0, 4, 8 held out
    assert "heldout_depth_mae_m" in res.metrics["splat"]  # ground truth still read


def test_ground_truth_poses_are_refused_for_a_map_built_at_other_poses(
        tmp_path: Path) -> None:
    """splat.poses: groundtruth beside a map fused at the SLAM poses trained splats from a
    map 1.4 m off them without a word (the report blamed a missing trajectory)."""
    from toolkit.eval.alignment import ground_truth_camera
    from toolkit.geometry import se3
    from toolkit.io.sequence import read_sequence
    from toolkit.recipe import StageError
    from toolkit.splat.synthetic import write_synthetic_inputs

    seq_dir, fused = write_synthetic_inputs(tmp_path / "in", n_frames=6, width=48, height=36,
                                            n_gaussians=200)
    seq = read_sequence(seq_dir)
    at_gt = ground_truth_camera(seq, seq.frame_stamps)
    write_tum(fused / "camera_poses.tum", at_gt)
    SplatStage._same_frame_as_the_map(seq, fused)  # built at ground truth: fine
    shifted = at_gt.transform(T_left=se3(np.eye(3), [1.4, 0.0, 0.0]))
    write_tum(fused / "camera_poses.tum", shifted)
    with pytest.raises(StageError, match="set the fuse stage's poses to groundtruth"):
        SplatStage._same_frame_as_the_map(seq, fused)


def test_stage_bench_writes_each_devices_figures(tmp_path: Path) -> None:
    from toolkit.splat.stage_bench import main

    out = tmp_path / "b.json"
    assert main(["--frames", "8", "--width", "32", "--height", "24", "-n", "400",
                 "--iterations", "12", "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    cpu = res["devices"]["cpu"]
    assert cpu["ok"] and cpu["device"] == "cpu" and cpu["iterations"] == 12
    assert cpu["train_views"] == 7 and cpu["train_iters_per_s"] > 0  # frame 0 held out
    assert res["scene"] == {"frames": 8, "width": 32, "height": 24, "gaussians": 400,
                            "iterations": 12}
    assert "settings" not in res


def test_stage_bench_sets_a_splat_setting_on_each_run(tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """``--set KEY=VALUE`` reaches the stage (views read from disk, exposure gains); a key
    the stage does not have, and the bench's own keys, are refused with the reason."""
    from toolkit.splat.stage_bench import main

    small = ["--frames", "8", "--width", "32", "--height", "24", "-n", "400",
             "--iterations", "6"]
    out = tmp_path / "b.json"
    assert main([*small, "--set", "view_cache_mb=0.001", "--set", "exposure=gain",
                 "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["settings"] == {"view_cache_mb": 0.001, "exposure": "gain"}
    assert res["devices"]["cpu"]["ok"] and res["devices"]["cpu"]["iterations"] == 6
    with pytest.raises(SystemExit):
        main([*small, "--set", "view_cache=1", "--out", str(out)])
    assert "did you mean 'view_cache_mb'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([*small, "--set", "iterations=3", "--out", str(out)])
    assert "the bench sets these itself" in capsys.readouterr().err


def test_heldout_depth_error_says_what_share_of_pixels_it_covers() -> None:
    """The held-out depth MAE is taken where the render's alpha exceeds 0.5: off the path
    that left out 2.3 % of the ground truth's pixels (counted at depth 0 the benchmark's
    0.120 m would read 0.176 m), and nothing said so. ``depth_coverage`` is that share:
    one Gaussian filling the left half of the view covers half of it, and none covers 0."""
    from toolkit.camera import PinholeCamera
    from toolkit.splat.model import GaussianModel
    from toolkit.splat.trainer import TrainView, evaluate_views

    cam = PinholeCamera(32, 24, 20.0, 20.0, 15.5, 11.5)
    view = TrainView(np.full((24, 32, 3), 128, np.uint8), cam, np.eye(4),
                     depth=np.full((24, 32), 2.0, np.float32))
    model = GaussianModel.empty(1, sh_degree=0)
    with torch.no_grad():
        model.params["means"][:] = torch.tensor([0.0, 0.0, -5.0])  # behind the camera
    res = evaluate_views(model, [view], "torch", (0.5,) * 3, [view.depth.numpy()])
    assert res["depth_coverage"] == 0.0 and "depth_mae_m" not in res
    model = GaussianModel.empty(1, sh_degree=0)
    with torch.no_grad():  # opaque and flat, alpha > 0.5 up to x = 0 (the left half)
        model.params["means"][:] = torch.tensor([-3.0, 0.0, 2.0])
        model.params["log_scales"][:] = torch.log(torch.tensor([2.55, 20.0, 0.01]))
        model.params["opacity_logits"][:] = 10.0
    res = evaluate_views(model, [view], "torch", (0.5,) * 3, [view.depth.numpy()])
    assert res["depth_coverage"] == pytest.approx(0.5, abs=0.05)
    assert res["depth_mae_m"] < 0.05


@pytest.mark.parametrize(("cores", "load", "default", "expected"), [
    (2, 0.1, 2, 1),   # two cores, idle: one torch thread (the kernels keep both)
    (1, 0.0, 1, 1),
    (8, 0.5, 8, 8),   # more cores, idle: torch's default
    (8, 9.0, 8, 1),   # every core already busy
])
def test_auto_threads_take_one_torch_thread_on_two_cores_or_a_busy_machine(
        monkeypatch: pytest.MonkeyPatch, cores: int, load: float, default: int,
        expected: int) -> None:
    from toolkit.splat import stage as splat_stage

    monkeypatch.setattr(splat_stage, "usable_cpus", lambda: cores)
    monkeypatch.setattr(splat_stage.os, "getloadavg", lambda: (load, load, load))
    monkeypatch.setattr(splat_stage.torch, "get_num_threads", lambda: default)
    assert splat_stage.choose_threads("auto") == expected
    assert splat_stage.choose_threads(3) == 3

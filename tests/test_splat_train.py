"""Training: a small fit converges, checkpoints resume exactly, densification keeps Adam
state aligned and respects the Gaussian budget."""

from __future__ import annotations

import io
import logging
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

from toolkit.camera import PinholeCamera
from toolkit.geometry import inv_se3
from toolkit.splat.model import GaussianModel, init_from_points
from toolkit.splat.rasterize import RenderMeta, render
from toolkit.splat.strategy import DefaultStrategy, StrategyConfig
from toolkit.splat.synthetic import ground_truth_model, look_pose, orbit_poses, room_points
from toolkit.splat.trainer import (
    TrainConfig,
    Trainer,
    TrainView,
    evaluate_views,
    masked_l1,
    scene_scale_of,
)

BACKEND = "auto"  # the C++ path when it builds, else the reference: both must train


# one torch thread for every test here (conftest.one_thread)
pytestmark = pytest.mark.usefixtures("one_thread")


def _views(n: int = 4, width: int = 40, height: int = 30, n_gauss: int = 1500) -> (
    list[TrainView]
):
    gt = ground_truth_model(n_gauss, seed=1)
    cam = PinholeCamera.from_fov(width, height, 70.0)
    views = []
    with torch.no_grad():
        for i, T_wc in enumerate(orbit_poses(n, seed=1)):
            T_cw = inv_se3(T_wc)
            out = render(gt, cam, T_cw, backend=BACKEND)
            img = (out.color.clamp(0, 1) * 255 + 0.5).to(torch.uint8)
            depth = torch.where(out.alpha > 0.5, out.depth, torch.zeros(()))
            views.append(TrainView(img, cam, T_cw, depth, f"v{i}"))
    return views


def _start_model(n: int, seed: int = 2) -> GaussianModel:
    pts, _ = room_points(n, seed=1)
    rng = np.random.default_rng(seed)
    grey = np.full_like(pts, 0.5) + rng.normal(0, 0.05, pts.shape)
    return init_from_points(pts + rng.normal(0, 0.01, pts.shape), grey, sh_degree=1)


def test_small_fit_raises_psnr() -> None:
    views = _views()
    model = _start_model(1500)
    before = evaluate_views(model, views, BACKEND)["psnr_db"]
    cfg = TrainConfig(iterations=50, sh_degree=1, lr_sh0=0.05, lr_opacities=0.1,
                      depth_weight=0.0, densify=StrategyConfig(enabled=False),
                      checkpoint_every=0, backend=BACKEND)
    summary = Trainer(model, views, cfg).train()
    after = evaluate_views(model, views, BACKEND)["psnr_db"]
    assert summary.steps == 50 and np.isfinite(summary.final_loss)
    assert after > before + 6.0, (before, after)


def _cfg(**kw: object) -> TrainConfig:
    base = dict(iterations=30, sh_degree=1, sh_degree_interval=10, checkpoint_every=15,
                backend=BACKEND, seed=3, pose_refine=True,
                densify=StrategyConfig(refine_start_iter=4, refine_every=5, reset_every=20,
                                       grow_grad2d=2e-5))
    base.update(kw)
    return TrainConfig(**base)  # type: ignore[arg-type]


def test_checkpoint_resume_reproduces_uninterrupted_run(tmp_path: Path) -> None:
    views = _views(n=3, width=32, height=24, n_gauss=600)
    straight = Trainer(_start_model(600), views, _cfg(), tmp_path / "a")
    straight.train()
    # Killed after step 17 (the last checkpoint is at 15), then a fresh trainer resumes.

    class Killed(Exception):
        pass

    def kill_after_17(steps: Iterable[int], total: int, desc: str) -> Iterator[int]:
        for s in steps:
            if s == 17:
                raise Killed
            yield s

    first = Trainer(_start_model(600), views, _cfg(), tmp_path / "b")
    with pytest.raises(Killed):
        first.train(iter_wrapper=kill_after_17)
    resumed = Trainer(_start_model(600), views, _cfg(), tmp_path / "b")
    assert resumed.resume() and resumed.step == 15
    resumed.train()
    assert resumed.step == straight.step == 30
    # The running averages came back too: the same history and final figures.
    assert resumed.history == straight.history
    assert straight.history[-1]["psnr_avg_db"] == resumed.history[-1]["psnr_avg_db"]
    for name, p in straight.model.params.items():
        assert torch.equal(resumed.model.params[name], p), name
    for name in straight.optimizers:
        sa = straight.optimizers[name].state_dict()["state"][0]
        sb = resumed.optimizers[name].state_dict()["state"][0]
        assert torch.equal(sa["exp_avg_sq"], sb["exp_avg_sq"]), name
    assert torch.equal(straight.strategy_state["grad2d"], resumed.strategy_state["grad2d"])
    assert straight.pose is not None and resumed.pose is not None
    assert torch.equal(straight.pose.delta, resumed.pose.delta)
    # densification really happened in this run, so the test covered it
    assert len(straight.model) != 600


def test_two_trainings_same_bytes_for_any_extension_thread_count(tmp_path: Path) -> None:
    """CPU training is bit-identical run to run, with pose refinement (the viewmat gradient
    is a sum over Gaussians in the C++ projection) and densification, whether its kernels
    run on one thread or several."""
    from toolkit.splat.rasterize import cpp_ext

    views = _views(n=3, width=32, height=24, n_gauss=600)
    before = cpp_ext._threads["composite"]
    runs = []
    try:
        for i, threads in enumerate((1, 2, 2)):
            cpp_ext.set_threads(threads)
            t = Trainer(_start_model(600), views, _cfg(checkpoint_every=0), tmp_path / str(i))
            t.train()
            runs.append(t)
    finally:
        cpp_ext.set_threads(before)
    a = runs[0]
    assert a.pose is not None and float(a.pose.delta.detach().abs().max()) > 0
    assert len(a.model) != 600
    for b in runs[1:]:
        for name, p in a.model.params.items():
            assert torch.equal(b.model.params[name], p), name
        assert b.pose is not None and torch.equal(a.pose.delta, b.pose.delta)


def test_depth_term_is_the_mean_error_over_pixels_with_depth() -> None:
    """The depth term is the mean |rendered - lidar-scaled| over the pixels that hold a
    depth (0 = none), whatever the others render; a view without any adds 0."""
    views = _views(n=1, width=32, height=24, n_gauss=600)
    v = views[0]
    assert v.depth is not None
    depth = v.depth.clone()
    depth[: depth.shape[0] // 2] = 0.0  # the top half: no depth
    depth[depth > 0] += 0.25  # 25 cm off where there is one
    cfg = _cfg(depth_weight=0.1, densify=StrategyConfig(enabled=False))
    model = ground_truth_model(600, seed=1)
    trainer = Trainer(model, [TrainView(v.image, v.camera, v.T_camera_world, depth, "d")], cfg)
    with torch.no_grad():
        out = render(model, v.camera, v.T_camera_world, backend=BACKEND)
    valid = depth > 0
    expected = float((out.depth - depth).abs()[valid].mean())
    rec = trainer.train_step()
    assert expected > 0.1
    assert rec["depth_l1_m"] == pytest.approx(expected, rel=1e-5)
    empty = Trainer(ground_truth_model(600, seed=1),
                    [TrainView(v.image, v.camera, v.T_camera_world, torch.zeros_like(depth),
                               "none")], cfg)
    rec = empty.train_step()
    assert rec["depth_l1_m"] == 0.0 and np.isfinite(rec["loss"])


def test_every_tensor_training_makes_names_its_device(tmp_path: Path) -> None:
    """The stage trains on a CUDA GPU too (views stay in CPU memory): a tensor made without
    a device would land on the CPU there and fail, or copy every step. With the default
    device set to ``meta``, any such tensor would be a meta tensor and fail here, on the
    CPU; the run must also be the one without it, to the bit."""
    views = _views(n=3, width=32, height=24, n_gauss=600)
    depths = [v.depth.numpy() for v in views]
    gt = ground_truth_model(600, seed=1)  # the views' own scene: it covers their depths
    runs = []
    for default in (None, "meta"):
        trainer = Trainer(_start_model(600), views, _cfg(depth_weight=0.1),
                          tmp_path / str(default))
        torch.set_default_device(default)
        try:
            trainer.train()
            # A finished run's checkpoint read back (resume() logs, not raises, a failure).
            assert trainer.resume() and trainer.done is not None
            ev = evaluate_views(gt, views, BACKEND, gt_depths=depths)
        finally:
            torch.set_default_device(None)
        runs.append((trainer, ev))
    (a, ev_a), (b, ev_b) = runs
    assert len(a.model) != 600  # densification ran
    assert ev_a == ev_b and "depth_rmse_m" in ev_a
    for name, p in a.model.params.items():
        assert torch.equal(b.model.params[name], p), name


def test_resume_refuses_other_settings_or_data_and_takes_finished_runs(tmp_path: Path) -> None:
    views = _views(n=2, width=24, height=18, n_gauss=300)
    t = Trainer(_start_model(300), views, _cfg(), tmp_path)
    t.train_step()
    t.train_step()
    t.save_checkpoint()  # as the periodic checkpoint of a run that is then killed
    other = Trainer(_start_model(300), views, _cfg(lambda_dssim=0.5), tmp_path)
    assert not other.resume() and other.step == 0
    other_data = Trainer(_start_model(300), views, _cfg(), tmp_path, data_key="x")
    assert not other_data.resume()
    # another step count: its learning-rate schedule differs from the checkpoint's steps
    steps = Trainer(_start_model(300), views, _cfg(iterations=40), tmp_path)
    assert not steps.resume() and steps.step == 0
    # a time limit or another checkpoint interval leaves the optimisation alone
    limited = Trainer(_start_model(300), views, _cfg(max_seconds=100.0, checkpoint_every=5),
                      tmp_path)
    assert limited.resume() and limited.step == 2
    same = Trainer(_start_model(300), views, _cfg(), tmp_path)
    assert same.resume() and same.step == 2
    done = same.train()  # finishes: a rerun takes its model, without training again
    again = Trainer(_start_model(300), views, _cfg(), tmp_path)
    assert again.resume() and again.step == done.steps
    summary = again.train()
    assert summary.steps == done.steps and summary.final_loss == done.final_loss
    assert torch.equal(again.model.means, same.model.means)
    # the intervals leave a finished run's model too (it was trained again from step 0)
    for kw in ({"checkpoint_every": 3}, {"log_every": 50}):
        interval = Trainer(_start_model(300), views, _cfg(**kw), tmp_path)
        assert interval.resume() and interval.step == done.steps
    # another time limit does not: the model it stopped at may differ
    assert not Trainer(_start_model(300), views, _cfg(max_seconds=0.5), tmp_path).resume()
    # more steps asked of a finished run: another training (the rates decay over the run)
    longer = Trainer(_start_model(300), views, _cfg(iterations=done.steps + 4), tmp_path)
    assert not longer.resume() and longer.step == 0
    # another scene (the trainer's own key: views and model size) does not resume it
    other_scene = Trainer(_start_model(200), _views(n=3, width=24, height=18, n_gauss=200),
                          _cfg(), tmp_path)
    assert not other_scene.resume() and other_scene.step == 0
    # a truncated checkpoint is ignored, not a crash on every rerun
    (tmp_path / "checkpoint.pt").write_bytes(b"")
    fresh = Trainer(_start_model(300), views, _cfg(), tmp_path)
    assert not fresh.resume() and fresh.step == 0


def test_a_checkpoint_with_a_flipped_bit_trains_afresh_with_a_warning(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    views = _views(n=2, width=24, height=18, n_gauss=300)
    t = Trainer(_start_model(300), views, _cfg(), tmp_path)
    t.train_step()
    t.train_step()
    path = t.save_checkpoint()
    raw = bytearray(path.read_bytes())
    means = t.model.means.detach().cpu().numpy().tobytes()  # [300, 3] float32
    at = raw.find(means)
    assert at >= 0 and raw.find(means, at + 1) < 0
    raw[at + len(means) // 2] ^= 0x04  # one bit of one coordinate, the size unchanged
    path.write_bytes(bytes(raw))
    # torch.load checks no CRC: the damaged zip still loads, with one coordinate changed.
    damaged = torch.load(io.BytesIO(bytes(raw[raw.index(b"PK\x03\x04"):])),
                         map_location="cpu", weights_only=False)
    changed = damaged["params"]["means"] != t.model.means.detach().cpu()
    assert int(changed.sum()) == 1
    with caplog.at_level(logging.WARNING, logger="toolkit.splat.trainer"):
        fresh = Trainer(_start_model(300), views, _cfg(), tmp_path)
        assert not fresh.resume() and fresh.step == 0 and fresh.resumed_from is None
    assert "SHA-256 does not match" in caplog.text
    # a good checkpoint still resumes (test_checkpoint_resume_reproduces_uninterrupted_run:
    # to the uninterrupted run's bytes)
    t.save_checkpoint()
    again = Trainer(_start_model(300), views, _cfg(), tmp_path)
    assert again.resume() and again.step == 2
    assert torch.equal(again.model.means, t.model.means)


def test_a_checkpoint_from_before_the_checksum_trains_afresh_with_a_warning(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    views = _views(n=2, width=24, height=18, n_gauss=300)
    t = Trainer(_start_model(300), views, _cfg(), tmp_path)
    t.train_step()
    torch.save(t.state_dict(), tmp_path / "checkpoint.pt")  # as the old trainer wrote it
    with caplog.at_level(logging.WARNING, logger="toolkit.splat.trainer"):
        fresh = Trainer(_start_model(300), views, _cfg(), tmp_path)
        assert not fresh.resume() and fresh.step == 0
    assert "before splat checkpoints carried a checksum" in caplog.text


def test_torch_load_reads_the_checkpoint_zip_as_a_file_of_its_own(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """torch.load was handed the checkpoint file standing after its header line: it worked
    because torch 2.13's zip reader takes the position it is given as the start, no
    documented guarantee. Now it gets the zip as a file whose offsets start at 0."""
    import zipfile

    import toolkit.splat.trainer as trainer_module

    views = _views(n=2, width=24, height=18, n_gauss=300)
    t = Trainer(_start_model(300), views, _cfg(), tmp_path)
    t.train_step()
    path = t.save_checkpoint()
    body = path.read_bytes().split(b"\n", 2)[2]  # after the header and digest lines
    seen: dict[str, object] = {}
    real_load = torch.load

    def load(f: object, *args: object, **kwargs: object) -> object:
        seen["tell"] = f.tell()  # type: ignore[attr-defined]
        seen["head"] = f.read(4)  # type: ignore[attr-defined]
        seen["size"] = f.seek(0, io.SEEK_END)  # type: ignore[attr-defined]
        f.seek(0)  # type: ignore[attr-defined]
        seen["names"] = zipfile.ZipFile(f).namelist()  # type: ignore[arg-type]
        f.seek(0)  # type: ignore[attr-defined]
        return real_load(f, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(trainer_module.torch, "load", load)
    again = Trainer(_start_model(300), views, _cfg(), tmp_path)
    assert again.resume() and again.step == 1
    assert seen["tell"] == 0 and seen["head"] == b"PK\x03\x04" and seen["size"] == len(body)
    assert any(n.endswith("data.pkl") for n in seen["names"])  # type: ignore[attr-defined]
    assert torch.equal(again.model.means, t.model.means)


def _same_state(a: object, b: object) -> bool:
    """Whether two nested checkpoint states (dicts, lists, tensors, numbers) are equal."""
    if isinstance(a, torch.Tensor) or isinstance(b, torch.Tensor):
        return (isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor)
                and a.shape == b.shape and torch.equal(a, b))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same_state(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(_same_state(x, y) for x, y in zip(a, b, strict=True))
    return a == b


def _break(state: dict, part: str) -> None:
    """Damage one of the parts ``load_state_dict`` reads after the parameters."""
    if part == "optimizer shape":  # a later group's moment, one Gaussian short (shN has
        # none yet: its degree starts at step 10)
        moments = state["optimizers"]["sh0"]["state"][0]
        moments["exp_avg"] = moments["exp_avg"][1:].clone()
    elif part == "strategy statistics":  # one per Gaussian, one short
        state["strategy_state"]["grad2d"] = state["strategy_state"]["grad2d"][1:].clone()
    elif part == "strategy state":
        state["strategy_state"] = None
    elif part == "generator":
        state["generator"] = torch.zeros(3, dtype=torch.uint8)
    elif part == "pose optimiser":
        del state["pose_opt"]
    else:
        raise AssertionError(part)


@pytest.mark.parametrize("part", ["optimizer shape", "strategy statistics", "strategy state",
                                  "generator", "pose optimiser"])
def test_a_checkpoint_broken_part_way_leaves_the_trainer_fresh(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, part: str) -> None:
    """A checkpoint whose later part fails to load: "training from the start" really is.
    load_state_dict replaced the parameters (and optimisers, strategy state) before
    failing, and resume trained on from that half-loaded state at step 0."""
    views = _views(n=2, width=24, height=18, n_gauss=300)
    cfg = _cfg(iterations=12)
    t = Trainer(_start_model(300), views, cfg, tmp_path)
    for _ in range(6):  # densifies at step 5: the model's size changes too
        t.train_step()
    state = t.state_dict()
    _break(state, part)
    monkeypatch.setattr(t, "state_dict", lambda *a, **kw: state)
    t.save_checkpoint()  # with its digest: the file is sound, its contents are not

    offered = Trainer(_start_model(300), views, cfg, tmp_path)
    assert not offered.resume()
    never = Trainer(_start_model(300), views, cfg)
    assert offered.step == 0 and offered.resumed_from is None
    assert offered.history == [] and offered.ema == {}
    fresh_state, offered_state = never.state_dict(), offered.state_dict()
    for k in ("params", "optimizers", "strategy_state", "generator", "pose", "pose_opt"):
        assert _same_state(offered_state[k], fresh_state[k]), k
    # and a training from it is the one never offered the checkpoint, to the bit
    offered.train()
    never.train()
    assert offered.history == never.history
    assert _same_state(offered.state_dict(), never.state_dict())


def _meta_for(model: GaussianModel, grads: torch.Tensor) -> RenderMeta:
    n = len(model)
    means2d = torch.zeros(n, 2, requires_grad=True)
    means2d.grad = grads
    return RenderMeta(torch.arange(n), means2d, torch.ones(n, 2, dtype=torch.int32),
                      torch.ones(n), 100, 100, n, "torch")


def _adam(model: GaussianModel) -> dict[str, torch.optim.Optimizer]:
    opts = {k: torch.optim.Adam([p], lr=1e-3) for k, p in model.params.items()}
    loss = sum((p * p).sum() for p in model.params.values())
    loss.backward()  # type: ignore[union-attr]
    for o in opts.values():
        o.step()
    return opts


def test_strategy_clone_split_prune_keeps_adam_state_aligned() -> None:
    n = 6
    model = GaussianModel(torch.randn(n, 3), torch.log(torch.tensor([[0.001] * 3] * 3
                                                                     + [[0.5] * 3] * 3)),
                          torch.tensor([[1.0, 0, 0, 0]] * n),
                          torch.logit(torch.tensor([0.5, 0.5, 0.001, 0.5, 0.5, 0.5])),
                          torch.zeros(n, 3), torch.zeros(n, 3, 3))
    opts = _adam(model)
    big = torch.exp(model.log_scales[3]).detach()
    s = DefaultStrategy(StrategyConfig(refine_start_iter=0, refine_every=1, reset_every=1000))
    state = s.initialize_state(n, scene_scale=1.0)
    # Large gradient for Gaussians 0 (small: clone) and 3 (large: split).
    g = torch.zeros(n, 2)
    g[0] = g[3] = 1.0
    report = s.step_post_backward(model, opts, state, 1, _meta_for(model, g),
                                  torch.Generator().manual_seed(0))
    assert report == {"cloned": 1, "split": 1, "pruned": 1, "reset": 0}
    # 6 + 1 clone + 1 (split: one replaced by two) - 1 pruned transparent one
    assert len(model) == 7
    for name, p in model.params.items():
        st = opts[name].state[p]
        assert st["exp_avg"].shape == p.shape, name
    split_scales = torch.exp(model.log_scales[-2:]).detach()
    torch.testing.assert_close(split_scales, (big / 1.6).expand(2, 3))


def test_strategy_respects_budget_and_resets_opacity() -> None:
    n = 10
    model = GaussianModel(torch.randn(n, 3), torch.full((n, 3), -7.0),
                          torch.tensor([[1.0, 0, 0, 0]] * n), torch.full((n,), 3.0),
                          torch.zeros(n, 3), torch.zeros(n, 0, 3))
    opts = _adam(model)
    s = DefaultStrategy(StrategyConfig(refine_start_iter=0, refine_every=1, reset_every=2),
                        max_gaussians=13)
    state = s.initialize_state(n, 1.0)
    g = torch.arange(n, dtype=torch.float32)[:, None].repeat(1, 2)  # all above threshold
    s.step_post_backward(model, opts, state, 1, _meta_for(model, g), None)
    assert len(model) == 13  # 3 strongest cloned, not all 9 candidates
    report = s.step_post_backward(model, opts, state, 2, _meta_for(model, torch.zeros(13, 2)),
                                  None)
    assert report["reset"] == 1
    assert float(torch.sigmoid(model.opacity_logits.detach()).max()) <= 0.01 + 1e-6


@pytest.mark.parametrize("budget_mb", [0.5])
def test_memory_budget_caps_count(budget_mb: float) -> None:
    from toolkit.splat.trainer import bytes_per_gaussian, gaussian_cap

    cfg = TrainConfig(memory_budget_mb=budget_mb, sh_degree=3)
    assert gaussian_cap(cfg) == int(budget_mb * 2**20 / bytes_per_gaussian(3))
    assert bytes_per_gaussian(3) == 59 * 16


def test_a_view_that_sees_no_gaussian_is_a_step_without_gradient() -> None:
    """Every Gaussian out of sight (50 m above the room): the reference rasteriser renders
    the background alone, with no gradient to take; training goes on instead of raising."""
    views = _views(n=2, width=24, height=18, n_gauss=300)
    model = _start_model(300)
    with torch.no_grad():
        model.means.data[:, 2] += 50.0
    cfg = TrainConfig(iterations=4, sh_degree=0, depth_weight=0.0, checkpoint_every=0,
                      densify=StrategyConfig(enabled=False), backend="torch")
    summary = Trainer(model, views, cfg).train()
    assert summary.steps == 4 and np.isfinite(summary.final_loss)


def test_views_take_numpy_images_and_refuse_other_dtypes() -> None:
    cam = PinholeCamera(8, 6, 10.0, 10.0, 3.5, 2.5)
    v = TrainView(np.zeros((6, 8, 3), np.uint8), cam, np.eye(4), np.ones((6, 8), np.float32))
    assert isinstance(v.image, torch.Tensor) and v.image.dtype == torch.uint8
    assert isinstance(v.depth, torch.Tensor) and v.depth.dtype == torch.float32
    with pytest.raises(ValueError, match="uint8"):
        TrainView(np.zeros((6, 8, 3), np.float32), cam, np.eye(4))
    # A 16-bit depth PNG's values (5000 per metre) are not metres.
    with pytest.raises(ValueError, match="float metres.*read_depth"):
        TrainView(np.zeros((6, 8, 3), np.uint8), cam, np.eye(4),
                  np.full((6, 8), 8250, np.uint16))
    # BGR -> RGB as cv2 users write it, a flipped depth: negative strides.
    bgr = np.arange(6 * 8 * 3, dtype=np.uint8).reshape(6, 8, 3)
    depth = np.arange(48, dtype=np.float32).reshape(6, 8)
    v = TrainView(bgr[..., ::-1], cam, np.eye(4), depth[::-1], mask=np.ones((6, 8), bool))
    assert np.array_equal(v.image.numpy(), bgr[..., ::-1])
    assert np.array_equal(v.depth.numpy(), depth[::-1]) and bool(v.mask.all())


def test_the_gaussian_cap_counts_the_models_own_sh_degree() -> None:
    """A degree-3 model trained at degree 1 stores degree-3 coefficients: the memory budget
    caps it at the degree-3 size (the config's degree let it hold 1.6 times the budget)."""
    from toolkit.splat.trainer import bytes_per_gaussian

    cfg = TrainConfig(memory_budget_mb=1.0, sh_degree=1, checkpoint_every=0)
    views = _views(n=2, width=24, height=18, n_gauss=300)
    pts, rgb = room_points(300, seed=1)
    trainer = Trainer(init_from_points(pts, rgb, sh_degree=3), views, cfg)
    assert trainer.model.max_sh_degree == 3
    assert trainer.cap == int(2**20 / bytes_per_gaussian(3))


def test_exposure_gain_is_the_least_squares_gain() -> None:
    from toolkit.splat.trainer import exposure_gain

    rng = np.random.default_rng(4)
    render = torch.as_tensor(rng.uniform(0.1, 0.9, (20, 30, 3)), dtype=torch.float32)
    g_true = torch.tensor([0.8, 1.0, 1.3])
    mask = torch.ones(20, 30, dtype=torch.bool)
    mask[:5] = False
    target = render * g_true
    target[:5] = 0.0  # outside the mask: not fitted
    assert torch.allclose(exposure_gain(render, target, mask), g_true, atol=1e-5)
    # Pulled towards 1 by the regulariser, never past it.
    g = exposure_gain(render, target, mask, reg=1.0)
    assert bool((g[0] > 0.8) & (g[0] < 1.0)) and bool((g[2] > 1.0) & (g[2] < 1.3))


def test_exposure_compensation_keeps_colours_apart_from_the_cameras_gain() -> None:
    """Images of one scene at gains 0.7-1.4 (auto exposure): fitting a gain per image keeps
    the scene's own colours; without it the splats learn the gains as view-dependent colour
    and score worse on images at gain 1 (and on their best gain)."""
    clean = _views(n=6)
    gains = [0.7, 1.4, 0.85, 1.2, 0.75, 1.3]
    exposed = [TrainView((v.image.float() * g).clamp(0, 255).round().to(torch.uint8), v.camera,
                         v.T_camera_world, v.depth, v.name) for v, g in zip(clean, gains,
                                                                              strict=True)]
    scores = {}
    for mode in ("none", "gain"):
        model = _start_model(1500)
        cfg = TrainConfig(iterations=120, sh_degree=1, lr_sh0=0.05, lr_opacities=0.1,
                          depth_weight=0.0, densify=StrategyConfig(enabled=False),
                          checkpoint_every=0, backend=BACKEND, exposure=mode)
        Trainer(model, exposed, cfg).train()
        scores[mode] = evaluate_views(model, clean, BACKEND)
    for key in ("psnr_db", "psnr_exposure_matched_db"):
        assert scores["gain"][key] > scores["none"][key] + 1.0, (key, scores)


def test_masked_l1_is_the_mean_over_the_valid_pixels() -> None:
    """A mean over every pixel (the masked ones set to the target) shrank the colour loss
    and its gradients by the valid share."""
    gt = torch.zeros(20, 30, 3)
    mask = torch.ones(20, 30, dtype=torch.bool)
    mask[:, :10] = False  # a third of the image: lens corners
    render = torch.full((20, 30, 3), 0.5, requires_grad=True)
    color = torch.where(mask[..., None], render, gt)
    loss = masked_l1(color, gt, mask)
    assert float(loss.detach()) == pytest.approx(0.5)
    loss.backward()
    assert float(render.grad[0, 15, 0]) == pytest.approx(1 / (20 * 20 * 3))
    assert float(render.grad[0, 5, 0]) == 0.0
    assert float(masked_l1(render.detach(), gt)) == pytest.approx(0.5)


def test_the_ssim_term_is_taken_over_a_views_valid_pixels(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Masked pixels hold the target and score SSIM 1: over every window, a lens mask
    shrank the SSIM term (and its gradients) by the valid share, against the L1's mean
    over valid pixels."""
    import dataclasses

    import toolkit.splat.trainer as trainer_module

    views = _views(n=2, width=24, height=18, n_gauss=300)
    mask = torch.ones(18, 24, dtype=torch.bool)
    mask[:, :8] = False
    views = [dataclasses.replace(v, mask=mask) for v in views]
    seen: list[object] = []
    ssim = trainer_module.ssim_fn

    def recording(a: torch.Tensor, b: torch.Tensor, **kw: object) -> torch.Tensor:
        seen.append(kw.get("mask"))
        return ssim(a, b, **kw)

    monkeypatch.setattr(trainer_module, "ssim_fn", recording)
    Trainer(_start_model(300), views, _cfg(iterations=2, checkpoint_every=0)).train()
    assert len(seen) == 2 and all(m is not None and torch.equal(m, mask) for m in seen)


def test_opacity_resets_can_be_turned_off_and_absgrad_is_refused() -> None:
    """reset_every 0 (a natural "never") and refine_every 0 divided by zero mid-training;
    absgrad was accepted and ignored."""
    from pydantic import ValidationError

    views = _views(n=2, width=24, height=18, n_gauss=300)
    never = _cfg(iterations=12, checkpoint_every=0,
                 densify=StrategyConfig(refine_start_iter=2, refine_every=5, reset_every=0))
    Trainer(_start_model(300), views, never).train()
    with pytest.raises(ValidationError, match="refine_every"):
        StrategyConfig(refine_every=0)
    with pytest.raises(ValidationError, match="absgrad: true"):
        StrategyConfig(absgrad=True)


def test_settings_out_of_range_are_refused_before_training() -> None:
    """A 0..255 background trained against a colour no render reaches and crashed the
    TSDF comparison after training; a negative lr_means_final made the rate complex at
    step 1; negative rates failed once the views were loaded."""
    from pydantic import ValidationError

    for bad in ({"background": (255, 255, 255)}, {"lr_means_final": -0.1},
                {"lr_scales": -1.0}, {"pose_reg": -1.0}):
        with pytest.raises(ValidationError):
            TrainConfig(**bad)  # type: ignore[arg-type]
    assert TrainConfig(background=(1.0, 1.0, 1.0)).background == (1.0, 1.0, 1.0)


def test_refinement_stops_at_half_the_training_by_default() -> None:
    """gsplat refines for 15000 of 30000 steps; the default of 15000 refined a 1500-step
    training to its step 1400 (its last clones had 100 steps to settle)."""
    views = _views(n=2, width=24, height=18, n_gauss=300)
    default = Trainer(_start_model(300), views, _cfg(iterations=40))
    assert default.strategy.cfg.refine_stop_iter == 20
    fixed = _cfg(iterations=40, densify=StrategyConfig(refine_stop_iter=35))
    assert Trainer(_start_model(300), views, fixed).strategy.cfg.refine_stop_iter == 35


def test_scene_scale_is_continuous_in_the_cameras_spread() -> None:
    # A 6 x 4 x 2.6 m room seen from cameras 2 x 9 cm and 2 x 11 cm apart: the scale (and
    # the means' rate and the size tests with it) jumped 22x at 10 cm.
    pts, _ = room_points(3000, seed=0)
    means = torch.as_tensor(pts)
    median = float(np.median(np.linalg.norm(pts - pts.mean(0), axis=1)))
    cam = PinholeCamera.from_fov(16, 12, 70.0)
    img = np.zeros((12, 16, 3), np.uint8)

    def scale(half: float) -> float:
        poses = [inv_se3(look_pose(np.array([x, 0.0, 1.2]), 0.0)) for x in (-half, half)]
        return scene_scale_of([TrainView(img, cam, T, None, f"v{i}")
                               for i, T in enumerate(poses)], means)

    assert scale(0.09) == pytest.approx(median, rel=1e-3)  # torch: the lower middle value
    assert scale(0.11) == pytest.approx(median, rel=1e-3)
    assert scale(5.0) == pytest.approx(5.5, rel=1e-9)  # cameras around the scene: gsplat's

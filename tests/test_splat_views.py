"""Training views read on demand: the memory budget holds, every view comes back as read,
and training on them gives the same model as on views held in memory."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import torch

# The tests folder is on sys.path.
from test_splat_train import _start_model, _views

import toolkit.splat.views as views_module
from toolkit.camera import PinholeCamera
from toolkit.splat.strategy import StrategyConfig
from toolkit.splat.trainer import TrainConfig, Trainer, TrainView
from toolkit.splat.views import LazyList, ViewSet, view_bytes

# tiny images train faster on one thread (conftest.one_thread)
pytestmark = pytest.mark.usefixtures("one_thread")


def _pose(i: int) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [0.1 * i, 0.0, 0.0]
    return T


VIEW_BYTES = 6 * 8 * 3 + 6 * 8 * 4  # a view of _loader: uint8 image, float32 depth


def _loader(n: int, calls: list[int] | None = None) -> tuple[np.ndarray, list[str], object]:
    cam = PinholeCamera.from_fov(8, 6, 70.0)

    def load(i: int) -> TrainView:
        if calls is not None:
            calls.append(i)
        img = np.full((6, 8, 3), i, np.uint8)
        return TrainView(img, cam, _pose(i), np.full((6, 8), 1.0 + i, np.float32), f"v{i}")

    return np.array([_pose(i) for i in range(n)]), [f"v{i}" for i in range(n)], load


def test_a_set_that_fits_is_read_once_up_front() -> None:
    calls: list[int] = []
    poses, names, load = _loader(10, calls)
    views = ViewSet(poses, names, load, cache_bytes=10**6)
    assert views.eager and sorted(calls) == list(range(10))
    assert [int(views[i].image[0, 0, 0]) for i in range(10)] == list(range(10))
    assert views.reads == 10 and views[-1].name == "v9"


def test_a_set_over_budget_holds_at_most_its_budget_and_reads_on_demand() -> None:
    calls: list[int] = []
    poses, names, load = _loader(20, calls)
    one = VIEW_BYTES
    views = ViewSet(poses, names, load, cache_bytes=3 * one)
    assert not views.eager and calls == [0]
    order = list(np.random.default_rng(0).permutation(20)) * 2
    for i in order:
        v = views[int(i)]
        assert v.name == f"v{i}" and float(v.depth[0, 0]) == 1.0 + i
        assert views.held_bytes <= 3 * one
    assert views.reads > 20  # a random order over more than the budget rereads
    with pytest.raises(IndexError):
        views[20]


def test_prefetched_views_are_read_once_and_in_the_background() -> None:
    calls: list[int] = []
    poses, names, load = _loader(12, calls)
    one = VIEW_BYTES
    views = ViewSet(poses, names, load, cache_bytes=2 * one)
    try:
        for i in range(1, 12):
            views.prefetch(i)
            assert views[i].name == f"v{i}"
        assert calls == [0] + list(range(1, 12))  # none read twice
    finally:
        views.close()


def test_in_the_trainers_order_each_view_is_read_once() -> None:
    """The trainer prefetches step s+1's view, then trains on step s's: the read for s+1
    must wait for its step (dropping finished reads read every view twice)."""
    calls: list[int] = []
    poses, names, load = _loader(6, calls)
    one = VIEW_BYTES
    views = ViewSet(poses, names, load, cache_bytes=one)
    order = [int(i) for i in np.random.default_rng(1).permutation(6)] * 5  # [30]
    try:
        for s, i in enumerate(order):
            if s + 1 < len(order):
                views.prefetch(order[s + 1])
            assert views[i].name == f"v{i}"
    finally:
        views.close()
    repeats = sum(a == b for a, b in zip(order, order[1:], strict=False))
    assert views.reads == 1 + len(order) - repeats - (order[0] == 0)


def test_views_larger_than_the_first_switch_to_reading_on_demand() -> None:
    """The first view decides whether all fit; a later view with a depth target the first
    lacked is larger: past the budget, the rest are read on demand and the held bytes come
    back under it."""
    cam = PinholeCamera.from_fov(8, 6, 70.0)

    def load(i: int) -> TrainView:
        depth = None if i == 0 else np.ones((6, 8), np.float32)
        return TrainView(np.zeros((6, 8, 3), np.uint8), cam, _pose(i), depth, f"v{i}")

    n = 10
    views = ViewSet(np.array([_pose(i) for i in range(n)]), [f"v{i}" for i in range(n)],
                    load, cache_bytes=n * 6 * 8 * 3 + 1)
    assert not views.eager and views.held_bytes <= n * 6 * 8 * 3 + 1
    assert [views[i].name for i in range(n)] == [f"v{i}" for i in range(n)]


def test_the_eager_set_is_read_by_several_threads_at_once(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Views 1 and 2 each wait for the other's read to start: one-by-one reading never
    gets past view 1 (the barrier breaks). By default, a thread per core (two here)."""
    monkeypatch.setattr(views_module, "usable_cpus", lambda: 2, raising=False)
    poses, names, plain = _loader(6)
    both = threading.Barrier(2, timeout=5)

    def load(i: int) -> TrainView:
        if i in (1, 2):
            both.wait()
        return plain(i)  # type: ignore[operator]

    views = ViewSet(poses, names, load, cache_bytes=10**6)
    assert views.eager and views.reads == 6


def test_views_read_by_threads_are_the_ones_read_one_by_one_in_order() -> None:
    """Later views finish first; each is kept under its own index, the progress bar counts
    every one, and the set is what one-by-one reading gives."""
    n = 24
    poses, names, plain = _loader(n)

    def load(i: int) -> TrainView:
        time.sleep(0.002 * ((n - i) % 5))  # reads finish out of order
        return plain(i)  # type: ignore[operator]

    def counting(seen: list[int]):  # type: ignore[no-untyped-def]
        def progress(it, total, desc):  # type: ignore[no-untyped-def]
            for i in it:
                seen.append(i)
                yield i
        return progress

    got = {}
    for workers in (1, 4):
        seen: list[int] = []
        views = ViewSet(poses, names, load, cache_bytes=10**6, progress=counting(seen),
                        read_workers=workers)
        assert views.eager and views.reads == n and seen == list(range(1, n))
        got[workers] = [(v.name, v.image.numpy().tobytes(), v.depth.numpy().tobytes())
                        for v in (views[i] for i in range(n))]
        assert views.reads == n  # all held: none read again
    assert got[4] == got[1]
    assert [name for name, _, _ in got[4]] == names


def test_a_threaded_read_past_the_budget_switches_as_one_by_one_reading_does() -> None:
    cam = PinholeCamera.from_fov(8, 6, 70.0)

    def load(i: int) -> TrainView:
        depth = None if i == 0 else np.ones((6, 8), np.float32)
        return TrainView(np.full((6, 8, 3), i, np.uint8), cam, _pose(i), depth, f"v{i}")

    n = 30
    first = 6 * 8 * 3
    held = {}
    for workers in (1, 3):
        seen: list[int] = []

        def progress(it, total, desc, seen=seen):  # type: ignore[no-untyped-def]
            for i in it:
                seen.append(i)
                yield i

        views = ViewSet(np.array([_pose(i) for i in range(n)]), [f"v{i}" for i in range(n)],
                        load, cache_bytes=n * first + 1, progress=progress,
                        read_workers=workers)
        assert not views.eager and views.held_bytes <= n * first + 1
        held[workers] = (list(views._cache), views.held_bytes, seen)
        # up to 2 reads per thread beyond the view that passed the budget, then dropped
        assert views.reads <= len(seen) + 1 + 2 * workers
        assert [int(views[i].image[0, 0, 0]) for i in range(n)] == list(range(n))
    assert held[3] == held[1]


def test_a_view_that_fails_to_read_raises_its_error_when_read_by_threads() -> None:
    poses, names, plain = _loader(40)
    calls: list[int] = []

    def load(i: int) -> TrainView:
        calls.append(i)
        if i == 5:
            raise FileNotFoundError("camera/images/000005.png: missing or not a readable "
                                    "image")
        return plain(i)  # type: ignore[operator]

    before = {t.ident for t in threading.enumerate()}
    with pytest.raises(FileNotFoundError, match=r"000005.png: missing or not a readable"):
        ViewSet(poses, names, load, cache_bytes=10**6, read_workers=3)
    assert max(calls) <= 5 + 2 * 3 + 1  # no further reading than the threads ran ahead
    # the reading threads are gone
    assert not [t for t in threading.enumerate()
                if t.ident not in before and t.name.startswith("prefetch")]


def test_a_loader_returning_another_pose_is_refused() -> None:
    poses, names, load = _loader(3)
    poses = poses.copy()
    poses[0, 0, 3] = 5.0
    with pytest.raises(ValueError, match="another pose"):
        ViewSet(poses, names, load, cache_bytes=10**6)


def test_lazy_list_computes_each_item_when_asked() -> None:
    seen: list[int] = []
    items = LazyList(3, lambda i: seen.append(i) or i * i)
    assert len(items) == 3 and items[2] == 4 and items[-1] == 4 and seen == [2, 2]
    with pytest.raises(IndexError):
        items[3]


def test_training_on_views_read_on_demand_gives_the_same_model() -> None:
    held = _views(n=5, width=32, height=24, n_gauss=600)
    poses = np.array([v.T_camera_world for v in held])
    lazy = ViewSet(poses, [v.name for v in held], lambda i: held[i],
                   cache_bytes=view_bytes(held[0]) + 1)
    assert not lazy.eager
    cfg = TrainConfig(iterations=20, sh_degree=1, sh_degree_interval=10, checkpoint_every=0,
                      seed=3, densify=StrategyConfig(refine_start_iter=4, refine_every=5,
                                                     grow_grad2d=2e-5))
    a = Trainer(_start_model(600), held, cfg)
    a.train()
    b = Trainer(_start_model(600), lazy, cfg)
    b.train()
    lazy.close()
    assert a.data_key == b.data_key
    for k, p in a.model.params.items():
        assert torch.equal(p, b.model.params[k]), k

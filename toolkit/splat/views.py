"""Training views read on demand, within a memory budget.

A long recording has more views than memory: an hour at 10 Hz is 36,000 images, 5.8 GB at
160x120 with depth and 79 GB at full size, while a training run of a few thousand steps
touches a few thousand of them. ``ViewSet`` holds every view's pose and name, and the pixels
of as many views as ``cache_bytes`` allows; the rest are read from disk when a step asks for
them (the most recently used stay), the next one in a background thread while the current
step trains (the view order is known in advance). A recording that fits is read once, up
front, as before: the results are the same either way, only the reading differs.

Up front, views are read by a few threads at once (PNG decoding, undistortion and resizing
in OpenCV release the GIL), kept in index order as they come: the same views, held and
counted against the budget in the same order as one after another.
"""

from __future__ import annotations

import contextlib
import threading
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar, overload

import numpy as np

from toolkit.io.prefetch import prefetched
from toolkit.recipe.timing import usable_cpus
from toolkit.splat.trainer import TrainView

T = TypeVar("T")


def view_bytes(view: TrainView) -> int:
    """Memory one view's pixels take: image and depth target (the lens mask is one tensor
    all views share)."""
    n = view.image.numel() * view.image.element_size()
    if view.depth is not None:
        n += view.depth.numel() * view.depth.element_size()
    return n


class _Indexed(Sequence[T]):
    """A sequence of ``len`` items, item i from ``_item(i)``: indexing, negative indices
    and slices in one place."""

    def _item(self, i: int) -> T:
        raise NotImplementedError

    @overload
    def __getitem__(self, i: int) -> T: ...

    @overload
    def __getitem__(self, i: slice) -> list[T]: ...

    def __getitem__(self, i: int | slice) -> T | list[T]:
        n = len(self)
        if isinstance(i, slice):
            return [self._item(j) for j in range(*i.indices(n))]
        if not -n <= i < n:
            raise IndexError(f"item {i} of {n}")
        return self._item(i % n)


class ViewSet(_Indexed[TrainView]):
    """``len(poses)`` views; ``load(i)`` reads view i (its pose must be ``poses[i]``).

    ``views[i]`` returns the view, from memory or read now; ``prefetch(i)`` starts reading
    it in the background. Every view is read up front when ``n * bytes of the first view``
    fits ``cache_bytes`` (``eager``) and keeps fitting as they are read (views differ: some
    have a depth target, some not); otherwise at most that many bytes of views are held.
    ``read_workers`` threads read the eager set (None: up to 4, as many as there are cores;
    1: one after another in the caller's thread); ``load`` must be safe to call from
    several threads at once (the lazy mode's prefetching calls it from a thread too).
    """

    def __init__(self, poses: np.ndarray, names: list[str], load: Callable[[int], TrainView],
                 cache_bytes: int,
                 progress: Callable[[Iterator[int], int, str], Iterator[int]] | None = None,
                 read_workers: int | None = None) -> None:
        if len(names) != len(poses):
            raise ValueError(f"{len(names)} names for {len(poses)} poses")
        self.poses = np.asarray(poses, dtype=np.float64)  # [N, 4, 4] T_camera_world
        self.names = list(names)
        self._load = load
        self._budget = int(cache_bytes)
        self._cache: OrderedDict[int, TrainView] = OrderedDict()
        self._held = 0
        self._pending: dict[int, Future[TrainView]] = {}
        self._pool: ThreadPoolExecutor | None = None
        self._lock = threading.Lock()
        self.reads = 0  # views read from disk (a view read twice counts twice)
        self.eager = True
        if not len(poses):
            return
        first = self._read(0)
        self.view_bytes = view_bytes(first)
        self.eager = self.view_bytes * len(poses) <= self._budget
        self._keep(0, first)
        if self.eager:
            workers = min(4, usable_cpus()) if read_workers is None else max(1, read_workers)
            rest: Iterator[int] = iter(range(1, len(poses)))
            if progress is not None:
                rest = iter(progress(rest, len(poses) - 1, "splat: load views"))
            # Reads run at most 2 per thread ahead of the view being kept: past the budget,
            # those few are all that is read beyond what one-by-one reading read (and are
            # dropped, not kept).
            reads = prefetched(self._read, range(1, len(poses)),
                               ahead=2 * workers if workers > 1 else 0, workers=workers)
            with contextlib.closing(reads):
                for i in rest:
                    j, view = next(reads)
                    assert j == i
                    self._keep(i, view)
                    if self._held > self._budget:
                        # Later views are larger than the first (it had no depth target):
                        # read the rest on demand, dropping what passed the budget.
                        self.eager = False
                        with self._lock:
                            self._evict()
                        break

    @property
    def held_bytes(self) -> int:
        return self._held

    def _read(self, i: int) -> TrainView:
        view = self._load(i)
        with self._lock:
            self.reads += 1
        if not np.array_equal(view.T_camera_world, self.poses[i]):
            raise ValueError(f"view {i} ({view.name}) was read with another pose than its "
                             "ViewSet entry")
        return view

    def _keep(self, i: int, view: TrainView) -> None:
        with self._lock:
            if i in self._cache:
                self._cache.move_to_end(i)
                return
            self._cache[i] = view
            self._held += view_bytes(view)
            self._evict()

    def _evict(self) -> None:
        """With the lock held: the eager set holds everything; a lazy one drops the least
        recently used views down to the budget, but never the view just asked for."""
        while not self.eager and self._held > self._budget and len(self._cache) > 1:
            _, old = self._cache.popitem(last=False)
            self._held -= view_bytes(old)

    def __len__(self) -> int:
        return len(self.poses)

    def _item(self, i: int) -> TrainView:
        with self._lock:
            view = self._cache.get(i)
            if view is not None:
                self._cache.move_to_end(i)
                return view
            fut = self._pending.pop(i, None)
        view = fut.result() if fut is not None else self._read(i)
        self._keep(i, view)
        return view

    def prefetch(self, i: int) -> None:
        """Start reading view ``i`` in the background unless it is held or on its way."""
        if self.eager or not 0 <= i < len(self):
            return
        with self._lock:
            if i in self._cache or i in self._pending:
                return
            if self._pool is None:
                self._pool = ThreadPoolExecutor(1, thread_name_prefix="splat-views")
            self._pending[i] = self._pool.submit(self._read, i)
            # The trainer asks for each prefetched view one step later; older reads it never
            # asked for (a stop at the time limit) are dropped.
            while len(self._pending) > 2:
                del self._pending[next(iter(self._pending))]

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        self._pending.clear()


class LazyList(_Indexed[T]):
    """``n`` items, item i computed by ``load(i)`` each time it is asked for (held-out
    ground truth, read once while scoring)."""

    def __init__(self, n: int, load: Callable[[int], T]) -> None:
        self._n, self._load = n, load

    def __len__(self) -> int:
        return self._n

    def _item(self, i: int) -> T:
        return self._load(i)

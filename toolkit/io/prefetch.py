"""Reading ahead and writing behind in a thread.

Decoding and encoding image files (OpenCV) and reading arrays (numpy) release the GIL, so a
thread doing them overlaps a stage's computation on a second core - unlike threads doing
the numpy-heavy computation itself, which mostly wait for each other. The thread's work
does compete for the cores, though: a stage that times its own processing (``work_*``
metrics) measures more CPU and, with multi-threaded libraries, more wall time while it runs.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, TypeVar

T = TypeVar("T")
R = TypeVar("R")


def prefetched(load: Callable[[T], R], items: Iterable[T], ahead: int = 2,
               workers: int = 1) -> Iterator[tuple[T, R]]:
    """``(item, load(item))`` for every item in order, the next ``ahead`` items loading in
    ``workers`` threads meanwhile (``ahead`` 0: no thread; ``load`` must be safe to call
    from several threads at once when ``workers`` > 1). An error in ``load`` is raised when
    its item's turn comes; closing the generator early drops the loads not started."""
    if ahead <= 0:
        for item in items:
            yield item, load(item)
        return
    it = iter(items)
    pool = ThreadPoolExecutor(max_workers=max(1, workers), thread_name_prefix="prefetch")
    pending: deque[tuple[T, Future]] = deque()
    try:
        for item in it:
            pending.append((item, pool.submit(load, item)))
            if len(pending) > ahead:
                first, fut = pending.popleft()
                yield first, fut.result()
        while pending:
            first, fut = pending.popleft()
            yield first, fut.result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


class WriteBehind:
    """Runs writes in a thread, in submission order, at most ``max_pending`` behind (or at
    once, with ``threaded=False``).

    Use as a context manager: leaving it waits for every write and raises the first error
    (as does a ``submit`` after a failed write).
    """

    def __init__(self, max_pending: int = 8, threaded: bool = True) -> None:
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="write-behind") \
            if threaded else None
        self._pending: deque[Future] = deque()
        self._max = max(1, max_pending)

    def submit(self, fn: Callable[..., Any], *args: Any) -> None:
        if self._pool is None:
            fn(*args)
            return
        while self._pending and (self._pending[0].done() or len(self._pending) >= self._max):
            self._pending.popleft().result()
        self._pending.append(self._pool.submit(fn, *args))

    def flush(self) -> None:
        """Wait until every write submitted so far is on disk (raising the first error)."""
        while self._pending:
            self._pending.popleft().result()

    def close(self) -> None:
        try:
            self.flush()
        finally:
            if self._pool is not None:
                self._pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> WriteBehind:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        if exc_type is None:
            self.close()
            return
        # Already failing: let the writes finish (each is atomic) without masking the error.
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)

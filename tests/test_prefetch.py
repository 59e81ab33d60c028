"""Reading ahead and writing behind in a thread: order, errors and overlap."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from toolkit.io.prefetch import WriteBehind, prefetched


def test_prefetched_keeps_order_and_loads_ahead() -> None:
    started: list[int] = []

    def load(i: int) -> int:
        started.append(i)
        return i * i

    out = []
    for i, sq in prefetched(load, range(6), ahead=2):
        out.append((i, sq))
        if i == 0:
            # The thread meanwhile loads items 1 and 2, and no further. Waited for, not
            # slept on: a loaded machine may not run the thread within a fixed 50 ms.
            deadline = time.monotonic() + 30
            while len(started) < 3 and time.monotonic() < deadline:
                time.sleep(0.001)
            time.sleep(0.01)  # room for a wrong fourth load to show
            assert started == [0, 1, 2]
    assert out == [(i, i * i) for i in range(6)]


def test_without_a_thread_the_same_in_the_callers_thread(tmp_path: Path) -> None:
    me = threading.get_ident()
    got = list(prefetched(lambda i: (i, threading.get_ident()), range(3), ahead=0))
    assert got == [(i, (i, me)) for i in range(3)]
    with WriteBehind(threaded=False) as w:
        w.submit(lambda: (tmp_path / "a").write_text(str(threading.get_ident())))
        assert (tmp_path / "a").read_text() == str(me)  # written before submit returned


def test_prefetched_raises_a_load_error_at_its_turn() -> None:
    def load(i: int) -> int:
        if i == 3:
            raise FileNotFoundError(f"frame {i}")
        return i

    seen = []
    with pytest.raises(FileNotFoundError, match="frame 3"):
        for i, _ in prefetched(load, range(6)):
            seen.append(i)
    assert seen == [0, 1, 2]


def test_write_behind_writes_everything_in_a_thread_in_order(tmp_path: Path) -> None:
    threads, order = set(), []

    def write(path: Path, text: str) -> None:
        threads.add(threading.get_ident())
        order.append(text)
        path.write_text(text)

    with WriteBehind(max_pending=2) as w:
        for k in range(5):
            w.submit(write, tmp_path / f"{k}.txt", str(k))
    assert order == [str(k) for k in range(5)]
    assert threading.get_ident() not in threads
    assert sorted(p.read_text() for p in tmp_path.glob("*.txt")) == [str(k) for k in range(5)]


def test_write_behind_reports_a_failed_write() -> None:
    def fail() -> None:
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        with WriteBehind() as w:
            w.submit(fail)

"""Peak resident memory of one stage, for the run's timing table.

Stages run one after another in the runner's process, whose peak resident set
(``ru_maxrss``) only grows: after the second stage it is the larger of the two. So:

- a stage that raised the process's peak gets that peak, **exact**;
- another one gets the largest resident set **sampled** every 20 ms while it ran
  (``/proc/self/statm``; a spike shorter than that can be missed), shown ``~``;
- where nothing can be sampled (no ``/proc``: macOS, Windows) it gets the process's peak
  so far, an upper **bound**, shown ``<=``.

The process's peak itself is never reset (Linux could, through ``/proc/self/clear_refs``),
so ``/usr/bin/time -v`` and other tools still see the whole run's. Memory of child
processes (a compiler building an extension) is not counted.

Between stages the runner hands back what the finished stage freed
(``release_freed_memory``): glibc keeps freed heap memory for the process (arrays under its
mmap threshold, which rises to 32 MiB once a larger array is freed, and every thread's
arena), so the next stage started where the last one's peak had left the resident set.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import os
import sys
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

try:
    import resource
except ImportError:  # Windows
    resource = None  # type: ignore[assignment]

How = Literal["exact", "sampled", "bound"]
_STATM = Path("/proc/self/statm")
SAMPLE_S = 0.02


@dataclass(frozen=True)
class PeakMemory:
    """A stage's peak resident memory in MiB (2^20 bytes) and how it is known (module
    doc): ``exact``, ``sampled`` (a lower bound) or ``bound`` (an upper bound)."""

    mib: float
    how: How

    def text(self) -> str:
        """For a table: ``1897``, ``~1195`` (sampled) or ``<= 1897`` (bound)."""
        prefix = {"exact": "", "sampled": "~", "bound": "<= "}[self.how]
        return f"{prefix}{self.mib:.0f}"


def _maxrss_mib() -> float | None:
    if resource is None:
        return None
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    # Bytes on macOS, KiB elsewhere (getrusage(2)).
    return peak / 2**20 if sys.platform == "darwin" else peak / 1024.0


def _page_mib() -> float:
    try:
        return os.sysconf("SC_PAGE_SIZE") / 2**20
    except (AttributeError, ValueError, OSError):
        return 4096 / 2**20


def _rss_mib(page_mib: float) -> float | None:
    try:
        return int(_STATM.read_text().split()[1]) * page_mib  # resident pages
    except (OSError, ValueError, IndexError):
        return None


class StagePeak:
    """Started when a stage starts (a sampling thread); ``finish()`` stops it and gives
    the stage's peak."""

    def __init__(self) -> None:
        self._start_peak = _maxrss_mib()
        self._page = _page_mib()
        self._sampled = _rss_mib(self._page)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if self._sampled is not None:
            self._thread = threading.Thread(target=self._sample, name="peak-memory",
                                            daemon=True)
            self._thread.start()

    def _sample(self) -> None:
        while not self._stop.wait(SAMPLE_S):
            rss = _rss_mib(self._page)
            if rss is not None and (self._sampled is None or rss > self._sampled):
                self._sampled = rss

    def finish(self) -> PeakMemory | None:
        """The stage's peak (module doc); None where the platform reports nothing."""
        if self._thread is not None:
            self._stop.set()
            self._thread.join()
            self._thread = None
            rss = _rss_mib(self._page)
            if rss is not None and self._sampled is not None:
                self._sampled = max(self._sampled, rss)
        peak = _maxrss_mib()
        if peak is not None and self._start_peak is not None and peak > self._start_peak:
            return PeakMemory(peak, "exact")  # the process's peak rose during this stage
        if self._sampled is not None:
            return PeakMemory(self._sampled, "sampled")
        return None if peak is None else PeakMemory(peak, "bound")


def _malloc_trim() -> bool:
    """glibc's ``malloc_trim(0)``: give the free memory of every arena back to the system.
    False where the C library has none (macOS, Windows, musl)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        trim = libc.malloc_trim
    except (OSError, AttributeError):
        return False
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    trim(0)
    return True


def release_freed_memory() -> None:
    """Collect reference cycles, then return the freed heap to the system (module doc).
    On the quickstart the fuse stage left the process near its peak once it returned; the
    stages after it started from there."""
    gc.collect()
    _malloc_trim()

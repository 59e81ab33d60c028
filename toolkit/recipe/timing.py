"""Work timing shared by the pipeline stages, so runtime tables compare like with like.

Each stage that does per-frame work (slam2d, depth, fuse, tsdf, camera_only, ...) reports
``work_seconds`` (wall clock), ``work_cpu_seconds`` (CPU time of the whole process, all
threads) and ``work_frames`` for its processing alone: reading inputs it would get from a
live robot, writing reports and scoring against ground truth are left out. The benchmark
tables add these up per configuration: frames/s = frames / sum(work_seconds), CPU load =
sum(work_cpu_seconds) / sum(work_seconds) as % of one core (the paper's Table II).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field


@dataclass
class WorkTimer:
    """Accumulates wall and process CPU time over any number of ``with timer:`` blocks."""

    seconds: float = 0.0
    cpu_seconds: float = 0.0
    _t0: float = field(default=0.0, repr=False)
    _c0: float = field(default=0.0, repr=False)

    def __enter__(self) -> WorkTimer:
        self._t0, self._c0 = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc: object) -> None:
        self.seconds += time.perf_counter() - self._t0
        self.cpu_seconds += time.process_time() - self._c0

    def add(self, seconds: float, cpu_seconds: float) -> None:
        """Add time measured elsewhere (e.g. by a library that times itself)."""
        self.seconds += float(seconds)
        self.cpu_seconds += float(cpu_seconds)

    def metrics(self, frames: int) -> dict[str, float | int | None]:
        """The standard ``work_*`` keys for ``metrics.json`` (``work_metrics``)."""
        return work_metrics(self.seconds, self.cpu_seconds, frames)


def usable_cpus() -> int:
    """CPU cores this process may run on: its affinity mask (what taskset or a container's
    cpuset leaves it), else the machine's count."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # no affinity call on macOS / Windows
        return os.cpu_count() or 1


def work_metrics(seconds: float, cpu_seconds: float, frames: int
                 ) -> dict[str, float | int | None]:
    """``work_seconds``, ``work_cpu_seconds``, ``work_frames``, ``work_fps``,
    ``work_cpu_load_pct`` (100 = one core busy) and ``work_cpu_cores`` (``usable_cpus``:
    a cached stage may have run on another machine, so each records its own). The rate and
    the load are None when ``seconds`` is 0."""
    return {
        "work_seconds": round(float(seconds), 4),
        "work_cpu_seconds": round(float(cpu_seconds), 4),
        "work_frames": int(frames),
        "work_fps": float(frames / seconds) if seconds > 0 else None,
        "work_cpu_load_pct": float(100.0 * cpu_seconds / seconds) if seconds > 0 else None,
        "work_cpu_cores": usable_cpus(),
    }

"""Peak resident memory of one stage, for the run's timing table.

Stages run one after another in the runner's process, so the process's peak (``VmHWM``,
``ru_maxrss``) after the second stage is the larger of the two. On Linux the peak is reset
when a stage starts (writing ``5`` to ``/proc/self/clear_refs``, Linux 4.0+), so each
stage's figure is its own. Where that cannot be done (another OS, a kernel without it)
the figure is the process's peak since it started: an upper bound, marked ``exact=False``.
Memory of child processes (a compiler building an extension) is not counted.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

try:
    import resource
except ImportError:  # Windows
    resource = None  # type: ignore[assignment]

_STATUS = Path("/proc/self/status")
_CLEAR_REFS = Path("/proc/self/clear_refs")


@dataclass(frozen=True)
class PeakMemory:
    """A stage's peak resident memory in MiB (2^20 bytes); ``exact`` False: the process's
    peak since it started, which may belong to an earlier stage."""

    mib: float
    exact: bool


def _hwm_mib() -> float | None:
    try:
        for line in _STATUS.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0  # kB
    except (OSError, ValueError, IndexError):
        return None
    return None


def _maxrss_mib() -> float | None:
    if resource is None:
        return None
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    # Bytes on macOS, KiB elsewhere (getrusage(2)).
    return peak / 2**20 if sys.platform == "darwin" else peak / 1024.0


def _reset_peak() -> bool:
    try:
        _CLEAR_REFS.write_text("5")
    except OSError:
        return False
    return True


class StagePeak:
    """Started when a stage starts; ``finish()`` gives its peak."""

    def __init__(self) -> None:
        self._exact = _reset_peak() and _hwm_mib() is not None

    def finish(self) -> PeakMemory | None:
        """The peak since ``__init__`` (or since the process started, ``exact=False``);
        None where the platform reports neither."""
        if self._exact:
            mib = _hwm_mib()
            if mib is not None:
                return PeakMemory(mib, True)
        mib = _maxrss_mib()
        return None if mib is None else PeakMemory(mib, False)

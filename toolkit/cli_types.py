"""argparse value types and signal handling shared by the command-line tools."""

from __future__ import annotations

import argparse
import signal
from types import FrameType
from typing import Any

INTERRUPTED = 130  # the exit status of a run stopped by Ctrl-C or SIGTERM (128 + SIGINT)


def positive_int(text: str) -> int:
    """An integer of at least 1 (frame counts, strides, repeats)."""
    v = int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {v}")
    return v


def positive_float(text: str) -> float:
    """A number above 0 (durations, sizes)."""
    v = float(text)
    if not v > 0:
        raise argparse.ArgumentTypeError(f"must be above 0, got {v}")
    return v


def sigterm_as_interrupt() -> signal.Handlers | Any | None:
    """Make SIGTERM end the command like Ctrl-C; returns the handler it replaced (None
    where signals cannot be set: not the main thread)."""

    # `kill` or a scheduler's preemption then unwinds as Ctrl-C does: an atomic write in
    # flight removes its temporary, and the command says what it had finished.
    def handler(signum: int, frame: FrameType | None) -> None:
        raise KeyboardInterrupt

    try:
        return signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread (embedded use): leave signals alone
        return None

"""argparse value types shared by the command-line tools."""

from __future__ import annotations

import argparse


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

"""Property tests, round 6: the calibration board's pose from its corners and its line in
the scan, the CPU splat rasterisers' invariances, the held-out split and the Freiburg
relations metric, which rounds 1-5 did not reach. Known answers come from construction."""

from __future__ import annotations

import math

import pytest

from calibration.board import BoardError, BoardSpec


@pytest.mark.parametrize("size", [(math.nan, 0.5), (0.6, math.nan), (math.inf, 0.5)])
def test_board_size_must_be_finite(size: tuple[float, float]) -> None:
    """A NaN side passed the "smaller than its pattern" check (NaN compares False), and
    every scan segment was then "wrong length"; an infinite one made the outline
    residuals of the joint refinement NaN. Both are refused, naming the option."""
    with pytest.raises(BoardError, match="--board-size"):
        BoardSpec(5, 4, 0.05, size)
    with pytest.raises(BoardError, match="--square"):
        BoardSpec(5, 4, math.inf)

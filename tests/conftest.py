"""Shared test helpers: where the shared real data lives."""

import os
from pathlib import Path

import pytest

# Spinning OpenMP waits make torch crawl when the test machine's cores are busy.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def shared_data_dir() -> Path:
    env = os.environ.get("TOOLKIT_SHARED_DATA")
    return Path(env) if env else Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture
def shared_data() -> Path:
    d = shared_data_dir()
    if not d.is_dir():
        pytest.skip(f"shared real data not found at {d} (set TOOLKIT_SHARED_DATA)")
    return d

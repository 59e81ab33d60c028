"""Shared test helpers: where the shared real data lives, one torch thread, the C++
rasteriser."""

import os
import shutil
from collections.abc import Iterator
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


@pytest.fixture
def one_thread() -> Iterator[None]:
    """Tiny images: threads only add OpenMP barriers (and on a busy CI box, long waits).
    Used by the splat test files through ``pytestmark``."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def cpp() -> None:
    """Skip where the C++ rasteriser cannot be built."""
    from toolkit.splat.rasterize import cpp_ext

    if shutil.which("c++") is None:
        pytest.skip("no C++ compiler on PATH: the fast rasteriser cannot be built")
    if cpp_ext.load_extension() is None:
        pytest.skip(f"C++ rasteriser build failed: {cpp_ext.extension_error()}")

"""The measuring scripts in benchmarks/ run and print what the docs read from them."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _run(*args: str) -> dict:
    done = subprocess.run([sys.executable, *args], cwd=REPO, capture_output=True, text=True,
                          timeout=300, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_map_figure_memory_draws_the_walls(tmp_path: Path) -> None:
    out = _run("benchmarks/map_figure_memory.py", "600", str(tmp_path / "map.png"))
    assert out["cells"] == 600 and out["black_pixels"] > 0
    assert out["peak_gib"] >= out["grid_rss_gib"] > 0
    assert (tmp_path / "map.png").stat().st_size > 0


def test_runner_digest_cost_hashes_every_file_once_after_a_copy(tmp_path: Path) -> None:
    out = _run("benchmarks/runner_digest_cost.py", "250", "--work", str(tmp_path))
    assert out["first_check_files_hashed"] == 250  # new mtimes: every file read once
    assert out["next_check_files_hashed"] == 0  # their mtimes stored: nothing read
    assert out["marker_bytes"] > 250 * 64  # a SHA-256 hex digest per file


def test_checkpoint_cost_saves_and_loads_the_state(tmp_path: Path) -> None:
    out = _run("benchmarks/checkpoint_cost.py", "1", "--repeats", "2", "--work", str(tmp_path))
    assert out["mib"] == 1 and out["file_bytes"] > 2**20  # the array and the header
    assert len(out["save_s"]) == len(out["load_s"]) == 2


def test_checkpoint_cost_saves_and_loads_a_splat_trainer(tmp_path: Path) -> None:
    out = _run("benchmarks/checkpoint_cost.py", "2", "--kind", "splat", "--repeats", "1",
               "--work", str(tmp_path))
    assert out["kind"] == "splat" and out["file_bytes"] > 2 * 2**20 * 0.9
    assert len(out["load_cpu_s"]) == 1 and out["peak_rss_mib"] >= out["peak_rss_before_load_mib"]

"""``python -m toolkit.recipe doctor``: each check says what works and how to fix what not."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from importlib import metadata
from pathlib import Path

import pytest
import torch

from toolkit.recipe import cli, doctor

REPO = Path(__file__).resolve().parents[1]


def _by_part(checks: list[doctor.Check]) -> dict[str, doctor.Check]:
    return {c.part: c for c in checks}


def test_this_installation_has_every_required_part(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["doctor", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["ok"] is True
    parts = {c["part"]: c for c in out["checks"]}
    assert parts["torch"]["detail"] == torch.__version__
    assert parts["numpy"]["status"] == "ok"
    expected = "CUDA" if torch.cuda.is_available() else "CPU only"
    assert parts["torch device"]["detail"].startswith(expected)
    assert "CPUExecutionProvider" in parts["depth network (onnxruntime)"]["detail"]


def test_a_missing_required_package_fails_with_the_install_command(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setattr(doctor, "PACKAGES", (*doctor.PACKAGES,
                                             ("no_such_module_xyz", "no-such-dist", True)))
    assert cli.main(["doctor"]) == 1
    out = capsys.readouterr().out
    assert "missing: no_such_module_xyz" in out
    check = _by_part(doctor.collect())["no_such_module_xyz"]
    assert check.status == "missing" and "ModuleNotFoundError" in check.detail
    assert "pip install 'no-such-dist'" in check.fix


def test_without_a_compiler_the_cpu_rasteriser_is_a_note_with_the_fix(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("TOOLKIT_NO_CPP_EXT", raising=False)
    monkeypatch.setenv("CXX", "no-such-compiler-xyz")
    check = doctor.check_cpp_rasteriser()
    assert check.status == "note" and "no C++ compiler" in check.detail
    assert "g++" in check.fix


def test_an_unbuilt_rasteriser_is_reported_not_built(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.delenv("TOOLKIT_NO_CPP_EXT", raising=False)
    monkeypatch.delenv("CXX", raising=False)
    monkeypatch.setenv("TOOLKIT_EXT_CACHE", str(tmp_path))
    check = doctor.check_cpp_rasteriser()
    if check.detail.startswith("no C++ compiler"):
        pytest.skip("no C++ compiler on this machine")
    assert check.status == "note" and "not built yet" in check.detail
    assert str(tmp_path) in check.detail and "--build" in check.fix
    assert list(tmp_path.iterdir()) == []  # nothing compiled without --build
    monkeypatch.setenv("TOOLKIT_NO_CPP_EXT", "1")
    assert "disabled" in doctor.check_cpp_rasteriser().detail


def test_the_table_shows_fixes_with_brackets_as_written() -> None:
    # rich reads "[cuda]" as markup unless escaped: the gsplat fix lost its extra's name.
    done = subprocess.run([sys.executable, "-m", "toolkit.recipe", "doctor"], cwd=REPO,
                          capture_output=True, text=True, timeout=120,
                          env={**os.environ, "COLUMNS": "200"})
    assert done.returncode == 0, done.stderr
    try:
        metadata.version("gsplat")
    except metadata.PackageNotFoundError:
        assert "pip install -e '.[cuda]'" in done.stdout
    assert "every required part works" in done.stdout

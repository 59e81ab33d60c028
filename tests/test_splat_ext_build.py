"""The C++ rasteriser's build folder after a build was killed (``cpp_ext._build_lock``).

torch's ``cpp_extension.load`` takes a build folder by creating a ``lock`` file in it and
deletes the file when done; a process killed in between (SIGKILL during a first build, a
``timeout``) left the file, and every later load waited for it to go: the next splat stage
hung for good, without a word.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
import torch.utils.cpp_extension
from torch.utils.file_baton import FileBaton

from toolkit.splat.rasterize import cpp_ext

_BUILT = ModuleType("built")  # what the stand-in for torch's load returns
TORCH_LOCK = "lock"  # the file torch's load takes its build folder with (FileBaton)


# Without flock (Windows) torch's file lock alone guards the folder, as before.
_FLOCK = pytest.mark.skipif(sys.platform == "win32", reason="no flock on Windows")


def _fresh_loader(monkeypatch: pytest.MonkeyPatch, cache: Path,
                  wait_s: float) -> tuple[list[str], Path]:
    """``load_extension`` as in a new process, building in ``cache``, with torch's load
    standing in: it takes torch's file lock as ``load`` does, but gives up after
    ``wait_s`` (torch waits for good). Returns the log of what the stand-in did and the
    build folder (made)."""
    monkeypatch.setenv(cpp_ext.ENV_CACHE, str(cache))
    monkeypatch.delenv(cpp_ext.ENV_DISABLE, raising=False)
    monkeypatch.setenv("CXX", sys.executable)  # any program on PATH: no compiler runs
    monkeypatch.setattr(cpp_ext, "_state", {"tried": False, "module": None, "error": None})
    done: list[str] = []

    def load(name: str, build_directory: str, **_: Any) -> ModuleType:
        baton = FileBaton(os.path.join(build_directory, TORCH_LOCK))
        t0 = time.monotonic()
        while not baton.try_acquire():
            if time.monotonic() - t0 > wait_s:
                done.append("waited")
                raise TimeoutError(f"{baton.lock_file_path} held for {wait_s} s")
            time.sleep(0.05)
        done.append("built")
        baton.release()
        return _BUILT

    monkeypatch.setattr(torch.utils.cpp_extension, "load", load)
    build_dir = cache / cpp_ext.build_name()
    build_dir.mkdir()
    return done, build_dir


@_FLOCK
def test_a_lock_left_by_a_killed_build_does_not_stop_the_next(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    done, build_dir = _fresh_loader(monkeypatch, tmp_path, wait_s=3.0)
    (build_dir / TORCH_LOCK).touch()  # what the killed build left
    assert cpp_ext.load_extension() is _BUILT, cpp_ext.extension_error()
    assert done == ["built"]
    assert not (build_dir / TORCH_LOCK).exists()


@_FLOCK
def test_a_build_in_progress_in_another_process_is_waited_for(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """A live build's lock is not taken for a stale one: the second process waits."""
    done, build_dir = _fresh_loader(monkeypatch, tmp_path, wait_s=60.0)
    baton = build_dir / TORCH_LOCK
    # The other process builds as load_extension does: our flock, then torch's lock file,
    # both let go when it is done; it says whether torch's was still its own at the end.
    builder = subprocess.Popen([sys.executable, "-c", f"""
import fcntl, os, sys, time
h = open({str(build_dir / getattr(cpp_ext, "BUILD_LOCK", ".unused"))!r}, "a")
fcntl.flock(h.fileno(), fcntl.LOCK_EX)
fd = os.open({str(baton)!r}, os.O_CREAT | os.O_EXCL)
print("building", flush=True)
time.sleep(1.5)
print("kept" if os.path.exists({str(baton)!r}) else "lost", flush=True)
os.close(fd)
os.remove({str(baton)!r})
"""], stdout=subprocess.PIPE, text=True)
    assert builder.stdout is not None
    assert builder.stdout.readline().strip() == "building"
    assert cpp_ext.load_extension() is _BUILT, cpp_ext.extension_error()
    assert builder.stdout.read().strip() == "kept"
    assert builder.wait() == 0 and done == ["built"]


@pytest.mark.slow  # two real builds of the extension: a minute or more each
@_FLOCK
def test_a_build_killed_midway_is_built_again_by_the_next_process(tmp_path: Path) -> None:
    """SIGKILL while g++ runs, then a new process loads the extension: it builds it (it
    waited for the killed one's lock for good before)."""
    import shutil

    if shutil.which(os.environ.get("CXX", "c++")) is None:
        pytest.skip("no C++ compiler on PATH")
    env = {**os.environ, cpp_ext.ENV_CACHE: str(tmp_path)}
    env.pop(cpp_ext.ENV_DISABLE, None)
    code = ("from toolkit.splat.rasterize import cpp_ext; m = cpp_ext.load_extension(); "
            "print('loaded' if m is not None else cpp_ext.extension_error())")
    # Its own process group, all killed: a compiler left running would build beside the
    # next process (as after a kill of the process alone) and only slow this test down.
    first = subprocess.Popen([sys.executable, "-c", code], env=env, start_new_session=True)
    baton = tmp_path / cpp_ext.build_name() / TORCH_LOCK
    t0 = time.monotonic()
    while not baton.exists() and first.poll() is None and time.monotonic() - t0 < 300:
        time.sleep(0.05)
    time.sleep(1.0)  # into the compiler's run
    assert first.poll() is None, "the first build ended before it could be killed"
    os.killpg(first.pid, signal.SIGKILL)
    first.wait()
    assert baton.exists()  # torch's lock, left behind
    second = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                            text=True, timeout=900)
    assert second.stdout.strip() == "loaded", second.stdout + second.stderr
    assert not baton.exists()

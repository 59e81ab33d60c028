"""Writes that fail (a full disk, a folder without write permission) in a recipe's stages.

A full disk was simulated here by ``os.statvfs`` reporting no free block and a writer that
behaves as the libraries do on one: cv2.imwrite and Open3D's writers return success
having left an empty or cut-off file (seen on a full tmpfs, 2026-11-28), and np.save
raises an OSError that names neither file nor cause ("19200 requested and 11232 written").
"""

from __future__ import annotations

import errno
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from toolkit.io.atomic import atomic_path, atomic_write_bytes, atomic_write_text
from toolkit.recipe import Stage, StageConfig, StageContext, registry
from toolkit.recipe.cli import main as cli_main

_DISK = {"full": False}  # the simulated disk: full or not
_REAL_STATVFS = os.statvfs


def _statvfs(path: Any) -> os.statvfs_result:
    st = _REAL_STATVFS(path)
    if not _DISK["full"]:
        return st
    # [bsize, frsize, blocks, bfree, bavail, files, ffree, favail, flag, namemax]
    return os.statvfs_result((st.f_bsize, st.f_frsize, st.f_blocks, 0, 0, st.f_files,
                              st.f_ffree, st.f_favail, st.f_flag, st.f_namemax))


@pytest.fixture
def disk(monkeypatch: pytest.MonkeyPatch) -> Iterator[dict[str, bool]]:
    """The simulated disk, not full to begin with."""
    monkeypatch.setattr(os, "statvfs", _statvfs)
    _DISK["full"] = False
    yield _DISK
    _DISK["full"] = False


def _write_like_a_library(tmp: Path, data: bytes) -> None:
    """What cv2.imwrite does: on a full disk an empty file, and success reported."""
    tmp.write_bytes(b"" if _DISK["full"] else data)


# --- the atomic writer ------------------------------------------------------------------


def test_a_file_a_library_cut_short_on_a_full_disk_replaces_nothing(
        tmp_path: Path, disk: dict[str, bool]) -> None:
    """cv2.imwrite and Open3D's writers said they had written a file they had cut short
    (a 0-byte PNG, a PLY ending mid-face), and it was moved into place as the output."""
    target = tmp_path / "000003.png"
    atomic_write_bytes(target, b"the frame a resumed run kept")
    disk["full"] = True
    with pytest.raises(OSError) as info, atomic_path(target) as tmp:
        _write_like_a_library(tmp, b"a new frame")
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(target)
    assert target.read_bytes() == b"the frame a resumed run kept"
    assert [p.name for p in tmp_path.iterdir()] == ["000003.png"]  # no temporary left
    disk["full"] = False
    with atomic_path(target) as tmp:
        _write_like_a_library(tmp, b"a new frame")
    assert target.read_bytes() == b"a new frame"


@pytest.mark.parametrize("full", [True, False])
def test_a_short_write_that_names_no_file_is_named(
        tmp_path: Path, disk: dict[str, bool], full: bool) -> None:
    """np.save on a full disk raised "OSError: 19200 requested and 11232 written": no
    errno, no file; the stage failed with that line alone."""
    target = tmp_path / "depth" / "000007.npy"
    disk["full"] = full
    with pytest.raises(OSError) as info, atomic_path(target) as tmp:
        tmp.write_bytes(b"\x93NUMPY")
        raise OSError("19200 requested and 11232 written")  # numpy's words
    assert info.value.filename == str(target)
    assert "19200 requested and 11232 written" in str(info.value)
    assert info.value.errno == (errno.ENOSPC if full else errno.EIO)
    assert list(target.parent.iterdir()) == []


def test_a_writer_that_fails_its_own_way_on_a_full_disk_is_named(
        tmp_path: Path, disk: dict[str, bool]) -> None:
    """torch.save (a splat checkpoint) on a full tmpfs: "RuntimeError: [enforce fail at
    inline_container.cc:672] . unexpected pos 2244224 vs 2244176", with a traceback and
    neither file nor cause; the same error on a disk with space is left as it is."""
    target = tmp_path / "checkpoints" / "checkpoint.pt"
    words = "[enforce fail at inline_container.cc:672] . unexpected pos 2244224 vs 2244176"
    disk["full"] = True
    with pytest.raises(OSError) as info, atomic_path(target) as tmp:
        tmp.write_bytes(b"PK")
        raise RuntimeError(words)
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(target)
    assert words in str(info.value) and list(target.parent.iterdir()) == []
    disk["full"] = False
    with pytest.raises(RuntimeError, match="unexpected pos"), atomic_path(target) as tmp:
        raise RuntimeError(words)


# --- a stage on a full disk -----------------------------------------------------------


class FramesConfig(StageConfig):
    frames: int = 6


class Frames(Stage):
    """Write one file per frame, keeping the frames an earlier run wrote (test stage)."""

    name = "t_frames"
    Config = FramesConfig
    provides = ("frames",)
    # What goes wrong, set by a test (not settings: a rerun has the same key).
    full_at: int | None = None  # the disk fills as this frame is written
    denied_at: int | None = None  # the folder is not writable then
    written: list[int] = []  # noqa: RUF012 - frames written by run(), all runs

    def run(self, ctx: StageContext) -> None:
        cfg: Any = self.config
        out = ctx.stage_dir / "frames"
        for i in range(cfg.frames):
            path = out / f"{i:06d}.png"
            if path.exists():  # resumed: written by an earlier run
                continue
            if i == Frames.full_at:
                _DISK["full"] = True
            if i == Frames.denied_at:
                # What open() raises for the temporary in a folder without write permission.
                raise PermissionError(errno.EACCES, "Permission denied",
                                      str(out / f".{i:06d}.123.0a0b0c0d.tmp.png"))
            with atomic_path(path) as tmp:
                _write_like_a_library(tmp, f"frame {i}".encode())
            Frames.written.append(i)
        atomic_write_text(ctx.stage_dir / "count.txt", str(cfg.frames))
        ctx.provide("frames", out)


class Before(Stage):
    """A stage before it, finished before the disk fills (test stage)."""

    name = "t_before"
    Config = StageConfig
    provides = ("number",)

    def run(self, ctx: StageContext) -> None:
        atomic_write_text(ctx.stage_dir / "n.txt", "1")
        ctx.provide("number", ctx.stage_dir / "n.txt")


@pytest.fixture
def stages() -> Iterator[None]:
    registry.register("t_frames", Frames)
    registry.register("t_before", Before)
    Frames.written, Frames.full_at, Frames.denied_at = [], None, None
    yield
    registry.unregister("t_frames")
    registry.unregister("t_before")


def _recipe(tmp_path: Path) -> Path:
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump({"name": "t", "output": str(tmp_path / "run"), "stages": [
        {"stage": "t_before"}, {"stage": "t_frames"}]}))
    return path


def _files(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file() and p.name != ".stage.json"}


def test_a_full_disk_fails_the_stage_naming_the_file_and_the_fix_and_a_rerun_resumes(
        tmp_path: Path, disk: dict[str, bool], stages: None,
        capsys: pytest.CaptureFixture[str]) -> None:
    """The stage wrote an empty frame 3 reported as written and finished, its output cut
    short; now it fails there, says which file and to free space, keeps frames 0-2 and
    the stage before it, and a run after the space is freed writes frames 3-5 only."""
    Frames.full_at = 3
    assert cli_main(["run", str(_recipe(tmp_path))]) == 1
    out = capsys.readouterr()
    frames = tmp_path / "run" / "t_frames" / "frames"
    assert (f"stage 't_frames' failed: cannot write {frames / '000003.png'} (No space left on "
            "device): free space on its disk, then run again") in out.out
    # The run's own files did not fit either: said as before, the finished stages kept.
    assert "metrics.json (No space left on device): free space on its disk" in out.err
    assert sorted(p.name for p in frames.iterdir()) == [f"{i:06d}.png" for i in range(3)]
    assert (tmp_path / "run" / "t_before" / ".stage.json").exists()
    assert Frames.written == [0, 1, 2]
    disk["full"], Frames.full_at = False, None  # space freed
    assert cli_main(["run", str(_recipe(tmp_path))]) == 0
    assert Frames.written == [0, 1, 2, 3, 4, 5]
    assert "t_before cached" in capsys.readouterr().out
    # The same files as a run the disk never stopped, and no temporaries.
    whole = tmp_path / "whole"
    whole.mkdir()
    assert cli_main(["run", str(_recipe(whole))]) == 0
    assert _files(tmp_path / "run" / "t_frames") == _files(whole / "run" / "t_frames")


def test_a_folder_without_write_permission_is_named_with_the_fix(
        tmp_path: Path, disk: dict[str, bool], stages: None,
        capsys: pytest.CaptureFixture[str]) -> None:
    """(chmod a-w on the stage's folder, as a user without root's override.) The message
    named the hidden temporary ("[Errno 13] Permission denied: '.../.000002.123...'")."""
    Frames.denied_at = 2
    assert cli_main(["run", str(_recipe(tmp_path))]) == 1
    frames = tmp_path / "run" / "t_frames" / "frames"
    assert (f"stage 't_frames' failed: cannot write {frames / '000002.png'} (Permission "
            f"denied): make {frames} writable, then run again") in capsys.readouterr().out
    Frames.denied_at = None
    assert cli_main(["run", str(_recipe(tmp_path))]) == 0
    assert Frames.written == [0, 1, 2, 3, 4, 5]

"""Atomic file writes: a reader (or a resumed run) sees the old file or the new one, never half.

Every writer goes to a temporary name in the target's own directory and is moved into
place with ``os.replace``, which is atomic on POSIX and Windows as long as source and
target share a filesystem - hence the same directory, never ``/tmp``.
"""

from __future__ import annotations

import contextlib
import errno
import glob
import hashlib
import json
import math
import os
import re
import secrets
import shutil
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

__all__ = [
    "FileTail",
    "HashingWriter",
    "atomic_path",
    "atomic_write_bytes",
    "atomic_write_json",
    "atomic_write_text",
    "digest_problem",
    "digested_write",
    "disk_full",
    "remove_leftover_temps",
    "remove_stale_temps",
    "target_of",
    "to_jsonable",
    "write_failure",
]


def _temp_name(path: Path) -> Path:
    # Hidden (leading dot) so globs such as "*.png" in the same folder skip a leftover from a
    # killed process; the real suffix stays last so writers that pick the format from the
    # extension (cv2.imwrite, np.save, open3d) still do the right thing.
    token = f"{os.getpid()}.{secrets.token_hex(4)}"
    return path.with_name(f".{path.stem}.{token}.tmp{path.suffix}")


def remove_leftover_temps(path: str | os.PathLike[str]) -> None:
    """Delete the temporary files that writes to ``path`` by killed processes left behind
    (call it where no other process can be writing ``path``)."""
    for tmp, _ in _temps_of(Path(path)):
        tmp.unlink(missing_ok=True)


# _temp_name's pattern: ".<stem>.<pid>.<8 hex>.tmp<suffix>".
_TEMP_NAME = re.compile(r"\.(?P<stem>.+)\.(?P<pid>\d+)\.[0-9a-f]{8}\.tmp(?P<suffix>\.[^.]*)?")
# A temporary this old is stale even where a process of its writer's id runs: that id was
# reused (one atomic write takes seconds, not a day).
STALE_TEMP_AGE_S = 24 * 3600.0


def _process_runs(pid: int) -> bool:
    """Whether a process of id ``pid`` runs on this machine (assumed so off POSIX, where
    signal 0 is no mere probe)."""
    if os.name != "posix":
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    except (OverflowError, ValueError):  # no process id at all
        return False
    return True


def remove_stale_temps(path: str | os.PathLike[str],
                       max_age_s: float = STALE_TEMP_AGE_S) -> list[Path]:
    """Delete the temporaries that killed writes of ``path`` left beside it (SIGKILL, a
    power cut: no handler ran), for writers outside run folders, where the runner's
    cleanup never comes; returns those deleted. Only provably stale ones of this very
    output go: its name pattern (``.<stem>.<pid>.<hex>.tmp<suffix>``, not another file's
    such as rig.unreliable.yaml's beside rig.yaml) and a writer whose process id runs no
    process here, or older than ``max_age_s`` (the id reused). A temporary of a running
    writer, this process's included, stays: it may be mid-write. A writer of the same
    file in another PID namespace (a container) sharing the folder is not seen: its write
    may fail, as two writers of one file would race anyway."""
    now = time.time()
    removed = []
    for tmp, m in _temps_of(Path(path)):
        try:
            age = now - tmp.lstat().st_mtime
        except FileNotFoundError:  # its writer finished meanwhile
            continue
        if age < max_age_s and _process_runs(int(m["pid"])):
            continue
        remove_path(tmp, ignore_errors=True)
        removed.append(tmp)
    return removed


def _temps_of(target: Path) -> Iterator[tuple[Path, re.Match[str]]]:
    """The temporaries of atomic writes of ``target`` beside it, with their name's match:
    only this file's (a glob without escaping read '[' and '*' in the name as patterns,
    and ".rig.*.tmp.yaml" also takes rig.unreliable.yaml's temporaries)."""
    pattern = f".{glob.escape(target.stem)}.*.tmp{glob.escape(target.suffix)}"
    for tmp in target.parent.glob(pattern):
        m = _TEMP_NAME.fullmatch(tmp.name)
        if m is not None and target_of(tmp) == target:
            yield tmp, m


def remove_temps_under(folder: str | os.PathLike[str]) -> int:
    """Delete every temporary file of a killed atomic write anywhere under ``folder`` (call
    it where no other process writes there: a stage's folder once the stage is done);
    returns how many went."""
    n = 0
    for p in Path(folder).rglob(".*"):
        if p.is_file() and _TEMP_NAME.fullmatch(p.name):
            p.unlink(missing_ok=True)
            n += 1
    return n


def target_of(path: str | os.PathLike[str]) -> Path:
    """The file an atomic write's temporary ``path`` was for (``path`` itself when it is
    no such temporary): an error about the temporary is about that file."""
    p = Path(path)
    m = _TEMP_NAME.fullmatch(p.name)
    return p.with_name(m["stem"] + (m["suffix"] or "")) if m else p


def write_failure(exc: OSError) -> str:
    """``cannot write <file> (<why>)[: <fix>]`` for ``exc``, an error writing a file that it
    names: the file meant (not the hidden temporary of its atomic write) and, for a full
    disk, a permission or a read-only filesystem, what to do."""
    target = target_of(exc.filename)
    why = str(exc.strerror or exc)
    # atomic_path's own words name the file once already
    why = why.replace(f" (writing {target})", "")
    if exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        fix = f"make {target.parent} writable, then run again"
    elif exc.errno in (errno.ENOSPC, errno.EDQUOT):
        fix = "free space on its disk, then run again"
    elif exc.errno == errno.EISDIR and "folder" not in why:
        fix = "a folder is in its place: move or delete it, then run again"
    else:  # the atomic writer's own words already say what to do (a folder in the way)
        return f"cannot write {target} ({why})"
    return f"cannot write {target} ({why}): {fix}"


@contextmanager
def atomic_path(path: str | os.PathLike[str], *, clean_stale: bool = False) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success move it onto ``path``.

    The temporary file does not exist yet; the caller's writer creates it. If the block
    raises, the temporary file (or folder) is removed and ``path`` is left untouched. If
    the block ends without having written anything (``cv2.imwrite`` returns False instead
    of raising), ``FileNotFoundError`` is raised rather than silently keeping no file.
    ``clean_stale``: first delete what killed writes of ``path`` left
    (``remove_stale_temps``), for a writer outside run folders; it lists the folder, so
    not for writers of thousands of files into one.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    if clean_stale:
        remove_stale_temps(target)
    tmp = _temp_name(target)
    try:
        yield tmp
        if disk_full(target.parent):
            # cv2.imwrite and Open3D's writers report success on a full disk, having left
            # an empty or cut-off file (seen on a full tmpfs: a 0-byte PNG, a PLY cut
            # mid-face), and cv2 gives up without a word on a large image: moved into
            # place, such a file was a finished stage's output.
            raise OSError(errno.ENOSPC, f"{os.strerror(errno.ENOSPC)} (writing {target})",
                          str(target))
        if not tmp.exists():
            raise FileNotFoundError(f"nothing was written for {target} (temporary path {tmp})")
        os.replace(tmp, target)
    except OSError as e:
        # Before the temporary goes: it may hold what filled the disk.
        full = type(e) is OSError and e.errno is None and e.filename is None and disk_full(
            target.parent)
        remove_path(tmp, ignore_errors=True)
        if target.is_dir() and not target.is_symlink():
            # "[Errno 21] Is a directory" named the temporary beside it and no way out.
            raise IsADirectoryError(errno.EISDIR, f"a folder is where the file {target} is to "
                                    "be written: move or delete that folder, then run again",
                                    str(target)) from e
        if e.filename is None and e.errno is not None:
            # A failed write() names no file (a full disk: "[Errno 28] No space left on
            # device"): say which one, so the message is worth reading.
            raise OSError(e.errno, f"{e.strerror} (writing {target})", str(target)) from e
        if e.filename is None and type(e) is OSError:
            # numpy's short write names neither file nor cause ("19200 requested and 11232
            # written", np.save on a full disk).
            if full:
                raise OSError(errno.ENOSPC, f"{os.strerror(errno.ENOSPC)}: {e}",
                              str(target)) from e
            raise OSError(errno.EIO, f"only part of it was written: {e}", str(target)) from e
        raise
    except BaseException as e:
        full = isinstance(e, Exception) and disk_full(target.parent)
        remove_path(tmp, ignore_errors=True)
        if full:
            # torch.save on a full disk: "RuntimeError: [enforce fail at
            # inline_container.cc:672] . unexpected pos 2244224 vs 2244176", no file named.
            why = (str(e).strip().splitlines() or [""])[0]
            raise OSError(errno.ENOSPC, f"{os.strerror(errno.ENOSPC)}: {type(e).__name__}: "
                          f"{why}", str(target)) from e
        raise


def disk_full(folder: str | os.PathLike[str]) -> bool:
    """True when the filesystem holding ``folder`` has no block left to write to (for
    root, none of the blocks kept back for it either); False where that cannot be told
    (no ``statvfs``, or a filesystem that gives no sizes)."""
    try:
        st = os.statvfs(folder)
    except (AttributeError, OSError):  # Windows; a folder that went
        return False
    free = st.f_bfree if hasattr(os, "geteuid") and os.geteuid() == 0 else st.f_bavail
    return st.f_blocks > 0 and free == 0


class HashingWriter:
    """A file for ``pickle.dump`` or ``torch.save`` that hashes (SHA-256) what goes through
    it: a checkpoint's digest is computed as it streams to disk, never held twice in
    memory (``digested_write``)."""

    def __init__(self, fh: IO[bytes]) -> None:
        self.fh = fh
        self.sha = hashlib.sha256()

    def write(self, data: bytes | memoryview) -> int:
        self.sha.update(data)
        return self.fh.write(data)

    def flush(self) -> None:  # torch.save flushes its buffer at the end
        self.fh.flush()


_DIGEST_LEN = 64  # hex SHA-256, then a newline


@contextmanager
def digested_write(path: str | os.PathLike[str], magic: bytes) -> Iterator[HashingWriter]:
    """Write ``path`` atomically as the header line ``magic``, the SHA-256 of the rest, and
    the rest: what is written to the yielded file (``pickle.dump``, ``torch.save``), hashed
    as it streams out. ``digest_problem`` checks such a file before it is loaded (a pickle
    or a zip carries no check of its own: a byte changed on disk that still loads gave a
    wrong state to resume from)."""
    if not magic.endswith(b"\n"):
        raise ValueError("the header must be one line, ending in a newline")
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(magic)
        digest_at = fh.tell()
        fh.write(b"0" * _DIGEST_LEN + b"\n")  # filled in once the rest is out
        out = HashingWriter(fh)
        yield out
        fh.seek(digest_at)
        fh.write(out.sha.hexdigest().encode("ascii"))


def digest_problem(fh: IO[bytes], magic: bytes, older: tuple[bytes, str]) -> str | None:
    """None when ``fh`` (open at its start) is a file ``digested_write`` wrote with
    ``magic`` whose SHA-256 matches, and then ``fh`` stands where its contents begin
    (``FileTail(fh)``: them as a file of their own, for a loader that seeks); else
    what is wrong: ``older[1]`` for a file that starts as ``older[0]`` (the format before
    the digest), a missing header, or a damaged file. The file is read twice (digest, then
    its load): a state of gigabytes is not held as bytes beside the objects made of it."""
    head = fh.readline(len(magic))
    if head != magic:
        return older[1] if head.startswith(older[0]) else (
            "no header line: another kind of file, or its first line is damaged")
    stored = fh.readline(_DIGEST_LEN + 1).strip().decode("ascii", "replace")
    start = fh.tell()
    if hashlib.file_digest(fh, "sha256").hexdigest() != stored:
        return "damaged: its SHA-256 does not match what was written"
    fh.seek(start)
    return None


class FileTail:
    """The rest of the open file ``fh``, from where it stands, as a file of its own: its
    offsets count from there. For a loader that seeks in what it reads (``torch.load``'s
    zip reader) once ``digest_problem`` has read the header: it reads the file's contents
    as the file it was written as, not trusting in a reader that takes the position it is
    given as its start (torch 2.13's does; no documented guarantee). A file-like object
    with ``read``, ``readinto``, ``readline``, ``tell`` and ``seek``, which is what
    ``torch.load`` and ``pickle.load`` ask for.

    Not a buffer of the contents in memory: reading the file once into one, checked and
    loaded from there, made a 70 MB checkpoint's load slower, not faster (a fresh buffer
    of its size to fault in and copy out of; the second read comes from the page cache)
    and added its size to the peak memory (measured: docs/splatting.md, at FileTail)."""

    def __init__(self, fh: IO[bytes]) -> None:
        self._fh = fh
        self._start = fh.tell()

    def read(self, size: int = -1) -> bytes:
        return self._fh.read(size)

    def readinto(self, buffer: Any) -> int:
        return self._fh.readinto(buffer)  # type: ignore[attr-defined]

    def readline(self, size: int = -1) -> bytes:
        return self._fh.readline(size)

    def tell(self) -> int:
        return self._fh.tell() - self._start

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        if whence == os.SEEK_SET:
            if offset < 0:
                raise ValueError(f"negative seek position {offset}")
            offset += self._start
        return self._fh.seek(offset, whence) - self._start

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True


def remove_path(path: Path, ignore_errors: bool = False) -> None:
    """Delete a folder tree, or a file or link in its place, if it is there (a link is
    removed, never followed into)."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=ignore_errors)
    elif ignore_errors:
        with contextlib.suppress(OSError):
            path.unlink(missing_ok=True)
    else:
        path.unlink(missing_ok=True)


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes, *, fsync: bool = False,
                       clean_stale: bool = False) -> None:
    """Write ``data`` to ``path`` atomically.

    ``fsync=True`` also survives power loss, not just a killed process; it costs a disk
    flush per file, so it is left to callers writing commit markers rather than every frame.
    ``clean_stale``: as ``atomic_path``'s.
    """
    with atomic_path(path, clean_stale=clean_stale) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data)
            if fsync:
                fh.flush()
                os.fsync(fh.fileno())


def atomic_write_text(
    path: str | os.PathLike[str], text: str, *, encoding: str = "utf-8", fsync: bool = False,
    clean_stale: bool = False,
) -> None:
    """Write ``text`` to ``path`` atomically (UTF-8 by default, no newline translation)."""
    atomic_write_bytes(path, text.encode(encoding), fsync=fsync, clean_stale=clean_stale)


def to_jsonable(obj: Any) -> Any:
    """Plain JSON types from ``obj``: NaN and infinities become None (JSON has no such
    numbers and ``float('nan')`` as bare ``NaN`` breaks strict parsers), numpy scalars and
    arrays become numbers and lists, paths become strings, tuples and sets become lists."""
    if obj is None or isinstance(obj, bool | int | str):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, Mapping):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, set | frozenset):
        return [to_jsonable(v) for v in sorted(obj, key=repr)]
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    # numpy (and torch) scalars/arrays, recognised by duck typing so this module never
    # imports numpy.
    if hasattr(obj, "tolist"):
        return to_jsonable(obj.tolist())
    if hasattr(obj, "model_dump"):
        return to_jsonable(obj.model_dump(mode="json"))
    raise TypeError(f"cannot write {type(obj).__name__} as JSON: {obj!r}")


def atomic_write_json(path: str | os.PathLike[str], obj: Any, *, fsync: bool = False,
                      compact: bool = False, clean_stale: bool = False) -> None:
    """Write ``obj`` as indented JSON (key order kept, NaN/inf as null) atomically;
    ``compact``: on one line without spaces, for large files that machines read (a list
    item per line made the runner's marker of a 120,000-file output 19.4 MB, 13.4 MB
    compact: docs/runner.md); ``clean_stale``: as ``atomic_path``'s."""
    text = json.dumps(
        to_jsonable(obj), indent=None if compact else 2,
        separators=(",", ":") if compact else None, sort_keys=False, ensure_ascii=False,
        allow_nan=False,
    )
    atomic_write_text(path, text + "\n", fsync=fsync, clean_stale=clean_stale)

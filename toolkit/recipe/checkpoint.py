"""A stage's in-memory state saved now and then, so that a killed stage resumes mid-way.

The state (any picklable object: numpy arrays, dataclasses) is written atomically to one
file in the stage's folder together with the stage's cache key; a later run loads it only
under the same key, so changed settings or inputs start afresh. The file is the stage's own
intermediate output, read back only by the stage that wrote it (it is a pickle: do not
load checkpoints from elsewhere).

The file is a header line, the SHA-256 of the rest, and the pickle. A pickle carries no
check of its own: a byte changed on disk (a bad sector, a bit flipped in the page cache)
that still unpickles gave the stage a wrong state to go on from, whose error then stood in
its finished, cached outputs. A checkpoint whose digest does not match is set aside (a
warning; the stage starts afresh), as one of another version of the stage is. So is one
written before the digest (format 1, a bare pickle): loading it unchecked would keep the
risk, and starting afresh costs the interrupted stage's work once, on the first run after
the upgrade.
"""

from __future__ import annotations

import logging
import pickle
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from toolkit.io.atomic import digest_problem, digested_write, remove_leftover_temps

_FORMAT = 2
_MAGIC = b"lidarcam-recon checkpoint 2\n"
# A bare pickle (protocol 2 and up start with 0x80): the format before the digest.
_OLDER = (b"\x80", "written before checkpoints carried a checksum (an older toolkit)")


class Checkpoint:
    """Saves a stage's state to ``path`` at most every ``every_s`` seconds (0: never), and
    no more often than keeps saving to ``max_share`` of the time: a state that grows with
    the recording (an hour's voxel map) takes longer to write each time, and at a fixed
    interval saving would come to cost more than the work it protects."""

    def __init__(self, path: Path, key: str, every_s: float,
                 log: logging.Logger | None = None, max_share: float = 0.05) -> None:
        if not 0 < max_share <= 1:
            raise ValueError(f"max_share {max_share}: give a fraction in (0, 1]")
        self.path = Path(path)
        self.key = key
        self.every_s = float(every_s)
        self.max_share = float(max_share)
        self.log = log or logging.getLogger(__name__)
        self.saves = 0
        self.seconds = 0.0  # spent saving
        self.last_save_s = 0.0  # how long the last save took
        self._last = time.monotonic()

    def load(self, valid: Callable[[Any], bool] | None = None) -> Any | None:
        """The state saved under this key, or None (no file, another key, unreadable, or
        rejected by ``valid``: a state written by other code under the same settings)."""
        # A save killed half way leaves its temporary file, as big as the checkpoint.
        remove_leftover_temps(self.path)
        if not self.path.exists():
            return None
        try:
            with open(self.path, "rb") as fh:
                problem = digest_problem(fh, _MAGIC, _OLDER)
                if problem is not None:
                    self.log.warning("%s: %s; starting afresh", self.path, problem)
                    return None
                # pickle reads on from here and never seeks: no FileTail needed
                saved = pickle.load(fh)
        except Exception as e:  # written by another version of the code, or damaged
            self.log.warning("%s: cannot read the checkpoint (%s); starting afresh", self.path, e)
            return None
        if not isinstance(saved, dict) or saved.get("format") != _FORMAT or (
                saved.get("key") != self.key):
            self.log.info("%s: checkpoint of other settings or inputs; starting afresh",
                          self.path)
            return None
        if valid is not None and not valid(saved["state"]):
            self.log.warning("%s: checkpoint from another version of the stage; starting afresh",
                             self.path)
            return None
        self._last = time.monotonic()
        return saved["state"]

    @property
    def interval_s(self) -> float:
        """Seconds between saves: ``every_s``, or longer where the last save took more than
        ``max_share`` of that."""
        return max(self.every_s, self.last_save_s / self.max_share)

    def due(self) -> bool:
        """Whether ``interval_s`` has passed since the last save (or load, or creation)."""
        return self.every_s > 0 and time.monotonic() - self._last >= self.interval_s

    def save(self, state: Any) -> None:
        """Write ``state`` atomically (a kill during the write leaves the previous one)."""
        t0 = time.perf_counter()
        with digested_write(self.path, _MAGIC) as out:
            pickle.dump({"format": _FORMAT, "key": self.key, "state": state}, out,
                        protocol=pickle.HIGHEST_PROTOCOL)
        self.saves += 1
        self.last_save_s = time.perf_counter() - t0
        self.seconds += self.last_save_s
        self._last = time.monotonic()

    def remove(self) -> None:
        """Drop the checkpoint once the stage's outputs are complete."""
        self.path.unlink(missing_ok=True)
        remove_leftover_temps(self.path)

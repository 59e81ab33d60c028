"""The ``depth`` artifact on disk: one prediction per camera frame plus an index.

    <dir>/meta.json        kind, backend settings, image size, frame count
    <dir>/index.csv        index,stamp,file,latency_s[,true_scale]
    <dir>/frames/NNNNNN.npy  [H, W] float32 (float16 when asked), NaN invalid
    <dir>/index.csv's beyond_float16: a frame's pixels float16 could not hold (written NaN)
    <dir>/journal.jsonl    a key line, then a line per frame on disk (a killed run's
                           frames are kept by a writer with the same key); kept after
                           ``close``, since the stage is not finished until its runner
                           says so

``.npy`` and not 16-bit PNG: relative predictions have no unit, and disparity can be
tiny or negative, which the TUM depth PNG cannot hold.

float16 holds magnitudes up to 65504 and down to 2^-24 (6e-8), as ``write_depth``'s PNG
holds 13.107 m: beyond the top a value would become inf, which reads as a depth (an
infinite one) or a disparity of 0; it is written NaN (invalid) and counted, as the PNG
writes 0 and counts. A non-zero value below the bottom would become 0, which reads as no
depth (or a disparity at infinity); it is written as +-2^-24, off by less than that, as
the PNG writes a depth below its quantum as one quantum.
"""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path
from typing import Any

import numpy as np

from toolkit.depth.protocol import DEPTH_KINDS, DepthKind, DepthPrediction
from toolkit.errors import InputError, MissingInputError
from toolkit.io.atomic import atomic_path, atomic_write_json, atomic_write_text
from toolkit.io.depth import file_complete

JOURNAL = "journal.jsonl"
_F16_TINY = float(np.finfo(np.float16).smallest_subnormal)  # 2^-24


def to_float16(values: np.ndarray) -> tuple[np.ndarray, int]:
    """(values [H, W] as float16, pixels beyond float16's range written NaN): see the
    module's notes; NaN stays NaN, +-inf stays +-inf."""
    v = np.asarray(values, dtype=np.float32)
    with np.errstate(over="ignore"):
        h = v.astype(np.float16)  # [H, W]
    beyond = np.isinf(h) & np.isfinite(v)
    h[beyond] = np.nan
    flushed = (h == 0) & (v != 0)
    h[flushed] = np.copysign(np.float16(_F16_TINY), v[flushed])
    return h, int(beyond.sum())


class DepthStoreWriter:
    """Writes predictions frame by frame; ``close`` writes the index and meta last.

    With a ``resume_key`` every frame is journaled once its file is in place, and a later
    writer given the same key (the same settings and inputs) keeps the frames an
    interrupted one wrote: ``done`` lists them, ``resumed`` counts them. Without a key, or
    with another one, the folder starts empty.
    """

    def __init__(self, root: Path, kind: DepthKind, info: dict[str, Any] | None = None,
                 dtype: str = "float32", resume_key: str | None = None) -> None:
        if dtype not in ("float32", "float16"):
            raise ValueError("dtype must be float32 or float16")
        self.root = Path(root)
        (self.root / "frames").mkdir(parents=True, exist_ok=True)
        (self.root / "meta.json").unlink(missing_ok=True)
        self.kind = kind
        self.info = info or {}
        self.dtype = dtype
        self.shape: tuple[int, int] | None = None
        head = {"key": resume_key, "kind": kind, "dtype": dtype}
        self.rows: list[dict[str, str]] = self._journaled(head) if resume_key else []
        if self.rows:
            last = np.load(self.root / self.rows[-1]["file"], mmap_mode="r")
            self.shape = (int(last.shape[0]), int(last.shape[1]))
        listed = {r["file"] for r in self.rows}
        for f in (self.root / "frames").glob("*.npy"):
            if f"frames/{f.name}" not in listed:
                f.unlink()  # another run's, or written after the journal's last line
        self.resumed = len(self.rows)
        self._journal_path = self.root / JOURNAL
        # Rewritten atomically from the rows kept, which drops a torn last line.
        atomic_write_text(self._journal_path, "".join(
            json.dumps(r) + "\n" for r in [head, *self.rows]))
        self._journal = self._journal_path.open("a", encoding="utf-8")

    def _journaled(self, head: dict[str, Any]) -> list[dict[str, str]]:
        """Rows of an earlier writer's journal with the same head whose files are whole
        (a frame cut short after it was journaled is predicted again, not kept)."""
        path = self.root / JOURNAL
        if not path.exists():
            return []
        rows: list[dict[str, str]] = []
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines()):
            try:
                item = json.loads(line)
            except json.JSONDecodeError:
                break  # a line torn by the kill: everything before it stands
            if n == 0:
                if item != head:
                    return []
            elif file_complete(self.root / item["file"]):
                rows.append(item)
        return rows

    @property
    def done(self) -> set[int]:
        """Frame indices already written (by this writer or a resumed one)."""
        return {int(r["index"]) for r in self.rows}

    @property
    def beyond_float16(self) -> int:
        """Pixels float16 could not hold, written NaN, over every frame on disk (a resumed
        writer's included); 0 when storing float32."""
        return sum(int(r.get("beyond_float16") or 0) for r in self.rows)

    def add(self, index: int, stamp: float, pred: DepthPrediction) -> int:
        """Write frame ``index``; returns its pixels beyond what the stored dtype can hold
        (float16: magnitudes above 65504), written NaN (invalid)."""
        if pred.kind != self.kind:
            raise ValueError(f"frame {index}: kind {pred.kind} differs from {self.kind}")
        rel = f"frames/{index:06d}.npy"
        values, beyond = (to_float16(pred.values) if self.dtype == "float16"
                          else (pred.values.astype(np.float32), 0))
        with atomic_path(self.root / rel) as tmp:
            np.save(tmp, values)
        self.shape = pred.values.shape
        row = {"index": str(index), "stamp": repr(float(stamp)), "file": rel,
               "latency_s": f"{pred.latency_s:.6f}"}
        for key in ("true_scale", "confident_fraction"):
            if key in pred.extra:
                row[key] = repr(float(pred.extra[key]))
        if beyond:
            row["beyond_float16"] = str(beyond)
        self.rows.append(row)
        # After the file: a journaled frame is complete on disk. Flushed, not fsynced: this
        # guards against a killed process, not against power loss.
        self._journal.write(json.dumps(row) + "\n")
        self._journal.flush()
        return beyond

    def close(self) -> Path:
        self.rows.sort(key=lambda r: int(r["index"]))
        fields: list[str] = []
        for r in self.rows:
            fields += [k for k in r if k not in fields]
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=fields or ["index", "stamp", "file", "latency_s"],
                           lineterminator="\n")
        w.writeheader()
        w.writerows(self.rows)
        atomic_write_text(self.root / "index.csv", buf.getvalue())
        meta = {"format": "lidarcam-depth", "version": 1, "kind": self.kind,
                "frames": len(self.rows), "height": self.shape[0] if self.shape else None,
                "width": self.shape[1] if self.shape else None, **self.info}
        atomic_write_json(self.root / "meta.json", meta)
        # The journal stays: a kill after this (the stage's figure and report, the
        # runner's manifest) resumes with every frame kept, not none.
        self._journal.close()
        return self.root


class DepthStore:
    """Reads a depth folder written by ``DepthStoreWriter``."""

    def __init__(self, root: Path | str) -> None:
        self.root = Path(root)
        meta_path = self.root / "meta.json"
        if not meta_path.exists():
            raise MissingInputError(f"{meta_path}: not a finished depth folder (no meta.json)")
        # A damaged file (a truncated copy, an edit by hand) failed as a JSONDecodeError or
        # a KeyError, which the runner shows as a bug, naming neither the file nor the field.
        fix = ("Fix: run the depth stage again (python -m toolkit.recipe run RECIPE --from "
               "<its id>), or give the reading stage an intact depth folder")
        try:
            meta = json.loads(meta_path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise InputError(f"{meta_path}: not a JSON file ({e}); {fix}") from None
        if not isinstance(meta, dict):
            raise InputError(f"{meta_path}: holds {type(meta).__name__}, not a mapping with "
                             f"field 'kind'; {fix}")
        self.meta: dict[str, Any] = meta
        kind = self.meta.get("kind")
        if kind not in DEPTH_KINDS:
            raise InputError(f"{meta_path}: field 'kind' is {kind!r}, not one of {DEPTH_KINDS}")
        self.kind: DepthKind = kind
        index_path = self.root / "index.csv"
        if not index_path.exists():
            raise MissingInputError(f"{index_path}: not there, but {meta_path} is (the "
                                    f"folder's frame list is lost); {fix}")
        with index_path.open(newline="") as f:
            reader = csv.DictReader(f)
            missing = [k for k in ("index", "file") if k not in (reader.fieldnames or [])]
            if missing:
                raise InputError(f"{index_path}: no column {', '.join(map(repr, missing))} "
                                 f"(header {reader.fieldnames}); {fix}")
            self.rows = list(reader)
        self._by_index = {}
        for line, r in enumerate(self.rows, start=2):
            try:
                self._by_index[int(r["index"])] = r
            except (TypeError, ValueError):
                raise InputError(f"{index_path}:{line}: field 'index' is {r['index']!r}, not a "
                                 f"frame number; {fix}") from None

    def __len__(self) -> int:
        return len(self.rows)

    @property
    def indices(self) -> list[int]:
        return sorted(self._by_index)

    def has(self, index: int) -> bool:
        return index in self._by_index

    def read(self, index: int) -> DepthPrediction:
        row = self._by_index.get(index)
        if row is None:
            # A KeyError, which the runner shows as a bug, named the folder only.
            held = (f"{len(self.rows)} frames, {self.indices[0]} to {self.indices[-1]}"
                    if self.rows else "no frames")
            raise MissingInputError(
                f"{self.root / 'index.csv'}: field 'index' lists no frame {index} (it holds "
                f"{held}): this depth folder holds no prediction for a frame that is read "
                "now. Fix: run the depth stage again for these frames (with every: 1 it "
                "predicts every frame), or give the reading stage the depth of this "
                "recording")
        values = np.load(self.root / row["file"]).astype(np.float32)
        extra = {"true_scale": float(row["true_scale"])} if row.get("true_scale") else {}
        return DepthPrediction(values, self.kind, float(row.get("latency_s") or 0.0), extra)

    def latencies(self) -> np.ndarray:
        return np.array([float(r.get("latency_s") or 0.0) for r in self.rows])

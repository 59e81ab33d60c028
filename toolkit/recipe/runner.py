"""Runs a validated recipe: run directory, per-stage cache, resume, logging and progress.

A stage is complete when ``<stage_dir>/.stage.json`` exists with the stage's current cache
key and its provided paths exist. The marker is written atomically after ``run`` returns
and deleted before a rerun starts, so a stage killed at any point (exception, Ctrl-C,
SIGKILL) is simply incomplete and the next run resumes there.

A stage's cache key holds its type, version, settings and external files, and a *token*
for every input it reads from an earlier stage. An output's token is the digest of its
content, taken when the stage finishes: a rerun (``--force``, ``--only``, an upgrade that
bumps a stage's version) that writes the same bytes leaves the stages reading that output
cached, and one that writes other bytes makes them stale, as ``make`` does on changed
files (the "early cutoff" of build systems). Results read from an earlier stage
(``reads``: its metrics, which hold timings) take a token drawn each time it runs: those
readers always follow a rerun. Markers written before output digests existed lend their
run token to every output, which is what later keys were made of then.

A finished stage's outputs are checked file by file before it is taken as cached: a file
missing or of another size reruns it. So does one edited in place to the same size (a
digit fixed in a YAML, an image rewritten at its shape): the marker keeps each file's
mtime and SHA-256 (``manifest_digests``, taken in the read that digests the outputs), and
a file whose mtime moved is hashed and compared. Same bytes (a copy of the run folder,
``touch``) keep the stage cached and the new mtimes are stored, so the next run reads
nothing; these per-file digests are no part of any cache key or token.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import logging
import math
import os
import re
import time
import uuid
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, TypeVar

import yaml
from rich.console import Console
from rich.logging import RichHandler
from rich.markup import escape
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from toolkit.errors import InputError, MissingInputError, WriteError
from toolkit.io.atomic import (
    atomic_write_json,
    atomic_write_text,
    remove_leftover_temps,
    remove_path,
    remove_temps_under,
    target_of,
    to_jsonable,
    write_failure,
)
from toolkit.recipe import registry, report
from toolkit.recipe.memory import PeakMemory, StagePeak, release_freed_memory
from toolkit.recipe.report import StageSummary
from toolkit.recipe.schema import (
    Recipe,
    RecipeError,
    StageSpec,
    config_data,
    dump_recipe_data,
    read_yaml_value,
)
from toolkit.recipe.stage import Stage, StageContext, StageError, StageResult

try:
    import fcntl
except ImportError:  # Windows: runs are not locked against each other there
    fcntl = None  # type: ignore[assignment]
try:
    import resource
except ImportError:  # Windows: CPU time of this process only
    resource = None  # type: ignore[assignment]

T = TypeVar("T")

STAGE_FILE = ".stage.json"
# Written when a stage starts, removed when it finishes: the key of the settings an
# interrupted run's files belong to (resumed only under that key).
STARTED_FILE = ".stage.started.json"
_MARKERS = frozenset({STAGE_FILE, STARTED_FILE})  # the runner's, not a stage's output
# Why a finished stage reruns when a file of its output was edited in place.
_CHANGED = "changed since the stage wrote it"
_UPSTREAM_UNFINISHED = "an earlier stage has not finished"
RESOLVED_FILE = "recipe.resolved.yaml"
LOG_FILE = "run.log"
LOCK_FILE = ".lock"
# SHA-256 of the external files stages key by content, by file and its size, times and
# inode: a 1 GB model is hashed when it changes, not on every run.
DIGESTS_FILE = ".file_digests.json"
# run_dir/.previous/<id>: a finished stage's folder, kept while the stage reruns from
# scratch; back in place when the rerun fails, deleted when it finishes. run_dir/.failed/<id>:
# the failed rerun's folder, for its logs and partial files.
PREVIOUS_DIR = ".previous"
FAILED_DIR = ".failed"

# Why a stage with a folder but no finished marker runs (the reason line says more):
# interrupted (killed, Ctrl-C), or failed with an error, which its started marker records.
_UNFINISHED = "did not finish last time"
_FAILED = "failed last time"

# Stages run with numpy's BLAS on this many threads (an integer, or "default" for the
# libraries' own setting): see _blas_limit.
BLAS_THREADS_ENV = "TOOLKIT_RECIPE_BLAS_THREADS"


def blas_threads() -> int | None:
    """The BLAS thread count stages run with: ``TOOLKIT_RECIPE_BLAS_THREADS`` (unset: 1),
    or None for "default" (the libraries' own, e.g. ``OPENBLAS_NUM_THREADS`` or a thread
    per core). Raises ``RecipeError`` for any other value."""
    value = os.environ.get(BLAS_THREADS_ENV, "").strip() or "1"
    if value.lower() == "default":
        return None
    try:
        n = int(value)
    except ValueError:
        n = 0
    if n < 1:
        raise RecipeError(f"environment variable {BLAS_THREADS_ENV}={value!r}: set a "
                          "number of threads (1 or more) or 'default'")
    return n


@contextlib.contextmanager
def _blas_limit(threads: int | None) -> Iterator[None]:
    """BLAS on ``threads`` threads while a stage runs (None: left alone).

    The stages' numpy products are point transforms ([N, 3] @ [3, 3]) and small solves;
    OpenBLAS splits them over its threads, which on a busy 2-core machine wait for each
    other and for the stage's own threads (Open3D's, torch's): docs/runner.md, "BLAS on
    one thread". The limit is OpenBLAS's global thread count, so the stage's worker
    threads run under it too; it covers the BLAS libraries loaded when the stage starts
    (numpy's, scipy's and OpenCV's, once the recipe's stage modules are imported)."""
    if threads is None:
        yield
        return
    from threadpoolctl import ThreadpoolController

    with ThreadpoolController().limit(limits=threads, user_api="blas"):
        yield


# Log records carrying this go to run.log only (tracebacks, lines already printed nicely).
_FILE_ONLY = {"console": False}


class StoppedAfterStage(KeyboardInterrupt):
    """Ctrl-C / SIGTERM once ``stage`` had finished (while its outputs were digested): that
    stage is done, and rerunning it (``--only`` it, ``--force``) would redo it."""

    def __init__(self, stage: str) -> None:
        super().__init__(f"interrupted after stage {stage!r} finished")
        self.stage = stage


@dataclass
class RunResult:
    """Outcome of ``run_recipe``: per-stage status and seconds, merged metrics, run dir."""

    run_dir: Path
    statuses: dict[str, str]  # stage id -> ran | cached | failed | not run
    metrics: dict[str, dict[str, Any]]
    seconds: dict[str, float | None]
    error: str | None = None
    failed_stage: str | None = None

    @property
    def ok(self) -> bool:
        """True when no stage failed."""
        return self.failed_stage is None


@dataclass
class _Record:
    spec: StageSpec
    status: str = "pending"
    reason: str = ""
    key: str | None = None
    # The key without the stage's resume_settings: an interrupted run's files are resumed
    # under it.
    folder_key: str | None = None
    token: str | None = None  # drawn when the stage last finished running (module doc)
    output_tokens: dict[str, str] = field(default_factory=dict)  # digest of each output
    seconds: float | None = None
    cpu_seconds: float | None = None
    peak: PeakMemory | None = None  # the stage's peak resident memory
    metrics: dict[str, Any] = field(default_factory=dict)
    report: list[str] = field(default_factory=list)
    provides: dict[str, Path] = field(default_factory=dict)
    # The stage's finished folder, moved aside while it reruns (PREVIOUS_DIR).
    previous: Path | None = None

    @property
    def finished(self) -> bool:
        return self.status in ("ran", "cached")

    # StageSummary, not report.StageSummary: in this class body ``report`` is the field
    # above, and type checkers looked the annotation up in it (mypy: name-defined).
    def summary(self, run_dir: Path | None = None) -> StageSummary:
        folder = run_dir / self.spec.id if run_dir is not None else None
        return StageSummary(
            id=self.spec.id,
            type=self.spec.type,
            status=self.status,
            seconds=self.seconds,
            cpu_seconds=self.cpu_seconds,
            peak=self.peak,
            markdown="\n\n".join(self.report),
            stale_files=self.status == "not run" and folder is not None and folder.is_dir()
            # Hidden names are the runner's bookkeeping (a run killed as the stage started).
            and any(not p.name.startswith(".") for p in folder.iterdir()),
        )


def run_recipe(
    recipe: Recipe,
    force: bool = False,
    from_stage: str | None = None,
    only: str | None = None,
    console: Console | None = None,
) -> RunResult:
    """Run ``recipe`` in its output folder, reusing every stage that is already complete.

    ``force`` reruns every selected stage; ``from_stage`` reruns that stage and all after it
    (the ones before must be complete); ``only`` reruns just that stage (the stages it takes
    artifacts from must be complete). A recipe or option problem raises ``RecipeError``; a
    failing stage does not raise but is reported in the result (``result.ok`` is False).
    """
    if from_stage is not None and only is not None:
        raise RecipeError("--from and --only cannot be combined")
    from_index = recipe.index_of(from_stage, "--from") if from_stage is not None else None
    only_index = recipe.index_of(only, "--only") if only is not None else None
    selected = [s.id for s in recipe.stages if (only_index is None or s.index == only_index)
                and (from_index is None or s.index >= from_index)]
    problems = missing_inputs(recipe, selected)
    if problems:
        raise RecipeError(problems)
    threads = blas_threads()
    console = console or Console()
    run_dir = recipe.output if recipe.output.is_absolute() else Path.cwd() / recipe.output
    # The folders this call makes: the run folder and any missing parents, top first.
    made = [p for p in (*reversed(run_dir.parents), run_dir) if not p.exists()]
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:  # a file in the way, no permission
        raise RecipeError(f"output: cannot make the run folder {run_dir}: {exc}; set "
                          f"'output' to a folder path") from None
    others = _not_a_run_folder(run_dir, recipe)
    if others:
        raise RecipeError(
            f"output: {run_dir} holds files but no run of a recipe ({', '.join(others[:5])}"
            f"{', ...' if len(others) > 5 else ''}): a run writes report.md, metrics.json and "
            "run.log there, replacing files of those names. Set 'output' to a new or empty "
            "folder (nothing was changed)")
    owner = _other_recipes_run(run_dir, recipe)
    if owner is not None:
        raise RecipeError(
            f"output: {run_dir} holds a run of recipe {owner!r} ({RESOLVED_FILE}), not of "
            f"{recipe.name!r}: a run would replace that run's results wherever the settings "
            "differ. Set 'output' to another folder; if this recipe is that one renamed, "
            f"delete {run_dir / RESOLVED_FILE} first (nothing was changed)")
    with _exclusive(run_dir):
        try:
            foreign = foreign_stage_folders(recipe, run_dir)
            if foreign:
                raise RecipeError(foreign)
            with _run_logging(run_dir, console) as log:
                run = _Run(recipe, run_dir, console, log, force, from_index, only_index)
                run.blas_threads = threads
                return run.execute()
        except RecipeError:
            # A refused --only / --from leaves no folders of lock and log behind; only
            # what this call made, and only while it holds the lock (a run that took the
            # folder first keeps it).
            _remove_if_only_bookkeeping(made)
            raise


def _not_a_run_folder(run_dir: Path, recipe: Recipe) -> list[str]:
    """The entries of ``run_dir`` when it holds files but no sign of a run (its lock, log or
    resolved recipe, or a stage folder with a marker): a typo'd or data folder as
    ``output``, whose report.md or metrics.json a run replaced. Empty when it is fine."""
    names = sorted(p.name for p in run_dir.iterdir())
    if not names or {LOCK_FILE, LOG_FILE, RESOLVED_FILE} & set(names):
        return []
    for spec in recipe.stages:
        d = run_dir / spec.id
        if (d / STAGE_FILE).exists() or (d / STARTED_FILE).exists():
            return []
    return names


def _drop_if_empty(folder: Path) -> None:
    """Remove ``folder`` when nothing is left in it (PREVIOUS_DIR, FAILED_DIR)."""
    with contextlib.suppress(OSError):  # not empty, or not there
        folder.rmdir()


def _other_recipes_run(run_dir: Path, recipe: Recipe) -> str | None:
    """The name of the recipe whose run ``run_dir`` holds, when it is not ``recipe``'s: an
    ``output:`` copied with a recipe, or mistyped, into another run's folder replaced that
    run's stages wherever the settings differed (every stage, for another recipe). None
    for a run of this recipe, or a folder without a readable resolved recipe."""
    try:
        data = read_yaml_value((run_dir / RESOLVED_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError, yaml.YAMLError):  # none (a new folder), or unreadable
        return None
    name = data.get("name") if isinstance(data, dict) else None
    return str(name) if name is not None and str(name) != recipe.name else None


def _foreign_folder_message(stage_dir: Path, stage_id: str) -> str:
    # The likely case first: a finished stage whose marker went (deleted by hand, a copy
    # or clean-up that skips hidden files). The runner cannot tell its outputs from
    # files put there, so it deletes neither.
    return (f"{stage_dir} holds files but no record of a run of stage {stage_id!r} "
            f"({STAGE_FILE} / {STARTED_FILE}): the stage's outputs whose record was "
            "deleted (a copy or clean-up that skips hidden files does that), or files "
            "that are not the runner's, which it does not delete. Delete the folder to "
            "run the stage again (move it elsewhere first if it holds files to keep), "
            "then run again (nothing was changed)")


def _file_in_the_way(path: str | os.PathLike[str] | None) -> Path | None:
    """The file standing where ``path`` or a folder above it must be a folder (what
    ENOTDIR and mkdir's EEXIST are about), or None."""
    if path is None:
        return None
    for p in (Path(os.fsdecode(path)), *Path(os.fsdecode(path)).parents):
        if p.is_symlink() or p.exists():
            return None if p.is_dir() else p
    return None


def _prepare_failure(run_dir: Path, stage_dir: Path, exc: OSError) -> str:
    """Why a stage's folder could not be made ready, and the fix for that cause."""
    blocker = _file_in_the_way(exc.filename)
    if exc.errno in (errno.ENOTDIR, errno.EEXIST) and blocker is not None:
        # "make the folder writable or free space" was the advice for a file named
        # .previous, which neither would fix.
        purpose = {run_dir / PREVIOUS_DIR: " (where a finished stage's output waits while "
                   "the stage reruns)", run_dir / FAILED_DIR: " (where a failed rerun's "
                   "files are kept)"}.get(blocker, "")
        return (f"cannot prepare its folder {stage_dir}: {blocker} is a file where the "
                f"runner needs a folder{purpose}; move or delete that file, then run again "
                "(the stage did not start)")
    # Named with the stage's folder: shutil.rmtree's errors name a file alone
    # ("Permission denied: 'path_020.png'"), not where it is.
    return (f"cannot prepare its folder {stage_dir} ({type(exc).__name__}: {exc}); make "
            "the folder writable or free space, then run again (the stage did not start)")


def _clear_marker_temporaries(stage_dir: Path) -> None:
    """Remove what a killed write of the runner's markers left (their atomic writes'
    temporaries): alone in a folder they made it look like files of someone else's."""
    for name in _MARKERS:
        remove_leftover_temps(stage_dir / name)


def foreign_stage_folders(recipe: Recipe, run_dir: Path) -> list[str]:
    """Messages for stage folders in ``run_dir`` that hold files but no record of a run of
    the runner's: checked before any stage runs (found when the stage's turn came, the
    stages before it had run and the exit code said nothing had)."""
    out = []
    for spec in recipe.stages:
        d = run_dir / spec.id
        if d.is_dir():
            _clear_marker_temporaries(d)
        if (d.is_dir() and any(d.iterdir()) and not (d / STAGE_FILE).exists()
                and _started_folder_key(d / STARTED_FILE) is None):
            out.append(_foreign_folder_message(d, spec.id))
    return out


def _remove_if_only_bookkeeping(made: list[Path]) -> None:
    if not made:
        return
    run_dir = made[-1]
    names = {p.name for p in run_dir.iterdir()}
    if not names <= {LOCK_FILE, LOG_FILE, DIGESTS_FILE}:
        return
    for name in names:
        (run_dir / name).unlink()
    for folder in reversed(made):
        if any(folder.iterdir()):
            break
        folder.rmdir()


class _Run:
    def __init__(
        self,
        recipe: Recipe,
        run_dir: Path,
        console: Console,
        log: logging.Logger,
        force: bool,
        from_index: int | None,
        only_index: int | None,
    ) -> None:
        self.recipe = recipe
        self.run_dir = run_dir
        self.console = console
        self.log = log
        self.force = force
        self.from_index = from_index
        self.only_index = only_index
        # --from and --only name stages the user wants run, so they rerun even if cached.
        self.rerun = force or from_index is not None or only_index is not None
        self.records = {spec.id: _Record(spec) for spec in recipe.stages}
        self.error: str | None = None
        self.failed_stage: str | None = None
        # Set when Ctrl-C / SIGTERM stopped the run after a stage finished, not inside one.
        self.interrupted: str | None = None
        self.bar_active = False
        self._resolved_written = False
        self.digests = FileDigests(run_dir / DIGESTS_FILE)
        self.blas_threads: int | None = 1  # BLAS threads the stages run with

    def write_resolved(self) -> None:
        """``recipe.resolved.yaml``, once something of this run is kept: an option check
        that refuses to run must not leave settings no result in the folder came from."""
        if not self._resolved_written:
            text = dump_recipe_data(self.recipe.resolved())
            atomic_write_text(self.run_dir / RESOLVED_FILE, text)
            self._resolved_written = True

    def selected(self, index: int) -> bool:
        if self.only_index is not None:
            return index == self.only_index
        return self.from_index is None or index >= self.from_index

    def option(self) -> str:
        if self.only_index is not None:
            return f"--only {self.recipe.stages[self.only_index].id}"
        if self.from_index is not None:
            return f"--from {self.recipe.stages[self.from_index].id}"
        return ""

    def execute(self) -> RunResult:
        options = " ".join(filter(None, [self.option(), "--force" if self.force else ""]))
        self.log.info(
            "=== run of recipe %r in %s%s",
            self.recipe.name,
            self.run_dir,
            f" ({options})" if options else "",
            extra=_FILE_ONLY,
        )
        self.console.print(
            f"recipe [bold]{escape(self.recipe.name)}[/] -> {escape(str(self.run_dir))}"
        )
        for spec in self.recipe.stages:
            if not self.process(self.records[spec.id]):
                break
        self.settle_pending()
        self.write_outputs()
        self.console.print(report.timing_table([r.summary() for r in self.records.values()]))
        return RunResult(
            run_dir=self.run_dir,
            statuses={i: r.status for i, r in self.records.items()},
            metrics=self.finished_metrics(),
            seconds={i: r.seconds for i, r in self.records.items()},
            error=self.error,
            failed_stage=self.failed_stage,
        )

    def process(self, record: _Record) -> bool:
        """Reuse, run or skip one stage; False stops the run (the stage failed)."""
        spec = record.spec
        selected = self.selected(spec.index)
        waiting = self.waiting_on(spec)
        if waiting:
            if selected:
                upstream = self.records[waiting[0]]
                root = self.first_unfinished(upstream)
                # The stage that stopped the chain and why (a recording or model not found
                # from this folder), not only "an earlier stage has not finished".
                before = ("" if root is upstream else
                          f"; before it, stage {root.spec.id!r}: {root.reason}")
                raise RecipeError(
                    f"{self.option()}: stage {spec.id!r} needs the output of stage "
                    f"{upstream.spec.id!r}, which has not finished ({upstream.reason}"
                    f"{before}); run it first, e.g. --from {root.spec.id}"
                )
            record.status, record.reason = "not run", _UPSTREAM_UNFINISHED
            return True
        start = time.perf_counter()
        try:
            stage = spec.cls(spec.config)
            record.key = _cache_key(spec, stage, self.upstream_tokens(spec),
                                    stage.speed_settings, self.digests)
            record.folder_key = _cache_key(spec, stage, self.upstream_tokens(spec),
                                           stage.resume_settings | stage.speed_settings,
                                           self.digests)
        except Exception as exc:
            if not selected:
                record.status, record.reason = "not run", f"cannot check its inputs: {exc}"
                return True
            self.fail(record, exc, start)
            return False
        stored, record.reason = _read_marker(self.run_dir / spec.id, record.key, spec.cls.provides)
        if not selected:
            if stored is not None:
                self.reuse(record, stored)
            elif self.from_index is not None:
                raise RecipeError(
                    f"{self.option()}: earlier stage {spec.id!r} has not finished "
                    f"({record.reason}); run it first, e.g. --from {spec.id}"
                )
            else:
                record.status = "not run"
                missing = [p for p in stage.external_inputs() if not Path(p).exists()]
                if missing:
                    record.reason += (f": its input {os.path.abspath(missing[0])} is missing "
                                      "(relative paths are read from the current folder)")
            return True
        if stored is not None and not self.rerun:
            self.reuse(record, stored)
            return True
        if stored is not None:
            record.reason = self.option() or "--force"
        elif record.reason in (_UNFINISHED, _FAILED):
            # Say whether it resumes (prepare_stage_dir's rule): an unfinished run of other
            # settings, or any under --force, starts afresh. A failed one is kept to resume
            # like an interrupted one, but "resumes" alone reads as "was interrupted".
            started = _started_folder_key(self.run_dir / spec.id / STARTED_FILE)
            if self.force:
                record.reason += "; --force starts it afresh"
            elif started != record.folder_key:
                record.reason += ", under other settings: starts afresh"
            elif record.reason == _FAILED:
                record.reason += ": runs again, on the files it wrote"
            else:
                record.reason += ": resumes"
        elif record.reason.endswith(_CHANGED):
            # The rerun replaces the edited file: say where it waits meanwhile (the whole
            # folder, moved aside; deleted when the rerun finishes).
            record.reason += (f"; the folder as it is waits in "
                              f"{self.run_dir / PREVIOUS_DIR / spec.id} until the rerun "
                              "finishes")
        ok = self.run_stage(record, stage)
        self.write_outputs()
        return ok

    def first_unfinished(self, record: _Record) -> _Record:
        """The earliest unfinished stage up the chain that ``record`` waits on (itself
        when it is not waiting on another)."""
        while record.reason == _UPSTREAM_UNFINISHED:
            waiting = self.waiting_on(record.spec)
            if not waiting:
                break
            record = self.records[waiting[0]]
        return record

    def waiting_on(self, spec: StageSpec) -> list[str]:
        """The stages ``spec`` reads from that have not finished."""
        return [s for s in dict.fromkeys((*spec.sources.values(), *spec.reads))
                if not self.records[s].finished]

    def upstream_tokens(self, spec: StageSpec) -> dict[str, str | None]:
        upstream = {n: self.records[s].output_tokens.get(n, self.records[s].token)
                    for n, s in spec.sources.items()}
        upstream.update({f"results:{s}": self.records[s].token for s in spec.reads})
        return upstream

    def settle_pending(self) -> None:
        """After a failed or interrupted stage: the stages not reached keep a finished result
        that is still valid (an independent branch), so metrics.json and the report do not
        lose it; the rest are 'not run'."""
        for record in self.records.values():
            if record.status != "pending":
                continue
            spec = record.spec
            record.status, record.reason = "not run", _UPSTREAM_UNFINISHED
            if self.waiting_on(spec):
                continue
            try:
                stage = spec.cls(spec.config)
                key = _cache_key(spec, stage, self.upstream_tokens(spec), stage.speed_settings,
                                 self.digests)
            except Exception:  # noqa: BLE001 - it is reported as not run, nothing more
                continue
            stored, _ = _read_marker(self.run_dir / spec.id, key, spec.cls.provides)
            if stored is not None:
                record.key = key
                self.reuse(record, stored)

    def reuse(self, record: _Record, stored: Mapping[str, Any]) -> None:
        stage_dir = self.run_dir / record.spec.id
        record.status = "cached"
        # Markers written before tokens existed stand for themselves by their key, which is
        # what downstream keys were made of then: those runs stay cached.
        record.token = str(stored.get("token") or stored["key"])
        record.output_tokens = {str(k): str(v) for k, v in
                                (stored.get("output_tokens") or {}).items()}
        record.seconds = stored.get("seconds")
        record.cpu_seconds = stored.get("cpu_seconds")
        record.peak = _stored_peak(stored)
        record.metrics = dict(stored.get("metrics") or {})
        text = stored.get("report") or ""
        record.report = [text] if text else []
        record.provides = {n: stage_dir / rel for n, rel in stored["provides"].items()}
        then, now = stored.get("speed_settings") or {}, _speed_values(record.spec)
        changed = [f"{k} {then.get(k)!r} -> {v!r}" for k, v in now.items()
                   if k in then and then[k] != v]
        # Its figures (timings) are the earlier run's: say so, and how to redo them.
        why = (f" (only {', '.join(changed)} changed, which does not change its output; "
               f"--only {record.spec.id} reruns it for its timings)") if changed else ""
        self.console.print(f"[cyan]{record.spec.id}[/] cached{why}")
        self.log.info("stage %s cached (key %s)", record.spec.id, record.key, extra=_FILE_ONLY)
        old = self.run_dir / PREVIOUS_DIR / record.spec.id
        if old.exists():
            # The rerun that made this output was killed before it deleted the output it
            # replaced: deleted now, as that rerun would have (else it stays for good).
            remove_path(old, ignore_errors=True)
            _drop_if_empty(old.parent)
            self.log.info("stage %s: deleted %s, the output its last rerun replaced",
                          record.spec.id, old, extra=_FILE_ONLY)

    def prepare_stage_dir(self, record: _Record) -> None:
        """Empty the stage's folder unless it holds an interrupted run of these very
        settings (which the stage resumes): files of other settings would otherwise be
        read as this run's (an old per-frame depth beside the new, an old capture, old
        renders), and ``--force`` means from scratch."""
        stage_dir = self.run_dir / record.spec.id
        aside = self.run_dir / PREVIOUS_DIR / record.spec.id
        if (aside / STAGE_FILE).exists():
            # A rerun killed (SIGKILL, Ctrl-C) left the finished output aside: this run
            # puts it back if it fails, as the rerun would have, and deletes it once done.
            record.previous = aside
        if not stage_dir.exists() or not any(stage_dir.iterdir()):
            return
        done = (stage_dir / STAGE_FILE).exists()
        started = _started_folder_key(stage_dir / STARTED_FILE)
        if not done and started is None:
            raise RecipeError(_foreign_folder_message(stage_dir, record.spec.id))
        # Only an interrupted run is resumed: a finished one reruns from scratch (--force,
        # --from, --only, other settings, a lost output).
        if not self.force and not done and started == record.folder_key:
            return
        if done:
            # A finished output is moved aside, not deleted: a rerun that fails (a bad
            # input, a mistyped setting) puts it back, so what was written is not lost
            # for nothing; one rename, no copy.
            keep = self.run_dir / PREVIOUS_DIR / record.spec.id
            remove_path(keep)
            keep.parent.mkdir(exist_ok=True)
            os.replace(stage_dir, keep)
            record.previous = keep
            return
        # A started marker no run resumes from goes in first, then the finished one: a run
        # interrupted while this empties the folder leaves it recognisably the runner's and
        # unfinished, to be emptied again (with the finished marker kept to the end, a
        # half-emptied folder was taken as finished by the next run of those settings).
        atomic_write_json(stage_dir / STARTED_FILE, {"key": None, "folder_key": "emptying"},
                          fsync=True)
        (stage_dir / STAGE_FILE).unlink(missing_ok=True)
        for child in sorted(stage_dir.iterdir(), key=lambda p: p.name == STARTED_FILE):
            remove_path(child)

    def run_stage(self, record: _Record, stage: Stage) -> bool:
        spec = record.spec
        stage_dir = self.run_dir / spec.id
        start = time.perf_counter()
        try:
            self.prepare_stage_dir(record)
            stage_dir.mkdir(parents=True, exist_ok=True)
            # The old marker goes first: a rerun killed halfway must not look complete next
            # time; the started marker says which settings its files belong to.
            (stage_dir / STAGE_FILE).unlink(missing_ok=True)
            atomic_write_json(stage_dir / STARTED_FILE,
                              {"key": record.key, "folder_key": record.folder_key}, fsync=True)
            self.write_resolved()
        except RecipeError:
            raise
        except OSError as exc:  # a full disk, a read-only folder, a file in the way
            self.fail(record, StageError(_prepare_failure(self.run_dir, stage_dir, exc)),
                      start)
            self.restore_previous(record)
            return False
        record.metrics, record.report, record.provides = {}, [], {}
        self.console.print(f"[bold]{spec.id}[/] running ({escape(record.reason)})")
        self.log.info(
            "stage %s (%s) started: %s", spec.id, spec.type, record.reason, extra=_FILE_ONLY
        )
        ctx = _Context(self, record)
        start = time.perf_counter()
        cpu_start = _cpu_seconds()
        peak = StagePeak()
        try:
            with _blas_limit(self.blas_threads):
                stage.run(ctx)
            # The stage's locals are gone: what they held goes back to the system, not to
            # the next stage's starting point (release_freed_memory).
            release_freed_memory()
            ctx.check_provided()
            # A kill before this run left half-written temporaries in the folder (a resumed
            # fuse's scaled depth): the finished folder holds outputs only.
            remove_temps_under(stage_dir)
            record.seconds = time.perf_counter() - start
            record.cpu_seconds = _cpu_seconds() - cpu_start
            record.peak = _finished_peak(peak)
            record.token = uuid.uuid4().hex
            record.output_tokens = {}
            marker = {
                "key": record.key,
                "token": record.token,
                "output_tokens": {},
                "stage": spec.type,
                "speed_settings": _speed_values(spec),
                "provides": {n: _relative(p, stage_dir) for n, p in record.provides.items()},
                "metrics": record.metrics,
                "report": "\n\n".join(record.report),
                "seconds": record.seconds,
                "cpu_seconds": record.cpu_seconds,
                **_peak_fields(record.peak),
                "finished_at": datetime.now(UTC).isoformat(timespec="seconds"),
                "manifest": {n: _manifest(p) for n, p in record.provides.items()},
            }
            atomic_write_json(stage_dir / STAGE_FILE, marker, fsync=True, compact=True)
        except Exception as exc:
            # What it reached before failing: a stage that ran out of memory says so.
            record.peak = _finished_peak(peak)
            self.fail(record, exc, start)
            # The next run tells a failure from an interruption (which leaves the marker
            # as it was) by this.
            _mark_started_failed(stage_dir / STARTED_FILE, self.error or "")
            self.restore_previous(record, exc)
            return False
        except BaseException:  # Ctrl-C / SIGTERM: keep what finished, then stop
            record.peak = _finished_peak(peak)
            self.fail(record, KeyboardInterrupt("interrupted"), start)
            self.settle_pending()
            self.write_outputs()
            raise
        # The marker is written: the stage is finished on disk (the next run takes it as
        # cached), so this run counts it finished too, its figures in metrics.json and the
        # report, whatever happens while its outputs are digested.
        record.status = "ran"
        self.console.print(f"[green]{spec.id}[/] ran in {record.seconds:.1f} s")
        self.log.info("stage %s finished in %.2f s", spec.id, record.seconds, extra=_FILE_ONLY)
        try:
            (stage_dir / STARTED_FILE).unlink(missing_ok=True)
            for aside in (PREVIOUS_DIR, FAILED_DIR):  # the old output, a failed attempt
                # A file of that name holds nothing of the stage; removing "inside" it
                # failed (ENOTDIR), which cost the stage its digests under a warning
                # blaming them. A rerun names the file (_prepare_failure).
                if (self.run_dir / aside).is_dir():
                    remove_path(self.run_dir / aside / spec.id)
                    _drop_if_empty(self.run_dir / aside)
            self.digest_outputs(record, marker)
        except Exception as exc:  # an unreadable output, a disk error: only the digest lost
            self.log.warning("stage %s finished, but its outputs could not be digested: %s",
                             spec.id, _digest_failure(exc))
        except BaseException as exc:  # Ctrl-C / SIGTERM: this stage is done, the run stops
            self.interrupted = (f"interrupted after stage {spec.id!r} finished, while its "
                                "outputs were digested; the stages after it did not run")
            self.log.warning("run stopped: %s", self.interrupted)
            self.settle_pending()
            self.write_outputs()
            if isinstance(exc, KeyboardInterrupt):
                raise StoppedAfterStage(spec.id) from None
            raise
        return True

    def restore_previous(self, record: _Record, exc: BaseException | None = None) -> None:
        """Put the finished folder a failed rerun had moved aside back in place; the failed
        attempt goes to FAILED_DIR. (An interrupted rerun keeps its folder to resume, and
        the finished one stays aside until the rerun finishes.) ``exc``: why it failed."""
        keep, record.previous = record.previous, None
        if keep is None or not keep.is_dir():
            return
        stage_dir = self.run_dir / record.spec.id
        failed = self.run_dir / FAILED_DIR / record.spec.id
        where = ""
        try:
            if stage_dir.exists():
                remove_path(failed)
                failed.parent.mkdir(exist_ok=True)
                os.replace(stage_dir, failed)
                where = f"; the failed attempt is in {failed}"
            os.replace(keep, stage_dir)
            _drop_if_empty(keep.parent)
        except OSError as exc:
            blocker = _file_in_the_way(exc.filename)
            fix = (f"; {blocker} is a file where the runner needs a folder: move or delete "
                   "it, then run again" if exc.errno in (errno.ENOTDIR, errno.EEXIST)
                   and blocker is not None else "")
            self.log.warning("stage %s: its previous output could not be put back from %s "
                             "(%s); it is still there%s", record.spec.id, keep, exc, fix)
            return
        self.console.print(f"[yellow]{record.spec.id}[/]: its previous output (the last "
                           f"finished run's) is back in {stage_dir}{escape(where)}",
                           soft_wrap=True)
        if isinstance(exc, OSError) and exc.errno == errno.ENOSPC:
            # Kept until the rerun finished, the old output held space the rerun needed
            # (deleted first, it would not have).
            self.console.print(
                f"[yellow]{record.spec.id}[/]: the disk filled while that previous output "
                f"was kept: delete {escape(str(stage_dir))} (and "
                f"{escape(str(self.run_dir / FAILED_DIR))}) to give the rerun its space",
                soft_wrap=True)
        self.log.info("stage %s: previous output restored%s", record.spec.id, where,
                      extra=_FILE_ONLY)

    def digest_outputs(self, record: _Record, marker: dict[str, Any]) -> None:
        """Record the content digest of a finished stage's outputs, for early cutoff, and
        each output file's mtime and SHA-256, for the check of a later run; one read.

        Taken once the stage stands finished (an hour's outputs take a minute or more to
        read): a marker left without them keys the stage's readers by its run token and
        checks its files by size alone. A stage whose outputs never repeat (timings in
        them) gets no token, but its files are digested all the same: an edited depth
        map is as wrong downstream as an edited trajectory."""
        spec = record.spec
        repeat = spec.cls.outputs_repeat
        t = time.perf_counter()
        tokens: dict[str, str] = {}
        manifest: dict[str, list[list[Any]]] = {}
        digests: dict[str, dict[str, list[Any]]] = {}
        for n, p in record.provides.items():
            tokens[n], manifest[n], digests[n] = _digest_output(p, token=repeat)
        # The manifest again, from the same listing: its entries and the digests align.
        new = {**marker, "manifest": manifest, "manifest_digests": digests}
        if repeat and all(tokens.values()):
            new["output_tokens"] = tokens
        atomic_write_json(self.run_dir / spec.id / STAGE_FILE, new, fsync=True, compact=True)
        if repeat and all(tokens.values()):
            record.output_tokens = tokens
        self.log.info("stage %s: outputs digested in %.1f s", spec.id,
                      time.perf_counter() - t, extra=_FILE_ONLY)

    def fail(self, record: _Record, exc: BaseException, start: float) -> None:
        record.status = "failed"
        record.seconds = time.perf_counter() - start
        sid = record.spec.id
        if isinstance(exc, StageError | KeyboardInterrupt):
            # A StageError message already says what to fix; a traceback would bury it.
            message = str(exc)
            self.log.error("stage %s failed: %s", sid, message, extra=_FILE_ONLY)
            hint = ""
        elif isinstance(exc, OSError) and _is_write_failure(exc, self.run_dir / sid):
            # "[Errno 28] No space left on device (writing ...)" named the file, not the
            # fix; the traceback stays in run.log.
            message = write_failure(exc)
            self.log.error("stage %s failed", sid, exc_info=exc, extra=_FILE_ONLY)
            hint = ""
        else:
            lines = str(exc).strip().splitlines()
            first = lines[0] if lines else ""
            # Bad input reads better without the class name ("ValueError: .../000050.png:
            # frame 50 is not a readable PNG image ..."); an unexpected error (a bug:
            # KeyError, AttributeError) keeps it, for the bug report.
            message = first if first and _is_input_error(exc) else (
                f"{type(exc).__name__}: {first}".rstrip(": "))
            self.log.error("stage %s failed", sid, exc_info=exc, extra=_FILE_ONLY)
            hint = f" (traceback in {self.run_dir / LOG_FILE})"
        self.error = f"stage {sid!r} failed: {message}"
        self.failed_stage = sid
        self.console.print(f"[bold red]error:[/] {escape(self.error + hint)}", soft_wrap=True)

    def finished_metrics(self) -> dict[str, dict[str, Any]]:
        # As plain JSON values, so a fresh run and a cached one compare equal (NaN -> None).
        return to_jsonable({i: r.metrics for i, r in self.records.items() if r.finished})

    def write_outputs(self) -> None:
        self.write_resolved()
        report.write_metrics(self.run_dir, self.finished_metrics())
        text = report.build_report(
            self.recipe.name,
            [r.summary(self.run_dir) for r in self.records.values()],
            description=self.recipe.description,
            error=self.error,
            interrupted=self.interrupted,
        )
        report.write_report(self.run_dir, text)


class _Context(StageContext):
    def __init__(self, run: _Run, record: _Record) -> None:
        spec = record.spec
        self.run_dir = run.run_dir
        self.stage_dir = run.run_dir / spec.id
        self.stage_id = spec.id
        self.recipe_name = run.recipe.name
        self.cache_key = record.key or ""
        self.resume_key = record.folder_key or self.cache_key
        self.log = logging.getLogger(f"toolkit.run.{spec.id}")
        self._run = run
        self._record = record
        self._spec = spec

    def artifact(self, name: str) -> Path:
        cls = self._spec.cls
        if name not in (*cls.requires, *cls.optional_requires):
            # Reading an undeclared artifact would hide a dependency from the cache key.
            raise StageError(
                f"stage {self.stage_id!r} asked for artifact {name!r} without declaring it; "
                f"add it to {cls.__name__}.requires or optional_requires"
            )
        source = self._spec.sources.get(name)
        if source is None:
            makers = registry.providers_of(name)
            raise StageError(
                f"stage {self.stage_id!r} needs artifact {name!r}, which no earlier stage "
                f"provides"
                + (f"; stage types that provide it: {', '.join(makers)}" if makers else "")
            )
        return self._run.records[source].provides[name]

    def has_artifact(self, name: str) -> bool:
        return name in self._spec.available

    def stage_result(self, stage_id: str) -> StageResult:
        if stage_id not in self._spec.reads:
            raise StageError(
                f"stage {self.stage_id!r} asked for the results of {stage_id!r} without "
                f"declaring it; {self._spec.cls.__name__}.reads_results must name it")
        rec = self._run.records[stage_id]
        # As a cached stage's record reads them back (NaN as None, numpy as Python): a
        # reader must not work on a fresh run and fail on the next.
        metrics = to_jsonable(dict(rec.metrics))
        return StageResult(id=stage_id, type=rec.spec.type, metrics=metrics,
                           seconds=rec.seconds, cpu_seconds=rec.cpu_seconds,
                           stage_dir=self._run.run_dir / stage_id, provides=dict(rec.provides))

    def provide(self, name: str, path: Path) -> None:
        cls = self._spec.cls
        if name not in cls.provides:
            raise StageError(
                f"stage {self.stage_id!r} provides {name!r}, which {cls.__name__}.provides "
                f"does not declare ({', '.join(cls.provides) or 'nothing'})"
            )
        full = (self.stage_dir / path).resolve()
        home = self.stage_dir.resolve()
        if full != home and home not in full.parents:
            raise StageError(
                f"stage {self.stage_id!r}: artifact {name!r} at {path} is outside {self.stage_dir}"
            )
        self._record.provides[name] = self.stage_dir / full.relative_to(home)

    def check_provided(self) -> None:
        for name in self._spec.cls.provides:
            path = self._record.provides.get(name)
            if path is None:
                raise StageError(f"stage {self.stage_id!r} finished without providing {name!r}")
            if not path.exists():
                raise StageError(
                    f"stage {self.stage_id!r} provided {name!r} as {path}, which does not exist"
                )

    def add_metrics(self, metrics: dict[str, Any]) -> None:
        _deep_merge(self._record.metrics, metrics)

    def report(self, markdown: str) -> None:
        self._record.report.append(markdown.strip("\n"))

    def progress(
        self, iterable: Iterable[T], total: int | None = None, description: str = ""
    ) -> Iterator[T]:
        if total is None:
            try:
                total = len(iterable)  # type: ignore[arg-type]
            except TypeError:
                total = None
        label = description or self.stage_id
        if self._run.bar_active:  # rich allows one live display; inner loops go quiet
            yield from iterable
        elif self._run.console.is_terminal:
            yield from self._bar(iterable, total, label)
        else:
            yield from self._logged(iterable, total, label)

    def _bar(self, iterable: Iterable[T], total: int | None, label: str) -> Iterator[T]:
        columns = (
            TextColumn("{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            TimeRemainingColumn(),
        )
        self._run.bar_active = True
        try:
            with Progress(*columns, console=self._run.console, transient=True) as bar:
                task = bar.add_task(label, total=total)
                for item in iterable:
                    yield item
                    bar.advance(task)
        finally:
            self._run.bar_active = False

    def _logged(self, iterable: Iterable[T], total: int | None, label: str) -> Iterator[T]:
        # Off a terminal a redrawn bar is noise in a log file; a line per ~10% is enough.
        step = max(1, math.ceil(total / 10)) if total else 0
        last = time.monotonic()
        count = 0
        for item in iterable:
            yield item
            count += 1
            if step and total and (count % step == 0 or count == total):
                self.log.info("%s: %d/%d (%d%%)", label, count, total, 100 * count // total)
            elif not step and time.monotonic() - last >= 10.0:
                last = time.monotonic()
                self.log.info("%s: %d done", label, count)


def setting_holding(data: Any, path: Path, prefix: str = "") -> str | None:
    """The dotted name (``rosbag.calibration``, ``path[1]``) of the setting in a stage's
    settings ``data`` whose value is ``path``; None where none is (a file the stage derives,
    such as a model's external weights)."""
    if isinstance(data, str):
        return (prefix or None) if os.path.normpath(data) == os.path.normpath(path) else None
    if isinstance(data, dict):
        items: Iterable[tuple[str, Any]] = ((f"{prefix}.{k}" if prefix else str(k), v)
                                            for k, v in data.items())
    elif isinstance(data, list):
        items = ((f"{prefix}[{i}]", v) for i, v in enumerate(data))
    else:
        return None
    for name, value in items:
        found = setting_holding(value, path, name)
        if found:
            return found
    return None


def missing_inputs(recipe: Recipe, stage_ids: Iterable[str] | None = None) -> list[str]:
    """One problem per external input (a recording, a model) of the named stages (all by
    default) that does not exist or is unusable (``Stage.input_problems``): found before
    hours of earlier stages, not after."""
    wanted = None if stage_ids is None else set(stage_ids)
    problems = []
    for spec in recipe.stages:
        if wanted is not None and spec.id not in wanted:
            continue
        try:
            stage = spec.cls(spec.config)
            paths = stage.external_inputs()
        except Exception:  # noqa: BLE001 - the stage reports it itself when it runs
            continue
        absent = [p for p in paths if not Path(p).exists()]
        for path in absent:
            relative = not Path(path).is_absolute()
            where = f" (relative to {Path.cwd()})" if relative else ""
            setting = setting_holding(config_data(spec.config), Path(path))
            fix = f"fix the stage's {setting!r} setting" if setting else "fix the path"
            if relative:
                fix += ", or run from the folder it is relative to"
            # A path made from an unset variable's default: setting the variable is the fix.
            made = [(name, default) for value, name, default in recipe.env_defaults
                    if os.path.normpath(value) == os.path.normpath(path)]
            if made:
                names = " and ".join(dict.fromkeys(name for name, _ in made))
                fix = (f"it comes from {', '.join(f'${{{n}:-{d}}}' for n, d in made)} with "
                       f"{names} unset: set {names} (e.g. export {made[0][0]}=/path/to/it), "
                       "or run from the folder the default is relative to")
            problems.append(f"{spec.label}: input {path} does not exist{where}; {fix}")
        if not absent:
            problems += [f"{spec.label}: {p}" for p in stage.input_problems()]
    return problems


def _cache_key(spec: StageSpec, stage: Stage, upstream: Mapping[str, str | None],
               leave_out: frozenset[str] = frozenset(),
               digests: FileDigests | None = None) -> str:
    external = [Path(p) for p in stage.external_inputs()]
    config = {k: v for k, v in config_data(spec.config).items() if k not in leave_out}
    # The files a stage reads by the folder-independent path: the same bag named from
    # another folder (or absolutely) is the same input, not "settings changed". A file
    # keyed by content is named by its digest alone: its path is no part of the key.
    named: dict[Path, str] = {}
    fingerprints: list[dict[str, Any]] = []
    for p in external:
        if stage.external_by_content and p.is_file():
            sha = (digests or FileDigests(None)).sha256(p)
            named[p] = f"sha256:{sha}"
            fingerprints.append({"sha256": sha})
        else:
            named[p] = os.path.abspath(p)
            fingerprints.append(_fingerprint(p))
    payload = {
        "stage": spec.type,
        "version": getattr(stage, "version", 1),
        "config": _absolute_inputs(config, named),
        "upstream": dict(sorted(upstream.items())),
        "external": fingerprints,
    }
    text = json.dumps(payload, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _speed_values(spec: StageSpec) -> dict[str, Any]:
    """The stage's speed settings as this recipe gives them (plain data)."""
    data = config_data(spec.config)
    return {k: data.get(k) for k in sorted(spec.cls.speed_settings)}


def _finished_peak(peak: StagePeak) -> PeakMemory | None:
    # To 0.1 MiB, as the marker stores it: the report of the run that measured it then
    # shows the figure a cached run reads back (unrounded, 367.47 read 367 there and,
    # stored as 367.5, 368 once cached).
    got = peak.finish()
    return None if got is None else PeakMemory(round(got.mib, 1), got.how)


def _peak_fields(peak: PeakMemory | None) -> dict[str, Any]:
    if peak is None:
        return {}
    return {"peak_rss_mib": peak.mib, "peak_rss_how": peak.how}


def _stored_peak(stored: Mapping[str, Any]) -> PeakMemory | None:
    # Markers written before the peak was recorded have none.
    mib, how = stored.get("peak_rss_mib"), stored.get("peak_rss_how")
    if (not isinstance(mib, int | float) or isinstance(mib, bool)
            or how not in ("exact", "sampled", "bound")):
        return None
    return PeakMemory(float(mib), how)


def _cpu_seconds() -> float:
    """CPU time of this process (all threads) and its finished children: what a stage
    costs on a machine of its own, whatever else shares the cores."""
    if resource is None:
        return time.process_time()
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def _absolute_inputs(value: Any, inputs: Mapping[Path, str]) -> Any:
    """``value`` with every string naming one of ``inputs`` (as given) in its absolute
    form."""
    if isinstance(value, dict):
        return {k: _absolute_inputs(v, inputs) for k, v in value.items()}
    if isinstance(value, list):
        return [_absolute_inputs(v, inputs) for v in value]
    if isinstance(value, str) and value and Path(value) in inputs:
        return inputs[Path(value)]
    return value


def _fingerprint(path: Path) -> dict[str, Any]:
    """Size and mtime of a file (every file, for a folder): cheap, unlike hashing a bag."""
    path = Path(os.path.abspath(path))
    if path.is_dir():
        files, links = _walk_files(path)
        entries = [[p.relative_to(path).as_posix(), *_stat(p)] for p in sorted(files)]
        out: dict[str, Any] = {"path": str(path), "files": entries}
        if links:  # a link pointed at another recording is another input
            out["links"] = sorted([p.relative_to(path).as_posix(), t] for p, t in links)
        return out
    if path.exists():
        return {"path": str(path), "file": _stat(path)}
    return {"path": str(path), "missing": True}


def _walk_files(root: Path) -> tuple[list[Path], list[tuple[Path, str]]]:
    """Every file under ``root``, through linked folders too (a dataset laid out as
    ``images -> /big/disk/images``: Path.rglob does not enter them, and changes there kept
    every stage cached), each real folder once; and the folder links with their targets."""
    files: list[Path] = []
    links: list[tuple[Path, str]] = []
    seen: set[tuple[int, int]] = set()
    for top, dirs, names in os.walk(root, followlinks=True):
        st = os.stat(top)
        if (st.st_dev, st.st_ino) in seen:  # a link loop, or a folder reached twice
            dirs.clear()
            continue
        seen.add((st.st_dev, st.st_ino))
        for d in dirs:
            if os.path.islink(os.path.join(top, d)):
                links.append((Path(top, d), os.readlink(os.path.join(top, d))))
        files.extend(p for p in (Path(top, n) for n in names) if p.is_file())
    return files, links


def _stat(path: Path) -> list[int]:
    st = path.stat()
    return [st.st_size, st.st_mtime_ns]


class FileDigests:
    """SHA-256 of files, remembered in ``path`` (a JSON file; None: for this object's life
    only) by absolute path with the file's size, mtime, ctime and inode, and hashed again
    when any of those differ. The ctime and inode are there because size and mtime alone
    are kept by ``cp -p`` and ``rsync -a``: other weights of the same size copied over a
    model with their own mtime restored would otherwise keep the old digest."""

    def __init__(self, path: Path | None) -> None:
        self.path = path
        self.known: dict[str, list[Any]] = {}
        if path is not None:
            try:
                data = json.loads(path.read_text(encoding="utf-8"))
            except (OSError, ValueError):  # none yet, or unreadable: hash afresh
                data = {}
            if isinstance(data, dict):
                self.known = {k: v for k, v in data.items()
                              if isinstance(v, list) and len(v) == 5}

    def sha256(self, file: Path) -> str:
        """Hex SHA-256 of the bytes of ``file``."""
        file = Path(os.path.abspath(file))
        st = file.stat()
        stamp = [st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino]
        entry = self.known.get(str(file))
        if entry is not None and entry[:4] == stamp:
            return str(entry[4])
        digest = _file_sha256(file)
        self.known[str(file)] = [*stamp, digest]
        if self.path is not None:
            with contextlib.suppress(OSError):  # a cache: not written, the file is hashed again
                atomic_write_json(self.path, self.known)
        return digest


def _hash_bytes(h: Any, path: Path) -> None:
    """Feed the bytes of file ``path`` to hash ``h``, a megabyte at a time."""
    with path.open("rb") as fh:
        while chunk := fh.read(1 << 20):
            h.update(chunk)


def _read_marker(
    stage_dir: Path, key: str, provides: tuple[str, ...]
) -> tuple[dict[str, Any] | None, str]:
    """The stored ``.stage.json`` if it proves the stage complete, else None; and why."""
    marker = stage_dir / STAGE_FILE
    if not marker.exists():
        if not stage_dir.exists():
            return None, "never ran"
        return None, _FAILED if _started_failed(stage_dir / STARTED_FILE) else _UNFINISHED
    try:
        data = json.loads(marker.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None, f"unreadable {STAGE_FILE}"
    if not isinstance(data, dict) or data.get("key") != key:
        return None, "settings or inputs changed"
    stored = data.get("provides")
    if not isinstance(stored, dict) or not set(provides) <= set(stored):
        return None, "settings or inputs changed"
    wrong = _marker_shape_problem(data)
    if wrong:
        # Read as it is, it stopped the whole run with a traceback; rerunning the stage
        # writes a good one.
        return None, f"unreadable {STAGE_FILE} ({wrong})"
    missing = [name for name, rel in stored.items() if not (stage_dir / rel).exists()]
    if missing:
        return None, f"output {missing[0]!r} is missing"
    # Markers written before manifests existed are trusted by the paths alone, those
    # before per-file digests by the sizes alone.
    digests = data.get("manifest_digests")
    digests = digests if isinstance(digests, dict) else {}
    moved = False
    for name, files in (data.get("manifest") or {}).items():
        if name not in stored:
            continue
        changed, refreshed = _manifest_changes(stage_dir / stored[name], files,
                                               digests.get(name))
        if changed:
            return None, f"output {name!r}: {changed}"
        if refreshed is not None:
            digests[name], moved = {**digests[name], "mtime_ns": refreshed}, True
    # The stage's own files its report links to (figures outside its artifacts, such as
    # simulate/preview.png): a lost one reruns the stage, not a report with a dead link.
    for target in _REPORT_LINK_RE.findall(str(data.get("report") or "")):
        if target.startswith(f"{stage_dir.name}/") and not (stage_dir.parent / target).exists():
            return None, f"report file {target!r} is missing"
    if moved:
        # Same bytes under new mtimes (a copied run folder): stored, so the next run does
        # not hash them again. A cache: a folder that cannot be written hashes next time.
        with contextlib.suppress(OSError):
            atomic_write_json(marker, {**data, "manifest_digests": digests}, fsync=True,
                              compact=True)
    return data, "up to date"


def _marker_shape_problem(data: Mapping[str, Any]) -> str | None:
    """What in a parsed finish marker is not of the type the runner reads it as (a hand
    edit, a flipped bit that still parses), or None; fields a marker from before lacks
    may be absent."""
    def number(v: Any) -> bool:
        return isinstance(v, int | float) and not isinstance(v, bool)

    if not all(isinstance(k, str) and isinstance(v, str) for k, v in data["provides"].items()):
        return "'provides' must map output names to paths"
    manifest = data.get("manifest")
    if manifest is not None:
        if not isinstance(manifest, dict):
            return "'manifest' must be a mapping"
        for files in manifest.values():
            if not isinstance(files, list) or not all(
                    isinstance(e, list) and len(e) >= 2 and isinstance(e[0], str)
                    and number(e[1]) for e in files):
                return "'manifest' must list [path, size] per file"
    for name, kind in (("metrics", dict), ("output_tokens", dict), ("report", str),
                       ("speed_settings", dict), ("manifest_digests", dict)):
        if data.get(name) is not None and not isinstance(data[name], kind):
            return f"{name!r} must be a {'mapping' if kind is dict else 'text'}"
    for name in ("seconds", "cpu_seconds"):
        if data.get(name) is not None and not number(data[name]):
            return f"{name!r} must be a number"
    return None


_REPORT_LINK_RE = re.compile(r"\]\(([^)\s]+)\)")  # [text](target) and ![alt](target)


def _read_started(path: Path) -> dict[str, Any]:
    """The started marker ``path`` as a mapping (empty: none, or unreadable)."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def _started_folder_key(path: Path) -> str | None:
    """The folder key in a started marker (None: no readable one)."""
    key = _read_started(path).get("folder_key")
    return str(key) if key else None


def _mark_started_failed(path: Path, error: str) -> None:
    """Record in the started marker ``path`` that the stage failed with ``error``."""
    data = _read_started(path)
    if data:
        # An unwritable folder: the next run reports the stage as unfinished.
        with contextlib.suppress(OSError):
            atomic_write_json(path, {**data, "failed": error}, fsync=True)


def _started_failed(path: Path) -> bool:
    """True when the started marker ``path`` records a failure (_mark_started_failed)."""
    return bool(_read_started(path).get("failed"))


def _manifest(path: Path) -> list[list[Any]]:
    """[[relative path, size], ...] of an output (every file of a folder): what a later run
    checks before it trusts the output (a deleted map inside a provided folder)."""
    if path.is_dir():
        # Hidden files are the runner's markers (a stage may provide its own folder) and
        # leftover temporaries of killed writes: not outputs.
        files = []
        for p in sorted(path.rglob("*")):
            rel = p.relative_to(path).as_posix()
            if p.is_file() and not any(part.startswith(".") for part in rel.split("/")):
                files.append([rel, p.stat().st_size])
        return files
    return [[".", path.stat().st_size]] if path.exists() else []


def _content_digest(path: Path) -> str:
    """SHA-256 of an output's content: a file's name and bytes, or a folder's files (names,
    sizes and bytes, in name order; the runner's markers left out). Empty where a folder
    holds a symbolic link: what it points to may change without the link changing, so such
    an output keeps its run token."""
    return _digest_output(path)[0]


def _digest_output(
    path: Path, token: bool = True
) -> tuple[str, list[list[Any]], dict[str, list[Any]]]:
    """An output's content digest (``_content_digest``'s; "" when ``token`` is False), its
    manifest (``_manifest``'s) and, aligned with it, each file's mtime and SHA-256
    (``{"mtime_ns": [...], "sha256": [...]}``: two flat lists, not a list per file, keep
    an hour's marker small to hold and to write), from one read of each file, a megabyte
    at a time: an hour's depth maps are read once and never held whole."""
    whole = hashlib.sha256()
    if path.is_file():
        files = [path]
    else:
        entries = sorted(path.rglob("*"))
        if any(p.is_symlink() for p in entries):
            token = False
        files = [p for p in entries if p.is_file() and p.name not in _MARKERS]
    manifest: list[list[Any]] = []
    mtimes: list[int] = []
    shas: list[str] = []
    for f in files:
        rel = "." if f == path else f.relative_to(path).as_posix()
        # The manifest's files: hidden ones are temporaries or the stage's bookkeeping.
        in_manifest = rel == "." or not any(part.startswith(".") for part in rel.split("/"))
        if not (token or in_manifest):
            continue
        own = hashlib.sha256()
        with f.open("rb") as fh:
            st = os.fstat(fh.fileno())
            if token:
                whole.update(f"{f.name if rel == '.' else rel}\0{st.st_size}\0".encode())
            while chunk := fh.read(1 << 20):
                own.update(chunk)
                if token:
                    whole.update(chunk)
        if in_manifest:
            manifest.append([rel, st.st_size])
            mtimes.append(st.st_mtime_ns)
            shas.append(own.hexdigest())
    return ((whole.hexdigest() if token else ""), manifest,
            {"mtime_ns": mtimes, "sha256": shas})


def _file_sha256(path: Path) -> str:
    """Hex SHA-256 of the bytes of ``path``."""
    h = hashlib.sha256()
    _hash_bytes(h, path)
    return h.hexdigest()


def _is_input_error(exc: BaseException) -> bool:
    """Whether ``exc`` says what is wrong with an input, so that the runner shows its
    message alone: one of ``toolkit.errors``' classes (InputError, MissingInputError,
    WriteError; each area's own, such as CalibrationFileError or BagError, subclasses one
    of them), whose messages start with the path they are about and say the fix; a
    RecipeError; or an OSError naming its file. Anything else is taken for a bug and keeps
    its class name beside the traceback in run.log: numpy's "operands could not be
    broadcast", a KeyError, a ValueError whose message starts with a path (the class
    decides, not the message), and the project's internal errors (StageError never gets
    here; NotATransformError, which its readers turn into a BagError naming the topic)."""
    if isinstance(exc, InputError | MissingInputError | WriteError | RecipeError):
        return True
    return isinstance(exc, OSError) and exc.filename is not None


def _is_write_failure(exc: OSError, stage_dir: Path) -> bool:
    """Whether ``exc`` is a write the user can make work (free space, a permission):
    a full disk or quota, a read-only filesystem, or no permission in the stage's own
    folder (elsewhere it may be an input that cannot be read)."""
    if not exc.filename:
        return False
    if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EROFS):
        return True
    target = Path(os.path.abspath(target_of(exc.filename)))
    return exc.errno in (errno.EACCES, errno.EPERM) and Path(
        os.path.abspath(stage_dir)) in target.parents


def _digest_failure(exc: Exception) -> str:
    """What went wrong digesting a finished stage's outputs, what it costs and the fix."""
    cost = ("the stage stays finished, its files are checked by size alone (not for an "
            "edit in place), and the stages reading its outputs rerun after any rerun of it, "
            "even one that writes the same bytes")
    if isinstance(exc, OSError) and exc.filename:
        return (f"{exc.filename}: {exc.strerror or exc}; {cost}. Check that file (its "
                f"permissions, the disk) before the stage's next rerun")
    lines = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {lines[0] if lines else ''}; {cost}"


def _manifest_changes(
    path: Path, files: list[list[Any]], digests: Any = None
) -> tuple[str | None, list[int] | None]:
    """What differs from a stored manifest: the first missing, resized or edited file;
    and, when nothing did but files had new mtimes, the mtimes to store.

    ``digests``: ``{"mtime_ns": [...], "sha256": [...]}`` aligned with ``files`` (None: a
    marker from before them, checked by size alone). A file of the same size and mtime
    is trusted unread, as ``make`` does; one whose mtime moved is hashed (``cp -r``, a
    checkout and ``touch`` move it without changing a byte)."""
    mtimes = shas = None
    if isinstance(digests, dict):
        mtimes, shas = digests.get("mtime_ns"), digests.get("sha256")
    if not (isinstance(mtimes, list) and isinstance(shas, list)
            and len(mtimes) == len(shas) == len(files)):
        mtimes = shas = None
    fresh: list[int] | None = None
    for i, (rel, size, *_) in enumerate(files):
        f = path if rel == "." else path / rel
        try:
            st = f.stat()
        except OSError:
            return f"{f} is missing", None
        if st.st_size != size:
            return f"{f} changed size ({size} -> {st.st_size} bytes)", None
        if mtimes is None or shas is None or st.st_mtime_ns == mtimes[i]:
            continue
        try:
            same = _file_sha256(f) == shas[i]
        except OSError as exc:
            return f"{f} could not be read ({exc.strerror or exc})", None
        if not same:
            return f"{f} {_CHANGED}", None
        if fresh is None:
            fresh = list(mtimes)
        fresh[i] = st.st_mtime_ns
    return None, fresh


def _relative(path: Path, stage_dir: Path) -> str:
    return path.relative_to(stage_dir).as_posix() or "."


def _deep_merge(into: dict[str, Any], new: Mapping[str, Any]) -> None:
    for key, value in new.items():
        if isinstance(value, Mapping) and isinstance(into.get(key), dict):
            _deep_merge(into[key], value)
        else:
            into[key] = dict(value) if isinstance(value, Mapping) else value


@contextlib.contextmanager
def _exclusive(run_dir: Path) -> Iterator[None]:
    """Hold a lock on the run folder so two runs of one recipe cannot interleave."""
    if fcntl is None:
        yield
        return
    try:
        handle = open(run_dir / LOCK_FILE, "a")  # closed by the with below
    except OSError as exc:  # a read-only run folder (or lock file): say so, not just errno
        raise RecipeError(f"output: cannot write in the run folder {run_dir} ({exc}); make "
                          "it writable, or set 'output' to another folder (nothing was "
                          "changed)") from None
    with handle:
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise RecipeError(f"{run_dir} is in use by another run; wait for it to "
                                  "end") from None
            raise RecipeError(f"{run_dir}: cannot lock {LOCK_FILE} ({exc.strerror or exc}): "
                              "this filesystem does not support file locks (some network "
                              "or FUSE mounts); set 'output' to a folder on a local disk"
                              ) from None
        yield


@contextlib.contextmanager
def _run_logging(run_dir: Path, console: Console) -> Iterator[logging.Logger]:
    """Send the ``toolkit`` loggers to run.log and the console for the length of a run."""
    base = logging.getLogger("toolkit")
    to_file = logging.FileHandler(run_dir / LOG_FILE, encoding="utf-8")
    to_file.setFormatter(logging.Formatter("%(asctime)s %(levelname)-7s %(name)s: %(message)s"))
    to_console = RichHandler(console=console, show_path=False, markup=False)
    to_console.setLevel(logging.INFO)
    to_console.addFilter(lambda record: getattr(record, "console", True))
    old_level = base.level
    if base.getEffectiveLevel() > logging.INFO:
        base.setLevel(logging.INFO)
    base.addHandler(to_file)
    base.addHandler(to_console)
    try:
        yield logging.getLogger("toolkit.recipe.runner")
    finally:
        base.removeHandler(to_console)
        base.removeHandler(to_file)
        to_file.close()
        base.setLevel(old_level)

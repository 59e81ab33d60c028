"""The contract between the recipe runner and the stages it runs.

A stage is a class with a pydantic ``Config`` (one per stage type, unknown keys
rejected), a one-line docstring shown by ``python -m toolkit.recipe list``, the
artifacts it ``requires`` from earlier stages and the ones it ``provides``, and a
``run(ctx)`` that does the work inside ``ctx.stage_dir``.

Artifacts are named paths inside a stage's folder ("sequence", "trajectory",
"depth", "map", ...). The runner resolves ``ctx.artifact(name)`` to the path the
nearest earlier stage provided, and caches a stage by hashing its settings together
with a digest of the content of the artifacts it draws (and the fingerprints of the
external files it names in ``external_inputs``, or their content digests with
``external_by_content``), so changing one stage reruns exactly
what reads an output that changed. A stage therefore reads of an earlier stage only the
paths ``ctx.artifact`` gives and what lies under them, never files beside them.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, TypeVar

from pydantic import BaseModel, ConfigDict, Field

T = TypeVar("T")


class StageConfig(BaseModel):
    """Base of every stage's settings. Unknown keys are errors, not silently ignored."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    stage: str
    # Folder and --set name of this stage in the run; defaults to the stage type, set it
    # when a recipe runs one stage type twice (e.g. two scale estimators side by side).
    id: str | None = None
    # Artifact name -> id of the earlier stage to take it from, when the nearest earlier
    # stage that provides it is not the one meant (a benchmark that runs two depth stages
    # and fuses each: ``inputs: {depth: depth_network}``); null leaves an optional artifact
    # out (``inputs: {tsdf_mesh: null}``: evaluate this row without a TSDF mesh).
    inputs: dict[str, str | None] = Field(default_factory=dict)


@dataclass(frozen=True)
class StageResult:
    """What a finished earlier stage left: for stages that tabulate other stages' results."""

    id: str
    type: str
    metrics: dict[str, Any]
    seconds: float | None
    cpu_seconds: float | None
    stage_dir: Path
    provides: dict[str, Path] = field(default_factory=dict)


class StageContext(ABC):
    """What a running stage may use: its folder, upstream artifacts, metrics, report."""

    run_dir: Path
    stage_dir: Path
    stage_id: str
    recipe_name: str
    log: logging.Logger
    # This run's cache key of the stage (settings, upstream keys, external files).
    cache_key: str = ""
    # The key to keep partial work under (checkpoints, journals): a killed run's work left
    # in stage_dir under the same key may be resumed. The cache key without the stage's
    # ``resume_settings`` (the same key for stages without any).
    resume_key: str = ""

    @abstractmethod
    def artifact(self, name: str) -> Path:
        """Path of artifact ``name`` provided by the nearest earlier stage: read what lies
        under it only (its content is what this stage's cache key holds).

        Raises a ``StageError`` naming the artifact and which stage types provide it.
        """

    @abstractmethod
    def has_artifact(self, name: str) -> bool:
        """Whether an earlier stage of this run provides ``name``."""

    @abstractmethod
    def provide(self, name: str, path: Path) -> None:
        """Publish ``path`` (inside ``stage_dir``) as artifact ``name`` for later stages."""

    @abstractmethod
    def add_metrics(self, metrics: dict[str, Any]) -> None:
        """Merge figures into ``metrics.json`` under this stage's id (units in key names)."""

    @abstractmethod
    def report(self, markdown: str) -> None:
        """Append markdown to this stage's section of ``report.md``.

        Paths to images should be relative to the run directory (``stage_id/plot.png``).
        """

    def stage_result(self, stage_id: str) -> StageResult:
        """Metrics, timing and artifacts of earlier stage ``stage_id``; only for the ids the
        stage declares in ``reads_results`` (they join its cache key)."""
        raise StageError(f"stage {self.stage_id!r}: this runner does not give stage results")

    @abstractmethod
    def progress(
        self, iterable: Iterable[T], total: int | None = None, description: str = ""
    ) -> Iterator[T]:
        """Wrap a long loop in a progress bar (quiet when not on a terminal)."""


class StageError(RuntimeError):
    """A stage cannot run: bad input, missing artifact. The message says what to fix."""


class Stage(ABC):
    """One step of a recipe. Subclasses set ``name``, ``Config``, ``requires``, ``provides``."""

    name: ClassVar[str]
    Config: ClassVar[type[StageConfig]]
    requires: ClassVar[tuple[str, ...]] = ()
    # Artifacts needed only when present upstream (e.g. "trajectory" for fuse may come
    # from slam2d or from ground truth); they join the cache key when they exist.
    optional_requires: ClassVar[tuple[str, ...]] = ()
    provides: ClassVar[tuple[str, ...]] = ()
    # Bump when a code change alters what the stage writes, so cached results rerun.
    version: ClassVar[int] = 1
    # Settings whose change leaves an interrupted run's files valid for the stage to resume
    # from (thread count, iteration count): a finished stage reruns when they change (they
    # are in its cache key), but an interrupted one keeps its folder.
    resume_settings: ClassVar[frozenset[str]] = frozenset()
    # Settings that change only how fast the stage runs, never what it writes (thread
    # count, device, prefetching): left out of the cache key, so a finished stage stays
    # cached when they change (rerunning an hour of depth, and every stage after it, for
    # a thread count was the cost); ``--force`` / ``--only`` rerun it for its timings.
    speed_settings: ClassVar[frozenset[str]] = frozenset()
    # A rerun under the same settings and inputs writes the same bytes: a later stage
    # reading an output whose digest did not change stays cached. False for a stage whose
    # outputs hold timings (depth's per-frame latencies, colmap's step times): they take a
    # token of the run instead (their files are still digested one by one, for the check
    # of an edit in place; runner.digest_outputs). The contract that
    # makes this safe: a stage reads of an earlier stage only the paths it is given
    # (``ctx.artifact``) and what lies under them, never files beside them.
    outputs_repeat: ClassVar[bool] = True
    # External input files are keyed by their content (SHA-256), not by where they lie and
    # when they were written: a depth model moved with its checkout (another folder, a git
    # worktree, a colleague's copy) stays cached, and one replaced in place by other
    # weights of the same size and time reruns. Folders keep the cheap size-and-time
    # fingerprint (hashing a recording of gigabytes every run is the cost it avoids).
    external_by_content: ClassVar[bool] = False

    def __init__(self, config: StageConfig) -> None:
        self.config = config

    @classmethod
    def reads_results(cls, config: StageConfig) -> tuple[str, ...]:
        """Ids of earlier stages whose results (``ctx.stage_result``) this stage reads."""
        return ()

    def external_inputs(self) -> list[Path]:
        """Files outside the run (a log, a model) whose change must rerun the stage."""
        return []

    def input_problems(self) -> list[str]:
        """What is wrong with existing ``external_inputs`` beyond their existence (a folder
        where a file is needed), found before earlier stages run; one line each."""
        return []

    @abstractmethod
    def run(self, ctx: StageContext) -> None:
        """Do the work, writing only inside ``ctx.stage_dir`` (atomically)."""

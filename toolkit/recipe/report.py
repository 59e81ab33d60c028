"""Assembly of a run's ``report.md``, ``metrics.json`` and timing table.

Both files are rebuilt whole from per-stage parts each time, never appended to, so a
rerun or a resumed run cannot duplicate a section.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rich.table import Table

from toolkit.io.atomic import atomic_write_json, atomic_write_text
from toolkit.recipe.memory import PeakMemory

REPORT_FILE = "report.md"
METRICS_FILE = "metrics.json"


@dataclass(frozen=True)
class StageSummary:
    """What the report and the timing table show about one stage."""

    id: str
    type: str
    status: str  # ran | cached | failed | pending | not run
    seconds: float | None = None
    cpu_seconds: float | None = None
    peak: PeakMemory | None = None
    markdown: str = ""
    # Not run this time, but its folder holds an earlier run's files (of other settings or
    # inputs): the report says so, lest they be taken for this run's.
    stale_files: bool = False


def stage_heading(stage_id: str, stage_type: str) -> str:
    """Section heading: the id, plus the type when a recipe renamed the stage."""
    return stage_id if stage_id == stage_type else f"{stage_id} ({stage_type})"


def _seconds(value: float | None) -> str:
    return "" if value is None else f"{value:.1f}"


def _load(s: StageSummary) -> str:
    if s.seconds is None or s.cpu_seconds is None or s.seconds <= 0:
        return ""
    return f"{100.0 * s.cpu_seconds / s.seconds:.0f} %"


def _peak(peak: PeakMemory | None) -> str:
    return "" if peak is None else peak.text()


def timing_rows(stages: Sequence[StageSummary]) -> list[tuple[str, str, str, str, str, str]]:
    """(stage, status, seconds, CPU seconds, CPU load, peak memory MiB) rows, with a total
    over the stages that have a time (its peak: the largest). CPU load is CPU time over
    wall time (100 % = one core busy)."""
    rows = [(s.id, s.status, _seconds(s.seconds), _seconds(s.cpu_seconds), _load(s),
             _peak(s.peak)) for s in stages]
    timed = [s for s in stages if s.seconds is not None]
    total = sum(s.seconds for s in timed)  # type: ignore[misc]
    with_cpu = [s for s in timed if s.cpu_seconds is not None]
    cpu = sum(s.cpu_seconds for s in with_cpu) if with_cpu else None  # type: ignore[misc]
    wall_cpu = sum(s.seconds for s in with_cpu)  # type: ignore[misc]
    load = StageSummary("", "", "", wall_cpu, cpu)
    peaks = [s.peak for s in stages if s.peak is not None]
    top = max(peaks, key=lambda p: p.mib) if peaks else None
    rows.append(("total", "", _seconds(total), _seconds(cpu), _load(load), _peak(top)))
    return rows


def build_report(
    title: str,
    stages: Sequence[StageSummary],
    description: str = "",
    error: str | None = None,
    interrupted: str | None = None,
) -> str:
    """The whole ``report.md``: title, finished stages' sections in order, timing table;
    ``error`` names a failed stage, ``interrupted`` a run stopped after a stage finished."""
    parts = [f"# {title}"]
    if description:
        parts.append(description.strip())
    parts.append("Settings: [recipe.resolved.yaml](recipe.resolved.yaml) · log: [run.log](run.log)")
    for stage in stages:
        if stage.status in ("ran", "cached") and stage.markdown.strip():
            parts.append(f"## {stage_heading(stage.id, stage.type)}\n\n{stage.markdown.strip()}")
    table = ["| stage | status | seconds | CPU seconds | CPU load | peak memory (MiB) |",
             "|---|---|---:|---:|---:|---:|"]
    table += ["| " + " | ".join(row) + " |" for row in timing_rows(stages)]
    timing = "## Timing\n\n" + "\n".join(table)
    timing += ("\n\nCached stages show the time of the run that computed them. CPU load = "
               "CPU time / wall time, 100 % = one core. Peak memory: the process's "
               "largest resident set while the stage ran (MiB = 2^20 bytes), exact where "
               "the stage raised the run's peak, \"~\" sampled every 20 ms otherwise, "
               "\"<=\" the run's peak so far where memory cannot be sampled.")
    parts.append(timing)
    if error:
        parts.append(f"**Failed:** {error} (details in run.log)")
    if interrupted:
        parts.append(f"**Stopped:** {interrupted}.")
    stale = [f"`{s.id}`" for s in stages if s.status == "not run" and s.stale_files]
    if stale:
        parts.append(f"**Not run this time:** {', '.join(stale)}: "
                     f"{'their folders hold' if len(stale) > 1 else 'its folder holds'} the "
                     "files of an earlier run, made before its settings, its inputs or an "
                     "upstream stage's output changed - not results of this one.")
    return "\n\n".join(parts) + "\n"


def write_report(run_dir: Path, text: str) -> None:
    """Replace ``run_dir/report.md``."""
    atomic_write_text(run_dir / REPORT_FILE, text)


def write_metrics(run_dir: Path, metrics: Mapping[str, Mapping[str, Any]]) -> None:
    """Replace ``run_dir/metrics.json`` with ``{stage_id: {...}}`` in recipe order."""
    atomic_write_json(run_dir / METRICS_FILE, dict(metrics))


_STYLES = {"ran": "green", "cached": "cyan", "failed": "bold red", "not run": "dim"}


def timing_table(stages: Sequence[StageSummary], title: str = "Timing") -> Table:
    """The timing table for the terminal."""
    table = Table(title=title, title_justify="left")
    table.add_column("stage")
    table.add_column("status")
    table.add_column("seconds", justify="right")
    table.add_column("CPU s", justify="right")
    table.add_column("CPU load", justify="right")
    table.add_column("peak MiB", justify="right")
    rows = timing_rows(stages)
    for index, (stage, status, seconds, cpu, load, peak) in enumerate(rows):
        if index == len(rows) - 1:
            table.add_section()
        style = _STYLES.get(status, "")
        table.add_row(stage, f"[{style}]{status}[/]" if style else status, seconds, cpu, load,
                      peak)
    return table

"""Command line: ``python -m toolkit.recipe run|validate|list|doctor``.

Exit codes: 0 success, 1 a stage failed (``doctor``: a required part is missing), 2 the
recipe or the command line is wrong (nothing ran), 130 interrupted.
"""

from __future__ import annotations

import argparse
import shlex
import signal
import sys
from collections.abc import Sequence

from toolkit.cli_types import INTERRUPTED, sigterm_as_interrupt
from toolkit.recipe import registry
from toolkit.recipe.runner import StoppedAfterStage, missing_inputs, run_recipe
from toolkit.recipe.schema import Recipe, RecipeError, load_recipe


def build_parser() -> argparse.ArgumentParser:
    """The argument parser (exposed for docs and tests)."""
    parser = argparse.ArgumentParser(
        prog="python -m toolkit.recipe",
        description="Run YAML recipes of reconstruction stages, with caching and resume.",
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    set_help = (
        "override a setting: <stage id>.<key>[.<subkey>]=VALUE, or name=/output=; "
        "VALUE is YAML (repeatable)"
    )
    run = commands.add_parser("run", help="run a recipe, reusing stages that are up to date")
    run.add_argument("file", metavar="FILE", help="recipe YAML file")
    run.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help=set_help)
    which = run.add_mutually_exclusive_group()
    which.add_argument(
        "--from",
        dest="from_stage",
        metavar="STAGE",
        help="rerun this stage and every stage after it (earlier ones must be complete)",
    )
    which.add_argument(
        "--only",
        metavar="STAGE",
        help="rerun only this stage (the stages it takes artifacts from must be complete)",
    )
    run.add_argument("--force", action="store_true", help="rerun selected stages even if cached")

    validate = commands.add_parser("validate", help="check a recipe without running it")
    validate.add_argument("file", metavar="FILE", help="recipe YAML file")
    validate.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help=set_help)

    commands.add_parser("list", help="list the stage types a recipe may use")
    doctor = commands.add_parser(
        "doctor", help="check what this installation can run (packages, C++ and GPU paths)")
    doctor.add_argument("--build", action="store_true",
                        help="build the splat rasterisers now (C++: ~1 min; gsplat on a GPU: "
                        "minutes) instead of saying the first run will")
    doctor.add_argument("--json", action="store_true", help="print JSON (for bug reports)")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    args = build_parser().parse_args(argv)
    try:
        if args.command == "list":
            return _list()
        if args.command == "doctor":
            return _doctor(build=args.build, as_json=args.json)
        recipe = load_recipe(args.file, args.set)
        if args.command == "validate":
            problems = missing_inputs(recipe)
            if problems:
                raise RecipeError(problems)
            _describe(recipe)
            return 0
        # A `kill` or a scheduler's preemption still writes the report and metrics of the
        # finished stages before the process exits.
        previous = sigterm_as_interrupt()
        try:
            result = run_recipe(
                recipe, force=args.force, from_stage=args.from_stage, only=args.only
            )
        finally:
            if previous is not None:
                signal.signal(signal.SIGTERM, previous)
        return 0 if result.ok else 1
    except RecipeError as exc:
        for problem in exc.problems:
            # A stage's problem names its place in the recipe; say which recipe too.
            where = f"{args.file}: " if problem.startswith("stages[") else ""
            print(f"error: {where}{problem}", file=sys.stderr)
        return 2
    except OSError as exc:  # the run's own files (report, metrics) could not be written
        print(f"error: {_write_error(exc)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt as exc:
        print(f"interrupted; {_resume_advice(args, exc)}", file=sys.stderr)
        return INTERRUPTED


def _write_error(exc: OSError) -> str:
    """An OSError from writing the run's own files, naming the file meant (not the hidden
    temporary of its atomic write) and the fix."""
    if not exc.filename:
        return str(exc)
    from toolkit.io.atomic import write_failure

    return f"{write_failure(exc)}; the finished stages are kept"


def _resume_advice(args: argparse.Namespace, exc: KeyboardInterrupt) -> str:
    """The command that goes on with an interrupted run.

    ``--force`` and ``--from`` rerun finished stages, so they are dropped (a plain run takes
    up from the stage that stopped, the earlier ones cached); ``--only X`` is kept: without
    ``--force`` it resumes X in its folder, where a plain run would also run every other
    stale stage."""
    only = getattr(args, "only", None)
    if isinstance(exc, StoppedAfterStage) and only == exc.stage:
        return f"stage {only!r} had finished: nothing is left to resume"
    if not (getattr(args, "force", False) or getattr(args, "from_stage", None)):
        return "run the same command to resume"
    words = ["python", "-m", "toolkit.recipe", "run", args.file]
    for item in args.set:
        words += ["--set", item]
    if only:
        words += ["--only", only]
    return (f"run {shlex.join(words)} to resume (without --force or --from, which would "
            "redo finished stages)")


def _doctor(build: bool, as_json: bool) -> int:
    import json

    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    from toolkit.recipe import doctor

    checks = doctor.collect(build=build)
    summary = doctor.as_dict(checks)
    if as_json:
        print(json.dumps(summary, indent=2))
    else:
        table = Table(title="lidarcam-recon doctor", title_justify="left")
        for column in ("part", "status", "detail", "fix"):
            table.add_column(column, overflow="fold")
        style = {"ok": "green", "note": "yellow", "missing": "bold red"}
        for c in checks:
            # Escaped: a fix such as pip install -e '.[cuda]' is not rich markup.
            table.add_row(escape(c.part), f"[{style[c.status]}]{c.status}[/]",
                          escape(c.detail), escape(c.fix))
        Console().print(table)
        missing = [c.part for c in checks if c.status == "missing"]
        print(f"missing: {', '.join(missing)}" if missing
              else "every required part works")
    return 0 if summary["ok"] else 1


def _list() -> int:
    names = registry.stage_names()
    if not names:
        print("no stages registered")
        return 0
    width = max(len(n) for n in names)
    for name in names:
        try:
            doc = registry.summary(registry.load_stage(name))
        except ImportError as exc:
            doc = f"(unavailable: {exc})"
        print(f"{name:<{width}}  {doc}".rstrip())
    return 0


def _describe(recipe: Recipe) -> None:
    # Plain print: one line per stage, unwrapped, so it can be grepped.
    print(f"recipe {recipe.name!r} is valid: {len(recipe.stages)} stage(s) -> {recipe.output}")
    for spec in recipe.stages:
        uses = ", ".join(f"{name} <- {src}" for name, src in spec.sources.items())
        line = f"  {spec.id} ({spec.type})"
        if uses:
            line += f"  uses: {uses}"
        if spec.cls.provides:
            line += f"  provides: {', '.join(spec.cls.provides)}"
        print(line)

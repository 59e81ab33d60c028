"""The stage types a recipe may name, imported only when a recipe (or ``list``) uses them.

Entries are strings, not classes, so that ``import toolkit.recipe`` stays cheap: a stage
module may pull in torch or open3d, and validating a recipe that does not use it must not
pay for that.
"""

from __future__ import annotations

import importlib
import os

from toolkit.recipe.stage import Stage

# Stage type name -> "module.path:ClassName". One line per stage, alphabetical.
STAGES: dict[str, str] = {
    "calibrate": "calibration.stage:CalibrateStage",
    "camera_only": "toolkit.baselines.stage:CameraOnlyStage",
    "colmap": "toolkit.baselines.stage:ColmapStage",
    "depth": "toolkit.depth.stage:DepthStage",
    "evaluate": "toolkit.eval.stage:EvaluateStage",
    "fuse": "toolkit.fusion.stage:FuseStage",
    "ingest": "toolkit.ingest.stage:IngestStage",
    "paper_tables": "toolkit.eval.paper_tables:PaperTablesStage",
    "simulate": "toolkit.sim.stage:SimulateStage",
    "slam2d": "toolkit.slam2d.stage:Slam2DStage",
    "splat": "toolkit.splat.stage:SplatStage",
    "tsdf": "toolkit.baselines.stage:TSDFStage",
}

# Extra stages outside the toolkit (plugins, and the test suite's own tiny stages when it
# drives the CLI in a subprocess): "name=module:Class,name2=module:Class2".
ENV_VAR = "TOOLKIT_RECIPE_STAGES"

# Classes registered in-process with ``register`` (tests); these win over everything else.
_registered: dict[str, type[Stage]] = {}


def register(name: str, cls: type[Stage]) -> None:
    """Make ``cls`` available as stage type ``name`` in this process (meant for tests)."""
    if not (isinstance(cls, type) and issubclass(cls, Stage)):
        raise TypeError(f"{cls!r} is not a Stage subclass")
    _registered[name] = cls


def unregister(name: str) -> None:
    """Undo ``register(name, ...)``; unknown names are ignored."""
    _registered.pop(name, None)


def _env_entries() -> dict[str, str]:
    entries: dict[str, str] = {}
    for item in os.environ.get(ENV_VAR, "").split(","):
        name, sep, target = item.strip().partition("=")
        if sep and name.strip() and target.strip():
            entries[name.strip()] = target.strip()
    return entries


def stage_names() -> list[str]:
    """Every stage type a recipe may name, sorted."""
    return sorted({*STAGES, *_env_entries(), *_registered})


def load_stage(name: str) -> type[Stage]:
    """The class of stage type ``name``.

    Raises ``KeyError`` for a name nobody registered and ``ImportError`` (naming the
    entry) when its module cannot be imported, e.g. an optional dependency is missing.
    """
    if name in _registered:
        return _registered[name]
    target = _env_entries().get(name) or STAGES.get(name)
    if target is None:
        raise KeyError(name)
    module_name, _, attr = target.partition(":")
    try:
        obj = getattr(importlib.import_module(module_name), attr)
    except (ImportError, AttributeError) as exc:
        raise ImportError(f"cannot load stage {name!r} from {target!r}: {exc}") from exc
    if not (isinstance(obj, type) and issubclass(obj, Stage)):
        raise ImportError(f"stage {name!r}: {target!r} is not a Stage subclass")
    return obj


def summary(cls: type) -> str:
    """First line of the class docstring: the one-line description ``list`` shows."""
    doc = (cls.__doc__ or "").strip()
    return doc.splitlines()[0].strip() if doc else ""


def providers_of(artifact: str) -> list[str]:
    """Stage types that declare ``artifact`` in ``provides`` (for error hints).

    Imports every registered stage, so only call it on an error path; stages that fail
    to import are skipped rather than turning a hint into a crash.
    """
    names = []
    for name in stage_names():
        try:
            cls = load_stage(name)
        except ImportError:
            continue
        if artifact in cls.provides:
            names.append(name)
    return names

"""Recipe files: YAML parsing, ``--set`` overrides, and validation whose messages name the path.

Everything that can be checked without running anything is checked here, so that a typo
in the last stage of a long recipe fails in a second instead of after an hour of SLAM.
"""

from __future__ import annotations

import builtins
import difflib
import io
import json
import os
import re
import shlex
import types
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ValidationError

from toolkit.recipe import registry
from toolkit.recipe.stage import Stage, StageConfig

TOP_LEVEL_KEYS = ("name", "output", "description", "stages")
# Keys that --set may change at the top of a recipe (``stages`` is edited per stage id).
_TOP_LEVEL_SETTABLE = ("name", "output", "description")
# An id names a folder and is the first part of a --set key, so no dots or slashes.
_ID_RE = re.compile(r"^[A-Za-z0-9_-]+$")


class RecipeError(Exception):
    """The recipe or the command line is wrong and nothing ran (CLI exit code 2)."""

    def __init__(self, problems: str | Sequence[str]) -> None:
        self.problems = [problems] if isinstance(problems, str) else list(problems)
        super().__init__("\n".join(self.problems))


@dataclass(frozen=True)
class StageSpec:
    """One validated stage of a recipe."""

    index: int
    id: str
    type: str
    # builtins.: in this class body ``type`` is the field above, and type checkers read
    # ``type[Stage]`` as an index into it (every use of ``cls`` came out untyped).
    cls: builtins.type[Stage]
    config: StageConfig
    # Artifact name -> id of the nearest earlier stage that provides it, for the names in
    # ``requires`` and those in ``optional_requires`` that some earlier stage provides.
    sources: Mapping[str, str] = field(default_factory=dict)
    # Every artifact an earlier stage provides (what ``ctx.has_artifact`` answers).
    available: frozenset[str] = frozenset()
    # Ids of earlier stages whose results this stage reads (``Stage.reads_results``).
    reads: tuple[str, ...] = ()

    @property
    def label(self) -> str:
        """How messages name this stage: ``stages[1] (slam2d)``."""
        return f"stages[{self.index}] ({self.id})"


@dataclass(frozen=True)
class Recipe:
    """A validated recipe: every stage's settings checked, defaults filled."""

    name: str
    output: Path
    stages: tuple[StageSpec, ...]
    description: str = ""
    source: Path | None = None
    # (value, NAME, default) for each ${NAME:-default} whose default made a value (NAME
    # unset): a missing input that is such a value names the variable (a relative default
    # such as ../shared/data holds only from the folder the recipe was written for).
    env_defaults: tuple[tuple[str, str, str], ...] = ()

    def index_of(self, stage_id: str, option: str = "stage") -> int:
        """Position of stage ``stage_id``; a ``RecipeError`` with a suggestion otherwise."""
        ids = [s.id for s in self.stages]
        if stage_id in ids:
            return ids.index(stage_id)
        raise RecipeError(
            f"{option} {stage_id!r}: no such stage id{_suggest(stage_id, ids)}; "
            f"stage ids: {', '.join(ids)}"
        )

    def resolved(self) -> dict[str, Any]:
        """The recipe as plain data with every default filled in (recipe.resolved.yaml)."""
        out: dict[str, Any] = {"name": self.name, "output": self.output.as_posix()}
        if self.description:
            out["description"] = self.description
        out["stages"] = [config_data(s.config) for s in self.stages]
        return out


def config_data(config: StageConfig) -> dict[str, Any]:
    """A stage's settings as plain data; an empty ``inputs`` is left out, so recipes and
    cache keys written before that option existed stay as they were."""
    data = config.model_dump(mode="json")
    if not data.get("inputs"):
        data.pop("inputs", None)
    return data


class _UniqueKeyLoader(yaml.SafeLoader):
    """SafeLoader that refuses a key given twice in one mapping (YAML keeps the last one
    without a word: a stage's setting written twice silently loses the first), and reads
    plain scalars by the YAML 1.2 core schema (below)."""


# PyYAML reads YAML 1.1: ``seed: 010`` is 8 (octal), ``topic: off`` and ``name: no`` are
# booleans, ``1:30`` is 90 and ``1e-3`` is the text "1e-3". Recipes are read by the YAML 1.2
# core schema instead (what ruamel.yaml, libyaml-based tools in other languages and the
# spec since 2009 do): only true/false are booleans, integers are decimal (0o / 0x
# prefixed otherwise), floats take exponents without a dot, no sexagesimals and no dates. The
# settings' own types still accept yes / on for a boolean setting.
_YAML11_TAGS = {"tag:yaml.org,2002:bool", "tag:yaml.org,2002:int", "tag:yaml.org,2002:float",
                "tag:yaml.org,2002:timestamp"}  # a date in a name stays text
_UniqueKeyLoader.yaml_implicit_resolvers = {
    first: [(tag, rx) for tag, rx in resolvers if tag not in _YAML11_TAGS]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_UniqueKeyLoader.add_implicit_resolver(
    "tag:yaml.org,2002:bool", re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"),
    list("tTfF"))
_UniqueKeyLoader.add_implicit_resolver(
    "tag:yaml.org,2002:int", re.compile(r"^(?:[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+)$"),
    list("-+0123456789"))
_UniqueKeyLoader.add_implicit_resolver(  # after int: "1" is an int, not a float
    "tag:yaml.org,2002:float",
    re.compile(r"^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?"
               r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"),
    list("-+.0123456789"))


def _yaml12_int(loader: _UniqueKeyLoader, node: yaml.ScalarNode) -> int:
    text = str(loader.construct_scalar(node))
    if text.startswith(("0o", "0x")):
        return int(text[2:], 8 if text[1] == "o" else 16)
    return int(text)  # decimal, leading zeros and all: 010 is ten


_UniqueKeyLoader.add_constructor("tag:yaml.org,2002:int", _yaml12_int)


class _RecipeDumper(yaml.SafeDumper):
    """SafeDumper that quotes text either YAML 1.1 or the 1.2 core schema would read as
    something else ("yes" and "1e3" alike), so a written recipe reads back the same here
    and in other YAML tools."""


for _first, _resolvers in _UniqueKeyLoader.yaml_implicit_resolvers.items():
    for _tag, _rx in _resolvers:
        _RecipeDumper.add_implicit_resolver(_tag, _rx, [_first])


def dump_recipe_data(data: Mapping[str, Any]) -> str:
    """YAML text of recipe data (recipe.resolved.yaml) that ``load_recipe`` reads back as
    it was."""
    return yaml.dump(dict(data), Dumper=_RecipeDumper, sort_keys=False, allow_unicode=True)


def read_yaml_value(text: str) -> Any:
    """One YAML value as a recipe file reads it (YAML 1.2 core scalars): ``--set`` items."""
    return yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 - a SafeLoader


def _read_otherwise(item: str) -> bool:
    """Whether a ``--set KEY=VALUE`` value is not the text typed once read as YAML (true,
    null, 1.10, [a]): only then may quoting it be the fix to suggest."""
    value = item.partition("=")[2]
    try:
        return not isinstance(read_yaml_value(value), str)
    except yaml.YAMLError:
        return True


def _quoted(item: str) -> str:
    """A ``--set`` item with its value as the text typed (a YAML double-quoted scalar)."""
    key, _, text = item.partition("=")
    return f"{key}={json.dumps(text.strip(), ensure_ascii=False)}"


def _quoting_hint(data: Any, overrides: Sequence[str], source: str | Path | None,
                  problems: int) -> str | None:
    """The advice to quote the ``--set`` values that YAML read as something other than the
    text typed, for those whose quoting leaves fewer problems (``label=true`` for a text
    setting; not ``duration_s=-1``, which reads as the same number quoted)."""
    helps = []
    for i, item in enumerate(overrides):
        if not _read_otherwise(item):
            continue
        trial = [*overrides[:i], _quoted(item), *overrides[i + 1:]]
        try:
            _parse_recipe(data, trial, source)
        except RecipeError as exc:
            if len(exc.problems) >= problems:
                continue
        helps.append(item)
    if not helps:
        return None
    fixes = " ".join(f"--set {shlex.quote(_quoted(item))}" for item in helps)
    return (f"(with --set {' '.join(helps)}: values are read as YAML, so quote text that YAML "
            f"reads otherwise: {fixes})")


def _mapping_without_repeats(loader: _UniqueKeyLoader, node: yaml.MappingNode,
                             deep: bool = False) -> dict[Any, Any]:
    seen: dict[Any, int] = {}
    for key_node, _ in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge":  # '<<: *defaults'
            continue
        key = loader.construct_object(key_node, deep=deep)
        try:
            hash(key)
        except TypeError:
            raise yaml.constructor.ConstructorError(
                "while reading a mapping", node.start_mark,
                f"found a {type(key).__name__} as a key (line {key_node.start_mark.line + 1});"
                " keys are names", key_node.start_mark) from None
        if key in seen:
            raise yaml.constructor.ConstructorError(
                "while reading a mapping", node.start_mark,
                f"key {key!r} is given twice (lines {seen[key] + 1} and "
                f"{key_node.start_mark.line + 1}); keep one", key_node.start_mark)
        seen[key] = key_node.start_mark.line
    return loader.construct_mapping(node, deep=deep)


_UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG,
                                 _mapping_without_repeats)


def load_recipe(path: str | Path, overrides: Sequence[str] = ()) -> Recipe:
    """Read and validate a recipe file; ``overrides`` are ``--set`` items (``KEY=VALUE``)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise RecipeError(f"{path}: no such recipe file") from None
    except OSError as exc:
        raise RecipeError(f"{path}: cannot read it: {exc}") from None
    except UnicodeDecodeError as exc:
        raise RecipeError(f"{path}: not UTF-8 text (byte {exc.start}); save the recipe as "
                          f"UTF-8") from None
    # A named stream: PyYAML's marks then say 'in "recipes/x.yaml", line 5', not
    # 'in "<unicode string>"'.
    stream = io.StringIO(text)
    stream.name = str(path)
    try:
        data = yaml.load(stream, Loader=_UniqueKeyLoader)  # noqa: S506 - a SafeLoader
    except yaml.YAMLError as exc:
        # PyYAML says only "found character '\t' that cannot start any token".
        fix = ("\nYAML indents with spaces only: replace the tab(s) with spaces"
               if "'\\t'" in str(exc) else "")
        raise RecipeError(f"{path}: not valid YAML: {exc}{fix}") from None
    return parse_recipe(data, overrides, source=path)


def parse_recipe(
    data: Any, overrides: Sequence[str] = (), source: str | Path | None = None
) -> Recipe:
    """Validate recipe data already loaded from YAML (or built in code)."""
    try:
        return _parse_recipe(data, overrides, source)
    except RecipeError as exc:
        if not overrides:
            raise
        problems = [_set_by(p, overrides, source) for p in exc.problems]
        hint = _quoting_hint(data, overrides, source, len(exc.problems))
        raise RecipeError([*problems, hint] if hint else problems) from None


def _set_by(problem: str, overrides: Sequence[str], source: str | Path | None) -> str:
    """``problem`` with the ``--set`` item that gave the value it is about, if one did: a
    problem of a value typed on the command line read as the file's ("tiny.yaml: stages[0]
    (simulate): unknown key 'camera.widht'"), and the file was searched for it in vain."""
    where = re.escape(str(source) if source is not None else "recipe")
    for item in overrides:
        key = item.partition("=")[0].strip()
        stage_id, _, path = key.partition(".")
        if path:
            # The key as the problem's location, or first in the message of a check of the
            # stage's own ("random_depth_m [5.0, 1.0]: give [near, far]", "scan:
            # scan.min_range (40.0 m) must be below"); not anywhere (a list of keys).
            about = (rf"stages\[\d+\] \({re.escape(stage_id)}\): "
                     rf"(?:unknown key '{re.escape(path)}'|{re.escape(path)}: |"
                     rf"(?:[\w.\[\]]+: )?{re.escape(path)}(?![\w.]))")
        else:
            about = rf"{where}: '{re.escape(key)}' "
        if re.match(about, problem):
            return f"{problem} (from --set {item})"
    return problem


def _parse_recipe(data: Any, overrides: Sequence[str], source: str | Path | None) -> Recipe:
    where = str(source) if source is not None else "recipe"
    if not isinstance(data, dict):
        raise RecipeError(
            f"{where}: a recipe is a mapping with keys {', '.join(TOP_LEVEL_KEYS)}; "
            f"got {type(data).__name__}"
        )
    # A fresh tree: YAML aliases (&a / *a) share one mapping between stages, which a
    # --set on one stage would change in all of them (deepcopy keeps the sharing).
    data = _unshared(data, environment=False)
    apply_overrides(data, overrides)
    # ~/ in --set values too (the shell leaves it in KEY=~/x); ${NAME} once, after --set,
    # which may replace a value naming a variable that is not set here.
    unset: list[str] = []
    defaults: list[tuple[str, str, str]] = []
    data = _unshared(data, environment=True, unset=unset, defaults=defaults)
    if unset:
        raise RecipeError([f"{where}: {line}" for line in unset])

    problems: list[str] = []
    for key in data:
        if key not in TOP_LEVEL_KEYS:
            problems.append(
                f"{where}: unknown top-level key {key!r}{_suggest(str(key), TOP_LEVEL_KEYS)}; "
                f"allowed keys: {', '.join(TOP_LEVEL_KEYS)}"
            )
    default_name = Path(source).stem if source is not None else None
    name = data.get("name", default_name)
    if not isinstance(name, str) or not name:
        problems.append(f"{where}: 'name' must be a non-empty string (got {name!r})")
        name = "recipe"
    output = data.get("output", f"runs/{name}")
    if not isinstance(output, str) or not output:
        problems.append(f"{where}: 'output' must be a folder path (got {output!r})")
        output = f"runs/{name}"
    description = data.get("description", "") or ""
    if not isinstance(description, str):
        problems.append(f"{where}: 'description' must be a string (got {description!r})")
        description = ""

    raw_stages = data.get("stages")
    if not isinstance(raw_stages, list) or not raw_stages:
        problems.append(f"{where}: 'stages' must be a non-empty list of '- stage: TYPE' entries")
        raw_stages = []
    specs: list[StageSpec] = []
    seen: dict[str, int] = {}
    for index, raw in enumerate(raw_stages):
        spec = _parse_stage(index, raw, problems)
        if spec is None:
            continue
        if spec.id in seen:
            problems.append(
                f"{spec.label}: duplicate id {spec.id!r} (also stages[{seen[spec.id]}]); "
                f"give one of them a distinct 'id:'"
            )
        seen.setdefault(spec.id, index)
        specs.append(spec)
    # Artifact wiring is judged only on an otherwise valid recipe: a stage that failed to
    # parse would make every stage after it report a missing artifact.
    if not problems:
        specs = _wire_artifacts(specs, problems)
    if problems:
        raise RecipeError(problems)
    return Recipe(
        name=name,
        output=Path(output),
        stages=tuple(specs),
        description=description,
        source=Path(source) if source is not None else None,
        env_defaults=tuple(defaults),
    )


def _parse_stage(index: int, raw: Any, problems: list[str]) -> StageSpec | None:
    where = f"stages[{index}]"
    known = registry.stage_names()
    if not isinstance(raw, dict):
        problems.append(f"{where}: expected a mapping such as '- stage: slam2d', got {raw!r}")
        return None
    stage_type = raw.get("stage")
    if not isinstance(stage_type, str) or not stage_type:
        problems.append(
            f"{where}: missing 'stage: TYPE' (known types: {', '.join(known) or 'none'})"
        )
        return None
    stage_id = raw.get("id", stage_type)
    if stage_id is None:  # ``id:`` left empty in YAML: the type, as without the key
        stage_id = stage_type
    if isinstance(stage_id, bool | int):
        text = str(stage_id).lower()  # true, not Python's True
        problems.append(f"{where} ({stage_type}): id {text} is read by YAML as a "
                        f"{'boolean' if isinstance(stage_id, bool) else 'number'}; an id is "
                        f"text: quote it (id: '{text}')")
        return None
    if not isinstance(stage_id, str) or not _ID_RE.match(stage_id):
        problems.append(
            f"{where} ({stage_type}): id {stage_id!r} may hold only letters, digits, '_' "
            f"and '-' (it names the stage's folder and its --set keys)"
        )
        return None
    label = f"{where} ({stage_id})"
    try:
        cls = registry.load_stage(stage_type)
    except KeyError:
        problems.append(
            f"{label}: unknown stage type {stage_type!r}{_suggest(stage_type, known)}; "
            f"known types: {', '.join(known) or 'none'}"
        )
        return None
    except ImportError as exc:
        problems.append(f"{label}: {exc}")
        return None
    flags = _booleans_for_numbers(cls.Config, raw)
    if flags:
        problems.extend(f"{label}: {key}: true / false where a number goes; write the "
                        "number (pydantic reads true as 1)" for key in flags)
        return None
    try:
        config = cls.Config.model_validate({**raw, "id": stage_id})
    except ValidationError as exc:
        problems.extend(format_validation_error(exc, label, cls.Config))
        return None
    return StageSpec(index=index, id=stage_id, type=stage_type, cls=cls, config=config)


def _booleans_for_numbers(model: type[BaseModel], data: Any, at: tuple[Any, ...] = ()) -> (
    list[str]
):
    """Key paths where ``data`` gives true / false for a setting of ``model`` that takes no
    boolean (``seed: true`` was seed 1, ``completeness_views: false`` 0, without a word)."""
    if not isinstance(data, dict):
        return []
    out: list[str] = []
    fields = _field_types(model)
    for key, value in data.items():
        if key in fields:
            out += _bool_in(fields[key], value, (*at, key))
    return out


def _bool_in(tp: Any, value: Any, at: tuple[Any, ...]) -> list[str]:
    if tp is Any or tp is bool:
        return []
    while typing.get_origin(tp) is typing.Annotated:
        tp = typing.get_args(tp)[0]
    members = _union_members(tp)
    if members is not None:
        if any(m is bool or m is Any for m in members):
            return []
        models = [m for m in members if _is_model(m)]
        if isinstance(value, dict) and len(models) == 1:
            return _booleans_for_numbers(models[0], value, at)
        if isinstance(value, bool):
            return [] if _admits_bool(tp) else [_fmt_loc(at)]
        if isinstance(value, list):
            seqs = [m for m in members if typing.get_origin(m) in (list, tuple)]
            if len(seqs) == 1:
                return _bool_in(seqs[0], value, at)
        return []
    if _is_model(tp):
        return _booleans_for_numbers(tp, value, at)
    if isinstance(value, bool):
        return [] if _admits_bool(tp) else [_fmt_loc(at)]
    origin = typing.get_origin(tp)
    if isinstance(value, list) and origin in (list, tuple):
        args = [a for a in typing.get_args(tp) if a is not Ellipsis]
        if not args:
            return []
        out: list[str] = []
        for i, v in enumerate(value):
            item = args[0] if len(args) == 1 else args[i] if i < len(args) else None
            if item is not None:
                out += _bool_in(item, v, (*at, i))
        return out
    if isinstance(value, dict) and origin is dict:
        args = typing.get_args(tp)
        if len(args) == 2:
            return [k for key, v in value.items() for k in _bool_in(args[1], v, (*at, key))]
    return []


def _admits_bool(tp: Any) -> bool:
    """Whether a setting of type ``tp`` may be true / false: bool itself, Any, a Literal of
    them, or a type it cannot be confused with a number for (strings refuse it anyway)."""
    if tp is bool or tp is Any:
        return True
    if typing.get_origin(tp) is typing.Literal:
        return any(isinstance(a, bool) for a in typing.get_args(tp))
    members = _union_members(tp)
    if members is not None:
        return any(_admits_bool(m) for m in members)
    return tp not in (int, float)


def _wire_artifacts(specs: list[StageSpec], problems: list[str]) -> list[StageSpec]:
    provided: dict[str, str] = {}
    # Every earlier stage id -> what it provides, for explicit ``inputs:``.
    earlier: dict[str, tuple[str, ...]] = {}
    wired = []
    for spec in specs:
        sources = {}
        declared = (*spec.cls.requires, *spec.cls.optional_requires)
        chosen = dict(spec.config.inputs)
        for name, source in chosen.items():
            if source is None:
                if name in spec.cls.requires:
                    problems.append(f"{spec.label}: inputs: {name}: null, but the stage "
                                    f"cannot run without {name!r}")
                elif name not in declared:
                    problems.append(f"{spec.label}: inputs: {name!r} is not an artifact this "
                                    f"stage uses ({', '.join(declared) or 'none'})")
                continue
            if name not in declared:
                problems.append(
                    f"{spec.label}: inputs: {name!r} is not an artifact this stage uses "
                    f"({', '.join(declared) or 'none'})")
            elif source not in earlier:
                problems.append(
                    f"{spec.label}: inputs: {name}: {source!r} is not an earlier stage id"
                    f"{_suggest(source, list(earlier))}")
            elif name not in earlier[source]:
                problems.append(
                    f"{spec.label}: inputs: {name}: stage {source!r} does not provide {name!r} "
                    f"(it provides {', '.join(earlier[source]) or 'nothing'})")
            else:
                sources[name] = source
        for name in spec.cls.requires:
            if name in sources or name in chosen:
                continue
            if name in provided:
                sources[name] = provided[name]
                continue
            later = [s.label for s in specs[specs.index(spec) + 1:] if name in s.cls.provides]
            makers = registry.providers_of(name)
            if later:
                hint = f"; {later[0]} provides it: move that stage before this one"
            elif makers:
                hint = f"; add a stage that provides it before this one ({', '.join(makers)})"
            else:
                hint = ""
            problems.append(
                f"{spec.label}: requires artifact {name!r}, which no earlier stage provides"
                + hint)
        for name in spec.cls.optional_requires:
            if name in provided and name not in chosen:
                sources[name] = provided[name]
        reads = tuple(spec.cls.reads_results(spec.config))
        for rid in reads:
            if rid not in earlier:
                problems.append(f"{spec.label}: reads the results of {rid!r}, which is not an "
                                f"earlier stage id{_suggest(rid, list(earlier))}")
        wired.append(
            StageSpec(
                index=spec.index,
                id=spec.id,
                type=spec.type,
                cls=spec.cls,
                config=spec.config,
                sources=sources,
                available=(frozenset(provided) | frozenset(sources))
                - {n for n, v in chosen.items() if v is None},
                reads=reads,
            )
        )
        for name in spec.cls.provides:
            provided[name] = spec.id
        earlier[spec.id] = tuple(spec.cls.provides)
    return wired


def apply_overrides(data: dict[str, Any], overrides: Sequence[str]) -> None:
    """Apply ``--set`` items to raw recipe data in place.

    ``<stage id>.<key>[.<subkey>...]=VALUE`` sets a stage setting and ``name=``, ``output=``
    or ``description=`` the top-level field; VALUE is read as the recipe file is
    (``read_yaml_value``) so ``0.5``, ``true``, ``[1, 2]`` and ``null`` mean what they do
    there.
    """
    for item in overrides:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise RecipeError(f"--set {item!r}: expected KEY=VALUE, e.g. "
                              "slam2d.local.linear_window_m=0.5")
        try:
            value = read_yaml_value(text)
        except yaml.YAMLError as exc:
            raise RecipeError(f"--set {item!r}: value is not valid YAML: {exc}") from None
        parts = key.split(".")
        if any(not p for p in parts):
            raise RecipeError(f"--set {item!r}: empty part in key {key!r}")
        if len(parts) == 1:
            if key not in _TOP_LEVEL_SETTABLE:
                raise RecipeError(
                    f"--set {item!r}{_suggest(key, _TOP_LEVEL_SETTABLE)}: "
                    f"expected <stage id>.<key>=VALUE, or one of "
                    f"{', '.join(p + '=' for p in _TOP_LEVEL_SETTABLE)}"
                )
            data[key] = value
            continue
        stage_id, *path = parts
        if path[0] in ("stage", "id"):
            raise RecipeError(f"--set {item!r}: a stage's '{path[0]}' is fixed by the recipe")
        target = _stage_mapping(data, stage_id, item)
        for depth, part in enumerate(path[:-1]):
            child = target.get(part)
            if child is None:
                child = target[part] = {}
            elif not isinstance(child, dict):
                inner = ".".join([stage_id, *path[: depth + 1]])
                raise RecipeError(f"--set {item!r}: {inner} is {child!r}, not a mapping")
            target = child
        target[path[-1]] = value


# ${NAME} or ${NAME:-default}: an environment variable, as a POSIX shell reads it.
_ENV_RE = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)(?::-([^}]*))?\}")


def _expand_env(text: str, defaults: list[tuple[str, str, str]] | None = None) -> str:
    """``text`` with its variables expanded; ``defaults`` collects (expanded text, NAME,
    default) for each ``${NAME:-default}`` whose default was taken."""
    taken: list[tuple[str, str]] = []

    def value(m: re.Match[str]) -> str:
        name, default = m.group(1), m.group(2)
        got = os.environ.get(name)
        if default is not None:  # ${NAME:-default}: the default when unset or empty
            if not got:
                taken.append((name, default))
            return got or default
        if got is not None:
            return got
        raise RecipeError(f"{text!r}: environment variable {name} is not set; set it, or "
                          f"give a default: ${{{name}:-...}}")
    out = _ENV_RE.sub(value, text)
    if defaults is not None:
        defaults += [(out, name, default) for name, default in taken]
    return out


def _unshared(value: Any, environment: bool = True, at: str = "",
              unset: list[str] | None = None,
              defaults: list[tuple[str, str, str]] | None = None) -> Any:
    """A copy of YAML data with every mapping and list its own, environment variables in
    strings expanded (``${TOOLKIT_SHARED_DATA:-../shared/data}/killian.g2o``: data a
    recipe shares with other checkouts), and paths written from the home folder
    (``~/data/run.bag``) expanded: a string starting with ``~/`` is nothing else in a
    recipe (recorded topic names are absolute). A variable that is not set is a
    RecipeError, or, given ``unset``, a line there naming its key path (``at``);
    ``defaults`` collects the variables whose default was taken."""
    if isinstance(value, dict):
        return {k: _unshared(v, environment, f"{at}.{k}" if at else str(k), unset, defaults)
                for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_unshared(v, environment, f"{at}[{i}]", unset, defaults)
                for i, v in enumerate(value)]
    if environment and isinstance(value, str) and "${" in value:
        try:
            value = _expand_env(value, defaults)
        except RecipeError as exc:
            if unset is None:
                raise
            unset.append(f"{at}: {exc}" if at else str(exc))
            return value
    if isinstance(value, str) and value.startswith("~/"):
        return os.path.expanduser(value)
    return value


def _stage_mapping(data: dict[str, Any], stage_id: str, item: str) -> dict[str, Any]:
    stages = data.get("stages")
    ids = []
    for raw in stages if isinstance(stages, list) else []:
        if isinstance(raw, dict):
            raw_id = raw.get("id") or raw.get("stage")
            if raw_id == stage_id:
                return raw
            ids.append(str(raw_id))
    raise RecipeError(
        f"--set {item!r}: no stage with id {stage_id!r}{_suggest(stage_id, ids)}; "
        f"stage ids: {', '.join(ids) or 'none'}"
    )


def format_validation_error(
    error: ValidationError, label: str, model: type[BaseModel]
) -> list[str]:
    """One readable line per problem, each starting with ``label`` and the key path."""
    lines: list[str] = []
    merged: dict[str, list[str]] = {}
    short: dict[str, tuple[int, Any]] = {}  # where -> (values expected, values given)
    for item in error.errors():
        loc = tuple(item["loc"])
        kind = item["type"]
        if kind == "extra_forbidden" and loc:
            parent, parent_type = _resolve_loc(model, loc[:-1])
            key = _fmt_loc((*parent, loc[-1]))
            allowed = _allowed_keys(parent_type, top=not parent)
            line = f"{label}: unknown key {key!r}{_suggest(str(loc[-1]), allowed)}"
            if allowed:
                line += f"; allowed keys: {', '.join(allowed)}"
            lines.append(line)
        elif kind == "missing" and isinstance(loc[-1], int) and isinstance(
                item.get("input"), list | tuple):
            # A fixed-length tuple given too few values: one error per absent position.
            parent, _ = _resolve_loc(model, loc[:-1])
            given = item["input"]
            where = f"{label}: {_fmt_loc(parent)}"
            short[where] = (max(short.get(where, (0, given))[0], loc[-1] + 1), given)
        elif kind == "missing" and loc:
            parent, _ = _resolve_loc(model, loc[:-1])
            lines.append(f"{label}: missing required key {_fmt_loc((*parent, loc[-1]))!r}")
        elif kind == "value_error" and isinstance(item.get("input"), Mapping):
            # A model's own check (scan.min_range below max_range, random_depth_m's order):
            # its message names the values; pydantic's "Value error, " prefix and the
            # whole settings mapping as "got" only buried it.
            path, _ = _resolve_loc(model, loc)
            where = f"{label}: {_fmt_loc(path)}" if path else label
            merged.setdefault(f"{where}: ", []).append(
                str(item["msg"]).removeprefix("Value error, "))
        else:
            path, _ = _resolve_loc(model, loc)
            where = f"{label}: {_fmt_loc(path)}" if path else label
            got = _short(repr(item.get("input")))
            merged.setdefault(f"{where}: ", []).append(
                f"{item['msg']} (got {got}){_unit_hint(path, kind, item.get('input'))}")
    for where, (expected, given) in short.items():
        lines.append(f"{where}: expects {expected} values, got {len(given)} "
                     f"({_short(repr(list(given)))})")
    for where, messages in merged.items():
        lines.append(where + "; or ".join(dict.fromkeys(messages)))
    return list(dict.fromkeys(lines))


# Key suffix -> the unit its number is in (longest suffix first).
_UNITS = (("_m_s", "metres per second"), ("_deg_s", "degrees per second"),
          ("_ms", "milliseconds"), ("_mb", "megabytes"), ("_deg", "degrees"),
          ("_rad", "radians"), ("_hz", "hertz"), ("_px", "pixels"), ("_db", "decibels"),
          ("_s", "seconds"), ("_m", "metres"))


def _unit_hint(path: tuple[Any, ...], kind: str, given: Any) -> str:
    """'; a plain number, in seconds (the key's _s)' for a number given as text with a unit
    ('8s', '15 cm'): the message said only that it was no valid number. A number above a
    unit key's upper bound is most often another unit's (voxel_size_m: 20, meant in cm):
    it gets the unit the key is in."""
    if not (path and isinstance(path[-1], str)):
        return ""
    text = isinstance(given, str) and kind in ("float_parsing", "int_parsing", "float_type",
                                               "int_type")
    too_large = (isinstance(given, int | float) and not isinstance(given, bool)
                 and kind in ("less_than", "less_than_equal"))
    if not (text or too_large):
        return ""
    key = path[-1].lower()
    for suffix, unit in _UNITS:
        if key.endswith(suffix):
            if text:
                return f"; write a plain number, in {unit} (the key's {suffix})"
            return f"; the key is in {unit} (its {suffix} suffix)"
    return ""


def _resolve_loc(model: type[BaseModel], loc: tuple[Any, ...]) -> tuple[tuple[Any, ...], Any]:
    """Strip pydantic's union tags (``'int'``, ``'MatcherConfig'``) from an error location.

    Returns the location as the user wrote it and the type found there (None when lost),
    so messages read ``matcher.window_m`` and can list the allowed keys of ``matcher``.
    """
    clean: list[Any] = []
    current: Any = model
    for part in loc:
        current = _unwrap(current)
        members = _union_members(current)
        if members is not None:
            # pydantic tags a generic member by its repr ('tuple[int, int]')
            match = [m for m in members if part in (getattr(m, "__name__", None), str(m))]
            if match:  # a union tag: not part of the user's path
                current = match[0]
                continue
            models = [m for m in members if _is_model(m) and part in _field_types(m)]
            current = models[0] if models else None
            if current is None:
                # No member's key either: one of pydantic's other tags ('constrained-int',
                # "literal['auto']", a generic's repr), not part of the user's path.
                if not isinstance(part, str):
                    clean.append(part)
                continue
        if _is_model(current) and isinstance(part, str):
            clean.append(part)
            current = _field_types(current).get(part)
        elif typing.get_origin(current) in (list, tuple, set, frozenset) and isinstance(part, int):
            clean.append(part)
            args = typing.get_args(current)
            current = args[0] if args else None
        elif typing.get_origin(current) is dict:
            clean.append(part)
            args = typing.get_args(current)
            current = args[1] if len(args) == 2 else None
        else:
            clean.append(part)
            current = None
    return tuple(clean), _unwrap(current)


def _unwrap(tp: Any) -> Any:
    while typing.get_origin(tp) is typing.Annotated:
        tp = typing.get_args(tp)[0]
    members = _union_members(tp)
    if members is not None:
        rest = [m for m in members if m is not type(None)]
        if len(rest) == 1:
            return _unwrap(rest[0])
    return tp


def _union_members(tp: Any) -> tuple[Any, ...] | None:
    origin = typing.get_origin(tp)
    if origin is typing.Union or origin is types.UnionType:
        return typing.get_args(tp)
    return None


def _is_model(tp: Any) -> bool:
    return isinstance(tp, type) and issubclass(tp, BaseModel)


def _field_types(model: type[BaseModel]) -> dict[str, Any]:
    return {(f.alias or name): f.annotation for name, f in model.model_fields.items()}


def _allowed_keys(tp: Any, top: bool) -> list[str]:
    if not _is_model(tp):
        return []
    keys = list(_field_types(tp))
    # 'stage' is always present in a stage entry; listing it as an option is noise.
    return [k for k in keys if not (top and k == "stage")]


def _fmt_loc(loc: Sequence[Any]) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


def _suggest(word: str, options: Sequence[str]) -> str:
    close = difflib.get_close_matches(word, list(options), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _short(text: str, limit: int = 60) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."

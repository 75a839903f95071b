"""The stages of the pipeline, found where they are declared, and their graph.

Every module under ``tasks/`` that assigns ``STAGE = StageDef(...)`` (:class:`tasks.stage.StageDef`)
declares a stage; adding a stage is writing such a module. The declarations are read from the
source, not imported, so that commands which only read (``cadestate status``) do not import every
stage's dependencies; a stage's functions are imported when they are called.

A function a declaration names is imported from where the stage's module imports it (``from X
import f`` at the top of the module), else from the stage's module: a heavy stage keeps the
functions that digest its inputs in a light module, so that ``cadestate status``, which calls them
for every clip, does not import the stage's dependencies.

A stage's ``code_hash`` (``runs.code_hash``) is the digest of its module and of every module of the
project's logic that it imports, directly or through others, as the source says (imports inside
functions count). The project's logic is ``tasks`` and the foundation (``cadestate``: geometry,
rendering) less what does not decide a stage's results (:data:`NOT_LOGIC`): the stage framework,
the parsing and digesting of the config (whose values count through the config hash), the digests
themselves and progress display. Storage (``warehouse``) and table definitions (``schemas``) are
not logic either.
"""

from __future__ import annotations

import ast
import contextlib
import dataclasses
import importlib
import json
import os
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import cache, cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cadestate.atomic import atomic_write_bytes
from cadestate.config import section_hash
from cadestate.lineage import digest

if TYPE_CHECKING:
    from cadestate.config import Config
    from tasks.stage import StageContext, StageDef, StageOutput
    from warehouse import Warehouse

ROOT = Path(__file__).resolve().parent.parent
"""The project root: module ``a.b`` is ``ROOT/a/b.py`` (or ``ROOT/a/b/__init__.py``)."""
LOGIC_PACKAGES = ("tasks", "cadestate")
NOT_LOGIC = frozenset({"tasks.registry", "tasks.stage", "tasks.status", "cadestate.config", "cadestate.lineage",
                       "cadestate.progress"})
FUNCTION_FIELDS = ("run", "config_inputs", "clip_inputs", "source_inputs")

_DECLARATION = re.compile(r"^STAGE = StageDef\(", re.M)
_IMPORT = re.compile(r"^[ \t]*(?:from[ \t]+([\w.]+)[ \t]+import[ \t]+(\([^)]*\)|[^\n#;]*)|import[ \t]+([^\n#;]*))", re.M)


class RegistryError(ValueError):
    """A stage declaration that cannot be read, or a stage graph that does not hold together."""


@dataclass(frozen=True)
class Stage:
    """A declared stage as the registry reads it: the values of its :class:`tasks.stage.StageDef`,
    its module, and the names of its functions (``functions``: field -> module-level name)."""

    name: str
    section: str | None
    scope: str
    upstream: tuple[str, ...]
    tables: tuple[str, ...]
    description: str
    extra_sections: tuple[str, ...]
    after: tuple[str, ...]
    module: str
    functions: tuple[tuple[str, str], ...]

    @cached_property
    def code_hash(self) -> str:
        """Digest of the source of the stage's module and the logic it imports (module docstring)."""
        return code_digest(self.module)

    @cached_property
    def definition(self) -> StageDef:
        """The declaration itself (imports the stage's module)."""
        return importlib.import_module(self.module).STAGE

    def has(self, function: str) -> bool:
        return function in dict(self.functions)

    def function(self, field: str) -> Any:
        """The function the declaration names for ``field``, imported from where the stage's module
        imports it, else from the stage's module (module docstring)."""
        name = dict(self.functions)[field]
        origin = _imported_from(self.module, name)
        return getattr(importlib.import_module(origin), name) if origin else getattr(self.definition, field)

    def run(self, ctx: StageContext) -> StageOutput:
        return self.definition.run(ctx)

    def config_inputs(self, config: Config) -> list[str]:
        return self.function("config_inputs")(config) if self.has("config_inputs") else []

    def clip_inputs(self, wh: Warehouse, unit: str) -> list[str]:
        return self.function("clip_inputs")(wh, unit) if self.has("clip_inputs") else []

    def submitted_inputs(self, config: Config, source: Any) -> list[str]:
        """Digests of what a run on ``source`` reads besides its upstream outputs, for a stage that
        declares ``source_inputs`` (what a flow submits; the others submit their
        ``config_inputs`` and ``clip_inputs``, see :mod:`tasks.inputs_memo`)."""
        return self.function("source_inputs")(source) + self.config_inputs(config)


@cache
def _module_file(name: str) -> Path | None:
    base = ROOT.joinpath(*name.split("."))
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return path
    return None


@cache
def _source(name: str) -> str:
    return _module_file(name).read_text(encoding="utf-8")


@cache
def _direct_imports(name: str) -> frozenset[str]:
    """Project modules that module ``name``'s source imports (anywhere in it)."""
    found = set()
    for m in _IMPORT.finditer(_source(name)):
        if m.group(1):
            found.add(m.group(1))
            names = m.group(2).strip("() \n").replace("\n", " ")
            found.update(f"{m.group(1)}.{n.split()[0]}" for n in names.split(",") if n.strip())
        else:
            found.update(part.split()[0] for part in m.group(3).split(",") if part.strip())
    return frozenset(f for f in found if f.split(".")[0] in LOGIC_PACKAGES and _module_file(f) is not None)


@cache
def _imported_from(module: str, name: str) -> str | None:
    """The project module from which ``module``'s top-level ``from X import ...`` takes ``name``."""
    for m in _IMPORT.finditer(_source(module)):
        if m.group(1) and not m.group(0).startswith((" ", "\t")) and m.group(1).split(".")[0] in LOGIC_PACKAGES:
            names = [n.split() for n in m.group(2).strip("() \n").replace("\n", " ").split(",") if n.strip()]
            if any(n[0] == name and len(n) == 1 for n in names):
                return m.group(1)
    return None


def code_digest(module: str) -> str:
    """Digest of the source of ``module`` and the logic modules it imports (:func:`logic_imports`)."""
    return digest(*(f"{m}\n{_source(m)}" for m in sorted(logic_imports(module))))


def logic_imports(module: str) -> set[str]:
    """``module`` and the logic modules it imports, directly or not (see the module docstring)."""
    seen, todo = set(), [module]
    while todo:
        name = todo.pop()
        if name in seen or (name in NOT_LOGIC and name != module):
            continue
        seen.add(name)
        todo.extend(_direct_imports(name))
    return {m for m in seen if not _module_file(m).name == "__init__.py" or m == module}


def _declaration(text: str, module: str) -> ast.Call | None:
    """The ``StageDef(...)`` call of a module's ``STAGE =`` line, parsed alone."""
    found = _DECLARATION.search(text)
    if found is None:
        return None
    start, end = found.start() + len("STAGE = "), found.end()
    while (end := text.find(")", end)) != -1:
        end += 1
        try:
            return ast.parse(text[start:end], mode="eval").body
        except SyntaxError:
            continue
    raise RegistryError(f"{module}: the STAGE = StageDef(...) declaration does not parse")


def _read_stage(module: str) -> Stage | None:
    call = _declaration(_source(module), module)
    if call is None:
        return None
    if call.args:
        raise RegistryError(f"{module}: declare STAGE = StageDef(...) with keywords only")
    values: dict[str, Any] = {"extra_sections": (), "after": ()}
    functions = []
    for kw in call.keywords:
        if kw.arg in FUNCTION_FIELDS:
            if not isinstance(kw.value, ast.Name):
                raise RegistryError(f"{module}: StageDef {kw.arg}= must name a module-level function")
            functions.append((kw.arg, kw.value.id))
            continue
        try:
            values[kw.arg] = ast.literal_eval(kw.value)
        except ValueError:
            raise RegistryError(f"{module}: StageDef {kw.arg}= must be a literal") from None
    try:
        return Stage(**values, module=module, functions=tuple(sorted(functions, key=lambda f: FUNCTION_FIELDS.index(f[0]))))
    except TypeError as e:
        raise RegistryError(f"{module}: StageDef: {e}") from None


def _pipeline_order(stages: dict[str, Stage]) -> list[Stage]:
    """Topological order over ``upstream`` and ``after``, clip stages first; among the stages ready,
    first those that follow the stage placed last (a chain stays together), then by name."""
    order: list[Stage] = []
    placed: set[str] = set()
    while len(order) < len(stages):
        ready = [s for s in stages.values() if s.name not in placed and set(s.upstream + s.after) <= placed]
        if not ready:
            raise RegistryError(f"stages in a cycle: {sorted(set(stages) - placed)}")
        last = order[-1].name if order else ""
        nxt = min(ready, key=lambda s: (s.scope != "clip", last not in s.upstream + s.after, s.name))
        order.append(nxt)
        placed.add(nxt.name)
    return order


def _discover() -> dict[str, Stage]:
    found: dict[str, Stage] = {}
    for path in sorted((ROOT / "tasks").rglob("*.py")):
        module = ".".join(path.relative_to(ROOT).with_suffix("").parts)
        stage = _read_stage(module)
        if stage is None:
            continue
        if stage.name in found:
            raise RegistryError(f"stage {stage.name!r} declared twice: {found[stage.name].module} and {module}")
        found[stage.name] = stage
    for s in found.values():
        for u in s.upstream + s.after:
            if u not in found or found[u].scope != s.scope:
                raise RegistryError(f"{s.module}: stage {s.name!r} names {u!r}, not a {s.scope} stage")
    return {s.name: s for s in _pipeline_order(found)}


KEPT = ROOT / "tasks" / "__pycache__" / "stage-registry.json"
"""The stages and their code digests as last read (what every command would read again), with the
state of the sources they were read from: used while no module of ``tasks`` or ``cadestate``
was added, removed or changed (size or modification time), else read again and rewritten. Not
kept where it cannot be written."""


def _sources_state() -> str:
    """Digest of the path, size and modification time of every module of :data:`LOGIC_PACKAGES`."""
    lines = []
    for package in LOGIC_PACKAGES:
        for folder, dirs, files in os.walk(ROOT / package):
            dirs[:] = [d for d in dirs if d != "__pycache__"]
            for name in files:
                if name.endswith(".py"):
                    st = os.stat(os.path.join(folder, name))
                    lines.append(f"{os.path.relpath(os.path.join(folder, name), ROOT)} {st.st_size} {st.st_mtime_ns}")
    return digest(*sorted(lines))


def _kept_stages() -> dict[str, Stage]:
    """:func:`_discover`, with each stage's ``code_hash``, from :data:`KEPT` when it holds."""
    state = _sources_state()
    with contextlib.suppress(OSError, ValueError, KeyError, TypeError):
        kept = json.loads(KEPT.read_text(encoding="utf-8"))
        if kept["state"] == state:
            stages = {}
            for record in kept["stages"]:
                stage = Stage(**{k: tuple(map(tuple, v)) if k == "functions" else tuple(v) if isinstance(v, list) else v
                                 for k, v in record.items() if k != "code_hash"})
                stage.__dict__["code_hash"] = record["code_hash"]  # the cached_property, filled in
                stages[stage.name] = stage
            return stages
    stages = _discover()
    records = [{**dataclasses.asdict(s), "code_hash": s.code_hash} for s in stages.values()]
    with contextlib.suppress(OSError):
        atomic_write_bytes(KEPT, json.dumps({"state": state, "stages": records}).encode())
    return stages


STAGES: dict[str, Stage] = _kept_stages()
"""Every stage by name, in pipeline order."""


def stages_of(scope: str) -> list[Stage]:
    """The stages of one scope, in pipeline order."""
    return [s for s in STAGES.values() if s.scope == scope]


def config_hash(stage: str, config: Config | Mapping[str, Any]) -> str:
    """``runs.config_hash`` of ``stage``: its section's digest, combined with the digests of its
    ``extra_sections`` (a whole section, or one key of it: ``"manual_tracks.keyframes"``);
    ``config``: a :class:`cadestate.config.Config` or a mapping of section names to their dataclasses."""
    section = config.__getitem__ if isinstance(config, Mapping) else config.section
    name = STAGES[stage].section
    own = section_hash(name, section(name)) if name is not None else digest("no config section")
    extra = STAGES[stage].extra_sections
    return digest(own, *(_extra_digest(e, section) for e in extra)) if extra else own


def _extra_digest(entry: str, section: Callable[[str], Any]) -> str:
    """Digest of an ``extra_sections`` entry: a section's :func:`section_hash`, or one key's value."""
    name, _, key = entry.partition(".")
    if not key:
        return section_hash(name, section(name))
    return digest(f"{entry}={json.dumps(getattr(section(name), key), sort_keys=True)}")


def extra_shown(entry: str) -> str:
    """An ``extra_sections`` entry as the docs show it: ``[embed]``, ``[manual_tracks] keyframes``."""
    name, _, key = entry.partition(".")
    return f"[{name}] {key}" if key else f"[{name}]"


def extra_inputs(stage: str, config: Config) -> list[str]:
    """Digests of the files the config names that ``stage`` reads (its ``config_inputs``)."""
    return STAGES[stage].config_inputs(config)


def clip_inputs(stage: str, wh: Warehouse, clip: str) -> list[str]:
    """Digests of the warehouse data of ``clip`` that ``stage`` reads besides its upstream outputs
    (its ``clip_inputs``)."""
    return STAGES[stage].clip_inputs(wh, clip)


def stages_markdown(scope: str) -> str:
    """The Markdown table of the stages of ``scope`` (the README's, which a test keeps equal)."""
    rows = ["| stage | after | writes | config | module | what it does |", "|---|---|---|---|---|---|"]
    for s in stages_of(scope):
        after = ", ".join(f"`{u}`" for u in s.upstream + s.after) or "(the source)"
        writes = ", ".join(f"`{t}`" for t in s.tables) or ("(files)" if s.has("source_inputs") else "(nothing)")
        config = f"`[{s.section}]`" if s.section else ""
        config += "".join(f", `{extra_shown(e)}`" for e in s.extra_sections)
        module = "tasks/" + "/".join(s.module.split(".")[1:]) + ".py"
        rows.append(f"| `{s.name}` | {after} | {writes} | {config} | `{module}` | {s.description} |")
    return "\n".join(rows)


def upstream_inputs_hash(output_hashes: list[str]) -> str:
    """``inputs_hash`` of a stage from its upstream stages' output hashes (in ``upstream`` order)
    followed by the digests of what else it reads."""
    return digest(*output_hashes)

"""Layers point one way (issue 14, "One stage, one place"), read from the source: every ``import`` and
``from ... import`` of the project's modules, those inside functions included (an import in a
function still runs, only later), and ``importlib.import_module("literal")``.

From the bottom up: the foundation (``cadestate/``: config and cron, geometry, render, lineage, progress,
atomic file writes, names), ``schemas/``, ``warehouse/``, ``tasks/``, then ``flows/``, the CLI and the web
app; ``bench/`` sits beside the top and only its own commands reach it.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("cadestate", "tasks", "flows", "warehouse", "schemas", "bench")
"""The project's top-level packages (``tests/`` is not a layer)."""

FOUNDATION = frozenset({"cadestate", "cadestate.atomic", "cadestate.config", "cadestate.cron", "cadestate.geometry",
                        "cadestate.lineage", "cadestate.names", "cadestate.progress", "cadestate.render"})
"""Modules that import no other project module but each other."""


@dataclass(frozen=True)
class Import:
    importer: str  # the importing module
    module: str  # the imported module (``from a.b import c``: a.b.c when that is a project module, else a.b)
    line: int
    function: str | None  # the enclosing function (dotted for nested ones); None: runs on import
    type_checking: bool  # under ``if TYPE_CHECKING:`` (never runs)

    def __str__(self) -> str:
        where = f"in {self.function}()" if self.function else "at module level"
        return f"{self.importer}:{self.line} imports {self.module} {where}"


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


@cache
def project_modules() -> dict[str, Path]:
    return {module_name(p): p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))}


def is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def imports_of(module: str, path: Path) -> list[Import]:
    """Every import in ``path`` (the module ``module``)."""
    modules = project_modules()
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: list[Import] = []

    def visit(node: ast.AST, function: str | None, type_checking: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                name = getattr(child, "name", "<lambda>")
                visit(child, f"{function}.{name}" if function else name, type_checking)
                continue
            if isinstance(child, ast.If) and is_type_checking(child.test):
                for stmt in child.body:
                    visit(ast.Module(body=[stmt], type_ignores=[]), function, True)
                for stmt in child.orelse:
                    visit(ast.Module(body=[stmt], type_ignores=[]), function, type_checking)
                continue
            if isinstance(child, ast.Import):
                names = [a.name for a in child.names]
            elif isinstance(child, ast.ImportFrom):
                base = child.module or ""
                if child.level:  # relative: from the package, up level - 1
                    up = package.split(".")[: len(package.split(".")) - child.level + 1]
                    base = ".".join([*up, base] if base else up)
                names = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in child.names]
            elif (isinstance(child, ast.Call) and child.args and isinstance(child.args[0], ast.Constant)
                  and isinstance(child.args[0].value, str)
                  and (getattr(child.func, "attr", None) or getattr(child.func, "id", None)) == "import_module"):
                names = [child.args[0].value]
            else:
                names = []
            found.extend(Import(module, n, child.lineno, function, type_checking) for n in names)
            visit(child, function, type_checking)

    visit(ast.parse(path.read_text(encoding="utf-8"), str(path)), None, False)
    return found


@cache
def all_imports() -> tuple[Import, ...]:
    return tuple(i for m, p in project_modules().items() for i in imports_of(m, p))


def under(module: str, *prefixes: str) -> bool:
    """Whether ``module`` is one of ``prefixes`` or inside one of them."""
    return any(module == p or module.startswith(p + ".") for p in prefixes)


def in_project(module: str) -> bool:
    return under(module, *PACKAGES)


def violations(importers: tuple[str, ...], forbidden: tuple[str, ...]) -> list[str]:
    return [str(i) for i in all_imports() if under(i.importer, *importers) and under(i.module, *forbidden)]


def test_the_scan_sees_imports_inside_functions_and_under_type_checking():
    """The rules below are not vacuous: the scan finds imports where they hide."""
    found = {(i.importer, i.module, i.function, i.type_checking) for i in all_imports()}
    assert ("cadestate.cli.bench", "bench.benchmark", "bench_generate", False) in found
    assert ("warehouse.store", "schemas.index", None, True) in found
    assert ("cadestate.render", "cadestate.geometry", None, False) in found
    assert len(project_modules()) > 100


def test_the_foundation_imports_only_the_foundation():
    """config, geometry, render, lineage, progress and atomic import no project module above them."""
    bad = [str(i) for i in all_imports() if i.importer in FOUNDATION and in_project(i.module) and i.module not in FOUNDATION]
    assert bad == []
    assert FOUNDATION <= set(project_modules())


def test_store_and_catalog_do_not_import_each_other():
    assert violations(("warehouse.store",), ("warehouse.catalog",)) == []
    assert violations(("warehouse.catalog",), ("warehouse.store",)) != []  # the catalog is built on the store
    # the store is the warehouse's bottom: of the warehouse it imports only leaves (modules that import
    # no project module, e.g. warehouse.read_cache)
    leaves = {m for m in project_modules() if not any(i.importer == m and in_project(i.module) for i in all_imports())}
    assert [v for v in violations(("warehouse.store",), ("warehouse",)) if v.split(" imports ")[1].split()[0] not in leaves] == []
    assert "warehouse.read_cache" in leaves and "warehouse.catalog" not in leaves


@pytest.mark.parametrize("layer, forbidden", [
    ("schemas", ("tasks", "flows", "warehouse", "bench", "cadestate.cli", "cadestate.webapp")),
    ("warehouse", ("tasks", "flows", "bench", "cadestate.cli", "cadestate.webapp")),
    ("tasks", ("flows", "bench", "cadestate.cli", "cadestate.webapp")),
    ("flows", ("bench", "cadestate.cli", "cadestate.webapp")),
])
def test_a_layer_imports_nothing_above_it(layer, forbidden):
    assert violations((layer,), forbidden) == []


def test_the_cli_imports_bench_only_in_bench_commands():
    """Nothing of bench/ at module level of any CLI module; inside functions only in the ``bench``
    commands (``cadestate.cli.bench``)."""
    bad = [str(i) for i in all_imports()
           if under(i.importer, "cadestate.cli") and under(i.module, "bench")
           and not (i.function and i.importer == "cadestate.cli.bench")]
    assert bad == []


def test_importing_the_cli_imports_nothing_of_bench():
    """What ``import cadestate.cli`` runs (module-level imports, followed through every module they
    import and its packages' ``__init__``) reaches no module of bench/."""
    modules = project_modules()
    on_import: dict[str, set[str]] = {}
    for i in all_imports():
        if i.function is None and not i.type_checking and in_project(i.module):
            on_import.setdefault(i.importer, set()).add(i.module)

    def with_packages(module: str) -> list[str]:
        parts = module.split(".")
        return [m for m in (".".join(parts[: k + 1]) for k in range(len(parts))) if m in modules]

    seen: dict[str, str] = {}  # module -> the module that imported it
    todo = [(m, "cadestate.cli") for m in with_packages("cadestate.cli")]
    while todo:
        module, by = todo.pop()
        if module in seen:
            continue
        seen[module] = by
        todo.extend((m, module) for imported in on_import.get(module, ()) for m in with_packages(imported))
    reached = sorted(m for m in seen if under(m, "bench"))
    assert reached == [], [f"{m} (imported by {seen[m]})" for m in reached]
    assert "cadestate.cli.bench" in seen and "cadestate.cli.common" in seen

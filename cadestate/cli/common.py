"""The ``cadestate`` command line: the Typer apps, shared state and output helpers.

Heavy modules (Prefect, PyAV, DuckDB) are imported inside the commands so that ``--help`` is instant
and Prefect's environment is set (per warehouse) before Prefect is first imported.
"""

from __future__ import annotations

import contextlib
import dataclasses
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console, ConsoleDimensions
from rich.markup import escape
from rich.table import Table

from cadestate.cli.params import install as _install_plain_params
from cadestate.config import Config, load_config

_install_plain_params()  # plain values (-w DIR, a SQL statement) are converted without Pydantic

app = typer.Typer(
    help="CAD-Estate annotation pipeline: RGB walkthrough videos -> CAD models with 9-DoF poses.\n\n"
    "Typical session:  cadestate ingest VIDEO CAMERAS.txt  ->  cadestate status  ->  "
    "cadestate sql \"SELECT * FROM frames LIMIT 5\".  Every table is also a view in "
    "<warehouse>/catalog.duckdb for any DuckDB client.",
    no_args_is_help=True,
    rich_markup_mode=None,
    pretty_exceptions_enable=False,
)
config_app = typer.Typer(help="Show or check the configuration (one TOML file, a section per stage).", no_args_is_help=True)
cad_app = typer.Typer(help="The CAD library: ingest CAD collections, render them, export them in the official layout.", no_args_is_help=True)
app.add_typer(config_app, name="config")
bench_app = typer.Typer(help="The synthetic benchmark: rendered walkthroughs with exact ground truth, evaluators.", no_args_is_help=True)
app.add_typer(cad_app, name="cad")
app.add_typer(bench_app, name="bench")
UNWRAPPED_WIDTH = 100_000
"""The width tables are laid out in when the output is not a terminal: their natural width."""


class LineConsole(Console):
    """A console whose lines are never hard-wrapped: text is soft-wrapped (a terminal folds long
    lines on screen, a script reads them whole), and when the output is not a terminal (a pipe, a
    file, CI) tables take their natural width instead of the 80 columns Rich assumes."""

    def __init__(self, *args, force_terminal: bool | None = None, **kwargs) -> None:
        super().__init__(*args, force_terminal=force_terminal, **kwargs)
        self._told_terminal = force_terminal

    def _on_a_terminal(self) -> bool:
        """Whether the output is a terminal: one the console was told it writes to, else a real one.
        Rich's ``is_terminal`` is also true in a pipe under ``FORCE_COLOR`` or ``TTY_COMPATIBLE``
        (CI sets them), where tables were cut at 80 columns."""
        if self._told_terminal is not None:
            return self._told_terminal
        try:
            return self.file.isatty()
        except (AttributeError, ValueError):  # no such method, or a closed file
            return False

    @property
    def size(self) -> ConsoleDimensions:
        size = Console.size.fget(self)
        return size if self.is_terminal and self._on_a_terminal() else ConsoleDimensions(UNWRAPPED_WIDTH, size.height)

    @size.setter
    def size(self, new_size: tuple[int, int]) -> None:
        Console.size.fset(self, new_size)


out = LineConsole(soft_wrap=True)
err = LineConsole(stderr=True, soft_wrap=True)  # error lines stay whole (greppable)


@dataclasses.dataclass
class State:
    config_path: Optional[Path] = None
    warehouse: Optional[Path] = None
    verbose: bool = False

    def config(self) -> Config:
        cfg = load_config(self.config_path)
        if self.warehouse:
            cfg = dataclasses.replace(cfg, warehouse=dataclasses.replace(cfg.warehouse, root=str(self.warehouse)))
        return cfg

    def root(self, cfg: Config | None = None) -> Path:
        """The warehouse folder of ``cfg`` (default: :meth:`config`), absolute (:class:`CliError`
        when a file is in its place)."""
        root = Path((cfg or self.config()).warehouse.root).expanduser().resolve()
        if root.exists() and not root.is_dir():
            raise CliError(f"{root}: the warehouse is not a folder (set by -w, [warehouse] root or $CADESTATE_WAREHOUSE)")
        return root

    def open_warehouse(self, must_exist: bool = False):
        """The warehouse; ``must_exist``: commands that read it or answer its clips refuse a folder
        that is not there (a typo in ``-w`` would otherwise create an empty warehouse and report
        nothing in it); only ingesting and the benchmark's runs create one."""
        from warehouse import Warehouse

        cfg = self.config()
        root = self.root(cfg)
        if must_exist and not root.exists():
            raise CliError(f"{root}: no warehouse there (set by -w, [warehouse] root or $CADESTATE_WAREHOUSE); "
                           "`cadestate ingest` or `cadestate cad ingest` makes one")
        if must_exist and not _warehouse_or_empty(root):  # a near miss (-w data, -w ~) was read as an empty warehouse
            raise CliError(f"{root}: not a warehouse (a folder of other files, with no tables/ folder; set by -w, "
                           "[warehouse] root or $CADESTATE_WAREHOUSE)")
        return Warehouse(root, compact_after=cfg.warehouse.compact_after_files)


def _warehouse_or_empty(root: Path) -> bool:
    """Whether the folder ``root`` is a warehouse (its tables, catalog or Prefect folder), or empty."""
    try:  # warehouse.store.TABLES_DIR, warehouse.catalog.CATALOG_FILE (not imported: a read command's start stays light)
        return any((root / name).exists() for name in ("tables", "catalog.duckdb", "_prefect")) or not any(root.iterdir())
    except OSError:  # not listable: what opens it next says why
        return True


class CliError(Exception):
    """An error to print as one line, without a traceback."""


def print_reports(reports, unit: str = "clip") -> int:
    """Print the stage runs' table, then one stderr line per failed or paused run naming its ``unit``
    (a clip, or a CAD library); returns the exit status (1 when a stage failed)."""
    table = Table(unit, "stage", "state", "rows", "seconds", "message", title="stage runs")
    colours = {"completed": "green", "cached": "cyan", "failed": "red", "skipped": "yellow", "paused": "magenta",
               "waiting": "magenta"}
    for r in reports:
        table.add_row(escape(r.clip), r.stage, f"[{colours[r.state]}]{r.state}[/]", str(r.rows_written),
                      f"{r.duration_s:.2f}", escape(r.message))
    out.print(table)
    failed = [r for r in reports if r.state == "failed"]
    for r in failed:
        err.print(f"[red]error:[/] {unit} {escape(r.clip)}, stage {r.stage}: {escape(r.message)}", highlight=False)
    paused = [r for r in reports if r.state == "paused"]
    for r in paused:
        err.print(f"[magenta]paused:[/] {unit} {escape(r.clip)}, stage {r.stage}: {escape(r.message)}", highlight=False)
    if paused and not failed:
        err.print("answer the task files with label files, then `cadestate labels ingest DIR` resumes the clips")
    return 1 if failed else 0


@contextlib.contextmanager
def cannot_write(where: Path, what: str, hint: str = "") -> Iterator[None]:
    """Within the block, an OSError (no permission, a file in the path, a folder named as a file)
    is one :class:`CliError` line: ``<where>: cannot write <what> there: <why><hint>``."""
    try:
        yield
    except OSError as e:
        raise CliError(f"{where}: cannot write {what} there: {e.strerror or e}{hint}") from None


def check_writable(root: Path) -> None:
    """Refuse (:class:`CliError`) a warehouse, or the folder it is to be made in, that this process
    cannot write: a run would otherwise wait out Prefect's start and blame it."""
    folder = root if root.exists() else next((p for p in root.parents if p.exists()), root)
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as e:
        raise CliError(f"{root}: the warehouse cannot be written ({e.strerror or e}); runs write their tables "
                       "there (read it with `cadestate sql`, or copy it somewhere writable)") from None


def run_sources(state: State, items, progress: bool, exit: bool = True) -> int:
    from flows.runtime import prepare_prefect_environment

    cfg = state.config()
    root = state.root(cfg)
    check_writable(root)
    api = prepare_prefect_environment(root, state.verbose, cfg.prefect.startup_timeout_s, start_api=True)  # before Prefect is imported
    from flows.annotate_clip import run_clips

    err.print(f"running {len(items)} clip(s) into {escape(str(root))} " + (f"on the Prefect server at {api}" if api else
              "(Prefect's local API starts alongside, ~3 s; `cadestate server start` saves it)"))
    code = print_reports(run_clips(items, cfg, show_progress=progress))
    if 0 < cfg.warehouse.snapshot_after_clips <= len(items):
        from warehouse import Warehouse
        from warehouse.catalog import compact_warehouse

        done = compact_warehouse(Warehouse(root, compact_after=cfg.warehouse.compact_after_files))
        err.print(f"{len(items)} clips ([warehouse] snapshot_after_clips = {cfg.warehouse.snapshot_after_clips}): "
                  f"compacted {len(done.compacted)} partition(s), snapshot of {len(done.snapshotted)} table(s) in the catalog",
                  highlight=False)
    if exit:
        raise typer.Exit(code)
    return code

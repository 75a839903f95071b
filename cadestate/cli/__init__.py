"""``cadestate``: the one command line of the pipeline (see ``cadestate --help``).

Modules: :mod:`cadestate.cli.common` (apps, state, output), :mod:`cadestate.cli.pipeline` (clips,
warehouse, configuration), :mod:`cadestate.cli.labels` (label files), :mod:`cadestate.cli.cad` (the
CAD library), :mod:`cadestate.cli.bench` (the synthetic benchmark). Importing them registers their
commands; each command imports what it needs when it runs, so a command pays only for itself (nothing
of ``bench/`` is imported unless a ``bench`` command runs: ``tests/test_layers.py``).
"""

from __future__ import annotations

import sys

from rich.markup import escape

from cadestate.cli import annotate, bench, cad, export, labels, pipeline, server  # noqa: F401  (register the commands)
from cadestate import exit_on_sigterm, quiet_exit
from cadestate.cli.common import app, err

__all__ = ["app", "main"]

INPUT_ERRORS = {
    "cadestate.cli.common": "CliError",
    "cadestate.config": "ConfigError",
    "tasks.video.camera_file": "CameraFileError",
    "tasks.video.decode": "VideoError",
    "tasks.video.sfm": "SfmError",
    "warehouse.store": "WarehouseError",
    "tasks.cad.sources": "CadSourceError",
    "tasks.cad.export": "ExportError",
    "bench.benchmark": "BenchmarkError",
    "tasks.human.labels": "LabelError",
    "tasks.video.clip_names": "ClipNameError",
    "schemas.official": "OfficialFormatError",
    "builtins": "FileNotFoundError",
}
"""Exception types that mean bad input (module -> class): shown as one line, exit status 2."""

GLOBAL_OPTIONS = frozenset({"-c", "--config", "-w", "--warehouse", "-v", "--verbose"})
"""The options of ``cadestate`` itself, which a user may put after a command (``status -w wh``)."""

ENVIRONMENT_ERRORS = {"flows.server": "ServerError"}
"""Exception types that mean the environment failed (Prefect's API): one line, exit status 1."""


def is_one_of(e: BaseException, types: dict[str, str]) -> bool:
    """Whether ``e`` is one of ``types`` (module -> class). Only modules already imported are looked at:
    an exception's class is imported before it can be raised, so no command imports a module for this."""
    return any(isinstance(e, getattr(sys.modules[m], name)) for m, name in types.items() if m in sys.modules)


def main() -> None:
    """Entry point: known input errors and usage errors (a mistyped option or value) become one
    clear line on stderr and exit status 2 (1 for a failing environment); Ctrl-C is "interrupted",
    status 130. SIGTERM ends the command as an exit (status 143), so that its cleanup runs
    (temporary folders, the Prefect API it launched), as Ctrl-C's does. Output is UTF-8 whatever
    the locale says (an 'é' in a CSV under an ASCII locale was a traceback half-way through). Once
    it is done, a SIGTERM or Ctrl-C while the process exits is ignored (:func:`cadestate.quiet_exit`)."""
    try:
        _main()
    finally:
        quiet_exit()


def _main() -> None:
    import typer
    from typer._click.exceptions import NoArgsIsHelpError, UsageError  # Typer carries its own Click

    for stream, errors in ((sys.stdout, "surrogateescape"), (sys.stderr, "backslashreplace")):  # a file name's bytes
        if hasattr(stream, "reconfigure"):
            stream.reconfigure(encoding="utf-8", errors=errors)

    exit_on_sigterm()
    try:
        code = typer.main.get_command(app).main(prog_name="cadestate", standalone_mode=False)
    except NoArgsIsHelpError as e:  # a group named alone: its help
        e.show()
        sys.exit(e.exit_code)
    except UsageError as e:  # a mistyped option or value: one line, and where the help is
        where = f" (`{e.ctx.command_path} --help`)" if e.ctx is not None else ""
        message = e.format_message().replace("Value error, ", "")  # Typer's parsing says it of every value
        if (option := getattr(e, "option_name", None)) in GLOBAL_OPTIONS and e.ctx is not None and e.ctx.parent is not None:
            where = f" ({option} is an option of `cadestate` itself: give it before the command, `cadestate {option} ... " \
                    f"{e.ctx.command_path.removeprefix('cadestate ')}`)"
        err.print(f"[red]error:[/] {escape(message)}{escape(where)}", highlight=False)
        sys.exit(e.exit_code)
    except typer.Abort:  # input ended where a prompt waited
        err.print("aborted", highlight=False)
        sys.exit(1)
    except Exception as e:
        codes = [code for types, code in ((INPUT_ERRORS, 2), (ENVIRONMENT_ERRORS, 1)) if is_one_of(e, types)]
        if not codes:
            raise
        err.print(f"[red]error:[/] {escape(str(e))}", highlight=False)
        sys.exit(codes[0])
    if code == 130:  # Typer's exit for Ctrl-C
        err.print("interrupted", highlight=False)
    sys.exit(code if isinstance(code, int) else 0)

"""The fuzz suite's harness: run the real ``cadestate`` command in-process on generated inputs and
check what a user must see for bad input.

Every generated case must end with:

- no traceback (an exception escaping :func:`cadestate.cli.main` fails the case with it),
- a non-zero exit code and one error line on stderr (naming the file, line, field or key),
- the warehouse unchanged: :func:`warehouse_digest` before and after are equal.

Cases are counted (:func:`count_case`); ``tests/conftest.py`` prints the count at the end of the run.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import subprocess
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

CASES: dict[str, int] = {}
"""Fuzz cases run, per suite (``pytest_terminal_summary`` prints them)."""


def count_case(suite: str) -> None:
    CASES[suite] = CASES.get(suite, 0) + 1


@dataclass(frozen=True)
class CliResult:
    """One in-process run of the command line: exit code and what it printed."""

    code: int
    stdout: str
    stderr: str


def run_cli(*args: str) -> CliResult:
    """Run ``cadestate ARGS`` in this process through its real entry point (``cadestate.cli.main``,
    which turns known errors into one line and exit code 2); any other exception propagates."""
    from cadestate.cli import main

    stdout, stderr = io.StringIO(), io.StringIO()
    argv = sys.argv
    sys.argv = ["cadestate", *args]
    code = 0
    try:
        with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
            main()
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    finally:
        sys.argv = argv
    return CliResult(code, stdout.getvalue(), stderr.getvalue())


def assert_clean_error(result: CliResult, *, mentions: str | None = None) -> str:
    """``result`` is a refusal: non-zero exit, no traceback, one line on stderr that starts with
    ``error:`` (and names ``mentions`` when given). Returns that line."""
    text = result.stdout + result.stderr
    assert "Traceback" not in text, text
    assert result.code != 0, f"exit code 0 for a bad input; printed:\n{text}"
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith("error:")]
    assert len(errors) == 1, f"expected one error line:\n{result.stderr}"
    if mentions is not None:
        assert mentions in errors[0], f"{mentions!r} not named in {errors[0]!r}"
    return errors[0]


def warehouse_digest(root: Path) -> dict[str, str]:
    """SHA-256 of every file of the warehouse's tables, task files, inputs, media and catalog, by
    relative path: equal before and after means nothing was written."""
    root = Path(root)
    out: dict[str, str] = {}
    files = [root / "catalog.duckdb"]
    for sub in ("tables", "label_tasks", "inputs", "media"):
        files += sorted((root / sub).rglob("*"))
    return {f.relative_to(root).as_posix(): hashlib.sha256(f.read_bytes()).hexdigest() for f in files if f.is_file()}


def killed_at_move(dst: Path, *args: str) -> subprocess.CompletedProcess:
    """Run ``cadestate ARGS`` in a new process that is killed (SIGKILL, as by a power loss) as it
    moves an entry to ``dst`` (``os.rename`` / ``os.replace``), before that move."""
    script = textwrap.dedent(f"""
        import os, signal, sys
        from pathlib import Path

        def killed_at(move):
            def moved(src, dst):
                if Path(dst) == Path({str(dst)!r}):
                    os.kill(os.getpid(), signal.SIGKILL)
                return move(src, dst)
            return moved

        os.rename, os.replace = killed_at(os.rename), killed_at(os.replace)
        from cadestate.cli import main

        sys.argv = ["cadestate", *{list(args)!r}]
        main()
    """)
    return subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)

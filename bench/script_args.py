"""The ``bench`` scripts that take no arguments (``python -m bench``, ``python -m bench.pose_bench``,
...): ``--help`` prints what the script measures, its module docstring, instead of starting a run
of minutes; any other argument is refused in one line."""

from __future__ import annotations

import inspect
import sys


def no_arguments(doc: str | None) -> None:
    """Return when the script was given no argument; else print ``doc`` and exit 0 for ``-h`` or
    ``--help``, or say on stderr that it takes none and exit 2."""
    args = sys.argv[1:]
    if not args:
        return
    if args[0] in ("-h", "--help"):
        print(inspect.cleandoc(doc or "(no description)"))
        raise SystemExit(0)
    print(f"error: {sys.argv[0]} takes no arguments (got {' '.join(args)}); --help says what it measures", file=sys.stderr)
    raise SystemExit(2)

"""Cron strings as the Prefect server's schedules take them, checked without importing Prefect.

``[schedule] inbox_cron`` and its siblings are checked when the config loads, which every command
does; importing Prefect for it would cost about a second a command (issue 16's budgets). Prefect
validates a cron string with the croniter it vendors (``prefect._internal.schemas.validators.
validate_cron_string``: ``croniter.is_valid``, and no random "R" or hashed "H" fields); that one
module is loaded from Prefect's install by its path (~20 ms: pytz and dateutil), and
``tests/test_config.py`` holds the two checks to the same answers, but for what cadestate refuses
and Prefect takes (a sixth field, read as seconds; a date that never comes: ``STRICTER`` there).
"""

from __future__ import annotations

import functools
import importlib.util
import re
from pathlib import Path
from types import ModuleType


@functools.cache
def _croniter() -> ModuleType:
    spec = importlib.util.find_spec("prefect")  # finds the package without importing it
    path = Path(spec.origin).parent / "_vendor" / "croniter" / "croniter.py"
    module_spec = importlib.util.spec_from_file_location("_cadestate_prefect_croniter", path)
    module = importlib.util.module_from_spec(module_spec)
    module_spec.loader.exec_module(module)
    return module


def cron_problem(value: str) -> str | None:
    """What is wrong with a cron string for a Prefect schedule (minute hour day month weekday,
    or @daily and the like), or None."""
    if not _croniter().croniter.is_valid(value):
        return "not a cron string (minute hour day-of-month month day-of-week, e.g. \"*/10 * * * *\")"
    if any(piece.casefold() in ("r", "h") for piece in re.split(r"[\s,/()-]+", value)):  # R/10 too: new minutes each loop
        return "random (R) and hashed (H) cron fields are not supported by Prefect"
    if not value.strip().startswith("@") and len(value.split()) != 5:  # croniter takes a sixth, seconds: 60 runs a minute
        return f"{len(value.split())} fields, not five (minute hour day-of-month month day-of-week)"
    cron = _croniter()
    try:
        cron.croniter(value).get_next(float)
    except cron.CroniterBadDateError:  # valid fields, but no such date (31 February): it would never run
        return "names no date that exists (it would never run)"
    return None

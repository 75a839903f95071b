"""Progress bars for long stages (rich), shown only on an interactive terminal."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterable, Iterator
from typing import TypeVar

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

T = TypeVar("T")


def progress(items: Iterable[T], total: int, description: str, enabled: bool = True) -> Iterator[T]:
    """Iterate ``items`` with a progress bar on stderr (off when not a TTY or CADESTATE_PROGRESS=0)."""
    show = enabled and sys.stderr.isatty() and os.environ.get("CADESTATE_PROGRESS", "1") != "0"
    if not show:
        yield from items
        return
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    with Progress(*columns, transient=True, console=Console(stderr=True)) as bar:  # rich's default is stdout
        task = bar.add_task(description, total=total)
        for item in items:
            yield item
            bar.advance(task)

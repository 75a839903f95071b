"""Overlap loading with work: the next item is loaded on a thread while the caller works on this one."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T, U = TypeVar("T"), TypeVar("U")


def prefetch(items: list[T], load: Callable[[T], U]) -> Iterator[tuple[T, U]]:
    """(item, load(item)) in order, loading the next item on a thread while the caller works."""
    with ThreadPoolExecutor(max_workers=1) as pool:
        pending = pool.submit(load, items[0]) if items else None
        for i, item in enumerate(items):
            value = pending.result()
            pending = pool.submit(load, items[i + 1]) if i + 1 < len(items) else None
            yield item, value

"""Training rooms rendered on every core, in room order: the trainers' data step.

A training room's frames (:func:`bench.detector_data.room_frames`) or crops
(:func:`bench.descriptor_data.room_crops`) are a function of the room alone, so rooms can be
rendered in any process: :func:`map_rooms` spreads them over spawned worker processes (each with
its own GL context and onnxruntime session, made once by ``make_state``) and returns the parts in
room order, byte for byte what one process makes (a test holds this). Spawned, not forked: a
forked child would inherit the parent's GL and onnxruntime threads.
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from contextlib import ExitStack
from typing import Any, TypeVar

from cadestate.progress import progress

T = TypeVar("T")
StateMaker = Callable[[ExitStack], Any]
"""Makes a process's state (its renderer, session, library rows), closing what needs it on the stack."""

_state: list[Any] = []
"""The worker process's state (one item, set by :func:`_start`)."""


def default_workers() -> int:
    """One worker per core this process may use, at most 4 (each holds a GL context and meshes)."""
    return max(1, min(4, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1))


def _start(make_state: StateMaker) -> None:
    _state.append(make_state(ExitStack()))  # lives as long as the worker; the GL context goes with it


def _room(fn: Callable[[Any, int], T], room: int) -> T:
    return fn(_state[0], room)


def _parts(make_state: StateMaker, fn: Callable[[Any, int], T], rooms: Sequence[int], workers: int) -> Iterator[T]:
    if workers <= 1 or len(rooms) < 2:
        with ExitStack() as stack:
            state = make_state(stack)
            yield from (fn(state, r) for r in rooms)
        return
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(min(workers, len(rooms)), mp_context=context, initializer=_start, initargs=(make_state,)) as pool:
        yield from pool.map(_room, [fn] * len(rooms), rooms)


def map_rooms(make_state: StateMaker, fn: Callable[[Any, int], T], rooms: Sequence[int], workers: int,
              description: str, show_progress: bool = True) -> list[T]:
    """``[fn(state, r) for r in rooms]`` with ``state = make_state(stack)`` made once per process, on
    ``workers`` spawned processes (in this one when 1). ``make_state`` and ``fn`` must be picklable
    (module-level functions, or :func:`functools.partial` of them)."""
    return list(progress(_parts(make_state, fn, rooms, workers), total=len(rooms), description=description,
                         enabled=show_progress))

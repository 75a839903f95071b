"""bench.room_pool: rooms spread over spawned worker processes come back in room order, and the
in-process state is closed when the rooms are done."""

from __future__ import annotations

import functools
import os
from contextlib import ExitStack

from bench.room_pool import default_workers, map_rooms


def _state(base: int, stack: ExitStack) -> tuple[int, int]:
    return base, os.getpid()


def _room(state: tuple[int, int], room: int) -> tuple[int, int]:
    base, pid = state
    return base + room * room, pid


def test_pooled_rooms_come_back_in_order_from_the_workers():
    rooms = list(range(7, -1, -1))
    out = map_rooms(functools.partial(_state, 100), _room, rooms, 2, "rooms", show_progress=False)
    assert [v for v, _ in out] == [100 + r * r for r in rooms]
    assert os.getpid() not in {pid for _, pid in out} and 1 <= len({pid for _, pid in out}) <= 2
    alone = map_rooms(functools.partial(_state, 100), _room, rooms, 1, "rooms", show_progress=False)
    assert [v for v, _ in alone] == [v for v, _ in out] and {pid for _, pid in alone} == {os.getpid()}
    assert map_rooms(functools.partial(_state, 0), _room, [], 2, "rooms", show_progress=False) == []
    assert 1 <= default_workers() <= 4


def test_in_process_state_is_closed_when_the_rooms_are_done():
    log: list[str] = []

    def state(stack: ExitStack) -> int:
        stack.callback(log.append, "closed")
        return 5

    assert map_rooms(state, lambda s, r: s + r, [1, 2], 1, "rooms", show_progress=False) == [6, 7]
    assert log == ["closed"]

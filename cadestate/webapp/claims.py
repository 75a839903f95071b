"""Items held by the browser tab that opened them: two people (or tabs) using one app are not given the same item.

Without it, two browsers were given the same next item, and the second person met a 409 after
doing the work. A page that opens an item claims it for its client (its browser tab: an id the
pages keep in ``sessionStorage`` and send as the ``X-Cadestate-Client`` header; another tab has its
own, so one person in two tabs is given two items), and claims it again every
:data:`HOLD_S` / 3 seconds while it stays open; a claim not renewed lapses after :data:`HOLD_S`,
and a page that is left gives its claim back. The next item (``/api/next``, the start page's, a
page's after an answer) skips the items another client holds, and the start page counts them.

A claim is advice, not a lock: a page opened on an item another client holds says so and can
still answer it (the answer that comes second is refused, 409, as without claims). Claims live in
the memory of the app's process: one app served to a team shares them; two apps over one warehouse
do not see each other's, and a restart forgets them (the pages claim again within HOLD_S / 3).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

HOLD_S = 180.0
"""How long a claim holds an item when its page stops renewing it (closed without a word, its
browser gone); the pages renew theirs every third of it."""

Item = tuple[str, str, int]
"""(clip, kind, track id; -1: a manual-track task, answered whole). Not the task id: a rerun that
replaces a task keeps its items held (the page's answer goes to the newer task where it fits)."""


@dataclass
class Claim:
    client: str
    since: float
    until: float


class Claims:
    """The claims of one app (module docstring); safe to share between threads. ``clock``: seconds
    (monotonic)."""

    def __init__(self, hold_s: float = HOLD_S, clock: Callable[[], float] = time.monotonic):
        self.hold_s = hold_s
        self._clock = clock
        self._claims: dict[Item, Claim] = {}
        self._lock = threading.Lock()

    def _live(self, now: float) -> dict[Item, Claim]:
        """The claims in force (lapsed ones dropped); called with the lock held."""
        for item in [i for i, c in self._claims.items() if c.until <= now]:
            del self._claims[item]
        return self._claims

    def claim(self, client: str, item: Item) -> Claim | None:
        """Hold ``item`` for ``client`` for :attr:`hold_s` from now (renewed if it held it); None,
        or the claim of the other client that holds it (left as it is)."""
        with self._lock:
            now = self._clock()
            held = self._live(now).get(item)
            if held is not None and held.client != client:
                return held
            self._claims[item] = Claim(client, held.since if held else now, now + self.hold_s)
            return None

    def release(self, client: str, item: Item) -> None:
        """Give ``item`` back, if ``client`` holds it."""
        with self._lock:
            if (held := self._claims.get(item)) is not None and held.client == client:
                del self._claims[item]

    def held_by_others(self, client: str | None) -> set[Item]:
        """The items held by clients other than ``client`` (None: by any)."""
        with self._lock:
            return {i for i, c in self._live(self._clock()).items() if c.client != client}

    def age_s(self, claim: Claim) -> float:
        """Seconds since ``claim``'s client opened its item."""
        return self._clock() - claim.since

"""Items held by the browser tab that opened them: two people (or tabs) are not given the same item.

Without it, two browsers were given the same next item, and the second person met a 409 after
doing the work. A page that opens an item claims it for its client (its browser tab: an id the
pages keep in ``sessionStorage`` and send as the ``X-Cadestate-Client`` header; another tab has its
own, so one person in two tabs is given two items), and claims it again every
:data:`HOLD_S` / 3 seconds while it stays open; a claim not renewed lapses after :data:`HOLD_S`,
and a page that is left gives its claim back. The next item (``/api/next``, the start page's, a
page's after an answer) skips the items another client holds, and the start page counts them.

A claim is advice, not a lock: a page opened on an item another client holds says so and can
still answer it (the answer that comes second is refused, 409, as without claims). Claims live in
the warehouse (``_claims/<item digest>.json``, one small file per held item, written whole), so
every app over one warehouse sees the others' (each annotator running ``cadestate annotate`` on
a shared warehouse), and an app restarted keeps them. Times are wall-clock seconds (``until``: the
claim's end as its writer's clock saw it); apps on machines whose clocks differ by a minute or more
see each other's claims lapse early or late by as much.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

from cadestate.atomic import atomic_write_bytes
from warehouse.store import file_lock

HOLD_S = 180.0
"""How long a claim holds an item when its page stops renewing it (closed without a word, its
browser gone); the pages renew theirs every third of it."""

CLAIMS_DIR = "_claims"
"""The folder of the claims, under the warehouse root."""

Item = tuple[str, str, int]
"""(clip, kind, track id; -1: a manual-track task, answered whole). Not the task id: a rerun that
replaces a task keeps its items held (the page's answer goes to the newer task where it fits)."""


@dataclass(frozen=True)
class Claim:
    """``client`` holds the item from ``since`` until ``until`` (wall-clock seconds since the epoch)."""

    client: str
    since: float
    until: float


class Claims:
    """The claims of every app over the warehouse at ``root`` (module docstring); safe to share
    between threads and processes (writes under an exclusive ``flock`` of ``_claims/.lock``).
    ``clock``: seconds (wall clock, as every app reads it)."""

    def __init__(self, root: Path, hold_s: float = HOLD_S, clock: Callable[[], float] = time.time):
        self.folder = Path(root) / CLAIMS_DIR
        self.hold_s = hold_s
        self._clock = clock

    def _path(self, item: Item) -> Path:
        key = json.dumps([item[0], item[1], int(item[2])]).encode()
        return self.folder / f"{hashlib.sha256(key).hexdigest()[:32]}.json"

    @staticmethod
    def _read(path: Path) -> tuple[Item, Claim] | None:
        """The claim in ``path``; None if it went (released meanwhile) or is not a claim (edited by hand)."""
        try:
            d = json.loads(path.read_bytes())
            return (str(d["clip"]), str(d["kind"]), int(d["track_id"])), Claim(str(d["client"]), float(d["since"]), float(d["until"]))
        except (OSError, ValueError, KeyError, TypeError):
            return None

    def all(self) -> dict[Item, Claim]:
        """Every claim in force (lapsed ones left out)."""
        now = self._clock()
        found = (self._read(p) for p in sorted(self.folder.glob("*.json")))
        return {item: c for item, c in filter(None, found) if c.until > now}

    def claim(self, client: str, item: Item) -> Claim | None:
        """Hold ``item`` for ``client`` for :attr:`hold_s` from now (renewed if it held it); None,
        or the claim of the other client that holds it (left as it is). Lapsed claims' files are
        removed on the way."""
        with file_lock(self.folder / ".lock"):
            now = self._clock()
            for path in self.folder.glob("*.json"):
                found = self._read(path)
                if found is not None and found[1].until <= now:
                    path.unlink(missing_ok=True)
            path = self._path(item)
            found = self._read(path)  # lapsed ones were removed just now
            held = found[1] if found is not None else None
            if held is not None and held.client != client:
                return held
            new = Claim(client, held.since if held else now, now + self.hold_s)
            doc = {"clip": item[0], "kind": item[1], "track_id": int(item[2]), **asdict(new)}
            atomic_write_bytes(path, json.dumps(doc).encode(), durable=False)
            return None

    def release(self, client: str, item: Item) -> None:
        """Give ``item`` back, if ``client`` holds it."""
        with file_lock(self.folder / ".lock"):
            path = self._path(item)
            found = self._read(path)
            if found is not None and found[1].client == client:
                path.unlink(missing_ok=True)

    def held_by_others(self, client: str | None) -> set[Item]:
        """The items held by clients other than ``client`` (None: by any)."""
        return {i for i, c in self.all().items() if c.client != client}

    def age_s(self, claim: Claim) -> float:
        """Seconds since ``claim``'s client opened its item."""
        return self._clock() - claim.since

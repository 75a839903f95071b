"""Input digests kept with what they read, so that ``cadestate status`` digests again only what changed.

A stage's ``clip_inputs`` (:meth:`tasks.registry.Stage.clip_inputs`: people's answers in force, the
CAD libraries' digest, ...) read warehouse tables, and digesting them costs the import of pyarrow
and the reads, for every stage of every clip on every ``status``. They depend on nothing but the
warehouse's files and the code, so each clip keeps them in ``_cache/inputs/<clip>.json``::

    {"version": ..., "stages": {stage: {"key": ..., "reads": [[...], ...], "states": [...], "inputs": [...]}}}

- ``key``: the memo's version, the stage and its code digest (other code, other digests);
- ``reads``: what the digests read, as the warehouse noted it (:func:`cadestate.lineage.note_read`):
  ``["files", table, partition, ...]`` (``"*"``: every partition) and ``["partitions", table]``;
- ``states``: per read, a digest of its files' (name, inode, size, modification time), or of the
  partitions listed with their folders' modification times.

An entry is used when its key matches and every read is in the same state: files are written
whole, under new names or by an atomic rename (a new inode), so unchanged states mean unchanged
data. An entry is stored only when nothing it read was modified while it was digested (else the
states could be newer than what was read), and storing is best effort: a read-only warehouse just
gets no memo. The flows store the digests they take before running a clip (:mod:`tasks.stage_chain`),
so a ``status`` after a run finds them.

The states and the settling rule are :mod:`warehouse.kept`'s, which keeps other values so too.
"""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Iterator

from cadestate.atomic import atomic_write_bytes
from cadestate.lineage import digest, one_reading, recording_reads
from tasks.registry import Stage
from warehouse import Warehouse
from warehouse.kept import SETTLE_NS, read_state
from warehouse.store import check_name

VERSION = "1"
"""Bump when what an entry means changes: every memo is then digested again."""

class InputsMemo:
    """The memo of one clip (or library): :meth:`clip_inputs` of its stages, then :meth:`save`."""

    def __init__(self, wh: Warehouse, unit: str):
        self.wh = wh
        self.path = wh.root / "_cache" / "inputs" / f"{check_name(unit)}.json"
        self.unit = unit
        self.entries = self._load()
        self.changed = False
        self._states: dict[tuple[str, ...], tuple[str, int]] = {}
        self._since_ns: int | None = None

    @contextlib.contextmanager
    def reading(self) -> Iterator[None]:
        """A block in which the stages' digests are taken from one reading of the warehouse
        (:func:`cadestate.lineage.one_reading`: what several stages digest alike is computed once).
        An entry stored inside counts as taken when the block began: a value computed for an
        earlier stage must not be stored with the state of files changed since. The state of each
        read is taken once in the block, for every stage that read it."""
        self._since_ns = time.time_ns()
        self._states.clear()
        try:
            with one_reading():
                yield
        finally:
            self._since_ns = None

    def _load(self) -> dict[str, dict]:
        try:
            data = json.loads(self.path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return {}
        stages = data.get("stages") if isinstance(data, dict) and data.get("version") == VERSION else None
        return stages if isinstance(stages, dict) else {}

    def _state(self, read: tuple[str, ...]) -> tuple[str, int]:
        if read not in self._states:
            self._states[read] = read_state(self.wh, read)
        return self._states[read]

    def clip_inputs(self, stage: Stage, fresh: bool = False) -> list[str]:
        """``stage.clip_inputs(wh, unit)``: from the memo when its entry holds (see the module), else
        digested again (always when ``fresh``) and kept."""
        if not stage.has("clip_inputs"):
            return []
        key = digest(VERSION, stage.name, stage.code_hash)
        entry = self.entries.get(stage.name)
        if not fresh and isinstance(entry, dict) and entry.get("key") == key and self._holds(entry):
            return list(entry["inputs"])
        started = self._since_ns or time.time_ns()
        with recording_reads() as noted:
            inputs = stage.clip_inputs(self.wh, self.unit)
        reads = list(dict.fromkeys(noted))
        # What was read may have changed while the memo's other entries were checked: states are taken
        # again, except in a reading (a state taken before a change is older than what was read, and an
        # entry of a reading counts from its start: :meth:`reading`).
        if self._since_ns is None:
            self._states.clear()
        states = [self._state(r) for r in reads]
        if all(newest < started - SETTLE_NS for _, newest in states):
            self.entries[stage.name] = {"key": key, "reads": [list(r) for r in reads],
                                        "states": [s for s, _ in states], "inputs": inputs}
            self.changed = True
        else:
            self.entries.pop(stage.name, None)
        return inputs

    def _holds(self, entry: dict) -> bool:
        try:
            reads = [tuple(str(x) for x in r) for r in entry["reads"]]
            return len(reads) == len(entry["states"]) and all(
                self._state(r)[0] == s for r, s in zip(reads, entry["states"]))
        except (KeyError, TypeError, IndexError):
            return False

    def save(self) -> None:
        """Write the memo if it changed (atomically; silently not when the warehouse is read-only)."""
        if self.changed:
            payload = json.dumps({"version": VERSION, "stages": self.entries}, sort_keys=True)
            with contextlib.suppress(OSError):
                atomic_write_bytes(self.path, payload.encode(), durable=False)  # a cache: lost, it is digested again
            self.changed = False

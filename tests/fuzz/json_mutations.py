"""Helpers of the fuzz suites to write JSON that ``json.dumps`` will not (NaN, ``0.0`` for an
integer, a repeated key) and to find and replace the nodes of a document."""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

WRONG_TYPES: dict[type, list] = {dict: ["x", 1, [1], True], list: ["x", 1, {"a": 1}, True], str: [7, True, [], {"a": 1}],
                                 int: ["0", True, [], {"a": 1}], float: ["0.5", True, [], {"a": 1}],
                                 bool: ["true", 1, [], {"a": 1}], type(None): [5, True, [], {"a": 1}]}
"""Values of another JSON type than a node of each type (no null: some fields allow it)."""

BAD_BYTES = [b"\xed\xa0\x80", b"\xff", b"\xc0\xaf", b"\xe9", b"\x80", b"\xf8\x88\x80\x80\x80"]
"""Bytes that are not UTF-8: an encoded surrogate, 0xFF, an overlong '/', Latin-1 'é', a lone
continuation byte, a 5-byte sequence."""


@dataclass(frozen=True)
class Raw:
    """JSON text written as is: NaN, 1e999, a whole number as 0.0, a 30-digit integer."""

    text: str


@dataclass(frozen=True)
class Dup:
    """An object written with a key twice."""

    pairs: tuple[tuple[str, Any], ...]


def dumps(node: Any) -> str:
    """JSON text of ``node``, with :class:`Raw` and :class:`Dup` as they say (strings ASCII-escaped,
    so a lone surrogate is written as ``\\ud800``)."""
    if isinstance(node, Raw):
        return node.text
    if isinstance(node, (dict, Dup)):
        pairs = node.pairs if isinstance(node, Dup) else node.items()
        return "{" + ", ".join(f"{json.dumps(k)}: {dumps(v)}" for k, v in pairs) + "}"
    if isinstance(node, list):
        return "[" + ", ".join(dumps(v) for v in node) + "]"
    return json.dumps(node)


def nodes(doc: Any, path: tuple = ()) -> list[tuple[tuple, Any]]:
    """(path, value) of every node under ``doc`` (not ``doc`` itself)."""
    items = doc.items() if isinstance(doc, dict) else enumerate(doc) if isinstance(doc, list) else ()
    out = []
    for k, v in items:
        out += [((*path, k), v), *nodes(v, (*path, k))]
    return out


def at(doc: Any, path: tuple) -> Any:
    """The node of ``doc`` at ``path``."""
    for k in path:
        doc = doc[k]
    return doc


def put_at(doc: Any, path: tuple, value: Any) -> Any:
    """``doc`` with the node at ``path`` replaced (``path`` empty: ``value`` itself)."""
    if not path:
        return value
    at(doc, path[:-1])[path[-1]] = value
    return doc

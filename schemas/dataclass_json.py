"""JSON Schema (draft 2020-12) from frozen dataclasses, and dataclasses from validated JSON.

The task and label files of :mod:`schemas.labels` are defined once, as dataclasses; their JSON
Schemas are generated here, so the published schema and the Python records cannot drift apart.

Supported field types: ``int``, ``float``, ``str``, ``bool``, ``Literal[...]``, ``X | None``,
nested dataclasses, ``tuple[X, ...]`` (an array) and ``tuple[X, X, X]`` (an array of fixed
length). Field metadata (see :func:`spec`) adds a description and JSON Schema keywords; keywords
under ``items`` apply to the elements of an array. Objects reject unknown properties; a field
without a default is required, and so is a field made with :func:`fixed` (its value is its default:
``kind``, ``format``).
"""

from __future__ import annotations

import dataclasses
import functools
import types
import typing
from typing import Any, Literal, Union

SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"


def spec(description: str, *, unit: str | None = None, frame: str | None = None, default: Any = dataclasses.MISSING,
         items: dict | None = None, omit_default: bool = False, **keywords: Any) -> Any:
    """A dataclass field with its meaning (``description``, ``unit``, ``frame``) and JSON Schema
    ``keywords`` (``minimum``, ``maxItems``, ...); ``items``: keywords for array elements.
    ``omit_default``: :func:`to_json` leaves the field out while it holds its default (a field
    added to a record that files already hold, so those files stay byte for byte the same)."""
    meta = {"description": description, "unit": unit, "frame": frame, "keywords": keywords, "items": items or {},
            "omit_default": omit_default}
    return dataclasses.field(default=default, metadata=meta)


def fixed(description: str, value: Any) -> Any:
    """A required field whose only valid value is ``value`` (also its default)."""
    return dataclasses.field(default=value, metadata={"description": description, "const": True})


def _describe(meta: dict) -> str:
    text = meta.get("description", "")
    extra = [f"unit: {meta['unit']}" if meta.get("unit") else "", f"frame: {meta['frame']}" if meta.get("frame") else ""]
    extra = [e for e in extra if e]
    return f"{text} ({'; '.join(extra)})" if extra else text


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    """The resolved types of the fields of dataclass ``cls``, by name (resolved once per class:
    documents are read often)."""
    hints = typing.get_type_hints(cls, include_extras=False)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def _optional(tp: Any) -> Any | None:
    """``X`` when ``tp`` is ``X | None``, else None."""
    if typing.get_origin(tp) in (Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1 and len(typing.get_args(tp)) == 2:
            return args[0]
    return None


def _type_schema(tp: Any, defs: dict[str, dict], items: dict) -> dict:
    inner = _optional(tp)
    if inner is not None:
        return {"anyOf": [_type_schema(inner, defs, items), {"type": "null"}]}
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        _define(tp, defs)
        return {"$ref": f"#/$defs/{tp.__name__}"}
    if origin is Literal:
        return {"enum": list(typing.get_args(tp))}
    if origin is tuple:
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return {"type": "array", "items": {**_type_schema(args[0], defs, {}), **items}}
        if len(set(args)) != 1:
            raise TypeError(f"fixed-length tuples must have one element type: {tp}")
        return {"type": "array", "items": {**_type_schema(args[0], defs, {}), **items},
                "minItems": len(args), "maxItems": len(args)}
    simple = {int: "integer", float: "number", str: "string", bool: "boolean"}
    if tp in simple:
        return {"type": simple[tp]}
    raise TypeError(f"unsupported field type {tp!r}")


def _define(cls: type, defs: dict[str, dict]) -> None:
    """Add ``cls`` (and the dataclasses it uses) to ``defs``."""
    if cls.__name__ in defs:
        return
    defs[cls.__name__] = {}  # placeholder: recursion stops here
    props, required = {}, []
    hints = _hints(cls)
    for f in dataclasses.fields(cls):
        meta = dict(f.metadata)
        if meta.get("const"):
            prop = {"const": f.default}
        else:
            prop = _type_schema(hints[f.name], defs, meta.get("items", {}))
            keywords = meta.get("keywords", {})
            if "anyOf" in prop and keywords:  # constraints apply to the non-null branch
                prop["anyOf"][0].update(keywords)
            else:
                prop.update(keywords)
        if meta.get("description"):
            prop = {"description": _describe(meta), **prop}
        props[f.name] = prop
        if meta.get("const") or (f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING):
            required.append(f.name)
    doc = " ".join((cls.__doc__ or "").split())
    defs[cls.__name__] = {"type": "object", "description": doc, "properties": props, "required": required,
                          "additionalProperties": False}


def json_schema_of(cls: type, *, schema_id: str, title: str) -> dict:
    """The JSON Schema document of dataclass ``cls`` (its own definition at the root)."""
    defs: dict[str, dict] = {}
    _define(cls, defs)
    root = defs.pop(cls.__name__)
    out = {"$schema": SCHEMA_DIALECT, "$id": schema_id, "title": title, **root}
    if defs:
        out["$defs"] = dict(sorted(defs.items()))
    return out


def from_json(tp: Any, value: Any) -> Any:
    """Build ``tp`` (a dataclass or a supported field type) from a document that already passed
    its JSON Schema. Arrays become tuples; numbers become ``float`` where a float is declared."""
    inner = _optional(tp)
    if inner is not None:
        return None if value is None else from_json(inner, value)
    if dataclasses.is_dataclass(tp):
        hints = _hints(tp)
        return tp(**{k: from_json(hints[k], v) for k, v in value.items() if k in hints})
    origin = typing.get_origin(tp)
    if origin is tuple:
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(from_json(args[0], v) for v in value)
        return tuple(from_json(a, v) for a, v in zip(args, value))
    if tp is float:
        return float(value)
    if tp is int:
        return int(value)
    return value


def to_json(obj: Any) -> Any:
    """A dataclass (or value) as plain JSON data: tuples become lists; every field is written but
    those made with ``omit_default`` that hold their default."""
    if dataclasses.is_dataclass(obj):
        return {f.name: to_json(getattr(obj, f.name)) for f in dataclasses.fields(obj)
                if not (f.metadata.get("omit_default") and getattr(obj, f.name) == f.default)}
    if isinstance(obj, (tuple, list)):
        return [to_json(v) for v in obj]
    return obj

"""Command-line values converted without Pydantic where the result is plain (issue "Seconds per command").

Typer (0.29) converts every parameter's value with a Pydantic ``TypeAdapter`` that it builds when the
command runs: importing Pydantic and its plugin loader (``importlib.metadata``) and building the
adapters costs about as much as importing DuckDB, in every command that takes a value (``-w DIR``).
:func:`install` makes Typer's parameters defer that: a value whose conversion is plain is converted
here exactly as Typer's adapter would (a ``str`` stays itself; a ``Path`` is ``Path(value)`` checked by
Typer's own :func:`typer._param_types.coerce_cli_path`; an enum member or choice by Typer's own
:func:`typer._param_types.coerce_cli_choice`; a ``list[str]`` is a list of the strings); any other
value, and any value the plain conversion refuses, goes to Typer's adapter, built then (so its
messages are Typer's). ``tests/test_cli_params.py`` checks each against Typer's adapter.

Relies on Typer's internals (``_TyperParameter.get_runtime_param``, ``RuntimeParam``): when they are
not there (another Typer), nothing is installed and Typer converts every value itself.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any, get_args, get_origin

_INSTALLED = False


def install() -> bool:
    """Make Typer convert plain values without Pydantic (see the module); False when Typer's
    internals are not the ones this was written for (nothing changed)."""
    global _INSTALLED
    if _INSTALLED:
        return True
    try:
        from typer._coercion import RuntimeParam, TypeDescriptor, build_runtime_param
        from typer._param_types import coerce_cli_choice, coerce_cli_path
        from typer.core import _TyperParameter
    except ImportError:
        return False
    original = getattr(_TyperParameter, "get_runtime_param", None)
    if original is None or "_runtime_param" not in getattr(_TyperParameter, "__annotations__", {}):
        return False

    @dataclass(frozen=True)
    class DeferredParam(RuntimeParam):
        """Converts plain values itself; builds Typer's runtime parameter for any other."""

        descriptor: TypeDescriptor

        def _typer(self):
            built = self.__dict__.get("_built")
            if built is None:
                built = build_runtime_param(self.descriptor)
                object.__setattr__(self, "_built", built)
            return built

        def _coerce_value(self, value: Any, param: Any, ctx: Any) -> Any:
            done, result = plain_value(self.descriptor, value, param, ctx)
            return result if done else self._typer()._coerce_value(value, param=param, ctx=ctx)

    def plain_value(descriptor: Any, value: Any, param: Any, ctx: Any) -> tuple[bool, Any]:
        info, annotation = descriptor.parameter_info, descriptor.annotation
        if info.parser is not None or descriptor.file_annotation is not None:
            return False, None
        if annotation is str and type(value) is str:
            return True, value
        if annotation is Path and info.path_type is None and type(value) is str:
            return True, coerce_cli_path(Path(value), info, path_type=Path, param=param, ctx=ctx)
        if isinstance(annotation, type) and issubclass(annotation, Enum):
            try:
                return True, coerce_cli_choice(value, choices=list(annotation), case_sensitive=info.case_sensitive, ctx=ctx)
            except ValueError:  # Typer's adapter words the error
                return False, None
        if get_origin(annotation) is list and get_args(annotation) == (str,) and isinstance(value, (list, tuple)) \
                and all(type(v) is str for v in value):
            return True, list(value)
        return False, None

    def get_runtime_param(self):
        if self._runtime_param is None:
            d = self.type_descriptor
            self._runtime_param = DeferredParam(parameter_info=d.parameter_info, annotation=d.annotation, descriptor=d)
        return self._runtime_param

    _TyperParameter.get_runtime_param = get_runtime_param
    install.plain_value = plain_value  # for the tests
    _INSTALLED = True
    return True

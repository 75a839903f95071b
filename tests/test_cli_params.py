"""Command-line values converted without Pydantic (:mod:`cadestate.cli.params`) come out exactly as
Typer's own adapter converts them, and anything else still goes to Typer's adapter."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Annotated, Optional

import pytest
import typer
from typer._click.exceptions import BadParameter
from typer._coercion import build_runtime_param
from typer.main import get_command
from typer.testing import CliRunner

from cadestate.cli import app
from cadestate.cli.params import install


class Colour(str, Enum):
    red = "red"
    green = "green"


demo = typer.Typer()
got: dict = {}


@demo.command()
def every(
    text: Annotated[str, typer.Argument()],
    clips: Annotated[Optional[list[str]], typer.Argument()] = None,
    where: Annotated[Optional[Path], typer.Option("--where")] = None,
    existing: Annotated[Optional[Path], typer.Option("--existing", exists=True, file_okay=False)] = None,
    colour: Annotated[Colour, typer.Option("--colour")] = Colour.red,
    number: Annotated[Optional[int], typer.Option("--number", min=0)] = None,
) -> None:
    got.update(text=text, clips=clips, where=where, existing=existing, colour=colour, number=number)


def test_installed_on_this_typer():
    assert install()  # the pinned Typer has the internals it relies on (else every value goes to Typer's adapter)


@pytest.mark.parametrize("argv", [
    ["plain"], ["", "a", "b"], ["x", "--where", "rel/dir"], ["x", "--where", ""], ["x", "--where", "/abs/ü"],
    ["x", "--colour", "green"], ["x", "--colour", "GREEN"], ["x", "--colour", "blue"], ["x", "--number", "3"],
    ["x", "--number", "-1"], ["x", "--existing", "/nonexistent/dir"], ["x", "--existing", "/"],
    ["x", "--existing", __file__], ["\udcff"],
])
def test_plain_values_as_typer_converts_them(argv, tmp_path):
    command = get_command(demo)
    for param in command.params:  # each value as the patched parameter converts it, and as Typer's adapter does
        ctx = command.make_context("every", list(argv), resilient_parsing=True)
        raw = ctx.params.get(param.name)
        param._runtime_param = None
        ours = _outcome(lambda: param.get_runtime_param().coerce(raw, param=param, ctx=ctx))
        theirs = _outcome(lambda: build_runtime_param(param.type_descriptor).coerce(raw, param=param, ctx=ctx))
        assert ours == theirs, (param.name, raw)


def _outcome(convert):
    try:
        value = convert()
        return ("value", type(value), value)
    except BadParameter as e:
        return ("error", e.format_message())


def test_commands_run_the_same():
    runner = CliRunner()
    result = runner.invoke(demo, ["t", "c1", "c2", "--where", "w", "--colour", "green"])
    assert result.exit_code == 0, result.output
    assert got == {"text": "t", "clips": ["c1", "c2"], "where": Path("w"), "existing": None, "colour": Colour.green,
                   "number": None}
    result = runner.invoke(demo, ["t", "--colour", "blue"])
    assert result.exit_code == 2 and "blue" in result.output
    result = runner.invoke(demo, ["t", "--existing", "/nonexistent/dir"])
    assert result.exit_code == 2 and "does not exist" in result.output
    assert runner.invoke(app, ["config", "show"]).exit_code == 0

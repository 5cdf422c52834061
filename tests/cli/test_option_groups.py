"""Option groups: one dataclass parameter standing for several command-line options."""

from __future__ import annotations

import inspect
from dataclasses import dataclass
from typing import Annotated

import pytest
import typer
from typer.testing import CliRunner

from deltar.cli.option_groups import option_group


@dataclass(frozen=True)
class _Pair:
    left: int = 1
    right: str = "r"


_pair_options = option_group("pair", _Pair, {
    "left": Annotated[int, typer.Option("--left", help="Left.")],
    "right": Annotated[str, typer.Option("--right", help="Right.")]})


def test_the_options_stand_where_the_parameter_stood_and_the_command_gets_one_object():
    seen = []

    @_pair_options
    def command(first: str = "f", pair: _Pair = _Pair(), last: int = 0) -> None:
        seen.append((first, pair, last))

    assert list(inspect.signature(command).parameters) == ["first", "left", "right", "last"]
    app = typer.Typer()
    app.command()(command)
    result = CliRunner().invoke(app, ["--left", "5", "--last", "2"])
    assert result.exit_code == 0, result.output
    assert seen == [("f", _Pair(5, "r"), 2)]
    with pytest.raises(TypeError, match="has no 'pair' parameter"):
        _pair_options(lambda first="f": None)

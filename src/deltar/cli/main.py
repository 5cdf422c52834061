"""Entry point of the ``deltar`` command: one typer app with the commands of
:data:`deltar.cli.commands.COMMANDS`."""

from __future__ import annotations

import typer

from deltar.cli.commands import COMMANDS
from deltar.cli.errors import DeltarGroup

app = typer.Typer(
    name="deltar",
    cls=DeltarGroup,
    help="Dense metric depth from an RGB camera and a multi-zone ToF sensor (DELTAR).",
    no_args_is_help=True,
    pretty_exceptions_show_locals=False,
)


@app.callback()
def _root() -> None:
    """Dense metric depth from an RGB camera and a multi-zone ToF sensor (DELTAR)."""


for _name, _command in COMMANDS:
    app.command(_name)(_command)


def main(args: list[str] | None = None) -> None:
    """Run the CLI (``args`` defaults to ``sys.argv[1:]``)."""
    app(args=args)


if __name__ == "__main__":
    main()

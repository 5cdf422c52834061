"""Entry point of the ``deltar`` command: one typer app, commands registered per concern."""

from __future__ import annotations

import typer

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


def _register_commands() -> None:
    # Each concern's module adds its commands to ``app``; imports stay here so that
    # ``deltar --help`` lists everything.
    from deltar.cli import commands  # noqa: F401


def main(args: list[str] | None = None) -> None:
    """Run the CLI (``args`` defaults to ``sys.argv[1:]``)."""
    _register_commands()
    app(args=args)


if __name__ == "__main__":
    main()

"""The ``deltar`` executable: stop signals handled from its first instruction to its last.

:class:`~deltar.cli.errors.DeltarGroup` handles Ctrl+C and SIGTERM while a command runs.
Before that (importing the command line takes a few tenths of a second) and after it
(the interpreter's teardown, a second or more once PyTorch is loaded) Python's defaults
would print a ``KeyboardInterrupt`` traceback or end the process without a word. Here a
stop during start-up ends it with the same ``error: interrupted by ...`` line and status
128 + the signal, and one during teardown is ignored: the command's outputs are complete
and its status stands.
"""

from __future__ import annotations

import os
import signal
import sys
from typing import Any

_STOPS = (signal.SIGINT, signal.SIGTERM)


def _stopped_while_starting(signum: int, frame: Any) -> None:
    """Nothing is written yet: say so in the commands' one line and end at once."""
    name = "Ctrl+C" if signum == signal.SIGINT else signal.Signals(signum).name
    os.write(2, f"error: interrupted by {name}\n".encode())
    os._exit(128 + signum)


# DeltarGroup replaces this handler with its own while a command runs, and restores it.
_stopped_while_starting.deltar_replaceable = True  # type: ignore[attr-defined]


def main(args: list[str] | None = None) -> None:
    """Run the ``deltar`` command line (``args`` defaults to ``sys.argv[1:]``)."""
    if _is_main_thread():
        for stop in _STOPS:
            if signal.getsignal(stop) in (signal.SIG_DFL, signal.default_int_handler):
                signal.signal(stop, _stopped_while_starting)
    from deltar.cli.main import main as run_command_line

    try:
        run_command_line(args)
    finally:
        if _is_main_thread():
            for stop in _STOPS:
                if signal.getsignal(stop) is _stopped_while_starting:
                    signal.signal(stop, signal.SIG_IGN)  # teardown: the outputs are done
    sys.exit(0)


def _is_main_thread() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()

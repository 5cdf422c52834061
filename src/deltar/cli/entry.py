"""The ``deltar`` executable: stop signals handled from its first instruction to its last.

:class:`~deltar.cli.errors.DeltarGroup` handles Ctrl+C and SIGTERM while a command runs.
Before that (importing the command line takes a few tenths of a second) and after it
(the interpreter's teardown, a second or more once PyTorch is loaded) Python's defaults
would print a ``KeyboardInterrupt`` traceback or end the process without a word. Here a
stop during start-up ends it with the same ``error: interrupted by ...`` line and status
128 + the signal, and one during teardown ends it at once with the finished command's
own status (its outputs are complete; a teardown that hangs, e.g. on a stalled camera
thread, still ends).

This module owns the process's stop signals to its end: it is the console script's and
``python -m deltar``'s entry point only. To run a command inside a Python process, call
:func:`deltar.cli.main.main`.
"""

from __future__ import annotations

import os
import signal
import sys
from typing import Any

_STOPS = (signal.SIGINT, signal.SIGTERM)
#: The finished command's exit status once it is known (None while starting or running).
_FINISHED: dict[str, int | None] = {"status": None}


def _stopped_outside_a_command(signum: int, frame: Any) -> None:
    """Starting: nothing is written yet, say so in the commands' one line and end.
    Finished: end at once with the command's status."""
    status = _FINISHED["status"]
    if status is None:
        name = "Ctrl+C" if signum == signal.SIGINT else signal.Signals(signum).name
        os.write(2, f"error: interrupted by {name}\n".encode())
        status = 128 + signum
    else:
        sys.stdout.flush()
    atomic = sys.modules.get("deltar.io.atomic")  # os._exit skips the exit hooks
    if atomic is not None:
        atomic.remove_unfinished_temporaries()
    os._exit(status)


# DeltarGroup replaces this handler with its own while a command runs, and restores it.
_stopped_outside_a_command.deltar_replaceable = True  # type: ignore[attr-defined]


def main() -> None:
    """Run the ``deltar`` command line on ``sys.argv[1:]`` and exit with its status."""
    if threading_is_main():
        for stop in _STOPS:
            if signal.getsignal(stop) in (signal.SIG_DFL, signal.default_int_handler):
                signal.signal(stop, _stopped_outside_a_command)
    from deltar.cli.main import main as run_command_line

    try:
        run_command_line()
    except SystemExit as end:
        code = end.code
        _FINISHED["status"] = code if isinstance(code, int) else (0 if code is None else 1)
        raise
    _FINISHED["status"] = 0


def threading_is_main() -> bool:
    """Whether this runs on the main thread (only it can set signal handlers)."""
    import threading

    return threading.current_thread() is threading.main_thread()

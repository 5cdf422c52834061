"""One error style for every command.

A user mistake ends with a single line ``error: <message naming the argument or file>``
on stderr: exit code 1 for bad input (files, values found wrong while running), 2 for
usage errors (options the command line parser or a command refuses before any work).
Warnings, the library's Python warnings included, are single ``warning: ...`` lines.
Messages are printed literally, never interpreted as rich markup (a file called
``[scan]frame.png`` prints as is).

:class:`DeltarGroup` (the ``deltar`` command group) turns the library's
``ValueError`` / ``OSError`` / ``ImportError`` into that line, so commands can let them
propagate; a missing optional module names the extra that installs it
(:func:`deltar.extras.missing_extra_message`). Set ``DELTAR_TRACEBACK=1`` to see the
Python traceback instead.

Ctrl+C and SIGTERM (a scheduler's or a service manager's stop) both stop a command the
way Ctrl+C does, so that files being written are finished or removed (every output is
written whole, then renamed) and all-or-nothing outputs are cleaned up; the command ends
with one ``error: interrupted by ...`` line and status 130 or 143 (128 + the signal).
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
import warnings
from typing import Any, NoReturn

import typer
from typer.core import TyperGroup

try:  # recent typer vendors click
    from typer._click.exceptions import ClickException, UsageError
    from typer._click.utils import echo
except ImportError:  # pragma: no cover - older typer on top of click
    from click import echo
    from click.exceptions import ClickException, UsageError

#: The stop signal a running command received ("SIGINT" / "SIGTERM"), None before one.
_INTERRUPT: dict[str, Any] = {"signal": None, "at": 0.0}
#: Whether a command printed its own ``error:`` line (:func:`fail`).
_REPORTED: dict[str, bool] = {"error": False}


#: Seconds after a stop signal during which a further one is ignored: it would raise a
#: second exception inside the first one's clean-up (two tools sending SIGTERM); later,
#: it is a user asking again because the first was lost, and stops once more.
REPEATED_STOP_S = 2.0


def _on_stop_signal(signum: int, frame: Any) -> None:
    """Stop as Ctrl+C does (``KeyboardInterrupt``), remembering which signal it was."""
    now = time.monotonic()
    if _INTERRUPT["signal"] is not None and now - _INTERRUPT["at"] < REPEATED_STOP_S:
        return
    _INTERRUPT["signal"], _INTERRUPT["at"] = signal.Signals(signum).name, now
    raise KeyboardInterrupt


def _quiet_after_stop(unraisable: Any) -> None:
    """``sys.unraisablehook`` while a command runs: once it was told to stop, exceptions
    Python can only print (a DataLoader worker killed by the same SIGTERM, the stop
    itself raised inside a weakref callback) are consequences of the stop, not news."""
    if _INTERRUPT["signal"] is None:
        sys.__unraisablehook__(unraisable)


def received_signal() -> str | None:
    """The stop signal the running command received ("SIGINT" / "SIGTERM"), or None."""
    return _INTERRUPT["signal"]


def stop_name() -> str:
    """How messages name the stop the running command received: ``"Ctrl+C"`` (also for
    a ``KeyboardInterrupt`` without a signal) or ``"SIGTERM"``."""
    name = _INTERRUPT["signal"]
    return "Ctrl+C" if name in (None, "SIGINT") else name


def check_interrupt() -> None:
    """Raise ``KeyboardInterrupt`` again when a stop signal arrived but its exception was
    lost (raised inside a callback Python ignores exceptions in, e.g. a weakref's): long
    loops call this once per item (:class:`~deltar.cli.progress.ProgressReport` does)."""
    if _INTERRUPT["signal"] is not None:
        raise KeyboardInterrupt


def _interrupt_status(status: Any) -> Any:
    """After a command stopped by Ctrl+C or SIGTERM (Typer ends both with status 130):
    say so in one line, unless the command already did, and give 128 + the signal."""
    name = _INTERRUPT["signal"]
    if status != 130 or name is None:
        return status
    if not _REPORTED["error"]:
        error_line(f"interrupted by {stop_name()}; every file written before it is "
                   "complete (each is written whole, then renamed)")
    return 128 + int(getattr(signal, name))


#: Exceptions that mean "the input (or the environment) is wrong", not "deltar is broken".
USER_ERRORS: tuple[type[BaseException], ...] = (ValueError, OSError, ImportError)


def format_error(err: BaseException) -> str:
    """One line describing ``err``; operating-system errors as ``<path>: <reason>``."""
    if isinstance(err, OSError) and err.strerror and err.filename:
        text = f"{err.filename}: {err.strerror}"
        if err.filename2:
            text = f"{err.filename} -> {err.filename2}: {err.strerror}"
    elif isinstance(err, ModuleNotFoundError) and err.name:
        from deltar.extras import missing_extra_message

        if "pip install" in str(err):  # already names its extra (deltar.extras)
            text = str(err)
        else:
            text = (missing_extra_message(err.name) or
                    f"{err}: install the optional dependency (see the README's extras)")
    else:
        text = str(err) or type(err).__name__
    return " ".join(text.split())


def error_line(message: str) -> None:
    """Print ``error: <message>`` on stderr as one literal line."""
    echo(f"error: {' '.join(str(message).split())}", err=True)


def warn(message: str) -> None:
    """Print ``warning: <message>`` on stderr as one literal line."""
    echo(f"warning: {' '.join(str(message).split())}", err=True)


def fail(err: BaseException | str, code: int = 1) -> NoReturn:
    """Print ``err`` as the ``error:`` line and exit with ``code`` (1: bad input)."""
    _REPORTED["error"] = True
    error_line(err if isinstance(err, str) else format_error(err))
    raise typer.Exit(code)


def _usage_message(err: UsageError) -> str:
    message = err.format_message()
    ctx = getattr(err, "ctx", None)
    if ctx is not None:
        message += f" (see '{ctx.command_path} --help')"
    return message


class DeltarGroup(TyperGroup):
    """The ``deltar`` group: every failure reaches the user as one ``error:`` line."""

    def main(self, args: Any = None, prog_name: str | None = None,
             complete_var: str | None = None, standalone_mode: bool = True,
             **extra: Any) -> Any:
        """Run the command line; in standalone mode, exit with the command's status."""
        if not standalone_mode:
            return super().main(args=args, prog_name=prog_name, complete_var=complete_var,
                                standalone_mode=False, **extra)
        formatter = warnings.formatwarning
        warnings.formatwarning = _format_warning
        handlers = {}
        if threading.current_thread() is threading.main_thread():
            for stop in (signal.SIGINT, signal.SIGTERM):
                current = signal.getsignal(stop)
                if current in (signal.SIG_DFL, signal.default_int_handler) or \
                        getattr(current, "deltar_replaceable", False):  # cli.entry's
                    handlers[stop] = signal.signal(stop, _on_stop_signal)
        _INTERRUPT["signal"], _REPORTED["error"] = None, False
        unraisable_hook, sys.unraisablehook = sys.unraisablehook, _quiet_after_stop
        try:
            try:
                status = super().main(args=args, prog_name=prog_name,
                                      complete_var=complete_var, standalone_mode=False,
                                      **extra)
            except KeyboardInterrupt:  # raised outside the command (e.g. in Typer's exit)
                status = 130
            status = _interrupt_status(status)
        except UsageError as err:
            if type(err).__name__ == "NoArgsIsHelpError":  # bare ``deltar``: the help
                err.show()
            else:
                error_line(_usage_message(err))
            sys.exit(err.exit_code)
        except ClickException as err:
            error_line(err.format_message())
            sys.exit(err.exit_code)
        except typer.Abort:
            error_line("aborted")
            sys.exit(1)
        except USER_ERRORS as err:
            if os.environ.get("DELTAR_TRACEBACK"):
                raise
            error_line(format_error(err))
            sys.exit(1)
        finally:
            warnings.formatwarning = formatter
            for stop, handler in handlers.items():
                signal.signal(stop, handler)
            sys.unraisablehook = unraisable_hook
            _INTERRUPT["signal"] = None  # the next command in this process starts afresh
        sys.exit(status if isinstance(status, int) else 0)


def _format_warning(message: Warning | str, category: type[Warning], filename: str,
                    lineno: int, line: str | None = None) -> str:
    """Library warnings as one ``warning:`` line (no source location, no code line)."""
    return f"warning: {' '.join(str(message).split())}\n"

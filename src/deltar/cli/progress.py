"""Progress of long commands, on a terminal and in a log file.

On a terminal, a rich progress bar (removed when done). When stdout is not a terminal
(a log file, a pipe, a CI job), plain lines instead, at most one every
``DELTAR_PROGRESS_SECONDS`` seconds (10 by default; 0 prints every step) plus a final
one::

    predicting: 40/120 frames, 3.2 frames/s, ETA 25 s
"""

from __future__ import annotations

import os
import sys
import time
from typing import Any

#: Environment variable: seconds between progress lines when stdout is not a terminal.
INTERVAL_ENV = "DELTAR_PROGRESS_SECONDS"
DEFAULT_INTERVAL_S = 10.0


#: Width of printed tables when stdout is not a terminal (a log file, a pipe) and
#: ``COLUMNS`` is not set: wide enough for every table the commands print, where rich's
#: default of 80 columns would cut the method names and figures to ellipses.
LOG_WIDTH = 160


def table_console() -> Any:
    """A ``rich.console.Console`` for printing tables: the terminal's own width when
    stdout is a terminal; elsewhere ``COLUMNS`` when it is a number, else
    :data:`LOG_WIDTH` columns.

    Whether stdout is a terminal is asked of stdout itself, as for the progress lines:
    rich counts ``FORCE_COLOR`` (set by many CI runners) as a terminal and would then
    fall back to 80 columns in a log.
    """
    from rich.console import Console

    if sys.stdout.isatty() or os.environ.get("COLUMNS", "").strip().isdigit():
        return Console()
    return Console(width=LOG_WIDTH)


def _interval_s() -> float:
    try:
        return max(0.0, float(os.environ.get(INTERVAL_ENV, DEFAULT_INTERVAL_S)))
    except ValueError:
        return DEFAULT_INTERVAL_S


def _duration(seconds: float) -> str:
    seconds = round(seconds)
    if seconds < 60:
        return f"{seconds} s"
    if seconds < 3600:
        return f"{seconds // 60} min {seconds % 60:02d} s"
    return f"{seconds // 3600} h {seconds % 3600 // 60:02d} min"


class ProgressReport:
    """Count steps of a long job and show them (use as a context manager).

    Args:
        description: what is being done, e.g. ``"predicting"``.
        total: number of steps when known.
        unit: what a step is, e.g. ``"frames"``.
        terminal: force the terminal (True) or line (False) display; by default a
            bar when stdout is a terminal.
    """

    def __init__(self, description: str, total: int | None = None, *, unit: str = "frames",
                 terminal: bool | None = None) -> None:
        self.description = description
        self.total = total
        self.unit = unit
        self.done = 0
        self.terminal = sys.stdout.isatty() if terminal is None else terminal
        self.interval_s = _interval_s()
        self._bar: Any = None
        self._task: Any = None
        self._start = self._last = 0.0

    def __enter__(self) -> ProgressReport:
        self._start = self._last = time.monotonic()
        if self.terminal:
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                TextColumn,
                TimeRemainingColumn,
            )

            self._bar = Progress(TextColumn("{task.description}"), BarColumn(),
                                 MofNCompleteColumn(), TimeRemainingColumn(), transient=True)
            self._bar.__enter__()
            self._task = self._bar.add_task(self.description, total=self.total)
        return self

    def __exit__(self, *exc_info: Any) -> None:
        if self._bar is not None:
            self._bar.__exit__(*exc_info)
        elif self.done and exc_info[0] is None:
            self._line()

    def set_total(self, total: int | None) -> None:
        """Change the number of steps once the job knows it better."""
        self.total = total
        if self._bar is not None:
            self._bar.update(self._task, total=total)

    def advance(self, steps: int = 1) -> None:
        """Count ``steps`` more steps done."""
        self.update(self.done + steps)

    def update(self, done: int) -> None:
        """Set the number of steps done (and stop here if a stop signal's exception was
        lost: :func:`~deltar.cli.errors.check_interrupt`)."""
        from deltar.cli.errors import check_interrupt

        check_interrupt()
        self.done = done
        if self._bar is not None:
            self._bar.update(self._task, completed=done)
            return
        now = time.monotonic()
        if now - self._last >= self.interval_s and (self.total is None or done < self.total):
            self._last = now
            self._line()

    def line(self) -> str:
        """The progress line as text (count, rate, ETA when the total is known)."""
        elapsed = max(time.monotonic() - self._start, 1e-9)
        rate = self.done / elapsed
        count = f"{self.done}/{self.total}" if self.total is not None else f"{self.done}"
        text = f"{self.description}: {count} {self.unit}, {rate:.2f} {self.unit}/s"
        if self.total is not None and self.done < self.total and rate > 0:
            text += f", ETA {_duration((self.total - self.done) / rate)}"
        elif self.total is not None and self.done >= self.total:
            text += f", done in {_duration(elapsed)}"
        return text

    def _line(self) -> None:
        print(self.line(), flush=True)

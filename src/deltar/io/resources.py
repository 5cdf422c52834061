"""What this machine has: CPUs, memory, free disk space; checks of requests against it.

Options that ask for resources (``--threads``, ``--batch``, a training run's
``devices``, the size of a set about to be written) are checked here before any work,
so a request the machine cannot meet ends with one message instead of a crash, an
out-of-memory kill or a full disk half-way.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

#: Threads per CPU a command may ask for; far beyond it, thread pools only add overhead
#: (and huge counts crash the native thread pools).
MAX_THREADS_PER_CPU = 4


def cpu_count() -> int:
    """CPUs this process may run on (its affinity mask where the system has one)."""
    try:
        return len(os.sched_getaffinity(0)) or 1
    except (AttributeError, OSError):  # pragma: no cover - macOS, Windows
        return os.cpu_count() or 1


def check_threads(threads: int, name: str = "threads") -> int:
    """Check a thread count: at least 1, at most :data:`MAX_THREADS_PER_CPU` per CPU.

    Args:
        threads: the requested count.
        name: the option or argument, for the message (e.g. ``"--threads"``).

    Returns:
        ``threads`` as an int.

    Raises:
        ValueError: ``"<name> must be between 1 and <limit> (4 x the <n> CPUs of this
            machine), got <threads>"``; also for booleans and fractions.
    """
    cpus = cpu_count()
    limit = MAX_THREADS_PER_CPU * cpus
    if isinstance(threads, bool) or int(threads) != threads or not 1 <= threads <= limit:
        raise ValueError(f"{name} must be between 1 and {limit} ({MAX_THREADS_PER_CPU} x the "
                         f"{cpus} CPUs of this machine), got {threads!r}")
    return int(threads)


def available_memory_bytes() -> int | None:
    """``MemAvailable`` of /proc/meminfo in bytes (None where there is none)."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def check_memory(need_bytes: float, what: str, advice: str) -> None:
    """Refuse work whose memory estimate exceeds the memory available now.

    Args:
        need_bytes: the estimate, bytes.
        what: the request, for the message (e.g. ``"--batch 4096 at 480x640"``).
        advice: what to lower, for the message.

    Raises:
        ValueError: ``"<what> needs about <n> MiB of memory, more than the <m> MiB this machine has
            available; <advice>"`` (nothing is checked where the available memory is
            unknown).
    """
    available = available_memory_bytes()
    if available is not None and need_bytes > available:
        raise ValueError(f"{what} needs about {need_bytes / 2**20:,.0f} MiB of memory, more "
                         f"than the {available / 2**20:,.0f} MiB this machine has available; "
                         f"{advice}")


def check_free_space(folder: str | os.PathLike, need_bytes: float, what: str) -> None:
    """Refuse to start writing ``need_bytes`` into ``folder`` when its disk has less free.

    Args:
        folder: where the files go (it, or its nearest existing parent, is measured).
        need_bytes: how much will be written, bytes (an upper estimate).
        what: the output, for the message (e.g. ``"OUT data/sim"``).

    Raises:
        OSError: ``"<what>: needs up to <n> MiB but <disk> has <m> MiB free"``.
    """
    probe = Path(folder)
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    free = shutil.disk_usage(probe).free
    if need_bytes > free:
        raise OSError(f"{what}: needs up to {need_bytes / 2**20:,.1f} MiB but "
                      f"{probe} has {free / 2**20:,.1f} MiB free")

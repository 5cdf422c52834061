"""A recording's ``zones.jsonl``: appending one zone frame a line, safely.

The one file of a recording that grows instead of being written whole
(docs/formats.md). An interrupted append leaves at most a partial last line
(:func:`end_partial_line` sets it aside before the next append), and every append
checks its frame against the file's own last frame under an exclusive lock, so that two
writers on one folder cannot interleave timestamps the reader refuses.
"""

from __future__ import annotations

import errno
import json
import os
import time
import warnings
from pathlib import Path

try:  # POSIX; elsewhere appends are checked without the lock
    import fcntl
except ImportError:  # pragma: no cover - not POSIX
    fcntl = None  # type: ignore[assignment]

from deltar.io.atomic import write_bytes_atomic
from deltar.io.zone_file import zone_frame_from_dict


def append_zone_line(path: Path, line: str, timestamp_s: float) -> None:
    """Append ``line`` (one zone frame's JSON and its newline) to ``path``, holding an
    exclusive lock, when ``timestamp_s`` is after the file's last frame.

    One write per line, flushed and synced: a crash leaves at most one partial last line.

    Raises:
        ValueError: ``timestamp_s`` not after the last frame in the file (e.g. written by
            another writer on the same folder).
    """
    with open(path, "a+b") as handle:
        _lock(handle)
        if handle.seek(0, os.SEEK_END) and not _ends_with_newline(handle):
            end_partial_line(path)  # another writer was interrupted mid-line
        last = _last_timestamp(handle)
        if last is not None and not timestamp_s > last:
            raise ValueError(f"zone frame timestamp {timestamp_s} is not after the previous "
                             f"one ({last}) in {path}")
        handle.write(line.encode("utf-8"))
        handle.flush()
        os.fsync(handle.fileno())


#: What flock answers on a filesystem without it (e.g. NFS without lockd, some FUSE mounts).
_NO_FLOCK = {errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOTSUP, errno.ENOSYS, errno.EINVAL}


def _lock(handle) -> None:
    """Lock ``handle`` exclusively (released when closed); where the filesystem has no
    flock, append unlocked (as a single writer always could) instead of failing."""
    if fcntl is None:
        return
    try:
        fcntl.flock(handle.fileno(), fcntl.LOCK_EX)
    except OSError as err:
        if err.errno not in _NO_FLOCK:
            raise


def _ends_with_newline(handle) -> bool:
    handle.seek(-1, os.SEEK_END)
    return handle.read(1) == b"\n"


def end_partial_line(path: Path) -> None:
    """Before appending to ``zones.jsonl``: an interrupted append can leave a last line
    without its newline, and a new line written after it would join it (the file would
    then hold a corrupt line in its middle). A complete reading that only lacks the
    newline gets it; an incomplete one is moved, byte for byte, to
    ``zones.jsonl.partial-<ns>`` beside it (with a warning) and cut from the file."""
    if not path.is_file():
        return
    data = path.read_bytes()
    if not data or data.endswith(b"\n"):
        return
    start = data.rfind(b"\n") + 1
    tail = data[start:]
    try:
        zone_frame_from_dict(json.loads(tail.decode("utf-8")), source=str(path))
    except (ValueError, UnicodeDecodeError):  # JSONDecodeError is a ValueError
        kept = path.with_name(f"{path.name}.partial-{time.time_ns()}")
        write_bytes_atomic(kept, tail, overwrite=False)
        warnings.warn(f"{path}: its last line was cut off (an interrupted recording); "
                      f"moved its {len(tail)} bytes to {kept.name} before appending",
                      stacklevel=3)
        with open(path, "r+b") as handle:
            handle.truncate(start)
            handle.flush()
            os.fsync(handle.fileno())
        return
    with open(path, "ab") as handle:
        handle.write(b"\n")
        handle.flush()
        os.fsync(handle.fileno())


def last_zone_timestamp(path: Path) -> float | None:
    """The ``timestamp_s`` of the last readable line of ``path`` (None: no file, or no
    frame with one); read from the end, so that each append costs the same."""
    if not path.is_file():
        return None
    with open(path, "rb") as handle:
        return _last_timestamp(handle)


def _last_timestamp(handle) -> float | None:
    pos, head = handle.seek(0, os.SEEK_END), b""
    while pos > 0:
        step = min(1 << 16, pos)
        pos -= step
        handle.seek(pos)
        lines = (handle.read(step) + head).split(b"\n")
        head = lines[0] if pos else b""  # possibly cut: read on with the block before
        for raw in reversed(lines if not pos else lines[1:]):
            try:
                data = json.loads(raw) if raw.strip() else None
            except ValueError:  # a cut or corrupt line (UnicodeDecodeError included)
                continue
            if isinstance(data, dict) and data.get("timestamp_s") is not None:
                return data["timestamp_s"]
    return None

"""Atomic file writes: an output is either complete or absent, never half written."""

from __future__ import annotations

import contextlib
import errno
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

#: Write errors that mean "the disk cannot take it": reported naming the output.
_DISK_ERRORS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, overwrite: bool = True) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; move it onto ``path`` only on success.

    Args:
        path: final destination file.
        overwrite: if False and ``path`` exists, raise ``FileExistsError`` instead of
            replacing it (used where inputs must never be overwritten).

    Yields:
        A temporary path in the same directory (same file system, so the final
        ``os.replace`` is atomic). The caller writes the whole file there.
    """
    final = Path(path)
    if not overwrite and final.exists():
        raise FileExistsError(f"refusing to overwrite existing file: {final}")
    final.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{final.name}.", suffix=".tmp" + final.suffix,
                                    dir=final.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        try:
            yield tmp
            # mkstemp creates 0600 files; give the output the permissions of a normal file.
            umask = os.umask(0)
            os.umask(umask)
            if tmp.exists():
                os.chmod(tmp, 0o666 & ~umask)
            if not overwrite and final.exists():
                raise FileExistsError(f"refusing to overwrite existing file: {final}")
            os.replace(tmp, final)
        except OSError as err:
            if err.errno not in _DISK_ERRORS:
                raise
            # A full, read-only or over-quota disk: say which output, not a temporary name.
            raise OSError(err.errno, os.strerror(err.errno), str(final)) from err
    finally:
        if tmp.exists():
            tmp.unlink()


def leftover_temporaries(folder: str | os.PathLike, suffix: str = "") -> list[Path]:
    """The temporaries :func:`atomic_path` left in ``folder`` for outputs ending in
    ``suffix``: only a process killed while writing (SIGKILL) leaves one, a hidden
    ``.<name>.<random>.tmp<suffix>`` file as large as the output."""
    return sorted(Path(folder).glob(f".*.tmp{suffix}"))


def write_bytes_atomic(path: str | os.PathLike, data: bytes, *, overwrite: bool = True) -> Path:
    """Write ``data`` to ``path`` atomically and return the path."""
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_text_atomic(path: str | os.PathLike, text: str, *, overwrite: bool = True) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically and return the path."""
    return write_bytes_atomic(path, text.encode("utf-8"), overwrite=overwrite)

"""Atomic file writes: an output is either complete or absent, never half written."""

from __future__ import annotations

import atexit
import contextlib
import errno
import os
import secrets
import shutil
from collections.abc import Iterator
from pathlib import Path

#: Write errors that mean "the disk cannot take it": reported naming the output.
_DISK_ERRORS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG)

#: Temporaries being written now. A stop (KeyboardInterrupt from Ctrl+C or the CLI's
#: SIGTERM handler) can land between any two bytecodes, also inside the ``finally`` that
#: removes a temporary; the exit hook below removes whatever such a stop left.
_UNFINISHED: set[Path] = set()


@atexit.register
def remove_unfinished_temporaries() -> None:
    """Remove the temporaries (files, or staging folders with what they hold) of writes
    that never finished (an exception skipped their own clean-up); run at interpreter
    exit, callable earlier."""
    for tmp in list(_UNFINISHED):
        with contextlib.suppress(OSError):
            if tmp.is_dir() and not tmp.is_symlink():
                shutil.rmtree(tmp)
            else:
                tmp.unlink(missing_ok=True)
        _UNFINISHED.discard(tmp)


def hidden_sibling(path: str | os.PathLike, suffix: str) -> Path:
    """A new, unused hidden name beside ``path``: ``.<name>.<random><suffix>``."""
    final = Path(path)
    return final.parent / f".{final.name}.{secrets.token_hex(6)}{suffix}"


@contextlib.contextmanager
def staging_folder(path: str | os.PathLike) -> Iterator[Path]:
    """Create a hidden staging folder beside ``path`` for a writer that builds a folder
    (a bag) and renames it into place; registered before it exists, so a stop at any
    moment leaves none behind (:func:`remove_unfinished_temporaries`).

    Yields:
        The new, empty folder. The caller renames its result out of it; when the block
        ends, by success or exception, the folder and whatever is still in it are removed.
    """
    staging = hidden_sibling(path, ".partial")
    _UNFINISHED.add(staging)
    try:
        staging.mkdir(parents=True)
        yield staging
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        _UNFINISHED.discard(staging)


def prove_writable(folder: str | os.PathLike) -> None:
    """Create and remove a hidden empty file in the existing ``folder``: proof that a file
    can be made there, which permission bits are not (root passes them on /proc or on a
    read-only mount). Registered before it exists, so a stop at any moment leaves no
    probe behind (:func:`remove_unfinished_temporaries`).

    Raises:
        OSError: the file could not be created (its ``strerror`` says why).
    """
    probe = Path(folder) / f".deltar-write-test.{secrets.token_hex(6)}"
    _UNFINISHED.add(probe)
    try:
        os.close(os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
    finally:
        probe.unlink(missing_ok=True)
        _UNFINISHED.discard(probe)


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
    # Named here and registered before it exists, so no stop can leave it unregistered;
    # created exclusively with the permissions of a normal file (0666 less the umask).
    tmp = hidden_sibling(final, f".tmp{final.suffix}")
    _UNFINISHED.add(tmp)
    try:
        try:
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            yield tmp
            move_into_place(tmp, final, overwrite)
        except OSError as err:
            if err.errno not in _DISK_ERRORS:
                raise
            # A full, read-only or over-quota disk: say which output, not a temporary name.
            raise OSError(err.errno, os.strerror(err.errno), str(final)) from err
    finally:
        tmp.unlink(missing_ok=True)
        _UNFINISHED.discard(tmp)


def move_into_place(tmp: Path, final: Path, overwrite: bool) -> None:
    """``os.replace(tmp, final)``; without ``overwrite`` a hard link instead, which fails
    atomically where ``final`` exists: a check and then a rename would replace a file
    another process made in between. (The temporary's name is removed by the caller.)
    Where the file system has no hard links, the check and the rename."""
    if overwrite:
        os.replace(tmp, final)
        return
    try:
        os.link(tmp, final)
    except FileExistsError:
        raise FileExistsError(f"refusing to overwrite existing file: {final}") from None
    except OSError as err:
        if err.errno not in _NO_HARD_LINKS:
            raise
        if final.exists():
            raise FileExistsError(f"refusing to overwrite existing file: {final}") from None
        os.replace(tmp, final)


#: ``os.link`` errors of a file system without hard links (FAT, some network mounts).
_NO_HARD_LINKS = (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.ENOSYS, errno.EMLINK,
                  errno.EXDEV)


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

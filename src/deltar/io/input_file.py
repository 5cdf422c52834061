"""Reading a user's file: one boundary for every reader, errors that name the file.

The helpers every reader of an input file uses:

- :func:`input_file` tells the kinds of bad path apart before reading: missing, a
  folder, or not a regular file (``/dev/null``, a pipe), each with its own message;
  :func:`input_folder` does the same for an input folder.
- :func:`reading` wraps the reading and parsing of one file: whatever goes wrong in
  there (Pillow's decompression-bomb guard, ``RecursionError`` from deeply nested
  JSON, ``BadZipFile`` / ``EOFError`` from a truncated NPZ, ``UnicodeDecodeError``,
  ``OverflowError`` / ``TypeError`` / ``AttributeError`` from fields of the wrong kind,
  h5py's errors) reaches the caller as an :class:`InputFileError` (a ``ValueError``)
  whose message starts with the file, the original exception chained as its cause.

Exceptions that are not about the file's content (``NameError``, ``AssertionError``,
``RuntimeError`` other than recursion, ``KeyboardInterrupt`` ...) pass unchanged: an
internal bug stays a bug, with its traceback.
"""

from __future__ import annotations

import contextlib
import os
import struct
import zipfile
from collections.abc import Iterable, Iterator
from pathlib import Path


class InputFileError(ValueError):
    """A user's file could not be read or holds what the reader cannot accept.

    Attributes:
        path: the file.
    """

    def __init__(self, path: str | os.PathLike, message: str) -> None:
        super().__init__(message)
        self.path = Path(path)


#: What a reader may raise on a file's content (besides Pillow's bomb guard).
READ_ERRORS: tuple[type[BaseException], ...] = (
    ValueError, OSError, EOFError, zipfile.BadZipFile, RecursionError, OverflowError,
    TypeError, AttributeError, LookupError, struct.error, MemoryError, SyntaxError)


def input_file(path: str | os.PathLike, what: str) -> Path:
    """Check that ``path`` is an existing regular file (readable as one).

    Args:
        path: the file.
        what: what it is, for the messages (e.g. ``"calibration file"``).

    Returns:
        ``path`` as a ``Path``.

    Raises:
        FileNotFoundError: ``"<what> not found: <path>"``.
        IsADirectoryError: ``"<what> <path> is a folder, not a file"``.
        InputFileError: ``"<what> <path> is not a regular file (a device, pipe or
            socket)"``.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{what} not found: {path}")
    if path.is_dir():
        raise IsADirectoryError(f"{what} {path} is a folder, not a file")
    if not path.is_file():
        raise InputFileError(path, f"{what} {path} is not a regular file (a device, pipe or "
                             "socket)")
    return path


def input_folder(path: str | os.PathLike, what: str) -> Path:
    """Check that ``path`` is an existing folder.

    Raises:
        FileNotFoundError: ``"<what> not found: <path>"``.
        NotADirectoryError: ``"<what> <path> is a file, not a folder"`` (or not a
            regular file either).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{what} not found: {path}")
    if not path.is_dir():
        kind = "a file" if path.is_file() else "not a regular file"
        raise NotADirectoryError(f"{what} {path} is {kind}, not a folder")
    return path


@contextlib.contextmanager
def reading(path: str | os.PathLike, what: str) -> Iterator[Path]:
    """Turn any failure of reading ``path`` into one error naming the file.

    Args:
        path: the file being read.
        what: what it is, for the message (e.g. ``"zone frame file"``).

    Yields:
        ``path`` as a ``Path``.

    Raises:
        InputFileError: ``"<path>: cannot read <what>: <reason>"`` for the exceptions
            of :data:`READ_ERRORS` and Pillow's ``DecompressionBombError``; a
            ``ValueError`` whose message already names the file, and an ``OSError``
            with a file name (permission denied ...), pass unchanged.
    """
    path = Path(path)
    try:
        yield path
    except InputFileError:
        raise
    except Exception as err:
        if not isinstance(err, READ_ERRORS) and not _is_decompression_bomb(err):
            raise
        if isinstance(err, (ValueError, OSError)) and not isinstance(
                err, (UnicodeError, RecursionError)) and (
                str(path) in str(err) or getattr(err, "filename", None)):
            raise
        raise InputFileError(path, f"{path}: cannot read {what}: {read_reason(err)}") from err


def read_reason(err: BaseException) -> str:
    """A short reason for a reader's exception, in the user's terms."""
    detail = " ".join(str(err).split())
    if _is_decompression_bomb(err):
        return f"the image is too large to decode safely ({detail})"
    if isinstance(err, RecursionError):
        return "nested too deeply to parse"
    if isinstance(err, (zipfile.BadZipFile, EOFError)):
        return f"corrupt or truncated file ({detail or type(err).__name__})"
    if isinstance(err, UnicodeDecodeError):
        return (f"not UTF-8 text (byte 0x{err.object[err.start]:02x} at position "
                f"{err.start})")
    if isinstance(err, OverflowError):
        return f"a number is out of range ({detail})"
    if isinstance(err, MemoryError):
        return "too large to load into memory"
    if isinstance(err, (TypeError, AttributeError, LookupError)):
        return f"a field has the wrong type or shape ({type(err).__name__}: {detail})"
    return detail or type(err).__name__


def _is_decompression_bomb(err: BaseException) -> bool:
    try:
        from PIL import Image
    except ImportError:  # pragma: no cover - Pillow is a dependency
        return False
    return isinstance(err, (Image.DecompressionBombError, Image.DecompressionBombWarning))


def not_8bit_colour(path: str | os.PathLike, dtype: object, channels: int) -> str:
    """Why a colour image file decoded to ``dtype`` with ``channels`` channels (not 8-bit)
    is refused: one channel deeper than 8 bits is most likely a depth map; several
    channels are a colour image of the wrong depth (a 16-bit RGB photo).

    Args:
        path: the image file, named first.
        dtype: the decoded sample type (e.g. ``numpy.uint16``).
        channels: 1 (grey), 3 or 4.

    Returns:
        The message, e.g. ``"x.png: a single-channel uint16 image (a depth map?), not an
        8-bit colour image"`` or ``"x.png: a 3-channel uint16 image; a colour image must
        be 8-bit RGB (convert it, e.g. image >> 8 for 16 bits per channel)"``.
    """
    if channels == 1:
        return f"{path}: a single-channel {dtype} image (a depth map?), not an 8-bit colour image"
    how = " (convert it, e.g. image >> 8 for 16 bits per channel)" if str(dtype) in (
        "uint16", "int16") else " (convert it to 8 bits per channel)"
    return f"{path}: a {channels}-channel {dtype} image; a colour image must be 8-bit RGB{how}"


def refuse_input_as_output(output: str | os.PathLike, inputs: Iterable[str | os.PathLike | None],
                           option: str, *, folder: bool = False) -> Path:
    """Refuse an output that would write over (or into) an input of the same command.

    Applies whatever ``--overwrite`` says: no command ever writes over its own input.
    Paths are compared resolved (symbolic links followed), and with
    ``os.path.samefile`` where both exist (hard links, bind mounts).

    Args:
        output: the output file, or folder when ``folder``.
        inputs: the command's input files and folders (``None`` entries are skipped).
        option: the option (or argument) naming the output, for the message.
        folder: the output is a folder: it may not lie inside an input folder either.
            An output file may lie inside an input folder only as a new file (one that
            does not exist yet, so no input is replaced).

    Returns:
        ``output`` as a ``Path``.

    Raises:
        ValueError: ``"<option> <output> is the input <input>; ..."`` or ``"<option>
            <output> is inside the input <input>; choose a path outside it"``.
    """
    output = Path(output)
    resolved = output.resolve()
    for source in inputs:
        if source is None:
            continue
        source = Path(source)
        origin = source.resolve()
        if resolved == origin or (output.exists() and source.exists()
                                  and os.path.samefile(output, source)):
            raise ValueError(f"{option} {output} is the input {source}; an output never "
                             "replaces an input (whatever --overwrite says): choose another "
                             "path")
        if origin.is_dir() and origin in resolved.parents and (folder or output.exists()):
            raise ValueError(f"{option} {output} is inside the input {source}; choose a "
                             "path outside it")
        if origin.is_dir() and output.is_file():
            linked = _same_file_in(output, origin)
            if linked is not None:
                raise ValueError(f"{option} {output} is the input {linked} (a link to it); "
                                 "an output never replaces an input (whatever --overwrite "
                                 "says): choose another path")
    return output


def _same_file_in(path: Path, folder: Path) -> Path | None:
    """The file under ``folder`` that is ``path`` (a hard link to it), or None."""
    target = path.stat()
    if target.st_nlink < 2:
        return None
    for root, _, names in os.walk(folder):
        for name in names:
            candidate = Path(root) / name
            with contextlib.suppress(OSError):
                found = candidate.stat()
                if (found.st_dev, found.st_ino) == (target.st_dev, target.st_ino):
                    return candidate
    return None

"""The shared CLI error style: OS errors read as path and reason, one line."""

from __future__ import annotations

import errno

from deltar.cli.errors import format_error


def test_os_errors_read_as_path_and_reason():
    err = OSError(errno.ENOTDIR, "Not a directory", "/data/file/sub")
    assert format_error(err) == "/data/file/sub: Not a directory"
    assert format_error(ValueError("two\nlines")) == "two lines"
    assert format_error(ModuleNotFoundError("No module named 'onnx'", name="onnx")) == (
        "No module named 'onnx': install the optional dependency (see the README's extras)")

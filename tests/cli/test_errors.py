"""The shared CLI error style: OS errors read as path and reason, one line."""

from __future__ import annotations

import errno

from deltar.cli.errors import format_error


def test_os_errors_read_as_path_and_reason():
    err = OSError(errno.ENOTDIR, "Not a directory", "/data/file/sub")
    assert format_error(err) == "/data/file/sub: Not a directory"
    assert format_error(ValueError("two\nlines")) == "two lines"
    assert format_error(ModuleNotFoundError("No module named 'onnx'", name="onnx")) == (
        "this command needs onnx, which the 'export' extra installs: "
        'pip install "deltar[export]"')
    assert format_error(ModuleNotFoundError("No module named 'torch.nn'", name="torch.nn")) == (
        "this command needs torch, which the 'torch' extra installs: "
        'pip install "deltar[torch]"')
    assert format_error(ModuleNotFoundError("No module named 'foo'", name="foo")) == (
        "No module named 'foo': install the optional dependency (see the README's extras)")

"""The shared CLI error style: OS errors read as path and reason, one line."""

from __future__ import annotations

import errno
import os

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


def _interrupted_record(tmp_path, signum):
    """``deltar record`` of a long simulated stream, stopped by ``signum`` once it has
    written some frames: (status, stderr, the recording folder)."""
    import shutil
    import subprocess
    import time

    out = tmp_path / "rec"
    process = subprocess.Popen(
        [shutil.which("deltar"), "record", str(out), "--simulate", "wall:1.5:1000000:48x64",
         "--frames", "1000000"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "OMP_NUM_THREADS": "1"})
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not (
            (out / "color").is_dir() and len(list((out / "color").iterdir())) >= 20):
        time.sleep(0.1)
    process.send_signal(signum)
    _, err = process.communicate(timeout=60)
    return process.returncode, err, out


def test_a_stopped_command_says_so_and_leaves_complete_files(tmp_path):
    """SIGTERM (a service manager's stop) ends a command as Ctrl+C does: one error line,
    status 128 + 15, and no hidden temporary left where a file was being written; the
    recording then reads and appends."""
    import signal

    from deltar.io.recording import Recording

    status, err, out = _interrupted_record(tmp_path, signal.SIGTERM)
    assert status == 143, err[-2000:]
    assert err.strip().splitlines()[-1] == (
        "error: interrupted by SIGTERM; every file written before it is complete (each is "
        "written whole, then renamed)")
    assert not [p for p in out.rglob(".*")], "a temporary was left behind"
    assert len(Recording(out).pairs(tolerance_s=0.05)) > 0


def test_a_stop_is_forgotten_when_its_command_ends_and_quiets_what_follows_it(tmp_path,
                                                                            capsys):
    """The signal a command received does not stop the next command run in the same
    process; while a command stops, exceptions Python can only print (e.g. a DataLoader
    worker killed by the same SIGTERM) are not printed, and otherwise they are."""
    import sys

    from typer.testing import CliRunner

    from deltar.cli import errors
    from deltar.cli.main import app

    errors._INTERRUPT["signal"] = "SIGTERM"  # as a stopped command would leave it
    result = CliRunner().invoke(app, ["simulate", "procedural:2", str(tmp_path / "set")])
    assert result.exit_code == 0, result.output
    assert errors.received_signal() is None
    errors.check_interrupt()  # nothing pending: no exception

    class Dying:
        def __del__(self):
            raise RuntimeError("DataLoader worker (pid 1) is killed by signal: Terminated")

    previous, sys.unraisablehook = sys.unraisablehook, errors._quiet_after_stop
    try:
        errors._INTERRUPT["signal"] = "SIGTERM"
        Dying()  # collected at once: its exception can only be printed
        quiet = capsys.readouterr().err
        errors._INTERRUPT["signal"] = None
        Dying()
        loud = capsys.readouterr().err
    finally:
        sys.unraisablehook, errors._INTERRUPT["signal"] = previous, None
    assert "DataLoader worker" not in quiet and "DataLoader worker" in loud
    assert sys.unraisablehook is not errors._quiet_after_stop  # restored after the command

"""The ``deltar`` executable's stop signals before and after a command runs."""

from __future__ import annotations

import subprocess
import sys

#: Runs ``deltar.cli.entry.main`` with a stand-in for the command line that ``BODY`` defines.
SCRIPT = """
import os, signal, sys, time, types
stand_in = types.ModuleType("deltar.cli.main")
{body}
sys.modules["deltar.cli.main"] = stand_in
from deltar.cli.entry import main
main()
"""


def _run(body: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", SCRIPT.format(body=body)],
                          capture_output=True, text=True, timeout=60)


def test_a_stop_while_the_command_line_loads_ends_with_the_one_line():
    """SIGTERM / Ctrl+C before a command's own handler exists: no traceback, the
    commands' error line, status 128 + the signal."""
    for name, status, said in (("SIGTERM", 143, "SIGTERM"), ("SIGINT", 130, "Ctrl+C")):
        result = _run("def main():\n"
                      f"    os.kill(os.getpid(), signal.{name}); time.sleep(30)\n"
                      "stand_in.main = main")
        assert (result.returncode, result.stderr) == (status, f"error: interrupted by {said}\n")


def test_a_stop_after_the_command_ended_ends_the_teardown_with_its_status():
    """During the interpreter's teardown a stop ends the process at once (a teardown that
    hangs still ends) with the finished command's status: its outputs are complete."""
    for status in (0, 1):
        result = _run("def main():\n"
                      f"    print('done', flush=True); raise SystemExit({status})\n"
                      "stand_in.main = main\n"
                      "import atexit\n"
                      "atexit.register(lambda: (os.kill(os.getpid(), signal.SIGTERM),\n"
                      "                         time.sleep(30), print('never')))")
        assert (result.returncode, result.stdout, result.stderr) == (status, "done\n", "")

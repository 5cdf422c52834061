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
main([])
"""


def _run(body: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", SCRIPT.format(body=body)],
                          capture_output=True, text=True, timeout=60)


def test_a_stop_while_the_command_line_loads_ends_with_the_one_line():
    """SIGTERM / Ctrl+C before a command's own handler exists: no traceback, the
    commands' error line, status 128 + the signal."""
    for name, status, said in (("SIGTERM", 143, "SIGTERM"), ("SIGINT", 130, "Ctrl+C")):
        result = _run("def main(args):\n"
                      f"    os.kill(os.getpid(), signal.{name}); time.sleep(30)\n"
                      "stand_in.main = main")
        assert (result.returncode, result.stderr) == (status, f"error: interrupted by {said}\n")


def test_a_stop_after_the_command_ended_leaves_its_status():
    """During the interpreter's teardown a stop is ignored: the outputs are complete and
    the command's own status stands."""
    result = _run("def main(args):\n"
                  "    raise SystemExit(0)\n"
                  "stand_in.main = main\n"
                  "import atexit\n"
                  "atexit.register(lambda: (os.kill(os.getpid(), signal.SIGTERM),\n"
                  "                         os.kill(os.getpid(), signal.SIGINT),\n"
                  "                         time.sleep(0.2), print('torn down')))")
    assert (result.returncode, result.stdout, result.stderr) == (0, "torn down\n", "")

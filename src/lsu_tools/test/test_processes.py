"""LaunchedProcess.stop: the teardown every graph test and benchmark uses ends the process in any case."""

from __future__ import annotations

import signal
import sys

from lsu_tools.processes import LaunchedProcess


def shell(script: str) -> LaunchedProcess:
    # the prefix runs in place of `lsu` (its arguments become the script's unused positional ones)
    return LaunchedProcess([], prefix=["sh", "-c", script, "sh"])


def python(script: str) -> LaunchedProcess:
    # like shell(); `lsu` becomes the script's unused sys.argv[1]
    return LaunchedProcess([], prefix=[sys.executable, "-c", script])


def test_stop_returns_the_exit_code_of_a_process_that_ends_on_sigint():
    # Python, not a shell trap: dash runs `sleep` by vfork with every signal blocked, and a SIGINT that
    # lands in that window can wait seconds for its trap (1 in ~1500 stops, far longer than the
    # sleep); Python's handler runs on the next bytecode, in time whatever the host's load.
    proc = python("import signal, sys, time\n"
                  "signal.signal(signal.SIGINT, lambda *_: sys.exit(3))\n"
                  "print('ready', flush=True)\n"
                  "while True:\n    time.sleep(1)\n")
    proc.wait_for_line("ready", timeout_s=10)
    assert proc.stop(timeout_s=10) == 3


def test_stop_kills_a_process_that_ignores_sigint():
    proc = shell("trap '' INT; echo ready; exec sleep 60")
    proc.wait_for_line("ready", timeout_s=10)
    assert proc.stop(timeout_s=0.3) is None
    assert proc.process.returncode == -signal.SIGKILL

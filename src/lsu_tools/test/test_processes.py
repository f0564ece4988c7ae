"""LaunchedProcess.stop: the teardown every graph test and benchmark uses ends the process in any case."""

from __future__ import annotations

import signal

from lsu_tools.processes import LaunchedProcess


def shell(script: str) -> LaunchedProcess:
    # the prefix runs in place of `lsu` (its arguments become the script's unused positional ones)
    return LaunchedProcess([], prefix=["sh", "-c", script, "sh"])


def test_stop_returns_the_exit_code_of_a_process_that_ends_on_sigint():
    proc = shell("trap 'exit 3' INT; echo ready; while :; do sleep 0.05; done")
    proc.wait_for_line("ready", timeout_s=10)
    assert proc.stop(timeout_s=10) == 3


def test_stop_kills_a_process_that_ignores_sigint():
    proc = shell("trap '' INT; echo ready; exec sleep 60")
    proc.wait_for_line("ready", timeout_s=10)
    assert proc.stop(timeout_s=0.3) is None
    assert proc.process.returncode == -signal.SIGKILL

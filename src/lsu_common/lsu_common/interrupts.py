"""Ctrl-C (SIGINT) held back during a process's start-up, and taken once the process can handle it.

`lsu launch` starts every node with SIGINT blocked (launcher `_child_setup`): a Ctrl-C or a
shutdown that comes while the interpreter is still starting (importing `site`, the node's
libraries) would otherwise end it with "Fatal Python error: init_import_site" and SIGABRT, a crash
in the launch's report. Blocked, the signal stays pending until the program has its handler
(rclpy's, or Python's KeyboardInterrupt) and calls `accept_interrupts`; then it is delivered and
the program ends the way it ends on any Ctrl-C. No rclpy import here: the web server uses it too.
"""

from __future__ import annotations

import signal

HELD = frozenset({signal.SIGINT})


def hold_interrupts() -> None:
    """Block SIGINT in this process (and the programs it executes) until `accept_interrupts`."""
    signal.pthread_sigmask(signal.SIG_BLOCK, HELD)


def accept_interrupts() -> None:
    """Unblock SIGINT: a pending one is delivered now, to the handler in place. Harmless when not blocked."""
    signal.pthread_sigmask(signal.SIG_UNBLOCK, HELD)

"""`lsu launch`: every node of a launch file as its own process (no rclpy import).

What a lab user expects from `ros2 launch`, on machines that have no launch package:
log lines prefixed with the node name, respawn, required nodes, Ctrl-C/SIGTERM shutting
everything down in order (SIGINT, grace, SIGTERM, SIGKILL), and no orphans: each child
gets PR_SET_PDEATHSIG, so even a SIGKILLed launcher takes its nodes with it.
"""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, TextIO

from lsu_common.interrupts import hold_interrupts

from .launch_file import LaunchDescription, NodeSpec
from .nodes_index import resolve_executable

_PR_SET_PDEATHSIG = 1


def _child_setup() -> None:
    """Runs in the child before exec: SIGTERM it when the launcher dies, however it dies; and SIGINT held until
    the node can handle it (lsu_common.interrupts: every LSU executable accepts it once its handler is in place)."""
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    hold_interrupts()


@dataclass
class _Child:
    spec: NodeSpec
    command: list[str]
    process: subprocess.Popen | None = None
    reader: threading.Thread | None = None
    restart_at: float | None = None
    starts: int = 0
    exit_code: int | None = None
    stopping: bool = False
    log: list[str] = field(default_factory=list)


class Launcher:
    """Starts, watches and stops the processes of a `LaunchDescription`."""

    def __init__(self, description: LaunchDescription, out: TextIO | None = None,
                 sigint_timeout_s: float = 2.5, sigterm_timeout_s: float = 1.5) -> None:
        out = sys.stdout if out is None else out
        self.description = description
        self.out = out
        self.sigint_timeout_s = sigint_timeout_s
        self.sigterm_timeout_s = sigterm_timeout_s
        self._lock = threading.Lock()
        self._tmp = tempfile.TemporaryDirectory(prefix="lsu-launch-")
        self._shutdown = threading.Event()
        self._reason = ""
        self._failed = False
        # set by the signal handler, acted on by the run loop: a handler runs between two bytecodes of the main
        # thread, which may hold the lock inside the Event it would set (Event.set there deadlocked the launcher)
        self._signalled: int | None = None
        self.children: list[_Child] = []
        for index, spec in enumerate(description.nodes):
            exe = resolve_executable(spec.package, spec.executable)
            inline = None
            if spec.params:
                inline = Path(self._tmp.name) / f"{index:02d}-{spec.label}.params.yaml"
                inline.write_text(spec.inline_params_yaml())
            self.children.append(_Child(spec, [str(exe), *spec.args, *spec.ros_args(inline)]))

    # -- output ------------------------------------------------------------------------------
    def say(self, text: str) -> None:
        """One line from the launcher itself."""
        with self._lock:
            self.out.write(f"[lsu launch] {text}\n")
            self.out.flush()

    def _pump(self, child: _Child, stream: IO[bytes]) -> None:
        prefix = f"[{child.spec.label}] "
        for raw in iter(stream.readline, b""):
            line = raw.decode("utf-8", "replace").rstrip("\n")
            with self._lock:
                self.out.write(prefix + line + "\n")
                self.out.flush()
        stream.close()

    # -- processes ---------------------------------------------------------------------------
    def _start(self, child: _Child) -> None:
        env = dict(os.environ)
        env.update(child.spec.env)
        env["PYTHONUNBUFFERED"] = "1"
        env.setdefault("RCUTILS_COLORIZED_OUTPUT", "0")
        # a node that crashes (a segmentation fault in a library) prints every thread's Python stack first:
        # what it was doing, in the launch's output
        env.setdefault("PYTHONFAULTHANDLER", "1")
        child.process = subprocess.Popen(
            child.command, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            env=env, start_new_session=True, preexec_fn=_child_setup)
        child.starts += 1
        child.exit_code = None
        child.restart_at = None
        child.reader = threading.Thread(target=self._pump, args=(child, child.process.stdout), daemon=True)
        child.reader.start()
        self.say(f"started {child.spec.label} ({child.spec.package}/{child.spec.executable}) pid {child.process.pid}")

    def request_shutdown(self, reason: str) -> None:
        """Ask the run loop to stop every node (from any thread; not from a signal handler: `_on_signal`)."""
        if not self._shutdown.is_set():
            self._reason = reason
            self._shutdown.set()

    def _signal_all(self, sig: int) -> None:
        for child in self.children:
            proc = child.process
            if proc is not None and proc.poll() is None:
                try:
                    os.killpg(proc.pid, sig)  # the node and anything it started
                except ProcessLookupError:
                    pass

    def _alive(self) -> list[_Child]:
        return [c for c in self.children if c.process is not None and c.process.poll() is None]

    def _stop_all(self) -> None:
        for child in self.children:
            child.stopping = True
        sent: set[int] = set()  # signals the launcher sent: a node they ended did not crash
        for sig, grace in ((signal.SIGINT, self.sigint_timeout_s), (signal.SIGTERM, self.sigterm_timeout_s),
                           (signal.SIGKILL, 2.0)):
            if not self._alive():
                break
            if sig != signal.SIGINT:
                self.say(f"{', '.join(c.spec.label for c in self._alive())} still running: sending {sig.name}")
            self._signal_all(sig)
            sent.add(int(sig))
            deadline = time.monotonic() + grace
            while self._alive() and time.monotonic() < deadline:
                time.sleep(0.02)
        for child in self.children:
            if child.reader is not None:
                child.reader.join(timeout=1.0)
        left = self._alive()
        if left:
            self.say(f"could not stop: {', '.join(f'{c.spec.label} pid {c.process.pid}' for c in left if c.process)}")
        else:
            self.say("all nodes stopped")
        self._report_stopped(sent)

    def _report_stopped(self, sent: set[int]) -> None:
        """How each node ended while stopping; one that ended by a signal the launcher did not send crashed
        (a segmentation fault in a library at shutdown): said, and the launch's exit code is 1."""
        for child in self.children:
            proc = child.process
            code = None if proc is None else proc.poll()
            if proc is None or code is None or code == 0:
                continue
            if code < 0 and -code not in sent:
                self._failed = True
                self.say(f"{child.spec.label} crashed while stopping (signal {signal.Signals(-code).name}, pid "
                         f"{proc.pid})")
            elif code > 0:
                self.say(f"{child.spec.label} ended with exit code {code} while stopping")

    def _reap(self, child: _Child, now: float) -> None:
        proc = child.process
        assert proc is not None
        code = proc.returncode
        child.exit_code = code
        child.process = None
        how = f"exit code {code}" if code >= 0 else f"signal {signal.Signals(-code).name}"
        if self._shutdown.is_set():
            return
        if child.spec.required:
            self._failed = True
            self.say(f"required node {child.spec.label} ended ({how}): shutting down")
            self.request_shutdown(f"required node {child.spec.label} ended")
        elif child.spec.respawn:
            self.say(f"{child.spec.label} ended ({how}); respawning in {child.spec.respawn_delay_s:g} s")
            child.restart_at = now + child.spec.respawn_delay_s
        else:
            if code != 0:
                self._failed = True
            self.say(f"{child.spec.label} ended ({how})")

    def run(self) -> int:
        """Start everything, supervise until shutdown or until no node is left; return the exit code."""
        previous = {sig: signal.signal(sig, self._on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
        try:
            for child in self.children:
                self._start(child)
            while not self._shutdown.is_set():
                if self._signalled is not None:
                    self.request_shutdown(f"received {signal.Signals(self._signalled).name}")
                    break
                now = time.monotonic()
                for child in self.children:
                    if child.process is not None and child.process.poll() is not None:
                        self._reap(child, now)
                    if child.restart_at is not None and now >= child.restart_at and not self._shutdown.is_set():
                        self._start(child)
                if all(c.process is None and c.restart_at is None for c in self.children):
                    self.say("all nodes have ended")
                    break
                self._shutdown.wait(0.05)
            if self._shutdown.is_set():
                self.say(f"shutting down: {self._reason}")
            self._stop_all()
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
            self._tmp.cleanup()
        return 1 if self._failed else 0

    def _on_signal(self, signum: int, _frame: object) -> None:
        # no lock may be taken here (see _signalled): only flags are read and set, and signals sent
        if self._signalled is not None or self._shutdown.is_set():
            # a second Ctrl-C: do not wait for the grace periods
            self._signal_all(signal.SIGKILL)
            return
        self._signalled = signum

"""A long-running `lsu ...` subprocess with its output collected (tests, demo, benchmarks, tools).

Started in its own session so it can be stopped as a group; `interrupt()` is Ctrl-C, `kill()` the
last resort.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

LSU = str(Path(sys.executable).parent / "lsu")


def pid_alive(pid: int) -> bool:
    """True while process ``pid`` runs (a zombie counts as gone: it only waits to be reaped)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # the state follows the ")" closing the command name, which may itself hold spaces
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False


class ProcessWaitError(AssertionError):
    """An expected output line did not come (an AssertionError, so pytest reports it as a failure)."""


class LaunchedProcess:
    """A running `lsu ...` subprocess whose output is collected in the background."""

    def __init__(self, args: list[str], cwd: str | None = None, prefix: Sequence[str] = (),
                 env: Mapping[str, str] | None = None) -> None:
        """``prefix``: a command that execs `lsu` (``ip netns exec NS``), so the pid stays `lsu`'s;
        ``env``: the whole environment (default: this process's)."""
        self.args = args
        self.lines: list[str] = []
        self._lock = threading.Lock()
        self.process = subprocess.Popen([*prefix, LSU, *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                        stdin=subprocess.DEVNULL, text=True, cwd=cwd, start_new_session=True,
                                        env=None if env is None else dict(env))
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            with self._lock:
                self.lines.append(line.rstrip("\n"))

    @property
    def output(self) -> str:
        with self._lock:
            return "\n".join(self.lines)

    def started_pids(self) -> dict[str, int]:
        """Node label -> pid from `lsu launch`'s "started X (...) pid N" lines (a respawn: the latest pid)."""
        return {m.group(1): int(m.group(2)) for m in re.finditer(r"started (\S+) \(.*\) pid (\d+)", self.output)}

    def wait_for_line(self, pattern: str, timeout_s: float = 20.0) -> re.Match[str]:
        """Wait for an output line matching ``pattern``; raises ProcessWaitError with the output so far."""
        regex = re.compile(pattern)
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            with self._lock:
                for line in self.lines:
                    match = regex.search(line)
                    if match:
                        return match
            if self.process.poll() is not None:
                time.sleep(0.2)  # let the reader drain
                with self._lock:
                    hit = next((regex.search(x) for x in self.lines if regex.search(x)), None)
                if hit:
                    return hit
                raise ProcessWaitError(f"`lsu {' '.join(self.args)}` exited ({self.process.returncode}) before "
                                       f"printing /{pattern}/:\n{self.output}")
            time.sleep(0.05)
        raise ProcessWaitError(f"no line /{pattern}/ from `lsu {' '.join(self.args)}` within {timeout_s} s:\n"
                               f"{self.output}")

    def wait(self, timeout_s: float) -> int:
        """Wait for the process to end by itself and for its output to be read; returns the exit code."""
        try:
            return self.process.wait(timeout=timeout_s)
        finally:
            self._reader.join(timeout=2.0)

    def interrupt(self, timeout_s: float = 10.0) -> int:
        """SIGINT (like Ctrl-C) and wait; returns the exit code."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
        try:
            return self.process.wait(timeout=timeout_s)
        finally:
            self._reader.join(timeout=2.0)

    def stop(self, timeout_s: float = 10.0) -> int | None:
        """SIGINT, then (not ended within ``timeout_s``) SIGKILL of the group: the exit code, None when killed.

        The teardown of every caller: an `interrupt` that times out raises, and a ``kill()`` after it in the
        same ``finally`` would never run, leaving the graph behind.
        """
        try:
            return self.interrupt(timeout_s)
        except subprocess.TimeoutExpired:
            return None
        finally:
            self.kill()  # a no-op once the process has ended

    def kill(self) -> None:
        """SIGKILL the process group (teardown of last resort)."""
        if self.process.poll() is None:
            try:
                os.killpg(self.process.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            self.process.wait(timeout=5)

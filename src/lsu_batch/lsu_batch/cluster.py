"""A Ray cluster of several nodes on this machine: to try `lsu batch --address`, and for its tests and benchmark.

Each node is `ray start --block` run as a child process in a process group of its own: `stop` ends those
groups by their ids and nothing else (``ray stop`` would end every Ray process of the machine, other people's
included). Every port is one chosen free here (never Ray's defaults, which another Ray on the machine may
hold), the temporary folder is private, and the nodes authenticate with a token of their own
(``RAY_AUTH_MODE=token``, ``RAY_AUTH_TOKEN_PATH``: without it a second node is refused with
InvalidAuthToken); `env` is what a driver needs to join (``lsu batch --address`` in that environment).
"""

from __future__ import annotations

import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

__all__ = ["RayNodes", "free_ports"]

NODE_START_S = 90.0  # a node that has not said it started by then is reported (a loaded host takes ~10-30 s)
# Ray gives a raylet a fixed 30 s to register with the GCS (ray/_private/node.py, not configurable); a busy host can
# miss it. That one failure is retried with a fresh node; any other ends the start.
RAY_REGISTER_TIMEOUT = "timed out during startup"
NODE_START_ATTEMPTS = 3


def free_ports(count: int) -> list[int]:
    """``count`` distinct TCP ports free on 127.0.0.1 now (held open together while chosen, then released)."""
    sockets = []
    try:
        for _ in range(count):
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.bind(("127.0.0.1", 0))
            sockets.append(s)
        return [s.getsockname()[1] for s in sockets]
    finally:
        for s in sockets:
            s.close()


class NodeStartError(RuntimeError):
    """A Ray node that did not start; ``output`` is the end of what it printed."""

    def __init__(self, what: str, lines: list[str]) -> None:
        self.output = "\n".join(lines[-20:])
        super().__init__(f"{what}:\n{self.output}")


class RayNodes:
    """``nodes`` Ray nodes (a head and workers) of ``cpus`` CPUs each on 127.0.0.1; a context manager."""

    def __init__(self, nodes: int = 2, cpus: int = 1, object_store_bytes: int = 100 << 20) -> None:
        if nodes < 1:
            raise ValueError("a cluster needs at least one node (the head)")
        self.nodes, self.cpus, self.object_store_bytes = nodes, cpus, object_store_bytes
        self.temp = Path(tempfile.mkdtemp(prefix="lsu-rayc-"))  # short: Ray's socket paths live under it
        token = self.temp / "auth_token"
        token.write_text(secrets.token_hex(32))
        token.chmod(0o600)
        self.env = {**os.environ, "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN_PATH": str(token)}
        self.env.pop("RAY_ADDRESS", None)
        self.address = ""
        self.processes: list[subprocess.Popen[str]] = []
        self.output: list[list[str]] = []

    def _ray(self) -> str:
        return str(Path(sys.executable).with_name("ray"))

    def _start_node(self, head: bool) -> None:
        for attempt in range(1, NODE_START_ATTEMPTS + 1):
            try:
                self._start_node_once(head)
                return
            except NodeStartError as e:
                if RAY_REGISTER_TIMEOUT not in e.output or attempt == NODE_START_ATTEMPTS:
                    raise
                self._stop_process(self.processes.pop())
                self.output.pop()

    def _start_node_once(self, head: bool) -> None:
        ports = free_ports(9)
        args = [self._ray(), "start", "--block", "--node-ip-address=127.0.0.1", f"--num-cpus={self.cpus}",
                f"--object-store-memory={self.object_store_bytes}", f"--node-manager-port={ports[1]}",
                f"--object-manager-port={ports[2]}", f"--dashboard-agent-listen-port={ports[3]}",
                f"--dashboard-agent-grpc-port={ports[4]}", f"--runtime-env-agent-port={ports[5]}",
                f"--metrics-export-port={ports[6]}", f"--worker-port-list={','.join(map(str, free_ports(8)))}",
                "--disable-usage-stats", "--log-style=record"]
        if head:
            self.address = f"127.0.0.1:{ports[0]}"
            args += ["--head", f"--port={ports[0]}", "--include-dashboard=false",
                     f"--temp-dir={self.temp}"]
        else:
            args += [f"--address={self.address}"]
        process = subprocess.Popen(args, env=self.env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                   start_new_session=True)  # its own process group: `stop` ends exactly it
        lines: list[str] = []
        started, ok = threading.Event(), threading.Event()

        def read() -> None:
            assert process.stdout is not None
            for line in process.stdout:
                lines.append(line.rstrip())
                if "Ray runtime started" in line:
                    ok.set()
                    started.set()
            started.set()  # its output ended: it failed to start (or ended after starting)

        threading.Thread(target=read, daemon=True, name="ray-node-output").start()
        self.processes.append(process)
        self.output.append(lines)
        deadline = time.monotonic() + NODE_START_S
        while not started.wait(0.2):
            if time.monotonic() > deadline:
                raise NodeStartError(f"Ray node did not start within {NODE_START_S:.0f} s", lines)
        if not ok.is_set():
            raise NodeStartError(f"Ray node ended with status {process.wait()}", lines)

    def start(self) -> str:
        """Start the head, then the workers; returns the head's address (host:port)."""
        try:
            self._start_node(head=True)
            for _ in range(self.nodes - 1):
                self._start_node(head=False)
        except BaseException:
            self.stop()
            raise
        return self.address

    @staticmethod
    def _stop_process(process: subprocess.Popen[str]) -> None:
        """End the process group of one node this object started."""
        for sig, wait_s in ((signal.SIGTERM, 15.0), (signal.SIGKILL, 5.0)):
            try:
                os.killpg(process.pid, sig)  # the group this object started, by its id
            except ProcessLookupError:
                return
            try:
                process.wait(wait_s)
            except subprocess.TimeoutExpired:
                continue
            try:  # `ray start` ended its node on SIGTERM; anything of the group still there goes too
                os.killpg(process.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            return

    def stop(self) -> None:
        """End every node's process group (workers first), then remove the temporary folder."""
        for process in reversed(self.processes):
            self._stop_process(process)
        self.processes = []
        shutil.rmtree(self.temp, ignore_errors=True)

    def __enter__(self) -> RayNodes:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

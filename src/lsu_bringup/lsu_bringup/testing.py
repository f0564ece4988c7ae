"""Pytest plugin for LSU tests (loaded by the workspace's conftest.py).

- Every test session claims its own ROS_DOMAIN_ID (a lock no other LSU run on this machine
  holds) and forces ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST before anything touches DDS;
  subprocesses inherit both.
- ``ros_context``: a fresh rclpy Context per test, always shut down.
- ``ros_node`` / ``spin_until``: a helper node on an executor and a bounded spin.
- ``launch``: starts `lsu launch ...` (or any `lsu` long-runner) in a subprocess and always
  tears it down (SIGINT, then SIGKILL to its whole process group).
- ``lsu_cli``: runs a short `lsu ...` command and returns the CompletedProcess.
"""

from __future__ import annotations

import os
import subprocess
import time
from typing import Any, Callable, Iterator, List, Optional

import pytest

from . import rosenv
from .processes import LSU, LaunchedProcess, ProcessWaitError  # noqa: F401  (re-exported for tests)

_claim: Optional[rosenv.DomainClaim] = None


def pytest_configure(config: pytest.Config) -> None:
    """Isolate DDS for the whole session before any test module imports rclpy."""
    global _claim
    forced = os.environ.get("LSU_TEST_DOMAIN_ID")
    os.environ[rosenv.DISCOVERY_VAR] = rosenv.LOCALHOST
    if forced:
        os.environ[rosenv.DOMAIN_VAR] = forced
    else:
        _claim = rosenv.isolate()
    os.environ.setdefault("RCUTILS_COLORIZED_OUTPUT", "0")


def pytest_report_header(config: pytest.Config) -> str:
    return (f"LSU: {rosenv.DISCOVERY_VAR}={os.environ.get(rosenv.DISCOVERY_VAR)} "
            f"{rosenv.DOMAIN_VAR}={os.environ.get(rosenv.DOMAIN_VAR)}")


def pytest_unconfigure(config: pytest.Config) -> None:
    if _claim is not None:
        _claim.release()


def spin_until(executor: Any, predicate: Callable[[], bool], timeout_s: float) -> bool:
    """Spin ``executor`` until ``predicate()`` holds or ``timeout_s`` passes; returns ``predicate()``."""
    end = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > end:
            return predicate()
        executor.spin_once(timeout_sec=0.05)
    return True


@pytest.fixture
def ros_context() -> Iterator[Any]:
    """A fresh, initialised rclpy Context for one test."""
    import rclpy
    from rclpy.context import Context

    context = Context()
    rclpy.init(context=context)
    try:
        yield context
    finally:
        rclpy.try_shutdown(context=context)


class NodeHarness:
    """A helper node plus executor inside ``ros_context``; add more nodes with ``add``."""

    def __init__(self, context: Any) -> None:
        import rclpy
        from rclpy.executors import MultiThreadedExecutor

        self.context = context
        self.node = rclpy.create_node(f"test_helper_{os.getpid()}", context=context)
        self.executor = MultiThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self._nodes: List[Any] = [self.node]

    def add(self, node: Any) -> Any:
        """Spin ``node`` with the helper; it is destroyed at teardown."""
        self.executor.add_node(node)
        self._nodes.append(node)
        return node

    def spin_until(self, predicate: Callable[[], bool], timeout_s: float = 10.0) -> bool:
        """Spin until ``predicate()`` or timeout; returns ``predicate()``."""
        return spin_until(self.executor, predicate, timeout_s)

    def call(self, client: Any, request: Any, timeout_s: float = 10.0) -> Any:
        """Wait for the service, call it, wait for the response; fails the test on timeout."""
        assert self.spin_until(client.service_is_ready, timeout_s), f"service {client.srv_name} not available"
        future = client.call_async(request)
        assert self.spin_until(future.done, timeout_s), f"no response from {client.srv_name}"
        return future.result()

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=2.0)
        for node in reversed(self._nodes):
            node.destroy_node()


@pytest.fixture
def ros_node(ros_context: Any) -> Iterator[NodeHarness]:
    """A `NodeHarness` (helper node + executor) in a fresh context."""
    harness = NodeHarness(ros_context)
    try:
        yield harness
    finally:
        harness.close()


@pytest.fixture
def launch() -> Iterator[Callable[..., LaunchedProcess]]:
    """Factory: ``launch("launch", "file.yaml", "a:=1")`` starts `lsu launch ...`; torn down always."""
    started: List[LaunchedProcess] = []

    def start(*args: str, cwd: Optional[str] = None) -> LaunchedProcess:
        proc = LaunchedProcess(list(args), cwd=cwd)
        started.append(proc)
        return proc

    yield start
    for proc in started:
        try:
            if proc.process.poll() is None:
                proc.interrupt(timeout_s=8.0)
        except subprocess.TimeoutExpired:
            pass
        finally:
            proc.kill()


@pytest.fixture
def lsu_cli() -> Callable[..., subprocess.CompletedProcess]:
    """Run ``lsu ARGS...`` to completion: ``lsu_cli("topic", "list", timeout=30)``."""

    def run(*args: str, timeout: float = 60.0, env: Optional[dict] = None) -> subprocess.CompletedProcess:
        return subprocess.run([LSU, *args], capture_output=True, text=True, timeout=timeout,
                              env=None if env is None else {**os.environ, **env})

    return run

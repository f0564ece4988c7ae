"""Pytest plugin for LSU tests (loaded by the workspace's conftest.py).

- Every test session claims its own ROS_DOMAIN_ID (a lock no other LSU run on this machine
  holds) and forces ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST before anything touches DDS;
  subprocesses inherit both. Under pytest-xdist every worker is a session of its own and claims
  its own domain, so the graphs of tests running side by side never see each other.
- `make test` runs the suite under pytest-xdist with ``--dist loadfile`` (a test module runs whole
  on one worker, so its module-scoped fixtures are built once); the tests marked ``serial``
  (timing-sensitive) and the fault tests are left to its second, serial pytest run.
- ``ros_context``: a fresh rclpy Context per test, always shut down.
- ``ros_node`` / ``spin_until``: a helper node on an executor and a bounded spin.
- ``launch``: starts `lsu launch ...` (or any `lsu` long-runner) in a subprocess and always
  tears it down (SIGINT, then SIGKILL to its whole process group).
- ``lsu_cli``: runs a short `lsu ...` command and returns the CompletedProcess.
- Fault suite: tests marked ``@pytest.mark.fault("name")`` inject one fault and record what
  followed with the ``fault_report`` fixture (error text shown, laser-on time after the fault,
  snaps captured and lost). At the end of the session the records go to ``faults.json``
  (``$LSU_FAULTS_JSON``, default ``test-results/faults.json``) with the totals: faults injected
  / survived (the test passed), the longest laser-on time after a fault, snaps lost.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from lsu_scan import rosenv
from lsu_tools.processes import LSU, LaunchedProcess, ProcessWaitError, pid_alive  # noqa: F401  (re-exported for tests)

# `lsu bag play` into `lsu launch replay`: play only once every reader of the replayed events and images has matched
# (volatile: a reader matched late misses STARTED and TEXTURE and extracts the snaps alone, another cloud). The
# extractor, the matcher and the face processor read the events; the first two the left images.
REPLAY_GRAPH_READERS = ("--expect", "/lsu/scan/events=3", "--expect", "/lsu/stereo/left/image_raw=2")

_claim: rosenv.DomainClaim | None = None


def pytest_configure(config: pytest.Config) -> None:
    """Isolate DDS for the whole session before any test module imports rclpy (and open3d without its
    plotly viewer, as every LSU process)."""
    global _claim
    from lsu_common.o3d import defer_plotly_viewer

    defer_plotly_viewer()
    # one forced domain cannot keep the graphs of two xdist workers apart: workers always claim
    forced = None if os.environ.get("PYTEST_XDIST_WORKER") else os.environ.get("LSU_TEST_DOMAIN_ID")
    os.environ[rosenv.DISCOVERY_VAR] = rosenv.LOCALHOST
    if forced:
        os.environ[rosenv.DOMAIN_VAR] = forced
    else:
        _claim = rosenv.isolate()
    os.environ.setdefault("RCUTILS_COLORIZED_OUTPUT", "0")
    _derandomize_hypothesis()


def _derandomize_hypothesis() -> None:
    """Property tests draw the same examples in every run and process (the project's rule: same input, same
    result): Hypothesis's examples come from a fixed seed per test, and no example database carries one run's
    finds into the next."""
    try:
        from hypothesis import settings
    except ImportError:
        return  # no property tests without it
    settings.register_profile("lsu", derandomize=True, database=None)
    settings.load_profile("lsu")


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Under pytest-xdist, modules with a ``slow`` test run first (each keeps its own order).

    `make test` runs `--dist loadfile --no-loadscope-reorder`, which hands out modules in collection
    order (xdist's default order, most tests first, put the long process-starting modules of one or
    two tests last, where one worker ran them while the other idled). Long modules first keeps both
    workers busy to the end. Outside xdist the order is left alone."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return
    slow_modules = {item.nodeid.split("::", 1)[0] for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: item.nodeid.split("::", 1)[0] not in slow_modules)  # stable sort


_FAULTS: dict[str, dict[str, Any]] = {}  # test id -> its fault record


class FaultReport:
    """What one fault test saw; filled by the test, judged by its outcome."""

    def __init__(self, fault: str, test_id: str) -> None:
        self.record: dict[str, Any] = {"fault": fault, "test": test_id, "error_shown": "", "laser_on_after_s": None,
                                       "laser_goal_s": None, "snaps_captured": None, "snaps_lost": 0,
                                       "data_kept": ""}

    def note(self, **fields: Any) -> None:
        """Record fields: error_shown (text the user saw), laser_on_after_s (time the laser stayed on
        after the fault, 0.0 if it was off), laser_goal_s (the time it should stay on at most: a
        measured figure against its goal, reported, not asserted), snaps_captured, snaps_lost,
        data_kept (what is on disk)."""
        unknown = set(fields) - set(self.record)
        if unknown:
            raise KeyError(f"unknown fault record fields: {sorted(unknown)}")
        self.record.update(fields)


@pytest.fixture
def fault_report(request: pytest.FixtureRequest) -> FaultReport:
    """The record of the fault this test injects (the test must carry ``@pytest.mark.fault(name)``)."""
    marker = request.node.get_closest_marker("fault")
    if marker is None or not marker.args:
        raise pytest.UsageError(f"{request.node.nodeid}: fault_report needs @pytest.mark.fault('name')")
    report = FaultReport(str(marker.args[0]), request.node.nodeid)
    _FAULTS[request.node.nodeid] = report.record
    return report


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: Any) -> Any:
    report = yield
    marker = item.get_closest_marker("fault")
    if marker is not None and marker.args:
        record = _FAULTS.setdefault(item.nodeid, FaultReport(str(marker.args[0]), item.nodeid).record)
        if report.when == "call" or (report.when == "setup" and report.outcome != "passed"):
            record["survived"] = report.outcome == "passed"
            if report.outcome == "failed":
                record["failure"] = str(report.longrepr)[-600:]
    return report


def fault_summary(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Totals of the fault records: injected, survived, longest laser-on time after a fault, snaps lost."""
    laser = [r["laser_on_after_s"] for r in records if r.get("laser_on_after_s") is not None]
    over = [r["fault"] for r in records if r.get("laser_goal_s") is not None
            and r.get("laser_on_after_s") is not None and r["laser_on_after_s"] > r["laser_goal_s"]]
    return {"faults_injected": len(records), "faults_survived": sum(1 for r in records if r.get("survived")),
            "max_laser_on_after_fault_s": max(laser) if laser else 0.0, "laser_on_over_goal": over,
            "snaps_lost": sum(int(r.get("snaps_lost") or 0) for r in records), "faults": records}


def pytest_terminal_summary(terminalreporter: Any, exitstatus: int, config: pytest.Config) -> None:
    """Write faults.json and print the fault table when any fault test ran."""
    if not _FAULTS:
        return
    summary = fault_summary(sorted(_FAULTS.values(), key=lambda r: r["test"]))
    path = Path(os.environ.get("LSU_FAULTS_JSON") or Path(str(config.rootpath)) / "test-results" / "faults.json")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(summary, indent=2) + "\n")
    tr = terminalreporter
    tr.section("LSU fault suite")
    for r in summary["faults"]:
        laser = "-" if r["laser_on_after_s"] is None else f"{r['laser_on_after_s']:.2f} s"
        if r["fault"] in summary["laser_on_over_goal"]:
            laser += f" (goal {r['laser_goal_s']:g} s)"
        tr.write_line(f"{'survived' if r.get('survived') else 'FAILED  '}  {r['fault']:<46} laser on after: {laser:>7}  "
                      f"snaps lost: {r['snaps_lost']}  | {str(r['error_shown'])[:90]}")
    tr.write_line(f"{summary['faults_survived']}/{summary['faults_injected']} faults survived; laser on at most "
                  f"{summary['max_laser_on_after_fault_s']:.2f} s after a fault; {summary['snaps_lost']} snaps lost; "
                  f"{len(summary['laser_on_over_goal'])} over their laser-off goal -> {path}")


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
        self._nodes: list[Any] = [self.node]

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

    def set_parameter(self, node: str, name: str, value: Any, timeout_s: float = 10.0) -> Any:
        """Set one parameter of ``node`` (fully qualified name) through its ``set_parameters`` service, as
        `lsu param set` does; returns the `SetParametersResult` (``successful``, ``reason``)."""
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter

        client = self.node.create_client(SetParameters, f"{node}/set_parameters")
        try:
            request = SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()])
            return self.call(client, request, timeout_s).results[0]
        finally:
            self.node.destroy_client(client)

    def check_parameters(self, node: Any, settable: dict[str, tuple[Any, Callable[[], bool]]]) -> None:
        """Every parameter of ``node`` means what it says, set through its parameter service.

        ``settable``: name -> (a new valid value, a check that the node now uses it). Every
        parameter the node declares (but ``use_sim_time``) must be either read-only, and then a set
        is refused and the value kept, or in ``settable``, and then the set succeeds and the check
        holds. A parameter added later without a case here fails the test.
        """
        name = node.get_fully_qualified_name()
        declared = set(node._parameters) - {"use_sim_time"}
        read_only = {p for p in declared if node.describe_parameter(p).read_only}
        assert declared - read_only == set(settable), (
            f"settable parameters without a case: {sorted(declared - read_only - set(settable))}; "
            f"cases for parameters that are not settable: {sorted(set(settable) - (declared - read_only))}")
        for pname in sorted(read_only):
            before = node.get_parameter(pname).value
            result = self.set_parameter(name, pname, before)
            assert not result.successful and "read-only" in result.reason, (pname, result.reason)
            assert node.get_parameter(pname).value == before, pname
        for pname, (value, took_effect) in settable.items():
            result = self.set_parameter(name, pname, value)
            assert result.successful, (pname, result.reason)
            assert self.spin_until(took_effect, 5.0), f"{pname} := {value!r} was accepted but did not take effect"

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


def _node_running(pid: int) -> bool:
    """A node `lsu launch` started still runs: alive and still the leader of its own session (the launcher
    starts each node in a new session), so a pid taken over by an unrelated process does not count."""
    try:
        return pid_alive(pid) and os.getsid(pid) == pid
    except ProcessLookupError:
        return False


@pytest.fixture
def launch() -> Iterator[Callable[..., LaunchedProcess]]:
    """Factory: ``launch("launch", "file.yaml", "a:=1")`` starts `lsu launch ...`; torn down always.

    A node still running after its launcher stopped is an error of the test: it would stay on the
    worker's ROS domain and confuse every later test there (it is killed and named).
    """
    started: list[LaunchedProcess] = []

    def start(*args: str, cwd: str | None = None) -> LaunchedProcess:
        proc = LaunchedProcess(list(args), cwd=cwd)
        started.append(proc)
        return proc

    yield start
    for proc in started:
        proc.stop(timeout_s=8.0)
    nodes = {f"{label} (pid {pid}) of `lsu {' '.join(proc.args)}`": pid
             for proc in started for label, pid in proc.started_pids().items()}
    end = time.monotonic() + 10.0  # a node the launcher's death signalled (SIGTERM) may still be ending
    while any(_node_running(pid) for pid in nodes.values()) and time.monotonic() < end:
        time.sleep(0.1)
    left = [name for name, pid in nodes.items() if _node_running(pid)]
    for name in left:
        try:
            os.kill(nodes[name], signal.SIGKILL)
        except ProcessLookupError:
            pass
    if left:
        pytest.fail(f"still running after the launcher stopped (now killed): {', '.join(left)}")


@pytest.fixture
def lsu_cli() -> Callable[..., subprocess.CompletedProcess]:
    """Run ``lsu ARGS...`` to completion: ``lsu_cli("topic", "list", timeout=30)``."""

    def run(*args: str, timeout: float = 60.0, env: dict | None = None) -> subprocess.CompletedProcess:
        return subprocess.run([LSU, *args], capture_output=True, text=True, timeout=timeout,
                              env=None if env is None else {**os.environ, **env})

    return run


class FakeGoalHandle:
    """What the scan coordinator uses of rclpy's ServerGoalHandle, for calling its scan directly in a test."""

    def __init__(self, **goal: Any) -> None:
        from lsu_interfaces.action import Scan

        self.request = Scan.Goal(**goal)
        self.is_cancel_requested = False
        self.ended = ""  # "succeeded", "aborted" or "canceled" once the scan ended the goal

    def publish_feedback(self, _fb: Any) -> None:
        pass

    def succeed(self) -> None:
        self.ended = "succeeded"

    def abort(self) -> None:
        self.ended = "aborted"

    def canceled(self) -> None:
        self.ended = "canceled"

"""LsuScanner against a Scan action server that answers at once (the client side of `lsu scan`).

The server here is a stand-in written for the test: it refuses or finishes each goal as soon as it
arrives, so every goal, result and cancel answer comes back within a millisecond. That is the case
where rclpy's unlocked ActionClient dropped answers taken by the spin thread before the calling
thread had registered the request (CI: "Ignoring unexpected goal response", then a 30 s timeout).
"""

from __future__ import annotations

import threading
import time

import pytest

from lsu_scan.scanner import LsuScanner, ScannerError, TaskResult


@pytest.fixture
def instant_server(ros_context):
    import rclpy
    from rclpy.action import ActionServer, CancelResponse, GoalResponse
    from rclpy.executors import MultiThreadedExecutor

    from lsu_interfaces.action import Scan

    node = rclpy.create_node("fake_scan_coordinator", namespace="/lsu", context=ros_context)
    seen = {"goals": 0, "canceled": 0}

    def on_goal(goal: Scan.Goal) -> GoalResponse:
        seen["goals"] += 1
        return GoalResponse.REJECT if goal.label == "reject" else GoalResponse.ACCEPT

    def execute(handle):
        result = Scan.Result(scan_id=handle.request.label, snaps=int(handle.request.end_steps))
        if handle.request.label == "wait-for-cancel":
            end = time.monotonic() + 10.0
            while not handle.is_cancel_requested and time.monotonic() < end:
                time.sleep(0.002)
            if handle.is_cancel_requested:
                seen["canceled"] += 1
                result.status, result.partial = "canceled", True
                handle.canceled()
                return result
        result.success, result.status = True, "finished"
        handle.succeed()
        return result

    server = ActionServer(node, Scan, "scan", execute_callback=execute, goal_callback=on_goal,
                          cancel_callback=lambda _h: CancelResponse.ACCEPT)
    executor = MultiThreadedExecutor(context=ros_context)
    executor.add_node(node)
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    try:
        yield seen
    finally:
        executor.shutdown(timeout_sec=2.0)
        server.destroy()
        node.destroy_node()


def test_every_instant_answer_reaches_the_caller(instant_server):
    with LsuScanner(wait_s=15) as scanner:
        for i in range(60):
            result = scanner.scan(start=0, end=i, step=1, label=f"goal-{i}")
            # each result is this goal's own: a dropped answer would time out, a mixed-up one would not match
            assert result.success and result.scan_id == f"goal-{i}" and result.snaps == i, result
            assert result.result == TaskResult.SUCCEEDED
    assert instant_server["goals"] == 60


def test_rejected_goal_and_cancel(instant_server):
    with LsuScanner(wait_s=15) as scanner:
        with pytest.raises(ScannerError, match="rejected"):
            scanner.start_scan(label="reject")
        for _ in range(5):
            scanner.start_scan(label="wait-for-cancel")
            scanner.cancel_task(timeout_s=10.0)
            result = scanner.get_result(timeout_s=15.0)
            assert result.partial and not result.success and result.status == "canceled"
            assert result.result == TaskResult.CANCELED
    assert instant_server["canceled"] == 5


class _SlowToRegister:
    """rclpy's action client handle, pausing after each request is sent: the answer is then always in
    before rclpy registers the request, which turns the rare race into a certain one."""

    def __init__(self, handle, pause_s: float) -> None:
        self._handle, self._pause_s = handle, pause_s

    def __getattr__(self, name: str):
        attr = getattr(self._handle, name)
        if not name.startswith("send_"):
            return attr

        def send(*args, **kwargs):
            sequence = attr(*args, **kwargs)
            time.sleep(self._pause_s)
            return sequence

        return send


def test_answers_faster_than_request_bookkeeping_are_kept(instant_server):
    with LsuScanner(wait_s=15) as scanner:
        scanner._action._client_handle = _SlowToRegister(scanner._action._client_handle, 0.05)
        for i in range(3):
            result = scanner.scan(start=0, end=i, step=1, label=f"slow-{i}")
            assert result.success and result.scan_id == f"slow-{i}", result
        scanner.start_scan(label="wait-for-cancel")
        scanner.cancel_task(timeout_s=10.0)
        assert scanner.get_result(timeout_s=15.0).status == "canceled"


SCRIPT_WITHOUT_CLOSE = """
from lsu_scan.scanner import LsuScanner
s = LsuScanner(wait_s=30)
r = s.scan(start=0, end=3, step=1, label="no-close")
print(r.result.name, r.scan_id, r.snaps)
"""


@pytest.mark.slow
def test_a_script_that_never_closes_the_scanner_exits_0(instant_server):
    import subprocess
    import sys

    # the README's three lines, no `with`, no close(): the interpreter's exit has to clean up
    done = subprocess.run([sys.executable, "-c", SCRIPT_WITHOUT_CLOSE], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ["SUCCEEDED", "no-close", "3"]
    assert "terminate called" not in done.stderr

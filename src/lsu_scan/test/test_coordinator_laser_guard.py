"""The coordinator's laser guard: a late move, capture or acknowledgement switches the laser off at once.

The coordinator runs its scan in this thread against stand-ins written for the test: a driver
that records every laser request with its arrival time, a camera whose first lit capture answers
late, and a matcher (the camera stand-in itself) that acknowledges each published capture unless
told not to. Truth is what the stand-in driver was asked and when, and what the camera returned.

No assertion here bounds a time from above (a busy host may be late on any of them): the tests
check the order of events (the off came before the late answer, the guard's off before the
scan's own) and that nothing happened early; the deadline arithmetic itself is unit-tested with
a fake clock in test_laser_guard.py.
"""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace
from typing import Any

import pytest
import rclpy
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import SetBool

from lsu_common import stamps
from lsu_interfaces.msg import ScannerState
from lsu_interfaces.srv import CaptureStereo, MoveTo
from lsu_scan.coordinator import ScanCoordinatorNode
from lsu_testing.plugin import FakeGoalHandle

NS = "/lsu_guard_test"
PAUSE_S = 0.3
EXPOSURE_S = 0.033


_stamp = stamps.from_seconds


class Rig:
    """Stand-in driver, camera and matcher, spun in a background thread."""

    def __init__(self, context: Any, late_s: float, late_call: str, exposed: str, acks: bool) -> None:
        self.node = rclpy.create_node("guard_rig", namespace=NS, context=context)
        group = ReentrantCallbackGroup()
        self.laser: list[tuple] = []       # (monotonic arrival, on)
        self.captures: list[dict[str, float]] = []
        self.moves = 0
        self.late_s, self.late_call, self.exposed, self.acks = late_s, late_call, exposed, acks
        self.late_done = False
        self.lit = False
        self.node.create_service(SetBool, "laser/set", self._laser, callback_group=group)
        self.node.create_service(MoveTo, "carriage/move_to", self._move, callback_group=group)
        self.node.create_service(CaptureStereo, "stereo/capture", self._capture, callback_group=group)
        self.state_pub = self.node.create_publisher(ScannerState, "driver/state",
                                                    QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE))
        self.points_pub = self.node.create_publisher(PointCloud2, "points",
                                                     QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE))
        self.node.create_timer(0.05, self._publish_state, callback_group=group)
        self.executor = MultiThreadedExecutor(num_threads=4, context=context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def _publish_state(self) -> None:
        self.state_pub.publish(ScannerState(connected=True, homed=True, position_steps=100, track_steps=470,
                                            step_rate_steps_per_s=200.0))

    def _late(self, call: str) -> None:
        if call == self.late_call and not self.late_done and (call != "capture" or self.lit):
            self.late_done = True
            time.sleep(self.late_s)

    def _laser(self, request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        self.laser.append((time.monotonic(), bool(request.data)))
        self.lit = bool(request.data)
        response.success = True
        return response

    def _move(self, request: MoveTo.Request, response: MoveTo.Response) -> MoveTo.Response:
        self.moves += 1
        self._late("move")
        response.success = True
        response.position_steps = request.position_steps
        response.stopped_stamp = _stamp(time.time())
        return response

    def _capture(self, request: CaptureStereo.Request, response: CaptureStereo.Response) -> CaptureStereo.Response:
        asked_wall, asked = time.time(), time.monotonic()
        lit = self.lit
        self._late("capture")
        # "early": exposed as soon as asked (only the answer is late); "late": exposed just now
        exposed = asked_wall if self.exposed == "early" else time.time()
        self.captures.append({"asked": asked, "answered": time.monotonic(), "lit_when_asked": lit})
        response.success = True
        response.stamp = _stamp(exposed)
        if self.acks and request.publish:
            ack = PointCloud2(width=100, height=1)
            ack.header.stamp = response.stamp
            self.points_pub.publish(ack)
        return response

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=2.0)
        self.node.destroy_node()


def make_coordinator(context: Any, tmp_path: Any, **params: Any) -> ScanCoordinatorNode:
    overrides = {"output_dir": str(tmp_path), "laser_pause_s": PAUSE_S, "exposure_s": EXPOSURE_S,
                 "cloud_timeout_s": 0.1, **params}
    coordinator = ScanCoordinatorNode(context=context, namespace=NS, parameter_overrides=[
        rclpy.parameter.Parameter(k, value=v) for k, v in overrides.items()])
    end = time.monotonic() + 10.0
    while coordinator.state is None or not coordinator.capture.service_is_ready():
        assert time.monotonic() < end, "the stand-ins were not discovered"
        time.sleep(0.05)
    return coordinator


def scan_with(coordinator: ScanCoordinatorNode) -> SimpleNamespace:
    handle = FakeGoalHandle(start_steps=100, end_steps=104, step_steps=2, settle_s=0.0, texture=True)
    result = coordinator._run_goal(handle)
    return SimpleNamespace(result=result, ended=handle.ended, pauses=[p.as_json() for p in coordinator.guard.pauses])


def run_scan(context: Any, tmp_path: Any, rig: Rig, **params: Any) -> SimpleNamespace:
    coordinator = make_coordinator(context, tmp_path, **params)
    try:
        return scan_with(coordinator)
    finally:
        coordinator.destroy_node()


@pytest.fixture
def rig_factory(ros_context):
    rigs: list[Rig] = []

    def make(**kw: Any) -> Rig:
        rigs.append(Rig(ros_context, **kw))
        return rigs[-1]

    yield make
    for rig in rigs:
        rig.close()


def first_guard_off(rig: Rig) -> float:
    """Arrival time of the first laser-off after the laser went on (the guard's)."""
    lit = False
    for t, on in rig.laser:
        if on:
            lit = True
        elif lit:
            return t
    pytest.fail(f"the laser never went off while lit: {rig.laser}")


@pytest.mark.parametrize("exposed", ["early", "late"])
def test_a_late_capture_switches_the_laser_off_and_a_capture_after_the_off_is_taken_again(
        ros_context, tmp_path, rig_factory, exposed):
    rig = rig_factory(late_s=1.0, late_call="capture", exposed=exposed, acks=True)
    scan = run_scan(ros_context, tmp_path, rig)
    assert scan.ended == "succeeded" and scan.result.snaps == 3, scan.result.status
    late = next(c for c in rig.captures if c["answered"] - c["asked"] > 0.5)
    off = first_guard_off(rig) - late["asked"]
    assert off > EXPOSURE_S + PAUSE_S - 0.05, f"laser off {off:.3f} s after the capture: before it was late"
    assert off < late["answered"] - late["asked"], "the guard must not wait for the late answer"
    assert len(scan.pauses) == 1 and "stereo/capture" in scan.pauses[0]["why"]
    lit_captures = sum(1 for c in rig.captures if c["lit_when_asked"])
    # exposed before the off: kept; exposed after it: the laser line may be missing, so taken again
    assert lit_captures == (3 if exposed == "early" else 4), rig.captures
    assert all(c["lit_when_asked"] for c in rig.captures[1:]), "every snap must be exposed with the laser on"
    assert rig.laser[-1][1] is False, "the laser must be off at the end"


def test_a_late_move_switches_the_laser_off_and_on_again_before_the_capture(ros_context, tmp_path, rig_factory):
    rig = rig_factory(late_s=1.0, late_call="move", exposed="early", acks=True)
    scan = run_scan(ros_context, tmp_path, rig)
    assert scan.ended == "succeeded" and scan.result.snaps == 3, scan.result.status
    assert len(scan.pauses) == 1 and "move to" in scan.pauses[0]["why"]
    assert all(c["lit_when_asked"] for c in rig.captures[1:]), "every snap must be exposed with the laser on"
    assert [on for _t, on in rig.laser] == [False, True, False, True, False]


def test_missing_acknowledgements_switch_the_laser_off_soon_after_the_capture(ros_context, tmp_path, rig_factory):
    rig = rig_factory(late_s=0.0, late_call="", exposed="early", acks=False)
    scan = run_scan(ros_context, tmp_path, rig, ack_timeout_s=1.5)
    assert scan.ended == "aborted" and "not acknowledged by stereo_matcher" in scan.result.status
    assert scan.result.partial and scan.result.snaps == 1
    off = first_guard_off(rig) - rig.captures[1]["answered"]
    assert off > PAUSE_S - 0.05, f"laser off {off:.3f} s after the unacknowledged capture: before it was late"
    assert len(scan.pauses) == 1 and "snap 0 not acknowledged" in scan.pauses[0]["why"]
    # the guard's off, then the scan's own off when it aborted ack_timeout_s after the capture
    assert [on for _t, on in rig.laser] == [False, True, False, False]


def test_a_scan_that_ended_while_the_laser_was_paused_leaves_the_next_scans_guard_armed(
        ros_context, tmp_path, rig_factory):
    rig = rig_factory(late_s=0.0, late_call="", exposed="early", acks=False)
    coordinator = make_coordinator(ros_context, tmp_path, ack_timeout_s=1.0)
    try:
        first = scan_with(coordinator)
        assert first.ended == "aborted" and len(first.pauses) == 1  # it ended paused
        rig.acks, rig.late_call, rig.late_s, rig.late_done = True, "move", 1.0, False
        rig.laser.clear()
        second = scan_with(coordinator)
    finally:
        coordinator.destroy_node()
    assert second.ended == "succeeded", second.result.status
    assert len(second.pauses) == 1 and "move to" in second.pauses[0]["why"], second.pauses
    assert [on for _t, on in rig.laser] == [False, True, False, True, False]


def test_a_slow_capture_does_not_delay_the_off_for_its_missing_acknowledgement(ros_context, tmp_path, rig_factory):
    # answered 0.25 s after it was asked: slow, but within exposure + pause, so no capture pause
    rig = rig_factory(late_s=0.25, late_call="capture", exposed="early", acks=False)
    scan = run_scan(ros_context, tmp_path, rig, ack_timeout_s=1.5)
    assert scan.ended == "aborted" and "not acknowledged by stereo_matcher" in scan.result.status
    slow = rig.captures[1]
    assert slow["answered"] - slow["asked"] > 0.2 and slow["lit_when_asked"]
    off = first_guard_off(rig) - slow["asked"]
    # due from when the exposure was due (test_laser_guard.py checks that arithmetic): not before that
    assert off > EXPOSURE_S + PAUSE_S - 0.05, f"laser off {off:.3f} s after the ask: before it was late"
    assert len(scan.pauses) == 1 and "snap 0 not acknowledged" in scan.pauses[0]["why"], scan.pauses
    assert [on for _t, on in rig.laser] == [False, True, False, False]

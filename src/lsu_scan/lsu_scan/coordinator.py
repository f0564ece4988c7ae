"""`scan_coordinator` node: stop-snap and sweep scans through the `/lsu/scan` action (thesis ch. 3.3).

Stop-snap: laser off -> texture pair -> laser on -> for each position: move, settle, the matcher's
acknowledgement of the previous snap (its per-snap `points`; processed during this move and
settle), capture, SNAP event -> last acknowledgement -> laser off -> FINISHED -> scan cloud on disk.

Sweep: laser off -> (a move to the nearer end of the range, unless the carriage stands at one: the
sweep runs from that end to the other, in either direction) -> laser on -> one move to the other
end at the sweep rate and the cameras' free-running stream (``stereo/stream``) -> SWEEP_START -> the
motion's and the stream's end -> stream stop -> SWEEP_END -> laser off -> texture pair (the
carriage stands still; the matcher meanwhile processes the last frames) -> the matcher's points of
every published frame (keyed on the pairs' stamps) -> FINISHED. No call per frame; frames dropped
are counted from the stamps (`sweep_plan.count_frames`). A cancel stops the carriage and the stream.

Safety: the laser is switched off in a `finally` on every way out (success, cancel, driver
fault, capture timeout, lost snap, node shutdown); what was captured is kept and the scan is
marked partial with the reason. While the scan runs, the laser is only on while the scan makes
progress: a move, a capture or a snap's acknowledgement that is ``laser_pause_s`` late switches it
off at once, without waiting for the late answer (the laser guard); it comes back on before the
next capture, and a capture exposed after the laser went off is taken again.
"""

from __future__ import annotations

import datetime as _dt
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import SetParametersResult
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import SetBool, Trigger

from lsu_cameras.polled import PolledGroup, take_latest
from lsu_common import qos, stamps
from lsu_common.node import LsuNode, main_of
from lsu_common.params import declare_parameters
from lsu_interfaces.action import Scan
from lsu_interfaces.msg import LaserLine, ScanEvent, ScannerState, StereoExposure
from lsu_interfaces.srv import CaptureStereo, MoveTo, StreamStereo

from .laser_guard import LaserGuard, ack_due_at
from .scan_plan import (
    ScanGoalError,
    ScanPlan,
    ScanRecord,
    SnapRecord,
    calibration_checksum,
    mechanical_lower_bound_s,
    new_scan_id,
    plan_positions,
)
from .settle import DEFAULT_TOLERANCE_PX, SETTLE_MODES, SettleTrace, profile_from_line, settle_from_images
from .sweep_plan import FrameCount, SweepPlan, count_frames, oriented, plan_sweep, scan_mode

EVENTS_QOS = qos.EVENTS
LATCHED = qos.LATCHED
# how long the end-of-scan laser-off call may still wait once a shutdown began: `lsu launch`
# SIGKILLs 4 s after its SIGINT, and scan.json and the bag must be on disk before that
SHUTDOWN_CALL_S = 0.5


class ScanAborted(Exception):
    """The scan cannot go on; the message is the reason given to the user."""


class ScanCanceled(ScanAborted):
    """The user canceled the goal."""


_key = stamps.to_ns  # an image stamp as the key of its acknowledgement
# after a sweep's last frame has its points, how long frames still without theirs are waited for [s]
SWEEP_POINTS_GRACE_S = 0.2
# how long a new scan waits for the driver's and the camera's services (a graph still starting) [s]
GRAPH_WAIT_S = 20.0


# name -> (default, description, (low, high) or None). Every one is read when it is used, so a
# `param set` takes effect at the next call, deadline or scan; values outside the range are refused.
PARAMETERS: dict[str, tuple[Any, str, tuple[float, float] | None]] = {
    "output_dir": ("", "parent folder of scans/<id>/; empty = scans/ in the directory the node was started from (applies from the next scan)", None),
    "capture_timeout_s": (1.0, "a stereo/capture call longer than this aborts (+ 0.3 s for the reply; below the "
                               "laser watchdog) [s]", (0.05, 30.0)),
    "ack_timeout_s": (5.0, "a snap the matcher does not acknowledge within this (from its capture) aborts the "
                           "scan [s]", (0.1, 600.0)),
    "laser_pause_s": (0.2, "a move, capture or snap acknowledgement this late switches the laser off until the "
                           "scan goes on [s] (applies from the next deadline)", (0.02, 1.5)),
    "move_timeout_s": (0.0, "carriage/move_to timeout [s]; 0 = the driver's own", (0.0, 600.0)),
    "cloud_timeout_s": (15.0, "wait for the matcher's scan/cloud after the scan [s]", (0.0, 600.0)),
    "exposure_s": (0.033, "camera exposure: the mechanical lower bound in scan.json, when a capture is due [s]",
                   (0.0, 1.0)),
    "calibration_dir": ("", "calibration folder used (its checksum goes in scan.json; applies from the next scan)",
                        None),
    "settle": ("fixed", "after each stop: 'fixed' waits the goal's settle_s; 'adaptive' captures as soon as the "
                        "laser line stopped moving (two frames agree), at the latest once settle_s has passed "
                        "(lsu_scan.settle)", None),
    "settle_tolerance_px": (DEFAULT_TOLERANCE_PX, "adaptive settle: the line counts as still when it moved less "
                                                  "than this between two frames [px]", (0.01, 5.0)),
}


@dataclass
class ScanRun:
    """One scan's state while it runs: what it is, and what it captured so far (kept on every way out)."""

    scan_id: str
    folder: Path
    plan: ScanPlan
    record: ScanRecord
    start_state: ScannerState                         # the driver's state when the goal came
    started: float                                    # monotonic
    captured: list[SnapRecord] = field(default_factory=list)
    points_total: int = 0
    abort_reason: str = ""
    canceled: bool = False
    sweep: SweepPlan | None = None                 # a sweep scan's plan; None: stop-snap
    frames: FrameCount | None = None                # a sweep's frames counted from stamps, once its stream ended
    stream: dict[str, Any] = field(default_factory=dict)  # a sweep's stream figures for scan.json
    first_key: int = 0                                # a sweep's first pair (stamp ns)
    frame_keys: list[int] = field(default_factory=list)          # stamps of the pairs the stream published
    frame_arrivals: dict[int, float] = field(default_factory=dict)  # stamp -> monotonic time its exposure came


class ScanCoordinatorNode(LsuNode):
    """Serves the ``scan`` action; publishes ``scan/events``; writes one folder per scan."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("scan_coordinator", **{"namespace": "/lsu", **kwargs})
        # the laser guard's books (scan thread only); the off call it sent without waiting for the reply
        self.guard = LaserGuard(pause_s=float(PARAMETERS["laser_pause_s"][0]))
        self._off_future: Any = None
        self._guarded_ack: int | None = None  # the image stamp whose points the "ack" deadline waits for
        self._capture_asked = 0.0  # monotonic time the last capture was asked for
        declare_parameters(self, PARAMETERS, check=self._check_parameters, apply=self._apply_parameters)
        group = ReentrantCallbackGroup()
        # The scan loop's own traffic (service calls, per-snap acknowledgements) lives on a private
        # node that the scan thread spins itself while it waits: a reply is handled in the thread
        # that waits for it, with no hand-off through the multi-threaded executor (a wait-set
        # rebuild and two thread switches per message, ~5-10 ms per call on a busy 2-core machine).
        # No global arguments: the process's `-r __node:=scan_coordinator` would give it our name.
        self._io = LsuNode("_scan_coordinator_io", namespace=self.get_namespace(), context=self.context,
                           use_global_arguments=False, start_parameter_services=False)
        self._io_executor = SingleThreadedExecutor(context=self.context)
        self._io_executor.add_node(self._io)
        self.laser = self._io.create_client(SetBool, "laser/set")
        self.move = self._io.create_client(MoveTo, "carriage/move_to")
        self.capture = self._io.create_client(CaptureStereo, "stereo/capture")
        self.stream = self._io.create_client(StreamStereo, "stereo/stream")
        self.stop_carriage = self._io.create_client(Trigger, "carriage/stop")
        # a sweep's published pairs: stamp -> (exposure_s, wall and monotonic time of arrival); one small
        # message per pair
        self._exposures: dict[int, tuple[float, float, float]] = {}
        self._io.create_subscription(StereoExposure, "stereo/exposure", self._on_exposure, QoSProfile(
            depth=100, reliability=ReliabilityPolicy.RELIABLE))
        # whether stereo_matcher places sweep frames on a laser sheet (its /diagnostics say), for scan.json
        self._matcher_sheet = ""
        self._io.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 10)
        self.events = self.create_publisher(ScanEvent, "scan/events", EVENTS_QOS)
        self._state: ScannerState | None = None
        self._acks: dict[int, tuple] = {}  # image stamp -> (points, monotonic arrival time)
        # adaptive settle: the laser_extractor's left lines by image stamp, subscribed at the first adaptive scan
        self._left_lines: OrderedDict[int, LaserLine] = OrderedDict()
        self._left_line_sub: Any = None
        self._cloud: PointCloud2 | None = None
        self._cloud_serial = 0
        self._cond = threading.Condition()
        self._stopping = False
        # read when a goal starts, not followed: as an executor-run subscription it woke the
        # multi-threaded executor 300-1300 times a second during a scan (the reader kept reporting
        # ready with nothing to take), 10-15 % of a core taken from the scan's own processes
        self._state_sub = self.create_subscription(
            ScannerState, "driver/state", lambda _msg: None,
            QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE), callback_group=PolledGroup())
        self._io.create_subscription(PointCloud2, "points", self._on_points, QoSProfile(
            depth=50, reliability=ReliabilityPolicy.RELIABLE))
        # on the main node: latched, and it must be current when the next scan starts
        self.create_subscription(PointCloud2, "scan/cloud", self._on_cloud, LATCHED, callback_group=group)
        self._busy = threading.Lock()      # held by the scan thread while a scan runs
        self._goal_lock = threading.Lock()  # makes "is a scan running or accepted?" and "accept" one step
        self._goal_active = False
        self._counter = 0
        self._server = ActionServer(self, Scan, "scan", execute_callback=self._execute,
                                    goal_callback=self._on_goal, cancel_callback=lambda _h: CancelResponse.ACCEPT,
                                    callback_group=group)

    # ------------------------------------------------------------------------------ inputs
    @property
    def state(self) -> ScannerState | None:
        """The newest gp32_driver state received (None before the first)."""
        latest = take_latest(self._state_sub)
        if latest is not None:
            self._state = latest
        return self._state

    def _on_points(self, msg: PointCloud2) -> None:
        with self._cond:
            self._acks[_key(msg.header.stamp)] = (int(msg.width) * int(msg.height), time.monotonic())
            self._cond.notify_all()

    def _on_exposure(self, msg: StereoExposure) -> None:
        if msg.streaming:
            self._exposures[_key(msg.header.stamp)] = (float(msg.exposure_s), time.time(), time.monotonic())

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name.endswith("stereo_matcher: stereo matching"):
                for value in status.values:
                    if value.key == "laser_sheet":
                        self._matcher_sheet = value.value

    def _on_cloud(self, msg: PointCloud2) -> None:
        with self._cond:
            self._cloud = msg
            self._cloud_serial += 1
            self._cond.notify_all()

    def _on_goal(self, _goal: Scan.Goal) -> GoalResponse:
        # One step under one lock: two goals sent at the same moment are not both accepted (the
        # second would otherwise be queued behind the first instead of refused).
        with self._goal_lock:
            if self._goal_active:
                self.get_logger().warning("scan goal rejected: a scan is already running")
                return GoalResponse.REJECT
            self._goal_active = True
        return GoalResponse.ACCEPT

    # ------------------------------------------------------------------------------ parameters
    def _check_parameters(self, changed: list[Parameter]) -> SetParametersResult:
        """Refuse values the scan could not use, with a sentence saying why (ranges are checked by rclpy)."""
        for param in changed:
            if param.name == "settle" and param.value not in SETTLE_MODES:
                return SetParametersResult(successful=False, reason=f"settle '{param.value}' is not one of "
                                                                    f"{', '.join(SETTLE_MODES)}")
            if param.name in ("output_dir", "calibration_dir") and param.value:
                path = Path(str(param.value))
                if path.exists() and not path.is_dir():
                    return SetParametersResult(successful=False,
                                               reason=f"{param.name} {path} exists and is not a folder")
        return SetParametersResult(successful=True)

    def _apply_parameters(self, changed: list[Parameter]) -> None:
        """Every accepted value takes effect now: the scan reads these attributes at each use."""
        for param in changed:
            if param.name not in PARAMETERS:
                continue
            value = param.value
            if param.name == "output_dir":
                self.output_dir = Path(value) if value else Path.cwd() / "scans"
            elif param.name in ("calibration_dir", "settle"):
                setattr(self, param.name, str(value))
            else:
                setattr(self, param.name, float(value))
                if param.name == "laser_pause_s":
                    self.guard.pause_s = float(value)

    # ------------------------------------------------------------------------------ helpers
    @property
    def shutting_down(self) -> bool:
        """The node is being stopped (Ctrl-C, SIGTERM, destroy_node): the scan must end now, data kept."""
        return self._stopping or not self.context.ok()

    def _call(self, client: Any, request: Any, timeout_s: float, what: str, stop_early: bool = True,
              due_s: float | None = None) -> Any:
        """One service call from the scan thread, spinning the private node until the reply is in.

        With ``stop_early`` a shutdown ends the wait at once (the answering node is going down too,
        and the launcher's grace period is short); the laser-off call at the end does not stop early
        but gives up :data:`SHUTDOWN_CALL_S` after a shutdown begins, even one that begins mid-call
        (the driver, stopped by the same Ctrl-C, switches the laser off itself and will not answer).
        ``due_s``: when the answer is expected; ``laser_pause_s`` past it the laser guard switches
        the laser off while the wait goes on.
        """
        # polled here rather than with client.wait_for_service, which sleeps 0.25 s at a time and
        # does not run the laser guard meanwhile
        available_by = time.monotonic() + min(timeout_s, 5.0)
        while not client.service_is_ready():
            if time.monotonic() >= available_by or not self.context.ok():
                raise ScanAborted(f"{what}: service {client.srv_name} is not available (is its node running?)")
            self._guard_laser()
            time.sleep(0.01)
        future = client.call_async(request)
        end = time.monotonic() + timeout_s
        if due_s is not None:
            self.guard.due("call", time.monotonic() + due_s, f"{what}: no answer from {client.srv_name}")
        try:
            self._await_future(future, client, end, stop_early)
        finally:
            self.guard.answered("call")
        if not future.done():
            client.remove_pending_request(future)
            raise ScanAborted(f"{what}: no answer from {client.srv_name} within {timeout_s:g} s")
        return future.result()

    def _await_future(self, future: Any, client: Any, end: float, stop_early: bool) -> None:
        """Spin the private node until ``future`` is done or ``end`` (monotonic) passed; see `_call`."""
        while not future.done() and time.monotonic() < end:
            if self.shutting_down:
                if stop_early or not self.context.ok():  # a shut-down context receives nothing any more
                    client.remove_pending_request(future)
                    raise ScanAborted("scan_coordinator is shutting down")
                end = min(end, time.monotonic() + SHUTDOWN_CALL_S)  # the first cut stays: later ones are later
            self._guard_laser()
            self._io_executor.spin_until_future_complete(future, timeout_sec=min(0.02, max(0.0, end - time.monotonic())))

    def _guard_laser(self) -> None:
        """Switch the laser off now if the scan is late on a deadline, without waiting for the reply.

        Called by every wait of the scan thread. A stalled pipeline (a hung camera, a dead matcher,
        a driver that does not report the stop) then leaves the laser on for ``laser_pause_s`` past
        the moment the answer was due, not for the whole timeout of the call it waits on.
        """
        if self._guarded_ack is not None and self._guarded_ack in self._acks:
            self.guard.answered("ack")
            self._guarded_ack = None
        warning = self.guard.overdue(time.monotonic())
        if warning is None:
            return
        self._off_future = self.laser.call_async(SetBool.Request(data=False))
        self.guard.switched_off(warning, time.time())
        self.get_logger().warning(f"{warning}: laser off until the scan can go on")

    def _resume_laser(self) -> None:
        """Laser on again before a capture if the guard switched it off (after its off call is through)."""
        if self._off_future is not None:
            # the driver serves calls concurrently: the on must not overtake the off
            future, self._off_future = self._off_future, None
            try:
                self._await_future(future, self.laser, time.monotonic() + 3.0, stop_early=True)
            finally:
                self.guard.off_settled()
            if not future.done():
                self.laser.remove_pending_request(future)
        if not self.guard.lit:
            self._set_laser(True)

    def _set_laser(self, on: bool, timeout_s: float = 3.0, stop_early: bool = True) -> None:
        if not on:
            self.guard.lit_by_scan(False)  # the guard must not send another off meanwhile
        response = self._call(self.laser, SetBool.Request(data=on), timeout_s, f"laser {'on' if on else 'off'}",
                              stop_early=stop_early)
        if not response.success:
            raise ScanAborted(f"laser {'on' if on else 'off'} failed: {response.message}")
        self.guard.lit_by_scan(on)

    def _laser_off_safely(self) -> str:
        # on shutdown the driver is stopping too (it switches the laser off itself): ask briefly
        timeout = SHUTDOWN_CALL_S if self.shutting_down else 3.0
        try:
            self._set_laser(False, timeout, stop_early=False)
            return ""
        except Exception as exc:  # noqa: BLE001 - a dead context raises rclpy's own types; never skip the files
            self.get_logger().error(f"could not switch the laser off: {exc} (the driver's shutdown or the "
                                    "firmware watchdog will)")
            return str(exc) or exc.__class__.__name__

    def _capture(self, lit: bool = True) -> Any:
        """One published stereo capture; with ``lit`` the laser is on during its exposure.

        A capture the laser guard interrupted is taken again unless its exposure (the image stamp,
        from the same system clock) ended before the laser was switched off.
        """
        exposure = float(self.exposure_s)
        for _attempt in range(3):
            if lit:
                self._resume_laser()
            self._capture_asked = time.monotonic()
            response = self._call(self.capture,
                                  CaptureStereo.Request(publish=True, timeout_s=float(self.capture_timeout_s)),
                                  float(self.capture_timeout_s) + 0.3, "capture", due_s=exposure if lit else None)
            if not response.success:
                raise ScanAborted(f"capture failed: {response.message}")
            exposed_until = stamps.to_seconds(response.stamp) + exposure
            if not lit or self.guard.lit or exposed_until < self.guard.last_off_wall:
                return response
            self.get_logger().warning("the capture came after the laser went off: taking it again")
        raise ScanAborted(f"capture: 3 captures in a row came {self.laser_pause_s:g} s late (the laser went off "
                          "meanwhile); is the camera overloaded?")

    def _event(self, kind: int, scan_id: str, folder: Path, **fields: Any) -> None:
        msg = ScanEvent(type=kind, scan_id=scan_id, output_dir=str(folder))
        msg.header.stamp = self.get_clock().now().to_msg()
        for name, value in fields.items():
            setattr(msg, name, value)
        try:
            self.events.publish(msg)
        except Exception as exc:  # noqa: BLE001 - rclpy raises its own types on a context going down
            if not self.shutting_down:
                raise
            self.get_logger().warning(f"scan event {kind} not published, shutting down ({exc.__class__.__name__})")

    def _wait(self, predicate: Callable[[], bool], timeout_s: float, spin: bool = True) -> bool:
        """Wait until ``predicate()``; with ``spin`` the scan thread handles the private node meanwhile."""
        end = time.monotonic() + timeout_s
        while not predicate():
            remaining = end - time.monotonic()
            if remaining <= 0:
                return False
            if self.shutting_down:
                raise ScanAborted("scan_coordinator is shutting down")
            if spin:
                self._guard_laser()
                self._io_executor.spin_once(timeout_sec=min(remaining, 0.02))
            else:
                with self._cond:
                    self._cond.wait(min(remaining, 0.05))
        return True

    def _check_cancel(self, goal_handle: Any) -> None:
        if goal_handle.is_cancel_requested:
            raise ScanCanceled("canceled by the user")
        if self.shutting_down:
            raise ScanAborted("scan_coordinator is shutting down")

    def _since_stop_s(self, stamp: Any) -> float | None:
        """Seconds since the driver saw the carriage stop (``MoveTo.Response.stopped_stamp``), or None.

        The vibration the settle waits out decays from the stop, not from when the move's reply
        reached us; a stamp that is missing (an older driver) or implausible (clock trouble) counts
        as no time passed, i.e. the full settle.
        """
        stopped = stamps.to_seconds(stamp)
        if stopped <= 0.0:
            return None
        elapsed = time.time() - stopped  # the driver stamps with the system clock of this machine
        return elapsed if 0.0 <= elapsed <= 0.5 else None

    def _sleep(self, goal_handle: Any, seconds: float) -> None:
        """Settle: wait ``seconds``, handling acknowledgements and checking for a cancel meanwhile."""
        end = time.monotonic() + seconds
        while True:
            remaining = end - time.monotonic()
            if remaining <= 0:
                return
            self._check_cancel(goal_handle)
            self._guard_laser()
            # an acknowledgement wakes this wait at once; the timeout only bounds how late a cancel
            # (handled on the main node) is seen, and each wake-up costs a wait-set rebuild
            self._io_executor.spin_once(timeout_sec=min(0.02, remaining))

    # ------------------------------------------------------------------------------ the scan
    def _execute(self, goal_handle: Any) -> Scan.Result:
        try:
            with self._busy:
                return self._scan(goal_handle)
        finally:
            with self._goal_lock:
                self._goal_active = False

    def _scan(self, goal_handle: Any) -> Scan.Result:
        """plan -> snap loop -> finish; the laser is off and the files are on disk on every way out."""
        run = self._plan(goal_handle)
        if isinstance(run, Scan.Result):
            return run  # refused before anything moved
        recorder = self._start_bag_or_warn(run) if goal_handle.request.record_bag else None
        if run.sweep is None:
            self.get_logger().info(f"scan {run.scan_id}: {len(run.plan.positions)} snaps {run.plan.positions[0]}.."
                                   f"{run.plan.positions[-1]} step {goal_handle.request.step_steps}, settle "
                                   f"{run.plan.settle_s:g} s -> {run.folder}")
        else:
            sweep = run.sweep
            self.get_logger().info(f"scan {run.scan_id}: sweep {sweep.start}..{sweep.end} ({sweep.direction}) at "
                                   f"{sweep.rate_steps_s:g} steps/s, {sweep.frames_expected} frames at "
                                   f"{sweep.frame_rate_hz:g} fps -> {run.folder}")
        self._event(ScanEvent.STARTED, run.scan_id, run.folder, expected_snaps=run.record.snaps_expected)
        cloud_serial_before = self._cloud_serial
        with self._cond:
            self._acks.clear()  # left from an earlier scan, or from a capture that was taken again
        self.guard.start_scan()
        try:
            (self._snap_loop if run.sweep is None else self._sweep_loop)(goal_handle, run)
        except ScanCanceled as exc:
            run.abort_reason, run.canceled = str(exc), True
        except ScanAborted as exc:
            run.abort_reason = str(exc)
        except Exception as exc:  # a bug must still leave the laser off and the data on disk
            if self.shutting_down:  # rclpy's own exceptions out of a context the signal handler shut down
                run.abort_reason = f"scan_coordinator is shutting down ({exc.__class__.__name__})"
            else:
                run.abort_reason = f"internal error: {exc.__class__.__name__}: {exc}"
                self.get_logger().error(run.abort_reason)
        finally:
            self.guard.clear()
            self._guarded_ack = None
            self._off_future = None  # superseded by this off (a left-over one would disarm the next scan's guard)
            laser_error = self._laser_off_safely()
        return self._finish(goal_handle, run, laser_error, cloud_serial_before, recorder)

    def _plan(self, goal_handle: Any) -> Any:
        """The scan's id, folder, record and validated positions, or the refusal (a Scan.Result, goal aborted)."""
        goal: Scan.Goal = goal_handle.request
        t0 = time.monotonic()
        self._counter += 1
        scan_id = new_scan_id(counter=self._counter)
        parent = Path(goal.output_dir) if goal.output_dir else self.output_dir
        folder = parent / scan_id
        calib = Path(self.calibration_dir) if self.calibration_dir else None
        record = ScanRecord(scan_id=scan_id, started=_dt.datetime.now().isoformat(timespec="seconds"),
                            goal={k: getattr(goal, k) for k in goal.get_fields_and_field_types()},
                            parameters={"capture_timeout_s": self.capture_timeout_s, "ack_timeout_s": self.ack_timeout_s,
                                        "cloud_timeout_s": self.cloud_timeout_s, "exposure_s": self.exposure_s,
                                        "laser_pause_s": self.laser_pause_s, "settle": self.settle,
                                        "settle_tolerance_px": self.settle_tolerance_px},
                            calibration=calibration_checksum(calib))
        state = self.state
        try:
            if state is None or not state.connected:
                raise ScanAborted("no state from gp32_driver (driver/state): is the driver running and connected?")
            if not state.homed:
                raise ScanAborted("the carriage is not homed: call carriage/home (or `lsu service call "
                                  "/lsu/carriage/home`) before scanning")
            # a scan asked for as soon as the graph is launched may come before the camera node is up (the
            # driver homes first): nothing is captured and the laser is off yet, so waiting here loses nothing
            clients = (self.laser, self.move, self.capture)
            if not self._wait(lambda: all(c.service_is_ready() for c in clients), GRAPH_WAIT_S):
                missing = [c.srv_name for c in clients if not c.service_is_ready()]
                raise ScanAborted(f"service {', '.join(missing)} is not available after {GRAPH_WAIT_S:g} s (is its "
                                  f"node running?)")
            try:
                plan = plan_positions(goal.start_steps, goal.end_steps, goal.step_steps, state.track_steps,
                                      goal.settle_s, goal.texture)
                sweep = None
                if scan_mode(goal.mode) == "sweep":
                    sweep = oriented(plan_sweep(goal.start_steps, goal.end_steps, state.track_steps,
                                                float(goal.sweep_rate_steps_s), float(goal.frame_rate_hz)),
                                     float(state.position_steps))
            except ScanGoalError as exc:
                raise ScanAborted(f"bad goal: {exc}") from None
        except ScanAborted as exc:
            self.get_logger().error(f"scan {scan_id} refused: {exc}")
            goal_handle.abort()
            return Scan.Result(scan_id=scan_id, output_dir=str(folder), status=str(exc))
        record.snaps_expected = len(plan.positions)
        record.timings_s["mechanical_lower_bound"] = mechanical_lower_bound_s(
            plan, state.position_steps, max(1.0, state.step_rate_steps_per_s), float(self.exposure_s))
        if sweep is not None:
            record.snaps_expected = sweep.frames_expected
            record.timings_s["mechanical_lower_bound"] = (
                abs(sweep.start - state.position_steps) / max(1.0, state.step_rate_steps_per_s) + sweep.duration_s
                + (float(self.exposure_s) if plan.texture else 0.0))
        folder.mkdir(parents=True, exist_ok=True)
        return ScanRun(scan_id=scan_id, folder=folder, plan=plan, record=record, start_state=state, started=t0,
                       sweep=sweep)

    def _start_bag_or_warn(self, run: ScanRun) -> Any:
        try:
            return self._start_bag(run.folder)
        except Exception as exc:  # no bag is no reason to lose the scan: say so and go on
            self.get_logger().error(f"bag recording could not start ({exc.__class__.__name__}: {exc}); "
                                    "scanning without a bag")
            return None

    def _snap_loop(self, goal_handle: Any, run: ScanRun) -> None:
        """Texture pair, then move / settle / previous snap's points / capture / SNAP for each position.

        Raises ScanAborted / ScanCanceled; ``run.captured`` holds every snap taken so far either way.
        """
        plan, state, total = run.plan, run.start_state, len(run.plan.positions)
        self._set_laser(False)
        if plan.texture:
            response = self._capture(lit=False)
            self._event(ScanEvent.TEXTURE, run.scan_id, run.folder, image_stamp=response.stamp)
        self._set_laser(True)
        snap_times: list[float] = []
        if self.settle == "adaptive":
            self._follow_left_lines()
        # the last snap, until the matcher acknowledges it: its processing overlaps the next move and
        # settle, so the ack is awaited only before the next capture (at most one snap in flight there)
        pending: dict[str, Any] | None = None
        rate = max(1.0, float(state.step_rate_steps_per_s))
        here = int(state.position_steps)
        for index, position in enumerate(plan.positions):
            t_snap = time.monotonic()
            self._check_cancel(goal_handle)
            self._feedback(goal_handle, "moving", index, total, position, run.points_total, snap_times)
            request = MoveTo.Request(position_steps=position, timeout_s=float(self.move_timeout_s))
            moved = self._call(self.move, request, float(self.move_timeout_s) or 60.0, f"move to {position}",
                               due_s=abs(position - here) / rate)
            if not moved.success:
                raise ScanAborted(f"move to {position} failed: {moved.message}")
            here = int(moved.position_steps)
            t_moved = time.monotonic()
            since_stop = self._since_stop_s(moved.stopped_stamp)
            trace: SettleTrace | None = None
            if self.settle == "adaptive":
                response, trace, t_slept, t_settled = self._adaptive_capture(goal_handle, run, pending, t_moved,
                                                                             plan.settle_s - (since_stop or 0.0))
                pending = None
            else:
                self._sleep(goal_handle, plan.settle_s - (since_stop or 0.0))
                t_slept = time.monotonic()
                if pending is not None:
                    run.points_total += self._await_ack(pending)
                    pending = None
                t_settled = time.monotonic()
                response = self._capture()
            t_captured = time.monotonic()
            key = _key(response.stamp)
            self._event(ScanEvent.SNAP, run.scan_id, run.folder, index=index, position_steps=moved.position_steps,
                        image_stamp=response.stamp, expected_snaps=total)
            # per-phase wall times: where a snap's time goes (bench_scan reads them)
            snap = SnapRecord(index=index, position_steps=int(moved.position_steps), stamp=stamps.to_text(key),
                              skew_s=float(response.skew_s), move_s=round(t_moved - t_snap, 4),
                              settle_s=round(t_slept - t_moved, 4),
                              stop_to_reply_s=None if since_stop is None else round(since_stop, 4),
                              ack_wait_s=round(t_settled - t_slept, 4), capture_s=round(t_captured - t_settled, 4))
            if trace is not None:
                snap.settle = trace.as_json()
            run.captured.append(snap)
            pending = {"snap": snap, "key": key, "t_captured": t_captured, "t_snap": t_snap}
            # Its points are due at once (~10 ms): a stalled pipeline must not keep the laser on.
            self._guarded_ack = key
            self.guard.due("ack", ack_due_at(t_captured, self._capture_asked, float(self.exposure_s)),
                           f"snap {index} not acknowledged by stereo_matcher")
            snap_times.append(time.monotonic() - t_snap)
        if pending is not None:
            run.points_total += self._await_ack(pending)
        self._feedback(goal_handle, "finishing", total, total, plan.positions[-1], run.points_total, snap_times)

    def _follow_left_lines(self) -> None:
        """Subscribe (once, on the private node the scan thread spins) to the extractor's left lines."""
        if self._left_line_sub is None:
            def keep(msg: LaserLine) -> None:
                self._left_lines[_key(msg.header.stamp)] = msg
                while len(self._left_lines) > 16:
                    self._left_lines.popitem(last=False)

            self._left_line_sub = self._io.create_subscription(
                LaserLine, "stereo/left/laser_line", keep,
                QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE))

    def _adaptive_capture(self, goal_handle: Any, run: ScanRun, pending: dict[str, Any] | None, t_moved: float,
                          settle_left_s: float) -> tuple[Any, SettleTrace, float, float]:
        """The snap's capture by the adaptive settle (lsu_scan.settle); also awaits the previous snap's ack.

        Returns (capture response, trace, end of the settle's probe, when the ack was in) for the SnapRecord.
        """
        fixed_end = t_moved + max(0.0, settle_left_s)
        marks = {"probed": t_moved, "acked": t_moved}

        def line_of(response: Any) -> Any:
            """The laser_extractor's left line of this capture (per-row profile; all NaN if it does not come)."""
            key = _key(response.stamp)
            self._wait(lambda: key in self._left_lines, float(self.capture_timeout_s))
            msg = self._left_lines.pop(key, None)
            if msg is None:
                return np.full(1, np.nan)
            return profile_from_line(np.frombuffer(msg.u, np.float32), np.frombuffer(msg.v, np.float32),
                                     int(msg.image_height))

        def probe() -> Any:
            self._check_cancel(goal_handle)
            line = line_of(self._capture())
            marks["probed"] = marks["acked"] = time.monotonic()
            return line

        def before_capture() -> None:
            nonlocal pending
            self._check_cancel(goal_handle)
            if pending is not None:
                run.points_total += self._await_ack(pending)
                pending = None
                marks["acked"] = time.monotonic()

        def capture() -> tuple[Any, Any]:
            response = self._capture()
            return response, line_of(response)

        response, trace = settle_from_images(probe, capture, lambda: time.monotonic() >= fixed_end,
                                             tolerance_px=float(self.settle_tolerance_px),
                                             before_capture=before_capture, profile=lambda line: line)
        if trace.captures > 1:
            self.get_logger().debug(f"adaptive settle: {trace.captures - 1} capture(s) moved before the snap")
        return response, trace, marks["probed"], marks["acked"]

    def _sweep_loop(self, goal_handle: Any, run: ScanRun) -> None:
        """Move to the sweep's start if needed, then the sweep: one move at the sweep rate while the cameras
        stream; the texture pair after it (`_end_sweep`).

        ``run.sweep`` is oriented (`sweep_plan.oriented`): its start is the end of the range the carriage
        stands at or nearer to. Raises ScanAborted / ScanCanceled (the carriage and the stream stopped
        first); ``run.captured`` holds every frame the stream published, acknowledged or not.
        """
        sweep, state = run.sweep, run.start_state
        assert sweep is not None
        self._set_laser(False)
        here = int(state.position_steps)
        if here != sweep.start:
            self._feedback(goal_handle, "moving", 0, sweep.frames_expected, sweep.start, 0, [])
            moved = self._call(self.move, MoveTo.Request(position_steps=sweep.start, timeout_s=float(self.move_timeout_s)),
                               float(self.move_timeout_s) or 60.0, f"move to {sweep.start}",
                               due_s=abs(sweep.start - here) / max(1.0, float(state.step_rate_steps_per_s)))
            if not moved.success:
                raise ScanAborted(f"move to {sweep.start} failed: {moved.message}")
            # the stop's vibration decays before the sweep's first frames, as before a stop-snap capture
            self._sleep(goal_handle, run.plan.settle_s - (self._since_stop_s(moved.stopped_stamp) or 0.0))
        self._mark(run, "at_start")
        if not self._wait(lambda: self.stream.service_is_ready(), 5.0):
            raise ScanAborted(f"service {self.stream.srv_name} is not available: the camera node cannot stream "
                              "(sweep scans need free-running capture; use --mode stopsnap)")
        self._set_laser(True)
        self._mark(run, "laser_on")
        with self._cond:
            self._exposures.clear()
        request = MoveTo.Request(position_steps=sweep.end, timeout_s=float(self.move_timeout_s),
                                 rate_steps_per_s=float(sweep.rate_steps_s))
        move = self.move.call_async(request)
        t0 = time.monotonic()
        # a driver that does not report the end of the motion must not keep the laser on
        self.guard.due("sweep", t0 + sweep.duration_s + 1.0, f"sweep to {sweep.end}: no answer from "
                                                            f"{self.move.srv_name}")
        first: int | None = None
        try:
            started = self._call(self.stream, StreamStereo.Request(frame_rate_hz=sweep.frame_rate_hz,
                                                                   frames=sweep.frames_expected),
                                 float(self.capture_timeout_s) + 0.3, "stream start")
            if not started.success:
                raise ScanAborted(f"stream start failed: {started.message}")
            first = _key(started.first_stamp)
            period_s = float(started.frame_period_s) or 1.0 / sweep.frame_rate_hz
            run.stream.update(frame_period_s=period_s, exposure_s=float(started.exposure_s))
            self._mark(run, "stream_started")
            self._event(ScanEvent.SWEEP_START, run.scan_id, run.folder, image_stamp=started.first_stamp,
                        expected_snaps=sweep.frames_expected, position_steps=sweep.start)
            self._await_sweep(goal_handle, run, move, first, period_s)
            moved = move.result()
            if not moved.success:
                raise ScanAborted(f"sweep to {sweep.end} failed: {moved.message}")
        except ScanAborted:
            if not move.done():  # the carriage must not run on to the end by itself
                self._stop_carriage(move)
            self._end_sweep(run, first, aborted=True)
            raise
        self._end_sweep(run, first, aborted=False)
        self._feedback(goal_handle, "finishing", len(run.captured), sweep.frames_expected, sweep.end,
                       run.points_total, [1.0 / sweep.frame_rate_hz])

    def _end_sweep(self, run: ScanRun, first: int | None, aborted: bool) -> None:
        """Stream stop and SWEEP_END, laser off, the texture pair (not after an abort), then the matcher's
        points of the frames published.

        On an abort the points are awaited only briefly (the frames so far stay in the cloud) and
        nothing here replaces the abort's reason.
        """
        self.guard.answered("sweep")
        self.guard.answered("stream")
        try:
            if first is not None:
                self._end_stream(run, first)
            if aborted:
                self._laser_off_safely()
            else:
                self._set_laser(False)
                self._mark(run, "laser_off")
                if run.plan.texture:
                    # the laser-off pair once the carriage has stopped: a continuous sweep has no laser-off
                    # frame, and here the capture overlaps the matcher's work on the last frames instead
                    # of delaying the sweep's start
                    response = self._capture(lit=False)
                    self._event(ScanEvent.TEXTURE, run.scan_id, run.folder, image_stamp=response.stamp)
                    self._mark(run, "texture")
            if first is not None and not self.shutting_down:
                self._await_sweep_points(run, min(1.0, float(self.ack_timeout_s)) if aborted else float(self.ack_timeout_s))
                self._mark(run, "points")
        except ScanAborted as exc:
            if not aborted:
                raise
            self.get_logger().error(f"sweep end: {exc}")

    @staticmethod
    def _mark(run: ScanRun, name: str) -> None:
        """A sweep's timeline in scan.json (``sweep.timeline_s``): seconds from the goal to each stage's end."""
        run.stream.setdefault("timeline_s", {})[name] = round(time.monotonic() - run.started, 4)

    def _published(self, first: int) -> list[int]:
        """Stamps of the stream's pairs received so far (from its first pair on), in order."""
        with self._cond:
            return sorted(k for k in self._exposures if k >= first)

    def _await_sweep(self, goal_handle: Any, run: ScanRun, move: Any, first: int, period_s: float) -> None:
        """Until the motion ended and the stream published its frames; cancel, stalls and time-outs raise."""
        sweep = run.sweep
        assert sweep is not None
        stall_s = float(self.capture_timeout_s) + 0.3
        seen, last_new = 0, time.monotonic()
        move_deadline = time.monotonic() + float(self.move_timeout_s or (sweep.duration_s * 2.0 + 10.0))
        next_feedback = 0.0
        while True:
            self._check_cancel(goal_handle)
            published = len(self._published(first))
            now = time.monotonic()
            if published > seen:
                seen, last_new = published, now
                # the camera keeps the laser's use alive frame by frame: a hung stream switches it off
                self.guard.due("stream", now + stall_s, "stream: no frame from the camera")
            if move.done():
                self.guard.answered("sweep")  # the carriage stopped; the stream's frames keep the laser's use alive
                if "motion_ended" not in run.stream.get("timeline_s", {}):
                    self._mark(run, "motion_ended")
                if published >= sweep.frames_expected:
                    self._mark(run, "frames_published")
                    return
            if now - last_new > stall_s + float(self.laser_pause_s):
                raise ScanAborted(f"stream: no frame from {self.stream.srv_name} for {now - last_new:.1f} s "
                                  f"({published} of {sweep.frames_expected} published): is the camera node running?")
            if not move.done() and now > move_deadline:
                raise ScanAborted(f"sweep to {sweep.end}: no answer from {self.move.srv_name}")
            if now >= next_feedback:
                points_so_far = sum(ack[0] for key, ack in list(self._acks.items()) if key >= first)
                self._feedback(goal_handle, "sweeping", published, sweep.frames_expected,
                               sweep.position_at(published * period_s), points_so_far, [period_s])
                next_feedback = now + 0.2
            self._guard_laser()
            # a frame's exposure or points wake this wait at once; the timeout bounds how late a cancel, a
            # stall or the laser guard is seen (goals of 0.5 s and more); each wake-up costs a wait-set
            # rebuild, CPU the camera and the extractor need during a sweep
            self._io_executor.spin_once(timeout_sec=0.05)

    def _stop_carriage(self, move: Any) -> None:
        """carriage/stop (a cancel or an abort during the sweep's motion); the move's own reply then ends it."""
        try:
            stopped = self._call(self.stop_carriage, Trigger.Request(), 2.0, "carriage stop", stop_early=False)
            if not stopped.success:
                self.get_logger().error(f"carriage stop failed: {stopped.message}")
        except ScanAborted as exc:
            self.get_logger().error(f"carriage stop: {exc}")
        self._await_future(move, self.move, time.monotonic() + 2.0, stop_early=False)
        if not move.done():
            self.move.remove_pending_request(move)

    def _end_stream(self, run: ScanRun, first: int) -> None:
        """Stop the stream (its totals), SWEEP_END, and count the frames published; on every way out."""
        sweep = run.sweep
        assert sweep is not None
        try:
            stopped = self._call(self.stream, StreamStereo.Request(frame_rate_hz=0.0),
                                 float(self.capture_timeout_s) + 0.3, "stream stop", stop_early=False)
        except ScanAborted as exc:
            self.get_logger().error(f"stream stop: {exc}")
            stopped = None
        # pairs on their way when the stream stopped (it said how many it published)
        if stopped is not None and stopped.success:
            self._wait(lambda: len(self._published(first)) >= int(stopped.frames_published), 1.0)
        keys = self._published(first)
        last = stamps.to_msg(keys[-1]) if keys else stamps.to_msg(first)
        if stopped is not None and stopped.success:
            last = stopped.first_stamp
            run.stream.update(camera_frames_published=int(stopped.frames_published),
                              camera_frames_dropped=int(stopped.frames_dropped))
        self._event(ScanEvent.SWEEP_END, run.scan_id, run.folder, image_stamp=last,
                    snaps_captured=len(keys), expected_snaps=sweep.frames_expected)
        self._mark(run, "stream_stopped")
        with self._cond:
            arrivals = [self._exposures[k] for k in keys]
        if keys:
            # how late the camera delivered: the last pair's arrival after its exposure ended (a
            # simulated camera renders slower than real time on a small machine)
            exposure_s, arrived, _mono = arrivals[-1]
            run.stream["camera_lag_s"] = round(arrived - stamps.ns_to_seconds(keys[-1]) - exposure_s, 4)
        period_s = float(run.stream.get("frame_period_s", 1.0 / sweep.frame_rate_hz))
        for key, (_exposure_s, _wall, arrived) in zip(keys, arrivals):
            slot = round((key - first) / stamps.seconds_to_ns(period_s))
            run.captured.append(SnapRecord(index=int(slot), position_steps=sweep.position_at(slot * period_s),
                                           stamp=stamps.to_text(key), skew_s=0.0, move_s=0.0, settle_s=0.0,
                                           stop_to_reply_s=None, ack_wait_s=0.0, capture_s=0.0))
            run.frame_arrivals[key] = arrived
        run.first_key, run.frame_keys = first, keys
        sheet = self._matcher_sheet
        run.stream["laser_sheet"] = ("each camera's line on the laser sheet" if sheet == "loaded" else
                                     f"stereo only: {sheet}" if sheet else "unknown (no /diagnostics from stereo_matcher)")
        run.frames = count_frames(first, stamps.seconds_to_ns(period_s), sweep.frames_expected, keys, [],
                                  int(run.stream.get("camera_frames_dropped", 0)))

    def _await_sweep_points(self, run: ScanRun, timeout_s: float) -> None:
        """The matcher's points of every published frame (or ``timeout_s``); frames without them are dropped."""
        keys = run.frame_keys
        # The matcher publishes a sweep's points in frame order: once the last frame's are in, a frame still
        # without points gets none before the scan's end releases what it holds back (FINISHED, after this
        # wait); so waiting longer than a short grace for stragglers only delays the scan.
        self._wait(lambda: all(k in self._acks for k in keys) or (bool(keys) and keys[-1] in self._acks), timeout_s)
        self._wait(lambda: all(k in self._acks for k in keys), min(timeout_s, SWEEP_POINTS_GRACE_S))
        processed = []
        for snap, key in zip(run.captured, keys):
            ack = self._acks.pop(key, None)
            if ack is None:
                continue
            processed.append(key)
            snap.points = int(ack[0])
            # the pair's arrival (its exposure message) to its points
            snap.ack_s = round(max(0.0, ack[1] - run.frame_arrivals.get(key, ack[1])), 4)
            run.points_total += snap.points
        if run.frames is not None and run.sweep is not None:
            period_ns = stamps.seconds_to_ns(float(run.stream.get("frame_period_s", 1.0 / run.sweep.frame_rate_hz)))
            run.frames = count_frames(run.first_key, period_ns, run.sweep.frames_expected, keys, processed,
                                      run.frames.camera_dropped)

    def _finish(self, goal_handle: Any, run: ScanRun, laser_error: str, cloud_serial_before: int,
                recorder: Any) -> Scan.Result:
        """FINISHED / ABORTED event, cloud.ply, the bag closed, scan.json; ends the goal."""
        abort_reason, record, folder, total = run.abort_reason, run.record, run.folder, len(run.plan.positions)
        if run.sweep is not None:
            total = run.sweep.frames_expected
        if abort_reason and self.shutting_down and "shutting down" not in abort_reason:
            # the other nodes got the same Ctrl-C: the driver's own stop may have ended the move first
            abort_reason = f"scan_coordinator is shutting down ({abort_reason})"
        if laser_error and not abort_reason:
            abort_reason = f"laser off failed at the end of the scan: {laser_error}"
        partial = bool(abort_reason)
        kind = ScanEvent.ABORTED if partial else ScanEvent.FINISHED
        self._event(kind, run.scan_id, folder, expected_snaps=total, snaps_captured=len(run.captured),
                    partial=partial, reason=abort_reason)
        record.timings_s["scan"] = time.monotonic() - run.started
        cloud_points = self._save_cloud(folder, cloud_serial_before, record) if run.captured else 0
        if recorder is not None:
            try:
                record.files.append(self._stop_bag(recorder))
            except Exception as exc:  # noqa: BLE001 - scan.json must still be written, saying what happened
                bag_error = f"the bag could not be finished: {exc.__class__.__name__}: {exc}"
                self.get_logger().error(bag_error)
                abort_reason = f"{abort_reason}; {bag_error}" if abort_reason else bag_error
                partial = True
        record.snaps = [snap.as_json() for snap in run.captured]
        if run.sweep is not None:
            record.sweep = {**run.sweep.record(run.frames), **run.stream}
        record.laser_pauses = [pause.as_json() for pause in self.guard.pauses]
        record.snaps_captured = len(run.captured)
        record.snaps_acknowledged = sum(1 for snap in run.captured if snap.acknowledged)
        record.points = cloud_points or run.points_total
        record.partial = partial
        record.status = (f"partial: {abort_reason}" if partial else
                         f"finished: {len(run.captured)} {'frames' if run.sweep else 'snaps'}, {record.points} points")
        record.timings_s["total"] = time.monotonic() - run.started
        record.files.append(str(record.write(folder)))
        result = Scan.Result(scan_id=run.scan_id, output_dir=str(folder), success=not partial, partial=partial,
                             snaps=len(run.captured), points=int(record.points),
                             seconds=float(record.timings_s["scan"]), files=[str(f) for f in record.files],
                             status=record.status)
        summary = f"scan {run.scan_id} {record.status} in {result.seconds:.1f} s; files in {folder}"
        if partial:  # rclpy refuses one call site logging at two severities
            self.get_logger().warning(summary)
        else:
            self.get_logger().info(summary)
        if run.canceled:
            goal_handle.canceled()
        elif partial:
            goal_handle.abort()
        else:
            goal_handle.succeed()
        return result

    def _await_ack(self, pending: dict[str, Any]) -> int:
        """Wait until stereo_matcher published the snap's points; returns their count.

        ``ack_timeout_s`` after the capture without them the scan aborts; the laser guard has switched
        the laser off long before (``laser_pause_s`` after the capture), and `_capture` switches it
        back on when the points came after all.
        """
        snap, key = pending["snap"], pending["key"]
        remaining = float(self.ack_timeout_s) - (time.monotonic() - pending["t_captured"])
        if not self._wait(lambda: key in self._acks, remaining):
            raise ScanAborted(f"snap {snap.index} (position {snap.position_steps}) was not acknowledged by "
                              f"stereo_matcher within {self.ack_timeout_s:g} s: is the extractor/matcher running?")
        self.guard.answered("ack")
        self._guarded_ack = None
        points, t_ack = self._acks.pop(key)
        snap.points = int(points)
        # from the arrival time, not from now: the wait may start long after the points came
        snap.ack_s = round(max(0.0, t_ack - pending["t_captured"]), 4)
        snap.snap_s = round(t_ack - pending["t_snap"], 4)
        return snap.points

    def _feedback(self, goal_handle: Any, stage: str, index: int, total: int, position: int, points: int,
                  snap_times: list[float]) -> None:
        fb = Scan.Feedback(stage=stage, snap_index=index, snaps_total=total, position_steps=int(position),
                           points_so_far=int(points))
        if snap_times:
            fb.eta_s = float(sum(snap_times) / len(snap_times) * (total - index))
        goal_handle.publish_feedback(fb)

    def _save_cloud(self, folder: Path, serial_before: int, record: ScanRecord) -> int:
        """Wait for the matcher's scan cloud and write cloud.ply; returns its point count (0 if none came)."""
        if self.shutting_down:  # the matcher is stopping too; scan.json and the bag must be on disk first
            self.get_logger().warning("shutting down: not waiting for stereo_matcher's scan/cloud; the per-snap "
                                      "data is in the bag if one was recorded")
            return 0
        try:
            arrived = self._wait(lambda: self._cloud_serial > serial_before, float(self.cloud_timeout_s), spin=False)
        except ScanAborted:  # shutdown while waiting
            arrived = False
        if not arrived:
            self.get_logger().warning(f"no scan/cloud from stereo_matcher within {self.cloud_timeout_s:g} s; "
                                      "the per-snap data is in the bag if one was recorded")
            return 0
        from lsu_bags.ply import write_cloud_ply
        from lsu_bags.pointcloud2 import decode, from_msg

        assert self._cloud is not None
        columns = decode(from_msg(self._cloud))
        record.files.append(str(write_cloud_ply(folder / "cloud.ply", columns, comment="lsu scan")))
        return len(columns["x"])

    def _start_bag(self, folder: Path) -> Any:
        """Record the scan's topics on a private node spun by its own single-threaded executor.

        Why not on this node: the recorder's subscriptions would be destroyed (on close) while the
        multi-threaded executor builds its wait set in another thread, which rclpy answers with
        InvalidHandle out of spin(): the coordinator died after the scan and the result was lost.
        Its own executor is stopped before the subscriptions go; a single-threaded executor also
        costs less than half as much per recorded message.
        """
        from rclpy.executors import SingleThreadedExecutor

        from lsu_bags.bag_cli import BagRecorder

        # Not /lsu/sim/truth: simulation only, and ~1 ms of executor time per message in this process
        # while the scan loop needs the CPU. The bag is for replaying the processing and for placing it
        # in the rig's frames (/tf_static: rig, cameras, laser origin; /tf: the laser per driver state);
        # `lsu bag record --all` still takes everything.
        topics = ["/lsu/scan/events", "/lsu/stereo/left/image_raw", "/lsu/stereo/right/image_raw",
                  "/lsu/stereo/left/camera_info", "/lsu/stereo/right/camera_info", "/lsu/stereo/extrinsics",
                  "/lsu/stereo/left/laser_line", "/lsu/stereo/right/laser_line", "/lsu/points", "/lsu/scan/cloud",
                  "/lsu/driver/state", "/lsu/stereo/exposure", "/lsu/driver/carriage", "/tf", "/tf_static"]
        # no global arguments: the process's `-r __node:=scan_coordinator` would give it our name
        node = rclpy.create_node("_scan_coordinator_bag", namespace=self.get_namespace(), context=self.context,
                                 use_global_arguments=False, start_parameter_services=False)
        executor = SingleThreadedExecutor(context=self.context)
        executor.add_node(node)
        stop = threading.Event()

        def spin() -> None:
            while not stop.is_set() and self.context.ok():
                executor.spin_once(timeout_sec=0.1)

        try:
            # uncompressed (rosbag2's default): the sensor noise leaves camera images ~1.8x compressible
            # with zstd, and decompressing them costs a replay ~6x the CPU of reading them plain
            recorder = BagRecorder(node, topics, folder / "bag", "mcap", compress=False,
                                   log=lambda text: self.get_logger().info(text))
        except BaseException:
            executor.shutdown()
            node.destroy_node()
            raise
        thread = threading.Thread(target=spin, name="lsu-scan-bag", daemon=True)
        thread.start()
        return recorder, node, executor, stop, thread

    @staticmethod
    def _stop_bag(bag: Any) -> str:
        recorder, node, executor, stop, thread = bag
        stop.set()
        thread.join(timeout=5.0)  # its executor no longer waits on the subscriptions closing below
        try:
            recorder.close()
        finally:
            executor.shutdown()
            node.destroy_node()
        return str(recorder.path)

    def destroy_node(self) -> None:
        if self._busy.locked():
            # the scan thread owns the private node: let it end the scan (laser off in its finally)
            self._stopping = True
            if self._busy.acquire(timeout=3.0):
                self._busy.release()
            else:
                self.get_logger().error("the scan did not end within 3 s of shutdown; the firmware watchdog "
                                        "switches the laser off")
        self._io_executor.shutdown(timeout_sec=1.0)
        self._io.destroy_node()
        super().destroy_node()


main = main_of(ScanCoordinatorNode, multi_threaded=True)

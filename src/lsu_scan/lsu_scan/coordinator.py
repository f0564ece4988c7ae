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
The matcher measures the subject's motion over the sweep (``scan/motion``, docs/MOTION.md), which goes
into scan.json; a sweep it flags (moved beyond correction) is scanned again within the goal, up to
``motion_rescans`` times, with the feedback stage and the result's status saying "hold still, scanning
again".

Safety: the laser is switched off in a `finally` on every way out (success, cancel, driver
fault, capture timeout, lost snap, node shutdown); what was captured is kept and the scan is
marked partial with the reason. While the scan runs, the laser is only on while the scan makes
progress: a move, a capture or a snap's acknowledgement that is ``laser_pause_s`` late switches it
off at once, without waiting for the late answer (the laser guard); it comes back on before the
next capture, and a capture exposed after the laser went off is taken again.

The node is the shell: its ``__init__`` sets up the topics, clients and the private node the scan
thread spins, and it accepts goals; the jobs live in their own modules: `scan_calls` (service calls,
laser guard, waits), `stopsnap_run`, `sweep_run`, `scan_run` (plan, finish, files), `scan_bag` (the
bag) and `scan_params` (parameters).
"""

from __future__ import annotations

import json
import threading
import time
from collections import OrderedDict
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import String
from std_srvs.srv import SetBool, Trigger

from lsu_cameras.polled import PolledGroup, take_latest
from lsu_common import qos
from lsu_common.node import LsuNode, main_of
from lsu_common.params import declare_parameters
from lsu_interfaces.action import Scan
from lsu_interfaces.msg import LaserLine, ScanEvent, ScannerState, StereoExposure
from lsu_interfaces.srv import CaptureStereo, MoveTo, StreamStereo
from lsu_reconstruct.motion import HOLD_STILL

from .laser_guard import LaserGuard
from .scan_bag import ScanBag, recover_killed_scans, storage_problem
from .scan_calls import MatcherSilent, ScanAborted, ScanCanceled, _key
from .scan_params import PARAMETERS, ScanParameters
from .scan_run import ScanRun, ScanRunSteps
from .stopsnap_run import StopSnapRun
from .sweep_run import SweepRun

__all__ = ["PARAMETERS", "ScanAborted", "ScanCanceled", "ScanCoordinatorNode", "main"]

EVENTS_QOS = qos.EVENTS
LATCHED = qos.LATCHED


class ScanCoordinatorNode(ScanParameters, StopSnapRun, SweepRun, ScanRunSteps):
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
        self._storage_check = None
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
        # stereo_matcher's motion record of each sweep (published before its cloud), by scan id
        self._motion: OrderedDict[str, dict] = OrderedDict()
        self.create_subscription(String, "scan/motion", self._on_motion, LATCHED, callback_group=group)
        self._busy = threading.Lock()      # held by the scan thread while a scan runs
        self._goal_lock = threading.Lock()  # makes "is a scan running or accepted?" and "accept" one step
        self._goal_active = False
        self._counter = 0
        self._server = ActionServer(self, Scan, "scan", execute_callback=self._execute,
                                    goal_callback=self._on_goal, cancel_callback=lambda _h: CancelResponse.ACCEPT,
                                    callback_group=group)
        # scans a killed coordinator left (its bag never closed): made whole beside the start-up, not delaying it
        threading.Thread(target=recover_killed_scans, args=(self.output_dir, self.get_logger()),
                         name="lsu-scan-recover", daemon=True).start()

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

    def _on_motion(self, msg: String) -> None:
        try:
            record = json.loads(msg.data)
        except ValueError:
            self.get_logger().error(f"scan/motion: not a JSON record: {msg.data[:80]!r}")
            return
        with self._cond:
            self._motion[str(record.get("scan_id", ""))] = record
            while len(self._motion) > 8:
                self._motion.popitem(last=False)
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

    # ------------------------------------------------------------------------------ the scan
    def _execute(self, goal_handle: Any) -> Scan.Result:
        try:
            with self._busy:
                return self._run_goal(goal_handle)
        finally:
            with self._goal_lock:
                self._goal_active = False

    def _run_goal(self, goal_handle: Any) -> Scan.Result:
        """The goal's scan, again while its subject moved beyond correction (``motion_rescans``); ends the goal."""
        result, run = self._scan(goal_handle)
        if run is None:
            return result  # refused (the goal is ended)
        rescans, moved = int(self.motion_rescans), []
        while run.record.motion.get("flagged") and rescans > 0 and not run.canceled \
                and not run.record.partial and not self.shutting_down:
            rescans -= 1
            message = str(run.record.motion.get("message", HOLD_STILL))
            moved.append(f"{message}: scan {run.scan_id} moved beyond correction "
                         f"({_motion_reasons(run.record.motion)})")
            self.get_logger().warning(moved[-1])
            self._feedback(goal_handle, message, 0, run.record.snaps_expected,
                           int(run.sweep.end if run.sweep else 0), 0, [])
            first = result
            result, again = self._scan(goal_handle, rescan_of=run.scan_id)
            result.files = [*first.files, *result.files]
            if again is None:
                return result
            run = again
        if moved:
            result.status = "; ".join([*moved, result.status])
        self._end_goal(goal_handle, run, result)
        return result

    def _scan(self, goal_handle: Any, rescan_of: str = "") -> tuple[Scan.Result, ScanRun | None]:
        """plan -> snap loop -> finish; the laser is off and the files are on disk on every way out. The goal is
        left running (`_end_goal`) unless the scan was refused (run None)."""
        run = self._plan(goal_handle)
        if isinstance(run, Scan.Result):
            return run, None  # refused before anything moved
        run.record.rescan_of = rescan_of
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
        self._storage_check = lambda: storage_problem(recorder, run.folder)
        try:
            (self._snap_loop if run.sweep is None else self._sweep_loop)(goal_handle, run)
        except ScanCanceled as exc:
            run.abort_reason, run.canceled = str(exc), True
        except ScanAborted as exc:
            run.abort_reason, run.matcher_silent = str(exc), isinstance(exc, MatcherSilent)
        except Exception as exc:  # a bug must still leave the laser off and the data on disk
            if self.shutting_down:  # rclpy's own exceptions out of a context the signal handler shut down
                run.abort_reason = f"scan_coordinator is shutting down ({exc.__class__.__name__})"
            else:
                run.abort_reason = f"internal error: {exc.__class__.__name__}: {exc}"
                self.get_logger().error(run.abort_reason)
        finally:
            self._storage_check = None
            self.guard.clear()
            self._guarded_ack = None
            self._off_future = None  # superseded by this off (a left-over one would disarm the next scan's guard)
            laser_error = self._laser_off_safely()
        return self._finish(goal_handle, run, laser_error, cloud_serial_before, recorder), run

    def _start_bag_or_warn(self, run: ScanRun) -> Any:
        try:
            return ScanBag.start(self, run.folder)
        except Exception as exc:  # no bag is no reason to lose the scan: say so and go on
            self.get_logger().error(f"bag recording could not start ({exc.__class__.__name__}: {exc}); "
                                    "scanning without a bag")
            return None

    def begin_shutdown(self) -> None:
        self._stopping = True  # the scan thread ends the scan at its next check (laser off, data on disk)

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


def _motion_reasons(motion: dict) -> str:
    """The unreliable frames of a flagged motion record and why, in one line."""
    reasons = motion.get("reasons") or {}
    where = motion.get("unreliable_positions_steps")
    text = "; ".join(f"frame {frame}: {why}" for frame, why in list(reasons.items())[:3])
    if len(reasons) > 3:
        text += f"; {len(reasons) - 3} more frames"
    return text + (f" (carriage {where[0]:.0f}..{where[1]:.0f} steps)" if where else "")


# deferred signals: the scan thread spins the private node's executor; a context shut down by rclpy's signal
# thread under that wait crashed the process (SIGSEGV) on Ctrl-C mid-scan, before scan.json was written
main = main_of(ScanCoordinatorNode, multi_threaded=True, defer_signals=True)

"""`LsuScanner`: script the scanner like prose (after nav2_simple_commander), and `lsu scan`.

    scanner = LsuScanner()
    scanner.home()
    result = scanner.scan(start=0, end=470, step=2)
    if result.result == TaskResult.SUCCEEDED:
        print(result.points, result.output_dir)

or non-blocking: ``scanner.start_scan(...)``, ``while not scanner.is_task_complete():
fb = scanner.get_feedback()``, ``scanner.cancel_task()``, ``scanner.get_result()``. Closing is
optional: `close()` (or ``with LsuScanner() as scanner:``) leaves the graph at once, otherwise it
happens when the interpreter exits.
"""

from __future__ import annotations

import argparse
import atexit
import enum
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from . import rosenv

# feedback stages that are notices to the user rather than progress (scan_coordinator's motion rescan)
NOTICE_PREFIXES = ("hold still",)


class ScannerError(RuntimeError):
    """The scanner graph is not there or did not answer; one line for the user."""


class TaskResult(enum.Enum):
    """How a scan ended (as nav2_simple_commander's TaskResult)."""

    UNKNOWN = 0
    SUCCEEDED = 1    # every snap captured and matched
    CANCELED = 2     # canceled; what was captured is kept (``partial``)
    FAILED = 3       # aborted or incomplete; ``status`` says why, captured data is kept (``partial``)


@dataclass(frozen=True)
class ScanResult:
    """The end of a scan: `result` plus the fields of ``lsu_interfaces/action/Scan`` Result."""

    result: TaskResult
    success: bool
    partial: bool
    scan_id: str
    snaps: int
    points: int
    seconds: float
    output_dir: str
    files: list[str] = field(default_factory=list)
    status: str = ""

    @classmethod
    def from_action(cls, goal_status: int, result: Any) -> ScanResult:
        """From the action's goal status (action_msgs/GoalStatus) and its ``Scan.Result``."""
        from action_msgs.msg import GoalStatus

        if goal_status == GoalStatus.STATUS_SUCCEEDED:
            outcome = TaskResult.SUCCEEDED if result.success else TaskResult.FAILED
        elif goal_status == GoalStatus.STATUS_CANCELED:
            outcome = TaskResult.CANCELED
        elif goal_status == GoalStatus.STATUS_ABORTED:
            outcome = TaskResult.FAILED
        else:
            outcome = TaskResult.UNKNOWN
        return cls(outcome, bool(result.success), bool(result.partial), str(result.scan_id), int(result.snaps),
                   int(result.points), float(result.seconds), str(result.output_dir), list(result.files),
                   str(result.status))


class LsuScanner:
    """A client of the LSU graph in its own rclpy context (safe to use beside other nodes)."""

    def __init__(self, namespace: str = "/lsu", wait_s: float = 15.0) -> None:
        rosenv.apply_defaults()
        from rclpy.action import ActionClient
        from std_srvs.srv import SetBool, Trigger

        from lsu_common.node import GraphClient
        from lsu_interfaces.action import Scan
        from lsu_interfaces.msg import ScannerState
        from lsu_interfaces.srv import MoveTo

        self._Scan = Scan
        self._graph = GraphClient(f"lsu_scanner_{id(self) & 0xFFFF:x}", namespace)
        self.context, self.node, self.executor = self._graph.context, self._graph.node, self._graph.executor
        self.wait_s = wait_s
        self._home = self.node.create_client(Trigger, "carriage/home")
        self._laser = self.node.create_client(SetBool, "laser/set")
        self._move = self.node.create_client(MoveTo, "carriage/move_to")
        self._action = ActionClient(self.node, Scan, "scan")
        self._latest_state: Any | None = None
        self.node.create_subscription(ScannerState, "driver/state", self._on_state, 10)
        self._goal_handle: Any | None = None
        self._result_future: Any | None = None
        self._feedback: Any | None = None
        # feedback stages that are notices to the user, not progress ("hold still, scanning again"), in order
        self.notices: list[str] = []
        self._closed = False
        # A script that never calls close() must still end cleanly: at interpreter exit the spin
        # thread would be inside rclpy's C++ wait set while the context is destroyed (abort, exit 134).
        atexit.register(self.close)

    def _on_state(self, msg: Any) -> None:
        self._latest_state = msg

    def close(self) -> None:
        """Leave the graph (idempotent; runs by itself at interpreter exit)."""
        if self._closed:
            return
        self._closed = True
        atexit.unregister(self.close)
        self._graph.close()

    def __enter__(self) -> LsuScanner:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------------------ plain calls
    def _wait_future(self, future: Any, timeout_s: float, what: str) -> Any:
        end = time.monotonic() + timeout_s
        while not future.done():
            if time.monotonic() > end:
                raise ScannerError(f"{what}: no answer within {timeout_s:g} s")
            time.sleep(0.005)
        return future.result()

    def _in_spin_thread(self, call: Callable[[], Any], timeout_s: float, what: str) -> Any:
        """Run ``call`` in the spin thread and return what it returned.

        Why: rclpy's ActionClient registers a request's sequence number only after sending it, without
        a lock; called from another thread, a fast answer taken by the spin thread in between is dropped
        ("Ignoring unexpected goal response") and the caller waits forever. Services lock; actions do not.
        """
        return self._wait_future(self.executor.create_task(call), timeout_s, what)

    def _call(self, client: Any, request: Any, timeout_s: float, what: str) -> Any:
        if not client.wait_for_service(timeout_sec=self.wait_s):
            raise ScannerError(f"{what}: service {client.srv_name} not available; is the LSU graph running "
                               f"(lsu launch sim) in ROS_DOMAIN_ID={__import__('os').environ.get('ROS_DOMAIN_ID')}?")
        return self._wait_future(client.call_async(request), timeout_s, what)

    def state(self, timeout_s: float = 5.0) -> Any:
        """The latest ``ScannerState`` from the driver (waits for the first one)."""
        end = time.monotonic() + timeout_s
        while self._latest_state is None and time.monotonic() < end:
            time.sleep(0.01)
        if self._latest_state is None:
            raise ScannerError("no /lsu/driver/state received: is gp32_driver running?")
        return self._latest_state

    def home(self, timeout_s: float = 60.0) -> str:
        """Home the carriage; returns the driver's message. Raises ScannerError on failure."""
        from std_srvs.srv import Trigger

        response = self._call(self._home, Trigger.Request(), timeout_s, "home")
        if not response.success:
            raise ScannerError(response.message)
        return response.message

    def laser(self, on: bool) -> None:
        """Switch the laser."""
        from std_srvs.srv import SetBool

        response = self._call(self._laser, SetBool.Request(data=on), 5.0, "laser")
        if not response.success:
            raise ScannerError(response.message)

    def move_to(self, position_steps: int, timeout_s: float = 30.0) -> int:
        """Move the carriage; returns the reached position."""
        from lsu_interfaces.srv import MoveTo

        response = self._call(self._move, MoveTo.Request(position_steps=position_steps), timeout_s, "move_to")
        if not response.success:
            raise ScannerError(response.message)
        return int(response.position_steps)

    # ------------------------------------------------------------------------------ scans
    def start_scan(self, start: int = 0, end: int = 470, step: int = 2, settle_s: float = 0.1, texture: bool = True,
                   record_bag: bool = False, output_dir: str = "", label: str = "", mode: str = "stopsnap",
                   sweep_rate_steps_s: float = 60.0, frame_rate_hz: float = 30.0) -> None:
        """Send a scan goal and return at once (see `is_task_complete`).

        ``mode``: "stopsnap" (``step``, ``settle_s``) or "sweep" (``sweep_rate_steps_s`` <= 180, frames at
        ``frame_rate_hz``; over ``start``..``end`` from the end the carriage stands at or is nearer to, in
        either direction); the coordinator refuses a bad goal with the reason in the result's status.
        """
        if not self._action.wait_for_server(timeout_sec=self.wait_s):
            raise ScannerError("the /lsu/scan action server (scan_coordinator) is not available; is the graph "
                               "running (lsu launch sim)?")
        self._feedback = None  # feedback of an earlier scan must not pass for this one's
        self.notices = []
        goal = self._Scan.Goal(start_steps=start, end_steps=end, step_steps=step, settle_s=float(settle_s),
                               texture=texture, record_bag=record_bag, output_dir=output_dir, label=label,
                               mode=mode, sweep_rate_steps_s=float(sweep_rate_steps_s),
                               frame_rate_hz=float(frame_rate_hz))
        sent = self._in_spin_thread(lambda: self._action.send_goal_async(goal, feedback_callback=self._on_feedback),
                                    self.wait_s, "scan goal")
        handle = self._wait_future(sent, self.wait_s, "scan goal")
        if not handle.accepted:
            raise ScannerError("scan goal rejected: another scan is running")
        self._goal_handle = handle
        self._result_future = self._in_spin_thread(handle.get_result_async, self.wait_s, "scan result request")

    def _on_feedback(self, message: Any) -> None:
        self._feedback = message.feedback
        if message.feedback.stage.startswith(NOTICE_PREFIXES):
            self.notices.append(message.feedback.stage)

    def is_task_complete(self) -> bool:
        """True when the running scan has a result."""
        return self._result_future is None or self._result_future.done()

    def get_feedback(self) -> Any | None:
        """The latest ``Scan.Feedback`` (or None)."""
        return self._feedback

    def cancel_task(self, timeout_s: float = 10.0) -> None:
        """Cancel the running scan (the coordinator switches the laser off and keeps the data)."""
        if self._goal_handle is not None and not self.is_task_complete():
            sent = self._in_spin_thread(self._goal_handle.cancel_goal_async, timeout_s, "cancel")
            self._wait_future(sent, timeout_s, "cancel")

    def get_result(self, timeout_s: float = 3600.0) -> ScanResult:
        """Wait for the scan's end and return it as a `ScanResult`."""
        if self._result_future is None:
            raise ScannerError("no scan was started")
        response = self._wait_future(self._result_future, timeout_s, "scan result")
        return ScanResult.from_action(response.status, response.result)

    def scan(self, feedback: Callable[[Any], None] | None = None, **goal: Any) -> ScanResult:
        """Run a scan to the end (keyword arguments of `start_scan`); returns its `ScanResult`."""
        self.start_scan(**goal)
        while not self.is_task_complete():
            if feedback is not None and self._feedback is not None:
                feedback(self._feedback)
            time.sleep(0.05)
        return self.get_result()


def _progress(fb: Any, unit: str = "snap") -> None:
    total = max(1, fb.snaps_total)
    done = min(fb.snap_index, total)
    bar = "#" * int(30 * done / total)
    sys.stderr.write(f"\r[{bar:<30}] {unit} {done}/{total} pos {fb.position_steps:4d} points {fb.points_so_far:8,d} "
                     f"ETA {fb.eta_s:5.1f} s ({fb.stage})   ")
    sys.stderr.flush()


def cmd_scan(args: argparse.Namespace) -> int:
    scanner = LsuScanner(wait_s=args.wait)
    try:
        if args.home or not scanner.state().homed:
            print(f"homing: {scanner.home()}")
        scanner.start_scan(start=args.start, end=args.end, step=args.step, settle_s=args.settle,
                           texture=not args.no_texture, record_bag=args.record, output_dir=args.out or "",
                           label=args.label, mode=args.mode, sweep_rate_steps_s=args.rate,
                           frame_rate_hz=args.fps)
        try:
            shown, told = None, 0
            while not scanner.is_task_complete():
                for notice in scanner.notices[told:]:
                    sys.stderr.write(f"\n{notice}\n")
                told = len(scanner.notices)
                fb = scanner.get_feedback()
                if fb is not None and fb is not shown:
                    _progress(fb, "snap" if args.mode == "stopsnap" else "frame")
                    shown = fb
                time.sleep(0.1)
        except KeyboardInterrupt:
            sys.stderr.write("\ncanceling the scan (the laser goes off, captured data is kept)...\n")
            scanner.cancel_task()
        result = scanner.get_result()
    finally:
        scanner.close()
    sys.stderr.write("\n")
    print(result.status)
    print(f"scan {result.scan_id}: {result.snaps} {'snaps' if args.mode == 'stopsnap' else 'frames'}, {result.points} points, {result.seconds:.1f} s")
    print(f"files in {result.output_dir}:")
    for path in result.files:
        print(f"  {path}")
    return 0 if result.success else 1


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `lsu scan`."""
    p = sub.add_parser("scan", help="run a scan on the running graph, stop-snap or sweep (Ctrl-C cancels, laser off)")
    p.add_argument("--mode", choices=("stopsnap", "sweep"), default="stopsnap",
                   help="stopsnap: move, settle, capture per position (default); sweep: one constant-rate move "
                        "with frames at --fps")
    p.add_argument("--start", type=int, default=0, help="first position [steps] (default 0); a sweep runs over --start..--end from "
                   "whichever end the carriage stands at or is nearer to")
    p.add_argument("--end", type=int, default=470, help="last position [steps] (default 470)")
    p.add_argument("--step", type=int, default=2, help="spacing [steps] (default 2)")
    p.add_argument("--settle", type=float, default=0.1, help="wait after each stop [s] (default 0.1)")
    p.add_argument("--rate", type=float, default=60.0,
                   help="sweep: carriage rate [steps/s], 20..180 (default 60: 236 frames over 0..470 at 30 fps)")
    p.add_argument("--fps", type=float, default=30.0, help="sweep: frame pairs per second (default 30)")
    p.add_argument("--no-texture", action="store_true", help="skip the laser-off colour pair")
    p.add_argument("--record", action="store_true", help="record the scan's topics into a bag in the scan folder")
    p.add_argument("--out", default="", help="parent folder for the scan folder (default: the node's output_dir)")
    p.add_argument("--label", default="", help="free text stored in scan.json")
    p.add_argument("--home", action="store_true", help="home first even if the carriage is homed")
    p.add_argument("--wait", type=float, default=15.0, help="seconds to wait for the graph (default 15)")
    p.set_defaults(func=cmd_scan)

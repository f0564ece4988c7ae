"""The scan thread's calls to the graph: service calls spun on the coordinator's private node, the laser
guard's switch-offs while they wait, captures, events, cancels, settles and feedback.

`ScanCalls` is the base of the scan's jobs (`stopsnap_run`, `sweep_run`, `scan_run`); `ScanCoordinatorNode`
(`coordinator`) sets up what they use: the private node ``_io`` and its executor, the service clients, the
laser guard and the acknowledgement books.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path
from typing import Any

from std_srvs.srv import SetBool

from lsu_common import stamps
from lsu_common.node import LsuNode
from lsu_interfaces.action import Scan
from lsu_interfaces.msg import LaserLine, ScanEvent
from lsu_interfaces.srv import CaptureStereo

from .laser_guard import LaserGuard

# how long the end-of-scan laser-off call may still wait once a shutdown began: `lsu launch`
# SIGKILLs 4 s after its SIGINT, and scan.json and the bag must be on disk before that
SHUTDOWN_CALL_S = 0.5


class ScanAborted(Exception):
    """The scan cannot go on; the message is the reason given to the user."""


class ScanCanceled(ScanAborted):
    """The user canceled the goal."""


class MatcherSilent(ScanAborted):
    """stereo_matcher stopped answering (a snap's points never came): no scan cloud will come either."""


_key = stamps.to_ns  # an image stamp as the key of its acknowledgement


class ScanCalls(LsuNode):
    """The scan thread's waits and calls (attributes set up by `ScanCoordinatorNode.__init__`)."""

    # the laser guard's books (scan thread only) and the off call it sent without waiting for the reply
    guard: LaserGuard
    _off_future: Any
    _guarded_ack: int | None  # the image stamp whose points the "ack" deadline waits for
    _capture_asked: float     # monotonic time the last capture was asked for
    _acks: dict[int, tuple]   # image stamp -> (points, monotonic arrival time)
    # adaptive settle: the laser_extractor's left lines by image stamp, subscribed at the first adaptive scan
    _left_lines: OrderedDict[int, LaserLine]
    _left_line_sub: Any
    _storage_check: Callable[[], str | None] | None  # during a scan: why its data can no longer be stored, or None

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
        if self._storage_check is not None and (problem := self._storage_check()):
            raise ScanAborted(problem)  # capturing on would only lose what is captured

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

    def _feedback(self, goal_handle: Any, stage: str, index: int, total: int, position: int, points: int,
                  snap_times: list[float]) -> None:
        fb = Scan.Feedback(stage=stage, snap_index=index, snaps_total=total, position_steps=int(position),
                           points_so_far=int(points))
        if snap_times:
            fb.eta_s = float(sum(snap_times) / len(snap_times) * (total - index))
        goal_handle.publish_feedback(fb)

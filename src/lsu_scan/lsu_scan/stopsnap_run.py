"""The stop-snap scan (thesis ch. 3.3): move, settle (fixed, or adaptive: lsu_scan.settle), the previous
snap's acknowledgement, capture and SNAP for each position; the texture pair first."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from rclpy.qos import QoSProfile, ReliabilityPolicy

from lsu_common import stamps
from lsu_interfaces.msg import LaserLine, ScanEvent
from lsu_interfaces.srv import MoveTo

from .laser_guard import ack_due_at
from .scan_calls import MatcherSilent, ScanAborted, ScanCalls, _key
from .scan_plan import SnapRecord
from .scan_run import ScanRun
from .settle import SettleTrace, profile_from_line, settle_from_images


class StopSnapRun(ScanCalls):
    """The stop-snap loop of `ScanCoordinatorNode`."""

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

    def _await_ack(self, pending: dict[str, Any]) -> int:
        """Wait until stereo_matcher published the snap's points; returns their count.

        ``ack_timeout_s`` after the capture without them the scan aborts; the laser guard has switched
        the laser off long before (``laser_pause_s`` after the capture), and `_capture` switches it
        back on when the points came after all.
        """
        snap, key = pending["snap"], pending["key"]
        remaining = float(self.ack_timeout_s) - (time.monotonic() - pending["t_captured"])
        if not self._wait(lambda: key in self._acks, remaining):
            raise MatcherSilent(f"snap {snap.index} (position {snap.position_steps}) was not acknowledged by "
                              f"stereo_matcher within {self.ack_timeout_s:g} s: is the extractor/matcher running?")
        self.guard.answered("ack")
        self._guarded_ack = None
        points, t_ack = self._acks.pop(key)
        snap.points = int(points)
        # from the arrival time, not from now: the wait may start long after the points came
        snap.ack_s = round(max(0.0, t_ack - pending["t_captured"]), 4)
        snap.snap_s = round(t_ack - pending["t_snap"], 4)
        return snap.points

"""The sweep scan: one move at the sweep rate while the cameras stream (``stereo/stream``), SWEEP_START and
SWEEP_END, the texture pair after it, and the matcher's points of every frame the stream published
(keyed on the pairs' stamps; frames dropped are counted from the stamps, `sweep_plan.count_frames`)."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from std_srvs.srv import Trigger

from lsu_common import stamps
from lsu_interfaces.msg import ScanEvent
from lsu_interfaces.srv import MoveTo, StreamStereo

from .scan_calls import ScanAborted, ScanCalls, _key
from .scan_plan import SnapRecord
from .scan_run import ScanRun
from .sweep_plan import count_frames

# after a sweep's last frame has its points, how long frames still without theirs are waited for [s]
SWEEP_POINTS_GRACE_S = 0.2


def wait_while_progressing(done: Callable[[], bool], progress: Callable[[], int],
                           wait: Callable[[Callable[[], bool], float], bool], idle_s: float) -> bool:
    """Wait (``wait(predicate, timeout_s)``) until ``done()``, for as long as ``progress()`` keeps growing: it
    gives up once ``idle_s`` passed without growth. True when done."""
    while not done():
        seen = progress()

        def moved(seen: int = seen) -> bool:
            return done() or progress() > seen

        if not wait(moved, idle_s):
            return done()
    return True


class SweepRun(ScanCalls):
    """The sweep of `ScanCoordinatorNode`."""

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
                self._await_sweep_points(run, min(1.0, float(self.ack_timeout_s)) if aborted else float(self.ack_timeout_s),
                                         follow=not aborted)
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

    def _await_sweep_points(self, run: ScanRun, timeout_s: float, follow: bool = True) -> None:
        """The matcher's points of every published frame; frames without them are dropped. ``follow``: waited for
        while they keep coming (``timeout_s`` without a new frame's ends it), else ``timeout_s`` at most."""
        keys = run.frame_keys
        # The matcher publishes a sweep's points in frame order: once the last frame's are in, a frame still
        # without points gets none before the scan's end releases what it holds back (FINISHED, after this
        # wait); so waiting longer than a short grace for stragglers only delays the scan. Before that, a busy
        # host's matcher may be seconds behind the stream's end and still placing frames: a fixed wait from the
        # stream's end dropped every frame of a sweep whose matcher was that far behind.
        def last_in() -> bool:
            return all(k in self._acks for k in keys) or (bool(keys) and keys[-1] in self._acks)

        if follow:
            wait_while_progressing(last_in, lambda: sum(k in self._acks for k in keys), self._wait, timeout_s)
        else:
            self._wait(last_in, timeout_s)
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

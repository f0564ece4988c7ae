"""One scan from its goal to its files: `ScanRun` (what it is and what it captured so far), the plan (or
the refusal, before anything moved), and the end: FINISHED / ABORTED, cloud.ply, the bag closed, scan.json."""

from __future__ import annotations

import datetime as _dt
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lsu_interfaces.action import Scan
from lsu_interfaces.msg import ScanEvent, ScannerState

from .scan_bag import ScanBag
from .scan_calls import ScanAborted, ScanCalls
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
from .sweep_plan import FrameCount, SweepPlan, oriented, plan_sweep, scan_mode

# how long a new scan waits for the driver's and the camera's services (a graph still starting) [s]
GRAPH_WAIT_S = 20.0


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
    matcher_silent: bool = False                      # aborted as stereo_matcher stopped answering: no cloud comes
    sweep: SweepPlan | None = None                 # a sweep scan's plan; None: stop-snap
    frames: FrameCount | None = None                # a sweep's frames counted from stamps, once its stream ended
    stream: dict[str, Any] = field(default_factory=dict)  # a sweep's stream figures for scan.json
    first_key: int = 0                                # a sweep's first pair (stamp ns)
    frame_keys: list[int] = field(default_factory=list)          # stamps of the pairs the stream published
    frame_arrivals: dict[int, float] = field(default_factory=dict)  # stamp -> monotonic time its exposure came


class ScanRunSteps(ScanCalls):
    """The start and the end of a scan of `ScanCoordinatorNode`."""

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

    def _finish(self, goal_handle: Any, run: ScanRun, laser_error: str, cloud_serial_before: int,
                recorder: ScanBag | None) -> Scan.Result:
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
        try:
            # a matcher that stopped acknowledging snaps sends no cloud: waiting cloud_timeout_s for it would only
            # hold the result back
            cloud_points = (self._save_cloud(folder, cloud_serial_before, record)
                            if run.captured and not run.matcher_silent else 0)
        except OSError as exc:  # a full disk, the folder gone: the points are still in the bag if one was recorded
            cloud_points = 0
            cloud_error = f"cloud.ply could not be written: {exc}"
            self.get_logger().error(cloud_error)
            abort_reason = f"{abort_reason}; {cloud_error}" if abort_reason else cloud_error
            partial = True
        if recorder is not None:
            try:
                record.files.append(recorder.stop())
            except Exception as exc:  # noqa: BLE001 - scan.json must still be written, saying what happened
                bag_error = f"the bag could not be finished: {exc.__class__.__name__}: {exc}"
                self.get_logger().error(bag_error)
                abort_reason = f"{abort_reason}; {bag_error}" if abort_reason else bag_error
                partial = True
        record.snaps = [snap.as_json() for snap in run.captured]
        if run.sweep is not None:
            record.sweep = {**run.sweep.record(run.frames), **run.stream}
        if run.sweep is not None and cloud_points:
            record.motion = self._motion_record(run.scan_id)
            if record.motion.get("flagged"):
                partial_note = f"; subject moved beyond correction: {record.motion.get('message', '')}"
            else:
                partial_note = ""
        else:
            partial_note = ""
        record.laser_pauses = [pause.as_json() for pause in self.guard.pauses]
        record.snaps_captured = len(run.captured)
        record.snaps_acknowledged = sum(1 for snap in run.captured if snap.acknowledged)
        record.points = cloud_points or run.points_total
        record.partial = partial
        record.status = (f"partial: {abort_reason}" if partial else
                         f"finished: {len(run.captured)} {'frames' if run.sweep else 'snaps'}, {record.points} points"
                         f"{partial_note}")
        record.timings_s["total"] = time.monotonic() - run.started
        try:
            record.files.append(str(record.write(folder)))
        except OSError as exc:  # told in the result, since scan.json cannot say it
            record.partial = partial = True
            record.status = f"partial: scan.json could not be written ({exc}); {record.status}"
            self.get_logger().error(f"scan {run.scan_id}: scan.json could not be written in {folder}: {exc}")
        result = Scan.Result(scan_id=run.scan_id, output_dir=str(folder), success=not partial, partial=partial,
                             snaps=len(run.captured), points=int(record.points),
                             seconds=float(record.timings_s["scan"]), files=[str(f) for f in record.files],
                             status=record.status)
        summary = f"scan {run.scan_id} {record.status} in {result.seconds:.1f} s; files in {folder}"
        if partial:  # rclpy refuses one call site logging at two severities
            self.get_logger().warning(summary)
        else:
            self.get_logger().info(summary)
        return result

    def _end_goal(self, goal_handle: Any, run: ScanRun, result: Scan.Result) -> None:
        """The goal ends as its (last) scan did: canceled, aborted (partial) or succeeded."""
        if run.canceled:
            goal_handle.canceled()
        elif result.partial:
            goal_handle.abort()
        else:
            goal_handle.succeed()

    def _motion_record(self, scan_id: str) -> dict:
        """stereo_matcher's motion record of the sweep ``scan_id`` (published before its cloud), or why there is none."""
        with self._cond:
            self._cond.wait_for(lambda: scan_id in self._motion or self.shutting_down, float(self.motion_timeout_s))
            record = self._motion.pop(scan_id, None)
        if record is None:
            return {"measured": False, "flagged": False, "corrected": False,
                    "why": f"no scan/motion record from stereo_matcher within {self.motion_timeout_s:g} s after the "
                           "cloud (its motion_measure parameter off, or a matcher without it)"}
        record.pop("scan_id", None)
        return record

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

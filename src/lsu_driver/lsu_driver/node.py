"""`gp32_driver` node: the GP32 on the ROS graph (services, state and carriage topics, diagnostics).

``driver/carriage`` carries where the carriage was and when: with a protocol v2 unit every ``!POS``
(at ``position_rate_hz`` during motion), ``!DONE`` and status reply, its device stamp mapped to ROS
time through the client's `DeviceClock` (fed by the status polls, which are round trips); with a v1
unit only the status replies, stamped at the middle of their round trip.

A thin adapter around `Gp32Client`. Safety: the laser is switched off and motion stopped on
shutdown; on ``!BOOT`` or a lost port the laser is considered off, the position unknown and
a running move fails with the reason; moves are refused until the carriage is homed.
"""

from __future__ import annotations

import threading
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TransformStamped
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from std_srvs.srv import SetBool, Trigger

from lsu_common import diagnostics, stamps
from lsu_common.node import LsuNode, main_of
from lsu_common.params import Param, declare_parameters
from lsu_interfaces.msg import CarriagePosition, ScannerState
from lsu_interfaces.srv import MoveTo, Step
from tf2_msgs.msg import TFMessage

from . import protocol as p
from .client import DeviceError, Gp32Client, Gp32Error, MotionResult, NotConnected

# Start-up-only parameters are read_only (the port is opened, the frames named once); the others
# take effect when set (`_apply_parameters`), or are refused with the reason.
PARAMETERS: dict[str, Param] = {
    "port": Param("/tmp/lsu-gp32", "serial device of the GP32 (emulator: its --link path)", read_only=True),
    "baud": Param(115200, "serial baud rate (9600 for the original RS232 link)", read_only=True),
    "command_timeout_s": Param(1.0, "reply timeout per command [s]", (0.01, 30.0)),
    "retries": Param(2, "re-sends of an idempotent command after a timeout", (0, 10)),
    "auto_home": Param(False, "home the carriage once after the first connect", read_only=True),
    "step_rate_steps_per_s": Param(200, "stepper rate [steps/s]; above ~180 the counter drifts",
                                   (p.RATE_MIN, p.RATE_MAX)),
    "watchdog_ms": Param(2000, "firmware laser watchdog [ms]; 0 disables it", (0, p.WATCHDOG_MAX_MS)),
    "laser_frame_id": Param("lsu_laser", "TF frame of the laser at the carriage position", read_only=True),
    "laser_origin_frame_id": Param("lsu_laser_origin", "TF parent of laser_frame_id: the laser at step 0",
                                   read_only=True),
    "track_step_m": Param(0.00042333, "metres per carriage step (1/60 inch)", (1e-6, 0.01), read_only=True),
    "state_rate_hz": Param(10.0, "status poll and state publish rate [Hz] (>= 5)", (5.0, 50.0)),
    "position_rate_hz": Param(20, "timed carriage positions (!POS) per second during motion, protocol v2 units; "
                                  "0 = only stops and status polls (at 9600 baud keep it <= 40)",
                              (0, p.POS_RATE_MAX_HZ)),
}


class Gp32DriverNode(LsuNode):
    """Services ``laser/set``, ``carriage/{move_to,step,home,stop}``; topic ``driver/state``."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("gp32_driver", **{"namespace": "/lsu", **kwargs})

        values = declare_parameters(self, PARAMETERS, check=self._check_parameters, apply=self._apply_parameters,
                                    apply_now=False)
        self.port = str(values["port"])
        self.auto_home = bool(values["auto_home"])
        self.rate = int(values["step_rate_steps_per_s"])
        self.watchdog_ms = int(values["watchdog_ms"])
        # the moving laser frame on /tf; the static frames (rig, cameras, laser origin) come from the camera node
        self.laser_frame = str(values["laser_frame_id"])
        self.laser_origin_frame = str(values["laser_origin_frame_id"])
        self.step_m = float(values["track_step_m"])
        self.position_rate_hz = int(values["position_rate_hz"])

        self.client = Gp32Client(self.port, int(values["baud"]), float(values["command_timeout_s"]),
                                 int(values["retries"]))
        self.client.position_rate_hz = int(self.position_rate_hz)
        self.client.add_listener(self._on_event)
        self.client.add_connection_listener(self._on_connection)
        self.client.add_error_listener(lambda err: self._count("malformed"))
        self._lock = threading.Lock()
        self.laser_on = False
        self.moving = False
        self.target: int | None = None
        self.fault = ""
        self.reconnects = 0
        self.counts = {"malformed": 0}
        self._last_state: tuple | None = None
        self._auto_homed = False

        services = ReentrantCallbackGroup()  # a move may block while stop and state keep going
        self.state_pub = self.create_publisher(ScannerState, "driver/state", 10)
        self.carriage_pub = self.create_publisher(CarriagePosition, "driver/carriage", 50)
        self.tf_pub = self.create_publisher(TFMessage, "/tf", 100)  # tf2's TransformBroadcaster QoS
        self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_service(SetBool, "laser/set", self._srv_laser, callback_group=services)
        self.create_service(MoveTo, "carriage/move_to", self._srv_move_to, callback_group=services)
        self.create_service(Step, "carriage/step", self._srv_step, callback_group=services)
        self.create_service(Trigger, "carriage/home", self._srv_home, callback_group=services)
        self.create_service(Trigger, "carriage/stop", self._srv_stop, callback_group=services)
        self._poll_group = MutuallyExclusiveCallbackGroup()
        self._poll_timer = self.create_timer(1.0 / float(values["state_rate_hz"]), self._poll,
                                             callback_group=self._poll_group)
        self.create_timer(1.0, self._diagnostics, callback_group=MutuallyExclusiveCallbackGroup())
        self._connect_timer = self.create_timer(1.0, self._try_connect,
                                                callback_group=MutuallyExclusiveCallbackGroup())
        self._try_connect()

    # ------------------------------------------------------------------------------ connection
    def _try_connect(self) -> None:
        if self.client.connected:
            return
        try:
            self.client.connect()
        except Gp32Error as exc:
            if self.fault != str(exc):
                self.get_logger().error(f"{exc}; retrying every 1 s")
            self.fault = str(exc)
            self._publish_state(force=True)
            return
        self._connect_timer.cancel()
        self._configure_device()
        if self.auto_home and not self._auto_homed:
            self._auto_homed = True
            self._home()

    def _configure_device(self) -> None:
        try:
            self.client.set_rate(int(self.rate))
            self.client.set_watchdog(int(self.watchdog_ms))
            if self.client.version >= 2:  # a reset unit is back at R0
                self.client.set_position_rate(int(self.position_rate_hz))
            self.client.laser(False)
            self.laser_on = False
        except Gp32Error as exc:
            self.get_logger().error(f"configuring the GP32 failed: {exc}")
        if not self.client.homed:
            self.fault = "carriage not homed: call carriage/home before moving"
        self.get_logger().info(f"connected to {p.DEVICE_NAME} on {self.port} "
                               f"(track {self.client.identity.track_steps if self.client.identity else '?'}, "
                               f"{self.rate} steps/s, watchdog {self.watchdog_ms} ms)")
        self._publish_state(force=True)

    def _on_connection(self, up: bool, reason: str) -> None:
        if up:
            if self._connect_timer.is_canceled():  # a reconnect (the first connect configures itself)
                self.reconnects += 1
                self.get_logger().warning(f"{reason}; the position is lost: call carriage/home")
                threading.Thread(target=self._configure_device, daemon=True).start()
            return
        self.laser_on = False
        self.moving = False
        self.fault = f"{reason}; laser considered off, position unknown"
        self.get_logger().error(self.fault)
        self._publish_state(force=True)

    def _on_event(self, event: p.Line) -> None:
        if isinstance(event, p.Boot):
            self.laser_on = False
            self.moving = False
            self.fault = "GP32 reset (!BOOT): position lost, laser off; call carriage/home"
            self.get_logger().error(self.fault)
            threading.Thread(target=self._configure_device, daemon=True).start()
        elif isinstance(event, p.WatchdogFired):
            self.laser_on = False
            self.fault = f"laser watchdog switched the laser off (no command for {self.watchdog_ms} ms)"
            self.get_logger().warning(self.fault)
        elif isinstance(event, p.HomeDone) and self.fault.startswith(("carriage not homed", "GP32 reset",
                                                                       "reconnected", "serial port")):
            self.fault = ""
        elif isinstance(event, p.Position):  # steady motion: no state change, only a timed position
            self._publish_carriage(event.position, event.device_ms, True, "pos")
            return
        elif isinstance(event, p.Done) and event.device_ms is not None:
            self._publish_carriage(event.position, event.device_ms, False, "done")
        self._publish_state(force=True)

    def _publish_carriage(self, position: int, device_ms: int | None, moving: bool, source: str,
                          bracket: tuple | None = None) -> None:
        """One timed position: a device stamp mapped to ROS time (v2), or the middle of a round trip."""
        if device_ms is not None:
            mapped = self.client.map_device_ms(device_ms)
            if mapped is None:
                return  # no round trip yet: the stamp cannot be placed
            stamp_s, uncertainty_s = mapped
        elif bracket is not None:
            stamp_s, uncertainty_s = 0.5 * (bracket[0] + bracket[1]), 0.5 * (bracket[1] - bracket[0])
        else:
            return
        if not self.client.homed or not self.context.ok():  # before homing the position means nothing
            return
        msg = CarriagePosition()
        msg.header.stamp = stamps.from_seconds(stamp_s)
        msg.header.frame_id = self.laser_origin_frame
        msg.position_steps = float(position)
        msg.moving = moving
        msg.uncertainty_s = float(uncertainty_s)
        msg.clock_drift_ppm = float(self.client.clock_drift_ppm() or 0.0) if device_ms is not None else 0.0
        msg.source = source
        self.carriage_pub.publish(msg)

    def _count(self, what: str) -> None:
        self.counts[what] = self.counts.get(what, 0) + 1

    # ------------------------------------------------------------------------------ state
    def _poll(self) -> None:
        if self.client.connected:
            try:
                # also feeds the laser watchdog and (v2) the device clock mapping
                status, sent_s, received_s = self.client.status_timed()
                self.laser_on = status.laser_on
                self.moving = status.moving
                self._publish_carriage(status.position, status.device_ms, status.moving, "status",
                                       (sent_s, received_s))
            except Gp32Error as exc:
                self.get_logger().warning(f"status poll failed: {exc}", throttle_duration_sec=5.0)
        self._publish_state(force=True)

    def _publish_state(self, force: bool = False) -> None:
        c = self.client
        status = c.last_status
        msg = ScannerState()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.connected = c.connected
        msg.homed = c.connected and c.homed
        msg.moving = self.moving
        msg.laser_on = self.laser_on and c.connected
        msg.at_start = bool(status and status.at_start and c.connected)
        msg.at_end = bool(status and status.at_end and c.connected)
        msg.position_steps = c.position if c.position is not None else 0
        msg.target_steps = self.target if self.moving and self.target is not None else msg.position_steps
        msg.track_steps = c.track_steps if c.homed else 0
        msg.step_rate_steps_per_s = float(self.rate)
        msg.watchdog_ms = int(self.watchdog_ms)
        msg.port = self.port
        msg.firmware = f"{p.DEVICE_NAME} v{c.identity.version}" if c.identity else ""
        msg.fault = self.fault
        key = (msg.connected, msg.homed, msg.moving, msg.laser_on, msg.at_start, msg.at_end, msg.position_steps,
               msg.fault)
        with self._lock:
            changed = key != self._last_state
            self._last_state = key
        if (force or changed) and self.context.ok():  # reader-thread events may race with shutdown
            self.state_pub.publish(msg)
            if msg.homed:  # before homing the position means nothing
                self.tf_pub.publish(TFMessage(transforms=[self._laser_tf(msg)]))

    def _laser_tf(self, state: ScannerState) -> TransformStamped:
        """The laser at the carriage position: -y of the laser origin (steps increase towards the right camera)."""
        tf = TransformStamped()
        tf.header.stamp = state.header.stamp
        tf.header.frame_id = self.laser_origin_frame
        tf.child_frame_id = self.laser_frame
        tf.transform.translation.y = -float(state.position_steps) * float(self.step_m)
        tf.transform.rotation.w = 1.0
        return tf

    def _diagnostics(self) -> None:
        c = self.client
        level = diagnostics.ERROR if not c.connected else diagnostics.WARN if self.fault else diagnostics.OK
        values: dict[str, object] = {"connected": c.connected, "homed": c.homed, "position_steps": c.position, "laser_on": self.laser_on,
                  "track_steps": c.track_steps, "malformed_lines": c.malformed_lines,
                  "stale_replies": c.stale_replies, "reconnects": self.reconnects, "protocol_version": c.version}
        uncertainty, drift = c.clock_uncertainty_s(), c.clock_drift_ppm()
        if c.version >= 2 and uncertainty is not None and drift is not None:
            values["clock_uncertainty_s"] = f"{uncertainty:.6f}"
            values["clock_drift_ppm"] = f"{drift:.1f}"
        self.diag_pub.publish(diagnostics.status_array(self, level, "lsu: gp32_driver", self.fault or "ok", values,
                                                       hardware_id=self.port))

    # ------------------------------------------------------------------------------ services
    def _srv_laser(self, request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        try:
            self.client.laser(request.data)
            self.laser_on = request.data
            response.success = True
            response.message = "laser on" if request.data else "laser off"
        except Gp32Error as exc:
            response.success = False
            response.message = str(exc)
        self._publish_state(force=True)
        return response

    def _refuse_motion(self) -> str:
        if not self.client.connected:
            return f"GP32 not connected ({self.fault or self.port}); check the port and power"
        if not self.client.homed:
            return ("carriage not homed: call carriage/home first (the position is unknown after power-on, "
                    "a reset or a reconnect)")
        return ""

    def _motion(self, target: int, run: Any) -> tuple:
        """Run a motion; returns (position, error text or '', wall-clock stop time or None)."""
        self.target = target
        self.moving = True
        self._publish_state(force=True)
        stopped_at = None
        try:
            result: MotionResult = run()
            position, error, stopped_at = result.position, "", result.stopped_at_s
            if not result.reached:
                why = (f"end sensor {result.end_sensor} tripped" if result.end_sensor is not None
                       else "stopped (carriage/stop or X)")
                error = f"stopped at {result.position} before reaching {target}: {why}"
                if result.end_sensor is not None:
                    error += "; the step counter has drifted: call carriage/home"
        except DeviceError as exc:
            position, error = (self.client.position or 0), str(exc)
            if exc.code == p.ERR_NOT_HOMED:  # we believed it homed: the unit restarted under us
                error += "; the unit lost its position (reset or power cycle), laser off: call carriage/home"
        except Gp32Error as exc:
            position, error = (self.client.position or 0), str(exc)
        finally:
            self.moving = False
            self._publish_state(force=True)
        return position, error, stopped_at

    def _srv_move_to(self, request: MoveTo.Request, response: MoveTo.Response) -> MoveTo.Response:
        response.message = self._refuse_motion()
        track = self.client.track_steps
        if not response.message and not 0 <= request.position_steps <= track:
            response.message = f"position {request.position_steps} outside the track 0..{track}"
        if response.message:
            response.success = False
            response.position_steps = self.client.position or 0
            return response
        timeout = request.timeout_s or None
        position, error, stopped_at = self._motion(request.position_steps,
                                                   lambda: self._move_at_rate(request.position_steps, timeout,
                                                                              request.rate_steps_per_s))
        response.success = not error
        response.position_steps = int(position)
        response.message = error
        if stopped_at is not None:
            response.stopped_stamp = stamps.from_seconds(stopped_at)
        return response

    def _move_at_rate(self, position: int, timeout: float | None, rate: float) -> MotionResult:
        """``move_to`` at ``rate`` steps/s for this move alone (0: the node's rate); the node's rate is set back."""
        rate = int(round(rate)) if rate > 0 else 0
        if not rate or rate == int(self.rate):
            return self.client.move_to(position, timeout)
        if not p.RATE_MIN <= rate <= p.RATE_MAX:
            raise Gp32Error(f"move refused: rate_steps_per_s {rate} is outside {p.RATE_MIN}..{p.RATE_MAX} steps/s")
        self.client.set_rate(rate)
        try:
            return self.client.move_to(position, timeout)
        finally:
            self.client.set_rate(int(self.rate))

    def _srv_step(self, request: Step.Request, response: Step.Response) -> Step.Response:
        response.message = self._refuse_motion()
        if not response.message and request.steps == 0:
            response.message = "a step of 0 steps does nothing; give a signed number of steps"
        if response.message:
            response.success = False
            response.position_steps = self.client.position or 0
            return response
        start = self.client.position or 0
        timeout = request.timeout_s or None
        position, error, _ = self._motion(start + request.steps, lambda: self.client.step(request.steps, timeout))
        response.success = not error
        response.position_steps = int(position)
        response.message = error
        return response

    def _home(self) -> str:
        """Home and return an error text ('' on success)."""
        self.moving = True
        self.target = 0
        self._publish_state(force=True)
        try:
            track = self.client.home()
        except Gp32Error as exc:
            return f"homing failed: {exc}"
        finally:
            self.moving = False
            self._publish_state(force=True)
        self.get_logger().info(f"homed: track {track} steps")
        if self.fault.startswith(("carriage not homed", "GP32 reset", "reconnected", "serial port")):
            self.fault = ""
        return ""

    def _srv_home(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if not self.client.connected:
            response.success, response.message = False, self._refuse_motion()
            return response
        error = self._home()
        response.success = not error
        response.message = error or f"homed: track {self.client.track_steps} steps"
        return response

    def _srv_stop(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        try:
            self.client.stop()
            response.success, response.message = True, "stopped"
        except Gp32Error as exc:
            response.success, response.message = False, str(exc)
        return response

    def _check_parameters(self, params: list[Any]) -> str | None:
        """Ranges and read-only are rclpy's; the unit's settings are sent here, so a refusal reaches the setter.

        The GP32 is the judge of its own settings (a v1 unit has no timed positions, a lost link
        takes none): the value is sent in the on-set callback and the set refused with the unit's
        answer; the node's copy changes in `_apply_parameters`, once the set is accepted.
        """
        for param in params:
            try:
                if param.name == "step_rate_steps_per_s" and self.client.connected:
                    self.client.set_rate(int(param.value))
                elif param.name == "watchdog_ms" and self.client.connected:
                    self.client.set_watchdog(int(param.value))
                elif param.name == "position_rate_hz":
                    self.client.set_position_rate(int(param.value))  # refused by a v1 unit (NotSupported)
            except NotConnected as exc:
                return str(exc)
            except Gp32Error as exc:
                return f"the GP32 refused {param.name}: {exc}"
        return None

    def _apply_parameters(self, params: list[Any]) -> None:
        """Accepted values take effect: the next configure uses them, the poll timer runs at the new rate."""
        for param in params:
            if param.name == "step_rate_steps_per_s":
                self.rate = int(param.value)
            elif param.name == "watchdog_ms":
                self.watchdog_ms = int(param.value)
            elif param.name == "position_rate_hz":
                self.position_rate_hz = int(param.value)
            elif param.name == "command_timeout_s":
                self.client.command_timeout_s = float(param.value)
            elif param.name == "retries":
                self.client.retries = int(param.value)
            elif param.name == "state_rate_hz":
                self.destroy_timer(self._poll_timer)
                self._poll_timer = self.create_timer(1.0 / float(param.value), self._poll,
                                                     callback_group=self._poll_group)

    # ------------------------------------------------------------------------------ shutdown
    def begin_shutdown(self) -> None:
        """The laser goes off the moment the process begins to stop, before its callbacks are waited for (at most
        `CALLBACK_GRACE_S`) and before the motion is stopped: only this driver can switch it when the unit's
        watchdog is off. `safe_shutdown` switches it again on the way out."""
        if self.client.connected:
            try:
                self.client.laser(False)
            except Gp32Error as exc:
                self.get_logger().warning(f"laser off at shutdown failed: {exc}; trying again after the motion stops")

    def safe_shutdown(self) -> None:
        """Motion stopped, laser off, port closed (runs on Ctrl-C and node destruction)."""
        try:
            self.client.close(safe=True)
        finally:
            self.laser_on = False

    def destroy_node(self) -> None:
        self.safe_shutdown()
        super().destroy_node()


main = main_of(Gp32DriverNode, multi_threaded=True)

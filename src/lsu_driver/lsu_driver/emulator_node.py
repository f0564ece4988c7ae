"""`gp32_emulator` node: a simulated GP32 unit plus its ground truth on ``sim/truth``.

``unit`` chooses what answers on the serial side: the Python emulator, or the unit's own
firmware (firmware/gp32) running in the HC08 simulator behind the host-side board. The serial
side is a pty (a stable symlink at ``link``); the ROS side only publishes what really happens
(true position, vibration, laser) for the simulated cameras, and accepts faults on its UNIX
control socket (`lsu gp32 fault`).
"""

from __future__ import annotations

import threading
import time
from typing import Any

from lsu_common import qos, stamps
from lsu_common.node import LsuNode, main_of
from lsu_common.params import Param, declare_parameters
from lsu_interfaces.msg import SimTruth

from .emulator import EmulatorConfig, Faults, Gp32Emulator, Truth
from .firmware import Gp32Firmware, build

_DEFAULTS = EmulatorConfig()
R = True  # read_only: the unit's power-on configuration and start-up faults (run-time faults: `lsu gp32 fault`)
PARAMETERS: dict[str, Param] = {
    "unit": Param("emulator", "emulator (Python) | firmware (firmware/gp32 in the HC08 simulator)", read_only=R),
    "link": Param("/tmp/lsu-gp32", "stable symlink to the emulated serial port (what the driver opens)", read_only=R),
    "control": Param("", "UNIX socket for run-time faults; empty = <link>.ctl", read_only=R),
    "track_steps": Param(_DEFAULTS.track_steps, "physical track between the sensors [steps]", read_only=R),
    "rate_steps_per_s": Param(_DEFAULTS.rate_steps_per_s, "power-on step rate [steps/s]", read_only=R),
    "watchdog_ms": Param(_DEFAULTS.watchdog_ms, "power-on laser watchdog [ms]", read_only=R),
    "start_position_steps": Param(_DEFAULTS.start_position_steps, "carriage position at power-on [steps]",
                                  read_only=R),
    "vibration_amplitude_steps": Param(_DEFAULTS.vibration_amplitude_steps,
                                       "residual vibration right after a stop at 200 steps/s [steps]", read_only=R),
    "vibration_tau_s": Param(_DEFAULTS.vibration_tau_s, "vibration decay constant [s]", read_only=R),
    "vibration_freq_hz": Param(_DEFAULTS.vibration_freq_hz, "vibration frequency [Hz]", read_only=R),
    "protocol_version": Param(_DEFAULTS.protocol_version,
                              "GP32 protocol the unit speaks: 2, or 1 (the v1 firmware, no device clock)", read_only=R),
    "clock_drift_ppm": Param(_DEFAULTS.clock_drift_ppm,
                             "how much faster the unit's millisecond clock runs than the host's [ppm]", read_only=R),
    "fault_garbage_probability": Param(0.0, "chance of garbage before each line", (0.0, 1.0), read_only=R),
    "fault_drop_probability": Param(0.0, "chance that each sent byte is lost", (0.0, 1.0), read_only=R),
    "fault_reply_delay_ms": Param(0, "delay of every sent line [ms]", read_only=R),
    "fault_stalled": Param(False, "the motor does not move (pulses are still counted)", read_only=R),
    "fault_seed": Param(0, "seed of the fault random generator", read_only=R),
    # a moving carriage is at a constant rate between samples (the camera extrapolates from the last one) and
    # every start, stop and rate change is a sample of its own: the periodic ones only bound an extrapolation
    "truth_rate_hz": Param(10.0, "sim/truth rate while the carriage moves [Hz]", (1.0, 1000.0)),
    "truth_rest_rate_hz": Param(5.0, "sim/truth rate at rest [Hz]", (0.1, 100.0)),
}


def truth_to_msg(truth: Truth) -> SimTruth:
    """The emulator's `Truth` as a ``lsu_interfaces/SimTruth`` message."""
    msg = SimTruth()
    msg.header.stamp = stamps.from_seconds(truth.stamp_s)
    msg.position_steps = float(truth.position_steps)
    msg.velocity_steps_per_s = float(truth.velocity_steps_per_s)
    msg.counter_steps = int(truth.counter_steps)
    msg.moving = truth.moving
    msg.laser_on = truth.laser_on
    msg.homed = truth.homed
    if truth.stopped_at_s > 0:
        msg.stopped_at = stamps.from_seconds(truth.stopped_at_s)
    msg.vibration_amplitude_steps = float(truth.vibration_amplitude_steps)
    msg.vibration_tau_s = float(truth.vibration_tau_s)
    msg.vibration_freq_hz = float(truth.vibration_freq_hz)
    msg.boot_count = int(truth.boot_count)
    return msg


class Gp32EmulatorNode(LsuNode):
    """Runs a `Gp32Emulator` or a `Gp32Firmware` and publishes its truth."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("gp32_emulator", **{"namespace": "/lsu", **kwargs})

        v = declare_parameters(self, PARAMETERS)
        unit, link, control = str(v["unit"]), str(v["link"]), str(v["control"])
        if unit not in ("emulator", "firmware"):
            raise ValueError(f"unit must be 'emulator' or 'firmware', not '{unit}'")
        config = EmulatorConfig(
            track_steps=v["track_steps"], rate_steps_per_s=v["rate_steps_per_s"], watchdog_ms=v["watchdog_ms"],
            start_position_steps=v["start_position_steps"], vibration_amplitude_steps=v["vibration_amplitude_steps"],
            vibration_tau_s=v["vibration_tau_s"], vibration_freq_hz=v["vibration_freq_hz"],
            protocol_version=v["protocol_version"], clock_drift_ppm=v["clock_drift_ppm"])
        faults = Faults(
            garbage_probability=v["fault_garbage_probability"], drop_probability=v["fault_drop_probability"],
            reply_delay_s=v["fault_reply_delay_ms"] / 1000.0, stalled=v["fault_stalled"], seed=v["fault_seed"])
        self.rest_period_s = 1.0 / float(v["truth_rest_rate_hz"])
        self.truth_pub = self.create_publisher(SimTruth, "sim/truth", qos.reliable(10))
        self._last_publish = 0.0
        # Every change (motion start/stop, laser, homing, reset) is published by the firmware thread the
        # moment it sees it, before the unit's reply to the command leaves (not by the executor later: a
        # camera captured on that reply rendered the state before it, e.g. a snap with the laser still off);
        # in between, the samples are periodic: a moving carriage is extrapolated from its velocity and a
        # resting one from its vibration model, so a fast stream would only cost CPU in every subscriber
        # (200 Hz took a fifth of a core per reader). One sender at a time keeps the samples in order.
        self._send_lock = threading.Lock()
        if unit == "firmware":
            if faults.garbage_probability or faults.drop_probability or faults.reply_delay_s:
                raise ValueError("the firmware unit simulates no serial-line faults (garbage, drop, late); "
                                 "set them to 0 or use unit:=emulator")
            if config.rate_steps_per_s != 200 or config.watchdog_ms != 2000:
                raise ValueError("the firmware's power-on rate (200 steps/s) and watchdog (2000 ms) are compiled "
                                 "in (firmware/gp32/lsu.c); leave rate_steps_per_s and watchdog_ms at their "
                                 "defaults with unit:=firmware, and send S/W commands instead")
            image = build().sim_image  # make: a no-op when the image is up to date
            self.emulator: Gp32Emulator | Gp32Firmware = Gp32Firmware(config, faults, link=link, control=control or f"{link}.ctl", image=image)
        else:
            self.emulator = Gp32Emulator(config, faults, link=link, control=control or f"{link}.ctl")
        self.emulator.on_change = self._on_change
        self.emulator.start()
        self.timer = self.create_timer(1.0 / float(v["truth_rate_hz"]), self._periodic)
        self.add_post_set_parameters_callback(self._apply_parameters)
        self.get_logger().info(f"GP32 {unit} on {self.emulator.device_path} (link {link}, control "
                               f"{self.emulator.control_path})")

    def _apply_parameters(self, params: list[Any]) -> None:
        for param in params:
            if param.name == "truth_rate_hz":
                self.destroy_timer(self.timer)
                self.timer = self.create_timer(1.0 / float(param.value), self._periodic)
            elif param.name == "truth_rest_rate_hz":
                self.rest_period_s = 1.0 / float(param.value)

    def _on_change(self) -> None:
        try:
            self._publish()  # on the firmware thread: rcl's publish is thread-safe
        except Exception:  # noqa: BLE001 - the node is being destroyed under the firmware thread
            pass

    def _periodic(self) -> None:
        with self._send_lock:
            self._send_events()
            truth = self.emulator.truth()
            if truth.moving or time.monotonic() - self._last_publish >= self.rest_period_s:
                self._send(truth)

    def _publish(self) -> None:
        with self._send_lock:
            self._send_events()
            self._send(self.emulator.truth())

    def _send_events(self) -> None:
        """The exact samples at each motion start, stop and velocity change, stamped when they happened: a
        camera rendering a frame across one extrapolates from the right side of it."""
        take = getattr(self.emulator, "take_truth_events", None)  # the firmware unit has none
        for truth in take() if take is not None else ():
            self._send(truth)

    def _send(self, truth: Truth) -> None:
        self._last_publish = time.monotonic()
        self.truth_pub.publish(truth_to_msg(truth))

    def destroy_node(self) -> None:
        self.emulator.close()
        super().destroy_node()


main = main_of(Gp32EmulatorNode)

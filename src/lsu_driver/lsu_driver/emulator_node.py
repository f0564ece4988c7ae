"""`gp32_emulator` node: a simulated GP32 unit plus its ground truth on ``sim/truth``.

``unit`` chooses what answers on the serial side: the Python emulator, or the unit's own
firmware (firmware/gp32) running in the HC08 simulator behind the host-side board. The serial
side is a pty (a stable symlink at ``link``); the ROS side only publishes what really happens
(true position, vibration, laser) for the simulated cameras, and accepts faults on its UNIX
control socket (`lsu gp32 fault`).
"""

from __future__ import annotations

import sys
import time
from typing import Any

import rclpy
from builtin_interfaces.msg import Time
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

from lsu_interfaces.msg import SimTruth

from .emulator import EmulatorConfig, Faults, Gp32Emulator, Truth
from .firmware import Gp32Firmware, build


def _stamp(seconds: float) -> Time:
    sec = int(seconds)
    return Time(sec=sec, nanosec=int(round((seconds - sec) * 1e9)) % 1_000_000_000)


def truth_to_msg(truth: Truth) -> SimTruth:
    """The emulator's `Truth` as a ``lsu_interfaces/SimTruth`` message."""
    msg = SimTruth()
    msg.header.stamp = _stamp(truth.stamp_s)
    msg.position_steps = float(truth.position_steps)
    msg.velocity_steps_per_s = float(truth.velocity_steps_per_s)
    msg.counter_steps = int(truth.counter_steps)
    msg.moving = truth.moving
    msg.laser_on = truth.laser_on
    msg.homed = truth.homed
    if truth.stopped_at_s > 0:
        msg.stopped_at = _stamp(truth.stopped_at_s)
    msg.vibration_amplitude_steps = float(truth.vibration_amplitude_steps)
    msg.vibration_tau_s = float(truth.vibration_tau_s)
    msg.vibration_freq_hz = float(truth.vibration_freq_hz)
    msg.boot_count = int(truth.boot_count)
    return msg


class Gp32EmulatorNode(Node):
    """Runs a `Gp32Emulator` or a `Gp32Firmware` and publishes its truth."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("gp32_emulator", **{"namespace": "/lsu", **kwargs})

        def declare(name: str, default: Any, description: str) -> Any:
            return self.declare_parameter(name, default, ParameterDescriptor(description=description)).value

        unit = self.declare_parameter("unit", "emulator", ParameterDescriptor(
            description="emulator (Python) | firmware (firmware/gp32 in the HC08 simulator)", read_only=True)).value
        if unit not in ("emulator", "firmware"):
            raise ValueError(f"unit must be 'emulator' or 'firmware', not '{unit}'")
        link = declare("link", "/tmp/lsu-gp32", "stable symlink to the emulated serial port (what the driver opens)")
        control = declare("control", "", "UNIX socket for run-time faults; empty = <link>.ctl")
        defaults = EmulatorConfig()
        config = EmulatorConfig(
            track_steps=declare("track_steps", defaults.track_steps, "physical track between the sensors [steps]"),
            rate_steps_per_s=declare("rate_steps_per_s", defaults.rate_steps_per_s, "power-on step rate [steps/s]"),
            watchdog_ms=declare("watchdog_ms", defaults.watchdog_ms, "power-on laser watchdog [ms]"),
            start_position_steps=declare("start_position_steps", defaults.start_position_steps,
                                         "carriage position at power-on [steps]"),
            vibration_amplitude_steps=declare("vibration_amplitude_steps", defaults.vibration_amplitude_steps,
                                              "residual vibration right after a stop at 200 steps/s [steps]"),
            vibration_tau_s=declare("vibration_tau_s", defaults.vibration_tau_s, "vibration decay constant [s]"),
            vibration_freq_hz=declare("vibration_freq_hz", defaults.vibration_freq_hz, "vibration frequency [Hz]"),
            protocol_version=declare("protocol_version", defaults.protocol_version,
                                     "GP32 protocol the unit speaks: 2, or 1 (the v1 firmware, no device clock)"),
            clock_drift_ppm=declare("clock_drift_ppm", defaults.clock_drift_ppm,
                                    "how much faster the unit's millisecond clock runs than the host's [ppm]"),
        )
        faults = Faults(
            garbage_probability=declare("fault_garbage_probability", 0.0, "chance of garbage before each line"),
            drop_probability=declare("fault_drop_probability", 0.0, "chance that each sent byte is lost"),
            reply_delay_s=declare("fault_reply_delay_ms", 0, "delay of every sent line [ms]") / 1000.0,
            stalled=declare("fault_stalled", False, "the motor does not move (pulses are still counted)"),
            seed=declare("fault_seed", 0, "seed of the fault random generator"),
        )
        rate_hz = declare("truth_rate_hz", 50.0, "sim/truth rate while the carriage moves [Hz]")
        self.rest_period_s = 1.0 / declare("truth_rest_rate_hz", 5.0, "sim/truth rate at rest [Hz]")
        self.truth_pub = self.create_publisher(SimTruth, "sim/truth",
                                               QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
        self._last_publish = 0.0
        # Every change (motion start/stop, laser, homing, reset) is published the moment the firmware
        # thread sees it; in between, the samples are periodic: a moving carriage is extrapolated from
        # its velocity and a resting one from its vibration model, so a fast stream would only cost CPU
        # in every subscriber (200 Hz took a fifth of a core per reader).
        self._changed = self.create_guard_condition(self._publish)
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
        self.timer = self.create_timer(1.0 / rate_hz, self._periodic)
        self.get_logger().info(f"GP32 {unit} on {self.emulator.device_path} (link {link}, control "
                               f"{self.emulator.control_path})")

    def _on_change(self) -> None:
        try:
            self._changed.trigger()  # thread-safe: the executor runs _publish
        except Exception:  # noqa: BLE001 - the node is being destroyed under the firmware thread
            pass

    def _periodic(self) -> None:
        truth = self.emulator.truth()
        if truth.moving or time.monotonic() - self._last_publish >= self.rest_period_s:
            self._send(truth)

    def _publish(self) -> None:
        self._send(self.emulator.truth())

    def _send(self, truth: Truth) -> None:
        self._last_publish = time.monotonic()
        self.truth_pub.publish(truth_to_msg(truth))

    def destroy_node(self) -> None:
        self.emulator.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Console script ``gp32_emulator``."""
    rclpy.init(args=sys.argv if args is None else args)
    node = Gp32EmulatorNode()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0

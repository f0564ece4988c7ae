"""Two small nodes that prove a graph works end to end (`lsu doctor --graph`, launch tests).

``selftest_talker`` keeps a pretend carriage position, publishes it as a
``lsu_interfaces/ScannerState`` on ``selftest/state`` at ``rate_hz`` and serves
``selftest/step`` (``lsu_interfaces/Step``) to move it. ``selftest_listener`` subscribes
to the state, republishes every message it got on ``selftest/echo`` with ``fault`` set to
"echo <n>", and every ``step_every`` messages calls the talker's step service, so one
lsu_interfaces message crosses the graph through a topic and a service in both directions.
"""

from __future__ import annotations

import sys
from typing import Any

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node

from lsu_common.node import run_node
from lsu_interfaces.msg import ScannerState
from lsu_interfaces.srv import Step


class SelftestTalker(Node):
    """Publishes a ScannerState with a position that the step service changes."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("selftest_talker", **kwargs)
        self.declare_parameter("rate_hz", 10.0, ParameterDescriptor(
            description="state publish rate [Hz]", read_only=True))
        self.declare_parameter("track_steps", 470, ParameterDescriptor(
            description="pretend track length [steps]", read_only=True))
        self.position_steps = 0
        self.track_steps = int(self.get_parameter("track_steps").value)
        self.pub = self.create_publisher(ScannerState, "selftest/state", 10)
        self.srv = self.create_service(Step, "selftest/step", self.on_step)
        self.timer = self.create_timer(1.0 / float(self.get_parameter("rate_hz").value), self.publish_state)

    def publish_state(self) -> None:
        msg = ScannerState()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.connected = True
        msg.homed = True
        msg.position_steps = self.position_steps
        msg.target_steps = self.position_steps
        msg.track_steps = self.track_steps
        msg.firmware = "selftest"
        self.pub.publish(msg)

    def on_step(self, request: Step.Request, response: Step.Response) -> Step.Response:
        target = self.position_steps + request.steps
        if not 0 <= target <= self.track_steps:
            response.success = False
            response.position_steps = self.position_steps
            response.message = f"target {target} outside the track 0..{self.track_steps}; step less"
            return response
        self.position_steps = target
        response.success = True
        response.position_steps = target
        return response


class SelftestListener(Node):
    """Echoes the talker's state and calls its step service now and then."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("selftest_listener", **kwargs)
        self.declare_parameter("step_every", 5, ParameterDescriptor(description="call step after this many messages"))
        self.declare_parameter("step_steps", 1, ParameterDescriptor(description="steps per step call"))
        self.received = 0
        self.echo = self.create_publisher(ScannerState, "selftest/echo", 10)
        self.sub = self.create_subscription(ScannerState, "selftest/state", self.on_state, 10)
        self.step = self.create_client(Step, "selftest/step")
        self._pending: Any | None = None

    def on_state(self, msg: ScannerState) -> None:
        self.received += 1
        msg.fault = f"echo {self.received}"
        self.echo.publish(msg)
        every = int(self.get_parameter("step_every").value)
        if every > 0 and self.received % every == 0 and self.step.service_is_ready():
            if self._pending is None or self._pending.done():
                request = Step.Request(steps=int(self.get_parameter("step_steps").value))
                self._pending = self.step.call_async(request)


def _main(node_class: type, args: list[str] | None) -> int:
    return run_node(node_class, args)


def talker_main(args: list[str] | None = None) -> int:
    """Console script ``selftest_talker``."""
    return _main(SelftestTalker, sys.argv if args is None else args)


def listener_main(args: list[str] | None = None) -> int:
    """Console script ``selftest_listener``."""
    return _main(SelftestListener, sys.argv if args is None else args)

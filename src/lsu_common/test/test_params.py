"""Table-driven parameters: the descriptor rclpy enforces, and a set through the parameter service that is
applied (post-set) or refused (range, read-only, on-set check) with the old value kept."""

from typing import Any

import pytest
from rclpy.node import Node

from lsu_common.params import Param, declare_parameters, descriptor

TABLE = {
    "rate_hz": Param(10.0, "rate [Hz]", (1.0, 50.0)),
    "depth": Param(5, "queue depth", (1, 100)),
    "port": Param("/dev/x", "device opened at start-up", read_only=True),
    "mode": Param("fast", "fast | slow"),
    "legacy": (0.5, "a plain (default, description, range) row", (0.0, 1.0)),
}


def test_descriptors_carry_description_range_of_the_default_type_and_read_only():
    d = descriptor(TABLE["rate_hz"])
    assert d.description == "rate [Hz]" and not d.read_only and not d.integer_range
    assert (d.floating_point_range[0].from_value, d.floating_point_range[0].to_value) == (1.0, 50.0)
    d = descriptor(TABLE["depth"])
    assert (d.integer_range[0].from_value, d.integer_range[0].to_value, d.integer_range[0].step) == (1, 100, 1)
    assert not d.floating_point_range
    assert descriptor(TABLE["port"]).read_only
    assert descriptor(TABLE["legacy"]).floating_point_range[0].to_value == 1.0
    with pytest.raises(TypeError, match="numeric default"):
        descriptor(Param(True, "a flag", (0, 1)))


class TableNode(Node):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__("table_node", **{"namespace": "/lsu_params_test", **kwargs})
        self.applied: list[list[str]] = []
        self.values: dict[str, Any] = {}
        self.declared = declare_parameters(self, TABLE, check=self._check, apply=self._apply)

    def _check(self, changed: list[Any]) -> Any:
        for p in changed:
            if p.name == "mode" and p.value not in ("fast", "slow"):
                return f"mode must be fast or slow, not {p.value}"
        return None

    def _apply(self, changed: list[Any]) -> None:
        self.applied.append(sorted(p.name for p in changed))
        self.values.update({p.name: p.value for p in changed})


def test_start_up_values_are_applied_once_through_the_same_path(ros_context):
    node = TableNode(context=ros_context, cli_args=["--ros-args", "-p", "rate_hz:=20.0", "-p", "port:=/dev/y"])
    try:
        assert node.applied == [sorted(TABLE)] and node.values == node.declared
        assert node.values["rate_hz"] == 20.0 and node.values["port"] == "/dev/y" and node.values["depth"] == 5
    finally:
        node.destroy_node()


def test_out_of_range_start_up_value_is_an_error_naming_the_parameter(ros_context):
    with pytest.raises(Exception, match="rate_hz"):
        TableNode(context=ros_context, cli_args=["--ros-args", "-p", "rate_hz:=500.0"])


def test_sets_through_the_parameter_service_are_applied_or_refused(ros_node):
    node = ros_node.add(TableNode(context=ros_node.context))
    name = node.get_fully_qualified_name()
    node.applied.clear()

    ok = ros_node.set_parameter(name, "rate_hz", 30.0)
    assert ok.successful, ok.reason
    assert node.applied == [["rate_hz"]] and node.values["rate_hz"] == 30.0

    for pname, value, why in (("rate_hz", 80.0, "range"), ("depth", 0, "range"), ("port", "/dev/z", "read-only"),
                              ("mode", "sideways", "fast or slow")):
        before = node.get_parameter(pname).value
        refused = ros_node.set_parameter(name, pname, value)
        assert not refused.successful, pname
        assert why in refused.reason or (why == "range" and refused.reason), refused.reason
        assert node.get_parameter(pname).value == before
    assert node.applied == [["rate_hz"]], "a refused set must not be applied"

    assert ros_node.set_parameter(name, "mode", "slow").successful
    assert node.applied[-1] == ["mode"] and node.values["mode"] == "slow"

"""scan_coordinator's parameters take effect when set or are refused; goals are accepted one at a time."""

from __future__ import annotations

import threading
from typing import Any

import pytest
from rclpy.action import GoalResponse
from rclpy.parameter import Parameter

from lsu_interfaces.action import Scan
from lsu_scan.coordinator import PARAMETERS, ScanCoordinatorNode
from lsu_testing.plugin import FakeGoalHandle


@pytest.fixture
def coordinator(ros_context, tmp_path):
    node = ScanCoordinatorNode(context=ros_context, namespace="/lsu_params_test",
                               parameter_overrides=[Parameter("output_dir", value=str(tmp_path))])
    yield node
    node.destroy_node()


NUMERIC = [name for name, (default, _d, bounds) in PARAMETERS.items() if bounds is not None]


@pytest.mark.parametrize("name", NUMERIC)
def test_a_numeric_parameter_set_at_run_time_is_what_the_scan_reads(coordinator, name):
    low, high = PARAMETERS[name][2]
    value = round(low + 0.37 * (high - low), 3)
    if isinstance(PARAMETERS[name][0], int):  # a count (motion_rescans)
        value = max(int(low) + 1, int(value))
    result = coordinator.set_parameters([Parameter(name, value=value)])[0]
    assert result.successful, result.reason
    assert getattr(coordinator, name) == pytest.approx(value)
    if name == "laser_pause_s":
        assert coordinator.guard.pause_s == pytest.approx(value), "the laser guard must use the new pause"


@pytest.mark.parametrize("name", NUMERIC)
def test_a_numeric_parameter_outside_its_range_is_refused_and_the_old_value_kept(coordinator, name):
    before = getattr(coordinator, name)
    high = PARAMETERS[name][2][1]
    result = coordinator.set_parameters([Parameter(name, value=float(high) * 2 + 1.0)])[0]
    assert not result.successful
    assert getattr(coordinator, name) == before


def test_output_dir_applies_to_the_next_scan_and_a_file_is_refused(coordinator, tmp_path):
    target = tmp_path / "elsewhere"
    assert coordinator.set_parameters([Parameter("output_dir", value=str(target))])[0].successful
    assert coordinator.output_dir == target
    a_file = tmp_path / "not_a_folder"
    a_file.write_text("x")
    refused = coordinator.set_parameters([Parameter("output_dir", value=str(a_file))])[0]
    assert not refused.successful and "not a folder" in refused.reason
    assert coordinator.output_dir == target


def test_settle_mode_takes_effect_or_is_refused_naming_the_modes(coordinator):
    assert coordinator.settle == "fixed"
    assert coordinator.set_parameters([Parameter("settle", value="adaptive")])[0].successful
    assert coordinator.settle == "adaptive"
    refused = coordinator.set_parameters([Parameter("settle", value="sometimes")])[0]
    assert not refused.successful and "fixed, adaptive" in refused.reason
    assert coordinator.settle == "adaptive"


def test_every_parameter_is_described_with_its_range(coordinator):
    for name, (_default, _text, bounds) in PARAMETERS.items():
        descriptor = coordinator.describe_parameter(name)
        assert descriptor.description
        if bounds is not None:
            ranges = descriptor.integer_range if isinstance(_default, int) else descriptor.floating_point_range
            assert ranges[0].from_value == bounds[0]
            assert ranges[0].to_value == bounds[1]


def test_of_two_goals_sent_at_the_same_moment_exactly_one_is_accepted(coordinator):
    for _round in range(50):
        barrier = threading.Barrier(2)
        answers: list[Any] = []

        def send() -> None:
            barrier.wait()
            answers.append(coordinator._on_goal(Scan.Goal()))

        threads = [threading.Thread(target=send) for _ in range(2)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        assert sorted(answer.name for answer in answers) == ["ACCEPT", "REJECT"]
        # the accepted goal ends (here: refused at once, no driver state) and frees the coordinator
        handle = FakeGoalHandle(start_steps=0, end_steps=10, step_steps=2)
        coordinator._execute(handle)
        assert handle.ended == "aborted"
    assert coordinator._on_goal(Scan.Goal()) == GoalResponse.ACCEPT

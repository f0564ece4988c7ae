"""Integer-nanosecond stamps: exact round trips, and the carry into seconds when rounding reaches 1 s."""

import pytest
from builtin_interfaces.msg import Time
from rclpy.time import Time as RclpyTime

from lsu_common import stamps


@pytest.mark.parametrize("ns", [0, 1, 999_999_999, 1_000_000_000, 1_800_000_000_123_456_789, 2**62 + 7])
def test_ns_to_msg_and_back_is_exact(ns):
    msg = stamps.to_msg(ns)
    assert isinstance(msg, Time)
    assert 0 <= msg.nanosec < 1_000_000_000
    assert msg.sec * 1_000_000_000 + msg.nanosec == ns  # the definition, written out
    assert stamps.to_ns(msg) == ns


@pytest.mark.parametrize("seconds, sec, nanosec", [
    (1.9999999999, 2, 0),            # rounds up to the next second: carried, not 1 s 0 ns
    (0.9999999996, 1, 0),
    (41.99999999995, 42, 0),
    (1.5, 1, 500_000_000),
    (2.0000000004, 2, 0),            # rounds down
    (1_800_000_000.25, 1_800_000_000, 250_000_000),
])
def test_float_seconds_round_to_the_nearest_ns_with_the_carry(seconds, sec, nanosec):
    msg = stamps.from_seconds(seconds)
    assert (msg.sec, msg.nanosec) == (sec, nanosec)


def test_text_form_is_exact():
    assert stamps.to_text(1_800_000_000_000_000_042) == "1800000000.000000042"
    assert stamps.to_text(stamps.to_ns(Time(sec=5, nanosec=120_000_000))) == "5.120000000"


def test_times_before_the_epoch_have_a_positive_nanosec():
    msg = stamps.to_msg(-1)  # 1 ns before 1970: sec -1, nanosec 999999999 (the ROS convention)
    assert (msg.sec, msg.nanosec) == (-1, 999_999_999)
    assert stamps.to_ns(msg) == -1
    assert stamps.split_ns(-1_500_000_000) == (-2, 500_000_000)


def test_seconds_and_rclpy_times():
    assert stamps.seconds_to_ns(0.1) == 100_000_000
    assert stamps.ns_to_seconds(1_500_000_000) == 1.5
    assert stamps.to_seconds(Time(sec=3, nanosec=250_000_000)) == 3.25
    assert stamps.from_rclpy_time(RclpyTime(seconds=5, nanoseconds=7)) == 5_000_000_007


def test_any_object_with_sec_and_nanosec_is_a_stamp():
    class Plain:  # a rosbags message or a parsed CDR header
        sec, nanosec = 7, 8
    assert stamps.to_ns(Plain()) == 7_000_000_008

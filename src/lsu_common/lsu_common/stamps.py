"""Stamps as integer nanoseconds: the one exact form (float seconds lose the last digits after ~2^53 ns).

A ROS ``builtin_interfaces/Time`` is ``(sec, nanosec)`` with ``0 <= nanosec < 1e9``; a time before
the epoch has a negative ``sec`` and a positive ``nanosec``. Conversions from float seconds round
to the nearest nanosecond and carry into ``sec`` (1.9999999999 s is 2 s 0 ns, not 1 s 0 ns).

Works with any object that has ``sec`` and ``nanosec`` (the ROS message, a rosbags message, a
`lsu_extract.image.ImageCdr`); only `to_msg` and `from_seconds` build a message.
"""

from __future__ import annotations

import math
from typing import Any

NS_PER_S = 1_000_000_000


def to_ns(stamp: Any) -> int:
    """``sec * 1e9 + nanosec`` of a Time message (or anything with ``sec`` and ``nanosec``)."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def split_ns(ns: int) -> tuple[int, int]:
    """``(sec, nanosec)`` of integer nanoseconds, ``0 <= nanosec < 1e9`` (floor division, also before 1970)."""
    sec, nanosec = divmod(int(ns), NS_PER_S)
    return sec, nanosec


def to_text(ns: int) -> str:
    """``"sec.nanosec"`` with nine digits after the point (exact, sortable as a key in files)."""
    sec, nanosec = split_ns(ns)
    return f"{sec}.{nanosec:09d}"


def to_msg(ns: int) -> Any:
    """A ``builtin_interfaces/Time`` of integer nanoseconds."""
    from builtin_interfaces.msg import Time

    sec, nanosec = split_ns(ns)
    return Time(sec=sec, nanosec=nanosec)


def seconds_to_ns(seconds: float) -> int:
    """Float seconds to integer nanoseconds, rounded to the nearest one.

    The whole seconds and the fraction are scaled apart: ``seconds * 1e9`` of a wall-clock time
    (~1.8e18 ns) is a double 256 ns coarse, the fraction alone is exact to well below 1 ns.
    """
    whole = math.floor(seconds)
    return int(whole) * NS_PER_S + int(round((seconds - whole) * NS_PER_S))


def ns_to_seconds(ns: int) -> float:
    """Integer nanoseconds to float seconds (for durations and display, not for keys)."""
    return int(ns) / NS_PER_S


def to_seconds(stamp: Any) -> float:
    """A Time message as float seconds (for arithmetic on durations; use `to_ns` for keys)."""
    return ns_to_seconds(to_ns(stamp))


def from_seconds(seconds: float) -> Any:
    """A ``builtin_interfaces/Time`` of float seconds, rounded to the nanosecond with the carry into ``sec``."""
    return to_msg(seconds_to_ns(seconds))


def from_rclpy_time(time: Any) -> int:
    """Integer nanoseconds of an ``rclpy.time.Time`` (e.g. ``node.get_clock().now()``)."""
    return int(time.nanoseconds)

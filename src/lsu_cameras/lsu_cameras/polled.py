"""Subscriptions read on demand instead of by an executor (rclpy only, no camera code)."""

from __future__ import annotations

from typing import Any

from rclpy.callback_groups import CallbackGroup


class PolledGroup(CallbackGroup):
    """A callback group no executor ever runs: its subscriptions are read on demand (`take_latest`).

    Why: a node that needs only the newest sample of a frequent topic (the camera: ``sim/truth``
    at up to 50 Hz, read at each capture; the scan coordinator: ``driver/state``, read when a goal
    starts) pays ~1 ms of Python per executor callback (single-threaded executor; ~2.5 ms
    multi-threaded) for samples it never looks at. A depth-1 reader keeps the newest sample inside
    DDS with no Python work until it is asked for. Its subscriptions never enter the wait set.
    """

    def can_execute(self, entity: Any) -> bool:
        return False

    def beginning_execution(self, entity: Any) -> bool:
        return False

    def ending_execution(self, entity: Any) -> None:
        pass


def take_all(subscription: Any) -> list[Any]:
    """Every message waiting in a `PolledGroup` subscription's reader, oldest first (serialized bytes if raw)."""
    taken_all: list[Any] = []
    with subscription.handle:  # raises InvalidHandle once destroyed, like an executor's take
        while True:
            taken = subscription.handle.take_message(subscription.msg_type, subscription.raw)
            if taken is None:
                return taken_all
            taken_all.append(taken[0])


def take_latest(subscription: Any) -> Any | None:
    """The newest message waiting in a `PolledGroup` subscription's reader (None if none arrived since)."""
    waiting = take_all(subscription)
    return waiting[-1] if waiting else None

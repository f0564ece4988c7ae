"""What the bridge offers for each ROS topic, without rclpy: schema, how to subscribe, how often to send.

- :func:`ros2msg_schema`: the ``ros2msg`` definition text Foxglove needs to decode a topic's CDR
  (the same text a rosbag2 mcap file carries, from the bag module's typestore, so our own
  ``lsu_interfaces`` types are described from their ``.msg`` files).
- :func:`topic_kind`: ``latched`` topics (every publisher transient-local: camera_info, the scan
  cloud, the mesh) are subscribed reliable + transient-local so a client that connects after the
  scan still gets them; ``image`` topics are rate-limited; everything else is ``stream``.
- :class:`RateLimiter`: at most ``max_hz`` messages per topic reach the clients.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass

from lsu_bags.bags import BagTypes

#: message types sent at most `image_max_hz` times a second per topic (big, and a person watching
#: does not need all of them)
IMAGE_TYPES = frozenset({"sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"})
#: topics never offered: every node's log and parameter chatter
EXCLUDED_TOPICS = frozenset({"/rosout", "/parameter_events"})


@dataclass(frozen=True)
class TopicOffer:
    """One ROS topic as the bridge advertises it to Foxglove clients."""

    topic: str
    msgtype: str
    schema_text: str
    kind: str  # "latched" | "image" | "stream"


def ros2msg_schema(msgtype: str, types: BagTypes, topic: str | None = None) -> str:
    """The ``ros2msg`` text of ``msgtype`` with every type it uses (rosbag2's mcap format).

    Raises:
        lsu_bags.bags.UnknownTypeError: no definition of the type (or a type it uses) is installed.
    """
    types.ensure(msgtype, topic)
    text, _hash = types.msgdef(msgtype)
    return text


def topic_kind(msgtype: str, durabilities: Sequence[str]) -> str:
    """``latched`` when every publisher offers transient-local, else ``image`` for image types, else ``stream``."""
    if durabilities and all(d == "transient_local" for d in durabilities):
        return "latched"
    return "image" if msgtype in IMAGE_TYPES else "stream"


def offered(topic: str) -> bool:
    """Topics the bridge offers: all but log/parameter chatter and hidden names (a segment starting with '_')."""
    return topic not in EXCLUDED_TOPICS and not any(part.startswith("_") for part in topic.split("/") if part)


class RateLimiter:
    """Lets at most ``max_hz`` messages per key through (0 = all); thread-safe.

    A message passes when at least ``1 / max_hz`` seconds went by since the last one that passed,
    so a burst is thinned to the rate instead of being queued behind it.
    """

    def __init__(self, max_hz: float) -> None:
        self._lock = threading.Lock()
        self._last: dict[str, float] = {}
        self.max_hz = max_hz

    @property
    def max_hz(self) -> float:
        return self._max_hz

    @max_hz.setter
    def max_hz(self, value: float) -> None:
        if value < 0:
            raise ValueError(f"max_hz must be >= 0 (0 = no limit), got {value}")
        self._max_hz = float(value)

    def allow(self, key: str, now_s: float) -> bool:
        """True when a message on ``key`` at time ``now_s`` may be sent."""
        if self._max_hz <= 0:
            return True
        with self._lock:
            last = self._last.get(key)
            if last is not None and now_s - last < 1.0 / self._max_hz:
                return False
            self._last[key] = now_s
            return True

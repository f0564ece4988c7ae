"""``foxglove_bridge``: the LSU graph live in Foxglove, over the Foxglove WebSocket protocol.

Every topic on the graph (but ``/rosout``, ``/parameter_events`` and hidden names) is advertised
to Foxglove clients as a channel with its ROS 2 message definition (schema encoding ``ros2msg``)
and message encoding ``cdr``; the bytes DDS delivers are passed on untouched (raw subscriptions,
nothing is deserialized). The WebSocket server is ``foxglove-sdk``'s.

It must never slow a scan down:
- a ROS topic is subscribed only while a client is subscribed to its channel;
- volatile topics are subscribed best-effort, so no publisher ever waits for the bridge's
  acknowledgement (a reliable reader would hold back a camera that waits for its readers);
  latched ones (camera_info, scan cloud, mesh) reliable + transient-local, so a client that
  connects after the scan still gets them;
- images reach the clients at most ``image_max_hz`` times a second per topic, and each client
  has a bounded backlog (``client_backlog_messages``) whose oldest message is dropped when a
  slow client falls behind.
"""

from __future__ import annotations

import sys
import threading
import time
from typing import Any

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from lsu_bags.bags import BagError, BagTypes
from lsu_bags.rosmsg import InterfaceError, get_interface
from lsu_common import qos
from lsu_common.node import LsuNode, main_of
from lsu_common.params import Param, declare_parameters

from .channels import RateLimiter, TopicOffer, offered, ros2msg_schema, topic_kind

#: latched outputs: the last sample, kept for late joiners
LATCHED_QOS = qos.LATCHED
#: everything else: best effort, so publishers never wait for the bridge
STREAM_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5, reliability=ReliabilityPolicy.BEST_EFFORT,
                        durability=DurabilityPolicy.VOLATILE)


# The server is started once with these (read-only); image_max_hz takes effect when set.
PARAMETERS: dict[str, Param] = {
    "host": Param("127.0.0.1", "address the WebSocket server listens on; 127.0.0.1 = this machine only, 0.0.0.0 = "
                  "every interface (anyone who reaches this PC sees the scan)", read_only=True),
    "port": Param(8765, "WebSocket port (0: any free port, printed at start)", (0, 65535), read_only=True),
    "image_max_hz": Param(5.0, "images sent to clients per topic and second at most (0: every image)", (0.0, 120.0)),
    "client_backlog_messages": Param(32, "messages buffered per client; the oldest is dropped when a slow client "
                                     "falls behind", (1, 4096), read_only=True),
    "graph_poll_s": Param(0.5, "how often new topics are looked for [s]", (0.05, 10.0), read_only=True),
}


class _Listener:
    """foxglove-sdk server callbacks (run on the SDK's threads): remember which channels are watched."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.subscribers: dict[int, set[int]] = {}  # channel id -> client ids
        self.changed = threading.Event()

    def on_subscribe(self, client: Any, channel: Any) -> None:
        with self.lock:
            self.subscribers.setdefault(channel.id, set()).add(client.id)
        self.changed.set()

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        with self.lock:
            self.subscribers.get(channel.id, set()).discard(client.id)
        self.changed.set()

    def watched(self) -> set[int]:
        with self.lock:
            return {cid for cid, clients in self.subscribers.items() if clients}


class FoxgloveBridgeNode(LsuNode):
    """A Foxglove WebSocket server offering the graph's topics (see the module docstring)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("foxglove_bridge", **{"namespace": "/lsu", **kwargs})
        import foxglove
        from foxglove import Context, Schema

        self._fx_schema = Schema
        self._image_limiter = RateLimiter(5.0)
        declare_parameters(self, PARAMETERS, apply=self._apply_parameters)
        self._bag_types = BagTypes()
        self._fx_offers: dict[str, TopicOffer] = {}
        self._fx_channels: dict[str, Any] = {}  # topic -> foxglove Channel
        self._fx_topic_of: dict[int, str] = {}  # channel id -> topic
        self._ros_subs: dict[str, Any] = {}  # topic -> rclpy subscription (only while watched)
        self._skipped_topics: set[str] = set()
        self._fx_listener = _Listener()
        self._fx_context = Context()
        host = str(self.get_parameter("host").value)
        try:
            self.server = foxglove.start_server(
                name="lsu", host=host, port=int(self.get_parameter("port").value), context=self._fx_context,
                server_listener=self._fx_listener,
                message_backlog_size=int(self.get_parameter("client_backlog_messages").value))
        except Exception as exc:  # the SDK raises its own error types for bind failures
            raise RuntimeError(f"cannot start the Foxglove WebSocket server on {host}:"
                               f"{self.get_parameter('port').value} ({exc}); choose another port "
                               f"(port:=N) or stop what holds it") from None
        self.url = f"ws://{host}:{self.server.port}"
        if host not in ("127.0.0.1", "localhost", "::1"):
            self.get_logger().warning(f"listening on {host}: clients on other machines can watch the scan")
        self.get_logger().info(f"Foxglove WebSocket server on {self.url} (Foxglove: Open connection > "
                               f"Foxglove WebSocket > {self.url})")
        self.create_timer(float(self.get_parameter("graph_poll_s").value), self.poll_graph)
        self.create_timer(0.05, self._sync_if_changed)
        self.poll_graph()

    # -- parameters ------------------------------------------------------------------------------
    def _apply_parameters(self, params: list[Any]) -> None:
        for p in params:
            if p.name == "image_max_hz":
                self._image_limiter.max_hz = float(p.value)  # the descriptor's range already refused < 0

    # -- graph -> channels -----------------------------------------------------------------------
    @property
    def offers(self) -> dict[str, TopicOffer]:
        """Topic -> what is advertised for it."""
        return dict(self._fx_offers)

    def poll_graph(self) -> None:
        """Advertise topics that appeared on the graph since the last poll."""
        for topic, types in self.get_topic_names_and_types():
            if topic in self._fx_offers or topic in self._skipped_topics or not offered(topic):
                continue
            publishers = self.get_publishers_info_by_topic(topic)
            if not publishers:
                continue  # only subscribers: nothing to show yet
            if len(types) != 1:
                self._skip(topic, f"it has several types on the graph ({', '.join(types)})")
                continue
            msgtype = types[0]
            try:
                get_interface(msgtype, "msg")
                schema = ros2msg_schema(msgtype, self._bag_types, topic)
            except (BagError, InterfaceError) as exc:
                self._skip(topic, str(exc))
                continue
            durability = [p.qos_profile.durability.name.lower() for p in publishers]
            offer = TopicOffer(topic, msgtype, schema, topic_kind(msgtype, durability))
            channel = self._make_channel(offer)
            self._fx_offers[topic] = offer
            self._fx_channels[topic] = channel
            self._fx_topic_of[channel.id()] = topic
            self.get_logger().debug(f"offering {topic} [{msgtype}] ({offer.kind})")
        self._sync_subscriptions()

    def _make_channel(self, offer: TopicOffer) -> Any:
        from foxglove import Channel

        return Channel(offer.topic, message_encoding="cdr", context=self._fx_context,
                       schema=self._fx_schema(name=offer.msgtype, encoding="ros2msg", data=offer.schema_text.encode()))

    def _skip(self, topic: str, why: str) -> None:
        self._skipped_topics.add(topic)
        self.get_logger().warning(f"not offering {topic}: {why}")

    # -- channels watched -> ROS subscriptions -----------------------------------------------------
    def _sync_if_changed(self) -> None:
        if self._fx_listener.changed.is_set():
            self._sync_subscriptions()

    def _sync_subscriptions(self) -> None:
        self._fx_listener.changed.clear()
        watched = {self._fx_topic_of[cid] for cid in self._fx_listener.watched() if cid in self._fx_topic_of}
        for topic in sorted(watched - set(self._ros_subs)):
            offer = self._fx_offers[topic]
            cls = get_interface(offer.msgtype, "msg")
            qos = LATCHED_QOS if offer.kind == "latched" else STREAM_QOS
            self._ros_subs[topic] = self.create_subscription(cls, topic, self._forward(offer), qos, raw=True)
        for topic in sorted(set(self._ros_subs) - watched):
            self.destroy_subscription(self._ros_subs.pop(topic))

    def _forward(self, offer: TopicOffer) -> Any:
        channel = self._fx_channels[offer.topic]
        limiter = self._image_limiter if offer.kind == "image" else None
        topic = offer.topic

        def on_message(data: bytes, info: dict[str, Any]) -> None:
            if limiter is not None and not limiter.allow(topic, time.monotonic()):
                return
            channel.log(data, log_time=int(info.get("received_timestamp") or 0) or time.time_ns())

        return on_message

    @property
    def watched_topics(self) -> list[str]:
        """Topics the bridge is subscribed to right now (a client watches them)."""
        return sorted(self._ros_subs)

    def destroy_node(self) -> None:
        server: Any | None = getattr(self, "server", None)
        if server is not None:
            server.stop()
        super().destroy_node()


main = main_of(FoxgloveBridgeNode, startup_errors=(RuntimeError,), program="foxglove_bridge")


if __name__ == "__main__":
    sys.exit(main())

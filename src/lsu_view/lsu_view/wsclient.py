"""A small client of the Foxglove WebSocket protocol, on ``websockets``.

The protocol was published as ``foxglove.websocket.v1``; servers of ``foxglove-sdk`` (0.30) accept
only its successor name ``foxglove.sdk.v1``, whose frames used here are the same. The client offers
both and works with either.

Written from the protocol specification, independently of the server library, so tests and the
benchmark check what any Foxglove client would see: ``serverInfo`` and ``advertise`` text frames,
``subscribe`` / ``unsubscribe`` requests, and binary message-data frames (opcode 0x01, then
uint32 subscription id, uint64 receive time in ns, payload; little endian).

    with FoxgloveClient("ws://127.0.0.1:8765") as client:
        client.wait_for_topics(["/lsu/points"])
        client.subscribe(["/lsu/points"])
        topic, stamp_ns, payload = client.next_message(timeout_s=10)
"""

from __future__ import annotations

import json
import queue
import struct
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from websockets.exceptions import ConnectionClosed
from websockets.sync.client import ClientConnection, connect

#: the subprotocols offered, preferred first
SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")
_MESSAGE_DATA = 0x01
_TIME = 0x02


class ProtocolError(RuntimeError):
    """The server sent something the protocol does not allow, or nothing in time."""


@dataclass(frozen=True)
class AdvertisedChannel:
    """A channel from an ``advertise`` frame."""

    id: int
    topic: str
    encoding: str
    schema_name: str
    schema: str
    schema_encoding: str


class FoxgloveClient:
    """Connects, collects advertised channels, subscribes by topic and queues received messages."""

    def __init__(self, url: str, open_timeout_s: float = 10.0, max_queue: int = 10000) -> None:
        self.url = url
        self.server_info: dict[str, object] = {}
        self.channels: dict[int, AdvertisedChannel] = {}
        self.bytes_received = 0
        self.messages_received = 0
        self._subscriptions: dict[int, int] = {}  # subscription id -> channel id
        self._next_sub = 1
        self.closed: str | None = None  # why the connection ended (set by the reader), None while open
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._queue: queue.Queue[tuple[str, int, bytes]] = queue.Queue(maxsize=max_queue)
        self._connector = connect(url, subprotocols=list(SUBPROTOCOLS), open_timeout=open_timeout_s, max_size=None)
        self._ws: ClientConnection = self._connector.__enter__()
        if self._ws.subprotocol not in SUBPROTOCOLS:
            self._connector.__exit__(None, None, None)
            raise ProtocolError(f"{url} accepted none of the subprotocols {', '.join(SUBPROTOCOLS)}")
        self.subprotocol = self._ws.subprotocol
        self._reader = threading.Thread(target=self._read, name="foxglove-client", daemon=True)
        self._reader.start()

    def __enter__(self) -> FoxgloveClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- receiving ---------------------------------------------------------------------------------
    def _read(self) -> None:
        try:
            for frame in self._ws:
                if isinstance(frame, str):
                    self._on_text(json.loads(frame))
                else:
                    self._on_binary(frame)
            why = "the server closed the connection"
        except ConnectionClosed as exc:
            why = f"the connection closed ({exc})"
        with self._changed:
            self.closed = why
            self._changed.notify_all()

    def _on_text(self, msg: dict[str, Any]) -> None:
        op = msg.get("op")
        with self._changed:
            if op == "serverInfo":
                self.server_info = msg
            elif op == "advertise":
                for ch in msg["channels"]:
                    self.channels[int(ch["id"])] = AdvertisedChannel(
                        int(ch["id"]), ch["topic"], ch["encoding"], ch["schemaName"], ch.get("schema", ""),
                        ch.get("schemaEncoding", ""))
            elif op == "unadvertise":
                for cid in msg["channelIds"]:
                    self.channels.pop(int(cid), None)
            self._changed.notify_all()

    def _on_binary(self, frame: bytes) -> None:
        if not frame:
            return
        if frame[0] == _MESSAGE_DATA:
            sub_id, stamp_ns = struct.unpack_from("<IQ", frame, 1)
            with self._lock:
                channel = self.channels.get(self._subscriptions.get(sub_id, -1))
                self.bytes_received += len(frame)
                self.messages_received += 1
            if channel is None:
                return  # data of a subscription we just dropped
            try:
                self._queue.put_nowait((channel.topic, stamp_ns, bytes(frame[13:])))
            except queue.Full:
                pass  # a test that stopped reading: keep the connection alive, drop the data

    # -- requests ----------------------------------------------------------------------------------
    def wait_for_topics(self, topics: Iterable[str], timeout_s: float = 20.0) -> dict[str, AdvertisedChannel]:
        """Wait until every topic is advertised; returns topic -> channel."""
        wanted = set(topics)
        end = time.monotonic() + timeout_s
        with self._changed:
            while True:
                have = {c.topic: c for c in self.channels.values()}
                if wanted <= set(have):
                    return {t: have[t] for t in wanted}
                left = end - time.monotonic()
                if self.closed is not None:
                    raise ProtocolError(f"{self.url}: {self.closed} before it advertised {sorted(wanted - set(have))}")
                if left <= 0:
                    raise ProtocolError(f"{self.url} did not advertise {sorted(wanted - set(have))} within "
                                        f"{timeout_s:g} s (advertised: {sorted(have)})")
                self._changed.wait(left)

    def subscribe(self, topics: Iterable[str]) -> list[int]:
        """Subscribe to advertised topics; returns the subscription ids."""
        with self._lock:
            by_topic = {c.topic: c.id for c in self.channels.values()}
            subs = []
            for topic in topics:
                if topic not in by_topic:
                    raise ProtocolError(f"{topic} is not advertised by {self.url}")
                subs.append({"id": self._next_sub, "channelId": by_topic[topic]})
                self._subscriptions[self._next_sub] = by_topic[topic]
                self._next_sub += 1
        self._ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
        return [s["id"] for s in subs]

    def next_message(self, timeout_s: float = 10.0, topic: str | None = None) -> tuple[str, int, bytes]:
        """The next received ``(topic, receive time ns, CDR payload)`` (of ``topic`` if given)."""
        end = time.monotonic() + timeout_s
        while True:
            left = end - time.monotonic()
            if left <= 0:
                raise ProtocolError(f"no message{f' on {topic}' if topic else ''} from {self.url} "
                                    f"within {timeout_s:g} s")
            try:
                item = self._queue.get(timeout=min(left, 0.2))
            except queue.Empty:
                if self.closed is not None:  # what came before the end was delivered first
                    raise ProtocolError(f"no message{f' on {topic}' if topic else ''} from {self.url}: "
                                        f"{self.closed}") from None
                continue
            if topic is None or item[0] == topic:
                return item

    def close(self) -> None:
        """Close the connection and wait for the reader."""
        self._connector.__exit__(None, None, None)
        self._reader.join(timeout=5.0)

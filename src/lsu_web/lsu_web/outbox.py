"""What the graph thread hands to each browser: bounded, dropping the oldest (no rclpy, no web framework).

The rclpy callbacks must never wait for a browser, and a slow or stalled browser must never make
memory grow: every client has two bounded deques, ``control`` (state, progress, events, results:
small, and the newest is what counts) and ``bulk`` (images, points: dropped first). ``put`` from any
thread appends (the oldest entry falls out when full, and is counted) and wakes the client's
coroutine through its event loop at most once per batch; the coroutine takes everything queued.
"""

from __future__ import annotations

import asyncio
import threading
from collections import deque
from dataclasses import dataclass, field
from typing import Any

CONTROL = "control"
BULK = "bulk"


@dataclass
class ClientBox:
    """One browser's two queues and its wake-up."""

    loop: asyncio.AbstractEventLoop
    control_max: int = 256
    bulk_max: int = 16
    dropped: int = 0
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _wake_pending: bool = False
    _event: asyncio.Event = field(default_factory=asyncio.Event)

    def __post_init__(self) -> None:
        self._control: deque[Any] = deque(maxlen=self.control_max)
        self._bulk: deque[Any] = deque(maxlen=self.bulk_max)

    def put(self, kind: str, item: Any) -> None:
        """Queue ``item`` (any thread); never blocks; drops the oldest of its queue when full."""
        with self._lock:
            q = self._control if kind == CONTROL else self._bulk
            if len(q) == q.maxlen:
                self.dropped += 1
            q.append(item)
            if self._wake_pending:
                return
            self._wake_pending = True
        try:
            self.loop.call_soon_threadsafe(self._event.set)
        except RuntimeError:  # the loop is closed: the client is gone
            pass

    async def take(self) -> list[Any]:
        """Wait for items, then return all of them (control first)."""
        await self._event.wait()
        with self._lock:
            self._event.clear()
            self._wake_pending = False
            items = list(self._control) + list(self._bulk)
            self._control.clear()
            self._bulk.clear()
        return items


class Outbox:
    """Every connected browser's `ClientBox`, and the last control message per topic for newcomers."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._clients: dict[int, ClientBox] = {}
        self._latest: dict[str, Any] = {}
        self._next_id = 1

    def add(self, box: ClientBox) -> int:
        with self._lock:
            cid = self._next_id
            self._next_id += 1
            self._clients[cid] = box
            latest = list(self._latest.values())
        for item in latest:
            box.put(CONTROL, item)
        return cid

    def remove(self, cid: int) -> None:
        with self._lock:
            self._clients.pop(cid, None)

    @property
    def count(self) -> int:
        with self._lock:
            return len(self._clients)

    def publish(self, kind: str, item: Any, latest_key: str | None = None) -> None:
        """Hand ``item`` to every client (any thread); ``latest_key``: keep it for clients that join later."""
        with self._lock:
            if latest_key is not None:
                self._latest[latest_key] = item
            boxes = list(self._clients.values())
        for box in boxes:
            box.put(kind, item)

    def latest(self, key: str) -> Any:
        with self._lock:
            return self._latest.get(key)

    def dropped(self) -> int:
        with self._lock:
            return sum(b.dropped for b in self._clients.values())

"""The graph's named QoS profiles (CONTRIBUTING.md, "QoS"): every node takes them from here.

- `LATCHED`: outputs a late subscriber must still get (extrinsics, /tf_static, scan cloud, mesh):
  reliable, transient-local, the last one.
- `EVENTS`: scan events and per-scan results that must not be dropped: reliable, keep-all.
- `SCAN_DATA`: images, laser lines, points of a scan: reliable, a few deep.
- `FRAME_QUEUE`: a reader that must see every frame of a camera stream: reliable, a second at 30 fps deep.
- `STATE`: the newest state only (driver state polled when a goal starts): reliable, depth 1.
"""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
EVENTS = QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.VOLATILE)
SCAN_DATA = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5, reliability=ReliabilityPolicy.RELIABLE)
# DDS acknowledges a sample (the camera's stream waits for that) once it is in the reader's queue, not once
# the node took it: a reader busy for longer than its queue lasts loses the oldest frames without a word.
# 30 frames (27 MB of 640x480 BGR) carry a reader through a second of a loaded host at 30 fps.
FRAME_QUEUE = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=30, reliability=ReliabilityPolicy.RELIABLE)
STATE = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE)


def reliable(depth: int) -> QoSProfile:
    """Reliable, volatile, the last ``depth`` messages (a queue sized for the topic's bursts)."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=int(depth), reliability=ReliabilityPolicy.RELIABLE)

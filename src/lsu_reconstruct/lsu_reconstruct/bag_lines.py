"""The stereo laser lines of a recorded scan (rosbag2): what `lsu reconstruct --bag` and `lsu calibrate --laser`
read. Topics are matched by their suffix, so any namespace works; read with lsu_bags (no ROS needed)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from lsu_bags.bags import BagError, BagTypes, bag_topics, deserialize, read_messages
from lsu_common import stamps
from lsu_common.arrays import AnyArray
from lsu_common.images import ImageFormatError, msg_to_bgr

from .matching import LineArrays

__all__ = ["EVENT_TYPE", "LINE_TYPE", "read_bag"]

LINE_TYPE = "lsu_interfaces/msg/LaserLine"
EVENT_TYPE = "lsu_interfaces/msg/ScanEvent"


_key = stamps.to_ns


def _line(msg: Any) -> LineArrays:
    return LineArrays(u=np.asarray(msg.u, dtype=np.float64), v=np.asarray(msg.v, dtype=np.float64),
                      peak=np.asarray(msg.peak), width=np.asarray(msg.width), quality=np.asarray(msg.quality),
                      image_width=int(msg.image_width), image_height=int(msg.image_height))


def _image(msg: Any) -> AnyArray:
    try:
        return msg_to_bgr(msg)
    except ImageFormatError as exc:
        raise BagError(f"texture image: {exc}") from None


def read_bag(path: str | Path) -> tuple[list[tuple[int, int, LineArrays, LineArrays]], AnyArray | None, dict[str, int]]:
    """Stereo laser-line pairs of a bag: ``[(snap, stamp_ns, left, right)]``, the texture image (or None), counts."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"bag {path} not found")
    topics = bag_topics(path)
    wanted: dict[str, str] = {}
    for topic, (msgtype, _qos) in topics.items():
        if topic.endswith("stereo/left/laser_line") and msgtype == LINE_TYPE:
            wanted[topic] = "left"
        elif topic.endswith("stereo/right/laser_line") and msgtype == LINE_TYPE:
            wanted[topic] = "right"
        elif topic.endswith("scan/events") and msgtype == EVENT_TYPE:
            wanted[topic] = "events"
    if not any(v in ("left", "right") for v in wanted.values()):
        have = ", ".join(sorted(f"{t} ({m})" for t, (m, _q) in topics.items())) or "none"
        raise BagError(f"bag {path} has no stereo/{{left,right}}/laser_line topics of type {LINE_TYPE}; "
                       f"it has: {have}")
    types = BagTypes()
    lines: dict[str, dict[int, LineArrays]] = {"left": {}, "right": {}}
    snaps: dict[int, int] = {}
    texture_keys: list[int] = []
    try:
        for message in read_messages(path, sorted(wanted)):
            msg = deserialize(message, types)
            kind = wanted[message.topic]
            if kind == "events":
                if msg.type == 2:      # SNAP
                    snaps[_key(msg.image_stamp)] = int(msg.index)
                elif msg.type == 1:    # TEXTURE
                    texture_keys.append(_key(msg.image_stamp))
            else:
                lines[kind][_key(msg.header.stamp)] = _line(msg)
        texture = None
        images = [t for t in topics if t.endswith("stereo/left/image_raw")]
        if texture_keys and images:
            for message in read_messages(path, images):
                msg = deserialize(message, types)
                if _key(msg.header.stamp) == texture_keys[-1]:
                    texture = _image(msg)
                    break
    except BagError:
        raise
    except Exception as exc:  # a message that does not deserialise: corrupt data under a valid index
        raise BagError(f"cannot read bag {path}: {exc.__class__.__name__}: {exc}") from None
    common = sorted(set(lines["left"]) & set(lines["right"]))
    counts = {"left": len(lines["left"]), "right": len(lines["right"]), "pairs": len(common)}
    if not common:
        raise BagError(f"bag {path}: {counts['left']} left and {counts['right']} right laser lines but no pair with "
                       f"equal header.stamp")
    pairs = []
    for order, key in enumerate(common):
        pairs.append((snaps.get(key, order), key, lines["left"][key], lines["right"][key]))
    return pairs, texture, counts

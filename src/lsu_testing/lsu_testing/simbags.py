"""Scan bags written straight from the simulated rig, without starting the graph (pure: no rclpy).

The bag holds what the scan coordinator's own recording holds for the processing to be replayed:
``/lsu/scan/events`` (STARTED, TEXTURE, one SNAP per pair, FINISHED) and both
``/lsu/stereo/{left,right}/image_raw`` (bgr8), stamped alike, so `lsu accuracy --bag` and
`lsu reconstruct` read it like a recorded scan. Used to make board-scan bags for tests and for
trying `lsu accuracy --bag` without a rig; a live recording (`lsu scan --record`) is the real thing.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from lsu_bags.bags import BagTypes, BagWriter
from lsu_common import stamps

__all__ = ["write_sim_scan_bag", "write_board_scan_bags", "EVENTS_TOPIC", "IMAGE_TOPICS"]

EVENTS_TOPIC = "/lsu/scan/events"
IMAGE_TOPICS = {"left": "/lsu/stereo/left/image_raw", "right": "/lsu/stereo/right/image_raw"}
FRAME_IDS = {"left": "lsu_left_optical", "right": "lsu_right_optical"}
_STARTED, _TEXTURE, _SNAP, _FINISHED = 0, 1, 2, 3


def write_sim_scan_bag(out_dir: Path | str, objects: Sequence | str, positions: Sequence[int], seed: int,
                       scan_id: str = "sim-scan", geometry=None, texture: bool = True, start_ns: int = 1_800_000_000 * 10**9,
                       period_ns: int = 100_000_000, storage: str = "mcap", compress: bool = True,
                       types: BagTypes | None = None) -> Path:
    """Render a stop-snap scan of ``objects`` (sim scene objects, or the name of a scene of `lsu_sim.build_scene`,
    e.g. ``person:3``) and write it as a rosbag2 folder.

    ``positions``: carriage positions [steps] of the laser snaps (settled, laser on); with ``texture``
    a laser-off pair comes first. Render noise is seeded ``seed + index``. Returns the bag folder.
    """
    from lsu_sim import CarriageState, SimulatedRig, build_scene, load_rig

    geometry = geometry or load_rig()
    scene = build_scene(objects, geometry) if isinstance(objects, str) else list(objects)
    rig = SimulatedRig(geometry, scene, seed=seed)
    types = types or BagTypes()
    store = types.typestore
    with BagWriter(out_dir, storage, compress=compress, types=types) as bag:
        bag.add_topic(EVENTS_TOPIC, "lsu_interfaces/msg/ScanEvent")
        for topic in IMAGE_TOPICS.values():
            bag.add_topic(topic, "sensor_msgs/msg/Image")
        Time = store.types["builtin_interfaces/msg/Time"]
        Header = store.types["std_msgs/msg/Header"]
        Image = store.types["sensor_msgs/msg/Image"]
        Event = store.types["lsu_interfaces/msg/ScanEvent"]

        def stamp(ns: int):
            sec, nanosec = stamps.split_ns(ns)
            return Time(sec=sec, nanosec=nanosec)

        def event(ns: int, kind: int, **fields) -> None:
            values = dict(header=Header(stamp=stamp(ns), frame_id=""), type=kind, scan_id=scan_id, expected_snaps=0,
                          index=0, position_steps=0, image_stamp=stamp(0), snaps_captured=0, partial=False, reason="",
                          output_dir="")
            values.update(fields)
            bag.write(EVENTS_TOPIC, ns, store.serialize_cdr(Event(**values), Event.__msgtype__))

        def pair(ns: int, frame) -> None:
            for side, image in (("left", frame.left), ("right", frame.right)):
                h, w = image.shape[:2]
                msg = Image(header=Header(stamp=stamp(ns), frame_id=FRAME_IDS[side]), height=h, width=w,
                            encoding="bgr8", is_bigendian=0, step=w * 3,
                            data=np.ascontiguousarray(image, dtype=np.uint8).reshape(-1))
                bag.write(IMAGE_TOPICS[side], ns, store.serialize_cdr(msg, Image.__msgtype__))

        t = int(start_ns)
        event(t, _STARTED, expected_snaps=len(positions))
        if texture:
            t += period_ns
            first = float(positions[0]) if len(positions) else 0.0
            pair(t, rig.render(CarriageState(first, laser_on=False), seed=seed - 1))
            event(t + 1, _TEXTURE, image_stamp=stamp(t))
        for index, position in enumerate(positions):
            t += period_ns
            pair(t, rig.render(float(position), seed=seed + index))
            event(t + 1, _SNAP, index=index, position_steps=int(position), image_stamp=stamp(t),
                  expected_snaps=len(positions))
        event(t + period_ns, _FINISHED, expected_snaps=len(positions), snaps_captured=len(positions))
    return Path(out_dir)


def write_board_scan_bags(root: Path | str, poses: Sequence, square_m: float = 0.02, step: int = 10, seed: int = 100,
                          geometry=None) -> list[Path]:
    """One board scan per `lsu_accuracy.accuracy.Pose` (carriage 0..track end every ``step``) as
    ``root/pose<i>/bag``, like `lsu scan --record` leaves them; input for `lsu accuracy --bag`
    (``--square`` = ``square_m`` in mm). Returns the bag folders."""
    from lsu_accuracy.accuracy import board_pose_object
    from lsu_sim import load_rig

    geometry = geometry or load_rig()
    bags = []
    for i, pose in enumerate(poses):
        board = board_pose_object(geometry, pose, square_m)
        bags.append(write_sim_scan_bag(Path(root) / f"pose{i}" / "bag", [board],
                                       list(range(0, int(geometry.track_steps) + 1, step)), seed=seed + 1000 * i,
                                       scan_id=f"pose{i}", geometry=geometry))
    return bags

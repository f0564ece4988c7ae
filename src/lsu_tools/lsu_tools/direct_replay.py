"""`lsu run replay BAG`: a recorded scan processed by the extractor and matcher in this process, handed over directly.

The bag's image pairs and scan events go straight from the bag reader to the ``laser_extractor``
node's extraction and its lines, as arrays, straight to the ``stereo_matcher``'s pairing (no DDS, no
(de)serialisation of images or lines between them, no LaserLine message unless someone subscribes
to the lines; an uncompressed bag's images are read in place from the mapped file, not copied:
`lsu_bags.bags.read_message_views`); the nodes are the ones of the launch file,
with its parameters, and they still publish what they publish live (``stereo/*/laser_line``
while someone subscribes, ``points`` per snap, ``scan/cloud``, ``/diagnostics``), so
subscribers see the same outputs. Their input subscriptions are removed: nothing arrives twice.
Replaying into a graph of separate nodes is `lsu bag play` into `lsu launch replay` (or
`lsu run replay` without a bag): the message path.

Hand-written because this is the integration of our own two nodes; the bag is read with
`rosbags` (lsu_bags.bags) and the extraction/matching are the nodes' own methods.
"""

from __future__ import annotations

import collections
import itertools
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

from lsu_bags.bags import bag_topics, read_message_views
from lsu_common import stamps
from lsu_common.read_ahead import read_ahead

__all__ = ["DirectReplay", "ReplayStats", "run_direct_replay"]

SIDES = ("left", "right")
SPIN_EVERY_S = 0.05  # timers and the other nodes' callbacks run at least this often during a replay
PREFETCH = 8  # bag messages read ahead (about 4 image pairs, ~8 MB)


@dataclass
class ReplayStats:
    """What one replay did: counts, wall and CPU time (CPU of the whole process, all threads)."""

    images: int = 0
    events: int = 0
    snap_events: int = 0
    pairs: int = 0              # image (or line) pairs matched, the laser-off texture pair included
    snaps: int = 0              # SNAP events whose pair was matched
    sweep_frames: int = 0       # pairs the sweeps' streams published (their SWEEP_END events)
    frames_dropped: int = 0     # images the extractor could not read
    lines_unpaired: int = 0     # lines that never found their partner (same stamp)
    seconds: float = 0.0
    cpu_s: float = 0.0          # the whole process, all threads
    read_cpu_s: float = 0.0     # of which the thread reading (and decompressing) the bag

    def summary(self, bag: Path) -> str:
        done = self.snaps + self.sweep_frames  # a sweep's frames are its snaps
        rate = done / self.seconds if self.seconds > 0 else 0.0
        cpu = 1000.0 * self.cpu_s / max(1, done)
        read = 1000.0 * self.read_cpu_s / max(1, done)
        sweep = f", {self.sweep_frames} sweep frames" if self.sweep_frames else ""
        return (f"replayed {bag}: {self.snaps} snaps ({self.snap_events} SNAP events, {self.pairs} pairs){sweep} in "
                f"{self.seconds:.2f} s, {rate:.0f} snaps/s, {cpu:.2f} ms CPU per snap ({read:.2f} ms of it reading "
                f"the bag); {self.frames_dropped} frames unreadable, "
                f"{self.lines_unpaired} lines unpaired")


def _side(topic: str, suffix: str) -> str | None:
    for side in SIDES:
        if topic.endswith(f"stereo/{side}/{suffix}"):
            return side
    return None


class DirectReplay:
    """Feeds a bag to an extractor and a matcher node of this process (see the module doc).

    ``nodes``: the nodes built from a launch file; one ``laser_extractor`` (LaserExtractorNode)
    and one ``stereo_matcher`` (StereoMatcherNode) must be among them.
    """

    def __init__(self, nodes: Sequence[Any]) -> None:
        from lsu_extract.node import LaserExtractorNode
        from lsu_reconstruct.node import IMAGES_KEPT, StereoMatcherNode

        extractors = [n for n in nodes if isinstance(n, LaserExtractorNode)]
        matchers = [n for n in nodes if isinstance(n, StereoMatcherNode)]
        if len(extractors) != 1 or len(matchers) != 1:
            raise LookupError(f"replaying a bag needs one laser_extractor and one stereo_matcher in the launch file "
                              f"(found {len(extractors)} and {len(matchers)}); use the 'replay' launch file, or play "
                              f"the bag into your graph with `lsu bag play`")
        self.extractor, self.matcher = extractors[0], matchers[0]
        # the replay is their only input: lines published for subscribers must not come back to the matcher
        for sub in list(self.extractor.subscriptions_):
            self.extractor.destroy_subscription(sub)
        for sub in list(self.matcher.input_subscriptions):
            self.matcher.destroy_subscription(sub)
        self._left_images: collections.deque[Any] = collections.deque(maxlen=IMAGES_KEPT)
        self.matcher.take_left_images = self._take_left_images

    def _take_left_images(self) -> list[Any]:
        taken = list(self._left_images)
        self._left_images.clear()
        return taken

    def run(self, bag: Path | str, spin: Callable[[], None] = lambda: None) -> ReplayStats:
        """Process every scan event and image pair of ``bag`` in recorded order; ``spin`` runs the executor once.

        Raises:
            lsu_bags.bags.BagError: the bag is missing, corrupt, or holds neither images nor laser lines.
        """
        from rclpy.serialization import deserialize_message
        from sensor_msgs.msg import CameraInfo

        from lsu_bags.bags import BagError
        from lsu_extract.node import line_fields, result_to_msg
        from lsu_interfaces.msg import CarriagePosition, LaserLine, ScanEvent, StereoExposure, StereoExtrinsics
        from lsu_reconstruct.matching import LineArrays

        topics = bag_topics(bag)
        images = {t: side for t in topics if (side := _side(t, "image_raw")) is not None}
        lines = {t: side for t in topics if (side := _side(t, "laser_line")) is not None}
        if images:
            lines = {}  # the lines are made again from the images, as the live graph would
        elif not lines:
            raise BagError(f"bag {bag} holds neither stereo/{{left,right}}/image_raw nor stereo/{{left,right}}/"
                           f"laser_line (it has: {', '.join(sorted(topics)) or 'no topics'})")
        events = [t for t in topics if t.endswith("scan/events")]
        # a sweep's frames are placed by the pairs' exposures and the driver's stamped carriage positions
        sweep_inputs = [t for t in topics if t.endswith(("stereo/exposure", "driver/carriage"))]
        calibration = []
        if str(self.matcher.get_parameter("calibration_source").value) == "topics":
            calibration = [t for t in topics if _side(t, "camera_info") or t.endswith("stereo/extrinsics")]
        extractor, matcher = self.extractor, self.matcher
        publishers = extractor.publishers_
        stats = ReplayStats()
        pairs_before = matcher.pairs
        lines_of: dict[int, int] = collections.Counter()  # stamp -> lines handed to the matcher
        reading: dict[str, float] = {"producer_s": 0.0}
        # the images reach the extractor as views of the mapped bag file, not copies (read_message_views);
        # the bag's reading (and a compressed bag's zstd decompression, which releases the GIL) runs on the
        # other core while this one extracts and matches
        messages = read_ahead(read_message_views(bag, [*images, *lines, *events, *sweep_inputs, *calibration]),
                              PREFETCH, "bag-reader", reading)
        first = next(messages, None)  # the window starts at the first message: opening the bag is start-up
        t0, cpu0, read0 = time.monotonic(), time.process_time(), reading["producer_s"]
        next_spin = t0 + SPIN_EVERY_S
        for m in itertools.chain([first] if first is not None else [], messages):
            side = images.get(m.topic)
            if side is not None:
                stats.images += 1
                if side == "left":
                    self._left_images.append(m.data)  # the texture is looked for among these
                extracted = extractor.extract_of(side, m.data)
                if extracted is not None:
                    # the arrays go to the matcher as they are: a LaserLine message only for subscribers
                    header, result = extracted
                    if publishers[side].get_subscription_count():
                        publishers[side].publish(result_to_msg(result, header))
                    lines_of[stamps.to_ns(header.stamp)] += 1
                    matcher.on_line_arrays(side, header, LineArrays(**line_fields(result), image_width=result.image_width,
                                                                    image_height=result.image_height))
            elif m.topic in lines:
                line = deserialize_message(bytes(m.data), LaserLine)
                lines_of[stamps.to_ns(line.header.stamp)] += 1
                matcher.on_line(lines[m.topic], line)
            elif m.topic in events:
                event = deserialize_message(bytes(m.data), ScanEvent)
                stats.events += 1
                if event.type == ScanEvent.SNAP:
                    stats.snap_events += 1
                    key = stamps.to_ns(event.image_stamp)
                    stats.snaps += lines_of[key] >= 2
                elif event.type == ScanEvent.SWEEP_END:
                    stats.sweep_frames += int(event.snaps_captured)
                extractor.on_event(event)
                matcher.on_event(event)
            elif m.topic.endswith("stereo/exposure"):
                matcher.on_exposure(deserialize_message(bytes(m.data), StereoExposure))
            elif m.topic.endswith("driver/carriage"):
                matcher.on_carriage(deserialize_message(bytes(m.data), CarriagePosition))
            elif m.topic.endswith("extrinsics"):
                matcher.on_extrinsics(deserialize_message(bytes(m.data), StereoExtrinsics))
            elif (side := _side(m.topic, "camera_info")) is not None:
                matcher.on_info(side, deserialize_message(bytes(m.data), CameraInfo))
            if time.monotonic() >= next_spin:
                spin()
                next_spin = time.monotonic() + SPIN_EVERY_S
        matcher._check_scan_end()  # a complete scan is published now, not at the matcher's next timer
        stats.seconds = time.monotonic() - t0
        stats.cpu_s = time.process_time() - cpu0
        stats.read_cpu_s = reading["producer_s"] - read0
        stats.pairs = matcher.pairs - pairs_before
        stats.frames_dropped = sum(extractor.dropped.values())
        stats.lines_unpaired = sum(matcher.unmatched.values()) + len(matcher.left) + len(matcher.right)
        return stats

    def scan_pending(self) -> bool:
        """A scan ended (FINISHED/ABORTED) whose cloud the matcher has not published yet (it waits for snaps)."""
        scan = self.matcher.scan
        return scan is not None and scan.end_type is not None and not scan.published


def run_direct_replay(description: Any, bag: Path, out: TextIO = sys.stdout, exit_when_done: bool = False) -> int:
    """Build the launch file's nodes, replay ``bag`` through them directly, then spin until Ctrl-C.

    With ``exit_when_done`` it returns once the bag is processed and a pending scan cloud is
    published (at most the matcher's scan_timeout_s later). One thread: the replay calls into
    the nodes between the executor's turns.
    """
    from lsu_bags.bags import BagError

    from .runner import spinning_nodes

    if not Path(bag).exists():
        raise FileNotFoundError(f"bag '{bag}' not found: give a bag folder (or its .mcap/.db3 file)")
    with spinning_nodes(description, out, "single") as (nodes, spinner):
        replay = DirectReplay(nodes)
        out.write(f"[lsu run] replaying {bag} directly into laser_extractor and stereo_matcher "
                  f"({len(nodes)} node(s) in one process)\n")
        out.flush()
        spinner.spin_once(timeout_sec=0.0)
        try:
            stats = replay.run(bag, spin=lambda: spinner.spin_once(timeout_sec=0.0))
        except BagError as exc:
            out.write(f"[lsu run] error: {exc}\n")
            return 2
        out.write(f"[lsu run] {stats.summary(Path(bag))}\n")
        out.flush()
        if exit_when_done:
            timeout = float(replay.matcher.get_parameter("scan_timeout_s").value) + 1.0
            deadline = time.monotonic() + timeout
            while replay.scan_pending() and time.monotonic() < deadline:
                spinner.spin_once(timeout_sec=0.05)
            spinner.spin_once(timeout_sec=0.0)
        else:
            out.write("[lsu run] replay done; the nodes keep running (Ctrl-C stops)\n")
            out.flush()
            spinner.spin()
    out.write("[lsu run] stopped\n")
    return 0

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

With ``workers`` (`lsu run replay BAG --workers N`), the extraction runs in N processes of
its own while this one matches: an uncompressed bag is mapped by each of them, and each runs the
extractor's frame logic (`lsu_extract.frames.FrameExtractor`: sizes, the laser-off background)
over every frame and event, so that all hold the same state. Each image goes to whichever is
expected to have it first, a process or this process's own extractor node (decided a few images
ahead from the lines each process has yet to send and this process's CPU per image, and sent to
the processes): the matching and the extraction share the cores without a fixed split or waits
for a line, and fewer processes than one per core plus this one contend for them. OpenCV runs on
one thread in every process: the processes are the parallelism. The lines come back in the bag's
order and the matcher sees exactly the calls of the one-process replay: the same points, bit for
bit, for stop-snap scans and sweeps alike. Meanwhile the extractor's parameters are those the
replay started with (changes are refused until it ends).

Hand-written because this is the integration of our own two nodes; the bag is read with
`rosbags` (lsu_bags.bags) and the extraction/matching are the nodes' own methods.
"""

from __future__ import annotations

import collections
import itertools
import multiprocessing
import os
import sys
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, TextIO

from lsu_bags.bags import bag_topics, read_message_views
from lsu_common import stamps
from lsu_common.read_ahead import read_ahead
from lsu_extract.frames import SIDES

__all__ = ["DirectReplay", "ReplayStats", "default_workers", "run_direct_replay"]

SPIN_EVERY_S = 0.05  # timers and the other nodes' callbacks run at least this often during a replay
PREFETCH = 8  # bag messages read ahead (about 4 image pairs, ~8 MB)
PIPE_BYTES = 1 << 20  # the lines an extraction process may send ahead (`_widen`)
WORKER_START_S = 60.0  # an extraction process that has not started by then is reported
OWN = 255  # an image's place (one byte): the replay's own process; 0..254: an extraction process
AHEAD = 16  # images whose place is decided before the replay reaches them
MAX_WORKERS = 4  # every process follows every frame and event: each one added costs that much CPU again
# where the replay places an image (`_ExtractionProcesses._choose`): its CPU per image, extracting one and the
# rest of its work, as first guesses (a 640x480 frame, two per snap) and then smoothed over ~16 images
EXTRACT_S, OTHER_S, SMOOTHING = 2e-3, 0.5e-3, 1.0 / 16.0


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
    seconds: float = 0.0        # without the turns of the executor (`spin_s`)
    cpu_s: float = 0.0          # the whole process, all threads (and the extraction processes), without `spin_s`'s
    spin_s: float = 0.0         # the executor's turns during the replay: other nodes' callbacks (a face processor
    #                             meshing the scan cloud), not the replay's work
    read_cpu_s: float = 0.0     # of which the thread reading (and decompressing) the bag
    workers: int = 0            # extraction processes (0: extracted in this process)
    workers_start_s: float = 0.0  # their start-up (before the timed window, like the nodes' construction)
    extracted_here: int = 0     # with extraction processes: the images this process extracted in their place

    def summary(self, bag: Path) -> str:
        done = self.snaps + self.sweep_frames  # a sweep's frames are its snaps
        rate = done / self.seconds if self.seconds > 0 else 0.0
        cpu = 1000.0 * self.cpu_s / max(1, done)
        read = 1000.0 * self.read_cpu_s / max(1, done)
        sweep = f", {self.sweep_frames} sweep frames" if self.sweep_frames else ""
        return (f"replayed {bag}: {self.snaps} snaps ({self.snap_events} SNAP events, {self.pairs} pairs){sweep} in "
                f"{self.seconds:.2f} s, {rate:.0f} snaps/s, {cpu:.2f} ms CPU per snap ({read:.2f} ms of it reading "
                f"the bag); {self.frames_dropped} frames unreadable, "
                f"{self.lines_unpaired} lines unpaired" +
                (f"; {self.spin_s:.2f} s of other callbacks during it not counted" if self.spin_s >= 0.005 else "") +
                (f"; extracted in {self.workers} processes (started in {self.workers_start_s:.2f} s, their CPU "
                 f"counted) and {self.extracted_here} of {self.images} images here" if self.workers else ""))


def default_workers() -> int:
    """Extraction processes of `lsu run replay BAG`: one per core beside the replay's own (which matches, and
    extracts what they leave), at most ``MAX_WORKERS``; none on a single core."""
    return max(0, min((os.cpu_count() or 1) - 1, MAX_WORKERS))


def _timed(items: Iterator[Any], cpu: dict[str, float]) -> Iterator[Any]:
    """``items``, with the CPU time of making them added to ``cpu["producer_s"]`` (as `read_ahead` counts it)."""
    while True:
        c0 = time.thread_time()
        item = next(items, None)
        cpu["producer_s"] += time.thread_time() - c0
        if item is None:
            return
        yield item


def _side(topic: str, suffix: str) -> str | None:
    for side in SIDES:
        if topic.endswith(f"stereo/{side}/{suffix}"):
            return side
    return None



def _extract_share(out: Any, places: Any, bag: str, images: dict[str, str], events: list[str],
                   params: dict[str, Any], background: str, index: int) -> None:
    """An extraction process: every frame and event of ``bag`` through a FrameExtractor; image n extracted
    and sent on ``out`` (in order) where the n-th byte read from ``places`` (a pipe, written by the replay
    ahead of its reading) is ``index`` (see the module doc)."""
    try:
        from lsu_extract.extractor import ExtractorParams, one_opencv_thread
        from lsu_extract.frames import FrameExtractor
        from lsu_extract.image import ImageFormatError

        one_opencv_thread()
        core = FrameExtractor(ExtractorParams(**params), background, copy_frames=False)  # the mapped file stays
        deserialize = None
        if background == "texture":
            from rclpy.serialization import deserialize_message

            from lsu_extract.node import follow_scan_event
            from lsu_interfaces.msg import ScanEvent

            deserialize = deserialize_message
        messages = read_message_views(bag, [*images, *(events if deserialize is not None else [])])
        first = next(messages, None)  # opening the bag is start-up, as for the replay's own reading
        out.send(("ready", time.process_time()))
        placed = bytearray()
        n = 0
        for m in itertools.chain([first] if first is not None else [], messages):
            side = images.get(m.topic)
            if side is None:
                assert deserialize is not None
                follow_scan_event(core, deserialize(bytes(m.data), ScanEvent))
                continue
            while len(placed) <= n:
                chunk = os.read(places.fileno(), 4096)
                if not chunk:
                    raise RuntimeError("the replay closed the image places before the last image")
                placed += chunk
            mine = placed[n] == index
            n += 1
            try:
                msg, result = core.extract(side, m.data, compute=mine)
            except ImageFormatError as exc:
                if mine:
                    out.send(("bad", str(exc)))
                continue
            if mine:
                out.send(("line", (msg.sec, msg.nanosec, msg.frame_id), result))
        out.send(("done", time.process_time()))
    except BaseException:  # noqa: BLE001 - handed to the replay, which raises it
        try:
            out.send(("error", traceback.format_exc()))
        except OSError:
            pass  # the replay has stopped reading (it failed or was interrupted itself)
    finally:
        out.close()


def _widen(pipe: Any) -> None:
    """Let a pipe hold ~50 lines (Linux: 1 MB, the default limit for a user): a process that runs ahead in
    longer bursts, rather than in turns of a few lines with a wake-up between, which a loaded host delays."""
    import fcntl

    try:
        fcntl.fcntl(pipe.fileno(), getattr(fcntl, "F_SETPIPE_SZ", 1031), PIPE_BYTES)
    except OSError:
        pass  # a smaller limit: the default size works, in shorter bursts


class _ExtractionProcesses:
    """``count`` processes running `_extract_share` on one bag, and the replay's extractor node beside them;
    `next` gives each image's outcome in bag order.

    Where image n is extracted is decided ``AHEAD`` images before the replay reaches it, and sent to every
    process (`_choose`): to whichever is expected to have it first, the replay's own process (``OWN``)
    when it would reach the image before any process had extracted it. That estimate counts each process's
    placed images it has not sent yet and the images the replay has to take before n, its own ones and its
    other work for each (matching, reading), at the CPU per image the replay measures for both. So the
    replay extracts what the processes cannot keep up with, without waiting for a line to find out, and on a
    host with as many cores as processes the two kinds of work balance without a fixed share. Every image's
    line is the same wherever it is extracted: each process, and the node, follows every frame and event
    (`FrameExtractor`).
    """

    def __init__(self, bag: Path | str, images: dict[str, str], events: list[str], extractor: Any, count: int) -> None:
        if not 0 < count < OWN:
            raise ValueError(f"{count} extraction processes: give 1 to {OWN - 1} (or 0 to extract in this process)")
        context = multiprocessing.get_context("spawn")  # not fork: this process runs DDS threads
        self.count, self.taken, self.own = count, 0, 0
        self.extractor = extractor
        self.inputs: list[Any] = []
        self.places: list[Any] = []  # write ends of the processes' place pipes (None: the process has ended)
        self.processes: list[Any] = []
        self.ready: list[collections.deque[tuple[Any, ...]]] = [collections.deque() for _ in range(count)]  # lines
        self.done: list[tuple[Any, ...] | None] = [None] * count  # a process's last message, read with its lines
        self.decided = bytearray(index % count for index in range(AHEAD))
        self.placed = [self.decided.count(index) for index in range(count)]  # placed and not yet taken
        self.own_placed = 0
        # the replay's CPU per image (thread clock): extracting one, and the rest of its work per image
        self.extract_s, self.other_s = EXTRACT_S, OTHER_S
        self._mark: float | None = None  # thread clock when the last image was taken ...
        self._extracting = 0.0  # ... and how much of the time since it spent extracting it
        t0 = time.monotonic()
        for index in range(count):
            reader, writer = context.Pipe(duplex=False)
            _widen(reader)
            # the places go down a pipe as raw bytes (its descriptor), one per image, without message framing
            place_reader, place_writer = context.Pipe(duplex=False)
            process = context.Process(
                target=_extract_share, name=f"lsu-replay-extract-{index}", daemon=True,
                args=(writer, place_reader, str(bag), images, events, asdict(extractor.params), extractor.background,
                      index))
            process.start()
            writer.close()
            place_reader.close()
            os.write(place_writer.fileno(), bytes(self.decided))
            self.inputs.append(reader)
            self.places.append(place_writer)
            self.processes.append(process)
        self.cpu_at_start = [float(self._receive(i, "ready", WORKER_START_S)[1]) for i in range(count)]
        self.start_s = time.monotonic() - t0

    def _receive(self, index: int, kind: str, timeout_s: float | None = None, done: bool = False) -> tuple[Any, ...]:
        """The next message of process ``index``, of ``kind`` (a line may be "bad"; ``done``: or "done")."""
        reader = self.inputs[index]
        if timeout_s is not None and not reader.poll(timeout_s):
            raise RuntimeError(f"extraction process {index} did not start within {timeout_s:.0f} s; replay with "
                               "--workers 0 to extract in this process")
        try:
            item = reader.recv()
        except EOFError:
            raise RuntimeError(f"extraction process {index} ended unexpectedly (exit code "
                               f"{self.processes[index].exitcode}); replay with --workers 0 to extract in this "
                               "process") from None
        if item[0] == "error":
            raise RuntimeError(f"extraction process {index} failed:\n{item[1]}")
        if item[0] != kind and not (kind == "line" and (item[0] == "bad" or (done and item[0] == "done"))):
            raise RuntimeError(f"extraction process {index} sent '{item[0]}' where '{kind}' was due")
        return tuple(item)

    def next(self, side: str, raw: Any) -> tuple[Any, Any] | None:
        """The next image's (header, LaserLineResult), counted by the extractor node; None: unreadable (reported).

        ``raw``: the image's buffer, which the extractor node follows (or extracts, in its turns) itself.
        """
        from lsu_extract.image import ImageFormatError

        now = time.thread_time()
        if self._mark is not None:  # all the replay did for the last image but extract it: matching, reading, ...
            self.other_s += SMOOTHING * (now - self._mark - self._extracting - self.other_s)
        self._mark, self._extracting = now, 0.0
        place = self.decided[self.taken]
        self.taken += 1
        if place == OWN:
            self.own += 1
            self.own_placed -= 1
            extracted = self.extractor.extract_of(side, raw)
            self._extracting = time.thread_time() - now
            self.extract_s += SMOOTHING * (self._extracting - self.extract_s)
        else:
            try:  # the node's frame state follows every image, as each process's does
                self.extractor.core.extract(side, raw, compute=False)
            except ImageFormatError:
                pass  # reported by the process that extracts it
            self.placed[place] -= 1
            item = self.ready[place].popleft() if self.ready[place] else self._receive(place, "line")
            extracted = self._line(side, item)
        self._decide(self._choose())
        return extracted

    def _choose(self) -> int:
        """The place of the image ``AHEAD - 1`` after the next one: whichever is expected to have it first.

        A process has it once it has extracted its placed images that are not sent yet, then this one; the
        replay reaches it after its own placed images and its other work for each image before it.
        """
        for index in range(self.count):  # the lines already sent, so that they count as done
            reader, ready = self.inputs[index], self.ready[index]
            while len(ready) < self.placed[index] and self.done[index] is None and reader.poll(0):
                item = self._receive(index, "line", done=True)
                if item[0] == "done":  # past the bag's last image: places are written ahead of the images
                    self.done[index] = item
                else:
                    ready.append(item)
        best, soonest = OWN, self.own_placed * self.extract_s + (AHEAD - 1) * self.other_s
        for index in range(self.count):
            at = (self.placed[index] - len(self.ready[index]) + 1) * self.extract_s
            if at <= soonest:  # a process before the replay when even: its core has nothing else to do
                best, soonest = index, at
        return best

    def _line(self, side: str, item: tuple[Any, ...]) -> tuple[Any, Any] | None:
        if item[0] == "bad":
            self.extractor.frame_dropped(side, item[1])
            return None
        sec, nanosec, frame_id = item[1]
        return self.extractor.frame_extracted(side, sec, nanosec, frame_id), item[2]

    def _decide(self, place: int) -> None:
        """Image ``taken + AHEAD - 1`` is extracted at ``place`` (a process, or ``OWN``): tell every process."""
        self.decided.append(place)
        if place == OWN:
            self.own_placed += 1
        else:
            self.placed[place] += 1
        for index, writer in enumerate(self.places):
            if writer is None:
                continue
            try:
                os.write(writer.fileno(), bytes((place,)))
            except BrokenPipeError:
                # The process has ended: past the bag's last image (places are written ahead of the images), or
                # failed, which its next line due, or `finish`, reports from its own message.
                writer.close()
                self.places[index] = None

    def finish(self) -> float:
        """Wait for every process to end; their CPU seconds since they were ready."""
        cpu = sum(float((self.done[i] or self._receive(i, "done"))[1]) - self.cpu_at_start[i] for i in range(self.count))
        self.close()
        return cpu

    def close(self) -> None:
        for writer in self.places:
            if writer is not None:
                writer.close()
        self.places = []
        for reader in self.inputs:
            reader.close()
        for process in self.processes:
            process.join(timeout=5.0)
            if process.is_alive():  # left early (an error here): it may be blocked writing to its pipe
                process.terminate()
                process.join(timeout=5.0)


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

    def run(self, bag: Path | str, spin: Callable[[], None] = lambda: None, workers: int = 0) -> ReplayStats:
        """Process every scan event and image pair of ``bag`` in recorded order; ``spin`` runs the executor once.

        ``workers``: extract in that many processes of their own (module doc) where the bag is read in
        place (one uncompressed MCAP file); 0, or any other bag: in this process.

        Raises:
            lsu_bags.bags.BagError: the bag is missing, corrupt, or holds neither images nor laser lines.
            RuntimeError: an extraction process failed or ended (``workers``).
        """
        from lsu_bags.bags import BagError

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
        stats = ReplayStats()
        pairs_before = matcher.pairs
        lines_of: dict[int, int] = collections.Counter()  # stamp -> lines handed to the matcher
        reading: dict[str, float] = {"producer_s": 0.0}
        # the images reach the extractor as views of the mapped bag file, not copies (read_message_views)
        source = read_message_views(bag, [*images, *lines, *events, *sweep_inputs, *calibration])
        first = next(source, None)  # the window starts at the first message: opening the bag is start-up
        pool = None
        # each process maps the file: with copies (a compressed bag) every one would decompress it all
        if workers > 0 and images and first is not None and isinstance(first.data, memoryview):
            pool = _ExtractionProcesses(bag, images, events, extractor, workers)
            stats.workers, stats.workers_start_s = workers, pool.start_s
            extractor.frozen_reason = (f"a replay extracts in {workers} processes with the parameters it started "
                                       "with; set them before it (launch arguments), or replay with --workers 0")
            # the extraction processes have the other cores, and views cost little to read: read here, with
            # no hand-off between threads
            messages: Iterator[Any] = _timed(source, reading)
        else:
            # the bag's reading (and a compressed bag's zstd decompression, which releases the GIL) runs on
            # the other core while this one extracts and matches
            messages = read_ahead(source, PREFETCH, "bag-reader", reading)
        # the bag's buffers stay as they are (views of the mapped file, or bytes of their own), unlike a
        # subscription's, which is reused: the laser-off background keeps them without a copy
        copying, extractor.core.copy_frames = extractor.core.copy_frames, False
        matcher.prepare_scan_cloud()  # a library's import is start-up, as the live node's at its scan's start
        try:
            t0, cpu0, read0 = time.monotonic(), time.process_time(), reading["producer_s"]
            spin_cpu = [0.0]
            self._replay(first, messages, pool, spin, images, lines, events, stats, lines_of, spin_cpu)
            matcher._check_scan_end()  # a complete scan is published now, not at the matcher's next timer
            stats.seconds = time.monotonic() - t0 - stats.spin_s
            stats.cpu_s = time.process_time() - cpu0 - spin_cpu[0] + (pool.finish() if pool is not None else 0.0)
            stats.extracted_here = pool.own if pool is not None else 0
            stats.read_cpu_s = reading["producer_s"] - read0
        finally:
            extractor.core.copy_frames = copying
            if pool is not None:
                pool.close()
                extractor.frozen_reason = None
        stats.pairs = matcher.pairs - pairs_before
        stats.frames_dropped = sum(extractor.dropped.values())
        stats.lines_unpaired = sum(matcher.unmatched.values()) + len(matcher.left) + len(matcher.right)
        return stats

    def _replay(self, first: Any, messages: Any, pool: _ExtractionProcesses | None, spin: Callable[[], None],
                images: dict[str, str], lines: dict[str, str], events: list[str], stats: ReplayStats,
                lines_of: dict[int, int], spin_cpu: list[float]) -> None:
        """The loop of `run` over the bag's messages (``first`` and the rest); the executor's turns are timed
        (``stats.spin_s``, ``spin_cpu[0]``)."""
        from rclpy.serialization import deserialize_message
        from sensor_msgs.msg import CameraInfo

        from lsu_extract.node import line_fields, result_to_msg
        from lsu_interfaces.msg import CarriagePosition, LaserLine, ScanEvent, StereoExposure, StereoExtrinsics
        from lsu_reconstruct.matching import LineArrays

        extractor, matcher = self.extractor, self.matcher
        publishers = extractor.publishers_
        next_spin = time.monotonic() + SPIN_EVERY_S
        carriage_held: Any = None  # the newest carriage position not handed over (`sweep_inputs_wanted`)
        for m in itertools.chain([first] if first is not None else [], messages):
            side = images.get(m.topic)
            if side is not None:
                stats.images += 1
                if side == "left":
                    self._left_images.append(m.data)  # the texture is looked for among these
                extracted = extractor.extract_of(side, m.data) if pool is None else pool.next(side, m.data)
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
                if carriage_held is not None and matcher.sweep_inputs_wanted():
                    matcher.on_carriage(deserialize_message(bytes(carriage_held), CarriagePosition))
                    carriage_held = None
            elif m.topic.endswith("stereo/exposure"):
                if matcher.sweep_inputs_wanted():  # a stop-snap scan's exposures serve no sweep: not decoded
                    matcher.on_exposure(deserialize_message(bytes(m.data), StereoExposure))
            elif m.topic.endswith("driver/carriage"):
                if matcher.sweep_inputs_wanted():
                    matcher.on_carriage(deserialize_message(bytes(m.data), CarriagePosition))
                else:  # during a stop-snap scan only the last position is handed over, once the scan has ended
                    carriage_held = m.data
            elif m.topic.endswith("extrinsics"):
                matcher.on_extrinsics(deserialize_message(bytes(m.data), StereoExtrinsics))
            elif (side := _side(m.topic, "camera_info")) is not None:
                matcher.on_info(side, deserialize_message(bytes(m.data), CameraInfo))
            if time.monotonic() >= next_spin:
                t0, cpu0 = time.monotonic(), time.process_time()
                spin()
                next_spin = time.monotonic() + SPIN_EVERY_S
                stats.spin_s += next_spin - SPIN_EVERY_S - t0
                spin_cpu[0] += time.process_time() - cpu0

    def scan_pending(self) -> bool:
        """A scan ended (FINISHED/ABORTED) whose cloud the matcher has not published yet (it waits for snaps)."""
        scan = self.matcher.scan
        return scan is not None and scan.end_type is not None and not scan.published


def run_direct_replay(description: Any, bag: Path, out: TextIO | None = None, exit_when_done: bool = False,
                      workers: int = 0) -> int:
    """Build the launch file's nodes, replay ``bag`` through them directly, then spin until Ctrl-C.

    With ``exit_when_done`` it returns once the bag is processed and a pending scan cloud is
    published (at most the matcher's scan_timeout_s later). One thread: the replay calls into
    the nodes between the executor's turns; ``workers``: extraction processes (`DirectReplay.run`).
    """
    out = sys.stdout if out is None else out
    from lsu_bags.bags import BagError
    from lsu_common.node import spin_until_shutdown

    from .runner import spinning_nodes

    if not Path(bag).exists():
        raise FileNotFoundError(f"bag '{bag}' not found: give a bag folder (or its .mcap/.db3 file)")
    from lsu_extract.extractor import one_opencv_thread

    one_opencv_thread()  # this process extracts too, beside its extraction processes
    with spinning_nodes(description, out, "single") as (nodes, spinner):
        replay = DirectReplay(nodes)
        out.write(f"[lsu run] replaying {bag} directly into laser_extractor and stereo_matcher "
                  f"({len(nodes)} node(s) in one process)\n")
        out.flush()
        spinner.spin_once(timeout_sec=0.0)
        try:
            stats = replay.run(bag, spin=lambda: spinner.spin_once(timeout_sec=0.0), workers=workers)
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
            spin_until_shutdown(spinner)
    out.write("[lsu run] stopped\n")
    return 0

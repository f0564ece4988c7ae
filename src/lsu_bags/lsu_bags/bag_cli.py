"""`lsu bag record|play|info`: rosbag2 recording and playback on the rclpy graph.

Serialized CDR travels untouched: the recorder subscribes with ``raw=True`` (its callback
gets the bytes) and the player publishes ``bytes``; nothing is deserialized on the way.
The file side (typestore, metadata, reading, writing) is :mod:`lsu_bags.bags`.

Python API (usable inside any node/process, e.g. by the scan coordinator or a test):

- ``BagRecorder(node, ["/lsu/scan/events"], out_dir, "mcap")`` records on ``node``'s
  executor until ``close()``.
- ``BagPlayer(node, bag_dir, rate=1.0).play(stop_event)`` publishes a bag with its timing.
"""

from __future__ import annotations

import argparse
import re
import shutil
import signal
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from lsu_common import stamps

from . import bags
from .bags import BagError, UnknownTypeError

#: topics `--all` leaves out: every node's log and parameter chatter (rosbag2 users exclude them too)
ALWAYS_EXCLUDED = ("/rosout", "/parameter_events")
#: history depth of the recorder's subscriptions: deep enough for scan bursts, bounded so a slow
#: disk makes the recorder drop instead of back-pressuring the live graph
RECORD_DEPTH = 1000
#: extra wait after late subscribers matched our publishers (see BagPlayer.wait_for_subscribers)
MATCH_GRACE_S = 0.3


def _hidden(topic: str) -> bool:
    """ROS hides names with a segment starting with '_' (action internals, CLI helper nodes)."""
    return any(part.startswith("_") for part in topic.split("/") if part)


def rosbags_qos(profile: Any) -> Any:
    """An rclpy QoSProfile (as discovered on the graph) as the rosbags Qos stored in metadata."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    def enum(target: Any, policy: Any) -> Any:
        return target.__members__.get(policy.name.upper(), target.UNKNOWN)

    def duration(d: Any) -> Any:
        ns = int(d.nanoseconds)
        # rmw reports "infinite" as INT64_MAX ns; rosbag2 stores it as (9223372036, 854775807)
        return bags.INFINITE_TIME if ns >= 2**63 - 1 else QosTime(*stamps.split_ns(ns))

    return Qos(enum(QosHistory, profile.history), int(profile.depth), enum(QosReliability, profile.reliability),
               enum(QosDurability, profile.durability), duration(profile.deadline), duration(profile.lifespan),
               enum(QosLiveliness, profile.liveliness), duration(profile.liveliness_lease_duration),
               bool(profile.avoid_ros_namespace_conventions))


def rclpy_qos(play: bags.PlaybackQos) -> Any:
    """The rclpy QoSProfile of a :class:`bags.PlaybackQos`."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(
        history=HistoryPolicy.KEEP_ALL if play.keep_all else HistoryPolicy.KEEP_LAST, depth=max(1, play.depth),
        reliability=ReliabilityPolicy.RELIABLE if play.reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if play.transient_local else DurabilityPolicy.VOLATILE)


def _message_class(topic: str, msgtype: str) -> type:
    from .rosmsg import InterfaceError, get_interface

    try:
        return get_interface(msgtype, "msg")
    except InterfaceError as exc:
        raise UnknownTypeError(f"topic '{topic}' has type '{msgtype}', which this Python cannot load ({exc}); "
                               f"install that interface package or leave the topic out (--exclude {topic})") from None


# --------------------------------------------------------------------------- recorder
class BagRecorder:
    """Records topics of the graph ``node`` lives on into a new rosbag2 folder.

    Types come from the graph (``get_topic_names_and_types``), which a timer polls every
    ``poll_s`` so topics that appear later are picked up (all of them with ``all_topics``;
    with explicit ``topics`` those not there yet are waited for). Each topic's publisher
    QoS profiles go into metadata. Errors on a topic the caller named (unknown type) stop
    the recording: :attr:`failure` is set and ``on_failure`` called; with ``all_topics`` such
    topics are skipped with a warning. Call :meth:`close` to finalise the bag.
    """

    def __init__(self, node: Any, topics: Sequence[str] | None, out_dir: Path | str, storage: str = "mcap", *,
                 compress: bool = False, all_topics: bool = False, exclude: str | None = None,
                 types: bags.BagTypes | None = None, poll_s: float = 0.5,
                 log: Callable[[str], None] | None = None,
                 on_failure: Callable[[BagError], None] | None = None) -> None:
        if not topics and not all_topics:
            raise BagError("nothing to record: name topics or use --all")
        self.node = node
        self.all_topics = all_topics
        self.wanted: set[str] = {node.resolve_topic_name(t) for t in (topics or ())}
        try:
            self.exclude = re.compile(exclude) if exclude else None
        except re.error as exc:
            raise BagError(f"--exclude '{exclude}' is not a regular expression: {exc}") from None
        self.log = log or (lambda text: node.get_logger().info(text))
        self.on_failure = on_failure
        self.failure: BagError | None = None
        self.writer = bags.BagWriter(out_dir, storage, compress=compress, types=types)
        self._subscriptions: dict[str, Any] = {}
        self._skipped: set[str] = set()
        self._closed = False
        self._lock = threading.Lock()
        self._started = time.monotonic()
        self._waiting_noted = False
        self._timer = node.create_timer(poll_s, self.poll_graph)
        self.poll_graph()

    @property
    def path(self) -> Path:
        """The bag folder."""
        return self.writer.path

    @property
    def counts(self) -> dict[str, int]:
        """Messages written per topic so far."""
        return dict(self.writer.counts)

    @property
    def recording(self) -> dict[str, str]:
        """Topic -> type of every topic being recorded."""
        return self.writer.topics

    def _selected(self, name: str) -> bool:
        if name in self.wanted:
            return True
        if not self.all_topics or name in ALWAYS_EXCLUDED or _hidden(name):
            return False
        return not (self.exclude and self.exclude.search(name))

    def poll_graph(self) -> None:
        """Subscribe to selected topics that appeared since the last poll."""
        with self._lock:
            if self._closed or self.failure is not None:
                return
            for name, types in self.node.get_topic_names_and_types():
                if name in self._subscriptions or name in self._skipped or not self._selected(name):
                    continue
                try:
                    self._start(name, types)
                except BagError as exc:
                    if name in self.wanted:
                        self._fail(exc)
                        return
                    self._skipped.add(name)
                    self.log(f"skipping {name}: {exc}")
            missing = sorted(self.wanted - set(self._subscriptions))
            if missing and not self._waiting_noted and time.monotonic() - self._started > 3.0:
                self._waiting_noted = True
                self.log(f"waiting for {', '.join(missing)} to appear on the graph")

    def _start(self, name: str, types: Sequence[str]) -> None:
        if len(types) != 1:
            raise BagError(f"topic '{name}' has several types on the graph ({', '.join(types)}); "
                           f"a bag topic needs exactly one")
        msgtype = types[0]
        publishers = self.node.get_publishers_info_by_topic(name)
        if not publishers:
            return  # only subscribers so far: the QoS to record is unknown until a publisher shows up
        cls = _message_class(name, msgtype)
        offered = [rosbags_qos(p.qos_profile) for p in publishers]
        self.writer.add_topic(name, msgtype, offered)
        play = bags.playback_qos(offered)  # the subscription mirrors what playback will offer
        qos = rclpy_qos(bags.PlaybackQos(play.reliable, play.transient_local, keep_all=False, depth=RECORD_DEPTH))
        self._subscriptions[name] = self.node.create_subscription(
            cls, name, self._callback(name), qos, raw=True)
        self.log(f"recording {name} [{msgtype}]")

    def _callback(self, topic: str) -> Callable[[bytes, dict[str, Any]], None]:
        writer = self.writer

        def on_message(data: bytes, info: dict[str, Any]) -> None:
            # the middleware's receive time, like rosbag2; fall back to now if the rmw gives none
            stamp = int(info.get("received_timestamp") or 0) or time.time_ns()
            writer.write(topic, stamp, data)

        return on_message

    def _fail(self, exc: BagError) -> None:
        self.failure = exc
        if self.on_failure is not None:
            self.on_failure(exc)

    def close(self) -> None:
        """Stop recording and finalise the bag (metadata.yaml); idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self.node.destroy_timer(self._timer)
            for sub in self._subscriptions.values():
                self.node.destroy_subscription(sub)
            self._subscriptions.clear()
        self.writer.close()


# ----------------------------------------------------------------------------- player
class BagPlayer:
    """Publishes a bag's messages as bytes with their recorded timing (gaps / ``rate``) and QoS.

    One publisher per topic on ``node``, created at construction with the QoS the recording
    says the original publishers offered (:func:`bags.playback_qos`). :meth:`play` blocks the
    calling thread; publishing needs no spinning.
    """

    def __init__(self, node: Any, bag_dir: Path | str, *, topics: Sequence[str] | None = None,
                 exclude: Sequence[str] | None = None, rate: float = 1.0, loop: bool = False,
                 wait_subscribers_s: float = 1.0, expect: dict[str, int] | None = None,
                 types: bags.BagTypes | None = None, log: Callable[[str], None] | None = None) -> None:
        self.node = node
        self.path = Path(bag_dir)
        self.loop = loop
        self.rate = float(rate)
        bags.PlaybackClock(self.rate)  # validates the rate before anything is created
        self.wait_subscribers_s = float(wait_subscribers_s)
        # topic -> subscribers to wait for (default 1): with several readers on a volatile topic,
        # the first one matched says nothing about the others
        self.expect = {node.resolve_topic_name(t): int(n) for t, n in (expect or {}).items()}
        self.log = log or (lambda text: node.get_logger().info(text))
        available = bags.bag_topics(self.path)
        selected = list(available) if topics is None else [node.resolve_topic_name(t) for t in topics]
        excluded = {node.resolve_topic_name(t) for t in (exclude or [])}
        if missing := sorted((set(selected) | excluded) - set(available)):
            raise BagError(f"bag {self.path} has no topic {', '.join(missing)} "
                           f"(it has: {', '.join(sorted(available)) or 'none'})")
        selected = [t for t in selected if t not in excluded]
        definitions = bags.stored_definitions(self.path)
        types = types or bags.BagTypes()
        #: topic -> why it is not played (its type cannot be loaded here, or its definition cannot be translated)
        self.skipped: dict[str, str] = {}
        self.converters: dict[str, bags.Converter] = {}
        self.publishers: dict[str, Any] = {}
        try:
            for name in selected:
                msgtype, offered = available[name]
                try:
                    cls = _message_class(name, msgtype)
                    converter, note = bags.definition_converter(name, msgtype, definitions[name][1], types)
                except BagError as exc:  # one topic a third-party bag has and we cannot play: the rest still plays
                    self.skipped[name] = str(exc)
                    self.log(f"warning: {exc}: skipped")
                    continue
                if converter is not None:
                    self.converters[name] = converter
                    self.log(f"warning: {note}")
                self.publishers[name] = node.create_publisher(cls, name, rclpy_qos(bags.playback_qos(offered)))
        except BaseException:
            self.destroy()
            raise
        if not self.publishers:
            raise BagError(f"nothing to play in {self.path}: " + "; ".join(self.skipped.values())
                           if self.skipped else f"nothing to play in {self.path}: every topic was excluded")
        self.topics: list[str] = list(self.publishers)
        self.published = 0

    def wait_for_subscribers(self, stop: threading.Event | None = None) -> bool:
        """Wait up to ``wait_subscribers_s`` until every publisher has a subscriber; True if all have.

        When it had to wait, it waits MATCH_GRACE_S more: our writer has matched the reader,
        but the reader may not have matched our writer yet, and a reliable sample sent in
        between only arrives with the next heartbeat, out of its recorded timing.
        """
        stop = stop or threading.Event()
        end = time.monotonic() + self.wait_subscribers_s
        waited = False
        while not all(p.get_subscription_count() >= self.expect.get(t, 1) for t, p in self.publishers.items()):
            if time.monotonic() >= end or stop.is_set():
                if not stop.is_set():  # playing on: the messages before a reader matches are lost to it
                    short = [f"{t} ({p.get_subscription_count()} of {self.expect.get(t, 1)})"
                             for t, p in self.publishers.items() if p.get_subscription_count() < self.expect.get(t, 1)]
                    self.log(f"warning: after {self.wait_subscribers_s:g} s still too few subscribers on "
                             f"{', '.join(short)}; playing anyway (volatile messages published before a reader "
                             f"matches never reach it: --wait-subscribers S waits longer)")
                return False
            waited = True
            time.sleep(0.02)
        if waited:
            stop.wait(MATCH_GRACE_S)
        return True

    def play(self, stop: threading.Event | None = None) -> int:
        """Publish the bag (again and again with ``loop``) until done or ``stop`` is set.

        Returns the number of messages published.
        """
        stop = stop or threading.Event()
        self.wait_for_subscribers(stop)
        while not stop.is_set():
            clock = bags.PlaybackClock(self.rate)
            for message in bags.read_messages(self.path, self.topics):
                if clock.first_ns is None:
                    clock.start(message.timestamp_ns, time.monotonic())
                delay = clock.due_s(message.timestamp_ns) - time.monotonic()
                if delay > 0 and stop.wait(delay):
                    break
                if stop.is_set():
                    break
                convert = self.converters.get(message.topic)
                self.publishers[message.topic].publish(message.data if convert is None else convert(message.data))
                self.published += 1
            if not self.loop or clock.first_ns is None:
                break
        self._flush()
        return self.published

    def _flush(self, timeout_s: float = 2.0) -> None:
        """Give reliable subscribers the chance to acknowledge the last messages before we go."""
        from rclpy.duration import Duration

        end = time.monotonic() + timeout_s
        for pub in self.publishers.values():
            remaining = max(0.0, end - time.monotonic())
            pub.wait_for_all_acked(Duration(nanoseconds=int(remaining * 1e9)))

    def destroy(self) -> None:
        """Remove the publishers from the node."""
        for pub in self.publishers.values():
            self.node.destroy_publisher(pub)
        self.publishers.clear()


# -------------------------------------------------------------------------------- CLI
class _RosSession:
    """One node in its own context for a CLI command; SIGINT/SIGTERM set :attr:`stop` (no traceback)."""

    def __init__(self, name: str) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        self.rclpy = rclpy
        self.stop = threading.Event()
        self.context = Context()
        # our own handlers: rclpy's would shut the context down under the bag we still must close
        rclpy.init(context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node(name, context=self.context, start_parameter_services=False)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> _RosSession:
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._previous[sig] = signal.signal(sig, lambda *_: self.stop.set())
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self.rclpy.try_shutdown(context=self.context)


def _say(text: str) -> None:
    print(f"[lsu bag] {text}", flush=True)


def cmd_record(args: argparse.Namespace) -> int:
    """`lsu bag record`."""
    if args.duration is not None and args.duration <= 0:
        raise BagError(f"--duration must be > 0 seconds, got {args.duration:g}")
    out = Path(args.output)
    if out.exists():
        raise BagError(f"output folder {out} exists already; choose another -o or remove it "
                       f"(a bag is never overwritten)")
    if not args.topics and not args.all:
        raise BagError("nothing to record: name topics (e.g. /lsu/scan/events) or use --all")
    with _RosSession("lsu_bag_recorder") as ros:
        _say(f"recording to {out} ({args.storage}{', zstd' if args.compress else ''}); Ctrl-C stops")
        recorder = BagRecorder(ros.node, args.topics, out, args.storage, compress=args.compress,
                               all_topics=args.all, exclude=args.exclude, log=_say)
        end = time.monotonic() + args.duration if args.duration else None
        try:
            while not ros.stop.is_set() and recorder.failure is None:
                if end is not None and time.monotonic() >= end:
                    break
                ros.executor.spin_once(timeout_sec=0.05)
        finally:
            recorder.close()
        counts = recorder.counts
    total = sum(counts.values())
    if recorder.failure is not None:
        if total == 0:
            shutil.rmtree(out, ignore_errors=True)  # an empty bag we just made helps nobody; -o stays free
            raise recorder.failure
        raise BagError(f"{recorder.failure} (bag {out} closed with {total} message(s) recorded before)")
    _say(f"wrote {total} message(s) on {len(counts)} topic(s) to {out}")
    return 0


def cmd_play(args: argparse.Namespace) -> int:
    """`lsu bag play`."""
    if args.wait_subscribers < 0:
        raise BagError(f"--wait-subscribers must be >= 0 seconds, got {args.wait_subscribers:g}")
    expect: dict[str, int] = {}
    for item in args.expect:
        topic, _, count = item.rpartition("=")
        if not topic or not count.isdigit() or int(count) < 1:
            raise BagError(f"--expect {item}: give TOPIC=N with N >= 1, e.g. --expect /lsu/scan/events=2")
        expect[topic] = int(count)
    with _RosSession("lsu_bag_player") as ros:
        player = BagPlayer(ros.node, args.bag, topics=args.topics, exclude=args.exclude, rate=args.rate,
                           loop=args.loop, wait_subscribers_s=args.wait_subscribers, expect=expect, log=_say)
        _say(f"playing {args.bag}: {len(player.topics)} topic(s)"
             f"{f' ({len(player.skipped)} skipped)' if player.skipped else ''} at rate {args.rate:g}"
             f"{', looping' if args.loop else ''}; Ctrl-C stops")
        try:
            count = player.play(ros.stop)
        finally:
            player.destroy()
    _say(f"published {count} message(s)")
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    """`lsu bag info`."""
    print(bags.format_info(bags.bag_info(args.bag)))
    return 0


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a number") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return value


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `lsu bag record|play|info`."""
    bag = subparsers.add_parser("bag", help="record, play and inspect rosbag2 bags (mcap, sqlite3)",
                                description="Standard rosbag2 folders (metadata.yaml + .mcap or .db3), "
                                            "readable by `ros2 bag` and the rosbags library.")
    verbs = bag.add_subparsers(dest="bag_command", required=True, metavar="VERB")

    p = verbs.add_parser("record", help="record topics into a new bag folder",
                         description="Record topics (types and QoS taken from the graph) until Ctrl-C, SIGTERM "
                                     "or --duration; the bag is closed properly in every case.")
    p.add_argument("topics", nargs="*", metavar="TOPIC", help="topics to record (waited for if not there yet)")
    p.add_argument("-o", "--output", required=True, metavar="DIR", help="bag folder to create (must not exist)")
    p.add_argument("-a", "--all", action="store_true",
                   help="record every topic, also those that appear later (not /rosout, /parameter_events "
                        "or hidden ones)")
    p.add_argument("--exclude", metavar="REGEX", help="with --all: leave out topics matching REGEX")
    p.add_argument("-s", "--storage", choices=bags.STORAGES, default="mcap", help="storage plugin (default mcap)")
    p.add_argument("--compress", action="store_true",
                   help="zstd compression (mcap: compressed chunks; sqlite3: per message)")
    p.add_argument("-d", "--duration", type=float, metavar="S", help="stop after S seconds")
    p.set_defaults(func=cmd_record)

    p = verbs.add_parser("play", help="publish a bag with its recorded timing and QoS",
                         description="Publish the serialized messages of a bag with the recorded gaps (scaled by "
                                     "1/rate) and the recorded QoS (latched topics stay latched).")
    p.add_argument("bag", metavar="DIR", help="bag folder (or a single .mcap/.db3 file)")
    p.add_argument("-r", "--rate", type=_positive_float, default=1.0, metavar="R",
                   help="playback speed factor (default 1.0)")
    p.add_argument("-l", "--loop", action="store_true", help="play again and again until Ctrl-C")
    p.add_argument("--topics", nargs="+", metavar="TOPIC", help="only these topics")
    p.add_argument("--exclude", nargs="+", default=[], metavar="TOPIC", help="leave these topics out")
    p.add_argument("--wait-subscribers", type=float, default=1.0, metavar="S",
                   help="wait up to S seconds for every topic to have a subscriber before the first "
                        "message (default 1)")
    p.add_argument("--expect", action="append", default=[], metavar="TOPIC=N",
                   help="wait for N subscribers on TOPIC instead of 1 (repeatable)")
    p.set_defaults(func=cmd_play)

    p = verbs.add_parser("info", help="summary of a bag (like `ros2 bag info`)")
    p.add_argument("bag", metavar="DIR", help="bag folder (or a single .mcap/.db3 file)")
    p.set_defaults(func=cmd_info)

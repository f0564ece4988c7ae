"""Bags: rosbag2 files written and read with rosbags, recorder and player on a real rclpy graph.

Ground truth: message bytes come from rclpy's own serializer (not from rosbags), fields are
read back by rosbags' AnyReader from the definitions stored *in the bag* (an empty
typestore), and type hashes are compared with what the middleware reports on the graph.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest
import yaml
from rosbags.highlevel import AnyReader
from rosbags.interfaces import QosDurability, QosReliability
from rosbags.rosbag2 import Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from lsu_bags import bags
from lsu_bags.bags import BagError, UnknownTypeError

STORAGE_CASES = [("mcap", False), ("mcap", True), ("sqlite3", False), ("sqlite3", True)]


def laser_line(i: int) -> Any:
    """A LaserLine whose every field depends on ``i`` (so a mix-up of messages shows)."""
    from lsu_interfaces.msg import LaserLine

    msg = LaserLine()
    msg.header.stamp.sec = 1000 + i
    msg.header.stamp.nanosec = 7 * i
    msg.header.frame_id = "lsu_left_optical"
    msg.image_width, msg.image_height = 640, 480
    msg.method = f"gaussian3-{i}"
    msg.u = [100.25 + i, 101.5 + i]
    msg.v = [float(i), float(i + 1)]
    msg.peak = [200.0, 180.0]
    msg.width = [3.5, 3.25]
    msg.quality = [1.0, 0.5]
    msg.rows_searched = 480
    msg.rows_ambiguous = i
    return msg


def serialized(msg: Any) -> bytes:
    from rclpy.serialization import serialize_message

    return serialize_message(msg)


def write_laser_bag(path: Path, storage: str, compress: bool, n: int = 5) -> list[tuple[int, bytes]]:
    """A bag with ``n`` LaserLines on /lsu/stereo/left/laser_line, 10 ms apart; returns (t, bytes)."""
    written = []
    with bags.BagWriter(path, storage, compress=compress) as bag:
        bag.add_topic("/lsu/stereo/left/laser_line", "lsu_interfaces/msg/LaserLine",
                      [bags.make_qos("reliable", "volatile")])
        for i in range(n):
            t = 1_795_000_000_000_000_000 + i * 10_000_000
            data = serialized(laser_line(i))
            bag.write("/lsu/stereo/left/laser_line", t, data)
            written.append((t, data))
    return written


# ------------------------------------------------------------------------- files only
@pytest.mark.parametrize("storage,compress", STORAGE_CASES)
def test_written_bag_reads_back_bytes_times_and_fields(tmp_path, storage, compress):
    path = tmp_path / "bag"
    written = write_laser_bag(path, storage, compress)
    got = list(bags.read_messages(path))
    assert [(m.timestamp_ns, m.data) for m in got] == written
    assert {m.msgtype for m in got} == {"lsu_interfaces/msg/LaserLine"}
    # rosbags' own reader, knowing no types at all: it must learn LaserLine from the bag itself
    with AnyReader([path], default_typestore=get_typestore(Stores.EMPTY)) as reader:
        decoded = [reader.deserialize(raw, conn.msgtype) for conn, _t, raw in reader.messages()]
    assert [d.method for d in decoded] == [f"gaussian3-{i}" for i in range(5)]
    assert [d.header.stamp.sec for d in decoded] == [1000 + i for i in range(5)]
    assert decoded[3].u.tolist() == pytest.approx([103.25, 104.5])
    assert decoded[4].rows_ambiguous == 4


@pytest.mark.parametrize("storage,compress", STORAGE_CASES)
def test_message_views_are_the_messages_and_map_an_uncompressed_mcap(tmp_path, storage, compress):
    """read_message_views gives read_messages' messages in its order (two topics, equal and out-of-order
    receive times); from an uncompressed MCAP file as views of the file, without a copy."""
    path = tmp_path / "bag"
    with bags.BagWriter(path, storage, compress=compress) as bag:
        for side in ("left", "right"):
            bag.add_topic(f"/lsu/stereo/{side}/laser_line", "lsu_interfaces/msg/LaserLine",
                          [bags.make_qos("reliable", "volatile")])
        for i, t in enumerate([5, 3, 3, 9, 1, 9, 9, 2]):
            bag.write(f"/lsu/stereo/{('left', 'right')[i % 2]}/laser_line", 1_795_000_000_000_000_000 + t,
                      serialized(laser_line(i)))
    for topics in (None, ["/lsu/stereo/right/laser_line"]):
        expected = [(m.topic, m.msgtype, m.timestamp_ns, m.data) for m in bags.read_messages(path, topics)]
        views = list(bags.read_message_views(path, topics))
        assert [(m.topic, m.msgtype, m.timestamp_ns, bytes(m.data)) for m in views] == expected
        assert len(expected) == (8 if topics is None else 4)
        assert all(isinstance(m.data, memoryview) and m.data.readonly for m in views) == (
            storage == "mcap" and not compress)
    with pytest.raises(BagError, match="has no topic /lsu/points"):
        list(bags.read_message_views(path, ["/lsu/points"]))


def test_message_views_of_a_truncated_mcap_name_the_file(tmp_path):
    path = tmp_path / "bag"
    write_laser_bag(path, "mcap", compress=False, n=400)
    data_file = path / "bag.mcap"
    data_file.write_bytes(data_file.read_bytes()[: data_file.stat().st_size // 2])
    with pytest.raises(BagError) as caught:
        list(bags.read_message_views(path))
    assert str(data_file) in str(caught.value) and "truncated or corrupt" in str(caught.value)


@pytest.mark.parametrize("storage", bags.STORAGES)
def test_metadata_is_standard_rosbag2(tmp_path, storage):
    path = tmp_path / "bag"
    write_laser_bag(path, storage, compress=False)
    meta = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["version"] == 9 and meta["storage_identifier"] == storage
    suffix = ".mcap" if storage == "mcap" else ".db3"
    assert meta["relative_file_paths"] == [f"bag{suffix}"] and (path / f"bag{suffix}").is_file()
    topic = meta["topics_with_message_count"][0]
    assert topic["message_count"] == 5
    assert topic["topic_metadata"]["offered_qos_profiles"][0]["reliability"] == "reliable"
    # RIHS01 of LaserLine as rosidl generated it for rclpy (the hash the middleware announces)
    from lsu_interfaces.msg import LaserLine

    assert topic["topic_metadata"]["type_description_hash"] == _rclpy_type_hash(LaserLine)


def _rclpy_type_hash(cls: type) -> str:
    """RIHS01 string of a generated class, from rosidl's own type description."""
    import rclpy
    from rclpy.context import Context

    context = Context()
    rclpy.init(context=context)
    try:
        node = rclpy.create_node("hash_probe", context=context)
        node.create_publisher(cls, "hash_probe_topic", 1)
        info = node.get_publishers_info_by_topic("/hash_probe_topic")[0]
        node.destroy_node()
        return str(info.topic_type_hash)
    finally:
        rclpy.try_shutdown(context=context)


@pytest.mark.parametrize("storage,compress", [("mcap", True), ("sqlite3", False)])
def test_info_reports_counts_times_and_compression(tmp_path, storage, compress):
    path = tmp_path / "bag"
    written = write_laser_bag(path, storage, compress, n=7)
    info = bags.bag_info(path)
    assert info.storage == storage and info.message_count == 7
    assert info.start_ns == written[0][0] and info.end_ns == written[-1][0]
    assert info.duration_ns == 60_000_000
    assert [(t.name, t.msgtype, t.count, t.serialization_format) for t in info.topics] == [
        ("/lsu/stereo/left/laser_line", "lsu_interfaces/msg/LaserLine", 7, "cdr")]
    assert ("zstd" in info.compression) == compress
    text = bags.format_info(info)
    assert "Messages:          7" in text and "Duration:          0.060000000s" in text
    assert "Topic: /lsu/stereo/left/laser_line | Type: lsu_interfaces/msg/LaserLine | Count: 7" in text


def test_existing_output_folder_is_refused(tmp_path):
    (tmp_path / "bag").mkdir()
    with pytest.raises(BagError, match=r"bag exists already; choose another -o"):
        bags.BagWriter(tmp_path / "bag", "mcap")


def test_unknown_storage_is_refused(tmp_path):
    with pytest.raises(BagError, match=r"unknown storage 'rosbag1'; use one of: mcap, sqlite3"):
        bags.BagWriter(tmp_path / "bag", "rosbag1")


@pytest.mark.parametrize("storage", bags.STORAGES)
@pytest.mark.fault('bag: truncated')
def test_truncated_bag_gives_one_line_error_naming_the_file(tmp_path, storage):
    path = tmp_path / "bag"
    write_laser_bag(path, storage, compress=False, n=400)
    data_file = next(p for p in path.iterdir() if p.name != "metadata.yaml")
    data_file.write_bytes(data_file.read_bytes()[: data_file.stat().st_size // 2])
    with pytest.raises(BagError) as caught:
        list(bags.read_messages(path))
    text = str(caught.value)
    assert str(data_file) in text and "truncated or corrupt" in text and "\n" not in text
    with pytest.raises(BagError, match="truncated or corrupt"):
        bags.bag_info(path)


def test_sqlite_cut_in_the_last_page_fails_while_reading(tmp_path):
    # sqlite opens a file cut inside its last page; the error must come when the lost rows are read
    path = tmp_path / "bag"
    write_laser_bag(path, "sqlite3", compress=False, n=400)
    data_file = path / "bag.db3"
    data_file.write_bytes(data_file.read_bytes()[:-1000])
    with pytest.raises(BagError, match=r"bag\.db3: cannot read a message, the file is truncated or corrupt"):
        list(bags.read_messages(path))


@pytest.mark.fault('bag: missing metadata')
def test_missing_metadata_says_what_happened(tmp_path):
    path = tmp_path / "bag"
    write_laser_bag(path, "mcap", compress=False)
    (path / "metadata.yaml").unlink()
    with pytest.raises(BagError, match=r"metadata\.yaml is missing: .*killed before it could close"):
        bags.bag_info(path)
    with pytest.raises(BagError, match=r"does not exist"):
        list(bags.read_messages(tmp_path / "nowhere"))


@pytest.mark.fault('bag: unknown message type')
def test_unknown_type_names_topic_and_type(tmp_path):
    with pytest.raises(UnknownTypeError) as caught:
        bags.BagTypes().ensure("nope_msgs/msg/Thing", "/lsu/nope")
    text = str(caught.value)
    assert "topic '/lsu/nope' has type 'nope_msgs/msg/Thing'" in text and "install its interface package" in text
    # lsu_interfaces is known only through its .msg files: without a search path it is unknown
    with bags.BagWriter(tmp_path / "bag", "mcap", types=bags.BagTypes(msg_dirs=[])) as bag:
        with pytest.raises(UnknownTypeError, match="topic '/x' has type 'lsu_interfaces/msg/ScanEvent'"):
            bag.add_topic("/x", "lsu_interfaces/msg/ScanEvent")


def test_msg_files_are_found_with_their_dependencies(tmp_path):
    pkg = tmp_path / "my_msgs" / "msg"
    pkg.mkdir(parents=True)
    (pkg / "Outer.msg").write_text("my_msgs/Inner[] items\nstd_msgs/Header header\n")
    (pkg / "Inner.msg").write_text("float64 x\nstring name\n")
    types = bags.BagTypes(msg_dirs=[tmp_path])
    types.ensure("my_msgs/msg/Outer")
    assert types.known("my_msgs/msg/Inner")
    store = types.typestore
    Outer, Inner = store.types["my_msgs/msg/Outer"], store.types["my_msgs/msg/Inner"]
    Header, Time = store.types["std_msgs/msg/Header"], store.types["builtin_interfaces/msg/Time"]
    msg = Outer(items=[Inner(x=1.5, name="a")], header=Header(stamp=Time(sec=1, nanosec=2), frame_id="f"))
    raw = store.serialize_cdr(msg, "my_msgs/msg/Outer")
    back = bags.deserialize(bags.BagMessage("/t", "my_msgs/msg/Outer", 0, bytes(raw)), types)
    assert back.items[0].x == 1.5 and back.items[0].name == "a" and back.header.frame_id == "f"


def test_read_messages_filters_topics_and_rejects_unknown_ones(tmp_path):
    path = tmp_path / "bag"
    with bags.BagWriter(path, "mcap") as bag:
        bag.add_topic("/a", "std_msgs/msg/String")
        bag.add_topic("/b", "std_msgs/msg/String")
        for i in range(4):
            bag.write("/a" if i % 2 else "/b", 100 + i, b"\x00\x01\x00\x00\x02\x00\x00\x00x\x00")
    assert [m.timestamp_ns for m in bags.read_messages(path, ["/a"])] == [101, 103]
    with pytest.raises(BagError, match=r"has no topic /c \(it has: /a, /b\)"):
        list(bags.read_messages(path, ["/c"]))


def test_deserialize_ros_gives_the_rclpy_message(tmp_path):
    path = tmp_path / "bag"
    write_laser_bag(path, "mcap", compress=False)
    msgs = [bags.deserialize_ros(m) for m in bags.read_messages(path)]
    assert msgs[2] == laser_line(2)


def test_playback_qos_follows_the_recorded_publishers():
    rel_tl = bags.make_qos("reliable", "transient_local")
    rel_vol = bags.make_qos("reliable", "volatile")
    be_vol = bags.make_qos("best_effort", "volatile")
    latched = bags.playback_qos([rel_tl])
    assert latched.reliable and latched.transient_local and latched.depth == 1
    mixed = bags.playback_qos([rel_tl, be_vol])
    assert not mixed.reliable and not mixed.transient_local and mixed.depth == bags.PLAY_DEPTH
    deep = bags.playback_qos([bags.make_qos("reliable", "volatile", "keep_last", 500), rel_vol])
    assert deep.depth == 500 and not deep.keep_all
    assert bags.playback_qos([bags.make_qos("reliable", "volatile", "keep_all")]).keep_all
    assert bags.playback_qos([]).reliable  # bags without QoS (old rosbag2): rosbag2's default, reliable


def test_playback_clock_scales_gaps_by_rate():
    clock = bags.PlaybackClock(rate=2.0)
    clock.start(first_ns=5_000_000_000, now_s=100.0)
    assert clock.due_s(5_000_000_000) == 100.0
    assert clock.due_s(6_000_000_000) == pytest.approx(100.5)
    with pytest.raises(BagError, match="--rate must be > 0"):
        bags.PlaybackClock(rate=0.0)


# --------------------------------------------------------------------- on the graph
def _publisher_node(ros_node: Any) -> Any:
    import rclpy

    return ros_node.add(rclpy.create_node("bag_test_publisher", context=ros_node.context))


@pytest.mark.parametrize("storage", bags.STORAGES)
def test_recorder_stores_graph_bytes_qos_and_late_topics(ros_node, tmp_path, storage):
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String

    from lsu_bags.bag_cli import BagRecorder
    from lsu_interfaces.msg import StereoExtrinsics

    pub_node = _publisher_node(ros_node)
    lines = pub_node.create_publisher(type(laser_line(0)), "/bagtest/laser_line", 10)
    latched_qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
    extrinsics = pub_node.create_publisher(StereoExtrinsics, "/bagtest/extrinsics", latched_qos)
    latched = StereoExtrinsics(right_frame_id="lsu_right_optical", rms_px=0.12)
    extrinsics.publish(latched)  # before the recorder exists: it must still get it (transient-local)
    noted: list[str] = []
    recorder = BagRecorder(ros_node.node, None, tmp_path / "bag", storage, all_topics=True, poll_s=0.2,
                           log=noted.append)
    assert ros_node.spin_until(lambda: {"/bagtest/laser_line", "/bagtest/extrinsics"} <= set(recorder.recording))
    assert ros_node.spin_until(lambda: lines.get_subscription_count() > 0)
    sent = []
    for i in range(6):
        msg = laser_line(i)
        lines.publish(msg)
        sent.append(msg)
        ros_node.spin_until(lambda: False, 0.05)
    late = pub_node.create_publisher(String, "/bagtest/late", 10)  # appears while recording
    assert ros_node.spin_until(lambda: "/bagtest/late" in recorder.recording and late.get_subscription_count() > 0)
    late.publish(String(data="late news"))
    assert ros_node.spin_until(lambda: recorder.counts.get("/bagtest/late") == 1
                               and recorder.counts.get("/bagtest/laser_line") == 6
                               and recorder.counts.get("/bagtest/extrinsics") == 1)
    recorder.close()
    assert "/rosout" not in recorder.recording and "/parameter_events" not in recorder.recording
    assert any("recording /bagtest/late [std_msgs/msg/String]" in n for n in noted)

    got: dict[str, list[bags.BagMessage]] = {}
    for m in bags.read_messages(tmp_path / "bag"):
        got.setdefault(m.topic, []).append(m)
    # compare decoded messages: CDR padding bytes are not defined, so two serializers may differ there
    assert [bags.deserialize_ros(m) for m in got["/bagtest/laser_line"]] == sent
    assert bags.deserialize_ros(got["/bagtest/extrinsics"][0]) == latched
    assert bags.deserialize_ros(got["/bagtest/late"][0]).data == "late news"
    stamps = [m.timestamp_ns for m in got["/bagtest/laser_line"]]
    assert stamps == sorted(stamps) and abs(stamps[0] - time.time_ns()) < 60e9  # receive time, epoch ns
    topics = bags.bag_topics(tmp_path / "bag")
    qos = topics["/bagtest/extrinsics"][1]
    assert len(qos) == 1 and qos[0].durability == QosDurability.TRANSIENT_LOCAL
    assert qos[0].reliability == QosReliability.RELIABLE
    assert topics["/bagtest/laser_line"][1][0].durability == QosDurability.VOLATILE
    meta = yaml.safe_load((tmp_path / "bag" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    hashes = {t["topic_metadata"]["name"]: t["topic_metadata"]["type_description_hash"]
              for t in meta["topics_with_message_count"]}
    announced = ros_node.node.get_publishers_info_by_topic("/bagtest/laser_line")[0].topic_type_hash
    assert hashes["/bagtest/laser_line"] == str(announced)


def test_recorder_fails_clearly_on_a_named_topic_of_unknown_type(ros_node, tmp_path):
    from lsu_bags.bag_cli import BagRecorder

    pub_node = _publisher_node(ros_node)
    pub_node.create_publisher(type(laser_line(0)), "/bagtest/mystery", 10)
    failures: list[BagError] = []
    recorder = BagRecorder(ros_node.node, ["/bagtest/mystery"], tmp_path / "bag", "mcap", poll_s=0.1,
                           types=bags.BagTypes(msg_dirs=[]), on_failure=failures.append)
    try:
        assert ros_node.spin_until(lambda: bool(failures))
    finally:
        recorder.close()
    assert isinstance(recorder.failure, UnknownTypeError)
    assert "topic '/bagtest/mystery' has type 'lsu_interfaces/msg/LaserLine'" in str(recorder.failure)


def test_player_keeps_bytes_timing_and_latching(ros_node, tmp_path):
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    from lsu_bags.bag_cli import BagPlayer
    from lsu_interfaces.msg import StereoExtrinsics

    path = tmp_path / "bag"
    gap_ns = 300_000_000
    t0 = 1_795_000_000_000_000_000
    latched = serialized(StereoExtrinsics(right_frame_id="lsu_right_optical", rms_px=0.2))
    sent = [serialized(laser_line(i)) for i in range(4)]
    with bags.BagWriter(path, "mcap") as bag:
        bag.add_topic("/bagplay/extrinsics", "lsu_interfaces/msg/StereoExtrinsics",
                      [bags.make_qos("reliable", "transient_local")])
        bag.add_topic("/bagplay/laser_line", "lsu_interfaces/msg/LaserLine", [bags.make_qos("reliable", "volatile")])
        bag.write("/bagplay/extrinsics", t0, latched)
        for i, data in enumerate(sent):
            bag.write("/bagplay/laser_line", t0 + (i + 1) * gap_ns, data)

    # each message with the time the player wrote it (the middleware's source timestamp), not the time this
    # process's executor got round to it: a busy host runs the callbacks of several arrivals at once
    arrivals: list[tuple[float, bytes]] = []
    ros_node.node.create_subscription(type(laser_line(0)), "/bagplay/laser_line",
                                      lambda data, info: arrivals.append((info["source_timestamp"] * 1e-9, data)), 10,
                                      raw=True)
    player = BagPlayer(ros_node.node, path, rate=2.0, wait_subscribers_s=0.0)
    done = threading.Event()
    stop = threading.Event()
    worker = threading.Thread(target=lambda: (player.play(stop), done.set()))
    # the laser-line subscriber exists, the extrinsics one does not: only wait for the former
    assert ros_node.spin_until(lambda: player.publishers["/bagplay/laser_line"].get_subscription_count() > 0)
    worker.start()
    try:
        assert ros_node.spin_until(lambda: len(arrivals) == 4 and done.is_set(), 15.0)
        # a subscriber that comes after play ended still gets the latched message
        late: list[bytes] = []
        latched_qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.TRANSIENT_LOCAL)
        ros_node.node.create_subscription(StereoExtrinsics, "/bagplay/extrinsics", late.append, latched_qos,
                                          raw=True)
        assert ros_node.spin_until(lambda: len(late) == 1)
    finally:
        stop.set()
        worker.join(5.0)
        player.destroy()
    assert [data for _t, data in arrivals] == sent
    assert late == [latched]
    # gaps of 300 ms at rate 2 are due 150 ms apart, and the player never sends early
    # (counted from the 2nd arrival: the 1st may wait for discovery to finish)
    assert arrivals[-1][0] - arrivals[1][0] >= 2 * 0.150 - 0.02


OLD_RANGE = """uint8 ULTRASOUND=0
uint8 INFRARED=1
std_msgs/Header header
uint8 radiation_type
float32 field_of_view
float32 min_range
float32 max_range
float32 range
"""


def write_third_party_bag(path: Path) -> None:
    """A bag as another tool might write it: a type nobody here has, an older sensor_msgs/Range
    (no ``variance``, as before Jazzy) and a std_msgs/String."""
    foreign = "other_msgs/msg/Widget"
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg("builtin_interfaces/Time stamp\nstring frame_id\n", "std_msgs/msg/Header"))
    store.register(get_types_from_msg(OLD_RANGE, "sensor_msgs/msg/Range"))
    store.register(get_types_from_msg("string data\n", "std_msgs/msg/String"))
    store.register(get_types_from_msg("float64 size\n", foreign))
    writer = Writer(path, version=9)
    writer.open()
    widgets = writer.add_connection("/widgets", foreign, typestore=store)
    ranges = writer.add_connection("/range", "sensor_msgs/msg/Range", typestore=store)
    chatter = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=store)
    Time, Header = store.types["builtin_interfaces/msg/Time"], store.types["std_msgs/msg/Header"]
    t0 = 1_795_000_000_000_000_000
    for i in range(3):
        t = t0 + i * 50_000_000
        writer.write(widgets, t, bytes(store.serialize_cdr(store.types[foreign](size=float(i)), foreign)))
        old = store.types["sensor_msgs/msg/Range"](header=Header(stamp=Time(sec=i, nanosec=7), frame_id="sonar"),
                                                   radiation_type=1, field_of_view=0.5, min_range=0.1,
                                                   max_range=4.0, range=1.0 + i)
        writer.write(ranges, t + 1, bytes(store.serialize_cdr(old, "sensor_msgs/msg/Range")))
        writer.write(chatter, t + 2, bytes(store.serialize_cdr(store.types["std_msgs/msg/String"](data=f"hi {i}"),
                                                               "std_msgs/msg/String")))
    writer.close()


def _play(ros_node: Any, player: Any, done_when: Any) -> None:
    done = threading.Event()
    worker = threading.Thread(target=lambda: (player.play(), done.set()))
    worker.start()
    try:
        assert ros_node.spin_until(lambda: done.is_set() and done_when(), 15.0)
    finally:
        worker.join(5.0)
        player.destroy()


def test_player_skips_what_it_cannot_load_translates_an_older_range_and_plays_the_rest(ros_node, tmp_path):
    from sensor_msgs.msg import Range
    from std_msgs.msg import String

    from lsu_bags.bag_cli import BagPlayer

    path = tmp_path / "bag"
    write_third_party_bag(path)
    lines: list[str] = []
    ranges: list[Any] = []
    chatter: list[Any] = []
    ros_node.node.create_subscription(Range, "/range", ranges.append, 10)
    ros_node.node.create_subscription(String, "/chatter", chatter.append, 10)
    player = BagPlayer(ros_node.node, path, wait_subscribers_s=10.0, log=lines.append)
    assert sorted(player.topics) == ["/chatter", "/range"] and list(player.skipped) == ["/widgets"]
    skipped = [line for line in lines if "/widgets" in line]
    assert len(skipped) == 1 and "other_msgs/msg/Widget" in skipped[0] and "skipped" in skipped[0]
    translated = [line for line in lines if "/range" in line]
    assert len(translated) == 1 and "translated" in translated[0] and "adds variance" in translated[0]
    _play(ros_node, player, lambda: len(ranges) == 3 and len(chatter) == 3)
    assert [m.data for m in chatter] == ["hi 0", "hi 1", "hi 2"]
    # every Range arrives (none dropped for a wrong size), with the recorded values and variance 0
    assert [m.range for m in ranges] == [1.0, 2.0, 3.0] and {m.variance for m in ranges} == {0.0}
    assert ranges[2].header.stamp.sec == 2 and ranges[2].header.frame_id == "sonar" and ranges[2].max_range == 4.0


def test_player_leaves_out_excluded_topics(ros_node, tmp_path):
    from lsu_bags.bag_cli import BagPlayer

    path = tmp_path / "bag"
    write_third_party_bag(path)
    lines: list[str] = []
    player = BagPlayer(ros_node.node, path, exclude=["/widgets", "/range"], wait_subscribers_s=0.0, log=lines.append)
    try:
        assert player.topics == ["/chatter"] and lines == []
    finally:
        player.destroy()
    with pytest.raises(BagError, match="has no topic /nope"):
        BagPlayer(ros_node.node, path, exclude=["/nope"])
    with pytest.raises(BagError, match=r"nothing to play.*other_msgs/msg/Widget.*--exclude /widgets"):
        BagPlayer(ros_node.node, path, topics=["/widgets"], log=lines.append)


@pytest.mark.parametrize("broken", ["rosbag2_bagfile_information: {version: 9, [unclosed\n", "just: text\n"])
def test_broken_metadata_is_named_and_the_storage_file_offered(tmp_path, broken):
    path = tmp_path / "bag"
    write_laser_bag(path, "mcap", compress=False)
    (path / "metadata.yaml").write_text(broken)
    with pytest.raises(BagError) as caught:
        bags.bag_info(path)
    text = str(caught.value)
    assert text.startswith(f"{path / 'metadata.yaml'}: ") and "truncated or corrupt" not in text
    assert f"can be opened directly: `lsu bag play {path / 'bag.mcap'}`" in text
    assert bags.bag_info(path / "bag.mcap").message_count == 5  # and it really can


def test_file_module_does_not_import_rclpy():
    code = "import sys, lsu_bags.bags; sys.exit('rclpy' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], timeout=60).returncode == 0


def test_a_thread_outliving_main_still_finishes_its_bag(tmp_path):
    """Ctrl-C: the coordinator's main thread returns while the scan thread still writes and closes
    the bag. The bag must be complete (a concurrent.futures worker would have quit at exit)."""
    path = tmp_path / "bag"
    code = f"""
import threading, time
from lsu_bags import bags
writer = bags.BagWriter({str(path)!r}, "mcap")
writer.add_topic("/t", "std_msgs/msg/String")
def finish():
    time.sleep(0.5)  # the main thread is exiting by now
    for i in range(3):
        writer.write("/t", 1_000 + i, bytes([0, 1, 0, 0, 2, 0, 0, 0, 65 + i, 0]))
    writer.close()
threading.Thread(target=finish).start()
"""
    result = subprocess.run([sys.executable, "-c", code], timeout=60, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert (path / "metadata.yaml").is_file(), result.stderr
    got = list(bags.read_messages(path))
    assert [m.timestamp_ns for m in got] == [1_000, 1_001, 1_002]
    assert bags.deserialize(got[2]).data == "C"


def test_player_says_which_topic_lacked_subscribers_when_it_plays_on(ros_node, tmp_path):
    from lsu_bags.bag_cli import BagPlayer

    path = tmp_path / "bag"
    write_third_party_bag(path)
    lines: list[str] = []
    player = BagPlayer(ros_node.node, path, topics=["/chatter"], expect={"/chatter": 2}, wait_subscribers_s=0.2,
                       log=lines.append)
    try:
        assert not player.wait_for_subscribers()  # nobody subscribes to /chatter here
    finally:
        player.destroy()
    assert len(lines) == 1 and "/chatter (0 of 2)" in lines[0] and "playing anyway" in lines[0], lines

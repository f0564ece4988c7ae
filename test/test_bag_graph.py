"""`lsu bag record|info|play` as separate processes against publishers and subscribers in this test.

Truth: the messages this test publishes (compared after decoding, since CDR padding bytes
are undefined), the counts it sent, the gaps it waited, and rosbags' own reader.
"""

from __future__ import annotations

import re
import signal
import time
from pathlib import Path
from typing import Any

import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

pytestmark = pytest.mark.slow

GAP_S = 0.25


def laser_line(i: int) -> Any:
    from lsu_interfaces.msg import LaserLine

    return LaserLine(method=f"gaussian3-{i}", image_width=640, image_height=480, u=[10.5 + i, 11.25],
                     v=[float(i), float(i + 1)], rows_searched=480 + i)


def one_line_error(result: Any) -> str:
    assert result.returncode == 2, (result.stdout, result.stderr)
    assert "Traceback" not in result.stderr + result.stdout
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    return lines[0]


@pytest.mark.parametrize("storage,stop", [("mcap", signal.SIGINT), ("sqlite3", signal.SIGTERM)])
def test_record_info_play_round_trip(ros_node, launch, capsys, tmp_path, storage, stop):
    import rclpy
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.serialization import deserialize_message

    from lsu_interfaces.msg import LaserLine, ScanEvent, StereoExtrinsics

    ns = f"/bagrt_{storage}"
    pub_node = ros_node.add(rclpy.create_node("bag_round_trip_publisher", context=ros_node.context))
    latched_qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
    events_qos = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
    pubs = {
        "laser_line": pub_node.create_publisher(LaserLine, f"{ns}/laser_line", 10),
        "events": pub_node.create_publisher(ScanEvent, f"{ns}/events", events_qos),
        "extrinsics": pub_node.create_publisher(StereoExtrinsics, f"{ns}/extrinsics", latched_qos),
    }
    extrinsics = StereoExtrinsics(right_frame_id="lsu_right_optical", rms_px=0.125, image_width=640)
    pubs["extrinsics"].publish(extrinsics)  # latched, before the recorder starts

    bag = tmp_path / "bag"
    args = ["bag", "record", "-o", str(bag), *(f"{ns}/{t}" for t in pubs), "--storage", storage]
    recorder = launch(*args, *(["--compress"] if storage == "sqlite3" else []))
    for topic in pubs:
        recorder.wait_for_line(rf"recording {ns}/{topic} \[")
    assert ros_node.spin_until(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), 15.0)

    lines = [laser_line(i) for i in range(5)]
    events = [ScanEvent(type=ScanEvent.STARTED, scan_id="s1", expected_snaps=5),
              ScanEvent(type=ScanEvent.FINISHED, scan_id="s1", snaps_captured=5)]
    pubs["events"].publish(events[0])
    for msg in lines:
        pubs["laser_line"].publish(msg)
        ros_node.spin_until(lambda: False, GAP_S)
    pubs["events"].publish(events[1])
    ros_node.spin_until(lambda: False, 1.0)  # let the last samples reach the recorder process
    recorder.process.send_signal(stop)
    assert recorder.process.wait(timeout=15) == 0, recorder.output
    recorder.wait_for_line(r"wrote 8 message\(s\) on 3 topic\(s\)")
    assert (bag / "metadata.yaml").is_file()

    info = lsu_in_process(capsys, "bag", "info", str(bag))
    assert info.returncode == 0, info.stderr
    counts = dict(re.findall(r"Topic: (\S+) \| Type: \S+ \| Count: (\d+)", info.stdout))
    assert counts == {f"{ns}/laser_line": "5", f"{ns}/events": "2", f"{ns}/extrinsics": "1"}
    assert re.search(rf"Storage id:\s+{storage}", info.stdout) and re.search(r"Messages:\s+8", info.stdout)

    with AnyReader([bag], default_typestore=get_typestore(Stores.EMPTY)) as reader:
        methods = [reader.deserialize(raw, c.msgtype).method for c, _t, raw in reader.messages()
                   if c.topic.endswith("laser_line")]
    assert methods == [m.method for m in lines]

    for pub in pubs.values():  # the live publishers go: what arrives now comes from the bag
        pub_node.destroy_publisher(pub)
    received: dict[str, list[tuple[float, bytes]]] = {t: [] for t in pubs}
    types = {"laser_line": LaserLine, "events": ScanEvent, "extrinsics": StereoExtrinsics}
    for topic, qos in (("laser_line", 10), ("events", events_qos), ("extrinsics", latched_qos)):
        ros_node.node.create_subscription(
            types[topic], f"{ns}/{topic}",
            lambda data, topic=topic: received[topic].append((time.monotonic(), data)), qos, raw=True)
    player = launch("bag", "play", str(bag), "--wait-subscribers", "15")
    expected = {"laser_line": 5, "events": 2, "extrinsics": 1}
    assert ros_node.spin_until(lambda: {t: len(r) for t, r in received.items()} == expected, 30.0), player.output
    assert player.process.wait(timeout=15) == 0, player.output
    player.wait_for_line(r"published 8 message\(s\)")
    decoded = {t: [deserialize_message(d, types[t]) for _ts, d in got] for t, got in received.items()}
    assert decoded["laser_line"] == lines
    assert decoded["events"] == events
    assert decoded["extrinsics"] == [extrinsics]
    stamps = [ts for ts, _d in received["laser_line"]]
    # recorded gaps kept: never played early (from the 2nd on: the 1st may wait for discovery)
    assert stamps[-1] - stamps[1] >= 3 * GAP_S - 0.05, stamps


def lsu_in_process(capsys: Any, *args: str) -> Any:
    """`lsu ARGS` through the console script's own main(), without paying its start-up again."""
    from types import SimpleNamespace

    from lsu_tools.cli import main

    code = main(list(args))
    out = capsys.readouterr()
    return SimpleNamespace(returncode=code, stdout=out.out, stderr=out.err)


def write_widget_bag(path: Path, count: int, storage: str = "sqlite3") -> None:
    """A bag of a type this machine does not have, written by rosbags as another tool would."""
    from rosbags.rosbag2 import StoragePlugin

    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(get_types_from_msg("float64 size\n", "other_msgs/msg/Widget"))
    writer = Writer(path, version=9, storage_plugin=StoragePlugin[storage.upper()])
    writer.open()
    conn = writer.add_connection("/widgets", "other_msgs/msg/Widget", typestore=store)
    for i in range(count):
        raw = store.serialize_cdr(store.types["other_msgs/msg/Widget"](size=float(i)), "other_msgs/msg/Widget")
        writer.write(conn, i, bytes(raw))
    writer.close()


def test_cli_errors_are_one_line(lsu_cli, capsys, tmp_path):
    foreign = tmp_path / "foreign"
    write_widget_bag(foreign, 1)
    assert "Type: other_msgs/msg/Widget | Count: 1" in lsu_in_process(capsys, "bag", "info", str(foreign)).stdout
    line = one_line_error(lsu_in_process(capsys, "bag", "play", str(foreign), "--wait-subscribers", "0"))
    assert "topic '/widgets' has type 'other_msgs/msg/Widget'" in line and "install" in line

    cut = tmp_path / "cut"
    write_widget_bag(cut, 50, "mcap")
    data = cut / "cut.mcap"
    data.write_bytes(data.read_bytes()[:-200])
    for verb in ("info", "play"):
        line = one_line_error(lsu_in_process(capsys, "bag", verb, str(cut)))
        assert str(data) in line and "truncated or corrupt" in line
    # and once through the real console script: no traceback, exit code 2
    line = one_line_error(lsu_cli("bag", "info", str(cut)))
    assert line.startswith("lsu bag: error: ") and str(data) in line

    (cut / "metadata.yaml").unlink()
    assert "metadata.yaml is missing" in one_line_error(lsu_in_process(capsys, "bag", "info", str(cut)))
    line = one_line_error(lsu_in_process(capsys, "bag", "record", "-o", str(foreign), "/anything"))
    assert f"output folder {foreign} exists already" in line

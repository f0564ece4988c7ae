"""A recorded scan replayed through extractor -> matcher gives the recorded cloud: through DDS (separate processes,
`lsu bag play`) and handed over directly in one process (`lsu run replay BAG`)."""

import collections
import subprocess
from pathlib import Path

import numpy as np
import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2

from lsu_bags.bags import deserialize_ros, read_messages
from lsu_bags.pointcloud2 import decode, from_msg
from lsu_common.arrays import AnyArray
from lsu_testing.plugin import LSU, REPLAY_GRAPH_READERS

BAG = Path(__file__).parent / "data" / "bags" / "scan_head"
REPLAYED = ["/lsu/scan/events", "/lsu/stereo/left/image_raw", "/lsu/stereo/right/image_raw"]


def xyz(msg: PointCloud2) -> AnyArray:
    columns = decode(from_msg(msg))
    return np.stack([columns["x"], columns["y"], columns["z"]], axis=1)


@pytest.mark.slow
def test_replayed_scan_gives_the_recorded_cloud(launch, ros_node):
    recorded = [deserialize_ros(m) for m in read_messages(BAG, ["/lsu/scan/cloud"])]
    assert len(recorded) == 1
    expected = xyz(recorded[0])
    assert len(expected) > 1000

    graph = launch("launch", "replay")
    graph.wait_for_line(r"\[stereo_matcher\].*calibration", timeout_s=60)
    graph.wait_for_line(r"started laser_extractor", timeout_s=60)
    clouds = []
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    ros_node.node.create_subscription(PointCloud2, "/lsu/scan/cloud", clouds.append, latched)
    ros_node.spin_until(lambda: False, 2.0)  # let the extractor's subscriptions be discovered
    play = subprocess.run([LSU, "bag", "play", str(BAG), "--topics", *REPLAYED, "--wait-subscribers", "20",
                           *REPLAY_GRAPH_READERS],
                          capture_output=True, text=True, timeout=120)
    assert play.returncode == 0, play.stdout + play.stderr
    assert ros_node.spin_until(lambda: len(clouds) >= 1, 30.0), graph.output[-3000:]
    replayed = xyz(clouds[0])
    assert replayed.shape == expected.shape
    assert np.max(np.abs(replayed - expected)) <= 1e-6


def points_by_stamp(messages) -> dict:
    """stamp (ns) -> (xyz (N, 3), snap indices (N,)) of PointCloud2 messages."""
    out = {}
    for msg in messages:
        columns = decode(from_msg(msg))
        key = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        out[key] = (np.stack([columns["x"], columns["y"], columns["z"]], axis=1), columns["snap"])
    return out


def test_direct_replay_gives_the_recorded_points_of_every_snap(ros_context, tmp_path):
    """The bag handed to the replay launch file's extractor and matcher in-process gives, snap by snap, the
    points the live graph (separate processes, DDS between them) published and recorded, and drops nothing."""
    from lsu_tools.cli import resolve_launch_file
    from lsu_tools.direct_replay import DirectReplay
    from lsu_tools.launch_file import load_launch, select_nodes
    from lsu_tools.nodes_index import resolve_executable
    from lsu_tools.runner import build_nodes

    recorded = points_by_stamp(deserialize_ros(m) for m in read_messages(BAG, ["/lsu/points"]))
    snap_events = [e for e in (deserialize_ros(m) for m in read_messages(BAG, ["/lsu/scan/events"])) if e.type == 2]
    assert len(recorded) == len(snap_events) == 6
    description = select_nodes(load_launch(resolve_launch_file("replay"), {}, resolve_executable),
                               ["laser_extractor", "stereo_matcher"], [], {})
    nodes = build_nodes(description, tmp_path, context=ros_context)
    try:
        replay = DirectReplay(nodes)
        published, clouds = [], []
        replay.matcher.points_pub.publish = published.append  # what subscribers of /lsu/points would get
        replay.matcher.points_pub.get_subscription_count = lambda: 1  # one, or the points are not encoded
        replay.matcher.cloud_pub.publish = clouds.append
        order: list[str] = []  # the scan cloud's libraries load before the timed window (its loop), not in it
        def spied(name: str, call):
            def spy(*args, **kwargs):
                order.append(name)
                return call(*args, **kwargs)
            return spy
        replay.matcher.prepare_scan_cloud = spied("prepare_scan_cloud", replay.matcher.prepare_scan_cloud)
        replay._replay = spied("_replay", replay._replay)
        handed: list[int] = []  # stamps of the carriage positions the matcher was given
        on_carriage = replay.matcher.on_carriage
        def carriage_spy(msg):
            handed.append(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)
            on_carriage(msg)
        replay.matcher.on_carriage = carriage_spy
        stats = replay.run(BAG)
    finally:
        for node in nodes:
            node.destroy_node()
    assert order[:2] == ["prepare_scan_cloud", "_replay"]
    # carriage positions serve sweeps only: the ones of the stop-snap scan (first SNAP to FINISHED) are not decoded,
    # except the last, handed over once the scan has ended (where a next sweep may start from)
    before, during, after, phase = [], [], [], 0
    for m in read_messages(BAG, ["/lsu/scan/events", "/lsu/driver/carriage"]):
        msg = deserialize_ros(m)
        if m.topic == "/lsu/driver/carriage":
            (before, during, after)[phase].append(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)
        elif msg.type == 2 and phase == 0 or msg.type == 3:  # the first SNAP; FINISHED
            phase += 1
    assert len(before) > 10 and len(during) > 10
    assert handed == before + during[-1:] + after
    assert (stats.snaps, stats.snap_events, stats.pairs, stats.frames_dropped, stats.lines_unpaired) == (6, 6, 7, 0, 0)
    replayed = points_by_stamp(published)
    assert sorted(replayed) == sorted(recorded)
    for key, (xyz_rec, snap_rec) in recorded.items():
        xyz_rep, snap_rep = replayed[key]
        assert xyz_rep.shape == xyz_rec.shape and len(xyz_rec) > 100
        assert np.max(np.abs(xyz_rep - xyz_rec)) <= 1e-6
        assert np.array_equal(snap_rep, snap_rec)
    # the scan cloud too (coloured by the texture pair found through the replay's own image source)
    expected = [deserialize_ros(m) for m in read_messages(BAG, ["/lsu/scan/cloud"])]
    assert len(clouds) == 1
    got, want = decode(from_msg(clouds[0])), decode(from_msg(expected[0]))
    assert np.array_equal(got["snap"], want["snap"]) and np.array_equal(got["rgb"], want["rgb"])
    assert np.max(np.abs(got["z"] - want["z"])) <= 1e-6


@pytest.mark.slow
def test_lsu_run_replay_bag_publishes_the_recorded_cloud(launch, ros_node):
    """`lsu run replay BAG` (the default replay) processes the bag, says nothing was lost, and late
    subscribers get the scan cloud the live graph recorded."""
    expected = xyz([deserialize_ros(m) for m in read_messages(BAG, ["/lsu/scan/cloud"])][0])
    graph = launch("run", "replay", str(BAG))
    line = graph.wait_for_line(r"replayed .*: (\d+) snaps \((\d+) SNAP events, \d+ pairs\).* (\d+) frames unreadable, "
                               r"(\d+) lines unpaired", timeout_s=120)
    assert line.groups() == ("6", "6", "0", "0")
    clouds = []
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    ros_node.node.create_subscription(PointCloud2, "/lsu/scan/cloud", clouds.append, latched)
    assert ros_node.spin_until(lambda: len(clouds) >= 1, 30.0), graph.output[-3000:]
    replayed = xyz(clouds[0])
    assert replayed.shape == expected.shape
    assert np.max(np.abs(replayed - expected)) <= 1e-6


def test_lsu_run_replay_names_a_missing_bag(tmp_path, capsys):
    from lsu_tools.cli import main

    assert main(["run", "replay", str(tmp_path / "no-such-bag"), "--exit"]) == 2
    err = capsys.readouterr().err
    assert "no-such-bag" in err and "not found" in err


def uncompressed_copy(bag: Path, out: Path) -> Path:
    """``bag`` rewritten as one uncompressed MCAP file (as the scan coordinator records): read in place."""
    from lsu_bags.bags import BagWriter, bag_topics

    with BagWriter(out, "mcap", compress=False) as writer:
        for topic, (msgtype, qos) in bag_topics(bag).items():
            writer.add_topic(topic, msgtype, qos)
        for m in read_messages(bag):
            writer.write(m.topic, m.timestamp_ns, m.data)
    return out


@pytest.mark.slow
@pytest.mark.parametrize("background, counts", [("none", (1, 2, 3)), ("texture", (1, 2))])
def test_replay_extracting_in_processes_gives_the_points_of_the_one_process_replay(ros_context, tmp_path, monkeypatch,
                                                                                    background, counts):
    """Extraction split over processes and the replay's own extractor gives every snap's points and the scan cloud
    of the replay in one process, bit for bit (and, with the default laser-off background, the points the live graph
    recorded); with that background every process holds the same texture pair. Extractor parameter changes are
    refused meanwhile."""
    from rclpy.parameter import Parameter

    from lsu_tools.cli import resolve_launch_file
    from lsu_tools.direct_replay import OWN, DirectReplay, _ExtractionProcesses
    from lsu_tools.launch_file import load_launch, select_nodes
    from lsu_tools.nodes_index import resolve_executable
    from lsu_tools.runner import build_nodes

    monkeypatch.setattr("lsu_tools.direct_replay.SPIN_EVERY_S", 0.0)  # spin after every message
    # places decided 4 images ahead, every third at the replay's own extractor and the others at the processes in
    # turn: the 14 images are extracted by both, whatever the host's timing
    monkeypatch.setattr("lsu_tools.direct_replay.AHEAD", 4)
    monkeypatch.setattr(_ExtractionProcesses, "_choose", lambda pool: OWN if pool.taken % 3 == 0 else pool.taken % pool.count)
    bag = uncompressed_copy(BAG, tmp_path / "bag")
    runs = {}
    for workers in (0, *counts):
        description = select_nodes(load_launch(resolve_launch_file("replay"), {}, resolve_executable),
                                   ["laser_extractor", "stereo_matcher"], [], {})
        nodes = build_nodes(description, tmp_path, context=ros_context)
        try:
            replay = DirectReplay(nodes)
            assert replay.extractor.set_parameters([Parameter("background", value=background)])[0].successful
            published, clouds, refused = [], [], []
            replay.matcher.points_pub.publish = published.append
            replay.matcher.points_pub.get_subscription_count = lambda: 1  # one, or the points are not encoded
            replay.matcher.cloud_pub.publish = clouds.append

            def spin() -> None:  # a parameter change while the replay runs
                refused.append(not replay.extractor.set_parameters([Parameter("min_contrast", value=40.0)])[0].successful)

            stats = replay.run(bag, spin=spin if workers else lambda: None, workers=workers)
            assert replay.extractor.frozen_reason is None  # taken again after the replay
        finally:
            for node in nodes:
                node.destroy_node()
        assert (stats.snaps, stats.pairs, stats.frames_dropped, stats.lines_unpaired, stats.workers) == \
            (6, 7, 0, 0, workers)
        assert stats.images == 14 and (0 < stats.extracted_here < 14) == (workers > 0)
        assert all(refused) and (len(refused) > 0) == (workers > 0)
        assert len(published) == 6 and len(clouds) == 1
        runs[workers] = ([(m.header.stamp.sec, m.header.stamp.nanosec, bytes(m.data)) for m in published],
                         bytes(clouds[0].data))
        if background == "texture":  # the live graph's default, with which the bag was recorded
            recorded = points_by_stamp(deserialize_ros(m) for m in read_messages(BAG, ["/lsu/points"]))
            for key, (xyz_rep, _) in points_by_stamp(published).items():
                assert np.max(np.abs(xyz_rep - recorded[key][0])) <= 1e-6
    for workers in counts:
        assert runs[workers] == runs[0]


class _Lines:
    """A process's pipe of lines as `_ExtractionProcesses` reads it: ``sent`` lines waiting."""

    def __init__(self, sent: int) -> None:
        self.sent = sent

    def poll(self, timeout: float = 0.0) -> bool:
        return self.sent > 0

    def recv(self) -> tuple:
        self.sent -= 1
        return ("line", (0, 0, "left"), None)


def test_replay_places_an_image_where_it_is_expected_to_be_extracted_first():
    """The replay takes an image itself when every process has more lines to send before it than the replay has
    work before reaching it, and leaves it to the least busy process otherwise; lines already sent count as done."""
    from lsu_tools.direct_replay import AHEAD, OWN, _ExtractionProcesses

    def pool(placed: list[int], sent: list[int], own_placed: int, extract_s: float = 2.0, other_s: float = 0.5):
        p = object.__new__(_ExtractionProcesses)  # the placement alone: no processes
        p.count, p.placed, p.own_placed, p.extract_s, p.other_s = len(placed), placed, own_placed, extract_s, other_s
        p.inputs, p.ready, p.done = [_Lines(n) for n in sent], [collections.deque() for _ in placed], [None] * len(placed)
        return p

    work = (AHEAD - 1) * 0.5  # the replay's other work before the image, at 0.5 per image
    busy = int(work // 2.0)  # unsent lines after which a process (2.0 per line) has the image later than that
    assert pool([busy], [0], 0)._choose() == OWN
    assert pool([busy - 1], [0], 0)._choose() == 0
    assert pool([busy + 2], [3], 0)._choose() == 0  # three of them sent already
    assert pool([busy], [0], 2)._choose() == 0  # the replay has two images of its own to extract first
    assert pool([busy + 4, 1, busy], [0, 0, 0], 0)._choose() == 1  # the least busy process
    p = pool([busy + 1], [2], 0)
    assert p._choose() == 0 and list(p.ready[0]) == [("line", (0, 0, "left"), None)] * 2  # read, kept in order

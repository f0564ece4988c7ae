"""The live view on a real graph: `lsu launch replay view:=true`, a recorded scan played in, and a
Foxglove WebSocket client (lsu_view.wsclient) receiving the scan cloud and per-snap points through the
bridge; decoded with rosbags they are the cloud the live run recorded."""

import subprocess
from pathlib import Path

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from lsu_bags.bags import read_messages
from lsu_common.arrays import AnyArray
from lsu_testing.plugin import LSU, REPLAY_GRAPH_READERS
from lsu_view.wsclient import FoxgloveClient, ProtocolError

BAG = Path(__file__).parent / "data" / "bags" / "scan_head"
REPLAYED = ["/lsu/scan/events", "/lsu/stereo/left/image_raw", "/lsu/stereo/right/image_raw"]
pytestmark = pytest.mark.slow


def xyz(payload: bytes, store) -> AnyArray:
    cloud = store.deserialize_cdr(payload, "sensor_msgs/msg/PointCloud2")
    offsets = {f.name: f.offset for f in cloud.fields}
    raw = np.frombuffer(cloud.data.tobytes(), dtype=np.uint8).reshape(cloud.width * cloud.height, cloud.point_step)
    return np.stack([raw[:, offsets[a]:offsets[a] + 4].copy().view("<f4")[:, 0] for a in "xyz"], axis=1)


def bridge_subscribed(topics: list[str], timeout_s: float) -> bool:
    """Wait until foxglove_bridge has a subscription on each topic (seen on the graph)."""
    import time

    from lsu_common.node import GraphClient

    probe = GraphClient("live_view_probe", namespace="/lsu_test")
    try:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if all(any(i.node_name == "foxglove_bridge" for i in probe.node.get_subscriptions_info_by_topic(t))
                   for t in topics):
                return True
            time.sleep(0.1)
        return False
    finally:
        probe.close()


def test_foxglove_client_gets_the_recorded_scan_cloud_through_the_bridge(launch):
    store = get_typestore(Stores.ROS2_JAZZY)
    recorded = [m.data for m in read_messages(BAG, ["/lsu/scan/cloud"])]
    assert len(recorded) == 1
    expected = xyz(recorded[0], store)
    assert len(expected) > 1000

    graph = launch("launch", "replay", "view:=true", "view_port:=0")
    url = graph.wait_for_line(r"Foxglove WebSocket server on (ws://\S+)", timeout_s=60).group(1)
    graph.wait_for_line(r"started laser_extractor", timeout_s=60)
    with FoxgloveClient(url) as client:
        channels = client.wait_for_topics(["/lsu/scan/cloud", "/lsu/points"], timeout_s=60)
        assert channels["/lsu/scan/cloud"].schema_encoding == "ros2msg"
        # the bridge's subscriptions on the graph before the bag plays: per-snap points are best effort, and
        # those published before the bridge's reader is discovered never reach it (on a loaded host, seconds).
        # A subscription sent right after the advertisement can reach the server before it knows the channel
        # ("attempted to subscribe to unknown channel" in its log): subscribed again, as a user would
        for _attempt in range(3):
            client.subscribe(["/lsu/scan/cloud", "/lsu/points"])
            if bridge_subscribed(["/lsu/scan/cloud", "/lsu/points"], timeout_s=20):
                break
        else:
            raise AssertionError(f"the bridge never subscribed to the scan topics:\n{graph.output[-3000:]}")
        play = subprocess.run([LSU, "bag", "play", str(BAG), "--topics", *REPLAYED, "--wait-subscribers", "60",
                               *REPLAY_GRAPH_READERS],
                              capture_output=True, text=True, timeout=180)
        assert play.returncode == 0, play.stdout + play.stderr
        received = {"/lsu/scan/cloud": [], "/lsu/points": []}
        try:
            while not received["/lsu/scan/cloud"]:
                topic, _, payload = client.next_message(timeout_s=60)
                received[topic].append(payload)
        except ProtocolError as exc:  # what the graph and the player said tells why (a node's error, a late reader)
            raise AssertionError(f"{exc}\n--- lsu bag play:\n{play.stdout}{play.stderr}\n--- lsu launch replay:\n"
                                 f"{graph.output[-6000:]}") from None
        replayed = xyz(received["/lsu/scan/cloud"][0], store)
        assert replayed.shape == expected.shape
        assert np.max(np.abs(replayed - expected)) <= 1e-6
        # per-snap points arrived while the scan was replayed (best effort: most of them), each one a point the
        # recording's per-snap messages hold; the scan cloud is made of those points (less the ones its
        # grazing-view rule drops)
        recorded_points = [xyz(m.data, store) for m in read_messages(BAG, ["/lsu/points"])]
        assert len(received["/lsu/points"]) >= 0.8 * len(recorded_points)
        snaps = np.concatenate([xyz(p, store) for p in received["/lsu/points"]])
        recorded_union = set(map(tuple, np.concatenate(recorded_points).tolist()))
        assert all(tuple(point) in recorded_union for point in snaps.tolist())
        assert all(tuple(point) in recorded_union for point in expected.tolist())

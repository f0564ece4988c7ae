"""foxglove_bridge seen by an independent Foxglove WebSocket client (lsu_view.wsclient, written from the
protocol specification): channels with ROS 2 schemas, CDR passed through byte for byte, points that
decode (with rosbags) to the analytic shape that was published, latched topics for late clients,
images thinned to image_max_hz."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosbags.typesys import Stores, get_typestore
from sensor_msgs.msg import Image, PointCloud2, PointField

from lsu_common.arrays import AnyArray
from lsu_view.channels import RateLimiter, topic_kind
from lsu_view.node import FoxgloveBridgeNode
from lsu_view.wsclient import FoxgloveClient, ProtocolError

CENTRE = np.array([0.01, -0.02, 0.30])
RADIUS = 0.05
SCAN_DATA = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


def sphere_points(n: int, seed: int) -> AnyArray:
    """``n`` points on the sphere (CENTRE, RADIUS), seeded."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    return (CENTRE + RADIUS * v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)


def cloud_msg(points: AnyArray, frame: str = "lsu_left_optical") -> PointCloud2:
    msg = PointCloud2()
    msg.header.frame_id = frame
    msg.height, msg.width = 1, len(points)
    msg.fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1) for i, n in enumerate("xyz")]
    msg.is_bigendian, msg.point_step, msg.row_step, msg.is_dense = False, 12, 12 * len(points), True
    msg.data = points.tobytes()
    return msg


def decode_xyz(payload: bytes, store) -> AnyArray:
    """x y z of a PointCloud2 CDR payload, decoded with rosbags (not with the code under test)."""
    cloud = store.deserialize_cdr(payload, "sensor_msgs/msg/PointCloud2")
    offsets = {f.name: f.offset for f in cloud.fields}
    raw = np.frombuffer(cloud.data.tobytes(), dtype=np.uint8).reshape(cloud.width * cloud.height, cloud.point_step)
    return np.stack([raw[:, offsets[a]:offsets[a] + 4].copy().view("<f4")[:, 0] for a in "xyz"], axis=1)


@pytest.fixture
def bridge(ros_node):
    node = ros_node.add(FoxgloveBridgeNode(context=ros_node.context, parameter_overrides=[
        Parameter("port", value=0), Parameter("graph_poll_s", value=0.1)]))
    spinner = threading.Thread(target=ros_node.executor.spin, daemon=True)
    spinner.start()
    yield node
    ros_node.executor.shutdown(timeout_sec=2.0)
    spinner.join(timeout=5.0)


def wait(predicate, timeout_s: float = 20.0) -> bool:
    import time

    end = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > end:
            return predicate()
        time.sleep(0.02)
    return True


def test_rate_limiter_thins_a_burst_to_the_rate_and_zero_passes_everything():
    limiter = RateLimiter(2.0)
    times = [0.0, 0.1, 0.2, 0.49, 0.5, 0.6, 1.0, 1.01]
    assert [limiter.allow("a", t) for t in times] == [True, False, False, False, True, False, True, False]
    assert limiter.allow("b", 0.1)  # per topic
    limiter.max_hz = 0.0
    assert all(limiter.allow("a", 1.02) for _ in range(5))
    with pytest.raises(ValueError):
        limiter.max_hz = -1.0


def test_topic_kind_from_type_and_offered_durability():
    assert topic_kind("sensor_msgs/msg/PointCloud2", ["transient_local"]) == "latched"
    assert topic_kind("sensor_msgs/msg/Image", ["reliable", "volatile"][1:]) == "image"
    assert topic_kind("sensor_msgs/msg/Image", ["transient_local", "volatile"]) == "image"
    assert topic_kind("lsu_interfaces/msg/LaserLine", ["volatile"]) == "stream"


def test_client_receives_points_byte_for_byte_and_they_lie_on_the_published_sphere(ros_node, bridge):
    store = get_typestore(Stores.ROS2_JAZZY)
    points_pub = ros_node.node.create_publisher(PointCloud2, "/lsu/points", SCAN_DATA)
    cloud_pub = ros_node.node.create_publisher(PointCloud2, "/lsu/scan/cloud", LATCHED)
    whole = sphere_points(2000, seed=3)
    cloud_pub.publish(cloud_msg(whole))  # latched, before any client exists
    snap = sphere_points(300, seed=4)
    snap_msg = cloud_msg(snap)
    delivered = []  # what DDS hands any raw subscriber: the bytes the bridge must pass on unchanged
    ros_node.node.create_subscription(PointCloud2, "/lsu/points", delivered.append, SCAN_DATA, raw=True)
    assert wait(lambda: {"/lsu/points", "/lsu/scan/cloud"} <= set(bridge.offers))
    with FoxgloveClient(bridge.url) as client:
        channels = client.wait_for_topics(["/lsu/points", "/lsu/scan/cloud"])
        for channel in channels.values():
            assert (channel.encoding, channel.schema_encoding, channel.schema_name) == \
                ("cdr", "ros2msg", "sensor_msgs/msg/PointCloud2")
            assert "PointField" in channel.schema and "uint32 row_step" in channel.schema
        client.subscribe(["/lsu/points", "/lsu/scan/cloud"])
        # the latched cloud arrives although it was published before the client came
        _, _, latched = client.next_message(timeout_s=20, topic="/lsu/scan/cloud")
        np.testing.assert_array_equal(decode_xyz(latched, store), whole)
        assert wait(lambda: "/lsu/points" in bridge.watched_topics)
        got = None
        for _ in range(100):  # best-effort subscription: publish until one arrives
            points_pub.publish(snap_msg)
            try:
                got = client.next_message(timeout_s=0.2, topic="/lsu/points")
                break
            except RuntimeError:
                continue
        assert got is not None, "no /lsu/points message reached the client"
        topic, stamp_ns, payload = got
        assert wait(lambda: len(delivered) > 0)
        assert payload == delivered[0]  # passed through, not re-encoded (CDR padding bytes included)
        xyz = decode_xyz(payload, store)
        np.testing.assert_array_equal(xyz, snap)
        # independent truth: every point on the sphere (float32 rounding of a 0.3 m coordinate: < 1e-7 m)
        np.testing.assert_allclose(np.linalg.norm(xyz - CENTRE, axis=1), RADIUS, atol=1e-6)
        assert stamp_ns > 0


def test_images_are_thinned_to_image_max_hz_and_the_parameter_takes_effect(ros_node, bridge):
    pub = ros_node.node.create_publisher(Image, "/lsu/stereo/left/image_raw", SCAN_DATA)
    image = Image(height=48, width=64, encoding="bgr8", step=192, data=bytes(48 * 192))
    # one image per 1000 s: exactly one passes, however slow this host is
    assert bridge.set_parameters([Parameter("image_max_hz", value=0.001)])[0].successful
    assert wait(lambda: "/lsu/stereo/left/image_raw" in bridge.offers)
    assert bridge.offers["/lsu/stereo/left/image_raw"].kind == "image"
    with FoxgloveClient(bridge.url) as client:
        client.wait_for_topics(["/lsu/stereo/left/image_raw"])
        client.subscribe(["/lsu/stereo/left/image_raw"])
        assert wait(lambda: bridge.watched_topics == ["/lsu/stereo/left/image_raw"])
        first = None
        for _ in range(100):
            pub.publish(image)
            try:
                first = client.next_message(timeout_s=0.2)
                break
            except RuntimeError:
                continue
        assert first is not None
        for _ in range(20):
            pub.publish(image)
        with pytest.raises(RuntimeError, match="no message"):
            client.next_message(timeout_s=1.0)
        # every image once the limit is lifted
        assert bridge.set_parameters([Parameter("image_max_hz", value=0.0)])[0].successful
        received = 0
        for _ in range(20):
            pub.publish(image)
            try:
                client.next_message(timeout_s=0.5)
                received += 1
            except RuntimeError:
                pass
        assert received >= 10  # best effort on the loopback: almost all of the 20
    # the client left: the bridge drops its ROS subscription, costing the graph nothing
    assert wait(lambda: bridge.watched_topics == [])


def test_a_negative_rate_is_refused_with_a_reason(ros_node, bridge):
    result = bridge.set_parameters([Parameter("image_max_hz", value=-1.0)])[0]
    assert not result.successful and result.reason


def test_our_own_types_get_their_definitions_from_the_msg_files():
    from lsu_bags.bags import BagTypes
    from lsu_view.channels import ros2msg_schema

    types = BagTypes()
    state = ros2msg_schema("lsu_interfaces/msg/ScannerState", types)
    line = ros2msg_schema("lsu_interfaces/msg/LaserLine", types)
    # the first block is the type itself, then every type it uses, each after a MSG: line
    assert "laser_on" in state.split("=" * 80)[0] and "MSG: std_msgs/Header" in state
    assert "MSG: std_msgs/Header" in line


def test_the_server_settings_are_read_only_and_the_image_rate_is_applied(bridge):
    # the executor spins in the fixture's thread: set in-process (the same callbacks the service runs)
    for name in ("host", "port", "client_backlog_messages", "graph_poll_s"):
        before = bridge.get_parameter(name).value
        result = bridge.set_parameters([Parameter(name, value=before)])[0]
        assert not result.successful and "read-only" in result.reason, name
    assert bridge.set_parameters([Parameter("image_max_hz", value=2.5)])[0].successful
    assert bridge._image_limiter.max_hz == 2.5


def test_a_server_that_goes_away_is_reported_as_such_not_as_silence(bridge):
    # a bridge that crashed or stopped: the waiting client says the connection ended (a respawned bridge has
    # another port), instead of waiting out its timeout and reporting "no message"
    with FoxgloveClient(bridge.url) as client:
        bridge.server.stop()
        with pytest.raises(ProtocolError, match="closed") as caught:
            client.next_message(timeout_s=600)
        assert "within" not in str(caught.value)
        with pytest.raises(ProtocolError, match="closed"):
            client.wait_for_topics(["/never/advertised"], timeout_s=600)

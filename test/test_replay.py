"""A recorded scan replayed through extractor -> matcher (separate processes) gives the recorded cloud."""

import subprocess
from pathlib import Path

import numpy as np
import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2

from lsu_bringup.bags import deserialize_ros, read_messages
from lsu_bringup.testing import LSU
from lsu_common.arrays import AnyArray
from lsu_reconstruct.node import msg_to_cloud
from lsu_reconstruct.pointcloud2 import decode

BAG = Path(__file__).parent / "data" / "bags" / "scan_head"
REPLAYED = ["/lsu/scan/events", "/lsu/stereo/left/image_raw", "/lsu/stereo/right/image_raw"]
pytestmark = pytest.mark.slow


def xyz(msg: PointCloud2) -> AnyArray:
    columns = decode(msg_to_cloud(msg))
    return np.stack([columns["x"], columns["y"], columns["z"]], axis=1)


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
                           "--expect", "/lsu/scan/events=2", "--expect", "/lsu/stereo/left/image_raw=2"],
                          capture_output=True, text=True, timeout=120)
    assert play.returncode == 0, play.stdout + play.stderr
    assert ros_node.spin_until(lambda: len(clouds) >= 1, 30.0), graph.output[-3000:]
    replayed = xyz(clouds[0])
    assert replayed.shape == expected.shape
    assert np.max(np.abs(replayed - expected)) <= 1e-6

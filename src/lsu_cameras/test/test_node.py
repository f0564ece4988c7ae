"""The stereo_camera node in-process: capture service, equal stamps, latched calibration, sim truth, bad inputs."""

import numpy as np
import pytest
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image

from lsu_cameras.node import StereoCameraNode
from lsu_cameras.paths import config_dir
from lsu_cameras.sim import SimulatedRig, build_scene, load_rig
from lsu_interfaces.msg import SimTruth, StereoExtrinsics
from lsu_interfaces.srv import CaptureStereo

LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def make_node(ros_node, **params):
    overrides = [Parameter(k, value=v) for k, v in {"sim_scene": "plane", **params}.items()]
    return ros_node.add(StereoCameraNode(context=ros_node.context, parameter_overrides=overrides))


def red_column(image_msg, row):
    img = np.frombuffer(bytes(image_msg.data), np.uint8).reshape(image_msg.height, image_msg.width, 3)
    return int(np.argmax(img[row, :, 2].astype(int) - img[row, :, 1].astype(int)))


def test_capture_publishes_a_pair_with_one_stamp_and_latched_calibration(ros_node):
    make_node(ros_node)
    helper = ros_node.node
    got = {"left": [], "right": [], "info": [], "ext": []}
    helper.create_subscription(Image, "/lsu/stereo/left/image_raw", got["left"].append, 10)
    helper.create_subscription(Image, "/lsu/stereo/right/image_raw", got["right"].append, 10)
    helper.create_subscription(CameraInfo, "/lsu/stereo/left/camera_info", got["info"].append, LATCHED)
    helper.create_subscription(StereoExtrinsics, "/lsu/stereo/extrinsics", got["ext"].append, LATCHED)
    client = helper.create_client(CaptureStereo, "/lsu/stereo/capture")
    assert ros_node.spin_until(lambda: got["info"] and got["ext"], 10.0)
    assert got["info"][0].k[0] == pytest.approx(812.4) and got["info"][0].distortion_model == "plumb_bob"
    assert got["ext"][0].translation[0] == pytest.approx(-0.1217) and got["ext"][0].right_frame_id == "lsu_right_optical"

    request = CaptureStereo.Request(publish=True, return_images=True)
    response = ros_node.call(client, request)
    assert response.success, response.message
    assert ros_node.spin_until(lambda: got["left"] and got["right"], 10.0)
    left, right = got["left"][0], got["right"][0]
    assert left.header.stamp == right.header.stamp == response.stamp
    assert (left.encoding, left.width, left.height, left.header.frame_id) == ("bgr8", 640, 480, "lsu_left_optical")
    assert response.left.data == left.data and response.skew_s == 0.0


def test_sim_source_follows_sim_truth_and_falls_back_to_the_parameter(ros_node):
    make_node(ros_node, carriage_position_steps=235.0)
    helper = ros_node.node
    client = helper.create_client(CaptureStereo, "/lsu/stereo/capture")
    truth_pub = helper.create_publisher(SimTruth, "/lsu/sim/truth", 10)
    rig = SimulatedRig(load_rig(), build_scene("plane", load_rig()))
    expected = {p: rig.laser_truth(p).left for p in (235.0, 120.0)}
    row = 240

    def column_for(p):
        cam = expected[p]
        return cam.pixels[np.round(cam.pixels[:, 1]) == row][0, 0]

    response = ros_node.call(client, CaptureStereo.Request(publish=False, return_images=True))
    assert abs(red_column(response.left, row) - column_for(235.0)) <= 1

    msg = SimTruth(position_steps=120.0, laser_on=True, homed=True)
    msg.header.stamp = helper.get_clock().now().to_msg()
    truth_pub.publish(msg)
    node = [n for n in ros_node._nodes if isinstance(n, StereoCameraNode)][0]
    assert ros_node.spin_until(lambda: node._truth is not None, 10.0)
    response = ros_node.call(client, CaptureStereo.Request(publish=False, return_images=True))
    assert abs(red_column(response.left, row) - column_for(120.0)) <= 1


@pytest.mark.parametrize("params, expected", [
    ({"source": "folder", "folder": "/nonexistent/lsu_pairs"}, "image folder '/nonexistent/lsu_pairs' not found"),
    ({"source": "v4l2", "devices": ["/dev/lsu_none0", "/dev/lsu_none1"]}, "cannot open the left camera"),
    ({"source": "v4l2", "profile": "bright"}, "camera profile 'bright' not found"),
])
@pytest.mark.fault('camera: missing/broken source')
def test_bad_source_keeps_the_node_up_and_capture_says_why(ros_node, params, expected):
    make_node(ros_node, **params)
    client = ros_node.node.create_client(CaptureStereo, "/lsu/stereo/capture")
    response = ros_node.call(client, CaptureStereo.Request())
    assert not response.success and expected in response.message


@pytest.mark.fault('calibration: size mismatch')
def test_calibration_of_another_size_is_not_published(ros_node, tmp_path):
    sim = config_dir() / "calibration" / "sim"
    for name in ("left.yaml", "right.yaml", "stereo.yaml"):
        text = (sim / name).read_text().replace("image_width: 640", "image_width: 800")
        (tmp_path / name).write_text(text)
    node = make_node(ros_node, calibration_dir=str(tmp_path))
    assert node.calibration is None
    assert "800x480 images but the cameras give 640x480" in node.status_message
    client = ros_node.node.create_client(CaptureStereo, "/lsu/stereo/capture")
    assert ros_node.call(client, CaptureStereo.Request(publish=False)).success  # images still flow

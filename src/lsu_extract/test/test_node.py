"""The laser_extractor node in-process: image in, LaserLine out with the same header; bad input reported."""


import numpy as np
import pytest
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.duration import Duration
from rclpy.parameter import Parameter
from sensor_msgs.msg import Image

from lsu_common import qos
from lsu_common.arrays import AnyArray
from lsu_extract.extractor import DEFAULT_METHOD
from lsu_extract.node import EVENTS_QOS, SCAN_DATA_QOS, LaserExtractorNode
from lsu_extract.synthetic import LineScene, render_line
from lsu_interfaces.msg import LaserLine, ScanEvent


def image_msg(bgr: AnyArray, sec: int, frame: str = "lsu_left_optical", encoding: str = "bgr8") -> Image:
    msg = Image(height=bgr.shape[0], width=bgr.shape[1], encoding=encoding, step=bgr.shape[1] * 3,
                data=bgr.tobytes())
    msg.header.stamp.sec = sec
    msg.header.stamp.nanosec = 12345
    msg.header.frame_id = frame
    return msg


def test_image_in_laser_line_out_with_the_same_header(ros_node):
    extractor = ros_node.add(LaserExtractorNode(context=ros_node.context))
    assert extractor.get_namespace() == "/lsu"
    lines: list[LaserLine] = []
    ros_node.node.create_subscription(LaserLine, "/lsu/stereo/right/laser_line", lines.append, SCAN_DATA_QOS)
    pub = ros_node.node.create_publisher(Image, "/lsu/stereo/right/image_raw", SCAN_DATA_QOS)
    assert ros_node.spin_until(lambda: pub.get_subscription_count() > 0 and
                               extractor.publishers_["right"].get_subscription_count() > 0, 10)
    bgr, truth, _ = render_line(LineScene(textured=False, height=120, seed=1))
    pub.publish(image_msg(bgr, 42, "lsu_right_optical"))
    assert ros_node.spin_until(lambda: len(lines) >= 1, 10)
    line = lines[0]
    assert (line.header.stamp.sec, line.header.stamp.nanosec, line.header.frame_id) == (42, 12345, "lsu_right_optical")
    assert (line.image_width, line.image_height, line.method) == (640, 120, DEFAULT_METHOD)
    u, v = np.asarray(line.u), np.asarray(line.v)
    assert len(u) == len(v) == len(line.peak) == len(line.width) == len(line.quality) == 120
    assert np.all(np.isfinite(u)) and np.sqrt(np.mean((u - truth[v.astype(int)]) ** 2)) < 0.1
    assert line.rows_searched == 120


def test_a_busy_extractor_loses_no_frame_of_a_stream(ros_node):
    """The camera counts a pair as delivered once every reader's DDS acknowledged it, which happens when the
    pair is in the reader's queue, not when the node took it: an extractor busy for many frame periods
    (a loaded host) must still find every frame there."""
    extractor = ros_node.add(LaserExtractorNode(context=ros_node.context))
    lines: list[LaserLine] = []
    ros_node.node.create_subscription(LaserLine, "/lsu/stereo/left/laser_line", lines.append, qos.reliable(50))
    pub = ros_node.node.create_publisher(Image, "/lsu/stereo/left/image_raw", qos.SCAN_DATA)  # the camera's QoS
    assert ros_node.spin_until(lambda: pub.get_subscription_count() > 0 and
                               extractor.publishers_["left"].get_subscription_count() > 0, 10)
    bgr, _, _ = render_line(LineScene(textured=False, height=48, width=160, u0_px=70.4, seed=3))
    frames = 20  # 0.67 s of a 30 fps stream with the extractor not running at all
    for sec in range(1, frames + 1):
        pub.publish(image_msg(bgr, sec))
        assert pub.wait_for_all_acked(Duration(seconds=10))  # what the camera's stream waits for
    assert ros_node.spin_until(lambda: len(lines) >= frames, 20)
    assert [m.header.stamp.sec for m in lines] == list(range(1, frames + 1))


@pytest.mark.fault('camera: wrong encoding and size change')
def test_bad_encoding_and_size_change_are_reported_not_fatal(ros_node):
    extractor = ros_node.add(LaserExtractorNode(context=ros_node.context))
    lines: list[LaserLine] = []
    diags: list[DiagnosticArray] = []
    ros_node.node.create_subscription(LaserLine, "/lsu/stereo/left/laser_line", lines.append, SCAN_DATA_QOS)
    ros_node.node.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 10)
    pub = ros_node.node.create_publisher(Image, "/lsu/stereo/left/image_raw", SCAN_DATA_QOS)
    assert ros_node.spin_until(lambda: pub.get_subscription_count() > 0 and
                               extractor.diagnostics.get_subscription_count() > 0 and
                               extractor.publishers_["left"].get_subscription_count() > 0, 10)
    bgr, _, _ = render_line(LineScene(textured=False, height=64, width=160, u0_px=80.3, seed=2))
    pub.publish(image_msg(bgr, 1, encoding="16UC1"))  # unsupported
    assert ros_node.spin_until(lambda: len(diags) >= 1, 10)
    status = diags[0].status[0]
    assert status.level == DiagnosticStatus.ERROR and "unsupported image encoding '16UC1'" in status.message
    pub.publish(image_msg(bgr, 2))  # good again: a line, then an OK status
    assert ros_node.spin_until(lambda: len(lines) >= 1 and len(diags) >= 2, 10)
    assert diags[1].status[0].level == DiagnosticStatus.OK and lines[0].header.stamp.sec == 2
    pub.publish(image_msg(np.ascontiguousarray(bgr[:32]), 3))  # size change: dropped and reported
    assert ros_node.spin_until(lambda: len(diags) >= 3, 10)
    assert "image size changed from 160x64 to 160x32" in diags[2].status[0].message
    pub.publish(image_msg(bgr, 4))
    assert ros_node.spin_until(lambda: len(lines) >= 2, 10)
    assert [m.header.stamp.sec for m in lines] == [2, 4] and extractor.dropped["left"] == 2


def test_parameters_are_validated_with_a_readable_reason(ros_node):
    extractor = ros_node.add(LaserExtractorNode(context=ros_node.context))
    bad = extractor.set_parameters([Parameter("method", value="sobel")])[0]
    assert not bad.successful and "must be one of: thesis" in bad.reason
    bad = extractor.set_parameters([Parameter("min_width_px", value=30.0)])[0]
    assert not bad.successful and "smaller than max_width_px" in bad.reason
    good = extractor.set_parameters([Parameter("method", value="thesis"), Parameter("min_contrast", value=20.0)])
    assert all(r.successful for r in good)
    assert extractor.params.method == "thesis" and extractor.params.min_contrast == 20.0


def texture_setup(ros_node):
    """An extractor, its left lines, image and event publishers (matched), and a laser frame and its laser-off
    frame: the laser only in rows 100..380, a red bar (a red object, not laser) at column 500 in every row."""
    extractor = ros_node.add(LaserExtractorNode(context=ros_node.context))
    lines: list[LaserLine] = []
    ros_node.node.create_subscription(LaserLine, "/lsu/stereo/left/laser_line", lines.append, SCAN_DATA_QOS)
    pub = ros_node.node.create_publisher(Image, "/lsu/stereo/left/image_raw", SCAN_DATA_QOS)
    events = ros_node.node.create_publisher(ScanEvent, "/lsu/scan/events", EVENTS_QOS)
    assert ros_node.spin_until(lambda: pub.get_subscription_count() > 0 and events.get_subscription_count() > 0 and
                               extractor.publishers_["left"].get_subscription_count() > 0, 10)
    scene = LineScene(first_row=100, last_row=380, seed=3, texture_seed=3)
    lit, truth, visible = render_line(scene)
    off, _, _ = render_line(scene.with_(amplitude_dn=0.0, seed=4))
    for frame in (lit, off):
        frame[:, 499:502] = (30, 30, 220)
    return extractor, lines, pub, events, lit, off, truth, visible


def test_background_texture_subtracts_the_laser_off_frame_the_texture_event_names(ros_node):
    extractor, lines, pub, events, lit, off, truth, visible = texture_setup(ros_node)
    assert extractor.set_parameters([Parameter("background", value="texture")])[0].successful
    assert not extractor.set_parameters([Parameter("background", value="dark")])[0].successful
    pub.publish(image_msg(lit, 1))  # no laser-off frame yet: the bar is taken for the laser
    pub.publish(image_msg(off, 10))
    assert ros_node.spin_until(lambda: len(lines) >= 2, 10)
    assert np.count_nonzero(~visible[np.asarray(lines[0].v).astype(int)]) > 100
    events.publish(ScanEvent(type=ScanEvent.TEXTURE, scan_id="s1", image_stamp=Time(sec=10, nanosec=12345)))
    assert ros_node.spin_until(lambda: "left" in extractor.textures, 10)
    pub.publish(image_msg(lit, 11))
    assert ros_node.spin_until(lambda: len(lines) >= 3, 10)
    u, v = np.asarray(lines[2].u), np.asarray(lines[2].v).astype(int)
    assert np.all(visible[v]) and len(v) >= 0.99 * np.count_nonzero(visible)
    assert np.max(np.abs(u - truth[v])) < 0.5
    events.publish(ScanEvent(type=ScanEvent.STARTED, scan_id="s2"))  # a new scan: its own laser-off pair
    assert ros_node.spin_until(lambda: not extractor.textures, 10)


@pytest.mark.parametrize("next_event", ["texture", "snap", "none"])
def test_frames_that_overtake_their_scans_texture_event_wait_for_it(ros_node, monkeypatch, next_event):
    """A stop-snap scan's laser-off pair and first snap delivered before its TEXTURE event (events and images travel
    on separate topics, unordered between them): held, then extracted minus that pair, in the order they came. A
    scan's SNAP (no pair) releases them as they are; without any event they go out after TEXTURE_WAIT_S."""
    import lsu_extract.node as node_module

    monkeypatch.setattr(node_module, "TEXTURE_WAIT_S", 0.3)
    extractor, lines, pub, events, lit, off, truth, visible = texture_setup(ros_node)
    events.publish(ScanEvent(type=ScanEvent.STARTED, scan_id="s1"))
    assert ros_node.spin_until(lambda: extractor._held is not None, 10)
    pub.publish(image_msg(off, 10))
    pub.publish(image_msg(lit, 11))
    assert ros_node.spin_until(lambda: extractor.frames_held == 2, 10)
    assert not lines  # nothing goes out before the scan's next event
    if next_event == "texture":
        events.publish(ScanEvent(type=ScanEvent.TEXTURE, scan_id="s1", image_stamp=Time(sec=10, nanosec=12345)))
    elif next_event == "snap":
        events.publish(ScanEvent(type=ScanEvent.SNAP, scan_id="s1", image_stamp=Time(sec=11, nanosec=12345)))
    assert ros_node.spin_until(lambda: len(lines) >= 2, 10)
    assert [m.header.stamp.sec for m in lines] == [10, 11] and extractor.frames_held == 0
    u, v = np.asarray(lines[1].u), np.asarray(lines[1].v).astype(int)
    bar = np.count_nonzero(~visible[v])
    if next_event == "texture":  # minus the pair: the laser rows only, on the line
        assert bar == 0 and len(v) >= 0.99 * np.count_nonzero(visible)
        assert np.max(np.abs(u - truth[v])) < 0.5
    else:  # alone: the red bar is taken for the laser where the laser is not
        assert bar > 100
    pub.publish(image_msg(lit, 12))  # after the hold: straight through
    assert ros_node.spin_until(lambda: len(lines) >= 3, 10)


def test_every_extractor_parameter_takes_effect_when_set_through_the_parameter_service(ros_node):
    extractor = ros_node.add(LaserExtractorNode(context=ros_node.context))
    new = {"method": "thesis", "min_contrast": 20.0, "contrast_sigmas": 4.0, "ambiguity_ratio": 0.5,
           "min_width_px": 2.0, "max_width_px": 20.0, "window_px": 16, "coarse_step_rows": 4, "saturation_level": 240,
           "clipped_centre": "red", "adaptive_width_px": 7.0, "grow_wide": False, "red_rise_ratio": 0.3, "red_threshold": 120,
           "blue_threshold": 90}
    cases = {name: (value, lambda name=name, value=value: getattr(extractor.params, name) == value)
             for name, value in new.items()}
    assert extractor.background == "texture"  # the default: the scan's laser-off pair once it is in
    cases["background"] = ("none", lambda: extractor.background == "none")
    assert all(getattr(extractor.params, name) != value for name, value in new.items()), "pick values that change"
    ros_node.check_parameters(extractor, cases)
    refused = ros_node.set_parameter("/lsu/laser_extractor", "background", "sky")
    assert not refused.successful and "must be one of" in refused.reason and extractor.background == "none"

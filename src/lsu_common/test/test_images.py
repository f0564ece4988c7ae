"""The image codec on messages: ROS encodings in, BGR arrays out, and the camera's bgr8 messages back."""

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from sensor_msgs.msg import Image

from lsu_common.images import (
    SUPPORTED_ENCODINGS,
    ImageFormatError,
    UnsupportedEncodingError,
    bgr_to_msg,
    encode_image,
    msg_to_array,
    msg_to_bgr,
)


def _bgr(seed=3, h=6, w=8):
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def test_bgr8_message_round_trip_keeps_pixels_stamp_and_frame():
    bgr = _bgr()
    msg = bgr_to_msg(bgr, Time(sec=5, nanosec=6), "lsu_left_optical")
    assert (msg.height, msg.width, msg.step, msg.encoding) == (6, 8, 24, "bgr8")
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (5, 6, "lsu_left_optical")
    np.testing.assert_array_equal(msg_to_bgr(msg), bgr)


@pytest.mark.parametrize("encoding", ["rgb8", "bgra8", "rgba8"])
def test_colour_encodings_decode_to_the_same_bgr(encoding):
    bgr = _bgr()
    msg = Image(height=6, width=8, encoding=encoding, step=8 * (3 if encoding == "rgb8" else 4),
                data=encode_image(bgr, encoding))
    np.testing.assert_array_equal(msg_to_bgr(msg), bgr)


def test_mono_with_padded_rows_is_mono_as_array_and_grey_bgr():
    mono = np.arange(4 * 5, dtype=np.uint8).reshape(4, 5)
    rows = np.zeros((4, 7), np.uint8)
    rows[:, :5] = mono
    msg = Image(height=4, width=5, encoding="mono8", step=7, data=rows.tobytes())
    np.testing.assert_array_equal(msg_to_array(msg), mono)
    bgr = msg_to_bgr(msg)
    assert bgr.shape == (4, 5, 3) and all(np.array_equal(bgr[..., c], mono) for c in range(3))


def test_opencv_type_names_are_read_as_their_ros_encodings():
    bgr = _bgr()
    msg = Image(height=6, width=8, encoding="8UC3", step=24, data=bgr.tobytes())
    np.testing.assert_array_equal(msg_to_bgr(msg), bgr)
    assert "8uc3" not in SUPPORTED_ENCODINGS  # an alias, not an encoding of its own


def test_bad_messages_say_what_is_wrong():
    with pytest.raises(UnsupportedEncodingError, match="unsupported image encoding '16UC1'.*bgr8"):
        msg_to_bgr(Image(height=2, width=2, encoding="16UC1", step=4, data=bytes(8)))
    with pytest.raises(ImageFormatError, match="too short"):
        msg_to_bgr(Image(height=4, width=4, encoding="bgr8", step=12, data=bytes(40)))
    with pytest.raises(ImageFormatError, match=r"\(H, W, 3\)"):
        bgr_to_msg(np.zeros((4, 4), np.uint8), Time(), "x")

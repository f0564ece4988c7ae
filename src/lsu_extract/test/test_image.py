"""Encodings: every supported ROS encoding decodes to the right BGR/mono pixels; bad buffers are named."""

import numpy as np
import pytest

from lsu_extract.extractor import extract_laser_line
from lsu_extract.image import (
    SUPPORTED_ENCODINGS,
    ImageFormatError,
    UnsupportedEncodingError,
    decode_image,
    encode_image,
)
from lsu_extract.synthetic import LineScene, render_line

BAYER = [e for e in SUPPORTED_ENCODINGS if e.startswith("bayer_")]


def test_packed_colour_encodings_round_trip_exactly():
    rng = np.random.default_rng(1)
    bgr = rng.integers(0, 256, (6, 8, 3), dtype=np.uint8)
    for encoding in ("bgr8", "rgb8", "bgra8", "rgba8"):
        np.testing.assert_array_equal(decode_image(encode_image(bgr, encoding), 8, 6, encoding), bgr)
    rgb_bytes = np.ascontiguousarray(bgr[..., ::-1]).tobytes()  # independent: numpy channel flip
    np.testing.assert_array_equal(decode_image(rgb_bytes, 8, 6, "rgb8"), bgr)


def test_row_padding_is_skipped():
    mono = np.arange(12, dtype=np.uint8).reshape(3, 4)
    padded = np.zeros((3, 7), np.uint8)
    padded[:, :4] = mono
    np.testing.assert_array_equal(decode_image(padded.tobytes(), 4, 3, "mono8", step=7), mono)


@pytest.mark.parametrize("encoding", BAYER)
def test_bayer_pattern_names_map_to_the_right_colours(encoding):
    # a pure red scene: the demosaiced image must be red, whatever the pattern
    red = np.zeros((8, 8, 3), np.uint8)
    red[..., 2] = 200
    out = decode_image(encode_image(red, encoding), 8, 8, encoding)
    inner = out[2:-2, 2:-2].reshape(-1, 3)
    assert np.all(inner[:, 2] == 200) and np.all(inner[:, :2] == 0)


@pytest.mark.parametrize("encoding", SUPPORTED_ENCODINGS)
def test_every_encoding_gives_the_line(encoding):
    scene = LineScene(textured=False, ambient=0.0 if encoding == "mono8" else 0.1, seed=11)
    bgr, truth, _ = render_line(scene)
    image = decode_image(encode_image(bgr, encoding), bgr.shape[1], bgr.shape[0], encoding)
    result = extract_laser_line(image)
    assert len(result) >= bgr.shape[0] - 2
    # demosaicing interpolates half the red samples: looser, still far below a pixel
    tolerance = 0.25 if encoding.startswith("bayer_") else 0.1
    assert np.sqrt(np.mean((result.u - truth[result.v.astype(int)]) ** 2)) <= tolerance


def test_unsupported_encoding_is_a_typed_error_naming_the_supported_ones():
    with pytest.raises(UnsupportedEncodingError, match="unsupported image encoding '16UC1'.*bgr8"):
        decode_image(b"\0" * 8, 2, 2, "16UC1")
    assert issubclass(UnsupportedEncodingError, ValueError)


def test_short_buffer_and_bad_step_are_named():
    with pytest.raises(ImageFormatError, match="too short"):
        decode_image(b"\0" * 10, 4, 4, "mono8")
    with pytest.raises(ImageFormatError, match="row step 3 bytes"):
        decode_image(b"\0" * 48, 4, 4, "bgr8", step=3)
    with pytest.raises(ImageFormatError, match="empty"):
        decode_image(b"", 0, 4, "bgr8")


# ------------------------------------------------------------------- serialized Image (raw subscription)
def _image_fields(frame_id: str, encoding: str, height: int, width: int, step: int, seed: int):
    rng = np.random.default_rng(seed)
    return dict(sec=-5 if seed == 3 else 1_800_000_000 + seed, nanosec=123_456_789, frame_id=frame_id, height=height,
                width=width, encoding=encoding, is_bigendian=seed % 2, step=step,
                data=rng.integers(0, 256, height * step, dtype=np.uint8))


@pytest.mark.parametrize("frame_id", ["", "a", "ab", "abc", "lsu_left_optical", "cam_é"])
@pytest.mark.parametrize("encoding", ["bgr8", "mono8", "rgba8"])
def test_serialized_image_fields_and_pixels_as_rclpy_wrote_them(frame_id, encoding):
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import Image

    from lsu_extract.image import parse_image_cdr

    f = _image_fields(frame_id, encoding, 5, 7, 7 * {"bgr8": 3, "mono8": 1, "rgba8": 4}[encoding] + 3, len(frame_id))
    msg = Image(height=f["height"], width=f["width"], encoding=encoding, is_bigendian=f["is_bigendian"], step=f["step"],
                data=f["data"].tobytes())
    msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id = f["sec"], f["nanosec"], frame_id
    got = parse_image_cdr(serialize_message(msg))
    assert (got.sec, got.nanosec, got.frame_id, got.height, got.width, got.encoding, got.is_bigendian, got.step) == \
        (f["sec"], f["nanosec"], frame_id, 5, 7, encoding, f["is_bigendian"], f["step"])
    assert bytes(got.data) == f["data"].tobytes()


@pytest.mark.parametrize("little_endian", [True, False])
def test_serialized_image_from_rosbags_in_both_byte_orders(little_endian):
    from rosbags.typesys import Stores, get_typestore

    from lsu_extract.image import parse_image_cdr

    store = get_typestore(Stores.ROS2_JAZZY)
    T = store.types
    f = _image_fields("lsu_right_optical", "bgr8", 4, 6, 18, 3)
    msg = T["sensor_msgs/msg/Image"](
        header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=f["sec"], nanosec=f["nanosec"]),
                                        frame_id=f["frame_id"]),
        height=4, width=6, encoding="bgr8", is_bigendian=f["is_bigendian"], step=18, data=f["data"])
    raw = store.serialize_cdr(msg, "sensor_msgs/msg/Image", little_endian=little_endian)
    got = parse_image_cdr(raw)
    assert (got.sec, got.nanosec, got.frame_id, got.width, got.height, got.step) == \
        (-5, 123_456_789, "lsu_right_optical", 6, 4, 18)
    np.testing.assert_array_equal(decode_image(got.data, got.width, got.height, got.encoding, got.step),
                                  f["data"].reshape(4, 18).reshape(4, 6, 3))


def test_truncated_or_foreign_serialized_image_is_named():
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import Image

    from lsu_extract.image import parse_image_cdr

    msg = Image(height=2, width=3, encoding="mono8", step=3, data=bytes(range(6)))
    msg.header.frame_id = "cam"
    raw = serialize_message(msg)
    for cut in range(len(raw)):
        with pytest.raises(ImageFormatError, match=r"serialized Image"):
            parse_image_cdr(raw[:cut])
    with pytest.raises(ImageFormatError, match=r"no CDR encapsulation header.*sensor_msgs/Image"):
        parse_image_cdr(b"\x07\x07\x00\x00" + raw[4:])

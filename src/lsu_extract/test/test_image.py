"""Encodings: every supported ROS encoding decodes to the right BGR/mono pixels; bad buffers are named."""

import numpy as np
import pytest

from lsu_extract.extractor import extract_laser_line
from lsu_extract.image import (SUPPORTED_ENCODINGS, ImageFormatError, UnsupportedEncodingError, decode_image,
                               encode_image)
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

"""The one sensor_msgs/Image codec: image buffers to the two array layouts LSU works on, and back.

Arrays are BGR (H, W, 3) uint8 or mono (H, W) uint8. Every supported ROS encoding is mapped onto
one of them with the fewest copies possible: bgr8 and mono8 are zero-copy views of the buffer when
the row step has no padding. Bayer images are demosaiced with OpenCV (the table cv_bridge uses);
cv_bridge itself is not on PyPI, which is why this is written here.
"""

from __future__ import annotations

import array
from typing import Any

import cv2
import numpy as np

from lsu_common.arrays import AnyArray

BufferLike = bytes | bytearray | memoryview | AnyArray

# OpenCV names Bayer patterns after the 2x2 block starting at pixel (1, 1), ROS after the one
# at (0, 0); so ROS "rggb" is OpenCV "BG" (the same table cv_bridge uses).
_BAYER_TO_BGR: dict[str, int] = {
    "bayer_rggb8": cv2.COLOR_BayerBG2BGR,
    "bayer_bggr8": cv2.COLOR_BayerRG2BGR,
    "bayer_gbrg8": cv2.COLOR_BayerGR2BGR,
    "bayer_grbg8": cv2.COLOR_BayerGB2BGR,
}
_CHANNELS: dict[str, int] = {"bgr8": 3, "rgb8": 3, "bgra8": 4, "rgba8": 4, "mono8": 1, **{k: 1 for k in _BAYER_TO_BGR}}

SUPPORTED_ENCODINGS: tuple[str, ...] = tuple(sorted(_CHANNELS))
# OpenCV type names some drivers publish for the same layouts
_ALIASES: dict[str, str] = {"8uc1": "mono8", "8uc3": "bgr8"}


class ImageFormatError(ValueError):
    """The image cannot be read: unsupported encoding, wrong size or a short buffer."""


class UnsupportedEncodingError(ImageFormatError):
    """The image encoding is not one of `SUPPORTED_ENCODINGS`."""


def check_encoding(encoding: str) -> str:
    """Return the normalised encoding name, or raise `UnsupportedEncodingError` naming the supported ones."""
    name = encoding.strip().lower()
    name = _ALIASES.get(name, name)
    if name not in _CHANNELS:
        raise UnsupportedEncodingError(
            f"unsupported image encoding '{encoding}': LSU reads {', '.join(SUPPORTED_ENCODINGS)}; "
            "configure the camera (or a converter node) to publish one of them")
    return name


def decode_image(data: BufferLike, width: int, height: int, encoding: str, step: int = 0) -> AnyArray:
    """An image buffer as a BGR (H, W, 3) or mono (H, W) uint8 array.

    Args:
        data: the raw bytes (``sensor_msgs/Image.data``) or an array holding them.
        width, height: image size in pixels.
        encoding: a ROS encoding name (see ``SUPPORTED_ENCODINGS``); Bayer images are demosaiced.
        step: bytes per row (0 = tightly packed).

    Raises:
        UnsupportedEncodingError: the encoding is not supported.
        ImageFormatError: the size or step does not match the buffer.
    """
    name = check_encoding(encoding)
    channels = _CHANNELS[name]
    if width <= 0 or height <= 0:
        raise ImageFormatError(f"image size {width}x{height} is empty; the camera sent no pixels")
    row_bytes = width * channels
    step = step or row_bytes
    if step < row_bytes:
        raise ImageFormatError(f"row step {step} bytes is shorter than a {width} px {name} row ({row_bytes} bytes)")
    raw = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) else data.reshape(-1).view(np.uint8)
    if raw.size < step * (height - 1) + row_bytes:
        raise ImageFormatError(f"buffer of {raw.size} bytes is too short for {width}x{height} {name} "
                               f"with step {step} (needs {step * (height - 1) + row_bytes})")
    rows = np.lib.stride_tricks.as_strided(raw, shape=(height, row_bytes), strides=(step, 1), writeable=False)
    if step != row_bytes:
        rows = np.ascontiguousarray(rows)
    if channels == 1:
        plane = rows.reshape(height, width)
        if name in _BAYER_TO_BGR:
            return cv2.cvtColor(np.ascontiguousarray(plane), _BAYER_TO_BGR[name])
        return plane
    pixels = rows.reshape(height, width, channels)
    if name == "bgr8":
        return pixels
    if name == "rgb8":
        return cv2.cvtColor(np.ascontiguousarray(pixels), cv2.COLOR_RGB2BGR)
    if name == "bgra8":
        return cv2.cvtColor(np.ascontiguousarray(pixels), cv2.COLOR_BGRA2BGR)
    return cv2.cvtColor(np.ascontiguousarray(pixels), cv2.COLOR_RGBA2BGR)


def encode_image(bgr: AnyArray, encoding: str) -> bytes:
    """Inverse of `decode_image` for tests and tools: BGR (or mono) uint8 -> packed buffer of ``encoding``.

    Bayer encodings sample the colour image on the named 2x2 pattern (no interpolation).
    """
    name = check_encoding(encoding)
    image = np.asarray(bgr, dtype=np.uint8)
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if name == "bgr8":
        out = image
    elif name == "rgb8":
        out = image[..., ::-1]
    elif name == "bgra8":
        out = cv2.cvtColor(image, cv2.COLOR_BGR2BGRA)
    elif name == "rgba8":
        out = cv2.cvtColor(image, cv2.COLOR_BGR2RGBA)
    elif name == "mono8":
        out = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    else:
        pattern = name[len("bayer_"):len("bayer_") + 4]  # e.g. "rggb": colours at (0,0) (0,1) (1,0) (1,1)
        channel = {"b": 0, "g": 1, "r": 2}
        out = np.empty(image.shape[:2], np.uint8)
        for k, (dy, dx) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
            out[dy::2, dx::2] = image[dy::2, dx::2, channel[pattern[k]]]
    return np.ascontiguousarray(out).tobytes()


def msg_to_array(msg: Any) -> AnyArray:
    """A sensor_msgs/Image (ROS or rosbags message) as BGR (H, W, 3) or mono (H, W) uint8 (see `decode_image`)."""
    return decode_image(msg.data, int(msg.width), int(msg.height), str(msg.encoding), int(msg.step))


def msg_to_bgr(msg: Any) -> AnyArray:
    """A sensor_msgs/Image as a contiguous BGR (H, W, 3) uint8 array (mono is repeated on the 3 channels)."""
    image = msg_to_array(msg)
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    return np.ascontiguousarray(image)


def bgr_to_msg(image: AnyArray, stamp: Any, frame_id: str) -> Any:
    """A bgr8 sensor_msgs/Image of a BGR (H, W, 3) uint8 array, with one copy of the pixels."""
    from sensor_msgs.msg import Image

    if image.ndim != 3 or image.shape[2] != 3:
        raise ImageFormatError(f"bgr8 needs an (H, W, 3) array, got shape {image.shape}")
    msg = Image()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.height, msg.width = int(image.shape[0]), int(image.shape[1])
    msg.encoding = "bgr8"
    msg.is_bigendian = 0
    msg.step = int(image.shape[1] * 3)
    data = array.array("B")
    # one copy straight from the numpy buffer; an array.array is stored as is (bytes would be copied again)
    data.frombytes(np.ascontiguousarray(image, dtype=np.uint8).data)
    msg.data = data
    return msg

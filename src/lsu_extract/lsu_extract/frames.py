"""What the extractor does with each serialized camera frame, without ROS: read, check, background, extract.

`FrameExtractor` holds the per-camera state the ``laser_extractor`` node keeps between frames:
the size of each camera's first frame (frames of another size are refused) and, with the
``texture`` background, the newest frames of each camera and the laser-off pair the scan's
TEXTURE event named, which stays the background of the scan's frames up to its last SNAP's stamp even
when the scan's end is in first (events and images come on different topics). The node adds diagnostics
and messages around it; a replay that extracts in
several processes runs one per process over the same frames and events, so that every process
holds the same state and each extracts its share of the frames exactly as the node would.

A pure module: numpy, no ROS.
"""

from __future__ import annotations

import collections

import numpy as np

from lsu_common import stamps
from lsu_common.arrays import AnyArray

from .extractor import ExtractorParams, LaserLineResult, extract_laser_line
from .image import ImageCdr, ImageFormatError, decode_image, parse_image_cdr

__all__ = ["BACKGROUNDS", "FRAMES_KEPT", "SIDES", "FrameExtractor"]

SIDES = ("left", "right")
BACKGROUNDS = ("none", "texture")
FRAMES_KEPT = 8  # newest frames per camera kept while a TEXTURE event may still name one of them


class FrameExtractor:
    """The line of each serialized sensor_msgs/Image, with the state kept from frame to frame (module doc).

    ``copy_frames``: with the texture background, keep copies of the recent frames (a subscription's
    buffer is reused after its callback); False where the buffers stay as they are (a mapped bag file).
    """

    def __init__(self, params: ExtractorParams, background: str = "texture", copy_frames: bool = True) -> None:
        if background not in BACKGROUNDS:
            raise ValueError(f"background '{background}' is unknown; must be one of: {', '.join(BACKGROUNDS)}")
        self.params = params
        self.background = background
        self.copy_frames = copy_frames  # a replay of a bag turns it off while it runs (the buffers stay as they are)
        self._recent: dict[str, collections.deque[tuple[int, AnyArray]]] = {
            side: collections.deque(maxlen=FRAMES_KEPT) for side in SIDES}
        self._texture_key: int | None = None  # stamp (ns) of the current scan's laser-off pair
        self.textures: dict[str, AnyArray] = {}
        self._last_snap: int | None = None     # stamp (ns) of the current scan's latest SNAP
        self._texture_until: int | None = None  # the scan ended: the pair is the background up to this stamp
        self._sizes: dict[str, tuple[int, int]] = {}

    def extract(self, side: str, raw: object, compute: bool = True) -> tuple[ImageCdr, LaserLineResult | None]:
        """The frame's fields and its laser line (None without ``compute``: the state is kept, nothing extracted).

        Raises:
            ImageFormatError: the buffer is not a readable image, or not of the size of the camera's first frame.
        """
        msg = parse_image_cdr(raw)  # type: ignore[arg-type]
        size = (msg.width, msg.height)
        expected = self._sizes.setdefault(side, size)
        if size != expected:
            raise ImageFormatError(
                f"image size changed from {expected[0]}x{expected[1]} to {size[0]}x{size[1]}; frames of the "
                "new size are dropped (the calibration is for the first size): restart the camera with "
                "the calibrated size or restart the extractor")
        if not compute and self.background != "texture":
            return msg, None  # the sizes are all the state kept without a texture background
        image = decode_image(msg.data, msg.width, msg.height, msg.encoding, msg.step)
        texture = None
        if self.background == "texture":
            key = stamps.to_ns(msg)
            self._recent[side].append((key, np.array(image) if self.copy_frames else image))
            if key == self._texture_key:
                self.textures[side] = self._recent[side][-1][1]
            texture = self.textures.get(side)
            if self._texture_until is not None and key > self._texture_until:
                texture = None  # after the ended scan's last snap: not the scan's frame
            if texture is not None and texture.shape != image.shape:
                texture = None  # a mono laser-off frame for a colour one, or the like: extract alone
        if not compute:
            return msg, None
        return msg, extract_laser_line(image, self.params, texture=texture)

    def forget_texture(self) -> None:
        """A scan started: the previous scan's laser-off pair no longer applies."""
        self._texture_key = None
        self.textures.clear()
        self._last_snap = self._texture_until = None

    def snap_taken(self, key: int) -> None:
        """A SNAP event of the current scan, its pair stamped ``key`` (ns)."""
        self._last_snap = key if self._last_snap is None else max(self._last_snap, key)

    def end_scan(self) -> None:
        """The scan finished or was aborted: its pair stays the background of its snaps still to come (their
        images may come after the event), up to its last SNAP's stamp; none after that."""
        if self._last_snap is None:
            self.forget_texture()
        else:
            self._texture_until = self._last_snap

    def take_texture(self, key: int) -> None:
        """The pair stamped ``key`` (ns) is the scan's laser-off pair: from the recent frames, or when it comes."""
        self._texture_key = key
        self.textures.clear()
        for side in SIDES:  # the pair usually came before its event; otherwise extract takes it
            for stamp, image in self._recent[side]:
                if stamp == key:
                    self.textures[side] = image

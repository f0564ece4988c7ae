"""FrameExtractor: the extractor node's per-frame state, shared alike by processes that each extract a share."""

from dataclasses import replace

import numpy as np
import pytest

from lsu_common.arrays import AnyArray
from lsu_extract.extractor import ExtractorParams
from lsu_extract.frames import FrameExtractor
from lsu_extract.image import ImageFormatError, parse_image_cdr
from lsu_extract.synthetic import LineScene, render_line


def serialized(image: AnyArray, sec: int) -> bytes:
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import Image

    h, w = image.shape[:2]
    msg = Image(height=h, width=w, encoding="bgr8", step=3 * w, data=image.tobytes())
    msg.header.stamp.sec = sec
    return serialize_message(msg)


@pytest.fixture(scope="module")
def stream():
    """(kind, side, payload, truth) in recorded order: a laser-off pair, its TEXTURE event, laser frames of both
    cameras (the line moving), a frame of another size, the scan's end, then frames without the texture."""
    base = LineScene(width=320, height=240, seed=3, texture_seed=5)
    off = render_line(replace(base, amplitude_dn=0.0))[0]
    items = [("image", "left", serialized(off, 1), None), ("image", "right", serialized(off, 1), None),
             ("texture", None, 1_000_000_000, None)]
    for k in range(6):
        for side, shift in (("left", 0.0), ("right", -14.0)):
            image, truth, _ = render_line(replace(base, u0_px=140.3 + 7.1 * k + shift, seed=10 + 2 * k + (side == "right")))
            items.append(("image", side, serialized(image, 2 + k), truth))
        if k == 2:
            items.append(("image", "left", serialized(np.zeros((120, 160, 3), np.uint8), 50), None))
        if k == 3:
            items.append(("forget", None, None, None))
    return items


def replay(stream, extractors, texture_background=True):
    """Every item through every extractor; image i computed by extractor i % len(extractors). Outcome per image."""
    outcomes = []
    images = 0
    for kind, side, payload, _ in stream:
        for k, ex in enumerate(extractors):
            if kind == "texture":
                ex.take_texture(payload)
            elif kind == "forget":
                ex.forget_texture()
            else:
                mine = images % len(extractors) == k
                try:
                    _, result = ex.extract(side, payload, compute=mine)
                except ImageFormatError as exc:
                    if mine:
                        outcomes.append(("bad", str(exc)))
                    continue
                if mine:
                    outcomes.append(("line", result))
        images += kind == "image"
    return outcomes


def same(a, b) -> bool:
    if a[0] != b[0]:
        return False
    if a[0] == "bad":
        return a[1] == b[1]
    return all(np.array_equal(getattr(a[1], f), getattr(b[1], f)) for f in ("u", "v", "peak", "width", "quality"))


def test_extractors_sharing_the_frames_give_the_one_extractors_lines(stream):
    params = ExtractorParams()
    alone = replay(stream, [FrameExtractor(params, "texture")])
    for count in (2, 3):
        shared = replay(stream, [FrameExtractor(params, "texture", copy_frames=False) for _ in range(count)])
        assert len(shared) == len(alone) == 15
        assert all(same(a, b) for a, b in zip(alone, shared))
    # the frame of another size is refused, by whichever extractor had it
    assert [o[0] for o in alone].count("bad") == 1 and "size changed from 320x240 to 160x120" in alone[8][1]
    # the truth: the drawn line centre (RMS within a tenth of a pixel, every row within 0.4 px)
    truths = [t for kind, _, _, t in stream if kind == "image" and t is not None]
    lines = [o[1] for o in alone if o[0] == "line"][2:]  # after the laser-off pair (no line)
    for line, truth in zip(lines, truths):
        assert len(line) > 200
        error = line.u - truth[line.v.astype(int)]
        assert np.sqrt(np.mean(error ** 2)) < 0.1 and np.max(np.abs(error)) < 0.4
    # the laser-off pair is used until the scan's end: the lines before differ from a frame-alone extraction
    plain = replay(stream, [FrameExtractor(params, "none")])
    differs = [not same(a, b) for a, b in zip(alone, plain)]
    assert any(differs[2:8]) and not any(differs[11:])


def test_a_scans_end_ahead_of_its_last_snaps_images_leaves_them_their_laser_off_pair(stream):
    """FINISHED can reach the extractor before the last snap's images (another topic): those frames, stamped up to
    the last SNAP's stamp, are still extracted minus the scan's laser-off pair; a frame after it is not."""
    params = ExtractorParams()
    frames = {(side, parse_image_cdr(payload).sec): payload for kind, side, payload, _ in stream if kind == "image"}
    in_order = FrameExtractor(params, "texture")             # every frame before the scan's end
    ended_early = FrameExtractor(params, "texture")
    plain = FrameExtractor(params, "none")
    for ex in (in_order, ended_early):
        ex.extract("left", frames[("left", 1)])
        ex.take_texture(1_000_000_000)
        for sec in (2, 3):
            ex.snap_taken(sec * 1_000_000_000)
    ended_early.end_scan()
    for sec in (2, 3):                                       # the scan's snaps, after its end came in
        _, want = in_order.extract("left", frames[("left", sec)])
        _, got = ended_early.extract("left", frames[("left", sec)])
        _, alone = plain.extract("left", frames[("left", sec)])
        assert same(("line", got), ("line", want)) and not same(("line", got), ("line", alone))
    _, late = ended_early.extract("left", frames[("left", 4)])  # stamped after the last snap: alone
    _, alone = plain.extract("left", frames[("left", 4)])
    assert same(("line", late), ("line", alone))

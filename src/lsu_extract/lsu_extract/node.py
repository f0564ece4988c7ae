"""``laser_extractor``: camera images in, sub-pixel laser lines out (a thin adapter over extractor.py).

Subscribes ``stereo/{left,right}/image_raw`` (sensor_msgs/Image), publishes
``stereo/{left,right}/laser_line`` (lsu_interfaces/LaserLine) with the image's header, so
the matcher pairs left and right by stamp. A frame it cannot read (unsupported encoding, a
size different from the first frame of that camera, a short buffer) is dropped with one
error line per distinct problem and an ERROR status on ``/diagnostics``; the node keeps running.

With ``background: texture`` (the default) it also follows ``scan/events``: the laser-off pair that a scan's
TEXTURE event names (by stamp, among the last `lsu_extract.frames.FRAMES_KEPT` frames of each camera, or the next
ones) becomes the background of that scan's frames: the extractor's signal is then the
difference from it (ambient light and red objects cancel). A new scan starts without one: a stop-snap
scan takes its pair before the first snap, so every snap has it; a sweep takes it after the sweep, so its
frames are extracted alone. Events and images travel on different topics, which DDS does not order
between them (a reliable event lost once comes with the next heartbeat, after images sent later): from a
scan's STARTED until its next event (TEXTURE, or SNAP / SWEEP_START of a scan without a pair) frames are
held, then extracted in the order they came, so a snap that overtook its scan's TEXTURE event still has
the pair; and a scan's end (FINISHED, ABORTED) that overtakes its last snap's images leaves the pair the
background of the frames up to the last SNAP's stamp. Frames are held at most `TEXTURE_WAIT_S` (then
extracted without the pair, with a warning), and no more than `lsu_extract.frames.FRAMES_KEPT` of a
camera: more before any event is a stream (a sweep's frames come before its SWEEP_START), not a
stop-snap's one texture and one snap pair.
"""

from __future__ import annotations

import array
import sys
from dataclasses import fields
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.parameter import Parameter
from sensor_msgs.msg import Image
from std_msgs.msg import Header

from lsu_common import diagnostics, qos, stamps
from lsu_common.arrays import AnyArray, Float32Array
from lsu_common.node import LsuNode, main_of
from lsu_common.params import Param, descriptor
from lsu_interfaces.msg import LaserLine, ScanEvent

from .detectors import METHODS
from .extractor import ExtractorParams, LaserLineResult, one_opencv_thread, param_problems
from .frames import BACKGROUNDS, FRAMES_KEPT, SIDES, FrameExtractor
from .image import ImageFormatError

# scan data: sensor-data depth, but reliable (a lost snap is a hole in the face)
SCAN_DATA_QOS = qos.SCAN_DATA
EVENTS_QOS = qos.EVENTS
# longest a started scan's frames wait for its next event (module doc): far beyond a texture capture and a
# retransmission, short enough that a scan whose events stopped still gets its lines
TEXTURE_WAIT_S = 5.0

_DESCRIPTIONS: dict[str, tuple[str, tuple[float, float] | None]] = {
    "method": (f"peak detector: one of {', '.join(METHODS)} ('thesis' = the pixel-level baseline of ch. 6)", None),
    "min_contrast": ("laser signal above the local background needed to accept a row [DN]", (1.0, 255.0)),
    "contrast_sigmas": ("on a frame quieter than that, accept this many of its noise sigmas instead (measured in "
                        "every frame, never below 12 DN); 0 = min_contrast always", (0.0, 100.0)),
    "ambiguity_ratio": ("a second peak at least this fraction of the first competes with it (reflection)",
                        (0.05, 1.0)),
    "min_width_px": ("smallest accepted laser FWHM [px]", (0.0, 64.0)),
    "max_width_px": ("largest accepted laser FWHM [px]; wider peaks are texture, not laser", (2.0, 64.0)),
    "window_px": ("tracking window half-width around the line of the neighbouring rows [px]; 0 = full rows",
                  (0, 128)),
    "coarse_step_rows": ("rows between the full-row searches that seed the tracking [rows]", (1, 64)),
    "saturation_level": ("red value from which the sensor clips [DN] (JPEG-softened cameras top out at 250-254)",
                         (1, 255)),
    "clipped_centre": ("where red clips: centre midway between the half-maximum crossings of the signal's flanks "
                       "('signal') or of red's ('red')", None),
    "adaptive_width_px": ("blais_rioux / adaptive methods: rows whose line is wider than this (FWHM) [px] take "
                          "the 8th-order filter / the centre of mass, narrower ones Blais-Rioux 4", (1.0, 64.0)),
    "grow_wide": ("follow the line row by row from its detections, accepting it up to 48 px wide there (a "
                  "full-row search keeps max_width_px)", None),
    "red_rise_ratio": ("colour frame without a laser-off frame: accept a row only where red itself rises over the "
                       "background by this fraction of the signal's contrast (red print does not); 0 = off", (0.0, 2.0)),
    "red_threshold": ("thesis method: a laser pixel has red above this [DN]", (0, 254)),
    "blue_threshold": ("thesis method: a laser pixel has blue below this [DN]", (1, 255)),
}


LINE_FIELDS = ("u", "v", "peak", "width", "quality")


def line_fields(result: LaserLineResult) -> dict[str, Float32Array]:
    """The per-row arrays a LaserLine carries (`LINE_FIELDS`), float32: rows with any non-finite value left
    out, quality clipped to 0..1. What a subscriber of the line gets, for callers that hand the arrays on."""
    values = [result.u, result.v, result.peak, result.width, result.quality]
    finite = np.isfinite(values[0])
    for column in values[1:]:
        finite &= np.isfinite(column)
    if not finite.all():
        values = [column[finite] for column in values]
    values[4] = np.clip(values[4], 0.0, 1.0)
    return {name: np.ascontiguousarray(column, dtype=np.float32) for name, column in zip(LINE_FIELDS, values)}


def result_to_msg(result: LaserLineResult, header: Any) -> LaserLine:
    """A `LaserLineResult` as a LaserLine message; rows with any non-finite value are left out."""
    fields = {name: array.array("f", column.tobytes()) for name, column in line_fields(result).items()}
    return LaserLine(header=header, image_width=result.image_width, image_height=result.image_height,
                     method=result.method, rows_searched=result.rows_searched, rows_ambiguous=result.rows_ambiguous,
                     rows_saturated=result.rows_saturated, **fields)


def follow_scan_event(core: FrameExtractor, msg: ScanEvent) -> None:
    """What a scan event means to the frame state (the node, and each extraction process of a replay): STARTED
    forgets the laser-off pair, TEXTURE takes the pair it names, SNAP notes its stamp, FINISHED and ABORTED
    keep the pair for the frames up to the last SNAP's stamp only."""
    if msg.type == ScanEvent.STARTED:
        core.forget_texture()
    elif msg.type == ScanEvent.TEXTURE:
        core.take_texture(stamps.to_ns(msg.image_stamp))
    elif msg.type == ScanEvent.SNAP:
        core.snap_taken(stamps.to_ns(msg.image_stamp))
    elif msg.type in (ScanEvent.FINISHED, ScanEvent.ABORTED):
        core.end_scan()


class LaserExtractorNode(LsuNode):
    """Extracts the laser line from both cameras' images."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("laser_extractor", **{"namespace": "/lsu", **kwargs})
        defaults = ExtractorParams()
        for spec in fields(ExtractorParams):
            value = getattr(defaults, spec.name)
            self.declare_parameter(spec.name, value, descriptor(Param(value, *_DESCRIPTIONS[spec.name])))
        self.declare_parameter("background", "texture", ParameterDescriptor(
            description="texture: minus the laser-off frame of the scan's TEXTURE event once it is in (ambient light "
                        "and red objects cancel; frames before it, and a sweep's, alone); none: each frame alone"))
        background = str(self.get_parameter("background").value)
        if background not in BACKGROUNDS:
            raise ValueError(f"background '{background}' is unknown; must be one of: {', '.join(BACKGROUNDS)}")
        self.core = FrameExtractor(self._read_params({}), background)
        # set while the parameters are in use elsewhere (a replay's extraction processes): changes are refused
        self.frozen_reason: str | None = None
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._after_set_parameters)
        self._reported: dict[str, str] = {}  # side -> last problem reported (one log line per problem)
        self.frames = {side: 0 for side in SIDES}
        self.dropped = {side: 0 for side in SIDES}
        # frames of a started scan that came before its next event (module doc); None while none are held
        self._held: list[tuple[str, Any]] | None = None
        self._hold_timer: Any = None
        self._hold_scan = ""
        self.diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.publishers_ = {side: self.create_publisher(LaserLine, f"stereo/{side}/laser_line", SCAN_DATA_QOS)
                            for side in SIDES}
        # raw: the pixels are read in place from the serialized message (rclpy's deserializer copies
        # them into an array.array first: ~0.4 ms per frame, a tenth of the extraction)
        # the events' subscription first: an executor serves the subscriptions ready in one wait in the order they
        # were made, so a TEXTURE event that came in with snap frames is taken before them (no hold needed)
        self.subscriptions_ = [self.create_subscription(ScanEvent, "scan/events", self.on_event, EVENTS_QOS)]
        self.subscriptions_ += [
            self.create_subscription(Image, f"stereo/{side}/image_raw",
                                     lambda raw, side=side: self.on_image(side, raw), qos.FRAME_QUEUE, raw=True)
            for side in SIDES]

    def _read_params(self, overrides: dict[str, Any]) -> ExtractorParams:
        values = {spec.name: overrides.get(spec.name, self.get_parameter(spec.name).value)
                  for spec in fields(ExtractorParams)}
        return ExtractorParams(**values)

    @property
    def params(self) -> ExtractorParams:
        return self.core.params

    @property
    def background(self) -> str:
        return self.core.background

    @property
    def frames_held(self) -> int:
        """Frames held for the started scan's next event (module doc)."""
        return len(self._held or ())

    @property
    def textures(self) -> dict[str, AnyArray]:
        """The laser-off frame of the current scan, per camera (the texture background)."""
        return self.core.textures

    def _on_set_parameters(self, changed: list[Parameter]) -> SetParametersResult:
        names = {spec.name for spec in fields(ExtractorParams)}
        if self.frozen_reason is not None and any(p.name in names or p.name == "background" for p in changed):
            return SetParametersResult(successful=False, reason=self.frozen_reason)
        current = {name: self.get_parameter(name).value for name in names}
        current.update({p.name: p.value for p in changed if p.name in names})
        problems = param_problems(current)
        for p in changed:
            if p.name == "background" and p.value not in BACKGROUNDS:
                problems.append(f"background '{p.value}' is unknown; must be one of: {', '.join(BACKGROUNDS)}")
        if problems:
            return SetParametersResult(successful=False, reason="; ".join(problems))
        return SetParametersResult(successful=True)

    def _after_set_parameters(self, changed: list[Parameter]) -> None:
        self.core.params = self._read_params({})
        self.core.background = str(self.get_parameter("background").value)
        self.get_logger().info(f"parameters now: method={self.params.method}, "
                               f"min_contrast={self.params.min_contrast}, window_px={self.params.window_px}")

    def on_image(self, side: str, raw: bytes) -> None:
        """Extract the line of one serialized sensor_msgs/Image and publish it; a bad image is reported, never raised.

        Held instead while a started scan's next event is awaited (module doc).
        """
        if self._held is not None:
            self._held.append((side, raw))  # bytes: the subscription hands each callback its own
            if sum(1 for s, _ in self._held if s == side) > FRAMES_KEPT:
                self._release_held()  # a stream, not a texture pair and a snap (module doc)
            return
        line = self.line_of(side, raw)
        if line is not None:
            self.publishers_[side].publish(line)

    def line_of(self, side: str, raw: Any) -> LaserLine | None:
        """The laser line of one serialized sensor_msgs/Image (any buffer: bytes, memoryview), not published.

        None for a frame that cannot be read (reported on /diagnostics, counted as dropped).
        """
        extracted = self.extract_of(side, raw)
        return None if extracted is None else result_to_msg(extracted[1], extracted[0])

    def extract_of(self, side: str, raw: Any) -> tuple[Header, LaserLineResult] | None:
        """`line_of` before the message is built: the image's header and the extraction's result.

        A direct replay calls this with the bag's buffers and hands the arrays on itself (`line_fields`).
        """
        try:
            msg, result = self.core.extract(side, raw)
        except ImageFormatError as exc:
            self.frame_dropped(side, str(exc))
            return None
        assert result is not None  # extracted (compute=True)
        return self.frame_extracted(side, msg.sec, msg.nanosec, msg.frame_id), result

    def frame_extracted(self, side: str, sec: int, nanosec: int, frame_id: str) -> Header:
        """Count a frame extracted (here or by a replay's extraction process); its header."""
        self.frames[side] += 1
        if side in self._reported:
            self._report(side, DiagnosticStatus.OK, f"{side} camera: extracting again")
        return Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame_id)

    def frame_dropped(self, side: str, problem: str) -> None:
        """Count and report a frame that could not be read (``problem``: what is wrong with it)."""
        self.dropped[side] += 1
        self._report(side, DiagnosticStatus.ERROR, f"{side} camera: {problem}")

    def on_event(self, msg: ScanEvent) -> None:
        """The event's meaning to the frame state; STARTED holds the frames until the scan's next event."""
        if self._held is not None and msg.type != ScanEvent.STARTED:
            follow_scan_event(self.core, msg)  # first: a TEXTURE event's pair is the background of the held frames
            self._release_held()
            return
        self._release_held(f"scan {msg.scan_id} started")  # a previous scan's frames, with its own background
        follow_scan_event(self.core, msg)
        if msg.type == ScanEvent.STARTED and self.background == "texture":
            self._held, self._hold_scan = [], msg.scan_id
            self._hold_timer = self.create_timer(
                TEXTURE_WAIT_S, lambda: self._release_held(f"no event in {TEXTURE_WAIT_S:g} s"))

    def _release_held(self, late: str = "") -> None:
        """Extract and publish the held frames in the order they came; ``late``: why without the scan's next event."""
        if self._hold_timer is not None:
            self.destroy_timer(self._hold_timer)
            self._hold_timer = None
        held, self._held = self._held, None
        if held and late:
            self.get_logger().warning(
                f"scan {self._hold_scan}: {late} after its start: {len(held)} frame(s) held for its laser-off "
                "pair extracted without it (ambient light and red objects may show as laser)")
        for side, raw in held or ():
            self.on_image(side, raw)

    def _report(self, side: str, level: bytes, message: str) -> None:
        if self._reported.get(side) == message:
            return  # one log line and one status per distinct problem, not one per frame
        if level == DiagnosticStatus.OK:
            self._reported.pop(side, None)
            self.get_logger().info(message)
        else:
            self._reported[side] = message
            self.get_logger().error(message)
        self.diagnostics.publish(diagnostics.status_array(
            self, level, f"{self.get_fully_qualified_name()}: {side}", message,
            {"frames": self.frames[side], "dropped": self.dropped[side]}, hardware_id=f"{side} camera"))


_run = main_of(LaserExtractorNode)


def main(args: list[str] | None = None) -> int:
    """Console script running LaserExtractorNode in a process of its own (`one_opencv_thread`)."""
    one_opencv_thread()
    return _run(args)


if __name__ == "__main__":
    sys.exit(main())

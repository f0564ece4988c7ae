"""The ``stereo_camera`` node: a camera source on the ROS graph.

Publishes ``stereo/{left,right}/image_raw`` (bgr8, one stamp per pair) and with every image its
``stereo/{left,right}/camera_info`` (same header, same QoS, as ROS camera drivers do),
``stereo/extrinsics`` and ``/tf_static`` (the rig frames of the calibration, see `lsu_cameras.frames`;
both transient-local), serves ``stereo/capture`` (a fresh pair, published and/or returned) and
optionally previews at ``preview_rate_hz``. Sources other than ``v4l2`` and ``folder`` are plug-ins
(`lsu_cameras.sources.open_plugin_source`): the simulated rig's ``sim`` (package lsu_sim) follows
``sim/truth`` (the GP32 emulator), which this node reads for it, and falls back to the
``carriage_position_steps`` parameter without it.

``stereo/stream`` (StreamStereo) runs the cameras free: a streaming thread publishes a pair per frame
slot (clocked sources: stamp ``t_k = t0 + k * period`` exactly; v4l2: the buffer stamps) and, with
every published pair (captures too), its ``stereo/exposure`` (StereoExposure: each camera's exposure
start relative to the stamp). A clocked source slower than the frame rate publishes late but never
skips a slot; the lag is on ``/diagnostics`` and in the stop reply, and a lag beyond
``stream_max_lag_s`` ends the stream with an error. Each pair waits (up to ``stream_ack_timeout_s``) until
every image reader acknowledged it, so the stream goes at its slowest reader's pace instead of
pushing unread images out of the publishers' short queues; a pair not acknowledged in time is counted
as dropped (stop reply, ``/diagnostics``). A stop request ends the stream at the request's
time: the reply comes once every slot before it is published, with the stream's totals. Captures are
refused while a stream runs (the stream's own frames are the pairs to use).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.duration import Duration
from sensor_msgs.msg import CameraInfo, Image

from lsu_common import diagnostics, qos, stamps
from lsu_common.images import bgr_to_msg
from lsu_common.node import LsuNode, main_of
from lsu_common.params import Param, declare_parameters
from lsu_common.read_ahead import read_ahead
from lsu_interfaces.msg import SimTruth, StereoExposure, StereoExtrinsics
from lsu_interfaces.srv import CaptureStereo, StreamStereo
from tf2_msgs.msg import TFMessage

from .calib_io import (
    CalibrationError,
    CalibrationSet,
    CalibrationSizeError,
    CameraCalibration,
    read_calibration_dir,
    read_camera_yaml,
)
from .frames import TrackGeometry, rig_transforms, transform_msg
from .paths import config_dir
from .polled import PolledGroup, take_all
from .profiles import ProfileError, load_profile
from .sources import CameraError, FolderSource, SourceContext, StereoPair, StereoSource, V4l2Source, open_plugin_source
from .stream import DropCounter, LagStats, TruthHistory, frame_period_ns, slot_stamp_ns

SOURCES = ("sim", "v4l2", "folder")  # sim: the lsu.camera_sources plug-in of lsu_sim


image_msg = bgr_to_msg  # a bgr8 sensor_msgs/Image of an HxWx3 uint8 array


R = True  # read_only: the source, calibration and frames are opened and published once, at start-up
PARAMETERS: dict[str, Param] = {
    "source": Param("sim", "camera source: sim | v4l2 | folder", read_only=R),
    "devices": Param(["/dev/video0", "/dev/video1"], "v4l2: left and right devices", read_only=R),
    "folder": Param("", "folder: directory of left_*.png/right_*.png pairs", read_only=R),
    "image_width": Param(640, "v4l2: requested width [px]", (1, 16384), read_only=R),
    "image_height": Param(480, "v4l2: requested height [px]", (1, 16384), read_only=R),
    "profile": Param("dark", "v4l2: camera property profile (config/profiles)", read_only=R),
    "calibration_dir": Param("", "left.yaml/right.yaml/stereo.yaml; empty: config/calibration/sim for sim, none "
                             "otherwise", read_only=R),
    "left_camera_info_url": Param("", "overrides left.yaml (file:// URL or path)", read_only=R),
    "right_camera_info_url": Param("", "overrides right.yaml (file:// URL or path)", read_only=R),
    "left_frame_id": Param("lsu_left_optical", "frame of the left images", read_only=R),
    "right_frame_id": Param("lsu_right_optical", "frame of the right images", read_only=R),
    "base_frame_id": Param("lsu_base", "rig frame of /tf_static (x forward, y left, z up; origin between the optical "
                           "centres)", read_only=R),
    "track_step_m": Param(TrackGeometry.step_m, "laser track: metres per carriage step (for the laser origin on "
                          "/tf_static)", read_only=R),
    "track_center_step": Param(TrackGeometry.center_step, "laser track: the carriage step in line with the rig centre",
                               read_only=R),
    "laser_forward_m": Param(TrackGeometry.laser_forward_m, "laser track: laser exit ahead (+) of the camera "
                             "baseline [m]", read_only=R),
    "preview_rate_hz": Param(0.0, "free-running publish rate [Hz]; 0 = capture only", (0.0, 100.0)),
    "capture_timeout_s": Param(2.0, "default capture timeout [s]", (0.01, 600.0)),
    "sim_scene": Param("head", "sim: plane | sphere | board | head | head:SEED | person | person:SEED | mesh file", read_only=R),
    "sim_rig": Param("", "sim: rig geometry YAML (default config/sim_rig.yaml)", read_only=R),
    "sim_seed": Param(0, "sim: sensor noise seed", read_only=R),
    "sim_motion": Param("still", "sim: the subject's motion (lsu_sim.motion, docs/MOTION.md): still | seated | standing "
                        "| turn (standing, then a sudden turn of the head); its clock starts at the first frame",
                        read_only=R),
    "sim_motion_seed": Param(0, "sim: the subject motion's seed", read_only=R),
    "sim_motion_turn_at_s": Param(1.0, "sim: sim_motion turn: when the head turns, after the first frame [s]",
                                  (0.0, 1e6), read_only=R),
    "sim_motion_hz": Param(5.0, "sim: how often the moving subject's pose is updated (each update re-casts both "
                           "views: the simulated camera falls behind real time) [Hz]", (0.1, 1000.0), read_only=R),
    "carriage_position_steps": Param(235.0, "sim: carriage position used until /lsu/sim/truth arrives [steps]"),
    "laser_on": Param(True, "sim: laser state used until /lsu/sim/truth arrives"),
    "stream_max_lag_s": Param(120.0, "stream: a pair published later than this after its stamp ends the stream with "
                              "an error (a source that cannot keep up must not pile up frames) [s]", (0.1, 600.0)),
    "stream_ack_timeout_s": Param(1.0, "stream: how long a pair may wait for every image reader (extractor, "
                                  "recorder) to acknowledge it; one not acknowledged by then is counted as "
                                  "dropped [s]", (0.01, 60.0)),
    "v4l2_latency_s": Param(0.0, "v4l2: exposure start to arrival of a frame, for drivers without buffer timestamps "
                            "[s]", (0.0, 10.0), read_only=R),
}

MAX_FRAME_RATE_HZ = 1000.0
START_PAST_LIMIT_S = 1.0  # a stream start further in the past is refused (clock mix-up)
# rendered pairs waiting for the publishing thread (a clocked stream): the render of the next pair overlaps
# the wait for the readers of this one
RENDER_AHEAD = 2
NO_WAIT = Duration(nanoseconds=0)
ACK_POLL_S = 0.0005  # between asking whether every image reader acknowledged a pair (see `_wait_for_readers`)
TRUTH_DEPTH = 64          # sim/truth samples held by DDS between two reads (50 Hz x > 1 s of rendering)


@dataclass
class _Stream:
    """One stream's clock, progress and totals; written by its thread, read under the node's stream lock."""

    rate_hz: float
    period_ns: int
    frames: int                      # 0: until stopped
    t0_ns: int                       # first slot (clocked) / first pair (free-running, once known)
    exposure_s: float
    drops: DropCounter
    lags: LagStats = field(default_factory=LagStats)
    stop_at_ns: int | None = None    # slots stamped at or after it are not taken
    last_stamp_ns: int = 0
    error: str = ""
    wake: threading.Event = field(default_factory=threading.Event)
    started: threading.Event = field(default_factory=threading.Event)   # first pair published (or the end)
    done: threading.Event = field(default_factory=threading.Event)
    thread: threading.Thread | None = None

    @property
    def running(self) -> bool:
        return not self.done.is_set()


def camera_info_msg(cal: CameraCalibration, frame_id: str) -> CameraInfo:
    """sensor_msgs/CameraInfo of a calibration."""
    msg = CameraInfo()
    msg.header.frame_id = frame_id
    msg.width, msg.height = cal.image_size
    msg.distortion_model = cal.distortion_model
    msg.d = [float(x) for x in cal.distortion_coefficients]
    msg.k = [float(x) for x in cal.camera_matrix.reshape(-1)]
    assert cal.rectification_matrix is not None and cal.projection_matrix is not None  # __post_init__ sets both
    msg.r = [float(x) for x in cal.rectification_matrix.reshape(-1)]
    msg.p = [float(x) for x in cal.projection_matrix.reshape(-1)]
    return msg


def _url_to_path(url: str) -> Path:
    return Path(url[len("file://"):]) if url.startswith("file://") else Path(url)


class StereoCameraNode(LsuNode):
    """Stereo camera pair (v4l2 | folder | sim) with synchronized capture."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("stereo_camera", **{"namespace": "/lsu", **kwargs})
        declare_parameters(self, PARAMETERS)

        self._lock = threading.Lock()
        self._publish_lock = threading.Lock()
        self._truth_lock = threading.Lock()
        self._truth_msg: SimTruth | None = None
        self._truth_history: TruthHistory[SimTruth] = TruthHistory()
        self._stream_lock = threading.Lock()
        self._stream: _Stream | None = None
        self.source: StereoSource | None = None
        self.calibration: CalibrationSet | None = None
        self.status_level = diagnostics.OK
        self.status_message = "ok"

        sensor_qos = qos.SCAN_DATA
        latched = qos.LATCHED
        self.pub_left = self.create_publisher(Image, "stereo/left/image_raw", sensor_qos)
        self.pub_right = self.create_publisher(Image, "stereo/right/image_raw", sensor_qos)
        # camera_info goes out with every image (same header and QoS), never latched alone: its stamp
        # then always names an image, as image pipelines expect
        self.pub_info_left = self.create_publisher(CameraInfo, "stereo/left/camera_info", sensor_qos)
        self.pub_info_right = self.create_publisher(CameraInfo, "stereo/right/camera_info", sensor_qos)
        self._info: tuple[CameraInfo, CameraInfo] | None = None
        self.pub_extrinsics = self.create_publisher(StereoExtrinsics, "stereo/extrinsics", latched)
        self.pub_exposure = self.create_publisher(StereoExposure, "stereo/exposure", qos.reliable(64))
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.pub_tf_static = self.create_publisher(TFMessage, "/tf_static", latched)  # tf2's static QoS

        self._open_source()
        self._load_calibration()
        self._publish_calibration()

        # read at capture time, never by the executor (see PolledGroup); deep enough that a stream rendering
        # behind the truth still finds the sample that held at each frame's stamp
        self._truth_sub = self.create_subscription(SimTruth, "sim/truth", lambda _msg: None, qos.reliable(TRUTH_DEPTH),
                                                   callback_group=PolledGroup())
        self.srv = self.create_service(CaptureStereo, "stereo/capture", self._on_capture)
        # its own group: a stop request waits for the stream's last frames while captures are still refused
        self.stream_srv = self.create_service(StreamStereo, "stereo/stream", self._on_stream,
                                              callback_group=MutuallyExclusiveCallbackGroup())
        self.preview: Any = None
        self._set_preview_rate(float(self.get_parameter("preview_rate_hz").value))
        self.add_post_set_parameters_callback(self._apply_parameters)
        self.create_timer(1.0, self._publish_diagnostics, callback_group=MutuallyExclusiveCallbackGroup())

    # ------------------------------------------------------------------ set-up
    def _fail(self, message: str) -> None:
        self.status_level, self.status_message = diagnostics.ERROR, message
        self.get_logger().error(message)

    def _set_preview_rate(self, rate_hz: float) -> None:
        if self.preview is not None:
            self.destroy_timer(self.preview)
        self.preview = self.create_timer(1.0 / rate_hz, self._on_preview) if rate_hz > 0 else None

    def _apply_parameters(self, params: list[Any]) -> None:
        """preview_rate_hz restarts the preview timer; the other settable ones are read where they are used."""
        for p in params:
            if p.name == "preview_rate_hz":
                self._set_preview_rate(float(p.value))

    @property
    def _truth(self) -> SimTruth | None:
        """The newest ``sim/truth`` received (None before the first), taken from the reader on demand."""
        with self._truth_lock:  # one reader, and `lsu run` may call this from several executor threads
            for msg in take_all(self._truth_sub):
                self._truth_history.add(stamps.to_ns(msg.header.stamp), msg)
            self._truth_msg = self._truth_history.newest
            return self._truth_msg

    def _truth_at(self, t_ns: int) -> tuple[SimTruth | None, list[SimTruth]]:
        """The ``sim/truth`` sample that held at ``t_ns`` (the newest stamped at or before it), and the samples
        after it up to the end of the pair's exposures (a motion starting or stopping while they last)."""
        if self._truth is None:
            return None, []
        window_ns = stamps.seconds_to_ns(self.source.ready_after_s if self.source is not None else 0.0)
        with self._truth_lock:
            truth = self._truth_history.at(t_ns)
            later = self._truth_history.between(t_ns, t_ns + window_ns)
            # later frames and captures look up later times only: older samples can go (bounded memory)
            self._truth_history.prune(min(t_ns, self._now_ns()) - stamps.seconds_to_ns(
                float(self.get_parameter("stream_max_lag_s").value) + 1.0))
        return truth, later

    def _now_ns(self) -> int:
        return int(self.get_clock().now().nanoseconds)

    def _open_source(self) -> None:
        kind = str(self.get_parameter("source").value)
        try:
            if kind == "v4l2":
                profile_name = str(self.get_parameter("profile").value)
                profile = load_profile(profile_name) if profile_name else None
                size = (int(self.get_parameter("image_width").value), int(self.get_parameter("image_height").value))
                self.source = V4l2Source(list(self.get_parameter("devices").value), size, profile,
                                         latency_s=float(self.get_parameter("v4l2_latency_s").value))
            elif kind == "folder":
                self.source = FolderSource(str(self.get_parameter("folder").value))
            else:
                context = SourceContext(parameter=lambda name: self.get_parameter(name).value,
                                        clock=lambda: stamps.ns_to_seconds(self._now_ns()), truth_at=self._truth_at)
                self.source = open_plugin_source(kind, context)
        except (CameraError, ProfileError, ValueError, OSError) as exc:
            self.source = None
            self._fail(f"camera source '{kind}' not available: {exc}")
            return
        for problem in self.source.report():
            self.get_logger().warning(f"camera setting: {problem}")
        self.get_logger().info(f"source '{kind}' open, images {self.source.image_size[0]}x{self.source.image_size[1]}")

    def _load_calibration(self) -> None:
        kind = str(self.get_parameter("source").value)
        directory = str(self.get_parameter("calibration_dir").value)
        if not directory and kind == "sim":
            directory = str(config_dir() / "calibration" / "sim")
        if not directory:
            self.get_logger().warning("no calibration_dir: camera_info and extrinsics are not published; "
                                      "run `lsu calibrate` and set calibration_dir")
            return
        try:
            cal = read_calibration_dir(directory)
            for side in ("left", "right"):
                url = str(self.get_parameter(f"{side}_camera_info_url").value)
                if url:
                    setattr(cal, side, read_camera_yaml(_url_to_path(url)))
            if cal.left.image_size != cal.right.image_size:
                raise CalibrationSizeError(f"left camera_info is {cal.left.image_size} but right is {cal.right.image_size}")
            if self.source is not None and cal.left.image_size != tuple(self.source.image_size):
                w, h = cal.left.image_size
                sw, sh = self.source.image_size
                raise CalibrationSizeError(f"calibration '{directory}' is for {w}x{h} images but the cameras give "
                                           f"{sw}x{sh}: recalibrate at this size or change the image size")
        except CalibrationError as exc:
            self._fail(f"calibration not published: {exc}")
            return
        self.calibration = cal

    def _publish_calibration(self) -> None:
        cal = self.calibration
        if cal is None:
            return
        stamp = self.get_clock().now().to_msg()
        left_id, right_id = str(self.get_parameter("left_frame_id").value), str(self.get_parameter("right_frame_id").value)
        self._info = (camera_info_msg(cal.left, left_id), camera_info_msg(cal.right, right_id))
        ext = StereoExtrinsics()
        ext.header.stamp = stamp
        ext.header.frame_id = left_id
        ext.right_frame_id = right_id
        s = cal.stereo
        ext.rotation = [float(x) for x in s.rotation.reshape(-1)]
        ext.translation = [float(x) for x in s.translation]
        assert s.essential is not None and s.fundamental is not None  # reading a calibration fills both
        ext.essential = [float(x) for x in s.essential.reshape(-1)]
        ext.fundamental = [float(x) for x in s.fundamental.reshape(-1)]
        ext.rms_px = float(s.rms_px)
        ext.image_width, ext.image_height = cal.image_size
        ext.calibration_id = cal.calibration_id
        self.pub_extrinsics.publish(ext)
        g = lambda name: float(self.get_parameter(name).value)  # noqa: E731
        track = TrackGeometry(g("track_step_m"), g("track_center_step"), g("laser_forward_m"))
        s.left_frame_id, s.right_frame_id = left_id, right_id
        transforms = rig_transforms(s, track, str(self.get_parameter("base_frame_id").value))
        self.pub_tf_static.publish(TFMessage(transforms=[transform_msg(t, stamp) for t in transforms]))

    # ------------------------------------------------------------------ runtime
    def grab(self, timeout_s: float) -> StereoPair:
        """A fresh pair from the source (raises CameraError)."""
        if self.source is None:
            raise CameraError(self.status_message)
        with self._lock:
            return self.source.grab_pair(timeout_s)

    def _stamp(self, pair: StereoPair) -> Time:
        if self.source is not None and self.source.stamps_on_node_clock:  # e.g. sim time: already the node's clock
            sec = pair.time_s
        else:  # device sources report wall time; stamp with the node clock at the same instant
            sec = stamps.ns_to_seconds(self.get_clock().now().nanoseconds)
        return stamps.from_seconds(sec)

    def _exposure_msg(self, pair: StereoPair, stamp: Time, frame_index: int = 0, streaming: bool = False
                      ) -> StereoExposure:
        msg = StereoExposure(left_start_offset_s=float(pair.left_offset_s), right_start_offset_s=float(pair.right_offset_s),
                             exposure_s=float(self.source.exposure_s if self.source is not None else 0.0),
                             frame_index=int(frame_index), streaming=bool(streaming))
        msg.header.stamp = stamp
        msg.header.frame_id = str(self.get_parameter("left_frame_id").value)
        return msg

    def _publish_pair(self, left: Image, right: Image, exposure: StereoExposure) -> None:
        # one pair at a time: the capture service, the preview timer and a stream may run in parallel
        # (`lsu run`), and the camera_info messages are reused with each pair's header
        with self._publish_lock:
            # the exposure first: a reader of the images or of their laser lines can already place them in time
            self.pub_exposure.publish(exposure)
            if self._info is not None:  # info first: whoever holds an image can already know its camera
                for pub, info, image in ((self.pub_info_left, self._info[0], left),
                                         (self.pub_info_right, self._info[1], right)):
                    info.header = image.header
                    pub.publish(info)
            self.pub_left.publish(left)
            self.pub_right.publish(right)

    def _wait_for_readers(self, timeout_s: float) -> bool:
        """Wait until every reliable reader of the images (extractor, matcher, bag recorder) acknowledged the
        pair just published, at most ``timeout_s`` in all; False if one did not. The publishers keep only the
        last few images: one more published before a slow reader took the older ones would push them out."""
        deadline_ns = self._now_ns() + stamps.seconds_to_ns(timeout_s)
        for pub in (self.pub_left, self.pub_right):
            # rclpy's wait_for_all_acked keeps the GIL while it blocks, which froze the render thread for
            # every acknowledgement's round trip: it is asked without waiting, and the wait is a sleep
            while not pub.wait_for_all_acked(NO_WAIT):
                if self._now_ns() >= deadline_ns:
                    return False
                time.sleep(ACK_POLL_S)
        return True

    def _streaming(self) -> _Stream | None:
        with self._stream_lock:
            return self._stream if self._stream is not None and self._stream.running else None

    def _on_capture(self, request: CaptureStereo.Request, response: CaptureStereo.Response) -> CaptureStereo.Response:
        timeout = float(request.timeout_s) if request.timeout_s > 0 else float(self.get_parameter("capture_timeout_s").value)
        stream = self._streaming()
        if stream is not None:
            response.success = False
            response.message = (f"capture refused: the cameras are streaming at {stream.rate_hz:g} Hz; use the stream's "
                                f"pairs or stop it first (stereo/stream with frame_rate_hz 0)")
            self.get_logger().warning(response.message, throttle_duration_sec=5.0)
            return response
        try:
            pair = self.grab(timeout)
        except CameraError as exc:
            response.success = False
            response.message = f"capture failed: {exc}"
            self.get_logger().error(response.message)
            return response
        stamp = self._stamp(pair)
        left = image_msg(pair.left, stamp, str(self.get_parameter("left_frame_id").value))
        right = image_msg(pair.right, stamp, str(self.get_parameter("right_frame_id").value))
        if request.publish:
            self._publish_pair(left, right, self._exposure_msg(pair, stamp))
            # A captured snap is one its readers have: wait until every reliable subscriber (extractor,
            # matcher, bag recorder) acknowledged both images, so a camera killed right after answering
            # cannot take the frames with it. Briefly: a reader that died still counts until discovery
            # drops it, and must not hold up the scan.
            if not self._wait_for_readers(0.2):
                self.get_logger().warning("capture: not every image subscriber acknowledged the frame in time",
                                          throttle_duration_sec=5.0)
        if request.return_images:
            response.left, response.right = left, right
        response.success = True
        response.stamp = stamp
        response.skew_s = float(pair.skew_s)
        return response

    def _on_preview(self) -> None:
        if self._streaming() is not None:  # the stream publishes the pairs
            return
        try:
            pair = self.grab(float(self.get_parameter("capture_timeout_s").value))
        except CameraError as exc:
            self.get_logger().error(f"preview: {exc}", throttle_duration_sec=5.0)
            return
        stamp = self._stamp(pair)
        self._publish_pair(image_msg(pair.left, stamp, str(self.get_parameter("left_frame_id").value)),
                           image_msg(pair.right, stamp, str(self.get_parameter("right_frame_id").value)),
                           self._exposure_msg(pair, stamp))

    # ------------------------------------------------------------------ stream
    def _on_stream(self, request: StreamStereo.Request, response: StreamStereo.Response) -> StreamStereo.Response:
        rate = float(request.frame_rate_hz)
        if not (math.isfinite(rate) and 0.0 <= rate <= MAX_FRAME_RATE_HZ):
            response.success = False
            response.message = (f"frame_rate_hz {rate} is not a rate: give 0 < frame_rate_hz <= {MAX_FRAME_RATE_HZ:g} "
                                f"to start a stream, 0 to stop it")
            return response
        if rate == 0.0:
            return self._stop_stream(response)
        if self.source is None:
            response.success = False
            response.message = f"stream not started: {self.status_message}"
            return response
        if self._streaming() is not None:  # a new rate restarts the stream
            self._stop_stream(StreamStereo.Response())
        now_ns = self._now_ns()
        start_ns = stamps.to_ns(request.start)
        if start_ns != 0 and start_ns < now_ns - stamps.seconds_to_ns(START_PAST_LIMIT_S):
            response.success = False
            response.message = (f"stream not started: its start is {stamps.ns_to_seconds(now_ns - start_ns):.3f} s in the "
                                f"past; give a start time ahead of the node's clock, or zero for now")
            return response
        source = self.source
        period_ns = frame_period_ns(rate)
        if not source.clocked:
            try:
                rate = source.start_stream(rate)
                period_ns = frame_period_ns(rate)
                for problem in source.report():
                    self.get_logger().warning(f"camera setting: {problem}", throttle_duration_sec=60.0)
            except CameraError as exc:
                response.success = False
                response.message = f"stream not started: {exc}"
                return response
        stream = _Stream(rate, period_ns, int(request.frames), start_ns or now_ns, source.exposure_s,
                         DropCounter(period_ns))
        stream.thread = threading.Thread(target=self._run_stream, args=(stream,), name="lsu-camera-stream", daemon=True)
        with self._stream_lock:
            self._stream = stream
        stream.thread.start()
        if not source.clocked:  # the first pair's buffer stamp is the stream's first stamp
            stream.started.wait(float(self.get_parameter("capture_timeout_s").value) + 1.0)
        with self._stream_lock:
            response.success = not stream.error
            response.message = stream.error
            response.first_stamp = stamps.to_msg(stream.t0_ns)
            response.frame_period_s = stamps.ns_to_seconds(stream.period_ns)
            response.exposure_s = float(stream.exposure_s)
            response.frames_published, response.frames_dropped = stream.drops.published, stream.drops.dropped
        self.get_logger().info(f"stream started: {rate:g} Hz from {stamps.to_text(stream.t0_ns)}"
                               + (f", {stream.frames} frames" if stream.frames else ""))
        return response

    def _stop_stream(self, response: StreamStereo.Response) -> StreamStereo.Response:
        with self._stream_lock:
            stream = self._stream
            if stream is None:
                response.success = True
                response.message = "no stream was started"
                return response
            if stream.stop_at_ns is None:
                stream.stop_at_ns = self._now_ns()
            stream.wake.set()
        # every slot before the stop is still published (a clocked source may be running behind)
        stream.done.wait()
        with self._stream_lock:
            response.success = not stream.error
            response.message = stream.error or stream.lags.summary()
            response.first_stamp = stamps.to_msg(stream.last_stamp_ns)
            response.frame_period_s = stamps.ns_to_seconds(stream.period_ns)
            response.exposure_s = float(stream.exposure_s)
            response.frames_published, response.frames_dropped = stream.drops.published, stream.drops.dropped
        self.get_logger().info(f"stream stopped: {response.frames_published} pairs, {response.frames_dropped} dropped; "
                               f"{response.message}")
        return response

    def _run_stream(self, stream: _Stream) -> None:
        source = self.source
        assert source is not None  # checked before the thread starts
        try:
            if source.clocked:
                self._run_clocked(stream, source)
            else:
                self._run_free(stream, source)
        except CameraError as exc:
            stream.error = f"stream ended: {exc}"
        except Exception as exc:
            if not self.context.ok():  # Ctrl-C / SIGTERM shut ROS down under the stream: a normal end
                stream.error = "stream ended: the node shut down"
                return
            stream.error = f"stream ended by an internal error: {exc!r}"  # a thread dies silently otherwise
            raise
        finally:
            if not source.clocked:
                source.stop_stream()
            if stream.error and self.context.ok():
                self.get_logger().error(stream.error)
            stream.started.set()
            stream.done.set()

    def _stream_publish(self, stream: _Stream, pair: StereoPair, stamp_ns: int, index: int) -> None:
        stamp = stamps.to_msg(stamp_ns)
        self._publish_pair(image_msg(pair.left, stamp, str(self.get_parameter("left_frame_id").value)),
                           image_msg(pair.right, stamp, str(self.get_parameter("right_frame_id").value)),
                           self._exposure_msg(pair, stamp, index, streaming=True))
        acknowledged = self._wait_for_readers(float(self.get_parameter("stream_ack_timeout_s").value))
        if not acknowledged:
            self.get_logger().warning(f"stream: pair {index} was not acknowledged by every image reader in time: "
                                      f"counted as dropped", throttle_duration_sec=5.0)
        lag_s = stamps.ns_to_seconds(self._now_ns() - stamp_ns)
        with self._stream_lock:
            stream.drops.add(stamp_ns, acknowledged)
            stream.lags.add(lag_s)
            stream.last_stamp_ns = stamp_ns
        stream.started.set()
        limit = float(self.get_parameter("stream_max_lag_s").value)
        if lag_s > limit:
            raise CameraError(f"pair {index} was published {lag_s:.1f} s after its stamp, more than stream_max_lag_s "
                              f"= {limit:g} s: the source cannot keep up with {stream.rate_hz:g} Hz; stream at a "
                              f"lower rate (every pair up to here was published)")

    def _run_clocked(self, stream: _Stream, source: StereoSource) -> None:
        """Frame k exposed from t_k = t0 + k * period, published once it can exist; never a slot skipped.

        Two stages: a render thread makes each pair once its slot's time has come (`_clocked_pairs`, through
        `read_ahead`), and this thread publishes them in order and waits for the readers' acknowledgements
        meanwhile. Done one after the other, a render (~30 ms of CPU for a simulated pair) plus the wait for the readers took
        longer than a 30 fps period and the stream fell behind; the pairs themselves are the same (their
        content is fixed by the slot's stamp, index and the carriage truth then).
        """
        for index, t_ns, pair in read_ahead(self._clocked_pairs(stream, source), RENDER_AHEAD, "lsu-camera-render"):
            self._stream_publish(stream, pair, t_ns, index)

    def _clocked_pairs(self, stream: _Stream, source: StereoSource) -> Iterator[tuple[int, int, StereoPair]]:
        """The render stage of `_run_clocked`: (index, stamp, pair) per slot in order, each once its time has come."""
        ready_ns = stamps.seconds_to_ns(source.ready_after_s)
        ready_ns += stamps.seconds_to_ns(source.render_delay_s)
        index = 0
        while not stream.frames or index < stream.frames:
            t_ns = slot_stamp_ns(stream.t0_ns, stream.period_ns, index)
            while True:
                with self._stream_lock:
                    stop_at = stream.stop_at_ns
                if stop_at is not None and t_ns >= stop_at:
                    return
                wait_ns = t_ns + ready_ns - self._now_ns()
                if wait_ns <= 0:
                    break
                stream.wake.wait(stamps.ns_to_seconds(wait_ns))
                stream.wake.clear()
            with self._lock:
                pair = source.pair_at(t_ns, index)
            yield index, t_ns, pair
            index += 1

    def _run_free(self, stream: _Stream, source: StereoSource) -> None:
        """Pairs at the devices' rate, stamped from their buffers; missing slots show as stamp gaps."""
        timeout = float(self.get_parameter("capture_timeout_s").value)
        index = 0
        first = True
        while not stream.frames or index < stream.frames:
            with self._lock:
                pair = source.next_pair(timeout)
            stamp_ns = stamps.seconds_to_ns(pair.time_s)
            with self._stream_lock:
                stop_at = stream.stop_at_ns
                if first:
                    if stamp_ns < stream.t0_ns:  # exposed before the requested start
                        continue
                    stream.t0_ns, first = stamp_ns, False
            if stop_at is not None and stamp_ns >= stop_at:
                return
            self._stream_publish(stream, pair, stamp_ns, index)
            index += 1

    def _publish_diagnostics(self) -> None:
        values: dict[str, object] = {"calibration_id": self.calibration.calibration_id if self.calibration else "",
                                     "sim_truth": "received" if self._truth is not None else "none"}
        level, message = self.status_level, self.status_message
        with self._stream_lock:
            stream = self._stream
            if stream is not None:
                values.update({"stream": (f"running at {stream.rate_hz:g} Hz" if stream.running else "stopped"),
                               "stream_frames_published": stream.drops.published,
                               "stream_frames_dropped": stream.drops.dropped,
                               "stream_frames_unacknowledged": stream.drops.unacknowledged,
                               "stream_lag_max_s": f"{stream.lags.max_s:.3f}",
                               "stream_lag_median_s": f"{stream.lags.median_s:.3f}"})
                if stream.error and level == diagnostics.OK:
                    level, message = diagnostics.WARN, stream.error
        self.pub_diag.publish(diagnostics.status_array(self, level, f"{self.get_name()}: cameras", message, values,
                                                       hardware_id=str(self.get_parameter("source").value)))

    def destroy_node(self) -> None:
        """End a stream (without waiting for a backlog) and release the cameras."""
        with self._stream_lock:
            stream = self._stream
            if stream is not None:
                stream.stop_at_ns = -1
                stream.wake.set()
        if stream is not None and stream.thread is not None:
            stream.thread.join(timeout=5.0)
        if self.source is not None:
            self.source.close()
        super().destroy_node()


# multi-threaded: a stream stop waits for the stream's last frames while captures get their refusal
main = main_of(StereoCameraNode, multi_threaded=True)

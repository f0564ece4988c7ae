"""The ``stereo_matcher`` node: left/right laser lines -> ``points`` per snap, ``scan/cloud`` per scan.

A thin adapter over :mod:`lsu_reconstruct.pipeline`:

- pairs ``stereo/left/laser_line`` and ``stereo/right/laser_line`` by exact ``header.stamp``
  (bounded buffers; lines that never find a partner are counted and reported on /diagnostics);
- publishes every pair's points on ``points`` (PointCloud2: x y z rgb u v snap);
- follows ``scan/events``: STARTED opens a scan, SNAP gives each stamp its snap index, TEXTURE
  names the laser-off colour pair (its left ``stereo/left/image_raw`` colours the points), and
  FINISHED / ABORTED publish the whole scan on ``scan/cloud`` (transient-local) once every
  expected snap is in, or after ``scan_timeout_s`` as a partial cloud (logged as partial);
- calibration from files (``calibration_source: file`` + ``calibration_dir``) or from the
  camera node's ``stereo/{left,right}/camera_info`` and ``stereo/extrinsics`` (``topics``);
- sweeps: between SWEEP_START and SWEEP_END every pair stamped from SWEEP_START's image stamp on
  is a sweep frame (:mod:`lsu_reconstruct.sweep_live` keeps the books); it follows
  ``driver/carriage`` and ``stereo/exposure`` and, once the carriage track covers a frame, turns it
  into points on the laser sheet (``laser_sheet_file``): by default across frames (``sweep_matching:
  cross_frame``, `SweepSequence`: the left line matched to the right lines exposed around it, so a
  frame's points may come one frame later, still stamped with its pair's stamp; the sweep's last
  frame, or the scan's end, flushes the rest), or ``per_frame`` (`reconstruct_sweep_frame`: each
  camera's line on the sheet at its own mid-exposure); without a sheet, stereo only (said once);
- a sweep's subject motion (``motion_correction``, docs/MOTION.md): every ``every_frames``-th sweep frame's
  image pair (``stereo/{left,right}/image_raw``, one channel kept) goes to
  :class:`lsu_reconstruct.motion.SweepMotion`; at the scan's end the subject's rigid motion is measured from
  their texture, the scan cloud's points are moved back to the middle frame's pose when it is within limits,
  and the ``motion`` record (per measured frame its pose, fit and reliability; flagged or not and why) is
  published on ``scan/motion`` (std_msgs/String, JSON, latched) before the cloud.
"""

from __future__ import annotations

import json
import struct
import sys
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from sensor_msgs.msg import PointField as RosPointField
from std_msgs.msg import Header, String

from lsu_bags.pointcloud2 import Cloud, decode, encode, from_msg
from lsu_cameras.polled import PolledGroup, take_all
from lsu_common import diagnostics, qos, stamps
from lsu_common.arrays import AnyArray
from lsu_common.images import msg_to_bgr
from lsu_common.node import LsuNode, main_of
from lsu_common.params import Param, declare_parameters
from lsu_interfaces.msg import CarriagePosition, LaserLine, ScanEvent, StereoExposure, StereoExtrinsics

from .laser_sheet import LaserSheet, LaserSheetError, read_laser_yaml
from .matching import LineArrays, MatchParams, prepare
from .motion import MotionParams, SweepMotion
from .pipeline import (
    MAX_VIEW_ANGLE_DEG,
    SnapPoints,
    colour_at,
    drop_grazing,
    load_drop_grazing,
    merge_snaps,
    reconstruct_snap,
)
from .stereo import CalibrationError, StereoModel
from .sweep import SweepParams, exposure_mid_s
from .sweep_live import SWEEP_MATCHING, Exposure, LiveSweep, SweepPoints
from .triangulate import METHODS

__all__ = ["StereoMatcherNode", "cloud_to_msg", "line_from_msg", "image_to_array", "decode_msg",
           "main"]

RELIABLE_DATA = qos.reliable(50)
EVENTS = qos.EVENTS
LATCHED = qos.LATCHED
IMAGES_KEPT = 8  # newest left frames kept for the texture: its TEXTURE event may come a few frames late
# a sweep's image pairs held (serialized, per side) until their frame is placed and the motion keeps them or not:
# a frame is placed once the lines and the carriage track cover it, some frames after its images came
SWEEP_IMAGES_HELD = 32
CARRIAGE_KEPT = 400  # newest carriage positions kept between sweeps (the stop before a sweep's start)
EXPOSURES_KEPT = 64  # exposures kept before their sweep's SWEEP_START event (the stream starts first)
# newest pairs that came outside a scan, kept for the next STARTED: DDS keeps no order across topics, so a scan's
# first pairs can come before its STARTED event (a bag played on a loaded host); those stamped after the event's
# stamp are the scan's
EARLY_PAIRS_KEPT = 16
# carriage reports a sweep is placed by: the device-stamped ones (a status reply is stamped at the middle
# of its round trip and may come out of order with them)
SWEEP_CARRIAGE_SOURCES = ("pos", "done")


# ---------------------------------------------------------------------------- message conversion
def cloud_to_msg(cloud: Cloud, header: Header) -> PointCloud2:
    """A codec :class:`Cloud` as sensor_msgs/PointCloud2 with ``header``."""
    msg = PointCloud2()
    msg.header = header
    msg.height, msg.width = int(cloud.height), int(cloud.width)
    msg.fields = [RosPointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count) for f in cloud.fields]
    msg.is_bigendian = bool(cloud.is_bigendian)
    msg.point_step, msg.row_step = int(cloud.point_step), int(cloud.row_step)
    msg.data = cloud.data
    msg.is_dense = bool(cloud.is_dense)
    return msg


def line_from_msg(msg: LaserLine) -> LineArrays:
    """lsu_interfaces/LaserLine -> :class:`LineArrays`."""
    def arr(values: Any) -> AnyArray:
        return np.frombuffer(values, dtype=np.float32).astype(np.float64) if len(values) else np.zeros(0)

    return LineArrays(u=arr(msg.u), v=arr(msg.v), peak=arr(msg.peak), width=arr(msg.width),
                      quality=arr(msg.quality), image_width=msg.image_width, image_height=msg.image_height)


def image_to_array(msg: Image) -> AnyArray:
    """A sensor_msgs/Image (any supported encoding) as an HxWx3 BGR uint8 array (the scan's texture)."""
    return msg_to_bgr(msg)


_stamp_key = stamps.to_ns


def _cdr_stamp_key(raw: bytes) -> int:
    """`_stamp_key` of a serialized message that starts with a std_msgs/Header (e.g. Image).

    CDR: a 4-byte encapsulation header (byte 1: 0 = big, 1 = little endian), then the
    header's stamp as int32 sec and uint32 nanosec, so the key is read without decoding the
    rest of a 900 KB image.
    """
    sec, nanosec = struct.unpack_from("<iI" if raw[1] & 1 else ">iI", raw, 4)
    return sec * stamps.NS_PER_S + nanosec


def parameter_table() -> dict[str, Param]:
    """The matcher's parameters; the calibration's source and folder are read at start-up (read-only)."""
    p = MatchParams()
    return {
        "calibration_source": Param("topics", "where the stereo calibration comes from: 'file' (calibration_dir) or "
                                    "'topics' (stereo/{left,right}/camera_info + stereo/extrinsics)", read_only=True),
        "calibration_dir": Param("", "folder with left.yaml, right.yaml, stereo.yaml (calibration_source: file)",
                                 read_only=True),
        "depth_min_m": Param(p.depth_min_m, "nearest accepted point along the left optical axis [m]", (0.0, 100.0)),
        "depth_max_m": Param(p.depth_max_m, "farthest accepted point along the left optical axis [m]", (1e-3, 100.0)),
        "max_gap_rows": Param(p.max_gap_rows, "right laser samples further apart than this [rows] are not joined",
                              (1e-3, 1000.0)),
        "max_step_px": Param(p.max_step_px, "nor samples whose column jumps more than this per row [px] (depth edges, "
                             "reflections)", (1e-3, 1000.0)),
        "max_order_dev": Param(p.max_order_dev, "ordering tolerance when a left point has several crossings "
                               "[segments]", (0.0, 1000.0)),
        "min_quality": Param(p.min_quality, "drop laser rows whose extractor quality is below this (0..1)", (0.0, 1.0)),
        "smooth_window_rows": Param(p.smooth_window_rows, "rows of the local quadratic fit along each laser line (odd, "
                                    ">= 5; 0 = no smoothing)", (0, 1001)),
        "min_run_rows": Param(p.min_run_rows, "a match needs both samples in continuous pieces of line this long "
                              "(stray detections form short pieces; 0 = off)", (0, 1001)),
        "max_view_angle_deg": Param(MAX_VIEW_ANGLE_DEG, "scan cloud: drop points whose surface (normal from the cloud) "
                                    "either camera sees flatter than this from its normal [deg]; 90 = keep all",
                                    (1.0, 90.0)),
        "max_reproj_px": Param(p.max_reproj_px, "reject points whose reprojection error exceeds this [px]",
                               (1e-3, 1000.0)),
        "triangulation": Param(p.method, "triangulation method: midpoint, dlt or optimal"),
        "pair_buffer": Param(64, "laser lines kept while waiting for their partner (per side)", (1, 100000)),
        "scan_timeout_s": Param(5.0, "after FINISHED/ABORTED, wait this long for missing snaps, then publish the "
                                "partial scan cloud [s]", (1e-3, 3600.0)),
        "laser_sheet_file": Param("", "laser sheet calibration (laser.yaml of `lsu calibrate --laser`) for sweep scans; "
                                  "empty = laser.yaml in calibration_dir; none found: sweeps are matched stereo only",
                                  read_only=True),
        "sweep_matching": Param(SWEEP_MATCHING[0], "sweep frames to points: 'cross_frame' (each left line matched to "
                                "the right lines exposed around it) or 'per_frame' (each frame alone); refused "
                                "while a sweep runs"),
        "motion_measure": Param(True, "sweep scans: measure the subject's motion from the frames' texture and publish "
                                "it on scan/motion (applies from the next sweep)"),
        "motion_correction": Param(True, "sweep scans: move the scan cloud's points back to one head pose when the "
                                   "measured motion is within limits (applies at the next scan's end)"),
        "motion_every_frames": Param(MotionParams().every_frames, "sweep scans: measure the motion on every Nth "
                                     "frame (applies from the next sweep)", (1, 100)),
        "motion_max_frames": Param(SweepMotion.MAX_FRAMES, "sweep scans: measure the motion on at most this many frames (a longer sweep "
                                   "on every Nth frame accordingly; each costs two dense flows before the scan's cloud "
                                   "is out; applies from the next sweep)", (6, 10000)),
    }


class _Line:
    """One side's laser line: its header and its arrays, converted from the message when first read
    (a malformed message is then reported where the pair is reconstructed)."""

    __slots__ = ("header", "_arrays", "_msg")

    def __init__(self, header: Header, arrays: LineArrays | None = None, msg: LaserLine | None = None) -> None:
        self.header, self._arrays, self._msg = header, arrays, msg

    @property
    def arrays(self) -> LineArrays:
        if self._arrays is None:
            assert self._msg is not None
            self._arrays = line_from_msg(self._msg)
        return self._arrays


@dataclass
class _Scan:
    scan_id: str
    expected: int
    snaps: dict[int, SnapPoints] = field(default_factory=dict)
    texture_key: int | None = None
    texture: AnyArray | None = None
    frames_after_texture: int = 0        # left frames seen stamped after the texture's, while it is missing
    end_type: int | None = None       # FINISHED or ABORTED once known
    end_reason: str = ""
    end_time_s: float = 0.0
    published: bool = False
    motion: SweepMotion | None = None    # a sweep's frames for the motion measurement (motion_measure)


class StereoMatcherNode(LsuNode):
    """Matches left/right laser lines along epipolar lines and publishes 3D points (see module doc)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("stereo_matcher", **{"namespace": "/lsu", **kwargs})
        declare_parameters(self, parameter_table(), check=self._check_parameters,
                           apply=lambda _: self._use_params(self._match_params()), apply_now=False)

        self.model: StereoModel | None = None
        self.calibration_error = ""
        self._use_params(self._match_params())
        self.left: OrderedDict[int, _Line] = OrderedDict()
        self.right: OrderedDict[int, _Line] = OrderedDict()
        self.unmatched = {"left": 0, "right": 0}
        self.pairs = 0
        self.points_last = 0
        self.errors = 0
        self.last_error = ""
        self.free_snap = 0
        self.scan: _Scan | None = None
        self.snap_of_stamp: dict[int, int] = {}
        # pairs whose SNAP (or SWEEP_START) event is not in yet: their lines, reconstructed once it is
        self.waiting: OrderedDict[int, tuple[_Line, _Line]] = OrderedDict()
        self._outside_scan: deque[tuple[int, _Line, _Line]] = deque(maxlen=EARLY_PAIRS_KEPT)
        self.sweep: LiveSweep | None = None
        self.sweep_points: SweepPoints | None = None  # the running sweep's frames to points (with a calibration)
        self.sweep_stats: dict[str, int] = {}
        self._carriage: deque[tuple[float, float, bool]] = deque(maxlen=CARRIAGE_KEPT)
        self._exposures: OrderedDict[int, Exposure] = OrderedDict()
        self.sheet: LaserSheet | None = None
        self.sheet_note = ""
        self._camera_info: dict[str, CameraInfo] = {}
        # left images taken while holding a sweep's and not held, not yet looked at for the texture
        self._left_seen: deque[Any] = deque(maxlen=IMAGES_KEPT)
        self._extrinsics: StereoExtrinsics | None = None

        self.points_pub = self.create_publisher(PointCloud2, "points", 10)
        self.cloud_pub = self.create_publisher(PointCloud2, "scan/cloud", LATCHED)
        self.motion_pub = self.create_publisher(String, "scan/motion", LATCHED)
        self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        # kept so that a direct replay, which hands lines and events over itself, can remove them
        self.input_subscriptions = [
            self.create_subscription(LaserLine, "stereo/left/laser_line", lambda m: self.on_line("left", m),
                                     RELIABLE_DATA),
            self.create_subscription(LaserLine, "stereo/right/laser_line", lambda m: self.on_line("right", m),
                                     RELIABLE_DATA),
            self.create_subscription(ScanEvent, "scan/events", self.on_event, EVENTS),
            self.create_subscription(CarriagePosition, "driver/carriage", self.on_carriage, RELIABLE_DATA),
            self.create_subscription(StereoExposure, "stereo/exposure", self.on_exposure, RELIABLE_DATA)]
        # Read on demand, only while a TEXTURE event names an image not yet found: the reader keeps
        # the newest few frames in DDS, and the snaps' frames (one per snap, 900 KB) are never
        # taken into Python nor wake the executor (each was a copy and a callback in the replay's
        # busiest thread). Raw: only the texture pair's image is ever decoded.
        self._image_sub = self.create_subscription(Image, "stereo/left/image_raw", lambda _raw: None, qos.reliable(IMAGES_KEPT),
            callback_group=PolledGroup(), raw=True)
        # the right images: read only during a sweep whose motion is measured
        self._right_image_sub = self.create_subscription(Image, "stereo/right/image_raw", lambda _raw: None,
                                                         qos.reliable(IMAGES_KEPT), callback_group=PolledGroup(),
                                                         raw=True)
        # where the texture image is looked for: serialized left images not yet looked at (a direct
        # replay, which has no image topic, gives its own source; it gives no right images: no motion measured)
        self.take_left_images: Callable[[], Iterable[Any]] = lambda: take_all(self._image_sub)
        self.take_right_images: Callable[[], Iterable[Any]] = lambda: take_all(self._right_image_sub)
        # a measured sweep's serialized images by stamp, per side, until their frame is placed (`_hold_images`)
        self._held: dict[str, OrderedDict[int, Any]] = {"left": OrderedDict(), "right": OrderedDict()}
        self._waiting_images: dict[int, int] = {}  # stamp -> index of measured frames placed before their images
        if self.get_parameter("calibration_source").value == "topics":
            # camera_info comes with every image (volatile, like the images); a volatile reader also
            # matches latched publishers (older bags), so either kind of camera is heard
            info_qos = qos.SCAN_DATA
            self.create_subscription(CameraInfo, "stereo/left/camera_info", lambda m: self.on_info("left", m), info_qos)
            self.create_subscription(CameraInfo, "stereo/right/camera_info", lambda m: self.on_info("right", m),
                                     info_qos)
            self.create_subscription(StereoExtrinsics, "stereo/extrinsics", self.on_extrinsics, LATCHED)
            self.calibration_error = "waiting for stereo/{left,right}/camera_info and stereo/extrinsics"
            self.get_logger().info(self.calibration_error)
        else:
            self._load_calibration_file()
        self._load_laser_sheet()
        self.create_timer(0.1, self._check_scan_end)
        self.create_timer(1.0, self.publish_diagnostics)

    # ------------------------------------------------------------------ parameters and calibration
    def _match_params(self) -> MatchParams:
        g = lambda name: self.get_parameter(name).value  # noqa: E731
        return MatchParams(depth_min_m=float(g("depth_min_m")), depth_max_m=float(g("depth_max_m")),
                           max_gap_rows=float(g("max_gap_rows")), max_step_px=float(g("max_step_px")),
                           max_order_dev=float(g("max_order_dev")),
                           min_quality=float(g("min_quality")), smooth_window_rows=int(g("smooth_window_rows")),
                           min_run_rows=int(g("min_run_rows")),
                           max_reproj_px=float(g("max_reproj_px")), method=str(g("triangulation")))

    def _use_params(self, params: MatchParams) -> None:
        prepare(params)  # caches filled now, not on the first snap
        self.params = params
        sweep_points: SweepPoints | None = getattr(self, "sweep_points", None)  # None before __init__ sets it
        if sweep_points is not None:
            sweep_points.use_params(SweepParams(match=params))

    def _check_parameters(self, params: list[Any]) -> str | None:
        """Choices and odd window sizes (the ranges are in the descriptors, checked by rclpy)."""
        for param in params:
            if param.name == "triangulation" and param.value not in METHODS:
                return f"triangulation must be one of {', '.join(METHODS)}"
            if param.name == "sweep_matching" and param.value not in SWEEP_MATCHING:
                return f"sweep_matching must be one of {', '.join(SWEEP_MATCHING)}"
            if param.name == "sweep_matching" and getattr(self, "sweep", None) is not None \
                    and param.value != self.get_parameter("sweep_matching").value:
                return "sweep_matching cannot change while a sweep runs: set it between sweeps"
            if param.name == "smooth_window_rows" and not (param.value == 0 or (param.value >= 5 and param.value % 2)):
                return "smooth_window_rows must be 0 or an odd number >= 5"
        return None

    def _load_calibration_file(self) -> None:
        folder = str(self.get_parameter("calibration_dir").value)
        if not folder:
            self.calibration_error = "calibration_source is 'file' but calibration_dir is empty; set it to a folder " \
                                     "with left.yaml, right.yaml and stereo.yaml"
            self.get_logger().error(self.calibration_error)
            return
        try:
            self.model = StereoModel.from_folder(folder)
        except CalibrationError as exc:
            self.calibration_error = str(exc)
            self.get_logger().error(f"cannot use the calibration: {exc}")
            return
        self.calibration_error = ""
        self.get_logger().info(f"calibration {self.model.calibration_id} from {folder}: baseline "
                               f"{self.model.baseline_m * 1000:.1f} mm")

    def _load_laser_sheet(self) -> None:
        path = str(self.get_parameter("laser_sheet_file").value)
        folder = str(self.get_parameter("calibration_dir").value)
        if not path and folder and (Path(folder) / "laser.yaml").exists():
            path = str(Path(folder) / "laser.yaml")
        if not path:
            self.sheet_note = "no laser sheet calibration (laser_sheet_file, or laser.yaml in calibration_dir)"
            return
        try:
            self.sheet = read_laser_yaml(path)
        except (LaserSheetError, OSError) as exc:
            self.sheet_note = f"laser sheet not usable: {exc}"
            self.get_logger().error(f"{self.sheet_note}; sweeps are matched stereo only")
            return
        self.get_logger().info(f"laser sheet from {path}")

    def on_info(self, side: str, msg: CameraInfo) -> None:
        """camera_info of one side (one per image); (re)builds the model when it changed and all parts are in."""
        previous = self._camera_info.get(side)
        self._camera_info[side] = msg
        if previous is None or (previous.width, previous.height, list(previous.k), list(previous.d)) != (
                msg.width, msg.height, list(msg.k), list(msg.d)):
            self._model_from_topics()

    def on_extrinsics(self, msg: StereoExtrinsics) -> None:
        """Latched stereo extrinsics."""
        self._extrinsics = msg
        self._model_from_topics()

    def _model_from_topics(self) -> None:
        left, right, ext = self._camera_info.get("left"), self._camera_info.get("right"), self._extrinsics
        if left is None or right is None or ext is None:
            return
        try:
            self.model = StereoModel.from_arrays(
                np.asarray(left.k), np.asarray(left.d), np.asarray(right.k), np.asarray(right.d),
                np.asarray(ext.rotation), np.asarray(ext.translation), (left.width, left.height),
                E=np.asarray(ext.essential), F=np.asarray(ext.fundamental), right_image_size=(right.width, right.height),
                source="camera_info + extrinsics topics", rms_px=float(ext.rms_px),
                calibration_id=ext.calibration_id, left_frame_id=ext.header.frame_id or "lsu_left_optical",
                right_frame_id=ext.right_frame_id or "lsu_right_optical")
        except CalibrationError as exc:
            self.model = None
            self.calibration_error = str(exc)
            self.get_logger().error(f"cannot use the calibration from the topics: {exc}")
            return
        self.calibration_error = ""
        self.get_logger().info(f"calibration from topics: baseline {self.model.baseline_m * 1000:.1f} mm")

    # ------------------------------------------------------------------ laser lines
    def on_line(self, side: str, msg: LaserLine) -> None:
        """Buffer one side's line; when its partner (same stamp) is in, reconstruct the pair."""
        self._on_line(side, _Line(msg.header, msg=msg))

    def on_line_arrays(self, side: str, header: Header, arrays: LineArrays) -> None:
        """`on_line` of a line already in arrays (a direct replay hands the extractor's over without a message)."""
        self._on_line(side, _Line(header, arrays))

    def _on_line(self, side: str, line: _Line) -> None:
        key = _stamp_key(line.header.stamp)
        other = self.right if side == "left" else self.left
        mine = self.left if side == "left" else self.right
        if key in other:
            partner = other.pop(key)
            left, right = (line, partner) if side == "left" else (partner, line)
            self.pairs += 1
            self.process_pair(key, left, right)
            return
        mine[key] = line
        while len(mine) > int(self.get_parameter("pair_buffer").value):
            mine.popitem(last=False)
            self.unmatched[side] += 1

    def process_pair(self, key: int, left: _Line, right: _Line) -> None:
        """Reconstruct one stereo pair and route it to ``points`` and the running scan."""
        if self.model is None:
            self._error(f"laser lines arrive but there is no calibration: {self.calibration_error}")
            return
        if self.sweep is not None and self.sweep.is_frame(key):
            self._hold_images()
            self.sweep.add_pair(key, left.arrays, right.arrays)
            self._sweep_progress()
            return
        if self.scan is not None and not self.scan.published:
            index = self.snap_of_stamp.get(key)
            if index is None:
                self.waiting[key] = (left, right)  # its SNAP (or SWEEP_START) event is still on the way
                while len(self.waiting) > int(self.get_parameter("pair_buffer").value):
                    self.waiting.popitem(last=False)
                return
            self._snap_of_pair(key, left, right, index)
            return
        self._outside_scan.append((key, left, right))
        snap = self._reconstruct(key, left, right)
        if snap is not None:
            self._publish_points(snap, self.free_snap, left.header)
            self.free_snap += 1

    def _reconstruct(self, key: int, left: _Line, right: _Line) -> SnapPoints | None:
        assert self.model is not None
        try:
            snap = reconstruct_snap(self.model, left.arrays, right.arrays, self.params)
        except (CalibrationError, ValueError) as exc:
            self._error(f"cannot reconstruct the pair stamped {key / 1e9:.3f}: {exc}")
            return None
        self.points_last = len(snap)
        return snap

    def _snap_of_pair(self, key: int, left: _Line, right: _Line, index: int) -> None:
        snap = self._reconstruct(key, left, right)
        if snap is not None:
            self._file_snap(index, snap, left.header)

    # ------------------------------------------------------------------ sweeps
    def on_carriage(self, msg: CarriagePosition) -> None:
        """A stamped carriage position (``driver/carriage``): kept, and it may place waiting sweep frames."""
        if msg.source not in SWEEP_CARRIAGE_SOURCES:
            return
        sample = (stamps.to_seconds(msg.header.stamp), float(msg.position_steps), bool(msg.moving))
        self._carriage.append(sample)
        if self.sweep is not None:
            self.sweep.add_carriage(*sample)
            self._sweep_progress()

    def sweep_inputs_wanted(self) -> bool:
        """Whether carriage positions and exposures can serve a sweep now: not while a stop-snap scan runs (its first
        SNAP seen, not ended; only stop-snap scans have SNAP events, and no sweep starts within one). A caller that
        feeds the matcher itself (the direct replay) may then leave them undecoded, handing over the last carriage
        position once this is True again (the stop a next sweep may start from)."""
        scan = self.scan
        return not (scan is not None and scan.end_type is None and self.sweep is None and self.snap_of_stamp)

    def on_exposure(self, msg: StereoExposure) -> None:
        """A pair's exposure (``stereo/exposure``): kept until its sweep frame is placed."""
        key = _stamp_key(msg.header.stamp)
        exposure = Exposure(float(msg.left_start_offset_s), float(msg.right_start_offset_s), float(msg.exposure_s),
                            int(msg.frame_index))
        if self.sweep is not None and self.sweep.is_frame(key):
            self.sweep.add_exposure(key, exposure)
            self._sweep_progress()
            return
        self._exposures[key] = exposure
        while len(self._exposures) > EXPOSURES_KEPT:
            self._exposures.popitem(last=False)

    def _start_sweep(self, msg: ScanEvent) -> None:
        first = _stamp_key(msg.image_stamp)
        sweep = self.sweep = LiveSweep(first, int(msg.expected_snaps), start_position=float(msg.position_steps))
        self.sweep_points = None
        for sample in self._carriage:
            sweep.add_carriage(*sample)
        for key, exposure in self._exposures.items():
            sweep.add_exposure(key, exposure)
        for key in [k for k in self.waiting if sweep.is_frame(k)]:
            left, right = self.waiting.pop(key)
            sweep.add_pair(key, left.arrays, right.arrays)
        if self.scan is not None and bool(self.get_parameter("motion_measure").value):
            self.scan.motion = SweepMotion.for_sweep(
                int(msg.expected_snaps), MotionParams(every_frames=int(self.get_parameter("motion_every_frames").value)),
                int(self.get_parameter("motion_max_frames").value))
        self._hold_images()
        if self.sheet is None:
            self.get_logger().warning(f"sweep: {self.sheet_note}; its frames are matched stereo only")
        self.get_logger().info(f"sweep: {msg.expected_snaps} frames from the pair stamped {first / 1e9:.3f}")
        self._sweep_progress()

    def _sweep_progress(self, finish: bool = False) -> None:
        """Reconstruct every sweep frame that can be placed now (all that wait with ``finish``)."""
        sweep = self.sweep
        if sweep is None or self.model is None:
            return
        if self.sweep_points is None:
            self.sweep_points = SweepPoints(self.model, self.sheet, SweepParams(match=self.params),
                                            str(self.get_parameter("sweep_matching").value))
        frames, track = sweep.finish() if finish else sweep.ready()
        self._frames_to_motion(frames, track)
        done = self.sweep_points.add(frames, track)
        if finish or sweep.complete:  # no later frame to match with: the frames still waiting come out
            done += self.sweep_points.flush()
        for key, message in self.sweep_points.errors:
            self._error(f"cannot reconstruct the sweep frame stamped {key / 1e9:.3f}: {message}")
        self.sweep_points.errors.clear()
        for key, index, points in done:
            for name, value in points.stats.items():
                self.sweep_stats[name] = self.sweep_stats.get(name, 0) + int(value)
            self.points_last = len(points)
            header = Header(stamp=stamps.to_msg(key))
            if self.scan is not None and not self.scan.published:
                self._file_snap(index, points, header)
            else:
                self._publish_points(points, index, header)
        if finish:
            for name, value in sweep.counts.items():
                self.sweep_stats[name] = value
            self.sweep, self.sweep_points = None, None

    def _hold_images(self) -> None:
        """A measured sweep's new images held by stamp until their frame is placed; images of frames the motion does
        not measure (their exposure says which slot they are) are let go at once."""
        scan, sweep = self.scan, self.sweep
        if scan is None or scan.motion is None or sweep is None:
            return
        for side, take in (("left", self.take_left_images), ("right", self.take_right_images)):
            held = self._held[side]
            for raw in take():
                key = _cdr_stamp_key(raw)
                exposure = sweep.exposures.get(key)
                if not sweep.is_frame(key) or (exposure is not None and not scan.motion.wants(exposure.frame_index)):
                    if side == "left":
                        self._left_seen.append(raw)  # the texture may be among them
                    continue
                held[key] = raw
                while len(held) > SWEEP_IMAGES_HELD:
                    held.popitem(last=False)
        # a frame placed before its images came (the matcher reads them on its own schedule)
        for key in [k for k in self._waiting_images if k in self._held["left"] and k in self._held["right"]]:
            images = self._read_images(key)
            if images is not None:
                scan.motion.add_images(self._waiting_images[key], images)
            del self._waiting_images[key]

    def _read_images(self, key: int) -> tuple[AnyArray, AnyArray] | None:
        """The held pair stamped ``key`` (let go) as one channel each: the blue one, where the red laser adds little
        (lsu_reconstruct.motion); None when either is missing or unreadable (said)."""
        if key not in self._held["left"] or key not in self._held["right"]:
            return None  # the one that came stays held for the other
        left_raw, right_raw = self._held["left"].pop(key), self._held["right"].pop(key)
        try:
            left, right = (np.ascontiguousarray(image_to_array(deserialize_message(bytes(raw), Image))[..., 0])
                           for raw in (left_raw, right_raw))
        except ValueError as exc:
            self._error(f"sweep frame stamped {key / 1e9:.3f}: its images cannot be read for the motion: {exc}")
            return None
        return left, right

    def _frames_to_motion(self, frames: list[tuple[int, Any]], track: Any) -> None:
        """Each placed sweep frame's time, lines and (every Nth) images to the scan's motion measurement."""
        scan = self.scan
        if scan is None or scan.motion is None or not frames:
            return
        self._hold_images()
        for key, frame in frames:
            t = exposure_mid_s(frame.left_start_s, frame.exposure_s)
            images = None
            if scan.motion.wants(frame.index):
                images = self._read_images(key)
                if images is None:
                    self._waiting_images[key] = frame.index
            else:
                for held in self._held.values():
                    held.pop(key, None)
            position = float(track.position_at(t)) if track is not None else None
            scan.motion.add_frame(frame.index, t, frame.left, frame.right, images, position)

    def _file_snap(self, index: int, snap: SnapPoints, header: Header) -> None:
        assert self.scan is not None
        self._publish_points(snap, index, header)
        self.scan.snaps[index] = snap

    def _publish_points(self, snap: SnapPoints, index: int, header: Header) -> None:
        snap.snap = np.full(len(snap), index, dtype=np.uint32)
        if not self.points_pub.get_subscription_count():
            return  # volatile: a message no reader holds is never seen, so it is not encoded (a replay's usual case)
        if self.scan is not None and self.scan.texture is not None:
            snap.rgb = colour_at(self.scan.texture, snap.u, snap.v)  # the scan cloud colours every snap again
        out = Header(stamp=header.stamp, frame_id=self.model.left_frame_id if self.model else "lsu_left_optical")
        self.points_pub.publish(cloud_to_msg(encode(snap.fields()), out))

    def _error(self, text: str) -> None:
        self.errors += 1
        self.last_error = text
        self.get_logger().error(text, throttle_duration_sec=5.0)

    def prepare_scan_cloud(self) -> None:
        """Load what the scan cloud's filters need (once per process), ahead of the scan's end: for a caller that
        times the scan (the direct replay). The live node leaves it to the scan's end: loaded as a scan starts, it
        held the matcher ~0.3 s (the import keeps the GIL) while a sweep's first frames and its laser-off pair
        came in, and a sweep's cloud came out uncoloured."""
        load_drop_grazing(float(self.get_parameter("max_view_angle_deg").value))

    # ------------------------------------------------------------------ scan events and texture
    def on_event(self, msg: ScanEvent) -> None:
        """Scan bookkeeping: STARTED, TEXTURE, SNAP, FINISHED, ABORTED."""
        self._look_for_texture()  # an image that came after its TEXTURE event
        if msg.type == ScanEvent.STARTED:
            self.scan = _Scan(msg.scan_id, int(msg.expected_snaps))
            self.snap_of_stamp.clear()
            self.waiting.clear()
            begun = _stamp_key(msg.header.stamp)
            for key, left, right in self._outside_scan:
                if 0 < begun <= key:  # the scan's own pair, come before its (stamped) STARTED event
                    self.waiting[key] = (left, right)
            self._outside_scan.clear()
            self.sweep, self.sweep_points, self.sweep_stats = None, None, {}
            for held in self._held.values():
                held.clear()
            self._waiting_images.clear()
            self.get_logger().info(f"scan {msg.scan_id}: started, {msg.expected_snaps} snaps expected")
            return
        if self.scan is None or (msg.scan_id and msg.scan_id != self.scan.scan_id):
            self.get_logger().warning(f"scan event {msg.type} for scan '{msg.scan_id}' without its STARTED; ignored",
                                      throttle_duration_sec=5.0)
            return
        key = _stamp_key(msg.image_stamp)
        if msg.type == ScanEvent.SNAP:
            self.snap_of_stamp[key] = int(msg.index)
            pair = self.waiting.pop(key, None)
            if pair is not None:
                self._snap_of_pair(key, pair[0], pair[1], int(msg.index))
        elif msg.type == ScanEvent.SWEEP_START:
            self._start_sweep(msg)
        elif msg.type == ScanEvent.SWEEP_END:
            if self.sweep is not None:
                self.sweep.end(key, int(msg.snaps_captured))
                self._sweep_progress()
        elif msg.type == ScanEvent.TEXTURE:
            self.scan.texture_key = key
            self._look_for_texture()
        elif msg.type in (ScanEvent.FINISHED, ScanEvent.ABORTED):
            if msg.type == ScanEvent.ABORTED:
                self._sweep_progress(finish=True)  # the scan is over: what still waits is placed as well as it can be
            self.scan.end_type = msg.type
            if msg.type == ScanEvent.FINISHED and msg.snaps_captured:
                self.scan.expected = int(msg.snaps_captured)
            self.scan.end_reason = msg.reason
            # monotonic, not the ROS clock: a step of the system clock (NTP, a user) must neither cut the wait
            # for the last snaps short nor stretch it
            self.scan.end_time_s = time.monotonic()
            self._check_scan_end()

    def _look_for_texture(self) -> None:
        """If the scan waits for its texture image, take the waiting left images and look for it."""
        scan = self.scan
        if scan is None or scan.texture_key is None or scan.texture is not None \
                or scan.frames_after_texture > IMAGES_KEPT:
            return
        # only the frames waiting now can hold it: the ones taken earlier were checked against the same key
        raw = None
        self._hold_images()
        seen = list(self._left_seen)
        self._left_seen.clear()
        for candidate in [*seen, *self.take_left_images()]:
            key = _cdr_stamp_key(candidate)
            if key == scan.texture_key:
                raw = candidate
            scan.frames_after_texture += key > scan.texture_key
        if raw is None:
            if scan.frames_after_texture > IMAGES_KEPT:  # it would be out of the reader's history by now
                self.get_logger().warning(f"scan {scan.scan_id}: the texture image (left, stamped "
                                          f"{scan.texture_key / 1e9:.3f}) never came; the cloud stays uncoloured")
            return
        try:
            scan.texture = image_to_array(deserialize_message(bytes(raw), Image))  # a buffer view is copied once
        except ValueError as exc:
            self._error(str(exc))

    def _check_scan_end(self) -> None:
        self._look_for_texture()
        scan = self.scan
        if scan is None or scan.end_type is None or scan.published:
            return
        waited = time.monotonic() - scan.end_time_s
        timeout_s = float(self.get_parameter("scan_timeout_s").value)
        if self.sweep is not None:
            # FINISHED may overtake the sweep's last frames: the extractor's lines come later than the events
            # (a replayed bag plays them at the recorded pace, the extraction lags on a busy host); the frames
            # SWEEP_END counted as published are awaited like missing snaps, then what waits is placed
            if not self.sweep.complete and waited < timeout_s:
                return
            self._sweep_progress(finish=True)
        complete = len(scan.snaps) >= scan.expected and scan.end_type == ScanEvent.FINISHED
        if not complete and waited < timeout_s:
            return
        self.publish_scan(partial=not complete)

    def publish_scan(self, partial: bool) -> None:
        """Publish the scan's points (in snap order, coloured if the texture is in) on ``scan/cloud``."""
        scan = self.scan
        assert scan is not None
        snaps = [scan.snaps[i] for i in sorted(scan.snaps)]
        if scan.texture is not None:
            for s in snaps:
                s.rgb = colour_at(scan.texture, s.u, s.v)
        cloud = merge_snaps(snaps)
        header = Header(stamp=self.get_clock().now().to_msg(),
                        frame_id=self.model.left_frame_id if self.model else "lsu_left_optical")
        if scan.motion is not None and self.model is not None:
            self._measure_motion(scan, cloud)
        if self.model is not None:
            cloud = drop_grazing(cloud, self.model, float(self.get_parameter("max_view_angle_deg").value))
        self.cloud_pub.publish(cloud_to_msg(encode(cloud.fields()), header))
        scan.published = True
        what = f"scan {scan.scan_id}: {len(cloud)} points from {len(snaps)} of {scan.expected} snaps"
        if scan.texture is None:
            what += " (no texture: uncoloured)"
        if partial:
            cause = "aborted: " + scan.end_reason if scan.end_type == ScanEvent.ABORTED else \
                f"missing snaps after {self.get_parameter('scan_timeout_s').value} s"
            self.get_logger().warning(f"{what}; PARTIAL cloud published ({cause})")
        else:
            self.get_logger().info(f"{what}; cloud published")

    def _measure_motion(self, scan: _Scan, cloud: SnapPoints) -> None:
        """The sweep's motion measured, the cloud corrected in place when within limits, ``scan/motion`` published."""
        assert scan.motion is not None and self.model is not None
        for held in self._held.values():
            held.clear()
        self._waiting_images.clear()
        started = time.monotonic()
        try:
            cloud.xyz, record = scan.motion.correct(self.model, cloud.xyz, cloud.snap,
                                                    apply=bool(self.get_parameter("motion_correction").value))
        except Exception as exc:  # noqa: BLE001 - the scan's cloud must still come out, saying what failed
            record = {"measured": False, "flagged": False, "corrected": False,
                      "why": f"the motion measurement failed: {exc.__class__.__name__}: {exc}"}
            self._error(record["why"])
        scan.motion = None  # its images are let go
        record = {"scan_id": scan.scan_id, **record, "compute_s": round(time.monotonic() - started, 3)}
        self.motion_pub.publish(String(data=json.dumps(record)))
        if record.get("flagged"):
            self.get_logger().warning(f"scan {scan.scan_id}: subject motion beyond correction in frames "
                                      f"{record.get('unreliable_frames')}: {record.get('message', '')}")
        else:
            self.get_logger().info(f"scan {scan.scan_id}: subject motion "
                                   + (f"{record.get('measured_motion_mm', 0.0):.2f} mm, "
                                      f"{'corrected' if record.get('corrected') else 'left as it is'}"
                                      if record.get("measured") else f"not measured: {record.get('why')}"))

    # ------------------------------------------------------------------ diagnostics
    def publish_diagnostics(self) -> None:
        """Pairing counts and calibration health on /diagnostics."""
        if self.model is None:
            level, message = diagnostics.ERROR, f"no calibration: {self.calibration_error}"
        elif self.unmatched["left"] or self.unmatched["right"] or self.errors:
            level = diagnostics.WARN
            message = (f"{self.unmatched['left']} left / {self.unmatched['right']} right lines never paired, "
                              f"{self.errors} errors")
        else:
            level, message = diagnostics.OK, f"{self.pairs} pairs matched"
        values = {"pairs": self.pairs, "unmatched_left": self.unmatched["left"],
                  "unmatched_right": self.unmatched["right"], "buffered_left": len(self.left),
                  "buffered_right": len(self.right), "points_last_snap": self.points_last, "errors": self.errors,
                  "last_error": self.last_error,
                  "calibration": self.model.calibration_id or self.model.source if self.model else "none",
                  "laser_sheet": "loaded" if self.sheet is not None else self.sheet_note,
                  **{f"sweep_{name}": value for name, value in self.sweep_stats.items()}}
        self.diag_pub.publish(diagnostics.status_array(
            self, level, f"{self.get_fully_qualified_name()}: stereo matching", message, values,
            hardware_id="lsu_stereo"))


def decode_msg(msg: PointCloud2, names: list[str] | None = None) -> dict[str, AnyArray]:
    """Columns of a sensor_msgs/PointCloud2 (any layout) as numpy arrays."""
    return decode(from_msg(msg), names)


main = main_of(StereoMatcherNode)


if __name__ == "__main__":
    sys.exit(main())

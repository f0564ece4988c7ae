"""The server's side of the ROS graph: one `LsuScanner` (its own rclpy context, spun by its own thread)
plus the subscriptions the page shows. Holds no scanner state of its own: the driver's state, the
coordinator's action and events, the matcher's points, the cameras' images are forwarded as they come.

Everything a callback hands to the browsers goes through the `Outbox` (bounded, drops the oldest),
so no callback ever waits for a browser. Images, laser lines and points are subscribed only while a
browser is connected, best effort (no camera waits for this reader's acknowledgement, as the Foxglove
bridge does), raw (a frame the rate limit drops is never deserialized), and images go out at most
``image_max_hz`` a side, downscaled JPEG.
"""

from __future__ import annotations

import json
import struct
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .outbox import BULK, CONTROL, Outbox

#: a ScanEvent type -> its name on the page
EVENT_NAMES = {0: "STARTED", 1: "TEXTURE", 2: "SNAP", 3: "FINISHED", 4: "ABORTED", 5: "SWEEP_START", 6: "SWEEP_END"}
#: longest "laser on" the hardware panel grants [s]: the page holds it, the server switches it off after this
LASER_TEST_MAX_S = 30.0
#: laser-line rows sent per line (every n-th row); the page draws a polyline through them
LINE_ROWS_MAX = 240


def _stamp_ns(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


@dataclass
class LaserHold:
    """The hardware panel's "laser on": who asked (a page's WebSocket id) and until when (monotonic)."""

    client: int
    until: float
    why_off: str = ""


@dataclass
class ScanWatch:
    """The page's view of the scan this server started (the goal handle lives in the LsuScanner)."""

    mode: str
    started: float
    reported: bool = False
    result: dict[str, Any] | None = None
    result_at: float = 0.0
    canceled_here: bool = False
    last_feedback: Any = None
    notices_told: int = 0      # of the scanner's notices ("hold still, scanning again"), how many the page was sent
    extra: dict[str, Any] = field(default_factory=dict)


class WebGraph:
    """The graph as the web server sees it (construct in the server process; `close` at exit)."""

    def __init__(self, outbox: Outbox, image_max_hz: float = 2.0, image_width_px: int = 400,
                 wait_s: float = 15.0) -> None:
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

        from lsu_common import qos
        from lsu_interfaces.msg import LaserLine, ScanEvent, ScannerState
        from lsu_interfaces.srv import Enroll, Identify
        from lsu_scan.scanner import LsuScanner

        self.outbox = outbox
        self.image_max_hz = float(image_max_hz)
        self.image_width_px = int(image_width_px)
        self.scanner = LsuScanner(wait_s=wait_s)
        self.node = self.scanner.node
        self._lock = threading.Lock()
        self._best_effort = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=2,
                                       reliability=ReliabilityPolicy.BEST_EFFORT)
        self._line_type = LaserLine
        self.state: Any | None = None
        self.state_at = 0.0
        self._state_sent = 0.0
        self.watch: ScanWatch | None = None
        self.laser_hold: LaserHold | None = None
        self.foreign_scan: dict[str, Any] = {}
        self._heavy: list[Any] = []
        self._last_image: dict[str, float] = {"left": 0.0, "right": 0.0}
        self._forwarded: dict[str, list[int]] = {"left": [], "right": []}
        self.points_forwarded = 0
        self.node.create_subscription(ScannerState, "driver/state", self._on_state, 10)
        self.node.create_subscription(ScanEvent, "scan/events", self._on_event, qos.EVENTS)
        self.enroll_client = self.node.create_client(Enroll, "face/enroll")
        self.identify_client = self.node.create_client(Identify, "face/identify")
        from action_msgs.srv import CancelGoal

        self._cancel_client = self.node.create_client(CancelGoal, "scan/_action/cancel_goal")
        from lsu_interfaces.srv import CaptureStereo

        self.capture_client = self.node.create_client(CaptureStereo, "stereo/capture")
        self.node.create_timer(0.1, self._tick)

    def close(self) -> None:
        self.scanner.close()

    # -------------------------------------------------------------- state and events (control)
    def _on_state(self, msg: Any) -> None:
        self.state = msg
        self.state_at = time.monotonic()
        now = time.monotonic()
        # the driver publishes on every change and >= 5 Hz: forward changes at once, repeats at 2 Hz
        last = self.outbox.latest("state")
        doc = state_doc(msg)
        if last is not None and {k: v for k, v in last.items() if k != "t"} == doc and now - self._state_sent < 0.5:
            return
        self._state_sent = now
        doc["t"] = time.time()
        self.outbox.publish(CONTROL, {"type": "state", **doc}, latest_key="state")

    def _on_event(self, msg: Any) -> None:
        name = EVENT_NAMES.get(int(msg.type), str(msg.type))
        doc = {"type": "event", "event": name, "scan_id": msg.scan_id, "expected": int(msg.expected_snaps),
               "index": int(msg.index), "position": int(msg.position_steps), "captured": int(msg.snaps_captured),
               "partial": bool(msg.partial), "reason": msg.reason, "output_dir": msg.output_dir}
        if name in ("STARTED", "SWEEP_START") and msg.expected_snaps:
            self.foreign_scan = {"scan_id": msg.scan_id, "total": int(msg.expected_snaps), "done": 0,
                                 "sweep": name == "SWEEP_START"}
        elif name == "SNAP" and self.foreign_scan.get("scan_id") == msg.scan_id:
            self.foreign_scan["done"] = int(msg.index) + 1
        self.outbox.publish(CONTROL, doc, latest_key=None if name == "SNAP" else "event")
        if name in ("FINISHED", "ABORTED"):
            self.foreign_scan = {}

    def _tick(self) -> None:
        """10 Hz in the spin thread: heavy subscriptions follow the browsers; scan progress; laser hold."""
        self._sync_heavy()
        self._scan_progress()
        self._laser_deadline()

    # -------------------------------------------------------------- scans
    def _scan_progress(self) -> None:
        w = self.watch
        if w is None:
            if self.foreign_scan.get("total") and not self.foreign_scan.get("sweep"):
                f = self.foreign_scan
                self.outbox.publish(CONTROL, {"type": "progress", "scan_id": f["scan_id"], "done": f["done"],
                                              "total": f["total"], "eta_s": None, "stage": "another client's scan",
                                              "points": None, "position": None}, latest_key="progress")
            return
        # notices (the coordinator's "hold still, scanning again" before a rescan) are sent once each, apart from
        # the progress: a progress message is replaced by the next one within a tick
        notices = self.scanner.notices
        for text in notices[w.notices_told:]:
            self.outbox.publish(CONTROL, {"type": "notice", "text": text})
        w.notices_told = len(notices)
        fb = self.scanner.get_feedback()
        if fb is not None and fb is not w.last_feedback:
            w.last_feedback = fb
            self.outbox.publish(CONTROL, {
                "type": "progress", "done": min(int(fb.snap_index) + 1, int(fb.snaps_total)),
                "total": int(fb.snaps_total), "eta_s": round(float(fb.eta_s), 1), "stage": fb.stage,
                "points": int(fb.points_so_far), "position": int(fb.position_steps)}, latest_key="progress")
        if not w.reported and self.scanner.is_task_complete():
            if w.result is None:
                r = self.scanner.get_result(timeout_s=1.0)
                w.result = {"type": "result", "outcome": r.result.name, "success": r.success, "partial": r.partial,
                            "scan_id": r.scan_id, "snaps": r.snaps, "points": r.points,
                            "seconds": round(r.seconds, 2), "output_dir": r.output_dir, "files": r.files,
                            "status": r.status, "canceled_here": w.canceled_here}
                w.result_at = time.monotonic()
            # the end is reported with the laser as the driver states it after the end (not as the page assumes)
            state_after = self.state is not None and self.state_at > w.result_at
            if state_after or time.monotonic() - w.result_at > 5.0:
                laser_on = bool(self.state.laser_on) if self.state is not None else None
                w.result["laser_on"] = laser_on
                w.result["laser_text"] = ("laser off (the driver reports it)" if laser_on is False else
                                          "the driver still reports the laser ON" if laser_on else
                                          "no driver state: laser unknown")
                w.reported = True
                self.outbox.publish(CONTROL, dict(w.result), latest_key="progress")

    def start_scan(self, goal: dict[str, Any]) -> None:
        """Send the scan goal (blocking; call from a worker thread). Raises ScannerError when refused."""
        with self._lock:
            if self.watch is not None and not self.watch.reported:
                from lsu_scan.scanner import ScannerError

                raise ScannerError("a scan started from this page is still running")
            self.scanner.start_scan(**goal)
            self.watch = ScanWatch(goal.get("mode", "stopsnap"), time.time())
            self.outbox.publish(CONTROL, {"type": "progress", "done": 0, "total": 0, "eta_s": None,
                                          "stage": "starting", "points": 0, "position": None}, latest_key="progress")

    def cancel_scan(self, timeout_s: float = 10.0) -> str:
        """Cancel every goal of the scan action (the scan started here or by anyone else)."""
        from action_msgs.srv import CancelGoal

        if self.watch is not None and not self.watch.reported:
            self.watch.canceled_here = True
        if not self._cancel_client.wait_for_service(timeout_sec=timeout_s):
            raise TimeoutError("the scan action's cancel service is not available (is scan_coordinator running?)")
        request = CancelGoal.Request()  # zero goal id and zero stamp: every goal (ROS 2 action semantics)
        response = self._wait(self._cancel_client.call_async(request), timeout_s, "cancel")
        if not response.goals_canceling:
            return "no scan was running"
        return f"canceling {len(response.goals_canceling)} scan(s): the coordinator switches the laser off"

    @staticmethod
    def _wait(future: Any, timeout_s: float, what: str) -> Any:
        end = time.monotonic() + timeout_s
        while not future.done():
            if time.monotonic() > end:
                raise TimeoutError(f"{what}: no answer within {timeout_s:g} s")
            time.sleep(0.005)
        return future.result()

    def call(self, client: Any, request: Any, timeout_s: float, what: str) -> Any:
        """Call a service (blocking; a worker thread)."""
        if not client.wait_for_service(timeout_sec=min(timeout_s, 5.0)):
            raise TimeoutError(f"{what}: service {client.srv_name} is not available (is its node running?)")
        return self._wait(client.call_async(request), timeout_s, what)

    def scanning(self) -> bool:
        """A scan runs (ours or anyone's), as the graph says."""
        return bool((self.watch is not None and not self.watch.reported) or self.foreign_scan)

    # -------------------------------------------------------------- hardware test: laser for a bounded time
    def laser_on_for(self, client: int, seconds: float) -> float:
        """Switch the laser on for at most LASER_TEST_MAX_S, held by WebSocket ``client``; returns the hold."""
        seconds = max(0.5, min(float(seconds), LASER_TEST_MAX_S))
        self.scanner.laser(True)
        self.laser_hold = LaserHold(client, time.monotonic() + seconds)
        self.outbox.publish(CONTROL, {"type": "laser_hold", "seconds": seconds, "why_off": ""}, latest_key="laser")
        return seconds

    def laser_off(self, why: str) -> None:
        """Switch the laser off now (blocking; any thread but the spin thread)."""
        self.laser_hold = None
        self.scanner.laser(False)
        self.outbox.publish(CONTROL, {"type": "laser_hold", "seconds": 0, "why_off": why}, latest_key="laser")

    def client_gone(self, client: int) -> None:
        """A page's WebSocket closed: a laser it holds goes off (called from the server's worker thread)."""
        hold = self.laser_hold
        if hold is not None and hold.client == client:
            self.laser_off("the page that switched the laser on was closed")

    def _laser_deadline(self) -> None:
        hold = self.laser_hold
        if hold is not None and time.monotonic() >= hold.until:
            from std_srvs.srv import SetBool

            self.laser_hold = None
            # in the spin thread: send and do not wait (the answer is taken by this very thread)
            self.scanner._laser.call_async(SetBool.Request(data=False))
            self.outbox.publish(CONTROL, {"type": "laser_hold", "seconds": 0,
                                          "why_off": "the laser test time ran out"}, latest_key="laser")

    # -------------------------------------------------------------- live data (bulk), only while watched
    def _sync_heavy(self) -> None:
        watched = self.outbox.count > 0
        if watched and not self._heavy:
            from sensor_msgs.msg import Image, PointCloud2

            from lsu_interfaces.msg import LaserLine

            for side in ("left", "right"):
                self._heavy.append(self.node.create_subscription(
                    Image, f"stereo/{side}/image_raw", self._image_cb(side), self._best_effort, raw=True))
                self._heavy.append(self.node.create_subscription(
                    LaserLine, f"stereo/{side}/laser_line", self._line_cb(side), self._best_effort, raw=True))
            self._heavy.append(self.node.create_subscription(PointCloud2, "points", self._on_points,
                                                             self._best_effort, raw=True))
        elif not watched and self._heavy:
            for sub in self._heavy:
                self.node.destroy_subscription(sub)
            self._heavy = []

    def _image_cb(self, side: str) -> Any:
        from rclpy.serialization import deserialize_message
        from sensor_msgs.msg import Image

        def on_image(data: bytes) -> None:
            now = time.monotonic()
            if self.image_max_hz <= 0 or now - self._last_image[side] < 1.0 / self.image_max_hz:
                return  # dropped before it was deserialized
            self._last_image[side] = now
            msg = deserialize_message(data, Image)
            frame = encode_preview(msg, self.image_width_px)
            if frame is None:
                return
            stamp = _stamp_ns(msg.header.stamp)
            kept = self._forwarded[side]
            kept.append(stamp)
            del kept[:-4]
            self.outbox.publish(BULK, b"I" + (b"L" if side == "left" else b"R") + struct.pack(
                "<qII", stamp, int(msg.width), int(msg.height)) + frame)

        return on_image

    def _line_cb(self, side: str) -> Any:
        from rclpy.serialization import deserialize_message

        line_type = self._line_type

        def on_line(data: bytes) -> None:
            # a line is small next to an image: read it, keep it only when its image was forwarded
            msg = deserialize_message(data, line_type)
            stamp = _stamp_ns(msg.header.stamp)
            if stamp not in self._forwarded[side]:
                return
            u = np.asarray(msg.u, dtype=np.float32)
            v = np.asarray(msg.v, dtype=np.float32)
            every = max(1, len(u) // LINE_ROWS_MAX + (1 if len(u) % LINE_ROWS_MAX else 0))
            u, v = u[::every], v[::every]
            self.outbox.publish(BULK, b"L" + (b"L" if side == "left" else b"R") + struct.pack(
                "<qI", stamp, len(u)) + u.tobytes() + v.tobytes())

        return on_line

    def _on_points(self, data: bytes) -> None:
        from rclpy.serialization import deserialize_message
        from sensor_msgs.msg import PointCloud2

        from lsu_bags.pointcloud2 import decode, from_msg, unpack_rgb

        msg = deserialize_message(data, PointCloud2)
        cloud = from_msg(msg)
        names = [f.name for f in cloud.fields]
        cols = decode(cloud, [n for n in ("x", "y", "z", "rgb") if n in names])
        if "x" not in cols or len(cols["x"]) == 0:
            return
        xyz = np.stack([cols["x"], cols["y"], cols["z"]], axis=1).astype(np.float32)
        ok = np.all(np.isfinite(xyz), axis=1)
        xyz = xyz[ok]
        rgb = (unpack_rgb(cols["rgb"])[ok].astype(np.uint8) if "rgb" in cols
               else np.full((len(xyz), 3), 200, np.uint8))
        self.points_forwarded += len(xyz)
        self.outbox.publish(BULK, b"P" + struct.pack("<I", len(xyz)) + xyz.tobytes() + rgb.tobytes())

    def capture_pair(self, timeout_s: float = 15.0) -> tuple[Any, Any]:
        """A fresh stereo pair as arrays from the camera node (blocking; a worker thread)."""
        from lsu_cameras.live import image_from_msg
        from lsu_interfaces.srv import CaptureStereo

        if self.scanning():
            raise RuntimeError("a scan is running: calibration captures wait until it ends")
        request = CaptureStereo.Request(publish=True, return_images=True)
        response = self.call(self.capture_client, request, timeout_s, "stereo/capture")
        if not response.success:
            raise RuntimeError(response.message or "stereo/capture failed")
        return image_from_msg(response.left), image_from_msg(response.right)

    # -------------------------------------------------------------- about
    def node_names(self) -> list[str]:
        return sorted(f"{ns.rstrip('/')}/{name}" for name, ns in self.node.get_node_names_and_namespaces()
                      if not name.startswith("_") and not name.startswith("lsu_scanner_"))

    def parameters(self, node_name: str, timeout_s: float = 5.0) -> dict[str, Any]:
        """Every parameter of ``node_name`` as its parameter services say (blocking; a worker thread)."""
        from rcl_interfaces.srv import GetParameters, ListParameters
        from rclpy.parameter import parameter_value_to_python

        lister = self.node.create_client(ListParameters, f"{node_name}/list_parameters")
        getter = self.node.create_client(GetParameters, f"{node_name}/get_parameters")
        try:
            names = list(self.call(lister, ListParameters.Request(), timeout_s, "list parameters").result.names)
            values = self.call(getter, GetParameters.Request(names=names), timeout_s, "get parameters").values
            return {n: parameter_value_to_python(v) for n, v in zip(names, values)}
        finally:
            self.node.destroy_client(lister)
            self.node.destroy_client(getter)


def state_doc(msg: Any) -> dict[str, Any]:
    return {"connected": bool(msg.connected), "homed": bool(msg.homed), "moving": bool(msg.moving),
            "laser_on": bool(msg.laser_on), "at_start": bool(msg.at_start), "at_end": bool(msg.at_end),
            "sweeping": bool(msg.sweeping), "position": int(msg.position_steps), "target": int(msg.target_steps),
            "track": int(msg.track_steps), "rate": round(float(msg.step_rate_steps_per_s), 1),
            "watchdog_ms": int(msg.watchdog_ms), "port": msg.port, "firmware": msg.firmware, "fault": msg.fault}


def encode_preview(msg: Any, width_px: int) -> bytes | None:
    """An Image message as a JPEG at most ``width_px`` wide (None if it cannot be decoded)."""
    import cv2

    from lsu_common.images import ImageFormatError, msg_to_bgr

    try:
        bgr = msg_to_bgr(msg)
    except ImageFormatError:
        return None
    h, w = bgr.shape[:2]
    if w > width_px:
        bgr = cv2.resize(bgr, (width_px, max(1, round(h * width_px / w))), interpolation=cv2.INTER_AREA)
    ok, jpeg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 75])
    return bytes(jpeg) if ok else None


def to_json(doc: Any) -> str:
    return json.dumps(doc, default=str)

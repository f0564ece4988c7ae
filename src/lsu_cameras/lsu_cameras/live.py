"""Guided live stereo calibration: board coverage tracking (pure) and a thin client of ``stereo/capture``.

Modelled on image_pipeline's ``camera_calibration``: every detected board is summarised by four
numbers measured in the image — X and Y (where the board centre is), size (how much of the image
it fills) and skew (how far it is tilted, from the angles of its outer corner quadrilateral). A
view is kept only when it differs from every kept view by more than a distance in that 4-D space
(so holding the board still adds nothing), and the views suffice when each number has spanned a
large enough range in both cameras and there are at least ``min_views`` of them.

`CoverageTracker` and `run_live_calibration` import no rclpy; `CaptureClient` is the only ROS code
here (imported lazily) and just turns ``/lsu/stereo/capture`` responses into image arrays.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from lsu_common.arrays import AnyArray
from lsu_common.images import ImageFormatError, msg_to_array

from .calibration import BoardSpec, CalibrationError, StereoCalibrationResult, calibrate_stereo, find_board

#: Parameter names in display order.
PARAMETERS = ("X", "Y", "size", "skew")


class LiveCalibrationError(CalibrationError):
    """Live calibration cannot go on (no capture service, camera failing, too few views)."""


@dataclass(frozen=True)
class BoardParams:
    """One board seen in one image, normalised to [0, 1] (see the module docstring)."""

    x: float
    y: float
    size: float
    skew: float

    def as_array(self) -> AnyArray:
        """``[x, y, size, skew]``."""
        return np.array([self.x, self.y, self.size, self.skew])


def _outside_corners(corners: AnyArray, board: BoardSpec) -> AnyArray:
    """The four extreme inner corners, in order up-left, up-right, down-right, down-left (4x2)."""
    grid = np.asarray(corners, dtype=np.float64).reshape(board.rows, board.cols, 2)
    return np.stack([grid[0, 0], grid[0, -1], grid[-1, -1], grid[-1, 0]])


def board_params(corners: AnyArray, board: BoardSpec, image_size: tuple[int, int]) -> BoardParams:
    """X, Y, size and skew of a detected board (``corners`` as from `find_board`) in a ``(w, h)`` image.

    X and Y are the corner centroid mapped so that a board touching the left/top edge is 0 and one
    touching the right/bottom edge is 1: the image is shrunk by the board's own side first, as
    camera_calibration does, otherwise a large board could never reach the ends of the range.
    size is the quadrilateral's area over the image area. skew is twice the mean deviation of its
    four angles from 90 deg (radians, clipped to 1): 0 for a board facing the camera, growing with
    tilt about either board axis and unchanged by rotation in the image plane.
    """
    width, height = image_size
    pts = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    quad = _outside_corners(pts, board)
    x, y = quad[:, 0], quad[:, 1]
    area = 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))  # shoelace
    side = np.sqrt(area)
    centre = pts.mean(axis=0)
    p_x = float(np.clip((centre[0] - side / 2) / max(width - side, 1.0), 0.0, 1.0))
    p_y = float(np.clip((centre[1] - side / 2) / max(height - side, 1.0), 0.0, 1.0))
    # angle at each vertex between its two edges (vectorised over the four vertices)
    a = np.roll(quad, 1, axis=0) - quad
    b = np.roll(quad, -1, axis=0) - quad
    cos = np.sum(a * b, axis=1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    angles = np.arccos(np.clip(cos, -1.0, 1.0))
    skew = float(min(1.0, 2.0 * np.mean(np.abs(np.pi / 2 - angles))))
    return BoardParams(p_x, p_y, float(area / (width * height)), skew)


@dataclass
class AcceptedView:
    """A kept stereo view: its images, detections and parameters in both cameras."""

    number: int                 # 1-based, in order of acceptance
    left: AnyArray
    right: AnyArray
    corners_left: AnyArray
    corners_right: AnyArray
    params_left: BoardParams
    params_right: BoardParams


@dataclass
class Verdict:
    """What `CoverageTracker.consider` decided about one pair."""

    accepted: bool
    reason: str = ""                      # why rejected (empty when accepted)
    view: AcceptedView | None = None   # the new view when accepted
    nearest: int | None = None         # number of the closest kept view (too-close rejections)
    distance: float = float("nan")        # parameter distance to that view


@dataclass
class Coverage:
    """Range reached by one parameter (the worse of the two cameras)."""

    name: str
    low: float
    high: float
    progress: float   # (high - low) / required range, clipped to [0, 1]


#: Required span of each parameter. camera_calibration asks for 0.7, 0.7, 0.4 (sqrt of the area
#: ratio) and 0.5. Our boards must stay whole in *both* verging cameras at 0.3-0.5 m, which leaves
#: far less room to move. With these, 40 seeded sessions of `random_board_poses` on the simulated
#: rig (0.33-0.50 m, tilts up to 35 deg) were good enough after a median of 12 views (at most 20)
#: with at most one repeat rejected, while boards at one distance or never tilted never are.
DEFAULT_RANGES: dict[str, float] = {"X": 0.25, "Y": 0.25, "size": 0.08, "skew": 0.30}


@dataclass
class CoverageTracker:
    """Accepts stereo board views that add coverage and says when they suffice.

    ``min_distance`` is the L1 distance in (X, Y, size, skew) of the left image below which a view
    counts as a repeat of a kept one (camera_calibration uses 0.2 on its own scale; ours is smaller
    because the reachable ranges are). Coverage is measured in both cameras; the worse one counts.
    """

    board: BoardSpec
    min_views: int = 12
    min_distance: float = 0.06
    ranges: dict[str, float] = field(default_factory=lambda: dict(DEFAULT_RANGES))
    views: list[AcceptedView] = field(default_factory=list)
    image_size: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        if self.min_views < 1:
            raise LiveCalibrationError(f"min_views {self.min_views} must be at least 1")
        missing = [p for p in PARAMETERS if not self.ranges.get(p, 0) > 0]
        if missing:
            raise LiveCalibrationError(f"coverage ranges need a positive value for {', '.join(missing)}")

    def consider(self, left: AnyArray, right: AnyArray) -> Verdict:
        """Detect the board in both images and keep the pair if it adds coverage."""
        size = (int(left.shape[1]), int(left.shape[0]))
        if (right.shape[1], right.shape[0]) != size:
            return Verdict(False, f"left image is {size[0]}x{size[1]} but right is {right.shape[1]}x{right.shape[0]}")
        if self.image_size is not None and size != self.image_size:
            return Verdict(False, f"image size {size[0]}x{size[1]} differs from the first view's "
                                  f"{self.image_size[0]}x{self.image_size[1]}")
        corners_l = find_board(left, self.board)
        corners_r = find_board(right, self.board) if corners_l is not None else None
        if corners_l is None or corners_r is None:
            missing = "left" if corners_l is None else "right"
            return Verdict(False, f"board not found in {missing} image")
        return self.add_detection(left, right, corners_l, corners_r)

    def add_detection(self, left: AnyArray, right: AnyArray, corners_left: AnyArray,
                      corners_right: AnyArray) -> Verdict:
        """Keep an already detected pair if it is far enough from every kept view."""
        size = (int(left.shape[1]), int(left.shape[0]))
        p_l = board_params(corners_left, self.board, size)
        p_r = board_params(corners_right, self.board, size)
        if self.views:
            kept = np.stack([v.params_left.as_array() for v in self.views])
            dist = np.abs(kept - p_l.as_array()).sum(axis=1)
            k = int(np.argmin(dist))
            if dist[k] <= self.min_distance:
                return Verdict(False, f"too close to view {self.views[k].number}", nearest=self.views[k].number,
                               distance=float(dist[k]))
        if self.image_size is None:
            self.image_size = size
        view = AcceptedView(len(self.views) + 1, left, right, corners_left, corners_right, p_l, p_r)
        self.views.append(view)
        return Verdict(True, view=view)

    def coverage(self) -> list[Coverage]:
        """Per-parameter range over the kept views (worse camera) and progress towards the required span."""
        out = []
        for k, name in enumerate(PARAMETERS):
            if not self.views:
                out.append(Coverage(name, 0.0, 0.0, 0.0))
                continue
            spans = []
            for side in ("params_left", "params_right"):
                values = np.array([getattr(v, side).as_array()[k] for v in self.views])
                spans.append((float(values.min()), float(values.max())))
            low, high = min(spans, key=lambda s: s[1] - s[0])
            out.append(Coverage(name, low, high, float(min(1.0, (high - low) / self.ranges[name]))))
        return out

    def is_good_enough(self) -> bool:
        """Every parameter spans its required range and at least ``min_views`` views are kept."""
        return len(self.views) >= self.min_views and all(c.progress >= 1.0 for c in self.coverage())

    def bars(self, width: int = 6) -> str:
        """``X [####  ] Y [###   ] size [##    ] skew [#     ]`` progress bars (full only when reached)."""
        return " ".join(f"{c.name} [{'#' * int(c.progress * width):<{width}}]" for c in self.coverage())

    def pairs(self) -> list[tuple[str, AnyArray, AnyArray]]:
        """Kept views as ``(name, left, right)`` for `calibrate_stereo`."""
        return [(f"{v.number:03d}", v.left, v.right) for v in self.views]


def save_pairs(views: Sequence[AcceptedView], directory: Path | str) -> list[Path]:
    """Write ``left_NNN.png`` / ``right_NNN.png`` of each view so ``lsu calibrate --pairs`` can redo the run."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for v in views:
        for side, image in (("left", v.left), ("right", v.right)):
            path = directory / f"{side}_{v.number:03d}.png"
            if not cv2.imwrite(str(path), image):
                raise LiveCalibrationError(f"cannot write {path}: check the --save-pairs folder is writable")
            written.append(path)
    return written


@dataclass
class LiveResult:
    """How a live session ended and, when it calibrated, the calibration."""

    captures: int
    views: list[AcceptedView]
    good_enough: bool
    stopped_by: str                                  # "good enough" | "max views" | "interrupted"
    calibration: StereoCalibrationResult | None = None


def run_live_calibration(capture: Callable[[], tuple[AnyArray, AnyArray]], tracker: CoverageTracker,
                         interval_s: float = 1.0, max_captures: int | None = None, min_views: int = 8,
                         save_dir: Path | str | None = None, report: Callable[[str], None] = print,
                         stop: threading.Event | None = None, max_failures: int = 3) -> LiveResult:
    """Capture, judge and report pairs until the coverage suffices, then calibrate like ``--pairs``.

    ``capture()`` returns one fresh ``(left, right)`` pair or raises `LiveCalibrationError` when the
    camera failed (``max_failures`` in a row end the session). The session also ends after
    ``max_captures`` captures, when ``stop`` is set, or on KeyboardInterrupt (Ctrl-C); it then
    calibrates when at least ``min_views`` views were kept and raises `LiveCalibrationError`
    otherwise. Nothing is written unless it calibrates (``save_dir`` gets the kept pairs first).
    """
    captures, failures, stopped_by = 0, 0, "interrupted"
    try:
        while True:
            if stop is not None and stop.is_set():
                break
            if max_captures is not None and captures >= max_captures:
                stopped_by = "max views"
                break
            if captures and interval_s > 0:
                time.sleep(interval_s)  # time for the user to move the board
            try:
                left, right = capture()
            except LiveCalibrationError as exc:
                failures += 1
                report(f"capture failed: {exc}")
                if failures >= max_failures:
                    raise LiveCalibrationError(f"{failures} captures in a row failed, last: {exc}") from None
                continue
            failures = 0
            captures += 1
            verdict = tracker.consider(left, right)
            if verdict.view is not None:
                report(f"capture {captures}: view {verdict.view.number} accepted: {tracker.bars()}")
            else:
                report(f"capture {captures}: rejected: {verdict.reason}")
            if tracker.is_good_enough():
                stopped_by = "good enough"
                break
    except KeyboardInterrupt:
        stopped_by = "interrupted"
    good = tracker.is_good_enough()
    n = len(tracker.views)
    if stopped_by == "good enough":
        report(f"coverage is good enough with {n} views: calibrating")
    if n < min_views:
        raise LiveCalibrationError(f"stopped ({stopped_by}) with {n} accepted views; need at least {min_views} "
                                   "to calibrate. Nothing written: run again and move the board between captures "
                                   "(across the image, nearer and farther, tilted).")
    if not good:
        lacking = [c.name for c in tracker.coverage() if c.progress < 1.0]
        report(f"stopped ({stopped_by}) with {n} views; coverage incomplete"
               + (f" in {', '.join(lacking)}" if lacking else f" (fewer than {tracker.min_views} views)")
               + ": calibrating anyway, check the result")
    if save_dir is not None:
        save_pairs(tracker.views, save_dir)
        report(f"saved {n} pairs to {save_dir} (repeat with `lsu calibrate --pairs {save_dir}`)")
    result = calibrate_stereo(tracker.pairs(), tracker.board, min_views=min_views)
    return LiveResult(captures, list(tracker.views), good, stopped_by, result)


def image_from_msg(msg: Any) -> AnyArray:
    """A BGR (or gray) uint8 array of a sensor_msgs/Image (`lsu_common.images`; bgr8, rgb8, mono8, bgra8, rgba8, Bayer)."""
    try:
        return np.ascontiguousarray(msg_to_array(msg))
    except ImageFormatError as exc:
        raise LiveCalibrationError(f"camera image: {exc}") from None


class CaptureClient:
    """Calls ``stereo/capture`` (return_images=true) from its own rclpy context; use as a context manager."""

    SERVICE = "stereo/capture"

    def __init__(self, namespace: str = "/lsu", wait_s: float = 10.0, timeout_s: float = 10.0) -> None:
        from lsu_common.node import GraphClient
        from lsu_interfaces.srv import CaptureStereo

        # publish=True as well: whoever watches image_raw (rviz, rqt) sees what the calibration judged
        self._request = CaptureStereo.Request(publish=True, return_images=True)
        self.timeout_s = timeout_s
        self._graph = GraphClient(f"lsu_calibrate_{id(self) & 0xFFFF:x}", namespace)
        self.context, self.node, self.executor = self._graph.context, self._graph.node, self._graph.executor
        self.client = self.node.create_client(CaptureStereo, self.SERVICE)
        self.service = self.node.resolve_service_name(self.SERVICE)
        if not self.client.wait_for_service(timeout_sec=wait_s):
            self.close()
            raise LiveCalibrationError(f"capture service {self.service} not available: start the cameras with "
                                       "`lsu launch sim` (simulated rig) or `lsu launch lab` (the unit), in the "
                                       "same ROS_DOMAIN_ID")

    def capture(self) -> tuple[AnyArray, AnyArray]:
        """One fresh pair as BGR arrays; raises `LiveCalibrationError` when the node reports a failure."""
        future = self.client.call_async(self._request)
        end = time.monotonic() + self.timeout_s
        while not future.done():
            if time.monotonic() > end:
                self.client.remove_pending_request(future)
                raise LiveCalibrationError(f"{self.service}: no answer within {self.timeout_s:g} s")
            time.sleep(0.005)
        response = future.result()
        if response is None or not response.success:
            raise LiveCalibrationError(response.message if response is not None else f"{self.service} failed")
        return image_from_msg(response.left), image_from_msg(response.right)

    def close(self) -> None:
        """Leave the graph."""
        self._graph.close()

    def __enter__(self) -> CaptureClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

"""Stop-snap settle from the images: capture as soon as the laser line has stopped moving (no rclpy).

After a stop the carriage rings on its belt (a decaying oscillation, see the emulator's vibration
model); the fixed settle waits a time long enough for every stop. ``adaptive`` watches the line
instead: captures right after the stop, each compared with the frame before it. The first capture
whose laser line lies where the previous frame's did (median shift over the image rows within half
of ``tolerance_px``) is the snap; a capture that moved is left unacknowledged (no SNAP event: the
matcher does not file it, the same as a capture the laser guard had taken again). Every candidate
is published, and its line is the one the graph's laser_extractor publishes for it: no image
travels twice, and the snap is the second frame after the stop when the line is already still.
(Returning the images in the capture's response and extracting in the coordinator was tried
first: on a loaded 2-core host the 1.8 MB responses made each snap several times slower than the
fixed settle.)

Bounds and limits:
- once the fixed settle (counted from the stop) has passed when a capture starts, that capture is
  the snap whatever it shows, so adaptive is never much later than fixed (a moving subject or a
  flickering line cannot stall the scan);
- an image shows the line where the sheet was on average over the exposure: a 20 ms exposure of a
  ~22 Hz ringing averages much of it away (the line widens a little rather than moves), so the
  images bound that average, the snap's measured line, and not the carriage's peak excursion;
- two frames agree when the line moved less than ``tolerance_px / 2`` between them, so the snap is
  within ``tolerance_px`` of rest when the frame before it was within half of it; two frames at the
  same point of the oscillation agree too. The test checks the snap's offset against the sim's
  truth over the range of phases at which the probe can fall;
- only the left image is compared: both cameras see the same sheet move.

`settle_from_images` takes the frames as callables, so the same decision runs on the laser_extractor's
lines in the coordinator and on rendered frames (`line_profile`, the extractor's own function) in tests.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lsu_common.arrays import AnyArray

__all__ = ["SETTLE_MODES", "DEFAULT_TOLERANCE_PX", "MIN_ROWS", "SettleTrace", "line_profile", "profile_from_line",
           "line_shift_px", "settle_from_images", "rendered_settle"]

SETTLE_MODES = ("fixed", "adaptive")
# How far from rest the snap's line may be [px]; frames agree within half of it. At 0.3 m one
# carriage step (1/60 inch) moves the line ~1.1 px, so 0.15 px is ~0.06 mm of sheet offset; the
# median over ~300 rows of two frames' extraction noise is ~0.02 px, well below the half.
DEFAULT_TOLERANCE_PX = 0.15
MIN_ROWS = 20   # rows with a line in both frames needed to compare them


def line_profile(image: AnyArray) -> AnyArray:
    """The laser line's sub-pixel column in each image row (NaN where the extractor found none)."""
    from lsu_extract.extractor import extract_laser_line

    result = extract_laser_line(image)
    return profile_from_line(result.u, result.v, image.shape[0])


def profile_from_line(u: AnyArray, v: AnyArray, height: int) -> AnyArray:
    """The same per-row profile from a LaserLine's samples (the laser_extractor's output for a published image)."""
    profile = np.full(int(height), np.nan)
    rows = np.rint(np.asarray(v, dtype=np.float64)).astype(np.int64)
    ok = (rows >= 0) & (rows < int(height))
    profile[rows[ok]] = np.asarray(u, dtype=np.float64)[ok]
    return profile


def line_shift_px(before: AnyArray, after: AnyArray, min_rows: int = MIN_ROWS) -> float:
    """Median column shift of the line from ``before`` to ``after`` over the rows both show; NaN if too few."""
    both = np.isfinite(before) & np.isfinite(after)
    if int(both.sum()) < min_rows:
        return float("nan")
    return float(np.median(after[both] - before[both]))


@dataclass
class SettleTrace:
    """What the adaptive settle saw: the line's shift before each capture and why it stopped."""

    shifts_px: list[float] = field(default_factory=list)   # one per published capture, vs the frame before it
    captures: int = 0                                      # published captures (the last one is the snap)
    reason: str = ""                                       # "still", "fixed settle passed", "limit"

    def as_json(self) -> dict:
        return {"captures": self.captures, "reason": self.reason,
                "shifts_px": [None if not np.isfinite(s) else round(s, 3) for s in self.shifts_px]}


def settle_from_images(probe: Callable[[], AnyArray], capture: Callable[[], tuple[Any, AnyArray]],
                       fixed_passed: Callable[[], bool], tolerance_px: float = DEFAULT_TOLERANCE_PX,
                       max_captures: int = 8, profile: Callable[[AnyArray], AnyArray] = line_profile,
                       before_capture: Callable[[], None] | None = None) -> tuple[Any, SettleTrace]:
    """Run the adaptive settle; returns (the snap's capture, what was seen).

    ``probe()`` -> the first frame after the stop (not the snap); ``capture()`` -> (its response, its
    frame); a frame is what ``profile`` turns into the line's column per row; ``fixed_passed()`` -> whether the fixed settle since the stop is over (checked before each
    capture); ``before_capture()`` runs before each published capture (the coordinator awaits the previous
    snap's acknowledgement there). A frame without enough line rows to compare (laser hidden) does not
    count as still.
    """
    if not tolerance_px > 0:
        raise ValueError(f"tolerance_px must be > 0 (got {tolerance_px})")
    trace = SettleTrace()
    if fixed_passed():  # the stop is already long enough ago (a late reply, a loaded host): no probe
        if before_capture is not None:
            before_capture()
        first, _image = capture()
        trace.captures, trace.reason = 1, "fixed settle passed"
        return first, trace
    previous = profile(probe())
    response: Any = None
    for _ in range(max(1, int(max_captures))):
        late = fixed_passed()
        if before_capture is not None:
            before_capture()
        response, image = capture()
        trace.captures += 1
        current = profile(image)
        shift = line_shift_px(previous, current)
        trace.shifts_px.append(shift)
        if np.isfinite(shift) and abs(shift) <= tolerance_px / 2.0:
            trace.reason = "still"
            return response, trace
        if late:
            trace.reason = "fixed settle passed"
            return response, trace
        previous = current
    trace.reason = "limit"
    return response, trace


def rendered_settle(render: Callable[[float, int], Any], first_frame_s: float, frame_period_s: float,
                    fixed_settle_s: float, seed: int = 0,
                    tolerance_px: float = DEFAULT_TOLERANCE_PX) -> tuple[Any, float, int, SettleTrace]:
    """The adaptive settle on frames a renderer makes (no ROS): a camera frame every ``frame_period_s`` from
    ``first_frame_s`` after the stop, ``render(t, seed)`` -> a frame with ``.left`` exposed from ``t``.

    Returns (the snap's frame, its exposure start after the stop, frames rendered with the probe, trace);
    the simulated scans of lsu_accuracy and the settle's tests and benchmark take the snap this way.
    """
    frames: list[tuple[float, Any]] = []

    def grab() -> Any:
        t = first_frame_s + len(frames) * frame_period_s
        frames.append((t, render(t, seed + len(frames))))
        return frames[-1][1]

    def capture() -> tuple[int, AnyArray]:
        frame = grab()
        return len(frames) - 1, frame.left

    snap, trace = settle_from_images(lambda: grab().left, capture,
                                     lambda: first_frame_s + len(frames) * frame_period_s >= fixed_settle_s,
                                     tolerance_px=tolerance_px)
    t_snap, frame = frames[int(snap)]
    return frame, t_snap, len(frames), trace

"""Sweep scan planning (no rclpy): the goal's mode checked, the frames a sweep should give, drops counted.

A sweep runs the carriage from ``start`` to ``end`` at a constant rate while the cameras free-run at
``frame_rate_hz`` (``/lsu/stereo/stream``); every pair is one sweep frame for the extractor and
matcher, keyed on its stamp. A dropped frame is a slot of the stream without a published pair (the
camera could not keep up) or a published pair the matcher gave no points for (`count_frames`),
counted in scan.json.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

from .scan_plan import ScanGoalError

MODES = ("stopsnap", "sweep")
# above this the carriage oversteps (the driver's step counter drifts from the true position)
MAX_SWEEP_RATE_STEPS_S = 180.0
MIN_SWEEP_RATE_STEPS_S = 20.0    # the GP32's slowest step rate
MAX_FRAME_RATE_HZ = 60.0


def scan_mode(mode: str) -> str:
    """The goal's mode, "" meaning the default "stopsnap"; ScanGoalError naming the choices otherwise."""
    mode = (mode or "stopsnap").strip().lower()
    if mode not in MODES:
        raise ScanGoalError(f"mode must be one of {', '.join(MODES)} (got {mode!r})")
    return mode


@dataclass(frozen=True)
class SweepPlan:
    """A checked sweep: from ``start`` to ``end`` at ``rate_steps_s`` with frames every 1 / ``frame_rate_hz``."""

    start: int
    end: int
    rate_steps_s: float
    frame_rate_hz: float

    @property
    def direction(self) -> str:
        """"forward" (towards higher positions) or "reverse"."""
        return "forward" if self.end >= self.start else "reverse"

    @property
    def duration_s(self) -> float:
        """Carriage time of the sweep [s]."""
        return abs(self.end - self.start) / self.rate_steps_s

    def position_at(self, elapsed_s: float) -> int:
        """The carriage [steps] ``elapsed_s`` after the motion's start at the commanded rate (for records and
        feedback; points are placed by the driver's stamped positions), held at the end once reached."""
        travelled = min(abs(self.end - self.start), max(0.0, elapsed_s) * self.rate_steps_s)
        return int(round(self.start + (1 if self.end >= self.start else -1) * travelled))

    @property
    def frames_expected(self) -> int:
        """Frame slots from the start of the motion to its end, both included."""
        return int(math.floor(self.duration_s * self.frame_rate_hz + 1e-9)) + 1

    def record(self, frames: FrameCount | None) -> dict[str, object]:
        """The scan.json ``sweep`` entry (``frames``: None when the stream never started)."""
        out: dict[str, object] = {
            "start_steps": self.start, "end_steps": self.end, "direction": self.direction,
            "rate_steps_s": self.rate_steps_s,
            "frame_rate_hz": self.frame_rate_hz, "duration_s": round(self.duration_s, 4),
            "frames_expected": self.frames_expected}
        frames = frames or FrameCount(self.frames_expected, 0, 0, 0)
        dropped = frames.dropped
        out.update(frames_captured=frames.published, frames_processed=frames.processed,
                   frames_not_published=frames.not_published, frames_not_processed=frames.not_processed,
                   frames_dropped=dropped, frames_dropped_pct=round(100.0 * dropped / max(1, frames.slots), 3))
        return out


@dataclass(frozen=True)
class FrameCount:
    """A sweep's frames counted from stamps: slots of the stream, pairs published, pairs the matcher processed."""

    slots: int
    published: int
    processed: int
    camera_dropped: int = 0   # what the camera itself reported (the stream's reply), for comparison

    @property
    def not_published(self) -> int:
        return max(0, self.slots - self.published)

    @property
    def not_processed(self) -> int:
        return max(0, self.published - self.processed)

    @property
    def dropped(self) -> int:
        """Slots the camera did not publish + frames the matcher did not process."""
        return self.not_published + self.not_processed


def count_frames(first_ns: int, period_ns: int, slots: int, published: Iterable[int],
                 processed: Iterable[int], camera_dropped: int = 0) -> FrameCount:
    """Count a sweep's frames from stamps [ns]: slot k is stamped ``first_ns + k * period_ns``.

    ``published``: stamps of the pairs the stream published (its exposures); ``processed``: stamps the
    matcher published points for. A stamp off the slot grid by more than a quarter period, or outside
    the ``slots`` slots, is not a frame of this stream and is not counted.
    """
    if period_ns <= 0 or slots < 0:
        raise ValueError(f"frame period {period_ns} ns and slot count {slots}: need a period > 0, slots >= 0")

    def slot_of(stamps_ns: Iterable[int]) -> set[int]:
        out = set()
        for ns in stamps_ns:
            k = round((int(ns) - first_ns) / period_ns)
            if 0 <= k < slots and abs(int(ns) - (first_ns + k * period_ns)) * 4 <= period_ns:
                out.add(k)
        return out

    pub = slot_of(published)
    done = slot_of(processed) & pub
    return FrameCount(slots, len(pub), len(done), int(camera_dropped))


def oriented(plan: SweepPlan, here_steps: float) -> SweepPlan:
    """The sweep over the same range that wastes no move from ``here_steps`` (where the carriage stands).

    A sweep gives the same frames in either direction, so it starts at whichever end of the range
    the carriage is nearer: where it stands when that is an end (e.g. after the previous scan, which
    ended at one), else after a move to the nearer end; on a tie the goal's own start.
    """
    to_start, to_end = abs(here_steps - plan.start), abs(here_steps - plan.end)
    if to_end < to_start:
        return SweepPlan(plan.end, plan.start, plan.rate_steps_s, plan.frame_rate_hz)
    return plan


def plan_sweep(start: int, end: int, track_steps: int, rate_steps_s: float, frame_rate_hz: float) -> SweepPlan:
    """Check a sweep goal against the track and the carriage's limits; ScanGoalError says what to change."""
    if track_steps <= 0:
        raise ScanGoalError("the track length is unknown: home the carriage (carriage/home) before scanning")
    for name, value in (("start_steps", start), ("end_steps", end)):
        if not 0 <= value <= track_steps:
            raise ScanGoalError(f"{name} {value} is outside the track 0..{track_steps}")
    if start == end:
        raise ScanGoalError("a sweep needs end_steps different from start_steps")
    if not (math.isfinite(rate_steps_s) and MIN_SWEEP_RATE_STEPS_S <= rate_steps_s <= MAX_SWEEP_RATE_STEPS_S):
        raise ScanGoalError(f"sweep_rate_steps_s must be within {MIN_SWEEP_RATE_STEPS_S:g}..{MAX_SWEEP_RATE_STEPS_S:g} "
                            f"steps/s (got "
                            f"{rate_steps_s:g}): above {MAX_SWEEP_RATE_STEPS_S:g} the carriage oversteps and "
                            "the positions of the frames are no longer known")
    if not (math.isfinite(frame_rate_hz) and 1.0 <= frame_rate_hz <= MAX_FRAME_RATE_HZ):
        raise ScanGoalError(f"frame_rate_hz must be within 1..{MAX_FRAME_RATE_HZ:g} (got {frame_rate_hz:g})")
    return SweepPlan(int(start), int(end), float(rate_steps_s), float(frame_rate_hz))

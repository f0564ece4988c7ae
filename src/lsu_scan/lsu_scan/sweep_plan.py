"""Sweep scan planning (no rclpy): the goal's mode checked, the frames a sweep should give, drops counted.

A sweep runs the carriage from ``start`` to ``end`` at a constant rate while the cameras take frame
pairs at ``frame_rate_hz``; every pair is one snap for the extractor and matcher. A frame slot that
passes without a capture (the camera or the pipeline could not keep up) is a dropped frame, counted
in scan.json.
"""

from __future__ import annotations

import math
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
    def duration_s(self) -> float:
        """Carriage time of the sweep [s]."""
        return abs(self.end - self.start) / self.rate_steps_s

    @property
    def frames_expected(self) -> int:
        """Frame slots from the start of the motion to its end, both included."""
        return int(math.floor(self.duration_s * self.frame_rate_hz + 1e-9)) + 1

    def frames_dropped(self, captured: int) -> int:
        """Slots without a frame."""
        return max(0, self.frames_expected - int(captured))

    def record(self, captured: int) -> dict[str, object]:
        """The scan.json ``sweep`` entry."""
        dropped = self.frames_dropped(captured)
        return {"start_steps": self.start, "end_steps": self.end, "rate_steps_s": self.rate_steps_s,
                "frame_rate_hz": self.frame_rate_hz, "duration_s": round(self.duration_s, 4),
                "frames_expected": self.frames_expected, "frames_captured": int(captured),
                "frames_dropped": dropped,
                "frames_dropped_pct": round(100.0 * dropped / max(1, self.frames_expected), 3)}


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

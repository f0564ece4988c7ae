"""Stop-snap scan planning and records (no rclpy): positions, timing bounds, output folders, scan.json."""

from __future__ import annotations

import datetime as _dt
import json
import platform
from dataclasses import asdict, dataclass, field
from pathlib import Path

from lsu_cameras.calib_io import calibration_checksum as checksum


class ScanGoalError(ValueError):
    """A scan goal that cannot run; the message says what to change."""


@dataclass(frozen=True)
class ScanPlan:
    """Validated goal: the carriage positions and the timing parameters."""

    positions: list[int]
    settle_s: float
    texture: bool


def plan_positions(start: int, end: int, step: int, track_steps: int, settle_s: float = 0.1,
                   texture: bool = True) -> ScanPlan:
    """Positions ``start, start+step, ...`` up to ``end`` (inclusive when on the grid), checked against the track.

    ``start > end`` scans backwards. Raises ScanGoalError with what to change.
    """
    if track_steps <= 0:
        raise ScanGoalError("the track length is unknown: home the carriage (carriage/home) before scanning")
    if step <= 0:
        raise ScanGoalError(f"step_steps must be > 0 (got {step})")
    for name, value in (("start_steps", start), ("end_steps", end)):
        if not 0 <= value <= track_steps:
            raise ScanGoalError(f"{name} {value} is outside the track 0..{track_steps}")
    if not 0.0 <= settle_s <= 5.0:
        raise ScanGoalError(f"settle_s must be within 0..5 s (got {settle_s:g})")
    direction = 1 if end >= start else -1
    positions = list(range(start, end + direction, direction * step))
    return ScanPlan(positions, float(settle_s), bool(texture))


def mechanical_lower_bound_s(plan: ScanPlan, start_position: int, rate_steps_per_s: float, exposure_s: float) -> float:
    """The time the hardware alone needs: every move at the step rate, every settle and exposure.

    The reference for `scan_wall_over_mechanical` (a scan cannot be faster than this).
    """
    moves = 0
    here = start_position
    for position in plan.positions:
        moves += abs(position - here)
        here = position
    snaps = len(plan.positions)
    return moves / rate_steps_per_s + snaps * (plan.settle_s + exposure_s) + (exposure_s if plan.texture else 0.0)


def new_scan_id(now: _dt.datetime | None = None, counter: int = 1) -> str:
    """``20261123-074501-0001``: sortable, unique per node run."""
    now = now or _dt.datetime.now()
    return f"{now:%Y%m%d-%H%M%S}-{counter:04d}"


def calibration_checksum(directory: Path | None) -> str:
    """The calibration's id (`lsu_cameras.calib_io.calibration_checksum`), or 'none'."""
    return (checksum(directory) if directory is not None else "") or "none"


def software_versions() -> dict[str, str]:
    """Versions recorded in scan.json."""
    import importlib.metadata as md

    out = {"python": platform.python_version()}
    for dist in ("lsu_common", "lsu_driver", "lsu_cameras", "lsu_extract", "lsu_reconstruct", "lsu_faces", "lsu_bags", "lsu_scan",
                 "ros-jazzy-rclpy", "numpy", "opencv-python-headless", "open3d-cpu", "rosbags"):
        try:
            out[dist] = md.version(dist)
        except md.PackageNotFoundError:
            pass
    return out


@dataclass
class ScanRecord:
    """What scan.json holds: enough to reproduce and audit a scan."""

    scan_id: str
    started: str
    goal: dict[str, object]
    parameters: dict[str, object]
    calibration: str
    versions: dict[str, str] = field(default_factory=software_versions)
    snaps_expected: int = 0
    snaps_captured: int = 0
    snaps_acknowledged: int = 0
    points: int = 0
    partial: bool = False
    status: str = ""
    timings_s: dict[str, float] = field(default_factory=dict)
    snaps: list[dict[str, object]] = field(default_factory=list)
    # each time the laser guard switched the laser off mid-scan: wall time and why (a late answer)
    laser_pauses: list[dict[str, object]] = field(default_factory=list)
    files: list[str] = field(default_factory=list)
    # a sweep scan: its rate, frame rate and the frames expected, captured and dropped (empty: stop-snap)
    sweep: dict[str, object] = field(default_factory=dict)
    # a sweep scan: the subject's motion as stereo_matcher measured it (its scan/motion record; docs/MOTION.md)
    motion: dict[str, object] = field(default_factory=dict)
    # the scan this one repeats: its subject moved beyond correction ("hold still, scanning again")
    rescan_of: str = ""

    def write(self, folder: Path) -> Path:
        """Write ``folder/scan.json`` atomically (a partial scan is always described on disk)."""
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / "scan.json"
        tmp = path.with_suffix(".json.tmp")
        try:
            tmp.write_text(json.dumps(asdict(self), indent=2) + "\n")
            tmp.replace(path)
        except BaseException:
            tmp.unlink(missing_ok=True)  # a full disk: no half-written record left behind
            raise
        return path



@dataclass
class SnapRecord:
    """One captured snap in scan.json: where, when, and where its time went (wall seconds per phase).

    ``points``, ``ack_s`` and ``snap_s`` are known once stereo_matcher acknowledged the snap; a snap
    without them was captured but never processed (a partial scan).
    """

    index: int
    position_steps: int
    stamp: str                      # image stamp "sec.nanosec" (the key of its images in the bag)
    skew_s: float                   # left/right capture skew the camera node measured
    move_s: float
    settle_s: float
    stop_to_reply_s: float | None  # driver's stop to the move's reply; None when the driver gave no stamp
    ack_wait_s: float               # waiting for the previous snap's points before this capture
    capture_s: float
    points: int | None = None
    ack_s: float | None = None   # capture to the arrival of its points
    snap_s: float | None = None  # start of the snap to the arrival of its points
    settle: dict[str, object] | None = None  # adaptive settle only: captures, reason, line shifts (settle.py)

    @property
    def acknowledged(self) -> bool:
        return self.points is not None

    def as_json(self) -> dict[str, object]:
        """The scan.json entry: the acknowledgement fields only once they are known."""
        out = asdict(self)
        for name in ("points", "ack_s", "snap_s", "settle"):
            if out[name] is None:
                del out[name]
        return out

"""Calibration from the page: board pairs with coverage feedback, the stereo solve, the laser sheet.

The page drives what `lsu calibrate --live` and `lsu calibrate --laser` do, through the same library
code (`lsu_cameras.live.CoverageTracker`, `calibrate_stereo`, `lsu_reconstruct.laser_cli.calibrate_laser`);
pairs come from the camera node's ``stereo/capture`` service (the capture itself is `WebGraph`'s).
The views kept so far are the page's calibration session (one per server, reset from the page); a
result is written to a new folder beside the scans (``calibration-<time>``), never over the
calibration the graph runs with: the user points ``calibration_dir`` at it after looking at it.
"""

from __future__ import annotations

import datetime as _dt
import shutil
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lsu_common.arrays import AnyArray


@dataclass
class CalibrationSession:
    board_text: str = "9x6"
    square_mm: float = 25.0
    min_views: int = 8
    _lock: threading.Lock = field(default_factory=threading.Lock)
    tracker: Any = None
    captures: int = 0
    last: dict[str, Any] = field(default_factory=dict)

    def reset(self, board_text: str, square_mm: float, min_views: int) -> None:
        from lsu_cameras.calibration import BoardSpec
        from lsu_cameras.live import CoverageTracker

        board = BoardSpec.parse(board_text, square_mm)  # CalibrationError says what is wrong with the text
        with self._lock:
            self.board_text, self.square_mm, self.min_views = board_text, square_mm, min_views
            self.tracker = CoverageTracker(board, min_views=max(min_views, 1))
            self.captures = 0
            self.last = {}

    def consider(self, left: AnyArray, right: AnyArray) -> dict[str, Any]:
        """Judge one captured pair; the verdict and the coverage so far."""
        with self._lock:
            if self.tracker is None:
                raise ValueError("start a calibration session first (board size and square)")
            verdict = self.tracker.consider(left, right)
            self.captures += 1
            self.last = {"accepted": verdict.accepted, "reason": verdict.reason}
            return self.status()

    def status(self) -> dict[str, Any]:
        if self.tracker is None:
            return {"session": False}
        return {"session": True, "board": self.board_text, "square_mm": self.square_mm, "min_views": self.min_views,
                "views": len(self.tracker.views), "captures": self.captures, "last": self.last,
                "coverage": [{"name": c.name, "progress": round(c.progress, 3)} for c in self.tracker.coverage()],
                "good_enough": self.tracker.is_good_enough()}

    def solve(self, out_root: Path) -> dict[str, Any]:
        """Calibrate from the kept views; write left/right/stereo.yaml into a new folder under ``out_root``."""
        from lsu_cameras.calib_io import write_calibration_dir
        from lsu_cameras.calibration import calibrate_stereo

        with self._lock:
            if self.tracker is None or not self.tracker.views:
                raise ValueError("no board views kept yet: capture pairs with the board in view first")
            result = calibrate_stereo(self.tracker.pairs(), self.tracker.board, min_views=self.min_views)
            folder = out_root / f"calibration-{_dt.datetime.now():%Y%m%d-%H%M%S}"
            write_calibration_dir(folder, result.left, result.right, result.stereo,
                                  header=f"lsu web calibration: {len(self.tracker.views)} views, board "
                                         f"{self.board_text} {self.square_mm:g} mm")
        return {"folder": str(folder), "left_rms_px": result.left_rms_px, "right_rms_px": result.right_rms_px,
                "stereo_rms_px": result.stereo.rms_px, "baseline_mm": result.stereo.baseline_m * 1000,
                "views": [{"name": v.name, "left_px": v.left_error_px, "right_px": v.right_error_px, "used": v.used,
                           "reason": v.reason} for v in result.views],
                "summary": result.summary()}


def laser_calibration(scan_folders: list[Path], calib_dir: Path, out_root: Path) -> dict[str, Any]:
    """Fit the laser sheet to scans of a flat board; laser.yaml and a copy of the stereo calibration it
    belongs to go into a new folder under ``out_root`` (a complete calibration_dir)."""
    from lsu_reconstruct.laser_cli import calibrate_laser
    from lsu_reconstruct.laser_sheet import write_laser_yaml

    sheet, report = calibrate_laser([str(p) for p in scan_folders], calib_dir)
    folder = out_root / f"calibration-laser-{_dt.datetime.now():%Y%m%d-%H%M%S}"
    folder.mkdir(parents=True)
    for name in ("left.yaml", "right.yaml", "stereo.yaml"):
        if (calib_dir / name).is_file():
            shutil.copy2(calib_dir / name, folder / name)
    write_laser_yaml(sheet, folder / "laser.yaml")
    return {"folder": str(folder), "residual_mm": sheet.residual_mm, "points": sheet.points,
            "rejected": sheet.rejected, "positions": list(sheet.positions),
            "scans": [{"name": r.name, "points": r.points, "rms_mm": r.rms_mm, "max_mm": r.max_mm,
                       "flatness_rms_mm": r.flatness_rms_mm} for r in report]}

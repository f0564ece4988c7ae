"""The scan_coordinator's parameters: their table, the on-set check that refuses what a scan could not use,
and the post-set apply that makes every accepted value take effect at its next use."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rcl_interfaces.msg import SetParametersResult
from rclpy.parameter import Parameter

from lsu_common.node import LsuNode

from .settle import DEFAULT_TOLERANCE_PX, SETTLE_MODES

# name -> (default, description, (low, high) or None). Every one is read when it is used, so a
# `param set` takes effect at the next call, deadline or scan; values outside the range are refused.
PARAMETERS: dict[str, tuple[Any, str, tuple[float, float] | None]] = {
    "output_dir": ("", "parent folder of scans/<id>/; empty = scans/ in the directory the node was started from (applies from the next scan)", None),
    "capture_timeout_s": (1.0, "a stereo/capture call longer than this aborts (+ 0.3 s for the reply; below the "
                               "laser watchdog) [s]", (0.05, 30.0)),
    "ack_timeout_s": (5.0, "a snap the matcher does not acknowledge within this (from its capture) aborts the "
                           "scan [s]", (0.1, 600.0)),
    "laser_pause_s": (0.2, "a move, capture or snap acknowledgement this late switches the laser off until the "
                           "scan goes on [s] (applies from the next deadline)", (0.02, 1.5)),
    "move_timeout_s": (0.0, "carriage/move_to timeout [s]; 0 = the driver's own", (0.0, 600.0)),
    "cloud_timeout_s": (30.0, "wait for the matcher's scan/cloud after the scan (a sweep's comes once the subject's "
                              "motion is measured: seconds of CPU) [s]", (0.0, 600.0)),
    "exposure_s": (0.033, "camera exposure: the mechanical lower bound in scan.json, when a capture is due [s]",
                   (0.0, 1.0)),
    "calibration_dir": ("", "calibration folder used (its checksum goes in scan.json; applies from the next scan)",
                        None),
    "settle": ("fixed", "after each stop: 'fixed' waits the goal's settle_s; 'adaptive' captures as soon as the "
                        "laser line stopped moving (two frames agree), at the latest once settle_s has passed "
                        "(lsu_scan.settle)", None),
    "motion_rescans": (1, "a sweep whose subject moved beyond correction (stereo_matcher's scan/motion says so) is "
                          "scanned again this many times within the goal, saying 'hold still, scanning again'; "
                          "0 = delivered flagged (applies from the next scan's end)", (0, 5)),
    "motion_timeout_s": (5.0, "after a sweep's cloud, wait this long for stereo_matcher's scan/motion record [s]",
                         (0.0, 600.0)),
    "settle_tolerance_px": (DEFAULT_TOLERANCE_PX, "adaptive settle: the line counts as still when it moved less "
                                                  "than this between two frames [px]", (0.01, 5.0)),
}


class ScanParameters(LsuNode):
    """`PARAMETERS`' check and apply for `ScanCoordinatorNode` (declared in its ``__init__``)."""

    def _check_parameters(self, changed: list[Parameter]) -> SetParametersResult:
        """Refuse values the scan could not use, with a sentence saying why (ranges are checked by rclpy)."""
        for param in changed:
            if param.name == "settle" and param.value not in SETTLE_MODES:
                return SetParametersResult(successful=False, reason=f"settle '{param.value}' is not one of "
                                                                    f"{', '.join(SETTLE_MODES)}")
            if param.name in ("output_dir", "calibration_dir") and param.value:
                path = Path(str(param.value))
                if path.exists() and not path.is_dir():
                    return SetParametersResult(successful=False,
                                               reason=f"{param.name} {path} exists and is not a folder")
        return SetParametersResult(successful=True)

    def _apply_parameters(self, changed: list[Parameter]) -> None:
        """Every accepted value takes effect now: the scan reads these attributes at each use."""
        for param in changed:
            if param.name not in PARAMETERS:
                continue
            value = param.value
            if param.name == "output_dir":
                self.output_dir = Path(value) if value else Path.cwd() / "scans"
            elif param.name in ("calibration_dir", "settle"):
                setattr(self, param.name, str(value))
            elif param.name == "motion_rescans":
                self.motion_rescans = int(value)
            else:
                setattr(self, param.name, float(value))
                if param.name == "laser_pause_s":
                    self.guard.pause_s = float(value)

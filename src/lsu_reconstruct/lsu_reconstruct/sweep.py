"""Sweep scanning: every frame of a constant-rate carriage sweep to 3D points (numpy, no rclpy).

During a sweep the sheet moves while each camera's shutter is open, and the two cameras need not
expose at the same time (the thesis' unit captured up to 50 ms apart, ch. 3). The laser line a
camera records is the sheet's sub-exposures averaged; for a constant rate its centre is the sheet
at *mid-exposure*. So every line is placed in time by its camera's own mid-exposure, and the
carriage position there is interpolated from the driver's stamped carriage positions
(`CarriageTrack`, from ``/lsu/driver/carriage``).

Per frame (`reconstruct_sweep_frame`):

- each camera's line is intersected with the calibrated laser sheet (`LaserSheet`) at that camera's
  mid-exposure position: laser triangulation with one camera, no matching needed;
- where the two exposures overlap (by at least ``min_overlap`` of the exposure), the pair is also
  matched and triangulated as in stop-snap (`reconstruct_snap`) and every stereo point is checked
  against the sheet (its distance to the sheet at the mean of the two mid-exposure positions): within
  ``consistency_mm`` the stereo point is kept,
  beyond it the point is rejected (a mismatch, or a carriage position / sheet that is off) and
  counted in the stats; the right camera's sheet points are then not added (they trace the same
  surface line as the left's);
- where the exposures do not overlap, both cameras' sheet points are kept: two lines per frame.

Sheet points whose ray meets the sheet at a grazing angle (below ``min_sheet_angle_deg``: the laser
near that camera's optical centre) are dropped: their depth error grows as 1 / tan(angle).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from .laser_sheet import LaserSheet
from .matching import LineArrays, MatchParams, _links, smooth_line
from .pipeline import SnapPoints, reconstruct_snap
from .stereo import StereoModel

FloatArray = NDArray[np.float64]

__all__ = ["SweepError", "CarriageTrack", "SweepParams", "SweepFrame", "exposure_mid_s", "sheet_points",
           "reconstruct_sweep_frame"]


class SweepError(ValueError):
    """The sweep data cannot be used as given; the message says what is wrong."""


def exposure_mid_s(start_s: float, exposure_s: float) -> float:
    """Mid-exposure time [s] of an exposure starting at ``start_s``: the time the line's centre shows."""
    if not (np.isfinite(start_s) and np.isfinite(exposure_s)) or exposure_s < 0:
        raise SweepError(f"exposure start {start_s} s / duration {exposure_s} s: need finite values, duration >= 0")
    return float(start_s) + 0.5 * float(exposure_s)


@dataclass(frozen=True)
class CarriageTrack:
    """Stamped carriage positions (device-clock stamps mapped to host time): where the carriage was when.

    ``moving``: per sample, the carriage was moving (``CarriagePosition.moving``: a `!POS`), else it
    had stopped there (a `!DONE`); default: every sample moving except the last (a complete motion).
    ``position_at`` interpolates linearly between samples. After a stopped last sample the carriage
    stays there; otherwise, and before the first sample, the end segment's rate is continued for
    ``max_extrapolate_s`` (the carriage runs at a constant rate between `!POS` events), further away
    the position is unknown (NaN).
    """

    stamps_s: FloatArray
    positions_steps: FloatArray
    moving: NDArray[np.bool_] | None = None
    max_extrapolate_s: float = 0.1

    def __post_init__(self) -> None:
        t = np.asarray(self.stamps_s, dtype=np.float64).reshape(-1)
        p = np.asarray(self.positions_steps, dtype=np.float64).reshape(-1)
        if t.size != p.size or t.size < 2:
            raise SweepError(f"carriage track needs at least 2 stamped positions of equal count "
                             f"(got {t.size} stamps, {p.size} positions): was the driver's carriage topic recorded?")
        if not (np.isfinite(t).all() and np.isfinite(p).all()):
            raise SweepError("carriage track holds non-finite stamps or positions")
        m = np.ones(t.size, bool) if self.moving is None else np.asarray(self.moving, bool).reshape(-1)
        if self.moving is None:
            m[-1] = False
        if m.size != t.size:
            raise SweepError(f"carriage track has {t.size} stamps but {m.size} moving flags")
        order = np.argsort(t, kind="stable")
        t, p, m = t[order], p[order], m[order]
        keep = np.r_[True, np.diff(t) > 0]  # a repeated stamp (a stop and a status at one instant) adds nothing
        object.__setattr__(self, "stamps_s", t[keep])
        object.__setattr__(self, "positions_steps", p[keep])
        object.__setattr__(self, "moving", m[keep])
        if self.stamps_s.size < 2:
            raise SweepError("carriage track has fewer than 2 distinct stamps")

    def position_at(self, t_s: float | FloatArray) -> FloatArray:
        """Carriage position [steps] at times ``t_s`` (NaN where unknown: see the class doc)."""
        t = np.asarray(t_s, dtype=np.float64)
        ts, ps = self.stamps_s, self.positions_steps
        out = np.interp(t, ts, ps)
        before, after = t < ts[0], t > ts[-1]
        rate0 = (ps[1] - ps[0]) / (ts[1] - ts[0])
        out = np.where(before, ps[0] + rate0 * (t - ts[0]), out)
        far = t < ts[0] - self.max_extrapolate_s
        if bool(self.moving[-1]):  # type: ignore[index]
            rate1 = (ps[-1] - ps[-2]) / (ts[-1] - ts[-2])
            out = np.where(after, ps[-1] + rate1 * (t - ts[-1]), out)
            far |= t > ts[-1] + self.max_extrapolate_s
        return np.where(far, np.nan, out)


@dataclass(frozen=True)
class SweepParams:
    """Sweep reconstruction settings."""

    match: MatchParams = MatchParams()
    consistency_mm: float = 0.5       # a stereo point farther than this from the sheet is rejected
    min_overlap: float = 0.5          # share of the exposure both cameras must have in common for stereo
    min_sheet_angle_deg: float = 10.0  # a ray meeting the sheet flatter than this gives no sheet point
    min_run_rows: int = 9             # sheet points: shorter continuous pieces of line are dropped
    trim_run_rows: int = 2            # sheet points: rows dropped at each end of a piece of line

    def __post_init__(self) -> None:
        if not self.consistency_mm > 0:
            raise SweepError(f"consistency_mm must be > 0, got {self.consistency_mm}")
        if not 0.0 < self.min_overlap <= 1.0:
            raise SweepError(f"min_overlap must be in (0, 1], got {self.min_overlap}")
        if not 0.0 <= self.min_sheet_angle_deg < 90.0:
            raise SweepError(f"min_sheet_angle_deg must be in [0, 90), got {self.min_sheet_angle_deg}")


@dataclass
class SweepFrame:
    """One frame pair of a sweep: both laser lines and each camera's exposure start [s, host time]."""

    index: int
    left: LineArrays
    right: LineArrays
    left_start_s: float
    right_start_s: float
    exposure_s: float

    @property
    def overlap(self) -> float:
        """Share of the exposure the two cameras have in common (1 = synchronised, 0 = disjoint)."""
        if self.exposure_s <= 0:
            return 1.0 if self.left_start_s == self.right_start_s else 0.0
        return float(max(0.0, 1.0 - abs(self.right_start_s - self.left_start_s) / self.exposure_s))


def _rays(model: StereoModel, side: str, u: FloatArray, v: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(origin, unit directions) in the left frame of raw pixels of one camera."""
    if side == "left":
        x = model.undistort_left(u, v)
        d = np.hstack([x, np.ones((len(x), 1))]) @ model.K1_inv.T
        origin = np.zeros(3)
    else:
        x = model.undistort_right(u, v)
        d = (np.hstack([x, np.ones((len(x), 1))]) @ model.K2_inv.T) @ model.R  # R^T d, row-wise
        origin = model.right_centre
    return origin, d / np.linalg.norm(d, axis=1, keepdims=True)


def sheet_points(model: StereoModel, sheet: LaserSheet, side: str, line: LineArrays, position_steps: float,
                 params: SweepParams = SweepParams()) -> tuple[FloatArray, FloatArray, FloatArray]:
    """One camera's line on the sheet at ``position_steps``: (xyz (N,3), u, v raw pixels of that camera).

    The line is smoothed along its rows as the stereo matcher does (same window); points behind the
    camera, outside the depth range or at a grazing angle to the sheet are left out.
    """
    if side not in ("left", "right"):
        raise SweepError(f"side must be 'left' or 'right', got {side!r}")
    ok = line.valid(params.match.min_quality)
    u, v = line.u[ok], line.v[ok]
    order = np.argsort(v, kind="stable")
    u, v = u[order], v[order]
    if len(u) == 0 or not np.isfinite(position_steps):
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0)
    linked = _links(u, v, params.match)[0]
    if params.match.smooth_window_rows:
        u = smooth_line(u, v, params.match.smooth_window_rows, linked)
    # One camera has no second view to reject a stray detection (a glint, the blurred end of the line
    # at a silhouette): keep only continuous runs of at least ``min_run_rows``, without their end rows.
    starts = np.r_[0, np.nonzero(~linked)[0] + 1]
    stops = np.r_[starts[1:], len(u)]
    solid = np.zeros(len(u), bool)
    trim = params.trim_run_rows
    for a, b in zip(starts, stops):
        if b - a >= params.min_run_rows:
            solid[a + trim:b - trim] = True
    u, v = u[solid], v[solid]
    origin, dirs = _rays(model, side, u, v)
    X = sheet.intersect_rays(origin, dirs, float(position_steps))
    n = np.asarray(sheet.normal, float)
    sin_angle = np.abs(dirs @ n)
    depth = X[:, 2]
    forward = ((X - origin) * dirs).sum(axis=1) > 0
    keep = (np.isfinite(X).all(axis=1) & forward & (depth >= params.match.depth_min_m)
            & (depth <= params.match.depth_max_m) & (sin_angle >= np.sin(np.radians(params.min_sheet_angle_deg))))
    return X[keep], u[keep], v[keep]


@dataclass
class SweepFramePoints:
    """Points of one sweep frame and where each came from."""

    points: SnapPoints
    source: NDArray[np.uint8]          # per point: 0 stereo (checked against the sheet), 1 left sheet, 2 right sheet
    positions_steps: tuple[float, float]  # carriage at each camera's mid-exposure
    stats: dict[str, int] = field(default_factory=dict)


SOURCE_STEREO, SOURCE_LEFT_SHEET, SOURCE_RIGHT_SHEET = 0, 1, 2


def reconstruct_sweep_frame(model: StereoModel, sheet: LaserSheet, track: CarriageTrack, frame: SweepFrame,
                            params: SweepParams = SweepParams()) -> SweepFramePoints:
    """Points of one sweep frame pair, each line triangulated at its camera's own mid-exposure (module doc)."""
    p_left = float(track.position_at(exposure_mid_s(frame.left_start_s, frame.exposure_s)))
    p_right = float(track.position_at(exposure_mid_s(frame.right_start_s, frame.exposure_s)))
    stats = {"stereo": 0, "stereo_rejected_inconsistent": 0, "left_sheet": 0, "right_sheet": 0,
             "no_carriage_position": int(not np.isfinite(p_left)) + int(not np.isfinite(p_right))}
    xl, ul, vl = sheet_points(model, sheet, "left", frame.left, p_left, params)
    parts = []
    if frame.overlap >= params.min_overlap and len(frame.left) and len(frame.right):
        snap = reconstruct_snap(model, frame.left, frame.right, params.match, snap=frame.index)
        p_both = 0.5 * (p_left + p_right)  # the overlapping exposures saw the sheet between the two
        if len(snap) and np.isfinite(p_both):
            # the stereo point's distance to the sheet, not to one camera's ray-sheet intersection:
            # along a ray meeting the sheet at a flat angle that distance is the same error magnified
            with np.errstate(invalid="ignore"):
                agree = np.abs(sheet.distance_m(snap.xyz, np.full(len(snap), p_both))) * 1000.0 <= params.consistency_mm
            stats["stereo_rejected_inconsistent"] = int(np.count_nonzero(~agree))
            keep = np.nonzero(agree)[0]
        else:  # no carriage position: nothing to check against; stereo alone is what stop-snap gives
            keep = np.arange(len(snap))
        stats["stereo"] = int(len(keep))
        parts.append((snap.xyz[keep], snap.u[keep], snap.v[keep], SOURCE_STEREO))
    else:
        xr, _ur, _vr = sheet_points(model, sheet, "right", frame.right, p_right, params)
        stats["left_sheet"], stats["right_sheet"] = len(xl), len(xr)
        parts.append((xl, ul, vl, SOURCE_LEFT_SHEET))
        if len(xr):
            # the left pixel of a right-only point: where the left camera would see it (for meshing in
            # left pixel space); it may be hidden from the left camera
            uv = model.project_left(xr)
            parts.append((xr, uv[:, 0], uv[:, 1], SOURCE_RIGHT_SHEET))
    xyz = np.concatenate([p[0] for p in parts]) if parts else np.zeros((0, 3))
    u = np.concatenate([p[1] for p in parts]) if parts else np.zeros(0)
    v = np.concatenate([p[2] for p in parts]) if parts else np.zeros(0)
    source = np.concatenate([np.full(len(p[0]), p[3], np.uint8) for p in parts]) if parts else np.zeros(0, np.uint8)
    points = SnapPoints(xyz=xyz, u=u, v=v, snap=np.full(len(xyz), frame.index, dtype=np.uint32), stats=stats)
    return SweepFramePoints(points, source, (p_left, p_right), stats)

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

Over a sequence of frames (`SweepSequence`, `reconstruct_sweep`) the left line is instead matched
*across frames*, to the right lines exposed just before and just after it. The carriage moves
the sheet by a fraction of a millimetre between those exposures, so on a left pixel's epipolar
plane the surface point the left camera saw lies between the two surface points the right lines
show; along the right epipolar line its image is interpolated linearly in carriage position
between the two crossings (exact for a plane up to perspective over ~2 steps; a face curves by
micrometres over 0.85 mm) and triangulated with the left ray as in stop-snap. This keeps what
stereo has over one camera and the sheet: the point is where both cameras see the same light on
the surface, so the skin's subsurface glow, which shifts the line's centre along the surface away
from the sheet, moves the point along the surface, not off it; and the depth error follows the
122 mm stereo baseline rather than a camera's distance to the sheet (which falls to zero twice a
sweep). Every such point is checked against the sheet at the left line's position; left pixels
whose two crossings jump apart (a depth edge between the exposures) give no point.

Sheet points whose ray meets the sheet at a grazing angle (below ``min_sheet_angle_deg``: the laser
near that camera's optical centre) are dropped: their depth error grows as 1 / tan(angle).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from .laser_sheet import LaserSheet
from .matching import LineArrays, MatchParams, _links, match_line, smooth_line
from .pipeline import SnapPoints, reconstruct_snap
from .stereo import StereoModel
from .triangulate import accept_points, triangulate

FloatArray = NDArray[np.float64]

__all__ = ["SweepError", "CarriageTrack", "SweepParams", "SweepFrame", "SweepFramePoints", "SweepSequence",
           "exposure_mid_s", "sheet_points", "reconstruct_sweep_frame", "reconstruct_sweep", "SOURCE_STEREO",
           "SOURCE_LEFT_SHEET", "SOURCE_RIGHT_SHEET", "SOURCE_CROSS_STEREO"]


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
    # across frames (`SweepSequence`): a right line within ``same_position_steps`` of the left's is
    # matched alone; else the right lines just before and after it, at most ``max_bracket_steps``
    # apart, are interpolated; a left pixel whose two crossings lie more than ``max_jump_px`` per
    # step of travel apart on its epipolar line (a depth edge between the exposures) gives no point
    # (8 steps: the right exposures of a 180 steps/s sweep at 30 fps lie 6 steps apart, +-1 of jitter)
    same_position_steps: float = 0.1
    max_bracket_steps: float = 8.0
    max_jump_px: float = 3.0

    def __post_init__(self) -> None:
        if not self.consistency_mm > 0:
            raise SweepError(f"consistency_mm must be > 0, got {self.consistency_mm}")
        if not 0.0 < self.min_overlap <= 1.0:
            raise SweepError(f"min_overlap must be in (0, 1], got {self.min_overlap}")
        if not 0.0 <= self.min_sheet_angle_deg < 90.0:
            raise SweepError(f"min_sheet_angle_deg must be in [0, 90), got {self.min_sheet_angle_deg}")
        for name in ("same_position_steps", "max_bracket_steps", "max_jump_px"):
            if not getattr(self, name) >= 0:
                raise SweepError(f"{name} must be >= 0, got {getattr(self, name)}")


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
    source: NDArray[np.uint8]          # per point: SOURCE_* (0 stereo, 1 left sheet, 2 right sheet, 3 cross-frame)
    positions_steps: tuple[float, float]  # carriage at each camera's mid-exposure
    stats: dict[str, int] = field(default_factory=dict)


SOURCE_STEREO, SOURCE_LEFT_SHEET, SOURCE_RIGHT_SHEET = 0, 1, 2
SOURCE_CROSS_STEREO = 3  # the left line matched to the right lines exposed around it (`SweepSequence`)


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


def _bracket_stereo(model: StereoModel, sheet: LaserSheet, left: LineArrays, p_left: float,
                    rights: list[tuple[LineArrays, float]], params: SweepParams, index: int,
                    stats: dict[str, int]) -> SnapPoints:
    """The left line against one right line at its position, or two around it interpolated (module doc)."""
    matches = [match_line(model, left, line, params.match) for line, _p in rights]
    if len(matches) == 1:
        rows, x1, x2 = matches[0].left_index, matches[0].x1, matches[0].x2
    else:
        (a, b), (pa, pb) = matches, (rights[0][1], rights[1][1])
        rows, ia, ib = np.intersect1d(a.left_index, b.left_index, assume_unique=True, return_indices=True)
        w = (p_left - pa) / (pb - pa)
        x1 = a.x1[ia]
        x2 = (1.0 - w) * a.x2[ia] + w * b.x2[ib]  # both on the left pixel's epipolar line: so is x2
        smooth = np.linalg.norm(b.x2[ib] - a.x2[ia], axis=1) <= params.max_jump_px * max(abs(pb - pa), 1.0)
        stats["cross_rejected_jump"] += int(np.count_nonzero(~smooth))
        rows, x1, x2 = rows[smooth], x1[smooth], x2[smooth]
    X = triangulate(model, x1, x2, params.match.method)
    ok, _counts = accept_points(model, X, x1, x2, params.match.depth_min_m, params.match.depth_max_m,
                                params.match.max_reproj_px)
    with np.errstate(invalid="ignore"):
        on_sheet = np.abs(sheet.distance_m(X, np.full(len(X), p_left))) * 1000.0 <= params.consistency_mm
    stats["cross_rejected_inconsistent"] += int(np.count_nonzero(ok & ~on_sheet))
    ok &= on_sheet
    rows, X = rows[ok], X[ok]
    order = np.argsort(left.v[rows], kind="stable")  # along the line, top to bottom, as reconstruct_snap
    rows, X = rows[order], X[order]
    return SnapPoints(xyz=X, u=left.u[rows].copy(), v=left.v[rows].copy(),
                      snap=np.full(len(rows), index, dtype=np.uint32), stats={})


class SweepSequence:
    """Sweep frames in, points out, each left line matched across frames (module doc).

    One sequence per sweep. Feed frames in capture order with `add`; a frame's points come out once
    right exposures with mid-exposure times before and after its left one have arrived (with the
    right camera late, at once; else one frame later), in frame order; `finish` gives the rest at
    the end of the sweep. The carriage track is passed with each
    call (the live track grows; positions are read when a frame is reconstructed). The first (last)
    left line of a sweep has no right exposure before (after) it: it waits for two after it (or, at
    `finish`, takes the two before it) and is extrapolated along the epipolar line. A left line with
    no usable right line around it (a dropped frame, a gap of more than ``max_bracket_steps``) falls
    back to `reconstruct_sweep_frame` (its own pair, or the sheet).
    """

    def __init__(self, model: StereoModel, sheet: LaserSheet, params: SweepParams = SweepParams()) -> None:
        self.model, self.sheet, self.params = model, sheet, params
        self._pending: list[SweepFrame] = []
        self._rights: list[tuple[float, LineArrays]] = []  # (mid-exposure [s], line), by time

    def add(self, frame: SweepFrame, track: CarriageTrack) -> list[SweepFramePoints]:
        """Take one frame; return the points of the frames now complete (possibly none)."""
        mid_r = exposure_mid_s(frame.right_start_s, frame.exposure_s)
        exposure_mid_s(frame.left_start_s, frame.exposure_s)  # refuses a bad start before it is buffered
        self._rights.append((mid_r, frame.right))
        self._rights.sort(key=lambda r: r[0])
        self._pending.append(frame)
        ready = []
        for f in self._pending:  # in frame order: a frame waits while an earlier one waits
            if not self._placeable(exposure_mid_s(f.left_start_s, f.exposure_s)):
                break
            ready.append(f)
        return self._emit(ready, track)

    def _placeable(self, mid_l: float) -> bool:
        """A right exposure on either side of the left one, or (the sweep's first frames) two after it."""
        after = sum(1 for t, _line in self._rights if t > mid_l)
        return after >= 2 or (after >= 1 and len(self._rights) > after)

    def finish(self, track: CarriageTrack) -> list[SweepFramePoints]:
        """The points of every frame still waiting (end of the sweep)."""
        return self._emit(list(self._pending), track)

    def _emit(self, ready: list[SweepFrame], track: CarriageTrack) -> list[SweepFramePoints]:
        out = [self._frame(f, track) for f in ready]
        self._pending = [f for f in self._pending if not any(f is r for r in ready)]
        # keep the right lines a later left line may still need: from the last one before the earliest
        # left mid-exposure still to come (a waiting frame's, else the last one reconstructed: frames
        # come in capture order, so later left lines are later still)
        mids = [exposure_mid_s(f.left_start_s, f.exposure_s) for f in self._pending + ready[-1:]]
        if mids:
            before = [i for i, r in enumerate(self._rights) if r[0] <= min(mids)]
            # two of them: the sweep's last left line may have no right one after it (extrapolated)
            self._rights = self._rights[max(before[-1] - 1, 0):] if before else self._rights
        return out

    def _frame(self, frame: SweepFrame, track: CarriageTrack) -> SweepFramePoints:
        params = self.params
        mid_l = exposure_mid_s(frame.left_start_s, frame.exposure_s)
        p_left = float(track.position_at(mid_l))
        times = np.array([r[0] for r in self._rights])
        positions = track.position_at(times)
        p_right = float(track.position_at(exposure_mid_s(frame.right_start_s, frame.exposure_s)))
        stats = {"stereo": 0, "stereo_rejected_inconsistent": 0, "left_sheet": 0, "right_sheet": 0,
                 "cross_stereo": 0, "cross_extrapolated": 0, "cross_rejected_jump": 0, "cross_rejected_inconsistent": 0,
                 "no_carriage_position": int(not np.isfinite(p_left)) + int(not np.isfinite(p_right))}
        rights: list[tuple[LineArrays, float]] = []
        if np.isfinite(p_left) and len(frame.left):
            known = np.isfinite(positions)
            near = np.nonzero(known & (np.abs(positions - p_left) <= params.same_position_steps))[0]
            before = np.nonzero(known & (times <= mid_l))[0]
            after = np.nonzero(known & (times > mid_l))[0]
            if near.size:
                best = near[np.argmin(np.abs(times[near] - mid_l))]
                rights = [(self._rights[best][1], float(positions[best]))]
            elif before.size and after.size:
                a, b = before[-1], after[0]
                if 0 < abs(positions[b] - positions[a]) <= params.max_bracket_steps and \
                        min(positions[a], positions[b]) <= p_left <= max(positions[a], positions[b]):
                    rights = [(self._rights[a][1], float(positions[a])), (self._rights[b][1], float(positions[b]))]
            elif (after.size >= 2 and not before.size) or (before.size >= 2 and not after.size):
                # the sweep's first (last) left line: no right one before (after) it, so the two nearest
                # on the other side are extrapolated. Still stereo: a carriage-time error common to both
                # cameras (the device clock's mapping) moves every position alike and cancels, where the
                # sheet alone would turn it into depth (one step of 0.42 mm at 10-25 deg: ~1 mm)
                a, b = (after[0], after[1]) if after.size >= 2 else (before[-2], before[-1])
                pa, pb = float(positions[a]), float(positions[b])
                if 0 < abs(pb - pa) <= params.max_bracket_steps and \
                        max(abs(p_left - pa), abs(p_left - pb)) <= params.max_bracket_steps:
                    rights = [(self._rights[a][1], pa), (self._rights[b][1], pb)]
                    stats["cross_extrapolated"] = 1
        if not rights:
            fallback = reconstruct_sweep_frame(self.model, self.sheet, track, frame, params)
            fallback.stats.update({k: v for k, v in stats.items() if k not in fallback.stats})
            return fallback
        points = _bracket_stereo(self.model, self.sheet, frame.left, p_left, rights, params, frame.index, stats)
        stats["cross_stereo"] = len(points)
        points.stats = stats
        return SweepFramePoints(points, np.full(len(points), SOURCE_CROSS_STEREO, np.uint8), (p_left, p_right), stats)


def reconstruct_sweep(model: StereoModel, sheet: LaserSheet, track: CarriageTrack, frames: list[SweepFrame],
                      params: SweepParams = SweepParams()) -> list[SweepFramePoints]:
    """Every frame of a recorded sweep (capture order) through `SweepSequence`: one result per frame, in order."""
    sequence = SweepSequence(model, sheet, params)
    out: list[SweepFramePoints] = []
    for frame in frames:
        out.extend(sequence.add(frame, track))
    out.extend(sequence.finish(track))
    return out

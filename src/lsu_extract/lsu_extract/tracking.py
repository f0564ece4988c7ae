"""Where to look for the laser in each row: full-row candidates, continuity, tracking windows.

The thesis (6.1.1, 12.1.7) proposed a "roving eyeball": once the line is found, look only
near where it was. Row by row that is a sequential loop; here it is done for all rows at
once: a coarse pass over every k-th row finds the line, each row then searches a window
around the line interpolated from its coarse neighbours, and rows where that window holds
no clean peak fall back to a full-row search. Competing peaks (reflections) are resolved
by continuity with the nearest unambiguous row, or rejected.

A pure module: numpy and OpenCV, no ROS.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Tuple

import cv2
import numpy as np

from .detectors import clamp as _clamp


_CONTINUITY_PASSES = 4
_SECOND_PEAK_RATIO = 0.25  # a second peak this strong is worth checking against the neighbours
BLANK = np.float32(-1.0e9)  # below any float signal (masks a peak out), finite so no arithmetic on it can give NaN


@dataclass(frozen=True)
class RowCandidates:
    """The two strongest separated peaks of each searched row (all arrays (n,))."""

    rows: np.ndarray     # row index
    first: np.ndarray    # column of the strongest peak
    second: np.ndarray   # column of the strongest peak outside +-suppress_px of the first
    first_contrast: np.ndarray   # its height above the row's background
    second_contrast: np.ndarray


@lru_cache(maxsize=32)
def _suppression_offsets(rows: int, width: int, suppress_px: int) -> np.ndarray:
    """(rows, 2 s + 1) flat offsets of the columns -s..s in each row of a (rows, width) array (cached)."""
    offsets = np.arange(0, rows * width, width)[:, None] + np.arange(-suppress_px, suppress_px + 1)[None, :]
    offsets.setflags(write=False)
    return offsets


def row_candidates(signal_rows: np.ndarray, rows: np.ndarray, suppress_px: int,
                   min_contrast: float = 0.0) -> RowCandidates:
    """Top-two peaks of each full row of the laser signal (n, W): float32, or uint8 clipped at 0.

    The background of a row is its mean signal: the laser covers a few pixels of hundreds,
    so the mean is the ambient/texture level (cheaper than a median, and the bias is small).
    Rows whose strongest peak is below ``min_contrast`` get no second peak (contrast
    ``BLANK``): nothing will be chosen in them, so the search for one is skipped.
    """
    n, w = signal_rows.shape
    if n == 0:
        none = np.zeros(0, np.int64)
        return RowCandidates(np.asarray(rows), none, none, np.zeros(0, np.float32), np.zeros(0, np.float32))
    if signal_rows.dtype != np.uint8:
        signal_rows = np.ascontiguousarray(signal_rows, dtype=np.float32)
    blank = 0 if signal_rows.dtype == np.uint8 else BLANK  # below every value of the signal
    first = np.argmax(signal_rows, axis=1)
    background = cv2.reduce(signal_rows, 1, cv2.REDUCE_AVG, dtype=cv2.CV_32F).ravel()
    starts = np.arange(0, n * w, w)
    first_contrast = signal_rows.ravel()[starts + first] - background
    strong = first_contrast >= min_contrast
    if strong.all():
        sub: "slice | np.ndarray" = slice(None)
        rest = signal_rows.copy()
    else:
        sub = np.flatnonzero(strong)
        rest = signal_rows[sub]
    m = rest.shape[0]
    second = first.copy()
    second_contrast = np.full(n, BLANK, np.float32)
    if m:
        # blank +-suppress_px around the first peak (a scatter of m x (2 s + 1) values, not a full-row mask)
        flat = rest.ravel()
        peak = first[sub]
        if peak.min() < suppress_px or peak.max() > w - 1 - suppress_px:
            offsets = _suppression_offsets(m, w, 0)
            flat[offsets + _clamp(peak[:, None] + np.arange(-suppress_px, suppress_px + 1), 0, w - 1)] = blank
        else:
            flat[_suppression_offsets(m, w, suppress_px) + peak[:, None]] = blank
        second[sub] = np.argmax(rest, axis=1)
        second_contrast[sub] = flat[starts[:m] + second[sub]] - background[sub]
    return RowCandidates(rows=np.asarray(rows), first=first, second=second,
                         first_contrast=first_contrast, second_contrast=second_contrast)


def nearest_reference(rows: np.ndarray, ref_rows: np.ndarray, ref_cols: np.ndarray,
                      max_gap_rows: int) -> np.ndarray:
    """Column of the nearest reference row (above or below) within ``max_gap_rows``; NaN if none.

    ``ref_rows`` must be sorted ascending.
    """
    out = np.full(rows.shape, np.nan)
    if ref_rows.size == 0 or rows.size == 0:
        return out
    pos = np.searchsorted(ref_rows, rows)
    below = _clamp(pos, 0, ref_rows.size - 1)
    above = _clamp(pos - 1, 0, ref_rows.size - 1)
    d_below = np.abs(ref_rows[below] - rows)
    d_above = np.abs(ref_rows[above] - rows)
    pick = np.where(d_below < d_above, below, above)
    dist = np.minimum(d_below, d_above)
    ok = dist <= max_gap_rows
    out[ok] = ref_cols[pick[ok]]
    return out


@dataclass(frozen=True)
class Decision:
    """Which column each candidate row keeps (-1 = none) and why rows were dropped."""

    column: np.ndarray     # (n,) chosen integer column, -1 when the row has no accepted peak
    ambiguous: np.ndarray  # (n,) bool: two competing peaks that continuity could not separate
    candidates: RowCandidates

    @property
    def uniqueness(self) -> np.ndarray:
        """(n,) 1 - (other peak / chosen peak), 0..1: computed on demand, the coarse pass never reads it."""
        c = self.candidates
        chosen_first = self.column == c.first
        other = np.where(chosen_first, c.second_contrast, c.first_contrast)
        mine = np.where(chosen_first, c.first_contrast, c.second_contrast)
        ratio = np.zeros(c.rows.shape)
        np.divide(np.maximum(other, 0.0), mine, out=ratio, where=mine > 0)
        return _clamp(1.0 - ratio, 0.0, 1.0)


def decide(c: RowCandidates, min_contrast: float, ambiguity_ratio: float, window_px: int,
           ref_rows: np.ndarray, ref_cols: np.ndarray, max_gap_rows: int) -> Decision:
    """Choose between the two strongest peaks of each row, by continuity where possible.

    Rows with a single peak above ``min_contrast`` keep it and become references. Rows with
    a second peak (above ``min_contrast`` and ``_SECOND_PEAK_RATIO`` of the first) keep
    whichever peak lies within ``window_px`` of the nearest reference row (``ref_rows`` /
    ``ref_cols`` or a resolved row here, within ``max_gap_rows``). Without a usable reference
    the stronger peak wins, unless the second is at least ``ambiguity_ratio`` of it: then the
    peaks compete, and the row is counted ambiguous and dropped.
    """
    strong = c.first_contrast >= min_contrast
    double = strong & (c.second_contrast >= min_contrast) & \
        (c.second_contrast >= _SECOND_PEAK_RATIO * c.first_contrast)
    if not double.any():
        # the common case, one clear peak or none per row: nothing to resolve
        return Decision(column=np.where(strong, c.first, -1), ambiguous=np.zeros(strong.shape, bool), candidates=c)
    competing = double & (c.second_contrast >= ambiguity_ratio * c.first_contrast)
    column = np.where(strong & ~double, c.first, -1)
    ref_rows = np.asarray(ref_rows, dtype=np.int64)
    ref_cols = np.asarray(ref_cols, dtype=np.float64)
    # Each pass lets rows resolved in the previous one serve as references for their
    # neighbours, so continuity spreads along a run of double-peaked rows (bounded: a loop
    # over passes, vectorised over rows).
    for _ in range(_CONTINUITY_PASSES):
        open_rows = double & (column < 0)
        if not open_rows.any():
            break
        known = column >= 0
        all_rows = np.concatenate([ref_rows, c.rows[known]])
        all_cols = np.concatenate([ref_cols, column[known].astype(np.float64)])
        order = np.argsort(all_rows, kind="stable")
        ref = nearest_reference(c.rows[open_rows], all_rows[order], all_cols[order], max_gap_rows)
        near_first = np.abs(c.first[open_rows] - ref) <= window_px
        near_second = np.abs(c.second[open_rows] - ref) <= window_px
        pick = np.where(near_first & ~near_second, c.first[open_rows],
                        np.where(near_second & ~near_first, c.second[open_rows], -1))
        if not (pick >= 0).any():
            break
        column[open_rows] = pick
    undecided = double & (column < 0)
    column = np.where(undecided & ~competing, c.first, column)
    ambiguous = undecided & competing
    return Decision(column=column, ambiguous=ambiguous, candidates=c)


def interpolate_track(rows: np.ndarray, track_rows: np.ndarray, track_cols: np.ndarray,
                      max_gap_rows: int) -> np.ndarray:
    """Expected line column at every row of ``rows`` from a sparse track; NaN far from the track.

    Linear interpolation between neighbouring track rows, only where the nearest track row
    is within ``max_gap_rows`` (beyond the ends of the line the search falls back to full rows).
    """
    out = np.full(rows.shape, np.nan)
    if track_rows.size == 0:
        return out
    near = ~np.isnan(nearest_reference(rows, track_rows, track_cols, max_gap_rows))
    out[near] = np.interp(rows[near], track_rows, track_cols)
    return out


@lru_cache(maxsize=16)
def coarse_neighbours(height: int, first_row: int, step: int) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each image row, the indices of the coarse rows (``first_row + k * step``) within ``step`` rows of it.

    Returns (before, nearest, after), each (height,) int64 into the coarse rows: a row between
    coarse rows k and k + 1 has both within reach; a coarse row k also has k - 1 and k + 1.
    Cached read-only arrays: the layout only depends on the image height and the step.
    """
    count = len(range(first_row, height, step))
    pos = (np.arange(height, dtype=np.float64) - first_row) / step
    out = []
    for index in (np.ceil(pos) - 1.0, np.rint(pos), np.floor(pos) + 1.0):
        index = np.clip(index, 0, count - 1).astype(np.int64)
        index.setflags(write=False)
        out.append(index)
    return out[0], out[1], out[2]


def coarse_track(height: int, coarse_rows: np.ndarray, column: np.ndarray, step: int) -> Tuple[np.ndarray, np.ndarray]:
    """Rows within ``step`` rows of a coarse row that found the line, and the line column expected in each.

    ``coarse_rows`` must be ``coarse_rows[0] + k * step``; ``column`` is the coarse decision
    (-1 = none). The expected column is interpolated linearly between the found coarse rows
    (held constant beyond the first and last one). Same rule as `interpolate_track`, with the
    neighbour search replaced by the cached layout of `coarse_neighbours`.
    """
    ok = column >= 0
    if ok.all():  # the line crosses the whole frame: every row is tracked
        rows = np.arange(height)
        return rows, np.interp(rows, coarse_rows, column)
    if not ok.any():
        return np.zeros(0, np.int64), np.zeros(0)
    before, nearest, after = coarse_neighbours(height, int(coarse_rows[0]), step)
    rows = np.flatnonzero(ok[before] | ok[nearest] | ok[after])
    guess = np.interp(rows, coarse_rows[ok], column[ok])
    return rows, guess

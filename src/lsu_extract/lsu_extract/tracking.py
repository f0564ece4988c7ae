"""Where to look for the laser in each row: full-row candidates, continuity, tracking windows.

The thesis (6.1.1, 12.1.7) proposed a "roving eyeball": once the line is found, look only
near where it was. Row by row that is a sequential loop; here it is done for all rows at
once: a coarse pass over every k-th row finds the line, each row then searches a window
around the line interpolated from its coarse neighbours, and rows where that window holds
no clean peak fall back to a full-row search. Competing peaks (reflections) are resolved
by continuity with the nearest unambiguous row, or rejected.

A pure module: numpy only, no ROS.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .detectors import clamp as _clamp


_CONTINUITY_PASSES = 4
_SECOND_PEAK_RATIO = 0.25  # a second peak this strong is worth checking against the neighbours


@dataclass(frozen=True)
class RowCandidates:
    """The two strongest separated peaks of each searched row (all arrays (n,))."""

    rows: np.ndarray     # row index
    first: np.ndarray    # column of the strongest peak
    second: np.ndarray   # column of the strongest peak outside +-suppress_px of the first
    first_contrast: np.ndarray   # its height above the row's background
    second_contrast: np.ndarray


def row_candidates(signal_rows: np.ndarray, rows: np.ndarray, suppress_px: int) -> RowCandidates:
    """Top-two peaks of each full row of the laser signal (n, W).

    The background of a row is its mean signal: the laser covers a few pixels of hundreds,
    so the mean is the ambient/texture level (cheaper than a median, and the bias is small).
    """
    n, w = signal_rows.shape
    first = np.argmax(signal_rows, axis=1)
    idx = np.arange(n)
    background = signal_rows.mean(axis=1)
    near = np.abs(np.arange(w)[None, :] - first[:, None]) <= suppress_px
    rest = np.where(near, np.iinfo(np.int16).min, signal_rows)
    second = np.argmax(rest, axis=1)
    return RowCandidates(rows=np.asarray(rows), first=first, second=second,
                         first_contrast=signal_rows[idx, first] - background,
                         second_contrast=rest[idx, second] - background)


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
    uniqueness: np.ndarray  # (n,) 1 - (other peak / chosen peak), 0..1


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
    chosen_first = column == c.first
    other = np.where(chosen_first, c.second_contrast, c.first_contrast)
    mine = np.where(chosen_first, c.first_contrast, c.second_contrast)
    uniqueness = np.zeros(c.rows.shape)
    np.divide(np.maximum(other, 0.0), mine, out=uniqueness, where=mine > 0)
    return Decision(column=column, ambiguous=ambiguous, uniqueness=_clamp(1.0 - uniqueness, 0.0, 1.0))


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

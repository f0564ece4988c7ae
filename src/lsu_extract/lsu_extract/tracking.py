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

import cv2
import numpy as np

from lsu_common.arrays import AnyArray

from . import workspace
from .detectors import clamp as _clamp

_CONTINUITY_PASSES = 4
PEAK_SNAP_PX = 3  # `local_candidates`: a peak is the signal's maximum this close to the top-hat's (a line's half width)
_SECOND_PEAK_RATIO = 0.25  # a second peak this strong is worth checking against the neighbours
BLANK = np.float32(-1.0e9)  # below any float signal (masks a peak out), finite so no arithmetic on it can give NaN
# the same for the integer signals: the clipped one (0..255) and the exact one (-255..255)
_BLANK_OF = {np.dtype(np.uint8): 0, np.dtype(np.int16): np.iinfo(np.int16).min}


@dataclass(frozen=True)
class RowCandidates:
    """The two strongest separated peaks of each searched row (all arrays (n,))."""

    rows: AnyArray     # row index
    first: AnyArray    # column of the strongest peak
    second: AnyArray   # column of the strongest peak outside +-suppress_px of the first
    first_contrast: AnyArray   # its height above the row's background
    second_contrast: AnyArray


@lru_cache(maxsize=32)
def _suppression_offsets(rows: int, width: int, suppress_px: int) -> AnyArray:
    """(rows, 2 s + 1) flat offsets of the columns -s..s in each row of a (rows, width) array (cached)."""
    offsets = np.arange(0, rows * width, width)[:, None] + np.arange(-suppress_px, suppress_px + 1)[None, :]
    offsets.setflags(write=False)
    return offsets


@lru_cache(maxsize=32)
def row_starts(rows: int, width: int) -> AnyArray:
    """(rows,) flat index of the first element of each row of a (rows, width) array (cached, read-only)."""
    starts = np.arange(0, rows * width, width)
    starts.setflags(write=False)
    return starts


def row_candidates(signal_rows: AnyArray, rows: AnyArray, suppress_px: int,
                   min_contrast: float = 0.0, strong_only: bool = False, scratch: bool = False,
                   local: bool = False) -> RowCandidates:
    """Top-two peaks of each full row of the laser signal (n, W): int16 or float32, or uint8 clipped at 0.

    With ``local`` the peaks are the two highest above their own surroundings (`local_candidates`), not
    the two highest.

    The background of a row is its mean signal: the laser covers a few pixels of hundreds,
    so the mean is the ambient/texture level (cheaper than a median, and the bias is small).
    Rows whose strongest peak is below ``min_contrast`` get no second peak (contrast
    ``BLANK``): nothing will be chosen in them, so the search for one is skipped. With
    ``strong_only`` they are left out of the result altogether (``rows`` then holds only the
    strong rows): `decide` never picks a weak row nor uses one as a reference, so its choice for
    the others is the same, and a frame where the line left the object (hundreds of lit rows
    without it) costs a fraction of the second-peak search (the strong rows are gathered into a
    per-thread buffer, `workspace.scratch`, which the result does not reference, where they are
    the fewer; else every row is searched and the weak ones dropped after). With ``scratch`` the
    caller hands over ``signal_rows`` (an array of its own, not a view of the frame) for the
    second-peak search to overwrite, instead of a copy.
    """
    n, w = signal_rows.shape
    if n == 0:
        none = np.zeros(0, np.int64)
        return RowCandidates(np.asarray(rows), none, none, np.zeros(0, np.float32), np.zeros(0, np.float32))
    if local:
        return local_candidates(signal_rows, rows, suppress_px, min_contrast, strong_only)
    if signal_rows.dtype not in (np.uint8, np.int16):
        signal_rows = np.ascontiguousarray(signal_rows, dtype=np.float32)
    blank = _BLANK_OF.get(signal_rows.dtype, BLANK)  # below every value of the signal
    first = signal_rows.argmax(axis=1)
    background = cv2.reduce(signal_rows, 1, cv2.REDUCE_AVG, dtype=cv2.CV_32F).ravel()
    starts = row_starts(n, w)
    first_contrast = signal_rows.ravel()[starts + first] - background
    strong = first_contrast >= min_contrast
    n_strong = np.count_nonzero(strong)
    keep_copied = False
    # Where the weak rows are the majority, the strong ones are copied out and searched alone; where
    # they are few, searching them along costs less than that copy, and their results are dropped.
    if strong_only and 2 * n_strong < n:
        keep = strong.nonzero()[0]
        strong_rows = workspace.scratch("strong rows", (keep.size, w), signal_rows.dtype)
        signal_rows, rows = np.take(signal_rows, keep, axis=0, out=strong_rows, mode="clip"), np.asarray(rows)[keep]
        keep_copied = True
        first, background, first_contrast = first[keep], background[keep], first_contrast[keep]
        strong = strong[keep]
        n = n_strong = keep.size
        if n == 0:
            none = np.zeros(0, np.int64)
            return RowCandidates(rows, none, none, np.zeros(0, np.float32), np.zeros(0, np.float32))
        starts = row_starts(n, w)
    # The second peak of every row, weak ones included (their result is then discarded): fewer
    # calls than picking out the strong rows and scattering their results back. Blanked in place where
    # the rows are a copy already (selected above, or handed over), so contiguous (ravel is a view).
    rest = signal_rows if scratch or keep_copied else signal_rows.copy()
    # blank +-suppress_px around the first peak (a scatter of n x (2 s + 1) values, not a full-row mask)
    flat = rest.ravel()
    if np.minimum.reduce(first) < suppress_px or np.maximum.reduce(first) > w - 1 - suppress_px:
        offsets = _suppression_offsets(n, w, 0)
        flat[offsets + _clamp(first[:, None] + np.arange(-suppress_px, suppress_px + 1), 0, w - 1)] = blank
    else:
        flat[_suppression_offsets(n, w, suppress_px) + first[:, None]] = blank
    second = rest.argmax(axis=1)
    second_contrast = flat[starts + second] - background
    if n_strong < n:
        if strong_only:
            keep = strong.nonzero()[0]
            return RowCandidates(rows=np.asarray(rows)[keep], first=first[keep], second=second[keep],
                                 first_contrast=first_contrast[keep], second_contrast=second_contrast[keep])
        # weak rows get no second peak: nothing will be chosen in them
        second = np.where(strong, second, first)
        second_contrast = np.where(strong, second_contrast, BLANK)
    return RowCandidates(rows=np.asarray(rows), first=first, second=second,
                         first_contrast=first_contrast, second_contrast=second_contrast)


def local_candidates(signal_rows: AnyArray, rows: AnyArray, suppress_px: int, min_contrast: float,
                     strong_only: bool = False) -> RowCandidates:
    """`row_candidates` whose two peaks are chosen by their height above the mean of the ``2 suppress_px + 1``
    samples around them (a top-hat), each at the signal's maximum within ``PEAK_SNAP_PX`` of that choice (where
    the tracking windows would put it). The first peak's contrast is still its height above the row's mean (what
    ``min_contrast`` is for); the second's is scaled from it by their ratio above their surroundings, which is
    what says whether they compete (`decide`).

    For the intensity of a mono frame: there a lit patch or a specular highlight broader than the line
    outshines it in the same rows, and, chosen for the row, fails as a line (too wide) and leaves the row
    empty; above its own surroundings a narrow line stands out and the broad patch does not. (A colour
    frame's signal removes white patches already; there the same ranking prefers narrow red features in
    rows without laser: bench/results/extract.json.)
    """
    n, w = signal_rows.shape
    values = signal_rows.astype(np.float32)
    ranked = values - cv2.blur(values, (2 * suppress_px + 1, 1), borderType=cv2.BORDER_REFLECT)
    background = cv2.reduce(values, 1, cv2.REDUCE_AVG, dtype=cv2.CV_32F).ravel()
    at = np.arange(n)
    cols = np.arange(w)[None, :]

    def snap(column: AnyArray) -> AnyArray:
        near = np.abs(cols - column[:, None]) <= PEAK_SNAP_PX
        return np.where(near, values, BLANK).argmax(axis=1)

    top = ranked.argmax(axis=1)
    first = snap(top)
    local_first = ranked[at, top]
    first_contrast = values[at, first] - background
    ranked[np.abs(cols - first[:, None]) <= suppress_px] = BLANK
    top = ranked.argmax(axis=1)
    second = snap(top)
    ratio = np.zeros(n, np.float32)
    np.divide(np.maximum(ranked[at, top], 0.0), local_first, out=ratio, where=local_first > 0)
    strong = first_contrast >= min_contrast
    # weak rows get no second peak: nothing will be chosen in them
    second = np.where(strong, second, first)
    second_contrast = np.where(strong, ratio * first_contrast, BLANK)
    rows = np.asarray(rows)
    keep = strong if strong_only else slice(None)
    return RowCandidates(rows=rows[keep], first=first[keep], second=second[keep],
                         first_contrast=first_contrast[keep], second_contrast=second_contrast[keep])


def nearest_reference(rows: AnyArray, ref_rows: AnyArray, ref_cols: AnyArray,
                      max_gap_rows: int) -> AnyArray:
    """Column of the nearest reference row (above or below) within ``max_gap_rows``; NaN if none.

    ``ref_rows`` must be sorted ascending. Of two references at the same distance, the one
    above (the smaller row) is taken.
    """
    if ref_rows.size == 0 or rows.size == 0:
        return np.full(rows.shape, np.nan)
    pos = np.searchsorted(ref_rows, rows)  # the first reference at or below (after) each row
    below = np.minimum(pos, ref_rows.size - 1)
    above = np.maximum(pos - 1, 0)
    d_below = np.abs(ref_rows[below] - rows)
    d_above = np.abs(ref_rows[above] - rows)
    use_below = d_below < d_above
    pick = np.where(use_below, below, above)
    dist = np.where(use_below, d_below, d_above)
    return np.where(dist <= max_gap_rows, ref_cols[pick], np.nan)


@dataclass(frozen=True)
class Decision:
    """Which column each candidate row keeps (-1 = none) and why rows were dropped."""

    column: AnyArray     # (n,) chosen integer column, -1 when the row has no accepted peak
    ambiguous: AnyArray  # (n,) bool: two competing peaks that continuity could not separate
    candidates: RowCandidates

    @property
    def uniqueness(self) -> AnyArray:
        """(n,) 1 - (other peak / chosen peak), 0..1: computed on demand, the coarse pass never reads it."""
        c = self.candidates
        chosen_first = self.column == c.first
        other = np.where(chosen_first, c.second_contrast, c.first_contrast)
        mine = np.where(chosen_first, c.first_contrast, c.second_contrast)
        ratio = np.zeros(c.rows.shape)
        np.divide(np.maximum(other, 0.0), mine, out=ratio, where=mine > 0)
        return _clamp(1.0 - ratio, 0.0, 1.0)


def decide(c: RowCandidates, min_contrast: float, ambiguity_ratio: float, window_px: int,
           ref_rows: AnyArray, ref_cols: AnyArray, max_gap_rows: int) -> Decision:
    """Choose between the two strongest peaks of each row, by continuity where possible.

    Rows with a single peak above ``min_contrast`` keep it and become references. Rows with
    a second peak (above ``min_contrast`` and ``_SECOND_PEAK_RATIO`` of the first) keep
    whichever peak lies within ``window_px`` of the nearest reference row (``ref_rows`` /
    ``ref_cols`` or a resolved row here, within ``max_gap_rows``). Without a usable reference
    the stronger peak wins, unless the second is at least ``ambiguity_ratio`` of it: then the
    peaks compete, and the row is counted ambiguous and dropped.

    ``c.rows`` and ``ref_rows`` must each be ascending (as the extractor makes them), and
    disjoint.
    """
    strong = c.first_contrast >= min_contrast
    # a second peak above both min_contrast and the ratio of the first (weak rows have none: BLANK)
    double = strong & (c.second_contrast >= np.maximum(_SECOND_PEAK_RATIO * c.first_contrast, min_contrast))
    if not np.count_nonzero(double):
        # the common case, one clear peak or none per row: nothing to resolve
        return Decision(column=np.where(strong, c.first, -1), ambiguous=np.zeros(strong.shape, bool), candidates=c)
    competing = double & (c.second_contrast >= ambiguity_ratio * c.first_contrast)
    column = np.where(strong > double, c.first, -1)  # strong and not double
    ref_rows = np.asarray(ref_rows, dtype=np.int64)
    # Every row that can serve as a reference, the external ones and these, in one ascending list
    # merged once (both are ascending and disjoint): each pass then only marks which of them are
    # known, instead of merging and sorting the references again.
    if ref_rows.size:
        merged = np.concatenate([ref_rows, c.rows])
        order = np.argsort(merged, kind="stable")
        all_rows = merged[order]
        at = np.empty_like(order)  # the merged position of each row of c
        at[order] = np.arange(order.size)
        at = at[ref_rows.size:]
        all_cols = np.concatenate([np.asarray(ref_cols, dtype=np.float64), column])[order]
        known = np.concatenate([np.ones(ref_rows.size, bool), column >= 0])[order]
    else:  # c.rows is ascending: it is the list
        all_rows, at, all_cols, known = c.rows, None, column.copy(), column >= 0
    # Each pass lets rows resolved in the previous one serve as references for their
    # neighbours, so continuity spreads along a run of double-peaked rows (bounded: a loop
    # over passes, vectorised over rows). Integer indices of the open rows, not masks: the
    # loop body is a few dozen calls on a handful of rows, so each call counts.
    for _ in range(_CONTINUITY_PASSES):
        open_idx = (double & (column < 0)).nonzero()[0]
        if not open_idx.size:
            break
        ref_idx = known.nonzero()[0]
        if not ref_idx.size:  # no reference at all: no open row can be resolved
            break
        ref = nearest_reference(c.rows[open_idx], all_rows[ref_idx], all_cols[ref_idx], max_gap_rows)
        first, second = c.first[open_idx], c.second[open_idx]
        near_first = np.abs(first - ref) <= window_px  # False where ref is NaN
        near_second = np.abs(second - ref) <= window_px
        pick = np.where(near_first > near_second, first, np.where(near_second > near_first, second, -1))
        resolved = pick >= 0
        if not np.count_nonzero(resolved):
            break
        column[open_idx] = pick
        if at is not None:
            open_idx = at[open_idx]
        all_cols[open_idx] = pick
        known[open_idx] = resolved
    undecided = double & (column < 0)
    column = np.where(undecided > competing, c.first, column)
    ambiguous = undecided & competing
    return Decision(column=column, ambiguous=ambiguous, candidates=c)


def interpolate_track(rows: AnyArray, track_rows: AnyArray, track_cols: AnyArray,
                      max_gap_rows: int) -> AnyArray:
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
def coarse_neighbours(height: int, first_row: int, step: int) -> tuple[AnyArray, AnyArray, AnyArray]:
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


@lru_cache(maxsize=16)
def _all_rows(height: int) -> tuple[AnyArray, AnyArray]:
    """``arange(height)`` as int64 and float64 (cached, read-only; np.interp is faster on floats)."""
    rows = np.arange(height)
    rows_f = rows.astype(np.float64)
    rows.setflags(write=False)
    rows_f.setflags(write=False)
    return rows, rows_f


def coarse_track(height: int, coarse_rows: AnyArray, column: AnyArray, step: int) -> tuple[AnyArray, AnyArray]:
    """Rows within ``step`` rows of a coarse row that found the line, and the line column expected in each.

    ``coarse_rows`` must be ``coarse_rows[0] + k * step``; ``column`` is the coarse decision
    (-1 = none). The expected column is interpolated linearly between the found coarse rows
    (held constant beyond the first and last one). Same rule as `interpolate_track`, with the
    neighbour search replaced by the cached layout of `coarse_neighbours`. When every coarse
    row found the line, the rows returned are a cached read-only ``arange(height)``.
    """
    ok = column >= 0
    found = np.count_nonzero(ok)
    if found == ok.size:  # the line crosses the whole frame: every row is tracked
        rows, rows_f = _all_rows(height)
        return rows, np.interp(rows_f, coarse_rows, column)
    if not found:
        return np.zeros(0, np.int64), np.zeros(0)
    before, nearest, after = coarse_neighbours(height, int(coarse_rows[0]), step)
    rows = (ok[before] | ok[nearest] | ok[after]).nonzero()[0]
    guess = np.interp(rows, coarse_rows[ok], column[ok])
    return rows, guess

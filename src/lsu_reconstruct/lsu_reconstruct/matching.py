"""Epipolar matching of a left laser line to the right laser polyline (thesis ch. 7.1, sub-pixel).

For every left laser sample: undistort it, build its right epipolar line ``l2 = F x1`` and
intersect that line with the right laser *polyline* (segments between right samples of
neighbouring rows, in undistorted pixels). The crossing is found by a sign change of the
signed point-line distance of the segment's end points and located by linear interpolation
between them, so the match is sub-pixel along the line, not snapped to a right pixel.

A whole line is matched at once: the distances of all right vertices to all left epipolar
lines form one (N_left x N_right) matrix (~480 x 480, one BLAS product), sign changes are
found with array comparisons, candidates with ``np.nonzero``.

Ambiguity (several crossings for one left point, e.g. a reflection or a folded curve):
1. depth range: a crossing must triangulate inside ``[depth_min_m, depth_max_m]``;
2. ordering: along a continuous surface the right polyline position grows monotonically with
   the left row, so a left point with several in-range crossings takes the one nearest to the
   position interpolated from its unambiguous neighbours, if it is within ``max_order_dev``
   segments and the runner-up is not;
3. otherwise the left point is rejected.
Occlusion (no crossing, or a crossing only across a gap in the right line) gives no point.

``match_thesis`` is the thesis chain as a baseline: integer laser pixels, the right laser
pixel nearest to the epipolar line (within half a pixel diagonal), no interpolation.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from lsu_common.arrays import AnyArray

from .stereo import StereoModel

__all__ = ["LineArrays", "MatchParams", "Matches", "LaserLineError", "match_line", "match_thesis", "smooth_line",
           "ray_depths"]


class LaserLineError(ValueError):
    """A laser line cannot be used (arrays of different length, NaN, wrong image size)."""


@dataclass
class LineArrays:
    """A LaserLine as numpy arrays (one entry per detected row); u, v raw distorted pixels."""

    u: AnyArray
    v: AnyArray
    peak: AnyArray | None = None
    width: AnyArray | None = None
    quality: AnyArray | None = None
    image_width: int = 0
    image_height: int = 0

    def __post_init__(self) -> None:
        self.u = np.asarray(self.u, dtype=np.float64).reshape(-1)
        self.v = np.asarray(self.v, dtype=np.float64).reshape(-1)
        n = self.u.size
        if self.v.size != n:
            raise LaserLineError(f"laser line has {n} u values but {self.v.size} v values; every row needs both")
        for name in ("peak", "width", "quality"):
            value = getattr(self, name)
            if value is not None:
                arr = np.asarray(value, dtype=np.float64).reshape(-1)
                if arr.size not in (0, n):
                    raise LaserLineError(f"laser line '{name}' has {arr.size} entries for {n} rows")
                # an extractor may leave optional arrays empty
                setattr(self, name, arr if arr.size else None)

    def __len__(self) -> int:
        return int(self.u.size)

    def valid(self, min_quality: float = 0.0) -> AnyArray:
        """Rows with finite u, v (NaN from an extractor must never reach a cloud) and enough quality."""
        ok = np.isfinite(self.u) & np.isfinite(self.v)
        if self.quality is not None and min_quality > 0.0:
            ok &= np.nan_to_num(self.quality, nan=0.0) >= min_quality
        return ok


@dataclass(frozen=True)
class MatchParams:
    """Matching and rejection settings (node parameters of the same names)."""

    depth_min_m: float = 0.12        # nearer crossings are not the subject (disparity range)
    depth_max_m: float = 0.80        # farther ones are background or wrong crossings
    max_gap_rows: float = 1.5        # right samples further apart in v are not joined (occlusion holes)
    max_step_px: float = 4.0         # nor are samples whose u jumps more than this per row (depth edges, reflections)
    max_order_dev: float = 3.0       # [segments] ordering tolerance for resolving ambiguous crossings
    min_quality: float = 0.0         # drop rows whose extractor quality is below this
    smooth_window_rows: int = 9      # odd >= 5: local quadratic fit of u(v) along each run; 0 = off
    min_run_rows: int = 9            # both samples of a match must lie in continuous pieces this long; 0 = off
    max_reproj_px: float = 0.5       # reject triangulated points whose reprojection error exceeds this
    method: str = "midpoint"         # triangulation: midpoint | dlt | optimal


@dataclass
class Matches:
    """Matched pairs of one snap: indices into the input left line, undistorted pixels of both sides."""

    left_index: AnyArray            # (K,) row indices into the left LineArrays
    x1: AnyArray                    # (K, 2) undistorted left pixels
    x2: AnyArray                    # (K, 2) undistorted right pixels (on the epipolar line)
    depth_m: AnyArray               # (K,) depth along the left optical axis from the candidate test
    stats: dict = field(default_factory=dict)
    # StereoModel.closest_approach of the pairs (x1, x2), already computed for the depth test, so
    # the midpoint triangulation need not repeat it; None where the matcher has not kept it.
    rays: tuple | None = None


def savgol_weights(window: int, pos: int) -> AnyArray:
    """Weights of the quadratic least-squares fit over ``window`` samples, evaluated at sample ``pos``
    (``weights @ y`` is the fitted value there): scipy.signal.savgol_coeffs(window, 2, pos=pos, use="dot").

    The same least-squares problem solved the same way (LAPACK's gelsd with scipy's rcond), so the weights
    are scipy's to the bit, with numpy's lstsq: importing scipy.signal (~1.3 s CPU) or scipy.linalg (~0.5 s)
    would be paid at every start of stereo_matcher and of a replay. A test compares them with scipy's.
    """
    x = np.arange(-pos, window - pos, dtype=np.float64)
    a = x ** np.arange(3, dtype=np.float64).reshape(-1, 1)
    coeffs, _, _, _ = np.linalg.lstsq(a, np.array([1.0, 0.0, 0.0]), rcond=np.finfo(np.float64).eps * max(a.shape))
    return np.asarray(coeffs)


@lru_cache(maxsize=16)
def _savgol_matrices(window: int) -> tuple:
    """Savitzky-Golay (quadratic) weights: centre kernel and the fits for the first/last half-window rows."""
    half = window // 2
    centre = savgol_weights(window, half)
    head = np.stack([savgol_weights(window, k) for k in range(half)])
    tail = np.stack([savgol_weights(window, window - half + k) for k in range(half)])
    return centre, head, tail


def prepare(params: MatchParams) -> None:
    """Fill the caches ``match_line`` needs for ``params`` ahead of the first snap (the node calls this at
    start-up and on a parameter change)."""
    window = params.smooth_window_rows
    if window >= 5:
        _savgol_matrices(window + 1 if window % 2 == 0 else window)


def smooth_line(u: AnyArray, v: AnyArray, window: int, linked: AnyArray | None = None) -> AnyArray:
    """Local quadratic (Savitzky-Golay) fit of u as a function of v along each run of consecutive rows.

    The laser trace on a smooth surface is a smooth curve; a quadratic fit over ``window`` rows
    cuts the extractor's per-row noise by ~sqrt(window / 2.3) and follows the curve (its bias
    grows with the third derivative of u(v) times window^3: negligible on planes, spheres and
    faces at 7-11 rows). Runs are split wherever rows are not consecutive (occlusions, missed
    rows) or, when given, wherever ``linked`` (len(u) - 1 flags) is False; runs shorter than
    ``window`` are left alone, so no curve is bridged across a gap or an edge. ``v`` must be sorted.
    """
    u = np.asarray(u, dtype=np.float64)
    if window < 5 or len(u) < window:
        return u
    if window % 2 == 0:
        window += 1
    centre, head, tail = _savgol_matrices(window)
    half = window // 2
    out = u.copy()
    v = np.asarray(v)
    cut = np.abs((v[1:] - v[:-1]) - 1.0) > 1e-3
    if linked is not None:
        cut |= ~np.asarray(linked, dtype=bool)
    bounds = [0, *(cut.nonzero()[0] + 1).tolist(), len(u)]
    for start, stop in zip(bounds[:-1], bounds[1:]):  # a handful of runs per line
        if stop - start < window:
            continue
        run = u[start:stop]
        out[start + half:stop - half] = np.convolve(run, centre[::-1], mode="valid")
        out[start:start + half] = head @ run[:window]
        out[stop - half:stop] = tail @ run[-window:]
    return out


def ray_depths(model: StereoModel, x1: AnyArray, x2: AnyArray) -> AnyArray:
    """Depth (z in the left frame) of the midpoint triangulation of undistorted pixel pairs (N, 2)."""
    r1, _r2, lam, _mu = model.closest_approach(x1, x2)
    return lam * r1[:, 2]


def _links(u: AnyArray, v: AnyArray, params: MatchParams) -> tuple:
    """Which consecutive samples (sorted by row) belong to one continuous piece of laser line.

    Two samples are linked when they lie in neighbouring rows (0 < dv <= max_gap_rows) and the
    column moves by at most ``max_step_px`` per row. Not linked: holes (occlusion), depth edges and
    jumps to a reflection (joining them would invent points in between), and rows that hold
    several samples (a LaserLine has one per row; several mean the extractor could not decide,
    so none of them is trusted). Returns ``(linked, shared_rows_count)``.
    """
    dv, du = v[1:] - v[:-1], np.abs(u[1:] - u[:-1])
    same_row = dv < 1e-6
    linked = (dv <= params.max_gap_rows) & (du <= params.max_step_px * np.maximum(dv, 1.0))
    if not same_row.any():  # the usual case: one sample per row
        return linked, 0
    shared = np.zeros(len(v), dtype=bool)
    shared[:-1] |= same_row
    shared[1:] |= same_row
    linked &= ~same_row & ~shared[:-1] & ~shared[1:]
    return linked, int(np.count_nonzero(shared))


PIECE_GAP_ROWS = 2.0  # a piece of line bridges one missed row (the extractor's occasional miss)


def _in_long_pieces(u: AnyArray, v: AnyArray, params: MatchParams) -> AnyArray:
    """Per sample (sorted by row): whether its piece of line holds at least ``params.min_run_rows`` samples.

    A piece: samples at most ``PIECE_GAP_ROWS`` rows apart whose column moves at most ``max_step_px`` per
    row. A stray detection (a lit hairline, a glint, a line broken up beside a silhouette) forms short
    pieces; a laser line on a surface is continuous over many rows. A stereo point is only as good as
    both of its samples: short pieces on either side give none (the sweep's sheet points use the same rule).
    """
    dv, du = v[1:] - v[:-1], np.abs(u[1:] - u[:-1])
    linked = (dv > 1e-6) & (dv <= PIECE_GAP_ROWS) & (du <= params.max_step_px * np.maximum(dv, 1.0))
    piece = np.r_[0, np.cumsum(~linked)]
    return np.bincount(piece)[piece] >= int(params.min_run_rows)


def match_line(model: StereoModel, left: LineArrays, right: LineArrays,
               params: MatchParams = MatchParams()) -> Matches:
    """Match every left sample to the right polyline by sub-pixel epipolar intersection (vectorised)."""
    stats = {"left_rows": len(left), "right_rows": len(right), "no_crossing": 0, "out_of_range": 0,
             "ambiguous_resolved": 0, "short_piece_rows": 0, "ambiguous_rejected": 0, "invalid_rows": 0}
    lidx = left.valid(params.min_quality).nonzero()[0]
    ridx = right.valid(params.min_quality).nonzero()[0]
    stats["invalid_rows"] = len(left) - lidx.size + len(right) - ridx.size
    vr = right.v[ridx]
    order = vr.argsort(kind="stable")
    vr = vr[order]
    ur = right.u[ridx[order]]
    joined, stats["right_shared_rows"] = _links(ur, vr, params)
    if params.min_run_rows > 1:
        joined = joined & _in_long_pieces(ur, vr, params)[:-1]
    if lidx.size == 0 or ur.size < 2:
        stats["no_crossing"] = int(lidx.size)
        return _no_matches(stats)
    window = params.smooth_window_rows
    if window:
        lidx = lidx[left.v[lidx].argsort(kind="stable")]
    ul, vl = left.u[lidx], left.v[lidx]
    if params.min_run_rows > 1 and lidx.size:
        if not window:  # pieces are found along the rows
            order = vl.argsort(kind="stable")
            lidx, ul, vl = lidx[order], ul[order], vl[order]
        long = _in_long_pieces(ul, vl, params)
        stats["short_piece_rows"] = int(lidx.size - np.count_nonzero(long))
        if not long.all():
            lidx, ul, vl = lidx[long], ul[long], vl[long]
        if lidx.size == 0:
            return _no_matches(stats)
    if window >= 5:  # smooth_line leaves lines shorter than the window alone: no links needed then
        if len(ul) >= window:
            ul = smooth_line(ul, vl, window, _links(ul, vl, params)[0])
        ur = smooth_line(ur, vr, window, joined)
    x1 = model.undistort_left(ul, vl)
    p = model.undistort_right(ur, vr)
    ii, jj, d0, d1 = _crossings(model.epipolar_lines(x1), p, joined)
    if ii.size == 0:
        stats["no_crossing"] = int(lidx.size)
        return _no_matches(stats)
    t = d0 / (d0 - d1)
    pj = p[jj]
    x2c = pj + t[:, None] * (p[jj + 1] - pj)
    x1c = x1[ii]
    rays = model.closest_approach(x1c, x2c)
    depth = rays[2] * rays[0][:, 2]  # ray_depths
    inside = (depth >= params.depth_min_m) & (depth <= params.depth_max_m)
    n_inside = int(np.count_nonzero(inside))
    # ii is sorted (row-major crossings), so rows with a crossing start where ii changes
    new_row = ii[1:] != ii[:-1]
    rows_crossed = 1 + int(np.count_nonzero(new_row))
    stats["no_crossing"] = int(lidx.size) - rows_crossed
    if n_inside == ii.size and rows_crossed == ii.size:
        # every crossing in range and one per left row: all of them are the matches
        return Matches(lidx[ii], x1c, x2c, depth, stats, rays)
    if n_inside == ii.size:
        pick = np.arange(ii.size)
    else:
        pick = inside.nonzero()[0]
        crossings = np.bincount(ii, minlength=lidx.size)
        stats["out_of_range"] = int(np.count_nonzero((crossings > 0)
                                                     & (np.bincount(ii[pick], minlength=lidx.size) == 0)))
    ii_in = ii[pick]
    count = np.bincount(ii_in, minlength=lidx.size)
    keep = count[ii_in] == 1
    if not keep.all():  # some left rows have several crossings in range
        keep |= _resolve_by_order(ii_in, jj[pick] + t[pick], keep, count, vl, params, stats)
    pick = pick[keep]
    # a single kept row would take numpy's one-row path in closest_approach: recompute it there
    kept_rays = tuple(a[pick] for a in rays) if pick.size != 1 or ii.size == 1 else None
    return Matches(lidx[ii[pick]], x1c[pick], x2c[pick], depth[pick], stats, kept_rays)


def _no_matches(stats: dict) -> Matches:
    return Matches(np.zeros(0, dtype=np.int64), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), stats)


def _crossings(lines: AnyArray, p: AnyArray, joined: AnyArray) -> tuple:
    """All (left i, segment j) pairs where epipolar line i crosses polyline segment j, with end distances.

    Only a band of segments can cross a line: over the polyline's x extent a (near-horizontal)
    epipolar line spans the rows [ylo, yhi]; vertices above ylo (resp. below yhi) lie on one side.
    With running max/min of the vertex rows (the polyline is sorted by raw row, its undistorted
    rows almost) ``searchsorted`` finds that band exactly, so the sign test runs on N x band
    instead of N x M distances. Steep lines or wide bands fall back to the full matrix.
    """
    a, b, c = lines[:, 0:1], lines[:, 1:2], lines[:, 2:3]
    x, y = p[:, 0], p[:, 1]
    m = len(p)
    if (np.abs(lines[:, 1]) > 0.2).all():
        # line rows at the x extremes; the two columns of -(a * [xmin, xmax] + c) / b, one at a time
        ya = -(lines[:, 0] * x.min() + lines[:, 2]) / lines[:, 1]
        yb = -(lines[:, 0] * x.max() + lines[:, 2]) / lines[:, 1]
        start = np.maximum.accumulate(y).searchsorted(np.minimum(ya, yb), side="left")
        start -= 1
        np.minimum(np.maximum(start, 0, out=start), m - 2, out=start)
        stop = np.minimum.accumulate(y[::-1])[::-1].searchsorted(np.maximum(ya, yb), side="right")
        np.minimum(np.maximum(stop, 1, out=stop), m - 1, out=stop)  # segments start..stop-1
        band = stop - start
        width = int(band.max(initial=0))
        if 0 < width <= m // 3:
            # vertex window, one row per offset (width + 1, N): numpy's loops run along the N lines, not the
            # few offsets
            k = np.arange(width + 1)[:, None] + start
            np.minimum(k, m - 1, out=k)
            dist = lines[:, 0] * x[k] + lines[:, 1] * y[k] + lines[:, 2]
            valid = (np.arange(width)[:, None] < band) & joined[np.minimum(k[:-1], m - 2)]
            side = dist >= 0.0                                    # half-open: a vertex on the line counts once
            valid &= side[:-1] != side[1:]
            # crossings ordered by line, then offset (as np.nonzero of the full matrix orders them)
            ii, kk = np.divmod(valid.T.ravel().nonzero()[0], width)
            f = kk * len(lines) + ii                              # (offset, line) in the window
            flat = dist.reshape(-1)
            return ii, start[ii] + kk, flat[f], flat[f + len(lines)]
        if width == 0:
            e = np.zeros(0, dtype=np.intp)
            return e, e, np.zeros(0), np.zeros(0)
    dist = a * x[None, :] + b * y[None, :] + c                    # (N, M) signed distances [px]
    side = dist >= 0.0
    cross = (side[:, :-1] != side[:, 1:]) & joined[None, :]
    ii, jj = np.nonzero(cross)
    return ii, jj, dist[ii, jj], dist[ii, jj + 1]


def _resolve_by_order(ii: AnyArray, pos: AnyArray, unique: AnyArray, count: AnyArray, vl: AnyArray,
                      params: MatchParams, stats: dict) -> AnyArray:
    """Pick, for left points with several crossings, the one the ordering constraint allows (or none)."""
    chosen = np.zeros(ii.size, dtype=bool)
    amb = ~unique
    n_amb = int(np.count_nonzero(count > 1))
    if np.count_nonzero(unique) < 2:
        stats["ambiguous_rejected"] += n_amb
        return chosen
    # Predict the right polyline position of each left row from the unambiguous rows (monotone map).
    uv, upos = vl[ii[unique]], pos[unique]
    order = np.argsort(uv, kind="stable")
    pred = np.interp(vl[ii[amb]], uv[order], upos[order])
    dev = np.abs(pos[amb] - pred)
    cand = np.nonzero(amb)[0]
    o = np.lexsort((dev, ii[cand]))  # group by left row, best deviation first
    cand, dev = cand[o], dev[o]
    rows = ii[cand]
    first = np.ones(cand.size, dtype=bool)
    first[1:] = rows[1:] != rows[:-1]
    has_second = np.zeros(cand.size, dtype=bool)
    has_second[:-1] = first[:-1] & ~first[1:]
    second_dev = np.full(cand.size, np.inf)
    second_dev[has_second] = dev[has_second.nonzero()[0] + 1]
    ok = first & (dev <= params.max_order_dev) & (second_dev > params.max_order_dev)
    chosen[cand[ok]] = True
    stats["ambiguous_resolved"] += int(np.count_nonzero(ok))
    stats["ambiguous_rejected"] += n_amb - int(np.count_nonzero(ok))
    return chosen


def match_thesis(model: StereoModel, left: LineArrays, right: LineArrays,
                 params: MatchParams = MatchParams()) -> Matches:
    """The thesis chain (ch. 7.1.2): integer pixels, nearest right laser pixel on the epipolar line.

    The thesis distorted the epipolar line into the raw right image and looked for a laser pixel
    under it. Equivalently (and vectorised) we take, for each left pixel, the right laser pixel
    whose undistorted position is nearest to the epipolar line, if the line passes through that
    pixel (distance <= half the pixel diagonal); no interpolation between pixels. Ties in depth
    range are broken by distance, as a linear search along the line would meet the first hit.
    """
    stats = {"left_rows": len(left), "right_rows": len(right), "no_crossing": 0, "out_of_range": 0,
             "ambiguous_resolved": 0, "ambiguous_rejected": 0, "invalid_rows": 0}
    lok, rok = left.valid(params.min_quality), right.valid(params.min_quality)
    lidx = np.nonzero(lok)[0]
    if lidx.size == 0 or not rok.any():
        return Matches(np.zeros(0, dtype=np.int64), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), stats)
    x1 = model.undistort_left(np.round(left.u[lidx]), np.round(left.v[lidx]))
    p = model.undistort_right(np.round(right.u[rok]), np.round(right.v[rok]))
    lines = model.epipolar_lines(x1)
    dist = np.abs(lines[:, :2] @ p.T + lines[:, 2:3])
    # Depth of every (left, right pixel) pair, to apply the same disparity range as the sub-pixel chain.
    best = np.argmin(dist, axis=1)
    bd = dist[np.arange(lidx.size), best]
    hit = bd <= np.sqrt(0.5)
    x2 = p[best]
    rays = model.closest_approach(x1, x2)
    depth = rays[2] * rays[0][:, 2]  # ray_depths
    inside = hit & (depth >= params.depth_min_m) & (depth <= params.depth_max_m)
    stats["no_crossing"] = int(np.count_nonzero(~hit))
    stats["out_of_range"] = int(np.count_nonzero(hit & ~inside))
    pick = inside.nonzero()[0]
    # a single kept row would take numpy's one-row path in closest_approach: recompute it there
    kept_rays = tuple(a[pick] for a in rays) if pick.size != 1 or lidx.size == 1 else None
    return Matches(lidx[pick], x1[pick], x2[pick], depth[pick], stats, kept_rays)

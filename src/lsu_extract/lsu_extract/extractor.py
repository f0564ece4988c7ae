"""Laser line extraction from one camera frame: the public entry point of lsu_extract.

``extract_laser_line(image, params)`` returns one detection per image row in which the
laser was found (a near-vertical line: one centre per row), with a sub-pixel column, the
peak height, the width (FWHM) and a quality score, plus counts of the rows it searched,
rejected as ambiguous (competing peaks) and found saturated. Pixel convention (OpenCV):
(0, 0) is the centre of the top-left pixel.

Pipeline for the sub-pixel methods (all rows at once, no loop over rows or pixels):

1. coarse: every ``coarse_step_rows``-th row is searched in full for its strongest peak (on
   the signal clipped at 0, in uint8); competing peaks are resolved by continuity with clear
   neighbouring rows (tracking.py);
2. tracking window: every row within ``coarse_step_rows`` of a coarse row that found the
   line looks for its peak within ``window_px`` of the line interpolated from the coarse
   rows (the thesis' "roving eyeball");
3. fallback: rows where the window holds no clean peak are searched in full, except rows
   dark in every channel (below ``min_contrast``), which cannot hold a laser that bright;
4. refinement: a window of the signal around each integer peak gives the background (the
   lower end), the sub-pixel centre (detectors.py), the width between the half-maximum
   crossings, and for a saturated plateau the centre between those crossings.

Speed: a 640x480 frame costs about a hundred numpy/OpenCV calls on arrays of a few
thousand elements, so the call count, not the arithmetic, sets the time. Hence the fast
paths for the usual case (every coarse row found, no window at a border, no clipped pixel,
every row valid) and the linear parts of the refinement fused into one matrix product.

A pure module: numpy and OpenCV, no ROS.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from functools import lru_cache
from typing import Dict, List, Optional

import numpy as np

from .detectors import BLAIS_RIOUX_ORDER, METHOD_SUPPORT_PX, METHODS, SUBPIXEL_METHODS, THESIS
from .detectors import clamp as _clamp
from .detectors import blais_rioux_kernel, blais_rioux_zero_crossing, half_max_crossings, thesis_detector
from .image import ImageFormatError
from .signal import LaserSignal
from .tracking import BLANK, coarse_track, decide, row_candidates

# Chosen by bench/bench_extract.py: the lowest RMS column error on the simulated rig (plane and
# head, default noise; see bench/results/extract.json). On the analytic lines blais_rioux8 is
# marginally better, but its +-5 px support picks up the curvature and albedo changes of a face.
DEFAULT_METHOD = "blais_rioux4"


class ExtractorConfigError(ValueError):
    """An extractor parameter is out of range; the message names it and the valid range."""


@dataclass(frozen=True)
class ExtractorParams:
    """Tuning of the extractor (the ``laser_extractor`` node's parameters have the same names)."""

    method: str = DEFAULT_METHOD
    min_contrast: float = 30.0       # laser signal above the local background to accept a row [DN]
    ambiguity_ratio: float = 0.6     # a second peak this strong relative to the first competes with it
    min_width_px: float = 1.0        # accepted FWHM range of the laser profile [px]
    max_width_px: float = 16.0
    window_px: int = 12              # tracking window half-width [px]; 0 = search every row in full
    coarse_step_rows: int = 8        # row spacing of the coarse full-row pass
    saturation_level: int = 255      # red value at which the sensor clips [DN]
    red_threshold: int = 150         # thesis method: laser pixels have red above this ...
    blue_threshold: int = 100        # ... and blue below this [DN]

    def __post_init__(self) -> None:
        # validated once here, so the per-frame path need not check again
        for problem in param_problems(asdict(self)):
            raise ExtractorConfigError(problem)

    @property
    def refine_half_px(self) -> int:
        """Half-width of the refinement window: wide enough for the half-maximum crossings."""
        return int(math.ceil(self.max_width_px / 2.0)) + 3


def param_problems(values: Dict[str, object]) -> List[str]:
    """Readable reasons why ``values`` (parameter name -> value) are not valid extractor parameters."""
    problems: List[str] = []
    method = values.get("method", DEFAULT_METHOD)
    if method not in METHODS:
        problems.append(f"method '{method}' is unknown; must be one of: {', '.join(METHODS)}")

    def number(name: str, low: float, high: float) -> None:
        if name not in values:
            return
        value = values[name]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(float(value)):
            problems.append(f"{name} must be a finite number, got {value!r}")
        elif not low <= float(value) <= high:
            problems.append(f"{name} must be within [{low:g}, {high:g}], got {value!r}")

    number("min_contrast", 1.0, 255.0)
    number("ambiguity_ratio", 0.05, 1.0)
    number("min_width_px", 0.0, 64.0)
    number("max_width_px", 2.0, 64.0)
    number("window_px", 0, 128)
    number("coarse_step_rows", 1, 64)
    number("saturation_level", 1, 255)
    number("red_threshold", 0, 254)
    number("blue_threshold", 1, 255)
    low, high = values.get("min_width_px", 1.0), values.get("max_width_px", 16.0)
    if isinstance(low, (int, float)) and isinstance(high, (int, float)) and low >= high:
        problems.append(f"min_width_px ({low}) must be smaller than max_width_px ({high})")
    for name in ("window_px", "coarse_step_rows", "saturation_level", "red_threshold", "blue_threshold"):
        value = values.get(name)
        if value is not None and isinstance(value, float) and not value.is_integer():
            problems.append(f"{name} must be a whole number, got {value!r}")
    return problems


@dataclass(frozen=True)
class LaserLineResult:
    """The laser line found in one frame: arrays of equal length, one entry per detected row, by row."""

    method: str
    image_width: int
    image_height: int
    u: np.ndarray        # sub-pixel column of the line centre [px], float32
    v: np.ndarray        # row [px], float32
    peak: np.ndarray     # laser signal above background at the peak [DN] (thesis: red value)
    width: np.ndarray    # FWHM of the profile [px] (thesis: laser pixels in the row)
    quality: np.ndarray  # 0..1: contrast x uniqueness (x 0.8 when saturated)
    rows_searched: int = 0
    rows_ambiguous: int = 0   # rejected: two competing peaks, continuity could not choose
    rows_saturated: int = 0   # detected rows whose peak was a saturated plateau
    rows_full_search: int = 0  # rows searched in full (coarse + fallback)
    extra: Dict[str, int] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.u.size)


_FIELDS = ("u", "peak", "width", "quality", "saturated")


def _mid(params: ExtractorParams) -> float:
    return 0.5 * (params.min_width_px + params.max_width_px)


def _span(params: ExtractorParams) -> float:
    return 0.5 * (params.max_width_px - params.min_width_px)


def _profiles(signal: np.ndarray, peak_idx: np.ndarray, half: int) -> np.ndarray:
    """The ``2 * half + 1`` signal samples centred on each row's peak: (n, 2 * half + 1) float32, a copy.

    Where the window holds them all (the tracking windows always do), one strided gather of
    short contiguous runs; otherwise the samples beyond a window end repeat its edge value.
    """
    n, length = signal.shape
    size = 2 * half + 1
    if n and half <= peak_idx.min() and peak_idx.max() <= length - 1 - half:
        runs = np.ndarray((n * length - size + 1, size), signal.dtype, signal, 0, (signal.itemsize,) * 2)
        return runs[np.arange(n) * length + (peak_idx - half)]
    idx = _clamp(peak_idx[:, None] + np.arange(-half, half + 1)[None, :], 0, length - 1)
    return np.take_along_axis(signal, idx, axis=1)


@lru_cache(maxsize=32)
def _linear_features(method: str, half: int) -> np.ndarray:
    """(2 * half + 1, k) matrix: the means of the two samples at each profile end, then the method's filter if linear.

    One matrix product gives the background estimate and, for Blais-Rioux, the filter values the
    zero crossing is interpolated from: the per-op cost of numpy, not the arithmetic, is what a
    480-row frame pays for.
    """
    size = 2 * half + 1
    ends = np.zeros((size, 2), np.float32)
    ends[:2, 0] = ends[-2:, 1] = 0.5
    if method in BLAIS_RIOUX_ORDER:
        ends = np.concatenate([ends, blais_rioux_kernel(BLAIS_RIOUX_ORDER[method], size)], axis=1)
    ends.setflags(write=False)
    return ends


def _refine(signal: np.ndarray, red: np.ndarray, first: np.ndarray, peak_idx: np.ndarray,
            params: ExtractorParams, image_width: int) -> Dict[str, np.ndarray]:
    """Sub-pixel centre, peak, FWHM and contrast quality of each row's peak within its window.

    ``signal``/``red`` are (n, L) windows starting at image column ``first``, ``peak_idx`` the
    integer peak in each. Returns per-row arrays (see `_FIELDS`) and ``valid``.
    """
    half = params.refine_half_px
    profile = _profiles(signal, peak_idx, half)
    features = profile @ _linear_features(params.method, half)
    # local background: the lower of the two window ends, so a neighbouring bright patch on one
    # side does not eat the contrast
    background = np.minimum(features[:, 0], features[:, 1])
    peak = profile[:, half] - background
    left, right, found = half_max_crossings(profile, background)
    if params.method in BLAIS_RIOUX_ORDER:
        offset = blais_rioux_zero_crossing(features[:, 2], features[:, 3], features[:, 4])
    else:
        profile -= background[:, None]
        offset = SUBPIXEL_METHODS[params.method](profile)
    # The signal's argmax can sit just beside the clipped red pixels (green/blue noise), so look
    # at the peak's neighbours too; the exact test only runs when the windows clip at all.
    if red.size and red.max() >= params.saturation_level:
        near = _clamp(peak_idx[:, None] + np.arange(-1, 2)[None, :], 0, red.shape[1] - 1)
        saturated = np.take_along_axis(red, near, axis=1).max(axis=1) >= params.saturation_level
        # A clipped top has no shape to fit; the flanks are intact and symmetric, so the centre is
        # midway between the half-maximum crossings.
        offset = np.where(saturated, 0.5 * (left + right), offset)
    else:
        saturated = None
    width = right - left
    column = first + peak_idx
    u = column + offset
    # u is finite by construction (finite signal, guarded divisions); the test keeps it so for any estimator
    valid = found & (peak >= params.min_contrast) & (np.abs(width - _mid(params)) <= _span(params)) & np.isfinite(u)
    # The estimator's samples and both half-maximum crossings must lie inside the image; nearer
    # the border the profile is cut and its centre is not observable. A peak at least `half`
    # columns from both borders has all of them inside (margin and crossings are within +-half).
    if column.min() < half or column.max() > image_width - 1 - half:
        margin = METHOD_SUPPORT_PX[params.method]
        valid &= ~((column < margin) | (column > image_width - 1 - margin) |
                   (column + left < 0.0) | (column + right > image_width - 1.0))
    quality = _clamp((peak - params.min_contrast) * (0.5 / params.min_contrast), 0.0, 1.0)
    if saturated is not None:
        quality = np.where(saturated, 0.8 * quality, quality)
    return {"u": u, "peak": peak, "width": width, "quality": quality, "saturated": saturated, "valid": valid}


def _keep(rows: np.ndarray, fit: Dict[str, Optional[np.ndarray]],
          uniqueness: Optional[np.ndarray] = None) -> Dict[str, np.ndarray]:
    """The valid rows of one refinement, with quality scaled by ``uniqueness`` when given."""
    ok = fit["valid"]
    if ok.all():  # the usual tracking result: nothing to drop
        kept = {name: fit[name] for name in ("u", "peak", "width", "quality")}
        kept["v"] = rows
    else:
        kept = {name: fit[name][ok] for name in ("u", "peak", "width", "quality")}  # type: ignore[index]
        kept["v"] = rows[ok]
    saturated = fit["saturated"]
    kept["saturated"] = np.zeros(kept["v"].shape, bool) if saturated is None else saturated[ok]
    if uniqueness is not None:
        kept["quality"] = kept["quality"] * uniqueness[ok]
    return kept


def extract_laser_line(image: np.ndarray, params: Optional[ExtractorParams] = None,
                       texture: Optional[np.ndarray] = None) -> LaserLineResult:
    """Find the laser line in a BGR (H, W, 3) or mono (H, W) uint8 frame.

    Args:
        image: the laser frame (decode ROS buffers with `lsu_extract.image.decode_image`).
        params: detector and thresholds (defaults: `ExtractorParams()`).
        texture: optional laser-off frame of the same view; the signal becomes the red
            difference, which cancels red objects and ambient light.

    Raises:
        ExtractorConfigError: a parameter is out of range.
        ImageFormatError: the image is not a uint8 BGR/mono array, or the texture frame does not match.
    """
    params = params or ExtractorParams()
    sig = LaserSignal(image, texture)
    height, width = sig.height, sig.width
    if params.method == THESIS:
        line = thesis_detector(sig.image, params.red_threshold, params.blue_threshold)
        return LaserLineResult(method=THESIS, image_width=width, image_height=height, u=line.u, v=line.v,
                               peak=line.peak, width=line.width, quality=line.quality, rows_searched=height,
                               rows_saturated=int(np.count_nonzero(line.peak >= params.saturation_level)),
                               rows_full_search=height)
    half = params.refine_half_px
    if width < 2 * half + 1:
        raise ImageFormatError(f"image is {width} px wide; the extractor needs at least {2 * half + 1} px "
                               f"(or a smaller max_width_px)")
    step = params.coarse_step_rows
    chunks: List[Dict[str, np.ndarray]] = []
    full_searched = 0
    pending: Optional[np.ndarray] = None  # None = every row
    if params.window_px > 0:
        w = params.window_px
        coarse = slice(min(step // 2, height - 1), height, step)
        coarse_rows = np.arange(height)[coarse]
        cand = row_candidates(sig.rows_clipped(coarse), coarse_rows, half, params.min_contrast)
        full_searched += coarse_rows.size
        pick = decide(cand, params.min_contrast, params.ambiguity_ratio, w, np.empty(0, np.int64),
                      np.empty(0), 2 * step)
        rows_w, guess = coarse_track(height, coarse_rows, pick.column, step)
        if rows_w.size:
            centre = np.rint(guess).astype(np.int64)
            reach = w + half  # the window holds the search region (+-w) and, beyond it, the refinement's +-half
            s, red, first = sig.windows(rows_w, centre - reach, 2 * reach + 1)
            if reach <= centre.min() and centre.max() <= width - 1 - reach:
                # no window was shifted at a border: the search region is the same slice in every row
                rel = reach
                peak_idx = np.argmax(s[:, half:half + 2 * w + 1], axis=1) + half
            else:
                rel = centre - first
                region = np.abs(np.arange(s.shape[1])[None, :] - rel[:, None]) <= w
                peak_idx = np.argmax(np.where(region, s, BLANK), axis=1)
            fit = _refine(s, red, first, peak_idx, params, width)
            # a peak on the region's edge may be a slope rising towards something outside: search the row
            fit["valid"] &= np.abs(peak_idx - rel) < w
            chunks.append(_keep(rows_w, fit))
        if chunks and chunks[0]["v"].size == height:
            pending = np.zeros(0, np.int64)
        elif chunks:
            missing = np.ones(height, bool)
            missing[chunks[0]["v"]] = False
            pending = np.flatnonzero(missing)
    ambiguous = 0
    if pending is None:
        pending = np.arange(height)
    if pending.size:
        pending = pending[sig.may_hold_laser(pending, params.min_contrast)]
    if pending.size:
        cand = row_candidates(sig.rows(pending), pending, half, params.min_contrast)
        full_searched += pending.size
        known_rows = chunks[0]["v"] if chunks else np.empty(0, np.int64)
        known_cols = chunks[0]["u"] if chunks else np.empty(0)
        pick = decide(cand, params.min_contrast, params.ambiguity_ratio, max(params.window_px, half),
                      known_rows, known_cols, 2 * step)
        ambiguous = int(np.count_nonzero(pick.ambiguous))
        ok = pick.column >= 0
        rows_f = pending[ok]
        if rows_f.size:
            s, red, first = sig.windows(rows_f, pick.column[ok] - half, 2 * half + 1)
            fit = _refine(s, red, first, pick.column[ok] - first, params, width)
            chunks.append(_keep(rows_f, fit, pick.uniqueness[ok]))
    if len(chunks) == 1:
        found = chunks[0]
    elif chunks:
        order = np.argsort(np.concatenate([c["v"] for c in chunks]), kind="stable")
        found = {name: np.concatenate([c[name] for c in chunks])[order] for name in ("v", *_FIELDS)}
    else:
        found = {name: np.zeros(0, bool if name == "saturated" else np.float32) for name in ("v", *_FIELDS)}
    return LaserLineResult(
        method=params.method, image_width=width, image_height=height,
        u=found["u"].astype(np.float32), v=found["v"].astype(np.float32),
        peak=found["peak"].astype(np.float32, copy=False), width=found["width"].astype(np.float32, copy=False),
        quality=found["quality"].astype(np.float32, copy=False),
        rows_searched=height, rows_ambiguous=ambiguous,
        rows_saturated=int(np.count_nonzero(found["saturated"])), rows_full_search=full_searched)

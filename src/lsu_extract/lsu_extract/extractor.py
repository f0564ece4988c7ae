"""Laser line extraction from one camera frame: the public entry point of lsu_extract.

``extract_laser_line(image, params)`` returns one detection per image row in which the
laser was found (a near-vertical line: one centre per row), with a sub-pixel column, the
peak height, the width (FWHM) and a quality score, plus counts of the rows it searched,
rejected as ambiguous (competing peaks) and found saturated. Pixel convention (OpenCV):
(0, 0) is the centre of the top-left pixel.

Pipeline for the sub-pixel methods (all rows at once, no loop over rows or pixels):

1. coarse: every ``coarse_step_rows``-th row is searched in full for its strongest peak;
   competing peaks are resolved by continuity with clear neighbouring rows (tracking.py);
2. tracking window: every row looks for its peak within ``window_px`` of the line
   interpolated from the coarse rows (the thesis' "roving eyeball");
3. fallback: rows where the window holds no clean peak are searched in full;
4. refinement: a window of the background-subtracted signal around each integer peak gives
   the sub-pixel centre (detectors.py), the half-maximum crossings give the width, and a
   saturated plateau is centred between its half-maximum crossings.

A pure module: numpy only, no ROS.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Dict, List, Optional

import numpy as np

from .detectors import METHOD_SUPPORT_PX, METHODS, SUBPIXEL_METHODS, THESIS
from .detectors import clamp as _clamp
from .detectors import half_max_crossings, thesis_detector
from .signal import LaserSignal
from .tracking import decide, interpolate_track, row_candidates

# Chosen by bench/bench_extract.py: the lowest RMS column error on the analytic lines at
# default noise and within the time budget (see bench/results/extract.json).
DEFAULT_METHOD = "blais_rioux8"


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


def _empty(n: int) -> np.ndarray:
    return np.zeros(n, np.float32)


class _Rows:
    """Accumulates per-row detections (NaN u = none yet)."""

    def __init__(self, height: int) -> None:
        self.u = np.full(height, np.nan, np.float64)
        self.peak = _empty(height)
        self.width = _empty(height)
        self.quality = _empty(height)
        self.saturated = np.zeros(height, bool)

    def put(self, rows: np.ndarray, fit: Dict[str, np.ndarray], uniqueness: np.ndarray) -> None:
        ok = fit["valid"]
        r = rows[ok]
        self.u[r] = fit["u"][ok]
        self.peak[r] = fit["peak"][ok]
        self.width[r] = fit["width"][ok]
        self.quality[r] = (fit["quality"] * uniqueness)[ok]
        self.saturated[r] = fit["saturated"][ok]


def _refine(signal: np.ndarray, red: np.ndarray, first: np.ndarray, peak_idx: np.ndarray,
            params: ExtractorParams, image_width: int) -> Dict[str, np.ndarray]:
    """Sub-pixel centre, peak, FWHM and contrast quality of each row's peak within its window."""
    n, length = signal.shape
    half = params.refine_half_px
    rows = np.arange(n)
    idx = _clamp(peak_idx[:, None] + np.arange(-half, half + 1)[None, :], 0, length - 1)
    profile = np.take_along_axis(signal, idx, axis=1).astype(np.float32)
    # local background: the lower of the two window ends, so a neighbouring bright patch on one
    # side does not eat the contrast
    background = np.minimum(profile[:, :2].mean(axis=1), profile[:, -2:].mean(axis=1))
    profile -= background[:, None]
    peak = profile[:, half]
    left, right, found = half_max_crossings(profile)
    # the signal's argmax can sit just beside the clipped red pixels (green/blue noise), so look
    # at the peak's neighbours too
    near = _clamp(peak_idx[:, None] + np.arange(-1, 2)[None, :], 0, length - 1)
    saturated = np.take_along_axis(red, near, axis=1).max(axis=1) >= params.saturation_level
    offset = SUBPIXEL_METHODS[params.method](profile)
    # A clipped top has no shape to fit; the flanks are intact and symmetric, so the centre is
    # midway between the half-maximum crossings.
    offset = np.where(saturated, 0.5 * (left + right), offset)
    width = right - left
    column = first + peak_idx
    u = column + offset
    # The estimator's samples and both half-maximum crossings must lie inside the image;
    # nearer the border the profile is cut and its centre is not observable.
    margin = METHOD_SUPPORT_PX[params.method]
    on_border = ((column < margin) | (column > image_width - 1 - margin) |
                 (column + left < 0.0) | (column + right > image_width - 1.0))
    valid = (found & (peak >= params.min_contrast) & (width >= params.min_width_px) &
             (width <= params.max_width_px) & ~on_border & np.isfinite(u))
    quality = _clamp((peak - params.min_contrast) / (2.0 * params.min_contrast), 0.0, 1.0)
    quality = np.where(saturated, 0.8 * quality, quality)
    return {"u": u, "peak": peak, "width": width, "quality": quality, "saturated": saturated, "valid": valid}


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
        from .image import ImageFormatError
        raise ImageFormatError(f"image is {width} px wide; the extractor needs at least {2 * half + 1} px "
                               f"(or a smaller max_width_px)")
    out = _Rows(height)
    all_rows = np.arange(height)
    step = params.coarse_step_rows
    full_searched = 0
    pending = all_rows
    if params.window_px > 0:
        w = params.window_px
        coarse = np.arange(min(step // 2, height - 1), height, step)
        cand = row_candidates(sig.rows(coarse), coarse, half)
        full_searched += coarse.size
        pick = decide(cand, params.min_contrast, params.ambiguity_ratio, w, np.empty(0, np.int64),
                      np.empty(0), 2 * step)
        ok = pick.column >= 0
        guess = interpolate_track(all_rows.astype(np.float64), coarse[ok].astype(np.float64),
                                  pick.column[ok].astype(np.float64), step)
        has = ~np.isnan(guess)
        rows_w = all_rows[has]
        if rows_w.size:
            centre = np.rint(guess[has]).astype(np.int64)
            length = 2 * (w + half) + 1
            s, red, first = sig.windows(rows_w, centre - w - half, length)
            rel = centre - first
            region = np.abs(np.arange(s.shape[1])[None, :] - rel[:, None]) <= w
            peak_idx = np.argmax(np.where(region, s, np.iinfo(np.int16).min), axis=1)
            inside = np.abs(peak_idx - rel) < w  # a peak on the window edge may be a slope: search the row
            fit = _refine(s, red, first, peak_idx, params, width)
            fit["valid"] &= inside
            out.put(rows_w, fit, np.ones(rows_w.size))
        pending = all_rows[np.isnan(out.u)]
    ambiguous = 0
    if pending.size:
        cand = row_candidates(sig.rows(pending), pending, half)
        full_searched += pending.size
        found = ~np.isnan(out.u)
        pick = decide(cand, params.min_contrast, params.ambiguity_ratio, max(params.window_px, half),
                      all_rows[found], out.u[found], 2 * step)
        ambiguous = int(np.count_nonzero(pick.ambiguous))
        ok = pick.column >= 0
        rows_f = pending[ok]
        if rows_f.size:
            s, red, first = sig.windows(rows_f, pick.column[ok] - half, 2 * half + 1)
            fit = _refine(s, red, first, pick.column[ok] - first, params, width)
            out.put(rows_f, fit, pick.uniqueness[ok])
    rows = np.nonzero(~np.isnan(out.u))[0]
    return LaserLineResult(
        method=params.method, image_width=width, image_height=height,
        u=out.u[rows].astype(np.float32), v=rows.astype(np.float32), peak=out.peak[rows],
        width=out.width[rows], quality=out.quality[rows], rows_searched=height, rows_ambiguous=ambiguous,
        rows_saturated=int(np.count_nonzero(out.saturated[rows])), rows_full_search=full_searched)

"""Laser line extraction from one camera frame: the public entry point of lsu_extract.

``extract_laser_line(image, params)`` returns one detection per image row in which the
laser was found (a near-vertical line: one centre per row), with a sub-pixel column, the
peak height, the width (FWHM) and a quality score, plus counts of the rows it searched,
rejected as ambiguous (competing peaks) and found saturated. Pixel convention (OpenCV):
(0, 0) is the centre of the top-left pixel.

Pipeline for the sub-pixel methods (all rows at once, no loop over rows or pixels):

1. coarse: every ``coarse_step_rows``-th row is searched in full for its strongest peak (on
   the signal clipped at 0, in uint8; on a mono frame the peak highest above its own surroundings,
   `tracking.local_candidates`); competing peaks are resolved by continuity with clear
   neighbouring rows (tracking.py);
2. tracking window: every row within ``coarse_step_rows`` of a coarse row that found the
   line looks for its peak within ``window_px`` of the line interpolated from the coarse
   rows (the thesis' "roving eyeball");
3. fallback: rows where the window holds no clean peak are searched in full, except rows
   dark in every channel (below ``min_contrast``), which cannot hold a laser that bright;
4. refinement: a window of the signal around each integer peak gives the background (the
   lower end), the sub-pixel centre (detectors.py) and the width (the equivalent width of the
   profile, see `_fit`); the half-maximum crossings are walked for the rows that need them,
   and give a saturated plateau its centre; the default ``adaptive`` method then centres each
   unclipped row by the model its measured width fits (`detectors.adaptive_offset`;
   `explain_rows` says which and why);
5. continuity: a weak detection that no detection in the neighbouring rows continues is noise
   (`drop_isolated`).

Speed: a 640x480 frame costs some 80 numpy/OpenCV calls on arrays of a few thousand
elements, so the call count, not the arithmetic, sets the time. Hence the fast paths for the
usual case (every coarse row found, no window at a border, no clipped pixel, every row
valid), the tracking windows kept column-major so that the per-row peak search is one
reduction over axis 0 (`_track`), and every linear feature of the refinement (background,
peak, width, width range, the Blais-Rioux filter) fused into one matrix product.

A pure module: numpy and OpenCV, no ROS.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from functools import lru_cache
from typing import Any

import cv2
import numpy as np

from lsu_common.arrays import AnyArray

from .detectors import (
    ADAPTIVE,
    ADAPTIVE_WIDTH_PX,
    BLAIS_RIOUX_ORDER,
    METHOD_SUPPORT_PX,
    METHODS,
    SUBPIXEL_METHODS,
    THESIS,
    blais_rioux_crossing,
    blais_rioux_kernel,
    com_offset,
    half_max_crossings,
    thesis_detector,
)
from .detectors import clamp as _clamp
from .image import ImageFormatError
from .signal import LaserSignal, contrast_noise
from .tracking import BLANK, coarse_track, decide, row_candidates

# Chosen by bench/study_extract.py, leave-one-set-out over the real development sets (weld stripes, the
# turntable's globe and box, two photographs) and the simulated rig's frames: the candidate whose worst
# set is best (bench/results/study_extract.json). The adaptive method takes Blais-Rioux 4 on narrow lines
# (the rig's 3-4 px) and the centre of mass above half height on wider ones (real photographs' 5-12 px),
# row by row from the width it measures; every fold of the study chose it on the sets it was not tested on.
DEFAULT_METHOD = "adaptive"
# Where red clips, how the centre is found on a colour frame without a laser-off frame. The sensor's
# colour crosstalk lifts green and blue in proportion to the laser (a few to 15 % of red), which only
# scales red - max(green, blue) while red follows the laser; once red clips, green and blue still
# rise and the signal's top bends into a plateau or a dip (real photographs: +20-50 DN in the core),
# which no peak fit can centre. Such rows are centred midway between the half-maximum crossings of
# the flanks: "signal": the signal's (robust where red clips on a bright white background too),
# "red": red's own, which crosstalk does not bend (better on the saturated real photograph, worse
# where daylight clips red around the line; bench/results/extract.json). JPEG-softened cameras top
# out at 250-254 instead of 255, hence the default saturation_level of 250.
CLIPPED_CENTRE = ("signal", "red")
# The contrast threshold of a frame. A fixed one (min_contrast, 30 DN) loses a faint line on a
# quiet frame (real photographs: 14 DN on dark surfaces), and lowered for every frame it accepts
# texture on a busy one. So each frame measures the noise of the very contrast it thresholds
# (`contrast_noise`, a robust sigma over a quarter of the coarse rows, which the coarse search reads
# anyway) and accepts contrast_sigmas (8) of it where that is below min_contrast; never below
# NOISE_FLOOR_DN, under which the 8-bit quantisation of smoothed webcam pictures says nothing.
NOISE_FLOOR_DN = 12.0
# A laser line is continuous from row to row. A weak detection (below ISOLATED_WEAK x the frame's threshold) that no
# detection within +-CONTINUITY_ROWS rows continues (at most CONTINUITY_PX_PER_ROW px per row of distance) is taken
# on noise: on a dark frame the threshold falls to NOISE_FLOOR_DN, where single rows at the faint end of a line (a
# sphere's limb) came from noise (bench_reconstruct's sphere; bench_extract's rig and real false rows).
ISOLATED_WEAK = 2.0
CONTINUITY_ROWS = 2
CONTINUITY_PX_PER_ROW = 3.0
# A line profile is symmetric about its centre; one cut by a silhouette (a sphere's limb, where the laser grazes the
# surface and the occluding contour clips one flank) or merged with a patch beside it is not. The adaptive method
# measures this per row as the distance between the Blais-Rioux centre and the centroid of the whole refinement
# window above the straight line through its ends; beyond SKEW_PX such a row is centred by the centre of mass above
# half height, which on the simulated sphere's limb rows is the less biased of the two (bench_reconstruct's
# sphere_radius_err_mm); a smaller SKEW_PX flags noise on weak narrow rows (bench_reconstruct's plane sigma).
SKEW_PX = 0.8
# red_rise_ratio. Laser light adds to a surface: red rises over the surface around the line, green and blue by
# their crosstalk (>= 0). The signal red - max(green, blue) also rises where green and blue fall: red print, a
# sticker, a label on a lighter ground, whose red does not rise (or less than the signal). So on a colour frame
# without a laser-off frame a row is accepted only where red itself rises over the window's lower end by at least
# red_rise_ratio x the signal's contrast (a laser's red rises by about that contrast or more, such print's hardly at
# all; bench/results/extract.json, *_red_rise_off); a row whose red clips at the peak cannot show its rise and is
# exempt. With a laser-off frame the signal is red's rise already.


class ExtractorConfigError(ValueError):
    """An extractor parameter is out of range; the message names it and the valid range."""


@dataclass(frozen=True)
class ExtractorParams:
    """Tuning of the extractor (the ``laser_extractor`` node's parameters have the same names)."""

    method: str = DEFAULT_METHOD
    min_contrast: float = 30.0       # laser signal above the local background to accept a row [DN] ...
    contrast_sigmas: float = 8.0     # ... lowered to this many noise sigmas of a quieter frame (0: fixed), `NOISE_FLOOR_DN`
    ambiguity_ratio: float = 0.6     # a second peak this strong relative to the first competes with it
    min_width_px: float = 1.0        # accepted FWHM range of the laser profile [px]
    max_width_px: float = 16.0
    window_px: int = 12              # tracking window half-width [px]; 0 = search every row in full
    coarse_step_rows: int = 8        # row spacing of the coarse full-row pass
    saturation_level: int = 250      # red value from which the sensor (or its JPEG-softened picture) clips [DN]
    clipped_centre: str = "signal"   # where red clips: centre between the flanks of the signal, or of red
    adaptive_width_px: float = ADAPTIVE_WIDTH_PX  # blais_rioux / adaptive: wider rows (FWHM) take the 8th order / com
    grow_wide: bool = True           # follow the line row by row from its detections, up to GROW_MAX_WIDTH_PX wide
    red_rise_ratio: float = 0.5      # colour, no laser-off frame: red must rise this x the signal's contrast (0: off)
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


def param_problems(values: dict[str, object]) -> list[str]:
    """Readable reasons why ``values`` (parameter name -> value) are not valid extractor parameters."""
    problems: list[str] = []
    method = values.get("method", DEFAULT_METHOD)
    if method not in METHODS:
        problems.append(f"method '{method}' is unknown; must be one of: {', '.join(METHODS)}")
    clipped = values.get("clipped_centre", "signal")
    if clipped not in CLIPPED_CENTRE:
        problems.append(f"clipped_centre '{clipped}' is unknown; must be one of: {', '.join(CLIPPED_CENTRE)}")

    def number(name: str, low: float, high: float) -> None:
        if name not in values:
            return
        value = values[name]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(float(value)):
            problems.append(f"{name} must be a finite number, got {value!r}")
        elif not low <= float(value) <= high:
            problems.append(f"{name} must be within [{low:g}, {high:g}], got {value!r}")

    number("min_contrast", 1.0, 255.0)
    number("contrast_sigmas", 0.0, 100.0)
    number("ambiguity_ratio", 0.05, 1.0)
    number("adaptive_width_px", 1.0, 64.0)
    number("red_rise_ratio", 0.0, 2.0)
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
    u: AnyArray        # sub-pixel column of the line centre [px], float32
    v: AnyArray        # row [px], float32
    peak: AnyArray     # laser signal above background at the peak [DN] (thesis: red value)
    width: AnyArray    # FWHM of the profile [px]: its equivalent width, or half-maximum crossings (see _fit)
    #                      (thesis: laser pixels in the row)
    quality: AnyArray  # 0..1: contrast x uniqueness (x 0.8 when saturated)
    rows_searched: int = 0
    rows_ambiguous: int = 0   # rejected: two competing peaks, continuity could not choose
    rows_saturated: int = 0   # detected rows whose peak was a saturated plateau
    rows_full_search: int = 0  # rows searched in full (coarse + fallback)
    extra: dict[str, int] = field(default_factory=dict)
    saturated: AnyArray | None = None  # per detected row: its peak was a clipped plateau (None: no row clipped)
    skewed: AnyArray | None = None     # per detected row: adaptive, centred as an asymmetric profile (`SKEW_PX`)

    def __len__(self) -> int:
        return int(self.u.size)


_FIELDS = ("u", "peak", "width", "quality")  # per-row outputs; plus the `_FLAGS` and "valid"
_FLAGS = ("saturated", "skewed")  # per-row flags, None where no row has them: a clipped peak; centred as skewed (`SKEW_PX`)


def _mid(params: ExtractorParams) -> float:
    return 0.5 * (params.min_width_px + params.max_width_px)


def _span(params: ExtractorParams) -> float:
    return 0.5 * (params.max_width_px - params.min_width_px)


# Area of a Gaussian of unit height per unit FWHM: sqrt(pi / (4 ln 2)). The equivalent width
# area / peak of a Gaussian profile is its FWHM times this.
GAUSSIAN_AREA_PER_FWHM = math.sqrt(math.pi / (4.0 * math.log(2.0)))
_TINY = 1e-6  # a Python float: numpy's fast path for scalars, and it keeps float32 float32


@lru_cache(maxsize=16)
def _peak_search_layout(rows: int, n: int, w: int) -> tuple[AnyArray, int, AnyArray, AnyArray]:
    """Cached read-only tables for `_peak_search` over a (rows, n) search region (rows = 2 w + 1).

    Returns (codes, bits, offset, interior): ``codes[j, i] = j * n + i``, the flat index that
    `_peak_search` returns and that the strided profile view of `_column_profiles` takes;
    ``bits`` how many low bits hold it; ``offset[j * n + i] = j - w``, the peak's column
    relative to the region's centre; ``interior[j * n + i]``: j is not on the region's edge.
    """
    bits = max(1, (rows * n - 1).bit_length())
    # the signal (-255..255) shifted left by `bits` must fit the key type
    dtype = np.int32 if bits <= 22 else np.int64
    codes = np.arange(rows * n, dtype=dtype).reshape(rows, n)
    offset = np.repeat(np.arange(-w, rows - w), n)
    interior = (offset > -w) & (offset < rows - 1 - w)
    for table in (codes, offset, interior):
        table.setflags(write=False)
    return codes, bits, offset, interior


def _peak_search(values: AnyArray, codes: AnyArray, bits: int) -> AnyArray:
    """``argmax(values, axis=0) * n + arange(n)`` of integer ``values`` (m, n): the first maximum on ties.

    numpy's argmax over axis 0 copies to make the axis contiguous, then loops per column: ~30 us
    for 25 x 480, then two more calls make the flat index. Instead each value is shifted left
    and its flat index (``codes``, `_peak_search_layout`) subtracted: of equal values the
    first row keeps the smallest key, and one min over axis 0, a vector operation per row,
    finds the largest value with its index in the low bits. Exact: the values are integers
    (the signal, -255..255, which `_peak_search_layout` sizes the key type for).
    """
    keys = codes - (values.astype(codes.dtype) << bits)
    return keys.min(axis=0) & ((1 << bits) - 1)


def _column_profiles(signal: AnyArray, flat_index: AnyArray, size: int) -> AnyArray:
    """``size`` samples down each column ``i`` of a column-major window from ``flat_index[i] = j * n + i``.

    Returns (n, size) float32: rows ``j .. j + size - 1`` of column ``i``. A strided view
    whose entry ``q`` holds the ``size`` samples from flat index ``q`` down one column (stride:
    one window row) turns the gather into one fancy index of n entries.
    """
    length, n = signal.shape
    item = signal.itemsize
    runs = np.ndarray(((length - size + 1) * n, size), signal.dtype, signal, 0, (item, item * n))
    return runs[flat_index].astype(np.float32)


@lru_cache(maxsize=16)
def _track_starts(height: int, width: int, reach: int) -> AnyArray:
    """``arange(height) * width - reach`` (cached, read-only): flat window starts of every row, less the centre column."""
    starts = np.arange(height) * width - reach
    starts.setflags(write=False)
    return starts


def _profiles(signal: AnyArray, peak_idx: AnyArray, half: int) -> AnyArray:
    """The ``2 * half + 1`` signal samples centred on each row's peak: (n, 2 * half + 1) float32, a copy.

    Where the window holds them all, one strided gather of short contiguous runs; otherwise
    (windows shifted at a border) the samples beyond a window end repeat its edge value.
    """
    n, length = signal.shape
    size = 2 * half + 1
    if n and half <= peak_idx.min() and peak_idx.max() <= length - 1 - half:
        runs = np.ndarray((n * length - size + 1, size), signal.dtype, signal, 0, (signal.itemsize,) * 2)
        return runs[np.arange(n) * length + (peak_idx - half)]
    idx = _clamp(peak_idx[:, None] + np.arange(-half, half + 1)[None, :], 0, length - 1)
    return np.take_along_axis(signal, idx, axis=1)


def _red_rise(centre: AnyArray, left: AnyArray, left_in: AnyArray, right_in: AnyArray, right: AnyArray) -> AnyArray:
    """Red's height at a peak above the lower of the two window ends (each the mean of its two outer samples), as
    rows 0 and 1 of `_linear_features` measure the signal's: from the five samples that enter it, float32."""
    c = centre.astype(np.float32)
    return np.maximum(c - 0.5 * (left.astype(np.float32) + left_in), c - 0.5 * (right.astype(np.float32) + right_in))


@lru_cache(maxsize=32)
def _linear_features(method: str, half: int, min_width: float, max_width: float) -> AnyArray:
    """(k, 2 * half + 1) matrix of linear features of a profile: ``matrix @ profile.T`` gives all of them.

    Rows: 0, 1: the centre sample's height above the mean of the two samples at the left /
    right window end (the peak is the larger: the background is the lower end); 2: the area
    above the straight line through the two end means, over `GAUSSIAN_AREA_PER_FWHM`; 3: the
    centre sample's height above that line (2 / 3 is the width); 4..7: the shortcut test of
    `_fit`, all > 0 when it holds: 4 x row 0 - 3 x row 1 and 4 x row 1 - 3 x row 0 (the end
    means differ by less than a quarter of the peak), row 2 - ``min_width`` x row 3 and
    ``max_width`` x row 3 - row 2 (the width is within those bounds); then, for Blais-Rioux,
    -g(0), g(0) - g(-1) and g(+1) - g(0) of its filter g (`blais_rioux_crossing`); for the adaptive method last
    the first moment above that line over `GAUSSIAN_AREA_PER_FWHM` (divided by row 2: the window's centroid, `SKEW_PX`).

    Each would be a few numpy calls of its own; the per-call cost of numpy, not the
    arithmetic, is what a 480-row frame pays for. Rows 0, 1, 4 and 5 have weights that are
    multiples of 0.5 (up to 4), so on the integer-valued signal they are exact. One row per
    feature: the products come out as contiguous rows, which the elementwise calls after it
    read faster than strided columns.
    """
    size = 2 * half + 1
    rows = np.zeros((8, size), np.float64)
    rows[0, :2] = rows[1, -2:] = -0.5
    rows[:2, half] = 1.0
    line = np.zeros(size)
    line[:2] = line[-2:] = 0.25  # the mean of the two end means: the line's mean height
    rows[2] = (1.0 - size * line) / GAUSSIAN_AREA_PER_FWHM
    rows[3] = -line
    rows[3, half] += 1.0
    rows[4] = 4.0 * rows[0] - 3.0 * rows[1]
    rows[5] = 4.0 * rows[1] - 3.0 * rows[0]
    rows[6] = rows[2] - min_width * rows[3]
    rows[7] = max_width * rows[3] - rows[2]
    for order in BLAIS_RIOUX_ORDER.get(method, ()):
        g = blais_rioux_kernel(order, size).T.astype(np.float64)  # g(-1), g(0), g(+1)
        rows = np.concatenate([rows, [-g[1], g[1] - g[0], g[2] - g[1]]])
    if method == ADAPTIVE:
        # first moment about the centre above the straight line through the two end means (`SKEW_PX`): the
        # line's constant part has no moment about the centre, its slope (R - L) / (size - 2) has sum x^2 x slope
        x = np.arange(-half, half + 1, dtype=np.float64)
        moment = x.copy()
        moment[:2] += np.sum(x * x) / (size - 2) * 0.5
        moment[-2:] -= np.sum(x * x) / (size - 2) * 0.5
        rows = np.concatenate([rows, [moment / GAUSSIAN_AREA_PER_FWHM]])
    matrix = rows.astype(np.float32)
    matrix.setflags(write=False)
    return matrix


def _shortcut_widths(params: ExtractorParams) -> tuple[float, float]:
    """The equivalent widths for which `_fit` skips the half-maximum crossings: the accepted range less a margin.

    The equivalent width and the crossings agree within ~0.2 px on a Gaussian line up to 8 px;
    wider, the window truncates the tails and the equivalent width reads up to ~4 px less at
    16 px. Rows nearer the limits than that are measured by the crossings, so that acceptance
    does not depend on which estimate a row got.
    """
    return params.min_width_px + 1.0, params.max_width_px - 4.0


def _fit(profile: AnyArray, column: AnyArray, saturated: AnyArray | None, params: ExtractorParams,
         image_width: int, accept: AnyArray | None = None, inside: bool = False,
         shape: AnyArray | None = None, red_rise: AnyArray | None = None) -> dict[str, AnyArray | None]:
    """Sub-pixel centre, peak, width and contrast quality of each row's profile around its integer peak.

    ``profile`` is (n, 2 * half + 1) float32, the signal around image column ``column`` (its
    centre sample); ``saturated`` flags rows whose peak is a clipped plateau (None: none is);
    ``accept``: rows the caller has already rejected are False (None: all accepted);
    ``inside``: the caller knows every column is at least ``half`` from both borders;
    ``shape``: the red channel around the same columns, given where red clips (``saturated``):
    those rows are centred on its flanks (`CLIPPED_CENTRE`); contrast, width and acceptance are
    always the signal's; ``red_rise``: red's own rise at each peak (`_red_rise`), given for a colour
    frame without a laser-off frame: rows where red does not rise (``red_rise_ratio``) are rejected.
    Returns per-row arrays (see `_FIELDS`) and ``valid`` (None: every row is valid).

    Width: walking out to the half-maximum crossings costs a dozen numpy calls, so the usual
    row takes its width from the matrix product instead: the equivalent width (area / height
    above the straight line through the window ends) over `GAUSSIAN_AREA_PER_FWHM`, which is the
    FWHM of a Gaussian line on a linear background (within ~0.1 px of the crossings up to 8 px;
    a wider line is truncated by the window and reads narrower). The crossings are walked, and
    give the width and the acceptance, for the rows where that shortcut is not sound:

    - a saturated plateau: its clipped top says nothing of the area; its centre is midway
      between the crossings;
    - window ends more than a quarter of the peak apart: a step or a neighbouring patch in the
      background, which the line does not model. Closer ends also guarantee what the walk
      checks, a sample below half height on each side (both end means are below it);
    - an equivalent width out of range or near its ends (`_shortcut_widths`): acceptance is
      decided by the crossings, as before, so the shortcut neither loses a row nor, where the
      two estimates differ a little (a hot pixel, a noisy broad bump), adds one;
    - rows near the image border, whose crossings must lie inside the image.
    """
    half = params.refine_half_px
    matrix = _linear_features(params.method, half, *_shortcut_widths(params))
    features = matrix @ profile.T
    # height above the local background, the lower of the two window ends, so that a
    # neighbouring bright patch on one side does not eat the contrast
    peak = np.maximum(features[0], features[1])
    strong = peak >= params.min_contrast
    if accept is not None:
        strong &= accept
    if red_rise is not None:
        # red's own rise over the lower window end (``red_rise_ratio``); a clipped red peak is exempt
        rises = red_rise >= params.red_rise_ratio * peak
        strong &= rises if saturated is None else rises | saturated
    # Nearly level ends (then the height above the line is > 0 too) and the width well in range.
    # With peak = max(row 0, row 1) > 0, |end difference| = |row 0 - row 1| < peak / 4 is the
    # same as min(row 0, row 1) > 3/4 max(row 0, row 1): two linear rows > 0, like the width.
    shortcut = np.minimum.reduce(features[4:8], axis=0) > 0.0
    valid = strong & shortcut
    width = features[2] / np.maximum(features[3], _TINY)
    if params.method in BLAIS_RIOUX_ORDER:
        offset = blais_rioux_crossing(features[8], features[9], features[10])
        if len(BLAIS_RIOUX_ORDER[params.method]) == 2:  # blais_rioux: the 8th order on the wider lines
            offset = np.where(width > params.adaptive_width_px, blais_rioux_crossing(features[11], features[12], features[13]),
                              offset)
    else:
        offset = SUBPIXEL_METHODS[params.method](profile - (profile[:, half] - peak)[:, None])
    n = valid.size
    if saturated is None and (inside or half <= column.min() and column.max() <= image_width - 1 - half) \
            and np.count_nonzero(valid) == n:
        all_valid = True  # the usual tracking result: no crossing to walk, no row to drop
    else:
        all_valid = False
        walk = strong > shortcut  # strong and not shortcut: weak rows are rejected anyway
        if saturated is not None:
            walk |= saturated & strong
        near_border = not inside and (column.min() < half or column.max() > image_width - 1 - half)
        if near_border:
            # A peak at least `half` columns from both borders has the estimator's samples and
            # both crossings inside the image (they are within +-half); only nearer rows are tested.
            walk |= ((column < half) | (column > image_width - 1 - half)) & strong
        if np.count_nonzero(walk):
            sub = walk.nonzero()[0]
            left, right, found = half_max_crossings(profile[sub], profile[sub, half] - peak[sub])
            width[sub] = right - left
            ok = found & (np.abs(width[sub] - _mid(params)) <= _span(params))
            if saturated is not None:
                # A clipped top has no shape to fit; the flanks are intact and symmetric, so the
                # centre is midway between the half-maximum crossings: of red's flanks when given
                # (`CLIPPED_CENTRE`), whose shape the sensor's crosstalk does not bend.
                if shape is not None:
                    red_peak = np.maximum.reduce(matrix[:2] @ shape[sub].T)
                    left, right, _ = half_max_crossings(shape[sub], shape[sub, half] - red_peak)
                offset[sub] = np.where(saturated[sub], 0.5 * (left + right), offset[sub])
            if near_border:
                # nearer the border the profile is cut and its centre is not observable
                margin = METHOD_SUPPORT_PX[params.method]
                col = column[sub]
                ok &= ~((col < margin) | (col > image_width - 1 - margin) |
                        (col + left < 0.0) | (col + right > image_width - 1.0))
            valid[sub] = ok
    skewed = None
    if params.method == ADAPTIVE:
        # `adaptive_offset`'s choice on the final width (crossings where walked): the unclipped rows wider than
        # adaptive_width_px take the centre of mass above half height, of the profile less its background; so do
        # the rows whose profile is not symmetric about the Blais-Rioux centre (`SKEW_PX`)
        skewed = np.abs(features[-1] - offset * features[2]) > SKEW_PX * np.abs(features[2])
        wide = (width > params.adaptive_width_px) | skewed
        if saturated is not None:
            wide &= ~saturated
            skewed &= ~saturated
        rows_wide = np.flatnonzero(wide)
        if rows_wide.size:
            part = profile[rows_wide]
            offset[rows_wide] = com_offset(part - (part[:, half] - peak[rows_wide])[:, None])
    u = np.add(offset, column, out=offset, casting="unsafe")  # float32, in place
    if params.method not in BLAIS_RIOUX_ORDER:
        # u is finite by construction (finite signal, guarded divisions); the test keeps it so for
        # any estimator (the Blais-Rioux crossing is clamped to [-1, 1])
        finite = np.isfinite(u)
        if np.count_nonzero(finite) < n:
            valid &= finite
            all_valid = False
    # only valid rows (peak >= min_contrast) are reported, so no clamp at 0 is needed
    quality = np.minimum((peak - params.min_contrast) * (0.5 / params.min_contrast), 1.0)
    if saturated is not None:
        quality = np.where(saturated, 0.8 * quality, quality)
    return {"u": u, "peak": peak, "width": width, "quality": quality, "saturated": saturated, "skewed": skewed,
            "valid": None if all_valid else valid}


def _refine(signal: AnyArray, red: AnyArray, first: AnyArray, peak_idx: AnyArray,
            params: ExtractorParams, image_width: int, accept: AnyArray | None = None,
            on_red: bool = False, check_red: bool = False) -> dict[str, AnyArray | None]:
    """`_fit` of each row's peak within its window: ``signal``/``red`` are (n, L) windows from image column ``first``.

    ``peak_idx`` is the integer peak in each window; ``on_red``: rows where red clips are centred on
    red's flanks (`CLIPPED_CENTRE`). The general (row-major) path: windows shifted at a border, and
    the fallback rows.
    """
    profile = _profiles(signal, peak_idx, params.refine_half_px)
    shape = None
    saturated = None
    half = params.refine_half_px
    red_profile = _profiles(red.astype(np.float32), peak_idx, half) if check_red else None
    red_rise = None if red_profile is None else _red_rise(red_profile[:, half], red_profile[:, 0], red_profile[:, 1],
                                                          red_profile[:, -2], red_profile[:, -1])
    # The signal's argmax can sit just beside the clipped red pixels (green/blue noise), so look
    # at the peak's neighbours too; the exact test only runs when the windows clip at all.
    if red.size and red.max() >= params.saturation_level:
        near = _clamp(peak_idx[:, None] + np.arange(-1, 2)[None, :], 0, red.shape[1] - 1)
        saturated = np.take_along_axis(red, near, axis=1).max(axis=1) >= params.saturation_level
        if on_red:
            shape = red_profile if red_profile is not None else _profiles(red.astype(np.float32), peak_idx, half)
    return _fit(profile, first + peak_idx, saturated, params, image_width, accept=accept, shape=shape,
                red_rise=red_rise)


def _refine_columns(sig: LaserSignal, rows: AnyArray, column: AnyArray, params: ExtractorParams,
                    image_width: int, on_red: bool = False, check_red: bool = False) -> dict[str, AnyArray | None]:
    """`_fit` of the peak at ``column`` in each of ``rows`` (the fallback rows), every window inside the image.

    The window of +-half around the peak is the profile itself: gathered column-major, it is
    already the transposed profile the matrix product of `_fit` wants, with no second gather.
    ``on_red``: as in `_refine`.
    """
    half = params.refine_half_px
    signal, red = sig.window_columns(rows * image_width + (column - half), 2 * half + 1)
    shape = None
    saturated = None
    # red is the profile window itself, column-major: its rows 0, 1, half, -2, -1 are the samples the rise needs
    red_rise = _red_rise(red[half], red[0], red[1], red[-2], red[-1]) if check_red else None
    if red.max() >= params.saturation_level:
        # the peak's neighbours too: the signal's argmax can sit just beside the clipped red pixels
        saturated = np.maximum.reduce(red[half - 1:half + 2], axis=0) >= params.saturation_level
        if on_red:
            shape = red.astype(np.float32).T
    return _fit(signal.astype(np.float32).T, column, saturated, params, image_width, inside=True, shape=shape,
                red_rise=red_rise)


def _track(sig: LaserSignal, rows: AnyArray, centre: AnyArray, params: ExtractorParams,
           image_width: int, on_red: bool = False, check_red: bool = False) -> dict[str, AnyArray | None]:
    """`_fit` of the strongest peak within ``window_px`` of ``centre`` in each row (every window inside the image).

    The fast path of the tracking stage: the windows (search region +- window_px, plus the
    refinement's +-half beyond it) are gathered column-major (`LaserSignal.window_columns`), so
    the peak search is one reduction over axis 0 and the profiles one strided gather.
    """
    w, half = params.window_px, params.refine_half_px
    reach = w + half
    n = rows.size
    if n == sig.height:  # every row (rows is then arange(height)): the row offsets are cached
        starts = _track_starts(sig.height, image_width, reach) + centre
    else:
        starts = rows * image_width + (centre - reach)
    signal, red = sig.window_columns(starts, 2 * reach + 1)
    codes, bits, offset, interior = _peak_search_layout(2 * w + 1, n, w)
    # the peak's flat index j * n + i in the search region (window rows half .. half + 2 w);
    # the profile runs from window row j, i.e. half rows before the peak
    flat = _peak_search(signal[half:half + 2 * w + 1], codes, bits)
    profile = _column_profiles(signal, flat, 2 * half + 1)
    shape = None
    column = centre + offset[flat]
    saturated = None
    red_rise = None
    if check_red:
        # the profile of row i runs down window rows flat // n .. + 2 half of column i: five samples of it
        start, cols = flat // n, np.arange(n)
        red_rise = _red_rise(red[start + half, cols], red[start, cols], red[start + 1, cols],
                             red[start + 2 * half - 1, cols], red[start + 2 * half, cols])
    if red.max() >= params.saturation_level:
        # the peak's neighbours too: the signal's argmax can sit just beside the clipped red pixels
        peak_row = flat // n + half
        near = red[peak_row[None, :] + np.arange(-1, 2)[:, None], np.arange(n)[None, :]]
        saturated = near.max(axis=0) >= params.saturation_level
        if on_red:
            shape = _column_profiles(np.ascontiguousarray(red), flat, 2 * half + 1)
    # a peak on the region's edge may be a slope rising towards something outside: search the row
    return _fit(profile, column, saturated, params, image_width, accept=interior[flat], inside=True, shape=shape,
                red_rise=red_rise)


@lru_cache(maxsize=64)
def _at_contrast(params: ExtractorParams, min_contrast: float) -> ExtractorParams:
    """``params`` with the frame's threshold (rounded to 0.5 DN by the caller, so the cache holds)."""
    return replace(params, min_contrast=min_contrast)


@lru_cache(maxsize=16)
def _coarse_rows(height: int, step: int) -> AnyArray:
    """The rows of the coarse pass, every ``step``-th from ``step // 2`` (cached, read-only)."""
    rows = np.arange(min(step // 2, height - 1), height, step)
    rows.setflags(write=False)
    return rows


_NO_ROWS = np.zeros(0, np.int64)
_NO_ROWS.setflags(write=False)
_NO_COLS = np.zeros(0)
_NO_COLS.setflags(write=False)


def _keep(rows: AnyArray, fit: dict[str, AnyArray | None],
          uniqueness: AnyArray | None = None) -> dict[str, Any]:
    """The valid rows of one refinement, with quality scaled by ``uniqueness`` when given.

    Every entry is an array except the `_FLAGS`, None where no row has the flag.
    """
    kept: dict[str, Any]
    ok = fit["valid"]
    if ok is None:  # every row valid: nothing to drop
        kept = {name: fit[name] for name in _FIELDS}
        kept["v"] = rows
    else:
        kept = {name: fit[name][ok] for name in _FIELDS}  # type: ignore[index]  # _FIELDS are never None
        kept["v"] = rows[ok]
    for flag in _FLAGS:
        value = fit.get(flag)
        kept[flag] = value if value is None or ok is None else value[ok]
    if uniqueness is not None:
        kept["quality"] = kept["quality"] * (uniqueness if ok is None else uniqueness[ok])
    return kept


def drop_isolated(found: dict[str, Any], threshold: float, height: int,
                  names: tuple[str, ...] = ("v", *_FIELDS)) -> tuple[dict[str, Any], int]:
    """``found`` (per-row arrays by row, "v" the rows; `_FIELDS`) without its weak isolated rows (`ISOLATED_WEAK`),
    and how many were dropped.

    Weak: a peak below ``ISOLATED_WEAK`` x ``threshold``. Isolated: no other row within ``CONTINUITY_ROWS``
    holds a detection within ``CONTINUITY_PX_PER_ROW`` px per row of distance of its column.
    """
    weak = found["peak"] < ISOLATED_WEAK * threshold
    if not np.any(weak):
        return found, 0
    v = found["v"].astype(np.int64)
    reach = CONTINUITY_ROWS
    column = np.full(height + 2 * reach, np.nan, np.float32)  # NaN: no detection (compares False)
    column[v + reach] = found["u"]
    continued = np.zeros(v.size, bool)
    for distance in range(1, reach + 1):
        for offset in (-distance, distance):
            continued |= np.abs(column[v + reach + offset] - found["u"]) <= CONTINUITY_PX_PER_ROW * distance
    keep = continued | ~weak
    dropped = int(v.size - np.count_nonzero(keep))
    if dropped == 0:
        return found, 0
    return {name: found[name][keep] for name in names}, dropped


# A line wider than max_width_px (grazing light, a defocused or bloomed part) is accepted only where it continues a
# line already found: row by row from the detected rows, up to GROW_MAX_WIDTH_PX wide, within window_px of the
# neighbouring row's centre (GROW_STEP_PX). A full-row search never accepts such a width (red print and lit patches are as wide).
GROW_MAX_WIDTH_PX = 48.0
GROW_PEAK_RATIO = 0.5  # ... and at least this fraction of its neighbour's peak: the same line, not a fainter patch
GROW_STEP_PX = 3.0  # a grown row's centre is at most this far from its neighbour's: a line, not a patch beside it
GROW_PASSES = 512  # bound on the rows grown from one end (a pass grows every front by one row)


# With a laser-off frame the signal is red's rise over it: texture, red print and lit patches cancel, which is what
# max_width_px guards against in a single frame. A line wider than that (grazing light, a defocused or near part:
# the turntable globe's grazing rows) is then accepted up to this width in one last full-row search of the rows still
# without a line (the searches before keep max_width_px: a wider refinement window adds the noise of the laser-off frame
# to every row's centre: the simulated plane's column RMS 0.10 -> 0.13 px). The cost: where the scene changed between
# the two frames (a person walking behind), wide differences pass too (bench/results/extract.json:
# false_rows_pct_ambient_diff_moving_person).
LASER_OFF_MAX_WIDTH_PX = 48.0


# ... and bounded by the colour of the change. The laser adds almost pure red: green and blue rise by its crosstalk
# (a few to 15 % of red's rise). A scene that changed between the two frames (a person walking behind) changes
# every channel: its differences pass the signal red - max(green, blue rise) where red rose most, but green or
# blue rose by half of red's rise or more. So with a laser-off frame of a colour camera a row is kept only where,
# over the 3 px at its centre, neither green nor blue rose by more than LASER_OFF_OTHER_RISE_RATIO x red's rise;
# a row whose red clips there is exempt (its rise is cut, crosstalk's is not). bench/results/extract.json:
# false_rows_pct_ambient_diff_moving_person, and the real sets' missed rows, which this costs little. 0 = no test.
LASER_OFF_OTHER_RISE_RATIO = 0.5


def _red_change(sig: LaserSignal, v: AnyArray, u: AnyArray, saturation: int) -> AnyArray:
    """Which detections (rows ``v``, columns ``u``) of a colour frame with its laser-off frame changed as a laser
    changes a scene (`LASER_OFF_OTHER_RISE_RATIO`): (n,) bool."""
    assert sig.texture is not None
    width = sig.width
    # the 3 pixels at each centre as flat indices into the (H * W, 3) frames: one gather per frame
    first = v * width + np.clip(np.rint(u).astype(np.int64), 1, width - 2) - 1
    at = first[:, None] + np.arange(3)[None, :]
    on = np.take(sig.image.reshape(-1, 3), at, axis=0)  # (n, 3 px, 3 channels) uint8; take: ~8x indexing's speed
    change = on.astype(np.int16)
    change -= np.take(sig.texture.reshape(-1, 3), at, axis=0)
    rise = change[:, 0] + change[:, 1] + change[:, 2]  # (n, 3): 3 x the mean rise of blue, green, red
    red = on[:, :, 2]
    clipped = np.maximum(np.maximum(red[:, 0], red[:, 1]), red[:, 2]) >= saturation
    return (np.maximum(rise[:, 0], rise[:, 1]) <= LASER_OFF_OTHER_RISE_RATIO * rise[:, 2]) | clipped


@lru_cache(maxsize=16)
def _laser_off_params(params: ExtractorParams) -> ExtractorParams:
    """``params`` with the width range of a frame given with its laser-off frame (`LASER_OFF_MAX_WIDTH_PX`)."""
    return replace(params, max_width_px=LASER_OFF_MAX_WIDTH_PX)


@lru_cache(maxsize=16)
def _grow_params(params: ExtractorParams) -> ExtractorParams:
    """``params`` with the width range of the rows grown along the line (`_grow_along`)."""
    return replace(params, max_width_px=max(params.max_width_px, GROW_MAX_WIDTH_PX))


def _grow_along(sig: LaserSignal, chunks: list[dict[str, Any]], params: ExtractorParams, image_width: int,
                on_red: bool, check_red: bool = False) -> list[dict[str, Any]]:
    """Rows next to a detection and without one, fitted within ``window_px`` of that detection's column with the
    wider width range of `_grow_params`, centred within `GROW_STEP_PX` of it; repeated from the rows found, until a pass finds none (`GROW_MAX_WIDTH_PX`).

    Each pass tries every row that has a detection directly above or below it and none itself (the mean of the two
    neighbours' columns where both have one), and no row twice. Returns the new rows as `_keep` chunks.
    """
    height = sig.height
    wide = _grow_params(params)
    w = max(params.window_px, 4)
    reach = w + wide.refine_half_px
    have = np.zeros(height + 2, bool)   # padded by one row at each end: row v is at v + 1
    col = np.zeros(height + 2, np.float64)
    peak = np.zeros(height + 2, np.float64)
    for c in chunks:
        have[c["v"] + 1] = True
        col[c["v"] + 1] = c["u"]
        peak[c["v"] + 1] = c["peak"]
    tried = have.copy()
    out: list[dict[str, Any]] = []
    for _ in range(GROW_PASSES):
        above, below = have[:-2], have[2:]
        rows = np.flatnonzero((above | below) & ~tried[1:-1])
        if not rows.size:
            break
        tried[rows + 1] = True
        a, b = above[rows], below[rows]
        guess = (np.where(a, col[rows], 0.0) + np.where(b, col[rows + 2], 0.0)) / (a.astype(np.float64) + b)
        ref_peak = np.maximum(np.where(a, peak[rows], 0.0), np.where(b, peak[rows + 2], 0.0))
        centre = np.rint(guess).astype(np.int64)
        s, red, first = sig.windows(rows, centre - reach, 2 * reach + 1)
        rel = centre - first  # windows at a border were shifted inside the image
        region = np.abs(np.arange(s.shape[1])[None, :] - rel[:, None]) <= w
        peak_idx = np.argmax(np.where(region, s, BLANK), axis=1)
        fit = _refine(s, red, first, peak_idx, wide, image_width, accept=np.abs(peak_idx - rel) < w, on_red=on_red,
                      check_red=check_red)
        kept = _keep(rows, fit)
        at = np.searchsorted(rows, kept["v"])
        step = (np.abs(kept["u"] - guess[at]) <= GROW_STEP_PX) & (kept["peak"] >= GROW_PEAK_RATIO * ref_peak[at])
        if not np.all(step):
            kept = {name: value if value is None else value[step] for name, value in kept.items()}
        if not kept["v"].size:
            break
        out.append(kept)
        have[kept["v"] + 1] = True
        col[kept["v"] + 1] = kept["u"]
        peak[kept["v"] + 1] = kept["peak"]
    return out


def _search_rows(sig: LaserSignal, rows: AnyArray, params: ExtractorParams, known: dict[str, Any] | None,
                 on_red: bool, check_red: bool) -> tuple[dict[str, Any] | None, int, AnyArray]:
    """Full-row search of ``rows`` (the line's other rows ``known``, for continuity): their `_keep` chunk (None
    where none was found), how many rows were ambiguous, and the strong rows: those whose highest peak stands
    ``min_contrast`` above their mean (the others can hold no line with these parameters)."""
    half, width = params.refine_half_px, sig.width
    # strong rows only: on a frame where the line has left the object, most pending rows are lit
    # skin or background without it, and they need no second-peak search nor a decision
    cand = row_candidates(sig.rows(rows, reuse=True), rows, half, params.min_contrast, strong_only=True,
                          scratch=True, local=not sig.colour)
    known_rows = known["v"].astype(np.int64) if known is not None else _NO_ROWS
    known_cols = known["u"] if known is not None else _NO_COLS
    pick = decide(cand, params.min_contrast, params.ambiguity_ratio, max(params.window_px, half),
                  known_rows, known_cols, 2 * params.coarse_step_rows)
    ambiguous = int(np.count_nonzero(pick.ambiguous))
    ok = pick.column >= 0
    rows_f = cand.rows[ok]
    if not rows_f.size:
        return None, ambiguous, cand.rows
    column = pick.column[ok]
    if half <= column.min() and column.max() <= width - 1 - half:
        fit = _refine_columns(sig, rows_f, column, params, width, on_red, check_red)
    else:  # some window is cut by the border: shifted inside the image, edge samples repeated
        s, red, first = sig.windows(rows_f, column - half, 2 * half + 1)
        fit = _refine(s, red, first, column - first, params, width, on_red=on_red, check_red=check_red)
    return _keep(rows_f, fit, pick.uniqueness[ok]), ambiguous, cand.rows


def _merge(chunks: list[dict[str, Any]]) -> tuple[dict[str, Any], tuple[str, ...]]:
    """`_keep` chunks as one set of per-row arrays by row, and their names ("v", `_FIELDS`, the flags some row has)."""
    # a per-row flag travels with the rows only when some row has it (`explain_rows`)
    flags = tuple(f for f in _FLAGS if any(c.get(f) is not None and np.any(c[f]) for c in chunks))
    for flag in flags:
        for c in chunks:
            if c.get(flag) is None:
                c[flag] = np.zeros(c["v"].size, bool)
    names = ("v", *_FIELDS, *flags)
    if len(chunks) == 1:
        return chunks[0], names
    if chunks:
        order = np.argsort(np.concatenate([c["v"] for c in chunks]), kind="stable")
        return {name: np.concatenate([c[name] for c in chunks])[order] for name in names}, names
    return {name: np.zeros(0, np.float32) for name in names}, names


def _clean(sig: LaserSignal, found: dict[str, Any], names: tuple[str, ...], params: ExtractorParams
           ) -> tuple[dict[str, Any], int, int]:
    """``found`` without the rows of a changed scene (`_red_change`) and the weak isolated rows (`drop_isolated`),
    and how many of each were dropped."""
    changed = 0
    if sig.texture is not None and sig.colour and found["v"].size and LASER_OFF_OTHER_RISE_RATIO > 0.0:
        keep = _red_change(sig, found["v"].astype(np.int64), found["u"], params.saturation_level)
        if not keep.all():
            changed = int(keep.size - np.count_nonzero(keep))
            found = {name: found[name][keep] for name in names}
    found, isolated = drop_isolated(found, params.min_contrast, sig.height, names)
    return found, changed, isolated


def one_opencv_thread() -> None:
    """Run OpenCV on one thread in this process, as every process that extracts laser lines does.

    The extraction's OpenCV calls work on one frame's rows and windows, too small for OpenCV's thread
    pool to speed up, and the pool's threads busy-wait between them, taking CPU from the other
    processes of the graph (or the replay's own extraction processes): parallelism comes from processes.
    """
    cv2.setNumThreads(1)


def extract_laser_line(image: AnyArray, params: ExtractorParams | None = None,
                       texture: AnyArray | None = None) -> LaserLineResult:
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
    on_red = params.clipped_centre == "red" and sig.colour and sig.texture is None
    check_red = sig.colour and sig.texture is None and params.red_rise_ratio > 0.0  # see red_rise_ratio above
    coarse_rows = _coarse_rows(height, step)
    coarse = exact = None
    if params.window_px > 0:
        if sig.texture is not None:
            # every 4th coarse row's exact signal, for the noise below, from the same planes
            coarse, exact = sig.rows_laser_off(coarse_rows, 4 if params.contrast_sigmas > 0.0 else 0)
        else:
            coarse = sig.rows_clipped(coarse_rows)
    if params.contrast_sigmas > 0.0:
        # every 4th coarse row: ~10^4 samples pin the median down; more only cost time
        if sig.texture is not None:
            # unclipped: see contrast_noise
            sigma = contrast_noise(sig.rows(coarse_rows[::4]) if exact is None else exact, half)
        else:
            sigma = contrast_noise(sig.rows_clipped(coarse_rows[::4]) if coarse is None else coarse[::4], half)
        threshold = max(NOISE_FLOOR_DN, round(params.contrast_sigmas * sigma * 2.0) / 2.0)
        if threshold < params.min_contrast:
            params = _at_contrast(params, threshold)
    wide = None
    if sig.texture is not None and params.max_width_px < LASER_OFF_MAX_WIDTH_PX:
        wide = _laser_off_params(params)
    chunks: list[dict[str, Any]] = []
    full_searched = 0
    pending: AnyArray | None = None  # None = every row
    if params.window_px > 0:
        w = params.window_px
        assert coarse is not None  # sampled whenever window_px > 0
        cand = row_candidates(coarse, coarse_rows, half, params.min_contrast, local=not sig.colour)
        full_searched += coarse_rows.size
        pick = decide(cand, params.min_contrast, params.ambiguity_ratio, w, _NO_ROWS, _NO_COLS, 2 * step)
        rows_w, guess = coarse_track(height, coarse_rows, pick.column, step)
        if rows_w.size:
            centre = np.rint(guess).astype(np.int64)
            reach = w + half  # the window holds the search region (+-w) and, beyond it, the refinement's +-half
            if reach <= centre.min() and centre.max() <= width - 1 - reach:
                # no window reaches a border (the usual case): column-major windows, fewest calls
                fit = _track(sig, rows_w, centre, params, width, on_red, check_red)
            else:
                s, red, first = sig.windows(rows_w, centre - reach, 2 * reach + 1)
                rel = centre - first  # windows at a border were shifted inside the image
                region = np.abs(np.arange(s.shape[1])[None, :] - rel[:, None]) <= w
                peak_idx = np.argmax(np.where(region, s, BLANK), axis=1)
                # a peak on the region's edge may be a slope rising towards something outside: search the row
                fit = _refine(s, red, first, peak_idx, params, width, accept=np.abs(peak_idx - rel) < w,
                              on_red=on_red, check_red=check_red)
            chunks.append(_keep(rows_w, fit))
        if chunks and chunks[0]["v"].size == height:
            pending = np.zeros(0, np.int64)
        elif chunks:
            missing = np.ones(height, bool)
            missing[chunks[0]["v"]] = False
            pending = missing.nonzero()[0]
    ambiguous = 0
    weak = _NO_ROWS  # rows that search found without a peak min_contrast above their mean
    if pending is None:
        pending = np.arange(height)
    if pending.size:
        pending = pending[sig.may_hold_laser(pending, params.min_contrast)]
    if pending.size:
        full_searched += pending.size
        known = chunks[0] if chunks else None
        searched, ambiguous, strong = _search_rows(sig, pending, params, known, on_red, check_red)
        weak = np.setdiff1d(pending, strong, assume_unique=True)
        if searched is not None:
            chunks.append(searched)
    saturated = sum(0 if c["saturated"] is None else int(np.count_nonzero(c["saturated"])) for c in chunks)
    found, names = _merge(chunks)
    found, changed, isolated = _clean(sig, found, names, params)
    grown = 0
    # grown from the rows that stay (a weak isolated row is noise: grown, it would no longer look isolated)
    if params.grow_wide and 0 < found["v"].size < height:
        more = _grow_along(sig, [found], params, width, on_red, check_red)
        if more:
            grown = sum(c["v"].size for c in more)
            saturated += sum(0 if c["saturated"] is None else int(np.count_nonzero(c["saturated"])) for c in more)
            found, names = _merge([found, *more])
            found, changed_grown, isolated_grown = _clean(sig, found, names, params)
            changed, isolated = changed + changed_grown, isolated + isolated_grown
    if wide is not None and found["v"].size < height:
        # with a laser-off frame, the rows still without a line are searched once more for a wide one
        missing = np.ones(height, bool)
        missing[found["v"].astype(np.int64)] = False
        pending = missing.nonzero()[0]
        if weak.size and sig.colour:
            # a colour row's strength (highest peak over its mean) does not depend on the width range: a row
            # weak in the search above is weak here too, and that search drops it unseen (`row_candidates`)
            pending = np.setdiff1d(pending, weak, assume_unique=True)
        pending = pending[sig.may_hold_laser(pending, params.min_contrast)]
        if pending.size:
            full_searched += pending.size
            wide_rows, _, _ = _search_rows(sig, pending, wide, found, False, False)
            if wide_rows is not None:  # only the wide ones: a narrower row there was left out by the searches before
                keep = wide_rows["width"] > params.max_width_px
                wide_rows = {name: value if value is None else value[keep] for name, value in wide_rows.items()}
            if wide_rows is not None and wide_rows["v"].size:
                saturated += 0 if wide_rows["saturated"] is None else int(np.count_nonzero(wide_rows["saturated"]))
                found, names = _merge([found, wide_rows])
                found, changed_wide, isolated_wide = _clean(sig, found, names, params)
                changed, isolated = changed + changed_wide, isolated + isolated_wide
    flags = names[1 + len(_FIELDS):]
    # every field is a fresh float32 array (u: column + offset) except v, the row indices
    return LaserLineResult(
        method=params.method, image_width=width, image_height=height,
        u=found["u"].astype(np.float32, copy=False), v=found["v"].astype(np.float32),
        peak=found["peak"].astype(np.float32, copy=False), width=found["width"].astype(np.float32, copy=False),
        quality=found["quality"].astype(np.float32, copy=False),
        rows_searched=height, rows_ambiguous=ambiguous, rows_saturated=saturated, rows_full_search=full_searched,
        extra={**({"rows_isolated": isolated} if isolated else {}), **({"rows_grown": grown} if grown else {}),
               **({"rows_scene_changed": changed} if changed else {})},
        saturated=found["saturated"].astype(bool, copy=False) if "saturated" in flags else None,
        skewed=found["skewed"].astype(bool, copy=False) if "skewed" in flags else None)


# The model each detected row was centred with (`explain_rows`), and why; the codes index this tuple.
ROW_MODELS: tuple[str, ...] = ("blais_rioux4", "blais_rioux8", "flanks_signal", "flanks_red", "method", "com")


def explain_rows(result: LaserLineResult, params: ExtractorParams | None = None,
                 textured: bool = False) -> tuple[AnyArray, dict[str, str]]:
    """Which model centred each detected row of ``result`` (codes into `ROW_MODELS`), and why each was used.

    The extractor decides per row from what it measured there: a clipped peak (red at or above
    ``saturation_level``) is centred between the half-maximum crossings of its flanks (`CLIPPED_CENTRE`);
    otherwise the adaptive Blais-Rioux takes the 4th-order filter on a line up to ``adaptive_width_px``
    wide (FWHM) and the 8th on a wider one; any other method centres every unclipped row itself.
    ``textured``: the result came with a laser-off frame (its signal is red's rise over that frame, and
    red's own flanks are not used). Returns (codes (n,) uint8, model name -> reason) for the models used.
    """
    params = params or ExtractorParams(method=result.method)
    n = len(result)
    if result.method == THESIS:
        return np.full(n, ROW_MODELS.index("method"), np.uint8), {
            "method": "thesis: mean column of the pixels with red above red_threshold and blue below blue_threshold"}
    if result.method in ("blais_rioux", ADAPTIVE):
        wide = ROW_MODELS.index("blais_rioux8" if result.method == "blais_rioux" else "com")
        codes = np.where(result.width > params.adaptive_width_px, wide, 0).astype(np.uint8)
        if result.skewed is not None:
            codes[result.skewed] = ROW_MODELS.index("com")
    else:
        codes = np.full(n, ROW_MODELS.index("method"), np.uint8)
    if result.saturated is not None:
        flanks = "flanks_red" if params.clipped_centre == "red" and not textured else "flanks_signal"
        codes[result.saturated] = ROW_MODELS.index(flanks)
    why = {
        "blais_rioux4": f"FWHM <= {params.adaptive_width_px:g} px: the 4th-order filter spans the line's flanks",
        "blais_rioux8": f"FWHM > {params.adaptive_width_px:g} px: a 4th-order filter would see only the line's flat top",
        "flanks_signal": f"red clipped (>= {params.saturation_level} DN) at the peak: no top to fit; centre midway "
                         "between the half-maximum crossings of the signal's flanks",
        "flanks_red": f"red clipped (>= {params.saturation_level} DN) at the peak: centre midway between red's own "
                      "half-maximum crossings (colour crosstalk bends the signal's clipped top)",
        "method": f"{result.method}: the configured estimator on every unclipped row",
        "com": f"FWHM > {params.adaptive_width_px:g} px: wider than a zero-crossing filter's model, or a profile not "
               f"symmetric about its Blais-Rioux centre (the window's centroid > {SKEW_PX:g} px off: one flank cut by a "
               "silhouette, a patch beside it); centre of mass of the part above half height",
    }
    used = {ROW_MODELS[int(c)] for c in np.unique(codes)}
    return codes, {name: why[name] for name in ROW_MODELS if name in used}

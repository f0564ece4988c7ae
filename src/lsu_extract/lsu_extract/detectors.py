"""Laser peak detectors: the thesis' pixel-level detector and sub-pixel peak estimators.

Sub-pixel estimators work on a window of the background-subtracted laser signal around the
integer peak of each row, all rows at once: ``profile`` is (n, 2R+1) float32 with the
integer peak at column R. Each returns the offset of the line centre from that column, in
pixels (positive = right). References:

- ``parabola``: 3-point parabola through the peak and its neighbours.
- ``gaussian3``: the same on the logarithm of the samples (exact for a sampled Gaussian).
- ``com``: centre of mass of the part of the peak above half its height, each sample
  weighted by its height above that level (a symmetric truncation, so no bias toward the
  window centre).
- ``blais_rioux4`` / ``blais_rioux8``: Blais & Rioux (1986), zero crossing of the 4th/8th
  order derivative filter ``g(i) = sum f(i-k) - sum f(i+k)``, linearly interpolated.
- ``blais_rioux``: the 4th-order filter on lines up to `ADAPTIVE_WIDTH_PX` wide (FWHM), the 8th
  on wider ones: a filter shorter than the line sees only its top, where noise and a flat or
  clipped crest decide; a longer one on a narrow line adds samples of background only.

A pure module: numpy only, no ROS.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from lsu_common.arrays import AnyArray

THESIS = "thesis"
ADAPTIVE = "adaptive"  # per row by width: `adaptive_offset`
_TINY = 1e-6


def clamp(values: AnyArray, low: float, high: float) -> AnyArray:
    """``np.clip`` without its Python-level dispatch, which costs more than the work on these small arrays."""
    return np.minimum(np.maximum(values, low), high)


def parabola_offset(profile: AnyArray) -> AnyArray:
    """3-point parabola vertex offset from the centre column of ``profile`` (n, 2R+1)."""
    r = profile.shape[1] // 2
    a, b, c = profile[:, r - 1], profile[:, r], profile[:, r + 1]
    return _vertex(a, b, c)


def gaussian3_offset(profile: AnyArray) -> AnyArray:
    """3-point Gaussian (log-parabola) offset; samples at or below zero are floored."""
    r = profile.shape[1] // 2
    # The floor keeps log finite on noisy flanks; at that point the row is weak and its quality low.
    logs = np.log(np.maximum(profile[:, r - 1:r + 2], 1e-3))
    return _vertex(logs[:, 0], logs[:, 1], logs[:, 2])


def _vertex(a: AnyArray, b: AnyArray, c: AnyArray) -> AnyArray:
    den = a - 2.0 * b + c
    ok = den < 0.0  # a maximum; flat or inverted triples (plateaus, noise) keep the integer peak
    off = np.zeros_like(b)
    np.divide(0.5 * (a - c), den, out=off, where=ok)
    return clamp(off, -0.5, 0.5)


def com_offset(profile: AnyArray) -> AnyArray:
    """Centre of mass of the contiguous part of the peak above half its height (offset from centre)."""
    r = profile.shape[1] // 2
    level = 0.5 * profile[:, r:r + 1]
    above = profile > level
    # keep only the run of samples connected to the peak: a neighbouring peak must not pull the mass
    right = np.logical_and.accumulate(above[:, r:], axis=1)
    left = np.logical_and.accumulate(above[:, r::-1], axis=1)[:, ::-1]
    mask = np.concatenate([left[:, :-1], right], axis=1)
    weight = np.where(mask, profile - level, 0.0)
    pos = np.arange(-r, r + 1, dtype=profile.dtype)
    total = weight.sum(axis=1)
    off = np.zeros(profile.shape[0], dtype=profile.dtype)
    np.divide(weight @ pos, total, out=off, where=total > 0)
    return off


def _blais_rioux_kernel(half: int) -> AnyArray:
    """(2 * half + 3, 3) matrix whose columns give the filter g at the centre column -1, 0, +1.

    ``g(i) = sum_k f(i - k) - f(i + k)`` for k = 1..half, over the 2 * half + 3 samples centred on
    the peak: one small matrix product instead of a cumulative sum and six gathers.
    """
    kernel = np.zeros((2 * half + 3, 3), np.float32)
    for column, centre in enumerate(range(half, half + 3)):  # 3 columns x half taps: setup, not per pixel
        kernel[centre - half:centre, column] = 1.0
        kernel[centre + 1:centre + half + 1, column] = -1.0
    kernel.setflags(write=False)
    return kernel


_BR_KERNELS: dict[int, AnyArray] = {half: _blais_rioux_kernel(half) for half in (2, 4)}


def blais_rioux_kernel(order: int, size: int) -> AnyArray:
    """The Blais-Rioux filter of ``order`` (4 or 8) at the centre column -1, 0, +1 of a ``size``-sample profile.

    ``profile @ blais_rioux_kernel(order, size)`` gives (g(r - 1), g(r), g(r + 1)), r = size // 2,
    for `blais_rioux_zero_crossing`: one small matrix product instead of cumulative sums and gathers.
    """
    half, r = order // 2, size // 2
    if r < half + 1:
        raise ValueError(f"blais_rioux{order} needs a window of at least +-{half + 1} px, got +-{r}")
    kernel = np.zeros((size, 3), np.float32)
    kernel[r - half - 1:r + half + 2] = _BR_KERNELS[half]
    return kernel


def blais_rioux_zero_crossing(gm: AnyArray, g0: AnyArray, gp: AnyArray) -> AnyArray:
    """Offset of the zero crossing of g next to the peak from g at the columns -1, 0, +1 (in [-1, 1])."""
    return blais_rioux_crossing(-g0, g0 - gm, gp - g0)


def blais_rioux_crossing(neg_g0: AnyArray, rise_left: AnyArray, rise_right: AnyArray) -> AnyArray:
    """`blais_rioux_zero_crossing` from -g(0), g(0) - g(-1) and g(+1) - g(0), all linear in the profile.

    g < 0 left of the peak and > 0 right of it; its zero crossing is interpolated on the segment
    next to the peak where g changes sign: [0, 1] when g(0) <= 0, else [-1, 0]. On either
    segment the interpolated crossing is -g(0) / (rise of g along the segment), so one division
    covers both (the sign of g(0) keeps each on its own side of 0), and dividing by at least
    |g(0)| clamps it to [-1, 1] on the way. A segment on which g does not rise (a flat or
    clipped top, noise) has no crossing: the offset is then the segment's far end, or 0 when
    g(0) = 0. Taking the three inputs from the extractor's matrix product leaves 6 numpy calls.
    """
    left = neg_g0 < 0.0
    rise = np.where(left, rise_left, rise_right)
    return neg_g0 / np.maximum(np.maximum(rise, np.abs(neg_g0)), _TINY)


def _blais_rioux(profile: AnyArray, order: int) -> AnyArray:
    g = profile @ blais_rioux_kernel(order, profile.shape[1]).astype(profile.dtype, copy=False)
    return blais_rioux_zero_crossing(g[:, 0], g[:, 1], g[:, 2]).astype(profile.dtype, copy=False)


def blais_rioux4_offset(profile: AnyArray) -> AnyArray:
    """Blais-Rioux 4th-order zero-crossing offset."""
    return _blais_rioux(profile, 4)


def blais_rioux8_offset(profile: AnyArray) -> AnyArray:
    """Blais-Rioux 8th-order zero-crossing offset."""
    return _blais_rioux(profile, 8)


ADAPTIVE_WIDTH_PX = 5.0  # blais_rioux: lines wider than this (FWHM) take the 8th-order filter


def blais_rioux_offset(profile: AnyArray) -> AnyArray:
    """Blais-Rioux of the order the line's width asks for (4th up to `ADAPTIVE_WIDTH_PX` FWHM, else 8th)."""
    left, right, _ = half_max_crossings(profile)
    return np.where(right - left > ADAPTIVE_WIDTH_PX, _blais_rioux(profile, 8), _blais_rioux(profile, 4))


def adaptive_offset(profile: AnyArray) -> AnyArray:
    """Per row by the line's measured width: Blais-Rioux 4 up to `ADAPTIVE_WIDTH_PX` FWHM, else the centre of mass.

    A zero-crossing filter models a line about as wide as itself: on a wider line it sees the
    flat, speckled top, and a longer filter still weighs the top's samples as much as the flanks.
    The centre of mass of the part above half height uses every sample of the line in proportion
    to its height, which on wide real lines (5-12 px) generalised best across data sets
    (bench/study_extract.py); on narrow lines it adds quantisation error that Blais-Rioux 4 has not.
    """
    left, right, _ = half_max_crossings(profile)
    return np.where(right - left > ADAPTIVE_WIDTH_PX, com_offset(profile), _blais_rioux(profile, 4))


SUBPIXEL_METHODS: dict[str, Callable[[AnyArray], AnyArray]] = {
    "gaussian3": gaussian3_offset,
    "parabola": parabola_offset,
    "com": com_offset,
    "blais_rioux4": blais_rioux4_offset,
    "blais_rioux8": blais_rioux8_offset,
    "blais_rioux": blais_rioux_offset,
    "adaptive": adaptive_offset,
}
METHODS: tuple[str, ...] = (THESIS, *SUBPIXEL_METHODS)
# How many pixels each side of the peak an estimator reads (rows nearer the border are dropped).
METHOD_SUPPORT_PX: dict[str, int] = {"gaussian3": 1, "parabola": 1, "com": 1, "blais_rioux4": 3, "blais_rioux8": 5,
                                     "blais_rioux": 5, "adaptive": 3}
# Methods that are a linear filter of the profile followed by a zero crossing: the filter ignores a
# constant background, so the extractor applies it to the raw profile in the same product as the
# background estimate.
BLAIS_RIOUX_ORDER: dict[str, tuple[int, ...]] = {"blais_rioux4": (4,), "blais_rioux8": (8,), "blais_rioux": (4, 8),
                                               "adaptive": (4,)}  # wider lines: com (`adaptive_offset`)


_WALK_STEP = np.array([1, -1])  # the two walks of `half_max_crossings`: right, left
_WALK_STEP.setflags(write=False)


def half_max_crossings(profile: AnyArray, base: AnyArray | None = None
                       ) -> tuple[AnyArray, AnyArray, AnyArray]:
    """Sub-pixel positions (relative to the centre column) where the peak falls to half its height.

    Walks out from the centre on each side to the first sample below half the centre value
    (half way between the centre and ``base`` per row, when the profile still holds its
    background) and interpolates linearly. Returns (left, right, found) where ``found`` is
    False for rows whose profile does not drop to half within the window on both sides (or
    whose centre is not above the level, i.e. not a positive peak); their positions are finite
    but meaningless.
    """
    profile = np.ascontiguousarray(profile)
    n, m = profile.shape
    r = m // 2
    if r < 1:
        raise ValueError(f"half_max_crossings needs at least 3 samples per row, got {m}")
    level = 0.5 * profile[:, r] if base is None else 0.5 * (profile[:, r] + base)
    below = profile < level[:, None]
    # Index of the first sample below the level going right / left from the centre, both walks
    # in one argmax over the two halves side by side; argmax gives 0 both when there is none
    # and when the centre itself is below: neither is a peak.
    j = np.concatenate([below[:, r:], below[:, r::-1]], axis=1).reshape(n, 2, r + 1).argmax(axis=2)
    found = np.minimum.reduce(j, axis=1) > 0
    # flat index of the first sample below the level (outer) and of the one before it (inner),
    # right then left: both interpolations in one set of (n, 2) operations
    outer = np.arange(r, n * m, m)[:, None] + _WALK_STEP * j
    flat = profile.ravel()
    low = flat[outer]
    high = flat[outer - _WALK_STEP]
    # high >= level > low on found rows; the floor only keeps the others finite
    frac = (level[:, None] - low) / np.maximum(high - low, _TINY)
    # right: jr - frac; left: frac - jl
    side = _WALK_STEP * (j - frac)
    return side[:, 1].astype(profile.dtype, copy=False), side[:, 0].astype(profile.dtype, copy=False), found


@dataclass(frozen=True)
class PixelLine:
    """Pixel-level detections of the thesis detector (one per row that has laser pixels)."""

    u: AnyArray      # column of the maximum red [px]
    v: AnyArray      # row [px]
    peak: AnyArray   # red value at that column
    width: AnyArray  # number of laser pixels in the row
    quality: AnyArray


def thesis_detector(image: AnyArray, red_threshold: int, blue_threshold: int) -> PixelLine:
    """The thesis' detector (ch. 6.1.5), faithfully: pixel level, whole frame.

    Per row, candidate laser pixels have red above ``red_threshold`` and blue below
    ``blue_threshold``; the laser is the candidate of maximum red, the first one on ties (as
    Matlab's ``max`` does). A mono image has no blue, so only the red test applies.
    Quality is how far the red value is above the threshold, 0..1.
    """
    red = image[..., 2] if image.ndim == 3 else image
    candidate = red > red_threshold
    if image.ndim == 3:
        candidate &= image[..., 0] < blue_threshold
    masked = np.where(candidate, red, 0)
    u = np.argmax(masked, axis=1)
    rows = np.nonzero(candidate.any(axis=1))[0]
    u = u[rows]
    peak = masked[rows, u].astype(np.float32)
    span = max(255 - red_threshold, 1)
    return PixelLine(u=u.astype(np.float32), v=rows.astype(np.float32), peak=peak,
                     width=candidate[rows].sum(axis=1).astype(np.float32),
                     quality=clamp((peak - red_threshold) / span, 0.0, 1.0).astype(np.float32))

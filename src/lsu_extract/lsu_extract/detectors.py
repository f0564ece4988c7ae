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

A pure module: numpy only, no ROS.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Dict, Tuple

import numpy as np

THESIS = "thesis"


def clamp(values: np.ndarray, low: float, high: float) -> np.ndarray:
    """``np.clip`` without its Python-level dispatch, which costs more than the work on these small arrays."""
    return np.minimum(np.maximum(values, low), high)


def parabola_offset(profile: np.ndarray) -> np.ndarray:
    """3-point parabola vertex offset from the centre column of ``profile`` (n, 2R+1)."""
    r = profile.shape[1] // 2
    a, b, c = profile[:, r - 1], profile[:, r], profile[:, r + 1]
    return _vertex(a, b, c)


def gaussian3_offset(profile: np.ndarray) -> np.ndarray:
    """3-point Gaussian (log-parabola) offset; samples at or below zero are floored."""
    r = profile.shape[1] // 2
    # The floor keeps log finite on noisy flanks; at that point the row is weak and its quality low.
    logs = np.log(np.maximum(profile[:, r - 1:r + 2], 1e-3))
    return _vertex(logs[:, 0], logs[:, 1], logs[:, 2])


def _vertex(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    den = a - 2.0 * b + c
    ok = den < 0.0  # a maximum; flat or inverted triples (plateaus, noise) keep the integer peak
    off = np.zeros_like(b)
    np.divide(0.5 * (a - c), den, out=off, where=ok)
    return clamp(off, -0.5, 0.5)


def com_offset(profile: np.ndarray) -> np.ndarray:
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


def _blais_rioux(profile: np.ndarray, order: int) -> np.ndarray:
    half = order // 2
    r = profile.shape[1] // 2
    if r < half + 1:
        raise ValueError(f"blais_rioux{order} needs a window of at least +-{half + 1} px, got +-{r}")
    # g at the columns r-1, r, r+1
    cs = np.zeros((profile.shape[0], profile.shape[1] + 1), profile.dtype)
    np.cumsum(profile, axis=1, out=cs[:, 1:])

    def g(i: int) -> np.ndarray:
        left = cs[:, i] - cs[:, i - half]           # f(i-half) .. f(i-1)
        right = cs[:, i + half + 1] - cs[:, i + 1]  # f(i+1) .. f(i+half)
        return left - right

    gm, g0, gp = g(r - 1), g(r), g(r + 1)
    # g < 0 left of the peak and > 0 right of it; interpolate its zero crossing next to the peak
    right_side = g0 <= 0.0
    lo = np.where(right_side, g0, gm)
    hi = np.where(right_side, gp, g0)
    base = np.where(right_side, 0.0, -1.0)
    den = hi - lo
    frac = np.full_like(g0, 0.5)
    np.divide(-lo, den, out=frac, where=den > 0)
    return clamp(base + clamp(frac, 0.0, 1.0), -1.0, 1.0).astype(profile.dtype)


def blais_rioux4_offset(profile: np.ndarray) -> np.ndarray:
    """Blais-Rioux 4th-order zero-crossing offset."""
    return _blais_rioux(profile, 4)


def blais_rioux8_offset(profile: np.ndarray) -> np.ndarray:
    """Blais-Rioux 8th-order zero-crossing offset."""
    return _blais_rioux(profile, 8)


SUBPIXEL_METHODS: Dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "gaussian3": gaussian3_offset,
    "parabola": parabola_offset,
    "com": com_offset,
    "blais_rioux4": blais_rioux4_offset,
    "blais_rioux8": blais_rioux8_offset,
}
METHODS: Tuple[str, ...] = (THESIS, *SUBPIXEL_METHODS)
# How many pixels each side of the peak an estimator reads (rows nearer the border are dropped).
METHOD_SUPPORT_PX: Dict[str, int] = {"gaussian3": 1, "parabola": 1, "com": 1, "blais_rioux4": 3, "blais_rioux8": 5}


def half_max_crossings(profile: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sub-pixel positions (relative to the centre column) where the peak falls to half its height.

    Walks out from the centre on each side to the first sample below half the centre value
    and interpolates linearly. Returns (left, right, found) where ``found`` is False for rows
    whose profile does not drop to half within the window on both sides.
    """
    n, m = profile.shape
    r = m // 2
    level = 0.5 * profile[:, r:r + 1]
    below = profile < level
    rows = np.arange(n)
    # first sample below the level going right / left from the centre
    right_below = below[:, r:]
    jr = np.argmax(right_below, axis=1)
    found_r = right_below[rows, jr]
    left_below = below[:, r::-1]
    jl = np.argmax(left_below, axis=1)
    found_l = left_below[rows, jl]
    lvl = level[:, 0]

    def cross(outer: np.ndarray, inner: np.ndarray) -> np.ndarray:
        fo, fi = profile[rows, outer], profile[rows, inner]
        den = fi - fo
        t = np.full(n, 0.5, dtype=profile.dtype)
        np.divide(lvl - fo, den, out=t, where=den > 0)
        return clamp(t, 0.0, 1.0)

    ir = clamp(r + jr, 0, m - 1)
    il = clamp(r - jl, 0, m - 1)
    right = (ir - r) - cross(ir, np.maximum(ir - 1, 0))
    left = (il - r) + cross(il, np.minimum(il + 1, m - 1))
    return left.astype(profile.dtype), right.astype(profile.dtype), found_l & found_r & (jl > 0) & (jr > 0)


@dataclass(frozen=True)
class PixelLine:
    """Pixel-level detections of the thesis detector (one per row that has laser pixels)."""

    u: np.ndarray      # column of the maximum red [px]
    v: np.ndarray      # row [px]
    peak: np.ndarray   # red value at that column
    width: np.ndarray  # number of laser pixels in the row
    quality: np.ndarray


def thesis_detector(image: np.ndarray, red_threshold: int, blue_threshold: int) -> PixelLine:
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

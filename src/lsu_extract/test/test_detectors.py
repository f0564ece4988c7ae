"""Sub-pixel estimators and the thesis detector against analytic profiles (truth: the normal CDF)."""

import numpy as np
import pytest
from scipy.special import ndtr

from lsu_common.arrays import AnyArray
from lsu_extract.detectors import (
    SUBPIXEL_METHODS,
    blais_rioux_kernel,
    blais_rioux_zero_crossing,
    half_max_crossings,
    thesis_detector,
)

FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))


def integrated_gaussian(offsets: AnyArray, fwhm: float, half: int = 11) -> AnyArray:
    """Rows of a unit Gaussian integrated over each pixel, centred ``offsets`` px right of column ``half``."""
    sigma = fwhm / FWHM_PER_SIGMA
    x = np.arange(-half, half + 1)[None, :] - offsets[:, None]
    return ((ndtr((x + 0.5) / sigma) - ndtr((x - 0.5) / sigma)) * 100.0).astype(np.float32)


OFFSETS = np.linspace(-0.45, 0.45, 19)


@pytest.mark.parametrize("method", sorted(SUBPIXEL_METHODS))
@pytest.mark.parametrize("fwhm", [3.0, 4.0, 6.0])
def test_estimator_recovers_known_offsets_of_a_pixel_integrated_gaussian(method, fwhm):
    offsets = SUBPIXEL_METHODS[method](integrated_gaussian(OFFSETS, fwhm))
    assert np.all(np.isfinite(offsets))
    # centre of mass above half height keeps only ~3 samples of a 3 px line: a known ~0.06 px
    # sawtooth bias (one reason it is not the default)
    tolerance = 0.07 if (method == "com" and fwhm <= 3.0) else 0.05
    assert np.max(np.abs(offsets - OFFSETS)) <= tolerance


@pytest.mark.parametrize("method", sorted(SUBPIXEL_METHODS))
def test_estimator_is_antisymmetric(method):
    left = SUBPIXEL_METHODS[method](integrated_gaussian(-OFFSETS, 4.0))
    right = SUBPIXEL_METHODS[method](integrated_gaussian(OFFSETS, 4.0))
    np.testing.assert_allclose(left, -right, atol=1e-4)


@pytest.mark.parametrize("method", sorted(SUBPIXEL_METHODS))
def test_estimator_gives_finite_offsets_on_flat_zero_and_negative_rows(method):
    rows = np.stack([np.zeros(23), np.full(23, 7.0), -np.ones(23), np.r_[np.zeros(11), [5.0], np.zeros(11)]])
    offsets = SUBPIXEL_METHODS[method](rows.astype(np.float32))
    assert np.all(np.isfinite(offsets)) and np.all(np.abs(offsets) <= 1.0)


def test_half_max_crossings_give_the_fwhm_of_a_wide_gaussian():
    fwhm = 8.0
    profile = integrated_gaussian(np.array([0.0, 0.3]), fwhm)
    left, right, found = half_max_crossings(profile)
    assert found.all()
    # pixel integration and linear interpolation widen the profile a little
    np.testing.assert_allclose(right - left, fwhm, atol=0.25)
    np.testing.assert_allclose(0.5 * (left + right), [0.0, 0.3], atol=0.02)


def test_half_max_crossings_report_a_profile_that_never_drops_to_half():
    _, _, found = half_max_crossings(np.full((1, 23), 50.0, np.float32))
    assert not found[0]


def test_thesis_detector_takes_the_reddest_pixel_passing_both_thresholds():
    image = np.zeros((3, 10, 3), np.uint8)
    image[0, 4] = (20, 30, 200)   # laser: red high, blue low
    image[0, 7] = (250, 250, 255)  # white highlight: red higher, but blue too high
    image[1, 2] = (20, 20, 100)   # red below the threshold
    image[2, 5] = (0, 0, 255)
    image[2, 6] = (0, 0, 255)     # tie: Matlab's max takes the first
    line = thesis_detector(image, red_threshold=150, blue_threshold=100)
    assert line.v.tolist() == [0.0, 2.0]
    assert line.u.tolist() == [4.0, 5.0]
    assert line.peak.tolist() == [200.0, 255.0]
    assert line.width.tolist() == [1.0, 2.0]


def test_half_max_crossings_on_a_profile_that_keeps_its_background():
    profile = integrated_gaussian(np.array([-0.3, 0.0, 0.27]), 5.0)
    background = np.array([12.0, -7.0, 30.0], np.float32)
    left, right, found = half_max_crossings(profile + background[:, None], background)
    left0, right0, found0 = half_max_crossings(profile)
    assert found.all() and found0.all()
    np.testing.assert_allclose(left, left0, atol=1e-4)
    np.testing.assert_allclose(right, right0, atol=1e-4)


@pytest.mark.parametrize("order", [4, 8])
def test_blais_rioux_filter_matches_its_definition(order):
    rng = np.random.default_rng(order)
    profile = rng.normal(size=(5, 23)).astype(np.float32)
    g = profile @ blais_rioux_kernel(order, 23)
    half, r = order // 2, 11
    for i, col in enumerate((r - 1, r, r + 1)):  # g(i) = sum_k f(i - k) - f(i + k), k = 1..order/2
        expected = sum(profile[:, col - k] - profile[:, col + k] for k in range(1, half + 1))
        np.testing.assert_allclose(g[:, i], expected, atol=1e-5)


def test_blais_rioux_crossing_is_the_interpolated_zero_crossing_next_to_the_peak():
    # the straightforward form: interpolate g linearly on the segment where it changes sign
    rng = np.random.default_rng(11)
    gm, g0, gp = (rng.normal(size=2000).astype(np.float32) for _ in range(3))
    gm, gp = gm - 2.0, gp + 2.0  # mostly rising through the peak, as g does
    offset = blais_rioux_zero_crossing(gm, g0, gp)
    right = g0 <= 0
    lo, hi = np.where(right, g0, gm), np.where(right, gp, g0)
    rising = hi > lo
    expected = np.clip(-lo / np.where(rising, hi - lo, 1.0), 0.0, 1.0) - (~right)
    np.testing.assert_allclose(offset[rising], expected[rising], atol=1e-5)
    assert np.all(np.abs(offset) <= 1.0) and np.all(np.isfinite(offset))
    # a flat top (g = 0 around the peak) has its centre on the peak
    assert blais_rioux_zero_crossing(np.zeros(1), np.zeros(1), np.zeros(1))[0] == 0.0

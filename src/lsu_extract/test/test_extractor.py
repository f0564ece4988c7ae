"""The whole extractor on analytic laser lines (truth: lsu_extract.synthetic, the analytic centres)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lsu_common.arrays import AnyArray
from lsu_extract import extractor as extractor_module
from lsu_extract.detectors import METHODS
from lsu_extract.extractor import (
    DEFAULT_METHOD,
    ExtractorConfigError,
    ExtractorParams,
    LaserLineResult,
    extract_laser_line,
)
from lsu_extract.image import ImageFormatError
from lsu_extract.signal import LaserSignal, contrast_noise
from lsu_extract.synthetic import LineScene, render_line

CLEAN = LineScene(textured=False, read_noise_dn=0.0, shot_gain=0.0)


def errors(result: LaserLineResult, truth: AnyArray) -> AnyArray:
    return result.u - truth[result.v.astype(int)]


def assert_finite(result: LaserLineResult) -> None:
    n = len(result)
    for name in ("u", "v", "peak", "width", "quality"):
        values = getattr(result, name)
        assert values.shape == (n,) and np.all(np.isfinite(values)), name
    assert np.all((result.quality >= 0) & (result.quality <= 1))


@pytest.mark.parametrize("u0", [200.0, 200.25, 200.5, 200.73, 431.9])
def test_default_method_recovers_slanted_curved_line_within_005_px(u0):
    image, truth, _ = render_line(CLEAN.with_(u0_px=u0, slope_px_per_row=0.13, bow_px=9.0))
    result = extract_laser_line(image)
    assert result.method == DEFAULT_METHOD
    assert len(result) == image.shape[0]
    assert np.max(np.abs(errors(result, truth))) <= 0.05


def test_default_method_beats_the_thesis_method_at_default_noise():
    image, truth, _ = render_line(LineScene(textured=False, seed=3))
    default = extract_laser_line(image)
    thesis = extract_laser_line(image, ExtractorParams(method="thesis"))
    rms_default = np.sqrt(np.mean(errors(default, truth) ** 2))
    rms_thesis = np.sqrt(np.mean(errors(thesis, truth) ** 2))
    assert len(default) == image.shape[0]
    assert rms_default <= 0.05
    assert 0.2 <= rms_thesis <= 0.45  # pixel quantisation: ~1/sqrt(12) px
    assert np.all(thesis.u == np.round(thesis.u))


def test_width_is_the_fwhm_of_the_drawn_profile():
    image, _, _ = render_line(CLEAN.with_(fwhm_px=6.0))
    result = extract_laser_line(image)
    assert abs(float(np.median(result.width)) - 6.0) <= 0.3


@pytest.mark.parametrize("method", METHODS)
def test_every_method_finds_every_row_of_a_clean_line(method):
    image, truth, _ = render_line(CLEAN)
    result = extract_laser_line(image, ExtractorParams(method=method))
    assert len(result) == image.shape[0]
    assert np.max(np.abs(errors(result, truth))) <= (0.6 if method == "thesis" else 0.05)  # thesis: nearest pixel, ties
    assert_finite(result)


def test_tracking_window_gives_the_same_line_as_full_row_search():
    image, _, _ = render_line(LineScene(seed=5))
    tracked = extract_laser_line(image)
    full = extract_laser_line(image, ExtractorParams(window_px=0))
    assert tracked.rows_full_search < image.shape[0] // 4 and full.rows_full_search == image.shape[0]
    np.testing.assert_array_equal(tracked.v, full.v)
    np.testing.assert_allclose(tracked.u, full.u, atol=1e-4)


def test_saturated_plateau_is_centred_between_its_flanks():
    image, truth, _ = render_line(CLEAN.with_(amplitude_dn=700.0, fwhm_px=5.0, read_noise_dn=1.0, shot_gain=0.05))
    assert (image[..., 2] == 255).sum(axis=1).min() >= 3  # really a plateau in every row
    result = extract_laser_line(image)
    assert result.rows_saturated == len(result) == image.shape[0]
    assert np.sqrt(np.mean(errors(result, truth) ** 2)) <= 0.1


def test_weaker_reflection_is_ignored():
    image, truth, _ = render_line(LineScene(reflection=0.4, seed=2))
    result = extract_laser_line(image)
    assert len(result) == image.shape[0] and result.rows_ambiguous == 0
    assert np.max(np.abs(errors(result, truth))) < 0.5


@pytest.mark.parametrize("window", [12, 0])
def test_competing_reflection_in_some_rows_is_resolved_by_continuity(window):
    plain, truth, _ = render_line(LineScene(seed=4))
    mirrored, _, _ = render_line(LineScene(seed=4, reflection=1.0))
    image = plain.copy()
    image[150:260] = mirrored[150:260]  # an equally bright reflection 70 px right, in 110 rows
    result = extract_laser_line(image, ExtractorParams(window_px=window))
    assert np.max(np.abs(errors(result, truth))) < 0.5  # never the reflection
    assert len(result) + result.rows_ambiguous == image.shape[0]
    assert len(result) >= image.shape[0] - 5


def test_competing_reflection_everywhere_is_counted_not_guessed():
    # a uniform background: the reflection is as bright as the laser in every row
    image, truth, _ = render_line(LineScene(reflection=1.0, reflection_offset_px=60.0, textured=False, seed=6))
    result = extract_laser_line(image)
    assert result.rows_ambiguous > image.shape[0] // 2
    assert len(result) + result.rows_ambiguous == image.shape[0]


def test_partial_line_on_textured_background_at_50pct_ambient():
    scene = LineScene(ambient=0.5, first_row=100, last_row=380, reflection=0.3, seed=8)
    image, truth, visible = render_line(scene)
    result = extract_laser_line(image)
    rows = result.v.astype(int)
    false = np.count_nonzero(~visible[rows])
    missed = np.count_nonzero(visible) - np.count_nonzero(visible[rows])
    assert false <= 0.005 * image.shape[0] and missed <= 0.01 * np.count_nonzero(visible)
    assert np.max(np.abs(errors(result, truth)[visible[rows]])) < 1.0


def test_texture_frame_cancels_a_red_background():
    scene = LineScene(ambient=0.6, seed=9)
    image, truth, _ = render_line(scene)
    texture, _, _ = render_line(scene.with_(amplitude_dn=0.0, seed=10))  # same view, laser off, new noise
    result = extract_laser_line(image, texture=texture)
    assert len(result) == image.shape[0]
    assert np.sqrt(np.mean(errors(result, truth) ** 2)) <= 0.1


def test_a_scene_change_between_the_laser_off_frame_and_the_snap_is_not_taken_for_the_laser(monkeypatch):
    # the laser in rows 0..239; in rows 240..479 something skin-coloured moved in between the two frames (a person
    # walking behind): a 20 px wide brightening of every channel, red most (+80 / +45 / +35 DN in R / G / B), which
    # passes red's rise less the larger of green's and blue's (35 DN). Truth: where the line was drawn and the patch.
    scene = LineScene(ambient=0.3, last_row=239, seed=11, texture_seed=11)
    image, truth, visible = render_line(scene)
    texture, _, _ = render_line(scene.with_(amplitude_dn=0.0, seed=12))
    cols = np.arange(image.shape[1])
    bump = np.exp(-0.5 * ((cols - 450.0) / 8.5) ** 2)
    moved = image.astype(np.float32)
    moved[240:] += bump[None, :, None] * np.array([35.0, 45.0, 80.0])[None, None, :]
    image = np.clip(np.rint(moved), 0, 255).astype(np.uint8)
    result = extract_laser_line(image, texture=texture)
    rows = result.v.astype(int)
    assert np.count_nonzero(visible[rows]) == np.count_nonzero(visible)  # every laser row
    assert np.count_nonzero(~visible[rows]) == 0 and result.extra.get("rows_scene_changed", 0) > 100
    assert np.max(np.abs(errors(result, truth))) < 0.5
    monkeypatch.setattr(extractor_module, "LASER_OFF_OTHER_RISE_RATIO", 0.0)  # without the test: the patch is taken
    assert np.count_nonzero(extract_laser_line(image, texture=texture).v >= 240) > 100


@pytest.mark.parametrize("method", ["blais_rioux4", "blais_rioux8", "gaussian3", "com"])
def test_line_running_off_the_border_keeps_only_observable_rows(method):
    image, truth, _ = render_line(CLEAN.with_(u0_px=4.0, slope_px_per_row=-0.02, bow_px=0.0))  # 8.8 .. -0.8 px
    result = extract_laser_line(image, ExtractorParams(method=method))
    assert_finite(result)
    kept = np.zeros(image.shape[0], bool)
    kept[result.v.astype(int)] = True
    assert kept[truth >= 6.5].all()  # well inside: every row found
    assert not kept[truth < 0.5].any()  # peak pixel on column 0 or outside: centre not observable
    assert np.max(np.abs(errors(result, truth))) <= 0.05


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("value", [0, 255])
def test_empty_and_all_saturated_images_give_no_line(method, value):
    image = np.full((48, 64, 3), value, np.uint8)
    result = extract_laser_line(image, ExtractorParams(method=method))
    assert_finite(result)
    if method != "thesis":
        assert len(result) == 0
    assert result.rows_searched == 48


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), method=st.sampled_from(METHODS), mono=st.booleans(),
       window=st.sampled_from([0, 3, 12]))
def test_output_is_always_finite_on_random_images(seed, method, mono, window):
    rng = np.random.default_rng(seed)
    shape = (int(rng.integers(1, 40)), int(rng.integers(24, 80)))
    image = rng.integers(0, 256, shape if mono else shape + (3,), dtype=np.uint8)
    if rng.random() < 0.5:  # spiky images: mostly dark with a few hot pixels
        image = np.where(rng.random(image.shape) < 0.05, image, 0).astype(np.uint8)
    result = extract_laser_line(image, ExtractorParams(method=method, window_px=window, coarse_step_rows=3))
    assert_finite(result)
    assert np.all((result.u >= 0) & (result.u <= shape[1] - 1))
    assert np.all((result.v >= 0) & (result.v <= shape[0] - 1))


def test_bad_parameters_raise_a_readable_error():
    with pytest.raises(ExtractorConfigError, match="method 'sobel' is unknown; must be one of: thesis"):
        ExtractorParams(method="sobel")
    with pytest.raises(ExtractorConfigError, match=r"min_contrast must be within \[1, 255\]"):
        ExtractorParams(min_contrast=-3.0)
    with pytest.raises(ExtractorConfigError, match="min_width_px .* smaller than max_width_px"):
        ExtractorParams(min_width_px=10.0, max_width_px=5.0)


def test_wrong_array_and_mismatched_texture_are_rejected():
    with pytest.raises(ImageFormatError, match="uint8"):
        extract_laser_line(np.zeros((10, 40, 3), np.float32))
    with pytest.raises(ImageFormatError, match="texture frame"):
        extract_laser_line(np.zeros((10, 40, 3), np.uint8), texture=np.zeros((10, 41, 3), np.uint8))


def test_dark_rows_without_laser_are_skipped_and_the_line_is_kept():
    # a line in the middle rows of a dark frame (a face on a black background, in miniature)
    scene = LineScene(ambient=0.0, textured=False, first_row=150, last_row=330, seed=11)
    image, truth, visible = render_line(scene)
    result = extract_laser_line(image)
    rows = result.v.astype(int)
    np.testing.assert_array_equal(rows, np.flatnonzero(visible))
    assert np.max(np.abs(errors(result, truth))) <= 0.1
    # the rows far from the line were dark: none of them cost a full-row search
    assert result.rows_full_search < 60 + 2 * 8 * 2


def test_lit_rows_without_laser_are_skipped_with_a_laser_off_frame_and_the_line_is_kept():
    # a line in the middle rows of a brightly lit, textured view (skin around a face): every row is bright, so only
    # the rise over the laser-off frame (noise, in the rows without the line) tells that most rows hold no line
    scene = LineScene(ambient=0.5, first_row=150, last_row=330, seed=13)
    image, truth, visible = render_line(scene)
    off = render_line(scene.with_(amplitude_dn=0.0, seed=scene.seed + 1))[0]
    result = extract_laser_line(image, texture=off)
    np.testing.assert_array_equal(result.v.astype(int), np.flatnonzero(visible))
    error = errors(result, truth)   # the bright view's shot noise: a looser bound than on a dark one
    assert np.sqrt(np.mean(error ** 2)) <= 0.1 and np.max(np.abs(error)) <= 0.3
    assert result.rows_full_search < 60 + 2 * 8 * 2
    # without the laser-off frame the same lit rows cannot be told apart cheaply: each is searched
    assert extract_laser_line(image).rows_full_search > image.shape[0] - (330 - 150 + 1)


def test_tracking_and_full_search_refine_the_same_peaks_on_a_bright_textured_frame():
    image, _, _ = render_line(LineScene(seed=12, ambient=0.3, slope_px_per_row=-0.11, bow_px=14.0))
    tracked = extract_laser_line(image)
    full = extract_laser_line(image, ExtractorParams(window_px=0))
    np.testing.assert_array_equal(tracked.v, full.v)
    np.testing.assert_allclose(tracked.u, full.u, atol=1e-4)
    np.testing.assert_allclose(tracked.width, full.width, atol=1e-4)
    np.testing.assert_allclose(tracked.peak, full.peak, atol=1e-3)


@pytest.mark.parametrize("fwhm", [2.5, 4.0, 6.0, 8.0])
def test_width_estimate_is_the_fwhm_of_an_analytic_gaussian_line(fwhm):
    # the equivalent width (area / height over the window) of a pixel-integrated Gaussian line
    image, _, _ = render_line(CLEAN.with_(fwhm_px=fwhm, slope_px_per_row=0.13, bow_px=9.0))
    result = extract_laser_line(image)
    assert len(result) == image.shape[0]
    # pixel integration widens a sampled line a little; the sub-pixel phase moves each row's value
    assert abs(float(np.median(result.width)) - fwhm) <= 0.05 * fwhm + 0.1
    assert np.all(np.abs(result.width - fwhm) <= 0.1 * fwhm + 0.3)


def test_width_on_a_step_in_the_background_comes_from_the_half_maximum_crossings():
    # a bright patch on one side of the line: the ends of the refinement window differ by more
    # than a quarter of the peak, so the width is measured between the crossings, not by area
    image, truth, _ = render_line(CLEAN.with_(fwhm_px=4.0, slope_px_per_row=0.0, bow_px=0.0))
    image = image.copy()
    image[:, 328:, 2] = np.minimum(image[:, 328:, 2].astype(int) + 60, 255).astype(np.uint8)
    result = extract_laser_line(image)
    assert len(result) == image.shape[0]
    assert np.max(np.abs(errors(result, truth))) <= 0.15
    assert abs(float(np.median(result.width)) - 4.0) <= 0.4


def test_saturated_rows_report_the_width_between_the_crossings_of_the_plateau():
    image, truth, _ = render_line(CLEAN.with_(amplitude_dn=700.0, fwhm_px=5.0))
    result = extract_laser_line(image)
    assert result.rows_saturated == len(result) == image.shape[0]
    # a clipped Gaussian of 700 DN at 255: half of 255 is reached ~1.7 x further out than half of 700
    assert np.all((result.width > 5.0) & (result.width < 12.0))
    assert np.max(np.abs(errors(result, truth))) <= 0.15


@pytest.mark.parametrize("method", ["blais_rioux4", "gaussian3", "com"])
def test_tracking_and_full_search_agree_on_mono_and_texture_frames(method):
    # the column-major tracking windows (colour, mono, with and without a laser-off frame)
    # against the row-major full-row search of the same frames
    scene = LineScene(ambient=0.3, seed=13, slope_px_per_row=-0.11, bow_px=14.0)
    image, truth, _ = render_line(scene)
    texture, _, _ = render_line(scene.with_(amplitude_dn=0.0, seed=14))
    for img, tex in ((image[..., 2].copy(), None), (image, texture), (image[..., 2].copy(), texture[..., 2].copy())):
        tracked = extract_laser_line(img, ExtractorParams(method=method), texture=tex)
        full = extract_laser_line(img, ExtractorParams(method=method, window_px=0), texture=tex)
        assert_finite(tracked)
        assert len(tracked) >= image.shape[0] - 2
        np.testing.assert_array_equal(tracked.v, full.v)
        np.testing.assert_allclose(tracked.u, full.u, atol=1e-4)
        np.testing.assert_allclose(tracked.width, full.width, atol=1e-4)
        assert np.max(np.abs(errors(tracked, truth))) <= 1.0  # on the line (mono frames clip: gaussian3 is coarse there)


def test_frame_noise_is_the_robust_sigma_of_the_thresholded_contrast():
    # mono frame of pure Gaussian noise sigma 4: a height above the mean of two samples 11 px away
    # has sigma 4 * sqrt(1 + 1/2)
    rng = np.random.default_rng(11)
    image = np.clip(np.rint(100.0 + 4.0 * rng.standard_normal((480, 640))), 0, 255).astype(np.uint8)
    sigma = contrast_noise(LaserSignal(image).rows_clipped(np.arange(4, 480, 8)), 11)
    assert abs(sigma - 4.0 * np.sqrt(1.5)) <= 0.1 * 4.0 * np.sqrt(1.5)


def test_a_faint_line_on_a_quiet_frame_is_found_below_the_fixed_threshold():
    # 18 DN of laser on a quiet uniform background: under the fixed 30 DN, over 8 sigmas of this frame's noise
    scene = CLEAN.with_(amplitude_dn=18.0, read_noise_dn=0.8, seed=2)
    image, truth, _ = render_line(scene)
    fixed = extract_laser_line(image, ExtractorParams(contrast_sigmas=0.0))
    adaptive = extract_laser_line(image)
    assert len(fixed) < 0.1 * image.shape[0]
    assert len(adaptive) == image.shape[0]
    assert np.sqrt(np.mean(errors(adaptive, truth) ** 2)) <= 0.15


def test_noisier_frames_keep_the_fixed_threshold():
    # at 50 % ambient on reddish texture the frame's 8 sigmas exceed 30 DN: min_contrast holds
    scene = LineScene(ambient=0.5, first_row=100, last_row=380, reflection=0.3, seed=8)
    image, _, _ = render_line(scene)
    a, b = extract_laser_line(image), extract_laser_line(image, ExtractorParams(contrast_sigmas=0.0))
    np.testing.assert_array_equal(a.u, b.u)


@pytest.mark.parametrize("name, value, message", [
    ("clipped_centre", "middle", "clipped_centre 'middle' is unknown; must be one of: signal, red"),
    ("contrast_sigmas", -1.0, r"contrast_sigmas must be within \[0, 100\]"),
])
def test_real_light_parameters_are_checked(name, value, message):
    with pytest.raises(ExtractorConfigError, match=message):
        ExtractorParams(**{name: value})


def test_a_weak_detection_no_neighbouring_row_continues_is_dropped():
    """`drop_isolated`: a weak row whose column no detection within 2 rows continues (3 px per row) goes; a strong
    one, or one the line continues (also across a missing row), stays."""
    from lsu_extract.extractor import drop_isolated

    v = np.array([10, 11, 12, 14, 30, 40, 50, 51], np.int64)
    u = np.array([100.0, 101.0, 102.0, 105.5, 300.0, 310.0, 200.0, 209.0], np.float32)
    peak = np.array([50.0, 13.0, 50.0, 13.0, 13.0, 60.0, 13.0, 13.0], np.float32)  # threshold 12: weak below 24
    found = {"v": v, "u": u, "peak": peak, "width": np.full(8, 3.0, np.float32), "quality": np.ones(8, np.float32)}
    kept, dropped = drop_isolated(found, 12.0, 64)
    # row 14 continues row 12 (3.5 px over 2 rows); rows 30, 50 and 51 are weak and alone (51 is 9 px from 50)
    assert dropped == 3 and kept["v"].tolist() == [10, 11, 12, 14, 40]
    assert kept["u"].tolist() == [100.0, 101.0, 102.0, 105.5, 310.0]
    assert set(kept) == {"v", "u", "peak", "width", "quality"}
    assert drop_isolated(found, 6.0, 64) == (found, 0)  # nothing weak at a 6 DN threshold: unchanged

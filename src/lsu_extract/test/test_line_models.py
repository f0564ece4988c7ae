"""The extractor's per-row models on four kinds of line, each against the analytic centre it was rendered with.

Truth: `lsu_extract.synthetic` (pixel-integrated Gaussian profile, crosstalk, texture, seeded noise), never a
detector's output. Each case states its error bound; the bounds hold with a margin of ~1.3x the RMS measured
over the same seeds (bench/study_extract.py and bench_extract's analytic sweeps give the figures).
"""

from __future__ import annotations

import numpy as np
import pytest

from lsu_common.arrays import AnyArray
from lsu_extract.extractor import ROW_MODELS, ExtractorParams, explain_rows, extract_laser_line
from lsu_extract.synthetic import LineScene, render_line

SEEDS = (0, 1, 2)

# name: (scene, RMS bound [px], the model most rows must be centred with)
CASES = {
    # red clips over ~4 px, green/blue +30-45 DN in the core (crosstalk): centred on the flanks
    "clipped_crosstalk": (LineScene(amplitude_dn=420.0, leak_green=0.10, leak_blue=0.08, fwhm_px=7.0), 0.16,
                          "flanks_signal"),
    # FWHM 12 px, 120 DN: wider than a zero-crossing filter's model
    "wide_soft": (LineScene(fwhm_px=12.0, amplitude_dn=120.0), 0.45, "com"),
    # FWHM 2.5 px on a plain background
    "thin_sharp": (LineScene(fwhm_px=2.5, textured=False), 0.04, "blais_rioux4"),
    # 50 % ambient on the reddish texture with redder blotches; the laser in rows 60..419 only
    "textured": (LineScene(ambient=0.5, first_row=60, last_row=419), 0.11, None),
}


def run(scene: LineScene, params: ExtractorParams) -> tuple[AnyArray, int, int, AnyArray]:
    """(errors of the correct detections, false rows, missed rows, model codes) over SEEDS."""
    errs, codes = [], []
    false = missed = 0
    for seed in SEEDS:
        image, truth, visible = render_line(scene.with_(seed=seed, texture_seed=seed))
        result = extract_laser_line(image, params)
        rows = result.v.astype(int)
        err = result.u - truth[rows]
        good = visible[rows] & (np.abs(err) <= 2.0)
        errs.append(err[good])
        false += int(np.count_nonzero(~good))
        missed += int(np.count_nonzero(visible)) - int(np.count_nonzero(good))
        codes.append(explain_rows(result, params)[0])
    return np.concatenate(errs), false, missed, np.concatenate(codes)


@pytest.mark.parametrize("case", list(CASES))
def test_adaptive_line_within_its_stated_error_with_the_model_it_says(case):
    scene, bound, model = CASES[case]
    params = ExtractorParams(method="adaptive")
    err, false, missed, codes = run(scene, params)
    visible_rows = len(SEEDS) * (scene.last_row - scene.first_row + 1 if scene.last_row >= 0 else scene.height)
    assert float(np.sqrt(np.mean(err ** 2))) <= bound
    assert abs(float(np.mean(err))) <= 0.1  # no bias of the model on a symmetric profile
    assert false == 0 and missed <= 0.01 * visible_rows
    if model is not None:
        assert np.count_nonzero(codes == ROW_MODELS.index(model)) >= 0.9 * codes.size


def test_wide_line_centre_of_mass_beats_the_zero_crossing_filter():
    # the reason the adaptive method leaves Blais-Rioux on wide lines: the same frames, the 8th-order filter
    scene = CASES["wide_soft"][0]
    adaptive = run(scene, ExtractorParams(method="adaptive"))[0]
    br8 = run(scene, ExtractorParams(method="blais_rioux8"))[0]
    assert np.sqrt(np.mean(adaptive ** 2)) < 0.95 * np.sqrt(np.mean(br8 ** 2))


def test_explain_names_a_reason_for_every_model_used():
    image, _, _ = render_line(CASES["clipped_crosstalk"][0])
    params = ExtractorParams(method="adaptive")
    result = extract_laser_line(image, params)
    codes, why = explain_rows(result, params)
    assert codes.shape == (len(result),)
    assert result.saturated is not None and result.saturated.shape == (len(result),)
    used = {ROW_MODELS[int(c)] for c in np.unique(codes)}
    assert used == set(why) and "flanks_signal" in used
    assert all("clipped" in why[m] for m in used if m.startswith("flanks"))
    # a frame without clipping carries no per-row flag, and no row is said to be clipped
    plain, _, _ = render_line(CASES["thin_sharp"][0])
    result = extract_laser_line(plain, params)
    assert result.saturated is None
    codes, why = explain_rows(result, params)
    assert not any(m.startswith("flanks") for m in why)
    # a thin symmetric line: Blais-Rioux 4; a rare row that noise makes look skewed takes the centre of mass
    assert np.count_nonzero(codes == ROW_MODELS.index("blais_rioux4")) >= 0.98 * codes.size


def test_a_line_widening_beyond_max_width_is_followed_only_with_grow_wide():
    # rows 0..239 a 4 px line, rows 240..479 the same line 28 px wide (FWHM; beyond max_width_px 16), as where the
    # light grazes a surface; truth: the analytic centre, the same for both halves
    narrow, truth, _ = render_line(LineScene(textured=False, seed=3))
    wide, _, _ = render_line(LineScene(textured=False, fwhm_px=28.0, amplitude_dn=120.0, seed=4))
    image = np.concatenate([narrow[:240], wide[240:]])
    default = extract_laser_line(image, ExtractorParams(grow_wide=False))
    grown = extract_laser_line(image, ExtractorParams(grow_wide=True))
    low = grown.v >= 240
    assert np.count_nonzero(low) >= 0.95 * 240 > np.count_nonzero(default.v >= 240)
    err = grown.u[low] - truth[grown.v[low].astype(int)]
    assert float(np.sqrt(np.mean(err ** 2))) <= 0.5


def test_grow_wide_does_not_follow_into_a_patch_without_the_line():
    # the line stops at row 239; below it, right where the line would go on, a broad red glow (FWHM 59 px, no laser):
    # wider than GROW_MAX_WIDTH_PX, so growing from the line's end takes none of it. (A glow within the width limits
    # is indistinguishable from a wide line row by row; and growth follows any detection that is not weak and
    # isolated, false ones too: grow_wide's false rows on frames alone, bench/results/extract.json.)
    image, truth, _ = render_line(LineScene(textured=False, last_row=239, seed=5))
    patch = image.astype(np.int16)
    cols = np.arange(image.shape[1])
    bump = (80.0 * np.exp(-0.5 * ((cols - truth[300]) / 25.0) ** 2)).astype(np.int16)
    patch[240:, :, 2] += bump[None, :]
    image = np.clip(patch, 0, 255).astype(np.uint8)
    grown = extract_laser_line(image, ExtractorParams(grow_wide=True))
    default = extract_laser_line(image, ExtractorParams(grow_wide=False))
    assert grown.extra.get("rows_grown", 0) <= 2
    assert np.count_nonzero(grown.v >= 242) <= np.count_nonzero(default.v >= 242) + 2



def test_a_profile_not_symmetric_about_its_centre_is_flagged_and_explained():
    # the 4 px line with a weaker patch (60 DN, FWHM 3.5 px) 5 px to its right, inside the refinement window: the
    # window's centroid leaves the Blais-Rioux centre by more than SKEW_PX, so the rows are centred by the centre of
    # mass above half height (which leaves the patch out) and say so; truth: the analytic centre. (The limb rows of
    # bench_reconstruct's sphere are what the rule is for; at 4 px the patch merges above half height and moves
    # both estimators.)
    scene = LineScene(textured=False, seed=7)
    image, truth, _ = render_line(scene)
    cols = np.arange(image.shape[1])[None, :]
    patched = image.astype(np.float64)
    patched[..., 2] += 60.0 * np.exp(-0.5 * ((cols - truth[:, None] - 5.0) / 1.5) ** 2)
    patched = np.clip(patched, 0, 255).astype(np.uint8)
    params = ExtractorParams(method="adaptive")
    result = extract_laser_line(patched, params)
    assert len(result) == image.shape[0]
    assert result.skewed is not None and np.count_nonzero(result.skewed) >= 0.9 * len(result)
    codes, why = explain_rows(result, params)
    assert np.all(codes[result.skewed] == ROW_MODELS.index("com")) and "symmetric" in why["com"]
    err = result.u - truth[result.v.astype(int)]
    assert float(np.sqrt(np.mean(err ** 2))) <= 0.1


def test_red_print_whose_red_does_not_rise_is_not_taken_for_the_laser():
    # A light grey-white ground (BGR 200/205/195) with a printed red stripe 4 px wide in rows 0..239: ink that takes
    # green and blue away (-110 DN) and leaves red as it was, so red - max(green, blue) rises as a laser's would. In rows
    # 240..479 a laser line of the same width adds 120 DN of red (and its 6/4 % crosstalk) to the same ground. Truth:
    # where each was drawn. A person tells them apart by red: the laser's rises, the print's does not
    # (`red_rise_ratio`); without the rule the print's rows are taken for the laser.
    height, width = 480, 640
    cols = np.arange(width, dtype=np.float64)
    ground = np.empty((height, width, 3))
    ground[...] = (200.0, 205.0, 195.0)
    rng = np.random.default_rng(11)
    print_u, laser_u = 201.3, 402.6
    ink = np.exp(-0.5 * ((cols - print_u) / (4.0 / 2.3548)) ** 2)
    light = np.exp(-0.5 * ((cols - laser_u) / (4.0 / 2.3548)) ** 2)
    ground[:240, :, :2] -= 110.0 * ink[None, :, None]
    ground[240:, :, 2] += 120.0 * light[None, :] * 0.45  # red stays below clipping: 195 + 54
    ground[240:, :, 1] += 0.06 * 120.0 * light[None, :]
    ground[240:, :, 0] += 0.04 * 120.0 * light[None, :]
    image = np.clip(ground + rng.normal(0.0, 1.0, ground.shape), 0, 255).astype(np.uint8)
    result = extract_laser_line(image)
    print_rows = result.v < 240
    assert np.count_nonzero(print_rows) == 0
    laser = result.v >= 240
    assert np.count_nonzero(laser) >= 0.99 * 240
    assert float(np.sqrt(np.mean((result.u[laser] - laser_u) ** 2))) <= 0.1
    # the rule switched off: the print is taken (what the rule is for)
    off = extract_laser_line(image, ExtractorParams(red_rise_ratio=0.0))
    assert np.count_nonzero(np.abs(off.u[off.v < 240] - print_u) <= 1.0) >= 0.9 * 240


def test_a_line_wider_than_max_width_is_found_with_its_laser_off_frame():
    # FWHM 36 px (beyond max_width_px 16, as where the turntable globe's line grazes the surface or nears the camera)
    # at 50 % ambient; the laser-off frame of the same view (new noise) cancels the background, so the width limit
    # that keeps red print out of a single frame is lifted to LASER_OFF_MAX_WIDTH_PX. Truth: the analytic centre. (A
    # uniform surface: on the mottled one the laser's own reflection is mottled, and so is a wide line's centroid.)
    scene = LineScene(fwhm_px=36.0, amplitude_dn=120.0, ambient=0.5, textured=False, seed=12)
    image, truth, _ = render_line(scene)
    off, _, _ = render_line(scene.with_(amplitude_dn=0.0, seed=13))
    alone = extract_laser_line(image)
    paired = extract_laser_line(image, texture=off)
    assert len(alone) < 0.05 * image.shape[0]
    assert len(paired) >= 0.99 * image.shape[0]
    err = paired.u - truth[paired.v.astype(int)]
    assert float(np.sqrt(np.mean(err ** 2))) <= 0.4 and abs(float(np.mean(err))) <= 0.05


def test_a_line_on_a_surface_whose_blue_clips_is_found():
    # A bluish-white ground (blue 255: clipped; green 200, red 165) and a 4 px laser line that adds 90 DN of red and 6 %
    # of it to green (blue cannot rise): red - max(green, blue) is <= 0 under the line, red - green rises 90 DN. Truth:
    # where the line was drawn.
    height, width = 480, 640
    cols = np.arange(width, dtype=np.float64)
    rng = np.random.default_rng(14)
    line_u = 300.4
    light = np.exp(-0.5 * ((cols - line_u) / (4.0 / 2.3548)) ** 2)
    image = np.empty((height, width, 3))
    image[..., 0] = 262.0  # clipped with its noise
    image[..., 1] = 200.0 + 0.06 * 90.0 * light[None, :]
    image[..., 2] = 165.0 + 90.0 * light[None, :]
    image = np.clip(image + rng.normal(0.0, 1.0, image.shape), 0, 255).astype(np.uint8)
    result = extract_laser_line(image)
    assert len(result) >= 0.99 * height
    assert float(np.sqrt(np.mean((result.u - line_u) ** 2))) <= 0.1


def test_a_mono_stripe_beside_a_brighter_broad_patch_is_found():
    # A mono frame (weld camera): a 4 px stripe 60 DN over a 60 DN ground, and 80 px to its left, in rows 100..379, a
    # lit patch (FWHM 40 px) that reaches 220 DN: brighter than the stripe in the same rows. Truth: where the stripe was
    # drawn. Chosen by raw height the patch wins those rows and fails as a line (too wide); above its own
    # surroundings the stripe stands out (`tracking.local_candidates`).
    height, width = 480, 640
    cols = np.arange(width, dtype=np.float64)
    rng = np.random.default_rng(15)
    stripe_u = 350.3
    image = np.full((height, width), 60.0)
    image += 60.0 * np.exp(-0.5 * ((cols - stripe_u) / (4.0 / 2.3548)) ** 2)[None, :]
    image[100:380] += 160.0 * np.exp(-0.5 * ((cols - stripe_u + 80.0) / (40.0 / 2.3548)) ** 2)[None, :]
    image = np.clip(image + rng.normal(0.0, 1.5, image.shape), 0, 255).astype(np.uint8)
    result = extract_laser_line(image)
    assert np.count_nonzero((result.v >= 100) & (result.v < 380)) >= 0.99 * 280
    assert len(result) >= 0.99 * height
    assert float(np.sqrt(np.mean((result.u - stripe_u) ** 2))) <= 0.1

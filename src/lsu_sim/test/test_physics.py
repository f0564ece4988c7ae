"""The simulated rig's physics: speckle, skin, blooming, Bayer mosaic, per-camera exposure start."""

import dataclasses

import cv2
import numpy as np
import pytest
import yaml
from scipy.special import erf

from lsu_cameras.paths import config_dir
from lsu_sim import (
    CarriageState,
    RigConfigError,
    SimulatedRig,
    build_scene,
    load_rig,
    make_plane,
    rig_from_dict,
)
from lsu_sim.physics import (
    BAYER_PATTERNS,
    ERF_ONE,
    bloom,
    demosaic,
    mosaic,
    skin_profile,
    skin_profile_box,
    skin_profile_tails,
    speckle_tiles,
    surface_profile_box,
)
from lsu_sim.scenes import SceneError, uniform_albedo


@pytest.mark.parametrize("pattern", sorted(BAYER_PATTERNS))
def test_bayer_mosaic_and_opencv_demosaic_restore_a_uniform_colour(pattern):
    img = np.zeros((12, 16, 3), np.uint8)
    img[...] = (10, 100, 200)  # B, G, R
    raw = mosaic(img, pattern)
    # the top-left 2x2 holds the colours the pattern's name says
    channel = {"B": 0, "G": 1, "R": 2}
    assert [raw[k // 2, k % 2] for k in range(4)] == [img[0, 0, channel[c]] for c in pattern]
    assert np.array_equal(demosaic(raw, pattern)[2:-2, 2:-2], img[2:-2, 2:-2])


def test_blooming_clips_at_full_well_and_spills_along_the_column():
    img = np.full((5, 5), 0.2, np.float32)
    img[2, 2] = 3.0
    bloom(img, 0.5)
    assert img[2, 2] == pytest.approx(1.0)
    # excess 2.0, half of it spills, split between the pixels above and below
    assert img[1, 2] == pytest.approx(0.7) and img[3, 2] == pytest.approx(0.7)
    assert img[2, 1] == pytest.approx(0.2) and img[2, 3] == pytest.approx(0.2)
    unsaturated = np.full((3, 3), 0.9, np.float32)
    bloom(unsaturated, 0.5)
    assert np.all(unsaturated == np.float32(0.9))


def test_skin_profile_keeps_the_energy_and_moves_and_widens_the_line_as_the_kernel_says():
    d = np.linspace(-0.03, 0.03, 60001)
    sheet = 0.001 / 2.3548
    s2 = np.full_like(d, sheet ** 2)
    b, shift, frac = 0.001, 0.0004, 0.9
    prof = skin_profile(d, s2, sheet, np.full_like(d, b), np.full_like(d, shift), frac)
    surface = np.exp(-0.5 * d * d / sheet ** 2)
    area = np.trapezoid(prof, d)
    assert area == pytest.approx(np.trapezoid(surface, d), rel=1e-4)
    mean = np.trapezoid(prof * d, d) / area
    var = np.trapezoid(prof * (d - mean) ** 2, d) / area
    assert mean == pytest.approx(frac * shift, rel=1e-3)
    # mixture: (1-f) N(0, s^2) + f (N(shift, s^2) * Laplace(b)); a Laplace kernel has variance 2 b^2
    expected_var = sheet ** 2 + frac * 2 * b * b + frac * (1 - frac) * shift ** 2
    assert var == pytest.approx(expected_var, rel=1e-3)


@pytest.mark.parametrize("b", [1e-3, 3e-4, 3e-5, 1e-6])
def test_closed_form_exposure_average_and_kernel_tails_equal_the_sampled_profile(b):
    # a moving sheet sweeps its offset uniformly over [lo, hi] during the exposure: the closed form must equal
    # the mean of the profile over 4000 sub-exposures (the midpoint rule, independent of the erf/CDF algebra)
    d = np.linspace(-0.012, 0.012, 4001)
    sheet = 0.001 / 2.3548
    s2, width, shift = np.full_like(d, 0.00045 ** 2), np.full_like(d, b), np.full_like(d, 0.0003)
    lo, hi = -0.0007, 0.0008
    offsets = lo + (np.arange(4000) + 0.5) / 4000 * (hi - lo)
    sampled = np.mean([skin_profile(d - o, s2, sheet, width, shift, 0.9) for o in offsets], axis=0)
    box = skin_profile_box(d - hi, d - lo, s2, sheet, width, shift, 0.9)
    assert np.max(np.abs(box - sampled)) < 1e-6 * sampled.max()
    exact = skin_profile(d, s2, sheet, width, shift, 0.9)
    assert np.max(np.abs(skin_profile_tails(d, s2, sheet, width, shift, 0.9) - exact)) < 1e-8 * exact.max()


def test_box_profile_skips_erf_only_where_it_is_exactly_one():
    # the closed-form box average leaves out intervals entirely beyond +-ERF_ONE: that needs erf(x) == 1.0
    # exactly there (a library that rounds it below 1 would change the images, so this fails instead)
    x = np.linspace(ERF_ONE, 40.0, 400001)
    assert np.all(erf(x) == 1.0) and np.all(erf(-x) == -1.0)
    # and the profile equals the plain formula (both erf evaluated) bit for bit, far and near the sheet
    rng = np.random.default_rng(4)
    sheet = 0.001 / 2.3548
    s2 = sheet ** 2 + rng.uniform(0.0, 4.0, 20000) * sheet ** 2
    d_lo = rng.uniform(-0.02, 0.02, 20000)
    d_hi = d_lo + rng.uniform(1e-5, 2e-3, 20000)
    r = 1.0 / np.sqrt(2.0 * s2)
    plain = (erf(d_hi * r) - erf(d_lo * r)) * (sheet * np.sqrt(0.5 * np.pi) / (d_hi - d_lo))
    assert np.array_equal(surface_profile_box(d_lo, d_hi, s2, sheet), plain)
    assert np.count_nonzero(plain == 0.0) > 1000 and np.count_nonzero(plain > 0.1) > 100


def test_speckle_tiles_are_seeded_and_independent_between_cameras():
    a = speckle_tiles(671e-9, 2.0, 0.02, 7.5e-6, 96, 32, 1, 0)
    b = speckle_tiles(671e-9, 2.0, 0.02, 7.5e-6, 96, 32, 1, 1)
    assert np.array_equal(a, speckle_tiles(671e-9, 2.0, 0.02, 7.5e-6, 96, 32, 1, 0))
    assert a.mean() == pytest.approx(1.0, abs=1e-5)
    assert abs(np.corrcoef(a.ravel(), b.ravel())[0, 1]) < 0.05
    # a pixel of 7.5 um averages several 3.3 um grains: contrast well below 1, well above 0
    assert 0.1 < a.std() < 0.4
    # at f/8 the grain is larger than the pixel: higher contrast
    assert speckle_tiles(671e-9, 8.0, 0.02, 7.5e-6, 96, 32, 1, 0).std() > 2 * a.std()


def _plane_rig(**sensor):
    g = load_rig()
    g = dataclasses.replace(g, sensor=dataclasses.replace(g.sensor, **sensor))
    x, y, z = g.rig_axes
    return SimulatedRig(g, [make_plane(g.rig_center + 0.3 * z, -z, albedo=uniform_albedo((0.8, 0.8, 0.8)))], seed=3)


def test_speckle_realisation_is_seeded_and_new_for_every_capture():
    rig = _plane_rig(read_noise_dn=0.0, full_well_e=1e15)
    a, b = rig.render(235.0, seed=5), rig.render(235.0, seed=5)
    c = rig.render(235.0, seed=6)
    assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
    # without sensor noise only the speckle differs between the two captures: on the line, not off it
    diff = np.abs(a.left.astype(int) - c.left.astype(int))[:, :, 2]
    line = a.left[:, :, 2] > np.percentile(a.left[:, :, 2], 99)
    assert diff[line].mean() > 3.0
    assert diff[~line].mean() < 0.5


def test_each_camera_reads_the_carriage_at_its_own_exposure_start():
    rig = _plane_rig(capture_offset_s=0.030)
    state = CarriageState(235.0, stopped_at_s=0.0, vibration_amplitude_steps=3.0, vibration_tau_s=0.08,
                          vibration_freq_hz=10.0)
    frame = rig.render(state, capture_time_s=0.002, seed=1)
    exposure = rig.geometry.sensor.exposure_s
    n = rig.geometry.sensor.sub_exposures
    for start, offset in zip((0.002, 0.032), frame.laser_offsets_steps):
        t = start + (np.arange(n) + 0.5) / n * exposure
        assert offset == pytest.approx(float(state.displacement_steps(t).mean()), abs=1e-12)
    assert frame.exposure_start_s == pytest.approx((0.002, 0.032))
    assert abs(frame.laser_offsets_steps[0] - frame.laser_offsets_steps[1]) > 0.1
    rig.set_capture_timing(0.0, 0.0)
    same = rig.render(state, capture_time_s=0.002, seed=1)
    assert same.laser_offsets_steps[0] == pytest.approx(same.laser_offsets_steps[1])
    with pytest.raises(ValueError, match="jitter"):
        rig.set_capture_timing(0.0, -1.0)


def test_bad_physics_settings_are_refused_with_the_field_named():
    data = yaml.safe_load((config_dir() / "sim_rig.yaml").read_text())
    for section, key, value, words in (("sensor", "bayer", "XYZW", "sensor.bayer"),
                                       ("sensor", "blooming", 2.0, "sensor.blooming"),
                                       ("speckle", "contrast", 1.5, "speckle.contrast"),
                                       ("skin", "subsurface_fraction", -0.1, "subsurface_fraction")):
        bad = yaml.safe_load(yaml.safe_dump(data))
        bad[section][key] = value
        with pytest.raises(RigConfigError, match=words):
            rig_from_dict(bad)
    with pytest.raises(SceneError, match="material"):
        make_plane((0, 0, 0.3)).__class__("x", make_plane((0, 0, 0.3)).mesh, uniform_albedo((1, 1, 1)),
                                           material="metal")


def _row_centres(image, columns, rows, half=10):
    """Red-minus-row-median centroid around the given columns (the test's own estimator)."""
    red = image[:, :, 2].astype(float)
    out = []
    for r, c in zip(rows, columns):
        lo = int(round(c)) - half
        w = np.clip(red[r, lo:lo + 2 * half + 1] - np.median(red[r]) - 6.0, 0.0, None)
        out.append((w * np.arange(lo, lo + 2 * half + 1)).sum() / w.sum() if w.sum() > 0 else np.nan)
    return np.array(out)


@pytest.mark.parametrize("noise", [False, True])
def test_fast_render_puts_the_line_where_the_reference_render_does_on_a_moving_skin_head(noise):
    g = load_rig()
    if not noise:
        g = dataclasses.replace(g, sensor=dataclasses.replace(g.sensor, read_noise_dn=0.0, full_well_e=1e15))
    objects = build_scene("head:7", g)
    assert any(o.material == "skin" for o in objects)
    fast, reference = SimulatedRig(g, objects, seed=3), SimulatedRig(g, objects, seed=3, reference=True)
    for position, start in ((150.0, 0.004), (300.0, 0.011)):
        state = CarriageState(position, velocity_steps_per_s=180.0, position_time_s=0.0)  # the fastest sweep
        a = fast.render(state, capture_time_s=start, seed=11)
        b = reference.render(state, capture_time_s=start, seed=11)
        assert a.laser_offsets_steps == b.laser_offsets_steps
        for side in ("left", "right"):
            # rows and columns from the renderer's ray-cast truth at the sheet's mid-exposure position
            truth = getattr(fast.laser_truth(position + a.laser_offsets_steps[0 if side == "left" else 1]), side)
            cols = truth.pixels[:, 0]
            keep = (cols > 15) & (cols < 625)
            rows = np.round(truth.pixels[keep, 1]).astype(int)
            ca = _row_centres(getattr(a, side), cols[keep], rows)
            cb = _row_centres(getattr(b, side), cols[keep], rows)
            diff = np.abs(ca - cb)[np.isfinite(ca - cb)]
            assert len(diff) > 300
            if not noise:
                # the same speckle and the same sheet: only the sub-exposure sum vs the exact interval average
                # and 1 DN of rounding differ
                assert np.percentile(diff, 95) < 0.02 and diff.max() < 0.2
            else:
                # independent noise realisations: the centres differ by the noise, not by a bias
                assert np.median(diff) < 0.1
                assert abs(np.median(np.clip((ca - cb)[np.isfinite(ca - cb)], -0.5, 0.5))) < 0.02
                err_a, err_b = np.nanmedian(np.abs(ca - cols[keep])), np.nanmedian(np.abs(cb - cols[keep]))
                assert err_a == pytest.approx(err_b, rel=0.15)


def test_fast_render_noise_has_the_reference_sigma_and_is_new_in_every_capture():
    g = load_rig()
    x, y, z = g.rig_axes
    plane = [make_plane(g.rig_center + 0.3 * z, -z, albedo=uniform_albedo((0.5, 0.5, 0.5)))]
    fast, reference = SimulatedRig(g, plane, seed=1), SimulatedRig(g, plane, seed=1, reference=True)
    off = CarriageState(235.0, laser_on=False)
    f1, f2 = fast.render(off, seed=1).left.astype(float), fast.render(off, seed=2).left.astype(float)
    r1, r2 = reference.render(off, seed=1).left.astype(float), reference.render(off, seed=2).left.astype(float)
    # the difference of two captures is pure noise (sqrt 2 sigma): same sigma as the reference's fresh draws
    centre = (slice(100, 380), slice(120, 520))
    assert np.std((f1 - f2)[centre]) == pytest.approx(np.std((r1 - r2)[centre]), rel=0.03)
    assert np.mean(f1[centre]) == pytest.approx(np.mean(r1[centre]), abs=0.05)
    # a pixel's noise is independent from capture to capture (high-passed: the lamp's shading removed)
    a, b = ((f - cv2.blur(f, (9, 9)))[centre].ravel() for f in (f1, f2))
    assert abs(np.corrcoef(a, b)[0, 1]) < 0.02
    assert np.array_equal(fast.render(off, seed=1).left, f1.astype(np.uint8))

"""The simulated rig's physics: speckle, skin, blooming, Bayer mosaic, per-camera exposure start."""

import dataclasses

import numpy as np
import pytest
import yaml

from lsu_cameras.paths import config_dir
from lsu_cameras.sim import CarriageState, RigConfigError, SimulatedRig, load_rig, make_plane, rig_from_dict
from lsu_cameras.sim.physics import BAYER_PATTERNS, bloom, demosaic, mosaic, skin_profile, speckle_tiles
from lsu_cameras.sim.scenes import SceneError, uniform_albedo


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

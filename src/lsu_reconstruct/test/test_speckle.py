"""The speckle limit: its closed forms, and the rendered speckle of the simulated rig measured against it."""

import dataclasses
import math

import numpy as np
import pytest

from lsu_common.arrays import AnyArray
from lsu_reconstruct.speckle import (
    correlation_area_m2,
    grain_diameter_m,
    image_aperture,
    row_correlation_integral_m,
    speckle_limit,
)
from lsu_sim import CarriageState, SimulatedRig, load_rig, make_plane
from lsu_sim.scenes import uniform_albedo

LAMBDA = 671e-9


def test_closed_forms_match_the_literature_numbers():
    # 671 nm at f/2, M ~ 0.02: grain 2.44 lambda N (1 + M) = 3.34 um; Dorsch's image-side floor lambda / (2 pi NA')
    na = image_aperture(2.0, 0.0207)
    assert grain_diameter_m(LAMBDA, 2.0, 0.0207) == pytest.approx(2.44 * 671e-9 * 2 * 1.0207, rel=1e-12)
    lim = speckle_limit(671, 2.0, 812.4, 7.5e-6, 0.1226, 0.30, 0.001 / 2.3548)
    assert lim.dorsch_px * 7.5e-6 == pytest.approx(LAMBDA / (2 * math.pi * na), rel=1e-3)
    # the row-averaged correlation integral tends to the correlation area / row height for tall rows
    for h in (30e-6, 100e-6):
        assert row_correlation_integral_m(LAMBDA, na, h) == pytest.approx(correlation_area_m2(LAMBDA, na) / h, rel=0.05)
    # a line of ~2 grains is above Dorsch's diffraction-limited floor, and the law grows as sqrt(width)
    assert lim.line_px > lim.dorsch_px
    wide = speckle_limit(671, 2.0, 812.4, 7.5e-6, 0.1226, 0.30, 4 * 0.001 / 2.3548)
    assert wide.line_px / lim.line_px == pytest.approx(2.0, rel=1e-9)
    # stereo depth: z^2 / (f B) * sqrt 2 * line error
    assert lim.depth_mm == pytest.approx(0.3 ** 2 / (812.4 * 0.1226) * math.sqrt(2) * lim.line_px * 1000, rel=1e-9)
    # an intensity blur after the speckle averages rows: lower, and at 0 the same
    assert speckle_limit(671, 2.0, 812.4, 7.5e-6, 0.1226, 0.30, 0.001 / 2.3548, row_blur_px=0.5).line_px < lim.line_px
    assert speckle_limit(671, 2.0, 812.4, 7.5e-6, 0.1226, 0.30, 0.001 / 2.3548, row_blur_px=0.0) == lim
    with pytest.raises(ValueError, match="f_number"):
        speckle_limit(671, 0.0, 812.4, 7.5e-6, 0.1226, 0.30, 0.0004)


def _row_centroids(on: AnyArray, off: AnyArray, pixels: AnyArray, half: int = 7) -> AnyArray:
    """Centre of mass of (laser on - laser off) red over a window around each true pixel (a plain estimator)."""
    diff = on[:, :, 2].astype(float) - off[:, :, 2].astype(float)
    out = []
    for u, v in pixels:
        lo = int(round(u)) - half
        w = diff[int(v), lo:lo + 2 * half + 1]
        cols = np.arange(lo, lo + 2 * half + 1)
        out.append((w * cols).sum() / w.sum())
    return np.array(out) - pixels[:, 0]


def _line_errors(contrast: float, positions, seed: int):
    geometry = load_rig()
    # no sensor noise, no blooming, a dimmer laser so nothing saturates: only speckle moves the centroid
    geometry = dataclasses.replace(
        geometry, sensor=dataclasses.replace(geometry.sensor, read_noise_dn=0.0, full_well_e=1e15, blooming=0.0),
        speckle=dataclasses.replace(geometry.speckle, contrast=contrast),
        laser=dataclasses.replace(geometry.laser, power=0.45))
    x, y, z = geometry.rig_axes
    plane = make_plane(geometry.rig_center + 0.30 * z, -z, albedo=uniform_albedo((0.8, 0.8, 0.8)))
    rig = SimulatedRig(geometry, [plane], seed=seed)
    errors = {"left": [], "right": []}
    depth = {"left": [], "right": []}
    peak = 0
    for i, pos in enumerate(positions):
        on = rig.render(pos, seed=seed + i, with_truth=True)
        off = rig.render(CarriageState(float(pos), laser_on=False), seed=seed + i)
        for side, cam in (("left", geometry.left), ("right", geometry.right)):
            t = getattr(on.truth, side)
            keep = (t.pixels[:, 0] > 20) & (t.pixels[:, 0] < 620) & (t.pixels[:, 1] > 5) & (t.pixels[:, 1] < 475)
            errors[side].append(_row_centroids(getattr(on, side), getattr(off, side), t.pixels[keep]))
            depth[side].append((t.points_m[keep] @ cam.R.T + cam.t)[:, 2])
            peak = max(peak, int(getattr(on, side)[:, :, 2].max()))
    return geometry, {k: np.concatenate(v) for k, v in errors.items()}, {k: np.concatenate(v) for k, v in depth.items()}, peak


def test_rendered_speckle_scatters_the_line_centre_as_the_speckle_limit_says():
    """Speckled plane at 300 mm: per-row centroid scatter against the renderer's true line vs `speckle_limit`.

    The renderer's speckle is built from first principles (random phases through the lens pupil),
    the limit from the closed form: an independent check of both. The rig's lens blur acts on the
    intensity after the speckle and averages neighbouring rows, so the limit is taken with it. The
    same scene without speckle shows the estimator's own error is far below the limit.
    """
    positions = (150.0, 200.0, 235.0, 270.0, 320.0)
    geometry, errs, depth, peak = _line_errors(1.0, positions, seed=11)
    _, clean, _, _ = _line_errors(0.0, positions, seed=11)
    assert peak < 255, "the test needs an unsaturated line"
    for side in ("left", "right"):
        e, c = errs[side], clean[side]
        assert len(e) > 1500
        lim = speckle_limit(geometry.laser.wavelength_nm, geometry.sensor.f_number, float(geometry.left.K[0, 0]),
                            geometry.sensor.pixel_size_m, float(np.linalg.norm(geometry.translation)),
                            float(np.median(depth[side])), geometry.laser.sheet_sigma_m, 1.0,
                            row_blur_px=geometry.sensor.psf_sigma_px)
        clean_sd = float(np.std(c))
        measured = float(np.sqrt(max(np.var(e) - clean_sd ** 2, 0.0)))
        assert clean_sd < 0.3 * lim.line_px, (side, clean_sd, lim.line_px)
        assert measured == pytest.approx(lim.line_px, rel=0.30), (side, measured, lim.line_px)
        # a line wider than a grain scatters more than Dorsch's diffraction-limited floor
        assert lim.dorsch_px < measured < 0.5

"""row_sigma_px against the scatter the extractor actually shows on analytic lines (truth: the rendered centre)."""

from __future__ import annotations

import numpy as np
import pytest

from lsu_extract.extractor import extract_laser_line
from lsu_extract.synthetic import LineScene, render_line
from lsu_extract.uncertainty import row_sigma_px


@pytest.mark.parametrize("amplitude, read_noise", [(160.0, 2.0), (60.0, 2.0), (160.0, 6.0)])
def test_estimated_sigma_follows_the_observed_scatter(amplitude, read_noise):
    scene = LineScene(textured=False, ambient=0.0, amplitude_dn=amplitude, read_noise_dn=read_noise, shot_gain=0.0)
    errs, sigmas = [], []
    for seed in range(3):
        image, truth, _ = render_line(scene.with_(seed=seed))
        result = extract_laser_line(image)
        errs.append(result.u - truth[result.v.astype(int)])
        # the signal is red - max(green, blue): its noise is about read noise x 1.2 (a max of two adds a little)
        sigmas.append(row_sigma_px(result.peak, result.width, 1.2 * read_noise))
    observed = float(np.sqrt(np.mean(np.concatenate(errs) ** 2)))
    estimated = float(np.sqrt(np.mean(np.concatenate(sigmas) ** 2)))
    assert 0.7 * observed <= estimated <= 1.6 * observed  # measured: 1.2-1.3x over these cases


def test_floor_adds_in_quadrature_and_bad_input_is_refused():
    sigma = row_sigma_px(np.array([1e6]), np.array([4.0]), 1.0, floor_px=0.08)
    assert sigma[0] == pytest.approx(0.08, rel=1e-3)
    clipped = row_sigma_px(np.array([100.0]), np.array([4.0]), 2.0, saturated=np.array([True]))
    assert clipped[0] == pytest.approx(2.0 * row_sigma_px(np.array([100.0]), np.array([4.0]), 2.0)[0])
    with pytest.raises(ValueError, match="standard deviations"):
        row_sigma_px(np.array([100.0]), np.array([4.0]), -1.0)

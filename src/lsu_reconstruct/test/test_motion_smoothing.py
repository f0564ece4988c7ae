"""The measured poses' smoothing and the noise-relative verdict (`lsu_reconstruct.motion.smoothed_poses`,
`beyond_noise`): on synthetic pose tracks with a known truth and seeded measurement noise of the size a still face's
measurement shows on the simulated skin (docs/MOTION.md: ~0.1 deg rotation, ~0.1 mm translation, pose by pose: a
scatter of 0.34-0.40 mm at the box corners here, 0.23-0.39 mm measured on still sweeps of person 2).

Ground truth: the synthetic trajectories themselves (a still head, a seated head's slow drift of ~1 mm).
"""

from __future__ import annotations

import numpy as np
import pytest

from lsu_common.arrays import AnyArray
from lsu_reconstruct.motion import MotionParams, _box_shift_mm, beyond_noise, smoothed_poses

RATE_HZ, SECONDS = 10.0, 6.0          # every 3rd frame of a 30 fps face sweep
ROT_NOISE_RAD, T_NOISE_M = np.radians(0.08), 0.0001
CENTRE = np.array([0.0, 0.0, 0.3])
BOX = CENTRE + np.array([[a, b, c] for a in (-0.07, 0.07) for b in (-0.09, 0.09) for c in (-0.05, 0.05)])


def _track(drift_m: float, seed: int) -> tuple[AnyArray, AnyArray, AnyArray, int]:
    """Times, true poses and measured poses (M,6) of a head drifting ``drift_m`` along x over the sweep; the
    middle frame the reference (its measured pose exactly zero, as `estimate_motion` gives it)."""
    times = np.arange(0.0, SECONDS, 1.0 / RATE_HZ)
    ref = len(times) // 2
    truth = np.zeros((len(times), 6))
    truth[:, 3] = drift_m * (times - times[ref]) / SECONDS
    truth[:, 5] = 0.3 * drift_m * np.sin(2 * np.pi * 0.2 * times)   # a slow sway in depth
    truth -= truth[ref]
    rng = np.random.default_rng(seed)
    noise = np.concatenate([rng.normal(0, ROT_NOISE_RAD, (len(times), 3)), rng.normal(0, T_NOISE_M, (len(times), 3))], 1)
    measured = truth + noise
    measured[ref] = 0.0
    return times, truth, measured, ref


def _error(poses: AnyArray, truth: AnyArray) -> float:
    """RMS over frames of the box corners' largest displacement [mm] between ``poses`` and ``truth``."""
    return float(np.sqrt(np.mean([_box_shift_mm(BOX, d, CENTRE) ** 2 for d in poses - truth])))


@pytest.mark.parametrize("seed", range(5))
def test_the_smoothed_poses_are_nearer_the_truth_and_the_noise_is_measured(seed):
    times, truth, measured, ref = _track(0.0012, seed)
    fitted = np.ones(len(times), bool)
    smoothed, noise = smoothed_poses(times, measured, fitted, ref, 0.25, BOX, CENTRE)
    assert np.all(smoothed[ref] == 0.0)
    raw_err, smooth_err = _error(measured, truth), _error(smoothed, truth)
    assert smooth_err < 0.75 * raw_err, (smooth_err, raw_err)
    # the scatter about the lines is the measurement's noise (a line through 5 frames takes a fifth of it)
    assert 0.6 * raw_err < noise < 1.1 * raw_err, (noise, raw_err)
    # without a window (0 s) the poses are the measured ones and the noise unknown
    same, unknown = smoothed_poses(times, measured, fitted, ref, 0.0, BOX, CENTRE)
    assert np.array_equal(same, measured) and np.isnan(unknown)


@pytest.mark.parametrize("seed", range(5))
def test_a_still_head_is_within_the_noise_and_a_seated_drift_beyond_it(seed):
    params = MotionParams()
    verdicts = {}
    for name, drift in (("still", 0.0), ("seated", 0.0016)):
        times, truth, measured, ref = _track(drift, 100 + seed)
        fitted = np.ones(len(times), bool)
        smoothed, noise = smoothed_poses(times, measured, fitted, ref, 0.5 * params.smooth_s, BOX, CENTRE)
        moved = max(_box_shift_mm(BOX, v, CENTRE) for v in smoothed)
        # the seated drift is below the absolute threshold: only the scan's own noise tells it from a still head
        assert moved < params.min_motion_mm, (name, moved)
        verdicts[name] = beyond_noise(moved, noise, params)
    assert verdicts == {"still": False, "seated": True}


def test_too_few_frames_in_a_window_leave_the_poses_and_the_absolute_threshold_alone():
    times, _, measured, ref = _track(0.0012, 7)
    sparse = times[::4], measured[::4]     # 2.5 Hz: one frame per 0.5 s window
    fitted = np.ones(len(sparse[0]), bool)
    smoothed, noise = smoothed_poses(sparse[0], sparse[1], fitted, ref // 4, 0.25, BOX, CENTRE)
    assert np.isnan(noise)
    assert np.array_equal(smoothed, sparse[1])
    params = MotionParams()
    assert not beyond_noise(1.0, noise, params) and beyond_noise(1.6, noise, params)

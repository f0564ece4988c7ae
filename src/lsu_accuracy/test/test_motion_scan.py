"""Sweeps of a living subject (`lsu_accuracy.motion_sim`): the motion measured from the frames' texture
(`lsu_reconstruct.motion`) corrects a swaying scan and a seated drift, leaves a still one alone and flags a sudden
turn; the same for the live graph's measurement (`SweepMotion`, as stereo_matcher runs it: every third frame's images
handed over as the frames are placed), on the same rendered sweeps.

Ground truth: the simulator's true pose per frame (`lsu_sim.motion`, the poses the frames were rendered at)
and the person's meshes at the reference frame's true pose. The sweeps cover the middle of the face
(nose and mouth) at the face sweep's rate, fewer frames than a whole face to keep the tests short; the turn's
sweep is shorter still, as it only has to show the flag.
"""

from __future__ import annotations

import numpy as np
import pytest

from lsu_accuracy.motion_sim import MotionScan, motion_scan
from lsu_config import config_dir
from lsu_reconstruct.laser_sheet import read_laser_yaml
from lsu_reconstruct.motion import HOLD_STILL, MotionParams
from lsu_reconstruct.stereo import StereoModel
from lsu_sim import build_scene, load_rig

pytestmark = [pytest.mark.slow, pytest.mark.timeout(1200)]

SCENE, START, END = "person:2", 190, 280
# the turn's sweep: the first 60 steps of that range (1.05 s, 32 frames, the reference the middle one at ~0.55 s);
# the head turns at 0.1..0.5 s, wholly before the reference: the frames before and during it are the far side
TURN_START, TURN_END, TURN_AT_S = 190, 250, 0.1


@pytest.fixture(scope="module")
def setting():
    calib = config_dir() / "calibration" / "sim"
    geometry = load_rig()
    return StereoModel.from_folder(calib), read_laser_yaml(calib / "laser.yaml"), geometry, build_scene(SCENE, geometry)


def _scan(setting, kind: str, seed: int = 2, start: int = START, end: int = END, **kw) -> MotionScan:
    model, sheet, geometry, objects = setting
    return motion_scan(model, sheet, geometry, objects, kind, seed=seed, start=start, end=end, **kw)


@pytest.fixture(scope="module")
def still(setting) -> MotionScan:
    return _scan(setting, "still", live=True)


def test_a_still_scan_is_left_as_it_is(still, setting):
    assert len(still.raw_xyz) > 10000
    assert np.all(still.true_poses == 0.0)
    assert not still.estimate.flagged, still.estimate.reasons
    # the measured motion of a statue is the measurement's noise: the scan is left exactly as it was
    assert not still.estimate.significant
    assert np.array_equal(still.corrected_xyz, still.raw_xyz)
    objects = setting[3]
    assert still.rms_mm(objects, corrected=True) == pytest.approx(still.rms_mm(objects, corrected=False), rel=0.05)
    assert "message" not in still.record and still.record["flagged"] is False
    # the live graph's measurement: not flagged, within the noise, the cloud exactly as it was
    live = still.live_record
    assert live is not None and live["measured"] and not live["flagged"] and not live["beyond_noise"], live
    assert not live["corrected"] and "message" not in live
    assert np.array_equal(still.live_xyz, still.raw_xyz)


def test_a_standing_scan_is_corrected_to_the_still_accuracy(still, setting):
    objects = setting[3]
    standing = _scan(setting, "standing", seed=5, live=True)
    assert not standing.estimate.flagged, standing.estimate.reasons
    base = still.rms_mm(objects)
    raw, corrected = standing.rms_mm(objects, corrected=False), standing.rms_mm(objects)
    assert raw > 1.3 * base, (raw, base)   # the sway shears the face measurably over the sweep
    assert corrected < 0.5 * raw, (corrected, raw, base)
    # the goal is corrected <= 1.5 x still, measured by the benchmark on whole-face sweeps (1.35 x); on
    # this short sweep (nose and mouth, 1.6 s) the still base is lower (0.177 mm with the matcher's piece-length
    # rule) and the ratio 1.60 x: the bound leaves that margin and a little more, no more
    assert corrected <= 1.7 * base, (corrected, raw, base)
    # the measured pose follows the true one: the fitted points' centre moves as the truth moves it
    errors = standing.pose_errors_mm()
    assert np.median(errors) < 0.3, errors
    # the live graph's measurement (a third of the frames, another reference frame) corrects it as well
    live = standing.live_record
    assert live is not None and live["corrected"] and not live["flagged"], live
    assert standing.live_rms_mm(objects) <= 1.7 * base, (standing.live_rms_mm(objects), raw, base)


# a seated drift: a sweep of 3.2 s over the face's middle, seed 6 (measured: the fitted points move ~1.0 mm, under
# min_motion_mm, at ~4x the measurement's own noise)
SEATED_START, SEATED_END, SEATED_SEED = 150, 330, 6


def test_a_seated_drift_below_the_absolute_threshold_is_corrected_by_the_noise_test(still, setting):
    objects = setting[3]
    seated = _scan(setting, "seated", seed=SEATED_SEED, start=SEATED_START, end=SEATED_END)
    est = seated.estimate
    assert not est.flagged, est.reasons
    # only the scan's own noise tells this drift from a still face's measurement (module doc, docs/MOTION.md)
    assert est.measured_mm < MotionParams().min_motion_mm, est.measured_mm
    assert np.isfinite(est.noise_mm) and est.significant and est.smoothed, (est.measured_mm, est.noise_mm)
    assert seated.record["beyond_noise"] and seated.record["poses_smoothed"] and seated.record["noise_mm"] > 0
    raw, corrected = seated.rms_mm(objects, corrected=False), seated.rms_mm(objects)
    assert corrected < 0.85 * raw, (corrected, raw)   # measured: 0.276 -> 0.223 mm
    assert corrected <= 1.5 * still.rms_mm(objects), (corrected, raw)
    # the still sweep's measurement is within its noise by the same test
    assert np.isfinite(still.estimate.noise_mm)
    assert still.estimate.measured_mm < MotionParams().min_motion_ratio * still.estimate.noise_mm


def test_a_sudden_turn_is_flagged_with_the_part_that_is_unreliable(setting):
    turn = _scan(setting, "turn", seed=2, start=TURN_START, end=TURN_END, turn_at_s=TURN_AT_S, live=True)
    assert turn.estimate.flagged
    record = turn.record
    assert record["message"] == HOLD_STILL
    assert record["reasons"] and all(record["reasons"].values())
    lo, hi = record["unreliable_positions_steps"]
    assert TURN_START <= lo <= hi <= TURN_END
    # the frames on the far side of the turn from the reference are the unreliable ones, not every frame: with
    # the turn before the reference, none after it (measured: measured frames 0, 3, .., 12 of 0..31, steps 190.6..213.6)
    bad = record["unreliable_frames"]
    assert 0 < len(bad) < len(record["frames"])
    assert max(bad) <= record["reference_frame"], bad
    # the live graph's measurement flags it too and leaves the sheared cloud as it is (it is scanned again)
    live = turn.live_record
    assert live is not None and live["flagged"] and live["message"] == HOLD_STILL and not live["corrected"], live
    assert 0 < len(live["unreliable_frames"]) < len(live["frames"])
    assert np.array_equal(turn.live_xyz, turn.raw_xyz)

"""Adaptive stop-snap settle against the simulated rig's post-stop vibration (truth from the sim's model)."""

from __future__ import annotations

import numpy as np
import pytest

from lsu_driver.emulator import EmulatorConfig
from lsu_scan.settle import DEFAULT_TOLERANCE_PX, line_shift_px, settle_from_images
from lsu_sim import CarriageState, SimulatedRig, build_scene, load_rig

FIXED_SETTLE_S = 0.1     # the Scan goal's default settle
FRAME_PERIOD_S = 0.033   # one frame per capture, a 30 fps camera (the coordinator's exposure_s default)
POSITION = 235.0


@pytest.fixture(scope="module")
def rig():
    geometry = load_rig()
    return SimulatedRig(geometry, build_scene("plane", geometry), seed=4)


def px_per_step(rig: SimulatedRig) -> float:
    """How far the left camera's line moves per carriage step, from the rig's exact laser truth."""
    a, b = rig.laser_truth(POSITION).left.pixels, rig.laser_truth(POSITION + 1.0).left.pixels
    rows = np.intersect1d(a[:, 1], b[:, 1])
    ua = {v: u for u, v in a}
    ub = {v: u for u, v in b}
    return float(abs(np.median([ub[v] - ua[v] for v in rows])))


def run_settle(rig: SimulatedRig, state: CarriageState, first_frame_s: float):
    """The adaptive settle on rendered frames, one every FRAME_PERIOD_S from ``first_frame_s`` after the stop."""
    times, frames = [], []

    def grab():
        t = first_frame_s + len(times) * FRAME_PERIOD_S
        frame = rig.render(state, capture_time_s=t, seed=100 + len(times))
        times.append(t)
        frames.append(frame)
        return frame

    def capture():
        frame = grab()
        return len(frames) - 1, frame.left

    snap, trace = settle_from_images(lambda: grab().left, capture,
                                     fixed_passed=lambda: first_frame_s + len(times) * FRAME_PERIOD_S >= FIXED_SETTLE_S)
    return snap, trace, times, frames


def emulator_ringing() -> CarriageState:
    config = EmulatorConfig()  # the emulator's vibration after a stop at 200 steps/s (the scans' rate)
    return CarriageState(POSITION, stopped_at_s=0.0, vibration_amplitude_steps=config.vibration_amplitude_steps,
                         vibration_tau_s=config.vibration_tau_s, vibration_freq_hz=config.vibration_freq_hz)


@pytest.mark.parametrize("first_frame_s", [0.012, 0.024])
def test_adaptive_capture_comes_when_the_line_is_still_and_before_the_fixed_settle(rig, first_frame_s):
    state = emulator_ringing()
    scale = px_per_step(rig)
    assert 0.8 < scale < 1.5  # ~1/60 inch at 0.3 m seen by an 812 px focal length
    snap, trace, times, frames = run_settle(rig, state, first_frame_s)
    assert trace.reason == "still" and snap == len(frames) - 1
    # order of events: the snap's exposure starts before the fixed settle would have ended
    assert times[snap] < FIXED_SETTLE_S
    # the sim's truth: the sheet's mean displacement over the snap's exposure (where its line is) is
    # within the tolerance ...
    assert abs(frames[snap].laser_offset_steps) * scale <= DEFAULT_TOLERANCE_PX
    # ... and during the probe's exposure the carriage still swung by more: the settle waited out real motion
    probe = np.linspace(times[0], times[0] + rig.geometry.sensor.exposure_s, 9)
    assert np.abs(state.displacement_steps(probe)).max() * scale > 2 * DEFAULT_TOLERANCE_PX


def test_over_every_phase_of_the_ringing_the_snap_is_within_tolerance_and_earlier_on_average(rig):
    """The probe falls anywhere in the first frame period after the stop (the move's reply latency varies)."""
    state = emulator_ringing()
    scale = px_per_step(rig)
    snap_times = []
    for first_frame_s in np.arange(0.0, FRAME_PERIOD_S, 0.004):
        snap, trace, times, frames = run_settle(rig, state, float(first_frame_s))
        assert abs(frames[snap].laser_offset_steps) * scale <= DEFAULT_TOLERANCE_PX, (first_frame_s, trace)
        assert times[snap] < FIXED_SETTLE_S + FRAME_PERIOD_S  # never more than a frame after the fixed settle
        snap_times.append(times[snap])
    assert np.mean(snap_times) < FIXED_SETTLE_S


def test_a_line_that_keeps_moving_is_captured_once_the_fixed_settle_has_passed(rig):
    # a carriage ringing far longer than the emulator's (tau 1 s): the frames never agree
    state = CarriageState(POSITION, stopped_at_s=0.0, vibration_amplitude_steps=2.0, vibration_tau_s=1.0,
                          vibration_freq_hz=7.0)
    snap, trace, times, _frames = run_settle(rig, state, 0.005)
    assert trace.reason == "fixed settle passed"
    assert times[snap - 1] < FIXED_SETTLE_S <= times[snap]
    assert all(abs(s) > DEFAULT_TOLERANCE_PX for s in trace.shifts_px)


def test_a_frame_without_the_line_is_not_still():
    line = np.full(480, np.nan)
    line[100:400] = 320.0
    assert line_shift_px(line, line + 0.05) == pytest.approx(0.05)
    assert np.isnan(line_shift_px(line, np.full(480, np.nan)))
    frames = iter([line, np.full(480, np.nan), line + 0.01, line + 0.02])
    snap, trace = settle_from_images(lambda: next(frames), lambda: ("capture", next(frames)), lambda: False,
                                     profile=lambda p: p)
    # the frame after the hidden one has nothing to compare with either: the next one decides
    assert trace.captures == 3 and trace.reason == "still"
    assert np.isnan(trace.shifts_px[0]) and np.isnan(trace.shifts_px[1])


def test_no_probe_when_the_fixed_settle_is_already_over():
    probes = []
    snap, trace = settle_from_images(lambda: probes.append(1), lambda: ("capture", np.zeros(480)), lambda: True,
                                     profile=lambda p: p)
    assert snap == "capture" and probes == [] and trace.captures == 1 and trace.reason == "fixed settle passed"


def test_the_adaptive_settles_cloud_is_as_accurate_as_the_fixed_ones_on_a_sphere():
    """Same scene, physics and sensor noise; only when each snap is taken differs (the sim's clock, no wall clock).

    Truth: the analytic 6 cm sphere the rig renders. The probe falls at a different phase of the first
    frame period after each stop (the move's reply latency varies).
    """
    from lsu_accuracy.sweep_sim import stopsnap_scene
    from lsu_config import config_dir
    from lsu_reconstruct.stereo import StereoModel
    from lsu_scan.settle import rendered_settle

    geometry = load_rig()
    sphere = build_scene("sphere", geometry)
    centre, radius = sphere[0].extra["center"], sphere[0].extra["radius_m"]
    model = StereoModel.from_folder(config_dir() / "calibration" / "sim")
    traces = []

    def adaptive(rig, state, index):
        first = (index * 0.618034) % 1.0 * FRAME_PERIOD_S
        frame, t_snap, rendered, trace = rendered_settle(
            lambda t, seed: rig.render(state, capture_time_s=t, seed=seed), first, FRAME_PERIOD_S, FIXED_SETTLE_S,
            seed=1000 * index)
        traces.append(trace)
        return frame, t_snap, rendered

    scans = {mode: stopsnap_scene(model, geometry, sphere, start=170, end=300, step=10, settle_s=FIXED_SETTLE_S,
                                  seed=3, capture=capture)
             for mode, capture in (("fixed", None), ("adaptive", adaptive))}
    rms = {mode: float(np.sqrt(np.mean((np.linalg.norm(scan.xyz - centre, axis=1) - radius) ** 2)))
           for mode, scan in scans.items()}
    assert all(len(scan.xyz) > 1000 for scan in scans.values())
    assert rms["adaptive"] <= 1.1 * rms["fixed"], rms
    assert rms["fixed"] < 0.2e-3  # a sub-millimetre scan to compare, not two bad ones
    # order of events: the snaps come once the line is still, before the fixed settle would have ended
    times = scans["adaptive"].snap_after_stop_s
    assert times is not None and np.mean(times) < FIXED_SETTLE_S
    assert np.all(times < FIXED_SETTLE_S + FRAME_PERIOD_S)
    assert sum(t.reason == "still" for t in traces) >= 0.8 * len(traces)

"""The simulated camera source: carriage states from sim/truth samples, stream frames as functions of seed,
index and truth, and the plug-in the stereo_camera node finds by name."""

import math

import numpy as np
import pytest

from lsu_cameras.sources import CameraError, SourceContext, open_plugin_source, plugin_source_names
from lsu_common import stamps
from lsu_sim import CarriageState, SimulatedRig, build_scene, load_rig
from lsu_sim.source import SimSource, carriage_from_truth


def test_a_motion_starting_or_stopping_within_the_exposures_rests_outside_it():
    # sample at t=1.0 s at 100 steps, 60 steps/s; the motion started at 0.9 s and stops at 1.2 s
    state = CarriageState(100.0, velocity_steps_per_s=60.0, position_time_s=1.0, motion_start_s=0.9,
                          motion_stop_s=1.2, vibration_amplitude_steps=0.5, vibration_tau_s=0.04, vibration_freq_hz=20.0)
    d = state.displacement_steps([0.8, 0.9, 1.1, 1.2, 1.2 + 0.025, 5.0])
    assert d[:3] == pytest.approx([-6.0, -6.0, 6.0])  # at rest at 94 before the start
    assert d[3] == pytest.approx(12.0 + 0.5)  # the stop at 112, and its vibration from there
    assert d[4] == pytest.approx(12.0 + 0.5 * math.exp(-0.025 / 0.04) * math.cos(math.pi)) and d[5] == pytest.approx(12.0)


def test_a_sim_stream_frame_is_a_function_of_seed_index_and_truth():
    geometry = load_rig()
    scene = build_scene("plane", geometry)

    def sweep(t_ns):  # a constant-rate sweep: the truth every source below is given
        return CarriageState(200.0, velocity_steps_per_s=120.0, position_time_s=1000.0)

    def source(rig_seed):
        rig = SimulatedRig(geometry, scene, seed=rig_seed)
        rig.set_capture_timing(0.05, 0.003)
        return SimSource(rig, sweep, seed=5)

    a, b = source(0), source(1)  # the rig's own generator (single captures) plays no part
    pairs = [a.pair_at(1_000_100_000_000, 7), b.pair_at(1_000_100_000_000, 7), a.pair_at(1_000_100_000_000, 8)]
    assert np.array_equal(pairs[0].left, pairs[1].left) and np.array_equal(pairs[0].right, pairs[1].right)
    assert (pairs[0].left_offset_s, pairs[0].skew_s) == (pairs[1].left_offset_s, pairs[1].skew_s)
    assert not np.array_equal(pairs[0].left, pairs[2].left)  # each frame its own noise and start jitter
    assert pairs[0].left_offset_s != pairs[2].left_offset_s
    # the starts follow the rig: right ~50 ms after the left, each jittered by a few ms
    assert abs(pairs[0].right_offset_s - 0.05) < 0.02 and abs(pairs[0].left_offset_s) < 0.015
    assert pairs[0].time_s == 1000.1 and a.ready_after_s == pytest.approx(0.05 + 0.009 + 0.020)


def _truth(t_s, position, moving=False, velocity=0.0, laser_on=True, stopped_at_s=0.0, amplitude=0.0):
    from lsu_interfaces.msg import SimTruth

    msg = SimTruth(position_steps=position, moving=moving, velocity_steps_per_s=velocity, laser_on=laser_on,
                   vibration_amplitude_steps=amplitude, vibration_tau_s=0.05, vibration_freq_hz=20.0)
    msg.header.stamp = stamps.from_seconds(t_s)
    msg.stopped_at = stamps.from_seconds(stopped_at_s)
    return msg


def _at(state, t_s):
    """Where the carriage of ``state`` is at ``t_s`` [steps]."""
    return state.position_steps + float(state.displacement_steps(np.array([t_s]))[0])


def test_the_carriage_follows_the_truth_sample_that_held_and_a_stop_within_the_exposures():
    fallback = CarriageState(235.0, laser_on=False)
    assert carriage_from_truth(None, [], fallback) is fallback  # no truth yet: the node's parameters
    rest = carriage_from_truth(_truth(10.0, 120.0, stopped_at_s=9.9, amplitude=0.4), [], fallback)
    assert (rest.position_steps, rest.laser_on, rest.stopped_at_s, rest.vibration_amplitude_steps) == (
        120.0, True, pytest.approx(9.9), pytest.approx(0.4))
    # moving at 60 steps/s from 100 at t=1 s, a stop sample at 1.2 s follows within the exposures
    moving = carriage_from_truth(_truth(1.0, 100.0, moving=True, velocity=60.0),
                                 [_truth(1.2, 112.0, stopped_at_s=1.2, amplitude=0.5)], fallback)
    assert _at(moving, 1.1) == pytest.approx(106.0) and _at(moving, 2.0) == pytest.approx(112.0)  # vibration decayed
    # at rest at t, the motion starts before the exposures end: at rest until the start's sample
    starting = carriage_from_truth(_truth(1.0, 100.0, stopped_at_s=0.5),
                                   [_truth(1.05, 100.0, moving=True, velocity=60.0)], fallback)
    assert _at(starting, 1.02) == pytest.approx(100.0) and _at(starting, 1.15) == pytest.approx(106.0)


def test_the_camera_node_finds_the_simulator_by_name_and_names_the_sources_when_one_is_missing():
    assert "sim" in plugin_source_names()
    params = {"sim_rig": "", "sim_scene": "sphere", "sim_seed": 3, "carriage_position_steps": 150.0, "laser_on": True,
              "sim_motion": "still", "sim_motion_seed": 0, "sim_motion_turn_at_s": 1.0, "sim_motion_hz": 5.0}
    context = SourceContext(parameter=params.__getitem__, clock=lambda: 1000.0, truth_at=lambda t_ns: (None, []))
    source = open_plugin_source("sim", context)
    assert isinstance(source, SimSource) and source.seed == 3 and source.stamps_on_node_clock
    assert [o.name for o in source.rig.objects] == [o.name for o in build_scene("sphere", load_rig())]
    params["carriage_position_steps"] = 90.0  # read at capture time, as the node's parameter is settable
    assert source.carriage(0).position_steps == 90.0
    with pytest.raises(CameraError, match=r"unknown source 'lidar': use one of v4l2, folder, .*sim"):
        open_plugin_source("lidar", context)


def test_a_moving_subject_is_rendered_at_its_pose_from_the_first_frame_on():
    """``sim_motion``: the rig holds the motion's pose of each frame's mid-exposure, its clock started at the first
    frame, updated in ``sim_motion_hz`` slots (truth: `lsu_sim.motion.scene_motion` of the same scene and seed)."""
    from lsu_sim.motion import scene_motion

    params = {"sim_rig": "", "sim_scene": "sphere", "sim_seed": 3, "carriage_position_steps": 150.0, "laser_on": True,
              "sim_motion": "standing", "sim_motion_seed": 4, "sim_motion_turn_at_s": 1.0, "sim_motion_hz": 5.0}
    context = SourceContext(parameter=params.__getitem__, clock=lambda: 1000.0, truth_at=lambda t_ns: (None, []))
    source = open_plugin_source("sim", context)
    assert isinstance(source, SimSource)
    truth = scene_motion("standing", 4, source.rig.geometry, source.rig.objects)
    t0 = 1_000_000_000_000
    half = 0.5 * source.exposure_s
    for index, after_s in ((0, 0.0), (1, 0.1), (7, 0.7)):
        source.pair_at(t0 + stamps.seconds_to_ns(after_s), index)
        pose = truth.pose(math.floor((after_s + half) * 5.0) / 5.0)
        assert np.allclose(source.rig._pose_R, pose.R) and np.allclose(source.rig._pose_t, pose.translation)
    assert not np.allclose(source.rig._pose_t, 0.0)  # it moved (standing sway: millimetres)
    params["sim_motion"] = "dancing"
    with pytest.raises(CameraError, match="unknown subject motion 'dancing': use one of still, seated, standing, turn"):
        open_plugin_source("sim", context)


def test_the_next_pose_is_cast_ahead_and_the_frames_are_those_of_a_cast_in_place():
    """A moving subject's next slot is cast by the source's caster thread while the current one renders; the frames
    are the ones a cast at the slot's first frame gives (the same pose, the same caches), bit for bit."""
    params = {"sim_rig": "", "sim_scene": "sphere", "sim_seed": 3, "carriage_position_steps": 150.0, "laser_on": True,
              "sim_motion": "standing", "sim_motion_seed": 4, "sim_motion_turn_at_s": 1.0, "sim_motion_hz": 5.0}
    context = SourceContext(parameter=params.__getitem__, clock=lambda: 1000.0, truth_at=lambda t_ns: (None, []))
    ahead, in_place = open_plugin_source("sim", context), open_plugin_source("sim", context)
    assert isinstance(ahead, SimSource) and isinstance(in_place, SimSource)
    in_place.close()  # no caster: every slot cast when its first frame comes
    t0 = 1_000_000_000_000
    try:
        for index, after_s in ((0, 0.0), (1, 0.1), (2, 0.25), (3, 0.45), (4, 0.61)):
            assert ahead._next_pose is not None and ahead._next_pose[0] == ahead._motion_slot + 1
            stamp = t0 + stamps.seconds_to_ns(after_s)
            a, b = ahead.pair_at(stamp, index), in_place.pair_at(stamp, index)
            assert ahead._motion_slot == in_place._motion_slot
            assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right), index
        assert ahead._motion_slot == 3   # four slots of 0.2 s passed: three casts taken from the caster
    finally:
        ahead.close()


def test_the_cameras_sim_source_is_prepared_before_its_first_frame_with_the_same_pixels():
    """The camera's sim source (`open_sim_source`) has the first render's caches built before the camera offers its
    capture service (a respawned camera's first capture: a scan's first snap, on time on a loaded host); a rig that
    builds them at its first render gives the same pixels (the preparation draws nothing from the rig's generator)."""
    params = {"sim_rig": "", "sim_scene": "sphere", "sim_seed": 3, "carriage_position_steps": 200.0, "laser_on": True}
    context = SourceContext(parameter=params.__getitem__, clock=lambda: 1000.0, truth_at=lambda t_ns: (None, []))
    source = open_plugin_source("sim", context)
    assert isinstance(source, SimSource)
    assert all(view.sensor_key for view in source.rig._views)  # nothing left for the first frame to build
    cold = SimulatedRig(source.rig.geometry, build_scene("sphere", source.rig.geometry), seed=3, shadow_cache=True)
    assert not any(view.sensor_key for view in cold._views)
    for position in (200.0, 260.0):
        prepared, built_then = source.rig.render(CarriageState(position)), cold.render(CarriageState(position))
        assert np.array_equal(prepared.left, built_then.left) and np.array_equal(prepared.right, built_then.right)

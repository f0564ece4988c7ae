"""The living subject's motion model (`lsu_sim.motion`) and the rig's subject pose (`SimulatedRig.set_subject_pose`).

Ground truth: the model's own stated figures (docs/MOTION.md), and for the rig the laser truth of the same
scene whose meshes were moved by the pose before the rig was built (open3d ray casts of moved triangles).
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from lsu_sim import SimulatedRig, build_scene, load_rig
from lsu_sim.motion import MOTION_KINDS, MotionError, SubjectMotion, motion_spec


def _motion(kind: str, seed: int = 3) -> SubjectMotion:
    return SubjectMotion(kind, seed, pivot=np.array([0.0, 0.1, 0.4]))


def test_still_is_the_identity_and_kinds_are_checked():
    v = _motion("still").vectors(np.linspace(0, 10, 50))
    assert np.all(v == 0.0)
    with pytest.raises(MotionError, match="seated"):
        _motion("jumping")
    assert set(MOTION_KINDS) == {"still", "seated", "standing", "turn"}


def test_motion_is_seeded_and_deterministic_in_time():
    t = np.linspace(0, 7, 100)
    assert np.array_equal(_motion("standing", 4).vectors(t), _motion("standing", 4).vectors(t))
    assert not np.allclose(_motion("standing", 4).vectors(t), _motion("standing", 5).vectors(t))
    # a pose is the same whichever times are asked with it
    assert np.allclose(_motion("seated").vectors(t)[37], _motion("seated").vectors(t[37])[0])


def test_sway_has_the_stated_size_and_frequency_content():
    # over many seeds and a short window (a scan's length, drift included), the sway's RMS per axis is the
    # specification's order, standing > seated, and its power is below 1 Hz
    t = np.arange(0, 6.4, 1 / 100)
    spec = motion_spec("standing")
    rms = {kind: np.mean([(1e3 * SubjectMotion(kind, s, np.zeros(3)).vectors(t)[:, 3:]).std(axis=0)
                          for s in range(20)], axis=0) for kind in ("seated", "standing")}
    assert np.all(rms["standing"] > rms["seated"])
    # the front-back sway over a scan: a good part of the specified RMS (components slower than the window
    # show as drift), never beyond it by much
    assert 0.2 * spec.sway_rms_m[2] * 1e3 < rms["standing"][2] < 2.0 * spec.sway_rms_m[2] * 1e3
    z = SubjectMotion("standing", 1, np.zeros(3)).vectors(np.arange(0, 200, 0.05))[:, 5]
    power = np.abs(np.fft.rfft(z - z.mean())) ** 2
    freqs = np.fft.rfftfreq(len(z), 0.05)
    assert power[freqs > 1.2].sum() < 0.01 * power.sum()


def test_turn_turns_the_stated_angle_within_its_duration():
    m = SubjectMotion("turn", 2, np.zeros(3), turn_at_s=1.0)
    before, after = m.vectors(0.99)[0], m.vectors(1.0 + 0.4 + 0.01)[0]
    assert abs(np.degrees(np.linalg.norm(after[:3] - before[:3])) - 15.0) < 1.5


def test_rig_with_a_subject_pose_sees_the_moved_scene():
    geometry = load_rig()
    objects = build_scene("head:3", geometry)
    pose = SubjectMotion("standing", 7, objects[0].mesh.get_center()).pose(2.0)
    # a bigger pose than sway, so that a wrong transform could not hide in the tolerance
    R = pose.R @ pose.R @ pose.R
    t = np.array([0.004, -0.002, 0.003])
    moved = []
    for obj in objects:
        o = copy.copy(obj)
        o.mesh = copy.deepcopy(obj.mesh)
        o.mesh.rotate(R, center=np.zeros(3))
        o.mesh.translate(t)
        o.mesh.compute_vertex_normals()
        moved.append(o)
    rig = SimulatedRig(geometry, objects, seed=1)
    rig.set_subject_pose(R, t)
    truth = rig.laser_truth(235.0)
    expected = SimulatedRig(geometry, moved, seed=1).laser_truth(235.0)
    assert len(truth.left.points_m) > 100
    assert len(truth.left.points_m) == pytest.approx(len(expected.left.points_m), rel=0.02)
    # every sample of the posed rig lies on the moved surface's sheet crossing: same rows, same 3D points
    rows = {int(v): p for v, p in zip(expected.left.pixels[:, 1], expected.left.points_m)}
    common = [(p, rows[int(v)]) for v, p in zip(truth.left.pixels[:, 1], truth.left.points_m) if int(v) in rows]
    diff = np.array([np.linalg.norm(a - b) for a, b in common])
    assert len(common) > 0.9 * len(truth.left.points_m)
    assert np.median(diff) < 1e-5
    # and the pose changes the image: back to identity gives the still rig's image again
    rig.set_subject_pose(np.eye(3), np.zeros(3))
    still = SimulatedRig(geometry, objects, seed=1)
    assert np.array_equal(rig.render(200.0, seed=3).left, still.render(200.0, seed=3).left)


def test_a_prepared_pose_leaves_the_render_as_it_is_until_applied():
    geometry = load_rig()
    objects = build_scene("head:3", geometry)
    pose = SubjectMotion("standing", 7, objects[0].mesh.get_center()).pose(2.0)
    rig = SimulatedRig(geometry, objects, seed=1)
    before = rig.render(200.0, seed=3).left
    prepared = rig.prepare_subject_pose(pose.R, pose.translation)
    assert np.array_equal(rig.render(200.0, seed=3).left, before)
    rig.apply_subject_pose(prepared)
    moved = rig.render(200.0, seed=3).left
    assert not np.array_equal(moved, before)
    posed = SimulatedRig(geometry, objects, seed=1)
    posed.set_subject_pose(pose.R, pose.translation)
    assert np.array_equal(posed.render(200.0, seed=3).left, moved)


def test_a_bad_pose_is_refused():
    geometry = load_rig()
    rig = SimulatedRig(geometry, build_scene("sphere", geometry))
    with pytest.raises(ValueError, match="rotation"):
        rig.set_subject_pose(2.0 * np.eye(3), np.zeros(3))

"""Rig frames for TF agree with the simulated rig's own geometry (its rig axes, optical centres and laser origin)."""

import numpy as np
import pytest

from lsu_cameras.calib_io import read_calibration_dir
from lsu_cameras.frames import LASER_FRAME, LASER_ORIGIN_FRAME, TrackGeometry, laser_transform, rig_transforms
from lsu_cameras.paths import config_dir
from lsu_sim import load_rig


def _to_left_optical(transforms, frame):
    """Pose (rotation, translation) of ``frame`` in the left optical frame, through the base frame."""
    by_child = {t.child: t for t in transforms}
    left = by_child["lsu_left_optical"]
    base_in_left_R, base_in_left_t = left.rotation.T, -left.rotation.T @ left.translation
    t = by_child[frame]
    return base_in_left_R @ t.rotation, base_in_left_R @ t.translation + base_in_left_t


def test_static_frames_match_the_simulated_rig():
    geometry = load_rig()
    cal = read_calibration_dir(config_dir() / "calibration" / "sim")
    track = TrackGeometry(geometry.step_m, geometry.center_step, geometry.laser_forward_m)
    transforms = rig_transforms(cal.stereo, track)
    assert [(t.parent, t.child) for t in transforms] == [
        ("lsu_base", "lsu_left_optical"), ("lsu_base", "lsu_right_optical"), ("lsu_base", LASER_ORIGIN_FRAME)]
    for t in transforms:
        assert np.allclose(t.rotation @ t.rotation.T, np.eye(3)) and np.linalg.det(t.rotation) == pytest.approx(1.0)
        assert np.linalg.norm(t.quaternion_xyzw) == pytest.approx(1.0)
    by_child = {t.child: t for t in transforms}
    # the base origin is the mid-point of the optical centres, the cameras ~61 mm left and right of it
    x_rig, y_rig, z_rig = geometry.rig_axes          # baseline, down, forward (left optical frame)
    base_in_left = by_child["lsu_left_optical"].rotation.T
    assert np.allclose(base_in_left, np.stack([z_rig, -x_rig, -y_rig], axis=1), atol=1e-9)
    half_baseline = np.linalg.norm(geometry.right.center) / 2
    assert by_child["lsu_left_optical"].translation == pytest.approx([0, half_baseline, 0], abs=1e-9)
    # the right camera: its pose through the base equals the calibration's X_right = R X_left + T
    R_right, c_right = _to_left_optical(transforms, "lsu_right_optical")
    assert np.allclose(R_right, geometry.rotation.T, atol=1e-9)
    assert np.allclose(c_right, geometry.right.center, atol=1e-9)
    # the laser at any carriage position: static origin + the driver's moving frame = the renderer's laser
    R0, t0 = _to_left_optical(transforms, LASER_ORIGIN_FRAME)
    for steps in (0, 117, 235, 470):
        moving = laser_transform(steps, geometry.step_m)
        assert (moving.parent, moving.child) == (LASER_ORIGIN_FRAME, LASER_FRAME)
        assert np.allclose(R0 @ moving.translation + t0, geometry.laser_origin(steps), atol=1e-9)

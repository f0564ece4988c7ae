"""The rig's coordinate frames for TF (REP 103 / REP 105 conventions), from a stereo calibration.

Frames (metres):

- ``lsu_base``: the rig. Origin at the mid-point of the two optical centres; x forward (the
  bisector of the two optical axes, made orthogonal to the baseline), y left (from the right
  optical centre to the left one), z up. This is the simulated rig's frame (``RigGeometry.rig_axes``)
  in REP 103 body axes.
- ``lsu_left_optical``, ``lsu_right_optical``: the cameras (z forward, x right, y down), placed
  by ``stereo.yaml`` (``X_right = R X_left + T``).
- ``lsu_laser_origin``: where the laser exits at carriage step 0 (the home end, left), axes as
  ``lsu_base`` (the light sheet is its x-z plane). The track is parallel to the baseline and
  centred on the rig: step ``center_step`` sits ``laser_forward_m`` ahead of the rig origin.
- ``lsu_laser``: the laser at the carriage's position, ``position_steps * step_m`` along -y
  (towards the right camera) of ``lsu_laser_origin``; the driver publishes it on ``/tf``.

Pure numpy/scipy: the nodes turn these `RigTransform` values into TransformStamped messages.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from lsu_common.arrays import AnyArray

from .calib_io import StereoCalibration

BASE_FRAME = "lsu_base"
LASER_ORIGIN_FRAME = "lsu_laser_origin"
LASER_FRAME = "lsu_laser"


@dataclass(frozen=True)
class TrackGeometry:
    """The laser carriage's track: metres per step, the step at the rig centre, the laser's forward offset."""

    step_m: float = 0.00042333       # 1/60 inch (a dot-matrix printer carriage)
    center_step: float = 235.0
    laser_forward_m: float = 0.0


@dataclass(frozen=True)
class RigTransform:
    """Pose of ``child`` in ``parent``: ``X_parent = rotation @ X_child + translation``."""

    parent: str
    child: str
    translation: AnyArray   # (3,) metres
    rotation: AnyArray      # 3x3

    @property
    def quaternion_xyzw(self) -> AnyArray:
        """The rotation as a unit quaternion (x, y, z, w), geometry_msgs order."""
        return Rotation.from_matrix(self.rotation).as_quat()


def base_axes(stereo: StereoCalibration) -> AnyArray:
    """Columns: ``lsu_base``'s x (forward), y (left), z (up) expressed in the left optical frame."""
    centre_right = -stereo.rotation.T @ stereo.translation
    baseline = centre_right / np.linalg.norm(centre_right)          # left -> right
    forward = np.array([0.0, 0.0, 1.0]) + stereo.rotation.T @ np.array([0.0, 0.0, 1.0])
    forward = forward - forward.dot(baseline) * baseline
    forward = forward / np.linalg.norm(forward)
    left = -baseline
    up = np.cross(forward, left)
    return np.stack([forward, left, up], axis=1)


def rig_transforms(stereo: StereoCalibration, track: TrackGeometry = TrackGeometry(),
                   base_frame: str = BASE_FRAME) -> list[RigTransform]:
    """The static transforms: base -> left optical, base -> right optical, base -> laser origin."""
    M = base_axes(stereo)                                           # left optical <- base rotation
    centre_right = -stereo.rotation.T @ stereo.translation
    origin = 0.5 * centre_right                                     # base origin in the left optical frame
    to_base = M.T                                                   # base <- left optical rotation
    # step 0 lies center_step steps to the left (+y) of the track centre
    laser0 = origin + track.laser_forward_m * M[:, 0] + track.center_step * track.step_m * M[:, 1]
    return [
        RigTransform(base_frame, stereo.left_frame_id, to_base @ (np.zeros(3) - origin), to_base),
        RigTransform(base_frame, stereo.right_frame_id, to_base @ (centre_right - origin), to_base @ stereo.rotation.T),
        RigTransform(base_frame, LASER_ORIGIN_FRAME, to_base @ (laser0 - origin), np.eye(3)),
    ]


def transform_msg(t: RigTransform, stamp: object) -> object:
    """A geometry_msgs/TransformStamped of ``t`` (imported here: this module stays importable without ROS)."""
    from geometry_msgs.msg import TransformStamped

    msg = TransformStamped()
    msg.header.stamp = stamp
    msg.header.frame_id = t.parent
    msg.child_frame_id = t.child
    msg.transform.translation.x, msg.transform.translation.y, msg.transform.translation.z = (
        float(v) for v in t.translation)
    q = t.quaternion_xyzw
    msg.transform.rotation.x, msg.transform.rotation.y, msg.transform.rotation.z, msg.transform.rotation.w = (
        float(v) for v in q)
    return msg


def laser_transform(position_steps: float, step_m: float = TrackGeometry.step_m) -> RigTransform:
    """The moving laser: ``lsu_laser`` in ``lsu_laser_origin`` at a carriage position."""
    return RigTransform(LASER_ORIGIN_FRAME, LASER_FRAME, np.array([0.0, -float(position_steps) * step_m, 0.0]),
                        np.eye(3))

"""A living subject: seeded rigid head motion of a seated or standing adult (pure: numpy, no rclpy).

`SubjectMotion.pose(t)` gives the head's true rigid pose at time ``t`` seconds after the motion's start:
``X_now = R (X - pivot) + pivot + d`` for a point X of the scene as `build_scene` made it (left optical
frame, metres). The rotation turns about ``pivot``, a point on the neck below the head centre (the head
turns on the upper cervical spine; the body's sway carries it as a whole). docs/MOTION.md gives the figures
and their sources; in short:

- postural sway: a stationary random process, a sum of sinusoids with seeded phases over
  ``SWAY_BAND_HZ`` whose spectrum falls as 1/f (most power below 0.5 Hz, nothing above 1 Hz), scaled to an
  RMS per axis: standing ~3.5 mm front-back (the rig's depth axis), ~2 mm sideways (the track's axis),
  seated a third of that (the trunk rests on the chair);
- drift: a constant velocity drawn per seed (sway is not stationary: trends over tens of seconds);
- breathing: a sinusoid at 0.2-0.3 Hz (12-18 breaths a minute) moving the head up and back by a few
  tenths of a millimetre;
- small head rotations (nodding, turning, tilting) with the sway's spectrum, a few tenths of a degree RMS;
- ``turn``: a seated subject (the face scanner's usual one) glancing aside: the seated sway plus a sudden turn
  of the head (``TURN_DEG`` about the vertical axis within ``TURN_S``, a raised-cosine step) at ``turn_at_s``:
  the case no correction can rescue. Seated, not standing: the subject is asked to hold still after it and is
  scanned again, and the live simulator updates the pose a few times a second (each update re-casts the
  views), which shows standing sway as jumps of 3-4.5 mm between two frames, ~40 mm/s, a speed the motion
  measurement rightly calls beyond correction and a real standing head does not reach (seated: <= 1.5 mm).

Every kind is deterministic in (kind, seed) and in ``t``; ``still`` is the identity. Blinks and jaw motion
are not modelled here (they are not rigid): see docs/MOTION.md.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np

from lsu_common.arrays import AnyArray

__all__ = ["MOTION_KINDS", "MotionSpec", "SubjectMotion", "SubjectPose", "MotionError", "motion_spec",
           "pivot_of", "scene_motion", "SWAY_BAND_HZ", "TURN_DEG", "TURN_S"]

MOTION_KINDS = ("still", "seated", "standing", "turn")
# the sway's band [Hz]: trends below it are the drift, above it the body's inertia leaves ~nothing
SWAY_BAND_HZ = (0.02, 1.0)
SWAY_COMPONENTS = 40          # sinusoids per axis (log-spaced frequencies, seeded phases)
TURN_DEG = 15.0               # the sudden turn of ``turn``: a glance aside
TURN_S = 0.4                  # its duration (raised cosine)
NECK_BELOW_CENTRE_M = 0.07    # the rotations' pivot below the head centre (upper cervical spine)


class MotionError(ValueError):
    """An unknown motion kind or a bad parameter; the message names the valid ones."""


@dataclass(frozen=True)
class MotionSpec:
    """The figures of one kind of subject (docs/MOTION.md): RMS per axis of the rig (x along the track,
    y down, z away from the rig), breathing, rotations and drift."""

    kind: str
    sway_rms_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation_rms_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)   # about x (nod), y (turn), z (tilt)
    breathing_amplitude_m: float = 0.0      # peak head displacement over a breath (up and back)
    breathing_hz: tuple[float, float] = (0.2, 0.3)
    drift_m_s: float = 0.0                  # std of the constant drift velocity per axis
    turn_deg: float = 0.0                   # a sudden turn about the vertical axis (``turn``)


SPECS = {
    "still": MotionSpec("still"),
    "seated": MotionSpec("seated", sway_rms_m=(0.6e-3, 0.3e-3, 1.0e-3), rotation_rms_deg=(0.15, 0.15, 0.1),
                         breathing_amplitude_m=0.4e-3, drift_m_s=0.1e-3),
    "standing": MotionSpec("standing", sway_rms_m=(2.0e-3, 0.5e-3, 3.5e-3), rotation_rms_deg=(0.3, 0.3, 0.2),
                           breathing_amplitude_m=0.3e-3, drift_m_s=0.3e-3),
}
SPECS["turn"] = dataclasses.replace(SPECS["seated"], kind="turn", turn_deg=TURN_DEG)


def motion_spec(kind: str) -> MotionSpec:
    """The figures of ``kind`` (one of `MOTION_KINDS`), or MotionError naming the kinds."""
    if kind not in SPECS:
        raise MotionError(f"unknown subject motion '{kind}': use one of {', '.join(MOTION_KINDS)}")
    return SPECS[kind]


@dataclass(frozen=True)
class SubjectPose:
    """The head's rigid pose at one time: ``X_now = R (X - pivot) + pivot + d`` (left frame, metres)."""

    R: AnyArray
    d: AnyArray
    pivot: AnyArray

    @property
    def translation(self) -> AnyArray:
        """t of ``X_now = R X + t``."""
        return self.pivot + self.d - self.R @ self.pivot

    def apply(self, points: AnyArray) -> AnyArray:
        """Scene points (N,3) moved to this pose."""
        return (np.asarray(points, dtype=np.float64) - self.pivot) @ self.R.T + self.pivot + self.d

    def inverse_apply(self, points: AnyArray) -> AnyArray:
        """Points at this pose (N,3) moved back to the scene as built."""
        return (np.asarray(points, dtype=np.float64) - self.pivot - self.d) @ self.R + self.pivot

    def as_vector(self) -> AnyArray:
        """(rx, ry, rz [rad, rotation vector], dx, dy, dz [m])."""
        rvec, _ = cv2.Rodrigues(np.asarray(self.R, dtype=np.float64))
        return np.r_[rvec.ravel(), self.d]

    @classmethod
    def from_vector(cls, vector: AnyArray, pivot: AnyArray) -> SubjectPose:
        """The pose of an `as_vector` vector about ``pivot``."""
        v = np.asarray(vector, dtype=np.float64).reshape(6)
        R, _ = cv2.Rodrigues(v[:3].reshape(3, 1))
        return cls(R, v[3:].copy(), pivot)


def pivot_of(head_center_m: AnyArray, down_axis: AnyArray) -> AnyArray:
    """The rotations' pivot: ``NECK_BELOW_CENTRE_M`` below the head centre along the rig's down axis."""
    return np.asarray(head_center_m, dtype=np.float64) + NECK_BELOW_CENTRE_M * np.asarray(down_axis, dtype=np.float64)


class SubjectMotion:
    """The seeded motion of one subject (module doc); ``axes``: the rig's axes (rows x, y, z, left frame)."""

    def __init__(self, kind: str, seed: int, pivot: AnyArray, axes: AnyArray | None = None,
                 turn_at_s: float = 3.0) -> None:
        self.spec = motion_spec(kind)
        self.kind = kind
        self.seed = int(seed)
        self.pivot = np.asarray(pivot, dtype=np.float64).reshape(3)
        self.axes = np.eye(3) if axes is None else np.asarray(axes, dtype=np.float64).reshape(3, 3)
        if not np.isfinite(turn_at_s):
            raise MotionError(f"turn_at_s must be finite, got {turn_at_s}")
        self.turn_at_s = float(turn_at_s)
        rng = np.random.default_rng([self.seed, MOTION_KINDS.index(kind)])
        lo, hi = SWAY_BAND_HZ
        self._freqs = np.geomspace(lo, hi, SWAY_COMPONENTS)
        # 1/f power: amplitude ~ f^-1/2 per log-spaced component (equal power per octave falls as 1/f per Hz)
        weights = self._freqs ** -0.5 * np.exp(-(self._freqs / hi) ** 2)   # rolled off towards the band's end
        weights /= np.sqrt(0.5 * np.sum(weights ** 2))                     # unit RMS
        self._trans = [(weights * rms, rng.uniform(0, 2 * np.pi, SWAY_COMPONENTS)) for rms in self.spec.sway_rms_m]
        self._rot = [(weights * np.radians(rms), rng.uniform(0, 2 * np.pi, SWAY_COMPONENTS))
                     for rms in self.spec.rotation_rms_deg]
        self._drift = rng.normal(0.0, self.spec.drift_m_s, 3)
        self._breath_hz = rng.uniform(*self.spec.breathing_hz)
        self._breath_phase = rng.uniform(0, 2 * np.pi)
        self._turn_sign = 1.0 if rng.uniform() < 0.5 else -1.0

    @staticmethod
    def _series(t: AnyArray, freqs: AnyArray, amps: AnyArray, phases: AnyArray) -> AnyArray:
        return np.sin(2 * np.pi * t[:, None] * freqs[None, :] + phases[None, :]) @ amps

    def vectors(self, t_s: AnyArray | float) -> AnyArray:
        """(N,6) rotation vector [rad] and displacement [m] of the pose at each time (left frame)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        trans = np.stack([self._series(t, self._freqs, a, p) for a, p in self._trans], axis=1)
        rot = np.stack([self._series(t, self._freqs, a, p) for a, p in self._rot], axis=1)
        trans = trans + t[:, None] * self._drift[None, :]
        # breathing: the head rises on inhalation and goes back a little (rig y is down, z away)
        breath = 0.5 * self.spec.breathing_amplitude_m * (1 - np.cos(2 * np.pi * self._breath_hz * t + self._breath_phase))
        trans[:, 1] -= breath
        trans[:, 2] += 0.5 * breath
        if self.spec.turn_deg:
            s = np.clip((t - self.turn_at_s) / TURN_S, 0.0, 1.0)
            rot[:, 1] += self._turn_sign * np.radians(self.spec.turn_deg) * 0.5 * (1 - np.cos(np.pi * s))
        # rig axes to the left frame: rows of ``axes`` are the rig's x, y, z in the left frame
        return np.concatenate([rot @ self.axes, trans @ self.axes], axis=1)

    def pose(self, t_s: float) -> SubjectPose:
        """The head's pose at ``t_s`` seconds after the motion's start."""
        return SubjectPose.from_vector(self.vectors(float(t_s))[0], self.pivot)


def scene_motion(kind: str, seed: int, geometry, objects, turn_at_s: float = 3.0) -> SubjectMotion:
    """The `SubjectMotion` of a scene's subject: the pivot below a person's head centre (else below the scene's
    centre), the rig's axes (``geometry.rig_axes``)."""
    centre = next((o.extra["head_center_m"] for o in objects if "head_center_m" in o.extra), None)
    if centre is None:  # not a person: the scene's centre
        centre = np.mean([np.asarray(o.mesh.get_axis_aligned_bounding_box().get_center()) for o in objects], axis=0)
    axes = geometry.rig_axes
    return SubjectMotion(kind, seed, pivot_of(centre, axes[1]), axes, turn_at_s=turn_at_s)

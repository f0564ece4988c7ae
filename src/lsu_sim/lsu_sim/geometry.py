"""Geometry of the simulated rig: cameras, extrinsics, track, laser sheet (from ``config/sim_rig.yaml``).

Frames: the left optical frame is the world (x right, y down, z forward, metres). The *rig frame*
is derived from the two cameras: ``x_axis`` along the baseline (left -> right optical centre),
``z_axis`` forward (the bisector of the two optical axes, made orthogonal to the baseline),
``y_axis = z x x`` (down). The rig centre is the mid-point of the optical centres; the subject sits
``subject.distance_m`` ahead of it (thesis: "around 30cm from the center of the stereo rig").

The laser rides on a track parallel to the baseline: its origin at ``position_steps`` is
``centre + laser_forward_m * z + (position_steps - center_step) * step_m * x`` and its light sheet
has the normal ``x`` (rotated by ``tilt_deg`` about ``z``), i.e. a vertical sheet pointing forward.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from lsu_cameras.calib_io import CameraCalibration, StereoCalibration, fundamental_from, write_calibration_dir
from lsu_common.arrays import AnyArray
from lsu_config import config_dir

from .physics import BAYER_PATTERNS, SkinModel, SpeckleModel


class RigConfigError(ValueError):
    """``sim_rig.yaml`` is missing, does not parse, or holds an impossible value."""


@dataclass
class CameraModel:
    """Pinhole + plumb_bob camera placed in the left optical frame (X_cam = R X_left + t)."""

    K: AnyArray
    D: AnyArray
    R: AnyArray = field(default_factory=lambda: np.eye(3))
    t: AnyArray = field(default_factory=lambda: np.zeros(3))
    width: int = 640
    height: int = 480

    @property
    def center(self) -> AnyArray:
        """Optical centre in the left frame."""
        return -self.R.T @ self.t

    def project(self, points_left: AnyArray) -> AnyArray:
        """Distorted pixel coordinates (N,2) of left-frame points (N,3), via OpenCV's plumb_bob model."""
        pts = np.asarray(points_left, dtype=np.float64).reshape(-1, 3)
        if len(pts) == 0:
            return np.zeros((0, 2))
        rvec, _ = cv2.Rodrigues(self.R)
        px, _ = cv2.projectPoints(pts, rvec, self.t.astype(np.float64), self.K, self.D)
        return px.reshape(-1, 2)

    def pixel_rays(self, pixels: AnyArray, iterations: int = 60, tolerance_px: float = 1e-12) -> AnyArray:
        """Unit ray directions (N,3) in the left frame through distorted pixels (N,2).

        OpenCV's iterative undistortion, run to convergence (not its 5-iteration default) so a ray
        re-projects onto its pixel to ``tolerance_px``: the ground truth relies on it. OpenCV's EPS
        criterion is that re-projection error, per point, so each point stops once it is met
        (``iterations`` is the cap for a point that never converges).
        """
        pix = np.asarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, iterations, tolerance_px)
        norm = cv2.undistortPoints(pix, self.K, self.D, None, None, None, criteria).reshape(-1, 2)
        rays_cam = np.concatenate([norm, np.ones((len(norm), 1))], axis=1)
        rays = rays_cam @ self.R  # R^T applied to row vectors: camera -> left frame
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)

    def calibration(self, name: str) -> CameraCalibration:
        """This camera as ROS camera_info (unrectified: R = I, P = [K | 0])."""
        return CameraCalibration(self.width, self.height, self.K.copy(), self.D.copy(), name)


@dataclass
class LaserModel:
    """Line laser sheet: Gaussian thickness, power, colour response."""

    sheet_sigma_m: float
    power: float
    spectral_bgr: AnyArray
    tilt_deg: float = 0.0
    wavelength_nm: float = 671.0


@dataclass
class Lighting:
    """Room light: ambient + one lamp with a Blinn-Phong highlight."""

    ambient: float = 0.22
    key: float = 0.30
    key_light_m: AnyArray = field(default_factory=lambda: np.array([0.06, -0.40, 0.05]))
    specular: float = 0.35
    shininess: float = 40.0
    background: float = 0.03


@dataclass
class SensorModel:
    """Exposure, noise and optics of both cameras."""

    exposure_s: float = 0.020
    sub_exposures: int = 8
    full_well_e: float = 6000.0
    read_noise_dn: float = 1.2
    psf_sigma_px: float = 0.5
    f_number: float = 2.0
    pixel_size_m: float = 7.5e-6
    blooming: float = 0.5              # share of the charge above full well that spills up/down the column
    bayer: str = "none"                # "none" or a Bayer pattern (RGGB, BGGR, GRBG, GBRG)
    capture_offset_s: float = 0.0      # right camera's exposure start minus the left's
    capture_jitter_s: float = 0.0      # std of each camera's exposure start


@dataclass
class RigGeometry:
    """Everything that fixes where things are in the simulated rig."""

    left: CameraModel
    right: CameraModel
    track_steps: int = 470
    step_m: float = 0.00042333
    center_step: float = 235.0
    laser_forward_m: float = 0.0
    subject_distance_m: float = 0.30
    laser: LaserModel = field(default_factory=lambda: LaserModel(0.0010 / 2.3548, 0.95, np.array([0.02, 0.07, 1.0])))
    lighting: Lighting = field(default_factory=Lighting)
    sensor: SensorModel = field(default_factory=SensorModel)
    speckle: SpeckleModel = field(default_factory=SpeckleModel)
    skin: SkinModel = field(default_factory=SkinModel)

    @property
    def magnification(self) -> float:
        """Lateral magnification at the subject distance (left camera's focal length)."""
        f_m = float(self.left.K[0, 0]) * self.sensor.pixel_size_m
        return f_m / max(self.subject_distance_m - f_m, 1e-9)

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height)."""
        return (self.left.width, self.left.height)

    @property
    def rotation(self) -> AnyArray:
        """R of the right camera w.r.t. the left (X_right = R X_left + T)."""
        return self.right.R

    @property
    def translation(self) -> AnyArray:
        """T [m]."""
        return self.right.t

    @property
    def rig_axes(self) -> AnyArray:
        """Rows x (baseline), y (down), z (forward) of the rig frame, in the left frame."""
        x = self.right.center - self.left.center
        x = x / np.linalg.norm(x)
        forward = np.array([0.0, 0.0, 1.0]) + self.right.R.T @ np.array([0.0, 0.0, 1.0])
        z = forward - forward.dot(x) * x
        z = z / np.linalg.norm(z)
        y = np.cross(z, x)
        return np.stack([x, y, z])

    @property
    def rig_center(self) -> AnyArray:
        """Mid-point of the two optical centres (left frame, m)."""
        return 0.5 * (self.left.center + self.right.center)

    @property
    def subject_center(self) -> AnyArray:
        """Where a subject is placed by default: ``subject_distance_m`` ahead of the rig centre."""
        return self.rig_center + self.subject_distance_m * self.rig_axes[2]

    def laser_origin(self, position_steps: float) -> AnyArray:
        """Laser exit point at a carriage position (left frame, m)."""
        x, _, z = self.rig_axes
        return self.rig_center + self.laser_forward_m * z + (position_steps - self.center_step) * self.step_m * x

    @property
    def laser_normal(self) -> AnyArray:
        """Unit normal of the light sheet (constant along the track)."""
        x, y, _ = self.rig_axes
        tilt = np.deg2rad(self.laser.tilt_deg)
        return np.cos(tilt) * x + np.sin(tilt) * y

    def laser_plane(self, position_steps: float) -> tuple[AnyArray, float]:
        """(n, c) with the sheet's centre plane n . X = c at ``position_steps``."""
        n = self.laser_normal
        return n, float(n.dot(self.laser_origin(position_steps)))

    def stereo_calibration(self) -> StereoCalibration:
        """The true extrinsics in ``stereo.yaml`` terms (RMS 0: exact)."""
        w, h = self.image_size
        F = fundamental_from(self.left.calibration("lsu_left"), self.right.calibration("lsu_right"),
                             self.rotation, self.translation)
        return StereoCalibration(w, h, self.rotation.copy(), self.translation.copy(), fundamental=F, rms_px=0.0,
                                 date="simulated")


def _get(data: dict[str, Any], path: str, default: Any = None) -> Any:
    node: Any = data
    for key in path.split("."):
        if not isinstance(node, dict) or key not in node:
            if default is None:
                raise RigConfigError(f"missing field '{path}'")
            return default
        node = node[key]
    return node


def _camera(data: dict[str, Any], side: str, w: int, h: int, R: AnyArray, t: AnyArray) -> CameraModel:
    K = np.asarray(_get(data, f"{side}.camera_matrix"), dtype=np.float64)
    D = np.asarray(_get(data, f"{side}.distortion_coefficients"), dtype=np.float64)
    if K.size != 9 or D.size != 5:
        raise RigConfigError(f"{side}: camera_matrix needs 9 numbers and distortion_coefficients 5")
    return CameraModel(K.reshape(3, 3), D.reshape(5), R, t, w, h)


def rig_from_dict(data: dict[str, Any]) -> RigGeometry:
    """Build a `RigGeometry` from the mapping of ``sim_rig.yaml``."""
    w, h = int(_get(data, "image_width")), int(_get(data, "image_height"))
    if w <= 0 or h <= 0:
        raise RigConfigError(f"image size {w}x{h} is not positive")
    rvec = np.asarray(_get(data, "stereo.rotation_vector"), dtype=np.float64).reshape(3)
    T = np.asarray(_get(data, "stereo.translation_m"), dtype=np.float64).reshape(3)
    R, _ = cv2.Rodrigues(rvec)
    left = _camera(data, "left", w, h, np.eye(3), np.zeros(3))
    right = _camera(data, "right", w, h, R, T)
    fwhm = float(_get(data, "laser.sheet_fwhm_m", 0.001))
    if fwhm <= 0:
        raise RigConfigError("laser.sheet_fwhm_m must be positive")
    laser = LaserModel(fwhm / (2.0 * np.sqrt(2.0 * np.log(2.0))), float(_get(data, "laser.power", 0.95)),
                       np.asarray(_get(data, "laser.spectral_bgr", [0.02, 0.07, 1.0]), dtype=np.float64),
                       float(_get(data, "laser.tilt_deg", 0.0)), float(_get(data, "laser.wavelength_nm", 671.0)))
    light = Lighting(float(_get(data, "lighting.ambient", 0.22)), float(_get(data, "lighting.key", 0.30)),
                     np.asarray(_get(data, "lighting.key_light_m", [0.06, -0.40, 0.05]), dtype=np.float64),
                     float(_get(data, "lighting.specular", 0.35)), float(_get(data, "lighting.shininess", 40.0)),
                     float(_get(data, "lighting.background", 0.03)))
    sensor = SensorModel(float(_get(data, "sensor.exposure_s", 0.02)), int(_get(data, "sensor.sub_exposures", 8)),
                         float(_get(data, "sensor.full_well_e", 6000.0)),
                         float(_get(data, "sensor.read_noise_dn", 1.2)), float(_get(data, "sensor.psf_sigma_px", 0.5)),
                         float(_get(data, "sensor.f_number", 2.0)), float(_get(data, "sensor.pixel_size_m", 7.5e-6)),
                         float(_get(data, "sensor.blooming", 0.5)), str(_get(data, "sensor.bayer", "none")),
                         float(_get(data, "sensor.capture_offset_s", 0.0)),
                         float(_get(data, "sensor.capture_jitter_s", 0.0)))
    if sensor.sub_exposures < 1 or sensor.exposure_s <= 0:
        raise RigConfigError("sensor.sub_exposures must be >= 1 and sensor.exposure_s > 0")
    if sensor.f_number <= 0 or sensor.pixel_size_m <= 0:
        raise RigConfigError("sensor.f_number and sensor.pixel_size_m must be positive")
    if not 0.0 <= sensor.blooming <= 1.0:
        raise RigConfigError(f"sensor.blooming must be in [0, 1] (share of the excess charge), got {sensor.blooming}")
    if sensor.bayer != "none" and sensor.bayer not in BAYER_PATTERNS:
        raise RigConfigError(f"sensor.bayer must be none or one of {', '.join(BAYER_PATTERNS)}, got {sensor.bayer!r}")
    if sensor.capture_jitter_s < 0:
        raise RigConfigError(f"sensor.capture_jitter_s must be >= 0, got {sensor.capture_jitter_s}")
    speckle = SpeckleModel(float(_get(data, "speckle.contrast", 1.0)), int(_get(data, "speckle.tiles", 2)),
                           int(_get(data, "speckle.tile_cols", 32)))
    if not 0.0 <= speckle.contrast <= 1.0 or speckle.tiles < 1 or speckle.tile_cols < 8:
        raise RigConfigError("speckle.contrast must be in [0, 1] (0 = off), speckle.tiles >= 1, speckle.tile_cols >= 8")
    skin = SkinModel(float(_get(data, "skin.diffusion_length_m", 0.001)),
                     float(_get(data, "skin.subsurface_fraction", 0.9)),
                     float(_get(data, "skin.mu_s_prime_per_mm", 1.5)) * 1000.0,
                     float(_get(data, "skin.mu_a_per_mm", 0.03)) * 1000.0,
                     float(_get(data, "skin.refractive_index", 1.4)))
    if skin.diffusion_length_m <= 0 or not 0.0 <= skin.subsurface_fraction <= 1.0 or skin.mu_s_prime_per_m <= 0 \
            or skin.mu_a_per_m < 0 or skin.refractive_index < 1.0:
        raise RigConfigError("skin: diffusion_length_m > 0, subsurface_fraction in [0, 1], mu_s_prime_per_mm > 0, "
                             "mu_a_per_mm >= 0 and refractive_index >= 1 are required")
    return RigGeometry(left, right, int(_get(data, "track.steps", 470)), float(_get(data, "track.step_m", 0.00042333)),
                       float(_get(data, "track.center_step", 235.0)), float(_get(data, "track.laser_forward_m", 0.0)),
                       float(_get(data, "subject.distance_m", 0.30)), laser, light, sensor, speckle, skin)


def default_rig_path() -> Path:
    """``config/sim_rig.yaml`` of this workspace."""
    return config_dir() / "sim_rig.yaml"


def load_rig(path: os.PathLike | str | None = None) -> RigGeometry:
    """Read ``sim_rig.yaml`` (default: the workspace's) into a `RigGeometry`."""
    path = Path(path) if path else default_rig_path()
    if not path.is_file():
        raise RigConfigError(f"{path}: simulated rig file not found")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise RigConfigError(f"{path}: not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise RigConfigError(f"{path}: expected a mapping")
    try:
        return rig_from_dict(data)
    except RigConfigError as exc:
        raise RigConfigError(f"{path}: {exc}") from None
    except (TypeError, ValueError) as exc:
        raise RigConfigError(f"{path}: bad value: {exc}") from None


def write_true_calibration(rig: RigGeometry, directory: os.PathLike | str) -> None:
    """Write the rig's exact calibration as left.yaml/right.yaml/stereo.yaml (what a perfect calibration gives)."""
    write_calibration_dir(directory, rig.left.calibration("lsu_left"), rig.right.calibration("lsu_right"),
                          rig.stereo_calibration(),
                          header="TRUE calibration of the simulated rig (config/sim_rig.yaml), written by\n"
                                 "`python -m lsu_sim --write-calibration DIR`. Do not edit: regenerate.")

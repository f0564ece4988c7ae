"""Stereo camera model of the LSU: intrinsics, extrinsics, undistortion and epipolar lines (thesis ch. 4).

Conventions (the thesis, Bouguet's toolbox and OpenCV's ``stereoCalibrate`` agree):

- The left optical frame is the world frame (``lsu_left_optical``): x right, y down, z forward.
- ``X_right = R @ X_left + T``. The right camera centre in the left frame is ``C = -R.T @ T``.
  On the LSU the right camera sits ~122 mm to the *right* of the left one, so ``C_x > 0`` and,
  for any sensible toe-in, ``T_x < 0`` (the thesis' calibration: ``T = [-121.7, ..., 14.5] mm``).
  A calibration whose right centre lies to the *left* of the left camera means the two cameras (or
  their files) were swapped; that is refused with :class:`CalibrationSwappedError`.
- Pixels follow the OpenCV convention of ``LaserLine.msg``: (0, 0) is the centre of the top-left pixel.
- "Undistorted pixels" are ideal pinhole pixels of the *same* camera matrix K (``undistortPoints``
  with ``P = K``), so the fundamental matrix works in pixels: ``x_right^T F x_left = 0``,
  ``F = K2^-T [T]x R K1^-1`` and the right epipolar line of a left point is ``l2 = F x1``.

This module imports no rclpy: the node builds a :class:`StereoModel` from CameraInfo/extrinsics
arrays with :meth:`StereoModel.from_arrays`, the offline tools from a calibration folder with
:meth:`StereoModel.from_folder`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import cv2
import numpy as np

# The calibration files have one reader, in lsu_cameras; its errors are this module's errors.
from lsu_cameras.calib_io import (
    CalibrationError,
    CalibrationFileError,
    CalibrationInconsistentError,
    CalibrationParseError,
    CalibrationSizeError,
    CalibrationSwappedError,
    check_camera_matrix,
    check_epipolar,
    check_extrinsics,
    read_calibration_dir,
    skew,
)
from lsu_common.arrays import AnyArray

__all__ = [
    "CalibrationError", "CalibrationFileError", "CalibrationParseError", "CalibrationSizeError",
    "CalibrationSwappedError", "CalibrationInconsistentError", "StereoModel", "skew", "fundamental_from",
]

# Sub-millipixel undistortion: OpenCV's default (5 fixed iterations) leaves ~0.01-0.1 px near the
# image corners with the LSU's barrel distortion, which is as large as the extractor's own noise.
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-12)
_EYE3 = np.eye(3)


def fundamental_from(K1: AnyArray, K2: AnyArray, R: AnyArray, T: AnyArray) -> tuple[AnyArray, AnyArray]:
    """Essential ``E = [T]x R`` and fundamental ``F = K2^-T E K1^-1`` (F scaled to unit Frobenius norm)."""
    return check_epipolar(K1, K2, R, T, None, None, "")


@dataclass(frozen=True)
class StereoModel:
    """Calibrated stereo pair: intrinsics (K, D) of both cameras and the right-from-left pose (R, T).

    Build it with :meth:`from_folder` or :meth:`from_arrays`; both validate and derive E and F.
    """

    K1: AnyArray
    D1: AnyArray
    K2: AnyArray
    D2: AnyArray
    R: AnyArray
    T: AnyArray
    image_size: tuple[int, int]  # (width, height) [px], equal for both cameras
    E: AnyArray = field(default_factory=lambda: np.zeros((3, 3)))
    F: AnyArray = field(default_factory=lambda: np.zeros((3, 3)))
    left_frame_id: str = "lsu_left_optical"
    right_frame_id: str = "lsu_right_optical"
    rms_px: float = 0.0
    calibration_id: str = ""
    source: str = "arrays"

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_arrays(cls, K1: Any, D1: Any, K2: Any, D2: Any, R: Any, T: Any,
                    image_size: tuple[int, int], E: Any | None = None, F: Any | None = None,
                    right_image_size: tuple[int, int] | None = None, source: str = "arrays",
                    **meta: Any) -> StereoModel:
        """Validate arrays (CameraInfo-like: K row-major 3x3, D plumb_bob, R 3x3, T [m]) into a model.

        E and F are derived from R, T and the intrinsics; when given, they must agree with them
        (up to scale and sign), else :class:`CalibrationInconsistentError` names the mismatch.
        """
        def arr(name: str, value: Any, shape: tuple[int, ...] | None = None) -> AnyArray:
            try:
                a = np.asarray(value, dtype=float)
            except (TypeError, ValueError):
                raise CalibrationParseError(f"{source}: {name} must be numeric") from None
            if shape is not None:
                if a.size != int(np.prod(shape)):
                    raise CalibrationParseError(f"{source}: {name} has {a.size} values, expected {int(np.prod(shape))}")
                a = a.reshape(shape)
            if not np.all(np.isfinite(a)):
                raise CalibrationParseError(f"{source}: {name} contains NaN or infinity")
            return a

        K1a, K2a = arr("K1", K1, (3, 3)), arr("K2", K2, (3, 3))
        D1a, D2a = arr("D1", D1).reshape(-1), arr("D2", D2).reshape(-1)
        Ra, Ta = arr("R", R, (3, 3)), arr("T", T, (3,))
        for name, K in (("K1", K1a), ("K2", K2a)):
            check_camera_matrix(K, source, name)
        for name, D in (("D1", D1a), ("D2", D2a)):
            if D.size not in (0, 4, 5, 8, 12, 14):
                raise CalibrationParseError(f"{source}: {name} has {D.size} coefficients; plumb_bob needs 5 "
                                            f"[k1, k2, p1, p2, k3]")
        w, h = (int(image_size[0]), int(image_size[1]))
        if w <= 0 or h <= 0:
            raise CalibrationSizeError(f"{source}: image size {w}x{h} must be positive")
        if right_image_size is not None and tuple(int(x) for x in right_image_size) != (w, h):
            raise CalibrationSizeError(f"{source}: left camera is {w}x{h} but right camera is "
                                       f"{right_image_size[0]}x{right_image_size[1]}; calibrate both at the same size")
        check_extrinsics(Ra, Ta, source)
        Ed, Fd = check_epipolar(K1a, K2a, Ra, Ta, None if E is None else arr("E", E, (3, 3)),
                                None if F is None else arr("F", F, (3, 3)), source)
        return cls(K1=K1a, D1=D1a, K2=K2a, D2=D2a, R=Ra, T=Ta, image_size=(w, h), E=Ed, F=Fd, source=source, **meta)

    @classmethod
    def from_folder(cls, folder: str | Path) -> StereoModel:
        """Load ``left.yaml``, ``right.yaml`` and ``stereo.yaml`` (CONTRIBUTING.md format) from ``folder``."""
        cal = read_calibration_dir(folder)
        s = cal.stereo
        return cls.from_arrays(cal.left.camera_matrix, cal.left.distortion_coefficients, cal.right.camera_matrix,
                               cal.right.distortion_coefficients, s.rotation, s.translation, cal.image_size,
                               E=s.essential, F=s.fundamental, source=str(folder), left_frame_id=s.left_frame_id,
                               right_frame_id=s.right_frame_id, rms_px=float(s.rms_px),
                               calibration_id=cal.calibration_id)

    # ------------------------------------------------------------------ geometry
    @property
    def baseline_m(self) -> float:
        """|T| [m]."""
        return float(np.linalg.norm(self.T))

    # The per-snap paths (undistortion, rays) use these for every line: computed once per model
    # (the model is frozen; its arrays are not changed after construction).
    @cached_property
    def right_centre(self) -> AnyArray:
        """Right optical centre in the left frame, ``-R^T T`` [m]."""
        return -self.R.T @ self.T

    @cached_property
    def K1_inv(self) -> AnyArray:
        """Inverse of the left camera matrix."""
        return np.linalg.inv(self.K1)

    @cached_property
    def K2_inv(self) -> AnyArray:
        """Inverse of the right camera matrix."""
        return np.linalg.inv(self.K2)

    @cached_property
    def _left_ray(self) -> tuple[AnyArray, AnyArray]:
        """``(K1^-1[:, :2].T, K1^-1[:, 2])``: undistorted left pixel -> ray (z = 1)."""
        return self.K1_inv[:, :2].T, self.K1_inv[:, 2]

    @cached_property
    def _right_ray(self) -> tuple[AnyArray, AnyArray]:
        """``(K2^-1[:, :2].T, K2^-1[:, 2])``: undistorted right pixel -> ray in the right frame."""
        return self.K2_inv[:, :2].T, self.K2_inv[:, 2]

    def closest_approach(self, x1: AnyArray, x2: AnyArray
                         ) -> tuple[AnyArray, AnyArray, AnyArray, AnyArray]:
        """Where the rays of undistorted pixel pairs (N, 2) pass closest: ``(r1, r2, lam, mu)``.

        ``r1``, ``r2``: ray directions in the left frame (z = 1 in each camera); the closest points
        are ``lam * r1`` on the left ray and ``right_centre + mu * r2`` on the right one (NaN or inf
        for parallel rays). The 2x2 normal equations are solved for all rows at once.

        Each row's result depends on that row only, for any two or more rows (numpy's matrix
        products take a vector path for a single row, whose last bits may differ); callers that
        keep a subset of rows rely on this to reuse the result instead of recomputing it.
        """
        m1, o1 = self._left_ray
        m2, o2 = self._right_ray
        r1 = x1 @ m1 + o1
        r2 = (x2 @ m2 + o2) @ self.R  # R^T r: in the left frame
        c = self.right_centre
        a = np.einsum("ij,ij->i", r1, r1)
        b = np.einsum("ij,ij->i", r1, r2)
        e = np.einsum("ij,ij->i", r2, r2)
        d1, d2 = r1 @ c, r2 @ c
        den = a * e - b * b
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = (d1 * e - b * d2) / den
            mu = (b * d1 - a * d2) / den
        return r1, r2, lam, mu

    @property
    def P1(self) -> AnyArray:
        """Left projection matrix ``K1 [I | 0]`` for undistorted pixels."""
        return self.K1 @ np.hstack([np.eye(3), np.zeros((3, 1))])

    @property
    def P2(self) -> AnyArray:
        """Right projection matrix ``K2 [R | T]`` for undistorted pixels."""
        return self.K2 @ np.hstack([self.R, self.T.reshape(3, 1)])

    def check_image_size(self, width: int, height: int, which: str = "image") -> None:
        """Raise :class:`CalibrationSizeError` when data of ``width`` x ``height`` does not fit this calibration."""
        if (int(width), int(height)) != self.image_size and (width, height) != (0, 0):
            raise CalibrationSizeError(
                f"{which} is {width}x{height} px but the calibration ({self.source}) is "
                f"{self.image_size[0]}x{self.image_size[1]}; recalibrate at this resolution or set the cameras back")

    @cached_property
    def _undistort_left_args(self) -> tuple:
        return self._undistort_args(self.K1, self.K1_inv, self.D1)

    @cached_property
    def _undistort_right_args(self) -> tuple:
        return self._undistort_args(self.K2, self.K2_inv, self.D2)

    @staticmethod
    def _undistort_args(K: AnyArray, Kinv: AnyArray, D: AnyArray) -> tuple:
        """The per-camera constants of :meth:`_undistort` (D is None for a camera without distortion)."""
        return Kinv[:2, :2].T, Kinv[:2, 2], (D if D.size and np.any(D != 0) else None), K[:2, :2].T, K[:2, 2]

    @staticmethod
    def _undistort(u: AnyArray, v: AnyArray, args: tuple) -> AnyArray:
        # Normalise with the full K^-1 ourselves (OpenCV's undistortPoints ignores skew K[0,1]),
        # let OpenCV invert the distortion in normalised coordinates, and map back with K.
        u = np.asarray(u, dtype=np.float64).reshape(-1)
        pts = np.empty((u.size, 2))
        pts[:, 0] = u
        pts[:, 1] = np.asarray(v, dtype=np.float64).reshape(-1)
        if pts.shape[0] == 0:
            return np.zeros((0, 2))
        kinv, kinv_offset, D, k, k_offset = args
        xd = pts @ kinv + kinv_offset
        if D is not None:
            xd = cv2.undistortPoints(xd.reshape(-1, 1, 2), _EYE3, D, criteria=_UNDISTORT_CRITERIA).reshape(-1, 2)
        return xd @ k + k_offset

    def undistort_left(self, u: AnyArray, v: AnyArray) -> AnyArray:
        """Raw left pixels -> undistorted left pixels, (N, 2)."""
        return self._undistort(u, v, self._undistort_left_args)

    def undistort_right(self, u: AnyArray, v: AnyArray) -> AnyArray:
        """Raw right pixels -> undistorted right pixels, (N, 2)."""
        return self._undistort(u, v, self._undistort_right_args)

    def distort_right(self, pts: AnyArray) -> AnyArray:
        """Undistorted right pixels (N, 2) -> raw right pixels (N, 2), via ``cv2.projectPoints``."""
        rays = np.hstack([(pts - self.K2[:2, 2]) @ np.linalg.inv(self.K2[:2, :2]).T, np.ones((len(pts), 1))])
        return self._project(rays, np.eye(3), np.zeros(3), self.K2, self.D2)

    @staticmethod
    def _project(X: AnyArray, R: AnyArray, T: AnyArray, K: AnyArray, D: AnyArray) -> AnyArray:
        if len(X) == 0:
            return np.zeros((0, 2))
        Kz = K.copy()
        Kz[0, 1] = 0.0  # projectPoints ignores skew; add it back below
        rvec, _ = cv2.Rodrigues(np.asarray(R, dtype=np.float64))
        out, _ = cv2.projectPoints(np.asarray(X, dtype=np.float64).reshape(-1, 1, 3), rvec,
                                   np.asarray(T, dtype=np.float64).reshape(3, 1), Kz, D)
        out = out.reshape(-1, 2)
        if K[0, 1] != 0.0:
            out[:, 0] += K[0, 1] * (out[:, 1] - K[1, 2]) / K[1, 1]
        return out

    def project_left(self, X: AnyArray) -> AnyArray:
        """3D points in the left frame [m] (N, 3) -> raw (distorted) left pixels (N, 2)."""
        return self._project(X, np.eye(3), np.zeros(3), self.K1, self.D1)

    def project_right(self, X: AnyArray) -> AnyArray:
        """3D points in the left frame [m] (N, 3) -> raw (distorted) right pixels (N, 2)."""
        return self._project(X, self.R, self.T, self.K2, self.D2)

    @cached_property
    def _epipolar(self) -> tuple[AnyArray, AnyArray]:
        """``(F[:, :2].T, F[:, 2])``: undistorted left pixel -> right epipolar line."""
        return self.F[:, :2].T, self.F[:, 2]

    def epipolar_lines(self, x1: AnyArray) -> AnyArray:
        """Right epipolar lines ``l2 = F x1`` of undistorted left pixels (N, 2), as (N, 3) with a^2 + b^2 = 1.

        With that normalisation ``l2 . (x, y, 1)`` is the signed distance in right pixels.
        """
        x1 = np.asarray(x1, dtype=np.float64).reshape(-1, 2)
        f, f_offset = self._epipolar
        lines = x1 @ f + f_offset
        norm = np.hypot(lines[:, 0], lines[:, 1])
        return lines / norm[:, None]

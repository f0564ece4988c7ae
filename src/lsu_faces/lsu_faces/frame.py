"""The face frame and the spherical embedding (thesis ch. 11.2): the types and maps that the nose finder
(`lsu_faces.face`) and the signatures (`lsu_faces.signature`) share.

Their own module because the nose finder checks its candidates with the face model (`lsu_faces.identity`),
which works on signatures: with these in `face`, face -> identity -> signature -> face would be a circle.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lsu_common.arrays import AnyArray

__all__ = ["NOSE_METHODS", "FaceError", "NotAFaceError", "FaceParams", "FaceFrame", "spherical_embedding",
           "parametric_map"]

NOSE_METHODS = ("template", "protrusion", "svd")


class FaceError(ValueError):
    """The face cannot be processed (too few points, bad parameters); the message says what to do."""


class NotAFaceError(FaceError):
    """The cloud holds no face: nothing protrudes like a nose (a plane, a ball, a box...)."""


@dataclass(frozen=True)
class FaceParams:
    """Settings of the face geometry (node parameters of the same names)."""

    nose_method: str = "template"
    depth_window_m: float = 0.20       # keep points within this depth of the nearest surface (drops background)
    svd_sphere_m: float = 0.07         # thesis: radius of the reduced cloud around the centroid
    ring_inner_m: float = 0.015        # protrusion ring around a candidate: inner radius
    ring_outer_m: float = 0.035        # and outer radius
    candidate_voxel_m: float = 0.005   # nose candidates: one per voxel of this size
    sample_voxel_m: float = 0.003      # surface samples for the ring statistics
    min_prominence_m: float = 0.006    # a nose protrudes at least this above its quadric ring
    radial_radius_m: float = 0.04      # plane fit around the tip for the radial vector
    crop_radius_m: float = 0.085       # face region: points within this of the nose tip
    sphere_radius_m: float = 0.09      # spherical embedding radius (about a head's half depth)
    max_symmetry_shift_m: float = 0.003  # the symmetry plane may move the nose tip at most this far
    min_points: int = 200
    ring_min_fraction: float = 0.5     # a nose candidate needs this much of its ring present (crop edges, rims)
    candidates: int = 12               # template stage: distinct candidates verified
    # below this the best candidate is "no face". The face-model check (max_model_weight) turns wrong places down,
    # so the layout need not: on the tuning people (ICT seeds 0-59, 180 captures per sensor) 0.40 found 11 of the 20
    # rig captures 0.45 refused, every nose within 4.1 mm, and changed nothing on the time-of-flight captures;
    # 0.35 put a time-of-flight nose 208 mm off
    min_confidence: float = 0.40
    # the layout confidence counts the template points the scanner sees within this angle of their normal (when
    # they are at least lsu_faces.face.FACING_MIN_SHARE of its core): flatter ones come back as nothing (the
    # matcher's scan cloud drops points seen beyond 75 deg, its max_view_angle_deg; a time-of-flight camera returns
    # holes near grazing). On the tuning people (ICT seeds 0-59, 360 captures per sensor, the far cheek and eye of
    # heads turned 20-30 deg): rig refusals 16 -> 4, every nose still right; time-of-flight refusals 17 -> 15, wrong
    # noses 4 -> 3. 180 counts every template point
    max_view_angle_deg: float = 75.0
    max_symmetry_mm: float = 4.0       # mirror residual of the verified face above this: a warning, never a refusal
    max_model_weight: float = 2.3      # face model fit at a candidate: RMS prior-normalised weight above this is no nose

    def __post_init__(self) -> None:
        if self.nose_method not in NOSE_METHODS:
            raise FaceError(f"nose_method must be one of {', '.join(NOSE_METHODS)} (got '{self.nose_method}')")
        if not 0 < self.ring_inner_m < self.ring_outer_m:
            raise FaceError("ring_inner_m must be positive and smaller than ring_outer_m")
        if not 0.0 < self.max_view_angle_deg <= 180.0:
            raise FaceError(f"max_view_angle_deg must be within (0, 180] (got {self.max_view_angle_deg})")
        for name in ("depth_window_m", "svd_sphere_m", "candidate_voxel_m", "sample_voxel_m", "radial_radius_m", "crop_radius_m",
                     "sphere_radius_m"):
            if not getattr(self, name) > 0:
                raise FaceError(f"{name} must be positive (got {getattr(self, name)})")


@dataclass
class FaceFrame:
    """Pose-normalising frame of a face: origin at the nose tip, rows = (right, down, out of the face)."""

    origin: AnyArray
    axes: AnyArray          # (3, 3) rows e1, e2, radial; local = (p - origin) @ axes.T

    def to_local(self, points: AnyArray) -> AnyArray:
        """Points in the face frame (z = height along the radial vector, <= 0 behind the tip)."""
        return (np.asarray(points, dtype=np.float64) - self.origin) @ self.axes.T


def spherical_embedding(points: AnyArray, frame: FaceFrame,
                        radius_m: float = FaceParams().sphere_radius_m) -> tuple[AnyArray, AnyArray, AnyArray]:
    """Map points onto the sphere touching the nose tip (thesis ch. 11.2.2).

    Returns (elevation [rad] from the radial vector, azimuth [rad] about it in (-pi, pi], radial
    distance from the sphere centre [m]).
    """
    centre = frame.origin - radius_m * frame.axes[2]
    d = (np.asarray(points, dtype=np.float64) - centre) @ frame.axes.T
    rho = np.linalg.norm(d, axis=1)
    unit = d / np.maximum(rho[:, None], 1e-12)
    elevation = np.arccos(np.clip(unit[:, 2], -1.0, 1.0))
    azimuth = np.arctan2(unit[:, 1], unit[:, 0])
    return elevation, azimuth, rho


def parametric_map(elevation: AnyArray, azimuth: AnyArray, rho: AnyArray, radius_m: float,
                   shape: tuple[int, int] = (24, 64), max_elevation_rad: float = np.radians(60.0)) -> AnyArray:
    """2D map (elevation rows x azimuth columns) of the mean height above the sphere [m]; NaN = no data.

    Row 0 is the ring around the nose tip (thesis Figure 56: "the bottom row represents all the points
    on a circle directly on top of the nose"); a roll about the radial vector shifts the columns cyclically.
    """
    rows, cols = shape
    r = np.floor(elevation / max_elevation_rad * rows).astype(np.int64)
    c = np.floor((azimuth + np.pi) / (2 * np.pi) * cols).astype(np.int64) % cols
    ok = (r >= 0) & (r < rows)
    flat = r[ok] * cols + c[ok]
    total = np.bincount(flat, weights=rho[ok] - radius_m, minlength=rows * cols)
    count = np.bincount(flat, minlength=rows * cols)
    out = np.full(rows * cols, np.nan)
    has = count > 0
    out[has] = total[has] / count[has]
    return out.reshape(rows, cols)

"""Triangulation of matched undistorted pixel pairs into 3D points of the left optical frame (thesis ch. 7.1.3).

Three methods, all vectorised over a snap:

- ``midpoint``: the point halfway between the closest points of the two viewing rays (what
  Bouguet's ``stereo_triangulation``, used by the thesis, computes).
- ``dlt``: linear homogeneous triangulation, ``cv2.triangulatePoints``.
- ``optimal``: Hartley-Sturm: move both pixels the least (in image distance) onto a pair that
  satisfies the epipolar constraint exactly (``cv2.correctMatches``), then triangulate; this
  minimises the reprojection error under Gaussian pixel noise.

When a match comes from an epipolar intersection (``matching.match_line``) the pair already
satisfies ``x2^T F x1 = 0``, so the rays meet and the three methods agree to rounding; they
differ on pairs that do not (e.g. the thesis' nearest-pixel matches). The benchmark compares
them; the default is ``midpoint`` (equal accuracy, fastest, no degenerate homogeneous scale).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from lsu_common.arrays import AnyArray

from .stereo import StereoModel

__all__ = ["METHODS", "TriangulationError", "triangulate", "triangulate_midpoint", "midpoint_of_rays",
           "triangulate_dlt", "triangulate_optimal", "reprojection_error_px", "accept_points"]

METHODS = ("midpoint", "dlt", "optimal")


class TriangulationError(ValueError):
    """Bad arguments for triangulation (unknown method, shapes that do not match)."""


def _check(x1: AnyArray, x2: AnyArray) -> tuple:
    x1 = np.asarray(x1, dtype=np.float64).reshape(-1, 2)
    x2 = np.asarray(x2, dtype=np.float64).reshape(-1, 2)
    if len(x1) != len(x2):
        raise TriangulationError(f"{len(x1)} left pixels but {len(x2)} right pixels; pass matched pairs")
    return x1, x2


def triangulate_midpoint(model: StereoModel, x1: AnyArray, x2: AnyArray) -> AnyArray:
    """Midpoint of the shortest segment between the two rays, (N, 3) [m]."""
    x1, x2 = _check(x1, x2)
    return midpoint_of_rays(model, model.closest_approach(x1, x2))


def midpoint_of_rays(model: StereoModel, rays: tuple) -> AnyArray:
    """The midpoint triangulation from ``model.closest_approach(x1, x2)`` of the pairs, (N, 3) [m]."""
    r1, r2, lam, mu = rays
    return 0.5 * (lam[:, None] * r1 + (model.right_centre + mu[:, None] * r2))


def triangulate_dlt(model: StereoModel, x1: AnyArray, x2: AnyArray) -> AnyArray:
    """Linear (DLT) triangulation with ``cv2.triangulatePoints``, (N, 3) [m]."""
    x1, x2 = _check(x1, x2)
    if len(x1) == 0:
        return np.zeros((0, 3))
    h = cv2.triangulatePoints(model.P1, model.P2, x1.T.copy(), x2.T.copy())
    with np.errstate(divide="ignore", invalid="ignore"):
        return (h[:3] / h[3]).T


def triangulate_optimal(model: StereoModel, x1: AnyArray, x2: AnyArray) -> AnyArray:
    """Hartley-Sturm optimal triangulation: ``cv2.correctMatches`` then DLT, (N, 3) [m]."""
    x1, x2 = _check(x1, x2)
    if len(x1) == 0:
        return np.zeros((0, 3))
    c1, c2 = cv2.correctMatches(model.F, x1.reshape(1, -1, 2), x2.reshape(1, -1, 2))
    return triangulate_dlt(model, c1.reshape(-1, 2), c2.reshape(-1, 2))


def triangulate(model: StereoModel, x1: AnyArray, x2: AnyArray, method: str = "midpoint") -> AnyArray:
    """Triangulate undistorted pixel pairs with ``method`` (one of :data:`METHODS`)."""
    if method == "midpoint":
        return triangulate_midpoint(model, x1, x2)
    if method == "dlt":
        return triangulate_dlt(model, x1, x2)
    if method == "optimal":
        return triangulate_optimal(model, x1, x2)
    raise TriangulationError(f"unknown triangulation method '{method}'; use one of {', '.join(METHODS)}")


def reprojection_error_px(model: StereoModel, X: AnyArray, x1: AnyArray, x2: AnyArray) -> AnyArray:
    """Larger of the left and right reprojection errors [undistorted px] of points X (N, 3)."""
    X = np.asarray(X, dtype=np.float64).reshape(-1, 3)
    h1 = X @ model.K1.T
    h2 = (X @ model.R.T + model.T) @ model.K2.T
    x1, x2 = np.asarray(x1), np.asarray(x2)
    with np.errstate(divide="ignore", invalid="ignore"):
        # column by column: numpy is slow on (N, 2) blocks
        ex, ey = h1[:, 0] / h1[:, 2] - x1[:, 0], h1[:, 1] / h1[:, 2] - x1[:, 1]
        fx, fy = h2[:, 0] / h2[:, 2] - x2[:, 0], h2[:, 1] / h2[:, 2] - x2[:, 1]
        # sqrt is monotone: the larger root is the root of the larger sum (NaN stays NaN)
        return np.sqrt(np.maximum(ex * ex + ey * ey, fx * fx + fy * fy))


@dataclass(frozen=True)
class Acceptance:
    """Counts of points rejected by :func:`accept_points`."""

    non_finite: int
    depth: int
    reprojection: int


def accept_points(model: StereoModel, X: AnyArray, x1: AnyArray, x2: AnyArray, depth_min_m: float,
                  depth_max_m: float, max_reproj_px: float) -> tuple:
    """Mask of points that are finite, in front of both cameras within the depth range, and reproject well.

    Returns ``(mask, Acceptance)``. NaN or infinite points (parallel rays, degenerate DLT) are
    always rejected, so they never reach a cloud.
    """
    X = np.asarray(X, dtype=np.float64)
    # a finite sum means finite rows (NaN and inf propagate); only otherwise look row by row
    all_finite = math.isfinite(X.sum())
    if all_finite:
        Xf, n_finite = X, len(X)
    else:
        finite = np.logical_and.reduce(np.isfinite(X), axis=1)
        n_finite = int(np.count_nonzero(finite))
        Xf = np.where(finite[:, None], X, 0.0)
    z = Xf[:, 2]
    depth_ok = (z >= depth_min_m) & (z <= depth_max_m) & (Xf @ model.R[2] + model.T[2] > 0)
    if not all_finite:
        depth_ok &= finite
    err = reprojection_error_px(model, Xf, x1, x2)
    reproj_ok = depth_ok & (err <= max_reproj_px)  # false for NaN and, below a finite limit, for inf
    if not math.isfinite(max_reproj_px):
        reproj_ok &= np.isfinite(err)
    n_depth_ok = int(np.count_nonzero(depth_ok))
    counts = Acceptance(non_finite=len(X) - n_finite, depth=n_finite - n_depth_ok,
                        reprojection=n_depth_ok - int(np.count_nonzero(reproj_ok)))
    return reproj_ok, counts

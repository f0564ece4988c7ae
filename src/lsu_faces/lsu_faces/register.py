"""Deterministic rigid registration: point-to-plane ICP on scipy's cKDTree with closed-form Gauss-Newton steps.

Hand-written because open3d's ICP runs its correspondence search and reductions in parallel: the
same input gives slightly different transforms in different processes, which changed identification
results run to run. Here every step is a fixed sequence of numpy operations (exact nearest
neighbours, a 6 x 6 normal-equation solve), so the same input gives the same bits in every process.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from lsu_common.arrays import AnyArray

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

__all__ = ["Registration", "icp_point_to_plane", "rotation_from_vector", "estimate_normals", "apply"]


@dataclass
class Registration:
    """Result of `icp_point_to_plane`: ``T`` maps source points onto the target."""

    T: AnyArray             # (4, 4)
    rms_m: float              # RMS point-to-plane residual of the inliers at the last distance
    inlier_fraction: float    # source points with a target point within the last distance
    inliers: AnyArray       # (N,) bool mask of the source points


def apply(T: AnyArray, points: AnyArray) -> AnyArray:
    """Points (N, 3) transformed by the 4 x 4 ``T``."""
    return np.asarray(points, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]


def rotation_from_vector(w: AnyArray) -> AnyArray:
    """Rotation matrix of the axis-angle vector ``w`` (Rodrigues); (K, 3) vectors give (K, 3, 3) matrices."""
    v = np.asarray(w, dtype=np.float64)
    many = v.reshape(-1, 3)
    theta = np.sqrt(np.sum(many * many, axis=1))
    small = theta < 1e-12
    k = many / np.where(small, 1.0, theta)[:, None]
    zero = np.zeros(len(many))
    K = np.stack([zero, -k[:, 2], k[:, 1], k[:, 2], zero, -k[:, 0], -k[:, 1], k[:, 0], zero], axis=1).reshape(-1, 3, 3)
    R = np.eye(3) + np.sin(theta)[:, None, None] * K + (1.0 - np.cos(theta))[:, None, None] * (K @ K)
    R[small] = np.eye(3)
    return R if v.ndim == 2 else R[0]


def estimate_normals(points: AnyArray, k: int = 12, towards: AnyArray | None = None,
                     tree: cKDTree | None = None) -> AnyArray:
    """Unit normals (least-spread direction of the ``k`` nearest neighbours), oriented towards ``towards``

    (a viewpoint; default the origin, i.e. the camera of a cloud in its optical frame).
    """
    from scipy.spatial import cKDTree
    p = np.asarray(points, dtype=np.float64)
    tree = tree or cKDTree(p)
    _, idx = tree.query(p, k=min(k, len(p)))
    nb = p[idx]
    c = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", c, c)
    _, vecs = np.linalg.eigh(cov)
    n = vecs[:, :, 0]
    view = (np.zeros(3) if towards is None else np.asarray(towards, dtype=np.float64)) - p
    n[np.einsum("ij,ij->i", n, view) < 0] *= -1.0
    return n


def icp_point_to_plane(source: AnyArray, target: AnyArray, target_normals: AnyArray,
                       init: AnyArray | None = None, distances: Sequence[float] = (0.01, 0.005, 0.0025),
                       iterations: int = 8, tree: cKDTree | None = None,
                       weights: AnyArray | None = None, trim: float = 0.1) -> Registration:
    """Align ``source`` onto the surface of ``target`` (points with normals).

    For each maximum correspondence distance in ``distances`` (coarse to fine), ``iterations``
    Gauss-Newton steps of the linearised point-to-plane error: nearest target point of every moved
    source point (exact, cKDTree), pairs farther than the distance dropped and the ``trim`` fraction of
    the largest residuals ignored (hair, occlusion rims), then the 6 x 6 least-squares step
    (rotation vector, translation) solved in closed form. ``weights`` (per source point) scale the
    pairs' influence. Stops early when a step moves less than 1 micrometre.
    """
    from scipy.spatial import cKDTree
    src = np.asarray(source, dtype=np.float64)
    tgt = np.asarray(target, dtype=np.float64)
    nrm = np.asarray(target_normals, dtype=np.float64)
    tree = tree or cKDTree(tgt)
    T = np.eye(4) if init is None else np.asarray(init, dtype=np.float64).copy()
    w_src = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64)
    rms, inl = float("inf"), np.zeros(len(src), bool)
    for dist in distances:
        for _ in range(iterations):
            moved = apply(T, src)
            d, j = tree.query(moved, distance_upper_bound=dist)
            inl = np.isfinite(d)
            if inl.sum() < 6:
                return Registration(T, float("inf"), float(inl.mean()) if len(inl) else 0.0, inl)
            p, q, n, w = moved[inl], tgt[j[inl]], nrm[j[inl]], w_src[inl]
            r = np.einsum("ij,ij->i", p - q, n)
            if trim > 0 and len(r) > 20:
                cut = np.quantile(np.abs(r), 1.0 - trim)
                w = w * (np.abs(r) <= cut)
            J = np.concatenate([np.cross(p, n), n], axis=1)
            A = (J * w[:, None]).T @ J
            b = -(J * w[:, None]).T @ r
            try:
                x = np.linalg.solve(A + 1e-12 * np.eye(6), b)
            except np.linalg.LinAlgError:
                break
            step = np.eye(4)
            step[:3, :3] = rotation_from_vector(x[:3])
            step[:3, 3] = x[3:]
            T = step @ T
            rms = float(np.sqrt(np.sum(w * r ** 2) / max(np.sum(w), 1e-12)))
            if np.linalg.norm(x[3:]) < 1e-6 and np.linalg.norm(x[:3]) < 1e-5:
                break
    moved = apply(T, src)
    d, j = tree.query(moved, distance_upper_bound=distances[-1])
    inl = np.isfinite(d)
    if inl.any():
        r = np.einsum("ij,ij->i", moved[inl] - tgt[j[inl]], nrm[j[inl]])
        r = np.sort(np.abs(r))[: max(1, int(round(len(r) * (1.0 - trim))))]
        rms = float(np.sqrt(np.mean(r ** 2)))
    return Registration(T, rms, float(inl.mean()), inl)

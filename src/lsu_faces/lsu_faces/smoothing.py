"""Mesh smoothing (thesis ch. 9.3) and how much it shrinks the surface.

- `laplacian_smooth`: the thesis' centroid-directed smoothing: every vertex moves a fraction
  ``factor`` of the way to the centroid of its neighbours, ``iterations`` times. The thesis' accuracy
  study (ch. 9.3.2) used 30 iterations at 0.1; it noted the contraction this causes.
- `taubin_smooth`: the expansion step the thesis proposed but did not try (ch. 9.3.1): each pass
  is a shrinking step with ``lam > 0`` followed by an inflating step with ``mu < -lam`` (Taubin 1995),
  a low-pass filter that removes noise without the contraction.
- `enclosed_volume`, `surface_area`, `shrinkage`: the volume of a closed mesh (divergence theorem)
  or, for an open scan surface, its relief volume above a back plane; area; the change in percent.

The umbrella operator is a sparse matrix built once from the neighbour lists (scipy.sparse), so an
iteration is one sparse product over all vertices.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from lsu_common.arrays import AnyArray

if TYPE_CHECKING:
    from scipy import sparse

from .mesh import _edge_counts, boundary_vertices, face_normals, is_closed, neighbours

__all__ = ["SmoothingError", "SmoothParams", "umbrella_operator", "laplacian_smooth", "taubin_smooth", "smooth",
           "enclosed_volume", "surface_area", "shrinkage", "METHODS", "THESIS_FACTOR", "THESIS_ITERATIONS"]

THESIS_FACTOR = 0.1       # ch. 9.3.2: "smoothed over 30 iterations with 0.1 scaling"
THESIS_ITERATIONS = 30
METHODS = ("taubin", "laplacian", "none")


class SmoothingError(ValueError):
    """Smoothing parameters out of range (the message names the parameter and the valid range)."""


@dataclass(frozen=True)
class SmoothParams:
    """Which smoother and its settings (node parameters of the same names)."""

    method: str = "taubin"
    iterations: int = THESIS_ITERATIONS     # Laplacian iterations, or Taubin (lam, mu) passes
    factor: float = THESIS_FACTOR           # Laplacian step
    taubin_lambda: float = 0.5
    taubin_mu: float = -0.53

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise SmoothingError(f"smoothing method must be one of {', '.join(METHODS)} (got '{self.method}')")
        if self.iterations < 0:
            raise SmoothingError(f"smoothing iterations must be >= 0 (got {self.iterations})")
        if not 0.0 < self.factor <= 1.0:
            raise SmoothingError(f"Laplacian factor must be in (0, 1] (got {self.factor})")
        if not 0.0 < self.taubin_lambda < 1.0:
            raise SmoothingError(f"taubin_lambda must be in (0, 1) (got {self.taubin_lambda})")
        if not self.taubin_mu < -self.taubin_lambda:
            raise SmoothingError(f"taubin_mu must be below -taubin_lambda = {-self.taubin_lambda} "
                                 f"(got {self.taubin_mu}); otherwise the pass shrinks instead of inflating")


def umbrella_operator(triangles: AnyArray, n_vertices: int, boundary_as_curve: bool = False) -> sparse.csr_matrix:
    """Sparse matrix W with (W @ X)[i] = centroid of i's neighbours (rows of isolated vertices: X[i] itself).

    ``boundary_as_curve``: a vertex on the mesh boundary averages only its boundary neighbours, so
    the rim of an open scan is smoothed as a curve instead of being pulled into the surface (the
    one-sided pull the thesis blamed for the contraction of the edges, ch. 9.3.1).
    """
    from scipy import sparse
    nb = neighbours(triangles, n_vertices)
    rows = np.repeat(np.arange(n_vertices), nb.counts)
    cols = nb.indices
    if boundary_as_curve:
        edges, counts = _edge_counts(triangles)
        rim = edges[counts == 1]
        on_rim = np.zeros(n_vertices, bool)
        on_rim[rim.ravel()] = True
        rim_key = set((rim[:, 0] * (n_vertices + 1) + rim[:, 1]).tolist())
        lo, hi = np.minimum(rows, cols), np.maximum(rows, cols)
        is_rim_edge = np.isin(lo * (n_vertices + 1) + hi, np.fromiter(rim_key, dtype=np.int64, count=len(rim_key)))
        keep = ~on_rim[rows] | is_rim_edge
        rows, cols = rows[keep], cols[keep]
    counts = np.bincount(rows, minlength=n_vertices)
    weights = 1.0 / np.maximum(counts, 1)[rows]
    W = sparse.csr_matrix((weights, (rows, cols)), shape=(n_vertices, n_vertices))
    lonely = np.flatnonzero(counts == 0)
    if len(lonely):
        W = W + sparse.csr_matrix((np.ones(len(lonely)), (lonely, lonely)), shape=(n_vertices, n_vertices))
    return W.tocsr()


def _steps(vertices: AnyArray, W: sparse.csr_matrix, factors: list, iterations: int) -> AnyArray:
    X = np.asarray(vertices, dtype=np.float64).copy()
    for _ in range(iterations):
        for f in factors:
            X = X + f * (W @ X - X)
    return X


def laplacian_smooth(vertices: AnyArray, triangles: AnyArray, factor: float = THESIS_FACTOR,
                     iterations: int = THESIS_ITERATIONS) -> AnyArray:
    """Thesis smoothing: ``X <- X + factor (centroid(neighbours) - X)``, ``iterations`` times; returns new vertices."""
    SmoothParams(method="laplacian", iterations=iterations, factor=factor)
    return _steps(vertices, umbrella_operator(triangles, len(vertices)), [factor], iterations)


def taubin_smooth(vertices: AnyArray, triangles: AnyArray, lam: float = 0.5, mu: float = -0.53,
                  iterations: int = THESIS_ITERATIONS) -> AnyArray:
    """Taubin lambda|mu smoothing: ``iterations`` passes of a shrink (lam) then an inflate (mu) step."""
    SmoothParams(method="taubin", iterations=iterations, taubin_lambda=lam, taubin_mu=mu)
    W = umbrella_operator(triangles, len(vertices), boundary_as_curve=True)
    return _steps(vertices, W, [lam, mu], iterations)


def smooth(vertices: AnyArray, triangles: AnyArray, params: SmoothParams = SmoothParams()) -> AnyArray:
    """Smooth with the method and settings of ``params`` (``none`` returns a copy)."""
    if params.method == "none" or params.iterations == 0 or len(triangles) == 0:
        return np.asarray(vertices, dtype=np.float64).copy()
    if params.method == "laplacian":
        return laplacian_smooth(vertices, triangles, params.factor, params.iterations)
    return taubin_smooth(vertices, triangles, params.taubin_lambda, params.taubin_mu, params.iterations)


def surface_area(vertices: AnyArray, triangles: AnyArray) -> float:
    """Total triangle area [m^2]."""
    return float(0.5 * np.linalg.norm(face_normals(vertices, triangles), axis=1).sum())


def enclosed_volume(vertices: AnyArray, triangles: AnyArray, axis: AnyArray | None = None,
                    back: float | None = None) -> float:
    """Volume [m^3] of a closed mesh, or the relief volume of an open surface.

    Closed (every edge in two triangles): the divergence theorem, sum of signed tetrahedra to the
    centroid. Open (a scan seen from one side): the volume between the surface and the plane
    perpendicular to ``axis`` (default: the viewing axis, left optical z) through the surface's
    farthest vertex along it (or at height ``back`` along it), i.e. the relief that smoothing can flatten.
    """
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    if len(t) == 0:
        return 0.0
    if is_closed(t):
        c = v[t].reshape(-1, 3).mean(axis=0)
        a, b, d = v[t[:, 0]] - c, v[t[:, 1]] - c, v[t[:, 2]] - c
        return float(abs(np.einsum("ij,ij->i", a, np.cross(b, d)).sum()) / 6.0)
    z = np.array([0.0, 0.0, 1.0]) if axis is None else np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    height = v @ z
    if back is None:
        back = float(height[np.unique(t)].max())
    # prism under each triangle: projected (signed) area times the mean height above the back plane
    fn = face_normals(v, t)
    projected = np.abs(fn @ z) * 0.5
    return float((projected * (back - height[t].mean(axis=1))).sum())


def shrinkage(before: AnyArray, after: AnyArray, triangles: AnyArray) -> dict[str, float]:
    """Volume and area change of a smoothing step, in percent of the original (negative = shrank).

    Also the mean vertex displacement [m] along the original normals (negative = moved inwards).
    """
    v0, v1 = np.asarray(before, dtype=np.float64), np.asarray(after, dtype=np.float64)
    # the same back plane for both, so a single vertex moving at the rear cannot shift the reference
    back = float((v0[np.unique(np.asarray(triangles))] @ np.array([0.0, 0.0, 1.0])).max()) if len(triangles) else 0.0
    vol0, vol1 = enclosed_volume(v0, triangles, back=back), enclosed_volume(v1, triangles, back=back)
    a0, a1 = surface_area(v0, triangles), surface_area(v1, triangles)
    fn = np.zeros_like(v0)
    fnt = face_normals(v0, triangles)
    for k in range(3):
        np.add.at(fn, np.asarray(triangles)[:, k], fnt)
    norm = np.linalg.norm(fn, axis=1, keepdims=True)
    n = np.divide(fn, norm, out=np.zeros_like(fn), where=norm > 0)
    used = norm[:, 0] > 0
    interior = used & ~boundary_vertices(triangles, len(v0))
    # the camera-facing normals of a scan point outwards, so motion along -n is inwards
    disp = np.einsum("ij,ij->i", v1 - v0, n)
    return {"volume_change_pct": 100.0 * (vol1 - vol0) / vol0 if vol0 > 0 else float("nan"),
            "area_change_pct": 100.0 * (a1 - a0) / a0 if a0 > 0 else float("nan"),
            "mean_normal_displacement_m": float(disp[interior].mean()) if np.any(interior) else 0.0}

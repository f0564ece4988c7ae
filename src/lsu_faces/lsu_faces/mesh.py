"""Surface mesh of a scan (thesis ch. 8): Delaunay in the left image plane, edge culling, neighbourhoods, normals.

The scanner sees the subject from the left camera, so the left-image pixel (u, v) of every point is a
2.5D parametrisation of the surface: a Delaunay triangulation of (u, v) (``scipy.spatial.Delaunay``)
connects each point to its image neighbours, and the triangle list indexes the 3D points directly
(the thesis kept the 2D and 3D arrays in the same order for exactly this reason).

Delaunay fills the whole convex hull, so it also bridges holes, silhouettes and depth jumps. Two
scale-free tests remove those triangles (thresholds relative to robust statistics of the scan
itself, so they hold at any distance and any carriage step):

- *over-long edge*: a 3D edge longer than ``max_edge_factor`` x the median 3D edge length;
- *stretch* (depth jump): an edge's 3D length per pixel of image distance, divided by its depth,
  is the inverse focal length times 1/cos(slant) on a continuous surface; an edge whose value exceeds
  ``max_stretch`` x the median value is a jump, not a surface seen at an angle.

Neighbour lists come from the unique edges of the kept triangles (thesis ch. 8.2.3), as CSR arrays.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from lsu_common.arrays import AnyArray

if TYPE_CHECKING:
    pass

__all__ = ["MeshError", "MeshParams", "FaceMesh", "Neighbours", "triangulate_image_plane", "unique_edges",
           "neighbours", "vertex_normals", "face_normals", "boundary_vertices", "is_closed"]


class MeshError(ValueError):
    """A mesh cannot be built (too few points, no u/v, degenerate pixels); the message says what to do."""


@dataclass(frozen=True)
class MeshParams:
    """Culling thresholds (dimensionless: relative to the scan's own median edge)."""

    max_edge_factor: float = 5.0     # cull triangles with a 3D edge longer than this x the median edge
    max_stretch: float = 6.0         # cull triangles with an edge stretched more than this x the median (jumps)
    min_points: int = 50             # fewer points than this make no useful surface

    def __post_init__(self) -> None:
        if not self.max_edge_factor > 1.0:
            raise MeshError(f"max_edge_factor must be > 1 (got {self.max_edge_factor})")
        if not self.max_stretch > 1.0:
            raise MeshError(f"max_stretch must be > 1 (got {self.max_stretch})")
        if self.min_points < 3:
            raise MeshError(f"min_points must be >= 3 (got {self.min_points})")


@dataclass
class Neighbours:
    """Vertex neighbourhoods in CSR form: the neighbours of vertex i are ``indices[indptr[i]:indptr[i+1]]``."""

    indptr: AnyArray
    indices: AnyArray

    def of(self, i: int) -> AnyArray:
        """Neighbour indices of vertex ``i``."""
        return self.indices[self.indptr[i]:self.indptr[i + 1]]

    @property
    def counts(self) -> AnyArray:
        """Number of neighbours per vertex."""
        return np.diff(self.indptr)


@dataclass
class FaceMesh:
    """A triangle mesh (metres, left optical frame) with optional per-vertex colours and image pixels."""

    vertices: AnyArray                       # (N, 3) float64
    triangles: AnyArray                      # (M, 3) int64, oriented with normals towards the camera
    colors: AnyArray | None = None        # (N, 3) uint8 R, G, B
    uv: AnyArray | None = None            # (N, 2) left image pixel
    stats: dict = field(default_factory=dict)  # culling counts, median edge

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.triangles = np.asarray(self.triangles, dtype=np.int64).reshape(-1, 3)

    @property
    def n_vertices(self) -> int:
        """Vertex count."""
        return int(len(self.vertices))

    @property
    def n_triangles(self) -> int:
        """Triangle count."""
        return int(len(self.triangles))

    def with_vertices(self, vertices: AnyArray) -> FaceMesh:
        """The same connectivity and colours with new vertex positions (e.g. after smoothing)."""
        return FaceMesh(np.asarray(vertices, dtype=np.float64).copy(), self.triangles.copy(),
                        None if self.colors is None else self.colors.copy(),
                        None if self.uv is None else self.uv.copy(), dict(self.stats))

    def compact(self) -> FaceMesh:
        """Drop vertices that no triangle uses (indices renumbered)."""
        used = np.zeros(self.n_vertices, bool)
        used[self.triangles.ravel()] = True
        remap = np.cumsum(used) - 1
        return FaceMesh(self.vertices[used], remap[self.triangles],
                        None if self.colors is None else self.colors[used],
                        None if self.uv is None else self.uv[used], dict(self.stats))

    def normals(self) -> AnyArray:
        """Unit vertex normals (area-weighted), see `vertex_normals`."""
        return vertex_normals(self.vertices, self.triangles)

    def neighbours(self) -> Neighbours:
        """Neighbour lists from the unique edges, see `neighbours`."""
        return neighbours(self.triangles, self.n_vertices)


def unique_edges(triangles: AnyArray) -> AnyArray:
    """Unique undirected edges (E, 2) of a triangle list, each as (low index, high index)."""
    return _edge_counts(triangles)[0]


def neighbours(triangles: AnyArray, n_vertices: int) -> Neighbours:
    """CSR neighbour lists from the unique edges (thesis ch. 8.2.3: sort the edge list by its first index)."""
    e = unique_edges(triangles)
    both = np.concatenate([e, e[:, ::-1]])
    order = np.lexsort((both[:, 1], both[:, 0]))
    both = both[order]
    counts = np.bincount(both[:, 0], minlength=n_vertices)
    indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return Neighbours(indptr, both[:, 1].astype(np.int64))


def face_normals(vertices: AnyArray, triangles: AnyArray) -> AnyArray:
    """Unnormalised triangle normals (cross product: length = 2 x area)."""
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    return np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])


def vertex_normals(vertices: AnyArray, triangles: AnyArray) -> AnyArray:
    """Area-weighted unit vertex normals; a vertex in no triangle gets (0, 0, 0)."""
    fn = face_normals(vertices, triangles)
    out = np.zeros((len(vertices), 3))
    for k in range(3):
        np.add.at(out, np.asarray(triangles)[:, k], fn)
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    return np.divide(out, norm, out=np.zeros_like(out), where=norm > 0)


def _edge_counts(triangles: AnyArray) -> tuple[AnyArray, AnyArray]:
    """Unique undirected edges (E, 2) as (low, high), in lexicographic order, and how many triangles use each."""
    tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    e = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    e.sort(axis=1)
    if not len(e):
        return np.zeros((0, 2), np.int64), np.zeros(0, np.int64)
    # one int64 key per edge, low * (max + 1) + high: its order is the rows' lexicographic order, and numpy's
    # unique on a 1-D array sorts numbers where its axis=0 form sorts the rows as opaque bytes (several times slower)
    base = int(e.max()) + 1
    keys, counts = np.unique(e[:, 0] * base + e[:, 1], return_counts=True)
    return np.stack([keys // base, keys % base], axis=1), counts


def is_closed(triangles: AnyArray) -> bool:
    """True when every edge is shared by exactly two triangles (a watertight surface)."""
    _, counts = _edge_counts(triangles)
    return bool(len(counts)) and bool(np.all(counts == 2))


def boundary_vertices(triangles: AnyArray, n_vertices: int) -> AnyArray:
    """Boolean mask of vertices on a boundary edge (an edge used by one triangle only)."""
    edges, counts = _edge_counts(triangles)
    mask = np.zeros(n_vertices, bool)
    mask[edges[counts == 1].ravel()] = True
    return mask


def triangulate_image_plane(xyz: AnyArray, uv: AnyArray, colors: AnyArray | None = None,
                            params: MeshParams = MeshParams()) -> FaceMesh:
    """Mesh a scan cloud: Delaunay on the left-image pixels ``uv``, cull jumps and long edges, orient to the camera.

    Args:
        xyz: (N, 3) points [m], left optical frame (the camera centre is the origin).
        uv: (N, 2) left image pixel of each point (the PointCloud2 fields u, v).
        colors: optional (N, 3) uint8 RGB per point.
        params: culling thresholds.

    Raises:
        MeshError: too few points, mismatched arrays, non-finite values, or all pixels on a line.
    """
    from scipy.spatial import Delaunay, QhullError
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if len(uv) != len(xyz):
        raise MeshError(f"{len(xyz)} points but {len(uv)} u/v pixels; every point needs its left-image pixel")
    if len(xyz) < params.min_points:
        raise MeshError(f"the cloud has {len(xyz)} points, fewer than the {params.min_points} a surface needs; "
                        f"check that the laser line was found (lsu topic echo /lsu/points) and scan again")
    if not (np.all(np.isfinite(xyz)) and np.all(np.isfinite(uv))):
        raise MeshError("the cloud holds NaN or infinite coordinates or pixels; drop them before meshing")
    # identical pixels (two snaps seeing the same spot) would be dropped by Qhull; jitter-free dedupe instead
    _, first = np.unique(np.round(uv, 6), axis=0, return_index=True)
    keep = np.sort(first)
    try:
        tri = Delaunay(uv[keep]).simplices
    except QhullError as exc:
        raise MeshError(f"the pixels of the cloud are degenerate (all on one line?): {str(exc).splitlines()[0]}") from None
    tri = keep[tri].astype(np.int64)
    total = len(tri)

    edges = unique_edges(tri)
    d3 = np.linalg.norm(xyz[edges[:, 0]] - xyz[edges[:, 1]], axis=1)
    d2 = np.linalg.norm(uv[edges[:, 0]] - uv[edges[:, 1]], axis=1)
    depth = 0.5 * (np.linalg.norm(xyz[edges[:, 0]], axis=1) + np.linalg.norm(xyz[edges[:, 1]], axis=1))
    stretch = d3 / np.maximum(d2 * depth, 1e-12)
    median_edge = float(np.median(d3))
    median_stretch = float(np.median(stretch))
    bad_edge = (d3 > params.max_edge_factor * median_edge) | (stretch > params.max_stretch * median_stretch)
    # a triangle is culled when any of its three edges is bad: look its edges up in the sorted edge table
    tri_edges = np.stack([np.sort(tri[:, [0, 1]], axis=1), np.sort(tri[:, [1, 2]], axis=1),
                          np.sort(tri[:, [2, 0]], axis=1)], axis=1)
    key_all = edges[:, 0] * (len(xyz) + 1) + edges[:, 1]
    key_tri = tri_edges[..., 0] * (len(xyz) + 1) + tri_edges[..., 1]
    bad_tri = bad_edge[np.searchsorted(key_all, key_tri)].any(axis=1)
    tri = tri[~bad_tri]
    # orient every triangle so that its normal faces the camera (origin of the left frame)
    fn = face_normals(xyz, tri)
    centre = xyz[tri].mean(axis=1)
    flip = np.einsum("ij,ij->i", fn, centre) > 0
    tri[flip] = tri[flip][:, [0, 2, 1]]
    stats = {"delaunay_triangles": int(total), "culled_triangles": int(bad_tri.sum()),
             "median_edge_m": median_edge, "median_stretch": median_stretch}
    cols = None if colors is None else np.asarray(colors, dtype=np.uint8).reshape(-1, 3)
    return FaceMesh(xyz.copy(), tri, cols, uv.copy(), stats)


def mesh_plain_cloud(xyz: AnyArray, colors: AnyArray | None = None, viewpoint: AnyArray | None = None
                     ) -> FaceMesh:
    """Mesh a cloud without a pixel grid (no u/v) by ball pivoting (open3d, Bernardini et al. 1999).

    Normals are estimated from the 16 nearest neighbours and turned towards ``viewpoint`` (default the
    origin: the sensor of a cloud in its optical frame); the balls' radii are 1.5, 3 and 6 times the
    median point spacing, so the method needs no scale setting.
    """
    import open3d as o3d
    from scipy.spatial import cKDTree

    p = np.asarray(xyz, dtype=np.float64)
    if len(p) < 10:
        raise MeshError(f"{len(p)} points are too few to mesh")
    d, _ = cKDTree(p).query(p, k=2)
    spacing = float(np.median(d[:, 1]))
    if not spacing > 0:
        raise MeshError("the cloud's points coincide; nothing to mesh")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(16))
    cloud.orient_normals_towards_camera_location(np.zeros(3) if viewpoint is None else np.asarray(viewpoint, float))
    radii = o3d.utility.DoubleVector([1.5 * spacing, 3.0 * spacing, 6.0 * spacing])
    mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(cloud, radii)
    tris = np.asarray(mesh.triangles, dtype=np.int64)
    if len(tris) == 0:
        raise MeshError("ball pivoting made no triangle (points too sparse or noisy)")
    # open3d keeps the input vertices in order: the triangles index the given points and colours
    return FaceMesh(p, tris, colors)

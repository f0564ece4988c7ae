"""Scene objects for the simulated rig: meshes (left optical frame, metres) with an albedo function.

An albedo function gets the hit points (N,3) and their pixel footprints dP/du, dP/dv (N,3 each,
metres per pixel) and returns BGR albedo (N,3) in [0, 1]. The footprints let the chessboard
box-filter its squares over each pixel (no aliasing: corner finding must be as good as on a real
camera, where the sensor integrates the light over the pixel).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import open3d as o3d

from lsu_common.arrays import AnyArray

AlbedoFn = Callable[[AnyArray, AnyArray, AnyArray], AnyArray]
MATERIALS = ("surface", "skin")


class SceneError(ValueError):
    """A scene cannot be built (unknown name, unreadable or empty mesh file, bad size)."""


@dataclass
class SceneObject:
    """One mesh of the scene with its surface appearance."""

    name: str
    mesh: o3d.geometry.TriangleMesh
    albedo: AlbedoFn
    specularity: float = 0.3   # scales the rig's highlight strength
    extra: dict = field(default_factory=dict)  # e.g. board corners, nose tip (left frame)
    # "surface": the laser line is the sheet's profile (paper, plaster, boards); "skin": red light
    # scatters below the surface (`physics.skin_profile`): wider line, centre shifted
    material: str = "surface"

    def __post_init__(self) -> None:
        if self.material not in MATERIALS:
            raise SceneError(f"{self.name}: material must be one of {', '.join(MATERIALS)}, got {self.material!r}")


def uniform_albedo(bgr: Sequence[float]) -> AlbedoFn:
    """Constant colour."""
    colour = np.asarray(bgr, dtype=np.float64).reshape(1, 3)

    def albedo(points: AnyArray, du: AnyArray, dv: AnyArray) -> AnyArray:
        return np.repeat(colour, len(points), axis=0)

    return albedo


def mottled_albedo(bgr: Sequence[float] | AnyArray, contrast: float = 0.12, seed: int = 0, scale_m: float = 0.02) -> AlbedoFn:
    """A colour with a smooth, seeded 3D texture (sum of random sinusoids): paper, skin, plaster."""
    rng = np.random.default_rng(seed)
    freqs = rng.normal(size=(6, 3)) / scale_m
    phases = rng.uniform(0, 2 * np.pi, size=6)
    colour = np.asarray(bgr, dtype=np.float64).reshape(1, 3)

    def albedo(points: AnyArray, du: AnyArray, dv: AnyArray) -> AnyArray:
        wave = np.sin(points @ freqs.T + phases).mean(axis=1, keepdims=True)
        return np.clip(colour * (1.0 + contrast * wave), 0.0, 1.0)

    return albedo


def _legacy(mesh: o3d.geometry.TriangleMesh) -> o3d.geometry.TriangleMesh:
    mesh.compute_vertex_normals()
    return mesh


def make_plane(point: Sequence[float], normal: Sequence[float] = (0.0, 0.0, -1.0), size_m: float = 0.8,
               albedo: AlbedoFn | None = None, name: str = "plane") -> SceneObject:
    """A square plane through ``point`` with ``normal`` (two triangles, ``size_m`` wide)."""
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    helper = np.array([0.0, 1.0, 0.0]) if abs(n[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    a = np.cross(n, helper)
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    p = np.asarray(point, dtype=np.float64)
    h = size_m / 2.0
    verts = np.array([p - h * a - h * b, p + h * a - h * b, p + h * a + h * b, p - h * a + h * b])
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts),
                                     o3d.utility.Vector3iVector(np.array([[0, 1, 2], [0, 2, 3]])))
    return SceneObject(name, _legacy(mesh), albedo or mottled_albedo((0.78, 0.80, 0.82), 0.08, seed=1), 0.15,
                       {"point": p, "normal": n})


def make_sphere(center: Sequence[float], radius_m: float = 0.06, resolution: int = 120,
                albedo: AlbedoFn | None = None, name: str = "sphere") -> SceneObject:
    """A sphere (open3d UV sphere, ``resolution`` segments: ~3 mm edges for a 6 cm radius at 120)."""
    if radius_m <= 0:
        raise SceneError(f"sphere radius must be positive, got {radius_m}")
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=radius_m, resolution=resolution)
    mesh.translate(np.asarray(center, dtype=np.float64))
    return SceneObject(name, _legacy(mesh), albedo or mottled_albedo((0.70, 0.74, 0.80), 0.10, seed=2), 0.6,
                       {"center": np.asarray(center, dtype=np.float64), "radius_m": radius_m})


def _box_square_wave(x: AnyArray, width: AnyArray) -> AnyArray:
    """sign(sin(pi x)) averaged over [x - w/2, x + w/2] (period 2): the pixel integral of a stripe pattern."""
    def tri(z: AnyArray) -> AnyArray:  # antiderivative of the unit square wave: a triangle wave
        m = np.mod(z, 2.0)
        return np.where(m < 1.0, m, 2.0 - m)

    w = np.maximum(width, 1e-9)
    return (tri(x + w / 2) - tri(x - w / 2)) / w


def board_albedo(origin: AnyArray, axis_x: AnyArray, axis_y: AnyArray, square_m: float,
                 squares: tuple[int, int], dark: float = 0.06, light: float = 0.85) -> AlbedoFn:
    """Checkerboard of ``squares`` (cols, rows) starting at the board's first square, white margin around."""
    cols, rows = squares

    def albedo(points: AnyArray, du: AnyArray, dv: AnyArray) -> AnyArray:
        rel = points - origin
        x, y = rel @ axis_x / square_m, rel @ axis_y / square_m
        # pixel footprint along the board axes (in squares): box filter widths
        wx = (np.abs(du @ axis_x) + np.abs(dv @ axis_x)) / square_m
        wy = (np.abs(du @ axis_y) + np.abs(dv @ axis_y)) / square_m
        # -1 dark, +1 light, first square dark; the product of 1D box filters is exact for an
        # axis-aligned footprint and close enough for the tilted ones of a calibration set
        pattern = -_box_square_wave(x, wx) * _box_square_wave(y, wy)
        inside = (x > 0) & (x < cols) & (y > 0) & (y < rows)
        value = np.where(inside, 0.5 * (light + dark) + 0.5 * (light - dark) * pattern, light)
        return np.repeat(value[:, None], 3, axis=1)

    return albedo


def make_board(pose_R: AnyArray, pose_t: Sequence[float] | AnyArray, inner_corners: tuple[int, int] = (9, 6),
               square_m: float = 0.025, margin_squares: float = 1.0, name: str = "board") -> SceneObject:
    """A flat calibration chessboard; corners (board frame) at (i*s, j*s, 0), i < cols, j < rows.

    The board frame maps to the left frame by ``X = pose_R @ X_board + pose_t``; ``pose_t`` is the
    first inner corner. ``extra["object_points"]`` / ``extra["corners_m"]`` hold the corners in
    board / left frame, in OpenCV's findChessboardCorners order (row-major).
    """
    cols, rows = inner_corners
    R = np.asarray(pose_R, dtype=np.float64).reshape(3, 3)
    t = np.asarray(pose_t, dtype=np.float64).reshape(3)
    ax, ay = R[:, 0], R[:, 1]
    first_square = t - square_m * (ax + ay)  # corner of the first square
    lo = -margin_squares - 1.0
    hi_x, hi_y = cols + margin_squares, rows + margin_squares
    corners = np.array([[lo, lo], [hi_x, lo], [hi_x, hi_y], [lo, hi_y]]) * square_m
    verts = t + corners[:, :1] * ax + corners[:, 1:] * ay
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts),
                                     o3d.utility.Vector3iVector(np.array([[0, 2, 1], [0, 3, 2]])))
    j, i = np.mgrid[0:rows, 0:cols]
    obj = np.stack([i.ravel() * square_m, j.ravel() * square_m, np.zeros(i.size)], axis=1)
    return SceneObject(name, _legacy(mesh), board_albedo(first_square, ax, ay, square_m, (cols + 1, rows + 1)), 0.05,
                       {"object_points": obj, "corners_m": obj @ R.T + t, "pose_R": R, "pose_t": t})


def load_mesh_file(path: os.PathLike | str, center: Sequence[float] | None = None, scale: float = 1.0,
                   albedo: AlbedoFn | None = None) -> SceneObject:
    """A PLY/OBJ/STL mesh (metres), optionally scaled and moved so its bounding-box centre is ``center``."""
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{path}: mesh file not found")
    mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.triangles) == 0:
        raise SceneError(f"{path}: no triangles read (not a PLY/OBJ/STL mesh, or empty)")
    mesh.scale(scale, center=np.zeros(3))
    if center is not None:
        mesh.translate(np.asarray(center, dtype=np.float64) - mesh.get_axis_aligned_bounding_box().get_center())
    return SceneObject(path.stem, _legacy(mesh), albedo or mottled_albedo((0.65, 0.70, 0.78), 0.1, seed=3), 0.3)

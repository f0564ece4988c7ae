"""Texture, mesh files and shaded renders from novel views (thesis ch. 8.3), headless.

- Texture: each vertex takes the colour of its left-image pixel in the laser-off colour pair (the
  cloud's ``rgb`` field, filled by the stereo_matcher), as the thesis did.
- Files: binary PLY with vertex colours and OBJ, written by open3d.
- Renders: a virtual pinhole camera looks at the mesh from a novel direction; open3d's
  ``RaycastingScene`` finds the visible triangle of every pixel, and numpy shades it
  (ambient + Lambert + Blinn-Phong highlight from a key light, smooth normals interpolated with the
  hit's barycentric coordinates) with the interpolated vertex colour. No display or GPU needed.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from lsu_common.arrays import AnyArray

if TYPE_CHECKING:  # open3d is imported where it is used: its import (~0.8 s CPU with its plotting packages) would
    import open3d as o3d  # otherwise be paid by every start of the face processor, which needs it once a cloud arrives

from .mesh import FaceMesh, vertex_normals

__all__ = ["TextureError", "Lighting", "unpack_rgb", "to_open3d", "write_mesh", "render_view", "render_views",
           "VIEWS"]

VIEWS: dict[str, float] = {"front": 0.0, "side": 60.0}   # yaw of the virtual camera about the face [deg]


class TextureError(ValueError):
    """A mesh cannot be written or rendered (bad path, empty mesh, bad view); the message says why."""


@dataclass(frozen=True)
class Lighting:
    """Shading model of the renders: ambient + Lambert + Blinn-Phong, one key light at the camera's upper left."""

    ambient: float = 0.30
    diffuse: float = 0.75
    specular: float = 0.25
    shininess: float = 30.0
    light_dir_cam: Sequence[float] = (-0.4, -0.6, -1.0)   # towards the light, camera frame (x right, y down, z fwd)
    background_bgr: Sequence[int] = (40, 32, 28)


def unpack_rgb(packed: AnyArray) -> AnyArray:
    """Packed PCL/RViz float32 ``rgb`` (bits 0x00RRGGBB) -> (N, 3) uint8 R, G, B."""
    bits = np.ascontiguousarray(packed, dtype=np.float32).view(np.uint32)
    return np.stack([(bits >> 16) & 0xFF, (bits >> 8) & 0xFF, bits & 0xFF], axis=1).astype(np.uint8)


def to_open3d(mesh: FaceMesh) -> o3d.geometry.TriangleMesh:
    """The mesh as an open3d TriangleMesh with vertex normals and (if any) vertex colours in [0, 1]."""
    import open3d as o3d

    out = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices),
                                    o3d.utility.Vector3iVector(mesh.triangles.astype(np.int32)))
    out.vertex_normals = o3d.utility.Vector3dVector(vertex_normals(mesh.vertices, mesh.triangles))
    if mesh.colors is not None:
        out.vertex_colors = o3d.utility.Vector3dVector(mesh.colors.astype(np.float64) / 255.0)
    return out


def write_mesh(mesh: FaceMesh, path: str | Path) -> Path:
    """Write ``mesh`` as binary PLY (``.ply``, vertex colours + normals) or OBJ (``.obj``); returns the path."""
    import open3d as o3d

    path = Path(path)
    if mesh.n_triangles == 0:
        raise TextureError(f"cannot write {path}: the mesh has no triangles")
    if path.suffix.lower() not in (".ply", ".obj"):
        raise TextureError(f"cannot write {path}: use a .ply or .obj file name")
    path.parent.mkdir(parents=True, exist_ok=True)
    ok = o3d.io.write_triangle_mesh(str(path), to_open3d(mesh.compact()), write_ascii=False, compressed=False,
                                    write_vertex_normals=True, write_vertex_colors=mesh.colors is not None,
                                    print_progress=False)
    if not ok:
        raise TextureError(f"open3d could not write {path} (is the folder writable?)")
    return path


def _look_at(target: AnyArray, eye: AnyArray, up_hint: AnyArray) -> AnyArray:
    """Rows x, y, z of a camera at ``eye`` looking at ``target`` (y down, as in the optical frame)."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(-up_hint, z)  # optical y is down, so 'up' is -y
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(np.array([1.0, 0.0, 0.0]), z)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def render_view(mesh: FaceMesh, yaw_deg: float = 0.0, pitch_deg: float = 0.0, size_px: int = 480,
                lighting: Lighting = Lighting(), use_colors: bool = True, fov_deg: float = 30.0) -> AnyArray:
    """A shaded BGR uint8 image of ``mesh`` seen from a camera orbiting the mesh centre.

    ``yaw_deg = pitch_deg = 0`` looks along the scanner's left optical axis; ``yaw_deg`` turns the
    virtual camera about the vertical axis through the mesh centre (positive: from the subject's
    left as the scanner sees it, i.e. from +x), ``pitch_deg`` from above (positive).
    """
    import open3d as o3d

    if mesh.n_triangles == 0:
        raise TextureError("cannot render a mesh without triangles")
    if size_px < 16:
        raise TextureError(f"render size must be at least 16 px (got {size_px})")
    m = mesh.compact()
    v = m.vertices
    centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
    radius = float(np.linalg.norm(v - centre, axis=1).max())
    distance = radius / np.tan(np.radians(fov_deg) / 2.0) * 1.05
    yaw, pitch = np.radians(yaw_deg), np.radians(pitch_deg)
    # orbit in the left optical frame: the scanner looks along +z, so the default eye is on -z of the centre
    offset = np.array([np.sin(yaw) * np.cos(pitch), -np.sin(pitch), -np.cos(yaw) * np.cos(pitch)]) * distance
    eye = centre + offset
    R = _look_at(centre, eye, np.array([0.0, -1.0, 0.0]))
    f = 0.5 * size_px / np.tan(np.radians(fov_deg) / 2.0)
    c = (size_px - 1) / 2.0
    u, w = np.meshgrid(np.arange(size_px, dtype=np.float64), np.arange(size_px, dtype=np.float64))
    rays_cam = np.stack([(u - c) / f, (w - c) / f, np.ones_like(u)], axis=-1).reshape(-1, 3)
    rays_cam /= np.linalg.norm(rays_cam, axis=1, keepdims=True)
    dirs = rays_cam @ R
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(m.triangles.astype(np.uint32)))
    rays = np.concatenate([np.broadcast_to(eye, dirs.shape), dirs], axis=1).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    t = hit["t_hit"].numpy()
    ok = np.isfinite(t)
    prim = hit["primitive_ids"].numpy()[ok].astype(np.int64)
    bary = hit["primitive_uvs"].numpy()[ok].astype(np.float64)
    tri = m.triangles[prim]
    w0 = 1.0 - bary[:, 0] - bary[:, 1]
    vn = vertex_normals(v, m.triangles)
    n = w0[:, None] * vn[tri[:, 0]] + bary[:, :1] * vn[tri[:, 1]] + bary[:, 1:] * vn[tri[:, 2]]
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    d = dirs[ok]
    n[np.einsum("ij,ij->i", n, d) > 0] *= -1.0   # two-sided: light the side the camera sees
    light = np.asarray(lighting.light_dir_cam, dtype=np.float64) @ R
    light /= np.linalg.norm(light)
    lambert = np.clip(n @ light, 0.0, None)
    half = light - d
    half /= np.maximum(np.linalg.norm(half, axis=1, keepdims=True), 1e-12)
    spec = lighting.specular * np.clip(np.einsum("ij,ij->i", n, half), 0.0, None) ** lighting.shininess
    if use_colors and m.colors is not None:
        col = m.colors.astype(np.float64) / 255.0
        albedo = w0[:, None] * col[tri[:, 0]] + bary[:, :1] * col[tri[:, 1]] + bary[:, 1:] * col[tri[:, 2]]
        albedo = albedo[:, ::-1]   # RGB -> BGR for OpenCV
    else:
        albedo = np.full((len(n), 3), 0.82)
    shade = albedo * (lighting.ambient + lighting.diffuse * lambert)[:, None] + spec[:, None]
    img = np.empty((size_px * size_px, 3), np.uint8)
    img[:] = np.asarray(lighting.background_bgr, dtype=np.uint8)
    img[ok] = np.clip(np.rint(shade * 255.0), 0, 255).astype(np.uint8)
    return img.reshape(size_px, size_px, 3)


def render_views(mesh: FaceMesh, folder: str | Path, size_px: int = 480, prefix: str = "render",
                 views: dict[str, float] | None = None, lighting: Lighting = Lighting()) -> dict[str, Path]:
    """Write ``{prefix}_{view}.png`` (textured) and ``{prefix}_{view}_shaded.png`` (grey, lit) for each view."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out: dict[str, Path] = {}
    for name, yaw in (views or VIEWS).items():
        for textured in ((True, False) if mesh.colors is not None else (False,)):
            img = render_view(mesh, yaw_deg=yaw, size_px=size_px, lighting=lighting, use_colors=textured)
            key = name if textured else f"{name}_shaded"
            path = folder / f"{prefix}_{key}.png"
            if not cv2.imwrite(str(path), img):
                raise TextureError(f"OpenCV could not write {path} (is the folder writable?)")
            out[key] = path
    return out

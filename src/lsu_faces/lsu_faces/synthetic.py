"""A fast, faithful stand-in for a full simulated scan: the points the scanner would see, by ray casting.

A real simulated scan renders both images for every carriage position, extracts the laser lines and
matches them (~40 ms per snap, several seconds per scan). For benchmarks over hundreds of heads this
module computes the same points directly from the rig's geometry (``lsu_sim``): every pixel
ray of the left camera is cast once into the scene (open3d), and for every carriage position the
laser sheet ``n . X = c`` is intersected with each image row by linear interpolation between adjacent
pixel hits on the same surface (what the extractor does at sub-pixel level). A sample is kept only
when the scanner could really measure it: lit by the laser (no shadow from the laser origin) and seen
by the right camera (inside its image, not occluded). Sensor noise is added along the left camera ray
(the direction triangulation noise takes) and a fraction of points is dropped.

This is test and benchmark support (it imports the simulated rig); the product never uses it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from lsu_common.arrays import AnyArray

__all__ = ["ScanSample", "fast_scan", "left_pixel_rays"]

_RAYS: dict[bytes, AnyArray] = {}


def left_pixel_rays(camera) -> AnyArray:  # noqa: ANN001 - lsu_sim.CameraModel
    """Unit rays (H*W, 3) through every pixel centre of ``camera`` (cached per camera model)."""
    key = b"".join(np.ascontiguousarray(a, dtype=np.float64).tobytes() for a in (camera.K, camera.D, camera.R, camera.t))
    if key not in _RAYS:
        u, v = np.meshgrid(np.arange(camera.width, dtype=np.float64), np.arange(camera.height, dtype=np.float64))
        _RAYS.clear()
        _RAYS[key] = camera.pixel_rays(np.stack([u.ravel(), v.ravel()], axis=1))
    return _RAYS[key]


@dataclass
class ScanSample:
    """A synthetic scan cloud: the LSU PointCloud2 columns and the exact, noise-free points."""

    columns: dict[str, AnyArray]      # x y z rgb u v snap (the /lsu/scan/cloud layout)
    true_xyz: AnyArray                # (N, 3) before noise

    def __len__(self) -> int:
        return int(len(self.true_xyz))


def _cast(scene: o3d.t.geometry.RaycastingScene, origins: AnyArray, dirs: AnyArray) -> dict[str, AnyArray]:
    rays = np.concatenate([np.broadcast_to(origins, dirs.shape), dirs], axis=1).astype(np.float32)
    return {k: v.numpy() for k, v in scene.cast_rays(o3d.core.Tensor(rays)).items()}


def _visible_from(scene: o3d.t.geometry.RaycastingScene, origins: AnyArray, points: AnyArray) -> AnyArray:
    to = points - origins
    dist = np.linalg.norm(to, axis=1)
    t = _cast(scene, origins, to / dist[:, None])["t_hit"].astype(np.float64)
    return t >= dist * (1.0 - 1e-4) - 1e-4


def fast_scan(objects: Sequence, geometry, positions_steps: Sequence[float], noise_m: float = 5e-5,  # noqa: ANN001
              drop_fraction: float = 0.0, seed: int = 0, ambient: float | None = None) -> ScanSample:
    """Points a stop-snap scan of ``objects`` (``lsu_sim.SceneObject``) would give.

    Args:
        objects: scene objects (meshes in the left optical frame, with albedo functions).
        geometry: the rig (``lsu_sim.RigGeometry``): cameras, laser track and sheet.
        positions_steps: carriage positions of the snaps.
        noise_m: sigma of the Gaussian noise along the left camera ray [m].
        drop_fraction: fraction of points removed at random (missed laser rows).
        seed: seeds the noise and the dropping.
    """
    rng = np.random.default_rng(seed)
    cam = geometry.left
    W, H = cam.width, cam.height
    dirs = left_pixel_rays(cam)
    origin = cam.center
    scene = o3d.t.geometry.RaycastingScene()
    for obj in objects:
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(obj.mesh))
    cast = _cast(scene, origin, dirs)
    t = cast["t_hit"].astype(np.float64)
    hit = np.isfinite(t)
    gid = np.where(hit, cast["geometry_ids"].astype(np.int64), -1).reshape(H, W)
    P = (origin + dirs * np.where(hit, t, 0.0)[:, None]).reshape(H, W, 3)
    normals = cast["primitive_normals"].astype(np.float64).reshape(H, W, 3)
    n = geometry.laser_normal
    pn = (P @ n).reshape(H, W)
    pos = np.asarray(positions_steps, dtype=np.float64)
    c = np.array([n.dot(geometry.laser_origin(p)) for p in pos])
    # adjacent pixel pairs of a row on the same surface (no depth jump between them)
    same = (gid[:, :-1] >= 0) & (gid[:, :-1] == gid[:, 1:])
    depth = t.reshape(H, W)
    same &= np.linalg.norm(P[:, 1:] - P[:, :-1], axis=2) < 0.05 * depth[:, :-1]
    rows, cols = np.nonzero(same)
    a, b = pn[rows, cols], pn[rows, cols + 1]
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    order = np.argsort(c)
    cs = c[order]
    first = np.searchsorted(cs, lo, side="left")
    last = np.searchsorted(cs, hi, side="left")   # sheets with lo <= c < hi cross this pixel pair
    count = last - first
    pair = np.repeat(np.arange(len(rows)), count)
    k_sorted = first[pair] + (np.arange(len(pair)) - np.repeat(np.cumsum(count) - count, count))
    k = order[k_sorted]
    r, j = rows[pair], cols[pair]
    s = (c[k] - pn[r, j]) / (pn[r, j + 1] - pn[r, j])
    X = P[r, j] + s[:, None] * (P[r, j + 1] - P[r, j])
    u = j + s
    v = r.astype(np.float64)
    g = gid[r, j]
    nrm = normals[r, j]
    # measurable only when the laser reaches the point and the right camera sees it
    laser_origins = np.stack([geometry.laser_origin(p) for p in pos])[k]
    ok = _visible_from(scene, laser_origins, X) if len(X) else np.zeros(0, bool)
    right = geometry.right
    if len(X):
        px = right.project(X)
        ok &= (px[:, 0] >= 0) & (px[:, 0] <= W - 1) & (px[:, 1] >= 0) & (px[:, 1] <= H - 1)
        ok &= _visible_from(scene, np.broadcast_to(right.center, X.shape), X)
    X, u, v, k, g, nrm = X[ok], u[ok], v[ok], k[ok], g[ok], nrm[ok]
    if drop_fraction > 0 and len(X):
        keep = rng.random(len(X)) >= drop_fraction
        X, u, v, k, g, nrm = X[keep], u[keep], v[keep], k[keep], g[keep], nrm[keep]
    ray = X - origin
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    noisy = X + ray * (noise_m * rng.standard_normal(len(X)))[:, None]
    # texture as the laser-off pair sees it: albedo under the rig's room light
    light = geometry.lighting
    bgr = np.zeros((len(X), 3))
    zeros = np.zeros((len(X), 3))
    for gi, obj in enumerate(objects):
        sel = g == gi
        if np.any(sel):
            bgr[sel] = obj.albedo(X[sel], zeros[sel], zeros[sel])
    to_lamp = light.key_light_m - X
    to_lamp /= np.maximum(np.linalg.norm(to_lamp, axis=1, keepdims=True), 1e-12)
    diffuse = np.abs(np.einsum("ij,ij->i", nrm, to_lamp))
    amb = light.ambient if ambient is None else ambient
    radiance = np.clip(bgr * (amb + light.key * diffuse)[:, None], 0.0, 1.0)
    rgb8 = np.rint(radiance[:, ::-1] * 255.0).astype(np.uint32)
    packed = ((rgb8[:, 0] << 16) | (rgb8[:, 1] << 8) | rgb8[:, 2]).astype("<u4").view("<f4")
    order = np.lexsort((v, k))
    cols_out = {"x": noisy[order, 0], "y": noisy[order, 1], "z": noisy[order, 2], "rgb": packed[order],
                "u": u[order], "v": v[order], "snap": k[order].astype(np.uint32)}
    return ScanSample(cols_out, X[order])

"""A consumer time-of-flight depth camera (Kinect v2 class): what it really delivers of a face at 0.8-0.9 m.

The figures and their sources are in docs/FACES.md ("The time-of-flight camera model"). In order:

1. geometry: a 512 x 424 pinhole (70.6 x 60 deg field of view: fx = fy = 365 px), rays cast into the
   scene (open3d); each pixel's true depth, surface normal and part;
2. multipath: light reaching a pixel by way of a neighbouring surface travels farther, so concave
   places (eye sockets, the nose-cheek fold, the mouth corners) read deeper. The bias is
   ``multipath_gain`` x how far the pixel lies behind the smooth surface around it (a Gaussian of
   ``multipath_sigma_px``), capped at ``multipath_max_m``;
3. the camera's own smoothing: the depth is averaged over a ``smooth_sigma_px`` Gaussian of the
   neighbours on the same surface (edge-aware: neighbours beyond ``edge_jump_m`` do not count), which
   also blurs the nose's ridge and the lips;
4. random noise: Gaussian, sigma ``noise_at_1m_m`` x (depth / 1 m)^2 + ``noise_floor_m``, growing
   with 1/sqrt(cos) of the incidence angle (less light back from a slanted surface), applied after the
   smoothing (what is left of it: the smoothing already removed part of the raw noise);
5. flying pixels: a pixel across a depth edge mixes the near and far surface's light and returns
   a depth anywhere between them (with ``flying_fraction`` of the edge pixels kept; the rest are
   dropped by the camera's own filter);
6. holes: surfaces seen at grazing angles (cos < ``min_cos``), dark hair (``hair_dropout``), and a
   small random share (``dropout``);
7. quantisation: depth in steps of ``depth_step_m`` (4 mm on the face at 0.8-0.9 m in the real maps).

Output frame: the camera's optical frame (x right, y down, z forward, metres), the frame ``lsu face``
takes; ``u``, ``v`` are the pixel coordinates. Deterministic for a seed.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from scipy import ndimage

from lsu_common.arrays import AnyArray

__all__ = ["TofCamera", "tof_scan"]


@dataclass(frozen=True)
class TofCamera:
    """Intrinsics and error model (defaults: Kinect v2 class at a face 0.8-0.9 m away; docs/FACES.md)."""

    width: int = 512
    height: int = 424
    fx: float = 365.0
    fy: float = 365.0
    noise_at_1m_m: float = 0.004       # random depth noise grows with the square of the distance
    noise_floor_m: float = 0.0005
    smooth_sigma_px: float = 1.0       # the camera's own (edge-aware) smoothing
    wiggle_m: float = 0.0015           # systematic error periodic in the distance ("wiggling")
    wiggle_period_m: float = 0.25
    multipath_gain: float = 0.35
    multipath_sigma_px: float = 6.0
    multipath_max_m: float = 0.006
    edge_jump_m: float = 0.02          # neighbours farther apart than this lie across a depth edge
    flying_fraction: float = 0.5       # share of the edge pixels returned with a mixed (flying) depth
    min_cos: float = 0.15              # grazing surfaces return too little light: holes
    hair_dropout: float = 0.5
    dropout: float = 0.01
    depth_step_m: float = 0.004
    max_range_m: float = 4.5


def _cast(objects: Sequence, T: AnyArray, cam: TofCamera) -> tuple[AnyArray, AnyArray, AnyArray, AnyArray, list[str]]:  # noqa: ANN001
    scene = o3d.t.geometry.RaycastingScene()
    names = []
    for obj in objects:
        m = o3d.geometry.TriangleMesh(obj.mesh)
        m.transform(T)
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(m))
        names.append(obj.name)
    u, v = np.meshgrid(np.arange(cam.width, dtype=np.float64), np.arange(cam.height, dtype=np.float64))
    d = np.stack([(u - (cam.width - 1) / 2) / cam.fx, (v - (cam.height - 1) / 2) / cam.fy, np.ones_like(u)], -1)
    rays = np.concatenate([np.zeros((d.size // 3, 3)), d.reshape(-1, 3)], axis=1).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    t = hit["t_hit"].numpy().astype(np.float64).reshape(cam.height, cam.width)   # d has z = 1: t is the depth
    gid = hit["geometry_ids"].numpy().astype(np.int64).reshape(cam.height, cam.width)
    nrm = hit["primitive_normals"].numpy().astype(np.float64).reshape(cam.height, cam.width, 3)
    ok = np.isfinite(t) & (t < cam.max_range_m)
    return d, np.where(ok, t, np.nan), np.where(ok, gid, -1), nrm, names


def _masked_gauss(z: AnyArray, valid: AnyArray, sigma: float) -> AnyArray:
    w = ndimage.gaussian_filter(valid.astype(np.float64), sigma, mode="constant")
    s = ndimage.gaussian_filter(np.where(valid, z, 0.0), sigma, mode="constant")
    return np.where(valid & (w > 1e-6), s / np.maximum(w, 1e-6), np.nan)


def tof_scan(objects: Sequence, camera_from_scene: AnyArray, cam: TofCamera = TofCamera(),  # noqa: ANN001
             seed: int = 0, truth: bool = False) -> dict[str, AnyArray]:
    """Cloud columns (x y z u v) the time-of-flight camera gives of ``objects`` (``SceneObject``, scene frame).

    ``camera_from_scene``: 4x4 transform of scene points into the camera's optical frame. With
    ``truth``, also ``true_z`` (the surface's depth at each returned pixel, NaN for a flying pixel) and
    ``flying`` (bool) per point.
    """
    rng = np.random.default_rng(seed)
    d, z, gid, nrm, names = _cast(objects, np.asarray(camera_from_scene, dtype=np.float64), cam)
    H, W = z.shape
    valid = np.isfinite(z)
    # depth edges: a neighbour farther than edge_jump_m (or missing) on any side
    pad = np.pad(z, 1, constant_values=np.nan)
    edge = np.zeros_like(valid)
    far_side = np.full(z.shape, np.nan)
    for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
        nb = pad[dy:dy + H, dx:dx + W]
        jump = ~np.isfinite(nb) | (np.abs(nb - z) > cam.edge_jump_m)
        edge |= valid & jump
        deeper = np.isfinite(nb) & (nb - z > cam.edge_jump_m)
        far_side = np.where(deeper & ~np.isfinite(far_side), nb, far_side)
    # 2. multipath: concave places read deeper
    smooth_large = _masked_gauss(z, valid & ~edge, cam.multipath_sigma_px)
    behind = np.clip(np.nan_to_num(z - smooth_large), 0.0, None)
    measured = z + np.minimum(cam.multipath_gain * behind, cam.multipath_max_m)
    # 2b. the systematic error periodic in the distance: a smooth warp of the face that changes with its distance
    measured = measured + cam.wiggle_m * np.sin(2 * np.pi * np.nan_to_num(z) / cam.wiggle_period_m)
    # 3. the camera's edge-aware smoothing (neighbours across an edge are excluded by masking them out)
    inner = valid & ~edge
    measured = np.where(inner, _masked_gauss(measured, inner, cam.smooth_sigma_px), measured)
    # 4. random noise, more on slanted surfaces
    rays = d / np.linalg.norm(d, axis=2, keepdims=True)
    cos = np.abs(np.einsum("hwi,hwi->hw", nrm, rays))
    sigma = (cam.noise_at_1m_m * np.nan_to_num(z) ** 2 + cam.noise_floor_m) / np.sqrt(np.maximum(cos, cam.min_cos))
    measured = measured + sigma * rng.standard_normal(z.shape)
    # 5. flying pixels: at an edge with a deeper neighbour, a mix of the two depths; other edge pixels dropped
    flying = edge & np.isfinite(far_side) & (rng.random(z.shape) < cam.flying_fraction)
    mix = rng.random(z.shape)
    measured = np.where(flying, z + mix * (far_side - z), measured)
    keep = valid & (~edge | flying)
    # 6. holes: grazing surfaces, dark hair, random dropouts
    keep &= (cos >= cam.min_cos) | flying
    hair = np.isin(gid, [k for k, n in enumerate(names) if n.endswith("hair")])
    keep &= ~(hair & (rng.random(z.shape) < cam.hair_dropout))
    keep &= rng.random(z.shape) >= cam.dropout
    # 7. quantisation
    depth = np.round(measured / cam.depth_step_m) * cam.depth_step_m
    idx = np.flatnonzero(keep.ravel())
    xyz = d.reshape(-1, 3)[idx] * depth.ravel()[idx, None]
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    out = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "u": u.ravel()[idx], "v": v.ravel()[idx]}
    if truth:
        out["true_z"] = np.where(flying.ravel()[idx], np.nan, z.ravel()[idx])
        out["flying"] = flying.ravel()[idx]
    return out

"""A coarse consumer depth camera (structured light / stereo IR class), for exercising face code on what it delivers.

Model (defaults after a Kinect-v1-class sensor at arm's length): a 640 x 480 pinhole camera with
fx = fy = 570 px at about 850 mm from the face; depth = range along the optical axis, rounded to
``depth_step_m`` (4 mm) after Gaussian noise of ``noise_m``; pixels whose neighbours jump by more
than ``edge_jump_m`` are dropped (mixed pixels at silhouettes come back as holes), and so are points
the projector (``baseline_m`` to the side) does not light: the shadow band beside every silhouette.
Dark, rough hair returns only part of its pixels (``hair_dropout``).

Output frame: the depth camera's optical frame (x right, y down, z forward, metres), which is the
frame a user hands to ``lsu face``; ``u``, ``v`` are its pixel coordinates.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from lsu_common.arrays import AnyArray

__all__ = ["DepthCamera", "depth_scan"]


@dataclass(frozen=True)
class DepthCamera:
    """Intrinsics and error model of the coarse depth camera."""

    width: int = 640
    height: int = 480
    fx: float = 570.0
    fy: float = 570.0
    depth_step_m: float = 0.004
    noise_m: float = 0.0015
    edge_jump_m: float = 0.02
    baseline_m: float = 0.075          # projector to the camera's left (-x)
    hair_dropout: float = 0.4
    max_range_m: float = 3.5


def depth_scan(objects: Sequence, camera_from_scene: AnyArray, cam: DepthCamera = DepthCamera(),  # noqa: ANN001
               seed: int = 0) -> dict[str, AnyArray]:
    """Cloud columns (x y z u v) the depth camera gives of ``objects`` (``SceneObject``, scene frame).

    ``camera_from_scene`` is the 4x4 transform of scene points into the depth camera's optical frame.
    """
    rng = np.random.default_rng(seed)
    T = np.asarray(camera_from_scene, dtype=np.float64)
    scene = o3d.t.geometry.RaycastingScene()
    hair_ids = []
    for k, obj in enumerate(objects):
        m = o3d.geometry.TriangleMesh(obj.mesh)
        m.transform(T)
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(m))
        if obj.name.endswith("hair"):
            hair_ids.append(k)
    u, v = np.meshgrid(np.arange(cam.width, dtype=np.float64), np.arange(cam.height, dtype=np.float64))
    d = np.stack([(u - (cam.width - 1) / 2) / cam.fx, (v - (cam.height - 1) / 2) / cam.fy, np.ones_like(u)], -1)
    d = d.reshape(-1, 3)
    rays = np.concatenate([np.zeros_like(d), d], axis=1).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    t = hit["t_hit"].numpy().astype(np.float64)        # along d, whose z is 1: t is the depth
    gid = hit["geometry_ids"].numpy().astype(np.int64)
    ok = np.isfinite(t) & (t < cam.max_range_m)
    z = np.where(ok, t, np.nan).reshape(cam.height, cam.width)
    # silhouettes: a pixel next to a depth jump is a mixed pixel, returned as a hole
    pad = np.pad(z, 1, constant_values=np.nan)
    jump = np.zeros_like(z, dtype=bool)
    for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
        nb = pad[dy:dy + cam.height, dx:dx + cam.width]
        jump |= ~np.isfinite(nb) | (np.abs(nb - z) > cam.edge_jump_m)
    valid = np.isfinite(z) & ~jump
    P = d * np.where(ok, t, 0.0)[:, None]
    # projector shadow: the point must be visible from the projector
    proj = np.array([-cam.baseline_m, 0.0, 0.0])
    idx = np.flatnonzero(valid.ravel())
    to = P[idx] - proj
    dist = np.linalg.norm(to, axis=1)
    r2 = np.concatenate([np.broadcast_to(proj, to.shape), to / dist[:, None]], axis=1).astype(np.float32)
    t2 = scene.cast_rays(o3d.core.Tensor(r2))["t_hit"].numpy().astype(np.float64)
    lit = t2 >= dist - 0.003
    idx = idx[lit]
    if hair_ids:
        on_hair = np.isin(gid[idx], hair_ids)
        idx = idx[~(on_hair & (rng.random(len(idx)) < cam.hair_dropout))]
    depth = P[idx, 2] + cam.noise_m * rng.standard_normal(len(idx))
    depth = np.round(depth / cam.depth_step_m) * cam.depth_step_m
    xyz = d[idx] * depth[:, None]
    return {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "u": u.ravel()[idx], "v": v.ravel()[idx]}

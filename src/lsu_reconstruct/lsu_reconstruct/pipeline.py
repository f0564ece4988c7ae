"""One snap from two laser lines to 3D points, and a scan as the union of its snaps (no rclpy).

``reconstruct_snap`` is what the ``stereo_matcher`` node and ``lsu reconstruct`` both run:
match (sub-pixel epipolar intersection, or the thesis chain), triangulate, reject (non-finite,
depth range, reprojection error). ``colour_at`` samples the laser-off texture image at the left
pixels of the points.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lsu_bags.pointcloud2 import pack_rgb
from lsu_common.arrays import AnyArray

from .matching import LineArrays, MatchParams, match_line, match_thesis
from .stereo import StereoModel
from .triangulate import accept_points, midpoint_of_rays, triangulate

__all__ = ["SnapPoints", "reconstruct_snap", "colour_at", "merge_snaps", "drop_grazing", "MAX_VIEW_ANGLE_DEG"]

# A surface seen flatter than this by either camera (angle between its normal and the line of sight) gives
# biased points: near a silhouette the line is foreshortened to a pixel or two and partly hidden, so its
# centre is off by a pixel or more (millimetres in depth) while both views still agree with each other.
MAX_VIEW_ANGLE_DEG = 75.0
NORMAL_NEIGHBOURS = 16  # points of the cloud a normal is fitted to (a few snaps' lines around the point)
PLANAR_SPREAD = 0.05    # their second spread (eigenvalue) at least this share of the first: a surface, not a line


@dataclass
class SnapPoints:
    """Points of one snap: xyz [m, left optical frame], left raw pixel (u, v), snap index, packed rgb."""

    xyz: AnyArray                        # (N, 3) float64
    u: AnyArray                          # (N,) raw left pixel column
    v: AnyArray                          # (N,) raw left pixel row
    snap: AnyArray                       # (N,) uint32
    rgb: AnyArray | None = None       # (N,) float32 packed 0x00RRGGBB, None = not coloured
    stats: dict[str, int] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(len(self.xyz))

    def fields(self) -> dict[str, AnyArray]:
        """Columns for the PointCloud2 codec (x y z rgb u v snap)."""
        rgb = self.rgb if self.rgb is not None else pack_rgb(np.full((len(self), 3), 255, dtype=np.uint8))
        return {"x": self.xyz[:, 0], "y": self.xyz[:, 1], "z": self.xyz[:, 2], "rgb": rgb, "u": self.u,
                "v": self.v, "snap": self.snap}


def reconstruct_snap(model: StereoModel, left: LineArrays, right: LineArrays, params: MatchParams = MatchParams(),
                     snap: int = 0, chain: str = "subpixel") -> SnapPoints:
    """Match ``left`` to ``right`` and triangulate; only finite, accepted points come out.

    ``chain="thesis"`` runs the thesis baseline (integer pixels, nearest-pixel match).
    """
    for line, which in ((left, "left"), (right, "right")):
        if line.image_width or line.image_height:
            model.check_image_size(line.image_width, line.image_height, f"{which} laser line image")
    if chain == "subpixel":
        m = match_line(model, left, right, params)
    elif chain == "thesis":
        m = match_thesis(model, left, right, params)
    else:
        raise ValueError(f"unknown matching chain '{chain}'; use 'subpixel' or 'thesis'")
    if params.method == "midpoint" and m.rays is not None:
        X = midpoint_of_rays(model, m.rays)  # the matcher's depth test already found the closest approach
    else:
        X = triangulate(model, m.x1, m.x2, params.method)
    ok, rejected = accept_points(model, X, m.x1, m.x2, params.depth_min_m, params.depth_max_m, params.max_reproj_px)
    points = int(np.count_nonzero(ok))
    stats = dict(m.stats)
    stats.update(matched=int(len(X)), points=points, rejected_non_finite=rejected.non_finite,
                 rejected_depth=rejected.depth, rejected_reprojection=rejected.reprojection)
    idx = m.left_index
    if points < len(X):
        pick = ok.nonzero()[0]
        idx, X = idx[pick], X[pick]
    v = left.v[idx]
    if (v[1:] < v[:-1]).any():  # points ordered along the line, top to bottom (already so when smoothed)
        order = v.argsort(kind="stable")
        idx, X, v = idx[order], X[order], v[order]
    return SnapPoints(xyz=np.ascontiguousarray(X), u=left.u[idx], v=v, snap=np.full(len(idx), snap, dtype=np.uint32),
                      stats=stats)


def colour_at(image_bgr: AnyArray, u: AnyArray, v: AnyArray) -> AnyArray:
    """Packed rgb (float32, 0x00RRGGBB) of a bgr8 (or mono8) image at raw pixels (nearest pixel, clamped)."""
    img = np.asarray(image_bgr)
    if not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] >= 3)):
        raise ValueError(f"texture image has shape {img.shape}; expected HxWx3 bgr8 or HxW mono8")
    h, w = img.shape[:2]
    # fmax/fmin: NaN to 0 and infinities to the border, in two calls (nan_to_num + clip cost ~5x more per snap)
    col = np.fmin(np.fmax(np.rint(u), 0.0), w - 1).astype(np.intp)
    row = np.fmin(np.fmax(np.rint(v), 0.0), h - 1).astype(np.intp)
    if img.ndim == 2:  # grey: the sampled pixels as r = g = b (not the whole image made bgr)
        grey = img[row, col]
        return pack_rgb(np.stack([grey, grey, grey], axis=1))
    return pack_rgb(img[row, col, :3][:, ::-1])


def merge_snaps(snaps: list[SnapPoints]) -> SnapPoints:
    """Concatenate snaps (in the given order) into one scan cloud."""
    if not snaps:
        return SnapPoints(np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.uint32),
                          np.zeros(0, dtype=np.float32))
    rgb = [s.fields()["rgb"] for s in snaps]
    return SnapPoints(xyz=np.concatenate([s.xyz for s in snaps]), u=np.concatenate([s.u for s in snaps]),
                      v=np.concatenate([s.v for s in snaps]), snap=np.concatenate([s.snap for s in snaps]),
                      rgb=np.concatenate(rgb).astype(np.float32))


def _planar(cov: AnyArray, normals: AnyArray) -> AnyArray:
    """Per point: do its neighbours span a surface (second eigenvalue of ``cov`` >= `PLANAR_SPREAD` x the
    largest), given ``normals``, the unit eigenvectors of the smallest eigenvalue?

    Neighbours along one line only (snaps far apart, a lone line) span no surface. The smallest eigenvalue is
    n'Cn; the other two are the roots of x^2 - s x + p with s and p from the trace and the sum of the principal
    2x2 minors less that eigenvalue's share: elementwise, where numpy's batched eigh solves each 3x3 matrix
    through LAPACK, one call per matrix (over 10x the time on a scan cloud).
    """
    small = np.einsum("ni,nij,nj->n", normals, cov, normals)
    trace = cov[:, 0, 0] + cov[:, 1, 1] + cov[:, 2, 2]
    minors = (cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] ** 2 + cov[:, 0, 0] * cov[:, 2, 2] - cov[:, 0, 2] ** 2
              + cov[:, 1, 1] * cov[:, 2, 2] - cov[:, 1, 2] ** 2)
    s = trace - small
    p = minors - small * s
    root = np.sqrt(np.maximum(s * s - 4.0 * p, 0.0))
    return (s - root) >= PLANAR_SPREAD * (s + root)  # both halves of the two roots: middle >= spread x largest


def load_drop_grazing(max_view_angle_deg: float = MAX_VIEW_ANGLE_DEG) -> None:
    """Import what `drop_grazing` needs (open3d: about a third of a second of CPU, once per process), for a caller
    that times the scan's processing and would otherwise count it there (`StereoMatcherNode.prepare_scan_cloud`)."""
    if max_view_angle_deg < 90.0:
        import open3d  # noqa: F401


def drop_grazing(cloud: SnapPoints, model: StereoModel, max_view_angle_deg: float = MAX_VIEW_ANGLE_DEG) -> SnapPoints:
    """The scan cloud without the points either camera sees at more than ``max_view_angle_deg`` from the surface normal.

    The normal comes from the cloud itself (open3d's plane fit to the ``NORMAL_NEIGHBOURS`` nearest points,
    across snaps), the lines of sight from the calibration: only what the scanner measured. 90 keeps all.
    """
    if max_view_angle_deg >= 90.0 or len(cloud) < NORMAL_NEIGHBOURS:
        return cloud
    import open3d as o3d  # only the scan cloud needs it

    xyz = np.asarray(cloud.xyz, dtype=np.float64)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    pc.estimate_covariances(o3d.geometry.KDTreeSearchParamKNN(NORMAL_NEIGHBOURS))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(NORMAL_NEIGHBOURS))  # from those covariances
    normals = np.asarray(pc.normals)
    spread = _planar(np.asarray(pc.covariances), normals)
    limit = np.cos(np.radians(max_view_angle_deg))
    seen = np.ones(len(xyz), bool)
    for centre in (np.zeros(3), np.asarray(model.right_centre, dtype=np.float64).reshape(3)):
        sight = xyz - centre
        sight /= np.linalg.norm(sight, axis=1, keepdims=True)
        seen &= np.abs(np.einsum("ij,ij->i", normals, sight)) >= limit
    keep = seen | ~spread
    if keep.all():
        return cloud
    stats = {**cloud.stats, "rejected_grazing": int(len(keep) - np.count_nonzero(keep))}
    return SnapPoints(xyz=cloud.xyz[keep], u=cloud.u[keep], v=cloud.v[keep], snap=cloud.snap[keep],
                      rgb=None if cloud.rgb is None else cloud.rgb[keep], stats=stats)

"""Face signatures and their comparison (thesis ch. 10.2.4, 11.2.4, and what measures better).

Two signatures, both computed in the pose-normalising face frame (origin at the nose tip, z along the
radial vector, y from the camera's down direction), so a turned or nodding head gives the same map:

- ``depthmap`` (default): the face's height along the radial vector sampled on a regular grid
  (``grid`` x ``grid`` cells over +-``extent_m``; mean of the points in each cell, NaN where the scanner
  saw nothing, e.g. behind the nose of a turned head). Two maps are compared after a rigid alignment
  (open3d point-to-plane ICP, from the frame's own alignment), by the trimmed RMS of the height
  differences where both maps have data. The frame's residual errors (a few degrees of radial
  vector, a millimetre of nose tip) are what ICP removes.
- ``fft`` (the thesis' proposal): the spherical parametric map (elevation x azimuth, see
  `lsu_faces.face.parametric_map`) and the magnitudes of its Fourier coefficients along the azimuth,
  which do not change when the face rolls about the radial vector. Compared by the RMS difference.

A score in (0, 1] is ``exp(-distance / scale)``: 1 for identical faces.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from typing import TYPE_CHECKING, Dict, Optional, Tuple

if TYPE_CHECKING:  # open3d costs ~1 s to import: only the functions that use it load it
    import open3d as o3d

import numpy as np

from .face import FaceFrame, FaceParams, parametric_map, spherical_embedding

__all__ = ["SignatureError", "Signature", "SignatureParams", "make_signature", "compare", "score_from_distance",
           "SIGNATURE_METHODS"]

SIGNATURE_METHODS = ("depthmap", "fft")


class SignatureError(ValueError):
    """A signature cannot be made, read or compared (bad blob, different methods or grids)."""


@dataclass(frozen=True)
class SignatureParams:
    """Signature settings; stored with each signature so a gallery stays comparable."""

    method: str = "depthmap"
    grid: int = 56                 # depth map cells per side
    extent_m: float = 0.07         # depth map half width [m]
    map_rows: int = 24             # spherical map: elevation bins
    map_cols: int = 64             # spherical map: azimuth bins
    max_elevation_deg: float = 60.0
    fft_orders: int = 16           # azimuth harmonics kept
    trim: float = 0.1              # fraction of the largest height differences ignored (hair, occlusion rims)
    min_overlap: float = 0.3       # maps sharing fewer valid cells than this fraction do not match
    scale_m: float = 0.0005        # distance giving score exp(-1)

    def __post_init__(self) -> None:
        if self.method not in SIGNATURE_METHODS:
            raise SignatureError(f"signature method must be one of {', '.join(SIGNATURE_METHODS)} "
                                 f"(got '{self.method}')")
        if self.grid < 8 or self.map_rows < 4 or self.map_cols < 8:
            raise SignatureError("signature grids are too small (grid >= 8, map_rows >= 4, map_cols >= 8)")


@dataclass
class Signature:
    """A face signature: ``method``, its array and the parameters that made it."""

    method: str
    data: np.ndarray
    params: SignatureParams
    points_used: int = 0

    def to_bytes(self) -> bytes:
        """Serialise (numpy .npz in memory): what the gallery stores."""
        buf = io.BytesIO()
        fields = {k: np.array(getattr(self.params, k)) for k in SignatureParams.__dataclass_fields__}
        np.savez_compressed(buf, data=self.data.astype(np.float32), points_used=np.array(self.points_used),
                            version=np.array(1), **{f"p_{k}": v for k, v in fields.items()})
        return buf.getvalue()

    @classmethod
    def from_bytes(cls, blob: bytes) -> "Signature":
        """Inverse of `to_bytes`; raises `SignatureError` for a blob that is not a signature."""
        try:
            with np.load(io.BytesIO(blob), allow_pickle=False) as z:
                kw = {}
                for k, f in SignatureParams.__dataclass_fields__.items():
                    value = z[f"p_{k}"]
                    kw[k] = str(value) if f.type in ("str", str) else value.item()
                params = SignatureParams(**kw)
                return cls(params.method, z["data"].astype(np.float64), params, int(z["points_used"]))
        except (OSError, KeyError, ValueError, TypeError) as exc:
            raise SignatureError(f"stored signature cannot be read ({exc.__class__.__name__}: {exc})") from None


def _depth_map(local: np.ndarray, params: SignatureParams) -> np.ndarray:
    g, e = params.grid, params.extent_m
    ij = np.floor((local[:, :2] + e) / (2 * e) * g).astype(np.int64)
    ok = np.all((ij >= 0) & (ij < g), axis=1)
    flat = ij[ok, 1] * g + ij[ok, 0]              # rows = y (down), columns = x (right)
    total = np.bincount(flat, weights=local[ok, 2], minlength=g * g)
    count = np.bincount(flat, minlength=g * g)
    out = np.full(g * g, np.nan)
    out[count > 0] = total[count > 0] / count[count > 0]
    return out.reshape(g, g)


def make_signature(points: np.ndarray, frame: FaceFrame, params: SignatureParams = SignatureParams(),
                   face: FaceParams = FaceParams()) -> Signature:
    """Signature of the face ``points`` (already cropped) in ``frame``."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) < 50:
        raise SignatureError(f"{len(p)} face points are too few for a signature")
    if params.method == "depthmap":
        data = _depth_map(frame.to_local(p), params)
    else:
        el, az, rho = spherical_embedding(p, frame, face.sphere_radius_m)
        m = parametric_map(el, az, rho, face.sphere_radius_m, (params.map_rows, params.map_cols),
                           np.radians(params.max_elevation_deg))
        data = _fft_magnitudes(m, params.fft_orders)
    return Signature(params.method, data, params, int(len(p)))


def _fft_magnitudes(m: np.ndarray, orders: int) -> np.ndarray:
    """|FFT along azimuth| per elevation row; empty cells take their row's mean, empty rows are NaN."""
    filled = m.copy()
    out = np.full((m.shape[0], orders), np.nan)
    for r in range(m.shape[0]):
        row = filled[r]
        valid = np.isfinite(row)
        if valid.sum() < 0.5 * len(row):
            continue
        row[~valid] = row[valid].mean()
        out[r] = np.abs(np.fft.rfft(row))[:orders] / len(row)
    return out


def _grid_points(sig: Signature) -> Tuple[np.ndarray, np.ndarray]:
    g, e = sig.params.grid, sig.params.extent_m
    centres = (np.arange(g) + 0.5) / g * 2 * e - e
    x, y = np.meshgrid(centres, centres)
    valid = np.isfinite(sig.data)
    return np.stack([x[valid], y[valid], sig.data[valid]], axis=1), valid


def _sample(sig: Signature, xy: np.ndarray) -> np.ndarray:
    """Bilinear height of a depth map at local (x, y); NaN outside or next to a hole."""
    g, e = sig.params.grid, sig.params.extent_m
    f = (xy + e) / (2 * e) * g - 0.5
    i0 = np.floor(f).astype(np.int64)
    w = f - i0
    out = np.full(len(xy), np.nan)
    ok = np.all((i0 >= 0) & (i0 < g - 1), axis=1)
    c, r, wx, wy = i0[ok, 0], i0[ok, 1], w[ok, 0], w[ok, 1]
    d = sig.data
    out[ok] = ((1 - wx) * (1 - wy) * d[r, c] + wx * (1 - wy) * d[r, c + 1] + (1 - wx) * wy * d[r + 1, c]
               + wx * wy * d[r + 1, c + 1])
    return out


def _depthmap_distance(probe: Signature, ref: Signature, ref_cloud: Optional["o3d.geometry.PointCloud"] = None
                       ) -> Tuple[float, float]:
    import open3d as o3d

    pp, _ = _grid_points(probe)
    rp, _ = _grid_points(ref)
    if len(pp) < 20 or len(rp) < 20:
        return float("inf"), 0.0
    if ref_cloud is None:
        ref_cloud = _cloud_with_normals(rp, ref.params)
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pp))
    T = np.eye(4)
    cell = 2 * ref.params.extent_m / ref.params.grid
    est = o3d.pipelines.registration.TransformationEstimationPointToPlane()
    for dist in (4 * cell, 1.5 * cell):   # coarse then fine: the frame is already close
        reg = o3d.pipelines.registration.registration_icp(
            src, ref_cloud, dist, T, est, o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=20))
        T = reg.transformation
    moved = pp @ T[:3, :3].T + T[:3, 3]
    diff = moved[:, 2] - _sample(ref, moved[:, :2])
    diff = np.abs(diff[np.isfinite(diff)])
    overlap = len(diff) / max(len(pp), 1)
    if overlap < probe.params.min_overlap or len(diff) < 20:
        return float("inf"), overlap
    diff.sort()
    kept = diff[: max(1, int(round(len(diff) * (1.0 - probe.params.trim))))]
    return float(np.sqrt(np.mean(kept ** 2))), overlap


def _cloud_with_normals(points: np.ndarray, params: SignatureParams) -> "o3d.geometry.PointCloud":
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cell = 2 * params.extent_m / params.grid
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3 * cell, max_nn=16))
    cloud.orient_normals_towards_camera_location(np.array([0.0, 0.0, 1.0]))
    return cloud


def _fft_distance(probe: Signature, ref: Signature) -> Tuple[float, float]:
    both = np.isfinite(probe.data[:, 0]) & np.isfinite(ref.data[:, 0])
    overlap = float(both.mean())
    if overlap < probe.params.min_overlap:
        return float("inf"), overlap
    d = probe.data[both] - ref.data[both]
    return float(np.sqrt(np.mean(d ** 2))), overlap


def score_from_distance(distance_m: float, scale_m: float) -> float:
    """Similarity in [0, 1]: exp(-distance / scale); 0 for no overlap."""
    return float(np.exp(-distance_m / scale_m)) if np.isfinite(distance_m) else 0.0


def compare(probe: Signature, ref: Signature, cache: Optional[Dict[int, o3d.geometry.PointCloud]] = None
            ) -> Tuple[float, float, float]:
    """(score 0..1, distance [m], overlap fraction) of ``probe`` against ``ref``.

    ``cache`` (keyed by ``id(ref)``) keeps the reference's normal-estimated cloud between calls.
    """
    if probe.method != ref.method:
        raise SignatureError(f"cannot compare a '{probe.method}' signature with a '{ref.method}' one; "
                             f"re-enrol the gallery with one method")
    if probe.data.shape != ref.data.shape:
        raise SignatureError(f"signature grids differ ({probe.data.shape} vs {ref.data.shape}); re-enrol the gallery")
    if probe.method == "depthmap":
        cloud = None
        if cache is not None:
            cloud = cache.get(id(ref))
            if cloud is None:
                rp, _ = _grid_points(ref)
                cloud = cache[id(ref)] = _cloud_with_normals(rp, ref.params) if len(rp) >= 20 else None
        dist, overlap = _depthmap_distance(probe, ref, cloud)
    else:
        dist, overlap = _fft_distance(probe, ref)
    return score_from_distance(dist, probe.params.scale_m), dist, overlap

"""Face signatures and their comparison (thesis ch. 10.2.4, 11.2.4, and what measures better).

Two signatures, both computed in the pose-normalising face frame (origin at the nose tip, z along the
radial vector, y from the camera's down direction), so a turned or nodding head gives the same map:

- ``depthmap`` (default): the face's height along the radial vector sampled on a regular grid
  (``grid`` x ``grid`` cells over +-``extent_m``; mean of the points in each cell, NaN where the scanner
  saw nothing, e.g. behind the nose of a turned head). Two maps are compared after a rigid alignment
  (`align_to_depthmap`: deterministic point-to-plane steps, from the frame's own alignment), by the
  trimmed, region-weighted RMS of the height differences where both maps have data: the rigid parts
  of a face (nose, eye sockets, forehead) count more than the parts that move with expressions
  (mouth, chin); see ``REGION_WEIGHTS``. Missing cells (occlusion, hair, a hand) simply do not count.
  That distance is combined (geometric mean) with a region ensemble over five discs no expression
  moves (``CORE_REGIONS``: nose, wider nose, bridge, eye-socket rims).
- ``fft`` (the thesis' proposal): the spherical parametric map (elevation x azimuth, see
  `lsu_faces.frame.parametric_map`) and the magnitudes of its Fourier coefficients along the azimuth,
  which do not change when the face rolls about the radial vector. Compared by the RMS difference.

Scores are calibrated, not fixed: `ImpostorModel` is a log-normal fitted to the distances between
different people actually seen (a gallery's own entries, shrunk towards a prior measured on synthetic
people with the LSU rig), and a match's score is ``1 - P(an impostor is this close)``. The gallery's
open-set decision (`lsu_faces.gallery`) calibrates on its own searches from 50 people on.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from lsu_common.arrays import AnyArray

if TYPE_CHECKING:
    pass

from .frame import FaceFrame, FaceParams, parametric_map, spherical_embedding
from .register import rotation_from_vector

__all__ = ["SignatureError", "Signature", "SignatureParams", "make_signature", "compare",
           "SIGNATURE_METHODS", "ImpostorModel", "REGION_WEIGHTS", "SIGNATURE_VERSION", "align_to_depthmap",
           "compact_vector", "prior_median_m", "REGION_WEIGHTS_FIRST_PASS", "smoothed", "smoothing_cells",
           "compare_many", "align_to_depthmaps", "CORE_REGIONS"]

SIGNATURE_VERSION = 2   # 2: generic-face frame, deterministic registration, region weights (1 is not comparable)
# weight of each face region in the depth-map distance (rigid regions up, expression regions down)
# mouth and chin move with every expression (an open jaw moves the whole lower face) and the lower
# cheeks with a smile: identity is compared on the rigid upper face (ICT population, tuning seeds)
REGION_WEIGHTS = {"nose": 2.0, "eyes": 1.5, "forehead": 1.5, "cheeks": 0.3, "mouth": 0.0, "chin": 0.0}
# the first pass's weights (its distances are the ones quoted against the real maps)
REGION_WEIGHTS_FIRST_PASS = {"nose": 2.0, "eyes": 1.5, "forehead": 1.2, "cheeks": 1.0, "mouth": 0.25, "chin": 0.4}

# the region ensemble of the depth-map distance (after Faltemier, Bowyer & Flynn 2008): discs (centre x, centre y,
# radius) [m] of the face frame over the parts that no expression moves (x right, y down, origin the nose tip).
# Each disc's trimmed RMS height difference after the face's one alignment; their geometric mean and the whole
# face's distance, combined by a geometric mean, rank a probe's candidates. Chosen on tuning people only
# (bench/study_faces_regions.py: the core five beat every other set, single regions, medians, Borda counts and
# per-region alignments there)
CORE_REGIONS = {"nose": (0.0, -0.005, 0.022), "nose_wide": (0.0, -0.01, 0.035), "bridge": (0.0, -0.035, 0.018),
                "eye_l": (-0.032, -0.032, 0.018), "eye_r": (0.032, -0.032, 0.018)}
CORE_TRIM = 0.1            # fraction of a region's largest differences ignored (a region is small: few outliers)

SIGNATURE_METHODS = ("depthmap", "fft")
ALIGN_STRIDE = 3          # every third cell of the probe aligns it onto the reference
ALIGN_ITERATIONS = 5      # Gauss-Newton steps per correspondence distance (two distances)
SMOOTH_CELLS_PER_MM = 1.5  # comparison smoothing per mm of the scans' measured noise (see smoothing_cells)
MIRROR_FILL = True         # hidden half of a turned face taken from the seen half (mirror_completed)
SMOOTH_MIN_CELLS = 0.8     # at least this: fills isolated empty cells
SMOOTH_MAX_CELLS = 3.0
# the smoothing is rounded to this step: a 1:N fine stage aligns the probe onto all candidates of one smoothing
# together (`compare_many`), and the noise of each enrolled scan differs a little, which without the rounding
# gave every candidate of a depth-camera gallery a smoothing, and an alignment, of its own (tuning people,
# 21 candidates: 64 -> 43 ms per probe; rank-1 on them the same within one probe of 281)
SMOOTH_STEP_CELLS = 0.25


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
    trim: float = 0.25             # fraction of the largest height differences ignored (expressions, hair, rims)
    min_overlap: float = 0.3       # maps sharing fewer valid cells than this fraction do not match

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
    data: AnyArray
    params: SignatureParams
    points_used: int = 0
    noise_m: float = float("nan")   # the scan's own depth noise (roughness about its tangent planes) [m]

    def to_bytes(self) -> bytes:
        """Serialise (numpy .npz in memory): what the gallery stores."""
        buf = io.BytesIO()
        fields: dict[str, Any] = {k: np.array(getattr(self.params, k)) for k in SignatureParams.__dataclass_fields__}
        np.savez_compressed(buf, data=self.data.astype(np.float32), points_used=np.array(self.points_used),
                            noise_m=np.array(float(self.noise_m)), version=np.array(SIGNATURE_VERSION),
                            **{f"p_{k}": v for k, v in fields.items()})
        return buf.getvalue()

    @classmethod
    def from_bytes(cls, blob: bytes) -> Signature:
        """Inverse of `to_bytes`; raises `SignatureError` for a blob that is not a signature."""
        try:
            with np.load(io.BytesIO(blob), allow_pickle=False) as z:
                version = int(z["version"]) if "version" in z.files else 1
                if version != SIGNATURE_VERSION:
                    raise SignatureError(f"stored signature has version {version}, this software makes version "
                                         f"{SIGNATURE_VERSION}; the two are not comparable: remove the entry and "
                                         f"enrol the person again")
                kw: dict[str, Any] = {}
                for k, f in SignatureParams.__dataclass_fields__.items():
                    value = z[f"p_{k}"]
                    kw[k] = str(value) if f.type in ("str", str) else value.item()
                params = SignatureParams(**kw)
                noise = float(z["noise_m"]) if "noise_m" in z.files else float("nan")
                return cls(params.method, z["data"].astype(np.float64), params, int(z["points_used"]), noise)
        except SignatureError:
            raise
        except (OSError, KeyError, ValueError, TypeError) as exc:
            raise SignatureError(f"stored signature cannot be read ({exc.__class__.__name__}: {exc})") from None


def _depth_map(local: AnyArray, params: SignatureParams) -> AnyArray:
    g, e = params.grid, params.extent_m
    ij = np.floor((local[:, :2] + e) / (2 * e) * g).astype(np.int64)
    ok = np.all((ij >= 0) & (ij < g), axis=1)
    flat = ij[ok, 1] * g + ij[ok, 0]              # rows = y (down), columns = x (right)
    total = np.bincount(flat, weights=local[ok, 2], minlength=g * g)
    count = np.bincount(flat, minlength=g * g)
    out = np.full(g * g, np.nan)
    out[count > 0] = total[count > 0] / count[count > 0]
    return out.reshape(g, g)


def make_signature(points: AnyArray, frame: FaceFrame, params: SignatureParams = SignatureParams(),
                   face: FaceParams = FaceParams(), noise_m: float = float("nan")) -> Signature:
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
    return Signature(params.method, data, params, int(len(p)), float(noise_m))


def _fft_magnitudes(m: AnyArray, orders: int) -> AnyArray:
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


def cell_centres(params: SignatureParams) -> AnyArray:
    """Coordinates [m] of the grid's cell centres along x (columns) and y (rows, down) of the face frame."""
    g, e = params.grid, params.extent_m
    return (np.arange(g) + 0.5) / g * 2 * e - e


def _grid_points(sig: Signature) -> tuple[AnyArray, AnyArray]:
    centres = cell_centres(sig.params)
    x, y = np.meshgrid(centres, centres)
    valid = np.isfinite(sig.data)
    return np.stack([x[valid], y[valid], sig.data[valid]], axis=1), valid


def _sample_gradient(data: AnyArray, extent_m: float, xy: AnyArray) -> tuple[AnyArray, AnyArray, AnyArray]:
    """Bilinear height of K depth maps ``data`` (K, g, g) at local (K, M, 2) points and its x, y slopes;
    NaN outside or next to a hole."""
    g = data.shape[-1]
    cell = 2 * extent_m / g
    f = (xy + extent_m) / cell - 0.5
    i0 = np.floor(f).astype(np.int64)
    w = f - i0
    ok = (i0[..., 0] >= 0) & (i0[..., 0] < g - 1) & (i0[..., 1] >= 0) & (i0[..., 1] < g - 1)
    at = np.where(ok, i0[..., 1] * g + i0[..., 0], 0) + (np.arange(len(data)) * g * g)[:, None]
    flat = np.ascontiguousarray(data).ravel()
    a, b, cc, dd = flat[at], flat[at + 1], flat[at + g], flat[at + g + 1]
    wx, wy = w[..., 0], w[..., 1]
    h = (1 - wx) * (1 - wy) * a + wx * (1 - wy) * b + (1 - wx) * wy * cc + wx * wy * dd
    hx = ((1 - wy) * (b - a) + wy * (dd - cc)) / cell
    hy = ((1 - wx) * (cc - a) + wx * (dd - b)) / cell
    return np.where(ok, h, np.nan), np.where(ok, hx, np.nan), np.where(ok, hy, np.nan)


def _row_quantiles(values: AnyArray, ok: AnyArray, q: float) -> AnyArray:
    """Per row of ``values`` (K, M), the ``q`` quantile of its entries where ``ok``: numpy's default
    (linear) quantile of each row's kept entries, all rows in one sort instead of one call per row."""
    s = np.sort(np.where(ok, values, np.inf), axis=1)
    n = ok.sum(axis=1)
    v = n * q + (1 - q) - 1
    lo = np.floor(v).astype(np.int64)
    hi = np.minimum(lo + 1, n - 1)
    t = v - lo
    a, b = np.take_along_axis(s, lo[:, None], 1)[:, 0], np.take_along_axis(s, hi[:, None], 1)[:, 0]
    return np.where(t >= 0.5, b - (b - a) * (1 - t), a + (b - a) * t)


def align_to_depthmaps(points: AnyArray, data: AnyArray, extent_m: float, weights: AnyArray,
                       distances: tuple[float, ...], iterations: int = 8, trim: float = 0.1) -> AnyArray:
    """(K, 4, 4) rigid transforms taking face-frame ``points`` (M, 3) onto the surfaces of K depth maps
    ``data`` (K, g, g) of half width ``extent_m``: `align_to_depthmap` against several maps at once.

    The K problems are solved side by side as stacked arrays (each map's steps, stopping rules and trim
    are its own), so a probe is aligned onto all its first-stage candidates in one pass of numpy calls
    rather than one pass per candidate. Deterministic: fixed numpy operations, same input, same bits.
    """
    p0 = np.asarray(points, dtype=np.float64)
    n_maps = len(data)
    T = np.tile(np.eye(4), (n_maps, 1, 1))
    alive = np.ones(n_maps, bool)            # False once a map shares fewer than 20 points: its T is final
    for dist in distances:
        moving = alive.copy()
        for _ in range(iterations):
            ks = np.flatnonzero(moving)
            if len(ks) == 0:
                break
            p = p0 @ T[ks, :3, :3].transpose(0, 2, 1) + T[ks, None, :3, 3]
            h, hx, hy = _sample_gradient(data[ks], extent_m, p[..., :2])
            norm = np.sqrt(hx * hx + hy * hy + 1.0)
            nx, ny, nz = -hx / norm, -hy / norm, 1.0 / norm
            r = (p[..., 2] - h) * nz                   # distance to the tangent plane at the vertical foot point
            ok = np.isfinite(r) & (np.abs(r) <= dist)
            few = ok.sum(axis=1) < 20
            alive[ks[few]] = False
            moving[ks[few]] = False
            if few.all():
                continue
            if few.any():
                ks, p, nx, ny, nz, r, ok = (v[~few] for v in (ks, p, nx, ny, nz, r, ok))
            w = np.where(ok, weights, 0.0)
            if trim > 0:
                w *= np.abs(r) <= _row_quantiles(np.abs(r), ok, 1.0 - trim)[:, None]
            px, py, pz = p[..., 0], p[..., 1], p[..., 2]
            J = np.stack([py * nz - pz * ny, pz * nx - px * nz, px * ny - py * nx, nx, ny, nz], axis=-1)
            J = np.where(ok[..., None], J, 0.0)
            Jw = (J * w[..., None]).transpose(0, 2, 1)
            A = Jw @ J + 1e-12 * np.eye(6)
            x = np.linalg.solve(A, -(Jw @ np.where(ok, r, 0.0)[..., None]))[..., 0]
            step = np.tile(np.eye(4), (len(ks), 1, 1))
            step[:, :3, :3] = rotation_from_vector(x[:, :3])
            step[:, :3, 3] = x[:, 3:]
            T[ks] = step @ T[ks]
            done = (np.linalg.norm(x[:, 3:], axis=1) < 1e-6) & (np.linalg.norm(x[:, :3], axis=1) < 1e-5)
            moving[ks[done]] = False
    return T


def align_to_depthmap(points: AnyArray, ref: Signature, weights: AnyArray,
                      distances: tuple[float, ...], iterations: int = 8, trim: float = 0.1) -> AnyArray:
    """4 x 4 rigid transform taking face-frame ``points`` onto the surface of the depth map ``ref``.

    Point-to-plane Gauss-Newton like `lsu_faces.register.icp_point_to_plane`, but the correspondence of
    a point is the map's surface straight below or above it (bilinear height and slope of the grid), so
    no nearest-neighbour search is needed: the maps are already in the same face frame and only small
    corrections remain. Deterministic: fixed numpy operations, same input, same bits.
    """
    return align_to_depthmaps(points, ref.data[None], ref.params.extent_m, weights, distances, iterations, trim)[0]


def smoothed(sig: Signature, sigma_cells: float) -> Signature:
    """The depth map averaged over a Gaussian of ``sigma_cells`` cells, NaN-aware; a hole at least half
    surrounded by measured cells is filled (a depth camera's pixels are about one cell apart, so its
    maps are sprinkled with empty cells, and the bilinear comparison needs four cells around a point)."""
    if sigma_cells <= 0:
        return sig
    from scipy import ndimage

    valid = np.isfinite(sig.data)
    w = ndimage.gaussian_filter(valid.astype(np.float64), sigma_cells, mode="constant")
    v = ndimage.gaussian_filter(np.where(valid, sig.data, 0.0), sigma_cells, mode="constant")
    data = np.where(valid | (w >= 0.5), v / np.maximum(w, 1e-9), np.nan)
    return Signature(sig.method, data, sig.params, sig.points_used, sig.noise_m)


def mirror_completed(sig: Signature) -> Signature:
    """Empty cells filled from their mirror image across the face's symmetry plane (x = 0 of the face frame).

    A turned head hides one cheek and the nose's far flank; two captures turned to opposite sides then
    share only the middle of the face. Faces are nearly mirror-symmetric, so the seen half stands in for
    the hidden one (where both halves were seen nothing changes).
    """
    mirrored = sig.data[:, ::-1]
    fill = ~np.isfinite(sig.data) & np.isfinite(mirrored)
    if not fill.any():
        return sig
    return Signature(sig.method, np.where(fill, mirrored, sig.data), sig.params, sig.points_used, sig.noise_m)


def smoothing_cells(a: Signature, b: Signature) -> float:
    """Gaussian (cells) both maps are averaged over before comparing: more for noisier scans.

    A depth map cell holds one or a few measured points, so a depth camera's millimetres of noise
    and quantisation steps would dominate the distance; people differ in shapes of centimetres.
    """
    noise = max(float(a.noise_m), float(b.noise_m))
    if not np.isfinite(noise):
        noise = 0.0
    cells = np.round(SMOOTH_CELLS_PER_MM * noise * 1000.0 / SMOOTH_STEP_CELLS) * SMOOTH_STEP_CELLS
    return float(np.clip(cells, SMOOTH_MIN_CELLS, SMOOTH_MAX_CELLS))


def _depthmap_distances(probe: Signature, refs: list[Signature], smooth: float | None = None,
                        weights: dict[str, float] | None = None, core: bool = True) -> list[tuple[float, float]]:
    """(distance, overlap) of ``probe`` against each of ``refs``: the probe is prepared once per smoothing
    and aligned onto all references of that smoothing together (`align_to_depthmaps`). ``core``: the whole
    face's distance combined with the core regions' (`CORE_REGIONS`); False: the whole face's alone."""
    out: list[tuple[float, float]] = [(float("inf"), 0.0)] * len(refs)
    sigmas = [smoothing_cells(probe, r) if smooth is None else float(smooth) for r in refs]
    mirror = smooth is None and MIRROR_FILL
    for sigma in sorted(set(sigmas)):
        group = [j for j, s in enumerate(sigmas) if s == sigma]
        pr = smoothed(mirror_completed(probe) if mirror else probe, sigma)
        pp, _ = _grid_points(pr)
        refs_s = [smoothed(mirror_completed(refs[j]) if mirror else refs[j], sigma) for j in group]
        use = [k for k, r in enumerate(refs_s) if np.isfinite(r.data).sum() >= 20]
        if len(pp) < 20 or not use:
            continue
        params = refs_s[use[0]].params
        data = np.stack([refs_s[k].data for k in use])
        cell = 2 * params.extent_m / params.grid
        # the rigid alignment (6 unknowns) needs only a third of the cells: same frame, small corrections;
        # the distance itself is taken over every cell
        sub = pp[::ALIGN_STRIDE]
        T = align_to_depthmaps(sub, data, params.extent_m, _region_weights(sub, weights), (4 * cell, 1.5 * cell),
                               iterations=ALIGN_ITERATIONS, trim=probe.params.trim)
        moved = pp @ T[:, :3, :3].transpose(0, 2, 1) + T[:, None, :3, 3]
        h, _, _ = _sample_gradient(data, params.extent_m, moved[..., :2])
        diff = moved[..., 2] - h
        discs = [np.hypot(pp[:, 0] - cx, pp[:, 1] - cy) <= r for cx, cy, r in CORE_REGIONS.values()] if core else []
        for k, j in enumerate(use):
            ok = np.isfinite(diff[k])
            overlap = float(ok.sum()) / max(len(pp), 1)
            if overlap < probe.params.min_overlap or ok.sum() < 20:
                out[group[j]] = (float("inf"), overlap)
                continue
            d, wd = np.abs(diff[k, ok]), _region_weights(moved[k, ok], weights)
            keep = d <= np.quantile(d, 1.0 - probe.params.trim)
            dist = float(np.sqrt(np.sum(wd[keep] * d[keep] ** 2) / np.sum(wd[keep])))
            if core:
                dist = float(np.sqrt(dist * _core_distance(np.abs(diff[k]), discs)))
            out[group[j]] = (dist, overlap)
    return out


def _core_distance(diff: AnyArray, discs: list[AnyArray]) -> float:
    """Geometric mean of the core regions' trimmed RMS of ``diff`` (|height difference| per probe cell, NaN
    where the reference has none) over the regions ``discs`` (masks of the probe's cells); a region with
    fewer than 20 cells, or under half of them (or 15) compared, does not count; inf below two that do."""
    logs = []
    for disc in discs:
        cells = int(disc.sum())
        d = diff[disc]
        d = np.sort(d[np.isfinite(d)])
        if cells < 20 or len(d) < max(15, 0.5 * cells):
            continue
        d = d[: max(1, int(round(len(d) * (1.0 - CORE_TRIM))))]
        logs.append(0.5 * np.log(max(float(np.mean(d ** 2)), 1e-30)))   # identical maps: ~0, not log(0)
    return float(np.exp(np.mean(logs))) if len(logs) >= max(1, len(discs) // 2) else float("inf")


def _region_weights(local: AnyArray, weights: dict[str, float] | None = None) -> AnyArray:
    from .template import REGIONS, region_of

    table = np.array([(weights or REGION_WEIGHTS)[r] for r in REGIONS])
    return table[region_of(local)]


def _fft_distance(probe: Signature, ref: Signature) -> tuple[float, float]:
    both = np.isfinite(probe.data[:, 0]) & np.isfinite(ref.data[:, 0])
    overlap = float(both.mean())
    if overlap < probe.params.min_overlap:
        return float("inf"), overlap
    d = probe.data[both] - ref.data[both]
    return float(np.sqrt(np.mean(d ** 2))), overlap


def compare(probe: Signature, ref: Signature, model: ImpostorModel | None = None,
            smooth: float | None = None, weights: dict[str, float] | None = None,
            core: bool = True) -> tuple[float, float, float]:
    """(score 0..1, distance [m], overlap fraction) of ``probe`` against ``ref``.

    The score is ``model.score(distance)`` (default model: the prior). ``smooth``: Gaussian in cells
    applied to both depth maps first (None: `smoothing_cells` from the scans' noise; 0: none).
    ``weights``: region weights (default `REGION_WEIGHTS`). ``core``: the whole face's distance combined
    with the core regions' (`CORE_REGIONS`, the default); False: the whole face's alone (the first pass).
    """
    return compare_many(probe, [ref], model, smooth, weights, core)[0]


def compare_many(probe: Signature, refs: list[Signature], model: ImpostorModel | None = None,
                 smooth: float | None = None, weights: dict[str, float] | None = None, core: bool = True
                 ) -> list[tuple[float, float, float]]:
    """`compare` of ``probe`` against each of ``refs`` (one 1:N fine stage: the probe's preparation and the
    alignments are shared, see `_depthmap_distances`)."""
    for ref in refs:
        if probe.method != ref.method:
            raise SignatureError(f"cannot compare a '{probe.method}' signature with a '{ref.method}' one; "
                                 f"re-enrol the gallery with one method")
        if probe.data.shape != ref.data.shape:
            raise SignatureError(f"signature grids differ ({probe.data.shape} vs {ref.data.shape}); "
                                 f"re-enrol the gallery")
    if probe.method == "depthmap":
        found = _depthmap_distances(probe, refs, smooth, weights, core)
    else:
        found = [_fft_distance(probe, ref) for ref in refs]
    model = model or ImpostorModel.prior(probe.method)
    return [(model.score(dist), dist, overlap) for dist, overlap in found]


@dataclass(frozen=True)
class ImpostorModel:
    """Log-normal model of the distances between DIFFERENT people: ln d ~ N(mu, sigma)."""

    log_mu: float
    log_sigma: float
    samples: int = 0                 # impostor distances it was fitted to (0: the prior alone)

    @classmethod
    def prior(cls, method: str = "depthmap", noise_m: float = float("nan")) -> ImpostorModel:
        """The prior for scans of depth noise ``noise_m`` (NaN: the LSU rig's): see `prior_median_m`."""
        mu, sigma = _PRIOR[method]
        if method == "depthmap" and np.isfinite(noise_m):
            mu = float(np.log(prior_median_m(noise_m)))
        return cls(mu, sigma, 0)

    @classmethod
    def fit(cls, distances: AnyArray | list, method: str = "depthmap", noise_m: float = float("nan")) -> ImpostorModel:
        """Model from impostor ``distances`` [m], shrunk towards the prior for ``noise_m`` (which dominates
        small samples)."""
        d = np.asarray([x for x in distances if np.isfinite(x) and x > 0], dtype=np.float64)
        prior = cls.prior(method, noise_m)
        mu0, s0 = prior.log_mu, prior.log_sigma
        if len(d) == 0:
            return cls(mu0, s0, 0)
        ln = np.log(d)
        n, k = len(ln), _PRIOR_WEIGHT
        mu = (k * mu0 + n * ln.mean()) / (k + n)
        var = (k * s0 ** 2 + n * ln.var() + k * n / (k + n) * (ln.mean() - mu0) ** 2) / (k + n)
        return cls(float(mu), float(np.sqrt(max(var, 1e-6))), int(n))

    def false_accept(self, distance_m: float) -> float:
        """Chance that a different person comes within ``distance_m`` of a face."""
        from scipy.special import ndtr
        if not np.isfinite(distance_m):
            return 1.0
        if distance_m <= 0:
            return 0.0
        return float(ndtr((np.log(distance_m) - self.log_mu) / self.log_sigma))

    def score(self, distance_m: float) -> float:
        """1 - `false_accept`: near 1 for the same person, near 0 for anybody."""
        return 1.0 - self.false_accept(distance_m)

    def threshold_m(self, false_accept_rate: float) -> float:
        """Distance below which a single comparison falsely accepts with ``false_accept_rate``."""
        from scipy.special import ndtri
        return float(np.exp(self.log_mu + self.log_sigma * ndtri(false_accept_rate)))


def prior_median_m(noise_m: float) -> float:
    """Median distance between two different people's scans of depth noise ``noise_m`` (prior of the model).

    Two parts add in quadrature: the shape difference of two people (``_PRIOR_SHAPE_M``, the median
    impostor distance with the LSU rig, whose ~0.1 mm noise adds nothing) and what the sensor's own
    noise, steps and artefacts add, proportional to the noise measured on the scans
    (``_PRIOR_NOISE_GAIN``; both from bench/bench_faces.py, rig and time-of-flight model).
    """
    return float(np.hypot(_PRIOR_SHAPE_M, _PRIOR_NOISE_GAIN * max(float(noise_m), 0.0)))


# prior impostor model: distances between different synthetic people (MakeHuman morphs with hair and
# expressions) scanned by the LSU rig, measured by bench/bench_faces.py; it counts as _PRIOR_WEIGHT pairs
_PRIOR = {"depthmap": (float(np.log(0.0013)), 0.30), "fft": (float(np.log(0.0008)), 0.45)}
_PRIOR_SHAPE_M = 0.0013
_PRIOR_NOISE_GAIN = 2.0
_PRIOR_WEIGHT = 20


# ------------------------------------------------------------------ compact signature (1:N first stage)
COMPACT_BLOCK = 4               # depth-map cells per block side (4 x 2.5 mm: 10 mm blocks)
COMPACT_RADIUS_M = 0.06         # blocks whose centre lies within this of the nose tip
_COMPACT: dict[tuple, tuple[AnyArray, AnyArray, AnyArray]] = {}


def _compact_layout(params: SignatureParams) -> tuple[AnyArray, AnyArray, AnyArray]:
    """(block rows, block cols, per-block weight, generic face's block heights) for ``params``' grid (kept)."""
    key = (params.grid, params.extent_m)
    if key not in _COMPACT:
        from .template import REGIONS, face_template, region_of

        nb = params.grid // COMPACT_BLOCK
        cell = 2 * params.extent_m / params.grid
        centres = (np.arange(nb) + 0.5) * COMPACT_BLOCK * cell - params.extent_m
        bx, by = np.meshgrid(centres, centres)
        inside = np.hypot(bx, by) <= COMPACT_RADIUS_M
        xy = np.stack([bx[inside], by[inside], np.zeros(int(inside.sum()))], axis=1)
        w = np.sqrt(np.array([REGION_WEIGHTS[r] for r in REGIONS])[region_of(xy)])
        generic = _blocks(_depth_map(face_template().points, params), params)
        _COMPACT[key] = (inside, w, generic[inside])
    return _COMPACT[key]


def _blocks(data: AnyArray, params: SignatureParams) -> AnyArray:
    """Mean height of each COMPACT_BLOCK x COMPACT_BLOCK block of a depth map (NaN: fewer than 4 cells seen)."""
    nb = params.grid // COMPACT_BLOCK
    d = data[: nb * COMPACT_BLOCK, : nb * COMPACT_BLOCK].reshape(nb, COMPACT_BLOCK, nb, COMPACT_BLOCK)
    valid = np.isfinite(d)
    count = valid.sum(axis=(1, 3))
    total = np.where(valid, d, 0.0).sum(axis=(1, 3))
    return np.where(count >= 4, total / np.maximum(count, 1), np.nan)


def compact_vector(sig: Signature) -> AnyArray:
    """Short float32 vector of a depth-map signature for the 1:N first stage (L2 ~ the weighted distance).

    The face's height (mirror-completed, `mirror_completed`) in 10 mm blocks within 60 mm of the nose
    tip, minus the generic face's (blocks
    the scan did not see take the generic face's height, i.e. count as no difference), less its mean
    (a tip found a little high or low shifts every height alike), each block scaled by the square root
    of its region's weight (`REGION_WEIGHTS`). Units: metres.
    """
    if sig.method != "depthmap":
        raise SignatureError("compact vectors are made from depth-map signatures only")
    inside, w, generic = _compact_layout(sig.params)
    b = _blocks(mirror_completed(sig).data, sig.params)[inside]
    diff = np.where(np.isfinite(b), b - generic, 0.0)
    diff -= diff.mean()
    return (diff * w).astype(np.float32)

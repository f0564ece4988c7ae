"""Face geometry (thesis ch. 11): crop, nose tip, radial vector, spherical embedding, parametric map.

Nose tip, three methods:

- ``svd`` (thesis ch. 11.1.2): centroid of the facial surface, the points within a sphere around it,
  their principal directions by SVD; the direction of least spread is the normal of the facial plane
  through the centroid and the point farthest in front of that plane is the tip. (The thesis text
  says "maximally weighted principal direction"; only the least-spread direction makes the nose the
  farthest point from the plane, which is what its Figure 51 shows.)
- ``template`` (the default; `nose_tip_template`): the protrusion candidates below, each verified by
  registering the generic face (`lsu_faces.template`) on the surface around it; the candidate whose
  surroundings match a face's layout (eyes above, mouth below, a narrow nose, mirror symmetry) wins
  with a confidence, and nothing face-like enough gives "no face". Real scenes have collars, chins,
  fists, hair and crop edges that protrude as much as a nose; only the layout tells them apart.
- ``protrusion`` (the default before, kept for comparison in bench/bench_faces.py): the nose is
  the point that stands out most from its *own* surroundings, whatever the pose. For candidates on a
  coarse voxel grid, a plane is fitted to the ring of surface 15-35 mm around each one and the height
  of the candidate above it is its protrusion; the best candidates are then re-scored against a
  quadric fitted to the ring (so the curvature of a round head, or of a ball, does not count as a
  nose), weighted by how squarely the bump faces the scanner (an ear of a turned head is seen
  edge-on), and the tip is refined on the full-resolution points along the ring's normal. A nose must
  protrude ``min_prominence_m`` above the quadric: a plane or a ball is reported as "no face".

Face frame (`embed_face`): with ``template``, the registered generic face's axes (mirror-symmetric,
so its x = 0 plane is the face's symmetry plane) with the origin on the measured nose tip. With the
other methods: the ring normal, then `symmetric_frame` (mirror-symmetry plane by ICP of the mirrored
face, which removes the bias of a turned head's hidden cheek) and the profile line (forehead to chin)
for the nod; the tip is moved onto the symmetry plane. Every registration is `lsu_faces.register`'s
deterministic ICP: the same cloud gives the same frame in every process.

Radial vector (ch. 11.2.1): the normal of the plane fitted to the points within ``radial_radius_m``
of the tip, pointing out of the face (towards the camera). Spherical embedding (ch. 11.2.2): the
sphere of radius ``sphere_radius_m`` whose surface touches the nose tip, centred behind it on the
radial vector; each point gets its unit direction from the centre and its radial distance. The 2D
parametric map (ch. 11.2.3) bins the points by elevation (angle from the radial vector) and azimuth
(angle about it) and stores the mean radial height above the sphere. The frame, the parameters and the two
maps are `lsu_faces.frame`'s (the signatures need them too), re-exported here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from lsu_common.arrays import AnyArray

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

from .frame import NOSE_METHODS, FaceError, FaceFrame, FaceParams, NotAFaceError, parametric_map, spherical_embedding

__all__ = ["FaceError", "NotAFaceError", "FaceParams", "NoseResult", "FaceFrame", "depth_window", "nose_tip_svd",
           "nose_tip_protrusion", "nose_tip_template", "nose_tip", "radial_vector", "face_frame", "crop_face",
           "spherical_embedding",
           "parametric_map", "NOSE_METHODS"]


@dataclass
class NoseResult:
    """A nose tip [m, left optical frame], the outward face normal there and how much the nose stands out."""

    tip: AnyArray
    normal: AnyArray
    prominence_m: float
    method: str
    confidence: float = 1.0           # 0..1: how face-like the surroundings are (template method)
    symmetry_mm: float = float("nan")   # median mirror residual of the face around the tip
    frame: FaceFrame | None = None  # the verified face frame (template method)
    noise_m: float = float("nan")   # the scan's depth noise: roughness about the local tangent planes
    warnings: list[str] = field(default_factory=list)   # what is unusual but no reason to refuse (asymmetry)
    runner_up_confidence: float = 0.0   # the best face fit more than 20 mm from this one (template method)
    runner_up_distance_mm: float = 0.0
    model_weight: float = float("nan")  # RMS prior-normalised weight of the face-model fit at this nose (template method)


def _check(points: AnyArray, params: FaceParams) -> AnyArray:
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) < params.min_points:
        raise FaceError(f"{len(p)} points are too few for a face (need {params.min_points}); scan closer or "
                        f"check the laser line extraction")
    if not np.all(np.isfinite(p)):
        raise FaceError("the cloud holds NaN or infinite points; drop them first")
    return p


def depth_window(points: AnyArray, params: FaceParams = FaceParams()) -> AnyArray:
    """Mask of the points within ``depth_window_m`` behind the nearest surface (robust 0.5 % depth)."""
    r = np.linalg.norm(points, axis=1)
    near = np.percentile(r, 0.5)
    return r <= near + params.depth_window_m


def _towards_camera(normal: AnyArray, at: AnyArray) -> AnyArray:
    return normal if np.dot(normal, -at) > 0 else -normal


def _plane_normal(points: AnyArray) -> AnyArray:
    c = points - points.mean(axis=0)
    _, _, vt = np.linalg.svd(c, full_matrices=False)
    return vt[-1]


def nose_tip_svd(points: AnyArray, params: FaceParams = FaceParams()) -> NoseResult:
    """The thesis' nose finder (ch. 11.1.2): farthest point from the SVD facial plane through the centroid."""
    p = _check(points, params)
    p = p[depth_window(p, params)]
    centroid = p.mean(axis=0)
    reduced = p[np.linalg.norm(p - centroid, axis=1) <= params.svd_sphere_m]
    if len(reduced) < 10:
        raise FaceError(f"only {len(reduced)} points within {params.svd_sphere_m * 1000:.0f} mm of the centroid; "
                        f"raise svd_sphere_m")
    n = _towards_camera(_plane_normal(reduced), centroid)
    height = (reduced - centroid) @ n
    i = int(np.argmax(height))
    return NoseResult(reduced[i].copy(), n, float(height[i]), "svd")


def _voxel_means(points: AnyArray, voxel: float) -> AnyArray:
    """Mean of the points in each occupied voxel (ordered by voxel key: deterministic)."""
    keys = np.floor(points / voxel).astype(np.int64)
    keys -= keys.min(axis=0)
    span = keys.max(axis=0) + 1
    flat = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
    _, inverse, counts = np.unique(flat, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    sums = np.stack([np.bincount(inverse, weights=points[:, k], minlength=len(counts)) for k in range(3)], axis=1)
    return sums / counts[:, None]


def _ring_planes(centres: AnyArray, samples: AnyArray, inner: float, outer: float) -> tuple[AnyArray, ...]:
    """For every centre: mean, unit normal (least spread) and count of the samples in the ring inner..outer."""
    from scipy import sparse
    from scipy.spatial import cKDTree
    tree_c, tree_s = cKDTree(centres), cKDTree(samples)
    dist = tree_c.sparse_distance_matrix(tree_s, outer, output_type="coo_matrix")
    keep = dist.data > inner
    A = sparse.csr_matrix((np.ones(int(keep.sum())), (dist.row[keep], dist.col[keep])),
                          shape=(len(centres), len(samples)))
    count = np.asarray(A.sum(axis=1)).ravel()
    safe = np.maximum(count, 1)[:, None]
    mean = (A @ samples) / safe
    outer_prod = np.einsum("ni,nj->nij", samples, samples).reshape(len(samples), 9)
    cov = ((A @ outer_prod) / safe).reshape(-1, 3, 3) - np.einsum("ni,nj->nij", mean, mean)
    _, vecs = np.linalg.eigh(cov)
    normal = vecs[:, :, 0]
    flip = np.einsum("ij,ij->i", normal, -centres) < 0
    normal[flip] *= -1.0
    return mean, normal, count


def _quadric_height(centre: AnyArray, normal: AnyArray, ring: AnyArray) -> float:
    """Height of ``centre`` above the quadric h(x, y) fitted to ``ring`` in the frame of ``normal``."""
    e1 = np.cross(normal, [0.0, 1.0, 0.0])
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.cross(normal, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    d = ring - centre
    x, y, h = d @ e1, d @ e2, d @ normal
    A = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=1)
    coef, *_ = np.linalg.lstsq(A, h, rcond=None)
    return float(-coef[0])   # the candidate sits at x = y = 0, h = 0


def nose_tip_protrusion(points: AnyArray, params: FaceParams = FaceParams(), top: int = 12) -> NoseResult:
    """The most protruding point of the surface relative to its own surroundings (see the module doc).

    Raises:
        NotAFaceError: nothing protrudes at least ``min_prominence_m`` above its quadric ring.
    """
    from scipy.spatial import cKDTree
    p = _check(points, params)
    p = p[depth_window(p, params)]
    samples = _voxel_means(p, params.sample_voxel_m)
    candidates = _voxel_means(p, params.candidate_voxel_m)
    mean, normal, count = _ring_planes(candidates, samples, params.ring_inner_m, params.ring_outer_m)
    # a candidate needs its ring mostly present: at the rim of the scan the ring is one-sided
    full_ring = np.pi * (params.ring_outer_m ** 2 - params.ring_inner_m ** 2) / params.sample_voxel_m ** 2
    ok = count >= 0.35 * full_ring
    if not np.any(ok):
        raise NotAFaceError("no part of the surface is wide enough for a face (every 35 mm neighbourhood is "
                            "mostly empty); scan the whole face at about 30 cm")
    height = np.einsum("ij,ij->i", candidates - mean, normal)
    height[~ok] = -np.inf
    best = np.argsort(height)[::-1][:top]
    tree = cKDTree(samples)
    scores = []
    for i in best:
        if not np.isfinite(height[i]):
            continue
        around = samples[tree.query_ball_point(candidates[i], params.ring_outer_m)]
        ring = around[np.linalg.norm(around - candidates[i], axis=1) > params.ring_inner_m]
        q = _quadric_height(candidates[i], normal[i], ring)
        # the nose points at the scanner more than any other bump (an ear of a turned head is seen edge-on)
        facing = max(float(np.dot(normal[i], -candidates[i]) / np.linalg.norm(candidates[i])), 0.0)
        scores.append((q * facing, q, int(i)))
    if not scores:
        raise NotAFaceError("no nose candidate found")
    _, prominence, i = max(scores)
    if prominence < params.min_prominence_m:
        raise NotAFaceError(f"no nose: the most prominent feature stands {prominence * 1000:.1f} mm out of its "
                            f"surroundings (a nose: > {params.min_prominence_m * 1000:.0f} mm); is a face in front "
                            f"of the scanner?")
    # refine on the full-resolution points: farthest along the ring normal near the candidate
    n = normal[i]
    near = p[np.linalg.norm(p - candidates[i], axis=1) <= params.ring_inner_m]
    h = (near - mean[i]) @ n
    top_k = np.argsort(h)[::-1][:5]
    tip = near[top_k].mean(axis=0)
    return NoseResult(tip, n, float(prominence), "protrusion")


def _candidates(p: AnyArray, samples: AnyArray, params: FaceParams) -> tuple[AnyArray, AnyArray, AnyArray]:
    """Nose candidates: (centres, ring normals, quadric protrusion) best first, one per 15 mm."""
    from scipy.spatial import cKDTree
    candidates = _voxel_means(p, params.candidate_voxel_m)
    # ring statistics on candidate-sized samples: the ring's plane and quadric need no finer surface
    samples = _voxel_means(p, params.candidate_voxel_m / 1.5)
    mean, normal, count = _ring_planes(candidates, samples, params.ring_inner_m, params.ring_outer_m)
    full_ring = np.pi * (params.ring_outer_m ** 2 - params.ring_inner_m ** 2) / (params.candidate_voxel_m / 1.5) ** 2
    ok = count >= params.ring_min_fraction * full_ring
    if not np.any(ok):
        raise NotAFaceError("no part of the surface is wide enough for a face (every 35 mm neighbourhood is "
                            "mostly empty): is the cloud in metres (--units), and the whole face in it?")
    height = np.einsum("ij,ij->i", candidates - mean, normal)
    height[~ok] = -np.inf
    order = np.argsort(-height, kind="stable")[: 8 * params.candidates]
    tree = cKDTree(samples)
    scored = []
    for i in order:
        if not np.isfinite(height[i]):
            continue
        around = samples[tree.query_ball_point(candidates[i], params.ring_outer_m)]
        ring = around[np.linalg.norm(around - candidates[i], axis=1) > params.ring_inner_m]
        q = _quadric_height(candidates[i], normal[i], ring)
        facing = max(float(np.dot(normal[i], -candidates[i]) / np.linalg.norm(candidates[i])), 0.0)
        scored.append((-q * facing, int(i), q))
    scored.sort()
    chosen: list = []
    for _, i, q in scored:
        if q < 0.5 * params.min_prominence_m:
            break
        if all(np.linalg.norm(candidates[i] - candidates[j]) > 0.015 for j, _ in chosen):
            chosen.append((i, q))
        if len(chosen) >= params.candidates:
            break
    if not chosen:
        raise NotAFaceError(f"no nose: nothing stands {params.min_prominence_m * 500:.0f} mm out of its "
                            f"surroundings; is a face in front of the scanner?")
    idx = np.array([i for i, _ in chosen])
    return candidates[idx], normal[idx], np.array([q for _, q in chosen])


def _roughness(samples: AnyArray, tree: cKDTree, normals: AnyArray) -> float:
    """Median distance of the samples from their neighbours' tangent plane (sensor noise, depth steps) [m]."""
    step = max(1, len(samples) // 2000)
    probe = samples[::step]
    _, idx = tree.query(probe, k=8)
    nb = samples[idx[:, 1:]]
    off = np.einsum("nkj,nj->nk", nb - nb.mean(axis=1, keepdims=True), normals[::step])
    return float(np.median(np.abs(off)))


def _refine_tip(local: AnyArray, smooth: bool, radius: float = 0.008) -> AnyArray:
    """Nose tip in the fitted face frame: the mean of the 5 highest points within ``radius`` of the frame's
    z axis; with ``smooth`` (a noisy sensor: depth steps of millimetres pull the highest points outwards)
    the peak of a quadric z(x, y) fitted to those points by least squares, where it has one there."""
    near = local[np.linalg.norm(local[:, :2], axis=1) <= radius]
    if len(near) < 3:
        return np.zeros(3)
    top = near[np.argsort(-near[:, 2], kind="stable")[:5]].mean(axis=0)
    if not smooth or len(near) < 12:
        return top
    x, y, z = near[:, 0], near[:, 1], near[:, 2]
    A = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=1)
    c, *_ = np.linalg.lstsq(A, z, rcond=None)
    H = np.array([[2 * c[3], c[4]], [c[4], 2 * c[5]]])
    if not np.all(np.linalg.eigvalsh(H) < 0):
        return top
    xy = np.linalg.solve(H, -c[1:3])
    if np.linalg.norm(xy) > radius:
        return top
    zp = c[0] + c[1] * xy[0] + c[2] * xy[1] + c[3] * xy[0] ** 2 + c[4] * xy[0] * xy[1] + c[5] * xy[1] ** 2
    return np.array([xy[0], xy[1], zp])


def _relief(local: AnyArray, inner: float = 0.025, outer: float = 0.045) -> float:
    """Height of the nose (highest point within 8 mm of the z axis) over the median of the inner..outer ring [m]."""
    r = np.linalg.norm(local[:, :2], axis=1)
    tip, ring = local[r <= 0.008, 2], local[(r >= inner) & (r <= outer), 2]
    if len(tip) < 3 or len(ring) < 10:
        return 0.0
    return float(np.max(tip) - np.median(ring))


def _symmetry_mm(local: AnyArray) -> float:
    """Median distance of the mirrored face (x -> -x) to the face, over the mirrored points that overlap it."""
    from scipy.spatial import cKDTree
    near = local[np.linalg.norm(local[:, :2], axis=1) < 0.06]
    if len(near) < 30:
        return float("inf")
    d, _ = cKDTree(near).query(near * np.array([-1.0, 1.0, 1.0]), distance_upper_bound=0.01)
    d = d[np.isfinite(d)]
    return float(np.median(d) * 1000.0) if len(d) > 0.3 * len(near) else float("inf")


# The layout confidence counts only the template points the scanner can see at the fitted pose (FaceParams.
# max_view_angle_deg) when at least this share of the template's core faces it; with less (a profile, a back of a
# head) the whole template counts, so a face turned away stays "no face".
FACING_MIN_SHARE = 0.6


def _facing(points: AnyArray, normals: AnyArray, T: AnyArray, max_angle_deg: float) -> AnyArray:
    """Which template ``points`` (face frame, with their outward ``normals``), placed by ``T``, the scanner at the
    origin sees within ``max_angle_deg`` of their normal: (n,) bool."""
    x = points @ T[:3, :3].T + T[:3, 3]
    n = normals @ T[:3, :3].T
    return np.einsum("ij,ij->i", n, -x) > math.cos(math.radians(max_angle_deg)) * np.linalg.norm(x, axis=1)


def nose_tip_template(points: AnyArray, params: FaceParams = FaceParams()) -> NoseResult:
    """Nose tip verified by the whole face: shape candidates, then the generic face registered on each.

    Candidates are the points that protrude most above a quadric fitted to their 15-35 mm ring (with
    at least ``ring_min_fraction`` of the ring present: crop edges and silhouettes have one-sided
    rings), one per 15 mm. The generic face (`lsu_faces.template`: nose, eye sockets, brows, mouth,
    chin in their usual layout) is registered onto the surface around each candidate; a candidate wins
    by how much of the face's layout the surface matches (``confidence`` = covered fraction of the
    template x closeness of the fit). A chin, a fist, a knuckle or a lock of hair protrudes too but
    has no eyes above and no mouth below it. The winner must also be mirror-symmetric
    (``max_symmetry_mm``). The tip is then the most prominent measured point along the fitted face
    normal within 8 mm of the template's nose.

    Raises:
        NotAFaceError: no candidate reaches ``min_confidence`` (a plane, a ball, a hand alone, a back
            of a head, a profile whose face is hidden).
    """
    from scipy.spatial import cKDTree

    from .register import estimate_normals, icp_point_to_plane
    from .template import REGIONS, face_template

    p = _check(points, params)
    p = p[depth_window(p, params)]
    samples = _voxel_means(p, params.sample_voxel_m)
    centres, normals, prominence = _candidates(p, samples, params)
    tpl = face_template()
    tree = cKDTree(samples)
    snormals = estimate_normals(samples, tree=tree)
    core = np.isin(tpl.region, [REGIONS.index(r) for r in ("nose", "eyes", "mouth", "cheeks", "forehead")])
    # a fit as good as the sensor allows scores 1: scale by the measured surface's own roughness
    noise_m = _roughness(samples, tree, snormals)
    rms_scale = 0.003 + 2.0 * noise_m
    sub = np.arange(0, len(tpl.points), 3)          # coarse stage: a third of the template

    def verify(T0: AnyArray, idx: AnyArray, distances: tuple[float, ...]) -> tuple[float, Any, dict[str, float]]:
        reg = icp_point_to_plane(tpl.points[idx], samples, snormals, T0, distances=distances, iterations=6,
                                 tree=tree, trim=0.2)
        out = reg.T[:3, 2]           # the fitted face must look at the scanner (its z axis towards the camera)
        if float(np.dot(out, -reg.T[:3, 3])) <= 0.0 or not np.isfinite(reg.rms_m):
            return -1.0, reg, {}
        # what the scanner cannot see at this pose (the far cheek and eye of a turned head) cannot be covered
        seen = _facing(tpl.points[idx], tpl.normals[idx], reg.T, params.max_view_angle_deg)
        if np.count_nonzero(seen & core[idx]) < FACING_MIN_SHARE * np.count_nonzero(core[idx]):
            seen = np.ones(len(idx), bool)
        in_sight = {r: seen & (tpl.region[idx] == k) for k, r in enumerate(REGIONS)}
        cover = {r: float(reg.inliers[m].mean()) if m.any() else 0.0 for r, m in in_sight.items()}
        conf = float(reg.inliers[core[idx] & seen].mean()) * float(np.exp(-(reg.rms_m / rms_scale) ** 2))
        if min(cover["nose"], max(cover["eyes"], cover["cheeks"])) < 0.35:
            conf = min(conf, 0.0)        # no nose, or nothing of the face beside it
        # the measured surface itself must hold a nose where the face has one: relief of the tip over the
        # ring 25-45 mm around it, along the fitted face normal (a chest or a shoulder fits loosely but is flat)
        local = (samples - reg.T[:3, 3]) @ reg.T[:3, :3]
        cover["relief_ratio"] = _relief(local) / tpl_relief
        # and the nose is narrow: most of its height is lost within 12-20 mm (a shoulder or a ball is a dome)
        cover["narrow_ratio"] = _relief(local, 0.012, 0.02) / tpl_narrow
        if not (0.55 <= cover["relief_ratio"] <= 1.8 and cover["narrow_ratio"] >= 0.5):
            conf = min(conf, 0.0)
        return conf, reg, cover

    tpl_relief, tpl_narrow = _relief(tpl.points), _relief(tpl.points, 0.012, 0.02)
    rough: list[tuple[float, int, AnyArray, Any]] = []
    for c, n, q in zip(centres, normals, prominence):
        frame = face_frame(c, n)
        T0 = np.eye(4)
        T0[:3, :3] = frame.axes.T
        T0[:3, 3] = c
        conf, reg, _ = verify(T0, sub, (0.02, 0.008))
        rough.append((-conf, len(rough), reg.T, q))
    rough.sort(key=lambda r: (r[0], r[1]))
    best = None
    verified = []
    layout_best = 0.0
    for _, _, T0, q in rough[:3]:
        conf, reg, cover = verify(T0, np.arange(len(tpl.points)), (0.008, 0.004))
        verified.append((conf, reg.T[:3, 3]))
        layout_best = max(layout_best, conf)
        if conf < params.min_confidence:
            continue
        # the layout fits loosely on a cheek or brow of a turned head too: the face model must explain the
        # surface around the candidate with the weights of a plausible person (see _model_weight)
        weight = _model_weight(p, reg.T, noise_m, params)
        factor = 1.0 if weight <= params.max_model_weight else 0.0
        if best is None or conf * factor > best[0] * best[3]:
            best = (conf, reg, q, factor, weight)
    if best is None or best[0] * best[3] < params.min_confidence:
        if best is not None:
            raise NotAFaceError(f"no face: the best nose candidate matches a face's layout (confidence {best[0]:.2f}) "
                                f"but the face model explains its surroundings only with implausible shape weights "
                                f"(RMS {best[4]:.2f} prior sigmas, a face: <= {params.max_model_weight:.2f}): a nose on "
                                f"a chin, cheek or collar? Turn the face towards the scanner and capture again")
        raise NotAFaceError(f"no face: the best nose candidate matches a face's layout with confidence "
                            f"{layout_best:.2f} (a face: >= {params.min_confidence:.2f}); is a face turned towards the "
                            f"scanner?")
    conf, reg, q, factor, weight = best
    conf *= factor
    axes = reg.T[:3, :3].T
    origin = reg.T[:3, 3]
    local = (p - origin) @ axes.T
    sym = _symmetry_mm(local)
    warnings = []
    if not sym <= params.max_symmetry_mm:
        # real faces and real captures (a turned head, hair, a collar) are often less symmetric than this:
        # the layout confidence decides what is a face, the asymmetry is only reported
        warnings.append(f"the face is not mirror-symmetric (median residual {sym:.1f} mm, usually <= "
                        f"{params.max_symmetry_mm:.1f} mm): check the scan if this person is hard to identify")
    tip = origin + _refine_tip(local, smooth=noise_m > 0.0003) @ axes
    frame = FaceFrame(tip, axes)
    # the best face fit elsewhere (more than 20 mm away): how clearly this place won
    others = [(c, float(np.linalg.norm(o - origin))) for c, o in verified if np.linalg.norm(o - origin) > 0.02]
    runner = max(others) if others else (0.0, 0.0)
    return NoseResult(tip, axes[2].copy(), float(q), "template", float(conf), float(sym), frame, float(noise_m),
                      warnings, float(runner[0]), runner[1] * 1000.0, float(weight))


MODEL_CHECK_NOISE_M = 0.0014   # depth noise the face-model check assumes at least (a time-of-flight camera's)
# something before the mouth and chin (a hand, a collar, a microphone) makes a real face look implausible to the
# whole face's fit: when a share OCCLUDED_SHARE of the face's cells more than MODEL_CHECK_BELOW_M [m] below the nose
# tip lies OCCLUDER_IN_FRONT_M or more in front of the model fitted to the face above them, that fit decides, and
# must find clearly a face there (weights <= OCCLUDED_MAX_WEIGHT). Set on 4 of the first bench's 16 people (0, 2,
# 5, 12) and a tuning person's turned head (ICT seed 1): the fists before the chin the whole fit refused cover
# 0.18-0.41 of the lower cells and fit above them with weights 0.9-1.5; unoccluded faces cover at most 0.05; the
# cheek of a turned head, which the check exists to refuse, fits above its "lower face" with 2.2 (and 2.1 on a
# bench person's, seen before the weight limit was set)
MODEL_CHECK_BELOW_M = 0.012
OCCLUDER_IN_FRONT_M = 0.010
OCCLUDED_SHARE = 0.1
OCCLUDED_MAX_WEIGHT = 1.75


def _model_weight(points: AnyArray, T: AnyArray, noise_m: float, params: FaceParams) -> float:
    """RMS prior-normalised weight of the face-model fit (`lsu_faces.identity`) around a nose candidate.

    A real nose is explained by identity weights of about one prior sigma each and a moderate expression;
    the surface around a cheek, brow or chin taken for a nose needs extreme weights to look like a face
    there. The fit sees the candidate's depth map in the frame of the registered generic face; where the
    lower face is covered by something in front of it, the face above it (``OCCLUDED_SHARE``).
    """
    from .identity import EXPRESSION_SIGMA, FIT_RADIUS_M, BasisError, IdentityFit, fit_signature, load_basis, model_map
    from .signature import Signature, SignatureError, cell_centres, make_signature

    def weight(fit: IdentityFit) -> float:
        b = load_basis()   # read once per process
        return float(np.sqrt(np.sum(fit.identity ** 2) / len(b.identity) + np.sum(fit.expression ** 2)
                             / (len(b.expression) * EXPRESSION_SIGMA ** 2)))

    frame = FaceFrame(T[:3, 3].copy(), T[:3, :3].T.copy())
    crop = points[np.linalg.norm(points - frame.origin, axis=1) <= params.crop_radius_m]
    try:
        # the same regularisation for every sensor (the threshold was set on time-of-flight scans): a
        # low-noise scan would otherwise buy fine detail with larger weights
        sig = make_signature(crop, frame, noise_m=max(float(noise_m), MODEL_CHECK_NOISE_M))
        whole = weight(fit_signature(sig))
        if whole <= params.max_model_weight:
            return whole
        g = sig.params
        c = cell_centres(g)   # rows run down (+y)
        below = (c[:, None] > MODEL_CHECK_BELOW_M) & (np.hypot(c[None, :], c[:, None]) <= FIT_RADIUS_M)
        upper_fit = fit_signature(Signature(sig.method, np.where(below, np.nan, sig.data), g, sig.points_used,
                                            sig.noise_m))
        in_front = sig.data[below] - model_map(upper_fit)[below]      # heights grow towards the scanner
        in_front = in_front[np.isfinite(in_front)]
        upper = weight(upper_fit)
        covered = len(in_front) > 0 and np.mean(in_front >= OCCLUDER_IN_FRONT_M) >= OCCLUDED_SHARE
        if covered and upper <= OCCLUDED_MAX_WEIGHT:
            return upper
        return whole
    except (SignatureError, BasisError):
        return float("inf")


def nose_tip(points: AnyArray, params: FaceParams = FaceParams()) -> NoseResult:
    """Nose tip with ``params.nose_method``."""
    if params.nose_method == "svd":
        return nose_tip_svd(points, params)
    if params.nose_method == "protrusion":
        return nose_tip_protrusion(points, params)
    return nose_tip_template(points, params)


def radial_vector(points: AnyArray, tip: AnyArray, params: FaceParams = FaceParams()) -> AnyArray:
    """Unit normal of the plane fitted to the points within ``radial_radius_m`` of the tip, out of the face."""
    p = np.asarray(points, dtype=np.float64)
    near = p[np.linalg.norm(p - tip, axis=1) <= params.radial_radius_m]
    if len(near) < 10:
        raise FaceError(f"only {len(near)} points within {params.radial_radius_m * 1000:.0f} mm of the nose tip")
    return _towards_camera(_plane_normal(near), tip)


def face_frame(tip: AnyArray, radial: AnyArray,
               up_hint: AnyArray | tuple[float, float, float] = (0.0, -1.0, 0.0)) -> FaceFrame:
    """Frame at the tip: z = radial vector, y = 'down' of the face taken from the camera's -``up_hint``."""
    z = np.asarray(radial, dtype=np.float64) / np.linalg.norm(radial)
    down = -np.asarray(up_hint, dtype=np.float64)
    y = down - down.dot(z) * z
    if np.linalg.norm(y) < 1e-6:
        y = np.cross(z, [1.0, 0.0, 0.0])
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    return FaceFrame(np.asarray(tip, dtype=np.float64).copy(), np.stack([x, y, z]))


def symmetric_frame(points: AnyArray, frame: FaceFrame, params: FaceParams = FaceParams(),
                    rounds: int = 2) -> FaceFrame:
    """Refine ``frame`` so that its x = 0 plane is the face's mirror-symmetry plane.

    The plane fitted around the nose is biased towards the side the scanner sees best (a turned head
    hides one cheek). Faces are mirror-symmetric: the face points mirrored in the frame's x = 0
    plane are aligned back onto the face by ICP (`lsu_faces.register`, point-to-plane, deterministic);
    the composed reflection is a reflection about the true symmetry plane, whose normal becomes the
    new x axis. The radial
    vector is kept in that plane, and the tip is moved onto it.
    """
    from .register import estimate_normals, icp_point_to_plane

    p = np.asarray(points, dtype=np.float64)
    local_all = frame.to_local(p)
    sel = np.linalg.norm(local_all, axis=1) <= params.crop_radius_m
    if sel.sum() < 50:
        return frame
    for _ in range(rounds):
        local = frame.to_local(p[sel])
        local = _voxel_means(local, params.sample_voxel_m)
        normals = estimate_normals(local, towards=np.array([0.0, 0.0, 1.0]))
        M = np.diag([-1.0, 1.0, 1.0])
        T = icp_point_to_plane(local @ M, local, normals, distances=(0.012, 0.005, 0.0025), iterations=15).T
        S = T[:3, :3] @ M                     # a reflection: its -1 eigenvector is the plane normal
        vals, vecs = np.linalg.eig(S)
        k = int(np.argmin(np.real(vals)))
        nx = np.real(vecs[:, k])
        nx /= np.linalg.norm(nx)
        if nx[0] < 0:
            nx = -nx
        # points x with S x + t = x lie on the plane: n . x = n . t / 2
        offset = 0.5 * float(nx @ T[:3, 3])
        axes_local = np.eye(3)
        z = axes_local[2] - (axes_local[2] @ nx) * nx
        z /= np.linalg.norm(z)
        y = np.cross(z, nx)
        new_axes_local = np.stack([nx, y, z])
        origin_local = offset * nx         # the old tip moved onto the plane
        # a failed mirror alignment (too little overlap) shows as a big jump: keep the frame we had
        if abs(offset) > params.max_symmetry_shift_m or nx[0] < np.cos(np.radians(35.0)):
            break
        frame = FaceFrame(frame.origin + origin_local @ frame.axes, new_axes_local @ frame.axes)
    return _profile_pitch(p[sel], frame, params)


def _profile_pitch(points: AnyArray, frame: FaceFrame, params: FaceParams) -> FaceFrame:
    """Tilt the radial vector (about the frame's x axis) perpendicular to the face's profile line.

    The profile (face points near the symmetry plane, away from the nose) runs from the forehead to the
    chin; its principal direction is the face's vertical whatever the nod, while the plane fitted
    around the nose leans towards the camera.
    """
    local = frame.to_local(points)
    r = np.linalg.norm(local, axis=1)
    prof = local[(np.abs(local[:, 0]) < 0.004) & (r > 0.03)]
    above, below = prof[prof[:, 1] < 0], prof[prof[:, 1] > 0]
    if len(above) < 10 or len(below) < 10:
        return frame   # forehead or chin missing: keep the fitted plane's direction
    yz = prof[:, 1:] - prof[:, 1:].mean(axis=0)
    _, _, vt = np.linalg.svd(yz, full_matrices=False)
    d = vt[0] if vt[0][0] > 0 else -vt[0]          # (y, z) of the profile direction, pointing down
    angle = np.arctan2(d[1], d[0])                 # lean of the profile towards +z (out of the face)
    c, s_ = np.cos(angle), np.sin(angle)
    # rotate y and z about x so that the profile direction becomes the new y
    y = c * frame.axes[1] + s_ * frame.axes[2]
    z = -s_ * frame.axes[1] + c * frame.axes[2]
    return FaceFrame(frame.origin, np.stack([frame.axes[0], y, z]))


def crop_face(points: AnyArray, tip: AnyArray, params: FaceParams = FaceParams()) -> AnyArray:
    """Mask of the points within ``crop_radius_m`` of the nose tip (the face, without hair, ears and neck)."""
    return np.linalg.norm(np.asarray(points) - tip, axis=1) <= params.crop_radius_m


def embed_face(points: AnyArray, params: FaceParams = FaceParams(),
               nose: NoseResult | None = None) -> tuple[NoseResult, FaceFrame, AnyArray]:
    """Nose tip, face frame and the mask of the cropped face points, in one call."""
    p = _check(points, params)
    nose = nose or nose_tip(p, params)
    if nose.frame is not None:       # the template method's frame is already the symmetric face frame
        return nose, nose.frame, crop_face(p, nose.frame.origin, params)
    frame = face_frame(nose.tip, nose.normal if nose.method == "protrusion" else radial_vector(p, nose.tip, params))
    frame = symmetric_frame(p, frame, params)
    return nose, frame, crop_face(p, frame.origin, params)

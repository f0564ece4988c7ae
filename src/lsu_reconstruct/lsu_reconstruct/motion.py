"""The subject's motion during a sweep, measured from the scan's own frames, and its correction (numpy, no rclpy).

A sweep takes seconds; a person sways, breathes and turns meanwhile (docs/MOTION.md). The laser line only
samples one curve of the face per frame, and curves taken at different times do not overlap, so the line
alone cannot tell a moving face from a differently shaped one. Every frame also shows the face's texture
in the room light around the line: the frames are a video of the face. Its image motion against a
reference frame (dense optical flow, OpenCV's DIS, on the blue channel where the red laser adds ~5 %, with
the laser lines of both frames masked out) at the pixels where the scan's own points project, in both
cameras, is the projection of one rigid motion of those points: a 6-parameter fit (rotation about the
points' centre and translation, robust loss) per measured frame gives the head's pose relative to the
reference frame's (`estimate_motion`). The poses are smoothed over ~0.5 s (`smoothed_poses`): their scatter
about the smoothed track is the measurement's own noise for this scan. Poses between measured frames are
interpolated linearly in time.

Correction (`MotionEstimate.correct`): each point moved from its frame's pose back to the reference
frame's, so that every line lies on one head before meshing. A motion within the measurement's noise
(`MotionParams.min_motion_mm`, `MotionParams.min_motion_ratio` x this scan's noise) leaves the scan as it is.

Beyond what can be corrected (`MotionParams`): a fit that does not explain the flow (few inliers or a large
residual: the face turned so far that its image changed, a blink, an occlusion), a rotation beyond
``max_rotation_deg`` from the reference (the other side of the face appears, masking by the nose changes),
or a surface speed beyond ``max_speed_mm_s`` (a line smears over its exposure, the interpolation between
measured frames no longer holds). Those frames are unreliable; a scan with any is flagged
(`MotionEstimate.flagged`), and `motion_record` says which frames and carriage positions.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from lsu_common.arrays import AnyArray

from .matching import LineArrays
from .stereo import StereoModel

__all__ = ["MotionParams", "MotionEstimate", "estimate_motion", "motion_record", "HOLD_STILL", "MotionError",
           "SweepMotion", "beyond_noise", "smoothed_poses"]

HOLD_STILL = "hold still, scanning again"


class MotionError(ValueError):
    """The motion cannot be measured from what was given; the message says what is missing."""


@dataclass(frozen=True)
class MotionParams:
    """How the motion is measured and what is beyond correction (module doc)."""

    every_frames: int = 3              # measure every Nth frame (10 Hz at 30 fps: sway is below 1 Hz)
    mask_px: int = 12                  # pixels either side of a laser line left out of the flow
    # scan points (seeded subsample) whose image motion is fitted: the fit's cost is per point; 2000 measured the
    # sweeps of bench_scan's motion part as well as 4000 at half the fit's CPU
    model_points: int = 2000
    inlier_px: float = 1.0             # a point's fit residual below this is an inlier
    max_residual_px: float = 0.8       # RMS of the inliers' residuals beyond which a frame is unreliable
    # share of the points that must be inliers: on simulated sweeps of person:2 and person:5 a rigidly moving head
    # gives 0.49..0.97 (the low end on short sweeps across a pose update), a head turned 15 deg from the reference
    # 0.01..0.09
    min_inlier_share: float = 0.3
    max_rotation_deg: float = 5.0      # rotation from the reference frame beyond which a frame is unreliable
    max_speed_mm_s: float = 40.0       # fastest point speed between measured frames beyond which it is unreliable
    # a measured motion whose fitted points move less than this over the scan may be the measurement's noise
    # (up to ~1 mm on a still simulated face, pose by pose): then it counts only by min_motion_ratio
    min_motion_mm: float = 1.5
    # the poses are smoothed by a straight line through the measured frames within smooth_s / 2 of each (sway is
    # below 1 Hz, the measurement's noise differs frame to frame); where >= 3 frames fall in it, the scatter about
    # those lines is the measurement's own noise, and a smoothed motion this many times that noise is real even below
    # min_motion_mm (a seated person's slow drift). 0 s: the poses as measured, min_motion_mm alone
    smooth_s: float = 0.5
    min_motion_ratio: float = 2.7
    seed: int = 0

    def __post_init__(self) -> None:
        if self.every_frames < 1 or self.model_points < 12 or self.mask_px < 0:
            raise MotionError("every_frames >= 1, model_points >= 12 and mask_px >= 0 are needed")
        if self.smooth_s < 0 or self.min_motion_ratio <= 0:
            raise MotionError("smooth_s >= 0 and min_motion_ratio > 0 are needed")


def _rotation(rvec: AnyArray) -> AnyArray:
    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))
    return R


def _moved(points: AnyArray, vector: AnyArray, centre: AnyArray) -> AnyArray:
    """``points`` (reference pose) where the pose ``vector`` (rotation vector [rad], d [m]) puts them:
    R (X - c) + c + d (`MotionEstimate`)."""
    return (points - centre) @ _rotation(vector[:3]).T + centre + vector[3:]


@dataclass
class MotionEstimate:
    """The head's pose per measured frame relative to the reference frame's: ``X_frame = R (X_ref - c) + c + d``.

    ``vectors``: (M,6) rotation vector [rad] and d [m]; ``centre`` c: the fitted points' centre (left frame).
    """

    frames: AnyArray                  # (M,) measured frame indices, ascending
    times_s: AnyArray                 # (M,) their times (left mid-exposure)
    vectors: AnyArray                 # (M,6)
    centre: AnyArray                  # (3,)
    reference_frame: int
    residual_px: AnyArray             # (M,) RMS of the inliers' residuals
    inlier_share: AnyArray            # (M,)
    speed_mm_s: AnyArray              # (M,) fastest point speed from the previous measured frame
    reliable: AnyArray                # (M,) bool
    reasons: list[str] = field(default_factory=list)  # per measured frame: why unreliable ('' when reliable)
    measured_mm: float = 0.0          # the largest displacement of the fitted points over the scan (smoothed poses)
    significant: bool = True          # beyond the noise (`MotionParams.min_motion_mm`, `min_motion_ratio`); else zeroed
    noise_mm: float = float("nan")    # RMS displacement of the measured poses about the smoothed ones (NaN: too few)
    smoothed: bool = False            # ``vectors`` are the smoothed poses (a slow drift), not the measured ones

    @property
    def flagged(self) -> bool:
        """Some of the scan is beyond correction."""
        return bool(np.any(~self.reliable))

    def vectors_at(self, t_s: AnyArray) -> AnyArray:
        """(N,6) pose vectors at times ``t_s``, linear between measured frames, held beyond them."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        return np.stack([np.interp(t, self.times_s, self.vectors[:, k]) for k in range(6)], axis=1)

    def reliable_at(self, t_s: AnyArray) -> AnyArray:
        """(N,) bool: both measured frames around each time are reliable."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        hi = np.clip(np.searchsorted(self.times_s, t, side="left"), 0, len(self.times_s) - 1)
        lo = np.clip(hi - 1, 0, len(self.times_s) - 1)
        exact = np.isclose(self.times_s[hi], t)
        return self.reliable[hi] & (exact | self.reliable[lo])

    def correct(self, xyz: AnyArray, t_s: AnyArray) -> AnyArray:
        """Points (N,3) seen at times ``t_s`` (N,) moved back to the reference frame's pose."""
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        if not np.any(self.vectors):
            return xyz.copy()  # no motion (within the noise): the points exactly as they were
        t = np.broadcast_to(np.asarray(t_s, dtype=np.float64), (len(xyz),))
        out = np.empty_like(xyz)
        # points of one frame share its time: one rotation per distinct time
        times, inverse = np.unique(t, return_inverse=True)
        vec = self.vectors_at(times)
        for k in range(len(times)):
            sel = inverse == k
            R = _rotation(vec[k, :3])
            out[sel] = (xyz[sel] - self.centre - vec[k, 3:]) @ R + self.centre
        return out


def _gray(image: AnyArray, crop: tuple[slice, slice] = (slice(None), slice(None))) -> AnyArray:
    """The blue channel of a BGR frame (the red laser adds ~5 % there), or the frame itself if grey, within ``crop``
    (`_crop`), as one contiguous copy."""
    img = np.asarray(image)
    return np.ascontiguousarray(img[crop + (0,)] if img.ndim == 3 else img[crop])


def _line_mask(line: LineArrays, shape: tuple[int, int], half_px: int) -> AnyArray:
    """bool (H,W): pixels within ``half_px`` columns of the line's samples (the laser and its glow)."""
    mask = np.zeros(shape, np.uint8)
    if len(line.u):
        u = np.clip(np.rint(line.u).astype(np.int64), 0, shape[1] - 1)
        v = np.clip(np.rint(line.v).astype(np.int64), 0, shape[0] - 1)
        mask[v, u] = 1
        mask = cv2.dilate(mask, np.ones((2 * half_px + 1, 2 * half_px + 1), np.uint8))
    return mask.astype(bool)


def _flow(ref: AnyArray, img: AnyArray) -> AnyArray:
    """Dense flow (H,W,2) from ``ref`` to ``img``: OpenCV's DIS (coarse-to-fine patches, follows a sway's ~20 px).

    Farneback's flow was 10x quieter on a still face but did not follow a swaying one on the simulated skin.
    """
    engine = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)  # type: ignore[attr-defined]
    return engine.calc(ref, img, None)


# pixels of texture around the fitted points' bounding box that the flow is computed on: more than a sway's ~20 px
# image motion, and room for DIS's coarsest patches
FLOW_MARGIN_PX = 48


def _crop(uv: AnyArray, shape: tuple[int, int]) -> tuple[slice, slice]:
    """(rows, columns) of the image around the pixels ``uv`` (N,2), widened by `FLOW_MARGIN_PX`."""
    lo = np.floor(uv.min(axis=0)).astype(int) - FLOW_MARGIN_PX
    hi = np.ceil(uv.max(axis=0)).astype(int) + FLOW_MARGIN_PX + 1
    return slice(max(lo[1], 0), min(hi[1], shape[0])), slice(max(lo[0], 0), min(hi[0], shape[1]))


def _sample(field2: AnyArray, uv: AnyArray) -> AnyArray:
    """Bilinear samples (N,2) of a 2-channel float32 image at pixels ``uv`` (N,2)."""
    maps = np.ascontiguousarray(uv.astype(np.float32).reshape(-1, 1, 2))
    return cv2.remap(field2, maps, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(-1, 2)


def estimate_motion(model: StereoModel, images: Sequence[tuple[AnyArray, AnyArray]], times_s: Sequence[float] | AnyArray,
                    lines: Sequence[tuple[LineArrays, LineArrays]], cloud_xyz: AnyArray,
                    params: MotionParams = MotionParams(), reference_frame: int | None = None) -> MotionEstimate:
    """The head's motion over a sweep's frames (module doc).

    ``images``: every frame's (left, right) BGR or grey pair; ``times_s``: each frame's time (left
    mid-exposure); ``lines``: each frame's extracted (left, right) laser lines (masked out of the flow);
    ``cloud_xyz``: the scan's points as reconstructed (left frame, m): where the surface is. The reference
    frame (default: the middle one) is the pose the corrected scan is delivered in.
    """
    from scipy.optimize import least_squares  # here: the matcher imports this module at start, scipy is ~0.5 s

    n = len(images)
    if n == 0 or len(times_s) != n or len(lines) != n:
        raise MotionError(f"need one time and one pair of lines per frame: {n} frames, {len(times_s)} times, "
                          f"{len(lines)} line pairs")
    cloud = np.asarray(cloud_xyz, dtype=np.float64).reshape(-1, 3)
    cloud = cloud[np.all(np.isfinite(cloud), axis=1)]
    if len(cloud) < params.model_points // 4:
        raise MotionError(f"the scan has {len(cloud)} points: too few to follow the subject's motion")
    ref = n // 2 if reference_frame is None else int(reference_frame)
    if not 0 <= ref < n:
        raise MotionError(f"reference frame {ref} is not one of the {n} frames")
    times = np.asarray(times_s, dtype=np.float64)
    H, W = np.asarray(images[0][0]).shape[:2]
    rng = np.random.default_rng(params.seed)
    pick = rng.choice(len(cloud), size=min(params.model_points, len(cloud)), replace=False)
    X = cloud[np.sort(pick)]
    centre = X.mean(axis=0)
    uv = [model.project_left(X), model.project_right(X)]
    inside = np.all([(p[:, 0] >= 1) & (p[:, 0] <= W - 2) & (p[:, 1] >= 1) & (p[:, 1] <= H - 2) for p in uv], axis=0)
    X, uv = X[inside], [p[inside] for p in uv]
    # the flow is computed on the points' bounding box widened by FLOW_MARGIN_PX (about half of a person's frame):
    # DIS's cost is per pixel, and only the flow at the points is used
    crops = [_crop(p, (H, W)) for p in uv]
    ref_gray = [_gray(images[ref][k], crops[k]) for k in range(2)]
    uv_crop = [p - np.array([c[1].start, c[0].start], float) for p, c in zip(uv, crops)]
    ref_masks = [_line_mask(lines[ref][k], (H, W), params.mask_px) for k in range(2)]
    measured = sorted(set(range(0, n, params.every_frames)) | {n - 1, ref})

    def project(x: AnyArray, Xw: AnyArray) -> list[AnyArray]:
        # x: rotation [mrad] and d [mm]: the scales of a head's sway, for a well-conditioned fit
        moved = _moved(Xw, x * 1e-3, centre)
        return [model.project_left(moved), model.project_right(moved)]

    vectors = np.zeros((len(measured), 6))
    residual = np.zeros(len(measured))
    share = np.zeros(len(measured))
    x0 = np.zeros(6)
    order = sorted(range(len(measured)), key=lambda i: (abs(measured[i] - ref), measured[i]))
    for i in order:
        k = measured[i]
        if k == ref:
            vectors[i], share[i] = 0.0, 1.0
            continue
        targets, keep = [], np.ones(len(X), bool)
        for cam in range(2):
            flow = _flow(ref_gray[cam], _gray(images[k][cam], crops[cam]))
            mask = ref_masks[cam] | _line_mask(lines[k][cam], (H, W), params.mask_px)
            pix = np.rint(uv[cam]).astype(np.int64)
            keep &= ~mask[pix[:, 1], pix[:, 0]]
            targets.append(uv[cam] + _sample(flow, uv_crop[cam]))
        if np.count_nonzero(keep) < 12:
            vectors[i], residual[i], share[i] = np.nan, np.inf, 0.0
            continue
        Xk, tk = X[keep], [t[keep] for t in targets]

        def fun(x: AnyArray, Xk: AnyArray = Xk, tk: list = tk) -> AnyArray:
            p = project(x, Xk)
            return np.concatenate([(p[0] - tk[0]).ravel(), (p[1] - tk[1]).ravel()])

        # start from the nearest measured frame towards the reference (already fitted): sway is smooth
        nearer = [j for j in range(len(measured)) if abs(measured[j] - ref) < abs(k - ref)
                  and np.all(np.isfinite(vectors[j]))]
        if nearer:
            j = min(nearer, key=lambda j: abs(measured[j] - k))
            x0 = np.r_[vectors[j, :3] * 1e3, vectors[j, 3:] * 1e3]
        fit = least_squares(fun, x0, loss="soft_l1", f_scale=0.5 * params.inlier_px, method="trf")
        err = np.hypot(*fit.fun.reshape(2, -1, 2).transpose(2, 0, 1)).ravel()
        inl = err < params.inlier_px
        share[i] = float(np.mean(inl))
        residual[i] = float(np.sqrt(np.mean(err[inl] ** 2))) if np.any(inl) else np.inf
        vectors[i] = np.r_[fit.x[:3] * 1e-3, fit.x[3:] * 1e-3]
    frames = np.asarray(measured)
    t_m = times[frames]
    speed = np.zeros(len(measured))
    reasons = []
    corners = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], float)
    lo_b, hi_b = X.min(axis=0), X.max(axis=0)
    box = lo_b + corners * (hi_b - lo_b)   # the fitted points' bounding box: its corners move fastest
    boxes = [_moved(box, v, centre) if np.all(np.isfinite(v)) else None for v in vectors]
    for i in range(1, len(measured)):
        now, before = boxes[i], boxes[i - 1]
        if now is not None and before is not None and t_m[i] > t_m[i - 1]:
            speed[i] = float(np.max(np.linalg.norm(now - before, axis=1)) / (t_m[i] - t_m[i - 1]) * 1e3)
    for i in range(len(measured)):
        why = []
        if not np.all(np.isfinite(vectors[i])):
            why.append("no texture left to follow")
        else:
            if share[i] < params.min_inlier_share or residual[i] > params.max_residual_px:
                why.append(f"the image moved unlike a rigid head ({100 * share[i]:.0f} % inliers, "
                           f"{residual[i]:.2f} px)")
            angle = float(np.degrees(np.linalg.norm(vectors[i, :3])))
            if angle > params.max_rotation_deg:
                why.append(f"turned {angle:.1f} deg")
        # a fast move spoils both measured frames around it
        fast = max(speed[i], speed[i + 1] if i + 1 < len(measured) else 0.0)
        if fast > params.max_speed_mm_s:
            why.append(f"moved at {fast:.0f} mm/s")
        reasons.append("; ".join(why))
    fitted = np.all(np.isfinite(vectors), axis=1)
    vectors = np.where(np.isfinite(vectors), vectors, 0.0)
    reliable = np.array([not r for r in reasons])
    # the limits above judge each measured pose; the verdict takes the smoothed ones (a frame without a fit counts
    # as unmoved: its pose is zero from here on)
    smoothed, noise = smoothed_poses(t_m, vectors, fitted, measured.index(ref), 0.5 * params.smooth_s, box, centre)
    moved = max(_box_shift_mm(box, v, centre) for v in smoothed)
    significant = beyond_noise(moved, noise, params)
    # the correction: a drift below min_motion_mm (real only by min_motion_ratio) is slow and of the noise's size, the
    # smoothed poses follow it; a larger motion moves faster, and a line over smooth_s cuts its turns: as measured
    drift = moved < params.min_motion_mm
    if drift:
        vectors = smoothed
    if not significant and reliable.all():
        vectors = np.zeros_like(vectors)
    return MotionEstimate(frames, t_m, vectors, centre, ref, residual, share, speed, reliable, reasons,
                          measured_mm=moved, significant=significant, noise_mm=noise,
                          smoothed=drift and bool(np.isfinite(noise)))


def beyond_noise(moved_mm: float, noise_mm: float, params: MotionParams) -> bool:
    """Whether a smoothed motion of ``moved_mm`` is real (`MotionParams.min_motion_mm`, ``min_motion_ratio`` x the
    scan's measured noise ``noise_mm``, NaN: unknown) and so corrected."""
    return bool(moved_mm >= params.min_motion_mm or (np.isfinite(noise_mm) and moved_mm >= params.min_motion_ratio * noise_mm))


def _box_shift_mm(box: AnyArray, vector: AnyArray, centre: AnyArray) -> float:
    """The largest displacement [mm] of the corners ``box`` (K,3) under the pose ``vector``."""
    return float(np.max(np.linalg.norm(_moved(box, vector, centre) - box, axis=1))) * 1e3


# frames with a smoothed pose needed before their scatter is taken as the measurement's noise
MIN_NOISE_FRAMES = 6


def smoothed_poses(times: AnyArray, vectors: AnyArray, fitted: AnyArray, ref: int, half_s: float, box: AnyArray,
                    centre: AnyArray) -> tuple[AnyArray, float]:
    """Poses (M,6) on a straight line through the fitted frames within ``half_s`` of each (where >= 3 are), zero at
    the reference ``ref``; and the measurement's noise: the RMS displacement [mm] of ``box`` under the measured
    poses' differences from those lines. Below `MIN_NOISE_FRAMES` such frames: the poses as measured, noise NaN."""
    if half_s <= 0:
        return vectors, float("nan")
    line = vectors.copy()
    smoothed = np.zeros(len(times), bool)
    for i, t in enumerate(times):
        near = fitted & (np.abs(times - t) <= half_s * (1 + 1e-9))
        if np.count_nonzero(near) >= 3 and fitted[i]:
            line[i] = np.polyfit(times[near] - t, vectors[near], 1)[1]   # the line's value at t
            smoothed[i] = True
    if np.count_nonzero(smoothed) < MIN_NOISE_FRAMES:
        return vectors, float("nan")
    noise = float(np.sqrt(np.mean([_box_shift_mm(box, d, centre) ** 2 for d in (vectors - line)[smoothed]])))
    # the reference frame's pose is zero by definition: the smoothed poses are relative to its smoothed one
    return np.where(fitted[:, None], line - line[ref], 0.0), noise


def motion_record(estimate: MotionEstimate, positions_steps: Sequence[float] | Mapping[int, float] | None = None,
                  corrected: bool = True) -> dict:
    """What scan.json (and the bag's record) says of the motion: per measured frame its time, pose, fit and
    reliability; the verdict; the unreliable frames' carriage positions when ``positions_steps`` (per frame)."""
    bad = [int(f) for f, ok in zip(estimate.frames, estimate.reliable) if not ok]
    record: dict = {
        "method": "texture flow of the sweep's frames, rigid fit in both cameras",
        "reference_frame": int(estimate.reference_frame),
        "centre_m": [float(c) for c in estimate.centre],
        "frames": [int(f) for f in estimate.frames],
        "times_s": [round(float(t), 6) for t in estimate.times_s],
        "rotation_vector_rad": [[round(float(a), 7) for a in v[:3]] for v in estimate.vectors],
        "translation_m": [[round(float(a), 7) for a in v[3:]] for v in estimate.vectors],
        "residual_px": [round(float(r), 4) if np.isfinite(r) else None for r in estimate.residual_px],
        "inlier_share": [round(float(s), 4) for s in estimate.inlier_share],
        "speed_mm_s": [round(float(s), 2) for s in estimate.speed_mm_s],
        "reliable": [bool(r) for r in estimate.reliable],
        "max_translation_mm": float(1e3 * np.max(np.linalg.norm(estimate.vectors[:, 3:], axis=1))),
        "max_rotation_deg": float(np.degrees(np.max(np.linalg.norm(estimate.vectors[:, :3], axis=1)))),
        "measured_motion_mm": round(float(estimate.measured_mm), 3),
        "noise_mm": round(float(estimate.noise_mm), 3) if np.isfinite(estimate.noise_mm) else None,
        "poses_smoothed": bool(estimate.smoothed),
        "beyond_noise": bool(estimate.significant),
        "corrected": bool(corrected and estimate.significant),
        "flagged": estimate.flagged,
        "unreliable_frames": bad,
        "reasons": {str(f): r for f, r in zip(estimate.frames, estimate.reasons) if r},
    }
    if positions_steps is not None and bad:
        pos = [float(positions_steps[f]) for f in bad]
        record["unreliable_positions_steps"] = [min(pos), max(pos)]
    if estimate.flagged:
        record["message"] = HOLD_STILL
    return record


class SweepMotion:
    """A sweep's frames as the live graph hands them over, for `estimate_motion` and the correction (pure).

    The matcher node gives every frame placed (`add_frame`: its index, its time, its laser lines) and, for
    the frames `wants` (every ``params.every_frames``-th index), the pair's images (one channel is enough:
    `_gray`). At the scan's end `correct` measures the motion on those frames alone (their decimation is the
    measurement's, so `estimate_motion` runs with ``every_frames`` 1) and moves the cloud's points, each
    by its frame index, back to the reference frame's pose when the motion is measured and within limits.
    """

    # fewer measured frames than this: the sweep is too short to follow the motion (its points all lie near the
    # laser lines masked out of the flow), it is said so rather than flagged
    MIN_FRAMES = 6
    # measured frames at most (`for_sweep`; the node's motion_max_frames): every 6th of a 30 fps face sweep, ~5 Hz, so
    # that `smoothed_poses` finds 3 frames in its 0.5 s; each costs two dense flows before the cloud is out
    MAX_FRAMES = 32

    def __init__(self, params: MotionParams = MotionParams()) -> None:
        self.params = params
        self.times_s: dict[int, float] = {}
        self.positions_steps: dict[int, float] = {}
        self._measured: dict[int, tuple[AnyArray, AnyArray, LineArrays, LineArrays]] = {}
        self._lines: dict[int, tuple[LineArrays, LineArrays]] = {}  # measured frames still without their images

    def wants(self, index: int) -> bool:
        """Whether frame ``index``'s images are measured."""
        return index % self.params.every_frames == 0

    def add_frame(self, index: int, time_s: float, left: LineArrays, right: LineArrays,
                  images: tuple[AnyArray, AnyArray] | None = None, position_steps: float | None = None) -> None:
        """One frame placed: its time (left mid-exposure), lines and, when `wants` it, its images."""
        self.times_s[int(index)] = float(time_s)
        if position_steps is not None:
            self.positions_steps[int(index)] = float(position_steps)
        if images is not None:
            self._measured[int(index)] = (images[0], images[1], left, right)
        elif self.wants(index):
            self._lines[int(index)] = (left, right)

    def add_images(self, index: int, images: tuple[AnyArray, AnyArray]) -> bool:
        """The images of a frame added before them (they came after its lines); False if it is not waiting for them."""
        lines = self._lines.pop(int(index), None)
        if lines is None:
            return False
        self._measured[int(index)] = (images[0], images[1], *lines)
        return True

    @property
    def measured_frames(self) -> int:
        return len(self._measured)

    @classmethod
    def for_sweep(cls, expected_frames: int, params: MotionParams = MotionParams(),
                  max_frames: int = MAX_FRAMES) -> SweepMotion:
        """A sweep of ``expected_frames`` measured on every ``params.every_frames``-th frame, fewer if that would be
        more than ``max_frames`` frames (each costs two dense flows at the scan's end, before its cloud is out)."""
        every = max(params.every_frames, -(-int(expected_frames) // max(1, int(max_frames))))
        return cls(dataclasses.replace(params, every_frames=every))

    def correct(self, model: StereoModel, xyz: AnyArray, frame_index: AnyArray,
                apply: bool = True) -> tuple[AnyArray, dict]:
        """The points (N,3) of frames ``frame_index`` (N,) corrected, and the scan.json ``motion`` record.

        Left as they are when the motion cannot be measured (the record says why), when it is within the
        measurement's noise, when some of it is beyond correction (flagged: the record says which frames and
        why; a sheared scan is better rescanned than bent) or when ``apply`` is false.
        """
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        index = np.asarray(frame_index, dtype=np.int64).reshape(-1)
        keys = sorted(self._measured)
        if len(keys) < self.MIN_FRAMES:
            return xyz.copy(), {"measured": False, "flagged": False, "corrected": False,
                                "why": f"{len(keys)} frames with images, every {self.params.every_frames}th: too few to "
                                       f"follow the subject's motion (a sweep of at least {self.MIN_FRAMES} x "
                                       f"{self.params.every_frames} frames is needed)"}
        missing = sorted(set(np.unique(index).tolist()) - set(self.times_s))
        if missing:
            raise MotionError(f"points of frames {missing[:5]} without a frame time: add_frame every frame first")
        try:
            estimate = estimate_motion(model, [self._measured[k][:2] for k in keys], [self.times_s[k] for k in keys],
                                       [self._measured[k][2:] for k in keys], xyz,
                                       dataclasses.replace(self.params, every_frames=1))
        except MotionError as exc:
            return xyz.copy(), {"measured": False, "flagged": False, "corrected": False, "why": str(exc)}
        usable = apply and not estimate.flagged
        times = np.array([self.times_s[int(k)] for k in index]) if len(index) else np.zeros(0)
        out = estimate.correct(xyz, times) if usable else xyz.copy()
        # the estimate's frames are positions in the measured list: the record names the sweep's frame indices
        estimate.frames = np.asarray([keys[int(i)] for i in estimate.frames])
        estimate.reference_frame = keys[int(estimate.reference_frame)]
        positions = None
        if all(k in self.positions_steps for k in keys):
            positions = {k: self.positions_steps[k] for k in keys}
        record = {"measured": True, **motion_record(estimate, positions, corrected=usable),
                  "measured_frames": len(keys), "every_frames": self.params.every_frames}
        return out, record

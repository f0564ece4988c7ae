"""The simulated stereo rig: ray-cast images of a scene lit by the laser sheet, with exact ground truth.

Per camera, every pixel's ray is cast once per scene (open3d ``RaycastingScene``) and everything
that does not depend on the carriage is cached: hit points, smooth normals, albedo, the ambient +
lamp + highlight image, and the hit points' signed distance to the sheet's normal direction. The
light sheet keeps its orientation along the track, so a new carriage position only changes the
sheet's offset ``c``: the laser term is a Gaussian of ``n . P - c`` evaluated on the few pixels
near the sheet. A capture integrates that term over the exposure (``sub_exposures`` offsets
following the post-stop vibration, from each camera's own exposure start: ``capture_offset_s`` and
``capture_jitter_s``), multiplies it by the camera's laser speckle, broadens and shifts it on skin,
then adds lens blur, saturation with blooming, the optional Bayer mosaic, shot + read noise, 8-bit
quantisation (and demosaicing). `physics` documents each effect and its sources. A constant-rate
motion is averaged over the exposure in closed form, and the sensor steps run on the laser's
rectangle of the image (`SimulatedRig.render`); a pixel's shadow ray is cast once per subject pose, from
the laser origin whose sheet centre holds it (`SimulatedRig._lit_at_own_origin`). ``reference=True``
renders the plain way, sub-exposure by sub-exposure, on the whole image and with a shadow ray per pixel
and frame, which the tests and the benchmark compare against.

Pixel integration: the laser sheet is only ~2.5 px thick, so sampling it at pixel centres would
alias. Over one pixel ``n . P`` is close to linear (slope g per pixel), and the box average of a
Gaussian over such a ramp is, to second order, a Gaussian of variance ``sigma^2 + g^2/12`` with
the same integral: the rendered line keeps the exact centre and energy of the real one.

Ground truth (`laser_truth`): for every image row and every crossing of the sheet along it, the
column where the pixel's ray meets the surface exactly on the sheet's centre plane is found by
regula falsi on real ray casts (float32 ray casting: ~3e-8 m), giving the 3D point (left frame),
its pixel in this camera (OpenCV ``projectPoints``) and its pixel/visibility in the other camera.
The truth describes the sheet at the carriage's rest position: vibration is an error source.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import open3d as o3d

from lsu_common.arrays import AnyArray

from .geometry import CameraModel, RigGeometry
from .physics import (
    KernelScale,
    SpeckleField,
    bloom,
    demosaic,
    mosaic,
    noise_window,
    skin_profile,
    skin_profile_box,
    skin_profile_tails,
    surface_profile_box,
)
from .scenes import SceneObject


@dataclass
class CarriageState:
    """Where the laser carriage really is (mirrors ``lsu_interfaces/msg/SimTruth``; times in seconds).

    Post-stop vibration: ``displacement(t) = A exp(-(t - t0) / tau) cos(2 pi f (t - t0))`` for
    ``t >= t0 = stopped_at_s``; ``stopped_at_s = None`` means settled long ago.
    Constant-rate motion (a sweep): ``velocity_steps_per_s`` != 0 with ``position_steps`` the position
    at ``position_time_s``; the displacement is then ``velocity (t - position_time_s)`` (no vibration).
    A motion that starts or stops during a frame's exposures has ``motion_start_s`` / ``motion_stop_s``:
    the carriage rests before the start, and after the stop vibrates as above with ``t0 = motion_stop_s``.
    """

    position_steps: float
    laser_on: bool = True
    stopped_at_s: float | None = None
    vibration_amplitude_steps: float = 0.0
    vibration_tau_s: float = 0.05
    vibration_freq_hz: float = 30.0
    velocity_steps_per_s: float = 0.0
    position_time_s: float | None = None
    motion_start_s: float | None = None
    motion_stop_s: float | None = None

    @property
    def moving(self) -> bool:
        """The carriage moves at a constant rate and the time of ``position_steps`` is known."""
        return self.velocity_steps_per_s != 0.0 and self.position_time_s is not None

    def displacement_steps(self, t_s: AnyArray) -> AnyArray:
        """Displacement from ``position_steps`` [steps] at times ``t_s``: the motion, or the post-stop vibration."""
        t = np.asarray(t_s, dtype=np.float64)
        if self.moving:
            lo = -np.inf if self.motion_start_s is None else self.motion_start_s
            hi = np.inf if self.motion_stop_s is None else self.motion_stop_s
            travel = self.velocity_steps_per_s * (np.clip(t, lo, hi) - float(self.position_time_s))  # type: ignore[arg-type]
            if self.motion_stop_s is None:
                return travel
            return travel + np.where(t >= self.motion_stop_s, self._vibration(t, self.motion_stop_s), 0.0)
        return self._vibration(t, self.stopped_at_s)

    def _vibration(self, t: AnyArray, stopped_at_s: float | None) -> AnyArray:
        if stopped_at_s is None or self.vibration_amplitude_steps == 0.0 or self.vibration_tau_s <= 0.0:
            return np.zeros_like(t)
        dt = np.maximum(t - stopped_at_s, 0.0)
        return (self.vibration_amplitude_steps * np.exp(-dt / self.vibration_tau_s)
                * np.cos(2.0 * np.pi * self.vibration_freq_hz * dt))


@dataclass
class CameraTruth:
    """Exact laser-line samples seen by one camera: one per (row, crossing)."""

    points_m: AnyArray          # (N,3) on surface and sheet centre plane, left optical frame
    pixels: AnyArray            # (N,2) distorted (u, v) in this camera; v is the integer row
    other_pixels: AnyArray      # (N,2) the same points in the other camera
    other_visible: AnyArray     # (N,) bool: the other camera sees the point (inside the image, not occluded)


@dataclass
class LaserTruth:
    """Ground truth of one laser position for both cameras."""

    position_steps: float
    plane_normal: AnyArray      # n, with the sheet centre plane n . X = plane_offset_m (left frame)
    plane_offset_m: float
    left: CameraTruth
    right: CameraTruth

    def to_npz(self, path: str | os.PathLike) -> None:
        """Save as an .npz (keys: position_steps, plane_normal, plane_offset_m, {left,right}_{points_m,...})."""
        arrays: dict[str, Any] = {"position_steps": np.array(self.position_steps),
                                         "plane_normal": self.plane_normal, "plane_offset_m": np.array(self.plane_offset_m)}
        for side in ("left", "right"):
            cam = getattr(self, side)
            for key in ("points_m", "pixels", "other_pixels", "other_visible"):
                arrays[f"{side}_{key}"] = getattr(cam, key)
        np.savez_compressed(path, **arrays)

    @classmethod
    def from_npz(cls, path: str | os.PathLike) -> LaserTruth:
        """Load what `to_npz` wrote."""
        with np.load(path) as z:
            cams = [CameraTruth(*(z[f"{side}_{k}"] for k in ("points_m", "pixels", "other_pixels", "other_visible")))
                    for side in ("left", "right")]
            return cls(float(z["position_steps"]), z["plane_normal"], float(z["plane_offset_m"]), *cams)


@dataclass
class StereoFrame:
    """One rendered pair (BGR uint8) and what produced it."""

    left: AnyArray
    right: AnyArray
    position_steps: float
    laser_on: bool
    capture_time_s: float | None
    laser_offset_steps: float = 0.0           # mean displacement (vibration or motion) over the left camera's exposure
    truth: LaserTruth | None = None
    # per camera (left, right): exposure start [s] and mean carriage displacement over that exposure (moving:
    # the displacement at mid-exposure, so the sheet a camera saw is at position_steps + its offset)
    exposure_start_s: tuple[float | None, float | None] = (None, None)
    laser_offsets_steps: tuple[float, float] = (0.0, 0.0)


@dataclass(frozen=True)
class PreparedPose:
    """The views' caches of a subject pose (`SimulatedRig.prepare_subject_pose`), ready to be swapped in."""

    R: AnyArray
    t: AnyArray
    views: list[dict[str, Any]]


@dataclass
class _View:
    """What one camera sees of the scene, cached between carriage positions."""

    camera: CameraModel
    origin: AnyArray
    dirs: AnyArray                          # (H*W,3) unit rays, left frame
    hit: AnyArray = field(default_factory=lambda: np.zeros(0, bool))
    t: AnyArray = field(default_factory=lambda: np.zeros(0))
    geom: AnyArray = field(default_factory=lambda: np.zeros(0, np.int64))
    points: AnyArray = field(default_factory=lambda: np.zeros((0, 3)))
    normals: AnyArray = field(default_factory=lambda: np.zeros((0, 3)))
    red_albedo: AnyArray = field(default_factory=lambda: np.zeros(0))
    base: AnyArray = field(default_factory=lambda: np.zeros((0, 0, 3), np.float32))
    pn: AnyArray = field(default_factory=lambda: np.zeros(0))          # n . P per pixel
    sigma2: AnyArray = field(default_factory=lambda: np.zeros(0))      # pixel-integrated sheet variance
    reach: AnyArray = field(default_factory=lambda: np.zeros(0))       # |n . P - c| beyond which the laser adds ~0
    reach_max: float = 0.0
    # the band table: the pixels that hit, by their n . P's bin (`PN_BIN_M`, ascending) and within a bin by
    # pixel index, so a capture's candidates are a contiguous run of it and come row by row along the line
    band_order: AnyArray = field(default_factory=lambda: np.zeros(0, np.int64))  # their pixel indices
    band_bin: AnyArray = field(default_factory=lambda: np.zeros(0, np.int64))    # floor(n . P / PN_BIN_M)
    band_pn: AnyArray = field(default_factory=lambda: np.zeros(0))               # their n . P
    band_reach: AnyArray = field(default_factory=lambda: np.zeros(0))            # their reach
    # their sigma2, the laser distance's and incidence's coefficients in the laser origin's track position s
    # (origin = band_start + s x: |origin - P|^2 = A + s (B + s), N . (origin - P) = C + s D) and red albedo
    band_rows: AnyArray = field(default_factory=lambda: np.zeros((0, 6)))
    band_start: AnyArray = field(default_factory=lambda: np.zeros(3))
    # their constants that do not change with the sheet's offset, one row each: the skin kernel's `KernelScale`
    # (sigma, b, sigma / b, (sigma / b)^2 / 2, sigma sqrt 2), 1 / sqrt(2 sigma2) and the normal's n . N
    band_consts: AnyArray = field(default_factory=lambda: np.zeros((7, 0)))
    band_skin: AnyArray = field(default_factory=lambda: np.zeros(0, bool))     # their skin flag
    # their shadow test (`SimulatedRig._lit_at_own_origin`): -1 not cast yet at this pose, 0 shadowed, 1 lit
    band_lit: AnyArray = field(default_factory=lambda: np.zeros(0, np.int8))
    skin: AnyArray = field(default_factory=lambda: np.zeros(0, bool))  # pixel sees a "skin" object
    speckle: SpeckleField | None = None
    # the sensor's view of ``base`` (lens-blurred) and its noise sigma (x 255, DN), for the settings in ``sensor_key``
    sensor_key: tuple = ()
    blurred: AnyArray = field(default_factory=lambda: np.zeros((0, 0, 3), np.float32))
    sigma255: AnyArray = field(default_factory=lambda: np.zeros((0, 0, 3), np.float32))
    base_saturates: bool = False


def _footprints(points: AnyArray, ok: AnyArray, depth: AnyArray, axis: int) -> AnyArray:
    """dP per pixel along ``axis`` (0 rows, 1 cols): central differences, one-sided at edges and depth jumps."""
    H, W = ok.shape
    fwd = np.zeros_like(points)
    ok_pair = np.zeros((H, W), bool)
    if axis == 1:
        fwd[:, :-1] = points[:, 1:] - points[:, :-1]
        ok_pair[:, :-1] = ok[:, 1:] & ok[:, :-1]
    else:
        fwd[:-1] = points[1:] - points[:-1]
        ok_pair[:-1] = ok[1:] & ok[:-1]
    # a neighbour more than 5 % of the depth away is across a depth jump, not on the same surface
    ok_pair &= np.linalg.norm(fwd, axis=2) < 0.05 * np.maximum(depth, 1e-6)
    bwd = np.zeros_like(points)
    ok_b = np.zeros((H, W), bool)
    if axis == 1:
        bwd[:, 1:], ok_b[:, 1:] = fwd[:, :-1], ok_pair[:, :-1]
    else:
        bwd[1:], ok_b[1:] = fwd[:-1], ok_pair[:-1]
    both = ok_pair & ok_b
    out = np.where(both[..., None], 0.5 * (fwd + bwd), np.where(ok_pair[..., None], fwd, np.where(ok_b[..., None], bwd, 0.0)))
    return out


_RAY_CACHE: dict[bytes, AnyArray] = {}

# Bin width of n . P in the band table [m], about a pixel's footprint at the subject distance: the pixels
# of a bin lie on a thin strip along the line, and in pixel order their shadow rays are coherent (Embree
# traverses consecutive rays through the same nodes: ~15 % less time than in n . P order)
PN_BIN_M = 0.5e-3


def _grid_rays(camera: CameraModel) -> AnyArray:
    """Rays of every pixel centre; cached per camera model (converged undistortion of every pixel)."""
    key = b"".join(np.ascontiguousarray(a, dtype=np.float64).tobytes()
                   for a in (camera.K, camera.D, camera.R, camera.t, np.array([camera.width, camera.height])))
    if key not in _RAY_CACHE:
        u, v = np.meshgrid(np.arange(camera.width, dtype=np.float64), np.arange(camera.height, dtype=np.float64))
        if len(_RAY_CACHE) > 8:
            _RAY_CACHE.clear()
        _RAY_CACHE[key] = camera.pixel_rays(np.stack([u.ravel(), v.ravel()], axis=1))
        _RAY_CACHE[key].setflags(write=False)
    return _RAY_CACHE[key]


class SimulatedRig:
    """The virtual LSU: a `RigGeometry`, a scene of `SceneObject`s, and a seeded sensor noise source."""

    def __init__(self, geometry: RigGeometry, objects: Sequence[SceneObject], seed: int = 0,
                 reference: bool = False, parallel: bool = True, shadow_cache: bool = False) -> None:
        self.geometry = geometry
        # reference: the plain render (every sub-exposure evaluated, fresh noise for the whole image, every
        # step on the full image); the default render gives the same images at a fraction of the CPU
        # (see `render`), the reference is what it is tested and benchmarked against
        self.reference = reference
        # parallel: the two views on two threads (numpy, OpenCV and the ray casts release the GIL in the
        # per-pixel work): less wall time per pair, more CPU (hand-offs, the views competing for the caches);
        # a caller that keeps both cores busy otherwise (a camera stream beside the rest of the graph)
        # renders serially
        self.parallel = parallel
        # shadow_cache: one shadow ray per pixel and subject pose (`_lit_at_own_origin`) instead of one per pixel
        # and frame; off (the default), the shadow rays go from every frame's own laser origin, as the reference's
        # do. On, a few pixels at shadow edges differ (<= 1e-4 of an image's values), enough to move the
        # accuracy figures' far-point counts: the live camera stream turns it on for its frame rate, the
        # accuracy and benchmark renders keep it off
        self.shadow_cache = shadow_cache
        self.rng = np.random.default_rng(seed)
        # one generator per camera, so the two views' images do not depend on the thread they render
        # on (nor on ``parallel``) and stay reproducible from ``seed``
        self._view_rngs = self.rng.spawn(2)
        self._pool: ThreadPoolExecutor | None = None
        # the sheet's frame along the track (`_sheet_frame`), for the geometry object it was computed of
        self._frame_of: RigGeometry | None = None
        self._frame: tuple[AnyArray, ...] = ()
        self._views = [_View(cam, cam.center, _grid_rays(cam)) for cam in (geometry.left, geometry.right)]
        for k, view in enumerate(self._views):
            # a bank per camera (seeded by the camera index: scene-independent, shared by every rig of
            # the process); the realisation of each capture comes from the capture's generator
            view.speckle = SpeckleField(geometry.speckle, geometry.laser.wavelength_nm * 1e-9, geometry.sensor.f_number,
                                        geometry.magnification, geometry.sensor.pixel_size_m, geometry.image_size[1], k)
        self.objects: list[SceneObject] = []
        # the subject's rigid pose (a living subject, `motion`): the scene as built maps to where it is now by
        # X_now = R X + t; ray casts go into the scene's own frame instead, so a new pose re-casts the views
        # without rebuilding the ray-casting structure
        self._pose_R = np.eye(3)
        self._pose_t = np.zeros(3)
        self.set_scene(objects)

    # ------------------------------------------------------------------ scene
    def set_scene(self, objects: Sequence[SceneObject]) -> None:
        """Replace the scene and recompute every per-camera cache."""
        if not objects:
            raise ValueError("the scene needs at least one object")
        self.objects = list(objects)
        self._scene = o3d.t.geometry.RaycastingScene()
        self._tris: list[AnyArray] = []
        self._vnormals: list[AnyArray] = []
        for obj in self.objects:
            mesh = obj.mesh
            if not mesh.has_vertex_normals():
                mesh.compute_vertex_normals()
            self._scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
            self._tris.append(np.asarray(mesh.triangles))
            self._vnormals.append(np.asarray(mesh.vertex_normals))
        self.apply_subject_pose(self.prepare_subject_pose(self._pose_R, self._pose_t))

    def set_subject_pose(self, R: AnyArray, t: AnyArray) -> None:
        """Move the whole scene rigidly to ``X_now = R X + t`` (X: the scene as built) and recompute the views.

        Rigid: hit distances, triangles and the surface's texture (evaluated in the scene's own frame, so it
        moves with the skin) are those of the scene as built; positions and normals turn with the pose.
        """
        if np.array_equal(R, self._pose_R) and np.array_equal(t, self._pose_t):
            return
        self.apply_subject_pose(self.prepare_subject_pose(R, t))  # refuses a pose that is not rigid

    def prepare_subject_pose(self, R: AnyArray, t: AnyArray) -> PreparedPose:
        """The views' caches for the subject at pose (``R``, ``t``), computed without changing what renders now: a
        thread may prepare the next pose while another renders the current one (`apply_subject_pose` swaps)."""
        R = np.asarray(R, dtype=np.float64).reshape(3, 3)
        t = np.asarray(t, dtype=np.float64).reshape(3)
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))) or not np.allclose(R.T @ R, np.eye(3), atol=1e-6):
            raise ValueError("the subject pose needs a finite rotation matrix and translation")
        return PreparedPose(R, t, [self._view_cache(view, R, t) for view in self._views])

    def apply_subject_pose(self, prepared: PreparedPose) -> None:
        """The subject at a pose `prepare_subject_pose` made the caches of (the renders after this see it)."""
        self._pose_R, self._pose_t = prepared.R, prepared.t
        for view, cache in zip(self._views, prepared.views):
            for name, value in cache.items():
                setattr(view, name, value)

    def _to_scene(self, origins: AnyArray, dirs: AnyArray, pose: tuple[AnyArray, AnyArray] | None = None
                  ) -> tuple[AnyArray, AnyArray]:
        """Rays (left frame) in the scene's own frame (the inverse of the subject pose: ``pose`` (R, t), by default
        the current one)."""
        R, t = pose if pose is not None else (self._pose_R, self._pose_t)
        if not t.any() and np.array_equal(R, np.eye(3)):
            return origins, dirs
        return (np.asarray(origins) - t) @ R, np.asarray(dirs) @ R

    def _cast(self, origins: AnyArray, dirs: AnyArray, pose: tuple[AnyArray, AnyArray] | None = None
              ) -> dict[str, AnyArray]:
        origins, dirs = self._to_scene(origins, dirs, pose)
        rays = np.concatenate([np.broadcast_to(origins, dirs.shape), dirs], axis=1).astype(np.float32)
        result = self._scene.cast_rays(o3d.core.Tensor(rays))
        return {k: v.numpy() for k, v in result.items()}

    def _smooth_normals(self, geom: AnyArray, prim: AnyArray, uvs: AnyArray) -> AnyArray:
        """Unit interpolated vertex normals of hit pixels (their object ids, triangles and barycentrics)."""
        normals = np.zeros((len(geom), 3))
        for gid in range(len(self.objects)):
            sel = geom == gid
            if not np.any(sel):
                continue
            tri = self._tris[gid][prim[sel]]
            vn = self._vnormals[gid]
            uv = uvs[sel].astype(np.float64)
            normals[sel] = ((1.0 - uv[:, :1] - uv[:, 1:]) * vn[tri[:, 0]] + uv[:, :1] * vn[tri[:, 1]]
                            + uv[:, 1:] * vn[tri[:, 2]])
        norm = np.linalg.norm(normals, axis=1, keepdims=True)
        return normals / np.where(norm > 0, norm, 1.0)

    def _view_cache(self, view: _View, pose_R: AnyArray, pose_t: AnyArray) -> dict[str, Any]:
        """What ``view`` sees of the scene with the subject at pose (``pose_R``, ``pose_t``): its cached fields by
        name. Reads the view's rays and the scene only: `prepare_subject_pose` runs it beside a render."""
        g = self.geometry
        W, H = g.image_size
        cast = self._cast(view.origin, view.dirs, (pose_R, pose_t))
        t = cast["t_hit"].astype(np.float64)
        hit = np.isfinite(t)
        geom = np.where(hit, cast["geometry_ids"].astype(np.int64), -1)
        t = np.where(hit, t, 0.0)
        points = view.origin + view.dirs * t[:, None]
        # the surface's terms on the pixels that hit only (about half of a person's view is background); a
        # pixel that misses gets what the whole-image formulas give it: no normal, the background's light,
        # the bare sheet's variance and reach
        hit_idx = np.flatnonzero(hit)
        dirs, geom_h = view.dirs[hit_idx], geom[hit_idx]
        nrm = self._smooth_normals(geom_h, cast["primitive_ids"][hit_idx].astype(np.int64), cast["primitive_uvs"][hit_idx])
        nrm = nrm @ pose_R.T  # the scene's normals as the subject is turned
        flip = np.einsum("ij,ij->i", nrm, dirs) > 0  # face the camera: both sides of a mesh are visible
        nrm[flip] *= -1.0
        ok = hit.reshape(H, W)
        depth = t.reshape(H, W)
        pts = points.reshape(H, W, 3)
        du = _footprints(pts, ok, depth, 1).reshape(-1, 3)[hit_idx]
        dv = _footprints(pts, ok, depth, 0).reshape(-1, 3)[hit_idx]
        pts_h = points[hit_idx]
        albedo = np.zeros((len(hit_idx), 3))
        spec = np.zeros(len(hit_idx))
        skin_h = np.zeros(len(hit_idx), bool)
        for gid, obj in enumerate(self.objects):
            sel = geom_h == gid
            if np.any(sel):
                # the texture is the scene's own: evaluated where the point is on the subject as built
                albedo[sel] = obj.albedo((pts_h[sel] - pose_t) @ pose_R, du[sel] @ pose_R, dv[sel] @ pose_R)
                spec[sel] = obj.specularity
                skin_h |= sel & (obj.material == "skin")
        light = g.lighting
        to_lamp = light.key_light_m - pts_h
        to_lamp /= np.maximum(np.linalg.norm(to_lamp, axis=1, keepdims=True), 1e-12)
        diffuse = np.clip(np.einsum("ij,ij->i", nrm, to_lamp), 0.0, None)
        half = to_lamp - dirs
        half /= np.maximum(np.linalg.norm(half, axis=1, keepdims=True), 1e-12)
        highlight = light.specular * spec * np.clip(np.einsum("ij,ij->i", nrm, half), 0.0, None) ** light.shininess
        radiance = np.empty((H * W, 3))
        radiance[:] = light.background
        radiance[hit_idx] = albedo * (light.ambient + light.key * diffuse)[:, None] + highlight[:, None]
        n = g.laser_normal
        slope2 = (du @ n) ** 2 + (dv @ n) ** 2
        # grazing pixels have huge footprints along n: cap so they stay in the band test but contribute ~0
        sigma2 = np.full(H * W, g.laser.sheet_sigma_m ** 2)
        sigma2[hit_idx] = g.laser.sheet_sigma_m ** 2 + np.minimum(slope2, (50.0 * g.laser.sheet_sigma_m) ** 2) / 12.0
        # skin: the diffusion kernel (length b sin psi in sheet-offset units, see `_skin_width`) and its
        # centre shift (at most |n . N| / (n_skin (mu_a + mu_s'))) reach further from the sheet
        n_dot_hit = nrm @ n
        n_dot_normal = np.zeros(H * W)
        n_dot_normal[hit_idx] = n_dot_hit
        nN = np.abs(n_dot_hit)
        reach = 5.0 * np.sqrt(sigma2)
        reach[hit_idx] += skin_h * (6.0 * g.skin.diffusion_length_m * np.sqrt(np.clip(1.0 - nN * nN, 0, 1))
                                    + g.skin.centre_shift_per_sin_t * nN / g.skin.refractive_index)
        normals = np.zeros((H * W, 3))
        normals[hit_idx] = nrm
        skin = np.zeros(H * W, bool)
        skin[hit_idx] = skin_h
        red_albedo = np.zeros(H * W)
        red_albedo[hit_idx] = albedo[:, 2]
        pn = np.where(hit, points @ n, np.nan)
        bins = np.floor(pn[hit_idx] / PN_BIN_M).astype(np.int64)
        order = np.argsort(bins, kind="stable")  # stable: by pixel index within a bin
        band_order = hit_idx[order]
        # what the laser term reads of a band's pixels, in the same order: one row gather per capture
        _, x, start = self._sheet_frame(g.center_step)
        to_start = start - points[band_order]
        band_normals = normals[band_order]
        band_rows = np.column_stack([sigma2[band_order], np.einsum("ij,ij->i", to_start, to_start),
                                     2.0 * (to_start @ x), np.einsum("ij,ij->i", band_normals, to_start),
                                     band_normals @ x, red_albedo[band_order]])
        # the sheet keeps its orientation (n and the skin model are the geometry's, as for every cache here):
        # what depends on n . N alone is fixed per pixel
        order_nN = n_dot_normal[band_order]
        scale = KernelScale.of(band_rows[:, 0], self._skin_width(order_nN))
        return {
            "hit": hit, "t": t, "geom": geom, "points": points, "normals": normals, "skin": skin, "reach": reach,
            "red_albedo": red_albedo, "base": radiance.reshape(H, W, 3).astype(np.float32),
            "sensor_key": (),  # the sensor's view of the base is made again at the next render
            "pn": pn, "sigma2": sigma2, "reach_max": float(reach[hit].max()) if np.any(hit) else 0.0,
            "band_order": band_order, "band_bin": bins[order], "band_pn": pn[band_order],
            "band_reach": reach[band_order], "band_start": start, "band_rows": band_rows,
            "band_skin": skin[band_order], "band_lit": np.full(len(band_order), -1, np.int8),
            "band_consts": np.stack([scale.sigma, scale.b, scale.rb, scale.h, scale.sigma_sqrt2,
                                     1.0 / np.sqrt(2.0 * band_rows[:, 0]), order_nN]),
        }

    # ------------------------------------------------------------------ laser
    def _lit(self, origin: AnyArray, points: AnyArray, any_hit: bool = False, dist: AnyArray | None = None) -> AnyArray:
        """True where the laser at ``origin`` reaches ``points`` unshadowed (nothing hit before 1e-5 m + 1e-5 of the way).

        ``any_hit``: an occlusion query (Embree's any-hit: cheaper than the closest hit) along the
        unnormalised rays, with the margin of the farthest point for all (self-hits are ~3e-8 m).
        ``dist``: the points' distances to ``origin`` when the caller has them.
        """
        if len(points) == 0:
            return np.zeros(0, bool)
        to = points - origin
        if dist is None:
            dist = np.linalg.norm(to, axis=1)
        if any_hit:
            rays = np.empty((len(to), 6), np.float32)
            rays[:, :3], rays[:, 3:] = self._to_scene(origin, to)
            tfar = float(1.0 - 1e-5 - 1e-5 / dist.max())
            return ~self._scene.test_occlusions(o3d.core.Tensor(rays), tnear=0.0, tfar=tfar).numpy().astype(bool)
        cast = self._cast(origin, to / dist[:, None])
        return cast["t_hit"].astype(np.float64) >= dist * (1.0 - 1e-5) - 1e-5

    def _lit_at_own_origin(self, view: _View, rows: AnyArray, idx: AnyArray) -> AnyArray:
        """Shadow test of the band table's ``rows`` (pixels ``idx``) from the laser origin whose sheet centre holds the point.

        A point's laser term matters only while the sheet is within its reach, a few millimetres of track
        around the position where the sheet's centre plane passes through it; its shadow ray is cast once per
        pose from there (an occlusion query, `_lit`) and kept in ``view.band_lit``. A sweep thus casts one ray
        per pixel and pose instead of one per pixel and frame. Where the laser's shadow edge crosses a
        point's band, the point is lit or shadowed as it is at the band's centre for the whole band (the
        reference render casts from every frame's own origin); test_render_cache states the difference.
        """
        known = view.band_lit[rows]
        todo = np.flatnonzero(known < 0)
        if len(todo):
            n, x, start = self._sheet_frame(self.geometry.center_step)
            pts = view.points[idx[todo]]
            # the origin start + s x whose sheet n . X = n . (start + s x) contains the point
            s = (pts @ n - float(n.dot(start))) / float(n.dot(x))
            origins = start + s[:, None] * x
            to = pts - origins
            dist = np.sqrt(np.einsum("ij,ij->i", to, to))
            rays = np.empty((len(to), 6), np.float32)
            rays[:, :3], rays[:, 3:] = self._to_scene(origins, to)
            tfar = float(1.0 - 1e-5 - 1e-5 / dist.max())
            lit = ~self._scene.test_occlusions(o3d.core.Tensor(rays), tnear=0.0, tfar=tfar).numpy().astype(bool)
            known[todo] = lit
            view.band_lit[rows[todo]] = lit
        return known.astype(bool)

    @staticmethod
    def _band_candidates(view: _View, lo: float, hi: float) -> AnyArray:
        """Rows of the view's band table whose pixel's n . P is within its reach of [lo, hi] (ascending).

        The table's run of bins within the largest reach (floor is monotone, so every pixel with
        lo - reach_max < n . P < hi + reach_max is in it), then each pixel's own reach.
        """
        a = int(np.searchsorted(view.band_bin, math.floor((lo - view.reach_max) / PN_BIN_M), side="left"))
        b = int(np.searchsorted(view.band_bin, math.floor((hi + view.reach_max) / PN_BIN_M), side="right"))
        pn, reach = view.band_pn[a:b], view.band_reach[a:b]
        return a + np.flatnonzero((pn > lo - reach) & (pn < hi + reach))

    def _laser_radiance(self, view: _View, offsets_m: AnyArray, origin: AnyArray,
                        box_m: tuple[float, float] | None = None):
        """(indices, (M,3) radiance) of the laser term averaged over the sheet offsets ``offsets_m``.

        ``box_m``: the sheet's offsets at the exposure's start and end when it moves at a constant rate
        (``offsets_m`` are then the sub-exposures' midpoints between them); unless this rig is the
        reference, the average is the closed-form average over that interval (`physics.surface_profile_box`,
        `physics.skin_profile_box`): one evaluation instead of one per sub-exposure, and the limit the
        sub-exposures' mean approaches (their midpoint sum of a profile that varies over ~2 sub-exposure
        spacings differs from it by a few 1e-3 of the peak). The sheet's normal is the geometry's
        (``laser_normal``, the one the view's caches were made with).
        """
        g = self.geometry
        sheet = g.laser.sheet_sigma_m
        use_box = box_m is not None and not self.reference and box_m[1] - box_m[0] > 1e-3 * sheet
        lo, hi = (float(box_m[0]), float(box_m[1])) if use_box and box_m is not None else \
            (float(offsets_m.min()), float(offsets_m.max()))
        sel = self._band_candidates(view, lo, hi)
        idx = view.band_order[sel]    # pixel indices (every step below is per pixel: their order does not matter)
        if len(idx) == 0:
            return idx, np.zeros((0, 3))
        rows = view.band_rows[sel]
        s2, red_albedo = rows[:, 0], rows[:, 5]
        pn = view.band_pn[sel]
        if self.reference:
            to_laser = origin - view.points[idx]
            dist = np.linalg.norm(to_laser, axis=1)
            cos_i = np.einsum("ij,ij->i", view.normals[idx], to_laser) / dist
        else:
            # the origin's track position: the sheet moves along x only (`_sheet_frame`)
            s = float(self._sheet_frame(g.center_step)[1].dot(origin - view.band_start))
            dist = np.sqrt(rows[:, 1] + s * (rows[:, 2] + s))
            cos_i = (rows[:, 3] + s * rows[:, 4]) / dist
        incidence = np.clip(cos_i, 0.0, None)
        on_skin = view.band_skin[sel]
        # the skin and the other pixels (a slice when the band is all one or the other: no copies)
        skin: slice | AnyArray = slice(None) if on_skin.all() else np.flatnonzero(on_skin)
        other: slice | AnyArray | None = None if on_skin.all() else (slice(None) if not on_skin.any()
                                                                      else np.flatnonzero(~on_skin))
        any_skin = bool(on_skin.any())
        profile = np.empty(len(idx))
        if use_box:
            d_lo, d_hi = pn - hi, pn - lo       # the interval of sheet offsets d = n . P - c
            if other is not None:
                profile[other] = surface_profile_box(d_lo[other], d_hi[other], s2[other], sheet)
        else:
            d = pn[None, :] - offsets_m[:, None]
            if other is not None:
                do, so = d[:, other], s2[other]
                profile[other] = (np.exp(-0.5 * do * do / so) * np.sqrt(sheet ** 2 / so)).mean(axis=0)
        if any_skin:
            consts = view.band_consts[:, sel[skin]]
            scale = KernelScale(*consts[:5])
            shift_d = self._skin_shift(cos_i[skin], consts[6])
            fraction = g.skin.subsurface_fraction
            if use_box:
                profile[skin] = skin_profile_box(d_lo[skin], d_hi[skin], s2[skin], sheet, None, shift_d, fraction,
                                                 scale, consts[5])
            else:
                prof = np.zeros(len(shift_d))
                for row in d[:, skin]:
                    if self.reference:  # the same profile, the exponential tails through the general form
                        prof += skin_profile(row, s2[skin], sheet, scale.b, shift_d, fraction)
                    else:
                        prof += skin_profile_tails(row, s2[skin], sheet, None, shift_d, fraction, scale)
                profile[skin] = prof / len(d)
        if any_skin or not self.reference:
            # the skin band is wide for the kernel's tail: drop pixels it leaves below 1e-3 of the peak
            # (< 0.2 DN at full power) before the shadow rays, the costly part
            keep = np.flatnonzero(profile > 1e-3)
            idx, profile, dist, incidence = idx[keep], profile[keep], dist[keep], incidence[keep]
            red_albedo, sel = red_albedo[keep], sel[keep]
        # the fan spreads in one direction only: irradiance falls as 1/r, referenced to the subject distance
        n, x, _ = self._sheet_frame(g.center_step)
        # (a sheet parallel to the track never moves over the scene: no origin of its own per point)
        if self.reference or not self.shadow_cache or abs(float(n.dot(x))) < 1e-9:
            lit = self._lit(origin, view.points[idx], any_hit=not self.reference, dist=dist)
        else:
            lit = self._lit_at_own_origin(view, sel, idx)
        power = g.laser.power * incidence * (g.subject_distance_m / dist) * lit
        value = (power * profile * red_albedo)[:, None] * g.laser.spectral_bgr[None, :]
        return idx, value

    def _skin_width(self, n_dot_normal: AnyArray) -> AnyArray:
        """Diffusion length of skin pixels' remitted light in sheet-offset units, from the normals' ``n . N``.

        Across the line on the surface, ``n . P`` changes at ``sin psi = |n - (n.N) N|`` per metre: the
        kernel's length (`physics.skin_profile`) is scaled by it.
        """
        sin_psi = np.sqrt(np.clip(1.0 - n_dot_normal * n_dot_normal, 0.0, 1.0))
        return self.geometry.skin.diffusion_length_m * np.maximum(sin_psi, 1e-3)

    def _skin_shift(self, cos_i: AnyArray, n_dot_normal: AnyArray) -> AnyArray:
        """Centre shift of skin pixels' remitted light in sheet-offset units (`physics.skin_profile`).

        The shift points along the surface away from the laser (the tangential part of the incident
        ray), length ``sin(alpha_t) / (mu_a + mu_s')`` with ``sin(alpha_t) = sin(alpha_i) / n_skin``.
        """
        g = self.geometry
        sin_i = np.sqrt(np.clip(1.0 - cos_i * cos_i, 0.0, 1.0))
        # incident direction u = -to_laser/|to_laser| lies in the sheet (u . n = 0), so its tangential part
        # u - (u.N) N has the sheet-normal component -(u.N)(N.n) = cos_i (N.n); per unit of it the shift is
        # shift_length / sin_i
        shift_len = g.skin.centre_shift_per_sin_t * sin_i / g.skin.refractive_index
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(sin_i > 1e-9, shift_len / np.maximum(sin_i, 1e-9) * np.clip(cos_i, 0.0, None) * n_dot_normal,
                            0.0)

    # ------------------------------------------------------------------ render
    def prepare(self) -> None:
        """Build now what the first `render` would build: each view's lens-blurred base and noise sigma, and the
        process's noise bank (`physics.noise_window`). No pixel of any later frame changes; the first frame then
        costs what the others cost instead of about half a second of CPU more."""
        for view in self._views:
            self._sensor_cache(view)
        noise_window(self._views[0].base.shape, np.random.default_rng(0))  # its own generator: the views' untouched

    def render(self, carriage: CarriageState | float, capture_time_s: float | None = None,
               seed: int | None = None, with_truth: bool = False, parallel: bool | None = None) -> StereoFrame:
        """Render a stereo pair exposed from ``capture_time_s`` for ``sensor.exposure_s``.

        ``carriage`` is a `CarriageState` or a plain position in steps (laser on, settled).
        ``seed`` fixes the sensor noise of this pair (default: the rig's own generator).
        ``parallel``: the two views on two threads (default: the rig's ``parallel``); the images are the same.

        Unless the rig is the reference, the laser term of a constant-rate motion is averaged in closed
        form over the exposure (`_laser_radiance`), and the sensor works on the laser's rows and columns
        only: the lens blur is linear, so the blurred image is the cached blurred base plus the blurred
        laser term; blooming moves only charge above full well, which only the laser's pixels hold when
        the blurred base stays below it; outside the laser's rectangle the noise sigma is the cached
        base's. The noise comes from a seeded bank (`physics.noise_window`).
        """
        state = carriage if isinstance(carriage, CarriageState) else CarriageState(float(carriage))
        g = self.geometry
        sensor = g.sensor
        rngs = np.random.default_rng(seed).spawn(2) if seed is not None else self._view_rngs
        starts: list[float | None] = [None, None]
        if capture_time_s is not None:
            # each camera's own exposure start (drawn first, so the noise stream does not depend on it)
            jitter = [float(r.standard_normal()) * sensor.capture_jitter_s for r in rngs]
            starts = [capture_time_s + jitter[0], capture_time_s + sensor.capture_offset_s + jitter[1]]
        sheet = self._sheet_frame(state.position_steps)
        laser = [self._laser_exposure(state, t0, sheet) for t0 in starts]

        def laser_term(k: int) -> tuple[AnyArray, AnyArray, AnyArray, AnyArray]:
            view = self._views[k]
            _, offsets, origin, box = laser[k]
            idx, value = self._laser_radiance(view, offsets, origin, box)
            assert view.speckle is not None  # set for both views in __init__
            rows, cols = np.divmod(idx, g.image_size[0])
            speckle = view.speckle.sample(rows, cols, rngs[k])
            if speckle is not None:
                value *= speckle[:, None]
            return idx, rows, cols, value.astype(np.float32)

        def expose(k: int) -> AnyArray:
            if not self.reference and sensor.bayer == "none":
                return self._expose_fast(k, laser_term(k) if state.laser_on else None, rngs[k])
            img = self._views[k].base.copy()
            if state.laser_on:
                idx, _, _, value = laser_term(k)
                img.reshape(-1, 3)[idx] += value
            if sensor.psf_sigma_px > 0:
                img = cv2.GaussianBlur(img, (0, 0), sensor.psf_sigma_px)
            bloom(img, sensor.blooming)
            if sensor.bayer != "none":
                img = mosaic(img, sensor.bayer)
            if self.reference:
                # shot + read noise, sigma^2 = max(img, 0) / full_well + read^2; in place, float32
                sigma = np.maximum(img, np.float32(0.0))
                sigma *= np.float32(1.0 / sensor.full_well_e)
                sigma += np.float32((sensor.read_noise_dn / 255.0) ** 2)
                np.sqrt(sigma, out=sigma)
                noise = rngs[k].standard_normal(img.shape, dtype=np.float32)
                noise *= sigma
                img += noise  # img is this capture's own copy of the base image
                img *= np.float32(255.0)
                np.rint(img, out=img)
                np.clip(img, 0, 255, out=img)
                out = img.astype(np.uint8)
            else:
                out = self._quantise(img, self._noise_sigma255(img), *noise_window(img.shape, rngs[k]))
            return demosaic(out, sensor.bayer) if sensor.bayer != "none" else out

        if self.parallel if parallel is None else parallel:
            if self._pool is None:
                self._pool = ThreadPoolExecutor(max_workers=2, thread_name_prefix="lsu-sim-render")
            images = list(self._pool.map(expose, range(2)))
        else:
            images = [expose(0), expose(1)]
        truth = self.laser_truth(state.position_steps) if with_truth and state.laser_on else None
        return StereoFrame(images[0], images[1], state.position_steps, state.laser_on, capture_time_s, laser[0][0], truth,
                           (starts[0], starts[1]), (laser[0][0], laser[1][0]))

    def _noise_sigma255(self, img: AnyArray) -> AnyArray:
        """Shot + read noise sigma x 255 of an image in full-scale units: ``sqrt(max(img, 0) / full_well + read^2)``."""
        sensor = self.geometry.sensor
        sigma = np.maximum(img, np.float32(0.0))
        sigma *= np.float32(255.0 ** 2 / sensor.full_well_e)
        sigma += np.float32(sensor.read_noise_dn ** 2)
        return cv2.sqrt(sigma)

    @staticmethod
    def _quantise(img: AnyArray, sigma255: AnyArray, noise: AnyArray, sign: float = 1.0) -> AnyArray:
        """8-bit image of ``img`` (full-scale units) plus ``sigma255 * noise`` DN: rounded to nearest, saturated.

        OpenCV's saturating conversion rounds half to even like ``np.rint`` and clips to 0..255.
        """
        noisy = cv2.multiply(sigma255, noise, scale=sign)
        return cv2.addWeighted(img, 255.0, noisy, 1.0, 0.0, dtype=cv2.CV_8U)

    def _sensor_cache(self, view: _View) -> None:
        """(Re)compute the view's blurred base and its noise sigma when the sensor settings changed."""
        sensor = self.geometry.sensor
        key = (sensor.psf_sigma_px, sensor.full_well_e, sensor.read_noise_dn, sensor.blooming)
        if view.sensor_key == key:
            return
        base = view.base
        if sensor.psf_sigma_px > 0:
            base = cv2.GaussianBlur(base, (0, 0), sensor.psf_sigma_px)
        view.base_saturates = bool(base.max() > 1.0)
        if view.base_saturates:
            # the laser-off image; laser-on ones then take the full-image path (`_expose_fast`)
            base = base.copy()
            bloom(base, sensor.blooming)
        view.blurred = base
        view.sigma255 = self._noise_sigma255(base)
        view.sensor_key = key

    def _expose_fast(self, k: int, laser: tuple[AnyArray, AnyArray, AnyArray, AnyArray] | None,
                     rng: np.random.Generator) -> AnyArray:
        """One camera's 8-bit image (no Bayer mosaic): the sensor steps on the laser's rectangle only (see `render`)."""
        view = self._views[k]
        sensor = self.geometry.sensor
        self._sensor_cache(view)
        base = view.blurred
        H, W = base.shape[:2]
        noise, sign = noise_window(base.shape, rng)
        if laser is None or len(laser[0]) == 0 or view.base_saturates:
            img = base
            if laser is not None and len(laser[0]):
                img = view.base.copy()
                img.reshape(-1, 3)[laser[0]] += laser[3]
                if sensor.psf_sigma_px > 0:
                    img = cv2.GaussianBlur(img, (0, 0), sensor.psf_sigma_px)
                bloom(img, sensor.blooming)
                return self._quantise(img, self._noise_sigma255(img), noise, sign)
            return self._quantise(img, view.sigma255, noise, sign)
        _, rows, cols, value = laser
        # the blur kernel's radius (OpenCV: ksize = round(8 sigma + 1) | 1) plus one row for the blooming spill;
        # the laser term is zero in the margin, so blurring the rectangle alone equals blurring the image
        margin = int(np.ceil(4.0 * sensor.psf_sigma_px)) + 2
        r0, r1 = max(int(rows.min()) - margin, 0), min(int(rows.max()) + margin + 1, H)
        c0, c1 = max(int(cols.min()) - margin, 0), min(int(cols.max()) + margin + 1, W)
        term = np.zeros((r1 - r0, c1 - c0, 3), np.float32)
        term.reshape(-1, 3)[(rows - r0) * (c1 - c0) + (cols - c0)] = value   # one flat index: cheaper than two
        if sensor.psf_sigma_px > 0:
            term = cv2.GaussianBlur(term, (0, 0), sensor.psf_sigma_px)
        term += base[r0:r1, c0:c1]
        bloom(term, sensor.blooming)
        # the whole image from the cached base (one contiguous pass is cheaper than the bands around the
        # rectangle), then the rectangle
        out = self._quantise(base, view.sigma255, noise, sign)
        out[r0:r1, c0:c1] = self._quantise(term, self._noise_sigma255(term), noise[r0:r1, c0:c1], sign)
        return out

    def _sheet_frame(self, position_steps: float) -> tuple[AnyArray, AnyArray, AnyArray]:
        """(sheet normal n, track axis x, laser origin) at ``position_steps``: the origin moves along x.

        The same numbers as ``geometry.laser_normal``, ``rig_axes[0]``, ``laser_origin``, with the axes
        computed once per geometry object (the rig replaces, never edits, its geometry).
        """
        g = self.geometry
        if self._frame_of is not g:
            x, _, z = g.rig_axes
            self._frame = (g.laser_normal, x, g.rig_center + g.laser_forward_m * z)
            self._frame_of = g
        n, x, start = self._frame
        return n, x, start + (position_steps - g.center_step) * g.step_m * x

    def _laser_exposure(self, state: CarriageState, start_s: float | None,
                        sheet: tuple[AnyArray, AnyArray, AnyArray] | None = None):
        """(mean displacement [steps], sheet offsets [m] of the sub-exposures, laser origin, moving box) of one exposure.

        The moving box: the sheet's offsets (low, high) at the start and end of the exposure when the
        carriage moves at a constant rate, else None.
        """
        g = self.geometry
        sensor = g.sensor
        if not state.laser_on:
            return 0.0, np.zeros(0), np.zeros(0), None
        box = None
        # the sheet keeps its orientation and its origin moves along the track's axis x: the offset is
        # linear in the displacement
        n, x, origin0 = sheet if sheet is not None else self._sheet_frame(state.position_steps)
        c0, per_step = float(n.dot(origin0)), float(n.dot(x)) * g.step_m
        if start_s is not None and state.moving:
            # the sheet sweeps over the surface while the shutter is open: the line is the sheet's
            # sub-exposures averaged (motion blur), centred on the sheet at mid-exposure
            times = start_s + (np.arange(sensor.sub_exposures) + 0.5) / sensor.sub_exposures * sensor.exposure_s
            disp = state.displacement_steps(times)
            ends = c0 + per_step * np.concatenate([state.displacement_steps(np.array([start_s, start_s + sensor.exposure_s])), disp])
            box = (float(ends.min()), float(ends.max()))
        elif start_s is None or state.stopped_at_s is None or state.vibration_amplitude_steps == 0.0:
            disp = np.zeros(1)
        else:
            times = start_s + (np.arange(sensor.sub_exposures) + 0.5) / sensor.sub_exposures * sensor.exposure_s
            disp = state.displacement_steps(times)
        mean_offset = float(disp.mean())
        offsets = c0 + per_step * disp
        return mean_offset, offsets, origin0 + (mean_offset * g.step_m) * x, box

    def set_capture_timing(self, offset_s: float, jitter_s: float) -> None:
        """Exposure start of the right camera relative to the left, and each start's jitter (std), seconds."""
        if not (np.isfinite(offset_s) and np.isfinite(jitter_s)) or jitter_s < 0:
            raise ValueError(f"capture offset must be finite and jitter >= 0 (got {offset_s}, {jitter_s})")
        # a copy: the geometry may be shared with other rigs
        self.geometry = dataclasses.replace(self.geometry, sensor=dataclasses.replace(
            self.geometry.sensor, capture_offset_s=float(offset_s), capture_jitter_s=float(jitter_s)))

    # ------------------------------------------------------------------ ground truth
    def _cast_pixels(self, view: _View, u: AnyArray, v: AnyArray):
        dirs = view.camera.pixel_rays(np.stack([u, v], axis=1))
        cast = self._cast(view.origin, dirs)
        t = cast["t_hit"].astype(np.float64)
        hit = np.isfinite(t)
        pts = view.origin + dirs * np.where(hit, t, 0.0)[:, None]
        return pts, hit, cast["geometry_ids"].astype(np.int64)

    def _camera_truth(self, view: _View, other: _View, n: AnyArray, c: float, origin: AnyArray,
                      iterations: int = 30) -> CameraTruth:
        W, H = self.geometry.image_size
        f = (view.pn - c).reshape(H, W)
        geom = view.geom.reshape(H, W)
        pts = view.points.reshape(H, W, 3)
        depth = view.t.reshape(H, W)
        f0, f1 = f[:, :-1], f[:, 1:]
        with np.errstate(invalid="ignore"):
            cross = ((f0 <= 0) & (f1 > 0)) | ((f0 > 0) & (f1 <= 0))
        cross &= (geom[:, :-1] >= 0) & (geom[:, :-1] == geom[:, 1:])
        cross &= np.linalg.norm(pts[:, 1:] - pts[:, :-1], axis=2) < 0.05 * depth[:, :-1]
        rows, cols = np.nonzero(cross)
        ua, ub = cols.astype(np.float64), cols + 1.0
        fa, fb = f0[rows, cols].astype(np.float64), f1[rows, cols].astype(np.float64)
        gid = geom[rows, cols]
        v = rows.astype(np.float64)
        ok = np.ones(len(rows), bool)
        P = pts[rows, cols].copy()
        fc = fa.copy()
        for _ in range(iterations):  # Illinois regula falsi: bracketing, superlinear, robust to curvature
            if not np.any(ok & (np.abs(fc) > 1e-12)):
                break
            uc = np.clip(ub - fb * (ub - ua) / np.where(fb != fa, fb - fa, 1.0), np.minimum(ua, ub), np.maximum(ua, ub))
            Pc, hit, g = self._cast_pixels(view, uc, v)
            ok &= hit & (g == gid)
            fc = Pc @ n - c
            P = np.where(ok[:, None], Pc, P)
            same_as_b = np.sign(fc) == np.sign(fb)
            # keep the bracket [a, c]; when b's side repeats, halve f(a) so a stale end cannot stall it
            fa = np.where(same_as_b, fa * 0.5, fb)
            ua = np.where(same_as_b, ua, ub)
            ub, fb = uc, fc
        ok &= np.abs(P @ n - c) < 1e-6
        ok &= self._lit(origin, P) if len(P) else ok
        P = P[ok]
        pixels = view.camera.project(P)
        other_pixels = other.camera.project(P)
        visible = ((other_pixels[:, 0] >= -0.5) & (other_pixels[:, 0] <= W - 0.5)
                   & (other_pixels[:, 1] >= -0.5) & (other_pixels[:, 1] <= H - 0.5))
        if len(P):
            to = P - other.origin
            dist = np.linalg.norm(to, axis=1)
            t = self._cast(other.origin, to / dist[:, None])["t_hit"].astype(np.float64)
            visible &= t >= dist * (1.0 - 1e-5) - 1e-5
        return CameraTruth(P, pixels, other_pixels, visible)

    def laser_truth(self, position_steps: float) -> LaserTruth:
        """Exact laser-line ground truth for both cameras with the carriage at rest at ``position_steps``."""
        n, c = self.geometry.laser_plane(position_steps)
        origin = self.geometry.laser_origin(position_steps)
        left, right = self._views
        return LaserTruth(float(position_steps), n.copy(), c, self._camera_truth(left, right, n, c, origin),
                          self._camera_truth(right, left, n, c, origin))

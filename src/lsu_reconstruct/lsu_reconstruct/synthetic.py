"""Synthetic laser-line stereo data with analytic ground truth, for tests and benchmarks.

Deliberately independent of the code it is used to test: it imports nothing from this package,
builds its own cameras (OpenCV ``projectPoints`` with plumb_bob distortion makes the pixels),
intersects the laser plane with analytic surfaces (planes, spheres) by ray casting in closed form,
checks visibility from each camera by casting the ray back to the camera, and samples the
projected laser curve at every integer image row of each camera (as an extractor would report
it), with the true 3D point of every sample.

Geometry defaults follow the thesis' unit: 640x480 cameras, ~122 mm baseline, right camera
toed in ~17 deg, subject ~300 mm away, a vertical line laser moved along x by the carriage.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import yaml

from lsu_common.arrays import AnyArray

__all__ = ["Rig", "Plane", "Sphere", "Laser", "LineSamples", "default_rig", "laser_samples", "fit_plane",
           "fit_sphere"]


def _rot_y(deg: float) -> AnyArray:
    a = np.radians(deg)
    return np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])


def _rot_z(deg: float) -> AnyArray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


@dataclass
class Rig:
    """Two plumb_bob cameras; ``X_right = R X_left + T`` (left optical frame = world) [m]."""

    K1: AnyArray
    D1: AnyArray
    K2: AnyArray
    D2: AnyArray
    R: AnyArray
    T: AnyArray
    width: int = 640
    height: int = 480

    @property
    def right_centre(self) -> AnyArray:
        """Right camera centre in the left frame [m]."""
        return -self.R.T @ self.T

    def project(self, X: AnyArray, camera: str) -> AnyArray:
        """World points (N, 3) -> raw distorted pixels (N, 2) of ``camera`` ('left' or 'right')."""
        if camera == "left":
            R, T, K, D = np.eye(3), np.zeros(3), self.K1, self.D1
        else:
            R, T, K, D = self.R, self.T, self.K2, self.D2
        if len(X) == 0:
            return np.zeros((0, 2))
        rvec, _ = cv2.Rodrigues(R)
        px, _ = cv2.projectPoints(np.asarray(X, dtype=np.float64).reshape(-1, 1, 3), rvec, T.reshape(3, 1), K, D)
        return px.reshape(-1, 2)

    def write_calibration(self, folder: str | Path, swap: bool = False,
                          right_size: tuple[int, int] | None = None) -> Path:
        """Write left.yaml / right.yaml / stereo.yaml (CONTRIBUTING.md format) into ``folder``.

        ``swap=True`` writes what a user gets with the cameras exchanged: each file describes
        the other camera and the extrinsics are those of the reversed pair.
        """
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        K1, D1, K2, D2, R, T = self.K1, self.D1, self.K2, self.D2, self.R, self.T
        if swap:
            K1, D1, K2, D2, R, T = K2, D2, K1, D1, R.T, -R.T @ T

        def mat(a: AnyArray) -> dict:
            a = np.atleast_2d(np.asarray(a, dtype=float))
            return {"rows": int(a.shape[0]), "cols": int(a.shape[1]), "data": [float(x) for x in a.reshape(-1)]}

        for name, K, D, size in (("left", K1, D1, (self.width, self.height)),
                                 ("right", K2, D2, right_size or (self.width, self.height))):
            doc = {"image_width": int(size[0]), "image_height": int(size[1]), "camera_name": f"lsu_{name}",
                   "camera_matrix": mat(K), "distortion_model": "plumb_bob",
                   "distortion_coefficients": mat(np.asarray(D).reshape(1, -1)),
                   "rectification_matrix": mat(np.eye(3)),
                   "projection_matrix": mat(np.hstack([K, np.zeros((3, 1))]))}
            (folder / f"{name}.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
        tx = np.array([[0, -T[2], T[1]], [T[2], 0, -T[0]], [-T[1], T[0], 0]])
        E = tx @ R
        F = np.linalg.inv(K2).T @ E @ np.linalg.inv(K1)
        stereo = {"image_width": self.width, "image_height": self.height, "left_frame_id": "lsu_left_optical",
                  "right_frame_id": "lsu_right_optical", "rotation": mat(R), "translation": mat(T.reshape(3, 1)),
                  "essential": mat(E), "fundamental": mat(F / np.linalg.norm(F)), "rms_px": 0.1,
                  "date": "2026-01-01T00:00:00+00:00"}
        (folder / "stereo.yaml").write_text(yaml.safe_dump(stereo, sort_keys=False))
        return folder


def default_rig() -> Rig:
    """The thesis-like rig: f ~800 px, barrel distortion, 122 mm baseline, right camera toed in 17 deg."""
    K1 = np.array([[805.0, 0.0, 322.4], [0.0, 801.0, 236.7], [0.0, 0.0, 1.0]])
    K2 = np.array([[798.0, 0.0, 316.1], [0.0, 796.5, 243.2], [0.0, 0.0, 1.0]])
    D1 = np.array([-0.118, 0.092, 0.0012, -0.0007, -0.02])
    D2 = np.array([-0.104, 0.071, -0.0009, 0.0011, 0.01])
    right_axes = _rot_y(-17.0) @ _rot_z(0.4)  # columns: right camera axes in the left frame
    centre = np.array([0.1218, 0.0018, 0.0045])
    R = right_axes.T
    return Rig(K1=K1, D1=D1, K2=K2, D2=D2, R=R, T=-R @ centre)


@dataclass
class Plane:
    """Surface ``normal . X = offset`` (normal made unit) [m]."""

    normal: AnyArray
    offset: float

    def __post_init__(self) -> None:
        n = np.asarray(self.normal, dtype=float)
        scale = float(np.linalg.norm(n))
        self.normal = n / scale
        self.offset = float(self.offset) / scale

    @classmethod
    def facing(cls, depth_m: float, tilt: Sequence[float] = (0.08, -0.05)) -> Plane:
        """A plane through (0, 0, depth_m), slightly tilted so no axis is special."""
        n = np.array([tilt[0], tilt[1], 1.0])
        n = n / np.linalg.norm(n)
        return cls(n, float(n @ np.array([0.0, 0.0, depth_m])))

    def hit(self, origins: AnyArray, dirs: AnyArray) -> AnyArray:
        """Ray parameter of the hit (inf when none ahead)."""
        denom = dirs @ self.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (self.offset - origins @ self.normal) / denom
        return np.where((np.abs(denom) > 1e-12) & (t > 1e-9), t, np.inf)

    def normal_at(self, X: AnyArray) -> AnyArray:
        """Surface normal at points X (sign arbitrary: visibility tests use |.|)."""
        return np.broadcast_to(self.normal, X.shape)


@dataclass
class Sphere:
    """Sphere of ``radius`` around ``centre`` [m]."""

    centre: AnyArray
    radius: float

    def hit(self, origins: AnyArray, dirs: AnyArray) -> AnyArray:
        """Ray parameter of the first hit from outside (inf when none ahead)."""
        oc = origins - np.asarray(self.centre, dtype=float)
        a = np.einsum("ij,ij->i", dirs, dirs)
        b = np.einsum("ij,ij->i", oc, dirs)
        c = np.einsum("ij,ij->i", oc, oc) - self.radius ** 2
        disc = b * b - a * c
        root = np.sqrt(np.maximum(disc, 0.0))
        t = (-b - root) / a
        return np.where((disc >= 0) & (t > 1e-9), t, np.inf)

    def normal_at(self, X: AnyArray) -> AnyArray:
        """Outward normals at points X."""
        n = X - np.asarray(self.centre, dtype=float)
        return n / np.linalg.norm(n, axis=1, keepdims=True)


Surface = Plane | Sphere


@dataclass
class Laser:
    """A fan laser at ``origin`` whose plane contains the image-vertical (y) axis, yawed by ``yaw_deg``."""

    origin: AnyArray = field(default_factory=lambda: np.array([0.06, -0.01, -0.02]))
    yaw_deg: float = 8.0

    @classmethod
    def at(cls, x_m: float, yaw_deg: float = 8.0) -> Laser:
        """The laser with the carriage at ``x_m`` along the left camera's x axis."""
        return cls(np.array([x_m, -0.01, -0.02]), yaw_deg)

    def rays(self, n: int, half_angle_deg: float = 40.0) -> tuple[AnyArray, AnyArray]:
        """Unit ray directions of the fan (n, 3) and their elevation angles [rad]."""
        phi = np.linspace(-np.radians(half_angle_deg), np.radians(half_angle_deg), n)
        fwd = _rot_y(self.yaw_deg) @ np.array([0.0, 0.0, 1.0])
        return np.cos(phi)[:, None] * fwd + np.sin(phi)[:, None] * np.array([0.0, 1.0, 0.0]), phi

    def ray(self, phi: AnyArray) -> AnyArray:
        """Ray directions at elevation angles ``phi`` [rad]."""
        fwd = _rot_y(self.yaw_deg) @ np.array([0.0, 0.0, 1.0])
        return np.cos(phi)[:, None] * fwd + np.sin(phi)[:, None] * np.array([0.0, 1.0, 0.0])


def _first_hit(scene: Sequence[Surface], origins: AnyArray, dirs: AnyArray) -> tuple[AnyArray, AnyArray]:
    ts = np.stack([s.hit(origins, dirs) for s in scene], axis=0)
    which = np.argmin(ts, axis=0)
    return ts[which, np.arange(len(dirs))], which


def _lit_points(scene: Sequence[Surface], laser: Laser, phi: AnyArray) -> tuple[AnyArray, AnyArray, AnyArray]:
    dirs = laser.ray(phi)
    origins = np.broadcast_to(laser.origin, dirs.shape)
    t, which = _first_hit(scene, origins, dirs)
    X = origins + np.where(np.isfinite(t), t, 0.0)[:, None] * dirs
    return X, np.isfinite(t), which


def _visible(scene: Sequence[Surface], X: AnyArray, which: AnyArray, centre: AnyArray) -> AnyArray:
    # Visible when the first surface hit from the camera centre towards X is X itself.
    d = X - centre
    dist = np.linalg.norm(d, axis=1)
    t, _ = _first_hit(scene, np.broadcast_to(centre, X.shape), d / np.maximum(dist, 1e-12)[:, None])
    return np.abs(t - dist) < 1e-7


@dataclass
class LineSamples:
    """One camera's laser line: one sample per integer image row, with its true 3D point."""

    u: AnyArray
    v: AnyArray
    X: AnyArray  # (N, 3) true points [m]

    def __len__(self) -> int:
        return int(len(self.u))

    def noisy(self, sigma_px: float, rng: np.random.Generator) -> LineSamples:
        """The same line with Gaussian noise of ``sigma_px`` on u (what a sub-pixel extractor leaves)."""
        return LineSamples(self.u + rng.normal(0.0, sigma_px, self.u.shape), self.v.copy(), self.X)

    def pixel_quantised(self) -> LineSamples:
        """u rounded to the pixel centre (the thesis' brute-force maximum search)."""
        return LineSamples(np.round(self.u), self.v.copy(), self.X)

    def without_rows(self, lo: float, hi: float) -> LineSamples:
        """Drop rows lo <= v < hi (something hides the laser from this camera there)."""
        keep = (self.v < lo) | (self.v >= hi)
        return LineSamples(self.u[keep], self.v[keep], self.X[keep])


def laser_samples(rig: Rig, scene: Sequence[Surface], laser: Laser, camera: str,
                  dense: int = 40001) -> LineSamples:
    """Sample the laser curve seen by ``camera`` at every integer row where it is lit and visible."""
    _, phi = laser.rays(dense)
    X, lit, which = _lit_points(scene, laser, phi)
    centre = np.zeros(3) if camera == "left" else rig.right_centre
    ok = lit & _visible(scene, X, which, centre)
    px = np.full((dense, 2), np.nan)
    px[ok] = rig.project(X[ok], camera)
    ok &= (px[:, 0] >= -0.5) & (px[:, 0] <= rig.width - 0.5) & (px[:, 1] >= -0.5) & (px[:, 1] <= rig.height - 0.5)
    v = px[:, 1]
    # Integer rows crossed between consecutive visible samples of the same surface.
    seg = ok[:-1] & ok[1:] & (which[:-1] == which[1:])
    lo, hi = np.minimum(v[:-1], v[1:]), np.maximum(v[:-1], v[1:])
    rows_out: list[float] = []
    phis: list[float] = []
    seen = set()
    for i in np.nonzero(seg & (np.floor(hi) >= np.ceil(lo)))[0]:
        for r in range(int(np.ceil(lo[i])), int(np.floor(hi[i])) + 1):
            if r in seen or r < 0 or r >= rig.height:
                continue  # one sample per row, like an extractor
            seen.add(r)
            f = (r - v[i]) / (v[i + 1] - v[i]) if v[i + 1] != v[i] else 0.0
            rows_out.append(float(r))
            phis.append(phi[i] + f * (phi[i + 1] - phi[i]))
    if not rows_out:
        return LineSamples(np.zeros(0), np.zeros(0), np.zeros((0, 3)))
    rows = np.array(rows_out)
    ph = np.array(phis)
    step = phi[1] - phi[0]
    for _ in range(3):  # Newton on v(phi) = row, with a central-difference slope
        Xa, _, _ = _lit_points(scene, laser, ph)
        Xb, _, _ = _lit_points(scene, laser, ph + 1e-3 * step)
        va = rig.project(Xa, camera)[:, 1]
        vb = rig.project(Xb, camera)[:, 1]
        ph = ph - (va - rows) / ((vb - va) / (1e-3 * step))
    Xf, _, _ = _lit_points(scene, laser, ph)
    pf = rig.project(Xf, camera)
    order = np.argsort(rows)
    return LineSamples(pf[order, 0], rows[order], Xf[order])


def fit_plane(X: AnyArray) -> tuple[AnyArray, float]:
    """Least-squares plane (unit normal, offset) through points (N, 3)."""
    c = X.mean(axis=0)
    _, _, vt = np.linalg.svd(X - c, full_matrices=False)
    n = vt[-1]
    return n, float(n @ c)


def fit_sphere(X: AnyArray) -> tuple[AnyArray, float]:
    """Least-squares sphere (centre, radius): algebraic fit refined by Gauss-Newton on the distances."""
    A = np.hstack([2 * X, np.ones((len(X), 1))])
    b = np.einsum("ij,ij->i", X, X)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    c = sol[:3]
    r = float(np.sqrt(sol[3] + c @ c))
    for _ in range(10):
        d = X - c
        dist = np.linalg.norm(d, axis=1)
        J = np.hstack([-d / dist[:, None], -np.ones((len(X), 1))])
        res = dist - r
        delta, *_ = np.linalg.lstsq(J, -res, rcond=None)
        c = c + delta[:3]
        r = r + float(delta[3])
    return c, r

"""Procedural synthetic heads: identity parameters + pose -> a closed triangle mesh and its nose tip.

A head is an ellipsoid displaced along its radius by smooth Gaussian features laid out in angular
face coordinates (alpha: azimuth from the face direction, positive towards +x; beta: elevation,
positive up): nose (tip, bridge, wings), eye sockets, brow ridge, cheekbones, lips, chin, ears.
Every size and amplitude is an identity parameter drawn from ``identity_seed``, so the same seed
always gives the same person and different seeds give measurably different faces (what the face
package's gallery needs for 50+ identities).

Head frame (the mesh frame): origin at the head centre, x to the subject's left as the camera sees
it (right in the image), y down, z away from the camera: an unposed head looks along -z, towards a
camera whose optical axis is +z. Pose = yaw (about y, positive turns the face towards -x), pitch
(about x, positive nods the face down), roll (about z), applied about the origin in that order.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from lsu_common.arrays import AnyArray

from .scenes import AlbedoFn, SceneObject


@dataclass(frozen=True)
class HeadIdentity:
    """Shape and skin parameters of one synthetic person (metres, radians, albedo units)."""

    half_width_m: float = 0.075
    half_height_m: float = 0.115
    half_depth_m: float = 0.095
    nose_protrusion_m: float = 0.022
    nose_width_rad: float = 0.085
    nose_length_rad: float = 0.30
    nose_tip_beta_rad: float = 0.0
    eye_separation_rad: float = 0.32
    eye_depth_m: float = 0.010
    eye_beta_rad: float = 0.30
    brow_m: float = 0.004
    cheek_m: float = 0.006
    lips_m: float = 0.006
    mouth_beta_rad: float = -0.26
    chin_m: float = 0.008
    ear_m: float = 0.012
    skin_tone: float = 1.0

    @classmethod
    def from_seed(cls, identity_seed: int) -> HeadIdentity:
        """Draw every parameter around the mean face (seeded, so identities are reproducible)."""
        rng = np.random.default_rng(np.random.SeedSequence([0x4EAD, int(identity_seed)]))
        mean = cls()
        spread = {"half_width_m": 0.06, "half_height_m": 0.05, "half_depth_m": 0.06, "nose_protrusion_m": 0.18,
                  "nose_width_rad": 0.15, "nose_length_rad": 0.12, "eye_separation_rad": 0.08,
                  "eye_depth_m": 0.25, "brow_m": 0.35, "cheek_m": 0.35, "lips_m": 0.25, "chin_m": 0.30,
                  "ear_m": 0.2, "skin_tone": 0.12}
        shifts = {"nose_tip_beta_rad": 0.03, "eye_beta_rad": 0.03, "mouth_beta_rad": 0.03}
        values: dict[str, float] = {}
        for f in fields(cls):
            base = getattr(mean, f.name)
            if f.name in spread:
                values[f.name] = float(base * np.clip(1.0 + spread[f.name] * rng.standard_normal(), 0.4, 1.8))
            else:
                values[f.name] = float(base + shifts[f.name] * rng.standard_normal())
        return cls(**values)


@dataclass
class Head:
    """A posed synthetic head in its mesh frame (origin = head centre)."""

    mesh: o3d.geometry.TriangleMesh
    nose_tip_m: AnyArray          # (3,) mesh frame, after pose: a vertex of the mesh
    identity: HeadIdentity
    pose_R: AnyArray              # head frame -> mesh frame rotation
    identity_seed: int

    def albedo_in(self, translation: AnyArray) -> AlbedoFn:
        """Albedo function for this head placed at ``translation`` (left frame)."""
        return _skin_albedo(self.identity, self.pose_R, np.asarray(translation, dtype=np.float64), self.identity_seed)


def _bump(alpha: AnyArray, beta: AnyArray, a0: float, b0: float, sa: float, sb: float, amp: float) -> AnyArray:
    da = np.angle(np.exp(1j * (alpha - a0)))  # wrap so features near alpha = +-pi stay continuous
    return amp * np.exp(-0.5 * ((da / sa) ** 2 + ((beta - b0) / sb) ** 2))


def _face_angles(d: AnyArray) -> tuple[AnyArray, AnyArray]:
    """(alpha, beta) of unit directions (head frame)."""
    alpha = np.arctan2(d[:, 0], -d[:, 2])
    beta = np.arcsin(np.clip(-d[:, 1], -1.0, 1.0))
    return alpha, beta


def head_radius(identity: HeadIdentity, d: AnyArray) -> AnyArray:
    """Distance from the head centre to the surface along unit directions ``d`` (N,3)."""
    p = identity
    r0 = 1.0 / np.sqrt((d[:, 0] / p.half_width_m) ** 2 + (d[:, 1] / p.half_height_m) ** 2
                       + (d[:, 2] / p.half_depth_m) ** 2)
    a, b = _face_angles(d)
    disp = _bump(a, b, 0.0, p.nose_tip_beta_rad, p.nose_width_rad, 0.08, p.nose_protrusion_m)
    for k in range(1, 7):  # the bridge: a ridge rising from the tip towards the brows, lower and narrower
        frac = k / 6.0
        disp += _bump(a, b, 0.0, p.nose_tip_beta_rad + frac * p.nose_length_rad, 0.75 * p.nose_width_rad,
                      0.06, p.nose_protrusion_m * (0.55 - 0.35 * frac) / 2.2)
    for side in (-1.0, 1.0):
        disp += _bump(a, b, side * 1.55 * p.nose_width_rad, p.nose_tip_beta_rad - 0.06, 0.05, 0.04, 0.006)
        disp += _bump(a, b, side * p.eye_separation_rad, p.eye_beta_rad, 0.12, 0.07, -p.eye_depth_m)
        disp += _bump(a, b, side * 0.30, p.eye_beta_rad + 0.13, 0.22, 0.05, p.brow_m)
        disp += _bump(a, b, side * 0.50, p.nose_tip_beta_rad + 0.02, 0.15, 0.12, p.cheek_m)
        disp += _bump(a, b, side * np.pi / 2, 0.05, 0.08, 0.16, p.ear_m)
    disp += _bump(a, b, 0.0, p.mouth_beta_rad + 0.04, 0.16, 0.04, p.lips_m)
    disp += _bump(a, b, 0.0, p.mouth_beta_rad - 0.05, 0.14, 0.04, 0.8 * p.lips_m)
    disp += _bump(a, b, 0.0, p.mouth_beta_rad, 0.15, 0.015, -0.003)
    disp += _bump(a, b, 0.0, p.mouth_beta_rad - 0.30, 0.16, 0.10, p.chin_m)
    return r0 + disp


def _uv_sphere(n_lat: int, n_lon: int) -> tuple[AnyArray, AnyArray]:
    """Unit directions and triangles of a latitude/longitude sphere with its poles on the y axis."""
    theta = np.linspace(0.0, np.pi, n_lat + 1)[1:-1]           # from -y (top) to +y (bottom), poles apart
    phi = np.linspace(0.0, 2 * np.pi, n_lon, endpoint=False)   # 0 = towards -z (the face)
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    dirs = np.stack([np.sin(th) * np.sin(ph), -np.cos(th), -np.sin(th) * np.cos(ph)], axis=-1).reshape(-1, 3)
    dirs = np.vstack([dirs, [[0.0, -1.0, 0.0], [0.0, 1.0, 0.0]]])
    top, bottom = len(dirs) - 2, len(dirs) - 1
    rows = n_lat - 1
    i, j = np.meshgrid(np.arange(rows - 1), np.arange(n_lon), indexing="ij")
    a = i * n_lon + j
    b = i * n_lon + (j + 1) % n_lon
    c = (i + 1) * n_lon + j
    d = (i + 1) * n_lon + (j + 1) % n_lon
    quads = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    j1 = np.arange(n_lon)
    cap_top = np.stack([np.full(n_lon, top), j1, (j1 + 1) % n_lon], -1)
    last = (rows - 1) * n_lon
    cap_bottom = np.stack([np.full(n_lon, bottom), last + (j1 + 1) % n_lon, last + j1], -1)
    return dirs, np.concatenate([quads, cap_top, cap_bottom]).astype(np.int32)


def make_head(identity_seed: int, yaw_deg: float = 0.0, pitch_deg: float = 0.0, roll_deg: float = 0.0,
              resolution: tuple[int, int] = (180, 360)) -> Head:
    """A synthetic head for ``identity_seed`` in the given pose; deterministic.

    ``resolution`` = (latitude rows, longitude columns): the default gives ~1.7 mm edges. The nose
    tip is the mesh vertex furthest towards -z in the unposed head (the most prominent point seen
    from the front), carried through the pose.
    """
    identity = HeadIdentity.from_seed(identity_seed)
    dirs, tris = _uv_sphere(*resolution)
    verts = dirs * head_radius(identity, dirs)[:, None]
    alpha, _ = _face_angles(dirs)
    front = np.abs(alpha) < 0.3
    tip_index = int(np.flatnonzero(front)[np.argmin(verts[front, 2])])
    R = Rotation.from_euler("zxy", [roll_deg, pitch_deg, yaw_deg], degrees=True).as_matrix()
    posed = verts @ R.T
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(posed), o3d.utility.Vector3iVector(tris))
    mesh.compute_vertex_normals()
    return Head(mesh, posed[tip_index].copy(), identity, R, int(identity_seed))


def _skin_albedo(identity: HeadIdentity, pose_R: AnyArray, translation: AnyArray, seed: int) -> AlbedoFn:
    rng = np.random.default_rng(np.random.SeedSequence([0x5C1, int(seed)]))
    freqs = rng.normal(size=(5, 3)) / 0.015
    phases = rng.uniform(0, 2 * np.pi, 5)
    skin = np.array([0.46, 0.55, 0.74]) * identity.skin_tone
    lips = np.array([0.35, 0.35, 0.62]) * identity.skin_tone
    brow = np.array([0.10, 0.11, 0.13])
    p = identity

    def albedo(points: AnyArray, du: AnyArray, dv: AnyArray) -> AnyArray:
        local = (points - translation) @ pose_R  # left frame -> head frame
        d = local / np.maximum(np.linalg.norm(local, axis=1, keepdims=True), 1e-12)
        a, b = _face_angles(d)
        out = skin[None, :] * (1.0 + 0.06 * np.sin(local @ freqs.T + phases).mean(axis=1, keepdims=True))
        w_lips = np.clip(_bump(a, b, 0.0, p.mouth_beta_rad, 0.13, 0.035, 1.0) * 1.5, 0.0, 1.0)[:, None]
        w_brow = np.zeros(len(points))
        for side in (-1.0, 1.0):
            w_brow = np.maximum(w_brow, _bump(a, b, side * 0.30, p.eye_beta_rad + 0.14, 0.12, 0.025, 1.0))
        w_brow = np.clip(w_brow * 1.6, 0.0, 1.0)[:, None]
        out = out * (1 - w_lips) + lips * w_lips
        out = out * (1 - w_brow) + brow * w_brow
        return np.clip(out, 0.0, 1.0)

    return albedo


def head_object(head: Head, translation: AnyArray, name: str = "head") -> SceneObject:
    """The head placed with its centre at ``translation`` (left frame) as a scene object."""
    t = np.asarray(translation, dtype=np.float64)
    mesh = o3d.geometry.TriangleMesh(head.mesh)
    mesh.translate(t)
    return SceneObject(name, mesh, head.albedo_in(t), 0.25,
                       {"nose_tip_m": head.nose_tip_m + t, "identity_seed": head.identity_seed, "head_center_m": t},
                       material="skin")

"""Realistic synthetic people for the simulated rig: real head meshes with identity morphs, hair, shoulders.

A person is built from ``config/heads/`` (see its CREDITS.md):

- ``makehuman_bust.npz``: MakeHuman's CC0 base mesh cut to head, neck and shoulders (metres), with its
  eyeballs, and the CC0 face morph targets (nose, mouth, chin, cheeks, forehead, brows, eyes, head
  shape) and expression units (open mouth, smile) restricted to those vertices. An identity is a seeded
  set of slider values (MakeHuman's own sliders, sigma 0.3), so the same seed gives the same person.
- ``leeperrysmith_bust.npz``: a real 3D head-and-shoulders scan (Lee Perry-Smith, CC BY 3.0), for a
  face that is not MakeHuman's topology (``base="leeperrysmith"``; no morphs: one identity, scaled).

On top: a hair volume (the scalp pushed out by a seeded thickness with strands' roughness and a dark
albedo), optional glasses (two rims, a bridge and temples) and an optional raised hand (palm and
fingers beside or in front of the face: what fools a nose finder that only looks for the most
protruding point).

Frames are those of ``sim/head.py``: the person's frame has its origin at the head centre, x to the
subject's left as the camera sees it (right in the image), y down, z away from the camera (an unposed
person looks along -z). Pose = yaw (about y), pitch (about x), roll (about z), as ``make_head``.
Truth: ``landmarks`` (pronasale = nose tip, eye centres, mouth centre, chin) are vertices of the
generator's mesh carried through morphs, subdivision and pose, never found by any face code.

Build the assets once from the original files: ``python -m lsu_sim.people build-assets
MAKEHUMAN_DIR LEEPERRYSMITH_DIR OUT_DIR``.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from lsu_common.arrays import AnyArray
from lsu_config import config_dir

from .scenes import AlbedoFn, SceneError, SceneObject

__all__ = ["PersonSpec", "Person", "make_person", "person_objects", "heads_dir", "build_assets", "EXPRESSIONS"]

# MakeHuman sliders used for identities (groups of modeling_modifiers.json) and the expression units kept
_ID_GROUPS = ("head", "forehead", "eyebrows", "nose", "mouth", "chin", "cheek", "eyes")
_EXPRESSION_UNITS = ("mouth-open", "mouth-corner-puller", "mouth-elevation", "mouth-upward-retraction",
                     "eyebrows-left-up", "eyebrows-right-up", "eye-left-slit", "eye-right-slit")
# expression name -> {unit: weight at strength 1}
EXPRESSIONS: dict[str, dict[str, float]] = {
    "neutral": {},
    "open_mouth": {"mouth-open": 1.0},
    "smile": {"mouth-corner-puller": 1.0, "mouth-upward-retraction": 0.5, "eye-left-slit": 0.3,
              "eye-right-slit": 0.3},
    "surprise": {"mouth-open": 0.6, "eyebrows-left-up": 1.0, "eyebrows-right-up": 1.0},
}
_BUST_MIN_Y_DM = 4.6          # base.obj y (decimetres) of the lowest kept vertex: shoulders and upper chest
_HEAD_CENTRE_DM = np.array([0.0, 7.2, 0.65])   # base.obj: middle of the cranium (origin of the person frame)
_NOSE_VERTEX = 297            # base.obj pronasale (PROVENANCE of the MakeHuman data)
_LPS_UNIT_M = 0.047           # Lee Perry-Smith units -> metres (head breadth 15 cm; +-5 %)


def heads_dir() -> Path:
    """``config/heads`` of this workspace."""
    return config_dir() / "heads"


# ------------------------------------------------------------------------------------------ asset building
def _read_obj(path: Path) -> tuple[AnyArray, list[list[int]], list[str]]:
    verts: list[list[float]] = []
    faces: list[list[int]] = []
    groups: list[str] = []
    group = ""
    with open(path) as fh:
        for line in fh:
            if line.startswith("v "):
                verts.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("g "):
                group = line.split()[1]
            elif line.startswith("f "):
                faces.append([int(t.split("/")[0]) - 1 for t in line.split()[1:]])
                groups.append(group)
    return np.asarray(verts), faces, groups


def _read_target(path: Path) -> tuple[AnyArray, AnyArray]:
    rows = [ln.split() for ln in open(path) if ln.strip() and not ln.startswith("#")]
    a = np.asarray(rows, dtype=np.float64).reshape(-1, 4)
    return a[:, 0].astype(np.int64), a[:, 1:]


def _triangulate(quads: Sequence[Sequence[int]]) -> AnyArray:
    tris = []
    for f in quads:
        for k in range(1, len(f) - 1):
            tris.append([f[0], f[k], f[k + 1]])
    return np.asarray(tris, dtype=np.int64)


def build_assets(makehuman_dir: str | Path, lps_dir: str | Path, out_dir: str | Path) -> list[Path]:
    """Cut, convert and save the bust meshes and the morph targets used here (see the module doc)."""
    mh, lps, out = Path(makehuman_dir), Path(lps_dir), Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    V, faces, groups = _read_obj(mh / "base.obj")
    keep_faces = [f for f, g in zip(faces, groups)
                  if (g == "body" and V[f, 1].min() >= _BUST_MIN_Y_DM) or g in ("helper-r-eye", "helper-l-eye")]
    part = np.asarray([0 if g == "body" else 1 for f, g in zip(faces, groups)
                       if (g == "body" and V[f, 1].min() >= _BUST_MIN_Y_DM) or g in ("helper-r-eye", "helper-l-eye")])
    used = np.unique(np.concatenate([np.asarray(f) for f in keep_faces]))
    inv = np.full(len(V), -1, dtype=np.int64)
    inv[used] = np.arange(len(used))
    tris = inv[_triangulate(keep_faces)]
    tri_part = np.repeat(part, [len(f) - 2 for f in keep_faces])
    # person frame: origin at the head centre, x subject's left (image right), y down, z away from the camera
    flip = np.array([1.0, -1.0, -1.0])
    verts_m = (V[used] - _HEAD_CENTRE_DM) * 0.1 * flip
    arrays: dict[str, Any] = {"vertices": verts_m.astype(np.float32), "triangles": tris.astype(np.int32),
                                     "eye_triangle": (tri_part == 1), "nose_vertex": np.array(inv[_NOSE_VERTEX])}
    mods = json.loads((mh / "modifiers" / "modeling_modifiers.json").read_text())
    sliders: list[dict[str, Any]] = []
    names: list[str] = []

    def add_target(name: str, path: Path) -> None:
        idx, d = _read_target(path)
        k = inv[idx]
        ok = k >= 0
        if not np.any(ok):
            return
        arrays[f"t:{name}:i"] = k[ok].astype(np.int32)
        arrays[f"t:{name}:d"] = (d[ok] * 0.1 * flip).astype(np.float32)
        names.append(name)

    for g in mods:
        if g["group"] not in _ID_GROUPS:
            continue
        for m in g["modifiers"]:
            t = m["target"]
            if t.startswith(("head-trans", "head-angle")):
                continue   # these move or tilt the head rather than shape it
            files = ([f"{t}-{m['min']}", f"{t}-{m['max']}"] if "min" in m else [t])
            for f in files:
                add_target(f, mh / "targets" / g["group"] / f"{f}.target")
            sliders.append({"group": g["group"], "target": t, "files": files})
    for unit in _EXPRESSION_UNITS:
        add_target(f"expr:{unit}", mh / "targets" / "expression" / "units" / "caucasian" / f"{unit}.target")
    arrays["sliders_json"] = np.array(json.dumps([s for s in sliders if all(f in names for f in s["files"])]))
    assets = [out / "makehuman_bust.npz"]
    np.savez_compressed(assets[0], **arrays)
    # Lee Perry-Smith: +Y up, +Z the face direction, arbitrary units -> the person frame in metres
    LV, lfaces, _ = _read_obj(lps / "LeePerrySmith.obj")
    lv = LV * _LPS_UNIT_M * flip
    ltris = _triangulate(lfaces)
    front = lv[:, 2] < np.percentile(lv[:, 2], 5)
    head = lv[:, 1] < np.percentile(lv[:, 1], 60)
    nose = int(np.flatnonzero(front & head)[np.argmin(lv[front & head, 2])])
    # origin at the cranium's middle: 0.10 m behind the nose tip, level with it
    centre = lv[nose] + np.array([0.0, -0.01, 0.10])
    lv = lv - centre
    assets.append(out / "leeperrysmith_bust.npz")
    np.savez_compressed(assets[1], vertices=lv.astype(np.float32), triangles=ltris.astype(np.int32),
                        nose_vertex=np.array(nose))
    return assets


# ------------------------------------------------------------------------------------------ assets
_ASSETS: dict[str, dict[str, AnyArray]] = {}


def _assets(name: str) -> dict[str, AnyArray]:
    """The arrays of ``config/heads/<name>.npz`` (read once per process: constant data)."""
    if name not in _ASSETS:
        path = heads_dir() / f"{name}.npz"
        if not path.exists():
            raise SceneError(f"{path} is missing; it ships with the repository (config/heads), or rebuild it with "
                             f"python -m lsu_sim.people build-assets")
        with np.load(path, allow_pickle=False) as z:
            _ASSETS[name] = {k: z[k] for k in z.files}
    return _ASSETS[name]


# ------------------------------------------------------------------------------------------ people
@dataclass(frozen=True)
class PersonSpec:
    """What to build: identity, expression, extras and pose."""

    identity_seed: int = 0
    base: str = "makehuman"              # or "leeperrysmith" (a real scan; one identity, scaled by the seed)
    expression: str = "neutral"          # one of EXPRESSIONS
    expression_strength: float = 1.0
    hair_m: float | None = None       # hair thickness on the crown; None: drawn from the seed (5-40 mm)
    fringe: bool = False                 # hair over the upper forehead
    glasses: bool = False
    hand: str | None = None           # None, "beside" (raised beside the face) or "front" (fist before the chin)
    yaw_deg: float = 0.0
    pitch_deg: float = 0.0
    roll_deg: float = 0.0
    identity_sigma: float = 0.3          # MakeHuman slider spread (0.25-0.3: varied, plausible adults)
    subdivide: bool = True               # one Loop subdivision (MakeHuman's ~5 mm quads -> ~2.5 mm, smooth)


@dataclass
class Person:
    """A posed person in its own frame (origin = head centre): meshes and the true landmarks."""

    parts: dict[str, o3d.geometry.TriangleMesh]     # skin, hair, glasses, hand (present ones)
    landmarks: dict[str, AnyArray]                # nose_tip, eye_r, eye_l, mouth, chin (posed, person frame)
    spec: PersonSpec
    pose_R: AnyArray
    identity_weights: dict[str, float] = field(default_factory=dict)


def _identity_weights(seed: int, sigma: float, sliders: list[dict[str, object]]) -> dict[str, float]:
    rng = np.random.default_rng(np.random.SeedSequence([0x9E0, int(seed)]))
    weights: dict[str, float] = {}
    right: dict[str, float] = {}
    for s in sliders:
        t = str(s["target"])
        files = [str(f) for f in s["files"]]  # type: ignore[attr-defined]
        base = t[2:] if t.startswith(("l-", "r-")) else None
        v = rng.normal(0.0, sigma)
        if base is not None and t.startswith("l-") and base in right:
            v = right[base] + rng.normal(0.0, 0.05)     # faces are nearly symmetric
        elif base is not None:
            right[base] = v
        v = float(np.clip(v, -1.0, 1.0))
        if len(files) == 2:
            weights[files[0] if v < 0 else files[1]] = abs(v)
        else:
            weights[files[0]] = abs(v)
    return weights


def _apply(verts: AnyArray, a: dict[str, AnyArray], weights: dict[str, float]) -> AnyArray:
    out = verts.astype(np.float64).copy()
    for name, w in weights.items():
        if w == 0 or f"t:{name}:i" not in a:
            continue
        np.add.at(out, a[f"t:{name}:i"], w * a[f"t:{name}:d"].astype(np.float64))
    return out


def _smooth_noise(points: AnyArray, rng: np.random.Generator, scale_m: float, n: int = 8) -> AnyArray:
    """Smooth seeded scalar field in [-1, 1] over 3D points (sum of random sinusoids)."""
    freqs = rng.normal(size=(n, 3)) / scale_m
    phases = rng.uniform(0, 2 * np.pi, n)
    return np.sin(points @ freqs.T + phases).mean(axis=1) * np.sqrt(2.0)


def _vertex_normals(v: AnyArray, t: AnyArray) -> AnyArray:
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(t))
    m.compute_vertex_normals()
    return np.asarray(m.vertex_normals)


def _hair(verts: AnyArray, tris: AnyArray, eye_tri: AnyArray, landmarks: dict[str, AnyArray],
          spec: PersonSpec, rng: np.random.Generator) -> o3d.geometry.TriangleMesh | None:
    """A hair shell: the scalp's triangles pushed out along the normals by a seeded thickness."""
    thickness = spec.hair_m if spec.hair_m is not None else float(rng.uniform(0.005, 0.040))
    if thickness <= 0:
        return None
    brow_y = min(landmarks["eye_r"][1], landmarks["eye_l"][1]) - 0.035   # y down: above the brows
    if spec.fringe:
        brow_y += 0.025
    # hairline: above the forehead at the front, down to the ear tops at the sides, the nape at the back
    front = -verts[:, 2]                         # > 0 towards the face
    hairline = np.where(front > 0.03, brow_y - 0.03 * rng.uniform(0.5, 1.5),
                        np.where(front > -0.04, -0.005, 0.06))
    on_scalp = (verts[:, 1] < hairline) & (np.linalg.norm(verts[:, [0, 2]], axis=1) < 0.14) & (verts[:, 1] > -0.2)
    tri_in = on_scalp[tris].all(axis=1) & ~eye_tri
    if tri_in.sum() < 10:
        return None
    normals = _vertex_normals(verts, tris)
    used = np.unique(tris[tri_in])
    inv = np.full(len(verts), -1)
    inv[used] = np.arange(len(used))
    p = verts[used]
    # thicker on the crown, thinner at the hairline; strands' roughness of a few millimetres
    crown = np.clip((hairline[used] - p[:, 1]) / 0.05, 0.15, 1.0)
    rough = 0.3 * thickness * _smooth_noise(p, rng, 0.02) + 0.0015 * _smooth_noise(p, rng, 0.003)
    shell = p + normals[used] * np.maximum(thickness * crown + rough, 0.002)[:, None]
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(shell), o3d.utility.Vector3iVector(inv[tris[tri_in]]))
    return mesh


def _glasses(landmarks: dict[str, AnyArray]) -> o3d.geometry.TriangleMesh:
    parts = o3d.geometry.TriangleMesh()
    er, el = landmarks["eye_r"], landmarks["eye_l"]
    z = min(er[2], el[2]) - 0.014                         # rims ~14 mm in front of the eyes
    for e in (er, el):
        rim = o3d.geometry.TriangleMesh.create_torus(torus_radius=0.022, tube_radius=0.0025, radial_resolution=40,
                                                     tubular_resolution=8)
        v = np.asarray(rim.vertices)   # torus in the xy plane? open3d: around z; make it an ellipse in x-y
        v = v[:, [0, 1, 2]] * np.array([1.05, 0.75, 1.0])
        rim.vertices = o3d.utility.Vector3dVector(v + np.array([e[0], e[1], z]))
        parts += rim
    bridge = o3d.geometry.TriangleMesh.create_cylinder(radius=0.002, height=abs(el[0] - er[0]) - 0.044)
    R = Rotation.from_euler("y", 90, degrees=True).as_matrix()
    bridge.rotate(R, center=(0, 0, 0))
    bridge.translate(((er[0] + el[0]) / 2, (er[1] + el[1]) / 2 - 0.004, z))
    parts += bridge
    for e, side in ((er, -1.0), (el, 1.0)):
        temple = o3d.geometry.TriangleMesh.create_cylinder(radius=0.0018, height=0.10)
        temple.translate((e[0] + side * 0.024, e[1], z + 0.05))
        parts += temple
    return parts


def _hand(landmarks: dict[str, AnyArray], where: str, rng: np.random.Generator) -> o3d.geometry.TriangleMesh:
    """A raised hand: a palm (flattened ellipsoid) and four fingers (capsules), pointing up."""
    nose = landmarks["nose_tip"]
    if where == "front":      # a fist before the chin, knuckles towards the camera: protrudes beyond the nose
        centre = landmarks["chin"] + np.array([0.0, 0.01, -0.05])
        palm_scale = np.array([0.045, 0.040, 0.035])
    elif where == "beside":   # an open hand raised beside the face, palm to the camera
        centre = nose + np.array([0.105 * (1 if rng.uniform() < 0.5 else -1), -0.01, -0.01])
        palm_scale = np.array([0.042, 0.050, 0.014])
    else:
        raise SceneError(f"hand must be None, 'beside' or 'front' (got {where!r})")
    palm = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=30)
    palm.vertices = o3d.utility.Vector3dVector(np.asarray(palm.vertices) * palm_scale + centre)
    hand = palm
    for k in range(4):
        x = centre[0] + (k - 1.5) * 0.019
        if where == "front":   # curled fingers: knuckle bumps in front of the fist
            f = o3d.geometry.TriangleMesh.create_sphere(radius=0.011, resolution=16)
            f.translate((x, centre[1] - 0.02, centre[2] - palm_scale[2] + 0.004))
        else:
            f = o3d.geometry.TriangleMesh.create_cylinder(radius=0.009, height=0.07 + 0.01 * (k in (1, 2)))
            f.rotate(Rotation.from_euler("x", 90, degrees=True).as_matrix(), center=(0, 0, 0))
            f.translate((x, centre[1] - palm_scale[1] - 0.03, centre[2]))
        hand += f
    return hand


def make_person(spec: PersonSpec = PersonSpec()) -> Person:
    """Build the person of ``spec`` (deterministic: same spec, same meshes, in every process)."""
    if spec.expression not in EXPRESSIONS:
        raise SceneError(f"expression must be one of {', '.join(EXPRESSIONS)} (got {spec.expression!r})")
    rng = np.random.default_rng(np.random.SeedSequence([0x9E1, int(spec.identity_seed)]))
    if spec.base == "makehuman":
        a = _assets("makehuman_bust")
        sliders = json.loads(str(a["sliders_json"]))
        weights = _identity_weights(spec.identity_seed, spec.identity_sigma, sliders)
        expr = {f"expr:{u}": w * spec.expression_strength for u, w in EXPRESSIONS[spec.expression].items()}
        verts = _apply(a["vertices"], a, {**weights, **expr})
        tris = a["triangles"].astype(np.int64)
        eye_tri = a["eye_triangle"].astype(bool)
        nose_i = int(a["nose_vertex"])
    elif spec.base == "leeperrysmith":
        a = _assets("leeperrysmith_bust")
        weights = {}
        if spec.expression != "neutral":
            raise SceneError("the Lee Perry-Smith scan has no expressions; use base='makehuman'")
        scale = float(np.clip(1.0 + 0.05 * rng.standard_normal(), 0.9, 1.1)) if spec.identity_seed else 1.0
        verts = a["vertices"].astype(np.float64) * scale
        tris = a["triangles"].astype(np.int64)
        eye_tri = np.zeros(len(tris), bool)
        nose_i = int(a["nose_vertex"])
    else:
        raise SceneError(f"base must be 'makehuman' or 'leeperrysmith' (got {spec.base!r})")
    if spec.subdivide:
        # Loop subdivision keeps the original vertices first (moved by the smoothing rule): indices stay valid
        n_eye = int(eye_tri.sum())
        skin = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector(tris[~eye_tri]))
        skin = skin.subdivide_loop(1)
        sv, st = np.asarray(skin.vertices), np.asarray(skin.triangles)
        if n_eye:
            verts = np.vstack([sv, verts])
            tris = np.vstack([st, tris[eye_tri] + len(sv)])
            eye_tri = np.r_[np.zeros(len(st), bool), np.ones(n_eye, bool)]
        else:
            verts, tris, eye_tri = sv, st, np.zeros(len(st), bool)
    landmarks = _landmarks(verts, tris, eye_tri, nose_i, spec.base)
    parts: dict[str, o3d.geometry.TriangleMesh] = {}
    parts["skin"] = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector(tris))
    hair = _hair(verts, tris, eye_tri, landmarks, spec, rng)
    if hair is not None:
        parts["hair"] = hair
    if spec.glasses:
        parts["glasses"] = _glasses(landmarks)
    if spec.hand:
        parts["hand"] = _hand(landmarks, spec.hand, rng)
    R = Rotation.from_euler("zxy", [spec.roll_deg, spec.pitch_deg, spec.yaw_deg], degrees=True).as_matrix()
    for m in parts.values():
        m.rotate(R, center=(0.0, 0.0, 0.0))
        m.compute_vertex_normals()
    posed = {k: v @ R.T for k, v in landmarks.items()}
    return Person(parts, posed, spec, R, weights)


def _landmarks(verts: AnyArray, tris: AnyArray, eye_tri: AnyArray, nose_i: int,
               base: str) -> dict[str, AnyArray]:
    nose = verts[nose_i].copy()
    out = {"nose_tip": nose}
    if eye_tri.any():
        ev = np.unique(tris[eye_tri])
        e = verts[ev]
        for name, side in (("eye_r", e[:, 0] < 0), ("eye_l", e[:, 0] > 0)):
            out[name] = e[side].mean(axis=0)
    else:   # a scan without eyeballs: the deepest points of the sockets, 32 mm either side, 35 mm above the tip
        for name, dx in (("eye_r", -0.032), ("eye_l", 0.032)):
            target = nose + np.array([dx, -0.035, 0.0])
            near = np.linalg.norm(verts[:, :2] - target[:2], axis=1) < 0.012
            front = near & (verts[:, 2] < nose[2] + 0.06)
            out[name] = verts[front][np.argmax(verts[front, 2])] if front.any() else target
    # mouth and chin on the midline: the most forward skin below the nose (y down), in two height bands
    mid = (np.abs(verts[:, 0]) < 0.004) & (verts[:, 2] < nose[2] + 0.05)
    for name, lo, hi in (("mouth", 0.015, 0.040), ("chin", 0.050, 0.075)):
        band = mid & (verts[:, 1] > nose[1] + lo) & (verts[:, 1] < nose[1] + hi)
        fallback = nose + np.array([0.0, (lo + hi) / 2, 0.02])
        out[name] = verts[band][np.argmin(verts[band, 2])] if band.any() else fallback
    return out


def _albedos(person: Person, translation: AnyArray) -> dict[str, tuple[AlbedoFn, float]]:
    from .scenes import mottled_albedo, uniform_albedo

    seed = person.spec.identity_seed
    rng = np.random.default_rng(np.random.SeedSequence([0x9E2, int(seed)]))
    tone = float(np.clip(1.0 + 0.15 * rng.standard_normal(), 0.55, 1.3))
    return {"skin": (mottled_albedo(np.array([0.46, 0.55, 0.74]) * tone, 0.08, seed=seed, scale_m=0.015), 0.25),
            "hair": (mottled_albedo(np.array([0.06, 0.08, 0.11]) * float(rng.uniform(0.7, 3.0)), 0.3, seed=seed + 1,
                                    scale_m=0.002), 0.1),
            "glasses": (uniform_albedo((0.05, 0.05, 0.05)), 0.8),
            "hand": (mottled_albedo(np.array([0.46, 0.55, 0.74]) * tone, 0.08, seed=seed + 2, scale_m=0.015), 0.25),
            # parts of the ICT people (lsu_sim.ict): eyeballs, the mouth's inside, a collar
            "eyes": (uniform_albedo((0.7, 0.7, 0.75)), 0.9),
            "mouth": (uniform_albedo((0.12, 0.1, 0.25)), 0.3),
            "collar": (mottled_albedo(np.array([0.3, 0.3, 0.3]) * float(rng.uniform(0.5, 2.5)), 0.1, seed=seed + 3,
                                      scale_m=0.01), 0.1)}


def person_objects(person: Person, translation: Sequence[float], name: str = "person") -> list[SceneObject]:
    """The person placed with its head centre at ``translation`` (left frame) as scene objects.

    The first object (the skin) carries the truth in ``extra``: ``nose_tip_m`` and ``landmarks_m``
    (left frame), ``identity_seed``, ``head_center_m``.
    """
    t = np.asarray(translation, dtype=np.float64)
    albedo = _albedos(person, t)
    out = []
    for part, mesh in person.parts.items():
        m = o3d.geometry.TriangleMesh(mesh)
        m.translate(t)
        fn, spec = albedo[part]
        extra: dict[str, object] = {}
        if part == "skin":
            extra = {"nose_tip_m": person.landmarks["nose_tip"] + t,
                     "landmarks_m": {k: v + t for k, v in person.landmarks.items()},
                     "identity_seed": person.spec.identity_seed, "head_center_m": t}
        # skin and the raised hand scatter red light below the surface; hair, glasses and clothes do not
        material = "skin" if part in ("skin", "hand") else "surface"
        out.append(SceneObject(f"{name}_{part}", m, fn, spec, extra, material=material))
    return out


def _main(argv: list[str]) -> int:
    if len(argv) == 4 and argv[0] == "build-assets":
        for f in build_assets(argv[1], argv[2], argv[3]):
            print(f"{f} {f.stat().st_size / 1e6:.2f} MB")
        return 0
    print("usage: python -m lsu_sim.people build-assets MAKEHUMAN_DIR LEEPERRYSMITH_DIR OUT_DIR",
          file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))

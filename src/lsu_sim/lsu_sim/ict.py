"""People from the ICT face model: identity shapes with the spread of real people, expressions, hair, collar.

The ICT Face Model (USC ICT-FaceKit, MIT; ``shared/devdata/face_model_ict_mit``, see its PROVENANCE.md)
is a morphable model built from light-stage scans of real people: a neutral skin surface (face, head
and neck), 100 identity modes scaled so that weights ~N(0, 1) give new people with the scanned
population's spread, and 57 expression blendshapes (ARKit names: mouthSmile_L, jawOpen, eyeBlink_R,
browInnerUp_L, ...). A person here is ``neutral + identity @ modes + expression @ blendshapes``:

- identity: 100 weights ~N(0, 1) drawn from the person's seed (same seed, same person, every process);
- an *occasion* (`Occasion`): expression weights (none to strong), pose (yaw, pitch, roll), hair
  thickness and fringe, a collar around the neck; what changes between two captures of one person;
- parts the model leaves out and a sensor would see: eyeballs (spheres in the sockets, so no ray
  goes through an open eye into the head), the mouth's inside (a dark ellipsoid behind the lips, seen
  when the jaw opens), a hair shell (`lsu_sim.people`'s, on the scalp), a collar (a torus
  round the neck: what a nose finder must not take for a nose).

Frames as `lsu_sim.people`: origin at the head centre (0.10 m behind the nose tip), x to the
image right, y down, z away from the camera (an unposed person looks along -z). Truth (`Person.landmarks`):
the model's own landmark vertices (Multi-PIE 68-point layout: nose tip 30, eye contours 36-47, mouth
48-67, chin 8), carried through identity, expression and pose; never found by face code.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from lsu_common.arrays import AnyArray

from .scenes import SceneError

__all__ = ["IctModel", "Occasion", "load_ict", "ict_person", "ict_vertices", "eyeballs", "random_occasion",
           "identity_weights", "EXPRESSION_SETS"]

# named expressions: {blendshape: weight at strength 1}
EXPRESSION_SETS: dict[str, dict[str, float]] = {
    "neutral": {},
    "smile": {"mouthSmile_L": 1.0, "mouthSmile_R": 1.0, "cheekSquint_L": 0.5, "cheekSquint_R": 0.5,
              "eyeSquint_L": 0.3, "eyeSquint_R": 0.3},
    "open_jaw": {"jawOpen": 0.8, "mouthLowerDown_L": 0.4, "mouthLowerDown_R": 0.4},
    "smile_open_jaw": {"mouthSmile_L": 1.0, "mouthSmile_R": 1.0, "jawOpen": 0.6, "cheekSquint_L": 0.5,
                       "cheekSquint_R": 0.5},
    "surprise": {"browInnerUp_L": 1.0, "browInnerUp_R": 1.0, "browOuterUp_L": 0.8, "browOuterUp_R": 0.8,
                 "eyeWide_L": 0.6, "eyeWide_R": 0.6, "jawOpen": 0.4},
    "frown": {"browDown_L": 1.0, "browDown_R": 1.0, "mouthFrown_L": 0.8, "mouthFrown_R": 0.8,
              "noseSneer_L": 0.4, "noseSneer_R": 0.4},
    "blink": {"eyeBlink_L": 1.0, "eyeBlink_R": 1.0},
    "pucker": {"mouthPucker": 1.0, "mouthFunnel": 0.4},
}
_NOSE, _CHIN = 30, 8
_EYE_R, _EYE_L, _MOUTH = list(range(36, 42)), list(range(42, 48)), list(range(48, 68))
_TO_PERSON = np.array([1.0, -1.0, -1.0])      # ICT (y up, z out of the face) -> person frame (y down, z away)


@dataclass
class IctModel:
    """The model's arrays in the person frame's axes (metres; not yet centred)."""

    neutral: AnyArray            # (V, 3)
    triangles: AnyArray          # (T, 3)
    identity: AnyArray           # (100, V * 3)
    expression: AnyArray         # (57, V * 3)
    expression_names: list[str]
    landmarks: AnyArray          # (68,) vertex indices
    face_vertex_count: int


_MODELS: dict[str, IctModel] = {}


def load_ict(folder: str | Path) -> IctModel:
    """The ICT model of ``folder`` (``face_model_ict_mit``), read once per process."""
    folder = Path(folder)
    key = str(folder.resolve())
    if key not in _MODELS:
        npz, marks = folder / "ict_face_model.npz", folder / "landmarks.json"
        if not npz.is_file() or not marks.is_file():
            raise SceneError(f"no ICT face model in {folder} (need ict_face_model.npz and landmarks.json; "
                             f"shared/devdata/face_model_ict_mit beside the repository)")
        import json

        with np.load(npz, allow_pickle=False) as z:
            V = z["neutral_m"].shape[0]
            _MODELS[key] = IctModel(
                neutral=z["neutral_m"].astype(np.float64) * _TO_PERSON,
                triangles=z["triangles"].astype(np.int64),
                # float32 (as stored): a person is one pass over these, memory-bound
                identity=(z["identity_modes_m"] * _TO_PERSON.astype(np.float32)).reshape(-1, V * 3),
                expression=(z["expression_modes_m"] * _TO_PERSON.astype(np.float32)).reshape(-1, V * 3),
                expression_names=[str(n) for n in z["expression_names"]],
                landmarks=np.asarray(json.loads(marks.read_text())["idx_to_landmark_verts"], dtype=np.int64),
                face_vertex_count=int(z["face_vertex_count"]))
    return _MODELS[key]


@dataclass(frozen=True)
class Occasion:
    """What differs between two captures of one person."""

    expression: str = "neutral"          # a key of EXPRESSION_SETS
    strength: float = 1.0                # 0..1 scale of the expression
    jitter_seed: int | None = None       # extra small random blendshape activations (None: none)
    yaw_deg: float = 0.0
    pitch_deg: float = 0.0
    roll_deg: float = 0.0
    hair_m: float = 0.015                # hair shell thickness on the crown (0: bald)
    fringe: bool = False
    collar: bool = False


def random_occasion(rng: np.random.Generator, neutral: bool = False, max_yaw_deg: float = 30.0,
                    max_pitch_deg: float = 15.0) -> Occasion:
    """A capture occasion: expression none to strong, pose within +-``max_yaw_deg`` / +-``max_pitch_deg``."""
    names = [n for n in EXPRESSION_SETS if n != "neutral"]
    expression = "neutral" if neutral else str(rng.choice(["neutral"] + names))
    return Occasion(expression=expression, strength=float(rng.uniform(0.3, 1.0)),
                    jitter_seed=None if neutral else int(rng.integers(1 << 30)),
                    yaw_deg=float(rng.uniform(-max_yaw_deg, max_yaw_deg)),
                    pitch_deg=float(rng.uniform(-max_pitch_deg, max_pitch_deg)),
                    roll_deg=float(rng.uniform(-5.0, 5.0)), hair_m=float(rng.uniform(0.0, 0.03)),
                    fringe=bool(rng.uniform() < 0.25), collar=bool(rng.uniform() < 0.3))


def identity_weights(seed: int, modes: int = 100) -> AnyArray:
    """The person's 100 identity weights ~N(0, 1), from its seed."""
    return np.random.default_rng(np.random.SeedSequence([0x1C7, int(seed)])).standard_normal(modes)


def ict_vertices(model: IctModel, seed: int, occasion: Occasion = Occasion()) -> tuple[AnyArray, dict[str, AnyArray]]:
    """Unposed skin vertices of person ``seed`` with ``occasion``'s expression (person frame) and its landmarks."""
    if occasion.expression not in EXPRESSION_SETS:
        raise SceneError(f"expression must be one of {', '.join(EXPRESSION_SETS)} (got {occasion.expression!r})")
    w_id = identity_weights(seed, len(model.identity)).astype(np.float32)
    w_ex = np.zeros(len(model.expression), dtype=np.float32)
    for name, w in EXPRESSION_SETS[occasion.expression].items():
        w_ex[model.expression_names.index(name)] = w * occasion.strength
    if occasion.jitter_seed is not None:   # a face is never exactly a named expression
        rng = np.random.default_rng(occasion.jitter_seed)
        w_ex += np.clip(rng.normal(0.0, 0.08, len(w_ex)), 0.0, None).astype(np.float32)
    w_ex = np.clip(w_ex, 0.0, 1.0)
    V = len(model.neutral)
    offset = w_id @ model.identity
    if np.any(w_ex > 0):
        offset += w_ex @ model.expression
    verts = model.neutral + offset.astype(np.float64).reshape(V, 3)
    lm = verts[model.landmarks]
    centre = lm[_NOSE] + np.array([0.0, -0.01, 0.10])
    verts = verts - centre
    lm = lm - centre
    landmarks = {"nose_tip": lm[_NOSE], "eye_r": lm[_EYE_R].mean(axis=0), "eye_l": lm[_EYE_L].mean(axis=0),
                 "mouth": lm[_MOUTH].mean(axis=0), "chin": lm[_CHIN]}
    if landmarks["eye_r"][0] > landmarks["eye_l"][0]:
        landmarks["eye_r"], landmarks["eye_l"] = landmarks["eye_l"], landmarks["eye_r"]
    return verts, landmarks


def eyeballs(landmarks: dict[str, AnyArray]) -> o3d.geometry.TriangleMesh:
    """12 mm spheres whose front sits just behind the eye contours (an open eye shows the ball, not the head's inside)."""
    eyes = o3d.geometry.TriangleMesh()
    for side in ("eye_r", "eye_l"):
        ball = o3d.geometry.TriangleMesh.create_sphere(radius=0.012, resolution=16)
        ball.translate(landmarks[side] + np.array([0.0, 0.0, 0.0145]))
        eyes += ball
    return eyes


def ict_person(model: IctModel, seed: int, occasion: Occasion = Occasion()):  # noqa: ANN201 - people.Person
    """Person ``seed`` on ``occasion`` as a `lsu_sim.people.Person` (skin, eyes, mouth, hair, collar)."""
    from .people import Person, PersonSpec, _hair

    verts, landmarks = ict_vertices(model, seed, occasion)
    tris = model.triangles
    skin = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector(tris))
    parts: dict[str, o3d.geometry.TriangleMesh] = {"skin": skin, "eyes": eyeballs(landmarks)}
    # the mouth's inside: a dark ellipsoid behind the lips, what an open jaw shows
    inside = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=16)
    inside.vertices = o3d.utility.Vector3dVector(np.asarray(inside.vertices) * np.array([0.024, 0.016, 0.02])
                                                 + landmarks["mouth"] + np.array([0.0, 0.004, 0.032]))
    parts["mouth"] = inside
    spec = PersonSpec(identity_seed=int(seed), hair_m=occasion.hair_m, fringe=occasion.fringe,
                      yaw_deg=occasion.yaw_deg, pitch_deg=occasion.pitch_deg, roll_deg=occasion.roll_deg)
    hair_rng = np.random.default_rng(np.random.SeedSequence([0x1C8, int(seed)]))
    # the scalp only (head and neck vertices behind the face area): hair never covers the face itself
    head_only = np.ones(len(tris), bool)
    head_only[(tris < model.face_vertex_count).any(axis=1) & (verts[tris].mean(axis=1)[:, 1] > -0.04)] = False
    hair = _hair(verts, tris, ~head_only, landmarks, spec, hair_rng) if occasion.hair_m > 0 else None
    if hair is not None:
        parts["hair"] = hair
    if occasion.collar:
        neck = verts[(verts[:, 1] > 0.10) & (verts[:, 1] < 0.14)]
        if len(neck):
            c = neck.mean(axis=0)
            r = float(np.median(np.linalg.norm((neck - c)[:, [0, 2]], axis=1)))
            collar = o3d.geometry.TriangleMesh.create_torus(torus_radius=r + 0.012, tube_radius=0.014,
                                                            radial_resolution=40, tubular_resolution=10)
            collar.rotate(Rotation.from_euler("x", 90, degrees=True).as_matrix(), center=(0, 0, 0))
            collar.translate(c + np.array([0.0, 0.01, 0.0]))
            parts["collar"] = collar
    R = Rotation.from_euler("zxy", [occasion.roll_deg, occasion.pitch_deg, occasion.yaw_deg], degrees=True).as_matrix()
    for m in parts.values():
        m.rotate(R, center=(0.0, 0.0, 0.0))
        m.compute_vertex_normals()
    posed = {k: v @ R.T for k, v in landmarks.items()}
    return Person(parts, posed, spec, R, {f"id{k}": float(w) for k, w in enumerate(identity_weights(seed)[:8])})

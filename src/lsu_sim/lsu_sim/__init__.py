"""The simulated LSU rig (pure: numpy, OpenCV, open3d; no rclpy).

Its own package above ``lsu_cameras`` (whose calibration files it writes): the camera node finds its
`source` through the ``lsu.camera_sources`` entry point and never imports it; `lsu render` is its ``lsu.commands``.

- `geometry`: cameras, extrinsics, track and laser sheet from ``config/sim_rig.yaml`` (`load_rig`).
- `scenes`: plane, sphere, calibration chessboard, mesh files; `head`: procedural synthetic heads.
- `rig`: `SimulatedRig.render(carriage, capture_time_s)` -> `StereoFrame` (+ exact `LaserTruth`).
- `source`: `SimSource`, the stereo_camera node's ``sim`` source (carriage from ``sim/truth``).
- `people`: realistic synthetic people (MakeHuman head and shoulders); `depthcam`: a coarse depth camera;
  `boards`: calibration board poses and their rendered pairs.
- `physics`: what real laser-line images have: laser speckle (per camera, a new realisation per
  capture), subsurface scattering on skin (objects with ``material="skin"``: the head scenes),
  blooming, an optional Bayer mosaic; each camera's own exposure start (``sensor.capture_offset_s``).

``build_scene(name, geometry)`` makes the named scenes of every sim entry point (`lsu render --scene`, the
node's ``sim_scene`` parameter, ``lsu launch sim scene:=``, `lsu demo --scene`, the bags of lsu_testing.simbags):
``plane``, ``sphere``, ``board``, ``head`` (``head:SEED``, the procedural egg-like head), ``person``
(``person:SEED``, a realistic person of `people`: a real head mesh with the seed's identity, hair, neck and
shoulders; ``person:ict:SEED``: a person of the ICT face model, real people's shape statistics, `ict`) or a
mesh file path.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from .geometry import CameraModel, RigConfigError, RigGeometry, load_rig, rig_from_dict, write_true_calibration
    from .head import Head, HeadIdentity, head_object, make_head
    from .rig import CameraTruth, CarriageState, LaserTruth, SimulatedRig, StereoFrame
    from .scenes import SceneError, SceneObject, load_mesh_file, make_board, make_plane, make_sphere

# every name of a module that needs OpenCV, scipy or open3d, imported on first use (PEP 562): every `lsu`
# command imports this package to register `lsu render`, and would otherwise pay those imports (~1.2 s CPU)
_LAZY = {**dict.fromkeys(("CameraModel", "RigConfigError", "RigGeometry", "load_rig", "rig_from_dict",
                          "write_true_calibration"), ".geometry"),
         **dict.fromkeys(("Head", "HeadIdentity", "head_object", "make_head"), ".head"),
         **dict.fromkeys(("CameraTruth", "CarriageState", "LaserTruth", "SimulatedRig", "StereoFrame"), ".rig"),
         **dict.fromkeys(("SceneError", "SceneObject", "load_mesh_file", "make_board", "make_plane", "make_sphere"),
                         ".scenes")}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'lsu_sim' has no attribute '{name}'")
    value = getattr(importlib.import_module(module, __name__), name)
    globals()[name] = value
    return value

__all__ = ["CameraModel", "RigConfigError", "RigGeometry", "load_rig", "rig_from_dict", "write_true_calibration",
           "Head", "HeadIdentity", "head_object", "make_head", "CameraTruth", "CarriageState", "LaserTruth",
           "SimulatedRig", "StereoFrame", "SceneError", "SceneObject", "load_mesh_file", "make_board", "make_plane",
           "make_sphere", "build_scene", "SCENE_NAMES"]

SCENE_NAMES = ("plane", "sphere", "board", "head", "person")
# the person's head centre behind the subject point [m]: its cheeks are then at about the subject distance
# (as the face benchmark places them)
PERSON_DEPTH_M = 0.10


def _ict_model():  # noqa: ANN202 - ict.IctModel
    """The ICT face model of the development data (``shared/devdata/face_model_ict_mit`` beside the repository:
    its licence and size keep it out of the repository), or SceneError saying where it is looked for."""
    from lsu_extract.devdata import DevDataMissing, devdata_dir

    from .ict import load_ict
    from .scenes import SceneError

    try:
        folder = devdata_dir() / "face_model_ict_mit"
    except DevDataMissing as exc:
        raise SceneError(f"person:ict:SEED needs the ICT face model of the development data: {exc}") from None
    return load_ict(folder)


def _seed_of(name: str, kind: str) -> int:
    """The SEED of ``kind`` or ``kind:SEED`` (0 without one)."""
    from .scenes import SceneError

    text = name[len(kind) + 1:] if name.startswith(kind + ":") else "0"
    try:
        return int(text)
    except ValueError:
        raise SceneError(f"scene '{name}': the seed after '{kind}:' must be a whole number (e.g. {kind}:7)") from None


def build_scene(name: str, geometry: RigGeometry, distance_m: float | None = None, yaw_deg: float = 0.0,
                pitch_deg: float = 0.0) -> list[SceneObject]:
    """A named scene centred on the rig's subject point (``distance_m`` overrides the subject distance).

    ``plane``: a textured plane facing the rig; ``sphere``: a 6 cm ball; ``board``: a 9x6, 20 mm
    chessboard facing the rig; ``head`` / ``head:SEED``: a procedural synthetic head; ``person`` /
    ``person:SEED``: a realistic person (`people.make_person`: MakeHuman's head, neck and shoulders with the
    seed's identity and hair; the skin object carries the true landmarks); yaw/pitch turn heads and people;
    anything else is read as a PLY/OBJ/STL file (metres) centred on the subject point.
    """
    from .head import head_object, make_head
    from .scenes import SceneError, load_mesh_file, make_board, make_plane, make_sphere

    axes = geometry.rig_axes
    dist = geometry.subject_distance_m if distance_m is None else float(distance_m)
    center = geometry.rig_center + dist * axes[2]
    if name == "plane":
        return [make_plane(center, -axes[2])]
    if name == "sphere":
        return [make_sphere(center, 0.06)]
    if name == "board":
        square = 0.020
        R = axes.T  # board x along the baseline, y down, facing the rig
        first = center - R @ np.array([4 * square, 2.5 * square, 0.0])
        return [make_board(R, first, (9, 6), square)]
    if name.startswith("person:ict"):
        from .ict import Occasion, ict_person
        from .people import person_objects

        seed = _seed_of(name, "person:ict")
        person = ict_person(_ict_model(), seed, Occasion(yaw_deg=yaw_deg, pitch_deg=pitch_deg))
        return person_objects(person, center + PERSON_DEPTH_M * axes[2])
    if name == "person" or name.startswith("person:"):
        from .people import PersonSpec, make_person, person_objects

        person = make_person(PersonSpec(identity_seed=_seed_of(name, "person"), yaw_deg=yaw_deg, pitch_deg=pitch_deg))
        return person_objects(person, center + PERSON_DEPTH_M * axes[2])
    if name == "head" or name.startswith("head:"):
        seed = _seed_of(name, "head")
        head = make_head(seed, yaw_deg=yaw_deg, pitch_deg=pitch_deg)
        # head centre behind the subject point so that the cheeks are at about the subject distance
        return [head_object(head, center + 0.09 * axes[2])]
    path = Path(name)
    if path.suffix.lower() in (".ply", ".obj", ".stl", ".off", ".gltf", ".glb") or path.exists():
        return [load_mesh_file(path, center=center)]
    raise SceneError(f"unknown scene '{name}': use one of {', '.join(SCENE_NAMES)}, head:SEED, person:SEED, "
                     f"person:ict:SEED or a PLY/OBJ file")

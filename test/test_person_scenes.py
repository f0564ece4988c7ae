"""The simulator's realistic people (`person:SEED`) at every sim entry point: the scene builder all of them use,
`lsu render`, the camera node's source plug-in, the bags of lsu_testing.simbags and `lsu demo`'s default.

Truth: the people model's own meshes (`lsu_sim.people`), placed by the rig's geometry, and the renderer's exact
laser truth; never the code that reads the scene names.
"""

from __future__ import annotations

import argparse

import numpy as np
import open3d as o3d
import pytest

from lsu_common.arrays import AnyArray
from lsu_sim import LaserTruth, SceneError, build_scene, load_rig
from lsu_sim.people import PersonSpec, make_person, person_objects


@pytest.fixture(scope="module")
def geometry():
    return load_rig()


@pytest.fixture(scope="module")
def person3(geometry):
    return build_scene("person:3", geometry)


def _vertices(obj) -> AnyArray:
    v = np.asarray(obj.mesh.vertices)
    used = np.unique(np.asarray(obj.mesh.triangles))
    return v[used]


def test_person_seed_is_the_people_models_person_with_hair_neck_and_shoulders(geometry, person3):
    head_centre = geometry.rig_center + (geometry.subject_distance_m + 0.10) * geometry.rig_axes[2]
    expected = person_objects(make_person(PersonSpec(identity_seed=3)), head_centre)
    assert [o.name for o in person3] == [o.name for o in expected] == ["person_skin", "person_hair"]
    for got, want in zip(person3, expected):
        assert np.array_equal(np.asarray(got.mesh.triangles), np.asarray(want.mesh.triangles))
        assert np.allclose(_vertices(got), _vertices(want), atol=1e-9)
    skin = person3[0]
    assert skin.material == "skin" and np.allclose(skin.extra["head_center_m"], head_centre)
    # the nose tip faces the rig at about the subject distance
    nose = skin.extra["nose_tip_m"]
    assert abs(np.dot(nose - geometry.rig_center, geometry.rig_axes[2]) - geometry.subject_distance_m) < 0.02
    # neck and shoulders: skin well below the chin (y down), and wider than any head
    v, chin = _vertices(skin), skin.extra["landmarks_m"]["chin"]
    below = v[v[:, 1] > chin[1] + 0.10]
    assert len(below) > 100 and np.ptp(below[:, 0]) > 0.30
    # the hair sits above the eyes
    eyes_y = min(skin.extra["landmarks_m"]["eye_r"][1], skin.extra["landmarks_m"]["eye_l"][1])
    assert np.median(_vertices(person3[1])[:, 1]) < eyes_y


def test_person_names_seeds_and_mistakes(geometry, person3):
    plain, zero = build_scene("person", geometry), build_scene("person:0", geometry)
    assert np.array_equal(plain[0].extra["nose_tip_m"], zero[0].extra["nose_tip_m"])
    assert np.linalg.norm(zero[0].extra["nose_tip_m"] - person3[0].extra["nose_tip_m"]) > 1e-4  # another face
    turned = build_scene("person:3", geometry, yaw_deg=30.0)
    assert np.linalg.norm(turned[0].extra["nose_tip_m"] - person3[0].extra["nose_tip_m"]) > 0.02
    for bad in ("person:x", "person:", "person:1.5"):
        with pytest.raises(SceneError, match=r"whole number \(e.g. person:7\)"):
            build_scene(bad, geometry)
    with pytest.raises(SceneError, match="person:SEED"):  # the unknown-scene message names the people
        build_scene("persons", geometry)


def test_lsu_render_of_a_person_puts_the_laser_truth_on_the_person(tmp_path, geometry, person3):
    from lsu_sim.cli import cmd_render

    args = argparse.Namespace(scene="person:3", position=[235.0], distance=None, yaw=0.0, pitch=0.0,
                              laser_off=False, vibration=0.0, after_stop=0.005, tau=0.06, freq=25.0, seed=0,
                              rig=None, output=str(tmp_path))
    assert cmd_render(args) == 0
    truth = LaserTruth.from_npz(tmp_path / "truth_000.npz")
    assert len(truth.left.points_m) > 200  # the line crosses the face from forehead to chin
    scene = o3d.t.geometry.RaycastingScene()
    for obj in person3:
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(obj.mesh))
    distance = scene.compute_distance(o3d.core.Tensor(truth.left.points_m.astype(np.float32))).numpy()
    assert distance.max() < 1e-4


def test_the_camera_nodes_sim_source_and_simbags_take_a_person(tmp_path, person3):
    from lsu_bags.bags import bag_topics, read_messages
    from lsu_cameras.sources import SourceContext, open_plugin_source
    from lsu_testing.simbags import IMAGE_TOPICS, write_sim_scan_bag

    params = {"sim_rig": "", "sim_scene": "person:3", "sim_seed": 0, "carriage_position_steps": 235.0,
              "laser_on": True}
    source = open_plugin_source("sim", SourceContext(parameter=params.__getitem__, clock=lambda: 0.0,
                                                     truth_at=lambda t_ns: (None, [])))
    assert [o.name for o in source.rig.objects] == ["person_skin", "person_hair"]
    assert np.array_equal(source.rig.objects[0].extra["nose_tip_m"], person3[0].extra["nose_tip_m"])
    bag = write_sim_scan_bag(tmp_path / "bag", "person:3", [235], seed=1)
    assert set(IMAGE_TOPICS.values()) <= set(bag_topics(bag))
    assert sum(1 for _ in read_messages(bag, [IMAGE_TOPICS["left"]])) == 2  # the texture pair and the snap


def test_the_demo_scans_a_person_by_default_and_the_egg_stays_a_scene(geometry):
    from lsu_tools.demo import DEMO_SCENE, register

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    assert parser.parse_args(["demo"]).scene == DEMO_SCENE and DEMO_SCENE.startswith("person")
    assert [o.name for o in build_scene(DEMO_SCENE, geometry)][:2] == ["person_skin", "person_hair"]
    assert [o.name for o in build_scene("head:7", geometry)] == ["head"]


def test_person_ict_seed_is_the_ict_models_person(geometry):
    """`person:ict:SEED`: a person of the ICT face model (development data; skipped without it)."""
    from lsu_extract import devdata
    from lsu_sim.ict import ict_person, load_ict

    try:
        folder = devdata.devdata_dir() / "face_model_ict_mit"
    except devdata.DevDataMissing as exc:
        pytest.skip(str(exc))
    if not (folder / "ict_face_model.npz").is_file():
        pytest.skip(f"no ICT face model at {folder}")
    objects = build_scene("person:ict:4", geometry)
    head_centre = geometry.rig_center + (geometry.subject_distance_m + 0.10) * geometry.rig_axes[2]
    expected = person_objects(ict_person(load_ict(folder), 4), head_centre)
    assert [o.name for o in objects] == [o.name for o in expected] and objects[0].name == "person_skin"
    assert np.allclose(objects[0].extra["nose_tip_m"], expected[0].extra["nose_tip_m"])
    other = build_scene("person:ict:5", geometry)[0]  # another identity: the same topology, another shape
    assert np.abs(np.asarray(other.mesh.vertices) - np.asarray(objects[0].mesh.vertices)).max() > 1e-3
    with pytest.raises(SceneError, match=r"whole number \(e.g. person:ict:7\)"):
        build_scene("person:ict:x", geometry)

"""Nose tip, non-face rejection and signatures on synthetic heads of the simulated rig (truth from the generator)."""

from __future__ import annotations

import numpy as np
import pytest

from lsu_faces.face import FaceError, FaceParams, NotAFaceError, embed_face, nose_tip_protrusion, nose_tip_svd
from lsu_faces.signature import Signature, SignatureParams, compare, make_signature

sim = pytest.importorskip("lsu_cameras.sim")
from lsu_faces.synthetic import fast_scan  # noqa: E402

POSITIONS = np.arange(0, 471, 4)


@pytest.fixture(scope="module")
def rig():
    return sim.load_rig()


def scan(rig, scene: str, yaw: float = 0.0, pitch: float = 0.0, seed: int = 0):
    objs = sim.build_scene(scene, rig, yaw_deg=yaw, pitch_deg=pitch)
    s = fast_scan(objs, rig, POSITIONS, noise_m=5e-5, drop_fraction=0.1, seed=seed)
    return np.stack([s.columns[c] for c in "xyz"], axis=1), objs[0].extra


@pytest.mark.parametrize("seed,yaw,pitch", [(1, 0, 0), (2, 30, 0), (3, -30, 15)])
def test_nose_tip_within_3mm_of_the_generator(rig, seed, yaw, pitch):
    pts, extra = scan(rig, f"head:{seed}", yaw, pitch, seed)
    nose = nose_tip_protrusion(pts)
    assert np.linalg.norm(nose.tip - extra["nose_tip_m"]) < 0.003
    assert nose.prominence_m > FaceParams().min_prominence_m


def test_thesis_svd_nose_finder_on_a_frontal_head(rig):
    pts, extra = scan(rig, "head:4")
    assert np.linalg.norm(nose_tip_svd(pts).tip - extra["nose_tip_m"]) < 0.006


@pytest.mark.parametrize("scene", ["plane", "sphere"])
def test_non_face_objects_are_reported(rig, scene):
    pts, _ = scan(rig, scene)
    with pytest.raises(NotAFaceError, match="no nose"):
        nose_tip_protrusion(pts)


def test_too_few_points_is_a_face_error():
    with pytest.raises(FaceError, match="too few"):
        nose_tip_protrusion(np.random.default_rng(0).normal(size=(20, 3)))


def test_same_person_in_another_pose_scores_higher_than_another_person(rig):
    sigs = []
    for seed, yaw in ((5, 0), (5, 30), (6, 0)):
        pts, _ = scan(rig, f"head:{seed}", yaw, 0, seed * 10 + yaw)
        _, frame, mask = embed_face(pts)
        sigs.append(make_signature(pts[mask], frame))
    same = compare(sigs[1], sigs[0])[0]
    other = compare(sigs[1], sigs[2])[0]
    assert same > 0.33 > other
    blob = Signature.from_bytes(sigs[0].to_bytes())
    assert blob.params == SignatureParams() and np.array_equal(np.isnan(blob.data), np.isnan(sigs[0].data))

"""Faces of a living subject (`lsu_accuracy.motion_sim.face_sweeps`): a standing person's sweep, corrected for the
measured motion, is identified as that person against still sweep enrolments, and the correction brings it nearer
its own enrolment than the sheared raw sweep.

Ground truth: the identities of the simulator's people (``person:SEED``, `lsu_sim.people`: each seed its own
face); the standing sweep moves as `lsu_sim.motion` ``standing`` (motion seed 5: the sway of test_motion_scan's
standing scan, which shears the face measurably over a sweep). Enrolment and identification are lsu_faces' own
(`Gallery.enroll`, `Gallery.identify`, `compare`), as `lsu face enroll`/`identify` run them. The benchmark's
figures (`bench_scan.py --only motion_faces`) are on 20 people of the face model; this test has three.
"""

from __future__ import annotations

import pytest

from lsu_accuracy.motion_sim import face_sweeps
from lsu_config import config_dir
from lsu_faces.gallery import Gallery
from lsu_faces.signature import compare
from lsu_reconstruct.laser_sheet import read_laser_yaml
from lsu_reconstruct.stereo import StereoModel
from lsu_sim import build_scene, load_rig

pytestmark = [pytest.mark.slow, pytest.mark.timeout(2400)]

PEOPLE = ("person:2", "person:3", "person:4")
PROBED = "person:2"
MOTION_SEED = 5


def test_a_corrected_standing_sweep_is_identified_and_nearer_its_enrolment_than_the_raw_one(tmp_path):
    calib = config_dir() / "calibration" / "sim"
    model, sheet, geometry = StereoModel.from_folder(calib), read_laser_yaml(calib / "laser.yaml"), load_rig()
    gallery = Gallery(tmp_path / "gallery.db")
    swept = {}
    for n, person in enumerate(PEOPLE):
        swept[person] = face_sweeps(model, sheet, geometry, build_scene(person, geometry), "standing",
                                    enrol_seed=n, probe_seed=MOTION_SEED, still_probe=False,
                                    moving_probe=person == PROBED)
        assert swept[person].enrolment is not None, swept[person].messages
        gallery.enroll(person, swept[person].enrolment)
    probed = swept[PROBED]
    raw, corrected = probed.probes["moving_raw"], probed.probes["moving_corrected"]
    assert raw is not None and corrected is not None, probed.messages
    assert not probed.flagged  # standing sway is within what the correction takes
    enrolment = probed.enrolment
    raw_mm, corrected_mm = compare(raw, enrolment)[1] * 1e3, compare(corrected, enrolment)[1] * 1e3
    # the sway shears the raw face; the corrected one is nearer the person's still enrolment
    assert corrected_mm < raw_mm, (corrected_mm, raw_mm)
    found = gallery.identify(corrected, max_results=len(PEOPLE))
    assert [m.name for m in found.matches][0] == PROBED, [(m.name, m.distance_m * 1e3) for m in found.matches]
    # and nearer its own enrolment than any other person's
    others = [compare(corrected, swept[p].enrolment)[1] * 1e3 for p in PEOPLE if p != PROBED]
    assert corrected_mm < min(others), (corrected_mm, others)

"""Which bags a batch finds, the folders it gives them, the steps it accepts, and the gallery it fills (no Ray)."""

from __future__ import annotations

from pathlib import Path

import pytest

from lsu_batch.bags import find_bags, output_names
from lsu_batch.task import parse_steps


def _bag_dir(path: Path) -> Path:
    path.mkdir(parents=True)
    (path / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    (path / "bag.mcap").write_bytes(b"")
    return path


def test_bags_are_found_in_folders_once_each_and_named_by_their_scan(tmp_path):
    a = _bag_dir(tmp_path / "scans" / "20261201-1" / "bag")
    b = _bag_dir(tmp_path / "scans" / "20261201-2" / "bag")
    loose = tmp_path / "scans" / "loose.mcap"
    loose.write_bytes(b"")
    out = tmp_path / "scans" / "out"
    _bag_dir(out / "copy")  # inside the output folder: not an input
    bags = find_bags([tmp_path / "scans", a], skip=[out])
    assert bags == sorted([a.resolve(), b.resolve(), loose.resolve()])  # a's storage file is not a second bag
    names = output_names(bags)
    assert names[a.resolve()] == "20261201-1" and names[b.resolve()] == "20261201-2"
    assert names[loose.resolve()] == "loose"


def test_colliding_names_get_a_hash_of_their_path(tmp_path):
    a = _bag_dir(tmp_path / "lab1" / "s" / "bag")
    b = _bag_dir(tmp_path / "lab2" / "s" / "bag")
    names = output_names(find_bags([tmp_path]))
    assert len(set(names.values())) == 2 and all(n.startswith("s-") for n in names.values())
    assert output_names(find_bags([tmp_path])) == names  # stable: a rerun finds its folders
    assert {a.resolve(), b.resolve()} == set(names)


def test_a_missing_input_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothere"):
        find_bags([tmp_path / "nothere"])


def test_steps_are_ordered_and_need_what_they_build_on():
    assert parse_steps("face,extract,match") == ("extract", "match", "face")
    with pytest.raises(ValueError, match="unknown step"):
        parse_steps("extract,points")
    with pytest.raises(ValueError, match="add 'match'"):
        parse_steps("extract,mesh")
    with pytest.raises(ValueError, match="starts with 'extract'"):
        parse_steps("match")


def _fake_signature(seed: int):
    """A smooth synthetic depth map on the default grid (a paraboloid 'face' with a seeded bump)."""
    import numpy as np

    from lsu_faces.signature import Signature, SignatureParams, cell_centres

    p = SignatureParams()
    c = cell_centres(p)
    x, y = np.meshgrid(c, c)
    rng = np.random.default_rng(seed)
    a, bx, by = rng.uniform(2, 6), rng.uniform(-0.03, 0.03), rng.uniform(-0.03, 0.03)
    z = -a * (x ** 2 + y ** 2) + 0.004 * np.exp(-((x - bx) ** 2 + (y - by) ** 2) / 0.0004)
    z[np.hypot(x, y) > p.extent_m] = np.nan
    return Signature("depthmap", z, p, 1000 + seed)


def test_the_gallery_gets_every_finished_face_once(tmp_path):
    import json

    from lsu_batch.batch import BatchSummary, enroll_finished
    from lsu_faces.gallery import Gallery

    out = tmp_path / "out"
    for i, (done, face) in enumerate([(True, True), (True, True), (True, False), (False, True)]):
        folder = out / f"bag{i}"
        folder.mkdir(parents=True)
        (folder / "result.json").write_text(json.dumps({"scan_id": f"scan-{i}"}))
        if done:
            (folder / "done.json").write_text(json.dumps({"steps": ["extract", "match", "mesh", "face"]}))
        if face:
            (folder / "signature.bin").write_bytes(_fake_signature(i).to_bytes())
    names = [f"bag{i}" for i in range(4)]
    gallery_file = tmp_path / "private" / "gallery.db"
    first = BatchSummary(str(out), ["face"])
    enroll_finished(out, names, gallery_file, first)
    assert first.enrolled == 2 and not first.failed  # bag2 is no face, bag3 is not finished
    gallery = Gallery(gallery_file)
    assert sorted(e.name for e in gallery.list()) == ["scan-0", "scan-1"]
    assert gallery.identify(_fake_signature(1)).best.name == "scan-1"
    again = BatchSummary(str(out), ["face"])
    enroll_finished(out, names, gallery_file, again)  # a rerun, or a resumed run
    assert again.enrolled == 0 and len(gallery.list()) == 2

"""Which bags a batch finds, the folders it gives them, and the steps it accepts (pure, no Ray)."""

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

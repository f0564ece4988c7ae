"""`lsu calibrate --laser`: simulated board scans (rig -> extractor -> matcher) against the rig's true sheet."""

from __future__ import annotations

import argparse
import json
import shutil

import numpy as np
import pytest

from lsu_cameras.cli import register as register_cameras
from lsu_reconstruct.cli import register as register_reconstruct
from lsu_reconstruct.laser_cli import SIM_POSITIONS, calibrate_laser, simulate_board_scans
from lsu_reconstruct.laser_sheet import LaserSheetError, read_laser_yaml
from lsu_sim import load_rig, write_true_calibration


@pytest.fixture(scope="module")
def board_scans(tmp_path_factory):
    """The simulated rig's true calibration and three scans of flat boards (0.26 m +10 deg, 0.30 m, 0.34 m -15 deg)."""
    root = tmp_path_factory.mktemp("laser")
    calib = root / "calib"
    write_true_calibration(load_rig(), calib)
    return calib, simulate_board_scans(root / "scans", calib, seed=3)


def lsu(*argv: str) -> int:
    """The `lsu` parser as the entry points build it: lsu_cameras' commands first, then lsu_reconstruct's."""
    parser = argparse.ArgumentParser(prog="lsu")
    sub = parser.add_subparsers(dest="command", required=True)
    register_cameras(sub)
    register_reconstruct(sub)
    args = parser.parse_args(list(argv))
    return args.func(args)


def test_calibrate_laser_writes_the_rigs_sheet(board_scans, tmp_path, capsys):
    calib, scans = board_scans
    out = tmp_path / "calib"
    shutil.copytree(calib, out)
    assert lsu("calibrate", "--laser", *map(str, scans), "-o", str(out)) == 0
    printed = capsys.readouterr().out
    assert "residual: RMS" in printed and all(s.name in printed for s in scans)
    sheet = read_laser_yaml(out / "laser.yaml")
    geometry = load_rig()
    # angle between the fitted and the true sheet normal
    angle = np.degrees(np.arccos(min(1.0, abs(float(np.dot(sheet.normal, geometry.laser_normal))))))
    assert angle < 0.2
    # offset: the two planes compared at the boards' depths along the sheet, over the scanned positions
    for p in (SIM_POSITIONS[0], SIM_POSITIONS[-1]):
        n, c = sheet.plane(float(p))
        for depth in (0.26, 0.34):
            probe = geometry.laser_origin(float(p)) + depth * geometry.rig_axes[2]
            assert abs(float(np.dot(n, probe)) - c) * 1000.0 < 0.2
    assert sheet.m_per_step == pytest.approx(geometry.step_m, rel=0.01)
    assert sheet.residual_mm < 0.3 and sheet.positions == (SIM_POSITIONS[0], SIM_POSITIONS[-1])


def test_bags_of_the_boards_give_the_same_sheet_as_their_clouds(board_scans, tmp_path):
    """Bare bags (laser lines + SNAP events, no scan.json): reconstructed here, positions from the events."""
    calib, scans = board_scans
    bags = simulate_board_scans(tmp_path / "bags", calib, seed=3, bags=True)
    assert all((b / "metadata.yaml").is_file() and not (b / "scan.json").exists() for b in bags)
    from_bags, report = calibrate_laser(bags, calib)
    from_clouds, _ = calibrate_laser(scans, calib)
    assert np.allclose(from_bags.normal, from_clouds.normal, atol=1e-5)
    assert from_bags.c0_m == pytest.approx(from_clouds.c0_m, abs=1e-6)
    assert [r.positions for r in report] == [len(SIM_POSITIONS)] * 3


def test_one_board_is_refused_with_what_to_scan(board_scans, capsys):
    calib, scans = board_scans
    assert lsu("calibrate", "--laser", str(scans[0]), "-o", str(calib)) == 2
    assert "2 or more distances" in capsys.readouterr().err
    assert not (calib / "laser.yaml").exists()


def test_scans_of_another_calibration_are_refused(board_scans, tmp_path):
    calib, scans = board_scans
    other = tmp_path / "other"
    shutil.copytree(calib, other)
    with open(other / "stereo.yaml", "a") as fh:
        fh.write("# recalibrated\n")
    with pytest.raises(LaserSheetError, match="made with calibration"):
        calibrate_laser(scans, other)


def test_too_few_positions_and_a_bent_board_are_refused(board_scans, tmp_path):
    calib, scans = board_scans
    few = tmp_path / "few"
    shutil.copytree(scans[0], few)
    record = json.loads((few / "scan.json").read_text())
    for snap in record["snaps"]:
        snap["position_steps"] = 200 + 10 * (snap["index"] % 2)   # every snap claims one of two positions
    (few / "scan.json").write_text(json.dumps(record))
    with pytest.raises(LaserSheetError, match="2 carriage position"):
        calibrate_laser([few, scans[1]], calib)
    # a "board" that is two boards 20 mm apart: not flat
    bent = tmp_path / "bent"
    bent.mkdir()
    from lsu_bags.ply import write_cloud_ply
    from lsu_reconstruct.laser_cli import _read_cloud_ply
    from lsu_reconstruct.pipeline import SnapPoints

    near, far = _read_cloud_ply(scans[0] / "cloud.ply"), _read_cloud_ply(scans[2] / "cloud.ply")
    xyz = np.concatenate([np.stack([c["x"], c["y"], c["z"]], axis=1) for c in (near, far)])
    snaps = np.concatenate([near["snap"], far["snap"]])
    write_cloud_ply(bent / "cloud.ply", SnapPoints(xyz.astype(float), np.zeros(len(xyz)), np.zeros(len(xyz)), snaps).fields())
    shutil.copy(scans[0] / "scan.json", bent / "scan.json")
    with pytest.raises(LaserSheetError, match="not a flat target"):
        calibrate_laser([bent, scans[1]], calib)

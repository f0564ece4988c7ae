"""Stereo calibration recovers the simulated rig's true geometry; impossible inputs are refused cleanly."""

import argparse

import cv2
import numpy as np
import pytest

from lsu_cameras.calib_io import read_calibration_dir
from lsu_cameras.calibration import BoardSpec, CalibrationError, calibrate_stereo
from lsu_cameras.cli import cmd_calibrate
from lsu_cameras.sim import load_rig
from lsu_cameras.sim.boards import random_board_poses, render_board_pairs

BOARD = BoardSpec(9, 6, 0.020)


@pytest.fixture(scope="module")
def geometry():
    return load_rig()


@pytest.fixture(scope="module")
def board_pairs(geometry):
    poses = random_board_poses(geometry, 13, seed=21, square_m=BOARD.square_m)
    return render_board_pairs(geometry, poses, seed=21, square_m=BOARD.square_m)


def check_against_truth(result, geometry):
    for cal, cam in ((result.left, geometry.left), (result.right, geometry.right)):
        K, Kt = cal.camera_matrix, cam.K
        for (i, j) in ((0, 0), (1, 1), (0, 2), (1, 2)):
            assert abs(K[i, j] / Kt[i, j] - 1.0) < 0.005, (i, j, K[i, j], Kt[i, j])
    baseline = np.linalg.norm(geometry.translation)
    assert abs(result.stereo.baseline_m / baseline - 1.0) < 0.005
    angle = np.degrees(np.linalg.norm(cv2.Rodrigues(result.stereo.rotation @ geometry.rotation.T)[0]))
    assert angle < 0.1


def test_calibration_from_13_board_pairs_recovers_the_rig(board_pairs, geometry):
    result = calibrate_stereo(board_pairs, BOARD)
    check_against_truth(result, geometry)
    assert 0.0 < result.stereo.rms_px < 0.3
    assert all(v.used for v in result.views) and len(result.views) == 13
    assert "stereo" in result.summary()


def test_cli_writes_a_calibration_that_reads_back(board_pairs, geometry, tmp_path):
    pairs_dir = tmp_path / "pairs"
    pairs_dir.mkdir()
    for name, left, right in board_pairs:
        cv2.imwrite(str(pairs_dir / f"left_{name}.png"), left)
        cv2.imwrite(str(pairs_dir / f"right_{name}.png"), right)
    out = tmp_path / "cal"
    args = argparse.Namespace(pairs=str(pairs_dir), board="9x6", square=20.0, min_views=8, live=False, output=str(out))
    assert cmd_calibrate(args) == 0
    cal = read_calibration_dir(out)
    assert cal.image_size == (640, 480)
    assert abs(cal.stereo.baseline_m / np.linalg.norm(geometry.translation) - 1.0) < 0.005


def test_an_outlier_view_is_dropped(board_pairs, geometry):
    name, left, right = board_pairs[0]
    # the right image shifted by 9 px: each camera alone still fits it, the pair is inconsistent
    shifted = np.roll(right, 9, axis=1)
    pairs = list(board_pairs[1:]) + [("shifted", left, shifted)]
    result = calibrate_stereo(pairs, BOARD)
    shifted_view = [v for v in result.views if v.name == "shifted"][0]
    assert not shifted_view.used and "outlier" in shifted_view.reason
    assert result.stereo.rms_px < 0.3
    check_against_truth(result, geometry)


def test_too_few_boards_is_refused_and_nothing_written(board_pairs, tmp_path):
    with pytest.raises(CalibrationError, match="only 5 of 5 pairs; need at least 8"):
        calibrate_stereo(board_pairs[:5], BOARD)


def test_wrong_board_size_says_no_board_found(board_pairs):
    with pytest.raises(CalibrationError, match=r"only 0 of 9 .*is the board really 7x5"):
        calibrate_stereo(board_pairs[:9], BoardSpec(7, 5, 0.02))


def test_mixed_image_sizes_are_refused(board_pairs):
    name, left, right = board_pairs[0]
    small = cv2.resize(right, (320, 240))
    with pytest.raises(CalibrationError, match="different sizes.*320x240"):
        calibrate_stereo(list(board_pairs[1:9]) + [(name, left, small)], BOARD)


def test_cli_errors_leave_no_files(tmp_path):
    out = tmp_path / "cal"
    empty = tmp_path / "empty"
    empty.mkdir()
    for pairs, board in ((str(tmp_path / "missing"), "9x6"), (str(empty), "9x6"), (str(empty), "9by6")):
        args = argparse.Namespace(pairs=pairs, board=board, square=25.0, min_views=8, live=False, output=str(out))
        with pytest.raises(CalibrationError):
            cmd_calibrate(args)
    assert not out.exists()

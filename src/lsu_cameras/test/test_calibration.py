"""Stereo calibration recovers the simulated rig's true geometry; impossible inputs are refused cleanly."""

import argparse

import cv2
import numpy as np
import pytest

from lsu_cameras.calib_io import read_calibration_dir
from lsu_cameras.calibration import BoardSpec, CalibrationError, calibrate_stereo, find_board, load_pairs
from lsu_cameras.cli import cmd_calibrate
from lsu_sim import load_rig
from lsu_testing.shared import board_pairs as shared_board_pairs

BOARD = BoardSpec(9, 6, 0.020)


@pytest.fixture(scope="module")
def geometry():
    return load_rig()


@pytest.fixture(scope="module")
def board_pairs(tmp_path_factory):
    """13 varied views of the simulated rig: the first 13 of test_live's 14, rendered once per run."""
    return shared_board_pairs(tmp_path_factory, 14, seed=21, square_m=BOARD.square_m)[:13]


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


def _rectified_rows(calib_dir, pairs, board):
    """y of every corner after rectification with the R, P of left.yaml / right.yaml alone (read as plain YAML)."""
    import yaml

    cams = {}
    for side in ("left", "right"):
        doc = yaml.safe_load((calib_dir / f"{side}.yaml").read_text())
        cams[side] = [np.array(doc[k]["data"]).reshape(doc[k]["rows"], doc[k]["cols"])
                      for k in ("camera_matrix", "distortion_coefficients", "rectification_matrix", "projection_matrix")]
    dy = []
    for _name, left, right in pairs:
        corners = {"left": find_board(left, board), "right": find_board(right, board)}
        if corners["left"] is None or corners["right"] is None:
            continue
        y = {side: cv2.undistortPoints(corners[side], K, D, R=R, P=P).reshape(-1, 2)[:, 1]
             for side, (K, D, R, P) in cams.items()}
        dy.append(y["left"] - y["right"])
    return np.abs(np.concatenate(dy)), cams


def test_calibrate_writes_the_rectification_of_the_pair(board_pairs, geometry, tmp_path):
    pairs_dir = tmp_path / "pairs"
    pairs_dir.mkdir()
    for name, left, right in board_pairs:
        cv2.imwrite(str(pairs_dir / f"left_{name}.png"), left)
        cv2.imwrite(str(pairs_dir / f"right_{name}.png"), right)
    out = tmp_path / "cal"
    args = argparse.Namespace(pairs=str(pairs_dir), board="9x6", square=20.0, min_views=8, live=False, output=str(out))
    assert cmd_calibrate(args) == 0
    dy, cams = _rectified_rows(out, board_pairs, BOARD)
    # corresponding corners land on the same rectified row (the renderer's boards, not the calibration, are the truth)
    assert len(dy) == 13 * 54 and np.median(dy) <= 0.15
    P_left, P_right = cams["left"][3], cams["right"][3]
    assert P_left[0, 3] == 0.0
    # camera_calibration's convention: the right P carries Tx = -fx' * baseline
    assert P_right[0, 3] == pytest.approx(-P_right[0, 0] * np.linalg.norm(geometry.translation), rel=0.005)
    # stereo.yaml keeps the raw extrinsics
    assert read_calibration_dir(out).stereo.rotation == pytest.approx(geometry.rotation, abs=2e-3)
    for name in ("left.yaml", "right.yaml", "stereo.yaml"):
        assert (out / name).stat().st_mode & 0o777 == 0o644


def test_committed_sim_calibration_rectifies_the_rendered_pairs(board_pairs):
    from lsu_cameras.paths import config_dir

    dy, _ = _rectified_rows(config_dir() / "calibration" / "sim", board_pairs, BOARD)
    assert np.median(dy) <= 0.15


def _write(folder, name, image, ext=".png"):
    folder.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(folder / f"{name}{ext}"), image)
    return folder / f"{name}{ext}"


def test_pairs_named_like_opencv_samples_or_in_side_folders_are_read(board_pairs, tmp_path):
    (name, left, right), (name2, left2, right2) = board_pairs[:2]
    samples = tmp_path / "samples"
    _write(samples, "left01", left, ".jpg")
    _write(samples, "right01", right, ".jpg")
    _write(samples, "left_02", left2, ".bmp")
    _write(samples, "right_02", right2, ".bmp")
    found = load_pairs(samples)
    assert [p[0] for p in found.pairs] == ["01", "02"] and found.report() == []
    assert found.pairs[1][1].shape == left2.shape
    folders = tmp_path / "folders"
    _write(folders / "left", "001", left)
    _write(folders / "right", "001", right)
    _write(folders / "left", "left002", left2, ".tif")
    _write(folders / "right", "right002", right2, ".tif")
    assert [p[0] for p in load_pairs(folders).pairs] == ["001", "002"]


def test_unpaired_and_unreadable_images_are_listed_by_name(board_pairs, tmp_path, capsys):
    folder = tmp_path / "pairs"
    for name, left, right in board_pairs[:9]:
        _write(folder, f"left_{name}", left)
        _write(folder, f"right_{name}", right)
    _write(folder, "left_lonely", board_pairs[9][1])
    cut = _write(folder, "left_cut", board_pairs[10][1], ".jpg")
    _write(folder, "right_cut", board_pairs[10][2], ".jpg")
    cut.write_bytes(cut.read_bytes()[:-3000])      # a copy that stopped early
    (folder / "right_junk.png").write_bytes(b"not an image")
    _write(folder, "left_junk", board_pairs[11][1])
    found = load_pairs(folder)
    report = "\n".join(found.report())
    assert "left_lonely.png: no partner image" in report
    assert "left_cut.jpg: truncated JPEG" in report
    assert "right_junk.png: not an image OpenCV can decode" in report
    assert len(found.pairs) == 9
    out = tmp_path / "cal"
    args = argparse.Namespace(pairs=str(folder), board="9x6", square=20.0, min_views=8, live=False, output=str(out))
    assert cmd_calibrate(args) == 0
    err = capsys.readouterr().err
    assert "left_lonely.png" in err and "left_cut.jpg" in err and "right_junk.png" in err


def test_a_larger_board_than_given_is_refused(board_pairs):
    with pytest.raises(CalibrationError, match=r"a 9x6 board is visible in .* given as 8x6.*--board 9x6"):
        calibrate_stereo(board_pairs[:9], BoardSpec(8, 6, 0.02))


def test_no_pairs_message_names_the_accepted_layouts(tmp_path):
    folder = tmp_path / "pairs"
    _write(folder, "cam0_01", np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(CalibrationError, match=r"no left/right image pairs.*leftNN.png / rightNN.png.*left/ and right/"):
        load_pairs(folder)

"""StereoModel: loading, validation with typed errors, undistortion and epipolar geometry against the synthetic rig."""

import numpy as np
import pytest
import yaml

from lsu_reconstruct import synthetic as S
from lsu_reconstruct.stereo import (
    CalibrationFileError,
    CalibrationInconsistentError,
    CalibrationParseError,
    CalibrationSizeError,
    CalibrationSwappedError,
    StereoModel,
)


@pytest.fixture
def rig():
    return S.default_rig()


@pytest.fixture
def calib(tmp_path, rig):
    return rig.write_calibration(tmp_path / "calib")


def random_points(n=200, seed=3):
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(-0.08, 0.1, n), rng.uniform(-0.07, 0.07, n), rng.uniform(0.22, 0.4, n)]


def test_folder_loads_the_rig_it_was_written_from(calib, rig):
    model = StereoModel.from_folder(calib)
    assert np.allclose(model.K1, rig.K1) and np.allclose(model.D2, rig.D2)
    assert np.allclose(model.R, rig.R) and np.allclose(model.T, rig.T)
    assert model.image_size == (640, 480)
    assert model.baseline_m == pytest.approx(np.linalg.norm([0.1218, 0.0018, 0.0045]), abs=1e-9)
    assert model.T[0] < 0  # right camera of a left-world rig
    assert len(model.calibration_id) == 16


def test_undistortion_inverts_opencv_projection(calib, rig):
    model = StereoModel.from_folder(calib)
    X = random_points()
    raw = rig.project(X, "left")
    ideal = (X / X[:, 2:3]) @ rig.K1.T  # pinhole projection, no distortion: analytic truth
    assert np.abs(model.undistort_left(raw[:, 0], raw[:, 1]) - ideal[:, :2]).max() < 1e-6
    raw_r = rig.project(X, "right")
    Xr = X @ rig.R.T + rig.T
    ideal_r = (Xr / Xr[:, 2:3]) @ rig.K2.T
    assert np.abs(model.undistort_right(raw_r[:, 0], raw_r[:, 1]) - ideal_r[:, :2]).max() < 1e-6


def test_true_correspondences_lie_on_their_epipolar_lines(calib, rig):
    model = StereoModel.from_folder(calib)
    X = random_points()
    x1 = model.undistort_left(*rig.project(X, "left").T)
    x2 = model.undistort_right(*rig.project(X, "right").T)
    lines = model.epipolar_lines(x1)
    assert np.allclose(np.hypot(lines[:, 0], lines[:, 1]), 1.0)
    assert np.abs(np.einsum("ij,ij->i", lines[:, :2], x2) + lines[:, 2]).max() < 1e-6  # pixels
    # and a wrong correspondence is far from it
    assert np.abs(np.einsum("ij,ij->i", lines[:, :2], np.roll(x2, 1, axis=0)) + lines[:, 2]).mean() > 1.0


def test_projection_matches_the_rig(calib, rig):
    model = StereoModel.from_folder(calib)
    X = random_points()
    assert np.abs(model.project_right(X) - rig.project(X, "right")).max() < 1e-9


def test_arrays_derive_E_and_F(rig):
    model = StereoModel.from_arrays(rig.K1, rig.D1, rig.K2, rig.D2, rig.R, rig.T, (640, 480))
    t = rig.T
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    assert np.allclose(model.E, tx @ rig.R)
    assert np.linalg.matrix_rank(model.F, tol=1e-9) == 2


def test_swapped_calibration_is_refused(tmp_path, rig):
    folder = rig.write_calibration(tmp_path / "swapped", swap=True)
    with pytest.raises(CalibrationSwappedError, match="swapped"):
        StereoModel.from_folder(folder)


def test_swapped_arrays_are_refused(rig):
    with pytest.raises(CalibrationSwappedError, match="T_x"):
        StereoModel.from_arrays(rig.K2, rig.D2, rig.K1, rig.D1, rig.R.T, -rig.R.T @ rig.T, (640, 480))


def test_exchanged_files_are_refused_by_camera_name(calib):
    left, right = (calib / "left.yaml").read_text(), (calib / "right.yaml").read_text()
    (calib / "left.yaml").write_text(right)
    (calib / "right.yaml").write_text(left)
    with pytest.raises(CalibrationSwappedError, match="camera_name"):
        StereoModel.from_folder(calib)


def test_missing_file_names_it(calib):
    (calib / "stereo.yaml").unlink()
    with pytest.raises(CalibrationFileError, match="stereo.yaml"):
        StereoModel.from_folder(calib)
    with pytest.raises(FileNotFoundError):
        StereoModel.from_folder(calib / "nowhere")


def test_unparseable_file_is_a_parse_error(calib):
    (calib / "left.yaml").write_text("camera_matrix: [1, 2\n")
    with pytest.raises(CalibrationParseError, match="left.yaml.*YAML"):
        StereoModel.from_folder(calib)


def test_missing_field_is_named(calib):
    doc = yaml.safe_load((calib / "right.yaml").read_text())
    del doc["camera_matrix"]
    (calib / "right.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(CalibrationParseError, match="camera_matrix"):
        StereoModel.from_folder(calib)


def test_image_size_mismatch_is_refused(tmp_path, rig):
    folder = rig.write_calibration(tmp_path / "c", right_size=(800, 600))
    with pytest.raises(CalibrationSizeError, match="800x600"):
        StereoModel.from_folder(folder)
    model = StereoModel.from_folder(rig.write_calibration(tmp_path / "ok"))
    with pytest.raises(CalibrationSizeError, match="1280x720"):
        model.check_image_size(1280, 720, "left laser line image")


def test_fundamental_that_disagrees_with_R_T_is_refused(calib):
    doc = yaml.safe_load((calib / "stereo.yaml").read_text())
    doc["fundamental"]["data"] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    (calib / "stereo.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(CalibrationInconsistentError, match="fundamental"):
        StereoModel.from_folder(calib)


def test_rodrigues_vector_instead_of_rotation_is_refused(rig):
    with pytest.raises(CalibrationParseError, match="R has 3 values"):
        StereoModel.from_arrays(rig.K1, rig.D1, rig.K2, rig.D2, [0.1, 0.2, 0.3], rig.T, (640, 480))
    with pytest.raises(CalibrationInconsistentError, match="rotation"):
        StereoModel.from_arrays(rig.K1, rig.D1, rig.K2, rig.D2, np.eye(3) * 2, rig.T, (640, 480))


def test_skewed_camera_matrix_is_honoured(rig):
    K1 = rig.K1.copy()
    K1[0, 1] = 1.5
    model = StereoModel.from_arrays(K1, rig.D1, rig.K2, rig.D2, rig.R, rig.T, (640, 480))
    X = random_points()
    raw = model.project_left(X)
    ideal = (X / X[:, 2:3]) @ K1.T
    assert np.abs(model.undistort_left(raw[:, 0], raw[:, 1]) - ideal[:, :2]).max() < 1e-6

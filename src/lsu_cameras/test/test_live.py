"""Guided live calibration: board coverage (X, Y, size, skew), view acceptance, and `lsu calibrate --live`
end to end against the stereo_camera node replaying rendered board pairs."""

import argparse
import threading

import cv2
import numpy as np
import pytest
from rclpy.parameter import Parameter
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import Image

from lsu_cameras.calib_io import read_calibration_dir
from lsu_cameras.calibration import BoardSpec
from lsu_cameras.cli import cmd_calibrate
from lsu_cameras.live import (
    CaptureClient,
    CoverageTracker,
    LiveCalibrationError,
    board_params,
    image_from_msg,
    run_live_calibration,
)
from lsu_cameras.node import StereoCameraNode
from lsu_sim import load_rig
from lsu_testing.shared import board_pairs as shared_board_pairs

BOARD = BoardSpec(9, 6, 0.020)
SIZE = (640, 480)


@pytest.fixture(scope="module")
def geometry():
    return load_rig()


@pytest.fixture(scope="module")
def board_pairs(tmp_path_factory):
    """14 varied views of the simulated rig (~20 s to render: shared by every test here and test_calibration)."""
    return shared_board_pairs(tmp_path_factory, 14, seed=21, square_m=BOARD.square_m)


def pinhole_corners(R, t, f=800.0, c=(320.0, 240.0)):
    """Board corners of pose (R, t) through an ideal pinhole camera (independent of OpenCV)."""
    p = BOARD.object_points.astype(np.float64) @ np.asarray(R).T + t
    return np.stack([f * p[:, 0] / p[:, 2] + c[0], f * p[:, 1] / p[:, 2] + c[1]], axis=1).astype(np.float32)


def centred_pose(R, distance=0.4):
    """Pose whose board centre is on the optical axis at ``distance``."""
    centre = np.array([(BOARD.cols - 1) / 2, (BOARD.rows - 1) / 2, 0.0]) * BOARD.square_m
    return R, np.array([0.0, 0.0, distance]) - R @ centre


def test_board_params_of_a_board_facing_the_camera_follow_pinhole_geometry():
    d, f = 0.4, 800.0
    params = board_params(pinhole_corners(*centred_pose(np.eye(3), d), f=f), BOARD, SIZE)
    width_px, height_px = 8 * 0.02 * f / d, 5 * 0.02 * f / d   # outer inner-corners span 8 x 5 squares
    side = np.sqrt(width_px * height_px)
    assert params.size == pytest.approx(width_px * height_px / (640 * 480), rel=1e-6)
    assert params.x == pytest.approx((320 - side / 2) / (640 - side), rel=1e-6)
    assert params.y == pytest.approx((240 - side / 2) / (480 - side), rel=1e-6)
    assert params.skew == pytest.approx(0.0, abs=1e-6)


def test_skew_grows_with_tilt_and_ignores_rotation_in_the_image_plane():
    in_plane = board_params(pinhole_corners(*centred_pose(Rotation.from_euler("z", 30, degrees=True).as_matrix())),
                            BOARD, SIZE)
    assert in_plane.skew == pytest.approx(0.0, abs=1e-6)
    skews = [board_params(pinhole_corners(*centred_pose(Rotation.from_euler(axis, a, degrees=True).as_matrix())),
                          BOARD, SIZE).skew for axis in "xy" for a in (10, 20, 30)]
    assert skews[0] < skews[1] < skews[2] and skews[3] < skews[4] < skews[5]
    assert skews[0] > 0.01


def test_varied_rendered_views_are_accepted_repeats_rejected_and_they_suffice(board_pairs):
    tracker = CoverageTracker(BOARD)
    good_after = None
    for k, (_, left, right) in enumerate(board_pairs):
        verdict = tracker.consider(left, right)
        assert verdict.accepted, (k, verdict.reason)
        assert verdict.view.number == k + 1 and len(tracker.views) == k + 1
        if good_after is None and tracker.is_good_enough():
            good_after = k + 1
        if k + 1 < tracker.min_views:
            assert not tracker.is_good_enough()  # never before min_views, whatever the coverage
    assert good_after is not None and good_after >= 12
    assert "[######]" in tracker.bars() and "[#" in tracker.bars()
    # the same pairs again (a board held still): each is a repeat of exactly its first showing
    for k, (_, left, right) in enumerate(board_pairs):
        verdict = tracker.consider(left, right)
        assert not verdict.accepted and verdict.nearest == k + 1
        assert verdict.reason == f"too close to view {k + 1}" and verdict.distance < 1e-9
    assert len(tracker.views) == len(board_pairs)


def test_a_board_missing_from_one_image_is_rejected_with_the_side(board_pairs):
    _, left, right = board_pairs[0]
    blank = np.full_like(right, 128)
    tracker = CoverageTracker(BOARD)
    assert tracker.consider(left, blank).reason == "board not found in right image"
    assert tracker.consider(blank, right).reason == "board not found in left image"
    assert tracker.consider(left, cv2.resize(right, (320, 240))).reason == "left image is 640x480 but right is 320x240"
    assert not tracker.views


def test_views_at_one_distance_without_tilt_never_suffice(geometry):
    """20 distinct views shifted over the image but all facing the rig at 0.40 m: X and Y are covered,
    size and skew are not, so more views of the same kind never make it good enough."""
    tracker = CoverageTracker(BOARD)
    axes = geometry.rig_axes
    R = axes.T
    offset = R @ (np.array([(BOARD.cols - 1) / 2, (BOARD.rows - 1) / 2, 0.0]) * BOARD.square_m)
    for dx in np.linspace(-0.05, 0.05, 5):
        for dy in np.linspace(-0.03, 0.03, 4):
            t = geometry.rig_center + 0.40 * axes[2] + dx * axes[0] + dy * axes[1] - offset
            pts = BOARD.object_points @ R.T + t
            left = geometry.left.project(pts).astype(np.float32)
            right = geometry.right.project(pts).astype(np.float32)
            tracker.add_detection(np.zeros((480, 640, 3), np.uint8), np.zeros((480, 640, 3), np.uint8), left, right)
    progress = {c.name: c.progress for c in tracker.coverage()}
    assert len(tracker.views) >= 12
    assert progress["X"] == 1.0 and progress["Y"] == 1.0
    assert progress["size"] < 0.5 and progress["skew"] < 0.5
    assert not tracker.is_good_enough()


def feed(pairs, then=KeyboardInterrupt):
    """A capture function replaying ``pairs`` and then raising ``then`` (Ctrl-C by default)."""
    it = iter(pairs)

    def capture():
        try:
            _, left, right = next(it)
        except StopIteration:
            raise then from None
        return left, right

    return capture


def test_ctrl_c_with_too_few_views_writes_nothing(board_pairs, tmp_path):
    lines = []
    with pytest.raises(LiveCalibrationError, match=r"stopped \(interrupted\) with 3 accepted views; need at least 8"):
        run_live_calibration(feed(board_pairs[:3]), CoverageTracker(BOARD), interval_s=0.0,
                             save_dir=tmp_path / "saved", report=lines.append)
    assert not (tmp_path / "saved").exists()
    assert lines[0].startswith("capture 1: view 1 accepted: X [")


def test_ctrl_c_with_enough_views_calibrates_and_saves_the_pairs(board_pairs, geometry, tmp_path):
    lines = []
    pairs = list(board_pairs[:10]) + [board_pairs[4]]  # one repeat among them
    live = run_live_calibration(feed(pairs), CoverageTracker(BOARD), interval_s=0.0, min_views=8,
                                save_dir=tmp_path / "saved", report=lines.append)
    assert live.stopped_by == "interrupted" and not live.good_enough and live.captures == 11
    assert len(live.views) == 10 and "capture 11: rejected: too close to view 5" in lines
    assert any("coverage incomplete" in line for line in lines)
    assert len(list((tmp_path / "saved").glob("left_*.png"))) == 10
    assert len(list((tmp_path / "saved").glob("right_*.png"))) == 10
    fx = live.calibration.left.camera_matrix[0, 0]
    assert abs(fx / geometry.left.K[0, 0] - 1.0) < 0.01


def test_max_captures_ends_the_session_and_camera_failures_are_fatal_after_three(board_pairs):
    blank = np.full_like(board_pairs[0][1], 128)
    lines = []
    with pytest.raises(LiveCalibrationError, match="with 0 accepted views"):
        run_live_calibration(lambda: (blank, blank), CoverageTracker(BOARD), interval_s=0.0, max_captures=4,
                             report=lines.append)
    assert lines == [f"capture {k}: rejected: board not found in left image" for k in range(1, 5)]

    def broken():
        raise LiveCalibrationError("capture failed: cannot open the left camera")

    with pytest.raises(LiveCalibrationError, match="3 captures in a row failed, last: capture failed: cannot open"):
        run_live_calibration(broken, CoverageTracker(BOARD), interval_s=0.0, report=lambda line: None)


@pytest.mark.parametrize("encoding, channels", [("bgr8", 3), ("rgb8", 3), ("mono8", 1)])
def test_image_messages_with_row_padding_decode_to_bgr(encoding, channels):
    rng = np.random.default_rng(4)
    image = rng.integers(0, 256, (5, 7, channels), dtype=np.uint8)
    step = 7 * channels + 3  # padded rows
    rows = np.zeros((5, step), np.uint8)
    rows[:, :7 * channels] = image.reshape(5, -1)
    msg = Image(height=5, width=7, encoding=encoding, step=step, data=rows.tobytes())
    out = image_from_msg(msg)
    expected = image[:, :, ::-1] if encoding == "rgb8" else (image[:, :, 0] if channels == 1 else image)
    assert np.array_equal(out, expected)
    with pytest.raises(LiveCalibrationError, match="unsupported image encoding '16UC1'"):
        image_from_msg(Image(height=5, width=7, encoding="16UC1", step=14, data=bytes(70)))


def test_a_missing_capture_service_is_one_line_naming_it_and_what_to_start():
    with pytest.raises(LiveCalibrationError) as info:
        CaptureClient(namespace="/lsu_nobody_here", wait_s=0.5)
    message = str(info.value)
    assert "/lsu_nobody_here/stereo/capture not available" in message
    assert "lsu launch sim" in message and "lsu launch lab" in message and "\n" not in message


def test_live_calibration_from_the_camera_node_recovers_the_rig(ros_node, board_pairs, geometry, tmp_path, capsys):
    folder = tmp_path / "replay"
    folder.mkdir()
    for name, left, right in board_pairs:
        cv2.imwrite(str(folder / f"left_{name}.png"), left)
        cv2.imwrite(str(folder / f"right_{name}.png"), right)
    overrides = [Parameter("source", value="folder"), Parameter("folder", value=str(folder))]
    ros_node.add(StereoCameraNode(context=ros_node.context, parameter_overrides=overrides))
    done = threading.Event()
    spinner = threading.Thread(target=ros_node.spin_until, args=(done.is_set, 120.0), daemon=True)
    spinner.start()
    try:
        args = argparse.Namespace(live=True, pairs=None, board="9x6", square=20.0, min_views=8, views=12,
                                  interval=0.0, max_views=40, save_pairs=str(tmp_path / "saved"),
                                  output=str(tmp_path / "cal"))
        assert cmd_calibrate(args) == 0
    finally:
        done.set()
        spinner.join(timeout=10.0)
    out = capsys.readouterr().out
    assert "capture 1: view 1 accepted: X [" in out and "coverage is good enough with" in out
    saved = len(list((tmp_path / "saved").glob("left_*.png")))
    assert 12 <= saved <= len(board_pairs) and f"good enough with {saved} views" in out
    cal = read_calibration_dir(tmp_path / "cal")
    for ours, truth in ((cal.left.camera_matrix, geometry.left.K), (cal.right.camera_matrix, geometry.right.K)):
        for (i, j) in ((0, 0), (1, 1), (0, 2), (1, 2)):
            assert abs(ours[i, j] / truth[i, j] - 1.0) < 0.005, (i, j, ours[i, j], truth[i, j])
    assert abs(cal.stereo.baseline_m / np.linalg.norm(geometry.translation) - 1.0) < 0.005

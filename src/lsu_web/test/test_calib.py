"""The page's calibration session without ROS: pairs judged by lsu_cameras' coverage tracker."""

import numpy as np
import pytest

from lsu_common.arrays import AnyArray
from lsu_web.calib import CalibrationSession


def chessboard(cols: int = 10, rows: int = 7, square_px: int = 40, margin: int = 60) -> AnyArray:
    """A flat chessboard of cols x rows squares ((cols-1) x (rows-1) inner corners), white margin, BGR."""
    h, w = rows * square_px + 2 * margin, cols * square_px + 2 * margin
    img = np.full((h, w), 255, np.uint8)
    for r in range(rows):
        for c in range(cols):
            if (r + c) % 2 == 0:
                img[margin + r * square_px: margin + (r + 1) * square_px,
                    margin + c * square_px: margin + (c + 1) * square_px] = 0
    return np.dstack([img] * 3)


def test_a_pair_is_kept_once_and_a_repeat_is_refused_with_the_reason():
    session = CalibrationSession()
    with pytest.raises(ValueError, match="start a calibration session"):
        session.consider(chessboard(), chessboard())
    session.reset("9x6", 25.0, 8)
    board = chessboard()
    first = session.consider(board, board)
    assert first["last"] == {"accepted": True, "reason": ""} and first["views"] == 1
    again = session.consider(board, board)
    assert not again["last"]["accepted"] and "too close" in again["last"]["reason"]
    assert again["views"] == 1 and again["captures"] == 2 and not again["good_enough"]
    blank = np.full_like(board, 128)
    assert session.consider(blank, blank)["last"]["reason"] == "board not found in left image"
    assert [c["name"] for c in session.status()["coverage"]] == ["X", "Y", "size", "skew"]


def test_a_board_text_that_does_not_parse_is_refused():
    from lsu_cameras.calibration import CalibrationError

    with pytest.raises(CalibrationError):
        CalibrationSession().reset("nine by six", 25.0, 8)

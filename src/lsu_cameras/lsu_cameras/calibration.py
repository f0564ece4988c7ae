"""Stereo calibration from chessboard image pairs (OpenCV), the way the thesis did it with Bouguet's toolbox.

`find_board` detects the inner corners (findChessboardCorners + cornerSubPix); `calibrate_stereo`
calibrates each camera (calibrateCamera), reports per-view reprojection errors, drops outlier views
and recalibrates, then estimates R, T with the intrinsics fixed (stereoCalibrate). k3 is fixed to 0
by default, as the thesis' toolbox did (its default model estimates k1, k2, p1, p2 only).
Everything that makes a calibration impossible raises `CalibrationError` with a sentence the user
can act on; nothing is written by this module (see `calib_io.write_calibration_dir`).
"""

from __future__ import annotations

import datetime as _dt
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from lsu_common.arrays import AnyArray

from .calib_io import CameraCalibration, StereoCalibration


class CalibrationError(RuntimeError):
    """Calibration is impossible with the given images or settings."""


@dataclass
class BoardSpec:
    """Chessboard: inner corners (cols x rows) and square size in metres."""

    cols: int = 9
    rows: int = 6
    square_m: float = 0.025

    @classmethod
    def parse(cls, text: str, square_mm: float) -> BoardSpec:
        """From ``"9x6"`` and a square size in millimetres."""
        match = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
        if not match:
            raise CalibrationError(f"board '{text}' is not COLSxROWS of inner corners, e.g. 9x6")
        cols, rows = int(match.group(1)), int(match.group(2))
        if cols < 3 or rows < 3 or cols == rows:
            raise CalibrationError(f"board {cols}x{rows}: need at least 3x3 inner corners and cols != rows "
                                   "(a square board has no unique orientation)")
        if not square_mm > 0:
            raise CalibrationError(f"square size {square_mm} mm must be positive")
        return cls(cols, rows, square_mm / 1000.0)

    @property
    def object_points(self) -> AnyArray:
        """Corner coordinates on the board (metres, z = 0), row-major like OpenCV's detections."""
        j, i = np.mgrid[0:self.rows, 0:self.cols]
        return np.stack([i.ravel(), j.ravel(), np.zeros(i.size)], axis=1).astype(np.float32) * self.square_m


@dataclass
class ViewResult:
    """One accepted or rejected image pair."""

    name: str
    left_error_px: float = float("nan")
    right_error_px: float = float("nan")
    used: bool = False
    reason: str = ""


@dataclass
class StereoCalibrationResult:
    """Both cameras, the extrinsics and the per-view report."""

    left: CameraCalibration
    right: CameraCalibration
    stereo: StereoCalibration
    left_rms_px: float
    right_rms_px: float
    views: list[ViewResult] = field(default_factory=list)
    coverage: tuple[float, float] = (0.0, 0.0)   # fraction of the image area covered by corners (left, right)

    def summary(self) -> str:
        """Human-readable report (one line per view)."""
        used = sum(v.used for v in self.views)
        lines = [f"views used: {used} of {len(self.views)}; RMS left {self.left_rms_px:.3f} px, right "
                 f"{self.right_rms_px:.3f} px, stereo {self.stereo.rms_px:.3f} px; baseline "
                 f"{self.stereo.baseline_m * 1000:.2f} mm; corner coverage left {self.coverage[0]:.0%}, "
                 f"right {self.coverage[1]:.0%}"]
        for v in self.views:
            state = "used" if v.used else f"dropped ({v.reason})"
            lines.append(f"  {v.name}: left {v.left_error_px:.3f} px, right {v.right_error_px:.3f} px  {state}")
        return "\n".join(lines)


def to_gray(image: AnyArray) -> AnyArray:
    """8-bit grayscale of a BGR or gray image."""
    if image.ndim == 2:
        return image
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


def find_board(image: AnyArray, board: BoardSpec) -> AnyArray | None:
    """Sub-pixel inner corners (N,1,2 float32) of ``board`` in ``image``, or None when not found."""
    gray = to_gray(image)
    found, corners = cv2.findChessboardCorners(gray, (board.cols, board.rows),
                                               cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not found:
        return None
    # window ~ a third of the smallest square side, so it never reaches the next corner
    side = np.min(np.linalg.norm(np.diff(corners.reshape(board.rows, board.cols, 2), axis=1), axis=2))
    half = int(np.clip(side / 3.0, 2, 11))
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    return cv2.cornerSubPix(gray, corners, (half, half), (-1, -1), criteria)


def larger_board_visible(image: AnyArray, board: BoardSpec) -> tuple[int, int] | None:
    """(cols, rows) of a board one corner wider or taller than ``board`` when it is found in ``image``.

    findChessboardCorners can lock onto part of a larger board; a calibration with the wrong
    corner count has the wrong square positions, so it is refused instead.
    """
    gray = to_gray(image)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
    for size in ((board.cols + 1, board.rows), (board.cols, board.rows + 1)):
        if size[0] != size[1] and cv2.findChessboardCorners(gray, size, flags)[0]:
            return size
    return None


def _view_errors(obj: list[AnyArray], img: list[AnyArray], K: AnyArray, D: AnyArray,
                 rvecs: Sequence[AnyArray], tvecs: Sequence[AnyArray]) -> AnyArray:
    errs = []
    for o, i, r, t in zip(obj, img, rvecs, tvecs):
        proj, _ = cv2.projectPoints(o, r, t, K, D)
        errs.append(float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - i.reshape(-1, 2)) ** 2, axis=1)))))
    return np.array(errs)


def _calibrate_mono(obj: list[AnyArray], img: list[AnyArray], size: tuple[int, int], flags: int):
    rms, K, D, rvecs, tvecs = cv2.calibrateCamera(obj, img, size, None, None, flags=flags)
    return rms, K, D.reshape(-1)[:5], _view_errors(obj, img, K, D, rvecs, tvecs)


def _calibrate_extrinsics(obj: list[AnyArray], img_l: list[AnyArray], img_r: list[AnyArray], K_l: AnyArray,
                          D_l: AnyArray, K_r: AnyArray, D_r: AnyArray, size: tuple[int, int]):
    """R, T, E, F with the intrinsics fixed, and each view's stereo RMS error (worst of its two images)."""
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-10)
    out = cv2.stereoCalibrateExtended(obj, img_l, img_r, K_l, D_l, K_r, D_r, size, None, None,
                                      flags=cv2.CALIB_FIX_INTRINSIC, criteria=criteria)
    per_view = np.asarray(out[11]).reshape(len(obj), -1).max(axis=1)
    return float(out[0]), out[5], out[6], out[7], out[8], per_view


def _coverage(points: list[AnyArray], size: tuple[int, int]) -> float:
    """Fraction of a 8x6 grid over the image that holds at least one detected corner."""
    grid = np.zeros((6, 8), bool)
    for p in points:
        q = p.reshape(-1, 2)
        gx = np.clip((q[:, 0] / size[0] * 8).astype(int), 0, 7)
        gy = np.clip((q[:, 1] / size[1] * 6).astype(int), 0, 5)
        grid[gy, gx] = True
    return float(grid.mean())


def calibrate_stereo(pairs: Sequence[tuple[str, AnyArray, AnyArray]], board: BoardSpec, min_views: int = 8,
                     outlier_factor: float = 3.0, fix_k3: bool = True) -> StereoCalibrationResult:
    """Calibrate both cameras and their extrinsics from ``(name, left_image, right_image)`` pairs.

    A view is an outlier when its reprojection error exceeds ``outlier_factor`` times the median
    (and 0.5 px); outliers are dropped and the cameras recalibrated once.
    """
    if not pairs:
        raise CalibrationError("no image pairs given")
    sizes: dict[tuple[int, int], list[str]] = {}
    for name, left, right in pairs:
        for side, image in (("left", left), ("right", right)):
            sizes.setdefault((image.shape[1], image.shape[0]), []).append(f"{name} ({side})")
    if len(sizes) > 1:
        detail = "; ".join(f"{w}x{h}: {', '.join(names[:3])}{' ...' if len(names) > 3 else ''}"
                           for (w, h), names in sizes.items())
        raise CalibrationError(f"images of different sizes cannot be calibrated together ({detail})")
    size = next(iter(sizes))
    views: list[ViewResult] = []
    obj, img_l, img_r, kept = [], [], [], []
    for name, left, right in pairs:
        cl, cr = find_board(left, board), find_board(right, board)
        view = ViewResult(name)
        if cl is None or cr is None:
            missing = " and ".join(s for s, c in (("left", cl), ("right", cr)) if c is None)
            view.reason = f"no {board.cols}x{board.rows} board found in the {missing} image"
        else:
            obj.append(board.object_points)
            img_l.append(cl)
            img_r.append(cr)
            kept.append(view)
        views.append(view)
    # two views tell (the board is the same in all); a check of every view would double the detection time
    for name, left, _right in pairs[:2]:
        larger = larger_board_visible(left, board)
        if larger is not None:
            raise CalibrationError(f"a {larger[0]}x{larger[1]} board is visible in {name} (left) but the board "
                                   f"was given as {board.cols}x{board.rows}: count the inner corners (where four "
                                   f"squares meet) and give --board {larger[0]}x{larger[1]}")
    if len(obj) < min_views:
        hint = (f" (no board at all: is the board really {board.cols}x{board.rows} inner corners?)"
                if not obj else "")
        raise CalibrationError(f"board found in both images of only {len(obj)} of {len(pairs)} pairs; need at "
                               f"least {min_views}{hint}. Capture more views at different angles and distances.")
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    active = list(range(len(obj)))
    # Two passes: calibrate, then drop views whose mono *or* stereo reprojection error is an outlier
    # (a view can fit each camera alone and still be inconsistent between them, e.g. a swapped or
    # re-timed image), and calibrate again without them.
    for attempt in range(2):
        o = [obj[k] for k in active]
        pl, pr = [img_l[k] for k in active], [img_r[k] for k in active]
        rms_l, K_l, D_l, err_l = _calibrate_mono(o, pl, size, flags)
        rms_r, K_r, D_r, err_r = _calibrate_mono(o, pr, size, flags)
        rms_s, R, T, E, F, err_s = _calibrate_extrinsics(o, pl, pr, K_l, D_l, K_r, D_r, size)
        for k, el, er in zip(active, err_l, err_r):
            kept[k].left_error_px, kept[k].right_error_px = float(el), float(er)
        worst = np.maximum(np.maximum(err_l, err_r), err_s)
        limit = max(outlier_factor * float(np.median(worst)), 0.5)
        bad = worst > limit
        if attempt == 1 or not np.any(bad):
            break
        for k, w in zip(active, worst):
            if w > limit:
                kept[k].reason = f"reprojection error {w:.2f} px > {limit:.2f} px (outlier)"
        active = [k for k, b in zip(active, bad) if not b]
        if len(active) < min_views:
            raise CalibrationError(f"only {len(active)} views are consistent (others exceed {limit:.2f} px); "
                                   f"need {min_views}. Check focus, that the board is flat and the pairs match.")
    for k in active:
        kept[k].used = True
        kept[k].reason = ""
    img_l, img_r = [img_l[k] for k in active], [img_r[k] for k in active]
    date = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    left_cal = CameraCalibration(size[0], size[1], K_l, D_l, "lsu_left")
    right_cal = CameraCalibration(size[0], size[1], K_r, D_r, "lsu_right")
    stereo = StereoCalibration(size[0], size[1], R, T.reshape(3), E, F / np.linalg.norm(F), rms_s, date)
    return StereoCalibrationResult(left_cal, right_cal, stereo, float(rms_l), float(rms_r), views,
                                   (_coverage(img_l, size), _coverage(img_r, size)))


# left01.png, left_01.png, left-01.png, Left01.JPG, ... (the key is what follows the side's name)
_SIDE_NAME = re.compile(r"^(left|right)[_-]?(.+)$", re.IGNORECASE)


@dataclass
class PairFolder:
    """Image pairs read from a folder, and what could not be used, by name."""

    pairs: list[tuple[str, AnyArray, AnyArray]]
    unpaired: list[str] = field(default_factory=list)
    unreadable: list[tuple[str, str]] = field(default_factory=list)   # (file, why)

    def report(self) -> list[str]:
        """One line per problem, for the user."""
        lines = [f"skipped {name}: no partner image (expected the same number with the other side's name)"
                 for name in self.unpaired]
        lines += [f"skipped {name}: {why}" for name, why in self.unreadable]
        return lines


def _read_image(path: Path) -> tuple[AnyArray | None, str]:
    """(BGR image, '') or (None, why). ``cv2.imread`` decodes a truncated JPEG with only a warning
    (the missing part grey), which later reads as "no board found": such files are named by their
    missing end-of-image marker here."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        return None, f"cannot be read ({exc.strerror})"
    if data[:2] == b"\xff\xd8" and b"\xff\xd9" not in data[-64:]:
        return None, "truncated JPEG (no end-of-image marker): copy it again"
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR) if data else None
    if image is None:
        return None, "not an image OpenCV can decode (empty, truncated or of an unsupported format)"
    return image, ""


def _side_files(directory: Path) -> dict[str, dict[str, Path]]:
    """{'left': {key: path}, 'right': {key: path}} from left/ + right/ sub-folders or leftNN / left_NN names."""
    sides: dict[str, dict[str, Path]] = {"left": {}, "right": {}}
    subdirs = {side: directory / side for side in sides if (directory / side).is_dir()}
    if len(subdirs) == 2:
        for side, folder in subdirs.items():
            for path in sorted(folder.iterdir()):
                if path.is_file() and not path.name.startswith("."):
                    match = _SIDE_NAME.match(path.stem)
                    # left/left01.png and left/01.png both pair with right/right01.png or right/01.png
                    key = match.group(2) if match and match.group(1).lower() == side else path.stem
                    sides[side][key.lstrip("_-")] = path
        return sides
    for path in sorted(directory.iterdir()):
        match = _SIDE_NAME.match(path.stem)
        if path.is_file() and match:
            sides[match.group(1).lower()][match.group(2)] = path
    return sides


def load_pairs(directory: os.PathLike | str) -> PairFolder:
    """Read stereo pairs from ``directory``: ``leftNN``/``rightNN`` or ``left_NN``/``right_NN`` files, or
    ``left/`` + ``right/`` sub-folders, in any image format OpenCV reads; pairs match by ``NN``.

    Unpaired and unreadable files are listed (`PairFolder.report`), not silently dropped.
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise CalibrationError(f"{directory}: image folder not found")
    sides = _side_files(directory)
    common = sorted(set(sides["left"]) & set(sides["right"]))
    unpaired = sorted(str(p.relative_to(directory)) for side, other in (("left", "right"), ("right", "left"))
                      for key, p in sides[side].items() if key not in sides[other])
    if not common:
        raise CalibrationError(
            f"{directory}: no left/right image pairs (found {len(sides['left'])} left and {len(sides['right'])} "
            f"right images). Name them leftNN.png / rightNN.png or left_NN.png / right_NN.png (any image format), "
            f"or put them in left/ and right/ sub-folders with equal names")
    found = PairFolder([], unpaired)
    for key in common:
        left, why_l = _read_image(sides["left"][key])
        right, why_r = _read_image(sides["right"][key])
        for path, why in ((sides["left"][key], why_l), (sides["right"][key], why_r)):
            if why:
                found.unreadable.append((str(path.relative_to(directory)), why))
        if left is not None and right is not None:
            found.pairs.append((key, left, right))
    if not found.pairs:
        raise CalibrationError(f"{directory}: none of the {len(common)} pairs could be read:\n  "
                               + "\n  ".join(found.report()))
    return found

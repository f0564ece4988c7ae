"""Calibration files, the one reader and writer of the project: ROS camera_calibration YAML
(``left.yaml``, ``right.yaml``) and the LSU ``stereo.yaml``.

Formats are those of CONTRIBUTING.md "Parameters and config". ``left.yaml``/``right.yaml`` carry
the rectification of the pair as ROS camera_calibration's stereo calibrator writes it (R and P of
each camera from ``cv2.stereoRectify``; the right P holds ``Tx = -fx' * baseline``), so any ROS
stereo consumer sees a rectified pair; ``stereo.yaml`` keeps the raw extrinsics
``X_right = R X_left + T`` [m].

Readers validate everything they return (shapes, finite numbers, positive size, left/right not
exchanged) and raise a `CalibrationError` subclass naming the file and the field, so a node can
refuse a broken file with one clear line.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import os
import tempfile
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from lsu_common.arrays import AnyArray, FloatArray

__all__ = [
    "CalibrationError", "CalibrationFileError", "CalibrationParseError", "CalibrationSizeError",
    "CalibrationSwappedError", "CalibrationInconsistentError", "CameraCalibration", "StereoCalibration",
    "CalibrationSet", "skew", "fundamental_from", "rectify", "read_camera_yaml", "read_stereo_yaml",
    "read_calibration_dir", "write_calibration_dir", "calibration_checksum", "camera_to_dict", "stereo_to_dict",
]

# distortion models of sensor_msgs/CameraInfo that OpenCV evaluates, and their coefficient counts
DISTORTION_MODELS = {"plumb_bob": (5,), "rational_polynomial": (8,)}


class CalibrationError(ValueError):
    """A calibration cannot be used; the message says what is wrong and what to do."""


class CalibrationFileError(CalibrationError, FileNotFoundError):
    """A calibration file or folder is missing."""


class CalibrationParseError(CalibrationError):
    """A calibration file does not parse, lacks a field or holds a value of the wrong shape."""


class CalibrationSizeError(CalibrationError):
    """Image sizes of the calibration files (or of the data) disagree."""


class CalibrationSwappedError(CalibrationError):
    """Left and right cameras are swapped (the baseline points the wrong way)."""


class CalibrationInconsistentError(CalibrationError):
    """Stored E/F disagree with R, T and the intrinsics, or a matrix is not what it claims to be."""


@dataclass
class CameraCalibration:
    """One camera in ROS camera_info terms (K, D, R, P) plus its image size."""

    image_width: int
    image_height: int
    camera_matrix: AnyArray                      # K, 3x3
    distortion_coefficients: AnyArray            # plumb_bob [k1, k2, p1, p2, k3]
    camera_name: str = "camera"
    rectification_matrix: AnyArray = field(default_factory=lambda: np.eye(3))
    projection_matrix: AnyArray | None = None  # 3x4; [K | 0] when not rectified
    distortion_model: str = "plumb_bob"

    def __post_init__(self) -> None:
        self.camera_matrix = np.asarray(self.camera_matrix, dtype=np.float64).reshape(3, 3)
        self.distortion_coefficients = np.asarray(self.distortion_coefficients, dtype=np.float64).reshape(-1)
        self.rectification_matrix = np.asarray(self.rectification_matrix, dtype=np.float64).reshape(3, 3)
        if self.projection_matrix is None:
            self.projection_matrix = np.hstack([self.camera_matrix, np.zeros((3, 1))])
        self.projection_matrix = np.asarray(self.projection_matrix, dtype=np.float64).reshape(3, 4)

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return (int(self.image_width), int(self.image_height))


@dataclass
class StereoCalibration:
    """Geometry of the right camera w.r.t. the left: X_right = R X_left + T (metres)."""

    image_width: int
    image_height: int
    rotation: AnyArray          # 3x3
    translation: AnyArray       # (3,) metres
    essential: AnyArray | None = None
    fundamental: AnyArray | None = None
    rms_px: float = 0.0
    date: str = ""
    left_frame_id: str = "lsu_left_optical"
    right_frame_id: str = "lsu_right_optical"

    def __post_init__(self) -> None:
        self.rotation = np.asarray(self.rotation, dtype=np.float64).reshape(3, 3)
        self.translation = np.asarray(self.translation, dtype=np.float64).reshape(3)
        if self.essential is None:
            self.essential = skew(self.translation) @ self.rotation
        self.essential = np.asarray(self.essential, dtype=np.float64).reshape(3, 3)
        if self.fundamental is not None:
            self.fundamental = np.asarray(self.fundamental, dtype=np.float64).reshape(3, 3)
        if not self.date:
            self.date = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")

    @property
    def baseline_m(self) -> float:
        """|T| in metres."""
        return float(np.linalg.norm(self.translation))


def skew(v: AnyArray) -> FloatArray:
    """Cross-product matrix [v]x with [v]x @ w == cross(v, w)."""
    x, y, z = np.asarray(v, dtype=np.float64).reshape(3)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def fundamental_from(left: CameraCalibration, right: CameraCalibration, rotation: AnyArray,
                     translation: AnyArray) -> AnyArray:
    """F for undistorted pixels, x_right^T F x_left = 0, scaled so that ||F|| = 1."""
    return check_epipolar(left.camera_matrix, right.camera_matrix, np.asarray(rotation, dtype=np.float64).reshape(3, 3),
                          np.asarray(translation, dtype=np.float64).reshape(3), None, None, "")[1]


def rectify(left: CameraCalibration, right: CameraCalibration, stereo: StereoCalibration,
            alpha: float = 0.0) -> tuple[CameraCalibration, CameraCalibration]:
    """Both cameras with the rectification of the pair (R1, P1, R2, P2 of ``cv2.stereoRectify``).

    As ROS camera_calibration's stereo calibrator: zero disparity at infinity, ``alpha`` 0 (only
    valid pixels), the right P carrying ``Tx = -fx' * baseline`` in ``P[0, 3]``.
    """
    R1, R2, P1, P2, _Q, _roi1, _roi2 = cv2.stereoRectify(
        left.camera_matrix, left.distortion_coefficients, right.camera_matrix, right.distortion_coefficients,
        left.image_size, stereo.rotation, stereo.translation.reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY,
        alpha=alpha)
    out = []
    for cam, R, P in ((left, R1, P1), (right, R2, P2)):
        out.append(CameraCalibration(cam.image_width, cam.image_height, cam.camera_matrix.copy(),
                                     cam.distortion_coefficients.copy(), cam.camera_name, R, P, cam.distortion_model))
    return out[0], out[1]


def _matrix(rows: int, cols: int, data: AnyArray) -> dict[str, Any]:
    return {"rows": rows, "cols": cols, "data": [float(x) for x in np.asarray(data, dtype=np.float64).reshape(-1)]}


def camera_to_dict(cal: CameraCalibration) -> dict[str, Any]:
    """The ROS camera_calibration YAML mapping of one camera."""
    assert cal.projection_matrix is not None  # __post_init__ sets it
    return {
        "image_width": int(cal.image_width),
        "image_height": int(cal.image_height),
        "camera_name": cal.camera_name,
        "camera_matrix": _matrix(3, 3, cal.camera_matrix),
        "distortion_model": cal.distortion_model,
        "distortion_coefficients": _matrix(1, cal.distortion_coefficients.size, cal.distortion_coefficients),
        "rectification_matrix": _matrix(3, 3, cal.rectification_matrix),
        "projection_matrix": _matrix(3, 4, cal.projection_matrix),
    }


def stereo_to_dict(cal: StereoCalibration) -> dict[str, Any]:
    """The ``stereo.yaml`` mapping of CONTRIBUTING.md."""
    assert cal.essential is not None  # __post_init__ sets it
    out: dict[str, Any] = {
        "image_width": int(cal.image_width),
        "image_height": int(cal.image_height),
        "left_frame_id": cal.left_frame_id,
        "right_frame_id": cal.right_frame_id,
        "rotation": _matrix(3, 3, cal.rotation),
        "translation": _matrix(3, 1, cal.translation),
        "essential": _matrix(3, 3, cal.essential),
    }
    if cal.fundamental is not None:
        out["fundamental"] = _matrix(3, 3, cal.fundamental)
    out["rms_px"] = float(cal.rms_px)
    out["date"] = cal.date
    return out


# ---------------------------------------------------------------------- validation shared with array inputs
def check_camera_matrix(K: AnyArray, source: str, name: str = "camera_matrix") -> None:
    """Refuse a K that is not [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with positive focal lengths."""
    if K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1.0 or np.any(K[1:, 0] != 0) or K[2, 1] != 0:
        raise CalibrationParseError(f"{source}: {name} is not a camera matrix [[fx, s, cx], [0, fy, cy], "
                                    f"[0, 0, 1]] with positive focal lengths: {K.tolist()}")


def check_extrinsics(R: AnyArray, T: AnyArray, source: str) -> None:
    """Refuse a non-rotation R, a zero or implausible baseline, and swapped cameras (right centre at x <= 0)."""
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0.99:
        raise CalibrationInconsistentError(f"{source}: rotation R is not a rotation matrix (R R^T != I or det "
                                           f"{np.linalg.det(R):.4f} != 1); check that 'rotation' holds the 3x3 "
                                           f"matrix row-major, not a Rodrigues vector")
    baseline = float(np.linalg.norm(T))
    if baseline < 1e-6:
        raise CalibrationInconsistentError(f"{source}: baseline |T| = {baseline} m; the cameras cannot share one centre")
    centre = -R.T @ T
    if centre[0] <= 0.0:
        raise CalibrationSwappedError(
            f"{source}: left/right cameras look swapped: the right camera centre -R^T T = "
            f"{np.round(centre * 1000, 1).tolist()} mm lies at x <= 0 (left of the left camera; T_x = "
            f"{T[0] * 1000:.1f} mm should be negative for X_right = R X_left + T). Exchange left.yaml and "
            f"right.yaml (or the camera devices) and recalibrate the extrinsics")
    if baseline > 5.0:
        raise CalibrationInconsistentError(f"{source}: baseline {baseline:.3f} m is implausible; T must be in "
                                           f"metres (the LSU's is ~0.122 m)")


def _same_up_to_scale(a: AnyArray, b: AnyArray, tol: float) -> bool:
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    return bool(min(np.linalg.norm(a - b), np.linalg.norm(a + b)) < tol)


def check_epipolar(K1: AnyArray, K2: AnyArray, R: AnyArray, T: AnyArray, E: AnyArray | None,
                   F: AnyArray | None, source: str) -> tuple[AnyArray, AnyArray]:
    """E = [T]x R and F = K2^-T E K1^-1 (unit norm); stored E/F (when given, non-zero) must equal them up to scale."""
    Ed = skew(T) @ R
    Fd = np.linalg.inv(K2).T @ Ed @ np.linalg.inv(K1)
    Fd = Fd / np.linalg.norm(Fd)
    if E is not None and np.any(E != 0) and not _same_up_to_scale(np.asarray(E, dtype=np.float64), Ed, 1e-3):
        raise CalibrationInconsistentError(f"{source}: the stored essential matrix does not equal [T]x R; "
                                           f"re-export the stereo calibration")
    if F is not None and np.any(F != 0) and not _same_up_to_scale(np.asarray(F, dtype=np.float64), Fd, 1e-3):
        raise CalibrationInconsistentError(f"{source}: the stored fundamental matrix does not equal "
                                           f"K2^-T [T]x R K1^-1 (for undistorted pixels); re-export the "
                                           f"stereo calibration")
    return Ed, Fd


# ---------------------------------------------------------------------- reading
def _load_yaml(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise CalibrationFileError(f"calibration file {path} not found; run `lsu calibrate` or point "
                                   f"calibration_dir at a folder with left.yaml, right.yaml and stereo.yaml")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise CalibrationParseError(f"{path}: not valid YAML{where}: {getattr(exc, 'problem', exc)}") from None
    if not isinstance(data, dict):
        raise CalibrationParseError(f"{path}: expected a YAML mapping of calibration fields, got {type(data).__name__}")
    return data


def _read_matrix(path: Path, data: dict[str, Any], key: str, shape: tuple[int, int]) -> FloatArray:
    if key not in data:
        rows, cols = shape if shape[0] * shape[1] else (1, "N")
        raise CalibrationParseError(f"{path}: missing field '{key}'; write it as {{rows: {rows}, cols: {cols}, "
                                    f"data: [...]}} (ROS camera_calibration format)")
    value = data[key]
    raw = value.get("data") if isinstance(value, dict) else value
    try:
        arr = np.asarray(raw, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise CalibrationParseError(f"{path}: field '{key}' must be a list of numbers") from None
    if shape[0] * shape[1] and arr.size != shape[0] * shape[1]:
        raise CalibrationParseError(f"{path}: field '{key}' has {arr.size} numbers, expected {shape[0] * shape[1]} "
                                    f"({shape[0]}x{shape[1]})")
    if not np.all(np.isfinite(arr)):
        raise CalibrationParseError(f"{path}: field '{key}' contains NaN or infinite values")
    return arr.reshape(shape) if shape[0] * shape[1] else arr


def _read_size(path: Path, data: dict[str, Any]) -> tuple[int, int]:
    try:
        w, h = int(data["image_width"]), int(data["image_height"])
    except KeyError as exc:
        raise CalibrationParseError(f"{path}: missing field '{exc.args[0]}'") from None
    except (TypeError, ValueError):
        raise CalibrationParseError(f"{path}: image_width/image_height must be integers") from None
    if w <= 0 or h <= 0:
        raise CalibrationParseError(f"{path}: image size {w}x{h} is not positive")
    return w, h


def read_camera_yaml(path: os.PathLike | str) -> CameraCalibration:
    """Read a ROS camera_calibration YAML (plumb_bob with 5 or rational_polynomial with 8 coefficients)."""
    path = Path(path)
    data = _load_yaml(path)
    w, h = _read_size(path, data)
    model = str(data.get("distortion_model", "plumb_bob"))
    if model not in DISTORTION_MODELS:
        raise CalibrationParseError(f"{path}: distortion_model '{model}' is not supported; use plumb_bob "
                                    f"([k1, k2, p1, p2, k3]) or rational_polynomial")
    K = _read_matrix(path, data, "camera_matrix", (3, 3))
    check_camera_matrix(K, str(path))
    D = _read_matrix(path, data, "distortion_coefficients", (0, 0))
    if D.size not in DISTORTION_MODELS[model]:
        raise CalibrationParseError(f"{path}: distortion_coefficients has {D.size} numbers; {model} needs "
                                    f"{DISTORTION_MODELS[model][0]}")
    R = _read_matrix(path, data, "rectification_matrix", (3, 3)) if "rectification_matrix" in data else np.eye(3)
    P = _read_matrix(path, data, "projection_matrix", (3, 4)) if "projection_matrix" in data else None
    return CameraCalibration(w, h, K, D, str(data.get("camera_name", path.stem)), R, P, model)


def read_stereo_yaml(path: os.PathLike | str) -> StereoCalibration:
    """Read an LSU ``stereo.yaml``: R a rotation, T non-zero and pointing from the right camera to the left one."""
    path = Path(path)
    data = _load_yaml(path)
    w, h = _read_size(path, data) if ("image_width" in data or "image_height" in data) else (0, 0)
    R = _read_matrix(path, data, "rotation", (3, 3))
    T = _read_matrix(path, data, "translation", (3, 1)).reshape(3)
    check_extrinsics(R, T, str(path))
    E = _read_matrix(path, data, "essential", (3, 3)) if "essential" in data else None
    F = _read_matrix(path, data, "fundamental", (3, 3)) if "fundamental" in data else None
    try:
        rms = float(data.get("rms_px", 0.0) or 0.0)
    except (TypeError, ValueError):
        raise CalibrationParseError(f"{path}: 'rms_px' must be a number") from None
    return StereoCalibration(w, h, R, T, E, F, rms, str(data.get("date", "")),
                             str(data.get("left_frame_id", "lsu_left_optical")),
                             str(data.get("right_frame_id", "lsu_right_optical")))


@dataclass
class CalibrationSet:
    """left.yaml + right.yaml + stereo.yaml of one directory, checked for a common image size."""

    left: CameraCalibration
    right: CameraCalibration
    stereo: StereoCalibration
    calibration_id: str = ""   # first 16 hex digits of the SHA-256 of the three files
    source: str = ""

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height) shared by the three files."""
        return self.left.image_size


def _check_sides(path: Path, cam: CameraCalibration, expect_left: bool) -> None:
    """camera_calibration files say which camera they describe: refuse left.yaml/right.yaml exchanged."""
    this, other = ("left", "right") if expect_left else ("right", "left")
    name = cam.camera_name.lower()
    if other in name and this not in name:
        raise CalibrationSwappedError(f"{path}: camera_name '{cam.camera_name}' says this is the {other} "
                                      f"camera; left.yaml and right.yaml look swapped")
    # a right projection matrix carries -fx' * baseline in P[0,3], a left one 0
    assert cam.projection_matrix is not None  # __post_init__ sets it
    tx = float(cam.projection_matrix[0, 3])
    if expect_left and tx < -1e-9:
        raise CalibrationSwappedError(f"{path}: projection_matrix has P[0,3] = {tx:.3f} (a left camera has 0, a "
                                      f"right one -fx*baseline); left.yaml and right.yaml look swapped")
    if not expect_left and tx > 1e-9:
        raise CalibrationSwappedError(f"{path}: projection_matrix has P[0,3] = {tx:.3f} > 0, i.e. this camera "
                                      f"sits left of the other; left/right look swapped")


def read_calibration_dir(directory: os.PathLike | str) -> CalibrationSet:
    """Read and cross-check ``left.yaml``, ``right.yaml`` and ``stereo.yaml`` from ``directory``."""
    directory = Path(directory)
    if not directory.is_dir():
        raise CalibrationFileError(f"calibration folder {directory} not found; it must hold left.yaml, right.yaml "
                                   f"and stereo.yaml (run `lsu calibrate`)")
    paths = [directory / name for name in ("left.yaml", "right.yaml", "stereo.yaml")]
    left, right, stereo = read_camera_yaml(paths[0]), read_camera_yaml(paths[1]), read_stereo_yaml(paths[2])
    sizes = {"left.yaml": left.image_size, "right.yaml": right.image_size}
    if stereo.image_width:
        sizes["stereo.yaml"] = (stereo.image_width, stereo.image_height)
    if len(set(sizes.values())) != 1:
        raise CalibrationSizeError(f"{directory}: image sizes differ between files: "
                                   + ", ".join(f"{k} {w}x{h}" for k, (w, h) in sizes.items())
                                   + "; calibrate both cameras at the same resolution")
    stereo.image_width, stereo.image_height = left.image_size
    _check_sides(paths[0], left, True)
    _check_sides(paths[1], right, False)
    stereo.essential, F = check_epipolar(left.camera_matrix, right.camera_matrix, stereo.rotation,
                                         stereo.translation, stereo.essential, stereo.fundamental, str(paths[2]))
    if stereo.fundamental is None:
        stereo.fundamental = F
    return CalibrationSet(left, right, stereo, calibration_checksum(directory), str(directory))


def calibration_checksum(directory: os.PathLike | str) -> str:
    """The calibration's id: first 16 hex digits of the SHA-256 over left.yaml, right.yaml and
    stereo.yaml (those present); '' when none is."""
    digest = hashlib.sha256()
    found = False
    for name in ("left.yaml", "right.yaml", "stereo.yaml"):
        path = Path(directory) / name
        if path.is_file():
            digest.update(path.read_bytes())
            found = True
    return digest.hexdigest()[:16] if found else ""


# ---------------------------------------------------------------------- writing
def _atomic_write_all(files: Iterable[tuple[Path, str]]) -> None:
    """Write every file or none: all go to temporaries first, then are renamed into place (mode 0644)."""
    staged: list[tuple[Path, Path]] = []
    try:
        for path, text in files:
            path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
            with os.fdopen(fd, "w") as handle:
                handle.write(text)
            # mkstemp creates 0600; calibration files are read by other users' nodes and tools
            os.chmod(tmp, 0o644)
            staged.append((Path(tmp), path))
        for staged_tmp, target in staged:
            os.replace(staged_tmp, target)
    finally:
        for staged_tmp, _ in staged:
            if staged_tmp.exists():
                staged_tmp.unlink()


def write_calibration_dir(directory: os.PathLike | str, left: CameraCalibration, right: CameraCalibration,
                          stereo: StereoCalibration, header: str = "", rectified: bool = True) -> None:
    """Write left.yaml, right.yaml and stereo.yaml (all or nothing).

    ``rectified``: R and P of both cameras from `rectify` (the camera_calibration convention);
    otherwise as given.
    """
    directory = Path(directory)
    prefix = "".join(f"# {line}\n" for line in header.splitlines()) if header else ""
    if stereo.fundamental is None:
        stereo.fundamental = fundamental_from(left, right, stereo.rotation, stereo.translation)

    def dump(d: dict[str, Any]) -> str:
        return prefix + yaml.safe_dump(d, sort_keys=False, default_flow_style=None, width=200)

    left.camera_name = left.camera_name if left.camera_name != "camera" else "lsu_left"
    right.camera_name = right.camera_name if right.camera_name != "camera" else "lsu_right"
    if rectified:
        left, right = rectify(left, right, stereo)
    _atomic_write_all([(directory / "left.yaml", dump(camera_to_dict(left))),
                       (directory / "right.yaml", dump(camera_to_dict(right))),
                       (directory / "stereo.yaml", dump(stereo_to_dict(stereo)))])

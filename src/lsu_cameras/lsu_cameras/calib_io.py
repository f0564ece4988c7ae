"""Calibration files: ROS camera_calibration YAML (left/right) and the LSU ``stereo.yaml``.

Formats are those of CONTRIBUTING.md "Parameters and config". Readers validate everything they
return (shapes, finite numbers, positive size) and raise `CalibrationFileError` naming the file
and the field, so a node can refuse a broken file with one clear line.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Iterable, Optional, Tuple

import numpy as np
import yaml


class CalibrationFileError(ValueError):
    """A calibration YAML is missing, does not parse, or does not describe a valid camera/stereo pair."""


@dataclass
class CameraCalibration:
    """One camera in ROS camera_info terms (K, D plumb_bob, R, P) plus its image size."""

    image_width: int
    image_height: int
    camera_matrix: np.ndarray                      # K, 3x3
    distortion_coefficients: np.ndarray            # [k1, k2, p1, p2, k3]
    camera_name: str = "camera"
    rectification_matrix: np.ndarray = field(default_factory=lambda: np.eye(3))
    projection_matrix: Optional[np.ndarray] = None  # 3x4; [K | 0] when not rectified

    def __post_init__(self) -> None:
        self.camera_matrix = np.asarray(self.camera_matrix, dtype=np.float64).reshape(3, 3)
        self.distortion_coefficients = np.asarray(self.distortion_coefficients, dtype=np.float64).reshape(-1)
        self.rectification_matrix = np.asarray(self.rectification_matrix, dtype=np.float64).reshape(3, 3)
        if self.projection_matrix is None:
            self.projection_matrix = np.hstack([self.camera_matrix, np.zeros((3, 1))])
        self.projection_matrix = np.asarray(self.projection_matrix, dtype=np.float64).reshape(3, 4)

    @property
    def image_size(self) -> Tuple[int, int]:
        """(width, height) in pixels."""
        return (int(self.image_width), int(self.image_height))


@dataclass
class StereoCalibration:
    """Geometry of the right camera w.r.t. the left: X_right = R X_left + T (metres)."""

    image_width: int
    image_height: int
    rotation: np.ndarray          # 3x3
    translation: np.ndarray       # (3,) metres
    essential: Optional[np.ndarray] = None
    fundamental: Optional[np.ndarray] = None
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
            self.date = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")

    @property
    def baseline_m(self) -> float:
        """|T| in metres."""
        return float(np.linalg.norm(self.translation))


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix [v]x."""
    x, y, z = np.asarray(v, dtype=np.float64).reshape(3)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def fundamental_from(left: CameraCalibration, right: CameraCalibration, rotation: np.ndarray,
                     translation: np.ndarray) -> np.ndarray:
    """F for undistorted pixels, x_right^T F x_left = 0, scaled so that ||F|| = 1."""
    E = skew(translation) @ np.asarray(rotation).reshape(3, 3)
    F = np.linalg.inv(right.camera_matrix).T @ E @ np.linalg.inv(left.camera_matrix)
    return F / np.linalg.norm(F)


def _matrix(rows: int, cols: int, data: np.ndarray) -> Dict[str, Any]:
    return {"rows": rows, "cols": cols, "data": [float(x) for x in np.asarray(data, dtype=np.float64).reshape(-1)]}


def camera_to_dict(cal: CameraCalibration) -> Dict[str, Any]:
    """The ROS camera_calibration YAML mapping of one camera."""
    return {
        "image_width": int(cal.image_width),
        "image_height": int(cal.image_height),
        "camera_name": cal.camera_name,
        "camera_matrix": _matrix(3, 3, cal.camera_matrix),
        "distortion_model": "plumb_bob",
        "distortion_coefficients": _matrix(1, 5, cal.distortion_coefficients),
        "rectification_matrix": _matrix(3, 3, cal.rectification_matrix),
        "projection_matrix": _matrix(3, 4, cal.projection_matrix),
    }


def stereo_to_dict(cal: StereoCalibration) -> Dict[str, Any]:
    """The ``stereo.yaml`` mapping of CONTRIBUTING.md."""
    out: Dict[str, Any] = {
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


def _load_yaml(path: Path) -> Dict[str, Any]:
    path = Path(path)
    if not path.is_file():
        raise CalibrationFileError(f"{path}: calibration file not found (run `lsu calibrate` or give the right path)")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise CalibrationFileError(f"{path}: not valid YAML{where}: {getattr(exc, 'problem', exc)}") from None
    if not isinstance(data, dict):
        raise CalibrationFileError(f"{path}: expected a YAML mapping of calibration fields, got {type(data).__name__}")
    return data


def _read_matrix(path: Path, data: Dict[str, Any], key: str, shape: Tuple[int, int]) -> np.ndarray:
    if key not in data:
        raise CalibrationFileError(f"{path}: missing field '{key}'")
    value = data[key]
    raw = value.get("data") if isinstance(value, dict) else value
    try:
        arr = np.asarray(raw, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise CalibrationFileError(f"{path}: field '{key}' must be a list of numbers") from None
    if arr.size != shape[0] * shape[1]:
        raise CalibrationFileError(f"{path}: field '{key}' has {arr.size} numbers, expected {shape[0] * shape[1]} "
                                   f"({shape[0]}x{shape[1]})")
    if not np.all(np.isfinite(arr)):
        raise CalibrationFileError(f"{path}: field '{key}' contains NaN or infinite values")
    return arr.reshape(shape)


def _read_size(path: Path, data: Dict[str, Any]) -> Tuple[int, int]:
    try:
        w, h = int(data["image_width"]), int(data["image_height"])
    except KeyError as exc:
        raise CalibrationFileError(f"{path}: missing field '{exc.args[0]}'") from None
    except (TypeError, ValueError):
        raise CalibrationFileError(f"{path}: image_width/image_height must be integers") from None
    if w <= 0 or h <= 0:
        raise CalibrationFileError(f"{path}: image size {w}x{h} is not positive")
    return w, h


def read_camera_yaml(path: os.PathLike | str) -> CameraCalibration:
    """Read a ROS camera_calibration YAML (plumb_bob, 5 coefficients)."""
    path = Path(path)
    data = _load_yaml(path)
    w, h = _read_size(path, data)
    model = data.get("distortion_model", "plumb_bob")
    if model != "plumb_bob":
        raise CalibrationFileError(f"{path}: distortion_model '{model}' is not supported (only plumb_bob)")
    K = _read_matrix(path, data, "camera_matrix", (3, 3))
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CalibrationFileError(f"{path}: camera_matrix has non-positive focal lengths {K[0, 0]}, {K[1, 1]}")
    D = _read_matrix(path, data, "distortion_coefficients", (1, 5)).reshape(5)
    R = _read_matrix(path, data, "rectification_matrix", (3, 3)) if "rectification_matrix" in data else np.eye(3)
    P = _read_matrix(path, data, "projection_matrix", (3, 4)) if "projection_matrix" in data else None
    return CameraCalibration(w, h, K, D, str(data.get("camera_name", path.stem)), R, P)


def read_stereo_yaml(path: os.PathLike | str) -> StereoCalibration:
    """Read an LSU ``stereo.yaml``; R must be a rotation and T non-zero."""
    path = Path(path)
    data = _load_yaml(path)
    w, h = _read_size(path, data)
    R = _read_matrix(path, data, "rotation", (3, 3))
    if abs(np.linalg.det(R) - 1.0) > 1e-3 or not np.allclose(R @ R.T, np.eye(3), atol=1e-3):
        raise CalibrationFileError(f"{path}: 'rotation' is not a rotation matrix (det {np.linalg.det(R):.4f})")
    T = _read_matrix(path, data, "translation", (3, 1)).reshape(3)
    if np.linalg.norm(T) <= 0:
        raise CalibrationFileError(f"{path}: 'translation' is zero: the cameras cannot share one centre")
    E = _read_matrix(path, data, "essential", (3, 3)) if "essential" in data else None
    F = _read_matrix(path, data, "fundamental", (3, 3)) if "fundamental" in data else None
    try:
        rms = float(data.get("rms_px", 0.0))
    except (TypeError, ValueError):
        raise CalibrationFileError(f"{path}: 'rms_px' must be a number") from None
    return StereoCalibration(w, h, R, T, E, F, rms, str(data.get("date", "")),
                             str(data.get("left_frame_id", "lsu_left_optical")),
                             str(data.get("right_frame_id", "lsu_right_optical")))


@dataclass
class CalibrationSet:
    """left.yaml + right.yaml + stereo.yaml of one directory, checked for a common image size."""

    left: CameraCalibration
    right: CameraCalibration
    stereo: StereoCalibration
    calibration_id: str = ""

    @property
    def image_size(self) -> Tuple[int, int]:
        """(width, height) shared by the three files."""
        return self.left.image_size


def read_calibration_dir(directory: os.PathLike | str) -> CalibrationSet:
    """Read ``left.yaml``, ``right.yaml`` and ``stereo.yaml`` from ``directory``."""
    directory = Path(directory)
    if not directory.is_dir():
        raise CalibrationFileError(f"{directory}: calibration directory not found")
    paths = [directory / name for name in ("left.yaml", "right.yaml", "stereo.yaml")]
    left, right, stereo = read_camera_yaml(paths[0]), read_camera_yaml(paths[1]), read_stereo_yaml(paths[2])
    sizes = {p.name: s for p, s in zip(paths, (left.image_size, right.image_size,
                                                   (stereo.image_width, stereo.image_height)))}
    if len(set(sizes.values())) != 1:
        raise CalibrationFileError(f"{directory}: image sizes differ between files: "
                                   + ", ".join(f"{k} {w}x{h}" for k, (w, h) in sizes.items()))
    if stereo.fundamental is None:
        stereo.fundamental = fundamental_from(left, right, stereo.rotation, stereo.translation)
    digest = hashlib.sha256(b"".join(p.read_bytes() for p in paths)).hexdigest()[:16]
    return CalibrationSet(left, right, stereo, digest)


def _atomic_write_all(files: Iterable[Tuple[Path, str]]) -> None:
    """Write every file or none: all go to temporaries first, then are renamed into place."""
    staged = []
    try:
        for path, text in files:
            path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
            with os.fdopen(fd, "w") as handle:
                handle.write(text)
            staged.append((Path(tmp), path))
        for tmp, path in staged:
            os.replace(tmp, path)
    finally:
        for tmp, _ in staged:
            if tmp.exists():
                tmp.unlink()


def write_calibration_dir(directory: os.PathLike | str, left: CameraCalibration, right: CameraCalibration,
                          stereo: StereoCalibration, header: str = "") -> None:
    """Write left.yaml, right.yaml and stereo.yaml (all or nothing)."""
    directory = Path(directory)
    prefix = "".join(f"# {line}\n" for line in header.splitlines()) if header else ""
    if stereo.fundamental is None:
        stereo.fundamental = fundamental_from(left, right, stereo.rotation, stereo.translation)

    def dump(d: Dict[str, Any]) -> str:
        return prefix + yaml.safe_dump(d, sort_keys=False, default_flow_style=None, width=200)

    left.camera_name = left.camera_name if left.camera_name != "camera" else "lsu_left"
    right.camera_name = right.camera_name if right.camera_name != "camera" else "lsu_right"
    _atomic_write_all([(directory / "left.yaml", dump(camera_to_dict(left))),
                       (directory / "right.yaml", dump(camera_to_dict(right))),
                       (directory / "stereo.yaml", dump(stereo_to_dict(stereo)))])

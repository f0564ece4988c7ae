"""Camera property profiles (thesis Table 1 "dark"/"normal") mapped to V4L2 controls via OpenCV.

A profile is ``config/profiles/<name>.yaml`` with a ``controls`` mapping of control name -> value.
`apply_profile` sets each control on an OpenCV capture, reads it back and returns the mismatches
(drivers silently clamp or ignore values: the user must see that).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import cv2
import yaml

from .paths import config_dir


class ProfileError(ValueError):
    """A profile is missing, does not parse, or names an unknown control."""


V4L2_CONTROLS: dict[str, int] = {
    "brightness": cv2.CAP_PROP_BRIGHTNESS,
    "contrast": cv2.CAP_PROP_CONTRAST,
    "saturation": cv2.CAP_PROP_SATURATION,
    "hue": cv2.CAP_PROP_HUE,
    "sharpness": cv2.CAP_PROP_SHARPNESS,
    "gamma": cv2.CAP_PROP_GAMMA,
    "gain": cv2.CAP_PROP_GAIN,
    "exposure": cv2.CAP_PROP_EXPOSURE,
    "auto_exposure": cv2.CAP_PROP_AUTO_EXPOSURE,
    "auto_white_balance": cv2.CAP_PROP_AUTO_WB,
    "white_balance_temperature": cv2.CAP_PROP_WB_TEMPERATURE,
    "white_balance_blue_u": cv2.CAP_PROP_WHITE_BALANCE_BLUE_U,
    "white_balance_red_v": cv2.CAP_PROP_WHITE_BALANCE_RED_V,
    "backlight": cv2.CAP_PROP_BACKLIGHT,
    "fps": cv2.CAP_PROP_FPS,
}


class Capture(Protocol):
    """What `apply_profile` needs from a capture (cv2.VideoCapture or a test double)."""

    def set(self, prop: int, value: float) -> bool: ...

    def get(self, prop: int) -> float: ...


@dataclass
class Profile:
    """A named set of control values."""

    name: str
    controls: dict[str, float]


def load_profile(name_or_path: str) -> Profile:
    """``dark``/``normal`` (from config/profiles) or a path to a profile YAML; unknown controls rejected."""
    path = Path(name_or_path)
    if not path.suffix:
        path = config_dir() / "profiles" / f"{name_or_path}.yaml"
    if not path.is_file():
        known = sorted(p.stem for p in (config_dir() / "profiles").glob("*.yaml"))
        raise ProfileError(f"camera profile '{name_or_path}' not found ({path}); known profiles: {', '.join(known)}")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ProfileError(f"{path}: not valid YAML: {exc}") from None
    if not isinstance(data, dict) or not isinstance(data.get("controls"), dict):
        raise ProfileError(f"{path}: expected a mapping with a 'controls' mapping of V4L2 control -> value")
    controls: dict[str, float] = {}
    for key, value in data["controls"].items():
        if key not in V4L2_CONTROLS:
            raise ProfileError(f"{path}: unknown control '{key}'; known controls: {', '.join(sorted(V4L2_CONTROLS))}")
        try:
            controls[key] = float(value)
        except (TypeError, ValueError):
            raise ProfileError(f"{path}: control '{key}' must be a number, got {value!r}") from None
    return Profile(str(data.get("name", path.stem)), controls)


def apply_profile(capture: Capture, profile: Profile, tolerance: float = 0.5) -> list[str]:
    """Set every control, read it back; returns one message per control that did not take."""
    problems: list[str] = []
    for key, value in profile.controls.items():
        prop = V4L2_CONTROLS[key]
        accepted = capture.set(prop, value)
        actual = capture.get(prop)
        if not accepted:
            problems.append(f"{key}: the driver refused {value:g} (reads {actual:g})")
        elif abs(actual - value) > tolerance:
            problems.append(f"{key}: set {value:g}, reads back {actual:g}")
    return problems


def profile_path(name: str) -> os.PathLike:
    """Path of a named profile in config/profiles."""
    return config_dir() / "profiles" / f"{name}.yaml"


def describe(profile: Profile) -> dict[str, Any]:
    """Profile as a plain mapping (for logs/diagnostics)."""
    return {"name": profile.name, **profile.controls}

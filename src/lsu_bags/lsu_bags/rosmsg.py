"""ROS interface types by name, and messages to/from plain data and YAML.

PyPI has no rosidl_runtime_py, so `lsu topic/service/param` use this small equivalent.
Works on any generated message class (fields from ``get_fields_and_field_types()``).
"""

from __future__ import annotations

import array
import importlib
import re
from collections.abc import Mapping
from typing import Any

import yaml

#: arrays longer than this are shortened when printed (like `ros2 topic echo` does)
DEFAULT_ARRAY_LIMIT = 16


class InterfaceError(ValueError):
    """An interface type name that cannot be resolved, or data that does not fit a message."""


def get_interface(type_name: str, kind: str | None = None) -> type[Any]:
    """Class of ``pkg/msg/Name`` (or ``pkg/Name`` with ``kind`` = msg/srv/action).

    Raises:
        InterfaceError: the name is malformed or the package/type is not installed.
    """
    parts = type_name.strip("/").split("/")
    if len(parts) == 2 and kind:
        parts = [parts[0], kind, parts[1]]
    if len(parts) != 3 or not all(parts):
        raise InterfaceError(f"'{type_name}' is not an interface type; write it like std_msgs/msg/String")
    package, sub, name = parts
    try:
        module = importlib.import_module(f"{package}.{sub}")
    except ImportError:
        hint = " (run `make setup` to build lsu_interfaces)" if package == "lsu_interfaces" else ""
        raise InterfaceError(f"interface package '{package}.{sub}' is not installed{hint}") from None
    try:
        return getattr(module, name)
    except AttributeError:
        raise InterfaceError(f"'{package}/{sub}' has no type '{name}'") from None


def type_name_of(cls: type) -> str:
    """``std_msgs/msg/String`` for a generated class."""
    module = cls.__module__.split(".")
    return f"{module[0]}/{module[1]}/{cls.__name__}"


def _is_message(value: Any) -> bool:
    return hasattr(value, "get_fields_and_field_types")


def to_data(msg: Any, array_limit: int | None = None) -> Any:
    """A message as nested dicts/lists of plain Python values (YAML-ready).

    Arrays longer than ``array_limit`` keep their first items and end with a note
    ``'... N more'`` (``None``: no limit).
    """
    import numpy as np  # here, not at the top: `lsu`'s launcher and short commands import this module, not numpy

    if _is_message(msg):
        return {name: to_data(getattr(msg, name), array_limit) for name in msg.get_fields_and_field_types()}
    if isinstance(msg, (list, tuple, array.array, np.ndarray)):
        items = msg.tolist() if isinstance(msg, (array.array, np.ndarray)) else list(msg)
        if array_limit is not None and len(items) > array_limit:
            shown = [to_data(v, array_limit) for v in items[:array_limit]]
            return shown + [f"... {len(items) - array_limit} more"]
        return [to_data(v, array_limit) for v in items]
    if isinstance(msg, bytes):
        return list(msg)
    if isinstance(msg, np.generic):
        return msg.item()
    return msg


def to_yaml(msg: Any, array_limit: int | None = DEFAULT_ARRAY_LIMIT) -> str:
    """A message as YAML text, the way `ros2 topic echo` prints it."""
    return yaml.safe_dump(to_data(msg, array_limit), sort_keys=False, default_flow_style=False, width=100)


def fill(msg: Any, data: Mapping[str, Any] | None) -> Any:
    """Set the fields of ``msg`` from nested dicts/lists; returns ``msg``.

    Raises:
        InterfaceError: unknown field or a value of the wrong kind, naming the field path.
    """
    if data is None:
        return msg
    if not isinstance(data, Mapping):
        raise InterfaceError(f"{type(msg).__name__} needs a mapping like '{{field: value}}', got {data!r}")
    fields: dict[str, str] = msg.get_fields_and_field_types()
    for key, value in data.items():
        if key not in fields:
            raise InterfaceError(f"{type(msg).__name__} has no field '{key}' (fields: {', '.join(fields)})")
        current = getattr(msg, key)
        try:
            if _is_message(current):
                fill(current, value)
            elif fields[key].startswith("sequence<") and "/" in fields[key]:
                item_cls = get_interface(fields[key][len("sequence<"):-1].split(",")[0], "msg")
                setattr(msg, key, [fill(item_cls(), item) for item in value])
            else:
                setattr(msg, key, _checked(fields[key], value))
        except InterfaceError as exc:
            raise InterfaceError(f"field '{key}' ({fields[key]}): {exc}") from None
        except (TypeError, ValueError, AssertionError) as exc:
            raise InterfaceError(f"field '{key}' ({fields[key]}) cannot take {value!r}: {exc}") from None
    return msg


_INT_RANGES = {f"{sign}int{bits}": ((0, 2**bits - 1) if sign else (-(2 ** (bits - 1)), 2 ** (bits - 1) - 1))
               for sign in ("", "u") for bits in (8, 16, 32, 64)}
_INT_RANGES.update({"octet": (0, 255), "char": (0, 255)})


def _checked(type_str: str, value: Any) -> Any:
    """Check ``value`` against a field type; rclpy checks nothing unless ROS_PYTHON_CHECK_FIELDS is set."""
    base = re.sub(r"\[\d*\]$|^sequence<(.*?)(, ?\d+)?>$", lambda m: m.group(1) or "", type_str)
    if base != type_str:  # an array or a sequence of a basic type
        if not isinstance(value, (list, tuple)):
            raise InterfaceError(f"needs a list for {type_str}, got {value!r}")
        return [_checked(base, v) for v in value]
    if type_str == "boolean":
        if not isinstance(value, bool):
            raise InterfaceError(f"needs true or false, got {value!r}")
    elif type_str in _INT_RANGES:
        low, high = _INT_RANGES[type_str]
        if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
            raise InterfaceError(f"needs an integer in {low}..{high} ({type_str}), got {value!r}")
    elif type_str in ("float", "double"):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InterfaceError(f"needs a number ({type_str}), got {value!r}")
        value = float(value)
    elif type_str.startswith(("string", "wstring")):
        if not isinstance(value, str):
            value = str(value)  # `{name: 42}` from YAML means the text "42"
    return value


def parse_yaml_mapping(text: str) -> dict[str, Any]:
    """Parse the YAML argument of `lsu topic pub` / `lsu service call` (``""`` = defaults)."""
    if not text.strip():
        return {}
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise InterfaceError(f"not valid YAML: {text!r} ({exc.__class__.__name__})") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise InterfaceError(f"expected a YAML mapping like \"{{field: value}}\", got {text!r}")
    return data

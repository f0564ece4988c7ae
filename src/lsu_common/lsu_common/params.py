"""Table-driven node parameters: one declaration, a range `param describe` shows, and one apply path.

A node lists its parameters in a table ``name -> Param(default, description, range, read_only)``
(a plain ``(default, description, range)`` tuple is accepted too) and calls `declare_parameters`:

- every parameter is declared with a `ParameterDescriptor` holding its description, its range
  (`IntegerRange` for an integer default, `FloatingPointRange` for a float one) and ``read_only``;
  rclpy refuses a value out of range or a set of a read-only parameter, with a reason;
- ``check(changed)`` runs in the on-set callback: it returns ``None`` to accept or a sentence that
  says why the values are refused (it must not change the node: the set may still be refused);
- ``apply(changed)`` runs in the post-set callback, after the values are stored: it makes them take
  effect (recreate a timer, reconfigure a device). It also runs once at declaration with every
  parameter, so the start-up values and later sets go through the same code.

Start-up-only parameters (ports, frames, paths opened once) are ``read_only=True``: a set is refused
instead of silently doing nothing.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult


class Param(NamedTuple):
    """One row of a parameter table."""

    default: Any
    description: str
    range: tuple[float, float] | None = None  # inclusive (low, high); None for strings, bools, arrays
    read_only: bool = False                      # start-up only: a later set is refused


ParamRow = Param | tuple[Any, ...]
Check = Callable[[list[Any]], "str | None | SetParametersResult"]
Apply = Callable[[list[Any]], None]


def as_param(row: ParamRow) -> Param:
    """A table row as a `Param` (plain tuples are ``(default, description[, range[, read_only]])``)."""
    return row if isinstance(row, Param) else Param(*row)


def descriptor(row: ParamRow) -> ParameterDescriptor:
    """The `ParameterDescriptor` of a table row: description, read_only and the range of its type."""
    spec = as_param(row)
    d = ParameterDescriptor(description=spec.description, read_only=bool(spec.read_only))
    if spec.range is not None:
        low, high = spec.range
        if isinstance(spec.default, bool) or not isinstance(spec.default, (int, float)):
            raise TypeError(f"a range needs a numeric default, got {spec.default!r}")
        if isinstance(spec.default, int):
            d.integer_range = [IntegerRange(from_value=int(low), to_value=int(high), step=1)]
        else:
            d.floating_point_range = [FloatingPointRange(from_value=float(low), to_value=float(high))]
    return d


def declare_parameters(node: Any, table: Mapping[str, ParamRow], *, check: Check | None = None,
                       apply: Apply | None = None, apply_now: bool = True) -> dict[str, Any]:
    """Declare every parameter of ``table`` on ``node``; returns their start-up values by name.

    Args:
        node: the rclpy node.
        table: ``name -> Param`` (or plain tuple).
        check: on-set validation of the changed parameters: None or a successful result accepts,
            a string (or an unsuccessful result) refuses the whole set with that reason.
        apply: post-set callback given the changed parameters (rclpy ``Parameter`` objects).
        apply_now: call ``apply`` once with every declared parameter before returning.
    """
    names: Sequence[str] = list(table)
    for name in names:
        node.declare_parameter(name, as_param(table[name]).default, descriptor(table[name]))
    if check is not None:
        node.add_on_set_parameters_callback(lambda changed: _result(check(changed)))
    if apply is not None:
        node.add_post_set_parameters_callback(apply)
    current = [node.get_parameter(name) for name in names]
    if apply is not None and apply_now:
        apply(current)
    return {p.name: p.value for p in current}


def _result(outcome: str | None | SetParametersResult) -> SetParametersResult:
    if isinstance(outcome, SetParametersResult):
        return outcome
    if outcome:
        return SetParametersResult(successful=False, reason=str(outcome))
    return SetParametersResult(successful=True)


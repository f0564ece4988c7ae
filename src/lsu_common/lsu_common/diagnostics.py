"""One ``/diagnostics`` message: a node's single status, its values as strings, stamped now."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

OK = DiagnosticStatus.OK
WARN = DiagnosticStatus.WARN
ERROR = DiagnosticStatus.ERROR


def status_array(node: Any, level: bytes, name: str, message: str, values: Mapping[str, Any],
                 hardware_id: str = "") -> DiagnosticArray:
    """A `DiagnosticArray` stamped with ``node``'s clock holding one status (values through ``str``)."""
    status = DiagnosticStatus(level=level, name=name, message=message, hardware_id=hardware_id,
                              values=[KeyValue(key=str(k), value=str(v)) for k, v in values.items()])
    array = DiagnosticArray(status=[status])
    array.header.stamp = node.get_clock().now().to_msg()
    return array

"""A numpy codec for the sensor_msgs/PointCloud2 wire layout, with no ROS types (sensor_msgs_py is not on PyPI).

:class:`Cloud` mirrors the message's layout fields (fields, data, width, height, point_step,
row_step, is_bigendian, is_dense); the node converts it to and from the real message. Reading
works for any cloud (only the named fields, any byte order, padding inside a point and at the
end of a row); writing uses the LSU layout of ARCHITECTURE.md unless told otherwise:

    x y z   float32  metres, lsu_left_optical
    rgb     float32  bits 0x00RRGGBB (the PCL / RViz "rgb" convention)
    u v     float32  left raw pixel of the point
    snap    uint32   snap index within the scan
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from lsu_common.arrays import AnyArray

__all__ = ["PointField", "Cloud", "CloudError", "LSU_FIELDS", "layout", "encode", "decode", "from_msg", "pack_rgb",
           "unpack_rgb", "INT8", "UINT8", "INT16", "UINT16", "INT32", "UINT32", "FLOAT32", "FLOAT64"]

# sensor_msgs/PointField datatype constants
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)
_NUMPY = {INT8: "i1", UINT8: "u1", INT16: "i2", UINT16: "u2", INT32: "i4", UINT32: "u4", FLOAT32: "f4",
          FLOAT64: "f8"}
_CODE = {np.dtype(v).str[1:]: k for k, v in _NUMPY.items()}


class CloudError(ValueError):
    """A PointCloud2 layout or buffer is inconsistent (the message says which field/size)."""


@dataclass(frozen=True)
class PointField:
    """One field of a point: like sensor_msgs/PointField."""

    name: str
    offset: int
    datatype: int
    count: int = 1


@dataclass
class Cloud:
    """The layout and bytes of a PointCloud2, without the header."""

    fields: list[PointField]
    data: bytes
    width: int
    height: int = 1
    point_step: int = 0
    row_step: int = 0
    is_bigendian: bool = False
    is_dense: bool = True

    @property
    def n_points(self) -> int:
        """width x height."""
        return int(self.width) * int(self.height)


def layout(names_types: Sequence[tuple], point_step: int | None = None) -> tuple:
    """Packed fields for ``[(name, datatype), ...]``; returns ``(fields, point_step)``."""
    fields: list[PointField] = []
    offset = 0
    for name, datatype in names_types:
        fields.append(PointField(name, offset, datatype, 1))
        offset += np.dtype(_NUMPY[datatype]).itemsize
    step = offset if point_step is None else int(point_step)
    if step < offset:
        raise CloudError(f"point_step {step} is smaller than the {offset} bytes of the fields")
    return fields, step


LSU_FIELDS, LSU_POINT_STEP = layout([("x", FLOAT32), ("y", FLOAT32), ("z", FLOAT32), ("rgb", FLOAT32),
                                     ("u", FLOAT32), ("v", FLOAT32), ("snap", UINT32)])


def _dtype(fields: Iterable[PointField], point_step: int, bigendian: bool,
           names: Sequence[str] | None = None) -> np.dtype:
    order = ">" if bigendian else "<"
    spec: dict[str, list] = {"names": [], "formats": [], "offsets": []}
    for f in fields:
        if names is not None and f.name not in names:
            continue
        if f.datatype not in _NUMPY:
            raise CloudError(f"field '{f.name}' has unknown datatype {f.datatype} (PointField uses 1..8)")
        if f.name in spec["names"]:
            raise CloudError(f"field '{f.name}' appears twice in the cloud layout")
        base = order + _NUMPY[f.datatype]
        size = np.dtype(base).itemsize * max(1, f.count)
        if f.offset < 0 or f.offset + size > point_step:
            raise CloudError(f"field '{f.name}' (offset {f.offset}, {size} bytes) does not fit point_step {point_step}")
        spec["names"].append(f.name)
        spec["formats"].append(base if f.count <= 1 else (base, (f.count,)))
        spec["offsets"].append(f.offset)
    return np.dtype({**spec, "itemsize": point_step})


def pack_rgb(rgb: AnyArray) -> AnyArray:
    """(N, 3) uint8 R, G, B -> (N,) float32 whose bits are 0x00RRGGBB (PCL / RViz 'rgb')."""
    rgb = np.asarray(rgb, dtype=np.uint32).reshape(-1, 3)
    bits = (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]
    return bits.astype("<u4").view("<f4").astype(np.float32)


def unpack_rgb(rgb: AnyArray) -> AnyArray:
    """(N,) packed float32 'rgb' -> (N, 3) uint8 R, G, B."""
    bits = np.ascontiguousarray(rgb, dtype=np.float32).view(np.uint32)
    return np.stack([(bits >> 16) & 0xFF, (bits >> 8) & 0xFF, bits & 0xFF], axis=1).astype(np.uint8)


def encode(columns: Mapping[str, AnyArray], fields: list[PointField] | None = None,
           point_step: int | None = None, is_bigendian: bool = False, height: int = 1) -> Cloud:
    """Pack named columns (each of length N, or (N, count)) into a :class:`Cloud`.

    Without ``fields`` the LSU layout is used. Bytes between and after fields (padding) are zero.
    NaN or infinite coordinates are refused: an LSU cloud is always dense.
    """
    if fields is None:
        fields, step = LSU_FIELDS, LSU_POINT_STEP
    else:
        step = max(f.offset + np.dtype(_NUMPY[f.datatype]).itemsize * max(1, f.count) for f in fields) if fields else 0
    if point_step is not None:
        step = int(point_step)
    dtype = _dtype(fields, step, is_bigendian)
    lengths = {name: len(np.asarray(columns[name])) for name in dtype.names if name in columns}
    missing = [name for name in dtype.names if name not in columns]
    if missing:
        raise CloudError(f"no data for field(s) {', '.join(missing)} of the cloud layout")
    n = next(iter(lengths.values()), 0)
    if any(v != n for v in lengths.values()):
        raise CloudError(f"columns have different lengths: {lengths}")
    if height < 1 or n % height:
        raise CloudError(f"{n} points cannot form {height} rows")
    for name in ("x", "y", "z"):
        if name in columns and not np.all(np.isfinite(np.asarray(columns[name], dtype=np.float64))):
            raise CloudError(f"field '{name}' contains NaN or infinity; reject such points before publishing")
    arr = np.zeros(n, dtype=dtype)
    for name in dtype.names:
        arr[name] = np.asarray(columns[name]).astype(dtype.fields[name][0].base, copy=False).reshape(arr[name].shape)
    width = n // height
    return Cloud(fields=list(fields), data=arr.tobytes(), width=width, height=height, point_step=step,
                 row_step=step * width, is_bigendian=is_bigendian, is_dense=True)


def from_msg(msg: Any) -> Cloud:
    """The layout and bytes of a sensor_msgs/PointCloud2 (rclpy or rosbags message; header dropped)."""
    return Cloud(fields=[PointField(f.name, f.offset, f.datatype, f.count) for f in msg.fields],
                 data=bytes(msg.data), width=msg.width, height=msg.height, point_step=msg.point_step,
                 row_step=msg.row_step, is_bigendian=msg.is_bigendian, is_dense=msg.is_dense)


def decode(cloud: Cloud, names: Sequence[str] | None = None) -> dict[str, AnyArray]:
    """Unpack a :class:`Cloud` into native-endian columns (N,) or (N, count); ``names`` limits the fields.

    Unknown fields are simply skipped when ``names`` is given, row padding (``row_step`` larger
    than ``width * point_step``) is dropped.
    """
    if names is not None:
        have = {f.name for f in cloud.fields}
        absent = [n for n in names if n not in have]
        if absent:
            raise CloudError(f"cloud has no field(s) {', '.join(absent)}; it has {', '.join(sorted(have)) or 'none'}")
    dtype = _dtype(cloud.fields, cloud.point_step, cloud.is_bigendian, names)
    n_row = cloud.width * cloud.point_step
    row_step = cloud.row_step or n_row
    if row_step < n_row:
        raise CloudError(f"row_step {row_step} is smaller than width x point_step = {n_row}")
    need = row_step * (cloud.height - 1) + n_row if cloud.height else 0
    buf = np.frombuffer(bytes(cloud.data), dtype=np.uint8)
    if buf.size < need:
        raise CloudError(f"cloud data has {buf.size} bytes, its layout needs {need} "
                         f"({cloud.height} rows of {cloud.width} points x {cloud.point_step} bytes)")
    if cloud.height == 0 or cloud.width == 0:
        return {name: np.zeros((0,) + dtype.fields[name][0].shape, dtype=dtype.fields[name][0].base.newbyteorder("="))
                for name in dtype.names}
    if row_step == n_row:
        points = buf[:need].view(dtype)
    else:
        rows = np.lib.stride_tricks.as_strided(buf, shape=(cloud.height, n_row), strides=(row_step, 1))
        points = np.ascontiguousarray(rows).reshape(-1).view(dtype)
    out = {}
    for name in dtype.names:
        col = points[name]
        out[name] = col.astype(col.dtype.newbyteorder("="))
    return out

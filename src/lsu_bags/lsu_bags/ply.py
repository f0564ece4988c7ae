"""Read PLY clouds and meshes with every vertex property, write LSU clouds (numpy).

open3d's readers keep only x y z, normals and colours, but an LSU cloud (``lsu reconstruct``,
``cloud.ply`` of a scan) carries the left-image pixel ``u v`` and the ``snap`` index that meshing
needs, so this small reader parses the header and maps the vertex element straight into a numpy
structured array. It reads ascii and binary (little and big endian) files, scalar vertex
properties of any type, and an optional ``face`` element of vertex index lists. The writer is
hand-written for the same reason: open3d's writer would drop ``u v`` and ``snap``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lsu_common.arrays import AnyArray

__all__ = ["PlyError", "read_ply", "write_ply", "write_cloud_ply"]

_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
          "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
          "double": "f8", "float64": "f8"}


UNITS = ("auto", "m", "mm")   # length units of cloud files (lsu_faces.pipeline.to_metres)


class PlyError(ValueError):
    """The file is not a PLY this reader understands; the message names the file and the problem."""


def read_ply(path: str | Path) -> tuple[dict[str, AnyArray], AnyArray | None]:
    """(vertex columns by property name, faces (M, 3) int64 or None) of a PLY file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"PLY file {path} not found")
    raw = path.read_bytes()
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise PlyError(f"{path} is not a PLY file (no 'ply' ... 'end_header' header)")
    body_start = raw.index(b"\n", end) + 1
    header = raw[:end].decode("ascii", errors="replace").splitlines()
    fmt = ""
    elements: list[dict[str, Any]] = []
    for line in header:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            elements.append({"name": parts[1], "count": int(parts[2]), "props": []})
        elif parts[0] == "property" and elements:
            if parts[1] == "list":
                elements[-1]["props"].append((parts[4], "list", _TYPES.get(parts[2]), _TYPES.get(parts[3])))
            else:
                if parts[1] not in _TYPES:
                    raise PlyError(f"{path}: unknown property type '{parts[1]}'")
                elements[-1]["props"].append((parts[2], _TYPES[parts[1]]))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise PlyError(f"{path}: unsupported PLY format '{fmt}'")
    order = "<" if fmt != "binary_big_endian" else ">"
    vertices: dict[str, AnyArray] = {}
    faces: AnyArray | None = None
    if fmt == "ascii":
        tokens = raw[body_start:].split()
        pos = 0
        for el in elements:
            if any(p[1] == "list" for p in el["props"]):
                rows = []
                for _ in range(el["count"]):
                    n = int(tokens[pos])
                    rows.append([int(t) for t in tokens[pos + 1:pos + 1 + n]])
                    pos += 1 + n
                if el["name"] == "face":
                    faces = _triangles(rows, path)
            else:
                k = len(el["props"])
                block = np.array(tokens[pos:pos + k * el["count"]], dtype=np.float64).reshape(el["count"], k)
                pos += k * el["count"]
                if el["name"] == "vertex":
                    vertices = {p[0]: block[:, i].astype(p[1]) for i, p in enumerate(el["props"])}
        return _checked(vertices, faces, path)
    offset = body_start
    for el in elements:
        if any(p[1] == "list" for p in el["props"]):
            if len(el["props"]) != 1:
                raise PlyError(f"{path}: element '{el['name']}' mixes lists and scalars; not supported")
            _, _, ctype, itype = el["props"][0]
            if ctype is None or itype is None:
                raise PlyError(f"{path}: bad list property types in element '{el['name']}'")
            # LSU and open3d meshes are triangles: read the fixed layout, then check every count is 3
            dt = np.dtype([("n", order + ctype), ("i", order + itype, (3,))])
            need = dt.itemsize * el["count"]
            if offset + need > len(raw):
                raise PlyError(f"{path}: file ends inside the '{el['name']}' element")
            arr = np.frombuffer(raw, dtype=dt, count=el["count"], offset=offset)
            if el["count"] and not np.all(arr["n"] == 3):
                raise PlyError(f"{path}: only triangle faces are supported")
            offset += need
            if el["name"] == "face":
                faces = arr["i"].astype(np.int64)
        else:
            dt = np.dtype([(p[0], order + p[1]) for p in el["props"]])
            need = dt.itemsize * el["count"]
            if offset + need > len(raw):
                raise PlyError(f"{path}: file ends inside the '{el['name']}' element ({el['count']} expected)")
            arr = np.frombuffer(raw, dtype=dt, count=el["count"], offset=offset)
            offset += need
            if el["name"] == "vertex":
                vertices = {name: arr[name].astype(arr[name].dtype.newbyteorder("=")) for name in dt.names or ()}
    return _checked(vertices, faces, path)


def _triangles(rows: list, path: Path) -> AnyArray:
    if any(len(r) != 3 for r in rows):
        raise PlyError(f"{path}: only triangle faces are supported")
    return np.asarray(rows, dtype=np.int64).reshape(-1, 3)


def _checked(vertices: dict[str, AnyArray], faces: AnyArray | None, path: Path):
    if not all(k in vertices for k in ("x", "y", "z")):
        raise PlyError(f"{path}: the vertex element has no x, y, z properties")
    n = len(vertices["x"])
    if faces is not None and len(faces) and (faces.min() < 0 or faces.max() >= n):
        raise PlyError(f"{path}: face indices outside the {n} vertices")
    return vertices, faces


# numpy dtype code -> PLY property type (the names the PLY spec and open3d use)
_PLY_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint", "f4": "float",
              "f8": "double"}


def write_ply(path: str | Path, vertices: Mapping[str, AnyArray], comments: Sequence[str] = ()) -> Path:
    """Binary little-endian PLY of one vertex element: a property per column, in the mapping's order.

    Each column's numpy dtype gives its PLY type (int8..uint32, float32, float64); returns ``path``.
    """
    path = Path(path)
    columns = {name: np.asarray(col) for name, col in vertices.items()}
    lengths = {len(c) for c in columns.values()}
    if len(lengths) > 1:
        raise PlyError(f"{path}: vertex columns have different lengths {sorted(lengths)}")
    for name, col in columns.items():
        if col.ndim != 1 or col.dtype.str[1:] not in _PLY_NAMES:
            raise PlyError(f"{path}: column '{name}' ({col.dtype}, shape {col.shape}) is not a 1-D column of a PLY "
                           f"type ({', '.join(_PLY_NAMES.values())})")
    n = lengths.pop() if lengths else 0
    rec = np.zeros(n, dtype=[(name, "<" + col.dtype.str[1:]) for name, col in columns.items()])
    for name, col in columns.items():
        rec[name] = col
    header = ["ply", "format binary_little_endian 1.0", *(f"comment {c}" for c in comments), f"element vertex {n}",
              *(f"property {_PLY_NAMES[col.dtype.str[1:]]} {name}" for name, col in columns.items()), "end_header", ""]
    path.parent.mkdir(parents=True, exist_ok=True)
    # written beside and renamed: a write cut short (a full disk) never leaves a PLY whose header promises
    # vertices it does not hold
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with open(tmp, "wb") as fh:
            fh.write("\n".join(header).encode("ascii"))
            fh.write(rec.tobytes())
        tmp.replace(path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def write_cloud_ply(path: str | Path, columns: Mapping[str, AnyArray], comment: str = "lsu") -> Path:
    """An LSU cloud from PointCloud2 columns (x y z [m], packed rgb, u v, snap) as the PLY the project reads.

    Properties: x y z (float, metres, lsu_left_optical), red green blue (uchar), u v (float, left
    raw pixel), snap (uint). No ``rgb`` column: white.
    """
    from .pointcloud2 import unpack_rgb

    n = len(columns["x"])
    rgb = unpack_rgb(columns["rgb"]) if "rgb" in columns and n else np.full((n, 3), 255, np.uint8)
    vertices = {"x": np.asarray(columns["x"], "<f4"), "y": np.asarray(columns["y"], "<f4"),
                "z": np.asarray(columns["z"], "<f4"), "red": rgb[:, 0], "green": rgb[:, 1], "blue": rgb[:, 2],
                "u": np.asarray(columns["u"], "<f4"), "v": np.asarray(columns["v"], "<f4"),
                "snap": np.asarray(columns["snap"], "<u4")}
    return write_ply(path, vertices, [f"{comment}, frame lsu_left_optical, metres"])

"""What the face_processor does with one scan cloud, without ROS: mesh, smooth, texture, files, face, signature.

`process_cloud` takes the PointCloud2 columns (x y z, and rgb u v when present) and returns a
`ScanResult`; each stage that fails (not a face -> no nose) records a one-line message and the
stages that can still run do. Meshing: the given triangles, else Delaunay on the pixel grid (u, v),
else ball pivoting of the plain cloud. `load_cloud_file` reads a PLY cloud or mesh, or an NPY array,
for `lsu mesh`, `lsu face` and the enrol/identify services.

Units and axes: clouds are in metres in the sensor's optical frame (x right, y down, z forward,
away from the sensor; the LSU's left camera, or any depth camera's), the face looking back at the
sensor. Files in millimetres are read with ``units="mm"``; ``units="auto"`` decides from the cloud's
size (a head and shoulders span 0.1-1 m), and a size implausible in the stated unit is an error
that says which unit it looks like.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lsu_bags.ply import UNITS, read_ply
from lsu_common.arrays import AnyArray

from .face import FaceError, FaceFrame, FaceParams, NoseResult, embed_face
from .mesh import FaceMesh, MeshError, MeshParams, mesh_plain_cloud, triangulate_image_plane
from .signature import Signature, SignatureError, SignatureParams, make_signature
from .smoothing import SmoothParams, smooth
from .texture import render_views, unpack_rgb, write_mesh

__all__ = ["ProcessParams", "ScanResult", "process_cloud", "load_cloud_file", "write_outputs", "CloudFileError",
           "to_metres", "UNITS"]


class CloudFileError(ValueError):
    """A cloud file cannot be used (the message names the file and why)."""


@dataclass(frozen=True)
class ProcessParams:
    """All settings of the processing chain."""

    mesh: MeshParams = MeshParams()
    smoothing: SmoothParams = SmoothParams()
    face: FaceParams = FaceParams()
    signature: SignatureParams = SignatureParams()


@dataclass
class ScanResult:
    """Everything made from one cloud; ``None`` where a stage could not run (see ``messages``)."""

    points: AnyArray
    colors: AnyArray | None = None
    mesh: FaceMesh | None = None              # smoothed
    raw_mesh: FaceMesh | None = None          # before smoothing
    nose: NoseResult | None = None
    frame: FaceFrame | None = None
    signature: Signature | None = None
    shrinkage: dict[str, float] = field(default_factory=dict)
    messages: list[str] = field(default_factory=list)

    @property
    def is_face(self) -> bool:
        """A nose was found and a signature made."""
        return self.signature is not None


def process_cloud(columns: dict[str, AnyArray], params: ProcessParams = ProcessParams(),
                  faces: AnyArray | None = None) -> ScanResult:
    """Mesh (Delaunay on u, v, or the given ``faces``), smooth, then find the face and its signature."""
    for name in ("x", "y", "z"):
        if name not in columns:
            raise MeshError(f"the cloud has no '{name}' field; it is not an LSU scan cloud")
    xyz = np.stack([np.asarray(columns[c], dtype=np.float64) for c in "xyz"], axis=1)
    finite = np.all(np.isfinite(xyz), axis=1)
    if not np.all(finite):
        xyz = xyz[finite]
    if len(xyz) == 0:
        raise MeshError("the cloud is empty: no points were triangulated (is the laser line visible to both "
                        "cameras? check lsu topic echo /lsu/points)")
    colors = unpack_rgb(np.asarray(columns["rgb"])[finite]) if "rgb" in columns else None
    if colors is None and all(k in columns for k in ("red", "green", "blue")):
        colors = np.stack([np.asarray(columns[k])[finite] for k in ("red", "green", "blue")], axis=1).astype(np.uint8)
    result = ScanResult(points=xyz, colors=colors)
    raw: FaceMesh | None = None
    if faces is not None and len(faces) and np.all(finite):
        raw = FaceMesh(xyz, np.asarray(faces, dtype=np.int64), colors)
    elif "u" in columns and "v" in columns:
        uv = np.stack([np.asarray(columns["u"], dtype=np.float64), np.asarray(columns["v"], dtype=np.float64)],
                      axis=1)[finite]
        try:
            raw = triangulate_image_plane(xyz, uv, colors, params.mesh)
        except MeshError as exc:
            result.messages.append(f"no mesh: {exc}")
    else:
        try:
            raw = mesh_plain_cloud(xyz, colors)
        except MeshError as exc:
            result.messages.append(f"no mesh: {exc}")
    if raw is not None and raw.n_triangles:
        result.raw_mesh = raw
        smoothed = raw.with_vertices(smooth(raw.vertices, raw.triangles, params.smoothing))
        result.mesh = smoothed
        from .smoothing import shrinkage
        result.shrinkage = shrinkage(raw.vertices, smoothed.vertices, raw.triangles)
    elif raw is not None:
        result.messages.append("no mesh: every triangle was culled (points too sparse or noisy)")
    # the face uses the measured points: the depth-map cells average their noise anyway, and a gallery
    # then stays valid whatever the smoothing settings of the node
    pts = xyz
    try:
        nose, frame, mask = embed_face(pts, params.face)
        result.nose, result.frame = nose, frame
        result.signature = make_signature(pts[mask], frame, params.signature, params.face, nose.noise_m)
        result.messages.extend(f"warning: {w}" for w in nose.warnings)
    except (FaceError, SignatureError) as exc:
        result.messages.append(f"no face: {exc}")
    return result


def to_metres(xyz: AnyArray, units: str = "auto", what: str = "the cloud") -> float:
    """Factor that takes ``xyz`` in ``units`` to metres; raises `CloudFileError` for an implausible size."""
    if units not in UNITS:
        raise CloudFileError(f"units must be one of {', '.join(UNITS)} (got {units!r})")
    p = np.asarray(xyz, dtype=np.float64)
    p = p[np.all(np.isfinite(p), axis=1)]
    if len(p) < 2:
        return 1.0 if units != "mm" else 0.001
    lo, hi = np.percentile(p, [1, 99], axis=0)
    size = float(np.max(hi - lo))
    if units == "auto":
        units = "mm" if size > 20.0 else "m"
    factor = 0.001 if units == "mm" else 1.0
    metres = size * factor
    if not 0.02 <= metres <= 10.0:
        guess = ("millimetres (--units mm)" if 20.0 <= size <= 10000.0 else
                 "metres (--units m)" if 0.02 <= size <= 10.0 else "neither metres nor millimetres")
        raise CloudFileError(f"{what} spans {size:.4g} {units}, which is {metres:.4g} m: not a head-sized scene "
                             f"(0.02-10 m); it looks like {guess}")
    return factor


def load_cloud_file(path: str | Path, units: str = "auto") -> dict[str, object]:
    """Columns in metres (and ``faces`` when the file is a mesh) of a PLY cloud/mesh or an NPY array.

    NPY: an (N, 3) array of x y z, (N, 5) of x y z u v, or a structured array with fields x y z (and
    optionally u v, rgb). ``units``: "m", "mm" or "auto" (see the module doc).
    """
    path = Path(path).expanduser()
    suffix = path.suffix.lower()
    if suffix == ".ply":
        vertices, faces = read_ply(path)
    elif suffix == ".npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise CloudFileError(f"{path}: not a readable NPY array ({exc})") from None
        faces = None
        if arr.dtype.names:
            vertices = {n: np.asarray(arr[n]) for n in arr.dtype.names}
        elif arr.ndim == 2 and arr.shape[1] in (3, 5, 6):
            names = {3: "xyz", 5: ("x", "y", "z", "u", "v"), 6: ("x", "y", "z", "nx", "ny", "nz")}[arr.shape[1]]
            vertices = {n: arr[:, k].astype(np.float64) for k, n in enumerate(names)}
        else:
            raise CloudFileError(f"{path}: an NPY cloud is an (N, 3) array of x y z in rows, (N, 5) x y z u v, or a "
                                 f"structured array with fields x y z; this one has shape {arr.shape}")
    else:
        raise CloudFileError(f"{path}: only PLY clouds/meshes and NPY arrays are read (lsu reconstruct and scans "
                             f"write PLY)")
    for c in "xyz":
        if c not in vertices:
            raise CloudFileError(f"{path}: no '{c}' field; the fields are {', '.join(vertices) or 'none'}")
    xyz = np.stack([np.asarray(vertices[c], dtype=np.float64) for c in "xyz"], axis=1)
    factor = to_metres(xyz, units, str(path))
    if factor != 1.0:
        for c in "xyz":
            vertices[c] = np.asarray(vertices[c], dtype=np.float64) * factor
    return {"columns": vertices, "faces": faces}


def write_outputs(result: ScanResult, folder: str | Path, render_size_px: int = 480,
                  renders: bool = True) -> list[Path]:
    """Write mesh.ply, mesh.obj and the renders of ``result`` into ``folder``; returns the files written."""
    if result.mesh is None:
        return []
    folder = Path(folder).expanduser()
    files = [write_mesh(result.mesh, folder / "mesh.ply"), write_mesh(result.mesh, folder / "mesh.obj")]
    if renders:
        files.extend(render_views(result.mesh, folder, size_px=render_size_px).values())
    return files

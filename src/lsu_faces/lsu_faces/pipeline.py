"""What the face_processor does with one scan cloud, without ROS: mesh, smooth, texture, files, face, signature.

`process_cloud` takes the PointCloud2 columns (x y z, and rgb u v when present) and returns a
`ScanResult`; each stage that fails (no u/v -> no mesh; not a face -> no nose) records a one-line
message and the stages that can still run do. `load_cloud_file` reads a PLY cloud or mesh for
`lsu mesh` and the enrol/identify services.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np

from .face import FaceError, FaceFrame, FaceParams, NoseResult, embed_face
from .mesh import FaceMesh, MeshError, MeshParams, triangulate_image_plane
from .plyio import read_ply
from .signature import Signature, SignatureError, SignatureParams, make_signature
from .smoothing import SmoothParams, smooth
from .texture import render_views, unpack_rgb, write_mesh

__all__ = ["ProcessParams", "ScanResult", "process_cloud", "load_cloud_file", "write_outputs", "CloudFileError"]


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

    points: np.ndarray
    colors: Optional[np.ndarray] = None
    mesh: Optional[FaceMesh] = None              # smoothed
    raw_mesh: Optional[FaceMesh] = None          # before smoothing
    nose: Optional[NoseResult] = None
    frame: Optional[FaceFrame] = None
    signature: Optional[Signature] = None
    shrinkage: Dict[str, float] = field(default_factory=dict)
    messages: List[str] = field(default_factory=list)

    @property
    def is_face(self) -> bool:
        """A nose was found and a signature made."""
        return self.signature is not None


def process_cloud(columns: Dict[str, np.ndarray], params: ProcessParams = ProcessParams(),
                  faces: Optional[np.ndarray] = None) -> ScanResult:
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
    raw: Optional[FaceMesh] = None
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
        result.messages.append("no mesh: the cloud has no u/v fields (left-image pixel of each point), which "
                               "meshing needs; use the stereo_matcher's /lsu/scan/cloud or a cloud.ply of a scan")
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
        result.signature = make_signature(pts[mask], frame, params.signature, params.face)
    except (FaceError, SignatureError) as exc:
        result.messages.append(f"no face: {exc}")
    return result


def load_cloud_file(path: "str | Path") -> Dict[str, object]:
    """Columns (and ``faces`` when the file is a mesh) of a PLY cloud/mesh, as `process_cloud` takes them."""
    path = Path(path).expanduser()
    if path.suffix.lower() != ".ply":
        raise CloudFileError(f"{path}: only PLY clouds and meshes are read (lsu reconstruct and scans write PLY)")
    vertices, faces = read_ply(path)
    return {"columns": vertices, "faces": faces}


def write_outputs(result: ScanResult, folder: "str | Path", render_size_px: int = 480,
                  renders: bool = True) -> List[Path]:
    """Write mesh.ply, mesh.obj and the renders of ``result`` into ``folder``; returns the files written."""
    if result.mesh is None:
        return []
    folder = Path(folder).expanduser()
    files = [write_mesh(result.mesh, folder / "mesh.ply"), write_mesh(result.mesh, folder / "mesh.obj")]
    if renders:
        files.extend(render_views(result.mesh, folder, size_px=render_size_px).values())
    return files

"""The scan library: the coordinator's scan folders on disk (no rclpy: unit-tested alone).

A scan folder is what scan_coordinator and face_processor wrote (scan.json, cloud.ply, mesh.ply,
mesh.obj, renders, the bag folder); the library only reads them, converts a mesh to STL on
request, and deletes a whole folder when asked. Every name that arrives from a request is resolved
and must stay inside the scans folder (``..``, absolute paths and symlinks out are refused).
"""

from __future__ import annotations

import io
import json
import re
import shutil
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

#: a scan folder's name as the coordinator makes it (date-id), and nothing that walks out of the folder
SCAN_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,127}$")
DOWNLOADS = {  # kind -> (file in the scan folder, media type, what it is)
    "cloud.ply": ("cloud.ply", "application/octet-stream", "the scan's point cloud (PLY)"),
    "mesh.ply": ("mesh.ply", "application/octet-stream", "the face mesh (PLY, vertex colours)"),
    "mesh.obj": ("mesh.obj", "text/plain", "the face mesh (OBJ)"),
    "mesh.stl": ("mesh.ply", "application/octet-stream", "the face mesh (STL, made from mesh.ply on request)"),
    "bag.zip": ("", "application/zip", "the recorded bag folder (zip)"),
    "scan.json": ("scan.json", "application/json", "the scan's record"),
}
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


class LibraryError(ValueError):
    """A request named something that is not a scan or a file of one; ``status`` is the HTTP answer."""

    def __init__(self, message: str, status: int = 404) -> None:
        super().__init__(message)
        self.status = status


@dataclass(frozen=True)
class Library:
    root: Path

    def folder(self, scan_id: str) -> Path:
        """The folder of ``scan_id``, refused unless it is a direct child of the scans folder."""
        if not SCAN_ID.match(scan_id or ""):
            raise LibraryError(f"'{scan_id}' is not a scan name (letters, digits, '-', '_', '.')", 400)
        root = self.root.resolve()
        folder = (root / scan_id).resolve()
        if folder.parent != root or not folder.is_dir():
            raise LibraryError(f"no scan '{scan_id}' in {self.root}")
        return folder

    def file(self, scan_id: str, name: str) -> Path:
        """A file inside a scan folder (sub-folders allowed), refused when it resolves outside that folder."""
        folder = self.folder(scan_id)
        if not name or name.startswith("/") or "\\" in name or "\x00" in name:
            raise LibraryError(f"'{name}' is not a file name inside the scan folder", 400)
        path = (folder / name).resolve()
        if not path.is_relative_to(folder):
            raise LibraryError(f"'{name}' lies outside the scan folder", 403)
        if not path.is_file():
            raise LibraryError(f"scan '{scan_id}' has no file '{name}'")
        return path

    def record(self, folder: Path) -> dict[str, Any]:
        try:
            data = json.loads((folder / "scan.json").read_text())
            return data if isinstance(data, dict) else {}
        except (OSError, ValueError):
            return {}

    def images(self, folder: Path) -> list[str]:
        """Render images of a scan (front first), as names relative to its folder."""
        found = [p for p in folder.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()]
        found.sort(key=lambda p: (0 if "front" in p.name else 1, str(p)))
        return [str(p.relative_to(folder)) for p in found]

    def bag_folder(self, folder: Path) -> Path | None:
        for meta in sorted(folder.rglob("metadata.yaml")):
            return meta.parent
        return None

    def summary(self, folder: Path) -> dict[str, Any]:
        """One row of the library (what the page lists)."""
        rec = self.record(folder)
        files = {p.name for p in folder.iterdir() if p.is_file()}
        kinds = [k for k, (name, _, _) in DOWNLOADS.items() if name and name in files]
        if self.bag_folder(folder) is not None:
            kinds.append("bag.zip")
        images = self.images(folder)
        goal: dict[str, Any] = rec["goal"] if isinstance(rec.get("goal"), dict) else {}
        timings: dict[str, Any] = rec["timings_s"] if isinstance(rec.get("timings_s"), dict) else {}
        snaps = rec.get("snaps_captured", rec.get("snaps"))
        return {
            "id": folder.name,
            "label": str(goal.get("label", rec.get("label", ""))),
            "when": str(rec.get("started", "")),
            "status": str(rec.get("status", "")),
            "mode": str(goal.get("mode", "") or ("stopsnap" if goal else "")),
            "snaps": len(snaps) if isinstance(snaps, list) else snaps,
            "snaps_expected": rec.get("snaps_expected"),
            "points": rec.get("points"),
            "seconds": timings.get("scan", rec.get("seconds")),
            "partial": bool(rec.get("partial", False)),
            "thumbnail": images[0] if images else "",
            "images": images,
            "downloads": kinds,
            "mtime": folder.stat().st_mtime,
        }

    def list(self) -> list[dict[str, Any]]:
        """Every scan folder, newest first."""
        if not self.root.is_dir():
            return []
        rows = [self.summary(p) for p in self.root.iterdir() if p.is_dir() and SCAN_ID.match(p.name)
                and ((p / "scan.json").is_file() or (p / "cloud.ply").is_file())]
        rows.sort(key=lambda r: r["mtime"], reverse=True)
        return rows

    def delete(self, scan_id: str) -> Path:
        folder = self.folder(scan_id)
        shutil.rmtree(folder)
        return folder

    def download(self, scan_id: str, kind: str) -> tuple[bytes | Path, str, str]:
        """(a file or bytes, media type, download name) of ``kind`` (a key of DOWNLOADS)."""
        if kind not in DOWNLOADS:
            raise LibraryError(f"unknown download '{kind}'; one of {', '.join(DOWNLOADS)}", 400)
        name, media, _ = DOWNLOADS[kind]
        folder = self.folder(scan_id)
        filename = f"{scan_id}-{kind}"
        if kind == "bag.zip":
            bag = self.bag_folder(folder)
            if bag is None:
                raise LibraryError(f"scan '{scan_id}' has no bag (scan with 'record bag' on)")
            return zip_folder(bag), media, filename
        path = self.file(scan_id, name)
        if kind == "mesh.stl":
            return mesh_to_stl(path), media, filename
        return path, media, filename


def zip_folder(folder: Path) -> bytes:
    """A folder as zip bytes (a bag is a folder of metadata + storage files)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as z:
        for p in sorted(folder.rglob("*")):
            if p.is_file():
                z.write(p, str(Path(folder.name) / p.relative_to(folder)))
    return buf.getvalue()


def mesh_to_stl(mesh_ply: Path) -> bytes:
    """mesh.ply as binary STL bytes (open3d writes STL to a path only: a temporary file)."""
    import tempfile

    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(mesh_ply))
    if len(mesh.triangles) == 0:
        raise LibraryError(f"{mesh_ply.name} has no triangles: nothing to write as STL", 409)
    mesh.compute_triangle_normals()
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "mesh.stl"
        if not o3d.io.write_triangle_mesh(str(out), mesh, write_ascii=False):
            raise LibraryError("open3d could not write the STL", 500)
        return out.read_bytes()

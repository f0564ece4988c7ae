"""`lsu mesh` and `lsu face`: the face_processor's chain and gallery offline, on PLY files (no ROS graph needed).

    lsu mesh scans/20261123-0641/cloud.ply                 # mesh.ply, mesh.obj, renders next to the cloud
    lsu mesh cloud.ply -o out/ --smoothing laplacian
    lsu face enroll alice cloud.ply                        # gallery: ~/.lsu/faces/gallery.db (or --gallery)
    lsu face identify probe.ply
    lsu face list
    lsu face remove alice            |  lsu face remove --id 7
"""

from __future__ import annotations

import argparse
from pathlib import Path

from .face import NOSE_METHODS, FaceParams
from .mesh import MeshParams
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .pipeline import ProcessParams
from .signature import SIGNATURE_METHODS, SignatureParams
from .smoothing import METHODS as SMOOTH_METHODS
from .smoothing import SmoothParams

__all__ = ["register", "DEFAULT_GALLERY", "DEFAULT_THRESHOLD"]

DEFAULT_GALLERY = "~/.lsu/faces/gallery.db"
DEFAULT_THRESHOLD = 0.33


def _params(args: argparse.Namespace) -> "ProcessParams":
    from .pipeline import ProcessParams

    sp = SmoothParams()
    return ProcessParams(mesh=MeshParams(),
                         smoothing=SmoothParams(method=getattr(args, "smoothing", sp.method),
                                                iterations=getattr(args, "iterations", sp.iterations)),
                         face=FaceParams(nose_method=getattr(args, "nose_method", "protrusion")),
                         signature=SignatureParams(method=getattr(args, "signature_method", "depthmap")))


def _process(path: str, args: argparse.Namespace):
    # the pipeline pulls in open3d (renders): imported when a command runs, not when `lsu` starts
    from .pipeline import load_cloud_file, process_cloud

    loaded = load_cloud_file(path)
    return process_cloud(loaded["columns"], _params(args), loaded["faces"])  # type: ignore[arg-type]


def run_mesh(args: argparse.Namespace) -> int:
    """`lsu mesh CLOUD.ply`."""
    result = _process(args.cloud, args)
    for text in result.messages:
        print(f"lsu mesh: {text}")
    if result.mesh is None:
        raise ValueError(f"{args.cloud}: no mesh could be made (see above)")
    out = Path(args.output) if args.output else Path(args.cloud).expanduser().parent
    from .pipeline import write_outputs

    files = write_outputs(result, out, args.size, renders=not args.no_renders)
    s = result.shrinkage
    print(f"lsu mesh: {len(result.points)} points -> {result.mesh.n_triangles} triangles "
          f"({result.raw_mesh.stats.get('culled_triangles', 0) if result.raw_mesh else 0} culled), smoothing "
          f"{args.smoothing}: volume {s.get('volume_change_pct', 0.0):+.2f} %")
    if result.nose is not None and result.frame is not None:
        print(f"lsu mesh: nose tip at {[round(float(x) * 1000, 1) for x in result.frame.origin]} mm "
              f"(left optical frame)")
    for f in files:
        print(f"  {f}")
    return 0


def run_face(args: argparse.Namespace) -> int:
    """`lsu face enroll|identify|list|remove`."""
    from .gallery import Gallery

    gallery = Gallery(args.gallery)
    if args.action == "list":
        entries = gallery.list()
        if not entries:
            print(f"gallery {gallery.path}: empty")
        for e in entries:
            print(f"{e.id:5d}  {e.name:<24s} {e.date}  {e.method:<8s} {e.points_used:6d} points  {e.mesh_file}")
        return 0
    if args.action == "remove":
        if args.id is None and not args.name:
            raise ValueError("lsu face remove needs a NAME or --id N")
        n = gallery.remove(name=args.name if args.id is None else None, entry_id=args.id)
        print(f"removed {n} entr{'y' if n == 1 else 'ies'} from {gallery.path}")
        return 0
    result = _process(args.cloud, args)
    if result.signature is None:
        raise ValueError(f"{args.cloud}: " + ("; ".join(result.messages) or "no face found"))
    if args.action == "enroll":
        entry = gallery.enroll(args.name, result.signature, str(Path(args.cloud).expanduser().resolve()))
        print(f"enrolled '{args.name}' as entry {entry} ({result.signature.points_used} face points) in {gallery.path}")
        return 0
    matches = gallery.identify(result.signature, args.max_results)
    if not matches:
        print(f"gallery {gallery.path} is empty; enrol faces first")
        return 1
    accepted = matches[0].score >= args.threshold
    print(f"best: {matches[0].name if accepted else '(rejected: no score >= %.2f)' % args.threshold}")
    for rank, m in enumerate(matches, 1):
        print(f"  {rank}. {m.name:<24s} score {m.score:.3f}  distance {m.distance_m * 1000:.3f} mm  entry {m.entry_id}")
    return 0 if accepted else 1


def register(subparsers: "argparse._SubParsersAction[argparse.ArgumentParser]") -> None:
    """Add `lsu mesh` and `lsu face` (``lsu.commands`` entry point)."""
    m = subparsers.add_parser("mesh", help="scan cloud (PLY with u v) -> textured mesh, renders, nose tip",
                              description="Mesh an LSU scan cloud like the face_processor: Delaunay on the left-image "
                                          "pixels, cull jumps, smooth, write mesh.ply, mesh.obj and front/side renders.")
    m.add_argument("cloud", metavar="CLOUD.ply", help="cloud written by lsu reconstruct or a scan (x y z rgb u v)")
    m.add_argument("-o", "--output", metavar="DIR", help="folder for the files (default: the cloud's folder)")
    m.add_argument("--smoothing", choices=SMOOTH_METHODS, default=SmoothParams().method, help="smoothing method")
    m.add_argument("--iterations", type=int, default=SmoothParams().iterations, help="smoothing iterations/passes")
    m.add_argument("--size", type=int, default=480, metavar="PX", help="render size (default 480)")
    m.add_argument("--no-renders", action="store_true", help="write the mesh files only")
    m.set_defaults(func=run_mesh)

    f = subparsers.add_parser("face", help="face gallery: enroll, identify, list, remove",
                              description="Enrol and identify faces from PLY scan clouds in the SQLite gallery the "
                                          "face_processor node uses.")
    f.add_argument("--gallery", default=DEFAULT_GALLERY, metavar="FILE", help=f"gallery file (default {DEFAULT_GALLERY})")
    actions = f.add_subparsers(dest="action", required=True, metavar="ACTION")
    e = actions.add_parser("enroll", help="add a face under a name")
    e.add_argument("name")
    e.add_argument("cloud", metavar="CLOUD.ply")
    i = actions.add_parser("identify", help="rank the gallery against a face (exit 1 when rejected)")
    i.add_argument("cloud", metavar="CLOUD.ply")
    i.add_argument("--max-results", type=int, default=5)
    i.add_argument("--threshold", type=float, default=DEFAULT_THRESHOLD, help="reject below this score (0..1)")
    for p in (e, i):
        p.add_argument("--nose-method", choices=NOSE_METHODS, default="protrusion")
        p.add_argument("--signature-method", choices=SIGNATURE_METHODS, default="depthmap")
    actions.add_parser("list", help="show the entries")
    r = actions.add_parser("remove", help="remove a name (all its samples) or one entry")
    r.add_argument("name", nargs="?")
    r.add_argument("--id", type=int, help="entry id to remove")
    f.set_defaults(func=run_face)

"""`lsu mesh` and `lsu face`: the face_processor's chain and gallery offline, on PLY/NPY files (no ROS graph needed).

    lsu mesh scans/20261123-0641/cloud.ply                 # mesh.ply, mesh.obj, renders next to the cloud
    lsu mesh cloud.ply -o out/ --smoothing laplacian
    lsu mesh depth.npy --units mm                          # a plain x y z cloud (no u/v): ball pivoting
    lsu face enroll alice cloud.ply                        # gallery: ~/.lsu/faces/gallery.db (or --gallery)
    lsu face identify probe.ply --false-accept 0.001
    lsu face list
    lsu face remove alice            |  lsu face remove --id 7

Clouds: metres (or ``--units mm``; ``auto`` decides from the size) in the sensor's optical frame (x right,
y down, z away from the sensor). Options go before or after the action (``lsu face --gallery G list`` or
``lsu face list --gallery G``).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from lsu_bags.ply import UNITS

from .face import NOSE_METHODS, FaceParams
from .gallery import DEFAULT_FALSE_ACCEPT
from .mesh import MeshParams

if TYPE_CHECKING:
    from .pipeline import ProcessParams
from .signature import SIGNATURE_METHODS, SignatureParams
from .smoothing import METHODS as SMOOTH_METHODS
from .smoothing import SmoothParams

__all__ = ["register", "DEFAULT_GALLERY"]

DEFAULT_GALLERY = "~/.lsu/faces/gallery.db"


def _params(args: argparse.Namespace) -> ProcessParams:
    from .pipeline import ProcessParams

    sp = SmoothParams()
    return ProcessParams(mesh=MeshParams(),
                         smoothing=SmoothParams(method=getattr(args, "smoothing", sp.method),
                                                iterations=getattr(args, "iterations", sp.iterations)),
                         face=FaceParams(nose_method=getattr(args, "nose_method", FaceParams().nose_method)),
                         signature=SignatureParams(method=getattr(args, "signature_method", "depthmap")))


def _process(path: str, args: argparse.Namespace):
    # the pipeline pulls in open3d (renders): imported when a command runs, not when `lsu` starts
    from .pipeline import load_cloud_file, process_cloud

    loaded = load_cloud_file(path, getattr(args, "units", "auto"))
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

    gallery = Gallery(getattr(args, "gallery", DEFAULT_GALLERY))
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
    for text in result.messages:          # warnings (an asymmetric face): reported, never a refusal
        print(f"lsu face: {text}")
    if args.action == "enroll":
        entry = gallery.enroll(args.name, result.signature, str(Path(args.cloud).expanduser().resolve()))
        noise = result.signature.noise_m * 1000.0
        print(f"enrolled '{args.name}' as entry {entry} ({result.signature.points_used} face points, depth noise "
              f"{noise:.2f} mm, nose confidence {result.nose.confidence if result.nose else float('nan'):.2f}) in "
              f"{gallery.path}")
        return 0
    ident = gallery.identify(result.signature, args.max_results, args.false_accept)
    if not ident.matches:
        print(f"gallery {gallery.path} is empty; enrol faces first")
        return 1
    best = ident.matches[0]
    if ident.accepted:
        print(f"best: {best.name}")
    else:
        print(f"best: (rejected: {ident.reason})")
    print(f"  stranger chances calibrated on {ident.calibration} (depth noise of the enrolled scans "
          f"{ident.gallery_noise_mm:.2f} mm, this scan {ident.probe_noise_mm:.2f} mm): accepting at FPIR "
          f"{ident.false_accept_rate:g} needs < {ident.threshold_m * 1000:.2f} mm")
    for rank, m in enumerate(ident.matches, 1):
        print(f"  {rank}. {m.name:<24s} score {m.score:.6f}  stranger chance {m.false_accept:.3e}  "
              f"distance {m.distance_m * 1000:.3f} mm  entry {m.entry_id}")
    return 0 if ident.accepted else 1


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `lsu mesh` and `lsu face` (``lsu.commands`` entry point)."""
    m = subparsers.add_parser("mesh", help="scan cloud (PLY with u v) -> textured mesh, renders, nose tip",
                              description="Mesh an LSU scan cloud like the face_processor: Delaunay on the left-image "
                                          "pixels, cull jumps, smooth, write mesh.ply, mesh.obj and front/side renders.")
    m.add_argument("cloud", metavar="CLOUD", help="PLY or NPY cloud (x y z, optional rgb u v) or mesh, sensor frame")
    m.add_argument("--units", choices=UNITS, default="auto",
                   help="length unit of the file (default: auto from the size)")
    m.add_argument("-o", "--output", metavar="DIR", help="folder for the files (default: the cloud's folder)")
    m.add_argument("--smoothing", choices=SMOOTH_METHODS, default=SmoothParams().method, help="smoothing method")
    m.add_argument("--iterations", type=int, default=SmoothParams().iterations, help="smoothing iterations/passes")
    m.add_argument("--size", type=int, default=480, metavar="PX", help="render size (default 480)")
    m.add_argument("--no-renders", action="store_true", help="write the mesh files only")
    m.set_defaults(func=run_mesh)

    f = subparsers.add_parser("face", help="face gallery: enroll, identify, list, remove",
                              description="Enrol and identify faces from PLY scan clouds in the SQLite gallery the "
                                          "face_processor node uses.")
    gallery_help = f"gallery file (default {DEFAULT_GALLERY}; private: 0600 in a 0700 folder)"
    f.add_argument("--gallery", default=DEFAULT_GALLERY, metavar="FILE", help=gallery_help)
    # the same option after the action: SUPPRESS keeps the value given before it when absent here
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--gallery", default=argparse.SUPPRESS, metavar="FILE", help=gallery_help)
    actions = f.add_subparsers(dest="action", required=True, metavar="ACTION")
    e = actions.add_parser("enroll", help="add a face under a name", parents=[common])
    e.add_argument("name")
    e.add_argument("cloud", metavar="CLOUD")
    i = actions.add_parser("identify", help="rank the gallery against a face (exit 1 when rejected)", parents=[common])
    i.add_argument("cloud", metavar="CLOUD")
    i.add_argument("--max-results", type=int, default=5)
    i.add_argument("--false-accept", type=float, default=DEFAULT_FALSE_ACCEPT, metavar="RATE",
                   help=f"accept the best match only when a stranger would come as close with at most this chance "
                        f"(default {DEFAULT_FALSE_ACCEPT:g})")
    for p in (e, i):
        p.add_argument("--units", choices=UNITS, default="auto", help="length unit of the file (default: auto)")
        p.add_argument("--nose-method", choices=NOSE_METHODS, default=FaceParams().nose_method)
        p.add_argument("--signature-method", choices=SIGNATURE_METHODS, default="depthmap")
    actions.add_parser("list", help="show the entries", parents=[common])
    r = actions.add_parser("remove", help="remove a name (all its samples) or one entry; nothing of it stays in "
                                          "the file", parents=[common])
    r.add_argument("name", nargs="?")
    r.add_argument("--id", type=int, help="entry id to remove")
    f.set_defaults(func=run_face)

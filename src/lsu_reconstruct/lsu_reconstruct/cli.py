"""`lsu reconstruct`: the stereo_matcher's pipeline offline, from a rosbag2 recording (or image pairs) to PLY.

    lsu reconstruct --calib config/calibration/lab --bag scans/20261123-0641 -o face.ply
    lsu reconstruct --calib config/calibration/lab --pairs shots/ -o face.ply   # left_*.png, right_*.png

The bag must hold ``/lsu/stereo/{left,right}/laser_line`` (``lsu_interfaces/msg/LaserLine``);
``/lsu/scan/events`` (snap indices, TEXTURE stamp) and ``/lsu/stereo/left/image_raw`` (the
texture) are used when present. Any namespace works: topics are matched by their suffix.
Bags are read with lsu_bags (the ``rosbags`` library; the lsu_interfaces types come from
their installed .msg files), so no ROS installation is needed to read them.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from lsu_bags.bags import BagError
from lsu_bags.ply import write_cloud_ply

from .bag_lines import read_bag
from .matching import LineArrays, MatchParams
from .pipeline import colour_at, merge_snaps, reconstruct_snap
from .stereo import StereoModel
from .triangulate import METHODS

__all__ = ["register", "BagError", "read_bag", "read_pairs", "run"]


def read_pairs(folder: str | Path) -> list[tuple[int, int, LineArrays, LineArrays]]:
    """Laser lines of ``left_*.png`` / ``right_*.png`` image pairs (same suffix), found by lsu_extract's detector."""
    try:
        from lsu_extract.extractor import extract_laser_line
    except ImportError as exc:
        raise LookupError(f"--pairs needs the lsu_extract package (laser line detector), which cannot be imported "
                          f"({exc}); record a bag with the laser_extractor running and use --bag") from None
    import cv2

    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"image folder {folder} not found")
    lefts = {p.name[len("left_"):]: p for p in folder.glob("left_*.png")}
    rights = {p.name[len("right_"):]: p for p in folder.glob("right_*.png")}
    common = sorted(set(lefts) & set(rights))
    if not common:
        raise FileNotFoundError(f"{folder} holds no left_*.png / right_*.png pairs with the same suffix")
    pairs = []
    for index, suffix in enumerate(common):
        lines = []
        for path in (lefts[suffix], rights[suffix]):
            image = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if image is None:
                raise BagError(f"{path} is not a readable image")
            r = extract_laser_line(image)
            lines.append(LineArrays(r.u, r.v, r.peak, r.width, r.quality, r.image_width, r.image_height))
        pairs.append((index, index, lines[0], lines[1]))
    return pairs


def run(args: argparse.Namespace) -> int:
    """`lsu reconstruct` (returns the exit code)."""
    model = StereoModel.from_folder(args.calib)
    params = MatchParams(depth_min_m=args.depth_min_m, depth_max_m=args.depth_max_m,
                         smooth_window_rows=args.smooth_window_rows, method=args.triangulation)
    if args.bag:
        pairs, texture, counts = read_bag(args.bag)
    else:
        pairs, texture = read_pairs(args.pairs), None
        counts = {"left": len(pairs), "right": len(pairs), "pairs": len(pairs)}
    snaps = []
    for snap, _, left, right in pairs:
        snaps.append(reconstruct_snap(model, left, right, params, snap=snap, chain=args.chain))
    cloud = merge_snaps(sorted(snaps, key=lambda s: int(s.snap[0]) if len(s) else 0))
    if texture is not None and len(cloud):
        cloud.rgb = colour_at(texture, cloud.u, cloud.v)
    out = write_cloud_ply(args.output, cloud.fields(), comment="lsu reconstruct")
    print(f"lsu reconstruct: {len(cloud)} points from {counts['pairs']} stereo pairs "
          f"({counts['left']} left, {counts['right']} right lines){'' if texture is not None else ', uncoloured'} "
          f"-> {out}")
    return 0


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `lsu reconstruct` (``lsu.commands`` entry point)."""
    defaults = MatchParams()
    p = subparsers.add_parser("reconstruct", help="laser lines of a recorded scan -> point cloud (PLY)",
                              description="Run the stereo_matcher's matching and triangulation offline on a rosbag2 "
                                          "recording of /lsu/stereo/{left,right}/laser_line and write a PLY cloud "
                                          "(metres, left optical frame).")
    p.add_argument("--calib", required=True, metavar="DIR", help="calibration folder (left.yaml, right.yaml, stereo.yaml)")
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--bag", metavar="BAG", help="rosbag2 folder or file (sqlite3 or mcap) with laser lines")
    source.add_argument("--pairs", metavar="DIR", help="folder of left_*.png / right_*.png laser images "
                                                       "(lines found with lsu_extract's detector)")
    p.add_argument("-o", "--output", required=True, metavar="cloud.ply", help="PLY file to write")
    p.add_argument("--smooth-window-rows", type=int, default=defaults.smooth_window_rows, metavar="N",
                   help=f"local quadratic fit along the line over N rows, 0 = off (default {defaults.smooth_window_rows})")
    p.add_argument("--triangulation", choices=METHODS, default=defaults.method, help="triangulation method")
    p.add_argument("--chain", choices=("subpixel", "thesis"), default="subpixel",
                   help="matching chain: sub-pixel epipolar intersection (default) or the thesis' nearest pixel")
    p.add_argument("--depth-min-m", type=float, default=defaults.depth_min_m, help="nearest accepted depth [m]")
    p.add_argument("--depth-max-m", type=float, default=defaults.depth_max_m, help="farthest accepted depth [m]")
    p.set_defaults(func=run)
    # `lsu calibrate --laser` (entry points load sorted by name: lsu_cameras' "cameras", which adds `calibrate`,
    # comes before this "reconstruct")
    from .laser_cli import register_laser

    register_laser(subparsers)

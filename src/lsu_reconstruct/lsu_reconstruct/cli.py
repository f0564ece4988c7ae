"""`lsu reconstruct`: the stereo_matcher's pipeline offline, from a rosbag2 recording (or image pairs) to PLY.

    lsu reconstruct --calib config/calibration/lab --bag scans/20261123-0641 -o face.ply
    lsu reconstruct --calib config/calibration/lab --pairs shots/ -o face.ply   # left_*.png, right_*.png

The bag must hold ``/lsu/stereo/{left,right}/laser_line`` (``lsu_interfaces/msg/LaserLine``);
``/lsu/scan/events`` (snap indices, TEXTURE stamp) and ``/lsu/stereo/left/image_raw`` (the
texture) are used when present. Any namespace works: topics are matched by their suffix.
Bags are read with the ``rosbags`` library; the lsu_interfaces types are registered from
their .msg files, so no ROS installation is needed to read them.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from lsu_common.arrays import AnyArray

from .matching import LineArrays, MatchParams
from .pipeline import SnapPoints, colour_at, merge_snaps, reconstruct_snap
from .pointcloud2 import unpack_rgb
from .stereo import StereoModel
from .triangulate import METHODS

__all__ = ["register", "BagError", "interfaces_msg_dir", "lsu_typestore", "read_bag", "read_pairs", "write_ply",
           "run"]

LINE_TYPE = "lsu_interfaces/msg/LaserLine"
EVENT_TYPE = "lsu_interfaces/msg/ScanEvent"


class BagError(ValueError):
    """A bag cannot be read or holds no usable laser lines; the message names the file and the cause."""


def interfaces_msg_dir() -> Path:
    """Folder with the lsu_interfaces .msg files (installed share/ first, then the source tree)."""
    candidates = [Path(sys.prefix) / "share" / "lsu_interfaces" / "msg",
                  Path(__file__).resolve().parents[2] / "lsu_interfaces" / "msg"]
    for c in candidates:
        if (c / "LaserLine.msg").is_file():
            return c
    raise FileNotFoundError(f"lsu_interfaces .msg files not found in {', '.join(map(str, candidates))}; "
                            f"run `make setup`")


def lsu_typestore() -> Any:
    """A rosbags Jazzy typestore with every lsu_interfaces message registered from its .msg file."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    types: dict[str, Any] = {}
    for path in sorted(interfaces_msg_dir().glob("*.msg")):
        types.update(get_types_from_msg(path.read_text(), f"lsu_interfaces/msg/{path.stem}"))
    store.register(types)
    return store


def _key(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _line(msg: Any) -> LineArrays:
    return LineArrays(u=np.asarray(msg.u, dtype=np.float64), v=np.asarray(msg.v, dtype=np.float64),
                      peak=np.asarray(msg.peak), width=np.asarray(msg.width), quality=np.asarray(msg.quality),
                      image_width=int(msg.image_width), image_height=int(msg.image_height))


def _image(msg: Any) -> AnyArray:
    channels = {"bgr8": 3, "rgb8": 3, "mono8": 1}
    if msg.encoding not in channels:
        raise BagError(f"texture image encoding '{msg.encoding}' is not supported (bgr8, rgb8, mono8)")
    c = channels[msg.encoding]
    img = np.asarray(msg.data, dtype=np.uint8).reshape(msg.height, msg.step)[:, :msg.width * c]
    img = img.reshape(msg.height, msg.width, c)
    if c == 1:
        return np.repeat(img, 3, axis=2)
    return img[:, :, ::-1] if msg.encoding == "rgb8" else img


def read_bag(path: str | Path) -> tuple[list[tuple[int, int, LineArrays, LineArrays]], AnyArray | None, dict[str, int]]:
    """Stereo laser-line pairs of a bag: ``[(snap, stamp_ns, left, right)]``, the texture image (or None), counts."""
    from rosbags.highlevel import AnyReader

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"bag {path} not found")
    store = lsu_typestore()
    lines: dict[str, dict[int, LineArrays]] = {"left": {}, "right": {}}
    snaps: dict[int, int] = {}
    texture_keys: list[int] = []
    try:
        with AnyReader([path], default_typestore=store) as reader:
            wanted = {}
            for c in reader.connections:
                if c.topic.endswith("stereo/left/laser_line") and c.msgtype == LINE_TYPE:
                    wanted[c.id] = "left"
                elif c.topic.endswith("stereo/right/laser_line") and c.msgtype == LINE_TYPE:
                    wanted[c.id] = "right"
                elif c.topic.endswith("scan/events") and c.msgtype == EVENT_TYPE:
                    wanted[c.id] = "events"
            if not any(v in ("left", "right") for v in wanted.values()):
                topics = ", ".join(sorted(f"{c.topic} ({c.msgtype})" for c in reader.connections)) or "none"
                raise BagError(f"bag {path} has no stereo/{{left,right}}/laser_line topics of type {LINE_TYPE}; "
                               f"it has: {topics}")
            conns = [c for c in reader.connections if c.id in wanted]
            for conn, _, raw in reader.messages(connections=conns):
                msg = reader.deserialize(raw, conn.msgtype)
                kind = wanted[conn.id]
                if kind == "events":
                    if msg.type == 2:      # SNAP
                        snaps[_key(msg.image_stamp)] = int(msg.index)
                    elif msg.type == 1:    # TEXTURE
                        texture_keys.append(_key(msg.image_stamp))
                else:
                    lines[kind][_key(msg.header.stamp)] = _line(msg)
            texture = None
            if texture_keys:
                images = [c for c in reader.connections if c.topic.endswith("stereo/left/image_raw")]
                for conn, _, raw in reader.messages(connections=images):
                    msg = reader.deserialize(raw, conn.msgtype)
                    if _key(msg.header.stamp) == texture_keys[-1]:
                        texture = _image(msg)
                        break
    except BagError:
        raise
    except Exception as exc:  # rosbags raises several reader/deserialisation types for corrupt files
        raise BagError(f"cannot read bag {path}: {exc.__class__.__name__}: {exc}") from None
    common = sorted(set(lines["left"]) & set(lines["right"]))
    counts = {"left": len(lines["left"]), "right": len(lines["right"]), "pairs": len(common)}
    if not common:
        raise BagError(f"bag {path}: {counts['left']} left and {counts['right']} right laser lines but no pair with "
                       f"equal header.stamp")
    pairs = []
    for order, key in enumerate(common):
        pairs.append((snaps.get(key, order), key, lines["left"][key], lines["right"][key]))
    return pairs, texture, counts


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


def write_ply(path: str | Path, cloud: SnapPoints) -> Path:
    """Binary little-endian PLY with x y z (float, metres), red green blue (uchar), u v (float), snap (uint)."""
    path = Path(path)
    n = len(cloud)
    rgb = unpack_rgb(cloud.fields()["rgb"]) if n else np.zeros((0, 3), np.uint8)
    rec = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"),
                             ("blue", "u1"), ("u", "<f4"), ("v", "<f4"), ("snap", "<u4")])
    rec["x"], rec["y"], rec["z"] = cloud.xyz[:, 0], cloud.xyz[:, 1], cloud.xyz[:, 2]
    rec["red"], rec["green"], rec["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    rec["u"], rec["v"], rec["snap"] = cloud.u, cloud.v, cloud.snap
    header = ("ply\nformat binary_little_endian 1.0\ncomment lsu reconstruct, frame lsu_left_optical, metres\n"
              f"element vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\n"
              "property float u\nproperty float v\nproperty uint snap\nend_header\n")
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(rec.tobytes())
    return path


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
    out = write_ply(args.output, cloud)
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

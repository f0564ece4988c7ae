"""`lsu accuracy --bag`: the thesis ch. 9 study on recorded board scans (pure: no rclpy).

A real rig has no renderer to say where the board is. The truth is the board itself: each scan
starts with a laser-off pair (the TEXTURE event), in which the chessboard is detected and its
pose solved from the left camera's intrinsics alone (OpenCV ``solvePnP``). The laser snaps of
the same scan are then reconstructed by both chains (ours and the thesis') and measured against
that plane exactly as the simulated study measures against the renderer's plane. The pose is
also solved from the right image and carried into the left frame with the stereo extrinsics:
how far the two disagree is reported as the truth's own uncertainty (it includes calibration
error, which the scan shares).

Input: a bag folder, or a folder holding bag folders (e.g. the ``scans/`` output folder: every
``*/bag`` inside is read). One pose per scan (``scan_id`` of the events): record each board pose
with ``lsu scan --record`` (or one `lsu bag record` spanning several scans, the board moved
between them). The bag needs ``scan/events`` and both ``stereo/{left,right}/image_raw``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from lsu_common import stamps
from lsu_common.arrays import AnyArray
from lsu_common.images import msg_to_array

from .accuracy import CHAINS, AccuracyError, ChainRunner, evaluate_pose, summarise

__all__ = ["BoardScan", "BoardPlane", "find_bags", "read_board_scans", "detect_board_plane", "run_bag_study",
           "BACKGROUND_GATE_MM"]

_TEXTURE, _SNAP = 1, 2
# Points farther than this from the detected board plane are not on the board (the wall behind,
# the hand holding it): ~100x the noise of either chain, so no measurement error is cut away.
BACKGROUND_GATE_MM = 10.0


@dataclass
class BoardScan:
    """One recorded scan of the board: the laser-off pair and the laser snaps (BGR or mono uint8)."""

    name: str
    texture: tuple[AnyArray, AnyArray]
    snaps: list[tuple[int, AnyArray, AnyArray]] = field(default_factory=list)


@dataclass(frozen=True)
class BoardPlane:
    """The detected board: board frame -> left frame ``X = R @ X_board + t`` and how well it is known."""

    R: AnyArray
    t: AnyArray
    extent_m: tuple[float, float, float, float]   # checkered area in board coordinates: x0, x1, y0, y1
    reprojection_px: float                        # RMS corner reprojection error in the left image
    stereo_offset_mm: float | None = None      # right-image pose, at the board centre, off the left plane
    stereo_tilt_deg: float | None = None       # angle between the two poses' normals

    @property
    def center(self) -> AnyArray:
        """Centre of the checkered area [m, left frame]."""
        x0, x1, y0, y1 = self.extent_m
        return self.R @ np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0]) + self.t

    @property
    def normal(self) -> AnyArray:
        """Unit normal pointing towards the left camera (the sim study's sign: positive = in front)."""
        n = self.R[:, 2]
        return -n if float(n @ self.center) > 0 else n

    def on_board(self, xyz: AnyArray) -> AnyArray:
        """Mask of points over the checkered area and within `BACKGROUND_GATE_MM` of the plane."""
        local = (np.asarray(xyz, dtype=np.float64) - self.t) @ self.R
        x0, x1, y0, y1 = self.extent_m
        return ((local[:, 0] >= x0) & (local[:, 0] <= x1) & (local[:, 1] >= y0) & (local[:, 1] <= y1)
                & (np.abs(local[:, 2]) * 1000.0 <= BACKGROUND_GATE_MM))


def find_bags(root: Path | str) -> list[Path]:
    """The bag folders at or under ``root`` (a folder with metadata.yaml is a bag)."""
    root = Path(root)
    if not root.exists():
        raise AccuracyError(f"--bag {root}: no such folder; give a bag folder or a folder of scans "
                            f"(`lsu scan --record` writes <scan>/bag)")
    if (root / "metadata.yaml").is_file():
        return [root]
    bags = sorted(p.parent for p in root.rglob("metadata.yaml"))
    if not bags:
        raise AccuracyError(f"--bag {root}: no rosbag2 folder (metadata.yaml) in it; record board scans with "
                            f"`lsu scan --record`, one scan per board pose")
    return bags


def _suffix_topic(topics: dict[str, tuple[str, tuple]], suffix: str, msgtype: str) -> str | None:
    found = [t for t, (ty, _) in topics.items() if t.endswith(suffix) and ty == msgtype]
    return found[0] if found else None


def read_board_scans(bag: Path, skip: Callable[[str], None] | None = None) -> Iterator[BoardScan]:
    """The scans of one bag, one per ``scan_id`` with a TEXTURE pair and at least one SNAP pair.

    With ``skip``, a scan that cannot be used (no laser-off pair) is reported to it and the others
    still come; without, it raises.

    Raises:
        AccuracyError: a topic is missing, or a scan has no laser-off pair (what to record is said).
        lsu_bags.bags.BagError: the bag is missing, truncated or corrupt.
    """
    from lsu_bags.bags import BagTypes, bag_topics, deserialize, read_messages

    topics = bag_topics(bag)
    events = _suffix_topic(topics, "scan/events", "lsu_interfaces/msg/ScanEvent")
    images = {side: _suffix_topic(topics, f"stereo/{side}/image_raw", "sensor_msgs/msg/Image")
              for side in ("left", "right")}
    missing = [name for name, topic in (("scan/events", events), ("stereo/left/image_raw", images["left"]),
                                        ("stereo/right/image_raw", images["right"])) if topic is None]
    if missing:
        raise AccuracyError(f"bag {bag} has no {', '.join(missing)}: the board study needs the scan events and both "
                            f"cameras' images; record with `lsu scan --record` (it has: {', '.join(sorted(topics))})")
    types = BagTypes()
    scans: dict[str, dict] = {}
    assert events is not None  # else missing above
    for message in read_messages(bag, [events]):
        ev = deserialize(message, types)
        key = stamps.to_ns(ev.image_stamp)
        scan = scans.setdefault(ev.scan_id, {"texture": None, "snaps": {}})
        if ev.type == _TEXTURE:
            scan["texture"] = key
        elif ev.type == _SNAP:
            scan["snaps"][key] = int(ev.index)
    wanted = {key for s in scans.values() for key in [s["texture"], *s["snaps"]] if key is not None}
    frames: dict[tuple[str, int], AnyArray] = {}
    side_of = {topic: side for side, topic in images.items() if topic is not None}
    for message in read_messages(bag, list(side_of)):
        msg = deserialize(message, types)
        key = stamps.to_ns(msg.header.stamp)
        if key in wanted:
            frames[(side_of[message.topic], key)] = msg_to_array(msg).copy()
    folder = bag.name if bag.name != "bag" else bag.parent.name  # `lsu scan --record` writes <scan_id>/bag
    for scan_id, scan in scans.items():
        name = scan_id if folder == scan_id else f"{folder}:{scan_id}"
        problem = ""
        tex: tuple[AnyArray | None, AnyArray | None] = (None, None)
        if scan["texture"] is None:
            problem = (f"{name}: no laser-off (TEXTURE) pair, so the board cannot be detected; scan with texture on "
                       f"(the default of `lsu scan`)")
        else:
            tex = (frames.get(("left", scan["texture"])), frames.get(("right", scan["texture"])))
            if tex[0] is None or tex[1] is None:
                problem = f"{name}: the laser-off pair's images are not in the bag (the recording started late?)"
        if problem:
            if skip is None:
                raise AccuracyError(problem)
            skip(problem)
            continue
        pairs = [(index, frames[("left", key)], frames[("right", key)]) for key, index in sorted(scan["snaps"].items())
                 if ("left", key) in frames and ("right", key) in frames]
        left_tex, right_tex = tex
        assert left_tex is not None and right_tex is not None  # else a problem above
        if pairs:
            yield BoardScan(name, (left_tex, right_tex), pairs)


def _solve(image: AnyArray, board, K: AnyArray, D: AnyArray) -> tuple[AnyArray, AnyArray, float] | None:
    import cv2

    from lsu_cameras.calibration import find_board

    corners = find_board(image, board)
    if corners is None:
        return None
    obj = board.object_points.astype(np.float64)
    img = corners.reshape(-1, 2).astype(np.float64)
    # IPPE is made for planar targets (no flip ambiguity of the iterative solver); LM polishes it
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, D, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, D, rvec, tvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, D)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))
    return cv2.Rodrigues(rvec)[0], tvec.reshape(3), rms


def detect_board_plane(texture: tuple[AnyArray, AnyArray], model, board, name: str = "scan") -> BoardPlane:
    """The board's pose from the laser-off pair: solved in the left image, checked against the right one.

    Raises:
        AccuracyError: the board is not found in the left image (says which board was looked for).
    """
    left = _solve(texture[0], board, model.K1, model.D1)
    if left is None:
        raise AccuracyError(f"{name}: no {board.cols}x{board.rows} chessboard found in the laser-off left image; "
                            f"check --board/--square and that the whole board is in view and lit")
    R, t, rms = left
    s = board.square_m
    extent = (-s, board.cols * s, -s, board.rows * s)  # inner corners 0..cols-1 plus the outer squares
    plane = BoardPlane(R, t, extent, rms)
    right = _solve(texture[1], board, model.K2, model.D2)
    if right is None:
        return plane
    Rr, tr, _ = right
    # right camera frame -> left frame: X_left = R^T (X_right - T)
    R_in_left, t_in_left = model.R.T @ Rr, model.R.T @ (tr - model.T.reshape(3))
    other = BoardPlane(R_in_left, t_in_left, extent, 0.0)
    offset = float(abs((other.center - plane.center) @ plane.normal) * 1000.0)
    tilt = float(np.degrees(np.arccos(min(1.0, abs(float(other.normal @ plane.normal))))))
    return BoardPlane(R, t, extent, rms, offset, tilt)


def _pose_of(plane: BoardPlane) -> dict[str, float]:
    n, c = plane.normal, plane.center
    # the board's tilt seen from the left camera: yaw about its y axis, pitch about its x axis
    return {"distance_m": float(np.linalg.norm(c)), "yaw_deg": math.degrees(math.atan2(-n[0], -n[2])),
            "pitch_deg": math.degrees(math.atan2(-n[1], -n[2]))}


def run_bag_study(bag_dir: Path | str, calibration: Path | str, board,
                  progress: Callable[[str], None] = lambda s: None) -> dict:
    """The study on recorded board scans; returns the same JSON-ready dict as `accuracy.run_study`.

    The reference pose (the headline figures) is the scan nearest to 300 mm among those tilted
    less than 20 degrees from the left camera's axis (any scan if none is).
    """
    from lsu_faces.smoothing import SmoothParams
    from lsu_reconstruct.stereo import StereoModel

    t_start = time.perf_counter()
    model = StereoModel.from_folder(calibration)
    per_pose: list[dict] = []
    pooled_z: dict[str, list[AnyArray]] = {c.name: [] for c in CHAINS}
    meshes_of: list[dict[str, tuple]] = []
    skipped: list[str] = []  # one unusable scan (board out of view, a head scan in the folder) loses only itself

    def measure(scan: BoardScan) -> None:
        t0 = time.perf_counter()
        h, w = scan.texture[0].shape[:2]
        model.check_image_size(w, h, f"{scan.name} images")
        plane = detect_board_plane(scan.texture, model, board, scan.name)
        runner = ChainRunner(model)
        for index, left, right in scan.snaps:
            runner.add_pair(left, right, index)
        pose = _pose_of(plane)
        label = f"{scan.name} ({pose['distance_m'] * 1000:.0f} mm, yaw {pose['yaw_deg']:+.0f}, " \
                f"pitch {pose['pitch_deg']:+.0f})"
        stats, z, meshes = evaluate_pose(runner.scans(), plane.center, plane.normal, label,
                                         hint="is the laser on the board in these snaps (scan range) and is "
                                              "the calibration the rig's?", keep=plane.on_board)
        truth = {"reprojection_px": plane.reprojection_px, "stereo_offset_mm": plane.stereo_offset_mm,
                 "stereo_tilt_deg": plane.stereo_tilt_deg}
        per_pose.append({"pose": pose, "label": label, "truth": truth, **stats})
        for name, zs in z.items():
            pooled_z[name].append(zs)
        meshes_of.append(meshes)
        progress(f"{label}: ours sigma {stats['ours']['raw']['sigma_mm']:.3f} mm, thesis sigma "
                 f"{stats['thesis']['raw']['sigma_mm']:.3f} mm; board reprojection {plane.reprojection_px:.3f} px"
                 f" ({time.perf_counter() - t0:.0f} s)")

    def skip(reason: str) -> None:
        skipped.append(reason)
        progress(f"skipped: {reason}")

    for bag in find_bags(bag_dir):
        try:
            for scan in read_board_scans(bag, skip):
                try:
                    measure(scan)
                except (AccuracyError, ValueError) as exc:
                    skip(str(exc))
        except (AccuracyError, ValueError) as exc:  # the whole bag: missing topics, truncated file
            skip(str(exc))
    if len(per_pose) < 2:
        why = "; ".join(skipped) if skipped else "no scan with a laser-off pair and laser snaps"
        raise AccuracyError(f"--bag {bag_dir}: {len(per_pose)} usable board scan(s), the error-against-distance fit "
                            f"needs >= 2 poses at different distances (the thesis-style study uses >= 8). "
                            f"Skipped: {why}")

    def tilt(p: dict) -> float:
        return math.hypot(p["pose"]["yaw_deg"], p["pose"]["pitch_deg"])

    candidates = [i for i, p in enumerate(per_pose) if tilt(p) < 20.0] or list(range(len(per_pose)))
    ref_index = min(candidates, key=lambda i: abs(per_pose[i]["pose"]["distance_m"] - 0.30))
    result: dict = {"source": "bag", "truth": "the board plane detected in each scan's laser-off left image",
                    "config": {"bag": str(bag_dir), "board": f"{board.cols}x{board.rows}",
                               "square_mm": board.square_m * 1000.0, "calibration": str(calibration),
                               "background_gate_mm": BACKGROUND_GATE_MM},
                    "skipped": skipped,
                    "calibration": str(calibration), "chains": {c.name: c.description for c in CHAINS},
                    "default_smoothing": asdict(SmoothParams())}
    summarise(result, per_pose, pooled_z, ref_index, meshes_of[ref_index])
    offsets = [p["truth"]["stereo_offset_mm"] for p in per_pose if p["truth"]["stereo_offset_mm"] is not None]
    result["figures"].update({
        "reference_distance_mm": per_pose[ref_index]["pose"]["distance_m"] * 1000.0,
        "truth_reprojection_px_max": max(p["truth"]["reprojection_px"] for p in per_pose),
        "truth_stereo_offset_mm_max": max(offsets) if offsets else float("nan"),
    })
    result["seconds"] = time.perf_counter() - t_start
    return result


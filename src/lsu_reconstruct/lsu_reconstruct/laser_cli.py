"""`lsu calibrate --laser SCANS... -o DIR`: the laser's light sheet from scans of a flat board or wall.

    lsu calibrate --laser scans/board-26cm scans/board-30cm scans/board-34cm -o config/calibration/lab

Each SCAN is a scan folder (``scan.json`` + ``cloud.ply``, as `lsu scan` writes them; a folder
whose cloud is missing is reconstructed from its ``bag/``) or a bag of one. The points of each
snap and the carriage position of that snap (``scan.json`` snaps, or the bag's SNAP events) go
to `fit_laser_sheet`; ``laser.yaml`` is written into DIR beside left/right/stereo.yaml, the
calibration the scans were made with (the sheet is in its left optical frame: scans whose
``scan.json`` names another calibration are refused).

The option is added to lsu_cameras' ``calibrate`` command from this package's own ``lsu.commands``
entry point, so that lsu_cameras (stereo calibration) never imports lsu_reconstruct.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lsu_common.arrays import AnyArray

from .laser_sheet import LaserSheet, LaserSheetError, fit_laser_sheet, write_laser_yaml

__all__ = ["ScanPoints", "ScanResidual", "load_scan", "calibrate_laser", "register_laser", "MIN_POSITIONS",
           "MAX_FLAT_RMS_MM"]

MIN_POSITIONS = 3       # carriage positions per scan: fewer cannot show the sheet's motion on that target
MAX_FLAT_RMS_MM = 1.5   # a "board" whose points are farther than this (RMS) from their best plane is not flat
MIN_SCANS = 2           # a single flat target fits its own plane as well as the sheet


@dataclass
class ScanPoints:
    """One scan's triangulated points (left optical frame, metres) and each point's carriage position."""

    name: str
    xyz: AnyArray
    position_steps: AnyArray
    calibration: str | None  # scan.json's calibration id; None when unknown (a bare bag, no calibration_dir)


@dataclass(frozen=True)
class ScanResidual:
    """How far one scan's points lie from the fitted sheet, and from their own best plane."""

    name: str
    points: int
    positions: int
    rms_mm: float
    max_mm: float
    flatness_rms_mm: float


def _read_cloud_ply(path: Path) -> dict[str, AnyArray]:
    """Columns x y z and snap of a scan's cloud.ply (lsu_bags.ply.write_cloud_ply)."""
    from lsu_bags.ply import PlyError, read_ply

    try:
        vertices, _faces = read_ply(path)
    except (PlyError, OSError, ValueError) as exc:
        raise LaserSheetError(f"{path} cannot be read as a PLY cloud ({exc})") from None
    if not {"x", "y", "z", "snap"} <= set(vertices):
        raise LaserSheetError(f"{path} is not an LSU scan cloud (x y z ... snap): give the scan's folder or its bag "
                              "instead")
    return {name: vertices[name] for name in ("x", "y", "z", "snap")}


def _bag_positions(bag: Path) -> dict[int, int]:
    """Snap index -> carriage position from a bag's SNAP scan events."""
    from lsu_bags.bags import BagTypes, bag_topics, deserialize, read_messages

    from .bag_lines import EVENT_TYPE

    topics = [t for t, (msgtype, _qos) in bag_topics(bag).items() if t.endswith("scan/events") and msgtype == EVENT_TYPE]
    out: dict[int, int] = {}
    if not topics:
        return out
    types = BagTypes()
    for message in read_messages(bag, topics):
        msg = deserialize(message, types)
        if msg.type == 2:  # SNAP
            out[int(msg.index)] = int(msg.position_steps)
    return out


def load_scan(path: str | Path, calib_dir: str | Path) -> ScanPoints:
    """Points and positions of one scan folder (cloud.ply + scan.json, or its bag) or bag."""
    path = Path(path)
    if not path.exists():
        raise LaserSheetError(f"{path}: no such scan folder or bag")
    record: dict[str, Any] = {}
    folder = path if (path / "scan.json").is_file() else path.parent
    if (folder / "scan.json").is_file():
        try:
            record = json.loads((folder / "scan.json").read_text())
        except (OSError, ValueError) as exc:
            raise LaserSheetError(f"{folder / 'scan.json'} cannot be read ({exc})") from None
    positions = {int(s["index"]): int(s["position_steps"]) for s in record.get("snaps", [])
                 if "index" in s and "position_steps" in s}
    # "none": the coordinator had no calibration_dir, so the scan cannot say which calibration it used
    calibration = record.get("calibration") if record.get("calibration") not in (None, "", "none") else None
    cloud = path / "cloud.ply"
    if path.is_dir() and cloud.is_file():
        if not record:
            raise LaserSheetError(f"{path}: cloud.ply without scan.json (the snaps' carriage positions are there)")
        c = _read_cloud_ply(cloud)
        xyz = np.stack([c["x"], c["y"], c["z"]], axis=1).astype(np.float64)
        snaps = c["snap"].astype(np.int64)
    else:
        bag = path / "bag" if (path / "bag").is_dir() else path
        from .bag_lines import read_bag
        from .matching import MatchParams
        from .pipeline import merge_snaps, reconstruct_snap
        from .stereo import StereoModel

        try:
            pairs, _texture, _counts = read_bag(bag)
        except (FileNotFoundError, ValueError) as exc:
            raise LaserSheetError(f"{path}: neither cloud.ply + scan.json nor a readable bag ({exc})") from None
        if not positions:
            positions = _bag_positions(bag)
        model = StereoModel.from_folder(calib_dir)
        merged = merge_snaps([reconstruct_snap(model, left, right, MatchParams(), snap=snap)
                              for snap, _, left, right in pairs])
        xyz, snaps = np.asarray(merged.xyz, np.float64), np.asarray(merged.snap, np.int64)
    missing = sorted(set(np.unique(snaps).tolist()) - set(positions))
    if missing:
        raise LaserSheetError(f"{path}: no carriage position for snap(s) {missing[:5]}"
                              f"{' ...' if len(missing) > 5 else ''} (scan.json snaps or the bag's SNAP events)")
    pos = np.array([positions[int(s)] for s in snaps], np.float64) if len(snaps) else np.zeros(0)
    return ScanPoints(path.name if path.name not in ("", ".") else str(path), xyz, pos, calibration)


def _flatness_rms_mm(xyz: AnyArray) -> float:
    """RMS distance of the points to their own least-squares plane [mm], after trimming 1 % strays."""
    if len(xyz) < 3:
        return float("nan")
    centred = xyz - xyz.mean(axis=0)
    normal = np.linalg.svd(centred, full_matrices=False)[2][2]
    d = np.abs(centred @ normal)
    d = d[d <= np.quantile(d, 0.99)]
    return float(np.sqrt(np.mean(d ** 2)) * 1000.0)


def calibrate_laser(scans: Sequence[str | Path], calib_dir: str | Path) -> tuple[LaserSheet, list[ScanResidual]]:
    """Fit the sheet to the scans of flat targets; LaserSheetError says which scan is unusable and why."""
    from lsu_cameras.calib_io import calibration_checksum

    calib_dir = Path(calib_dir)
    ours = calibration_checksum(calib_dir)
    if not ours:
        raise LaserSheetError(f"{calib_dir} holds no left.yaml/right.yaml/stereo.yaml: give -o the stereo "
                              "calibration the scans were made with (laser.yaml goes beside it)")
    if len(scans) < MIN_SCANS:
        raise LaserSheetError(f"{len(scans)} scan given: scan a flat board or wall at {MIN_SCANS} or more distances "
                              "(or tilts) and give every scan")
    loaded = [load_scan(s, calib_dir) for s in scans]
    flatness = []
    for scan in loaded:
        if scan.calibration is not None and scan.calibration != ours:
            raise LaserSheetError(f"{scan.name}: made with calibration {scan.calibration}, not with {calib_dir} "
                                  f"({ours}): scan again with this calibration, or give -o the scans' calibration")
        count = len(np.unique(scan.position_steps))
        if count < MIN_POSITIONS:
            raise LaserSheetError(f"{scan.name}: points from {count} carriage position(s); at least {MIN_POSITIONS} "
                                  "are needed: scan across the board (e.g. --start 150 --end 330 --step 10)")
        flat = _flatness_rms_mm(scan.xyz)
        if not flat <= MAX_FLAT_RMS_MM:
            raise LaserSheetError(f"{scan.name}: not a flat target: its points are {flat:.2f} mm (RMS) from their "
                                  f"best plane (at most {MAX_FLAT_RMS_MM:g} mm): scan a flat board or wall")
        flatness.append(flat)
    sheet = fit_laser_sheet(np.concatenate([s.xyz for s in loaded]),
                            np.concatenate([s.position_steps for s in loaded]))
    report = []
    for scan, flat in zip(loaded, flatness):
        d = np.abs(sheet.distance_m(scan.xyz, scan.position_steps)) * 1000.0
        # the same trimming as the fit: strays beyond 4 robust sigmas are not the sheet's residual
        kept = d[d <= max(4.0 * 1.4826 * np.median(d), 1e-6)] if len(d) else d
        report.append(ScanResidual(scan.name, len(scan.xyz), len(np.unique(scan.position_steps)),
                                   float(np.sqrt(np.mean(kept ** 2))) if len(kept) else float("nan"),
                                   float(kept.max()) if len(kept) else float("nan"), flat))
    return sheet, report


def cmd_calibrate_laser(args: argparse.Namespace) -> int:
    """Fit, print the residuals, write laser.yaml (nothing written on a refusal)."""
    try:
        sheet, report = calibrate_laser(args.laser, args.output)
    except LaserSheetError as exc:
        print(f"lsu calibrate --laser: error: {exc}", file=sys.stderr)
        return 2
    path = write_laser_yaml(sheet, Path(args.output) / "laser.yaml")
    n = sheet.normal
    print(f"laser sheet: normal ({n[0]:.5f}, {n[1]:.5f}, {n[2]:.5f}), {sheet.c0_m * 1000:.3f} mm + "
          f"{sheet.m_per_step * 1e6:.3f} um/step, positions {sheet.positions[0]}..{sheet.positions[1]}")
    print(f"residual: RMS {sheet.residual_mm:.3f} mm over {sheet.points} points ({sheet.rejected} trimmed), max "
          f"{max(r.max_mm for r in report):.3f} mm")
    for r in report:
        print(f"  {r.name}: {r.points} points, {r.positions} positions, RMS {r.rms_mm:.3f} mm, max {r.max_mm:.3f} mm "
              f"(flatness {r.flatness_rms_mm:.3f} mm)")
    print(f"wrote {path}")
    return 0


# the simulated rig's calibration targets: three flat boards, at the near and far end of the working range
# and at the subject distance, two of them tilted (the sheet is then fixed by more than depth)
SIM_BOARDS = ((0.26, 10.0), (0.30, 0.0), (0.34, -15.0))   # (distance [m], yaw about the vertical [deg])
SIM_POSITIONS = tuple(range(150, 331, 20))


def _write_line_bag(path: Path, lines: Sequence[tuple[Any, Any]], positions: Sequence[int]) -> Path:
    """A bag as a recording scan holds it, for what this command reads: laser lines and SNAP events."""
    from lsu_bags.bags import BagTypes, BagWriter

    from .bag_lines import EVENT_TYPE, LINE_TYPE

    types = BagTypes()
    for msgtype in (EVENT_TYPE, LINE_TYPE):
        types.ensure(msgtype)
    store = types.typestore
    T = store.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    with BagWriter(path, "sqlite3", types=types) as writer:
        conns = {side: f"/lsu/stereo/{side}/laser_line" for side in ("left", "right")}
        events = "/lsu/scan/events"
        for topic, msgtype in ((conns["left"], LINE_TYPE), (conns["right"], LINE_TYPE), (events, EVENT_TYPE)):
            writer.add_topic(topic, msgtype)
        for index, (pair, position) in enumerate(zip(lines, positions)):
            stamp = Time(sec=1_800_000_000 + index, nanosec=0)
            t = (1_800_000_000 + index) * 1_000_000_000
            event = T[EVENT_TYPE](header=Header(stamp=stamp, frame_id=""), type=2, scan_id="sim-board",
                                  expected_snaps=len(positions), index=index, position_steps=int(position),
                                  image_stamp=stamp, snaps_captured=0, partial=False, reason="", output_dir="")
            writer.write(events, t, store.serialize_cdr(event, EVENT_TYPE))
            for side, line in zip(("left", "right"), pair):
                msg = T[LINE_TYPE](header=Header(stamp=stamp, frame_id=f"lsu_{side}_optical"),
                                   image_width=line.image_width, image_height=line.image_height, method="sim",
                                   u=np.asarray(line.u, np.float32), v=np.asarray(line.v, np.float32),
                                   peak=np.asarray(line.peak, np.float32), width=np.asarray(line.width, np.float32),
                                   quality=np.asarray(line.quality, np.float32), rows_searched=line.image_height,
                                   rows_ambiguous=0, rows_saturated=0)
                writer.write(conns[side], t + 1, store.serialize_cdr(msg, LINE_TYPE))
    return path


def simulate_board_scans(out: str | Path, calib_dir: str | Path, boards: Sequence[tuple[float, float]] = SIM_BOARDS,
                         positions: Sequence[int] = SIM_POSITIONS, seed: int = 0, bags: bool = False) -> list[Path]:
    """Scan folders (cloud.ply + scan.json) of flat boards seen by the simulated rig: rendered frames, the
    extractor's lines and this package's matcher, as the live graph makes them (no carriage vibration).

    ``calib_dir`` is the calibration the matcher uses and the scans name (e.g. config/calibration/sim).
    With ``bags`` each scan is a bare bag of the laser lines and SNAP events instead (no scan.json).
    """
    from lsu_bags.ply import write_cloud_ply
    from lsu_cameras.calib_io import calibration_checksum
    from lsu_extract.extractor import extract_laser_line
    from lsu_sim import SimulatedRig, load_rig, make_plane

    from .matching import LineArrays
    from .pipeline import merge_snaps, reconstruct_snap
    from .stereo import StereoModel

    geometry = load_rig()
    model = StereoModel.from_folder(calib_dir)
    checksum = calibration_checksum(calib_dir)
    axes = geometry.rig_axes
    folders = []
    for k, (distance, yaw_deg) in enumerate(boards):
        yaw = np.radians(yaw_deg)
        normal = -(np.cos(yaw) * axes[2] + np.sin(yaw) * axes[0])
        board = make_plane(geometry.rig_center + distance * axes[2], normal, name="board")
        rig = SimulatedRig(geometry, [board], seed=seed + k)
        snaps, records, pairs = [], [], []
        for index, position in enumerate(positions):
            frame = rig.render(float(position), seed=seed + 1000 * k + index)
            lines = []
            for image in (frame.left, frame.right):
                r = extract_laser_line(image)
                lines.append(LineArrays(r.u, r.v, r.peak, r.width, r.quality, r.image_width, r.image_height))
            pairs.append((lines[0], lines[1]))
            snaps.append(reconstruct_snap(model, lines[0], lines[1], snap=index))
            records.append({"index": index, "position_steps": int(position)})
        folder = Path(out) / f"board-{round(distance * 1000)}mm-yaw{yaw_deg:+.0f}"
        if bags:
            folder.parent.mkdir(parents=True, exist_ok=True)
            folders.append(_write_line_bag(folder, pairs, positions))
            continue
        folder.mkdir(parents=True, exist_ok=True)
        write_cloud_ply(folder / "cloud.ply", merge_snaps(snaps).fields(), comment="simulated flat board")
        (folder / "scan.json").write_text(json.dumps(
            {"scan_id": folder.name, "label": f"simulated flat board at {distance * 1000:.0f} mm, yaw {yaw_deg:g} deg",
             "calibration": checksum, "snaps": records}, indent=2) + "\n")
        folders.append(folder)
    return folders


def register_laser(subparsers: Any) -> None:
    """Add ``--laser SCANS...`` to `lsu calibrate` (lsu_cameras registers it first: entry points load by name)."""
    calibrate = subparsers.choices.get("calibrate")
    if calibrate is None:  # without lsu_cameras: a calibrate command that only calibrates the sheet
        calibrate = subparsers.add_parser("calibrate", help="laser sheet calibration from scans of a flat board")
        calibrate.add_argument("-o", "--output", default="calibration", help="calibration folder")
    stereo = calibrate.get_default("func")
    calibrate.description = ((calibrate.description or "") + " With --laser SCAN...: the laser's light sheet from "
                             "scans of a flat board at 2+ distances -> laser.yaml in -o DIR.").strip()
    calibrate.add_argument("--laser", nargs="+", metavar="SCAN",
                           help="laser sheet calibration instead: scan folders (scan.json + cloud.ply, or bag/) or "
                                "bags of a flat board/wall at 2+ distances, made with the calibration in -o DIR; "
                                "writes DIR/laser.yaml and prints the residual")

    def run(args: argparse.Namespace) -> int:
        if getattr(args, "laser", None):
            return cmd_calibrate_laser(args)
        if stereo is None:
            print("lsu calibrate: error: give --laser SCAN... (stereo calibration needs lsu_cameras)", file=sys.stderr)
            return 2
        return stereo(args)

    calibrate.set_defaults(func=run)


def main(argv: list[str] | None = None) -> int:
    """``python -m lsu_reconstruct.laser_cli sim-boards OUT [--calib DIR]``: the simulated board scans."""
    parser = argparse.ArgumentParser(prog="python -m lsu_reconstruct.laser_cli",
                                     description="Write scan folders of flat boards seen by the simulated rig, for "
                                                 "`lsu calibrate --laser OUT/* -o DIR`.")
    parser.add_argument("what", choices=["sim-boards"])
    parser.add_argument("out", help="folder for the scan folders")
    parser.add_argument("--calib", default="config/calibration/sim", help="calibration the matcher uses")
    args = parser.parse_args(argv)
    for folder in simulate_board_scans(args.out, args.calib):
        print(folder)
    return 0


if __name__ == "__main__":
    sys.exit(main())

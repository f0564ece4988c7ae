"""`lsu demo` (what `make demo` runs): the whole graph on the emulated unit, one full scan, a report.

1. claims a ROS domain of its own (localhost only) and starts `lsu launch sim` (GP32 emulator,
   driver, simulated cameras looking at a realistic simulated person, extractor, matcher, face processor,
   scan coordinator) as separate processes;
2. runs a full scan through the `/lsu/scan` action with a bag recorded (``--mode``: a sweep, the
   default since it meets its targets (the carriage at a constant rate while the cameras free-run),
   or stop-snap: stop, settle and capture per line);
3. measures the cloud against the renderer's geometry (distance of every point to the true
   surface of the person: truth from the simulator, not from the code under test);
4. stops everything and prints where the files are.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from lsu_scan import rosenv

# what the demo scans: a realistic person of the simulator (lsu_sim.people: MakeHuman's head, neck and shoulders
# with seed 2's identity and hair)
DEMO_SCENE = "person:2"


def accuracy_against_scene(cloud_ply: Path, scene: str) -> dict[str, float]:
    """Point-to-surface distances [mm] between a cloud and the simulated scene's meshes."""
    import numpy as np
    import open3d as o3d

    from lsu_accuracy.accuracy import surface_distances_m
    from lsu_sim import build_scene, load_rig

    cloud = o3d.io.read_point_cloud(str(cloud_ply))
    points = np.asarray(cloud.points, dtype=np.float32)
    if len(points) == 0:
        return {}
    distance_mm = surface_distances_m(build_scene(scene, load_rig()), points) * 1000.0
    return {"points": float(len(points)), "median_mm": float(np.median(distance_mm)),
            "rms_mm": float(np.sqrt(np.mean(distance_mm ** 2))), "p95_mm": float(np.percentile(distance_mm, 95)),
            "within_0.1mm_pct": float(100.0 * np.mean(distance_mm <= 0.1))}


def cmd_demo(args: argparse.Namespace) -> int:
    from lsu_scan.scanner import LsuScanner, ScannerError

    from .processes import LaunchedProcess

    claim = rosenv.isolate()
    out = Path(args.out or "scans").resolve()
    print(f"[demo] DDS: localhost only, ROS_DOMAIN_ID={claim.domain_id} (claimed for this run)")
    with tempfile.TemporaryDirectory(prefix="lsu-demo-") as tmp:
        port = str(Path(tmp) / "gp32")
        graph = LaunchedProcess(["launch", "sim", f"port:={port}", f"scene:={args.scene}", f"output_dir:={out}"])
        print(f"[demo] starting the sim graph (lsu launch sim scene:={args.scene}); node logs: {Path(tmp) / 'graph.log'}")
        scanner = None
        try:
            scanner = LsuScanner(wait_s=60)
            # the scan also needs the cameras: on a loaded host the camera node (which builds the scene) can
            # come up well after the driver homed, later than the scan coordinator waits for it
            from lsu_interfaces.srv import CaptureStereo

            camera = scanner.node.create_client(CaptureStereo, "stereo/capture")
            t0 = time.monotonic()
            while True:
                try:
                    if scanner.state(timeout_s=1.0).homed and camera.service_is_ready():
                        break
                except ScannerError:
                    pass  # the driver is still starting
                if graph.process.poll() is not None or time.monotonic() - t0 > 90:
                    raise ScannerError("the graph did not come up (driver not homed, or the cameras not serving "
                                       "stereo/capture, within 90 s); see the log above")
            how = (f"step {args.step} (settle {args.settle} s)" if args.mode == "stopsnap" else
                   f"sweeping at {args.rate:g} steps/s, {args.fps:g} fps")
            print(f"[demo] graph up (carriage homed, cameras serving) after {time.monotonic() - t0:.1f} s; scanning "
                  f"{args.start}..{args.end} {how}, recording a bag")
            last = [-1]
            unit = "snap" if args.mode == "stopsnap" else "frame"

            def progress(fb) -> None:
                if fb.snap_index // 25 != last[0]:
                    last[0] = fb.snap_index // 25
                    print(f"[demo]   {unit} {fb.snap_index}/{fb.snaps_total} at {fb.position_steps} steps, "
                          f"{fb.points_so_far} points, ETA {fb.eta_s:.0f} s", flush=True)

            result = scanner.scan(feedback=progress, start=args.start, end=args.end, step=args.step,
                                  settle_s=args.settle, record_bag=True, label="make demo", mode=args.mode,
                                  sweep_rate_steps_s=args.rate, frame_rate_hz=args.fps)
            mesh = Path(result.output_dir) / "mesh.ply"
            deadline = time.monotonic() + 60.0  # face_processor meshes and renders the cloud after the scan
            while result.points and not mesh.is_file() and time.monotonic() < deadline:
                time.sleep(0.2)
            seen, stable_since = -1, time.monotonic()
            while mesh.is_file() and time.monotonic() - stable_since < 3.0 and time.monotonic() < deadline:
                count = sum(1 for _ in mesh.parent.glob("*"))  # renders follow the mesh: wait until files settle
                if count != seen:
                    seen, stable_since = count, time.monotonic()
                time.sleep(0.2)
            if not mesh.is_file():
                print("[demo]   no mesh.ply from face_processor within 60 s (see the graph log)")
        except ScannerError as exc:
            print(f"[demo] FAILED: {exc}")
            print("\n".join(graph.lines[-40:]))
            return 1
        finally:
            if scanner is not None:
                scanner.close()
            code = graph.stop(timeout_s=20)
            (Path(tmp) / "graph.log").write_text(graph.output)
            claim.release()
    folder = Path(result.output_dir)
    print(f"[demo] scan {result.scan_id}: {result.status}")
    print(f"[demo]   {result.snaps} {'snaps' if args.mode == 'stopsnap' else 'frames'}, {result.points} points in "
          f"{result.seconds:.1f} s")
    record = json.loads((folder / "scan.json").read_text()) if (folder / "scan.json").is_file() else {}
    bound = record.get("timings_s", {}).get("mechanical_lower_bound")
    if bound:
        print(f"[demo]   mechanical lower bound {bound:.1f} s (moves + settle + exposure): "
              f"wall/mechanical = {result.seconds / bound:.2f}")
    cloud = folder / "cloud.ply"
    if cloud.is_file():
        acc = accuracy_against_scene(cloud, args.scene)
        if acc:
            print(f"[demo]   accuracy against the simulator's true surface: median {acc['median_mm']:.3f} mm, "
                  f"RMS {acc['rms_mm']:.3f} mm, 95 % within {acc['p95_mm']:.3f} mm, "
                  f"{acc['within_0.1mm_pct']:.1f} % of points within 0.1 mm")
            record.setdefault("demo", {})["accuracy_vs_truth"] = acc
            (folder / "scan.json").write_text(json.dumps(record, indent=2) + "\n")
    files: list[str] = sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())
    print(f"[demo] files in {folder}:")
    for name in files:
        print(f"[demo]   {name}")
    print(f"[demo] graph stopped (lsu launch exit code {code}); the laser is off (driver shutdown + watchdog).")
    print("[demo] the same in a web page: `lsu launch sim web:=true`, then open http://127.0.0.1:8080/ (README 'The web page')")
    return 0 if result.success and code == 0 else 1


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `demo` to the `lsu` parser."""
    p = sub.add_parser("demo", help="start the sim graph, run a full scan, report accuracy and files (make demo)")
    p.add_argument("--scene", default=DEMO_SCENE, help=f"sim scene (default {DEMO_SCENE}: a realistic person with hair, "
                   f"neck and shoulders; head:7 is the procedural head; see `lsu render --help`)")
    p.add_argument("--start", type=int, default=0)
    p.add_argument("--end", type=int, default=470)
    p.add_argument("--step", type=int, default=2)
    p.add_argument("--settle", type=float, default=0.1, help="stop-snap: settle after each stop [s]")
    p.add_argument("--mode", choices=("stopsnap", "sweep"), default="sweep",
                   help="sweep (constant rate, free-running cameras; the default) or stopsnap (stop, settle, "
                        "capture per line)")
    p.add_argument("--rate", type=float, default=60.0, help="sweep: carriage rate [steps/s], at most 180")
    p.add_argument("--fps", type=float, default=30.0, help="sweep: camera frame rate [frames/s]")
    p.add_argument("--out", default="", help="parent folder of the scan folder (default scans/ in the current directory)")
    p.set_defaults(func=cmd_demo)



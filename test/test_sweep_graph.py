"""A sweep scan through the whole sim graph (separate processes), its bag replayed to the same cloud, and a cancel.

Truth: the rendered plane's geometry (the scene the camera renders), the stream's slots (stamped
t0 + k / fps, none skipped) against scan.json's frame accounting, the cloud recorded live against
the replayed ones, and the emulator's ground truth (/lsu/sim/truth) after a cancel. The rig's right
camera exposes 50 ms after the left (the thesis' worst case): the exposures never overlap, so each left
line is matched to the right lines exposed around it (the first two: the two after them).
"""

import json
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2

from lsu_bags.bags import deserialize_ros, read_messages
from lsu_bags.pointcloud2 import decode, from_msg
from lsu_common import qos, stamps
from lsu_common.arrays import AnyArray
from lsu_interfaces.msg import SimTruth
from lsu_scan.scanner import LsuScanner
from lsu_testing.plugin import LSU, REPLAY_GRAPH_READERS, LaunchedProcess

pytestmark = pytest.mark.slow
REPLAYED = ["/lsu/scan/events", "/lsu/stereo/left/image_raw", "/lsu/stereo/right/image_raw", "/lsu/stereo/exposure",
            "/lsu/driver/carriage"]
OFFSET_S = 0.05  # the right camera's exposure start after the left's
START, END, RATE, FPS = 220, 238, 60.0, 30.0  # the plane's line seen by both cameras beyond the sheet's grazing limit
FRAMES = 10  # 18 steps at 60 steps/s: 0.3 s at 30 fps, both ends


def xyz(msg: PointCloud2) -> AnyArray:
    columns = decode(from_msg(msg))
    return np.stack([columns["x"], columns["y"], columns["z"]], axis=1)


def by_frame(msg: PointCloud2) -> dict[int, AnyArray]:
    """A scan cloud's points per frame index."""
    columns = decode(from_msg(msg))
    points = np.stack([columns["x"], columns["y"], columns["z"]], axis=1)
    return {int(i): points[columns["snap"] == i] for i in np.unique(columns["snap"])}


def same_frames(replayed: PointCloud2, live: PointCloud2) -> None:
    """The replay gives every frame's points exactly as recorded live (the stream waits for its readers:
    the recorder and the live graph hold the same frames)."""
    got, want = by_frame(replayed), by_frame(live)
    assert sorted(got) == sorted(want) == list(range(FRAMES))
    for index in want:
        assert got[index].shape == want[index].shape and np.max(np.abs(got[index] - want[index])) <= 1e-9, index


def timeline(bag: Path) -> str:
    """The bag's carriage reports, exposures and events around the sweep, in stamp order (for a failure's message)."""
    rows = []
    for msg in (deserialize_ros(m) for m in read_messages(bag, ["/lsu/driver/carriage", "/lsu/stereo/exposure",
                                                                  "/lsu/scan/events"])):
        stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9 if hasattr(msg, "header") else float("nan")
        rows.append((stamp, type(msg).__name__, {k: getattr(msg, k) for k in msg.get_fields_and_field_types()
                                                 if k != "header"}))
    rows.sort(key=lambda r: r[0])
    return "\n".join(f"{t:.4f} {name} {fields}" for t, name, fields in rows[:80])


def late_right_camera_rig(folder: Path) -> Path:
    """The packaged sim rig with the right camera exposing ``OFFSET_S`` after the left."""
    from lsu_sim.geometry import default_rig_path

    text = default_rig_path().read_text()
    assert "capture_offset_s: 0.0 " in text
    path = folder / "rig_late_right.yaml"
    path.write_text(text.replace("capture_offset_s: 0.0 ", f"capture_offset_s: {OFFSET_S} "))
    return path


def test_sweep_scan_with_a_50ms_capture_offset_its_replays_and_a_cancel(tmp_path, ros_context, ros_node):
    from lsu_accuracy.accuracy import surface_distances_m
    from lsu_sim import build_scene, load_rig

    port = str(tmp_path / "gp32")
    rig = late_right_camera_rig(tmp_path)
    diagnostics: list = []
    truths: list[SimTruth] = []
    ros_node.node.create_subscription(DiagnosticArray, "/diagnostics", diagnostics.append, 10)
    ros_node.node.create_subscription(SimTruth, "/lsu/sim/truth", truths.append, qos.STATE)
    graph = LaunchedProcess(["launch", "sim", f"port:={port}", "scene:=plane", f"rig:={rig}",
                             f"output_dir:={tmp_path / 'scans'}"])
    try:
        graph.wait_for_line(r"\[gp32_driver\].*homed: track 470", timeout_s=60)
        graph.wait_for_line(r"\[stereo_camera\].*source 'sim' open", timeout_s=60)
        with LsuScanner(wait_s=30) as scanner:
            refused = scanner.scan(start=START, end=END, mode="sweep", sweep_rate_steps_s=200.0)
            assert not refused.success and "sweep_rate_steps_s" in refused.status and "180" in refused.status
            # the camera renders each frame from the emulator's truth sample that held at its exposure:
            # the emulator sends one at the motion's start and stop, stamped when they happened
            scanner.move_to(START)
            result = scanner.scan(start=START, end=END, mode="sweep", sweep_rate_steps_s=RATE, frame_rate_hz=FPS,
                                  record_bag=True, output_dir=str(tmp_path / "scans"))

            def sweep_counts() -> dict:
                return {v.key: v.value for d in diagnostics for s in d.status
                        if s.name.endswith("stereo_matcher: stereo matching") for v in s.values}

            ros_node.spin_until(lambda: "sweep_no_position" in sweep_counts(), 5.0)  # the sweep ended
            values = sweep_counts()
            # a cancel mid-sweep stops the carriage where it is, and the laser
            scanner.start_scan(start=250, end=470, mode="sweep", sweep_rate_steps_s=20.0, frame_rate_hz=30.0,
                               output_dir=str(tmp_path / "scans"))
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline:
                fb = scanner.get_feedback()
                if fb is not None and fb.stage == "sweeping" and fb.snap_index >= 3:
                    break
                time.sleep(0.05)
            scanner.cancel_task()
            canceled = scanner.get_result(timeout_s=60)
            ros_node.spin_until(lambda: False, 1.0)
    finally:
        graph.stop(timeout_s=15)
    assert result.success, result.status + graph.output[-3000:]
    record = json.loads((Path(result.output_dir) / "scan.json").read_text())
    sweep = record["sweep"]
    assert sweep["frames_expected"] == FRAMES
    # the stream never skips a slot, waits for its readers, and the matcher gave points for every frame
    assert sweep["frames_captured"] == sweep["camera_frames_published"] == FRAMES == result.snaps
    assert sweep["frames_not_published"] == sweep["camera_frames_dropped"] == 0
    assert sweep["frames_dropped"] == sweep["frames_not_processed"] == 0 and sweep["frames_processed"] == FRAMES
    assert record["snaps_acknowledged"] == FRAMES
    # every frame matched across frames, the first ones too (no frame placed by the sheet alone: a carriage
    # stamp off by the device clock's mapping error would put it ~1 mm off the plane on a busy host)
    assert int(values["sweep_cross_stereo"]) > 0, values
    assert int(values["sweep_left_sheet"]) == int(values["sweep_right_sheet"]) == 0, values
    assert sweep["laser_sheet"] == "each camera's line on the laser sheet"
    assert int(values["sweep_no_position"]) == int(values["sweep_no_carriage_position"]) == int(values["sweep_stereo"]) == 0
    recorded = [deserialize_ros(m) for m in read_messages(Path(result.output_dir) / "bag", ["/lsu/scan/cloud"])]
    assert len(recorded) == 1
    live = xyz(recorded[0])
    assert len(live) == result.points > sweep["frames_processed"] * 2 * 200, (sweep, values)  # the counts say why
    assert len(by_frame(recorded[0])) == sweep["frames_processed"]
    # Every frame on the plane, the first and last of the motion too (the camera renders each exposure from
    # the emulator's exact samples at the start and stop, the matcher places it by the driver's stamped
    # counters): what is left is the sim's image noise through the line extraction, about a tenth of a mm
    # (median ~0.1 mm); a frame placed one whole step (0.42 mm of sheet travel) off would show.
    scene = build_scene("plane", load_rig())
    distances_mm = surface_distances_m(scene, live) * 1000.0
    per_frame = {k: float(np.median(surface_distances_m(scene, v))) * 1000.0 for k, v in by_frame(recorded[0]).items()}
    placement = (f"per-frame median [mm] {per_frame}, scan.json sweep {sweep}\n"
                 f"{timeline(Path(result.output_dir) / 'bag')}\ntruth (stamp, steps, moving): "
                 f"{[(round(stamps.to_seconds(t.header.stamp), 4), t.position_steps, t.moving) for t in truths if START - 0.5 <= t.position_steps <= END + 0.5][:80]}"
                 f"\n{graph.output[-3000:]}")
    assert np.median(distances_mm) < 0.4 and np.percentile(distances_mm, 99) < 1.0, \
        f"{np.percentile(distances_mm, [50, 99])}; {placement}"
    assert max(per_frame.values()) < 0.6, placement

    assert not canceled.success and "cancel" in canceled.status
    # the frames taken before the cancel are kept: in scan.json (partial) and in the cloud
    partial = json.loads((Path(canceled.output_dir) / "scan.json").read_text())
    assert partial["partial"] and partial["sweep"]["frames_captured"] == canceled.snaps >= 3
    assert canceled.points > 0 and (Path(canceled.output_dir) / "cloud.ply").exists()
    last = truths[-1]
    assert last.velocity_steps_per_s == 0.0 and not last.moving and not last.laser_on
    assert 250 < last.position_steps < 400  # stopped on the way, not run to the end

    # the bag, handed directly to the replay launch file's extractor and matcher (`lsu run replay BAG`)
    from lsu_tools.cli import resolve_launch_file
    from lsu_tools.direct_replay import DirectReplay
    from lsu_tools.launch_file import load_launch, select_nodes
    from lsu_tools.nodes_index import resolve_executable
    from lsu_tools.runner import build_nodes

    description = select_nodes(load_launch(resolve_launch_file("replay"), {}, resolve_executable),
                               ["laser_extractor", "stereo_matcher"], [], {})
    clouds_direct: list = []
    for workers in (0, 2):  # extracting in this process, and in two of its own (`lsu run replay`'s default)
        nodes = build_nodes(description, tmp_path, context=ros_context)
        try:
            replay = DirectReplay(nodes)
            replay.matcher.cloud_pub.publish = clouds_direct.append
            stats = replay.run(Path(result.output_dir) / "bag", workers=workers)
        finally:
            for node in nodes:
                node.destroy_node()
        # every frame in the bag: its complete pairs are the sweep's and the laser-off texture pair
        assert (stats.sweep_frames, stats.frames_dropped, stats.pairs) == (FRAMES, 0, FRAMES + 1)
        assert stats.workers == workers  # the bag is read in place, so the processes took the extraction
    assert len(clouds_direct) == 2
    same_frames(clouds_direct[0], recorded[0])
    # the processes' lines reach the matcher in the bag's order: the same cloud, bit for bit
    assert bytes(clouds_direct[1].data) == bytes(clouds_direct[0].data)
    assert clouds_direct[1].width == clouds_direct[0].width

    # and through the graph of separate nodes (`lsu bag play` into `lsu launch replay`)
    replay_graph = LaunchedProcess(["launch", "replay"])
    try:
        replay_graph.wait_for_line(r"\[stereo_matcher\].*calibration", timeout_s=60)
        replay_graph.wait_for_line(r"started laser_extractor", timeout_s=60)
        clouds = []
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        ros_node.node.create_subscription(PointCloud2, "/lsu/scan/cloud", clouds.append, latched)
        ros_node.spin_until(lambda: False, 2.0)  # let the extractor's subscriptions be discovered
        play = subprocess.run([LSU, "bag", "play", str(Path(result.output_dir) / "bag"), "--topics", *REPLAYED,
                               "--wait-subscribers", "20",
                               *REPLAY_GRAPH_READERS],
                              capture_output=True, text=True, timeout=180)
        assert play.returncode == 0, play.stdout + play.stderr
        assert ros_node.spin_until(lambda: len(clouds) >= 1, 60.0), replay_graph.output[-3000:]
    finally:
        replay_graph.stop(timeout_s=15)
    try:
        same_frames(clouds[0], recorded[0])
    except AssertionError as exc:  # the graph's own account of the frames (a DDS path under load)
        raise AssertionError(f"{exc}\n{replay_graph.output[-4000:]}") from exc

"""Sweeps in the whole sim graph start where the carriage stands: back from the end of the range, or from its
nearer end, and a reverse sweep's frames, cloud, texture and replay are right.

Truth: the rendered plane's geometry (the scene the camera renders), the emulator's carriage (the driver's
state after each sweep), the bag's texture image (the laser-off pair) against the cloud's colours, and
the cloud recorded live against its direct replay.
"""

import json
from pathlib import Path

import numpy as np
import pytest
from sensor_msgs.msg import PointCloud2

from lsu_bags.bags import deserialize_ros, read_messages
from lsu_bags.pointcloud2 import decode, from_msg
from lsu_common import stamps
from lsu_common.arrays import AnyArray
from lsu_interfaces.msg import ScanEvent
from lsu_scan.scanner import LsuScanner
from lsu_testing.plugin import LaunchedProcess

pytestmark = pytest.mark.slow
START, END, RATE, FPS = 220, 238, 60.0, 30.0  # the plane's line seen by both cameras (as test_sweep_graph)
FRAMES = 10  # 18 steps at 60 steps/s: 0.3 s at 30 fps, both ends


def by_frame(msg: PointCloud2) -> dict[int, AnyArray]:
    """A scan cloud's points per frame index."""
    columns = decode(from_msg(msg))
    points = np.stack([columns["x"], columns["y"], columns["z"]], axis=1)
    return {int(i): points[columns["snap"] == i] for i in np.unique(columns["snap"])}


def test_a_sweep_runs_back_from_the_end_it_stands_at_and_otherwise_from_the_nearer_end(tmp_path, ros_context):
    from lsu_accuracy.accuracy import surface_distances_m
    from lsu_reconstruct.node import image_to_array
    from lsu_reconstruct.pipeline import colour_at
    from lsu_sim import build_scene, load_rig

    graph = LaunchedProcess(["launch", "sim", f"port:={tmp_path / 'gp32'}", "scene:=plane",
                             f"output_dir:={tmp_path / 'scans'}"])
    try:
        graph.wait_for_line(r"\[gp32_driver\].*homed: track 470", timeout_s=60)
        graph.wait_for_line(r"\[stereo_camera\].*source 'sim' open", timeout_s=60)
        with LsuScanner(wait_s=30) as scanner:
            scanner.move_to(END)
            back = scanner.scan(start=START, end=END, mode="sweep", sweep_rate_steps_s=RATE, frame_rate_hz=FPS,
                                record_bag=True, output_dir=str(tmp_path / "scans"))
            after_back = scanner.state().position_steps
            # from 300 the range's nearer end is 238: there first, then back to 220 (not a move to 220 and up)
            scanner.move_to(300)
            nearer = scanner.scan(start=START, end=END, mode="sweep", sweep_rate_steps_s=RATE, frame_rate_hz=FPS,
                                  output_dir=str(tmp_path / "scans"))
            after_nearer = scanner.state().position_steps
    finally:
        graph.stop(timeout_s=15)
    assert back.success, back.status + graph.output[-3000:]
    assert nearer.success, nearer.status + graph.output[-3000:]
    assert after_back == START and after_nearer == START

    record = json.loads((Path(back.output_dir) / "scan.json").read_text())
    sweep = record["sweep"]
    assert (sweep["start_steps"], sweep["end_steps"], sweep["direction"]) == (END, START, "reverse")
    assert record["goal"]["start_steps"] == START and record["goal"]["end_steps"] == END
    assert sweep["frames_expected"] == sweep["frames_processed"] == FRAMES and sweep["frames_dropped"] == 0
    # no move before it (it stood at the range's end), and the laser-off pair after the laser went off
    timeline = sweep["timeline_s"]
    order = ["at_start", "laser_on", "stream_started", "motion_ended", "frames_published", "stream_stopped",
             "laser_off", "texture", "points"]
    assert set(timeline) == set(order) and [timeline[k] for k in order] == sorted(timeline.values()), timeline
    assert record["timings_s"]["mechanical_lower_bound"] < (END - START) / RATE + 0.1  # the sweep and the texture
    # the frames' positions at the commanded rate: from the end down, 2 steps a frame
    assert [s["position_steps"] for s in record["snaps"]] == [END - 2 * k for k in range(FRAMES)]
    moved = json.loads((Path(nearer.output_dir) / "scan.json").read_text())["sweep"]
    assert (moved["start_steps"], moved["end_steps"], moved["direction"]) == (END, START, "reverse")

    bag = Path(back.output_dir) / "bag"
    events = [deserialize_ros(m) for m in read_messages(bag, ["/lsu/scan/events"])]
    kinds = [e.type for e in events]
    # the laser-off pair after the sweep, once the carriage stands still; SWEEP_START names the end it started at
    assert kinds.index(ScanEvent.SWEEP_START) < kinds.index(ScanEvent.SWEEP_END) < kinds.index(ScanEvent.TEXTURE)
    assert events[kinds.index(ScanEvent.SWEEP_START)].position_steps == END
    texture_key = stamps.to_ns(events[kinds.index(ScanEvent.TEXTURE)].image_stamp)
    texture = [deserialize_ros(m) for m in read_messages(bag, ["/lsu/stereo/left/image_raw"])
               if stamps.to_ns(deserialize_ros(m).header.stamp) == texture_key]
    assert len(texture) == 1
    clouds = [deserialize_ros(m) for m in read_messages(bag, ["/lsu/scan/cloud"])]
    assert len(clouds) == 1
    columns = decode(from_msg(clouds[0]))
    # the cloud coloured from that laser-off image, as with the texture pair before the sweep
    want = colour_at(image_to_array(texture[0]), columns["u"], columns["v"])
    assert np.array_equal(columns["rgb"].view(np.uint32), np.asarray(want).view(np.uint32))
    assert np.count_nonzero(columns["rgb"].view(np.uint32)) > 0.9 * len(want)

    # every frame on the rendered plane (as the forward sweep's test: a few tenths of a mm; a frame placed
    # at the forward sweep's position, the wrong end of the range, would be millimetres off)
    scene = build_scene("plane", load_rig())
    frames = by_frame(clouds[0])
    assert sorted(frames) == list(range(FRAMES))
    per_frame = {k: float(np.median(surface_distances_m(scene, v))) * 1000.0 for k, v in frames.items()}
    assert max(per_frame.values()) < 0.6, per_frame

    # the bag replayed directly (`lsu run replay BAG`) gives every frame's points as recorded live
    from lsu_tools.cli import resolve_launch_file
    from lsu_tools.direct_replay import DirectReplay
    from lsu_tools.launch_file import load_launch, select_nodes
    from lsu_tools.nodes_index import resolve_executable
    from lsu_tools.runner import build_nodes

    description = select_nodes(load_launch(resolve_launch_file("replay"), {}, resolve_executable),
                               ["laser_extractor", "stereo_matcher"], [], {})
    nodes = build_nodes(description, tmp_path, context=ros_context)
    try:
        replay = DirectReplay(nodes)
        replayed: list = []
        replay.matcher.cloud_pub.publish = replayed.append
        stats = replay.run(bag)
    finally:
        for node in nodes:
            node.destroy_node()
    assert (stats.sweep_frames, stats.frames_dropped) == (FRAMES, 0) and len(replayed) == 1
    got = by_frame(replayed[0])
    assert sorted(got) == sorted(frames)
    for index, points in frames.items():
        assert got[index].shape == points.shape and np.max(np.abs(got[index] - points)) <= 1e-9, index

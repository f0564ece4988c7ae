"""Scan benchmark: live sim scan wall time against the mechanical lower bound, and bag replay speed.

    make bench-scan   ->  bench/results/scan.json
    .venv/bin/python bench/bench_scan.py --only view,two_host   (only parts 3 and 4, merged into scan.json)
    .venv/bin/python bench/bench_scan.py --only sweep           (only part 6, merged into scan.json)
    .venv/bin/python bench/bench_scan.py --only sweep_live      (only part 6's live sweeps, no accuracy study)
    .venv/bin/python bench/bench_scan.py --only sweep_accuracy  (only part 6's accuracy figures, no ROS)
    .venv/bin/python bench/bench_scan.py --only web             (only part 7: the web page's cost)
    .venv/bin/python bench/bench_scan.py --only person_stopsnap (only part 8: stop-snap of a realistic person, no ROS)
    .venv/bin/python bench/bench_scan.py --only motion          (only part 9: a living subject, no ROS)
    .venv/bin/python bench/bench_scan.py --only motion_live     (only part 9's live 60 fps sweep)
    .venv/bin/python bench/bench_scan.py --only motion_faces    (only part 10: faces of moving people, no ROS)
    .venv/bin/python bench/bench_scan.py --only replay [--bag DIR]   (only part 2, on a simulated scan bag
                                                                      unless a bag is given)

1. `lsu launch sim` (separate processes, synthetic head), two full scans 0..470 step 2, settle 0.1 s:
   a default one (what `lsu scan` does: no bag) and one recording its bag (`lsu scan --record`).
   scan_wall_over_mechanical = the default scan's action wall time / (moves at the emulator's rate +
   settle + exposure for every snap), the bound the coordinator computes from the parameters;
   scan_wall_over_mechanical_recording: the same for the recording scan.
2. Replay of the recorded bag: the scan's computation called directly on its frames, per snap and the cloud's (no ROS:
   replay_compute_ms_per_snap), `lsu run replay BAG --exit` (the default replay, bag handed to the
   extractor and matcher in one process: replay_snaps_per_s, replay_cpu_ms_per_snap and
   replay_cpu_over_compute = the two CPU times per snap), and the message path (images + events as
   raw CDR published closed-loop, each snap waiting for its /lsu/points, into `lsu run replay`:
   replay_dds_*); three runs each, medians. Beside them the code before issue 33 (REPLAY_BEFORE, a temporary git
   worktree first on PYTHONPATH) replayed alternately with this one, with today's extractor background (the same
   work: replay_snaps_per_s_over_before, replay_cpu_over_before) and with its own defaults (*_defaults).
3. Live view: a default scan with `lsu view` running and a Foxglove client (lsu_view.wsclient) subscribed
   to every channel, images included, then one more default scan without them:
   bridge_overhead_pct = that scan's wall time over the mean of the two default scans without, minus 1.
4. Two hosts (where network namespaces can be made: root): the sim graph split into `--group rig` and
   `--group processing`, a default scan 0..470 step 2, once with both groups here (localhost settings)
   and once with each group in its own network namespace joined by a veth pair (UDP only):
   two_host_scan_wall_over_one_host; two_host_lines_scan_wall_over_one_host the same with the
   extractor on the rig host (groups rig_extract / processing_lines: only laser lines cross).
5. Settle (`--only settle`): full scans with scan_coordinator's settle fixed and adaptive, same graph and
   scene: stopsnap_adaptive_settle_scan_s beside stopsnap_fixed_settle_scan_s, and the clouds' RMS distance
   to the true surface (stopsnap_adaptive_rms_over_fixed), so that speed is not bought with error.
6. Sweep (`lsu scan --mode sweep`) on the sim graph (synthetic head 7), 60 steps/s, 30 fps frame pairs: the
   default stop-snap scan's lines on the face (stopsnap_lines_on_face) and their range of carriage positions,
   sweeps over that range (sweep_scan_s: action wall time, sweep_lines_on_face, sweep_frames_dropped_pct) and
   over the whole track (sweep_full_track_scan_s). Then
   the same head rendered and reconstructed without ROS (`lsu_accuracy.sweep_sim`), same scene and
   physics: a stop-snap scan 0..470 step 2 (settle 0.1 s after the emulator's post-stop vibration) and
   sweeps at 60 steps/s, 30 fps, synchronised and with the right camera 50 ms late (+-5 ms jitter);
   sweep_rms_over_stopsnap(_50ms) = RMS distance to the rendered head mesh, sweep / stop-snap.
7. Web page (`--only web`): `lsu launch sim web:=true`, default scans 0..470 step 2 without a page, with the
   page open in headless Chromium (live images, laser lines and points streaming to it), and without again:
   web_overhead_pct = the watched scan's wall time over the mean of the two without, minus 1.
8. Person stop-snap (`--only person_stopsnap`, no ROS): a realistic person rendered stop-snap, points more than 1 mm
   off the true surface (stopsnap_points_over_1mm_pct), and the adaptive settle against the fixed one on the same
   scene and frames (adaptive_settle_rms_over_fixed, adaptive_settle_time_over_fixed).
9. A living subject (`--only motion`, `--only motion_live`): see MOTION_NOTES.
10. Faces of a living subject (`--only motion_faces`, no ROS; LSU_BENCH_MOTION_FACES_N people, default 20): face
   identification rank-1 of still and standing (raw, corrected) sweeps against still sweep enrolments, see
   MOTION_FACES_NOTES.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import write_result

from lsu_scan import rosenv
from lsu_tools.twohosts import TwoHosts, split_scan, why_unavailable


def start_sim_graph(tmp: Path, port: str, output_dir: str, *args: str, scene: str = "head:7"):
    """`lsu launch sim` on ``scene`` with its GP32 port and scans under ``tmp``, returned once the carriage is
    homed and the simulated cameras are open (the caller stops it)."""
    from lsu_testing.plugin import LaunchedProcess

    graph = LaunchedProcess(["launch", "sim", f"port:={tmp}/{port}", f"scene:={scene}", f"output_dir:={tmp}/{output_dir}",
                             *args])
    try:
        graph.wait_for_line(r"\[gp32_driver\].*homed: track", timeout_s=120)
        graph.wait_for_line(r"\[stereo_camera\].*source 'sim' open", timeout_s=120)
    except BaseException:
        graph.stop()
        raise
    return graph

def live_scan(tmp: Path, baseline: bool = True, view: bool = True) -> dict:
    from lsu_scan.scanner import LsuScanner

    graph = start_sim_graph(tmp, "gp32", "scans")
    try:
        runs = {}
        with LsuScanner(wait_s=60) as scanner:
            # one short warm-up scan: first-call costs (imports, caches) are not the steady state we measure
            scanner.scan(start=230, end=240, step=5, settle_s=0.1, output_dir=str(tmp / "warmup"))
            def full_scan(name: str, record_bag: bool) -> None:
                scanner.start_scan(start=0, end=470, step=2, settle_s=0.1, record_bag=record_bag)
                result = scanner.get_result(timeout_s=600)  # a lost result fails the benchmark instead of hanging it
                if not result.success:
                    raise RuntimeError(f"the {name} scan failed: {result.status}")
                runs[name] = {"result": result,
                              "record": json.loads((Path(result.output_dir) / "scan.json").read_text())}

            full_scan("default", False)
            if baseline:
                full_scan("recording", True)
            if view:
                with watching_client() as (client, view_pid):
                    cpu0 = _cpu_s(view_pid)
                    full_scan("bridge", False)
                    runs["bridge"]["client"] = {"messages": client.messages_received, "bytes": client.bytes_received,
                                                "bridge_cpu_s": _cpu_s(view_pid) - cpu0}
                full_scan("after_bridge", False)
    finally:
        graph.stop(timeout_s=30)
    return runs


@contextlib.contextmanager
def watching_client():
    """`lsu view` on a free port and a Foxglove client subscribed to every topic the graph has."""
    from lsu_testing.plugin import LaunchedProcess
    from lsu_view.wsclient import FoxgloveClient

    view = LaunchedProcess(["view", "--port", "0"])
    try:
        url = view.wait_for_line(r"(ws://[0-9.]+:\d+)", timeout_s=60).group(1)
        wanted = ["/lsu/stereo/left/image_raw", "/lsu/stereo/right/image_raw", "/lsu/stereo/left/laser_line",
                  "/lsu/stereo/right/laser_line", "/lsu/points", "/lsu/scan/cloud", "/lsu/driver/state"]
        with FoxgloveClient(url, max_queue=1) as client:  # received and counted, not kept
            client.wait_for_topics(wanted, timeout_s=60)
            client.subscribe(sorted({c.topic for c in client.channels.values()}))
            time.sleep(1.0)  # the bridge subscribes on its next poll
            yield client, view.process.pid
    finally:
        view.stop(timeout_s=20)


#: a capture may take longer than the default 1 s abort limit when a loaded host moves 1.8 MB over UDP;
#: the same limit for the one-host reference
LAUNCH_ARGS = ["capture_timeout_s:=5.0"]


def two_host_runs(tmp: Path) -> dict:
    """Full default scans of the split graph: here, across the veth pair, and across it with lines only."""
    scan = ["--start", "0", "--end", "470", "--step", "2"]
    walls = {}
    for name, groups, two in (("one_host", ("rig", "processing"), False), ("two_host", ("rig", "processing"), True),
                              ("two_host_lines", ("rig_extract", "processing_lines"), True)):
        if two:
            with TwoHosts() as hosts:
                folder = split_scan(tmp / name, hosts, groups, scan_args=scan, record=False, launch_args=LAUNCH_ARGS)
        else:
            folder = split_scan(tmp / name, None, groups, scan_args=scan, record=False, launch_args=LAUNCH_ARGS)
        walls[name] = json.loads((folder / "scan.json").read_text())["timings_s"]["scan"]
    return walls


LIVE_UNITS = {"scan_wall_over_mechanical": "x", "scan_wall_s": "s", "scan_mechanical_bound_s": "s", "scan_snaps": "snaps",
              "scan_wall_over_mechanical_recording": "x", "scan_wall_s_recording": "s", "scan_points": "points",
              "ack_ms_median": "ms", "ack_ms_max": "ms", "move_ms_median": "ms", "capture_ms_median": "ms"}


def live_figures(runs: dict) -> dict:
    """The live stop-snap figures of `live_scan`'s default and recording scans."""
    default, recording = runs["default"], runs["recording"]
    result, record = default["result"], default["record"]
    acks = sorted(s.get("ack_s", 0.0) for s in record["snaps"])
    # where a snap's time goes (the coordinator records each phase per snap; the first snap's move
    # from the texture position is left out)
    phases = {name: sorted(s[f"{name}_s"] for s in record["snaps"][1:] if f"{name}_s" in s) or [0.0]
              for name in ("move", "capture")}
    return {"scan_wall_over_mechanical": ratio(default), "scan_wall_s": result.seconds,
            "scan_mechanical_bound_s": record["timings_s"]["mechanical_lower_bound"], "scan_snaps": result.snaps,
            "scan_points": result.points, "scan_wall_over_mechanical_recording": ratio(recording),
            "scan_wall_s_recording": recording["result"].seconds,
            "ack_ms_median": 1000 * acks[len(acks) // 2], "ack_ms_max": 1000 * acks[-1],
            "move_ms_median": 1000 * phases["move"][len(phases["move"]) // 2],
            "capture_ms_median": 1000 * phases["capture"][len(phases["capture"]) // 2]}


def ratio(run: dict) -> float:
    """A scan's wall time over its mechanical lower bound."""
    return run["result"].seconds / run["record"]["timings_s"]["mechanical_lower_bound"]


def _wait_acks(node, acks: set, in_flight: list, done: int) -> None:
    """Wait for the oldest in-flight snap's points."""
    import rclpy

    key = in_flight[0]
    deadline = time.monotonic() + 10.0
    while key not in acks:
        if time.monotonic() > deadline:
            raise RuntimeError(f"snap {done} not acknowledged during replay")
        rclpy.spin_once(node, timeout_sec=0.01)
    in_flight.pop(0)


REPLAYS = 5


def _cpu_s(pid: int) -> float:
    """CPU seconds (user + system, all threads) used so far by process ``pid`` (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def replay(bag: Path, window: int = 4) -> dict:
    """Replay a scan's snaps (recorded images as raw CDR) with at most ``window`` snaps awaiting their points.

    The window stays below the image topics' queue depth (5), so no snap is dropped: every snap is
    acknowledged, and snaps/s is the graph's sustained processing rate.
    """
    import rclpy
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image, PointCloud2

    from lsu_bags.bags import deserialize_ros, read_messages
    from lsu_interfaces.msg import ScanEvent
    from lsu_testing.plugin import LaunchedProcess

    images = {}  # (topic, stamp) -> CDR bytes; the stamp is read straight from the CDR header
    events = []
    for m in read_messages(bag, ["/lsu/scan/events", "/lsu/stereo/left/image_raw", "/lsu/stereo/right/image_raw"]):
        if m.topic.endswith("image_raw"):
            # CDR: 4-byte encapsulation, then std_msgs/Header.stamp (int32 sec, uint32 nanosec), little endian
            images[(m.topic, struct.unpack_from("<iI", m.data, 4))] = m.data
        else:
            events.append((deserialize_ros(m), m.data))
    snaps = []  # (messages before it as (topic, bytes), left bytes, right bytes, stamp key, snap event bytes)
    before: list = []
    missing = 0
    for event, raw in events:
        key = (event.image_stamp.sec, event.image_stamp.nanosec)
        left = images.get(("/lsu/stereo/left/image_raw", key))
        right = images.get(("/lsu/stereo/right/image_raw", key))
        if event.type != ScanEvent.SNAP:
            if event.type == ScanEvent.TEXTURE and left is not None and right is not None:
                before += [("left", left), ("right", right)]  # the laser-off pair, ahead of its event as live
            before.append(("events", raw))
            continue
        if left is None or right is None:
            missing += 1
            continue
        snaps.append((before, left, right, key, raw))
        before = []
    graph = LaunchedProcess(["run", "replay", "--executor", "single"])
    rclpy.init()
    node = rclpy.create_node("bench_replay")
    acks = set()
    node.create_subscription(PointCloud2, "/lsu/points",
                             lambda msg: acks.add((msg.header.stamp.sec, msg.header.stamp.nanosec)),
                             QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE))
    data_qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
    events_qos = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
    pub_events = node.create_publisher(ScanEvent, "/lsu/scan/events", events_qos)
    pub_left = node.create_publisher(Image, "/lsu/stereo/left/image_raw", data_qos)
    pub_right = node.create_publisher(Image, "/lsu/stereo/right/image_raw", data_qos)
    try:
        graph.wait_for_line(r"spinning \d+ node", timeout_s=120)
        end = time.monotonic() + 30
        while (pub_left.get_subscription_count() == 0 or pub_events.get_subscription_count() == 0) \
                and time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.05)
        time.sleep(1.0)
        t0, cpu0 = time.monotonic(), _cpu_s(graph.process.pid)
        done = 0
        in_flight: list = []  # keys published but not yet acknowledged; at most `window`
        for before, left, right, key, snap_event in snaps:
            while len(in_flight) >= window:
                _wait_acks(node, acks, in_flight, done)
                done += 1
            for topic, raw in before:
                {"events": pub_events, "left": pub_left, "right": pub_right}[topic].publish(raw)
            pub_left.publish(left)
            pub_right.publish(right)
            pub_events.publish(snap_event)
            in_flight.append(key)
        while in_flight:
            _wait_acks(node, acks, in_flight, done)
            done += 1
        seconds = time.monotonic() - t0
        cpu = _cpu_s(graph.process.pid) - cpu0
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        graph.stop(timeout_s=20)
    return {"snaps": done, "seconds": seconds, "cpu_s": cpu, "missing_in_bag": missing}


CONFIG = Path(__file__).resolve().parents[1] / "config"


def _node_params(name: str) -> dict:
    """The ``ros__parameters`` of config/params/NAME.yaml (what the replay launch file gives the node)."""
    import yaml

    return yaml.safe_load((CONFIG / "params" / f"{name}.yaml").read_text())["/**"]["ros__parameters"]


def compute_reference(bag: Path, passes: int = 3) -> dict:
    """CPU per snap of the scan's computation called directly on the bag's frames (no ROS).

    The frames are read from the bag first (not timed); then per snap: the two images read from
    their CDR buffers (lsu_extract.image), two extractions with the replay launch file's extractor
    parameters (against the scan's laser-off pair with its `background: texture`), matching + triangulation (lsu_reconstruct.pipeline.reconstruct_snap) with its
    matcher parameters and calibration; and once per scan what the matcher computes for its cloud:
    colours from the laser-off frame, the snaps merged, the grazing points dropped (colour_at,
    merge_snaps, drop_grazing): the functions the nodes call. The median of ``passes``
    passes (after one untimed one) of CPU time (this process, all threads), with OpenCV on one
    thread as in the replay's extraction processes: its thread pool, of no use to a frame this
    small, would add its own CPU to the reference and hide the replay's overhead.
    """
    from dataclasses import fields

    import cv2
    import numpy as np

    cv2.setNumThreads(1)  # for the rest of this process: the graphs it measures run in processes of their own

    from lsu_bags.bags import deserialize_ros, read_message_views, read_messages
    from lsu_extract.extractor import ExtractorParams, extract_laser_line
    from lsu_extract.image import decode_image, parse_image_cdr
    from lsu_reconstruct.matching import LineArrays, MatchParams
    from lsu_reconstruct.pipeline import colour_at, drop_grazing, merge_snaps, reconstruct_snap
    from lsu_reconstruct.stereo import StereoModel

    ext = _node_params("laser_extractor")
    params = ExtractorParams(**{f.name: ext[f.name] for f in fields(ExtractorParams) if f.name in ext})
    mat = _node_params("stereo_matcher")
    match = MatchParams(**{f.name: mat[f.name] for f in fields(MatchParams) if f.name in mat},
                        method=mat["triangulation"])
    model = StereoModel.from_folder(CONFIG / "calibration" / "sim")
    frames: dict = {}
    events = []
    for m in read_messages(bag, ["/lsu/scan/events", "/lsu/stereo/left/image_raw", "/lsu/stereo/right/image_raw"]):
        if m.topic.endswith("image_raw"):
            frames.setdefault(struct.unpack_from("<iI", m.data, 4), {})[m.topic.split("/")[-2]] = m.data
        else:
            events.append(deserialize_ros(m))
    pairs = [(f["left"], f["right"]) for _, f in sorted(frames.items()) if len(f) == 2]
    off: dict = {}  # the laser-off pair the scan's TEXTURE event names: the cloud's colours (left), and the
    #                 extractor's background with `background: texture`, as the nodes use it
    for event in events:
        if event.type == event.TEXTURE:
            for side, raw in frames.get((event.image_stamp.sec, event.image_stamp.nanosec), {}).items():
                msg = parse_image_cdr(raw)
                off[side] = decode_image(msg.data, msg.width, msg.height, msg.encoding, msg.step)
    texture = off.get("left")
    background = off if ext.get("background", "none") == "texture" else {}

    def line(raw: bytes, side: str) -> LineArrays:
        msg = parse_image_cdr(raw)
        r = extract_laser_line(decode_image(msg.data, msg.width, msg.height, msg.encoding, msg.step), params,
                               texture=background.get(side))
        return LineArrays(u=r.u, v=r.v, peak=r.peak, width=r.width, quality=np.clip(r.quality, 0.0, 1.0),
                          image_width=r.image_width, image_height=r.image_height)

    def one_pass() -> int:
        snaps = [reconstruct_snap(model, line(left, "left"), line(right, "right"), match) for left, right in pairs]
        if texture is not None:
            for snap in snaps:
                snap.rgb = colour_at(texture, snap.u, snap.v)
        return len(drop_grazing(merge_snaps(snaps), model, float(mat["max_view_angle_deg"])))

    def timed_pass() -> float:
        c0 = time.process_time()
        one_pass()
        return time.process_time() - c0

    points = one_pass()
    cpu = [timed_pass() for _ in range(passes)]
    # what reading the bag alone costs the way the direct replay reads it (views of the mapped file where it
    # is an uncompressed MCAP, else rosbags with decompression): the part no message path can save
    c0 = time.process_time()
    for _ in read_message_views(bag, ["/lsu/scan/events", "/lsu/stereo/left/image_raw",
                                      "/lsu/stereo/right/image_raw"]):
        pass
    read_s = time.process_time() - c0
    return {"snaps": len(pairs), "cpu_s": sorted(cpu)[len(cpu) // 2], "points": points, "read_cpu_s": read_s,
            "timed_pass": timed_pass}


def _default_workers() -> int:
    from lsu_tools.direct_replay import default_workers

    return default_workers()


REPLAY_WORKERS = _default_workers()  # `lsu run replay`'s default: extraction processes beside the one that matches


def replay_direct(bag: Path, workers: int = REPLAY_WORKERS) -> dict:
    """`lsu run replay BAG --exit --workers N` (the default replay: bag -> extractor -> matcher, no DDS between;
    the extraction in N processes of its own, or in the replay's process with 0).

    The figures are the ones the command prints for its processing window (first message read to
    the scan cloud published): snaps, wall seconds, CPU (whole process, all threads, and its
    extraction processes) per snap.
    """
    import re

    from lsu_testing.plugin import LaunchedProcess

    graph = LaunchedProcess(["run", "replay", str(bag), "--exit", "--workers", str(workers)])
    try:
        graph.wait(timeout_s=600)
    finally:
        graph.kill()
    match = re.search(r"replayed .*: (\d+) snaps .* in ([\d.]+) s, \d+ snaps/s, ([\d.]+) ms CPU per snap \(([\d.]+) "
                      r"ms of it reading the bag\); (\d+) frames unreadable, (\d+) lines unpaired", graph.output)
    if graph.process.returncode != 0 or match is None:
        raise RuntimeError(f"lsu run replay {bag} failed (exit {graph.process.returncode}): {graph.output[-3000:]}")
    if workers and f"extracted in {workers} processes" not in graph.output:
        raise RuntimeError(f"lsu run replay {bag} --workers {workers} extracted in one process: {graph.output[-3000:]}")
    snaps = int(match.group(1))
    here = re.search(r"and (\d+) of (\d+) images here", graph.output)
    return {"snaps": snaps, "seconds": float(match.group(2)), "cpu_s": float(match.group(3)) * snaps / 1000.0,
            "read_cpu_s": float(match.group(4)) * snaps / 1000.0, "lost": int(match.group(5)) + int(match.group(6)),
            "here_pct": 100.0 * int(here.group(1)) / max(1, int(here.group(2))) if here else 0.0}


def _bag_mb(bag: Path) -> float:
    return sum(f.stat().st_size for f in Path(bag).rglob("*") if f.is_file()) / 1e6


def compression_cost(bag: Path, snaps: int) -> dict:
    """Disk size per snap of ``bag`` and of a zstd-compressed copy (mcap chunks, rosbags' level), and the
    CPU per snap of reading the copy's scan events and images (what reading cost with compressed scan bags)."""
    from lsu_bags.bags import BagWriter, bag_topics, read_messages

    topics = ["/lsu/scan/events", "/lsu/stereo/left/image_raw", "/lsu/stereo/right/image_raw"]
    with tempfile.TemporaryDirectory(prefix="lsu-bench-zstd-") as tmp:
        copy = Path(tmp) / "bag"
        with BagWriter(copy, "mcap", compress=True) as out:
            for topic, (msgtype, qos) in bag_topics(bag).items():
                out.add_topic(topic, msgtype, qos)
            for m in read_messages(bag):
                out.write(m.topic, m.timestamp_ns, m.data)
        c0 = time.process_time()
        for _ in read_messages(copy, topics):
            pass
        read_s = time.process_time() - c0
        return {"replay_bag_mb_per_snap": _bag_mb(bag) / max(1, snaps),
                "replay_bag_zstd_mb_per_snap": _bag_mb(copy) / max(1, snaps),
                "replay_read_zstd_ms_per_snap": 1000 * read_s / max(1, snaps)}


def replay_figures(bag: Path, direct_runs: int = REPLAYS, dds_runs: int = REPLAYS) -> dict:
    """replay_cpu_over_compute and replay_snaps_per_s (direct replay), beside the message path's (dds)."""
    # The host is shared: the CPU a fixed piece of work takes drifts with the other core's load (cache,
    # memory bandwidth). So each replay run is paired with a reference pass right before and right after
    # it (passes and runs alternate), and its ratio taken against their mean.
    reference = compute_reference(bag, passes=1)
    snaps = max(1, reference["snaps"])
    passes = [reference["cpu_s"]]
    direct: list[dict] = []
    serial: list[dict] = []  # the same replay extracting in its own process (--workers 0), alternating with it
    for _ in range(direct_runs):
        for workers, runs in ((REPLAY_WORKERS, direct), (0, serial)):
            run = replay_direct(bag, workers)
            passes.append(reference["timed_pass"]())
            run["ratio"] = (run["cpu_s"] / max(1, run["snaps"])) / ((passes[-2] + passes[-1]) / 2 / snaps)
            runs.append(run)
    compute_ms = 1000 * sorted(passes)[len(passes) // 2] / snaps

    def median(values: list[float]) -> float:
        return sorted(values)[len(values) // 2]

    by_speed = sorted(direct, key=lambda r: r["snaps"] / r["seconds"])
    rep = by_speed[len(by_speed) // 2]
    figures = {"replay_compute_ms_per_snap": compute_ms,
               "replay_snaps_per_s": rep["snaps"] / rep["seconds"],
               "replay_snaps_per_s_min": by_speed[0]["snaps"] / by_speed[0]["seconds"],
               "replay_snaps_per_s_max": by_speed[-1]["snaps"] / by_speed[-1]["seconds"],
               "replay_cpu_ms_per_snap": median([1000 * r["cpu_s"] / max(1, r["snaps"]) for r in direct]),
               "replay_snaps": rep["snaps"], "replay_lost": max(r["lost"] for r in direct + serial),
               "replay_cpu_over_compute": median([r["ratio"] for r in direct]),
               "replay_cpu_over_compute_min": min(r["ratio"] for r in direct),
               "replay_cpu_over_compute_max": max(r["ratio"] for r in direct),
               "replay_workers": float(REPLAY_WORKERS),
               "replay_extracted_here_pct": median([r["here_pct"] for r in direct]),
               "replay_one_process_snaps_per_s": median([r["snaps"] / r["seconds"] for r in serial]),
               "replay_one_process_cpu_over_compute": median([r["ratio"] for r in serial]),
               "replay_snaps_per_s_over_one_process": median([(d["snaps"] / d["seconds"]) / (o["snaps"] / o["seconds"])
                                                              for d, o in zip(direct, serial)])}
    read_ms = 1000 * reference["read_cpu_s"] / max(1, reference["snaps"])
    figures["replay_read_ms_per_snap"] = read_ms
    figures["replay_cpu_over_compute_and_read"] = figures["replay_cpu_ms_per_snap"] / (compute_ms + read_ms)
    figures["replay_processing_cpu_over_compute"] = median(
        [r["ratio"] * (r["cpu_s"] - r["read_cpu_s"]) / r["cpu_s"] for r in direct])
    figures.update(compression_cost(bag, reference["snaps"]))
    if dds_runs:
        dds = sorted((replay(bag) for _ in range(dds_runs)), key=lambda r: r["snaps"] / r["seconds"])
        mid = dds[len(dds) // 2]
        figures.update({"replay_dds_snaps_per_s": mid["snaps"] / mid["seconds"],
                        "replay_dds_cpu_ms_per_snap": 1000 * mid["cpu_s"] / max(1, mid["snaps"]),
                        "replay_dds_snaps": mid["snaps"], "bag_snaps_missing_images": mid["missing_in_bag"]})
        figures["replay_dds_cpu_over_compute"] = figures["replay_dds_cpu_ms_per_snap"] / compute_ms
    return figures


REPLAY_BEFORE = "59ff447"  # the code before issue 33 (replay CPU), measured beside the current code in the same run


def _source_path(checkout: Path) -> str:
    """PYTHONPATH putting the Python packages of ``checkout`` before this venv's editable installs (its generated
    interfaces, not Python sources, stay the venv's)."""
    return os.pathsep.join(str(pkg) for pkg in sorted((checkout / "src").iterdir())
                           if (pkg / pkg.name / "__init__.py").is_file())


def replay_before_figures(bag: Path, runs: int = REPLAYS, before: str = REPLAY_BEFORE) -> dict:
    """`lsu run replay BAG --exit` of the code at ``before`` (a temporary git worktree, its packages first on
    PYTHONPATH) and of this checkout, alternated in one run on one host (median of the rounds' ratios).

    The code before extracted each frame alone by default; today's default subtracts the scan's laser-off
    frame, which that code could do too (its `background: texture`). So it runs twice per round: with the
    extractor background of today's default (replay_snaps_per_s_over_before, replay_cpu_over_before: the same
    work, the replay's own cost compared) and with its own defaults (the *_defaults figures: what a user of
    each version got out of the box)."""
    root = Path(__file__).resolve().parents[1]
    background = str(_node_params("laser_extractor").get("background", "none"))
    with tempfile.TemporaryDirectory(prefix="lsu-bench-before-") as tmp:
        checkout = Path(tmp) / "before"
        subprocess.run(["git", "-C", str(root), "worktree", "add", "--detach", str(checkout), before], check=True,
                       capture_output=True)
        try:
            env_defaults = {**os.environ, "PYTHONPATH": _source_path(checkout)}
            same = Path(tmp) / "config_same"
            shutil.copytree(checkout / "config", same)
            params = same / "params" / "laser_extractor.yaml"
            text = params.read_text()
            if background != "none":
                if "background: none" not in text:
                    raise RuntimeError(f"{before}'s {params.name} has no 'background: none' to set to {background}")
                params.write_text(text.replace("background: none", f"background: {background}", 1))
            env_same = {**env_defaults, "LSU_CONFIG_DIR": str(same)}
            rounds = []
            for _ in range(runs):
                rounds.append((_replay_with_env(bag, env_same), _replay_with_env(bag, env_defaults),
                               _replay_with_env(bag, dict(os.environ))))
        finally:
            subprocess.run(["git", "-C", str(root), "worktree", "remove", "--force", str(checkout)], check=False,
                           capture_output=True)

    def median(values: list[float]) -> float:
        return sorted(values)[len(values) // 2]

    figures = {}
    for which, suffix in ((0, ""), (1, "_defaults")):
        pairs = [(r[which], r[2]) for r in rounds]
        figures.update({
            f"replay_snaps_per_s_over_before{suffix}": median([(n["snaps"] / n["seconds"]) / (o["snaps"] / o["seconds"])
                                                               for o, n in pairs]),
            f"replay_cpu_over_before{suffix}": median([(n["cpu_s"] / n["snaps"]) / (o["cpu_s"] / o["snaps"])
                                                      for o, n in pairs]),
            f"replay_before_snaps_per_s{suffix}": median([o["snaps"] / o["seconds"] for o, _ in pairs])})
    return figures


def _replay_with_env(bag: Path, env: dict) -> dict:
    """`lsu run replay BAG --exit --workers N` in ``env``: snaps, seconds, CPU seconds (the command's own figures)."""
    from lsu_testing.plugin import LaunchedProcess

    graph = LaunchedProcess(["run", "replay", str(bag), "--exit", "--workers", str(REPLAY_WORKERS)], env=env)
    try:
        graph.wait(timeout_s=600)
    finally:
        graph.kill()
    match = re.search(r"replayed .*: (\d+) snaps .* in ([\d.]+) s, \d+ snaps/s, ([\d.]+) ms CPU per snap", graph.output)
    if graph.process.returncode != 0 or match is None:
        raise RuntimeError(f"lsu run replay {bag} failed (exit {graph.process.returncode}): {graph.output[-3000:]}")
    snaps = int(match.group(1))
    return {"snaps": snaps, "seconds": float(match.group(2)), "cpu_s": float(match.group(3)) * snaps / 1000.0}


REPLAY_BEFORE_UNITS = {f"{name}{suffix}": unit for suffix in ("", "_defaults")
                       for name, unit in (("replay_snaps_per_s_over_before", "x"), ("replay_cpu_over_before", "x"),
                                          ("replay_before_snaps_per_s", "snaps/s"))}


REPLAY_UNITS = {"replay_compute_ms_per_snap": "ms", "replay_snaps_per_s": "snaps/s", "replay_snaps_per_s_min": "snaps/s",
                "replay_snaps_per_s_max": "snaps/s", "replay_cpu_ms_per_snap": "ms", "replay_snaps": "snaps",
                "replay_lost": "frames+lines", "replay_cpu_over_compute": "x", "replay_cpu_over_compute_min": "x",
                "replay_cpu_over_compute_max": "x", "replay_dds_snaps_per_s": "snaps/s",
                "replay_dds_cpu_ms_per_snap": "ms", "replay_dds_snaps": "snaps", "bag_snaps_missing_images": "snaps",
                "replay_dds_cpu_over_compute": "x", "replay_read_ms_per_snap": "ms",
                "replay_cpu_over_compute_and_read": "x", "replay_processing_cpu_over_compute": "x",
                "replay_bag_mb_per_snap": "MB", "replay_bag_zstd_mb_per_snap": "MB", "replay_read_zstd_ms_per_snap": "ms",
                "replay_workers": "processes", "replay_extracted_here_pct": "%",
                "replay_one_process_snaps_per_s": "snaps/s",
                "replay_one_process_cpu_over_compute": "x", "replay_snaps_per_s_over_one_process": "x"}
REPLAY_NOTES = (
    "replay: the recording scan's bag (scan events + image pairs, the laser-off texture pair included). "
    "replay_compute_ms_per_snap: CPU per snap of the computation called directly on the bag's frames, "
    "no ROS (images read from their CDR buffers, two extractions and matching + triangulation with the "
    "replay launch file's parameters, and the scan cloud's colours, merge and grazing filter as the matcher "
    "computes them once per scan, shared out per snap; OpenCV on one thread as in the extraction processes; median of the "
    "passes, one before and one after each replay run). "
    "replay_snaps_per_s / replay_cpu_ms_per_snap: "
    "`lsu run replay BAG --exit` (the default replay: the bag read and handed to the extractor and "
    "matcher nodes without DDS, which publish lines and points (to subscribers) and the scan cloud as "
    "live; the images extracted in replay_workers processes of their own, each mapping the bag, and by the "
    "replay's own extractor node wherever it would have the image before every process "
    "(replay_extracted_here_pct of the images, median), while the replay's process matches), from the "
    "first message read to the "
    "scan cloud published (bag reading included, the extraction processes' start-up not: like the "
    "nodes' construction it comes before), CPU of the whole process (all threads) and of its extraction "
    "processes, without the executor's turns the replay gives the launch file's other nodes (the face "
    "processor meshing the scan cloud once it is out: seconds of work that landed inside the window or "
    "not by chance), which the command prints apart; median of 5 runs, min and max beside it; "
    "replay_cpu_over_compute: each run's CPU per snap over the mean of the reference passes right before "
    "and after it (the host's load changes the CPU a fixed work takes), median of the 5 runs (min, max "
    "beside it); replay_one_process_*: the same with --workers 0 (everything in the replay's process), "
    "its runs alternating with those; replay_snaps_per_s_over_one_process: the median of each pair's "
    "ratio; replay_lost: "
    "frames unreadable + lines unpaired. The direct replay hands the extractor's arrays to the matcher "
    "without LaserLine messages (one is built only for a subscriber of the lines) and reads an "
    "uncompressed bag as views of the mapped file (lsu_bags.bags.read_message_views), so the images reach "
    "the extractor without a copy. replay_read_ms_per_snap: CPU per snap of reading the bag alone that way "
    "(scan bags are recorded uncompressed; same run; the pages of the images are then read by the "
    "extraction), which the direct replay does in a second thread when it extracts in its own process and "
    "between the lines it receives when processes extract; replay_cpu_over_compute_and_read = "
    "replay CPU / (compute + read); "
    "replay_processing_cpu_over_compute: the replay's CPU without its bag-reading thread's (thread CPU "
    "clock) over compute, paired like replay_cpu_over_compute, like for like with replay_dds_cpu_over_compute, whose bag was read beforehand "
    "by the benchmark. replay_dds_*: the message path (`lsu run replay --executor "
    "single`, the bag's raw CDR published into it closed-loop with at most 4 snaps awaiting their "
    "/lsu/points, below the image queue depth 5), CPU of that process only (median of 5 runs, each in a "
    "fresh graph); these were replay_snaps_per_s / replay_cpu_ms_per_snap before the direct replay. "
    "replay_bag_mb_per_snap: the bag's disk size per snap; replay_bag_zstd_mb_per_snap and "
    "replay_read_zstd_ms_per_snap: a zstd-compressed copy of it (mcap chunks, as scan bags were recorded "
    "before) and the CPU per snap of reading that copy, same run. replay_snaps_per_s_over_before / "
    "replay_cpu_over_before: this checkout's `lsu run replay BAG --exit` against the code before issue 33 "
    "(REPLAY_BEFORE) with the extractor background of today's default (`background: texture`, which that code "
    "had as an option: the same extraction work; it had no grow_wide, which today's default adds), alternated, "
    "median of the rounds' ratios; the *_defaults figures: the same against that code with its own defaults "
    "(each frame extracted alone, no grazing filter). ")


def sim_bag(tmp: Path) -> Path:
    """A recorded-like scan bag of synthetic head 7, 0..470 step 2 with the texture pair, without the graph."""
    from lsu_sim import build_scene, load_rig
    from lsu_testing.simbags import write_sim_scan_bag

    geometry = load_rig()
    return write_sim_scan_bag(tmp / "bag", build_scene("head:7", geometry), list(range(0, 471, 2)), seed=7,
                              geometry=geometry, compress=False)  # as the scan coordinator records


VIEW_NOTES = (
    "bridge: a default scan with `lsu view` and a Foxglove WebSocket client "
    "subscribed to every channel (images at the bridge's default 5 Hz per camera), then one without; "
    "bridge_overhead_pct against the mean of the default scan and that one; bridge_cpu_ms_per_snap: CPU time (all threads) of the lsu view process during the watched scan per snap. two_host (root only): the "
    "graph split by `lsu launch sim --group rig|processing`, default full scans (no bag), both halves here "
    "with localhost settings vs each in its own network namespace joined by a veth pair (SUBNET discovery "
    "+ static peer, UDPv4 only); _lines: the extractor on the rig host (rig_extract / processing_lines).")
UNITS = {"bridge_overhead_pct": "%", "scan_wall_s_bridge": "s", "scan_wall_s_after_bridge": "s",
         "bridge_client_mb": "MB", "bridge_client_messages": "messages", "bridge_cpu_ms_per_snap": "ms",
         "two_host_scan_wall_over_one_host": "x", "two_host_lines_scan_wall_over_one_host": "x",
         "one_host_split_scan_wall_s": "s", "two_host_scan_wall_s": "s", "two_host_lines_scan_wall_s": "s"}


def view_figures(runs: dict) -> dict:
    """bridge_overhead_pct: the scan watched through the bridge against the mean of the two scans without."""
    without = (runs["default"]["result"].seconds + runs["after_bridge"]["result"].seconds) / 2
    bridge = runs["bridge"]
    return {"bridge_overhead_pct": 100.0 * (bridge["result"].seconds / without - 1.0),
            "scan_wall_s_bridge": bridge["result"].seconds, "scan_wall_s_after_bridge": runs["after_bridge"]["result"].seconds,
            "bridge_client_mb": bridge["client"]["bytes"] / 1e6, "bridge_client_messages": bridge["client"]["messages"],
            "bridge_cpu_ms_per_snap": 1000 * bridge["client"]["bridge_cpu_s"] / max(1, bridge["result"].snaps)}


WEB_UNITS = {"web_overhead_pct": "%", "scan_wall_s_web": "s", "scan_wall_s_without_web": "s",
             "web_points_drawn_pct": "%", "web_server_cpu_ms_per_snap": "ms", "web_images_shown": "images"}
WEB_NOTES = (" web: `lsu launch sim web:=true` (head 7), after a warm-up a default scan 0..470 step 2 with no page "
             "open, one with the page open in headless Chromium (Debian's, Playwright; images at the server's "
             "default 2 Hz per camera, laser lines and every snap's points streamed), one without again: "
             "web_overhead_pct = the watched scan over the mean of the two without, minus 1; web_points_drawn_pct: "
             "points the page drew over the scan's points (frames dropped for a slow page lower it); "
             "web_server_cpu_ms_per_snap: CPU time of the web_server process during the watched scan per snap.")


def web_figures(tmp: Path) -> dict:
    """Part 7: the same scan with and without the web page open and live data streaming to it."""
    import socket

    from playwright.sync_api import sync_playwright

    from lsu_scan.scanner import LsuScanner

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    graph = start_sim_graph(tmp, "gp32w", "web_scans", "web:=true", f"web_port:={port}", *LAUNCH_ARGS)
    walls: dict[str, float] = {}
    try:
        graph.wait_for_line(r"\[web_server\] lsu web: open", timeout_s=120)
        web_pid = graph.started_pids()["web_server"]
        with LsuScanner(wait_s=60) as scanner:
            scanner.scan(start=230, end=240, step=5, settle_s=0.1, output_dir=str(tmp / "warmup"))

            def full_scan(name: str) -> tuple[int, int]:
                result = scanner.scan(start=0, end=470, step=2, settle_s=0.1)
                if not result.success:
                    raise RuntimeError(f"the {name} scan failed: {result.status}")
                walls[name] = result.seconds
                return int(result.points), int(result.snaps)

            full_scan("before")
            with sync_playwright() as pw:
                browser = pw.chromium.launch(executable_path="/usr/bin/chromium", args=["--no-sandbox"])
                page = browser.new_page(viewport={"width": 1400, "height": 1000})
                page.goto(f"http://127.0.0.1:{port}/", wait_until="commit", timeout=120000)
                page.wait_for_function("window.lsu && window.lsu.connected", timeout=180000)
                time.sleep(1.0)  # the server subscribes the live topics on its next tick
                cpu0 = _cpu_s(web_pid)
                points, snaps = full_scan("web")
                cpu = _cpu_s(web_pid) - cpu0
                time.sleep(1.0)  # the last frames reach the page
                drawn = int(page.evaluate("window.lsu.pointsDrawn"))
                images = int(page.evaluate("window.lsu.imagesShown"))
                browser.close()
            full_scan("after")
    finally:
        graph.stop(timeout_s=30)
    without = (walls["before"] + walls["after"]) / 2
    return {"web_overhead_pct": 100.0 * (walls["web"] / without - 1.0), "scan_wall_s_web": walls["web"],
            "scan_wall_s_without_web": without, "web_points_drawn_pct": 100.0 * drawn / max(1, points),
            "web_server_cpu_ms_per_snap": 1000.0 * cpu / max(1, snaps), "web_images_shown": images}


def two_host_figures(walls: dict) -> dict:
    if not walls:
        return {}
    return {"two_host_scan_wall_over_one_host": walls["two_host"] / walls["one_host"],
            "two_host_lines_scan_wall_over_one_host": walls["two_host_lines"] / walls["one_host"],
            "one_host_split_scan_wall_s": walls["one_host"], "two_host_scan_wall_s": walls["two_host"],
            "two_host_lines_scan_wall_s": walls["two_host_lines"]}


SETTLE_UNITS = {"stopsnap_adaptive_settle_scan_s": "s", "stopsnap_fixed_settle_scan_s": "s",
                "stopsnap_adaptive_over_fixed": "x", "stopsnap_adaptive_rms_mm": "mm", "stopsnap_fixed_rms_mm": "mm",
                "stopsnap_adaptive_rms_over_fixed": "x", "stopsnap_adaptive_captures_per_snap": "captures",
                "stopsnap_settle_scan_snaps": "snaps"}
SETTLE_NOTES = (
    "settle: in one `lsu launch sim` graph (synthetic head 7 at 300 mm, or the scene LSU_BENCH_SETTLE_SCENE named: the "
    "measured entry says which), after a warm-up scan, scans of "
    "stopsnap_settle_scan_snaps snaps (0..470 step 2 unless LSU_BENCH_SETTLE_SCAN said otherwise) with the settle parameter of scan_coordinator fixed (settle_s 0.1) and adaptive (lsu_scan.settle, "
    "tolerance 0.15 px, at most settle_s), capture_timeout_s 5 s and laser_pause_s 1.5 s for both, in the order fixed, adaptive, adaptive, fixed; each figure the mean of its "
    "two scans: stopsnap_*_settle_scan_s the action's wall time, *_rms_mm the cloud's RMS distance to the true head "
    "surface (the demo's measure), adaptive_captures_per_snap the captures per snap after the first frame after the stop "
    "(that probe is published too, but never the snap). The sim's capture is a render (~40 ms), standing in for the wait for a camera frame.")


def settle_figures(tmp: Path) -> dict:
    """Fixed vs adaptive stop-snap settle on the same scene and physics: scan time and accuracy.

    LSU_BENCH_SETTLE_SCAN=START,END,STEP scans part of the range (a loaded host; the notes say which);
    LSU_BENCH_SETTLE_SCENE another scene (default head:7).
    """
    from lsu_scan.scanner import LsuScanner
    from lsu_tools.demo import accuracy_against_scene

    scene = os.environ.get("LSU_BENCH_SETTLE_SCENE", "head:7")
    graph = start_sim_graph(tmp, "gp32s", "settle", scene=scene)
    runs: dict = {"fixed": [], "adaptive": []}
    try:
        with LsuScanner(wait_s=60) as scanner:
            scanner.scan(start=230, end=240, step=5, settle_s=0.1, output_dir=str(tmp / "warmup-settle"))
            lsu = str(Path(sys.executable).parent / "lsu")
            # a loaded shared host stretches captures past the default 1 s limit and the laser guard's 0.2 s
            # (both modes get the same limits)
            for name, value in (("capture_timeout_s", "5.0"), ("laser_pause_s", "1.5")):
                subprocess.run([lsu, "param", "set", "/lsu/scan_coordinator", name, value], check=True,
                               capture_output=True, timeout=60)
            for mode in ("fixed", "adaptive", "adaptive", "fixed"):
                subprocess.run([lsu, "param", "set", "/lsu/scan_coordinator", "settle", mode], check=True,
                               capture_output=True, timeout=60)
                start, end, step = (int(v) for v in os.environ.get("LSU_BENCH_SETTLE_SCAN", "0,470,2").split(","))
                scanner.start_scan(start=start, end=end, step=step, settle_s=0.1)
                result = scanner.get_result(timeout_s=600)
                if not result.success:
                    raise RuntimeError(f"the {mode}-settle scan failed: {result.status}")
                folder = Path(result.output_dir)
                record = json.loads((folder / "scan.json").read_text())
                if record["parameters"].get("settle") != mode:
                    raise RuntimeError(f"scan.json says settle {record['parameters'].get('settle')}, not {mode}")
                captures = [s.get("settle", {}).get("captures", 1) for s in record["snaps"]]
                runs[mode].append({"range": f"{start}..{end} step {step}", "seconds": result.seconds, "captures": sum(captures) / max(1, len(captures)),
                                   "rms_mm": accuracy_against_scene(folder / "cloud.ply", scene)["rms_mm"]})
    finally:
        graph.stop(timeout_s=30)

    def mean(mode: str, key: str) -> float:
        return sum(r[key] for r in runs[mode]) / len(runs[mode])

    return {"stopsnap_adaptive_settle_scan_s": mean("adaptive", "seconds"),
            "stopsnap_fixed_settle_scan_s": mean("fixed", "seconds"),
            "stopsnap_adaptive_over_fixed": mean("adaptive", "seconds") / mean("fixed", "seconds"),
            "stopsnap_adaptive_rms_mm": mean("adaptive", "rms_mm"), "stopsnap_fixed_rms_mm": mean("fixed", "rms_mm"),
            "stopsnap_adaptive_rms_over_fixed": mean("adaptive", "rms_mm") / mean("fixed", "rms_mm"),
            "stopsnap_adaptive_captures_per_snap": mean("adaptive", "captures"),
            "stopsnap_settle_scan_snaps": float(len(record["snaps"]))}


SWEEP_RATE, SWEEP_FPS, SWEEP_OFFSET_S, SWEEP_JITTER_S = 60.0, 30.0, 0.050, 0.005
# a line lands on the face when at least this many of its points lie within ON_FACE_MM of the true head
ON_FACE_POINTS, ON_FACE_MM = 20, 1.0
FACE_MARGIN_STEPS = 4  # added at each end of the stop-snap scan's range of lines on the face (2 lines at 2 steps)
# the face sweeps' rate: 5 % more frames over the range than stop-snap's 2 steps per line, so that a frame or
# two lost on a loaded host still leaves at least as many lines on the face (60 / 1.05 steps/s)
FACE_SWEEP_RATE = round(SWEEP_RATE / 1.05, 1)
SWEEP_NOTES = (
    f"sweep: live on lsu launch sim (head 7 at 300 mm, no bag, texture on; the cameras free-run, /lsu/stereo/stream, "
    f"{SWEEP_FPS:g} fps, {SWEEP_RATE:g} steps/s), in one graph after a warm-up sweep: the default stop-snap scan 0..470 "
    f"step 2; stopsnap_lines_on_face = its snaps with at least {ON_FACE_POINTS} points within {ON_FACE_MM:g} mm of the "
    "true head surface, at carriage positions sweep_face_start_steps..sweep_face_end_steps (the first and last such "
    f"snap, widened by {FACE_MARGIN_STEPS} steps at each end). Then the full track as a sweep (it starts at 470, where "
    "the stop-snap scan left the carriage, and runs back to 0: no move): sweep_full_track_scan_s (236 frames). Then "
    f"three sweeps over the face range at {FACE_SWEEP_RATE:g} steps/s (5 % more frames than stop-snap's 2 steps per "
    "line over the range, so that a frame lost on a loaded host still leaves as many lines on the face): the first from "
    "0 (a move to the range's nearer end, then forward): "
    "sweep_face_with_move_scan_s; then back (reverse) and forth (forward), each starting where the carriage stands: "
    "sweep_scan_s is the mean of those two action wall times (the goal's figure: a sweep over the face with at least as "
    "many lines on the face as the default stop-snap scan), sweep_lines_on_face the fewer of their lines on the face "
    "(same rule). Each wall time is the action's: laser on, stream start, the motion, the stream's end, laser off, "
    "the texture pair (taken after the sweep, carriage stopped), the last frames' points, the cloud. Every scan "
    "starts from an idle graph: the bench waits for the face processor's result of the previous cloud (meshing and "
    "identifying a sweep's cloud takes seconds of CPU after the scan's result) before the next goal. "
    "sweep_lines the fewer frames with the matcher's points of the two, "
    "sweep_frames_dropped_pct (slots without a published pair + pairs the matcher gave no points for, scan.json) and "
    "sweep_live_rms_mm (the cloud's RMS distance to the true head) of the face sweeps (the larger); "
    "sweep_camera_lag_s how late the camera delivered the face sweeps' last pair after its exposure ended (the "
    "simulated rig renders slower than 30 fps on a small host; the larger of the two), sweep_scan_minus_render_lag_s "
    "the mean of each face sweep's wall time less its lag (what a real camera at 30 fps would give), "
    "sweep_face_motion_s the mean time from the stream's start to the end of the motion (scan.json "
    "sweep.timeline_s); _full_track the same for the full-track sweep (60 steps/s). Accuracy without ROS (lsu_accuracy.sweep_sim, head 7 at 300 mm, calibration "
    "config/calibration/sim with its laser.yaml): stop-snap 0..470 step 2 with the emulator's vibration 0.1 s "
    f"after each stop vs sweeps at {SWEEP_RATE:g} steps/s, {SWEEP_FPS:g} fps (sheet moving during each 20 ms exposure), "
    f"synchronised and with the right camera {1000 * SWEEP_OFFSET_S:g} ms late (jitter {1000 * SWEEP_JITTER_S:g} ms "
    "std), rendered once each: every left line matched across frames (lsu_reconstruct.sweep.reconstruct_sweep: "
    "to the right line at its mid-exposure carriage position, from 20 Hz stamped positions, or to the two right "
    "lines exposed around it, interpolated along the epipolar line by carriage position) and checked against "
    "the sheet; RMS distance of the raw points to the rendered head mesh, sweep / stop-snap. The sweep's check "
    "against the sheet also rejects stereo mismatches that stop-snap keeps: _checked figures divide by the "
    "stop-snap points that pass the same check. _per_frame: the same 50 ms frames frame by frame "
    "(reconstruct_sweep_frame: each camera's line on the sheet at its own mid-exposure position).")
SWEEP_UNITS = {"sweep_scan_s": "s", "sweep_lines": "lines", "sweep_frames_dropped_pct": "%", "sweep_points": "points",
               "sweep_rms_over_stopsnap": "x", "sweep_rms_over_stopsnap_50ms": "x", "stopsnap_rms_mm": "mm",
               "sweep_rms_mm": "mm", "sweep_50ms_rms_mm": "mm", "sweep_50ms_lines": "lines",
               "sweep_sim_lines": "lines", "stopsnap_sim_lines": "lines", "stopsnap_checked_rms_mm": "mm",
               "sweep_rms_over_stopsnap_checked": "x", "sweep_rms_over_stopsnap_checked_50ms": "x",
               "sweep_50ms_per_frame_rms_mm": "mm", "sweep_rms_over_stopsnap_checked_50ms_per_frame": "x",
               "sweep_live_rms_mm": "mm", "sweep_camera_lag_s": "s", "sweep_scan_minus_render_lag_s": "s",
               "sweep_frames_not_published": "frames", "sweep_frames_not_processed": "frames",
               "sweep_lines_on_face": "lines", "stopsnap_lines_on_face": "lines", "sweep_face_start_steps": "steps",
               "sweep_face_end_steps": "steps", "sweep_face_frames": "frames", "sweep_face_with_move_scan_s": "s",
               "sweep_scan_s_reverse": "s", "sweep_scan_s_forward": "s", "sweep_full_track_scan_s": "s",
               "sweep_full_track_lines_on_face": "lines", "sweep_full_track_frames": "frames",
               "sweep_full_track_camera_lag_s": "s", "sweep_full_track_minus_render_lag_s": "s",
               "sweep_full_track_frames_dropped_pct": "%", "stopsnap_face_scan_s": "s", "sweep_face_motion_s": "s",
               "sweep_face_rate_steps_s": "steps/s"}

LIVE_NOTES = (
    "live: lsu launch sim (6 processes, synthetic head 7), after a 3-snap warm-up scan two scans 0..470 step 2, "
    "settle 0.1 s, texture on: the default one (no bag, like `lsu scan`) gives scan_wall_over_mechanical and "
    "the per-snap figures, one recording its bag in the coordinator (`lsu scan --record`) gives "
    "scan_wall_over_mechanical_recording; bound = moves at the emulator's 200 steps/s + (settle + 33 ms "
    "exposure) per snap + the texture exposure; move/capture: per-snap medians of the move_to and stereo/capture "
    "round trips (the sim's render stands in for the exposure). ")
NOTES = LIVE_NOTES + REPLAY_NOTES + VIEW_NOTES + " " + SETTLE_NOTES + " " + SWEEP_NOTES + (
    " When and how each part was measured: \"measured\" (`--only PART` measures one part again, the others kept).")
# the parts of scan.json, each with its own "measured" note; `--only sweep` is sweep_live and sweep_accuracy
PARTS = ("live", "replay", "view", "two_host", "settle", "sweep_live", "sweep_accuracy")


def measured_note(command: str) -> str:
    """When and by what a part's figures were measured, with the host's load then (the host is shared)."""
    return (f"{time.strftime('%Y-%m-%d %H:%M', time.gmtime())} UTC by `{command}`, load average "
            f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores at the end")


def lines_on_face(folder: Path, scene: str = "head:7") -> dict[int, int]:
    """A scan's lines (snaps or sweep frames) that land on the face: carriage position [steps] -> points on it.

    A line counts when at least ON_FACE_POINTS of its points lie within ON_FACE_MM of the true head surface
    (the sim's scene: it holds the head only, so a line off the head gives no points or a few stray ones).
    """
    import numpy as np

    from lsu_accuracy.accuracy import surface_distances_m
    from lsu_bags.ply import read_ply
    from lsu_sim import build_scene, load_rig

    record = json.loads((folder / "scan.json").read_text())
    position = {int(s["index"]): int(s["position_steps"]) for s in record["snaps"]}
    columns, _faces = read_ply(folder / "cloud.ply")
    xyz = np.stack([columns["x"], columns["y"], columns["z"]], axis=1)
    near = surface_distances_m(build_scene(scene, load_rig()), xyz) * 1000.0 <= ON_FACE_MM
    out = {}
    for index in np.unique(columns["snap"]):
        count = int(np.count_nonzero(near[columns["snap"] == index]))
        if count >= ON_FACE_POINTS:
            out[position[int(index)]] = count
    return out


def sweep_live(tmp: Path) -> dict:
    """Part 6, live: the default stop-snap scan's lines on the face, then sweeps over that range and the whole track."""
    from lsu_scan.scanner import LsuScanner
    from lsu_tools.demo import accuracy_against_scene

    graph = start_sim_graph(tmp, "gp32s", "scans")
    runs: dict = {}
    try:
        with LsuScanner(wait_s=60) as scanner:
            scanner.scan(start=200, end=230, mode="sweep", sweep_rate_steps_s=SWEEP_RATE)  # warm-up

            def scan(name: str, **goal) -> Path:
                result = scanner.scan(**goal)
                if not result.success:
                    raise RuntimeError(f"the {name} scan failed: {result.status}")
                runs[name] = result
                # each scan is timed from an idle graph, as a person sitting for one scan finds it: the face
                # processor meshes and identifies the previous cloud (~5-7 s of CPU for a sweep's) after the
                # scan's result, and would otherwise compete with the next scan's camera on the 2 cores
                graph.wait_for_line(rf"\[face_processor\].*scan {re.escape(Path(result.output_dir).name)}: \d+ points",
                                    timeout_s=120)
                return Path(result.output_dir)

            face = lines_on_face(scan("stopsnap", start=0, end=470, step=2, settle_s=0.1))
            if not face:
                raise RuntimeError("the stop-snap scan has no line on the face")
            lo, hi = max(0, min(face) - FACE_MARGIN_STEPS), min(470, max(face) + FACE_MARGIN_STEPS)
            sweep = {"mode": "sweep", "sweep_rate_steps_s": FACE_SWEEP_RATE, "frame_rate_hz": SWEEP_FPS}
            # the stop-snap scan ended at 470: the full track runs back from there
            scan("full_track", start=0, end=470, **{**sweep, "sweep_rate_steps_s": SWEEP_RATE})
            scan("face_with_move", start=lo, end=hi, **sweep)  # from 0: to the nearer end (lo), then up
            scan("face_reverse", start=lo, end=hi, **sweep)    # from hi, where the last one ended: back down
            scan("face_forward", start=lo, end=hi, **sweep)    # from lo: up
    finally:
        graph.stop(timeout_s=20)
    records = {name: json.loads((Path(r.output_dir) / "scan.json").read_text()) for name, r in runs.items()}
    sweeps = {name: rec["sweep"] for name, rec in records.items() if "sweep" in rec and rec["sweep"]}
    directions = {name: sweeps[name]["direction"] for name in ("full_track", "face_reverse", "face_forward")}
    if directions != {"full_track": "reverse", "face_reverse": "reverse", "face_forward": "forward"}:
        raise RuntimeError(f"the sweeps did not start where the carriage stood: {directions}")
    on_face = {name: lines_on_face(Path(runs[name].output_dir)) for name in ("full_track", "face_reverse", "face_forward")}
    faces = ("face_reverse", "face_forward")
    wall = sum(runs[n].seconds for n in faces) / 2
    lags = {n: max(0.0, float(sweeps[n].get("camera_lag_s", 0.0))) for n in faces}
    timeline = {n: sweeps[n]["timeline_s"] for n in faces}
    motion = sum(t["motion_ended"] - t["stream_started"] for t in timeline.values()) / 2
    full_lag = float(sweeps["full_track"].get("camera_lag_s", 0.0))
    rms = max(accuracy_against_scene(Path(runs[n].output_dir) / "cloud.ply", "head:7")["rms_mm"] for n in faces)
    return {"sweep_scan_s": wall, "sweep_scan_s_reverse": runs["face_reverse"].seconds,
            "sweep_scan_s_forward": runs["face_forward"].seconds,
            "sweep_face_with_move_scan_s": runs["face_with_move"].seconds,
            "sweep_lines_on_face": min(len(on_face[n]) for n in faces), "stopsnap_lines_on_face": len(face),
            "stopsnap_face_scan_s": runs["stopsnap"].seconds,
            "sweep_face_start_steps": lo, "sweep_face_end_steps": hi,
            "sweep_face_frames": min(sweeps[n]["frames_expected"] for n in faces),
            "sweep_lines": min(sweeps[n]["frames_processed"] for n in faces),
            "sweep_points": min(runs[n].points for n in faces),
            "sweep_frames_dropped_pct": max(sweeps[n]["frames_dropped_pct"] for n in faces),
            "sweep_frames_not_published": max(sweeps[n]["frames_not_published"] for n in faces),
            "sweep_frames_not_processed": max(sweeps[n]["frames_not_processed"] for n in faces),
            "sweep_live_rms_mm": rms, "sweep_camera_lag_s": max(lags.values()),
            "sweep_scan_minus_render_lag_s": sum(runs[n].seconds - lags[n] for n in faces) / 2,
            "sweep_face_motion_s": motion, "sweep_face_rate_steps_s": FACE_SWEEP_RATE,
            "sweep_full_track_scan_s": runs["full_track"].seconds,
            "sweep_full_track_frames": sweeps["full_track"]["frames_processed"],
            "sweep_full_track_lines_on_face": len(on_face["full_track"]),
            "sweep_full_track_frames_dropped_pct": sweeps["full_track"]["frames_dropped_pct"],
            "sweep_full_track_camera_lag_s": full_lag,
            "sweep_full_track_minus_render_lag_s": runs["full_track"].seconds - max(0.0, full_lag)}


def sweep_accuracy() -> dict:
    """Part 5, without ROS: RMS to the rendered head of sweeps against stop-snap, same scene and physics."""
    from lsu_accuracy.accuracy import surface_rms_mm
    from lsu_accuracy.sweep_sim import reconstruct_rendered, render_sweep, stopsnap_scene
    from lsu_config import config_dir
    from lsu_reconstruct.laser_sheet import read_laser_yaml
    from lsu_reconstruct.stereo import StereoModel
    from lsu_sim import build_scene, load_rig

    calib = config_dir() / "calibration" / "sim"
    model, sheet = StereoModel.from_folder(calib), read_laser_yaml(calib / "laser.yaml")
    geometry = load_rig()
    head = build_scene("head:7", geometry)
    stop = stopsnap_scene(model, geometry, head, seed=7, sheet=sheet)
    sync = reconstruct_rendered(model, sheet, render_sweep(geometry, head, SWEEP_RATE, SWEEP_FPS, seed=7))
    late_frames = render_sweep(geometry, head, SWEEP_RATE, SWEEP_FPS, offset_s=SWEEP_OFFSET_S,
                               jitter_s=SWEEP_JITTER_S, seed=7)
    late = reconstruct_rendered(model, sheet, late_frames)
    late_per_frame = reconstruct_rendered(model, sheet, late_frames, cross_frame=False)
    rms = {name: surface_rms_mm(head, scan.xyz)
           for name, scan in (("stop", stop), ("sync", sync), ("late", late), ("late_per_frame", late_per_frame))}
    rms["stop_checked"] = surface_rms_mm(head, stop.checked_xyz)
    return {"sweep_rms_over_stopsnap": rms["sync"] / rms["stop"], "sweep_rms_over_stopsnap_50ms": rms["late"] / rms["stop"],
            "stopsnap_rms_mm": rms["stop"], "sweep_rms_mm": rms["sync"], "sweep_50ms_rms_mm": rms["late"],
            "sweep_50ms_lines": late.lines, "sweep_sim_lines": sync.lines, "stopsnap_sim_lines": stop.lines,
            "stopsnap_checked_rms_mm": rms["stop_checked"],
            "sweep_rms_over_stopsnap_checked": rms["sync"] / rms["stop_checked"],
            "sweep_rms_over_stopsnap_checked_50ms": rms["late"] / rms["stop_checked"],
            "sweep_50ms_per_frame_rms_mm": rms["late_per_frame"],
            "sweep_rms_over_stopsnap_checked_50ms_per_frame": rms["late_per_frame"] / rms["stop_checked"]}



PERSON_SCENE = "person:7"
PERSON_FRAME_PERIOD_S = 0.033  # the adaptive settle's frames: a 30 fps camera (the coordinator's exposure_s)
PERSON_UNITS = {"stopsnap_points_over_1mm_pct": "%", "stopsnap_points_over_1mm_pct_unfiltered": "%",
                "person_stopsnap_rms_mm": "mm", "person_stopsnap_rms_mm_unfiltered": "mm",
                "person_stopsnap_points": "points", "person_stopsnap_points_unfiltered": "points",
                "adaptive_settle_rms_over_fixed": "x", "adaptive_settle_time_over_fixed": "x",
                "adaptive_settle_rms_mm": "mm", "fixed_settle_rms_mm": "mm", "adaptive_settle_frames_per_snap": "frames"}
PERSON_NOTES = (
    f" person_stopsnap (`--only person_stopsnap`, no ROS: lsu_accuracy.sweep_sim.stopsnap_scene): the realistic person "
    f"{PERSON_SCENE} at the subject distance, stop-snap 0..470 step 2 rendered by the simulated rig with the emulator's "
    "post-stop vibration, extracted and matched as the graph does, the cloud as the matcher node publishes it; distances "
    "to the rendered meshes (skin and hair: the sim's truth). stopsnap_points_over_1mm_pct: points farther than 1 mm "
    "from the true surface, % of the cloud (settle fixed 0.1 s); _unfiltered: the same frames matched without the "
    "matcher's piece-length rule (min_run_rows 0) and without the grazing-view rule (max_view_angle_deg 90). "
    "adaptive_settle_*: the same scan taken with the adaptive settle (lsu_scan.settle.rendered_settle: frames every "
    f"{PERSON_FRAME_PERIOD_S} s from a probe at a phase of the first frame period that differs per snap, the fixed "
    "settle as its bound), same sensor noise seeds for the snaps that agree at once: rms_over_fixed = the clouds' RMS "
    "distance to the true surface, adaptive / fixed; time_over_fixed = mean snap exposure start after the stop, "
    "adaptive / fixed (simulated time: what a 30 fps camera gives, not the sim graph's wall time, where each capture is "
    "a ~40 ms render: stopsnap_adaptive_over_fixed).")


def person_stopsnap_figures() -> dict:
    """Stop-snap accuracy on a realistic person without ROS: far points (filters on and off) and adaptive vs fixed settle."""
    import numpy as np

    from lsu_accuracy.accuracy import surface_distances_m
    from lsu_accuracy.sweep_sim import stopsnap_scene
    from lsu_config import config_dir
    from lsu_reconstruct.matching import MatchParams
    from lsu_reconstruct.stereo import StereoModel
    from lsu_scan.settle import rendered_settle
    from lsu_sim import build_scene, load_rig

    geometry = load_rig()
    person = build_scene(PERSON_SCENE, geometry)
    model = StereoModel.from_folder(config_dir() / "calibration" / "sim")

    def adaptive(rig, state, index):
        first = (index * 0.618034) % 1.0 * PERSON_FRAME_PERIOD_S
        frame, t_snap, rendered, _trace = rendered_settle(
            lambda t, seed: rig.render(state, capture_time_s=t, seed=seed), first, PERSON_FRAME_PERIOD_S, 0.1,
            seed=7 + index)
        return frame, t_snap, rendered

    scans = {"fixed": stopsnap_scene(model, geometry, person, seed=7),
             "unfiltered": stopsnap_scene(model, geometry, person, seed=7, params=MatchParams(min_run_rows=0),
                                          max_view_angle_deg=90.0),
             "adaptive": stopsnap_scene(model, geometry, person, seed=7, capture=adaptive)}
    dist = {name: surface_distances_m(person, scan.xyz) * 1000.0 for name, scan in scans.items()}
    rms = {name: float(np.sqrt(np.mean(d * d))) for name, d in dist.items()}
    times = {name: float(np.mean(scans[name].snap_after_stop_s)) for name in ("fixed", "adaptive")}
    return {"stopsnap_points_over_1mm_pct": float(100.0 * np.mean(dist["fixed"] > 1.0)),
            "stopsnap_points_over_1mm_pct_unfiltered": float(100.0 * np.mean(dist["unfiltered"] > 1.0)),
            "person_stopsnap_rms_mm": rms["fixed"], "person_stopsnap_rms_mm_unfiltered": rms["unfiltered"],
            "person_stopsnap_points": float(len(dist["fixed"])),
            "person_stopsnap_points_unfiltered": float(len(dist["unfiltered"])),
            "adaptive_settle_rms_over_fixed": rms["adaptive"] / rms["fixed"],
            "adaptive_settle_time_over_fixed": times["adaptive"] / times["fixed"],
            "adaptive_settle_rms_mm": rms["adaptive"], "fixed_settle_rms_mm": rms["fixed"],
            "adaptive_settle_frames_per_snap": scans["adaptive"].captures / len(scans["adaptive"].snap_after_stop_s)}

# ---------------------------------------------------------------- a living subject (issue 36)
MOTION_SUBJECTS = ("person:2",)      # every kind of motion scanned on each (one person: the bench takes ~20 min)
MOTION_KINDS_BENCH = ("still", "seated", "standing", "turn")
MOTION_FPS_60, MOTION_RATE_60 = 60.0, 2 * FACE_SWEEP_RATE
MOTION_NOTES = (
    " motion (`--only motion`, no ROS; lsu_accuracy.motion_sim): sweeps over each person's face (the carriage "
    "positions whose sheet crosses the true landmarks, +-4 mm) at the face sweep's rate and 30 fps of "
    f"{', '.join(MOTION_SUBJECTS)} moving as lsu_sim.motion's still, seated, standing and turn (seated sway plus a "
    "15 deg turn in 0.4 s a third into the sweep: beyond the stated limit of 5 deg / 40 mm/s), motion seed = person "
    "seed, the subject's pose updated at 15 Hz; the motion measured from the frames' texture and the points "
    "corrected (lsu_reconstruct.motion). motion_rms_mm_<kind>_raw/_corrected: RMS distance of the cloud (raw: each line "
    "where it was seen; corrected: moved back to the middle frame's pose) to the person's meshes at the middle "
    "frame's true pose, mean over the people; motion_rms_standing_corrected_over_still the corrected standing RMS "
    "over the still one; motion_flagged_pct_<kind>: scans flagged as beyond correction (beyond_limit = turn); "
    "motion_pose_error_mm_<kind>: median distance between the measured and true displacement of the fitted points' "
    "centre. 60 fps (sweep at twice the rate, same lines): sweep_60fps_rms_mm beside sweep_30fps_rms_mm, still "
    "person, raw points; motion_rms_mm_standing_corrected_60fps. motion_bench_s: this part's wall time. "
    "sweep_scan_s_60fps (`--only motion_live`): live on lsu launch sim (person 2, still), a face sweep at "
    f"{MOTION_RATE_60:g} steps/s and {MOTION_FPS_60:g} fps over the face range of sweep_face_start/end_steps, action "
    "wall time, beside a 30 fps one at the face rate (sweep_scan_s_30fps_motion_live); "
    "sweep_scan_minus_render_lag_s_<fps>fps: each less its sweep_camera_lag (the simulated camera renders slower than "
    "the frame rate: what a real camera at that rate would give). motion_live_*_<fps>fps: the live graph's motion "
    "measurement of those sweeps (stereo_matcher, lsu_reconstruct.motion.SweepMotion, at most motion_max_frames "
    "frames): flagged (1/0, a still person: 0 expected), the measured motion [mm], the frames measured and the CPU "
    "time it added before the cloud was out (compute_s). sweep_60fps_render_cpu_ms_per_pair: the simulated camera's "
    "CPU per stereo pair of that 60 fps sweep (person 2, both views on one thread as the camera stream renders, a "
    "fresh rig per sweep, no ROS, measured before the graph starts), with its shadow rays cast once per pixel and "
    "pose (the default) and _uncached with one per pixel and frame (the renderer's images before the cache, bit for "
    "bit), alternated over MOTION_RENDER_ROUNDS sweeps each; sweep_60fps_render_cpu_over_uncached their ratio.")
MOTION_RENDER_ROUNDS = 2
MOTION_UNITS = {"sweep_60fps_render_cpu_ms_per_pair": "ms", "sweep_60fps_render_cpu_ms_per_pair_uncached": "ms",
                "sweep_60fps_render_cpu_over_uncached": "x","motion_rms_standing_corrected_over_still": "x", "motion_rms_standing_raw_over_still": "x",
                "motion_flagged_pct_beyond_limit": "%", "motion_flagged_pct_still": "%",
                "motion_flagged_pct_seated": "%", "motion_flagged_pct_standing": "%", "sweep_scan_s_60fps": "s",
                "sweep_scan_s_30fps_motion_live": "s", "sweep_60fps_rms_mm": "mm", "sweep_30fps_rms_mm": "mm",
                "sweep_60fps_rms_over_30fps": "x", "motion_rms_mm_standing_corrected_60fps": "mm",
                "motion_bench_s": "s", "sweep_60fps_frames_dropped_pct": "%", "sweep_60fps_camera_lag_s": "s",
                **{f"{name}_{fps}fps": unit for fps in ("30", "60") for name, unit in (
                    ("sweep_scan_minus_render_lag_s", "s"), ("motion_live_flagged", "1/0"),
                    ("motion_live_measured_mm", "mm"), ("motion_live_compute_s", "s"), ("motion_live_frames", "frames"))},
                **{f"motion_rms_mm_{k}_{c}": "mm" for k in MOTION_KINDS_BENCH for c in ("raw", "corrected")},
                **{f"motion_pose_error_mm_{k}": "mm" for k in MOTION_KINDS_BENCH}}


def motion_figures() -> dict:
    """A living subject without ROS: accuracy still / seated / standing, raw and corrected, flagging, 60 fps."""
    import numpy as np

    from lsu_accuracy.accuracy import surface_rms_mm
    from lsu_accuracy.motion_sim import face_range_steps, motion_scan
    from lsu_accuracy.sweep_sim import reconstruct_rendered, render_sweep
    from lsu_config import config_dir
    from lsu_reconstruct.laser_sheet import read_laser_yaml
    from lsu_reconstruct.stereo import StereoModel
    from lsu_sim import build_scene, load_rig

    started = time.monotonic()
    calib = config_dir() / "calibration" / "sim"
    model, sheet = StereoModel.from_folder(calib), read_laser_yaml(calib / "laser.yaml")
    geometry = load_rig()
    rms: dict = {}
    flagged: dict = {}
    pose_err: dict = {}
    out: dict = {}
    for subject in MOTION_SUBJECTS:
        objects = build_scene(subject, geometry)
        seed = int(subject.rsplit(":", 1)[1])
        for kind in MOTION_KINDS_BENCH:
            scan = motion_scan(model, sheet, geometry, objects, kind, seed=seed, rate_steps_s=FACE_SWEEP_RATE)
            rms.setdefault(kind, []).append((scan.rms_mm(objects, corrected=False), scan.rms_mm(objects)))
            flagged.setdefault(kind, []).append(scan.estimate.flagged)
            pose_err.setdefault(kind, []).append(float(np.median(scan.pose_errors_mm())))
            print(f"[motion] {subject} {kind}: raw {rms[kind][-1][0]:.3f} mm, corrected {rms[kind][-1][1]:.3f} mm, "
                  f"flagged {scan.estimate.flagged}, {scan.frames} frames", flush=True)
        if subject == MOTION_SUBJECTS[0]:
            lo, hi = face_range_steps(geometry, objects)
            for fps, rate in ((SWEEP_FPS, FACE_SWEEP_RATE), (MOTION_FPS_60, MOTION_RATE_60)):
                still = reconstruct_rendered(model, sheet, render_sweep(geometry, objects, rate, fps, lo, hi, seed=seed))
                out[f"sweep_{fps:g}fps_rms_mm"] = surface_rms_mm(objects, still.xyz)
            fast = motion_scan(model, sheet, geometry, objects, "standing", seed=seed, rate_steps_s=MOTION_RATE_60,
                               fps=MOTION_FPS_60)
            out["motion_rms_mm_standing_corrected_60fps"] = fast.rms_mm(objects)
    for kind in MOTION_KINDS_BENCH:
        out[f"motion_rms_mm_{kind}_raw"] = float(np.mean([r[0] for r in rms[kind]]))
        out[f"motion_rms_mm_{kind}_corrected"] = float(np.mean([r[1] for r in rms[kind]]))
        out[f"motion_pose_error_mm_{kind}"] = float(np.mean(pose_err[kind]))
        name = "beyond_limit" if kind == "turn" else kind
        out[f"motion_flagged_pct_{name}"] = 100.0 * float(np.mean(flagged[kind]))
    out["motion_rms_standing_corrected_over_still"] = out["motion_rms_mm_standing_corrected"] / out["motion_rms_mm_still_corrected"]
    out["motion_rms_standing_raw_over_still"] = out["motion_rms_mm_standing_raw"] / out["motion_rms_mm_still_corrected"]
    out["sweep_60fps_rms_over_30fps"] = out["sweep_60fps_rms_mm"] / out["sweep_30fps_rms_mm"]
    out["motion_bench_s"] = time.monotonic() - started
    return out


# faces of a living subject (issue 36): identification on corrected standing sweeps against still ones
MOTION_FACES_N = int(os.environ.get("LSU_BENCH_MOTION_FACES_N", "20"))
MOTION_FACES_NOTES = (
    " motion_faces (`--only motion_faces`, no ROS; lsu_accuracy.motion_sim.face_sweeps): face identification on sweeps "
    f"of moving people: {MOTION_FACES_N} people of the face model (ICT, MIT; the face bench's population seeds "
    "bench_faces.POP_SEED.., never used for tuning; scene person:ict:SEED, neutral, frontal), each swept over the face "
    "range widened by motion_sim.FACE_SWEEP_MARGIN_M (20 mm: the nose finder needs the face around the nose) at "
    "the face sweep's rate and 30 fps: an enrolment from a still sweep (render seed 2 i), then probes of a "
    "second sweep (render and motion seed 2 i + 1): still, and standing (lsu_sim.motion) as reconstructed (raw) and "
    "as corrected. Every cloud through lsu face's pipeline (lsu_faces.pipeline.process_cloud), the enrolments in a "
    "fresh lsu_faces Gallery, each probe identified by Gallery.identify: motion_face_rank1_pct_<probe> = probes "
    "whose nearest name is their own (a probe without a face counts as a miss); "
    "motion_face_rank1_standing_corrected_minus_still (goal >= 0: corrected standing identified as well as still); "
    "motion_face_accepted_pct_<probe>: probes identified as their own person and accepted by the gallery's open-set "
    "rule at its default false-accept rate (lsu face identify's exit 0); "
    "motion_face_genuine_mm_<probe>: median full-comparison distance of a probe to its own enrolment; "
    "motion_face_corrected_nearer_pct: people whose corrected standing probe is nearer their enrolment than the raw "
    "one; motion_face_flagged_pct: standing sweeps flagged beyond correction; motion_faces_bench_s: this part's "
    "wall time (bench_faces' pool of POP_WORKERS processes, a host shared with other jobs).")
MOTION_FACE_PROBES = {"still": "still", "moving_raw": "standing_raw", "moving_corrected": "standing_corrected"}
MOTION_FACES_UNITS = {**{f"motion_face_rank1_pct_{n}": "%" for n in MOTION_FACE_PROBES.values()},
                      **{f"motion_face_accepted_pct_{n}": "%" for n in MOTION_FACE_PROBES.values()},
                      **{f"motion_face_genuine_mm_{n}": "mm" for n in MOTION_FACE_PROBES.values()},
                      "motion_face_rank1_standing_corrected_minus_still": "pct points",
                      "motion_face_corrected_nearer_pct": "%", "motion_face_flagged_pct": "%",
                      "motion_face_people": "people", "motion_face_refused_pct": "%", "motion_faces_bench_s": "s"}


def motion_face_person(seed: int) -> dict:
    """One person's signatures (bytes, b"" where no face was found): still enrolment, still and standing probes;
    cached by content in bench_faces' cache (the code of the sweeps, the motion and the face pipeline)."""
    import hashlib
    import importlib
    import pickle

    from bench_faces import CACHE, POP_SEED, _code_tag

    h = hashlib.sha256(f"motion-face-{seed}-{_code_tag()}-{FACE_SWEEP_RATE}".encode())
    for mod in ("lsu_accuracy.motion_sim", "lsu_accuracy.sweep_sim", "lsu_reconstruct.motion", "lsu_reconstruct.sweep",
                "lsu_sim.motion", "lsu_faces.pipeline"):
        h.update(Path(importlib.import_module(mod).__file__ or "").read_bytes())
    cached = CACHE / f"motion-face-{h.hexdigest()[:24]}.pkl"
    if cached.is_file():
        return pickle.loads(cached.read_bytes())  # noqa: S301 (this benchmark's own cache)

    from lsu_accuracy.motion_sim import face_sweeps
    from lsu_config import config_dir
    from lsu_reconstruct.laser_sheet import read_laser_yaml
    from lsu_reconstruct.stereo import StereoModel
    from lsu_sim import build_scene, load_rig

    calib = config_dir() / "calibration" / "sim"
    geometry = load_rig()
    t0 = time.monotonic()
    index = seed - POP_SEED
    found = face_sweeps(StereoModel.from_folder(calib), read_laser_yaml(calib / "laser.yaml"), geometry,
                        build_scene(f"person:ict:{seed}", geometry), "standing", enrol_seed=2 * index,
                        probe_seed=2 * index + 1, rate_steps_s=FACE_SWEEP_RATE)
    print(f"[motion faces] person {seed}: {time.monotonic() - t0:.0f} s, flagged {found.flagged}, points "
          f"{found.points}, {[k for k, v in found.probes.items() if v is None]} without a face", flush=True)
    out = {"seed": seed, "enrolment": found.enrolment.to_bytes() if found.enrolment is not None else b"",
           "flagged": found.flagged,
           **{name: sig.to_bytes() if sig is not None else b"" for name, sig in found.probes.items()}}
    CACHE.mkdir(parents=True, exist_ok=True)
    cached.write_bytes(pickle.dumps(out))
    return out


def motion_face_figures() -> dict:
    """Rank-1 identification of still and standing (raw, corrected) sweep probes against still sweep enrolments."""
    import numpy as np
    from bench_faces import POP_SEED, POP_WORKERS, _parallel

    from lsu_faces.gallery import Gallery
    from lsu_faces.signature import Signature, compare

    started = time.monotonic()
    seeds = [POP_SEED + i for i in range(MOTION_FACES_N)]
    # a pool per POP_WORKERS people: they finish in order, each cached, so a run cut short leaves its first people
    people = [p for k in range(0, len(seeds), POP_WORKERS) for p in _parallel(motion_face_person, seeds[k:k + POP_WORKERS])]
    out: dict = {}
    with tempfile.TemporaryDirectory(prefix="lsu-bench-motion-faces-") as tmp:
        gallery = Gallery(Path(tmp) / "gallery.db")
        enrolled = {p["seed"]: Signature.from_bytes(p["enrolment"]) for p in people if p["enrolment"]}
        for seed, sig in enrolled.items():
            gallery.enroll(str(seed), sig)
        genuine: dict = {}
        for probe, name in MOTION_FACE_PROBES.items():
            hits, accepted = [], []
            for p in people:
                sig = Signature.from_bytes(p[probe]) if p[probe] else None
                if sig is None or p["seed"] not in enrolled:
                    hits.append(False)
                    accepted.append(False)
                    continue
                found = gallery.identify(sig, max_results=len(enrolled))
                hits.append(bool(found.matches) and found.matches[0].name == str(p["seed"]))
                accepted.append(hits[-1] and found.accepted)
                genuine.setdefault(probe, {})[p["seed"]] = compare(sig, enrolled[p["seed"]])[1] * 1000.0
            out[f"motion_face_rank1_pct_{name}"] = 100.0 * float(np.mean(hits))
            out[f"motion_face_accepted_pct_{name}"] = 100.0 * float(np.mean(accepted))
            out[f"motion_face_genuine_mm_{name}"] = float(np.median(list(genuine.get(probe, {}).values()) or [np.nan]))
    raw, corrected = genuine.get("moving_raw", {}), genuine.get("moving_corrected", {})
    both = [s for s in raw if s in corrected]
    out["motion_face_rank1_standing_corrected_minus_still"] = (out["motion_face_rank1_pct_standing_corrected"]
                                                               - out["motion_face_rank1_pct_still"])
    out["motion_face_corrected_nearer_pct"] = 100.0 * float(np.mean([corrected[s] < raw[s] for s in both])) \
        if both else float("nan")
    out["motion_face_flagged_pct"] = 100.0 * float(np.mean([p["flagged"] for p in people]))
    out["motion_face_refused_pct"] = 100.0 * float(np.mean([not p[k] for p in people
                                                            for k in ("enrolment", *MOTION_FACE_PROBES)]))
    out["motion_face_people"] = float(len(enrolled))
    out["motion_faces_bench_s"] = time.monotonic() - started
    print("[motion faces] " + ", ".join(f"{k}={v:.3g}" for k, v in out.items()), flush=True)
    return out

def motion_render_cpu(lo: int, hi: int) -> dict:
    """CPU per pair of the simulated camera rendering the 60 fps face sweep, shadow cache on and off (MOTION_NOTES)."""
    from lsu_sim import CarriageState, SimulatedRig, build_scene, load_rig

    geometry = load_rig(None)
    scene = build_scene("person:2", geometry)
    frames = int((hi - lo) / MOTION_RATE_60 * MOTION_FPS_60)
    cpu: dict[bool, list[float]] = {True: [], False: []}
    for _ in range(MOTION_RENDER_ROUNDS):
        for cached in (True, False):
            rig = SimulatedRig(geometry, scene, seed=0, shadow_cache=cached)
            rig.render(CarriageState(float(lo), False), capture_time_s=99.0, seed=0, parallel=False)  # sensor caches
            state = CarriageState(float(lo), True, velocity_steps_per_s=MOTION_RATE_60, position_time_s=100.0)
            start = time.process_time()
            for index in range(frames):
                rig.render(state, capture_time_s=100.0 + index / MOTION_FPS_60, seed=index, parallel=False)
            cpu[cached].append(1e3 * (time.process_time() - start) / frames)
    cached_ms, uncached_ms = statistics.median(cpu[True]), statistics.median(cpu[False])
    return {"sweep_60fps_render_cpu_ms_per_pair": cached_ms, "sweep_60fps_render_cpu_ms_per_pair_uncached": uncached_ms,
            "sweep_60fps_render_cpu_over_uncached": cached_ms / uncached_ms}


def motion_live(tmp: Path) -> dict:
    """sweep_scan_s_60fps: a face sweep at 60 fps and twice the rate, live, beside one at 30 fps."""
    from lsu_scan.scanner import LsuScanner

    old = json.loads((Path(__file__).resolve().parent / "results" / "scan.json").read_text())["figures"]
    lo, hi = int(old.get("sweep_face_start_steps", 82)), int(old.get("sweep_face_end_steps", 438))
    render = motion_render_cpu(lo, hi)
    graph = start_sim_graph(tmp, "gp32m", "scans", scene="person:2")
    runs: dict = {}
    try:
        with LsuScanner(wait_s=60) as scanner:
            scanner.scan(start=200, end=230, mode="sweep", sweep_rate_steps_s=SWEEP_RATE)  # warm-up
            for name, rate, fps in (("30", FACE_SWEEP_RATE, SWEEP_FPS), ("60", MOTION_RATE_60, MOTION_FPS_60)):
                scanner.scan(start=lo, end=lo + 1, mode="sweep", sweep_rate_steps_s=SWEEP_RATE)  # to the range's start
                result = scanner.scan(start=lo, end=hi, mode="sweep", sweep_rate_steps_s=rate, frame_rate_hz=fps)
                if not result.success:
                    raise RuntimeError(f"the {name} fps sweep failed: {result.status}")
                runs[name] = result
                graph.wait_for_line(rf"\[face_processor\].*scan {re.escape(Path(result.output_dir).name)}: \d+ points",
                                    timeout_s=120)
    finally:
        graph.stop(timeout_s=20)
    records = {name: json.loads((Path(run.output_dir) / "scan.json").read_text()) for name, run in runs.items()}
    sweep60 = records["60"].get("sweep", {})
    out = {"sweep_scan_s_60fps": runs["60"].seconds, "sweep_scan_s_30fps_motion_live": runs["30"].seconds,
           "sweep_60fps_frames_dropped_pct": float(sweep60.get("frames_dropped_pct", float("nan"))),
           "sweep_60fps_camera_lag_s": float(sweep60.get("camera_lag_s", float("nan"))), **render}
    for name, record in records.items():
        lag = float(record.get("sweep", {}).get("camera_lag_s", float("nan")))
        out[f"sweep_scan_minus_render_lag_s_{name}fps"] = runs[name].seconds - lag
        # the live graph's motion measurement of a still person: not flagged, and what it cost before the cloud
        motion = record.get("motion", {})
        out[f"motion_live_flagged_{name}fps"] = float(bool(motion.get("flagged")))
        out[f"motion_live_measured_mm_{name}fps"] = float(motion.get("measured_motion_mm", float("nan")))
        out[f"motion_live_compute_s_{name}fps"] = float(motion.get("compute_s", float("nan")))
        out[f"motion_live_frames_{name}fps"] = float(len(motion.get("frames", [])))
    return out


def only(parts: set, bag: Path | None = None) -> int:
    """Measure only the named parts (`PARTS`; sweep = sweep_live + sweep_accuracy) and merge them into the existing scan.json."""
    unknown = parts - {"live", "replay", "view", "two_host", "settle", "sweep", "sweep_live", "sweep_accuracy", "web",
                       "person_stopsnap", "motion", "motion_live", "motion_faces"}
    if unknown:
        raise SystemExit("--only takes live, replay, view, two_host, settle, sweep, sweep_live, sweep_accuracy, web, "
                         "person_stopsnap, motion, motion_live, motion_faces (comma-separated); "
                         f"not {', '.join(sorted(unknown))}")
    claim = rosenv.isolate()
    figures: dict = {}
    failure = None
    replay_source = ""
    try:
        with tempfile.TemporaryDirectory(prefix="lsu-bench-scan-") as tmp_name:
            tmp = Path(tmp_name)
            if "replay" in parts:
                source = "a recorded scan bag given with --bag" if bag else "a bag written by lsu_testing.simbags (synthetic head 7, " \
                    "0..470 step 2 + texture pair, rendered by the simulated rig without the graph)"
                replay_bag = bag or sim_bag(tmp)
                figures.update(replay_figures(replay_bag))
                figures.update(replay_before_figures(replay_bag))
                replay_source = source
            if "live" in parts:
                figures.update(live_figures(live_scan(tmp, baseline=True, view=False)))
            if "view" in parts:
                figures.update(view_figures(live_scan(tmp, baseline=False, view=True)))
            if "settle" in parts:
                figures.update(settle_figures(tmp))
            if "web" in parts:
                figures.update(web_figures(tmp))
            if parts & {"sweep", "sweep_live"}:
                figures.update(sweep_live(tmp))
            if parts & {"sweep", "sweep_accuracy"}:
                figures.update(sweep_accuracy())
            if "person_stopsnap" in parts:
                figures.update(person_stopsnap_figures())
            if "motion" in parts:
                figures.update(motion_figures())
            if "motion_live" in parts:
                figures.update(motion_live(tmp))
            if "motion_faces" in parts:
                figures.update(motion_face_figures())
            if "two_host" in parts:
                unavailable = why_unavailable()
                if unavailable is not None:
                    raise SystemExit(f"two_host figures need network namespaces: {unavailable}")
                try:
                    figures.update(two_host_figures(two_host_runs(tmp)))
                except RuntimeError as exc:
                    failure = exc  # the view figures measured so far are still written
                    parts = parts - {"two_host"}
    finally:
        claim.release()
    path = Path(__file__).resolve().parent / "results" / "scan.json"
    old = json.loads(path.read_text()) if path.is_file() else {"figures": {}, "units": {}, "notes": ""}
    merged = {**old["figures"], **figures}
    note = measured_note(f"bench_scan.py --only {','.join(sorted(parts))}")
    done = {p for part in parts for p in (("sweep_live", "sweep_accuracy") if part == "sweep" else (part,))}
    measured = {**old.get("measured", {}), **{part: note for part in done}}
    if "replay" in parts:
        measured["replay"] += f", on {replay_source}"
    if "settle" in parts:
        measured["settle"] += f", scene {os.environ.get('LSU_BENCH_SETTLE_SCENE', 'head:7')}"
    if parts:
        write_result("scan", merged, {**old["units"], **LIVE_UNITS, **UNITS, **REPLAY_UNITS, **REPLAY_BEFORE_UNITS,
                                      **SETTLE_UNITS, **SWEEP_UNITS, **WEB_UNITS, **PERSON_UNITS, **MOTION_UNITS,
                                      **MOTION_FACES_UNITS},
                     notes=NOTES + WEB_NOTES + PERSON_NOTES + MOTION_NOTES + MOTION_FACES_NOTES,
                     extra={"measured": measured})
    if failure is not None:
        print(f"two_host figures not measured: {str(failure)[:2000]}", file=sys.stderr)
        return 1
    return 0


def main() -> int:
    if len(sys.argv) > 2 and sys.argv[1] == "--only":
        bag = Path(sys.argv[4]) if len(sys.argv) > 4 and sys.argv[3] == "--bag" else None
        return only(set(sys.argv[2].split(",")), bag)
    claim = rosenv.isolate()
    try:
        with tempfile.TemporaryDirectory(prefix="lsu-bench-scan-") as tmp_name:
            tmp = Path(tmp_name)
            runs = live_scan(tmp)
            # medians of REPLAYS runs (each in a fresh process): one run is at the mercy of the host's noise
            replays = replay_figures(Path(runs["recording"]["result"].output_dir) / "bag")
            replays.update(replay_before_figures(Path(runs["recording"]["result"].output_dir) / "bag"))
            unavailable = why_unavailable()
            walls = two_host_runs(tmp) if unavailable is None else {}
            settle = settle_figures(tmp)
            sweep = {**sweep_live(tmp), **sweep_accuracy()}
            web = web_figures(tmp)
            web.update(person_stopsnap_figures())
            motion = {**motion_figures(), **motion_live(tmp), **motion_face_figures()}
    finally:
        claim.release()
    write_result(
        "scan",
        {**live_figures(runs), **replays, **view_figures(runs), **two_host_figures(walls), **settle, **sweep, **web,
         **motion},
        {**LIVE_UNITS, **REPLAY_UNITS, **REPLAY_BEFORE_UNITS, **UNITS, **SETTLE_UNITS, **SWEEP_UNITS, **WEB_UNITS,
         **PERSON_UNITS, **MOTION_UNITS, **MOTION_FACES_UNITS},
        notes=NOTES + WEB_NOTES + PERSON_NOTES + MOTION_NOTES + MOTION_FACES_NOTES,
        extra={"measured": {part: measured_note("make bench-scan")
                            for part in (*PARTS, "web", "person_stopsnap", "motion", "motion_live", "motion_faces")
                            if part != "two_host" or unavailable is None}})
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Scan benchmark: live sim scan wall time against the mechanical lower bound, and bag replay speed.

    make bench-scan   ->  bench/results/scan.json

1. `lsu launch sim` (separate processes, synthetic head), two full scans 0..470 step 2, settle 0.1 s:
   a default one (what `lsu scan` does: no bag) and one recording its bag (`lsu scan --record`).
   scan_wall_over_mechanical = the default scan's action wall time / (moves at the emulator's rate +
   settle + exposure for every snap), the bound the coordinator computes from the parameters;
   scan_wall_over_mechanical_recording: the same for the recording scan.
2. The recorded bag's snaps replayed closed-loop (images + events as raw CDR, each snap waiting for
   its /lsu/points) into `lsu run replay` (extractor + matcher in one process), three times, each in a
   fresh graph: replay_snaps_per_s is the median run, replay_cpu_ms_per_snap that run's CPU per snap.
"""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import write_result

from lsu_bringup import rosenv


def live_scan(tmp: Path) -> dict:
    from lsu_bringup.scanner import LsuScanner
    from lsu_bringup.testing import LaunchedProcess

    graph = LaunchedProcess(["launch", "sim", f"port:={tmp}/gp32", "scene:=head:7", f"output_dir:={tmp}/scans"])
    try:
        graph.wait_for_line(r"homed: track", timeout_s=120)
        graph.wait_for_line(r"source 'sim' open", timeout_s=120)
        runs = {}
        with LsuScanner(wait_s=60) as scanner:
            # one short warm-up scan: first-call costs (imports, caches) are not the steady state we measure
            scanner.scan(start=230, end=240, step=5, settle_s=0.1, output_dir=str(tmp / "warmup"))
            for name, record_bag in (("default", False), ("recording", True)):
                scanner.start_scan(start=0, end=470, step=2, settle_s=0.1, record_bag=record_bag)
                result = scanner.get_result(timeout_s=600)  # a lost result fails the benchmark instead of hanging it
                if not result.success:
                    raise RuntimeError(f"the {name} scan failed: {result.status}")
                runs[name] = {"result": result,
                              "record": json.loads((Path(result.output_dir) / "scan.json").read_text())}
    finally:
        graph.interrupt(timeout_s=30)
        graph.kill()
    return runs


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


REPLAYS = 3


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

    from lsu_bringup.bags import deserialize_ros, read_messages
    from lsu_bringup.testing import LaunchedProcess
    from lsu_interfaces.msg import ScanEvent

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
        graph.interrupt(timeout_s=20)
        graph.kill()
    return {"snaps": done, "seconds": seconds, "cpu_s": cpu, "missing_in_bag": missing}


def main() -> int:
    claim = rosenv.isolate()
    try:
        with tempfile.TemporaryDirectory(prefix="lsu-bench-scan-") as tmp_name:
            tmp = Path(tmp_name)
            runs = live_scan(tmp)
            default, recording = runs["default"], runs["recording"]
            result, record = default["result"], default["record"]
            bound = record["timings_s"]["mechanical_lower_bound"]
            acks = sorted(s.get("ack_s", 0.0) for s in record["snaps"])
            # where a snap's time goes (the coordinator records each phase per snap; the first snap's move
            # from the texture position is left out)
            phases = {name: sorted(s[f"{name}_s"] for s in record["snaps"][1:] if f"{name}_s" in s) or [0.0]
                      for name in ("move", "capture")}
            # the median of REPLAYS runs (each in a fresh graph): one run is at the mercy of the host's noise
            replays = sorted((replay(Path(recording["result"].output_dir) / "bag") for _ in range(REPLAYS)),
                             key=lambda r: r["snaps"] / r["seconds"])
            rep = replays[len(replays) // 2]
    finally:
        claim.release()
    write_result(
        "scan",
        {"scan_wall_over_mechanical": ratio(default), "scan_wall_s": result.seconds,
         "scan_mechanical_bound_s": bound, "scan_snaps": result.snaps, "scan_points": result.points,
         "scan_wall_over_mechanical_recording": ratio(recording), "scan_wall_s_recording": recording["result"].seconds,
         "ack_ms_median": 1000 * acks[len(acks) // 2], "ack_ms_max": 1000 * acks[-1],
         "move_ms_median": 1000 * phases["move"][len(phases["move"]) // 2],
         "capture_ms_median": 1000 * phases["capture"][len(phases["capture"]) // 2],
         "replay_snaps_per_s": rep["snaps"] / rep["seconds"],
         "replay_snaps_per_s_min": replays[0]["snaps"] / replays[0]["seconds"],
         "replay_snaps_per_s_max": replays[-1]["snaps"] / replays[-1]["seconds"],
         "replay_cpu_ms_per_snap": 1000 * rep["cpu_s"] / max(1, rep["snaps"]),
         "replay_snaps": rep["snaps"], "bag_snaps_missing_images": rep["missing_in_bag"]},
        {"scan_wall_over_mechanical": "x", "scan_wall_s": "s", "scan_mechanical_bound_s": "s", "scan_snaps": "snaps",
         "scan_wall_over_mechanical_recording": "x", "scan_wall_s_recording": "s",
         "scan_points": "points", "ack_ms_median": "ms", "ack_ms_max": "ms", "move_ms_median": "ms",
         "capture_ms_median": "ms", "replay_snaps_per_s": "snaps/s", "replay_cpu_ms_per_snap": "ms",
         "replay_snaps_per_s_min": "snaps/s", "replay_snaps_per_s_max": "snaps/s",
         "replay_snaps": "snaps", "bag_snaps_missing_images": "snaps"},
        notes="live: lsu launch sim (6 processes, synthetic head 7), after a 3-snap warm-up scan two scans 0..470 step 2, "
              "settle 0.1 s, texture on: the default one (no bag, like `lsu scan`) gives scan_wall_over_mechanical and "
              "the per-snap figures, one recording its bag in the coordinator (`lsu scan --record`) gives "
              "scan_wall_over_mechanical_recording; bound = moves at the emulator's 200 steps/s + (settle + 33 ms "
              "exposure) per snap + the texture exposure; move/capture: per-snap medians of the move_to and stereo/capture round trips (the sim's render stands in for the exposure). replay: the recording scan's bag, its scan events and image pairs, the laser-off texture pair included (raw CDR "
              "from the bag) published into lsu run replay (extractor + matcher in one process) with at most 4 snaps "
              "awaiting their /lsu/points acknowledgement (below the image queue depth 5): no snap is dropped and "
              "snaps/s is the graph's sustained processing rate (median of 3 replays, each in a fresh graph; min and max "
              "beside it); replay_cpu_ms_per_snap: CPU time (all threads) of the "
              "replay process over the same window per snap (on a shared host it varies too: the same work took 10-20 ms).")
    return 0


if __name__ == "__main__":
    sys.exit(main())

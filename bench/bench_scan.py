"""Scan benchmark: live sim scan wall time against the mechanical lower bound, and bag replay speed.

    make bench-scan   ->  bench/results/scan.json
    .venv/bin/python bench/bench_scan.py --only view,two_host   (only parts 3 and 4, merged into scan.json)

1. `lsu launch sim` (separate processes, synthetic head), two full scans 0..470 step 2, settle 0.1 s:
   a default one (what `lsu scan` does: no bag) and one recording its bag (`lsu scan --record`).
   scan_wall_over_mechanical = the default scan's action wall time / (moves at the emulator's rate +
   settle + exposure for every snap), the bound the coordinator computes from the parameters;
   scan_wall_over_mechanical_recording: the same for the recording scan.
2. The recorded bag's snaps replayed closed-loop (images + events as raw CDR, each snap waiting for
   its /lsu/points) into `lsu run replay` (extractor + matcher in one process), three times, each in a
   fresh graph: replay_snaps_per_s is the median run, replay_cpu_ms_per_snap that run's CPU per snap.
3. Live view: a default scan with `lsu view` running and a Foxglove client (lsu_view.wsclient) subscribed
   to every channel, images included, then one more default scan without them:
   bridge_overhead_pct = that scan's wall time over the mean of the two default scans without, minus 1.
4. Two hosts (where network namespaces can be made: root): the sim graph split into `--group rig` and
   `--group processing`, a default scan 0..470 step 2, once with both groups here (localhost settings)
   and once with each group in its own network namespace joined by a veth pair (UDP only):
   two_host_scan_wall_over_one_host; two_host_lines_scan_wall_over_one_host the same with the
   extractor on the rig host (groups rig_extract / processing_lines: only laser lines cross).
"""

from __future__ import annotations

import contextlib
import json
import os
import struct
import sys
import tempfile
import time
from pathlib import Path

from common import write_result

from lsu_bringup import rosenv
from lsu_bringup.twohosts import TwoHosts, split_scan, why_unavailable


def live_scan(tmp: Path, baseline: bool = True, view: bool = True) -> dict:
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
        graph.interrupt(timeout_s=30)
        graph.kill()
    return runs


@contextlib.contextmanager
def watching_client():
    """`lsu view` on a free port and a Foxglove client subscribed to every topic the graph has."""
    from lsu_bringup.testing import LaunchedProcess
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
        view.interrupt(timeout_s=20)
        view.kill()


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


def two_host_figures(walls: dict) -> dict:
    if not walls:
        return {}
    return {"two_host_scan_wall_over_one_host": walls["two_host"] / walls["one_host"],
            "two_host_lines_scan_wall_over_one_host": walls["two_host_lines"] / walls["one_host"],
            "one_host_split_scan_wall_s": walls["one_host"], "two_host_scan_wall_s": walls["two_host"],
            "two_host_lines_scan_wall_s": walls["two_host_lines"]}


def only(parts: set) -> int:
    """Measure only the live-view and/or two-host figures and merge them into the existing scan.json."""
    claim = rosenv.isolate()
    figures: dict = {}
    failure = None
    try:
        with tempfile.TemporaryDirectory(prefix="lsu-bench-scan-") as tmp_name:
            tmp = Path(tmp_name)
            if "view" in parts:
                figures.update(view_figures(live_scan(tmp, baseline=False, view=True)))
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
    note = (f" {VIEW_NOTES} [{', '.join(sorted(parts))} figures measured {time.strftime('%Y-%m-%d %H:%M', time.gmtime())} UTC by "
            f"`bench_scan.py --only {','.join(sorted(parts))}`, load average {os.getloadavg()[0]:.1f} on "
            f"{os.cpu_count()} cores at the end; the others on {old.get('when', '?')}]")
    if parts:
        write_result("scan", merged, {**old["units"], **UNITS},
                     notes=old.get("notes", "").split(" bridge: a default")[0] + note)
    if failure is not None:
        print(f"two_host figures not measured: {str(failure)[:2000]}", file=sys.stderr)
        return 1
    return 0


def main() -> int:
    if len(sys.argv) > 2 and sys.argv[1] == "--only":
        return only(set(sys.argv[2].split(",")))
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
            unavailable = why_unavailable()
            walls = two_host_runs(tmp) if unavailable is None else {}
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
         "replay_snaps": rep["snaps"], "bag_snaps_missing_images": rep["missing_in_bag"],
         **view_figures(runs), **two_host_figures(walls)},
        {"scan_wall_over_mechanical": "x", "scan_wall_s": "s", "scan_mechanical_bound_s": "s", "scan_snaps": "snaps",
         "scan_wall_over_mechanical_recording": "x", "scan_wall_s_recording": "s",
         "scan_points": "points", "ack_ms_median": "ms", "ack_ms_max": "ms", "move_ms_median": "ms",
         "capture_ms_median": "ms", "replay_snaps_per_s": "snaps/s", "replay_cpu_ms_per_snap": "ms",
         "replay_snaps_per_s_min": "snaps/s", "replay_snaps_per_s_max": "snaps/s",
         "replay_snaps": "snaps", "bag_snaps_missing_images": "snaps",
         **UNITS},
        notes="live: lsu launch sim (6 processes, synthetic head 7), after a 3-snap warm-up scan two scans 0..470 step 2, "
              "settle 0.1 s, texture on: the default one (no bag, like `lsu scan`) gives scan_wall_over_mechanical and "
              "the per-snap figures, one recording its bag in the coordinator (`lsu scan --record`) gives "
              "scan_wall_over_mechanical_recording; bound = moves at the emulator's 200 steps/s + (settle + 33 ms "
              "exposure) per snap + the texture exposure; move/capture: per-snap medians of the move_to and stereo/capture round trips (the sim's render stands in for the exposure). replay: the recording scan's bag, its scan events and image pairs, the laser-off texture pair included (raw CDR "
              "from the bag) published into lsu run replay (extractor + matcher in one process) with at most 4 snaps "
              "awaiting their /lsu/points acknowledgement (below the image queue depth 5): no snap is dropped and "
              "snaps/s is the graph's sustained processing rate (median of 3 replays, each in a fresh graph; min and max "
              "beside it); replay_cpu_ms_per_snap: CPU time (all threads) of the "
              "replay process over the same window per snap (on a shared host it varies too: the same work took 10-20 ms). "
              + VIEW_NOTES)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The whole sim graph as separate processes: live scans through the action, and faults mid-scan.

Truth about the laser comes from the emulator's control socket (what the unit really does), never
from the driver's or the coordinator's word. How long the laser stayed on after a fault is measured
and reported (faults.json, goal 0.5 s), not asserted: a busy host may be late on any time limit. The
tests assert the cause instead: the laser guard's pause named the stalled part, no watchdog fired.
"""

import json
import os
import re
import signal
import struct
import time
from pathlib import Path

import pytest

from lsu_common.arrays import AnyArray
from lsu_driver.emulator import send_control
from lsu_scan.scanner import LsuScanner
from lsu_testing.plugin import LaunchedProcess

pytestmark = [pytest.mark.slow, pytest.mark.serial]  # timing-sensitive: alone, in the serial part


@pytest.fixture(scope="module")
def graph(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("scan_graph")
    port = str(tmp / "gp32")
    proc = LaunchedProcess(["launch", "sim", f"port:={port}", "scene:=plane", f"output_dir:={tmp / 'scans'}"])
    try:
        proc.wait_for_line(r"\[gp32_driver\].*homed: track 470", timeout_s=60)
        proc.wait_for_line(r"\[stereo_camera\].*source 'sim' open", timeout_s=60)
        scanner = LsuScanner(wait_s=30)
        yield {"proc": proc, "scanner": scanner, "control": port + ".ctl", "out": tmp / "scans"}
        scanner.close()
    finally:
        proc.stop(timeout_s=15)


def laser_on(g) -> bool:
    return bool(send_control(g["control"], {"get": "truth"})["truth"]["laser_on"])


def pid_of(g, node: str) -> int:
    return g["proc"].started_pids()[node]


def scan_json(result) -> dict:
    return json.loads((Path(result.output_dir) / "scan.json").read_text())


def wait_for_laser_on(g, timeout_s: float = 30.0) -> None:
    end = time.monotonic() + timeout_s
    while not laser_on(g):
        assert time.monotonic() < end and not g["scanner"].is_task_complete(), "the laser never came on again"
        time.sleep(0.005)


def wait_for_snap(g, index: int, timeout_s: float = 60.0) -> None:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        fb = g["scanner"].get_feedback()
        if fb is not None and fb.snap_index >= index:
            return
        assert not g["scanner"].is_task_complete(), "the scan ended early"
        time.sleep(0.01)
    pytest.fail(f"snap {index} not reached")


WATCHDOG_LINE = "laser watchdog switched the laser off"
LASER_GOAL_S = 0.5  # laser off within this of a fault the software handles (reported in faults.json)


def laser_off_after_fault(g) -> float:
    """Seconds from now until the emulator's laser is off; the LSU software, not the unit's watchdog, did it.

    Fails (with the graph's log) if the laser is still on 10 s later, far past every timeout.
    """
    t0, wall, seen = time.monotonic(), time.time(), len(g["proc"].output)
    while laser_on(g):
        if time.monotonic() - t0 >= 10.0:
            pytest.fail(f"laser still on 10 s after the fault (injected at {wall:.3f}, the log's clock)\n"
                        f"{g['proc'].output[-4000:]}")
        time.sleep(0.01)
    off = time.monotonic() - t0
    time.sleep(0.2)  # the driver logs a watchdog event it received just before the off was seen
    assert WATCHDOG_LINE not in g["proc"].output[seen:], f"the unit's watchdog had to do it\n{g['proc'].output[-3000:]}"
    return off


def guard_paused_after(result, injected_wall: float) -> None:
    """The laser guard switched the laser off after the fault was injected, before the scan ended.

    Which late answer it names depends on the host's load (a capture due before the missing points,
    or the points), so the reason is not checked, only that the guard, not the abort, acted first.
    """
    pauses = scan_json(result).get("laser_pauses", [])
    assert any(p["at"] >= injected_wall - 0.05 for p in pauses), f"no laser pause after the fault: {pauses}"


def start(g, **goal):
    scanner = g["scanner"]
    if not scanner.is_task_complete():  # an earlier test failed mid-scan: do not cascade
        scanner.cancel_task()
        scanner.get_result(timeout_s=60)
    # with a bag: the captured images are the data a fault must not lose
    scanner.start_scan(settle_s=0.05, output_dir=str(g["out"]), record_bag=True, **goal)


def snaps_lost(result) -> list:
    """Captured snaps (scan.json) whose image pair is not in the scan's bag: data a fault destroyed."""
    from lsu_bags.bags import read_messages

    record = scan_json(result)
    stamps = {}
    for m in read_messages(Path(result.output_dir) / "bag", ["/lsu/stereo/left/image_raw",
                                                            "/lsu/stereo/right/image_raw"]):
        sec, nanosec = struct.unpack_from("<iI", m.data, 4)  # CDR: encapsulation, then header.stamp
        stamps.setdefault(f"{sec}.{nanosec:09d}", set()).add(m.topic)
    return [s for s in record["snaps"] if len(stamps.get(s["stamp"], ())) < 2]


def note_fault(g, report, result, laser_s: float) -> None:
    lost = snaps_lost(result)
    report.note(error_shown=result.status, laser_on_after_s=laser_s, laser_goal_s=LASER_GOAL_S,
                snaps_captured=result.snaps,
                snaps_lost=len(lost),
                data_kept=f"scan.json, bag with {result.snaps - len(lost)} image pairs, cloud of the acknowledged snaps")
    assert not lost, (f"snaps without their image pair in the bag: {lost}\nlaser pauses: "
                      f"{scan_json(result).get('laser_pauses')}\n{g['proc'].output[-4000:]}")


def test_live_scan_of_60_snaps(graph):
    result = graph["scanner"].scan(start=120, end=238, step=2, settle_s=0.05, output_dir=str(graph["out"]))
    assert result.success and not result.partial, result.status
    assert result.snaps == 60
    record = scan_json(result)
    assert record["snaps_captured"] == 60 and record["snaps_acknowledged"] == 60
    assert [s["position_steps"] for s in record["snaps"]] == list(range(120, 239, 2))
    assert result.points == record["points"] and result.points > 60 * 300  # a plane fills most rows
    assert (Path(result.output_dir) / "cloud.ply").stat().st_size > result.points * 12
    assert not laser_on(graph)  # the unit's truth, not the driver's word


def test_a_scan_of_100_snaps_on_a_loaded_host_has_no_empty_snap(graph, ros_node):
    """Every snap sees the laser line: the camera renders a capture with the laser-on that preceded it, even
    when the host is too busy for the emulator to tell the change at once (one snap in eleven came out empty).

    The laser goes on before a capture after each pause of the laser guard: a short ``laser_pause_s`` and two
    busy loops beside the graph make pauses (and so laser-ons right before captures) frequent."""
    import subprocess
    import sys

    coordinator = "/lsu/scan_coordinator"
    assert ros_node.set_parameter(coordinator, "laser_pause_s", 0.03).successful
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]  # ended by pid
    try:
        result = graph["scanner"].scan(start=120, end=219, step=1, settle_s=0.05, output_dir=str(graph["out"]))
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()
        assert ros_node.set_parameter(coordinator, "laser_pause_s", 0.2).successful
    assert result.success and not result.partial, result.status
    record = scan_json(result)
    assert len(record["snaps"]) == 100
    assert [s["index"] for s in record["snaps"] if not s["points"]] == [], \
        f"{len(record['laser_pauses'])} laser pauses"


@pytest.mark.fault("scan: canceled mid-scan")
def test_cancel_mid_scan_turns_the_laser_off_and_keeps_the_data(graph, fault_report):
    start(graph, start=100, end=300, step=2)
    wait_for_snap(graph, 5)
    wait_for_laser_on(graph)  # the fault hits a lit scan (the guard may have paused it on a busy host)
    graph["scanner"].cancel_task()
    off = laser_off_after_fault(graph)
    result = graph["scanner"].get_result()
    assert result.partial and not result.success and "canceled" in result.status, graph["proc"].output[-3000:]
    record = scan_json(result)
    assert record["partial"] and record["snaps_captured"] >= 5
    note_fault(graph, fault_report, result, off)


@pytest.mark.fault("scan: unit reset mid-scan")
def test_emulator_reset_mid_scan(graph, fault_report):
    start(graph, start=100, end=300, step=2)
    wait_for_snap(graph, 5)
    wait_for_laser_on(graph)  # the fault hits a lit scan (the guard may have paused it on a busy host)
    send_control(graph["control"], {"fault": "reset"})
    off = laser_off_after_fault(graph)
    result = graph["scanner"].get_result()
    assert result.partial and "reset" in result.status, result.status
    assert scan_json(result)["snaps_captured"] >= 5
    note_fault(graph, fault_report, result, off)
    assert "homed" in graph["scanner"].home()  # the next scans need a homed carriage again


@pytest.mark.fault("scan: camera hangs (capture timeout)")
def test_camera_capture_timeout(graph, fault_report):
    start(graph, start=100, end=300, step=2)
    wait_for_snap(graph, 5)
    wait_for_laser_on(graph)  # the fault hits a lit scan (the guard may have paused it on a busy host)
    camera = pid_of(graph, "stereo_camera")
    os.kill(camera, signal.SIGSTOP)  # the camera hangs: captures get no answer
    hung_at = time.time()
    try:
        # the laser guard switches the laser off laser_pause_s (0.2 s) after the capture was due, without waiting
        off = laser_off_after_fault(graph)
        result = graph["scanner"].get_result(timeout_s=30)
        hung_capture = "capture" in result.status and "no answer" in result.status
        images_never_came = "not acknowledged" in result.status
        assert result.partial and (hung_capture or images_never_came), \
            f"{result.status}\n{graph['proc'].output[-4000:]}"  # the graph's log says what stalled
        guard_paused_after(result, hung_at)  # before the capture timeout's abort
        assert scan_json(result)["snaps_captured"] >= 5
        note_fault(graph, fault_report, result, off)
    finally:
        os.kill(camera, signal.SIGCONT)


@pytest.mark.fault("scan: matcher SIGKILLed (respawned)")
def test_matcher_killed_mid_scan(graph, fault_report):
    start(graph, start=100, end=300, step=2)
    wait_for_snap(graph, 5)
    wait_for_laser_on(graph)  # the fault hits a lit scan (the guard may have paused it on a busy host)
    os.kill(pid_of(graph, "stereo_matcher"), signal.SIGKILL)
    killed_at = time.time()
    # no acknowledgement laser_pause_s (0.2 s) after the last capture: the laser guard switches it off
    off = laser_off_after_fault(graph)
    result = graph["scanner"].get_result(timeout_s=30)
    assert result.partial and "not acknowledged by stereo_matcher" in result.status, result.status
    guard_paused_after(result, killed_at)  # before ack_timeout_s aborted the scan
    assert not laser_on(graph)
    record = scan_json(result)
    assert record["snaps_captured"] >= 5 and record["partial"]
    note_fault(graph, fault_report, result, off)


@pytest.mark.fault("scan: camera SIGKILLed and respawned")
def test_camera_killed_and_respawned_mid_scan(graph, fault_report):
    start(graph, start=100, end=300, step=2)
    wait_for_snap(graph, 5)
    wait_for_laser_on(graph)  # the fault hits a lit scan (the guard may have paused it on a busy host)
    camera = pid_of(graph, "stereo_camera")
    opened = len(re.findall(r"\[stereo_camera\].*source 'sim' open", graph["proc"].output))
    os.kill(camera, signal.SIGKILL)
    off = laser_off_after_fault(graph)
    result = graph["scanner"].get_result(timeout_s=30)
    assert result.partial and not result.success, result.status
    assert not laser_on(graph)
    note_fault(graph, fault_report, result, off)
    # the launcher respawns the camera: the next scan works
    end = time.monotonic() + 90
    while len(re.findall(r"\[stereo_camera\].*source 'sim' open", graph["proc"].output)) <= opened:
        assert time.monotonic() < end, graph["proc"].output[-3000:]
        time.sleep(0.2)
    assert pid_of(graph, "stereo_camera") != camera
    again = graph["scanner"].scan(start=120, end=130, step=2, settle_s=0.05, output_dir=str(graph["out"]))
    assert again.success and again.snaps == 6, again.status


def test_the_bag_places_the_laser_at_every_snap_for_a_plain_rosbags_reader(graph):
    """Another program, with rosbags alone (no LSU code), finds the laser's pose in the rig's frame at every
    snap from the bag's /tf_static (rig -> laser origin) and /tf (laser origin -> laser, per driver state).

    Ground truth: the positions the scan commanded and the configured track (1/60 inch per step, step 235
    in line with the rig centre, laser on the baseline: config/params/stereo_camera.yaml)."""
    import bisect

    import numpy as np
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore
    from scipy.spatial.transform import Rotation

    result = graph["scanner"].scan(start=150, end=240, step=10, settle_s=0.05, output_dir=str(graph["out"]),
                                   record_bag=True)
    assert result.success, result.status
    snaps = scan_json(result)["snaps"]
    assert [s["position_steps"] for s in snaps] == list(range(150, 241, 10))

    typestore = get_typestore(Stores.ROS2_JAZZY)
    static: dict[str, tuple[str, AnyArray, Rotation]] = {}  # child -> (parent, translation, rotation)
    moving: list[tuple[int, str, str, AnyArray, Rotation]] = []  # (stamp ns, parent, child, t, r)
    with Reader(Path(result.output_dir) / "bag") as reader:
        connections = [c for c in reader.connections if c.topic in ("/tf", "/tf_static")]
        assert {c.topic for c in connections} == {"/tf", "/tf_static"}
        for connection, _, raw in reader.messages(connections=connections):
            for t in typestore.deserialize_cdr(raw, connection.msgtype).transforms:
                tr = t.transform
                pose = (np.array([tr.translation.x, tr.translation.y, tr.translation.z]),
                        Rotation.from_quat([tr.rotation.x, tr.rotation.y, tr.rotation.z, tr.rotation.w]))
                if connection.topic == "/tf_static":
                    static[t.child_frame_id] = (t.header.frame_id, *pose)
                else:
                    stamp = t.header.stamp.sec * 1_000_000_000 + t.header.stamp.nanosec
                    moving.append((stamp, t.header.frame_id, t.child_frame_id, *pose))
    moving.sort(key=lambda m: m[0])
    stamps_ns = [m[0] for m in moving]

    def in_base(child: str, translation: AnyArray, rotation: Rotation) -> AnyArray:
        """``translation`` given in ``child`` expressed in the root of the static tree (rig base)."""
        point = translation
        while child in static:
            parent, t, r = static[child]
            point, child = t + r.apply(point), parent
        assert child == "lsu_base", child
        return point

    for snap in snaps:
        sec, nanosec = (int(x) for x in snap["stamp"].split("."))
        i = bisect.bisect_right(stamps_ns, sec * 1_000_000_000 + nanosec) - 1  # the transform holding then
        assert i >= 0, f"no /tf before snap {snap['index']}"
        _, parent, child, t, r = moving[i]
        assert child == "lsu_laser"
        laser = in_base(parent, t, r)  # the laser frame's origin in the rig's base frame
        expected = np.array([0.0, (235.0 - snap["position_steps"]) * 0.00042333, 0.0])
        assert np.allclose(laser, expected, atol=1e-6), (snap["index"], laser, expected)


@pytest.mark.fault("scan: disk full while recording")
def test_a_full_disk_stops_the_scan_with_every_captured_pair_in_its_bag(graph, fault_report, tmp_path):
    import subprocess

    disk = tmp_path / "disk"
    disk.mkdir()
    if os.geteuid() != 0:
        pytest.skip("a full disk needs a small tmpfs, and mounting one needs root")
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=48m", "tmpfs", str(disk)], capture_output=True,
                             text=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here: {mounted.stderr.strip()}")
    try:
        scanner = graph["scanner"]
        if not scanner.is_task_complete():
            scanner.cancel_task()
            scanner.get_result(timeout_s=60)
        # 101 snaps of two ~0.9 MB images do not fit on 48 MiB
        scanner.start_scan(start=100, end=300, step=2, settle_s=0.05, output_dir=str(disk), record_bag=True)
        result = scanner.get_result(timeout_s=180)
        assert result.partial and "nearly full" in result.status, result.status
        assert not laser_on(graph)
        record = scan_json(result)  # the record fits in the space kept
        assert record["partial"] and 3 <= record["snaps_captured"] < 101, record["status"]
        lost = snaps_lost(result)  # the bag opens, with both images of every captured snap
        assert not lost, lost
        assert not [p for p in Path(result.output_dir).rglob("*") if p.name.endswith(".tmp")]
        fault_report.note(error_shown=result.status, snaps_captured=result.snaps, snaps_lost=len(lost),
                          laser_on_after_s=0.0,
                          data_kept=f"scan.json, a closed bag with the {result.snaps} captured image pairs")
    finally:
        subprocess.run(["umount", "-l", str(disk)], check=False)

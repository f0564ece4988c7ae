"""`lsu batch` on a private local Ray (one per module, shared by its tests): the recorded scan gives the cloud the
live graph recorded and the one `lsu run replay` makes; reruns skip; a killed driver's run resumes; bad bags are
reported with their reason and the others finish."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from lsu_bags.bags import BagWriter, bag_topics, deserialize_ros, read_messages
from lsu_bags.ply import read_ply
from lsu_bags.pointcloud2 import decode, from_msg
from lsu_batch.batch import local_ray, run_batch
from lsu_batch.task import PARTIAL_DIR, done_steps
from lsu_common.arrays import AnyArray

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[3]
RECORDED = ROOT / "test" / "data" / "bags" / "scan_head"  # a scan recorded by the live sim graph (tools/make_test_bags.py)
LSU = str(Path(os.environ.get("VIRTUAL_ENV", ROOT / ".venv")) / "bin" / "lsu")
STEPS = ("extract", "match")


def _sim_scene():
    from lsu_sim import build_scene, load_rig
    geometry = load_rig()
    return geometry, build_scene("head:7", geometry)


@pytest.fixture(scope="module")
def ray_here():
    with local_ray(2) as address:
        yield address


@pytest.fixture(scope="module")
def archive(tmp_path_factory):
    """Scan bags as `lsu scan --record` lays them out (scans/<id>/bag): the recorded one, three short simulated
    ones (lsu_testing.simbags), a corrupt one and one without scan events (the recorded bag's other topics)."""
    from lsu_testing.simbags import write_sim_scan_bag

    root = tmp_path_factory.mktemp("archive")
    shutil.copytree(RECORDED, root / "recorded" / "bag")
    geometry, scene = _sim_scene()
    for i in range(3):
        write_sim_scan_bag(root / f"sim{i}" / "bag", scene, [215 + 5 * i, 235 + 5 * i], seed=11 + i,
                           scan_id=f"sim{i}", geometry=geometry)
    corrupt = root / "corrupt" / "bag"
    shutil.copytree(RECORDED, corrupt)
    data = (corrupt / "bag.mcap").read_bytes()
    (corrupt / "bag.mcap").write_bytes(data[:64] + bytes(len(data) // 3))  # header kept, the rest zeros
    topics = bag_topics(RECORDED)
    keep = ["/lsu/stereo/left/image_raw", "/lsu/stereo/right/image_raw"]
    with BagWriter(root / "noevents" / "bag", "mcap") as bag:
        for topic in keep:
            bag.add_topic(topic, topics[topic][0])
        for m in read_messages(RECORDED, keep):
            bag.write(m.topic, m.timestamp_ns, bytes(m.data))
    return root


def xyz_of_ply(path: Path) -> AnyArray:
    vertices, _ = read_ply(path)
    return np.stack([vertices["x"], vertices["y"], vertices["z"]], axis=1)


def test_batch_gives_the_recorded_cloud_and_the_replays(ray_here, archive, tmp_path, ros_context):
    """The batch's cloud.ply of the recorded bag equals the cloud the live graph published (recorded in the bag)
    within float rounding, and the one `lsu run replay`'s code path makes in this process bit for bit."""
    from lsu_tools.cli import resolve_launch_file
    from lsu_tools.direct_replay import DirectReplay, default_workers
    from lsu_tools.launch_file import load_launch, select_nodes
    from lsu_tools.nodes_index import resolve_executable
    from lsu_tools.runner import build_nodes

    summary = run_batch([archive / "recorded"], tmp_path / "out", STEPS, progress=False)
    assert [r["name"] for r in summary.done] == ["recorded"] and not summary.failed
    batch = xyz_of_ply(tmp_path / "out" / "recorded" / "cloud.ply")

    recorded = [deserialize_ros(m) for m in read_messages(RECORDED, ["/lsu/scan/cloud"])]
    live = decode(from_msg(recorded[0]))
    live_xyz = np.stack([live["x"], live["y"], live["z"]], axis=1)
    assert batch.shape == live_xyz.shape and len(batch) > 1000
    assert np.max(np.abs(batch - live_xyz)) <= 1e-6

    description = select_nodes(load_launch(resolve_launch_file("replay"), {}, resolve_executable),
                               ["laser_extractor", "stereo_matcher"], [], {})
    nodes = build_nodes(description, tmp_path, context=ros_context)
    try:
        replay = DirectReplay(nodes)
        clouds: list = []
        replay.matcher.cloud_pub.publish = clouds.append
        replay.run(RECORDED, workers=default_workers())  # as `lsu run replay BAG` runs by default
    finally:
        for node in nodes:
            node.destroy_node()
    columns = decode(from_msg(clouds[-1]))
    np.testing.assert_array_equal(batch, np.stack([columns["x"], columns["y"], columns["z"]], axis=1))


def test_bad_bags_are_reported_the_others_finish_and_a_rerun_skips(ray_here, archive, tmp_path):
    out = tmp_path / "out"
    first = run_batch([archive], out, STEPS, progress=False)
    done = sorted(r["name"] for r in first.done)
    assert done == ["recorded", "sim0", "sim1", "sim2"]
    reasons = {r["name"]: r["reason"] for r in first.failed}
    assert set(reasons) == {"corrupt", "noevents"}
    assert "corrupt" in reasons["corrupt"].lower() or "read" in reasons["corrupt"].lower(), reasons["corrupt"]
    assert "not a recorded scan" in reasons["noevents"] and "scan/events" in reasons["noevents"]
    assert not (out / "corrupt").exists() and not (out / PARTIAL_DIR).exists()
    for name in done:
        assert done_steps(out / name) == STEPS
        assert len(xyz_of_ply(out / name / "cloud.ply")) > 0
    written = json.loads((out / "summary.json").read_text())
    assert {r["name"] for r in written["failed"]} == {"corrupt", "noevents"} and written["ok"] is False

    inode = (out / "sim1" / "cloud.ply").stat().st_ino
    second = run_batch([archive], out, STEPS, progress=False)
    assert sorted(second.skipped) == done and not second.done
    assert {r["name"] for r in second.failed} == {"corrupt", "noevents"}  # still reported, tried again
    assert (out / "sim1" / "cloud.ply").stat().st_ino == inode  # not rewritten

    more = run_batch([archive / "sim1"], out, ("extract", "match", "mesh"), progress=False)  # a step added: redone
    assert [r["name"] for r in more.done] == ["sim1"] and done_steps(out / "sim1") == ("extract", "match", "mesh")


def test_extract_alone_writes_the_lines_of_every_snap(ray_here, archive, tmp_path):
    summary = run_batch([archive / "sim0"], tmp_path / "out", ("extract",), progress=False)
    assert [r["name"] for r in summary.done] == ["sim0"]
    lines = np.load(tmp_path / "out" / "sim0" / "lines.npz")
    events = [deserialize_ros(m) for m in read_messages(archive / "sim0" / "bag", ["/lsu/scan/events"])]
    snaps = {e.image_stamp.sec * 10**9 + e.image_stamp.nanosec for e in events if e.type == 2}  # SNAP
    assert len(snaps) == 2 and set(np.unique(lines["stamp_ns"]).tolist()) == snaps  # the laser-off pair has no line
    for stamp in snaps:  # both cameras saw the line in each snap
        assert set(lines["side"][lines["stamp_ns"] == stamp].tolist()) == {0, 1}
    assert np.all(np.isfinite(lines["u"])) and len(lines["u"]) > 100


def _session_members(sid: int) -> list[int]:
    members = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            fields = stat[stat.rindex(")") + 2:].split()  # after "pid (comm) ": state, ppid, pgrp, session
            if int(fields[3]) == sid and fields[0] != "Z":
                members.append(int(entry.name))
    return members


def _wait_session_gone(sid: int, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while (left := _session_members(sid)) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not left, f"processes of the killed batch still run after {timeout_s} s: {left}"


def test_a_killed_batch_resumes_where_it_stopped(ray_here, archive, tmp_path):
    """The driver (and its Ray) killed after its first finished bag; the next run skips what was finished, removes
    the half-written folders and does the rest."""
    sims = tmp_path / "sims"
    for name in ("sim0", "sim1", "sim2", "recorded"):
        shutil.copytree(archive / name, sims / name)
    out = tmp_path / "out"
    driver = subprocess.Popen([LSU, "batch", str(sims), "--out", str(out), "--steps", "extract,match", "--workers",
                               "1", "--no-progress"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                              start_new_session=True)  # with its Ray in its process group
    try:
        deadline = time.monotonic() + 240
        while not list(out.glob("*/done.json")) and driver.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        assert driver.poll() is None, f"the batch ended before it was killed:\n{driver.communicate()[0]}"
        finished_before = {p.parent.name for p in out.glob("*/done.json")}
        assert finished_before
    finally:
        os.killpg(driver.pid, signal.SIGKILL)
        driver.communicate()
    _wait_session_gone(driver.pid)  # Ray workers have process groups of their own, in the driver's session
    finished_at_kill = {p.parent.name for p in out.glob("*/done.json")}
    assert len(finished_at_kill) < 4, "the batch finished everything before it was killed: nothing to resume"

    resumed = run_batch([sims], out, STEPS, progress=False)
    assert set(resumed.skipped) == finished_at_kill
    assert {r["name"] for r in resumed.done} == {"sim0", "sim1", "sim2", "recorded"} - finished_at_kill
    assert not resumed.failed and not (out / PARTIAL_DIR).exists()
    assert all(done_steps(out / n) == STEPS for n in ("sim0", "sim1", "sim2", "recorded"))

"""The graph on two machines: the rig's nodes (emulator, driver, cameras) on one host, the processing
nodes (extractor, matcher, faces, coordinator) on another, in two network namespaces this test makes
and joins with a veth pair (10.231.0.1/30 - 10.231.0.2/30, nothing else). Discovery SUBNET plus the
other end as static peer, UDP only. A short scan completes and gives the cloud and bag of one host."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest

from lsu_bags.bags import BagTypes, bag_info, deserialize, read_messages
from lsu_tools.demo import accuracy_against_scene
from lsu_tools.processes import LSU
from lsu_tools.twohosts import TwoHosts, split_scan, why_unavailable

pytestmark = [pytest.mark.slow, pytest.mark.serial]  # timing-sensitive: alone, in the serial part
UNAVAILABLE = why_unavailable()
needs_namespaces = pytest.mark.skipif(UNAVAILABLE is not None,
                                      reason=f"two hosts need network namespaces here: {UNAVAILABLE}")
# the middle of the track, where the laser crosses the synthetic head; 11 snaps
SCAN = ["--start", "200", "--end", "240", "--step", "4"]
# a capture crossing the link on a loaded host can take longer than the default 1 s abort limit
LAUNCH = ["capture_timeout_s:=5.0"]


def cloud_by_pixel(folder: Path) -> dict:
    """(snap, left pixel row) -> x y z [m] of a scan's cloud.ply."""
    from lsu_bags.ply import read_ply

    cols, _ = read_ply(folder / "cloud.ply")
    keys = zip(cols["snap"].astype(int).tolist(), np.round(cols["v"] * 8).astype(int).tolist())
    xyz = np.stack([cols["x"], cols["y"], cols["z"]], axis=1)
    return dict(zip(keys, xyz))


def stops(bag: Path) -> list[float]:
    """Positions of the carriage's final reports of its moves (!DONE) in a scan's bag, in order."""
    types = BagTypes()
    return [msg.position_steps for msg in (deserialize(m, types) for m in read_messages(bag, ["/lsu/driver/carriage"]))
            if msg.source == "done"]


@needs_namespaces
def test_scan_across_two_hosts_gives_the_cloud_and_bag_of_one_host(tmp_path):
    one = split_scan(tmp_path / "one", None, scan_args=SCAN, launch_args=LAUNCH)
    with TwoHosts() as hosts:
        two = split_scan(tmp_path / "two", hosts, scan_args=SCAN, launch_args=LAUNCH)
    assert not any(hosts.namespaces[h] in subprocess.run(["ip", "netns", "list"], capture_output=True,
                                                          text=True).stdout for h in hosts.namespaces)
    a, b = cloud_by_pixel(one), cloud_by_pixel(two)
    assert len(a) > 1000, f"the one-host scan saw too little of the head ({len(a)} points)"
    # a snap captured while the coordinator's laser guard held the laser off (a capture answered later
    # than laser_pause_s on a loaded host) has no points, on one host as on two: compare the snaps
    # that have points in both scans, and require most of them
    snaps_a, snaps_b = {k[0] for k in a}, {k[0] for k in b}
    both = snaps_a & snaps_b
    assert len(both) >= 8, f"snaps with points: one host {sorted(snaps_a)}, two hosts {sorted(snaps_b)}"
    a = {k: v for k, v in a.items() if k[0] in both}
    b = {k: v for k, v in b.items() if k[0] in both}
    common = set(a) & set(b)
    # the same rows of the same snaps were seen (a row at the edge of detection may come and go with the noise)
    assert len(common) >= 0.97 * max(len(a), len(b)), (len(a), len(b), len(common))
    keys = sorted(common)
    diff_mm = 1000 * np.linalg.norm(np.array([a[k] for k in keys]) - np.array([b[k] for k in keys]), axis=1)
    assert np.median(diff_mm) < 0.1, f"two-host points differ from one-host ones: median {np.median(diff_mm):.3f} mm"
    # both against the renderer's true surface
    for folder in (one, two):
        acc = accuracy_against_scene(folder / "cloud.ply", "head:7")
        # the extractor subtracts the scan's laser-off frame by default, whose noise adds to each centre
        assert acc["median_mm"] < 0.12, (folder, acc)
    # the bags hold the same topics and types, and the same message counts (every image pair crossed the
    # link) except for those the driver publishes at a rate, so with the scan's and the moves' durations: the
    # scanner state, and the carriage positions (a !POS every 1/R s while moving, besides one !DONE per move)
    info_a, info_b = bag_info(one / "bag"), bag_info(two / "bag")
    rated = {"/lsu/driver/state", "/lsu/driver/carriage", "/tf"}  # /tf: one laser transform per state
    counts_a = {t.name: (t.msgtype, t.count) for t in info_a.topics if t.name not in rated}
    counts_b = {t.name: (t.msgtype, t.count) for t in info_b.topics if t.name not in rated}
    assert {t.name for t in info_a.topics} == {t.name for t in info_b.topics}
    assert counts_a == counts_b
    carriage_a, carriage_b = ({t.name: t.count for t in info.topics}["/lsu/driver/carriage"] for info in (info_a, info_b))
    assert carriage_a >= 10 and carriage_b >= 10  # at least one !DONE per move between the 11 snaps
    # how many !POS reports a move gives depends on how long the host took (load), where the carriage stopped
    # does not: the same stops, in the same order, crossed the link
    stops_a, stops_b = stops(one / "bag"), stops(two / "bag")
    assert {200.0, 220.0, 240.0} <= set(stops_a) and stops_a == stops_b, (stops_a, stops_b)
    assert counts_b["/lsu/stereo/left/image_raw"][1] >= 12  # 11 snaps + the laser-off texture pair


@needs_namespaces
def test_doctor_on_the_rig_host_names_the_peer_route_and_interface():
    with TwoHosts() as hosts:
        done = subprocess.run([*hosts.prefix("rig"), LSU, "doctor"], env=hosts.env("rig"), capture_output=True,
                              text=True, timeout=120)
    out = done.stdout
    assert done.returncode == 0, out + done.stderr
    assert "OK    multi-host discovery" in out and "SUBNET" in out, out
    peer = hosts.addresses["processing"]
    assert "OK    multi-host peer" in out and f"{peer} ({peer}) via {hosts.interfaces['rig']} " \
        f"{hosts.addresses['rig']}" in out, out

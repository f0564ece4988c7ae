"""A living subject in the live graph: `lsu launch sim motion:=turn` turns the person's head during the first
sweep; stereo_matcher flags the sweep (scan/motion, into scan.json and the bag), `lsu scan` says "hold still,
scanning again" and the coordinator scans again within the same goal.

Truth: the simulator's motion (lsu_testing.motion: a 15 deg turn of the head that the sweep's frames after its
first 2 s see, the middle one not; the head stays turned for the second sweep) and the sweep's own frame times. A
still subject is left unchanged by the correction: test_motion_scan (the same `SweepMotion` the matcher runs, on
rendered sweeps), without a graph.
"""

from __future__ import annotations

import json
import subprocess

import pytest

from lsu_bags.bags import read_messages
from lsu_reconstruct.motion import HOLD_STILL
from lsu_testing.motion import SWEEP_END, SWEEP_RATE, SWEEP_START, launch_args
from lsu_testing.plugin import LSU

pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]


def test_a_sudden_turn_is_flagged_and_scanned_again(tmp_path, launch):
    scans = tmp_path / "scans"
    graph = launch("launch", "sim", f"port:={tmp_path / 'gp32'}", *launch_args(), f"output_dir:={scans}")
    graph.wait_for_line(r"\[gp32_driver\].*homed: track 470", timeout_s=60)
    graph.wait_for_line(r"\[stereo_camera\].*source 'sim' open", timeout_s=60)
    run = subprocess.run([LSU, "scan", "--mode", "sweep", "--start", str(SWEEP_START), "--end", str(SWEEP_END),
                          "--rate", str(SWEEP_RATE), "--record", "--no-texture", "--wait", "30"],
                         capture_output=True, text=True, timeout=240)
    said = run.stdout + run.stderr
    assert run.returncode == 0, said + graph.output[-3000:]
    assert f"\n{HOLD_STILL}\n" in run.stderr, said  # said while the goal runs, on its own line
    assert HOLD_STILL in run.stdout, said           # and in the result's status
    folders = sorted(p.parent for p in scans.glob("*/scan.json"))
    assert len(folders) == 2, (folders, said)
    records = {f: json.loads((f / "scan.json").read_text()) for f in folders}
    first_folder = next(f for f, r in records.items() if not r["rescan_of"])
    first, second = records[first_folder], next(r for r in records.values() if r["rescan_of"])
    # the first sweep: flagged, with the frames and carriage positions that are unreliable and why
    motion = first["motion"]
    assert motion["measured"] and motion["flagged"] and motion["message"] == HOLD_STILL, motion
    assert not motion["corrected"]  # a sheared scan is scanned again, not bent
    bad = motion["unreliable_frames"]
    assert bad and all(str(f) in motion["reasons"] and motion["reasons"][str(f)] for f in bad)
    # the frames turned from the reference are the ones after the pose changed, not the reference's neighbours
    turned = [int(f) for f, why in motion["reasons"].items() if "turned" in why]
    assert turned and min(turned) > motion["reference_frame"] + 1, motion
    lo, hi = motion["unreliable_positions_steps"]
    assert SWEEP_START <= lo <= hi <= SWEEP_END
    assert "moved beyond correction" in first["status"]
    # the bag holds the same record on its own topic (std_msgs/String, JSON: readable by plain rosbags)
    recorded = list(read_messages(first_folder / "bag", ["/lsu/scan/motion"]))
    assert len(recorded) == 1
    from rosbags.typesys import Stores, get_typestore

    text = get_typestore(Stores.ROS2_JAZZY).deserialize_cdr(bytes(recorded[0].data), "std_msgs/msg/String").data
    assert json.loads(text)["unreliable_frames"] == bad
    # the second: the same goal, the head held still in its new pose
    assert second["rescan_of"] == first["scan_id"]
    assert second["motion"]["measured"] and not second["motion"]["flagged"], json.dumps(second["motion"])
    assert not second["partial"] and second["points"] > 5000

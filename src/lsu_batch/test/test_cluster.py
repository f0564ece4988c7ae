"""`lsu batch --address` on a two-node Ray cluster made on this machine (a head and a worker node, one CPU each,
started with `ray start`): every bag is done, on both nodes, with the files a local batch writes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from lsu_batch.cluster import RayNodes
from lsu_batch.task import done_steps

pytestmark = pytest.mark.slow

LSU = str(Path(sys.executable).with_name("lsu"))


def test_two_node_cluster_does_every_bag_on_both_nodes(tmp_path):
    from lsu_sim import build_scene, load_rig
    from lsu_testing.simbags import write_sim_scan_bag
    geometry = load_rig()
    scene = build_scene("head:7", geometry)
    names = [f"scan{i}" for i in range(4)]
    for i, name in enumerate(names):
        write_sim_scan_bag(tmp_path / "scans" / name / "bag", scene, [220 + 4 * i, 240], seed=21 + i, scan_id=name,
                           geometry=geometry)
    out = tmp_path / "out"
    with RayNodes(nodes=2, cpus=1) as cluster:
        run = subprocess.run([LSU, "batch", str(tmp_path / "scans"), "--out", str(out), "--address", cluster.address,
                              "--steps", "extract,match", "--no-progress"], env=cluster.env, capture_output=True,
                             text=True, timeout=600)
    assert run.returncode == 0, run.stdout + run.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert sorted(r["name"] for r in summary["done"]) == names and not summary["failed"]
    assert summary["workers"] == 2  # the cluster's CPUs: one per node
    # four one-CPU tasks on two one-CPU nodes: the second node took some (the multi-node path ran)
    assert len({r["node_id"] for r in summary["done"]}) == 2, summary["done"]
    for name in names:
        assert done_steps(out / name) == ("extract", "match") and (out / name / "cloud.ply").stat().st_size > 0

"""A graph started and shut down 30 times: no node crashes on the way out, no process is left behind.

The replay graph (laser_extractor, stereo_matcher, face_processor: the node that ended in a segmentation
fault inside the middleware at shutdown) is launched with `lsu launch` and stopped with Ctrl-C (SIGINT)
at a different moment each time: while the nodes are still starting, and once each is on the graph.
A crash is read from the processes themselves: the launcher's report of how each node ended (a signal
it did not send), Python's fault handler (on in every node: a segmentation fault prints "Fatal Python
error"), and core files. Leftovers are looked for by the pid and the process group of every node the
launcher said it started.
"""

from __future__ import annotations

import os
import random
import re
import time
from pathlib import Path

import pytest

from lsu_tools.processes import LaunchedProcess, pid_alive

pytestmark = pytest.mark.slow

LAUNCHES = 30
NODES = ("laser_extractor", "stereo_matcher", "face_processor")
CRASH = re.compile(r"crashed while stopping|Fatal Python error|Segmentation fault|core dumped|signal SIG(SEGV|ABRT|BUS)")


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    # a group of zombies only waits to be reaped by the launcher, which has ended: count live members only
    return any(pid_alive(int(p.name)) for p in Path("/proc").iterdir() if p.name.isdigit() and _pgid(int(p.name)) == pgid)


def _pgid(pid: int) -> int | None:
    try:
        return os.getpgid(pid)
    except ProcessLookupError:
        return None


def _on_graph(node_names: set[str], timeout_s: float) -> bool:
    """Wait until every node of the replay graph is discovered."""
    from lsu_common.node import GraphClient

    client = GraphClient("restart_probe", namespace="/lsu_restart_probe")
    try:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if node_names <= set(client.node.get_node_names()):
                return True
            time.sleep(0.1)
        return False
    finally:
        client.close()


@pytest.mark.timeout(3600)  # 30 launches of three nodes: minutes on a busy host (no time is asserted)
def test_a_graph_started_and_stopped_30_times_never_crashes_and_leaves_nothing(tmp_path):
    rng = random.Random(33)
    env = {**os.environ, "PYTHONFAULTHANDLER": "1"}
    crashes: list[str] = []
    leftovers: list[str] = []
    for launch in range(LAUNCHES):
        cwd = tmp_path / f"launch{launch:02d}"  # a node's core file would land here
        cwd.mkdir()
        graph = LaunchedProcess(["launch", "replay"], cwd=str(cwd), env=env)
        try:
            # every third stop comes while the nodes are still starting, the others once all are on the graph
            graph.wait_for_line(r"started face_processor .* pid \d+", timeout_s=60)
            if launch % 3:
                assert _on_graph(set(NODES), 90), f"launch {launch}: nodes not on the graph\n{graph.output[-3000:]}"
            time.sleep(rng.uniform(0.0, 1.0))
            pids = graph.started_pids()
            assert set(NODES) <= set(pids), graph.output[-2000:]
            code = graph.stop(timeout_s=30)
        finally:
            graph.kill()
        text = graph.output
        if code != 0 or CRASH.search(text) or any(cwd.glob("core*")):
            crashes.append(f"launch {launch}: exit {code}\n" + "\n".join(
                line for line in text.splitlines() if CRASH.search(line) or "while stopping" in line)[-2000:])
        left = [f"{label} pid {pid}" for label, pid in pids.items() if pid_alive(pid) or _group_alive(pid)]
        if left:
            leftovers.append(f"launch {launch}: {', '.join(left)}")
    assert not crashes, "\n".join(crashes)
    assert not leftovers, "\n".join(leftovers)

"""`lsu launch` / `lsu run` with a real two-node graph, seen through the `lsu` introspection tools."""

import os
import re
import subprocess
import time
from pathlib import Path

import pytest
import yaml

from lsu_tools.processes import pid_alive

DATA = Path(__file__).parent / "data"
PINGPONG = str(DATA / "launch" / "pingpong.launch.yaml")

pytestmark = pytest.mark.slow


def check_exchange(lsu_cli, ns: str) -> None:
    """The listener echoes the talker's ScannerState; the talker's Step service moves it."""
    echo = lsu_cli("topic", "echo", f"/{ns}/selftest/echo", "--once", "--timeout", "20")
    assert echo.returncode == 0, echo.stderr
    msg = yaml.safe_load(echo.stdout.split("---")[0])
    assert msg["firmware"] == "selftest" and msg["track_steps"] == 1000000  # inline param reached the talker
    assert re.fullmatch(r"echo \d+", msg["fault"])  # it went through the listener
    call = lsu_cli("service", "call", f"/{ns}/selftest/step", "lsu_interfaces/srv/Step", "{steps: 7}",
                   "--timeout", "20")
    assert call.returncode == 0, call.stderr
    response = yaml.safe_load(call.stdout.split("response:", 1)[1])
    assert response["success"] is True
    # the listener also calls step (param file: 2 steps every 4 messages), so at least our 7
    assert response["position_steps"] >= 7
    state = yaml.safe_load(lsu_cli("topic", "echo", f"/{ns}/selftest/state", "--once", "--timeout", "20").stdout.split("---")[0])
    assert state["position_steps"] >= response["position_steps"]


def wait_until_listed(lsu_cli, expected: set[str], timeout_s: float = 60.0) -> None:
    """`lsu node list` shows every node of ``expected``, asked again until it does (at most ``timeout_s``).

    Each `lsu node list` discovers the graph afresh and stops once nothing new appeared for a
    moment; on a loaded host one node's announcement can come later than that, so a single listing
    may miss a node that is running (the exchange before proved both are). Listing again is what a
    user would do; a node that never shows up fails with what was listed.
    """
    deadline = time.monotonic() + timeout_s
    listings: list[list[str]] = []
    while time.monotonic() < deadline:
        listed = lsu_cli("node", "list")
        assert listed.returncode == 0, listed.stderr
        listings.append(listed.stdout.split())
        if expected <= set(listings[-1]):
            return
    pytest.fail(f"`lsu node list` did not show {sorted(expected - set(listings[-1]))} within {timeout_s:g} s "
                f"({len(listings)} listings; the last: {listings[-1]})")


def test_launch_exchange_and_sigint_stops_every_process(launch, lsu_cli):
    proc = launch("launch", PINGPONG, "ns:=pp_launch")
    proc.wait_for_line(r"started listener .* pid \d+")
    pids = proc.started_pids()
    assert set(pids) == {"talker", "listener"} and all(pid_alive(p) for p in pids.values())
    check_exchange(lsu_cli, "pp_launch")
    wait_until_listed(lsu_cli, {"/pp_launch/talker", "/pp_launch/listener"})

    code = proc.interrupt(timeout_s=10)
    # the launcher returned: every node it started has ended with it (waited for, not timed)
    t0 = time.monotonic()
    while any(pid_alive(p) for p in pids.values()) and time.monotonic() - t0 < 30:
        time.sleep(0.05)
    assert not any(pid_alive(p) for p in pids.values()), proc.output
    assert code == 0, proc.output
    assert "[talker]" in proc.output or "[lsu launch] all nodes stopped" in proc.output


def test_run_gives_the_same_exchange_in_one_process(launch, lsu_cli):
    proc = launch("run", PINGPONG, "ns:=pp_run")
    proc.wait_for_line(r"spinning 2 node\(s\) in one process \(multi-threaded")
    check_exchange(lsu_cli, "pp_run")
    children = subprocess.run(["pgrep", "-P", str(proc.process.pid)], capture_output=True, text=True).stdout.split()
    assert children == []  # both nodes live inside the lsu process
    code = proc.interrupt(timeout_s=10)
    assert code == 0, proc.output[-3000:]


def test_params_can_be_read_set_and_dumped(launch, lsu_cli):
    proc = launch("launch", PINGPONG, "ns:=pp_param")
    proc.wait_for_line(r"started listener")
    lsu_cli("service", "call", "/pp_param/selftest/step", "{steps: 0}", "--timeout", "20")  # up and answering
    assert lsu_cli("param", "get", "/pp_param/listener", "step_every", "--timeout", "20").stdout.strip() == "4"
    result = lsu_cli("param", "set", "/pp_param/listener", "step_every", "9", "--timeout", "20")
    assert result.returncode == 0 and "successful" in result.stdout
    dump = yaml.safe_load(lsu_cli("param", "dump", "/pp_param/listener", "--timeout", "20").stdout)
    assert dump["/pp_param/listener"]["ros__parameters"]["step_every"] == 9
    missing = lsu_cli("param", "get", "/pp_param/listener", "nope", "--timeout", "20")
    assert missing.returncode != 0 and "no parameter 'nope'" in missing.stderr


@pytest.mark.fault('process: required node dies')
def test_required_node_death_ends_the_launch_with_an_error(launch):
    proc = launch("launch", PINGPONG, "ns:=pp_req", "talker_required:=true")
    proc.wait_for_line(r"started listener")
    pids = proc.started_pids()
    os.kill(pids["talker"], 9)
    assert proc.process.wait(timeout=15) != 0
    assert "required node talker ended" in proc.output
    assert not pid_alive(pids["listener"])


def test_respawn_restarts_a_dead_node(launch):
    proc = launch("launch", PINGPONG, "ns:=pp_resp", "listener_respawn:=true")
    proc.wait_for_line(r"started listener")
    first = proc.started_pids()["listener"]
    os.kill(first, 9)
    proc.wait_for_line(r"listener ended .*respawning")
    deadline = time.monotonic() + 10
    while proc.started_pids()["listener"] == first and time.monotonic() < deadline:
        time.sleep(0.05)
    assert proc.started_pids()["listener"] != first and pid_alive(proc.started_pids()["listener"])


@pytest.mark.fault('process: launcher SIGKILLed')
def test_killed_launcher_leaves_no_orphans(launch):
    proc = launch("launch", PINGPONG, "ns:=pp_orphan")
    proc.wait_for_line(r"started listener")
    pids = proc.started_pids()
    proc.process.kill()  # SIGKILL: the launcher gets no chance to clean up
    proc.process.wait(timeout=5)
    deadline = time.monotonic() + 5
    while any(pid_alive(p) for p in pids.values()) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(pid_alive(p) for p in pids.values())


BAD_FILES = {
    "syntax": ("launch:\n- node:\n    pkg: lsu_tools\n    exec: [oops\n", r":\d+: .*YAML syntax error"),
    "package": ("launch:\n- node:\n    pkg: lsu_missing\n    exec: x\n", r":3: node.pkg: unknown package 'lsu_missing'"),
    "executable": ("launch:\n- node:\n    pkg: lsu_tools\n    exec: ghost\n",
                   r":4: node.exec: package 'lsu_tools' has no executable 'ghost'"),
    "param_file": ("launch:\n- node:\n    pkg: lsu_tools\n    exec: selftest_talker\n    param:\n"
                   "    - from: $(dirname)/nowhere.yaml\n", r":6: node selftest_talker.param.from: parameter file not found"),
    "var": ("launch:\n- node:\n    pkg: lsu_tools\n    exec: selftest_talker\n    name: $(var who)\n",
            r":5: node.name: unknown launch argument \$\(var who\)"),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_launch_file_gives_one_line_error(case, tmp_path, lsu_cli):
    text, expected = BAD_FILES[case]
    path = tmp_path / f"{case}.launch.yaml"
    path.write_text(text)
    for verb in ("launch", "run"):
        result = lsu_cli(verb, str(path), timeout=30)
        assert result.returncode == 2
        assert "Traceback" not in result.stderr + result.stdout
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1, result.stderr
        assert str(path) in lines[0] and re.search(expected, lines[0]), lines[0]


def test_unknown_launch_name_lists_the_known_ones(lsu_cli):
    result = lsu_cli("launch", "no_such_graph")
    assert result.returncode == 2 and "selftest" in result.stderr and "Traceback" not in result.stderr

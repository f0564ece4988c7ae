"""Two "hosts" on one machine for tests and benchmarks: network namespaces joined by a veth pair.

A rig PC and a processing PC, each with its own network stack (``lo`` plus one end of the veth
pair, addresses 10.231.0.1/30 and 10.231.0.2/30 that exist only inside these namespaces), so DDS
traffic between the two halves of the graph really crosses a network link (UDP only: shared
memory is off, as it would be between two PCs). Everything is removed by :meth:`TwoHosts.delete`
(the veth pair goes with its namespaces). Needs root (CAP_NET_ADMIN) and iproute2.

    with TwoHosts() as hosts:
        rig = LaunchedProcess(["launch", "sim", "--group", "rig"], prefix=hosts.prefix("rig"), env=hosts.env("rig"))
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from collections.abc import Mapping, Sequence
from pathlib import Path

from lsu_scan.rosenv import DISCOVERY_VAR

HOSTS = ("rig", "processing")
#: a /30 of its own: the two ends of the veth pair and nothing else
ADDRESSES = {"rig": "10.231.0.1", "processing": "10.231.0.2"}
PREFIX_LEN = 30
#: DDS discovery over the link: SUBNET (multicast on the veth) plus the other end as a static peer
PEERS_VAR = "ROS_STATIC_PEERS"


class NamespaceError(RuntimeError):
    """The namespaces cannot be made here (not root, no iproute2, no network namespaces)."""


def _ip(*args: str) -> None:
    done = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10)
    if done.returncode != 0:
        raise NamespaceError(f"`ip {' '.join(args)}` failed: {done.stderr.strip() or done.returncode}")


def why_unavailable() -> str | None:
    """None when network namespaces can be made here, else the reason (for a skip message)."""
    if shutil.which("ip") is None:
        return "iproute2 (`ip`) is not installed"
    if os.geteuid() != 0:
        return "making network namespaces needs root (CAP_NET_ADMIN)"
    probe = f"lsu-probe-{os.getpid()}"
    try:
        _ip("netns", "add", probe)
    except NamespaceError as exc:
        return str(exc)
    try:
        _ip("netns", "delete", probe)
    except NamespaceError:
        pass
    return None


class TwoHosts:
    """The rig and processing namespaces, their veth pair and addresses; a context manager."""

    def __init__(self, tag: str | None = None) -> None:
        tag = tag or str(os.getpid() % 1_000_000)
        self.namespaces = {"rig": f"lsu-rig-{tag}", "processing": f"lsu-proc-{tag}"}
        self.interfaces = {"rig": f"lsur{tag}"[:15], "processing": f"lsup{tag}"[:15]}
        self.addresses = dict(ADDRESSES)
        self._made: list[str] = []

    def create(self) -> TwoHosts:
        """Make both namespaces, the veth pair between them, addresses, and bring the links up."""
        try:
            for host in HOSTS:
                _ip("netns", "add", self.namespaces[host])
                self._made.append(self.namespaces[host])
            _ip("link", "add", self.interfaces["rig"], "netns", self.namespaces["rig"], "type", "veth",
                "peer", "name", self.interfaces["processing"], "netns", self.namespaces["processing"])
            for host in HOSTS:
                ns, dev = self.namespaces[host], self.interfaces[host]
                _ip("-n", ns, "addr", "add", f"{self.addresses[host]}/{PREFIX_LEN}", "dev", dev)
                _ip("-n", ns, "link", "set", "lo", "up")
                _ip("-n", ns, "link", "set", dev, "up")
                # DDS discovery multicast (239.255.0.1) leaves through the veth, the namespace's only link
                _ip("-n", ns, "route", "add", "224.0.0.0/4", "dev", dev)
        except Exception:
            self.delete()
            raise
        return self

    def delete(self) -> None:
        """Remove the namespaces (and with them the veth pair); safe to call twice."""
        while self._made:
            ns = self._made.pop()
            try:
                _ip("netns", "delete", ns)
            except NamespaceError:
                pass

    def __enter__(self) -> TwoHosts:
        return self.create()

    def __exit__(self, *exc: object) -> None:
        self.delete()

    def other(self, host: str) -> str:
        return HOSTS[1 - HOSTS.index(host)]

    def prefix(self, host: str) -> list[str]:
        """Command prefix that runs a program on ``host`` (it execs it: the pid is the program's)."""
        return ["ip", "netns", "exec", self.namespaces[host]]

    def env(self, host: str, base: Mapping[str, str] | None = None) -> dict[str, str]:
        """The environment of an LSU process on ``host``: what README "Rig PC and processing PC" says to set."""
        env = dict(os.environ if base is None else base)
        env[DISCOVERY_VAR] = "SUBNET"
        env[PEERS_VAR] = self.addresses[self.other(host)]
        # between two PCs there is no shared memory; here both namespaces share /dev/shm, so switch it off
        env["FASTDDS_BUILTIN_TRANSPORTS"] = "UDPv4"
        return env


def split_scan(out: Path, hosts: TwoHosts | None, groups: Sequence[str] = ("rig", "processing"),
               scan_args: Sequence[str] = (), launch_args: Sequence[str] = (), record: bool = True,
               timeout_s: float = 600.0) -> Path:
    """Run the sim graph as two `lsu launch sim --group G` processes and one `lsu scan`; returns the scan folder.

    With ``hosts`` the first group runs on the rig host and the second (and `lsu scan`) on the processing
    host; without, all three run here with the usual localhost settings (the one-host reference).
    Every process started is ended (SIGINT, then SIGKILL of its process group) before returning.
    """
    from .processes import LaunchedProcess

    out.mkdir(parents=True, exist_ok=True)
    common = ["launch", "sim", f"port:={out}/gp32", f"output_dir:={out}/scans", *launch_args]

    def where(host: str) -> dict[str, object]:
        return {"prefix": hosts.prefix(host), "env": hosts.env(host)} if hosts else {}

    started: list[LaunchedProcess] = []
    try:
        rig = LaunchedProcess([*common, "--group", groups[0]], **where("rig"))  # type: ignore[arg-type]
        started.append(rig)
        processing = LaunchedProcess([*common, "--group", groups[1]], **where("processing"))  # type: ignore[arg-type]
        started.append(processing)
        rig.wait_for_line(r"homed: track", timeout_s=180)
        rig.wait_for_line(r"source 'sim' open", timeout_s=180)
        scan = LaunchedProcess(["scan", *(["--record"] if record else []), "--wait", "120", "--out", str(out / "scans"),
                                *scan_args],
                               **where("processing"))  # type: ignore[arg-type]
        started.append(scan)
        code = scan.wait(timeout_s)
        match = re.search(r"files in (.+):", scan.output)
        if code != 0 or match is None:
            raise RuntimeError(f"`lsu scan` failed ({code}):\n{scan.output}\n--- rig:\n{rig.output[-3000:]}\n"
                               f"--- processing:\n{processing.output[-3000:]}")
        return Path(match.group(1))
    finally:
        for proc in reversed(started):
            proc.stop(timeout_s=15)

"""`lsu doctor`: is this machine ready to run the LSU graph? One line per check.

FAIL lines make the exit code non-zero and say what to do; WARN lines are information a
lab user wants (no serial port yet, no camera) but that do not stop a simulated run.
"""

from __future__ import annotations

import argparse
import glob
import importlib
import importlib.metadata as metadata
import ipaddress
import os
import platform
import socket
import subprocess
import sys
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from lsu_scan.rosenv import DISCOVERY_VAR, DOMAIN_VAR, LOCALHOST, EnvReport

INTERFACES = [
    "lsu_interfaces/msg/ScannerState", "lsu_interfaces/msg/SimTruth", "lsu_interfaces/msg/LaserLine",
    "lsu_interfaces/msg/ScanEvent", "lsu_interfaces/msg/StereoExtrinsics", "lsu_interfaces/srv/MoveTo",
    "lsu_interfaces/srv/Step", "lsu_interfaces/srv/CaptureStereo", "lsu_interfaces/srv/Enroll",
    "lsu_interfaces/srv/Identify", "lsu_interfaces/action/Scan", "lsu_interfaces/msg/CarriagePosition",
    "tf2_msgs/msg/TFMessage",
    "sensor_msgs/msg/PointCloud2", "sensor_msgs/msg/Image", "std_srvs/srv/SetBool",
    "diagnostic_msgs/msg/DiagnosticArray", "visualization_msgs/msg/Marker", "shape_msgs/msg/Mesh",
]
LIBRARIES = [("numpy", "numpy"), ("scipy", "scipy"), ("opencv", "cv2"), ("open3d", "open3d"),
             ("pyserial", "serial"), ("rosbags", "rosbags"), ("yaml", "yaml"), ("foxglove-sdk", "foxglove"),
             ("websockets", "websockets")]


@dataclass
class Check:
    """Outcome of one check."""

    status: str  # "OK", "WARN", "FAIL"
    name: str
    detail: str


def _interfaces() -> Check:
    missing = []
    for full in INTERFACES:
        package, kind, name = full.split("/")
        try:
            getattr(importlib.import_module(f"{package}.{kind}"), name)
        except Exception as exc:  # any import failure is the finding itself
            missing.append(f"{full} ({exc.__class__.__name__}: {exc})")
    if missing:
        return Check("FAIL", "interfaces", f"not importable: {missing[0]}"
                     f"{f' and {len(missing) - 1} more' if len(missing) > 1 else ''}; "
                     "run `make setup` to (re)build lsu_interfaces")
    return Check("OK", "interfaces", f"{len(INTERFACES)} types import (lsu_interfaces + common_interfaces)")


def _rclpy() -> Check:
    try:
        import rclpy
        from rclpy.context import Context
    except Exception as exc:
        return Check("FAIL", "rclpy", f"cannot import rclpy ({exc}); run `make setup`")
    context = Context()
    try:
        rclpy.init(context=context)
        node = rclpy.create_node(f"_lsu_doctor_{os.getpid()}", context=context)
        node.destroy_node()
        rmw = rclpy.get_rmw_implementation_identifier()
    except Exception as exc:
        return Check("FAIL", "rclpy", f"cannot start a ROS context ({exc.__class__.__name__}: {exc})")
    finally:
        rclpy.try_shutdown(context=context)
    return Check("OK", "rmw", f"{rmw} (RMW_IMPLEMENTATION={os.environ.get('RMW_IMPLEMENTATION', 'unset')})")


def _libraries() -> list[Check]:
    out = []
    for label, module in LIBRARIES:
        try:
            mod = importlib.import_module(module)
            version = getattr(mod, "__version__", None) or metadata.version(label)
            out.append(Check("OK", label, str(version)))
        except Exception as exc:
            hint = " (Debian: apt-get install libusb-1.0-0)" if "libusb" in str(exc) else " (run `make setup`)"
            out.append(Check("FAIL", label, f"cannot import {module}: {exc}{hint}"))
    return out


def _env(report: EnvReport | None) -> list[Check]:
    rng = os.environ.get(DISCOVERY_VAR, "")
    domain = os.environ.get(DOMAIN_VAR, "")
    by = " (set by lsu: it was unset)" if report and report.discovery_set_by_lsu else " (from your environment)"
    checks = [Check("OK" if rng == LOCALHOST else "WARN", "discovery",
                    f"{DISCOVERY_VAR}={rng}{by}" + ("" if rng == LOCALHOST else
                                                    "; DDS traffic may leave this machine"))]
    by = " (set by lsu: it was unset)" if report and report.domain_set_by_lsu else " (from your environment)"
    try:
        ok = 0 <= int(domain) <= 232
    except ValueError:
        ok = False
    checks.append(Check("OK" if ok else "FAIL", "domain", f"{DOMAIN_VAR}={domain}{by}" +
                        ("" if ok else "; must be an integer 0..232")))
    return checks


PEERS_VAR = "ROS_STATIC_PEERS"
TRANSPORTS_VAR = "FASTDDS_BUILTIN_TRANSPORTS"
_IFF_UP, _IFF_MULTICAST = 0x1, 0x1000
#: a port in the DDS range, only used to ask the kernel for a route (connect() on UDP sends nothing)
_PROBE_PORT = 7400


def local_addresses() -> dict[str, str]:
    """IPv4 address -> interface name of this machine (``ip -o -4 addr``)."""
    try:
        out = subprocess.run(["ip", "-o", "-4", "addr", "show"], capture_output=True, text=True, timeout=5).stdout
    except (OSError, subprocess.SubprocessError):
        return {}
    found = {}
    for line in out.splitlines():
        parts = line.split()
        if len(parts) > 3 and parts[2] == "inet":
            found[parts[3].split("/")[0]] = parts[1].split("@")[0]
    return found


def _interface_flags(name: str) -> int:
    try:
        return int(Path(f"/sys/class/net/{name}/flags").read_text().strip(), 16)
    except (OSError, ValueError):
        return 0


def route_to(address: str) -> str | None:
    """The local IPv4 address the kernel would send from to reach ``address`` (nothing is sent)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            sock.connect((address, _PROBE_PORT))
            return sock.getsockname()[0]
        except OSError:
            return None


def multi_host_checks(env: Mapping[str, str], report: EnvReport | None = None) -> list[Check]:
    """Settings a graph spread over two PCs needs (README "Rig PC and processing PC").

    On LOCALHOST without peers this is a single line; otherwise: the domain id chosen explicitly
    (both PCs need the same one), discovery that reaches the other PC, each static peer resolved
    and routed through a non-loopback interface that is up, and a transport that crosses machines.
    """
    rng = env.get(DISCOVERY_VAR, "") or "SYSTEM_DEFAULT"
    peers = [p.strip() for p in env.get(PEERS_VAR, "").replace(",", ";").split(";") if p.strip()]
    if rng == LOCALHOST and not peers:
        return [Check("OK", "multi-host", "off: DDS stays on this machine (LOCALHOST, no ROS_STATIC_PEERS); "
                      "README 'Rig PC and processing PC' says what to set for two PCs")]
    checks: list[Check] = []
    if rng == "OFF":
        checks.append(Check("FAIL", "multi-host discovery", f"{DISCOVERY_VAR}=OFF finds no node, not even the "
                            "static peers; use SUBNET"))
    elif rng == LOCALHOST:
        checks.append(Check("WARN", "multi-host discovery", f"{DISCOVERY_VAR}=LOCALHOST: only the static peers "
                            f"{', '.join(peers)} are looked for beyond this machine; SUBNET also finds them by multicast"))
    else:
        checks.append(Check("OK", "multi-host discovery", f"{DISCOVERY_VAR}={rng}" +
                            (f", static peers {', '.join(peers)}" if peers else ", by multicast only (no "
                             f"{PEERS_VAR}; set it where multicast does not pass, e.g. Wi-Fi)")))
    if report is not None and report.domain_set_by_lsu:
        checks.append(Check("WARN", "multi-host domain", f"{DOMAIN_VAR} was unset (lsu uses {env.get(DOMAIN_VAR)}); "
                            "set the same ROS_DOMAIN_ID on both PCs, so the graph is yours alone"))
    else:
        checks.append(Check("OK", "multi-host domain", f"{DOMAIN_VAR}={env.get(DOMAIN_VAR, '')}: use the same on "
                            "the other PC"))
    transports = env.get(TRANSPORTS_VAR, "")
    if transports.upper() == "SHM":
        checks.append(Check("FAIL", "multi-host transport", f"{TRANSPORTS_VAR}=SHM: shared memory carries nothing "
                            "to another PC; unset it or use UDPv4"))
    addresses = local_addresses()
    for peer in peers:
        try:
            target = str(socket.getaddrinfo(peer, None, socket.AF_INET)[0][4][0])
        except (socket.gaierror, IndexError):
            checks.append(Check("FAIL", "multi-host peer", f"{peer} does not resolve to an IPv4 address; write "
                                f"the other PC's address in {PEERS_VAR}"))
            continue
        source = route_to(target)
        if source is None:
            checks.append(Check("FAIL", "multi-host peer", f"{peer} ({target}): no route from this machine; "
                                "connect the network / check the address"))
            continue
        if ipaddress.ip_address(source).is_loopback:
            checks.append(Check("WARN", "multi-host peer", f"{peer} ({target}) is this machine itself"))
            continue
        iface = addresses.get(source, "")
        flags = _interface_flags(iface) if iface else 0
        up = bool(flags & _IFF_UP)
        detail = f"{peer} ({target}) via {iface or '?'} {source}"
        if iface and not up:
            checks.append(Check("FAIL", "multi-host peer", f"{detail}: the interface is down"))
        elif iface and rng not in (LOCALHOST, "OFF") and not flags & _IFF_MULTICAST:
            checks.append(Check("WARN", "multi-host peer", f"{detail}: no multicast on it, so discovery relies on "
                                f"{PEERS_VAR} (set it on both PCs)"))
        else:
            checks.append(Check("OK", "multi-host peer", detail))
    if not peers and rng not in (LOCALHOST, "OFF"):
        usable = sorted(name for addr, name in addresses.items()
                        if not ipaddress.ip_address(addr).is_loopback
                        and _interface_flags(name) & (_IFF_UP | _IFF_MULTICAST) == _IFF_UP | _IFF_MULTICAST)
        checks.append(Check("OK" if usable else "FAIL", "multi-host interface",
                            f"multicast discovery on {', '.join(usable)}" if usable else
                            "no network interface with multicast is up: nothing reaches another PC"))
    return checks


def _devices() -> list[Check]:
    ports = sorted(glob.glob("/dev/ttyUSB*") + glob.glob("/dev/ttyACM*"))
    videos = sorted(glob.glob("/dev/video*"))
    return [
        Check("OK" if ports else "WARN", "serial ports",
              ", ".join(ports) if ports else "no USB serial port (fine for the emulator: lsu gp32 emulate)"),
        Check("OK" if videos else "WARN", "video devices",
              ", ".join(videos) if videos else "no /dev/video* (fine for the simulated rig)"),
    ]


def _graph_selftest(timeout_s: float) -> Check:
    """Talker + listener in this process: a message through a topic and a service round trip."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor

    from .selftest import SelftestListener, SelftestTalker

    context = Context()
    rclpy.init(context=context)
    try:
        talker = SelftestTalker(context=context)
        listener = SelftestListener(context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(talker)
        executor.add_node(listener)
        end = time.monotonic() + timeout_s
        while time.monotonic() < end and not (listener.received >= 5 and talker.position_steps > 0):
            executor.spin_once(timeout_sec=0.05)
        ok = listener.received >= 5 and talker.position_steps > 0
        executor.shutdown()
        talker.destroy_node()
        listener.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
    if not ok:
        return Check("FAIL", "graph", f"selftest exchange incomplete after {timeout_s:g} s "
                     f"({listener.received} messages, position {talker.position_steps}); DDS is not working")
    return Check("OK", "graph", f"topic + service round trip in one process ({listener.received} messages)")


def run_checks(report: EnvReport | None, graph: bool) -> list[Check]:
    """All checks, in the order they are printed."""
    checks = [Check("OK", "python", f"{platform.python_version()} at {sys.executable}")]
    checks += _env(report)
    checks += multi_host_checks(os.environ, report)
    checks += _libraries()
    checks.append(_interfaces())
    checks.append(_rclpy())
    checks += _devices()
    if graph and all(c.status != "FAIL" for c in checks):
        checks.append(_graph_selftest(10.0))
    return checks


def cmd_doctor(args: argparse.Namespace) -> int:
    checks = run_checks(getattr(args, "env_report", None), args.graph)
    width = max(len(c.name) for c in checks)
    for c in checks:
        print(f"{c.status:<4}  {c.name:<{width}}  {c.detail}")
    failed = [c.name for c in checks if c.status == "FAIL"]
    if failed:
        print(f"lsu doctor: {len(failed)} problem(s): {', '.join(failed)}", file=sys.stderr)
        return 1
    print("lsu doctor: all checks passed")
    return 0


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `doctor` to the `lsu` parser (``lsu.commands`` entry point)."""
    p = sub.add_parser("doctor", help="check the installation, ROS environment and devices")
    p.add_argument("--graph", action="store_true", help="also run a talker/listener exchange through DDS")
    p.set_defaults(func=cmd_doctor)

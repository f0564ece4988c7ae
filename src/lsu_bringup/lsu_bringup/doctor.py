"""`lsu doctor`: is this machine ready to run the LSU graph? One line per check.

FAIL lines make the exit code non-zero and say what to do; WARN lines are information a
lab user wants (no serial port yet, no camera) but that do not stop a simulated run.
"""

from __future__ import annotations

import argparse
import glob
import importlib
import importlib.metadata as metadata
import os
import platform
import sys
import time
from dataclasses import dataclass
from typing import Callable, List, Optional

from .rosenv import DISCOVERY_VAR, DOMAIN_VAR, LOCALHOST, EnvReport

INTERFACES = [
    "lsu_interfaces/msg/ScannerState", "lsu_interfaces/msg/SimTruth", "lsu_interfaces/msg/LaserLine",
    "lsu_interfaces/msg/ScanEvent", "lsu_interfaces/msg/StereoExtrinsics", "lsu_interfaces/srv/MoveTo",
    "lsu_interfaces/srv/Step", "lsu_interfaces/srv/CaptureStereo", "lsu_interfaces/srv/Enroll",
    "lsu_interfaces/srv/Identify", "lsu_interfaces/action/Scan",
    "sensor_msgs/msg/PointCloud2", "sensor_msgs/msg/Image", "std_srvs/srv/SetBool",
    "diagnostic_msgs/msg/DiagnosticArray", "visualization_msgs/msg/Marker", "shape_msgs/msg/Mesh",
]
LIBRARIES = [("numpy", "numpy"), ("scipy", "scipy"), ("opencv", "cv2"), ("open3d", "open3d"),
             ("pyserial", "serial"), ("rosbags", "rosbags"), ("yaml", "yaml")]


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


def _libraries() -> List[Check]:
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


def _env(report: Optional[EnvReport]) -> List[Check]:
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


def _devices() -> List[Check]:
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


def run_checks(report: Optional[EnvReport], graph: bool) -> List[Check]:
    """All checks, in the order they are printed."""
    checks = [Check("OK", "python", f"{platform.python_version()} at {sys.executable}")]
    checks += _env(report)
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


def register(sub: "argparse._SubParsersAction[argparse.ArgumentParser]",
             env_report: Callable[[], Optional[EnvReport]]) -> None:
    """Add `doctor` to the `lsu` parser."""
    p = sub.add_parser("doctor", help="check the installation, ROS environment and devices")
    p.add_argument("--graph", action="store_true", help="also run a talker/listener exchange through DDS")
    p.set_defaults(func=cmd_doctor, env_report=env_report())

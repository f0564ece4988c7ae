"""`lsu demo` (what `make demo` runs): start a graph, show it working, stop it, say what happened.

Today the graph is the selftest pair: the hardware nodes (driver, cameras, extraction,
matching, faces) and the scan coordinator arrive with their issues, and the demo grows
into a full scan of a synthetic head on the emulated unit.
"""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
import time
from pathlib import Path

from . import rosenv


def _lsu(*args: str, timeout: float = 30.0) -> subprocess.CompletedProcess:
    return subprocess.run([str(Path(sys.executable).parent / "lsu"), *args], capture_output=True, text=True,
                          timeout=timeout)


def cmd_demo(args: argparse.Namespace) -> int:
    claim = rosenv.isolate()
    print(f"[demo] DDS: localhost only, ROS_DOMAIN_ID={claim.domain_id} (claimed for this run)")
    launch = subprocess.Popen([str(Path(sys.executable).parent / "lsu"), "launch", "selftest"],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    steps = []
    try:
        time.sleep(1.0)
        echo = _lsu("topic", "echo", "/lsu/selftest/echo", "--once", "--timeout", "15")
        steps.append(("topic echo /lsu/selftest/echo (ScannerState through the listener)", echo))
        call = _lsu("service", "call", "/lsu/selftest/step", "{steps: 5}", "--timeout", "15")
        steps.append(("service call /lsu/selftest/step {steps: 5} (lsu_interfaces/srv/Step)", call))
        nodes = _lsu("node", "list")
        steps.append(("node list", nodes))
    finally:
        launch.send_signal(signal.SIGINT)
        try:
            output, _ = launch.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            launch.kill()
            output, _ = launch.communicate()
        claim.release()
    ok = True
    for title, result in steps:
        ok &= result.returncode == 0
        print(f"[demo] $ lsu {title}: {'ok' if result.returncode == 0 else 'FAILED'}")
        for line in (result.stdout or result.stderr).strip().splitlines()[:12]:
            print(f"         {line}")
    print(f"[demo] lsu launch ended with exit code {launch.returncode} after SIGINT")
    print("[demo] what ran: the selftest graph (two nodes exchanging lsu_interfaces messages over DDS).")
    print("[demo] not yet: GP32 emulator, simulated cameras, extraction, triangulation, meshing and the scan "
          "action arrive with their issues; then this demo runs a full scan and writes cloud, mesh, renders "
          "and a bag.")
    return 0 if ok and launch.returncode == 0 else 1


def register(sub: "argparse._SubParsersAction[argparse.ArgumentParser]") -> None:
    """Add `demo` to the `lsu` parser."""
    p = sub.add_parser("demo", help="run the demo graph on this machine and report what it did")
    p.set_defaults(func=cmd_demo)


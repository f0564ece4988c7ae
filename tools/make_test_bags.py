"""Regenerate the committed test bags under test/data/bags/ with the project's own simulator.

    .venv/bin/python tools/make_test_bags.py

Starts the sim graph (emulated GP32, simulated rig looking at synthetic head 7) in a domain of
its own, runs a short scan with a bag (mcap + zstd) and copies the bag to
test/data/bags/scan_head/. Small on purpose: a few snaps keep the file at a few MB.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    from lsu_scan import rosenv
    from lsu_scan.scanner import LsuScanner
    from lsu_tools.processes import LaunchedProcess

    claim = rosenv.isolate()
    target = ROOT / "test" / "data" / "bags" / "scan_head"
    with tempfile.TemporaryDirectory(prefix="lsu-bags-") as tmp:
        graph = LaunchedProcess(["launch", "sim", f"port:={tmp}/gp32", "scene:=head:7", f"output_dir:={tmp}/scans"])
        try:
            graph.wait_for_line(r"homed: track", timeout_s=120)
            scanner = LsuScanner(wait_s=60)
            time.sleep(1.0)
            result = scanner.scan(start=205, end=265, step=12, settle_s=0.1, record_bag=True)
            scanner.close()
        finally:
            graph.stop(timeout_s=20)
            claim.release()
        if not result.success:
            print(f"scan failed: {result.status}", file=sys.stderr)
            return 1
        if target.exists():
            shutil.rmtree(target)
        shutil.copytree(Path(result.output_dir) / "bag", target)
    size = sum(p.stat().st_size for p in target.rglob("*") if p.is_file())
    print(f"{target}: {result.snaps} snaps, {result.points} points, {size / 1e6:.1f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())

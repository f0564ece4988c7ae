"""Soak benchmark: one sim graph, many scans back to back; does any node grow?

    make bench-soak   ->  bench/results/soak.json

`lsu launch sim` (separate processes, synthetic head), a few warm-up scans (first-call costs:
imports, caches, allocator arenas), then ``LSU_SOAK_SCANS`` (default 50) scans of 48 snaps each,
as a lab session would run them. After every scan the resident memory (VmRSS) and the open file
descriptors of every node process are read from /proc. Per node, the growth per scan is the
Theil-Sen slope of RSS over the scan index (robust to the allocator's occasional jumps);
``rss_growth_mb_per_scan_max`` is the largest over the nodes (goal <= 0.2) and ``fd_growth`` the
largest rise of a node's descriptor count from the first measured scan to the last (goal 0).
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

from common import write_result
from scipy.stats import theilslopes

from lsu_scan import rosenv

SCANS = int(os.environ.get("LSU_SOAK_SCANS", "50"))
WARMUP_SCANS = 3
START, END, STEP = 130, 224, 2  # 48 snaps across the face


def rss_mb(pid: int) -> float:
    """Resident memory of ``pid`` [MB] (VmRSS of /proc/PID/status)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    raise RuntimeError(f"no VmRSS for pid {pid}")


def open_fds(pid: int) -> int:
    return len(os.listdir(f"/proc/{pid}/fd"))


def soak(tmp: Path) -> dict[str, dict[str, list[float]]]:
    from lsu_scan.scanner import LsuScanner
    from lsu_testing.plugin import LaunchedProcess

    # generous capture/ack timeouts: this measures growth, not speed, and a busy host must not abort scans
    graph = LaunchedProcess(["launch", "sim", f"port:={tmp}/gp32", "scene:=head:7", f"output_dir:={tmp}/scans",
                             "capture_timeout_s:=10.0", "ack_timeout_s:=30.0"])
    samples: dict[str, dict[str, list[float]]] = {}
    try:
        graph.wait_for_line(r"homed: track", timeout_s=120)
        graph.wait_for_line(r"source 'sim' open", timeout_s=120)
        with LsuScanner(wait_s=60) as scanner:
            for index in range(WARMUP_SCANS + SCANS):
                result = scanner.scan(start=START, end=END, step=STEP, settle_s=0.05,
                                      output_dir=str(tmp / "scans"))
                if not result.success:
                    raise RuntimeError(f"scan {index} failed: {result.status}")
                if index < WARMUP_SCANS:
                    continue
                time.sleep(1.0)  # face_processor meshes after FINISHED: measure between scans, not during
                pids = graph.started_pids()
                for name, pid in pids.items():
                    node = samples.setdefault(name, {"rss_mb": [], "fds": []})
                    node["rss_mb"].append(rss_mb(pid))
                    node["fds"].append(float(open_fds(pid)))
                print(f"[bench-soak] scan {index - WARMUP_SCANS + 1}/{SCANS}: " + ", ".join(
                    f"{n} {s['rss_mb'][-1]:.0f} MB/{s['fds'][-1]:.0f} fd" for n, s in sorted(samples.items())),
                    flush=True)
    finally:
        graph.stop(timeout_s=30)
    return samples


def main() -> int:
    claim = rosenv.isolate()
    try:
        with tempfile.TemporaryDirectory(prefix="lsu-soak-") as tmp:
            samples = soak(Path(tmp))
    finally:
        claim.release()
    figures: dict[str, float] = {}
    units: dict[str, str] = {}
    slopes = {}
    for name, s in sorted(samples.items()):
        slope = float(theilslopes(s["rss_mb"], range(len(s["rss_mb"])))[0]) if len(s["rss_mb"]) > 1 else 0.0
        slopes[name] = slope
        figures[f"rss_growth_mb_per_scan_{name}"] = round(slope, 4)
        figures[f"rss_mb_end_{name}"] = round(s["rss_mb"][-1], 1)
        units[f"rss_growth_mb_per_scan_{name}"] = "MB/scan"
        units[f"rss_mb_end_{name}"] = "MB"
    figures["rss_growth_mb_per_scan_max"] = round(max(slopes.values()), 4)
    figures["fd_growth"] = max(int(s["fds"][-1] - s["fds"][0]) for s in samples.values())
    figures["soak_scans"] = SCANS
    units.update(rss_growth_mb_per_scan_max="MB/scan", fd_growth="descriptors", soak_scans="scans")
    worst = max(slopes, key=slopes.get)
    notes = (f"{SCANS} scans of {len(range(START, END + 1, STEP))} snaps on one `lsu launch sim` (head scene) after "
             f"{WARMUP_SCANS} warm-up scans; RSS and fds read 1 s after each scan; growth = Theil-Sen slope. "
             f"Largest grower: {worst}. Goals: rss_growth_mb_per_scan_max <= 0.2, fd_growth 0.")
    write_result("soak", figures, units, notes)
    print(f"[bench-soak] rss growth max {figures['rss_growth_mb_per_scan_max']:.3f} MB/scan ({worst}), "
          f"fd growth {figures['fd_growth']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

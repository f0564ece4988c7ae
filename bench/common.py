"""Shared helpers for benchmarks: timing and the one JSON format of ARCHITECTURE.md "Benchmarks".

Each `bench/bench_<area>.py` measures its figures and calls `write_result(area, figures, units, notes)`,
which writes `bench/results/<area>.json`:
``{"area", "when", "machine": {cpu, cores, python, numpy, opencv, open3d}, "figures", "units", "notes"}``.
Ratios are measured against a reference timed in the same run (see `time_calls`).
"""

from __future__ import annotations

import datetime as _dt
import importlib
import json
import os
import platform
import statistics
import time
from collections.abc import Callable
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def _version(module: str) -> str:
    try:
        return str(getattr(importlib.import_module(module), "__version__", "?"))
    except Exception as exc:  # a missing library is reported, not fatal for the benchmark
        return f"unavailable ({exc.__class__.__name__})"


def machine_info() -> dict[str, object]:
    """CPU, core count and library versions, recorded with every result."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(),
            "numpy": _version("numpy"), "opencv": _version("cv2"), "open3d": _version("open3d")}


def time_calls(fn: Callable[[], object], repeat: int = 50, warmup: int = 3) -> list[float]:
    """Wall times of ``repeat`` calls of ``fn`` in milliseconds (after ``warmup`` untimed calls)."""
    for _ in range(warmup):
        fn()
    out = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        out.append((time.perf_counter() - t0) * 1000.0)
    return out


def median(values: list[float]) -> float:
    """Median of a list."""
    return float(statistics.median(values))


def percentile(values: list[float], pct: float) -> float:
    """``pct`` percentile (nearest rank)."""
    ordered = sorted(values)
    index = min(len(ordered) - 1, max(0, int(round(pct / 100.0 * len(ordered) + 0.5)) - 1))
    return float(ordered[index])


def write_result(area: str, figures: dict[str, float], units: dict[str, str], notes: str = "",
                 extra: dict[str, object] | None = None) -> Path:
    """Write ``bench/results/<area>.json`` and print a short summary; returns the path."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    record: dict[str, object] = {
        "area": area,
        "when": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "machine": machine_info(),
        "figures": {k: float(v) for k, v in figures.items()},
        "units": units,
        "notes": notes,
    }
    if extra:
        record.update(extra)
    path = RESULTS / f"{area}.json"
    path.write_text(json.dumps(record, indent=2) + "\n")
    print(f"[bench {area}] -> {path}")
    for name, value in figures.items():
        print(f"  {name:<32} {value:12.4f} {units.get(name, '')}")
    return path

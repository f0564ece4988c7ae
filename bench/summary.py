"""`make bench` summary: the headline figures of every bench/results/<area>.json in one Markdown table.

    python bench/summary.py   ->  bench/results/SUMMARY.md (and printed)

Each row: area, figure, value with its unit, the issue's target where one exists, and whether it
is met; the result's date and machine come from the JSON itself. Nothing is measured here.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"

# (area, figure, target text, test) - the acceptance figures of the issues; other figures stay in the JSON
HEADLINES: list[tuple[str, str, str, str | None]] = [
    ("driver", "roundtrip_ms_median", "", None),
    ("firmware", "flash_bytes", "<= 32768 (GP32 flash)", "<= 32768"),
    ("firmware", "ram_bytes", "<= 512 (GP32 RAM)", "<= 512"),
    ("firmware", "roundtrip_ms_median", "(through the HC08 simulator)", None),
    ("cameras", "render_pair_ms_median", "", None),
    ("cameras", "calib_focal_err_pct", "<= 0.5", "<= 0.5"),
    ("cameras", "calib_baseline_err_pct", "<= 0.5", "<= 0.5"),
    ("cameras", "calib_rotation_err_deg", "<= 0.1", "<= 0.1"),
    ("extract", "rms_px_default", "(rig physics on: speckle, skin; <= 0.1 on clean frames)", None),
    ("extract", "rms_px_plane_blais_rioux", "(plane at 300 mm, near its speckle limit)", None),
    ("extract", "rms_px_thesis", "(thesis method)", None),
    ("extract", "rms_px_real_dev", "<= 0.3 (real photographs)", "<= 0.3"),
    ("extract", "rms_px_real_worst_set", "<= 0.3 (the worst real set; default chosen by bench/study_extract.py)", "<= 0.3"),
    ("extract", "missed_rows_pct_real_dev", "<= 1", "<= 1"),
    ("extract", "false_rows_pct_real_dev", "<= 0.5", "<= 0.5"),
    ("extract", "false_rows_pct_ambient", "<= 0.5", "<= 0.5"),
    ("extract", "false_rows_pct_ambient_diff", "0 (with the laser-off frame)", "<= 0"),
    ("extract", "missed_rows_pct_ambient", "<= 1", "<= 1"),
    ("extract", "extract_ms_median", "<= 2", "<= 2"),
    ("extract", "extract_over_copy_ratio", "<= 8", "<= 8"),
    ("extract", "extract_over_copy_ratio_1152", "<= 8", "<= 8"),
    ("extract", "extract_over_copy_ratio_rig_head", "", None),
    ("reconstruct", "plane_sigma_mm_300", "", None),
    ("reconstruct", "sphere_radius_err_mm", "within 0.1 (60 mm sphere)", "within 0.1 of 0"),
    ("accuracy", "speckle_limit_mm_300", "(physical limit)", None),
    ("accuracy", "plane_sigma_mm_300", "", None),
    ("accuracy", "plane_sigma_over_speckle_limit", "<= 1.5", "<= 1.5"),
    ("accuracy", "three_sigma_mm_300_smoothed", "<= 0.15", "<= 0.15"),
    ("accuracy", "thesis_three_sigma_mm_300", "(thesis chain)", None),
    ("accuracy", "gaussian_1sigma_pct", "68.2 +- 3", "within 3 of 68.2"),
    ("accuracy", "gaussian_2sigma_pct", "95.4 +- 3", "within 3 of 95.4"),
    ("accuracy", "gaussian_3sigma_pct", "99.7 +- 3", "within 3 of 99.7"),
    ("faces", "rank1_pct_realistic", ">= 99", ">= 99"),
    ("faces", "rank1_pct_coarse_depth", ">= 95", ">= 95"),
    ("faces", "nose_within_5mm_pct_realistic", ">= 99", ">= 99"),
    ("faces", "same_result_across_processes", "1", ">= 1"),
    ("faces", "false_accept_pct_at_threshold", "<= 1", "<= 1"),
    ("faces", "false_reject_pct_at_threshold", "", None),
    ("faces", "false_reject_pct_at_threshold_coarse_depth", "", None),
    ("faces", "genuine_distance_mm_median_tof", "within 20 % of 2.48 (real depth maps)", "within 0.496 of 2.48"),
    ("faces", "impostor_distance_mm_median_tof", "within 20 % of 3.35 (real depth maps)", "within 0.67 of 3.35"),
    ("faces", "rank1_pct_population_tof", ">= 99 (N = 1,000, ICT people, ToF model)", ">= 99"),
    ("faces", "rank1_pct_population_rig", ">= 99.5 (N = 1,000, ICT people, LSU rig)", ">= 99.5"),
    ("faces", "fnir_pct_at_fpir_1_tof", "<= 5", "<= 5"),
    ("faces", "identify_ms_at_100k", "<= 100", "<= 100"),
    ("faces", "enroll_refused_pct", "0 (real faces)", "<= 0"),
    ("scan", "scan_wall_over_mechanical", "<= 1.2", "<= 1.2"),
    ("scan", "scan_wall_over_mechanical_recording", "(with its bag)", None),
    ("scan", "replay_snaps_per_s", ">= 300 (`lsu run replay BAG`)", ">= 300"),
    ("scan", "replay_cpu_over_compute", "<= 1.15 (replay CPU / the computation called directly)", "<= 1.15"),
    ("scan", "replay_snaps_per_s_over_before", ">= 1.2 (against the code before issue 33 on the same work, same run)", ">= 1.2"),
    ("scan", "replay_cpu_over_compute_and_read", "(the same, reading the bag counted in the reference)", None),
    ("scan", "replay_dds_snaps_per_s", "(the message path: bag played into the replay graph)", None),
    ("scan", "bridge_overhead_pct", "<= 5 (live view)", "<= 5"),
    ("scan", "web_overhead_pct", "<= 5 (the web page open, live points)", "<= 5"),
    ("scan", "two_host_scan_wall_over_one_host", "<= 1.1", "<= 1.1"),
    ("scan", "adaptive_settle_rms_over_fixed", "<= 1.1 (realistic person, same frames)", "<= 1.1"),
    ("scan", "adaptive_settle_time_over_fixed", "< 1 (faster than the fixed settle)", "<= 0.999"),
    ("scan", "stopsnap_points_over_1mm_pct", "<= 0.1 (realistic person)", "<= 0.1"),
    ("scan", "motion_rms_standing_corrected_over_still", "<= 1.5 (standing subject, corrected)", "<= 1.5"),
    ("scan", "motion_flagged_pct_beyond_limit", "100 (scans beyond the stated motion limit)", ">= 100"),
    ("scan", "motion_flagged_pct_still", "0 (still scans)", "<= 0"),
    ("scan", "sweep_60fps_rms_over_30fps", "(60 fps sweep at twice the rate, still person)", None),
    ("scan", "sweep_scan_s_60fps", "<= 4 s (60 fps face sweep at twice the rate, live sim)", "<= 4"),
    ("scan", "sweep_scan_minus_render_lag_s_60fps", "(the same less the simulated camera's render lag)", None),
    ("soak", "rss_growth_mb_per_scan_max", "<= 0.2", "<= 0.2"),
    ("soak", "fd_growth", "0", "<= 0"),
    ("batch", "speedup_2_workers", ">= 1.8", ">= 1.8"),
    ("batch", "task_overhead_pct", "<= 5", "<= 5"),
    ("batch", "bags_equal_to_replay_pct", "100", ">= 100"),
    ("batch", "two_node_bags_done_pct", "100 (two Ray nodes on this machine)", ">= 100"),
]

# figures of an area whose parts are measured apart ("measured" in its JSON: part -> when and how)
PART_OF = {("scan", "scan_wall_over_mechanical"): "live", ("scan", "scan_wall_over_mechanical_recording"): "live",
           **{("scan", name): "replay" for _, name, _, _ in HEADLINES if name.startswith("replay_")},
           ("scan", "adaptive_settle_rms_over_fixed"): "person_stopsnap",
           ("scan", "adaptive_settle_time_over_fixed"): "person_stopsnap",
           ("scan", "stopsnap_points_over_1mm_pct"): "person_stopsnap",
           **{("scan", name): "motion" for _, name, _, _ in HEADLINES if name.startswith(("motion_", "sweep_60fps"))},
           ("scan", "sweep_scan_s_60fps"): "motion_live", ("scan", "sweep_scan_minus_render_lag_s_60fps"): "motion_live",
           ("scan", "bridge_overhead_pct"): "view", ("scan", "web_overhead_pct"): "web", ("scan", "two_host_scan_wall_over_one_host"): "two_host"}


def _when(result: dict, area: str, name: str) -> str:
    """When ``name`` was measured: its part's date where the area measures parts apart, else the result's."""
    part = result.get("measured", {}).get(PART_OF.get((area, name), ""), "")
    return part[:16].replace(" ", "T") if part else result["when"][:16]


def _met(value: float, test: str | None) -> str:
    if test is None:
        return ""
    op, _, ref = test.partition(" ")
    if op == "<=":
        return "yes" if value <= float(ref) else "NO"
    if op == ">=":
        return "yes" if value >= float(ref) else "NO"
    if op == "within":
        width, _, centre = ref.partition(" of ")
        return "yes" if abs(value - float(centre)) <= float(width) else "NO"
    raise ValueError(f"unknown target test {test!r}")


def summary(results: Path = RESULTS) -> str:
    """The Markdown table of the headline figures found under ``results``."""
    data: dict[str, dict] = {}
    for path in sorted(results.glob("*.json")):
        data[path.stem] = json.loads(path.read_text())
    lines = ["| area | figure | value | target | met | measured |", "|---|---|---|---|---|---|"]
    for area, name, target, test in HEADLINES:
        result = data.get(area)
        if result is None or name not in result.get("figures", {}):
            lines.append(f"| {area} | {name} | (not measured: run `make bench-{area}`) | {target} | | |")
            continue
        value = float(result["figures"][name])
        unit = result.get("units", {}).get(name, "")
        lines.append(f"| {area} | {name} | {value:.4g} {unit} | {target} | {_met(value, test)} | {_when(result, area, name)} |")
    machines = {r["machine"].get("cpu", "?") + f", {r['machine'].get('cores', '?')} cores" for r in data.values()
                if "machine" in r}
    return "\n".join(["# Benchmark summary", "", f"Machine(s): {'; '.join(sorted(machines))}.", "",
                      *lines, "", "Every figure, its unit and how it was measured: bench/results/<area>.json.", ""])


def main() -> int:
    text = summary()
    (RESULTS / "SUMMARY.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Sweep goal checks and frame accounting (lsu_scan.sweep_plan)."""

import pytest

from lsu_scan.scan_plan import ScanGoalError
from lsu_scan.sweep_plan import plan_sweep, scan_mode


def test_mode_defaults_to_stopsnap_and_names_the_choices():
    assert scan_mode("") == "stopsnap" and scan_mode("Sweep") == "sweep"
    with pytest.raises(ScanGoalError, match="stopsnap, sweep"):
        scan_mode("continuous")


def test_full_track_sweep_at_60_steps_per_s_gives_as_many_frames_as_the_default_stop_snap_scan():
    plan = plan_sweep(0, 470, 470, 60.0, 30.0)
    assert plan.duration_s == pytest.approx(470 / 60.0)
    # frames at 0, 1/30, ... up to the end of the motion: 7.83 s * 30 + 1; stop-snap 0..470 step 2 has 236
    assert plan.frames_expected == 236
    record = plan.record(230)
    assert record["frames_dropped"] == 6 and record["frames_dropped_pct"] == pytest.approx(100 * 6 / 236, abs=1e-3)
    assert plan.record(240)["frames_dropped"] == 0


@pytest.mark.parametrize("args,needle", [
    ((0, 470, 470, 200.0, 30.0), "180"),           # the carriage oversteps above 180 steps/s
    ((0, 470, 470, 10.0, 30.0), "20..180"),
    ((0, 470, 470, 60.0, 0.0), "frame_rate_hz"),
    ((0, 500, 470, 60.0, 30.0), "outside the track"),
    ((100, 100, 470, 60.0, 30.0), "different"),
    ((0, 470, 0, 60.0, 30.0), "home"),
])
def test_bad_sweep_goals_are_refused_with_what_to_change(args, needle):
    with pytest.raises(ScanGoalError, match=needle):
        plan_sweep(*args)

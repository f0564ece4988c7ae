"""Sweep goal checks and frame accounting (lsu_scan.sweep_plan)."""

import pytest

from lsu_scan.scan_plan import ScanGoalError
from lsu_scan.sweep_plan import count_frames, oriented, plan_sweep, scan_mode


def test_mode_defaults_to_stopsnap_and_names_the_choices():
    assert scan_mode("") == "stopsnap" and scan_mode("Sweep") == "sweep"
    with pytest.raises(ScanGoalError, match="stopsnap, sweep"):
        scan_mode("continuous")


def test_full_track_sweep_at_60_steps_per_s_gives_as_many_frames_as_the_default_stop_snap_scan():
    plan = plan_sweep(0, 470, 470, 60.0, 30.0)
    assert plan.duration_s == pytest.approx(470 / 60.0)
    # frames at 0, 1/30, ... up to the end of the motion: 7.83 s * 30 + 1; stop-snap 0..470 step 2 has 236
    assert plan.frames_expected == 236


def test_dropped_frames_are_counted_from_stamps_slots_not_published_plus_frames_not_processed():
    first, period = 1_700_000_000_123_456_789, 33_333_333
    slots = 10
    grid = [first + k * period for k in range(slots)]
    published = [s for k, s in enumerate(grid) if k not in (3, 7)]          # the camera skipped slots 3 and 7
    processed = [s for s in published if s != grid[5]] + [first - period]   # one not processed; one not a frame
    frames = count_frames(first, period, slots, published + [first + 3 * period + period // 2], processed,
                          camera_dropped=2)
    assert (frames.published, frames.processed) == (8, 7)
    assert (frames.not_published, frames.not_processed, frames.dropped) == (2, 1, 3)
    record = plan_sweep(0, 470, 470, 60.0, 30.0).record(frames)
    assert record["frames_dropped"] == 3 and record["frames_dropped_pct"] == pytest.approx(30.0)
    assert record["frames_not_published"] == frames.camera_dropped == 2
    # a stamp a little off the grid (a clock's rounding) is still its slot
    assert count_frames(first, period, slots, [grid[2] + 1000], [grid[2] + 1000]).processed == 1


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


def test_position_at_follows_the_commanded_rate_both_ways_and_holds_at_the_end():
    up = plan_sweep(100, 400, 470, 60.0, 30.0)
    assert [up.position_at(t) for t in (0.0, 0.5, 5.0, 9.0)] == [100, 130, 400, 400]
    down = plan_sweep(400, 100, 470, 60.0, 30.0)
    assert [down.position_at(t) for t in (0.0, 0.5, 5.0, 9.0)] == [400, 370, 100, 100]


@pytest.mark.parametrize("here,start,end", [
    (470, 470, 150),   # at the goal's end (the previous scan ended there): back from there, no move
    (150, 150, 470),   # at the goal's start: as asked
    (300, 150, 470),   # between, nearer the start
    (320, 470, 150),   # between, nearer the end: a move there, then the sweep back
    (0, 150, 470),     # outside the range, before it
    (460, 470, 150),   # outside the range, past it
    (310, 150, 470),   # half way: as asked
])
def test_a_sweep_starts_at_the_end_of_its_range_the_carriage_stands_at_or_is_nearer_to(here, start, end):
    plan = oriented(plan_sweep(150, 470, 470, 60.0, 30.0), here)
    assert (plan.start, plan.end) == (start, end)
    assert plan.direction == ("forward" if end > start else "reverse")
    # the same range, rate and frames either way
    assert plan.frames_expected == 161 and plan.duration_s == pytest.approx(320 / 60.0)
    assert plan.record(None)["direction"] == plan.direction


def test_a_reverse_sweeps_frames_are_counted_and_placed_like_a_forward_ones():
    down = oriented(plan_sweep(100, 400, 470, 60.0, 30.0), 470)
    assert (down.start, down.end, down.frames_expected) == (400, 100, 151)
    assert [down.position_at(k / 30.0) for k in (0, 1, 150)] == [400, 398, 100]
    first, period = 1_000_000_000, 33_333_333
    stamps = [first + k * period for k in range(down.frames_expected)]
    assert count_frames(first, period, down.frames_expected, stamps, stamps).dropped == 0


class _LateMatcher:
    """A matcher whose points come one frame every ``every_s`` (on a fake clock) up to ``frames``, then stop."""

    def __init__(self, every_s: float, frames: int) -> None:
        self.now, self.every_s, self.frames = 0.0, every_s, frames

    def acked(self) -> int:
        return min(self.frames, int(self.now / self.every_s))

    def wait(self, predicate, timeout_s: float) -> bool:  # as ScanCalls._wait, its clock stepped 10 ms a turn
        end = self.now + timeout_s
        while not predicate():
            if self.now >= end:
                return False
            self.now += 0.01
        return True


def test_the_sweep_points_are_awaited_while_they_keep_coming_not_a_fixed_time():
    from lsu_scan.sweep_run import wait_while_progressing

    # a busy host's matcher, a frame every 3 s: a fixed 5 s wait took 1 of the 10 frames; this takes all
    late = _LateMatcher(3.0, 10)
    assert wait_while_progressing(lambda: late.acked() == 10, late.acked, late.wait, 5.0)
    assert late.acked() == 10 and late.now == pytest.approx(30.0, abs=0.05)
    # a matcher that stops after 4 frames: given up 5 s after the 4th
    stalled = _LateMatcher(3.0, 4)
    assert not wait_while_progressing(lambda: stalled.acked() == 10, stalled.acked, stalled.wait, 5.0)
    assert stalled.acked() == 4 and stalled.now == pytest.approx(12.0 + 5.0, abs=0.05)

"""LaserGuard's decisions with the clock passed in: when the laser must go off during a scan, and when not."""

from lsu_scan.laser_guard import LaserGuard, ack_due_at


def lit_guard(pause_s: float = 0.2) -> LaserGuard:
    guard = LaserGuard(pause_s=pause_s)
    guard.start_scan()
    guard.lit_by_scan(True)
    return guard


def test_nothing_fires_before_the_pause_past_a_deadline_and_the_earliest_fires_after():
    guard = lit_guard(0.2)
    guard.due("call", 10.0, "move to 40: no answer from carriage/move_to")
    guard.due("ack", 9.9, "snap 3 not acknowledged by stereo_matcher")
    assert guard.overdue(10.0) is None           # 0.1 s past the ack: still within the pause
    assert guard.overdue(10.0999) is None
    warning = guard.overdue(10.1)                # the ack's deadline + 0.2 s is the earliest
    assert warning == "snap 3 not acknowledged by stereo_matcher 0.2 s after it was due"


def test_an_answer_removes_its_deadline():
    guard = lit_guard()
    guard.due("call", 1.0, "capture: no answer")
    guard.answered("call")
    assert not guard.is_due("call") and guard.overdue(100.0) is None


def test_one_off_at_a_time_and_none_while_the_laser_is_off():
    guard = lit_guard(0.2)
    guard.due("call", 1.0, "capture: no answer")
    warning = guard.overdue(1.3)
    assert warning is not None
    guard.switched_off(warning, wall_time=1700000000.5)
    assert guard.overdue(5.0) is None, "the laser is off: nothing more to switch off"
    assert [p.as_json() for p in guard.pauses] == [{"at": 1700000000.5, "why": warning}]
    assert guard.last_off_wall == 1700000000.5
    # lit again before the next capture while the late answer is still missing and the off not yet answered
    guard.lit_by_scan(True)
    assert guard.overdue(5.0) is None, "an outstanding off request must be answered before another one"
    guard.off_settled()
    assert guard.overdue(5.0) == warning


def test_a_new_scan_forgets_deadlines_pauses_and_an_outstanding_off():
    guard = lit_guard()
    guard.due("ack", 1.0, "snap 0 not acknowledged by stereo_matcher")
    guard.switched_off(guard.overdue(2.0) or "", wall_time=5.0)
    guard.start_scan()
    guard.lit_by_scan(True)
    assert guard.pauses == [] and guard.last_off_wall == 0.0 and not guard.off_pending
    guard.due("call", 3.0, "move to 10: no answer")
    assert guard.overdue(3.25) is not None, "a left-over off from the last scan must not disarm this one"


def test_a_changed_pause_applies_to_the_next_deadline():
    guard = lit_guard(0.2)
    guard.due("call", 1.0, "first")
    guard.pause_s = 0.5
    guard.due("ack", 1.0, "second")
    assert guard.overdue(1.25) == "first 0.2 s after it was due"
    guard.answered("call")
    assert guard.overdue(1.25) is None and guard.overdue(1.5) == "second 0.5 s after it was due"


def test_points_are_due_from_the_capture_or_from_when_its_exposure_was_due_whichever_is_first():
    assert ack_due_at(captured_at=10.05, capture_asked_at=10.0, exposure_s=0.033) == 10.033
    assert ack_due_at(captured_at=10.02, capture_asked_at=10.0, exposure_s=0.033) == 10.02

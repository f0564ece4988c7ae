"""Stream bookkeeping without ROS: frame clock, drop accounting by stamps, buffer stamps, truth history."""


import pytest

from lsu_cameras.stream import (
    DropCounter,
    DropTally,
    LagStats,
    TruthHistory,
    buffer_stamp_s,
    count_drops,
    frame_period_ns,
    frame_seed,
    missing_slots,
    slot_stamp_ns,
)

MS = 1_000_000


def test_frame_clock_is_exact_in_integer_nanoseconds():
    period = frame_period_ns(30.0)
    assert period == 33_333_333
    t0 = 1_764_633_600_123_456_789  # a wall-clock stamp: too large for float seconds to keep every nanosecond
    assert [slot_stamp_ns(t0, period, k) - t0 for k in (0, 1, 3)] == [0, 33_333_333, 99_999_999]
    with pytest.raises(ValueError, match="frame rate must be a finite number > 0 Hz"):
        frame_period_ns(0.0)
    with pytest.raises(ValueError, match="frame rate"):
        frame_period_ns(float("nan"))


def test_a_complete_jittery_stream_drops_nothing():
    period = 33 * MS
    # up to +-8 ms (a quarter period) around each slot: neighbours at most 1.5 periods apart, no slot missing
    offsets = [0, 8, -8, 8, -4, 0]
    stamps = [k * period + o * MS for k, o in enumerate(offsets)]
    assert count_drops(stamps, period) == DropTally(expected=6, published=6, dropped=0)


def test_gaps_count_the_slots_they_skipped():
    period = 10 * MS
    # slots 0 1 . . 4 5 . 7 (2, 3 and 6 missing; 7 a little late)
    stamps = [0, 10 * MS, 40 * MS, 50 * MS, 72 * MS]
    tally = count_drops(stamps, period)
    assert tally == DropTally(expected=8, published=5, dropped=3)
    assert tally.dropped_pct == pytest.approx(37.5)
    assert missing_slots(int(1.5 * period), period) == 0      # at the threshold: jitter, not a drop
    assert missing_slots(int(1.6 * period), period) == 1
    assert missing_slots(-period, period) == missing_slots(0, period) == 0  # repeated/reordered stamps
    assert count_drops([], period) == DropTally(0, 0, 0) and DropTally(0, 0, 0).dropped_pct == 0.0


def test_buffer_stamps_come_from_the_driver_else_from_arrival_minus_latency():
    wall, mono = 1_764_633_600.500, 5_000.250
    # the driver stamped the buffer 30 ms before it arrived (monotonic clock, milliseconds)
    assert buffer_stamp_s((mono - 0.030) * 1000.0, wall, mono, latency_s=0.1) == pytest.approx(wall - 0.030, abs=1e-9)
    assert buffer_stamp_s(0.0, wall, mono, latency_s=0.045) == pytest.approx(wall - 0.045)     # no driver stamp
    assert buffer_stamp_s(33.3, wall, mono, latency_s=0.045) == pytest.approx(wall - 0.045)    # a frame count, not a time
    assert buffer_stamp_s((mono + 1.0) * 1000.0, wall, mono, 0.045) == pytest.approx(wall - 0.045)  # in the future


def test_lag_summary_names_max_and_median():
    lags = LagStats()
    for lag in (0.1, 0.4, 0.2):
        lags.add(lag)
    assert (lags.max_s, lags.median_s) == (pytest.approx(0.4), pytest.approx(0.2))
    assert lags.summary() == "publish lag (publish - stamp) max 0.400 s, median 0.200 s over 3 pairs"
    assert LagStats().max_s == LagStats().median_s == 0.0


def test_truth_history_gives_the_sample_at_or_before_a_time_and_prunes_what_no_lookup_needs():
    history: TruthHistory[str] = TruthHistory()
    assert history.at(5) is None and history.newest is None
    for stamp, name in ((100, "a"), (300, "c"), (200, "b")):  # out of order: kept sorted
        history.add(stamp, name)
    assert [history.at(t) for t in (50, 100, 199, 200, 250, 300, 10_000)] == ["a", "a", "a", "b", "b", "c", "c"]
    assert history.newest == "c"
    history.prune(250)  # lookups from 250 on need "b" (holding at 250) and later
    assert len(history) == 2 and history.at(250) == "b" and history.at(0) == "b"
    history.add(300, "c2")  # a repeated stamp replaces
    assert len(history) == 2 and history.at(300) == "c2"
    assert history.between(200, 300) == ["c2"] and history.between(199, 299) == ["b"] and history.between(300, 900) == []


def test_a_pair_some_reader_did_not_acknowledge_is_dropped_not_published():
    counter = DropCounter(10 * MS)
    for stamp, acknowledged in ((0, True), (10 * MS, False), (20 * MS, True), (40 * MS, True)):
        counter.add(stamp, acknowledged)
    assert counter.tally == DropTally(expected=5, published=3, dropped=2) and counter.unacknowledged == 1


def test_frame_seeds_depend_on_the_seed_and_index_only():
    assert frame_seed(0, 3) == frame_seed(0, 3)
    assert len({frame_seed(s, k) for s in (0, 1) for k in range(50)}) == 100

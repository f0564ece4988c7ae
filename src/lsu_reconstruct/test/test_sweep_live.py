"""A live sweep's frame bookkeeping (lsu_reconstruct.sweep_live), without rclpy.

Truth: an analytic constant-rate motion (position = start + rate * (t - t_start)) sampled as the
driver reports it, and a stream whose slot k is stamped t0 + k / fps.
"""

import numpy as np
import pytest

from lsu_common import stamps
from lsu_reconstruct.matching import LineArrays
from lsu_reconstruct.sweep_live import Exposure, LiveSweep

T0 = 1_700_000_000.0   # the stream's first stamp [s]
FPS = 30.0
EXPOSURE = 0.02
RATE, START = 60.0, 150.0
MOTION_AT = T0 - 0.01  # the carriage starts moving just before the first frame


def key(k: int) -> int:
    return stamps.seconds_to_ns(T0) + k * stamps.seconds_to_ns(1.0 / FPS)


def line(k: int) -> LineArrays:
    return LineArrays(u=np.full(3, float(k)), v=np.arange(3.0))


def true_position(t: float) -> float:
    return START + RATE * max(0.0, t - MOTION_AT)


def test_frames_wait_for_the_track_and_come_out_in_order_at_each_cameras_mid_exposure():
    sweep = LiveSweep(key(0), expected=6)
    sweep.add_carriage(MOTION_AT - 1.2, START - 40, True)  # the move to the start,
    sweep.add_carriage(MOTION_AT - 1.0, START, False)      # and its stop there: not the sweep's end
    offsets = (0.0, 0.05)                               # the right camera 50 ms late
    for k in (2, 0, 1):                                 # pairs and exposures out of order
        sweep.add_pair(key(k), line(k), line(k))
        sweep.add_exposure(key(k), Exposure(offsets[0], offsets[1], EXPOSURE, k))
    assert sweep.ready()[0] == []                      # one sample: no track yet
    # !POS at 40 Hz from the start of the motion up to T0 + 0.115 s: covers frame 0's and 1's mid-exposures
    # (the right camera's of frame 1 at T0 + 0.093 s), not frame 2's right one (T0 + 0.127 s)
    for t in np.arange(MOTION_AT, T0 + 0.12, 0.025):
        sweep.add_carriage(float(t), round(true_position(float(t))), True)
    frames, track = sweep.ready()
    assert [k for k, _f in frames] == [key(0), key(1)] and sweep.waiting == 1
    assert [f.index for _k, f in frames] == [0, 1]
    for k, frame in frames:
        mid_right = stamps.ns_to_seconds(k) + offsets[1] + EXPOSURE / 2
        assert frame.right_start_s - frame.left_start_s == pytest.approx(0.05)
        assert float(track.position_at(mid_right)) == pytest.approx(true_position(mid_right), abs=1.0)
    # the final stop ends the track: frame 2 is placed (at the stop), nothing is handed out twice
    sweep.add_carriage(T0 + 0.12, true_position(T0 + 0.12), True)
    sweep.add_carriage(T0 + 0.13, true_position(T0 + 0.13), False)
    frames, _track = sweep.ready()
    assert [f.index for _k, f in frames] == [2] and sweep.waiting == 0
    sweep.add_pair(key(1), line(1), line(1))
    assert sweep.waiting == 0
    assert sweep.counts == {"no_position": 0, "no_exposure": 0}


def test_a_frame_before_the_motions_first_report_is_placed_at_the_start_with_or_without_older_samples():
    positions = []
    for older in (False, True):  # a live graph may still hold the stop from before the scan; a bag may not
        sweep = LiveSweep(key(0), expected=2, start_position=START)
        if older:
            sweep.add_carriage(T0 - 0.6, START, False)
        sweep.add_pair(key(0), line(0), line(0))
        sweep.add_exposure(key(0), Exposure(0.0, 0.0, EXPOSURE, 0))
        for t in (T0 + 0.05, T0 + 0.10):  # the motion starts after frame 0's exposure
            sweep.add_carriage(t, START + RATE * (t - T0 - 0.05), True)
        frames, track = sweep.ready()
        assert [f.index for _k, f in frames] == [0]
        positions.append(float(track.position_at(T0 + EXPOSURE / 2)))
    assert positions[0] == pytest.approx(positions[1], abs=1e-6) and positions[0] == pytest.approx(START, abs=1e-5)


def test_the_end_bounds_the_sweep_and_finish_counts_what_could_not_be_placed():
    sweep = LiveSweep(key(0), expected=4)
    assert not sweep.is_frame(key(0) - 1)              # the texture pair, before the stream
    for k in range(4):
        sweep.add_pair(key(k), line(k), line(k))
    for k in (0, 1):
        sweep.add_exposure(key(k), Exposure(0.0, 0.0, EXPOSURE, k))
    sweep.end(key(2), published=3)                     # frame 3 came after the stream's last pair: not a frame
    assert not sweep.is_frame(key(3)) and sweep.waiting == 3
    # no carriage report at all (a v1 unit): every frame is placed without a position, frame 2 also without exposure
    frames, track = sweep.finish()
    assert track is None and [f.index for _k, f in frames] == [0, 1, 2]
    assert sweep.counts == {"no_position": 3, "no_exposure": 1}
    assert frames[2][1].exposure_s == EXPOSURE and frames[2][1].left_start_s == stamps.ns_to_seconds(key(2))

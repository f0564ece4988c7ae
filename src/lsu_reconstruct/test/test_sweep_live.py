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


# ---------------------------------------------------------------------------- frames to points (SweepPoints)
# Analytic truth: the renderer's own sheet (its geometry) on a plane 0.3 m away, each camera's line the
# sheet at the true carriage position of its mid-exposure, projected with the true calibration.
@pytest.fixture(scope="module")
def plane_rig(tmp_path_factory):
    from lsu_reconstruct.laser_sheet import LaserSheet
    from lsu_reconstruct.stereo import StereoModel
    from lsu_sim import load_rig, write_true_calibration

    geometry = load_rig()
    folder = tmp_path_factory.mktemp("calib")
    write_true_calibration(geometry, folder)
    n = geometry.laser_normal
    c0 = float(n @ geometry.laser_origin(0.0))
    sheet = LaserSheet(normal=tuple(float(x) for x in n), c0_m=c0, m_per_step=float(n @ geometry.laser_origin(1.0)) - c0,
                       residual_mm=0.0, points=0, rejected=0, positions=(0, int(geometry.track_steps)))
    return StereoModel.from_folder(folder), sheet


def plane_line(model, sheet, side: str, position: float) -> LineArrays:
    n, c = sheet.plane(position)
    y = np.linspace(-0.04, 0.04, 400)
    X = np.column_stack([(c - n[1] * y - n[2] * 0.3) / n[0], y, np.full_like(y, 0.3)])
    uv = model.project_left(X) if side == "left" else model.project_right(X)
    order = np.argsort(uv[:, 1])
    return LineArrays(uv[order, 0], uv[order, 1])


SWEEP_START = 250.0
RIGHT_OFFSET = -0.012  # the right camera 12 ms early: its next exposure follows the left one


def sweep_position(t: float) -> float:
    return SWEEP_START + RATE * max(0.0, t - MOTION_AT)


def plane_frame(model, sheet, k: int) -> tuple[LineArrays, LineArrays, Exposure]:
    t = stamps.ns_to_seconds(key(k))
    left = plane_line(model, sheet, "left", sweep_position(t + EXPOSURE / 2))
    right = plane_line(model, sheet, "right", sweep_position(t + RIGHT_OFFSET + EXPOSURE / 2))
    return left, right, Exposure(0.0, RIGHT_OFFSET, EXPOSURE, k)


def feed_live(model, sheet, n: int, matching: str = "cross_frame"):
    """A live sweep of ``n`` frames, the driver's !POS at 40 Hz arriving with the frames; what comes out when."""
    from lsu_reconstruct.sweep import SweepParams
    from lsu_reconstruct.sweep_live import SweepPoints

    sweep = LiveSweep(key(0), expected=n, start_position=SWEEP_START)
    points = SweepPoints(model, sheet, SweepParams(), matching)
    reports = list(np.arange(MOTION_AT, stamps.ns_to_seconds(key(n)), 0.025))
    out, handed = [], []
    for k in range(n):
        t = stamps.ns_to_seconds(key(k))
        while reports and reports[0] <= t + 0.04:  # the frame's mid-exposures are covered (not always the next's)
            at = float(reports.pop(0))
            sweep.add_carriage(at, sweep_position(at), True)
        left, right, exposure = plane_frame(model, sheet, k)
        sweep.add_pair(key(k), left, right)
        sweep.add_exposure(key(k), exposure)
        frames, track = sweep.ready()
        handed += [f for _key, f in frames]
        out.append(points.add(frames, track))
    end = stamps.ns_to_seconds(key(n - 1)) + 0.05
    sweep.add_carriage(end, sweep_position(end), False)  # the motion's final stop
    sweep.end(key(n - 1), published=n)
    frames, track = sweep.ready()
    handed += [f for _key, f in frames]
    last = points.add(frames, track)
    assert sweep.complete
    return out, last, points.flush(), handed, track, points


def test_cross_frame_points_come_one_frame_later_in_order_and_the_last_with_the_flush(plane_rig):
    model, sheet = plane_rig
    out, last, flushed, handed, _track, points = feed_live(model, sheet, 6)
    # each frame is handed out once the track covers it, and its points once the next right exposure is in
    assert [f.index for f in handed] == list(range(6))
    assert [[(k, i) for k, i, _p in got] for got in out] == [[]] + [[(key(k - 1), k - 1)] for k in range(1, 6)]
    assert last == [] and [(k, i) for k, i, _p in flushed] == [(key(5), 5)] and points.waiting == 0
    for _k, i, p in [got[0] for got in out[1:]] + flushed:
        assert len(p) > 100 and np.all(p.snap == i)
        assert np.max(np.abs(p.xyz[:, 2] - 0.3)) * 1000.0 < 0.05  # on the plane
        if i < 5:  # matched across frames: on the sheet at the left line's true position
            t = stamps.ns_to_seconds(key(i)) + EXPOSURE / 2
            assert np.max(np.abs(sheet.distance_m(p.xyz, np.full(len(p), sweep_position(t))))) * 1000.0 < 0.05
    assert points.flush() == []  # nothing is given twice


def test_live_points_equal_a_recorded_sweeps_on_the_same_frames(plane_rig):
    from lsu_reconstruct.sweep import SOURCE_CROSS_STEREO, reconstruct_sweep, reconstruct_sweep_frame

    model, sheet = plane_rig
    out, last, flushed, handed, track, _points = feed_live(model, sheet, 6)
    live = [p for got in out for _k, _i, p in got] + [p for _k, _i, p in last + flushed]
    whole = reconstruct_sweep(model, sheet, track, handed)
    assert len(live) == len(whole) == 6
    for a, b in zip(live, whole):
        np.testing.assert_array_equal(a.xyz, b.points.xyz)
        np.testing.assert_array_equal(a.u, b.points.u)
    assert all(np.all(r.source == SOURCE_CROSS_STEREO) for r in whole[:5])
    # per_frame: each frame at once, as reconstruct_sweep_frame places it alone
    out, last, flushed, handed, track, _points = feed_live(model, sheet, 6, matching="per_frame")
    assert [[i for _k, i, _p in got] for got in out] == [[k] for k in range(6)] and flushed == []
    for (_k, _i, a), frame in zip([got[0] for got in out], handed):
        np.testing.assert_array_equal(a.xyz, reconstruct_sweep_frame(model, sheet, track, frame).points.xyz)


def test_sweep_points_refuse_an_unknown_matching(plane_rig):
    from lsu_reconstruct.sweep_live import SweepPoints

    model, sheet = plane_rig
    with pytest.raises(ValueError, match="cross_frame, per_frame"):
        SweepPoints(model, sheet, matching="across")


def test_a_frame_that_cannot_be_placed_is_reported_and_costs_no_other(plane_rig):
    from lsu_reconstruct.sweep import CarriageTrack, SweepFrame
    from lsu_reconstruct.sweep_live import SweepPoints

    model, sheet = plane_rig
    t = np.arange(MOTION_AT, stamps.ns_to_seconds(key(6)), 0.025)
    track = CarriageTrack(t, np.array([sweep_position(float(x)) for x in t]), np.ones(len(t), bool))
    points = SweepPoints(model, sheet)

    def frame(k: int, exposure_s: float = EXPOSURE) -> tuple[int, SweepFrame]:
        left, right, _e = plane_frame(model, sheet, k)
        start = stamps.ns_to_seconds(key(k))
        return key(k), SweepFrame(k, left, right, start, start + RIGHT_OFFSET, exposure_s)

    assert [i for _k, i, _p in points.add([frame(0), frame(1)], track)] == [0]
    # frame 2's exposure time is not a number: reported; frame 1, waiting for it, is placed alone
    got = points.add([frame(2, float("nan"))], track)
    assert [i for _k, i, _p in got] == [1] and len(got[0][2]) > 100
    assert [k for k, _m in points.errors] == [key(2), key(2)] and "exposure" in points.errors[1][1]
    # the frames after it are matched across frames again
    assert [i for _k, i, _p in points.add([frame(3), frame(4)], track)] == [3]
    assert [i for _k, i, _p in points.flush()] == [4] and points.waiting == 0

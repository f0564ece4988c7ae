"""Sweep reconstruction (lsu_reconstruct.sweep) against analytic and rendered ground truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lsu_common.arrays import AnyArray
from lsu_extract.extractor import extract_laser_line
from lsu_reconstruct.laser_sheet import LaserSheet
from lsu_reconstruct.matching import LineArrays
from lsu_reconstruct.stereo import StereoModel
from lsu_reconstruct.sweep import (
    SOURCE_CROSS_STEREO,
    SOURCE_LEFT_SHEET,
    SOURCE_RIGHT_SHEET,
    SOURCE_STEREO,
    CarriageTrack,
    SweepError,
    SweepFrame,
    SweepParams,
    SweepSequence,
    exposure_mid_s,
    reconstruct_sweep,
    reconstruct_sweep_frame,
)
from lsu_sim import CarriageState, SimulatedRig, build_scene, load_rig, write_true_calibration

RATE = 60.0  # steps/s: a whole-track sweep at 30 fps gives 235 frames


def true_sheet(geometry) -> LaserSheet:
    """The renderer's own sheet (its geometry), as a LaserSheet."""
    n = geometry.laser_normal
    c0 = float(n @ geometry.laser_origin(0.0))
    k = float(n @ geometry.laser_origin(1.0)) - c0
    return LaserSheet(normal=tuple(float(x) for x in n), c0_m=c0, m_per_step=k, residual_mm=0.0, points=0,
                      rejected=0, positions=(0, int(geometry.track_steps)))


def driver_track(duration_s: float, rate_hz: float = 20.0, start: float = 0.0, velocity: float = RATE) -> CarriageTrack:
    """What the driver publishes during a sweep: the integer step counter every 1/rate_hz s, and the stop."""
    stamps = np.r_[np.arange(0.0, duration_s, 1.0 / rate_hz), duration_s]
    return CarriageTrack(stamps, np.rint(start + velocity * stamps))


def lines(image: AnyArray) -> LineArrays:
    res = extract_laser_line(image)
    return LineArrays(res.u, res.v, res.peak, res.width, res.quality, image.shape[1], image.shape[0])


def surface_distance_mm(objects, xyz: AnyArray) -> AnyArray:
    """Distance to the rendered meshes themselves (open3d): the renderer's geometry, not the code under test."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    for obj in objects:
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(obj.mesh))
    return scene.compute_distance(o3d.core.Tensor(np.asarray(xyz, np.float32))).numpy().astype(np.float64) * 1000.0


@pytest.fixture(scope="module")
def rig_model(tmp_path_factory):
    geometry = load_rig()
    folder = tmp_path_factory.mktemp("calib")
    write_true_calibration(geometry, folder)
    return geometry, StereoModel.from_folder(folder)


def test_carriage_position_at_exposure_mid_from_stamped_counter():
    track = driver_track(4.0)
    for start in (0.013, 1.2345, 3.9):
        mid = exposure_mid_s(start, 0.02)
        assert mid == pytest.approx(start + 0.01)
        # the counter is an integer sampled at 20 Hz: interpolation is within half a step of the true motion
        assert abs(float(track.position_at(mid)) - RATE * mid) <= 0.5
    # after the stop (the last sample) the carriage stays there; before the first sample and after a
    # sample still moving, the rate goes on for a short while, then the position is unknown
    assert float(track.position_at(4.5)) == 240.0
    assert float(track.position_at(-0.05)) == pytest.approx(-3.0) and np.isnan(track.position_at(-0.5))
    running = CarriageTrack(track.stamps_s[:-1], track.positions_steps[:-1], moving=np.ones(len(track.stamps_s) - 1))
    assert float(running.position_at(3.95 + 0.05)) == pytest.approx(237.0 + 3.0, abs=0.6)
    assert np.isnan(running.position_at(4.5))
    with pytest.raises(SweepError, match="at least 2"):
        CarriageTrack(np.array([0.0]), np.array([1.0]))
    with pytest.raises(SweepError, match="duration"):
        exposure_mid_s(0.0, -1.0)


def test_moving_line_is_the_sheet_at_mid_exposure(rig_model):
    """The rendered motion-blurred line lies where a still sheet at the mid-exposure position puts it."""
    geometry, _model = rig_model
    rig = SimulatedRig(geometry, build_scene("plane", geometry, distance_m=0.30), seed=3)
    exposure = geometry.sensor.exposure_s
    moving = rig.render(CarriageState(200.0, True, velocity_steps_per_s=180.0, position_time_s=0.0),
                        capture_time_s=0.0, seed=5)
    assert moving.laser_offsets_steps[0] == pytest.approx(180.0 * exposure / 2.0)
    mid = rig.render(200.0 + 180.0 * exposure / 2.0, seed=5)
    start = rig.render(200.0, seed=5)
    lm, lmid, lstart = lines(moving.left), lines(mid.left), lines(start.left)
    rows = np.intersect1d(np.intersect1d(lm.v, lmid.v), lstart.v)
    assert len(rows) > 300

    def at(line: LineArrays) -> AnyArray:
        return line.u[np.searchsorted(line.v, rows)]

    off_mid = np.median(np.abs(at(lm) - at(lmid)))
    off_start = np.median(np.abs(at(lm) - at(lstart)))
    # 1.8 steps of travel during the exposure move the line ~1.5 px; half of it at mid-exposure
    assert off_start > 0.5
    assert off_mid < 0.1 * off_start


def render_sweep(geometry, objects, offset_s: float, jitter_s: float, frames, seed: int = 1, start: float = 0.0,
                 velocity: float = RATE):
    """Frames ``frames`` of a sweep from ``start`` at ``velocity`` steps/s (negative: towards 0), 30 fps."""
    rig = SimulatedRig(geometry, objects, seed=seed)
    rig.set_capture_timing(offset_s, jitter_s)
    out = []
    for index in frames:
        t = index / 30.0
        frame = rig.render(CarriageState(start, True, velocity_steps_per_s=velocity, position_time_s=0.0),
                           capture_time_s=t, seed=seed + index)
        out.append(SweepFrame(index, lines(frame.left), lines(frame.right), float(frame.exposure_start_s[0]),
                              float(frame.exposure_start_s[1]), geometry.sensor.exposure_s))
    return out


def test_sweep_with_50ms_discrepancy_on_rendered_frames(rig_model):
    """Each camera's line on the sheet at its own mid-exposure: both lines land on the rendered sphere."""
    geometry, model = rig_model
    objects = build_scene("sphere", geometry)
    frames = render_sweep(geometry, objects, offset_s=0.05, jitter_s=0.003, frames=range(100, 136, 5))
    sheet, track = true_sheet(geometry), driver_track(7.9)
    errors, sources = [], []
    for frame in frames:
        assert frame.overlap == 0.0  # 50 ms apart, 20 ms exposures: no stereo
        out = reconstruct_sweep_frame(model, sheet, track, frame)
        errors.append(surface_distance_mm(objects, out.points.xyz))
        sources.append(out.source)
        # the two cameras saw the sheet 3 steps apart: two different lines of the surface
        assert out.positions_steps[1] - out.positions_steps[0] == pytest.approx(RATE * 0.05, abs=1.0)
    err, src = np.concatenate(errors), np.concatenate(sources)
    assert np.count_nonzero(src == SOURCE_LEFT_SHEET) > 1000 and np.count_nonzero(src == SOURCE_RIGHT_SHEET) > 1000
    assert np.sqrt(np.mean(err ** 2)) < 0.25
    # the same lines placed at the frame's nominal time (the left camera's) miss the surface by far more
    nominal = CarriageTrack(track.stamps_s + 0.05, track.positions_steps)  # right line at the left's time
    naive_right = [reconstruct_sweep_frame(model, sheet, nominal, f) for f in frames]
    wrong = np.concatenate([surface_distance_mm(objects, o.points.xyz[o.source == SOURCE_RIGHT_SHEET])
                            for o in naive_right])
    assert np.sqrt(np.mean(wrong ** 2)) > 3.0 * np.sqrt(np.mean(err ** 2))


def test_synchronised_sweep_uses_stereo_and_the_sheet_check_rejects_a_wrong_position(rig_model):
    geometry, model = rig_model
    objects = build_scene("sphere", geometry)
    frames = render_sweep(geometry, objects, offset_s=0.0, jitter_s=0.0, frames=(110, 120))
    sheet, track = true_sheet(geometry), driver_track(7.9)
    for frame in frames:
        out = reconstruct_sweep_frame(model, sheet, track, frame)
        assert np.all(out.source == SOURCE_STEREO) and len(out.points) > 300
        assert out.stats["stereo_rejected_inconsistent"] < 0.02 * len(out.points)
        err = surface_distance_mm(objects, out.points.xyz)
        assert np.sqrt(np.mean(err ** 2)) < 0.2
        # a carriage track 4 steps off (1.7 mm of sheet): the stereo points no longer agree with it
        off = CarriageTrack(track.stamps_s, track.positions_steps + 4.0)
        bad = reconstruct_sweep_frame(model, sheet, off, frame, SweepParams(consistency_mm=0.5))
        assert bad.stats["stereo_rejected_inconsistent"] > 0.9 * len(out.points)


def test_the_sim_rigs_laser_yaml_is_its_true_sheet():
    """config/calibration/sim/laser.yaml (fitted on rendered flat targets) against the rig's own geometry."""
    from lsu_reconstruct.laser_sheet import read_laser_yaml

    geometry = load_rig()
    sheet = read_laser_yaml(Path(__file__).resolve().parents[3] / "config" / "calibration" / "sim" / "laser.yaml")
    angle = np.degrees(np.arccos(min(1.0, abs(float(np.asarray(sheet.normal) @ geometry.laser_normal)))))
    assert angle < 0.01
    for p in (0.0, 235.0, 470.0):
        n, c = sheet.plane(p)
        probe = geometry.laser_origin(p) + 0.3 * geometry.rig_axes[2]  # on the true sheet, at the subject
        assert abs(float(n @ probe) - c) * 1000.0 < 0.01


def test_params_refuse_nonsense():
    with pytest.raises(SweepError, match="consistency_mm"):
        SweepParams(consistency_mm=0.0)
    with pytest.raises(SweepError, match="min_overlap"):
        SweepParams(min_overlap=1.5)


@pytest.fixture(scope="module")
def head_sweep_50ms(rig_model):
    """16 consecutive frames over the rendered head (carriage 248..278), the right camera 50 ms late."""
    geometry, model = rig_model
    objects = build_scene("head:7", geometry)
    frames = render_sweep(geometry, objects, offset_s=0.05, jitter_s=0.005, frames=range(124, 140), seed=7)
    return geometry, model, objects, frames


def test_50ms_sweep_matched_across_frames_lies_on_the_rendered_head(head_sweep_50ms):
    """Each left line against the right lines exposed around it: as accurate as stop-snap, unlike the sheet."""
    geometry, model, objects, frames = head_sweep_50ms
    sheet, track = true_sheet(geometry), driver_track(7.9)
    results = reconstruct_sweep(model, sheet, track, frames)
    assert [r.points.snap[0] for r in results if len(r.points)] == [f.index for f in frames if len(f.left)]
    # from the third frame on, a right exposure lies on either side of every left one (-17 ms, +17 ms);
    # the first two have both right ones after them: extrapolated, still matched across frames
    assert [r.stats["cross_extrapolated"] for r in results] == [1, 1] + [0] * (len(results) - 2)
    assert all(np.all(r.source == SOURCE_CROSS_STEREO) and len(r.points) > 150 for r in results)
    cross = results[2:]
    err = np.concatenate([surface_distance_mm(objects, r.points.xyz) for r in cross])
    rms = float(np.sqrt(np.mean(err ** 2)))
    # frame by frame (each camera's line on the sheet: rays 10-25 deg to the sheet, the skin's glow
    # shifted off the sheet) the same lines miss the skin by about twice as much
    per_frame = [reconstruct_sweep_frame(model, sheet, track, f) for f in frames[2:]]
    err_sheet = np.concatenate([surface_distance_mm(objects, r.points.xyz) for r in per_frame])
    rms_sheet = float(np.sqrt(np.mean(err_sheet ** 2)))
    assert rms < 0.17 < rms_sheet
    # each point keeps its own left pixel (the raw extracted one; the point is on the row-smoothed line)
    for r in cross:
        uv = model.project_left(r.points.xyz)
        assert np.median(np.hypot(uv[:, 0] - r.points.u, uv[:, 1] - r.points.v)) < 0.3


def test_the_first_frames_extrapolated_across_frames_ignore_a_common_clock_error(head_sweep_50ms):
    """The sweep's first two left lines have no right exposure before them. The driver's carriage stamps can
    be off by the device clock mapping's error (half a round trip on a busy host: 15 ms here, about one step
    at 60 steps/s), the same for both cameras: stereo against the two right lines after them cancels it,
    the sheet alone turns it into depth."""
    geometry, model, objects, frames = head_sweep_50ms
    sheet, exact = true_sheet(geometry), driver_track(7.9)

    def rms(results) -> float:
        return float(np.sqrt(np.mean(np.concatenate([surface_distance_mm(objects, r.points.xyz) for r in results]) ** 2)))

    for clock_error_s in (0.0, 0.015, -0.015):
        track = CarriageTrack(exact.stamps_s + clock_error_s, exact.positions_steps, exact.moving)
        first = reconstruct_sweep(model, sheet, track, frames)[:2]
        assert all(r.stats["cross_extrapolated"] == 1 and np.all(r.source == SOURCE_CROSS_STEREO) for r in first)
        sheet_only = [reconstruct_sweep_frame(model, sheet, track, f) for f in frames[:2]]
        # measured: 0.33-0.36 mm extrapolated at every clock error; the sheet 0.37 mm exact, 1.2-1.7 mm off
        assert rms(first) < 0.45
        if clock_error_s:
            assert rms(sheet_only) > 1.0


def test_sweep_sequence_gives_each_frame_once_the_next_right_exposure_is_in(head_sweep_50ms):
    geometry, model, _objects, frames = head_sweep_50ms
    sheet, track = true_sheet(geometry), driver_track(7.9)
    sequence = SweepSequence(model, sheet)
    out = []
    for k, frame in enumerate(frames):
        got = sequence.add(frame, track)
        # the right camera is 50 ms late: a frame's own right exposure already follows its left one, and
        # from the third frame on one precedes it; the first two wait for two right exposures after them
        want = [] if k == 0 else [frames[0].index, frame.index] if k == 1 else [frame.index]
        assert [r.points.snap[0] for r in got if len(r.points)] == want
        out.extend(got)
    assert sequence.finish(track) == []
    whole = reconstruct_sweep(model, sheet, track, frames)
    for a, b in zip(out, whole):
        np.testing.assert_array_equal(a.points.xyz, b.points.xyz)
    # synchronised cameras: the frame's own pair, at one carriage position, matched as in stop-snap
    early = SweepSequence(model, sheet)
    first = frames[5]
    sync = SweepFrame(first.index, first.left, first.left, first.left_start_s, first.left_start_s, first.exposure_s)
    assert len(early.add(sync, track)) == 0  # no right exposure after its left one yet
    done = early.finish(track)
    assert len(done) == 1 and done[0].positions_steps[0] == done[0].positions_steps[1]


def _plane_line(model: StereoModel, sheet: LaserSheet, side: str, position: float, z_m: float) -> LineArrays:
    """The sheet at ``position`` on the plane z = ``z_m`` as one camera's line (projected, < 1 px apart)."""
    n, c = sheet.plane(position)
    y = np.linspace(-0.04, 0.04, 400)
    x = (c - n[1] * y - n[2] * z_m) / n[0]
    X = np.column_stack([x, y, np.full_like(y, z_m)])
    uv = model.project_left(X) if side == "left" else model.project_right(X)
    order = np.argsort(uv[:, 1])
    return LineArrays(uv[order, 0], uv[order, 1])


def test_cross_frame_interpolation_puts_the_left_line_on_the_sheet_and_rejects_a_depth_edge(rig_model):
    """Analytic lines on a plane: the right lines at 249 and 251 steps, the left at 250 between them."""
    geometry, model = rig_model
    sheet = true_sheet(geometry)
    track = CarriageTrack(np.array([0.0, 10.0]), np.array([0.0, 10.0 * RATE]))
    exposure = 0.02

    def frame(index: int, p_left: float, p_right: float, right_z: float = 0.3) -> SweepFrame:
        return SweepFrame(index, _plane_line(model, sheet, "left", p_left, 0.3),
                          _plane_line(model, sheet, "right", p_right, right_z),
                          p_left / RATE - exposure / 2, p_right / RATE - exposure / 2, exposure)

    out = reconstruct_sweep(model, sheet, track, [frame(0, 248.0, 249.0), frame(1, 250.0, 251.0)])[1]
    assert np.all(out.source == SOURCE_CROSS_STEREO) and len(out.points) > 100
    xyz = out.points.xyz
    assert np.max(np.abs(xyz[:, 2] - 0.3)) * 1000.0 < 0.005
    assert np.max(np.abs(sheet.distance_m(xyz, np.full(len(xyz), 250.0)))) * 1000.0 < 0.005
    # the right line just after the left exposure lies on a nearer surface (a depth edge between the
    # two exposures): its crossings are tens of pixels away, no point is interpolated across it
    edge = reconstruct_sweep(model, sheet, track, [frame(0, 248.0, 249.0), frame(1, 250.0, 251.0, right_z=0.27)])[1]
    assert len(edge.points) == 0 and edge.stats["cross_rejected_jump"] > 100


# ---------------------------------------------------------------- the reverse direction (end -> start)
REVERSE_START = 470.0  # a sweep back from the end of the track, e.g. after a scan that ended there


def test_a_reverse_carriage_track_interpolates_and_extrapolates_downwards():
    track = driver_track(4.0, start=REVERSE_START, velocity=-RATE)
    for start in (0.013, 1.2345, 3.9):
        mid = exposure_mid_s(start, 0.02)
        assert abs(float(track.position_at(mid)) - (REVERSE_START - RATE * mid)) <= 0.5
    assert float(track.position_at(4.5)) == REVERSE_START - 240.0  # stopped at the end of the motion
    assert float(track.position_at(-0.05)) == pytest.approx(REVERSE_START + 3.0)  # the rate continued backwards
    running = CarriageTrack(track.stamps_s[:-1], track.positions_steps[:-1], moving=np.ones(len(track.stamps_s) - 1))
    assert float(running.position_at(4.0)) == pytest.approx(REVERSE_START - 240.0, abs=0.6)


def test_reverse_cross_frame_interpolation_puts_the_left_line_on_the_sheet(rig_model):
    """Analytic lines on a plane, carriage running down: the right lines at 251 and 249, the left at 250."""
    geometry, model = rig_model
    sheet = true_sheet(geometry)
    track = CarriageTrack(np.array([0.0, 10.0]), np.array([REVERSE_START, REVERSE_START - 10.0 * RATE]))
    exposure = 0.02

    def frame(index: int, p_left: float, p_right: float) -> SweepFrame:
        t_left, t_right = (REVERSE_START - p_left) / RATE, (REVERSE_START - p_right) / RATE
        return SweepFrame(index, _plane_line(model, sheet, "left", p_left, 0.3),
                          _plane_line(model, sheet, "right", p_right, 0.3),
                          t_left - exposure / 2, t_right - exposure / 2, exposure)

    out = reconstruct_sweep(model, sheet, track, [frame(0, 252.0, 251.0), frame(1, 250.0, 249.0)])
    assert [r.positions_steps[0] for r in out] == pytest.approx([252.0, 250.0])
    # the second left line (250) lies between the right lines exposed before (251) and after (249) it
    second = out[1]
    assert np.all(second.source == SOURCE_CROSS_STEREO) and len(second.points) > 100
    xyz = second.points.xyz
    assert np.max(np.abs(xyz[:, 2] - 0.3)) * 1000.0 < 0.005
    assert np.max(np.abs(sheet.distance_m(xyz, np.full(len(xyz), 250.0)))) * 1000.0 < 0.005


def test_a_reverse_50ms_sweep_lies_on_the_rendered_head_like_a_forward_one(rig_model):
    """Carriage 470 -> 0 at 60 steps/s over the head (frames at 280..250 steps), right camera 50 ms late:
    each left line matched across frames lands on the rendered head as in the forward sweep."""
    geometry, model = rig_model
    objects = build_scene("head:7", geometry)
    frames = render_sweep(geometry, objects, offset_s=0.05, jitter_s=0.005, frames=range(95, 111), seed=7,
                          start=REVERSE_START, velocity=-RATE)
    sheet, track = true_sheet(geometry), driver_track(7.9, start=REVERSE_START, velocity=-RATE)
    results = reconstruct_sweep(model, sheet, track, frames)
    assert [r.points.snap[0] for r in results if len(r.points)] == [f.index for f in frames if len(f.left)]
    # each frame placed where the carriage was at its left camera's mid-exposure (the driver's integer counter
    # at 20 Hz: within half a step), decreasing frame by frame
    lefts = np.array([r.positions_steps[0] for r in results])
    truth = np.array([REVERSE_START - RATE * exposure_mid_s(f.left_start_s, f.exposure_s) for f in frames])
    assert np.max(np.abs(lefts - truth)) <= 0.5 and np.all(np.diff(lefts) < 0)
    cross = results[2:]
    assert all(np.all(r.source == SOURCE_CROSS_STEREO) and len(r.points) > 150 for r in cross)
    err = np.concatenate([surface_distance_mm(objects, r.points.xyz) for r in cross])
    assert float(np.sqrt(np.mean(err ** 2))) < 0.17

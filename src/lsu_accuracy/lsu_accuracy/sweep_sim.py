"""Sweep and stop-snap scans of a simulated scene, rendered and reconstructed without ROS (pure).

`sweep_scene` renders what a constant-rate sweep gives: the carriage runs from ``start`` to ``end``
at ``rate_steps_s`` while both cameras free-run at ``fps``, each frame exposed from its camera's own
start (the rig's ``capture_offset_s`` / ``capture_jitter_s``), with the sheet moving during the
exposure; the carriage positions come stamped as the driver publishes them (`!POS` at
``position_rate_hz``), and `lsu_reconstruct.sweep` turns the frames into points (`render_sweep` renders and
extracts once, `reconstruct_rendered` reconstructs those lines across frames or frame by frame). `stopsnap_scene`
renders the same scene stop-snap (settled after each move, the emulator's residual vibration after
the settle time), through the same extractor and matcher: the reference of the sweep's accuracy.

The simulated rig's laser sheet (``config/calibration/sim/laser.yaml``) is calibrated as in a lab,
by `lsu calibrate --laser` on scans of flat boards (`lsu_reconstruct.laser_cli`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from lsu_common.arrays import AnyArray

if TYPE_CHECKING:
    from lsu_reconstruct.sweep import CarriageTrack, SweepFrame

__all__ = ["SweepScan", "RenderedSweep", "render_sweep", "reconstruct_rendered", "sweep_scene", "stopsnap_scene",
           "sweep_frame_count"]

# the emulator's post-stop vibration (lsu_driver.emulator.EmulatorConfig defaults, at 200 steps/s)
VIBRATION_AMPLITUDE_STEPS = 0.6
VIBRATION_TAU_S = 0.040
VIBRATION_FREQ_HZ = 22.0


@dataclass
class SweepScan:
    """A reconstructed scan: points (left frame, m), lines (frames or snaps with points), per-source counts."""

    xyz: AnyArray
    lines: int
    frames: int
    seconds: float                      # simulated carriage time of the scan [s]
    stats: dict[str, int] = field(default_factory=dict)
    checked_xyz: AnyArray | None = None  # stop-snap with a sheet: the points that pass the sweep's sheet check
    snap_after_stop_s: AnyArray | None = None  # stop-snap: each snap's exposure start after its stop [s]
    captures: int = 0                   # stop-snap: frames rendered (an adaptive settle's probes included)


def sweep_frame_count(start: int, end: int, rate_steps_s: float, fps: float) -> int:
    """Frames a free-running camera takes while the carriage sweeps ``start``..``end`` at ``rate_steps_s``."""
    return int(np.floor(abs(end - start) / rate_steps_s * fps)) + 1


def _lines(image: AnyArray):
    from lsu_extract.extractor import extract_laser_line
    from lsu_reconstruct.matching import LineArrays

    res = extract_laser_line(image)
    return LineArrays(res.u, res.v, res.peak, res.width, res.quality, image.shape[1], image.shape[0])


@dataclass
class RenderedSweep:
    """The extracted lines of a rendered sweep, every frame with each camera's exposure start, and the track."""

    frames: list[SweepFrame]
    track: CarriageTrack
    seconds: float
    # a living subject (``motion``): per frame, the true pose (rotation vector [rad], displacement [m] about the
    # motion's pivot, `lsu_sim.motion.SubjectPose`) at the left camera's mid-exposure, and the images
    poses: AnyArray | None = None
    images: list[tuple[AnyArray, AnyArray]] | None = None


def render_sweep(geometry, objects: Sequence, rate_steps_s: float, fps: float = 30.0, start: int = 0,
                 end: int = 470, offset_s: float = 0.0, jitter_s: float = 0.0, position_rate_hz: float = 20.0,
                 seed: int = 0, frames: int | None = None, motion=None, motion_t0_s: float = 0.0,
                 keep_images: bool = False, rig=None, motion_hz: float = 15.0) -> RenderedSweep:
    """Render a sweep (module doc) and extract both lines of every frame; ``frames`` limits the count (tests).

    ``motion``: a `lsu_sim.motion.SubjectMotion`; every frame is rendered with the subject at its pose at
    ``motion_t0_s`` + the left camera's mid-exposure, updated at ``motion_hz`` (a new pose re-casts the whole
    image, the costly part of a frame; sway moves < 0.5 mm in 1/15 s), its ``poses`` hold the pose each
    frame was rendered at. ``keep_images``: keep every
    frame's pair (the motion estimate reads their texture). ``rig``: a rig of these objects to reuse.
    """
    from lsu_reconstruct.sweep import CarriageTrack, SweepFrame
    from lsu_sim import CarriageState, SimulatedRig

    rig = rig if rig is not None else SimulatedRig(geometry, objects, seed=seed)
    rig.set_capture_timing(offset_s, jitter_s)
    poses: list[AnyArray] = []
    images: list[tuple[AnyArray, AnyArray]] = []
    direction = 1.0 if end >= start else -1.0
    duration = abs(end - start) / rate_steps_s
    # the driver's stamped positions: the counter at every 1/R s from the start, and the stop
    stamps = np.r_[np.arange(0.0, duration, 1.0 / position_rate_hz), duration]
    track = CarriageTrack(stamps, np.rint(start + direction * rate_steps_s * stamps))
    count = sweep_frame_count(start, end, rate_steps_s, fps) if frames is None else int(frames)
    exposure = geometry.sensor.exposure_s
    out: list[SweepFrame] = []
    for index in range(count):
        t = index / fps  # the left camera's nominal exposure start; the rig draws each camera's jitter
        state = CarriageState(float(start), True, velocity_steps_per_s=direction * rate_steps_s, position_time_s=0.0)
        if t + exposure > duration:  # the carriage stopped at the end: the last frames see it there
            state = CarriageState(float(end), True)
        if motion is not None:
            if index % max(1, int(round(fps / motion_hz))) == 0:
                pose = motion.pose(motion_t0_s + t + 0.5 * exposure)
                rig.set_subject_pose(pose.R, pose.translation)
            poses.append(pose.as_vector())
        frame = rig.render(state, capture_time_s=t, seed=seed + index)
        assert frame.exposure_start_s[0] is not None and frame.exposure_start_s[1] is not None  # given capture_time_s
        out.append(SweepFrame(index, _lines(frame.left), _lines(frame.right), float(frame.exposure_start_s[0]),
                              float(frame.exposure_start_s[1]), exposure))
        if keep_images:
            images.append((frame.left, frame.right))
    return RenderedSweep(out, track, duration, np.array(poses) if motion is not None else None,
                         images if keep_images else None)


def reconstruct_rendered(model, sheet, rendered: RenderedSweep, params=None, cross_frame: bool = True) -> SweepScan:
    """Points of a rendered sweep: across frames (`lsu_reconstruct.sweep.reconstruct_sweep`) or frame by frame."""
    from lsu_reconstruct.sweep import SweepParams, reconstruct_sweep, reconstruct_sweep_frame

    params = params or SweepParams()
    if cross_frame:
        results = reconstruct_sweep(model, sheet, rendered.track, rendered.frames, params)
    else:
        results = [reconstruct_sweep_frame(model, sheet, rendered.track, f, params) for f in rendered.frames]
    xyz: list[AnyArray] = []
    stats: dict[str, int] = {}
    lines = 0
    for out in results:
        for key, value in out.stats.items():
            stats[key] = stats.get(key, 0) + int(value)
        if len(out.points):
            xyz.append(out.points.xyz)
            lines += int(len(np.unique(out.source)))
    return SweepScan(np.concatenate(xyz) if xyz else np.zeros((0, 3)), lines, len(rendered.frames), rendered.seconds,
                     stats)


def sweep_scene(model, sheet, geometry, objects: Sequence, rate_steps_s: float, fps: float = 30.0,
                start: int = 0, end: int = 470, offset_s: float = 0.0, jitter_s: float = 0.0,
                position_rate_hz: float = 20.0, seed: int = 0, params=None,
                frames: int | None = None, cross_frame: bool = True) -> SweepScan:
    """Render and reconstruct a sweep (module doc); ``frames`` limits the count (tests)."""
    rendered = render_sweep(geometry, objects, rate_steps_s, fps, start, end, offset_s, jitter_s, position_rate_hz,
                            seed, frames)
    return reconstruct_rendered(model, sheet, rendered, params, cross_frame)


def stopsnap_scene(model, geometry, objects: Sequence, start: int = 0, end: int = 470, step: int = 2,
                   settle_s: float = 0.1, seed: int = 0, params=None, sheet=None, capture=None,
                   max_view_angle_deg: float | None = None) -> SweepScan:
    """Render and reconstruct a stop-snap scan of the same scene (settled ``settle_s`` after each stop).

    With ``sheet``, ``checked_xyz`` also holds the stop-snap points that pass the sweep's check against
    the sheet at the snap's position (what the sweep's stereo path keeps), for a like-for-like comparison.
    ``capture(rig, state, index)`` -> (the snap's StereoFrame, its exposure start after the stop [s], frames
    rendered) takes the snap instead of the fixed settle's render at ``settle_s`` (an adaptive settle: lsu_scan's
    tests and bench_scan compose it with `lsu_scan.settle`). The cloud is what the matcher node publishes:
    the snaps' points without those seen at a grazing angle (`lsu_reconstruct.pipeline.drop_grazing`,
    ``max_view_angle_deg``, default the node's).
    """
    from lsu_reconstruct.matching import MatchParams
    from lsu_reconstruct.pipeline import MAX_VIEW_ANGLE_DEG, drop_grazing, merge_snaps, reconstruct_snap
    from lsu_reconstruct.sweep import CarriageTrack, SweepFrame, SweepParams, reconstruct_sweep_frame
    from lsu_sim import CarriageState, SimulatedRig

    rig = SimulatedRig(geometry, objects, seed=seed)
    snaps = []
    checked: list[AnyArray] = []
    after_stop: list[float] = []
    captures = 0
    positions = list(range(start, end + 1, step))
    for index, position in enumerate(positions):
        state = CarriageState(float(position), True, stopped_at_s=0.0,
                              vibration_amplitude_steps=VIBRATION_AMPLITUDE_STEPS, vibration_tau_s=VIBRATION_TAU_S,
                              vibration_freq_hz=VIBRATION_FREQ_HZ)
        if capture is None:
            frame, t_snap, rendered = rig.render(state, capture_time_s=settle_s, seed=seed + index), settle_s, 1
        else:
            frame, t_snap, rendered = capture(rig, state, index)
        after_stop.append(float(t_snap))
        captures += int(rendered)
        left, right = _lines(frame.left), _lines(frame.right)
        snap = reconstruct_snap(model, left, right, params or MatchParams(), snap=index)
        if len(snap):
            snaps.append(snap)
        if sheet is not None:
            at_rest = CarriageTrack(np.array([0.0, 1.0]), np.array([float(position)] * 2), moving=np.zeros(2, bool))
            out = reconstruct_sweep_frame(model, sheet, at_rest, SweepFrame(index, left, right, 0.0, 0.0, 0.02),
                                          SweepParams(match=params or MatchParams()))
            checked.append(out.points.xyz)
    cloud = drop_grazing(merge_snaps(snaps), model,
                         MAX_VIEW_ANGLE_DEG if max_view_angle_deg is None else float(max_view_angle_deg))
    points = np.asarray(cloud.xyz)
    return SweepScan(points, len(snaps), len(positions), 0.0,
                     {"stereo": int(len(points)), "rejected_grazing": int(cloud.stats.get("rejected_grazing", 0))},
                     np.concatenate(checked) if checked else (np.zeros((0, 3)) if sheet is not None else None),
                     np.asarray(after_stop), captures)

"""The simulated rig as a camera source of the ``stereo_camera`` node (entry point ``lsu.camera_sources``: ``sim``).

`SimSource` renders the pair of a capture time from where the carriage is then; `carriage_from_truth` turns
the GP32 emulator's ``sim/truth`` samples (lsu_interfaces/SimTruth, read by the node) into that
`CarriageState`; `open_sim_source` builds both from the node's ``sim_*`` parameters. Pure module (no rclpy).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

from lsu_cameras.sources import CameraError, SourceContext, StereoPair, StereoSource
from lsu_cameras.stream import frame_seed
from lsu_common import stamps
from lsu_common.stamps import ns_to_seconds, seconds_to_ns

from .rig import CarriageState, SimulatedRig

# a simulated pair of a stream is rendered this long after its exposures ended [s]: the emulator publishes its
# exact samples of a motion's start or stop from its executor, on a busy host tens of ms after they happened,
# and a pair rendered before they are in shows the carriage where it was not
TRUTH_DELAY_S = 0.1
# a moving subject's pose is updated at this rate by default: a new pose re-casts both views (~0.5-2 s of CPU for a
# person on a small host), cast by a thread of its own while the slot before it renders; a camera whose frames
# reach the next slot before it is ready waits for it (its frames keep their slots' stamps); sway moves < 1 mm in
# 1/5 s. `lsu_accuracy.sweep_sim.render_sweep` (no ROS) uses 15 Hz.
MOTION_HZ = 5.0


class SimSource(StereoSource):
    """The simulated rig; ``carriage(t_ns)`` says where the carriage is at time t_ns (integer ns: from
    /lsu/sim/truth or a parameter)."""

    stamps_on_node_clock = True  # the capture time is the node's clock
    render_delay_s = TRUTH_DELAY_S

    def __init__(self, rig: SimulatedRig, carriage: Callable[[int], CarriageState],
                 clock: Callable[[], float] = time.time, seed: int = 0, motion: Any = None,
                 motion_hz: float = MOTION_HZ) -> None:
        self.rig = rig
        self.carriage = carriage
        self.clock = clock
        self.seed = int(seed)
        # a living subject (`lsu_sim.motion.SubjectMotion`): its clock starts at the first frame rendered
        self.motion = motion
        self.motion_hz = float(motion_hz)
        self._motion_t0: float | None = None
        self._motion_slot: int | None = None
        self._render_lock = threading.Lock()  # a pose holds for the whole render of a pair
        # the next slot's pose, cast beside the renders of the current one: (slot, its future)
        self._next_pose: tuple[int, Future] | None = None
        self._caster: ThreadPoolExecutor | None = None
        if motion is not None:
            # the first slot's pose cast now (a pose costs a re-cast of the views, ~0.5 s of CPU): the scan's first
            # frames come on time instead of waiting for it
            pose = motion.pose(0.0)
            rig.set_subject_pose(pose.R, pose.translation)
            self._motion_slot = 0
            self._caster = ThreadPoolExecutor(1, thread_name_prefix="lsu-sim-pose")
            self._cast_ahead(1)

    @property
    def image_size(self) -> tuple[int, int]:
        return self.rig.geometry.image_size

    @property
    def exposure_s(self) -> float:
        return self.rig.geometry.sensor.exposure_s

    @property
    def ready_after_s(self) -> float:
        sensor = self.rig.geometry.sensor
        # the later camera's exposure end (jitter: 3 sigma), as a real frame would arrive
        return max(sensor.capture_offset_s, 0.0) + 3.0 * sensor.capture_jitter_s + sensor.exposure_s

    def _pair(self, t_ns: int, seed: int | None, parallel: bool | None = None) -> StereoPair:
        t = ns_to_seconds(t_ns)
        carriage = self.carriage(t_ns)
        with self._render_lock:
            self._place_subject(t)
            # both exposures start at t unless the rig models a capture discrepancy (capture_offset_s/_jitter_s);
            # the carriage is looked up by the exact stamp (float seconds of a wall-clock time are 256 ns coarse)
            frame = self.rig.render(carriage, capture_time_s=t, seed=seed, parallel=parallel)
        left_start, right_start = frame.exposure_start_s
        assert left_start is not None and right_start is not None  # a capture time gives both starts
        return StereoPair(frame.left, frame.right, t, right_start - left_start, left_offset_s=left_start - t)

    def _place_subject(self, t_s: float) -> None:
        """The moving subject at its pose of the frame exposed from ``t_s`` (mid-exposure, in ``motion_hz`` slots)."""
        if self.motion is None:
            return
        if self._motion_t0 is None:
            self._motion_t0 = t_s
        slot = math.floor((t_s - self._motion_t0 + 0.5 * self.exposure_s) * self.motion_hz)
        if slot != self._motion_slot:
            ahead = self._next_pose
            if ahead is not None and ahead[0] == slot:
                prepared = ahead[1].result()  # cast meanwhile, or waited for: the frame is of its slot's pose
            else:
                if ahead is not None:
                    ahead[1].cancel()
                pose = self.motion.pose(slot / self.motion_hz)
                prepared = self.rig.prepare_subject_pose(pose.R, pose.translation)
            self.rig.apply_subject_pose(prepared)
            self._motion_slot = slot
            self._cast_ahead(slot + 1)

    def _cast_ahead(self, slot: int) -> None:
        """The pose of ``slot`` cast by the caster thread (the rig's caches of the current pose are not touched)."""
        if self._caster is None or self.motion is None:
            return
        pose = self.motion.pose(slot / self.motion_hz)
        self._next_pose = (slot, self._caster.submit(self.rig.prepare_subject_pose, pose.R, pose.translation))

    def pair_at(self, stamp_ns: int, index: int) -> StereoPair:
        """The pair exposed from ``stamp_ns`` with the carriage as known then; its noise (and start jitter)
        seeded by the sim seed and ``index`` (`frame_seed`).

        Rendered on the calling thread only: a stream renders on its own thread beside the publishing
        one and the rest of the graph, where the rig's second render thread costs CPU and gains no frames;
        a single capture (`grab_pair`) keeps the rig's default for its latency.
        """
        return self._pair(stamp_ns, frame_seed(self.seed, index), parallel=False)

    def close(self) -> None:
        """The caster thread let go (a pose it is casting is not waited for)."""
        if self._caster is not None:
            self._caster.shutdown(wait=False, cancel_futures=True)
            self._caster = None
            self._next_pose = None

    def grab_pair(self, timeout_s: float = 2.0) -> StereoPair:
        started = time.monotonic()
        pair = self._pair(seconds_to_ns(self.clock()), None)
        # a real frame is not there before its exposure has ended: a render faster than the
        # exposure must not make a simulated scan faster than the unit could be
        remaining = self.rig.geometry.sensor.exposure_s - (time.monotonic() - started)
        if remaining > 0:
            time.sleep(remaining)
        return pair


def carriage_from_truth(truth: Any, later: Sequence[Any], fallback: CarriageState) -> CarriageState:
    """The carriage during a pair exposed from the stamp ``truth`` held at: ``truth`` is the SimTruth sample that
    held then (None: none received yet, ``fallback`` is used), ``later`` the samples after it up to the end of the
    pair's exposures (a motion starting or stopping while they last)."""
    if truth is None:
        return fallback
    later = list(later)
    stamp = stamps.to_seconds(truth.header.stamp)
    start = next((s for s in later if s.moving and s.velocity_steps_per_s != 0.0), None)
    if (not truth.moving or truth.velocity_steps_per_s == 0.0) and start is not None:
        # at rest at t, moving before the later camera's exposure ends: rest until the start's sample
        truth, stamp, later = start, stamps.to_seconds(start.header.stamp), later[later.index(start) + 1:]
        started: float | None = stamp
    else:
        started = None
    if truth.moving:
        # the carriage keeps going between samples: the renderer follows it through each camera's
        # own exposure (motion blur) from the sample's position and time, up to a stop in that time
        stop = next((s for s in later if not s.moving), None)
        if stop is None:
            return CarriageState(truth.position_steps, truth.laser_on,
                                 velocity_steps_per_s=truth.velocity_steps_per_s, position_time_s=stamp,
                                 motion_start_s=started)
        return CarriageState(truth.position_steps, truth.laser_on, velocity_steps_per_s=truth.velocity_steps_per_s,
                             position_time_s=stamp, motion_start_s=started,
                             motion_stop_s=stamps.to_seconds(stop.stopped_at) or stamps.to_seconds(stop.header.stamp),
                             vibration_amplitude_steps=stop.vibration_amplitude_steps,
                             vibration_tau_s=stop.vibration_tau_s, vibration_freq_hz=stop.vibration_freq_hz)
    stopped = stamps.to_seconds(truth.stopped_at)
    return CarriageState(truth.position_steps, truth.laser_on, stopped if stopped > 0 else None,
                         truth.vibration_amplitude_steps, truth.vibration_tau_s, truth.vibration_freq_hz)


def open_sim_source(context: SourceContext) -> SimSource:
    """The node's ``sim`` source from its parameters ``sim_rig``, ``sim_scene``, ``sim_seed``, ``sim_motion``
    (``sim_motion_seed``, ``sim_motion_turn_at_s``, ``sim_motion_hz``) and, until ``sim/truth`` arrives, ``carriage_position_steps``
    and ``laser_on``."""
    from . import build_scene, load_rig
    from .motion import MotionError, scene_motion

    param = context.parameter
    geometry = load_rig(str(param("sim_rig")) or None)
    scene = build_scene(str(param("sim_scene")), geometry)
    seed = int(param("sim_seed"))

    def carriage(t_ns: int) -> CarriageState:
        truth, later = context.truth_at(t_ns)
        fallback = CarriageState(float(param("carriage_position_steps")), bool(param("laser_on")))
        return carriage_from_truth(truth, later, fallback)

    def optional(name: str, default: Any) -> Any:
        # the motion settings are the camera node's; a caller with only the scene's parameters gets a still subject
        try:
            value = param(name)
        except LookupError:
            return default
        return default if value is None else value

    kind = str(optional("sim_motion", "") or "still")
    try:
        motion = None if kind == "still" else scene_motion(kind, int(optional("sim_motion_seed", 0)), geometry, scene,
                                                           float(optional("sim_motion_turn_at_s", 1.0)))
    except MotionError as exc:
        raise CameraError(f"sim_motion: {exc}") from None
    # the shadow cache: a person at 60 fps on a small host (its few pixels at shadow edges: `SimulatedRig`)
    rig = SimulatedRig(geometry, scene, seed=seed, shadow_cache=True)
    # before the camera offers its capture service: a camera respawned mid-session answers a scan's first snap
    # within the coordinator's capture timeout on a loaded host too (the first render's caches took longer)
    rig.prepare()
    return SimSource(rig, carriage, clock=context.clock, seed=seed, motion=motion,
                     motion_hz=float(optional("sim_motion_hz", 5.0)))


__all__ = ["SimSource", "carriage_from_truth", "open_sim_source", "TRUTH_DELAY_S"]

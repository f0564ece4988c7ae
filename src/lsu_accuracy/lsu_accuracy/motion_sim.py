"""Sweeps of a living subject, rendered, reconstructed, measured and corrected without ROS (pure).

`motion_scan` renders a sweep of a person (`sweep_sim.render_sweep`) with the subject moving as
`lsu_sim.motion` says (``still``, ``seated``, ``standing``, ``turn``), reconstructs it across frames
(`lsu_reconstruct.sweep`), measures the motion from the frames' texture and corrects the points
(`lsu_reconstruct.motion`). Its accuracy figures are against the true moving surface: the delivered cloud
(raw or corrected) is in the subject's pose at the reference frame (the middle one), and its distance is
taken to the person's meshes at that true pose (`MotionScan.rms_mm`).

`face_sweeps`: the face signatures of a person's sweeps as `lsu face enroll`/`identify` make them
(`lsu_faces.pipeline.process_cloud`): an enrolment from a still sweep, probes from a second still sweep and from a
moving one (raw and corrected), for identification on moving subjects.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from lsu_common.arrays import AnyArray

__all__ = ["MotionScan", "motion_scan", "face_range_steps", "FaceSweeps", "face_sweeps", "FACE_PROBES"]

# the probes of `face_sweeps`: a second still sweep, the moving one as reconstructed and as corrected
FACE_PROBES = ("still", "moving_raw", "moving_corrected")
# `face_sweeps`' margin around the face's landmarks: the nose finder needs the cheeks and brow around the nose (the
# landmarks' own range, 4 mm, leaves it no face to find)
FACE_SWEEP_MARGIN_M = 0.02


@dataclass
class MotionScan:
    """A rendered sweep of a moving subject, its measured motion and both clouds."""

    raw_xyz: AnyArray            # as reconstructed (each line at its own frame's pose)
    corrected_xyz: AnyArray      # moved back to the reference frame's pose
    point_frame: AnyArray        # (N,) frame index of every point
    point_reliable: AnyArray     # (N,) bool: its frame's motion was measured reliably
    true_poses: AnyArray         # (F,6) the subject's true pose per frame (lsu_sim.motion.SubjectPose.as_vector)
    pivot: AnyArray
    estimate: object             # lsu_reconstruct.motion.MotionEstimate
    record: dict                 # lsu_reconstruct.motion.motion_record
    frames: int
    seconds: float
    # ``live``: the cloud and motion record as the live graph's matcher makes them (`lsu_reconstruct.motion.SweepMotion`:
    # every Nth frame's images handed over as the frames are placed, corrected only within limits)
    live_xyz: AnyArray | None = None
    live_record: dict | None = None

    def rms_mm(self, objects: Sequence, corrected: bool = True, reliable_only: bool = False) -> float:
        """RMS distance [mm] of the cloud to the subject's true surface at the reference frame's pose."""
        xyz = self.corrected_xyz if corrected else self.raw_xyz
        if reliable_only:
            xyz = xyz[self.point_reliable]
        return self._rms_mm(objects, xyz, int(self.estimate.reference_frame))  # type: ignore[attr-defined]

    def live_rms_mm(self, objects: Sequence) -> float:
        """`rms_mm` of the live graph's cloud (``live``), at its own reference frame's true pose."""
        assert self.live_xyz is not None and self.live_record is not None, "motion_scan(live=True) makes it"
        return self._rms_mm(objects, self.live_xyz, int(self.live_record.get("reference_frame", 0)))

    def _rms_mm(self, objects: Sequence, xyz: AnyArray, reference_frame: int) -> float:
        from lsu_accuracy.accuracy import surface_rms_mm
        from lsu_sim.motion import SubjectPose

        reference = self.true_poses[reference_frame]
        return surface_rms_mm(objects, SubjectPose.from_vector(reference, self.pivot).inverse_apply(xyz))

    def pose_errors_mm(self) -> list[float]:
        """Per measured frame, the distance [mm] between the measured and the true displacement of the fitted
        points' centre relative to the reference frame (the truth: the poses the frames were rendered at)."""
        from lsu_sim.motion import SubjectPose

        est: Any = self.estimate
        ref = SubjectPose.from_vector(self.true_poses[est.reference_frame], self.pivot)
        centre = est.centre[None]
        return [float(np.linalg.norm(SubjectPose.from_vector(self.true_poses[f], self.pivot)
                                     .apply(ref.inverse_apply(centre))[0] - est.centre - est.vectors[k, 3:]) * 1e3)
                for k, f in enumerate(est.frames)]


def face_range_steps(geometry, objects: Sequence, margin_m: float = 0.004) -> tuple[int, int]:
    """Carriage positions whose sheet crosses the face (the skin's true landmarks, widened by ``margin_m``)."""
    marks = next((o.extra["landmarks_m"] for o in objects if "landmarks_m" in o.extra), None)
    if not marks:
        raise ValueError("face_range_steps needs a person scene (its skin carries the true landmarks)")
    pts = np.array(list(marks.values()), dtype=np.float64)
    steps = np.arange(0, geometry.track_steps + 1) if hasattr(geometry, "track_steps") else np.arange(0, 471)
    side = []
    for p in steps:
        n, c = geometry.laser_plane(float(p))
        side.append((float(np.min(pts @ n - c)), float(np.max(pts @ n - c))))
    inside = [int(p) for p, (lo, hi) in zip(steps, side) if lo - margin_m <= 0.0 <= hi + margin_m]
    return min(inside), max(inside)


def motion_scan(model, sheet, geometry, objects: Sequence, kind: str, seed: int = 0, rate_steps_s: float = 57.1,
                fps: float = 30.0, start: int | None = None, end: int | None = None, params=None,
                turn_at_s: float | None = None, correct: bool = True, live: bool = False) -> MotionScan:
    """Render, reconstruct, measure and correct a sweep of ``objects`` moving as ``kind`` (module doc).

    ``start``/``end`` default to the face's range (`face_range_steps`); ``turn_at_s`` (``turn``): when the head
    turns, default a third into the sweep. ``live``: also the live graph's cloud and record (`MotionScan.live_xyz`).
    """
    from lsu_reconstruct.motion import MotionParams, SweepMotion, estimate_motion, motion_record
    from lsu_reconstruct.sweep import SweepParams, exposure_mid_s, reconstruct_sweep
    from lsu_sim.motion import scene_motion

    from .sweep_sim import render_sweep

    if start is None or end is None:
        lo, hi = face_range_steps(geometry, objects)
        start, end = (lo if start is None else start), (hi if end is None else end)
    duration = abs(end - start) / rate_steps_s
    motion = scene_motion(kind, seed, geometry, objects, duration / 3 if turn_at_s is None else turn_at_s)
    rendered = render_sweep(geometry, objects, rate_steps_s, fps, start, end, seed=seed, motion=motion,
                            keep_images=True)
    results = reconstruct_sweep(model, sheet, rendered.track, rendered.frames, SweepParams())
    times = np.array([exposure_mid_s(f.left_start_s, f.exposure_s) for f in rendered.frames])
    xyz = [r.points.xyz for r in results]
    frame_of = np.concatenate([np.full(len(x), k) for k, x in enumerate(xyz)]).astype(np.int64)
    raw = np.concatenate(xyz) if xyz else np.zeros((0, 3))
    assert rendered.images is not None and rendered.poses is not None  # keep_images, motion given
    estimate = estimate_motion(model, rendered.images, times, [(f.left, f.right) for f in rendered.frames], raw,
                               params or MotionParams(seed=seed))
    corrected = estimate.correct(raw, times[frame_of]) if correct else raw.copy()
    positions = [float(rendered.track.position_at(t)) for t in times]
    scan = MotionScan(raw, corrected, frame_of, estimate.reliable_at(times[frame_of]), rendered.poses, motion.pivot,
                      estimate, motion_record(estimate, positions, corrected=correct), len(rendered.frames),
                      rendered.seconds)
    if live:
        sweep = SweepMotion.for_sweep(len(rendered.frames), params or MotionParams(seed=seed))
        for k, frame in enumerate(rendered.frames):
            sweep.add_frame(k, times[k], frame.left, frame.right, rendered.images[k] if sweep.wants(k) else None,
                            positions[k])
        scan.live_xyz, scan.live_record = sweep.correct(model, raw, frame_of, apply=correct)
    return scan


@dataclass
class FaceSweeps:
    """A person's face signatures (`lsu_faces.signature.Signature`, None where the pipeline found no face) from
    sweeps: ``enrolment`` (a still sweep) and ``probes`` by `FACE_PROBES`; ``messages`` the pipeline's words for
    each, ``flagged`` whether the moving sweep was flagged beyond correction."""

    enrolment: Any
    probes: dict[str, Any]
    messages: dict[str, list[str]]
    flagged: bool
    points: dict[str, int]


def face_sweeps(model, sheet, geometry, objects: Sequence, kind: str = "standing", enrol_seed: int = 0,
                probe_seed: int = 1, rate_steps_s: float = 57.1, still_probe: bool = True,
                moving_probe: bool = True) -> FaceSweeps:
    """Sweeps over the face of ``objects`` (`face_range_steps`, `FACE_SWEEP_MARGIN_M`): a still one with
    ``enrol_seed`` (render noise) for the enrolment, then with ``probe_seed`` a still one (``still_probe``) and one
    moving as ``kind`` (``moving_probe``; motion seed ``probe_seed``), each cloud taken through the face pipeline
    `lsu face` uses. A probe not asked for is absent from ``probes``."""
    from lsu_faces.pipeline import ProcessParams, process_cloud

    def signature(xyz: AnyArray, name: str) -> Any:
        result = process_cloud({c: xyz[:, k] for k, c in enumerate("xyz")}, ProcessParams())
        messages[name], points[name] = result.messages, len(xyz)
        return result.signature

    def still_sweep(seed: int) -> AnyArray:
        # the same render and reconstruction as `motion_scan`'s, without the motion measurement (images kept,
        # dense flows) that a still subject does not need
        from .sweep_sim import reconstruct_rendered, render_sweep

        return reconstruct_rendered(model, sheet, render_sweep(geometry, objects, rate_steps_s, 30.0, lo, hi,
                                                               seed=seed)).xyz

    messages: dict[str, list[str]] = {}
    points: dict[str, int] = {}
    lo, hi = face_range_steps(geometry, objects, FACE_SWEEP_MARGIN_M)
    enrolment = signature(still_sweep(enrol_seed), "enrolment")
    probes: dict[str, Any] = {}
    if still_probe:
        probes["still"] = signature(still_sweep(probe_seed), "still")
    flagged = False
    if moving_probe:
        moving = motion_scan(model, sheet, geometry, objects, kind, seed=probe_seed, rate_steps_s=rate_steps_s,
                             start=lo, end=hi)
        probes["moving_raw"] = signature(moving.raw_xyz, "moving_raw")
        probes["moving_corrected"] = signature(moving.corrected_xyz, "moving_corrected")
        flagged = bool(moving.estimate.flagged)  # type: ignore[attr-defined]
    return FaceSweeps(enrolment, probes, messages, flagged, points)

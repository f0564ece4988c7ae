"""A sweep's frames in the live graph (numpy, no rclpy): which pairs are sweep frames, when each can be placed.

The matcher node feeds a `LiveSweep` what arrives, in any order: the pairs of laser lines (keyed on
the pair's stamp, integer ns), each pair's exposure (`/lsu/stereo/exposure`: each camera's start
offset from the stamp and the exposure time), the driver's stamped carriage positions
(`/lsu/driver/carriage`) and the sweep's end (SWEEP_END: the stamp of the stream's last pair).
`ready` hands back the frames that can be reconstructed now, in stamp order, as `SweepFrame`s with
the `CarriageTrack` of the sweep:

- a pair is a sweep frame when its stamp is >= the stream's first stamp (SWEEP_START) and, once the
  end is known, <= the last one;
- a frame waits for its exposure and for both of its cameras' mid-exposures to be covered by the
  track (a carriage sample at or after it, or the sweep motion's final stop reported), so that it is
  placed the same whatever the order its inputs come in (live or replayed);
- `finish` (the scan ended) releases what still waits: a frame without a position is counted as
  "no position" (`reconstruct_sweep_frame` then gives its stereo points only), one without its
  exposure as "no exposure" (placed at the pair's stamp with the last known exposure time).

A frame's index is the stream's ``frame_index`` of its exposure (its slot: the same in the live graph
and in a replay, whatever order the messages come in).

`SweepPoints` turns the frames `ready` / `finish` hand out into points: by default across frames
(`SweepSequence`: each left line matched to the right lines exposed around it), so a frame's points
may come one frame later than the frame, and `flush` (the sweep's last frame is out, or the scan
ended) gives the rest; ``per_frame`` places each frame alone (`reconstruct_sweep_frame`). Since a
frame is handed out only once the track covers both its mid-exposures, every right line a left one
is matched to is placed by interpolation between the same carriage samples as in a recorded sweep:
the points equal `reconstruct_sweep`'s on the same frames, whatever order the inputs came in.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lsu_common import stamps

from .laser_sheet import LaserSheet
from .matching import LineArrays
from .pipeline import SnapPoints, reconstruct_snap
from .stereo import CalibrationError, StereoModel
from .sweep import (
    CarriageTrack,
    SweepFrame,
    SweepFramePoints,
    SweepParams,
    SweepSequence,
    exposure_mid_s,
    reconstruct_sweep_frame,
)

__all__ = ["Exposure", "LiveSweep", "SweepPoints", "SWEEP_MATCHING", "CARRIAGE_LOOKBACK_S"]

SWEEP_MATCHING = ("cross_frame", "per_frame")  # `SweepPoints`: the first is the default

# carriage samples kept from before the stream's first frame: the stop at the sweep's start (the
# driver's first !POS is at the start of the motion, and the stream may start before it)
CARRIAGE_LOOKBACK_S = 2.0


@dataclass(frozen=True)
class Exposure:
    """One pair's exposure: each camera's start relative to the pair's stamp, and the exposure time [s]."""

    left_offset_s: float
    right_offset_s: float
    exposure_s: float
    frame_index: int


@dataclass
class LiveSweep:
    """Bookkeeping of one sweep's frames (module doc). Stamps are integer ns keys."""

    first_key: int
    expected: int = 0
    # where the carriage stands until the motion's first report (SWEEP_START's position): frames before
    # it are placed there whatever samples from before the scan a live graph still holds and a bag lacks
    start_position: float | None = None
    last_key: int | None = None
    published: int | None = None
    pairs: dict[int, tuple[LineArrays, LineArrays]] = field(default_factory=dict)
    exposures: dict[int, Exposure] = field(default_factory=dict)
    carriage: list[tuple[float, float, bool]] = field(default_factory=list)  # (stamp s, position, moving)
    done: set[int] = field(default_factory=set)       # frames handed out by `ready` / `finish`
    counts: dict[str, int] = field(default_factory=lambda: {"no_position": 0, "no_exposure": 0})
    # the samples and track as of the key (first_key, start_position, len(carriage)): `ready` runs at every
    # line, the carriage samples change at 20 Hz; `carriage` is only ever appended to (`add_carriage`)
    _track_cache: tuple[tuple, list, CarriageTrack | None] | None = field(default=None, repr=False, compare=False)

    def is_frame(self, key: int) -> bool:
        """The pair stamped ``key`` belongs to this sweep."""
        return key >= self.first_key and (self.last_key is None or key <= self.last_key)

    def add_pair(self, key: int, left: LineArrays, right: LineArrays) -> None:
        if self.is_frame(key) and key not in self.done:
            self.pairs[key] = (left, right)

    def add_exposure(self, key: int, exposure: Exposure) -> None:
        if self.is_frame(key):
            self.exposures[key] = exposure

    def add_carriage(self, stamp_s: float, position_steps: float, moving: bool) -> None:
        self.carriage.append((float(stamp_s), float(position_steps), bool(moving)))

    def end(self, last_key: int, published: int) -> None:
        """SWEEP_END: the stream's last pair and how many it published; later pairs are not sweep frames."""
        self.last_key, self.published = int(last_key), int(published)
        for key in [k for k in self.pairs if k > last_key]:
            del self.pairs[key]

    # ------------------------------------------------------------------ the carriage track
    def _cached(self) -> tuple[list[tuple[float, float, bool]], CarriageTrack | None]:
        key = (self.first_key, self.start_position, len(self.carriage))
        if self._track_cache is None or self._track_cache[0] != key:
            since = stamps.ns_to_seconds(self.first_key) - CARRIAGE_LOOKBACK_S
            seed = [] if self.start_position is None else [(since, float(self.start_position), False)]
            samples = sorted(seed + [s for s in self.carriage if s[0] > since])
            track = None
            if len({s[0] for s in samples}) >= 2:
                arr = np.asarray([(t, p) for t, p, _m in samples], dtype=np.float64)
                track = CarriageTrack(arr[:, 0], arr[:, 1], np.asarray([m for _t, _p, m in samples], dtype=bool))
            self._track_cache = (key, samples, track)
        return self._track_cache[1], self._track_cache[2]

    def _samples(self) -> list[tuple[float, float, bool]]:
        return self._cached()[0]

    def track_end_s(self) -> float | None:
        """Stamp of the sweep motion's final stop, None while it runs.

        The first stop reported after the stream's first stamp: the stream starts once the carriage
        stands at the sweep's start (the stop of the move there is earlier), and the sweep's motion
        is still running at its first frame.
        """
        first_s = stamps.ns_to_seconds(self.first_key)
        for t, _p, moving in self._samples():
            if not moving and t > first_s:
                return t
        return None

    def track(self) -> CarriageTrack | None:
        """The sweep's carriage track so far (None with fewer than 2 samples)."""
        return self._cached()[1]

    # ------------------------------------------------------------------ frames out
    def _frame(self, key: int, exposure: Exposure) -> SweepFrame:
        left, right = self.pairs[key]
        t = stamps.ns_to_seconds(key)
        return SweepFrame(exposure.frame_index, left, right, t + exposure.left_offset_s, t + exposure.right_offset_s,
                          exposure.exposure_s)

    def _mid_exposures(self, key: int, exposure: Exposure) -> float:
        t = stamps.ns_to_seconds(key)
        return max(exposure_mid_s(t + exposure.left_offset_s, exposure.exposure_s),
                   exposure_mid_s(t + exposure.right_offset_s, exposure.exposure_s))

    def ready(self) -> tuple[list[tuple[int, SweepFrame]], CarriageTrack | None]:
        """Frames whose pair, exposure and carriage positions are in, in stamp order, with the track to use."""
        track = self.track()
        if track is None:
            return [], None
        covered_until = float(track.stamps_s[-1])
        ended = self.track_end_s() is not None
        out = []
        for key in sorted(self.pairs):
            exposure = self.exposures.get(key)
            if exposure is None:
                continue
            if not ended and self._mid_exposures(key, exposure) > covered_until:
                break  # later frames are later still: they wait too
            out.append((key, self._frame(key, exposure)))
        for key, frame in out:
            self._count_position(frame, track)
            self._take(key)
        return out, track

    def finish(self) -> tuple[list[tuple[int, SweepFrame]], CarriageTrack | None]:
        """Every frame still waiting (the scan ended), placed as well as the data allows; counted (module doc)."""
        ready, track = self.ready()
        last_exposure = max(self.exposures.values(), key=lambda e: e.frame_index, default=None)
        out = list(ready)
        for key in sorted(self.pairs):
            exposure = self.exposures.get(key)
            if exposure is None:
                self.counts["no_exposure"] += 1
                exposure = Exposure(0.0, 0.0, last_exposure.exposure_s if last_exposure else 0.0,
                                    self._index_by_order(key))
            out.append((key, self._frame(key, exposure)))
        for key, frame in out[len(ready):]:
            self._count_position(frame, track)
            self._take(key)
        return out, track

    def _count_position(self, frame: SweepFrame, track: CarriageTrack | None) -> None:
        mids = np.asarray([exposure_mid_s(frame.left_start_s, frame.exposure_s),
                           exposure_mid_s(frame.right_start_s, frame.exposure_s)])
        if track is None or not np.isfinite(track.position_at(mids)).all():
            self.counts["no_position"] += 1

    def _index_by_order(self, key: int) -> int:
        """A frame without its exposure: its place among the sweep's stamps seen so far."""
        return sum(1 for k in (*self.done, *self.pairs) if k < key)

    def _take(self, key: int) -> None:
        self.pairs.pop(key, None)
        self.done.add(key)

    @property
    def complete(self) -> bool:
        """The sweep's end is known and its last frame (or as many frames as the stream published) is out."""
        return self.last_key is not None and (self.last_key in self.done or len(self.done) >= (self.published or 0))

    @property
    def waiting(self) -> int:
        """Frames received but not handed out yet."""
        return len(self.pairs)


class SweepPoints:
    """A sweep's frames (as `LiveSweep` hands them out) to points, across frames or frame by frame (module doc).

    Without a laser sheet, or for frames handed out without a track (no carriage report at all),
    each frame is matched stereo only (`reconstruct_snap`). A frame that cannot be reconstructed is
    reported in `errors` (pair stamp, message) and the frames waiting with it are placed frame by
    frame, so one bad frame costs no other.
    """

    def __init__(self, model: StereoModel, sheet: LaserSheet | None, params: SweepParams | None = None,
                 matching: str = SWEEP_MATCHING[0]) -> None:
        if matching not in SWEEP_MATCHING:
            raise ValueError(f"sweep matching '{matching}' is not one of {', '.join(SWEEP_MATCHING)}")
        self.model, self.sheet, self.matching = model, sheet, matching
        self.params = params if params is not None else SweepParams()
        self._sequence = self._new_sequence()
        self._in_sequence: dict[int, tuple[int, SweepFrame]] = {}  # frame index -> (pair stamp, frame), waiting
        self._track: CarriageTrack | None = None
        self.errors: list[tuple[int, str]] = []

    def _new_sequence(self) -> SweepSequence | None:
        if self.sheet is None or self.matching != "cross_frame":
            return None
        return SweepSequence(self.model, self.sheet, self.params)

    def use_params(self, params: SweepParams) -> None:
        """New settings (the matcher's parameters were set): for every frame reconstructed from now on."""
        self.params = params
        if self._sequence is not None:
            self._sequence.params = params

    @property
    def waiting(self) -> int:
        """Frames taken whose points are not out yet."""
        return len(self._in_sequence)

    def add(self, frames: list[tuple[int, SweepFrame]],
            track: CarriageTrack | None) -> list[tuple[int, int, SnapPoints]]:
        """Frames in stamp order with the track they were placed on; (pair stamp, index, points) of those done."""
        out: list[tuple[int, int, SnapPoints]] = []
        if track is not None:
            self._track = track
        for key, frame in frames:
            if self._sequence is None or track is None:
                out.extend(self._alone(key, frame, track))
                continue
            self._in_sequence[frame.index] = (key, frame)
            try:
                done = self._sequence.add(frame, track)
            except (CalibrationError, ValueError) as exc:
                out.extend(self._recover(key, exc))
                continue
            out.extend(self._taken(done))
        return out

    def flush(self) -> list[tuple[int, int, SnapPoints]]:
        """The points of every frame still waiting for a later one (the sweep's frames are all in)."""
        if self._sequence is None or self._track is None or not self._in_sequence:
            return []
        try:
            return self._taken(self._sequence.finish(self._track))
        except (CalibrationError, ValueError) as exc:
            return self._recover(next(iter(self._in_sequence.values()))[0], exc)

    def _taken(self, done: list[SweepFramePoints]) -> list[tuple[int, int, SnapPoints]]:
        """The sequence's results, one per frame in the order the frames were added: each to its pair stamp.

        A result with points names its frame (``snap``); one without is the earliest frame waiting that
        no other result names (the frames come out in capture order).
        """
        named = {int(r.points.snap[0]) for r in done if len(r.points)}
        unnamed = iter([i for i in self._in_sequence if i not in named])
        out = []
        for result in done:
            index = int(result.points.snap[0]) if len(result.points) else next(unnamed)
            key, _frame = self._in_sequence.pop(index)
            out.append((key, index, result.points))
        return out

    def _alone(self, key: int, frame: SweepFrame, track: CarriageTrack | None) -> list[tuple[int, int, SnapPoints]]:
        try:
            if self.sheet is not None and track is not None:
                points = reconstruct_sweep_frame(self.model, self.sheet, track, frame, self.params).points
            else:
                points = reconstruct_snap(self.model, frame.left, frame.right, self.params.match, snap=frame.index)
        except (CalibrationError, ValueError) as exc:
            self.errors.append((key, str(exc)))
            return []
        return [(key, frame.index, points)]

    def _recover(self, key: int, exc: Exception) -> list[tuple[int, int, SnapPoints]]:
        """The sequence failed (at ``key``): report it, place its waiting frames alone, start a new one."""
        self.errors.append((key, f"across frames: {exc}; the frames waiting are placed frame by frame"))
        waiting = sorted(self._in_sequence.values(), key=lambda kf: kf[0])
        self._in_sequence.clear()
        self._sequence = self._new_sequence()
        out = []
        for k, frame in waiting:
            out.extend(self._alone(k, frame, self._track))
        return out

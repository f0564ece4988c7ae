"""Free-running stereo capture, the parts without ROS: the frame clock, drop accounting by stamps,
device buffer stamps, the publish lag and the carriage-truth history a clocked source renders from.

Stamps are integer nanoseconds (`lsu_common.stamps`): a stream's stamps are compared for equality
(the extractor and matcher pair images by exact stamp), which float seconds cannot promise.

Two kinds of source stream (`lsu_cameras.sources`):

- *clocked* (sim, folder): frame k is made to order for its slot ``t_k = t0 + k * period``; a slow
  source publishes late but never skips a slot (the frame's content is fixed by its stamp);
- *free-running* (v4l2): the devices expose at their own rate and each pair carries the drivers'
  buffer stamps; a slot without a pair shows as a gap between stamps and is counted as dropped.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Generic, TypeVar

import numpy as np

from lsu_common.stamps import NS_PER_S

#: A gap between consecutive stamps longer than this many periods means frames are missing.
GAP_PERIODS = 1.5

T = TypeVar("T")


def frame_period_ns(rate_hz: float) -> int:
    """The frame period of ``rate_hz`` in whole nanoseconds (the stream's stamps are exact multiples of it)."""
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"frame rate must be a finite number > 0 Hz, got {rate_hz}")
    return max(1, round(NS_PER_S / rate_hz))


def slot_stamp_ns(t0_ns: int, period_ns: int, index: int) -> int:
    """Stamp of frame slot ``index`` of a stream starting at ``t0_ns``: ``t0 + index * period``."""
    return int(t0_ns) + int(index) * int(period_ns)


def frame_seed(seed: int, index: int) -> int:
    """Noise seed of frame ``index`` of a simulated stream: a function of the sim seed and the index only,
    so the same seed and the same carriage truth give the same frames in any process."""
    return int(np.random.SeedSequence([int(seed), int(index)]).generate_state(1)[0])


def missing_slots(gap_ns: int, period_ns: int) -> int:
    """Frame slots missing between two consecutive stamps ``gap_ns`` apart.

    A gap up to `GAP_PERIODS` periods is one period plus the drivers' stamp jitter: nothing missing.
    A longer one held ``round(gap / period) - 1`` unpublished slots. A gap <= 0 (a repeated or
    reordered stamp) misses nothing.
    """
    if gap_ns <= GAP_PERIODS * period_ns:
        return 0
    return max(0, round(gap_ns / period_ns) - 1)


@dataclass(frozen=True)
class DropTally:
    """Frame slots of a stream: ``expected`` = ``published`` + ``dropped``."""

    expected: int
    published: int
    dropped: int

    @property
    def dropped_pct(self) -> float:
        """Dropped share of the expected slots [%] (0 for an empty stream)."""
        return 100.0 * self.dropped / self.expected if self.expected else 0.0


@dataclass
class DropCounter:
    """Running drop accounting of one stream, fed the published stamps in order (`add`)."""

    period_ns: int
    published: int = 0
    dropped: int = 0
    unacknowledged: int = 0   # of the dropped: sent, but not acknowledged by every reader in time
    last_ns: int | None = None

    def add(self, stamp_ns: int, acknowledged: bool = True) -> int:
        """Count a pair sent; returns the slots found missing just before it. A pair some reader did not
        acknowledge may be lost to it: it counts as dropped, not published."""
        missing = 0 if self.last_ns is None else missing_slots(int(stamp_ns) - self.last_ns, self.period_ns)
        if acknowledged:
            self.published += 1
        else:
            self.dropped += 1
            self.unacknowledged += 1
        self.dropped += missing
        self.last_ns = int(stamp_ns)
        return missing

    @property
    def tally(self) -> DropTally:
        """The slots so far."""
        return DropTally(self.published + self.dropped, self.published, self.dropped)


def count_drops(stamps_ns: Iterable[int], period_ns: int) -> DropTally:
    """Slots expected vs published of a stream, from its published stamps (in publish order).

    The expected slots run from the first stamp to the last; slots missing at either end of a stream
    are not visible in its stamps.
    """
    counter = DropCounter(int(period_ns))
    for stamp in stamps_ns:
        counter.add(stamp)
    return counter.tally


def buffer_stamp_s(driver_ms: float, arrival_wall_s: float, arrival_mono_s: float, latency_s: float,
                   max_age_s: float = 1.0) -> float:
    """Wall-clock time of a V4L2 frame from the driver's buffer timestamp, else its arrival minus a latency.

    ``driver_ms`` is OpenCV's ``CAP_PROP_POS_MSEC`` of the V4L2 backend: the buffer's timestamp, taken
    by UVC drivers on ``CLOCK_MONOTONIC`` (V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC) when the frame started
    to arrive; it is moved to the wall clock by the monotonic-to-wall offset read at arrival
    (``arrival_wall_s``, ``arrival_mono_s`` read together). Drivers without one report 0 or a
    frame count that does not lie in the last ``max_age_s`` before arrival; then the frame is placed
    ``latency_s`` (the measured device latency) before its arrival.
    """
    age_s = arrival_mono_s - driver_ms / 1000.0
    if driver_ms > 0 and 0.0 <= age_s <= max_age_s:
        return arrival_wall_s - age_s
    return arrival_wall_s - latency_s


@dataclass
class LagStats:
    """Publish time minus stamp of each pair of a stream [s]."""

    lags_s: list[float] = field(default_factory=list)

    def add(self, lag_s: float) -> None:
        self.lags_s.append(float(lag_s))

    @property
    def max_s(self) -> float:
        return max(self.lags_s) if self.lags_s else 0.0

    @property
    def median_s(self) -> float:
        return float(np.median(self.lags_s)) if self.lags_s else 0.0

    def summary(self) -> str:
        """One line for a reply or a log: max and median lag and the pairs they cover."""
        return (f"publish lag (publish - stamp) max {self.max_s:.3f} s, median {self.median_s:.3f} s "
                f"over {len(self.lags_s)} pairs")


class TruthHistory(Generic[T]):
    """Stamped samples of the carriage truth, to look up the one that held at a time.

    A clocked source renders frame k with the carriage as known at ``t_k``: the newest sample at or
    before ``t_k``, extrapolated (constant-rate motion) by the renderer. Samples arrive in stamp order
    but a stream may be rendered seconds behind them, so the history keeps them until `prune`.
    """

    def __init__(self) -> None:
        self._stamps: list[int] = []
        self._samples: list[T] = []

    def __len__(self) -> int:
        return len(self._stamps)

    def add(self, stamp_ns: int, sample: T) -> None:
        """Insert a sample (kept sorted by stamp; an equal stamp replaces the older sample)."""
        i = bisect.bisect_left(self._stamps, int(stamp_ns))
        if i < len(self._stamps) and self._stamps[i] == int(stamp_ns):
            self._samples[i] = sample
            return
        self._stamps.insert(i, int(stamp_ns))
        self._samples.insert(i, sample)

    @property
    def newest(self) -> T | None:
        return self._samples[-1] if self._samples else None

    def at(self, t_ns: int) -> T | None:
        """The newest sample stamped at or before ``t_ns``; the oldest one if all are later; None if empty."""
        if not self._samples:
            return None
        i = bisect.bisect_right(self._stamps, int(t_ns))
        return self._samples[max(i - 1, 0)]

    def between(self, after_ns: int, until_ns: int) -> list[T]:
        """The samples stamped after ``after_ns`` and at or before ``until_ns``, oldest first."""
        lo = bisect.bisect_right(self._stamps, int(after_ns))
        hi = bisect.bisect_right(self._stamps, int(until_ns))
        return self._samples[lo:hi]

    def prune(self, before_ns: int) -> None:
        """Forget samples no lookup at or after ``before_ns`` can return (the one holding then stays)."""
        i = bisect.bisect_right(self._stamps, int(before_ns)) - 1
        if i > 0:
            del self._stamps[:i]
            del self._samples[:i]

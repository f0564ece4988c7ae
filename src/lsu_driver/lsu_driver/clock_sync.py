"""The GP32's millisecond clock mapped to the host's clock: offset, drift and how well they are known.

The device stamps what it reports (where the carriage was, when it stopped) with its own free-running
millisecond counter; the host needs those instants on its own clock (ROS time) to place the laser
sheet at a camera's exposure. Every command round trip gives one sample: the host's send and receive
times bracket the instant the device read its counter for the reply. So the true host time of that
device reading lies in ``[send, receive]``; its midpoint is off by at most half the round trip.

Model: ``host = offset + scale * device`` (``scale = 1 / (1 + drift)``, drift: how much faster the
device counts) over a sliding window of samples (300: 30 s of the driver's 10 Hz status polls, long
enough to see a drift of tens of ppm through the 1 ms counter). The fit uses the samples with the
shortest round trips (their midpoints are the tightest brackets; a reply delayed by a busy host or
USB adapter only widens its own bracket), weighted by the inverse of their variance: the half round
trip squared plus the counter's own (a reading k is uniform over [k, k+1) ms: 1/12 ms^2). The counter's
part matters: by the round trip alone, a few round trips of microseconds would weigh thousands of times
more than the others and, close together in time, set the drift alone. The reported uncertainty is the
bracket half-width of the best samples plus the fit's own residual scatter plus one counter tick (a
reading k means "somewhere in [k, k+1) ms", for the round trips as for the stamp being mapped): what a
stamp mapped now can be off by.

Why hand-written: NTP/PTP implementations exist but speak their own protocols to clocks that run
them; here the "server" is a line-based serial device with a bare millisecond counter (wrapping), and
the estimator is twenty lines of weighted least squares.

A pure module: numpy only, no ROS.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

WRAP_MS = 2 ** 32  # the device counter is an unsigned 32-bit millisecond count


class ClockSyncError(RuntimeError):
    """No mapping yet (no round trip seen)."""


@dataclass(frozen=True)
class ClockSample:
    """One round trip: host send / receive times [s] and the device's counter in the reply [ms]."""

    host_send_s: float
    host_recv_s: float
    device_ms: int

    @property
    def half_rtt_s(self) -> float:
        return 0.5 * (self.host_recv_s - self.host_send_s)

    @property
    def host_mid_s(self) -> float:
        return 0.5 * (self.host_send_s + self.host_recv_s)


class DeviceClock:
    """Maps device milliseconds to host seconds from recent round trips (see the module text)."""

    def __init__(self, window: int = 300, best_fraction: float = 0.5, wrap_ms: int = WRAP_MS,
                 max_drift: float = 1e-3, resolution_ms: float = 1.0) -> None:
        if window < 2:
            raise ValueError("window must hold at least 2 samples")
        self._samples: deque[tuple[float, float, float]] = deque(maxlen=window)  # (device s unwrapped, mid, half rtt)
        self._best_fraction = best_fraction
        self._wrap_ms = wrap_ms
        self._max_drift = max_drift
        self._resolution_s = resolution_ms / 1000.0
        self._last_raw: int | None = None
        self._wraps = 0
        self._fit: tuple[float, float, float] | None = None  # (offset, 1 + drift, uncertainty)

    # -------------------------------------------------------------------------------- input
    def _unwrap(self, device_ms: int) -> float:
        raw = int(device_ms) % self._wrap_ms
        if self._last_raw is not None and raw < self._last_raw - self._wrap_ms // 2:
            self._wraps += 1
        self._last_raw = raw
        return (self._wraps * self._wrap_ms + raw) / 1000.0

    def add(self, sample: ClockSample) -> None:
        """One round trip; samples must come in the order the device read its counter."""
        if sample.host_recv_s < sample.host_send_s:
            raise ValueError("a reply cannot arrive before its command was sent")
        device_s = self._unwrap(sample.device_ms)
        self._samples.append((device_s, sample.host_mid_s, max(sample.half_rtt_s, 1e-6)))
        self._fit = None

    # -------------------------------------------------------------------------------- output
    def _solve(self) -> tuple[float, float, float]:
        if not self._samples:
            raise ClockSyncError("no round trip with the device yet: the device clock cannot be mapped")
        data = np.array(self._samples)
        device, mid, half = data[:, 0], data[:, 1], data[:, 2]
        best = half <= np.quantile(half, self._best_fraction)
        device, mid, half = device[best], mid[best], half[best]
        d0 = device[-1]  # regress around the newest sample: the mapping matters most near "now"
        w = 1.0 / (half ** 2 + self._resolution_s ** 2 / 12.0)  # inverse variance (module doc)
        if len(device) < 2 or np.ptp(device) < 1e-3:
            scale = 1.0
            offset = float(np.average(mid - device, weights=w))
            spread = 0.0
        else:
            A = np.column_stack([np.ones_like(device), device - d0])
            coef = np.linalg.lstsq(A * np.sqrt(w)[:, None], mid * np.sqrt(w), rcond=None)[0]
            scale = float(np.clip(coef[1], 1.0 - self._max_drift, 1.0 + self._max_drift))
            offset = float(coef[0] - scale * d0)
            spread = float(np.sqrt(np.average((mid - (offset + scale * device)) ** 2, weights=w)))
        uncertainty = float(np.min(half) + spread + self._resolution_s)
        return offset, scale, uncertainty

    def _current(self) -> tuple[float, float, float]:
        if self._fit is None:
            self._fit = self._solve()
        return self._fit

    def to_host(self, device_ms: int) -> float:
        """Host time [s] of a device stamp; a stamp read after the newest sample may have wrapped once more."""
        offset, scale, _ = self._current()
        raw = int(device_ms) % self._wrap_ms
        wraps = self._wraps
        if self._last_raw is not None and raw < self._last_raw - self._wrap_ms // 2:
            wraps += 1  # stamped after a wrap that no round trip has shown yet
        return offset + scale * (wraps * self._wrap_ms + raw) / 1000.0

    @property
    def drift_ppm(self) -> float:
        """How much faster the device clock runs than the host's [parts per million]."""
        return (1.0 / self._current()[1] - 1.0) * 1e6

    @property
    def uncertainty_s(self) -> float:
        """How far a mapped stamp can be off [s]: the best bracket's half width, the fit's scatter, one tick."""
        return self._current()[2]

    @property
    def samples(self) -> int:
        return len(self._samples)

"""DeviceClock: the device's millisecond stamps mapped to host time, against a simulated device clock."""

from __future__ import annotations

import numpy as np
import pytest

from lsu_driver.clock_sync import WRAP_MS, ClockSample, ClockSyncError, DeviceClock


class FakeDevice:
    """A device clock with its own offset and drift; ``ms(t)`` is its counter at host time ``t``."""

    def __init__(self, start_ms: int, drift_ppm: float, host0_s: float = 1000.0) -> None:
        self.start_ms, self.rate, self.host0 = start_ms, 1.0 + drift_ppm * 1e-6, host0_s

    def ms(self, host_s: float) -> int:
        return int(np.floor(self.start_ms + (host_s - self.host0) * self.rate * 1000.0)) % WRAP_MS


def round_trips(clock: DeviceClock, device: FakeDevice, start_s: float, seconds: float, seed: int,
                slow_fraction: float = 0.1) -> float:
    """Feed a round trip every 0.1 s (as the driver's status poll does); returns the host time at the end."""
    rng = np.random.default_rng(seed)
    t = start_s
    while t < start_s + seconds:
        out = rng.uniform(0.2e-3, 1.5e-3)
        back = rng.uniform(0.2e-3, 1.5e-3)
        if rng.random() < slow_fraction:  # a busy host or adapter: one leg 20-80 ms late
            back += rng.uniform(0.02, 0.08)
        clock.add(ClockSample(t, t + out + back, device.ms(t + out)))
        t += 0.1
    return t


@pytest.mark.parametrize("drift_ppm", [-300.0, 0.0, 250.0])
def test_stamps_map_to_host_time_within_the_reported_uncertainty(drift_ppm):
    device = FakeDevice(start_ms=123_456_789, drift_ppm=drift_ppm)
    clock = DeviceClock()
    now = round_trips(clock, device, 1000.0, 30.0, seed=1)
    for event_s in (now - 1.0, now, now + 0.5):
        mapped = clock.to_host(device.ms(event_s))
        # the counter's 1 ms resolution plus the reported uncertainty bound the error
        assert abs(mapped - event_s) <= clock.uncertainty_s + 1e-3, (mapped - event_s, clock.uncertainty_s)
    assert clock.uncertainty_s < 2e-3
    assert clock.drift_ppm == pytest.approx(drift_ppm, abs=30.0)


def test_a_late_event_is_placed_when_it_happened_not_when_it_arrived():
    device = FakeDevice(start_ms=5_000, drift_ppm=120.0)
    clock = DeviceClock()
    now = round_trips(clock, device, 1000.0, 20.0, seed=2)
    happened = now + 0.2
    received = happened + 0.05  # e.g. a !DONE held up 50 ms in a USB adapter's buffer
    mapped = clock.to_host(device.ms(happened))
    assert abs(mapped - happened) < 2e-3
    assert received - mapped > 0.045


def test_slow_replies_do_not_pull_the_mapping():
    device = FakeDevice(start_ms=0, drift_ppm=0.0)
    calm, busy = DeviceClock(), DeviceClock()
    end_calm = round_trips(calm, device, 1000.0, 10.0, seed=3, slow_fraction=0.0)
    round_trips(busy, device, 1000.0, 10.0, seed=3, slow_fraction=0.4)
    stamp = device.ms(end_calm)
    assert abs(busy.to_host(stamp) - calm.to_host(stamp)) < 1.5e-3


def test_the_counter_wrapping_around_keeps_the_mapping_continuous():
    device = FakeDevice(start_ms=WRAP_MS - 3_000, drift_ppm=50.0)  # wraps 3 s into the run
    clock = DeviceClock()
    now = round_trips(clock, device, 1000.0, 10.0, seed=4)
    assert device.ms(now) < 10_000  # it did wrap
    assert abs(clock.to_host(device.ms(now)) - now) < 2e-3
    # an event stamped after a wrap that no round trip has shown yet
    clock2 = DeviceClock()
    device2 = FakeDevice(start_ms=WRAP_MS - 2_500, drift_ppm=0.0)
    t = round_trips(clock2, device2, 1000.0, 2.0, seed=5)
    later = t + 1.0  # the counter wrapped in between
    assert device2.ms(later) < 1_000
    assert abs(clock2.to_host(device2.ms(later)) - later) < 2e-3


def test_no_round_trip_yet_is_an_error_that_says_so():
    with pytest.raises(ClockSyncError, match="no round trip"):
        DeviceClock().to_host(1000)


def test_a_few_very_short_round_trips_do_not_set_the_drift_alone():
    """3 s of polls at 800 ppm (the driver's device-time test) where five round trips in a row, 0.4 s into it,
    took 4 us (the rest 0.4..3 ms): the counter's 1 ms tick is most of what those readings are off by, and the drift
    comes from all the samples, not from five readings 0.4 s apart."""
    device = FakeDevice(start_ms=5_000, drift_ppm=800.0)
    clock = DeviceClock()
    rng = np.random.default_rng(3)
    for k in range(30):
        t = 1000.0 + 0.1 * k
        half = 2e-6 if 4 <= k < 9 else rng.uniform(0.2e-3, 1.5e-3)
        clock.add(ClockSample(t, t + 2 * half, device.ms(t + half + rng.uniform(-0.5, 0.5) * 1e-6)))
    assert clock.drift_ppm == pytest.approx(800.0, abs=300.0)

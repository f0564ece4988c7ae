"""The emulator's ground truth (what the simulated cameras render from) against its own motion model.

Truth: the model itself, pulse n of a motion started at t0 is due at ``t0 + n / rate`` and moves the
carriage by `overstep_gain`; the emulator is driven on a synthetic monotonic time line (no firmware
thread), so every instant is known exactly whatever the host's load.
"""

import pytest

from lsu_driver.emulator import EmulatorConfig, Gp32Emulator, Truth, mono_to_wall, overstep_gain

CLOCK_S = 1e-4  # the monotonic-to-wall offset is read afresh by each conversion


def follows(sample: Truth, t_s: float) -> float:
    """The position a camera renders at wall time ``t_s`` from ``sample`` (moving: linear from its stamp)."""
    return sample.position_steps + sample.velocity_steps_per_s * (t_s - sample.stamp_s) if sample.moving \
        else sample.position_steps


@pytest.mark.parametrize("rate", [60, 200])  # below and above the overstep threshold
def test_samples_at_start_stop_and_between_follow_the_motion_model(rate):
    emu = Gp32Emulator(EmulatorConfig(start_position_steps=100.0, rate_steps_per_s=rate))
    gain = overstep_gain(emu.config, float(rate))
    with emu._lock:
        emu._start_motion("move", +1, 30)
        t0 = emu._motion.started
    [start] = emu.take_truth_events()
    assert start.moving and start.position_steps == 100.0
    assert start.stamp_s == pytest.approx(mono_to_wall(t0), abs=CLOCK_S)
    assert start.velocity_steps_per_s == pytest.approx(rate * gain)

    emu._advance(t0 + 10.5 / rate)  # half-way between pulses 10 and 11
    mid = emu.truth()
    assert mid.moving and mid.position_steps == pytest.approx(100.0 + 10 * gain)
    assert mid.stamp_s == pytest.approx(mono_to_wall(t0 + 10 / rate), abs=CLOCK_S)  # pulse 10, not now
    assert follows(start, mid.stamp_s) == pytest.approx(mid.position_steps, abs=rate * CLOCK_S)
    assert emu.take_truth_events() == []  # steady motion: no event

    emu._advance(t0 + 30.7 / rate)  # the loop notices the last pulse late
    [stop] = emu.take_truth_events()
    t_stop = mono_to_wall(t0 + 30 / rate)
    assert not stop.moving and stop.velocity_steps_per_s == 0.0
    assert stop.stamp_s == pytest.approx(t_stop, abs=CLOCK_S) and stop.stopped_at_s == stop.stamp_s
    assert stop.position_steps == pytest.approx(100.0 + 30 * gain)
    assert follows(start, stop.stamp_s) == pytest.approx(stop.position_steps, abs=rate * CLOCK_S)
    assert stop.displacement_steps(stop.stamp_s) == pytest.approx(stop.vibration_amplitude_steps)
    # the !DONE carries the same instant on the device clock
    assert emu.timed_events[-1]["line"].startswith("!DONE") and emu.timed_events[-1]["wall_s"] == \
        pytest.approx(t_stop, abs=CLOCK_S)
    rest = emu.truth()  # at rest: the same stop and position
    assert (rest.position_steps, rest.stopped_at_s, rest.moving) == (stop.position_steps, stop.stopped_at_s, False)


def test_a_sweep_reversal_is_a_sample_at_its_pulse():
    emu = Gp32Emulator(EmulatorConfig(start_position_steps=460.0, rate_steps_per_s=100))
    with emu._lock:
        emu._start_motion("sweep", +1, None)
        t0 = emu._motion.started
    [start] = emu.take_truth_events()
    emu._advance(t0 + 15.5 / 100)  # the end sensor at pulse 10, then 5 pulses back
    [reverse] = emu.take_truth_events()
    assert reverse.moving and reverse.position_steps == 470.0 and reverse.velocity_steps_per_s == -100.0
    assert reverse.stamp_s == pytest.approx(mono_to_wall(t0 + 10 / 100), abs=CLOCK_S)
    assert follows(start, reverse.stamp_s) == pytest.approx(470.0, abs=100 * CLOCK_S)
    now = emu.truth()
    assert now.position_steps == 465.0
    assert follows(reverse, now.stamp_s) == pytest.approx(465.0, abs=100 * CLOCK_S)


def test_a_laser_switch_is_a_sample_at_its_instant_told_before_the_reply_leaves():
    """The simulated cameras render from the truth: the sample of a laser switch must be out before the
    unit's reply, which starts the chain (driver, coordinator, capture) that ends in a frame of that laser."""
    import os
    import select
    import time
    import tty

    emu = Gp32Emulator(EmulatorConfig())
    seen: list[tuple[bool, bool]] = []  # (laser on, reply already on the line) at each change notification
    emu.start()
    fd = os.open(emu.device_path, os.O_RDWR | os.O_NOCTTY)
    try:
        tty.setraw(fd)
        emu.on_change = lambda: seen.append((emu.truth().laser_on, bool(select.select([fd], [], [], 0)[0])))
        before = time.time()
        os.write(fd, b"L1\n")
        reply = b""
        while b"OK L1\n" not in reply:  # after the power-on !BOOT
            assert select.select([fd], [], [], 10)[0], "no reply to L1"
            reply += os.read(fd, 256)
        after = time.time()
        assert (True, False) in seen, seen  # told with the laser on, before the reply was readable
        [event] = [t for t in emu.take_truth_events() if t.laser_on]
        assert before <= event.stamp_s <= after and not event.moving
    finally:
        emu.on_change = None
        os.close(fd)
        emu.close()

"""Gp32Client over a real pty against both units (the emulator and the firmware in the HC08
simulator): motion and physics; and every serial fault against the emulator."""

import os
import threading
import time

import pytest

from lsu_driver import protocol as p
from lsu_driver.client import (
    CommandTimeout,
    DeviceError,
    DeviceReset,
    Gp32Client,
    MotionTimeout,
    NotConnected,
    VersionMismatch,
)
from lsu_driver.emulator import EmulatorConfig, Faults, Gp32Emulator


@pytest.fixture
def emulator(tmp_path):
    emu = Gp32Emulator(EmulatorConfig(start_position_steps=20.0), Faults(seed=1), link=str(tmp_path / "gp32"),
                       control=str(tmp_path / "gp32.ctl")).start()
    yield emu
    emu.close()


@pytest.fixture
def client(emulator):
    c = Gp32Client(str(emulator.link), command_timeout_s=0.5)
    c.connect()
    yield c
    c.close()


@pytest.fixture
def unit_client(unit):
    c = Gp32Client(str(unit.link), command_timeout_s=1.0)
    c.connect()
    yield c
    c.close()


def test_home_learns_the_track_and_move_to_takes_real_time(unit_client, unit):
    assert unit_client.identity.version == 2 and not unit_client.homed
    assert unit_client.home() == 470
    t0 = time.monotonic()
    result = unit_client.move_to(235)
    elapsed = time.monotonic() - t0
    assert result.reached and result.position == 235
    assert elapsed >= 235 / 200  # steps / rate: motion takes real time
    assert abs(unit.truth().position_steps - 235) < 0.5


# physics of the carriage (the model both units share): on the emulator only; the firmware's part of it,
# stopping at the end sensor with !END and counting the track while homing, is checked on the firmware by
# test_units_protocol's moves test and by test_home_learns_the_track_and_move_to_takes_real_time
@pytest.mark.parametrize("unit", ["emulator"], indirect=True)
def test_high_speed_oversteps_like_the_thesis_and_rehoming_restores(unit_client, unit):
    unit_client.set_rate(400)
    assert unit_client.home() == 467  # thesis ch. 3.2.3: 467 pulses instead of 470 at high speed
    unit_client.set_rate(200)
    assert unit_client.home() == 470
    unit_client.set_rate(400)
    result = unit_client.move_to(470)  # counter believes 470 is reachable; the carriage gets there early
    assert not result.reached and result.end_sensor == 1
    assert 466 <= result.position <= 469
    assert unit.truth().position_steps == pytest.approx(470.0)
    unit_client.set_rate(200)
    assert unit_client.home() == 470 and unit_client.status().position == 0


def test_watchdog_switches_the_laser_off_when_the_host_falls_silent(unit_client, unit):
    unit_client.set_watchdog(300)
    unit_client.laser(True)
    assert unit.truth().laser_on
    time.sleep(0.6)
    assert not unit.truth().laser_on
    assert any(isinstance(e, p.WatchdogFired) for e in unit_client.recent_events())


def test_moves_need_homing_and_the_range(unit_client):
    with pytest.raises(DeviceError) as info:
        unit_client.move_to(100)
    assert info.value.code == p.ERR_NOT_HOMED and "home the carriage first" in str(info.value)
    unit_client.home()
    with pytest.raises(DeviceError) as info:
        unit_client.move_to(600)
    assert info.value.code == p.ERR_RANGE


def test_stop_preempts_a_running_move_and_busy_is_reported(unit_client, unit):
    unit_client.home()
    unit_client.set_rate(100)
    outcome = {}
    mover = threading.Thread(target=lambda: outcome.setdefault("r", unit_client.move_to(400)))
    mover.start()
    time.sleep(0.3)
    with pytest.raises(DeviceError) as info:
        unit_client.move_to(10)
    assert info.value.code == p.ERR_BUSY
    unit_client.stop()
    mover.join(timeout=5)
    result = outcome["r"]
    assert not result.reached and 10 < result.position < 100
    assert not unit.truth().moving


def test_sweep_runs_between_the_sensors_until_stopped(unit_client, unit):
    unit_client.set_rate(400)
    unit_client.sweep()
    deadline = time.monotonic() + 4
    while time.monotonic() < deadline and not any(isinstance(e, p.EndSensor) and e.which == 1
                                                  for e in unit_client.recent_events()):
        time.sleep(0.05)
    unit_client.stop()
    ends = [e.which for e in unit_client.recent_events() if isinstance(e, p.EndSensor)]
    assert 1 in ends and not unit.truth().moving


@pytest.mark.fault('serial: garbage bytes')
def test_garbage_is_reported_and_the_link_keeps_working(client, emulator):
    errors = []
    client.add_error_listener(errors.append)
    for _ in range(5):
        emulator.inject_garbage(10)
        assert client.status().position == 0
    time.sleep(0.1)
    assert client.malformed_lines >= 5 and len(errors) == client.malformed_lines
    assert all(isinstance(e, p.MalformedLine) and e.raw for e in errors)


@pytest.mark.fault('serial: dropped bytes')
def test_dropped_bytes_fail_cleanly_or_succeed(client, emulator):
    emulator.set_faults(drop_probability=0.01)  # per byte: ~1 reply line in 5 is damaged
    outcomes = {"ok": 0, "timeout": 0}
    for _ in range(30):
        try:
            client.status()
            outcomes["ok"] += 1
        except CommandTimeout as exc:
            assert "did not answer 'P'" in str(exc)
            outcomes["timeout"] += 1
    emulator.clear_faults()
    assert outcomes["ok"] >= 20  # retries recover most lost replies
    assert client.status().position == 0


@pytest.mark.fault('serial: late replies')
def test_late_replies_time_out_clearly_and_are_not_mistaken_later(client, emulator):
    client.set_watchdog(0)  # the test stays silent longer than the default watchdog
    emulator.set_faults(reply_delay_s=1.6)
    with pytest.raises(CommandTimeout) as info:
        client.laser(True)
    assert "did not answer 'L1'" in str(info.value) and "check the cable" in str(info.value)
    emulator.clear_faults()
    time.sleep(1.8)
    assert client.status().laser_on  # the late "OK L1"s were discarded, not read as P's reply
    client.laser(False)
    assert not client.status().laser_on


@pytest.mark.fault('serial: unit reset mid-move')
def test_reset_mid_move_reports_lost_position_and_laser_off(client, emulator):
    client.home()
    client.laser(True)

    def reset_once_moving() -> None:  # not a fixed delay: under load the move may start late
        end = time.monotonic() + 10.0
        while emulator.truth().counter_steps <= 10 and time.monotonic() < end:
            time.sleep(0.005)
        emulator.reset()

    threading.Thread(target=reset_once_moving, daemon=True).start()
    with pytest.raises(DeviceReset) as info:
        client.move_to(400)
    assert "position lost" in str(info.value)
    truth = emulator.truth()
    assert not truth.laser_on and not truth.moving and truth.boot_count == 2
    assert not client.homed and not client.status().homed


@pytest.mark.fault('serial: stalled motor')
def test_stalled_motor_times_out_and_stop_is_sent(client, emulator):
    emulator.set_faults(stalled=True)
    with pytest.raises(MotionTimeout) as info:
        client.home(timeout_s=1.0)
    assert "stalled motor" in str(info.value) and "stop sent" in str(info.value)
    assert "< X" in emulator.log
    assert not emulator.truth().moving


@pytest.mark.fault('serial: port unplugged and back')
def test_port_removed_and_recreated_reconnects_and_asks_for_homing(client, emulator):
    client.home()
    states = []
    client.add_connection_listener(lambda up, why: states.append((up, time.monotonic(), why)))
    emulator.unplug(0.5)
    time.sleep(0.2)
    assert not client.connected
    with pytest.raises(NotConnected):
        client.status()
    replugged = time.monotonic() + 0.3
    deadline = replugged + 2.0
    while not client.connected and time.monotonic() < deadline:
        time.sleep(0.02)
    assert client.connected, states
    assert [s[0] for s in states] == [False, True]
    assert states[1][1] - replugged < 2.0
    assert not client.homed and not client.status().homed


@pytest.mark.fault('serial: missing port')
def test_missing_port_is_a_clear_error(tmp_path):
    with pytest.raises(NotConnected) as info:
        Gp32Client(str(tmp_path / "nothing")).connect()
    assert str(tmp_path / "nothing") in str(info.value) and "check the cable" in str(info.value)


def test_wrong_version_is_refused(tmp_path):
    master, slave = os.openpty()
    import tty

    tty.setraw(slave)

    def device():
        buf = b""
        while b"?" not in buf:
            buf += os.read(master, 64)
        os.write(master, b"OK LSU-GP32 v3 track=470 speed=200\n")

    threading.Thread(target=device, daemon=True).start()
    try:
        with pytest.raises(VersionMismatch) as info:
            Gp32Client(os.ttyname(slave), command_timeout_s=1.0, reconnect=False).connect()
        assert "v3" in str(info.value) and "needs v1 or v2" in str(info.value)
    finally:
        os.close(master)
        os.close(slave)


def test_fuzzed_line_never_breaks_the_client(client, emulator):
    """Random garbage before a third of the lines: only protocol-level errors, every bad line reported."""
    emulator.set_faults(garbage_probability=0.3)
    errors = []
    client.add_error_listener(errors.append)
    for _ in range(40):
        try:
            client.status()
        except CommandTimeout:
            pass  # a garbled reply after every retry is a clean, reported failure
    emulator.clear_faults()
    time.sleep(0.1)
    assert errors and client.malformed_lines == len(errors)
    assert client.status().position == 0


def test_a_port_vanishing_during_a_write_is_a_lost_connection_not_a_crash():
    """tcdrain on a pty whose other end is gone raises termios.error, which is not an OSError: it must
    reach callers (the driver's status poll timer) as NotConnected, never escape as termios.error."""
    import termios

    class VanishedPort:
        is_open = True

        def write(self, data: bytes) -> int:
            return len(data)

        def flush(self) -> None:
            raise termios.error(5, "Input/output error")

    c = Gp32Client("/dev/null-gp32", command_timeout_s=0.2)
    c._serial = VanishedPort()  # what the client holds when the unplug races a command
    with pytest.raises(NotConnected, match="Input/output error"):
        c.status()

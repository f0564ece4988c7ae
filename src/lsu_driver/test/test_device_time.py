"""Protocol v2 through the real client against the emulator, whose millisecond clock has its own
offset (a random 32-bit start) and drift (+150 ppm): every stamped event (``!POS``, ``!DONE``) is
placed at the host time it really happened, within the uncertainty the mapping reports, also when
the line arrives late; and the client falls back to v1 with a v1 unit. Ground truth: the host time
the emulator logged for each stamped event (its control socket's ``{"get": "events"}``)."""

from __future__ import annotations

import threading
import time

import pytest

from lsu_driver import protocol as p
from lsu_driver.client import Gp32Client, NotSupported
from lsu_driver.emulator import EmulatorConfig, Faults, Gp32Emulator, send_control


@pytest.fixture
def emulator(tmp_path):
    emu = Gp32Emulator(EmulatorConfig(start_position_steps=20.0), Faults(seed=3), link=str(tmp_path / "gp32"),
                       control=str(tmp_path / "gp32.ctl")).start()
    yield emu
    emu.close()


class Recorder:
    """What a driver does with stamped events: map each one at its arrival."""

    def __init__(self, client: Gp32Client) -> None:
        self.client = client
        self.mapped: list[tuple[p.Line, float, float, float]] = []  # (event, host stamp, uncertainty, arrival)
        client.add_listener(self)

    def __call__(self, event: p.Line) -> None:
        device_ms = getattr(event, "device_ms", None)
        if device_ms is not None:
            mapped = self.client.map_device_ms(device_ms) or (float("nan"), float("nan"))  # nan: fails below
            self.mapped.append((event, mapped[0], mapped[1], time.time()))


def truth_by_line(control: str) -> dict[str, float]:
    answer = send_control(control, {"get": "events"})
    assert answer["ok"]
    return {e["line"]: e["wall_s"] for e in answer["events"]}  # type: ignore[index,union-attr]


def poll(client: Gp32Client, stop: threading.Event, period_s: float = 0.05) -> None:
    """Status polls as the driver node makes them: each one a round trip for the clock mapping."""
    while not stop.is_set():
        client.status()
        stop.wait(period_s)


def test_position_and_stop_stamps_map_to_when_they_happened(emulator):
    client = Gp32Client(str(emulator.link), command_timeout_s=1.0)
    client.position_rate_hz = 25
    client.connect()
    try:
        assert client.version == 2
        recorder = Recorder(client)
        stop = threading.Event()
        poller = threading.Thread(target=poll, args=(client, stop), daemon=True)
        poller.start()
        try:
            time.sleep(0.3)
            result = client.step(+120)
            client.step(-40)
        finally:
            stop.set()
            poller.join()
    finally:
        client.close()  # its X ends with one more stamped !DONE
    truth = truth_by_line(str(emulator.control_path))
    assert result.reached and result.stopped_device_ms is not None
    # the device's counter is nowhere near host milliseconds: the offset is estimated, not assumed
    assert abs(result.stopped_device_ms / 1000.0 - result.stopped_at_s) > 100.0
    kinds = [type(e) for e, *_ in recorder.mapped]
    assert kinds.count(p.Done) == 3 and kinds.count(p.Position) >= 10, kinds
    for event, stamp, uncertainty, _ in recorder.mapped:
        happened = truth[p.encode_line(event).decode().strip()]
        assert abs(stamp - happened) <= uncertainty, (event, stamp - happened, uncertainty)
        assert uncertainty < 5e-3  # a pty's round trips: a few ms at most, or the mapping is useless
    first_done = next(e for e, *_ in recorder.mapped if isinstance(e, p.Done))
    assert first_done.position == 120 and result.stopped_device_ms == first_done.device_ms
    happened = truth[p.encode_line(first_done).decode().strip()]
    assert abs(result.stopped_at_s - happened) <= result.stopped_uncertainty_s


def test_a_late_line_is_stamped_when_it_happened_not_when_it_arrived(emulator):
    client = Gp32Client(str(emulator.link), command_timeout_s=1.5)
    client.connect()
    try:
        recorder = Recorder(client)
        for _ in range(30):  # prompt round trips before the fault
            client.status()
        assert send_control(str(emulator.control_path), {"fault": "late", "delay_ms": 400})["ok"]
        result = client.step(+30)  # its status read and its !DONE both arrive 400 ms late
    finally:
        emulator.clear_faults()
        client.close()
    truth = truth_by_line(str(emulator.control_path))
    event, stamp, uncertainty, arrival = next(m for m in recorder.mapped if m[0] == p.Done(30, result.stopped_device_ms))
    happened = truth[p.encode_line(event).decode().strip()]
    assert arrival - happened >= 0.4  # it did arrive late
    assert abs(stamp - happened) <= uncertainty < 5e-3
    assert result.stopped_uncertainty_s is not None
    assert abs(result.stopped_at_s - happened) <= result.stopped_uncertainty_s


def test_a_v1_unit_gets_v1_commands_only_and_stops_are_stamped_on_arrival(tmp_path):
    with Gp32Emulator(EmulatorConfig(start_position_steps=20.0, protocol_version=1),
                      link=str(tmp_path / "gp32")) as emulator:
        client = Gp32Client(str(emulator.link), command_timeout_s=1.0)
        client.position_rate_hz = 20  # wanted, but a v1 unit has no !POS: not sent
        client.connect()
        try:
            assert client.version == 1 and client.status().device_ms is None
            with pytest.raises(NotSupported, match="needs GP32 protocol v2"):
                client.read_clock()
            with pytest.raises(NotSupported, match="update the firmware"):
                client.set_position_rate(10)
            before = time.time()
            result = client.step(+30)
            after = time.time()
        finally:
            client.close()
        log = list(emulator.log)  # one copy: the unit's thread may still append while a loop walks the deque
        sent = [x[2:] for x in log if x.startswith("< ")]
        assert not any(x.startswith(("T", "R")) for x in sent), sent
        assert not any(x.startswith("> !POS") for x in log)
    assert result.reached and result.stopped_device_ms is None and result.stopped_uncertainty_s is None
    assert before < result.stopped_at_s < after  # the arrival of its !DONE
    assert client.clock_uncertainty_s() is None  # no stamp ever fed the mapping


def test_the_clock_restarts_with_the_device(emulator):
    client = Gp32Client(str(emulator.link), command_timeout_s=1.0)
    client.connect()
    try:
        time.sleep(1.2)
        before = client.read_clock()  # >= 1.2 s after power-on: the old mapping would be >= 1.2 s off below
        emulator.reset()  # power cycle: the counter starts again from its power-on value
        deadline = time.monotonic() + 3.0
        while not any(isinstance(e, p.Boot) for e in client.recent_events()) and time.monotonic() < deadline:
            time.sleep(0.01)
        after = client.read_clock()
        mapped = client.map_device_ms(after)
        # the old mapping is gone with the old counter: kept, it would place the restarted (smaller)
        # count seconds in the past. (Whether the client has re-read the clock yet is a race: not checked.)
        assert mapped is not None and abs(mapped[0] - time.time()) < 0.5
        assert after < before  # it restarted from its power-on value (it would have counted on otherwise)
    finally:
        client.close()


def test_the_drift_of_a_fast_device_clock_is_estimated_and_taken_out(tmp_path):
    """800 ppm (a poor crystal): over 3 s of polls the device gains 2.4 ms, more than the mapping's
    uncertainty, so a stamp is only placed right if the drift is estimated."""
    config = EmulatorConfig(start_position_steps=20.0, clock_drift_ppm=800.0, clock_seed=7)
    with Gp32Emulator(config, link=str(tmp_path / "gp32"), control=str(tmp_path / "gp32.ctl")) as emulator:
        client = Gp32Client(str(emulator.link), command_timeout_s=1.0)
        client.connect()
        try:
            recorder = Recorder(client)
            stop = threading.Event()
            poller = threading.Thread(target=poll, args=(client, stop), daemon=True)
            poller.start()
            try:
                time.sleep(3.0)
                result = client.step(+20)
            finally:
                stop.set()
                poller.join()
            drift = client.clock_drift_ppm()
        finally:
            client.close()
        truth = truth_by_line(str(emulator.control_path))
    assert drift == pytest.approx(800.0, abs=300.0), drift
    event, stamp, uncertainty, _ = next(m for m in recorder.mapped if m[0] == p.Done(20, result.stopped_device_ms))
    assert abs(stamp - truth[p.encode_line(event).decode().strip()]) <= uncertainty


def test_a_late_firmware_loop_sends_one_position_event_not_a_burst():
    """!POS comes at its rate; a loop that wakes late (a busy host) sends one for the position now, not a catch-up
    burst repeating it (the driver publishes every event it gets: a repeat was a duplicate carriage sample)."""
    emu = Gp32Emulator()  # not started: its loop is driven by hand with chosen instants
    emu.pos_rate_hz = 20
    emu._start_motion("move", +1, 100)
    started = emu._motion.started
    def positions() -> list[int]:
        return [int(e["line"].split()[1]) for e in emu.timed_events if e["line"].startswith("!POS")]

    rate = emu.rate  # steps/s: pulse n is due at started + n / rate

    def pulses_by(offset: float) -> int:
        # the same float arithmetic as the loop: started + 0.30 - started may be 0.2999..., one pulse fewer
        return int(((started + offset) - started) * rate)

    emu._advance(started)             # the first at the start
    emu._advance(started + 0.30)      # 6 periods late: one event, the counter where the pulses got to
    emu._advance(started + 0.3005)    # half a millisecond later: not due yet
    emu._advance(started + 0.3495)
    assert positions() == [0, pulses_by(0.30)]
    emu._advance(started + 0.3505)    # one period after the late one
    assert positions() == [0, pulses_by(0.30), pulses_by(0.3505)]

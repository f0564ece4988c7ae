"""Protocol v2 line by line on both units (emulator and firmware in the HC08 simulator): the
replies the protocol page prescribes for every command form, error codes, over-long lines, the
power-on ``!BOOT`` and the device clock (``T``, ``R``, ``!POS``, stamps). Expected lines come from
the protocol module's own encoder; the v1 forms are checked with the stamps taken off."""

from __future__ import annotations

import re
import statistics
import time

import pytest
import serial

from lsu_driver import protocol as p

_STAMPED = re.compile(rb"((?:!DONE|!POS|!HOME) -?\d+|OK P.* H[01]) T?\d+\n")


def unstamped(raw: bytes) -> bytes:
    """The line without its v2 device stamp: ``!DONE 5 81234`` -> ``!DONE 5``, ``OK P0 ... H0 T12`` -> ``OK P0 ... H0``."""
    match = _STAMPED.fullmatch(raw)
    return match.group(1) + b"\n" if match else raw


class Line:
    """A raw serial connection: send one command, collect the lines that follow (stamps taken off;
    ``raw_since_command`` keeps them)."""

    def __init__(self, path: str) -> None:
        self.port = serial.Serial(path, 115200, timeout=0.05)
        self.buffer = b""
        self.since_command: list[bytes] = []  # every line since the last command was sent
        self.raw_since_command: list[bytes] = []

    def read_lines(self, until: float) -> list[bytes]:
        lines = []
        while time.monotonic() < until:
            self.buffer += self.port.read(max(1, self.port.in_waiting))
            while b"\n" in self.buffer:
                raw, self.buffer = self.buffer.split(b"\n", 1)
                lines.append(raw + b"\n")
        self.raw_since_command += lines
        lines = [unstamped(x) for x in lines]
        self.since_command += lines
        return lines

    def ask(self, command: bytes, settle_s: float = 0.1, timeout_s: float = 3.0) -> list[bytes]:
        """The lines after sending ``command``: up to its reply (OK/ERR), then ``settle_s`` more (so a
        second reply would show)."""
        self.since_command = []
        self.raw_since_command = []
        self.port.write(command)
        end = time.monotonic() + timeout_s
        while time.monotonic() < end and not any(x.startswith((b"OK", b"ERR")) for x in self.since_command):
            self.read_lines(time.monotonic() + 0.02)
        self.read_lines(time.monotonic() + settle_s)
        return self.since_command

    def wait_for(self, wanted: bytes, timeout_s: float) -> list[bytes]:
        """Every line since the last command, once ``wanted`` is among them (or the timeout passed)."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end and wanted not in self.since_command:
            self.read_lines(time.monotonic() + 0.05)
        return self.since_command


@pytest.fixture
def line(unit):
    connection = Line(str(unit.link))
    connection.read_lines(time.monotonic() + 0.2)  # a !BOOT from the power-on, if it came late
    yield connection
    connection.port.close()


def err(code: int) -> bytes:
    return p.encode_line(p.Err(code, p.ERROR_TEXT[code]))


def test_identify_status_and_settings_answer_exactly_as_the_protocol_page(line):
    assert line.ask(b"?\n") == [p.encode_line(p.Ok(p.format_identify(p.IdentifyInfo(2, 470, 200))))]
    assert line.ask(b"p\r\n") == [p.encode_line(p.Ok(p.format_status(
        p.StatusInfo(0, False, False, False, False, False))))]  # case-insensitive, CR ignored
    assert line.ask(b"  S350 \n") == [b"OK S350\n"]
    assert line.ask(b"W0\n") == [b"OK W0\n"]
    assert line.ask(b"L1\n") == [b"OK L1\n"]
    assert line.ask(b"?\n") == [b"OK LSU-GP32 v2 track=470 speed=350\n"]
    assert line.ask(b"L0\n") == [b"OK L0\n"]


@pytest.mark.parametrize("command, code", [
    (b"Z\n", p.ERR_UNKNOWN), (b"PX\n", p.ERR_UNKNOWN), (b"\xe9\n", p.ERR_UNKNOWN), (b" \n", p.ERR_UNKNOWN),
    (b"Gx\n", p.ERR_ARGUMENT), (b"L2\n", p.ERR_ARGUMENT), (b"S900\n", p.ERR_ARGUMENT), (b"S19\n", p.ERR_ARGUMENT),
    (b"M0\n", p.ERR_ARGUMENT), (b"W60001\n", p.ERR_ARGUMENT), (b"M+1234567\n", p.ERR_ARGUMENT),
    (b"G-4\n", p.ERR_RANGE), (b"G100\n", p.ERR_NOT_HOMED),
])
def test_bad_commands_get_their_error_code(line, command, code):
    if code == p.ERR_NOT_HOMED:
        assert p.parse_command(command) == p.GoTo(100)
    else:  # the protocol module's parser agrees on the code
        with pytest.raises(p.CommandError) as info:
            p.parse_command(command)
        assert info.value.code == code
    assert line.ask(command) == [err(code)]


def test_over_long_lines_get_one_error_and_the_next_line_works(line):
    assert line.ask(b"P" * 32 + b"\n") == [err(p.ERR_UNKNOWN)]  # 32 characters: a command, just not a known one
    assert line.ask(b"P" * 33 + b"\n") == [err(p.ERR_TOO_LONG)]
    assert line.ask(b"M+1" + b" " * 100 + b"\n") == [err(p.ERR_TOO_LONG)]
    assert line.ask(b"P\n")[0].startswith(b"OK P0 ")


def test_moves_report_done_and_the_end_sensor(line, unit):
    assert line.ask(b"M-5\n", 0.0)[0] == b"OK\n"
    assert line.wait_for(b"!DONE -5\n", 3.0) == [b"OK\n", b"!DONE -5\n"]
    assert line.ask(b"M-30\n", 0.0)[0] == b"OK\n"  # the carriage started at 20: the start sensor stops it
    seen = line.wait_for(b"!DONE -20\n", 3.0)  # 15 pulses to the sensor
    assert seen == [b"OK\n", b"!END 0\n", b"!DONE -20\n"], seen
    assert line.ask(b"M-1\n") == [err(p.ERR_END_SENSOR)]
    assert unit.truth().position_steps == pytest.approx(0.0)


def test_power_cycle_announces_boot_and_forgets_position(line, unit):
    assert line.ask(b"M+5\n", 0.0)[0] == b"OK\n"
    assert line.wait_for(b"!DONE 5\n", 3.0) == [b"OK\n", b"!DONE 5\n"]
    line.since_command = []
    unit.reset()
    assert line.wait_for(b"!BOOT LSU-GP32 v2\n", 5.0) == [b"!BOOT LSU-GP32 v2\n"]
    assert line.ask(b"P\n") == [b"OK P0 L0 M0 E00 H0\n"]
    assert unit.truth().position_steps == pytest.approx(25.0, abs=0.01)  # the carriage did not move


def _clock(line: Line) -> int:
    reply = line.ask(b"T\n", 0.0)
    assert reply == [reply[0]] and reply[0].startswith(b"OK T"), reply
    return p.parse_clock(p.parse_line(reply[0]).payload)  # type: ignore[union-attr]


def test_pos_stamps_the_instant_of_its_counters_last_pulse(line):
    """!POS reports the counter with the instant it got there (its last pulse), not the millisecond the event
    leaves: between pulses the carriage is on its way to the next step, and a sweep frame is placed by these
    stamps. At 20 steps/s (a pulse every 50 ms) and 15 events/s the events fall at every phase of the pulse
    period: every stamp lies on the pulse grid, start + n * 50 ms (within the firmware's 1 ms tick and the
    millisecond it skips at the start), where the send time would miss it by up to 49 ms."""
    assert line.ask(b"S20\n") == [b"OK S20\n"]
    assert line.ask(b"R15\n") == [b"OK R15\n"]
    assert line.ask(b"M+12\n", 0.0)[0] == b"OK\n"
    seen = line.wait_for(b"!DONE 12\n", 5.0)
    assert seen[-1] == b"!DONE 12\n", seen
    events = [p.parse_line(x) for x in line.raw_since_command if x.startswith(b"!POS")]
    positions = [e for e in events if isinstance(e, p.Position) and e.device_ms is not None]
    assert len(positions) >= 6 and positions[0].position == 0, events  # 0.6 s at 15 Hz, the first at the start
    start_ms = positions[0].device_ms
    offsets = [(e.device_ms - start_ms) - 50 * e.position for e in positions[1:]]
    assert all(0 <= off <= 2 for off in offsets), offsets
    assert len({e.position for e in positions}) >= 5  # the events did fall between pulses, at varied phases


def test_v2_clock_stamps_and_position_events(line):
    """T, R and the stamps of P, !POS and !DONE on the device's own clock: the stamps never go back,
    a motion of n pulses at r steps/s spans at least n / r on it, and !POS comes every 1 / R s."""
    t0 = _clock(line)
    line.ask(b"P\n", 0.0)
    status = p.parse_status(p.parse_line(line.raw_since_command[0]).payload)  # type: ignore[union-attr]
    assert status.device_ms is not None and status.device_ms >= t0
    assert line.ask(b"R51\n") == [err(p.ERR_ARGUMENT)]
    assert line.ask(b"R-1\n") == [err(p.ERR_ARGUMENT)]
    assert line.ask(b"r20\n") == [b"OK R20\n"]
    t1 = _clock(line)
    assert line.ask(b"M+100\n", 0.0)[0] == b"OK\n"
    line.port.write(b"T\n")  # answered during motion, between the events
    seen = line.wait_for(b"!DONE 100\n", 5.0)
    assert seen[-1] == b"!DONE 100\n", seen
    during = [p.parse_clock(x[3:].decode().strip()) for x in line.raw_since_command if x.startswith(b"OK T")]
    assert len(during) == 1 and during[0] >= t1
    events = [p.parse_line(x) for x in line.raw_since_command if x.startswith(b"!")]
    positions = [e for e in events if isinstance(e, p.Position)]
    done = events[-1]
    assert isinstance(done, p.Done) and done.device_ms is not None
    assert done.device_ms - t1 >= 100 / 200 * 1000 - 2  # 100 pulses at 200 steps/s, on the device clock
    assert len(positions) >= 8, events  # 0.5 s at 20 Hz, the first at the start
    assert [e.position for e in positions] == sorted(e.position for e in positions)
    assert positions[0].position <= 2 and positions[-1].position < 100
    stamps = [e.device_ms for e in positions] + [done.device_ms]
    assert stamps == sorted(stamps)
    gaps = [b - a for a, b in zip(stamps[:-2], stamps[1:-1])]
    assert statistics.median(gaps) == pytest.approx(50, abs=2), gaps
    for event in positions:  # where the counter was at that instant: rate x elapsed device time
        assert event.position == pytest.approx((event.device_ms - positions[0].device_ms) * 0.2
                                               + positions[0].position, abs=3)
    assert line.ask(b"R0\n") == [b"OK R0\n"]
    assert line.ask(b"M-10\n", 0.0)[0] == b"OK\n"
    assert line.wait_for(b"!DONE 90\n", 3.0)[-1] == b"!DONE 90\n"
    assert not any(x.startswith(b"!POS") for x in line.raw_since_command)  # R0: off

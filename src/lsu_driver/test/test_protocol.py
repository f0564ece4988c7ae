"""Protocol v2 codec (v1 its subset): round trips (hypothesis) and fuzzing with random bytes."""

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lsu_driver import protocol as p

positions = st.integers(min_value=0, max_value=999999)
commands = st.one_of(
    st.just(p.Identify()), st.just(p.Status()), st.builds(p.Laser, st.booleans()), st.builds(p.GoTo, positions),
    st.builds(p.Move, st.integers(-99999, 99999).filter(lambda n: n != 0)), st.just(p.Home()), st.just(p.Sweep()),
    st.just(p.Stop()), st.builds(p.SetRate, st.integers(p.RATE_MIN, p.RATE_MAX)),
    st.builds(p.SetWatchdog, st.integers(0, p.WATCHDOG_MAX_MS)), st.just(p.ReadClock()),
    st.builds(p.SetPositionRate, st.integers(0, p.POS_RATE_MAX_HZ)))
stamps = st.integers(0, p.MS_WRAP - 1)
printable = st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=126), min_size=1, max_size=40)
lines = st.one_of(
    st.builds(p.Ok, st.one_of(st.just(""), printable.map(str.strip).filter(bool))),
    st.builds(p.Err, st.integers(1, 7), printable.map(str.strip).filter(bool)),
    st.builds(p.Boot, st.integers(0, 999)), st.builds(p.Done, st.integers(-99999, 999999), st.none() | stamps),
    st.builds(p.Position, st.integers(-99999, 999999), stamps),
    st.builds(p.HomeDone, positions, st.none() | stamps), st.builds(p.EndSensor, st.integers(0, 1)),
    st.just(p.WatchdogFired()))


@given(commands)
def test_every_command_round_trips(cmd):
    raw = p.encode_command(cmd)
    assert raw.endswith(b"\n") and len(raw) - 1 <= p.MAX_LINE
    assert p.parse_command(raw) == cmd
    assert p.parse_command(raw.lower().replace(b"\n", b"\r\n")) == cmd  # case-insensitive, CR ignored


@given(lines)
def test_every_reply_and_event_round_trips(line):
    raw = p.encode_line(line)
    parsed = p.parse_line(raw)
    assert parsed == line
    assert p.is_event(parsed) == isinstance(line, (p.Boot, p.Done, p.Position, p.HomeDone, p.EndSensor,
                                                   p.WatchdogFired))


@given(st.builds(p.IdentifyInfo, st.integers(0, 999), positions, st.integers(0, 9999)))
def test_identify_payload_round_trips(info):
    assert p.parse_identify(p.format_identify(info)) == info


@given(st.builds(p.StatusInfo, st.integers(-999999, 999999), st.booleans(), st.booleans(), st.booleans(),
                 st.booleans(), st.booleans(), st.none() | stamps))
def test_status_payload_round_trips(info):
    payload = p.format_status(info)
    assert p.parse_status(payload) == info
    assert len(p.encode_line(p.Ok(payload))) - 1 <= p.MAX_REPLY_LINE


@settings(max_examples=500)
@given(st.binary(max_size=80))
@pytest.mark.fault('serial: random bytes into the parser')
def test_random_bytes_never_escape_as_anything_but_protocol_errors(raw):
    try:
        p.parse_line(raw)
    except p.MalformedLine as exc:
        assert exc.raw == raw
    try:
        p.parse_command(raw)
    except p.CommandError as exc:
        assert exc.code in p.ERROR_TEXT


def test_device_side_errors_carry_the_protocol_codes():
    cases = {b"Z\n": p.ERR_UNKNOWN, b"Gx\n": p.ERR_ARGUMENT, b"S900\n": p.ERR_ARGUMENT, b"M0\n": p.ERR_ARGUMENT,
             b"G-4\n": p.ERR_RANGE, b"P" * 40 + b"\n": p.ERR_TOO_LONG}
    for raw, code in cases.items():
        with pytest.raises(p.CommandError) as info:
            p.parse_command(raw)
        assert info.value.code == code, raw


def test_host_refuses_values_the_device_would_reject():
    for bad in (p.SetRate(10), p.SetRate(401), p.SetWatchdog(-1), p.GoTo(-1), p.Move(0), p.SetPositionRate(51),
                p.SetPositionRate(-1)):
        with pytest.raises(p.CommandError):
            p.encode_command(bad)


def test_payload_parsers_are_strict():
    assert p.parse_status("P235 L1 M0 E01 H1") == p.StatusInfo(235, True, False, False, True, True)
    for bad in ("P235 L1 M0 E01", "P235 L2 M0 E01 H1", "X"):
        with pytest.raises(p.MalformedLine):
            p.parse_status(bad)
    with pytest.raises(p.MalformedLine):
        p.parse_identify("LSU-GP32 v1 track=470")


def test_v1_lines_parse_as_before_and_v2_stamps_are_32_bit():
    assert p.parse_line(b"!DONE 235\n") == p.Done(235, None)
    assert p.parse_line(b"!DONE 235 4294967295\n") == p.Done(235, 2 ** 32 - 1)
    assert p.parse_line(b"!HOME 470\n") == p.HomeDone(470)
    assert p.parse_line(b"!POS -3 17\n") == p.Position(-3, 17)
    assert p.parse_status("P235 L1 M0 E01 H1").device_ms is None
    assert p.parse_status("P235 L1 M0 E01 H1 T81234").device_ms == 81234
    assert p.parse_clock("T0") == 0
    for bad in (b"!DONE 235 4294967296\n", b"!POS 5\n", b"!DONE 1 2 3\n"):
        with pytest.raises(p.MalformedLine):
            p.parse_line(bad)
    for payload in ("T", "T-1", "T4294967296", "81234"):
        with pytest.raises(p.MalformedLine):
            p.parse_clock(payload)

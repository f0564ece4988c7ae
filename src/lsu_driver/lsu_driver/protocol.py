"""GP32 serial protocol v2 (and v1, its subset): typed commands, replies and events (see GP32_PROTOCOL.md).

v2 adds the device's millisecond clock: ``T`` reads it, ``R<hz>`` sets the rate of ``!POS <pos> <ms>``
events during motion, and the status reply, ``!DONE`` and ``!HOME`` carry the counter of the instant they
report. Every v1 line parses as before, with ``device_ms`` None.

Strict both ways: encoding refuses values the firmware would reject, and parsing a line
that is not exactly one of the protocol's forms raises `MalformedLine` carrying the raw
bytes, never anything else. The same module serves the host (client) and the emulator.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass

PROTOCOL_VERSION = 2
SUPPORTED_VERSIONS = (1, 2)  # what the client speaks; v2 features are used only with a v2 device
DEVICE_NAME = "LSU-GP32"
MAX_LINE = 32            # commands (host -> device): the GP32's receive buffer
# Device lines may be longer: the identify reply "OK LSU-GP32 v1 track=470 speed=200" of the
# spec itself has 35 characters, so the 32-character limit can only bind commands.
MAX_REPLY_LINE = 64
RATE_MIN, RATE_MAX = 20, 400
WATCHDOG_MAX_MS = 60000
POS_RATE_MAX_HZ = 50      # !POS events per second at most (a 20-character event: 1 kB/s at 50 Hz)
MS_WRAP = 2 ** 32         # the device's millisecond counter is unsigned 32-bit

# error codes of the protocol
ERR_UNKNOWN, ERR_ARGUMENT, ERR_NOT_HOMED, ERR_BUSY, ERR_RANGE, ERR_TOO_LONG, ERR_END_SENSOR = 1, 2, 3, 4, 5, 6, 7
ERROR_TEXT = {ERR_UNKNOWN: "unknown command", ERR_ARGUMENT: "bad argument", ERR_NOT_HOMED: "not homed",
              ERR_BUSY: "busy", ERR_RANGE: "out of range", ERR_TOO_LONG: "line too long",
              ERR_END_SENSOR: "end sensor hit"}


class ProtocolError(Exception):
    """Base of the protocol's errors."""


class MalformedLine(ProtocolError):
    """A received line is not valid protocol; ``raw`` holds the bytes as received."""

    def __init__(self, raw: bytes, reason: str) -> None:
        self.raw = raw
        self.reason = reason
        super().__init__(f"malformed line {raw!r}: {reason}")


class CommandError(ProtocolError):
    """A command line the device rejects; ``code`` is the protocol error code to answer with."""

    def __init__(self, code: int, text: str, raw: bytes = b"") -> None:
        self.code = code
        self.text = text
        self.raw = raw
        super().__init__(f"ERR {code} {text}")


# ------------------------------------------------------------------------------------ commands
@dataclass(frozen=True)
class Identify:
    """``?``"""


@dataclass(frozen=True)
class Status:
    """``P``"""


@dataclass(frozen=True)
class Laser:
    """``L1`` / ``L0``"""

    on: bool


@dataclass(frozen=True)
class GoTo:
    """``G<pos>``: absolute move (needs homing)."""

    position: int


@dataclass(frozen=True)
class Move:
    """``M<+/-n>``: relative move."""

    steps: int


@dataclass(frozen=True)
class Home:
    """``H``"""


@dataclass(frozen=True)
class Sweep:
    """``C``: sweep between the sensors until ``X``."""


@dataclass(frozen=True)
class Stop:
    """``X``"""


@dataclass(frozen=True)
class SetRate:
    """``S<n>``: step rate in steps/s."""

    steps_per_s: int


@dataclass(frozen=True)
class SetWatchdog:
    """``W<ms>``: laser watchdog (0 = off)."""

    ms: int


@dataclass(frozen=True)
class ReadClock:
    """``T`` (v2): the device's millisecond counter, ``OK T<ms>``."""


@dataclass(frozen=True)
class SetPositionRate:
    """``R<hz>`` (v2): ``!POS`` events per second during motion (0 = off, the power-on value)."""

    hz: int


Command = (Identify | Status | Laser | GoTo | Move | Home | Sweep | Stop | SetRate | SetWatchdog | ReadClock
           | SetPositionRate)

_INT = r"([+-]?\d{1,6})"
_COMMAND_FORMS: list[tuple[re.Pattern[str], Callable[[re.Match[str]], Command]]] = [
    (re.compile(r"\?"), lambda m: Identify()),
    (re.compile(r"P"), lambda m: Status()),
    (re.compile(r"L([01])"), lambda m: Laser(m.group(1) == "1")),
    (re.compile(r"G" + _INT), lambda m: GoTo(int(m.group(1)))),
    (re.compile(r"M" + _INT), lambda m: Move(int(m.group(1)))),
    (re.compile(r"H"), lambda m: Home()),
    (re.compile(r"C"), lambda m: Sweep()),
    (re.compile(r"X"), lambda m: Stop()),
    (re.compile(r"S" + _INT), lambda m: SetRate(int(m.group(1)))),
    (re.compile(r"W" + _INT), lambda m: SetWatchdog(int(m.group(1)))),
    (re.compile(r"T"), lambda m: ReadClock()),
    (re.compile(r"R" + _INT), lambda m: SetPositionRate(int(m.group(1)))),
]


def _check(cmd: Command) -> None:
    if isinstance(cmd, GoTo) and cmd.position < 0:
        raise CommandError(ERR_RANGE, f"position {cmd.position} < 0")
    if isinstance(cmd, Move) and cmd.steps == 0:
        raise CommandError(ERR_ARGUMENT, "move of 0 steps")
    if isinstance(cmd, SetRate) and not RATE_MIN <= cmd.steps_per_s <= RATE_MAX:
        raise CommandError(ERR_ARGUMENT, f"rate {cmd.steps_per_s} outside {RATE_MIN}..{RATE_MAX}")
    if isinstance(cmd, SetWatchdog) and not 0 <= cmd.ms <= WATCHDOG_MAX_MS:
        raise CommandError(ERR_ARGUMENT, f"watchdog {cmd.ms} outside 0..{WATCHDOG_MAX_MS}")
    if isinstance(cmd, SetPositionRate) and not 0 <= cmd.hz <= POS_RATE_MAX_HZ:
        raise CommandError(ERR_ARGUMENT, f"position rate {cmd.hz} outside 0..{POS_RATE_MAX_HZ}")


def encode_command(cmd: Command) -> bytes:
    """The line for ``cmd``, ``\\n``-terminated.

    Raises:
        CommandError: a value the device would reject (checked here so the host fails early).
    """
    _check(cmd)
    if isinstance(cmd, Identify):
        text = "?"
    elif isinstance(cmd, Status):
        text = "P"
    elif isinstance(cmd, Laser):
        text = "L1" if cmd.on else "L0"
    elif isinstance(cmd, GoTo):
        text = f"G{cmd.position}"
    elif isinstance(cmd, Move):
        text = f"M{cmd.steps:+d}"
    elif isinstance(cmd, Home):
        text = "H"
    elif isinstance(cmd, Sweep):
        text = "C"
    elif isinstance(cmd, Stop):
        text = "X"
    elif isinstance(cmd, SetRate):
        text = f"S{cmd.steps_per_s}"
    elif isinstance(cmd, SetWatchdog):
        text = f"W{cmd.ms}"
    elif isinstance(cmd, ReadClock):
        text = "T"
    elif isinstance(cmd, SetPositionRate):
        text = f"R{cmd.hz}"
    else:
        raise TypeError(f"not a GP32 command: {cmd!r}")
    return (text + "\n").encode("ascii")


def _clean(raw: bytes) -> str:
    """Line text without terminators; raises MalformedLine for non-ASCII or overlong lines."""
    body = raw.rstrip(b"\n").replace(b"\r", b"")
    if len(body) > MAX_REPLY_LINE:
        raise MalformedLine(raw, f"longer than {MAX_REPLY_LINE} characters")
    try:
        text = body.decode("ascii")
    except UnicodeDecodeError:
        raise MalformedLine(raw, "not ASCII") from None
    if not text.isprintable():
        raise MalformedLine(raw, "control characters in line")
    return text


def parse_command(raw: bytes) -> Command:
    """Parse a command line (device side). Case-insensitive, surrounding spaces ignored.

    Raises:
        CommandError: with the protocol error code the device answers with.
    """
    body = raw.rstrip(b"\n").replace(b"\r", b"")
    if len(body) > MAX_LINE:
        raise CommandError(ERR_TOO_LONG, f"more than {MAX_LINE} characters", raw)
    try:
        text = body.decode("ascii").strip().upper()
    except UnicodeDecodeError:
        raise CommandError(ERR_UNKNOWN, "not ASCII", raw) from None
    for pattern, make in _COMMAND_FORMS:
        match = pattern.fullmatch(text)
        if match:
            cmd = make(match)
            try:
                _check(cmd)
            except CommandError as exc:
                raise CommandError(exc.code, exc.text, raw) from None
            return cmd
    if text[:1] in ("L", "G", "M", "S", "W", "R"):
        raise CommandError(ERR_ARGUMENT, f"bad argument in '{text}'", raw)
    raise CommandError(ERR_UNKNOWN, f"unknown command '{text}'", raw)


# ------------------------------------------------------------------------------ replies/events
@dataclass(frozen=True)
class Ok:
    """``OK[ payload]``"""

    payload: str = ""


@dataclass(frozen=True)
class Err:
    """``ERR <code> <text>``"""

    code: int
    text: str


@dataclass(frozen=True)
class Boot:
    """``!BOOT LSU-GP32 v<version>``: the device (re)started; position lost."""

    version: int


@dataclass(frozen=True)
class Done:
    """``!DONE <pos>[ <ms>]``: a motion ended at step counter ``position``; v2: at device ms ``device_ms``."""

    position: int
    device_ms: int | None = None


@dataclass(frozen=True)
class Position:
    """``!POS <pos> <ms>`` (v2): during motion the step counter was ``position`` at device ms ``device_ms``."""

    position: int
    device_ms: int


@dataclass(frozen=True)
class HomeDone:
    """``!HOME <track>[ <ms>]``: homing finished, ``track`` steps between the sensors (v2: at ``device_ms``)."""

    track: int
    device_ms: int | None = None


@dataclass(frozen=True)
class EndSensor:
    """``!END 0`` (start sensor) / ``!END 1`` (end sensor) beam broken."""

    which: int


@dataclass(frozen=True)
class WatchdogFired:
    """``!WDOG``: the laser watchdog switched the laser off."""


Reply = Ok | Err
Event = Boot | Done | Position | HomeDone | EndSensor | WatchdogFired
Line = Ok | Err | Boot | Done | Position | HomeDone | EndSensor | WatchdogFired

_MS = r"(\d{1,10})"  # an unsigned 32-bit millisecond count


def _ms(text: str | None) -> int | None:
    if text is None:
        return None
    value = int(text)
    if value >= MS_WRAP:
        raise ValueError(f"millisecond count {value} does not fit 32 bits")
    return value

_LINE_FORMS: list[tuple[re.Pattern[str], Callable[[re.Match[str]], Line]]] = [
    (re.compile(r"OK(?: ([ -~]{1,60}))?"), lambda m: Ok(m.group(1) or "")),
    (re.compile(r"ERR ([1-9]) ([ -~]{1,58})"), lambda m: Err(int(m.group(1)), m.group(2))),
    (re.compile(r"!BOOT " + DEVICE_NAME + r" v(\d{1,3})"), lambda m: Boot(int(m.group(1)))),
    (re.compile(r"!DONE (-?\d{1,6})(?: " + _MS + ")?"), lambda m: Done(int(m.group(1)), _ms(m.group(2)))),
    (re.compile(r"!POS (-?\d{1,6}) " + _MS), lambda m: Position(int(m.group(1)), int(_ms(m.group(2)) or 0))),
    (re.compile(r"!HOME (\d{1,6})(?: " + _MS + ")?"), lambda m: HomeDone(int(m.group(1)), _ms(m.group(2)))),
    (re.compile(r"!END ([01])"), lambda m: EndSensor(int(m.group(1)))),
    (re.compile(r"!WDOG"), lambda m: WatchdogFired()),
]


def parse_line(raw: bytes) -> Line:
    """Parse a line from the device.

    Raises:
        MalformedLine: anything that is not exactly one protocol form (with the raw bytes).
    """
    text = _clean(raw)
    for pattern, make in _LINE_FORMS:
        match = pattern.fullmatch(text)
        if match:
            try:
                return make(match)
            except ValueError as exc:
                raise MalformedLine(raw, str(exc)) from None
    raise MalformedLine(raw, "not a reply (OK/ERR) or event (!...)")


def is_event(line: Line) -> bool:
    """Events arrive unasked; replies answer the oldest command in flight."""
    return isinstance(line, (Boot, Done, Position, HomeDone, EndSensor, WatchdogFired))


def encode_line(line: Line) -> bytes:
    """The device's text for a reply or event (emulator side), ``\\n``-terminated."""
    if isinstance(line, Ok):
        text = f"OK {line.payload}" if line.payload else "OK"
    elif isinstance(line, Err):
        text = f"ERR {line.code} {line.text}"
    elif isinstance(line, Boot):
        text = f"!BOOT {DEVICE_NAME} v{line.version}"
    elif isinstance(line, Done):
        text = f"!DONE {line.position}" + ("" if line.device_ms is None else f" {line.device_ms}")
    elif isinstance(line, Position):
        text = f"!POS {line.position} {line.device_ms}"
    elif isinstance(line, HomeDone):
        text = f"!HOME {line.track}" + ("" if line.device_ms is None else f" {line.device_ms}")
    elif isinstance(line, EndSensor):
        text = f"!END {line.which}"
    elif isinstance(line, WatchdogFired):
        text = "!WDOG"
    else:
        raise TypeError(f"not a GP32 line: {line!r}")
    if len(text) > MAX_REPLY_LINE:
        raise ValueError(f"line longer than {MAX_REPLY_LINE}: {text!r}")
    return (text + "\n").encode("ascii")


# ------------------------------------------------------------------------------------ payloads
@dataclass(frozen=True)
class IdentifyInfo:
    """Payload of the ``?`` reply."""

    version: int
    track_steps: int
    rate_steps_per_s: int


@dataclass(frozen=True)
class StatusInfo:
    """Payload of the ``P`` reply."""

    position: int
    laser_on: bool
    moving: bool
    at_start: bool
    at_end: bool
    homed: bool
    device_ms: int | None = None   # v2: the device's counter when it read this status


_IDENT = re.compile(DEVICE_NAME + r" v(\d{1,3}) track=(\d{1,6}) speed=(\d{1,4})")
_STATUS = re.compile(r"P(-?\d{1,6}) L([01]) M([01]) E([01])([01]) H([01])(?: T" + _MS + ")?")
_CLOCK = re.compile(r"T" + _MS)


def parse_identify(payload: str, raw: bytes | None = None) -> IdentifyInfo:
    """``LSU-GP32 v1 track=470 speed=200`` -> IdentifyInfo; MalformedLine otherwise."""
    match = _IDENT.fullmatch(payload)
    if not match:
        raise MalformedLine(raw or payload.encode(), f"not an identify payload: {payload!r}")
    return IdentifyInfo(int(match.group(1)), int(match.group(2)), int(match.group(3)))


def format_identify(info: IdentifyInfo) -> str:
    """Emulator side of `parse_identify`."""
    return f"{DEVICE_NAME} v{info.version} track={info.track_steps} speed={info.rate_steps_per_s}"


def parse_status(payload: str, raw: bytes | None = None) -> StatusInfo:
    """``P235 L1 M0 E00 H1`` (v1) / ``P235 L1 M0 E00 H1 T81234`` (v2) -> StatusInfo; MalformedLine otherwise."""
    match = _STATUS.fullmatch(payload)
    if not match:
        raise MalformedLine(raw or payload.encode(), f"not a status payload: {payload!r}")
    g = match.groups()
    try:
        device_ms = _ms(g[6])
    except ValueError as exc:
        raise MalformedLine(raw or payload.encode(), str(exc)) from None
    return StatusInfo(int(g[0]), g[1] == "1", g[2] == "1", g[3] == "1", g[4] == "1", g[5] == "1", device_ms)


def format_status(info: StatusInfo) -> str:
    """Emulator side of `parse_status`."""
    b = lambda flag: "1" if flag else "0"  # noqa: E731
    return (f"P{info.position} L{b(info.laser_on)} M{b(info.moving)} "
            f"E{b(info.at_start)}{b(info.at_end)} H{b(info.homed)}"
            + ("" if info.device_ms is None else f" T{info.device_ms}"))


def parse_clock(payload: str, raw: bytes | None = None) -> int:
    """``T81234`` (the ``T`` reply, v2) -> the device's millisecond counter; MalformedLine otherwise."""
    match = _CLOCK.fullmatch(payload)
    try:
        if match:
            return int(_ms(match.group(1)) or 0)
    except ValueError:
        pass
    raise MalformedLine(raw or payload.encode(), f"not a clock payload: {payload!r}")

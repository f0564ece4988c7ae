"""A pyserial client for the GP32 (protocol v1 and v2), usable without ROS.

    with Gp32Client("/dev/ttyUSB0") as unit:
        unit.home()
        unit.move_to(235)

- A reader thread splits the byte stream into lines; replies go to the command that is
  waiting, ``!`` events to listeners and to motion waiters, so an event is never taken for
  a reply. Malformed lines (garbage, dropped bytes) are counted and reported, never raised
  in the reader.
- One command in flight at a time (thread-safe); every command has a timeout and
  idempotent commands are retried. A reply is checked against the command it answers
  (``OK L1`` for ``L1``, ``OK P...`` for ``P``), so a late reply to an earlier command is
  discarded instead of being mistaken for the current one.
- Motions wait for ``!DONE`` / ``!HOME`` outside the command lock, with a timeout from
  distance and rate; `stop()` from another thread preempts them. On a timeout the client
  sends ``X``.
- When the port vanishes, the client marks itself disconnected, fails waiting calls, and
  reconnects with backoff (the emulator and USB adapters come back under the same path).
- The version comes from ``?``: with a v2 device every stamped reply (``P``, ``T``) is a round trip
  that feeds `clock` (a `DeviceClock`), so the device's stamps in ``!DONE``, ``!POS`` and ``!HOME``
  map to host time (`map_device_ms`); with a v1 device the client uses v1 commands only and stamps a
  stop by the arrival of its ``!DONE``.
"""

from __future__ import annotations

import logging
import queue
import termios
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import serial

from . import protocol as p
from .clock_sync import ClockSample, ClockSyncError, DeviceClock

# What a serial port that vanishes can raise: pyserial's own error, OSError from read/ioctl, and
# termios.error from tcdrain/tcflush (flush(), reset_input_buffer()), which is not an OSError.
PORT_ERRORS = (serial.SerialException, OSError, termios.error)

log = logging.getLogger("lsu_driver.client")


class Gp32Error(Exception):
    """Base of the client's errors; the message says what happened and what to do."""


class NotConnected(Gp32Error):
    """The serial port is not open (missing, vanished, or not yet reconnected)."""


class VersionMismatch(Gp32Error):
    """The device speaks no protocol version this client knows."""


class NotSupported(Gp32Error):
    """The command needs a newer protocol version than the device speaks."""


class CommandTimeout(Gp32Error):
    """No (valid) reply to a command in time."""


class DeviceError(Gp32Error):
    """The device answered ``ERR <code>``."""

    def __init__(self, code: int, text: str, command: str) -> None:
        self.code = code
        self.text = text
        hints = {p.ERR_NOT_HOMED: "home the carriage first", p.ERR_BUSY: "wait for the motion or stop it",
                 p.ERR_RANGE: "stay within 0..track", p.ERR_END_SENSOR: "the carriage is at that end already"}
        hint = hints.get(code, "")
        super().__init__(f"GP32 refused '{command}': ERR {code} {text}" + (f" ({hint})" if hint else ""))


class MotionTimeout(Gp32Error):
    """A motion did not finish in time (stalled motor, broken sensor); ``X`` was sent."""


class DeviceReset(Gp32Error):
    """The device sent ``!BOOT`` (reset / power loss): position lost, laser off."""


class PortLost(Gp32Error):
    """The serial port vanished during the call."""


@dataclass(frozen=True)
class MotionResult:
    """How a motion ended."""

    position: int                 # step counter when it stopped
    target: int | None         # requested absolute target (None for a sweep)
    end_sensor: int | None     # sensor (0 start / 1 end) that tripped during the motion, if any
    # host (wall-clock) time the carriage stopped: v2, the !DONE's device stamp mapped through `clock`;
    # v1 (or no round trip yet), the arrival of the !DONE
    stopped_at_s: float | None = None
    stopped_device_ms: int | None = None   # v2: the device's counter when it stopped
    stopped_uncertainty_s: float | None = None  # how far stopped_at_s can be off (None: arrival time)

    @property
    def reached(self) -> bool:
        """True when the carriage stopped at the requested target."""
        return self.target is not None and self.position == self.target


Listener = Callable[[p.Line], None]


class Gp32Client:
    """Thread-safe GP32 client over a serial port (see the module docstring)."""

    def __init__(self, port: str, baud: int = 115200, command_timeout_s: float = 1.0, retries: int = 2,
                 reconnect: bool = True, motion_margin: float = 1.5) -> None:
        self.port = port
        self.baud = baud
        self.command_timeout_s = command_timeout_s
        self.retries = retries
        self.reconnect = reconnect
        self.motion_margin = motion_margin
        self.identity: p.IdentifyInfo | None = None
        self.last_status: p.StatusInfo | None = None
        self.rate_steps_per_s = 200
        self.track_steps = 0
        self.homed = False
        self.position: int | None = None   # step counter as last reported (status or !DONE)
        self.malformed_lines = 0
        self.stale_replies = 0
        self.position_rate_hz = 0             # !POS events per second during motion (v2), set at every connect
        self.clock = DeviceClock()            # the device's ms counter -> host time (v2; renewed at !BOOT)
        self._clock_lock = threading.Lock()
        self._serial: serial.Serial | None = None
        self._cmd_lock = threading.Lock()
        # replies with the host time their line was complete
        self._replies: queue.Queue[tuple[p.Ok | p.Err, float]] = queue.Queue()
        self._state = threading.Condition()
        self._event_seq = 0
        self._events: list[p.Line | _PortLostMarker] = []       # recent events (bounded), newest last
        self.last_stop_s: float | None = None  # host time of the last stop (see MotionResult.stopped_at_s)
        self.last_stop_uncertainty_s: float | None = None
        self._listeners: list[Listener] = []
        self._error_listeners: list[Callable[[p.MalformedLine], None]] = []
        self._connection_listeners: list[Callable[[bool, str], None]] = []
        self._connected = False
        self._closing = False
        self._reader: threading.Thread | None = None
        self._supervisor: threading.Thread | None = None
        self._lost = threading.Event()

    # ------------------------------------------------------------------------------ listeners
    def add_listener(self, callback: Listener) -> None:
        """``callback(event)`` for every ``!`` event (from the reader thread: keep it short)."""
        self._listeners.append(callback)

    def add_error_listener(self, callback: Callable[[p.MalformedLine], None]) -> None:
        """``callback(error)`` for every malformed line received."""
        self._error_listeners.append(callback)

    def add_connection_listener(self, callback: Callable[[bool, str], None]) -> None:
        """``callback(connected, reason)`` when the link goes down or comes back."""
        self._connection_listeners.append(callback)

    @property
    def connected(self) -> bool:
        """True while the port is open and the device passed the version check."""
        return self._connected

    @property
    def version(self) -> int:
        """Protocol version of the connected device (0 before the first ``?``)."""
        return self.identity.version if self.identity else 0

    # ------------------------------------------------------------------------------ device clock
    def _add_clock_sample(self, sent_s: float, recv_s: float, device_ms: int | None) -> None:
        if device_ms is None:
            return
        with self._clock_lock:
            self.clock.add(ClockSample(sent_s, recv_s, device_ms))

    def _reset_clock(self) -> None:
        with self._clock_lock:
            self.clock = DeviceClock()

    def map_device_ms(self, device_ms: int) -> tuple[float, float] | None:
        """(host time [s], uncertainty [s]) of a device stamp, or None before the first round trip."""
        with self._clock_lock:
            try:
                return self.clock.to_host(device_ms), self.clock.uncertainty_s
            except ClockSyncError:
                return None

    def clock_uncertainty_s(self) -> float | None:
        """How far a mapped device stamp can be off now [s], or None before the first round trip."""
        with self._clock_lock:
            try:
                return self.clock.uncertainty_s
            except ClockSyncError:
                return None

    def clock_drift_ppm(self) -> float | None:
        """Estimated drift of the device clock [ppm], or None before the first round trip."""
        with self._clock_lock:
            try:
                return self.clock.drift_ppm
            except ClockSyncError:
                return None

    # ------------------------------------------------------------------------------ connection
    def connect(self) -> p.IdentifyInfo:
        """Open the port, flush it, check the version; start reconnect supervision.

        Raises:
            NotConnected: the port cannot be opened (message names the port and the fix).
            VersionMismatch: the device is not an LSU-GP32 v1 or v2.
        """
        self._closing = False
        self._open()
        try:
            info = self._handshake()
        except Gp32Error:
            self._close_port()
            raise
        if self.reconnect and self._supervisor is None:
            self._supervisor = threading.Thread(target=self._supervise, name="gp32-reconnect", daemon=True)
            self._supervisor.start()
        return info

    def __enter__(self) -> Gp32Client:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self, safe: bool = True) -> None:
        """Switch the laser off and stop motion (``safe``; the laser first: it is the hazard), read the unit's
        status (the laser off, or once more; the stop's ``!DONE`` read before the port goes), then close the port."""
        if safe and self._connected:
            for action in (lambda: self.laser(False), self.stop, self._laser_seen_off):
                try:
                    action()
                except Gp32Error as exc:
                    log.warning("while closing %s: %s", self.port, exc)
        self._closing = True
        self._close_port()
        if self._supervisor is not None:
            self._supervisor.join(timeout=2.0)
            self._supervisor = None

    def _laser_seen_off(self) -> None:
        if self.status().laser_on:
            self.laser(False)

    def _open(self) -> None:
        try:
            ser = serial.Serial(self.port, self.baud, timeout=0.05, write_timeout=1.0)
            ser.reset_input_buffer()
        except (*PORT_ERRORS, ValueError) as exc:
            raise NotConnected(f"cannot open serial port {self.port} at {self.baud} baud ({exc}); check the "
                               "cable/adapter, the port name (lsu doctor lists ports) and permissions") from None
        self._serial = ser
        self._lost.clear()
        while not self._replies.empty():
            self._replies.get_nowait()
        self._reader = threading.Thread(target=self._read_loop, args=(ser,), name="gp32-reader", daemon=True)
        self._reader.start()

    def _handshake(self) -> p.IdentifyInfo:
        info = self.identify()
        if info.version not in p.SUPPORTED_VERSIONS:
            known = " or ".join(f"v{v}" for v in p.SUPPORTED_VERSIONS)
            raise VersionMismatch(f"{self.port} speaks {p.DEVICE_NAME} v{info.version}; this driver needs "
                                  f"{known} (update the firmware or the driver)")
        self.rate_steps_per_s = info.rate_steps_per_s
        self._reset_clock()  # a new connection may be a new power-on: the counter restarted
        if info.version >= 2:
            for _ in range(5):  # a first mapping before any stamped event can arrive
                self.read_clock()
            self._command(p.SetPositionRate(self.position_rate_hz),
                          accept=lambda ok: ok.payload == f"R{self.position_rate_hz}")
        status = self.status()
        self.homed = status.homed
        if status.homed:
            self.track_steps = info.track_steps
        self._connected = True
        self._notify_connection(True, f"connected to {self.port}: {p.DEVICE_NAME} v{info.version}")
        return info

    def _close_port(self) -> None:
        ser, self._serial = self._serial, None
        self._connected = False
        if ser is not None:
            try:
                ser.close()
            except PORT_ERRORS:
                pass
        if self._reader is not None and self._reader is not threading.current_thread():
            self._reader.join(timeout=1.0)

    def _notify_connection(self, up: bool, reason: str) -> None:
        for callback in self._connection_listeners:
            callback(up, reason)

    def _supervise(self) -> None:
        """Reconnect with backoff whenever the reader reports the port lost."""
        while not self._closing:
            if not self._lost.wait(timeout=0.2):
                continue
            if self._closing:
                return
            delay = 0.05
            while not self._closing:
                time.sleep(delay)
                try:
                    self._close_port()
                    self._open()
                    self._handshake()
                    break
                except Gp32Error as exc:
                    log.debug("reconnect to %s failed: %s", self.port, exc)
                    self._close_port()
                    self._lost.set()
                    delay = min(0.5, delay * 2)

    # ------------------------------------------------------------------------------ reader
    def _read_loop(self, ser: serial.Serial) -> None:
        buffer = b""
        while True:
            try:
                # read(n) waits for n bytes or the timeout: ask for what is there (at least 1) so a
                # reply is handed over the moment its bytes arrive, not 50 ms later
                chunk = ser.read(max(1, ser.in_waiting))
            except (*PORT_ERRORS, TypeError, AttributeError) as exc:
                if self._serial is ser and not self._closing:
                    self._port_lost(f"serial port {self.port} vanished ({exc.__class__.__name__})")
                return
            if not ser.is_open:
                return
            buffer += chunk
            while b"\n" in buffer:
                raw, buffer = buffer.split(b"\n", 1)
                if raw.strip(b"\r"):
                    self._dispatch(raw + b"\n")
            if len(buffer) > 2 * p.MAX_REPLY_LINE:  # garbage without newlines: drop it, report once
                self._malformed(p.MalformedLine(buffer, "no line end"))
                buffer = b""

    def _port_lost(self, reason: str) -> None:
        self._connected = False
        self.homed = False
        with self._state:
            self._event_seq += 1
            self._events.append(_PortLostMarker(reason))
            self._state.notify_all()
        self._notify_connection(False, reason + ("; reconnecting" if self.reconnect else ""))
        self._lost.set()

    def _malformed(self, error: p.MalformedLine) -> None:
        self.malformed_lines += 1
        log.warning("%s: %s", self.port, error)
        for callback in self._error_listeners:
            callback(error)

    def _dispatch(self, raw: bytes) -> None:
        arrived = time.time()
        try:
            line = p.parse_line(raw)
        except p.MalformedLine as exc:
            self._malformed(exc)
            return
        if not p.is_event(line):
            self._replies.put((line, arrived))  # type: ignore[arg-type]
            return
        if isinstance(line, p.Boot):
            self.homed = False
            self.position = None
            self._reset_clock()  # the device's counter restarted
        elif isinstance(line, p.HomeDone):
            self.homed = True
            self.track_steps = line.track
            self.position = 0
        elif isinstance(line, p.Done):
            self.position = line.position
            # settling counts from the stop, not the reply: the device's stamp (v2) or the arrival (v1)
            mapped = self.map_device_ms(line.device_ms) if line.device_ms is not None else None
            self.last_stop_s, self.last_stop_uncertainty_s = mapped if mapped else (arrived, None)
        elif isinstance(line, p.Position):
            self.position = line.position
        with self._state:
            self._event_seq += 1
            self._events.append(line)
            del self._events[:-64]
            self._state.notify_all()
        for callback in self._listeners:
            callback(line)

    # ------------------------------------------------------------------------------ commands
    def _command(self, cmd: p.Command, accept: Callable[[p.Ok], bool] = lambda ok: True,
                 retry: bool = True) -> p.Ok:
        """Send ``cmd`` and return its ``OK``; raises on ERR, timeout or a lost port."""
        return self._command_timed(cmd, accept, retry)[0]

    def _command_timed(self, cmd: p.Command, accept: Callable[[p.Ok], bool] = lambda ok: True,
                       retry: bool = True) -> tuple[p.Ok, float, float]:
        """`_command` and the host times that bracket the device's handling of it: (reply, sent, received).

        ``sent`` is the first attempt's: a reply to an earlier attempt, delayed, stays inside the bracket.
        """
        line = p.encode_command(cmd)
        text = line.decode().strip()
        attempts = 1 + (self.retries if retry else 0)
        sent_s: float | None = None
        with self._cmd_lock:
            for attempt in range(attempts):
                ser = self._serial
                if ser is None or self._lost.is_set():
                    raise NotConnected(f"GP32 on {self.port} is not connected; cannot send '{text}'")
                while not self._replies.empty():  # replies that arrived after their command timed out
                    self._replies.get_nowait()
                    self.stale_replies += 1
                if sent_s is None:
                    sent_s = time.time()
                try:
                    ser.write(line)
                    ser.flush()
                except PORT_ERRORS as exc:
                    raise NotConnected(f"writing '{text}' to {self.port} failed ({exc})") from None
                deadline = time.monotonic() + self.command_timeout_s
                while True:
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        break
                    try:
                        reply, received_s = self._replies.get(timeout=min(remaining, 0.05))
                    except queue.Empty:
                        if self._lost.is_set():
                            raise PortLost(f"serial port {self.port} vanished while waiting for '{text}'") from None
                        continue
                    if isinstance(reply, p.Err):
                        if attempt > 0 and reply.code == p.ERR_BUSY and isinstance(cmd, (p.GoTo, p.Home)):
                            return p.Ok(), sent_s, received_s  # our first try was accepted; only its reply was lost
                        raise DeviceError(reply.code, reply.text, text)
                    if accept(reply):
                        return reply, sent_s, received_s
                    self.stale_replies += 1  # an answer to something else: keep waiting for ours
                log.warning("%s: no valid reply to '%s' within %.2f s (attempt %d/%d)", self.port, text,
                            self.command_timeout_s, attempt + 1, attempts)
        raise CommandTimeout(f"GP32 on {self.port} did not answer '{text}' within {self.command_timeout_s:g} s "
                             f"({attempts} attempt(s)); check the cable, the baud rate ({self.baud}) and power")

    @staticmethod
    def _parses(parser: Callable[[str], object]) -> Callable[[p.Ok], bool]:
        """Accept a reply only if its payload parses (a byte lost inside it makes it invalid)."""
        def accept(ok: p.Ok) -> bool:
            try:
                parser(ok.payload)
            except p.MalformedLine:
                return False
            return True
        return accept

    def identify(self) -> p.IdentifyInfo:
        """``?`` -> device name, version, track and speed."""
        reply = self._command(p.Identify(), accept=self._parses(p.parse_identify))
        self.identity = p.parse_identify(reply.payload)
        return self.identity

    def status(self) -> p.StatusInfo:
        """``P`` -> position, laser, moving, sensors, homed (v2: and the device's counter)."""
        return self.status_timed()[0]

    def status_timed(self) -> tuple[p.StatusInfo, float, float]:
        """``P`` and the host times bracketing the device's reading of it: (status, sent, received).

        With a v2 device the reply's stamp feeds `clock`.
        """
        seq = self._event_seq
        reply, sent_s, received_s = self._command_timed(p.Status(), accept=self._parses(p.parse_status))
        self.last_status = status = p.parse_status(reply.payload)
        self._add_clock_sample(sent_s, received_s, status.device_ms)
        if self._event_seq == seq:  # an event after the reply (e.g. !HOME) is newer than this snapshot
            self.homed = status.homed
            self.position = status.position
        return status, sent_s, received_s

    def _need_v2(self, what: str) -> None:
        if self.version < 2:
            raise NotSupported(f"{what} needs GP32 protocol v2; {self.port} speaks v{self.version} "
                               "(update the firmware for timed carriage positions)")

    def read_clock(self) -> int:
        """``T`` (v2): the device's millisecond counter; the round trip feeds `clock`."""
        self._need_v2("reading the device clock (T)")
        reply, sent_s, received_s = self._command_timed(p.ReadClock(), accept=self._parses(p.parse_clock))
        device_ms = p.parse_clock(reply.payload)
        self._add_clock_sample(sent_s, received_s, device_ms)
        return device_ms

    def set_position_rate(self, hz: int) -> None:
        """``R<hz>`` (v2): ``!POS`` events per second during motion (0 = off); kept for reconnects."""
        if hz and self.connected:
            self._need_v2("!POS position events (R)")
        if self.connected and self.version >= 2:
            self._command(p.SetPositionRate(hz), accept=lambda ok: ok.payload == f"R{hz}")
        self.position_rate_hz = hz

    def laser(self, on: bool) -> None:
        """Switch the laser."""
        expected = "L1" if on else "L0"
        self._command(p.Laser(on), accept=lambda ok: ok.payload == expected)

    def set_rate(self, steps_per_s: int) -> None:
        """Step rate for the next motions (20..400 steps/s)."""
        self._command(p.SetRate(steps_per_s), accept=lambda ok: ok.payload == f"S{steps_per_s}")
        self.rate_steps_per_s = steps_per_s

    def set_watchdog(self, ms: int) -> None:
        """Laser watchdog: the laser goes off when no command arrives for ``ms`` (0 = off)."""
        self._command(p.SetWatchdog(ms), accept=lambda ok: ok.payload == f"W{ms}")

    def stop(self) -> None:
        """``X``: stop any motion now (preempts a waiting `move_to` / `home`)."""
        self._command(p.Stop(), accept=lambda ok: ok.payload == "")

    def sweep(self) -> None:
        """``C``: sweep between the sensors until `stop()`."""
        self._command(p.Sweep(), accept=lambda ok: ok.payload == "", retry=False)

    # ------------------------------------------------------------------------------ motions
    def _motion_timeout(self, steps: float) -> float:
        return abs(steps) / max(1, self.rate_steps_per_s) * self.motion_margin + 1.0

    def _wait_event(self, since: int, want: Callable[[p.Line], bool], timeout_s: float, what: str) -> p.Line:
        """Wait for an event after sequence ``since`` that ``want`` accepts."""
        deadline = time.monotonic() + timeout_s
        with self._state:
            while True:
                unseen = self._event_seq - since
                fresh = self._events[max(0, len(self._events) - unseen):] if unseen > 0 else []
                for event in fresh:
                    if isinstance(event, _PortLostMarker):
                        raise PortLost(f"{event.reason} during {what}; the position is unknown: re-home")
                    if isinstance(event, p.Boot):
                        raise DeviceReset(f"GP32 reset (!BOOT) during {what}: position lost, laser off; re-home")
                    if want(event):
                        return event
                since = self._event_seq
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                self._state.wait(timeout=min(remaining, 0.1))
        try:
            self.stop()
        except Gp32Error as exc:
            log.warning("could not stop after a motion timeout: %s", exc)
        raise MotionTimeout(f"{what} did not finish within {timeout_s:.1f} s (stalled motor or broken end "
                            "sensor?); stop sent")

    def _run_motion(self, cmd: p.Command, distance: float, target: int | None, timeout_s: float | None,
                    what: str) -> MotionResult:
        since = self._event_seq
        self._command(cmd, accept=lambda ok: ok.payload == "", retry=isinstance(cmd, p.GoTo))
        sensor: list[int] = []

        def done(event: p.Line) -> bool:
            if isinstance(event, p.EndSensor):
                sensor.append(event.which)
            return isinstance(event, p.Done)

        event = self._wait_event(since, done, timeout_s or self._motion_timeout(distance), what)
        assert isinstance(event, p.Done)
        # one motion at a time: the latest !DONE is this one
        return MotionResult(event.position, target, sensor[-1] if sensor else None, self.last_stop_s,
                            event.device_ms, self.last_stop_uncertainty_s)

    def move_to(self, position: int, timeout_s: float | None = None) -> MotionResult:
        """``G<pos>`` and wait until the carriage stopped; returns where it stopped.

        Raises:
            DeviceError: not homed (ERR 3), out of range (ERR 5), busy (ERR 4).
            MotionTimeout / DeviceReset / PortLost: the motion did not end normally.
        """
        known = self.position if self.homed and self.position is not None else None
        distance = abs(position - known) if known is not None else max(position, self.track_steps or 470)
        return self._run_motion(p.GoTo(position), distance, position, timeout_s, f"move to {position}")

    def step(self, steps: int, timeout_s: float | None = None) -> MotionResult:
        """``M<n>`` and wait until the carriage stopped."""
        start = self.status().position
        return self._run_motion(p.Move(steps), abs(steps), start + steps, timeout_s, f"step of {steps:+d}")

    def home(self, timeout_s: float | None = None) -> int:
        """``H`` and wait for ``!HOME``: returns the measured track length (steps)."""
        since = self._event_seq
        self._command(p.Home(), accept=lambda ok: ok.payload == "")
        longest = 3 * max(self.track_steps, (self.identity.track_steps if self.identity else 0), 470)
        event = self._wait_event(since, lambda e: isinstance(e, p.HomeDone), timeout_s or
                                 self._motion_timeout(longest), "homing")
        assert isinstance(event, p.HomeDone)
        return event.track

    def recent_events(self) -> list[p.Line]:
        """The last events received (newest last), for diagnostics and tests."""
        with self._state:
            return [e for e in self._events if not isinstance(e, _PortLostMarker)]


@dataclass(frozen=True)
class _PortLostMarker:
    """Internal event: the port vanished (wakes motion waiters)."""

    reason: str

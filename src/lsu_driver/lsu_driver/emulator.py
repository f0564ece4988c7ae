"""A GP32 behind a pseudo-terminal: protocol v2 (or v1) with the unit's physics and faults on demand.

Nobody else has the original board, so this is the unit for developers, CI, the demo and the
simulated cameras. It models what the thesis observed (ch. 3.2.3-3.3):

- real-time motion at the step rate, one pulse at a time, with beam-break sensors at both
  ends of a 470-step track;
- an open-loop step counter: above ~180 steps/s the carriage's momentum makes each pulse
  travel a little more than one step, so a full track needs 467 pulses instead of 470 and the
  counter drifts from the true position until the next homing;
- residual vibration after each stop, decaying with a time constant (the reason for
  stop-snap scanning), exposed with the true position for the simulated cameras;
- homing that measures the track, sweep mode, the laser watchdog and ``!BOOT`` on reset;
- a millisecond counter of its own (protocol v2), with an offset (a seeded random start) and a
  drift (+150 ppm by default), like a microcontroller's crystal, so the host's clock mapping is
  exercised; the true host time of every stamped event is kept for tests (`timed_events`);
- faults: garbage bytes, dropped bytes, late replies, reset (also mid-motion), a stalled
  motor and the port vanishing and coming back.

No rclpy here: `emulator_node.py` publishes the truth on ROS.
"""

from __future__ import annotations

import collections
import json
import math
import os
import random
import select
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

from . import protocol as p
from .pty_unit import ControlServer, PtyUnit, close_pty, open_pty

# the thesis: 470 pulses at low speed, 467 at high speed for the same physical track
_HIGH_SPEED_GAIN = 470.0 / 467.0 - 1.0
# lines kept in a unit's log: hours of sweeps at 20 position events/s would otherwise grow it without end
LOG_LINES = 4096


@dataclass
class EmulatorConfig:
    """Physical and firmware parameters of the emulated unit."""

    track_steps: int = 470                      # physical distance between the sensors [true steps]
    rate_steps_per_s: int = 200                 # power-on step rate
    watchdog_ms: int = 2000                     # power-on laser watchdog
    start_position_steps: float = 123.0         # where the carriage sits at power-on
    overstep_threshold_steps_per_s: float = 180.0   # above this rate momentum adds travel per pulse
    overstep_gain_at_max: float = _HIGH_SPEED_GAIN  # extra travel per pulse at the maximum rate
    vibration_amplitude_steps: float = 0.6      # residual displacement right after a stop at 200 steps/s
    vibration_tau_s: float = 0.040              # decay time constant of the residual vibration
    vibration_freq_hz: float = 22.0             # oscillation frequency of the carriage on its belt
    protocol_version: int = p.PROTOCOL_VERSION  # 1: the v1 firmware (no T, R, !POS or stamps)
    clock_start_ms: int | None = None        # device counter at power-on; None: seeded random 32-bit value
    clock_drift_ppm: float = 150.0              # how much faster the device counts than the host
    clock_seed: int = 0                         # seeds the random clock start


@dataclass
class Faults:
    """Fault injection settings (all off by default)."""

    garbage_probability: float = 0.0   # chance per output line that random bytes are sent before it
    drop_probability: float = 0.0      # chance that each output byte is lost
    reply_delay_s: float = 0.0         # every output line is delayed by this much
    stalled: bool = False              # pulses are counted but the carriage does not move
    seed: int = 0                      # seeds the fault RNG, so runs are reproducible


@dataclass
class Truth:
    """What really happens on the unit (SimTruth), for the simulated cameras and tests."""

    stamp_s: float                 # wall-clock instant the position holds at [s since epoch]
    position_steps: float          # true carriage position, vibration excluded
    velocity_steps_per_s: float    # true travel per second (overstep included): position + v * (t - stamp)
    counter_steps: int
    moving: bool
    laser_on: bool
    homed: bool
    stopped_at_s: float            # wall-clock instant of the last stop (its last pulse); 0 while moving
    vibration_amplitude_steps: float
    vibration_tau_s: float
    vibration_freq_hz: float
    boot_count: int

    def displacement_steps(self, t_s: float) -> float:
        """Residual vibration displacement at wall-clock time ``t_s``."""
        if self.moving or self.stopped_at_s <= 0.0 or t_s < self.stopped_at_s:
            return 0.0
        dt = t_s - self.stopped_at_s
        return (self.vibration_amplitude_steps * math.exp(-dt / self.vibration_tau_s)
                * math.cos(2.0 * math.pi * self.vibration_freq_hz * dt))


def overstep_gain(config: EmulatorConfig, rate: float | None) -> float:
    """Travel of one pulse [true steps] at ``rate`` steps/s: 1 below the overstep threshold, rising
    linearly to 1 + ``overstep_gain_at_max`` at the maximum rate; 1 for ``None`` (from rest)."""
    if rate is None:
        return 1.0
    span = p.RATE_MAX - config.overstep_threshold_steps_per_s
    x = (rate - config.overstep_threshold_steps_per_s) / span if span > 0 else 0.0
    return 1.0 + config.overstep_gain_at_max * min(1.0, max(0.0, x))


def sensors_at(config: EmulatorConfig, position: float) -> tuple[bool, bool]:
    """(start, end) beam broken with the carriage at ``position`` [true steps]."""
    eps = 1e-6  # 467 pulses x (470/467) must trip the end sensor despite rounding
    return position <= eps, position >= config.track_steps - eps


def pulse_travel(config: EmulatorConfig, position: float, direction: int, rate: float | None) -> float:
    """The carriage position after one pulse; the sensors at both ends are the mechanical stops."""
    moved = position + direction * overstep_gain(config, rate)
    return min(float(config.track_steps), max(0.0, moved))


def stop_vibration_amplitude(config: EmulatorConfig, rate: float) -> float:
    """Residual vibration right after a stop from ``rate`` steps/s [steps]."""
    return config.vibration_amplitude_steps * rate / 200.0


def mono_to_wall(mono: float) -> float:
    """Wall-clock time (the host time base of ROS stamps) of monotonic instant ``mono``: the motion runs on
    the monotonic clock, stamps are on the wall clock; their offset is read now, so a stepped wall
    clock moves past instants with it.

    The offset is read between two monotonic reads, the tightest of a few brackets: a thread preempted between
    two clock reads on a busy host would put the truth milliseconds off the device's own counter."""
    best_width, offset = math.inf, 0.0
    for _ in range(5):
        before = time.monotonic()
        wall = time.time()
        after = time.monotonic()
        if after - before < best_width:
            best_width, offset = after - before, wall - 0.5 * (before + after)
        if best_width < 20e-6:
            break
    return mono + offset


@dataclass
class _Motion:
    kind: str                    # "goto", "move", "home", "sweep"
    direction: int               # +1 away from the start sensor, -1 towards it
    pulses: int | None        # pulses to send; None = until a sensor (homing, sweep)
    rate: float
    started: float               # monotonic time of the phase start
    sent: int = 0
    phase: str = ""              # homing: "seek", "measure", "return"

    @property
    def last_pulse_at(self) -> float:
        """Monotonic instant of the last pulse sent (pulse n is due at ``started + n / rate``); the start
        before the first."""
        return self.started + self.sent / self.rate


class Gp32Emulator(PtyUnit):
    """The emulated GP32. Use as a context manager, or `start()` / `close()` (the lifecycle of `PtyUnit`).

    ``device_path`` is the pty a client opens; with ``link`` a stable symlink points at it
    (it survives an emulated unplug/replug, while the pty itself changes, like a real USB
    adapter coming back). ``control`` opens a UNIX socket for run-time faults (JSON lines,
    see `handle_control`).
    """

    def __init__(self, config: EmulatorConfig | None = None, faults: Faults | None = None,
                 link: str | None = None, control: str | None = None) -> None:
        super().__init__(link, control)
        self.config = config or EmulatorConfig()
        self.faults = faults or Faults()
        self._lock = threading.RLock()
        self._rng = random.Random(self.faults.seed)
        self._inbuf = b""
        self._outq: list[tuple[float, bytes]] = []
        self._unplugged_until: float | None = None
        # the recent lines in and out, for tests and debugging (bounded: a unit runs for hours)
        self.log: collections.deque[str] = collections.deque(maxlen=LOG_LINES)
        self.boot_count = 0
        self._true = float(self.config.start_position_steps)
        if self.config.protocol_version not in p.SUPPORTED_VERSIONS:
            raise ValueError(f"protocol_version {self.config.protocol_version} is not one of {p.SUPPORTED_VERSIONS}")
        self._clock_start_ms = (self.config.clock_start_ms if self.config.clock_start_ms is not None
                                else random.Random(self.config.clock_seed).randrange(p.MS_WRAP))
        # stamped events with the true host time of the instant they report: {"line", "device_ms", "wall_s"}
        self.timed_events: collections.deque[dict[str, object]] = collections.deque(maxlen=512)
        self._stamp_wall = 0.0
        # exact samples at every motion start, stop, velocity change and laser switch, for the ROS node
        # (`take_truth_events`)
        self._truth_events: collections.deque[Truth] = collections.deque(maxlen=256)
        # called (from the firmware thread) whenever the discrete state changes: motion started or
        # stopped, laser, homing, reset; the ROS node publishes the truth at once instead of polling
        self.on_change: Callable[[], None] | None = None
        self._change_key: tuple = ()
        self._power_on()

    # ----------------------------------------------------------------------------- lifecycle
    def _power_on(self) -> None:
        self.counter = 0
        self.homed = False
        self.laser_on = False
        self.rate = self.config.rate_steps_per_s
        self.watchdog_ms = self.config.watchdog_ms
        self.track_measured = 0
        self._motion: _Motion | None = None
        self._last_command = time.monotonic()
        self._stopped_at_wall = 0.0
        self._vib_amp = 0.0
        self._velocity = 0.0
        self.boot_count += 1
        self._at_start, self._at_end = self._sensors()
        self.pos_rate_hz = 0
        self._next_pos = 0.0
        self._clock_mono0 = time.monotonic()  # the counter restarts at every power-on

    @property
    def v2(self) -> bool:
        return self.config.protocol_version >= 2

    def device_ms(self, mono: float | None = None) -> int:
        """The device's millisecond counter at monotonic time ``mono`` (now by default)."""
        elapsed = (time.monotonic() if mono is None else mono) - self._clock_mono0
        ticks = math.floor(elapsed * 1000.0 * (1.0 + self.config.clock_drift_ppm * 1e-6))
        return (self._clock_start_ms + ticks) % p.MS_WRAP

    def _stamp(self, mono: float | None = None) -> int | None:
        """The counter at monotonic ``mono`` (now by default; None for a v1 unit), with the true host time
        logged by `_send_timed`."""
        if not self.v2:
            return None
        mono = time.monotonic() if mono is None else mono
        self._stamp_wall = mono_to_wall(mono)
        return self.device_ms(mono)

    def _send_timed(self, line: p.Line) -> None:
        """Send an event stamped by `_stamp` and remember when it really happened."""
        self._send(line)
        device_ms = getattr(line, "device_ms", None)
        if device_ms is not None:
            self.timed_events.append({"line": p.encode_line(line).decode().strip(), "device_ms": device_ms,
                                      "wall_s": self._stamp_wall})

    thread_name = "gp32-emulator"

    def _power_up(self) -> None:
        """`start`: the firmware says ``!BOOT`` (its thread answers from then on)."""
        self._send(p.Boot(self.config.protocol_version))

    # ---------------------------------------------------------------------------- physics
    def _sensors(self) -> tuple[bool, bool]:
        return sensors_at(self.config, self._true)

    def _pulse(self, motion: _Motion) -> int | None:
        """One step pulse; returns the sensor (0/1) that tripped in the direction of travel."""
        self.counter += motion.direction
        motion.sent += 1
        if not self.faults.stalled:
            self._true = pulse_travel(self.config, self._true, motion.direction, motion.rate)
        at_start, at_end = self._sensors()
        tripped = None
        if at_start and not self._at_start:
            self._send(p.EndSensor(0))
        if at_end and not self._at_end:
            self._send(p.EndSensor(1))
        self._at_start, self._at_end = at_start, at_end
        if motion.direction < 0 and at_start:
            tripped = 0
        elif motion.direction > 0 and at_end:
            tripped = 1
        return tripped

    def _finish_motion(self, done: bool = True) -> None:
        motion = self._motion
        self._motion = None
        self._velocity = 0.0
        stop_mono = None
        if motion is not None:
            # the carriage stopped at its last pulse, not when this loop noticed
            stop_mono = motion.last_pulse_at
            self._stopped_at_wall = mono_to_wall(stop_mono)
            self._vib_amp = stop_vibration_amplitude(self.config, motion.rate)
            self._truth_events.append(self._truth_at(self._stopped_at_wall))
        if done:
            self._send_timed(p.Done(self.counter, self._stamp(stop_mono)))

    def _velocity_of(self, motion: _Motion) -> float:
        """True travel per second of ``motion``: its pulse rate times the travel of one pulse."""
        return motion.direction * motion.rate * overstep_gain(self.config, motion.rate)

    def _new_phase(self, motion: _Motion) -> None:
        """A motion (or a new phase of one: sweep reversal, homing) starts at ``motion.started``."""
        self._motion = motion
        self._velocity = self._velocity_of(motion)
        self._truth_events.append(self._truth_at(mono_to_wall(motion.started)))

    def _advance(self, now: float) -> None:
        motion = self._motion
        if motion is None:
            return
        due = int((now - motion.started) * motion.rate) - motion.sent
        for _ in range(max(0, due)):
            if motion.pulses is not None and motion.sent >= motion.pulses:
                break
            tripped = self._pulse(motion)
            if motion.kind == "home" and tripped is not None:
                self._homing_phase(tripped, now)
                return
            if motion.kind == "sweep" and tripped is not None:
                # the reversal happens at the tripping pulse; the pulses still due follow on its clock
                self._new_phase(_Motion("sweep", -motion.direction, None, motion.rate, motion.last_pulse_at))
                assert self._motion is not None
                motion = self._motion
                continue
            if tripped is not None:  # a sensor ended a G/M early: the counter has drifted or the target is off-track
                self._finish_motion()
                return
        if motion.pulses is not None and motion.sent >= motion.pulses:
            self._finish_motion()
        elif self.pos_rate_hz and self._motion is not None and now >= self._next_pos:
            # the counter holds since its last pulse: that is the instant it reports
            self._send_timed(p.Position(self.counter, int(self._stamp(motion.last_pulse_at) or 0)))
            period = 1.0 / self.pos_rate_hz
            # one period after the last one; a loop that ran late sends no burst of catch-up events (they would
            # repeat this one's position and stamp: the counter has not moved since)
            self._next_pos += period
            if self._next_pos <= now:
                self._next_pos = now + period

    def _homing_phase(self, tripped: int, now: float) -> None:
        motion = self._motion
        assert motion is not None
        if motion.phase in ("seek", "return") and tripped == 0:
            self.counter = 0
            if motion.phase == "return":
                self.homed = True
                self._finish_motion(done=False)
                self._send_timed(p.HomeDone(self.track_measured, self._stamp(motion.last_pulse_at)))
                return
            self._new_phase(_Motion("home", +1, None, motion.rate, motion.last_pulse_at, phase="measure"))
        elif motion.phase == "measure" and tripped == 1:
            self.track_measured = self.counter
            self._new_phase(_Motion("home", -1, None, motion.rate, motion.last_pulse_at, phase="return"))

    def _check_watchdog(self, now: float) -> None:
        if self.laser_on and self.watchdog_ms > 0 and (now - self._last_command) * 1000.0 > self.watchdog_ms:
            self.laser_on = False
            self._send(p.WatchdogFired())

    # ---------------------------------------------------------------------------- commands
    def _start_motion(self, kind: str, direction: int, pulses: int | None, phase: str = "") -> None:
        self._stopped_at_wall = 0.0
        motion = _Motion(kind, direction, pulses, float(self.rate), time.monotonic(), phase=phase)
        self._new_phase(motion)
        self._next_pos = motion.started  # the first !POS at the start, then one every 1 / R s

    def _handle(self, raw: bytes) -> None:
        self.log.append("< " + raw.decode("ascii", "replace").rstrip())
        self._last_command = time.monotonic()
        try:
            cmd = p.parse_command(raw)
        except p.CommandError as exc:
            code = exc.code
            if not self.v2 and raw.strip().upper()[:1] in (b"T", b"R"):
                code = p.ERR_UNKNOWN  # a v1 firmware has no T or R command at all
            self._send(p.Err(code, p.ERROR_TEXT[code]))
            return
        busy = self._motion is not None
        if not self.v2 and isinstance(cmd, (p.ReadClock, p.SetPositionRate)):
            self._send(p.Err(p.ERR_UNKNOWN, p.ERROR_TEXT[p.ERR_UNKNOWN]))  # what a v1 firmware answers
        elif isinstance(cmd, p.Identify):
            self._send(p.Ok(p.format_identify(p.IdentifyInfo(self.config.protocol_version, self.track_measured or
                                                               self.config.track_steps, self.rate))))
        elif isinstance(cmd, p.Status):
            self._send(p.Ok(p.format_status(p.StatusInfo(self.counter, self.laser_on, busy, self._at_start,
                                                           self._at_end, self.homed, self._stamp()))))
        elif isinstance(cmd, p.ReadClock):
            self._send(p.Ok(f"T{self.device_ms()}"))
        elif isinstance(cmd, p.SetPositionRate):
            self.pos_rate_hz = cmd.hz
            self._send(p.Ok(f"R{cmd.hz}"))
        elif isinstance(cmd, p.Laser):
            self.laser_on = cmd.on
            self._truth_events.append(self._truth_at(mono_to_wall(time.monotonic())))  # the switch's instant
            self._send(p.Ok("L1" if cmd.on else "L0"))
        elif isinstance(cmd, p.SetRate):
            self.rate = cmd.steps_per_s
            self._send(p.Ok(f"S{cmd.steps_per_s}"))
        elif isinstance(cmd, p.SetWatchdog):
            self.watchdog_ms = cmd.ms
            self._send(p.Ok(f"W{cmd.ms}"))
        elif isinstance(cmd, p.Stop):
            self._send(p.Ok())
            self._finish_motion()
        elif busy:
            self._send(p.Err(p.ERR_BUSY, p.ERROR_TEXT[p.ERR_BUSY]))
        elif isinstance(cmd, p.GoTo):
            if not self.homed:
                self._send(p.Err(p.ERR_NOT_HOMED, p.ERROR_TEXT[p.ERR_NOT_HOMED]))
            elif cmd.position > self.track_measured:
                self._send(p.Err(p.ERR_RANGE, p.ERROR_TEXT[p.ERR_RANGE]))
            else:
                self._send(p.Ok())
                delta = cmd.position - self.counter
                if delta == 0:
                    self._finish_motion_now()
                else:
                    self._start_motion("goto", 1 if delta > 0 else -1, abs(delta))
        elif isinstance(cmd, p.Move):
            direction = 1 if cmd.steps > 0 else -1
            target = self.counter + cmd.steps
            if (direction < 0 and self._at_start) or (direction > 0 and self._at_end):
                self._send(p.Err(p.ERR_END_SENSOR, p.ERROR_TEXT[p.ERR_END_SENSOR]))
            elif self.homed and not 0 <= target <= self.track_measured:
                self._send(p.Err(p.ERR_RANGE, p.ERROR_TEXT[p.ERR_RANGE]))
            else:
                self._send(p.Ok())
                self._start_motion("move", direction, abs(cmd.steps))
        elif isinstance(cmd, p.Home):
            self._send(p.Ok())
            self.homed = False
            if self._at_start:  # already on the start sensor: go straight to measuring
                self.counter = 0
                self._start_motion("home", +1, None, phase="measure")
            else:
                self._start_motion("home", -1, None, phase="seek")
        elif isinstance(cmd, p.Sweep):
            self._send(p.Ok())
            self._start_motion("sweep", -1 if self._at_end else 1, None)

    def _finish_motion_now(self) -> None:
        self._send_timed(p.Done(self.counter, self._stamp()))

    # ---------------------------------------------------------------------------- output
    def _send(self, line: p.Line) -> None:
        data = p.encode_line(line)
        self.log.append("> " + data.decode().rstrip())
        if self.faults.garbage_probability and self._rng.random() < self.faults.garbage_probability:
            data = self._garbage(self._rng.randint(1, 12)) + data
        if self.faults.drop_probability:
            data = bytes(b for b in data if self._rng.random() >= self.faults.drop_probability)
        self._outq.append((time.monotonic() + self.faults.reply_delay_s, data))

    def _garbage(self, n: int) -> bytes:
        return bytes(self._rng.randrange(256) for _ in range(n))

    def _flush(self, now: float) -> None:
        while self._outq and self._outq[0][0] <= now:
            _, data = self._outq.pop(0)
            if self._master is not None and data:
                try:
                    os.write(self._master, data)
                except OSError:
                    pass  # nobody can hear us (unplugged); the bytes are lost like on a real line

    # ---------------------------------------------------------------------------- loop
    def _loop(self) -> None:
        while self._running:
            self._iterate()
            self._notify_change()

    def _iterate(self) -> None:
        with self._lock:
            master = self._master
            unplugged_until = self._unplugged_until
        now = time.monotonic()
        if unplugged_until is not None:
            if now >= unplugged_until:
                with self._lock:
                    self._replug()
            else:
                time.sleep(0.005)
            return
        data = b""
        if master is None:  # no pty (closing): nothing to read; wait instead of spinning
            time.sleep(0.005)
        else:
            try:
                readable, _, _ = select.select([master], [], [], self._idle_timeout(now))
                data = os.read(master, 4096) if readable else b""
            except (OSError, ValueError):
                pass  # the pty closed under us: like a line with nothing on it
        with self._lock:
            if data:
                self._inbuf += data
                while b"\n" in self._inbuf:
                    line, self._inbuf = self._inbuf.split(b"\n", 1)
                    if line.strip(b"\r"):
                        self._handle(line + b"\n")
                if len(self._inbuf) > 4 * p.MAX_LINE:  # no newline for too long: answer and resync
                    self._inbuf = b""
                    self._send(p.Err(p.ERR_TOO_LONG, p.ERROR_TEXT[p.ERR_TOO_LONG]))
            now = time.monotonic()
            self._advance(now)
            self._check_watchdog(now)
        # a change is told before the replies that acknowledge it leave: a reply starts the chain (driver,
        # coordinator, capture) that ends in a simulated frame, which must already know of the change
        self._notify_change()
        with self._lock:
            self._flush(now)

    def _idle_timeout(self, now: float) -> float:
        """How long the loop may wait for host bytes before something else is due [s].

        Until the next step pulse or !POS while the carriage moves, the next delayed reply or the
        watchdog, at most 10 ms: host bytes end the wait at once, and a pulse's instant is its
        schedule's (``_Motion.last_pulse_at``), so waking only when something is due changes no
        stamp and spends no CPU in between.
        """
        with self._lock:
            due = now + 0.01
            motion = self._motion
            if motion is not None:
                # the next pulse (its instant is fixed by the schedule, not by when this loop runs) and !POS
                due = min(due, motion.started + (motion.sent + 1) / motion.rate)
                if self.pos_rate_hz:
                    due = min(due, self._next_pos)
            if self._outq:
                due = min(due, self._outq[0][0])
            if self.laser_on and self.watchdog_ms > 0:
                due = min(due, self._last_command + self.watchdog_ms / 1000.0)
        return min(0.01, max(0.0005, due - now))

    def _notify_change(self) -> None:
        """Call `on_change` when what `truth` reports has changed other than by steady motion."""
        with self._lock:
            key = (self._motion is not None, self._velocity, self.laser_on, self.homed, self.boot_count,
                   self._stopped_at_wall, self.faults.stalled, self._unplugged_until is not None)
            changed, self._change_key = key != self._change_key, key
        if changed and self.on_change is not None:
            self.on_change()

    # ---------------------------------------------------------------------------- truth / faults
    def truth(self) -> Truth:
        """The physical state now: while moving, stamped at the last pulse (the instant its position holds
        at; the carriage goes on at its velocity from there), at rest stamped now."""
        with self._lock:
            return self._truth_at(mono_to_wall(self._motion.last_pulse_at if self._motion is not None
                                               else time.monotonic()))

    def take_truth_events(self) -> list[Truth]:
        """The exact samples at the motion starts, stops, velocity changes and laser switches since the last call,
        oldest first."""
        with self._lock:
            events = list(self._truth_events)
            self._truth_events.clear()
            return events

    def _truth_at(self, stamp_s: float) -> Truth:
        """The state as it is now, stamped ``stamp_s`` (wall clock): the instant it holds at."""
        with self._lock:
            moving = self._motion is not None
            return Truth(
                stamp_s=stamp_s, position_steps=self._true,
                velocity_steps_per_s=self._velocity if not self.faults.stalled else 0.0,
                counter_steps=self.counter, moving=moving, laser_on=self.laser_on, homed=self.homed,
                stopped_at_s=0.0 if moving else self._stopped_at_wall,
                vibration_amplitude_steps=0.0 if moving else self._vib_amp,
                vibration_tau_s=self.config.vibration_tau_s, vibration_freq_hz=self.config.vibration_freq_hz,
                boot_count=self.boot_count)

    def reset(self) -> None:
        """Power-cycle the firmware: motion stops where it is, laser off, position lost, ``!BOOT``."""
        with self._lock:
            self._power_on()
            self._send(p.Boot(self.config.protocol_version))

    def unplug(self, duration_s: float) -> None:
        """The port vanishes for ``duration_s`` (pty closed, link removed), then a new one appears."""
        with self._lock:
            self._outq.clear()
            self._close_pty()
            self._motion = None
            self.laser_on = False  # the adapter powered the board: it went down with it
            self._unplugged_until = time.monotonic() + duration_s

    def _replug(self) -> None:
        self._unplugged_until = None
        self._power_on()
        self._open_pty()
        self._send(p.Boot(self.config.protocol_version))

    def inject_garbage(self, n_bytes: int) -> None:
        """Send ``n_bytes`` random bytes followed by a newline right now."""
        with self._lock:
            self._outq.append((time.monotonic(), self._garbage(n_bytes) + b"\n"))

    def set_faults(self, **changes: object) -> None:
        """Change fault settings at run time (names of `Faults`)."""
        with self._lock:
            for name, value in changes.items():
                if not hasattr(self.faults, name):
                    raise ValueError(f"unknown fault '{name}' (known: {', '.join(asdict(self.faults))})")
                setattr(self.faults, name, type(getattr(self.faults, name))(value))

    def clear_faults(self) -> None:
        """All faults off."""
        with self._lock:
            self.faults = Faults(seed=self.faults.seed)

    # ---------------------------------------------------------------------------- control channel
    def handle_control(self, request: dict[str, object]) -> dict[str, object]:
        """One control request (also what the UNIX socket speaks, one JSON object per line).

        ``{"fault": "garbage", "bytes": 20}``, ``{"fault": "garbage_rate", "probability": 0.2}``,
        ``{"fault": "drop", "probability": 0.1}``, ``{"fault": "late", "delay_ms": 800}``,
        ``{"fault": "reset"}``, ``{"fault": "stall", "on": true}``,
        ``{"fault": "unplug", "duration_s": 1.0}``, ``{"fault": "clear"}``, ``{"get": "truth"}``,
        ``{"get": "events"}`` (the stamped events with the true host time of what they report).
        """
        try:
            if request.get("get") == "truth":
                return {"ok": True, "truth": asdict(self.truth())}
            if request.get("get") == "events":
                with self._lock:
                    return {"ok": True, "events": list(self.timed_events)}
            fault = request.get("fault")
            if fault == "garbage":
                self.inject_garbage(int(str(request.get("bytes", 16))))
            elif fault == "garbage_rate":
                self.set_faults(garbage_probability=request.get("probability", 0.2))
            elif fault == "drop":
                self.set_faults(drop_probability=request.get("probability", 0.1))
            elif fault == "late":
                self.set_faults(reply_delay_s=float(request.get("delay_ms", 500)) / 1000.0)  # type: ignore[arg-type]
            elif fault == "reset":
                self.reset()
            elif fault == "stall":
                self.set_faults(stalled=bool(request.get("on", True)))
            elif fault == "unplug":
                self.unplug(float(request.get("duration_s", 1.0)))  # type: ignore[arg-type]
            elif fault == "clear":
                self.clear_faults()
            else:
                return {"ok": False, "error": f"unknown request {request!r}; see lsu gp32 fault --help"}
        except (TypeError, ValueError) as exc:
            return {"ok": False, "error": str(exc)}
        return {"ok": True}


def send_control(path: str, request: dict[str, object], timeout_s: float = 5.0) -> dict[str, object]:
    """Send one request to an emulator's control socket and return its answer."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout_s)
        sock.connect(path)
        sock.sendall((json.dumps(request) + "\n").encode())
        data = b""
        while not data.endswith(b"\n"):
            chunk = sock.recv(4096)
            if not chunk:
                break
            data += chunk
    return json.loads(data)


__all__ = ["ControlServer", "EmulatorConfig", "Faults", "Gp32Emulator", "Truth", "close_pty", "open_pty",
           "overstep_gain", "pulse_travel", "send_control", "sensors_at", "stop_vibration_amplitude"]

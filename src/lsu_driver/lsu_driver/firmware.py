"""The unit's own firmware (firmware/gp32) running in the ucsim HC08 simulator behind a pty.

`Gp32Firmware` looks to a client exactly like `Gp32Emulator`: a pty (with a stable symlink)
speaking protocol v2. Behind it, ``shc08`` executes the firmware image built with SDCC and this
module is the board around the microcontroller:

- it owns the simulator interface's input and output (two ptys, see ``hal_sim.c`` for the byte
  codes) and forwards the serial bytes both ways;
- it is the clock: wall-clock time goes to the firmware as tick bytes every ~2 ms, so the
  firmware's time is real time (ucsim itself runs the HC08 faster than real time);
- it is the mechanics: the step and direction pins move a carriage with the emulator's physics
  (`emulator.pulse_travel`, overstep above 180 steps/s, vibration after a stop), and the
  end-sensor pins follow the carriage (near the ends the firmware waits for them after each pulse,
  elsewhere the board grants pulses that cannot reach a sensor); the laser pin is reported in
  `truth`.

Each pulse carries the firmware millisecond it was sent in, so the rate that decides the
overstep is measured in firmware time (the mean of the last four intervals) however late the
board reads it; the first pulse from rest has no momentum (gain 1).
What the board knows of the firmware's state (counter, homed, moving) it reads from the pulses
and from the firmware's own ``!DONE``/``!HOME``/``!BOOT`` lines, as a logic analyser would.

No rclpy here: `emulator_node.py` publishes the truth on ROS for either unit.
"""

from __future__ import annotations

import collections
import ctypes
import os
import random
import re
import select
import shutil
import signal
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

from . import protocol as p
from .emulator import (
    LOG_LINES,
    EmulatorConfig,
    Faults,
    Truth,
    overstep_gain,
    pulse_travel,
    sensors_at,
    stop_vibration_amplitude,
)
from .pty_unit import PtyUnit, open_pty

# byte codes of the simulator link (firmware/gp32/hal_sim.c)
IN_TICK, IN_SENSORS, IN_HIGH_BYTE, IN_CREDIT = 0x80, 0xC0, 0xC4, 0xC5
MAX_CREDIT = 127
OUT_PINS = 0x80
PIN_STEP, PIN_DIR, PIN_LASER = 0x01, 0x02, 0x04
MAX_TICK_MS = 63
TICK_PERIOD_S = 0.002         # how often the board passes wall-clock time on
SIF_ADDRESS = 0x7FFF          # the simulator interface's mailbox (hal_sim.c SIF_ADDRESS)

# the GP32's memory (MC68HC908GP32 data sheet): 512 B RAM at 0x40, 32 KB flash at 0x8000 (user flash
# ends at 0xfdff; the monitor ROM and the vectors follow)
GP32_RAM = (0x0040, 0x0240)
GP32_FLASH_BYTES = 32 * 1024
STACK_RESERVE_BYTES = 64      # the deepest call chain plus an interrupt frame, with room to spare

_RATE_WINDOW = 4              # pulse intervals averaged for the rate that decides the overstep
_FROM_REST_MS = 60            # a pulse later than this after the previous one starts from rest (20 steps/s = 50 ms)


def _die_with_parent_thread() -> None:
    """In the simulator's child process: SIGKILL when the board's thread ends. ucsim spins while it
    waits for input, so an orphan would take a core for ever. (The board starts it from its own
    thread, which lives as long as the board.)"""
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG


class FirmwareUnavailable(RuntimeError):
    """The toolchain or the image is missing, or the simulator failed; the message says what to do."""


def firmware_dir() -> Path:
    """``firmware/gp32`` of this checkout (editable install), or of ``$LSU_WORKSPACE``."""
    root = Path(os.environ["LSU_WORKSPACE"]) if os.environ.get("LSU_WORKSPACE") else \
        Path(__file__).resolve().parents[3]
    return root / "firmware" / "gp32"


def toolchain_missing() -> str | None:
    """Why the firmware cannot be built and run here, or None when sdcc, shc08 and make exist."""
    missing = [tool for tool in ("sdcc", "shc08", "make") if shutil.which(tool) is None]
    if not missing:
        return None
    return (f"{', '.join(missing)} not found: install the Debian packages sdcc and sdcc-ucsim "
            "(make setup does), then try again")


@dataclass(frozen=True)
class ImageSize:
    """Memory use of a linked image, from the linker's map file."""

    flash_bytes: int          # code, constants, initialisers and interrupt vectors
    ram_bytes: int            # static variables (zero page + the rest); the stack comes on top
    ram_end: int              # first address after the static variables
    stack_bytes: int          # what is left for the stack below the top of RAM

    def check(self) -> None:
        """Raise FirmwareUnavailable when the image does not fit the GP32."""
        if self.flash_bytes > GP32_FLASH_BYTES:
            raise FirmwareUnavailable(f"firmware needs {self.flash_bytes} B of flash, the GP32 has {GP32_FLASH_BYTES}")
        if self.stack_bytes < STACK_RESERVE_BYTES:
            raise FirmwareUnavailable(
                f"firmware variables end at 0x{self.ram_end:04x}: {self.stack_bytes} B left for the stack, "
                f"needs {STACK_RESERVE_BYTES}; shrink the buffers in hal_gp32.c or lsu.c")


_AREA = re.compile(r"^(\S+)\s+([0-9A-Fa-f]{8})\s+([0-9A-Fa-f]{8})\s+=\s+(\d+)\. bytes \(([^)]*)\)", re.M)
_RAM_AREAS = ("DSEG", "OSEG", "XSEG", "XISEG")


def image_size(map_file: Path) -> ImageSize:
    """Flash and RAM use from an SDCC/sdld ``.map`` file."""
    flash = ram = 0
    ram_end = GP32_RAM[0]
    for name, addr, _size, size_dec, attrs in _AREA.findall(map_file.read_text()):
        size = int(size_dec)
        if name in _RAM_AREAS:
            ram += size
            ram_end = max(ram_end, int(addr, 16) + size)
        elif "CODE" in attrs.split(",") or name.startswith("CODEIVT") or name == "XINIT":
            flash += size
    return ImageSize(flash, ram, ram_end, GP32_RAM[1] - ram_end)


@dataclass(frozen=True)
class Build:
    """What `build` produced."""

    directory: Path
    s19: Path                 # for the real GP32 (monitor-mode loader)
    hex: Path                 # the same as Intel HEX
    sim_image: Path           # with the simulator HAL, for shc08
    size: ImageSize           # of the real image
    sim_size: ImageSize


def build(source: Path | None = None, out: Path | None = None, baud: int = 9600) -> Build:
    """Compile the firmware with SDCC (``make`` in firmware/gp32) and check that it fits the GP32.

    Raises:
        FirmwareUnavailable: toolchain missing, compile error (with the compiler's output), too big.
    """
    reason = toolchain_missing()
    if reason:
        raise FirmwareUnavailable(reason)
    source = source or firmware_dir()
    if not (source / "Makefile").exists():
        raise FirmwareUnavailable(f"no firmware sources in {source}; set LSU_WORKSPACE to the checkout")
    out = out or source / "build"
    result = subprocess.run(["make", "-C", str(source), f"BUILD={out}", f"BAUD={baud}"], capture_output=True,
                            text=True)
    if result.returncode != 0:
        raise FirmwareUnavailable(f"firmware build failed:\n{result.stdout}{result.stderr}")
    made = Build(out, out / "lsu-gp32.s19", out / "lsu-gp32.ihx", out / "lsu-gp32-sim.ihx",
                 image_size(out / "lsu-gp32.map"), image_size(out / "lsu-gp32-sim.map"))
    made.size.check()
    made.sim_size.check()
    return made


@dataclass(frozen=True)
class StepRecord:
    """One step pulse as the board saw it."""

    wall_s: float             # monotonic time the board received it
    firmware_ms: int          # the firmware's millisecond it belongs to
    direction: int


class Gp32Firmware(PtyUnit):
    """The firmware in shc08 plus the host-side board. Use as a context manager, or `start()` / `close()` (the
    lifecycle of `PtyUnit`).

    The same surface as `Gp32Emulator` for clients, tests and the truth node: ``device_path``,
    ``link``, ``control_path``, `truth`, `reset`, ``log``, ``on_change``, `handle_control`.
    Faults: garbage bytes, a stalled motor and reset; the emulator covers the rest.
    """

    def __init__(self, config: EmulatorConfig | None = None, faults: Faults | None = None,
                 link: str | None = None, control: str | None = None, image: Path | None = None) -> None:
        super().__init__(link, control)
        self.config = config or EmulatorConfig()
        self.faults = faults or Faults()
        self.image = Path(image) if image else firmware_dir() / "build" / "lsu-gp32-sim.ihx"
        self._rng = random.Random(self.faults.seed)
        self._lock = threading.RLock()
        self._sim: subprocess.Popen | None = None
        self._sim_fds: list[int] = []
        self._sim_in = self._sim_out = -1
        self.log: collections.deque[str] = collections.deque(maxlen=LOG_LINES)  # the recent lines, as the emulator's
        self.boot_count = 0
        self.steps: collections.deque[StepRecord] = collections.deque(maxlen=4096)
        self.on_change: Callable[[], None] | None = None
        self._position = float(self.config.start_position_steps)
        self._booted = threading.Event()  # the firmware's !BOOT line since the last power-on
        self._power_request = threading.Event()  # (re)start the simulator, from the board's own thread
        self._line = b""
        self._host_line = b""
        self._reset_board_state()

    def _reset_board_state(self) -> None:
        self._fw_ms = 0                   # milliseconds sent to the firmware
        self._stamp: list[int] = []       # millisecond bytes of the pulse being read
        self._credit = 0                  # pulses the firmware sends before it waits for the sensors
        self._in_stamp = False
        self._t0 = time.monotonic()
        self._pins = 0
        self._sensors = self._sensor_bits()
        self._counter = 0
        self._homed = False
        self._moving = False
        self._rate: float | None = None
        self._stopped_at_wall = 0.0
        self._vib_amp = 0.0
        self._recent_ms: collections.deque[int] = collections.deque(maxlen=_RATE_WINDOW + 1)
        self._pending: collections.deque[bytes] = collections.deque()  # host command lines not answered yet
        self._change_key: tuple = ()

    # ----------------------------------------------------------------------------- lifecycle
    thread_name = "gp32-board"

    def _check_startable(self) -> None:
        """`start` needs shc08 and the firmware image."""
        reason = toolchain_missing()
        if reason:
            raise FirmwareUnavailable(reason)
        if not self.image.exists():
            raise FirmwareUnavailable(f"no firmware image {self.image}: run `lsu gp32 firmware build` first")

    def _power_up(self) -> None:
        """`start`: the board's thread starts the simulator with the image; the firmware sends ``!BOOT``."""
        self._power_request.set()

    def _release(self) -> None:
        """`close`: the simulator stops and its link closes (the board's thread has stopped)."""
        self._stop_sim()
        self._close_sim_link()

    def _close_sim_link(self) -> None:
        for fd in self._sim_fds:
            try:
                os.close(fd)
            except OSError:
                pass  # already closed: nothing left to release
        self._sim_fds = []

    def _stop_sim(self) -> None:
        if self._sim is not None:
            self._sim.kill()
            self._sim.wait(timeout=5)
            if self._sim.stdin is not None:
                self._sim.stdin.close()
            self._sim = None
            self._sim_stderr.close()

    def _power_on(self) -> None:
        """(Re)start the simulator: the firmware starts from its reset vector with the pins low."""
        with self._lock:
            self._stop_sim()
            # a fresh link: bytes the old instance left unread (ticks!) must not reach the new one
            self._close_sim_link()
            in_master, in_slave, in_path = open_pty(None)
            out_master, out_slave, out_path = open_pty(None)
            self._sim_fds = [in_master, in_slave, out_master, out_slave]
            self._sim_in, self._sim_out = in_master, out_master
            self._reset_board_state()
            self.boot_count += 1
            self._booted.clear()
            self._line = b""
            init = firmware_dir() / "ucsim.cmd"
            cmd = ["shc08", "-C", str(init), "-I", f"if=rom[0x{SIF_ADDRESS:x}],in={in_path},out={out_path}",
                   "-G", str(self.image)]
            # stdin stays open (ucsim's console quits on end of input); stderr to a file, never a pipe
            # that could fill up and stop the simulator
            self._sim_stderr = tempfile.TemporaryFile()
            self._sim = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL,
                                         stderr=self._sim_stderr, start_new_session=True,
                                         preexec_fn=_die_with_parent_thread)
            self._write_sim(bytes([IN_SENSORS | self._sensors]))

    # ---------------------------------------------------------------------------- physics
    def _sensor_bits(self) -> int:
        at_start, at_end = sensors_at(self.config, self._position)
        return (1 if at_start else 0) | (2 if at_end else 0)

    def _measured_rate(self) -> float | None:
        """Steps/s of the running pulse train in firmware time; None for a pulse from rest."""
        times = [t for t in self._recent_ms]
        if len(times) < 2 or times[-1] - times[-2] > _FROM_REST_MS:
            return None
        n = 1
        while n < len(times) - 1 and times[-1 - n] - times[-2 - n] <= _FROM_REST_MS:
            n += 1
        return 1000.0 * n / max(1, times[-1] - times[-1 - n])

    def _step(self, now: float, stamp: int) -> None:
        """A rising edge on the step pin in firmware millisecond ``stamp`` (14 bits)."""
        direction = 1 if self._pins & PIN_DIR else -1
        fw_ms = self._fw_ms - ((self._fw_ms - stamp) % (1 << 14))  # unwrap: not after what was sent
        self._recent_ms.append(fw_ms)
        rate = self._measured_rate()
        self._rate = rate if rate is not None else self._rate
        if not self.faults.stalled:
            self._position = pulse_travel(self.config, self._position, direction, rate)
        self._counter += direction
        self._moving = True
        self._stopped_at_wall = 0.0
        self.steps.append(StepRecord(now, fw_ms, direction))
        self._sensors = self._sensor_bits()
        if self._credit > 0:  # granted: this pulse cannot have changed the sensors
            self._credit -= 1
            return
        self._credit = self._pulse_credit()
        self._write_sim(bytes([IN_CREDIT, self._credit, IN_SENSORS | self._sensors]))  # the firmware waits for it

    def _pulse_credit(self) -> int:
        """Pulses that cannot change the sensors from here, in either direction at any rate."""
        if self._sensors:
            return 0
        room = min(self._position, self.config.track_steps - self._position)
        return max(0, min(MAX_CREDIT, int((room - 1e-6) / overstep_gain(self.config, p.RATE_MAX)) - 1))

    def _stopped(self) -> None:
        if self._moving:
            self._moving = False
            self._stopped_at_wall = time.time()
            self._vib_amp = stop_vibration_amplitude(self.config, self._rate or float(self.config.rate_steps_per_s))

    # ------------------------------------------------------------------------------ bytes
    def _write_sim(self, data: bytes) -> None:
        try:
            os.write(self._sim_in, data)
        except OSError:
            pass  # no simulator running (power-cycling or exited, which the loop reports): the pins are dead

    def _from_host(self, data: bytes) -> None:
        """Client bytes to the firmware's SCI (bytes >= 0x80 escaped, see hal_sim.c)."""
        self._host_line += data
        while b"\n" in self._host_line:
            line, self._host_line = self._host_line.split(b"\n", 1)
            self.log.append("< " + line.decode("ascii", "replace").rstrip())
            if line.strip(b"\r"):
                self._pending.append(line.strip().upper())
        out = bytearray()
        for b in data:
            if b >= 0x80:
                out += bytes([IN_HIGH_BYTE, b & 0x7F])
            else:
                out.append(b)
        self._write_sim(bytes(out))

    def _from_sim(self, data: bytes, now: float) -> None:
        """Handle firmware output: serial bytes to the host, pin changes to the mechanics."""
        sci = bytearray()
        for b in data:
            if self._in_stamp:
                self._stamp.append(b)
                if len(self._stamp) == 2:
                    self._in_stamp = False
                    self._step(now, self._stamp[0] | self._stamp[1] << 7)
            elif b & OUT_PINS:
                rising = (b & PIN_STEP) and not (self._pins & PIN_STEP)
                self._pins = b & 0x7F
                if rising:
                    self._in_stamp, self._stamp = True, []
            else:
                sci.append(b)
                self._line += bytes([b])
                if b == 0x0A:
                    self._firmware_line(self._line)
                    self._line = b""
        if sci and self._master is not None:
            try:
                os.write(self._master, bytes(sci))
            except OSError:
                pass  # nobody has the port open: the bytes are lost like on a real line

    def _firmware_line(self, raw: bytes) -> None:
        self.log.append("> " + raw.decode("ascii", "replace").rstrip())
        try:
            line = p.parse_line(raw)
        except p.MalformedLine:
            return
        if isinstance(line, p.Done):
            self._counter = line.position
            self._stopped()
        elif isinstance(line, p.HomeDone):
            self._counter, self._homed = 0, True
            self._stopped()
        elif isinstance(line, p.Boot):
            self._pending.clear()
            self._booted.set()
        elif not p.is_event(line) and self._pending:
            command = self._pending.popleft()
            if command == b"H" and isinstance(line, p.Ok):  # homing started: the old zero is void
                self._homed = False
            elif command == b"X" and isinstance(line, p.Ok):  # stopped before it answers; !DONE follows
                self._stopped()

    # ------------------------------------------------------------------------------- loop
    def _loop(self) -> None:
        while self._running:
            try:
                if self._power_request.is_set():
                    self._power_request.clear()
                    self._power_on()
                self._iterate()
            except OSError:
                if self._running:
                    time.sleep(0.01)
            self._notify_change()

    def _iterate(self) -> None:
        with self._lock:
            next_tick = self._t0 + self._fw_ms / 1000.0 + TICK_PERIOD_S
        timeout = max(0.0, next_tick - time.monotonic())
        with self._lock:
            fds = [fd for fd in (self._master, self._sim_out) if fd is not None and fd >= 0]
        readable, _, _ = select.select(fds, [], [], timeout)
        with self._lock:
            if self._sim_out not in fds:
                return  # power-cycled meanwhile: the link changed
            now = time.monotonic()
            if self._master is not None and self._master in readable:
                try:
                    data = os.read(self._master, 4096)
                except OSError:
                    data = b""
                if data:
                    self._from_host(data)
            if self._sim_out in readable:
                self._from_sim(os.read(self._sim_out, 4096), now)
            due = int((now - self._t0) * 1000.0) - self._fw_ms
            while due > 0:
                n = min(due, MAX_TICK_MS)
                self._write_sim(bytes([IN_TICK | n]))
                self._fw_ms += n
                due -= n
            if self._sim is not None and self._sim.poll() is not None and self._running:
                self._sim_stderr.seek(0)
                err = self._sim_stderr.read().decode(errors="replace")
                self.log.append(f"! simulator exited ({self._sim.returncode}): {err.strip()[-300:]}")
                self._sim = None

    def _notify_change(self) -> None:
        with self._lock:
            key = (self._moving, self._pins & (PIN_DIR | PIN_LASER), self._homed, self.boot_count,
                   self._stopped_at_wall, self.faults.stalled)
            changed, self._change_key = key != self._change_key, key
        if changed and self.on_change is not None:
            self.on_change()

    # ---------------------------------------------------------------------------- truth / faults
    def truth(self) -> Truth:
        """The physical state right now (firmware state as seen on its pins and lines)."""
        with self._lock:
            moving = self._moving
            direction = 1 if self._pins & PIN_DIR else -1
            rate = self._rate or float(self.config.rate_steps_per_s)
            return Truth(
                stamp_s=time.time(), position_steps=self._position,
                velocity_steps_per_s=direction * rate if moving and not self.faults.stalled else 0.0,
                counter_steps=self._counter, moving=moving, laser_on=bool(self._pins & PIN_LASER),
                homed=self._homed, stopped_at_s=0.0 if moving else self._stopped_at_wall,
                vibration_amplitude_steps=0.0 if moving else self._vib_amp,
                vibration_tau_s=self.config.vibration_tau_s, vibration_freq_hz=self.config.vibration_freq_hz,
                boot_count=self.boot_count)

    def reset(self, carriage_at: float | None = None, wait_s: float = 10.0) -> None:
        """Power-cycle the microcontroller: the simulator restarts the image and this returns once
        the firmware has sent ``!BOOT``. The carriage stays where it is, or is put at
        ``carriage_at`` [steps] (a test starting from a known place)."""
        with self._lock:
            if carriage_at is not None:
                self._position = float(carriage_at)
            self._booted.clear()
            self._power_request.set()
        if not self._booted.wait(wait_s):
            raise FirmwareUnavailable(f"the firmware did not boot within {wait_s:g} s in the simulator; "
                                      f"last lines: {list(self.log)[-5:]}")

    def power_off(self) -> None:
        """Unpower the microcontroller until the next `reset`: the simulator stops (no replies, the
        pins go low). Tests keep one board per module and switch the simulator off between their
        tests, since a running ucsim takes a host core."""
        with self._lock:
            self._stop_sim()
            self._close_sim_link()
            self._sim_in = self._sim_out = -1
            self._pins = 0
            self._stopped()

    def wait_booted(self, timeout_s: float = 10.0) -> bool:
        """True once the firmware has sent ``!BOOT`` after the last power-on."""
        return self._booted.wait(timeout_s)

    def inject_garbage(self, n_bytes: int) -> None:
        """Random bytes and a newline on the line to the host right now (a noisy cable)."""
        with self._lock:
            if self._master is not None:
                os.write(self._master, bytes(self._rng.randrange(256) for _ in range(n_bytes)) + b"\n")

    def set_faults(self, **changes: object) -> None:
        """Change fault settings (``stalled`` acts on the board; the byte faults are the emulator's)."""
        with self._lock:
            for name, value in changes.items():
                if name != "stalled":
                    raise ValueError(f"the firmware unit simulates the fault 'stalled' only, not '{name}'; "
                                     "use the emulator (unit:=emulator) for serial-line faults")
                self.faults.stalled = bool(value)

    def clear_faults(self) -> None:
        with self._lock:
            self.faults = Faults(seed=self.faults.seed)

    def handle_control(self, request: dict[str, object]) -> dict[str, object]:
        """The control requests of `Gp32Emulator.handle_control` that the firmware unit supports:
        truth, garbage, reset, stall, clear."""
        try:
            if request.get("get") == "truth":
                return {"ok": True, "truth": asdict(self.truth())}
            fault = request.get("fault")
            if fault == "garbage":
                self.inject_garbage(int(str(request.get("bytes", 16))))
            elif fault == "reset":
                self.reset()
            elif fault == "stall":
                self.set_faults(stalled=bool(request.get("on", True)))
            elif fault == "clear":
                self.clear_faults()
            else:
                return {"ok": False, "error": f"the firmware unit does not simulate {request!r}; it supports "
                                              "garbage, reset, stall, clear and truth (the emulator has all)"}
        except (TypeError, ValueError) as exc:
            return {"ok": False, "error": str(exc)}
        return {"ok": True}

    def step_jitter_ms(self, rate: float, firmware_time: bool = False) -> tuple[float, int]:
        """Largest deviation of a pulse interval from 1/rate [ms] over the pulse trains of the
        recorded steps (gaps longer than a stop excluded), and the number of intervals: as the board
        received them (wall clock), or in the firmware's own milliseconds (``firmware_time``)."""
        nominal = 1000.0 / rate
        worst, n = 0.0, 0
        steps = list(self.steps)
        for a, b in zip(steps, steps[1:]):
            if b.firmware_ms - a.firmware_ms > _FROM_REST_MS or a.direction != b.direction:
                continue
            interval = b.firmware_ms - a.firmware_ms if firmware_time else (b.wall_s - a.wall_s) * 1000.0
            worst = max(worst, abs(interval - nominal))
            n += 1
        return worst, n


__all__ = ["Build", "FirmwareUnavailable", "Gp32Firmware", "ImageSize", "StepRecord", "build", "firmware_dir",
           "image_size", "toolchain_missing"]

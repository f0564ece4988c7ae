"""The lifecycle both simulated units share (`lsu_driver.pty_unit.PtyUnit`): start opens, close undoes, in order."""

from __future__ import annotations

import json
import os
import select
import socket
import time

import pytest

from lsu_driver.emulator import Gp32Emulator
from lsu_driver.firmware import FirmwareUnavailable, Gp32Firmware
from lsu_driver.pty_unit import PtyUnit


class EchoUnit(PtyUnit):
    """A unit that sends back every byte it reads, and records the order of its lifecycle's steps."""

    thread_name = "echo-unit"

    def __init__(self, link: str | None = None, control: str | None = None) -> None:
        super().__init__(link, control)
        self.steps: list[str] = []

    def _power_up(self) -> None:
        self.steps.append(f"power_up (pty open: {self._master is not None}, thread: {self._thread is not None})")

    def _loop(self) -> None:
        while self._running:
            readable, _, _ = select.select([self._master], [], [], 0.01)
            if readable:
                os.write(self._master, os.read(self._master, 64))
        self.steps.append("loop ended")

    def handle_control(self, request: dict[str, object]) -> dict[str, object]:
        return {"ok": True, "echo": request}

    def _release(self) -> None:
        self.steps.append(f"release (pty open: {self._master is not None})")


def _read(fd: int, n: int, timeout_s: float = 5.0) -> bytes:
    deadline, data = time.monotonic() + timeout_s, b""
    while len(data) < n and time.monotonic() < deadline:
        try:
            data += os.read(fd, n - len(data))
        except BlockingIOError:
            time.sleep(0.005)
    return data


def test_start_opens_pty_link_thread_and_socket_and_close_undoes_them_in_reverse(tmp_path):
    link, control = tmp_path / "gp32", tmp_path / "gp32.ctl"
    with EchoUnit(str(link), str(control)) as unit:
        assert unit.steps == ["power_up (pty open: True, thread: False)"]  # powered with its pty, before its thread
        assert os.readlink(link) == unit.device_path and unit._thread is not None and unit._thread.name == "echo-unit"
        fd = os.open(link, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            os.write(fd, b"ping\n")
            assert _read(fd, 5) == b"ping\n"  # the unit's thread answers on the pty behind the link
        finally:
            os.close(fd)
        with socket.socket(socket.AF_UNIX) as sock:
            sock.connect(str(control))
            sock.sendall(b'{"get": "x"}\n')
            assert json.loads(sock.makefile().readline()) == {"ok": True, "echo": {"get": "x"}}
        thread = unit._thread
    # the thread ended before the unit was released, and that before its pty closed
    assert unit.steps[1:] == ["loop ended", "release (pty open: True)"]
    assert not thread.is_alive() and unit._master is None
    assert not link.exists() and not link.is_symlink() and not control.exists()


def test_a_unit_that_cannot_start_opens_nothing(tmp_path):
    link = tmp_path / "gp32"
    unit = Gp32Firmware(link=str(link), image=tmp_path / "missing.ihx")
    with pytest.raises(FirmwareUnavailable):
        unit.start()
    assert unit.device_path == "" and not link.is_symlink() and unit._thread is None


def test_both_simulated_units_have_the_one_lifecycle():
    for unit in (Gp32Emulator, Gp32Firmware):
        assert issubclass(unit, PtyUnit)
        assert all(name not in vars(unit) for name in ("start", "close", "__enter__", "__exit__")), unit.__name__
    assert (Gp32Emulator.thread_name, Gp32Firmware.thread_name) == ("gp32-emulator", "gp32-board")

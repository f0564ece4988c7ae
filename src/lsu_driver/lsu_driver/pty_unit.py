"""What every simulated GP32 shares: a pty a client opens as its serial port, a control socket for faults,
and one lifecycle (`PtyUnit`): the emulator (`emulator.Gp32Emulator`) and the firmware on its simulated
board (`firmware.Gp32Firmware`) both derive from it. No rclpy here."""

from __future__ import annotations

import abc
import json
import os
import socket
import threading
import tty
from collections.abc import Callable
from pathlib import Path
from typing import Self


def open_pty(link: Path | None) -> tuple[int, int, str]:
    """A raw pty pair (master, slave, slave path); ``link`` (if given) points at the slave."""
    master, slave = os.openpty()
    tty.setraw(slave)  # bytes pass unchanged: no echo, no CR/LF translation
    path = os.ttyname(slave)
    if link is not None:
        tmp = link.with_name(link.name + ".tmp")
        if tmp.is_symlink() or tmp.exists():
            tmp.unlink()
        tmp.symlink_to(path)
        os.replace(tmp, link)  # atomic: a client never sees a missing link during replug
    return master, slave, path


def close_pty(master: int | None, slave: int | None, link: Path | None, path: str) -> None:
    """Close a pair from `open_pty` and remove ``link`` if it still points at ``path``."""
    for fd in (master, slave):
        if fd is not None:
            try:
                os.close(fd)
            except OSError:
                pass  # already closed: nothing left to release
    if link is not None and link.is_symlink() and os.readlink(link) == path:
        link.unlink()


class ControlServer:
    """A UNIX socket that answers JSON-line requests with ``handler(request)`` (one thread)."""

    def __init__(self, path: Path, handler: Callable[[dict[str, object]], dict[str, object]]) -> None:
        self.path = path
        self._handler = handler
        if path.exists() or path.is_symlink():
            path.unlink()
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._sock.bind(str(path))
        self._sock.listen(4)
        self._sock.settimeout(0.2)
        self._running = True
        self._thread = threading.Thread(target=self._serve, name="gp32-control", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._running = False
        self._sock.close()
        if self.path.exists():
            self.path.unlink()

    def _serve(self) -> None:
        while self._running:
            try:
                conn, _ = self._sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            with conn, conn.makefile("rwb") as stream:
                for raw in stream:
                    try:
                        request = json.loads(raw)
                        answer = self._handler(request) if isinstance(request, dict) else \
                            {"ok": False, "error": "send one JSON object per line"}
                    except json.JSONDecodeError as exc:
                        answer = {"ok": False, "error": f"not JSON: {exc}"}
                    stream.write((json.dumps(answer) + "\n").encode())
                    stream.flush()


class PtyUnit(abc.ABC):
    """A simulated unit behind a pty. Use as a context manager, or `start()` / `close()`.

    `start` opens the client's pty (``device_path``; with ``link`` a stable symlink points at it), powers the
    unit on (`_power_up`), starts the unit's thread (`_loop`, which runs while ``_running``) and, with
    ``control``, the control socket (`handle_control`, one JSON object per line). `close` undoes them in
    reverse order: the thread stops, the socket goes, the unit lets go of what else it holds (`_release`),
    and the pty is closed and the link removed.
    """

    #: the name of the unit's thread
    thread_name = "gp32-unit"

    def __init__(self, link: str | None = None, control: str | None = None) -> None:
        self.link = Path(link) if link else None
        self.control_path = Path(control) if control else None
        self._running = False
        self._thread: threading.Thread | None = None
        self._control: ControlServer | None = None
        self._master: int | None = None
        self._slave: int | None = None
        self.device_path = ""

    def _check_startable(self) -> None:  # noqa: B027 (optional: most units can always start)
        """Raise, before anything is opened, when the unit cannot start."""

    @abc.abstractmethod
    def _power_up(self) -> None:
        """Power the unit on: its pty is open, its thread not started yet."""

    @abc.abstractmethod
    def _loop(self) -> None:
        """The unit's thread: runs until ``_running`` is False."""

    @abc.abstractmethod
    def handle_control(self, request: dict[str, object]) -> dict[str, object]:
        """One control request (what the control socket speaks)."""

    def _release(self) -> None:  # noqa: B027 (optional: a unit that holds nothing besides its pty)
        """Let go of what the unit holds besides its pty (its thread has stopped)."""

    def start(self) -> Self:
        """Open the pty (and link, control socket), power the unit on and start its thread."""
        self._check_startable()
        self._open_pty()
        self._running = True
        self._power_up()
        self._thread = threading.Thread(target=self._loop, name=self.thread_name, daemon=True)
        self._thread.start()
        if self.control_path is not None:
            self._control = ControlServer(self.control_path, self.handle_control)
        return self

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop the unit's thread, remove the control socket, release the unit, close the pty, remove the link."""
        self._running = False
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self._control is not None:
            self._control.close()
        self._release()
        self._close_pty()

    def _open_pty(self) -> None:
        self._master, self._slave, self.device_path = open_pty(self.link)

    def _close_pty(self) -> None:
        close_pty(self._master, self._slave, self.link, self.device_path)
        self._master = self._slave = None


__all__ = ["ControlServer", "PtyUnit", "close_pty", "open_pty"]

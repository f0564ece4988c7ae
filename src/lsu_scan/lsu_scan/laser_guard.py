"""The scan's laser guard (no rclpy): deadlines by which a stop-snap scan must make progress.

While a scan runs the laser may only be on while the scan goes on: a move, a capture or a snap's
points that are ``pause_s`` late mean a stalled pipeline (a hung camera, a dead matcher, a driver
that does not report the stop), and the laser must go off at once, without waiting for the late
answer. The coordinator asks :meth:`LaserGuard.overdue` in every wait of its scan thread and sends
the laser-off request itself; this class only keeps the books, with the clock passed in, so its
decisions are unit-tested without ROS or time.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class Pause:
    """One time the guard switched the laser off mid-scan (listed in scan.json as ``laser_pauses``)."""

    at: float   # wall time of the off request [s since the epoch]
    why: str    # which answer was late, in words

    def as_json(self) -> dict[str, object]:
        return {"at": round(self.at, 3), "why": self.why}


@dataclass
class LaserGuard:
    """What the driver was last asked, what is due when, and the pauses so far.

    Invariants: at most one off request is outstanding (``off_pending``); no deadline fires while
    the laser is off or an off is outstanding; a scan starts with no deadlines.
    """

    pause_s: float
    lit: bool = False
    off_pending: bool = False
    pauses: list[Pause] = field(default_factory=list)
    _deadlines: dict[str, tuple[float, str]] = field(default_factory=dict)

    def start_scan(self) -> None:
        """A new scan: no deadlines, no pauses, no outstanding off (a left-over one would disarm the guard)."""
        self._deadlines.clear()
        self.pauses = []
        self.off_pending = False

    def due(self, name: str, due_at: float, what: str) -> None:
        """``name``'s answer is due at monotonic ``due_at``; ``pause_s`` later the laser goes off."""
        self._deadlines[name] = (due_at + self.pause_s, f"{what} {self.pause_s:g} s after it was due")

    def answered(self, name: str) -> None:
        """``name`` answered (or its wait ended): no deadline for it any more."""
        self._deadlines.pop(name, None)

    def is_due(self, name: str) -> bool:
        return name in self._deadlines

    def clear(self) -> None:
        """The scan ended: nothing is due; the end-of-scan off supersedes an outstanding one."""
        self._deadlines.clear()
        self.off_pending = False

    def overdue(self, now: float) -> str | None:
        """The warning of the earliest deadline passed at ``now``, if the laser must go off now, else None."""
        if not self.lit or self.off_pending or not self._deadlines:
            return None
        deadline, warning = min(self._deadlines.values(), key=lambda d: d[0])
        return warning if now >= deadline else None

    def switched_off(self, warning: str, wall_time: float) -> None:
        """The off request for ``warning`` was sent (its reply is not awaited)."""
        self.lit = False
        self.off_pending = True
        self.pauses.append(Pause(wall_time, warning))

    def off_settled(self) -> None:
        """The outstanding off request was answered (or given up): the guard may fire again once lit."""
        self.off_pending = False

    def lit_by_scan(self, on: bool) -> None:
        """The scan itself set the laser (its own on/off calls, not the guard's)."""
        self.lit = on

    @property
    def last_off_wall(self) -> float:
        """Wall time of the latest pause's off request (0 when none): captures exposed after it are retaken."""
        return self.pauses[-1].at if self.pauses else 0.0


def ack_due_at(captured_at: float, capture_asked_at: float, exposure_s: float) -> float:
    """When a snap's points are due: at the capture's answer, or when its exposure was due if that came later.

    A capture slowed down while the graph is in trouble must not add its delay to the laser's time on.
    """
    return min(captured_at, capture_asked_at + exposure_s)

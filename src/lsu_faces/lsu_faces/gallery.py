"""The face gallery: an SQLite file (sqlite3, standard library) of enrolled signatures.

Table ``faces``: id, name, signature (blob, `lsu_faces.signature.Signature.to_bytes`), method,
date (ISO 8601, UTC), mesh_file, points_used. Every write runs in its own transaction
(``BEGIN IMMEDIATE`` ... ``COMMIT``, rolled back on any error), so a failure or a crash half-way never
leaves a partial row and never touches existing entries. A gallery file that another process holds
locked gives `GalleryLockedError` after ``timeout_s``; a file that is not an SQLite gallery gives
`GalleryCorruptError` and is left exactly as it was (never overwritten or "repaired").

Privacy: a gallery is biometric data. Its folder is created 0700 and the file 0600; opening a gallery
file that other local users can read or write, or one in a folder they can write, is refused with
`GalleryPermissionError` (as ssh refuses a private key others can read) until the owner runs ``chmod``.
Removal runs with SQLite's ``secure_delete`` on and then ``VACUUM``s the file, so no byte of the removed person's signature or name
stays in the file (free pages are zeroed and dropped).

Scores (`identify`) are calibrated on the gallery's own impostor distances: every pair of entries of
different names is compared once (kept for the life of this object, keyed by the entry ids, and
recomputed only when entries change), and `lsu_faces.signature.ImpostorModel.fit` turns them into the
chance that a stranger comes that close.
"""

from __future__ import annotations

import builtins
import datetime as _dt
import os
import sqlite3
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from .signature import ImpostorModel, Signature, SignatureError, compare

__all__ = ["GalleryError", "GalleryLockedError", "GalleryCorruptError", "GalleryPermissionError", "GalleryEntry",
           "Match", "Identification", "Gallery", "DEFAULT_FALSE_ACCEPT"]

DEFAULT_FALSE_ACCEPT = 0.01      # open-set decision: chance that an unenrolled person is accepted as someone

_SCHEMA = """
CREATE TABLE IF NOT EXISTS faces (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    name TEXT NOT NULL,
    signature BLOB NOT NULL,
    method TEXT NOT NULL,
    date TEXT NOT NULL,
    mesh_file TEXT NOT NULL DEFAULT '',
    points_used INTEGER NOT NULL DEFAULT 0
);
CREATE INDEX IF NOT EXISTS faces_name ON faces(name);
"""


class GalleryError(ValueError):
    """The gallery cannot be used; the message names the file, the cause and what to do."""


class GalleryLockedError(GalleryError):
    """Another process holds the gallery file locked."""


class GalleryCorruptError(GalleryError):
    """The gallery file is not a readable SQLite gallery; it has been left untouched."""


class GalleryPermissionError(GalleryError):
    """The gallery file or its folder is readable or writable by other users: refused until fixed."""


@dataclass
class GalleryEntry:
    """One enrolled sample."""

    id: int
    name: str
    method: str
    date: str
    mesh_file: str
    points_used: int


@dataclass
class Match:
    """One ranked candidate of an identification."""

    name: str
    score: float                 # 1 - false_accept: calibrated on the gallery's impostor distances
    entry_id: int
    distance_m: float
    false_accept: float = 1.0    # chance that a different person comes this close (one comparison)


@dataclass
class Identification:
    """Ranked matches and the open-set decision."""

    matches: list[Match]
    accepted: bool               # the best match's false_accept x people compared <= the stated rate
    false_accept_rate: float     # the stated rate
    threshold_m: float           # distance the best match had to beat
    model: ImpostorModel

    @property
    def best(self) -> Match | None:
        return self.matches[0] if self.matches and self.accepted else None

class Gallery:
    """An SQLite face gallery at ``path`` (created on first write; the folder must exist or is created)."""

    def __init__(self, path: str | Path, timeout_s: float = 2.0) -> None:
        self.path = Path(path).expanduser()
        self.timeout_s = float(timeout_s)
        self._signatures: dict[int, Signature] = {}
        self._impostor: dict[tuple, ImpostorModel] = {}

    # ------------------------------------------------------------------ privacy
    def _check_private(self) -> None:
        """Refuse a gallery others can read or write, or a folder others can write (they could swap the file)."""
        checks = ((self.path.parent, 0o022, "700"), (self.path, 0o077, "600"))
        for path, forbidden, want in checks:
            if not path.exists():
                continue
            mode = stat.S_IMODE(path.stat().st_mode)
            if mode & forbidden:
                what = "folder" if path.is_dir() else "gallery"
                raise GalleryPermissionError(
                    f"{what} {path} is {'writable' if path.is_dir() else 'accessible'} by other users (mode {mode:o}); "
                    f"a face gallery holds biometric data and must be private: run 'chmod {want} {path}' and retry")

    def _make_private(self) -> None:
        if not self.path.parent.exists():
            self.path.parent.mkdir(parents=True, mode=0o700)
            os.chmod(self.path.parent, 0o700)     # mkdir's mode is masked by the umask
        if not self.path.exists():
            fd = os.open(self.path, os.O_CREAT | os.O_WRONLY, 0o600)
            os.close(fd)
            os.chmod(self.path, 0o600)

    # ------------------------------------------------------------------ connection
    def _translate(self, exc: sqlite3.Error) -> GalleryError:
        text = str(exc)
        if "locked" in text or "busy" in text:
            return GalleryLockedError(f"gallery {self.path} is locked by another process ({text}); wait for it to "
                                      f"finish or close it, then retry")
        if "not a database" in text or "malformed" in text or "file is encrypted" in text or "no such" in text:
            return GalleryCorruptError(f"gallery {self.path} is not a valid face gallery ({text}); it was left "
                                       f"untouched: move it away or restore a backup, then enrol again")
        return GalleryError(f"gallery {self.path}: {text}")

    @contextmanager
    def _connect(self, write: bool) -> Iterator[sqlite3.Connection]:
        if not write and not self.path.exists():
            raise FileNotFoundError(f"gallery {self.path} does not exist yet; enrol a face first")
        self._check_private()
        if write:
            self._make_private()
        try:
            conn = sqlite3.connect(str(self.path), timeout=self.timeout_s, isolation_level=None)
            conn.execute("PRAGMA secure_delete = ON")
        except sqlite3.Error as exc:
            raise self._translate(exc) from None
        try:
            try:
                conn.execute("BEGIN IMMEDIATE" if write else "BEGIN")
                if write:
                    for statement in _SCHEMA.split(";"):
                        if statement.strip():
                            conn.execute(statement)
                self._check_schema(conn)
                yield conn
                conn.execute("COMMIT")
            except BaseException:
                if conn.in_transaction:
                    conn.execute("ROLLBACK")
                raise
        except sqlite3.Error as exc:
            raise self._translate(exc) from None
        finally:
            conn.close()

    def _check_schema(self, conn: sqlite3.Connection) -> None:
        cols = {row[1] for row in conn.execute("PRAGMA table_info(faces)")}
        need = {"id", "name", "signature", "method", "date", "mesh_file", "points_used"}
        if not need <= cols:
            raise GalleryCorruptError(f"gallery {self.path} is an SQLite file but has no 'faces' table with columns "
                                      f"{', '.join(sorted(need))}; it was left untouched: use another gallery file")

    # ------------------------------------------------------------------ operations
    def enroll(self, name: str, signature: Signature, mesh_file: str = "") -> int:
        """Add one sample for ``name`` (a name may hold several samples); returns the new entry id."""
        name = name.strip()
        if not name:
            raise GalleryError("the name to enrol is empty; give the person's name")
        blob = signature.to_bytes()
        date = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
        with self._connect(write=True) as conn:
            cur = conn.execute("INSERT INTO faces (name, signature, method, date, mesh_file, points_used) "
                               "VALUES (?, ?, ?, ?, ?, ?)", (name, blob, signature.method, date, str(mesh_file),
                                                            int(signature.points_used)))
            return int(cur.lastrowid or 0)  # set by every INSERT

    def list(self) -> builtins.list[GalleryEntry]:
        """Every entry, oldest first (empty when the gallery file does not exist yet)."""
        if not self.path.exists():
            return []
        with self._connect(write=False) as conn:
            rows = conn.execute("SELECT id, name, method, date, mesh_file, points_used FROM faces ORDER BY id").fetchall()
        return [GalleryEntry(int(r[0]), r[1], r[2], r[3], r[4], int(r[5])) for r in rows]

    def remove(self, name: str | None = None, entry_id: int | None = None) -> int:
        """Remove every sample of ``name``, or the entry ``entry_id``; returns how many rows went."""
        if (name is None) == (entry_id is None):
            raise GalleryError("remove needs either a name or an entry id")
        if not self.path.exists():
            raise FileNotFoundError(f"gallery {self.path} does not exist")
        with self._connect(write=True) as conn:
            if name is not None:
                n = conn.execute("DELETE FROM faces WHERE name = ?", (name,)).rowcount
            else:
                n = conn.execute("DELETE FROM faces WHERE id = ?", (int(entry_id or 0),)).rowcount
        if n == 0:
            raise LookupError(f"gallery {self.path} has no entry {'named ' + repr(name) if name else entry_id}")
        self._vacuum()
        self._signatures.clear()     # ids may be reused; drop every per-entry state
        self._impostor.clear()
        return int(n)

    def _vacuum(self) -> None:
        """Rewrite the file without free pages (secure_delete zeroed them; VACUUM also drops the index's)."""
        try:
            conn = sqlite3.connect(str(self.path), timeout=self.timeout_s, isolation_level=None)
        except sqlite3.Error as exc:
            raise self._translate(exc) from None
        try:
            conn.execute("PRAGMA secure_delete = ON")
            conn.execute("VACUUM")
        except sqlite3.Error as exc:
            raise self._translate(exc) from None
        finally:
            conn.close()

    def _load(self) -> builtins.list[tuple]:
        with self._connect(write=False) as conn:
            rows = conn.execute("SELECT id, name, signature FROM faces ORDER BY id").fetchall()
        present = {int(r[0]) for r in rows}
        for stale in [k for k in self._signatures if k not in present]:   # removed by another process
            del self._signatures[stale]
        out = []
        for entry_id, name, blob in rows:
            sig = self._signatures.get(entry_id)
            if sig is None:
                try:
                    sig = Signature.from_bytes(blob)
                except SignatureError as exc:
                    raise GalleryCorruptError(f"gallery {self.path}: entry {entry_id} ({name}): {exc}") from None
                self._signatures[entry_id] = sig
            out.append((int(entry_id), name, sig))
        return out

    def impostor_model(self, method: str = "depthmap", entries: builtins.list[tuple] | None = None) -> ImpostorModel:
        """Impostor distances of this gallery (every pair of different names, once) fitted as a log-normal."""
        entries = self._load() if entries is None else entries
        entries = [e for e in entries if e[2].method == method]
        key = (method, tuple(e[0] for e in entries))
        if key not in self._impostor:
            distances = []
            for i, (_, name_a, a) in enumerate(entries):
                for _, name_b, b in entries[i + 1:]:
                    if name_a != name_b:
                        distances.append(compare(a, b)[1])
            self._impostor.clear()    # one model per gallery state: never grows with the scans
            self._impostor[key] = ImpostorModel.fit(distances, method)
        return self._impostor[key]

    def identify(self, probe: Signature, max_results: int = 5,
                 false_accept_rate: float = DEFAULT_FALSE_ACCEPT) -> Identification:
        """Candidates ranked by distance (best first), one per name (its best sample), and the open-set decision.

        The best match is accepted when its chance of being a stranger (`ImpostorModel.false_accept`),
        times the number of names compared, is at most ``false_accept_rate``.
        """
        if not 0 < false_accept_rate < 1:
            raise GalleryError(f"false_accept_rate must be in (0, 1) (got {false_accept_rate})")
        if not self.path.exists():
            return Identification([], False, false_accept_rate, 0.0, ImpostorModel.prior(probe.method))
        entries = self._load()
        model = self.impostor_model(probe.method, entries)
        best: dict[str, Match] = {}
        for entry_id, name, ref in entries:
            if ref.method != probe.method:
                continue
            _, dist, _ = compare(probe, ref, model)
            if name not in best or dist < best[name].distance_m:
                best[name] = Match(name, model.score(dist), entry_id, dist, model.false_accept(dist))
        ranked = sorted(best.values(), key=lambda m: (m.distance_m, m.name))
        per_comparison = false_accept_rate / max(len(ranked), 1)
        accepted = bool(ranked) and ranked[0].false_accept <= per_comparison
        ranked = ranked[:max(1, int(max_results))] if max_results else ranked
        return Identification(ranked, accepted, false_accept_rate, model.threshold_m(per_comparison), model)

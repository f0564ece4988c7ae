"""The face gallery: an SQLite file (sqlite3, standard library) of enrolled signatures.

Table ``faces``: id, name, signature (blob, `lsu_faces.signature.Signature.to_bytes`), method,
date (ISO 8601, UTC), mesh_file, points_used. Every write runs in its own transaction
(``BEGIN IMMEDIATE`` ... ``COMMIT``, rolled back on any error), so a failure or a crash half-way never
leaves a partial row and never touches existing entries. A gallery file that another process holds
locked gives `GalleryLockedError` after ``timeout_s``; a file that is not an SQLite gallery gives
`GalleryCorruptError` and is left exactly as it was (never overwritten or "repaired").
"""

from __future__ import annotations

import datetime as _dt
import sqlite3
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Iterator, List, Optional

from .signature import Signature, SignatureError, compare

__all__ = ["GalleryError", "GalleryLockedError", "GalleryCorruptError", "GalleryEntry", "Match", "Gallery"]

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
    score: float
    entry_id: int
    distance_m: float


class Gallery:
    """An SQLite face gallery at ``path`` (created on first write; the folder must exist or is created)."""

    def __init__(self, path: "str | Path", timeout_s: float = 2.0) -> None:
        self.path = Path(path).expanduser()
        self.timeout_s = float(timeout_s)
        self._cache: Dict[int, object] = {}
        self._signatures: Dict[int, Signature] = {}

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
        if write:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            conn = sqlite3.connect(str(self.path), timeout=self.timeout_s, isolation_level=None)
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
        date = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
        with self._connect(write=True) as conn:
            cur = conn.execute("INSERT INTO faces (name, signature, method, date, mesh_file, points_used) "
                               "VALUES (?, ?, ?, ?, ?, ?)", (name, blob, signature.method, date, str(mesh_file),
                                                            int(signature.points_used)))
            return int(cur.lastrowid)

    def list(self) -> List[GalleryEntry]:
        """Every entry, oldest first (empty when the gallery file does not exist yet)."""
        if not self.path.exists():
            return []
        with self._connect(write=False) as conn:
            rows = conn.execute("SELECT id, name, method, date, mesh_file, points_used FROM faces ORDER BY id").fetchall()
        return [GalleryEntry(int(r[0]), r[1], r[2], r[3], r[4], int(r[5])) for r in rows]

    def remove(self, name: Optional[str] = None, entry_id: Optional[int] = None) -> int:
        """Remove every sample of ``name``, or the entry ``entry_id``; returns how many rows went."""
        if (name is None) == (entry_id is None):
            raise GalleryError("remove needs either a name or an entry id")
        if not self.path.exists():
            raise FileNotFoundError(f"gallery {self.path} does not exist")
        with self._connect(write=True) as conn:
            if name is not None:
                n = conn.execute("DELETE FROM faces WHERE name = ?", (name,)).rowcount
            else:
                n = conn.execute("DELETE FROM faces WHERE id = ?", (int(entry_id),)).rowcount
        if n == 0:
            raise LookupError(f"gallery {self.path} has no entry {'named ' + repr(name) if name else entry_id}")
        return int(n)

    def _load(self) -> List[tuple]:
        with self._connect(write=False) as conn:
            rows = conn.execute("SELECT id, name, signature FROM faces ORDER BY id").fetchall()
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

    def identify(self, probe: Signature, max_results: int = 5) -> List[Match]:
        """Candidates ranked by score (best first), one per name (its best sample)."""
        if not self.path.exists():
            return []
        best: Dict[str, Match] = {}
        for entry_id, name, ref in self._load():
            if ref.method != probe.method:
                continue
            score, dist, _ = compare(probe, ref, self._cache)
            if name not in best or score > best[name].score:
                best[name] = Match(name, score, entry_id, dist)
        ranked = sorted(best.values(), key=lambda m: (-m.score, m.distance_m))
        return ranked[:max(1, int(max_results))] if max_results else ranked

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

1:N (`identify`) runs in two stages. First, a faiss index (``IndexFlatL2``: exact, deterministic, no
training, so it is valid for any gallery size) over the compact vectors of the entries
(`lsu_faces.signature.compact_vector`, stored in each row beside the full signature) gives the
``first_stage`` nearest entries (one query on one thread: a memory-bound scan that OpenMP threads only
slow down); then the full comparison (`lsu_faces.signature.compare_many`: alignment and region-weighted
trimmed RMS, the probe aligned onto all candidates in one pass of stacked arrays) ranks those. The SQLite file stays the source of truth: the index
lives in memory only (no second copy of biometric data on disk), is built from the rows on first use
and is checked against the file before every identification: the file's identity, size, modification
time and SQLite's own file change counter (header bytes 24-27, bumped by every committed write of any
process), and the row count. A file changed behind this object's back (another process, a restored
backup, an edited row) is noticed and the index rebuilt; this object's own writes update it in place.

Open set: the best match is accepted when the chance that a stranger's search comes as close is at
most the stated false-positive identification rate (FPIR, per search); a rejection says why. The
gallery calibrates that chance on itself, with scans of its own sensor and noise:

- from `SELF_CALIBRATION_PEOPLE` depth-map people on, by leave-one-out searches: a fixed, seeded sample
  of ``calibration_searches`` entries, each searched as `identify` searches (first stage, then the full
  comparison) with its own person left out, is exactly a stranger's search of this gallery; the
  distances to their nearest other person, fitted as a log-normal, give the per-search chance directly
  (`nearest_stranger_distances`). A chance per comparison times the people compared (below) assumes
  the comparisons independent and the log-normal right far into its tail, and so over a thousand
  people accepts nobody at a stated 1 %;
- in smaller galleries (too few searches for a 1 % tail), by the gallery's impostor distances (pairs of
  entries of different names: all pairs of a small gallery, a fixed, seeded sample of
  ``impostor_pairs`` pairs of a larger one), fitted as a log-normal (`lsu_faces.signature.ImpostorModel.fit`)
  shrunk towards a prior for the depth noise of the scans actually enrolled (each row keeps its
  scan's measured noise: a gallery of time-of-flight scans is judged by a time-of-flight stranger,
  not the LSU rig's), times the number of people compared.

The leave-one-out calibration costs seconds per thousand people (200 searches); it is stored in the file's
``calibration`` table under a key of the gallery's depth-map entries (ids and names: an entry never
changes once enrolled) and what a search is (`CALIBRATION_VERSION`, the first stage, the searches, the core
regions of the distance), so another process (each `lsu face identify`, a restarted node) reads it instead
of searching again; any enrolment or removal changes the key, and a new calibration replaces the old row.
It holds two numbers and a count, nothing of any face. A gallery that cannot be written (read-only, locked)
keeps it in memory only.
"""

from __future__ import annotations

import builtins
import collections
import datetime as _dt
import hashlib
import os
import sqlite3
import stat
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lsu_common.arrays import AnyArray

from .signature import CORE_REGIONS, ImpostorModel, Signature, SignatureError, compact_vector, compare, compare_many

__all__ = ["GalleryError", "GalleryLockedError", "GalleryCorruptError", "GalleryPermissionError", "GalleryEntry",
           "Match", "Identification", "Gallery", "DEFAULT_FALSE_ACCEPT",
           "nearest_stranger_distances", "stranger_model"]

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
CREATE TABLE IF NOT EXISTS calibration (
    key TEXT PRIMARY KEY,
    log_mu REAL,
    log_sigma REAL,
    samples INTEGER NOT NULL,
    date TEXT NOT NULL
);
"""
# columns added after the first release: added to older galleries on their first write
_NEW_COLUMNS = {"compact": "BLOB", "noise_mm": "REAL"}
FIRST_STAGE = 20         # entries the compact index hands to the full comparison (compared in one batch)
IMPOSTOR_PAIRS = 300     # impostor pairs a large gallery calibrates its scores on (all pairs below that)
SELF_CALIBRATION_PEOPLE = 50   # depth-map people from which the gallery calibrates on leave-one-out searches
CALIBRATION_SEARCHES = 200     # leave-one-out searches of that calibration (every entry below that)
# part of a stored calibration's key (module doc): raise it when what a search's distance is changes otherwise
# than through the key's other parts (the comparison, the first stage), so that no stored calibration is read
CALIBRATION_VERSION = 2  # 2: the comparison's smoothing rounded (`signature.SMOOTH_STEP_CELLS`)


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
    noise_mm: float = float("nan")


@dataclass
class Match:
    """One ranked candidate of an identification."""

    name: str
    score: float                 # 1 - false_accept
    entry_id: int
    distance_m: float
    false_accept: float = 1.0    # chance that a stranger's search of this gallery comes this close (module doc)


@dataclass
class Identification:
    """Ranked matches and the open-set decision."""

    matches: list[Match]
    accepted: bool               # the best match's false_accept <= the stated rate
    false_accept_rate: float     # the stated rate (FPIR, per search)
    threshold_m: float           # distance the best match had to beat
    model: ImpostorModel         # log-normal of a stranger's nearest distance, or of one impostor pair (calibration)
    reason: str = ""             # why the best match was rejected (empty when accepted)
    probe_noise_mm: float = float("nan")
    gallery_noise_mm: float = float("nan")
    calibration: str = ""        # what the stranger chances were calibrated on

    @property
    def best(self) -> Match | None:
        return self.matches[0] if self.matches and self.accepted else None

class Gallery:
    """An SQLite face gallery at ``path`` (created on first write; the folder must exist or is created)."""

    def __init__(self, path: str | Path, timeout_s: float = 2.0) -> None:
        self.path = Path(path).expanduser()
        self.timeout_s = float(timeout_s)
        self._signatures: dict[int, Signature] = {}      # decoded full signatures (bounded: see _signature)
        self._impostor: dict[tuple, ImpostorModel] = {}
        self._index: _Index | None = None
        self.index_builds = 0                            # how often the index was (re)built from the file
        self.first_stage = FIRST_STAGE
        self.impostor_pairs = IMPOSTOR_PAIRS
        self.calibration_searches = CALIBRATION_SEARCHES
        self._stranger: dict[str, ImpostorModel | None] = {}  # by calibration_key: one gallery state

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
                if write:
                    have = {row[1] for row in conn.execute("PRAGMA table_info(faces)")}
                    for col, kind in _NEW_COLUMNS.items():
                        if col not in have:
                            conn.execute(f"ALTER TABLE faces ADD COLUMN {col} {kind}")
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
        compact = compact_vector(signature).tobytes() if signature.method == "depthmap" else None
        noise_mm = float(signature.noise_m) * 1000.0 if np.isfinite(signature.noise_m) else None
        date = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
        with self._connect(write=True) as conn:
            before = self._fingerprint()
            cur = conn.execute("INSERT INTO faces (name, signature, method, date, mesh_file, points_used, compact, "
                               "noise_mm) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                               (name, blob, signature.method, date, str(mesh_file), int(signature.points_used),
                                compact, noise_mm))
            entry_id = int(cur.lastrowid or 0)  # set by every INSERT
        # our own write: carry the index along when nothing else changed the file in between
        if self._index is not None and before == self._index.fingerprint and compact is not None:
            self._index.add(entry_id, name, np.frombuffer(compact, dtype=np.float32),
                            float("nan") if noise_mm is None else noise_mm, self._fingerprint())
        else:
            self._index = None
        return entry_id

    def list(self) -> builtins.list[GalleryEntry]:
        """Every entry, oldest first (empty when the gallery file does not exist yet)."""
        if not self.path.exists():
            return []
        with self._connect(write=False) as conn:
            noise = "noise_mm" if "noise_mm" in self._columns(conn) else "NULL"
            rows = conn.execute(f"SELECT id, name, method, date, mesh_file, points_used, {noise} FROM faces "
                                f"ORDER BY id").fetchall()
        return [GalleryEntry(int(r[0]), r[1], r[2], r[3], r[4], int(r[5]), float("nan") if r[6] is None else r[6])
                for r in rows]

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
            conn.execute("DELETE FROM calibration")  # of a gallery state that is gone
        if n == 0:
            raise LookupError(f"gallery {self.path} has no entry {'named ' + repr(name) if name else entry_id}")
        self._vacuum()
        self._signatures.clear()     # ids may be reused; drop every per-entry state
        self._impostor.clear()
        self._stranger.clear()
        self._index = None
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

    # ------------------------------------------------------------------ the first-stage index
    @staticmethod
    def _columns(conn: sqlite3.Connection) -> set[str]:
        return {row[1] for row in conn.execute("PRAGMA table_info(faces)")}

    def _fingerprint(self) -> tuple:
        """What changes whenever any process commits to the file (or replaces it): see the module doc."""
        try:
            st = os.stat(self.path)
            with open(self.path, "rb") as fh:
                header = fh.read(28)
        except OSError:
            return ()
        wal = Path(str(self.path) + "-wal")
        wal_st = wal.stat() if wal.exists() else None
        return (st.st_ino, st.st_size, st.st_mtime_ns, header[24:28],
                (wal_st.st_size, wal_st.st_mtime_ns) if wal_st else None)

    def index(self) -> _Index:
        """The first-stage index, rebuilt from the file when the file changed behind this object's back."""
        fingerprint = self._fingerprint()
        with self._connect(write=False) as conn:
            count = int(conn.execute("SELECT count(*) FROM faces").fetchone()[0])
            if self._index is not None and self._index.fingerprint == fingerprint and self._index.count == count:
                return self._index
            cols = self._columns(conn)
            compact = "compact" if "compact" in cols else "NULL"
            noise = "noise_mm" if "noise_mm" in cols else "NULL"
            rows = conn.execute(f"SELECT id, name, method, {compact}, {noise} FROM faces ORDER BY id").fetchall()
            missing = [int(r[0]) for r in rows if r[2] == "depthmap" and r[3] is None]
            made: dict[int, bytes] = {}
            for start in range(0, len(missing), 500):   # a gallery from before compact vectors: made here once
                part = missing[start:start + 500]
                q = f"SELECT id, signature FROM faces WHERE id IN ({','.join('?' * len(part))})"
                for entry_id, blob in conn.execute(q, part):
                    made[int(entry_id)] = compact_vector(self._decode(int(entry_id), "", blob)).tobytes()
        self._signatures.clear()
        self._impostor.clear()
        self._stranger.clear()
        idx = _Index(fingerprint)
        depth = [r for r in rows if r[2] == "depthmap"]
        if depth:
            vectors = np.stack([np.frombuffer(made.get(int(r[0]), r[3] or b""), dtype=np.float32) for r in depth])
            idx.build([int(r[0]) for r in depth], [r[1] for r in depth], vectors,
                      [float("nan") if r[4] is None else float(r[4]) for r in depth])
        idx.count = len(rows)
        idx.other = [(int(r[0]), r[1]) for r in rows if r[2] != "depthmap"]
        self._index = idx
        self.index_builds += 1
        return idx

    def _decode(self, entry_id: int, name: str, blob: bytes) -> Signature:
        try:
            return Signature.from_bytes(blob)
        except SignatureError as exc:
            raise GalleryCorruptError(f"gallery {self.path}: entry {entry_id} ({name}): {exc}") from None

    def signatures(self, ids: builtins.list[int]) -> dict[int, Signature]:
        """Full signatures of the entries ``ids`` (decoded once; at most 4096 kept)."""
        want = [i for i in dict.fromkeys(int(i) for i in ids) if i not in self._signatures]
        if want:
            with self._connect(write=False) as conn:
                for start in range(0, len(want), 500):
                    part = want[start:start + 500]
                    q = f"SELECT id, name, signature FROM faces WHERE id IN ({','.join('?' * len(part))})"
                    for entry_id, name, blob in conn.execute(q, part):
                        if len(self._signatures) >= 4096:
                            self._signatures.clear()
                        self._signatures[int(entry_id)] = self._decode(int(entry_id), name, blob)
        return {int(i): self._signatures[int(i)] for i in ids if int(i) in self._signatures}

    # ------------------------------------------------------------------ open set
    def impostor_model(self, method: str = "depthmap", idx: _Index | None = None) -> ImpostorModel:
        """Impostor distances of this gallery (pairs of different names) fitted as a log-normal.

        Every pair of a gallery with at most ``impostor_pairs`` of them, else a fixed sample of that many
        (seeded: the same gallery gives the same model in every process), shrunk towards the prior for
        the median depth noise of the enrolled scans. Kept until the gallery changes. ``idx``: the index
        just checked against the file (`index`), so one identification checks the file once.
        """
        idx = idx or self.index()
        key = (method, idx.fingerprint, idx.count)
        if key in self._impostor:
            return self._impostor[key]
        if method == "depthmap":
            ids, names = idx.ids.tolist(), idx.names
        else:
            ids, names = [i for i, _ in idx.other], [n for _, n in idx.other]
        n = len(ids)
        pairs: builtins.list[tuple[int, int]]
        if n * (n - 1) // 2 <= self.impostor_pairs:
            pairs = [(a, b) for a in range(n) for b in range(a + 1, n) if names[a] != names[b]]
        else:
            rng = np.random.default_rng(0x1A5)
            pairs = []
            for a, b in rng.integers(0, n, size=(4 * self.impostor_pairs, 2)):
                if names[a] != names[b]:
                    pairs.append((int(a), int(b)))
                if len(pairs) >= self.impostor_pairs:
                    break
        sigs = self.signatures([ids[a] for a, _ in pairs] + [ids[b] for _, b in pairs])
        distances = [compare(sigs[ids[a]], sigs[ids[b]])[1] for a, b in pairs]   # each pair its own probe
        model = ImpostorModel.fit(distances, method, idx.noise_m)
        self._impostor.clear()    # one model per gallery state: never grows with the scans
        self._impostor[key] = model
        return model

    def stranger_model(self, idx: _Index | None = None) -> ImpostorModel | None:
        """Log-normal of a stranger's nearest distance in this gallery's depth-map search, from leave-one-out
        searches (module doc); None below `SELF_CALIBRATION_PEOPLE` people (or too few searches found anybody:
        `stranger_model`). Kept until the gallery changes."""
        idx = idx or self.index()
        if idx.people < SELF_CALIBRATION_PEOPLE:
            return None
        key = self.calibration_key(idx)
        if key not in self._stranger:
            found, model = self._stored_calibration(key)
            if not found:
                model = stranger_model(idx, self.signatures, self.first_stage, self.calibration_searches)
                self._store_calibration(key, model)
            self._stranger.clear()
            self._stranger[key] = model
        return self._stranger[key]

    def calibration_key(self, idx: _Index | None = None) -> str:
        """The key of the gallery state's stored calibration (module doc)."""
        idx = idx or self.index()
        digest = hashlib.sha256(f"{CALIBRATION_VERSION}|{self.first_stage}|{self.calibration_searches}|"
                                f"{CORE_REGIONS!r}|".encode())
        digest.update(np.ascontiguousarray(idx.ids, dtype="<i8").tobytes())
        digest.update("\0".join(idx.names).encode())
        return digest.hexdigest()

    def _stored_calibration(self, key: str) -> tuple[bool, ImpostorModel | None]:
        """(found, model) of the calibration stored under ``key``; a None model: too few searches found anybody."""
        with self._connect(write=False) as conn:
            if conn.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'calibration'").fetchone() is None:
                return False, None   # a gallery from before stored calibrations
            row = conn.execute("SELECT log_mu, log_sigma, samples FROM calibration WHERE key = ?", (key,)).fetchone()
        if row is None:
            return False, None
        return True, (None if row[0] is None else ImpostorModel(float(row[0]), float(row[1]), int(row[2])))

    def _store_calibration(self, key: str, model: ImpostorModel | None) -> None:
        """``model`` stored under ``key``, replacing any other; a gallery that cannot be written keeps it in memory."""
        before = self._fingerprint()
        date = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
        try:
            with self._connect(write=True) as conn:
                conn.execute("DELETE FROM calibration")
                conn.execute("INSERT INTO calibration (key, log_mu, log_sigma, samples, date) VALUES (?, ?, ?, ?, ?)",
                             (key, None if model is None else model.log_mu, None if model is None else model.log_sigma,
                              0 if model is None else model.samples, date))
        except GalleryError:
            return
        # our own write: the index stays valid when nothing else changed the file in between
        if self._index is not None and before == self._index.fingerprint:
            self._index.fingerprint = self._fingerprint()

    def identify(self, probe: Signature, max_results: int = 5,
                 false_accept_rate: float = DEFAULT_FALSE_ACCEPT) -> Identification:
        """Candidates ranked by distance (best first), one per name (its best sample), and the open-set decision.

        Depth-map probes: the ``first_stage`` nearest entries of the compact index, then the full
        comparison on those. The best match is accepted when the chance that a stranger's search comes as
        close is at most ``false_accept_rate`` (the FPIR aimed at; calibrated as the module doc says);
        otherwise ``reason`` says why it was rejected.
        """
        if not 0 < false_accept_rate < 1:
            raise GalleryError(f"false_accept_rate must be in (0, 1) (got {false_accept_rate})")
        probe_noise = float(probe.noise_m) * 1000.0
        if not self.path.exists():
            return Identification([], False, false_accept_rate, 0.0, ImpostorModel.prior(probe.method),
                                  "the gallery is empty: enrol faces first", probe_noise)
        idx = self.index()
        if probe.method == "depthmap":
            cand, people = idx.search(compact_vector(probe), self.first_stage), idx.people
        else:
            cand, people = idx.other, len({n for _, n in idx.other})
        if not cand:
            return Identification([], False, false_accept_rate, 0.0, ImpostorModel.prior(probe.method),
                                  f"no entry of the gallery has a '{probe.method}' signature", probe_noise)
        stranger = self.stranger_model(idx) if probe.method == "depthmap" else None
        if stranger is not None:
            model, compared = stranger, 1
            calibration = f"{model.samples} searches of this gallery by its own people, each left out"
        else:
            model, compared = self.impostor_model(probe.method, idx), max(people, 1)
            calibration = (f"{model.samples} impostor distances of this gallery (+ the prior for its scans' depth "
                           f"noise), for each of the {compared} {'person' if compared == 1 else 'people'} compared")
        threshold = model.threshold_m(false_accept_rate / compared)
        sigs = self.signatures([i for i, _ in cand])
        best: dict[str, Match] = {}
        found = compare_many(probe, [sigs[entry_id] for entry_id, _ in cand], model)
        for (entry_id, name), (_, dist, _) in zip(cand, found):
            if name not in best or dist < best[name].distance_m:
                chance = min(1.0, model.false_accept(dist) * compared)
                best[name] = Match(name, 1.0 - chance, entry_id, dist, chance)
        ranked = sorted(best.values(), key=lambda m: (m.distance_m, m.name))
        accepted = bool(ranked) and ranked[0].false_accept <= false_accept_rate
        gallery_noise = idx.noise_m * 1000.0
        reason = ""
        if not accepted and ranked:
            top = ranked[0]
            reason = (f"the nearest face, {top.name}, is {top.distance_m * 1000:.2f} mm away; a stranger's search of "
                      f"this gallery comes that close with chance {top.false_accept:.2g} (calibrated on "
                      f"{calibration}): accepting at FPIR {false_accept_rate:g} needs < {threshold * 1000:.2f} mm")
            if np.isfinite(probe_noise) and np.isfinite(gallery_noise) and \
                    max(probe_noise, gallery_noise) > 2.0 * max(min(probe_noise, gallery_noise), 0.05):
                reason += (f" (this scan's depth noise is {probe_noise:.2f} mm, the gallery's {gallery_noise:.2f} mm: "
                           f"another sensor or distance than the enrolments?)")
        ranked = ranked[:max(1, int(max_results))] if max_results else ranked
        return Identification(ranked, accepted, false_accept_rate, threshold, model, reason, probe_noise,
                              gallery_noise, calibration)


def nearest_stranger_distances(idx: _Index, signatures: Callable[[builtins.list[int]], dict[int, Signature]],
                               first_stage: int, searches: int, seed: int = 0x5EA) -> builtins.list[float]:
    """Leave-one-out searches of a gallery's depth-map entries: the distance [m] from each entry of a fixed,
    seeded sample of ``searches`` (every entry if fewer) to its nearest entry of another name, found as
    `Gallery.identify` finds it (the compact first stage, its own name's entries skipped, then the full
    comparison on ``first_stage`` candidates): a stranger's search of the rest of the gallery.

    ``signatures``: entry ids -> their signatures (the gallery's, or a bench's own).
    """
    n = len(idx.ids)
    picks = np.sort(np.random.default_rng(seed).choice(n, size=min(n, int(searches)), replace=False))
    own = collections.Counter(idx.names)
    probes = signatures([int(idx.ids[p]) for p in picks])
    out: builtins.list[float] = []
    for p in picks:
        probe, name = probes[int(idx.ids[p])], idx.names[p]
        cand = [e for e, other in idx.search(compact_vector(probe), first_stage + own[name]) if other != name]
        refs = signatures(cand[:first_stage])
        found = compare_many(probe, [refs[e] for e in cand[:first_stage]])
        out.append(min((dist for _, dist, _ in found), default=float("inf")))
    return out


def stranger_model(idx: _Index, signatures: Callable[[builtins.list[int]], dict[int, Signature]],
                   first_stage: int, searches: int) -> ImpostorModel | None:
    """Log-normal of a stranger's nearest distance in a search of the gallery ``idx``: fitted (mean and
    deviation of the logs) to its `nearest_stranger_distances`; None when fewer than
    `SELF_CALIBRATION_PEOPLE` / 2 of them found anybody (entries that overlap no other)."""
    found = nearest_stranger_distances(idx, signatures, first_stage, searches)
    d = np.log([x for x in found if np.isfinite(x) and x > 0])
    if len(d) < SELF_CALIBRATION_PEOPLE // 2:
        return None
    return ImpostorModel(float(d.mean()), float(max(d.std(), 1e-3)), len(d))


class _Index:
    """The first-stage index of a gallery state: faiss over the compact vectors, entry ids and names."""

    def __init__(self, fingerprint: tuple) -> None:
        self.fingerprint = fingerprint
        self.count = 0                                    # rows of the file (every method)
        self.ids = np.zeros(0, dtype=np.int64)
        self.names: builtins.list[str] = []
        self.noise_mm: builtins.list[float] = []
        self.other: builtins.list[tuple[int, str]] = []   # entries without a compact vector (fft signatures)
        self.faiss: Any = None                          # faiss.IndexFlatL2 once built
        self._people: set[str] = set()
        self._noise_m: float | None = None                # median of noise_mm [m], kept until an entry is added

    def build(self, ids: builtins.list[int], names: builtins.list[str], vectors: AnyArray,
              noise_mm: builtins.list[float]) -> None:
        import faiss

        self.faiss = faiss.IndexFlatL2(int(vectors.shape[1]))
        self.faiss.add(np.ascontiguousarray(vectors, dtype=np.float32))
        self.ids = np.asarray(ids, dtype=np.int64)
        self.names = list(names)
        self.noise_mm = list(noise_mm)
        self._people = set(names)
        self._noise_m = None

    def add(self, entry_id: int, name: str, vector: AnyArray, noise_mm: float, fingerprint: tuple) -> None:
        if self.faiss is None:
            self.build([entry_id], [name], vector[None, :], [noise_mm])
        else:
            self.faiss.add(np.ascontiguousarray(vector[None, :], dtype=np.float32))
            self.ids = np.append(self.ids, np.int64(entry_id))
            self.names.append(name)
            self.noise_mm.append(noise_mm)
            self._people.add(name)
            self._noise_m = None
        self.count += 1
        self.fingerprint = fingerprint

    @property
    def people(self) -> int:
        """Distinct names with a depth-map entry."""
        return len(self._people)

    @property
    def noise_m(self) -> float:
        """Median depth noise of the enrolled scans [m] (NaN: none recorded)."""
        if self._noise_m is None:
            noise = np.asarray(self.noise_mm, dtype=np.float64)
            known = noise[np.isfinite(noise)]
            self._noise_m = float(np.median(known)) / 1000.0 if len(known) else float("nan")
        return self._noise_m

    def search(self, vector: AnyArray, k: int) -> builtins.list[tuple[int, str]]:
        """(entry id, name) of the ``k`` nearest entries, nearest first (ties by entry id: deterministic)."""
        if self.faiss is None or self.faiss.ntotal == 0:
            return []
        import faiss

        k = min(int(k), int(self.faiss.ntotal))
        # one query scans the vectors once, a memory-bound loop: faiss's OpenMP threads only wait on each
        # other there (on a loaded host many times slower than one thread), so one query runs on one thread
        threads = faiss.omp_get_max_threads()
        faiss.omp_set_num_threads(1)
        try:
            d, pos = self.faiss.search(np.ascontiguousarray(vector[None, :], dtype=np.float32), k)
        finally:
            faiss.omp_set_num_threads(threads)
        order = sorted((float(dd), int(self.ids[p]), int(p)) for dd, p in zip(d[0], pos[0]) if p >= 0)
        return [(entry_id, self.names[p]) for _, entry_id, p in order]

    def memory_bytes(self) -> int:
        """Bytes the index holds per the vectors and ids (names and Python objects not counted)."""
        dim = self.faiss.d if self.faiss is not None else 0
        return int(len(self.ids) * (4 * dim + 8))

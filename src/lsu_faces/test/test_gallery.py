"""Gallery: enrol, identify, list, remove; every write a transaction; locked and corrupt files."""

from __future__ import annotations

import sqlite3

import numpy as np
import pytest

from lsu_faces.gallery import Gallery, GalleryCorruptError, GalleryError, GalleryLockedError, GalleryPermissionError
from lsu_faces.signature import Signature, SignatureParams, cell_centres


def fake_signature(seed: int) -> Signature:
    """A smooth synthetic depth map (a paraboloid 'face' with a seeded bump) on the default grid."""
    p = SignatureParams()
    c = cell_centres(p)
    x, y = np.meshgrid(c, c)
    rng = np.random.default_rng(seed)
    a, bx, by = rng.uniform(2, 6), rng.uniform(-0.03, 0.03), rng.uniform(-0.03, 0.03)
    z = -a * (x ** 2 + y ** 2) + 0.004 * np.exp(-((x - bx) ** 2 + (y - by) ** 2) / 0.0004)
    z[np.hypot(x, y) > p.extent_m] = np.nan
    return Signature("depthmap", z, p, 1000 + seed)


def test_enrol_identify_list_remove(tmp_path):
    g = Gallery(tmp_path / "g.db")
    ids = [g.enroll(f"person{i}", fake_signature(i)) for i in range(4)]
    assert [e.name for e in g.list()] == [f"person{i}" for i in range(4)]
    ident = g.identify(fake_signature(2), max_results=3)
    matches = ident.matches
    assert ident.accepted and ident.best.name == "person2" and matches[0].entry_id == ids[2]
    assert matches[0].score == pytest.approx(1.0) and len(matches) == 3
    assert matches[0].score > matches[1].score >= matches[2].score
    assert 1 <= ident.model.samples <= 6             # the (overlapping) impostor pairs of the gallery itself
    assert g.remove(name="person2") == 1
    assert "person2" not in [m.name for m in g.identify(fake_signature(2)).matches]
    with pytest.raises(LookupError):
        g.remove(name="nobody")


def test_failed_write_rolls_back_and_keeps_entries(tmp_path, monkeypatch):
    g = Gallery(tmp_path / "g.db")
    g.enroll("alice", fake_signature(1))
    monkeypatch.setattr(Signature, "to_bytes", lambda self: object())  # sqlite cannot bind this
    with pytest.raises((GalleryError, sqlite3.Error, TypeError, ValueError)):
        g.enroll("bob", fake_signature(2))
    assert [e.name for e in g.list()] == ["alice"]


def test_locked_gallery_is_a_clear_error_and_loses_nothing(tmp_path):
    path = tmp_path / "g.db"
    g = Gallery(path, timeout_s=0.2)
    g.enroll("alice", fake_signature(1))
    other = sqlite3.connect(str(path), isolation_level=None)
    other.execute("BEGIN EXCLUSIVE")
    try:
        with pytest.raises(GalleryLockedError, match="locked"):
            g.enroll("bob", fake_signature(2))
    finally:
        other.execute("ROLLBACK")
        other.close()
    assert [e.name for e in g.list()] == ["alice"]
    g.enroll("bob", fake_signature(2))
    assert [e.name for e in g.list()] == ["alice", "bob"]


def test_corrupt_gallery_is_a_clear_error_and_left_untouched(tmp_path):
    path = tmp_path / "g.db"
    garbage = b"this is not an sqlite database " * 64
    path.write_bytes(garbage)
    path.chmod(0o600)                                  # private, so only the content is at fault
    g = Gallery(path)
    with pytest.raises(GalleryCorruptError, match="untouched"):
        g.list()
    with pytest.raises(GalleryCorruptError):
        g.enroll("alice", fake_signature(1))
    assert path.read_bytes() == garbage


def test_foreign_sqlite_file_is_not_taken_over(tmp_path):
    path = tmp_path / "other.db"
    conn = sqlite3.connect(str(path))
    conn.execute("CREATE TABLE faces (something TEXT)")
    conn.commit()
    conn.close()
    path.chmod(0o600)
    with pytest.raises(GalleryCorruptError, match="untouched"):
        Gallery(path).enroll("alice", fake_signature(1))


def test_empty_name_is_refused(tmp_path):
    with pytest.raises(GalleryError, match="empty"):
        Gallery(tmp_path / "g.db").enroll("  ", fake_signature(1))


def test_gallery_is_created_private_and_a_readable_one_is_refused(tmp_path):
    import os
    import stat

    path = tmp_path / "faces" / "g.db"
    g = Gallery(path)
    g.enroll("alice", fake_signature(1))
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700
    os.chmod(path, 0o644)                              # world-readable: refused, nothing read or changed
    before = path.read_bytes()
    for op in (g.list, lambda: g.identify(fake_signature(1)), lambda: g.enroll("bob", fake_signature(2))):
        with pytest.raises(GalleryPermissionError, match="chmod 600"):
            op()
    assert path.read_bytes() == before
    os.chmod(path, 0o600)
    os.chmod(path.parent, 0o777)                       # others could swap the file
    with pytest.raises(GalleryPermissionError, match="chmod 700"):
        g.list()
    os.chmod(path.parent, 0o700)
    assert [e.name for e in g.list()] == ["alice"]


def test_removed_person_leaves_no_byte_in_the_file(tmp_path):
    path = tmp_path / "g.db"
    g = Gallery(path)
    secret = "Zebediah Quixote-Vandersloot"
    g.enroll("alice", fake_signature(1))
    g.enroll(secret, fake_signature(2))
    blob = fake_signature(2).to_bytes()
    assert secret.encode() in path.read_bytes() and blob[-64:] in path.read_bytes()
    assert g.remove(name=secret) == 1
    data = path.read_bytes()
    assert secret.encode() not in data and blob[-64:] not in data and blob[100:164] not in data
    assert [e.name for e in g.list()] == ["alice"]

"""1:N: the faiss first stage over compact vectors, the index checked against the SQLite file, open-set reasons."""

from __future__ import annotations

import sqlite3

import numpy as np
import pytest

from lsu_faces.gallery import Gallery, _Index
from lsu_faces.signature import Signature, SignatureParams, cell_centres, compact_vector


def face_like(seed: int, noise_m: float = 0.0) -> Signature:
    """A smooth synthetic depth map: a paraboloid 'face' with a seeded relief all over it, on the default grid."""
    p = SignatureParams()
    c = cell_centres(p)
    x, y = np.meshgrid(c, c)
    rng = np.random.default_rng(seed)
    z = -rng.uniform(2, 6) * (x ** 2 + y ** 2)
    for _ in range(12):
        bx, by = rng.uniform(-0.05, 0.05, 2)
        z += rng.normal(0.0, 0.003) * np.exp(-((x - bx) ** 2 + (y - by) ** 2) / 0.0003)
    if noise_m:
        z = z + np.random.default_rng(seed + 10_000).normal(0, noise_m, z.shape)
    z[np.hypot(x, y) > p.extent_m] = np.nan
    return Signature("depthmap", z, p, 1000 + seed, noise_m if noise_m else 1e-4)


def test_index_over_100000_signatures_returns_the_planted_person_first():
    rng = np.random.default_rng(32)
    planted = compact_vector(face_like(7))
    dim = len(planted)
    # 100,000 other people: vectors with the spread of real compact vectors (per-block sigma of the population)
    spread = np.std([compact_vector(face_like(s)) for s in range(100, 140)], axis=0)
    others = (rng.standard_normal((100_000, dim)) * spread).astype(np.float32)
    idx = _Index(())
    ids = list(range(1, 100_001))
    idx.build(ids, [f"p{i}" for i in ids], others, [0.1] * len(ids))
    idx.add(100_001, "planted", planted, 0.1, ())
    probe = compact_vector(face_like(7, noise_m=2e-4))       # the same person scanned again, noisier
    found = idx.search(probe, 24)
    assert found[0] == (100_001, "planted")
    assert len(found) == 24 and idx.people == 100_001
    assert idx.memory_bytes() == 100_001 * (4 * dim + 8)


def test_index_is_rebuilt_after_the_gallery_file_changed_behind_its_back(tmp_path):
    path = tmp_path / "g.db"
    g = Gallery(path)
    for i in range(4):
        g.enroll(f"person{i}", face_like(i))
    assert g.identify(face_like(2)).matches[0].name == "person2"
    builds = g.index_builds
    g.enroll("person4", face_like(4))                 # its own write: carried into the index, no rebuild
    assert g.identify(face_like(4)).matches[0].name == "person4" and g.index_builds == builds
    # another process renames a person and removes another, straight in the file
    conn = sqlite3.connect(str(path))
    conn.execute("UPDATE faces SET name = 'mallory' WHERE name = 'person2'")
    conn.execute("DELETE FROM faces WHERE name = 'person3'")
    conn.commit()
    conn.close()
    ident = g.identify(face_like(2))
    assert g.index_builds == builds + 1
    assert ident.matches[0].name == "mallory"
    assert "person3" not in [m.name for m in g.identify(face_like(3), max_results=10).matches]
    # another Gallery object (another process) enrols: noticed too
    Gallery(path).enroll("person9", face_like(9))
    assert g.identify(face_like(9)).matches[0].name == "person9" and g.index_builds == builds + 2


def test_stranger_is_rejected_with_the_reason_and_a_member_accepted(tmp_path):
    g = Gallery(tmp_path / "g.db")
    for i in range(6):
        g.enroll(f"person{i}", face_like(i))
    member = g.identify(face_like(3, noise_m=1e-4))
    assert member.accepted and member.best.name == "person3" and member.reason == ""
    stranger = g.identify(face_like(77, noise_m=1e-4))
    assert not stranger.accepted and stranger.best is None
    assert "comes that close with chance" in stranger.reason and "FPIR 0.01" in stranger.reason
    assert "impostor distances" in stranger.calibration     # 6 people: too few to calibrate on its own searches


def test_a_large_gallery_states_the_fpir_its_strangers_reach(tmp_path):
    """From SELF_CALIBRATION_PEOPLE people on, a stranger's chance comes from the gallery's own leave-one-out
    searches: strangers of the population it was enrolled from are accepted at about the stated FPIR (a little
    under it: 7 of these 200 at a stated 10 %), members found again are accepted. The chance per pair times the people
    compared (the rule of small galleries) accepts none of these strangers."""
    from lsu_faces.gallery import SELF_CALIBRATION_PEOPLE

    g = Gallery(tmp_path / "g.db")
    for i in range(SELF_CALIBRATION_PEOPLE + 10):
        g.enroll(f"person{i}", face_like(i))
    stated = 0.1
    strangers = [g.identify(face_like(5000 + i), false_accept_rate=stated) for i in range(200)]
    assert all("each left out" in s.calibration for s in strangers)
    reached = np.mean([s.accepted for s in strangers])
    assert 0.02 <= reached <= 0.2, reached
    members = [g.identify(face_like(i, noise_m=1e-4), false_accept_rate=stated) for i in range(0, 50, 5)]
    assert all(m.accepted and m.best.name == f"person{i}" for m, i in zip(members, range(0, 50, 5)))


def test_the_calibration_is_stored_with_the_gallery_and_redone_when_it_changes(tmp_path, monkeypatch):
    """Another process (a new Gallery object on the file) reads the stored calibration instead of searching; an
    enrolment changes the gallery's key and the next identification searches again; a removal drops the row."""
    import lsu_faces.gallery as gallery_module
    from lsu_faces.gallery import SELF_CALIBRATION_PEOPLE

    searched = []
    real = gallery_module.nearest_stranger_distances
    monkeypatch.setattr(gallery_module, "nearest_stranger_distances",
                        lambda *a, **k: searched.append(1) or real(*a, **k))
    path = tmp_path / "g.db"
    first = Gallery(path)
    for i in range(SELF_CALIBRATION_PEOPLE + 2):
        first.enroll(f"person{i}", face_like(i))
    probe = face_like(5001)
    said = first.identify(probe)
    assert len(searched) == 1 and "each left out" in said.calibration
    builds = first.index_builds
    assert first.identify(probe).matches == said.matches and first.index_builds == builds  # its own write: index kept
    second = Gallery(path)
    again = second.identify(probe)
    assert len(searched) == 1                       # read, not searched
    assert second.stranger_model() == first.stranger_model()
    assert [(m.name, m.distance_m, m.false_accept) for m in again.matches] == \
        [(m.name, m.distance_m, m.false_accept) for m in said.matches]
    second.enroll("newcomer", face_like(999))
    key = second.calibration_key()
    Gallery(path).identify(probe)
    assert len(searched) == 2
    with sqlite3.connect(path) as conn:
        assert conn.execute("SELECT key FROM calibration").fetchall() == [(key,)]
    second.remove("newcomer")
    with sqlite3.connect(path) as conn:
        assert conn.execute("SELECT count(*) FROM calibration").fetchone()[0] == 0


def test_threshold_follows_the_noise_of_the_enrolled_scans(tmp_path):
    from lsu_faces.signature import ImpostorModel

    quiet = ImpostorModel.prior("depthmap", 1e-4)
    noisy = ImpostorModel.prior("depthmap", 1.5e-3)
    assert noisy.threshold_m(0.01) > 1.5 * quiet.threshold_m(0.01)
    g = Gallery(tmp_path / "g.db")
    for i in range(3):
        g.enroll(f"p{i}", face_like(i, noise_m=1.5e-3))
    assert g.identify(face_like(0, noise_m=1.5e-3)).gallery_noise_mm == pytest.approx(1.5)


def test_fine_stage_aligns_the_probe_onto_each_candidate_and_ranks_like_single_comparisons():
    from lsu_faces.signature import align_to_depthmaps, compare, compare_many

    p = SignatureParams()
    c = cell_centres(p)
    x, y = np.meshgrid(c, c)
    rng = np.random.default_rng(5)
    bumps = [(rng.uniform(-0.04, 0.04, 2), rng.normal(0.0, 0.004)) for _ in range(10)]

    def height(u, v):      # an analytic face-like surface: a paraboloid with smooth bumps
        return -4.0 * (u ** 2 + v ** 2) + sum(a * np.exp(-((u - b[0]) ** 2 + (v - b[1]) ** 2) / 0.0002)
                                              for b, a in bumps)

    inside = np.hypot(x, y) <= 0.06
    points = np.stack([x[inside], y[inside], height(x, y)[inside]], axis=1)
    # candidates: the same surface moved by known translations (truth), and one map with almost nothing seen
    shifts = np.array([[0.0, 0.0, 0.0], [0.0015, -0.001, 0.0005], [-0.002, 0.0005, -0.001], [0.001, 0.002, 0.0]])
    maps = [np.where(inside, height(x - dx, y - dy) + dz, np.nan) for dx, dy, dz in shifts]
    empty = np.full_like(maps[0], np.nan)
    empty[:3, :3] = 0.0
    cell = 2 * p.extent_m / p.grid
    T = align_to_depthmaps(points, np.stack(maps + [empty]), p.extent_m, np.ones(len(points)),
                           (4 * cell, 1.5 * cell), iterations=10, trim=0.1)
    for k, shift in enumerate(shifts):
        assert np.abs(T[k, :3, 3] - shift).max() < 1e-4, (k, T[k, :3, 3], shift)
        assert np.allclose(T[k, :3, :3], np.eye(3), atol=5e-3)
    assert np.array_equal(T[-1], np.eye(4))                # fewer than 20 shared points: left where it was
    # the batch gives each candidate its own result, in the candidates' order, whatever their noise (smoothing)
    probe = face_like(7, noise_m=3e-4)
    refs = [face_like(s, noise_m=n) for s, n in ((3, 1e-4), (7, 1e-4), (9, 1.2e-3), (7, 1.2e-3), (4, 0.0))]
    batch = [d for _, d, _ in compare_many(probe, refs)]
    single = [compare(probe, r)[1] for r in refs]
    assert np.allclose(batch, single, rtol=1e-9, atol=0.0)
    assert int(np.argmin(batch)) in (1, 3) and min(batch[1], batch[3]) < 0.5 * min(batch[0], batch[2], batch[4])
    # scans whose noise differs a little share one smoothing, so that they are aligned together
    from lsu_faces.signature import SMOOTH_STEP_CELLS, smoothing_cells

    cells = [smoothing_cells(probe, face_like(1, noise_m=n)) for n in (1.28e-3, 1.33e-3, 1.38e-3, 1.6e-3, 1.85e-3)]
    assert cells[0] == cells[1] == cells[2] == 2.0 and cells[3] == 2.5 and cells[4] == 2.75
    assert all(c / SMOOTH_STEP_CELLS == round(c / SMOOTH_STEP_CELLS) for c in cells)

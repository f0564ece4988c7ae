"""Study (issue 32): a region ensemble and a model-aligned first stage against today's 1:N on the ICT population.

Population and captures as ``bench/bench_faces.py`` builds them (``capture``, ``exact_signature``: one neutral
near-frontal enrolment and two probes on other occasions per person, through the time-of-flight model "tof" and
the LSU rig "rig"; galleries beyond the captured people filled with exact-path enrolments of further ICT people).
Two splits of identities:

- ``tune`` (``LSU_STUDY_SPLIT=tune``, the default): captured people seeds 0..59 (development seeds; as many as the report split), fillers
  seeds 100..; every choice below (regions, fusion, first-stage size) is made here;
- ``report``: the bench's people (seeds ``POP_SEED``.., fillers after them), never used for a choice.

Matchers (each a rank-1 figure per gallery size N and sensor):

- ``today``: the product's 1:N: faiss first stage over `compact_vector` (``FIRST_STAGE + 1`` candidates), then
  `compare_many` (one rigid alignment, region-weighted trimmed RMS);
- ``today_all``: `compare_many` over the whole gallery (no first stage): the fine stage's own ceiling;
- ``re_*``: region ensemble after Faltemier, Bowyer & Flynn (2008): each of ``REGIONS`` (discs of the face frame
  over the expression-stable parts: nose, bridge, eye-socket rims, forehead, upper face) aligned on its own onto
  the reference map (`align_to_depthmaps` with the region's cells only), its trimmed RMS height difference taken;
  fused per pair by the geometric mean (``re_gmean``) or median (``re_median``) of the region distances (a
  distance per pair: open set keeps working), or by a Borda count over the gallery (``re_borda``, Faltemier's
  rank fusion; needs the whole candidate list); ``*_all`` over the whole gallery, ``*_fs<k>`` over the first
  ``k`` candidates of the first stage;
- first stages: ``compact`` (today's vector) and ``compact_afm``: the same vector of the map re-gridded after a
  rigid alignment onto the ICT mean face (the "average face model" of Kakadiaris et al. 2007), so a face frame
  a few degrees off no longer tilts every block; recall of the true person among the first k.

Run: ``LSU_STUDY_SPLIT=tune .venv/bin/python bench/study_faces_regions.py``, then ``LSU_STUDY_SPLIT=report``
(seeded, deterministic; captures from the bench's cache, a miss renders: the tuning people's ~360 captures take
~40 min on a loaded 2-core host). The tuning split compares every gallery entry (``LSU_STUDY_FULL=1``) at
N = 20, 100, with the per-region alignments (``LSU_STUDY_EACH_REGION=1``); the report split at N = 20, 100,
1,000 compares only the first stage's candidates and the regions after the whole face's alignment (the
per-region alignments and the model-aligned first stage lost on the tuning split), and states the variant the
tuning split chose (``chosen_on_tune``) beside today's. Writes ``bench/results/study_faces_regions_<split>.json``.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_faces as bf  # noqa: E402

from lsu_common.arrays import AnyArray  # noqa: E402
from lsu_faces.gallery import FIRST_STAGE, _Index  # noqa: E402
from lsu_faces.identity import load_basis  # noqa: E402
from lsu_faces.signature import (  # noqa: E402
    CORE_REGIONS,
    Signature,
    _depth_map,
    _grid_points,
    _region_weights,
    _sample_gradient,
    align_to_depthmap,
    align_to_depthmaps,
    compact_vector,
    compare_many,
    mirror_completed,
    smoothed,
    smoothing_cells,
)

SPLIT = os.environ.get("LSU_STUDY_SPLIT", "tune")
NS = tuple(int(n) for n in os.environ.get("LSU_STUDY_NS", "20,100" if SPLIT == "tune" else "20,100,1000").split(","))
if SPLIT == "tune":
    PEOPLE = list(range(0, 60))
    FILL0 = 100
else:
    PEOPLE = [bf.POP_SEED + i for i in range(bf.POP_TEST)]
    FILL0 = bf.POP_SEED + bf.POP_TEST
FIRST_KS = tuple(int(k) for k in os.environ.get("LSU_STUDY_KS", "11,20,30").split(","))   # first-stage sizes
# 0: only the first stages' candidates are compared (the ``*_all`` matchers are left out): for N = 1,000
FULL = os.environ.get("LSU_STUDY_FULL", "1" if SPLIT == "tune" else "0") == "1"
# 0: the regions are compared after the whole face's alignment only (the per-region alignments lost on the
# tuning split and cost most of the time) and the model-aligned first stage is left out (lower recall there)
EACH_REGION = os.environ.get("LSU_STUDY_EACH_REGION", "1" if SPLIT == "tune" else "0") == "1"
PEOPLE = PEOPLE[: int(os.environ.get("LSU_STUDY_PEOPLE", len(PEOPLE)))]
SENSORS = tuple(os.environ.get("LSU_STUDY_SENSORS", "tof,rig").split(","))
RESULT = Path(os.environ.get("LSU_STUDY_OUT", str(Path(__file__).resolve().parent / "results" /
                                                   f"study_faces_regions_{SPLIT}.json")))

# regions: (centre x, centre y, radius) in the face frame [m] (x right, y down, origin the nose tip)
REGIONS = {
    **CORE_REGIONS,     # nose, nose_wide, bridge, eye_l, eye_r: the ensemble the product adopted from this study
    "brow": (0.0, -0.05, 0.03),
    "forehead": (0.0, -0.062, 0.022),
    "cheek_l": (-0.04, 0.0, 0.02),
    "cheek_r": (0.04, 0.0, 0.02),
    "upper": (0.0, -0.025, 0.05),
}
REGION_TRIM = 0.1


def region_distances(probe: Signature, refs: list[Signature]) -> AnyArray:
    """(2 x regions, refs) trimmed RMS height differences [m]: rows [0, R) after each region's own rigid
    alignment, rows [R, 2R) after one alignment of the whole face (today's, region-weighted); inf: too few
    shared cells."""
    R = len(REGIONS)
    out = np.full((2 * R, len(refs)), np.inf)
    sigmas = [smoothing_cells(probe, r) for r in refs]
    for sigma in sorted(set(sigmas)):
        group = [j for j, s in enumerate(sigmas) if s == sigma]
        pp, _ = _grid_points(smoothed(mirror_completed(probe), sigma))
        data = np.stack([smoothed(mirror_completed(refs[j]), sigma).data for j in group])
        params = probe.params
        cell = 2 * params.extent_m / params.grid
        sub = pp[::3]
        Tg = align_to_depthmaps(sub, data, params.extent_m, _region_weights(sub), (4 * cell, 1.5 * cell),
                                iterations=5, trim=0.25)
        for r, (cx, cy, rad) in [(i, reg) for i, reg in enumerate(REGIONS.values())] + \
                [(R + i, reg) for i, reg in enumerate(REGIONS.values())]:
            pts = pp[np.hypot(pp[:, 0] - cx, pp[:, 1] - cy) <= rad]
            if len(pts) < 20:
                continue
            if r < R and not EACH_REGION:
                continue
            if r < R:
                sub = pts[:: max(1, len(pts) // 150)]       # ~150 points fix 6 unknowns; the distance uses all
                T = align_to_depthmaps(sub, data, params.extent_m, np.ones(len(sub)), (4 * cell, 1.5 * cell),
                                       iterations=5, trim=0.25)
            else:
                T = Tg
            moved = pts @ T[:, :3, :3].transpose(0, 2, 1) + T[:, None, :3, 3]
            h, _, _ = _sample_gradient(data, params.extent_m, moved[..., :2])
            diff = np.abs(moved[..., 2] - h)
            for k, j in enumerate(group):
                d = diff[k][np.isfinite(diff[k])]
                if len(d) < 0.5 * len(pts) or len(d) < 15:
                    continue
                d = np.sort(d)[: max(1, int(round(len(d) * (1 - REGION_TRIM))))]
                out[r, j] = float(np.sqrt(np.mean(d ** 2)))
    return out


def afm_signature(sig: Signature) -> Signature:
    """The map re-gridded after a rigid alignment of its cells onto the ICT mean face (its nose-tip frame)."""
    b = load_basis()
    mean = Signature("depthmap", b.mean, sig.params)
    pp, _ = _grid_points(smoothed(mirror_completed(sig), 1.0))
    near = pp[np.hypot(pp[:, 0], pp[:, 1]) <= 0.06]
    if len(near) < 20:
        return sig
    cell = 2 * sig.params.extent_m / sig.params.grid
    w = np.where(near[:, 1] < 0.012, 1.0, 0.2)     # the upper face leads (the mouth moves)
    T = align_to_depthmap(near[::2], mean, w[::2], (6 * cell, 2 * cell), iterations=8, trim=0.25)
    pts, _ = _grid_points(sig)
    moved = pts @ T[:3, :3].T + T[:3, 3]
    return Signature("depthmap", _depth_map(moved, sig.params), sig.params, sig.points_used, sig.noise_m)


def fuse(dist: AnyArray, kind: str, use: list[int]) -> AnyArray:
    """One distance per reference from (regions, refs) ``dist`` over the regions ``use``."""
    d = dist[use]
    if kind == "gmean":
        with np.errstate(divide="ignore"):
            ld = np.log(np.where(np.isfinite(d), d, 1.0))
        bad = ~np.isfinite(d)
        m = np.where(bad, 0.0, ld).sum(axis=0) / np.maximum(np.sum(~bad, axis=0), 1)   # mean over the finite ones
        m = np.where(np.sum(~bad, axis=0) >= max(1, len(use) // 2), m, np.inf)
        return np.exp(m)
    if kind == "median":
        d = np.where(np.isfinite(d), d, 1.0)
        return np.median(d, axis=0)
    # borda: per region, rank of each reference (0 best); summed
    ranks = np.argsort(np.argsort(np.where(np.isfinite(d), d, np.inf), axis=1, kind="stable"), axis=1)
    return ranks.sum(axis=0).astype(np.float64)


def main() -> None:
    t_start = time.perf_counter()
    nmax = max(NS)
    fillers = list(range(FILL0, FILL0 + nmax - len(PEOPLE)))
    filler_sigs = [Signature.from_bytes(b) for b in bf._parallel(bf.exact_signature, fillers)]
    print(f"[study] {len(fillers)} fillers after {time.perf_counter() - t_start:.0f} s", flush=True)
    results: dict[str, object] = {"split": SPLIT, "people": PEOPLE[:1] + PEOPLE[-1:], "fillers_from": FILL0,
                                  "ns": list(NS), "regions": REGIONS, "sensors": {}}
    afm_cache: dict[int, AnyArray] = {}
    for sensor in SENSORS:
        recs = bf._parallel(bf.capture, [(sensor, s, k) for s in PEOPLE for k in range(3)])
        sigs = {(r["seed"], r["k"]): Signature.from_bytes(r["sig"]) for r in recs if r["sig"]}  # type: ignore[arg-type]
        ids = [s for s in PEOPLE if (s, 0) in sigs]
        gallery = [sigs[(s, 0)] for s in ids] + filler_sigs
        probes = [(s, k) for s in ids for k in (1, 2)]
        vec = np.stack([compact_vector(g) for g in gallery])
        vec_afm = np.stack([afm_cache[i] if i >= len(ids) and i in afm_cache else compact_vector(afm_signature(g))
                            for i, g in enumerate(gallery)])
        for i in range(len(ids), len(gallery)):
            afm_cache[i] = vec_afm[i]
        print(f"[study] {sensor}: {len(sigs)} captures, vectors after {time.perf_counter() - t_start:.0f} s",
              flush=True)
        hits: dict[str, dict[int, list[bool]]] = {}
        recall: dict[str, dict[int, list[bool]]] = {}
        per_region_gen: list[AnyArray] = []
        per_region_imp: list[AnyArray] = []

        def note(table: dict[str, dict[int, list[bool]]], name: str, n: int, v: bool) -> None:
            table.setdefault(name, {}).setdefault(n, []).append(v)

        nmax = len(gallery)
        idxs, idxs_afm = {}, {}
        for n in NS:
            n = min(n, nmax)
            idxs[n], idxs_afm[n] = _Index(()), _Index(())
            idxs[n].build(list(range(n)), [str(i) for i in range(n)], vec[:n], [0.0] * n)
            idxs_afm[n].build(list(range(n)), [str(i) for i in range(n)], vec_afm[:n], [0.0] * n)
        names = list(REGIONS)
        R = len(names)
        sets = {"all": list(range(len(names))),
                "rigid": [names.index(r) for r in ("nose", "nose_wide", "bridge", "eye_l", "eye_r", "brow",
                                                   "forehead", "upper")],
                "core": [names.index(r) for r in ("nose", "nose_wide", "bridge", "eye_l", "eye_r")]}
        sets.update({f"g{k}": [R + i for i in v] for k, v in list(sets.items())})
        if not EACH_REGION:
            sets = {k: v for k, v in sets.items() if k.startswith("g")}
        for p in probes:
            s, _ = p
            true = ids.index(s)
            if p not in sigs:
                for n in idxs:
                    if true >= n:
                        continue
                    for name in ("today", "today_all") if FULL else ("today",):
                        note(hits, name, n, False)
                continue
            probe = sigs[p]
            v1, v2 = compact_vector(probe), compact_vector(afm_signature(probe))
            c1s = {n: [e for e, _ in idxs[n].search(v1, max(FIRST_KS))] for n in idxs}
            c2s = {n: [e for e, _ in idxs_afm[n].search(v2, max(FIRST_KS))] for n in idxs}
            # the whole gallery once (a smaller gallery is a prefix of it), or only the candidates
            comp = list(range(nmax)) if FULL else sorted({e for c in (*c1s.values(), *(c2s.values() if EACH_REGION else ()))
                                                          for e in c})
            d_full = np.full(nmax, np.inf)
            d_full[comp] = [f[1] for f in compare_many(probe, [gallery[e] for e in comp])]
            rd_full = np.full((2 * R, nmax), np.inf)
            rd_full[:, comp] = region_distances(probe, [gallery[e] for e in comp])
            for n in idxs:
                if true >= n:             # not enrolled in a gallery this small (the bench's rule)
                    continue
                c1, c2 = c1s[n], c2s[n]
                for k in FIRST_KS:
                    note(recall, f"compact_k{k}", n, true in c1[:k])
                    note(recall, f"compact_afm_k{k}", n, true in c2[:k])
                d_all = d_full[:n]
                if FULL:
                    note(hits, "today_all", n, int(np.argmin(d_all)) == true)
                cand = c1[:FIRST_STAGE + 1]
                note(hits, "today", n, min(cand, key=lambda e: (d_all[e], e)) == true)
                for k in FIRST_KS[1:]:
                    if EACH_REGION:
                        note(hits, f"today_afm_fs{k}", n, min(c2[:k], key=lambda e: (d_all[e], e)) == true)
                    note(hits, f"today_fs{k}", n, min(c1[:k], key=lambda e: (d_all[e], e)) == true)
                rd = rd_full[:, :n]
                if n == min(idxs):
                    per_region_gen.append(rd[:, true])
                    per_region_imp.append(np.delete(rd, true, axis=1))
                for sname, use in sets.items():
                    for kind in ("gmean", "median", "borda"):
                        f = fuse(rd, kind, use)
                        if FULL:
                            note(hits, f"re_{kind}_{sname}_all", n, int(np.argmin(f)) == true)
                        for k in FIRST_KS:
                            for tag, cc in (("afm_", c2[:k]), ("", c1[:k])) if EACH_REGION else (("", c1[:k]),):
                                ff = fuse(rd[:, cc], kind, use)
                                note(hits, f"re_{kind}_{sname}_{tag}fs{k}", n, cc[int(np.argmin(ff))] == true)
                    fg = fuse(rd, "gmean", use)
                    comb = np.log(fg) + np.log(d_all)
                    if FULL:
                        note(hits, f"re_gmean_{sname}_plus_today_all", n, int(np.argmin(comb)) == true)
                    for k in FIRST_KS:
                        for tag, cc in (("afm_", c2[:k]), ("", c1[:k])) if EACH_REGION else (("", c1[:k]),):
                            cb = np.log(fuse(rd[:, cc], "gmean", use)) + np.log(d_all[cc])
                            note(hits, f"re_gmean_{sname}_plus_today_{tag}fs{k}", n, cc[int(np.argmin(cb))] == true)
                for r, name in enumerate(names):
                    if FULL:
                        note(hits, f"region_{name}_all", n, int(np.argmin(rd[r])) == true)
                        note(hits, f"region_g{name}_all", n, int(np.argmin(rd[R + r])) == true)
        for n in idxs:
            print(f"[study] {sensor} N={n} after {time.perf_counter() - t_start:.0f} s: " + ", ".join(
                f"{k}={100 * np.mean(v[n]):.1f}" for k, v in hits.items()
                if k in ("today", "today_all", "re_gmean_rigid_all", "re_borda_all_all")), flush=True)

        def pct(v: list[bool], n: int) -> float:
            """Share of the probes of the gallery's people (a capture refused as no face counts as a miss for
            every matcher)."""
            members = sum(1 for s, _ in probes if ids.index(s) < n)
            return float(100.0 * np.sum(v) / members) if v else float("nan")

        gen = np.array(per_region_gen)
        imp = np.concatenate(per_region_imp, axis=1) if per_region_imp else np.zeros((len(REGIONS), 0))
        dprime = {}
        for r, name in enumerate([*REGIONS, *[f"g{n}" for n in REGIONS]]):
            g, i_ = gen[:, r], imp[r]
            g, i_ = np.log(g[np.isfinite(g)]), np.log(i_[np.isfinite(i_)])
            if len(g) < 2 or len(i_) < 2:
                continue
            dprime[name] = {"genuine_mm_median": float(1000 * np.exp(np.median(g))),
                            "impostor_mm_median": float(1000 * np.exp(np.median(i_))),
                            "d_prime_log": float((i_.mean() - g.mean()) / np.sqrt((i_.var() + g.var()) / 2))}
        results["sensors"][sensor] = {  # type: ignore[index]
            "probes": len(probes),
            "rank1_pct": {name: {str(n): pct(v, n) for n, v in t.items()} for name, t in sorted(hits.items())},
            "first_stage_recall_pct": {name: {str(n): pct(v, n) for n, v in t.items()} for name, t in sorted(recall.items())},
            "regions": dprime}
        RESULT.write_text(json.dumps(results, indent=1, sort_keys=True) + "\n")
    tune_file = RESULT.with_name("study_faces_regions_tune.json")
    if SPLIT == "report" and tune_file.exists():
        # the variant chosen on the tuning split (rank-1 at its largest N, ToF + rig; ties: fewer candidates,
        # then the name), and its figures here
        tune = json.loads(tune_file.read_text())["sensors"]
        here = results["sensors"]  # type: ignore[assignment]
        n_t = {s: str(max(int(n) for n in tune[s]["rank1_pct"]["today"])) for s in tune}   # a refused enrolment: N - 1
        names = [k for k in here["tof"]["rank1_pct"] if k in tune["tof"]["rank1_pct"]]   # type: ignore[index]

        def key(k: str) -> tuple[float, int, str]:
            fs = int(k.rsplit("fs", 1)[1]) if "_fs" in k else FIRST_STAGE + 1
            return (-sum(tune[s]["rank1_pct"][k][n_t[s]] for s in tune), fs, k)

        best = min(names, key=key)
        results["chosen_on_tune"] = {"name": best, "tune_n": n_t, "tune": {s: tune[s]["rank1_pct"][best] for s in tune},
                                     "report": {s: here[s]["rank1_pct"][best] for s in here},  # type: ignore[index]
                                     "today_report": {s: here[s]["rank1_pct"]["today"] for s in here}}  # type: ignore[index]
    results["wall_s"] = time.perf_counter() - t_start
    results["host"] = "2 cores shared with 4 other agents: times are inflated"
    RESULT.write_text(json.dumps(results, indent=1, sort_keys=True) + "\n")
    print(f"[study] done in {results['wall_s']:.0f} s", flush=True)


if __name__ == "__main__":
    main()

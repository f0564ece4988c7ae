"""Study (issue 32): does identity-from-model-fit rank the ICT population better than today's depth-map distance?

Population and captures exactly as ``bench/bench_faces.py`` builds them (``population()``): the ICT model's
people with seeds ``POP_SEED``.. (never used for tuning the code), one neutral near-frontal enrolment and
``POP_PROBES`` probes on other occasions (expression, pose, hair, collar), each through the time-of-flight
model ("tof") and the LSU rig ("rig"); galleries of N > ``POP_TEST`` filled with exact-path enrolments of
further ICT people. The captures are read back from the bench's content-keyed cache (``bench_faces.capture``,
``bench_faces.exact_signature``: the same code gives cache hits; a miss renders, slowly).

Matchers compared, each on N = 20, 100, 1000 (the bench's galleries):

- ``today``: the product's 1:N: faiss first stage over `compact_vector` (``FIRST_STAGE + 1`` candidates, as the
  bench), then `compare_many` (alignment + region-weighted trimmed RMS) on those;
- ``id_*``: the identity part of a face-model fit (`lsu_faces.identity.fit_signature`), ranked over the whole
  gallery (the distances are a few dozen numbers: no first stage needed):
  ``id_vec`` the Euclidean distance of `identity_vector` (RMS shape difference of the rigid face [m]),
  ``id_w<k>`` the Euclidean distance of the first k raw weights (= Mahalanobis under the N(0, 1) prior),
  ``id_cos`` the cosine distance of the raw weights; fit variants: the expression prior sigma (0.25, 0.5,
  1.0) and the identity modes fitted (20, 40, 60 of the basis);
- ``fuse_*``: ``fuse_idfirst`` the identity vector as first stage (``FIRST_STAGE + 1`` candidates), today's
  compare as the fine stage; ``fuse_z<w>`` the union of both first stages' candidates ranked by today's
  z-score plus w times the identity vector's, each z-scored with the log-distance mean/std of the gallery's
  own impostor pairs (300 seeded pairs, as the product calibrates); controls without the identity score:
  ``control_union_today`` (the union ranked by today's distance) and ``control_wide_today`` (as many
  candidates from today's first stage as the union holds, ranked by today's distance).

Figures per matcher and sensor: rank-1 at each N, first-stage recall (true person among the first-stage
candidates), genuine/impostor median distance and d' (each probe against its own enrolment and the next 20
test people's, the bench's pairs). The per-capture fit cost is timed (median ms of ``fit_signature``; the
host is shared: absolute times may be inflated). Fit accuracy against the generator's own identity weights
(``lsu_sim.ict.identity_weights``: ground truth) is reported as the RMS weight error per sensor.

``fit_variant_sweep``: the fit variants against the generator's weights (rigid-face RMS error of one solve of
`fit_identity` on 8 people's exact, ToF enrolment and ToF probe maps): what the variants can gain at most.

Tuning honesty: the test people are split in halves by index (first half "select", second half "report");
the variant and fusion weight are chosen on the select half only, and the report half's figures of that
choice are given beside the full population's.

Run: ``.venv/bin/python bench/study_faces_identity.py`` (seeded, deterministic: a second run gives the same
figures; fits cached in ``~/.cache/lsu/study_faces_identity``; the first run fits ~1,300 maps, about 15 min on a
loaded 2-core host). ``LSU_STUDY_NS`` (default 20,100,1000) sets the gallery sizes, ``LSU_STUDY_VARIANTS`` adds fit
variants to the ranking (each refits every map; the sweep below covers them all cheaply). Writes ``bench/results/study_faces_identity.json``.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_faces as bf  # noqa: E402

from lsu_common.arrays import AnyArray  # noqa: E402
from lsu_faces import identity as ident  # noqa: E402
from lsu_faces.gallery import FIRST_STAGE, _Index  # noqa: E402
from lsu_faces.signature import (  # noqa: E402
    REGION_WEIGHTS_FIRST_PASS,
    Signature,
    compact_vector,
    compare,
    compare_many,
)

NS = tuple(int(n) for n in os.environ.get("LSU_STUDY_NS", "20,100,1000").split(","))   # gallery sizes
FIT_CACHE = Path(os.environ.get("LSU_STUDY_CACHE", str(Path.home() / ".cache" / "lsu" / "study_faces_identity")))
WORKERS = int(os.environ.get("LSU_STUDY_WORKERS", "2"))
# fit variants: (expression prior sigma, identity modes fitted)
ALL_VARIANTS = {"s0.5_k60": (0.5, 60), "s0.05_k60": (0.05, 60), "s0.25_k60": (0.25, 60), "s1.0_k60": (1.0, 60), "s0.5_k40": (0.5, 40),
                "s0.5_k20": (0.5, 20)}
# the product's fit (s0.5_k60) always; others by name (each costs a fit of every capture and filler)
VARIANTS = {n: ALL_VARIANTS[n] for n in ["s0.5_k60"] + [v for v in os.environ.get("LSU_STUDY_VARIANTS", "").split(",")
                                                         if v in ALL_VARIANTS and v != "s0.5_k60"]}
FUSE_WEIGHTS = (0.25, 0.5, 1.0, 2.0)
RESULT = Path(__file__).resolve().parent / "results" / "study_faces_identity.json"


def _fit_tag() -> str:
    h = hashlib.sha256(Path(ident.__file__).read_bytes())
    h.update(ident.basis_path().read_bytes())
    return h.hexdigest()[:16]


def fit_job(job: tuple[bytes, str]) -> dict[str, object]:
    """Fit variant ``name`` to one signature blob (cached by content); returns weights and the fit's time."""
    blob, name = job
    sigma, modes = ALL_VARIANTS[name]
    key = hashlib.sha256(blob + json.dumps([name, sigma, modes, _fit_tag()]).encode()).hexdigest()[:24]
    path = FIT_CACHE / f"{key}.npz"
    if path.exists():
        with np.load(path) as z:
            return {k: z[k] for k in z.files}
    b = ident.load_basis()
    if modes < len(b.identity):
        b = ident.FaceBasis(b.grid, b.extent_m, b.mean, b.identity[:modes], b.expression, b.expression_names,
                            b.rigid_weight)
    ident.EXPRESSION_SIGMA = sigma       # fit_identity reads the module's prior (one variant per call)
    sig = Signature.from_bytes(blob)
    t0 = time.perf_counter()
    try:
        fit = ident.fit_signature(sig, b)
        out = {"identity": fit.identity, "expression": fit.expression, "residual": np.array(fit.residual_m),
               "vec": ident.identity_vector(fit, b), "ok": np.array(True)}
    except ident.BasisError:
        out = {"identity": np.full(modes, np.nan), "expression": np.full(len(b.expression), np.nan),
               "residual": np.array(np.nan), "vec": np.full(modes, np.nan, np.float32), "ok": np.array(False)}
    out["ms"] = np.array((time.perf_counter() - t0) * 1000.0)
    ident.EXPRESSION_SIGMA = 0.5
    FIT_CACHE.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, **out)
    os.replace(tmp, path)
    return out


def prior_sweep(people: int = 8) -> dict[str, dict[str, float]]:
    """Ground truth for the fit variants, cheaply: the rigid-face RMS error [mm] of the fitted identity (one
    solve of `fit_identity`, no re-alignment) against the generator's weights, per expression prior sigma and
    identity modes fitted, on ``people`` exact-path enrolments and ToF enrolments and probes (test seeds)."""
    from lsu_sim.ict import identity_weights

    b0 = ident.load_basis()
    P = b0.projection
    jobs = [("exact_filler", bf.exact_signature(bf.POP_SEED + bf.POP_TEST + i), bf.POP_SEED + bf.POP_TEST + i)
            for i in range(people)]
    for k, tag in ((0, "tof_enrol"), (1, "tof_probe")):
        jobs += [(tag, bf.capture(("tof", bf.POP_SEED + i, k))["sig"], bf.POP_SEED + i) for i in range(people)]
    out: dict[str, dict[str, float]] = {}
    for name, (sigma, modes) in ALL_VARIANTS.items():
        b = ident.FaceBasis(b0.grid, b0.extent_m, b0.mean, b0.identity[:modes], b0.expression, b0.expression_names,
                            b0.rigid_weight)
        ident.EXPRESSION_SIGMA = sigma
        errs: dict[str, list[float]] = {}
        for tag, blob, seed in jobs:
            if not blob:
                continue
            sig = Signature.from_bytes(blob)  # type: ignore[arg-type]
            fit = ident.fit_identity(sig.data, sig.params.extent_m, sig.noise_m, b)
            w = np.zeros(len(b0.identity))
            w[:modes] = fit.identity
            errs.setdefault(tag, []).append(1000 * float(np.linalg.norm(P @ (w - identity_weights(seed)[:len(w)]))))
        out[name] = {f"vec_err_mm_{t}": float(np.median(e)) for t, e in errs.items()}
    ident.EXPRESSION_SIGMA = 0.5
    # the reference: no fit at all (the mean face, all weights 0)
    out["mean_face_no_fit"] = {f"vec_err_mm_{t}": float(np.median([1000 * np.linalg.norm(
        P @ identity_weights(seed)[:len(b0.identity)]) for tg, blob, seed in jobs if tg == t and blob]))
        for t in ("exact_filler", "tof_enrol", "tof_probe")}
    return out


def d_prime(gen: AnyArray, imp: AnyArray) -> float:
    gen, imp = gen[np.isfinite(gen)], imp[np.isfinite(imp)]
    return float((imp.mean() - gen.mean()) / np.sqrt((imp.var() + gen.var()) / 2))


def main() -> None:
    t_start = time.perf_counter()
    test_seeds = [bf.POP_SEED + i for i in range(bf.POP_TEST)]
    fillers = [bf.POP_SEED + bf.POP_TEST + i for i in range(max(NS) - bf.POP_TEST)]
    t0 = time.perf_counter()
    filler_blobs = bf._parallel(bf.exact_signature, fillers)
    print(f"[study] {len(fillers)} fillers in {time.perf_counter() - t0:.0f} s", flush=True)
    filler_sigs = [Signature.from_bytes(b) for b in filler_blobs]
    filler_vecs = np.stack([compact_vector(s) for s in filler_sigs])
    half = len(test_seeds) // 2
    select = set(test_seeds[:half])
    from lsu_sim.ict import identity_weights

    results: dict[str, object] = {"people": len(test_seeds), "probes_per_person": bf.POP_PROBES, "ns": list(NS),
                                  "first_stage": FIRST_STAGE + 1, "variants": VARIANTS, "sensors": {}}
    for sensor in ("tof", "rig"):
        t0 = time.perf_counter()
        recs = bf._parallel(bf.capture, [(sensor, s, k) for s in test_seeds for k in range(1 + bf.POP_PROBES)])
        print(f"[study] {sensor}: {len(recs)} captures in {time.perf_counter() - t0:.0f} s", flush=True)
        blobs = {(r["seed"], r["k"]): r["sig"] for r in recs if r["sig"]}
        sigs = {key: Signature.from_bytes(b) for key, b in blobs.items()}  # type: ignore[arg-type]
        ids = [s for s in test_seeds if (s, 0) in sigs]
        all_ids = ids + fillers
        gallery_blobs = [blobs[(s, 0)] for s in ids] + filler_blobs
        gallery_sigs = [sigs[(s, 0)] for s in ids] + filler_sigs
        probes = [(s, k) for s in test_seeds for k in range(1, 1 + bf.POP_PROBES) if s in ids]
        # ---- fits (every variant, every capture and gallery filler)
        fits: dict[str, dict[str, object]] = {}
        for name in VARIANTS:
            t0 = time.perf_counter()
            jobs = [(b, name) for b in gallery_blobs] + [(blobs[p], name) for p in probes if p in blobs]
            out = bf._parallel(fit_job, jobs)
            gal = out[:len(gallery_blobs)]
            pro = dict(zip([p for p in probes if p in blobs], out[len(gallery_blobs):]))
            fits[name] = {"gallery": gal, "probes": pro,
                          "ms_median": float(np.median([float(o["ms"]) for o in out])),   # type: ignore[arg-type]
                          "wall_s": time.perf_counter() - t0}
            print(f"[study] {sensor} {name}: {len(jobs)} fits, median {fits[name]['ms_median']:.0f} ms "
                  f"({fits[name]['wall_s']:.0f} s wall)", flush=True)
        # ---- fit accuracy against the generator's weights (ground truth)
        acc = {}
        for name, (_, modes) in VARIANTS.items():
            err_g = [np.sqrt(np.mean((f["identity"] - identity_weights(s)[:modes]) ** 2))  # type: ignore[index]
                     for s, f in zip(ids, fits[name]["gallery"][:len(ids)])]  # type: ignore[index]
            err_p = [np.sqrt(np.mean((f["identity"] - identity_weights(s)[:modes]) ** 2))  # type: ignore[index]
                     for (s, _), f in fits[name]["probes"].items()]  # type: ignore[union-attr]
            acc[name] = {"weight_rms_err_enrol": float(np.nanmedian(err_g)),
                         "weight_rms_err_probe": float(np.nanmedian(err_p))}
            if modes == len(ident.load_basis().identity):
                # the same in identity_vector's units: RMS shape error [mm] of the fitted identity over the rigid
                # face, beside two different people's RMS shape difference
                P = ident.load_basis().projection
                vec_g = [1000 * np.linalg.norm(f["vec"] - P @ identity_weights(s)[:modes])  # type: ignore[index]
                         for s, f in zip(ids, fits[name]["gallery"][:len(ids)])]  # type: ignore[index]
                vec_p = [1000 * np.linalg.norm(f["vec"] - P @ identity_weights(s)[:modes])  # type: ignore[index]
                         for (s, _), f in fits[name]["probes"].items()]  # type: ignore[union-attr]
                vec_f = [1000 * np.linalg.norm(f["vec"] - P @ identity_weights(s)[:modes])  # type: ignore[index]
                         for s, f in zip(fillers, fits[name]["gallery"][len(ids):])]  # type: ignore[index]
                W = [P @ identity_weights(s)[:modes] for s in test_seeds]
                acc[name].update({"vec_err_mm_enrol": float(np.nanmedian(vec_g)),
                                  "vec_err_mm_probe": float(np.nanmedian(vec_p)),
                                  "vec_err_mm_exact_filler": float(np.nanmedian(vec_f)),
                                  "true_two_people_mm": float(np.median([1000 * np.linalg.norm(W[i] - W[j])
                                                                         for i in range(len(W)) for j in range(i)]))})
        # ---- distances: every matcher gives a function probe -> distances to gallery entries [0..n)
        def id_dist(name: str, kind: str, probe: tuple[int, int], n: int) -> AnyArray:
            f = fits[name]
            p = f["probes"].get(probe)  # type: ignore[union-attr]
            if p is None:
                return np.full(n, np.inf)
            if kind == "vec":
                G = np.stack([g["vec"] for g in f["gallery"][:n]]).astype(np.float64)  # type: ignore[index]
                return np.linalg.norm(G - p["vec"], axis=1)
            G = np.stack([g["identity"] for g in f["gallery"][:n]])  # type: ignore[index]
            q = p["identity"]
            if kind == "cos":
                return 1.0 - (G @ q) / (np.linalg.norm(G, axis=1) * np.linalg.norm(q) + 1e-12)
            k = int(kind[1:])
            return np.linalg.norm(G[:, :k] - q[:k], axis=1)

        id_matchers = {f"id_vec_{n}": (n, "vec") for n in VARIANTS}
        id_matchers.update({f"id_w{k}_{n}": (n, f"w{k}") for n in VARIANTS for k in (10, 20, 40, 60)
                            if k <= VARIANTS[n][1]})
        id_matchers.update({f"id_cos_{n}": (n, "cos") for n in VARIANTS})
        out_s: dict[str, dict[str, float]] = {}
        rank_hits: dict[str, dict[int, list[bool]]] = {}
        recall_hits: dict[str, dict[int, list[bool]]] = {}

        def note(name: str, N: int, probe: tuple[int, int], hit: bool, recalled: bool | None = None) -> None:
            rank_hits.setdefault(name, {}).setdefault(N, []).append(hit)
            if recalled is not None:
                recall_hits.setdefault(name, {}).setdefault(N, []).append(recalled)

        def fine(probe: tuple[int, int], cand: list[int], d_today: dict[int, float]) -> int:
            """Today's fine stage over ``cand`` (distances kept in ``d_today``, computed once): the best entry."""
            new = [e for e in cand if e not in d_today]
            if new:
                for e, f in zip(new, compare_many(sigs[probe], [gallery_sigs[e] for e in new])):
                    d_today[e] = f[1]
            return min(cand, key=lambda e: (d_today[e], e))

        probe_order: list[tuple[int, int]] = []
        for N in NS:
            n = min(N, len(all_ids))   # a refused enrolment: N - 1 entries (as the bench)
            sub = _Index(())
            vecs = np.concatenate([np.stack([compact_vector(s) for s in gallery_sigs[:len(ids)]]), filler_vecs])[:n]
            sub.build(list(range(n)), [str(s) for s in all_ids[:n]], vecs, [0.0] * n)
            # impostor statistics of the gallery's own pairs (the product's calibration), for the z-scores
            rng = np.random.default_rng(5)
            pairs = [(int(a), int(b)) for a, b in rng.integers(0, n, size=(300, 2)) if a != b]
            today_imp = np.log([compare(gallery_sigs[a], gallery_sigs[b])[1] for a, b in pairs])
            vname = "s0.5_k60"
            gv = np.stack([g["vec"] for g in fits[vname]["gallery"][:n]]).astype(np.float64)  # type: ignore[index]
            id_imp = np.log([np.linalg.norm(gv[a] - gv[b]) for a, b in pairs])
            zt = (today_imp[np.isfinite(today_imp)].mean(), today_imp[np.isfinite(today_imp)].std())
            zi = (id_imp.mean(), id_imp.std())
            members = ids[:min(n, len(ids))]
            for probe in probes:
                s, _ = probe
                if s not in members:
                    continue
                if N == NS[-1]:
                    probe_order.append(probe)
                true = ids.index(s)
                if probe not in sigs:
                    for name in ["today", "fuse_idfirst", "control_union_today", "control_wide_today", *id_matchers,
                                 *[f"fuse_z{w}" for w in FUSE_WEIGHTS]]:
                        note(name, N, probe, False, False)
                    continue
                # today's
                cand = [e for e, _ in sub.search(compact_vector(sigs[probe]), FIRST_STAGE + 1)]
                found = compare_many(sigs[probe], [gallery_sigs[e] for e in cand])
                d_today = {e: f[1] for e, f in zip(cand, found)}
                best = min(cand, key=lambda e: (d_today[e], e))
                note("today", N, probe, best == true, true in cand)
                # identity matchers over the whole gallery
                for name, (v, kind) in id_matchers.items():
                    d = id_dist(v, kind, probe, n)
                    note(name, N, probe, bool(np.isfinite(d[true]) and np.sum(d <= d[true]) == 1))
                # fusion: identity first stage, today's fine stage
                did = id_dist(vname, "vec", probe, n)
                cand_id = [int(e) for e in np.argsort(did, kind="stable")[:FIRST_STAGE + 1]]
                note("fuse_idfirst", N, probe, fine(probe, cand_id, d_today) == true, true in cand_id)
                union = sorted(set(cand) | set(cand_id))
                # controls: the union's (or as many compact candidates') gain without the identity score
                best = min(union, key=lambda e: (d_today[e], e))
                note("control_union_today", N, probe, best == true, true in union)
                wide = [e for e, _ in sub.search(compact_vector(sigs[probe]), len(union))]
                note("control_wide_today", N, probe, fine(probe, wide, d_today) == true, true in wide)
                for w, label in [(w, f"fuse_z{w}") for w in FUSE_WEIGHTS]:
                    score = {e: (np.log(d_today[e]) - zt[0]) / zt[1] + w * (np.log(did[e]) - zi[0]) / zi[1]
                             for e in union}
                    best = min(union, key=lambda e: (score[e], e))
                    note(label, N, probe, best == true, true in union)
            print(f"[study] {sensor} N={N} done after {time.perf_counter() - t_start:.0f} s", flush=True)
        # ---- genuine / impostor distances (the bench's pairs) for today and the identity vectors
        dist_fig: dict[str, dict[str, float]] = {}
        gen_pairs, imp_pairs = [], []
        for nidx, s in enumerate(test_seeds):
            for k in range(1, 1 + bf.POP_PROBES):
                if (s, k) not in sigs:
                    continue
                for m in range(21):
                    other = test_seeds[(nidx + m) % len(test_seeds)]
                    if other in ids and (m == 0 or other != s):
                        (gen_pairs if m == 0 else imp_pairs).append(((s, k), ids.index(other)))

        def pair_d(fn) -> dict[str, float]:  # noqa: ANN001
            g = np.array([fn(p, e) for p, e in gen_pairs], dtype=np.float64)
            i_ = np.array([fn(p, e) for p, e in imp_pairs], dtype=np.float64)
            return {"genuine_median": float(np.nanmedian(g[np.isfinite(g)])),
                    "impostor_median": float(np.nanmedian(i_[np.isfinite(i_)])), "d_prime": d_prime(g, i_)}

        dist_fig["today_first_pass_mm"] = pair_d(lambda p, e: 1000 * compare(
            sigs[p], gallery_sigs[e], smooth=0.0, weights=REGION_WEIGHTS_FIRST_PASS)[1])
        dist_fig["today_mm"] = pair_d(lambda p, e: 1000 * compare(sigs[p], gallery_sigs[e])[1])
        for name, (v, kind) in id_matchers.items():
            scale = 1000.0 if kind == "vec" else 1.0
            dist_fig[name + ("_mm" if kind == "vec" else "")] = pair_d(
                lambda p, e, v=v, kind=kind, scale=scale: scale * float(id_dist(v, kind, p, len(ids))[e]))

        def pct(hits: list[bool]) -> float:
            return float(100.0 * np.mean(hits)) if hits else float("nan")

        for name in rank_hits:
            row: dict[str, float] = {}
            for N, hits in rank_hits[name].items():
                row[f"rank1_pct_n{N}"] = pct(hits)
                if N == NS[-1]:
                    sel = [h for h, p in zip(hits, probe_order) if p[0] in select]
                    rep = [h for h, p in zip(hits, probe_order) if p[0] not in select]
                    row[f"rank1_pct_n{N}_select_half"] = pct(sel)
                    row[f"rank1_pct_n{N}_report_half"] = pct(rep)
            for N, hits in recall_hits.get(name, {}).items():
                row[f"first_stage_recall_pct_n{N}"] = pct(hits)
            out_s[name] = row
        results["sensors"][sensor] = {  # type: ignore[index]
            "rank": out_s, "distances": dist_fig, "fit_accuracy": acc,
            "fit_ms_median": {n: fits[n]["ms_median"] for n in VARIANTS},
            "fit_wall_s": {n: fits[n]["wall_s"] for n in VARIANTS}, "probes": len(probe_order)}
        RESULT.write_text(json.dumps(results, indent=1, sort_keys=True) + "\n")
    # ---- the choice, on the select half only
    choice = {}
    for family in ("id_", "fuse_z"):
        names = [n for n in results["sensors"]["tof"]["rank"] if n.startswith(family)]  # type: ignore[index]
        key = f"rank1_pct_n{NS[-1]}_select_half"
        best = max(names, key=lambda n: (results["sensors"]["tof"]["rank"][n][key]  # type: ignore[index]
                                         + results["sensors"]["rig"]["rank"][n][key], n))  # type: ignore[index]
        choice[family.rstrip("_")] = best
    results["chosen_on_select_half"] = choice
    RESULT.write_text(json.dumps(results, indent=1, sort_keys=True) + "\n")
    results["fit_variant_sweep"] = prior_sweep()
    results["wall_s"] = time.perf_counter() - t_start
    results["host"] = "2 cores shared with 4 other agents: times are inflated"
    RESULT.write_text(json.dumps(results, indent=1, sort_keys=True) + "\n")
    print(json.dumps(choice), f"{results['wall_s']:.0f} s", flush=True)


if __name__ == "__main__":
    main()

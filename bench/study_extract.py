"""Leave-one-set-out study of the laser extractor's defaults: which method and parameters generalise.

Every candidate (each sub-pixel method at the default parameters, and each parameter varied one at a
time around the default) is scored on every set, each set on its own:

- real (``lsu_extract.devdata``, read from ``../shared/devdata``): ``weld`` (the weld stripes' views,
  hand-drawn masks), ``globe`` (turntable, laser-on minus laser-off reference), ``photos`` (two
  photographs with a hand-checked polyline), ``box`` (turntable pairs with two lines per row: false
  rows only; a seeded subsample of the pairs);
- simulated rig with its physics (speckle, crosstalk, blooming, skin; the renderer's per-row laser
  pixels are the reference): ``sim_plane``, ``sim_head``, ``sim_ambient`` (reddish wall at 50 %
  ambient, the laser masked to the middle rows).

Every image is extracted as a stop-snap scan extracts it, with its laser-off frame where its set has one (globe,
box: as captured; the simulated sets: one laser-off pair per scene, `bench_extract.laser_off_pairs`), else alone
(weld, photos).

Per set and candidate: RMS of the detections from a robust smooth fit along the line (the same
`devdata.smooth_fit_residuals` on every set, so real and simulated numbers compare; the simulated sets
also give the RMS to the renderer's truth), missed rows (% of clear rows) and false rows (% of scored
rows).

Choice: a candidate is eligible when its missed and false rows over all sets are at most
``ROWS_TOLERANCE_PCT`` points above the current default's (a better sub-pixel figure must not be
bought with rows). Leave-one-set-out: for each set, the eligible
candidate whose worst RMS over the *other* sets is best is chosen, and its RMS on the held-out set is
reported beside the best any candidate reached there (the regret says whether a choice made without
the set carries over to it). The default is the eligible candidate whose worst set is best (minimax
over the held-out sets), by more than ``MARGIN_PX`` (the current default stays otherwise: smaller
differences are within what the choice of frames moves). The same run prints the README's table.

Run: ``.venv/bin/python bench/study_extract.py`` (a few minutes; ``--quick`` for fewer frames).
Writes bench/results/study_extract.json.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Sequence  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_extract  # noqa: E402
from common import write_result  # noqa: E402

from lsu_common.arrays import AnyArray  # noqa: E402
from lsu_extract import devdata  # noqa: E402
from lsu_extract.detectors import SUBPIXEL_METHODS  # noqa: E402
from lsu_extract.extractor import DEFAULT_METHOD, ExtractorParams, extract_laser_line  # noqa: E402

SEED = 20261206
ROWS_TOLERANCE_PCT = 0.5   # missed / false rows (all sets) at most this far above the default's are eligible
BOX_PAIRS = 10             # box pairs drawn (seeded) of 30: two lines per row, scored for false rows only
MARGIN_PX = 0.01          # a new default must beat the current one's worst-set RMS by more than this
SINGLE = ("weld", "globe", "photos", "sim_plane", "sim_head", "sim_ambient")  # RMS is scored on these


def candidates() -> dict[str, ExtractorParams]:
    """name -> parameters: every sub-pixel method at the defaults, then one parameter at a time."""
    base = ExtractorParams()
    out = {"default": base}
    out.update({f"method={m}": replace(base, method=m) for m in SUBPIXEL_METHODS if m != DEFAULT_METHOD})
    adaptive = replace(base, method="adaptive")
    out["adaptive+clipped_centre=red"] = replace(adaptive, clipped_centre="red")
    out["adaptive+max_width_px=20"] = replace(adaptive, max_width_px=20.0)
    out["grow_wide=False"] = replace(base, grow_wide=False)
    for name, values in (("red_rise_ratio", (0.0, 0.3, 0.7)), ("contrast_sigmas", (0.0, 6.0, 10.0)), ("ambiguity_ratio", (0.5, 0.75)),
                         ("clipped_centre", ("red",)), ("saturation_level", (255,)),
                         ("window_px", (8, 16)), ("adaptive_width_px", (4.0, 6.0, 7.0)), ("max_width_px", (12.0, 20.0, 24.0))):
        for value in values:
            out[f"{name}={value:g}" if isinstance(value, float) else f"{name}={value}"] = replace(
                base, **{name: value})
    return out


def sim_images(quick: bool) -> dict[str, list[devdata.DevImage]]:
    """The simulated rig's frames as `devdata.DevImage` with the renderer's laser pixels as reference runs."""
    scenes = bench_extract.rig_scenes()
    out: dict[str, list[devdata.DevImage]] = {}
    for name, (rig, positions, seeds) in scenes.items():
        positions = positions[::2] if quick else positions
        images: list[devdata.DevImage] = []
        frames = bench_extract.rig_frames(rig, positions, seeds[:1])
        laser_off = bench_extract.laser_off_pairs(rig, frames, positions)
        for k, (image, truth) in enumerate(frames):
            height = image.shape[0]
            rows = np.rint(truth[:, 1]).astype(np.int64)
            runs: list[tuple[tuple[float, float, float], ...]] = [() for _ in range(height)]
            for v, u in zip(rows, truth[:, 0]):
                if 0 <= v < height:
                    runs[v] = runs[v] + ((float(u), float(u), float(u)),)
            clear = np.array([len(r) == 1 for r in runs])  # one crossing: a one-line extractor can find it
            scored = np.ones(height, bool)
            images.append(devdata.DevImage(f"sim {name} {k}", image, devdata.RowReference(tuple(runs), clear, scored),
                                           texture=laser_off[k]))
        out[f"sim_{name}"] = images
    return out


def real_images() -> dict[str, list[devdata.DevImage]]:
    """The real sets (`devdata`); the box pairs a seeded subsample; empty when the folder is absent."""
    try:
        rng = np.random.default_rng(SEED)
        pairs = sorted(int(p) for p in rng.choice(np.arange(2, 32), BOX_PAIRS, replace=False))
        return {"weld": devdata.weld_images(), "globe": devdata.globe_images(), "photos": devdata.photo_images(),
                "box": devdata.box_images(pairs=pairs)}
    except devdata.DevDataMissing as exc:
        print(f"real sets skipped: {exc}", file=sys.stderr)
        return {}


def truth_rms(images: Sequence[devdata.DevImage], params: ExtractorParams) -> float:
    """RMS of the matched detections to the reference centre (simulated sets: the renderer's truth)."""
    errs: list[float] = []
    for dev in images:
        result = extract_laser_line(dev.image, params, texture=dev.texture)
        for v, u in zip(result.v.astype(np.int64), result.u):
            cands = [c for _, _, c in dev.reference.runs[v]]
            if cands:
                e = min((u - c for c in cands), key=abs)
                if abs(e) <= devdata.MATCH_PX:
                    errs.append(float(e))
    return float(np.sqrt(np.mean(np.square(errs)))) if errs else float("nan")


def score_set(images: Sequence[devdata.DevImage], params: ExtractorParams) -> devdata.RowScore:
    """`devdata.score_images` of ``params``, each image with its laser-off frame where its set has one (globe, box),
    as the default pipeline gets it in a stop-snap scan."""
    def run(dev: devdata.DevImage) -> tuple[AnyArray, AnyArray]:
        result = extract_laser_line(dev.image, params, texture=dev.texture)
        return result.v, result.u
    return devdata.score_images(images, run)


def study(sets: dict[str, list[devdata.DevImage]], cands: dict[str, ExtractorParams]) -> dict[str, object]:
    """Scores of every candidate on every set, the leave-one-set-out choices and the minimax default."""
    table: dict[str, dict[str, dict[str, float]]] = {}
    for name, params in cands.items():
        started = time.perf_counter()
        row: dict[str, dict[str, float]] = {}
        total = devdata.RowScore()
        real = devdata.RowScore()
        for set_name, images in sets.items():
            s = score_set(images, params)
            total.add(s)
            if not set_name.startswith("sim_"):
                real.add(s)
            row[set_name] = {"rms_px": s.rms_px, "missed_pct": s.missed_pct, "false_pct": s.false_pct}
            if set_name.startswith("sim_"):
                row[set_name]["truth_rms_px"] = truth_rms(images, params)
        # missed rows count on the single-line sets; false rows on every set (rows-weighted)
        row["all"] = {"rms_px": total.rms_px, "missed_pct": total.missed_pct, "false_pct": total.false_pct}
        row["real"] = {"rms_px": real.rms_px, "missed_pct": real.missed_pct, "false_pct": real.false_pct}
        table[name] = row
        print(f"{name:<28} " + " ".join(f"{k}:{v['rms_px']:.3f}/{v['missed_pct']:.1f}/{v['false_pct']:.2f}"
                                         for k, v in row.items()) + f"  ({time.perf_counter() - started:.1f} s)",
              flush=True)
    rms_sets = [s for s in sets if s in SINGLE]
    ref = table["default"]["all"]
    eligible = [n for n, r in table.items() if r["all"]["missed_pct"] <= ref["missed_pct"] + ROWS_TOLERANCE_PCT
                and r["all"]["false_pct"] <= ref["false_pct"] + ROWS_TOLERANCE_PCT]

    def worst(name: str, over: Sequence[str]) -> float:
        return max(table[name][s]["rms_px"] for s in over)

    def choose(over: Sequence[str]) -> str:
        # the default stays unless another candidate's worst set is better by more than the margin
        best = min(eligible, key=lambda n: worst(n, over))
        return best if worst("default", over) - worst(best, over) > MARGIN_PX else "default"

    loso: dict[str, dict[str, object]] = {}
    for held in rms_sets:
        others = [s for s in rms_sets if s != held]
        chosen = choose(others)
        best = min(table, key=lambda n: table[n][held]["rms_px"])
        loso[held] = {"chosen": chosen, "held_out_rms_px": table[chosen][held]["rms_px"],
                      "best": best, "best_rms_px": table[best][held]["rms_px"],
                      "regret_px": table[chosen][held]["rms_px"] - table[best][held]["rms_px"]}
    minimax = choose(rms_sets)
    return {"table": table, "eligible": eligible, "loso": loso, "minimax": minimax,
            "worst_set_rms_px": {n: worst(n, rms_sets) for n in table}}


def markdown(result: dict[str, object], sets: Sequence[str]) -> str:
    """The README's table: per candidate, per set RMS / missed / false, the worst set, and the LOSO choices."""
    table = result["table"]
    worst = result["worst_set_rms_px"]
    assert isinstance(table, dict) and isinstance(worst, dict)
    head = "| candidate | " + " | ".join(sets) + " | real sets: missed / false | all: missed / false | worst-set RMS |"
    lines = [head, "|" + "---|" * (len(sets) + 4)]
    for name, row in table.items():
        cells = []
        for s in sets:
            c = row[s]
            cells.append(f"{c['missed_pct']:.1f} / {c['false_pct']:.2f}" if s not in SINGLE else
                         f"{c['rms_px']:.3f} / {c['missed_pct']:.1f} / {c['false_pct']:.2f}")
        mark = " **(chosen)**" if name == result["minimax"] else ""
        lines.append(f"| {name}{mark} | " + " | ".join(cells) +
                     f" | {row['real']['missed_pct']:.1f} / {row['real']['false_pct']:.2f}"
                     f" | {row['all']['missed_pct']:.1f} / {row['all']['false_pct']:.2f} | {worst[name]:.3f} |")
    loso = result["loso"]
    assert isinstance(loso, dict)
    lines.append("")
    lines.append("| held-out set | chosen on the others | its RMS there | best there (RMS) |")
    lines.append("|---|---|---|---|")
    for held, c in loso.items():
        lines.append(f"| {held} | {c['chosen']} | {c['held_out_rms_px']:.3f} | {c['best']} ({c['best_rms_px']:.3f}) |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run the study, print the table, write bench/results/study_extract.json."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="half the simulated positions")
    parser.add_argument("--only", nargs="*", help="candidate names to run (default: all)")
    args = parser.parse_args(argv)
    started = time.perf_counter()
    sets = {**real_images(), **sim_images(args.quick)}
    cands = candidates()
    if args.only:
        cands = {n: p for n, p in cands.items() if n in args.only or n == "default"}
    result = study(sets, cands)
    order = list(sets)
    text = markdown(result, order)
    print(text)
    figures: dict[str, float] = {}
    units: dict[str, str] = {}
    table = result["table"]
    assert isinstance(table, dict)
    for name, row in table.items():
        key = name.replace("=", "_").replace(".", "p")
        for s, c in row.items():
            for metric, value in c.items():
                figures[f"{metric}_{s}_{key}"] = value
                units[f"{metric}_{s}_{key}"] = "px" if metric.endswith("px") else "%"
    figures["study_wall_s"] = time.perf_counter() - started
    units["study_wall_s"] = "s"
    counts = ", ".join(f"{s} {len(v)}" for s, v in sets.items())
    notes = (f"Leave-one-set-out over the sets ({counts} images); RMS from a robust smooth fit along the line on "
             "every set (sim_*: truth_rms_px too); missed: % of clear rows; false: % of scored rows; 'all' sums "
             f"the rows of every set. Eligible: missed and false at most {ROWS_TOLERANCE_PCT} points above the "
             f"default's. Chosen (minimax over the sets' RMS among the eligible, by more than {MARGIN_PX} px, else "
             f"the default): {result['minimax']}.")
    write_result("study_extract", figures, units, notes,
                 extra={"loso": result["loso"], "minimax": result["minimax"], "eligible": result["eligible"],
                        "worst_set_rms_px": result["worst_set_rms_px"], "markdown": text})
    return 0


if __name__ == "__main__":
    sys.exit(main())

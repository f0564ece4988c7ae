"""Benchmark of lsu_extract: speed against np.copy, column error, false and missed rows.

Truth: analytic laser lines (lsu_extract.synthetic: pixel-integrated Gaussian profile,
reddish texture, crosstalk, shot + read noise, 8-bit quantisation) until the simulated rig
of lsu_cameras lands; the same figures will then be measured on the rig.

Writes bench/results/extract.json and bench/results/extract.png (RMS error vs noise, line
width and ambient light per method, drawn with OpenCV). Single thread throughout.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy: timings are single-thread
os.environ.setdefault("OMP_NUM_THREADS", "1")

import sys  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Dict, List, Sequence, Tuple  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, median, time_calls, write_result  # noqa: E402

from lsu_extract.detectors import METHODS  # noqa: E402
from lsu_extract.extractor import DEFAULT_METHOD, ExtractorParams, extract_laser_line  # noqa: E402
from lsu_extract.synthetic import LineScene, render_line  # noqa: E402

cv2.setNumThreads(1)
DEFAULT_SCENE = LineScene()  # 640x480, FWHM 4 px, ambient 10 %, reddish texture, read 1 DN + shot 0.05 DN/DN
FRAMES = 8


def rms_error(method: str, scene: LineScene, frames: int = FRAMES) -> Tuple[float, float]:
    """RMS column error [px] over detected visible rows, and the fraction of visible rows detected."""
    errs: List[np.ndarray] = []
    found = total = 0
    for seed in range(frames):
        image, truth, visible = render_line(scene.with_(seed=seed, texture_seed=seed))
        result = extract_laser_line(image, ExtractorParams(method=method))
        rows = result.v.astype(int)
        keep = visible[rows]
        errs.append(result.u[keep] - truth[rows[keep]])
        found += int(keep.sum())
        total += int(visible.sum())
    err = np.concatenate(errs)
    return (float(np.sqrt(np.mean(err ** 2))) if err.size else float("nan")), found / max(total, 1)


def false_and_missed(method: str, frames: int = 10) -> Tuple[float, float]:
    """At 50 % ambient on reddish texture with a weak reflection: false and missed rows in %.

    False: a detection in a row without laser, or more than 2 px from the true line.
    Missed: a row where the laser is visible and no (correct) detection was reported.
    """
    false = missed = visible_rows = empty_rows = 0
    for seed in range(frames):
        scene = DEFAULT_SCENE.with_(ambient=0.5, first_row=60, last_row=419, reflection=0.3, seed=100 + seed,
                                    texture_seed=100 + seed)
        image, truth, visible = render_line(scene)
        result = extract_laser_line(image, ExtractorParams(method=method))
        rows = result.v.astype(int)
        good = visible[rows] & (np.abs(result.u - truth[rows]) <= 2.0)
        false += int((~good).sum())
        missed += int(visible.sum() - good.sum())
        visible_rows += int(visible.sum())
        empty_rows += int((~visible).sum())
    return 100.0 * false / image.shape[0] / frames, 100.0 * missed / visible_rows


def timing(methods: Sequence[str]) -> Dict[str, Tuple[float, float]]:
    """Median ms per frame for each method and its ratio to np.copy of the frame, timed alternately."""
    image, _, _ = render_line(DEFAULT_SCENE)
    out: Dict[str, Tuple[float, float]] = {}
    for method in methods:
        params = ExtractorParams(method=method)
        copies: List[float] = []
        runs: List[float] = []
        for _ in range(5):  # interleave so both see the same machine load
            copies += time_calls(lambda: np.copy(image), repeat=60)
            runs += time_calls(lambda: extract_laser_line(image, params), repeat=60)
        out[method] = (median(runs), median(runs) / median(copies))
    out["np.copy"] = (median(copies), 1.0)
    return out


def plot(tables: Dict[str, Tuple[str, Sequence[float], Dict[str, List[float]]]], path: Path) -> None:
    """Panels of RMS error vs a scene parameter, one polyline per method (OpenCV drawing)."""
    colours = {"thesis": (60, 60, 60), "gaussian3": (200, 120, 0), "parabola": (0, 160, 220),
               "com": (160, 0, 160), "blais_rioux4": (0, 150, 0), "blais_rioux8": (0, 0, 220)}
    pw, ph, m = 420, 320, 50
    canvas = np.full((ph + 60, pw * len(tables), 3), 255, np.uint8)
    ymax = 0.5
    for k, (title, (xlabel, xs, series)) in enumerate(tables.items()):
        x0 = k * pw + m
        w, h = pw - m - 15, ph - m - 20
        top = 30
        cv2.rectangle(canvas, (x0, top), (x0 + w, top + h), (0, 0, 0), 1)
        cv2.putText(canvas, title, (x0, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        cv2.putText(canvas, xlabel, (x0 + w // 3, top + h + 35), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
        for tick in np.arange(0.0, ymax + 1e-9, 0.1):
            y = int(top + h - tick / ymax * h)
            cv2.line(canvas, (x0, y), (x0 + w, y), (220, 220, 220), 1)
            cv2.putText(canvas, f"{tick:.1f}", (x0 - 35, y + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
        for i, x in enumerate(xs):
            px = int(x0 + i / max(len(xs) - 1, 1) * w)
            cv2.putText(canvas, f"{x:g}", (px - 10, top + h + 15), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
        for method, values in series.items():
            pts = [(int(x0 + i / max(len(xs) - 1, 1) * w), int(top + h - min(v, ymax) / ymax * h))
                   for i, v in enumerate(values) if np.isfinite(v)]
            if len(pts) > 1:
                cv2.polylines(canvas, [np.array(pts, np.int32)], False, colours.get(method, (0, 0, 0)), 2, cv2.LINE_AA)
    for i, method in enumerate(METHODS):
        cv2.putText(canvas, method, (10 + i * 150, ph + 45), cv2.FONT_HERSHEY_SIMPLEX, 0.5, colours[method], 2)
    cv2.putText(canvas, "RMS column error [px]", (5, ph + 20), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
    cv2.imwrite(str(path), canvas)


def main() -> int:
    """Measure everything and write the result files."""
    times = timing(METHODS)
    default_rms = {m: rms_error(m, DEFAULT_SCENE) for m in METHODS}
    false_pct, missed_pct = false_and_missed(DEFAULT_METHOD)
    false_thesis, missed_thesis = false_and_missed("thesis")

    noise_scale = [0.0, 0.5, 1.0, 2.0, 4.0]
    widths = [2.5, 3.0, 4.0, 6.0, 9.0, 12.0]
    ambients = [0.0, 0.1, 0.25, 0.5, 0.75]
    base = DEFAULT_SCENE
    noise_tab = {m: [rms_error(m, base.with_(read_noise_dn=base.read_noise_dn * s, shot_gain=base.shot_gain * s),
                               3)[0] for s in noise_scale] for m in METHODS}
    width_tab = {m: [rms_error(m, base.with_(fwhm_px=wd), 3)[0] for wd in widths] for m in METHODS}
    ambient_tab = {m: [rms_error(m, base.with_(ambient=a), 3)[0] for a in ambients] for m in METHODS}
    plain_rms = {m: rms_error(m, base.with_(textured=False), 4)[0] for m in METHODS}
    RESULTS.mkdir(parents=True, exist_ok=True)
    plot({"error vs noise (x default)": ("noise scale", noise_scale, noise_tab),
          "error vs line width": ("FWHM [px]", widths, width_tab),
          "error vs ambient light": ("ambient (fraction of full scale)", ambients, ambient_tab)},
         RESULTS / "extract.png")

    figures = {
        "extract_ms_median": times[DEFAULT_METHOD][0],
        "extract_over_copy_ratio": times[DEFAULT_METHOD][1],
        "rms_px_default": default_rms[DEFAULT_METHOD][0],
        "rms_px_thesis": default_rms["thesis"][0],
        "false_rows_pct_ambient": false_pct,
        "missed_rows_pct_ambient": missed_pct,
        "copy_ms_median": times["np.copy"][0],
        "false_rows_pct_ambient_thesis": false_thesis,
        "missed_rows_pct_ambient_thesis": missed_thesis,
    }
    units = {"extract_ms_median": "ms", "extract_over_copy_ratio": "x np.copy", "rms_px_default": "px",
             "rms_px_thesis": "px", "false_rows_pct_ambient": "% of rows", "missed_rows_pct_ambient":
             "% of visible rows", "copy_ms_median": "ms", "false_rows_pct_ambient_thesis": "% of rows",
             "missed_rows_pct_ambient_thesis": "% of visible rows"}
    for m in METHODS:
        figures[f"ms_median_{m}"] = times[m][0]
        figures[f"over_copy_ratio_{m}"] = times[m][1]
        figures[f"rms_px_{m}"] = default_rms[m][0]
        figures[f"rms_px_plain_{m}"] = plain_rms[m]
        units.update({f"ms_median_{m}": "ms", f"over_copy_ratio_{m}": "x np.copy", f"rms_px_{m}": "px",
                      f"rms_px_plain_{m}": "px"})
    notes = (
        f"Default method {DEFAULT_METHOD}. Truth: analytic lines (lsu_extract.synthetic), 640x480, slanted "
        "(0.05 px/row) and bowed (6 px), Gaussian profile FWHM 4 px integrated over each pixel, amplitude "
        "160 DN, 6/4 % crosstalk into green/blue, ambient 10 % on a reddish skin-like texture (the laser "
        "is modulated by it too), read noise 1 DN + shot noise variance 0.05 DN/DN, 8-bit. "
        f"{FRAMES} frames per RMS figure, 3 per table cell. rms_px_plain_*: uniform background. "
        "False/missed: 50 % ambient, texture, laser in rows 60..419 only, a 30 % reflection 70 px away; "
        "false = detections in laser-free rows or > 2 px off, in % of all rows. Timing: one frame, "
        "single thread, median of 300 calls, np.copy of the same frame timed alternately in the same run "
        "(hot cache). Tables (RMS px per method): see 'tables'.")
    write_result("extract", figures, units, notes, extra={"tables": {
        "noise_scale": {"x": noise_scale, "rms_px": noise_tab},
        "fwhm_px": {"x": widths, "rms_px": width_tab},
        "ambient": {"x": ambients, "rms_px": ambient_tab},
        "detected_fraction_default": {m: default_rms[m][1] for m in METHODS},
    }, "plot": "bench/results/extract.png"})
    return 0


if __name__ == "__main__":
    sys.exit(main())

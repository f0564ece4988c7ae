"""Benchmark of lsu_reconstruct: accuracy against analytic truth and the time of one snap.

Truth comes from `lsu_reconstruct.synthetic` (analytic ray casting of a laser plane on planes
and a sphere, pixels made by OpenCV projectPoints with plumb_bob distortion), which shares no
code with the matcher. Lines get seeded Gaussian noise on u (what a sub-pixel extractor leaves);
the thesis chain gets the same lines rounded to whole pixels.

Writes bench/results/reconstruct.json (figure names of ARCHITECTURE.md, plus more).
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path
from typing import Dict, List, Sequence, Tuple

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import median, time_calls, write_result  # noqa: E402

from lsu_reconstruct import synthetic as S  # noqa: E402
from lsu_reconstruct.matching import LineArrays, MatchParams  # noqa: E402
from lsu_reconstruct.pipeline import reconstruct_snap  # noqa: E402
from lsu_reconstruct.stereo import StereoModel  # noqa: E402
from lsu_reconstruct.triangulate import METHODS  # noqa: E402

NOISE_PX = 0.05          # sigma of the sub-pixel extractor's column noise
SEED = 20261123
PLANE_LASER_X = np.linspace(-0.07, 0.05, 9)     # carriage positions [m] (laser plane yawed 8 deg)
SPHERE = S.Sphere(np.array([0.0, 0.0, 0.33]), 0.05)
SPHERE_LASER_X = np.linspace(-0.10, -0.005, 25)


def sweep(rig: S.Rig, scene: Sequence, xs: Sequence[float]) -> List[Tuple[S.LineSamples, S.LineSamples]]:
    """Noise-free left/right lines of a stop-snap sweep."""
    out = []
    for x in xs:
        laser = S.Laser.at(float(x))
        out.append((S.laser_samples(rig, scene, laser, "left"), S.laser_samples(rig, scene, laser, "right")))
    return out


def cloud(model: StereoModel, lines: List[Tuple[S.LineSamples, S.LineSamples]], params: MatchParams,
          noise_px: float, chain: str = "subpixel") -> np.ndarray:
    """All points of a sweep, with fresh seeded noise (or pixel quantisation for the thesis chain)."""
    rng = np.random.default_rng(SEED)
    pts = []
    for i, (left, right) in enumerate(lines):
        if chain == "thesis":
            left, right = left.pixel_quantised(), right.pixel_quantised()
        else:
            left, right = left.noisy(noise_px, rng), right.noisy(noise_px, rng)
        snap = reconstruct_snap(model, LineArrays(left.u, left.v), LineArrays(right.u, right.v), params, snap=i,
                                chain=chain)
        pts.append(snap.xyz)
    return np.concatenate(pts)


def plane_stats(points: np.ndarray, plane: S.Plane) -> Tuple[float, float, int]:
    """sigma and mean [mm] of the signed distance to the TRUE plane, and the point count."""
    d = (points @ plane.normal - plane.offset) * 1000.0
    return float(d.std()), float(d.mean()), int(len(d))


def main() -> None:
    rig = S.default_rig()
    model = StereoModel.from_folder(rig.write_calibration(Path(tempfile.mkdtemp(prefix="lsu_bench_calib_"))))
    default = MatchParams()
    raw = MatchParams(smooth_window_rows=0)
    figures: Dict[str, float] = {}
    units: Dict[str, str] = {}

    for depth in (0.25, 0.30, 0.35):
        mm = int(round(depth * 1000))
        plane = S.Plane.facing(depth)
        lines = sweep(rig, [plane], PLANE_LASER_X)
        sigma, mean, n = plane_stats(cloud(model, lines, default, NOISE_PX), plane)
        figures[f"plane_sigma_mm_{mm}"], figures[f"plane_bias_mm_{mm}"] = sigma, mean
        figures[f"plane_points_{mm}"] = n
        sigma_raw, mean_raw, _ = plane_stats(cloud(model, lines, raw, NOISE_PX), plane)
        figures[f"plane_sigma_mm_{mm}_unsmoothed"], figures[f"plane_bias_mm_{mm}_unsmoothed"] = sigma_raw, mean_raw
        sigma_t, mean_t, n_t = plane_stats(cloud(model, lines, raw, 0.0, chain="thesis"), plane)
        figures[f"thesis_plane_sigma_mm_{mm}"], figures[f"thesis_plane_bias_mm_{mm}"] = sigma_t, mean_t
        figures[f"thesis_plane_points_{mm}"] = n_t
        if mm == 300:
            for method in METHODS:
                p = MatchParams(smooth_window_rows=0, method=method)
                figures[f"plane_sigma_mm_300_unsmoothed_{method}"] = plane_stats(cloud(model, lines, p, NOISE_PX),
                                                                                 plane)[0]
                pt = MatchParams(smooth_window_rows=0, method=method, max_reproj_px=2.0)
                figures[f"thesis_plane_sigma_mm_300_{method}"] = plane_stats(
                    cloud(model, lines, pt, 0.0, chain="thesis"), plane)[0]
            figures["plane_sigma_mm_300_noiseless"] = plane_stats(cloud(model, lines, raw, 0.0), plane)[0]

    sphere_lines = sweep(rig, [SPHERE], SPHERE_LASER_X)
    for name, params in (("", default), ("_unsmoothed", raw)):
        pts = cloud(model, sphere_lines, params, NOISE_PX)
        centre, radius = S.fit_sphere(pts)
        figures[f"sphere_radius_err_mm{name}"] = (radius - SPHERE.radius) * 1000.0
        figures[f"sphere_centre_err_mm{name}"] = float(np.linalg.norm(centre - SPHERE.centre) * 1000.0)
        figures[f"sphere_points{name}"] = len(pts)
    pts_t = cloud(model, sphere_lines, raw, 0.0, chain="thesis")
    figures["thesis_sphere_radius_err_mm"] = (S.fit_sphere(pts_t)[1] - SPHERE.radius) * 1000.0

    # Time of one snap (~480 rows each side), plane at 300 mm, default parameters.
    plane = S.Plane.facing(0.30)
    left, right = sweep(rig, [plane], [0.0])[0]
    rng = np.random.default_rng(SEED)
    ln, rn = left.noisy(NOISE_PX, rng), right.noisy(NOISE_PX, rng)
    la, ra = LineArrays(ln.u, ln.v), LineArrays(rn.u, rn.v)
    figures["rows_per_snap"] = len(la)
    figures["match_triangulate_ms_median"] = median(time_calls(lambda: reconstruct_snap(model, la, ra, default),
                                                               repeat=300, warmup=10))
    for method in METHODS:
        p = MatchParams(method=method)
        figures[f"match_triangulate_ms_median_{method}"] = median(
            time_calls(lambda: reconstruct_snap(model, la, ra, p), repeat=100, warmup=5))
    figures["thesis_match_triangulate_ms_median"] = median(time_calls(
        lambda: reconstruct_snap(model, LineArrays(np.round(ln.u), ln.v), LineArrays(np.round(rn.u), rn.v), raw,
                                 chain="thesis"), repeat=100, warmup=5))

    for k in figures:
        units[k] = "ms" if k.endswith("ms_median") or "_ms_median_" in k else "mm" if "_mm" in k else "count"
    notes = (f"Synthetic rig (lsu_reconstruct.synthetic, independent of the matcher): 640x480, f~800 px, plumb_bob "
             f"distortion, baseline 122 mm, right camera toed in 17 deg, laser plane yawed 8 deg. Input noise: "
             f"Gaussian sigma {NOISE_PX} px on u of every left and right sample (seed {SEED}); thesis chain: the same "
             f"lines rounded to whole pixels, nearest-pixel match on the epipolar line, midpoint triangulation. Plane "
             f"figures are signed point-to-plane distances to the TRUE plane over {len(PLANE_LASER_X)} snaps; sphere "
             f"r = {SPHERE.radius * 1000:.0f} mm at {SPHERE.centre[2] * 1000:.0f} mm, {len(SPHERE_LASER_X)} snaps, "
             f"least-squares sphere fit. Default parameters: smooth_window_rows={default.smooth_window_rows} (local "
             f"quadratic fit of u(v) along each line before matching), triangulation={default.method}; '_unsmoothed' "
             f"figures are without the smoothing. Triangulation methods agree on intersection matches (the pair is "
             f"epipolar-consistent by construction); they differ on the thesis chain's nearest-pixel matches. Timing: "
             f"one snap of ~480 rows per side, single thread, shared 2-core machine.")
    write_result("reconstruct", figures, units, notes)


if __name__ == "__main__":
    main()

"""Benchmark of lsu_reconstruct: end-to-end accuracy on the simulated rig, and the time of one snap.

Rig figures (the ARCHITECTURE.md names: ``plane_sigma_mm_300``, ``plane_bias_mm_300``,
``sphere_radius_err_mm``, ``thesis_plane_sigma_mm_300``, ...): `lsu_sim` renders stereo
pairs of a plane at 250/300/350 mm and of its 6 cm sphere at every 4th carriage step of the track
(default noise, settled carriage), `lsu_extract` finds the laser lines (its default sub-pixel
method, and the thesis' pixel detector), the matcher uses ``config/calibration/sim`` (the rig's
true calibration). Truth is the renderer's: the scene geometry in the left camera frame, and its
per-row laser pixels (`LaserTruth`), which split the error into extraction error (extracted vs
true pixel columns) and geometry error (the true pixels through the same matcher).

Synthetic figures (prefix ``synthetic_``): `lsu_reconstruct.synthetic` (analytic laser lines,
independent of the matcher) with an assumed Gaussian column noise of 0.05 px; they isolate the
matcher from the extractor.

Writes bench/results/reconstruct.json.
"""

from __future__ import annotations

import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import median, time_calls, write_result  # noqa: E402

from lsu_common.arrays import AnyArray  # noqa: E402
from lsu_extract.detectors import SUBPIXEL_METHODS  # noqa: E402
from lsu_extract.extractor import DEFAULT_METHOD, ExtractorParams, LaserLineResult, extract_laser_line  # noqa: E402
from lsu_reconstruct import synthetic as S  # noqa: E402
from lsu_reconstruct.matching import LineArrays, MatchParams  # noqa: E402
from lsu_reconstruct.pipeline import reconstruct_snap  # noqa: E402
from lsu_reconstruct.stereo import StereoModel  # noqa: E402
from lsu_reconstruct.triangulate import METHODS  # noqa: E402
from lsu_sim import SimulatedRig, build_scene, load_rig  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SIM_CALIBRATION = ROOT / "config" / "calibration" / "sim"

# ---------------------------------------------------------------- simulated rig
RIG_SEED = 20261123
RIG_STEPS = range(0, 471, 4)            # every 4th carriage step of the 470-step track
RIG_PLANE_DEPTHS_M = (0.25, 0.30, 0.35)
THESIS_EXTRACTION = ExtractorParams(method="thesis")
# The other sub-pixel detectors of lsu_extract, compared through the same matcher (plane 300 mm, sphere).
OTHER_METHODS = tuple(m for m in SUBPIXEL_METHODS if m != DEFAULT_METHOD)

# ---------------------------------------------------------------- synthetic lines
NOISE_PX = 0.05          # sigma of the sub-pixel extractor's column noise
SEED = 20261123
PLANE_LASER_X = np.linspace(-0.07, 0.05, 9)     # carriage positions [m] (laser plane yawed 8 deg)
SPHERE = S.Sphere(np.array([0.0, 0.0, 0.33]), 0.05)
SPHERE_LASER_X = np.linspace(-0.10, -0.005, 25)


# ================================================================ simulated rig
def line_arrays(res: LaserLineResult) -> LineArrays:
    """An extractor result as the matcher's input (what the node builds from a LaserLine message)."""
    return LineArrays(res.u, res.v, res.peak, res.width, res.quality, res.image_width, res.image_height)


def column_errors(res: LaserLineResult, truth_pixels: AnyArray, height: int) -> AnyArray:
    """Extracted minus true column [px] on the rows where both exist (one true crossing per row here)."""
    true_u = np.full(height, np.nan)
    rows = np.rint(truth_pixels[:, 1]).astype(np.intp)
    true_u[rows] = truth_pixels[:, 0]
    err = res.u.astype(np.float64) - true_u[np.rint(res.v).astype(np.intp)]
    return err[np.isfinite(err)]


@dataclass
class RigSweep:
    """Everything one scan of the simulated rig gives: clouds per chain and per-row extraction errors."""

    clouds: dict[str, list[AnyArray]] = field(default_factory=dict)
    col_err: dict[str, list[AnyArray]] = field(default_factory=dict)
    snaps: int = 0
    seconds: dict[str, float] = field(default_factory=dict)
    timing_lines: tuple[LineArrays, LineArrays, LineArrays, LineArrays] | None = None

    @staticmethod
    def add(store: dict[str, list[AnyArray]], key: str, value: AnyArray) -> None:
        """Append one snap's array to ``store[key]``."""
        store.setdefault(key, []).append(value)

    def cloud(self, key: str) -> AnyArray:
        """All points [m] of one chain."""
        return np.concatenate(self.clouds[key]) if self.clouds.get(key) else np.zeros((0, 3))

    def errors(self, key: str) -> AnyArray:
        """All column errors [px] of one extraction method and side."""
        return np.concatenate(self.col_err[key]) if self.col_err.get(key) else np.zeros(0)


# The chains compared on every snap: (name, extraction, match parameters, matching chain).
RIG_CHAINS = (
    ("default", "default", MatchParams(), "subpixel"),
    ("unsmoothed", "default", MatchParams(smooth_window_rows=0), "subpixel"),
    ("thesis", "thesis", MatchParams(smooth_window_rows=0), "thesis"),
    ("truth_px", "truth", MatchParams(smooth_window_rows=0), "subpixel"),
)
# How each chain appears in the figure names: (chain, prefix, suffix).
CHAIN_NAMES = (("default", "", ""), ("unsmoothed", "", "_unsmoothed"), ("thesis", "thesis_", ""),
               ("truth_px", "", "_truth_px"))


def rig_sweep(model: StereoModel, scene_name: str, distance_m: float | None,
              other_methods: Sequence[str] = ()) -> tuple[RigSweep, object]:
    """Render a stop-snap scan of one scene, extract both lines with both methods, reconstruct every chain.

    ``other_methods``: further lsu_extract sub-pixel methods to compare, each through the default
    matcher (chain name ``method:<name>``, column errors under ``<name>_left`` / ``<name>_right``).
    """
    geometry = load_rig()
    scene = build_scene(scene_name, geometry, distance_m=distance_m)
    rig = SimulatedRig(geometry, scene, seed=RIG_SEED)
    height = geometry.image_size[1]
    out = RigSweep(seconds={"render": 0.0, "extract": 0.0, "reconstruct": 0.0})
    for step in RIG_STEPS:
        t0 = time.perf_counter()
        frame = rig.render(float(step), with_truth=True, seed=RIG_SEED + step)
        out.seconds["render"] += time.perf_counter() - t0
        truth = frame.truth
        if len(truth.left.pixels) == 0 and len(truth.right.pixels) == 0:
            continue  # the laser misses the object at this carriage position
        out.snaps += 1
        t0 = time.perf_counter()
        ext = {"default": (extract_laser_line(frame.left), extract_laser_line(frame.right)),
               "thesis": (extract_laser_line(frame.left, THESIS_EXTRACTION),
                          extract_laser_line(frame.right, THESIS_EXTRACTION))}
        for method in other_methods:
            p = ExtractorParams(method=method)
            ext[method] = (extract_laser_line(frame.left, p), extract_laser_line(frame.right, p))
        out.seconds["extract"] += time.perf_counter() - t0
        lines = {k: (line_arrays(a), line_arrays(b)) for k, (a, b) in ext.items()}
        lines["truth"] = (LineArrays(truth.left.pixels[:, 0], truth.left.pixels[:, 1]),
                          LineArrays(truth.right.pixels[:, 0], truth.right.pixels[:, 1]))
        out.add(out.clouds, "truth_points", truth.left.points_m[truth.left.other_visible])
        for method, (left, right) in ext.items():
            out.add(out.col_err, f"{method}_left", column_errors(left, truth.left.pixels, height))
            out.add(out.col_err, f"{method}_right", column_errors(right, truth.right.pixels, height))
        t0 = time.perf_counter()
        for name, source, params, chain in RIG_CHAINS:
            left, right = lines[source]
            out.add(out.clouds, name, reconstruct_snap(model, left, right, params, snap=step, chain=chain).xyz)
        for method in other_methods:
            out.add(out.clouds, f"method:{method}", reconstruct_snap(model, *lines[method], snap=step).xyz)
        out.seconds["reconstruct"] += time.perf_counter() - t0
        if out.timing_lines is None and step >= geometry.center_step:
            out.timing_lines = (*lines["default"], *lines["thesis"])
    return out, scene[0]


def plane_distances_mm(points: AnyArray, point: AnyArray, normal: AnyArray) -> AnyArray:
    """Signed distances [mm] of points to the TRUE plane (renderer's scene geometry)."""
    return (points - point) @ normal * 1000.0


def rig_figures(model: StereoModel, figures: dict[str, float]) -> tuple[RigSweep, list[str]]:
    """Plane at 250/300/350 mm and the sphere on the simulated rig; returns the 300 mm sweep (for timing)."""
    notes: list[str] = []
    sweep300: RigSweep | None = None
    for depth in RIG_PLANE_DEPTHS_M:
        mm = int(round(depth * 1000))
        sweep, plane = rig_sweep(model, "plane", depth, OTHER_METHODS if mm == 300 else ())
        p0, n = plane.extra["point"], plane.extra["normal"]
        for name, prefix, tag in CHAIN_NAMES:
            d = plane_distances_mm(sweep.cloud(name), p0, n)
            figures[f"{prefix}plane_sigma_mm_{mm}{tag}"] = float(d.std())
            figures[f"{prefix}plane_bias_mm_{mm}{tag}"] = float(d.mean())
            if name in ("default", "thesis"):
                figures[f"{prefix}plane_points_{mm}"] = len(d)
                figures[f"{prefix}plane_p99_abs_mm_{mm}"] = float(np.percentile(np.abs(d), 99))
        for method in ("default", "thesis"):
            e = np.concatenate([sweep.errors(f"{method}_left"), sweep.errors(f"{method}_right")])
            figures[f"rig_extract_rms_px_{mm}_{method}"] = float(np.sqrt(np.mean(e * e)))
            figures[f"rig_extract_bias_px_{mm}_{method}"] = float(e.mean())
        figures[f"rig_snaps_{mm}"] = sweep.snaps
        if mm == 300:
            sweep300 = sweep
            for method in OTHER_METHODS:
                d = plane_distances_mm(sweep.cloud(f"method:{method}"), p0, n)
                figures[f"plane_sigma_mm_300_extract_{method}"] = float(d.std())
                figures[f"plane_bias_mm_300_extract_{method}"] = float(d.mean())
                e = np.concatenate([sweep.errors(f"{method}_left"), sweep.errors(f"{method}_right")])
                figures[f"rig_extract_rms_px_300_{method}"] = float(np.sqrt(np.mean(e * e)))
        notes.append(f"plane {mm} mm: {sweep.snaps} snaps, render {sweep.seconds['render']:.1f} s, extract "
                     f"{sweep.seconds['extract']:.1f} s, reconstruct {sweep.seconds['reconstruct']:.1f} s")

    sweep, sphere = rig_sweep(model, "sphere", None, OTHER_METHODS)
    centre, radius = sphere.extra["center"], float(sphere.extra["radius_m"])
    # The rendered sphere is a triangle mesh: its surface lies slightly inside the nominal sphere.
    # The renderer's exact laser points on it (seen by both cameras) give the best radius a scan can fit.
    figures["sphere_mesh_radius_err_mm"] = (S.fit_sphere(sweep.cloud("truth_points"))[1] - radius) * 1000.0
    for name, prefix, tag in CHAIN_NAMES:
        pts = sweep.cloud(name)
        c, r = S.fit_sphere(pts)
        figures[f"{prefix}sphere_radius_err_mm{tag}"] = (r - radius) * 1000.0
        figures[f"{prefix}sphere_centre_err_mm{tag}"] = float(np.linalg.norm(c - centre) * 1000.0)
        d = (np.linalg.norm(pts - centre, axis=1) - radius) * 1000.0
        figures[f"{prefix}sphere_bias_mm{tag}"] = float(d.mean())
        figures[f"{prefix}sphere_sigma_mm{tag}"] = float(d.std())
        figures[f"{prefix}sphere_points{tag}"] = len(pts)
    # Only a cap of the sphere is seen, so a free fit trades radius for centre depth; the points near
    # the limbs (grazing view and laser) carry the extraction's largest bias. The fit over the part of
    # the cap facing the rig (normal within 60 deg of the direction to the rig centre) shows how much.
    pts = sweep.cloud("default")
    normals = (pts - centre) / np.linalg.norm(pts - centre, axis=1, keepdims=True)
    to_rig = load_rig().rig_center - pts
    facing = np.einsum("ij,ij->i", normals, to_rig / np.linalg.norm(to_rig, axis=1, keepdims=True)) > 0.5
    figures["sphere_radius_err_mm_facing60"] = (S.fit_sphere(pts[facing])[1] - radius) * 1000.0
    figures["sphere_points_facing60"] = int(np.count_nonzero(facing))
    for method in OTHER_METHODS:
        pts = sweep.cloud(f"method:{method}")
        figures[f"sphere_radius_err_mm_extract_{method}"] = (S.fit_sphere(pts)[1] - radius) * 1000.0
        figures[f"sphere_bias_mm_extract_{method}"] = float(((np.linalg.norm(pts - centre, axis=1) - radius)
                                                             * 1000.0).mean())
        e = np.concatenate([sweep.errors(f"{method}_left"), sweep.errors(f"{method}_right")])
        figures[f"rig_extract_rms_px_sphere_{method}"] = float(np.sqrt(np.mean(e * e)))
    for method in ("default", "thesis"):
        e = np.concatenate([sweep.errors(f"{method}_left"), sweep.errors(f"{method}_right")])
        figures[f"rig_extract_rms_px_sphere_{method}"] = float(np.sqrt(np.mean(e * e)))
    figures["rig_snaps_sphere"] = sweep.snaps
    notes.append(f"sphere: {sweep.snaps} snaps")
    assert sweep300 is not None
    return sweep300, notes


# ================================================================ synthetic lines
def sweep(rig: S.Rig, scene: Sequence, xs: Sequence[float]) -> list[tuple[S.LineSamples, S.LineSamples]]:
    """Noise-free left/right lines of a stop-snap sweep."""
    out = []
    for x in xs:
        laser = S.Laser.at(float(x))
        out.append((S.laser_samples(rig, scene, laser, "left"), S.laser_samples(rig, scene, laser, "right")))
    return out


def cloud(model: StereoModel, lines: list[tuple[S.LineSamples, S.LineSamples]], params: MatchParams,
          noise_px: float, chain: str = "subpixel") -> AnyArray:
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


def plane_stats(points: AnyArray, plane: S.Plane) -> tuple[float, float, int]:
    """sigma and mean [mm] of the signed distance to the TRUE plane, and the point count."""
    d = (points @ plane.normal - plane.offset) * 1000.0
    return float(d.std()), float(d.mean()), int(len(d))


def synthetic_figures(figures: dict[str, float]) -> tuple[StereoModel, S.Rig]:
    """Accuracy on analytic lines with assumed 0.05 px noise (matcher alone), all names prefixed ``synthetic_``."""
    rig = S.default_rig()
    model = StereoModel.from_folder(rig.write_calibration(Path(tempfile.mkdtemp(prefix="lsu_bench_calib_"))))
    default = MatchParams()
    raw = MatchParams(smooth_window_rows=0)
    for depth in (0.25, 0.30, 0.35):
        mm = int(round(depth * 1000))
        plane = S.Plane.facing(depth)
        lines = sweep(rig, [plane], PLANE_LASER_X)
        sigma, mean, n = plane_stats(cloud(model, lines, default, NOISE_PX), plane)
        figures[f"synthetic_plane_sigma_mm_{mm}"], figures[f"synthetic_plane_bias_mm_{mm}"] = sigma, mean
        figures[f"synthetic_plane_points_{mm}"] = n
        sigma_raw, mean_raw, _ = plane_stats(cloud(model, lines, raw, NOISE_PX), plane)
        figures[f"synthetic_plane_sigma_mm_{mm}_unsmoothed"] = sigma_raw
        figures[f"synthetic_plane_bias_mm_{mm}_unsmoothed"] = mean_raw
        sigma_t, mean_t, n_t = plane_stats(cloud(model, lines, raw, 0.0, chain="thesis"), plane)
        figures[f"synthetic_thesis_plane_sigma_mm_{mm}"], figures[f"synthetic_thesis_plane_bias_mm_{mm}"] = sigma_t, mean_t
        figures[f"synthetic_thesis_plane_points_{mm}"] = n_t
        if mm == 300:
            for method in METHODS:
                p = MatchParams(smooth_window_rows=0, method=method)
                figures[f"synthetic_plane_sigma_mm_300_unsmoothed_{method}"] = plane_stats(
                    cloud(model, lines, p, NOISE_PX), plane)[0]
                pt = MatchParams(smooth_window_rows=0, method=method, max_reproj_px=2.0)
                figures[f"synthetic_thesis_plane_sigma_mm_300_{method}"] = plane_stats(
                    cloud(model, lines, pt, 0.0, chain="thesis"), plane)[0]
            figures["synthetic_plane_sigma_mm_300_noiseless"] = plane_stats(cloud(model, lines, raw, 0.0), plane)[0]

    sphere_lines = sweep(rig, [SPHERE], SPHERE_LASER_X)
    for name, params in (("", default), ("_unsmoothed", raw)):
        pts = cloud(model, sphere_lines, params, NOISE_PX)
        centre, radius = S.fit_sphere(pts)
        figures[f"synthetic_sphere_radius_err_mm{name}"] = (radius - SPHERE.radius) * 1000.0
        figures[f"synthetic_sphere_centre_err_mm{name}"] = float(np.linalg.norm(centre - SPHERE.centre) * 1000.0)
        figures[f"synthetic_sphere_points{name}"] = len(pts)
    pts_t = cloud(model, sphere_lines, raw, 0.0, chain="thesis")
    figures["synthetic_thesis_sphere_radius_err_mm"] = (S.fit_sphere(pts_t)[1] - SPHERE.radius) * 1000.0
    return model, rig


def timing_figures(model: StereoModel, lines: tuple[LineArrays, LineArrays, LineArrays, LineArrays],
                   figures: dict[str, float]) -> None:
    """Match + triangulate one real snap (rig, plane at 300 mm, extracted lines), per method and chain."""
    left, right, tleft, tright = lines
    default = MatchParams()
    figures["rows_per_snap"] = len(left)
    figures["match_triangulate_ms_median"] = median(time_calls(lambda: reconstruct_snap(model, left, right, default),
                                                               repeat=300, warmup=10))
    for method in METHODS:
        p = MatchParams(method=method)
        figures[f"match_triangulate_ms_median_{method}"] = median(
            time_calls(lambda: reconstruct_snap(model, left, right, p), repeat=100, warmup=5))
    raw = MatchParams(smooth_window_rows=0)
    figures["thesis_match_triangulate_ms_median"] = median(time_calls(
        lambda: reconstruct_snap(model, tleft, tright, raw, chain="thesis"), repeat=100, warmup=5))


def unit_of(name: str) -> str:
    """Unit of a figure, from its name."""
    if name.endswith("ms_median") or "_ms_median_" in name:
        return "ms"
    if "_px" in name and not name.endswith("_truth_px"):
        return "px"
    if "_mm" in name:
        return "mm"
    return "count"


def main() -> None:
    figures: dict[str, float] = {}
    t0 = time.perf_counter()
    model = StereoModel.from_folder(SIM_CALIBRATION)
    sweep300, rig_notes = rig_figures(model, figures)
    assert sweep300.timing_lines is not None
    timing_figures(model, sweep300.timing_lines, figures)
    synthetic_figures(figures)
    # the physical limit beside the rig figures (the renders carry laser speckle): one row's line centre
    # and one stereo point's depth at 300 mm (lsu_reconstruct.speckle)
    from lsu_accuracy.accuracy import rig_speckle_limit

    limit = rig_speckle_limit(load_rig(), 0.30)
    figures["speckle_limit_px_300"] = limit["line_px"]
    figures["speckle_limit_mm_300"] = limit["depth_mm"]
    figures["speckle_limit_mm_300_with_lens_blur"] = rig_speckle_limit(load_rig(), 0.30, with_lens_blur=True)["depth_mm"]
    figures["plane_sigma_over_speckle_limit_300"] = figures["plane_sigma_mm_300"] / limit["depth_mm"]
    figures["plane_sigma_unsmoothed_over_speckle_limit_300"] = figures["plane_sigma_mm_300_unsmoothed"] / limit["depth_mm"]
    figures["rig_extract_rms_over_speckle_limit_300"] = figures["rig_extract_rms_px_300_default"] / limit["line_px"]
    units = {k: unit_of(k) for k in figures}
    for k in ("plane_sigma_over_speckle_limit_300", "plane_sigma_unsmoothed_over_speckle_limit_300",
              "rig_extract_rms_over_speckle_limit_300"):
        units[k] = "ratio"
    default = MatchParams()
    notes = (f"RIG figures (unprefixed, the ARCHITECTURE.md names): lsu_sim with config/sim_rig.yaml "
             f"(its physics on: laser speckle, crosstalk, blooming; default sensor noise, settled carriage, render "
             f"seed {RIG_SEED} + step), carriage at steps "
             f"{RIG_STEPS.start}..{RIG_STEPS.stop - 1} every {RIG_STEPS.step} (snaps where the laser misses the "
             f"object skipped), plane facing the rig at 250/300/350 mm from the rig centre, the 6 cm sphere at "
             f"300 mm. Lines by lsu_extract (default method '{DEFAULT_METHOD}'; thesis chain: 'thesis' pixel "
             f"detector + nearest-pixel match + midpoint, no smoothing), matched with config/calibration/sim (the "
             f"rig's TRUE calibration), default MatchParams (smooth_window_rows={default.smooth_window_rows}, "
             f"method={default.method}, max_reproj_px={default.max_reproj_px}). Truth: the renderer's scene "
             f"geometry in the left frame (signed point-to-plane distances; sphere fit vs the nominal radius and "
             f"centre). '_truth_px': the renderer's exact per-row laser pixels through the same matcher (geometry "
             f"error alone); rig_extract_*_px: extracted minus true column on both cameras (extraction error "
             f"alone); '_unsmoothed': smooth_window_rows=0; sphere_mesh_radius_err_mm: sphere fit to the "
             f"renderer's exact 3D laser points (the mesh's own deviation from the nominal 60 mm sphere); sphere_radius_err_mm_facing60: fit over the part of the cap facing the rig "
             f"(normal within 60 deg of the rig centre); '_extract_<method>': the other lsu_extract sub-pixel "
             f"methods through the same matcher. speckle_limit_*_300: lsu_reconstruct.speckle for the rig's optics "
             f"(one row's line centre, one stereo point's depth; row smoothing averages below it; _with_lens_blur: with the "
             f"rig's PSF, which the renderer applies to the intensity after the speckle). Timing: match + triangulate one extracted rig snap (plane 300 mm, "
             f"first snap at/after the track centre), single thread, shared 2-core machine. "
             + "; ".join(rig_notes) + ". "
             f"SYNTHETIC figures (prefix synthetic_): lsu_reconstruct.synthetic (analytic, independent of the "
             f"matcher): 640x480, f~800 px, plumb_bob distortion, baseline 122 mm, right camera toed in 17 deg, "
             f"laser plane yawed 8 deg, Gaussian sigma {NOISE_PX} px on u of every sample (seed {SEED}); thesis "
             f"chain: the same lines rounded to whole pixels. Planes over {len(PLANE_LASER_X)} snaps; sphere "
             f"r = {SPHERE.radius * 1000:.0f} mm at {SPHERE.centre[2] * 1000:.0f} mm, {len(SPHERE_LASER_X)} snaps. "
             f"Whole benchmark: {time.perf_counter() - t0:.0f} s.")
    write_result("reconstruct", figures, units, notes)


if __name__ == "__main__":
    main()

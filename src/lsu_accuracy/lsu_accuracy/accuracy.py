"""The thesis' accuracy study (ch. 9) redone on the simulated rig, with exact truth (pure: no rclpy).

The thesis scanned its calibration board at several poses, fitted the board plane and measured the
point-to-plane distances of the scan: their spread (a Gaussian check: fractions within 1, 2, 3 sigma
against 68.2 / 95.4 / 99.7 %), their mean and standard deviation against the mean distance from the
left camera (straight-line fits), and the effect of Laplacian smoothing (30 iterations at 0.1). It
quoted 1.4 mm at 30 cm: 3 sigma (0.9 mm) plus a 0.5 mm bias. We do the same here:

- `scan_scene`: a stop-snap scan of any `lsu_sim` scene, through *both* chains in the same
  run: ours (the default sub-pixel extractor + sub-pixel matching) and the thesis chain (the thesis'
  pixel detector + nearest-pixel match, no row smoothing). Reusable by any study of the sim rig.
- `plane_pose_object`: a textured flat board at a distance, yawed and pitched about the rig centre.
- `run_study`: poses from 200 to 450 mm, per pose and chain the distances to the TRUE plane (the
  renderer's) and a free plane fit (what a real rig without truth does), raw and after meshing in the
  image plane and smoothing; the Gaussian table; error against distance with linear fits; a smoothing
  study (Laplacian iterations x factor grid, Taubin passes) on the flat board (noise left) and on a
  curved truth (the sphere: RMS deviation from the rendered surface, i.e. how much shape smoothing
  takes away).
- `rig_speckle_limit`: the speckle-limited sigma of one point (`lsu_reconstruct.speckle`) for the
  simulated rig's optics, printed beside the measured sigma at 300 mm with their ratio: the renders
  carry laser speckle, the physical limit of laser triangulation (Dorsch et al. 1994).
- `write_report`: report.md, PNG plots (matplotlib, Agg) and accuracy.json.

"3 sigma" figures follow the thesis' quote: ``|bias| + 3 * sigma`` of the signed distances to the
true plane (the thesis' 1.4 mm = 0.5 mm bias + 3 x 0.3 mm); the pure ``3 * sigma`` is reported too.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from lsu_common.arrays import AnyArray

__all__ = ["AccuracyError", "Pose", "StudyConfig", "ChainScan", "ChainSpec", "CHAINS", "GAUSSIAN_EXPECTED_PCT",
           "LAPLACIAN_ITERATIONS", "LAPLACIAN_FACTORS", "TAUBIN_PASSES", "default_poses", "plane_pose_object",
           "scan_scene", "plane_distances_mm", "fit_plane", "gaussian_table", "error_stats", "linear_fit",
           "mesh_scan", "smooth_vertices", "surface_rms_mm", "run_study", "write_report", "THESIS_QUOTE_MM_300",
           "ChainRunner", "evaluate_pose", "summarise", "board_pose_object", "rig_speckle_limit"]

# Normal-distribution fractions within 1, 2, 3 sigma, as the thesis' Table 2 rounded them.
GAUSSIAN_EXPECTED_PCT = (68.2, 95.4, 99.7)
THESIS_QUOTE_MM_300 = 1.4      # ch. 9.4: 3 x 0.3 mm + 0.5 mm bias, smoothed, around 30 cm
THESIS_GAUSSIAN_PCT = (66.0, 95.8, 100.0)  # ch. 9.1.2, Table 2 (the real rig's first data set)
LAPLACIAN_ITERATIONS = (10, 30, 100)
LAPLACIAN_FACTORS = (0.1, 0.5, 1.0)
TAUBIN_PASSES = (10, 30, 100)
REFERENCE_DISTANCE_M = 0.30
# Tilts cycled over the poses (yaw about the rig's vertical axis, pitch about its baseline), degrees:
# the thesis moved its board by hand to "several poses"; these span what a hand-held board does.
TILTS_DEG = ((0.0, 0.0), (20.0, 0.0), (-20.0, 5.0), (0.0, 15.0), (10.0, -15.0), (-25.0, 0.0), (15.0, 10.0),
             (-10.0, -10.0), (25.0, -5.0), (0.0, -20.0))


class AccuracyError(ValueError):
    """The study cannot run as asked (bad pose count or step, a scan with too few points); says what to do."""


@dataclass(frozen=True)
class Pose:
    """A board pose: distance of its centre from the rig centre along the rig's forward axis, and its tilt."""

    distance_m: float
    yaw_deg: float = 0.0
    pitch_deg: float = 0.0

    @property
    def label(self) -> str:
        """Short human label, e.g. ``300 mm, yaw 0, pitch 0``."""
        return f"{self.distance_m * 1000:.0f} mm, yaw {self.yaw_deg:+.0f}, pitch {self.pitch_deg:+.0f}"


@dataclass(frozen=True)
class StudyConfig:
    """What `run_study` does: pose count, carriage step between snaps, seeds, calibration folder."""

    poses: int = 10
    step: int = 8
    seed: int = 20261123
    calibration: Path | None = None     # None: <workspace>/config/calibration/sim (the rig's true calibration)
    min_distance_m: float = 0.20
    max_distance_m: float = 0.45
    curved_scene: str = "sphere"

    def check(self) -> None:
        """Raise `AccuracyError` on values the study cannot use."""
        if self.poses < 3:
            raise AccuracyError(f"--poses must be >= 3 for a linear fit of error against distance (got {self.poses}); "
                                f"the thesis-style study uses >= 8")
        if not 1 <= self.step <= 235:
            raise AccuracyError(f"--step must be a carriage step count in 1..235 (got {self.step}); "
                                f"8 gives ~60 snaps per pose")
        if not 0.15 <= self.min_distance_m < self.max_distance_m <= 0.7:
            raise AccuracyError(f"distances must satisfy 0.15 <= min < max <= 0.7 m "
                                f"(got {self.min_distance_m}..{self.max_distance_m})")


@dataclass
class ChainScan:
    """Points of one chain over a whole scan: xyz [m, left frame] and the left pixel (u, v) of each."""

    xyz: AnyArray
    uv: AnyArray
    snaps: int = 0


@dataclass(frozen=True)
class ChainSpec:
    """One reconstruction chain: extractor method, match parameters, matching chain, smoothing of its mesh."""

    name: str
    extractor_method: str          # "" = lsu_extract's DEFAULT_METHOD
    smooth_window_rows: int | None  # None = MatchParams default
    matching: str                  # "subpixel" | "thesis"
    mesh_smoothing: tuple[str, int, float]  # (method, iterations, Laplacian factor) applied for "smoothed"
    description: str


# Ours: lsu_extract's default sub-pixel detector, sub-pixel matching with its row smoothing, our default
# mesh smoothing (lsu_faces SmoothParams(): Taubin). Thesis: pixel detector, nearest-pixel match, no row
# smoothing, the thesis' own mesh smoothing (Laplacian, 30 iterations at 0.1, ch. 9.3.2).
CHAINS = (
    ChainSpec("ours", "", None, "subpixel", ("default", 0, 0.0),
              "default sub-pixel extraction + sub-pixel matching (MatchParams defaults) + default mesh smoothing"),
    ChainSpec("thesis", "thesis", 0, "thesis", ("laplacian", 30, 0.1),
              "thesis pixel extraction + nearest-pixel match, no row smoothing + Laplacian 30 x 0.1 (ch. 9.3.2)"),
)


def default_poses(n: int, min_m: float = 0.20, max_m: float = 0.45) -> list[Pose]:
    """``n`` poses from ``min_m`` to ``max_m``, tilts cycled from `TILTS_DEG`; one pose faces the rig at 300 mm."""
    distances = np.linspace(min_m, max_m, n)
    tilts = [TILTS_DEG[i % len(TILTS_DEG)] for i in range(n)]
    if min_m <= REFERENCE_DISTANCE_M <= max_m:
        # the headline figure is at 300 mm facing the rig (the thesis' quote); move the nearest pose there
        ref = int(np.argmin(np.abs(distances - REFERENCE_DISTANCE_M)))
        distances[ref] = REFERENCE_DISTANCE_M
        zero = tilts.index((0.0, 0.0)) if (0.0, 0.0) in tilts else ref
        tilts[ref], tilts[zero] = tilts[zero], tilts[ref]
        tilts[ref] = (0.0, 0.0)
    return [Pose(float(d), *t) for d, t in zip(distances, tilts)]


def _rotation(axis: AnyArray, deg: float) -> AnyArray:
    import cv2

    R, _ = cv2.Rodrigues(np.asarray(axis, dtype=np.float64) * math.radians(deg))
    return R


def plane_pose_object(geometry, pose: Pose):
    """The flat textured board of one pose (an `lsu_sim.SceneObject`; extra: point, normal)."""
    from lsu_sim import make_plane

    x, y, z = geometry.rig_axes
    center = geometry.rig_center + pose.distance_m * z
    normal = _rotation(x, pose.pitch_deg) @ _rotation(y, pose.yaw_deg) @ (-z)
    return make_plane(center, normal, size_m=0.8, name=f"board {pose.label}")


def board_pose_object(geometry, pose: Pose, square_m: float = 0.02, inner_corners: tuple[int, int] = (9, 6)):
    """The sim's chessboard at a pose: centre ``pose.distance_m`` in front of the rig, tilted like
    `plane_pose_object`; ``extra["pose_R"]`` / ``extra["pose_t"]`` hold its true pose (left frame)."""
    from lsu_sim import make_board

    x, y, z = geometry.rig_axes
    R = _rotation(x, pose.pitch_deg) @ _rotation(y, pose.yaw_deg) @ geometry.rig_axes.T
    centre = geometry.rig_center + pose.distance_m * z
    cols, rows = inner_corners
    first = centre - R @ np.array([(cols - 1) / 2 * square_m, (rows - 1) / 2 * square_m, 0.0])
    return make_board(R, first, inner_corners, square_m, name=f"chessboard {pose.label}")


def _line_arrays(res):
    from lsu_reconstruct.matching import LineArrays

    return LineArrays(res.u, res.v, res.peak, res.width, res.quality, res.image_width, res.image_height)


class ChainRunner:
    """Reconstructs stereo pairs through every chain; both chains see the same pixels of each pair."""

    def __init__(self, model, chains: Sequence[ChainSpec] = CHAINS) -> None:
        from lsu_extract.extractor import ExtractorParams
        from lsu_reconstruct.matching import MatchParams

        self.model, self.chains = model, tuple(chains)
        self._extractors = {spec.extractor_method: (ExtractorParams(method=spec.extractor_method)
                                                    if spec.extractor_method else ExtractorParams())
                            for spec in self.chains}
        self._match = {spec.name: (MatchParams() if spec.smooth_window_rows is None
                                   else MatchParams(smooth_window_rows=spec.smooth_window_rows)) for spec in self.chains}
        self._xyz: dict[str, list[AnyArray]] = {s.name: [] for s in self.chains}
        self._uv: dict[str, list[AnyArray]] = {s.name: [] for s in self.chains}
        self._snaps = {s.name: 0 for s in self.chains}

    def add_pair(self, left: AnyArray, right: AnyArray, snap: int) -> None:
        """Extract, match and triangulate one laser-on pair (BGR or mono uint8) with every chain."""
        from lsu_extract.extractor import extract_laser_line
        from lsu_reconstruct.pipeline import reconstruct_snap

        lines = {method: (_line_arrays(extract_laser_line(left, params)), _line_arrays(extract_laser_line(right, params)))
                 for method, params in self._extractors.items()}
        for spec in self.chains:
            line_l, line_r = lines[spec.extractor_method]
            if len(line_l.u) == 0 or len(line_r.u) == 0:
                continue  # the laser misses the target in one camera at this carriage position
            pts = reconstruct_snap(self.model, line_l, line_r, self._match[spec.name], snap=snap, chain=spec.matching)
            if len(pts):
                self._xyz[spec.name].append(pts.xyz)
                self._uv[spec.name].append(np.column_stack([pts.u, pts.v]))
                self._snaps[spec.name] += 1

    def scans(self) -> dict[str, ChainScan]:
        """What every chain reconstructed so far."""
        return {s.name: ChainScan(np.concatenate(self._xyz[s.name]) if self._xyz[s.name] else np.zeros((0, 3)),
                                  np.concatenate(self._uv[s.name]) if self._uv[s.name] else np.zeros((0, 2)),
                                  self._snaps[s.name]) for s in self.chains}


def scan_scene(model, geometry, objects: Sequence, step: int, seed: int,
               chains: Sequence[ChainSpec] = CHAINS) -> dict[str, ChainScan]:
    """Stop-snap scan of a sim scene (carriage 0..track end every ``step``), reconstructed by every chain.

    Each pair is rendered once (settled carriage, laser on, render noise seeded ``seed + step``) and
    both chains see the same pixels, so their difference is the chain alone.
    """
    from lsu_sim import SimulatedRig

    rig = SimulatedRig(geometry, objects, seed=seed)
    runner = ChainRunner(model, chains)
    for carriage in range(0, int(geometry.track_steps) + 1, step):
        frame = rig.render(float(carriage), seed=seed + carriage)
        runner.add_pair(frame.left, frame.right, carriage)
    return runner.scans()


def plane_distances_mm(xyz: AnyArray, point: AnyArray, normal: AnyArray) -> AnyArray:
    """Signed distances [mm] of points to the plane through ``point`` with unit ``normal``."""
    n = np.asarray(normal, dtype=np.float64)
    return (np.asarray(xyz) - np.asarray(point)) @ (n / np.linalg.norm(n)) * 1000.0


def fit_plane(xyz: AnyArray) -> tuple[AnyArray, AnyArray]:
    """Least-squares plane (centroid, unit normal) by SVD: the free fit a rig without truth would make."""
    pts = np.asarray(xyz, dtype=np.float64)
    if len(pts) < 3:
        raise AccuracyError(f"a plane fit needs >= 3 points, got {len(pts)}")
    c = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - c, full_matrices=False)
    return c, vt[-1]


def gaussian_table(residuals: AnyArray) -> tuple[float, float, float]:
    """Percent of residuals within 1, 2, 3 standard deviations of their mean (thesis Table 2)."""
    r = np.asarray(residuals, dtype=np.float64)
    if len(r) < 2:
        raise AccuracyError(f"the Gaussian table needs >= 2 residuals, got {len(r)}")
    z = np.abs(r - r.mean()) / max(float(r.std()), 1e-300)
    return tuple(float(np.mean(z <= k) * 100.0) for k in (1, 2, 3))  # type: ignore[return-value]


def error_stats(d_mm: AnyArray) -> dict[str, float]:
    """Mean (bias), median, sigma, RMS, 3 sigma and the thesis' bound |bias| + 3 sigma of signed distances [mm]."""
    d = np.asarray(d_mm, dtype=np.float64)
    if len(d) == 0:
        raise AccuracyError("no points to measure: the scan found no laser line on the target")
    sigma, mean = float(d.std()), float(d.mean())
    return {"points": int(len(d)), "mean_mm": mean, "median_mm": float(np.median(d)), "sigma_mm": sigma,
            "rms_mm": float(np.sqrt(np.mean(d * d))), "three_sigma_mm": 3.0 * sigma,
            "bound_mm": abs(mean) + 3.0 * sigma, "max_abs_mm": float(np.abs(d).max())}


def linear_fit(x: Sequence[float], y: Sequence[float]) -> tuple[float, float]:
    """Least-squares straight line ``y = slope * x + intercept`` (the thesis' trend lines, Fig. 43)."""
    x_arr, y_arr = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if len(x_arr) < 2 or np.ptp(x_arr) == 0:
        raise AccuracyError("a linear fit needs >= 2 distinct distances")
    slope, intercept = np.polyfit(x_arr, y_arr, 1)
    return float(slope), float(intercept)


def mesh_scan(scan: ChainScan):
    """Mesh a scan in the left image plane (lsu_faces); returns the `FaceMesh` and its used vertex indices."""
    from lsu_faces.mesh import MeshError, triangulate_image_plane

    try:
        mesh = triangulate_image_plane(scan.xyz, scan.uv)
    except MeshError as exc:
        raise AccuracyError(f"cannot mesh the scan: {exc}") from None
    used = np.unique(mesh.triangles)
    return mesh, used


def smooth_vertices(mesh, method: str, iterations: int, factor: float) -> AnyArray:
    """Vertices after lsu_faces smoothing (``method`` ``default`` = SmoothParams(), ``laplacian``, ``taubin``)."""
    from lsu_faces.smoothing import SmoothParams, smooth

    if method == "default":
        params = SmoothParams()
    elif method == "laplacian":
        params = SmoothParams(method="laplacian", iterations=iterations, factor=factor)
    else:
        params = SmoothParams(method="taubin", iterations=iterations)
    return smooth(mesh.vertices, mesh.triangles, params)


def surface_distances_m(objects: Sequence, xyz: AnyArray) -> AnyArray:
    """Distance [m] of each point to the rendered scene meshes (open3d ray-casting scene: exact truth)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    for obj in objects:
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(obj.mesh))
    return scene.compute_distance(o3d.core.Tensor(np.asarray(xyz, dtype=np.float32))).numpy().astype(np.float64)


def surface_rms_mm(objects: Sequence, xyz: AnyArray) -> float:
    """RMS distance [mm] of points to the rendered scene meshes."""
    d = surface_distances_m(objects, xyz)
    return float(np.sqrt(np.mean(d * d)) * 1000.0)


def _smoothing_grid() -> list[tuple[str, str, int, float]]:
    """(label, method, iterations, factor) of the smoothing study, the raw mesh first."""
    grid = [("none", "none", 0, 0.0)]
    grid += [(f"laplacian {it} x {f:g}", "laplacian", it, f) for it in LAPLACIAN_ITERATIONS for f in LAPLACIAN_FACTORS]
    grid += [(f"taubin {it}", "taubin", it, 0.0) for it in TAUBIN_PASSES]
    return grid


def evaluate_pose(scans: dict[str, ChainScan], p0: AnyArray, n: AnyArray, label: str,
                  hint: str = "use a smaller --step or keep the poses inside 200..450 mm",
                  keep: Callable[[AnyArray], AnyArray] | None = None) -> tuple[dict, dict, dict]:
    """Statistics of one pose for every chain against its truth plane (``p0``, unit ``n``, left frame).

    ``keep(xyz) -> bool mask`` selects the points on the target (a real board has a wall behind it).
    Returns (row: per-chain statistics, z: normalised residuals per chain for the pooled Gaussian
    table, meshes: per chain (mesh, used vertex indices, p0, n) for the smoothing study).
    """
    row: dict = {}
    pooled: dict[str, AnyArray] = {}
    meshes: dict[str, tuple] = {}
    for spec in CHAINS:
        scan = scans[spec.name]
        if keep is not None and len(scan.xyz):
            mask = keep(scan.xyz)
            scan = ChainScan(scan.xyz[mask], scan.uv[mask], scan.snaps)
        if len(scan.xyz) < 50:
            raise AccuracyError(f"{label}: the {spec.name} chain reconstructed only {len(scan.xyz)} points on the "
                                f"board; {hint}")
        d = plane_distances_mm(scan.xyz, p0, n)
        c, nf = fit_plane(scan.xyz)
        free = plane_distances_mm(scan.xyz, c, nf)
        mesh, used = mesh_scan(scan)
        method, its, fac = spec.mesh_smoothing
        smoothed = smooth_vertices(mesh, method, its, fac)[used]
        ds = plane_distances_mm(smoothed, p0, n)
        pooled[spec.name] = (d - d.mean()) / max(float(d.std()), 1e-300)
        row[spec.name] = {
            "snaps": scan.snaps,
            "mean_distance_mm": float(np.linalg.norm(scan.xyz, axis=1).mean() * 1000.0),
            "raw": error_stats(d), "smoothed": error_stats(ds), "free_fit": error_stats(free),
            "free_fit_tilt_err_deg": float(np.degrees(np.arccos(min(1.0, abs(float(nf @ n)))))),
            "free_fit_offset_mm": float(abs((c - p0) @ n) * 1000.0),
            "gaussian_pct": list(gaussian_table(d)),
        }
        meshes[spec.name] = (mesh, used, p0, n)
    return row, pooled, meshes


def summarise(result: dict, per_pose: list[dict], pooled_z: dict[str, list[AnyArray]], ref_index: int,
              ref_meshes: dict[str, tuple]) -> dict:
    """Fill ``result`` with the Gaussian table, the trends, the board smoothing study and the figures."""
    result["poses"] = per_pose
    # Gaussian table: every pose's residuals normalised by its own mean and sigma, pooled (the thesis
    # checked one data set; pooling shows the shape holds over distances and tilts).
    result["gaussian"] = {name: list(gaussian_table(np.concatenate(zs))) for name, zs in pooled_z.items()}
    edges = np.linspace(-4.0, 4.0, 41)
    result["gaussian"]["hist_edges"] = edges.tolist()
    for name, zs in pooled_z.items():
        result["gaussian"][f"hist_{name}"] = np.histogram(np.concatenate(zs), edges, density=True)[0].tolist()
    result["gaussian"]["expected"] = list(GAUSSIAN_EXPECTED_PCT)
    result["gaussian"]["thesis_rig"] = list(THESIS_GAUSSIAN_PCT)

    # Error against the mean distance from the left camera's optical centre (thesis Fig. 43, 46).
    trends: dict = {}
    for spec in CHAINS:
        dist = [r[spec.name]["mean_distance_mm"] for r in per_pose]
        for state in ("raw", "smoothed"):
            for stat in ("sigma_mm", "mean_mm", "median_mm"):
                slope, icpt = linear_fit(dist, [r[spec.name][state][stat] for r in per_pose])
                trends[f"{spec.name}_{state}_{stat}"] = {"slope_per_mm": slope, "intercept_mm": icpt,
                                                         "at_300_mm": slope * 300.0 + icpt}
    result["trends"] = trends

    # Smoothing study on the reference board: noise left after each smoother, per chain.
    smoothing: dict = result.setdefault("smoothing", {})
    smoothing["plane_300"] = {}
    for spec in CHAINS:
        mesh, used, p0, n = ref_meshes[spec.name]
        rows = []
        for label, method, its, fac in _smoothing_grid():
            v = mesh.vertices[used] if method == "none" else smooth_vertices(mesh, method, its, fac)[used]
            st = error_stats(plane_distances_mm(v, p0, n))
            rows.append({"label": label, "method": method, "iterations": its, "factor": fac, **st})
        smoothing["plane_300"][spec.name] = rows

    ref = per_pose[ref_index]
    result["reference_pose"] = ref["label"]
    result["figures"] = {
        "three_sigma_mm_300_smoothed": ref["ours"]["smoothed"]["bound_mm"],
        "three_sigma_mm_300_raw": ref["ours"]["raw"]["bound_mm"],
        "sigma_mm_300_smoothed": ref["ours"]["smoothed"]["sigma_mm"],
        "bias_mm_300_smoothed": ref["ours"]["smoothed"]["mean_mm"],
        "thesis_three_sigma_mm_300": ref["thesis"]["smoothed"]["bound_mm"],
        "thesis_three_sigma_mm_300_raw": ref["thesis"]["raw"]["bound_mm"],
        "thesis_sigma_mm_300_smoothed": ref["thesis"]["smoothed"]["sigma_mm"],
        "thesis_quote_mm_300": THESIS_QUOTE_MM_300,
        "gaussian_1sigma_pct": result["gaussian"]["ours"][0],
        "gaussian_2sigma_pct": result["gaussian"]["ours"][1],
        "gaussian_3sigma_pct": result["gaussian"]["ours"][2],
        "thesis_gaussian_1sigma_pct": result["gaussian"]["thesis"][0],
        "thesis_gaussian_2sigma_pct": result["gaussian"]["thesis"][1],
        "thesis_gaussian_3sigma_pct": result["gaussian"]["thesis"][2],
        "sigma_slope_mm_per_m": trends["ours_raw_sigma_mm"]["slope_per_mm"] * 1000.0,
        "thesis_sigma_slope_mm_per_m": trends["thesis_raw_sigma_mm"]["slope_per_mm"] * 1000.0,
        "poses": len(per_pose),
    }
    return result


def rig_speckle_limit(geometry, distance_m: float = REFERENCE_DISTANCE_M, with_lens_blur: bool = False) -> dict[str, float]:
    """`lsu_reconstruct.speckle.speckle_limit` for a simulated rig's optics at ``distance_m`` (JSON-ready).

    ``with_lens_blur``: include the rig's Gaussian PSF, which the renderer applies to the intensity after
    the speckle and so averages neighbouring rows (the limit of the rendered images, below the optics').
    """
    from lsu_reconstruct.speckle import speckle_limit

    return speckle_limit(geometry.laser.wavelength_nm, geometry.sensor.f_number, float(geometry.left.K[0, 0]),
                         geometry.sensor.pixel_size_m, float(np.linalg.norm(geometry.translation)), distance_m,
                         geometry.laser.sheet_sigma_m, geometry.speckle.contrast,
                         geometry.sensor.psf_sigma_px if with_lens_blur else 0.0).as_dict()


def run_study(config: StudyConfig = StudyConfig(), progress: Callable[[str], None] = lambda s: None) -> dict:
    """The whole study on the simulated rig; returns a JSON-ready dict (see `write_report`)."""
    from lsu_config import config_dir
    from lsu_faces.smoothing import SmoothParams
    from lsu_reconstruct.stereo import StereoModel
    from lsu_sim import build_scene, load_rig

    config.check()
    t_start = time.perf_counter()
    calibration = config.calibration or (config_dir() / "calibration" / "sim")
    model = StereoModel.from_folder(calibration)
    geometry = load_rig()
    poses = default_poses(config.poses, config.min_distance_m, config.max_distance_m)
    per_pose: list[dict] = []
    pooled_z: dict[str, list[AnyArray]] = {c.name: [] for c in CHAINS}
    ref_index = None
    ref_meshes: dict[str, tuple] = {}
    for i, pose in enumerate(poses):
        t0 = time.perf_counter()
        board = plane_pose_object(geometry, pose)
        p0, n = board.extra["point"], board.extra["normal"]
        scans = scan_scene(model, geometry, [board], config.step, config.seed + 1000 * i)
        stats, z, meshes = evaluate_pose(scans, p0, n, f"pose {pose.label}")
        row: dict = {"pose": asdict(pose), "label": pose.label, **stats}
        for name, zs in z.items():
            pooled_z[name].append(zs)
        if ref_index is None and pose.distance_m == REFERENCE_DISTANCE_M and pose.yaw_deg == 0.0 \
                and pose.pitch_deg == 0.0:
            ref_index, ref_meshes = i, meshes
        per_pose.append(row)
        progress(f"pose {i + 1}/{len(poses)} ({pose.label}): ours sigma {row['ours']['raw']['sigma_mm']:.3f} mm, "
                 f"thesis sigma {row['thesis']['raw']['sigma_mm']:.3f} mm ({time.perf_counter() - t0:.0f} s)")
    if ref_index is None:
        raise AccuracyError("no pose at 300 mm facing the rig: keep 300 mm inside the distance range")

    result: dict = {"source": "sim", "truth": "the renderer's plane",
                    "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(config).items()},
                    "calibration": str(calibration), "chains": {c.name: c.description for c in CHAINS},
                    "default_smoothing": asdict(SmoothParams())}
    result["config"]["calibration"] = str(calibration)
    summarise(result, per_pose, pooled_z, ref_index, ref_meshes)
    limit = rig_speckle_limit(geometry)
    blurred = rig_speckle_limit(geometry, with_lens_blur=True)
    result["speckle"] = {"limit": limit, "limit_with_lens_blur": blurred, "contrast": geometry.speckle.contrast,
                         "f_number": geometry.sensor.f_number}
    ref = per_pose[ref_index]
    result["figures"].update({
        "speckle_limit_mm_300": limit["depth_mm"],
        "speckle_limit_px": limit["line_px"],
        "plane_sigma_mm_300": ref["ours"]["raw"]["sigma_mm"],
        "plane_sigma_over_speckle_limit": ref["ours"]["raw"]["sigma_mm"] / limit["depth_mm"]
        if limit["depth_mm"] > 0 else float("inf"),
        "thesis_plane_sigma_mm_300": ref["thesis"]["raw"]["sigma_mm"],
        "speckle_limit_mm_300_with_lens_blur": blurred["depth_mm"],
    })
    progress("smoothing study on the board done; scanning the curved truth")

    # Detail loss: the same smoothers on a curved truth; RMS distance from the rendered surface.
    curved_objects = build_scene(config.curved_scene, geometry)
    scans = scan_scene(model, geometry, curved_objects, config.step, config.seed + 999_000)
    curved: dict = {}
    for spec in CHAINS:
        mesh, used = mesh_scan(scans[spec.name])
        rows = []
        for label, method, its, fac in _smoothing_grid():
            v = mesh.vertices[used] if method == "none" else smooth_vertices(mesh, method, its, fac)[used]
            rows.append({"label": label, "method": method, "iterations": its, "factor": fac,
                         "rms_mm": surface_rms_mm(curved_objects, v), "points": int(len(used))})
        default_v = smooth_vertices(mesh, "default", 0, 0.0)[used]
        rows.append({"label": "default (ours)", "method": "default", "iterations": SmoothParams().iterations,
                     "factor": 0.0, "rms_mm": surface_rms_mm(curved_objects, default_v), "points": int(len(used))})
        curved[spec.name] = rows
    result["smoothing"]["curved"] = curved
    result["smoothing"]["curved_scene"] = config.curved_scene
    result["figures"]["curved_rms_mm_raw"] = curved["ours"][0]["rms_mm"]
    result["figures"]["curved_rms_mm_default_smoothing"] = curved["ours"][-1]["rms_mm"]
    result["seconds"] = time.perf_counter() - t_start
    return result


# ---------------------------------------------------------------- report
def _plots(result: dict, out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = []
    # 1. Gaussian check: pooled normalised residuals against the unit normal density, and the table.
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    edges = np.asarray(result["gaussian"]["hist_edges"])
    centres = 0.5 * (edges[1:] + edges[:-1])
    z = np.linspace(edges[0], edges[-1], 400)
    for ax, name in zip(axes, ("ours", "thesis")):
        ax.bar(centres, result["gaussian"][f"hist_{name}"], width=np.diff(edges), alpha=0.6, label="measured")
        ax.plot(z, np.exp(-0.5 * z * z) / math.sqrt(2 * math.pi), "k-", label="normal")
        ax.set_title(f"{name} chain: within 1/2/3 sigma {' / '.join(f'{p:.1f}' for p in result['gaussian'][name])} %",
                     fontsize=9)
        ax.set_xlabel("(distance - mean) / sigma, per pose")
        ax.set_ylabel("density")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "gaussian_table.png", dpi=90)
    plt.close(fig)
    names.append("gaussian_table.png")

    # 2. Error against distance (thesis Fig. 43/46), both chains, raw and smoothed, with linear fits.
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for ax, name in zip(axes, ("ours", "thesis")):
        dist = np.array([r[name]["mean_distance_mm"] for r in result["poses"]])
        xs = np.linspace(dist.min(), dist.max(), 2)
        for state, style in (("raw", "o"), ("smoothed", "s")):
            for stat, colour in (("sigma_mm", "tab:green"), ("mean_mm", "tab:blue"), ("median_mm", "tab:red")):
                y = [r[name][state][stat] for r in result["poses"]]
                ax.plot(dist, y, style, color=colour, alpha=0.5 if state == "raw" else 1.0,
                        label=f"{stat[:-3]} {state}")
                t = result["trends"][f"{name}_{state}_{stat}"]
                ax.plot(xs, t["slope_per_mm"] * xs + t["intercept_mm"], "-" if state == "smoothed" else ":",
                        color=colour)
        ax.set_title(f"{name} chain: error vs distance")
        ax.set_xlabel("mean distance from left camera [mm]")
        ax.set_ylabel("distance to true plane [mm]")
        ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(out / "error_vs_distance.png", dpi=90)
    plt.close(fig)
    names.append("error_vs_distance.png")

    # 3. Smoothing study: noise left on the board and detail lost on the curved truth.
    panels = [("plane_300", "sigma_mm", f"board, {result.get('reference_pose', '300 mm')}: sigma vs true plane")]
    if "curved" in result["smoothing"]:  # the simulated study only: a real rig has no curved truth
        panels.append(("curved", "rms_mm", f"{result['smoothing']['curved_scene']}: RMS from true surface"))
    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4.2), squeeze=False)
    for ax, (key, stat, title) in zip(axes[0], panels):
        for name, marker in (("ours", "o"), ("thesis", "s")):
            rows = result["smoothing"][key][name]
            base = rows[0][stat]
            ax.axhline(base, color="grey" if name == "ours" else "black", ls=":", lw=1)
            for f in LAPLACIAN_FACTORS:
                sel = [r for r in rows if r["method"] == "laplacian" and r["factor"] == f]
                ax.plot([r["iterations"] for r in sel], [r[stat] for r in sel], marker + "-",
                        label=f"{name} Laplacian x{f:g}")
            sel = [r for r in rows if r["method"] == "taubin"]
            ax.plot([r["iterations"] for r in sel], [r[stat] for r in sel], marker + "--", label=f"{name} Taubin")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("iterations / passes (dotted: unsmoothed)")
        ax.set_ylabel(f"{stat[:-3]} [mm]")
        ax.set_title(title, fontsize=9)
        ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(out / "smoothing.png", dpi=90)
    plt.close(fig)
    names.append("smoothing.png")
    return names


def _fmt(x: float, digits: int = 3) -> str:
    return f"{x:.{digits}f}"


def _speckle_lines(result: dict) -> list[str]:
    """The speckle-limit section of report.md (simulated study only: a real rig's optics are not known here)."""
    if "speckle" not in result:
        return []
    f, lim = result["figures"], result["speckle"]["limit"]
    return ["## Speckle limit (300 mm)", "",
            f"The renders carry laser speckle (contrast {result['speckle']['contrast']:g}, f/{result['speckle']['f_number']:g}, "
            f"grain {lim['grain_px']:.2f} px). Speckle-limited sigma of one point: line centre "
            f"{lim['line_px']:.3f} px per row (Dorsch et al.'s diffraction-limited floor {lim['dorsch_px']:.3f} px), "
            f"depth {lim['depth_mm']:.3f} mm (stereo, independent speckle in both cameras; Dorsch's laser-"
            f"triangulation form {lim['dorsch_depth_mm']:.3f} mm). Averaging along the line (row smoothing, mesh "
            f"smoothing) may go below it; a single point cannot. The renderer's lens blur acts on the intensity "
            f"after the speckle and averages neighbouring rows: the limit of the rendered images is "
            f"{result['figures'].get('speckle_limit_mm_300_with_lens_blur', float('nan')):.3f} mm.", "",
            "| | measured sigma [mm] | speckle limit [mm] | ratio |", "|---|---|---|---|",
            f"| ours, raw | {_fmt(f['plane_sigma_mm_300'], 4)} | {_fmt(f['speckle_limit_mm_300'], 4)} | "
            f"{f['plane_sigma_over_speckle_limit']:.2f} |",
            f"| thesis chain, raw | {_fmt(f['thesis_plane_sigma_mm_300'], 4)} | {_fmt(f['speckle_limit_mm_300'], 4)} | "
            f"{f['thesis_plane_sigma_mm_300'] / max(f['speckle_limit_mm_300'], 1e-300):.2f} |", ""]


def write_report(result: dict, out_dir: Path) -> list[Path]:
    """Write report.md, the PNG plots and accuracy.json into ``out_dir``; returns the files written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    pngs = _plots(result, out)
    (out / "accuracy.json").write_text(json.dumps(result, indent=1, default=float))
    f = result["figures"]
    g = result["gaussian"]
    bag = result.get("source") == "bag"
    if bag:
        c = result["config"]
        lines = ["# LSU accuracy report (thesis ch. 9, recorded board scans)", "",
                 f"{len(result['poses'])} recorded scans of a {c['board']} chessboard ({c['square_mm']:g} mm squares) "
                 f"from `{c['bag']}`; calibration `{result['calibration']}`; truth: {result['truth']} (OpenCV "
                 f"solvePnP with the left intrinsics), points over the checkered area within "
                 f"{c['background_gate_mm']:g} mm of it. Both chains reconstruct the same recorded pairs:", ""]
    else:
        lines = [
            "# LSU accuracy report (thesis ch. 9, simulated rig)", "",
            f"{len(result['poses'])} poses of a flat textured board, {result['config']['min_distance_m'] * 1000:.0f} "
            f"to {result['config']['max_distance_m'] * 1000:.0f} mm from the rig centre, tilted up to 25 deg; "
            f"stop-snap scans every {result['config']['step']} carriage steps; calibration `{result['calibration']}`; "
            f"truth: the renderer's plane. Both chains reconstruct the same rendered pairs:", "",
        ]
    lines += [f"- **{k}**: {v}" for k, v in result["chains"].items()]
    lines += ["", "\"3 sigma\" is the thesis' quote: |bias| + 3 sigma of the signed distances to the true plane "
              "(ch. 9.4: 0.5 mm + 3 x 0.3 mm = 1.4 mm at 30 cm, smoothed).", "",
              f"## Headline ({'reference pose: ' + result['reference_pose'] if bag else '300 mm, facing the rig'})", "",
              "| | ours | thesis chain | thesis (real rig, 2005) |", "|---|---|---|---|",
              f"| 3 sigma + bias, smoothed [mm] | {_fmt(f['three_sigma_mm_300_smoothed'])} | "
              f"{_fmt(f['thesis_three_sigma_mm_300'])} | {THESIS_QUOTE_MM_300} |",
              f"| 3 sigma + bias, raw [mm] | {_fmt(f['three_sigma_mm_300_raw'])} | "
              f"{_fmt(f['thesis_three_sigma_mm_300_raw'])} | |",
              f"| sigma smoothed [mm] | {_fmt(f['sigma_mm_300_smoothed'])} | {_fmt(f['thesis_sigma_mm_300_smoothed'])}"
              f" | 0.3 |", "",
              f"Target 3 sigma <= 0.15 mm: **{'met' if f['three_sigma_mm_300_smoothed'] <= 0.15 else 'NOT met'}**.", "",
              *_speckle_lines(result),
              "## Gaussian table (all poses, residuals normalised per pose)", "",
              "| within | ours [%] | thesis chain [%] | normal [%] | thesis real rig [%] |", "|---|---|---|---|---|"]
    for k in range(3):
        lines.append(f"| {k + 1} sigma | {g['ours'][k]:.1f} | {g['thesis'][k]:.1f} | {g['expected'][k]} | "
                     f"{g['thesis_rig'][k]} |")
    ok = all(abs(g["ours"][k] - g["expected"][k]) <= 3.0 for k in range(3))
    lines += ["", f"Within 3 points of the normal fractions (ours): **{'yes' if ok else 'no'}**.", "",
              "![Gaussian table](gaussian_table.png)", "", "## Per pose", "",
              "| pose | chain | snaps | points | mean dist [mm] | bias [mm] | sigma raw [mm] | sigma smoothed [mm] "
              "| 3s+bias smoothed [mm] | free-fit sigma [mm] | free-fit tilt err [deg] |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in result["poses"]:
        for name in ("ours", "thesis"):
            c = r[name]
            lines.append(f"| {r['label']} | {name} | {c['snaps']} | {c['raw']['points']} | {c['mean_distance_mm']:.0f} | "
                         f"{_fmt(c['raw']['mean_mm'], 4)} | {_fmt(c['raw']['sigma_mm'], 4)} | "
                         f"{_fmt(c['smoothed']['sigma_mm'], 4)} | {_fmt(c['smoothed']['bound_mm'])} | "
                         f"{_fmt(c['free_fit']['sigma_mm'], 4)} | {c['free_fit_tilt_err_deg']:.3f} |")
    if bag:
        lines += ["", "## Truth (the detected board)", ""]
        if result.get("skipped"):
            lines += ["Scans left out of every figure:", ""] + [f"- {reason}" for reason in result["skipped"]] + [""]
        lines += ["How well each board pose is known: the RMS reprojection of its corners in the left image, and "
                  "how far the pose solved from the right image (carried into the left frame by the stereo "
                  "calibration) lies from it at the board centre. Errors below these are not resolved.", "",
                  "| pose | reprojection [px] | right-image pose offset [mm] | tilt between them [deg] |",
                  "|---|---|---|---|"]
        for r in result["poses"]:
            t = r["truth"]
            off = "not found" if t["stereo_offset_mm"] is None else _fmt(t["stereo_offset_mm"], 4)
            tilt = "" if t["stereo_tilt_deg"] is None else _fmt(t["stereo_tilt_deg"], 4)
            lines.append(f"| {r['label']} | {_fmt(t['reprojection_px'], 4)} | {off} | {tilt} |")
    lines += ["", "## Error against distance (linear fits, mm per metre of mean distance)", "",
              "| chain | state | sigma slope | sigma at 300 mm | bias slope | bias at 300 mm |", "|---|---|---|---|---|---|"]
    for name in ("ours", "thesis"):
        for state in ("raw", "smoothed"):
            s, b = result["trends"][f"{name}_{state}_sigma_mm"], result["trends"][f"{name}_{state}_mean_mm"]
            lines.append(f"| {name} | {state} | {s['slope_per_mm'] * 1000:.4f} | {_fmt(s['at_300_mm'], 4)} | "
                         f"{b['slope_per_mm'] * 1000:.4f} | {_fmt(b['at_300_mm'], 4)} |")
    lines += ["", "![error vs distance](error_vs_distance.png)", "", "## Smoothing study", ""]
    sp = result["smoothing"]
    curved = "curved" in sp
    if curved:
        lines += [f"Board at 300 mm: sigma of the smoothed mesh against the true plane (noise left). "
                  f"{sp['curved_scene']}: RMS distance of the smoothed mesh from the rendered surface "
                  f"(noise left plus shape lost: Laplacian smoothing shrinks a curved surface).", "",
                  "| smoother | ours board sigma [mm] | thesis board sigma [mm] | ours curved RMS [mm] | "
                  "thesis curved RMS [mm] |", "|---|---|---|---|---|"]
    else:
        lines += [f"Board ({result['reference_pose']}): sigma of the smoothed mesh against the detected plane "
                  f"(noise left). Shape loss needs a curved truth, which only the simulated study has "
                  f"(`lsu accuracy --sim`).", "",
                  "| smoother | ours board sigma [mm] | thesis board sigma [mm] |", "|---|---|---|"]
    for i, row in enumerate(sp["plane_300"]["ours"]):
        cells = [row["label"], _fmt(row["sigma_mm"], 4), _fmt(sp["plane_300"]["thesis"][i]["sigma_mm"], 4)]
        if curved:
            cells += [_fmt(sp["curved"]["ours"][i]["rms_mm"], 4), _fmt(sp["curved"]["thesis"][i]["rms_mm"], 4)]
        lines.append("| " + " | ".join(cells) + " |")
    if curved:
        lines.append(f"| default (ours: {result['default_smoothing']['method']} "
                     f"{result['default_smoothing']['iterations']}) | | | {_fmt(sp['curved']['ours'][-1]['rms_mm'], 4)} "
                     f"| {_fmt(sp['curved']['thesis'][-1]['rms_mm'], 4)} |")
    lines += [
              "", "![smoothing](smoothing.png)", "",
              f"Run time {result['seconds']:.0f} s. Figures: `accuracy.json`."]
    (out / "report.md").write_text("\n".join(lines) + "\n")
    return [out / "report.md", out / "accuracy.json", *(out / p for p in pngs)]

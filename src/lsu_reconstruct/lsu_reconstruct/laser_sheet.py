"""The laser's light sheet as a function of the carriage position, fitted from scans of flat targets.

Model: the carriage carries the line laser along a straight track without turning it, so the sheet
keeps its orientation and translates: at carriage position ``p`` (steps) its centre plane is
``n . X = c0 + k p`` (``n`` unit normal, left optical frame, metres; ``k`` metres per step along
``n``). FabScan and Horus calibrate the same plane for their single camera; here it complements the
stereo pair: with it, one camera's laser line gives points on its own (a sweep whose two cameras
expose at different times, a snap where one camera's line is hidden).

The fit uses triangulated scan points with the carriage position of their snap. Every point of a
snap lies on the sheet; the points of one flat target also lie on the target's plane, so at least
two targets (different distances or tilts) are needed, else the target's plane fits as well as the
sheet. Minimising the squared distances ``(n . X_i - c0 - k p_i)^2`` over ``c0, k`` for a given ``n``
is linear least squares; eliminating them leaves the smallest eigenvector of a 3x3 matrix for ``n``
(closed form, no iteration, no initial guess). Outliers (stray points at board edges, mismatches)
are removed by a few rounds of trimming at a multiple of the robust residual scale.

A pure module: numpy only, no ROS.
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from lsu_common.arrays import FloatArray

# an acceptable sheet: its second-best direction must fit at least this much worse than the best
MIN_CONDITION = 25.0


class LaserSheetError(ValueError):
    """The points cannot determine the sheet; the message says what to scan."""


@dataclass(frozen=True)
class LaserSheet:
    """The fitted sheet and how well it fits."""

    normal: tuple[float, float, float]  # unit normal, left optical frame
    c0_m: float                          # plane offset at position 0 [m]
    m_per_step: float                    # offset change per carriage step [m]
    residual_mm: float                   # RMS point-to-sheet distance of the kept points [mm]
    points: int                          # points kept by the fit
    rejected: int                        # points trimmed as outliers
    positions: tuple[int, int]           # carriage range the points came from [steps]

    def plane(self, position_steps: float) -> tuple[FloatArray, float]:
        """(n, c) with the sheet's centre plane ``n . X = c`` at ``position_steps``."""
        return np.asarray(self.normal, float), float(self.c0_m + self.m_per_step * position_steps)

    def distance_m(self, points: FloatArray, position_steps: FloatArray) -> FloatArray:
        """Signed distance of each point to the sheet at its carriage position [m]."""
        n = np.asarray(self.normal, float)
        return np.asarray(points, float) @ n - (self.c0_m + self.m_per_step * np.asarray(position_steps, float))

    def intersect_rays(self, origin: FloatArray, directions: FloatArray, position_steps: float) -> FloatArray:
        """Where rays ``origin + t d`` (one camera's pixel rays, left frame) meet the sheet; NaN when parallel."""
        n, c = self.plane(position_steps)
        d = np.asarray(directions, float).reshape(-1, 3)
        o = np.asarray(origin, float).reshape(3)
        denom = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (c - o @ n) / denom
        t = np.where(np.abs(denom) > 1e-12, t, np.nan)
        return o + t[:, None] * d


def _solve(points: FloatArray, positions: FloatArray, weights: FloatArray | None = None
           ) -> tuple[FloatArray, float, float, FloatArray]:
    """(Weighted) least-squares (n, c0, k) and the eigenvalues of the reduced problem (ascending).

    ``weights``: per point, the inverse variance of its distance to the sheet (None: all equal);
    each row of the problem is scaled by its weight's square root.
    """
    design = np.column_stack([np.ones_like(positions), positions])
    if weights is not None:
        root = np.sqrt(weights)[:, None]
        design, points = design * root, points * root
    # project the point coordinates off span{1, p}: what c0 + k p cannot explain
    coef, *_ = np.linalg.lstsq(design, points, rcond=None)
    reduced = points - design @ coef
    scatter = reduced.T @ reduced
    values, vectors = np.linalg.eigh(scatter)
    n = vectors[:, 0]
    # orientation convention: the normal points along the carriage's travel (c grows with p)
    c0, k = coef @ n
    if k < 0:
        n, c0, k = -n, -c0, -k
    return n, float(c0), float(k), values


# Huber's constant: weights fall off beyond this many robust sigmas of a point's own normalised residual
HUBER_K = 1.345


def fit_laser_sheet(points: FloatArray, positions: FloatArray, trim_sigmas: float = 4.0,
                    rounds: int = 3, sigma_m: FloatArray | None = None) -> LaserSheet:
    """Fit the sheet to scan points (N x 3, metres) and the carriage position of each one's snap (N,).

    ``sigma_m``: each point's own uncertainty along the sheet's normal [m] (from its row's estimated
    centre uncertainty, `lsu_extract.uncertainty.row_sigma_px`, through the triangulation), or None
    (all equal). With it the fit is iteratively reweighted: each point weighs by its inverse variance
    times Huber's weight of its residual in its own sigmas (over the robust scale of those normalised
    residuals), and the trimming tests that normalised residual, so a noisy row neither pulls the sheet
    as much as a clean one nor is trimmed for noise it was expected to have. The reported residual is
    the plain RMS of the kept points either way.

    Raises LaserSheetError when the points cannot determine the sheet (too few, one position, or all
    on one flat target, or uncertainties that are not positive).
    """
    X = np.asarray(points, float).reshape(-1, 3)
    p = np.asarray(positions, float).reshape(-1)
    if len(X) != len(p):
        raise LaserSheetError(f"{len(X)} points but {len(p)} positions: give one carriage position per point")
    sigma = None if sigma_m is None else np.asarray(sigma_m, float).reshape(-1)
    if sigma is not None:
        if len(sigma) != len(p):
            raise LaserSheetError(f"{len(X)} points but {len(sigma)} uncertainties: give one sigma_m per point")
        if not np.all(sigma[np.isfinite(sigma)] > 0):
            raise LaserSheetError("every point's uncertainty sigma_m must be positive (metres)")
    finite = np.isfinite(X).all(axis=1) & np.isfinite(p)
    if sigma is not None:
        finite &= np.isfinite(sigma)
        sigma = sigma[finite]
    X, p = X[finite], p[finite]
    if len(X) < 50:
        raise LaserSheetError(f"only {len(X)} usable points: scan a flat board or wall at two or more distances")
    if np.ptp(p) <= 0:
        raise LaserSheetError("every point comes from one carriage position: scan across the target "
                              "(several positions)")
    keep = np.ones(len(X), bool)
    robust = np.ones(len(X))
    # with uncertainties: more rounds, as the Huber weights settle more slowly than a plain trim
    for _ in range(rounds + 1 if sigma is None else 3 * rounds + 1):
        weights = None if sigma is None else (robust / sigma ** 2)[keep]
        n, c0, k, values = _solve(X[keep], p[keep], weights)
        residual = X @ n - (c0 + k * p)
        z = residual if sigma is None else residual / sigma  # in each point's own sigmas
        scale = 1.4826 * np.median(np.abs(z[keep] - np.median(z[keep])))
        new_keep = np.abs(z) <= max(trim_sigmas * scale, 1e-9)
        if sigma is not None:
            new_robust = np.minimum(1.0, HUBER_K * max(scale, 1e-12) / np.maximum(np.abs(z), 1e-30))
            settled = np.allclose(new_robust, robust, rtol=1e-3, atol=1e-4)
            robust = new_robust
            if np.array_equal(new_keep, keep) and settled:
                break
        elif np.array_equal(new_keep, keep):
            break
        keep = new_keep
        if keep.sum() < 50:
            raise LaserSheetError("too few points agree on one sheet: are the scans of one rig and flat targets?")
    if values[1] < MIN_CONDITION * max(values[0], 1e-30):
        raise LaserSheetError(
            "the points do not determine the sheet: they lie (nearly) on one plane besides the sheet, as the "
            "scans of a single flat target do. Scan the board at two or more distances or tilts")
    rms = float(np.sqrt(np.mean((X[keep] @ n - (c0 + k * p[keep])) ** 2)))
    return LaserSheet(normal=(float(n[0]), float(n[1]), float(n[2])), c0_m=c0, m_per_step=k,
                      residual_mm=rms * 1000.0, points=int(keep.sum()), rejected=int((~keep).sum()),
                      positions=(int(p.min()), int(p.max())))


def write_laser_yaml(sheet: LaserSheet, path: str | Path) -> Path:
    """``laser.yaml`` beside left/right/stereo.yaml (same folder, readable by every user: 0644)."""
    path = Path(path)
    data = {"model": "translating_plane", "frame_id": "lsu_left_optical",
            "normal": [round(v, 9) for v in sheet.normal], "c0_m": round(sheet.c0_m, 9),
            "m_per_step": round(sheet.m_per_step, 12), "residual_mm": round(sheet.residual_mm, 4),
            "points": sheet.points, "rejected": sheet.rejected, "positions": list(sheet.positions),
            "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")}
    text = ("# Laser light sheet: n . X = c0_m + m_per_step * position_steps (left optical frame, metres).\n"
            + yaml.safe_dump(data, sort_keys=False))
    path.write_text(text)
    path.chmod(0o644)
    return path


def read_laser_yaml(path: str | Path) -> LaserSheet:
    """The sheet written by `write_laser_yaml`; LaserSheetError naming the file when it is not one."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
        normal = tuple(float(v) for v in data["normal"])
        if len(normal) != 3 or abs(np.linalg.norm(normal) - 1.0) > 1e-6:
            raise ValueError("normal must be a unit vector of 3 numbers")
        return LaserSheet(normal=normal, c0_m=float(data["c0_m"]), m_per_step=float(data["m_per_step"]),
                          residual_mm=float(data.get("residual_mm", float("nan"))), points=int(data.get("points", 0)),
                          rejected=int(data.get("rejected", 0)),
                          positions=tuple(int(v) for v in data.get("positions", (0, 0))))  # type: ignore[arg-type]
    except FileNotFoundError:
        raise LaserSheetError(f"{path}: no laser sheet calibration here (make one with `lsu calibrate --laser`)") \
            from None
    except (yaml.YAMLError, KeyError, TypeError, ValueError) as exc:
        raise LaserSheetError(f"{path}: not a laser sheet calibration ({exc})") from None

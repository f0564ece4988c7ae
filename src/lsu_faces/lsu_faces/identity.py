"""Identity from a morphable-model fit: the face's shape explained as identity + expression, identity compared.

Blanz & Vetter (2003, "Face recognition based on fitting a 3D morphable model", IEEE PAMI 25(9)) separate
who a person is from how the face is held by fitting a morphable model and comparing only the identity
coefficients. Here the model is the ICT Face Model (USC ICT-FaceKit, MIT; see config/heads/CREDITS.md):
100 identity modes (principal components of light-stage scans of real people, weights ~N(0, 1)) and 57
expression blendshapes (weights 0..1).

The fit works on the signature's depth map (`lsu_faces.signature`, face frame: origin at the nose tip,
x right, y down, z out of the face), so it needs no point cloud and no correspondence search:

- the basis (`config/heads/ict_face_basis.npz`, made by `build_basis` from the model) holds the mean face's
  depth map and, per mode, how the depth map changes per unit weight (a central difference of two ray-cast
  depth maps, each in its own nose-tip frame, so a mode that moves the nose tip is measured from the tip);
- a probe's map is explained by ``mean + identity @ B_id + expression @ B_ex + small rigid motion`` in a
  regularised least-squares sense (the weights' priors: identity ~N(0, 1), expression ~N(0, 0.5^2), the
  map's noise from the scan's measured noise plus the model's own error), with the cells whose residual is
  largest left out and the fit repeated (hair, a collar, flying pixels, a hand: what no mode explains);
- cells the sensor did not see simply do not count: the prior fills what the data leave open.

The identity weights (`IDENTITY_MODES` of them, the modes with most variance) are the signature for 1:N: two
people differ by about sqrt(2 x IDENTITY_MODES) in this space, two captures of one person by what noise,
occlusion and expression leave undetermined. Mapped through the rigid face's basis (`identity_vector`)
the Euclidean distance between two vectors is the RMS shape difference [m] of the two fitted identities
over the nose, eyes and forehead: what faiss's L2 index ranks and what the open-set model calibrates.

Hand-written because no library fits a morphable model to a depth map: the solve itself is numpy's.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lsu_common.arrays import AnyArray

from .signature import Signature

__all__ = ["FaceBasis", "IdentityFit", "load_basis", "fit_identity", "identity_vector", "build_basis",
           "basis_path", "IDENTITY_MODES", "BasisError"]

IDENTITY_MODES = 60          # identity modes fitted and compared (the rest carry < 1 % of the shape variance)
FIT_RADIUS_M = 0.065         # cells within this of the nose tip take part in the fit
MODEL_ERROR_M = 0.0008       # what the linearised model cannot explain on a clean scan (adds to the scan's noise)
EXPRESSION_SIGMA = 0.5       # prior of the expression weights
TRIM = 0.15                  # fraction of the worst-explained cells left out in the second and third solve
BASIS_FILE = "ict_face_basis.npz"
ALIGN_ROUNDS = 2             # rigid re-alignments of the map onto the fitted face (see fit_signature)


class BasisError(RuntimeError):
    """The model basis is missing or does not fit the signature's grid."""


@dataclass
class FaceBasis:
    """The linearised model on a signature grid: mean map and per-mode derivative maps (NaN-free)."""

    grid: int
    extent_m: float
    mean: AnyArray            # (g, g) mean face height, NaN where the model has no surface
    identity: AnyArray        # (K, g, g) height change per unit identity weight
    expression: AnyArray      # (E, g, g) height change per unit expression weight
    expression_names: list[str]
    rigid_weight: AnyArray    # (g, g) weight of a cell in identity_vector (rigid face: nose, eyes, forehead)
    _projection: AnyArray | None = None

    @property
    def projection(self) -> AnyArray:
        """(K, K) map of identity weights to a vector whose L2 norm is the RMS height over the rigid face."""
        if self._projection is None:
            w = self.rigid_weight.ravel()
            B = self.identity.reshape(len(self.identity), -1)[:, w > 0] * np.sqrt(w[w > 0])
            # B^T B = V S^2 V^T: x -> S V^T x keeps ||B^T x|| / sqrt(sum w)
            _, s, vt = np.linalg.svd(B.T, full_matrices=False)
            self._projection = (s[:, None] * vt) / np.sqrt(w.sum())
        return self._projection


@dataclass
class IdentityFit:
    """What a fit found: identity and expression weights, the rigid correction and how well it explains the map."""

    identity: AnyArray          # (K,) identity weights
    expression: AnyArray        # (E,) expression weights
    rigid: AnyArray             # (6,) small rotation (rad) and translation (m) the map was off by
    residual_m: float           # RMS of the kept cells' residuals
    cells: int                  # cells that took part


def basis_path() -> Path:
    """``config/heads`` of this workspace, where the basis ships (as the simulator's head assets)."""
    from lsu_config import config_dir

    return config_dir() / "heads" / BASIS_FILE


_BASIS: dict[str, FaceBasis] = {}


def load_basis(path: str | Path | None = None) -> FaceBasis:
    """The basis file (read once per process: constant data)."""
    path = Path(path) if path is not None else basis_path()
    key = str(path)
    if key not in _BASIS:
        if not path.is_file():
            raise BasisError(f"{path} is missing; it ships with the repository (config/heads), or rebuild it with "
                             f"'python -m lsu_faces.identity build-basis ICT_MODEL_DIR {path.parent}'")
        with np.load(path, allow_pickle=False) as z:
            _BASIS[key] = FaceBasis(int(z["grid"]), float(z["extent_m"]), z["mean"].astype(np.float64),
                                    z["identity"].astype(np.float64), z["expression"].astype(np.float64),
                                    [str(n) for n in z["expression_names"]], z["rigid_weight"].astype(np.float64))
    return _BASIS[key]


def _slopes(h: AnyArray, cell: float) -> tuple[AnyArray, AnyArray]:
    hy, hx = np.gradient(np.where(np.isfinite(h), h, 0.0), cell)
    return hx, hy


def fit_identity(data: AnyArray, extent_m: float, noise_m: float = float("nan"),
                 basis: FaceBasis | None = None) -> IdentityFit:
    """Fit the model to a signature's depth map ``data`` (g x g, NaN = not seen) of half width ``extent_m``."""
    b = basis or load_basis()
    g = data.shape[0]
    if data.shape != (b.grid, b.grid) or abs(extent_m - b.extent_m) > 1e-9:
        raise BasisError(f"the model basis is for a {b.grid} x {b.grid} grid of +-{b.extent_m * 1000:.0f} mm, the "
                         f"signature is {data.shape[0]} x {data.shape[1]} of +-{extent_m * 1000:.0f} mm")
    cell = 2 * extent_m / g
    centres = (np.arange(g) + 0.5) * cell - extent_m
    x, y = np.meshgrid(centres, centres)
    use = np.isfinite(data) & np.isfinite(b.mean) & (np.hypot(x, y) <= FIT_RADIUS_M)
    if use.sum() < 50:
        raise BasisError(f"only {int(use.sum())} cells of the face were seen; a fit needs at least 50")
    h0 = np.where(np.isfinite(b.mean), b.mean, 0.0)
    hx, hy = _slopes(b.mean, cell)
    # small rigid motion (rotation w, translation t) of the surface point (x, y, h): height change
    # dz - hx dx - hy dy with d = w x p + t
    px, py, pz = x[use], y[use], h0[use]
    sx, sy = hx[use], hy[use]
    rigid = np.stack([py + sy * pz,            # wx: d = (0, -pz, py)
                      -px - sx * pz,           # wy: d = (pz, 0, -px)
                      sx * py - sy * px,       # wz: d = (-py, px, 0)
                      -sx, -sy, np.ones_like(px)], axis=1)
    K, E = len(b.identity), len(b.expression)
    A = np.concatenate([b.identity[:, use].T, b.expression[:, use].T, rigid], axis=1)
    r = data[use] - h0[use]
    noise = float(noise_m) if np.isfinite(noise_m) else 0.0
    var = noise ** 2 + MODEL_ERROR_M ** 2
    prior = np.concatenate([np.ones(K), np.full(E, 1.0 / EXPRESSION_SIGMA ** 2),
                            np.full(3, 1.0 / 0.1 ** 2), np.full(3, 1.0 / 0.005 ** 2)])
    keep = np.ones(len(r), bool)
    theta = np.zeros(A.shape[1])
    for it in range(3):
        Ak, rk = A[keep], r[keep]
        theta = np.linalg.solve(Ak.T @ Ak / var + np.diag(prior), Ak.T @ rk / var)
        res = r - A @ theta
        if it < 2:
            keep = np.abs(res) <= np.quantile(np.abs(res), 1.0 - TRIM)
    res = r - A @ theta
    return IdentityFit(theta[:K], theta[K:K + E], theta[K + E:], float(np.sqrt(np.mean(res[keep] ** 2))),
                       int(keep.sum()))


def model_map(fit: IdentityFit, basis: FaceBasis | None = None) -> AnyArray:
    """The depth map the fitted identity and expression give (without the rigid correction)."""
    b = basis or load_basis()
    return b.mean + np.tensordot(fit.identity, b.identity, 1) + np.tensordot(fit.expression, b.expression, 1)


def fit_signature(sig: Signature, basis: FaceBasis | None = None, rounds: int = ALIGN_ROUNDS) -> IdentityFit:
    """`fit_identity` of a depth-map signature, alternating with a rigid re-alignment of its cells.

    The face frame of a noisy scan can be a few millimetres and degrees off the model's nose-tip frame;
    the fit's linearised rigid terms absorb only small motions, so the map's cells are moved onto the
    fitted face (`lsu_faces.signature.align_to_depthmap`), binned again and fitted again.
    """
    from .register import apply
    from .signature import _depth_map, _grid_points, _region_weights, align_to_depthmap

    b = basis or load_basis()
    fit = fit_identity(sig.data, sig.params.extent_m, sig.noise_m, b)
    pts, _ = _grid_points(sig)
    cell = 2 * sig.params.extent_m / sig.params.grid
    for _ in range(rounds):
        ref = Signature(sig.method, model_map(fit, b), sig.params)
        T = align_to_depthmap(pts, ref, _region_weights(pts), (4 * cell, 1.5 * cell), iterations=5, trim=0.2)
        data = _depth_map(apply(T, pts), sig.params)
        fit = fit_identity(data, sig.params.extent_m, sig.noise_m, b)
    return fit


def identity_vector(fit: IdentityFit, basis: FaceBasis | None = None) -> AnyArray:
    """float32 vector whose Euclidean distance to another is the RMS height difference [m] of the two fitted
    identities over the rigid face (see the module doc)."""
    b = basis or load_basis()
    return (b.projection @ fit.identity).astype(np.float32)


# ------------------------------------------------------------------ building the basis from the model
def _depth_map_of(verts: AnyArray, triangles: AnyArray, tip: AnyArray, eyes, grid: int,  # noqa: ANN001
                  extent_m: float) -> AnyArray:
    """Depth map (face frame heights) of a surface in the person frame, one ray through each cell centre."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(verts.astype(np.float32)), o3d.core.Tensor(triangles.astype(np.uint32)))
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(eyes))
    cell = 2 * extent_m / grid
    c = (np.arange(grid) + 0.5) * cell - extent_m
    x, y = np.meshgrid(c, c)
    origins = np.stack([x.ravel() + tip[0], y.ravel() + tip[1], np.full(x.size, tip[2] - 0.2)], axis=1)
    rays = np.concatenate([origins, np.tile([0.0, 0.0, 1.0], (len(origins), 1))], axis=1).astype(np.float32)
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
    t[~np.isfinite(t)] = np.nan
    # person frame z points away from the camera; the face frame's height points out of the face
    return (-(origins[:, 2] + t - tip[2])).reshape(grid, grid)


def build_basis(ict_dir: str | Path, out_dir: str | Path, grid: int = 56, extent_m: float = 0.07) -> Path:
    """Write ``out_dir/ict_face_basis.npz`` from the ICT model in ``ict_dir`` (see the module doc)."""
    from lsu_sim.ict import _NOSE, eyeballs, load_ict

    from .template import REGIONS, region_of

    model = load_ict(ict_dir)
    lm = model.landmarks

    def depth(offset: AnyArray) -> AnyArray:
        verts = model.neutral + offset.reshape(-1, 3)
        marks = verts[lm]
        tip = marks[_NOSE]
        eyes = {"eye_r": marks[36:42].mean(axis=0), "eye_l": marks[42:48].mean(axis=0)}
        return _depth_map_of(verts, model.triangles, tip, eyeballs(eyes), grid, extent_m)

    zero = np.zeros(model.neutral.size)
    mean = depth(zero)
    ident = []
    for k in range(IDENTITY_MODES):
        d = model.identity[k].astype(np.float64)
        ident.append((depth(d) - depth(-d)) / 2.0)
    expr = []
    for k in range(len(model.expression)):
        d = model.expression[k].astype(np.float64)
        expr.append((depth(0.5 * d) - mean) / 0.5)
    ident_a, expr_a = np.array(ident), np.array(expr)
    # a cell where some mode jumps (a ray passing a silhouette, an eyelid over the ball) is no smooth
    # function of the weights: left out of the fit (the mean is NaN there)
    jumps = np.any(~np.isfinite(ident_a) | (np.abs(ident_a) > 0.015), axis=0) | \
        np.any(~np.isfinite(expr_a) | (np.abs(expr_a) > 0.04), axis=0)
    mean[jumps] = np.nan
    ident_a = np.where(np.isfinite(ident_a), ident_a, 0.0)
    expr_a = np.where(np.isfinite(expr_a), expr_a, 0.0)
    cell = 2 * extent_m / grid
    c = (np.arange(grid) + 0.5) * cell - extent_m
    x, y = np.meshgrid(c, c)
    reg = region_of(np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)).reshape(grid, grid)
    rigid = np.isin(reg, [REGIONS.index(r) for r in ("nose", "eyes", "forehead")])
    rigid_weight = (rigid & np.isfinite(mean) & (np.hypot(x, y) <= FIT_RADIUS_M)).astype(np.float32)
    out = Path(out_dir) / BASIS_FILE
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out, grid=np.array(grid), extent_m=np.array(extent_m), mean=mean.astype(np.float32),
                        identity=ident_a.astype(np.float16), expression=expr_a.astype(np.float16),
                        expression_names=np.array(model.expression_names), rigid_weight=rigid_weight)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m lsu_faces.identity",
                                     description="build the ICT model basis of the identity fit")
    sub = parser.add_subparsers(dest="cmd", required=True)
    b = sub.add_parser("build-basis", help="write ict_face_basis.npz from the ICT model folder")
    b.add_argument("ict_dir")
    b.add_argument("out_dir")
    args = parser.parse_args(argv)
    print(build_basis(args.ict_dir, args.out_dir))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

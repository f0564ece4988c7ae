"""Smoothing: Taubin keeps the volume, the thesis' Laplacian shrinks it; both remove noise."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from lsu_faces.smoothing import (
    SmoothingError,
    SmoothParams,
    enclosed_volume,
    laplacian_smooth,
    shrinkage,
    taubin_smooth,
)

RADIUS = 0.05


@pytest.fixture(scope="module")
def noisy_sphere():
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=RADIUS, resolution=60)
    v = np.asarray(mesh.vertices)
    t = np.asarray(mesh.triangles).astype(np.int64)
    rng = np.random.default_rng(7)
    noisy = v + (v / np.linalg.norm(v, axis=1, keepdims=True)) * rng.normal(0, 2e-4, (len(v), 1))
    return noisy, t


def test_closed_volume_matches_the_analytic_sphere(noisy_sphere):
    v, t = noisy_sphere
    assert enclosed_volume(v, t) == pytest.approx(4 / 3 * np.pi * RADIUS ** 3, rel=0.01)


def test_taubin_keeps_volume_where_laplacian_shrinks(noisy_sphere):
    v, t = noisy_sphere
    lap = shrinkage(v, laplacian_smooth(v, t, 0.1, 30), t)["volume_change_pct"]
    tau = shrinkage(v, taubin_smooth(v, t, 0.5, -0.53, 30), t)["volume_change_pct"]
    assert abs(tau) < 1.0
    assert lap < -1.0


def test_smoothing_removes_noise(noisy_sphere):
    v, t = noisy_sphere
    err0 = np.std(np.linalg.norm(v, axis=1) - RADIUS)
    for out in (laplacian_smooth(v, t), taubin_smooth(v, t)):
        r = np.linalg.norm(out, axis=1)
        assert np.std(r - r.mean()) < 0.5 * err0


def test_bad_parameters_are_named():
    with pytest.raises(SmoothingError, match="taubin_mu"):
        SmoothParams(taubin_lambda=0.5, taubin_mu=-0.4)
    with pytest.raises(SmoothingError, match="method"):
        SmoothParams(method="gauss")
